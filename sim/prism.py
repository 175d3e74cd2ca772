"""The square-prism scene of Mai et al. (Section 4.1): 8 vertices seen from 21 sonar poses.

Pure NumPy and seeded. Everything is geometric: a feature return is the exact
``(range, azimuth)`` of a prism vertex plus Gaussian noise, with known correspondences
(the vertex index is the feature id); odometry is the true relative motion with a
right-perturbation error whose standard deviation is proportional to the motion.

Scene (world = the first sonar frame, x forward, y left, z up):

- a 0.2 x 0.2 x 0.3 m (W x L x H) square prism centred 2.5 m ahead, ``(2.5, 0, 0)``;
- 21 viewpoints. The paper varies ``x, y, z`` and ``psi`` (its real experiment calls
  ``psi`` the roll, rolled 0..70 deg) and keeps the two other angles at 0 while the sonar
  "always faces the object". Here the sonar moves 0.5 m closer, sways +-0.4 m sideways and
  rises 0.25 m, rolls 0 -> 70 deg about its boresight, and its boresight stays on the prism
  centre (so yaw and pitch are the few degrees that keeping it in view takes).
  Rolling is what makes elevation observable for a sonar: it turns elevation into azimuth.

The sensor defaults follow the paper's ARIS Explorer 3000: 32 deg azimuth, 14 deg elevation.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from gpumap.ekf import SonarEKF, wrap_angle
from gpumap.lie import se3_exp, se3_inverse, se3_log

__all__ = [
    "PrismConfig",
    "PrismRun",
    "FilterTrace",
    "prism_vertices",
    "look_at",
    "prism_trajectory",
    "measure",
    "motion_cov",
    "simulate",
    "run_filter",
    "run_odometry",
    "pose_error",
    "nees",
    "nees_world",
]


@dataclass(frozen=True)
class PrismConfig:
    """Parameters of the prism simulation (defaults: the scene described in the module)."""

    n_views: int = 21
    center_W: tuple[float, float, float] = (2.5, 0.0, 0.0)
    size_m: tuple[float, float, float] = (0.2, 0.2, 0.3)
    #: Vertex localisation noise: about one ARIS range bin, 0.4 of its 0.25 deg beam spacing.
    range_sigma_m: float = 0.003
    bearing_sigma_rad: float = float(np.deg2rad(0.1))
    hfov_rad: float = float(np.deg2rad(32.0))
    vfov_rad: float = float(np.deg2rad(14.0))
    #: Odometry noise, per axis: sigma_t = k_t |dt| + floor, sigma_r = k_r |dphi| + k_rt |dt| + floor.
    #: Wrist-on-an-arm levels. The sonar's pitch (about its own y axis) moves every feature in
    #: elevation only, which it does not measure, so pitch drift is held by odometry alone and
    #: feature height errors grow like range x pitch drift: see the sweep in bench/ekf_bench.py.
    k_t: float = 0.02
    k_r: float = 0.01
    k_rt_rad_per_m: float = 0.002
    floor_t_m: float = 1e-5
    floor_r_rad: float = 1e-5
    #: Trajectory amplitudes.
    advance_m: float = 0.5
    sway_m: float = 0.4
    rise_m: float = 0.25
    roll_end_rad: float = float(np.deg2rad(70.0))
    #: Fraction of the run over which the roll ramps from 0 to ``roll_end_rad`` (then holds).
    roll_ramp: float = 1.0


@dataclass
class PrismRun:
    """One seeded realisation of the scene.

    Attributes
    ----------
    points_W : (8, 3) float64
        True vertex positions (feature id = row).
    T_W_S : (n, 4, 4) float64
        True sonar poses.
    U_odo : (n - 1, 4, 4) float64
        Measured relative motions ``T_Sk_Sk+1`` (noisy).
    Q : (n - 1, 6, 6) float64
        Motion covariances the filter is told (computed from ``U_odo``).
    ids : list of (m_k,) int arrays
        Feature ids seen at each view.
    ranges_m, bearings_rad : list of (m_k,) float64 arrays
        Noisy returns at each view.
    """

    config: PrismConfig
    points_W: np.ndarray
    T_W_S: np.ndarray
    U_odo: np.ndarray
    Q: np.ndarray
    ids: list[np.ndarray] = field(default_factory=list)
    ranges_m: list[np.ndarray] = field(default_factory=list)
    bearings_rad: list[np.ndarray] = field(default_factory=list)


def prism_vertices(
    center_W: tuple[float, float, float] = (2.5, 0.0, 0.0),
    size_m: tuple[float, float, float] = (0.2, 0.2, 0.3),
) -> np.ndarray:
    """The 8 vertices of an axis-aligned box, bottom face first.

    Returns
    -------
    (8, 3) float64, world metres.
    """
    c = np.asarray(center_W, dtype=np.float64)
    h = 0.5 * np.asarray(size_m, dtype=np.float64)
    signs = np.array(
        [[-1, -1, -1], [1, -1, -1], [1, 1, -1], [-1, 1, -1],
         [-1, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1]], dtype=np.float64
    )
    return c + signs * h


def look_at(position_W: np.ndarray, target_W: np.ndarray, roll_rad: float = 0.0) -> np.ndarray:
    """Sonar pose at ``position_W`` with its x axis on ``target_W``, rolled about x.

    With ``roll_rad = 0`` the sonar's y axis is horizontal (z as close to world up as can be).

    Returns
    -------
    (4, 4) float64 ``T_W_S``.
    """
    p = np.asarray(position_W, dtype=np.float64)
    x = np.asarray(target_W, dtype=np.float64) - p
    x /= np.linalg.norm(x)
    y = np.cross([0.0, 0.0, 1.0], x)
    y /= np.linalg.norm(y)
    z = np.cross(x, y)
    c, s = np.cos(roll_rad), np.sin(roll_rad)
    y, z = c * y + s * z, -s * y + c * z
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x, y, z])
    T[:3, 3] = p
    return T


def prism_trajectory(config: PrismConfig | None = None) -> np.ndarray:
    """The true sonar poses of the scene.

    Returns
    -------
    (n_views, 4, 4) float64 ``T_W_S``; the first is the identity.
    """
    cfg = config or PrismConfig()
    s = np.linspace(0.0, 1.0, cfg.n_views)
    pos = np.stack(
        [cfg.advance_m * s, cfg.sway_m * np.sin(2 * np.pi * s), cfg.rise_m * np.sin(np.pi * s)], axis=1
    )
    roll = cfg.roll_end_rad * np.minimum(1.0, s / cfg.roll_ramp)
    return np.stack([look_at(p, cfg.center_W, ri) for p, ri in zip(pos, roll, strict=True)])


def measure(
    T_W_S: np.ndarray,
    points_W: np.ndarray,
    rng: np.random.Generator | None = None,
    range_sigma_m: float = 0.0,
    bearing_sigma_rad: float = 0.0,
    hfov_rad: float = np.pi,
    vfov_rad: float = np.pi,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Returns of the points inside the field of view, with Gaussian noise.

    Parameters
    ----------
    T_W_S : (4, 4) float
    points_W : (n, 3) float
    rng : numpy Generator, optional
        Needed when a sigma is positive.
    range_sigma_m, bearing_sigma_rad : float
    hfov_rad, vfov_rad : float
        Full apertures; a point is seen when ``|azimuth| <= hfov/2`` and ``|elevation| <= vfov/2``.

    Returns
    -------
    ids : (m,) int64
        Row indices of the points seen.
    ranges_m : (m,) float64
    bearings_rad : (m,) float64
        Azimuths, wrapped to ``(-pi, pi]``.
    """
    T = np.asarray(T_W_S, dtype=np.float64)
    p = (np.asarray(points_W, dtype=np.float64) - T[:3, 3]) @ T[:3, :3]
    r = np.linalg.norm(p, axis=1)
    az = np.arctan2(p[:, 1], p[:, 0])
    el = np.arctan2(p[:, 2], np.hypot(p[:, 0], p[:, 1]))
    seen = (np.abs(az) <= 0.5 * hfov_rad) & (np.abs(el) <= 0.5 * vfov_rad) & (r > 0)
    ids = np.flatnonzero(seen)
    r, az = r[ids], az[ids]
    if range_sigma_m > 0 or bearing_sigma_rad > 0:
        if rng is None:
            raise ValueError("Expected a numpy Generator for 'rng' when a noise sigma is > 0, but got None")
        r = r + range_sigma_m * rng.standard_normal(r.shape)
        az = az + bearing_sigma_rad * rng.standard_normal(az.shape)
    return ids, np.abs(r), wrap_angle(az)


