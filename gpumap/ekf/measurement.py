"""Measurement models of the sonar EKF: (range, azimuth) of a point, ranges to a known plane.

A point ``l_W`` seen from pose ``T_W_S``: ``p = T_W_S^-1 l_W`` in the sonar frame (x forward,
y left, z up); ``r = |p|``, ``azimuth = atan2(p_y, p_x)``; the elevation ``atan2(p_z, |p_xy|)``
is not measured. Pose Jacobians are for the right perturbation ``T = T_hat @ Exp(rho, phi)``.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "MIN_HORIZONTAL_M",
    "MIN_PLANE_COS",
    "observation_model",
    "plane_range_model",
    "spherical_point",
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

    Returns ``z (k, 2)``, ``H_pose (k, 2, 6)``, ``H_l (k, 2, 3)``, the horizontal
    distance ``(k,)`` (for the degenerate-geometry test) and the points in the sonar frame.
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
    return z, Hp, Hl, rh, P


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
    z, Hp, Hl, _, _ = _observe_batch(T[:3, :3], T[:3, 3], np.asarray(l_W, dtype=np.float64)[None])
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


def _anchored_to_world(
    S: np.ndarray, Ra: np.ndarray, ta: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """World points ``(k, 3)`` and ``d l / d s`` ``(k, 3, 3)`` of anchored features."""
    if S.shape[0] == 0:
        return np.zeros((0, 3)), np.zeros((0, 3, 3))
    p, D = spherical_point(S)
    return ta + np.einsum("kij,kj->ki", Ra, p), Ra @ D


def _linearize(
    T: np.ndarray, S: np.ndarray, Ra: np.ndarray, ta: np.ndarray, meas: np.ndarray,
    curvature: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Innovations ``(k, 2)``, ``H_pose (k, 2, 6)``, ``H_s (k, 2, 3)``, a usable mask ``(k,)``
    and the second derivative of ``(range, azimuth)`` in the anchored elevation ``(k, 2)``.

    ``S``, ``Ra``, ``ta`` are the anchored coordinates and anchors of the ``k`` returns'
    features, ``meas`` their ``(range, azimuth)``. A return is not usable when its feature is
    predicted on the sonar's z axis (azimuth undefined) or its anchored coordinates are
    degenerate (``r <= 0`` or elevation at +-90 deg). ``curvature=False``: zeros for the last.
    """
    Lw, J = _anchored_to_world(S, Ra, ta)
    R, t = T[:3, :3], T[:3, 3]
    z, Hp, Hl, rh, q = _observe_batch(R, t, Lw)
    ok = (rh > MIN_HORIZONTAL_M * np.maximum(1.0, z[:, 0])) & (S[:, 0] > 0) & (np.cos(S[:, 2]) > 1e-6)
    nu = meas - z
    nu[:, 1] = wrap_angle(nu[:, 1])
    Hs = Hl @ J
    if not curvature:
        return nu, Hp, Hs, ok, np.zeros_like(nu)
    # d^2 z / d el^2 (see _elevation_curvature, the reference form), from what is at hand:
    # dz/dq q'' = H_l (-(l - t_A)); q_hat . v = H_s[:, 0, 2]; |v| = r_A (the arc's radius).
    hee = np.einsum("kij,kj->ki", Hl, ta - Lw)
    rs = np.where(z[:, 0] > 0, z[:, 0], 1.0)
    hee[:, 0] += (S[:, 0] ** 2 - Hs[:, 0, 2] ** 2) / rs
    v = J[:, :, 2] @ R
    x, y, vx, vy = q[:, 0], q[:, 1], v[:, 0], v[:, 1]
    h2 = np.where(rh > 0, rh * rh, 1.0)
    hee[:, 1] += (2 * x * y * (vx * vx - vy * vy) + 2 * (y * y - x * x) * vx * vy) / (h2 * h2)
    return nu, Hp, Hs, ok, hee


def _elevation_curvature(
    R: np.ndarray, t: np.ndarray, Lw: np.ndarray, J: np.ndarray, arm_W: np.ndarray
) -> np.ndarray:
    """``d^2 (range, azimuth) / d el^2`` ``(k, 2)`` of anchored features seen from ``(R, t)``.

    The point moves on its elevation arc: ``d l / d el = J[:, :, 2]`` and
    ``d^2 l / d el^2 = -(l - t_A)`` (``arm_W``, the anchor-to-point vector: ``d^2 p / d el^2 = -p``
    in spherical coordinates). With ``q = R^T (l - t)`` and ``v = dq/d el``:
    ``r'' = q_hat . q'' + (|v|^2 - (q_hat . v)^2) / |q|`` and, for ``az = atan2(y, x)``,
    ``az'' = (x q''_y - y q''_x) / rho^2 + (2 x y (v_x^2 - v_y^2) + 2 (y^2 - x^2) v_x v_y) / rho^4``.
    At elevation 0 the range has no first-order sensitivity to elevation; this is the term
    that carries the chord effect (``SonarEKF(second_order=True)``).
    """
    q = (Lw - t) @ R
    v = J[:, :, 2] @ R
    a = -(arm_W @ R)
    x, y = q[:, 0], q[:, 1]
    r = np.linalg.norm(q, axis=1)
    rs = np.where(r > 0, r, 1.0)
    rho2 = x * x + y * y
    hs = np.where(rho2 > 0, rho2, 1.0)
    qv = np.einsum("ki,ki->k", q, v) / rs
    d_r = np.einsum("ki,ki->k", q, a) / rs + (np.einsum("ki,ki->k", v, v) - qv * qv) / rs
    vx, vy = v[:, 0], v[:, 1]
    d_az = (x * a[:, 1] - y * a[:, 0]) / hs + (
        2 * x * y * (vx * vx - vy * vy) + 2 * (y * y - x * x) * vx * vy) / (hs * hs)
    return np.stack([d_r, d_az], axis=1)


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
