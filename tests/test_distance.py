"""The distance field of the safe map (gpumap.layers.distance) on every backend, against independent
references.

References share no code with the kernels: SciPy's ``distance_transform_edt`` (with the voxel size as
sampling), brute force over every obstacle centre on tiny grids, analytic fields (a slab of obstacles
gives a distance linear in x), and finite differences for the gradient. The kernels' NumPy twin
(``edt_reference``) is itself checked against brute force, then every backend's integers against it.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import pose, rot_y, rot_z
from scipy import ndimage

import gpumap
from gpumap.core.params import MapperParams
from gpumap.errors import BackendUnavailableError
from gpumap.layers.distance import DistanceField, cap_squared, trilinear
from gpumap.layers.distance_device import INF, edt_reference, make_transform

SPEC = gpumap.SonarSpec.uniform(hfov_deg=120, vfov_deg=20, n_beams=48, n_bins=60, range_min_m=0.15,
                                range_max_m=1.5)
GRID = gpumap.GridSpec((-0.3, -1.2, -0.6), (1.6, 1.2, 0.6), 0.05)
RNG = np.random.default_rng(44)


def _pings(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(n, n_bins, n_beams) float32 images (dark water, then a return per beam and speckle behind it)
    and (n, 4, 4) poses sweeping in yaw, so that every batch observes new space."""
    rng = np.random.default_rng(seed)
    nb, nj = SPEC.image_shape
    imgs, poses = [], []
    for i in range(n):
        first = rng.integers(15, nb + 10, nj)
        after = np.arange(nb)[:, None] >= first[None, :]
        imgs.append(np.where(after, rng.random((nb, nj)) ** 2, 0.05 * rng.random((nb, nj))))
        yaw = -1.2 + 2.4 * i / max(n - 1, 1) + rng.uniform(-0.05, 0.05)
        poses.append(pose(rot_z(yaw) @ rot_y(rng.uniform(-0.3, 0.3)), rng.uniform(-0.05, 0.05, 3)))
    return np.asarray(imgs, np.float32), np.asarray(poses)


@pytest.fixture(scope="module")
def run():
    """A small mapped run, kept as the values after each of its batches."""
    imgs, poses = _pings(24, 1)
    m = gpumap.MinMaxMapper(SPEC, GRID, "numpy", MapperParams(threshold=0.3))
    return m, imgs, poses


class FakeMapper:
    """The four things the layer reads of a mapper, over values set by hand."""

    def __init__(self, values: np.ndarray, grid: gpumap.GridSpec, threshold: float = 0.5,
                 backend: str = "numpy") -> None:
        self.v, self.grid, self.threshold, self.backend = values, grid, threshold, backend

    def values(self) -> np.ndarray:
        return self.v.copy()


def _scipy_field(obstacles: np.ndarray, voxel: float, cap: float | None, signed: bool) -> np.ndarray:
    def edt(free):
        if free.all():
            return np.full(free.shape, np.inf)
        return ndimage.distance_transform_edt(free, sampling=voxel)

    d = edt(~obstacles)
    if signed:
        d = d - edt(obstacles)
    return d if cap is None else np.clip(d, -cap, cap)


def _brute_d2(mask: np.ndarray) -> np.ndarray:
    obs = np.argwhere(mask)
    idx = np.indices(mask.shape).reshape(3, -1).T
    if not len(obs):
        return np.full(mask.shape, INF, np.int64)
    return ((idx[:, None, :] - obs[None]) ** 2).sum(-1).min(1).reshape(mask.shape)


def _random_masks(n: int):
    rng = np.random.default_rng(3)
    for _ in range(n):
        shape = tuple(int(x) for x in rng.integers(1, 12, 3))
        p = float(rng.choice([0.0, 0.01, 0.1, 0.5, 1.0]))
        yield rng.random(shape) < p, int(rng.choice([INF - 1, 0, 3, 17]))


# ------------------------------------------------------------------ the transform
def test_kernel_twin_is_brute_force():
    for mask, cap2 in _random_masks(40):
        for inv in (False, True):
            bf = _brute_d2(mask != inv)
            want = np.where(bf > cap2, INF, bf)
            np.testing.assert_array_equal(edt_reference(mask, cap2, inv), want)


