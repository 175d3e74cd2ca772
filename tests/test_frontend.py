"""The EKF's front-end (issue #23): detection in the polar image, association, the loop."""

from __future__ import annotations

import json
import math
import warnings

import numpy as np
import pytest
from conftest import DATA, needs_data

import gpumap
from gpumap.ekf import SonarEKF
from gpumap.ekf.association import FeatureTracker
from gpumap.ekf.frontend import PointDetector, PointMeasurements
from gpumap.ekf.loop import drifting_odometry, motion_cov, pose_errors
from gpumap.lie import se3_exp
from gpumap.pipeline.ekf_replay import compare_maps


def _uneven_spec() -> gpumap.SonarSpec:
    # beams unevenly spaced (steps grow with |azimuth|), as real sonars have them
    u = np.linspace(-1.0, 1.0, 256)
    bearings = 0.9 * (u + 0.15 * u**3) / 1.15
    return gpumap.SonarSpec(0.1, 2.0, 400, bearings, math.radians(20))


def _blob_image(spec, points, rng, sigma_cells=(1.2, 1.5), amp=0.8):
    """Speckle floor plus Gaussian returns at exact (range, azimuth) positions."""
    img = rng.rayleigh(0.04, spec.image_shape).astype(np.float32)
    ii = np.arange(spec.n_bins)[:, None] + 0.5
    jj = np.arange(spec.n_beams)[None, :]
    for r, az in points:
        fi = (r - spec.range_min_m) / spec.bin_size_m
        fj = np.interp(az, spec.bearings_rad, np.arange(spec.n_beams))
        img += amp * np.exp(-0.5 * (((ii - fi) / sigma_cells[0]) ** 2 + ((jj - fj) / sigma_cells[1]) ** 2))
    return np.clip(img, 0, 1).astype(np.float32)


def test_point_at_known_range_azimuth_is_found_within_a_cell():
    spec = _uneven_spec()
    det = PointDetector(spec)
    rng = np.random.default_rng(3)
    # 0.4 cell off a cell's centre in range and in beam (the nearest centre is 0.4 cell away),
    # one where the beams are widest apart
    cells = [(130, 40), (240, 128), (330, 230)]
    truth = [(spec.range_min_m + (i + 0.9) * spec.bin_size_m,
              float(np.interp(j + 0.4, np.arange(spec.n_beams), spec.bearings_rad))) for i, j in cells]
    m = det.detect(_blob_image(spec, truth, rng))
    assert len(m) == 3
    step = np.gradient(spec.bearings_rad)
    for (r, az), (_, j) in zip(truth, cells, strict=True):
        k = int(np.argmin(np.hypot(m.ranges_m - r, m.bearings_rad - az)))
        assert abs(m.ranges_m[k] - r) < 0.2 * spec.bin_size_m  # sub-cell: well within the cell
        assert abs(m.bearings_rad[k] - az) < 0.2 * step[j]
        # the stated covariance covers the error (2-dof chi-square 99.9 %)
        e = np.array([m.ranges_m[k] - r, m.bearings_rad[k] - az])
        assert e @ np.linalg.solve(m.covs[k], e) < 13.8


def test_lines_and_arcs_are_not_points():
    spec = _uneven_spec()
    rng = np.random.default_rng(4)
    img = rng.rayleigh(0.04, spec.image_shape).astype(np.float32)
    img[200:203, 40:220] += 0.8  # an arc (one range across many beams): a wall or the floor's edge
    img[60:300, 100:102] += 0.8  # a radial line
    img = np.clip(img, 0, 1)
    assert len(PointDetector(spec).detect(img)) == 0
    img[120, 30] = 1.0  # a compact return next to them is still found
    img[119:122, 29:32] = np.maximum(img[119:122, 29:32], 0.7)
    assert len(PointDetector(spec).detect(img)) == 1


def test_detector_checks_its_input():
    spec = _uneven_spec()
    det = PointDetector(spec)
    with pytest.raises(ValueError, match=r"Expected an image of shape \(400, 256\)"):
        det.detect(np.zeros((256, 400), np.float32))
    with pytest.raises(TypeError, match="dtype int32"):
        det.detect(np.zeros((400, 256), np.int32))
    with pytest.raises(ValueError, match="ring_ratio"):
        PointDetector(spec, ring_ratio=0.0)


def _heave_scene(n=31):
    """The sonar heaves from z = -0.15 to 0.15 m looking along x: two points above and below its
    path have the same azimuth throughout and their ranges cross at z = 0."""
    spec = gpumap.SonarSpec.uniform(hfov_deg=130, vfov_deg=44, n_beams=256, n_bins=400,
                                    range_min_m=0.1, range_max_m=2.0)
    L = {1: np.array([1.0, 0.1, 0.2]), 2: np.array([1.0, 0.1, -0.2]), 3: np.array([1.3, -0.4, 0.02])}
    T = []
    for h in np.linspace(-0.15, 0.15, n):
        P = np.eye(4)
        P[2, 3] = h
        T.append(P)
    return spec, L, np.stack(T)


