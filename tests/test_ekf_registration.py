"""Scan-to-local-map registration (gpumap.ekf.registration) against an analytic scene.

The scene: vertical walls (a room and a pillar) seen by a sonar whose imaging plane is the
world's horizontal plane, so each beam's first return is the ray cast of its bearing against
the walls' 2-D outline (independent of the code under test). Poses differ in-plane
(``x, y, yaw``) by known offsets; the out-of-plane components (``z``, roll, pitch) are what
the sonar cannot see.
"""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
from conftest import DATA, needs_data

import gpumap.ekf.registration as reg_mod
from gpumap.ekf.frontend import PointMeasurements
from gpumap.ekf.loop import drifting_odometry, motion_cov, pose_errors, run_ekf_loop
from gpumap.ekf.registrar import ScanRegistrar
from gpumap.ekf.registration import (
    fuse_revisit,
    fuse_step,
    image_agreement,
    image_descriptor,
    place_scores,
    plane_points,
    register_scan,
)
from gpumap.lie import se3_exp, se3_inverse, se3_log
from gpumap.spec import SonarSpec

SPEC = SonarSpec(range_min_m=0.1, range_max_m=2.0, n_bins=400,
                 bearings_rad=np.linspace(-np.deg2rad(60), np.deg2rad(60), 256), vfov_rad=np.deg2rad(20))

ROOM = np.array([[-0.5, -1.0], [1.6, -1.0], [1.6, 1.2], [-0.5, 1.2]])
PILLAR = np.array([[0.9, 0.3], [1.1, 0.3], [1.1, 0.5], [0.9, 0.5]])


def _segments() -> np.ndarray:
    segs = []
    for poly in (ROOM, PILLAR):
        for i in range(len(poly)):
            segs.append((poly[i], poly[(i + 1) % len(poly)]))
    return np.array(segs)  # (s, 2, 2)


def first_returns(T_W_S: np.ndarray, spec: SonarSpec = SPEC, segs=None) -> np.ndarray:
    """Ray cast of each beam (its bearing, in the sonar's plane = the world's horizontal plane)
    against vertical walls: the nearest hit, ``inf`` where none is in the range window."""
    segs = _segments() if segs is None else segs
    o = T_W_S[:2, 3]
    th = np.arctan2(T_W_S[1, 0], T_W_S[0, 0]) + spec.bearings_rad
    d = np.stack([np.cos(th), np.sin(th)], axis=1)  # (n, 2)
    a, b = segs[:, 0], segs[:, 1]
    e = b - a  # (s, 2)
    # o + t d = a + u e  ->  [d, -e] [t, u]^T = a - o
    den = d[:, None, 0] * (-e[None, :, 1]) - d[:, None, 1] * (-e[None, :, 0])
    w = a[None] - o  # (1, s, 2)
    t = (w[..., 0] * (-e[None, :, 1]) - w[..., 1] * (-e[None, :, 0])) / np.where(den == 0, np.nan, den)
    u = (d[:, None, 0] * w[..., 1] - d[:, None, 1] * w[..., 0]) / np.where(den == 0, np.nan, den)
    t = np.where((t > 0) & (u >= 0) & (u <= 1), t, np.inf)
    r = np.nanmin(t, axis=1)
    return np.where((r >= spec.range_min_m) & (r < spec.range_max_m), r, np.inf)


def pose(x: float, y: float, yaw: float, z: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    c, s = np.cos(yaw), np.sin(yaw)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:3, 3] = [x, y, z]
    return T


def _world(T: np.ndarray, pts_S: np.ndarray) -> np.ndarray:
    return pts_S @ T[:3, :3].T + T[:3, 3]


T0 = pose(0.2, 0.0, 0.1)
OFFSET = np.array([0.006, -0.004, 0.0, 0.0, 0.0, 0.012])  # in-plane: x, y, yaw


def _register(T_true, T_pred, map_pose=T0, **kw):
    pts = plane_points(first_returns(T_true), SPEC.bearings_rad)
    mp = _world(map_pose, plane_points(first_returns(map_pose), SPEC.bearings_rad))
    return register_scan(pts, mp, T_pred, vfov_rad=SPEC.vfov_rad, **kw)


