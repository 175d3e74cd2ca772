"""Peak memory of ``gpumap replay`` against the grid's voxel count, per backend and rule.

    python -m bench.memory [--recording PATH] [--out bench/results/memory_cpu_2c.json]
"""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
import tempfile

import numpy as np

from .common import bench_parser

#: Half-extents (m) of the boxes measured, centred on the OASIS tank, at 5 cm voxels.
HALF_EXTENTS = ((6.0, 6.0, 3.0), (8.0, 8.0, 4.0), (10.0, 10.0, 5.0))
BACKENDS = ("numpy", "warp-cpu", "opencl-cpu")
RULES = ("plain", "visible", "evidence")


def peak_rss(argv: list[str]) -> tuple[int, int]:
    """(exit status, peak resident set in bytes) of ``gpumap`` run with ``argv`` in a child process."""
    p = subprocess.Popen([sys.executable, "-m", "gpumap.commands", *argv], stdout=subprocess.DEVNULL,
                         stderr=subprocess.PIPE)
    _, status, usage = os.wait4(p.pid, 0)
    p.returncode = os.waitstatus_to_exitcode(status)
    if p.returncode and p.stderr:
        print(p.stderr.read().decode(errors="replace")[-2000:], file=sys.stderr)
    return p.returncode, int(usage.ru_maxrss) * 1024  # Linux: kilobytes


def measure(recording: str, frames: int, pictures: bool) -> list[dict]:
    points = []
    for backend in BACKENDS:
        for rule in RULES:
            for h in HALF_EXTENTS:
                box = ",".join(f"{v:g}" for v in (-h[0], -h[1], -h[2], *h))
                n = int(np.prod([round(2 * x / 0.05) for x in h]))
                with tempfile.TemporaryDirectory() as out:
                    rc, rss = peak_rss(["replay", recording, f"--grid={box}", "--voxel-size", "0.05",
                                        "--backend", backend, "--rule", rule, "--max-frames", str(frames),
                                        "--no-progress", "--out", out,
                                        *([] if pictures else ["--no-pictures"])])
                points.append({"backend": backend, "rule": rule, "voxels": n, "pictures": pictures, "rc": rc,
                               "peak_rss_bytes": rss})
                print(f"{backend:<10} {rule:<7} {n:>11,} voxels pictures={pictures}: "
                      f"{rss / 2**20:8.1f} MiB (rc {rc})", flush=True)
    return points


def fit(points: list[dict]) -> dict:
    """Per backend, rule and pictures: ``bytes_per_voxel``, the slope between the two largest boxes (the
    *marginal* cost: at small boxes another phase of the run, the pictures say, sets the peak); and the
    least-squares line through all points (``lsq_bytes_per_voxel``, ``fixed_mib``), for reference."""
    out: dict = {}
    for key in sorted({(p["backend"], p["rule"], p["pictures"]) for p in points}):
        pts = [p for p in points if (p["backend"], p["rule"], p["pictures"]) == key and p["rc"] == 0]
        if len(pts) < 2:
            continue
        x = np.array([p["voxels"] for p in pts], float)
        y = np.array([p["peak_rss_bytes"] for p in pts], float)
        slope, icpt = np.polyfit(x, y, 1)
        o = np.argsort(x)[-2:]
        out[f"{key[0]}/{key[1]}" + ("" if key[2] else "/no-pictures")] = {
            "bytes_per_voxel": round(float((y[o[1]] - y[o[0]]) / (x[o[1]] - x[o[0]])), 2),
            "lsq_bytes_per_voxel": round(float(slope), 2), "fixed_mib": round(icpt / 2**20, 1),
            "worst_residual_mib": round(float(np.max(np.abs(y - (slope * x + icpt)))) / 2**20, 1)}
    return out


def main(argv: list[str] | None = None) -> int:
    ap = bench_parser("memory", __doc__, out="bench/results/memory_cpu_2c.json")
    ap.add_argument("--recording", default="../shared/data/oasis_tank", help="the recording replayed")
    ap.add_argument("--frames", type=int, default=8, help="frames replayed per point (default 8)")
    ap.add_argument("--no-pictures", action="store_true", help="also measure with --no-pictures")
    ap.add_argument("--refit", action="store_true", help="only recompute the fits of the --out file's points")
    a = ap.parse_args(argv)
    if a.refit:
        res = json.loads(a.out.read_text())
        res["fit"] = fit(res["points"])
    else:
        points = measure(a.recording, a.frames, True)
        points += measure(a.recording, a.frames, False) if a.no_pictures else []
        res = {"what": "peak RSS of gpumap replay (first frames of the recording, 5 cm voxels) against the "
                       "grid's voxels; bytes_per_voxel is the least-squares slope", "recording": a.recording,
               "frames": a.frames, "machine": platform.processor() or platform.machine(),
               "cpus": os.cpu_count(), "fit": fit(points), "points": points}
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(res, indent=1) + "\n")
    for k, v in res["fit"].items():
        print(f"{k:<34} {v['bytes_per_voxel']:6.1f} B/voxel at the margin ({v['lsq_bytes_per_voxel']:.1f} "
              f"through every point, + {v['fixed_mib']:.1f} MiB)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
