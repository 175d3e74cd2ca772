"""``python -m bench.speed``: latency and throughput on the real OASIS tank frames, and the
public OASIS implementation side by side, in one run.

The frames are the real Oculus M3000d tank sequence of ``shared/data/oasis_tank`` (123 frames,
Cartesian fans with arm poses), converted once to polar uint8 (the reader's ``fan_to_polar``,
timed apart) and cached in ``bench/results/tmp/oasis_polar.npz`` (carry that file to a machine
without the data, e.g. the GPU box). The grid is the OASIS configuration's box (2.4 x 2.4 x
1.3 m from (-0.5, -1.2, -0.5)). Per backend, rule and voxel size:

- latency: ``integrate`` + ``synchronize`` per frame, p50 / p99 / max (what a vehicle waits),
  and what a 10, 20 or 40 Hz sonar leaves free of each ping period at p99;
- throughput: frames handed over back to back, one synchronize at the end;
- batched throughput (GPUs): ``integrate_batch`` of ``--batch`` frames, upload included;
- checks: the batched map equals the sequential one bit for bit, GPU maps equal the NumPy oracle.

``--oasis-src DIR`` (a checkout of the public OASIS code, chaos-whoi/oasis_iros, with opencv
and open3d importable; nothing of it ships here) times its ``SonarVoxelGrid.update_voxel_grid``
on the same frames (its own input: the Cartesian PNG, grey), at its voxel sizes (range
resolution x downsample factor: 10 -> 5.03 cm, 6 -> 3.02 cm), and gpumap at those sizes.

    python -m bench.speed --oasis-src /path/to/oasis_iros          # CPU machine
    python -m bench.speed --gpu --frames-from bench/results/tmp/oasis_polar.npz --out $OUT
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

import gpumap

from .common import (
    CpuShare,
    bench_parser,
    machine_tag,
    oasis_tank_dir,
    run_header,
    stream_rate,
    synced_ms,
    tagged_path,
    warm_up,
    write_json,
)

CACHE = Path("bench/results/tmp/oasis_polar.npz")
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
            spec = gpumap.SonarSpec.from_dict(json.loads(str(z["spec"])))
            pngs = json.loads(str(z["pngs"])) if "pngs" in z.files else []
            polar_ms = float(z["polar_ms"]) if "polar_ms" in z.files else None
            return Frames(z["imgs"], z["T"], spec, pngs, polar_ms)
    from gpumap.io import open_recording

    data = oasis_tank_dir()
    if data is None:
        raise SystemExit("bench.speed: shared/data/oasis_tank not found; pass --frames-from NPZ")
    rec = open_recording(data)
    imgs, poses, times = [], [], []
    spec = None
    t = time.perf_counter()
    for fr in rec:  # reading the PNG + fan -> polar, per frame
        dt, t = time.perf_counter() - t, time.perf_counter()
        if fr.T_W_S is None:
            continue
        spec = fr.spec
        imgs.append(np.round(fr.image * 255).astype(np.uint8))
        poses.append(fr.T_W_S)
        times.append(dt)
    pngs = sorted(str(p) for p in (data / "sonar").glob("*.png"))
    out = Frames(np.stack(imgs), np.stack(poses), spec, pngs, 1e3 * float(np.median(times[1:])))
    dest = Path(path or CACHE)
    dest.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(dest, imgs=out.images, T=out.poses, spec=json.dumps(spec.to_dict()),
                        pngs=json.dumps(pngs), polar_ms=out.polar_ms)
    return out


def oasis_grid(voxel_size_m: float) -> gpumap.GridSpec:
    return gpumap.GridSpec(*OASIS_BOX, voxel_size_m)


def _pct(ms: list[float]) -> dict[str, float]:
    a = np.asarray(ms)
    return {"p50_ms": float(np.percentile(a, 50)), "p99_ms": float(np.percentile(a, 99)),
            "max_ms": float(a.max()), "mean_ms": float(a.mean()), "n": int(a.size)}


def sonar_budget(p99_ms: float) -> dict[str, float]:
    """Fraction of each ping period left free at ``p99_ms`` per ping, per sonar rate (Hz)."""
    return {str(hz): 1.0 - p99_ms / (1e3 / hz) for hz in RATES_HZ}


def time_backend(fr: Frames, backend: str, voxel_size_m: float, rule: str, *, n_latency: int,
                 n_stream: int, batch: int | None, check: bool) -> dict[str, Any]:
    """One row: latency, sequential and batched throughput, and the batch check."""
    with CpuShare() as share:
        row = _time_backend(fr, backend, voxel_size_m, rule, n_latency=n_latency, n_stream=n_stream,
                            batch=batch, check=check)
    row["others_cores"] = share.others_cores  # what other processes took of the machine meanwhile
    return row


def _time_backend(fr: Frames, backend: str, voxel_size_m: float, rule: str, *, n_latency: int,
                  n_stream: int, batch: int | None, check: bool) -> dict[str, Any]:
    grid = oasis_grid(voxel_size_m)
    n = len(fr.images)
    t0 = time.perf_counter()
    m = gpumap.MinMaxMapper(fr.spec, grid, backend=backend, rule=rule)
    warm_up(m, fr.images, fr.poses, WARMUP)
    row: dict[str, Any] = {"backend": backend, "device": m.device, "voxel_m": voxel_size_m, "rule": rule,
                           "grid_shape": list(grid.shape), "setup_s": time.perf_counter() - t0}
    row["latency"] = _pct(synced_ms(m, fr.images, fr.poses, n_latency))
    row["free_at_hz"] = sonar_budget(row["latency"]["p99_ms"])
    row["img_per_s"] = stream_rate(m, fr.images, fr.poses, n_stream)
    row["observed_voxels"] = int(m.observed().sum())
    if batch:
        imgs = np.ascontiguousarray(fr.images[:batch])
        poses = fr.poses[:batch]
        m.integrate_batch(imgs, poses)  # buffers, and the batch kernels' first launch
        m.synchronize()
        reps = max(1, 1280 // batch)
        rates = []
        for _ in range(3):
            t = time.perf_counter()
            for _ in range(reps):
                m.integrate_batch(imgs, poses)
            m.synchronize()
            rates.append(reps * batch / (time.perf_counter() - t))
        row["batch"] = batch
        row["img_per_s_batched"] = float(np.median(rates))
        if backend == "warp-cuda":  # where a batch's GPU time goes, per ping
            row["gpu_us_per_ping"] = _warp_profile(m, imgs, poses, reps)
    if check:  # batched == sequential, bit for bit, on this backend
        k = min(n, 40)
        a = gpumap.MinMaxMapper(fr.spec, grid, backend=backend, rule=rule)
        b = gpumap.MinMaxMapper(fr.spec, grid, backend=backend, rule=rule)
        for i in range(k):
            a.integrate(fr.images[i], fr.poses[i])
        b.integrate_batch(fr.images[:k], fr.poses[:k])
        diff = int((a.raw_values().view(np.uint32) != b.raw_values().view(np.uint32)).sum())
        if rule == "visible":
            ea, eb = a.evidence(), b.evidence()
            diff += sum(int((ea[x].view(np.uint8) != eb[x].view(np.uint8)).sum()) for x in ea)
        row["batch_vs_sequential_diff"] = diff
    del m
    return row


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


def oracle_check(fr: Frames, backends: list[str], voxel_size_m: float, n: int = 20) -> dict[str, int]:
    """Voxels (values and evidence) where each backend differs from the NumPy oracle."""
    out = {}
    grid = oasis_grid(voxel_size_m)
    for rule in ("plain", "visible"):
        ref = gpumap.MinMaxMapper(fr.spec, grid, backend="numpy", rule=rule)
        ref.integrate_batch(fr.images[:n], fr.poses[:n])
        rv = ref.raw_values()
        for b in backends:
            m = gpumap.MinMaxMapper(fr.spec, grid, backend=b, rule=rule)
            m.integrate_batch(fr.images[:n], fr.poses[:n])
            out[f"{b}/{rule}"] = int((m.raw_values().view(np.uint32) != rv.view(np.uint32)).sum())
    return out


# ------------------------------------------------------------------------------ the public OASIS code
def _import_oasis(src: Path):
    """Import the public code's ``SonarVoxelGrid`` from a checkout at ``src``.

    open3d imports its plotly/dash helpers at import time; the mapping never uses them, so
    where dash is missing an empty stand-in module takes its place.
    """
    import types

    try:
        import dash  # noqa: F401
    except ImportError:
        class _Stub(types.ModuleType):
            def __getattr__(self, name: str):
                if name.startswith("__"):
                    raise AttributeError(name)
                sub = _Stub(f"{self.__name__}.{name}")
                sys.modules[sub.__name__] = sub
                return sub

            def __call__(self, *a, **k):
                return self

        for name in ("dash", "dash.html", "dash.dcc"):
            sys.modules.setdefault(name, _Stub(name))
    sys.path.insert(0, str(src))
    from sonar_reconstruction.sonar_voxel_grid import SonarVoxelGrid  # type: ignore[import-not-found]

    return SonarVoxelGrid


def oasis_mapper(cls, downsample: int):
    """The public ``SonarVoxelGrid`` with its configs/base.yaml values, built as its constructor
    builds it but without the two render windows (not part of the mapping; they need a display)."""
    import math

    import open3d as o3d  # type: ignore[import-not-found]
    from sonar_reconstruction.polar_remapper import PolarRemapper  # type: ignore[import-not-found]

    g = cls.__new__(cls)
    g.sonar_params = {"min_range": 0.1, "max_range": 2.0, "h_fov": 2.26892803, "v_fov": 0.34906585,
                      "num_beams": 512, "num_ranges": 398, "range_resolution": 2.0 / 398,
                      "downsample_factor": downsample, "polar_img": False}
    g.voxel_grid_params = {"grid_size": np.array([2.4, 2.4, 1.3]),
                           "grid_origin": np.array([-0.5, -1.2, -0.5]),
                           "default_color": np.array([1, 0, 0])}
    g.filtering_params = {"range_window": 20, "empty_ranges": 10, "occupancy_threshold": 1,
                          "false_negative_rate": 0.5}
    g.occ_ratio_thresh = 1 - g.filtering_params["false_negative_rate"]
    g.voxel_grid_params["voxel_size"] = g.sonar_params["range_resolution"] * downsample
    g.voxel_grid_params["voxel_radius"] = g.voxel_grid_params["voxel_size"] * math.sqrt(2)
    g.voxel_template = g.compute_voxel_template()
    g.voxel_grid = o3d.geometry.VoxelGrid()
    g.voxel_grid.origin = g.voxel_grid_params["grid_origin"]
    g.voxel_grid.voxel_size = g.voxel_grid_params["voxel_size"]
    shape = (g.voxel_grid_params["grid_size"] / g.voxel_grid_params["voxel_size"] + 1).astype(int)
    g.obs_count = np.zeros(shape)
    g.occ_count = np.zeros(shape)
    g.occ_ratio = -np.ones(shape)
    g.remapper = PolarRemapper(g.sonar_params)
    return g


def oasis_frame_ms(cls, fr: Frames, downsample: int, n: int):
    """Times of the public ``update_voxel_grid``, ms, for frames 1..n into a fresh grid (frame 0
    warms up another one first); returns (the times, that grid)."""
    from PIL import Image

    fans = [np.array(Image.open(p).convert("L")) for p in fr.pngs[: n + 1]]
    g = oasis_mapper(cls, downsample)
    g.update_voxel_grid(fans[0], fr.poses[0])
    g = oasis_mapper(cls, downsample)
    ms = []
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


# ------------------------------------------------------------------------------ the run
def main(argv: list[str] | None = None) -> int:
    ap = bench_parser("speed", __doc__)
    ap.add_argument("--frames-from", type=Path, default=None, help="cached frames (.npz) of this module")
    ap.add_argument("--gpu", action="store_true", help="GPU backends (warp-cuda, opencl-gpu) at 3, 1, 0.5 cm")
    ap.add_argument("--backend", nargs="+", default=None, help="backends (default: the CPU or GPU ones here)")
    ap.add_argument("--voxel-size", "--voxel", dest="voxel", type=float, nargs="+", default=None,
                    help="voxel edges in metres (default: each target's)")
    ap.add_argument("--rule", nargs="+", default=["visible", "plain"], help="mapping rules (default both)")
    ap.add_argument("--batch", type=int, default=64, help="frames per integrate_batch call (GPUs)")
    ap.add_argument("--latency-pings", type=int, default=None,
                    help="synchronized pings per latency figure (default: by backend and voxel size)")
    ap.add_argument("--oasis-src", type=Path, default=None, help="checkout of the public OASIS code")
    ap.add_argument("--oasis-frames", type=int, default=20, help="frames the public code maps (default 20)")
    ap.add_argument("--out", type=Path, default=Path("bench/results"), help="results folder")
    ap.add_argument("--tag", default=None, help="result file stem after speed_ (default: from the machine)")
    a = ap.parse_args(argv)
    fr = load_frames(a.frames_from or CACHE)
    avail = gpumap.available_backends()
    gpu_names = ("warp-cuda", "opencl-gpu")
    if a.backend:
        backends = a.backend
    elif a.gpu:
        backends = [b for b in gpu_names if b in avail]
    else:
        backends = [b for b in ("warp-cpu", "opencl-cpu", "numpy") if b in avail]
    voxels = a.voxel or (GPU_VOXELS if a.gpu else CPU_VOXELS)
    res: dict[str, Any] = {
        **run_header("gpumap-speed/1", argv),
        "frames": {"source": "shared/data/oasis_tank (real Oculus M3000d, arm poses)",
                   "n": len(fr.images), "image_shape": list(fr.images.shape[1:]),
                   "dtype": "uint8", "fan_to_polar_ms": fr.polar_ms},
        "grid_box_m": OASIS_BOX, "rows": [], "oasis_public": [],
    }
    if a.oasis_src:
        for ds in (10, 6):
            if any(abs(v - ds * OASIS_RES_M) < 1e-6 for v in voxels):
                try:
                    r = time_oasis(a.oasis_src, fr, ds, a.oasis_frames)
                except Exception as e:  # recorded, not fatal: the rest of the run still counts
                    r = {"downsample": ds, "error": repr(e)}
                res["oasis_public"].append(r)
                print("oasis public", {k: r.get(k) for k in ("voxel_m", "img_per_s", "error")}, flush=True)
    on_gpu = any(b in gpu_names for b in backends)
    for v in voxels:
        for b in backends:
            for rule in a.rule:
                slow = b == "numpy"
                gpu = b in gpu_names
                n_lat = a.latency_pings or (10 if slow else 200 if gpu else 60 if v >= 0.02 else 20)
                try:
                    row = time_backend(fr, b, v, rule, n_latency=n_lat, n_stream=400 if gpu else n_lat,
                                       batch=a.batch if gpu else None, check=gpu)
                except Exception as e:
                    row = {"backend": b, "voxel_m": v, "rule": rule, "error": repr(e)}
                res["rows"].append(row)
                print({k: row.get(k) for k in ("backend", "voxel_m", "rule", "img_per_s", "img_per_s_batched",
                                                "batch_vs_sequential_diff", "error")},
                      row.get("latency", {}).get("p99_ms"), flush=True)
    if on_gpu:
        res["oracle_diff_5cm"] = oracle_check(fr, [b for b in backends if b in gpu_names], 10 * OASIS_RES_M)
        print("oracle", res["oracle_diff_5cm"], flush=True)
    tag = a.tag or machine_tag(res["machine"], on_gpu)
    path = write_json(tagged_path(a.out, "speed_", tag), res, digits=4)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
