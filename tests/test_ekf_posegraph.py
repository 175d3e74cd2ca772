"""The pose graph (gpumap.ekf.posegraph) against analytic cases: a linear chain with one closure
(least squares by hand), a drifting loop closed by exact revisits, and a false closure."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import DATA, needs_data

from gpumap.core.params import MapperParams
from gpumap.ekf import posegraph as pg
from gpumap.ekf.loop import drifting_odometry, motion_cov, pose_errors
from gpumap.ekf.posegraph import PoseGraph, run_pose_graph
from gpumap.lie import se3_adjoint, se3_exp, se3_inverse, se3_log


def test_batched_lie_functions_match_the_scalar_ones():
    rng = np.random.default_rng(0)
    xi = rng.normal(size=(40, 6)) * [0.5, 0.5, 0.5, 0.6, 0.6, 0.6]
    ang = np.linalg.norm(xi[:, 3:], axis=1, keepdims=True)
    xi[:, 3:] *= np.minimum(1.0, 2.5 / ang)  # Log returns angles below pi
    xi[0] = 0.0
    xi[1, 3:] = 1e-9  # the small-angle branches
    xi[2, 3:] = [0.0, 3.1, 0.0]  # near pi: the scalar fallback
    T = np.stack([se3_exp(x) for x in xi])
    np.testing.assert_allclose(pg._exp(xi), T, atol=1e-12)
    np.testing.assert_allclose(pg._log(T), xi, atol=1e-9)
    np.testing.assert_allclose(pg._adjoint(T), np.stack([se3_adjoint(t) for t in T]), atol=1e-12)
    np.testing.assert_allclose(pg._inv(T), np.stack([se3_inverse(t) for t in T]), atol=1e-12)


def test_without_closures_the_graph_is_the_odometry():
    T_true = np.stack([se3_exp(np.array([0.01 * k, 0.0, 0.0, 0.0, 0.0, 0.02 * k])) for k in range(30)])
    U, T_odo = drifting_odometry(T_true, 0.003, 0.003, 1)
    r = run_pose_graph(U, motion_cov(0.003, 0.003), T_true[0], [])
    np.testing.assert_allclose(r.poses, T_odo, atol=1e-12)
    np.testing.assert_allclose(r.online, T_odo, atol=1e-12)
    assert r.solves == 0 and r.loops == 0


def test_one_closure_on_a_straight_chain_spreads_its_error_as_least_squares_says():
    # translation along x only: the problem is linear. Steps u_i with variance q, a closure from
    # node 0 to node n with variance r: every step gets c = (L - sum u) q / (r + n q)
    n, q, r = 8, 0.01 ** 2, 0.02 ** 2
    u = np.linspace(0.05, 0.12, n)
    L = u.sum() + 0.09
    cov_q = np.diag([q, q, q, 1e-6, 1e-6, 1e-6])
    cov_r = np.diag([r, r, r, 1e-6, 1e-6, 1e-6])
    g = PoseGraph(np.eye(4))
    for ui in u:
        g.add_odometry(se3_exp(np.array([ui, 0, 0, 0, 0, 0])), cov_q)
    g.add_loop(0, n, np.array([L, 0, 0, 0, 0, 0]), cov_r)
    out = g.solve()
    assert out["loops_rejected"] == 0
    c = (L - u.sum()) * q / (r + n * q)
    x = g.poses[:, 0, 3]
    np.testing.assert_allclose(np.diff(x), u + c, atol=1e-9)
    np.testing.assert_allclose(g.poses[:, :3, :3], np.broadcast_to(np.eye(3), (n + 1, 3, 3)), atol=1e-12)


def _circle(n: int = 120) -> np.ndarray:
    """Twice round a circle of 1 m radius, facing along it (the second lap revisits the first)."""
    a = np.linspace(0, 4 * np.pi, n, endpoint=False)
    T = np.zeros((n, 4, 4))
    for i, t in enumerate(a):
        T[i] = se3_exp(np.array([0, 0, 0, 0, 0, t]))
        T[i, :3, 3] = [np.cos(t), np.sin(t), 0.1 * np.sin(3 * t)]
    return T


def _closures(T_true: np.ndarray, sigma: tuple[float, float] = (0.002, 0.002)):
    n = len(T_true)
    R = np.diag([sigma[0] ** 2] * 3 + [sigma[1] ** 2] * 3)
    return [(k, k - n // 2, se3_log(se3_inverse(T_true[k - n // 2]) @ T_true[k]), R)
            for k in range(n // 2, n)]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_exact_revisits_take_most_of_the_drift_out(seed):
    T_true = _circle()
    U, T_odo = drifting_odometry(T_true, 0.01, 0.01, seed)
    r = run_pose_graph(U, motion_cov(0.01, 0.01), T_true[0], _closures(T_true))
    eo, eg = pose_errors(T_odo, T_true), pose_errors(r.poses, T_true)
    assert eg["position_m"]["mean"] < 0.5 * eo["position_m"]["mean"]
    assert eg["rotation_rad"]["mean"] < 0.5 * eo["rotation_rad"]["mean"]
    assert r.loops == len(T_true) // 2 and r.loops_rejected == 0 and r.solves >= 1
    # every closure holds at the solution to within a few of its sigmas
    for k, j, d, _ in _closures(T_true):
        res = se3_log(se3_inverse(r.poses[j] @ se3_exp(d)) @ r.poses[k])
        assert np.abs(res).max() < 0.02


def test_a_false_closure_is_switched_off():
    T_true = _circle()
    U, _ = drifting_odometry(T_true, 0.01, 0.01, 0)
    good = _closures(T_true)
    bad = (100, 10, np.array([0.5, -0.4, 0.0, 0.0, 0.0, 0.8]), good[0][3])
    Q = motion_cov(0.01, 0.01)
    clean = run_pose_graph(U, Q, T_true[0], good)
    r = run_pose_graph(U, Q, T_true[0], [*good, bad])
    assert r.loops_rejected == 1
    np.testing.assert_allclose(r.poses[:, :3, 3], clean.poses[:, :3, 3], atol=1e-4)


def test_bad_input_is_refused_with_what_was_expected():
    g = PoseGraph(np.eye(4))
    with pytest.raises(ValueError, match="positive definite"):
        g.add_odometry(np.eye(4), np.zeros((6, 6)))
    g.add_odometry(np.eye(4), np.eye(6))
    with pytest.raises(ValueError, match="two distinct nodes"):
        g.add_loop(0, 5, np.zeros(6), np.eye(6))
    with pytest.raises(ValueError, match="older ping"):
        run_pose_graph(np.stack([np.eye(4)] * 3), np.eye(6), np.eye(4), [(1, 2, np.zeros(6), np.eye(6))])


@needs_data
def test_segment_maps_merge_to_the_map_of_every_ping_and_remap_only_what_moved():
    from gpumap import MinMaxMapper
    from gpumap.ekf.submaps import SegmentMaps
    from gpumap.io import open_recording
    from gpumap.pipeline.ekf_replay import posed_frames
    from gpumap.spec import auto_grid

    images, T, spec = posed_frames(open_recording(DATA / "oasis_tank"), max_frames=24)
    grid = auto_grid(spec, list(T), 0.1)

    def direct(poses):
        m = MinMaxMapper(spec, grid, "numpy", MapperParams(threshold=0.4))
        m.integrate_batch(np.stack(images), poses)
        return m.values()

    sm = SegmentMaps(spec, grid, segment=5, backend="numpy")
    assert sm.update(images, T) == [0, 1, 2, 3, 4]
    np.testing.assert_array_equal(sm.values(), direct(T))  # exact, NaN where unknown
    moved = T.copy()
    moved[12:15, :3, 3] += [0.03, -0.02, 0.0]  # inside segment 2 only
    assert sm.update(images, moved) == [2]
    np.testing.assert_array_equal(sm.values(), direct(moved))
    assert sm.update(images, moved) == [] and sm.integrations == 6
