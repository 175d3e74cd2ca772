"""``python -m bench`` (``gpumap bench``, ``python -m bench sweep``): speed against error on the
simulated tank, in one run.

The tank's pings are rendered once (or loaded with ``--pings-from``) and the same pings go
to every configuration: voxel size x backend x method of gpumap, and the baselines of
:mod:`bench.baselines` (the paper's six steps in plain NumPy, the OASIS rule, OctoMap).
Per row: median / p95 ms per image (each ping synchronized, image upload included),
images/s (pings handed over back to back, one sync at the end, when the row is fast
enough to repeat), peak host memory (RSS rise) and device memory where the backend can
tell, and the map's errors against ground truth (:func:`gpumap.sim.metrics.evaluate`).
Then scaling (time vs voxels in view, vs image size; EKF update cost vs features; the
simulator's images/s). Writes ``bench/results/<machine-tag>.json``; ``python -m
bench.report`` turns every JSON there into ``BENCHMARKS.md`` and its plots.

    python -m bench                      # full CPU sweep (about 10 min on 2 cores)
    python -m bench --quick              # 5 and 3 cm, 16 pings, no scaling
    python -m bench --save-pings bench/tank_pings.npz      # also keep the pings (~6 MB)
    python -m bench --gpu-only --pings-from bench/tank_pings.npz   # GPU box (no renderer)
"""

from __future__ import annotations

import argparse
import gc
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

import gpumap

from .common import (
    OASIS_PUBLISHED_MS,
    PAPER_TABLE_I,
    TARGETS,
    CpuShare,
    PeakRSS,
    compact,
    machine_info,
    machine_tag,
    mark_load,
    stream_rate,
    synced_ms,
    warm_up,
    write_json,
)
from .tank import TankPings, VoxelTruth, load_pings, simulate_tank, voxel_truth

CPU_VOXELS = (0.06, 0.05, 0.04, 0.03, 0.02, 0.01)
GPU_EXTRA_VOXELS = (0.005,)
GPU_ONLY_VOXELS = (0.03, 0.01, 0.005)
GPU_BACKENDS = ("warp-cuda", "opencl-gpu")
METHODS = ("gather", "template")
WARMUP = 3  # pings integrated and discarded before timing (kernel compile, caches); 1 for pure NumPy
STREAM_SECONDS = {False: 1.0, True: 2.0}  # aim of the back-to-back throughput pass (CPU, GPU)
PROBE_PINGS = 4  # single-ping maps used for voxels-in-view and template holes


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
    p.add_argument(
        "--gpu-only",
        action="store_true",
        help="warp-cuda / opencl-gpu rows at 3, 1, 0.5 cm only; no baselines",
    )
    p.add_argument("--quick", action="store_true", help="5 and 3 cm, 16 pings, no scaling section")
    p.add_argument("--no-baselines", action="store_true",
                   help="skip the baselines (the paper in NumPy, OASIS hit ratio, OctoMap)")
    p.add_argument("--no-scaling", action="store_true",
                   help="skip the scaling section (rate against grid size)")
    p.add_argument(
        "--numpy-cap",
        type=int,
        default=8,
        help="timed pings of the numpy backend at <= 2 cm (its map quality is then taken "
        "from another backend: the same algorithm)",
    )
    p.add_argument(
        "--threshold", type=float, default=None, help="occupied intensity (default: the simulator's)"
    )
    p.add_argument("--fnr", type=float, default=0.5, help="OASIS false-negative rate")
    p.add_argument(
        "--shadow-m",
        type=float,
        default=0.0,
        help="gpumap's shadow_m (a return also counts this far behind it; 0 = the paper)",
    )
    p.add_argument("--seed", type=int, default=0, help="random seed of the simulated pings (default 0)")
    p.add_argument("--out", type=Path, default=Path("bench/results"),
                   help="folder for the results (JSON, plots); default bench/results")
    p.add_argument("--tag", default=None, help="result file stem (default: from the machine)")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    return p


