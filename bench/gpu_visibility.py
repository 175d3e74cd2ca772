"""GPU check of the visibility-aware rule: agreement with the NumPy oracle and speed, plain vs visible.

Two steps, because the GPU machine has no EGL for the simulator:

    python -m bench.gpu_visibility --make-pings bench/results/tmp/tank_pings.npz   # here (CPU)
    python -m bench.gpu_visibility --pings bench/results/tmp/tank_pings.npz        # on the GPU machine

The second writes ``$OUT/gpu_check.json`` (or ``--out``): per backend and rule, the number of
voxels that differ from the oracle after 20 tank pings at 5 cm (0 = bit for bit), and per voxel
size (3 cm, 1 cm, 5 mm) the throughput of 400 sequential ``integrate`` calls (uint8 images,
upload included, one synchronize at the end) and the p50/p99 latency of 100 synchronized calls.
"""
import argparse
import json
import os
import time

import numpy as np

import gpumap


def make_pings(path: str) -> None:
    from gpumap.sim.scenes import make_scene
    from gpumap.sim.sonar import SonarSimulator

    scene = make_scene("tank", voxel_size_m=0.03, seed=0)
    with SonarSimulator(scene, seed=0) as sim:
        imgs = [sim.ping(T, k).image for k, T in enumerate(scene.T_W_S)]
    os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
    np.savez_compressed(path, imgs=np.round(np.array(imgs) * 255).astype(np.uint8), T=scene.T_W_S)


def run(pings: str, out: str) -> None:
    z = np.load(pings)
    imgs, T = z["imgs"], z["T"]
    spec = gpumap.SonarSpec.uniform(hfov_deg=130, vfov_deg=20, n_beams=512, n_bins=400,
                                    range_min_m=0.1, range_max_m=2.0)
    res = {"backends": gpumap.available_backends(), "agree": {}, "speed": []}
    # agreement at 5 cm (the oracle is slow at fine voxels)
    grid = gpumap.GridSpec((-2, -1.5, -0.5), (2, 1.5, 0.5), 0.05)
    ref = {}
    for rule in ("plain", "visible"):
        m = gpumap.MinMaxMapper(spec, grid, backend="numpy", rule=rule)
        for im, P in zip(imgs[:20], T[:20], strict=True):
            m.integrate(im, P)
        ref[rule] = m.raw_values()
    for b in ("warp-cuda", "opencl-gpu"):
        for rule in ("plain", "visible"):
            try:
                m = gpumap.MinMaxMapper(spec, grid, backend=b, rule=rule)
                for im, P in zip(imgs[:20], T[:20], strict=True):
                    m.integrate(im, P)
                v = m.raw_values()
                res["agree"][f"{b}/{rule}"] = int((v != ref[rule]).sum())
            except Exception as e:
                res["agree"][f"{b}/{rule}"] = repr(e)
    print(res["agree"], flush=True)
    for b in ("warp-cuda", "opencl-gpu"):
        for vs in (0.03, 0.01, 0.005):
            grid = gpumap.GridSpec((-2, -1.5, -0.5), (2, 1.5, 0.5), vs)
            for rule in ("plain", "visible"):
                m = gpumap.MinMaxMapper(spec, grid, backend=b, rule=rule)
                for im, P in zip(imgs[:5], T[:5], strict=True):
                    m.integrate(im, P)
                m.synchronize()
                n = 400
                t0 = time.perf_counter()
                for k in range(n):
                    m.integrate(imgs[k % 40], T[k % 40])
                m.synchronize()
                thr = n / (time.perf_counter() - t0)
                lat = []
                for k in range(100):
                    t1 = time.perf_counter()
                    m.integrate(imgs[k % 40], T[k % 40])
                    m.synchronize()
                    lat.append(time.perf_counter() - t1)
                row = {"backend": b, "voxel_m": vs, "rule": rule, "img_per_s": thr,
                       "latency_ms_p50": 1e3 * float(np.percentile(lat, 50)),
                       "latency_ms_p99": 1e3 * float(np.percentile(lat, 99)), "device": m.device}
                res["speed"].append(row)
                print(row, flush=True)
    with open(os.path.join(out, "gpu_check.json"), "w") as f:
        json.dump(res, f, indent=1)


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--make-pings", metavar="NPZ")
    ap.add_argument("--pings", metavar="NPZ")
    ap.add_argument("--out", default=os.environ.get("OUT", "bench/results/tmp"))
    a = ap.parse_args()
    if a.make_pings:
        make_pings(a.make_pings)
    if a.pings:
        run(a.pings, a.out)
