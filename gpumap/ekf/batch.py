"""Batch MAP over all sonar poses and point features: the EKF's yardstick, and a smoother.

Solves at once the model that :class:`gpumap.ekf.SonarEKF` filters, by nonlinear least squares
(:func:`scipy.optimize.least_squares`, method ``"trf"``, analytic sparse Jacobian). Factors:

- **first pose**: ``T_0 = T_W_S0 @ Exp(d)``, ``d ~ N(0, pose_cov0)``; an all-zero ``pose_cov0``
  holds ``T_0`` at ``T_W_S0`` (the world is the first sonar frame);
- **odometry**, as ``SonarEKF.predict``: ``T_k+1 = T_k @ U_k @ Exp(w_k)``, ``w_k ~ N(0, motion_cov_k)``;
- **returns**: ``(range, azimuth)`` of ``p_S = T_k^-1 p_W`` plus ``N(0, diag(range_sigma^2,
  bearing_sigma^2))``, the azimuth residual wrapped by :func:`gpumap.ekf.wrap_angle`;
- **elevation prior**, as the EKF's new features: the elevation of ``p_W`` in the sonar frame
  where it is first seen is ``N(0, vfov^2 / 12)`` (the moments of ``U(-vfov/2, vfov/2)``).

Pose errors are right perturbations ``(rho m, phi rad)`` (:mod:`gpumap.lie`); features are world
Cartesian metres. A robust loss acts on the range/azimuth residuals only (whitened, so ``f_scale``
is in sigmas); the other factors stay quadratic. Covariances are the inverse of the Gauss-Newton
information ``J^T W J`` at the solution (``W``: the loss's weights, 1 for ``"linear"``), inverted
densely (fine up to a few thousand unknowns; the Jacobian itself is sparse).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.optimize
import scipy.sparse as sp
import threadpoolctl

from gpumap.ekf.measurement import spherical_point, wrap_angle
from gpumap.errors import check_finite_scalar, check_pose
from gpumap.lie import orthonormalize, se3_ad, se3_adjoint, se3_inverse, se3_log, so3_exp, so3_right_jacobian

__all__ = ["LOSSES", "BatchProblem", "BatchResult", "solve"]

#: Robust losses ``rho(u)`` of ``u = (f / f_scale)^2`` and their first two derivatives (scipy's).
LOSSES = {
    "linear": lambda u: (u, np.ones_like(u), np.zeros_like(u)),
    "huber": lambda u: (np.where(u > 1, 2 * np.sqrt(np.maximum(u, 1)) - 1, u),
                        np.where(u > 1, np.maximum(u, 1) ** -0.5, 1.0),
                        np.where(u > 1, -0.5 * np.maximum(u, 1) ** -1.5, 0.0)),
    "soft_l1": lambda u: (2 * (np.sqrt(1 + u) - 1), (1 + u) ** -0.5, -0.5 * (1 + u) ** -1.5),
}
#: Up to this many unknowns the trust-region steps are exact (dense SVD), above by sparse LSMR (its
#: tolerances at 1e-10: at scipy's 1e-6 it took 500 iterations instead of 6 on the 21-view prism).
DENSE_MAX_UNKNOWNS = 1000


@dataclass(frozen=True)
class BatchResult:
    """MAP estimate and its Gauss-Newton covariance.

    ``poses (n, 4, 4)``: ``T_W_S`` per view. ``landmarks``: id -> ``(3,)`` world position (m).
    ``landmark_ids``: feature order in ``covariance (6n + 3L, 6n + 3L)``, whose rows ``6k:6k+6``
    are pose ``k``'s right perturbation (zero for a held first pose), then the features'
    positions. ``cost``: ``0.5 sum rho(f^2)`` of the whitened residuals ``f`` (scipy's);
    ``chi2``: ``sum f^2`` (``~ chi2(dof)`` when the model holds), ``dof`` = residuals - unknowns;
    ``n_iterations``: Jacobian evaluations; ``success``, ``message``: the solver's.
    """

    poses: np.ndarray
    landmarks: dict[int, np.ndarray]
    landmark_ids: tuple[int, ...]
    covariance: np.ndarray
    cost: float
    chi2: float
    dof: int
    n_iterations: int
    success: bool
    message: str

    @property
    def pose_cov(self) -> np.ndarray:
        """(n, 6, 6) float64 covariance of each pose's right perturbation."""
        C, k = self.covariance, 6 * np.arange(len(self.poses))
        return C[k[:, None, None] + np.arange(6)[:, None], k[:, None, None] + np.arange(6)]

    @property
    def landmark_cov(self) -> dict[int, np.ndarray]:
        """Feature id -> (3, 3) float64 covariance of its world position."""
        o = 6 * len(self.poses)
        return {i: self.covariance[o + 3 * j : o + 3 * j + 3, o + 3 * j : o + 3 * j + 3].copy()
                for j, i in enumerate(self.landmark_ids)}


def _whitener(C: object, name: str, allow_zero: bool) -> np.ndarray | None:
    """``L^-1`` (6, 6) with ``C = L L^T``; None for an all-zero ``C`` where that is allowed."""
    a = np.asarray(C)
    if a.dtype.kind not in "iuf":
        raise TypeError(f"Expected a real (6, 6) covariance for '{name}', but got dtype {a.dtype}")
    a = a.astype(np.float64)
    if a.shape != (6, 6) or not np.all(np.isfinite(a)) or np.abs(a - a.T).max() > 1e-9 * np.abs(a).max():
        raise ValueError(f"Expected a finite symmetric (6, 6) covariance for '{name}', but got {a!r}")
    if allow_zero and not np.any(a):
        return None
    try:
        L = np.linalg.cholesky(0.5 * (a + a.T))
    except np.linalg.LinAlgError:
        raise ValueError(f"Expected a positive definite {'(or all-zero) ' if allow_zero else ''}'{name}', "
                         f"but got smallest eigenvalue {np.linalg.eigvalsh(a).min():.3g}") from None
    return scipy.linalg.solve_triangular(L, np.eye(6), lower=True)


def _se3_right_jacobian_inv(xi: np.ndarray) -> np.ndarray:
    """``J_r^-1(xi)`` (6, 6): ``Log(Exp(xi) Exp(e)) ~= xi + J_r^-1 e``, ``J_r = int_0^1 exp(-s ad) ds``.

    Bernoulli series ``I + ad/2 + ad^2/12 - ad^4/720 + ...`` below 0.2 rad (error < 1e-13), else the
    inverse of ``J_r`` read off one 12x12 matrix exponential."""
    A = se3_ad(xi)
    if float(np.linalg.norm(xi[3:])) < 0.2:
        A2 = A @ A
        return np.eye(6) + 0.5 * A + A2 @ (np.eye(6) / 12 + A2 @ (-np.eye(6) / 720 + A2 @ (
            np.eye(6) / 30240 - A2 / 1209600)))
    M = np.zeros((12, 12))
    M[:6, :6], M[:6, 6:] = -A, np.eye(6)
    return np.linalg.inv(scipy.linalg.expm(M)[:6, 6:])


def _check_view(item: Sequence, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One view's ``(ids (m,) int, ranges_m (m,), bearings_rad (m,))``, checked."""
    if len(item) != 3:
        raise ValueError(f"Expected (ids, ranges_m, bearings_rad) in returns[{k}], but got {len(item)} items")
    ids = np.asarray(item[0])
    if ids.ndim != 1 or (ids.size and ids.dtype.kind not in "iu"):
        raise TypeError(f"Expected 1-D integer ids in returns[{k}], but got {ids.dtype} {ids.shape}")
    if len(set(ids.tolist())) != ids.size:
        raise ValueError(f"Expected each id at most once in returns[{k}], but got {ids.tolist()}")
    r, b = (np.asarray(v, dtype=np.float64) for v in item[1:])
    if r.shape != ids.shape or b.shape != ids.shape or not np.all(np.isfinite(r) & np.isfinite(b) & (r > 0)):
        raise ValueError(f"Expected {ids.shape} finite ranges_m > 0 and bearings_rad in returns[{k}], but "
                         f"got {r!r} and {b!r}")
    return ids.astype(np.int64), r, b


class BatchProblem:
    """The factors of one recorded sequence (measurements and noise; no estimate).

    Parameters
    ----------
    T_W_S0 : (4, 4) float
    pose_cov0 : (6, 6) float
        Prior of the first pose (right perturbation, m and rad): positive definite, or zeros to hold it.
    odometry : sequence of ((4, 4) float, (6, 6) float)
        ``(T_Sprev_Snext, motion_cov)`` from view ``k`` to ``k + 1`` as ``SonarEKF.predict`` takes them.
    returns : sequence of ((m,) int, (m,) float, (m,) float)
        Per view (``len(odometry) + 1``): feature ids (each at most once), ranges (m, > 0), azimuths (rad).
    range_sigma_m, bearing_sigma_rad, vfov_rad : float
        Measurement noise standard deviations (> 0) and full vertical aperture (in ``(0, pi)``).
    """

    def __init__(self, T_W_S0: np.ndarray, pose_cov0: np.ndarray,
                 odometry: Sequence[tuple[np.ndarray, np.ndarray]],
                 returns: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]], *,
                 range_sigma_m: float, bearing_sigma_rad: float, vfov_rad: float) -> None:
        self.T_W_S0 = check_pose(T_W_S0, "T_W_S0")
        self.T_W_S0[:3, :3] = orthonormalize(self.T_W_S0[:3, :3])
        self._W0 = _whitener(pose_cov0, "pose_cov0", allow_zero=True)
        bad = [k for k, item in enumerate(odometry) if len(item) != 2]
        if bad:
            raise ValueError(f"Expected (T_Sprev_Snext, motion_cov) pairs in 'odometry', but got other "
                             f"lengths at {bad[:3]}")
        self.U = [check_pose(U, f"odometry[{k}][0]") for k, (U, _) in enumerate(odometry)]
        for U in self.U:
            U[:3, :3] = orthonormalize(U[:3, :3])
        self._Wq = [_whitener(Q, f"odometry[{k}][1]", allow_zero=False) for k, (_, Q) in enumerate(odometry)]
        self.n_poses = len(self.U) + 1
        if len(returns) != self.n_poses:
            raise ValueError(f"Expected {self.n_poses} views in 'returns' (len(odometry) + 1), but got "
                             f"{len(returns)}")
        sr, sb, vf = (check_finite_scalar(v, n) for v, n in ((range_sigma_m, "range_sigma_m"),
                      (bearing_sigma_rad, "bearing_sigma_rad"), (vfov_rad, "vfov_rad")))
        if sr <= 0 or sb <= 0 or not 0 < vf < math.pi:
            raise ValueError(f"Expected range_sigma_m > 0, bearing_sigma_rad > 0 and 0 < vfov_rad < pi, "
                             f"but got {sr}, {sb} and {vf}")
        self._w = np.array([1 / sr, 1 / sb, math.sqrt(12.0) / vf])  # whitening of (r, az) and elevation
        self._slot: dict[int, int] = {}  # id -> feature index, in order of first sighting
        first, kk, jj, zz = [], [], [], [np.zeros((0, 2))]
        for k, item in enumerate(returns):
            ids, r, b = _check_view(item, k)
            for i in ids.tolist():
                if i not in self._slot:
                    self._slot[i] = len(first)
                    first.append(k)
                jj.append(self._slot[i])
            kk += [k] * ids.size
            zz.append(np.column_stack([r, b]))
        self.landmark_ids = tuple(self._slot)
        self._first = np.array(first, dtype=np.int64)  # view of each feature's first sighting
        self._k, self._j, self._z = np.array(kk, np.int64), np.array(jj, np.int64), np.concatenate(zz)
        self._held = self._W0 is None
        m0 = (0 if self._held else 6) + 6 * len(self.U)
        self._meas_rows = np.arange(m0, m0 + 2 * len(kk))  # where a robust loss applies
        self.n_residuals = m0 + 2 * len(kk) + len(first)

    def _terms(self, T: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, sp.csr_array]:
        """Whitened residuals ``(m,)`` and their local Jacobian (see :meth:`linearize`)."""
        f, rows, cols, vals, r0 = [], [], [], [], 0

        def block(J: np.ndarray, r: np.ndarray, c: np.ndarray) -> None:  # J (B, a, b) at rows r, columns c
            rows.append(np.broadcast_to(r[:, None, None] + np.arange(J.shape[1])[:, None], J.shape).ravel())
            cols.append(np.broadcast_to(c[:, None, None] + np.arange(J.shape[2]), J.shape).ravel())
            vals.append(J.ravel())

        if not self._held:
            e = se3_log(se3_inverse(self.T_W_S0) @ T[0])
            f.append(self._W0 @ e)
            block((self._W0 @ _se3_right_jacobian_inv(e))[None], np.array([0]), np.array([0]))
            r0 = 6
        for k, U in enumerate(self.U):  # e = Log(U^-1 T_k^-1 T_k+1); T_k Exp(d): e - J_r^-1 Ad(B^-1) d
            B = se3_inverse(T[k]) @ T[k + 1]
            e = se3_log(se3_inverse(U) @ B)
            Je = self._Wq[k] @ _se3_right_jacobian_inv(e)
            f.append(self._Wq[k] @ e)
            block(np.stack([-Je @ se3_adjoint(se3_inverse(B)), Je]), np.array([r0] * 2), 6 * np.r_[k, k + 1])
            r0 += 6
        for kv, jv in ((self._k, self._j), (self._first, np.arange(self._first.size))):  # returns, elevations
            R, t = T[kv, :3, :3], T[kv, :3, 3]
            p = np.einsum("kji,kj->ki", R, P[jv] - t)  # p_S = R^T (p_W - t)
            x, y, z = p[:, 0], p[:, 1], p[:, 2]
            h2 = np.maximum(x * x + y * y, 1e-300)
            r = np.linalg.norm(p, axis=1)
            if kv is self._k:  # d(r, az)/dp_S
                D = np.zeros((kv.size, 2, 3))
                D[:, 0], D[:, 1, 0], D[:, 1, 1] = p / r[:, None], -y / h2, x / h2
                res = np.stack([r - self._z[:, 0], wrap_angle(np.arctan2(y, x) - self._z[:, 1])], axis=1)
                w = self._w[:2]
            else:  # elevation atan2(z, hypot(x, y)), prior mean 0
                D = np.stack([-x * z, -y * z, h2], axis=1)[:, None] / (np.sqrt(h2) * r * r)[:, None, None]
                res, w = np.arctan2(z, np.sqrt(h2))[:, None], self._w[2:]
            D = D * w[:, None]
            f.append((res * w).ravel())
            hat_p = np.zeros((kv.size, 3, 3))
            hat_p[:, 0, 1], hat_p[:, 0, 2], hat_p[:, 1, 2] = -z, y, -x
            hat_p -= np.swapaxes(hat_p, 1, 2)
            rws = r0 + D.shape[1] * np.arange(kv.size)
            block(np.concatenate([-D, D @ hat_p], axis=2), rws, 6 * kv)  # dp_S/d(rho, phi) = [-I, hat(p_S)]
            block(D @ np.swapaxes(R, 1, 2), rws, 6 * len(T) + 3 * jv)  # dp_S/dp_W = R^T
            r0 += D.shape[1] * kv.size
        J = sp.csr_array((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                         shape=(self.n_residuals, 6 * len(T) + 3 * len(P)))
        return np.concatenate(f), J

    def linearize(self, poses: np.ndarray, landmarks: Mapping[int, np.ndarray]
                  ) -> tuple[np.ndarray, sp.csr_array]:
        """Whitened residuals ``(m,)`` and their Jacobian ``(m, 6n + 3L)`` (CSR) at given estimates.

        Columns ``6k:6k+6``: pose ``k``'s right perturbation ``T_k Exp(d)`` (even for a held first
        pose), then each feature's world position in :attr:`landmark_ids` order."""
        return self._terms(self._check_poses(poses, "poses"), self._check_landmarks(landmarks, "landmarks"))

    def jacobian_sparsity(self) -> sp.csr_array:
        """(m, 6n + 3L) 0/1 pattern of :meth:`linearize`'s Jacobian: every block that can be non-zero."""
        _, J = self._terms(np.tile(np.eye(4), (self.n_poses, 1, 1)),
                           np.tile([1.0, 0.2, 0.3], (len(self._slot), 1)))
        J.data[:] = 1.0
        return J

    def cost(self, poses: np.ndarray, landmarks: Mapping[int, np.ndarray], loss: str = "linear",
             f_scale: float = 3.0) -> float:
        """Objective ``0.5 sum rho(f^2)`` at given estimates (e.g. an EKF's), as :meth:`solve` reports it."""
        f, _ = self.linearize(poses, landmarks)
        return 0.5 * float(np.sum(self._loss(loss, f_scale)(f * f)[0]))

    def _loss(self, loss: str, f_scale: float):
        """scipy loss callable (``z = f^2 -> (3, m)``): robust on the range/azimuth rows only."""
        if loss not in LOSSES:
            raise ValueError(f"Expected loss in {tuple(LOSSES)}, but got {loss!r}")
        c2 = check_finite_scalar(f_scale, "f_scale") ** 2
        if not c2 > 0:
            raise ValueError(f"Expected f_scale > 0 (sigmas), but got {f_scale}")

        def rho(z: np.ndarray) -> np.ndarray:
            out, m = np.stack(LOSSES["linear"](z)), self._meas_rows
            out[:, m] = np.stack(LOSSES[loss](z[m] / c2)) * np.array([[c2], [1.0], [1.0 / c2]])
            return out

        return rho

    def _check_poses(self, poses: object, name: str) -> np.ndarray:
        a = np.asarray(poses)
        if a.shape != (self.n_poses, 4, 4):
            raise ValueError(f"Expected shape ({self.n_poses}, 4, 4) for '{name}', but got {a.shape}")
        T = np.stack([check_pose(a[k], f"{name}[{k}]") for k in range(self.n_poses)])
        T[:, :3, :3] = [orthonormalize(R) for R in T[:, :3, :3]]
        return T

    def _check_landmarks(self, lm: Mapping[int, np.ndarray], name: str, complete: bool = True) -> np.ndarray:
        unknown, missing = sorted(set(lm) - set(self._slot)), sorted(set(self._slot) - set(lm))
        if unknown or (complete and missing):
            raise ValueError(f"Expected the feature ids {sorted(self._slot)} in '{name}', but got unknown "
                             f"{unknown} and missing {missing if complete else []}")
        P = np.full((len(self._slot), 3), np.nan)
        for i, v in lm.items():
            a = np.asarray(v, dtype=np.float64)
            if a.shape != (3,) or not np.all(np.isfinite(a)):
                raise ValueError(f"Expected a finite (3,) position for id {i} in '{name}', but got {a!r}")
            P[self._slot[i]] = a
        return P

    def initial_guess(self, init_poses: np.ndarray | None = None,
                      init_landmarks: Mapping[int, np.ndarray] | None = None,
                      ) -> tuple[np.ndarray, np.ndarray]:
        """Poses ``(n, 4, 4)`` (dead reckoning from ``T_W_S0`` unless given) and features ``(L, 3)``.

        Features not in ``init_landmarks`` start on their first return at elevation 0."""
        if init_poses is None:
            T = np.stack(list(itertools.accumulate(self.U, np.matmul, initial=self.T_W_S0)))
        else:
            T = self._check_poses(init_poses, "init_poses")
        P = self._check_landmarks(init_landmarks or {}, "init_landmarks", complete=False)
        for j in np.flatnonzero(np.isnan(P[:, 0])):
            q = int(np.flatnonzero(self._j == j)[0])
            P[j] = T[self._k[q], :3, :3] @ spherical_point([*self._z[q], 0.0])[0] + T[self._k[q], :3, 3]
        return T, P

    def solve(self, *, loss: str = "linear", f_scale: float = 3.0, init_poses: np.ndarray | None = None,
              init_landmarks: Mapping[int, np.ndarray] | None = None, max_nfev: int | None = None,
              blas_threads: int | None = 1) -> BatchResult:
        """MAP estimate of every pose and feature (see the module notes).

        The unknowns are, per estimated pose, its translation (m) and a rotation vector on its
        initial rotation (``R = R_init Exp(phi)``), then the features. ``loss`` is a key of
        :data:`LOSSES`, ``f_scale`` in sigmas. Initial values: :meth:`initial_guess`. BLAS runs on
        ``blas_threads`` threads (threadpoolctl; None: as the process has it): on a loaded 2-core box
        OpenBLAS's own threads made the solver's 376 x 144 SVD 2 s instead of 5 ms.
        """
        rho = self._loss(loss, f_scale)
        T0, P0 = self.initial_guess(init_poses, init_landmarks)
        n, L, a = self.n_poses, len(P0), int(self._held)
        T0[0] = self.T_W_S0 if self._held else T0[0]
        free = np.arange(6 * a, 6 * n + 3 * L)  # local columns that are unknowns
        x0 = np.concatenate([np.column_stack([T0[a:, :3, 3], np.zeros((n - a, 3))]).ravel(), P0.ravel()])
        if x0.size == 0:
            raise ValueError("Expected something to estimate, but got one held pose and no features")
        dense = x0.size <= DENSE_MAX_UNKNOWNS

        def unpack(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            y, T = x[: 6 * (n - a)].reshape(-1, 6), T0.copy()
            T[a:, :3, 3] = y[:, :3]
            T[a:, :3, :3] = T0[a:, :3, :3] @ np.stack([so3_exp(v) for v in y[:, 3:]] or [np.eye(3)])
            return T, x[6 * (n - a) :].reshape(L, 3), y

        def jacobian(x: np.ndarray) -> np.ndarray | sp.csr_array:
            T, P, y = unpack(x)  # d(local)/d(unknowns): blockdiag(R^T, J_r(phi)) per pose, I for features
            D = sp.block_diag([scipy.linalg.block_diag(T[a + k, :3, :3].T, so3_right_jacobian(y[k, 3:]))
                               for k in range(n - a)] + [sp.eye_array(3 * L)], format="csr")
            J = (self._terms(T, P)[1][:, free] @ D).tocsr()
            return J.toarray() if dense else J

        with threadpoolctl.threadpool_limits(blas_threads, user_api="blas"):
            sol = scipy.optimize.least_squares(lambda x: self._terms(*unpack(x)[:2])[0], x0, jac=jacobian,
                                               method="trf", loss=rho, f_scale=1.0, x_scale="jac", ftol=1e-12,
                                               xtol=1e-12, gtol=1e-12, max_nfev=max_nfev,
                                               tr_options={} if dense else dict(atol=1e-10, btol=1e-10))
            T, P, _ = unpack(sol.x)
            f, J = self._terms(T, P)
            info = (J[:, free].T @ sp.diags_array(rho(f * f)[1]) @ J[:, free]).toarray()
            C, msg = np.zeros((6 * n + 3 * L, 6 * n + 3 * L)), str(sol.message)
            try:
                cho = scipy.linalg.cho_factor(info)
                C[np.ix_(free, free)] = scipy.linalg.cho_solve(cho, np.eye(free.size))
            except np.linalg.LinAlgError:
                C[np.ix_(free, free)] = np.nan
                msg += " (information matrix singular: covariance is NaN)"
        return BatchResult(
            poses=T, landmarks={i: P[j].copy() for j, i in enumerate(self.landmark_ids)},
            landmark_ids=self.landmark_ids, covariance=0.5 * (C + C.T), cost=float(sol.cost),
            chi2=float(f @ f), dof=int(f.size - free.size), n_iterations=int(sol.njev or sol.nfev),
            success=bool(sol.success), message=msg)


def solve(T_W_S0: np.ndarray, pose_cov0: np.ndarray, odometry: Sequence[tuple[np.ndarray, np.ndarray]],
          returns: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]], *, range_sigma_m: float,
          bearing_sigma_rad: float, vfov_rad: float, loss: str = "linear", f_scale: float = 3.0,
          init_poses: np.ndarray | None = None, init_landmarks: Mapping[int, np.ndarray] | None = None,
          ) -> BatchResult:
    """MAP of a whole sequence, ``BatchProblem(...).solve(...)`` (arguments as there), e.g.
    ``solve(T0, P0, list(zip(U_odo, Q)), list(zip(ids, ranges_m, bearings_rad)), range_sigma_m=0.003,
    bearing_sigma_rad=0.0017, vfov_rad=0.24, loss="huber").poses[-1]``."""
    problem = BatchProblem(T_W_S0, pose_cov0, odometry, returns, range_sigma_m=range_sigma_m,
                           bearing_sigma_rad=bearing_sigma_rad, vfov_rad=vfov_rad)
    return problem.solve(loss=loss, f_scale=f_scale, init_poses=init_poses, init_landmarks=init_landmarks)
