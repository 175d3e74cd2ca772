"""Tests of the batch MAP (gpumap.ekf.batch) against exact data, finite differences, the EKF on the
same model (prism scene), a robust loss against one outlier, and bad input."""

from __future__ import annotations

import numpy as np
import pytest
from gpumap.sim.prism import (
    PrismConfig,
    look_at,
    measure,
    motion_cov,
    pose_error,
    run_filter,
    run_odometry,
    simulate,
)
from scipy.stats import chi2

from gpumap.ekf import spherical_point
from gpumap.ekf.batch import BatchProblem, solve
from gpumap.lie import se3_exp, se3_inverse

CFG = PrismConfig()
SIGMAS = dict(range_sigma_m=CFG.range_sigma_m, bearing_sigma_rad=CFG.bearing_sigma_rad, vfov_rad=CFG.vfov_rad)


def _problem(run, pose_cov0=None, **kw) -> BatchProblem:
    return BatchProblem(run.T_W_S[0], np.zeros((6, 6)) if pose_cov0 is None else pose_cov0,
                        list(zip(run.U_odo, run.Q, strict=True)),
                        list(zip(run.ids, run.ranges_m, run.bearings_rad, strict=True)), **(SIGMAS | kw))


def _landmark_error(landmarks: dict, points_W: np.ndarray) -> float:
    return float(np.mean([np.linalg.norm(landmarks[i] - points_W[i]) for i in landmarks]))


def _exact_scene(n_views: int = 7, seed: int = 0):
    """Noiseless sequence in which each point lies at elevation 0 in the view where it is first
    seen, so that every factor (elevation prior included) is exactly zero at the truth."""
    rng = np.random.default_rng(seed)
    s = np.linspace(0, 1, n_views)
    T = np.stack([look_at([0.4 * si, 0.3 * np.sin(2 * np.pi * si), 0.2 * si], [2.5, 0, 0], 1.2 * si)
                  for si in s])
    first = [min(k, n_views - 1) for k in (0, 0, 0, 1, 2, 3)]
    pts = np.stack([T[k, :3, :3] @ spherical_point([rng.uniform(2, 3), rng.uniform(-0.2, 0.2), 0.0])[0]
                    + T[k, :3, 3] for k in first])
    returns = []
    for k in range(n_views):
        ids, r, b = measure(T[k], pts)  # no noise; all in view (apertures default to pi)
        keep = np.array([k >= first[i] for i in ids], dtype=bool)
        returns.append((ids[keep], r[keep], b[keep]))
    U = [se3_inverse(T[k]) @ T[k + 1] for k in range(n_views - 1)]
    return T, pts, [(u, motion_cov(u, CFG)) for u in U], returns


@pytest.mark.parametrize("held", [True, False])
def test_noiseless_data_give_the_exact_poses_and_points(held: bool) -> None:
    T, pts, odo, returns = _exact_scene()
    P0 = np.zeros((6, 6)) if held else np.diag([0.01**2] * 3 + [0.02**2] * 3)
    rng = np.random.default_rng(3)
    # Start 2-3 cm and ~1 degree off every pose (features start on their first return from there).
    init = np.stack([T[k] @ se3_exp(np.r_[0.02 * rng.normal(size=3), 0.02 * rng.normal(size=3)])
                     for k in range(len(T))])
    init[0] = T[0] if held else init[0]
    res = solve(T[0], P0, odo, returns, **SIGMAS, init_poses=init)
    assert res.success
    np.testing.assert_allclose(res.poses, T, atol=1e-6)
    for i, p in res.landmarks.items():
        np.testing.assert_allclose(p, pts[i], atol=1e-6)
    assert res.chi2 < 1e-12 and res.cost < 1e-12
    assert res.dof == 2 * sum(len(r[0]) for r in returns) - 2 * len(pts)
    assert np.all(np.linalg.eigvalsh(res.covariance[6 * held :, 6 * held :]) > 0)
    if held:
        np.testing.assert_array_equal(res.pose_cov[0], 0.0)