def motion_cov(U: np.ndarray, config: PrismConfig | None = None) -> np.ndarray:
    """Odometry covariance for a relative motion: standard deviations proportional to it.

    Returns
    -------
    (6, 6) float64, diagonal, ``(translation m, rotation vector rad)``.
    """
    cfg = config or PrismConfig()
    xi = se3_log(U)
    dt = float(np.linalg.norm(U[:3, 3]))
    dr = float(np.linalg.norm(xi[3:]))
    st = cfg.k_t * dt + cfg.floor_t_m
    sr = cfg.k_r * dr + cfg.k_rt_rad_per_m * dt + cfg.floor_r_rad
    return np.diag([st * st] * 3 + [sr * sr] * 3)


def simulate(seed: int, config: PrismConfig | None = None) -> PrismRun:
    """One seeded run: true poses, noisy odometry and noisy returns at every view."""
    cfg = config or PrismConfig()
    rng = np.random.default_rng(seed)
    pts = prism_vertices(cfg.center_W, cfg.size_m)
    T = prism_trajectory(cfg)
    n = T.shape[0]
    U_odo = np.empty((n - 1, 4, 4))
    Q = np.empty((n - 1, 6, 6))
    for k in range(n - 1):
        U_true = se3_inverse(T[k]) @ T[k + 1]
        C = motion_cov(U_true, cfg)
        w = rng.multivariate_normal(np.zeros(6), C)
        # U_true = U_odo @ Exp(w)  =>  U_odo = U_true @ Exp(-w)
        U_odo[k] = U_true @ se3_exp(-w)
        Q[k] = motion_cov(U_odo[k], cfg)
    run = PrismRun(cfg, pts, T, U_odo, Q)
    for k in range(n):
        ids, r, b = measure(
            T[k], pts, rng, cfg.range_sigma_m, cfg.bearing_sigma_rad, cfg.hfov_rad, cfg.vfov_rad
        )
        run.ids.append(ids)
        run.ranges_m.append(r)
        run.bearings_rad.append(b)
    return run


