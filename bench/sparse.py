"""Sparse vs dense maps: memory and images per second on the tank and survey pings.

    python -m bench.sparse [--backends warp-cpu,opencl-cpu] [--section cpu] [--out bench/results/sparse.json]
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

import gpumap
from gpumap.core.sparse import SparseMinMaxMapper, SparseSpec

from . import common
from .common import TMP, bench_parser, load_ping_arrays, merge_json, render_survey, stream_rate

MEMORY_KEYS = ("blocks", "observed_voxels", "block_bytes", "observed_bytes", "block_over_observed",
               "pool_bytes",
               "index_bytes", "total_bytes", "dense_bytes")


def _stream(m, images, poses, passes: int, batch: int = 1) -> float:
    """Best images/s over ``passes`` fresh-map streams of every ping, after a warm-up stream; ``batch`` >
    1: ``integrate_batch`` of that many pings at a time."""
    rates = []
    for _ in range(passes + 1):
        m.reset()
        m.synchronize()
        rates.append(stream_rate(m, images, poses, batch=batch))
    return max(rates[1:], default=0.0)


def _row(scene: str, kind: str, backend: str, voxel: float, ips: float, n: int, extra: dict) -> dict:
    r = {"scene": scene, "map": kind, "backend": backend, "voxel_size_m": voxel, "pings": n,
         "images_per_s": round(ips, 1), **extra}
    print(json.dumps(r), flush=True)
    return r


def run_scene(name: str, grid: gpumap.GridSpec, spec: gpumap.SonarSpec, images, poses, backends, passes: int,
              dense: bool, unbounded: bool, batches: tuple[int, ...] = (1,)) -> list[dict]:
    rows, v, grid_bytes = [], grid.voxel_size_m, grid.n_voxels * 9
    maps = [("sparse", SparseSpec(v, (grid.min_corner_m, grid.max_corner_m)))]
    maps += [("sparse-unbounded", SparseSpec(v, origin_m=grid.min_corner_m))] if unbounded else []
    for be in backends:
        ref = None
        if dense:
            d = gpumap.MinMaxMapper(spec, grid, backend=be)
            by_b = {b: round(_stream(d, images, poses, passes, b), 1) for b in batches if b > 1}
            ips, ref = _stream(d, images, poses, passes), d.raw_values()
            rows.append(_row(name, "dense", be, v, ips, len(images), {
                "grid_shape": list(grid.shape), "dense_bytes": grid_bytes,
                "observed_voxels": int(np.isfinite(ref).sum()), "device": d.device,
                "images_per_s_batch": by_b}))
            del d
        for label, sp in maps:
            m = SparseMinMaxMapper(spec, sp, backend=be)
            by_b = {b: round(_stream(m, images, poses, passes, b), 1) for b in batches if b > 1}
            ips, st = _stream(m, images, poses, passes), m.memory_stats()
            extra = {k: st[k] for k in MEMORY_KEYS} | {
                "dense_grid_bytes": grid_bytes,
                "total_over_dense_grid": round(st["total_bytes"] / grid_bytes, 4), "device": m.device,
                "images_per_s_batch": by_b}
            if ref is not None and label == "sparse":
                extra["identical_to_dense"] = bool(np.array_equal(m.raw_values(), ref))
            rows.append(_row(name, label, be, v, ips, len(images), extra))
            del m
    return rows


def _scene_of(name: str, v: float, path: Path) -> tuple[gpumap.GridSpec, gpumap.SonarSpec]:
    """The scene's grid and sonar: from the ping file when it carries them (machines without trimesh),
    else from the scene."""
    with np.load(path, allow_pickle=False) as z:
        if "grid_min" in z.files:
            return (gpumap.GridSpec(tuple(z["grid_min"]), tuple(z["grid_max"]), v),
                    gpumap.SonarSpec.from_dict(json.loads(str(z["spec"]))))
    from gpumap.sim.scenes import make_scene

    sc = make_scene(name, voxel_size_m=v)
    return sc.grid, sc.sonar_spec


def main(argv: list[str] | None = None) -> int:
    p = bench_parser("sparse", __doc__, out="bench/results/sparse.json")
    p.add_argument("--backends", default="warp-cpu,opencl-cpu", help="comma-separated backends")
    p.add_argument("--tank-pings", type=Path, default=TMP / "tank_pings.npz", help="tank pings (.npz)")
    p.add_argument("--survey-pings", type=Path, default=TMP / "survey_pings.npz", help="survey pings (.npz)")
    p.add_argument("--render-survey", action="store_true", help="render the survey pings first")
    p.add_argument("--tank-voxels", default="0.03,0.02,0.01", help="comma-separated tank voxel edges, metres")
    p.add_argument("--survey-voxels", default="0.05,0.02", help="dense rows only at 5 cm and coarser")
    p.add_argument("--passes", type=int, default=2, help="timed streams per row, the best kept (default 2)")
    p.add_argument("--batch", default="1", help="also time integrate_batch of these sizes (e.g. 1,8)")
    p.add_argument("--section", default="cpu", help="name of this run's section in --out")
    a = p.parse_args(argv)
    backends = [b for b in a.backends.split(",") if b]
    batches = tuple(int(b) for b in a.batch.split(",") if b)
    rows, t0 = [], time.time()
    if a.tank_pings.is_file() and a.tank_voxels:
        images, poses = load_ping_arrays(a.tank_pings)
        for v in (float(x) for x in a.tank_voxels.split(",") if x):
            grid, spec = _scene_of("tank", v, a.tank_pings)
            rows += run_scene("tank", grid, spec, images, poses, backends, a.passes, True, False, batches)
    if a.render_survey:
        render_survey(a.survey_pings)
    if a.survey_pings.is_file():
        images, poses = load_ping_arrays(a.survey_pings)
        for v in (float(x) for x in a.survey_voxels.split(",") if x):
            grid, spec = _scene_of("survey", v, a.survey_pings)
            dense = grid.n_voxels * 9 < 1.5e9
            rows += run_scene("survey", grid, spec, images, poses, backends, a.passes if dense else 1, dense,
                              v >= 0.05, batches)
    note = ("images_per_s: integrate() per ping, images_per_s_batch: integrate_batch() of B pings at a "
            "time; best of --passes back-to-back streams over every ping of the set into a fresh map (uint8 "
            "images, one synchronize at the end, warm-up pass untimed); bytes: dense = grid voxels x 9 "
            "(float32 min_all + float32 bright + uint8 count, the visible rule); sparse: memory_stats() "
            "after the stream (block_bytes = blocks x 512 voxels x 9; total = pool incl. spare slots + "
            "coarse index)")
    merge_json(a.out, [a.section], {"created": common.now(), "machine": common.machine_info(),
                                    "argv": argv if argv is not None else sys.argv[1:],
                                    "duration_s": round(time.time() - t0, 1), "rows": rows},
               schema="gpumap-bench-sparse/1", note=note)
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
