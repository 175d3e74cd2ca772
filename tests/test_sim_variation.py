"""The simulated sonar's view-to-view variation (gpumap.sim.variation.SonarVariation) and its measurement."""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest
from gpumap.sim.metrics import evaluate
from gpumap.sim.scenes import box_scene, pose_from_xyz_ypr
from gpumap.sim.sonar import OCCUPIED_THRESHOLD, SonarSimulator, detected_points
from gpumap.sim.truth import occupancy, points_to_voxels
from gpumap.sim.variation import (
    REAL_TANK,
    SonarVariation,
    VariationStats,
    ar1_series,
    headline,
    surface_normals,
    surface_texture,
)

import gpumap
from gpumap.core.params import MapperParams
from gpumap.lie import so3_log

#: A small sonar: renders in a few milliseconds per ping.
SPEC = gpumap.SonarSpec.uniform(hfov_deg=130, vfov_deg=20, n_beams=64, n_bins=100,
                                range_min_m=0.1, range_max_m=2.0)
FAST = {"elevation_step_rad": math.radians(0.4)}
FLOOR = ((0.0, 0.0, -0.55), (4.0, 3.0, 0.1))  # top at z = -0.5
BLOCK = ((0.9, 0.1, -0.35), (0.2, 0.3, 0.3))


def _poses(n: int, period: int = 20) -> np.ndarray:
    """``n`` poses nodding and sliding over a ``period`` (a sonar at its own rate over the same ground)."""
    out = []
    for k in range(n):
        a = 2 * math.pi * (k % period) / period
        out.append(pose_from_xyz_ypr(np.array([0.0, 0.15 * math.sin(a), 0.0]), 0.05 * math.cos(a),
                                     math.radians(30 + 8 * math.sin(a))))
    return np.array(out)


def _scene(boxes=(FLOOR,), n: int = 1, voxel_m: float = 0.05):
    return box_scene(list(boxes), T_W_S=_poses(n), spec=SPEC, voxel_size_m=voxel_m)


# ------------------------------------------------------------------------------ the parameter object
def test_none_is_the_simulator_as_before_bit_for_bit():
    scene = _scene((FLOOR, BLOCK), n=3)
    out = []
    for var in (None, SonarVariation.none()):
        with SonarSimulator(scene, seed=4, variation=var, **FAST) as sim:
            out.append([sim.ping(T, k) for k, T in enumerate(scene.T_W_S)])
    for a, b in zip(*out, strict=True):
        assert np.array_equal(a.image, b.image) and np.array_equal(a.clean_image, b.clean_image)
        assert np.array_equal(a.points_W, b.points_W) and np.array_equal(a.T_W_S, b.T_W_S)
        assert b.T_W_S_actual is None and not b.dropped
    assert SonarVariation.none().is_none and not SonarVariation.real_tank().is_none


def test_variation_is_deterministic_per_seed_and_ping_order_free():
    scene = _scene((FLOOR, BLOCK), n=6)
    var = SonarVariation.real_tank()
    with SonarSimulator(scene, seed=1, variation=var, **FAST) as sim:
        fwd = {k: sim.ping(scene.T_W_S[k], k) for k in (2, 5)}
    with SonarSimulator(scene, seed=1, variation=var, **FAST) as sim:
        rev = {k: sim.ping(scene.T_W_S[k], k) for k in (5, 2)}
    with SonarSimulator(scene, seed=2, variation=var, **FAST) as sim:
        other = sim.ping(scene.T_W_S[2], 2)
    for k in (2, 5):
        assert np.array_equal(fwd[k].image, rev[k].image)
        assert np.array_equal(fwd[k].T_W_S_actual, rev[k].T_W_S_actual)
        assert np.array_equal(fwd[k].T_W_S, scene.T_W_S[k])  # the ping reports the nominal pose
        assert not np.allclose(fwd[k].T_W_S_actual, scene.T_W_S[k])  # and was taken elsewhere
    assert not np.array_equal(fwd[2].image, other.image)


