"""The visibility-aware rule on every backend: analytic cases, order, and a brute-force clear test.

References here share no code with the kernels or gpumap.reference: clear views are found in
float64 from the bounding sphere, scenes are drawn by hand or rendered by the simulator.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import pose, rot_y, rot_z
from test_mapper import GRID, SPEC, T_A, T_B, centres_S, sphere_footprint

import gpumap
from gpumap.core.params import MapperParams

RNG = np.random.default_rng(11)
THR = 0.1


def _mapper(backend, rule="visible", spec=SPEC, grid=GRID):
    return gpumap.MinMaxMapper(spec, grid, backend, MapperParams(rule=rule, threshold=THR))


def _run(backend, pings, rule="visible"):
    m = _mapper(backend, rule)
    for img, T in pings:
        m.integrate(img, T)
    return m


def _random_pings(n, seed):
    """Pings whose views reach every branch of the visible rule (counted by _fold_views).

    Per beam: water up to a first return (none in some beams), then one to three return cells
    (a third of them exactly at the threshold), then shadow and now and then a further return.
    Water and shadow are dark, per beam either very dark (below threshold / 2) or speckle
    between threshold / 2 and the threshold; a few cells lie exactly at threshold / 2.
    No cell at or above the threshold lies in the last ``win`` bins (see _fold_views).
    """
    rng = np.random.default_rng(seed)
    out = []
    nb, nj = SPEC.image_shape
    thr, half = np.float32(THR), np.float32(THR) * np.float32(0.5)
    last = nb - _win()  # returns only in bins [0, last)
    for _ in range(n):
        very_dark = rng.random(nj) < 0.6
        u = rng.random((nb, nj))
        img = np.where(very_dark[None, :], half * u, half + (thr - half) * u)
        img[rng.random((nb, nj)) < 0.05] = half
        img = img.astype(np.float32)
        for j in range(nj):
            f = int(rng.integers(3, 2 * last))
            while f < last:
                length = int(rng.integers(1, 4))
                value = thr if rng.random() < 1 / 3 else np.float32(rng.uniform(THR, 1.0))
                img[f : min(f + length, last), j] = value
                f += length + int(rng.integers(4, last))
        T = pose(rot_z(rng.uniform(-0.3, 0.3)) @ rot_y(rng.uniform(-0.2, 0.2)), rng.uniform(-0.1, 0.1, 3))
        out.append((img, T))
    return out


def _win() -> int:
    return int(_mapper("numpy")._params["win"])


def _fold_views(pings):
    """The visible rule's evidence from its definition, view by view, and how often each branch ran.

    Independent of the rule's code: a view's value v is the single-ping map of the plain rule
    (the footprint max, itself checked against brute force in test_mapper). Its clearness comes
    from the same plain footprint max over ``X``, the image's running max along range shifted
    down by ``win`` bins: over the footprint's rows ``[b0, b0 + win - 1]`` that max is ``X``'s
    last row, i.e. the image's max over bins ``[0, b0)`` of the footprint's beams, exactly the
    cells that block the view (the window is never clipped at the last bin for a bright cell:
    _random_pings keeps the last ``win`` bins dark). Shifting by ``win + 1`` finds the views
    blocked only by a return in bin ``b0 - 1``, the edge of the blocking test.
    """
    thr, half = np.float32(THR), np.float32(THR) * np.float32(0.5)
    win = _win()
    n = GRID.n_voxels
    min_all = np.full(n, np.inf, np.float32)
    bright = np.full(n, np.inf, np.float32)
    count = np.zeros(n, np.int64)
    dark_views = np.zeros(n, np.int64)  # the evidence rule's counts: clear dark views, bright views
    bright_views = np.zeros(n, np.int64)
    branches = ("bright", "at_threshold", "clear_very_dark", "at_half", "clear_dark", "blocked_dark",
                "blocked_at_b0_minus_1")
    hits = dict.fromkeys(branches, 0)

    def plain_value(img, T):
        m = gpumap.MinMaxMapper(SPEC, GRID, "numpy", MapperParams(rule="plain", threshold=THR))
        m.integrate(img, T)
        return m.raw_values().ravel()

    def shifted_running_max(img, k):
        x = np.zeros_like(img)
        x[k:] = np.maximum.accumulate(img, axis=0)[:-k]
        return x

    for img, T in pings:
        v = plain_value(img, T)
        seen = np.isfinite(v)
        clear = plain_value(shifted_running_max(img, win), T) < thr
        clear_but_last = plain_value(shifted_running_max(img, win + 1), T) < thr
        lit = seen & (v >= thr)
        dark = seen & ~lit
        min_all[seen] = np.minimum(min_all[seen], v[seen])
        bright[lit] = np.minimum(bright[lit], v[lit])
        count[dark & clear] += np.where(v[dark & clear] < half, 2, 1)
        dark_views += dark & clear
        bright_views += lit
        hits["bright"] += lit.sum()
        hits["at_threshold"] += (seen & (v == thr)).sum()
        hits["clear_very_dark"] += (dark & clear & (v < half)).sum()
        hits["at_half"] += (dark & clear & (v == half)).sum()
        hits["clear_dark"] += (dark & clear & (v >= half)).sum()
        hits["blocked_dark"] += (dark & ~clear).sum()
        hits["blocked_at_b0_minus_1"] += (dark & ~clear & clear_but_last).sum()
    ev = {"min_all": min_all, "bright": bright, "count": np.minimum(count, 255).astype(np.uint8),
          "dark_views": dark_views, "bright_views": bright_views}
    return {k: a.reshape(GRID.shape) for k, a in ev.items()}, hits


@pytest.fixture(scope="module")
def branch_pings():
    pings = _random_pings(8, 3)
    return pings, *_fold_views(pings)


def test_random_views_reach_every_branch_of_the_rule(branch_pings):
    """The inputs of the comparisons below exercise each branch many times (counts printed)."""
    _, _, hits = branch_pings
    print("views per branch:", hits)
    assert min(hits.values()) >= 50, hits


def test_rule_matches_its_definition_view_by_view(backend, branch_pings):
    """Every backend's evidence equals the rule folded view by view (_fold_views), exactly."""
    pings, want, _ = branch_pings
    got = _run(backend, pings).evidence()
    for k in ("min_all", "bright", "count"):
        np.testing.assert_array_equal(got[k], want[k], err_msg=k)
    assert want["count"].max() >= 4 and np.isfinite(want["bright"]).sum() > 100