def test_recovers_the_in_plane_offset_and_reports_the_rest_unobserved():
    T_true = T0 @ se3_exp(OFFSET)
    r = _register(T_true, T0)
    assert r is not None and r.observed == 3
    want = se3_log(se3_inverse(T0) @ T_true)
    np.testing.assert_allclose(r.delta[[0, 1, 5]], want[[0, 1, 5]], atol=5e-4)
    # elevation directions: no correction, no information
    assert np.all(r.delta[[2, 3, 4]] == 0)
    assert np.all(r.info[[2, 3, 4], :] == 0) and np.all(r.info[:, [2, 3, 4]] == 0)
    assert np.allclose(r.basis[:, [2, 3, 4]], 0)
    # the registered pose is closer to the truth than the prediction, in every observed direction
    after = se3_log(se3_inverse(T0 @ se3_exp(r.delta)) @ T_true)
    assert np.all(np.abs(after[[0, 1, 5]]) < 0.2 * np.abs(want[[0, 1, 5]]))


def test_out_of_plane_offset_is_not_mistaken_for_in_plane_motion():
    # the true pose differs only in height: the walls look the same, nothing in-plane moves
    T_true = T0 @ se3_exp(np.array([0.0, 0.0, 0.03, 0.0, 0.0, 0.0]))
    r = _register(T_true, T0)
    assert r is not None
    assert np.abs(r.delta).max() < 2e-4


def test_one_wall_observes_its_normal_not_the_slide_along_it():
    wall = np.array([[[1.2, -3.0], [1.2, 3.0]]])  # x = 1.2, the only surface
    Tm = pose(0.0, 0.0, 0.0)
    seen = lambda T: plane_points(first_returns(T, SPEC, wall), SPEC.bearings_rad)  # noqa: E731
    T_true = Tm @ se3_exp(np.array([0.01, 0.02, 0, 0, 0, 0]))
    r = register_scan(seen(T_true), _world(Tm, seen(Tm)), Tm, vfov_rad=SPEC.vfov_rad)
    assert r is not None
    along_wall = np.array([0, 1.0, 0, 0, 0, 0])
    assert np.abs(r.basis @ along_wall).max() < 1e-3  # projected out: no information along y
    assert abs(r.delta[1]) < 1e-6
    assert abs(r.delta[0] - 0.01) < 1e-3  # the distance to the wall is measured


def test_a_ping_that_shows_nothing_never_moves_the_pose():
    assert register_scan(np.zeros((0, 3)), np.zeros((0, 3)), T0, vfov_rad=SPEC.vfov_rad) is None
    mp = _world(T0, plane_points(first_returns(T0), SPEC.bearings_rad))
    assert register_scan(np.zeros((0, 3)), mp, T0, vfov_rad=SPEC.vfov_rad) is None
    ranges = np.stack([first_returns(T0), np.full(SPEC.n_beams, np.inf)])
    rg = ScanRegistrar(SPEC, ranges=ranges, step=True, revisit=True, min_gap=1, min_image_ncc=None)
    Q = motion_cov(0.005, 0.005)
    U = se3_exp(np.array([0.01, 0.0, 0.0, 0.0, 0.0, 0.02]))
    rg.correct_step(0, None, T0, np.eye(4), Q)
    rg.remember(T0)
    Un, Qn = rg.correct_step(1, None, T0, U, Q)
    assert Un is U and Qn is Q  # exactly the odometry step


def test_map_points_outside_the_vertical_aperture_are_ignored():
    # a ghost of the walls 0.5 m above the fan (elevation > 17 deg): the sonar cannot see it,
    # but projected onto the imaging plane it lies exactly where the new returns fall at the
    # predicted pose; a registration that matched it would stay at the prediction
    T_true = T0 @ se3_exp(OFFSET)
    pts = plane_points(first_returns(T_true), SPEC.bearings_rad)
    walls = _world(T0, plane_points(first_returns(T0), SPEC.bearings_rad))
    ghost = _world(T0, pts + np.array([0.0, 0.0, 0.5]))
    mp = np.concatenate([walls, ghost])
    want = se3_log(se3_inverse(T0) @ T_true)[[0, 1, 5]]
    r = register_scan(pts, mp, T0, vfov_rad=SPEC.vfov_rad)
    np.testing.assert_allclose(r.delta[[0, 1, 5]], want, atol=5e-4)


def test_mutant_ignoring_the_aperture_fails(monkeypatch):
    """The test above kills a mutant that matches every map point, seen or not."""
    monkeypatch.setattr(reg_mod, "_map_in_plane",
                        lambda m, T, h: ((m - T[:3, 3]) @ T[:3, :3])[:, :2])
    with pytest.raises(AssertionError):
        test_map_points_outside_the_vertical_aperture_are_ignored()


