"""Kalman update algebra of the sonar EKF for block-sparse ``H`` (private).

Each return's Jacobian has a pose block ``(2, 6)`` and one feature block ``(2, 3)``; gains come
from a Cholesky solve of the innovation covariance (never its inverse), the covariance update
is the Joseph form, and the iterated update (IEKF) relinearises at the updated estimate.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg

from gpumap.ekf.measurement import _linearize
from gpumap.ekf.motion import _inject
from gpumap.lie import se3_ad, se3_exp

_EYE6 = np.eye(6)


def _hp(P: np.ndarray, Hp: np.ndarray, Hs: np.ndarray, slots: np.ndarray) -> np.ndarray:
    """``H @ P`` for block-sparse ``H`` (pose block + one feature block per return), ``(k, 2, N)``."""
    rows = 6 + 3 * slots[:, None] + np.arange(3)[None]  # (k, 3)
    return np.einsum("kij,jn->kin", Hp, P[:6]) + np.einsum("kij,kjn->kin", Hs, P[rows])


def _s_blocks(HP: np.ndarray, Hp: np.ndarray, Hs: np.ndarray, slots: np.ndarray) -> np.ndarray:
    """Diagonal ``2x2`` blocks of ``H P H^T``, ``(k, 2, 2)``."""
    k = HP.shape[0]
    cols = 6 + 3 * slots[:, None] + np.arange(3)[None]
    own = HP[np.arange(k)[:, None, None], np.arange(2)[None, :, None], cols[:, None, :]]
    return np.einsum("kin,kjn->kij", HP[:, :, :6], Hp) + np.einsum("kin,kjn->kij", own, Hs)


@dataclass
class _Gain:
    """One linearisation's gain: ``K^T`` (2a, N), ``H P`` (2a, N), the pose block of ``H``
    (2a, 6), the feature blocks ``H_s`` (a, 2, 3) and their state columns (3a,), the
    measurement covariance blocks ``R`` (a, 2, 2) and the Cholesky factor of the innovation
    covariance."""

    KT: np.ndarray
    HPf: np.ndarray
    Hpf: np.ndarray
    Hs: np.ndarray
    cols: np.ndarray
    Rb: np.ndarray
    cho: tuple[np.ndarray, bool]

    def nis(self, nu: np.ndarray) -> float:
        """``nu^T S^-1 nu`` for a stacked innovation ``(2a,)``."""
        return float(nu @ _cho_solve(self.cho, nu))

    def h_times(self, dx: np.ndarray) -> np.ndarray:
        """``H dx`` for a full error-state vector ``(N,)``; returns ``(2a,)``."""
        a = self.Hs.shape[0]
        return self.Hpf @ dx[:6] + np.einsum("kij,kj->ki", self.Hs, dx[self.cols].reshape(a, 3)).reshape(-1)


@dataclass
class _Returns:
    """What an update needs of ``a`` returns besides the state: their features' anchored
    coordinates ``S (a, 3)``, anchors ``Ra (a, 3, 3)``, ``ta (a, 3)``, state slots ``(a,)``,
    measurements ``(a, 2)``, the noise variances ``r_var (2,)`` (or each return's own
    covariance, ``(a, 2, 2)``) and, for the second-order
    elevation term, each feature's prior elevation variance ``ve (a,)`` (zeros: first order).
    """

    S: np.ndarray
    Ra: np.ndarray
    ta: np.ndarray
    slots: np.ndarray
    meas: np.ndarray
    r_var: np.ndarray
    ve: np.ndarray

    def take(self, sel: np.ndarray) -> _Returns:
        return _Returns(self.S[sel], self.Ra[sel], self.ta[sel], self.slots[sel], self.meas[sel],
                        self.r_var[sel] if self.r_var.ndim == 3 else self.r_var, self.ve[sel])

    def terms(self, nu: np.ndarray, hee: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Second-order innovations and measurement covariance blocks ``(a, 2)``, ``(a, 2, 2)``.

        For an elevation ``e ~ N(e_hat, ve)`` the Gaussian second-order filter predicts
        ``E[h] = h(e_hat) + h_ee ve / 2`` and adds ``h_ee h_ee^T ve^2 / 2`` to ``R`` (only the
        elevation direction is curved enough to matter: at ``e = 0`` the range has no
        first-order sensitivity to it, only this one).
        """
        if self.r_var.ndim == 3:
            Rb = self.r_var.copy()
        else:
            Rb = np.zeros((nu.shape[0], 2, 2))
            Rb[:, 0, 0], Rb[:, 1, 1] = self.r_var[0], self.r_var[1]
        if not np.any(self.ve):
            return nu, Rb
        Rb += (0.5 * self.ve**2)[:, None, None] * hee[:, :, None] * hee[:, None, :]
        return nu - 0.5 * self.ve[:, None] * hee, Rb


