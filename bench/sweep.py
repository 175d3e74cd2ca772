"""``python -m bench`` (``gpumap bench``, ``python -m bench sweep``): speed against error on the
simulated tank, every backend, voxel size, method and baseline on the same pings; writes
``bench/results/<machine-tag>.json`` (bench/README.md tells more).
"""

from __future__ import annotations

import argparse
import gc
import json
import math
import os
import sys
import time
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

import gpumap
from gpumap.core.params import MapperParams

from . import common
from .common import GPU_BACKENDS, CpuShare, PeakRSS, linear_fit, progress_bar, synced_ms, warm_up

CPU_VOXELS = (0.06, 0.05, 0.04, 0.03, 0.02, 0.01)
GPU_EXTRA_VOXELS = (0.005,)
GPU_ONLY_VOXELS = (0.03, 0.01, 0.005)
METHODS = ("gather", "template")
WARMUP = 3  # pings integrated and discarded before timing (kernel compile, caches); 1 for pure NumPy
STREAM_SECONDS = {False: 1.0, True: 2.0}  # aim of the back-to-back throughput pass (CPU, GPU)
PROBE_PINGS = 4  # single-ping maps used for voxels-in-view and template holes
#: Edge of the cells that record which surface points the pings saw, metres.
SEEN_CELL_M = 0.005
#: (n_bins, n_beams) of the image-size sweep.
IMAGE_SIZES = ((200, 128), (400, 256), (400, 512), (800, 512), (800, 1024))
#: Ping rates of imaging sonars the summary table checks against (an Oculus runs at up to 40 Hz).
SONAR_RATES_HZ = (5, 10, 20, 40)


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="gpumap bench", description="speed against error on the simulated tank, "
                                "in one run (python -m bench in a checkout; python -m bench --list for "
                                "the other benchmarks)")
    p.add_argument("--voxel-size", "--voxel", dest="voxel", type=float, nargs="+", default=None,
                   help="voxel sizes, metres")
    p.add_argument("--backend", nargs="+", default=None, help="default: every available backend")
    p.add_argument("--method", nargs="+", default=list(METHODS), choices=METHODS,
                   help="mapping methods to time (default: all)")
    p.add_argument("--pings", type=int, default=None, help="pings along the tank trajectory (default all 40)")
    p.add_argument("--pings-from", type=Path, default=None, help="load pings saved by --save-pings")
    p.add_argument("--save-pings", type=Path, default=None, help="write the simulated pings (.npz)")
    p.add_argument("--gpu-only", action="store_true",
                   help="warp-cuda / opencl-gpu rows at 3, 1, 0.5 cm only; "
                   "no baselines")
    p.add_argument("--quick", action="store_true", help="5 and 3 cm, 16 pings, no scaling section")
    p.add_argument("--no-baselines", action="store_true",
                   help="skip the baselines (the paper in NumPy, OASIS hit ratio, OctoMap)")
    p.add_argument("--no-scaling", action="store_true",
                   help="skip the scaling section (rate against grid size)")
    p.add_argument("--numpy-cap", type=int, default=8,
                   help="timed pings of the numpy backend at <= 2 cm (its map "
                   "quality is then taken from another backend: the same algorithm)")
    p.add_argument("--threshold", type=float, default=None,
                   help="occupied intensity (default: the simulator's)")
    p.add_argument("--fnr", type=float, default=0.5, help="OASIS false-negative rate")
    p.add_argument("--shadow-m", type=float, default=0.0,
                   help="gpumap's shadow_m (a return also counts this far behind it; 0 = the paper)")
    p.add_argument("--seed", type=int, default=0, help="random seed of the simulated pings (default 0)")
    p.add_argument("--out", type=Path, default=Path("bench/results"),
                   help="folder for the results (JSON, plots); default bench/results")
    p.add_argument("--tag", default=None, help="result file stem (default: from the machine)")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    return p


