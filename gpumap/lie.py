"""SO(3) / SE(3) exponential and logarithm maps, adjoints and Jacobians (NumPy, float64).

Conventions
-----------
- A twist ``xi`` is a ``(6,)`` vector ordered ``(rho, phi)``: translation part first
  (metres), rotation vector second (radians). This is the order of every 6x6 pose
  covariance in gpumap (:mod:`gpumap.ekf`).
- ``se3_exp(xi)`` is the matrix exponential of ``[[hat(phi), rho], [0, 0]]``; so the
  translation of ``Exp(xi)`` is ``J_l(phi) @ rho``, not ``rho``.
- Perturbations are on the right: ``T = T_hat @ se3_exp(delta)``.
- ``se3_adjoint(T)`` is the 6x6 matrix with ``T @ Exp(xi) @ T^-1 == Exp(Ad(T) @ xi)``.

All functions are small and allocation-light; they take and return float64 arrays and do
not validate their input (callers at the API boundary do).
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "hat",
    "so3_exp",
    "so3_log",
    "so3_left_jacobian",
    "so3_right_jacobian",
    "se3_exp",
    "se3_log",
    "se3_inverse",
    "se3_adjoint",
    "se3_ad",
    "orthonormalize",
    "rpy_from_rotation",
    "rotation_from_rpy",
]

_SMALL = 1e-8


def hat(v: np.ndarray) -> np.ndarray:
    """Skew-symmetric matrix of a 3-vector: ``hat(a) @ b == cross(a, b)``.

    Parameters
    ----------
    v : (3,) float

    Returns
    -------
    (3, 3) float64
    """
    x, y, z = float(v[0]), float(v[1]), float(v[2])
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def so3_exp(phi: np.ndarray) -> np.ndarray:
    """Rotation matrix of a rotation vector (Rodrigues; Taylor series near zero).

    Parameters
    ----------
    phi : (3,) float
        Rotation vector, radians.

    Returns
    -------
    (3, 3) float64 rotation matrix.
    """
    phi = np.asarray(phi, dtype=np.float64)
    th2 = float(phi @ phi)
    K = hat(phi)
    if th2 < _SMALL:
        a = 1.0 - th2 / 6.0 + th2 * th2 / 120.0
        b = 0.5 - th2 / 24.0 + th2 * th2 / 720.0
    else:
        th = np.sqrt(th2)
        a = np.sin(th) / th
        b = 2.0 * np.sin(0.5 * th) ** 2 / th2
    return np.eye(3) + a * K + b * (K @ K)


def so3_log(R: np.ndarray) -> np.ndarray:
    """Rotation vector of a rotation matrix, angle in ``[0, pi]``; robust near 0 and pi.

    Parameters
    ----------
    R : (3, 3) float
        Rotation matrix.

    Returns
    -------
    (3,) float64 rotation vector, radians.
    """
    R = np.asarray(R, dtype=np.float64)
    c = np.clip((np.trace(R) - 1.0) * 0.5, -1.0, 1.0)
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    # atan2 keeps full precision at small angles (arccos loses half the digits near 1).
    th = float(np.arctan2(0.5 * np.linalg.norm(w), c))
    if th < 1e-4:
        # sin(th)/th ~ 1 - th^2/6; w = 2 sin(th) * axis
        return 0.5 * w * (1.0 + th * th / 6.0)
    if np.pi - th < 1e-3:
        # Near pi, sin(th) ~ 0: read the axis from the symmetric part R + R^T = 2 c I + 2 (1-c) a a^T.
        B = (R + R.T) * 0.5 - c * np.eye(3)
        k = int(np.argmax(np.diag(B)))
        axis = B[:, k] / np.sqrt(max(B[k, k], 1e-300))
        axis /= np.linalg.norm(axis)
        # Fix the sign with the antisymmetric part (w = 2 sin(th) axis).
        if axis @ w < 0:
            axis = -axis
        return th * axis
    return th / (2.0 * np.sin(th)) * w


def so3_left_jacobian(phi: np.ndarray) -> np.ndarray:
    """Left Jacobian ``J_l(phi)`` of SO(3): ``Exp(phi + d) ~= Exp(J_l d) Exp(phi)``.

    Parameters
    ----------
    phi : (3,) float

    Returns
    -------
    (3, 3) float64
    """
    phi = np.asarray(phi, dtype=np.float64)
    th2 = float(phi @ phi)
    K = hat(phi)
    if th2 < _SMALL:
        b = 0.5 - th2 / 24.0
        c = 1.0 / 6.0 - th2 / 120.0
    else:
        th = np.sqrt(th2)
        b = 2.0 * np.sin(0.5 * th) ** 2 / th2
        c = (th - np.sin(th)) / (th2 * th)
    return np.eye(3) + b * K + c * (K @ K)


def so3_right_jacobian(phi: np.ndarray) -> np.ndarray:
    """Right Jacobian ``J_r(phi) = J_l(-phi)``: ``Exp(phi + d) ~= Exp(phi) Exp(J_r d)``."""
    return so3_left_jacobian(-np.asarray(phi, dtype=np.float64))


def _so3_left_jacobian_inv(phi: np.ndarray) -> np.ndarray:
    phi = np.asarray(phi, dtype=np.float64)
    th2 = float(phi @ phi)
    K = hat(phi)
    if th2 < 1e-4:
        d = 1.0 / 12.0 + th2 / 720.0 + th2 * th2 / 30240.0
    else:
        th = np.sqrt(th2)
        # 1 - cos = 2 sin^2(th/2) avoids cancellation.
        d = (1.0 - th * np.sin(th) / (4.0 * np.sin(0.5 * th) ** 2)) / th2
    return np.eye(3) - 0.5 * K + d * (K @ K)


def se3_exp(xi: np.ndarray) -> np.ndarray:
    """Homogeneous transform of a twist ``xi = (rho, phi)``.

    Parameters
    ----------
    xi : (6,) float
        Translation part (m) then rotation vector (rad).

    Returns
    -------
    (4, 4) float64 rigid transform.
    """
    xi = np.asarray(xi, dtype=np.float64)
    T = np.eye(4)
    T[:3, :3] = so3_exp(xi[3:])
    T[:3, 3] = so3_left_jacobian(xi[3:]) @ xi[:3]
    return T


def se3_log(T: np.ndarray) -> np.ndarray:
    """Twist ``(rho, phi)`` of a rigid transform (inverse of :func:`se3_exp`).

    Parameters
    ----------
    T : (4, 4) float

    Returns
    -------
    (6,) float64
    """
    T = np.asarray(T, dtype=np.float64)
    phi = so3_log(T[:3, :3])
    rho = _so3_left_jacobian_inv(phi) @ T[:3, 3]
    return np.concatenate([rho, phi])


def se3_inverse(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform, ``[[R^T, -R^T t], [0, 1]]``."""
    T = np.asarray(T, dtype=np.float64)
    Ti = np.eye(4)
    Ti[:3, :3] = T[:3, :3].T
    Ti[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return Ti


def se3_adjoint(T: np.ndarray) -> np.ndarray:
    """6x6 adjoint of ``T`` in ``(rho, phi)`` order: ``[[R, hat(t) R], [0, R]]``."""
    T = np.asarray(T, dtype=np.float64)
    R, t = T[:3, :3], T[:3, 3]
    A = np.zeros((6, 6))
    A[:3, :3] = R
    A[3:, 3:] = R
    A[:3, 3:] = hat(t) @ R
    return A


def se3_ad(xi: np.ndarray) -> np.ndarray:
    """6x6 small adjoint (Lie bracket matrix) of a twist: ``[[hat(phi), hat(rho)], [0, hat(phi)]]``."""
    xi = np.asarray(xi, dtype=np.float64)
    A = np.zeros((6, 6))
    P = hat(xi[3:])
    A[:3, :3] = P
    A[3:, 3:] = P
    A[:3, 3:] = hat(xi[:3])
    return A


def orthonormalize(R: np.ndarray) -> np.ndarray:
    """Nearest rotation matrix (polar decomposition by SVD, det +1)."""
    U, _, Vt = np.linalg.svd(np.asarray(R, dtype=np.float64))
    D = np.eye(3)
    D[2, 2] = np.sign(np.linalg.det(U @ Vt))
    return U @ D @ Vt


def rotation_from_rpy(roll_rad: float, pitch_rad: float, yaw_rad: float) -> np.ndarray:
    """Rotation ``Rz(yaw) @ Ry(pitch) @ Rx(roll)`` (Z-Y-X intrinsic), as a (3, 3) float64 array."""
    cr, sr = np.cos(roll_rad), np.sin(roll_rad)
    cp, sp = np.cos(pitch_rad), np.sin(pitch_rad)
    cy, sy = np.cos(yaw_rad), np.sin(yaw_rad)
    Rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]], dtype=np.float64)
    Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]], dtype=np.float64)
    Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]], dtype=np.float64)
    return Rz @ Ry @ Rx


def rpy_from_rotation(R: np.ndarray) -> np.ndarray:
    """``(roll, pitch, yaw)`` radians of ``R = Rz(yaw) Ry(pitch) Rx(roll)``; output only.

    At gimbal lock (``|pitch| = pi/2``) roll and yaw are not separable: roll is reported as
    0 and yaw carries the whole rotation about the vertical. Always finite.

    Returns
    -------
    (3,) float64 ``[roll, pitch, yaw]``, pitch in ``[-pi/2, pi/2]``.
    """
    R = np.asarray(R, dtype=np.float64)
    sp = float(np.clip(-R[2, 0], -1.0, 1.0))
    pitch = float(np.arcsin(sp))
    if np.hypot(R[2, 1], R[2, 2]) < 1e-9:
        roll = 0.0
        # R = [[0, -s(y -/+ r) ...]]: with roll 0, yaw from the top-left 2x2 block's second column.
        yaw = float(np.arctan2(-R[0, 1], R[1, 1]))
    else:
        roll = float(np.arctan2(R[2, 1], R[2, 2]))
        yaw = float(np.arctan2(R[1, 0], R[0, 0]))
    return np.array([roll, pitch, yaw])