def test_every_backend_gives_the_twins_integers(backend):
    tr = make_transform(backend)
    cases = list(_random_masks(30))
    cases += [(np.zeros((1, 1, 9), bool), INF - 1), (np.ones((9, 1, 1), bool), INF - 1)]
    line = np.zeros((1, 40, 1), bool)
    line[0, [3, 4, 20, 39], 0] = True  # equal and tied parabolas in one line
    cases.append((line, INF - 1))
    for mask, cap2 in cases:
        got = tr(mask, cap2, (False, True))
        for inv, g in zip((False, True), got, strict=True):
            assert g.dtype == np.int32
            np.testing.assert_array_equal(g, edt_reference(mask, cap2, inv), err_msg=f"{mask.shape} {cap2}")


def test_cap_squared_is_the_largest_square_within_the_radius():
    assert cap_squared(None, 0.05) == INF - 1
    for r, s in ((0.5, 0.05), (0.1, 0.03), (0.01, 0.05), (1.0, 0.02)):
        c = cap_squared(r, s)
        assert np.sqrt(c) * s <= r + 1e-12 and np.sqrt(c + 1) * s > r - 1e-12


# ------------------------------------------------------------------ the field against SciPy
@pytest.mark.parametrize("unknown_is_obstacle", [True, False])
@pytest.mark.parametrize("cap", [None, 0.2])
def test_field_is_scipys_on_a_mapped_run(backend, run, unknown_is_obstacle, cap):
    m, imgs, poses = run
    m.reset()
    m.integrate_batch(imgs[:12], poses[:12])
    for signed in (False, True):
        df = DistanceField(m, unknown_is_obstacle=unknown_is_obstacle, max_distance_m=cap, signed=signed,
                           backend=backend)
        v = m.values()
        obst = (v >= np.float32(m.threshold)) | (np.isnan(v) if unknown_is_obstacle else False)
        np.testing.assert_array_equal(df.obstacles(), obst)
        assert 0.02 < obst.mean() < 0.98  # a real mix of obstacles and free voxels
        f = df.field()
        assert f.dtype == np.float32 and f.shape == GRID.shape
        want = _scipy_field(obst, GRID.voxel_size_m, cap, signed)
        np.testing.assert_allclose(f, want, rtol=0, atol=1e-5)
        if not signed:
            assert np.all(f[obst] == 0) and np.all(f[~obst] > 0)


def test_field_is_brute_force_on_a_tiny_grid(backend):
    g = gpumap.GridSpec((0.0, 0.0, 0.0), (0.35, 0.3, 0.2), 0.05)
    rng = np.random.default_rng(5)
    v = np.where(rng.random(g.shape) < 0.15, 0.9, 0.1).astype(np.float32)
    v[rng.random(g.shape) < 0.1] = np.nan
    df = DistanceField(FakeMapper(v, g), backend=backend)
    obst = (v >= 0.5) | np.isnan(v)
    c = g.all_centers().reshape(-1, 3)
    want = np.linalg.norm(c[:, None, :] - c[obst.ravel()][None], axis=2).min(1).reshape(g.shape)
    np.testing.assert_allclose(df.field(), want, rtol=0, atol=1e-6)


def test_no_obstacle_and_no_free_voxel():
    g = gpumap.GridSpec((0.0, 0.0, 0.0), (0.3, 0.2, 0.2), 0.05)
    free = np.zeros(g.shape, np.float32)
    assert np.all(DistanceField(FakeMapper(free, g)).field() == np.inf)
    assert np.all(DistanceField(FakeMapper(free, g), max_distance_m=0.12).field() == np.float32(0.12))
    unknown = np.full(g.shape, np.nan, np.float32)
    assert np.all(DistanceField(FakeMapper(unknown, g)).field() == 0)
    assert np.all(DistanceField(FakeMapper(unknown, g), signed=True).field() == -np.inf)
    assert np.all(DistanceField(FakeMapper(unknown, g), unknown_is_obstacle=False).field() == np.inf)


# ------------------------------------------------------------------ incremental
@pytest.mark.parametrize("options", [{}, {"unknown_is_obstacle": False}, {"max_distance_m": 0.15},
                                     {"signed": True, "max_distance_m": 0.3}])
def test_incremental_equals_full_after_every_batch(backend, run, options):
    m, imgs, poses = run
    m.reset()
    df = DistanceField(m, backend=backend, **options)
    kinds, n = [], GRID.n_voxels
    for a in range(0, len(imgs), 3):
        m.integrate_batch(imgs[a:a + 3], poses[a:a + 3])
        work = df.update()
        kinds.append(df.last_update["kind"])
        assert 0 <= work <= n
        full = DistanceField(m, backend="numpy", **options)
        np.testing.assert_array_equal(df.field(), full.field(), err_msg=f"after pings {a}..{a + 2}")
        np.testing.assert_array_equal(df.obstacles(), full.obstacles())
    # the run exercised the partial path (on the NumPy path's boxes, where distances stay short)
    if backend != "numpy" or options != {"unknown_is_obstacle": False}:
        assert "incremental" in kinds, kinds


