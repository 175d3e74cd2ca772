"""Simulator, DVL and ground truth against analytic references."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh
from gpumap.sim.dvl import DVLSimulator
from gpumap.sim.scenes import SceneObject, box_scene, make_scene, pose_from_xyz_ypr
from gpumap.sim.sonar import OCCUPIED_THRESHOLD, Ping, SonarSimulator, detected_points
from gpumap.sim.truth import ground_truth_masks, occupancy

import gpumap

SPEC = gpumap.SonarSpec.uniform(hfov_deg=130, vfov_deg=20, n_beams=256, n_bins=200,
                                range_min_m=0.1, range_max_m=2.0)
CLEAN = {"noise_floor": 0.0, "looks": 1e9}  # no additive noise, speckle ~ 1


def _sim(scene, **kw):
    return SonarSimulator(scene, spec=SPEC, **{**CLEAN, **kw})


def test_plane_lands_in_the_right_bins():
    d = 1.0
    scene = box_scene([((d + 0.05, 0.0, 0.0), (0.1, 6.0, 6.0))], spec=SPEC)
    with _sim(scene) as sim:
        img = sim.ping(np.eye(4)).image
    first = SPEC.bin_index(d)
    assert np.all(img[: first - 1] == 0), "returns nearer than the plane"
    # On the central beams the strongest return is the normal-incidence bin at range d.
    centre = np.flatnonzero(np.abs(SPEC.bearings_rad) < math.radians(5))
    peak = img[:, centre].argmax(axis=0)
    assert np.all(np.abs(peak - first) <= 1), (peak, first)
    # A beam at azimuth a first sees the plane at range d / cos(a).
    j = int(SPEC.beam_index(math.radians(40)))
    nz = np.flatnonzero(img[:, j] > 0)
    expect = SPEC.bin_index(d / math.cos(SPEC.bearings_rad[j]))
    assert abs(nz[0] - expect) <= 1


def test_small_sphere_lands_in_the_right_beam():
    az, r = math.radians(30.0), 1.2
    c = r * np.array([math.cos(az), math.sin(az), 0.0])
    scene = box_scene([((5, 5, 5), (0.01, 0.01, 0.01))], spec=SPEC)  # far away, out of range
    scene.objects.append(SceneObject("ball", trimesh.creation.icosphere(3, radius=0.02).apply_translation(c),
                                     "target"))
    with _sim(scene) as sim:
        img = sim.ping(np.eye(4)).image
    b, j = np.unravel_index(img.argmax(), img.shape)
    assert abs(int(j) - int(SPEC.beam_index(az))) <= 1
    assert abs(int(b) - int(SPEC.bin_index(r - 0.02))) <= 1
    # Nothing beyond a few beams from it.
    far = np.abs(np.arange(SPEC.n_beams) - j) > 4
    assert img[:, far].max() == 0


def test_shadowed_object_returns_nothing():
    target = ((1.5, 0.0, 0.0), (0.1, 0.1, 0.1))
    occluder = ((0.8, 0.0, 0.0), (0.05, 0.6, 1.2))  # covers +-20 deg az, +-37 deg el
    j = np.flatnonzero(np.abs(SPEC.bearings_rad) < math.radians(2))
    rows = slice(SPEC.bin_index(1.44), SPEC.bin_index(1.6))
    with _sim(box_scene([target], spec=SPEC)) as sim:
        alone = sim.ping(np.eye(4))
    assert alone.image[rows, j].max() > 0.1
    with _sim(box_scene([target, occluder], spec=SPEC)) as sim:
        shadowed = sim.ping(np.eye(4))
    assert shadowed.image[rows, j].max() == 0
    assert shadowed.image[SPEC.bin_index(0.775), j].max() > 0.1  # the occluder itself
    # The occluded target has no visible surface points either.
    assert np.all(shadowed.points_W[:, 0] < 1.0)


def test_seeds_reproduce():
    scene = make_scene("tank", voxel_size_m=0.06)
    T = scene.T_W_S[10]
    with SonarSimulator(scene, seed=3) as a:
        p1, p2 = a.ping(T, 5), a.ping(T, 5)
        p3 = a.ping(T, 6)
    with SonarSimulator(scene, seed=3) as b:
        q = b.ping(T, 5)
    assert np.array_equal(p1.image, p2.image) and np.array_equal(p1.image, q.image)
    assert not np.array_equal(p1.image, p3.image)
    assert p1.image.dtype == np.float32 and p1.image.shape == scene.sonar_spec.image_shape
    assert 0.0 <= p1.image.min() and p1.image.max() <= 1.0
    # Same scene twice (seeded geometry) -> same meshes.
    again = make_scene("tank", voxel_size_m=0.06)
    for o1, o2 in zip(scene.objects, again.objects, strict=True):
        assert np.array_equal(o1.mesh.vertices, o2.mesh.vertices)


def test_tank_features_are_visible_and_true():
    scene = make_scene("tank", voxel_size_m=0.06)
    with SonarSimulator(scene) as sim:
        p = sim.ping(scene.T_W_S[8], 8)
    assert len(p.feature_ids) >= 3
    k = np.searchsorted(scene.feature_ids, p.feature_ids)
    pol = scene.sonar_spec.to_polar((scene.features_W[k] - p.T_W_S[:3, 3]) @ p.T_W_S[:3, :3])
    np.testing.assert_allclose(p.feature_ranges_m, pol[:, 0])
    np.testing.assert_allclose(p.feature_bearings_rad, pol[:, 1])


@pytest.mark.parametrize("n_ring", [0, 6])
def test_dvl_hits_a_floor_at_the_right_ranges(n_ring):
    h = 0.7
    scene = box_scene([((0.0, 0.0, -h - 0.05), (20.0, 20.0, 0.1))])
    dvl = DVLSimulator(scene, n_ring=n_ring)
    T_W_D = pose_from_xyz_ypr(np.zeros(3), 0.3, math.pi / 2)  # axis straight down
    r = dvl.ranges(T_W_D)
    axis_range = h / math.cos(math.radians(22.5))
    if n_ring == 0:
        np.testing.assert_allclose(r, axis_range, rtol=1e-9)
    else:  # leading edge: the nearest ray of the 4.4 deg cone, at most 2.2 deg nearer vertical
        assert np.all(r < axis_range) and np.all(r >= h / math.cos(math.radians(22.5 - 2.2)) - 1e-9)
    pts = dvl.points_W(T_W_D, dvl.ranges(T_W_D))
    assert np.all(pts[:, 2] < 0)
    # Looking up: no surface -> NaN.
    assert np.all(np.isnan(dvl.ranges(pose_from_xyz_ypr(np.zeros(3), 0.0, -math.pi / 2))))


def test_truth_occupancy_of_an_analytic_box():
    s = 0.03
    lo, hi = np.array([0.015, -0.285, -0.165]), np.array([0.345, 0.105, 0.075])  # half-voxel offsets
    scene = box_scene([(tuple((lo + hi) / 2), tuple(hi - lo))], voxel_size_m=s)
    truth = occupancy(scene, samples_per_voxel=8)
    g = scene.grid
    c = g.all_centers()
    vlo, vhi = c - s / 2, c + s / 2
    expect = np.all((vhi > lo) & (vlo < hi), axis=-1)  # voxel cube meets the box
    assert truth.occupied.sum() == expect.sum()
    assert np.array_equal(truth.occupied, expect)
    assert np.all(truth.label[expect] == 0)


# ------------------------------------------------------------------------------ detectable truth
def test_plane_at_normal_incidence_is_detectable():
    scene = box_scene([((1.05, 0.0, 0.0), (0.1, 6.0, 6.0))], spec=SPEC)
    with _sim(scene) as sim:
        p = sim.ping(np.eye(4))
    assert p.clean_image.shape == p.image.shape and p.clean_image.dtype == np.float32
    assert len(p.ray_bins) == len(p.ray_beams) == len(p.points_W)
    # Without speckle and noise the image is the clean image.
    np.testing.assert_allclose(p.image, p.clean_image, atol=1e-4)
    det = detected_points(p, OCCUPIED_THRESHOLD)
    assert len(det) > 0 and len(det) <= len(p.points_W)
    assert np.array_equal(p.detected_W, det)
    # Detected points are visible points (rows of points_W) ...
    assert set(map(tuple, det.tolist())) <= set(map(tuple, p.points_W.tolist()))
    # ... and the points at normal incidence (straight ahead) are among them.
    ahead = det[np.hypot(det[:, 1], det[:, 2]) < 0.03]
    assert len(ahead) > 0 and np.allclose(ahead[:, 0], 1.0, atol=1e-3)
    # Each point's cell is where its range and azimuth put it.
    pol = SPEC.to_polar(p.points_W)
    assert np.all(np.abs(p.ray_bins - SPEC.bin_index(pol[:, 0])) <= 1)
    assert np.all(np.abs(p.ray_beams - SPEC.beam_index(pol[:, 1])) <= 1)
    # The threshold is on the clean image: nothing is brighter than 1, everything >= 0.
    assert len(detected_points(p, 1.01)) == 0
    assert len(detected_points(p, 0.0)) == len(p.points_W)


def test_ping_without_clean_image_has_no_detections():
    p = Ping(np.zeros(SPEC.image_shape, np.float32), np.eye(4), np.zeros((3, 3), np.float32),
             np.zeros(0, np.int64), np.zeros(0), np.zeros(0))
    with pytest.raises(ValueError, match="clean_image"):
        detected_points(p)


# ------------------------------------------------------------------------------ the circle scene
def _stations(scene):
    """(n_stations,) list of pose-index arrays, one per sonar position."""
    pos = np.round(scene.T_W_S[:, :3, 3], 9)
    _, inv = np.unique(pos, axis=0, return_inverse=True)
    return [np.flatnonzero(inv == s) for s in range(inv.max() + 1)]


def test_circle_scene_is_deterministic_per_seed():
    a, b = make_scene("circle", voxel_size_m=0.06, seed=1), make_scene("circle", voxel_size_m=0.06, seed=1)
    c = make_scene("circle", voxel_size_m=0.06, seed=2)
    assert a.object_names == b.object_names and a.object_names[0] == "sand"
    assert set(a.small_objects) == {"box", "rock", "pipe", "post"}
    for o1, o2 in zip(a.objects, b.objects, strict=True):
        assert np.array_equal(o1.mesh.vertices, o2.mesh.vertices)
    assert np.array_equal(a.T_W_S, b.T_W_S) and np.array_equal(a.features_W, b.features_W)
    assert not np.array_equal(a.object("sand").mesh.vertices, c.object("sand").mesh.vertices)
    assert not np.array_equal(a.object("rock").mesh.vertices, c.object("rock").mesh.vertices)
    # Features lie on surfaces: within 5 mm of each there is solid and there is water.
    assert a.feature_ids[0] == 100 and len(np.unique(a.feature_ids)) == len(a.feature_ids)
    steps = 0.005 * np.stack(np.meshgrid(*[[-1, 0, 1]] * 3, indexing="ij"), -1).reshape(-1, 3)
    for f in a.features_W:
        q = f + steps
        solid = np.logical_or.reduce([o.contains(q) for o in a.objects])
        assert solid.any() and not solid.all(), f
    # A valid SE(3) trajectory inside the grid.
    R = a.T_W_S[:, :3, :3]
    np.testing.assert_allclose(R @ R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    lo, hi = np.array(a.grid.min_corner_m), np.array(a.grid.max_corner_m)
    assert np.all((a.T_W_S[:, :3, 3] > lo) & (a.T_W_S[:, :3, 3] < hi))


def test_circle_stations_see_every_object_from_opposite_sides():
    scene = make_scene("circle", voxel_size_m=0.06)
    stations = _stations(scene)
    assert len(stations) == 5
    sp = scene.sonar_spec
    centres = {}
    for name in scene.small_objects:
        V = np.asarray(scene.object(name).mesh.vertices)
        centres[name] = V.mean(0)
        in_view = []
        for idx in stations:
            T = scene.T_W_S[idx]
            p_S = np.einsum("kji,knj->kni", T[:, :3, :3], V[None] - T[:, None, :3, 3])
            in_view.append(bool(sp.in_fov(p_S).any()))
        assert sum(in_view) >= (3 if name == "pipe" else 5), (name, in_view)
    # Every object is viewed from directions more than 120 deg apart.
    for name, c in centres.items():
        d = np.array([c[:2] - scene.T_W_S[idx[0], :2, 3] for idx in stations])
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        worst = np.degrees(np.arccos(np.clip((d @ d.T).min(), -1, 1)))
        assert worst > 120, (name, worst)
    # Each station pitches and rolls.
    for idx in stations:
        T = scene.T_W_S[idx]
        pitch = np.degrees(np.arcsin(-T[:, 2, 0]))  # boresight below the horizon
        roll = np.degrees(np.arctan2(T[:, 2, 1], T[:, 2, 2]))
        assert np.ptp(pitch) >= 20 and np.ptp(roll) >= 20


def test_circle_far_sides_are_shadowed_in_some_views():
    scene = make_scene("circle", voxel_size_m=0.03)
    truth = occupancy(scene)
    stations = _stations(scene)
    # One ping per station, looking at the objects level (roll = 0, pitched at the centre).
    roll = np.arctan2(scene.T_W_S[:, 2, 1], scene.T_W_S[:, 2, 2])
    sel = [idx[np.argmin(np.abs(roll[idx]))] for idx in stations]
    with _sim(scene) as sim:
        pings = [sim.ping(scene.T_W_S[k], k) for k in sel]
    seen, det = ground_truth_masks(pings, scene.grid, OCCUPIED_THRESHOLD)
    assert not np.any(det & ~seen), "detectable voxels must be seen"
    # Grazing sand far away is seen but too faint to detect.
    sand = truth.mask("sand")
    assert (seen & ~det & sand).sum() > 0
    # Every object is detected, and from no single station is all of it seen: its far side
    # is in the shadow of that view, and another view sees it.
    for name in scene.small_objects:
        m = truth.mask(name)
        assert (det & m).any(), name
        each = [ground_truth_masks([p], scene.grid)[0] & m for p in pings]
        union = np.logical_or.reduce(each)
        assert all((union & ~e).any() for e in each), name
