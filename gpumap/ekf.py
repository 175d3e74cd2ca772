"""EKF for the imaging-sonar pose and point features (range/azimuth only), after Mai et al.

The filter keeps the sonar pose ``T_W_S`` and the world positions of point features in one
joint Gaussian, as in Mai et al., "3-D Reconstruction of Underwater Object Based on Extended
Kalman Filter by Using Acoustic Camera Images" (Section 3), with these changes:

- **Attitude** is a rotation matrix; its error is a rotation vector (error-state EKF on
  SE(3)), so there is no gimbal lock. Roll/pitch/yaw exist only as output
  (:attr:`SonarEKF.rpy_rad`).
- **New features** start along the elevation arc of their first (range, azimuth) return:
  elevation mean 0 with the variance of a uniform law over the vertical aperture,
  ``vfov^2 / 12``, pushed through the inverse-measurement Jacobian together with the pose
  uncertainty, which also gives the pose-feature cross-covariance. (The paper sets the
  elevation to 0 and says nothing of its uncertainty; a small variance there makes the
  first updates overconfident, a huge one makes them wrong through linearisation.)
- **Triangulated elevation** (``init="triangulate"``; default ``"arc"``): a new feature
  enters the state as above, anchored where first seen, but its returns are *held* (not
  fused) and stored with the relative pose from the anchor (the filter's estimates) and its
  odometry covariance. Each held return triggers a small Gauss-Newton triangulation in the
  anchor frame (:func:`triangulate`: scan along the first arc, then refine; residuals weighted
  by the measurement noise inflated by the relative-pose covariance; covariance from the
  Hessian). Once the elevation sigma is below ``init_elevation_sigma_rad`` (default half
  the prior's) and the residual passes a chi-square test, the arc prior's independent
  elevation term ``U(-vfov/2, vfov/2)`` is replaced by the triangulated ``N(el, sigma^2)``.
  That is exact bookkeeping, because no return of the feature was fused, so that term is
  still independent of everything else; the anchor-pose cross-covariance is kept. The held
  returns are spent on the triangulation. Features that never get parallax are never fused
  (consistent, but they add nothing). Measured (see bench/ekf_bench.py): consistent (pose
  NEES ~6.6 on the prism and the tank) but not better overall: prism feature error 12.0 mm vs
  9.3 mm for the arc; tank at 0.005 m/rad odometry noise 3.3 cm vs 4.0 cm; at 0.02 nothing
  triangulates (relative pitch from odometry is too loose), so it falls back to odometry.
  Hence ``"arc"`` stays the default.
- **Iterated update** (``iterations > 1``): Gauss-Newton passes that relinearise at the
  updated estimate (IEKF); a return failing the gate at the prior's linearisation gets an
  iterated second test. Default 1 (plain EKF): on the tank and prism scenes iterating gains
  little, because the error comes from the elevation prior's mean (0), not the Jacobian.
- **Immature features** (``mature_elevation_sigma_rad``, off by default): returns of
  features whose elevation given the pose is still looser than this update only their own
  feature (Schmidt-Kalman consider update; Joseph form keeps the covariance right). This
  restores consistency (pose NEES ~6) but, in the tank demo, almost no feature matures.
- **Ranges to a known plane** (:meth:`SonarEKF.update_plane_ranges`): slant ranges along
  rays fixed to the sonar (a DVL's beams through its mount) to a known world plane (the
  floor). They observe what range/azimuth features hardly do: height above the plane and
  tilt relative to it (pitch, roll); never position along it or heading. Gated per ray
  (chi-square, 1 dof); NaN ranges (no return) and rays parallel to the plane are skipped.
- **Gating**: each return's innovation is tested on its own ``2x2`` innovation covariance
  against a chi-square (2 dof) quantile; returns that fail are reported, not used.
- **Numerics**: gains by Cholesky solve of the innovation covariance (never its inverse),
  Joseph-form covariance update, symmetrised; azimuth residuals wrapped to ``(-pi, pi]``;
  after each update the pose-error covariance is moved to the new linearisation point
  (first-order reset ``I - ad(dx)/2``).

Conventions
-----------
State order: pose error ``(rho (m), phi (rad))`` then landmarks ``(x, y, z)`` in world
metres, in the order of :attr:`SonarEKF.landmark_ids`. The pose error is a right
perturbation on SE(3): ``T_W_S = T_hat @ Exp(delta)``, ``delta = (rho, phi)``
(:mod:`gpumap.lie`); ``pose_cov0``, ``motion_cov`` and :attr:`SonarEKF.pose_cov` all use it.

Measurement of feature ``l_W`` from pose ``T_W_S``: ``p = T_W_S^-1 l_W`` in the sonar frame
(x forward, y left, z up); ``r = |p|``, ``azimuth = atan2(p_y, p_x)``.

Features out of view are kept, with their covariance and correlations, for as long as the
caller wants; :meth:`SonarEKF.forget` marginalises one out (exact for a Gaussian: its rows
and columns are dropped). There is no automatic ageing: the caller knows best when a
feature will not come back.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg

from gpumap.errors import check_finite_scalar, check_pose
from gpumap.lie import (
    orthonormalize,
    rpy_from_rotation,
    se3_ad,
    se3_adjoint,
    se3_exp,
    se3_inverse,
)

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


__all__ = [
    "PlaneUpdateResult",
    "SonarEKF",
    "UpdateResult",
    "anchor_jacobian",
    "motion_jacobian",
    "observation_model",
    "plane_range_model",
    "spherical_point",
    "triangulate",
    "Triangulation",
    "wrap_angle",
]

#: Returns whose horizontal distance from the sonar axis is below this are not used: their
#: azimuth is undefined and its Jacobian unbounded.
MIN_HORIZONTAL_M = 1e-9


def wrap_angle(a: np.ndarray | float) -> np.ndarray:
    """Wrap angles to ``(-pi, pi]``.

    Parameters
    ----------
    a : float or (...,) float
        Angles, radians.

    Returns
    -------
    (...,) float64
    """
    a = np.asarray(a, dtype=np.float64)
    w = np.remainder(a + np.pi, 2.0 * np.pi) - np.pi
    return np.where(w == -np.pi, np.pi, w)


def _observe_batch(
    R: np.ndarray, t: np.ndarray, L: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Predicted ``(r, azimuth)`` and Jacobians for ``k`` world points at once.

    Returns ``z (k, 2)``, ``H_pose (k, 2, 6)``, ``H_l (k, 2, 3)`` and the horizontal
    distance ``(k,)`` (for the degenerate-geometry test).
    """
    P = (L - t) @ R  # (k, 3): rows are R^T (l - t)
    x, y = P[:, 0], P[:, 1]
    r = np.linalg.norm(P, axis=1)
    rho2 = x * x + y * y
    rh = np.sqrt(rho2)
    rs = np.where(r > 0, r, 1.0)
    hs = np.where(rho2 > 0, rho2, 1.0)
    dz_dp = np.zeros((P.shape[0], 2, 3))
    dz_dp[:, 0, :] = P / rs[:, None]
    dz_dp[:, 1, 0] = -y / hs
    dz_dp[:, 1, 1] = x / hs
    # dp/d(rho) = -I, dp/d(phi) = hat(p), dp/dl = R^T
    dp_dphi = np.zeros((P.shape[0], 3, 3))
    dp_dphi[:, 0, 1], dp_dphi[:, 0, 2] = -P[:, 2], P[:, 1]
    dp_dphi[:, 1, 0], dp_dphi[:, 1, 2] = P[:, 2], -P[:, 0]
    dp_dphi[:, 2, 0], dp_dphi[:, 2, 1] = -P[:, 1], P[:, 0]
    Hp = np.empty((P.shape[0], 2, 6))
    Hp[:, :, :3] = -dz_dp
    Hp[:, :, 3:] = dz_dp @ dp_dphi
    Hl = dz_dp @ R.T
    z = np.stack([r, np.arctan2(y, x)], axis=1)
    return z, Hp, Hl, rh