def _numeric_jacobian(problem: BatchProblem, T: np.ndarray, L: dict, eps: float = 1e-6) -> np.ndarray:
    """Central differences of the whitened residuals in the local coordinates of linearize()."""
    ids = problem.landmark_ids
    cols = []
    for k in range(len(T)):
        for a in range(6):
            d = np.zeros(6)
            d[a] = eps
            Tp, Tm = T.copy(), T.copy()
            Tp[k], Tm[k] = T[k] @ se3_exp(d), T[k] @ se3_exp(-d)
            cols.append((problem.linearize(Tp, L)[0] - problem.linearize(Tm, L)[0]) / (2 * eps))
    for i in ids:
        for a in range(3):
            Lp, Lm = dict(L), dict(L)
            Lp[i] = L[i] + eps * np.eye(3)[a]
            Lm[i] = L[i] - eps * np.eye(3)[a]
            cols.append((problem.linearize(T, Lp)[0] - problem.linearize(T, Lm)[0]) / (2 * eps))
    return np.stack(cols, axis=1)


def test_jacobian_matches_finite_differences_inside_its_sparsity_pattern() -> None:
    cfg = PrismConfig(n_views=5)
    run = simulate(4, cfg)
    problem = _problem(run, pose_cov0=np.diag([0.02**2] * 3 + [0.01**2] * 3))
    rng = np.random.default_rng(1)
    # Away from the solution (large prior/odometry residuals exercise J_r^-1 of SE(3)).
    T = np.stack([t @ se3_exp(0.05 * rng.normal(size=6)) for t in run_odometry(run)])
    L = {i: run.points_W[i] + 0.03 * rng.normal(size=3) for i in problem.landmark_ids}
    f, J = problem.linearize(T, L)
    Jn = _numeric_jacobian(problem, T, L)
    S = problem.jacobian_sparsity().toarray()
    assert f.shape == (problem.n_residuals,) and J.shape == Jn.shape == S.shape
    scale = np.abs(Jn).max()
    assert np.all(np.abs(Jn[S == 0]) <= 1e-7 * scale), "a non-zero derivative outside the pattern"
    assert np.all(S[J.toarray() != 0] == 1)
    np.testing.assert_allclose(J.toarray(), Jn, atol=1e-6 * scale, rtol=1e-5)


@pytest.fixture(scope="module")
def prism_pairs():
    out = []
    for seed in range(8):
        run = simulate(seed)
        out.append((run, run_filter(run), _problem(run)))
    return out


def test_batch_is_the_map_of_the_ekf_model_on_the_prism(prism_pairs) -> None:
    err_b, err_e, err_o, pose_b, nees_pose, nees_lm, chi2s, dofs = [], [], [], [], [], [], [], []
    for run, tr, problem in prism_pairs:
        res = problem.solve()
        assert res.success and res.n_iterations < 30
        L_ekf = {i: tr.landmarks[-1][i] for i in problem.landmark_ids}
        # It is the minimum of its objective: the EKF's (filtered) estimate costs more.
        assert problem.cost(tr.T_W_S, L_ekf) >= res.cost
        assert problem.cost(res.poses, res.landmarks) == pytest.approx(res.cost, rel=1e-9)
        err_b.append(_landmark_error(res.landmarks, run.points_W))
        err_e.append(_landmark_error(L_ekf, run.points_W))
        err_o.append(np.linalg.norm(run_odometry(run)[-1, :3, 3] - run.T_W_S[-1, :3, 3]))
        pose_b.append(np.linalg.norm(res.poses[-1, :3, 3] - run.T_W_S[-1, :3, 3]))
        e = pose_error(res.poses[-1], run.T_W_S[-1])
        nees_pose.append(e @ np.linalg.solve(res.pose_cov[-1], e))
        el = np.concatenate([run.points_W[i] - res.landmarks[i] for i in res.landmark_ids])
        o = 6 * len(res.poses)
        nees_lm.append(el @ np.linalg.solve(res.covariance[o:, o:], el))
        chi2s.append(res.chi2)
        dofs.append(res.dof)
    S = len(prism_pairs)
    # Same model, same data: the MAP is at least as good as the filter on average (5 % slack:
    # the MAP minimises the posterior cost, not each realisation's error).
    assert np.mean(err_b) <= 1.05 * np.mean(err_e), (np.mean(err_b), np.mean(err_e))
    assert np.mean(pose_b) < np.mean(err_o)
    # And honest: NEES of the last pose and of the features, and the residual chi-square,
    # inside their 99 % bands over the seeds.
    for v, dof in ((nees_pose, 6), (nees_lm, 24)):
        lo, hi = chi2.ppf([0.005, 0.995], dof * S) / S
        assert lo <= np.mean(v) <= hi, (np.mean(v), lo, hi)
    lo, hi = chi2.ppf([0.005, 0.995], sum(dofs))
    assert lo <= sum(chi2s) <= hi


