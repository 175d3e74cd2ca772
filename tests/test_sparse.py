"""SparseMinMaxMapper: the dense grid's values bit for bit, memory only where pings looked.

References: the dense :class:`gpumap.MinMaxMapper` on the same backend (itself tested
against float64 brute force in test_mapper / test_visibility) and plain NumPy set algebra
over its observed voxels; scenes are rendered by the simulator.
"""

from __future__ import annotations

import math
import zipfile

import numpy as np
import pytest
from conftest import pose, rot_y, rot_z
from maps import make_mapper
from test_mapper import GRID, SPEC
from test_visibility import _random_pings

import gpumap
from gpumap import MapMemoryError, SparseMinMaxMapper, SparseSpec
from gpumap.core.params import MapperParams
from gpumap.reference import split_counts

S = GRID.voxel_size_m
BOUNDED = SparseSpec(S, (GRID.min_corner_m, GRID.max_corner_m))
# unbounded, on the dense grid's lattice (bitwise equality needs the same voxel centres)
UNBOUNDED = SparseSpec(S, origin_m=GRID.min_corner_m)


def _dense(backend, pings, rule="visible", spec=SPEC, grid=GRID, **kw):
    m = gpumap.MinMaxMapper(spec, grid, backend, MapperParams(rule=rule, threshold=0.1))
    for img, T, *cov in pings:
        m.integrate(img, T, *cov, **kw)
    return m


def _sparse(backend, pings, sparse=BOUNDED, rule="visible", spec=SPEC, **kw):
    m = make_mapper(
        spec,
        sparse,
        backend=backend,
        rule=rule,
        threshold=0.1,
        initial_blocks=2,
        **kw,
        cls=SparseMinMaxMapper,
    )
    for img, T, *cov in pings:
        m.integrate(img, T, *cov)
    return m


def _in_grid(m: SparseMinMaxMapper, grid: gpumap.GridSpec, name: str = "values") -> np.ndarray:
    """The sparse map's ``name`` over the dense grid's voxels (+inf / 0 where no block)."""
    i0 = np.round((np.asarray(grid.min_corner_m) - m.storage.origin) / grid.voxel_size_m).astype(np.int64)
    return m.storage.dense(i0, i0 + np.asarray(grid.shape) - 1, (name,))[name]


def _assert_same(sparse: SparseMinMaxMapper, dense: gpumap.MinMaxMapper) -> None:
    sparse.check()  # no observed voxel fell outside the allocated blocks
    if dense.rule != "plain":
        ev = dense.evidence()
        for k in ("min_all", "bright"):
            np.testing.assert_array_equal(_in_grid(sparse, dense.grid, k), ev[k], err_msg=k)
        dark, hits = split_counts(_in_grid(sparse, dense.grid, "count"))
        np.testing.assert_array_equal(dark, ev["count"], err_msg="count")
        np.testing.assert_array_equal(hits, ev["hits"], err_msg="hits")
    np.testing.assert_array_equal(_in_grid(sparse, dense.grid), dense.raw_values())