def test_backends_agree_bitwise_with_the_reference(other_backend, branch_pings):
    pings = branch_pings[0]
    ref, got = _run("numpy", pings).evidence(), _run(other_backend, pings).evidence()
    for k in ("min_all", "bright", "count"):
        np.testing.assert_array_equal(got[k], ref[k], err_msg=k)


def test_count_saturates_at_255(backend):
    """130 very dark clear views of a voxel seen bright: the count stops at 255 (uint8), not wraps."""
    spec = gpumap.SonarSpec.uniform(hfov_deg=20, vfov_deg=10, n_beams=8, n_bins=20, range_min_m=0.1,
                                    range_max_m=1.0)
    grid = gpumap.GridSpec((0.3, -0.1, -0.05), (0.7, 0.1, 0.05), 0.05)
    m = gpumap.MinMaxMapper(spec, grid, backend, MapperParams(threshold=THR, rule="visible"))
    m.integrate(np.full(spec.image_shape, 0.5, np.float32), np.eye(4))
    dark = np.zeros(spec.image_shape, np.float32)
    for _ in range(130):
        m.integrate(dark, np.eye(4))
    count = m.evidence()["count"]
    seen = np.isfinite(m.evidence()["bright"])
    assert seen.sum() > 10
    np.testing.assert_array_equal(count[seen], 255)


def test_order_of_pings_does_not_change_the_map(backend):
    pings = _random_pings(6, 4)
    a = _run(backend, pings)
    b = _run(backend, [pings[i] for i in (3, 0, 5, 1, 4, 2)])
    for k in ("min_all", "bright", "count"):
        np.testing.assert_array_equal(a.evidence()[k], b.evidence()[k], err_msg=k)
    np.testing.assert_array_equal(a.raw_values(), b.raw_values())