def test_mutant_with_the_wrong_sign_of_the_correction_fails(monkeypatch):
    orig = reg_mod.register_scan

    def flipped(*a, **k):
        r = orig(*a, **k)
        return reg_mod.ScanRegistration(-r.delta, r.info, r.basis, r.returns, r.rms_m)

    monkeypatch.setattr(reg_mod, "register_scan", flipped)
    monkeypatch.setitem(globals(), "register_scan", flipped)
    with pytest.raises(AssertionError):
        test_recovers_the_in_plane_offset_and_reports_the_rest_unobserved()


def test_fuse_step_corrects_only_the_observed_directions():
    rng = np.random.default_rng(3)
    Q = motion_cov(0.005, 0.005)
    U_true = se3_exp(np.array([0.006, 0.002, 0.001, 0.01, -0.01, 0.02]))
    w = rng.normal(0, 0.005, 6)
    U = U_true @ se3_exp(w)  # odometry: the true step plus noise
    T_prev = pose(0.3, -0.1, 0.2)
    delta = se3_log(se3_inverse(T_prev @ U) @ (T_prev @ U_true))
    idx = [0, 1, 5]
    basis = np.zeros((3, 6))
    basis[[0, 1, 2], idx] = 1.0
    info = np.zeros((6, 6))
    info[idx, idx] = 1e8  # 0.1 mm, 0.1 mrad
    d = np.zeros(6)
    d[idx] = delta[idx]
    r = reg_mod.ScanRegistration(d, info, basis, 200, 0.001)
    Un, Qn, nis, fused = fuse_step(U, Q, r, gate=None)
    assert fused and nis > 0
    err_before = se3_log(se3_inverse(U) @ U_true)
    err_after = se3_log(se3_inverse(Un) @ U_true)
    assert np.all(np.abs(err_after[idx]) < 0.05 * np.abs(err_before[idx]) + 1e-5)
    np.testing.assert_allclose(err_after[[2, 3, 4]], err_before[[2, 3, 4]], atol=1e-4)
    assert np.all(np.diag(Qn)[idx] < 1e-3 * np.diag(Q)[idx])
    np.testing.assert_allclose(np.diag(Qn)[[2, 3, 4]], np.diag(Q)[[2, 3, 4]], rtol=1e-9)
    # the gate: an innovation 100 sigma away is refused and the step is odometry's
    far = reg_mod.ScanRegistration(d + 0.5 * np.array([1, 1, 0, 0, 0, 1.0]), info, basis, 200, 0.001)
    Uf, Qf, _, fused = fuse_step(U, Q, far, gate=16.3)
    assert not fused and Uf is U and Qf is Q


def test_fuse_revisit_returns_to_the_old_pose_against_the_drift():
    T_j = pose(0.4, 0.2, 0.3)
    drift = np.array([0.05, -0.03, 0.02, 0.02, -0.03, 0.04])
    T_pred = T_j @ se3_exp(drift)  # the same place, after drifting
    D = np.diag([0.04 ** 2] * 3 + [0.04 ** 2] * 3)
    R = np.diag([1e-6] * 3 + [1e-6] * 3)
    d, post, nis, fused = fuse_revisit(T_pred, D, T_j, np.zeros((6, 6)), np.zeros(6), R, gate=None)
    assert fused
    back = se3_log(se3_inverse(T_pred @ se3_exp(d)) @ T_j)
    assert np.abs(back).max() < 0.02 * np.abs(drift).max()
    assert np.all(np.diag(post) < 0.01 * np.diag(D))
    # the old pose's own error is carried into the new one, so only the drift since counts:
    # with the old pose as uncertain as the drift the correction still goes all the way ...
    d2, _, _, _ = fuse_revisit(T_pred, 2 * D, T_j, D, np.zeros(6), R, gate=None)
    assert 0.95 < np.linalg.norm(d2) / np.linalg.norm(d) < 1.05
    # ... and a measurement as noisy as the drift takes it half way
    d3, _, _, _ = fuse_revisit(T_pred, 2 * D, T_j, D, np.zeros(6), D, gate=None)
    assert 0.4 < np.linalg.norm(d3) / np.linalg.norm(d) < 0.6
    # refused by the gate when the drift cannot explain the innovation
    _, p3, _, fused = fuse_revisit(T_pred, 1e-6 * np.eye(6), T_j, np.zeros((6, 6)), np.zeros(6), R, gate=22.5)
    assert not fused and np.array_equal(p3, 1e-6 * np.eye(6))