@pytest.mark.parametrize("cap", [None, 0.4])
def test_removing_the_nearest_obstacle_moves_distances_far_away(backend, cap):
    """One obstacle voxel removed: every voxel that had it nearest now measures to the other one,
    across the whole grid (the region an update must reach is far wider than the change)."""
    g = gpumap.GridSpec((0.0, 0.0, 0.0), (1.5, 0.6, 0.4), 0.05)
    v = np.zeros(g.shape, np.float32)
    v[2, 5, 3] = v[27, 6, 4] = 0.9
    fm = FakeMapper(v, g, backend=backend)
    df = DistanceField(fm, max_distance_m=cap)
    for change in ((2, 5, 3, 0.0), (14, 2, 1, 0.9), (27, 6, 4, 0.0), (2, 5, 3, 0.9)):
        fm.v[change[:3]] = change[3]
        df.update()
        want = _scipy_field(fm.v >= 0.5, g.voxel_size_m, cap, False)
        np.testing.assert_allclose(df.field(), want, rtol=0, atol=1e-5)


def test_a_margin_too_narrow_is_caught_and_widened(monkeypatch):
    """The NumPy path transforms boxes with a margin and keeps a distance only where nothing beyond the
    margin could be nearer; a first margin of one voxel must be widened, never trusted."""
    g = gpumap.GridSpec((0.0, 0.0, 0.0), (15.0, 0.3, 0.3), 0.05)
    v = np.zeros(g.shape, np.float32)
    v[2:300:16] = 0.9  # planes of obstacles across x, 16 voxels apart
    fm = FakeMapper(v, g)
    df = DistanceField(fm, tile=4)
    monkeypatch.setattr(DistanceField, "_first_margin", lambda self, lo, hi: 1)
    fm.v[18] = 0.0  # the middle plane goes: the band around it now measures to the planes 16 voxels away
    df.update()
    assert df.last_update["kind"] == "incremental" and df.last_update["retries"] > 0
    np.testing.assert_allclose(df.field(), _scipy_field(fm.v >= 0.5, 0.05, None, False), rtol=0, atol=1e-5)


def test_an_update_without_change_recomputes_nothing_and_a_new_grid_everything(backend):
    g = gpumap.GridSpec((0.0, 0.0, 0.0), (0.4, 0.3, 0.2), 0.05)
    v = np.zeros(g.shape, np.float32)
    v[1, 1, 1] = 1.0
    fm = FakeMapper(v, g, backend=backend)
    df = DistanceField(fm)
    assert df.update() == 0 and df.last_update["kind"] == "none"
    g2 = gpumap.GridSpec((0.0, 0.0, 0.0), (0.5, 0.3, 0.2), 0.05)
    fm.grid, fm.v = g2, np.zeros(g2.shape, np.float32)
    fm.v[9, 0, 0] = 1.0
    assert df.update() == g2.n_voxels and df.grid == g2
    np.testing.assert_allclose(df.field(), _scipy_field(fm.v >= 0.5, 0.05, None, False), atol=1e-6)


def test_update_from_values_read_by_the_caller(backend):
    """update(values=...) is the field of those values, not of a read of the map (the node hands it the
    read its clouds came from); values of another shape or dtype are refused and the field stays."""
    g = gpumap.GridSpec((0.0, 0.0, 0.0), (0.4, 0.3, 0.2), 0.05)
    v = np.zeros(g.shape, np.float32)
    v[1, 1, 1] = 1.0
    fm = FakeMapper(v, g, backend=backend)
    df = DistanceField(fm, unknown_is_obstacle=False)
    given = v.copy()
    given[6, 4, 2] = 1.0  # an obstacle only in the values handed over
    given[0, 5, 0] = np.nan
    assert df.update(values=given) > 0 and df.last_update["kind"] != "none"
    want = _scipy_field(given >= 0.5, 0.05, None, False)
    np.testing.assert_allclose(df.field(), want, rtol=0, atol=1e-6)
    for bad, err in ((given[:-1], ValueError), (given.astype(np.float64), TypeError)):
        with pytest.raises(err, match="values"):
            df.update(values=bad)
        np.testing.assert_allclose(df.field(), want, rtol=0, atol=1e-6)
    assert df.update() > 0  # the map's own values again
    np.testing.assert_allclose(df.field(), _scipy_field(v >= 0.5, 0.05, None, False), rtol=0, atol=1e-6)


