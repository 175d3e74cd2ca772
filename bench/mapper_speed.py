"""Mapper speed: images/s per voxel size x backend x method, image upload included.

The pings are the paper's set-up (130 x 20 deg, 512 beams x 400 bins, 0.1-2 m, a 4 x 3 x 1 m
grid) along a wrist trajectory that pitches the sonar and then moves it, with sparse
speckled images (each ping different, so no cache flatters a backend). Two figures per
row: throughput (pings handed over back to back, one sync at the end: what a stream of
pings sees) and latency (sync after every ping: median and p95). Warm-up pings (not timed)
compile kernels and fill caches.

    python -m bench.mapper_speed --voxel 0.03 0.01 --backend opencl-cpu warp-cpu --out DIR
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

import gpumap

from .common import bench_parser, machine_info, stream_rate, synced_ms, warm_up, write_json

WARMUP = 3


def tank_spec() -> gpumap.SonarSpec:
    return gpumap.SonarSpec.uniform(
        hfov_deg=130, vfov_deg=20, n_beams=512, n_bins=400, range_min_m=0.1, range_max_m=2.0
    )


def tank_grid(voxel_size_m: float) -> gpumap.GridSpec:
    return gpumap.GridSpec((-2.0, -1.5, -0.5), (2.0, 1.5, 0.5), voxel_size_m)


def trajectory(n: int) -> list[np.ndarray]:
    """Sonar poses: pitch sweep in place (first half), then a lateral wrist move."""
    out = []
    for k in range(n):
        u = k / max(1, n - 1)
        pitch = np.deg2rad(12.8 + (25 * np.sin(np.pi * 2 * u) if u < 0.5 else 0))
        y = 0.0 if u < 0.5 else 0.8 * (u - 0.5)
        yaw = 0.3 * np.sin(2 * np.pi * u)
        cp, sp, cy, sy = np.cos(pitch), np.sin(pitch), np.cos(yaw), np.sin(yaw)
        Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
        Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
        T = np.eye(4)
        T[:3, :3] = Rz @ Ry
        T[:3, 3] = (-1.4, y, 0.35)
        out.append(T)
    return out


def images(spec: gpumap.SonarSpec, n: int, seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [(rng.random(spec.image_shape, dtype=np.float32) ** 6) for _ in range(n)]


def time_mapper(backend: str, method: str, voxel: float, n: int, seed: int = 0) -> dict:
    spec = tank_spec()
    grid = tank_grid(voxel)
    imgs = images(spec, min(n, 16), seed)
    poses = trajectory(n)
    t0 = time.perf_counter()
    m = gpumap.MinMaxMapper(spec, grid, backend=backend, method=method)
    warm_up(m, imgs, poses, WARMUP)
    setup_s = time.perf_counter() - t0
    thr = stream_rate(m, imgs, poses, n)  # throughput: back to back
    observed = int(m.observed().sum())
    lat_ms = np.array(synced_ms(m, imgs, poses, min(n, 50)))  # latency: synced per ping
    return {
        "backend": m.backend,
        "backend_requested": backend,
        "device": m.device,
        "method": method,
        "voxel_size_m": voxel,
        "grid_shape": list(grid.shape),
        "images": n,
        "images_per_s": thr,
        "ms_per_image_median": float(np.median(lat_ms)),
        "ms_per_image_p95": float(np.percentile(lat_ms, 95)),
        "setup_s_incl_warmup": setup_s,
        "voxels_observed": observed,
    }


def main(argv: list[str] | None = None) -> int:
    ap = bench_parser("mapper_speed", __doc__)
    ap.add_argument("--voxel-size", "--voxel", dest="voxel", type=float, nargs="+",
                    default=[0.05, 0.03, 0.01],
                    help="voxel edges in metres (default 0.05 0.03 0.01)")
    ap.add_argument("--backend", nargs="+", default=None, help="default: every available backend")
    ap.add_argument("--method", nargs="+", default=["gather", "template"], help="methods (default both)")
    ap.add_argument("--images", type=int, default=None, help="pings per row (default scales with voxel size)")
    ap.add_argument("--out", type=Path, default=Path("bench/results"), help="results folder")
    ap.add_argument("--tag", default="mapper_speed", help="result file stem (default mapper_speed)")
    a = ap.parse_args(argv)
    backends = a.backend or gpumap.available_backends()
    rows = []
    for v in a.voxel:
        for b in backends:
            for meth in a.method:
                n = a.images or (200 if v >= 0.02 else 60)
                if b == "numpy":
                    n = min(n, 10 if v >= 0.02 else 3)
                try:
                    r = time_mapper(b, meth, v, n)
                except Exception as e:  # record and go on: one failing backend must not hide the rest
                    r = {"backend_requested": b, "method": meth, "voxel_size_m": v, "error": repr(e)}
                rows.append(r)
                print(
                    json.dumps(
                        {
                            k: r.get(k)
                            for k in (
                                "backend_requested",
                                "method",
                                "voxel_size_m",
                                "images_per_s",
                                "ms_per_image_median",
                                "error",
                            )
                        }
                    ),
                    flush=True,
                )
    path = write_json(a.out / f"{a.tag}.json",
                      {"machine": machine_info(), "warmup_pings": WARMUP, "rows": rows})
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
