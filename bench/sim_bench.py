"""Simulator throughput: sonar images per second (and DVL pings per second) on this machine.

Usage::

    python -m bench.sim_bench --out sim_bench.json [--pings 40] [--cameras 3]

The GL renderer in use (Mesa llvmpipe on a CPU-only machine, the GPU's driver otherwise)
is recorded with the numbers.
"""

from __future__ import annotations

import json
import os
import platform
import time

import numpy as np

from .common import bench_parser, gl_renderer, load_average, write_json


def main(argv: list[str] | None = None) -> int:
    p = bench_parser("sim_bench", __doc__)
    p.add_argument("--out", default=None, help="JSON file to write")
    p.add_argument("--pings", type=int, default=40, help="pings timed (default 40)")
    p.add_argument("--cameras", type=int, default=3, help="the simulator's cameras (default 3)")
    p.add_argument("--scene", default="tank", help="scene (default tank)")
    a = p.parse_args(argv)
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

    from gpumap.sim.dvl import DVLSimulator
    from gpumap.sim.scenes import make_scene
    from gpumap.sim.sonar import SonarSimulator

    scene = make_scene(a.scene)
    poses = scene.T_W_S[np.arange(a.pings) % len(scene.T_W_S)]
    t0 = time.perf_counter()
    with SonarSimulator(scene, n_cameras=a.cameras) as sim:
        sim.ping(poses[0], 0)  # GL context, shader compile, upload
        init_s = time.perf_counter() - t0
        gl = gl_renderer()
        t0 = time.perf_counter()
        for i, T in enumerate(poses):
            sim.ping(T, i)
        sonar_s = time.perf_counter() - t0
        rays = sim.rays_per_ping
    dvl = DVLSimulator(scene)
    dposes = scene.T_W_D[np.arange(a.pings) % len(scene.T_W_D)]
    t0 = time.perf_counter()
    for T in dposes:
        dvl.ranges(T)
    dvl_s = time.perf_counter() - t0
    res = {
        "scene": a.scene,
        "gl_renderer": gl,
        "machine": platform.machine(),
        "cpu_count": os.cpu_count(),
        "cameras": a.cameras,
        "rays_per_ping": int(rays),
        "image_shape": list(scene.sonar_spec.image_shape),
        "pings": a.pings,
        "init_s": init_s,
        "sonar_images_per_s": a.pings / sonar_s,
        "sonar_ms_per_image": 1e3 * sonar_s / a.pings,
        "dvl_pings_per_s": a.pings / dvl_s,
        "load_avg": load_average(),
    }
    print(json.dumps(res, indent=1))
    if a.out:
        write_json(a.out, res, indent=2)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