# ------------------------------------------------------------------ queries
def _slab_field(backend="numpy"):
    """Obstacles on the plane i = 0: the distance is x - x0 everywhere, linear."""
    g = gpumap.GridSpec((0.0, -0.2, -0.1), (0.6, 0.2, 0.15), 0.05)
    v = np.zeros(g.shape, np.float32)
    v[0] = 1.0
    return DistanceField(FakeMapper(v, g, backend=backend)), g


def test_interpolation_is_exact_on_linear_fields():
    g = gpumap.GridSpec((-0.2, 0.1, 0.3), (0.3, 0.45, 0.6), 0.05)
    a, b = 0.7, np.array([1.5, -2.0, 0.25])
    f = (a + g.all_centers() @ b).astype(np.float64)
    lo = np.asarray(g.min_corner_m) + g.voxel_size_m / 2
    hi = np.asarray(g.min_corner_m) + (np.asarray(g.shape) - 0.5) * g.voxel_size_m
    p = RNG.uniform(lo, hi, (200, 3))
    val, grad = trilinear(f, g, p, gradient=True)
    np.testing.assert_allclose(val, a + p @ b, rtol=0, atol=1e-9)
    np.testing.assert_allclose(grad, np.broadcast_to(b, grad.shape), rtol=0, atol=1e-9)
    df, gs = _slab_field()
    x0 = gs.min_corner_m[0] + gs.voxel_size_m / 2
    q = RNG.uniform(np.asarray(gs.min_corner_m) + 0.05, np.asarray(gs.min_corner_m) + [0.55, 0.35, 0.2],
                    (100, 3))
    np.testing.assert_allclose(df.distance_at(q), q[:, 0] - x0, rtol=0, atol=1e-6)
    np.testing.assert_allclose(df.gradient_at(q), np.tile([1.0, 0.0, 0.0], (100, 1)), rtol=0, atol=1e-4)


@pytest.mark.parametrize("signed", [False, True])
def test_gradient_is_the_finite_difference_of_distance(run, signed):
    m, imgs, poses = run
    m.reset()
    m.integrate_batch(imgs[:12], poses[:12])
    df = DistanceField(m, signed=signed)
    s = GRID.voxel_size_m
    # points well inside cells (away from the faces where the interpolant's slope jumps)
    cell = RNG.integers(1, np.asarray(GRID.shape) - 2, (300, 3))
    p = np.asarray(GRID.min_corner_m) + (cell + 0.5 + RNG.uniform(0.2, 0.8, (300, 3))) * s
    grad = df.gradient_at(p)
    h = 1e-5
    for a in range(3):
        e = np.zeros(3)
        e[a] = h
        fd = (df.distance_at(p + e) - df.distance_at(p - e)) / (2 * h)
        np.testing.assert_allclose(grad[:, a], fd, rtol=0, atol=1e-6)
    assert np.abs(grad).max() > 0.5  # not a flat field


def test_queries_refuse_bad_points_and_change_nothing():
    df, g = _slab_field()
    before = df.field()
    hi = np.asarray(g.min_corner_m) + np.asarray(g.shape) * g.voxel_size_m
    inside = np.asarray(g.min_corner_m) + 0.01
    bad = [
        (np.zeros((4, 2)), ValueError, r"shape \(N, 3\), but got \(4, 2\)"),
        (np.zeros(3), ValueError, r"shape \(N, 3\), but got \(3,\)"),
        (np.zeros((2, 3, 1)), ValueError, "shape"),
        (np.array([inside, [np.nan, 0, 0]]), ValueError, "finite.*row 1"),
        (np.array([[np.inf, 0, 0]]), ValueError, "finite"),
        (np.array([inside, hi]), ValueError, "inside the grid.*1 of 2 are outside.*row 1"),
        (np.array([[-5.0, 0, 0]]), ValueError, "outside"),
        (np.array([["a", "b", "c"]]), TypeError, "real numbers"),
        (np.array([[True, False, True]]), TypeError, "real numbers"),
        (np.array([[1j, 0, 0]]), TypeError, "real numbers"),
    ]
    for pts, err, msg in bad:
        for q in (df.distance_at, df.gradient_at):
            with pytest.raises(err, match=msg):
                q(pts)
    for center, half, err in (((0, 0), 0.1, ValueError), ((9.0, 0, 0), 0.1, ValueError),
                              ((0.2, 0, 0), -0.1, ValueError), ((0.2, 0, 0), (0.1, 0.1), ValueError),
                              ((0.2, 0, 0), np.nan, ValueError), ((0.2, 0, 0), "x", TypeError)):
        with pytest.raises(err):
            df.block(center, half)
    np.testing.assert_array_equal(df.field(), before)
    assert df.distance_at(np.zeros((0, 3))).shape == (0,)