@pytest.mark.parametrize("bad", [{"looks": 0.0}, {"gain_correlation": 1.0}, {"dropout_prob": 1.5},
                                 {"jitter_translation_m": -0.01}, {"texture_shape": 0.0},
                                 {"gain_offset_db": math.inf}])
def test_invalid_parameters_are_refused(bad):
    with pytest.raises(ValueError):
        SonarVariation(**bad)
    with pytest.raises(TypeError):
        SonarVariation(gain_sigma_db="3")
    with pytest.raises(TypeError):
        SonarSimulator(_scene(), variation={"looks": 1.0})


def test_ar1_series_has_unit_variance_its_correlation_and_stable_prefixes():
    rho = 0.8
    x = ar1_series(7, 1, 40_000, 1, rho)[:, 0]
    n_eff = len(x) * (1 - rho) / (1 + rho)  # effective samples of a mean under AR(1)
    assert abs(x.mean()) < 5 / math.sqrt(n_eff)
    assert abs(x.var() - 1.0) < 0.05
    assert abs(np.corrcoef(x[:-1], x[1:])[0, 1] - rho) < 0.02
    # a row depends on its index only, never on how long a series was asked for
    assert np.array_equal(ar1_series(7, 1, 300, 2, 0.5)[:100], ar1_series(7, 1, 100, 2, 0.5))
    assert not np.array_equal(ar1_series(7, 1, 10, 1, 0.5), ar1_series(7, 2, 10, 1, 0.5))


def test_gain_jitter_and_dropouts_match_their_parameters():
    var = SonarVariation(gain_offset_db=-3.0, gain_sigma_db=2.5, gain_correlation=0.5,
                         jitter_translation_m=0.004, jitter_rotation_rad=math.radians(0.4),
                         jitter_correlation=0.5, dropout_prob=0.1)
    n = 4000
    with SonarSimulator(_scene(), seed=3, variation=var, **FAST) as sim:  # nothing is rendered here
        g_db = 10 * np.log10([sim.ping_gain(k) for k in range(n)])
        J = np.array([sim.jitter(k) for k in range(n)])
        drops = np.array([sim.is_dropped(k) for k in range(n)])
    n_eff = n * (1 - 0.5) / (1 + 0.5)
    assert abs(g_db.mean() - (-3.0)) < 5 * 2.5 / math.sqrt(n_eff)
    assert abs(g_db.std() / 2.5 - 1) < 0.08
    assert abs(np.corrcoef(g_db[:-1], g_db[1:])[0, 1] - 0.5) < 0.06
    rot = np.array([so3_log(T[:3, :3]) for T in J])
    assert np.allclose(rot.std(0) / math.radians(0.4), 1, atol=0.08)
    assert np.allclose(J[:, :3, 3].std(0) / 0.004, 1, atol=0.08)
    assert np.allclose(J[:, 3, :], [0, 0, 0, 1])
    assert abs(drops.mean() - 0.1) < 5 * math.sqrt(0.1 * 0.9 / n)


@pytest.mark.parametrize("looks, nu", [(1.0, math.inf), (3.0, math.inf), (1.0, 2.0)])
def test_speckle_multiplier_has_the_analytic_mean_and_variance(looks, nu):
    """Gamma(L) speckle: mean 1, variance 1/L; with a Gamma(nu) texture (K): E[s^2] = (1 + 1/L)(1 + 1/nu)."""
    scene = _scene((FLOOR, BLOCK), n=3)
    var = SonarVariation(looks=looks, texture_shape=nu)
    s = []
    with SonarSimulator(scene, seed=5, variation=var, noise_floor=0.0, **FAST) as sim:
        for k in range(3):
            p = sim.ping(scene.T_W_S[k], k)
            c = p.clean_image.astype(np.float64)
            ok = (c > 0.02) & (c < 0.3)  # the display's linear-ish part: no clipping, float32 is exact enough
            s.append(np.log1p(-p.image[ok].astype(np.float64)) / np.log1p(-c[ok]))
    s = np.concatenate(s)
    assert s.size > 2000
    m2 = (1 + 1 / looks) * (1 + (0.0 if math.isinf(nu) else 1 / nu))
    v = m2 - 1
    se_mean = math.sqrt(v / s.size)
    se_var = math.sqrt((np.mean((s - s.mean()) ** 4) - s.var() ** 2) / s.size)
    assert abs(s.mean() - 1) < 5 * se_mean + 1e-3
    assert abs(s.var() - v) < 5 * se_var + 1e-3