@pytest.mark.parametrize(("rule", "step"), [("visible", 2), ("evidence", 1)])
def test_clear_views_match_a_float64_brute_force(backend, rule, step):
    """After one dark ping with a few bright cells, a voxel's count is ``step`` (a very dark view:
    2 for the visible rule, 1 for the evidence rule) exactly where no bright cell lies nearer than
    its footprint in its beams (float64 sphere; boundary cases skipped), else 0."""
    img = np.zeros(SPEC.image_shape, np.float32)
    cells = [(10, 5), (25, 20), (40, 33), (3, 44)]
    for c in cells:
        img[c] = 1.0
    m = _run(backend, [(img, T_B)], rule)
    ev = m.evidence()
    count = ev["count"].ravel()
    obs = np.isfinite(ev["min_all"].ravel())
    dark = obs & ~np.isfinite(ev["bright"].ravel())
    p = centres_S(T_B)
    rho = math.sqrt(3) / 2 * GRID.voxel_size_m
    clear, unsure = np.ones(len(p), bool), np.zeros(len(p), bool)
    for eps in (-1e-4, 1e-4):
        b0, _, j0, j1 = sphere_footprint(SPEC, p, rho + eps)
        blocked = np.zeros(len(p), bool)
        for b, j in cells:
            blocked |= (j0 <= j) & (j <= j1) & (b < b0)
        if eps < 0:
            clear_lo = ~blocked
        else:
            unsure = clear_lo != ~blocked
            clear = ~blocked
    sure = dark & ~unsure
    assert sure.sum() > 1000 and (~clear[sure]).sum() > 100 and clear[sure].sum() > 100
    np.testing.assert_array_equal(count[sure], np.where(clear[sure], step, 0))


def _one_voxel_pings(bright_views: int, dark_value: float, dark_views: int = 1):
    """Pings from one pose: a bright band across the fan at 0.8 m, then dark pings that hold
    ``dark_value`` at that band (nothing in front of it). Returns pings and the band's voxels."""
    bins = SPEC.bin_index(np.array([0.80, 0.86]))
    bright = np.zeros(SPEC.image_shape, np.float32)
    bright[bins[0] : bins[1] + 1] = 0.7
    dark = np.zeros(SPEC.image_shape, np.float32)
    dark[bins[0] : bins[1] + 1] = dark_value
    pings = [(bright, T_A)] * bright_views + [(dark, T_A)] * dark_views
    r = np.linalg.norm(centres_S(T_A), axis=1)
    band = (r > 0.75) & (r < 0.85)  # footprints (radius 6 cm) that reach the band
    return pings, band


def test_surface_bright_in_nine_views_survives_one_speckle_dark_view(backend):
    pings, band = _one_voxel_pings(9, 0.08)  # below the threshold, above threshold / 2
    vis = _run(backend, pings).values().ravel()
    plain = _run(backend, pings, "plain").values().ravel()
    seen = band & np.isfinite(vis)
    assert seen.sum() > 20
    assert np.all(vis[seen] >= THR), "one speckle-dark view erased a surface seen bright nine times"
    assert np.all(plain[seen] < THR)  # the paper's rule does erase it: the test can fail
    # two such views, or one far darker, do carve
    pings2, _ = _one_voxel_pings(9, 0.08, dark_views=2)
    m2 = _run(backend, pings2)
    assert np.all(m2.values().ravel()[seen] < THR)
    m2.carve_views = 3  # a read-time knob: more evidence needed, the surface is back
    assert np.all(m2.values().ravel()[seen] >= THR)
    pings3, _ = _one_voxel_pings(9, 0.01)
    assert np.all(_run(backend, pings3).values().ravel()[seen] < THR)


@pytest.fixture(scope="module")
def box_pings():
    """A box seen from the front (three poses) and from behind (one), rendered without noise."""
    from gpumap.sim.scenes import box_scene, pose_from_xyz_ypr
    from gpumap.sim.sonar import SonarSimulator

    spec = gpumap.SonarSpec.uniform(hfov_deg=90, vfov_deg=20, n_beams=128, n_bins=150,
                                    range_min_m=0.1, range_max_m=2.0)
    box = ((0.0, 0.0, 0.0), (0.3, 0.3, 0.3))
    front = [pose_from_xyz_ypr(np.array([-1.0, y, 0.05]), 0.0, math.radians(5)) for y in (-0.1, 0.0, 0.1)]
    back = [pose_from_xyz_ypr(np.array([1.0, 0.0, 0.05]), math.pi, math.radians(5))]
    scene = box_scene([box], np.array(front + back), spec=spec, voxel_size_m=0.05)
    with SonarSimulator(scene, seed=0, noise_floor=0.0, looks=1e9) as sim:
        pings = [(sim.ping(T, i).image, T) for i, T in enumerate(scene.T_W_S)]
    return scene, pings


