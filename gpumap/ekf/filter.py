"""The sonar EKF: one joint Gaussian over the sonar pose and its point features.

See :mod:`gpumap.ekf` for the model, the conventions and the differences from Mai et al.
"""

from __future__ import annotations

import collections
import logging
import math
import warnings
from collections.abc import Iterable

import numpy as np

from gpumap.ekf._checks import (
    _check_cov,
    _check_ids,
    _check_vector,
    _chi2_2dof,
    _chi2_quantile,
    _real_array,
)
from gpumap.ekf.guard import TrustGuard
from gpumap.ekf.initialisation import anchor_jacobian
from gpumap.ekf.measurement import (
    _linearize,
    wrap_angle,
)
from gpumap.ekf.motion import _inject_gauge, _renormalized, motion_jacobian
from gpumap.ekf.plane import PlaneUpdateResult, fuse_plane_ranges
from gpumap.ekf.state import EKFState, InnovationStats, UpdateResult, _blas_limited, _nis_band
from gpumap.ekf.update import (
    _apply,
    _elevation_var_given_pose,
    _hp,
    _iterate,
    _nis_2x2,
    _Returns,
    _s_blocks,
)
from gpumap.errors import check_finite_scalar, check_pose
from gpumap.lie import orthonormalize

__all__ = ["InnovationStats", "PlaneUpdateResult", "SonarEKF", "UpdateResult"]

_log = logging.getLogger("gpumap.ekf")