def test_block_is_the_field_of_the_box_around_a_point():
    df, g = _slab_field()
    box, vals = df.block((0.3, 0.0, 0.0), (0.1, 0.07, 0.05))
    f = df.field()
    c = g.all_centers()
    inside = np.all(np.abs(c - [0.3, 0.0, 0.0]) <= [0.1 + 1e-9, 0.07 + 1e-9, 0.05 + 1e-9], axis=-1)
    np.testing.assert_array_equal(vals.ravel(), f[inside])
    assert box.shape == vals.shape and box.voxel_size_m == g.voxel_size_m
    np.testing.assert_allclose(box.all_centers().reshape(-1, 3), c[inside], atol=1e-9)
    # clipped at the grid's faces
    box2, vals2 = df.block((0.01, 0.0, 0.0), 1.0)
    assert vals2.shape == g.shape and box2.shape == g.shape


def test_named_backend_never_falls_back():
    df_args = (FakeMapper(np.zeros((2, 2, 2), np.float32), gpumap.GridSpec((0, 0, 0), (1, 1, 1), 0.5)),)
    with pytest.raises(ValueError, match="one of"):
        DistanceField(*df_args, backend="cuda")
    from gpumap.backends import available_backends

    for name in ("warp-cuda", "opencl-gpu"):
        if name not in available_backends([name]):
            with pytest.raises(BackendUnavailableError):
                DistanceField(*df_args, backend=name)
    with pytest.raises(TypeError, match="MinMaxMapper"):
        DistanceField(np.zeros(3))
    with pytest.raises(ValueError, match="max_distance_m > 0"):
        DistanceField(*df_args, max_distance_m=0.0)


# ------------------------------------------------------------------ ROS 2 messages
def _msg_points(msg) -> np.ndarray:
    from gpumap.ros.distance import DISTANCE_DTYPE

    assert [f.name for f in msg.fields] == ["x", "y", "z", "distance"] and msg.point_step == 16
    assert all(f.datatype == 7 and f.offset == 4 * i for i, f in enumerate(msg.fields))  # FLOAT32
    assert msg.row_step == 16 * msg.width and len(msg.data) == msg.row_step * msg.height
    return np.frombuffer(bytes(msg.data), DISTANCE_DTYPE).reshape(msg.height, msg.width)


def test_ros_slice_and_cloud_carry_the_field():
    pytest.importorskip("sensor_msgs.msg")
    from gpumap.ros.distance import cloud_message, slice_message

    df, g = _slab_field()
    f = df.field()
    s = g.voxel_size_m
    z = g.min_corner_m[2] + 2.3 * s  # inside layer 2
    msg = slice_message(f, g, z, "world", 1_500_000_123)
    assert (msg.header.frame_id, msg.header.stamp.sec, msg.header.stamp.nanosec) == ("world", 1, 500_000_123)
    rec = _msg_points(msg)
    assert rec.shape == (g.shape[1], g.shape[0]) and msg.is_dense
    np.testing.assert_array_equal(rec["distance"], f[:, :, 2].T)
    c = g.all_centers()[:, :, 2]  # (nx, ny, 3)
    for a, n in enumerate("xyz"):
        np.testing.assert_allclose(rec[n], c[..., a].T.astype(np.float32), atol=1e-6)
    with pytest.raises(ValueError, match="z_m within"):
        slice_message(f, g, g.min_corner_m[2] - 0.01, "world", 0)
    with pytest.raises(ValueError, match="shape"):
        slice_message(f[:-1], g, z, "world", 0)
    with pytest.raises(TypeError, match="stamp"):
        slice_message(f, g, z, "world", 1.5)

    cloud = cloud_message(f, g, 0.12, "world", msg.header.stamp)
    pts = _msg_points(cloud)[0]
    want = (f > 0) & (f <= np.float32(0.12))
    assert cloud.height == 1 and len(pts) == int(want.sum()) > 0
    np.testing.assert_array_equal(pts["distance"], f[want])
    np.testing.assert_allclose(np.stack([pts[n] for n in "xyz"], 1), g.all_centers()[want], atol=1e-6)
    both = _msg_points(cloud_message(f, g, 0.12, "world", 0, include_obstacles=True))[0]
    assert len(both) == len(pts) + int((f == 0).sum())
    with pytest.raises(ValueError, match="radius_m >= 0"):
        cloud_message(f, g, -1.0, "world", 0)