def test_back_of_a_box_seen_from_behind_survives_views_from_the_front(backend, box_pings):
    scene, pings = box_pings
    g = scene.grid
    c = g.all_centers().reshape(-1, 3)
    back_face = (np.abs(c[:, 0] - 0.15) < g.voxel_size_m / 2) & np.all(np.abs(c[:, 1:]) < 0.1, axis=1)
    order = [pings[3], *pings[:3]]  # seen from behind first, then carved from the front?
    m = gpumap.MinMaxMapper(scene.sonar_spec, g, backend, MapperParams(threshold=THR))
    p = gpumap.MinMaxMapper(scene.sonar_spec, g, backend, MapperParams(rule="plain", threshold=THR))
    for img, T in order:
        m.integrate(img, T)
        p.integrate(img, T)
    vis, plain = m.values().ravel(), p.values().ravel()
    assert back_face.sum() >= 9 and np.all(np.isfinite(vis[back_face]))
    assert np.all(vis[back_face] >= THR), "views from the front carved the back face"
    assert np.mean(plain[back_face] < THR) > 0.5  # the plain rule carves it


def test_free_water_in_front_of_a_surface_is_carved_within_two_views(backend, box_pings):
    scene, pings = box_pings
    g = scene.grid
    m = gpumap.MinMaxMapper(scene.sonar_spec, g, backend, MapperParams(threshold=THR))
    c = g.all_centers().reshape(-1, 3)
    # water between the first two front poses and the box face at x = -0.15 m, clear of it
    water = (c[:, 0] > -0.8) & (c[:, 0] < -0.3) & np.all(np.abs(c[:, 1:]) < 0.1, axis=1)
    for img, T in pings[:2]:
        m.integrate(img, T)
    v = m.values().ravel()
    water &= np.isfinite(v)  # those the two views observed
    assert water.sum() > 20
    assert np.mean(v[water] < THR) >= 0.99


def test_bad_rule_and_threshold_are_refused():
    with pytest.raises(ValueError, match="rule"):
        gpumap.MinMaxMapper(SPEC, GRID, "numpy", MapperParams(rule="max"))
    with pytest.raises(ValueError, match="method='gather'"):
        gpumap.MinMaxMapper(SPEC, GRID, "numpy", MapperParams(rule="visible", method="template"))
    for bad in (0.0, 1.5, float("nan")):
        with pytest.raises(ValueError, match="threshold"):
            gpumap.MinMaxMapper(SPEC, GRID, "numpy", MapperParams(threshold=bad))
    for bad in (0, 256, 1.5, True):
        with pytest.raises(ValueError, match="carve_views"):
            gpumap.MinMaxMapper(SPEC, GRID, "numpy", MapperParams(carve_views=bad))
    assert gpumap.MinMaxMapper(SPEC, GRID, "numpy", MapperParams(method="template")).rule == "plain"
    with pytest.raises(ValueError, match="evidence"):
        gpumap.MinMaxMapper(SPEC, GRID, "numpy", MapperParams(rule="plain")).evidence()


def test_save_load_keeps_the_evidence(backend, tmp_path):
    pings = _random_pings(3, 5)
    m = _run(backend, pings)
    m2 = gpumap.MinMaxMapper.load(m.save(tmp_path / "map.npz"), backend=backend)
    assert m2.rule == "visible" and m2.threshold == pytest.approx(THR) and m2.carve_views == 2
    for k in ("min_all", "bright", "count"):
        np.testing.assert_array_equal(m2.evidence()[k], m.evidence()[k])
    # and it goes on integrating as the original would
    img, T = _random_pings(1, 6)[0]
    m.integrate(img, T)
    m2.integrate(img, T)
    np.testing.assert_array_equal(m2.raw_values(), m.raw_values())