# ------------------------------------------------------------------------------ scoring
# what score() keeps of gpumap.sim.metrics.evaluate, and what it adds
EVALUATION_KEYS = (
    "observed_fraction",
    "false_negative_rate",
    "false_negative_rate_objects",
    "false_positive_rate",
    "false_positive_rate_far",
    "free_carved_fraction",
    "height_error_m",
    "pipe_found",
)
SCORE_EXTRA_KEYS = ("miss_rate_seen", "height_error_mean_m")


def score(values: np.ndarray, vt: VoxelTruth, threshold: float) -> dict[str, Any]:
    """Errors of a map against the truth, plus the miss rate over every seen surface voxel."""
    from gpumap.sim.metrics import evaluate

    ev = evaluate(values, vt.truth, threshold, vt.seen, vt.scene.grid.voxel_size_m).to_dict()
    occ = np.nan_to_num(values, nan=-np.inf) >= threshold
    target = vt.truth.occupied & vt.seen
    n = int(target.sum())
    out = {k: ev[k] for k in EVALUATION_KEYS}
    # A seen obstacle voxel the map does not call occupied, observed or not (OctoMap observes little).
    out["miss_rate_seen"] = float((target & ~occ).sum() / n) if n else float("nan")
    he = [x for x in ev["height_error_m"].values() if x is not None and np.isfinite(x)]
    out["height_error_mean_m"] = float(np.mean(he)) if he else float("nan")
    return out


def _sync_time(fn, *a) -> float:
    t = time.perf_counter()
    fn(*a)
    return time.perf_counter() - t


def _latency(ms: list[float]) -> dict[str, float]:
    a = np.asarray(ms)
    return {
        "ms_median": float(np.median(a)),
        "ms_p95": float(np.percentile(a, 95)),
        "ms_mean": float(a.mean()),
        "images_per_s_synced": float(1e3 / a.mean()),
    }


def _device_mem_probe(backend: str):
    """A callable returning device bytes in use (None if the backend cannot tell)."""
    if backend not in GPU_BACKENDS:
        return None
    try:
        import warp as wp

        dev = wp.get_device("cuda:0")
        if backend == "warp-cuda" and wp.is_mempool_enabled(dev):
            probe = lambda: int(wp.get_mempool_used_mem_current(dev))  # noqa: E731
        else:
            probe = lambda: int(dev.total_memory - dev.free_memory)  # noqa: E731
        probe()
    except Exception:  # informative only: no device memory figure
        return None

    def safe() -> int | None:
        try:
            return probe()
        except Exception:
            return None

    return safe


