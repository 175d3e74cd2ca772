"""Innovation-consistency guard of the sonar EKF: when the pings do not fit, lean on odometry.

A return that passes its own chi-square gate can still be wrong in a way no single return
shows: real sonar returns are mostly not fixed point scatterers (a glint slides along a wall
as the sonar moves), so the filter's model of them is wrong, its corrections of the pose are
noise, and the pose ends worse than dead reckoning. What *can* be seen without ground truth
is whether the innovations have the statistics the model promises. :class:`TrustGuard` pools
the normalised innovations of the last ``window`` fused returns and trusts the pings with the
pose only while they are consistent:

- **Per return**: the filter's own chi-square gate (2 dof for a ``(range, azimuth)`` return,
  at its ``gate_prob``) refuses outliers, as before.
- **Windowed NIS**: the sum of the window's NIS over its ``2 n`` degrees of freedom must lie
  inside the two-sided band ``[chi2(p_lo, 2n), chi2(p_hi, 2n)] / 2n`` with ``p_lo = (1 - prob)
  / 2``, ``p_hi = 1 - p_lo``. Too high: the covariance is overconfident (outliers, wrong
  associations). Too low: the covariance the filter gives its returns is far too loose, so
  the model is not what generates them (on the real tank the NIS per dof sits at 0.6-0.7
  while the corrections are uncorrelated with the pose's true error).
- **Per component** (``per_component=True``): the same band on range and on azimuth alone
  (``sum nu_i^2 / S_ii`` over ``n`` returns, ``n`` dof each): a biased range whose azimuth
  is fine cannot hide behind a loose azimuth.
- **Two windows**: a short one (``window`` returns) that reacts fast and a long one
  (``long_window``) whose band is tight enough to see a small but steady mismatch; both must
  be in band, the long one full (by default).
- **Hold**: trust comes only after ``hold`` updates in a row with both windows in band, and
  goes at the first update that leaves them.
- **Track quality**: only returns of tracks at least ``min_track_hits`` long count in the
  window (a just-confirmed track's returns have the elevation's prior in them).

While the guard does not trust the pings (and until the window first fills: trust is
earned, not assumed), :class:`~gpumap.ekf.SonarEKF` fuses each accepted return as a Schmidt
("consider") update that corrects its own feature only: the pose and its covariance keep
exactly the odometry's increment, the features keep being refined, and the innovations keep
being computed (so consistency can come back and trust with it).

The guard is a small value object with counters; the filter feeds it (:meth:`add`) and asks
it (:attr:`trusted`).
"""

from __future__ import annotations

import collections
import functools

import numpy as np

from gpumap.ekf._checks import _chi2_quantile
from gpumap.errors import check_finite_scalar

__all__ = ["TrustGuard", "nis_band"]


@functools.lru_cache(maxsize=256)
def nis_band(prob: float, dof: int) -> tuple[float, float]:
    """Two-sided band of ``chi2(dof) / dof`` holding probability ``prob``.

    Parameters
    ----------
    prob : float
        Probability inside the band, in (0, 1).
    dof : int
        Degrees of freedom (>= 1).

    Returns
    -------
    (float, float)
        ``(chi2.ppf((1 - prob) / 2, dof) / dof, chi2.ppf((1 + prob) / 2, dof) / dof)``.
    """
    a = 0.5 * (1.0 - prob)
    return _chi2_quantile(a, dof) / dof, _chi2_quantile(1.0 - a, dof) / dof


