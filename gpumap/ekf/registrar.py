"""The scan registrar of a replay (:class:`ScanRegistrar`): scans registered against the map, revisits
verified by their images, fused into the filter; the registration itself is :mod:`gpumap.ekf.registration`.
"""

from __future__ import annotations

import collections

import numpy as np

from gpumap.ekf.guard import nis_band
from gpumap.ekf.registration import (
    IN_PLANE,
    PLACE_BEAM_STRIDE,
    REGISTER_DEFAULTS,
    RegistrarStats,
    ScanRegistration,
    _scores,
    fuse_revisit,
    fuse_step,
    image_agreement,
    image_descriptor,
    marginal,
    plane_points,
    register_scan,
)
from gpumap.lie import se3_adjoint, se3_exp, se3_inverse

__all__ = ["ScanRegistrar"]


class ScanRegistrar:
    """The local map, the stored pings and the registration steps of the EKF loop.

    Per ping ``k`` (:func:`gpumap.ekf.loop.run_ekf_loop`): :meth:`correct_step` before the
    prediction (returns the step to predict with), :meth:`remember` after the update (adds the
    ping's returns at the filter's pose).

    Two measurements, each optional:

    - ``step``: the ping registered against the local map of the last ``keep`` pings
      (:func:`register_scan`, :func:`fuse_step`), guarded by the NIS window;
    - ``revisit``: the ping's first returns compared with every stored ping at least
      ``min_gap`` pings older (:func:`place_scores`); of those under ``place_threshold``, the
      one whose image agrees best (:func:`image_agreement`) is a revisit when that agreement
      reaches ``min_image_ncc`` (module docstring; ``min_image_ncc`` None: the best first-return
      match, unverified, as first built): the in-plane offset from it by :func:`register_scan`
      (from its pose), the other components 0 with ``revisit_sigma`` (m, rad), fused by
      :func:`fuse_revisit` against the drift since then (the registrar tracks its own pose
      covariance). Each verified revisit is also kept in :attr:`closures` (a pose graph's loop
      edge, :mod:`gpumap.ekf.posegraph`).

    Parameters
    ----------
    spec : SonarSpec
    threshold : float
        First-return intensity threshold.
    keep, window : int
        Pings in the local map; registrations in the NIS window (two-sided band ``prob``).
    gate_prob : float
        Per-measurement chi-square gate.
    two_sided : bool
        Whether a window whose NIS is below its band is distrusted too (:attr:`trusted`).
    ranges : (n, n_beams) float, optional
        Precomputed first returns per ping (else measured from each image).
    descriptors : (n, m) float, optional
        Precomputed :func:`image_descriptor` per ping (else computed from each image).
    step, revisit : bool
        Which measurements to use. Default: revisits only. On the full real tank run the step
        registration alone was worse than odometry on some seeds of frames 0-799 (up to 1.27x
        position) while the revisits alone never were; with both, the mean was lower on frames
        0-799 but the held-out frames 800-1222 (which hold no revisit) reached 1.33x on one seed
        (``bench/results/ekf_registration.json``).
    min_gap, place_threshold, revisit_sigma
        The revisit's search (pings older than ``min_gap``, :func:`place_scores` below
        ``place_threshold`` metres) and the noise of its offset besides the registration's
        own (``(metres, radians)``, per axis).
    graph : bool
        Keep a pose graph (:class:`gpumap.ekf.posegraph.PoseGraph`) of the odometry steps as
        given and the verified revisits, solved when a burst of revisits ends (or every
        ``solve_every`` of them); the ping of a solve is predicted onto the graph's pose of it
        (:meth:`correct_step` returns the step that lands there), so the filter carries on
        from what every revisit so far says together, not only from its own last correction.
        On by default: on frames 0-799 of the full real tank run (5 seeds, drifts 0.005 and
        0.02) it lowered the mean position error over odometry's from 0.59 / 0.61 to 0.51 / 0.52
        and the worst seed's heading from 0.84 / 0.82 to 0.66 / 0.68 (``bench/ekf_pose.py``).
    solve_every : int
        See ``graph``.
    min_image_ncc : float or None
        The revisit's verification (:func:`image_agreement` of the best-agreeing candidate must
        reach it); None: none, the best first-return match is taken (as first built). The
        default, 0.97 with ``place_threshold`` 0.04, was chosen on frames 0-799 of the full real
        tank run (``bench/ekf_pose.py``): from 0.96 to 0.98 no seed of drifts 0.005 and 0.02
        ended worse than odometry in position or heading; at 0.95 the heading did.
    step_components : tuple of int
        Which of the in-plane components ``(0, 1, 5)`` (``rho_x, rho_y, phi_z``) the step
        registration corrects (the others marginalised out, :func:`marginal`).
    step_floor : (float, float)
        Standard deviation (metres, radians per axis) added to each step registration's own
        (:func:`fuse_step`'s ``floor``).
    **register_kw
        Passed to :func:`register_scan` (over :data:`REGISTER_DEFAULTS`).
    """

    def __init__(self, spec, *, threshold: float = 0.4, keep: int = 1, window: int = 20,
                 prob: float = 0.999, gate_prob: float = 0.999, ranges: np.ndarray | None = None,
                 step: bool = False, revisit: bool = True, min_gap: int = 30,
                 place_threshold: float = 0.04, revisit_sigma: tuple[float, float] = (0.005, 0.03),
                 step_floor: tuple[float, float] = (0.0, 0.0), step_components: tuple[int, ...] = IN_PLANE,
                 two_sided: bool = False, descriptors: np.ndarray | None = None,
                 min_image_ncc: float | None = 0.97, graph: bool = True, solve_every: int = 10,
                 **register_kw) -> None:
        from scipy.stats import chi2

        if keep < 1 or window < 1 or min_gap < 1:
            raise ValueError(f"Expected keep, window and min_gap >= 1, but got {keep}, {window}, {min_gap}")
        self.spec = spec
        self.threshold = float(threshold)
        self.keep = int(keep)
        self.window = int(window)
        self.prob = float(prob)
        self.two_sided = bool(two_sided)
        self._gate = {m: float(chi2.ppf(gate_prob, m)) for m in range(1, 7)}
        self.ranges = None if ranges is None else np.asarray(ranges, np.float64)
        self.descriptors = None if descriptors is None else np.asarray(descriptors, np.float32)
        if min_image_ncc is not None and not -1.0 <= float(min_image_ncc) <= 1.0:
            raise ValueError(f"Expected min_image_ncc in [-1, 1] or None, but got {min_image_ncc}")
        self.min_image_ncc = None if min_image_ncc is None else float(min_image_ncc)
        self._db_desc: np.ndarray | None = None  # (capacity, m) image descriptors of the stored pings
        self._desc: np.ndarray | None = None
        #: Verified revisits ``(k, j, delta (6,), R (6, 6), fused)``: ping ``k`` was taken at
        #: ``T_j Exp(delta)`` with noise ``R``; ``fused``: whether the filter took it (its NIS gate).
        self.closures: list = []
        self.graph = bool(graph)
        self.solve_every = int(solve_every)
        self._graph = None  # PoseGraph, made at the first ping
        self._pending = 0
        self.solves = 0
        self.step, self.revisit = bool(step), bool(revisit)
        self.min_gap = int(min_gap)
        self.place_threshold = float(place_threshold)
        self.revisit_sigma = (float(revisit_sigma[0]), float(revisit_sigma[1]))
        if not set(step_components) <= set(IN_PLANE) or not step_components:
            raise ValueError(f"Expected step_components among {IN_PLANE}, but got {step_components}")
        self.step_components = tuple(int(i) for i in step_components)
        self.step_floor = np.diag([float(step_floor[0]) ** 2] * 3 + [float(step_floor[1]) ** 2] * 3)
        self.register_kw = {**REGISTER_DEFAULTS, **register_kw}
        self._map: collections.deque = collections.deque(maxlen=self.keep)
        self._win: collections.deque = collections.deque(maxlen=self.window)
        self._db_r: list = []  # per stored ping: first returns, pose, registrar covariance, points
        self._db_T: list = []
        self._db_sigma: list = []
        self._db_pts: list = []
        nb = len(range(0, spec.n_beams, PLACE_BEAM_STRIDE))
        self._db_val = np.zeros((0, nb), np.float32)  # first returns of every 4th beam, 0 where none
        self._db_ok = np.zeros((0, nb), bool)
        self._sigma = np.zeros((6, 6))
        self.stats = RegistrarStats()
        self.last: ScanRegistration | None = None
        self.last_revisit: int | None = None

    def _returns(self, k: int, image) -> np.ndarray:
        from gpumap.layers.first_return import measured_first_returns

        if self.ranges is not None:
            return self.ranges[k]
        return measured_first_returns(image, self.spec, self.threshold)

    @property
    def trusted(self) -> bool:
        """Whether the window's NIS per dof is inside its band (True while the window fills);
        with ``two_sided`` False only above it counts (a registration noisier than it says;
        below, it is only weighted less than it could be)."""
        if len(self._win) < self.window:
            return True
        nis = sum(a for a, _ in self._win)
        dof = sum(b for _, b in self._win)
        lo, hi = nis_band(self.prob, int(dof))
        return (lo <= nis / dof or not self.two_sided) and nis / dof <= hi

    def _step(self, T_prev, U, Q):
        map_W = np.concatenate([p @ T[:3, :3].T + T[:3, 3] for T, p in self._map])
        reg = register_scan(self._pts, map_W, T_prev @ U, vfov_rad=self.spec.vfov_rad, **self.register_kw)
        if reg is not None and self.step_components != IN_PLANE:
            reg = marginal(reg, self.step_components)
        if reg is None or reg.observed == 0:
            return U, Q
        self.stats.registered += 1
        self.last = reg
        trusted = self.trusted
        Un, Qn, nis, fused = fuse_step(U, Q, reg, self._gate[reg.observed], self.step_floor)
        if nis is not None:
            self._win.append((nis, reg.observed))
            self.stats.nis.append(nis / reg.observed)
        if not fused:
            self.stats.gated += 1
            return U, Q
        if not trusted:
            self.stats.distrusted += 1
            return U, Q
        self.stats.fused += 1
        return Un, Qn

    def _match(self, n_old: int) -> int | None:
        """The stored ping (index) the current one revisits, or None (class docstring)."""
        sc = _scores(self._r[::PLACE_BEAM_STRIDE], self._db_val[:n_old], self._db_ok[:n_old])
        if self.min_image_ncc is None:
            j = int(np.argmin(sc))
            return j if sc[j] < self.place_threshold else None
        cand = np.flatnonzero(sc < self.place_threshold)
        if not len(cand):
            return None
        agree = image_agreement(self._desc, self._db_desc[cand])
        i = int(np.argmax(agree))
        if not agree[i] >= self.min_image_ncc:
            self.stats.revisits_unverified += 1
            return None
        return int(cand[i])

    def _revisit(self, T_pred: np.ndarray) -> np.ndarray | None:
        n_old = len(self._db_r) - self.min_gap
        if n_old <= 0 or len(self._pts) < 30:
            return None
        j = self._match(n_old)
        if j is None:
            return None
        self.stats.revisits += 1
        T_j = self._db_T[j]
        pts_j = self._db_pts[j]
        reg = register_scan(self._pts, pts_j @ T_j[:3, :3].T + T_j[:3, 3], T_j, vfov_rad=self.spec.vfov_rad,
                            **self.register_kw)
        st, sr = self.revisit_sigma
        R = np.diag([st * st] * 3 + [sr * sr] * 3)
        delta = np.zeros(6)
        if reg is not None and reg.observed:
            B = reg.basis
            delta = reg.delta
            Rin = np.linalg.inv(B @ reg.info @ B.T)
            # in the directions the registration observed, its covariance; elsewhere the prior
            R = R + B.T @ Rin @ B  # the out-of-plane prior everywhere, plus the registration's own
        d, post, _, fused = fuse_revisit(T_pred, self._sigma, T_j, self._db_sigma[j], delta, R,
                                         self._gate[6])
        self.closures.append((len(self._db_r), j, delta.copy(), R, bool(fused)))
        if not fused:
            self.stats.revisits_gated += 1
            return None
        self.stats.revisits_fused += 1
        self.last_revisit = j
        self._sigma = post
        return d

    def correct_step(self, k: int, image, T_prev: np.ndarray, U: np.ndarray, Q: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray]:
        """The step to predict ping ``k`` with: ``(U, Q)`` corrected by the registrations, or as given."""
        self.stats.pings += 1
        self._r = np.asarray(self._returns(k, image), np.float64)
        self._pts = plane_points(self._r, self.spec.bearings_rad)
        if self.revisit and self.min_image_ncc is not None:
            if self.descriptors is None and image is None:
                raise ValueError("Expected an image (or precomputed descriptors) for the revisit's "
                                 "verification (min_image_ncc), but got None; pass min_image_ncc=None to "
                                 "match on first returns alone")
            self._desc = self.descriptors[k] if self.descriptors is not None else image_descriptor(image)
        self.last = None
        self.last_revisit = None
        if not self._db_r:
            if self.graph:
                from gpumap.ekf.posegraph import PoseGraph

                self._graph = PoseGraph(T_prev)
            return U, Q
        if self._graph is not None:
            self._graph.add_odometry(U, Q)
            n_closures = len(self.closures)
        if self.step and self._map:
            U, Q = self._step(T_prev, U, Q)
        A = se3_adjoint(se3_inverse(U))
        self._sigma = A @ self._sigma @ A.T + Q
        if self.revisit:
            d = self._revisit(T_prev @ U)
            if d is not None:
                U = U @ se3_exp(d)
        if self._graph is not None:
            k = len(self._db_r)
            new = self.closures[n_closures:]
            for c in new:
                self._graph.add_loop(c[1], k, c[2], c[3])
            self._pending += len(new)
            if self._pending and (not new or self._pending >= self.solve_every):
                self._graph.solve()
                self.solves += 1
                self._pending = 0
                U = se3_inverse(T_prev) @ self._graph._T[k]
        return U, Q

    def remember(self, T_W_S: np.ndarray) -> None:
        """Store the ping last passed to :meth:`correct_step` at ``T_W_S`` (the filter's pose)."""
        T = np.array(T_W_S, np.float64)
        if len(self._pts):
            self._map.append((T, self._pts))
        self._db_r.append(self._r)
        self._db_T.append(T)
        self._db_sigma.append(self._sigma.copy())
        self._db_pts.append(self._pts)
        if len(self._db_r) > len(self._db_val):
            grow = max(64, len(self._db_val))
            nb = self._db_val.shape[1]
            self._db_val = np.concatenate([self._db_val, np.zeros((grow, nb), np.float32)])
            self._db_ok = np.concatenate([self._db_ok, np.zeros((grow, nb), bool)])
        r = self._r[::PLACE_BEAM_STRIDE]
        ok = np.isfinite(r)
        self._db_val[len(self._db_r) - 1] = np.where(ok, r, 0.0)
        self._db_ok[len(self._db_r) - 1] = ok
        if self._desc is not None:
            if self._db_desc is None or len(self._db_desc) < len(self._db_val):
                old = np.zeros((0, self._desc.size), np.float32) if self._db_desc is None else self._db_desc
                self._db_desc = np.concatenate([old, np.zeros((len(self._db_val) - len(old), self._desc.size),
                                                             np.float32)])
            self._db_desc[len(self._db_r) - 1] = self._desc
