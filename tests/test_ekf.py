"""Tests of the sonar EKF against independent references: finite differences, Monte Carlo,
a dense textbook EKF step, chi-square bounds, and invariances."""

from __future__ import annotations

import copy
import dataclasses

import numpy as np
import pytest
import scipy.linalg
from gpumap.sim.prism import (
    PrismConfig,
    measure,
    nees,
    pose_error,
    prism_vertices,
    run_filter,
    run_odometry,
    simulate,
)
from scipy.stats import chi2

from gpumap.ekf import (
    SonarEKF,
    anchor_jacobian,
    motion_jacobian,
    observation_model,
    plane_range_model,
    spherical_point,
    triangulate,
    wrap_angle,
)
from gpumap.lie import (
    hat,
    rotation_from_rpy,
    rpy_from_rotation,
    se3_adjoint,
    se3_exp,
    se3_inverse,
    se3_log,
    so3_exp,
    so3_log,
)

VFOV = np.deg2rad(14.0)


def _sph(p: np.ndarray) -> np.ndarray:
    return np.array([np.linalg.norm(p), np.arctan2(p[1], p[0]), np.arctan2(p[2], np.hypot(p[0], p[1]))])


def _assert_healthy(ekf: SonarEKF) -> None:
    P = ekf.native_covariance
    assert np.all(np.isfinite(P))
    assert np.all(np.isfinite(ekf.pose))
    assert all(np.all(np.isfinite(v)) for v in ekf.landmarks.values())
    np.testing.assert_array_equal(P, P.T)
    lam = np.linalg.eigvalsh(P)
    assert lam.min() >= -1e-10 * max(lam.max(), 1e-300), (lam.min(), lam.max())
    R = ekf.pose[:3, :3]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)


def _snapshot(ekf: SonarEKF) -> dict:
    return copy.deepcopy(ekf.__dict__)


