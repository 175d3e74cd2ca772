"""``python -m bench.refine``: plain / visible / refined maps, against truth and on held-out pings (issue 19).

    python -m bench.refine                                   # tank, circle, oasis at 3 cm, CPU
    python -m bench.refine --cases oasis --voxel-sizes 0.05 0.03 --device cuda
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

import gpumap
from gpumap.core.params import MapperParams

from .common import bench_parser, load_average, machine_info, merge_json, oasis_tank_dir, simulate, write_json

SIM_THRESHOLD = 0.1
BAND_VOXELS = 1  # RefineResult.banded: the visible voxels within one voxel of a refined surface
SCORE_KEYS = ("false_negative_rate_detectable", "false_negative_rate_objects_detectable",
              "false_positive_rate_far",
              "free_carved_fraction", "pipe_found", "height_error_m")
OVERRIDES = ("iterations", "sparsity", "smoothness", "power", "learning_rate")


def _parser() -> argparse.ArgumentParser:
    p = bench_parser("refine", __doc__, out="bench/results/refine.json", backend="auto", voxel=[0.03],
                     progress=True)
    p.add_argument("--cases", nargs="+", default=["tank", "circle", "oasis"],
                   help="simulated scenes (tank, circle, survey) and/or oasis (the real tank)")
    p.add_argument("--holdout-every", type=int, default=5, help="hold out every k-th ping")
    p.add_argument("--device", default="auto", help="refinement device: auto, cpu, cuda")
    for name in OVERRIDES:
        p.add_argument(f"--{name.replace('_', '-')}", type=int if name == "iterations" else float,
                       default=None,
                       help=f"override the refine option {name}")
    p.add_argument("--save-maps", type=Path, default=None,
                   help="also write each simulated scene's maps (npz: plain, visible, refined) here")
    p.add_argument("--cache", type=Path,
                   default=Path(os.environ.get("TMPDIR", "/tmp")) / "gpumap_refine_cache",
                   help="folder for simulated pings and truth masks")
    p.add_argument("--data", type=Path, default=None,
                   help="folder holding oasis_tank (default: shared/data beside the checkout)")
    p.add_argument("--section", default=None,
                   help="merge the rows into runs.NAME of --out instead (candidates)")
    p.add_argument("--rescore-maps", type=Path, default=None,
                   help="no mapping: score the maps a --save-maps run wrote (refined at several cuts, banded "
                   "by 0-3 voxels) and add them to the matching rows of --out as 'truth_frontier'")
    return p


def _truth(c: dict, values: np.ndarray, threshold: float, voxel: float, keys=SCORE_KEYS) -> dict:
    from gpumap.sim.metrics import evaluate

    ev = evaluate(values, c["truth"], threshold, c["seen"], voxel, detectable=c["det"]).to_dict()
    return {k: ev[k] for k in keys}


def rescore(a: argparse.Namespace) -> int:
    """The FN-FP frontier of saved maps, added to the rows of ``a.out`` (same case and voxel size)."""
    from scipy import ndimage

    res = json.loads(a.out.read_text())
    for row in res["rows"]:
        f = a.rescore_maps / f"{row['case']}_{row['voxel_size_m']:g}.npz"
        if row["case"] == "oasis" or not f.exists():
            continue
        c, z, v = sim_case(row["case"], row["voxel_size_m"], a.cache, False), np.load(f), row["voxel_size_m"]
        obs = np.isfinite(z["visible"])
        vis = np.nan_to_num(z["visible"], nan=-1.0) >= c["threshold"]
        ref = np.nan_to_num(z["refined"], nan=0.0)
        keys = [k for k in SCORE_KEYS if k != "height_error_m"]

        def score(mask: np.ndarray, c=c, obs=obs, v=v, keys=keys) -> dict:
            return _truth(c, np.where(obs, mask.astype(np.float32), np.nan), 0.5, v, keys)

        fr = [{"kind": "refined", "cut": t, **score(ref >= t)} for t in (0.05, 0.1, 0.2, 0.3, 0.5, 0.7)]
        for b in (0, 1, 2, 3):
            occ = ref >= 0.5
            if b:
                occ = ndimage.binary_dilation(occ, structure=np.ones((3, 3, 3), bool), iterations=b)
            fr.append({"kind": "refined_band", "band_voxels": b, **score(occ & vis)})
        row["truth_frontier"] = fr
    write_json(a.out, res)
    return 0


def sim_case(name: str, voxel: float, cache: Path, progress: bool) -> dict:
    """Pings (uint8), poses, spec, grid and truth masks of a simulated scene, cached in ``cache``."""
    from gpumap.sim.scenes import make_scene
    from gpumap.sim.truth import Truth

    cache.mkdir(parents=True, exist_ok=True)
    f, scene = cache / f"{name}_{voxel:g}.npz", make_scene(name, voxel_size_m=voxel, seed=0)
    if not f.exists():
        from gpumap.sim.metrics import ground_truth_masks
        from gpumap.sim.truth import occupancy

        pings, images, poses, _ = simulate(name, 0, progress)
        truth = occupancy(scene, seed=0)
        seen, det = ground_truth_masks(pings, scene.grid, SIM_THRESHOLD)
        np.savez_compressed(f, images=images, poses=poses, occupied=truth.occupied, surface=truth.surface,
                            label=truth.label, seen=seen, det=det, names=np.array(truth.names),
                            small=np.array(truth.small_objects))
    z = np.load(f)
    truth = Truth(z["occupied"], z["surface"], z["label"], [str(x) for x in z["names"]],
                  tuple(str(x) for x in z["small"]))
    return {"images": z["images"], "poses": z["poses"], "spec": scene.sonar_spec, "grid": scene.grid,
            "truth": truth, "seen": z["seen"], "det": z["det"], "threshold": SIM_THRESHOLD}


def oasis_case(voxel: float, data: Path | None) -> dict:
    from gpumap.layers.refine import recording_frames as load_frames
    from gpumap.pipeline.replay import DEFAULT_THRESHOLD
    from gpumap.spec import auto_grid

    if data is None and oasis_tank_dir() is None:
        raise ValueError("Expected shared/data/oasis_tank beside the checkout, but found none: pass --data")
    spec, images, poses = load_frames(str((data or oasis_tank_dir().parent) / "oasis_tank"))
    return {"images": images, "poses": poses, "spec": spec, "grid": auto_grid(spec, list(poses), voxel),
            "threshold": DEFAULT_THRESHOLD}


def build_maps(c: dict, sel: np.ndarray, backend: str, device: str, overrides: dict) -> dict:
    """Plain and visible maps of pings ``sel``, the refinement of the visible one, and its band."""
    from gpumap.layers.refine import RefineOptions, refine

    out = {}
    for rule in ("plain", "visible"):
        m = gpumap.MinMaxMapper(
            c["spec"], c["grid"], backend, MapperParams(rule=rule, threshold=c["threshold"])
        )
        t = time.perf_counter()
        m.integrate_batch(c["images"][sel], c["poses"][sel])
        m.synchronize()
        out[rule] = {"values": m.values(), "seconds": time.perf_counter() - t, "mapper": m}
    res = refine(out["visible"]["mapper"], c["images"][sel], c["poses"][sel],
                 options=RefineOptions(**overrides),
                 device=device)
    out["refined"] = {"values": res.occupancy, "seconds": res.stats["seconds"], "result": res}
    vis = out["visible"]["values"]
    band = res.banded(vis, c["threshold"], BAND_VOXELS)
    out["refined_band"] = {"values": np.where(np.isnan(vis), np.nan, band.astype(np.float32)),
                           "seconds": res.stats["seconds"]}
    return out


def truth_scores(c: dict, maps: dict, voxel: float) -> dict:
    from gpumap.layers.refine import OCCUPIED_LEVEL

    return {name: _truth(c, mp["values"], OCCUPIED_LEVEL if name.startswith("refined") else c["threshold"],
                         voxel)
            | {"seconds": mp["seconds"]} for name, mp in maps.items()}


def heldout(c: dict, k: int, backend: str, device: str, overrides: dict) -> dict:
    from gpumap.layers.refine import OCCUPIED_LEVEL, heldout_scores, render_map
    from gpumap.layers.render import PingRenderer

    test = np.arange(len(c["images"])) % k == k - 1
    maps = build_maps(c, np.flatnonzero(~test), backend, device, overrides)
    r = PingRenderer(c["spec"], c["grid"], device=device)
    measured, res = r.coarsen(c["images"][test]), maps["refined"]["result"]
    out = {"pings_train": int((~test).sum()), "pings_test": int(test.sum()), "device": res.stats["device"],
           "refine_seconds": res.stats["seconds"], "render_cells": res.stats["render_cells"],
           "map_seconds": {k: maps[k]["seconds"] for k in ("plain", "visible")}}
    for name, mp in maps.items():
        if name == "refined":
            occ = np.nan_to_num(res.occupancy, nan=0.0)
            occ = -np.log1p(-np.minimum(occ, 1 - 1e-6)) / r.model.kappa  # back to the fitted field
            pred, _, _ = render_map(r, occ, c["poses"][test], reflectivity=res.reflectivity, gain=res.gain,
                                    floor=res.floor)
        else:
            thr = OCCUPIED_LEVEL if name == "refined_band" else c["threshold"]
            occ = (np.nan_to_num(mp["values"], nan=-1.0) >= thr).astype(np.float32)
            pred, _, _ = render_map(r, occ, c["poses"][test], train_images=c["images"][~test],
                                    train_poses=c["poses"][~test])
        out[name] = heldout_scores(pred, measured, c["threshold"])
        level = OCCUPIED_LEVEL if name == "refined" else c["threshold"]
        out[name]["occupied_voxels"] = int(np.sum(np.nan_to_num(mp["values"], nan=-1.0) >= level))
    return out


def main(argv: list[str] | None = None) -> int:
    a = _parser().parse_args(argv)
    if a.rescore_maps is not None:
        return rescore(a)
    overrides = {k: getattr(a, k) for k in OVERRIDES if getattr(a, k) is not None}
    rows = []
    for case in a.cases:
        for v in a.voxel:
            t0 = time.perf_counter()
            c = oasis_case(v, a.data) if case == "oasis" else sim_case(case, v, a.cache, not a.no_progress)
            row = {"case": case, "voxel_size_m": v, "pings": len(c["images"]),
                   "grid_shape": list(c["grid"].shape),
                   "threshold": c["threshold"], "load_before": load_average()}
            if case != "oasis":
                maps = build_maps(c, np.arange(len(c["images"])), a.backend, a.device, overrides)
                res = maps["refined"]["result"]
                row["truth"] = truth_scores(c, maps, v)
                row["refine_stats"] = {k: x for k, x in res.stats.items() if k not in ("options", "model")}
                row["options"], row["model"] = res.stats["options"], res.stats["model"]
                if a.save_maps is not None:
                    a.save_maps.mkdir(parents=True, exist_ok=True)
                    np.savez_compressed(a.save_maps / f"{case}_{v:g}.npz", plain=maps["plain"]["values"],
                                        visible=maps["visible"]["values"], refined=res.occupancy,
                                        confidence=res.confidence, raised=res.raised)
                del maps
            row["heldout"] = heldout(c, a.holdout_every, a.backend, a.device, overrides)
            row["device"] = row["heldout"].get("device") or (row.get("refine_stats") or {}).get("device")
            row["seconds_total"], row["load_after"] = time.perf_counter() - t0, load_average()
            rows.append(row)
            print(json.dumps(row, default=float)[:2000], flush=True)
    doc = json.loads(a.out.read_text()) if a.out.exists() else {}
    old = doc.get("runs", {}).get(a.section, []) if a.section else doc.get("rows", [])
    new = {(n["case"], n["voxel_size_m"], n.get("device")) for n in rows}
    keep = [r for r in old if (r["case"], r["voxel_size_m"], r.get("device")) not in new]
    if a.section:
        merge_json(a.out, ["runs", a.section], keep + rows)
    else:
        write_json(a.out, {"machine": machine_info(), "rows": keep + rows})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
