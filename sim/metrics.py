"""Map quality against ground truth.

Definitions (``v`` the map's values, NaN = never observed; ``thr`` the occupied threshold):

- **observed**: ``~isnan(v)``.
- **false-negative rate**: of the truly occupied voxels that some ping actually saw (a
  visible surface point fell in them, :attr:`Evaluation.seen`) and the map observed, the
  fraction called free (``v < thr``). This is the safety number: a seen obstacle mapped as
  free. ``false_negative_rate_all`` uses every occupied voxel the map observed instead
  (it also counts insides of solids and surfaces hidden in every view, which no sonar can
  see). ``false_negative_rate_objects`` counts only the objects' voxels (not sand, walls).
- **false-positive rate**: of the truly free voxels the map observed, the fraction called
  occupied. ``false_positive_rate_far`` ignores free voxels within one voxel of an
  occupied one (discretisation at surfaces).
- **free carved**: fraction of the scene's water voxels (free in truth) that the map calls
  free: how far free space was carved.
- **height error** of an object: over the columns (x, y) of the object's truth voxels, the
  map's highest occupied voxel minus the truth's highest, averaged over the columns the
  map observed, metres. Positive = the elevation "stretch"; it shrinks as views add up.
- **pipe found**: the pipe's truth voxels are split along its axis into segments two
  voxels long; a segment is found if any of its voxels is called occupied; the pipe is
  found when at least 80 % of the segments that were seen are found.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy import ndimage

from .truth import Truth

__all__ = ["Evaluation", "evaluate"]


@dataclass
class Evaluation:
    threshold: float
    observed_fraction: float
    false_negative_rate: float
    false_negative_rate_all: float
    false_negative_rate_objects: float
    false_positive_rate: float
    false_positive_rate_far: float
    free_carved_fraction: float
    height_error_m: dict[str, float]
    object_recall: dict[str, float]
    pipe_found: bool | None
    pipe_segments_found: float | None

    def to_dict(self) -> dict:
        return asdict(self)


def _rate(num: np.ndarray, den: np.ndarray) -> float:
    d = int(den.sum())
    return float((num & den).sum() / d) if d else float("nan")


def evaluate(
    values: np.ndarray,
    truth: Truth,
    threshold: float,
    seen: np.ndarray | None = None,
    voxel_size_m: float = 1.0,
    objects: tuple[str, ...] = ("chain", "rock", "basket", "pipe"),
    pipe_axis: tuple[np.ndarray, np.ndarray] | None = None,
) -> Evaluation:
    """Score map ``values`` ((nx, ny, nz) float32, NaN unknown) against ``truth``.

    Parameters
    ----------
    seen : (nx, ny, nz) bool, optional
        Voxels holding a visible surface point of some ping (default: every surface voxel).
    voxel_size_m : float
        For height errors in metres.
    pipe_axis : ((3,), (3,)) voxel-index coordinates of the pipe's ends, optional
        Used to split the pipe into segments; without it the pipe's longest box axis is used.
    """
    v = np.asarray(values)
    if v.shape != truth.occupied.shape:
        raise ValueError(f"Expected values of shape {truth.occupied.shape}, but got {v.shape}")
    obs = ~np.isnan(v)
    occ_map = obs & (np.nan_to_num(v, nan=-np.inf) >= threshold)
    free_map = obs & ~occ_map
    T = truth.occupied
    seen = truth.surface if seen is None else seen
    near = ndimage.binary_dilation(T, structure=np.ones((3, 3, 3), bool))
    fn = _rate(free_map, T & seen & obs)
    fn_all = _rate(free_map, T & obs)
    small = np.isin(truth.label, [truth.names.index(n) for n in objects if n in truth.names])
    fn_obj = _rate(free_map, T & seen & obs & small)
    fp = _rate(occ_map, ~T & obs)
    fp_far = _rate(occ_map, ~near & obs)
    water = ~T & _water_mask(truth)
    carved = _rate(free_map, water)

    heights, recall = {}, {}
    for name in objects:
        if name not in truth.names:
            continue
        m = truth.mask(name)
        recall[name] = _rate(occ_map, m & seen & obs)
        heights[name] = _height_error(occ_map, obs, m, voxel_size_m)
    pipe_found, seg = None, None
    if "pipe" in truth.names:
        seg = _pipe_segments(occ_map, truth.mask("pipe") & seen & obs)
        pipe_found = bool(seg >= 0.8) if np.isfinite(seg) else False
    return Evaluation(threshold, float(obs.mean()), fn, fn_all, fn_obj, fp, fp_far, carved, heights, recall,
                      pipe_found, seg)


def _water_mask(truth: Truth) -> np.ndarray:
    """Voxels above the highest truth voxel of each column's lowest solid run: the water."""
    T = truth.occupied
    nz = T.shape[2]
    k = np.arange(nz)
    # The water is above the sand: the first occupied voxel from below starts the sand;
    # everything above its top surface, below the walls' rim, counts.
    sand = truth.names.index("sand") if "sand" in truth.names else None
    if sand is None:
        return np.ones_like(T)
    s = truth.label == sand
    top = np.where(s.any(2), nz - 1 - np.argmax(s[:, :, ::-1], axis=2), -1)
    return (k[None, None, :] > top[:, :, None]) & (top[:, :, None] >= 0)


def _height_error(occ_map: np.ndarray, obs: np.ndarray, m: np.ndarray, s: float) -> float:
    cols = m.any(2)
    if not cols.any():
        return float("nan")
    nz = m.shape[2]
    truth_top = nz - 1 - np.argmax(m[:, :, ::-1], axis=2)
    has = occ_map.any(2) & cols & obs.any(2)
    if not has.any():
        return float("nan")
    map_top = nz - 1 - np.argmax(occ_map[:, :, ::-1], axis=2)
    return float(np.mean(map_top[has] - truth_top[has]) * s)


def _pipe_segments(occ_map: np.ndarray, pipe: np.ndarray) -> float:
    idx = np.argwhere(pipe)
    if len(idx) == 0:
        return float("nan")
    c = idx.mean(0)
    u = np.linalg.svd(idx - c, full_matrices=False)[2][0]
    t = (idx - c) @ u
    seg = np.floor((t - t.min()) / 2.0).astype(int)
    hit = occ_map[tuple(idx.T)]
    found = np.zeros(seg.max() + 1, bool)
    present = np.zeros(seg.max() + 1, bool)
    present[seg] = True
    np.logical_or.at(found, seg, hit)
    return float(found[present].mean())