# ------------------------------------------------------------------------------ the pings and the truth
@dataclass
class TankPings:
    """The tank trajectory's pings, uint8 (as the Oculus delivers), rendered once for every row:
    images (n, bins, beams), true poses ``T_W_S``, ``seen_cells`` (indices of the :data:`SEEN_CELL_M`
    cells from the grid's min corner that held a visible surface point: every voxel size is a multiple
    of 5 mm, so each cell lies in one voxel) and meta (scene, seed, simulator speed and renderer)."""

    images: np.ndarray
    poses: np.ndarray
    seen_cells: np.ndarray
    meta: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.images.shape[0])

    def save(self, path: str | os.PathLike) -> Path:
        """Write the pings to ``path`` (.npz, compressed: carry it to a machine that cannot render)."""
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(path, images=self.images, poses=self.poses, seen_cells=self.seen_cells,
                            meta=np.array(json.dumps(self.meta)))
        return Path(path)


def load_pings(path: str | os.PathLike) -> TankPings:
    """Read pings written by :meth:`TankPings.save`."""
    with np.load(path, allow_pickle=False) as z:
        missing = {"images", "poses", "seen_cells", "meta"} - set(z.files)
        if missing:
            raise ValueError(f"Expected a bench ping file with {sorted(missing)}, but {path} has {z.files}")
        out = TankPings(z["images"], z["poses"], z["seen_cells"], json.loads(str(z["meta"])))
    if out.images.dtype != np.uint8 or out.images.ndim != 3:
        raise ValueError(f"Expected (n, bins, beams) uint8 images in {path}, but got {out.images.shape} "
                         f"{out.images.dtype}")
    out.meta["loaded_from"] = str(path)
    return out


def simulate_tank(n_pings: int | None = None, seed: int = 0, progress: bool = True) -> TankPings:
    """Render the tank trajectory's pings (all, or ``n_pings`` evenly spaced); the simulator's speed
    (after the first ping, which builds the GL context) and renderer go into ``meta``."""
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    from gpumap.sim.scenes import make_scene
    from gpumap.sim.sonar import SonarSimulator

    scene = make_scene("tank", seed=seed)
    n_all, sel = len(scene.T_W_S), np.arange(len(scene.T_W_S))
    if n_pings is not None and n_pings < n_all:
        sel = np.unique(np.linspace(0, n_all - 1, n_pings).round().astype(int))
    images, cells, times, lo = [], [], [], np.asarray(scene.grid.min_corner_m)
    t_first = time.perf_counter()
    with SonarSimulator(scene, seed=seed) as sim:
        for i, k in enumerate(progress_bar(sel, desc="simulate tank", unit="ping", disable=not progress)):
            t0 = time.perf_counter()
            p = sim.ping(scene.T_W_S[k], int(k))
            times.append(time.perf_counter() - t0)
            if i == 0:
                init_s, gl = time.perf_counter() - t_first, common.gl_renderer()
            images.append(common.quantize(p.image))
            cells.append(np.unique(np.floor((p.points_W - lo) / SEEN_CELL_M).astype(np.int32), axis=0))
        rays = int(sim.rays_per_ping)
    t = np.array(times[1:] if len(times) > 1 else times)
    meta = {"scene": "tank", "seed": seed, "ping_indices": sel.tolist(), "pings_in_trajectory": n_all,
            "image_shape": list(scene.sonar_spec.image_shape),
            "quantized": "uint8 (intensity * 255, rounded)",
            "sim": {"images_per_s": float(1.0 / t.mean()), "ms_per_image_median": float(1e3 * np.median(t)),
                    "init_s": float(init_s), "rays_per_ping": rays, "gl_renderer": gl,
                    "note": "pyrender sonar simulator, first ping (GL context) excluded"}}
    return TankPings(np.stack(images), scene.T_W_S[sel].copy(), np.unique(np.concatenate(cells), axis=0),
                     meta)


@dataclass
class VoxelTruth:
    """The scene, its ground truth and the seen mask on one voxel size's grid."""

    scene: Any
    truth: Any
    seen: np.ndarray
    truth_s: float