def test_huber_loss_down_weights_one_outlier_return(prism_pairs) -> None:
    run = prism_pairs[0][0]
    k, q = 10, 3  # view 10, its fourth return (not a first sighting)
    i = int(run.ids[k][q])
    clean = _problem(run).solve()
    ranges = [r.copy() for r in run.ranges_m]
    ranges[k][q] += 0.3  # 100 sigma
    bad = BatchProblem(run.T_W_S[0], np.zeros((6, 6)), list(zip(run.U_odo, run.Q, strict=True)),
                       list(zip(run.ids, ranges, run.bearings_rad, strict=True)), **SIGMAS)
    lin, hub = bad.solve(), bad.solve(loss="huber", f_scale=3.0)
    soft = bad.solve(loss="soft_l1", f_scale=3.0)
    d_lin = np.linalg.norm(lin.landmarks[i] - clean.landmarks[i])
    d_hub = np.linalg.norm(hub.landmarks[i] - clean.landmarks[i])
    d_soft = np.linalg.norm(soft.landmarks[i] - clean.landmarks[i])
    assert d_lin > 5e-3  # the outlier drags the quadratic MAP by millimetres...
    assert d_hub < 0.1 * d_lin and d_soft < 0.1 * d_lin  # ...and the robust ones hardly move
    pos = [np.linalg.norm(r.poses[:, :3, 3] - clean.poses[:, :3, 3], axis=1).max() for r in (lin, hub)]
    assert pos[1] < 0.1 * pos[0]
    # The robust objective is what it reports, and the outlier's weight is tiny.
    assert bad.cost(hub.poses, hub.landmarks, "huber", 3.0) == pytest.approx(hub.cost, rel=1e-9)
    assert np.trace(hub.landmark_cov[i]) >= np.trace(clean.landmark_cov[i])


def _bad_calls():
    T, _, odo, ret = _exact_scene(n_views=3)
    ok = dict(T_W_S0=T[0], pose_cov0=np.zeros((6, 6)), odometry=odo, returns=ret, **SIGMAS)
    bad_T = T[0].copy()
    bad_T[0, 0] = 2.0
    neg = np.diag([-1e-4] + [1e-4] * 5)
    cases = [
        (dict(T_W_S0=bad_T), ValueError),
        (dict(pose_cov0=np.eye(5)), ValueError),
        (dict(pose_cov0=neg), ValueError),
        (dict(pose_cov0=np.full((6, 6), np.nan)), ValueError),
        (dict(pose_cov0=np.eye(6).astype(complex)), TypeError),
        (dict(odometry=[(odo[0][0], np.zeros((6, 6)))] + odo[1:]), ValueError),  # motion_cov must be PD
        (dict(odometry=[(odo[0][0],)] + odo[1:]), ValueError),
        (dict(odometry=odo[:1]), ValueError),  # views and odometry disagree
        (dict(returns=[(ret[0][0].astype(float), *ret[0][1:])] + ret[1:]), TypeError),
        (dict(returns=[(np.r_[0, 0], np.r_[2.0, 2.0], np.r_[0.0, 0.0])] + ret[1:]), ValueError),
        (dict(returns=[(ret[0][0], -ret[0][1], ret[0][2])] + ret[1:]), ValueError),
        (dict(returns=[(ret[0][0], ret[0][1][:-1], ret[0][2])] + ret[1:]), ValueError),
        (dict(returns=[(ret[0][0], ret[0][1], ret[0][2] * np.nan)] + ret[1:]), ValueError),
        (dict(range_sigma_m=0.0), ValueError),
        (dict(vfov_rad=4.0), ValueError),
        (dict(bearing_sigma_rad="0.1"), TypeError),
    ]
    return ok, cases