def test_surface_texture_is_log_normal_of_its_spread_fixed_per_cube_and_seeded():
    """One value per cube of side size_m (a line crosses a new cube every size_m), log-normal
    with mean 1 and the configured SD in dB, the same for the same points in any order, per seed."""
    size, sigma = 0.04, 6.0
    g = np.arange(30) * size  # a lattice of the cubes' spacing: one point in each of 27,000 cubes
    pts = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3) + 0.013
    t = surface_texture(pts, 3, sigma, size)
    n, s = len(t), sigma * math.log(10) / 10
    db = 10 * np.log10(t)
    assert abs(db.std() / sigma - 1) < 5 / math.sqrt(2 * n)
    assert abs(db.mean() - 10 * math.log10(math.exp(-s * s / 2))) < 5 * sigma / math.sqrt(n)
    assert abs(t.mean() - 1) < 5 * math.sqrt((math.exp(s * s) - 1) / n)
    line = np.zeros((4000, 3)) + [0.3, 0.7, 0.2]
    line[:, 0] += np.arange(4000) * size / 40  # 100 cubes' length in steps of a 40th of a cube
    changes = np.count_nonzero(np.diff(surface_texture(line, 3, sigma, size)))
    assert 99 <= changes <= 100
    assert np.array_equal(surface_texture(pts[::-1], 3, sigma, size), t[::-1])
    assert np.mean(surface_texture(pts, 4, sigma, size) == t) < 0.01
    assert np.array_equal(surface_texture(pts, 3, 0.0, size), np.ones(n))


def test_the_real_tank_presets_per_ping_gain_spread_shows_in_rendered_pings():
    """The refit's per-ping gain, measured on rendered pings (each ping's echo energy over its
    noise-free image's, averaged over cells where the display is not saturated), is the ping's own
    draw within the speckle's noise, and its spread over pings is the preset's gain_sigma_db within
    sampling error (the gain made independent between pings here, so that 60 pings are 60 draws)."""
    var = SonarVariation(**{**REAL_TANK, "gain_correlation": 0.0})
    scene = _scene((FLOOR, BLOCK), n=60)
    measured_db, drawn_db = [], []
    with SonarSimulator(scene, seed=7, variation=var, noise_floor=0.0, **FAST) as sim:
        for k in range(len(scene.T_W_S)):
            p = sim.ping(scene.T_W_S[k], k)
            c = p.clean_image.astype(np.float64)
            ok = (c > 1e-3) & (c < 0.2) & (p.image < 0.999)
            assert ok.sum() > 300
            e = np.log1p(-p.image[ok].astype(np.float64)) / np.log1p(-c[ok])  # g_ping / median * speckle
            measured_db.append(10 * np.log10(e.mean()))
            drawn_db.append(10 * np.log10(sim.ping_gain(k)) - var.gain_offset_db)
    measured_db, drawn_db = np.array(measured_db), np.array(drawn_db)
    assert np.max(np.abs(measured_db - drawn_db)) < 0.5  # 4 looks averaged over hundreds of cells
    n = len(drawn_db)
    assert abs(measured_db.std(ddof=1) / var.gain_sigma_db - 1) < 3 / math.sqrt(2 * (n - 1))
    assert abs(measured_db.mean()) < 3 * var.gain_sigma_db / math.sqrt(n)


def test_headline_reads_the_two_fitted_figures():
    st = {"ping_gain": {"bright_cells_log_sd": 0.5}, "persistence": {"lag1_correlation": 0.7}}
    assert headline(st) == {"per_ping_spread": 0.5, "persistence": 0.7}
    assert all(math.isnan(v) for v in headline({"persistence": {"pairs": 0}}).values())