def _blocks_of_observed(dense: gpumap.MinMaxMapper, B: int) -> set:
    return {tuple(b) for b in np.argwhere(dense.observed()) // B}


def _block_set(m: SparseMinMaxMapper) -> set:
    """The blocks the map holds (memory_stats first frees those allocated but never observed)."""
    m.memory_stats()
    return {tuple(c) for c in m.storage.coords[m.storage.used]}


# ------------------------------------------------------------------------------ identical maps
@pytest.mark.parametrize("rule", ["evidence", "visible", "plain"])
def test_random_pings_bounded_and_unbounded_equal_dense(backend, rule):
    pings = _random_pings(5, 3)
    d = _dense(backend, pings, rule)
    b = _sparse(backend, pings, BOUNDED, rule)
    u = _sparse(backend, pings, UNBOUNDED, rule)
    assert b.grid == GRID and b.raw_values().shape == GRID.shape
    np.testing.assert_array_equal(b.raw_values(), d.raw_values())
    np.testing.assert_array_equal(b.observed(), d.observed())
    _assert_same(b, d)
    _assert_same(u, d)
    np.testing.assert_array_equal(b.occupied_points(0.1), d.occupied_points(0.1))
    # the unbounded map also holds what the dense grid clips away, at negative indices too
    assert u.memory_stats()["observed_voxels"] > d.observed().sum()
    assert np.any(np.asarray(u.grid.min_corner_m) < np.asarray(GRID.min_corner_m) - S)
    # blocks: exactly those holding an observed voxel
    assert _block_set(b) == _blocks_of_observed(d, 8)


def test_pose_covariance_and_uint8_images_equal_dense(backend):
    rng = np.random.default_rng(5)
    C = np.diag([1e-4, 2e-4, 1e-4, 1e-4, 3e-4, 2e-4])
    pings = [((img * 255).astype(np.uint8), T, C * rng.uniform(0.5, 2)) for img, T in _random_pings(3, 8)]
    _assert_same(_sparse(backend, pings, UNBOUNDED), _dense(backend, pings))


def test_block_size_does_not_change_values(backend):
    pings = _random_pings(3, 9)
    d = _dense(backend, pings)
    for B in (4, 16):
        m = _sparse(backend, pings, SparseSpec(S, origin_m=GRID.min_corner_m, block=B))
        _assert_same(m, d)


def test_order_of_pings_does_not_change_the_sparse_map(backend):
    pings = _random_pings(5, 4)
    a = _sparse(backend, pings, UNBOUNDED)
    b = _sparse(backend, [pings[i] for i in (3, 0, 4, 1, 2)], UNBOUNDED)
    np.testing.assert_array_equal(a.raw_values(), b.raw_values())
    assert a.grid == b.grid


# ------------------------------------------------------------------------------ simulated scenes
@pytest.fixture(scope="module", params=["tank", "circle"])
def scene_pings(request):
    """(scene, 8 pings evenly spaced along its trajectory) at 6 cm voxels."""
    from gpumap.sim.scenes import make_scene
    from gpumap.sim.sonar import SonarSimulator

    scene = make_scene(request.param, voxel_size_m=0.06)
    ks = np.linspace(0, len(scene.T_W_S) - 1, 8).round().astype(int)
    with SonarSimulator(scene, seed=1) as sim:
        pings = [(sim.ping(scene.T_W_S[k], k).image, scene.T_W_S[k]) for k in ks]
    return scene, pings


@pytest.mark.parametrize("rule", ["evidence", "visible", "plain"])
def test_scenes_sparse_equals_dense(backend, scene_pings, rule):
    scene, pings = scene_pings
    d = _dense(backend, pings, rule, spec=scene.sonar_spec, grid=scene.grid)
    g = scene.grid
    b = _sparse(
        backend,
        pings,
        SparseSpec(g.voxel_size_m, (g.min_corner_m, g.max_corner_m)),
        rule,
        spec=scene.sonar_spec,
    )
    u = _sparse(
        backend, pings, SparseSpec(g.voxel_size_m, origin_m=g.min_corner_m), rule, spec=scene.sonar_spec
    )
    np.testing.assert_array_equal(b.raw_values(), d.raw_values())
    _assert_same(u, d)
    assert _block_set(b) == _blocks_of_observed(d, 8)
    assert d.observed().sum() > 1000  # the pings see something


# ------------------------------------------------------------------------------ queries
def test_values_in_box_and_points_near_a_pose():
    pings = _random_pings(4, 6)
    d = _dense("numpy", pings)
    m = _sparse("numpy", pings, UNBOUNDED)
    lo, hi = np.array([0.2, -0.5, -0.3]), np.array([0.9, 0.4, 0.2])
    box, v = m.values_in_box(lo, hi)
    c = box.all_centers()
    assert np.all(c >= lo) and np.all(c <= hi) and box.voxel_size_m == S
    # every dense voxel centre inside [lo, hi] is in the box, with the dense value
    cd = GRID.all_centers()
    inside = np.all((cd >= lo) & (cd <= hi), axis=-1)
    assert inside.sum() == np.prod(v.shape)
    np.testing.assert_array_equal(np.nan_to_num(v.ravel(), nan=-1), np.nan_to_num(d.values()[inside], nan=-1))
    # points around a pose: the dense occupied points within the radius, brute force
    T = pings[1][1]
    r = 0.6
    want = d.occupied_points(0.1)
    want = want[np.linalg.norm(want - T[:3, 3], axis=1) <= r]
    got = m.occupied_points(0.1, center_m=T, radius_m=r)
    assert len(want) > 20
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="together"):
        m.occupied_points(0.1, center_m=T)


