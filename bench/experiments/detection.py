"""Detection that adapts to the ping: per-range normalisation with a background floor.

A fixed intensity threshold asks every range of every ping to be equally bright: gain, spreading
loss and ringing near strong returns change that from ping to ping and from range to range. This
detector decides per range bin (row of the polar image) instead, after the scheme of the OASIS
reconstruction's preprocessing (Phung et al.'s public code; re-implemented here from its
description, vectorised):

1. the background: mean ``mu_0`` and standard deviation ``s_0`` of the first ``empty_bins`` rows
   (the water right in front of the sonar, assumed empty);
2. a row is searched only when its maximum exceeds ``mu_0 + 2 s_0`` (else it holds no detection);
3. in a searched row, a cell is a detection when ``(I - mu) / s >= z``, where ``mu`` and ``s`` are
   the mean and standard deviation of the rows within ``window_bins`` of it (the window
   ``[r - window_bins, r + window_bins)``, clipped to the image), floored at the background's.

The result is a polar image of the same shape: 1.0 at detections, 0.0 elsewhere, so a map fed
with it is occupied at any threshold in (0, 1]. It runs at the I/O edge, before the mapper, so
every backend maps the same detections; ``python -m bench decision`` measures it against the
fixed threshold on the real run.
"""

from __future__ import annotations

import numpy as np

__all__ = ["adaptive_detect"]


def adaptive_detect(image: np.ndarray, empty_bins: int = 10, window_bins: int = 20,
                    z: float = 1.0) -> np.ndarray:
    """Per-range adaptive detection of one polar image (module docstring).

    Parameters
    ----------
    image : (n_bins, n_beams) float array
        Intensities (any scale: the test is on standard scores).
    empty_bins : int
        Rows at the near end that hold background only, >= 2.
    window_bins : int
        Half-height of the window of rows whose statistics normalise a row, >= 1.
    z : float
        Standard scores at or above which a cell is a detection.

    Returns
    -------
    (n_bins, n_beams) float32
        1.0 at detections, else 0.0.
    """
    img = np.asarray(image, dtype=np.float64)
    if img.ndim != 2:
        raise ValueError(f"Expected a 2-D polar image (n_bins, n_beams) for 'image', but got shape "
                         f"{img.shape}")
    n_bins, n_beams = img.shape
    if not 2 <= int(empty_bins) <= n_bins:
        raise ValueError(f"Expected empty_bins in [2, {n_bins}], but got {empty_bins}")
    if int(window_bins) < 1:
        raise ValueError(f"Expected window_bins >= 1, but got {window_bins}")
    if not np.isfinite(z):
        raise ValueError(f"Expected a finite z, but got {z}")
    bg = img[:empty_bins]
    mu0, s0 = bg.mean(), bg.std()
    # window sums over rows by prefix sums: rows [r - w, r + w) clipped, every cell of them
    row_sum, row_sq = img.sum(1), (img * img).sum(1)
    c1, c2 = np.r_[0.0, np.cumsum(row_sum)], np.r_[0.0, np.cumsum(row_sq)]
    r = np.arange(n_bins)
    lo, hi = np.maximum(0, r - window_bins), np.minimum(n_bins, r + window_bins)
    cells = (hi - lo) * n_beams
    mu = (c1[hi] - c1[lo]) / cells
    var = np.maximum((c2[hi] - c2[lo]) / cells - mu * mu, 0.0)
    mu, s = np.maximum(mu, mu0), np.maximum(np.sqrt(var), s0)
    searched = img.max(1) > mu0 + 2.0 * s0
    hit = (img - mu[:, None]) >= z * s[:, None]
    if s0 == 0.0:  # a flat background: the floor would divide by zero; standard scores need s > 0
        hit &= s[:, None] > 0.0
    return (hit & searched[:, None]).astype(np.float32)
