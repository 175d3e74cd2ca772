"""MinMaxMapper.integrate_batch: the same map, bit for bit, as one integrate call per ping.

Every update is a min or a saturating count, so a batch must give exactly the grid (and, for the
visible rule, the evidence) of sequential calls, on every backend, for both rules, uint8 and
float images, with pose uncertainty, and when the batch is split (far-apart pings, more pings
than one launch takes). The GPU batch kernels also run here on the CPU devices (Warp's CPU
device, PoCL), so machines without a GPU test them too. Bad input is refused with the map as
it was.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import pose, rot_y, rot_z
from maps import make_mapper
from test_mapper import GRID, SPEC

import gpumap
import gpumap.backends
from gpumap.core.params import MapperParams

RULES = ("plain", "visible")


def _pings(n: int, seed: int, spread_m: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """(n, n_bins, n_beams) float32 images (dark water, then returns and shadows per beam) and
    (n, 4, 4) poses within ``spread_m`` of the origin."""
    rng = np.random.default_rng(seed)
    nb, nj = SPEC.image_shape
    imgs, poses = [], []
    for _ in range(n):
        first = rng.integers(5, nb + 20, nj)
        after = np.arange(nb)[:, None] >= first[None, :]
        imgs.append(np.where(after, rng.random((nb, nj)) ** 3, 0.09 * rng.random((nb, nj))))
        R = rot_z(rng.uniform(-0.4, 0.4)) @ rot_y(rng.uniform(-0.3, 0.3))
        poses.append(pose(R, rng.uniform(-spread_m, spread_m, 3)))
    return np.asarray(imgs, np.float32), np.asarray(poses)


def _state(m: gpumap.MinMaxMapper) -> dict[str, np.ndarray]:
    out = {"values": m.raw_values()}
    if m.rule == "visible":
        out.update(m.evidence())
    return out


def _assert_same(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for k in a:
        assert a[k].dtype == b[k].dtype
        # bitwise: +inf and NaN-free float maps compare exactly; view as bits to be strict
        assert np.array_equal(a[k].view(np.uint8), b[k].view(np.uint8)), f"{k} differs"


def _sequential(backend, rule, imgs, poses, covs=None, **kw) -> gpumap.MinMaxMapper:
    m = make_mapper(SPEC, GRID, backend=backend, rule=rule, **kw)
    for k in range(len(imgs)):
        m.integrate(imgs[k], poses[k], None if covs is None else covs[k])
    return m


def _batch_kernels(m: gpumap.MinMaxMapper) -> gpumap.MinMaxMapper:
    """Make a CPU backend fold batches with the GPU batch kernels (warp-cpu, opencl-cpu)."""
    if not hasattr(m.storage.backend, "batch_kernels"):
        pytest.skip(f"{m.backend} has no batch kernels")
    m.storage.backend.batch_kernels = True
    return m


@pytest.mark.parametrize("rule", RULES)
@pytest.mark.parametrize("kernels", [False, True], ids=["as-shipped", "batch-kernels"])
def test_batch_equals_sequential_bitwise(backend, rule, kernels):
    imgs, poses = _pings(9, seed=1)
    ref = _state(_sequential(backend, rule, imgs, poses))
    m = gpumap.MinMaxMapper(SPEC, GRID, backend, MapperParams(rule=rule))
    if kernels:
        _batch_kernels(m)
    m.integrate_batch(imgs[:4], poses[:4])
    m.integrate_batch(imgs[4:], poses[4:])
    _assert_same(_state(m), ref)
    assert m.n_integrated == 9
    # and the batch observed something: the comparison is not between two empty maps
    assert np.isfinite(ref["values"]).sum() > 1000


@pytest.mark.parametrize("rule", RULES)
def test_uint8_batch_equals_sequential(backend, rule, monkeypatch):
    monkeypatch.setattr(gpumap.backends, "COPY_SPLIT_BYTES", 0)  # staging filled on threads
    monkeypatch.setattr(gpumap.backends, "COPY_THREADS", 3)
    imgs, poses = _pings(6, seed=2)
    u8 = np.round(imgs * 255).astype(np.uint8)
    ref = _state(_sequential(backend, rule, u8, poses))
    for kernels in (False, True):
        m = gpumap.MinMaxMapper(SPEC, GRID, backend, MapperParams(rule=rule))
        if kernels and hasattr(m.storage.backend, "batch_kernels"):
            _batch_kernels(m)
        m.integrate_batch(u8, poses)
        _assert_same(_state(m), ref)


@pytest.mark.parametrize("rule", RULES)
def test_batch_with_pose_cov_equals_sequential(backend, rule):
    imgs, poses = _pings(5, seed=3)
    rng = np.random.default_rng(3)
    covs = []
    for _ in range(5):
        A = rng.normal(size=(6, 6)) * 1e-3
        covs.append(A @ A.T)
    covs = np.asarray(covs)
    ref = _state(_sequential(backend, rule, imgs, poses, covs))
    m = gpumap.MinMaxMapper(SPEC, GRID, backend, MapperParams(rule=rule))
    if hasattr(m.storage.backend, "batch_kernels"):
        _batch_kernels(m)
    m.integrate_batch(imgs, poses, pose_cov=covs)
    _assert_same(_state(m), ref)
    # one covariance for the whole batch
    ref1 = _state(_sequential(backend, rule, imgs, poses, [covs[0]] * 5))
    m1 = gpumap.MinMaxMapper(SPEC, GRID, backend, MapperParams(rule=rule))
    m1.integrate_batch(imgs, poses, pose_cov=covs[0])
    _assert_same(_state(m1), ref1)
    # wider footprints than without: the pad did something
    plain = _state(_sequential(backend, rule, imgs, poses))
    assert np.isfinite(ref["values"]).sum() >= np.isfinite(plain["values"]).sum()
    assert not np.array_equal(ref["values"], plain["values"])


@pytest.mark.parametrize("rule", RULES)
def test_split_batches_far_apart_and_over_the_launch_cap(backend, rule, monkeypatch):
    """Pings far apart (the union of their boxes is mostly empty) and more pings than one launch
    takes are split into several launches: still the sequential map."""
    monkeypatch.setattr(gpumap.backends, "BATCH_MAX", 3)
    imgs, poses = _pings(8, seed=4)
    poses[4:, 0, 3] += 1.2  # the last four pings 1.2 m away along x
    ref = _state(_sequential(backend, rule, imgs, poses))
    m = gpumap.MinMaxMapper(SPEC, GRID, backend, MapperParams(rule=rule))
    if hasattr(m.storage.backend, "batch_kernels"):
        _batch_kernels(m)
    m.integrate_batch(imgs, poses)
    _assert_same(_state(m), ref)


def test_union_groups_split_far_apart_boxes_and_long_runs(monkeypatch):
    monkeypatch.setattr(gpumap.backends, "BATCH_MAX", 3)
    params = np.zeros(8, dtype=gpumap.geometry.PING_DTYPE)
    params["box_n"] = 10
    params["box_lo"][4:] = (100, 0, 0)  # the last four boxes far from the first four
    n_threads = np.full(8, 100)
    n_threads[2] = 0  # a ping that sees no voxel joins any run
    runs = gpumap.backends._union_groups(params, n_threads)
    assert runs[0][0] == 0 and runs[-1][1] == 8
    assert all(a1 == b0 for (_, a1), (b0, _) in zip(runs, runs[1:], strict=False))
    assert all(b - a <= 3 for a, b in runs)
    assert all(not (a < 4 < b) for a, b in runs)  # never across the jump
    monkeypatch.setattr(gpumap.backends, "BATCH_MAX", 64)
    assert gpumap.backends._union_groups(params, n_threads) == [(0, 4), (4, 8)]


def test_knobs_set_on_the_package_reach_the_backends(monkeypatch):
    """gpumap.pipeline.workers and bench/ab.py set gpumap.backends.CPU_THREADS and GPU_CHUNK, and tests
    patch the others there: each lands in gpumap.backends.base, where the backends read it."""
    from gpumap.backends import base

    for name, value in (("CPU_THREADS", 1), ("GPU_CHUNK", 5), ("CPU_CHUNK", 7), ("BATCH_MAX", 3),
                        ("BATCH_BOX_VOXELS_MAX", 11), ("COPY_THREADS", 3), ("COPY_SPLIT_BYTES", 0)):
        before = getattr(base, name)
        monkeypatch.setattr(gpumap.backends, name, value)
        assert getattr(base, name) == value and getattr(gpumap.backends, name) == value, name
        assert name not in vars(gpumap.backends), name  # never a copy that could go stale
        monkeypatch.undo()
        assert getattr(base, name) == before and getattr(gpumap.backends, name) == before, name
    if "warp-cpu" in gpumap.available_backends():  # and a backend made afterwards follows them
        monkeypatch.setattr(gpumap.backends, "CPU_THREADS", 1)
        monkeypatch.setattr(gpumap.backends, "CPU_CHUNK", 7)
        be = gpumap.backends.make_backend("warp-cpu", SPEC)
        assert be._pool is None and be.chunk == 7


def test_empty_batch_is_a_no_op():
    m = gpumap.MinMaxMapper(SPEC, GRID, backend="numpy")
    m.integrate_batch(np.zeros((0, *SPEC.image_shape), np.float32), np.zeros((0, 4, 4)))
    assert m.n_integrated == 0 and not m.observed().any()


def _bad_inputs():
    imgs, poses = _pings(3, seed=5)
    nan = imgs.copy()
    nan[2, 10, 7] = np.nan
    big = imgs.copy()
    big[1, 0, 0] = 1.5
    bad_pose = poses.copy()
    bad_pose[1, :3, :3] *= 1.1  # not orthonormal
    cov_neg = -np.eye(6)
    masked = np.ma.MaskedArray(imgs, mask=np.zeros(imgs.shape, bool))
    return [
        ("list", (list(imgs), poses), {}, TypeError, "numpy array"),
        ("2-D", (imgs[0], poses[:1]), {}, ValueError, "shape"),
        ("shape", (imgs[:, :-1], poses), {}, ValueError, "shape"),
        ("dtype", (imgs.astype(np.int16), poses), {}, TypeError, "dtype"),
        ("NaN", (nan, poses), {}, ValueError, "ping 2, bin 10, beam 7"),
        ("range", (big, poses), {}, ValueError, "ping 1"),
        ("masked", (masked, poses), {}, TypeError, "masked"),
        ("n poses", (imgs, poses[:2]), {}, ValueError, "(3, 4, 4)"),
        ("bad pose", (imgs, bad_pose), {}, ValueError, "T_W_S[1]"),
        ("cov shape", (imgs, poses), {"pose_cov": np.eye(5)}, ValueError, "pose_cov"),
        ("cov negative", (imgs, poses), {"pose_cov": np.stack([np.eye(6) * 1e-4] * 2 + [cov_neg])},
         ValueError, "semi-definite"),
        ("sigmas", (imgs, poses), {"pose_cov": np.eye(6) * 1e-4, "pose_sigmas": -1.0}, ValueError,
         "pose_sigmas"),
    ]


@pytest.mark.parametrize("case", _bad_inputs(), ids=lambda c: c[0])
def test_bad_batches_are_refused_and_the_map_is_unchanged(backend, case):
    _, args, kw, err, text = case
    imgs, poses = _pings(2, seed=6)
    m = gpumap.MinMaxMapper(SPEC, GRID, backend=backend)
    m.integrate_batch(imgs, poses)
    before = _state(m)
    with pytest.raises(err, match=text.replace("(", r"\(").replace(")", r"\)").replace("[", r"\[")
                       .replace("]", r"\]")):
        m.integrate_batch(*args, **kw)
    _assert_same(_state(m), before)
    assert m.n_integrated == 2


def test_first_bright_per_cell_equals_per_beam(backend):
    """The GPUs' per-cell first-bright kernels (an atomic min per bright cell) give the per-beam
    scan's map, run here on whatever device the backend has."""
    imgs, poses = _pings(5, seed=7)
    ref = _state(_sequential(backend, "visible", imgs, poses))
    m = gpumap.MinMaxMapper(SPEC, GRID, backend, MapperParams(rule="visible"))
    if not hasattr(m.storage.backend, "first_bright_cells"):
        pytest.skip(f"{m.backend} has one first-bright path")
    m.storage.backend.first_bright_cells = not m.storage.backend.first_bright_cells  # the other path
    for k in range(len(imgs)):
        m.integrate(imgs[k], poses[k])
    _assert_same(_state(m), ref)
    assert (ref["count"] > 0).any()  # some clear views: the first bright bins mattered