# ------------------------------------------------------------------------------ memory
def test_memory_counts_only_blocks_with_an_observed_voxel():
    pings = _random_pings(5, 10)
    m = _sparse("numpy", pings, UNBOUNDED)
    st = m.memory_stats()
    obs = np.argwhere(m.observed())
    i0 = np.round((np.asarray(m.grid.min_corner_m) - m.storage.origin) / S).astype(np.int64)
    blocks = {tuple(b) for b in (obs + i0) // 8}
    assert st["blocks"] == len(blocks) == len(_block_set(m))
    assert st["observed_voxels"] == len(obs)
    assert st["block_bytes"] == st["blocks"] * 512 * 16
    assert st["observed_bytes"] == len(obs) * 16
    assert st["total_bytes"] == st["pool_bytes"] + st["index_bytes"]
    assert st["pool_blocks"] >= st["blocks"]
    # the pool grew from 2 slots by 1.5x steps, never far past what the blocks need
    assert st["pool_blocks"] <= max(2, math.ceil(1.5 * st["blocks"]) + 64)


def test_memory_grows_with_what_was_seen_not_with_the_box():
    """A ping far away adds its blocks only: the map's memory is two pings' worth, not the box's."""
    spec = SPEC
    img = np.full(spec.image_shape, 0.05, np.float32)
    T0 = pose(np.eye(3), (0.0, 0.0, 0.0))
    T1 = pose(rot_z(0.4), (40.0, -25.0, 3.0))
    one = _sparse("numpy", [(img, T0)], SparseSpec(0.05)).memory_stats()
    two = _sparse("numpy", [(img, T0), (img, T1)], SparseSpec(0.05)).memory_stats()
    assert 1.5 * one["blocks"] <= two["blocks"] <= 2.5 * one["blocks"]
    assert two["dense_bytes"] > 100 * two["block_bytes"]
    assert two["index_bytes"] < 0.02 * two["dense_bytes"]


# ------------------------------------------------------------------------------ save / load
@pytest.mark.parametrize("sparse", [BOUNDED, UNBOUNDED], ids=["bounded", "unbounded"])
@pytest.mark.parametrize("rule", ["evidence", "visible", "plain"])
def test_save_load_round_trip(tmp_path, backend, sparse, rule):
    pings = _random_pings(5, 12)
    m = _sparse(backend, pings[:3], sparse, rule)
    m.carve_views = 3
    path = m.save(tmp_path / "map")
    assert path.suffix == ".npz"
    back = SparseMinMaxMapper.load(path, backend=backend)
    assert back.n_integrated == 3 and back.carve_views == 3 and back.rule == rule
    assert back.sparse == sparse and back.spec == SPEC
    np.testing.assert_array_equal(back.raw_values(), m.raw_values())
    if rule != "plain":
        for k, a in m.evidence().items():
            np.testing.assert_array_equal(back.evidence()[k], a, err_msg=k)
    # a loaded map goes on exactly as the original would
    for img, T in pings[3:]:
        m.integrate(img, T)
        back.integrate(img, T)
    np.testing.assert_array_equal(back.raw_values(), m.raw_values())
    assert back.memory_stats()["blocks"] == m.memory_stats()["blocks"]


def _rewrite(src, dst, **changes):
    """Copy a saved map, replacing members (name -> array)."""
    with np.load(src) as z:
        arrays = {k: z[k] for k in z.files}
    arrays.update(changes)
    np.savez_compressed(dst, **arrays)
    return dst


def test_load_refuses_bad_files(tmp_path):
    m = _sparse("numpy", _random_pings(3, 13), UNBOUNDED)
    path = m.save(tmp_path / "ok.npz")
    with np.load(path) as z:
        blocks, values, min_all = z["blocks"], z["values"], z["min_all"]
    bad = values.copy()
    bad[0, 0, 0, 0] = 2.0
    dup = blocks.copy()
    dup[1] = dup[0]
    with np.load(path) as z:
        bright, count = z["bright"], z["count"]
    unseen = {k: np.inf * np.ones_like(v[:1]) for k, v in (("values", values), ("min_all", min_all))}
    cases = {
        "in \\[0, 1\\]": dict(values=bad),
        "each block once": dict(blocks=dup),
        "shape": dict(blocks=blocks[:-1]),
        "observed voxel": dict(
            blocks=np.concatenate([blocks, [[999, 999, 999]]]).astype(np.int32),
            values=np.concatenate([values, unseen["values"]]),
            min_all=np.concatenate([min_all, unseen["min_all"]]),
            bright=np.concatenate([bright, unseen["min_all"]]),
            count=np.concatenate([count, np.zeros((1, 8, 8, 8), np.uint64)]),
        ),
        "format": dict(meta=np.array('{"format": "other"}')),
    }
    for msg, change in cases.items():
        with pytest.raises(ValueError, match=msg):
            SparseMinMaxMapper.load(_rewrite(path, tmp_path / "bad.npz", **change), backend="numpy")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="cannot be read"):
        SparseMinMaxMapper.load(tmp_path / "junk.npz", backend="numpy")
    with zipfile.ZipFile(tmp_path / "empty.npz", "w"):
        pass
    with pytest.raises(ValueError, match="'meta' and 'blocks'"):
        SparseMinMaxMapper.load(tmp_path / "empty.npz", backend="numpy")


