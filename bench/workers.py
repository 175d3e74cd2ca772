"""Worker overhead: the survey mapped by one process against N Dask workers on the same cores.

    python -m bench.workers [--workers 2] [--reps 3] [--sparse] [--worker-threads N] [--section NAME]
"""

from __future__ import annotations

import json
import logging
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np

from gpumap.core.params import MapperParams

from . import common
from .common import TMP, bench_parser, load_average, load_ping_arrays, merge_json, render_survey


def survey_recording(path: Path, voxel_size_m: float, passes: int = 1):
    """(Recording of the survey pings as float32 frames, ``passes`` times over, the scene's grid)."""
    from gpumap.sim.scenes import make_scene

    from gpumap.backends import U8_SCALE
    from gpumap.io import Recording, SonarFrame

    if not path.is_file():
        render_survey(path)
    images, poses = load_ping_arrays(path)
    sc = make_scene("survey", voxel_size_m=voxel_size_m)
    if images.dtype != np.uint8:
        raise ValueError(f"Expected uint8 survey pings in {path}, but got {images.dtype}")

    def frames():
        for _ in range(passes):
            for img, T in zip(images, poses, strict=True):
                yield SonarFrame(np.multiply(img, U8_SCALE, dtype=np.float32), sc.sonar_spec, None, T)

    return Recording(str(path), "survey-arrays", frames, True, count=lambda: passes * len(images),
                     poses=lambda: passes * list(poses)), sc.grid


def main(argv: list[str] | None = None) -> int:
    p = bench_parser("workers", __doc__, out="bench/results/workers.json", backend="warp-cpu", voxel=0.05)
    p.add_argument("--workers", type=int, default=2, help="Dask worker processes (default 2)")
    p.add_argument("--reps", type=int, default=3, help="repetitions of the pair (default 3)")
    p.add_argument("--sparse", action="store_true", help="workers keep sparse maps (and so does 'one')")
    p.add_argument("--worker-threads", type=int, default=None,
                   help="threads each worker's CPU backend splits a gather into (default: as one process, 2)")
    p.add_argument("--section", default="dense", help="name of this run's section in --out")
    p.add_argument("--split", default="space", choices=["space", "pings"],
                   help="how pings are shared among the workers (run_replay_workers' split)")
    p.add_argument("--passes", type=int, default=1,
                   help="feed the survey's pings this many times (a resurvey "
                   "of the same area: more pings for the same map size)")
    p.add_argument("--pings", type=Path, default=TMP / "survey_pings.npz", help="survey pings (.npz)")
    a = p.parse_args(argv)
    from distributed import Client, LocalCluster

    from gpumap.core.sparse import SparseMinMaxMapper, SparseSpec
    from gpumap.pipeline.replay import run_replay
    from gpumap.pipeline.workers import run_replay_workers

    rec, grid = survey_recording(a.pings, a.voxel, a.passes)
    kw = dict(backend=a.backend, grid=grid, progress=False)

    def sparse_cls(spec, g, backend="auto", params=None):  # the bounded sparse map on the grid's lattice
        params = (params or MapperParams()).replace(method="gather")
        return SparseMinMaxMapper(spec, SparseSpec(g.voxel_size_m, (g.min_corner_m, g.max_corner_m)), backend,
                                  params)

    rows, t_start, tc = [], time.time(), time.perf_counter()
    cluster = LocalCluster(n_workers=a.workers, threads_per_worker=1, processes=True, dashboard_address=":0",
                           silence_logs=logging.CRITICAL)
    client = Client(cluster)
    seconds_cluster = time.perf_counter() - tc
    try:
        for rep in range(a.reps):
            load0, t0 = load_average(), time.perf_counter()
            one, s1 = run_replay(rec, mapper_cls=sparse_cls if a.sparse else None, **kw)
            wall_one, load1, t0 = time.perf_counter() - t0, load_average(), time.perf_counter()
            got, sw = run_replay_workers(rec, workers=a.workers, client=client, sparse=a.sparse,
                                         cpu_threads=a.worker_threads, split=a.split, **kw)
            wall_w = time.perf_counter() - t0
            row = {"rep": rep, "cold_workers": rep == 0, "frames": s1["frames"],
                   "one_wall_s": round(wall_one, 3),
                   "one_setup_s": round(s1["seconds_setup"], 3), "workers_wall_s": round(wall_w, 3),
                   **{f"workers_{k}_s": round(sw[f"seconds_{k}"], 3)
                      for k in ("setup", "map", "gather", "merge")},
                   "per_worker": [{k: (round(v, 3) if isinstance(v, float) else v) for k, v in w.items()}
                                  for w in sw["per_worker"]],
                   "overhead": round(wall_w / wall_one - 1.0, 4), "loadavg_before_one": load0,
                   "loadavg_before_workers": load1, "loadavg_after": load_average()}
            if rep == 0:
                ea, eb = one.evidence(), got.evidence()
                row["bitwise_equal"] = bool(all(np.array_equal(ea[k], eb[k]) for k in ea)
                                            and np.array_equal(one.raw_values(), got.raw_values())
                                            and one.n_integrated == got.n_integrated)
            del one, got
            print(json.dumps(row), flush=True)
            rows.append(row)
    finally:
        client.close()
        cluster.close()
    warm = [r for r in rows if not r["cold_workers"]] or rows
    one_med, w_med = (statistics.median(r[k] for r in warm) for k in ("one_wall_s", "workers_wall_s"))
    sec = {
        "created": common.now(),
           "command": "python -m bench.workers " + " ".join(sys.argv[1:] if argv is None else argv),
        "scene": "survey (200 pings, 50 x 20 m lawnmower)", "passes": a.passes, "voxel_size_m": a.voxel,
        "grid_shape": list(grid.shape), "map": "sparse (bounded)" if a.sparse else "dense",
           "backend": a.backend,
        "workers": a.workers, "worker_threads": a.worker_threads or "default (2)", "split": a.split,
        "cpu_count": os.cpu_count(), "machine": common.machine_info(),
           "seconds_cluster_start": round(seconds_cluster, 3),
        "duration_s": round(time.time() - t_start, 1),
        "note": "one_wall_s: run_replay in one process; workers_wall_s: run_replay_workers on a running "
        "LocalCluster of single-threaded worker processes (cluster start apart: seconds_cluster_start), "
        "sending pings, worker setup, gathering and merging included; overhead = workers / one - 1 "
        "per repetition; summary over the warm repetitions (the first one's workers import their "
        "backend). Same machine, same backend: warp-cpu uses 2 threads per mapper in both. "
        "Loaded machine: see loadavg_* per run.",
        "rows": rows,
        "summary": {"one_wall_s_median": one_med, "workers_wall_s_median": w_med,
                    "overhead_median": round(w_med / one_med - 1.0, 4),
                    "overhead_min": min(r["overhead"] for r in warm),
                    "bitwise_equal": rows[0].get("bitwise_equal")}}
    merge_json(a.out, [a.section], sec, schema="gpumap-bench-workers/1")
    print(json.dumps(sec["summary"]))
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