# ------------------------------------------------------------------------------ gpumap rows
def gpumap_row(
    pings: TankPings,
    vt: VoxelTruth,
    backend: str,
    method: str,
    threshold: float,
    cap: int | None,
    ref_obs: dict | None,
    shadow_m: float = 0.0,
) -> tuple[dict, dict]:
    """Time and score one gpumap configuration; returns the row and its observed masks."""
    spec, grid = vt.scene.sonar_spec, vt.scene.grid
    n = len(pings)
    n_timed = n if cap is None else min(n, cap)
    warm = 1 if backend == "numpy" else WARMUP
    mem = _device_mem_probe(backend)
    gc.collect()
    dev0 = mem() if mem else None
    with PeakRSS() as rss, CpuShare() as cpu:
        t0 = time.perf_counter()
        extra = {"shadow_m": shadow_m} if shadow_m else {}  # older gpumap has no shadow_m
        m = gpumap.MinMaxMapper(spec, grid, backend=backend, method=method, **extra)
        warm_up(m, pings.images, pings.poses, warm)
        setup_s = time.perf_counter() - t0
        lat = synced_ms(m, pings.images, pings.poses, n_timed)
        dev1 = mem() if mem else None
        values = m.values() if n_timed == n else None
        row: dict[str, Any] = {
            "kind": "gpumap",
            "backend": backend,
            "backend_reported": m.backend,
            "device": m.device,
            "on_gpu": backend in GPU_BACKENDS,
            "method": method,
            "shadow_m": shadow_m,
            "voxel_size_m": grid.voxel_size_m,
            "grid_shape": list(grid.shape),
            "pings": n,
            "pings_timed": n_timed,
            "warmup_pings": warm,
            "setup_s_incl_warmup": setup_s,
            **_latency(lat),
        }
        # Throughput: pings back to back, one sync at the end (what a ping stream sees).
        aim = STREAM_SECONDS[backend in GPU_BACKENDS]
        if sum(lat) < 1e3 * aim:
            reps = max(1, math.ceil(aim * 1e3 / max(sum(lat), 1e-3)))
            reps = min(max(reps, 3), 300)
            rates = []  # three chunks; the median damps a burst of other work on a shared machine
            for chunk in np.array_split(np.arange(reps), 3):
                rates.append(stream_rate(m, pings.images, pings.poses, len(chunk) * n))
            row["images_per_s_stream"] = float(np.median(rates))
            row["images_per_s_stream_chunks"] = rates
            row["stream_pings"] = reps * n
        row["images_per_s"] = row.get("images_per_s_stream", row["images_per_s_synced"])
        # Single-ping maps: voxels in view, and the template's holes against gather.
        probe = np.unique(np.linspace(0, n - 1, PROBE_PINGS).round().astype(int))
        obs1 = {}
        for k in probe:
            m.reset()
            m.integrate(pings.images[k], pings.poses[k])
            obs1[int(k)] = m.observed()
    row["peak_host_rss_mb"] = rss.delta_mb
    row["grid_mb"] = grid.nbytes / 2**20
    row["others_cores"], row["steal_cores"] = cpu.others_cores, cpu.steal_cores
    if dev0 is not None and dev1 is not None:
        row["device_mem_mb"] = (dev1 - dev0) / 2**20
    row["voxels_in_view"] = float(np.mean([o.sum() for o in obs1.values()]))
    obs_all = None
    if values is not None:
        obs_all = ~np.isnan(values)
        row.update(score(values, vt, threshold))
    if method == "template" and ref_obs is not None:
        g1 = ref_obs.get("single", {})
        fr = [float((g1[k] & ~obs1[k]).sum() / max(1, g1[k].sum())) for k in obs1 if k in g1]
        if fr:
            row["hole_fraction_single_ping"] = float(np.mean(fr))
        if obs_all is not None and ref_obs.get("all") is not None:
            g = ref_obs["all"]
            row["hole_fraction_all_pings"] = float((g & ~obs_all).sum() / max(1, g.sum()))
    del m
    return row, {"single": obs1, "all": obs_all}


# ------------------------------------------------------------------------------ baseline rows
def baseline_row(
    name: str, make, pings: TankPings, vt: VoxelTruth, threshold: float, score_threshold: float, extra: dict
) -> dict:
    """Time a baseline over every ping (1 warm-up ping, then reset) and score its map."""
    grid = vt.scene.grid
    gc.collect()
    with PeakRSS() as rss, CpuShare() as cpu:
        t0 = time.perf_counter()
        b = make()
        b.integrate(pings.images[0], pings.poses[0])
        setup_s = time.perf_counter() - t0
        b = make()  # fresh state: the warm-up ping must not count twice
        lat = [1e3 * _sync_time(b.integrate, pings.images[k], pings.poses[k]) for k in range(len(pings))]
        t = time.perf_counter()
        values = b.values()
        extract_s = time.perf_counter() - t
    row = {
        "kind": name,
        "voxel_size_m": grid.voxel_size_m,
        "grid_shape": list(grid.shape),
        "pings": len(pings),
        "pings_timed": len(pings),
        "warmup_pings": 1,
        "setup_s_incl_warmup": setup_s,
        **_latency(lat),
        "map_extract_s": extract_s,
        "peak_host_rss_mb": rss.delta_mb,
        "others_cores": cpu.others_cores,
        "steal_cores": cpu.steal_cores,
        "threshold": threshold,
        **extra,
    }
    row["images_per_s"] = row["images_per_s_synced"]
    row.update(score(values, vt, score_threshold))
    return row


