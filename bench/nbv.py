"""Next best views: planned vs evenly spread rolled vs random views, and the view gain's speed.

    python -m bench.nbv [--scenes tank,circle,survey] [--plan 10] [--section cpu]
    python -m bench.nbv --speed-only --section gpu      # view_gain timing only (needs the saved map)
"""

from __future__ import annotations

import os
import platform
import time
from pathlib import Path

import numpy as np

import gpumap
from gpumap.layers.confidence import with_confidence

from . import common
from .common import TMP, Section, bench_parser, load_average, merge_json, render_pings

MAP = TMP / "nbv_tank_map.npz"
VOXEL_M = {"tank": 0.03, "circle": 0.03, "survey": 0.10}
#: Trajectory pings used (evenly spaced, as ``gpumap demo --pings``); None: all.
PINGS = {"survey": 45}
N_CANDIDATES = 10_000


def _simulate(scene_name: str):
    """The scene and its trajectory pings (every one, or ``PINGS`` evenly spaced)."""
    from gpumap.sim.scenes import make_scene

    scene = make_scene(scene_name, voxel_size_m=VOXEL_M[scene_name], seed=0)
    sel = np.arange(len(scene.T_W_S))
    if PINGS.get(scene_name):
        sel = np.unique(np.linspace(0, len(sel) - 1, PINGS[scene_name]).round().astype(int))
    return scene, scene.T_W_S[sel], render_pings(scene, select=sel)


def _save_speed_map(scene, pings, backend: str) -> None:
    """The tank map (with its confidence layer) and poses the speed rows score candidates on."""
    m = with_confidence(gpumap.MinMaxMapper(scene.sonar_spec, scene.grid, backend=backend))
    m.integrate_batch(np.stack([p.image for p in pings]), scene.T_W_S)
    TMP.mkdir(parents=True, exist_ok=True)
    m.save(MAP)
    np.save(TMP / "nbv_tank_poses.npy", scene.T_W_S)


def quality(scene_name: str, n_plan: int, backend: str, out_dir: Path, quiet: bool,
            unknown_weight: float) -> dict:
    from gpumap.sim.plan_demo import run_plan
    from gpumap.sim.truth import occupancy

    scene, T_traj, pings = _simulate(scene_name)
    truth = occupancy(scene, seed=0)
    out_dir.mkdir(parents=True, exist_ok=True)
    if scene_name == "tank":
        _save_speed_map(scene, pings, backend)
    res = run_plan(scene, pings, T_traj, truth, n_plan, backend, 0.1, 0, quiet, out_dir, unknown_weight)
    return res | {"voxel_size_m": VOXEL_M[scene_name], "trajectory_pings": len(pings)}


