"""The confidence layer's pass on the device (issue 37; gpumap.layers.confidence_device,
kernels/confidence.*):
every backend's layer (``confirmed``, ``arcs``) and map equal the NumPy reference's
(gpumap.layers.confidence.confirm_ping, which the ``numpy`` backend runs) bit for bit, on random map states of
every rule and random pings, and on the real tank; the layer's host and device copies stay one."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import needs_data
from maps import make_mapper

import gpumap
from gpumap.core.params import MapperParams
from gpumap.layers.confidence import with_confidence
from gpumap.reference import pack_counts

SPEC = gpumap.SonarSpec.uniform(hfov_deg=70, vfov_deg=20, n_beams=48, n_bins=90, range_min_m=0.1,
                                range_max_m=1.2)
GRID = gpumap.GridSpec((-0.6, -0.6, -0.4), (0.6, 0.6, 0.4), 0.04)
OPTIONS = {"carve_views": 3, "bright_share": 0.35, "share_z": 1.2}


def _pose(rng: np.random.Generator) -> np.ndarray:
    """A sonar inside the grid, its boresight anywhere (a random rotation), so the box, the column
    walk and the rivals' region meet the grid's edges at every angle."""
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    T = np.eye(4)
    T[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                 [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                 [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]]
    T[:3, 3] = rng.uniform(-0.4, 0.4, 3)
    return T


def _image(rng: np.random.Generator) -> np.ndarray:
    """Speckle: a share of lit cells (some rows dense, most sparse) over a dark floor."""
    img = rng.uniform(0.0, 0.09, SPEC.image_shape).astype(np.float32)
    share = rng.choice([0.002, 0.02, 0.3], size=(SPEC.n_bins, 1))
    lit = rng.random(SPEC.image_shape) < share
    img[lit] = rng.uniform(0.1, 1.0, int(lit.sum())).astype(np.float32)
    return img


def _random_state(m: gpumap.MinMaxMapper, rng: np.random.Generator) -> None:
    """A hand-made map state: unknown, free, occupied voxels, and for the rules with evidence small
    view counts (bright shares near the evidence rule's bound) and their bright minima."""
    shape = GRID.shape
    grid = rng.choice(np.float32([np.inf, 0.02, 0.05, 0.1, 0.3, 0.8]), size=shape)
    st = m.storage
    arrays = [st.to_pool_order(grid.astype(np.float32), np.inf).ravel(), None, None]
    if m.rule != "plain":
        hits = rng.integers(0, 5, shape)
        dark = rng.integers(0, 9, shape)
        bright = np.where(hits > 0, rng.uniform(0.1, 1.0, shape), np.inf).astype(np.float32)
        arrays[1] = st.to_pool_order(bright, np.inf).ravel()
        arrays[2] = st.to_pool_order(pack_counts(dark, hits), 0).ravel()
    st.backend.write(*arrays)
    st.empty = False


def _layer(m: gpumap.MinMaxMapper) -> tuple[np.ndarray, np.ndarray]:
    return m.layer("confidence").confirmed.copy(), m.layer("confidence").arcs.copy()


@pytest.mark.parametrize("rule", ["evidence", "visible", "plain"])
def test_the_device_pass_equals_the_reference_on_random_states_and_pings(other_backend, rule, monkeypatch):
    if rule == "evidence":  # warp-cpu: the pass in two parts on two threads too
        monkeypatch.setattr("gpumap.layers.confidence_device.CPU_SPLIT", True)
    rng = np.random.default_rng({"evidence": 1, "visible": 2, "plain": 3}[rule])
    ref, dev = (make_mapper(SPEC, GRID, backend=b, rule=rule, confidence=True, **OPTIONS)
                for b in ("numpy", other_backend))
    seed = int(rng.integers(1 << 30))
    _random_state(ref, np.random.default_rng(seed))
    _random_state(dev, np.random.default_rng(seed))
    pings = [(_image(rng), _pose(rng)) for _ in range(8)]
    for k, (img, T) in enumerate(pings):
        # every other ping with a pose covariance: its own footprint pad (rho, the walk's bounds)
        cov = np.diag(rng.uniform(1e-7, 4e-5, 6)) if k % 2 else None
        for m in (ref, dev):
            m.integrate(img, T, pose_cov=cov)
        if k == 3:  # a read halfway (the device's arrays come to the host, then go back)
            c, a = _layer(dev)
            np.testing.assert_array_equal(c, ref.layer("confidence").confirmed)
            np.testing.assert_array_equal(a, ref.layer("confidence").arcs)
    np.testing.assert_array_equal(dev.raw_values().view(np.uint32), ref.raw_values().view(np.uint32))
    c_ref, a_ref = _layer(ref)
    c_dev, a_dev = _layer(dev)
    # not an empty comparison: the pings observed voxels along their arcs and confirmed some
    assert (a_ref != 0).sum() > 100 and c_ref.sum() >= 1
    np.testing.assert_array_equal(c_dev, c_ref)
    np.testing.assert_array_equal(a_dev, a_ref)
    np.testing.assert_array_equal(dev.layer("confidence").states(), ref.layer("confidence").states())


def test_host_writes_reach_the_device_and_reset_clears_it(other_backend):
    """Writes into the host's arrays (as a map file's load makes them) are what the next pass starts
    from; reset forgets the device's layer too."""
    rng = np.random.default_rng(5)
    ref, dev = (with_confidence(gpumap.MinMaxMapper(SPEC, GRID, b, MapperParams(rule="visible")))
                for b in ("numpy", other_backend))
    pings = [(_image(rng), _pose(rng)) for _ in range(4)]
    for img, T in pings[:2]:
        for m in (ref, dev):
            m.integrate(img, T)
    marks = rng.integers(0, 1 << 13, GRID.n_voxels).astype(np.uint16)
    for m in (ref, dev):
        m.layer("confidence").arcs[:] = marks
        m.layer("confidence").confirmed[::7] = 1
    for img, T in pings[2:]:
        for m in (ref, dev):
            m.integrate(img, T)
    for x, y in zip(_layer(dev), _layer(ref), strict=True):
        np.testing.assert_array_equal(x, y)
    dev.reset()
    fresh = with_confidence(gpumap.MinMaxMapper(SPEC, GRID, "numpy", MapperParams(rule="visible")))
    for m in (dev, fresh):
        m.integrate(*pings[3])
    for x, y in zip(_layer(dev), _layer(fresh), strict=True):
        np.testing.assert_array_equal(x, y)


@needs_data
def test_the_device_pass_equals_the_reference_on_the_real_tank(other_backend):
    """The real Oculus tank frames (every 8th) at 5 cm on the OASIS box, the default rule."""
    from merged_maps import tank

    frames = [f for f in tank(8) if f.T_W_S is not None]
    grid = gpumap.GridSpec((-0.5, -1.2, -0.5), (1.9, 1.2, 0.8), 0.05)
    ref, dev = (with_confidence(gpumap.MinMaxMapper(frames[0].spec, grid, backend=b))
                for b in ("numpy", other_backend))
    for f in frames:
        for m in (ref, dev):
            m.integrate(f.image, f.T_W_S)
    c_ref, a_ref = _layer(ref)
    c_dev, a_dev = _layer(dev)
    assert c_ref.sum() >= 1 and (a_ref != 0).sum() > 1000
    np.testing.assert_array_equal(c_dev, c_ref)
    np.testing.assert_array_equal(a_dev, a_ref)
    np.testing.assert_array_equal(dev.raw_values().view(np.uint32), ref.raw_values().view(np.uint32))


def test_the_gpu_launches_run_on_warp_cpu_too(monkeypatch):
    """The launch sequence GPUs take (the kernels' whole-image passes, one rival table, a thread per
    box voxel for the candidates) run by Warp on the CPU: the same layer as the reference (the CI
    machine has no GPU; the CPU sequence replaces two of these kernels with NumPy)."""
    from gpumap.backends import available_backends
    from gpumap.layers.confidence_device import DeviceConfidence

    if "warp-cpu" not in available_backends(["warp-cpu"]):
        pytest.skip("warp-cpu is not available here")
    init = DeviceConfidence._init_warp

    def as_gpu(self):
        init(self)
        self.gpu = True

    monkeypatch.setattr(DeviceConfidence, "_init_warp", as_gpu)
    rng = np.random.default_rng(6)
    ref, dev = (make_mapper(SPEC, GRID, backend=b, confidence=True, **OPTIONS)
                for b in ("numpy", "warp-cpu"))
    seed = int(rng.integers(1 << 30))
    _random_state(ref, np.random.default_rng(seed))
    _random_state(dev, np.random.default_rng(seed))
    for _ in range(6):
        img, T = _image(rng), _pose(rng)
        for m in (ref, dev):
            m.integrate(img, T)
    assert dev.layer("confidence")._device.gpu
    c_ref, a_ref = _layer(ref)
    assert c_ref.sum() >= 1
    for x, y in zip(_layer(dev), (c_ref, a_ref), strict=True):
        np.testing.assert_array_equal(x, y)
