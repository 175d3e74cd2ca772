"""``python -m bench.speed``: latency and throughput on the real OASIS tank frames, and the public
OASIS code beside them; ``--synthetic``: the synthetic tank; ``--gpu-check``: the GPU backends against
the NumPy oracle on simulated tank pings (bench/README.md tells more).

    python -m bench.speed --oasis-src /path/to/oasis_iros          # CPU machine
    python -m bench.speed --gpu --frames-from bench/results/tmp/oasis_polar.npz --out $OUT
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

import gpumap
from gpumap.core.params import MapperParams

from . import common
from .common import GPU_BACKENDS, TMP, CpuShare, bench_parser, stream_rate, synced_ms, warm_up, write_json
from .oasis_public import import_oasis as _import_oasis  # noqa: F401 (bench.peer_ratio takes it here)
from .oasis_public import oasis_mapper

CACHE = TMP / "oasis_polar.npz"
#: The OASIS configuration's grid box (configs/base.yaml of the public code), metres.
OASIS_BOX = ((-0.5, -1.2, -0.5), (1.9, 1.2, 0.8))
#: OASIS voxel = range resolution (2 m / 398 bins) x its image downsample factor.
OASIS_RES_M = 2.0 / 398
CPU_VOXELS = (10 * OASIS_RES_M, 6 * OASIS_RES_M, 0.01)
GPU_VOXELS = (0.03, 0.01, 0.005)
RATES_HZ = (10, 20, 40)
WARMUP = 3


@dataclass
class Frames:
    """Real tank frames: polar uint8 images, poses, the spec, and the fan PNG paths."""

    images: np.ndarray
    poses: np.ndarray
    spec: gpumap.SonarSpec
    pngs: list[str]
    polar_ms: float | None = None  # fan -> polar conversion per frame, when measured here


def load_frames(path: Path | None = None) -> Frames:
    """The tank frames from ``path`` (a cache written here) or from shared/data (then cached)."""
    if path is not None and Path(path).is_file():
        with np.load(path) as z:
            return Frames(z["imgs"], z["T"], gpumap.SonarSpec.from_dict(json.loads(str(z["spec"]))),
                          json.loads(str(z["pngs"])) if "pngs" in z.files else [],
                          float(z["polar_ms"]) if "polar_ms" in z.files else None)
    from gpumap.io import open_recording

    data = common.oasis_tank_dir()
    if data is None:
        raise SystemExit("bench.speed: shared/data/oasis_tank not found; pass --frames-from NPZ")
    imgs, poses, times, spec = [], [], [], None
    t = time.perf_counter()
    for fr in open_recording(data):  # reading the PNG + fan -> polar, per frame
        dt, t = time.perf_counter() - t, time.perf_counter()
        if fr.T_W_S is not None:
            spec = fr.spec
            imgs.append(common.quantize(fr.image))
            poses.append(fr.T_W_S)
            times.append(dt)
    pngs = sorted(str(p) for p in (data / "sonar").glob("*.png"))
    out = Frames(np.stack(imgs), np.stack(poses), spec, pngs, 1e3 * float(np.median(times[1:])))
    dest = Path(path or CACHE)
    dest.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(dest, imgs=out.images, T=out.poses, spec=json.dumps(spec.to_dict()),
                        pngs=json.dumps(pngs),
                        polar_ms=out.polar_ms)
    return out


def oasis_grid(voxel_size_m: float) -> gpumap.GridSpec:
    return gpumap.GridSpec(*OASIS_BOX, voxel_size_m)


def _pct(ms: list[float]) -> dict[str, float]:
    a = np.asarray(ms)
    return {"p50_ms": float(np.percentile(a, 50)), "p99_ms": float(np.percentile(a, 99)),
            "max_ms": float(a.max()),
            "mean_ms": float(a.mean()), "n": int(a.size)}


def time_backend(fr: Frames, backend: str, voxel_size_m: float, rule: str, *, n_latency: int, n_stream: int,
                 batch: int | None, check: bool) -> dict[str, Any]:
    """One row: latency, sequential and batched throughput, the batch check, others' cores meanwhile."""
    with CpuShare() as share:
        grid, n, t0 = oasis_grid(voxel_size_m), len(fr.images), time.perf_counter()
        m = gpumap.MinMaxMapper(fr.spec, grid, backend, MapperParams(rule=rule))
        warm_up(m, fr.images, fr.poses, WARMUP)
        row: dict[str, Any] = {"backend": backend, "device": m.device, "voxel_m": voxel_size_m, "rule": rule,
                               "grid_shape": list(grid.shape), "setup_s": time.perf_counter() - t0}
        row["latency"] = _pct(synced_ms(m, fr.images, fr.poses, n_latency))
        # the share of each ping period left free at p99, per sonar rate (Hz)
        row["free_at_hz"] = {str(hz): 1.0 - row["latency"]["p99_ms"] / (1e3 / hz) for hz in RATES_HZ}
        row["img_per_s"] = stream_rate(m, fr.images, fr.poses, n_stream)
        row["observed_voxels"] = int(m.observed().sum())
        if batch:
            imgs, poses = np.ascontiguousarray(fr.images[:batch]), fr.poses[:batch]
            m.integrate_batch(imgs, poses)  # buffers, and the batch kernels' first launch
            m.synchronize()
            reps, rates = max(1, 1280 // batch), []
            for _ in range(3):
                t = time.perf_counter()
                for _ in range(reps):
                    m.integrate_batch(imgs, poses)
                m.synchronize()
                rates.append(reps * batch / (time.perf_counter() - t))
            row["batch"], row["img_per_s_batched"] = batch, float(np.median(rates))
            if backend == "warp-cuda":  # where a batch's GPU time goes, per ping
                row["gpu_us_per_ping"] = _warp_profile(m, imgs, poses, reps)
        if check:  # batched == sequential, bit for bit, on this backend
            k = min(n, 40)
            a, b = (gpumap.MinMaxMapper(fr.spec, grid, backend, MapperParams(rule=rule)) for _ in range(2))
            for i in range(k):
                a.integrate(fr.images[i], fr.poses[i])
            b.integrate_batch(fr.images[:k], fr.poses[:k])
            diff = int((a.raw_values().view(np.uint32) != b.raw_values().view(np.uint32)).sum())
            if rule == "visible":
                ea, eb = a.evidence(), b.evidence()
                diff += sum(int((ea[x].view(np.uint8) != eb[x].view(np.uint8)).sum()) for x in ea)
            row["batch_vs_sequential_diff"] = diff
        del m
    return row | {"others_cores": share.others_cores}  # what other processes took of the machine meanwhile


def _warp_profile(m: gpumap.MinMaxMapper, imgs: np.ndarray, poses: np.ndarray, reps: int) -> dict[str, float]:
    """GPU microseconds per ping of each kernel and copy of ``integrate_batch`` (Warp's timing)."""
    import warp as wp

    wp.timing_begin(cuda_filter=wp.TIMING_ALL)
    for _ in range(reps):
        m.integrate_batch(imgs, poses)
    m.synchronize()
    out: dict[str, float] = {}
    for r in wp.timing_end():
        out[r.name] = out.get(r.name, 0.0) + 1e3 * r.elapsed / (reps * len(imgs))
    return out


def oracle_check(spec, grid, images, poses, backends: list[str], n: int = 20, batch: bool = True,
                 dtype: type = np.uint32) -> dict[str, Any]:
    """Voxels where each backend's map of the first ``n`` pings differs from the NumPy oracle's, per rule
    (``batch``: integrate_batch, else one integrate a ping; the error where a backend fails)."""
    def mapped(backend: str, rule: str) -> np.ndarray:
        m = gpumap.MinMaxMapper(spec, grid, backend, MapperParams(rule=rule))
        if batch:
            m.integrate_batch(images[:n], poses[:n])
        for im, T in zip(images[:n], poses[:n], strict=True) if not batch else ():
            m.integrate(im, T)
        return m.raw_values().view(dtype) if dtype is np.uint32 else m.raw_values()

    out, refs = {}, {rule: mapped("numpy", rule) for rule in ("plain", "visible")}
    pairs = [(b, r) for r in refs for b in backends] if batch else [(b, r) for b in backends for r in refs]
    for b, rule in pairs:
        try:
            out[f"{b}/{rule}"] = int((mapped(b, rule) != refs[rule]).sum())
        except Exception as e:  # a backend that cannot run here: say so
            out[f"{b}/{rule}"] = repr(e)
    return out


# ------------------------------------------------------------------------------ the public OASIS code
def oasis_frame_ms(cls, fr: Frames, downsample: int, n: int):
    """Times of the public ``update_voxel_grid``, ms, for frames 1..n into a fresh grid (frame 0 warms
    up another one first); returns (the times, that grid)."""
    from PIL import Image

    fans = [np.array(Image.open(p).convert("L")) for p in fr.pngs[: n + 1]]
    oasis_mapper(cls, downsample).update_voxel_grid(fans[0], fr.poses[0])
    g, ms = oasis_mapper(cls, downsample), []
    for k in range(1, n + 1):
        t = time.perf_counter()
        g.update_voxel_grid(fans[k], fr.poses[k])
        ms.append(1e3 * (time.perf_counter() - t))
    return ms, g


def time_oasis(src: Path, fr: Frames, downsample: int, n: int) -> dict[str, Any]:
    """ms per frame of the public ``update_voxel_grid`` on the first ``n`` frames (1 warm-up)."""
    cls = _import_oasis(src)
    t0 = time.perf_counter()
    oasis_mapper(cls, downsample)
    setup_s = time.perf_counter() - t0
    ms, g = oasis_frame_ms(cls, fr, downsample, n)
    return {"downsample": downsample, "voxel_m": downsample * OASIS_RES_M, "setup_s": setup_s,
            "template_points": int(g.voxel_template.shape[1]), "latency": _pct(ms),
            "img_per_s": 1e3 / float(np.mean(ms)),
            "input": "Cartesian fan PNG (grey), as the public code reads it"}


# ------------------------------------------------------------------------------ the synthetic tank
def synthetic(a) -> int:
    """``--synthetic``: images/s (back to back) and ms per image (synced) per voxel size, backend and
    method on the synthetic tank; writes ``OUT/<tag>.json`` (default mapper_speed.json)."""
    spec, rows = common.tank_spec(), []
    for v in a.voxel or [0.05, 0.03, 0.01]:
        for b in a.backend or gpumap.available_backends():
            for meth in a.method:
                n = a.images or (200 if v >= 0.02 else 60)
                n = min(n, 10 if v >= 0.02 else 3) if b == "numpy" else n
                try:
                    imgs, poses, t0 = common.speckle(spec,
                                                     min(n, 16)), common.trajectory(n), time.perf_counter()
                    m = gpumap.MinMaxMapper(spec, common.tank_grid(v), b, MapperParams(method=meth))
                    warm_up(m, imgs, poses, WARMUP)
                    setup_s, thr = time.perf_counter() - t0, stream_rate(m, imgs, poses, n)
                    observed, lat = int(m.observed().sum()), np.array(synced_ms(m, imgs, poses, min(n, 50)))
                    r = {"backend": m.backend, "backend_requested": b, "device": m.device, "method": meth,
                         "voxel_size_m": v, "grid_shape": list(m.grid.shape), "images": n,
                         "images_per_s": thr,
                         "ms_per_image_median": float(np.median(lat)),
                         "ms_per_image_p95": float(np.percentile(lat, 95)),
                         "setup_s_incl_warmup": setup_s, "voxels_observed": observed}
                except Exception as e:  # record and go on: one failing backend must not hide the rest
                    r = {"backend_requested": b, "method": meth, "voxel_size_m": v, "error": repr(e)}
                rows.append(r)
                keys = ("backend_requested", "method", "voxel_size_m", "images_per_s", "ms_per_image_median",
                        "error")
                print(json.dumps({k: r.get(k) for k in keys}), flush=True)
    doc = {"machine": common.machine_info(), "warmup_pings": WARMUP, "rows": rows}
    print(f"wrote {write_json(a.out / ((a.tag or 'mapper_speed') + '.json'), doc)}")
    return 0


def gpu_check(a) -> int:
    """``--gpu-check PINGS``: the GPU backends' maps of 20 tank pings (a ping file of ``python -m bench
    --save-pings``) at 5 cm against the NumPy oracle's (voxels that differ, per rule: 0 = bit for bit),
    then per voxel size (3, 1, 0.5 cm) and rule the throughput of 400 integrate calls (uint8, upload
    included, one synchronize at the end) and the p50/p99 latency of 100 synchronized calls; writes
    ``OUT/visibility_<tag>.json``."""
    imgs, T = common.load_ping_arrays(a.gpu_check)
    spec, backends = common.tank_spec(), a.backend or list(GPU_BACKENDS)
    agree = oracle_check(spec, common.tank_grid(0.05), imgs, T, backends, batch=False, dtype=float)
    res = {"backends": gpumap.available_backends(), "agree": agree, "speed": []}
    print(res["agree"], flush=True)
    for b in backends:
        for vs in a.voxel or GPU_VOXELS:
            for rule in ("plain", "visible"):
                m = gpumap.MinMaxMapper(spec, common.tank_grid(vs), b, MapperParams(rule=rule))
                warm_up(m, imgs, T, 5)
                thr, lat = stream_rate(m, imgs[:40], T[:40], 400), synced_ms(m, imgs[:40], T[:40], 100)
                res["speed"].append({"backend": b, "voxel_m": vs, "rule": rule, "img_per_s": thr,
                                     "latency_ms_p50": float(np.percentile(lat, 50)),
                                     "latency_ms_p99": float(np.percentile(lat, 99)), "device": m.device})
                print(res["speed"][-1], flush=True)
    print(f"wrote {write_json(common.tagged_path(a.out, 'visibility_', a.tag or 'gpu'), res)}")
    return 0


# ------------------------------------------------------------------------------ the run
def main(argv: list[str] | None = None) -> int:
    ap = bench_parser("speed", __doc__, out="bench/results", backend=(), voxel=(), tag="")
    ap.add_argument("--frames-from", type=Path, default=None, help="cached frames (.npz) of this module")
    ap.add_argument("--max-frames", type=int, default=None, help="map only the first N frames")
    ap.add_argument("--gpu", action="store_true", help="GPU backends (warp-cuda, opencl-gpu) at 3, 1, 0.5 cm")
    ap.add_argument("--rule", nargs="+", default=["visible", "plain"], help="mapping rules (default both)")
    ap.add_argument("--batch", type=int, default=64, help="frames per integrate_batch call (GPUs)")
    ap.add_argument("--latency-pings", type=int, default=None,
                    help="synchronized pings per latency figure (default: by backend and voxel size)")
    ap.add_argument("--oasis-src", type=Path, default=None, help="checkout of the public OASIS code")
    ap.add_argument("--oasis-frames", type=int, default=20, help="frames the public code maps (default 20)")
    ap.add_argument("--synthetic", action="store_true", help="the synthetic tank instead (mapper_speed.json)")
    ap.add_argument("--method", nargs="+", default=["gather", "template"],
                    help="--synthetic: methods (default both)")
    ap.add_argument("--images", type=int, default=None,
                    help="--synthetic: pings per row (default by voxel size)")
    ap.add_argument("--gpu-check", type=Path, metavar="PINGS",
                    help="the GPU check on these tank pings instead")
    a = ap.parse_args(argv)
    if a.synthetic or a.gpu_check:
        return synthetic(a) if a.synthetic else gpu_check(a)
    fr = load_frames(a.frames_from or CACHE)
    fr = Frames(fr.images[: a.max_frames], fr.poses[: a.max_frames], fr.spec, fr.pngs, fr.polar_ms)
    avail = gpumap.available_backends()
    here = GPU_BACKENDS if a.gpu else ("warp-cpu", "opencl-cpu", "numpy")
    backends = a.backend or [b for b in here if b in avail]
    voxels = a.voxel or (GPU_VOXELS if a.gpu else CPU_VOXELS)
    res: dict[str, Any] = {
        **common.run_header("gpumap-speed/1", argv),
        "frames": {"source": "shared/data/oasis_tank (real Oculus M3000d, arm poses)", "n": len(fr.images),
                   "image_shape": list(fr.images.shape[1:]), "dtype": "uint8",
                   "fan_to_polar_ms": fr.polar_ms},
        "grid_box_m": OASIS_BOX, "rows": [], "oasis_public": []}
    for ds in (10, 6) if a.oasis_src else ():
        if any(abs(v - ds * OASIS_RES_M) < 1e-6 for v in voxels):
            try:
                r = time_oasis(a.oasis_src, fr, ds, a.oasis_frames)
            except Exception as e:  # recorded, not fatal: the rest of the run still counts
                r = {"downsample": ds, "error": repr(e)}
            res["oasis_public"].append(r)
            print("oasis public", {k: r.get(k) for k in ("voxel_m", "img_per_s", "error")}, flush=True)
    for v in voxels:
        for b in backends:
            for rule in a.rule:
                gpu = b in GPU_BACKENDS
                n_lat = a.latency_pings or (10 if b == "numpy" else 200 if gpu else 60 if v >= 0.02 else 20)
                try:
                    row = time_backend(fr, b, v, rule, n_latency=n_lat, n_stream=400 if gpu else n_lat,
                                       batch=a.batch if gpu else None, check=gpu)
                except Exception as e:
                    row = {"backend": b, "voxel_m": v, "rule": rule, "error": repr(e)}
                res["rows"].append(row)
                keys = ("backend", "voxel_m", "rule", "img_per_s", "img_per_s_batched",
                        "batch_vs_sequential_diff",
                        "error")
                print({k: row.get(k) for k in keys}, row.get("latency", {}).get("p99_ms"), flush=True)
    on_gpu = [b for b in backends if b in GPU_BACKENDS]
    if on_gpu:
        grid = oasis_grid(10 * OASIS_RES_M)
        res["oracle_diff_5cm"] = oracle_check(fr.spec, grid, fr.images, fr.poses, on_gpu)
        print("oracle", res["oracle_diff_5cm"], flush=True)
    tag = a.tag or common.machine_tag(res["machine"], bool(on_gpu))
    print(f"wrote {write_json(common.tagged_path(a.out, 'speed_', tag), res, digits=4)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