# ------------------------------------------------------------------ gpumap export --layer distance
def test_export_writes_the_distance_field_of_a_saved_map(run, tmp_path, capsys):
    """.npz: the whole field and its grid, SciPy's of the saved map (unknown as obstacles, as free, capped);
    .ply: the free voxels within --radius-m, centres and distances; a refined file: its safe layer; the
    wrong suffix and the distance flags without --layer distance are refused."""
    import json

    from gpumap.commands import main
    from gpumap.io import read_ply
    from gpumap.layers.refined_map import RefineResult

    m, imgs, poses = run
    m.reset()
    m.integrate_batch(imgs[:12], poses[:12])
    path = m.save(tmp_path / "map.npz")
    v = m.values()
    for flags, unknown, cap in (([], True, None), (["--unknown-free"], False, None),
                                (["--unknown-free", "--max-distance-m", "0.2"], False, 0.2)):
        out = tmp_path / "d.npz"
        assert main(["export", str(path), str(out), "--layer", "distance", *flags]) == 0
        info = json.loads(capsys.readouterr().out)
        obst = (v >= np.float32(0.3)) | (np.isnan(v) if unknown else False)
        assert info["unknown_is_obstacle"] == unknown and info["obstacle_voxels"] == int(obst.sum())
        with np.load(out) as z:
            want = _scipy_field(obst, 0.05, cap, False)
            np.testing.assert_allclose(z["distance_m"], want, rtol=0, atol=1e-5)
            assert z["distance_m"].dtype == np.float32
            np.testing.assert_array_equal(z["min_corner_m"], GRID.min_corner_m)
            assert float(z["voxel_size_m"]) == GRID.voxel_size_m and bool(z["unknown_is_obstacle"]) == unknown
            assert np.isnan(z["max_distance_m"]) if cap is None else float(z["max_distance_m"]) == cap
    ply = tmp_path / "d.ply"
    assert main(["export", str(path), str(ply), "--layer", "distance", "--radius-m", "0.15"]) == 0
    assert json.loads(capsys.readouterr().out)["voxels"] > 0
    want = _scipy_field((v >= np.float32(0.3)) | np.isnan(v), 0.05, None, False)
    band = (want > 0) & (want <= 0.15 + 1e-9)
    p = read_ply(ply)
    assert set(p) == {"x", "y", "z", "distance"} and len(p["x"]) == int(band.sum())
    np.testing.assert_allclose(np.stack([p[c] for c in "xyz"], 1), GRID.centers(np.argwhere(band)), atol=1e-6)
    np.testing.assert_allclose(p["distance"], want[band], rtol=0, atol=1e-5)
    # a refined file: the distance field of its safe layer, at its own threshold
    z0 = np.zeros(GRID.shape, np.float32)
    res = RefineResult(z0, z0, z0, z0 > 0, z0 > 0, 1.0, 0.0, threshold=0.5, rule="evidence", map_values=v,
                       spec=SPEC, grid=GRID)
    refined = res.save(tmp_path / "refined.npz")
    assert main(["export", str(refined), str(out), "--layer", "distance"]) == 0
    capsys.readouterr()
    with np.load(out) as z:
        obst = (v >= np.float32(0.5)) | np.isnan(v)
        np.testing.assert_allclose(z["distance_m"], _scipy_field(obst, 0.05, None, False), rtol=0, atol=1e-5)
    for argv, what in (([str(tmp_path / "d.bt"), "--layer", "distance"], ".ply or .npz"),
                       ([str(ply), "--radius-m", "0.2"], "--layer distance only"),
                       ([str(ply), "--layer", "distance", "--max-distance-m", "0.1"],
                        "at most --max-distance-m"),
                       ([str(out), "--layer", "distance", "--max-distance-m", "-1"], "a number > 0")):
        with pytest.raises(SystemExit) as e:
            main(["export", str(path), *argv])
        assert e.value.code == 2 and what in capsys.readouterr().err, argv
