"""Worker overhead: the survey mapped by one process against N Dask workers on the same cores.

    python -m bench.workers [--backend warp-cpu] [--voxel-size 0.05] [--workers 2] [--reps 3]
                            [--sparse] [--worker-threads N] [--passes K] [--split space|pings]
                            [--section NAME]
                            [--out bench/results/workers.json]

Pings: the survey scene's 200 (``bench/results/tmp/survey_pings.npz``, rendered first if
missing, as ``python -m bench.sparse --render-survey`` renders them), fed as a recording of
float32 frames (byte / 255, what every reader yields) on the scene's grid. Each repetition
times, back to back on this machine:

- ``one``: :func:`gpumap.replay.run_replay` in this process (mapper creation included);
- ``workers``: :func:`gpumap.workers.run_replay_workers` on a LocalCluster of ``--workers``
  single-threaded worker processes started once before the first repetition (the
  ``--scheduler`` case: a running cluster); the first repetition's workers also import and
  initialise their backend (``cold``). Its wall time includes sending the pings, the
  workers' mapper creation, gathering their maps and merging them.

Equal cores: both run on the same machine with the same backend; ``warp-cpu`` splits every
gather into two halves on two threads (``gpumap.backends.CPU_THREADS``), in the one process
and in each worker alike. The first repetition also checks that the merged map equals the
one-process map bit for bit (values and evidence). ``os.getloadavg()`` is recorded around
every run: on a shared machine these are loaded figures, not headlines.
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

from .common import bench_parser, load_average, load_ping_arrays, machine_info, merge_json

TMP = Path("bench/results/tmp")


def survey_recording(path: Path, voxel_size_m: float, passes: int = 1):
    """(Recording of the survey pings as float32 frames, ``passes`` times over, the scene's grid)."""
    import gpumap
    from gpumap.backends import U8_SCALE
    from gpumap.io import Recording, SonarFrame

    if not path.is_file():
        from .sparse import render_survey

        render_survey(path)
    images, poses = load_ping_arrays(path)
    from gpumap.sim.scenes import make_scene

    sc = make_scene("survey", voxel_size_m=voxel_size_m)
    spec, grid = sc.sonar_spec, sc.grid
    assert images.dtype == np.uint8 and isinstance(grid, gpumap.GridSpec)

    def frames():
        for _ in range(passes):
            for img, T in zip(images, poses, strict=True):
                yield SonarFrame(np.multiply(img, U8_SCALE, dtype=np.float32), spec, None, T)

    rec = Recording(str(path), "survey-arrays", frames, True, count=lambda: passes * len(images),
                    poses=lambda: passes * list(poses))
    return rec, grid


def main(argv: list[str] | None = None) -> int:
    p = bench_parser("workers", __doc__)
    p.add_argument("--backend", default="warp-cpu", help="every mapper's backend (default warp-cpu)")
    p.add_argument("--voxel-size", "--voxel", dest="voxel", type=float, default=0.05,
                   help="voxel size, metres (default 0.05)")
    p.add_argument("--workers", type=int, default=2, help="Dask worker processes (default 2)")
    p.add_argument("--reps", type=int, default=3, help="repetitions of the pair (default 3)")
    p.add_argument("--sparse", action="store_true", help="workers keep sparse maps (and so does 'one')")
    p.add_argument("--worker-threads", type=int, default=None,
                   help="threads each worker's CPU backend splits a gather into (default: as one process, 2)")
    p.add_argument("--section", default="dense", help="name of this run's section in --out")
    p.add_argument("--split", default="space", choices=["space", "pings"],
                   help="how pings are shared among the workers (run_replay_workers' split)")
    p.add_argument("--passes", type=int, default=1,
                   help="feed the survey's pings this many times (a resurvey of the same area: more "
                        "pings for the same map size)")
    p.add_argument("--pings", type=Path, default=TMP / "survey_pings.npz", help="survey pings (.npz)")
    p.add_argument("--out", type=Path, default=Path("bench/results/workers.json"))
    args = p.parse_args(argv)

    from distributed import Client, LocalCluster

    from gpumap.replay import run_replay
    from gpumap.sparse import SparseMinMaxMapper, SparseSpec
    from gpumap.workers import run_replay_workers

    rec, grid = survey_recording(args.pings, args.voxel, args.passes)
    kw = dict(backend=args.backend, grid=grid, progress=False)
    cls = None
    if args.sparse:
        def cls(spec, g, **o):  # the bounded sparse map on the grid's lattice
            o.pop("method", None)
            box = SparseSpec(g.voxel_size_m, (g.min_corner_m, g.max_corner_m))
            return SparseMinMaxMapper(spec, box, **o)
    rows = []
    t_start = time.time()
    tc = time.perf_counter()
    cluster = LocalCluster(n_workers=args.workers, threads_per_worker=1, processes=True,
                           dashboard_address=":0", silence_logs=logging.CRITICAL)
    client = Client(cluster)
    seconds_cluster = time.perf_counter() - tc
    try:
        for rep in range(args.reps):
            load0 = load_average()
            t0 = time.perf_counter()
            one, s1 = run_replay(rec, mapper_cls=cls, **kw)
            wall_one = time.perf_counter() - t0
            load1 = load_average()
            t0 = time.perf_counter()
            got, sw = run_replay_workers(rec, workers=args.workers, client=client, sparse=args.sparse,
                                         cpu_threads=args.worker_threads, split=args.split, **kw)
            wall_w = time.perf_counter() - t0
            load2 = load_average()
            row = {
                "rep": rep,
                "cold_workers": rep == 0,
                "frames": s1["frames"],
                "one_wall_s": round(wall_one, 3),
                "one_setup_s": round(s1["seconds_setup"], 3),
                "workers_wall_s": round(wall_w, 3),
                "workers_setup_s": round(sw["seconds_setup"], 3),
                "workers_map_s": round(sw["seconds_map"], 3),
                "workers_gather_s": round(sw["seconds_gather"], 3),
                "workers_merge_s": round(sw["seconds_merge"], 3),
                "per_worker": [{k: (round(v, 3) if isinstance(v, float) else v) for k, v in w.items()}
                               for w in sw["per_worker"]],
                "overhead": round(wall_w / wall_one - 1.0, 4),
                "loadavg_before_one": load0,
                "loadavg_before_workers": load1,
                "loadavg_after": load2,
            }
            if rep == 0:
                a, b = one.evidence(), got.evidence()
                row["bitwise_equal"] = bool(
                    all(np.array_equal(a[k], b[k]) for k in a)
                    and np.array_equal(one.raw_values(), got.raw_values())
                    and one.n_integrated == got.n_integrated
                )
            del one, got
            print(json.dumps(row), flush=True)
            rows.append(row)
    finally:
        client.close()
        cluster.close()
    warm = [r for r in rows if not r["cold_workers"]] or rows
    one_med = statistics.median(r["one_wall_s"] for r in warm)
    w_med = statistics.median(r["workers_wall_s"] for r in warm)
    sec = {
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "command": "python -m bench.workers " + " ".join(argv if argv is not None else sys.argv[1:]),
        "scene": "survey (200 pings, 50 x 20 m lawnmower)",
        "passes": args.passes,
        "voxel_size_m": args.voxel,
        "grid_shape": list(grid.shape),
        "map": "sparse (bounded)" if args.sparse else "dense",
        "backend": args.backend,
        "workers": args.workers,
        "worker_threads": args.worker_threads or "default (2)",
        "split": args.split,
        "cpu_count": os.cpu_count(),
        "machine": machine_info(),
        "seconds_cluster_start": round(seconds_cluster, 3),
        "duration_s": round(time.time() - t_start, 1),
        "note": (
            "one_wall_s: run_replay in one process; workers_wall_s: run_replay_workers on a running "
            "LocalCluster of single-threaded worker processes (cluster start apart: seconds_cluster_start), "
            "sending pings, worker setup, gathering and merging included; overhead = workers / one - 1 "
            "per repetition; summary over the warm repetitions (the first one's workers import their "
            "backend). Same machine, same backend: warp-cpu uses 2 threads per mapper in both. "
            "Loaded machine: see loadavg_* per run."
        ),
        "rows": rows,
        "summary": {
            "one_wall_s_median": one_med,
            "workers_wall_s_median": w_med,
            "overhead_median": round(w_med / one_med - 1.0, 4),
            "overhead_min": min(r["overhead"] for r in warm),
            "bitwise_equal": rows[0].get("bitwise_equal"),
        },
    }
    merge_json(args.out, [args.section], sec, schema="gpumap-bench-workers/1")
    print(json.dumps(sec["summary"]))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
