"""The evidence rule's calibrated decision (gpumap.bench.experiments.calibration) against independent
references.

References: counts drawn from known beta-binomial mixtures (the fit must recover what generated
them), the posterior written out with scipy.stats.betabinom and Bayes' rule, and hand-made noise-free
and noisy count patterns whose right answer is plain.
"""

from __future__ import annotations

import numpy as np
import pytest
from gpumap.bench.experiments.calibration import (
    MIN_FIT_VOXELS,
    ViewModel,
    calibrated_occupied,
    fit_view_model,
)
from scipy.stats import betabinom

from gpumap.reference import pack_counts, split_counts


def _draw(rng, m, pi, surf, water, n_lo=3, n_hi=60):
    """``m`` voxels: n uniform in [n_lo, n_hi], class surface with probability pi; k ~ BB(n, class)."""
    n = rng.integers(n_lo, n_hi + 1, m)
    is_s = rng.random(m) < pi
    p = np.where(is_s, rng.beta(*surf, m), rng.beta(*water, m))
    k = rng.binomial(n, p)
    return (n - k).astype(np.uint32), k.astype(np.uint32), is_s


@pytest.mark.parametrize("pi, surf, water", [(0.3, (8.0, 1.5), (1.0, 4.0)), (0.6, (20.0, 1.0), (2.0, 3.0))])
def test_fit_recovers_the_mixture_that_generated_the_counts(pi, surf, water):
    rng = np.random.default_rng(7)
    dark, hits, _ = _draw(rng, 60_000, pi, surf, water)
    m = fit_view_model(dark, hits)
    # only ever-bright voxels are modelled: the generating weight among them
    keep = hits > 0
    n = (dark + hits).astype(float)  # n does not depend on the class: its mean over every voxel
    ps = np.mean(1 - betabinom.pmf(0, n, *surf))
    pw = np.mean(1 - betabinom.pmf(0, n, *water))
    pi_bright = pi * ps / (pi * ps + (1 - pi) * pw)
    assert m.fitted and m.voxels == int(keep.sum())
    assert m.pi == pytest.approx(pi_bright, abs=0.03)
    assert m.surface_mean_share == pytest.approx(surf[0] / sum(surf), abs=0.02)
    assert m.water_mean_share == pytest.approx(water[0] / sum(water), abs=0.03)
    assert m.surface[0] == pytest.approx(surf[0], rel=0.25)
    assert m.water[1] == pytest.approx(water[1], rel=0.25)


def _bayes(model: ViewModel, k, n):
    """P(surface | k, n, k >= 1): each class's pmf truncated to k >= 1."""
    ps = model.pi * betabinom.pmf(k, n, *model.surface) / betabinom.sf(0, n, *model.surface)
    pw = (1 - model.pi) * betabinom.pmf(k, n, *model.water) / betabinom.sf(0, n, *model.water)
    return ps / (ps + pw)


@pytest.mark.parametrize("cost", [0.5, 3.0, 10.0, 1000.0])
@pytest.mark.parametrize("model", [ViewModel(0.4, (6.0, 1.0), (1.0, 2.5), 0, 0, 0.0),
                                   # water U-shaped, surfaces mid-share: the posterior is not monotone in k
                                   ViewModel(0.5, (20.0, 20.0), (0.3, 0.3), 0, 0, 0.0)])
def test_decision_is_the_bayes_posterior_against_the_cost(cost, model):
    """Occupied exactly where P(surface | k, n) >= 1 / (1 + cost) (scipy's pmf, Bayes' rule), or where
    a pair of the same n with fewer bright views is."""
    n = np.repeat(np.arange(1, 40), np.arange(1, 40))  # every (k, n) with 1 <= k <= n < 40
    k = np.concatenate([np.arange(1, j + 1) for j in range(1, 40)])
    post = _bayes(model, k, n)
    raw = post >= 1 / (1 + cost)
    want = np.array([raw[(n == nn) & (k <= kk)].any() for kk, nn in zip(k, n, strict=True)])
    got = calibrated_occupied((n - k).astype(np.uint32), k.astype(np.uint32), cost, model)
    np.testing.assert_array_equal(got, want)
    assert want.any() and not want.all()
    if model.water == (0.3, 0.3) and cost < 100:  # the monotone closure keeps what the posterior alone frees
        assert (want & ~raw).any()


