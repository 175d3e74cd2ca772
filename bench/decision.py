"""``python -m bench decision``: the evidence rule's decisions side by side (issue #36).

The same counts decided by the share test (today's default), by the calibrated view model
(:mod:`gpumap.bench.experiments.calibration`) at several miss costs, and the visible rule beside them, on

- the simulated scenes (tank, circle, side; 40 pings at 3 cm) without and with the real tank's
  variation: objects missed, all detectable surface missed, far water called occupied;
- the real full-rate tank, development split only: frames 0-599 mapped at every frame, frames
  600-799 judged by first returns (``gpumap.layers.first_return``). Frames 800-1222 stay held out for
  ``python -m bench real_frontier``. Beside the fixed threshold (0.4), the pings' own per-range
  detections (:func:`gpumap.bench.experiments.detection.adaptive_detect`, the OASIS preprocessing's scheme)
  at a
  few standard scores, mapped at 0.5; the judge's first returns stay the fixed threshold's.

Writes ``bench/results/decision.json``; ``--report BENCHMARKS.md`` writes its block.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from gpumap.core.params import MapperParams

from . import common
from .common import Section, bench_parser, oasis_full_dir, progress_bar, quantize, run_header, write_json

SCHEMA = "gpumap-decision/1"
COSTS = (1.0, 3.0, 10.0, 100.0)
SCENES = ("tank", "circle", "side")
VARIATIONS = ("none", "real_tank")
THRESHOLD = 0.1
DEV_MAP, DEV_JUDGE = (0, 600), (600, 800)
REAL_SHARES = (0.3, 0.5)  # the share test's and the directional decision's frontier on the real run
RATE_FRAMES, RATE_STRIDES = 800, (10, 3, 1)
DETECT_Z = (2.0, 3.0)  # adaptive detection's standard scores measured beside the fixed threshold


def _decisions(m, directional=None, shares: tuple[float, ...] = ()) -> dict[str, dict]:
    """Decision name -> {"options": ..., "values": the evidence map ``m``'s values read under it}:
    the share test (default, and at ``shares``), the calibrated decision at each of COSTS, the
    directional decision (``directional``: a :class:`gpumap.bench.experiments.directions.DirectionalEvidence`
    of the
    same pings) at the default share and ``shares``, and every voxel ever seen bright (the floor of
    any rule's misses: a voxel never bright is free under every rule)."""
    out = {"share 0.2 (default)": {"options": {"decision": "share"}, "values": m.values()}}
    default = m.bright_share
    for p in shares:
        m.bright_share = p
        out[f"share {p:g}"] = {"options": {"decision": "share", "bright_share": p}, "values": m.values()}
    m.bright_share = default
    m.decision = "calibrated"
    for c in COSTS:
        m.miss_cost = c
        out[f"calibrated, miss cost {c:g}"] = {"options": {"decision": "calibrated", "miss_cost": c},
                                               "values": m.values()}
    m.decision = "share"
    if directional is not None:
        for p in (default, *shares):
            m.bright_share = p
            out[f"directional, share {p:g}"] = {"options": {"decision": "directional", "bright_share": p},
                                                "values": directional.values(m)}
        m.bright_share = default
    ev = m.evidence()
    ever = np.where(ev["hits"] > 0, ev["bright"], ev["min_all"])
    out["ever bright (floor)"] = {"options": {"decision": "ever bright"},
                                  "values": np.where(np.isinf(ever), np.nan, ever).astype(np.float32)}
    return out


def sim_rows(backend: str, progress: bool) -> list[dict]:
    from gpumap.bench.experiments.directions import DirectionalEvidence
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
                maps[rule] = gpumap.MinMaxMapper(
                    scene.sonar_spec, scene.grid, backend, MapperParams(rule=rule, threshold=THRESHOLD)
                )
            directional = DirectionalEvidence(scene.sonar_spec, scene.grid, backend=backend,
                                              threshold=THRESHOLD)
            for p in pings:
                for m in (*maps.values(), directional):
                    m.integrate(quantize(p.image), p.T_W_S)
            reads = _decisions(maps["evidence"], directional) | {
                "visible rule": {"options": {"rule": "visible"}, "values": maps["visible"].values()}}
            model = maps["evidence"].view_model().to_dict()
            for label, r in reads.items():
                ev = evaluate(r["values"], truth, THRESHOLD, seen, 0.03, detectable=det).to_dict()
                rows.append({"scene": name, "variation": var, **r["options"], "label": label,
                             "miss_rate_objects": ev["miss_rate_objects"], "miss_rate": ev["miss_rate"],
                             "false_positive_rate_far": ev["false_positive_rate_far"], "view_model": model})
    return rows


def real_rows(backend: str, progress: bool, stride: int) -> dict:
    from gpumap.bench.experiments.detection import adaptive_detect
    from gpumap.bench.experiments.directions import DirectionalEvidence

    import gpumap
    from gpumap.layers.first_return import first_return_score
    from gpumap.spec import auto_grid

    from .rate_real import _load

    data = oasis_full_dir()
    if data is None:
        return {"skipped": "the full real run was not found (shared/data/README.md)"}
    spec, images, poses = _load(data, progress)
    grid = auto_grid(spec, poses, 0.05)
    m = gpumap.MinMaxMapper(spec, grid, backend, MapperParams(rule="evidence", threshold=0.4))
    directional = DirectionalEvidence(spec, grid, backend=backend, threshold=0.4)
    for a in range(DEV_MAP[0], DEV_MAP[1], 32):
        for mm in (m, directional):
            mm.integrate_batch(images[a:min(a + 32, DEV_MAP[1])], poses[a:min(a + 32, DEV_MAP[1])])
    judged = range(DEV_JUDGE[0], DEV_JUDGE[1], stride)
    reads = {
        f"{k} (threshold 0.4)": {**r, "detection": "threshold 0.4"}
        for k, r in _decisions(m, directional, REAL_SHARES).items()
    }
    for z in (
        DETECT_Z
    ):  # the pings' own detections instead of a fixed threshold (gpumap.bench.experiments.detection)
        det = np.stack([adaptive_detect(im, z=z) for im in images[DEV_MAP[0]:DEV_MAP[1]]])
        md = gpumap.MinMaxMapper(spec, grid, backend, MapperParams(rule="evidence", threshold=0.5))
        dev_poses = poses[DEV_MAP[0]:DEV_MAP[1]]
        for a in range(0, len(det), 32):
            md.integrate_batch(det[a:a + 32], dev_poses[a:a + 32])
        dd = _decisions(md)
        for k in ("share 0.2 (default)", f"calibrated, miss cost {COSTS[2]:g}"):
            reads[f"{k} (adaptive detection, z {z:g})"] = {**dd[k], "detection": f"adaptive, z {z:g}"}
    rows = []
    for label, r in progress_bar(reads.items(), desc="judge", disable=not progress):
        sc = first_return_score(r["values"], grid, 0.4, ((images[i], poses[i]) for i in judged), spec)
        rows.append({**r["options"], "label": label, "detection": r["detection"],
                     "agreement": sc.agreement, "phantom_rate": sc.phantom_rate,
                     "missing_rate": sc.missing_rate,
                     "occupied": int((np.nan_to_num(r["values"], nan=0.0) >= 0.4).sum())})
    rate = _rate_rows(spec, grid, images, poses, backend)
    return {"data": str(data), "mapped_frames": list(DEV_MAP), "rate": rate,
            "judged_frames": [*DEV_JUDGE, stride],
            "voxel_size_m": 0.05, "threshold": 0.4, "view_model": m.view_model().to_dict(),
            "directional_classes": sorted(directional.maps), "directional_bytes": directional.memory_bytes(),
            "evidence_bytes": m.memory_stats()["block_bytes"], "rows": rows}


def _rate_rows(spec, grid, images, poses, backend: str) -> dict:
    """Frames 0-799 mapped every 10th, 3rd and every frame: occupied voxels on the voxels all three
    maps observe, per decision (a decision that holds at any ping rate keeps these close)."""
    from .rate_real import _map

    maps = {s: _map(spec, grid, images, poses, range(0, RATE_FRAMES, s), "evidence", backend, 0.4)[0]
            for s in RATE_STRIDES}
    common_obs = np.logical_and.reduce([m.observed() for m in maps.values()])
    out = {"frames": RATE_FRAMES, "strides": list(RATE_STRIDES), "observed_common": int(common_obs.sum()),
           "occupied": {}}
    for label in ("share 0.2 (default)", *(f"calibrated, miss cost {c:g}" for c in COSTS)):
        occ = []
        for m in maps.values():
            m.decision = "share" if label.startswith("share") else "calibrated"
            if m.decision == "calibrated":
                m.miss_cost = float(label.rsplit(" ", 1)[1])
            occ.append(int((common_obs & (np.nan_to_num(m.values(), nan=0.0) >= 0.4)).sum()))
        out["occupied"][label] = occ
    return out


def main(argv: list[str] | None = None) -> int:
    ap = bench_parser("decision", __doc__, out="bench/results", backend="opencl-cpu", progress=True,
                      report="decision.json")
    ap.add_argument("--judge-stride", type=int, default=2, help="judge every N-th dev frame (default 2)")
    a = ap.parse_args(argv)
    if SECTION.reported(a):
        return 0
    t0 = time.perf_counter()
    res = {**run_header(SCHEMA, argv), "costs": list(COSTS),
           "real_dev": real_rows(a.backend, not a.no_progress, a.judge_stride),
           "sim": sim_rows(a.backend, not a.no_progress)}
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
    labels = list(dict.fromkeys(r["label"] for r in res["sim"]))
    for lab in labels:
        cells = []
        for s in SCENES:
            for v in VARIATIONS:
                r = next(r for r in res["sim"]
                         if r["label"] == lab and r["scene"] == s and r["variation"] == v)
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
            out.append(f"| {r['label']} | {r['occupied']:,} | {_pct(r['agreement'])} % | "
                       f"{_pct(r['phantom_rate'])} % | {_pct(r['missing_rate'])} % |")
        rt = rd["rate"]
        out += ["", f"Frames 0-{rt['frames'] - 1} mapped every " + " / ".join(map(str, rt["strides"]))
                + f" frames: occupied voxels on the {rt['observed_common']:,} voxels all three maps observe "
                "(a decision that holds at any rate keeps them close): "
                + "; ".join(f"{k}: {' / '.join(f'{x:,}' for x in v)} "
                            f"(spread {max(v) / max(1, min(v)) - 1:.0%})"
                            for k, v in rt["occupied"].items()) + "."]
        out += ["", "The directional decision keeps one evidence map per view-direction class: the real "
                f"run's views fell in {len(rd['directional_classes'])} of the 6 classes, whose maps hold "
                f"{rd['directional_bytes'] / 1e6:.1f} MB against the pooled map's "
                f"{rd['evidence_bytes'] / 1e6:.1f} MB (bounded box, every block allocated)."]
    return "\n".join(out)


SECTION = Section("decision", "## The evidence rule's decisions: share test against the calibrated view "
                  "model (issue #36)", "decision.json", markdown)

if __name__ == "__main__":
    raise SystemExit(main())