def _assert_same_state(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for k in a:
        if isinstance(a[k], np.ndarray):
            np.testing.assert_array_equal(a[k], b[k], err_msg=k)
        else:
            assert a[k] == b[k], k


# --------------------------------------------------------------------------- Lie helpers
@pytest.mark.parametrize("angle", [0.0, 1e-9, 1e-4, 0.3, 2.0, np.pi - 1e-6, np.pi])
def test_se3_exp_matches_matrix_exponential_and_log_inverts(angle: float) -> None:
    rng = np.random.default_rng(1)
    xi = rng.normal(size=6)
    ax = xi[3:] / np.linalg.norm(xi[3:])
    xi[3:] = angle * ax
    M = np.zeros((4, 4))
    M[:3, :3] = hat(xi[3:])
    M[:3, 3] = xi[:3]
    T = se3_exp(xi)
    np.testing.assert_allclose(T, scipy.linalg.expm(M), atol=1e-12)
    # Log(Exp(x)) == x (at pi the axis sign is ambiguous: compare transforms).
    np.testing.assert_allclose(se3_exp(se3_log(T)), T, atol=1e-9)
    if angle < np.pi - 1e-3:
        np.testing.assert_allclose(se3_log(T), xi, atol=1e-9)
    np.testing.assert_allclose(so3_exp(so3_log(T[:3, :3])), T[:3, :3], atol=1e-9)


def test_adjoint_moves_twists_through_transforms() -> None:
    rng = np.random.default_rng(2)
    T = se3_exp(rng.normal(size=6))
    x = 0.4 * rng.normal(size=6)
    np.testing.assert_allclose(T @ se3_exp(x) @ se3_inverse(T), se3_exp(se3_adjoint(T) @ x), atol=1e-12)


@pytest.mark.parametrize("pitch", [np.pi / 2, -np.pi / 2, np.pi / 2 - 1e-7, 0.3])
def test_rpy_output_is_finite_and_reproduces_the_rotation(pitch: float) -> None:
    R = rotation_from_rpy(0.2, pitch, -0.7)
    rpy = rpy_from_rotation(R)
    assert np.all(np.isfinite(rpy))
    np.testing.assert_allclose(rotation_from_rpy(*rpy), R, atol=1e-6)


# --------------------------------------------------------------------------- Jacobians
def _num_jac(f, x0: np.ndarray, eps: float = 1e-6) -> np.ndarray:
    cols = []
    for i in range(x0.size):
        d = np.zeros_like(x0)
        d[i] = eps
        cols.append((f(x0 + d) - f(x0 - d)) / (2 * eps))
    return np.stack(cols, axis=-1)


POINTS_S = [
    np.array([2.5, 0.1, -0.2]),  # ordinary
    np.array([0.05, 0.04, 0.002]),  # very short range, azimuth ~ 39 deg
    np.array([1.0, 1.6, 0.1]),  # azimuth ~ 58 deg (edge of a 130 deg fan)
    np.array([-2.0, 1e-3, 0.3]),  # azimuth near pi (wrap)
]


@pytest.mark.parametrize("p_S", POINTS_S)
def test_observation_jacobians_match_finite_differences(p_S: np.ndarray) -> None:
    rng = np.random.default_rng(3)
    T = se3_exp(rng.normal(size=6))
    l_W = T[:3, :3] @ p_S + T[:3, 3]
    z, Hp, Hl = observation_model(T, l_W)
    np.testing.assert_allclose(z, [np.linalg.norm(p_S), np.arctan2(p_S[1], p_S[0])], atol=1e-12)

    def h_pose(d):
        zz = observation_model(T @ se3_exp(d), l_W)[0]
        return np.array([zz[0], float(wrap_angle(zz[1] - z[1]))])

    def h_l(x):
        zz = observation_model(T, x)[0]
        return np.array([zz[0], float(wrap_angle(zz[1] - z[1]))])

    scale = np.linalg.norm(p_S)
    np.testing.assert_allclose(Hp, _num_jac(h_pose, np.zeros(6), 1e-7 * scale), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(Hl, _num_jac(h_l, l_W, 1e-7 * scale), rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize(
    "s", [np.array([2.5, 0.1, 0.05]), np.array([0.05, -1.0, -0.12]), np.array([3.0, 3.1, 0.0])]
)
def test_spherical_and_anchor_jacobians_match_finite_differences(s: np.ndarray) -> None:
    p, D = spherical_point(s)
    np.testing.assert_allclose(_sph(p), [s[0], s[1], s[2]], atol=1e-12)
    np.testing.assert_allclose(D, _num_jac(lambda x: spherical_point(x)[0], s), rtol=1e-6, atol=1e-8)

    def s_of_delta(d):
        out = _sph(se3_exp(d)[:3, :3] @ p + se3_exp(d)[:3, 3])
        out[1] = s[1] + float(wrap_angle(out[1] - s[1]))
        return out

    np.testing.assert_allclose(
        anchor_jacobian(s), _num_jac(s_of_delta, np.zeros(6), 1e-7), rtol=1e-5, atol=1e-6
    )


def test_motion_jacobian_matches_finite_differences() -> None:
    rng = np.random.default_rng(4)
    T, U = se3_exp(rng.normal(size=6)), se3_exp(rng.normal(size=6))
    Tn = T @ U
    F = _num_jac(lambda d: se3_log(se3_inverse(Tn) @ T @ se3_exp(d) @ U), np.zeros(6))
    np.testing.assert_allclose(motion_jacobian(U), F, atol=1e-7)


# --------------------------------------------------------------------------- one step vs references
#: The plain (first-order, single-pass) EKF step, for comparison with the textbook formulas.
PLAIN = dict(second_order=False, relinearize_iterations=1)


def _filter_with_features(seed: int = 5, pose_sigma: float = 0.05, **kw) -> tuple[SonarEKF, np.ndarray]:
    rng = np.random.default_rng(seed)
    pts = prism_vertices()
    ekf = SonarEKF(np.eye(4), np.zeros((6, 6)), range_sigma_m=0.01, bearing_sigma_rad=0.005,
                   vfov_rad=VFOV, **(PLAIN | kw))
    ekf.predict(np.eye(4), np.diag([pose_sigma**2] * 3 + [(pose_sigma / 3) ** 2] * 3))
    ids, r, b = measure(np.eye(4), pts, rng, 0.01, 0.005)
    ekf.update(ids, r, b)
    U = se3_exp(np.array([0.05, 0.2, 0.1, 0.3, 0.02, -0.05]))
    ekf.predict(U, np.diag([1e-4] * 3 + [1e-4] * 3))
    return ekf, pts


def test_update_matches_a_dense_textbook_ekf_with_numerical_jacobians() -> None:
    ekf, pts = _filter_with_features()
    T0 = ekf.pose
    P0 = ekf.native_covariance
    anchors = ekf.landmark_anchors
    order = ekf.landmark_ids
    rng = np.random.default_rng(6)
    ids, r, b = measure(T0 @ se3_exp(np.array([0.01, 0, 0, 0, 0.01, 0])), pts, rng, 0.01, 0.005)

    def h(x):  # full measurement vector of the error state x = (delta, ds_1..ds_n)
        T = T0 @ se3_exp(x[:6])
        out = []
        for i in ids:
            Ta, s = anchors[i]
            k = order.index(i)
            p = spherical_point(s + x[6 + 3 * k : 9 + 3 * k])[0]
            q = se3_inverse(T) @ (Ta @ np.r_[p, 1.0])
            out += [np.linalg.norm(q[:3]), np.arctan2(q[1], q[0])]
        return np.array(out)

    x0 = np.zeros(P0.shape[0])
    H = _num_jac(h, x0, 1e-7)
    z = np.ravel(np.column_stack([r, b]))
    nu = z - h(x0)
    nu[1::2] = wrap_angle(nu[1::2])
    Rm = np.diag(np.tile([0.01**2, 0.005**2], len(ids)))
    S = H @ P0 @ H.T + Rm
    K = np.linalg.solve(S, H @ P0).T
    dx = K @ nu
    P_ref = (np.eye(x0.size) - K @ H) @ P0
    G = np.eye(x0.size)
    ad = np.zeros((6, 6))
    ad[:3, :3] = ad[3:, 3:] = hat(dx[3:6])
    ad[:3, 3:] = hat(dx[:3])
    G[:6, :6] -= 0.5 * ad
    P_ref = G @ P_ref @ G.T

    res = ekf.update(ids, r, b)
    assert res.accepted_ids == tuple(int(i) for i in ids) and not res.rejected
    np.testing.assert_allclose(ekf.pose, T0 @ se3_exp(dx[:6]), atol=1e-8)
    np.testing.assert_allclose(ekf.native_covariance, 0.5 * (P_ref + P_ref.T), atol=1e-9, rtol=1e-5)
    np.testing.assert_allclose(res.nis, nu @ np.linalg.solve(S, nu), rtol=1e-5)
    _assert_healthy(ekf)


def test_iterated_update_matches_dense_gauss_newton_with_numerical_jacobians() -> None:
    """Iterated EKF: x_{i+1} = K_i (z - h(x_i) + H_i x_i), H_i by finite differences at x_i."""
    ekf, pts = _filter_with_features()
    it_ekf = SonarEKF(np.eye(4), np.zeros((6, 6)), range_sigma_m=0.01, bearing_sigma_rad=0.005,
                      vfov_rad=VFOV, iterations=8, **PLAIN)
    it_ekf.__dict__.update(copy.deepcopy({k: v for k, v in ekf.__dict__.items() if k != "iterations"}))
    T0, P0 = ekf.pose, ekf.native_covariance
    anchors, order = ekf.landmark_anchors, ekf.landmark_ids
    rng = np.random.default_rng(6)
    ids, r, b = measure(T0 @ se3_exp(np.array([0.02, 0, 0, 0, 0.02, 0])), pts, rng, 0.01, 0.005)

    def h(x):
        T = T0 @ se3_exp(x[:6])
        out = []
        for i in ids:
            Ta, s = anchors[i]
            k = order.index(i)
            q = se3_inverse(T) @ (Ta @ np.r_[spherical_point(s + x[6 + 3 * k : 9 + 3 * k])[0], 1.0])
            out += [np.linalg.norm(q[:3]), np.arctan2(q[1], q[0])]
        return np.array(out)

    z = np.ravel(np.column_stack([r, b]))
    Rm = np.diag(np.tile([0.01**2, 0.005**2], len(ids)))
    x = np.zeros(P0.shape[0])
    for _ in range(8):
        H = _num_jac(h, x, 1e-7)
        nu = z - h(x)
        nu[1::2] = wrap_angle(nu[1::2])
        K = np.linalg.solve(H @ P0 @ H.T + Rm, H @ P0).T
        x = K @ (nu + H @ x)
    res = it_ekf.update(ids, r, b)
    assert res.accepted_ids == tuple(int(i) for i in ids)
    # The filter's right Jacobian is first order (I - ad/2): agreement to second order in x.
    np.testing.assert_allclose(it_ekf.pose, T0 @ se3_exp(x[:6]), atol=1e-5)
    one = SonarEKF(np.eye(4), np.zeros((6, 6)), range_sigma_m=0.01, bearing_sigma_rad=0.005, vfov_rad=VFOV,
                   **PLAIN)
    one.__dict__.update(copy.deepcopy({k: v for k, v in ekf.__dict__.items() if k != "iterations"}))
    one.update(ids, r, b)
    # Iterating moved the estimate away from the single-pass one, toward the MAP.
    assert np.abs(se3_log(se3_inverse(one.pose) @ it_ekf.pose)).max() > 10 * np.abs(
        se3_log(se3_inverse(T0 @ se3_exp(x[:6])) @ it_ekf.pose)).max()
    _assert_healthy(it_ekf)


def test_new_feature_covariance_matches_monte_carlo_of_the_arc() -> None:
    """Pose uncertainty + range/azimuth noise + uniform elevation, propagated by sampling."""
    P0 = np.diag([0.02**2, 0.03**2, 0.01**2, 0.01**2, 0.02**2, 0.015**2])
    T_hat = se3_exp(np.array([0.3, -0.2, 0.1, 0.1, -0.2, 0.4]))
    sr, sb = 0.01, 0.004
    # The pose uncertainty must come from motion: pose_cov0 is the gauge's (state_covariance).
    ekf = SonarEKF(T_hat, np.zeros((6, 6)), range_sigma_m=sr, bearing_sigma_rad=sb, vfov_rad=VFOV)
    ekf.predict(np.eye(4), P0)
    r_m, az_m = 2.5, 0.2
    ekf.update([7], [r_m], [az_m])
    C = ekf.native_covariance

    rng = np.random.default_rng(7)
    n = 200_000
    delta = rng.multivariate_normal(np.zeros(6), P0, size=n)
    s_true = np.column_stack([
        r_m - sr * rng.standard_normal(n),
        az_m - sb * rng.standard_normal(n),
        rng.uniform(-VFOV / 2, VFOV / 2, n),
    ])
    p_true = spherical_point(s_true)[0]
    # The true point in the anchor (= estimated) frame is Exp(delta) p_true.
    pairs = zip(delta[:20000], p_true[:20000], strict=True)
    q = np.stack([se3_exp(d)[:3, :3] @ p + se3_exp(d)[:3, 3] for d, p in pairs])
    e_s = np.stack([_sph(x) for x in q]) - np.array([r_m, az_m, 0.0])
    E = np.column_stack([delta[:20000], e_s])
    C_mc = np.cov(E.T)
    sd = np.sqrt(np.diag(C))
    # Compare correlation-normalised entries (sampling error ~ 1/sqrt(2e4) ~ 0.007).
    np.testing.assert_allclose(C_mc / np.outer(sd, sd), C / np.outer(sd, sd), atol=0.03)
    np.testing.assert_allclose(np.sqrt(np.diag(C_mc)), sd, rtol=0.03)


# --------------------------------------------------------------------------- prism scene
N_SEEDS = 16


@pytest.fixture(scope="module")
def prism_runs():
    out = []
    for seed in range(N_SEEDS):
        run = simulate(seed)
        out.append((run, run_filter(run)))
    return out


def test_nees_over_seeds_is_inside_the_chi_square_band(prism_runs) -> None:
    n_views = prism_runs[0][0].T_W_S.shape[0]
    pose = np.array([tr.pose_nees[1:] for _, tr in prism_runs])  # view 0: pose exact (NaN)
    lm = np.array([tr.landmark_nees[-1] for _, tr in prism_runs])
    # NEES at successive views of one run are correlated; the per-run time averages are
    # independent across seeds, each with mean 6 and variance at most that of one view
    # (2 * 6), so the chi2(6 N) / N band of their mean is the conservative one (99 %, two-sided).
    lo, hi = chi2.ppf([0.005, 0.995], 6 * N_SEEDS) / N_SEEDS
    assert lo <= pose.mean() <= hi, (pose.mean(), lo, hi)
    # And at the last view, where views don't enter, directly.
    assert lo <= pose[:, -1].mean() <= hi, (pose[:, -1].mean(), lo, hi)
    lo, hi = chi2.ppf([0.005, 0.995], 24 * N_SEEDS) / N_SEEDS
    assert lo <= lm.mean() <= hi, (lm.mean(), lo, hi)
    assert n_views == 21


def test_ekf_beats_odometry_and_reconstructs_the_prism(prism_runs) -> None:
    feat, pos_ekf, pos_odo = [], [], []
    for run, tr in prism_runs:
        feat.append(np.linalg.norm(tr.landmarks[-1] - run.points_W, axis=1).mean())
        pos_ekf.append(np.linalg.norm(tr.T_W_S[:, :3, 3] - run.T_W_S[:, :3, 3], axis=1).mean())
        To = run_odometry(run)
        pos_odo.append(np.linalg.norm(To[:, :3, 3] - run.T_W_S[:, :3, 3], axis=1).mean())
        # Features started 0.1-0.2 m off (elevation unknown) and every one got closer.
        first = np.linalg.norm(tr.landmarks[0] - run.points_W, axis=1)
        assert np.all(np.linalg.norm(tr.landmarks[-1] - run.points_W, axis=1) < np.maximum(first, 0.02))
    assert np.mean(pos_ekf) < np.mean(pos_odo)
    assert np.mean(feat) < 0.015


def test_pitch_at_90_degrees_gives_the_same_answer_as_level_flight() -> None:
    """Rotating the whole world so the sonar starts pitched +-90 deg changes nothing relative."""
    run = simulate(3)
    ref = run_filter(run)
    for pitch in (np.pi / 2, -np.pi / 2, np.pi / 2 - 1e-9):
        W = np.eye(4)
        W[:3, :3] = rotation_from_rpy(0.4, pitch, 0.0)
        W[:3, 3] = [1.0, -2.0, 3.0]
        r2 = dataclasses.replace(run, T_W_S=W @ run.T_W_S, points_W=run.points_W @ W[:3, :3].T + W[:3, 3])
        tr = run_filter(r2)
        np.testing.assert_allclose(tr.landmarks[-1], ref.landmarks[-1] @ W[:3, :3].T + W[:3, 3], atol=1e-8)
        np.testing.assert_allclose(tr.pose_nees[1:], ref.pose_nees[1:], rtol=1e-6)
        assert np.all(np.isfinite(tr.final.rpy_rad))
        assert abs(abs(tr.final.rpy_rad[1]) - np.pi / 2) < 0.3
        _assert_healthy(tr.final)


def _along_the_beam_run(**kw) -> tuple[SonarEKF, np.ndarray]:
    """Straight along the boresight with no rotation: a feature's elevation stays unobservable."""
    rng = np.random.default_rng(8)
    sr, sb = 0.003, np.deg2rad(0.1)
    pts = np.array([[3.0, 0.05, 0.25], [3.0, -0.1, -0.2], [3.2, 0.15, 0.0]])
    ekf = SonarEKF(np.eye(4), np.zeros((6, 6)), range_sigma_m=sr, bearing_sigma_rad=sb, vfov_rad=VFOV, **kw)
    T = np.eye(4)
    step = se3_exp(np.array([0.05, 0, 0, 0, 0, 0]))
    Q = np.diag([1e-8] * 3 + [1e-10] * 3)
    for k in range(30):
        if k:
            T = T @ step
            ekf.predict(step, Q)
        ids, r, b = measure(T, pts, rng, sr, sb)
        ekf.update(ids, r, b)
        _assert_healthy(ekf)
    return ekf, pts


def test_motion_along_the_beam_keeps_elevation_uncertain() -> None:
    ekf, pts = _along_the_beam_run()
    P = ekf.native_covariance
    for k in range(len(pts)):
        assert np.sqrt(P[8 + 3 * k, 8 + 3 * k]) > 0.5 * VFOV / np.sqrt(12)  # elevation sd


def test_motion_along_the_beam_stays_consistent() -> None:
    """Linearised at elevation 0 a range has no first-order sensitivity to elevation: without the
    second-order term the chord effect r (1 - cos el) became a ~4 sigma range bias here."""
    ekf, pts = _along_the_beam_run()
    # Judge it where its Gaussian lives: anchored (r, az, el) of each feature.
    P = ekf.native_covariance
    for k, (i, (T_a, s_hat)) in enumerate(ekf.landmark_anchors.items()):
        q = se3_inverse(T_a) @ np.r_[pts[i], 1.0]
        e = _sph(q[:3]) - s_hat
        C = P[6 + 3 * k : 9 + 3 * k, 6 + 3 * k : 9 + 3 * k]
        assert np.sqrt(C[2, 2]) > 0.5 * VFOV / np.sqrt(12)  # not falsely confident in elevation
        assert e @ np.linalg.solve(C, e) < chi2.ppf(0.999, 3)  # and the error is inside it


def test_short_range_edge_azimuth_and_wrap_around() -> None:
    rng = np.random.default_rng(9)
    pts = np.array([[0.004, 0.003, 0.0002], [-2.0, 1e-4, 0.05], [1.0, 1.9, 0.0]])
    ekf = SonarEKF(np.eye(4), np.diag([1e-6] * 6), range_sigma_m=1e-4, bearing_sigma_rad=1e-3, vfov_rad=VFOV)
    T = np.eye(4)
    for k in range(50):
        if k:
            U = se3_exp(1e-4 * rng.normal(size=6))
            T = T @ U
            ekf.predict(U, np.diag([1e-8] * 6))
        ids, r, b = measure(T, pts, rng, 1e-4, 1e-3, hfov_rad=2 * np.pi)
        res = ekf.update(ids, r, b)
        _assert_healthy(ekf)
        if k:
            assert res.accepted_ids == (0, 1, 2), res
    # The feature behind is seen at azimuths on both sides of +-pi: residuals must be wrapped.
    assert np.linalg.norm(ekf.landmarks[1] - pts[1]) < 0.05
    assert np.linalg.norm(ekf.landmarks[0] - pts[0]) < 1e-3


def test_a_feature_on_the_sonar_axis_is_reported_degenerate_not_used() -> None:
    ekf = SonarEKF(np.eye(4), np.zeros((6, 6)), range_sigma_m=0.01, bearing_sigma_rad=0.01, vfov_rad=VFOV)
    ekf.update([1, 2], [2.0, 2.0], [0.0, 0.1])
    # Rotate so that feature 1's anchored point lies on the new z axis.
    U = np.eye(4)
    U[:3, :3] = rotation_from_rpy(0.0, -np.pi / 2, 0.0)
    ekf.predict(U, np.zeros((6, 6)))
    before = ekf.landmarks[1]
    res = ekf.update([1, 2], [2.0, 2.0], [0.0, 0.0])
    assert res.degenerate_ids == (1,)
    np.testing.assert_allclose(ekf.landmarks[1], before, atol=1e-12)
    _assert_healthy(ekf)


def test_huge_initial_uncertainty_stays_finite_and_learns_relative_geometry() -> None:
    run = simulate(11)
    ref = run_filter(run)
    tr = run_filter(run, pose_cov0=np.diag([1e4] * 3 + [0.3**2] * 3))
    ekf = tr.final
    _assert_healthy(ekf)
    # The world pose can't be learned without an absolute reference, but features relative
    # to the sonar can, nearly as well as when the start is known exactly.
    Tt = se3_inverse(run.T_W_S[-1])

    def rel_err(f):
        Ti = se3_inverse(f.pose)
        return max(
            np.linalg.norm((Ti[:3, :3] @ lw + Ti[:3, 3]) - (Tt[:3, :3] @ run.points_W[i] + Tt[:3, 3]))
            for i, lw in f.landmarks.items()
        )

    assert rel_err(ekf) < 2.0 * rel_err(ref.final) + 0.01


def test_huge_initial_uncertainty_keeps_the_absolute_pose_uncertain() -> None:
    """pose_cov0 is the uncertainty of the frame the filter runs in (its gauge): relative
    returns never observe it, so it stays, and the world covariances carry it."""
    tr = run_filter(simulate(11), pose_cov0=np.diag([1e4] * 3 + [0.3**2] * 3))
    assert np.sqrt(tr.final.pose_cov[0, 0]) > 10.0
    assert all(np.sqrt(np.diag(tr.final.landmark_cov(i))).max() > 10.0 for i in tr.final.landmark_ids)


def test_the_gauge_adds_its_uncertainty_to_world_outputs_and_nothing_else() -> None:
    """A known start (pose_cov0 = 0) and an uncertain one give the same estimates; the world
    covariances differ by the gauge pushed through the pose and each feature (first order)."""
    run = simulate(4)
    P0 = np.diag([0.01**2] * 3 + [0.02**2] * 3)
    a, b = run_filter(run).final, run_filter(run, pose_cov0=P0).final
    np.testing.assert_allclose(b.pose, a.pose, atol=1e-12)
    np.testing.assert_allclose(b.native_covariance, a.native_covariance, atol=1e-15)
    Ad = se3_adjoint(se3_inverse(run.T_W_S[0]) @ a.pose)  # right perturbation of G seen at the pose
    Ai = np.linalg.inv(Ad)
    np.testing.assert_allclose(b.pose_cov, a.pose_cov + Ai @ P0 @ Ai.T, atol=1e-12)
    i = a.landmark_ids[0]
    q = se3_inverse(run.T_W_S[0]) @ np.r_[a.landmarks[i], 1.0]
    J = run.T_W_S[0][:3, :3] @ np.concatenate([np.eye(3), -hat(q[:3])], axis=1)
    np.testing.assert_allclose(b.landmark_cov(i), a.landmark_cov(i) + J @ P0 @ J.T, atol=1e-12)


@pytest.mark.parametrize("gate_prob", [0.999, None])
def test_tiny_measurement_noise(gate_prob) -> None:
    """sigma = 0.1 um / 10 nrad: far below the linearisation error of the elevation arc.

    The first re-observations' NIS at the prior's linearisation is huge (the arc's curvature,
    not noise); gated at the relinearised estimate they pass, and the filter converges either
    way. The plain single-pass gate refuses them (the behaviour this replaced).
    """
    cfg = PrismConfig(range_sigma_m=1e-7, bearing_sigma_rad=1e-8, k_t=1e-6, k_r=1e-6,
                      k_rt_rad_per_m=1e-7, floor_t_m=1e-9, floor_r_rad=1e-9)
    run = simulate(12, cfg)
    tr = run_filter(run, gate_prob=gate_prob)
    _assert_healthy(tr.final)
    assert tr.rejected == 0
    assert np.abs(tr.landmarks[-1] - run.points_W).max() < 1e-3
    if gate_prob is not None:
        ekf = SonarEKF(run.T_W_S[0], np.zeros((6, 6)), range_sigma_m=cfg.range_sigma_m,
                       bearing_sigma_rad=cfg.bearing_sigma_rad, vfov_rad=cfg.vfov_rad, **PLAIN)
        ekf.update(run.ids[0], run.ranges_m[0], run.bearings_rad[0])
        ekf.predict(run.U_odo[0], run.Q[0])
        assert ekf.update(run.ids[1], run.ranges_m[1], run.bearings_rad[1]).rejected


def _off_axis_run(el_deg: float, seed: int, **kw) -> tuple[int, float]:
    """Points at +-el_deg elevation (40 deg aperture) seen from a rolling, swaying sonar:
    (returns rejected by the 0.999 gate, mean feature error m)."""
    rng = np.random.default_rng(seed)
    vfov = np.deg2rad(40.0)
    n = 8
    s = np.column_stack([rng.uniform(2.0, 3.0, n), rng.uniform(-0.25, 0.25, n),
                         np.deg2rad(el_deg) * rng.choice([-1.0, 1.0], n)])
    pts = spherical_point(s)[0]
    sr, sb = 0.003, np.deg2rad(0.1)
    ekf = SonarEKF(np.eye(4), np.zeros((6, 6)), range_sigma_m=sr, bearing_sigma_rad=sb, vfov_rad=vfov, **kw)
    T, Q, rejected = np.eye(4), np.diag([1e-8] * 3 + [1e-9] * 3), 0
    for k in range(12):
        if k:
            T_next = se3_exp(np.array([0.0, 0.1 * np.sin(k), 0.02 * k, 0.25 * k, 0.0, 0.0]))
            U = se3_inverse(T) @ T_next
            T = T_next
            ekf.predict(U, Q)
        ids, r, b = measure(T, pts, rng, sr, sb, hfov_rad=np.deg2rad(60.0), vfov_rad=vfov)
        rejected += len(ekf.update(ids, r, b).rejected)
    return rejected, float(np.mean([np.linalg.norm(v - pts[i]) for i, v in ekf.landmarks.items()]))


@pytest.mark.parametrize("init", ["arc", "triangulate"])
def test_returns_18_degrees_off_axis_pass_the_relinearised_gate(init: str) -> None:
    """Issue #11: gated at elevation 0 such returns were refused. Relinearised, none is."""
    rej, err = zip(*(_off_axis_run(18.0, seed, init=init) for seed in range(4)), strict=True)
    assert sum(rej) == 0, rej
    assert max(err) < 0.01, err
    # The single-pass gate at elevation 0 is what refused them.
    assert sum(_off_axis_run(18.0, seed, **PLAIN)[0] for seed in range(4)) > 0


def test_second_order_update_matches_a_dense_reference() -> None:
    """One update with the elevation's second-order term: h + h_ee var/2 and R + h_ee h_ee^T var^2/2,
    h_ee by finite differences along each feature's arc, var the elevation variance given the pose."""
    ekf, pts = _filter_with_features(second_order=True)
    T0, P0 = ekf.pose, ekf.native_covariance
    anchors, order = ekf.landmark_anchors, ekf.landmark_ids
    rng = np.random.default_rng(6)
    ids, r, b = measure(T0 @ se3_exp(np.array([0.01, 0, 0, 0, 0.01, 0])), pts, rng, 0.01, 0.005)

    def h(x):
        T = T0 @ se3_exp(x[:6])
        out = []
        for i in ids:
            Ta, s = anchors[i]
            k = order.index(i)
            q = se3_inverse(T) @ (Ta @ np.r_[spherical_point(s + x[6 + 3 * k : 9 + 3 * k])[0], 1.0])
            out += [np.linalg.norm(q[:3]), np.arctan2(q[1], q[0])]
        return np.array(out)

    x0 = np.zeros(P0.shape[0])
    H = _num_jac(h, x0, 1e-7)
    bias, Rm = np.zeros(2 * len(ids)), np.diag(np.tile([0.01**2, 0.005**2], len(ids)))
    for j, i in enumerate(ids):
        k = order.index(i)
        e = np.zeros_like(x0)
        e[8 + 3 * k] = 1e-4
        hee = (h(e) - 2 * h(x0) + h(-e))[2 * j : 2 * j + 2] / 1e-8
        c = P0[8 + 3 * k, :6]
        var = min(P0[8 + 3 * k, 8 + 3 * k] - c @ np.linalg.solve(P0[:6, :6], c), VFOV**2 / 12)
        bias[2 * j : 2 * j + 2] = 0.5 * hee * var
        Rm[2 * j : 2 * j + 2, 2 * j : 2 * j + 2] += 0.5 * np.outer(hee, hee) * var**2
    nu = np.ravel(np.column_stack([r, b])) - h(x0) - bias
    nu[1::2] = wrap_angle(nu[1::2])
    S = H @ P0 @ H.T + Rm
    dx = np.linalg.solve(S, H @ P0).T @ nu
    res = ekf.update(ids, r, b)
    assert res.accepted_ids == tuple(int(i) for i in ids)
    np.testing.assert_allclose(ekf.pose, T0 @ se3_exp(dx[:6]), atol=1e-8)
    np.testing.assert_allclose(res.nis, nu @ np.linalg.solve(S, nu), rtol=1e-4)


def _noise_run(bearing_factor: float, seed: int = 0, **kw) -> tuple[SonarEKF, list]:
    """The prism flown back and forth for 600 returns, with bearing noise bearing_factor x the configured."""
    import warnings as _w

    cfg = PrismConfig()
    rng = np.random.default_rng(seed)
    pts = prism_vertices()
    ekf = SonarEKF(np.eye(4), np.zeros((6, 6)), range_sigma_m=cfg.range_sigma_m,
                   bearing_sigma_rad=cfg.bearing_sigma_rad, vfov_rad=cfg.vfov_rad, **kw)
    T, Q = np.eye(4), np.diag([1e-6] * 6)
    with _w.catch_warnings(record=True) as caught:
        _w.simplefilter("always")
        for k in range(80):
            if k:
                T_next = se3_exp(np.array([0, 0.2 * np.sin(k / 5), 0.1 * np.sin(k / 7), np.sin(k / 4), 0, 0]))
                U_true = se3_inverse(T) @ T_next
                T = T_next
                ekf.predict(U_true @ se3_exp(-rng.multivariate_normal(np.zeros(6), Q)), Q)
            ids, r, b = measure(T, pts, rng, cfg.range_sigma_m, bearing_factor * cfg.bearing_sigma_rad)
            ekf.update(ids, r, b)
    return ekf, [w for w in caught if issubclass(w.category, RuntimeWarning)]


def test_innovation_monitor_is_quiet_when_the_noise_is_right() -> None:
    ekf, warned = _noise_run(1.0)
    st = ekf.innovation_stats()
    assert not warned
    assert st.band[0] <= st.nis_per_dof <= st.band[1]
    assert st.returns >= ekf.nis_window


def test_innovation_monitor_warns_and_estimates_a_bearing_noise_twice_the_configured() -> None:
    ekf, warned = _noise_run(2.0)
    st = ekf.innovation_stats()
    assert len(warned) == 1 and "overconfident" in str(warned[0].message)
    assert st.nis_per_dof > st.band[1]
    assert st.bearing_nis > 2.0 and st.range_nis < 1.5
    cfg = PrismConfig()
    assert 1.6 < st.bearing_sigma_rad / cfg.bearing_sigma_rad < 2.4


def test_ten_thousand_cycles_stay_healthy_and_consistent() -> None:
    cfg = PrismConfig()
    rng = np.random.default_rng(13)
    pts = prism_vertices()
    ekf = SonarEKF(np.eye(4), np.zeros((6, 6)), range_sigma_m=cfg.range_sigma_m,
                   bearing_sigma_rad=cfg.bearing_sigma_rad, vfov_rad=cfg.vfov_rad)
    T = np.eye(4)
    nees_pose = []
    Q = np.diag([1e-6] * 3 + [1e-6] * 3)
    for k in range(10_000):
        if k:
            # Wander around the start, rolling back and forth, keeping the prism in view.
            target = np.array([0.0, 0.2 * np.sin(k / 50), 0.1 * np.sin(k / 70), np.sin(k / 40), 0.0, 0.0])
            T_next = se3_exp(target)
            U_true = se3_inverse(T) @ T_next
            w = rng.multivariate_normal(np.zeros(6), Q)
            T = T_next
            ekf.predict(U_true @ se3_exp(-w), Q)
        ids, r, b = measure(T, pts, rng, cfg.range_sigma_m, cfg.bearing_sigma_rad)
        ekf.update(ids, r, b)
        if k % 100 == 0:
            e = pose_error(ekf.pose, T)
            nees_pose.append(e @ np.linalg.solve(ekf.pose_cov, e) if k else 6.0)
    _assert_healthy(ekf)
    assert np.abs(np.stack([ekf.landmarks[i] for i in range(8)]) - pts).max() < 0.01
    m = len(nees_pose)
    lo, hi = chi2.ppf([0.0005, 0.9995], 6 * m) / m
    assert lo <= np.mean(nees_pose) <= hi, (np.mean(nees_pose), lo, hi)


def test_repeated_identical_measurements() -> None:
    ekf = SonarEKF(np.eye(4), np.diag([1e-4] * 6), range_sigma_m=0.01, bearing_sigma_rad=0.005, vfov_rad=VFOV)
    ids, r, b = measure(np.eye(4), prism_vertices())
    ekf.update(ids, r, b)
    traces = []
    # zero innovations, again and again: the NIS monitor must say the covariance is too loose
    with pytest.warns(RuntimeWarning, match="too loose"):
        for _ in range(1000):
            res = ekf.update(ids, r, b)
            assert len(res.accepted_ids) == 8
            traces.append(np.trace(ekf.native_covariance))
    _assert_healthy(ekf)
    assert np.all(np.diff(traces) <= 1e-15)  # information only ever adds
    z = np.array([observation_model(ekf.pose, ekf.landmarks[i])[0] for i in ids])
    np.testing.assert_allclose(z[:, 0], r, atol=1e-6)
    np.testing.assert_allclose(z[:, 1], b, atol=1e-6)


# --------------------------------------------------------------------------- gating and forgetting
def test_outlier_is_gated_reported_and_ignored() -> None:
    ekf, pts = _filter_with_features()
    twin = copy.deepcopy(ekf)
    rng = np.random.default_rng(14)
    ids, r, b = measure(ekf.pose, pts, rng, 0.01, 0.005)
    r_bad = r.copy()
    r_bad[3] += 0.5
    res = ekf.update(ids, r_bad, b)
    assert set(res.rejected) == {int(ids[3])}
    assert res.rejected[int(ids[3])] > chi2.ppf(0.999, 2)
    keep = np.arange(len(ids)) != 3
    res2 = twin.update(ids[keep], r[keep], b[keep])
    assert res.accepted_ids == res2.accepted_ids
    np.testing.assert_allclose(ekf.pose, twin.pose, atol=1e-14)
    np.testing.assert_allclose(ekf.native_covariance, twin.native_covariance, atol=1e-14)
    assert res.nis == pytest.approx(res2.nis) and ekf.nis_dof == 2 * (len(ids) - 1)


def test_forget_marginalises_and_a_forgotten_feature_comes_back_fresh() -> None:
    ekf, pts = _filter_with_features()
    ids = ekf.landmark_ids
    P = ekf.native_covariance
    ekf.forget(ids[2])
    keep = np.r_[0:12, 15 : P.shape[0]]
    np.testing.assert_array_equal(ekf.native_covariance, P[np.ix_(keep, keep)])
    assert ids[2] not in ekf.landmarks
    with pytest.raises(KeyError):
        ekf.landmark_cov(ids[2])
    z, _, _ = observation_model(ekf.pose, pts[ids[2]])
    res = ekf.update([ids[2]], [z[0]], [z[1]])
    assert res.initialized_ids == (ids[2],)


# --------------------------------------------------------------------------- bad input
def _bad_updates():
    ok_ids, ok_r, ok_b = [0, 1], [2.0, 2.1], [0.0, 0.1]
    return [
        ((ok_ids, [np.nan, 2.1], ok_b), ValueError),
        ((ok_ids, [2.0, -1.0], ok_b), ValueError),
        ((ok_ids, [2.0, 0.0], ok_b), ValueError),
        ((ok_ids, ok_r, [0.0, np.inf]), ValueError),
        ((ok_ids, [2.0], ok_b), ValueError),
        (([[0, 1]], ok_r, ok_b), ValueError),
        (([0.0, 1.0], ok_r, ok_b), TypeError),
        (([0, 0], ok_r, ok_b), ValueError),
        ((ok_ids, ["a", "b"], ok_b), TypeError),
        ((ok_ids, [[2.0, 2.1]], ok_b), ValueError),
    ]


@pytest.mark.parametrize("args,exc", _bad_updates())
def test_bad_update_input_raises_and_leaves_state_untouched(args, exc) -> None:
    ekf, _ = _filter_with_features()
    before = _snapshot(ekf)
    with pytest.raises(exc, match="Expected"):
        ekf.update(*args)
    _assert_same_state(before, _snapshot(ekf))


def _bad_predicts():
    Q = np.eye(6) * 1e-4
    U = se3_exp(np.full(6, 0.1))
    skew = U.copy()
    skew[0, 1] += 0.1
    asym = Q.copy()
    asym[0, 1] = 1e-3
    neg = Q.copy()
    neg[0, 0] = -1.0
    nanq = Q.copy()
    nanq[2, 2] = np.nan
    return [
        ((skew, Q), ValueError),
        ((U[:3], Q), ValueError),
        ((np.where(np.eye(4) > 0, np.nan, U), Q), ValueError),
        ((U, asym), ValueError),
        ((U, neg), ValueError),
        ((U, nanq), ValueError),
        ((U, np.eye(3)), ValueError),
    ]


@pytest.mark.parametrize("args,exc", _bad_predicts())
def test_bad_predict_input_raises_and_leaves_state_untouched(args, exc) -> None:
    ekf, _ = _filter_with_features()
    before = _snapshot(ekf)
    with pytest.raises(exc, match="Expected"):
        ekf.predict(*args)
    _assert_same_state(before, _snapshot(ekf))


@pytest.mark.parametrize(
    "kwargs",
    [
        dict(range_sigma_m=0.0),
        dict(bearing_sigma_rad=-1.0),
        dict(vfov_rad=0.0),
        dict(vfov_rad=4.0),
        dict(range_sigma_m=np.nan),
        dict(gate_prob=1.0),
        dict(pose_cov0=-np.eye(6)),
        dict(T_W_S0=np.zeros((4, 4))),
        dict(iterations=0),
    ],
)
def test_bad_constructor_arguments_raise(kwargs) -> None:
    args = dict(T_W_S0=np.eye(4), pose_cov0=np.zeros((6, 6)), range_sigma_m=0.01,
                bearing_sigma_rad=0.01, vfov_rad=VFOV)
    args.update(kwargs)
    with pytest.raises(ValueError, match="Expected"):
        SonarEKF(**args)


def test_nees_helper_agrees_with_a_direct_computation() -> None:
    run = simulate(15)
    tr = run_filter(run)
    ekf = tr.final
    e = pose_error(ekf.pose, run.T_W_S[-1])
    direct = e @ np.linalg.solve(ekf.pose_cov, e)
    assert nees(ekf, run.T_W_S[-1], run.points_W)[0] == pytest.approx(direct, rel=1e-9)


# --------------------------------------------------------------------------- triangulated initialisation
def _views_around(p_S: np.ndarray, n: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """Views of a point rolled and raised around the reference frame; returns ``T_V_S`` and ``z``."""
    X, z = [], []
    for j in range(n):
        a = (j - (n - 1)) / max(n - 1, 1)  # the reference view (identity) comes last
        T_S_V = se3_exp(np.array([0.1 * a, 0.05 * a, 0.15 * a, 0.6 * a, 0.05 * a, -0.03 * a]))
        Xj = se3_inverse(T_S_V)
        q = Xj[:3, :3] @ p_S + Xj[:3, 3]
        X.append(Xj)
        z.append([np.linalg.norm(q), np.arctan2(q[1], q[0])])
    return np.stack(X), np.array(z)


def test_triangulation_is_exact_on_noiseless_views_and_its_sigma_is_honest() -> None:
    p_S = spherical_point(np.array([2.3, 0.15, np.deg2rad(5.0)]))[0]
    X, z = _views_around(p_S)
    r_var = np.array([0.003**2, np.deg2rad(0.1) ** 2])
    C = np.zeros((len(X), 6, 6))
    tri = triangulate(X, z, C, r_var, VFOV)
    np.testing.assert_allclose(tri.s, _sph(p_S), atol=1e-9)
    assert tri.cost < 1e-12 and tri.dof == 2 * len(X) - 3
    # With noise on the returns and on the relative poses, the stated covariance is right:
    # the normalised squared errors average 3 (chi-square, 3 dof) over many trials.
    rng = np.random.default_rng(21)
    Ce = np.diag([1e-4**2] * 3 + [2e-4**2] * 3)
    d2 = []
    for _ in range(300):
        Xn = np.stack([x @ se3_exp(rng.multivariate_normal(np.zeros(6), Ce)) for x in X[:-1]] + [X[-1]])
        zn = z + rng.standard_normal(z.shape) * np.sqrt(r_var)
        t = triangulate(Xn, zn, np.concatenate([np.broadcast_to(Ce, (len(X) - 1, 6, 6)), C[:1]]),
                        r_var, VFOV)
        e = _sph(p_S) - t.s
        d2.append(e @ np.linalg.solve(t.cov, e))
    lo, hi = chi2.ppf([0.0005, 0.9995], 3 * 300) / 300
    assert lo <= np.mean(d2) <= hi, (np.mean(d2), lo, hi)


def test_triangulation_without_parallax_leaves_elevation_unknown() -> None:
    p_S = spherical_point(np.array([2.0, 0.1, 0.05]))[0]
    q = p_S
    z = np.array([[np.linalg.norm(q), np.arctan2(q[1], q[0])]] * 4)
    tri = triangulate(np.broadcast_to(np.eye(4), (4, 4, 4)).copy(), z, np.zeros((4, 6, 6)),
                      np.array([1e-4, 1e-6]), VFOV)
    assert tri is None or tri.elevation_sigma_rad > VFOV


def _run_triangulate(run, **kw) -> SonarEKF:
    cfg = run.config
    ekf = SonarEKF(run.T_W_S[0], np.zeros((6, 6)), range_sigma_m=cfg.range_sigma_m,
                   bearing_sigma_rad=cfg.bearing_sigma_rad, vfov_rad=cfg.vfov_rad, init="triangulate", **kw)
    for k in range(run.T_W_S.shape[0]):
        if k:
            ekf.predict(run.U_odo[k - 1], run.Q[k - 1])
        res = ekf.update(run.ids[k], run.ranges_m[k], run.bearings_rad[k])
        seen = set(res.accepted_ids) | set(res.rejected) | set(res.initialized_ids)
        assert seen == set(run.ids[k].tolist())
    return ekf


def test_triangulated_init_on_the_prism_is_consistent_and_as_good_as_the_arc() -> None:
    n = 12
    pose, feat, feat_arc = [], [], []
    for seed in range(n):
        run = simulate(100 + seed)
        ekf = _run_triangulate(run)
        _assert_healthy(ekf)
        pn, _, _, _ = nees(ekf, run.T_W_S[-1], run.points_W)
        pose.append(pn)
        feat.append(np.mean([np.linalg.norm(ekf.landmarks[i] - run.points_W[i]) for i in range(8)]))
        arc = run_filter(run).final
        feat_arc.append(np.mean([np.linalg.norm(arc.landmarks[i] - run.points_W[i]) for i in range(8)]))
    lo, hi = chi2.ppf([0.005, 0.995], 6 * n) / n
    assert lo <= np.mean(pose) <= hi, (np.mean(pose), lo, hi)
    assert np.mean(feat) < 0.02
    assert np.mean(feat) <= 1.1 * np.mean(feat_arc), (np.mean(feat), np.mean(feat_arc))


def test_triangulate_start_leaves_the_stationary_point_at_elevation_zero() -> None:
    """Along the beam the arc's symmetry makes elevation 0 a stationary point of every update:
    Gauss-Newton from the estimate never leaves it; the scan along the arc does."""
    ekf_arc, pts = _along_the_beam_run()
    ekf_tri, _ = _along_the_beam_run(init="triangulate")
    el_true = [_sph(se3_inverse(T_a)[:3, :3] @ pts[i] + se3_inverse(T_a)[:3, 3])[2]
               for i, (T_a, _) in ekf_tri.landmark_anchors.items()]
    el_arc = [s[2] for _, s in ekf_arc.landmark_anchors.values()]
    el_tri = [s[2] for _, s in ekf_tri.landmark_anchors.values()]
    assert np.abs(el_arc).max() < 0.25 * np.abs(el_true).max()
    assert np.abs(el_tri[0]) > 0.5 * abs(el_true[0]), (el_tri, el_true)
    _assert_healthy(ekf_tri)


# --------------------------------------------------------------------------- ranges to a known plane
FLOOR_N = np.array([0.0, 0.0, 1.0])
FLOOR_D = -0.42


def _dvl_rays_S() -> tuple[np.ndarray, np.ndarray]:
    """Four beams tilted 22.5 deg in an X around the sonar's -z, from an offset origin."""
    from gpumap.sim.dvl import dvl_beam_directions

    R_S_D = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])  # DVL x -> sonar -z
    u = dvl_beam_directions(22.5) @ R_S_D.T
    return np.tile([0.05, 0.02, -0.06], (4, 1)), u


def _plane_ranges(T_W_S: np.ndarray, o: np.ndarray, u: np.ndarray) -> np.ndarray:
    R, t = T_W_S[:3, :3], T_W_S[:3, 3]
    return (FLOOR_D - (o @ R.T + t) @ FLOOR_N) / ((u @ R.T) @ FLOOR_N)


def _level_pose(z: float = 0.05, yaw: float = 0.4) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = rotation_from_rpy(0.0, 0.0, yaw)
    T[:3, 3] = [0.3, -0.2, z]
    return T


def _plane_filter(T_hat: np.ndarray, sig_t: float = 0.03, sig_r: float = 0.03) -> SonarEKF:
    P0 = np.diag([sig_t**2] * 3 + [sig_r**2] * 3)
    return SonarEKF(T_hat, P0, range_sigma_m=0.01, bearing_sigma_rad=0.005, vfov_rad=VFOV)


@pytest.mark.parametrize("tilt", [0.0, 0.3, 1.2])
def test_plane_range_jacobian_matches_finite_differences(tilt: float) -> None:
    rng = np.random.default_rng(3)
    o, u = _dvl_rays_S()
    T = _level_pose() @ se3_exp(np.r_[0.0, 0.0, 0.0, tilt, -0.5 * tilt, 0.1])
    n = np.array([0.1, -0.05, 1.0])
    n /= np.linalg.norm(n)
    u = u @ so3_exp(rng.normal(0, 0.1, 3)).T  # not the X pattern any more
    r, H, cos_inc = plane_range_model(T, o, u, n, FLOOR_D)
    ok = np.abs(cos_inc) > 0.05  # the model holds behind the origin too (r < 0)
    assert ok.sum() >= 2
    Hn = _num_jac(lambda d: plane_range_model(T @ se3_exp(d), o, u, n, FLOOR_D)[0], np.zeros(6))
    np.testing.assert_allclose(H[ok], Hn[ok], rtol=1e-6, atol=1e-8)
    hit = T[:3, :3] @ (o + r[:, None] * u).T + T[:3, 3:4]
    np.testing.assert_allclose((n @ hit)[ok], FLOOR_D, atol=1e-12)


def test_plane_ranges_observe_height_roll_pitch_only() -> None:
    o, u = _dvl_rays_S()
    T = _level_pose()
    ekf = _plane_filter(T)
    P0 = ekf.pose_cov
    res = ekf.update_plane_ranges(o, u, _plane_ranges(T, o, u), FLOOR_N, FLOOR_D, 0.005)
    assert res.accepted == (0, 1, 2, 3) and not res.rejected and res.nis == pytest.approx(0.0, abs=1e-20)
    P = ekf.pose_cov
    unobs = [0, 1, 5]  # x, y (level sonar: body = world horizontal) and yaw
    np.testing.assert_allclose(P[np.ix_(unobs, unobs)], P0[np.ix_(unobs, unobs)], rtol=1e-12, atol=1e-18)
    for i in (2, 3, 4):  # height, roll, pitch
        assert P[i, i] < 0.5 * P0[i, i], (i, P[i, i], P0[i, i])
    np.testing.assert_allclose(ekf.pose, T, atol=1e-15)
    _assert_healthy(ekf)


def test_plane_ranges_converge_to_the_true_tilt_and_height() -> None:
    o, u = _dvl_rays_S()
    T_true = _level_pose() @ se3_exp(np.r_[0.0, 0.0, 0.0, 0.15, -0.2, 0.0])
    e0 = np.array([0.02, -0.03, 0.04, 0.05, -0.04, 0.03])
    ekf = _plane_filter(T_true @ se3_exp(-e0), 0.05, 0.05)
    r = _plane_ranges(T_true, o, u)
    yaw0 = ekf.rpy_rad[2]
    for _ in range(15):  # a hovering vehicle: no motion, some process noise, the same ranges
        ekf.predict(np.eye(4), np.eye(6) * 1e-4)
        ekf.update_plane_ranges(o, u, r, FLOOR_N, FLOOR_D, 1e-3)
    T = ekf.pose
    assert T[2, 3] == pytest.approx(T_true[2, 3], abs=1e-9)
    np.testing.assert_allclose(T[:3, :3].T @ FLOOR_N, T_true[:3, :3].T @ FLOOR_N, atol=1e-9)  # tilt
    np.testing.assert_allclose(_plane_ranges(T, o, u), r, atol=1e-9)
    # Position along the floor and heading are not observed: they stay where the prior put them.
    assert abs(np.linalg.norm(T[:2, 3] - T_true[:2, 3]) - np.linalg.norm(e0[:2])) < 0.02
    assert abs(ekf.rpy_rad[2] - yaw0) < 0.02
    _assert_healthy(ekf)


def test_plane_ranges_nees_over_seeds_is_inside_the_chi_square_band() -> None:
    o, u = _dvl_rays_S()
    P0 = np.diag([0.02**2] * 3 + [0.02**2] * 3)
    Q = np.diag([0.004**2] * 3 + [0.004**2] * 3)
    n_seeds, total = 60, 0.0
    for seed in range(n_seeds):
        rng = np.random.default_rng(1000 + seed)
        T_true = _level_pose(yaw=rng.uniform(-3, 3)) @ se3_exp(np.r_[0, 0, 0, rng.normal(0, 0.2, 2), 0])
        T_hat = T_true @ se3_exp(-rng.multivariate_normal(np.zeros(6), P0))
        ekf = SonarEKF(T_hat, P0, range_sigma_m=0.01, bearing_sigma_rad=0.005, vfov_rad=VFOV)
        for _ in range(8):
            U_true = se3_exp(np.r_[rng.normal(0, 0.05, 2), 0.0, rng.normal(0, 0.02, 2), rng.normal(0, 0.1)])
            T_true = T_true @ U_true
            ekf.predict(U_true @ se3_exp(-rng.multivariate_normal(np.zeros(6), Q)), Q)
            r = _plane_ranges(T_true, o, u) + rng.normal(0, 0.01, 4)
            res = ekf.update_plane_ranges(o, u, r, FLOOR_N, FLOOR_D, 0.01)
            assert len(res.accepted) + len(res.rejected) == 4
        e = se3_log(se3_inverse(ekf.pose) @ T_true)
        total += float(e @ np.linalg.solve(ekf.pose_cov, e))
    lo, hi = chi2.ppf([0.005, 0.995], 6 * n_seeds) / n_seeds
    assert lo < total / n_seeds < hi, (total / n_seeds, lo, hi)


def test_plane_rays_parallel_behind_or_without_return_are_skipped_cleanly() -> None:
    o, u = _dvl_rays_S()
    T = _level_pose()
    r = _plane_ranges(T, o, u)
    o6 = np.vstack([o, o[:2]])
    u6 = np.vstack([u, [[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]])  # parallel to the floor; pointing up
    r6 = np.r_[r[0], np.nan, r[2] + 0.5, r[3], 1.0, 1.0]  # no return; outlier
    ekf = _plane_filter(T)
    res = ekf.update_plane_ranges(o6, u6, r6, FLOOR_N, FLOOR_D, 0.005)
    assert res.accepted == (0, 3) and res.skipped == (1,) and res.degenerate == (4, 5)
    assert set(res.rejected) == {2} and res.rejected[2] > chi2.ppf(0.999, 1)
    _assert_healthy(ekf)
    twin = _plane_filter(T)
    twin.update_plane_ranges(o[[0, 3]], u[[0, 3]], r[[0, 3]], FLOOR_N, FLOOR_D, 0.005)
    np.testing.assert_allclose(ekf.native_covariance, twin.native_covariance, atol=1e-15)
    # Nothing usable: nothing changes.
    before = _snapshot(ekf)
    res = ekf.update_plane_ranges(o6[4:], u6[4:], r6[4:], FLOOR_N, FLOOR_D, 0.005)
    assert res.accepted == () and res.degenerate == (0, 1) and res.nis is None
    _assert_same_state(before, _snapshot(ekf))


def test_plane_ranges_move_correlated_features() -> None:
    ekf, _ = _filter_with_features()
    o, u = _dvl_rays_S()
    L0 = ekf.landmarks
    r = _plane_ranges(ekf.pose, o, u) + 0.02
    res = ekf.update_plane_ranges(o, u, r, FLOOR_N, FLOOR_D, 0.01)
    assert len(res.accepted) == 4
    assert max(np.abs(ekf.landmarks[i] - L0[i]).max() for i in L0) > 1e-6
    _assert_healthy(ekf)


def test_the_plane_step_is_pure_and_its_result_type_is_importable_from_the_filter() -> None:
    """gpumap.ekf.plane (issue 32): fuse_plane_ranges changes none of the state it is given; the
    filter's method is that step; PlaneUpdateResult stays importable from gpumap.ekf.filter."""
    import gpumap.ekf.filter
    from gpumap.ekf.plane import PlaneUpdateResult, fuse_plane_ranges

    assert gpumap.ekf.filter.PlaneUpdateResult is PlaneUpdateResult is gpumap.ekf.PlaneUpdateResult
    ekf, _ = _filter_with_features()
    o, u = _dvl_rays_S()
    r = _plane_ranges(ekf.pose, o, u) + 0.02
    state = [a.copy() for a in (ekf._T, ekf._P, ekf._S, ekf._G)]
    new, res = fuse_plane_ranges(*state, ekf._ng, ekf.pose, ekf._pose_rows(), ekf._gate1,
                                 o, u, r, FLOOR_N, FLOOR_D, 0.01)
    for a, b in zip(state, (ekf._T, ekf._P, ekf._S, ekf._G), strict=True):
        np.testing.assert_array_equal(a, b)
    assert len(res.accepted) == 4 and new is not None
    assert ekf.update_plane_ranges(o, u, r, FLOOR_N, FLOOR_D, 0.01) == res
    for a, b in zip(new, (ekf._T, ekf._P, ekf._S, ekf._G), strict=True):
        np.testing.assert_array_equal(a, b)


def _bad_plane_updates():
    o, u = _dvl_rays_S()
    r = np.full(4, 0.5)
    return [
        ((o[:3], u, r, FLOOR_N, FLOOR_D, 0.01), ValueError),
        ((o, 2.0 * u, r, FLOOR_N, FLOOR_D, 0.01), ValueError),
        ((o, np.where(u > 0, np.nan, u), r, FLOOR_N, FLOOR_D, 0.01), ValueError),
        ((o, u, r[:3], FLOOR_N, FLOOR_D, 0.01), ValueError),
        ((o, u, np.r_[r[:3], np.inf], FLOOR_N, FLOOR_D, 0.01), ValueError),
        ((o, u, np.r_[r[:3], -1.0], FLOOR_N, FLOOR_D, 0.01), ValueError),
        ((o, u, ["a"] * 4, FLOOR_N, FLOOR_D, 0.01), TypeError),
        ((o, u, r, np.zeros(3), FLOOR_D, 0.01), ValueError),
        ((o, u, r, FLOOR_N[:2], FLOOR_D, 0.01), ValueError),
        ((o, u, r, FLOOR_N, np.nan, 0.01), ValueError),
        ((o, u, r, FLOOR_N, FLOOR_D, 0.0), ValueError),
        ((o.ravel(), u, r, FLOOR_N, FLOOR_D, 0.01), ValueError),
    ]


@pytest.mark.parametrize("args,exc", _bad_plane_updates())
def test_bad_plane_update_input_raises_and_leaves_state_untouched(args, exc) -> None:
    ekf, _ = _filter_with_features()
    before = _snapshot(ekf)
    with pytest.raises(exc, match="Expected"):
        ekf.update_plane_ranges(*args)
    _assert_same_state(before, _snapshot(ekf))


def test_blas_threads_are_pinned_inside_a_step_and_restored_after():
    from threadpoolctl import ThreadpoolController

    from gpumap.ekf.state import _blas_limited

    ctl = ThreadpoolController()
    before = [lib.num_threads for lib in ctl.select(user_api="blas").lib_controllers]

    class Step:
        _blas_threads = 1

        @_blas_limited
        def run(self):
            return [lib.num_threads for lib in ThreadpoolController().select(user_api="blas").lib_controllers]

    inside = Step().run()
    after = [lib.num_threads for lib in ThreadpoolController().select(user_api="blas").lib_controllers]
    assert inside and all(n == 1 for n in inside)
    assert after == before
    with pytest.raises(ValueError, match="blas_threads"):
        SonarEKF(np.eye(4), np.eye(6) * 1e-4, range_sigma_m=0.01, bearing_sigma_rad=0.01,
                 vfov_rad=0.3, blas_threads=0)


def test_elevation_curvature_matches_finite_differences_and_the_fast_path() -> None:
    """d^2 (range, azimuth) / d el^2 along each feature's arc: the reference formula, the form
    _linearize uses (built from its Jacobians), and central differences agree."""
    from gpumap.ekf.measurement import _anchored_to_world, _elevation_curvature, _linearize

    rng = np.random.default_rng(21)
    for _ in range(5):
        T, Ta = se3_exp(0.5 * rng.normal(size=6)), se3_exp(0.5 * rng.normal(size=6))
        S = np.column_stack([rng.uniform(1, 3, 4), rng.uniform(-0.5, 0.5, 4), rng.uniform(-0.3, 0.3, 4)])
        Ra, ta = np.repeat(Ta[None, :3, :3], 4, 0), np.repeat(Ta[None, :3, 3], 4, 0)
        fast = _linearize(T, S, Ra, ta, np.zeros((4, 2)))[4]
        Lw, J = _anchored_to_world(S, Ra, ta)
        ref = _elevation_curvature(T[:3, :3], T[:3, 3], Lw, J, Lw - ta)
        np.testing.assert_allclose(fast, ref, atol=1e-12)
        h = 1e-4
        d = np.zeros_like(S)
        d[:, 2] = h
        z = [-_linearize(T, S + k * d, Ra, ta, np.zeros((4, 2)), False)[0] for k in (-1, 0, 1)]
        d_az = wrap_angle(z[2][:, 1] - z[1][:, 1]) - wrap_angle(z[1][:, 1] - z[0][:, 1])
        fd = np.column_stack([(z[2][:, 0] - 2 * z[1][:, 0] + z[0][:, 0]) / h**2, d_az / h**2])
        np.testing.assert_allclose(fast, fd, atol=1e-5 * (1 + np.abs(fd).max()))


def test_adapt_noise_raises_the_bearing_sigma_to_the_true_one_and_the_nis_comes_back() -> None:
    ekf, warned = _noise_run(2.0, adapt_noise=True)
    cfg = PrismConfig()
    assert warned and "adapt_noise: now" in str(warned[0].message)
    assert 1.6 < ekf.bearing_sigma_rad / cfg.bearing_sigma_rad < 2.4
    assert ekf.range_sigma_m >= cfg.range_sigma_m
    st = ekf.innovation_stats()
    assert st.band[0] <= st.nis_per_dof <= st.band[1]
    quiet, _ = _noise_run(1.0, adapt_noise=True)
    assert quiet.bearing_sigma_rad == cfg.bearing_sigma_rad and quiet.range_sigma_m == cfg.range_sigma_m
