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
project's ping model (:func:`gpumap.layers.refine_heldout.render_map`, gain and floor fitted on the even
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
    from gpumap.sim.metrics import evaluate
    from scipy import ndimage

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
    for name, t in (("seen", truth.surface & case["seen"]),
                    ("detectable", truth.surface & case["detectable"])):
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


# ------------------------------------------------------------------------------ the maps of one case
def _maps(case: dict, pick: np.ndarray, backend: str, options) -> tuple[dict, dict]:
    """The evidence map of the pings ``pick``, today's surface layer and the fit on the same map: binary
    surfaces by name, and their seconds and counts."""
    from gpumap.layers.surface_fit import fit_surface
    from gpumap.layers.surface_live import surface_from_mapper

    t0 = time.perf_counter()
    m = _mapper(case, pick, backend)
    v = m.values()
    maps = {"evidence": np.nan_to_num(v, nan=-np.inf) >= m.threshold}
    info = {"evidence": {"seconds": time.perf_counter() - t0, "backend": m.backend}}
    images, poses = case["images"][pick], case["poses"][pick]
    t0 = time.perf_counter()
    layer = surface_from_mapper(m, images, poses)
    maps["surface_layer"] = layer.surface
    info["surface_layer"] = {"seconds": time.perf_counter() - t0}
    t0 = time.perf_counter()
    fit = fit_surface(m, images, poses, options)
    maps["fit"] = fit.surface
    maps["fit_and_undecided"] = fit.surface | fit.undecided
    info["fit"] = {"seconds": time.perf_counter() - t0,
                   **{k: v for k, v in fit.stats.items() if k not in ("options", "seconds")}}
    return maps, {**info, "observed": np.isfinite(v), "fit_object": fit}


def _heldout(case: dict, backend: str, options) -> dict:
    """Maps of the even pings rendered at the odd ones (module docstring): rms over the coarse cells."""
    from gpumap.layers.refine_heldout import render_map
    from gpumap.layers.render import PingRenderer

    even, odd = np.arange(0, len(case["images"]), 2), np.arange(1, len(case["images"]), 2)
    maps, info = _maps(case, even, backend, options)
    maps = {**maps, "truth_surface": case["truth"].surface, "empty": np.zeros_like(case["truth"].surface)}
    sc = case["scene"]
    r = PingRenderer(sc.sonar_spec, sc.grid, device="cpu")
    measured = r.coarsen(case["images"][odd])
    out = {"pings_fitted": even.tolist(), "pings_judged": odd.tolist(),
           "fit_model": _model_heldout(case, info["fit_object"], odd)}
    for name, mask in maps.items():
        t0 = time.perf_counter()
        pred, gain, floor = render_map(r, mask.astype(np.float32), case["poses"][odd],
                                       train_images=case["images"][even], train_poses=case["poses"][even])
        out[name] = {"rms": float(np.sqrt(np.mean((pred - measured) ** 2))), "gain": gain, "floor": floor,
                     "voxels": int(mask.sum()), "render_seconds": time.perf_counter() - t0}
    return out


def _model_heldout(case: dict, fit, odd: np.ndarray) -> dict:
    """The fit as a model: its weights (fitted on the even pings) predict the odd pings' coarse cells
    through its own forward model (only a gain per judged ping is fitted, on that ping); rms of the
    intensity ``1 - exp(-y)`` over the cells its candidates reach, against the noise floor alone."""
    from gpumap.layers.surface_fit import FitOptions, _fit

    sc = case["scene"]
    opts = FitOptions(iterations=0)
    res = _fit(fit.candidates, sc.grid, sc.sonar_spec, case["images"][odd], case["poses"][odd],
               case["threshold"], opts)
    pk, A = res["pk"], res["A"]
    x = fit.weight[tuple(res["idx"].T)].astype(np.float64)
    sig = A @ x
    floor = pk.floor[pk.cell_ping]
    num = np.bincount(pk.cell_ping, weights=sig * np.maximum(pk.y - floor, 0.0), minlength=len(odd))
    den = np.bincount(pk.cell_ping, weights=sig * sig, minlength=len(odd))
    g = np.divide(num, den, out=np.zeros(len(odd)), where=den > 0)  # least squares gain per ping
    ok = ~pk.censored
    meas = 1.0 - np.exp(-pk.y[ok])
    pred = 1.0 - np.exp(-(g[pk.cell_ping] * sig + floor)[ok])
    empty = 1.0 - np.exp(-floor[ok])
    return {"rms": float(np.sqrt(np.mean((pred - meas) ** 2))),
            "rms_floor_only": float(np.sqrt(np.mean((empty - meas) ** 2))), "cells": int(ok.sum())}