def voxel_truth(voxel_size_m: float, seen_cells: np.ndarray, seed: int = 0) -> VoxelTruth:
    """Ground truth of the tank on the ``voxel_size_m`` grid (trimesh only), and the voxels the pings saw."""
    from gpumap.sim.scenes import make_scene
    from gpumap.sim.truth import occupancy, points_to_voxels

    t0 = time.perf_counter()
    scene = make_scene("tank", voxel_size_m=voxel_size_m, seed=seed)
    truth, grid = occupancy(scene, seed=seed), scene.grid
    seen = np.zeros(grid.shape, bool)
    ratio = round(voxel_size_m / SEEN_CELL_M)
    if ratio >= 1 and abs(ratio * SEEN_CELL_M - voxel_size_m) < 1e-9:
        idx = seen_cells // ratio
        seen[tuple(idx[np.all((idx >= 0) & (idx < np.array(grid.shape)), axis=1)].T)] = True
    else:  # not nested: use the cell centres (off by at most half a cell at voxel faces)
        centres = np.asarray(grid.min_corner_m) + (seen_cells + 0.5) * SEEN_CELL_M
        seen.reshape(-1)[points_to_voxels(centres, grid)] = True
    return VoxelTruth(scene, truth, seen, time.perf_counter() - t0)


# ------------------------------------------------------------------------------ rows
# what score() keeps of gpumap.sim.metrics.evaluate, and what it adds
EVALUATION_KEYS = ("observed_fraction", "false_negative_rate", "false_negative_rate_objects",
                   "false_positive_rate",
                   "false_positive_rate_far", "free_carved_fraction", "height_error_m", "pipe_found")
SCORE_EXTRA_KEYS = ("miss_rate_seen", "height_error_mean_m")


def score(values: np.ndarray, vt: VoxelTruth, threshold: float) -> dict[str, Any]:
    """Errors of a map against the truth, plus the miss rate over every seen surface voxel."""
    from gpumap.sim.metrics import evaluate

    ev = evaluate(values, vt.truth, threshold, vt.seen, vt.scene.grid.voxel_size_m).to_dict()
    target = vt.truth.occupied & vt.seen
    n = int(target.sum())
    out = {k: ev[k] for k in EVALUATION_KEYS}
    # A seen obstacle voxel the map does not call occupied, observed or not (OctoMap observes little).
    occ = np.nan_to_num(values, nan=-np.inf) >= threshold
    out["miss_rate_seen"] = float((target & ~occ).sum() / n) if n else float("nan")
    he = [x for x in ev["height_error_m"].values() if x is not None and np.isfinite(x)]
    out["height_error_mean_m"] = float(np.mean(he)) if he else float("nan")
    return out


def _latency(ms: list[float]) -> dict[str, float]:
    a = np.asarray(ms)
    return {"ms_median": float(np.median(a)), "ms_p95": float(np.percentile(a, 95)),
            "ms_mean": float(a.mean()),
            "images_per_s_synced": float(1e3 / a.mean())}


def _device_mem_probe(backend: str):
    """A callable returning device bytes in use (None if the backend cannot tell)."""
    if backend not in GPU_BACKENDS:
        return None
    try:
        import warp as wp

        dev = wp.get_device("cuda:0")
        pool = backend == "warp-cuda" and wp.is_mempool_enabled(dev)
        probe = (lambda: int(wp.get_mempool_used_mem_current(dev))) if pool else (
            lambda: int(dev.total_memory - dev.free_memory))
        probe()
    except Exception:  # informative only: no device memory figure
        return None

    def safe() -> int | None:
        try:
            return probe()
        except Exception:
            return None

    return safe


