"""CI must not pass by skipping: every CPU backend it is meant to test is present and works.

On a machine without, say, PoCL, every ``opencl-cpu`` test skips and the run stays green. When
``CI`` is set (``.ci/run`` sets it) these tests require numpy, warp-cpu and opencl-cpu
(``GPUMAP_REQUIRE_BACKENDS=a,b`` names others; empty outside CI, where nothing is required).
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import _AVAILABLE, REQUIRED_BACKENDS

import gpumap
from gpumap.backends import BACKENDS


def test_required_backends_are_named_correctly():
    unknown = set(REQUIRED_BACKENDS) - set(BACKENDS)
    assert not unknown, f"GPUMAP_REQUIRE_BACKENDS names unknown backends {sorted(unknown)}"


@pytest.mark.parametrize("name", REQUIRED_BACKENDS or [pytest.param(None, marks=pytest.mark.skip(
    reason="no backend required here (set CI or GPUMAP_REQUIRE_BACKENDS)"))])
def test_required_backend_is_present_and_maps(name):
    assert name in _AVAILABLE, (
        f"backend {name} is required here but unavailable (this machine has {', '.join(_AVAILABLE)}): "
        "its tests would all skip"
    )
    # present is not enough: it must build its kernels and map a ping as the reference does
    spec = gpumap.SonarSpec.uniform(hfov_deg=60, vfov_deg=12, n_beams=16, n_bins=20, range_min_m=0.1,
                                    range_max_m=1.0)
    grid = gpumap.GridSpec((0.0, -0.5, -0.2), (1.0, 0.5, 0.2), 0.1)
    img = np.random.default_rng(0).random(spec.image_shape).astype(np.float32)
    got = gpumap.MinMaxMapper(spec, grid, backend=name)
    ref = gpumap.MinMaxMapper(spec, grid, backend="numpy")
    for m in (got, ref):
        m.integrate(img, np.eye(4))
    assert got.backend == name
    assert np.isfinite(ref.raw_values()).sum() > 10
    np.testing.assert_array_equal(got.raw_values(), ref.raw_values())


def test_opencl_takes_the_first_device_that_builds(monkeypatch):
    """Two platforms for one CPU, the first unable to compile (bundled PoCL on a processor its LLVM
    does not know): the backend must skip it, and fail with every reason when none builds."""
    from gpumap.backends import opencl_backend as backends  # where the device search looks them up
    from gpumap.errors import BackendUnavailableError

    broken, good = object(), object()
    monkeypatch.setattr(backends, "opencl_devices", lambda kind: [broken, good])

    def fake_context(d):
        if d is broken:
            raise BackendUnavailableError("OpenCL cannot build gpumap's kernels for broken")
        return ("ctx", "prg")

    monkeypatch.setattr(backends, "_opencl_context", fake_context)
    assert backends.usable_opencl_device("cpu") is good
    cl = backends._opencl()

    class _Dev:
        name = "no-context "

    def no_context(d):
        if isinstance(d, _Dev):
            raise cl.Error("clCreateContext failed: DEVICE_NOT_AVAILABLE")
        return fake_context(d)

    monkeypatch.setattr(backends, "_opencl_context", no_context)
    monkeypatch.setattr(backends, "opencl_devices", lambda kind: [_Dev(), good])
    assert backends.usable_opencl_device("cpu") is good
    monkeypatch.setattr(backends, "opencl_devices", lambda kind: [_Dev()])
    with pytest.raises(BackendUnavailableError, match="cannot open no-context: clCreateContext"):
        backends.usable_opencl_device("cpu")
    monkeypatch.setattr(backends, "opencl_devices", lambda kind: [broken, broken])
    with pytest.raises(BackendUnavailableError, match="broken; OpenCL cannot build"):
        backends.usable_opencl_device("cpu")
    monkeypatch.setattr(backends, "opencl_devices", lambda kind: [])
    with pytest.raises(BackendUnavailableError, match="finds none"):
        backends.usable_opencl_device("cpu")
