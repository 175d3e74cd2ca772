"""Adaptive detection (gpumap.bench.experiments.detection) against a row-by-row loop written from
its definition."""

from __future__ import annotations

import numpy as np
import pytest
from gpumap.bench.experiments.detection import adaptive_detect


def _loop(img, empty, window, z):
    img = img.astype(np.float64)
    mu0, s0 = img[:empty].mean(), img[:empty].std()
    out = np.zeros(img.shape, np.float32)
    for r in range(img.shape[0]):
        if img[r].max() <= mu0 + 2 * s0:
            continue
        win = img[max(0, r - window):min(img.shape[0], r + window)]
        mu, s = max(win.mean(), mu0), max(win.std(), s0)
        out[r] = ((img[r] - mu) / s >= z) if s > 0 else 0.0
    return out


@pytest.mark.parametrize("seed, empty, window, z", [(0, 10, 20, 1.0), (1, 4, 3, 2.5), (2, 30, 1, 0.5)])
def test_detections_equal_the_row_loop(seed, empty, window, z):
    rng = np.random.default_rng(seed)
    img = rng.gamma(1.0, 0.05, (120, 64)).astype(np.float32)
    img[60:63, 10:20] += 0.8  # a return
    img[90, :] += 0.3  # a bright row (ringing)
    got = adaptive_detect(img, empty, window, z)
    np.testing.assert_array_equal(got, _loop(img, empty, window, z))
    assert got[60:63, 10:20].all() and got.dtype == np.float32


def test_a_ping_of_background_only_holds_no_detection():
    rng = np.random.default_rng(4)
    img = np.full((50, 20), 0.02, np.float32) + rng.uniform(0, 1e-3, (50, 20)).astype(np.float32)
    img[:10] = rng.uniform(0.0, 0.04, (10, 20))  # the background's spread covers every later row
    assert not adaptive_detect(img, 10, 5, 1.0).any()


@pytest.mark.parametrize("kw, match", [({"empty_bins": 1}, "empty_bins"), ({"window_bins": 0}, "window_bins"),
                                       ({"z": float("nan")}, "finite z")])
def test_bad_settings_say_what_was_expected(kw, match):
    with pytest.raises(ValueError, match=match):
        adaptive_detect(np.zeros((20, 4)), **kw)
    with pytest.raises(ValueError, match="2-D polar image"):
        adaptive_detect(np.zeros(20))
