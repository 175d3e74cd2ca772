"""The surface layer (gpumap.layers.surface, issue 30): one voxel of the evidence map per bright cell.

An analytic scene (a floor plane and a box on it) is ray-cast here, independently of the simulator
and of the mapper: per beam and elevation ray, the first hit's range lights its bin. The layer's
properties are checked against that truth and against geometry computed here by another route.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

import gpumap
from gpumap.core.params import MapperParams
from gpumap.layers.surface import SURFACE_LEVEL, SurfaceLayer, SurfaceOptions, surface_from_evidence
from gpumap.layers.surface_live import surface_from_mapper

SPEC = gpumap.SonarSpec.uniform(hfov_deg=60, vfov_deg=20, n_beams=64, n_bins=160, range_min_m=0.1,
                                range_max_m=2.0)
GRID = gpumap.GridSpec((-0.2, -0.8, -0.4), (1.8, 0.8, 0.5), 0.04)
FLOOR_Z = -0.2
BOX_LO, BOX_HI = np.array([0.9, -0.15, FLOOR_Z]), np.array([1.2, 0.15, FLOOR_Z + 0.2])
THR = 0.5


def _first_hit(o: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Range of the first hit of rays from ``o`` along unit ``d`` (k, 3) with the floor and the box."""
    with np.errstate(divide="ignore", invalid="ignore"):
        tp = (FLOOR_Z - o[2]) / d[:, 2]
        t1, t2 = (BOX_LO - o) / d, (BOX_HI - o) / d
    t_floor = np.where(tp > 0, tp, np.inf)
    tn = np.nanmax(np.minimum(t1, t2), axis=1)
    tf = np.nanmin(np.maximum(t1, t2), axis=1)
    t_box = np.where((tf >= tn) & (tn > 0), tn, np.inf)
    return np.minimum(t_floor, t_box)


def _render(T_W_S: np.ndarray, n_el: int = 81, per_beam: int = 3) -> np.ndarray:
    """The ping of pose ``T_W_S``: 1 where a first hit of some ray in the nominal fan falls, else 0."""
    img = np.zeros(SPEC.image_shape, np.float32)
    edges = np.asarray(SPEC.beam_edges_rad)
    az = np.concatenate([np.linspace(edges[j], edges[j + 1], per_beam + 2)[1:-1]
                         for j in range(SPEC.n_beams)])
    beam = np.repeat(np.repeat(np.arange(SPEC.n_beams), per_beam), n_el)
    el = np.linspace(-SPEC.vfov_rad / 2, SPEC.vfov_rad / 2, n_el)
    A, E = np.meshgrid(az, el, indexing="ij")
    d_S = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], -1).reshape(-1, 3)
    r = _first_hit(T_W_S[:3, 3], d_S @ T_W_S[:3, :3].T)
    ok = (r >= SPEC.range_min_m) & (r < SPEC.range_max_m)
    img[((r[ok] - SPEC.range_min_m) / SPEC.bin_size_m).astype(int), beam[ok]] = 1.0
    return img


def _poses() -> np.ndarray:
    from gpumap.sim.scenes import pose_from_xyz_ypr

    return np.array([pose_from_xyz_ypr(np.array([0.03 * k, -0.3 + 0.05 * k, 0.3]),
                                       math.radians(5 * (k % 3) - 5), math.radians(20 + 25 * (k % 4) / 3))
                     for k in range(12)])


def _surface_distance(p: np.ndarray) -> np.ndarray:
    """Distance (m) of points ``p`` (k, 3) from the scene's surfaces (floor outside the box, box)."""
    q = np.clip(p, BOX_LO, BOX_HI)
    d_box = np.linalg.norm(p - q, axis=1)
    inside = np.all((p > BOX_LO) & (p < BOX_HI), axis=1)
    return np.where(inside, 0.0, np.minimum(np.abs(p[:, 2] - FLOOR_Z), d_box))


def _centres(mask: np.ndarray) -> np.ndarray:
    return np.asarray(GRID.min_corner_m) + (np.argwhere(mask) + 0.5) * GRID.voxel_size_m


