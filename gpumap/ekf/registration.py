"""Scan-to-local-map registration of a ping's first returns, fused as a correction of the odometry step.

Issue 29. Each ping's *first returns* (per beam, the range of the nearest bin at or above the
threshold, :func:`gpumap.layers.first_return.measured_first_returns`) are placed in the sonar's
imaging plane (elevation 0). The *local map* is the first returns of the last ``K`` pings,
each put in the world by the filter's own pose of that ping (never the recorded poses). A
new ping is registered against it from the filter's predicted pose ``T_pred = T_prev U``:

- :func:`register_scan`: point-to-line ICP in the predicted sonar's imaging plane (the map's
  points projected onto it, only those inside the vertical aperture): each return's
  nearest map point and the line through that point's map neighbours; Huber-weighted
  Gauss-Newton over the in-plane correction ``(rho_x, rho_y, phi_z)`` of the right
  perturbation ``T = T_pred Exp(delta)``. The sonar does not see its elevation, so
  ``rho_z``, ``phi_x`` and ``phi_y`` are not observed: they stay 0 in ``delta`` and have no
  information; of the in-plane three, directions the geometry does not fix (a flat wall
  fixes only the distance to it) are projected out by the eigenvalues of the information
  matrix (:class:`ScanRegistration`'s ``basis``).
- :func:`fuse_step`: the registration measures the odometry step's error, not the absolute
  pose: the map was built from the same estimate, so only the motion since it is observed.
  It is fused into the step as a linear measurement of the step's noise ``w`` (prior
  ``N(0, Q)``, ``U_true = U Exp(w)``): gain by Cholesky solve, Joseph form, and a
  chi-square gate on its NIS. The result ``(U Exp(w_hat), Q_post)`` goes to
  :meth:`~gpumap.ekf.filter.SonarEKF.predict` in place of ``(U, Q)``.
- :func:`place_scores` and :func:`fuse_revisit`: a *revisit*. Every ping is stored with the
  filter's pose; a new ping whose first returns match a stored one at least ``min_gap`` pings
  older closely enough is taken where that one was (up to the in-plane offset registered
  between them), and fused against the drift since (the registrar tracks its own pose
  covariance). This is the only measurement here that brings the pose back, not only slows
  its drift; without a pose graph it is approximate (see :func:`fuse_revisit`).
- :func:`image_descriptor` and :func:`image_agreement`: the revisit's *verification*. A
  revisit asserts more than the registration measures: that the unseen height, roll and pitch
  are the stored ping's too. Places whose first returns match but whose sonar was rolled or
  pitched 10-25 degrees apart are common on the real tank (the arm passes the same spot at
  another attitude), and fusing them worsened the heading. The whole image tells them apart
  where the first returns do not: of the stored pings whose first returns match, the one whose
  coarse polar image (block means, zero mean, unit norm) correlates best with the new ping's is
  taken, and only when that correlation reaches ``min_image_ncc``; otherwise no revisit.
- :class:`ScanRegistrar`: the local map, the stored pings, the noise model and the trust
  window: the NIS of the step registrations over the last ``window`` pings must stay under
  (``two_sided``: inside) its chi-square band (:func:`gpumap.ekf.guard.nis_band`), else the
  step is odometry's exactly (as the :class:`~gpumap.ekf.guard.TrustGuard` does for point
  returns).

The noise of a registration: ``sigma_m`` per return (the range bin and the surface's
roughness), times ``sqrt(corr_beams)`` because neighbouring beams see the same patch of
surface and their errors are not independent (the information is that of
``n / corr_beams`` returns). On the real tank the errors are also correlated from ping to
ping (the unseen elevation of the surface is the same in consecutive pings), so summed over a
run they drift like a bias; ``corr_beams`` was chosen on frames 0-799 of the full tank run
(``bench/ekf_registration.py``), where weighting the registration less than its per-ping NIS
suggests gave the lower pose error.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from gpumap.ekf.update import _cho_solve, _robust_cholesky
from gpumap.lie import se3_adjoint, se3_exp, se3_inverse, se3_log

__all__ = [
    "RegistrarStats",
    "ScanRegistration",
    "fuse_revisit",
    "fuse_step",
    "image_agreement",
    "image_descriptor",
    "marginal",
    "place_scores",
    "plane_points",
    "register_scan",
]

#: The in-plane components of the 6-vector ``(rho, phi)`` a ping observes.
IN_PLANE = (0, 1, 5)
#: :func:`register_scan`'s settings in :class:`ScanRegistrar` unless given (chosen on frames
#: 0-799 of the full real tank run, ``bench/ekf_registration.py``).
REGISTER_DEFAULTS = {"huber_m": 0.004, "max_pair_m": 0.02, "corr_beams": 128.0}
#: Places are compared on every this many beams' first returns.
PLACE_BEAM_STRIDE = 4
#: Block (bins, beams) of :func:`image_descriptor`'s block means.
DESCRIPTOR_BLOCK = (8, 8)


@dataclass(frozen=True)
class ScanRegistration:
    """One registration (:func:`register_scan`).

    Attributes
    ----------
    delta : (6,) float64
        Correction of the predicted pose, ``T = T_pred Exp(delta)``; 0 in directions not observed.
    info : (6, 6) float64
        Its information matrix (zero in the unobserved directions).
    basis : (m, 6) float64
        Orthonormal rows spanning the observed directions (``m`` <= 3; 0 rows: nothing observed).
    returns : int
        Returns used (inliers of the last iteration).
    rms_m : float
        RMS point-to-line residual of the inliers after the last iteration, metres.
    """

    delta: np.ndarray
    info: np.ndarray
    basis: np.ndarray
    returns: int
    rms_m: float

    @property
    def observed(self) -> int:
        return int(self.basis.shape[0])


def plane_points(ranges_m: np.ndarray, bearings_rad: np.ndarray) -> np.ndarray:
    """(n, 3) sonar-frame points of the finite ``ranges_m`` at their beam's bearing, elevation 0."""
    r = np.asarray(ranges_m, np.float64)
    b = np.asarray(bearings_rad, np.float64)
    ok = np.isfinite(r)
    return np.stack([r[ok] * np.cos(b[ok]), r[ok] * np.sin(b[ok]), np.zeros(int(ok.sum()))], axis=1)