def gpumap_row(pings: TankPings, vt: VoxelTruth, backend: str, method: str, threshold: float, cap: int | None,
               ref_obs: dict | None, shadow_m: float = 0.0) -> tuple[dict, dict]:
    """Time and score one gpumap configuration; returns the row and its observed masks."""
    spec, grid, n = vt.scene.sonar_spec, vt.scene.grid, len(pings)
    n_timed, warm = n if cap is None else min(n, cap), 1 if backend == "numpy" else WARMUP
    mem = _device_mem_probe(backend)
    gc.collect()
    dev0 = mem() if mem else None
    with PeakRSS() as rss, CpuShare() as cpu:
        t0 = time.perf_counter()
        extra = {"shadow_m": shadow_m} if shadow_m else {}  # older gpumap has no shadow_m
        m = gpumap.MinMaxMapper(spec, grid, backend, MapperParams(method=method, **extra))
        warm_up(m, pings.images, pings.poses, warm)
        setup_s = time.perf_counter() - t0
        lat = synced_ms(m, pings.images, pings.poses, n_timed)
        dev1 = mem() if mem else None
        values = m.values() if n_timed == n else None
        row: dict[str, Any] = {
            "kind": "gpumap", "backend": backend, "backend_reported": m.backend, "device": m.device,
            "on_gpu": backend in GPU_BACKENDS, "method": method, "shadow_m": shadow_m,
                               "voxel_size_m": grid.voxel_size_m,
            "grid_shape": list(grid.shape), "pings": n, "pings_timed": n_timed, "warmup_pings": warm,
            "setup_s_incl_warmup": setup_s, **_latency(lat)}
        aim = STREAM_SECONDS[backend in GPU_BACKENDS]  # throughput: back to back, one sync at the end
        if sum(lat) < 1e3 * aim:
            reps = min(max(max(1, math.ceil(aim * 1e3 / max(sum(lat), 1e-3))), 3), 300)
            # three chunks; the median damps a burst of other work on a shared machine
            rates = [common.stream_rate(m, pings.images, pings.poses, len(chunk) * n)
                     for chunk in np.array_split(np.arange(reps), 3)]
            row.update(images_per_s_stream=float(np.median(rates)), images_per_s_stream_chunks=rates,
                       stream_pings=reps * n)
        row["images_per_s"] = row.get("images_per_s_stream", row["images_per_s_synced"])
        obs1 = {}  # single-ping maps: voxels in view, and the template's holes against gather
        for k in np.unique(np.linspace(0, n - 1, PROBE_PINGS).round().astype(int)):
            m.reset()
            m.integrate(pings.images[k], pings.poses[k])
            obs1[int(k)] = m.observed()
    row.update(peak_host_rss_mb=rss.delta_mb, grid_mb=grid.nbytes / 2**20, others_cores=cpu.others_cores,
               steal_cores=cpu.steal_cores)
    if dev0 is not None and dev1 is not None:
        row["device_mem_mb"] = (dev1 - dev0) / 2**20
    row["voxels_in_view"] = float(np.mean([o.sum() for o in obs1.values()]))
    obs_all = None if values is None else ~np.isnan(values)
    if values is not None:
        row.update(score(values, vt, threshold))
    if method == "template" and ref_obs is not None:
        g1 = ref_obs.get("single", {})
        fr = [float((g1[k] & ~obs1[k]).sum() / max(1, g1[k].sum())) for k in obs1 if k in g1]
        if fr:
            row["hole_fraction_single_ping"] = float(np.mean(fr))
        g = ref_obs.get("all")
        if obs_all is not None and g is not None:
            row["hole_fraction_all_pings"] = float((g & ~obs_all).sum() / max(1, g.sum()))
    del m
    return row, {"single": obs1, "all": obs_all}


def baseline_row(name: str, make, pings: TankPings, vt: VoxelTruth, threshold: float, score_threshold: float,
                 extra: dict) -> dict:
    """Time a baseline over every ping (1 warm-up ping, then reset) and score its map."""
    gc.collect()
    with PeakRSS() as rss, CpuShare() as cpu:
        t0 = time.perf_counter()
        make().integrate(pings.images[0], pings.poses[0])
        setup_s = time.perf_counter() - t0
        b = make()  # fresh state: the warm-up ping must not count twice
        lat = []
        for k in range(len(pings)):
            t = time.perf_counter()
            b.integrate(pings.images[k], pings.poses[k])
            lat.append(1e3 * (time.perf_counter() - t))
        t = time.perf_counter()
        values = b.values()
        extract_s = time.perf_counter() - t
    row = {"kind": name, "voxel_size_m": vt.scene.grid.voxel_size_m, "grid_shape": list(vt.scene.grid.shape),
           "pings": len(pings), "pings_timed": len(pings), "warmup_pings": 1, "setup_s_incl_warmup": setup_s,
           **_latency(lat), "map_extract_s": extract_s, "peak_host_rss_mb": rss.delta_mb,
           "others_cores": cpu.others_cores, "steal_cores": cpu.steal_cores, "threshold": threshold, **extra}
    return row | {"images_per_s": row["images_per_s_synced"]} | score(values, vt, score_threshold)


