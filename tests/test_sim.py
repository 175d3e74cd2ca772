"""Simulator, DVL and ground truth against analytic references."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh
from gpumap.sim.dvl import DVLSimulator
from gpumap.sim.scenes import SceneObject, box_scene, make_scene, pose_from_xyz_ypr
from gpumap.sim.sonar import SonarSimulator
from gpumap.sim.truth import occupancy

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