def _map_in_plane(map_W: np.ndarray, T_pred: np.ndarray, half_vfov: float) -> np.ndarray:
    """(m, 2) the map points inside the predicted sonar's vertical aperture, on its imaging plane."""
    p = (map_W - T_pred[:3, 3]) @ T_pred[:3, :3]
    h = np.hypot(p[:, 0], p[:, 1])
    ok = (p[:, 0] > 0) & (np.abs(p[:, 2]) <= np.tan(half_vfov) * h)
    return p[ok, :2]


def _line_normals(m: np.ndarray, tree, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals (m, 2) of the line through each map point's ``k`` nearest map points, and how
    line-like that neighbourhood is (smaller eigenvalue over larger, (m,))."""
    kk = min(k, len(m))
    _, nb = tree.query(m, kk)
    nb = nb.reshape(len(m), kk)
    q = m[nb] - m[nb].mean(axis=1, keepdims=True)
    C = np.einsum("nki,nkj->nij", q, q)
    w, v = np.linalg.eigh(C)
    return v[:, :, 0], w[:, 0] / np.maximum(w[:, 1], 1e-18)


def register_scan(points_S: np.ndarray, map_W: np.ndarray, T_pred: np.ndarray, *, vfov_rad: float,
                  sigma_m: float = 0.005, corr_beams: float = 8.0, huber_m: float = 0.01,
                  max_pair_m: float = 0.05, iterations: int = 5, neighbours: int = 6,
                  min_returns: int = 30, min_eig: float = 1e2) -> ScanRegistration | None:
    """Register a ping's first returns against the local map (module docstring).

    Parameters
    ----------
    points_S : (n, 3) float
        The ping's first returns in its sonar frame (:func:`plane_points`).
    map_W : (m, 3) float
        The local map's points in the world.
    T_pred : (4, 4) float
        Predicted pose of the ping.
    vfov_rad : float
        The sonar's vertical aperture: only map points inside it are matched.
    sigma_m, corr_beams : float
        Noise of one return (m) and how many neighbouring beams share an error (module docstring).
    huber_m : float
        Huber threshold of the residuals (m).
    max_pair_m : float
        Returns farther than this from their nearest map point are not paired.
    iterations, neighbours, min_returns : int
        Gauss-Newton passes (each re-pairs), map points per line fit, fewest paired returns.
    min_eig : float
        Directions of the information matrix (translation in m, rotation in rad) below this
        eigenvalue are not observed (projected out).

    Returns
    -------
    ScanRegistration or None
        None when the ping or the map shows too little (fewer than ``min_returns`` pairs).
    """
    from scipy.spatial import cKDTree

    q = np.asarray(points_S, np.float64)[:, :2]
    if len(q) < min_returns or len(map_W) < max(min_returns, neighbours):
        return None
    m = _map_in_plane(np.asarray(map_W, np.float64), np.asarray(T_pred, np.float64), 0.5 * vfov_rad)
    if len(m) < max(min_returns, neighbours):
        return None
    tree = cKDTree(m)
    normals, flat = _line_normals(m, tree, neighbours)
    x = np.zeros(3)  # (rho_x, rho_y, phi_z)
    var = sigma_m * sigma_m * corr_beams
    A = np.zeros((3, 3))
    used, rms = 0, float("nan")
    for _ in range(iterations):
        c, s = np.cos(x[2]), np.sin(x[2])
        qt = q @ np.array([[c, s], [-s, c]]) + x[:2]
        d, j = tree.query(qt, 1, distance_upper_bound=max_pair_m)
        ok = np.isfinite(d) & (flat[np.minimum(j, len(m) - 1)] < 0.1)
        if int(ok.sum()) < min_returns:
            return None
        j = j[ok]
        n = normals[j]
        e = np.einsum("ni,ni->n", n, qt[ok] - m[j])
        qr = qt[ok] - x[:2]  # rotated return; d(qt)/d(phi) = perp(qr)
        J = np.stack([n[:, 0], n[:, 1], n[:, 1] * qr[:, 0] - n[:, 0] * qr[:, 1]], axis=1)
        a = np.abs(e)
        w = np.where(a <= huber_m, 1.0, huber_m / np.maximum(a, 1e-12))
        A = (J * w[:, None]).T @ J
        g = (J * w[:, None]).T @ e
        dx = -np.linalg.lstsq(A + 1e-9 * np.eye(3), g, rcond=None)[0]
        x = x + dx
        used = int(ok.sum())
        rms = float(np.sqrt(np.mean(e[a <= 3 * huber_m] ** 2))) if np.any(a <= 3 * huber_m) else float("nan")
        if np.linalg.norm(dx) < 1e-5:  # 10 um, 10 urad
            break
    info3 = A / var
    ev, V = np.linalg.eigh(0.5 * (info3 + info3.T))
    keep = ev >= min_eig
    B3 = V[:, keep].T  # (k, 3)
    info3 = (B3.T * ev[keep]) @ B3
    x = B3.T @ (B3 @ x)  # the correction in the observed directions only
    idx = list(IN_PLANE)
    delta = np.zeros(6)
    delta[idx] = x
    info = np.zeros((6, 6))
    info[np.ix_(idx, idx)] = info3
    basis = np.zeros((B3.shape[0], 6))
    basis[:, idx] = B3
    return ScanRegistration(delta, info, basis, used, rms)


def marginal(reg: ScanRegistration, components: tuple[int, ...]) -> ScanRegistration | None:
    """The registration of ``components`` alone (indices into the 6-vector), the others
    marginalised out; None when the registration does not observe all of them."""
    idx = list(components)
    B = reg.basis
    if B.shape[0] == 0:
        return None
    C = B.T @ np.linalg.inv(B @ reg.info @ B.T) @ B  # covariance in the observed directions
    E = np.zeros((len(idx), 6))
    E[np.arange(len(idx)), idx] = 1.0
    if np.linalg.matrix_rank(E @ B.T, tol=1e-6) < len(idx):
        return None
    Cs = C[np.ix_(idx, idx)]
    info = np.zeros((6, 6))
    info[np.ix_(idx, idx)] = np.linalg.inv(Cs)
    delta = np.zeros(6)
    delta[idx] = reg.delta[idx]
    return ScanRegistration(delta, info, E, reg.returns, reg.rms_m)


def fuse_step(U: np.ndarray, Q: np.ndarray, reg: ScanRegistration, gate: float | None,
              floor: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, float | None, bool]:
    """Fuse a registration into an odometry step (module docstring).

    ``T_pred = T_prev U``; the registration says ``T = T_pred Exp(delta)``, so it measures the
    step's noise ``w`` (``U_true = U Exp(w)``, prior ``N(0, Q)``) in its observed directions
    ``B``: ``z = B delta = B w + v``, ``v ~ N(0, (B info B^T)^-1 + B floor B^T)``; ``floor``
    (6, 6), optional: a covariance added to the registration's own (errors it does not see:
    the elevation of the surface, shared by consecutive pings).

    Returns
    -------
    (U_post (4, 4), Q_post (6, 6), nis or None, fused)
        ``nis`` over ``m`` dof (None when nothing is observed); with ``fused`` False (nothing
        observed, or the NIS above ``gate``) the step is ``(U, Q)`` unchanged.
    """
    B = reg.basis
    if B.shape[0] == 0:
        return U, Q, None, False
    z = B @ reg.delta
    R = np.linalg.inv(B @ reg.info @ B.T)
    if floor is not None:
        R = R + B @ floor @ B.T
    R = 0.5 * (R + R.T)
    HQ = B @ Q
    S = HQ @ B.T + R
    S = 0.5 * (S + S.T)
    cho = _robust_cholesky(S)
    nis = float(z @ _cho_solve(cho, z))
    if gate is not None and not nis <= gate:
        return U, Q, nis, False
    KT = _cho_solve(cho, HQ)  # (m, 6) = K^T
    w = KT.T @ z
    AQ = Q - KT.T @ HQ
    Qp = AQ - (AQ @ B.T) @ KT + KT.T @ R @ KT  # Joseph form
    return U @ se3_exp(w), 0.5 * (Qp + Qp.T), nis, True


def place_scores(ranges: np.ndarray, db: np.ndarray) -> np.ndarray:
    """How unlike each stored ping's first returns ``db`` ((m, n_beams), ``inf`` no return) are
    to ``ranges`` ((n_beams,)): mean absolute range difference over the beams with a return in
    both, plus ``0.05 m`` times the share of beams with a return in only one (m,)."""
    db = np.asarray(db, np.float64)
    b = np.isfinite(db)
    return _scores(np.asarray(ranges, np.float64), np.where(b, db, 0.0).astype(np.float32), b)


def _scores(ranges: np.ndarray, db_val: np.ndarray, db_ok: np.ndarray) -> np.ndarray:
    """:func:`place_scores` on a store kept as values (0 where no return, float32) and a mask."""
    a = np.isfinite(ranges)
    r = np.where(a, ranges, 0.0).astype(np.float32)
    both = db_ok & a
    cnt = both.sum(axis=1)
    either = db_ok.sum(axis=1) + int(a.sum()) - cnt
    d = (np.abs(db_val - r) * both).sum(axis=1, dtype=np.float64)
    return d / np.maximum(cnt, 1) + 0.05 * (1.0 - cnt / np.maximum(either, 1))


def image_descriptor(image: np.ndarray, block: tuple[int, int] = DESCRIPTOR_BLOCK) -> np.ndarray:
    """A ping's coarse polar image for :func:`image_agreement`: the means of ``block`` (bins,
    beams) blocks of ``image`` ((n_bins, n_beams); a partial last block is dropped), less their
    mean, scaled to unit norm (all zeros for a constant image). uint8 and float images give the
    same descriptor (the scale cancels).

    Returns
    -------
    (n_bins // block[0] * (n_beams // block[1]),) float32
    """
    a = np.asarray(image)
    if a.ndim != 2:
        raise ValueError(f"Expected a 2D (n_bins, n_beams) image for 'image', but got shape {a.shape}")
    fb, fe = (int(v) for v in block)
    if fb < 1 or fe < 1 or a.shape[0] < fb or a.shape[1] < fe:
        raise ValueError(f"Expected a block of at least 1 x 1 that fits the image {a.shape}, but got {block}")
    nb, ne = a.shape[0] // fb, a.shape[1] // fe
    d = a[:nb * fb, :ne * fe].astype(np.float64).reshape(nb, fb, ne, fe).mean(axis=(1, 3)).ravel()
    d -= d.mean()
    n = float(np.linalg.norm(d))
    return (d / n if n > 0 else d).astype(np.float32)


def image_agreement(descriptor: np.ndarray, stored: np.ndarray) -> np.ndarray:
    """Normalised cross-correlation of a ping's :func:`image_descriptor` ((m,)) with stored ones
    ((n, m)): (n,) in [-1, 1], 1 for the same coarse image up to brightness and contrast."""
    return np.asarray(stored, np.float32) @ np.asarray(descriptor, np.float32)


def fuse_revisit(T_pred: np.ndarray, sigma_pred: np.ndarray, T_j: np.ndarray, sigma_j: np.ndarray,
                 delta: np.ndarray, R: np.ndarray, gate: float | None
                 ) -> tuple[np.ndarray, np.ndarray, float, bool]:
    """A revisit: ping ``k`` (predicted ``T_pred``) was taken where ping ``j`` was, up to ``delta``
    (``T_k = T_j Exp(delta)``, noise ``R`` (6, 6)).

    ``sigma_pred`` and ``sigma_j`` are the covariances of the poses' errors as the registrar
    tracked them; the error of ``k`` is that of ``j`` carried along (``Phi e_j``, ``Phi`` the
    adjoint of the relative motion) plus the drift since, independent of it, so the
    measurement observes only the drift: innovation ``nu = Log(T_pred^-1 T_j Exp(delta))``,
    ``D = sigma_pred - Phi sigma_j Phi^T``, gain ``D+ S^-1`` (Cholesky solve), ``S = |D| + R``.
    ``D+`` keeps D's positive eigenvalues (the drift of ``k`` since ``j``); its negative ones
    are where ``j`` is the less certain (``k`` was already brought back to an older ping, ``j``
    was not): that part of the innovation is ``j``'s own error, which counts in ``S`` and is
    not corrected. (A pose graph would keep the cross-covariances instead.)

    Returns
    -------
    (correction (6,), sigma_post (6, 6), nis (6 dof), fused)
        ``T = T_pred Exp(correction)``; unchanged (zero correction) when the NIS is above ``gate``.
    """
    nu = se3_log(se3_inverse(T_pred) @ T_j @ se3_exp(delta))
    Phi = se3_adjoint(se3_inverse(se3_inverse(T_j) @ T_pred))
    w, V = np.linalg.eigh(sigma_pred - Phi @ sigma_j @ Phi.T)
    G = (V * np.maximum(w, 0.0)) @ V.T  # the drift since j: cov(e_k, nu)
    S = (V * np.abs(w)) @ V.T + R  # ... plus, where j is the less certain, j's own drift
    S = 0.5 * (S + S.T)
    cho = _robust_cholesky(S)
    nis = float(nu @ _cho_solve(cho, nu))
    if gate is not None and not nis <= gate:
        return np.zeros(6), sigma_pred, nis, False
    KT = _cho_solve(cho, G.T)  # (6, 6) = K^T
    post = sigma_pred - G @ KT
    w, V = np.linalg.eigh(0.5 * (post + post.T))
    return KT.T @ nu, (V * np.maximum(w, 0.0)) @ V.T, nis, True


@dataclass
class RegistrarStats:
    """What a :class:`ScanRegistrar` did, per ping."""

    pings: int = 0
    registered: int = 0  # a step registration was found
    fused: int = 0  # ... and corrected the step
    gated: int = 0  # refused by the per-ping gate
    distrusted: int = 0  # refused because the window's NIS was out of its band
    revisits: int = 0  # a stored ping matched the new one
    revisits_fused: int = 0  # ... and corrected the pose
    revisits_gated: int = 0
    revisits_unverified: int = 0  # first returns matched, but no such ping's image agreed (not used)
    nis: list = field(default_factory=list)

    def to_dict(self) -> dict:
        n = np.array(self.nis, float)
        return {"pings": self.pings, "registered": self.registered, "fused": self.fused,
                "gated": self.gated, "distrusted": self.distrusted,
                "fused_share": self.fused / self.pings if self.pings else 0.0,
                "nis_per_dof_median": float(np.median(n)) if n.size else None,
                "revisits": self.revisits, "revisits_fused": self.revisits_fused,
                "revisits_gated": self.revisits_gated, "revisits_unverified": self.revisits_unverified}