class TrustGuard:
    """Windowed innovation consistency that decides whether the pings may correct the pose.

    Parameters
    ----------
    window : int, default 60
        Fused returns pooled (the most recent ones; whole updates are dropped from the old end
        while the rest still holds ``window``).
    prob : float, default 0.99
        Probability of the two-sided chi-square band (see the module docstring).
    per_component : bool, default True
        Also test range and azimuth alone.
    min_track_hits : int, default 0
        Returns of tracks with fewer hits do not enter the window (the caller passes each
        return's track length to :meth:`add`; 0 counts every return).
    long_window : int, default 300
        Fused returns of the long window (>= ``window``), tested against its own, tighter
        band: a model error too small to show in ``window`` returns (the real tank's NIS per
        dof of 0.66 sits inside the 120-dof band) shows in 600 dof.
    long_full : bool, default True
        Trust only once the long window is full (False: test it with what it holds).
    hold : int, default 10
        Updates in a row after which both windows were consistent before the pings are
        trusted (trust lost at the first inconsistent one): a brief stretch of consistency
        after a long one of odometry alone, when the pose covariance is largest and one
        update can move the pose most, is not enough.

    Attributes
    ----------
    trusted : bool
        Whether the next update may correct the pose.
    updates, pose_updates : int
        Updates fed to the guard, and those made while it trusted the pings.
    fused_pose, fused_features_only, gated : int
        Returns fused with a pose correction, returns fused into their own feature only
        (Schmidt), and returns refused by the filter's per-return gate.
    """

    def __init__(self, window: int = 60, prob: float = 0.99, per_component: bool = True,
                 min_track_hits: int = 0, long_window: int = 300, long_full: bool = True,
                 hold: int = 10) -> None:
        if isinstance(window, bool) or not isinstance(window, (int, np.integer)) or window < 1:
            raise ValueError(f"Expected an integer window >= 1, but got {window!r}")
        p = check_finite_scalar(prob, "prob")
        if not 0 < p < 1:
            raise ValueError(f"Expected 0 < prob < 1, but got {p}")
        if isinstance(min_track_hits, bool) or not isinstance(min_track_hits, (int, np.integer)) \
                or min_track_hits < 0:
            raise ValueError(f"Expected an integer min_track_hits >= 0, but got {min_track_hits!r}")
        if isinstance(long_window, bool) or not isinstance(long_window, (int, np.integer)) \
                or long_window < window:
            raise ValueError(f"Expected an integer long_window >= window ({window}), but got {long_window!r}")
        self.window = int(window)
        self.long_window = int(long_window)
        self.long_full = bool(long_full)
        if isinstance(hold, bool) or not isinstance(hold, (int, np.integer)) or hold < 1:
            raise ValueError(f"Expected an integer hold >= 1, but got {hold!r}")
        self.hold = int(hold)
        self._run = 0  # consecutive updates after which the windows were consistent
        self.prob = p
        self.per_component = bool(per_component)
        self.min_track_hits = int(min_track_hits)
        # per update: (returns, NIS, sum nu_r^2 / S_rr, sum nu_b^2 / S_bb)
        self._rows: collections.deque = collections.deque()
        self._sum = np.zeros(4)
        self._long: collections.deque = collections.deque()
        self._lsum = np.zeros(4)
        self.trusted = False
        self.updates = self.pose_updates = 0
        self.fused_pose = self.fused_features_only = self.gated = 0

    def reset(self) -> None:
        """Forget the window (trust must be earned again); the counters stay."""
        self._rows.clear()
        self._sum = np.zeros(4)
        self._long.clear()
        self._lsum = np.zeros(4)
        self._run = 0
        self.trusted = False

    @property
    def returns(self) -> int:
        """Returns in the window now."""
        return int(round(self._sum[0]))

    @property
    def nis_per_dof(self) -> float | None:
        """The window's NIS over its ``2 n`` dof; None while empty."""
        n = self._sum[0]
        return float(self._sum[1] / (2.0 * n)) if n > 0 else None

    def component_nis(self) -> tuple[float, float] | None:
        """``(range, azimuth)`` mean of ``nu_i^2 / S_ii`` over the window; None while empty."""
        n = self._sum[0]
        return (float(self._sum[2] / n), float(self._sum[3] / n)) if n > 0 else None

    def _in_band(self, v: np.ndarray) -> bool:
        n = int(round(v[0]))
        lo, hi = nis_band(self.prob, 2 * n)
        if not lo <= v[1] / (2 * n) <= hi:
            return False
        if self.per_component:
            lo1, hi1 = nis_band(self.prob, n)
            return all(lo1 <= x / n <= hi1 for x in v[2:4])
        return True

    def consistent(self) -> bool:
        """Whether the short window is full and it and the long window are inside their bands."""
        if self.returns < self.window or (self.long_full and self._lsum[0] < self.long_window):
            return False
        return self._in_band(self._sum) and self._in_band(self._lsum)

    def add(self, nis: np.ndarray, nu: np.ndarray, S: np.ndarray, *, gated: int = 0,
            pose_corrected: bool, track_hits: np.ndarray | None = None) -> None:
        """Feed one update's fused returns; recompute :attr:`trusted` for the next update.

        Parameters
        ----------
        nis : (a,) float
            Each fused return's own NIS (2 dof).
        nu : (a, 2) float
            Their innovations ``(range m, azimuth rad)``.
        S : (a, 2, 2) float
            Their innovation covariances.
        gated : int
            Returns of this update refused by the per-return gate.
        pose_corrected : bool
            Whether this update corrected the pose.
        track_hits : (a,) int, optional
            Each return's track length (for ``min_track_hits``).
        """
        nis = np.asarray(nis, dtype=np.float64).reshape(-1)
        a = nis.size
        self.updates += 1
        self.pose_updates += bool(pose_corrected and a)
        self.gated += int(gated)
        if pose_corrected:
            self.fused_pose += a
        else:
            self.fused_features_only += a
        if a == 0:
            return
        use = np.ones(a, bool)
        if track_hits is not None and self.min_track_hits:
            use = np.asarray(track_hits).reshape(-1) >= self.min_track_hits
        if not np.any(use):
            return
        nu = np.asarray(nu, dtype=np.float64).reshape(a, 2)[use]
        S = np.asarray(S, dtype=np.float64).reshape(a, 2, 2)[use]
        row = np.array([float(use.sum()), float(nis[use].sum()),
                        float(np.sum(nu[:, 0] ** 2 / S[:, 0, 0])), float(np.sum(nu[:, 1] ** 2 / S[:, 1, 1]))])
        self._rows.append(row)
        self._sum = self._sum + row
        while self._sum[0] - self._rows[0][0] >= self.window:
            self._sum = self._sum - self._rows.popleft()
        self._long.append(row)
        self._lsum = self._lsum + row
        while self._lsum[0] - self._long[0][0] >= self.long_window:
            self._lsum = self._lsum - self._long.popleft()
        self._run = self._run + 1 if self.consistent() else 0
        self.trusted = self._run >= self.hold

    def summary(self) -> dict:
        """JSON-ready counters and the window's state."""
        total = self.fused_pose + self.fused_features_only
        cn = self.component_nis()
        return {"trusted_now": bool(self.trusted), "updates": self.updates,
                "pose_updates": self.pose_updates, "fused_with_pose": self.fused_pose,
                "fused_features_only": self.fused_features_only, "gated": self.gated,
                "share_fused_with_pose": self.fused_pose / total if total else 0.0,
                "window_returns": self.returns, "window_nis_per_dof": self.nis_per_dof,
                "window_range_nis": None if cn is None else cn[0],
                "window_bearing_nis": None if cn is None else cn[1],
                "band": list(nis_band(self.prob, 2 * self.window)), "window": self.window,
                "prob": self.prob, "per_component": self.per_component,
                "long_window": self.long_window, "long_window_returns": int(round(self._lsum[0])),
                "long_window_nis_per_dof": (float(self._lsum[1] / (2 * self._lsum[0]))
                                            if self._lsum[0] else None),
                "min_track_hits": self.min_track_hits, "hold": self.hold}

    def __repr__(self) -> str:
        v = self.nis_per_dof
        return (f"TrustGuard(window={self.window}, prob={self.prob}, trusted={self.trusted}, "
                f"nis_per_dof={'-' if v is None else f'{v:.3f}'})")
