"""Scaling of the mapper's cost: against voxels in view, against image size; the EKF against features."""

from __future__ import annotations

from collections import defaultdict
from typing import Any

import numpy as np
from tqdm import tqdm

import gpumap

from .common import synced_ms, warm_up

__all__ = ["IMAGE_SIZES", "ekf_cost", "image_size_sweep", "linear_fit", "voxels_fit"]

#: (n_bins, n_beams) of the image-size sweep.
IMAGE_SIZES = ((200, 128), (400, 256), (400, 512), (800, 512), (800, 1024))


def linear_fit(x: np.ndarray, y: np.ndarray) -> dict[str, float]:
    """Least-squares ``y = a + b x`` with R^2, and the log-log slope (1 = linear growth)."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    A = np.stack([np.ones_like(x), x], 1)
    (a, b), *_ = np.linalg.lstsq(A, y, rcond=None)
    ss_res = float(np.sum((y - (a + b * x)) ** 2))
    ss_tot = float(np.sum((y - y.mean()) ** 2))
    ok = (x > 0) & (y > 0)
    slope = float(np.polyfit(np.log(x[ok]), np.log(y[ok]), 1)[0]) if ok.sum() >= 2 else float("nan")
    return {
        "intercept": float(a),
        "slope": float(b),
        "r2": 1.0 - ss_res / ss_tot if ss_tot > 0 else 1.0,
        "loglog_slope": slope,
    }


def voxels_fit(rows: list[dict]) -> list[dict[str, Any]]:
    """Per (backend, method): median ms per image against voxels in view, fitted linearly."""
    groups: dict[tuple[str, str, str], list[dict]] = defaultdict(list)
    for r in rows:
        if r.get("kind") == "gpumap" and "ms_median" in r and r.get("voxels_in_view"):
            groups[(r["backend"], r.get("device", ""), r["method"])].append(r)
    out = []
    for (b, dev, m), rs in sorted(groups.items()):
        if len(rs) < 2:
            continue
        x = np.array([r["voxels_in_view"] for r in rs])
        y = np.array([r["ms_median"] for r in rs])
        f = linear_fit(x, y)
        out.append(
            {
                "backend": b,
                "device": dev,
                "on_gpu": b in ("warp-cuda", "opencl-gpu"),
                "method": m,
                "voxels_in_view": x.tolist(),
                "ms_median": y.tolist(),
                "voxel_size_m": [r["voxel_size_m"] for r in rs],
                "ms_fixed": f["intercept"],
                "ns_per_voxel": 1e6 * f["slope"],
                "r2": f["r2"],
                "loglog_slope": f["loglog_slope"],
            }
        )
    return out


def _pose(k: int, n: int) -> np.ndarray:
    """The tank sonar's poses of :mod:`bench.mapper_speed` (pitch sweep, then a wrist move)."""
    from .mapper_speed import trajectory

    return trajectory(n)[k]


def image_size_sweep(
    backends: list[str],
    voxel_size_m: float = 0.03,
    pings: int = 20,
    method: str = "gather",
    progress: bool = True,
) -> list[dict[str, Any]]:
    """Median ms per image against image size (bins x beams) at one voxel size, synthetic speckle."""
    from .mapper_speed import tank_grid, trajectory

    grid = tank_grid(voxel_size_m)
    poses = trajectory(pings)
    out = []
    jobs = [(b, s) for b in backends for s in IMAGE_SIZES]
    for b, (nb, nbeam) in tqdm(jobs, desc="image sizes", unit="row", disable=not progress):
        spec = gpumap.SonarSpec.uniform(
            hfov_deg=130, vfov_deg=20, n_beams=nbeam, n_bins=nb, range_min_m=0.1, range_max_m=2.0
        )
        rng = np.random.default_rng(0)
        imgs = [
            (rng.random(spec.image_shape, dtype=np.float32) ** 6 * 255).astype(np.uint8) for _ in range(8)
        ]
        n = pings if b != "numpy" else min(pings, 6)
        try:
            m = gpumap.MinMaxMapper(spec, grid, backend=b, method=method)
            warm_up(m, imgs, poses, 3)
            lat = synced_ms(m, imgs, poses, n)
            out.append(
                {
                    "backend": b,
                    "device": m.device,
                    "on_gpu": b in ("warp-cuda", "opencl-gpu"),
                    "method": method,
                    "voxel_size_m": voxel_size_m,
                    "n_bins": nb,
                    "n_beams": nbeam,
                    "pixels": nb * nbeam,
                    "pings": n,
                    "ms_median": float(np.median(lat)),
                    "ms_p95": float(np.percentile(lat, 95)),
                }
            )
        except Exception as e:
            out.append({"backend": b, "n_bins": nb, "n_beams": nbeam, "error": repr(e)})
    return out


def ekf_cost(
    counts: tuple[int, ...] = (4, 8, 16, 32, 64, 128, 200), reps: int = 50, blas_threads: int | None = None
) -> list[dict[str, Any]]:
    """Median predict / update cost of :class:`gpumap.ekf.SonarEKF` against features in the state.

    ``blas_threads`` runs the timing in a subprocess with ``OPENBLAS_NUM_THREADS`` (and the
    OpenMP / MKL equivalents) set, since BLAS threads cannot be changed once NumPy has loaded.
    """
    if blas_threads is not None:
        import json
        import os
        import subprocess
        import sys
        from pathlib import Path

        env = dict(os.environ)
        for k in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
            env[k] = str(blas_threads)
        code = (
            f"import json, sys; from {__package__}.scaling import ekf_cost; "
            f"print(json.dumps(ekf_cost({tuple(counts)!r}, {reps})))"
        )
        root = Path(__file__).resolve().parents[1]
        p = subprocess.run(
            [sys.executable, "-c", code], cwd=root, env=env, capture_output=True, text=True, check=True
        )
        rows = json.loads(p.stdout.strip().splitlines()[-1])
        for r in rows:
            r["blas_threads"] = blas_threads
        return rows
    from .ekf_bench import _time_updates

    rows = [_time_updates(n, reps) for n in counts]
    f = linear_fit(np.array([r["state_dim"] for r in rows]), np.array([r["update_us_median"] for r in rows]))
    for r in rows:
        r["loglog_slope_vs_state_dim"] = f["loglog_slope"]
        r["blas_threads"] = "default"
    return rows
