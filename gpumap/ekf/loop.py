"""The EKF loop on pings: odometry, measurements found in the images, association, filter.

:func:`run_ekf_loop` runs, per ping: :meth:`SonarEKF.predict` with the odometry step, the
detector (:class:`~gpumap.ekf.frontend.PointDetector`) on the image, the tracker
(:class:`~gpumap.ekf.association.FeatureTracker`) which fuses the associated returns, and
records the pose, its covariance, what the tracker did and the time each part took.

:func:`drifting_odometry` is the drift model used where a recording has no odometry of its
own: each step's relative motion between recorded poses, ``U_k = T_{k-1}^-1 T_k``, is
perturbed on the right by ``Exp(w_k)``, ``w_k ~ N(0, diag(s_t^2 I3, s_r^2 I3))`` (translation
metres, rotation vector radians, in the previous sonar frame), independently per step and
seeded; the odometry poses chain these steps from the first recorded pose (exactly known).
That is the demo's model (``gpumap demo --pose-noise S`` takes ``s_t = s_r = S``).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np

from gpumap.ekf.association import FeatureTracker, TrackerStep
from gpumap.ekf.filter import SonarEKF
from gpumap.ekf.frontend import PointDetector, PointMeasurements
from gpumap.ekf.registrar import ScanRegistrar
from gpumap.errors import check_finite_scalar, check_pose
from gpumap.lie import rpy_from_rotation, se3_exp, se3_inverse
from gpumap.spec import SonarSpec

__all__ = ["LoopResult", "drifting_odometry", "motion_cov", "pose_errors", "run_ekf_loop"]


def motion_cov(trans_sigma_m: float, rot_sigma_rad: float) -> np.ndarray:
    """(6, 6) ``diag(s_t^2 I3, s_r^2 I3)`` of one odometry step."""
    st = check_finite_scalar(trans_sigma_m, "trans_sigma_m")
    sr = check_finite_scalar(rot_sigma_rad, "rot_sigma_rad")
    if st < 0 or sr < 0:
        raise ValueError(f"Expected odometry noise >= 0, but got {st} m and {sr} rad")
    return np.diag([st * st] * 3 + [sr * sr] * 3)


def drifting_odometry(T_W_S: np.ndarray, trans_sigma_m: float, rot_sigma_rad: float,
                      seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Odometry increments and dead-reckoned poses from recorded poses (module docstring's model).

    Parameters
    ----------
    T_W_S : (n, 4, 4) float
        Recorded poses.
    trans_sigma_m, rot_sigma_rad : float
        Per-step standard deviation of each translation axis (m) and rotation axis (rad).
    seed : int
        Seed of ``numpy.random.default_rng``.

    Returns
    -------
    U : (n, 4, 4) float64
        ``U[0] = I``; ``U[k]`` the noisy step from ping ``k - 1`` to ``k``.
    T_odo : (n, 4, 4) float64
        ``T_odo[0] = T_W_S[0]``, ``T_odo[k] = T_odo[k - 1] @ U[k]``.
    """
    T = np.asarray(T_W_S, dtype=np.float64)
    if T.ndim != 3 or T.shape[1:] != (4, 4) or T.shape[0] < 1:
        raise ValueError(f"Expected poses of shape (n, 4, 4) with n >= 1, but got {T.shape}")
    Q = motion_cov(trans_sigma_m, rot_sigma_rad)
    sd = np.sqrt(np.diag(Q))
    rng = np.random.default_rng(seed)
    n = T.shape[0]
    U = np.zeros((n, 4, 4))
    T_odo = np.zeros((n, 4, 4))
    U[0] = np.eye(4)
    T_odo[0] = check_pose(T[0], "T_W_S[0]")
    for k in range(1, n):
        U[k] = se3_inverse(T[k - 1]) @ T[k] @ se3_exp(rng.normal(0.0, 1.0, 6) * sd)
        T_odo[k] = T_odo[k - 1] @ U[k]
    return U, T_odo


