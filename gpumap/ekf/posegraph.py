"""A pose graph over the pings: odometry edges and loop closures from verified revisits.

Issue 39. Every ping is a node ``T_i`` (``T_W_S``, the first one fixed: the start is known).
Two kinds of edge, each a relative pose ``Z`` between two nodes with a (6, 6) covariance in the
right perturbation (translation then rotation, as :mod:`gpumap.ekf.loop`):

- odometry ``(i - 1, i)``: ``Z = U_i`` with covariance ``Q`` (:func:`gpumap.ekf.loop.motion_cov`);
- loop closure ``(j, k)``: ping ``k`` was taken at ``T_j Exp(delta)``, a revisit that
  :class:`~gpumap.ekf.registrar.ScanRegistrar` found and verified (its :attr:`closures`):
  ``Z = Exp(delta)``, covariance ``R`` (the in-plane registration's own, plus its prior on
  the unseen height, roll and pitch).

The residual of an edge ``(a, b, Z)`` is ``r = Log(Z^-1 T_a^-1 T_b)``; :meth:`PoseGraph.solve`
minimises ``sum r^T cov^-1 r`` by Gauss-Newton over right perturbations ``T_i <- T_i Exp(xi_i)``
(``dr/dxi_b = Jr^-1(r)``, ``dr/dxi_a = -Jr^-1(r) Ad(T_b^-1 T_a)``, ``Jr^-1(r) ~ I + ad(r) / 2``),
each step a sparse symmetric solve (``scipy.sparse.linalg.spsolve``, SuperLU). Unlike the
filter's revisit (:func:`gpumap.ekf.registration.fuse_revisit`), which can only move the pose
at the revisit and after, a closure here moves every pose since the revisited ping, each by
what the odometry's covariance says it could have drifted; and the cross-covariances a filter
drops are kept.

A closure that the solution does not fit (its own chi-square over 6 dof above the gate) is
switched off and the graph solved again (:meth:`PoseGraph.solve`), so one wrong match cannot
bend the path.

Incremental (:func:`run_pose_graph`): nodes join as the pings come, each at the latest
estimate times its odometry step; the graph is solved, warm-started from the last solution,
when a burst of closures ends (a ping with no closure after some) or every ``solve_every``
closures. Why scipy and not a solver library (GTSAM's iSAM2, g2o): the graph is small (one node per
ping: 1,223 on the real run, 7,338 unknowns), a re-solve from a warm start takes a few
Gauss-Newton steps, and scipy is already a dependency; iSAM2 would re-linearise less but
brings a large compiled dependency for no change in the answer.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from gpumap.lie import se3_exp, se3_inverse, se3_log

__all__ = ["GraphRun", "PoseGraph", "run_pose_graph"]


def _hat(v: np.ndarray) -> np.ndarray:
    """(m, 3, 3) skew matrices of (m, 3) vectors."""
    z = np.zeros(len(v))
    return np.stack([np.stack([z, -v[:, 2], v[:, 1]], 1), np.stack([v[:, 2], z, -v[:, 0]], 1),
                     np.stack([-v[:, 1], v[:, 0], z], 1)], 1)


def _exp(xi: np.ndarray) -> np.ndarray:
    """(m, 4, 4) :func:`gpumap.lie.se3_exp` of (m, 6) twists."""
    rho, phi = xi[:, :3], xi[:, 3:]
    th = np.linalg.norm(phi, axis=1)
    K = _hat(phi)
    K2 = K @ K
    small = th < 1e-6
    ts = np.where(small, 1.0, th)
    a = np.where(small, 1.0 - th ** 2 / 6, np.sin(ts) / ts)
    b = np.where(small, 0.5 - th ** 2 / 24, (1 - np.cos(ts)) / ts ** 2)
    c = np.where(small, 1 / 6 - th ** 2 / 120, (ts - np.sin(ts)) / ts ** 3)
    eye = np.eye(3)[None]
    T = np.zeros((len(xi), 4, 4))
    T[:, :3, :3] = eye + a[:, None, None] * K + b[:, None, None] * K2
    T[:, :3, 3] = np.einsum("nij,nj->ni", eye + b[:, None, None] * K + c[:, None, None] * K2, rho)
    T[:, 3, 3] = 1.0
    return T


def _log(T: np.ndarray) -> np.ndarray:
    """(m, 6) :func:`gpumap.lie.se3_log` of (m, 4, 4) transforms (rotations near pi by the scalar one)."""
    R, t = T[:, :3, :3], T[:, :3, 3]
    c = np.clip((np.trace(R, axis1=1, axis2=2) - 1) / 2, -1.0, 1.0)
    th = np.arccos(c)
    v = np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], 1)
    small = th < 1e-6
    ts = np.where(small, 1.0, th)
    phi = v * np.where(small, 0.5 + th ** 2 / 12, ts / (2 * np.sin(ts)))[:, None]
    K = _hat(phi)
    d = np.where(small, 1 / 12 + th ** 2 / 720, (1 - ts * np.sin(ts) / (4 * np.sin(0.5 * ts) ** 2)) / ts ** 2)
    rho = np.einsum("nij,nj->ni", np.eye(3)[None] - 0.5 * K + d[:, None, None] * (K @ K), t)
    out = np.concatenate([rho, phi], axis=1)
    for i in np.flatnonzero(th > 3.0):
        out[i] = se3_log(T[i])
    return out


def _inv(T: np.ndarray) -> np.ndarray:
    Ti = np.zeros_like(T)
    Rt = np.transpose(T[:, :3, :3], (0, 2, 1))
    Ti[:, :3, :3] = Rt
    Ti[:, :3, 3] = -np.einsum("nij,nj->ni", Rt, T[:, :3, 3])
    Ti[:, 3, 3] = 1.0
    return Ti


def _adjoint(T: np.ndarray) -> np.ndarray:
    R = T[:, :3, :3]
    A = np.zeros((len(T), 6, 6))
    A[:, :3, :3] = R
    A[:, 3:, 3:] = R
    A[:, :3, 3:] = _hat(T[:, :3, 3]) @ R
    return A


def _ad(xi: np.ndarray) -> np.ndarray:
    A = np.zeros((len(xi), 6, 6))
    P = _hat(xi[:, 3:])
    A[:, :3, :3] = P
    A[:, 3:, 3:] = P
    A[:, :3, 3:] = _hat(xi[:, :3])
    return A


@dataclass
class GraphRun:
    """What :func:`run_pose_graph` produced.

    Attributes
    ----------
    poses : (n, 4, 4) float64
        The graph's poses after the last solve (smoothed: every pose uses every closure).
    online : (n, 4, 4) float64
        Each ping's pose as the graph knew it when that ping came (the latest node after that
        ping's solve, if any): what a vehicle could have used then.
    solves : int
        Solves run.
    loops, loops_rejected : int
        Closures added, and of them those switched off by the gate at the last solve.
    ms_per_ping : (n,) float64
        Time spent per ping (adding the node and edges, and any solve).
    """

    poses: np.ndarray
    online: np.ndarray
    solves: int
    loops: int
    loops_rejected: int
    ms_per_ping: np.ndarray
    stats: dict = field(default_factory=dict)


def _sqrt_info(cov: np.ndarray, name: str) -> np.ndarray:
    c = np.asarray(cov, np.float64)
    if c.shape != (6, 6) or not np.all(np.isfinite(c)):
        raise ValueError(f"Expected a finite (6, 6) covariance for '{name}', but got shape {c.shape}")
    w, V = np.linalg.eigh(0.5 * (c + c.T))
    if w.min() <= 0:
        raise ValueError(f"Expected a positive definite covariance for '{name}', but its smallest "
                         f"eigenvalue is {w.min():.3g}")
    return (V / np.sqrt(w)).T  # W^T W = cov^-1


class PoseGraph:
    """Nodes (poses) and edges (relative poses with covariances), solved by sparse Gauss-Newton.

    Parameters
    ----------
    T0 : (4, 4) float
        The first node's pose, held fixed.
    gate_prob : float
        A loop closure whose chi-square (6 dof) at the solution is above this quantile is
        switched off (module docstring); odometry edges are never switched off.
    iterations : int
        Most Gauss-Newton steps per solve (it stops earlier when a step moves every pose by
        less than 1e-5: 10 um, 10 urad).
    """

    def __init__(self, T0: np.ndarray, *, gate_prob: float = 0.999, iterations: int = 8) -> None:
        from scipy.stats import chi2

        from gpumap.errors import check_pose

        if iterations < 1:
            raise ValueError(f"Expected iterations >= 1, but got {iterations}")
        self._T = np.zeros((64, 4, 4))
        self._T[0] = np.array(check_pose(T0, "T0"), np.float64)
        self._n = 1
        self._a: list[int] = []  # per edge: from, to, inverse measurement, square-root information, loop
        self._b: list[int] = []
        self._Zi: list[np.ndarray] = []
        self._W: list[np.ndarray] = []
        self._loop: list[bool] = []
        self.active = np.ones(0, bool)
        self.gate = float(chi2.ppf(gate_prob, 6))
        self.iterations = int(iterations)

    @property
    def n(self) -> int:
        return self._n

    @property
    def poses(self) -> np.ndarray:
        """(n, 4, 4) the current estimates."""
        return self._T[:self._n].copy()

    def _edge(self, a: int, b: int, Z_inv: np.ndarray, W: np.ndarray, loop: bool) -> None:
        self._a.append(a)
        self._b.append(b)
        self._Zi.append(Z_inv)
        self._W.append(W)
        self._loop.append(loop)
        self.active = np.append(self.active, True)

    def add_odometry(self, U: np.ndarray, Q: np.ndarray) -> int:
        """A new node at the last one's estimate times ``U`` ((4, 4)), joined to it by ``U`` with
        covariance ``Q`` ((6, 6)); returns its index."""
        U = np.asarray(U, np.float64)
        if U.shape != (4, 4):
            raise ValueError(f"Expected a (4, 4) odometry step, but got shape {U.shape}")
        i = self._n
        if i == len(self._T):
            self._T = np.concatenate([self._T, np.zeros_like(self._T)])
        self._T[i] = self._T[i - 1] @ U
        self._n += 1
        self._edge(i - 1, i, se3_inverse(U), _sqrt_info(Q, "Q"), False)
        return i

    def add_loop(self, j: int, k: int, delta: np.ndarray, R: np.ndarray) -> None:
        """A closure: node ``k`` at ``T_j Exp(delta)`` ((6,)), covariance ``R`` ((6, 6))."""
        if not (0 <= j < self._n and 0 <= k < self._n and j != k):
            raise ValueError(f"Expected two distinct nodes below {self._n}, but got {j} and {k}")
        d = np.asarray(delta, np.float64)
        if d.shape != (6,) or not np.all(np.isfinite(d)):
            raise ValueError(f"Expected a finite (6,) 'delta', but got {d}")
        self._edge(j, k, se3_exp(-d), _sqrt_info(R, "R"), True)

    def _arrays(self):
        return (np.array(self._a), np.array(self._b), np.stack(self._Zi), np.stack(self._W),
                np.array(self._loop))

    def _residuals(self, a, b, Zi) -> np.ndarray:
        T = self._T
        return _log(Zi @ _inv(T[a]) @ T[b])

    def chi2(self) -> np.ndarray:
        """(edges,) each edge's squared Mahalanobis residual at the current estimates."""
        a, b, Zi, W, _ = self._arrays()
        w = np.einsum("nij,nj->ni", W, self._residuals(a, b, Zi))
        return np.einsum("ni,ni->n", w, w)

    def _step(self, a, b, Zi, W) -> float:
        from scipy.sparse import coo_matrix
        from scipy.sparse.linalg import spsolve

        n = self._n
        r = self._residuals(a, b, Zi)
        Jb = W @ (np.eye(6)[None] + 0.5 * _ad(r))
        Ja = -Jb @ _adjoint(_inv(self._T[b]) @ self._T[a])
        w = np.einsum("nij,nj->ni", W, r)
        g = np.zeros((n, 6))
        np.add.at(g, a, np.einsum("nji,nj->ni", Ja, w))
        np.add.at(g, b, np.einsum("nji,nj->ni", Jb, w))
        blocks, rows, cols = [], [], []
        i6 = np.arange(6)
        for p, Jp in ((a, Ja), (b, Jb)):
            for q, Jq in ((a, Ja), (b, Jb)):
                blocks.append(np.transpose(Jp, (0, 2, 1)) @ Jq)  # (m, 6, 6)
                rows.append((6 * p[:, None, None] + i6[None, :, None]).repeat(6, 2))
                cols.append((6 * q[:, None, None] + i6[None, None, :]).repeat(6, 1))
        ij = (np.concatenate(rows).ravel(), np.concatenate(cols).ravel())
        H = coo_matrix((np.concatenate(blocks).ravel(), ij), shape=(6 * n, 6 * n))
        H = H.tocsc()[6:, 6:]  # node 0 fixed
        xi = np.asarray(spsolve(H, -g.ravel()[6:]), np.float64).reshape(n - 1, 6)
        self._T[1:n] = self._T[1:n] @ _exp(xi)
        return float(np.abs(xi).max()) if len(xi) else 0.0

    def _gauss_newton(self) -> int:
        a, b, Zi, W, _ = self._arrays()
        on = self.active
        for it in range(1, self.iterations + 1):
            if self._step(a[on], b[on], Zi[on], W[on]) < 1e-5:
                return it
        return self.iterations

    def solve(self) -> dict:
        """Gauss-Newton to convergence, then switch off the worst closure above the gate and
        solve again, until every active one fits; closures the final solution fits are switched
        back on (and solved with).

        Returns
        -------
        dict
            ``iterations`` (Gauss-Newton steps), ``loops_active``, ``loops_rejected``.
        """
        if self._n < 2:
            return {"iterations": 0, "loops_active": 0, "loops_rejected": 0}
        loop = np.array(self._loop)
        its = self._gauss_newton()
        for _ in range(int(loop.sum()) + 1):
            c = self.chi2()
            bad = np.flatnonzero(loop & self.active & (c > self.gate))
            if len(bad):
                self.active[bad[np.argmax(c[bad])]] = False
                its += self._gauss_newton()
                continue
            back = np.flatnonzero(loop & ~self.active & (c <= self.gate))
            if not len(back):
                break
            self.active[back] = True
            its += self._gauss_newton()
        return {"iterations": its, "loops_active": int((loop & self.active).sum()),
                "loops_rejected": int((loop & ~self.active).sum())}