def run_baselines(pings: TankPings, vt: VoxelTruth, threshold: float, fnr: float, fast_backend: str,
                  progress: bool) -> list[dict]:
    from .baselines import OasisRule, OctoMapBaseline, PaperSixSteps

    spec, grid, rows = vt.scene.sonar_spec, vt.scene.grid, []
    jobs = [("paper-numpy", lambda: PaperSixSteps(spec, grid), threshold,
             {"note": "paper Section II-B six steps in plain NumPy (template, round, max over the bins x "
              "beams of the voxel's corners)"}),
            ("oasis-rule", lambda: OasisRule(spec, grid, threshold, fnr, backend=fast_backend), 0.5,
             {"fnr": fnr, "backend": fast_backend,
              "note": f"OASIS hits/observations > 1 - fnr rule on gpumap "
              f"{fast_backend} footprints (our implementation, not the OASIS code)"}),
            ("octomap", lambda: OctoMapBaseline(spec, grid, threshold), 0.5,
             {"note": "pyoctomap insertPointCloud, strongest return per beam at elevation 0, ray casting"})]
    for name, make, thr, extra in jobs:
        try:
            rows.append(baseline_row(name, make, pings, vt, threshold, thr, extra))
        except Exception as e:  # one failing baseline must not hide the rest
            rows.append({"kind": name, "voxel_size_m": grid.voxel_size_m, "error": repr(e), **extra})
        if progress:
            r = rows[-1]
            tqdm.write(f"  {name:12s} {grid.voxel_size_m * 100:4.1f} cm  "
                                 f"{r.get('images_per_s', float('nan')):8.1f} img/s  "
                                 f"FN {r.get('false_negative_rate', float('nan')):.3f}  {r.get('error', '')}")
    return rows


# ------------------------------------------------------------------------------ scaling
def voxels_fit(rows: list[dict]) -> list[dict[str, Any]]:
    """Per (backend, method): median ms per image against voxels in view, fitted linearly."""
    groups: dict[tuple[str, str, str], list[dict]] = defaultdict(list)
    for r in rows:
        if r.get("kind") == "gpumap" and "ms_median" in r and r.get("voxels_in_view"):
            groups[(r["backend"], r.get("device", ""), r["method"])].append(r)
    out = []
    for (b, dev, m), rs in sorted(groups.items()):
        if len(rs) >= 2:
            x, y = np.array([r["voxels_in_view"] for r in rs]), np.array([r["ms_median"] for r in rs])
            f = linear_fit(x, y)
            out.append({"backend": b, "device": dev, "on_gpu": b in GPU_BACKENDS, "method": m,
                        "voxels_in_view": x.tolist(), "ms_median": y.tolist(),
                        "voxel_size_m": [r["voxel_size_m"] for r in rs], "ms_fixed": f["intercept"],
                        "ns_per_voxel": 1e6 * f["slope"], "r2": f["r2"], "loglog_slope": f["loglog_slope"]})
    return out