def _observe(T, L, ids, rng, sr, sb):
    z = []
    for i in ids:
        p = T[:3, :3].T @ (L[i] - T[:3, 3])
        z.append((np.linalg.norm(p) + rng.normal(0, sr), math.atan2(p[1], p[0]) + rng.normal(0, sb)))
    return np.array(z).reshape(-1, 2)


def _run_tracker(spec, L, T, extra=None, seed=0, **kw):
    rng = np.random.default_rng(seed)
    sr, sb = 0.003, math.radians(0.2)
    ekf = SonarEKF(T[0], np.zeros((6, 6)), range_sigma_m=sr, bearing_sigma_rad=sb, vfov_rad=spec.vfov_rad,
                   iterations=3)
    tr = FeatureTracker(ekf, spec, **kw)
    Q = motion_cov(0.002, 0.002)
    U, _ = drifting_odometry(T, 0.002, 0.002, seed)
    truth_of = []  # per ping: the true id of each return (-1: spurious)
    steps = []
    for k in range(len(T)):
        if k:
            ekf.predict(U[k], Q)
        ids = list(L)
        z = _observe(T[k], L, ids, rng, sr, sb)
        lab = list(ids)
        if extra is not None and k in extra:
            z = np.vstack([z, extra[k]])
            lab.append(-1)
        perm = rng.permutation(len(lab))
        covs = np.tile(np.diag([sr**2, sb**2]), (len(lab), 1, 1))
        st = tr.step(PointMeasurements.from_arrays(z[perm, 0], z[perm, 1], covs), Q if k else None)
        truth_of.append(np.array(lab)[perm])
        steps.append(st)
    return tr, ekf, steps, truth_of


def test_two_crossing_tracks_keep_their_ids():
    spec, L, T = _heave_scene()
    tr, ekf, steps, truth_of = _run_tracker(spec, L, T)
    # the two crossing points' ranges do meet (the test is not trivial)
    r1 = [np.linalg.norm(L[1] - P[:3, 3]) for P in T]
    r2 = [np.linalg.norm(L[2] - P[:3, 3]) for P in T]
    assert min(abs(a - b) for a, b in zip(r1, r2, strict=True)) < 0.003
    owner: dict[int, set] = {}
    for st, lab in zip(steps, truth_of, strict=True):
        for j, t in enumerate(st.labels):
            if t >= 0:
                owner.setdefault(int(t), set()).add(int(lab[j]))
    confirmed = [t for t in tr.tracks.values() if t.confirmed_at is not None]
    # every track only ever took returns of one point, and each point has one track
    assert all(len(owner[t.id]) == 1 for t in confirmed)
    assert sorted(next(iter(owner[t.id])) for t in confirmed) == [1, 2, 3]
    # the tracks live on through the crossing, under the ids they had before it
    for t in confirmed:
        assert t.confirmed_at < 5 and t.status == "confirmed" and t.last_seen == len(T) - 1
    assert set(ekf.landmark_ids) == {t.id for t in confirmed}
    for t in confirmed:  # and each one's estimate is its own point's
        assert np.linalg.norm(ekf.landmarks[t.id] - L[next(iter(owner[t.id]))]) < 0.05


def test_track_consistency_sees_a_swapped_return():
    from types import SimpleNamespace

    from gpumap.pipeline.ekf_replay import track_consistency

    spec, L, T = _heave_scene()
    tr, ekf, steps, truth_of = _run_tracker(spec, L, T)
    meas = [PointMeasurements.from_arrays(*_observe(T[k], L, list(truth_of[k]), np.random.default_rng(k),
                                                    0.003, math.radians(0.2)).T,
                                          np.tile(np.diag([0.003**2, math.radians(0.2) ** 2]), (3, 1, 1)))
            for k in range(len(T))]
    loop = SimpleNamespace(tracker=tr, measurements=meas)
    c = track_consistency(loop, T)
    assert c["tracks"] == 3 and c["consistent_fraction"] >= 0.97
    # one track's late returns taken from the other point: caught
    t = next(t for t in tr.tracks.values()
             if t.confirmed_at is not None and truth_of[t.returns[0][0]][t.returns[0][1]] == 1)
    other = {k: list(truth_of[k]).index(2) for k in range(len(T))}
    t.returns = [(k, j if k < 20 else other[k]) for k, j in t.returns]
    c2 = track_consistency(loop, T)
    assert c2["consistent_fraction"] < c["consistent_fraction"] - 0.05 and c2["tracks_all_consistent"] < 1