def run_pose_graph(U: np.ndarray, Q: np.ndarray, T0: np.ndarray, closures, *, solve_every: int = 10,
                   gate_prob: float = 0.999, iterations: int = 8, on_solve=None) -> GraphRun:
    """The pose graph built and solved ping by ping (module docstring).

    Parameters
    ----------
    U : (n, 4, 4) float
        Odometry steps (``U[0]`` unused), as :func:`gpumap.ekf.loop.run_ekf_loop` takes them.
    Q : (6, 6) float
        Covariance of each step.
    T0 : (4, 4) float
        The first ping's pose (fixed).
    closures : iterable of (k, j, delta, R, ...)
        Loop closures (:attr:`gpumap.ekf.registrar.ScanRegistrar.closures`): ping ``k`` at
        ``T_j Exp(delta)`` ((6,)) with covariance ``R`` ((6, 6)); ``j < k < n``. Further tuple
        items are ignored.
    solve_every : int
        Solve at least every this many closures within a burst.
    on_solve : callable, optional
        ``on_solve(k, poses)`` after each solve: ``k`` the latest ping, ``poses`` ((k + 1, 4, 4))
        the solution (e.g. :meth:`gpumap.ekf.submaps.SegmentMaps.update`); not timed.

    Returns
    -------
    GraphRun
    """
    U = np.asarray(U, np.float64)
    if U.ndim != 3 or U.shape[1:] != (4, 4):
        raise ValueError(f"Expected odometry steps of shape (n, 4, 4), but got {U.shape}")
    if solve_every < 1:
        raise ValueError(f"Expected solve_every >= 1, but got {solve_every}")
    n = len(U)
    by_k: dict[int, list] = {}
    for c in closures:
        k, j = int(c[0]), int(c[1])
        if not 0 <= j < k < n:
            raise ValueError(f"Expected a closure from an older ping j < k < {n}, but got j={j}, k={k}")
        by_k.setdefault(k, []).append(c)
    g = PoseGraph(T0, gate_prob=gate_prob, iterations=iterations)
    online = np.zeros((n, 4, 4))
    online[0] = g.poses[0]
    ms = np.zeros(n)
    pending, solves, loops, last = 0, 0, 0, {}
    for k in range(1, n):
        t0 = time.perf_counter()
        g.add_odometry(U[k], Q)
        for c in by_k.get(k, ()):
            g.add_loop(int(c[1]), k, c[2], c[3])
            pending += 1
            loops += 1
        solved = bool(pending and (k not in by_k or pending >= solve_every))
        if solved:
            last = g.solve()
            solves += 1
            pending = 0
        online[k] = g._T[k]
        ms[k] = 1e3 * (time.perf_counter() - t0)
        if solved and on_solve is not None:
            on_solve(k, g.poses)
    if pending:
        last = g.solve()
        solves += 1
        if on_solve is not None:
            on_solve(n - 1, g.poses)
    return GraphRun(g.poses, online, solves, loops, int(last.get("loops_rejected", 0)), ms,
                    {"last_solve": last})
