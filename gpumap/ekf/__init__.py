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

Modules
-------
:mod:`~gpumap.ekf.measurement` (range/azimuth and plane-range models), :mod:`~gpumap.ekf.motion`
(odometry), :mod:`~gpumap.ekf.initialisation` (anchored features, triangulation),
:mod:`~gpumap.ekf.filter` (:class:`SonarEKF`), :mod:`~gpumap.ekf.batch` (the MAP of the same
model over a whole sweep: the filter's yardstick, and a smoother).
"""

from __future__ import annotations

from gpumap.ekf.filter import PlaneUpdateResult, SonarEKF, UpdateResult
from gpumap.ekf.initialisation import Triangulation, anchor_jacobian, triangulate
from gpumap.ekf.measurement import (
    MIN_HORIZONTAL_M,
    MIN_PLANE_COS,
    observation_model,
    plane_range_model,
    spherical_point,
    wrap_angle,
)
from gpumap.ekf.motion import motion_jacobian

__all__ = [
    "MIN_HORIZONTAL_M",
    "MIN_PLANE_COS",
    "PlaneUpdateResult",
    "SonarEKF",
    "Triangulation",
    "UpdateResult",
    "anchor_jacobian",
    "motion_jacobian",
    "observation_model",
    "plane_range_model",
    "spherical_point",
    "triangulate",
    "wrap_angle",
]