def image_size_sweep(backends: list[str], voxel_size_m: float = 0.03, pings: int = 20, method: str = "gather",
                     progress: bool = True) -> list[dict[str, Any]]:
    """Median ms per image against image size (bins x beams) at one voxel size, synthetic speckle."""
    grid, poses, out = common.tank_grid(voxel_size_m), common.trajectory(pings), []
    jobs = [(b, s) for b in backends for s in IMAGE_SIZES]
    for b, (nb, nbeam) in progress_bar(jobs, desc="image sizes", unit="row", disable=not progress):
        spec = common.tank_spec(n_beams=nbeam, n_bins=nb)
        rng = np.random.default_rng(0)
        imgs = [(rng.random(spec.image_shape,
                            dtype=np.float32) ** 6 * 255).astype(np.uint8) for _ in range(8)]
        n = pings if b != "numpy" else min(pings, 6)
        try:
            m = gpumap.MinMaxMapper(spec, grid, b, MapperParams(method=method))
            warm_up(m, imgs, poses, 3)
            lat = synced_ms(m, imgs, poses, n)
            out.append({"backend": b, "device": m.device, "on_gpu": b in GPU_BACKENDS, "method": method,
                        "voxel_size_m": voxel_size_m, "n_bins": nb, "n_beams": nbeam, "pixels": nb * nbeam,
                        "pings": n, "ms_median": float(np.median(lat)),
                        "ms_p95": float(np.percentile(lat, 95))})
        except Exception as e:
            out.append({"backend": b, "n_bins": nb, "n_beams": nbeam, "error": repr(e)})
    return out


def ekf_cost(counts: tuple[int, ...] = (4, 8, 16, 32, 64, 128, 200), reps: int = 50,
             blas_threads: int | None = None) -> list[dict[str, Any]]:
    """Median predict / update cost of :class:`gpumap.ekf.SonarEKF` against features in the state.

    ``blas_threads`` runs the timing in a subprocess with ``OPENBLAS_NUM_THREADS`` (and the OpenMP /
    MKL equivalents) set, since BLAS threads cannot be changed once NumPy has loaded.
    """
    if blas_threads is not None:
        import subprocess

        threads = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
        env = dict(os.environ) | {k: str(blas_threads) for k in threads}
        code = (f"import json, sys; from {__package__}.sweep import ekf_cost; "
                f"print(json.dumps(ekf_cost({tuple(counts)!r}, {reps})))")
        p = subprocess.run([sys.executable, "-c", code], cwd=Path(__file__).resolve().parents[1], env=env,
                           capture_output=True, text=True, check=True)
        return [r | {"blas_threads": blas_threads} for r in json.loads(p.stdout.strip().splitlines()[-1])]
    from .ekf_bench import _time_updates

    rows = [_time_updates(n, reps) for n in counts]
    f = linear_fit([r["state_dim"] for r in rows], [r["update_us_median"] for r in rows])
    return [r | {"loglog_slope_vs_state_dim": f["loglog_slope"], "blas_threads": "default"} for r in rows]


# ------------------------------------------------------------------------------ the run
def _choose_backends(requested: list[str] | None, gpu_only: bool) -> list[str]:
    avail = gpumap.available_backends()
    out = list(avail)
    if requested:
        missing = [b for b in requested if b not in avail and b not in ("opencl",)]
        if missing:
            print(f"gpumap bench: skipping unavailable backends {missing} (available: {avail})",
                  file=sys.stderr)
        out = [b for b in requested if b in avail or b == "opencl"]
    # numpy last: its slow rows borrow map quality from the others
    return sorted((b for b in out if b in GPU_BACKENDS or not gpu_only), key=lambda b: (b == "numpy", b))


def _capped(row: dict, rows: list[dict], meth: str, v: float) -> None:
    """A capped numpy row takes its map quality from another backend's row (the same algorithm)."""
    src = next((r for r in rows if r.get("kind") == "gpumap" and r.get("method") == meth
                and r.get("voxel_size_m") == v and "false_negative_rate" in r), None)
    if src is not None:
        row.update({k: src[k] for k in (*EVALUATION_KEYS, *SCORE_EXTRA_KEYS,
                                        "hole_fraction_all_pings") if k in src})
        row["quality_from"] = src["backend"]
    row["note"] = (f"timed on the first {row['pings_timed']} pings (slow row capped); map "
                   f"quality copied from {row.get('quality_from', 'nothing')} (same algorithm)")


