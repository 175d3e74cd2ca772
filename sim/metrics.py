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

Against what the sonar could detect (``detectable``: voxels holding a visible surface
point whose *noise-free* image cell reaches the threshold in some ping,
:func:`~.truth.ground_truth_masks`; ``seen`` stands in when it is not given). A seen
surface can be too faint to detect (grazing sand, far, off-axis); a detectable one was
bright in at least one view, so mapping it free is the mapper's doing (for min-max: an
acoustic shadow in another view carving it):

- **false-negative rate (detectable)**: of the occupied, detectable voxels the map
  observed, the fraction called free; ``..._objects_detectable`` restricted to the small
  objects (:attr:`~.truth.Truth.small_objects`, not sand or walls).
- **miss rate**: of the occupied, detectable voxels, observed or not, the fraction *not*
  called occupied (unknown counts as missed, so a map that leaves obstacles unknown
  cannot score well); ``miss_rate_objects`` restricted to the small objects.
- **observed surface fraction**: of the seen voxels, the fraction the map observed.
- **miss rate by object**: the miss rate of each named part of the truth (sand, walls, each
  object) on its own (:func:`miss_by_object`; the demo's ``errors_by_object.png`` draws it).
- **phantom voxels** (:func:`phantom_far`): the voxels the false-positive rate (far) counts,
  free voxels more than one voxel from any occupied one that the map calls occupied.

:func:`fn_fp_curve` sweeps the threshold over a fixed map for an FN-vs-FP plot.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np
from scipy import ndimage

from .truth import Truth, ground_truth_masks

__all__ = ["Evaluation", "evaluate", "fn_fp_curve", "ground_truth_masks", "miss_by_object", "phantom_far"]


@dataclass
class Evaluation:
    """Scores of one map (see the module docstring for each definition); rates are NaN
    when their denominator is empty."""

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
    false_negative_rate_detectable: float = float("nan")
    false_negative_rate_objects_detectable: float = float("nan")
    miss_rate: float = float("nan")
    miss_rate_objects: float = float("nan")
    observed_surface_fraction: float = float("nan")
    miss_rate_by_object: dict[str, float] = field(default_factory=dict)

    def to_dict(self) -> dict:
        return asdict(self)


def _rate(num: np.ndarray, den: np.ndarray) -> float:
    d = int(den.sum())
    return float((num & den).sum() / d) if d else float("nan")


def _mask_arg(m: np.ndarray | None, shape: tuple[int, ...], name: str) -> np.ndarray | None:
    if m is None:
        return None
    m = np.asarray(m)
    if m.shape != shape or m.dtype != bool:
        raise ValueError(f"Expected a bool array of shape {shape} for {name!r}, but got {m.dtype} {m.shape}")
    return m


def _maps(values: np.ndarray, threshold: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(observed, called occupied, called free) masks of a map."""
    obs = ~np.isnan(values)
    occ_map = obs & (np.nan_to_num(values, nan=-np.inf) >= threshold)
    return obs, occ_map, obs & ~occ_map


def evaluate(
    values: np.ndarray,
    truth: Truth,
    threshold: float,
    seen: np.ndarray | None = None,
    voxel_size_m: float = 1.0,
    objects: tuple[str, ...] | None = None,
    pipe_axis: tuple[np.ndarray, np.ndarray] | None = None,
    detectable: np.ndarray | None = None,
) -> Evaluation:
    """Score map ``values`` ((nx, ny, nz) float32, NaN unknown) against ``truth``.

    Parameters
    ----------
    seen : (nx, ny, nz) bool, optional
        Voxels holding a visible surface point of some ping (default: every surface voxel).
    voxel_size_m : float
        For height errors in metres.
    objects : tuple of str, optional
        Names of the obstacles for the "objects" rates, recalls and height errors
        (default: ``truth.small_objects``).
    pipe_axis : ((3,), (3,)) voxel-index coordinates of the pipe's ends, optional
        Used to split the pipe into segments; without it the pipe's longest box axis is used.
    detectable : (nx, ny, nz) bool, optional
        Voxels holding a surface point some ping could detect above the threshold
        (:func:`~.truth.ground_truth_masks`); default: ``seen``.
    """
    v = np.asarray(values)
    if v.shape != truth.occupied.shape:
        raise ValueError(f"Expected values of shape {truth.occupied.shape}, but got {v.shape}")
    shape = truth.occupied.shape
    seen = _mask_arg(seen, shape, "seen")
    detectable = _mask_arg(detectable, shape, "detectable")
    objects = truth.small_objects if objects is None else tuple(objects)
    obs, occ_map, free_map = _maps(v, threshold)
    T = truth.occupied
    seen = truth.surface if seen is None else seen
    det = seen if detectable is None else detectable
    near = ndimage.binary_dilation(T, structure=np.ones((3, 3, 3), bool))
    fn = _rate(free_map, T & seen & obs)
    fn_all = _rate(free_map, T & obs)
    small = truth.objects_mask(objects)
    fn_obj = _rate(free_map, T & seen & obs & small)
    fp = _rate(occ_map, ~T & obs)
    fp_far = _rate(occ_map, ~near & obs)  # = phantom_far(...).sum() / (~near & obs).sum()
    water = ~T & _water_mask(truth)
    carved = _rate(free_map, water)
    fn_det = _rate(free_map, T & det & obs)
    fn_obj_det = _rate(free_map, T & det & obs & small)
    miss = _rate(~occ_map, T & det)
    miss_obj = _rate(~occ_map, T & det & small)
    obs_surface = _rate(obs, seen)

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
    by_object = {n: m / d for n, (m, d) in miss_by_object(v, truth, threshold, det).items()}
    return Evaluation(threshold, float(obs.mean()), fn, fn_all, fn_obj, fp, fp_far, carved, heights, recall,
                      pipe_found, seg, fn_det, fn_obj_det, miss, miss_obj, obs_surface, by_object)


def miss_by_object(
    values: np.ndarray, truth: Truth, threshold: float, detectable: np.ndarray
) -> dict[str, tuple[int, int]]:
    """The miss rate's counts per named part of the truth: name -> (missed, detectable).

    ``detectable`` (nx, ny, nz) bool as in :func:`evaluate`; a detectable occupied voxel of the
    part is missed when the map does not call it occupied (free, or never observed). Parts
    with no detectable voxel are left out.
    """
    _, occ_map, _ = _maps(np.asarray(values), threshold)
    out = {}
    for i, name in enumerate(truth.names):
        d = truth.occupied & detectable & (truth.label == i)
        n = int(d.sum())
        if n:
            out[name] = (int((d & ~occ_map).sum()), n)
    return out


def phantom_far(values: np.ndarray, truth: Truth, threshold: float) -> np.ndarray:
    """(nx, ny, nz) bool: the voxels the false-positive rate (far) counts as wrong, free voxels
    more than one voxel from any occupied one that the map calls occupied."""
    _, occ_map, _ = _maps(np.asarray(values), threshold)
    near = ndimage.binary_dilation(truth.occupied, structure=np.ones((3, 3, 3), bool))
    return occ_map & ~near


def fn_fp_curve(
    values: np.ndarray,
    truth: Truth,
    thresholds: np.ndarray,
    seen: np.ndarray | None = None,
    detectable: np.ndarray | None = None,
    objects: tuple[str, ...] | None = None,
) -> dict[str, np.ndarray]:
    """False negatives against false positives of one map as the occupied threshold moves.

    Parameters
    ----------
    values : (nx, ny, nz) float
        The map, NaN unknown.
    truth : Truth
    thresholds : (t,) float
    seen, detectable, objects
        As in :func:`evaluate` (same defaults).

    Returns
    -------
    dict of str -> (t,) float64
        ``threshold``, ``false_negative_rate_detectable``, ``false_negative_rate_all``,
        ``false_negative_rate_objects_detectable``, ``false_positive_rate_far``,
        ``miss_rate`` and ``miss_rate_objects``, each as :func:`evaluate` defines it at that
        threshold.
    """
    v = np.asarray(values)
    if v.shape != truth.occupied.shape:
        raise ValueError(f"Expected values of shape {truth.occupied.shape}, but got {v.shape}")
    th = np.asarray(thresholds, np.float64).reshape(-1)
    shape = truth.occupied.shape
    seen = _mask_arg(seen, shape, "seen")
    detectable = _mask_arg(detectable, shape, "detectable")
    T = truth.occupied
    seen = truth.surface if seen is None else seen
    det = seen if detectable is None else detectable
    small = truth.objects_mask(objects)
    near = ndimage.binary_dilation(T, structure=np.ones((3, 3, 3), bool))
    obs = ~np.isnan(v)
    # Only the voxels some rate counts matter: gather them once, sweep the threshold on those.
    den = {
        "false_negative_rate_detectable": T & det & obs,
        "false_negative_rate_all": T & obs,
        "false_negative_rate_objects_detectable": T & det & obs & small,
        "false_positive_rate_far": ~near & obs,
        "miss_rate": T & det,
        "miss_rate_objects": T & det & small,
    }
    out = {"threshold": th}
    for key, m in den.items():
        x = np.nan_to_num(v[m], nan=-np.inf)  # unknown is never called occupied
        n = x.size
        # Compared as evaluate() compares (the map's dtype against a Python float).
        n_occ = np.array([np.count_nonzero(x >= float(t)) for t in th], np.float64)
        counted = n_occ if key == "false_positive_rate_far" else n - n_occ
        out[key] = counted / n if n else np.full(th.shape, np.nan)
    return out


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