def test_dense_map_file_is_not_a_sparse_one(tmp_path):
    p = _dense("numpy", _random_pings(1, 2)).save(tmp_path / "dense.npz")
    with pytest.raises(ValueError, match="sparse map file"):
        SparseMinMaxMapper.load(p, backend="numpy")


# ------------------------------------------------------------------------------ bad input
def test_spec_too_large_is_refused_up_front():
    with pytest.raises(MapMemoryError, match="blocks"):
        SparseMinMaxMapper(SPEC, SparseSpec(0.001, ((0, 0, 0), (1000, 1000, 100))), backend="numpy")
    with pytest.raises(MapMemoryError, match="max_bytes"):
        SparseMinMaxMapper(
            SPEC, SparseSpec(0.01, ((0, 0, 0), (10, 10, 4))), "numpy", MapperParams(max_bytes=10_000)
        )
    for bad in (
        dict(voxel_size_m=0.0),
        dict(voxel_size_m=0.1, block=1),
        dict(voxel_size_m=0.1, block=8.0),
        dict(voxel_size_m=0.1, bounds=((0, 0, 0), (1, 1, 0))),
        dict(voxel_size_m=0.1, bounds=((0, 0, 0), (1, 1, 1)), origin_m=(0, 0, 0)),
    ):
        with pytest.raises(ValueError):
            SparseSpec(**bad)
    with pytest.raises(ValueError, match="max_bytes"):
        SparseMinMaxMapper(SPEC, BOUNDED, "numpy", MapperParams(max_bytes=0))


def test_cap_exceeded_raises_with_the_map_unchanged(backend):
    pings = [
        (img, pose(T[:3, :3], T[:3, 3] + (0.0, 0.7 * k, 0.0)))
        for k, (img, T) in enumerate(_random_pings(6, 14))
    ]
    first = _sparse(backend, pings[:1], UNBOUNDED)
    cap = first.memory_stats()["total_bytes"] + 2 * (512 * 9 + 1)
    m = _sparse(backend, pings[:1], UNBOUNDED, max_bytes=cap)
    for img, T in pings[1:]:
        before, n, blocks = m.raw_values(), m.n_integrated, m.memory_stats()["blocks"]
        try:
            m.integrate(img, T)
        except MapMemoryError as e:
            assert "max_bytes" in str(e)
            break
    else:
        pytest.fail("Expected a ping to pass the cap")
    assert m.n_integrated == n  # the failing ping is not counted
    np.testing.assert_array_equal(m.raw_values(), before)
    st = m.memory_stats()
    assert st["blocks"] == blocks and st["total_bytes"] <= cap


def test_bad_images_and_poses_leave_the_map_unchanged():
    pings = _random_pings(2, 15)
    m = _sparse("numpy", pings[:1], UNBOUNDED)
    before, n = m.raw_values(), m.memory_stats()["blocks"]
    img, T = pings[1]
    far = T.copy()
    far[:3, 3] = (1e9, 0, 0)
    for args, err in (
        ((img[:-1], T), ValueError),
        ((img * 2, T), ValueError),
        ((img, far), ValueError),
        ((img, np.eye(3)), ValueError),
        ((img.astype(np.int16), T), TypeError),
    ):
        with pytest.raises(err):
            m.integrate(*args)
    np.testing.assert_array_equal(m.raw_values(), before)
    assert m.memory_stats()["blocks"] == n and m.n_integrated == 1