def run(args: argparse.Namespace) -> dict:
    """Run the sweep for parsed ``args``; returns the result dict (also written as JSON)."""
    progress, t_start = not args.no_progress, time.perf_counter()
    share = CpuShare().__enter__()
    info = common.machine_info()
    from gpumap.sim.sonar import OCCUPIED_THRESHOLD

    threshold = OCCUPIED_THRESHOLD if args.threshold is None else args.threshold
    n_pings = args.pings if args.pings is not None else (16 if args.quick else None)
    if args.pings_from:
        pings = load_pings(args.pings_from)
        if n_pings is not None and n_pings < len(pings):
            sel = np.unique(np.linspace(0, len(pings) - 1, n_pings).round().astype(int))
            pings = TankPings(pings.images[sel], pings.poses[sel], pings.seen_cells, dict(pings.meta))
            pings.meta["subset"] = sel.tolist()
    else:
        pings = simulate_tank(n_pings, seed=args.seed, progress=progress)
    if args.save_pings:
        pings.save(args.save_pings)
    backends = _choose_backends(args.backend, args.gpu_only)
    if not backends:
        raise SystemExit(f"gpumap bench: no backend to run (available: {gpumap.available_backends()})")
    if args.voxel:
        voxels = list(args.voxel)
    elif args.gpu_only or args.quick:
        voxels = list(GPU_ONLY_VOXELS) if args.gpu_only else [0.05, 0.03]
    else:
        on_gpu = any(b in GPU_BACKENDS for b in backends)
        voxels = list(CPU_VOXELS) + (list(GPU_EXTRA_VOXELS) if on_gpu else [])
    fast = next((b for b in backends if b != "numpy"), backends[0])
    plan = [(v, b, m) for v in voxels for b in backends for m in args.method
            if not (v < 0.01 - 1e-9 and b not in GPU_BACKENDS)]
    rows: list[dict] = []
    truth_s = {}
    bar = progress_bar(total=len(plan), desc="bench", unit="row", disable=not progress)
    for v in voxels:
        todo = [(b, m) for vv, b, m in plan if vv == v]
        if not todo:
            continue
        vt = voxel_truth(v, pings.seen_cells, seed=pings.meta.get("seed", args.seed))
        truth_s[v] = vt.truth_s
        gather_obs: dict[str, dict] = {}
        for b, meth in todo:
            cap = args.numpy_cap if (b == "numpy" and v <= 0.02 + 1e-9) else None
            try:
                row, obs = gpumap_row(pings, vt, b, meth, threshold, cap, gather_obs.get(b), args.shadow_m)
                if meth == "gather":
                    gather_obs[b] = obs
            except Exception as e:  # record and go on: one failing backend must not hide the rest
                row = {"kind": "gpumap", "backend": b, "method": meth, "voxel_size_m": v, "error": repr(e)}
            if cap is not None and "error" not in row and "false_negative_rate" not in row:
                _capped(row, rows, meth, v)
            rows.append(row)
            bar.update()
            if progress:
                bar.write(f"  {b:11s} {meth:8s} {v * 100:4.1f} cm  "
                          f"{row.get('images_per_s', float('nan')):8.1f} img/s  "
                          f"median {row.get('ms_median', float('nan')):8.2f} ms  "
                          f"FN {row.get('false_negative_rate', float('nan')):.3f}  {row.get('error', '')}")
        if not (args.gpu_only or args.no_baselines):
            rows += run_baselines(pings, vt, threshold, args.fnr, fast, progress)
        del vt, gather_obs
        gc.collect()
    bar.close()
    scaling: dict[str, Any] = {}
    if not (args.no_scaling or args.quick):
        scaling["voxels_in_view_fit"] = voxels_fit(rows)
        sized = [b for b in backends if b != "numpy" or not args.gpu_only]
        scaling["image_size"] = image_size_sweep(sized, progress=progress)
        if not args.gpu_only:
            scaling["ekf"], scaling["ekf_one_blas_thread"] = ekf_cost(), ekf_cost(blas_threads=1)
    if "sim" in pings.meta and not args.pings_from:
        scaling["simulator"] = pings.meta["sim"]
    share.__exit__(None, None, None)
    common.mark_load(info, share)
    run_info = {
        "scene": "tank", "seed": pings.meta.get("seed", args.seed), "pings": len(pings),
        "ping_source": pings.meta.get("loaded_from", "simulated in this run"),
        "image_shape": list(pings.images.shape[1:]), "image_dtype": "uint8 (as the Oculus delivers)",
        "threshold": threshold, "oasis_fnr": args.fnr, "shadow_m": args.shadow_m, "warmup_pings": WARMUP,
        "warmup_note": f"{WARMUP} pings (1 for numpy and baselines) integrated, synchronized and "
        "discarded (map reset) before timing; not in any figure", "numpy_cap": args.numpy_cap,
        "quick": bool(args.quick), "gpu_only": bool(args.gpu_only),
        "timing_note": "ms_*: each ping integrate()+synchronize(), image upload included; images_per_s: "
        "back-to-back stream with one sync at the end where the row was fast enough, else 1000 / ms_mean",
        "truth_s": {str(k): v for k, v in truth_s.items()}, "duration_s": time.perf_counter() - t_start}
    published = {"paper_table_i_s_per_image": {str(k): v for k, v in common.PAPER_TABLE_I.items()},
                 "oasis_code_ms_per_image_issue6": {str(k): v for k, v in common.OASIS_PUBLISHED_MS.items()},
                 "targets": [{"device": d, "voxel_size_m": v,
                              "images_per_s": h} for d, v, h in common.TARGETS]}
    return common.compact({"schema": "gpumap-bench/1",
                           "tag": args.tag or common.machine_tag(info, args.gpu_only, True),
                           "created": common.now(), "argv": sys.argv[1:] if args.argv is None else args.argv,
                           "machine": info, "run": run_info, "published": published, "rows": rows,
                           "scaling": scaling})


