"""Data association for point-like sonar returns: which feature (if any) each return belongs to.

:class:`FeatureTracker` sits between a detector (:mod:`gpumap.ekf.frontend`, or any source
of unlabelled ``(range, azimuth)`` returns with covariances) and :class:`~gpumap.ekf.SonarEKF`:

- **Confirmed tracks** are the EKF's features. Each one expected in view (range and azimuth
  inside the fan, elevation within the aperture by 3 sigma) is predicted from the filter's
  joint covariance: ``z_hat = h(T_W_S, l_W)``, ``S = H C H^T + R``. A return is a candidate
  when its squared Mahalanobis distance passes the chi-square gate (2 dof, ``gate_prob``).
  Where a return or a track has a single candidate and the pair is mutual, it is taken (nearest
  neighbour); where candidates overlap (a cluster of tracks and returns), the assignment is
  chosen by **joint compatibility** (JCBB, Neira and Tardos 2001): the largest set of pairs whose
  *joint* innovation, with the cross-covariances of pose and features, passes the chi-square
  gate of ``2k`` dof, the smallest joint NIS breaking ties. Clusters above ``max_cluster``
  tracks fall back to the optimal assignment of the pairwise distances.
- **Ambiguity**: a pair is not taken when the track's gate holds another unclaimed return, or
  the return lies in the gate of another unpaired track, less than ``ambiguity_margin``
  farther (squared Mahalanobis distance) than the chosen pairing; such a track is neither hit
  nor missed at this ping, and the doubtful returns start nothing.
- **Tentative tracks** hold returns not explained by any confirmed track. A return is a
  repeat of a tentative track when it lies near the track's first return moved into the
  current sonar frame: that return's elevation is unknown, so its elevation arc is sampled
  (``arc_samples`` points over the aperture) and the nearest sample still consistent counts,
  with the covariance of both returns, of the motion since (the odometry's, summed) and of
  the arc's sampling step; each hit keeps only the samples it passes (a coarse triangulation).
  Pairs are the optimal assignment of these distances, under the same ambiguity rule.
  A tentative track seen ``confirm_hits`` times, with at most ``max_gap - 1`` pings between hits,
  becomes confirmed: it joins the EKF (initialised from its latest return) under its id.
  One return alone never starts a feature.
- **Ending**: a confirmed track missed (no return, or its return refused by the EKF's own gate)
  in ``max_misses`` consecutive pings where it was expected in view is ended and marginalised
  out of the filter (:meth:`SonarEKF.forget`); a tentative track not repeated within
  ``max_gap`` pings is dropped. Ids are never reused.

Everything is deterministic (no random numbers); the tracker keeps each track's history of
``(ping, return index)`` for the caller's statistics (:attr:`FeatureTracker.tracks`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import linear_sum_assignment

from gpumap.ekf._checks import _chi2_2dof, _chi2_quantile
from gpumap.ekf.filter import SonarEKF
from gpumap.ekf.frontend import PointMeasurements
from gpumap.ekf.measurement import _observe_batch, spherical_point, wrap_angle
from gpumap.errors import check_finite_scalar
from gpumap.lie import se3_inverse
from gpumap.spec import SonarSpec

__all__ = ["FeatureTracker", "Track", "TrackerStep"]


@dataclass
class Track:
    """One track: a run of returns believed to come from one scatterer.

    Attributes
    ----------
    id : int
        Stable id (also the EKF's feature id once confirmed); never reused.
    status : str
        ``"tentative"``, ``"confirmed"`` or ``"ended"`` (``"dropped"``: a tentative one that
        never confirmed).
    born, last_seen : int
        Ping index of the first and the latest return.
    confirmed_at, ended_at : int or None
        Ping index of confirmation and of the end.
    hits : int
        Returns associated with the track.
    misses : int
        Consecutive pings where a confirmed track was expected in view and not seen.
    returns : list of (int, int)
        ``(ping, index of the return in that ping's measurements)`` of every hit.
    """

    id: int
    status: str
    born: int
    last_seen: int
    hits: int = 1
    misses: int = 0
    confirmed_at: int | None = None
    ended_at: int | None = None
    returns: list = field(default_factory=list)
    # tentative state: the latest return, its covariance, the pose it was seen from and the
    # motion covariance accumulated since
    z: np.ndarray | None = None
    R: np.ndarray | None = None
    T_W_S: np.ndarray | None = None
    Q_since: np.ndarray | None = None
    el_ok: np.ndarray | None = None


@dataclass(frozen=True)
class TrackerStep:
    """What :meth:`FeatureTracker.step` did with one ping's returns.

    Attributes
    ----------
    labels : (m,) int64
        Track id of each return (-1: none, the return was refused by every gate and started
        nothing, which happens only when ``max_tracks`` is reached).
    confirmed_hits : dict of int to int
        Confirmed track id -> return index fused into the EKF this ping.
    tentative_hits : dict of int to int
        Tentative track id -> return index (including tracks confirmed at this ping).
    started : tuple of int
        New tentative tracks.
    confirmed : tuple of int
        Tracks confirmed at this ping (now EKF features).
    ended : tuple of int
        Confirmed tracks ended (and forgotten by the EKF) at this ping.
    refused : dict of int to float
        Confirmed track id -> NIS of a return the tracker paired with it but the EKF's own gate
        refused (counted as a miss).
    expected : tuple of int
        Confirmed tracks predicted in view.
    """

    labels: np.ndarray
    confirmed_hits: dict
    tentative_hits: dict
    started: tuple
    confirmed: tuple
    ended: tuple
    refused: dict
    expected: tuple


class FeatureTracker:
    """Associate unlabelled point returns with the features of a :class:`SonarEKF`.

    Parameters
    ----------
    ekf : SonarEKF
        The filter; the tracker calls its :meth:`~SonarEKF.update` and
        :meth:`~SonarEKF.forget`. Features already in it are taken as confirmed tracks.
    spec : SonarSpec
        The sonar (field of view for the "expected in view" test).
    gate_prob : float, default 0.999
        Chi-square gate of single pairs (2 dof) and of joint compatibility (2k dof).
    confirm_hits : int, default 3
        Returns needed before a tentative track becomes a feature (>= 2).
    max_gap : int, default 2
        A tentative track must be seen again within this many pings.
    max_misses : int, default 5
        Consecutive expected-but-missed pings that end a confirmed track.
    arc_samples : int, default 15
        Elevation samples of a tentative track's arc.
    max_cluster : int, default 6
        Largest cluster (tracks) solved by joint compatibility; larger ones by assignment.
    max_features : int, default 60
        Most confirmed tracks kept in the EKF; past it the one unseen longest is forgotten.
    ambiguity_margin : float, default 4.0
        A track whose gate holds another unclaimed return less than this much farther
        (squared Mahalanobis distance) than its chosen one is left unpaired this ping (neither
        hit nor miss): ambiguous returns are not guessed.
    first_id : int, default 0
        The first track id.
    """

    def __init__(
        self,
        ekf: SonarEKF,
        spec: SonarSpec,
        *,
        gate_prob: float = 0.999,
        confirm_hits: int = 3,
        max_gap: int = 2,
        max_misses: int = 5,
        arc_samples: int = 15,
        max_cluster: int = 6,
        max_features: int = 60,
        ambiguity_margin: float = 4.0,
        first_id: int = 0,
    ) -> None:
        if not isinstance(ekf, SonarEKF):
            raise TypeError(f"Expected a SonarEKF for 'ekf', but got {type(ekf).__name__}")
        if not isinstance(spec, SonarSpec):
            raise TypeError(f"Expected a SonarSpec for 'spec', but got {type(spec).__name__}")
        gp = check_finite_scalar(gate_prob, "gate_prob")
        if not 0 < gp < 1:
            raise ValueError(f"Expected 0 < gate_prob < 1, but got {gp}")
        for name, v, lo in (("confirm_hits", confirm_hits, 2), ("max_gap", max_gap, 1),
                            ("max_misses", max_misses, 1), ("arc_samples", arc_samples, 2),
                            ("max_cluster", max_cluster, 1), ("max_features", max_features, 1),
                            ("first_id", first_id, -(2**62))):
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < lo:
                raise ValueError(f"Expected an integer {name} >= {lo}, but got {v!r}")
        self.ekf = ekf
        self.spec = spec
        self.gate_prob = gp
        self._gate = _chi2_2dof(gp)
        self.confirm_hits = int(confirm_hits)
        self.max_gap = int(max_gap)
        self.max_misses = int(max_misses)
        self.arc_samples = int(arc_samples)
        self.max_cluster = int(max_cluster)
        self.max_features = int(max_features)
        am = check_finite_scalar(ambiguity_margin, "ambiguity_margin")
        if am < 0:
            raise ValueError(f"Expected ambiguity_margin >= 0, but got {am}")
        self.ambiguity_margin = am
        self._next_id = int(first_id)
        self._ping = -1
        self.tracks: dict[int, Track] = {}
        for i in ekf.landmark_ids:
            self.tracks[i] = Track(i, "confirmed", 0, 0, confirmed_at=0)
            self._next_id = max(self._next_id, i + 1)

    # ------------------------------------------------------------------ helpers
    def _new_id(self) -> int:
        i = self._next_id
        self._next_id += 1
        return i

    def _confirmed_predictions(self):
        """Ids in view, predicted z (k, 2), Jacobian rows into the world covariance, covariance."""
        ids = [i for i in self.ekf.landmark_ids if self.tracks[i].status == "confirmed"]
        if not ids:
            return [], None, None, None
        T = self.ekf.pose
        C = self.ekf.covariance
        order = {i: k for k, i in enumerate(self.ekf.landmark_ids)}
        L = self.ekf.landmarks
        Lw = np.array([L[i] for i in ids])
        z, Hp, Hl, _, P = _observe_batch(T[:3, :3], T[:3, 3], Lw)
        pol = self.spec.to_polar(P)
        edges = self.spec.beam_edges_rad
        # elevation's sd from the feature's covariance seen from the sonar
        el_sd = np.empty(len(ids))
        for q, i in enumerate(ids):
            s = 6 + 3 * order[i]
            n_el = spherical_point(pol[q])[1][:, 2] / max(pol[q, 0], 1e-9)  # d p / d el / r
            u = T[:3, :3] @ (n_el / max(np.linalg.norm(n_el), 1e-12))
            el_sd[q] = math.sqrt(max(float(u @ C[s:s + 3, s:s + 3] @ u), 0.0)) / max(pol[q, 0], 1e-9)
        inview = ((pol[:, 0] >= self.spec.range_min_m) & (pol[:, 0] < self.spec.range_max_m)
                  & (pol[:, 1] >= edges[0]) & (pol[:, 1] <= edges[-1])
                  & (np.abs(pol[:, 2]) <= 0.5 * self.spec.vfov_rad + 3.0 * el_sd))
        sel = np.flatnonzero(inview)
        ids = [ids[q] for q in sel]
        cols = [np.r_[0:6, 6 + 3 * order[i] : 9 + 3 * order[i]] for i in ids]
        H = np.concatenate([Hp[sel], Hl[sel]], axis=2)  # (k, 2, 9)
        return ids, z[sel], (H, cols), C

    def _gated(self, ids, z_hat, Hc, C, meas: PointMeasurements):
        """Pairwise squared Mahalanobis distances (k, m), inf outside the gate."""
        k, m = len(ids), len(meas)
        D = np.full((k, m), np.inf)
        if k == 0 or m == 0:
            return D, None
        H, cols = Hc
        S0 = np.stack([H[q] @ C[np.ix_(cols[q], cols[q])] @ H[q].T for q in range(k)])  # (k, 2, 2)
        zm = np.stack([meas.ranges_m, meas.bearings_rad], axis=1)
        nu = zm[None, :, :] - z_hat[:, None, :]
        nu[..., 1] = wrap_angle(nu[..., 1])
        S = S0[:, None] + meas.covs[None]  # (k, m, 2, 2)
        a, b, d = S[..., 0, 0], S[..., 0, 1], S[..., 1, 1]
        det = a * d - b * b
        d2 = (d * nu[..., 0] ** 2 - 2 * b * nu[..., 0] * nu[..., 1] + a * nu[..., 1] ** 2) / det
        D[d2 <= self._gate] = d2[d2 <= self._gate]
        return D, nu

    def _joint_nis(self, pairs, Hc, C, nu, meas) -> float:
        H, cols = Hc
        allc = np.unique(np.concatenate([cols[q] for q, _ in pairs]))
        pos = {c: n for n, c in enumerate(allc)}
        J = np.zeros((2 * len(pairs), allc.size))
        v = np.empty(2 * len(pairs))
        Rb = np.zeros((2 * len(pairs), 2 * len(pairs)))
        for n, (q, j) in enumerate(pairs):
            J[2 * n : 2 * n + 2, [pos[c] for c in cols[q]]] = H[q]
            v[2 * n : 2 * n + 2] = nu[q, j]
            Rb[2 * n : 2 * n + 2, 2 * n : 2 * n + 2] = meas.covs[j]
        S = J @ C[np.ix_(allc, allc)] @ J.T + Rb
        try:
            L = np.linalg.cholesky(0.5 * (S + S.T))
        except np.linalg.LinAlgError:
            return math.inf
        w = np.linalg.solve(L, v)
        return float(w @ w)

    def _jcbb(self, tq: list[int], D, Hc, C, nu, meas) -> list[tuple[int, int]]:
        """Largest jointly compatible pairing of tracks ``tq`` (rows of D), least joint NIS."""
        best: list = [[], math.inf]
        options = [[j for j in np.flatnonzero(np.isfinite(D[q]))] for q in tq]

        def rec(n: int, used: set, pairs: list, nis: float) -> None:
            if len(pairs) + (len(tq) - n) < len(best[0]):
                return  # cannot beat the best pairing's size
            if n == len(tq):
                if len(pairs) > len(best[0]) or (len(pairs) == len(best[0]) and nis < best[1]):
                    best[0], best[1] = list(pairs), nis
                return
            q = tq[n]
            for j in sorted(options[n], key=lambda j: D[q, j]):
                if j in used:
                    continue
                cand = pairs + [(q, j)]
                jn = self._joint_nis(cand, Hc, C, nu, meas)
                if jn <= _chi2_quantile(self.gate_prob, 2 * len(cand)):
                    rec(n + 1, used | {j}, cand, jn)
            rec(n + 1, used, pairs, nis)  # this track unpaired

        rec(0, set(), [], 0.0)
        return best[0]

    def _assign_confirmed(self, D, Hc, C, nu, meas) -> list[tuple[int, int]]:
        k, m = D.shape
        if k == 0 or m == 0:
            return []
        G = np.isfinite(D)
        # clusters: connected components of the bipartite gate graph
        seen_t = np.zeros(k, bool)
        pairs: list[tuple[int, int]] = []
        for q0 in range(k):
            if seen_t[q0] or not G[q0].any():
                continue
            tq, mj = {q0}, set()
            frontier = [q0]
            while frontier:
                q = frontier.pop()
                for j in np.flatnonzero(G[q]):
                    if j not in mj:
                        mj.add(int(j))
                        for q2 in np.flatnonzero(G[:, j]):
                            if q2 not in tq:
                                tq.add(int(q2))
                                frontier.append(int(q2))
            seen_t[list(tq)] = True
            tq_l = sorted(tq)
            if len(tq_l) == 1 and len(mj) == 1:
                pairs.append((tq_l[0], next(iter(mj))))
            elif len(tq_l) <= self.max_cluster:
                pairs += self._jcbb(tq_l, D, Hc, C, nu, meas)
            else:
                sub = D[np.ix_(tq_l, sorted(mj))]
                big = 1e9
                r, c = linear_sum_assignment(np.where(np.isfinite(sub), sub, big))
                mj_l = sorted(mj)
                pairs += [(tq_l[a], mj_l[b]) for a, b in zip(r, c, strict=True) if sub[a, b] < big]
        return pairs

    def _unambiguous(self, pairs: list[tuple[int, int]], D: np.ndarray) -> tuple[list, set]:
        """The pairs no other unclaimed return or unpaired track nearly explains; the others' returns."""
        pj = {j for _, j in pairs}
        pq = {q for q, _ in pairs}
        keep, doubt = [], set()
        for q, j in pairs:
            lim = D[q, j] + self.ambiguity_margin
            row = [j2 for j2 in np.flatnonzero(D[q] < lim) if j2 != j and j2 not in pj]
            col = [q2 for q2 in np.flatnonzero(D[:, j] < lim) if q2 != q and q2 not in pq]
            if row or col:
                doubt.add(j)
                doubt.update(int(x) for x in row)
            else:
                keep.append((q, j))
        return keep, doubt

    def _tentative_d2(self, tr: Track, T_now: np.ndarray, meas: PointMeasurements) -> np.ndarray:
        """(n, m) squared Mahalanobis distance of each return to each sample of the track's moved arc."""
        n = self.arc_samples
        vf = self.spec.vfov_rad
        els = np.linspace(-0.5 * vf, 0.5 * vf, n)
        s = np.stack([np.full(n, tr.z[0]), np.full(n, tr.z[1]), els], axis=1)
        p_prev, D = spherical_point(s)  # (n, 3), (n, 3, 3)
        T_rel = se3_inverse(tr.T_W_S) @ T_now  # current pose in the old sonar frame
        z, Hp, Hl, _, _ = _observe_batch(T_rel[:3, :3], T_rel[:3, 3], p_prev)
        step2 = (vf / (n - 1)) ** 2 / 12.0
        Jm = Hl @ D  # (n, 2, 3): d z / d (r, az, el) of the old return
        Jt = np.transpose
        S0 = Hp @ tr.Q_since @ Jt(Hp, (0, 2, 1)) + Jm[:, :, :2] @ tr.R @ Jt(Jm[:, :, :2], (0, 2, 1))
        S0 += step2 * Jm[:, :, 2:3] @ Jt(Jm[:, :, 2:3], (0, 2, 1))
        zm = np.stack([meas.ranges_m, meas.bearings_rad], axis=1)
        nu = zm[None] - z[:, None]
        nu[..., 1] = wrap_angle(nu[..., 1])
        S = S0[:, None] + meas.covs[None]
        a, b, d = S[..., 0, 0], S[..., 0, 1], S[..., 1, 1]
        d2 = (d * nu[..., 0] ** 2 - 2 * b * nu[..., 0] * nu[..., 1] + a * nu[..., 1] ** 2) / (a * d - b * b)
        return np.where(tr.el_ok[:, None], d2, np.inf)

    # ------------------------------------------------------------------ the step
    def step(self, meas: PointMeasurements, motion_cov: np.ndarray | None = None) -> TrackerStep:
        """Associate one ping's returns; update the EKF; start, confirm and end tracks.

        Call it after :meth:`SonarEKF.predict` for this ping.

        Parameters
        ----------
        meas : PointMeasurements
            This ping's returns (ranges, bearings, covariances).
        motion_cov : (6, 6) float, optional
            Covariance of the odometry step that led to this ping (the one given to
            ``predict``); it widens the tentative tracks' gates. None: no motion (first ping).

        Returns
        -------
        TrackerStep
        """
        if not isinstance(meas, PointMeasurements):
            raise TypeError(f"Expected PointMeasurements for 'meas', but got {type(meas).__name__}")
        Q = np.zeros((6, 6)) if motion_cov is None else np.asarray(motion_cov, dtype=np.float64)
        if Q.shape != (6, 6) or not np.all(np.isfinite(Q)):
            raise ValueError(f"Expected a finite (6, 6) 'motion_cov', but got shape {Q.shape}")
        self._ping += 1
        ping = self._ping
        m = len(meas)
        labels = np.full(m, -1, dtype=np.int64)

        # 1. confirmed tracks: gate, assign (NN / JCBB), fuse
        ids, z_hat, Hc, C = self._confirmed_predictions()
        pairs: list[tuple[int, int]] = []
        if ids and m:
            D, nu = self._gated(ids, z_hat, Hc, C, meas)
            pairs, doubt = self._unambiguous(self._assign_confirmed(D, Hc, C, nu, meas), D)
            paired = {q for q, _ in pairs}
            dl = np.zeros(m, bool)
            dl[list(doubt)] = True
            # unpaired tracks whose gate holds a doubtful return: ambiguous, not missed
            unsure = {ids[q] for q in range(len(ids)) if q not in paired and np.any(np.isfinite(D[q]) & dl)}
        else:
            doubt, unsure = set(), set()
        confirmed_hits: dict[int, int] = {}
        refused: dict[int, float] = {}
        if pairs:
            tid = np.array([ids[q] for q, _ in pairs], dtype=np.int64)
            js = np.array([j for _, j in pairs])
            res = self.ekf.update(tid, meas.ranges_m[js], meas.bearings_rad[js], meas.covs[js],
                                  track_hits=np.array([self.tracks[i].hits for i in tid.tolist()]))
            acc = set(res.accepted_ids)
            for i, j in zip(tid.tolist(), js.tolist(), strict=True):
                if i in acc:
                    confirmed_hits[i] = j
                    labels[j] = i
                else:
                    refused[i] = float(res.rejected.get(i, math.nan))
        for i in ids:
            tr = self.tracks[i]
            if i in unsure and i not in confirmed_hits and i not in refused:
                continue  # ambiguous this ping: neither hit nor miss
            if i in confirmed_hits:
                tr.hits += 1
                tr.misses = 0
                tr.last_seen = ping
                tr.returns.append((ping, confirmed_hits[i]))
            else:
                tr.misses += 1
        ended = []
        for i in ids:
            tr = self.tracks[i]
            if tr.status == "confirmed" and tr.misses >= self.max_misses:
                tr.status, tr.ended_at = "ended", ping
                self.ekf.forget(i)
                ended.append(i)

        # 2. the other returns against tentative tracks (moved into the current frame)
        T_now = self.ekf.pose
        free = np.flatnonzero(labels < 0)
        # returns paired with a confirmed track but refused by the EKF start nothing
        used_by_refused = {j for q, j in pairs if ids[q] in refused} | doubt
        free = np.array([j for j in free if j not in used_by_refused], dtype=np.int64)
        tent = [t for t in self.tracks.values() if t.status == "tentative"]
        for t in tent:
            t.Q_since = t.Q_since + Q
        tentative_hits: dict[int, int] = {}
        if tent and free.size:
            sub = meas.take(free)
            Dn = [self._tentative_d2(t, T_now, sub) for t in tent]  # each (n, m_free)
            Dt = np.stack([d.min(axis=0) for d in Dn])
            big = 1e9
            cost = np.where(Dt <= self._gate, Dt, big)
            r, c = linear_sum_assignment(cost)
            tp, tdoubt = self._unambiguous([(int(a), int(b)) for a, b in zip(r, c, strict=True)
                                            if cost[a, b] < big], np.where(cost < big, Dt, np.inf))
            used_by_refused |= {int(free[b]) for b in tdoubt}
            for a, b in tp:
                tentative_hits[tent[a].id] = int(free[b])
                tent[a].el_ok = tent[a].el_ok & (Dn[a][:, b] <= self._gate)
        confirmed_now = []
        for t in tent:
            if t.id in tentative_hits:
                j = tentative_hits[t.id]
                t.hits += 1
                t.last_seen = ping
                t.returns.append((ping, j))
                labels[j] = t.id
                if t.hits >= self.confirm_hits:
                    confirmed_now.append(t)
            elif ping - t.last_seen >= self.max_gap:
                t.status, t.ended_at = "dropped", ping
                t.z = t.R = t.T_W_S = t.Q_since = t.el_ok = None
        if confirmed_now:
            idc = np.array([t.id for t in confirmed_now], dtype=np.int64)
            js = np.array([tentative_hits[t.id] for t in confirmed_now])
            self.ekf.update(idc, meas.ranges_m[js], meas.bearings_rad[js], meas.covs[js])
            for t in confirmed_now:
                t.status, t.confirmed_at = "confirmed", ping
                t.misses = 0
        # 3. what is left starts tentative tracks
        started = []
        for j in np.flatnonzero(labels < 0):
            if j in used_by_refused:
                continue
            t = Track(self._new_id(), "tentative", ping, ping, returns=[(ping, int(j))],
                      z=np.array([meas.ranges_m[j], meas.bearings_rad[j]]), R=meas.covs[j].copy(),
                      T_W_S=T_now.copy(), Q_since=np.zeros((6, 6)), el_ok=np.ones(self.arc_samples, bool))
            self.tracks[t.id] = t
            labels[j] = t.id
            started.append(t.id)
        # 4. bound the EKF's size: forget the confirmed tracks unseen longest
        live = [self.tracks[i] for i in self.ekf.landmark_ids]
        if len(live) > self.max_features:
            live.sort(key=lambda t: t.last_seen)
            for t in live[: len(live) - self.max_features]:
                t.status, t.ended_at = "ended", ping
                self.ekf.forget(t.id)
                ended.append(t.id)
        return TrackerStep(labels=labels, confirmed_hits=confirmed_hits, tentative_hits=tentative_hits,
                           started=tuple(started), confirmed=tuple(t.id for t in confirmed_now),
                           ended=tuple(ended), refused=refused, expected=tuple(ids))

    def lifetimes(self) -> dict:
        """Summary of the confirmed tracks: count, hits and lifetimes (pings from birth to last hit).

        Returns
        -------
        dict
            ``confirmed`` (tracks ever confirmed), ``live`` (still in the EKF), ``ended``,
            ``dropped_tentative``, ``hits_median``, ``lifetime_pings_median`` and ``_max``.
        """
        conf = [t for t in self.tracks.values() if t.confirmed_at is not None]
        life = np.array([t.last_seen - t.born + 1 for t in conf]) if conf else np.zeros(0)
        hits = np.array([t.hits for t in conf]) if conf else np.zeros(0)
        return {
            "confirmed": len(conf),
            "live": sum(t.status == "confirmed" for t in conf),
            "ended": sum(t.status == "ended" for t in conf),
            "dropped_tentative": sum(t.status == "dropped" for t in self.tracks.values()),
            "hits_median": float(np.median(hits)) if hits.size else 0.0,
            "hits_max": int(hits.max()) if hits.size else 0,
            "lifetime_pings_median": float(np.median(life)) if life.size else 0.0,
            "lifetime_pings_max": int(life.max()) if life.size else 0,
        }