def test_range_loss_scales_each_range_bin_by_its_law():
    """The extra range loss multiplies the echo energy of range bin r by 10 ** (-L (r - 1) / 10),
    in the noise-free image as in the ping."""
    scene = _scene((FLOOR, BLOCK), n=1)
    out = []
    for loss in (0.0, 6.0):
        with SonarSimulator(scene, seed=2, variation=SonarVariation(range_loss_db_per_m=loss), **FAST) as sim:
            out.append(sim.ping(scene.T_W_S[0], 0).clean_image.astype(np.float64))
    base, lossy = out
    ok = (base > 1e-4) & (base < 0.5)
    r = SPEC.range_min_m + (np.nonzero(ok)[0] + 0.5) * SPEC.bin_size_m
    ratio = np.log1p(-lossy[ok]) / np.log1p(-base[ok])
    assert ok.sum() > 200
    assert np.allclose(ratio, 10 ** (-6.0 * (r - 1.0) / 10), rtol=2e-3)


# ------------------------------------------------------------------------------ the measurement
def _floor_share(var: SonarVariation, n: int = 20) -> float:
    """Mean bright share of the floor's surface voxels over the ``n`` pings that observe them (the
    bench's measurement; a floor voxel has the floor nearer in its own beams, so few views are clear)."""
    scene = _scene((FLOOR,), n=n)
    truth = occupancy(scene)
    idx = np.argwhere(truth.surface)
    normals, _ = surface_normals(truth.surface, idx)
    st = VariationStats(SPEC, scene.grid, idx, normals, OCCUPIED_THRESHOLD)
    with SonarSimulator(scene, seed=0, variation=var, **FAST) as sim:
        for k in range(n):
            p = sim.ping(scene.T_W_S[k], k)
            st.add(p.image, p.T_W_S)
    share = st.summary(min_views=5)["bright_share_all_observed_views"]
    assert share["voxels"] > 50
    return share["mean"]


def test_bright_share_of_a_flat_floor_falls_as_the_pings_vary_more():
    """On a floor above the threshold, the share of bright views falls as the pings dim (a gain
    offset) and vary (a per-ping gain spread dims whole pings at once)."""
    base = _floor_share(SonarVariation.none())
    assert base > 0.95  # the simulator's floor, as it was: bright in (nearly) every view
    dim = _floor_share(SonarVariation(gain_offset_db=-8.0))
    spread = _floor_share(SonarVariation(gain_offset_db=-8.0, gain_sigma_db=4.0))
    assert base > dim + 0.05 and dim > spread + 0.05


def test_heavier_speckle_brightens_a_dim_floor_footprint_max():
    """Speckle alone does not erode: a footprint max over many cells of heavier speckle reaches
    the threshold more often (measured: 0.90 with looks 1 against 0.78 with looks 16 on a floor
    dimmed by 8 dB). Views go dark through the ping's gain and geometry, not through speckle."""
    heavy = _floor_share(SonarVariation(gain_offset_db=-8.0, looks=1.0))
    light = _floor_share(SonarVariation(gain_offset_db=-8.0, looks=16.0))
    assert heavy > light + 0.05


