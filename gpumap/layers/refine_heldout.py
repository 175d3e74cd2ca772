"""Held-out prediction: a map rendered at pings it was not fitted on (:func:`render_map`), and
how well it predicts their bright cells (:func:`heldout_scores`, :func:`roc_auc`); ``bench.refine``
scores the plain, visible and refined maps with them.
"""

from __future__ import annotations

import math
import warnings

import numpy as np

from gpumap.layers.refine_fit import _calibrate
from gpumap.layers.render import PingRenderer

__all__ = ["heldout_scores", "render_map", "roc_auc"]


def roc_auc(score: np.ndarray, label: np.ndarray) -> float:
    """Area under the ROC curve of ``score`` for boolean ``label`` (ties count half); NaN if one class."""
    s = np.asarray(score, np.float64).ravel()
    y = np.asarray(label, bool).ravel()
    n1, n0 = int(y.sum()), int((~y).sum())
    if n1 == 0 or n0 == 0:
        return float("nan")
    from scipy.stats import rankdata

    ranks = rankdata(s)
    return float((ranks[y].sum() - n1 * (n1 + 1) / 2) / (n1 * n0))


def render_map(
    renderer: PingRenderer,
    field: np.ndarray | None = None,
    poses: np.ndarray | None = None,
    *,
    reflectivity=None,
    train_images: np.ndarray | None = None,
    train_poses: np.ndarray | None = None,
    gain: float | None = None,
    floor: float | None = None,
    delta: float = 0.1,
    occupancy: np.ndarray | None = None,
) -> tuple[np.ndarray, float, float]:
    """Rendered images of a map at ``poses``: ``(images, gain, floor)``.

    ``field`` (nx, ny, nz) float in [0, 1], NaN unknown (rendered empty): the field ``o`` the
    renderer takes, e.g. :attr:`~gpumap.layers.refine.RefineResult.field`, or a 0/1 map. Not
    :attr:`~gpumap.layers.refine.RefineResult.occupancy` (``1 - exp(-kappa o)``, a probability):
    :func:`~gpumap.layers.refine.field_from_occupancy` converts. ``occupancy=`` is the former name of
    ``field`` (same meaning, deprecated). Without ``gain`` the display gain and floor are fitted
    on ``train_images`` / ``train_poses`` (as :func:`~gpumap.layers.refine.refine` calibrates), so every
    map is compared at its own best scale.
    """
    if occupancy is not None:
        if field is not None:
            raise TypeError("Expected 'field' or its former name 'occupancy', but got both")
        warnings.warn("render_map(occupancy=...) is deprecated: the argument is the field o "
                      "(RefineResult.field), pass it as field=", DeprecationWarning, stacklevel=2)
        field = occupancy
    if field is None or poses is None:
        raise TypeError("Expected 'field' and 'poses' for render_map, but got None")
    occ = np.nan_to_num(np.asarray(field, np.float32), nan=0.0)
    refl = (
        np.full(occ.shape, 0.5, np.float32) if reflectivity is None else np.asarray(reflectivity, np.float32)
    )
    if gain is None:
        if train_images is None or train_poses is None:
            raise ValueError("Expected train_images and train_poses to fit the gain, but got None")
        lg, floor = _calibrate(
            renderer,
            occ,
            refl,
            renderer.coarsen(train_images),
            PingRenderer._check_poses(train_poses),
            delta,
            n=16,
        )
        gain = math.exp(lg)
    return renderer.render(occ, refl, poses, gain, floor or 0.0), float(gain), float(floor or 0.0)


def heldout_scores(predicted: np.ndarray, measured: np.ndarray, threshold: float) -> dict[str, float]:
    """Bright-cell prediction of held-out pings: ``roc_auc`` of the rendered intensity for the
    cells whose measured (cell-averaged) intensity is ``>= threshold``, the Pearson
    ``correlation`` of rendered and measured intensities, and the ``bright_fraction``."""
    p = np.asarray(predicted, np.float64).ravel()
    m = np.asarray(measured, np.float64).ravel()
    y = m >= threshold
    corr = float(np.corrcoef(p, m)[0, 1]) if p.std() > 0 and m.std() > 0 else float("nan")
    return {"roc_auc": roc_auc(p, y), "correlation": corr, "bright_fraction": float(y.mean())}

