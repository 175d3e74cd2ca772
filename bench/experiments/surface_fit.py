"""``python -m bench.experiments.surface_fit``: the generative surface fit (issue 43) against the evidence
map and the surface layer, on the simulated tank and circle (3 cm, true poses, 40 pings as ``gpumap demo
--pings 40`` picks them, with and without the real tank's variation).

Scores against the simulator's truth (:func:`surface_scores`): precision, recall and F at one and two
voxels (Chebyshev distance between voxel centres; precision against every true surface voxel, recall of
the *observed* true surface: surface voxels holding a point some ping could detect, as
:func:`gpumap.sim.truth.ground_truth_masks` finds them), Chamfer-L1 (the mean of the two mean nearest
distances, metres), recall of the small objects' observed surface at one voxel, object tops (map top minus
true top over the object's columns, voxels: :func:`gpumap.sim.metrics.evaluate`), and the safe map's miss
rate of the objects.

Held out: every map is also built from the even pings alone and rendered at the odd ones with the
project's ping model (:func:`gpumap.refine_heldout.render_map`, display gain and floor fitted on the even
pings); the rms against the odd pings' coarse cells is compared with the true surface's and an empty map's.

Pings are simulated once per case and cached in ``/tmp/gpumap_surface_fit`` (``--cache``)::

    python -m bench.experiments.surface_fit                     # tank and circle, none and real_tank
    python -m bench.experiments.surface_fit --scenes tank --variations none --no-heldout
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np

from bench.common import load_average, machine_info, write_json

VOXEL_M = 0.03
N_PINGS = 40
SEED = 0
CACHE = Path("/tmp/gpumap_surface_fit")


# ------------------------------------------------------------------------------ the case
def _case(scene_name: str, variation: str, cache: Path, n_pings: int = N_PINGS) -> dict:
    """Scene, truth, pings (images float32, true poses) and the seen / detectable masks; the pings and
    masks from ``cache`` when there (simulated as ``gpumap demo --pings`` selects and renders them)."""
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    from gpumap.sim.demo import VARIATIONS
    from gpumap.sim.scenes import make_scene
    from gpumap.sim.sonar import OCCUPIED_THRESHOLD, SonarSimulator
    from gpumap.sim.truth import ground_truth_masks, occupancy

    scene = make_scene(scene_name, voxel_size_m=VOXEL_M, seed=SEED)
    n = len(scene.T_W_S)
    sel = np.unique(np.linspace(0, n - 1, min(n_pings, n)).round().astype(int))
    path = cache / f"{scene_name}_{variation}_{len(sel)}.npz"
    if path.exists():
        z = np.load(path)
        images, seen, det = z["images"], z["seen"], z["detectable"]
    else:
        with SonarSimulator(scene, seed=SEED, variation=VARIATIONS[variation](), **scene.sonar_params) as sim:
            pings = [sim.ping(scene.T_W_S[k], int(k)) for k in sel]
        images = np.stack([p.image for p in pings]).astype(np.float32)
        seen, det = ground_truth_masks(pings, scene.grid, OCCUPIED_THRESHOLD)
        cache.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(path, images=images, seen=seen, detectable=det)
    return {"scene": scene, "truth": occupancy(scene, seed=SEED), "images": images,
            "poses": scene.T_W_S[sel], "seen": seen, "detectable": det, "threshold": OCCUPIED_THRESHOLD,
            "select": sel}


def _mapper(case: dict, pick: np.ndarray, backend: str):
    """The evidence map of the pings ``pick`` (as the demo builds and feeds it)."""
    from gpumap.sim.demo import build_mapper

    m = build_mapper(case["scene"], backend, "gather", "evidence", case["threshold"])
    for k in pick:
        m.integrate(case["images"][k], case["poses"][k])
    m.synchronize()
    return m


# ------------------------------------------------------------------------------ scores
def surface_scores(pred: np.ndarray, case: dict) -> dict:
    """Scores of a binary surface ``pred`` ((nx, ny, nz) bool) against the case's truth.

    The target is the issue's: the true surface voxels the safe map of every ping observed
    (``case["observed"]``). Precision: the share of ``pred`` within ``k`` voxels (Euclidean, between
    centres) of the target; recall: the share of the target within ``k`` voxels of ``pred``; F their
    harmonic mean (k = 1, 2). Chamfer-L1: the mean of the two mean nearest distances, metres. Object
    recall: the share of the small objects' target voxels within one voxel of ``pred``. Tops and the
    objects' miss rate: :func:`gpumap.sim.metrics.evaluate` of ``pred`` as a 1 / 0 map."""
    from scipy import ndimage

    from gpumap.sim.metrics import evaluate

    truth, h = case["truth"], case["scene"].grid.voxel_size_m
    target = truth.surface & case["observed"]
    out: dict = {"voxels": int(pred.sum()), "target_voxels": int(target.sum())}
    d_target = ndimage.distance_transform_edt(~target)
    d_pred = ndimage.distance_transform_edt(~pred) if pred.any() else np.full(pred.shape, np.inf)
    for k in (1, 2):
        p = float((d_target[pred] <= k).mean()) if pred.any() else 0.0
        r = float((d_pred[target] <= k).mean())
        out[f"precision_{k}"], out[f"recall_{k}"] = p, r
        out[f"f_{k}"] = 2 * p * r / (p + r) if p + r > 0 else 0.0
    out["chamfer_m"] = float(0.5 * (d_target[pred].mean() + d_pred[target].mean()) * h) if pred.any() \
        else float("nan")
    # the surface some ping's ray hit (seen), and of it what a ping could detect: recall of those, precision
    # against every true surface voxel (a claim on a true surface no ping saw is no phantom)
    d_surf = ndimage.distance_transform_edt(~truth.surface)
    p_all = float((d_surf[pred] <= 1).mean()) if pred.any() else 0.0
    out["precision_any_1"] = p_all
    for name, t in (("seen", truth.surface & case["seen"]), ("detectable", truth.surface & case["detectable"])):
        r = float((d_pred[t] <= 1).mean())
        out[f"recall_{name}_1"] = r
        out[f"f_{name}_1"] = 2 * p_all * r / (p_all + r) if p_all + r > 0 else 0.0
    by, hit, n = {}, 0, 0
    for name in truth.small_objects:
        if name in truth.names:
            m = truth.mask(name) & target
            by[name] = float((d_pred[m] <= 1).mean()) if m.any() else float("nan")
            hit, n = hit + int((d_pred[m] <= 1).sum()), n + int(m.sum())
    out["object_recall_1"] = hit / max(1, n)
    out["object_recall_1_by_object"] = by
    values = np.where(case["observed"], 0.0, np.nan).astype(np.float32)
    values[pred] = 1.0
    ev = evaluate(values, truth, 0.5, case["seen"], h, detectable=case["detectable"]).to_dict()
    out["top_error_voxels"] = {k: v / h for k, v in ev["height_error_m"].items()}
    out["miss_rate_objects"] = ev["miss_rate_objects"]
    out["phantom_far_rate"] = ev["false_positive_rate_far"]
    return out