@pytest.mark.parametrize("rule", ["plain", "visible", "evidence"])
@pytest.mark.parametrize("sparse", [False, True], ids=["dense", "sparse"])
def test_batch_kernel_equals_the_oracle(backend, rule, sparse, monkeypatch):
    """The GPU batch kernel (a thread per voxel of the union box, holding its values in registers
    over the pings) gives the NumPy oracle's map and evidence bit for bit, for every rule, on a
    bounded map and on one with blocks on demand, uint8 pings included, and in batches split over
    several launches."""
    monkeypatch.setattr(gpumap.backends, "BATCH_MAX", 4)
    imgs, poses = _pings(7, seed=11)
    poses[5:, 1, 3] += 0.6  # the last pings elsewhere: a second group
    u8 = np.round(imgs * 255).astype(np.uint8)

    def state(m):
        out = {"values": m.raw_values()}
        if m.rule != "plain":
            out.update(m.evidence())
        return out

    ref = gpumap.MinMaxMapper(SPEC, GRID, "numpy", MapperParams(rule=rule, sparse=sparse))
    ref.integrate_batch(u8[:3], poses[:3])
    ref.integrate_batch(imgs[3:], poses[3:])
    m = gpumap.MinMaxMapper(SPEC, GRID, backend, MapperParams(rule=rule, sparse=sparse))
    if hasattr(m.storage.backend, "batch_kernels"):
        _batch_kernels(m)
    m.integrate_batch(u8[:3], poses[:3])
    m.integrate_batch(imgs[3:], poses[3:])
    _assert_same(state(m), state(ref))
    assert np.isfinite(state(ref)["values"]).sum() > 1000
    m.storage.check()  # no observed voxel without a block