def _gain(
    P: np.ndarray,
    Hp: np.ndarray,
    Hs: np.ndarray,
    slots: np.ndarray,
    Rb: np.ndarray,
    own_only: np.ndarray | None = None,
    HP: np.ndarray | None = None,
) -> _Gain:
    """Kalman gain of ``a`` returns with block-sparse ``H`` (pose block + each return's feature).

    ``Rb (a, 2, 2)`` are the returns' measurement covariances. ``own_only`` (a,) bool marks
    returns whose gain is cut to their own feature's three states (Schmidt-Kalman "consider"
    update: the rest of the state is not corrected by them; the Joseph form keeps the
    covariance right for this suboptimal gain). ``HP``: :func:`_hp`, if the caller has it.
    """
    a = Hp.shape[0]
    N = P.shape[0]
    HPf = (_hp(P, Hp, Hs, slots) if HP is None else HP).reshape(2 * a, N)
    Hpf = Hp.reshape(2 * a, 6)
    cols = (6 + 3 * slots[:, None] + np.arange(3)[None]).reshape(-1)  # (3a,)
    S = HPf[:, :6] @ Hpf.T
    S += np.einsum("mkj,kij->mki", HPf[:, cols].reshape(2 * a, a, 3), Hs).reshape(2 * a, 2 * a)
    S4 = S.reshape(a, 2, a, 2)
    S4[np.arange(a), :, np.arange(a), :] += Rb
    S = 0.5 * (S + S.T)
    cho = _robust_cholesky(S)
    KT = _cho_solve(cho, HPf)  # (2a, N) = K^T, no inverse
    if own_only is not None and np.any(own_only):
        for j in np.flatnonzero(own_only):
            keep = KT[2 * j : 2 * j + 2, cols[3 * j : 3 * j + 3]].copy()
            KT[2 * j : 2 * j + 2] = 0.0
            KT[2 * j : 2 * j + 2, cols[3 * j : 3 * j + 3]] = keep
    return _Gain(KT, HPf, Hpf, Hs, cols, Rb, cho)


def _iterate(
    T: np.ndarray,
    P: np.ndarray,
    ret: _Returns,
    lin: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    iterations: int,
    own_only: np.ndarray | None = None,
    dx0: np.ndarray | None = None,
    pre: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, _Gain, float, float]:
    """Iterated (Gauss-Newton) EKF solve of ``a`` returns; the first pass is the plain EKF.

    ``lin = (nu, H_pose, H_s, h_ee)`` is :func:`_linearize` at the prior. Pass ``i``
    relinearises at the current estimate ``x_i`` (pose ``T Exp(dx_pose)``, features
    ``S + dx_s``) and solves ``x_{i+1} = K_i (z - h(x_i) + H_i x_i)``, where the pose block of
    ``H_i`` carries the right Jacobian ``J_r(dx_pose) ~ I - ad(dx_pose)/2`` because the error
    state stays in the prior's tangent space. ``dx0`` starts the passes there instead of at
    the prior (a start elsewhere on the elevation arc; the prior's own linearisation is then
    only a fallback). It stops when the step stops changing, after ``iterations`` passes, or
    when a relinearisation would be degenerate (then it keeps the last good pass). ``pre``:
    ``ret.terms(nu, hee)`` and :func:`_hp` at the prior, if the caller has them.

    Returns
    -------
    dx : (N,) float64
        Error-state correction in the prior's tangent space.
    gain : _Gain
        The gain of the last linearisation (for the covariance update).
    nis_prior, nis_last : float
        NIS of the prior linearisation, and of the last one (``nu_eff^T S^-1 nu_eff``, the
        minimum of the linearised MAP cost: the nonlinear NIS at convergence).
    """
    nu, Hp, Hs, hee = lin
    nu_e, Rb, HP = (*ret.terms(nu, hee), None) if pre is None else pre
    g = _gain(P, Hp, Hs, ret.slots, Rb, own_only, HP)
    nu_f = nu_e.reshape(-1)
    nis0 = nis = g.nis(nu_f)
    dx = g.KT.T @ nu_f
    start = 1
    if dx0 is not None:
        dx, start = dx0, 0
    rows = (6 + 3 * ret.slots[:, None] + np.arange(3)[None]).reshape(-1)
    curv = bool(np.any(ret.ve))
    for _ in range(start, iterations):
        dpose = dx[:6]
        Ti = T @ se3_exp(dpose)
        Si = ret.S + dx[rows].reshape(-1, 3)
        nu_i, Hp_i, Hs_i, ok, hee_i = _linearize(Ti, Si, ret.Ra, ret.ta, ret.meas, curv)
        if not np.all(ok):
            break
        Hp_i = Hp_i @ (_EYE6 - 0.5 * se3_ad(dpose))
        nu_i, Rb_i = ret.terms(nu_i, hee_i)
        gi = _gain(P, Hp_i, Hs_i, ret.slots, Rb_i, own_only)
        eff = nu_i.reshape(-1) + gi.h_times(dx)
        dx_new = gi.KT.T @ eff
        if not np.all(np.isfinite(dx_new)):
            break
        step = float(np.abs(dx_new - dx).max())
        g, dx, nis = gi, dx_new, gi.nis(eff)
        if step <= 1e-12 + 1e-9 * float(np.abs(dx).max()):
            break
    return dx, g, nis0, nis