def keeps_up_table(res: dict, rates=SONAR_RATES_HZ) -> str:
    """The sweep in a few lines: per voxel size, the fastest gpumap row (backend, method) in images per
    second and the sonar ping rates of ``rates`` it keeps up with."""
    best: dict[float, dict] = {}
    for r in res.get("rows", ()):
        if r.get("kind") == "gpumap" and "error" not in r and r.get("images_per_s"):
            v = float(r["voxel_size_m"])
            if v not in best or r["images_per_s"] > best[v]["images_per_s"]:
                best[v] = r
    lines = [f"{'voxel':>7}  {'fastest here':<22} {'images/s':>9}  keeps up with a sonar pinging at"]
    for v in sorted(best, reverse=True):
        r = best[v]
        ok = [f"{h} Hz" for h in rates if r["images_per_s"] >= h]
        not_ok = [f"{h} Hz" for h in rates if r["images_per_s"] < h]
        verdict = ", ".join(ok) if ok else "none of " + ", ".join(not_ok)
        if ok and not_ok:
            verdict += f" (not {', '.join(not_ok)})"
        who = f"{r['backend']} {r['method']}"
        lines.append(f"{v * 100:5.1f} cm  {who:<22} {r['images_per_s']:9.1f}  {verdict}")
    if not best:
        lines.append("  (no gpumap row finished: see the errors in the results file)")
    return "\n".join(lines)


def write_result(res: dict, out: Path) -> Path:
    """Write a sweep's result as ``out/<tag>.json``, say where, and end with :func:`keeps_up_table`."""
    path = common.write_json(out / f"{res['tag']}.json", res, indent=None)
    print(f"wrote {path} ({path.stat().st_size / 1024:.0f} kB) in {res['run']['duration_s']:.0f} s; "
          f"in a checkout, python -m bench.report --results {out} writes BENCHMARKS.md from that folder")
    print(keeps_up_table(res))
    return path


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``python -m bench.sweep`` (``python -m bench`` runs it through the runner)."""
    args = _parser().parse_args(argv)
    args.argv = argv
    write_result(run(args), args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
