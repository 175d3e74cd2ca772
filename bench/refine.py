"""``python -m bench.refine``: plain / visible / refined maps, against truth and on held-out pings (issue 19).

For each simulated scene (true poses): the plain and the visible rule map every ping, the visible
map is refined (:func:`gpumap.refine.refine`, default options), and each map is scored against
the truth (:func:`gpumap.sim.metrics.evaluate`: FN on detectable surfaces, FN of the objects, FP
far from surfaces, water carved, pipe found; plain and visible at the mapper's threshold 0.1,
refined at :data:`gpumap.refine.OCCUPIED_LEVEL`). Held-out prediction, on the simulated scenes and
on the real OASIS tank: every ``k``-th ping is held out, the three maps are built (and refined)
from the others, and the held-out pings are rendered from each map through the same ping model
(:class:`gpumap.render.PingRenderer`: occlusion and incidence included; plain and visible maps
as occupancy 1 where called occupied, reflectivity 0.5, each with its own display gain and floor
fitted on the training pings) and compared with the measured images averaged onto the rendered
cells: ROC AUC of the rendered intensity for the cells whose measured mean is ``>= threshold``,
and the correlation.

    python -m bench.refine                                   # tank, circle, oasis at 3 cm, CPU
    python -m bench.refine --cases oasis --voxel-sizes 0.05 0.03 --device cuda

Writes ``bench/results/refine.json`` (merged by case, voxel size and device: a run on another
device or case keeps the others' rows).
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

import gpumap

from .common import bench_parser, load_average, machine_info, oasis_tank_dir, write_json

SIM_THRESHOLD = 0.1
BAND_VOXELS = 1  # RefineResult.banded: the visible voxels within one voxel of a refined surface
SCORE_KEYS = (
    "false_negative_rate_detectable",
    "false_negative_rate_objects_detectable",
    "false_positive_rate_far",
    "free_carved_fraction",
    "pipe_found",
    "height_error_m",
)


def _parser() -> argparse.ArgumentParser:
    p = bench_parser("refine", __doc__)
    p.add_argument(
        "--cases",
        nargs="+",
        default=["tank", "circle", "oasis"],
        help="simulated scenes (tank, circle, survey) and/or oasis (the real tank)",
    )
    p.add_argument("--voxel-sizes", type=float, nargs="+", default=[0.03], help="metres")
    p.add_argument("--holdout-every", type=int, default=5, help="hold out every k-th ping")
    p.add_argument("--device", default="auto", help="refinement device: auto, cpu, cuda")
    p.add_argument("--backend", default="auto", help="mapper backend")
    p.add_argument("--iterations", type=int, default=None, help="override the refine iterations")
    p.add_argument("--sparsity", type=float, default=None, help="override the refine sparsity weight")
    p.add_argument("--smoothness", type=float, default=None, help="override the refine smoothness weight")
    p.add_argument("--power", type=float, default=None, help="override the refine loss power")
    p.add_argument(
        "--save-maps",
        type=Path,
        default=None,
        help="also write each simulated scene's maps (npz: plain, visible, refined) here",
    )
    p.add_argument(
        "--cache",
        type=Path,
        default=Path(os.environ.get("TMPDIR", "/tmp")) / "gpumap_refine_cache",
        help="folder for simulated pings and truth masks",
    )
    p.add_argument(
        "--data",
        type=Path,
        default=None,
        help="folder holding oasis_tank (default: shared/data beside the checkout)",
    )
    p.add_argument("--out", type=Path, default=Path("bench/results/refine.json"),
                   help="results file (rows merged by case, voxel size and device)")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.add_argument(
        "--rescore-maps",
        type=Path,
        default=None,
        help="no mapping: score the maps a --save-maps run wrote (refined at several cuts, banded "
        "by 0-3 voxels) and add them to the matching rows of --out as 'truth_frontier'",
    )
    return p


def rescore(a: argparse.Namespace) -> int:
    """The FN-FP frontier of saved maps, added to the rows of ``a.out`` (same case and voxel size)."""
    from gpumap.sim.metrics import evaluate
    from scipy import ndimage

    res = json.loads(a.out.read_text())
    for row in res["rows"]:
        f = a.rescore_maps / f"{row['case']}_{row['voxel_size_m']:g}.npz"
        if row["case"] == "oasis" or not f.exists():
            continue
        c = sim_case(row["case"], row["voxel_size_m"], a.cache, False)
        z = np.load(f)
        obs = np.isfinite(z["visible"])
        vis = np.nan_to_num(z["visible"], nan=-1.0) >= c["threshold"]
        ref = np.nan_to_num(z["refined"], nan=0.0)

        def score(mask: np.ndarray, c=c, obs=obs, voxel=row["voxel_size_m"]) -> dict:
            v = np.where(obs, mask.astype(np.float32), np.nan)
            ev = evaluate(v, c["truth"], 0.5, c["seen"], voxel, detectable=c["det"]).to_dict()
            return {k: ev[k] for k in SCORE_KEYS if k != "height_error_m"}

        fr = [{"kind": "refined", "cut": t, **score(ref >= t)} for t in (0.05, 0.1, 0.2, 0.3, 0.5, 0.7)]
        for b in (0, 1, 2, 3):
            occ = ref >= 0.5
            if b:
                occ = ndimage.binary_dilation(occ, structure=np.ones((3, 3, 3), bool), iterations=b)
            fr.append({"kind": "refined_band", "band_voxels": b, **score(occ & vis)})
        row["truth_frontier"] = fr
    write_json(a.out, res)
    return 0


# ---------------------------------------------------------------------- inputs
def sim_case(name: str, voxel: float, cache: Path, progress: bool) -> dict:
    """Pings (uint8), poses, spec, grid and truth masks of a simulated scene, cached in ``cache``."""
    from gpumap.sim.scenes import make_scene
    from gpumap.sim.truth import Truth

    cache.mkdir(parents=True, exist_ok=True)
    f = cache / f"{name}_{voxel:g}.npz"
    scene = make_scene(name, voxel_size_m=voxel, seed=0)
    if not f.exists():
        from gpumap.sim.metrics import ground_truth_masks
        from gpumap.sim.truth import occupancy

        from .visibility import simulate

        pings, images, poses, _ = simulate(name, 0, progress)
        truth = occupancy(scene, seed=0)
        seen, det = ground_truth_masks(pings, scene.grid, SIM_THRESHOLD)
        np.savez_compressed(
            f,
            images=images,
            poses=poses,
            occupied=truth.occupied,
            surface=truth.surface,
            label=truth.label,
            seen=seen,
            det=det,
            names=np.array(truth.names),
            small=np.array(truth.small_objects),
        )
    z = np.load(f)
    truth = Truth(
        z["occupied"],
        z["surface"],
        z["label"],
        [str(x) for x in z["names"]],
        tuple(str(x) for x in z["small"]),
    )
    return {
        "images": z["images"],
        "poses": z["poses"],
        "spec": scene.sonar_spec,
        "grid": scene.grid,
        "truth": truth,
        "seen": z["seen"],
        "det": z["det"],
        "threshold": SIM_THRESHOLD,
    }


def _find_data() -> Path:
    tank = oasis_tank_dir()
    if tank is None:
        raise ValueError("Expected shared/data/oasis_tank beside the checkout, but found none: pass --data")
    return tank.parent


def oasis_case(voxel: float, data: Path | None) -> dict:
    from gpumap.refine import recording_frames as load_frames
    from gpumap.replay import DEFAULT_THRESHOLD
    from gpumap.spec import auto_grid

    spec, images, poses = load_frames(str((data or _find_data()) / "oasis_tank"))
    grid = auto_grid(spec, list(poses), voxel)
    return {"images": images, "poses": poses, "spec": spec, "grid": grid, "threshold": DEFAULT_THRESHOLD}


# ---------------------------------------------------------------------- maps
def build_maps(c: dict, sel: np.ndarray, backend: str, device: str, overrides: dict) -> dict:
    """Plain and visible maps of pings ``sel`` and the refinement of the visible one."""
    from gpumap.refine import RefineOptions, refine

    out = {}
    for rule in ("plain", "visible"):
        m = gpumap.MinMaxMapper(c["spec"], c["grid"], backend=backend, rule=rule, threshold=c["threshold"])
        t = time.perf_counter()
        m.integrate_batch(c["images"][sel], c["poses"][sel])
        m.synchronize()
        out[rule] = {"values": m.values(), "seconds": time.perf_counter() - t, "mapper": m}
    opts = RefineOptions(**overrides)
    res = refine(out["visible"]["mapper"], c["images"][sel], c["poses"][sel], options=opts, device=device)
    out["refined"] = {"values": res.occupancy, "seconds": res.stats["seconds"], "result": res}
    return out


def truth_scores(c: dict, maps: dict, voxel: float) -> dict:
    from gpumap.sim.metrics import evaluate

    from gpumap.refine import OCCUPIED_LEVEL

    rows = {}
    maps = dict(maps)
    vis = maps["visible"]["values"]
    band = maps["refined"]["result"].banded(vis, c["threshold"], BAND_VOXELS)
    maps["refined_band"] = {
        "values": np.where(np.isnan(vis), np.nan, band.astype(np.float32)),
        "seconds": maps["refined"]["seconds"],
    }
    for name, mp in maps.items():
        thr = OCCUPIED_LEVEL if name.startswith("refined") else c["threshold"]
        ev = evaluate(mp["values"], c["truth"], thr, c["seen"], voxel, detectable=c["det"]).to_dict()
        rows[name] = {k: ev[k] for k in SCORE_KEYS}
        rows[name]["seconds"] = mp["seconds"]
    return rows


def heldout(c: dict, k: int, backend: str, device: str, overrides: dict) -> dict:
    from gpumap.refine import OCCUPIED_LEVEL, heldout_scores, render_map
    from gpumap.render import PingRenderer

    n = len(c["images"])
    test = np.arange(n) % k == k - 1
    maps = build_maps(c, np.flatnonzero(~test), backend, device, overrides)
    r = PingRenderer(c["spec"], c["grid"], device=device)
    measured = r.coarsen(c["images"][test])
    res = maps["refined"]["result"]
    out = {
        "pings_train": int((~test).sum()),
        "pings_test": int(test.sum()),
        "device": res.stats["device"],
        "refine_seconds": res.stats["seconds"],
        "render_cells": res.stats["render_cells"],
        "map_seconds": {k: maps[k]["seconds"] for k in ("plain", "visible")},
    }
    vis = maps["visible"]["values"]
    band = res.banded(vis, c["threshold"], BAND_VOXELS)
    maps["refined_band"] = {"values": np.where(np.isnan(vis), np.nan, band.astype(np.float32))}
    for name, mp in maps.items():
        if name == "refined":
            occ = np.nan_to_num(res.occupancy, nan=0.0)
            occ = -np.log1p(-np.minimum(occ, 1 - 1e-6)) / r.model.kappa  # back to the fitted field
            pred, _, _ = render_map(
                r, occ, c["poses"][test], reflectivity=res.reflectivity, gain=res.gain, floor=res.floor
            )
        else:
            thr = OCCUPIED_LEVEL if name == "refined_band" else c["threshold"]
            occ = (np.nan_to_num(mp["values"], nan=-1.0) >= thr).astype(np.float32)
            pred, _, _ = render_map(
                r, occ, c["poses"][test], train_images=c["images"][~test], train_poses=c["poses"][~test]
            )
        out[name] = heldout_scores(pred, measured, c["threshold"])
        out[name]["occupied_voxels"] = int(
            np.sum(
                np.nan_to_num(mp["values"], nan=-1.0)
                >= (OCCUPIED_LEVEL if name == "refined" else c["threshold"])
            )
        )
    return out


def main(argv: list[str] | None = None) -> int:
    a = _parser().parse_args(argv)
    if a.rescore_maps is not None:
        return rescore(a)
    names = ("iterations", "sparsity", "smoothness", "power")
    overrides = {k: getattr(a, k) for k in names if getattr(a, k) is not None}
    rows = []
    for case in a.cases:
        for v in a.voxel_sizes:
            t0 = time.perf_counter()
            c = oasis_case(v, a.data) if case == "oasis" else sim_case(case, v, a.cache, not a.no_progress)
            row = {
                "case": case,
                "voxel_size_m": v,
                "pings": len(c["images"]),
                "grid_shape": list(c["grid"].shape),
                "threshold": c["threshold"],
                "load_before": load_average(),
            }
            if case != "oasis":
                maps = build_maps(c, np.arange(len(c["images"])), a.backend, a.device, overrides)
                row["truth"] = truth_scores(c, maps, v)
                res = maps["refined"]["result"]
                row["refine_stats"] = {k: x for k, x in res.stats.items() if k not in ("options", "model")}
                row["options"], row["model"] = res.stats["options"], res.stats["model"]
                if a.save_maps is not None:
                    a.save_maps.mkdir(parents=True, exist_ok=True)
                    np.savez_compressed(
                        a.save_maps / f"{case}_{v:g}.npz",
                        plain=maps["plain"]["values"],
                        visible=maps["visible"]["values"],
                        refined=res.occupancy,
                        confidence=res.confidence,
                        raised=res.raised,
                    )
                del maps
            row["heldout"] = heldout(c, a.holdout_every, a.backend, a.device, overrides)
            row["device"] = row["heldout"].get("device") or (row.get("refine_stats") or {}).get("device")
            row["seconds_total"] = time.perf_counter() - t0
            row["load_after"] = load_average()
            rows.append(row)
            print(json.dumps(row, default=float)[:2000], flush=True)
    old = json.loads(a.out.read_text()) if a.out.exists() else {"rows": []}
    keep = [
        r
        for r in old.get("rows", [])
        if not any(
            r["case"] == n["case"]
            and r["voxel_size_m"] == n["voxel_size_m"]
            and r.get("device") == n.get("device")
            for n in rows
        )
    ]
    write_json(a.out, {"machine": machine_info(), "rows": keep + rows})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
