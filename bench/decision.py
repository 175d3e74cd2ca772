"""``python -m bench decision``: the evidence rule's decisions side by side (issue #36).

The same counts decided by the share test (today's default), by the calibrated view model
(:mod:`gpumap.calibration`) at several miss costs, and the visible rule beside them, on

- the simulated scenes (tank, circle, side; 40 pings at 3 cm) without and with the real tank's
  variation: objects missed, all detectable surface missed, far water called occupied;
- the real full-rate tank, development split only: frames 0-599 mapped at every frame, frames
  600-799 judged by first returns (``gpumap.first_return``). Frames 800-1222 stay held out for
  ``python -m bench real_frontier``. Beside the fixed threshold (0.4), the pings' own per-range
  detections (:func:`gpumap.detection.adaptive_detect`, the OASIS preprocessing's scheme) at a
  few standard scores, mapped at 0.5; the judge's first returns stay the fixed threshold's.

Writes ``bench/results/decision.json``; ``--report BENCHMARKS.md`` writes its block.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from . import common
from .common import Section, bench_parser, oasis_full_dir, progress_bar, quantize, run_header, write_json

SCHEMA = "gpumap-decision/1"
COSTS = (1.0, 3.0, 10.0, 100.0)
SCENES = ("tank", "circle", "side")
VARIATIONS = ("none", "real_tank")
THRESHOLD = 0.1
DEV_MAP, DEV_JUDGE = (0, 600), (600, 800)
DETECT_Z = (2.0, 3.0)  # adaptive detection's standard scores measured beside the fixed threshold


def _decisions(m) -> dict[str, dict]:
    """Decision name -> {"options": ..., "values": the map's values read under it}."""
    out = {"share (default)": {"options": {"decision": "share"}, "values": m.values()}}
    m.decision = "calibrated"
    for c in COSTS:
        m.miss_cost = c
        out[f"calibrated, miss cost {c:g}"] = {"options": {"decision": "calibrated", "miss_cost": c},
                                               "values": m.values()}
    m.decision = "share"
    return out


def sim_rows(backend: str, progress: bool) -> list[dict]:
    from gpumap.sim.metrics import evaluate, ground_truth_masks
    from gpumap.sim.scenes import make_scene
    from gpumap.sim.truth import occupancy
    from gpumap.sim.variation import SonarVariation

    import gpumap

    rows = []
    for name in SCENES:
        scene = make_scene(name, voxel_size_m=0.03, seed=0)
        truth = occupancy(scene, seed=0)
        for var in VARIATIONS:
            variation = SonarVariation.real_tank() if var == "real_tank" else None
            pings = common.render_pings(scene, seed=0, variation=variation, scene_sonar=False,
                                        progress=progress, desc=f"{name} {var}")
            seen, det = ground_truth_masks(pings, scene.grid, THRESHOLD)
            maps = {}
            for rule in ("evidence", "visible"):
                m = gpumap.MinMaxMapper(scene.sonar_spec, scene.grid, backend=backend, rule=rule,
                                        threshold=THRESHOLD)
                for p in pings:
                    m.integrate(quantize(p.image), p.T_W_S)
                maps[rule] = m
            reads = _decisions(maps["evidence"]) | {"visible rule": {"options": {"rule": "visible"},
                                                                      "values": maps["visible"].values()}}
            model = maps["evidence"].view_model().to_dict()
            for label, r in reads.items():
                ev = evaluate(r["values"], truth, THRESHOLD, seen, 0.03, detectable=det).to_dict()
                rows.append({"scene": name, "variation": var, "decision": label, **r["options"],
                             "miss_rate_objects": ev["miss_rate_objects"], "miss_rate": ev["miss_rate"],
                             "false_positive_rate_far": ev["false_positive_rate_far"], "view_model": model})
    return rows


def real_rows(backend: str, progress: bool, stride: int) -> dict:
    import gpumap
    from gpumap.detection import adaptive_detect
    from gpumap.first_return import first_return_score
    from gpumap.spec import auto_grid

    from .rate_real import _load

    data = oasis_full_dir()
    if data is None:
        return {"skipped": "the full real run was not found (shared/data/README.md)"}
    spec, images, poses = _load(data, progress)
    grid = auto_grid(spec, poses, 0.05)
    m = gpumap.MinMaxMapper(spec, grid, backend=backend, rule="evidence", threshold=0.4)
    for a in range(DEV_MAP[0], DEV_MAP[1], 32):
        m.integrate_batch(images[a:min(a + 32, DEV_MAP[1])], poses[a:min(a + 32, DEV_MAP[1])])
    judged = range(DEV_JUDGE[0], DEV_JUDGE[1], stride)
    reads = {f"{k} (threshold 0.4)": {**r, "detection": "threshold 0.4"} for k, r in _decisions(m).items()}
    for z in DETECT_Z:  # the pings' own detections instead of a fixed threshold (gpumap.detection)
        det = np.stack([adaptive_detect(im, z=z) for im in images[DEV_MAP[0]:DEV_MAP[1]]])
        md = gpumap.MinMaxMapper(spec, grid, backend=backend, rule="evidence", threshold=0.5)
        for a in range(0, len(det), 32):
            md.integrate_batch(det[a:a + 32], poses[DEV_MAP[0] + a:DEV_MAP[0] + a + 32])
        dd = _decisions(md)
        for k in ("share (default)", f"calibrated, miss cost {COSTS[2]:g}"):
            reads[f"{k} (adaptive detection, z {z:g})"] = {**dd[k], "detection": f"adaptive, z {z:g}"}
    rows = []
    for label, r in progress_bar(reads.items(), desc="judge", disable=not progress):
        sc = first_return_score(r["values"], grid, 0.4, ((images[i], poses[i]) for i in judged), spec)
        rows.append({"decision": label, **r["options"], "detection": r["detection"],
                     "agreement": sc.agreement, "phantom_rate": sc.phantom_rate,
                     "missing_rate": sc.missing_rate,
                     "occupied": int((np.nan_to_num(r["values"], nan=0.0) >= 0.4).sum())})
    return {"data": str(data), "mapped_frames": list(DEV_MAP), "judged_frames": [*DEV_JUDGE, stride],
            "voxel_size_m": 0.05, "threshold": 0.4, "view_model": m.view_model().to_dict(), "rows": rows}


def main(argv: list[str] | None = None) -> int:
    ap = bench_parser("decision", __doc__, out="bench/results", backend="opencl-cpu", progress=True,
                      report="decision.json")
    ap.add_argument("--judge-stride", type=int, default=2, help="judge every N-th dev frame (default 2)")
    a = ap.parse_args(argv)
    if SECTION.reported(a):
        return 0
    t0 = time.perf_counter()
    res = {**run_header(SCHEMA, argv), "costs": list(COSTS), "sim": sim_rows(a.backend, not a.no_progress),
           "real_dev": real_rows(a.backend, not a.no_progress, a.judge_stride)}
    res["duration_s"] = time.perf_counter() - t0
    path = write_json(a.out / "decision.json", res, digits=4)
    print(f"wrote {path}; BENCHMARKS.md: python -m bench decision --report BENCHMARKS.md")
    return 0


def _pct(x: float) -> str:
    return f"{100 * x:.1f}"


def markdown(res: dict, folder: Path) -> str:
    m = res["machine"]
    out = [f"`python -m bench decision` ({res['created']}, {m['cpu_model']} x{m['cpu_count']}, "
           f"{res['duration_s']:.0f} s). The evidence rule's counts read under each decision (read-time "
           "options of one map); the visible rule beside them. Simulated scenes, 40 pings at 3 cm, "
           "threshold 0.1: objects missed / all detectable surface missed / far water called occupied, %.",
           "",
           "| decision | " + " | ".join(f"{s} ({v})" for s in SCENES for v in VARIATIONS) + " |",
           "|---|" + "---|" * (len(SCENES) * len(VARIATIONS))]
    labels = list(dict.fromkeys(r["decision"] for r in res["sim"]))
    for lab in labels:
        cells = []
        for s in SCENES:
            for v in VARIATIONS:
                r = next(r for r in res["sim"]
                         if r["decision"] == lab and r["scene"] == s and r["variation"] == v)
                cells.append(f"{_pct(r['miss_rate_objects'])} / {_pct(r['miss_rate'])} / "
                             f"{_pct(r['false_positive_rate_far'])}")
        out.append(f"| {lab} | " + " | ".join(cells) + " |")
    rd = res["real_dev"]
    if "rows" in rd:
        vm = rd["view_model"]
        out += ["", f"Real full-rate tank, development split only (frames {rd['mapped_frames'][0]}-"
                f"{rd['mapped_frames'][1] - 1} mapped at every frame, 5 cm; every "
                f"{rd['judged_frames'][2]}nd frame of {rd['judged_frames'][0]}-"
                f"{rd['judged_frames'][1] - 1} judged by first returns). The "
                f"fitted view model: surface weight {vm['pi']:.2f}, mean bright share of a surface "
                f"{vm['surface_mean_share']:.2f}, of the stretch {vm['water_mean_share']:.2f}.", "",
                "| decision | occupied voxels | first returns agreed | phantoms in front | missed |",
                "|---|---|---|---|---|"]
        for r in rd["rows"]:
            out.append(f"| {r['decision']} | {r['occupied']:,} | {_pct(r['agreement'])} % | "
                       f"{_pct(r['phantom_rate'])} % | {_pct(r['missing_rate'])} % |")
    return "\n".join(out)


SECTION = Section("decision", "## The evidence rule's decisions: share test against the calibrated view "
                  "model (issue #36)", "decision.json", markdown)

if __name__ == "__main__":
    raise SystemExit(main())
