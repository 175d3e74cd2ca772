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
- **Second-order elevation term** (``second_order=True``): linearised at elevation 0 a
  range has no first-order sensitivity to elevation, so the chord effect ``r (1 - cos el)``
  of a point off the horizontal plane used to become a range bias (~4 sigma after 1.5 m
  along the beam). Each return's prediction and noise get the Gaussian second-order terms
  of the elevation direction (``h_ee var_e / 2``, ``h_ee h_ee^T var_e^2 / 2``); they vanish
  as the elevation is learned.
- **Relinearised updates and gate** (``relinearize_iterations=5``): an update holding a
  return of a feature whose elevation is still uncertain (sd given the pose above
  ``init_elevation_sigma_rad``, default half the prior's) runs Gauss-Newton passes (IEKF),
  and such a return that fails the chi-square gate at the prior's linearisation is tested
  again at its own relinearised estimate (off-axis points were refused at elevation 0).
  ``iterations`` (default 1) sets the passes for the other updates.
- **Triangulated start** (``init="triangulate"``; default ``"arc"``): every return is fused
  as with the arc, so the cross-covariances are the same; each return of an uncertain
  feature first triangulates it along its arc: Gauss-Newton from ``init_starts``
  elevations over the aperture (and from the estimate), on that return with the filter's
  full prior, the lowest MAP cost wins and the joint update starts there. (An earlier
  version held the returns back and replaced the elevation by an independent triangulated
  one: it lost the returns' pose information and was 1.1-2.3x the batch MAP's error.)
- **Gauge**: the filter runs in the frame of the first pose estimate ``G = T_W_S0``;
  ``pose_cov0`` is the uncertainty of ``G`` (the last 6 states), which relative returns
  never observe and every world output (:attr:`SonarEKF.pose_cov`, ``landmark_cov``,
  ``covariance``) adds. (Before, a huge ``pose_cov0`` went through the features' anchors by
  a linearisation that could not hold, and the absolute pose covariance collapsed.)
- **Innovation monitor** (``nis_window=200``): :meth:`SonarEKF.innovation_stats` pools the
  NIS and the innovations of the last returns and estimates the range and bearing noise
  from them (Mehra's covariance matching); an update whose pooled NIS leaves its 99.99 %
  band warns once (``RuntimeWarning``; logged at INFO on ``gpumap.ekf``).
- **Trust guard** (``guard=TrustGuard()``, issue 29; on in ``gpumap replay --ekf``): the
  NIS of the fused returns over a short and a long sliding window, each against its
  two-sided chi-square band (and per component), decides whether the returns may correct
  the pose; while they may not (and until trust is earned: a full long window, then
  ``hold`` consistent updates in a row) accepted returns update their own feature only
  (Schmidt), so the pose keeps the odometry increment exactly. On the real tank the point
  returns never earn it and the EKF stays at odometry, where the plain filter ends up to 4x
  worse (``bench/results/ekf_real.json``).
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
  against a chi-square (2 dof) quantile (at the relinearised estimate for uncertain
  features); returns that fail are reported, not used.
- **Numerics**: gains by Cholesky solve of the innovation covariance (never its inverse),
  Joseph-form covariance update, symmetrised; azimuth residuals wrapped to ``(-pi, pi]``;
  after each update the pose-error covariance is moved to the new linearisation point
  (first-order reset ``I - ad(dx)/2``).

Conventions
-----------
Outputs (:attr:`SonarEKF.covariance`): pose error ``(rho (m), phi (rad))`` then landmarks
``(x, y, z)`` in world metres, in the order of :attr:`SonarEKF.landmark_ids`. The pose error
is a right perturbation on SE(3): ``T_W_S = T_hat @ Exp(delta)``, ``delta = (rho, phi)``
(:mod:`gpumap.lie`); ``pose_cov0``, ``motion_cov`` and :attr:`SonarEKF.pose_cov` all use it.
The filter's own state (:attr:`SonarEKF.state_covariance`): the pose error in the gauge's
frame, each feature's anchored ``(r, az, el)``, then the gauge's error (only when
``pose_cov0`` is not zero).

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
:mod:`~gpumap.ekf.filter` (:class:`SonarEKF`), :mod:`~gpumap.ekf.plane` (its update from ranges
to a known plane), :mod:`~gpumap.ekf.batch` (the MAP of the same model over a whole sweep: the
filter's yardstick, and a smoother); for real pings (issue #23)
:mod:`~gpumap.ekf.frontend` (point returns found in a polar image, with covariances),
:mod:`~gpumap.ekf.association` (which feature each return belongs to: tracks) and
:mod:`~gpumap.ekf.loop` (odometry, detection, association and filter, ping by ping);
:mod:`~gpumap.ekf.guard` (when the pings' innovations do not fit, lean on odometry);
:mod:`~gpumap.ekf.registration` (each ping's first returns registered against the last pings
and against revisited places, each revisit verified by its image, fused into the odometry step);
:mod:`~gpumap.ekf.posegraph` (odometry and verified revisits as a pose graph, issue #39) and
:mod:`~gpumap.ekf.submaps` (segment maps re-mapped where corrected poses moved them).
"""

from __future__ import annotations

from gpumap.ekf.filter import InnovationStats, PlaneUpdateResult, SonarEKF, UpdateResult
from gpumap.ekf.guard import TrustGuard, nis_band
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
    "InnovationStats",
    "PlaneUpdateResult",
    "SonarEKF",
    "Triangulation",
    "TrustGuard",
    "UpdateResult",
    "anchor_jacobian",
    "motion_jacobian",
    "nis_band",
    "observation_model",
    "plane_range_model",
    "spherical_point",
    "triangulate",
    "wrap_angle",
]
