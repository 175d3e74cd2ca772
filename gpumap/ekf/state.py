"""The sonar EKF's state and its read-only views (:class:`EKFState`), and the records its steps
return (:class:`UpdateResult`, :class:`InnovationStats`); the steps are :class:`gpumap.ekf.filter.SonarEKF`'s.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np

from gpumap.ekf._checks import _chi2_quantile
from gpumap.ekf.measurement import _anchored_to_world
from gpumap.lie import rpy_from_rotation, se3_adjoint, se3_inverse

__all__ = ["EKFState", "InnovationStats", "UpdateResult"]


@functools.lru_cache(maxsize=64)
def _nis_band(dof: int) -> tuple[float, float]:
    """Two-sided 99.99 % band of ``chi2(dof) / dof``."""
    return _chi2_quantile(0.00005, dof) / dof, _chi2_quantile(0.99995, dof) / dof

_BLAS = None  # threadpoolctl controller, made on first use (it scans the loaded libraries once)


def _blas_limited(method):
    """Run an EKF step with the filter's BLAS thread limit (see ``SonarEKF(blas_threads=)``)."""

    @functools.wraps(method)
    def wrapper(self, *args, **kwargs):
        global _BLAS
        if self._blas_threads is None:
            return method(self, *args, **kwargs)
        if _BLAS is None:
            from threadpoolctl import ThreadpoolController

            _BLAS = ThreadpoolController()
        with _BLAS.limit(limits=self._blas_threads, user_api="blas"):
            return method(self, *args, **kwargs)

    return wrapper


@dataclass(frozen=True)
class UpdateResult:
    """What :meth:`SonarEKF.update` did with each return.

    Attributes
    ----------
    accepted_ids : tuple of int
        Known features whose returns passed the gate and were fused.
    rejected : dict of int to float
        Known features whose returns failed the chi-square gate, with their NIS (2 dof).
    initialized_ids : tuple of int
        Features seen for the first time, added to the state (their return is spent on the
        initialisation and not fused as an update).
    degenerate_ids : tuple of int
        Known features predicted on the sonar's z axis (azimuth undefined); not used.
    nis : float or None
        Joint normalised innovation squared of the accepted returns, ``dof = 2 * len(accepted_ids)``;
        None when nothing was fused.
    """

    accepted_ids: tuple[int, ...] = ()
    rejected: dict[int, float] = field(default_factory=dict)
    initialized_ids: tuple[int, ...] = ()
    degenerate_ids: tuple[int, ...] = ()
    nis: float | None = None

    @property
    def nis_dof(self) -> int:
        """Degrees of freedom of :attr:`nis`."""
        return 2 * len(self.accepted_ids)


@dataclass(frozen=True)
class InnovationStats:
    """What :meth:`SonarEKF.innovation_stats` found in the recent innovations.

    Attributes
    ----------
    returns : int
        Fused returns pooled (the last ``nis_window``, or fewer).
    nis_per_dof : float
        Their summed NIS over ``2 * returns``: about 1 when the configured noise is right.
    band : (float, float)
        Two-sided 99.99 % band of ``nis_per_dof`` for a consistent filter (chi-square).
    range_nis, bearing_nis : float
        ``mean(nu_i^2) / mean(S_ii)`` per component (1 when consistent): which one is off.
    range_sigma_m, bearing_sigma_rad : float
        Noise estimated from the innovations: ``sqrt(mean(nu_i^2) - mean((H P H^T)_ii))``
        (Mehra's covariance matching, clamped at 0). Noisy with few returns, and biased when
        the state's own covariance is wrong; a hint for ``range_sigma_m`` and
        ``bearing_sigma_rad``, not a calibration.
    """

    returns: int
    nis_per_dof: float
    band: tuple[float, float]
    range_nis: float
    bearing_nis: float
    range_sigma_m: float
    bearing_sigma_rad: float




