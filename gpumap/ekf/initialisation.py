"""Landmark initialisation: anchored spherical coordinates and delayed triangulation.

A new feature is stored as ``s = (r, az, el)`` in the frame of the sonar pose where it was
first seen (its anchor); :func:`anchor_jacobian` carries the anchor pose's uncertainty into
``s``. :func:`triangulate` locates a point from several (range, azimuth) returns at known
relative poses (a standalone tool: ``SonarEKF(init="triangulate")`` scans the arc inside the
update instead, with the filter's full prior).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from gpumap.ekf.measurement import _hat_batch, _range_azimuth, spherical_point, wrap_angle

__all__ = ["Triangulation", "anchor_jacobian", "triangulate"]


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