def test_a_spurious_return_does_not_start_a_track():
    spec, L, T = _heave_scene(12)
    L = {1: L[1]}
    spurious = {5: np.array([[1.5, -0.7]])}
    tr, ekf, steps, truth_of = _run_tracker(spec, L, T, extra=spurious)
    sp_track = int(steps[5].labels[list(truth_of[5]).index(-1)])
    assert sp_track in steps[5].started  # it was seen: a tentative track ...
    assert tr.tracks[sp_track].status == "dropped"  # ... that never confirmed
    assert sp_track not in ekf.landmark_ids and len(ekf.landmark_ids) == 1
    # the same return repeated from where the point really is does confirm (control)
    p_W = T[5][:3, :3] @ np.array([1.5 * math.cos(-0.7), 1.5 * math.sin(-0.7), 0.0]) + T[5][:3, 3]
    tr2, ekf2, _, _ = _run_tracker(spec, {**L, 2: p_W}, T)
    assert len(ekf2.landmark_ids) == 2


def test_update_with_per_return_covariances():
    spec, L, T = _heave_scene(3)
    sr, sb = 0.003, math.radians(0.2)

    def run(covs):
        ekf = SonarEKF(T[0], np.zeros((6, 6)), range_sigma_m=sr, bearing_sigma_rad=sb, vfov_rad=spec.vfov_rad)
        z = _observe(T[0], L, [1, 2, 3], np.random.default_rng(0), 0, 0)
        ekf.update([1, 2, 3], z[:, 0], z[:, 1])
        ekf.predict(np.eye(4) @ se3_exp(np.r_[0.0, 0.0, 0.02, 0, 0, 0]), motion_cov(0.01, 0.01))
        z = _observe(T[0], L, [1, 2, 3], np.random.default_rng(1), sr, sb)
        ekf.update([1, 2, 3], z[:, 0], z[:, 1], covs)
        return ekf.pose, ekf.pose_cov

    P0, C0 = run(None)
    P1, C1 = run(np.tile(np.diag([sr**2, sb**2]), (3, 1, 1)))
    np.testing.assert_allclose(P1, P0, atol=1e-12)
    np.testing.assert_allclose(C1, C0, atol=1e-15)
    P2, C2 = run(np.tile(np.diag([(10 * sr) ** 2, (10 * sb) ** 2]), (3, 1, 1)))
    assert np.trace(C2) > np.trace(C0)  # looser returns, looser pose
    with pytest.raises(ValueError, match=r"Expected shape \(3, 2, 2\) for 'covs'"):
        SonarEKF(T[0], np.zeros((6, 6)), range_sigma_m=sr, bearing_sigma_rad=sb,
                 vfov_rad=spec.vfov_rad).update([1, 2, 3], [1.0, 1.0, 1.0], [0.0, 0.1, 0.2], np.eye(2))


def test_drift_model_is_seeded_and_exact_without_noise():
    _, _, T = _heave_scene(8)
    U, T0 = drifting_odometry(T, 0.0, 0.0, 0)
    np.testing.assert_allclose(T0, T, atol=1e-12)
    _, Ta = drifting_odometry(T, 0.01, 0.02, 5)
    _, Tb = drifting_odometry(T, 0.01, 0.02, 5)
    np.testing.assert_array_equal(Ta, Tb)
    e = pose_errors(Ta, T)
    assert e["position_m"]["final"] > 0 and e["position_m"]["mean"] > 0
    assert pose_errors(T, T)["heading_rad"]["max"] == 0.0


def test_compare_maps_counts_unknown_as_not_occupied():
    ref = np.array([0.9, 0.9, 0.1, np.nan, 0.5])
    same = compare_maps(ref, ref, 0.4)
    assert same["disagree"] == 0 and same["fn"] == 0
    unknown = compare_maps(ref, np.full(5, np.nan), 0.4)
    assert unknown["fn_rate"] == 1.0 and unknown["disagree"] == 3  # leaving voxels unknown is no help
    c = compare_maps(ref, np.array([0.9, 0.1, 0.8, 0.9, 0.5]), 0.4)
    assert (c["fn"], c["fp"], c["disagree"]) == (1, 2, 3)


@needs_data
def test_replay_ekf_cli(tmp_path):
    from gpumap.commands.replay import main

    out = tmp_path / "o"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        rc = main([str(DATA / "oasis_tank"), "--ekf", "--odometry-noise", "0.005", "0.01",
                   "--max-frames", "16", "--out", str(out), "--quiet", "--backend", "numpy", "--seed", "3"])
    assert rc == 0
    s = json.loads((out / "summary.json").read_text())["ekf"]
    assert s["frames"] == 16 and s["drift_model"]["rot_sigma_rad"] == 0.01 and s["drift_model"]["seed"] == 3
    assert s["pose_error"]["odometry"]["position_m"]["mean"] > 0
    assert set(s["map_vs_recorded"]) == {"odometry", "ekf"}
    assert (out / "ekf_paths.png").stat().st_size > 0 and (out / "ekf_measurements.png").stat().st_size > 0
    assert main([str(DATA / "oasis_tank"), "--ekf", "--record", str(tmp_path / "r.rec"),
                 "--out", str(tmp_path / "x")]) == 2