def speed(repeat: int) -> dict:
    from gpumap.layers.viewgain import _fov, candidate_poses, gain_points, poses_to_rows, view_gain_reference

    if not (MAP.exists() and (TMP / "nbv_tank_poses.npy").exists()):  # --speed-only on a fresh checkout
        scene, _, pings = _simulate("tank")
        _save_speed_map(scene, pings, "auto")
    poses = np.load(TMP / "nbv_tank_poses.npy")
    per = -(-N_CANDIDATES // len(poses))
    # candidate_poses' default offsets are the demo's wrist limits (gpumap.sim.plan_demo.WRIST_LIMITS)
    C = np.concatenate([candidate_poses(T, per, seed=k) for k, T in enumerate(poses)])[:N_CANDIDATES]
    ref, rows = None, {}
    for b in gpumap.available_backends():
        try:
            m = gpumap.MinMaxMapper.load(MAP, backend=b)
        except Exception as e:  # a backend listed but unable to build here: say so
            rows[b] = {"error": repr(e)[:300]}
            continue
        m.layer("confidence").gains(C[:16])
        best = np.inf
        for _ in range(repeat):
            t0 = time.perf_counter()
            g = m.layer("confidence").gains(C)
            best = min(best, time.perf_counter() - t0)
        if ref is None:
            pts = gain_points(
                m.raw_values(),
                m.layer("confidence").states() == 3,
                m.threshold,
                m.grid,
                m.layer("confidence").arcs,
            )
            s, u = view_gain_reference(poses_to_rows(C), pts, _fov(m._params))
            ref, n_points = s + 1.0 * u, int(pts.points.shape[0])
        rows[b] = {"device": m.device, "seconds": best, "candidates_per_s": N_CANDIDATES / best,
                   "equal_to_reference": bool(np.array_equal(g, ref)), "loadavg": load_average()}
        print(f"{b:12s} {best:.3f} s for {N_CANDIDATES} candidates  equal={rows[b]['equal_to_reference']}  "
              f"load {rows[b]['loadavg']}", flush=True)
    return {"candidates": N_CANDIDATES, "points": n_points, "map": str(MAP), "machine": platform.node(),
            "cpus": os.cpu_count(), "rows": rows}


def markdown(data: dict, folder: Path) -> str:
    """The BENCHMARKS.md block of a results file (every figure read from it)."""
    out = [common.template("nbv-intro"), ""]
    for key, title in (("quality", "planner gain as the demo runs it (unknown_weight 0)"),
                       ("quality_unknown_weight_1",
                        "planner gain counting never-observed voxels too (unknown_weight 1)")):
        if key not in data:
            continue
        out += [f"**{title}**", "", common.template("nbv-quality-head")]
        for scene, q in data[key].items():
            c0 = q["arms"]["planned"]["curve"][0]
            out.append(f"| {scene} | {100 * q['voxel_size_m']:g} cm | {c0['pings']} | trajectory | "
                       f"{100 * c0['false_positive_rate_far']:.1f} % | "
                       f"{c0.get('false_positive_far_voxels', '–')} | "
                       f"{100 * c0['false_negative_rate_objects_detectable']:.1f} % | "
                       f"{c0['worst_object_top_m']:+.3f} m | | |")
            for arm, r in q["arms"].items():
                c, cf = r["curve"][-1], r["confidence"]
                out.append(f"| | | {c['pings']} | {arm} | {100 * c['false_positive_rate_far']:.1f} % | "
                           f"{c.get('false_positive_far_voxels', '–')} | "
                           f"{100 * c['false_negative_rate_objects_detectable']:.1f} % | "
                           f"{c['worst_object_top_m']:+.3f} m | {cf['confirmed_voxels']} "
                           f"({100 * cf['confirmed_far_fraction']:.1f} %) | "
                           f"{100 * cf['far_occupied_unconfirmed_fraction']:.1f} % |")
        out.append("")
    out.append(common.template("nbv-speed-head"))
    for sec, sp in data.get("speed", {}).items():
        for b, r in sp["rows"].items():
            if "seconds" not in r:
                out.append(f"| {sec} | {b} | – | could not run: {r.get('error', '')[:80]} | | |")
                continue
            la = ", ".join(f"{x:.1f}" for x in r["loadavg"])
            out.append(f"| {sec} | {b} | {r['device']} | {r['seconds']:.3f} | {r['equal_to_reference']} "
                       f"| {la} |")
    return "\n".join(out)


SECTION = Section("nbv", "## Next best views and the confidence layer (issue 20)", "nbv.json", markdown)


def main(argv: list[str] | None = None) -> int:
    p = bench_parser("nbv", __doc__, out="bench/results/nbv.json", backend="warp-cpu", progress=True,
                     report="nbv.json")
    p.add_argument("--scenes", default="tank,circle,survey",
                   help="comma-separated scenes for the quality rows")
    p.add_argument("--plan", type=int, default=10, help="views added by each arm")
    p.add_argument("--unknown-weight", type=float, default=0.0,
                   help="weight of a never-observed voxel in the planner's gain (the demo's is 0)")
    p.add_argument("--section", default="cpu", help="key of the speed rows in the results file")
    p.add_argument("--repeat", type=int, default=3, help="timed view_gain calls per backend (best kept)")
    p.add_argument("--speed-only", action="store_true", help="only the view_gain timing")
    p.add_argument("--pictures", default="bench/results/tmp/nbv", help="folder for the quality pictures")
    a = p.parse_args(argv)
    if a.report is not None:  # the results file is --out itself
        SECTION.write(a.report, a.out.parent)
        return 0
    key = "quality" if a.unknown_weight == 0 else f"quality_unknown_weight_{a.unknown_weight:g}"
    if not a.speed_only:
        for s in a.scenes.split(","):
            t0 = time.perf_counter()
            res = quality(s, a.plan, a.backend, Path(a.pictures) / s, a.no_progress, a.unknown_weight)
            merge_json(a.out, [key, s], res | {"loadavg": load_average()})
            fin = {k: v["curve"][-1] for k, v in res["arms"].items()}
            print(s, f"{time.perf_counter() - t0:.0f} s",
                  {k: round(v["false_positive_rate_far"], 3) for k, v in fin.items()}, flush=True)
    merge_json(a.out, ["speed", a.section], speed(a.repeat))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
