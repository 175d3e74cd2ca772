"""Tests of the EKF's innovation-consistency guard (issue 29): the chi-square bands it uses,
the odometry fallback (Schmidt updates that leave the pose exactly at the odometry's), and on
simulated runs: trust earned on a consistent model, odometry kept when the returns are
corrupted (sliding scatterers, as real glints are), where the plain EKF ends far worse."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
from conftest import DATA, needs_data
from gpumap.sim.prism import PrismConfig, position_ratio, simulate
from scipy.stats import chi2

from gpumap.ekf import SonarEKF
from gpumap.ekf.guard import TrustGuard, nis_band
from gpumap.ekf.motion import motion_jacobian
from gpumap.lie import se3_exp

#: A prism run long enough for the guard's long window (8 vertices x 150 views), with odometry
#: drift large enough that the features matter.
CFG = PrismConfig(n_views=150, k_t=0.1, k_r=0.05)


def _prism(seed: int, guard: TrustGuard | None, slide: float = 0.0) -> tuple[float, SonarEKF]:
    """Mean position error of the EKF over that of dead reckoning on one prism run of CFG
    (:func:`gpumap.sim.prism.position_ratio`; ``slide``: sliding scatterers)."""
    return position_ratio(simulate(seed, CFG), guard, slide, seed)


# ------------------------------------------------------------------------------ the bands
@pytest.mark.parametrize("prob, dof", [(0.99, 1), (0.99, 120), (0.999, 600), (0.9, 7)])
def test_nis_band_is_the_two_sided_chi_square_quantile_over_dof(prob, dof) -> None:
    lo, hi = nis_band(prob, dof)
    assert lo == pytest.approx(chi2.ppf((1 - prob) / 2, dof) / dof, rel=1e-12)
    assert hi == pytest.approx(chi2.ppf((1 + prob) / 2, dof) / dof, rel=1e-12)


def test_per_return_gates_use_the_quantile_of_their_measurement_dimension() -> None:
    ekf = SonarEKF(np.eye(4), np.zeros((6, 6)), range_sigma_m=0.01, bearing_sigma_rad=0.01,
                   vfov_rad=0.2, gate_prob=0.995)
    assert ekf._gate == pytest.approx(chi2.ppf(0.995, 2), rel=1e-12)  # (range, azimuth): 2 dof
    assert ekf._gate1 == pytest.approx(chi2.ppf(0.995, 1), rel=1e-12)  # a plane range: 1 dof


def _feed(g: TrustGuard, a2: float, b2: float, n: int) -> None:
    """One update of ``n`` returns with ``nu = (a, b)``, ``S = I``."""
    nu = np.tile([np.sqrt(a2), np.sqrt(b2)], (n, 1))
    g.add(np.full(n, a2 + b2), nu, np.tile(np.eye(2), (n, 1, 1)), pose_corrected=False)


@pytest.mark.parametrize("side", ["lo", "hi"])
def test_windowed_nis_band_has_two_dof_per_return(side) -> None:
    n, p = 10, 0.99
    lo, hi = (chi2.ppf((1 - p) / 2, 2 * n) / (2 * n), chi2.ppf((1 + p) / 2, 2 * n) / (2 * n))
    edge = lo if side == "lo" else hi
    inside = edge * (1.001 if side == "lo" else 0.999)
    outside = edge * (0.999 if side == "lo" else 1.001)
    for per_dof, trusted in ((inside, True), (outside, False)):
        g = TrustGuard(window=n, long_window=n, prob=p, per_component=False, hold=1)
        _feed(g, per_dof, per_dof, n)  # NIS per return 2 x per_dof, i.e. per_dof per dof
        assert g.nis_per_dof == pytest.approx(per_dof)
        assert g.trusted is trusted


def test_per_component_band_has_one_dof_per_return_and_catches_a_loose_range() -> None:
    n, p = 10, 0.99
    lo1 = chi2.ppf((1 - p) / 2, n) / n
    for a2, trusted in ((1.01 * lo1, True), (0.99 * lo1, False)):
        g = TrustGuard(window=n, long_window=n, prob=p, per_component=True, hold=1)
        _feed(g, a2, 2.0 - a2, n)  # joint NIS per dof exactly 1: only the range is off
        assert g.nis_per_dof == pytest.approx(1.0)
        assert g.trusted is trusted
        g2 = TrustGuard(window=n, long_window=n, prob=p, per_component=False, hold=1)
        _feed(g2, a2, 2.0 - a2, n)
        assert g2.trusted


def test_trust_needs_a_full_long_window_and_both_windows_in_band() -> None:
    g = TrustGuard(window=4, long_window=12, prob=0.99, per_component=False, hold=1)
    for _ in range(2):
        _feed(g, 0.5, 0.5, 4)
    assert g.returns == 4 and not g.trusted  # short window full, long one not yet
    _feed(g, 0.5, 0.5, 4)
    assert g.trusted
    for _ in range(3):
        _feed(g, 0.5, 0.5, 4)
    _feed(g, 40.0, 40.0, 1)  # one wild update: the short window leaves its band
    assert not g.trusted
    g.reset()
    assert g.returns == 0 and not g.trusted and g.updates == 7


@pytest.mark.parametrize("kw", [{"window": 0}, {"window": 5, "long_window": 4}, {"prob": 1.0},
                                {"prob": 0.0}, {"min_track_hits": -1}, {"window": True}])
def test_bad_guard_arguments_raise(kw) -> None:
    with pytest.raises((ValueError, TypeError)):
        TrustGuard(**kw)


def test_min_track_hits_keeps_young_tracks_out_of_the_window() -> None:
    g = TrustGuard(window=2, long_window=2, prob=0.99, per_component=False, min_track_hits=3)
    g.add(np.array([1.0, 50.0]), np.array([[0.7, 0.7], [5.0, 5.0]]), np.tile(np.eye(2), (2, 1, 1)),
          pose_corrected=False, track_hits=np.array([5, 1]))
    assert g.returns == 1 and g.nis_per_dof == pytest.approx(0.5)
    assert g.fused_features_only == 2


# ------------------------------------------------------------------------------ the fallback
def _filter_seeing(guard: TrustGuard | None) -> tuple[SonarEKF, np.ndarray]:
    """A filter that has seen 6 points twice (a few poses apart); the points (6, 3)."""
    rng = np.random.default_rng(3)
    pts = np.stack([rng.uniform(2.0, 3.0, 6), rng.uniform(-0.8, 0.8, 6), rng.uniform(-0.05, 0.05, 6)], 1)
    ekf = SonarEKF(np.eye(4), np.zeros((6, 6)), range_sigma_m=0.01, bearing_sigma_rad=0.005,
                   vfov_rad=np.deg2rad(14), guard=guard, nis_window=0)
    ekf.update(np.arange(6), np.linalg.norm(pts, axis=1), np.arctan2(pts[:, 1], pts[:, 0]))
    return ekf, pts


def _returns(T: np.ndarray, pts: np.ndarray, dr: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    q = (pts - T[:3, 3]) @ T[:3, :3]
    return np.linalg.norm(q, axis=1) + dr, np.arctan2(q[:, 1], q[:, 0])


@pytest.mark.parametrize("case", ["untrusted", "all_rejected"])
def test_fallback_keeps_the_odometry_increment_exactly(case) -> None:
    g = TrustGuard(window=5, long_window=5)
    ekf, pts = _filter_seeing(g)
    U = se3_exp(np.array([0.02, 0.01, 0.0, 0.0, 0.0, 0.03]))
    Q = np.diag([1e-4] * 3 + [1e-4] * 3)
    T0, P0 = ekf.pose, ekf.pose_cov
    S0 = {i: v.copy() for i, v in ekf.landmarks.items()}
    ekf.predict(U, Q)
    T_true = T0 @ U @ se3_exp(np.array([0.01, -0.01, 0.0, 0.0, 0.0, 0.01]))  # odometry is off
    r, b = _returns(T_true, pts, dr=(0.0 if case == "untrusted" else 5.0))
    if case == "all_rejected":
        g.trusted = True  # the guard would let them correct the pose, but the gate refuses all
    assert g.trusted is (case == "all_rejected")
    res = ekf.update(np.arange(6), r, b)
    np.testing.assert_allclose(ekf.pose, T0 @ U, rtol=0, atol=1e-12)
    F = motion_jacobian(U)
    np.testing.assert_allclose(ekf.pose_cov, F @ P0 @ F.T + Q, rtol=1e-9, atol=1e-15)
    if case == "untrusted":
        assert len(res.accepted_ids) == 6 and g.fused_features_only == 6 and g.fused_pose == 0
        moved = max(float(np.abs(ekf.landmarks[i] - S0[i]).max()) for i in S0)
        assert moved > 1e-4  # the features still learn from the returns
    else:
        assert not res.accepted_ids and len(res.rejected) == 6 and g.gated == 6


def test_a_trusted_guard_lets_the_same_returns_correct_the_pose() -> None:
    g = TrustGuard(window=5, long_window=5)
    ekf, pts = _filter_seeing(g)
    U = se3_exp(np.array([0.02, 0.01, 0.0, 0.0, 0.0, 0.03]))
    T0 = ekf.pose
    ekf.predict(U, np.diag([1e-4] * 6))
    g.trusted = True
    ekf.update(np.arange(6), *_returns(T0 @ U @ se3_exp(np.array([0.01, -0.01, 0, 0, 0, 0.01])), pts))
    assert float(np.abs(ekf.pose - T0 @ U).max()) > 1e-3
    assert g.fused_pose == 6 and g.pose_updates == 1


# ------------------------------------------------------------------------------ simulated runs
def test_guard_earns_trust_on_a_consistent_model_and_beats_odometry() -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        out = [_prism(s, TrustGuard()) for s in range(3)]
    ratios = [r for r, _ in out]
    # Trust comes late (a full long window, then `hold` consistent updates), so the guarded
    # EKF gives up part of the plain one's gain (0.34-0.47 here) to stay safe on real pings.
    assert np.mean(ratios) < 0.95, ratios
    assert max(ratios) <= 1.0 + 1e-9, ratios
    assert sum(ekf.guard.pose_updates for _, ekf in out) > 10


@pytest.mark.parametrize("seed", [0, 1])
def test_sliding_scatterers_leave_the_guarded_ekf_at_odometry_and_the_plain_one_far_worse(seed) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        guarded, ekf = _prism(seed, TrustGuard(), slide=0.5)
        plain, _ = _prism(seed, None, slide=0.5)
    assert guarded <= 1.03, guarded
    assert plain > 1.5, plain
    assert ekf.guard.pose_updates == 0


def test_trust_comes_after_hold_consistent_updates_in_a_row_and_goes_at_the_first_bad_one() -> None:
    g = TrustGuard(window=4, long_window=4, prob=0.99, per_component=False, hold=3)
    seen = []
    for a2 in (0.5, 0.5, 0.5, 0.5, 40.0, 0.5, 0.5, 0.5, 0.5, 0.5, 0.5, 0.5):
        _feed(g, a2, a2, 4 if a2 < 1 else 1)
        seen.append(g.trusted)
    # consistent from the first update on: trusted at the third; the wild one spoils the short
    # window until it has left it (4 more returns), then three in a row again
    assert seen == [False, False, True, True, False, False, False, True, True, True, True, True]


@needs_data
def test_replay_ekf_reports_how_much_it_trusted_the_pings(tmp_path, capsys) -> None:
    unguarded = False  # the unguarded filter is for comparison only: bench, not the command
    from gpumap.commands.replay import main

    out = tmp_path / "o"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        rc = main([str(DATA / "oasis_tank"), "--ekf", "--max-frames", "12", "--out", str(out),
                   "--backend", "numpy", "--no-pictures", "--no-progress"]
                  )
    assert rc == 0
    t = json.loads((out / "summary.json").read_text())["ekf"]["trust"]
    assert t["guard"] is (not unguarded)
    for k in ("fused_with_pose", "fused_features_only", "gated", "pings_pose_corrected_share",
              "window_nis_per_dof", "returns", "paired"):
        assert k in t
    if not unguarded:  # 12 pings never fill the long window: the pose is the odometry's
        assert t["fused_with_pose"] == 0 and t["pings_pose_corrected_share"] == 0.0
        assert t["guard_state"]["trusted_now"] is False
    assert "trust in the pings:" in capsys.readouterr().out
