"""Motion model of the sonar EKF: the pose error through odometry, and its reset after a correction.

Pose errors are right perturbations on SE(3): ``T_W_S = T_hat @ Exp(delta)``,
``delta = (rho m, phi rad)`` (:mod:`gpumap.lie`). Odometry ``U`` moves the pose
``T_next = T_prev @ U @ Exp(w)``, ``w ~ N(0, motion_cov)``.
"""

from __future__ import annotations

import numpy as np

from gpumap.lie import orthonormalize, se3_ad, se3_adjoint, se3_exp, se3_inverse

__all__ = ["motion_jacobian"]


def motion_jacobian(T_Sprev_Snext: np.ndarray) -> np.ndarray:
    """Jacobian of the pose error through a relative motion: ``Ad(T_Sprev_Snext^-1)``.

    With ``T_next = T_prev @ U`` and right perturbations, ``delta_next = Ad(U^-1) delta_prev + w``
    where ``w`` is the motion noise (right perturbation of ``U``).

    Returns
    -------
    (6, 6) float64
    """
    return se3_adjoint(se3_inverse(np.asarray(T_Sprev_Snext, dtype=np.float64)))


def _inject(T: np.ndarray, Pn: np.ndarray, dpose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Apply the pose correction ``dpose`` (6,) to ``T``; move ``Pn``'s pose rows/columns with it.

    ``T_true = T Exp(e)``, ``T_new = T Exp(d)``  =>  ``e_new ~= J_r(d) (e - d)``,
    ``J_r ~= I - ad(d)/2``. Returns the new pose and the symmetrised covariance.
    """
    Tn = _renormalized(T @ se3_exp(dpose))
    G = np.eye(6) - 0.5 * se3_ad(dpose)
    Pn[:6, :] = G @ Pn[:6, :]
    Pn[:, :6] = Pn[:, :6] @ G.T
    Pn = 0.5 * (Pn + Pn.T)
    return Tn, Pn


def _inject_gauge(G: np.ndarray, Pn: np.ndarray, dg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_inject` for the gauge, the last 6 states (nothing to do for a zero correction)."""
    if not np.any(dg):
        return G, Pn
    Gn = _renormalized(G @ se3_exp(dg))
    J = np.eye(6) - 0.5 * se3_ad(dg)
    Pn[-6:, :] = J @ Pn[-6:, :]
    Pn[:, -6:] = Pn[:, -6:] @ J.T
    return Gn, 0.5 * (Pn + Pn.T)


def _renormalized(T: np.ndarray) -> np.ndarray:
    """``T`` with its rotation projected back onto SO(3) once round-off has moved it 1e-12 away
    (the SVD costs more than the whole check; products of rotations drift slowly)."""
    R = T[:3, :3]
    if float(np.abs(R.T @ R - np.eye(3)).max()) > 1e-12:
        T[:3, :3] = orthonormalize(R)
    return T