@dataclass
class FilterTrace:
    """Per-view record of a filter run over a :class:`PrismRun`.

    Attributes
    ----------
    T_W_S : (n, 4, 4) float64
        Estimated poses after each view's update.
    pose_nees : (n,) float64
        6-dof NEES of the pose after each view (NaN at view 0 if the pose is exactly known).
    landmarks : (n, 8, 3) float64
        Feature estimates after each view (NaN before a feature is first seen).
    landmark_nees : (n,) float64
        NEES of all features in the state jointly (3 dof each).
    full_nees : (n,) float64
        NEES of pose and features jointly; ``full_dof`` gives its dof.
    full_dof : (n,) int
    n_obs : (n, 8) int
        How many times each feature has been seen up to and including each view.
    rejected : int
        Returns gated out over the whole run.
    """

    T_W_S: np.ndarray
    pose_nees: np.ndarray
    landmarks: np.ndarray
    landmark_nees: np.ndarray
    full_nees: np.ndarray
    full_dof: np.ndarray
    n_obs: np.ndarray
    rejected: int
    final: SonarEKF | None = None


def pose_error(T_hat: np.ndarray, T_true: np.ndarray) -> np.ndarray:
    """Right-perturbation error ``Log(T_hat^-1 T_true)``, ``(rho m, phi rad)``, shape (6,)."""
    return se3_log(se3_inverse(T_hat) @ T_true)


def _nees(e: np.ndarray, P: np.ndarray) -> float:
    try:
        c = np.linalg.cholesky(P)
    except np.linalg.LinAlgError:
        return float("nan")
    y = np.linalg.solve(c, e)
    return float(y @ y)


def _spherical(p: np.ndarray) -> np.ndarray:
    return np.array([np.linalg.norm(p), np.arctan2(p[1], p[0]), np.arctan2(p[2], np.hypot(p[0], p[1]))])


def nees(ekf: SonarEKF, T_W_S_true: np.ndarray, points_W: np.ndarray) -> tuple[float, float, float, int]:
    """NEES of a filter against the truth, on its own state: ``(pose, landmarks, full, full_dof)``.

    Feature errors are taken where the filter's Gaussian lives: the true point's anchored
    ``(r, az, el)`` minus the estimate's, in each feature's anchor frame
    (:attr:`SonarEKF.landmark_anchors`). ``points_W[i]`` is the true position of feature ``i``.
    """
    e_pose = pose_error(ekf.pose, T_W_S_true)
    anchors = ekf.landmark_anchors
    ids = ekf.landmark_ids
    e_l = []
    for i in ids:
        T_a, s_hat = anchors[i]
        s_true = _spherical(se3_inverse(T_a)[:3, :3] @ points_W[i] + se3_inverse(T_a)[:3, 3])
        d = s_true - s_hat
        d[1] = float(wrap_angle(d[1]))
        e_l.append(d)
    e_l = np.concatenate(e_l) if ids else np.zeros(0)
    P = ekf.native_covariance
    pn = _nees(e_pose, P[:6, :6])
    ln = _nees(e_l, P[6:, 6:]) if ids else float("nan")
    fn = _nees(np.concatenate([e_pose, e_l]), P)
    return pn, ln, fn, P.shape[0]