def test_eviction_keeps_memory_under_the_cap_and_the_latest_view(backend):
    """evict='farthest': the map stays under max_bytes, and what the last ping saw is mapped as a
    fresh map of that ping alone maps it (or lower, where earlier pings also saw it)."""
    spec = SPEC
    rng = np.random.default_rng(3)
    img = (rng.random(spec.image_shape) * 0.5).astype(np.float32)
    poses = [pose(rot_z(0.3 * k), (2.0 * k, 0.0, 0.0)) for k in range(6)]
    one = _sparse(backend, [(img, poses[0])], SparseSpec(0.1)).memory_stats()
    cap = 2 * one["blocks"] * (512 * 16 + 1) + 4096
    m = _sparse(backend, [(img, T) for T in poses], SparseSpec(0.1), max_bytes=cap, evict="farthest")
    st = m.memory_stats()
    assert st["total_bytes"] <= cap and m.n_integrated == 6
    last = _sparse(backend, [(img, poses[-1])], SparseSpec(0.1))
    box = last.grid
    lo, hi = np.asarray(box.min_corner_m), np.asarray(box.max_corner_m)
    _, want = last.values_in_box(lo, hi)
    _, got = m.values_in_box(lo, hi)
    seen = ~np.isnan(want)
    assert seen.sum() > 100
    assert np.all(~np.isnan(got[seen])) and np.all(got[seen] <= want[seen])
    # the first pose's blocks (farthest from the last) were evicted
    first = _sparse(backend, [(img, poses[0])], SparseSpec(0.1))
    assert not (_block_set(first) & _block_set(m))


def test_reset_forgets_every_block():
    m = _sparse("numpy", _random_pings(2, 16), UNBOUNDED)
    m.reset()
    st = m.memory_stats()
    assert st["blocks"] == 0 and st["observed_voxels"] == 0 and m.n_integrated == 0
    assert m.occupied_points(0.0).shape == (0, 3)


def test_rotated_sonar_far_from_origin_equals_dense():
    """A pose 30 m from the origin on a grid placed there: float32 rounding of world
    coordinates does not make the block test miss a voxel (the kernel's err flag stays 0)."""
    t = np.array([30.0, -20.0, 5.0])
    grid = gpumap.GridSpec(tuple(t - 1.6), tuple(t + 1.6), 0.05)
    pings = [(img, pose(T[:3, :3] @ rot_y(0.3), t + T[:3, 3])) for img, T in _random_pings(3, 17)]
    d = _dense("numpy", pings, grid=grid)
    u = _sparse("numpy", pings, SparseSpec(0.05, origin_m=grid.min_corner_m))
    _assert_same(u, d)


def test_integrate_batch_is_the_map_of_single_pings_and_checks_first(backend):
    pings = _random_pings(4, 18)
    one = _sparse(backend, pings, UNBOUNDED)
    m = _sparse(backend, [], UNBOUNDED)
    imgs = np.stack([img for img, _ in pings])
    Ts = np.stack([T for _, T in pings])
    m.integrate_batch(imgs, Ts)
    np.testing.assert_array_equal(m.raw_values(), one.raw_values())
    assert m.n_integrated == 4
    bad = imgs.copy()
    bad[2, 0, 0] = np.nan
    before = m.raw_values()
    with pytest.raises(ValueError, match="ping 2"):
        m.integrate_batch(bad, Ts)
    np.testing.assert_array_equal(m.raw_values(), before)
    assert m.n_integrated == 4
    # a batch that passes the cap changes nothing (its blocks are allocated before any ping)
    far = Ts.copy()
    far[:, 0, 3] += np.arange(4) * 2.0 + 5.0
    capped = _sparse(backend, pings, UNBOUNDED, max_bytes=one.memory_stats()["total_bytes"])
    before = capped.raw_values()
    with pytest.raises(MapMemoryError):
        capped.integrate_batch(imgs, far)
    np.testing.assert_array_equal(capped.raw_values(), before)
    assert capped.n_integrated == 4



