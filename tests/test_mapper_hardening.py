"""Hostile input and concurrent use of MinMaxMapper: clear errors, nothing changed, no leaks."""

from __future__ import annotations

import gc
import json
import os
import stat
import threading
import zipfile

import numpy as np
import pytest
from conftest import pose, rot_y, rot_z
from test_mapper import GRID, SPEC, T_A, T_B

import gpumap
from gpumap.backends import available_backends
from gpumap.core.params import MapperParams

RNG = np.random.default_rng(5)


def _pings(n):
    return [((RNG.random(SPEC.image_shape) ** 5).astype(np.float32),
             pose(rot_z(RNG.uniform(-0.3, 0.3)) @ rot_y(RNG.uniform(-0.2, 0.2)), RNG.uniform(-0.1, 0.1, 3)))
            for _ in range(n)]


def test_two_threads_give_the_map_of_one(backend):
    pings = _pings(16)
    one = gpumap.MinMaxMapper(SPEC, GRID, backend=backend)
    for img, T in pings:
        one.integrate(img, T)
    two = gpumap.MinMaxMapper(SPEC, GRID, backend=backend)

    def work(part):
        for img, T in part:
            two.integrate(img, T)

    threads = [threading.Thread(target=work, args=(pings[i::2],)) for i in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    np.testing.assert_array_equal(two.raw_values(), one.raw_values())
    assert two.n_integrated == 16


def test_masked_and_complex_input_is_refused():
    m = gpumap.MinMaxMapper(SPEC, GRID, backend="numpy")
    img = np.ma.masked_array(np.zeros(SPEC.image_shape, np.float32), mask=False)
    img.data[0, 0] = 5.0
    img.mask[0, 0] = True
    with pytest.raises(TypeError, match="masked"):
        m.integrate(img, T_A)
    with pytest.raises(TypeError, match="dtype"):
        m.integrate(np.zeros(SPEC.image_shape, np.complex64), T_A)
    with pytest.raises(TypeError, match="complex"):
        m.integrate(np.zeros(SPEC.image_shape, np.float32), T_A.astype(np.complex128))
    with pytest.raises(TypeError, match="masked"):
        m.integrate(np.zeros(SPEC.image_shape, np.float32), np.ma.masked_array(T_A))
    assert m.n_integrated == 0 and np.all(np.isinf(m.raw_values()))


def _saved(tmp_path, rule="visible"):
    m = gpumap.MinMaxMapper(SPEC, GRID, "numpy", MapperParams(rule=rule))
    for img, T in _pings(2):
        m.integrate(img, T)
    return m.save(tmp_path / f"{rule}.npz")


def _rewrite(src, dst, change):
    """Copy the map file ``src`` to ``dst`` with ``change(name, array or meta dict)`` applied."""
    with np.load(src) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(str(arrays.pop("meta")))
    for k in list(arrays):
        arrays[k] = change(k, arrays[k])
    meta = change("meta", meta)
    np.savez_compressed(dst, **arrays, meta=np.array(json.dumps(meta)))
    return dst


@pytest.mark.parametrize(
    "change, msg",
    [
        (lambda k, a: np.where(np.isinf(a), a, 5.0).astype(a.dtype) if k == "values" else a, r"\[0, 1\]"),
        (lambda k, a: np.full_like(a, np.nan) if k == "values" else a, r"\[0, 1\]"),
        (lambda k, a: np.full_like(a, -np.inf) if k == "min_all" else a, r"\[0, 1\]"),
        (lambda k, a: {**a, "n_integrated": -3} if k == "meta" else a, "n_integrated"),
        (lambda k, a: {**a, "n_integrated": "12"} if k == "meta" else a, "n_integrated"),
        (lambda k, a: {**a, "rule": "magic"} if k == "meta" else a, "rule"),
        (lambda k, a: {**a, "grid": {"min_corner_m": [0, 0]}} if k == "meta" else a, "grid spec"),
        (lambda k, a: {**a, "carve_views": 0} if k == "meta" else a, "carve_views"),
        (lambda k, a: a[:-1] if k == "bright" else a, "bright"),
        (lambda k, a: a.astype(np.float64) if k == "count" else a, "count"),
        (lambda k, a: np.where(np.isfinite(a), 0, a).astype(a.dtype) if k == "values" else a,
         "follow from its state"),
    ],
)
def test_load_refuses_values_a_map_cannot_hold(tmp_path, change, msg):
    src = _saved(tmp_path)
    bad = _rewrite(src, tmp_path / "bad.npz", change)
    with pytest.raises(ValueError, match=msg):
        gpumap.MinMaxMapper.load(bad, backend="numpy")


def test_load_refuses_a_small_file_that_declares_a_huge_grid_before_allocating(tmp_path):
    """A 6 GB grid declared by a file of a few KB: refused from the headers, fast."""
    import time

    src = _saved(tmp_path, "plain")
    big = gpumap.GridSpec((0, 0, 0), (12, 10, 10), 0.01)  # 1.2e9 voxels, 4.8 GB of float32
    dst = tmp_path / "bomb.npz"
    with zipfile.ZipFile(src) as zi, zipfile.ZipFile(dst, "w", zipfile.ZIP_DEFLATED) as zo:
        meta = json.loads(str(np.lib.format.read_array(zi.open("meta.npy"))))
        meta["grid"] = big.to_dict()
        with zo.open("meta.npy", "w") as f:
            np.lib.format.write_array(f, np.array(json.dumps(meta)))
        # a values header that declares the whole grid, and a few bytes of data
        with zo.open("values.npy", "w", force_zip64=True) as f:
            np.lib.format.write_array_header_1_0(
                f, {"descr": "<f4", "fortran_order": False, "shape": big.shape})
            f.write(b"\0" * 64)
    t0 = time.perf_counter()
    with pytest.raises(ValueError, match="declared|inflate"):
        gpumap.MinMaxMapper.load(dst, backend="numpy")
    assert time.perf_counter() - t0 < 1.0


def test_plain_and_visible_maps_round_trip(tmp_path):
    for rule in ("plain", "visible"):
        p = _saved(tmp_path, rule)
        m = gpumap.MinMaxMapper.load(p, backend="numpy")
        assert m.rule == rule and m.n_integrated == 2


def test_opencl_mappers_do_not_leak():
    if "opencl-cpu" not in available_backends():
        pytest.skip("no OpenCL CPU device here")
    spec = gpumap.SonarSpec.uniform(n_beams=64, n_bins=50)
    grid = gpumap.GridSpec((-1, -1, -0.5), (1, 1, 0.5), 0.1)
    img = np.zeros(spec.image_shape, np.float32)

    def rss_mb():
        with open("/proc/self/status") as f:
            return next(int(x.split()[1]) for x in f if x.startswith("VmRSS")) / 1024

    def churn(n):
        for _ in range(n):
            m = gpumap.MinMaxMapper(spec, grid, backend="opencl-cpu")
            m.integrate(img, T_B)
            m.synchronize()
            del m
        gc.collect()

    churn(5)
    before = rss_mb()
    churn(150)
    assert rss_mb() - before < 40


# ----------------------------------------------------------------------------- property-based
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402
from hypothesis.extra import numpy as hnp  # noqa: E402

_FUZZ_IMAGE = (np.random.default_rng(8).random(SPEC.image_shape) ** 5).astype(np.float32)
_FUZZ_MAPPER = gpumap.MinMaxMapper(SPEC, GRID, backend="numpy")
_FUZZ_MAPPER.integrate(_FUZZ_IMAGE, T_A)
_FUZZ_BEFORE = _FUZZ_MAPPER.evidence()

_images = st.one_of(
    hnp.arrays(st.sampled_from([np.float32, np.float64, np.uint8, np.int16, np.complex64, np.bool_]),
               st.sampled_from([SPEC.image_shape, SPEC.image_shape[::-1], (SPEC.n_bins,), (0, 0)]),
               elements=None),
    hnp.arrays(np.float32, SPEC.image_shape,
               elements=st.one_of(st.floats(-2, 2, width=32), st.sampled_from([np.nan, np.inf, -np.inf]))),
)
_poses = st.one_of(
    hnp.arrays(np.float64, st.sampled_from([(4, 4), (3, 4), (4,)]),
               elements=st.one_of(st.floats(-10, 10), st.sampled_from([np.nan, np.inf]))),
    st.just(T_B),
)


@settings(max_examples=150, deadline=None, derandomize=True, suppress_health_check=list(HealthCheck))
@given(image=_images, T=_poses)
def test_integrate_either_maps_or_refuses_and_changes_nothing(image, T):
    """Random images (any dtype, shape, NaN, out of range) and poses: a valid ping maps, anything
    else raises ValueError/TypeError with the map byte-identical."""
    m = _FUZZ_MAPPER
    before_n = m.n_integrated
    try:
        m.integrate(image, T)
    except (ValueError, TypeError):
        after = m.evidence()
        for k in after:
            np.testing.assert_array_equal(after[k], _FUZZ_BEFORE[k])
        assert m.n_integrated == before_n
    else:  # it took the ping: undo, so every example starts from the same map
        v = m.raw_values()
        assert np.all(np.isinf(v) | ((v >= 0) & (v <= 1)))
        m.reset()
        m.integrate(_FUZZ_IMAGE, T_A)


def test_saved_map_gets_normal_file_permissions(tmp_path):
    """A new map file gets 0o666 less the umask (as open() would), not mkstemp's 0o600;
    an existing file keeps its permissions when it is replaced."""
    old = os.umask(0o022)
    try:
        m = gpumap.MinMaxMapper(SPEC, GRID, backend="numpy")
        p = m.save(tmp_path / "m.npz")
        assert stat.S_IMODE(p.stat().st_mode) == 0o644
        p.chmod(0o640)
        m.save(p)
        assert stat.S_IMODE(p.stat().st_mode) == 0o640
    finally:
        os.umask(old)


def test_load_errors_are_gpumap_format_errors(tmp_path):
    """A damaged map file ends in gpumap's reader error family (FormatError, a ValueError)."""
    from gpumap.errors import FormatError

    p = gpumap.MinMaxMapper(SPEC, GRID, backend="numpy").save(tmp_path / "m.npz")
    with zipfile.ZipFile(p) as z:
        members = {n: z.read(n) for n in z.namelist()}
    import io

    meta = json.loads(str(np.load(io.BytesIO(members["meta.npy"]))))
    meta["format"] = "not-gpumap"
    buf = io.BytesIO()
    np.save(buf, np.array(json.dumps(meta)))
    members["meta.npy"] = buf.getvalue()
    bad = tmp_path / "bad.npz"
    with zipfile.ZipFile(bad, "w") as z:
        for n, data in members.items():
            z.writestr(n, data)
    with pytest.raises(FormatError, match="Expected format"):
        gpumap.MinMaxMapper.load(bad)
    (tmp_path / "junk.npz").write_bytes(b"PK\x03\x04" + b"\0" * 40)
    with pytest.raises(FormatError, match="cannot be read"):
        gpumap.MinMaxMapper.load(tmp_path / "junk.npz")


def test_auto_says_which_backend_it_picked_and_a_named_one_stays_quiet(caplog, monkeypatch):
    import logging

    import gpumap.core.mapper

    monkeypatch.setattr(gpumap.core.mapper, "_ANNOUNCED", set())  # it says so once a process

    spec = gpumap.SonarSpec.uniform(n_beams=4, n_bins=4)
    grid = gpumap.GridSpec((0, 0, 0), (1, 1, 1), 0.5)
    with caplog.at_level(logging.INFO, logger="gpumap"):
        m = gpumap.MinMaxMapper(spec, grid, backend="auto")
    assert f"backend {m.backend} on" in caplog.text
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="gpumap"):
        gpumap.MinMaxMapper(spec, grid, backend="numpy")
    assert "backend numpy" not in caplog.text
