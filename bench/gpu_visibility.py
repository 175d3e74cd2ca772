"""GPU check of the visibility-aware rule: agreement with the NumPy oracle and speed, plain vs visible.

Two steps, because the GPU machine has no EGL for the simulator:

    python -m bench.gpu_visibility --make-pings bench/results/tmp/tank_pings.npz   # here (CPU)
    python -m bench.gpu_visibility --pings bench/results/tmp/tank_pings.npz        # on the GPU machine

The second writes ``$OUT/gpu_check.json`` (or ``--out``): per backend and rule, the number of
voxels that differ from the oracle after 20 tank pings at 5 cm (0 = bit for bit), and per voxel
size (3 cm, 1 cm, 5 mm) the throughput of 400 sequential ``integrate`` calls (uint8 images,
upload included, one synchronize at the end) and the p50/p99 latency of 100 synchronized calls.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

import gpumap

from .common import (
    bench_parser,
    load_ping_arrays,
    quantize,
    render_pings,
    stream_rate,
    synced_ms,
    warm_up,
    write_json,
)
from .mapper_speed import tank_grid, tank_spec

GPU_BACKENDS = ("warp-cuda", "opencl-gpu")
RULES = ("plain", "visible")


def make_pings(path: str | os.PathLike) -> None:
    """Render the tank trajectory's pings (uint8) to ``path`` (.npz: imgs, T)."""
    from gpumap.sim.scenes import make_scene

    scene = make_scene("tank", voxel_size_m=0.03, seed=0)
    imgs = np.stack([quantize(p.image) for p in render_pings(scene, scene_sonar=False)])
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, imgs=imgs, T=scene.T_W_S)


def _integrate_all(m: gpumap.MinMaxMapper, imgs: np.ndarray, T: np.ndarray) -> gpumap.MinMaxMapper:
    for im, P in zip(imgs, T, strict=True):
        m.integrate(im, P)
    return m


def run(pings: str | os.PathLike, out: str | os.PathLike) -> None:
    """Agreement with the oracle at 5 cm, then speed per backend, voxel size and rule; writes
    ``out/gpu_check.json``."""
    imgs, T = load_ping_arrays(pings)
    spec = tank_spec()
    res = {"backends": gpumap.available_backends(), "agree": {}, "speed": []}
    grid = tank_grid(0.05)  # agreement at 5 cm (the oracle is slow at fine voxels)
    ref = {}
    for rule in RULES:
        m = gpumap.MinMaxMapper(spec, grid, backend="numpy", rule=rule)
        ref[rule] = _integrate_all(m, imgs[:20], T[:20]).raw_values()
    for b in GPU_BACKENDS:
        for rule in RULES:
            try:
                m = _integrate_all(gpumap.MinMaxMapper(spec, grid, backend=b, rule=rule), imgs[:20], T[:20])
                res["agree"][f"{b}/{rule}"] = int((m.raw_values() != ref[rule]).sum())
            except Exception as e:
                res["agree"][f"{b}/{rule}"] = repr(e)
    print(res["agree"], flush=True)
    for b in GPU_BACKENDS:
        for vs in (0.03, 0.01, 0.005):
            for rule in RULES:
                m = gpumap.MinMaxMapper(spec, tank_grid(vs), backend=b, rule=rule)
                warm_up(m, imgs, T, 5)
                thr = stream_rate(m, imgs[:40], T[:40], 400)
                lat = synced_ms(m, imgs[:40], T[:40], 100)
                row = {"backend": b, "voxel_m": vs, "rule": rule, "img_per_s": thr,
                       "latency_ms_p50": float(np.percentile(lat, 50)),
                       "latency_ms_p99": float(np.percentile(lat, 99)), "device": m.device}
                res["speed"].append(row)
                print(row, flush=True)
    write_json(Path(out) / "gpu_check.json", res)


def main(argv: list[str] | None = None) -> int:
    ap = bench_parser("gpu_visibility", __doc__)
    ap.add_argument("--make-pings", metavar="NPZ", help="render the tank pings to this file (needs EGL)")
    ap.add_argument("--pings", metavar="NPZ", help="check and time the GPU backends on these pings")
    ap.add_argument("--out", default=os.environ.get("OUT", "bench/results/tmp"),
                    help="folder for gpu_check.json (default $OUT, else bench/results/tmp)")
    a = ap.parse_args(argv)
    if a.make_pings:
        make_pings(a.make_pings)
    if a.pings:
        run(a.pings, a.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
