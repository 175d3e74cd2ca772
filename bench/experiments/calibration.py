"""The evidence rule's calibrated decision: how reliable this sonar's views are, learnt from the map itself.

Every voxel of an evidence map keeps two counts (:mod:`gpumap.reference`): ``k`` bright views and
``d`` clear dark views (``n = k + d`` views that could have shown it dark). A surface is bright in most
of the views that see it; water that the elevation aperture painted bright ("the stretch") is
bright in some views and clear-dark in others. How often a real surface is dark, and how often the
stretch is bright, depends on the sonar, its gain, the scene and the trajectory: a noise-free
simulator's surfaces are bright in every view, the real tank's in a median ~0.8 of them.

So the decision is fitted per map, from the map's own evidence. The histogram of ``(k, n)`` over
the voxels ever seen bright is modelled as a two-class mixture, each class a beta-binomial (views
of one voxel are correlated: consecutive pings of a sonar see nearly the same thing, so a
binomial would over-trust many views; the beta-binomial's spread absorbs it, which keeps the
decision the same at the sonar's rate and at every 10th ping):

    P(k | n, k >= 1) = pi BB+(k; n, a_s, b_s) + (1 - pi) BB+(k; n, a_w, b_w)

(``BB+``: the beta-binomial truncated to ``k >= 1``, since only ever-bright voxels are modelled)

with the surface class the one of higher mean share, fitted by maximum likelihood (L-BFGS-B over the
five parameters with the analytic gradient, from a fixed start). A voxel is **occupied** when its
posterior of being surface is at least ``1 / (1 + miss_cost)``: ``miss_cost`` is how many phantom
voxels one avoided miss is worth (the user's knob; large: safer and fuller, small: cleaner). Among
the voxels of equal ``n`` the decision is made monotone in ``k`` (more bright views never free a
voxel a smaller ``k`` keeps). Voxels never seen bright are free once observed, never-observed ones
unknown, as in every rule.

The fit reads only the counts, which merge by saturating sums: a merged map is decided exactly as
the map of all its pings. Where the map holds too little evidence to fit (fewer than
:data:`MIN_FIT_VOXELS` ever-bright voxels with a clear dark view), every ever-bright voxel is kept
occupied (sound at any ping count).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy.optimize import minimize
from scipy.special import betaln, digamma, gammaln

__all__ = ["MIN_FIT_VOXELS", "ViewModel", "calibrated_occupied", "count_histogram", "fit_view_model",
           "surface_log_odds"]

#: Ever-bright voxels with at least one clear dark view needed before the views are modelled.
MIN_FIT_VOXELS = 50
_LOG_BOUND = 7.0  # beta-binomial shape parameters kept in [e^-7, e^7]
_MAX_ITER = 200  # quasi-Newton iterations of the likelihood's maximisation


@dataclass(frozen=True)
class ViewModel:
    """A fitted two-class view model (module docstring). ``surface`` and ``water`` are the
    beta-binomial shapes ``(a, b)`` (mean share ``a / (a + b)``), ``pi`` the surface class's weight
    among the ever-bright voxels; ``fitted`` False when the map held too little evidence (then
    every ever-bright voxel is occupied)."""

    pi: float
    surface: tuple[float, float]
    water: tuple[float, float]
    voxels: int  # ever-bright voxels the fit saw
    iterations: int
    log_likelihood: float  # mean per voxel
    fitted: bool = True

    @property
    def surface_mean_share(self) -> float:
        a, b = self.surface
        return a / (a + b)

    @property
    def water_mean_share(self) -> float:
        a, b = self.water
        return a / (a + b)

    def to_dict(self) -> dict:
        return {**asdict(self), "surface_mean_share": self.surface_mean_share,
                "water_mean_share": self.water_mean_share}


def _pairs(dark: np.ndarray, hits: np.ndarray):
    """The ever-bright voxels' flat indices, their distinct ``(k, n)`` pairs sorted by ``(n, k)``,
    how many voxels hold each, and each voxel's pair."""
    h = np.asarray(hits).reshape(-1)
    idx = np.flatnonzero(h)
    k = h[idx].astype(np.int64)
    n = k + np.asarray(dark).reshape(-1)[idx].astype(np.int64)
    pairs, inverse, w = np.unique(np.stack([n, k], 1), axis=0, return_inverse=True, return_counts=True)
    return idx, pairs[:, 1], pairs[:, 0], w.astype(np.float64), inverse.reshape(-1)