def nees_world(ekf: SonarEKF, points_W: np.ndarray) -> float:
    """NEES of all features jointly in world Cartesian coordinates (first-order covariance)."""
    lm = ekf.landmarks
    ids = ekf.landmark_ids
    e = np.concatenate([points_W[i] - lm[i] for i in ids])
    return _nees(e, ekf.covariance[6:, 6:])


def run_filter(
    run: PrismRun,
    pose_cov0: np.ndarray | None = None,
    vfov_rad: float | None = None,
    gate_prob: float | None = 0.999,
    init: str = "arc",
) -> FilterTrace:
    """Drive a :class:`SonarEKF` through a run: update at view 0, then predict + update.

    The filter starts at the true first pose with ``pose_cov0`` (default zero: the world is
    the first sonar frame, as in the paper). ``init`` selects the feature initialisation
    (:class:`SonarEKF`'s ``init``: ``"arc"`` or ``"triangulate"``).
    """
    cfg = run.config
    n = run.T_W_S.shape[0]
    npts = run.points_W.shape[0]
    ekf = SonarEKF(
        run.T_W_S[0],
        np.zeros((6, 6)) if pose_cov0 is None else pose_cov0,
        range_sigma_m=cfg.range_sigma_m,
        bearing_sigma_rad=cfg.bearing_sigma_rad,
        vfov_rad=cfg.vfov_rad if vfov_rad is None else vfov_rad,
        gate_prob=gate_prob,
        init=init,
    )
    Ts = np.empty((n, 4, 4))
    lms = np.full((n, npts, 3), np.nan)
    pn, ln, fn = np.full(n, np.nan), np.full(n, np.nan), np.full(n, np.nan)
    fd = np.zeros(n, dtype=int)
    n_obs = np.zeros((n, npts), dtype=int)
    seen = np.zeros(npts, dtype=int)
    rejected = 0
    for k in range(n):
        if k > 0:
            ekf.predict(run.U_odo[k - 1], run.Q[k - 1])
        res = ekf.update(run.ids[k], run.ranges_m[k], run.bearings_rad[k])
        rejected += len(res.rejected)
        seen[run.ids[k]] += 1
        n_obs[k] = seen
        Ts[k] = ekf.pose
        for i, v in ekf.landmarks.items():
            lms[k, i] = v
        pn[k], ln[k], fn[k], fd[k] = nees(ekf, run.T_W_S[k], run.points_W)
    return FilterTrace(Ts, pn, lms, ln, fn, fd, n_obs, rejected, ekf)


def position_ratio(run: PrismRun, guard=None, slide: float = 0.0, seed: int = 0) -> tuple[float, SonarEKF]:
    """Mean position error of a :class:`SonarEKF` (known associations, ``guard``: a
    :class:`~gpumap.ekf.guard.TrustGuard` or None) over that of dead reckoning on ``run``, and
    the filter at the end.

    ``slide`` > 0 makes every vertex a sliding scatterer: it is measured at ``p + slide *
    (t_k - t_0)``, moving with the sonar (what a glint on a wall does), so the returns are
    wrong for a model of fixed points while each one alone looks plausible; their noise draws
    from ``np.random.default_rng(1000 + seed)``.
    """
    cfg = run.config
    rng = np.random.default_rng(1000 + seed)
    ekf = SonarEKF(run.T_W_S[0], np.zeros((6, 6)), range_sigma_m=cfg.range_sigma_m,
                   bearing_sigma_rad=cfg.bearing_sigma_rad, vfov_rad=cfg.vfov_rad, guard=guard,
                   nis_window=0)
    T = np.empty_like(run.T_W_S)
    for k in range(len(T)):
        if k:
            ekf.predict(run.U_odo[k - 1], run.Q[k - 1])
        ids, r, b = run.ids[k], run.ranges_m[k], run.bearings_rad[k]
        if slide:
            pts = run.points_W + slide * (run.T_W_S[k, :3, 3] - run.T_W_S[0, :3, 3])
            ids, r, b = measure(run.T_W_S[k], pts, rng, cfg.range_sigma_m, cfg.bearing_sigma_rad,
                                cfg.hfov_rad, cfg.vfov_rad)
        ekf.update(ids, r, b)
        T[k] = ekf.pose
    To = run_odometry(run)
    e = np.linalg.norm(T[:, :3, 3] - run.T_W_S[:, :3, 3], axis=1).mean()
    o = np.linalg.norm(To[:, :3, 3] - run.T_W_S[:, :3, 3], axis=1).mean()
    return float(e / o), ekf


def run_odometry(run: PrismRun) -> np.ndarray:
    """Dead reckoning: poses from the first true pose and the noisy increments, (n, 4, 4)."""
    T = [run.T_W_S[0]]
    for U in run.U_odo:
        T.append(T[-1] @ U)
    return np.stack(T)