def test_place_scores_find_the_same_place():
    a = first_returns(pose(0.2, 0.0, 0.1))
    db = np.stack([first_returns(pose(0.5, 0.3, 1.0)), a + 0.001, first_returns(pose(0.0, -0.2, -0.4))])
    s = place_scores(a, db)
    assert int(np.argmin(s)) == 1 and s[1] < 0.002


def _loop(ranges, U, T_start, registrar):
    empty = PointMeasurements(np.zeros(0), np.zeros(0), np.zeros((0, 2, 2)), *(np.zeros(0) for _ in range(4)))
    return run_ekf_loop([None] * len(U), U, T_start, SPEC, odometry_cov=motion_cov(0.004, 0.004),
                        measure=lambda k, _i: empty, registrar=registrar)


def test_the_loop_with_registration_beats_drifting_odometry_in_plane():
    # a path through the room with only in-plane motion: what the ping sees fixes the drift
    n = 60
    s = np.linspace(0, 1, n)
    T_true = np.stack([pose(0.1 + 0.3 * t, -0.1 + 0.2 * np.sin(3 * t), 0.3 * np.sin(2 * t)) for t in s])
    ranges = np.stack([first_returns(T) for T in T_true])
    ratios = []
    for seed in range(3):
        U, T_odo = drifting_odometry(T_true, 0.004, 0.004, seed)
        # the analytic scene's returns are exact and their errors independent: weight them as
        # such (the default corr_beams is the real tank's, whose errors are shared by neighbours)
        loop = _loop(ranges, U, T_true[0], ScanRegistrar(SPEC, ranges=ranges, step=True, revisit=False,
                                                         corr_beams=8.0))
        eo, ee = pose_errors(T_odo, T_true), pose_errors(loop.poses, T_true)
        ratios.append(ee["position_m"]["mean"] / eo["position_m"]["mean"])
    assert max(ratios) < 0.9, ratios


@needs_data
@pytest.mark.parametrize("off", [False, True])
def test_replay_ekf_says_how_much_it_trusted_the_registration(tmp_path, capsys, off) -> None:
    from gpumap.commands.replay import main

    out = tmp_path / "o"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        rc = main([str(DATA / "oasis_tank"), "--ekf", "--max-frames", "12", "--out", str(out),
                   "--backend", "numpy", "--no-pictures", "--no-progress"]
                  + ([] if off else ["--ekf-registration"]))
    assert rc == 0
    r = json.loads((out / "summary.json").read_text())["ekf"]["registration"]
    assert r["used"] is (not off)
    if not off:
        assert r["pings"] == 12 and 0.0 <= r["fused_share"] <= 1.0
        for k in ("registered", "fused", "gated", "distrusted", "revisits", "revisits_fused",
                  "revisits_unverified"):
            assert k in r
    line = capsys.readouterr().out
    assert ("scan registration off" in line) is off and ("scan registration corrected" in line) is (not off)


def _out_and_back(n: int = 40):
    """Out along a path and back along the same poses; each pose's image descriptor a random unit
    vector, the same for a pose and its revisit (the images of one place agree)."""
    s = np.linspace(0, 1, n)
    out = [pose(0.1 + 0.3 * t, -0.1 + 0.2 * np.sin(3 * t), 0.3 * np.sin(2 * t)) for t in s]
    T_true = np.stack(out + out[::-1])
    ranges = np.stack([first_returns(T) for T in T_true])
    d = np.random.default_rng(7).normal(size=(n, 64))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return T_true, ranges, np.concatenate([d, d[::-1]]).astype(np.float32)


def test_a_revisit_brings_the_pose_back():
    _revisit_brings_the_pose_back(graph=True)


def test_a_revisit_brings_the_pose_back_without_the_graph():
    _revisit_brings_the_pose_back(graph=False)