@pytest.fixture(scope="module")
def scene():
    poses = _poses()
    images = np.stack([_render(T) for T in poses])
    m = gpumap.MinMaxMapper(SPEC, GRID, "numpy", MapperParams(rule="evidence", threshold=THR))
    m.integrate_batch(images, poses)
    return {"images": images, "poses": poses, "mapper": m}


def _view_of(T: np.ndarray, centres: np.ndarray, image: np.ndarray, opts: SurfaceOptions | None = None):
    from gpumap.geometry import beam_tan_edges
    from gpumap.layers.first_return import measured_first_returns
    from gpumap.layers.surface import _lit_cells, _view

    s = GRID.voxel_size_m
    lit = _lit_cells(image, SPEC, THR, 0.5 * s)
    half_el = 0.5 * SPEC.vfov_rad * (opts or SurfaceOptions()).aperture_scale
    return _view(SPEC, beam_tan_edges(SPEC), T, centres, lit, 0.5 * s, 0.5 * s, half_el,
                 measured_first_returns(image, SPEC, THR), s), lit


# ------------------------------------------------------------------------------ the analytic scene
def test_winners_gather_on_the_true_surfaces(scene):
    """The voxels the bright cells elect lie on the floor and the box far more often than the evidence
    map's occupied voxels do (the arcs' intersection across views picks the elevation), and the box's
    top in the surface layer is within two voxels of the true top where the evidence map's is not."""
    s = GRID.voxel_size_m
    layer = surface_from_mapper(scene["mapper"], scene["images"], scene["poses"],
                                SurfaceOptions(band_voxels=0, max_front_share=1.0, aperture_scale=1.0))
    on_cand = _surface_distance(_centres(layer.candidates)) <= 0.9 * s  # the voxel holds the surface
    on_surf = _surface_distance(_centres(layer.surface)) <= 0.9 * s
    assert layer.surface.sum() > 50
    assert on_surf.mean() >= 2 * on_cand.mean()
    assert on_surf.mean() >= 0.5


def test_surface_never_outside_the_evidence_map(scene):
    """A voxel never observed, or carved by the evidence rule, never becomes surface: the layer is a
    subset of the evidence rule's occupied voxels, whatever the options."""
    from gpumap.reference import evidence_occupied

    m = scene["mapper"]
    ev = m.evidence()
    occ = evidence_occupied(ev["count"], ev["hits"], m.bright_share, m.share_z)
    obs = np.isfinite(ev["min_all"])
    for opts in (SurfaceOptions(), SurfaceOptions(band_voxels=2, max_front_share=1.0, passes=2)):
        layer = surface_from_mapper(m, scene["images"], scene["poses"], opts)
        assert not (layer.surface & ~occ).any()
        assert not (layer.surface & ~obs).any()
        v = layer.values()
        assert np.isnan(v[~obs]).all() and (v[obs & ~layer.surface] == 0).all()
        assert (v[layer.surface] >= SURFACE_LEVEL).all()
    # the candidates one passes are the only ones: an empty set gives an empty layer
    none = surface_from_evidence(np.zeros(GRID.shape, bool), obs, GRID, SPEC, scene["images"], scene["poses"],
                                 THR)
    assert not none.surface.any()


def test_every_bright_cell_is_explained_by_exactly_one_voxel(scene):
    """Per ping: each bright cell that some candidate spans elects one of them (so the winners of a
    ping are at most its bright cells), and every such cell is spanned by a winner."""
    from gpumap.layers.surface import _explain

    m = scene["mapper"]
    layer = surface_from_mapper(m, scene["images"], scene["poses"], SurfaceOptions(band_voxels=0))
    idx = np.argwhere(layer.candidates)
    centres = _centres(layer.candidates)
    n_cells = None
    alive = np.ones(len(idx), bool)
    for k in (0, 5, 11):
        v, lit = _view_of(scene["poses"][k], centres, scene["images"][k])
        n_cells = lit.size
        half_el = 0.5 * SPEC.vfov_rad * SurfaceOptions().aperture_scale
        _, votes, _ = _explain([v], len(idx), n_cells, None, SPEC, half_el, 48, 0.08, 0.02, 20, alive)
        won = votes > 0
        cells = np.unique(v.cell)
        assert 0 < won.sum() <= len(cells)
        covered = np.unique(v.cell[won[v.cand[v.pair]]])
        np.testing.assert_array_equal(covered, cells)