def test_decision_is_monotone_in_bright_views_and_in_the_cost():
    rng = np.random.default_rng(3)
    dark, hits, _ = _draw(rng, 20_000, 0.4, (5.0, 2.0), (2.0, 3.0))
    model = fit_view_model(dark, hits)
    occ = {c: calibrated_occupied(dark, hits, c, model) for c in (0.1, 1.0, 10.0, 100.0)}
    for lo, hi in zip((0.1, 1.0, 10.0), (1.0, 10.0, 100.0), strict=True):
        assert np.all(occ[hi] >= occ[lo])  # a larger miss cost never frees a voxel
    assert occ[100.0].sum() > occ[0.1].sum()
    n = dark.astype(np.int64) + hits
    for c, o in occ.items():  # at equal n, a kept k keeps every larger k
        for nn in (10, 30, 50):
            ks = np.unique(hits[(n == nn) & o])
            lost = np.unique(hits[(n == nn) & (hits > 0) & ~o])
            if ks.size and lost.size:
                assert lost.max() < ks.min(), (c, nn)


def test_noise_free_views_carve_the_stretch_and_keep_every_surface():
    """Surfaces bright in every view; the stretch bright in some views and clear-dark in others: the
    fit learns that a surface is never dark, and two dark views carve a voxel."""
    rng = np.random.default_rng(11)
    n_s = rng.integers(2, 40, 3000)
    surf_dark, surf_hits = np.zeros(3000, np.uint32), n_s.astype(np.uint32)
    n_w = rng.integers(3, 40, 6000)
    k_w = np.maximum(1, rng.binomial(n_w, rng.beta(2.0, 2.0, 6000))).clip(max=n_w - 2)
    dark = np.r_[surf_dark, (n_w - k_w).astype(np.uint32)]
    hits = np.r_[surf_hits, k_w.astype(np.uint32)]
    occ = calibrated_occupied(dark, hits, 10.0)
    assert occ[:3000].all()
    assert occ[3000:].mean() < 0.01
    model = fit_view_model(dark, hits)
    assert model.surface_mean_share > 0.99


def test_little_evidence_keeps_every_bright_voxel():
    """Fewer than MIN_FIT_VOXELS ever-bright voxels with a clear dark view: no fit, all kept."""
    m = MIN_FIT_VOXELS - 1
    dark = np.r_[np.ones(m, np.uint32) * 9, np.zeros(500, np.uint32), np.ones(20, np.uint32)]
    hits = np.r_[np.ones(m, np.uint32), np.ones(500, np.uint32) * 5, np.zeros(20, np.uint32)]
    model = fit_view_model(dark, hits)
    assert not model.fitted
    np.testing.assert_array_equal(calibrated_occupied(dark, hits, 1.0), hits > 0)


def test_fit_does_not_depend_on_voxel_order_or_shape():
    rng = np.random.default_rng(5)
    dark, hits, _ = _draw(rng, 5000, 0.5, (6.0, 1.0), (1.0, 3.0))
    perm = rng.permutation(dark.size)
    a = calibrated_occupied(dark, hits, 5.0)
    b = calibrated_occupied(dark[perm].reshape(50, 100), hits[perm].reshape(50, 100), 5.0)
    np.testing.assert_array_equal(a[perm].reshape(50, 100), b)


def test_counts_round_trip_through_the_packed_state():
    rng = np.random.default_rng(0)
    dark, hits, _ = _draw(rng, 2000, 0.5, (6.0, 1.0), (1.0, 3.0))
    d2, h2 = split_counts(pack_counts(dark, hits))
    np.testing.assert_array_equal(calibrated_occupied(d2, h2, 4.0), calibrated_occupied(dark, hits, 4.0))