def count_histogram(dark: np.ndarray, hits: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The ``(k, n)`` pairs of the voxels ever seen bright and how many voxels hold each.

    ``dark``, ``hits``: clear dark and bright views per voxel (any shape, unsigned ints). Returns
    ``k`` (m,) int64, ``n`` (m,) int64 (``k + dark``) and ``weight`` (m,) float64, pairs sorted by
    ``(n, k)``."""
    _, k, n, w, _ = _pairs(dark, hits)
    return k, n, w


def _log_binom(k: np.ndarray, n: np.ndarray) -> np.ndarray:
    return gammaln(n + 1.0) - gammaln(k + 1.0) - gammaln(n - k + 1.0)


def _log_bb(k, n, a, b, log_binom) -> np.ndarray:
    """log BB(k; n, a, b) (float64 arrays)."""
    return log_binom + betaln(k + a, n - k + b) - betaln(a, b)


def _bb_terms(k, n, a, b, log_binom):
    """log BB(k; n, a, b | k >= 1) (zero-truncated: only ever-bright voxels are modelled) and its
    derivatives in log a and log b."""
    dab = digamma(n + a + b) - digamma(a + b)
    log0 = betaln(a, n + b) - betaln(a, b)  # log BB(0; n, a, b)
    p0 = np.exp(log0)
    t = p0 / -np.expm1(log0)  # d log(1 - p0) = -t d log p0
    da0, db0 = -dab, digamma(n + b) - digamma(b) - dab
    return (_log_bb(k, n, a, b, log_binom) - np.log1p(-p0),
            a * (digamma(k + a) - digamma(a) - dab + t * da0),
            b * (digamma(n - k + b) - digamma(b) - dab + t * db0))


def _neg_log_likelihood(x, k, n, w, log_binom, total):
    """Mean negative log-likelihood of the mixture at ``x`` = (logit pi, log a_s, log b_s, log a_w,
    log b_w), and its gradient."""
    lpi, lpw = -np.logaddexp(0.0, -x[0]), -np.logaddexp(0.0, x[0])
    ls, gas, gbs = _bb_terms(k, n, np.exp(x[1]), np.exp(x[2]), log_binom)
    lw, gaw, gbw = _bb_terms(k, n, np.exp(x[3]), np.exp(x[4]), log_binom)
    ls, lw = ls + lpi, lw + lpw
    norm = np.logaddexp(ls, lw)
    rs = w * np.exp(ls - norm)
    rw = w - rs
    grad = np.array([rs.sum() - total * np.exp(lpi), rs @ gas, rs @ gbs, rw @ gaw, rw @ gbw])
    return -float(w @ norm) / total, -grad / total


def fit_view_model(dark: np.ndarray, hits: np.ndarray) -> ViewModel:
    """Fit the two-class view model (module docstring) to a map's counts.

    Parameters
    ----------
    dark, hits : ndarray of unsigned int, same size
        Clear dark views and bright views per voxel (:meth:`gpumap.MinMaxMapper.evidence`'s
        ``count`` and ``hits``, or :func:`gpumap.reference.split_counts` of a packed state).

    Returns
    -------
    ViewModel
        Deterministic for the same counts (fixed start, fixed iteration rule).
    """
    dark, hits = np.asarray(dark), np.asarray(hits)
    if dark.size != hits.size:
        raise ValueError(f"Expected dark and hits of the same size, but got {dark.size} and {hits.size}")
    return _fit(*count_histogram(dark, hits))


def _fit(k: np.ndarray, n: np.ndarray, w: np.ndarray) -> ViewModel:
    """:func:`fit_view_model` on the histogram of ``(k, n)`` pairs with their voxel counts ``w``."""
    voxels = int(w.sum())
    if float(w[n > k].sum()) < MIN_FIT_VOXELS:
        return ViewModel(1.0, (1.0, 0.0), (0.0, 1.0), voxels, 0, 0.0, fitted=False)
    kf, nf = k.astype(np.float64), n.astype(np.float64)
    lb = _log_binom(kf, nf)
    x0 = np.log([1.0, 4.0, 1.0, 1.0, 3.0])  # a fixed start: pi 0.5, mean shares 0.8 and 0.25
    bounds = [(-12.0, 12.0)] + [(-_LOG_BOUND, _LOG_BOUND)] * 4
    r = minimize(_neg_log_likelihood, x0, args=(kf, nf, w, lb, float(voxels)), jac=True, method="L-BFGS-B",
                 bounds=bounds, options={"maxiter": _MAX_ITER, "ftol": 1e-13, "gtol": 1e-9})
    x = r.x
    pi = float(1.0 / (1.0 + np.exp(-x[0])))
    surf, water = (float(np.exp(x[1])), float(np.exp(x[2]))), (float(np.exp(x[3])), float(np.exp(x[4])))
    it, ll = int(r.nit), -float(r.fun)
    if surf[0] / (surf[0] + surf[1]) < water[0] / (water[0] + water[1]):  # the brighter class is surface
        pi, surf, water = 1.0 - pi, water, surf
    return ViewModel(pi, surf, water, voxels, it, ll)


def surface_log_odds(model: ViewModel, k: np.ndarray, n: np.ndarray) -> np.ndarray:
    """log P(surface | k, n) / P(water | k, n) of an ever-bright voxel (``k >= 1``) under ``model``,
    float64."""
    kf, nf = np.asarray(k, np.float64), np.asarray(n, np.float64)
    lb = _log_binom(kf, nf)
    return (np.log(model.pi) - np.log1p(-model.pi) + _bb_terms(kf, nf, *model.surface, lb)[0]
            - _bb_terms(kf, nf, *model.water, lb)[0])


def calibrated_occupied(dark: np.ndarray, hits: np.ndarray, miss_cost: float,
                        model: ViewModel | None = None) -> np.ndarray:
    """The calibrated decision (module docstring): bool of ``hits``'s shape, True where a voxel is
    occupied: ever bright, and its posterior of being surface under ``model`` (default: fitted to
    these counts) at least ``1 / (1 + miss_cost)``, made monotone in ``k`` at equal ``n``."""
    h = np.asarray(hits)
    out = h > 0
    idx, k, n, w, inverse = _pairs(dark, hits)  # pairs sorted by (n, k)
    model = _fit(k, n, w) if model is None else model
    if not model.fitted:
        return out
    keep = surface_log_odds(model, k, n) >= -np.log(miss_cost)
    # monotone in k at equal n: a pair is kept when it, or a pair of the same n with fewer bright views, is
    start = np.r_[0, np.flatnonzero(np.diff(n)) + 1]
    csum = np.cumsum(keep)
    before = np.repeat(np.r_[0, csum[start[1:] - 1]], np.diff(np.r_[start, n.size]))
    out.reshape(-1)[idx] = ((csum - before) > 0)[inverse]
    return out


#: How many phantom voxels one avoided miss is worth, by default (was gpumap.geometry.MISS_COST).
MISS_COST = 10.0


def calibrated_values(grid: np.ndarray, bright: np.ndarray, count: np.ndarray, miss_cost: float
                      ) -> np.ndarray:
    """Map values of the evidence rule with the calibrated decision (this module's view model fitted to
    these counts): ``bright`` where a voxel is occupied, else ``grid``. The model is fitted
    to the ever-bright voxels only, which are the ones ``_bright_where`` hands over."""
    from gpumap.reference import _bright_where, split_counts

    return _bright_where(grid, bright, count, lambda c: calibrated_occupied(*split_counts(c), miss_cost))
