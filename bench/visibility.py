"""``python -m bench.visibility``: the visible rule against the paper's plain min-max (issue #10).

    python -m bench.visibility                                   # tank and circle, 5 to 1 cm
    python -m bench.visibility --carve-sweep 1 2 3 4 --voxel-sizes 0.03 0.02   # quality only
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

import numpy as np

import gpumap
from gpumap.core.params import MapperParams

from . import common
from .common import CpuShare, bench_parser, progress_bar, simulate, synced_ms, warm_up, write_json

RULES = ("plain", "visible")
THRESHOLD = 0.1
CURVE_THRESHOLDS = np.linspace(0.02, 0.6, 30)
PLOT_VOXEL_M = 0.03
WARMUP = 2  # pings integrated, synchronized and discarded (map reset) before timing
SCORE_KEYS = ("false_negative_rate_detectable", "false_negative_rate_objects_detectable", "miss_rate",
              "miss_rate_objects", "observed_surface_fraction", "false_positive_rate_far",
              "free_carved_fraction",
              "pipe_found", "height_error_m")
# (header, row key, format): the printed table
COLUMNS = (("scene", "scene", "s"), ("voxel", "voxel_cm", "cm"), ("rule", "rule", "s"),
           ("ms/img (median)", "ms_median", ".1f"), ("images/s", "images_per_s", ".0f"),
           ("FN det", "false_negative_rate_detectable", "%"),
           ("FN obj det", "false_negative_rate_objects_detectable", "%"),
           ("miss", "miss_rate", "%"), ("miss obj", "miss_rate_objects", "%"),
           ("obs surface", "observed_surface_fraction", "%"), ("FP far", "false_positive_rate_far", "%"),
           ("water carved", "free_carved_fraction", "%"), ("carved vs plain", "carved_vs_plain", ".2f"),
           ("pipe", "pipe_found", "s"), ("worst height err (vox)", "height_error_worst_vox", "+.1f"))


def _parser() -> argparse.ArgumentParser:
    p = bench_parser("visibility", __doc__, out="bench/results/visibility.json", backend="opencl",
                     voxel=[0.05, 0.03, 0.02, 0.01], seed=0, progress=True)
    p.add_argument("--scenes", nargs="+", default=["tank", "circle"], help="scenes (default tank circle)")
    p.add_argument("--fig-dir", type=Path, default=Path("docs"), help="where the FN-FP plots go")
    p.add_argument("--carve-sweep", type=int, nargs="+", metavar="K",
                   help="quality only: score the visible map at each carve_views K (1..255)")
    return p


def _scene(name: str, v: float, seed: int, pings: list):
    """The scene at voxel edge ``v``, its truth, and the seen / detectable masks of ``pings``."""
    from gpumap.sim.metrics import ground_truth_masks
    from gpumap.sim.scenes import make_scene
    from gpumap.sim.truth import occupancy

    scene = make_scene(name, voxel_size_m=v, seed=seed)
    return scene, occupancy(scene, seed=seed), *ground_truth_masks(pings, scene.grid, THRESHOLD)


def score(values: np.ndarray, truth, seen: np.ndarray, det: np.ndarray, voxel_m: float) -> dict[str, Any]:
    """The scores of :data:`SCORE_KEYS` at :data:`THRESHOLD`, plus the worst height error in voxels."""
    from gpumap.sim.metrics import evaluate

    ev = evaluate(values, truth, THRESHOLD, seen, voxel_m, detectable=det).to_dict()
    he = {k: x for k, x in ev["height_error_m"].items() if x is not None and np.isfinite(x)}
    worst = max(he.values(), key=abs) if he else float("nan")  # signed: + is the elevation stretch
    return {k: ev[k] for k in SCORE_KEYS} | {"height_error_worst_vox": worst / voxel_m}


def carve_sweep(args: argparse.Namespace) -> list[dict]:
    """Rows of the ``--carve-sweep`` run: the plain rule, then the visible rule at each K."""
    rows = []
    for name in args.scenes:
        pings, images, poses, _ = simulate(name, args.seed, not args.no_progress)
        for v in args.voxel:
            scene, truth, seen, det = _scene(name, v, args.seed, pings)
            maps = {}
            for rule in RULES:
                m = maps[rule] = gpumap.MinMaxMapper(
                    scene.sonar_spec, scene.grid, args.backend, MapperParams(rule=rule, threshold=THRESHOLD)
                )
                for img, T in zip(images, poses, strict=True):
                    m.integrate(img, T)
            plain = score(maps["plain"].values(), truth, seen, det, v)
            rows.append({"scene": name, "voxel_cm": v * 100, "rule": "plain", "carve_views": None, **plain,
                         "carved_vs_plain": 1.0})
            for k in args.carve_sweep:
                maps["visible"].carve_views = k
                r = score(maps["visible"].values(), truth, seen, det, v)
                r["carved_vs_plain"] = r["free_carved_fraction"] / plain["free_carved_fraction"]
                rows.append({"scene": name, "voxel_cm": v * 100, "rule": "visible", "carve_views": k, **r})
    return rows


def run_scene(name: str, args: argparse.Namespace, bar) -> tuple[list[dict], dict, dict]:
    """Rows, FN-FP curves (by voxel size, then rule) and simulation facts of one scene."""
    from gpumap.sim.metrics import fn_fp_curve

    pings, images, poses, sim_rate = simulate(name, args.seed, not args.no_progress)
    rows, curves = [], {}
    for v in args.voxel:
        t0 = time.perf_counter()
        scene, truth, seen, det = _scene(name, v, args.seed, pings)
        if not np.allclose(scene.T_W_S, poses):
            raise RuntimeError(f"Expected {name}'s poses not to depend on the voxel size, but {v} m differs")
        truth_s, by_rule = time.perf_counter() - t0, {}
        for rule in RULES:
            bar.set_postfix_str(f"{name} {v * 100:g} cm {rule}")
            m = gpumap.MinMaxMapper(
                scene.sonar_spec, scene.grid, args.backend, MapperParams(rule=rule, threshold=THRESHOLD)
            )
            warm_up(m, images, poses, WARMUP)
            a = np.asarray(synced_ms(m, images, poses))
            values = m.values()
            rows.append({"scene": name, "voxel_size_m": v, "voxel_cm": v * 100, "rule": rule,
                         "backend": m.backend,
                         "device": m.device, "grid_shape": list(scene.grid.shape), "pings": len(images),
                         "truth_s": truth_s, "ms_median": np.median(a), "ms_p95": np.percentile(a, 95),
                         "images_per_s": 1e3 * a.size / a.sum(), **score(values, truth, seen, det, v)})
            curve = fn_fp_curve(values, truth, CURVE_THRESHOLDS, seen, det)
            by_rule[rule] = {k: x.tolist() for k, x in curve.items()}
            bar.update()
        plain = next(r for r in rows if r["voxel_size_m"] == v and r["rule"] == "plain")
        for r in rows[-len(RULES):]:
            r["carved_vs_plain"] = r["free_carved_fraction"] / plain["free_carved_fraction"]
        curves[str(v)] = by_rule
    return rows, curves, {"pings": len(images), "image_shape": list(images.shape[1:]),
                          "simulator_images_per_s": sim_rate}


def plot_curves(name: str, by_rule: dict, path: Path) -> None:
    """Two panels (FN detectable and miss rate against FP far), one curve per rule; dot = 0.1."""
    fig, axes = common.pyplot().subplots(1, 2, figsize=(8, 3.4), dpi=80)
    i = int(np.argmin(np.abs(CURVE_THRESHOLDS - THRESHOLD)))
    for ax, key, label in zip(axes, ("false_negative_rate_detectable", "miss_rate"),
                              ("FN (detectable)", "miss rate (unknown = missed)"), strict=True):
        for rule, color in zip(RULES, ("tab:blue", "tab:orange"), strict=True):
            c = by_rule[rule]
            fp, y = 100 * np.asarray(c["false_positive_rate_far"]), 100 * np.asarray(c[key])
            ax.plot(fp, y, ".-", color=color, label=rule)
            ax.plot(fp[i], y[i], "o", color=color)
        ax.set(xlabel="FP far (%)", ylabel=f"{label} (%)")
        ax.grid(alpha=0.3)
    axes[0].legend(title=f"rule (dot: threshold {CURVE_THRESHOLDS[i]:.2f})", fontsize=8)
    fig.suptitle(f"{name}, {PLOT_VOXEL_M * 100:g} cm: thresholds {CURVE_THRESHOLDS[0]:g} to "
                 f"{CURVE_THRESHOLDS[-1]:g}", fontsize=10)
    common.save_figure(fig, path, dpi=80)


def _cell(x: Any, fmt: str) -> str:
    if x is None or isinstance(x, bool) or (isinstance(x, float) and not np.isfinite(x)):
        return common.fnum(x)
    if fmt in ("%", "cm"):
        return f"{100 * x:.1f} %" if fmt == "%" else f"{x:g} cm"
    return str(x) if fmt == "s" else format(x, fmt)


def markdown_table(rows: list[dict], columns: tuple | list = COLUMNS) -> str:
    """The rows as a markdown table (default :data:`COLUMNS`)."""
    return "\n".join(["| " + " | ".join(h for h, _, _ in columns) + " |",
                      "|" + "|".join("---" if f == "s" else "---:" for _, _, f in columns) + "|",
                      *("| " + " | ".join(_cell(r.get(k), f) for _, k, f in columns) + " |" for r in rows)])


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``python -m bench.visibility``."""
    args, t_start = _parser().parse_args(argv), time.perf_counter()
    if args.carve_sweep:
        if min(args.carve_sweep) < 1 or max(args.carve_sweep) > 255:
            raise SystemExit(f"--carve-sweep: expected values in 1..255, got {args.carve_sweep}")
        rows = carve_sweep(args)
        out = args.out
        if out == _parser().get_default("out"):
            out = out.with_name("visibility_carve.json")
        write_json(out, {**common.run_header("gpumap-visibility-carve/1", argv),
                         "run": {"seed": args.seed, "threshold": THRESHOLD, "backend": args.backend,
                                 "poses": "true (simulator)", "duration_s": time.perf_counter() - t_start},
                         "rows": rows}, indent=None, digits=4)
        keep = SCORE_KEYS + ("carved_vs_plain", "height_error_worst_vox")
        print(markdown_table(rows, [*COLUMNS[:3], ("carve_views", "carve_views", "s"),
                                    *(c for c in COLUMNS if c[1] in keep)]))
        print(f"\nwrote {out}")
        return 0
    head = common.run_header("gpumap-visibility/1", argv)  # not "gpumap-bench/": the report's sweep skips it
    rows, curves, sims = [], {}, {}
    bar = progress_bar(total=len(args.scenes) * len(args.voxel) * len(RULES), desc="visibility", unit="map",
                       disable=args.no_progress)
    with CpuShare() as share:
        for name in args.scenes:
            r, curves[name], sims[name] = run_scene(name, args, bar)
            rows += r
            if str(PLOT_VOXEL_M) in curves[name]:
                plot_curves(name, curves[name][str(PLOT_VOXEL_M)],
                            args.fig_dir / f"visibility_fn_fp_{name}.png")
    bar.close()
    common.mark_load(head["machine"], share)
    result = {**head, "run": {
        "scenes": sims, "seed": args.seed, "threshold": THRESHOLD, "backend": args.backend,
                              "rules": list(RULES),
        "warmup_pings": WARMUP, "poses": "true (simulator)",
        "image_dtype": "uint8 (intensity * 255, rounded; as the Oculus delivers)",
        "timing_note": "each ping integrate()+synchronize(), image upload included; images_per_s = "
        "pings / summed synced time", "curve_thresholds": CURVE_THRESHOLDS.tolist(),
        "duration_s": time.perf_counter() - t_start}, "rows": rows, "fn_fp_curves": curves}
    write_json(args.out, result, indent=None, digits=4)
    print(markdown_table(rows))
    print(f"\nwrote {args.out} in {result['run']['duration_s']:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