def run_baselines(
    pings: TankPings, vt: VoxelTruth, threshold: float, fnr: float, fast_backend: str, progress: bool
) -> list[dict]:
    from .baselines import OasisRule, OctoMapBaseline, PaperSixSteps

    spec, grid = vt.scene.sonar_spec, vt.scene.grid
    rows = []
    jobs = [
        (
            "paper-numpy",
            lambda: PaperSixSteps(spec, grid),
            threshold,
            {
                "note": "paper Section II-B six steps in plain NumPy (template, round, max over the bins x "
                "beams of the voxel's corners)"
            },
        ),
        (
            "oasis-rule",
            lambda: OasisRule(spec, grid, threshold, fnr, backend=fast_backend),
            0.5,
            {
                "fnr": fnr,
                "backend": fast_backend,
                "note": f"OASIS hits/observations > 1 - fnr rule on gpumap {fast_backend} footprints "
                "(our implementation, not the OASIS code)",
            },
        ),
        (
            "octomap",
            lambda: OctoMapBaseline(spec, grid, threshold),
            0.5,
            {"note": "pyoctomap insertPointCloud, strongest return per beam at elevation 0, ray casting"},
        ),
    ]
    for name, make, thr, extra in jobs:
        try:
            rows.append(baseline_row(name, make, pings, vt, threshold, thr, extra))
        except Exception as e:  # one failing baseline must not hide the rest
            rows.append({"kind": name, "voxel_size_m": grid.voxel_size_m, "error": repr(e), **extra})
        if progress:
            r = rows[-1]
            tqdm.write(
                f"  {name:12s} {grid.voxel_size_m * 100:4.1f} cm  "
                f"{r.get('images_per_s', float('nan')):8.1f} img/s  "
                f"FN {r.get('false_negative_rate', float('nan')):.3f}  {r.get('error', '')}"
            )
    return rows


# ------------------------------------------------------------------------------ the run
def _choose_backends(requested: list[str] | None, gpu_only: bool) -> list[str]:
    avail = gpumap.available_backends()
    if requested:
        missing = [b for b in requested if b not in avail and b not in ("opencl",)]
        if missing:
            print(
                f"gpumap bench: skipping unavailable backends {missing} (available: {avail})", file=sys.stderr
            )
        out = [b for b in requested if b in avail or b == "opencl"]
    else:
        out = list(avail)
    if gpu_only:
        out = [b for b in out if b in GPU_BACKENDS]
    # numpy last: its slow rows borrow map quality from the others
    return sorted(out, key=lambda b: (b == "numpy", b))