OK, CASES = _bad_calls()


@pytest.mark.parametrize(("change", "exc"), CASES, ids=[f"{next(iter(c))}{i}" for i, (c, _) in
                                                         enumerate(CASES)])
def test_bad_input_raises(change: dict, exc: type) -> None:
    with pytest.raises(exc, match="Expected"):
        solve(**(OK | change))


def test_bad_solve_and_cost_arguments_raise() -> None:
    problem = BatchProblem(**OK)
    T, L = problem.initial_guess()
    good = {i: L[j] for j, i in enumerate(problem.landmark_ids)}
    with pytest.raises(ValueError, match="Expected loss"):
        problem.solve(loss="tukey")
    with pytest.raises(ValueError, match="f_scale"):
        problem.solve(loss="huber", f_scale=0.0)
    with pytest.raises(ValueError, match="shape"):
        problem.solve(init_poses=T[:-1])
    with pytest.raises(ValueError, match="unknown"):
        problem.solve(init_landmarks={99: np.zeros(3)})
    with pytest.raises(ValueError, match="missing"):
        problem.cost(T, {i: v for i, v in good.items() if i != problem.landmark_ids[0]})
    with pytest.raises(ValueError, match="finite"):
        problem.cost(T, good | {problem.landmark_ids[0]: np.array([np.nan, 0, 0])})


@pytest.mark.parametrize("angle", [0.0, 1e-3, 0.19, 0.21, 1.5])
def test_se3_right_jacobian_inverse_matches_finite_differences_of_log(angle: float) -> None:
    from gpumap.ekf.batch import _se3_right_jacobian_inv
    from gpumap.lie import se3_log

    rng = np.random.default_rng(5)
    xi = np.r_[rng.normal(size=3), rng.normal(size=3)]
    xi[3:] *= angle / max(np.linalg.norm(xi[3:]), 1e-300)
    T = se3_exp(xi)
    eps = 1e-6
    num = np.stack([(se3_log(T @ se3_exp(eps * e)) - se3_log(T @ se3_exp(-eps * e))) / (2 * eps)
                    for e in np.eye(6)], axis=1)
    np.testing.assert_allclose(_se3_right_jacobian_inv(xi), num, atol=1e-7)


def test_sparse_lsmr_steps_reach_the_dense_solution(prism_pairs, monkeypatch) -> None:
    import gpumap.ekf.batch

    problem = prism_pairs[1][2]
    dense = problem.solve()
    monkeypatch.setattr(gpumap.ekf.batch, "DENSE_MAX_UNKNOWNS", 0)
    sparse = problem.solve()
    assert sparse.success and sparse.n_iterations < 30
    np.testing.assert_allclose(sparse.poses, dense.poses, atol=1e-8)
    for i in dense.landmarks:
        np.testing.assert_allclose(sparse.landmarks[i], dense.landmarks[i], atol=1e-8)
    assert sparse.cost == pytest.approx(dense.cost, rel=1e-9)