class EKFState:
    """The joint Gaussian of :class:`gpumap.ekf.filter.SonarEKF` (its fields are set there) and what
    reads it: the pose, the features, their covariances, the last update's NIS; and ``forget``."""

    @property
    def pose(self) -> np.ndarray:
        """(4, 4) float64 copy of the estimated ``T_W_S``."""
        return self._G @ self._T

    def _pose_rows(self) -> np.ndarray:
        """(6, N) map from the state's error to the world pose's right perturbation.

        ``T_W_S = G Exp(g) T Exp(d) = G T Exp(Ad(T^-1) g + d)``.
        """
        B = np.zeros((6, self._P.shape[0]))
        B[:, :6] = np.eye(6)
        if self._ng:
            B[:, -6:] = se3_adjoint(se3_inverse(self._T))
        return B

    @property
    def pose_cov(self) -> np.ndarray:
        """(6, 6) float64 pose covariance, ``(translation m, rotation vector rad)``, right perturbation."""
        B = self._pose_rows()
        C = B @ self._P @ B.T
        return 0.5 * (C + C.T)

    @property
    def rpy_rad(self) -> np.ndarray:
        """(3,) ``[roll, pitch, yaw]`` of the estimate, ``R = Rz(yaw) Ry(pitch) Rx(roll)``; output only."""
        return rpy_from_rotation(self.pose[:3, :3])

    @property
    def landmarks(self) -> dict[int, np.ndarray]:
        """Feature id -> (3,) float64 world position."""
        L, _ = self._world_points()
        return {i: L[k].copy() for i, k in self._index.items()}

    @property
    def landmark_ids(self) -> tuple[int, ...]:
        """Feature ids in state order (the order of :attr:`covariance` after the pose)."""
        return tuple(self._ids)

    @property
    def covariance(self) -> np.ndarray:
        """(6 + 3n, 6 + 3n) float64 covariance of pose and world feature positions.

        Pose block as :attr:`pose_cov`; feature blocks are world Cartesian, first-order
        (``J P J^T`` with ``J = R_W_A dp/ds`` per feature).
        """
        L, J = self._world_points()
        n = len(self._ids)
        B = np.zeros((6 + 3 * n, self._P.shape[0]))
        B[:6] = self._pose_rows()
        for k in range(n):
            s = 6 + 3 * k
            B[s : s + 3, s : s + 3] = J[k]
            if self._ng:
                B[s : s + 3, -6:] = self._gauge_jacobian(L[k])
        C = B @ self._P @ B.T
        return 0.5 * (C + C.T)

    def _gauge_jacobian(self, l_W: np.ndarray) -> np.ndarray:
        """(3, 6) derivative of a world point ``G l_L`` in the gauge's right perturbation."""
        R = self._G[:3, :3]
        q = R.T @ (l_W - self._G[:3, 3])
        return np.concatenate([R, -R @ np.array([[0.0, -q[2], q[1]], [q[2], 0.0, -q[0]],
                                                 [-q[1], q[0], 0.0]])], axis=1)

    @property
    def native_covariance(self) -> np.ndarray:
        """(6 + 3n, 6 + 3n) float64 covariance of the filter's own state, less the gauge.

        Pose error ``(rho, phi)``, then each feature's anchored ``(r m, az rad, el rad)``;
        both relative to the first pose estimate ``G = T_W_S0``. With ``pose_cov0 = 0`` (the
        world is the first sonar frame) that is the whole state; otherwise the error of ``G``
        is in :attr:`state_covariance`.
        """
        n = self._P.shape[0] - self._ng
        return self._P[:n, :n].copy()

    @property
    def state_covariance(self) -> np.ndarray:
        """(6 + 3n + g, 6 + 3n + g) float64: :attr:`native_covariance` and, last, the right
        perturbation of the first pose estimate ``G`` (it starts as ``pose_cov0``; only
        :meth:`update_plane_ranges`, an absolute measurement, changes it). ``g = 6``, or 0
        when ``pose_cov0`` was zero (``G`` is then exact and not kept in the state)."""
        return self._P.copy()

    @property
    def landmark_anchors(self) -> dict[int, tuple[np.ndarray, np.ndarray]]:
        """Feature id -> ``(T_W_A (4, 4), s (3,))``: anchor pose and anchored ``(r, az, el)``."""
        out = {}
        for i, k in self._index.items():
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = self._Ra[k], self._ta[k]
            out[i] = (self._G @ T, self._S[k].copy())
        return out

    @property
    def nis(self) -> float | None:
        """Joint NIS of the last update's fused returns (``dof = nis_dof``); None if none fused."""
        return self._nis

    @property
    def nis_dof(self) -> int:
        """Degrees of freedom of :attr:`nis` (2 per fused return)."""
        return self._nis_dof

    def landmark_cov(self, landmark_id: int) -> np.ndarray:
        """(3, 3) float64 covariance of one feature's world position (first order).

        Raises
        ------
        KeyError
            If the feature is not in the state.
        """
        k = self._slot(landmark_id)
        s = 6 + 3 * k
        L, D = self._world_points(self._S[k : k + 1], self._Ra[k : k + 1], self._ta[k : k + 1])
        J = np.concatenate([D[0], self._gauge_jacobian(L[0])], axis=1) if self._ng else D[0]
        idx = np.r_[s : s + 3, self._P.shape[0] - self._ng : self._P.shape[0]]
        C = J @ self._P[np.ix_(idx, idx)] @ J.T
        return 0.5 * (C + C.T)

    def _slot(self, landmark_id: int) -> int:
        try:
            return self._index[int(landmark_id)]
        except (KeyError, TypeError, ValueError):
            raise KeyError(f"Expected a feature id in the state {sorted(self._index)}, but got "
                           f"{landmark_id!r}") from None

    def _world_points(
        self, S: np.ndarray | None = None, Ra: np.ndarray | None = None, ta: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """World points ``(n, 3)`` and ``d l / d s`` ``(n, 3, 3)`` of anchored features."""
        S = self._S if S is None else S
        Ra = self._Ra if Ra is None else Ra
        ta = self._ta if ta is None else ta
        L, J = _anchored_to_world(S, Ra, ta)
        R = self._G[:3, :3]
        return L @ R.T + self._G[:3, 3], R @ J

    # ------------------------------------------------------------------ filter steps

    def forget(self, landmark_id: int) -> None:
        """Marginalise one feature out of the state (drop its rows and columns).

        Raises
        ------
        KeyError
            If the feature is not in the state.
        """
        k = self._slot(landmark_id)
        s = 6 + 3 * k
        keep = np.r_[0:s, s + 3 : self._P.shape[0]]
        self._P = self._P[np.ix_(keep, keep)].copy()
        self._S = np.delete(self._S, k, axis=0)
        self._Ra = np.delete(self._Ra, k, axis=0)
        self._ta = np.delete(self._ta, k, axis=0)
        del self._ids[k]
        self._index = {i: j for j, i in enumerate(self._ids)}
