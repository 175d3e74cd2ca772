"""``python -m bench long_run``: every mapping rule over a long simulated run with realistic variation.

Writes ``bench/results/long_run.json`` and ``long_run.png`` (``--quick``: ``long_run_quick.*``; another
``--voxel-size``: ``long_run_<mm>mm.*``); ~15 min on 2 cores (bench/README.md tells more).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from gpumap.core.params import MapperParams

from . import common
from .common import CpuShare, Section, bench_parser, mark_load, progress_bar, quantize, run_header

SCHEMA = "gpumap-long-run/1"
CHECKPOINTS = (40, 100, 200, 500, 1000)
QUICK_CHECKPOINTS = (20, 40, 60)
#: Other settings of the evidence rule's bright_share decided from the same counts (the frontier).
SHARE_FRONTIER = (0.1, 0.2, 0.3, 0.4, 0.5)
#: Per rule, a read-time option and its other settings, decided from the same counts as the rule's
#: own map (curves ``rule@value``); a rule missing from :data:`gpumap.geometry.RULES` is skipped.
FRONTIERS: dict[str, tuple[str, tuple[float, ...]]] = {"evidence": ("bright_share", SHARE_FRONTIER)}
SCORES = ("miss_rate_objects", "miss_rate", "false_positive_rate_far", "false_negative_rate_detectable",
          "observed_surface_fraction")


def run_scene(name: str, checkpoints: tuple[int, ...], voxel_m: float, variation: Any, backend: str,
              seed: int, progress: bool) -> dict[str, Any]:
    """Fly scene ``name`` for ``max(checkpoints)`` pings, mapping by every rule; score at the checkpoints."""
    from gpumap.sim.metrics import evaluate
    from gpumap.sim.scenes import long_run_scene
    from gpumap.sim.sonar import OCCUPIED_THRESHOLD, SonarSimulator
    from gpumap.sim.truth import detected_points, occupancy, points_to_voxels

    import gpumap
    from gpumap.geometry import RULES

    n = max(checkpoints)
    scene = long_run_scene(name, n, voxel_m, seed=seed)
    t0 = time.perf_counter()
    truth = occupancy(scene, seed=seed)
    truth_s, grid = time.perf_counter() - t0, scene.grid
    mappers = {
        r: gpumap.MinMaxMapper(
            scene.sonar_spec, grid, backend, MapperParams(rule=r, threshold=OCCUPIED_THRESHOLD)
        )
        for r in RULES
    }
    default_rule = default_rule_of(scene.sonar_spec, grid, backend)
    seen, det = np.zeros(grid.n_voxels, bool), np.zeros(grid.n_voxels, bool)
    sim_s, eval_s, map_s, dropped = 0.0, 0.0, dict.fromkeys(RULES, 0.0), 0
    curves: dict[str, list[dict]] = {r: [] for r in RULES}
    # read-time options: the same counts decided at other settings too
    alt = {r: (opt, [v for v in values if v != getattr(mappers[r], opt)])
           for r, (opt, values) in FRONTIERS.items() if r in mappers}
    curves.update({f"{r}@{v:g}": [] for r, (_, values) in alt.items() for v in values})

    def score(m: Any) -> dict:
        ev = evaluate(m.values(), truth, OCCUPIED_THRESHOLD, seen.reshape(grid.shape), voxel_m,
                      detectable=det.reshape(grid.shape)).to_dict()
        return {"pings": k + 1, **{s: ev[s] for s in SCORES}}

    with SonarSimulator(scene, seed=seed, variation=variation, **scene.sonar_params) as sim:
        for k in progress_bar(range(n), disable=not progress, desc=f"{name}", unit="ping"):
            t = time.perf_counter()
            p = sim.ping(scene.T_W_S[k], k)
            img = quantize(p.image)
            seen[points_to_voxels(p.points_W, grid)] = True
            det[points_to_voxels(detected_points(p, OCCUPIED_THRESHOLD), grid)] = True
            dropped += p.dropped
            sim_s += time.perf_counter() - t
            for r, m in mappers.items():
                t = time.perf_counter()
                m.integrate(img, p.T_W_S)
                m.synchronize()
                map_s[r] += time.perf_counter() - t
            if k + 1 in checkpoints:
                t = time.perf_counter()
                for r, m in mappers.items():
                    curves[r].append(score(m))
                    if r in alt:
                        opt, values = alt[r]
                        own = getattr(m, opt)
                        for v in values:
                            setattr(m, opt, v)
                            curves[f"{r}@{v:g}"].append(score(m))
                        setattr(m, opt, own)
                eval_s += time.perf_counter() - t
    return {"pings": n, "voxel_size_m": voxel_m, "grid_shape": list(grid.shape),
            "backend": next(iter(mappers.values())).backend, "rules": list(RULES),
            "default_rule": default_rule,
            "frontiers": {r: {"option": opt, "own": getattr(mappers[r], opt), "values": values}
                          for r, (opt, values) in alt.items()},
            "dropped_pings": int(dropped),
            "curves": curves, "seconds": {"truth": truth_s, "simulate": sim_s, "evaluate": eval_s,
                                          **{f"map_{r}": s for r, s in map_s.items()}},
            "sim_pings_per_s": n / sim_s if sim_s > 0 else None,
            "map_ms_per_ping": {r: 1e3 * s / n for r, s in map_s.items()}}


def default_rule_of(spec: Any, grid: Any, backend: str) -> str:
    """The rule a :class:`gpumap.MinMaxMapper` takes when none is asked for (read off a small map
    of the same sonar, so no name is written here)."""
    import gpumap

    lo = np.asarray(grid.min_corner_m, np.float64)
    box = gpumap.GridSpec(tuple(lo), tuple(lo + 4 * grid.voxel_size_m), grid.voxel_size_m)
    return gpumap.MinMaxMapper(spec, box, backend=backend).rule


def markdown(res: dict, folder: Path) -> str:
    """The BENCHMARKS.md section of a ``long_run.json``: per scene and rule, the misses of the
    objects and of every detectable surface and the far phantoms at each checkpoint."""
    fronts = {r: f["option"] for sc in res["scenes"].values() for r, f in sc.get("frontiers", {}).items()}
    fronts = fronts or {r: opt for r, (opt, _) in FRONTIERS.items()  # files written before "frontiers"
                        if any(c.startswith(f"{r}@") for sc in res["scenes"].values() for c in sc["curves"])}
    out = [common.template("long-run", command=res["command"].strip(), res=res, m=res["machine"],
                           last=res["checkpoints"][-1],
                           fronts=", ".join(f"{r}: {o}" for r, o in fronts.items()) or "none"), "",
           "| scene | rule | " + " | ".join(f"{c} pings" for c in res["checkpoints"]) + " |",
           "|---|---|" + "---|" * len(res["checkpoints"])]
    for name, sc in res["scenes"].items():
        for rule, rows in sc["curves"].items():
            cells = [f"{100 * r['miss_rate_objects']:.1f} / {100 * r['miss_rate']:.1f} / "
                     f"{100 * r['false_positive_rate_far']:.1f} %" for r in rows]
            label = f"{rule} (default)" if rule == sc.get("default_rule") else rule
            out.append(f"| {name} | {label} | " + " | ".join(cells) + " |")
    out += ["", f"![misses and phantoms as pings accumulate]({folder.as_posix()}/long_run.png)"]
    return "\n".join(out)


SECTION = Section("long-run", "## Long simulated runs with the real sonar's variation (issue #28)",
                  "long_run.json", markdown)


def plot(path: Path, scenes: dict[str, dict]) -> None:
    """Miss rate (objects, all) and far false positives against pings, one line per rule."""
    keys = (("miss_rate_objects", "miss rate, objects (FN)"), ("miss_rate", "miss rate, all surface (FN)"),
            ("false_positive_rate_far", "false positives, far (FP)"))
    fig, ax = common.pyplot().subplots(len(scenes), len(keys), figsize=(14, 3.6 * len(scenes)), squeeze=False)
    for i, (name, res) in enumerate(scenes.items()):
        for j, (key, label) in enumerate(keys):
            a = ax[i, j]
            for rule, rows in res["curves"].items():
                a.plot([r["pings"] for r in rows], [r[key] for r in rows], "o-", label=rule)
            a.set(xlabel="pings", ylabel=label, title=f"{name}: {label}", xscale="log")
            if key.startswith("miss"):
                a.set_ylim(0.0, 1.02)
            a.grid(alpha=0.3)
            if j == 0:
                a.legend(fontsize=8)
    common.save_figure(fig, path, dpi=110)


def main(argv: list[str] | None = None) -> int:
    ap = bench_parser("long_run", __doc__, out="bench/results", voxel=0.03, backend="auto", seed=0,
                      progress=True,
                      report="long_run.json")
    ap.add_argument("--scenes", nargs="+", default=["tank", "circle"], choices=["tank", "circle"],
                    help="scenes (default tank circle)")
    ap.add_argument("--checkpoints", type=int, nargs="+", default=None,
                    help=f"pings at which the maps are scored (default {' '.join(map(str, CHECKPOINTS))})")
    ap.add_argument("--variation", default="real_tank", choices=["real_tank", "none"],
                    help="the simulator's view-to-view variation (default real_tank)")
    ap.add_argument("--quick", action="store_true",
                    help=f"a short run: {max(QUICK_CHECKPOINTS)} pings, scored at "
                         f"{' '.join(map(str, QUICK_CHECKPOINTS))}; writes long_run_quick.*")
    a = ap.parse_args(argv)
    if SECTION.reported(a):
        return 0
    from gpumap.sim.sonar import OCCUPIED_THRESHOLD
    from gpumap.sim.variation import SonarVariation

    checkpoints = tuple(sorted(set(a.checkpoints or (QUICK_CHECKPOINTS if a.quick else CHECKPOINTS))))
    if checkpoints[0] < 1:
        raise SystemExit("bench.long_run: checkpoints must be >= 1")
    var = SonarVariation.real_tank() if a.variation == "real_tank" else SonarVariation.none()
    head, t0, scenes = run_header(SCHEMA, argv), time.perf_counter(), {}
    with CpuShare() as share:
        for name in a.scenes:
            scenes[name] = run_scene(name, checkpoints, a.voxel, var, a.backend, a.seed, not a.no_progress)
            for rule, rows in scenes[name]["curves"].items():
                last = rows[-1]
                print(f"{name} {rule:>8} @ {last['pings']}: miss objects {last['miss_rate_objects']:.3f}  "
                      f"miss {last['miss_rate']:.3f}  FP far {last['false_positive_rate_far']:.4f}")
    mark_load(head["machine"], share)
    stem = ("long_run_quick" if a.quick else "long_run") + (
        "" if abs(a.voxel - 0.03) < 1e-9 else f"_{round(a.voxel * 1000)}mm")
    res = {**head, "command": "python -m bench long_run " + " ".join(argv or []),
           "variation": {"name": a.variation, **var.to_dict()}, "checkpoints": list(checkpoints),
           "threshold": OCCUPIED_THRESHOLD,
           "image_dtype": "uint8 (intensity * 255, rounded; as the Oculus delivers)",
           "poses": "the pings' reported poses (nominal; the variation's jitter is the error)",
           "scenes": scenes, "duration_s": time.perf_counter() - t0}
    path = common.write_json(a.out / f"{stem}.json", res, digits=4)
    plot(a.out / f"{stem}.png", scenes)
    print(f"wrote {path} in {res['duration_s']:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