def _apply(T: np.ndarray, P: np.ndarray, dx: np.ndarray, g: _Gain) -> tuple[np.ndarray, np.ndarray]:
    """Joseph-form covariance update with gain ``g``; inject the pose part of ``dx``.

    Returns the new pose and covariance; the feature part ``dx[6:]`` is the caller's.
    """
    N = P.shape[0]
    a = g.Hs.shape[0]
    # Joseph form (I - K H) P (I - K H)^T + K R K^T, evaluated with the sparse H.
    AP = P - g.KT.T @ g.HPf
    APHt = AP[:, :6] @ g.Hpf.T + np.einsum(
        "nkj,kij->nki", AP[:, g.cols].reshape(N, a, 3), g.Hs
    ).reshape(N, 2 * a)
    KT3 = g.KT.reshape(a, 2, N)
    RKT = np.einsum("kij,kjn->kin", g.Rb, KT3).reshape(2 * a, N)
    Pn = AP - APHt @ g.KT + g.KT.T @ RKT
    return _inject(T, Pn, dx[:6])


def _elevation_var_given_pose(P: np.ndarray, slots: np.ndarray) -> np.ndarray:
    """Variance of each feature's anchored elevation given the current pose, ``(k,)``.

    ``P_ee - P_ep P_pp^+ P_pe``: how well the relative geometry (not the pose) fixes it.
    """
    e = 6 + 3 * slots + 2
    Ppp = P[:6, :6]
    Pep = P[np.ix_(e, np.arange(6))]  # (k, 6)
    scale = float(np.abs(np.diag(Ppp)).max())
    c, info = _POTRF(Ppp, lower=1, clean=1)
    if info == 0 and float(np.diag(c).min()) ** 2 > 1e-12 * scale:  # well conditioned: Cholesky
        y, _ = _POTRS(c, Pep.T, lower=1)
        return P[e, e] - np.einsum("ik,ik->k", Pep.T, y)
    lam, V = np.linalg.eigh(Ppp)  # singular (an exactly known pose direction): pseudo-inverse
    tol = max(float(lam.max()), 1e-300) * 1e-12
    inv = (V / np.where(lam > tol, lam, np.inf)) @ V.T
    return P[e, e] - np.einsum("ki,ij,kj->k", Pep, inv, Pep)


def _nis_2x2(S: np.ndarray, nu: np.ndarray) -> np.ndarray:
    """``nu_k^T S_k^-1 nu_k`` for ``k`` symmetric 2x2 blocks, by the 2x2 Cholesky factor.

    A block that is not positive definite gives ``inf`` (the return is then gated out).
    """
    a = S[:, 0, 0]
    b = 0.5 * (S[:, 0, 1] + S[:, 1, 0])
    c = S[:, 1, 1]
    ok = a > 0
    l11 = np.sqrt(np.where(ok, a, 1.0))
    l21 = b / l11
    d = c - l21 * l21
    ok &= d > 0
    l22 = np.sqrt(np.where(ok, d, 1.0))
    y1 = nu[:, 0] / l11
    y2 = (nu[:, 1] - l21 * y1) / l22
    return np.where(ok, y1 * y1 + y2 * y2, np.inf)


_POTRF, _POTRS = scipy.linalg.lapack.get_lapack_funcs(("potrf", "potrs"), (np.zeros(1),))


def _cho_solve(cho: tuple[np.ndarray, bool], b: np.ndarray) -> np.ndarray:
    """``S^-1 b`` from :func:`_robust_cholesky`'s factor (LAPACK ``potrs``, no checks: hot path)."""
    x, info = _POTRS(cho[0], b, lower=1)
    if info != 0:
        raise FloatingPointError(f"Expected a solvable innovation covariance, but LAPACK potrs said {info}")
    return x


def _robust_cholesky(S: np.ndarray) -> tuple[np.ndarray, bool]:
    """Lower Cholesky factor of a symmetric ``S`` (LAPACK ``potrf``), as ``(L, True)``; adds
    growing jitter only if round-off broke positive definiteness."""
    c, info = _POTRF(S, lower=1, clean=1)
    if info == 0:
        return c, True
    d = np.abs(np.diag(S)).max()
    for k in range(-14, -5):
        c, info = _POTRF(S + (d * 10.0**k) * np.eye(S.shape[0]), lower=1, clean=1)
        if info == 0:
            return c, True
    raise FloatingPointError(
        "Expected a positive definite innovation covariance, but Cholesky failed even with "
        "jitter; the filter is unchanged"
    )