def run(args: argparse.Namespace) -> dict:
    """Run the sweep for parsed ``args``; returns the result dict (also written as JSON)."""
    progress = not args.no_progress
    t_start = time.perf_counter()
    share = CpuShare().__enter__()
    info = machine_info()
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
    elif args.gpu_only:
        voxels = list(GPU_ONLY_VOXELS)
    elif args.quick:
        voxels = [0.05, 0.03]
    else:
        on_gpu = any(b in GPU_BACKENDS for b in backends)
        voxels = list(CPU_VOXELS) + (list(GPU_EXTRA_VOXELS) if on_gpu else [])
    fast = next((b for b in backends if b != "numpy"), backends[0])
    rows: list[dict] = []
    truth_s = {}
    plan = [
        (v, b, m)
        for v in voxels
        for b in backends
        for m in args.method
        if not (v < 0.01 - 1e-9 and b not in GPU_BACKENDS)
    ]
    bar = tqdm(total=len(plan), desc="bench", unit="row", disable=not progress)
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
                src = next(
                    (
                        r
                        for r in rows
                        if r.get("kind") == "gpumap"
                        and r.get("method") == meth
                        and r.get("voxel_size_m") == v
                        and "false_negative_rate" in r
                    ),
                    None,
                )
                if src is not None:
                    for k in (*EVALUATION_KEYS, *SCORE_EXTRA_KEYS, "hole_fraction_all_pings"):
                        if k in src:
                            row[k] = src[k]
                    row["quality_from"] = src["backend"]
                row["note"] = (
                    f"timed on the first {row['pings_timed']} pings (slow row capped); map "
                    f"quality copied from {row.get('quality_from', 'nothing')} (same algorithm)"
                )
            rows.append(row)
            bar.update()
            if progress:
                tqdm.write(
                    f"  {b:11s} {meth:8s} {v * 100:4.1f} cm  "
                    f"{row.get('images_per_s', float('nan')):8.1f} img/s  "
                    f"median {row.get('ms_median', float('nan')):8.2f} ms  "
                    f"FN {row.get('false_negative_rate', float('nan')):.3f}  {row.get('error', '')}"
                )
        if not (args.gpu_only or args.no_baselines):
            rows += run_baselines(pings, vt, threshold, args.fnr, fast, progress)
        del vt, gather_obs
        gc.collect()
    bar.close()

    scaling: dict[str, Any] = {}
    if not (args.no_scaling or args.quick):
        from .scaling import ekf_cost, image_size_sweep, voxels_fit

        scaling["voxels_in_view_fit"] = voxels_fit(rows)
        scaling["image_size"] = image_size_sweep(
            [b for b in backends if b != "numpy" or not args.gpu_only], progress=progress
        )
        if not args.gpu_only:
            scaling["ekf"] = ekf_cost()
            scaling["ekf_one_blas_thread"] = ekf_cost(blas_threads=1)
    if "sim" in pings.meta and not args.pings_from:
        scaling["simulator"] = pings.meta["sim"]

    share.__exit__(None, None, None)
    mark_load(info, share)
    result = {
        "schema": "gpumap-bench/1",
        "tag": args.tag or machine_tag(info, args.gpu_only, model=True),
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "argv": sys.argv[1:] if args.argv is None else args.argv,
        "machine": info,
        "run": {
            "scene": "tank",
            "seed": pings.meta.get("seed", args.seed),
            "pings": len(pings),
            "ping_source": pings.meta.get("loaded_from", "simulated in this run"),
            "image_shape": list(pings.images.shape[1:]),
            "image_dtype": "uint8 (as the Oculus delivers)",
            "threshold": threshold,
            "oasis_fnr": args.fnr,
            "shadow_m": args.shadow_m,
            "warmup_pings": WARMUP,
            "warmup_note": f"{WARMUP} pings (1 for numpy and baselines) integrated, synchronized and "
            "discarded (map reset) before timing; not in any figure",
            "numpy_cap": args.numpy_cap,
            "quick": bool(args.quick),
            "gpu_only": bool(args.gpu_only),
            "timing_note": "ms_*: each ping integrate()+synchronize(), image upload included; images_per_s: "
            "back-to-back stream with one sync at the end where the row was fast enough, "
            "else 1000 / ms_mean",
            "truth_s": {str(k): v for k, v in truth_s.items()},
            "duration_s": time.perf_counter() - t_start,
        },
        "published": {
            "paper_table_i_s_per_image": {str(k): v for k, v in PAPER_TABLE_I.items()},
            "oasis_code_ms_per_image_issue6": {str(k): v for k, v in OASIS_PUBLISHED_MS.items()},
            "targets": [{"device": d, "voxel_size_m": v, "images_per_s": h} for d, v, h in TARGETS],
        },
        "rows": rows,
        "scaling": scaling,
    }
    return compact(result)


#: Ping rates of imaging sonars the summary table checks against (an Oculus runs at up to 40 Hz).
SONAR_RATES_HZ = (5, 10, 20, 40)


def keeps_up_table(res: dict, rates=SONAR_RATES_HZ) -> str:
    """The sweep in a few lines: per voxel size, the fastest gpumap row (backend, method) in
    images per second and the sonar ping rates of ``rates`` it keeps up with."""
    best: dict[float, dict] = {}
    for r in res.get("rows", ()):
        if r.get("kind") != "gpumap" or "error" in r or not r.get("images_per_s"):
            continue
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
    path = write_json(out / f"{res['tag']}.json", res, indent=None)
    print(
        f"wrote {path} ({path.stat().st_size / 1024:.0f} kB) in {res['run']['duration_s']:.0f} s; "
        f"in a checkout, python -m bench.report --results {out} writes BENCHMARKS.md from that folder"
    )
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