def pose_errors(T_est: np.ndarray, T_ref: np.ndarray) -> dict:
    """Position and heading errors of a pose sequence against a reference one.

    Heading is the yaw of ``R = Rz(yaw) Ry(pitch) Rx(roll)`` (rotation about the world's
    vertical); ``rotation`` is the whole rotation error's angle.

    Returns
    -------
    dict
        ``position_m`` and ``heading_rad`` / ``rotation_rad``, each with ``mean``, ``rms``,
        ``max`` and ``final`` over the run; ``per_ping`` arrays are in ``_series``.
    """
    A = np.asarray(T_est, dtype=np.float64)
    B = np.asarray(T_ref, dtype=np.float64)
    dp = np.linalg.norm(A[:, :3, 3] - B[:, :3, 3], axis=1)
    yaw_a = np.array([rpy_from_rotation(R)[2] for R in A[:, :3, :3]])
    yaw_b = np.array([rpy_from_rotation(R)[2] for R in B[:, :3, :3]])
    dh = np.abs(np.angle(np.exp(1j * (yaw_a - yaw_b))))
    Rr = np.einsum("nji,njk->nik", A[:, :3, :3], B[:, :3, :3])
    dr = np.arccos(np.clip((np.trace(Rr, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0))

    def stats(x):
        return {"mean": float(x.mean()), "rms": float(np.sqrt(np.mean(x * x))), "max": float(x.max()),
                "final": float(x[-1])}

    return {"position_m": stats(dp), "heading_rad": stats(dh), "rotation_rad": stats(dr),
            "_series": {"position_m": dp, "heading_rad": dh, "rotation_rad": dr}}


@dataclass
class LoopResult:
    """What :func:`run_ekf_loop` produced.

    Attributes
    ----------
    poses : (n, 4, 4) float64
        EKF pose after each ping's update.
    pose_covs : (n, 6, 6) float64
        Their covariances (right perturbation, translation then rotation).
    measurements : list of PointMeasurements
        Each ping's returns.
    steps : list of TrackerStep
        What the tracker did at each ping.
    ms_detect, ms_track : (n,) float64
        Milliseconds per ping in the detector and in association + EKF (predict included).
    tracker : FeatureTracker
        Its ``tracks`` and :meth:`~FeatureTracker.lifetimes`; ``tracker.ekf`` is the filter.
    trusted : (n,) bool
        Whether the filter's guard (:class:`~gpumap.ekf.guard.TrustGuard`) trusted the pings
        with the pose at each ping's update (all True without a guard).
    window_nis : (n,) float64
        The guard's windowed NIS per dof after each ping (NaN while empty or without a guard).
    """

    poses: np.ndarray
    pose_covs: np.ndarray
    measurements: list
    steps: list
    ms_detect: np.ndarray
    ms_track: np.ndarray
    tracker: FeatureTracker
    trusted: np.ndarray | None = None
    window_nis: np.ndarray | None = None


#: Defaults of the filter in the loop (``ekf_kwargs`` overrides them). The range and bearing
#: noise are only used where a return comes without a covariance; the detector gives one.
EKF_DEFAULTS = {"iterations": 3, "range_sigma_m": 0.01, "bearing_sigma_rad": np.deg2rad(0.3)}


def run_ekf_loop(
    images: Iterable[np.ndarray],
    U: np.ndarray,
    T_W_S0: np.ndarray,
    spec: SonarSpec,
    *,
    odometry_cov: np.ndarray,
    detector: PointDetector | None = None,
    measure: Callable[[int, np.ndarray], PointMeasurements] | None = None,
    before_update: Callable[[int, SonarEKF], None] | None = None,
    ekf_kwargs: dict | None = None,
    tracker_kwargs: dict | None = None,
    registrar: ScanRegistrar | None = None,
    progress: bool = False,
) -> LoopResult:
    """Odometry + detected returns + association through :class:`SonarEKF`, ping by ping.

    Parameters
    ----------
    images : iterable of (n_bins, n_beams) arrays
        The pings, in order (one per row of ``U``); read lazily.
    U : (n, 4, 4) float
        Odometry steps: ``U[k]`` moves ping ``k - 1``'s pose to ping ``k``'s (``U[0]`` unused).
    T_W_S0 : (4, 4) float
        Pose of the first ping (taken as exact).
    spec : SonarSpec
    odometry_cov : (6, 6) float
        Covariance of each odometry step (:func:`motion_cov`).
    detector : PointDetector, optional
        Default ``PointDetector(spec)``.
    measure : callable, optional
        ``measure(k, image) -> PointMeasurements`` instead of the detector (the simulator's
        unlabelled features, for instance).
    before_update : callable, optional
        ``before_update(k, ekf)`` after the prediction and before the returns (other sensors,
        e.g. a DVL's plane ranges).
    ekf_kwargs, tracker_kwargs : dict, optional
        Passed to :class:`SonarEKF` (over :data:`EKF_DEFAULTS`) and :class:`FeatureTracker`.
    registrar : ScanRegistrar, optional
        Scan-to-local-map registration (:mod:`gpumap.ekf.registration`): each odometry step is
        corrected by the ping's registration before the prediction, and the ping joins the
        local map at the filter's pose after the update.

    progress : bool
        A tqdm bar.

    Returns
    -------
    LoopResult
    """
    from tqdm import tqdm

    U = np.asarray(U, dtype=np.float64)
    if U.ndim != 3 or U.shape[1:] != (4, 4):
        raise ValueError(f"Expected odometry steps of shape (n, 4, 4), but got {U.shape}")
    Q = np.asarray(odometry_cov, dtype=np.float64)
    if Q.shape != (6, 6):
        raise ValueError(f"Expected a (6, 6) 'odometry_cov', but got {Q.shape}")
    kw = {**EKF_DEFAULTS, "vfov_rad": spec.vfov_rad, **(ekf_kwargs or {})}
    ekf = SonarEKF(T_W_S0, np.zeros((6, 6)), **kw)
    tracker = FeatureTracker(ekf, spec, **(tracker_kwargs or {}))
    if measure is None:
        det = detector if detector is not None else PointDetector(spec)
        measure = lambda k, img: det.detect(img)  # noqa: E731
    n = U.shape[0]
    poses = np.zeros((n, 4, 4))
    covs = np.zeros((n, 6, 6))
    ms_d, ms_t = np.zeros(n), np.zeros(n)
    trusted, wnis = np.ones(n, bool), np.full(n, np.nan)
    meas_all: list[PointMeasurements] = []
    steps: list[TrackerStep] = []
    k = -1
    for k, img in enumerate(tqdm(images, total=n, unit="ping", disable=not progress, desc="ekf")):
        if k >= n:
            raise ValueError(f"Expected {n} images (one per odometry step), but got more")
        t0 = time.perf_counter()
        meas = measure(k, img)
        t1 = time.perf_counter()
        Uk, Qk = U[k], Q
        if registrar is not None:  # the first ping only starts the local map
            Uk, Qk = registrar.correct_step(k, img, ekf.pose, Uk if k else np.eye(4), Qk)
        if k:
            ekf.predict(Uk, Qk)
        if before_update is not None:
            before_update(k, ekf)
        if ekf.guard is not None:
            trusted[k] = ekf.guard.trusted
        st = tracker.step(meas, Q if k else None)
        if registrar is not None:
            registrar.remember(ekf.pose)
        t2 = time.perf_counter()
        poses[k], covs[k] = ekf.pose, ekf.pose_cov
        ms_d[k], ms_t[k] = 1e3 * (t1 - t0), 1e3 * (t2 - t1)
        if ekf.guard is not None and ekf.guard.nis_per_dof is not None:
            wnis[k] = ekf.guard.nis_per_dof
        meas_all.append(meas)
        steps.append(st)
    if k + 1 != n:
        raise ValueError(f"Expected {n} images (one per odometry step), but got {k + 1}")
    return LoopResult(poses, covs, meas_all, steps, ms_d, ms_t, tracker, trusted, wnis)
