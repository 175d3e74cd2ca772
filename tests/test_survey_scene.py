"""The survey scene: deterministic, a lawnmower over the whole seabed, truth and DVL checked
against the scene's analytic seabed and solids."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from gpumap.sim.dvl import DVLSimulator
from gpumap.sim.scenes import SURVEY, make_scene, survey_mounts
from gpumap.sim.sonar import SonarSimulator
from gpumap.sim.truth import occupancy

import gpumap
from gpumap.errors import check_pose
from gpumap.lie import se3_inverse


@pytest.fixture(scope="module")
def scene():
    return make_scene("survey")


def _vehicle(scene) -> np.ndarray:
    T_V_S, _ = survey_mounts()
    return scene.T_W_S @ se3_inverse(T_V_S)


def test_same_seed_same_scene_other_seed_other_seabed(scene):
    again = make_scene("survey", seed=0)
    for a, b in zip(scene.objects, again.objects, strict=True):
        assert a.name == b.name
        np.testing.assert_array_equal(a.mesh.vertices, b.mesh.vertices)
        np.testing.assert_array_equal(a.mesh.faces, b.mesh.faces)
    np.testing.assert_array_equal(scene.T_W_S, again.T_W_S)
    np.testing.assert_array_equal(scene.T_W_D, again.T_W_D)
    np.testing.assert_array_equal(scene.features_W, again.features_W)
    other = make_scene("survey", seed=1)
    x, y = np.meshgrid(np.linspace(-20, 20, 41), np.linspace(-8, 8, 17))
    assert np.abs(other.seabed_z_m(x, y) - scene.seabed_z_m(x, y)).max() > 0.05
    assert not np.array_equal(other.object("rocks").mesh.vertices, scene.object("rocks").mesh.vertices)


def test_scene_is_cheap_to_render_and_holds_the_objects(scene):
    assert scene.object_names == ["sand", "wreck", "pipe", "rocks"]
    assert scene.small_objects == ("wreck", "pipe", "rocks")
    n_tri = sum(len(o.mesh.faces) for o in scene.objects)
    assert n_tri <= 250_000, n_tri
    lo, hi = scene.object("sand").mesh.bounds
    np.testing.assert_allclose(lo[:2], [-25, -10])
    np.testing.assert_allclose(hi[:2], [25, 10])
    # about 4 m of water: the seabed's mean is 4 m down, its relief within +-0.5 m
    x, y = np.meshgrid(np.linspace(-25, 25, 501), np.linspace(-10, 10, 201))
    h = scene.seabed_z_m(x, y)
    assert abs(h.mean() + 4.0) < 0.1 and h.min() > -4.5 and h.max() < -3.5
    # the mesh is the heightfield at its vertices
    V = scene.object("sand").mesh.vertices
    np.testing.assert_allclose(V[:, 2], scene.seabed_z_m(V[:, 0], V[:, 1]), atol=1e-12)
    # the dense grid is the seabed band: from below the deepest solid to above the wreck
    g = scene.grid
    assert g.voxel_size_m == 0.05 and g.shape == (1000, 400, 60)
    assert g.min_corner_m[2] < h.min() - 0.2
    assert g.max_corner_m[2] > scene.object("wreck").mesh.bounds[1, 2]


def test_poses_are_valid_and_fly_a_lawnmower(scene):
    n = len(scene.T_W_S)
    assert 150 <= n <= 300
    for T in (*scene.T_W_S, *scene.T_W_D):
        check_pose(T)
    V = _vehicle(scene)
    p = V[:, :3, 3]
    np.testing.assert_allclose(p[:, 2], SURVEY["vehicle_z_m"], atol=1e-9)
    steps = np.linalg.norm(np.diff(p[:, :2], axis=0), axis=1)
    assert np.all(np.abs(steps - 1.0) < 0.05), (steps.min(), steps.max())  # a ping every metre of path
    fwd = V[:, :3, 0]
    yaw = np.arctan2(fwd[:, 1], fwd[:, 0])
    # four straight lines 5 m apart, alternating direction, each 44 m long
    for i, y in enumerate((-7.5, -2.5, 2.5, 7.5)):
        on = np.abs(p[:, 1] - y) < 1e-6
        heading = 0.0 if i % 2 == 0 else math.pi
        dyaw = np.angle(np.exp(1j * (yaw[on] - heading)))
        assert np.all(np.abs(dyaw) < 1e-6)
        xs = p[on, 0]
        assert xs.min() <= -21.0 and xs.max() >= 21.0 and np.all(np.abs(xs) <= 22.0 + 1e-9)
        order = np.flatnonzero(on)
        assert np.all(np.diff(xs) * (1 if i % 2 == 0 else -1) > 0), "along the line, in order"
        assert np.all(np.diff(order) == 1), "one line is one run of pings"
    # turns stay inside the 50 m area
    assert np.all(np.abs(p[:, 0]) <= 25.0) and np.all(np.abs(p[:, 1]) <= 10.0)
    # the sonar looks ahead 30 deg down (+- the wobble), the DVL straight down
    below = np.degrees(-np.arcsin(scene.T_W_S[:, 2, 0]))
    assert np.all(np.abs(below - SURVEY["sonar_pitch_deg"]) < 3.0), (below.min(), below.max())
    np.testing.assert_allclose(scene.T_W_D[:, 2, 0], -1.0, atol=2e-3)


def test_sonar_footprints_cover_the_seabed(scene):
    spec = scene.sonar_spec
    x, y = np.meshgrid(np.arange(-24.5, 25.0, 1.0), np.arange(-9.5, 10.0, 1.0), indexing="ij")
    pts = np.stack([x.ravel(), y.ravel(), scene.seabed_z_m(x, y).ravel()], 1)
    views = np.zeros(len(pts), int)
    for T in scene.T_W_S:
        views += spec.in_fov((pts - T[:3, 3]) @ T[:3, :3])
    assert views.min() >= 1, pts[views < 1]
    assert np.mean(views >= 2) > 0.99, pts[views < 2]  # all but the corners, by several pings
    # inside the survey's middle most points are seen from several lines' passes
    mid = (np.abs(pts[:, 0]) < 20) & (np.abs(pts[:, 1]) < 8)
    assert np.median(views[mid]) >= 8


def test_truth_marks_seabed_objects_and_water(scene):
    h = scene.seabed_z_m
    wreck = scene.object("wreck")
    hull_c = wreck.mesh.vertices[:8].mean(0)  # the hull box's centre (first part of the wreck)
    s = 0.05
    lo = np.floor(hull_c / s) * s - [4.0, 4.0, 1.0]
    grid = gpumap.GridSpec(lo, lo + [8.0, 8.0, 3.5], s)
    truth = occupancy(scene, grid)

    def at(p):
        i = tuple(int(v) for v in grid.index_of(np.asarray(p, float)[None])[0])
        return bool(truth.occupied[i]), truth.names[truth.label[i]] if truth.label[i] >= 0 else None

    assert at(hull_c) == (True, "wreck")
    assert at(hull_c + [0, 0, 0.5]) == (True, "wreck")  # the hull is solid, not only a shell
    # far from the wreck (its corners reach 3.6 m): the seabed is solid, the water above is free
    for dx, dy in ((-3.8, -3.8), (3.8, 3.8), (-3.8, 3.8)):
        x, y = hull_c[0] + dx, hull_c[1] + dy
        if scene.object("rocks").contains(np.array([[x, y, float(h(x, y))]]))[0]:
            continue
        z = float(h(x, y))
        assert at([x, y, z + 1.0]) == (False, None), (x, y)
        assert at([x, y, z + 0.3]) == (False, None), (x, y)
        assert at([x, y, z - 0.2]) == (True, "sand"), (x, y)
        assert at([x, y, z - 0.6]) == (True, "sand"), (x, y)  # the interior, far below the mesh
        assert at([x, y, z])[0], (x, y)
    # the deckhouse's top: occupied, and 10 cm above it free water
    top = wreck.mesh.vertices[8:].max(0)[2]
    house_c = wreck.mesh.vertices[8:16].mean(0)
    assert at([*house_c[:2], top - 0.05]) == (True, "wreck")
    assert at([*house_c[:2], top + 0.1]) == (False, None)


def test_truth_marks_pipe_and_rocks(scene):
    pipe, rocks = scene.object("pipe"), scene.object("rocks")
    # a point on the pipeline's axis: the centre of the segment nearest x = 0 (the mean of a
    # cylinder's vertices, two rings of 16 and the two cap centres)
    segs = pipe.mesh.split(only_watertight=False)
    assert len(segs) > 15
    mids = np.array([m.vertices.mean(0) for m in segs])
    c = mids[np.argmin(np.abs(mids[:, 0]))]
    assert np.all(np.diff(np.sort(mids[:, 0])) < 2.5)  # no gap along the pipeline
    s = 0.05
    lo = np.floor(c / s) * s - 1.0
    grid = gpumap.GridSpec(lo, lo + 2.0, s)
    truth = occupancy(scene, grid)
    i = tuple(grid.index_of(c[None])[0])
    assert truth.occupied[i] and truth.names[truth.label[i]] == "pipe"
    above = tuple(grid.index_of((c + [0, 0, 0.5])[None])[0])
    assert not truth.occupied[above]
    # each rock's centre, taken from its mesh, is inside the rock (rocks are solid)
    Vr = rocks.mesh.vertices.reshape(-1, 642, 3)  # one icosphere (subdivisions=3) per rock
    centres = Vr.mean(1)
    assert rocks.contains(centres).all()
    assert not rocks.contains(centres + [0, 0, 2.0]).any()


def test_dvl_ranges_meet_the_analytic_seabed(scene):
    dvl = DVLSimulator(scene)
    h = scene.seabed_z_m
    Vr = scene.object("rocks").mesh.vertices.reshape(-1, 642, 3)  # one icosphere per rock
    boxes = [scene.object("wreck").mesh.bounds, *np.stack([Vr.min(1), Vr.max(1)], 1)]
    checked = 0
    for k in range(0, len(scene.T_W_D), 9):
        T = scene.T_W_D[k]
        o = T[:3, 3]
        dirs = dvl._rays_D @ T[:3, :3].T  # (4, rays, 3) world directions of each beam's cone
        # the analytic range of each ray: bisection on z(t) - h(x(t), y(t))
        t_lo, t_hi = np.zeros(dirs.shape[:2]), np.full(dirs.shape[:2], 10.0)
        for _ in range(60):
            t = 0.5 * (t_lo + t_hi)
            q = o + t[..., None] * dirs
            above = q[..., 2] > h(q[..., 0], q[..., 1])
            t_lo, t_hi = np.where(above, t, t_lo), np.where(above, t_hi, t)
        hits = o + t_lo[..., None] * dirs
        clear = all(np.all(np.any((hits < b[0] - 0.3) | (hits > b[1] + 0.3), axis=-1)) for b in boxes)
        d_pipe = _pipe_distance(scene, hits.reshape(-1, 3))
        if not clear or d_pipe.min() < 0.5 or np.any(np.abs(hits[..., :2]) > [24.5, 9.5]):
            continue
        r = dvl.ranges(T)
        expect = t_lo.min(axis=1)
        np.testing.assert_allclose(r, expect, atol=0.01)  # the mesh is the heightfield within mm
        # altitude from the four slant ranges (level DVL) against the seabed below the vehicle
        alt = float(np.mean(r)) * math.cos(math.radians(22.5))
        assert abs(alt - (o[2] - float(h(o[0], o[1])))) < 0.15
        checked += 1
    assert checked >= 10, checked


def _pipe_distance(scene, p: np.ndarray) -> np.ndarray:
    V = scene.object("pipe").mesh.vertices
    a, b = V[:, :2].min(0), V[:, :2].max(0)
    # the pipeline runs straight in plan from (-24.5, 6) to (24.5, -1)
    p0, p1 = np.array([-24.5, 6.0]), np.array([24.5, -1.0])
    u = (p1 - p0) / np.linalg.norm(p1 - p0)
    d = p[:, :2] - p0
    assert np.all(a >= [-25, -2]) and np.all(b <= [25, 7])
    return np.abs(d[:, 0] * u[1] - d[:, 1] * u[0])


def test_dvl_over_the_wreck_sees_the_wreck(scene):
    wreck = scene.object("wreck")
    hull_c = wreck.mesh.vertices[:8].mean(0)
    top = wreck.mesh.vertices[8:].max(0)[2]
    V = _vehicle(scene)
    k = int(np.argmin(np.linalg.norm(V[:, :2, 3] - hull_c[:2], axis=1)))
    T = scene.T_W_D[k]
    assert np.linalg.norm(T[:2, 3] - hull_c[:2]) < 1.5
    r = DVLSimulator(scene).ranges(T)
    alt = np.nanmean(r) * math.cos(math.radians(22.5))
    seabed_alt = T[2, 3] - float(scene.seabed_z_m(*T[:2, 3]))
    assert alt < seabed_alt - 0.8  # the wreck stands ~1.6 m proud of the seabed
    assert alt > T[2, 3] - top - 0.05


def test_survey_sonar_sees_the_seabed(scene):
    spec = scene.sonar_spec
    V = _vehicle(scene)
    k = int(np.argmin(np.linalg.norm(V[:, :2, 3] - [-12.0, -2.5], axis=1)))  # mid-line
    with SonarSimulator(scene, seed=0, **scene.sonar_params) as sim:
        p = sim.ping(scene.T_W_S[k], k)
    assert p.image.shape == (spec.n_bins, spec.n_beams)
    # the seabed is in view from 3 to 8 m and mostly bright enough to detect
    r = np.linalg.norm(p.points_W - scene.T_W_S[k][:3, 3], axis=1)
    assert len(r) > 50_000 and r.min() > 2.5
    assert len(p.detected_W) > 0.5 * len(p.points_W)
    # the visible points away from the objects lie on the seabed
    q = p.points_W.astype(np.float64)
    off = np.ones(len(q), bool)
    Vr = scene.object("rocks").mesh.vertices.reshape(-1, 642, 3)
    for lo, hi in [scene.object("wreck").mesh.bounds, *np.stack([Vr.min(1), Vr.max(1)], 1)]:
        off &= np.any((q < lo - 0.1) | (q > hi + 0.1), axis=1)
    off &= _pipe_distance(scene, q) > 0.4
    assert off.sum() > 0.5 * len(q)
    dz = q[off, 2] - scene.seabed_z_m(q[off, 0], q[off, 1])
    assert np.percentile(np.abs(dz), 99) < 0.02, np.percentile(np.abs(dz), 99)


def test_demo_survey_reports_memory_and_sparse_maps_the_same(tmp_path):
    from maps import run_demo

    from gpumap.commands.demo import main

    args = ["--scene", "survey", "--voxel-size", "0.2", "--pings", "4", "--backend", "numpy", "--no-progress"]
    assert main([*args, "--out", str(tmp_path / "dense")]) == 0
    run_demo(args, tmp_path / "sparse", sparse=True)
    d, s = (json.loads((tmp_path / n / "metrics.json").read_text()) for n in ("dense", "sparse"))
    assert d["scene"] == "survey" and d["images"] == 4 and d["voxel_size_m"] == 0.2
    assert d["grid_shape"] == [250, 100, 15]
    md, ms = d["memory"], s["memory"]
    assert md["storage"] == "dense" and ms["storage"] == "sparse"
    assert md["map_bytes"] == md["dense_grid_bytes"] == 250 * 100 * 15 * 16
    assert md["dense_water_column_bytes"] == 250 * 100 * 23 * 16  # from 4.6 m down to the surface
    # the same pings into either storage: the same observed voxels and the same scores
    assert 0 < md["observed_voxels"] == ms["observed_voxels"] < 250 * 100 * 15
    assert ms["map_bytes"] == ms["sparse"]["total_bytes"]
    for key in ("false_negative_rate_detectable", "false_positive_rate_far", "miss_rate",
                "miss_rate_by_object", "observed_surface_fraction", "free_carved_fraction"):
        assert d[key] == s[key], key
    assert d["rules"]["plain"]["miss_rate"] == s["rules"]["plain"]["miss_rate"]
