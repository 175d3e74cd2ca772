"""MinMaxMapper on every backend, against independent float64 references.

The references here share no code with the kernels or with gpumap.reference: footprints
come from brute-force supersampling of each voxel cube, or from the bounding sphere in
float64, and scenes are rendered analytically.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import pose, rot_y, rot_z

import gpumap
from gpumap.backends import available_backends
from gpumap.core.params import MapperParams
from gpumap.geometry import ping_params

# A small sonar and grid keep brute force cheap but exercise every code path: uneven beams,
# voxels larger than bins and beams, voxels near the apex that span every beam.
RNG = np.random.default_rng(7)
_steps = RNG.uniform(0.8, 1.2, 47)
_b = np.concatenate([[0.0], np.cumsum(_steps)])
BEARINGS = np.deg2rad(-60 + 120 * (_b - _b[0]) / (_b[-1] - _b[0]))
SPEC = gpumap.SonarSpec(0.15, 1.5, 60, BEARINGS, np.deg2rad(20))
GRID = gpumap.GridSpec((-0.3, -1.2, -0.6), (1.6, 1.2, 0.6), 0.07)
T_A = pose(rot_z(0.1) @ rot_y(0.15), (0.02, 0.03, 0.05))
T_B = pose(rot_z(-0.05) @ rot_y(-0.2), (0.1, -0.04, -0.02))


def sphere_footprint(spec: gpumap.SonarSpec, p_S: np.ndarray, rho: float):
    """float64 cell rectangle touched by spheres of radius rho at p_S: (b0, b1, j0, j1), inclusive."""
    r = np.linalg.norm(p_S, axis=-1)
    h = np.hypot(p_S[..., 0], p_S[..., 1])
    az = np.arctan2(p_S[..., 1], p_S[..., 0])
    dr = spec.bin_size_m
    b0 = np.clip(np.floor((r - rho - spec.range_min_m) / dr), 0, spec.n_bins - 1).astype(int)
    b1 = np.clip(np.floor((r + rho - spec.range_min_m) / dr), 0, spec.n_bins - 1).astype(int)
    wide = h <= rho
    dth = np.arcsin(np.clip(rho / np.maximum(h, 1e-12), 0, 1))
    edges = spec.beam_edges_rad
    j0 = np.clip(np.searchsorted(edges, az - dth, side="right") - 1, 0, spec.n_beams - 1)
    j1 = np.clip(np.searchsorted(edges, az + dth, side="right") - 1, 0, spec.n_beams - 1)
    j0 = np.where(wide, 0, j0)
    j1 = np.where(wide, spec.n_beams - 1, j1)
    return b0, b1, j0, j1


def centres_S(T_W_S: np.ndarray) -> np.ndarray:
    c = GRID.all_centers().reshape(-1, 3)
    return (c - T_W_S[:3, 3]) @ T_W_S[:3, :3]


def integrate(backend, pings, method="gather", spec=SPEC, grid=GRID, rule=None):
    m = gpumap.MinMaxMapper(spec, grid, backend, MapperParams(method=method, rule=rule))
    for img, T in pings:
        m.integrate(img, T)
    return m


def test_auto_picks_first_available_backend():
    m = gpumap.MinMaxMapper(SPEC, GRID)
    assert m.backend == available_backends()[0]  # named as gpumap info names it


def test_observed_set_is_the_field_of_view(backend):
    """A voxel is observed iff its centre is in the FOV (float64 check, boundary slack 1e-5 m)."""
    img = np.zeros(SPEC.image_shape, np.float32)
    m = integrate(backend, [(img, T_A)])
    obs = m.observed().ravel()
    p = centres_S(T_A)
    inside = SPEC.in_fov(p)
    # voxels within 1e-5 m of the FOV boundary may go either way in float32
    shrink = p * (1 + 1e-5 / np.maximum(np.linalg.norm(p, axis=1, keepdims=True), 1e-9))
    grow = p * (1 - 1e-5 / np.maximum(np.linalg.norm(p, axis=1, keepdims=True), 1e-9))
    unsure = SPEC.in_fov(shrink) != SPEC.in_fov(grow)
    assert inside.sum() > 1000
    assert np.array_equal(obs[~unsure], inside[~unsure])
    np.testing.assert_array_equal(m.values().ravel()[obs], 0.0)


@pytest.mark.parametrize("seed", [5, 7, 15])  # seeds where a too-wide footprint near r_min shows
def test_conservative_and_tight_against_supersampled_cubes(backend, seed):
    """Ping value >= max over every cell hit by the cube inside the FOV, and <= sphere footprint + 1 cell."""
    img = (np.random.default_rng(seed).random(SPEC.image_shape) ** 12).astype(np.float32)  # spiky
    m = integrate(backend, [(img, T_A)])
    v = m.values().reshape(-1)
    obs = np.flatnonzero(np.isfinite(v))
    p = centres_S(T_A)[obs]
    s = GRID.voxel_size_m
    # brute force: 7^3 lattice over the cube (faces, edges and corners included) + 64 random points
    u = np.linspace(-0.5, 0.5, 7)
    lattice = np.stack(np.meshgrid(u, u, u, indexing="ij"), -1).reshape(-1, 3)
    offs = np.concatenate([lattice, RNG.uniform(-0.5, 0.5, (64, 3))]) * s
    R_SW = T_A[:3, :3].T  # cube axes are world axes
    brute = np.zeros(obs.size)
    for o in offs:
        q = p + o @ R_SW.T
        ok = SPEC.in_fov(q)
        pol = SPEC.to_polar(q)
        bi = SPEC.bin_index(pol[:, 0])
        bj = SPEC.beam_index(pol[:, 1])
        val = np.where(ok & (bi >= 0) & (bj >= 0), img[np.maximum(bi, 0), np.maximum(bj, 0)], 0.0)
        brute = np.maximum(brute, val)
    assert np.all(v[obs] >= brute.astype(np.float32)), "footprint misses cells the cube touches"
    # How far beyond the cube the footprint may reach is bounded below (the bounding sphere plus
    # one cell, float64): the fraction above the cube's own max is reported, not bounded.
    print(f"ping value above the cube's max: {(v[obs] > brute).mean():.1%} of {obs.size} voxels")
    b0, b1, j0, j1 = sphere_footprint(SPEC, p, math.sqrt(3) / 2 * s)
    b0, j0 = np.maximum(b0 - 1, 0), np.maximum(j0 - 1, 0)
    b1, j1 = np.minimum(b1 + 1, SPEC.n_bins - 1), np.minimum(j1 + 1, SPEC.n_beams - 1)
    upper = np.array([img[a : b + 1, c : d + 1].max() for a, b, c, d in zip(b0, b1, j0, j1, strict=True)])
    assert np.all(v[obs] <= upper), "footprint reaches beyond the bounding sphere plus one cell"


@pytest.mark.parametrize("shadow_m", [0.0, 0.1])
@pytest.mark.parametrize("cell", [(5, 3), (30, 24), (59, 47), (12, 40)])
def test_single_bright_cell_lights_exactly_the_touching_voxels(backend, cell, shadow_m):
    img = np.zeros(SPEC.image_shape, np.float32)
    img[cell] = 1.0
    m = gpumap.MinMaxMapper(SPEC, GRID, backend, MapperParams(shadow_m=shadow_m))
    m.integrate(img, T_B)
    v = m.values().reshape(-1)
    obs = np.isfinite(v)
    p = centres_S(T_B)
    rho = math.sqrt(3) / 2 * GRID.voxel_size_m
    # the footprint's height is fixed: floor((2 rho + shadow) / dr) + 2 bins from its first bin,
    # which lies rho + shadow in front of the centre
    win = math.floor((2 * rho + shadow_m) / SPEC.bin_size_m) + 2

    def touching(r_first_bin, r_beams):
        dr = SPEC.bin_size_m
        b0 = np.floor((np.linalg.norm(p, axis=1) - r_first_bin - shadow_m - SPEC.range_min_m) / dr)
        _, _, j0, j1 = sphere_footprint(SPEC, p, r_beams)
        return (b0 <= cell[0]) & (cell[0] <= b0 + win - 1) & (j0 <= cell[1]) & (cell[1] <= j1)

    lit = obs & (v == 1.0)
    must = obs & touching(rho, rho)
    # float32 rounding slack: the first bin may move by one either way at a boundary
    may = obs & (touching(rho + 1e-4, rho + 1e-4) | touching(rho - 1e-4, rho + 1e-4))
    assert must.sum() > 0
    assert np.all(lit[must]), "a voxel whose footprint touches the bright cell was not lit"
    assert not np.any(lit & ~may), "a voxel was lit whose footprint does not touch the bright cell"
    assert np.all(v[obs & ~lit] == 0.0)


@pytest.mark.parametrize("footprint_max", ["table", "loop"])
def test_backends_agree_with_numpy_reference(other_backend, footprint_max):
    """Bit for bit: the kernels do the reference's float32 arithmetic in the same order (no FMA
    contraction), so every observed set and every value is the same (the plain rule here; the
    visible rule's evidence is compared in test_visibility)."""
    imgs = [(RNG.random(SPEC.image_shape) ** 4).astype(np.float32) for _ in range(3)]
    poses = [T_A, T_B, pose(rot_z(0.3) @ rot_y(0.05), (-0.05, 0.1, 0.0))]
    for method in ("gather", "template"):
        for shadow_m in (0.0, 0.05):
            ref = gpumap.MinMaxMapper(
                SPEC, GRID, "numpy", MapperParams(method=method, rule="plain", shadow_m=shadow_m)
            )
            m = gpumap.MinMaxMapper(
                SPEC,
                GRID,
                other_backend,
                MapperParams(method=method, rule="plain", footprint_max=footprint_max, shadow_m=shadow_m),
            )
            for img, T in zip(imgs, poses, strict=True):
                ref.integrate(img, T)
                m.integrate(img, T)
            assert np.isfinite(ref.raw_values()).sum() > 1000
            np.testing.assert_array_equal(m.raw_values(), ref.raw_values(), err_msg=f"{method} {shadow_m}")


def test_template_method_matches_gather_where_it_lands_and_report_holes(backend):
    img = (RNG.random(SPEC.image_shape) ** 4).astype(np.float32)
    g = integrate(backend, [(img, T_A)], "gather").raw_values()
    t = integrate(backend, [(img, T_A)], "template").raw_values()
    tg, tt = np.isfinite(g), np.isfinite(t)
    assert not np.any(tt & ~tg), "the template observed a voxel whose centre is outside the FOV"
    np.testing.assert_array_equal(t[tt], g[tt])
    holes = 1 - tt.sum() / tg.sum()
    print(f"template hole fraction ({backend}, {GRID.voxel_size_m} m voxels): {holes:.3%}")
    assert 0 <= holes < 0.35


def _render_plane(spec, T_W_S, x_plane, n_sub=24):
    """Analytic image of the world plane x = x_plane: 1 in every cell a ray within the FOV hits."""
    img = np.zeros(spec.image_shape, np.float32)
    edges = spec.beam_edges_rad
    for j in range(spec.n_beams):
        th = (
            np.linspace(edges[j], edges[j + 1], n_sub, endpoint=False)
            + 0.5 * (edges[j + 1] - edges[j]) / n_sub
        )
        ph = np.linspace(-spec.vfov_rad / 2, spec.vfov_rad / 2, 8 * n_sub)
        TH, PH = np.meshgrid(th, ph)
        d_S = np.stack([np.cos(PH) * np.cos(TH), np.cos(PH) * np.sin(TH), np.sin(PH)], -1).reshape(-1, 3)
        d_W = d_S @ T_W_S[:3, :3].T
        with np.errstate(divide="ignore", invalid="ignore"):
            r = (x_plane - T_W_S[0, 3]) / d_W[:, 0]
        bi = spec.bin_index(np.where(r > 0, r, -1))
        img[bi[bi >= 0], j] = 1.0
    return img


def test_plane_of_returns_is_kept_and_space_in_front_is_carved_over_two_views(backend):
    D = 1.0
    views = [pose(rot_y(0.0), (0, 0, 0)), pose(rot_y(0.25), (0.0, 0.0, 0.15))]
    pings = [(_render_plane(SPEC, T, D), T) for T in views]
    m = integrate(backend, pings, rule="visible")  # one very dark clear view carves
    v = m.values()
    c = GRID.all_centers()
    s = GRID.voxel_size_m
    obs = np.isfinite(v)
    on_plane = obs & (np.abs(c[..., 0] - D) <= s / 2)
    assert on_plane.sum() > 50
    assert np.all(v[on_plane] == 1.0), "a voxel on the plane was called free (false negative)"
    # In front of the plane, after both views: free exactly where a float64 footprint says a view
    # was dark (no plane cell in the footprint) and clear (none nearer in its beams), a voxel
    # either way within 1e-4 m of a footprint edge aside.
    front = obs & (c[..., 0] < D - (math.sqrt(3) / 2 * s + SPEC.bin_size_m)) & (c[..., 0] > 0.3)
    front = front.ravel()
    carved_by = []
    unsure = np.zeros(front.shape, bool)
    for img, T in pings:
        p = centres_S(T)[front]
        seen = np.zeros(front.shape, bool)
        seen[front] = SPEC.in_fov(p)
        ways = []
        for eps in (-1e-4, 1e-4):
            dark_clear = np.zeros(front.shape, bool)
            dark_clear[front] = _dark_and_clear(img, p, math.sqrt(3) / 2 * s + eps) & seen[front]
            ways.append(dark_clear)
        unsure |= ways[0] != ways[1]
        carved_by.append(ways[0])
    sure = front & ~unsure
    want_one, want_two = carved_by[0][sure], carved_by[0][sure] | carved_by[1][sure]
    single = integrate(backend, pings[:1], rule="visible").values().ravel()[sure]
    carved_one, carved_two = single == 0, v.ravel()[sure] == 0
    print(f"carved in front of the plane: {carved_one.mean():.1%} after one view, {carved_two.mean():.1%} "
          f"after two ({sure.sum()} voxels, {(front & unsure).sum()} on a footprint edge left out)")
    assert sure.sum() > 100 and (front & unsure).sum() < 0.05 * front.sum()
    np.testing.assert_array_equal(carved_one, want_one)
    np.testing.assert_array_equal(carved_two, want_two)
    assert carved_two.sum() > carved_one.sum()  # the second view removes elevation "stretch"


def _dark_and_clear(img, p_S, rho):
    """float64: the footprint of spheres of radius rho at p_S (window of the mapper's height from
    the first bin, the sphere's beams) holds no lit cell, and no lit cell lies nearer in its beams."""
    win = math.floor(2 * rho / SPEC.bin_size_m) + 2
    r = np.linalg.norm(p_S, axis=1)
    b0 = np.floor((r - rho - SPEC.range_min_m) / SPEC.bin_size_m).astype(int)
    _, _, j0, j1 = sphere_footprint(SPEC, p_S, rho)
    out = np.empty(len(p_S), bool)
    for n, (a, c, d) in enumerate(zip(b0, j0, j1, strict=True)):
        out[n] = not img[: max(a + win, 0), c : d + 1].any()
    return out


def test_shadow_keeps_the_far_side_of_a_thin_return(backend):
    """A bright cell at range r keeps voxels up to shadow_m behind it occupied; none in front."""
    img = np.zeros(SPEC.image_shape, np.float32)
    img[20, :] = 1.0  # a shell of returns at bin 20 in every beam
    r_ret = SPEC.range_min_m + 20.5 * SPEC.bin_size_m
    p = centres_S(T_A)
    r = np.linalg.norm(p, axis=1)
    rho = math.sqrt(3) / 2 * GRID.voxel_size_m
    dr = SPEC.bin_size_m
    for shadow in (0.0, 0.2):
        m = gpumap.MinMaxMapper(SPEC, GRID, backend, MapperParams(shadow_m=shadow))
        m.integrate(img, T_A)
        v = m.values().ravel()
        obs = np.isfinite(v)
        # margins: the return's bin is dr deep, and the window may hold one bin more
        behind = obs & (r > r_ret + rho + dr) & (r < r_ret + shadow - dr)
        ahead = obs & (r < r_ret - rho - 2 * dr)
        far = obs & (r > r_ret + shadow + rho + 2 * dr)
        assert np.all(v[ahead] == 0) and np.all(v[far] == 0)
        if shadow:
            assert behind.sum() > 100 and np.all(v[behind] == 1.0)


def test_uint8_image_is_scaled(backend):
    img8 = RNG.integers(0, 256, SPEC.image_shape, dtype=np.uint8)
    a = integrate(backend, [(img8, T_A)]).raw_values()
    b = integrate(backend, [(img8.astype(np.float32) * np.float32(1 / 255), T_A)]).raw_values()
    np.testing.assert_array_equal(a, b)


def test_min_over_pings_is_order_independent(backend):
    imgs = [(RNG.random(SPEC.image_shape) ** 3).astype(np.float32) for _ in range(3)]
    poses = [T_A, T_B, T_A]
    a = integrate(backend, zip(imgs, poses, strict=True)).raw_values()
    b = integrate(backend, zip(imgs[::-1], poses[::-1], strict=True)).raw_values()
    np.testing.assert_array_equal(a, b)
    # The min over pings is the plain rule's map, and the visible rule's min_all; the visible
    # rule's values are not (a voxel bright in one view and clear-dark in one other keeps its
    # bright value), so comparing them with single-ping maps held only for lucky images.
    for rule in ("plain", "visible"):
        def run(pings, rule=rule):
            m = gpumap.MinMaxMapper(SPEC, GRID, backend, MapperParams(rule=rule))
            for img, T in pings:
                m.integrate(img, T)
            return m.raw_values() if rule == "plain" else m.evidence()["min_all"]

        singles = [run([(i, T)]) for i, T in zip(imgs, poses, strict=True)]
        np.testing.assert_array_equal(run(zip(imgs, poses, strict=True)), np.minimum.reduce(singles))


# ------------------------------------------------------------------ bad input
def _bad_images():
    nan = np.zeros(SPEC.image_shape, np.float32)
    nan[3, 4] = np.nan
    inf = np.zeros(SPEC.image_shape, np.float32)
    inf[0, 0] = np.inf
    return [
        (np.zeros(SPEC.image_shape[::-1], np.float32), ValueError, "shape"),
        (np.zeros(SPEC.image_shape, np.int32), TypeError, "dtype"),
        (nan, ValueError, "finite"),
        (inf, ValueError, "finite"),
        (np.full(SPEC.image_shape, 1.5, np.float32), ValueError, r"\[0, 1\]"),
        ([[0.0]], TypeError, "numpy array"),
    ]


def _bad_poses():
    nan = T_A.copy()
    nan[0, 3] = np.nan
    skew = T_A.copy()
    skew[:3, :3] *= 1.01
    left = T_A.copy()
    left[:3, 0] *= -1
    row = T_A.copy()
    row[3, 0] = 0.5
    return [
        (nan, "finite"),
        (skew, "orthonormal"),
        (left, "right-handed"),
        (row, "last row"),
        (np.eye(3), r"\(4, 4\)"),
    ]


def test_bad_input_raises_and_leaves_map_untouched(backend):
    m = integrate(backend, [((RNG.random(SPEC.image_shape) ** 2).astype(np.float32), T_A)])
    before = m.raw_values()
    good = np.zeros(SPEC.image_shape, np.float32)
    for img, err, msg in _bad_images():
        with pytest.raises(err, match=msg):
            m.integrate(img, T_B)
    for T, msg in _bad_poses():
        with pytest.raises(ValueError, match=msg):
            m.integrate(good, T)
    np.testing.assert_array_equal(m.raw_values(), before)
    assert m.n_integrated == 1


def test_bad_specs_are_refused_with_the_reason():
    with pytest.raises(ValueError, match="strictly ascending"):
        gpumap.SonarSpec(0.1, 2.0, 10, np.array([0.1, 0.0, 0.2]), 0.3)
    with pytest.raises(ValueError, match="strictly ascending"):
        gpumap.SonarSpec(0.1, 2.0, 10, np.array([0.0, 0.1, 0.1]), 0.3)
    with pytest.raises(ValueError, match="range_min_m < range_max_m"):
        gpumap.SonarSpec(2.0, 1.0, 10, np.array([0.0, 0.1]), 0.3)
    with pytest.raises(ValueError, match="non-empty box"):
        gpumap.GridSpec((0, 0, 0), (1, 0, 1), 0.1)
    with pytest.raises(ValueError, match="non-empty box"):
        gpumap.GridSpec((1, 0, 0), (0, 1, 1), 0.1)
    with pytest.raises(ValueError, match="voxel_size_m > 0"):
        gpumap.GridSpec((0, 0, 0), (1, 1, 1), 0.0)
    # 1e12 voxels: 16 bytes each under the default (evidence) rule, 4 under the plain one
    with pytest.raises(ValueError, match=r"14901\.2 GiB with the default evidence rule's 16 bytes per voxel, "
                                         r"3725\.3 GiB with the plain rule's 4"):
        gpumap.GridSpec((0, 0, 0), (100, 100, 100), 0.01)
    with pytest.raises(ValueError, match="backend"):
        gpumap.MinMaxMapper(SPEC, GRID, backend="cuda")
    with pytest.raises(ValueError, match="method"):
        gpumap.MinMaxMapper(SPEC, GRID, "auto", MapperParams(method="fast"))


def test_grid_too_big_for_memory_says_how_much_it_needs(monkeypatch):
    from gpumap import memory

    grid = gpumap.GridSpec((0, 0, 0), (10, 10, 10), 0.01)  # 1e9 voxels = 3.73 GiB of float32
    assert memory.free_memory_bytes("numpy") > 0  # this machine's own figure is readable
    monkeypatch.setattr(memory, "free_memory_bytes", lambda name, device_index=None: 2**30)  # 1 GiB free
    with pytest.raises(ValueError, match=r"need 3\.73 GiB and numpy has 1\.00 GiB free"):
        gpumap.MinMaxMapper(SPEC, grid, "numpy", MapperParams(rule="plain"))
    # the evidence rule keeps 12 more bytes per voxel (bright float32, count uint64): 16 / 4 as much
    with pytest.raises(ValueError, match=r"need 14\.90 GiB and numpy has 1\.00 GiB free"):
        gpumap.MinMaxMapper(SPEC, grid, backend="numpy")
    with pytest.raises(gpumap.BackendUnavailableError, match="fits in memory"):
        gpumap.MinMaxMapper(SPEC, grid, backend="auto")  # auto tries each, then says why none ran


def test_opencl_refuses_a_grid_beyond_its_largest_buffer():
    if "opencl-cpu" not in available_backends():
        pytest.skip("no OpenCL CPU device here")
    from gpumap.backends import opencl_devices

    limit = opencl_devices("cpu")[0].max_mem_alloc_size
    m = (limit // 4 // 64 // 8 + 1) * 8  # one block column more than the largest buffer holds
    if m * 64 > 2**31 - 1:
        pytest.skip("this device's largest buffer holds more than a map may address")
    grid = gpumap.GridSpec((0, 0, 0), (m, 8, 8), 1.0)
    with pytest.raises(ValueError, match=r"fits in one OpenCL buffer, but .* GiB"):
        gpumap.MinMaxMapper(SPEC, grid, "opencl-cpu", MapperParams(rule="plain"))


def test_named_backend_never_falls_back(monkeypatch):
    """With Warp and OpenCL made unavailable (on any machine, GPUs or not), each backend named
    raises with its reason, while ``auto`` falls back to numpy."""
    from gpumap.backends import opencl_backend, warp_backend

    def no_warp():
        raise gpumap.BackendUnavailableError("warp-lang cannot be imported: test")

    monkeypatch.setattr(warp_backend, "_warp", no_warp)
    monkeypatch.setattr(opencl_backend, "opencl_devices", lambda kind: [])
    for name in ("warp-cuda", "warp-cpu", "opencl", "opencl-gpu", "opencl-cpu"):
        why = "warp-lang cannot" if "warp" in name else "(?i)opencl"
        with pytest.raises(gpumap.BackendUnavailableError, match=why):
            gpumap.MinMaxMapper(SPEC, GRID, backend=name)
    assert gpumap.MinMaxMapper(SPEC, GRID, backend="auto").backend == "numpy"


# ------------------------------------------------------------------ persistence
def test_save_load_roundtrip_is_lossless(backend, tmp_path):
    m = integrate(backend, [((RNG.random(SPEC.image_shape) ** 2).astype(np.float32), T_A)], "template")
    path = m.save(tmp_path / "map.npz")
    m2 = gpumap.MinMaxMapper.load(path, backend=backend)
    np.testing.assert_array_equal(m2.raw_values(), m.raw_values())
    assert m2.spec == SPEC and m2.grid == GRID and m2.method == "template" and m2.n_integrated == 1
    assert np.isnan(m2.values()).any()


def test_save_is_atomic(tmp_path, monkeypatch):
    m = integrate("numpy", [(np.zeros(SPEC.image_shape, np.float32), T_A)])
    path = m.save(tmp_path / "map.npz")
    before = path.read_bytes()
    m.integrate(np.ones(SPEC.image_shape, np.float32), T_B)

    def boom(*a, **k):
        raise OSError("disk full")

    monkeypatch.setattr(np, "savez_compressed", boom)
    with pytest.raises(OSError, match="disk full"):
        m.save(path)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["map.npz"]


def test_load_refuses_other_versions(tmp_path):
    import json

    path = tmp_path / "m.npz"
    meta = {"format": "gpumap.MinMaxMapper", "version": 99}
    np.savez(path, values=np.zeros(3, np.float32), meta=np.array(json.dumps(meta)))
    with pytest.raises(ValueError, match="version 1"):
        gpumap.MinMaxMapper.load(path)


def test_occupied_points_are_world_centres():
    m = integrate("numpy", [(np.ones(SPEC.image_shape, np.float32), T_A)])
    pts = m.occupied_points(0.5)
    assert pts.shape == (int(m.observed().sum()), 3)
    assert np.all(SPEC.in_fov((pts - T_A[:3, 3]) @ T_A[:3, :3]))


def test_gpu_table_builders_match_cpu_ones():
    """The per-cell (GPU) and per-row (CPU) max-table builders build the same table, on the CPU."""
    from gpumap.backends import table_size

    img = (RNG.random(SPEC.image_shape) ** 3).astype(np.float32)
    have = available_backends()
    m = gpumap.MinMaxMapper(
        SPEC, GRID, "numpy", MapperParams(rule="plain")
    )  # the backends below hold no evidence
    params = m.integrator.params
    n_cols = ping_params(params, T_A, m.integrator.fov_pts_S, GRID)
    n_levels = int(params["n_levels"])
    plane = SPEC.n_bins * SPEC.n_beams
    tables = {}
    if "warp-cpu" in have:
        import warp as wp

        from gpumap.backends import _warp, _warp_params

        _, k = _warp()
        P = _warp_params(k, params)
        im = wp.array(img, dtype=float, device="cpu")
        for name, (win, lev, dims) in {
            "rows": (k.build_bin_window, k.build_beam_levels, (SPEC.n_beams, SPEC.n_bins)),
            "cells": (
                k.build_bin_window_cells,
                k.build_beam_levels_cells,
                (SPEC.image_shape, SPEC.image_shape),
            ),
        }.items():
            t = wp.zeros(table_size(SPEC), dtype=float, device="cpu")
            wp.launch(win, dim=dims[0], inputs=[P, im, t], device="cpu")
            wp.launch(lev, dim=dims[1], inputs=[P, t], device="cpu")
            tables[f"warp-{name}"] = t.numpy()[: n_levels * plane]
    if "opencl-cpu" in have:
        from gpumap.backends import OpenCLBackend

        for gpu_style in (False, True):
            be = OpenCLBackend(SPEC, None, use_table=True, kind="cpu")
            be.is_gpu = gpu_style  # pick the builder, not the device
            prg = be.k_gather.program
            names = ("build_bin_window_cells", "build_beam_levels_cells") if gpu_style else (
                "build_bin_window", "build_beam_levels")
            be.k_window, be.k_levels = (be.cl.Kernel(prg, n) for n in names)
            be.integrate(params, img, "gather", n_cols)
            out = np.empty(table_size(SPEC), np.float32)
            be.cl.enqueue_copy(be.queue, out, be.table, is_blocking=True)
            tables[f"opencl-{'cells' if gpu_style else 'rows'}"] = out[: n_levels * plane]
    if not tables:
        pytest.skip("no Warp or OpenCL CPU backend here")
    # independent reference: max over bins [i, i + win - 1] and beams [j, j + 2^k - 1], clipped
    win = int(params["win"])
    ref = np.empty((n_levels, *SPEC.image_shape), np.float32)
    for i in range(SPEC.n_bins):
        for j in range(SPEC.n_beams):
            for lv in range(n_levels):
                ref[lv, i, j] = img[i : i + win, j : j + (1 << lv)].max()
    for name, t in tables.items():
        np.testing.assert_array_equal(t.reshape(ref.shape), ref, err_msg=name)


@pytest.mark.parametrize("name", ["warp-cpu", "opencl-cpu"])
@pytest.mark.parametrize("chunk", [1, 3, 16])
def test_gather_in_short_column_chunks_matches_reference(name, chunk):
    """GPUs split columns into short chunks (one per thread); run that split here on a CPU."""
    if name not in available_backends():
        pytest.skip(f"{name} is not available here")
    imgs = [(RNG.random(SPEC.image_shape) ** 4).astype(np.float32) for _ in range(2)]
    ref = integrate("numpy", zip(imgs, [T_A, T_B], strict=True)).raw_values()
    m = gpumap.MinMaxMapper(SPEC, GRID, backend=name)
    m.storage.backend.chunk = chunk
    for img, T in zip(imgs, [T_A, T_B], strict=True):
        m.integrate(img, T)
    np.testing.assert_array_equal(m.raw_values(), ref)


def test_float64_and_negative_zero_images_are_accepted_as_float32():
    img = (RNG.random(SPEC.image_shape) ** 3).astype(np.float32)
    a = integrate("numpy", [(img, T_A)]).raw_values()
    b = integrate("numpy", [(img.astype(np.float64), T_A)]).raw_values()
    neg0 = img.copy()
    neg0[img == img.min()] = -0.0
    c = integrate("numpy", [(neg0, T_A)]).raw_values()
    np.testing.assert_array_equal(a, b)
    assert not np.signbit(c[np.isfinite(c)]).any()
    strided = np.zeros((SPEC.n_bins, 2 * SPEC.n_beams), np.float32)[:, ::2]
    strided[...] = img
    np.testing.assert_array_equal(integrate("numpy", [(strided, T_A)]).raw_values(), a)


def test_load_refuses_a_truncated_file(tmp_path):
    m = integrate("numpy", [(np.zeros(SPEC.image_shape, np.float32), T_A)])
    path = m.save(tmp_path / "map.npz")
    data = path.read_bytes()
    cut = tmp_path / "cut.npz"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match="cannot be read"):
        gpumap.MinMaxMapper.load(cut)