def _revisit_brings_the_pose_back(graph: bool):
    # on the way back every ping matches one of the way out (first returns and image), and the
    # drift gathered since is taken out (by the filter alone, or with the pose graph behind it)
    n = 40
    T_true, ranges, desc = _out_and_back(n)
    gains = []
    for seed in range(3):
        U, T_odo = drifting_odometry(T_true, 0.004, 0.004, seed)
        rg = ScanRegistrar(SPEC, ranges=ranges, descriptors=desc, min_gap=10, graph=graph)
        loop = _loop(ranges, U, T_true[0], rg)
        back = slice(n + n // 2, 2 * n)  # the second half of the way back
        eo = np.linalg.norm(T_odo[back, :3, 3] - T_true[back, :3, 3], axis=1).mean()
        ee = np.linalg.norm(loop.poses[back, :3, 3] - T_true[back, :3, 3], axis=1).mean()
        gains.append(ee / eo)
        assert rg.stats.revisits_fused > 0 and (rg.solves > 0) is graph
    assert max(gains) < 0.5, gains


def test_mutant_revisit_with_the_wrong_sign_fails(monkeypatch):
    orig = reg_mod.fuse_revisit

    def flipped(*a, **k):
        d, post, nis, fused = orig(*a, **k)
        return -d, post, nis, fused

    import gpumap.ekf.registrar as registrar_mod  # the registrar calls it from there

    monkeypatch.setattr(reg_mod, "fuse_revisit", flipped)
    monkeypatch.setattr(registrar_mod, "fuse_revisit", flipped)
    with pytest.raises(AssertionError):
        test_a_revisit_brings_the_pose_back()


def test_a_place_whose_image_disagrees_is_no_revisit():
    # the same first returns, but every ping's image unlike every other's (another attitude):
    # nothing is fused, and the pose is the odometry's exactly
    T_true, ranges, desc = _out_and_back(40)
    other = np.random.default_rng(8).normal(size=desc.shape)
    other = (other / np.linalg.norm(other, axis=1, keepdims=True)).astype(np.float32)
    U, T_odo = drifting_odometry(T_true, 0.004, 0.004, 0)
    rg = ScanRegistrar(SPEC, ranges=ranges, descriptors=other, min_gap=10)
    loop = _loop(ranges, U, T_true[0], rg)
    assert rg.stats.revisits_fused == 0 and rg.stats.revisits_unverified > 0 and rg.closures == []
    np.testing.assert_allclose(loop.poses, T_odo, atol=1e-9)
    # without the verification the same pings are fused (the check is what refused them)
    rg = ScanRegistrar(SPEC, ranges=ranges, descriptors=other, min_gap=10, min_image_ncc=None)
    _loop(ranges, U, T_true[0], rg)
    assert rg.stats.revisits_fused > 0


def test_of_the_matching_places_the_one_whose_image_agrees_is_taken():
    # two stored pings with the same first returns; only the second one's image is the new ping's
    T = pose(0.2, 0.0, 0.1)
    r = first_returns(T)
    ranges = np.stack([r, r, np.full_like(r, np.inf), r])
    d = np.eye(4, 16, dtype=np.float32)
    desc = np.stack([d[0], d[1], d[2], d[1]])
    rg = ScanRegistrar(SPEC, ranges=ranges, descriptors=desc, min_gap=1)
    Q = motion_cov(0.004, 0.004)
    for k in range(3):
        rg.correct_step(k, None, T, np.eye(4), Q)
        rg.remember(T)
    rg.correct_step(3, None, T, np.eye(4), Q)
    assert rg.last_revisit == 1 and [c[:2] for c in rg.closures] == [(3, 1)]


def test_image_descriptor_is_the_same_for_uint8_and_float_and_agrees_with_itself():
    rng = np.random.default_rng(3)
    img = rng.integers(0, 256, size=(398, 512)).astype(np.uint8)
    a = image_descriptor(img)
    b = image_descriptor(img.astype(np.float32) / 255.0)
    assert a.shape == (49 * 64,) and a.dtype == np.float32
    np.testing.assert_allclose(a, b, atol=1e-6)
    assert abs(float(np.linalg.norm(a)) - 1.0) < 1e-5 and abs(float(a.mean())) < 1e-6
    # block means by brute force: the first block and the last whole one
    m = img[:392, :512].astype(np.float64).reshape(49, 8, 64, 8).mean(axis=(1, 3)).ravel()
    m = (m - m.mean()) / np.linalg.norm(m - m.mean())
    np.testing.assert_allclose(a, m, atol=1e-6)
    other = image_descriptor(rng.integers(0, 256, size=(398, 512)).astype(np.uint8))
    agree = image_agreement(a, np.stack([a, other, -a]))
    np.testing.assert_allclose(agree[[0, 2]], [1.0, -1.0], atol=1e-5)
    assert abs(agree[1]) < 0.1
    with pytest.raises(ValueError, match="2D"):
        image_descriptor(np.zeros(5))
    assert not np.any(image_descriptor(np.ones((16, 16))))  # a constant image: no pattern


def test_a_revisit_without_an_image_says_what_it_needs():
    r = first_returns(pose(0.2, 0.0, 0.1))
    rg = ScanRegistrar(SPEC, ranges=r[None])
    with pytest.raises(ValueError, match="min_image_ncc=None"):
        rg.correct_step(0, None, np.eye(4), np.eye(4), motion_cov(0.004, 0.004))