class SonarEKF(EKFState):
    """Joint EKF over the sonar pose and point features seen as (range, azimuth).

    Features are stored as anchored spherical coordinates ``s = (r, az, el)`` in the sonar
    frame where they were first seen (the anchor, a fixed transform equal to the pose
    estimate at that moment), so the elevation arc of a first return is a straight line in
    the state and its uniform prior is represented without the chord error of a Cartesian
    Gaussian. The anchor's pose uncertainty is carried by the feature's covariance and its
    cross-covariance with the pose (:func:`anchor_jacobian`). Everything the class returns
    (:attr:`landmarks`, :meth:`landmark_cov`, :attr:`covariance`) is in world Cartesian
    coordinates; :attr:`native_covariance` is the filter's own.

    Parameters
    ----------
    T_W_S0 : (4, 4) float
        Initial sonar pose (world from sonar).
    pose_cov0 : (6, 6) float
        Initial pose covariance over ``(translation m, rotation vector rad)``, right perturbation.
    range_sigma_m : float
        Standard deviation of a range measurement, metres (> 0).
    bearing_sigma_rad : float
        Standard deviation of an azimuth measurement, radians (> 0).
    vfov_rad : float
        Full vertical aperture, radians, in ``(0, pi)``. A new feature's elevation is taken
        uniform over ``[-vfov/2, vfov/2]``: mean 0, variance ``vfov^2 / 12``.
    gate_prob : float or None, default 0.999
        Chi-square (2 dof) gate probability for each return; None disables gating.
    iterations : int, default 1
        Most Gauss-Newton passes of each update (iterated EKF); 1 is the plain EKF. Passes
        stop early once the correction stops changing.
    mature_elevation_sigma_rad : float or None, default None
        If given, returns of features whose anchored elevation, conditioned on the pose, has
        a standard deviation above this correct only their own feature (Schmidt update).
    init : {"arc", "triangulate"}, default "arc"
        Where the updates of a feature whose elevation is still uncertain (standard deviation
        above ``init_elevation_sigma_rad``) are linearised. Both fuse every return from the
        first re-observation on, so the pose-feature cross-covariances are the same.
        ``"arc"``: Gauss-Newton from the filter's estimate (elevation 0 at first).
        ``"triangulate"``: each such return first triangulates the feature along its
        elevation arc: Gauss-Newton from ``init_starts`` elevations spread over the
        aperture and from the estimate, each on that return with the filter's prior (all
        cross-covariances included); the start with the lowest MAP cost is where the joint
        update starts (Gauss-Newton cannot leave the stationary point at elevation 0 that
        the arc's symmetry makes, a scan can).
    init_elevation_sigma_rad : float or None, default None
        Elevation standard deviation (given the pose) above which a feature counts as
        uncertain: its returns are relinearised (``relinearize_iterations``) and gated at the
        relinearised estimate. None gives half the prior's, ``vfov / (2 sqrt(12))``.
    relinearize_iterations : int, default 5
        Most Gauss-Newton passes of an update that holds a return of an uncertain feature
        (the larger of this and ``iterations``); such a return that fails the gate at the
        prior's linearisation is tested again at its own relinearised estimate. 1 turns
        both off.
    init_starts : int, default 5
        ``init="triangulate"``: elevations of the scan, evenly over 80 % of the aperture.
    second_order : bool, default True
        Gaussian second-order terms in the elevation direction: the predicted
        ``(range, azimuth)`` get ``h_ee var_e / 2`` and ``R`` gets ``h_ee h_ee^T var_e^2 / 2``,
        where ``h_ee`` is the second derivative in the anchored elevation and ``var_e`` its
        variance given the pose (at most the aperture prior's). Linearised at elevation 0 a
        range has no first-order sensitivity to elevation; without this term the chord
        effect ``r (1 - cos el)`` of a point off the horizontal plane is absorbed as a range
        bias. It vanishes as the elevation is learned.
    nis_window : int, default 200
        Returns over which :meth:`innovation_stats` pools the NIS and the innovations; once
        the window is full, an update whose pooled NIS per dof falls outside the two-sided
        99.99 % chi-square band warns once (``RuntimeWarning``; also logged at INFO on
        ``gpumap.ekf``) with the noise the innovations suggest. 0 turns the monitor off.
    adapt_noise : bool, default False
        When the monitor finds the covariance overconfident, raise ``range_sigma_m`` and
        ``bearing_sigma_rad`` to the innovations' estimates (never lower them), say so in the
        warning, and start a new window (it may raise them again). Off by default: an
        estimator that rewrites its own noise needs the user's consent; on real data whose
        noise was never measured it is the honest choice.
    guard : TrustGuard or None, default None
        Innovation-consistency guard (:mod:`gpumap.ekf.guard`): each update asks it whether
        the returns may correct the pose; while it says no, accepted returns are fused as
        Schmidt updates of their own feature only (the pose and its covariance keep the
        odometry's increment exactly), and every update's innovations are fed to it. None:
        every update corrects the pose (the plain EKF).
    blas_threads : int or None, default 1
        BLAS threads used inside ``predict`` and the updates (through threadpoolctl, set and
        restored around each call, about 10 µs). The filter's matrices are small and dense:
        on a loaded 2-core computer OpenBLAS's own threads made a 32-feature update 15 ms
        instead of 1 ms (``bench/``). None leaves BLAS as the process has it.

    Examples
    --------
    >>> ekf = SonarEKF(np.eye(4), np.zeros((6, 6)), range_sigma_m=0.01,
    ...                bearing_sigma_rad=0.005, vfov_rad=np.deg2rad(14))
    >>> ekf.predict(T_Sprev_Snext, motion_cov)          # doctest: +SKIP
    >>> res = ekf.update(ids, ranges_m, bearings_rad)    # doctest: +SKIP
    """

    def __init__(
        self,
        T_W_S0: np.ndarray,
        pose_cov0: np.ndarray,
        *,
        range_sigma_m: float,
        bearing_sigma_rad: float,
        vfov_rad: float,
        gate_prob: float | None = 0.999,
        iterations: int = 1,
        mature_elevation_sigma_rad: float | None = None,
        init: str = "arc",
        init_elevation_sigma_rad: float | None = None,
        relinearize_iterations: int = 5,
        init_starts: int = 5,
        second_order: bool = True,
        nis_window: int = 200,
        adapt_noise: bool = False,
        guard: TrustGuard | None = None,
        blas_threads: int | None = 1,
    ) -> None:
        if guard is not None and not isinstance(guard, TrustGuard):
            raise TypeError(f"Expected a TrustGuard or None for 'guard', but got {type(guard).__name__}")
        self.guard = guard
        if blas_threads is not None and (isinstance(blas_threads, bool) or int(blas_threads) < 1):
            raise ValueError(f"Expected blas_threads >= 1 or None, but got {blas_threads!r}")
        self._blas_threads = None if blas_threads is None else int(blas_threads)
        T = check_pose(T_W_S0, "T_W_S0")
        P0 = _check_cov(pose_cov0, 6, "pose_cov0")
        sr = check_finite_scalar(range_sigma_m, "range_sigma_m")
        sb = check_finite_scalar(bearing_sigma_rad, "bearing_sigma_rad")
        vf = check_finite_scalar(vfov_rad, "vfov_rad")
        if sr <= 0 or sb <= 0:
            raise ValueError(
                f"Expected range_sigma_m > 0 and bearing_sigma_rad > 0, but got {sr} and {sb}"
            )
        if not 0 < vf < math.pi:
            raise ValueError(f"Expected 0 < vfov_rad < pi, but got {vf}")
        if gate_prob is not None:
            gp = check_finite_scalar(gate_prob, "gate_prob")
            if not 0 < gp < 1:
                raise ValueError(f"Expected 0 < gate_prob < 1 (or None), but got {gp}")
            self._gate = _chi2_2dof(gp)
            self._gate1 = _chi2_quantile(gp, 1)
        else:
            self._gate = self._gate1 = math.inf
        if isinstance(iterations, bool) or not isinstance(iterations, (int, np.integer)) or iterations < 1:
            raise ValueError(f"Expected an integer iterations >= 1, but got {iterations!r}")
        self.iterations = int(iterations)
        if mature_elevation_sigma_rad is not None:
            me = check_finite_scalar(mature_elevation_sigma_rad, "mature_elevation_sigma_rad")
            if me <= 0:
                raise ValueError(f"Expected mature_elevation_sigma_rad > 0 (or None), but got {me}")
            mature_elevation_sigma_rad = me
        self.mature_elevation_sigma_rad = mature_elevation_sigma_rad
        if init not in ("arc", "triangulate"):
            raise ValueError(f"Expected init 'arc' or 'triangulate', but got {init!r}")
        self.init = init
        if init_elevation_sigma_rad is None:
            init_elevation_sigma_rad = 0.5 * vf / math.sqrt(12.0)
        ie = check_finite_scalar(init_elevation_sigma_rad, "init_elevation_sigma_rad")
        if ie <= 0:
            raise ValueError(f"Expected init_elevation_sigma_rad > 0, but got {ie}")
        self.init_elevation_sigma_rad = ie
        for name, v, lo in (("relinearize_iterations", relinearize_iterations, 1),
                            ("init_starts", init_starts, 1), ("nis_window", nis_window, 0)):
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < lo:
                raise ValueError(f"Expected an integer {name} >= {lo}, but got {v!r}")
        self.relinearize_iterations = int(relinearize_iterations)
        self.init_starts = int(init_starts)
        self.second_order = bool(second_order)
        self.nis_window = int(nis_window)
        self.adapt_noise = bool(adapt_noise)
        self.range_sigma_m = sr
        self.bearing_sigma_rad = sb
        self.vfov_rad = vf
        self.elevation_var_rad2 = vf * vf / 12.0
        T[:3, :3] = orthonormalize(T[:3, :3])
        # The filter runs in the frame of the first pose estimate, G = T_W_S0 (the gauge):
        # inside, the pose starts at the identity, exactly known, and pose_cov0 is the
        # uncertainty of G, the last 6 states. Nothing relative observes G, so a huge
        # pose_cov0 stays huge instead of passing through the features' anchors.
        self._G = T
        self._T = np.eye(4)
        # With pose_cov0 = 0 the gauge is exact and its states are left out (_ng = 0).
        self._ng = 6 if np.any(P0) else 0
        self._P = np.zeros((6 + self._ng, 6 + self._ng))
        self._P[6:, 6:] = P0[: self._ng, : self._ng]
        self._S = np.zeros((0, 3))  # anchored spherical coordinates (r, az, el)
        self._Ra = np.zeros((0, 3, 3))  # anchor rotations R_L_A (L: the gauge's frame)
        self._ta = np.zeros((0, 3))  # anchor positions t_L_A
        self._ids: list[int] = []
        self._index: dict[int, int] = {}
        self._nis: float | None = None
        self._nis_dof = 0
        # Innovation monitor: per fused update (returns, NIS, sum nu nu^T, sum S) over the
        # last nis_window returns, their running sum; _nis_warned avoids repeating the warning.
        self._innov: collections.deque = collections.deque()
        self._isum = np.zeros(10)
        self._nis_warned = False

    @_blas_limited
    def predict(self, T_Sprev_Snext: np.ndarray, motion_cov: np.ndarray) -> None:
        """Move the pose by a relative motion measured in the previous sonar frame.

        Parameters
        ----------
        T_Sprev_Snext : (4, 4) float
            Odometry increment ``U``: ``T_W_Snext = T_W_Sprev @ U``.
        motion_cov : (6, 6) float
            Covariance of ``w`` in ``U_true = U @ Exp(w)``, ``(translation m, rotation vector rad)``.
        """
        U = check_pose(T_Sprev_Snext, "T_Sprev_Snext")
        Q = _check_cov(motion_cov, 6, "motion_cov")
        U = _renormalized(U)
        F = motion_jacobian(U)
        P = self._P.copy()
        P[:6, :] = F @ P[:6, :]
        P[:, :6] = P[:, :6] @ F.T
        P[:6, :6] += Q
        P = 0.5 * (P + P.T)
        T = _renormalized(self._T @ U)
        if not (np.all(np.isfinite(P)) and np.all(np.isfinite(T))):
            raise FloatingPointError("predict produced non-finite values; the filter is unchanged")
        self._T, self._P = T, P

    @_blas_limited
    def update(
        self, ids: Iterable[int] | np.ndarray, ranges_m: np.ndarray, bearings_rad: np.ndarray,
        covs: np.ndarray | None = None, track_hits: np.ndarray | None = None,
    ) -> UpdateResult:
        """Fuse one ping's feature returns; add features seen for the first time.

        Known features are gated one by one (chi-square, 2 dof, on each return's own
        innovation covariance), then the accepted ones are fused jointly. New features are
        then initialised from the updated pose. On any error the filter is left unchanged.

        Parameters
        ----------
        ids : (m,) int
            Feature ids (known correspondences), each at most once.
        ranges_m : (m,) float
            Measured ranges, metres, > 0.
        bearings_rad : (m,) float
            Measured azimuths ``atan2(y, x)`` in the sonar frame, radians (any branch).
        covs : (m, 2, 2) float, optional
            Each return's own covariance of ``(range m, azimuth rad)`` (e.g. from
            :class:`gpumap.ekf.frontend.PointDetector`); default: ``diag(range_sigma_m^2,
            bearing_sigma_rad^2)`` for every return.
        track_hits : (m,) int, optional
            Each return's track length so far, for the guard's ``min_track_hits``.

        Returns
        -------
        UpdateResult
        """
        id_list = _check_ids(ids)
        m = len(id_list)
        rng_m = _check_vector(ranges_m, m, "ranges_m")
        brg = _check_vector(bearings_rad, m, "bearings_rad")
        if np.any(rng_m <= 0):
            raise ValueError(f"Expected ranges_m > 0, but got minimum {float(rng_m.min())}")
        if covs is not None:
            covs = _real_array(covs, "covs")
            if covs.shape != (m, 2, 2):
                raise ValueError(f"Expected shape ({m}, 2, 2) for 'covs', but got {covs.shape}")
            covs = np.stack([_check_cov(c, 2, "covs") for c in covs]) if m else covs.reshape(0, 2, 2)
            if m and not np.all(np.linalg.eigvalsh(covs)[:, 0] > 0):
                raise ValueError("Expected positive definite 2x2 blocks in 'covs', but got a singular one")

        known = [k for k in range(m) if id_list[k] in self._index]
        new = [k for k in range(m) if id_list[k] not in self._index]
        T, P, S, G = self._T, self._P, self._S, self._G
        accepted: list[int] = []
        rejected: dict[int, float] = {}
        degenerate: list[int] = []
        nis: float | None = None
        innov = None

        pose_ok = self.guard is None or self.guard.trusted
        guard_feed = None
        if known:
            slots = np.array([self._index[id_list[k]] for k in known])
            meas = np.stack([rng_m[known], brg[known]], axis=1)
            Ra, ta = self._Ra[slots], self._ta[slots]
            # How loose each elevation is relative to the current pose (what the returns see;
            # a common pose offset is not), at most the aperture prior's. The second-order term
            # is left out where even a generous bound on it (|h_ee| <= 10 r_A for the range,
            # 10 for the azimuth) stays under 1 % of the noise; the conditional variance, below
            # the marginal one, is only needed where the marginal one is above both thresholds.
            ve = P[6 + 3 * slots + 2, 6 + 3 * slots + 2]
            small2 = 2e-3 * np.minimum(self.range_sigma_m / S[slots, 0], self.bearing_sigma_rad)
            if np.any(ve > np.minimum(small2, self.init_elevation_sigma_rad**2)):
                ve = np.minimum(_elevation_var_given_pose(P, slots), self.elevation_var_rad2)
            ve2 = np.where(ve > small2, ve, 0.0) if self.second_order else 0.0 * ve
            nu, Hp, Hs, ok, hee = _linearize(T, S[slots], Ra, ta, meas, bool(np.any(ve2)))
            degenerate = [id_list[known[j]] for j in np.flatnonzero(~ok)]
            sel = np.flatnonzero(ok)
            if degenerate:
                nu, Hp, Hs, hee, slots = nu[sel], Hp[sel], Hs[sel], hee[sel], slots[sel]
                meas, Ra, ta, ve, ve2 = meas[sel], Ra[sel], ta[sel], ve[sel], ve2[sel]
            e = 6 + 3 * slots + 2
            uncertain = ve > self.init_elevation_sigma_rad**2
            r_var = np.array([self.range_sigma_m**2, self.bearing_sigma_rad**2])
            if covs is not None:
                r_var = covs[known][sel] if degenerate else covs[known]
            ret = _Returns(S[slots], Ra, ta, slots, meas, r_var, ve2)
            nu_e, Rb = ret.terms(nu, hee)
            # Per-return gate on the 2x2 marginal innovation covariance. A return of a feature
            # whose elevation is uncertain is also solved on its own by Gauss-Newton (from
            # several elevations with init="triangulate"): if it failed at the prior's
            # linearisation it is judged again by the NIS there (the arc's curvature, not the
            # return, may be what failed), and the best start seeds the joint update.
            HP = _hp(P, Hp, Hs, slots)  # (k, 2, N)
            Sb = _s_blocks(HP, Hp, Hs, slots) + Rb
            d2 = _nis_2x2(Sb, nu_e)
            passes = max(self.iterations, self.relinearize_iterations)
            shift = np.zeros(len(slots))
            if passes > 1:
                scan = self.init == "triangulate"
                for j in np.flatnonzero(uncertain & (scan | ~(d2 <= self._gate))):
                    js = np.array([j])
                    lin = (nu[js], Hp[js], Hs[js], hee[js])
                    best = _iterate(T, P, ret.take(js), lin, passes)[3], 0.0
                    if scan:
                        for el in np.linspace(-0.4, 0.4, self.init_starts) * self.vfov_rad:
                            dx0 = np.zeros(P.shape[0])
                            dx0[e[j]] = el - S[slots[j], 2]
                            c = _iterate(T, P, ret.take(js), lin, passes, dx0=dx0)[3]
                            if c < best[0]:
                                best = c, dx0[e[j]]
                    if not d2[j] <= self._gate:
                        d2[j] = best[0]
                    shift[j] = best[1]
            keep = np.flatnonzero(d2 <= self._gate)
            if self.guard is not None:
                th = None if track_hits is None else np.asarray(track_hits)[np.asarray(known)[sel[keep]]]
                guard_feed = (d2[keep], nu_e[keep], Sb[keep], int(len(slots) - keep.size), pose_ok, th)
            for j in np.flatnonzero(~(d2 <= self._gate)):
                rejected[id_list[known[sel[j]]]] = float(d2[j])
            if keep.size:
                kk = keep
                own = None
                if self.mature_elevation_sigma_rad is not None:
                    own = _elevation_var_given_pose(P, slots[kk]) > self.mature_elevation_sigma_rad**2
                if not pose_ok:  # the guard does not trust the pings: features only
                    own = np.ones(kk.size, bool)
                dx0 = None
                if np.any(shift[kk]):
                    dx0 = np.zeros(P.shape[0])
                    dx0[e[kk]] = shift[kk]
                if kk.size == len(slots):  # all gated in: reuse the gate's products
                    sub, lin, pre = ret, (nu, Hp, Hs, hee), (nu_e, Rb, HP)
                else:
                    sub, lin, pre = ret.take(kk), (nu[kk], Hp[kk], Hs[kk], hee[kk]), None
                dx, g, _, nis = _iterate(T, P, sub, lin, passes if np.any(uncertain[kk])
                                         else self.iterations, own, dx0, pre)
                T, P = _apply(T, P, dx, g)
                if self._ng:
                    G, P = _inject_gauge(G, P, dx[-6:])
                S = S + dx[6 : P.shape[0] - self._ng].reshape(-1, 3)
                S[:, 1] = wrap_angle(S[:, 1])
                accepted = [id_list[known[sel[j]]] for j in keep]
                if self.nis_window:
                    innov = np.concatenate([[len(kk), nis], (nu_e[kk].T @ nu_e[kk]).ravel(),
                                            Sb[kk].sum(axis=0).ravel()])

        new_ids: list[int] = []
        index = dict(self._index)
        ids_order = list(self._ids)
        Ra, ta = self._Ra, self._ta
        Nz = np.diag([self.range_sigma_m**2, self.bearing_sigma_rad**2, self.elevation_var_rad2])
        inits = [(k, np.array([rng_m[k], float(wrap_angle(brg[k])), 0.0]), Nz if covs is None else
                  np.block([[covs[k], np.zeros((2, 1))], [np.zeros((1, 2)), Nz[2:, 2:]]])) for k in new]
        if inits:
            Nn = P.shape[0]
            n_new = len(inits)
            Pn = np.zeros((Nn + 3 * n_new, Nn + 3 * n_new))
            Pn[:Nn, :Nn] = P
            s_new = np.zeros((n_new, 3))
            for q, (k, s_k, N_k) in enumerate(inits):
                s_new[q] = s_k
                A = anchor_jacobian(s_new[q])
                c = Nn + 3 * q
                cross = A @ Pn[:6, :c]  # (3, c): correlated through the anchor pose only
                Pn[c : c + 3, :c] = cross
                Pn[:c, c : c + 3] = cross.T
                Pn[c : c + 3, c : c + 3] = A @ Pn[:6, :6] @ A.T + N_k
                index[id_list[k]] = len(ids_order)
                ids_order.append(id_list[k])
                new_ids.append(id_list[k])
            S = np.concatenate([S, s_new], axis=0)
            Ra = np.concatenate([Ra, np.broadcast_to(T[:3, :3], (n_new, 3, 3))], axis=0)
            ta = np.concatenate([ta, np.broadcast_to(T[:3, 3], (n_new, 3))], axis=0)
            # The new features went after the gauge's 6 states: move those back to the end.
            g = self._ng
            order = np.r_[0 : Nn - g, Nn : Nn + 3 * n_new, Nn - g : Nn]
            Pn = Pn[np.ix_(order, order)]
            P = 0.5 * (Pn + Pn.T)

        if not (np.all(np.isfinite(P)) and np.all(np.isfinite(T)) and np.all(np.isfinite(S))
                and np.all(np.isfinite(G))):
            raise FloatingPointError("update produced non-finite values; the filter is unchanged")
        self._T, self._P, self._S, self._Ra, self._ta, self._G = T, P, S, Ra, ta, G
        self._index, self._ids = index, ids_order
        if accepted:
            self._nis, self._nis_dof = nis, 2 * len(accepted)
            self._monitor(innov)
        if guard_feed is not None:
            g_nis, g_nu, g_S, g_gated, g_pose, g_hits = guard_feed
            self.guard.add(g_nis, g_nu, g_S, gated=g_gated, pose_corrected=g_pose, track_hits=g_hits)
        return UpdateResult(
            accepted_ids=tuple(accepted),
            rejected=rejected,
            initialized_ids=tuple(new_ids),
            degenerate_ids=tuple(degenerate),
            nis=nis if accepted else None,
        )

    @_blas_limited
    def update_plane_ranges(
        self,
        origins_S: np.ndarray,
        directions_S: np.ndarray,
        ranges_m: np.ndarray,
        plane_n_W: np.ndarray,
        plane_d_m: float,
        range_sigma_m: float,
    ) -> PlaneUpdateResult:
        """Fuse ranges measured along known rays to a known world plane (e.g. DVL beams to the floor).

        Ray ``i`` starts at ``T_W_S @ origins_S[i]`` and runs along ``R_W_S @ directions_S[i]``;
        its range is where it meets the plane ``n . p = d`` (:func:`plane_range_model`). For a
        DVL on the same rigid body, pass its beams through the fixed mount: origins
        ``T_S_D[:3, 3]`` and directions ``T_S_D[:3, :3] @ beam_D``. Such ranges observe the
        sonar's height above the plane and its tilt relative to it (pitch and roll for a level
        floor), never the position along the plane or the rotation about its normal.

        NaN ranges are skipped; rays (nearly) parallel to the plane, or hitting it behind their
        origin, are reported degenerate; each other ray is gated on its own innovation
        variance (chi-square, 1 dof, at the filter's ``gate_prob``), then the accepted rays are
        fused jointly (one linearisation, Cholesky gain, Joseph form). The features move with
        the pose through their correlations. On any error the filter is left unchanged.

        Parameters
        ----------
        origins_S : (m, 3) float
            Ray origins in the sonar frame, metres.
        directions_S : (m, 3) float
            Unit ray directions in the sonar frame.
        ranges_m : (m,) float
            Measured ranges along each ray, metres, > 0; NaN = no return (skipped).
        plane_n_W : (3,) float
            Plane normal in the world (normalised here; ``plane_d_m`` is scaled with it).
        plane_d_m : float
            Plane offset, ``n . p = d``; for a floor at height ``z0``: ``n = (0, 0, 1)``, ``d = z0``.
        range_sigma_m : float
            Standard deviation of each range, metres (> 0): sensor noise plus the plane's
            roughness seen along the ray.

        Returns
        -------
        PlaneUpdateResult
        """
        state, res = fuse_plane_ranges(
            self._T, self._P, self._S, self._G, self._ng, self.pose, self._pose_rows(), self._gate1,
            origins_S, directions_S, ranges_m, plane_n_W, plane_d_m, range_sigma_m,
        )
        if state is not None:
            self._T, self._P, self._S, self._G = state
        return res

    def innovation_stats(self) -> InnovationStats | None:
        """NIS and measurement noise estimated from the last ``nis_window`` fused returns.

        Returns None before any return was fused (or with ``nis_window=0``). See
        :class:`InnovationStats`.
        """
        if not self._innov:
            return None
        v = np.sum(self._innov, axis=0)  # (n, nis, sum nu nu^T (4), sum S (4))
        n = v[0]
        NN, SS = v[2:6].reshape(2, 2) / n, v[6:10].reshape(2, 2) / n
        dof = int(round(2 * n))
        lo, hi = _nis_band(dof)
        r_var = np.array([self.range_sigma_m**2, self.bearing_sigma_rad**2])
        # Mehra: E[nu nu^T] = H P H^T + R, so R ~ mean(nu nu^T) - mean(H P H^T).
        R_hat = np.maximum(np.diag(NN) - (np.diag(SS) - r_var), 0.0)
        return InnovationStats(
            returns=int(round(n)), nis_per_dof=float(v[1] / dof), band=(lo, hi),
            range_nis=float(NN[0, 0] / SS[0, 0]), bearing_nis=float(NN[1, 1] / SS[1, 1]),
            range_sigma_m=float(math.sqrt(R_hat[0])), bearing_sigma_rad=float(math.sqrt(R_hat[1])))

    def _monitor(self, innov: np.ndarray | None) -> None:
        """Add an update's innovations to the window; warn once when the NIS leaves its band."""
        if innov is None or self.nis_window == 0:
            return
        self._innov.append(innov)
        self._isum = self._isum + innov
        while self._isum[0] - self._innov[0][0] >= self.nis_window:
            self._isum = self._isum - self._innov.popleft()
        if self._isum[0] < self.nis_window:
            return
        dof = int(round(2 * self._isum[0]))
        lo, hi = _nis_band(dof)
        if lo <= self._isum[1] / dof <= hi:
            self._nis_warned = False
            return
        if self._nis_warned:
            return
        self._nis_warned = True
        st = self.innovation_stats()
        msg = (f"SonarEKF: NIS per dof over the last {st.returns} returns is {st.nis_per_dof:.2f}, "
               f"outside the 99.99 % band [{lo:.2f}, {hi:.2f}] of a filter whose noise is right: "
               f"its covariance is {'overconfident' if st.nis_per_dof > hi else 'too loose'}. "
               f"Configured range_sigma_m={self.range_sigma_m:.4g}, bearing_sigma_rad="
               f"{self.bearing_sigma_rad:.4g}; the innovations suggest {st.range_sigma_m:.4g} m and "
               f"{st.bearing_sigma_rad:.4g} rad (innovation_stats()).")
        if self.adapt_noise and st.nis_per_dof > hi:
            self.range_sigma_m = max(self.range_sigma_m, st.range_sigma_m)
            self.bearing_sigma_rad = max(self.bearing_sigma_rad, st.bearing_sigma_rad)
            self._innov.clear()
            self._isum = np.zeros(10)
            self._nis_warned = False
            msg += (f" adapt_noise: now range_sigma_m={self.range_sigma_m:.4g}, "
                    f"bearing_sigma_rad={self.bearing_sigma_rad:.4g}.")
        _log.info(msg)
        warnings.warn(msg, RuntimeWarning, stacklevel=4)
