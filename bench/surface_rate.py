"""``python -m bench surface_rate``: the live surface layer at the sonar's rate on the full real tank run.

**Stream** (per mapper backend): the full run (1,223 frames, 5 cm, threshold 0.4), read into memory
first (not timed), is played at ``--hz`` (default 20, the sonar's rate) in real time, in one thread:
each cycle maps the pings that have arrived (``integrate_batch``) and hands them to
:class:`gpumap.layers.surface_live.LiveSurface`, then updates the layer of every ping so far (each update
equals the
offline layer of those pings). A ping's *age* is the time from its arrival to the end of the first
update that covers it. Recorded: updates, their seconds, the ages, the layer's work per ping (add +
updates over the pings), the mapping's, and whether the layer kept pace (the last update ended within
``--pace-s`` of the last arrival). The layer is host NumPy whatever the backend: the backend only maps
and gives the map to read.

**Replay** (``--replay-pairs N``): ``gpumap replay`` of the full run (5 cm, ``--no-pictures``) writing
the safe layer alone (``--no-surface``) and both layers, alternating (safe, both, both, safe, ...) in
one session so that load drifts hit both alike; wall seconds of each run and the ratio per pair.

Writes ``bench/results/surface_rate.json``; about 3 minutes a backend and 1 a replay run on 2 cores::

    python -m bench surface_rate --backends opencl-cpu warp-cpu --replay-pairs 2
    python -m bench surface_rate --report BENCHMARKS.md
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from gpumap.core.params import MapperParams

from . import common
from .common import CpuShare, Section, bench_parser, load_average, oasis_full_dir, run_header, write_json

SCHEMA = "gpumap-surface-rate/1"
HEADING = "## The live surface layer at the sonar's rate (issue #37)"


def _parser():
    p = bench_parser("surface_rate", __doc__, out="bench/results", voxel=0.05, report="surface_rate.json")
    p.add_argument("--data", type=Path, default=None, help="the full tank run (default: oasis_tank_full)")
    p.add_argument("--backends", nargs="+", default=["opencl-cpu", "warp-cpu"],
                   help="mapper backends to stream on (default opencl-cpu warp-cpu)")
    p.add_argument("--hz", type=float, default=20.0, help="ping rate of the stream (default 20)")
    p.add_argument("--frames", type=int, default=None, help="the first N frames only (default all)")
    p.add_argument("--pace-s", type=float, default=1.0,
                   help="the layer kept pace when its last update ended within this of the last arrival")
    p.add_argument("--replay-pairs", type=int, default=0, help="gpumap replay safe/both pairs (default 0)")
    p.add_argument("--threshold", type=float, default=0.4, help="bright / occupied (default 0.4)")
    return p


def _load(path: Path, n: int | None):
    from gpumap.io import open_recording

    rec = open_recording(path)
    frames = [(np.array(f.image), f.T_W_S, f.spec) for f in rec if f.T_W_S is not None][:n]
    return frames[0][2], np.stack([f[0] for f in frames]), np.stack([f[1] for f in frames])


def stream(spec, grid, images, poses, backend: str, hz: float, threshold: float, pace_s: float) -> dict:
    """Play ``images`` at ``hz`` in real time through a mapper and its LiveSurface (module docstring)."""
    import gpumap
    from gpumap.layers.surface_live import LiveSurface

    m = gpumap.MinMaxMapper(spec, grid, backend, MapperParams(threshold=threshold))
    m.integrate_batch(images[:1], poses[:1])  # kernels built and warmed before the clock starts
    m.reset()
    live = LiveSurface(m)
    n = len(images)
    mapped = covered = 0
    ages, updates = np.zeros(n), []
    t_map = t_add = t_upd = 0.0
    load0 = load_average()
    with CpuShare() as share:
        t0 = time.perf_counter()
        while covered < n:
            now = time.perf_counter() - t0
            due = min(n, int(now * hz) + 1)
            if due == mapped == covered:  # nothing new: wait for the next ping
                time.sleep(max(0.0, mapped / hz - now))
                continue
            a = time.perf_counter()
            if due > mapped:
                m.integrate_batch(images[mapped:due], poses[mapped:due])
                m.synchronize()
                b = time.perf_counter()
                live.add(images[mapped:due], poses[mapped:due])
                t_map, t_add = t_map + b - a, t_add + time.perf_counter() - b
                mapped = due
            b = time.perf_counter()
            layer = live.update()
            e = time.perf_counter()
            t_upd += e - b
            ages[covered:mapped] = (e - t0) - np.arange(covered, mapped) / hz
            updates.append({"pings": mapped, "seconds": e - b, "pairs": layer.stats.get("pairs"),
                            "candidates": layer.stats["candidates"], "surface": layer.stats["surface"]})
            covered = mapped
        t_end = time.perf_counter() - t0
    last_arrival = (n - 1) / hz
    return {"backend": m.backend, "pings": n, "hz": hz, "updates": updates, "seconds_wall": t_end,
            "seconds_map": t_map, "seconds_add": t_add, "seconds_update": t_upd,
            "age_s": {"median": float(np.median(ages)), "p90": float(np.percentile(ages, 90)),
                      "max": float(ages.max())},
            "surface_ms_per_ping": 1e3 * (t_add + t_upd) / n, "map_ms_per_ping": 1e3 * t_map / n,
            "surface_pings_per_s": n / (t_add + t_upd), "lag_after_last_s": t_end - last_arrival,
            "kept_pace": bool(t_end - last_arrival <= pace_s), "pace_s": pace_s,
            "surface_voxels": int(layer.surface.sum()), "candidates": int(layer.stats["candidates"]),
            "pairs": layer.stats.get("pairs"), "load_avg_before": load0, "load_avg_after": load_average(),
            "others_cores": share.others_cores}


def replay_pairs(data: Path, voxel: float, pairs: int) -> dict:
    """``gpumap replay`` with and without the surface layer, alternating (module docstring)."""
    runs = []
    order = [("safe", "both") if k % 2 == 0 else ("both", "safe") for k in range(pairs)]
    with tempfile.TemporaryDirectory() as tmp:
        for k, pair in enumerate(order):
            for what in pair:
                out = Path(tmp) / f"{what}{k}"
                cmd = [sys.executable, "-m", "gpumap.commands", "replay", str(data), "--voxel-size",
                       str(voxel), "--no-pictures", "--no-progress", "--out", str(out)]
                cmd += ["--no-surface"] if what == "safe" else []
                load0 = load_average()
                t = time.perf_counter()
                subprocess.run(cmd, check=True, capture_output=True)
                wall = time.perf_counter() - t
                s = json.loads((out / "summary.json").read_text())
                runs.append({"pair": k, "layers": what, "seconds_wall": wall,
                             "seconds_total": s["seconds_total"], "frames": s["frames"],
                             "backend": s["backend"], "surface": s.get("surface"),
                             "load_avg_before": load0, "load_avg_after": load_average()})
                print(f"replay {what} (pair {k}): {wall:.1f} s wall", flush=True)
    ratios = [next(r["seconds_wall"] for r in runs if r["pair"] == k and r["layers"] == "both")
              / next(r["seconds_wall"] for r in runs if r["pair"] == k and r["layers"] == "safe")
              for k in range(pairs)]
    return {"runs": runs, "ratios": ratios, "ratio_median": float(np.median(ratios)),
            "command": "gpumap replay FULL_RUN --voxel-size 0.05 --no-pictures --no-progress [--no-surface]"}


def main(argv: list[str] | None = None) -> int:
    a = _parser().parse_args(argv)
    if SECTION.reported(a):
        return 0
    data = a.data or oasis_full_dir()
    if data is None:
        raise SystemExit("bench.surface_rate: the full tank run was not found; get it as "
                         "shared/data/README.md says (oasis_tank_full/get_images.sh) and pass --data")
    from gpumap.spec import auto_grid

    t_start = time.perf_counter()
    spec, images, poses = _load(data, a.frames)
    grid = auto_grid(spec, list(poses), a.voxel)
    res = {**run_header(SCHEMA, argv), "data": str(data), "voxel_size_m": a.voxel, "threshold": a.threshold,
           "grid_shape": list(grid.shape), "frames": len(images), "streams": []}
    for backend in a.backends:
        r = stream(spec, grid, images, poses, backend, a.hz, a.threshold, a.pace_s)
        res["streams"].append(r)
        print(f"{r['backend']}: {r['pings']} pings at {a.hz:g} Hz, {len(r['updates'])} updates, age median "
              f"{r['age_s']['median']:.1f} s max {r['age_s']['max']:.1f} s, surface "
              f"{r['surface_ms_per_ping']:.1f} ms a ping, kept pace: {r['kept_pace']}", flush=True)
    if a.replay_pairs:
        res["replay"] = replay_pairs(data, a.voxel, a.replay_pairs)
    res["seconds_total"] = time.perf_counter() - t_start
    path = write_json(a.out / "surface_rate.json", res, digits=4)
    print(f"wrote {path}; BENCHMARKS.md: python -m bench surface_rate --report BENCHMARKS.md")
    return 0


def markdown(res: dict, folder: Path) -> str:
    """The BENCHMARKS.md section of a ``surface_rate.json``."""
    m = res["machine"]
    out = [common.template("surface-rate", res=res, m=m, load=m.get("load_avg_start"),
                           cpus=m.get("affinity_cpus") or m["cpu_count"]),
           "", "| backend | pings at Hz | updates | update s (first / median / last) | pairs at the end | "
           "layer age s (median / p90 / max) | surface ms a ping (mapping) | kept pace | "
           "load before -> after, others' cores |", "|---|---|---|---|---|---|---|---|---|"]
    for r in res["streams"]:
        u = [x["seconds"] for x in r["updates"]]
        lb = (r.get("load_avg_before") or [float("nan")])[0]
        la = (r.get("load_avg_after") or [float("nan")])[0]
        out.append(f"| {r['backend']} | {r['pings']} at {r['hz']:g} | {len(u)} | {u[0]:.2f} / "
                   f"{np.median(u):.2f} / {u[-1]:.2f} | {r['pairs']:,} | {r['age_s']['median']:.1f} / "
                   f"{r['age_s']['p90']:.1f} / {r['age_s']['max']:.1f} | {r['surface_ms_per_ping']:.1f} "
                   f"({r['map_ms_per_ping']:.1f}) | "
                   f"{common.fnum(r['kept_pace'])} (last update {r['lag_after_last_s']:.1f} s after the last "
                   f"ping) | {lb:.1f} -> {la:.1f}, {common.fnum(r['others_cores'], '.2f')} |")
    rp = res.get("replay")
    if rp:
        out += ["", common.template("surface-rate-replay", rp=rp, backend=rp["runs"][0]["backend"],
                                    pairs=len(rp["ratios"]))]
        out += ["", "| pair | safe layer alone s | both layers s (the layer's s after mapping) | ratio | "
                "load at the start |", "|---|---|---|---|---|"]
        for k, ratio in enumerate(rp["ratios"]):
            s = next(r for r in rp["runs"] if r["pair"] == k and r["layers"] == "safe")
            b = next(r for r in rp["runs"] if r["pair"] == k and r["layers"] == "both")
            out.append(f"| {k} | {s['seconds_wall']:.1f} | {b['seconds_wall']:.1f} "
                       f"({b['surface']['seconds_after_mapping']:.1f}) | {ratio:.2f}x | "
                       f"{(s['load_avg_before'] or [float('nan')])[0]:.1f}, "
                       f"{(b['load_avg_before'] or [float('nan')])[0]:.1f} |")
    return "\n".join(out)


SECTION = Section("surface-rate", HEADING, "surface_rate.json", markdown)


if __name__ == "__main__":
    raise SystemExit(main())