def test_cells_span_the_voxel_width_exactly():
    """A voxel spans the range cells within half an edge of its centre's range and the beams whose
    cells its width reaches in azimuth: computed here in angles (not tangents), for every voxel of
    an all-bright ping (the arc is neither a cell short nor a cell long)."""
    rng = np.random.default_rng(3)
    T = np.eye(4)
    s = GRID.voxel_size_m
    p_S = np.stack([rng.uniform(0.4, 1.8, 400), rng.uniform(-0.5, 0.5, 400), rng.uniform(-0.1, 0.1, 400)], -1)
    image = np.ones(SPEC.image_shape, np.float32)
    v, lit = _view_of(T, p_S, image, SurfaceOptions(aperture_scale=2.0))
    cell_m, half = 0.5 * s, 0.5 * s
    edges = np.asarray(SPEC.beam_edges_rad)
    checked = 0
    for i, c in enumerate(v.cand):
        x, y, z = p_S[c]
        r, h, az = math.sqrt(x * x + y * y + z * z), math.hypot(x, y), math.atan2(y, x)
        lo, hi = (r - half - SPEC.range_min_m) / cell_m, (r + half - SPEC.range_min_m) / cell_m
        da = math.asin(half / h)
        b_lo = np.searchsorted(edges, az - da, side="right") - 1
        b_hi = np.searchsorted(edges, az + da, side="right") - 1
        near_edge = (min(abs(lo - round(lo)), abs(hi - round(hi))) < 1e-4
                     or np.min(np.abs(edges - (az - da))) < 1e-6 or np.min(np.abs(edges - (az + da))) < 1e-6)
        if near_edge:
            continue
        want = {(rc, b) for rc in range(int(lo), int(hi) + 1)
                for b in range(max(b_lo, 0), min(b_hi, SPEC.n_beams - 1) + 1)}
        got = {(int(k) // SPEC.n_beams, int(k) % SPEC.n_beams) for k in v.cell[v.pair == i]}
        assert got == want, (i, sorted(got - want), sorted(want - got))
        assert v.n_cells[i] == len(want)
        checked += 1
    assert checked > 300


def test_a_winner_shadows_the_voxels_behind_it():
    """The occlusion test: a voxel more than ``occlusion_m`` behind a surface voxel on the same ray is
    occluded; one just behind it, one beside it in elevation and the surface voxel itself are not."""
    from gpumap.layers.surface import _occluded

    s = GRID.voxel_size_m
    pts = np.array([[1.0, 0.0, 0.0], [1.5, 0.0, 0.0], [1.5, 0.0, 0.2], [1.05, 0.0, 0.0], [0.8, 0.0, 0.0]])
    v, _ = _view_of(np.eye(4), pts, np.ones(SPEC.image_shape, np.float32))
    assert list(v.cand) == [0, 1, 2, 3, 4]
    surface = np.array([True, False, False, False, False])
    occ = _occluded(v, surface, SPEC.n_beams, 0.5 * SPEC.vfov_rad * 1.5, 48, 2 * s, 0.5 * s)
    np.testing.assert_array_equal(occ, [False, True, False, False, False])


def test_occlusion_passes_keep_the_shadow_out():
    """With a second pass, no surface voxel lies in the acoustic shadow of a first-pass winner in
    every ping: a voxel whose only bright cells come from views in which a nearer surface voxel
    covers its direction does not win them."""
    from gpumap.layers.surface import _explain

    s = GRID.voxel_size_m
    # A in front, B right behind it on the same ray (0.3 m), both spanning the same bright cell range:
    # B's own cells are lit by a bin placed at B's range
    pts = np.array([[1.0, 0.0, 0.0], [1.3, 0.0, 0.0]])
    image = np.zeros(SPEC.image_shape, np.float32)
    for r in (1.0, 1.3):
        image[int((r - SPEC.range_min_m) / SPEC.bin_size_m), 30:34] = 1.0
    v, lit = _view_of(np.eye(4), pts, image)
    half_el = 0.5 * SPEC.vfov_rad * 1.5
    alive = np.ones(2, bool)
    _, first, _ = _explain([v], 2, lit.size, None, SPEC, half_el, 48, 2 * s, 0.5 * s, 20, alive)
    assert first.tolist() == [1, 1]  # without occlusion each explains its own cells
    _, second, _ = _explain([v], 2, lit.size, first > 0, SPEC, half_el, 48, 2 * s, 0.5 * s, 20, alive)
    assert second.tolist() == [1, 0]  # B lies in A's shadow


def test_a_voxel_in_front_of_first_returns_is_not_surface(scene):
    """A lone candidate that lies in front of the first return in most of the pings whose fan holds
    it (clear water there) is not surface, though it spans bright cells of some ping; without the
    first-return test (max_front_share=1) it is (nothing else explains those cells)."""
    from gpumap.layers.first_return import map_first_returns, measured_first_returns

    m = scene["mapper"]
    ev = m.evidence()
    obs = np.isfinite(ev["min_all"])
    s = GRID.voxel_size_m
    idx = np.argwhere(obs)
    rng = np.random.default_rng(0)
    found = None
    for i in rng.permutation(len(idx))[:4000]:
        c = np.asarray(GRID.min_corner_m) + (idx[i] + 0.5) * s
        in_fan = front = 0
        for img, T in zip(scene["images"], scene["poses"], strict=True):
            pred = map_first_returns(c[None], T, SPEC, s)  # the beams whose fan holds the voxel
            if not np.isfinite(pred).any():
                continue
            in_fan += 1
            meas = measured_first_returns(img, SPEC, THR)
            beams = np.flatnonzero(np.isfinite(pred))
            front += bool(np.all(pred[beams] < meas[beams] - 1.5 * s))
        if in_fan >= 4 and front >= 0.75 * in_fan and front < in_fan:
            cand = np.zeros(GRID.shape, bool)
            cand[tuple(idx[i])] = True
            plain = surface_from_evidence(cand, obs, GRID, SPEC, scene["images"], scene["poses"], THR,
                                          SurfaceOptions(max_front_share=1.0, band_voxels=0))
            if plain.surface.any():
                found = cand
                break
    assert found is not None, "expected a water voxel in front of most first returns that spans a bright cell"
    layer = surface_from_evidence(found, obs, GRID, SPEC, scene["images"], scene["poses"], THR,
                                  SurfaceOptions(band_voxels=0))
    assert not layer.surface.any()


# ------------------------------------------------------------------------------ the API and the files
def test_options_and_inputs_are_checked(scene):
    for bad in (dict(passes=0), dict(min_votes=0), dict(iterations=-1), dict(aperture_scale=0.5),
                dict(max_front_share=1.5), dict(cell_m=0.0), dict(band_voxels=1.5), dict(passes=True)):
        with pytest.raises(ValueError):
            SurfaceOptions(**bad)
    m = scene["mapper"]
    with pytest.raises(ValueError, match="images of shape"):
        surface_from_mapper(m, scene["images"][:, :10], scene["poses"])
    with pytest.raises(ValueError, match="poses of shape"):
        surface_from_mapper(m, scene["images"], scene["poses"][:3])
    with pytest.raises(ValueError, match="either images and poses or frames"):
        surface_from_mapper(m)
    with pytest.raises(ValueError, match="bool array of the grid's shape"):
        surface_from_evidence(np.zeros((2, 2, 2), bool), np.zeros(GRID.shape, bool), GRID, SPEC,
                              scene["images"], scene["poses"], THR)
    with pytest.raises(ValueError, match="threshold"):
        surface_from_evidence(np.zeros(GRID.shape, bool), np.zeros(GRID.shape, bool), GRID, SPEC,
                              scene["images"], scene["poses"], 0.0)


def test_frames_stream_gives_the_same_layer(scene):
    m = scene["mapper"]
    a = surface_from_mapper(m, scene["images"], scene["poses"])
    b = surface_from_mapper(m, frames=iter(list(zip(scene["images"], scene["poses"], strict=True))))
    np.testing.assert_array_equal(a.surface, b.surface)
    u8 = np.round(scene["images"] * 255).astype(np.uint8)  # uint8 pings read as the mapper reads them
    c = surface_from_mapper(m, u8, scene["poses"])
    np.testing.assert_array_equal(a.surface, c.surface)


def test_two_layer_file_reads_back_in_view_and_export(scene, tmp_path):
    """Saved beside map.npz as surface.npz, both layers read back: load_refined, the viewer's
    map_layer and gpumap export --layer, from surface.npz or from the map.npz beside it."""
    from gpumap.commands.export import main as export_main
    from gpumap.layers.refine import load_refined
    from gpumap.layers.refined_map import SURFACE_FILE, layers_file
    from gpumap.viewer.session import map_layer

    m = scene["mapper"]
    layer = surface_from_mapper(m, scene["images"], scene["poses"])
    assert isinstance(layer, SurfaceLayer)
    m.save(tmp_path / "map.npz")
    assert layers_file(tmp_path / "map.npz") is None
    path = layer.save(tmp_path / SURFACE_FILE, m.values(), SPEC, THR)
    assert layers_file(tmp_path / "map.npz") == path
    res = load_refined(path)
    np.testing.assert_array_equal(res.occupied(), layer.surface)
    np.testing.assert_array_equal(res.safe(), np.nan_to_num(m.values(), nan=-1) >= np.float32(THR))
    d = map_layer(tmp_path / "map.npz", "surface")
    assert d["layer"] == "surface" and int((d["values"] >= d["threshold"]).sum()) == int(layer.surface.sum())
    assert map_layer(tmp_path / "map.npz")["layer"] is None  # without --layer: the map itself
    assert export_main([str(tmp_path / "map.npz"), str(tmp_path / "s.ply"), "--layer", "surface"]) == 0
    text = (tmp_path / "s.ply").read_bytes()
    assert f"element vertex {int(layer.surface.sum())}".encode() in text


def test_demo_and_replay_take_no_surface():
    from gpumap.commands import demo, replay

    assert demo._parser().parse_args([]).surface is True
    assert demo._parser().parse_args(["--no-surface"]).surface is False
    assert "surface.npz" in demo.OUTPUTS and "surface.npz" in replay.OUTPUTS
    assert replay._parser().parse_args(["x"]).surface is False  # opt-in: --surface
    assert replay._parser().parse_args(["x", "--surface"]).surface is True


def test_live_surface_warm_start_stays_inside_the_map(scene):
    """With warm_start the first update is the offline layer; later ones start from the last weights
    and keep the layer inside the map's occupied voxels of that moment."""
    from gpumap.layers.surface_live import LiveSurface

    images, poses = scene["images"], scene["poses"]
    m = gpumap.MinMaxMapper(SPEC, GRID, "numpy", MapperParams(rule="evidence", threshold=THR))
    live = LiveSurface(m, warm_start=True)
    m.integrate_batch(images[:6], poses[:6])
    live.add(images[:6], poses[:6])
    first = live.update()
    offline = surface_from_mapper(m, images[:6], poses[:6])
    np.testing.assert_array_equal(first.surface, offline.surface)
    assert first.stats["warm"] is False
    m.integrate_batch(images[6:], poses[6:])
    live.add(images[6:], poses[6:])
    second = live.update()
    assert second.stats["warm"] is True and live.n_pings == len(images)
    v = m.values()
    assert not (second.surface & ~(v >= THR)).any()
    assert second.surface.sum() > 0
    with pytest.raises(ValueError, match="rule"):
        LiveSurface(gpumap.MinMaxMapper(SPEC, GRID, "numpy", MapperParams(rule="plain")))


@pytest.mark.parametrize("opts", [SurfaceOptions(), SurfaceOptions(band_voxels=0, iterations=3,
                                                                   max_front_share=0.5, min_votes=2)],
                         ids=["defaults", "other"])
def test_live_surface_equals_the_offline_layer_after_every_batch(scene, opts):
    """Each (ping, voxel) worked out once, the passes over all pings at once: after every batch
    (candidates come, go and come back as the map changes) the live layer is the offline one of the
    same pings on the same map, every count and the weights bit for bit."""
    from gpumap.geometry import SHARE_Z
    from gpumap.layers.surface import _layer, _prepare
    from gpumap.layers.surface_live import LiveSurface, map_candidates

    images, poses = scene["images"], scene["poses"]
    m = gpumap.MinMaxMapper(SPEC, GRID, "numpy", MapperParams(rule="evidence", threshold=THR))
    live = LiveSurface(m, opts)
    went = came = 0
    last = None
    # the decision's share moves between updates (a read-time option): candidates go and come back
    batches = ((0, 1), (1, 4), (4, 5), (5, 9), (9, 12))
    for (a, b), share in zip(batches, (0.2, 0.2, 1.0, 0.2, 0.2), strict=True):
        m.bright_share, m.share_z = share, (0.0 if share == 1.0 else SHARE_Z)
        m.integrate_batch(images[a:b], poses[a:b])
        live.add(images[a:b], poses[a:b])
        got = live.update()
        ref = surface_from_mapper(m, images[:b], poses[:b], opts)
        for name in ("surface", "candidates", "observed", "votes", "views", "bright_views"):
            np.testing.assert_array_equal(getattr(got, name), getattr(ref, name), err_msg=f"{name} after {b}")
        if last is not None:
            went += int((last & ~got.candidates).sum())
            came += int((got.candidates & ~last).sum())
        last = got.candidates
        cand, obs = map_candidates(m)
        pings = [_prepare(i, T, SPEC, THR, 0.5 * GRID.voxel_size_m, opts.live_ping_share)
                 for i, T in zip(images[:b], poses[:b], strict=True)]
        w_ref = _layer(cand, obs, GRID, SPEC, pings, opts)[1]
        w_got = live._pairs.explain(np.flatnonzero(cand), None)[1]
        assert np.array_equal(w_got, w_ref)
    assert went > 0 and came > 0  # the candidate set changed both ways between updates
    assert got.surface.sum() > 0 and live.n_pairs > 0


def test_map_candidates_are_the_evidence_rules_decision(scene):
    from gpumap.layers.surface_live import map_candidates
    from gpumap.reference import evidence_occupied

    m = scene["mapper"]
    ev = m.evidence()
    cand, obs = map_candidates(m)
    np.testing.assert_array_equal(cand, evidence_occupied(ev["count"], ev["hits"], m.bright_share, m.share_z))
    np.testing.assert_array_equal(obs, np.isfinite(ev["min_all"]))


def test_empty_beams_clear_the_water_only_in_live_pings():
    """A voxel in a beam without a return lies in front of nothing in a dim ping (a low gain or a
    dropped ping says nothing about the water) but in clear water in a ping that returns on most
    beams."""
    from gpumap.geometry import beam_tan_edges
    from gpumap.layers.surface import _prepare, _view

    s = GRID.voxel_size_m
    opts = SurfaceOptions()
    pts = np.array([[1.0, 0.0, 0.0]])  # on the fan's axis: beams 31-32
    flags = []
    for beams in (slice(0, 2), slice(0, 20)):  # 2 of 64 beams return (dim), then 20 of 64 (live)
        image = np.zeros(SPEC.image_shape, np.float32)
        image[150, beams] = 1.0
        pc = _prepare(image, np.eye(4), SPEC, THR, 0.5 * s, opts.live_ping_share)
        n_rc = int(np.ceil((SPEC.range_max_m - SPEC.range_min_m) / (0.5 * s))) + 1
        lit = np.zeros(SPEC.n_beams * n_rc, bool)
        lit[pc.lit] = True
        v = _view(SPEC, beam_tan_edges(SPEC), pc.T_W_S, pts, lit.reshape(-1, SPEC.n_beams), 0.5 * s, 0.5 * s,
                  0.5 * SPEC.vfov_rad * opts.aperture_scale, pc.first, s)
        flags.append(bool(v.front[0]))
    assert flags == [False, True]


def test_side_scene_is_a_single_side_pitched_sweep_without_roll():
    from gpumap.sim.scenes import make_scene

    scene = make_scene("side", voxel_size_m=0.05)
    T = scene.T_W_S
    assert T.shape == (40, 4, 4)
    assert np.ptp(T[:, 1, 3]) == 0.0  # one side: a straight line at one y
    x_S = T[:, :3, 0]  # boresight, world frame
    y_S = T[:, :3, 1]
    assert np.all(np.abs(y_S[:, 2]) < 1e-9)  # no roll: the sonar's y axis stays level
    pitch_deg = np.degrees(np.arcsin(-x_S[:, 2]))
    assert pitch_deg.min() >= 10 - 1e-6 and pitch_deg.max() <= 40 + 1e-6 and np.ptp(pitch_deg) > 20
    assert np.all(x_S[:, 1] > 0.7)  # every ping looks across to the objects' side (+y)


def test_replay_builds_the_surface_layer_in_its_one_pass(tmp_path, monkeypatch):
    """gpumap replay opens the recording once (the layer is fed by the mapping pass's batch hook)
    and its surface.npz is the offline layer of the same pings, voxel for voxel."""
    from conftest import DATA

    import gpumap.commands.replay
    import gpumap.io
    from gpumap.layers.refined_map import load_refined
    from gpumap.pipeline.replay import select_strided

    if DATA is None:
        pytest.skip("shared/data not found")
    opened = []
    real = gpumap.io.open_recording

    def open_recording(*a, **k):
        opened.append(a)
        return real(*a, **k)

    monkeypatch.setattr(gpumap.io, "open_recording", open_recording)
    out = tmp_path / "out"
    args = [str(DATA / "oasis_tank"), "--stride", "10", "--max-frames", "6", "--voxel-size", "0.1",
            "--backend", "numpy", "--no-progress", "--no-pictures", "--surface", "--out", str(out)]
    monkeypatch.setattr(gpumap.pipeline.replay, "REPLAY_BATCH", 4)  # two batches: the hook sees 4 + 2 pings
    assert gpumap.commands.replay.main(args) == 0
    assert len(opened) == 1
    m = gpumap.MinMaxMapper.load(out / "map.npz", backend="numpy")
    frames = [(f.image, f.T_W_S) for f in select_strided(real(DATA / "oasis_tank"), 10, 6)]
    ref = surface_from_mapper(m, frames=iter(frames))
    got = load_refined(out / "surface.npz")
    assert ref.stats["pings"] == 6 and ref.surface.sum() > 0
    np.testing.assert_array_equal(got.occupancy, ref.values())


def test_live_surface_with_a_window_is_the_offline_layer_of_the_newest_pings(scene):
    """max_pings: each update drops the oldest pings (their sums out, their pairs cut off) and is the
    offline layer of the newest max_pings pings on the map of every ping, voxel for voxel."""
    from gpumap.layers.surface_live import LiveSurface

    images, poses = scene["images"], scene["poses"]
    m = gpumap.MinMaxMapper(SPEC, GRID, "numpy", MapperParams(rule="evidence", threshold=THR))
    live = LiveSurface(m, max_pings=4)
    held = []
    for a, b in ((0, 3), (3, 5), (5, 6), (6, 11), (11, 12)):
        m.integrate_batch(images[a:b], poses[a:b])
        live.add(images[a:b], poses[a:b])
        got = live.update()
        lo = max(0, b - 4)
        ref = surface_from_mapper(m, images[lo:b], poses[lo:b])
        for name in ("surface", "votes", "views", "bright_views"):
            np.testing.assert_array_equal(getattr(got, name), getattr(ref, name), err_msg=f"{name} after {b}")
        assert got.stats["pings"] == b - lo and got.stats["first_ping"] == lo and live.n_added == b
        held.append(live.n_pairs)
    assert live.n_pings == 4 and max(held) < 2 * min(held[2:])  # bounded, not growing with the run
    with pytest.raises(ValueError, match="max_pings"):
        LiveSurface(m, max_pings=0)