def observation_model(
    T_W_S: np.ndarray, l_W: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Predicted measurement of one feature and its Jacobians.

    Parameters
    ----------
    T_W_S : (4, 4) float
        Sonar pose.
    l_W : (3,) float
        Feature position in the world, metres.

    Returns
    -------
    z : (2,) float64
        ``[range_m, azimuth_rad]``.
    H_pose : (2, 6) float64
        Jacobian with respect to the right pose perturbation ``(rho, phi)``.
    H_l : (2, 3) float64
        Jacobian with respect to ``l_W``.
    """
    T = np.asarray(T_W_S, dtype=np.float64)
    z, Hp, Hl, _ = _observe_batch(T[:3, :3], T[:3, 3], np.asarray(l_W, dtype=np.float64)[None])
    return z[0], Hp[0], Hl[0]


def spherical_point(s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cartesian point of spherical sonar coordinates, and its Jacobian.

    Parameters
    ----------
    s : (3,) or (k, 3) float
        ``(range m, azimuth rad, elevation rad)``.

    Returns
    -------
    p : (3,) or (k, 3) float64
        ``r [cos(el) cos(az), cos(el) sin(az), sin(el)]``.
    dp_ds : (3, 3) or (k, 3, 3) float64
        Columns ``dp/dr, dp/daz, dp/del`` (mutually orthogonal, norms ``1, r cos(el), r``).
    """
    s = np.asarray(s, dtype=np.float64)
    one = s.ndim == 1
    s = np.atleast_2d(s)
    r, az, el = s[:, 0], s[:, 1], s[:, 2]
    ca, sa, ce, se = np.cos(az), np.sin(az), np.cos(el), np.sin(el)
    u = np.stack([ce * ca, ce * sa, se], axis=1)
    D = np.empty((s.shape[0], 3, 3))
    D[:, :, 0] = u
    D[:, :, 1] = r[:, None] * np.stack([-ce * sa, ce * ca, np.zeros_like(ca)], axis=1)
    D[:, :, 2] = r[:, None] * np.stack([-se * ca, -se * sa, ce], axis=1)
    p = r[:, None] * u
    return (p[0], D[0]) if one else (p, D)


def anchor_jacobian(s: np.ndarray) -> np.ndarray:
    """Jacobian of a feature's anchored coordinates with respect to the anchor pose error.

    A feature is stored as spherical coordinates ``s`` in an anchor frame ``A`` (the pose
    estimate when it was first seen). If the true anchor pose is ``T_hat @ Exp(delta)``,
    the true coordinates are ``sph(Exp(delta) @ p(s))``; this returns their derivative in
    ``delta = (rho, phi)`` at ``delta = 0``: ``(dp/ds)^-1 [I, -hat(p)]``.

    Parameters
    ----------
    s : (3,) float
        ``(range m, azimuth rad, elevation rad)``, with ``r > 0`` and ``|el| < pi/2``.

    Returns
    -------
    (3, 6) float64
    """
    p, D = spherical_point(s)
    # dp/ds has orthogonal columns: its inverse is diag(1/|col|^2) D^T (no matrix inverse).
    r, ce = float(s[0]), math.cos(float(s[2]))
    Dinv = np.diag([1.0, 1.0 / (r * ce) ** 2, 1.0 / (r * r)]) @ D.T
    J = np.empty((3, 6))
    J[:, :3] = Dinv
    J[:, 3:] = -Dinv @ np.array([[0.0, -p[2], p[1]], [p[2], 0.0, -p[0]], [-p[1], p[0], 0.0]])
    return J


def motion_jacobian(T_Sprev_Snext: np.ndarray) -> np.ndarray:
    """Jacobian of the pose error through a relative motion: ``Ad(T_Sprev_Snext^-1)``.

    With ``T_next = T_prev @ U`` and right perturbations, ``delta_next = Ad(U^-1) delta_prev + w``
    where ``w`` is the motion noise (right perturbation of ``U``).

    Returns
    -------
    (6, 6) float64
    """
    return se3_adjoint(se3_inverse(np.asarray(T_Sprev_Snext, dtype=np.float64)))


def plane_range_model(
    T_W_S: np.ndarray,
    origins_S: np.ndarray,
    directions_S: np.ndarray,
    plane_n_W: np.ndarray,
    plane_d_m: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Predicted ranges along rays fixed in the sonar frame to a world plane, and their Jacobian.

    Ray ``i`` starts at ``T_W_S @ o_i`` and runs along ``R_W_S @ u_i``; it meets the plane
    ``n . p = d`` at ``r_i = (d - n . o_W) / (n . u_W)``. With the right perturbation
    ``T_W_S = T_hat @ Exp(delta)``, ``dr/d(rho) = -n_S / (n . u_W)`` and
    ``dr/d(phi) = (n_S x p_S) / (n . u_W)``, where ``n_S = R^T n`` and ``p_S = o + r u`` is the
    hit point in the sonar frame.

    Parameters
    ----------
    T_W_S : (4, 4) float
        Sonar pose.
    origins_S : (m, 3) float
        Ray origins in the sonar frame, metres.
    directions_S : (m, 3) float
        Unit ray directions in the sonar frame.
    plane_n_W : (3,) float
        Unit plane normal in the world.
    plane_d_m : float
        Plane offset: points ``p`` with ``n . p = d``.

    Returns
    -------
    r : (m,) float64
        Predicted ranges, metres (negative: the plane is behind the ray; ``inf``/``nan`` when
        the ray is parallel to it).
    H_pose : (m, 6) float64
        Jacobian with respect to ``(rho, phi)``.
    cos_incidence : (m,) float64
        ``n . u_W``: how squarely each ray meets the plane (0 = parallel).
    """
    T = np.asarray(T_W_S, dtype=np.float64)
    R, t = T[:3, :3], T[:3, 3]
    o = np.asarray(origins_S, dtype=np.float64)
    u = np.asarray(directions_S, dtype=np.float64)
    n_S = R.T @ np.asarray(plane_n_W, dtype=np.float64)
    den = u @ n_S
    num = float(plane_d_m) - (o @ n_S + float(n_S @ (R.T @ t)))
    with np.errstate(divide="ignore", invalid="ignore"):
        r = num / den
        p = o + r[:, None] * u
        H = np.empty((o.shape[0], 6))
        H[:, :3] = -n_S[None, :] / den[:, None]
        H[:, 3:] = np.cross(n_S[None, :], p) / den[:, None]
    return r, H, den


#: Rays meeting the plane more obliquely than this (``|n . u| <`` it, about 89.4 deg from the
#: normal) are not used: their range is unbounded and its Jacobian blows up.
MIN_PLANE_COS = 1e-2


@dataclass(frozen=True)
class PlaneUpdateResult:
    """What :meth:`SonarEKF.update_plane_ranges` did with each ray (indices into its input).

    Attributes
    ----------
    accepted : tuple of int
        Rays that passed the gate and were fused.
    rejected : dict of int to float
        Rays that failed the chi-square (1 dof) gate, with their NIS.
    skipped : tuple of int
        Rays with a NaN range (no return).
    degenerate : tuple of int
        Rays (nearly) parallel to the plane or whose predicted hit lies behind the origin.
    nis : float or None
        Joint NIS of the accepted rays (``dof = len(accepted)``); None if none was fused.
    """

    accepted: tuple[int, ...] = ()
    rejected: dict[int, float] = field(default_factory=dict)
    skipped: tuple[int, ...] = ()
    degenerate: tuple[int, ...] = ()
    nis: float | None = None


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
    deferred_ids : tuple of int
        ``init="triangulate"``: held features whose return was stored, not fused.
    released_ids : tuple of int
        ``init="triangulate"``: held features whose elevation was triangulated by this return.
    nis : float or None
        Joint normalised innovation squared of the accepted returns, ``dof = 2 * len(accepted_ids)``;
        None when nothing was fused.
    """

    accepted_ids: tuple[int, ...] = ()
    rejected: dict[int, float] = field(default_factory=dict)
    initialized_ids: tuple[int, ...] = ()
    degenerate_ids: tuple[int, ...] = ()
    nis: float | None = None
    deferred_ids: tuple[int, ...] = ()
    released_ids: tuple[int, ...] = ()

    @property
    def nis_dof(self) -> int:
        """Degrees of freedom of :attr:`nis`."""
        return 2 * len(self.accepted_ids)


def _check_cov(C: object, n: int, name: str) -> np.ndarray:
    a = np.array(C, dtype=np.float64, copy=True)
    if a.shape != (n, n):
        raise ValueError(f"Expected a ({n}, {n}) covariance for '{name}', but got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"Expected finite entries in '{name}', but got NaN or inf")
    scale = max(float(np.abs(a).max()), 1e-300)
    if float(np.abs(a - a.T).max()) > 1e-9 * scale:
        raise ValueError(f"Expected a symmetric matrix for '{name}', but got asymmetry "
                         f"{float(np.abs(a - a.T).max()):.3g}")
    a = 0.5 * (a + a.T)
    lam = float(np.linalg.eigvalsh(a).min())
    if lam < -1e-12 * scale:
        raise ValueError(f"Expected a positive semi-definite matrix for '{name}', but got "
                         f"smallest eigenvalue {lam:.3g}")
    return a


def _real_array(v: object, name: str) -> np.ndarray:
    """``v`` as a float64 copy, or TypeError if it does not hold real numbers."""
    a = np.asarray(v)
    if a.dtype == object or not np.issubdtype(a.dtype, np.number) or np.issubdtype(
        a.dtype, np.complexfloating
    ):
        raise TypeError(f"Expected real numbers in '{name}', but got dtype {a.dtype}")
    return np.array(a, dtype=np.float64, copy=True)


def _check_vector(v: object, m: int | None, name: str) -> np.ndarray:
    a = _real_array(v, name)
    if a.ndim != 1 or (m is not None and a.shape[0] != m):
        want = f"({m},)" if m is not None else "(m,)"
        raise ValueError(f"Expected shape {want} for '{name}', but got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"Expected finite values in '{name}', but got NaN or inf")
    return a


def _check_matrix3(v: object, m: int | None, name: str) -> np.ndarray:
    a = _real_array(v, name)
    if a.ndim != 2 or a.shape[1] != 3 or (m is not None and a.shape[0] != m):
        want = f"({m}, 3)" if m is not None else "(m, 3)"
        raise ValueError(f"Expected shape {want} for '{name}', but got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"Expected finite values in '{name}', but got NaN or inf")
    return a


def _check_ids(ids: object) -> list[int]:
    a = np.asarray(ids)
    if a.ndim != 1:
        raise ValueError(f"Expected a 1-D sequence of integer ids for 'ids', but got shape {a.shape}")
    if a.size and not np.issubdtype(a.dtype, np.integer):
        raise TypeError(f"Expected integer ids for 'ids', but got dtype {a.dtype}")
    out = [int(i) for i in a]
    if len(set(out)) != len(out):
        dup = sorted({i for i in out if out.count(i) > 1})
        raise ValueError(f"Expected each id at most once per update in 'ids', but got repeats {dup}")
    return out


@dataclass(frozen=True)
class _Held:
    """Returns of one held feature, for :func:`triangulate` in its anchor frame ``A``.

    ``C`` is the covariance of the right perturbation of ``T_A^-1 T_now`` (odometry since the
    anchor, grown by each predict). ``X (k, 4, 4)`` are the views' frames from the anchor frame
    (``T_V^-1 T_A``, estimates when taken), ``z (k, 2)`` the returns and ``Ce (k, 6, 6)`` the
    covariance of each ``X``'s right perturbation. The anchor's own return is last.
    """

    C: np.ndarray
    X: np.ndarray
    z: np.ndarray
    Ce: np.ndarray

    @staticmethod
    def start(z0: np.ndarray) -> _Held:
        return _Held(np.zeros((6, 6)), np.eye(4)[None], np.asarray(z0, float)[None], np.zeros((1, 6, 6)))

    def moved(self, F: np.ndarray, Q: np.ndarray) -> _Held:
        return _Held(F @ self.C @ F.T + Q, self.X, self.z, self.Ce)

    def add(self, X: np.ndarray, r: float, a: float, max_views: int) -> _Held:
        # X = T_V^-1 T_A = Y^-1 with Y = T_A^-1 T_V, Y_true = Y Exp(eps), cov(eps) = C
        # => X_true = X Exp(-Ad(Y) eps).
        Ad = se3_adjoint(se3_inverse(X))
        Xs = np.concatenate([self.X[:-1], X[None], self.X[-1:]])
        zs = np.concatenate([self.z[:-1], [[r, a]], self.z[-1:]])
        Cs = np.concatenate([self.Ce[:-1], (Ad @ self.C @ Ad.T)[None], self.Ce[-1:]])
        if Xs.shape[0] > max_views:  # keep the anchor (last) and the newest
            Xs, zs, Cs = Xs[1:], zs[1:], Cs[1:]
        return _Held(self.C, Xs, zs, Cs)

    def drop_oldest(self) -> _Held:
        if self.X.shape[0] <= 2:
            return _Held(self.C, self.X[-1:], self.z[-1:], self.Ce[-1:])
        return _Held(self.C, self.X[1:], self.z[1:], self.Ce[1:])


def _chi2_quantile(prob: float, dof: int) -> float:
    """Chi-square quantile (``dof >= 1``)."""
    from scipy.stats import chi2

    return float(chi2.ppf(prob, dof))


def _chi2_2dof(prob: float) -> float:
    # Chi-square with 2 dof is exponential: P(X <= x) = 1 - exp(-x/2).
    return -2.0 * math.log1p(-prob)


class SonarEKF:
    """Joint EKF over the sonar pose and point features seen as (range, azimuth).

    Features are stored as anchored spherical coordinates ``s = (r, az, el)`` in the sonar
    frame where they were first seen (the anchor, a fixed transform equal to the pose
    estimate at that moment), so the elevation arc of a first return is a straight line in
    the state and its uniform prior is represented without the chord error of a Cartesian
    Gaussian. The anchor's pose uncertainty is carried by the feature's covariance and its
    cross-covariance with the pose (:func:`anchor_jacobian`). Everything the class returns
    (:attr:`landmarks`, :meth:`landmark_cov`, :attr:`covariance`) is in world Cartesian
    coordinates; :attr:`native_covariance` is the filter's own.

    Parameters
    ----------
    T_W_S0 : (4, 4) float
        Initial sonar pose (world from sonar).
    pose_cov0 : (6, 6) float
        Initial pose covariance over ``(translation m, rotation vector rad)``, right perturbation.
    range_sigma_m : float
        Standard deviation of a range measurement, metres (> 0).
    bearing_sigma_rad : float
        Standard deviation of an azimuth measurement, radians (> 0).
    vfov_rad : float
        Full vertical aperture, radians, in ``(0, pi)``. A new feature's elevation is taken
        uniform over ``[-vfov/2, vfov/2]``: mean 0, variance ``vfov^2 / 12``.
    gate_prob : float or None, default 0.999
        Chi-square (2 dof) gate probability for each return; None disables gating.
    iterations : int, default 1
        Most Gauss-Newton passes of each update (iterated EKF); 1 is the plain EKF. Passes
        stop early once the correction stops changing.
    mature_elevation_sigma_rad : float or None, default None
        If given, returns of features whose anchored elevation, conditioned on the pose, has
        a standard deviation above this correct only their own feature (Schmidt update).
    init : {"arc", "triangulate"}, default "arc"
        Feature initialisation: ``"arc"`` fuses every return from the first re-observation on,
        linearised at elevation 0; ``"triangulate"`` holds a feature's returns until its
        elevation is triangulated (see the module notes), then fuses later returns.
    init_elevation_sigma_rad : float or None, default None
        ``init="triangulate"``: elevation standard deviation at which a held feature is
        released; None gives half the prior's, ``vfov / (2 sqrt(12))``.
    init_max_views : int, default 12
        ``init="triangulate"``: most returns kept per held feature (the anchor's and the newest).
    blas_threads : int or None, default 1
        BLAS threads used inside ``predict`` and the updates (through threadpoolctl, set and
        restored around each call, about 10 µs). The filter's matrices are small and dense:
        on a loaded 2-core computer OpenBLAS's own threads made a 32-feature update 15 ms
        instead of 1 ms (``bench/``). None leaves BLAS as the process has it.

    Examples
    --------
    >>> ekf = SonarEKF(np.eye(4), np.zeros((6, 6)), range_sigma_m=0.01,
    ...                bearing_sigma_rad=0.005, vfov_rad=np.deg2rad(14))
    >>> ekf.predict(T_Sprev_Snext, motion_cov)          # doctest: +SKIP
    >>> res = ekf.update(ids, ranges_m, bearings_rad)    # doctest: +SKIP
    """

    def __init__(
        self,
        T_W_S0: np.ndarray,
        pose_cov0: np.ndarray,
        *,
        range_sigma_m: float,
        bearing_sigma_rad: float,
        vfov_rad: float,
        gate_prob: float | None = 0.999,
        iterations: int = 1,
        mature_elevation_sigma_rad: float | None = None,
        init: str = "arc",
        init_elevation_sigma_rad: float | None = None,
        init_max_views: int = 12,
        blas_threads: int | None = 1,
    ) -> None:
        if blas_threads is not None and (isinstance(blas_threads, bool) or int(blas_threads) < 1):
            raise ValueError(f"Expected blas_threads >= 1 or None, but got {blas_threads!r}")
        self._blas_threads = None if blas_threads is None else int(blas_threads)
        T = check_pose(T_W_S0, "T_W_S0")
        P0 = _check_cov(pose_cov0, 6, "pose_cov0")
        sr = check_finite_scalar(range_sigma_m, "range_sigma_m")
        sb = check_finite_scalar(bearing_sigma_rad, "bearing_sigma_rad")
        vf = check_finite_scalar(vfov_rad, "vfov_rad")
        if sr <= 0 or sb <= 0:
            raise ValueError(
                f"Expected range_sigma_m > 0 and bearing_sigma_rad > 0, but got {sr} and {sb}"
            )
        if not 0 < vf < math.pi:
            raise ValueError(f"Expected 0 < vfov_rad < pi, but got {vf}")
        if gate_prob is not None:
            gp = check_finite_scalar(gate_prob, "gate_prob")
            if not 0 < gp < 1:
                raise ValueError(f"Expected 0 < gate_prob < 1 (or None), but got {gp}")
            self._gate = _chi2_2dof(gp)
            self._gate1 = _chi2_quantile(gp, 1)
        else:
            self._gate = self._gate1 = math.inf
        if isinstance(iterations, bool) or not isinstance(iterations, (int, np.integer)) or iterations < 1:
            raise ValueError(f"Expected an integer iterations >= 1, but got {iterations!r}")
        self.iterations = int(iterations)
        if mature_elevation_sigma_rad is not None:
            me = check_finite_scalar(mature_elevation_sigma_rad, "mature_elevation_sigma_rad")
            if me <= 0:
                raise ValueError(f"Expected mature_elevation_sigma_rad > 0 (or None), but got {me}")
            mature_elevation_sigma_rad = me
        self.mature_elevation_sigma_rad = mature_elevation_sigma_rad
        if init not in ("arc", "triangulate"):
            raise ValueError(f"Expected init 'arc' or 'triangulate', but got {init!r}")
        self.init = init
        if init_elevation_sigma_rad is None:
            init_elevation_sigma_rad = 0.5 * vf / math.sqrt(12.0)
        ie = check_finite_scalar(init_elevation_sigma_rad, "init_elevation_sigma_rad")
        if ie <= 0:
            raise ValueError(f"Expected init_elevation_sigma_rad > 0, but got {ie}")
        self.init_elevation_sigma_rad = ie
        if (isinstance(init_max_views, bool) or not isinstance(init_max_views, (int, np.integer))
                or init_max_views < 2):
            raise ValueError(f"Expected an integer init_max_views >= 2, but got {init_max_views!r}")
        self.init_max_views = int(init_max_views)
        self.range_sigma_m = sr
        self.bearing_sigma_rad = sb
        self.vfov_rad = vf
        self.elevation_var_rad2 = vf * vf / 12.0
        T[:3, :3] = orthonormalize(T[:3, :3])
        self._T = T
        self._P = P0
        self._S = np.zeros((0, 3))  # anchored spherical coordinates (r, az, el)
        self._Ra = np.zeros((0, 3, 3))  # anchor rotations R_W_A
        self._ta = np.zeros((0, 3))  # anchor positions t_W_A
        self._ids: list[int] = []
        self._index: dict[int, int] = {}
        self._nis: float | None = None
        self._nis_dof = 0
        # init="triangulate": features whose returns are held back until their elevation is
        # triangulated: id -> (covariance of the pose since the anchor, held returns).
        self._held: dict[int, _Held] = {}

    # ------------------------------------------------------------------ read-only views
    @property
    def pose(self) -> np.ndarray:
        """(4, 4) float64 copy of the estimated ``T_W_S``."""
        return self._T.copy()

    @property
    def pose_cov(self) -> np.ndarray:
        """(6, 6) float64 pose covariance, ``(translation m, rotation vector rad)``, right perturbation."""
        return self._P[:6, :6].copy()

    @property
    def rpy_rad(self) -> np.ndarray:
        """(3,) ``[roll, pitch, yaw]`` of the estimate, ``R = Rz(yaw) Ry(pitch) Rx(roll)``; output only."""
        return rpy_from_rotation(self._T[:3, :3])

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
        _, J = self._world_points()
        n = len(self._ids)
        B = np.zeros_like(self._P)
        B[:6, :6] = np.eye(6)
        for k in range(n):
            s = 6 + 3 * k
            B[s : s + 3, s : s + 3] = J[k]
        C = B @ self._P @ B.T
        return 0.5 * (C + C.T)

    @property
    def native_covariance(self) -> np.ndarray:
        """(6 + 3n, 6 + 3n) float64 covariance of the filter's own state.

        Pose error ``(rho, phi)``, then each feature's anchored ``(r m, az rad, el rad)``.
        """
        return self._P.copy()

    @property
    def landmark_anchors(self) -> dict[int, tuple[np.ndarray, np.ndarray]]:
        """Feature id -> ``(T_W_A (4, 4), s (3,))``: anchor pose and anchored ``(r, az, el)``."""
        out = {}
        for i, k in self._index.items():
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = self._Ra[k], self._ta[k]
            out[i] = (T, self._S[k].copy())
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
        _, D = spherical_point(self._S[k])
        J = self._Ra[k] @ D
        C = J @ self._P[s : s + 3, s : s + 3] @ J.T
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
        return _anchored_to_world(S, Ra, ta)

    # ------------------------------------------------------------------ filter steps
    @_blas_limited
    def predict(self, T_Sprev_Snext: np.ndarray, motion_cov: np.ndarray) -> None:
        """Move the pose by a relative motion measured in the previous sonar frame.

        Parameters
        ----------
        T_Sprev_Snext : (4, 4) float
            Odometry increment ``U``: ``T_W_Snext = T_W_Sprev @ U``.
        motion_cov : (6, 6) float
            Covariance of ``w`` in ``U_true = U @ Exp(w)``, ``(translation m, rotation vector rad)``.
        """
        U = check_pose(T_Sprev_Snext, "T_Sprev_Snext")
        Q = _check_cov(motion_cov, 6, "motion_cov")
        U[:3, :3] = orthonormalize(U[:3, :3])
        F = motion_jacobian(U)
        P = self._P.copy()
        P[:6, :] = F @ P[:6, :]
        P[:, :6] = P[:, :6] @ F.T
        P[:6, :6] += Q
        P = 0.5 * (P + P.T)
        T = self._T @ U
        T[:3, :3] = orthonormalize(T[:3, :3])
        if not (np.all(np.isfinite(P)) and np.all(np.isfinite(T))):
            raise FloatingPointError("predict produced non-finite values; the filter is unchanged")
        held = {i: h.moved(F, Q) for i, h in self._held.items()}
        self._T, self._P, self._held = T, P, held

    @_blas_limited
    def update(
        self, ids: Iterable[int] | np.ndarray, ranges_m: np.ndarray, bearings_rad: np.ndarray
    ) -> UpdateResult:
        """Fuse one ping's feature returns; add features seen for the first time.

        Known features are gated one by one (chi-square, 2 dof, on each return's own
        innovation covariance), then the accepted ones are fused jointly. New features are
        then initialised from the updated pose. On any error the filter is left unchanged.

        Parameters
        ----------
        ids : (m,) int
            Feature ids (known correspondences), each at most once.
        ranges_m : (m,) float
            Measured ranges, metres, > 0.
        bearings_rad : (m,) float
            Measured azimuths ``atan2(y, x)`` in the sonar frame, radians (any branch).

        Returns
        -------
        UpdateResult
        """
        id_list = _check_ids(ids)
        m = len(id_list)
        rng_m = _check_vector(ranges_m, m, "ranges_m")
        brg = _check_vector(bearings_rad, m, "bearings_rad")
        if np.any(rng_m <= 0):
            raise ValueError(f"Expected ranges_m > 0, but got minimum {float(rng_m.min())}")

        known = [k for k in range(m) if id_list[k] in self._index and id_list[k] not in self._held]
        held_k = [k for k in range(m) if id_list[k] in self._held]
        new = [k for k in range(m) if id_list[k] not in self._index]
        T, P, S = self._T, self._P, self._S
        accepted: list[int] = []
        rejected: dict[int, float] = {}
        degenerate: list[int] = []
        nis: float | None = None

        if known:
            slots = np.array([self._index[id_list[k]] for k in known])
            meas = np.stack([rng_m[known], brg[known]], axis=1)
            Ra, ta = self._Ra[slots], self._ta[slots]
            nu, Hp, Hs, ok = _linearize(T, S[slots], Ra, ta, meas)
            degenerate = [id_list[known[j]] for j in np.flatnonzero(~ok)]
            sel = np.flatnonzero(ok)
            nu, Hp, Hs, slots = nu[sel], Hp[sel], Hs[sel], slots[sel]
            meas, Ra, ta = meas[sel], Ra[sel], ta[sel]
            r_var = np.array([self.range_sigma_m**2, self.bearing_sigma_rad**2])
            # Per-return gate on the 2x2 marginal innovation covariance. A return that fails
            # at the prior's linearisation gets a second, iterated test on its own (the arc's
            # curvature, not the return, may be what failed), judged by its nonlinear NIS.
            HP = _hp(P, Hp, Hs, slots)  # (k, 2, N)
            d2 = _nis_2x2(_s_blocks(HP, Hp, Hs, slots) + np.diag(r_var), nu)
            if self.iterations > 1:
                for j in np.flatnonzero(~(d2 <= self._gate)):
                    js = slice(j, j + 1)
                    _, _, _, d2j = _iterate(T, P, S[slots[js]], Ra[js], ta[js], slots[js], meas[js],
                                            nu[js], Hp[js], Hs[js], r_var, self.iterations)
                    if d2j <= self._gate:
                        d2[j] = d2j
            keep = np.flatnonzero(d2 <= self._gate)
            for j in np.flatnonzero(~(d2 <= self._gate)):
                rejected[id_list[known[sel[j]]]] = float(d2[j])
            if keep.size:
                kk = keep
                own = None
                if self.mature_elevation_sigma_rad is not None:
                    own = _elevation_var_given_pose(P, slots[kk]) > self.mature_elevation_sigma_rad**2
                dx, g, nis, _ = _iterate(T, P, S[slots[kk]], Ra[kk], ta[kk], slots[kk], meas[kk],
                                         nu[kk], Hp[kk], Hs[kk], r_var, self.iterations, own)
                T, P = _apply(T, P, dx, g)
                S = S + dx[6:].reshape(-1, 3)
                S[:, 1] = wrap_angle(S[:, 1])
                accepted = [id_list[known[sel[j]]] for j in keep]

        new_ids: list[int] = []
        index = dict(self._index)
        ids_order = list(self._ids)
        Ra, ta = self._Ra, self._ta
        held, deferred, released = self._held, [], []
        if held_k:
            S, P, held, deferred, released = self._release(
                T, S, P, [(id_list[k], rng_m[k], brg[k]) for k in held_k])
        Nz = np.diag([self.range_sigma_m**2, self.bearing_sigma_rad**2, self.elevation_var_rad2])
        inits = [(k, np.array([rng_m[k], float(wrap_angle(brg[k])), 0.0]), Nz) for k in new]
        if inits and self.init == "triangulate":
            held = dict(held)
            for k, s_k, _ in inits:
                held[id_list[k]] = _Held.start(s_k[:2])
        if inits:
            Nn = P.shape[0]
            n_new = len(inits)
            Pn = np.zeros((Nn + 3 * n_new, Nn + 3 * n_new))
            Pn[:Nn, :Nn] = P
            s_new = np.zeros((n_new, 3))
            for q, (k, s_k, N_k) in enumerate(inits):
                s_new[q] = s_k
                A = anchor_jacobian(s_new[q])
                c = Nn + 3 * q
                cross = A @ Pn[:6, :c]  # (3, c): correlated through the anchor pose only
                Pn[c : c + 3, :c] = cross
                Pn[:c, c : c + 3] = cross.T
                Pn[c : c + 3, c : c + 3] = A @ Pn[:6, :6] @ A.T + N_k
                index[id_list[k]] = len(ids_order)
                ids_order.append(id_list[k])
                new_ids.append(id_list[k])
            S = np.concatenate([S, s_new], axis=0)
            Ra = np.concatenate([Ra, np.broadcast_to(T[:3, :3], (n_new, 3, 3))], axis=0)
            ta = np.concatenate([ta, np.broadcast_to(T[:3, 3], (n_new, 3))], axis=0)
            P = 0.5 * (Pn + Pn.T)

        if not (np.all(np.isfinite(P)) and np.all(np.isfinite(T)) and np.all(np.isfinite(S))):
            raise FloatingPointError("update produced non-finite values; the filter is unchanged")
        self._T, self._P, self._S, self._Ra, self._ta = T, P, S, Ra, ta
        self._index, self._ids = index, ids_order
        self._held = held
        if accepted:
            self._nis, self._nis_dof = nis, 2 * len(accepted)
        return UpdateResult(
            accepted_ids=tuple(accepted),
            rejected=rejected,
            initialized_ids=tuple(new_ids),
            degenerate_ids=tuple(degenerate),
            nis=nis if accepted else None,
            deferred_ids=tuple(deferred),
            released_ids=tuple(released),
        )

    @_blas_limited
    def update_plane_ranges(
        self,
        origins_S: np.ndarray,
        directions_S: np.ndarray,
        ranges_m: np.ndarray,
        plane_n_W: np.ndarray,
        plane_d_m: float,
        range_sigma_m: float,
    ) -> PlaneUpdateResult:
        """Fuse ranges measured along known rays to a known world plane (e.g. DVL beams to the floor).

        Ray ``i`` starts at ``T_W_S @ origins_S[i]`` and runs along ``R_W_S @ directions_S[i]``;
        its range is where it meets the plane ``n . p = d`` (:func:`plane_range_model`). For a
        DVL on the same rigid body, pass its beams through the fixed mount: origins
        ``T_S_D[:3, 3]`` and directions ``T_S_D[:3, :3] @ beam_D``. Such ranges observe the
        sonar's height above the plane and its tilt relative to it (pitch and roll for a level
        floor), never the position along the plane or the rotation about its normal.

        NaN ranges are skipped; rays (nearly) parallel to the plane, or hitting it behind their
        origin, are reported degenerate; each other ray is gated on its own innovation
        variance (chi-square, 1 dof, at the filter's ``gate_prob``), then the accepted rays are
        fused jointly (one linearisation, Cholesky gain, Joseph form). The features move with
        the pose through their correlations. On any error the filter is left unchanged.

        Parameters
        ----------
        origins_S : (m, 3) float
            Ray origins in the sonar frame, metres.
        directions_S : (m, 3) float
            Unit ray directions in the sonar frame.
        ranges_m : (m,) float
            Measured ranges along each ray, metres, > 0; NaN = no return (skipped).
        plane_n_W : (3,) float
            Plane normal in the world (normalised here; ``plane_d_m`` is scaled with it).
        plane_d_m : float
            Plane offset, ``n . p = d``; for a floor at height ``z0``: ``n = (0, 0, 1)``, ``d = z0``.
        range_sigma_m : float
            Standard deviation of each range, metres (> 0): sensor noise plus the plane's
            roughness seen along the ray.

        Returns
        -------
        PlaneUpdateResult
        """
        o = _check_matrix3(origins_S, None, "origins_S")
        m = o.shape[0]
        u = _check_matrix3(directions_S, m, "directions_S")
        un = np.linalg.norm(u, axis=1)
        if m and float(np.abs(un - 1.0).max()) > 1e-6:
            raise ValueError(f"Expected unit vectors in 'directions_S', but got norms from "
                             f"{float(un.min()):.6g} to {float(un.max()):.6g}")
        rng_m = _real_array(ranges_m, "ranges_m")
        if rng_m.shape != (m,):
            raise ValueError(f"Expected shape ({m},) for 'ranges_m', but got {rng_m.shape}")
        if np.any(np.isinf(rng_m)):
            raise ValueError("Expected finite values or NaN (no return) in 'ranges_m', but got inf")
        valid = ~np.isnan(rng_m)
        if np.any(rng_m[valid] <= 0):
            raise ValueError(f"Expected ranges_m > 0, but got minimum {float(rng_m[valid].min())}")
        n_W = _check_vector(plane_n_W, 3, "plane_n_W")
        nn = float(np.linalg.norm(n_W))
        if not nn > 0:
            raise ValueError("Expected a non-zero 'plane_n_W', but got the zero vector")
        d = check_finite_scalar(plane_d_m, "plane_d_m") / nn
        n_W = n_W / nn
        sr = check_finite_scalar(range_sigma_m, "range_sigma_m")
        if not sr > 0:
            raise ValueError(f"Expected range_sigma_m > 0, but got {sr}")

        skipped = tuple(int(i) for i in np.flatnonzero(~valid))
        r_hat, H, cos_inc = plane_range_model(self._T, o, u, n_W, d)
        ok = valid & (np.abs(cos_inc) >= MIN_PLANE_COS) & np.isfinite(r_hat) & (r_hat > 0)
        degenerate = tuple(int(i) for i in np.flatnonzero(valid & ~ok))
        idx = np.flatnonzero(ok)
        if idx.size == 0:
            return PlaneUpdateResult(skipped=skipped, degenerate=degenerate)
        P = self._P
        nu = rng_m[idx] - r_hat[idx]
        Hp = H[idx]  # (a, 6); the features' columns of H are zero
        var = sr * sr
        HPp = Hp @ P[:6, :6]
        s_ii = np.einsum("ij,ij->i", HPp, Hp) + var
        d2 = nu * nu / s_ii
        rejected = {int(idx[j]): float(d2[j]) for j in np.flatnonzero(~(d2 <= self._gate1))}
        keep = np.flatnonzero(d2 <= self._gate1)
        if keep.size == 0:
            return PlaneUpdateResult(rejected=rejected, skipped=skipped, degenerate=degenerate)
        Hp, nu = Hp[keep], nu[keep]
        HP = Hp @ P[:6]  # (a, N)
        S = HP[:, :6] @ Hp.T
        S[np.diag_indices(keep.size)] += var
        S = 0.5 * (S + S.T)
        cho = _robust_cholesky(S)
        KT = scipy.linalg.cho_solve(cho, HP, check_finite=False)  # (a, N) = K^T, no inverse
        nis = float(nu @ scipy.linalg.cho_solve(cho, nu, check_finite=False))
        dx = KT.T @ nu
        # Joseph form (I - K H) P (I - K H)^T + K R K^T with H = [Hp, 0].
        AP = P - KT.T @ HP
        Pn = AP - (AP[:, :6] @ Hp.T) @ KT + var * (KT.T @ KT)
        T, Pn = _inject(self._T, Pn, dx[:6])
        S_f = self._S + dx[6:].reshape(-1, 3)
        S_f[:, 1] = wrap_angle(S_f[:, 1])
        if not (np.all(np.isfinite(Pn)) and np.all(np.isfinite(T)) and np.all(np.isfinite(S_f))):
            raise FloatingPointError(
                "update_plane_ranges produced non-finite values; the filter is unchanged")
        self._T, self._P, self._S = T, Pn, S_f
        return PlaneUpdateResult(
            accepted=tuple(int(i) for i in idx[keep]),
            rejected=rejected,
            skipped=skipped,
            degenerate=degenerate,
            nis=nis,
        )

    @property
    def held_ids(self) -> tuple[int, ...]:
        """Features in the state whose returns are held back until their elevation is triangulated."""
        return tuple(self._held)

    def _release(
        self, T: np.ndarray, S: np.ndarray, P: np.ndarray, returns: list[tuple[int, float, float]]
    ) -> tuple[np.ndarray, np.ndarray, dict, list[int], list[int]]:
        """Store held features' returns; triangulate each and release those that are ready.

        ``returns`` are ``(id, range, azimuth)`` at the current pose estimate ``T``. A feature
        is released when its elevation in the anchor frame is triangulated to
        ``init_elevation_sigma_rad`` with a residual that passes a chi-square test (0.999);
        a failing residual drops the oldest non-anchor return (an outlier, or a view whose
        relative pose drifted more than its covariance says). Releasing replaces the
        independent elevation term of the arc prior, ``U(-vfov/2, vfov/2)`` (mean 0, variance
        ``vfov^2 / 12``), by the triangulated ``N(el, sigma^2)``: this is exact bookkeeping
        because none of the feature's returns was fused, so that term is still independent of
        the rest of the state, untouched by every update since. The returns used for the
        triangulation are spent (not fused again). Nothing here mutates ``self``.

        Returns
        -------
        S, P : new anchored coordinates and covariance
        held : dict, the new held table
        deferred, released : lists of ids
        """
        held = dict(self._held)
        S, P = S.copy(), P.copy()
        r_var = np.array([self.range_sigma_m**2, self.bearing_sigma_rad**2])
        deferred, released = [], []
        for i, r, a in returns:
            k = self._index[i]
            T_W_A = np.eye(4)
            T_W_A[:3, :3], T_W_A[:3, 3] = self._Ra[k], self._ta[k]
            h = held[i].add(se3_inverse(T) @ T_W_A, float(r), float(wrap_angle(a)), self.init_max_views)
            tri = triangulate(h.X, h.z, h.Ce, r_var, self.vfov_rad) if h.z.shape[0] >= 2 else None
            if tri is not None and tri.cost > _chi2_quantile(0.999, tri.dof):
                h = h.drop_oldest()
                tri = None
            ready = (tri is not None and tri.elevation_sigma_rad <= self.init_elevation_sigma_rad
                     and abs(tri.s[2]) <= 0.5 * self.vfov_rad + 3.0 * tri.elevation_sigma_rad)
            if ready:
                e = 6 + 3 * k + 2
                S[k, 2] += tri.s[2]
                P[e, e] += tri.cov[2, 2] - self.elevation_var_rad2
                del held[i]
                released.append(i)
            else:
                held[i] = h
                deferred.append(i)
        return S, 0.5 * (P + P.T), held, deferred, released

    def forget(self, landmark_id: int) -> None:
        """Marginalise one feature out of the state (drop its rows and columns).

        Raises
        ------
        KeyError
            If the feature is not in the state.
        """
        k = self._slot(landmark_id)
        self._held.pop(int(landmark_id), None)
        s = 6 + 3 * k
        keep = np.r_[0:s, s + 3 : self._P.shape[0]]
        self._P = self._P[np.ix_(keep, keep)].copy()
        self._S = np.delete(self._S, k, axis=0)
        self._Ra = np.delete(self._Ra, k, axis=0)
        self._ta = np.delete(self._ta, k, axis=0)
        del self._ids[k]
        self._index = {i: j for j, i in enumerate(self._ids)}


def _hp(P: np.ndarray, Hp: np.ndarray, Hs: np.ndarray, slots: np.ndarray) -> np.ndarray:
    """``H @ P`` for block-sparse ``H`` (pose block + one feature block per return), ``(k, 2, N)``."""
    rows = 6 + 3 * slots[:, None] + np.arange(3)[None]  # (k, 3)
    return np.einsum("kij,jn->kin", Hp, P[:6]) + np.einsum("kij,kjn->kin", Hs, P[rows])


def _s_blocks(HP: np.ndarray, Hp: np.ndarray, Hs: np.ndarray, slots: np.ndarray) -> np.ndarray:
    """Diagonal ``2x2`` blocks of ``H P H^T``, ``(k, 2, 2)``."""
    k = HP.shape[0]
    cols = 6 + 3 * slots[:, None] + np.arange(3)[None]
    own = HP[np.arange(k)[:, None, None], np.arange(2)[None, :, None], cols[:, None, :]]
    return np.einsum("kin,kjn->kij", HP[:, :, :6], Hp) + np.einsum("kin,kjn->kij", own, Hs)


def _anchored_to_world(
    S: np.ndarray, Ra: np.ndarray, ta: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """World points ``(k, 3)`` and ``d l / d s`` ``(k, 3, 3)`` of anchored features."""
    if S.shape[0] == 0:
        return np.zeros((0, 3)), np.zeros((0, 3, 3))
    p, D = spherical_point(S)
    return ta + np.einsum("kij,kj->ki", Ra, p), Ra @ D


def _linearize(
    T: np.ndarray, S: np.ndarray, Ra: np.ndarray, ta: np.ndarray, meas: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Innovations ``(k, 2)``, ``H_pose (k, 2, 6)``, ``H_s (k, 2, 3)`` and a usable mask ``(k,)``.

    ``S``, ``Ra``, ``ta`` are the anchored coordinates and anchors of the ``k`` returns'
    features, ``meas`` their ``(range, azimuth)``. A return is not usable when its feature is
    predicted on the sonar's z axis (azimuth undefined) or its anchored coordinates are
    degenerate (``r <= 0`` or elevation at +-90 deg).
    """
    Lw, J = _anchored_to_world(S, Ra, ta)
    z, Hp, Hl, rh = _observe_batch(T[:3, :3], T[:3, 3], Lw)
    ok = (rh > MIN_HORIZONTAL_M * np.maximum(1.0, z[:, 0])) & (S[:, 0] > 0) & (np.cos(S[:, 2]) > 1e-6)
    nu = meas - z
    nu[:, 1] = wrap_angle(nu[:, 1])
    return nu, Hp, Hl @ J, ok


@dataclass
class _Gain:
    """One linearisation's gain: ``K^T`` (2a, N), ``H P`` (2a, N), the pose block of ``H``
    (2a, 6), the feature blocks ``H_s`` (a, 2, 3) and their state columns (3a,), ``R`` (2a,)
    and the Cholesky factor of the innovation covariance."""

    KT: np.ndarray
    HPf: np.ndarray
    Hpf: np.ndarray
    Hs: np.ndarray
    cols: np.ndarray
    Rd: np.ndarray
    cho: tuple[np.ndarray, bool]

    def nis(self, nu: np.ndarray) -> float:
        """``nu^T S^-1 nu`` for a stacked innovation ``(2a,)``."""
        return float(nu @ scipy.linalg.cho_solve(self.cho, nu, check_finite=False))

    def h_times(self, dx: np.ndarray) -> np.ndarray:
        """``H dx`` for a full error-state vector ``(N,)``; returns ``(2a,)``."""
        a = self.Hs.shape[0]
        return self.Hpf @ dx[:6] + np.einsum("kij,kj->ki", self.Hs, dx[self.cols].reshape(a, 3)).reshape(-1)


def _gain(
    P: np.ndarray,
    Hp: np.ndarray,
    Hs: np.ndarray,
    slots: np.ndarray,
    r_var: np.ndarray,
    own_only: np.ndarray | None = None,
) -> _Gain:
    """Kalman gain of ``a`` returns with block-sparse ``H`` (pose block + each return's feature).

    ``own_only`` (a,) bool marks returns whose gain is cut to their own feature's three
    states (Schmidt-Kalman "consider" update: the rest of the state is not corrected by
    them; the Joseph form keeps the covariance right for this suboptimal gain).
    """
    a = Hp.shape[0]
    N = P.shape[0]
    HPf = _hp(P, Hp, Hs, slots).reshape(2 * a, N)
    Hpf = Hp.reshape(2 * a, 6)
    cols = (6 + 3 * slots[:, None] + np.arange(3)[None]).reshape(-1)  # (3a,)
    S = HPf[:, :6] @ Hpf.T
    S += np.einsum("mkj,kij->mki", HPf[:, cols].reshape(2 * a, a, 3), Hs).reshape(2 * a, 2 * a)
    Rd = np.tile(r_var, a)
    S[np.diag_indices(2 * a)] += Rd
    S = 0.5 * (S + S.T)
    cho = _robust_cholesky(S)
    KT = scipy.linalg.cho_solve(cho, HPf, check_finite=False)  # (2a, N) = K^T, no inverse
    if own_only is not None and np.any(own_only):
        for j in np.flatnonzero(own_only):
            keep = KT[2 * j : 2 * j + 2, cols[3 * j : 3 * j + 3]].copy()
            KT[2 * j : 2 * j + 2] = 0.0
            KT[2 * j : 2 * j + 2, cols[3 * j : 3 * j + 3]] = keep
    return _Gain(KT, HPf, Hpf, Hs, cols, Rd, cho)


def _iterate(
    T: np.ndarray,
    P: np.ndarray,
    S: np.ndarray,
    Ra: np.ndarray,
    ta: np.ndarray,
    slots: np.ndarray,
    meas: np.ndarray,
    nu: np.ndarray,
    Hp: np.ndarray,
    Hs: np.ndarray,
    r_var: np.ndarray,
    iterations: int,
    own_only: np.ndarray | None = None,
) -> tuple[np.ndarray, _Gain, float, float]:
    """Iterated (Gauss-Newton) EKF solve of ``a`` returns; the first pass is the plain EKF.

    Pass ``i`` relinearises at the current estimate ``x_i`` (pose ``T Exp(dx_pose)``,
    features ``S + dx_s``) and solves ``x_{i+1} = K_i (z - h(x_i) + H_i x_i)``, where the
    pose block of ``H_i`` carries the right Jacobian ``J_r(dx_pose) ~ I - ad(dx_pose)/2``
    because the error state stays in the prior's tangent space. It stops when the step
    stops changing, after ``iterations`` passes, or when a relinearisation would be
    degenerate (then it keeps the last good pass).

    Returns
    -------
    dx : (N,) float64
        Error-state correction in the prior's tangent space.
    gain : _Gain
        The gain of the last linearisation (for the covariance update).
    nis_prior, nis_last : float
        NIS of the prior linearisation, and of the last one (``nu_eff^T S^-1 nu_eff``, the
        minimum of the linearised MAP cost: the nonlinear NIS at convergence).
    """
    g = _gain(P, Hp, Hs, slots, r_var, own_only)
    nu_f = nu.reshape(-1)
    nis0 = nis = g.nis(nu_f)
    dx = g.KT.T @ nu_f
    for _ in range(1, iterations):
        dpose = dx[:6]
        Ti = T @ se3_exp(dpose)
        rows = (6 + 3 * slots[:, None] + np.arange(3)[None]).reshape(-1)
        Si = S + dx[rows].reshape(-1, 3)
        nu_i, Hp_i, Hs_i, ok = _linearize(Ti, Si, Ra, ta, meas)
        if not np.all(ok):
            break
        Hp_i = Hp_i @ (np.eye(6) - 0.5 * se3_ad(dpose))
        gi = _gain(P, Hp_i, Hs_i, slots, r_var, own_only)
        eff = nu_i.reshape(-1) + gi.h_times(dx)
        dx_new = gi.KT.T @ eff
        if not np.all(np.isfinite(dx_new)):
            break
        step = float(np.abs(dx_new - dx).max())
        g, dx, nis = gi, dx_new, gi.nis(eff)
        if step <= 1e-12 + 1e-9 * float(np.abs(dx).max()):
            break
    return dx, g, nis0, nis


def _apply(T: np.ndarray, P: np.ndarray, dx: np.ndarray, g: _Gain) -> tuple[np.ndarray, np.ndarray]:
    """Joseph-form covariance update with gain ``g``; inject the pose part of ``dx``.

    Returns the new pose and covariance; the feature part ``dx[6:]`` is the caller's.
    """
    N = P.shape[0]
    a = g.Hs.shape[0]
    # Joseph form (I - K H) P (I - K H)^T + K R K^T, evaluated with the sparse H.
    AP = P - g.KT.T @ g.HPf
    APHt = AP[:, :6] @ g.Hpf.T + np.einsum(
        "nkj,kij->nki", AP[:, g.cols].reshape(N, a, 3), g.Hs
    ).reshape(N, 2 * a)
    Pn = AP - APHt @ g.KT + (g.KT.T * g.Rd) @ g.KT
    return _inject(T, Pn, dx[:6])


def _inject(T: np.ndarray, Pn: np.ndarray, dpose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Apply the pose correction ``dpose`` (6,) to ``T``; move ``Pn``'s pose rows/columns with it.

    ``T_true = T Exp(e)``, ``T_new = T Exp(d)``  =>  ``e_new ~= J_r(d) (e - d)``,
    ``J_r ~= I - ad(d)/2``. Returns the new pose and the symmetrised covariance.
    """
    Tn = T @ se3_exp(dpose)
    Tn[:3, :3] = orthonormalize(Tn[:3, :3])
    G = np.eye(6) - 0.5 * se3_ad(dpose)
    Pn[:6, :] = G @ Pn[:6, :]
    Pn[:, :6] = Pn[:, :6] @ G.T
    Pn = 0.5 * (Pn + Pn.T)
    return Tn, Pn


def _elevation_var_given_pose(P: np.ndarray, slots: np.ndarray) -> np.ndarray:
    """Variance of each feature's anchored elevation given the current pose, ``(k,)``.

    ``P_ee - P_ep P_pp^+ P_pe``: how well the relative geometry (not the pose) fixes it.
    """
    e = 6 + 3 * slots + 2
    Ppp = P[:6, :6]
    Pep = P[np.ix_(e, np.arange(6))]  # (k, 6)
    lam, V = np.linalg.eigh(Ppp)
    tol = max(float(lam.max()), 1e-300) * 1e-12
    inv = (V / np.where(lam > tol, lam, np.inf)) @ V.T
    return P[e, e] - np.einsum("ki,ij,kj->k", Pep, inv, Pep)


def _nis_2x2(S: np.ndarray, nu: np.ndarray) -> np.ndarray:
    """``nu_k^T S_k^-1 nu_k`` for ``k`` symmetric 2x2 blocks, by the 2x2 Cholesky factor.

    A block that is not positive definite gives ``inf`` (the return is then gated out).
    """
    a = S[:, 0, 0]
    b = 0.5 * (S[:, 0, 1] + S[:, 1, 0])
    c = S[:, 1, 1]
    ok = a > 0
    l11 = np.sqrt(np.where(ok, a, 1.0))
    l21 = b / l11
    d = c - l21 * l21
    ok &= d > 0
    l22 = np.sqrt(np.where(ok, d, 1.0))
    y1 = nu[:, 0] / l11
    y2 = (nu[:, 1] - l21 * y1) / l22
    return np.where(ok, y1 * y1 + y2 * y2, np.inf)


def _robust_cholesky(S: np.ndarray) -> tuple[np.ndarray, bool]:
    """Cholesky factor of a symmetric ``S``; adds growing jitter only if round-off broke PD."""
    try:
        return scipy.linalg.cho_factor(S, lower=True, check_finite=False)
    except np.linalg.LinAlgError:
        pass
    d = np.abs(np.diag(S)).max()
    for k in range(-14, -5):
        try:
            return scipy.linalg.cho_factor(
                S + (d * 10.0**k) * np.eye(S.shape[0]), lower=True, check_finite=False
            )
        except np.linalg.LinAlgError:
            continue
    raise FloatingPointError(
        "Expected a positive definite innovation covariance, but Cholesky failed even with "
        "jitter; the filter is unchanged"
    )


# --------------------------------------------------------------------------- delayed initialisation
def _range_azimuth(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(r, azimuth)`` of sonar-frame points ``q (k, 3)`` and ``dz/dq (k, 2, 3)``."""
    x, y = q[:, 0], q[:, 1]
    r = np.linalg.norm(q, axis=1)
    h2 = x * x + y * y
    rs = np.where(r > 0, r, 1.0)
    hs = np.where(h2 > 0, h2, 1.0)
    J = np.zeros((q.shape[0], 2, 3))
    J[:, 0, :] = q / rs[:, None]
    J[:, 1, 0] = -y / hs
    J[:, 1, 1] = x / hs
    return np.stack([r, np.arctan2(y, x)], axis=1), J


def _hat_batch(p: np.ndarray) -> np.ndarray:
    H = np.zeros((p.shape[0], 3, 3))
    H[:, 0, 1], H[:, 0, 2] = -p[:, 2], p[:, 1]
    H[:, 1, 0], H[:, 1, 2] = p[:, 2], -p[:, 0]
    H[:, 2, 0], H[:, 2, 1] = -p[:, 1], p[:, 0]
    return H


@dataclass(frozen=True)
class Triangulation:
    """Result of :func:`triangulate`.

    Attributes
    ----------
    s : (3,) float64
        ``(range m, azimuth rad, elevation rad)`` of the point in the reference frame.
    cov : (3, 3) float64
        Its covariance: the inverse Gauss-Newton Hessian, with each view's residual weighted
        by ``R + J_e C_rel J_e^T`` (measurement noise inflated by that view's relative-pose
        uncertainty), pushed into spherical coordinates.
    cost : float
        Weighted squared residual at the solution (chi-square with ``dof`` degrees of freedom
        when the model holds).
    dof : int
        ``2 k - 3`` for ``k`` views.
    """

    s: np.ndarray
    cov: np.ndarray
    cost: float
    dof: int

    @property
    def elevation_sigma_rad(self) -> float:
        """Standard deviation of the triangulated elevation."""
        return math.sqrt(max(float(self.cov[2, 2]), 0.0))


def triangulate(
    T_V_S: np.ndarray,
    z: np.ndarray,
    rel_cov: np.ndarray,
    r_var: np.ndarray,
    vfov_rad: float,
    n_scan: int = 15,
    max_iter: int = 8,
) -> Triangulation | None:
    """Locate a point from ``k`` (range, azimuth) returns taken at known relative poses.

    The reference frame ``S`` is the sonar frame of the last return (``T_V_S[-1]`` is normally
    the identity). The point is first found on the last return's elevation arc by a scan of
    ``n_scan`` elevations over the aperture (the cost is multimodal along the arc when the
    parallax is small), then refined in Cartesian coordinates by Gauss-Newton over all returns.

    Parameters
    ----------
    T_V_S : (k, 4, 4) float
        Each view's frame from the reference frame: ``q_k = T_V_S[k] @ p``.
    z : (k, 2) float
        ``(range m, azimuth rad)`` of each return.
    rel_cov : (k, 6, 6) float
        Covariance of the right perturbation ``e_k`` in ``T_V_S[k]_true = T_V_S[k] Exp(e_k)``.
    r_var : (2,) float
        Range and azimuth noise variances.
    vfov_rad : float
        Vertical aperture (the scan's span).

    Returns
    -------
    Triangulation or None
        None when the geometry is degenerate (singular Hessian, point behind every view).
    """
    R, t = T_V_S[:, :3, :3], T_V_S[:, :3, 3]
    k = z.shape[0]
    r0, az0 = float(z[-1, 0]), float(z[-1, 1])
    # Coarse scan along the last return's arc (range/azimuth fixed), vectorised.
    els = np.linspace(-0.5 * vfov_rad, 0.5 * vfov_rad, n_scan)
    cand = spherical_point(np.column_stack([np.full(n_scan, r0), np.full(n_scan, az0), els]))[0]
    q = np.einsum("kij,cj->cki", R, cand) + t[None]  # (c, k, 3)
    zz, _ = _range_azimuth(q.reshape(-1, 3))
    res = z[None] - zz.reshape(n_scan, k, 2)
    res[..., 1] = wrap_angle(res[..., 1])
    p = cand[int(np.argmin(np.sum(res * res / r_var, axis=(1, 2))))].copy()

    def normal_equations(p: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        qk = np.einsum("kij,j->ki", R, p) + t
        zk, Jq = _range_azimuth(qk)
        nu = z - zk
        nu[:, 1] = wrap_angle(nu[:, 1])
        Jp = Jq @ R  # (k, 2, 3)
        Je = np.concatenate([Jp, -Jp @ _hat_batch(np.broadcast_to(p, (k, 3)))], axis=2)  # (k, 2, 6)
        Sk = np.einsum("kij,kjl,kml->kim", Je, rel_cov, Je)
        Sk[:, 0, 0] += r_var[0]
        Sk[:, 1, 1] += r_var[1]
        det = Sk[:, 0, 0] * Sk[:, 1, 1] - Sk[:, 0, 1] * Sk[:, 1, 0]
        W = np.stack([np.stack([Sk[:, 1, 1], -Sk[:, 0, 1]], 1), np.stack([-Sk[:, 1, 0], Sk[:, 0, 0]], 1)],
                     1) / det[:, None, None]
        W = 0.5 * (W + np.swapaxes(W, 1, 2))
        JtW = np.swapaxes(Jp, 1, 2) @ W  # (k, 3, 2)
        H = np.einsum("kij,kjl->il", JtW, Jp)
        g = np.einsum("kij,kj->i", JtW, nu)
        cost = float(np.einsum("ki,kij,kj->", nu, W, nu))
        return H, g, cost

    H, g, cost = normal_equations(p)
    lam = 1e-6
    for _ in range(max_iter):
        d = np.diag(H)
        try:
            step = np.linalg.solve(H + lam * np.diag(np.maximum(d, 1e-300)), g)
        except np.linalg.LinAlgError:
            return None
        Hn, gn, cn = normal_equations(p + step)
        if cn <= cost:
            p, H, g, cost_prev, cost = p + step, Hn, gn, cost, cn
            lam = max(lam * 0.1, 1e-9)
            if cost_prev - cost <= 1e-10 * (1.0 + cost):
                break
        else:
            lam *= 100.0
    if not (np.all(np.isfinite(H)) and np.all(np.isfinite(p))):
        return None
    lam_h, V = np.linalg.eigh(0.5 * (H + H.T))
    if lam_h.min() <= 1e-12 * max(lam_h.max(), 1e-300):
        return None
    Cp = (V / lam_h) @ V.T
    s = np.array([np.linalg.norm(p), math.atan2(p[1], p[0]), math.atan2(p[2], math.hypot(p[0], p[1]))])
    if s[0] <= 0 or math.cos(s[2]) <= 1e-6:
        return None
    _, D = spherical_point(s)
    ce = math.cos(float(s[2]))
    Dinv = np.diag([1.0, 1.0 / (s[0] * ce) ** 2, 1.0 / (s[0] * s[0])]) @ D.T
    Cs = Dinv @ Cp @ Dinv.T
    return Triangulation(s, 0.5 * (Cs + Cs.T), cost, 2 * k - 3)