def run_case(scene: str, variation: str, backend: str, cache: Path, heldout: bool, options=None) -> dict:
    """Every map of one case scored against the truth, and (``heldout``) on held-out pings."""
    from gpumap.layers.surface_fit import FitOptions

    options = options or FitOptions()
    load0 = load_average()
    t0 = time.perf_counter()
    case = _case(scene, variation, cache)
    row: dict = {"scene": scene, "variation": variation, "pings": len(case["images"]),
                 "voxel_size_m": VOXEL_M, "threshold": case["threshold"], "load_before": load0,
                 "case_seconds": time.perf_counter() - t0}
    maps, info = _maps(case, np.arange(len(case["images"])), backend, options)
    case["observed"] = info.pop("observed")
    fit = info.pop("fit_object")
    row["maps"] = {name: {**surface_scores(mask, case), **info.get(name, {})} for name, mask in maps.items()}
    row["maps"]["truth_seen_surface"] = surface_scores(case["truth"].surface & case["seen"], case)
    row["fit_sure_quantiles"] = [float(q) for q in np.nanquantile(fit.sure, [0.1, 0.25, 0.5, 0.75, 0.9])]
    if heldout:
        row["heldout"] = _heldout(case, backend, options)
    row["options"] = options.to_dict()
    row["load_after"] = load_average()
    return row


def _line(row: dict) -> str:
    parts = [f"{row['scene']} ({row['variation']}):"]
    for name, x in row["maps"].items():
        parts.append(f"  {name:20s} n {x['voxels']:6d}  P {x['precision_1']:.3f} R {x['recall_1']:.3f} "
                     f"F {x['f_1']:.3f} (2 vox {x['f_2']:.3f}, seen {x['f_seen_1']:.3f})  Chamfer "
                     f"{100 * x['chamfer_m']:.1f} cm  objects {x['object_recall_1']:.3f}  tops "
                     + ", ".join(f"{k} {v:+.1f}" for k, v in x["top_error_voxels"].items()))
    if "heldout" in row:
        parts.append("  held out (even -> odd pings, rms of the coarse cells): " + ", ".join(
            f"{k} {v['rms']:.4f}" for k, v in row["heldout"].items() if isinstance(v, dict))
            + f" (fit's own model: floor alone {row['heldout']['fit_model']['rms_floor_only']:.4f})")
    return "\n".join(parts)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.experiments.surface_fit",
                                description=__doc__.split("\n")[0])
    p.add_argument("--scenes", nargs="+", default=["tank", "circle"], choices=["tank", "circle", "side"])
    p.add_argument("--variations", nargs="+", default=["none", "real_tank"], choices=["none", "real_tank"])
    p.add_argument("--backend", default="auto", help="the evidence map's backend")
    p.add_argument("--cache", type=Path, default=CACHE, help="simulated pings (npz per case)")
    p.add_argument("--out", type=Path, default=Path("bench/results/surface_fit.json"))
    p.add_argument("--no-heldout", action="store_true", help="skip the held-out renders")
    a = p.parse_args(argv)
    t0 = time.perf_counter()
    res = {"schema": "gpumap-surface-fit/1", "machine": machine_info(), "cases": []}
    for scene in a.scenes:
        for var in a.variations:
            row = run_case(scene, var, a.backend, a.cache, not a.no_heldout)
            res["cases"].append(row)
            print(_line(row), flush=True)
    res["seconds_total"] = time.perf_counter() - t0
    res["load_end"] = load_average()
    path = write_json(a.out, res, digits=4)
    print(f"wrote {path} ({res['seconds_total']:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