def test_variation_stats_counts_views_runs_and_shadows():
    """One voxel 1 m ahead, views bright or dark in a known order; a view with a bright cell in
    front of the voxel in its beams is a shadow, not a dark view."""
    grid = gpumap.GridSpec((-1.0, -1.0, -1.0), (2.0, 1.0, 1.0), 0.05)
    idx = grid.index_of(np.array([[1.0, 0.0, 0.0]]))
    st = VariationStats(SPEC, grid, idx, np.array([[1.0, 0.0, 0.0]]), threshold=0.5)
    r0 = SPEC.bin_index(np.array([1.0]))[0]
    bright = np.zeros(SPEC.image_shape, np.float32)
    bright[r0 - 1:r0 + 2] = 0.9  # every beam: cells inside the footprint (none in front of it) bright
    shadow = np.zeros(SPEC.image_shape, np.float32)
    shadow[r0 - 20] = 0.9  # a return well in front of the voxel
    pattern = "BBDDSDB"  # S: shadowed, not seen
    for c in pattern:
        st.add({"B": bright, "D": np.zeros_like(bright), "S": shadow}[c], np.eye(4))
    assert st.n_seen[0] == 6 and st.n_bright[0] == 3 and st.n_observed[0] == 7
    # consecutive views that both see it: BB, BD, DD, then S breaks the chain, then DB
    assert st.pairs[0].tolist() == [[1, 1], [1, 1]]
    s = st.summary(min_views=1)
    assert s["bright_share"]["quantiles"]["q50"] == 0.5
    assert s["by_range"][2]["views"] == 6 and s["by_range"][2]["pooled_bright"] == 0.5  # 1 m: bin 0.8-1.1
    assert s["by_incidence"][0]["views"] == 6  # looking along the normal: 0 deg
    assert s["ping_gain"]["pings_without_bright_cells"] == 3


def test_surface_normals_of_a_plane_and_incidence_bins():
    m = np.zeros((12, 12, 12), bool)
    m[:, :, 5] = True
    idx = np.argwhere(m)[::7]
    n, flat = surface_normals(m, idx)
    assert np.allclose(np.abs(n[:, 2]), 1.0) and np.all(flat > 0.99)


# ------------------------------------------------------------------------------ what it does to a map
@functools.lru_cache(maxsize=2)
def _miss_rates(preset: str, checkpoints=(40, 400)) -> dict[str, list[float]]:
    """Per rule, the miss rate of the detectable surface after each checkpoint's pings (one
    simulated pass, every rule mapping the same pings)."""
    var = getattr(SonarVariation, preset)()
    scene = _scene((FLOOR, BLOCK), n=max(checkpoints), voxel_m=0.05)
    truth = occupancy(scene)
    rules = ("visible", "evidence")
    maps = {
        r: gpumap.MinMaxMapper(SPEC, scene.grid, "auto", MapperParams(rule=r, threshold=OCCUPIED_THRESHOLD))
        for r in rules
    }
    det = np.zeros(scene.grid.n_voxels, bool)
    out: dict[str, list[float]] = {r: [] for r in rules}
    with SonarSimulator(scene, seed=0, variation=var, **FAST) as sim:
        for k in range(max(checkpoints)):
            p = sim.ping(scene.T_W_S[k], k)
            det[points_to_voxels(detected_points(p), scene.grid)] = True
            for m in maps.values():
                m.integrate(p.image, p.T_W_S)
            if k + 1 in checkpoints:
                for r, m in maps.items():
                    ev = evaluate(m.values(), truth, OCCUPIED_THRESHOLD,
                                  detectable=det.reshape(scene.grid.shape))
                    out[r].append(ev.miss_rate)
    return out


def test_visible_rule_erodes_a_surface_as_realistic_pings_accumulate():
    """The issue's erosion: with the real tank's variation the visible rule's map loses more of
    the detectable surface after 400 pings than after 40 (clear dark views accumulate)."""
    early, late = _miss_rates("real_tank")["visible"]
    assert late > early + 0.05


def test_the_evidence_rule_keeps_the_surface_as_realistic_pings_accumulate():
    """The default rule on the same pings keeps most of the surface at 400 pings as at 40, where
    the visible rule has lost most of it (with the earlier, noisier real_tank preset: 9 % and 13 %
    missed against 83 % and 100 %). Its decision converges: what it frees as views accumulate is
    floor at grazing incidence that is bright in fewer than half of its views (bright_share), not an
    erosion that goes on."""
    rates = _miss_rates("real_tank")
    early, late = rates["evidence"]
    assert early < 0.2 and late <= early + 0.05
    assert late < rates["visible"][1] / 4


def test_without_variation_more_pings_do_not_erode():
    """The simulator as it was hides the erosion: 400 pings miss no more than 40 do."""
    early, late = _miss_rates("none")["visible"]
    assert late <= early + 0.01
