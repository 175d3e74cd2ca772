"""Ranges to a known plane: the EKF step that fuses slant ranges along rays fixed to the sonar
(a DVL's beams through its mount) to a known world plane (the floor).

:meth:`gpumap.ekf.filter.SonarEKF.update_plane_ranges` documents the step and runs
:func:`fuse_plane_ranges`, a pure function of the filter's state: it returns the new state (or
None when no ray was fused) and what it did with each ray (:class:`PlaneUpdateResult`). The
model is :func:`gpumap.ekf.measurement.plane_range_model`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from gpumap.ekf._checks import _check_matrix3, _check_vector, _real_array
from gpumap.ekf.measurement import MIN_PLANE_COS, plane_range_model, wrap_angle
from gpumap.ekf.motion import _inject, _inject_gauge
from gpumap.ekf.update import _cho_solve, _robust_cholesky
from gpumap.errors import check_finite_scalar

__all__ = ["PlaneUpdateResult", "fuse_plane_ranges"]


@dataclass(frozen=True)
class PlaneUpdateResult:
    """What :meth:`~gpumap.ekf.filter.SonarEKF.update_plane_ranges` did with each ray (indices into
    its input).

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


def fuse_plane_ranges(
    T: np.ndarray, P: np.ndarray, S_feat: np.ndarray, G: np.ndarray, n_gauge: int,  # the filter's state
    T_W_S: np.ndarray, pose_rows: np.ndarray, gate: float,  # read from it: pose, pose rows, 1-dof gate
    origins_S: np.ndarray, directions_S: np.ndarray, ranges_m: np.ndarray,  # the rays and the plane,
    plane_n_W: np.ndarray, plane_d_m: float, range_sigma_m: float,  # as update_plane_ranges takes them
) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None, PlaneUpdateResult]:
    """One plane-range update of the filter's state (:meth:`~gpumap.ekf.filter.SonarEKF.update_plane_ranges`).

    Parameters
    ----------
    T : (4, 4) float
        The pose in the gauge's frame.
    P : (N, N) float
        The state covariance (pose error, features, then ``n_gauge`` gauge states).
    S_feat : (n, 3) float
        The features' anchored ``(r, az, el)``.
    G : (4, 4) float
        The gauge, the first pose estimate.
    n_gauge : int
        Gauge states at the end of ``P`` (6, or 0 when the gauge is exact).
    T_W_S : (4, 4) float
        The pose estimate, ``G @ T``.
    pose_rows : (6, N) float
        Map from the state's error to the world pose's right perturbation.
    gate : float
        Chi-square (1 dof) gate of each ray's NIS.
    origins_S, directions_S, ranges_m, plane_n_W, plane_d_m, range_sigma_m
        As :meth:`~gpumap.ekf.filter.SonarEKF.update_plane_ranges`.

    Returns
    -------
    ((T, P, S_feat, G) or None, PlaneUpdateResult)
        The updated state (new arrays; the inputs are not changed), None when no ray was fused.

    Raises
    ------
    ValueError
        Inputs of the wrong shape or values (checked before anything is computed).
    FloatingPointError
        Non-finite values in the updated state.
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
    r_hat, H, cos_inc = plane_range_model(T_W_S, o, u, n_W, d)
    ok = valid & (np.abs(cos_inc) >= MIN_PLANE_COS) & np.isfinite(r_hat) & (r_hat > 0)
    degenerate = tuple(int(i) for i in np.flatnonzero(valid & ~ok))
    idx = np.flatnonzero(ok)
    if idx.size == 0:
        return None, PlaneUpdateResult(skipped=skipped, degenerate=degenerate)
    nu = rng_m[idx] - r_hat[idx]
    Hp = H[idx] @ pose_rows  # (a, N): pose and gauge; the features' columns are zero
    var = sr * sr
    s_ii = np.einsum("ij,ij->i", Hp @ P, Hp) + var
    d2 = nu * nu / s_ii
    rejected = {int(idx[j]): float(d2[j]) for j in np.flatnonzero(~(d2 <= gate))}
    keep = np.flatnonzero(d2 <= gate)
    if keep.size == 0:
        return None, PlaneUpdateResult(rejected=rejected, skipped=skipped, degenerate=degenerate)
    Hp, nu = Hp[keep], nu[keep]
    HP = Hp @ P  # (a, N)
    S = HP @ Hp.T
    S[np.diag_indices(keep.size)] += var
    S = 0.5 * (S + S.T)
    cho = _robust_cholesky(S)
    KT = _cho_solve(cho, HP)  # (a, N) = K^T, no inverse
    nis = float(nu @ _cho_solve(cho, nu))
    dx = KT.T @ nu
    # Joseph form (I - K H) P (I - K H)^T + K R K^T with H = [Hp, 0].
    AP = P - KT.T @ HP
    Pn = AP - (AP @ Hp.T) @ KT + var * (KT.T @ KT)
    T, Pn = _inject(T, Pn, dx[:6])
    if n_gauge:
        G, Pn = _inject_gauge(G, Pn, dx[-6:])
    S_f = S_feat + dx[6 : Pn.shape[0] - n_gauge].reshape(-1, 3)
    S_f[:, 1] = wrap_angle(S_f[:, 1])
    if not (np.all(np.isfinite(Pn)) and np.all(np.isfinite(T)) and np.all(np.isfinite(S_f))
            and np.all(np.isfinite(G))):
        raise FloatingPointError(
            "update_plane_ranges produced non-finite values; the filter is unchanged")
    return (T, Pn, S_f, G), PlaneUpdateResult(
        accepted=tuple(int(i) for i in idx[keep]),
        rejected=rejected,
        skipped=skipped,
        degenerate=degenerate,
        nis=nis,
    )
