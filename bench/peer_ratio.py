"""``python -m bench.peer_ratio``: gpumap against the public OASIS code, measured fairly.

    python -m bench.peer_ratio --oasis-src /path/to/oasis_iros          # on an idle machine
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import numpy as np

import gpumap
from gpumap.core.params import MapperParams

from . import common
from .common import CpuShare, bench_parser, idle_check, pooled_others, refuse, spread, synced_ms
from .speed import CACHE, OASIS_RES_M, Frames, _import_oasis, load_frames, oasis_frame_ms, oasis_grid

SCHEMA = "gpumap-peer-ratio/1"


def summarize(oasis_ms: list[float], gpumap_ms: list[float]) -> dict[str, Any]:
    """Per-repeat ratio (OASIS ms / gpumap ms per frame), its median and its spread."""
    r = np.asarray(oasis_ms, float) / np.asarray(gpumap_ms, float)
    return {"oasis_ms_per_frame": spread(oasis_ms), "gpumap_ms_per_frame": spread(gpumap_ms),
            "ratio_per_repeat": r.tolist(), **{f"ratio_{k}": x for k, x in spread(r).items()}}


def time_gpumap(fr: Frames, backend: str, rule: str, voxel_m: float, n: int) -> float:
    """Mean ms per frame of ``integrate`` + ``synchronize`` over frames 1..n (frame 0 warms up)."""
    grid = oasis_grid(voxel_m)
    warm = gpumap.MinMaxMapper(fr.spec, grid, backend, MapperParams(rule=rule))
    warm.integrate(fr.images[0], fr.poses[0])
    warm.synchronize()
    m = gpumap.MinMaxMapper(fr.spec, grid, backend, MapperParams(rule=rule))
    return float(np.mean(synced_ms(m, fr.images, fr.poses, n, start=1)))


def _parser() -> argparse.ArgumentParser:
    ap = bench_parser("peer_ratio", __doc__, out="bench/results", backend="opencl", tag="")
    ap.add_argument("--oasis-src", type=Path, required=True,
                    help="checkout of the public OASIS code (chaos-whoi/oasis_iros; opencv and open3d "
                    "importable)")
    ap.add_argument("--frames", type=int, default=20, help="frames timed per pass (default 20)")
    ap.add_argument("--repeats", type=int, default=5, help="passes of each side, taken in turn (default 5)")
    ap.add_argument("--rule", default="visible", help="gpumap rule (default visible, the default rule)")
    ap.add_argument("--downsample", type=int, default=10,
                    help="OASIS image downsample factor: voxel = factor x 2 m / 398 (default 10: 5.03 cm)")
    ap.add_argument("--max-load", type=float, default=0.3, help="largest 1-minute load average to start")
    ap.add_argument("--max-others", type=float, default=0.2,
                    help="largest number of cores other processes may keep busy, before and during")
    ap.add_argument("--allow-loaded", action="store_true",
                    help="run on a loaded machine anyway; the results are marked not valid")
    ap.add_argument("--frames-from", type=Path, default=None, help="cached frames (.npz) of bench.speed")
    return ap


def main(argv: list[str] | None = None) -> int:
    a = _parser().parse_args(argv)
    before = idle_check(a.max_load, a.max_others)
    print(f"before: load {before['load_avg']}, other processes {before['others_cores']} cores", flush=True)
    if not before["idle"] and not a.allow_loaded:
        return refuse("bench.peer_ratio", before, (a.max_load, a.max_others), "--allow-loaded")
    fr = load_frames(a.frames_from or CACHE)
    if len(fr.pngs) < a.frames + 1 or len(fr.images) < a.frames + 1:
        raise SystemExit(f"bench.peer_ratio: need {a.frames + 1} frames with their fan PNGs, "
                         f"got {len(fr.pngs)}")
    cls, voxel_m, passes = _import_oasis(a.oasis_src), a.downsample * OASIS_RES_M, []
    for r in range(a.repeats):
        for side in ("oasis", "gpumap"):
            with CpuShare() as share:
                ms = (float(np.mean(oasis_frame_ms(cls, fr, a.downsample, a.frames)[0])) if side == "oasis"
                      else time_gpumap(fr, a.backend, a.rule, voxel_m, a.frames))
            passes.append({"repeat": r, "side": side, "ms_per_frame": ms, "others_cores": share.others_cores,
                           "own_cores": share.own_cores, "wall_s": share.wall_s})
            print(f"repeat {r} {side}: {ms:.2f} ms/frame (others {share.others_cores})", flush=True)
    after, during = idle_check(a.max_load, a.max_others), pooled_others(passes)
    quiet = (during is None or during <= a.max_others) and (after["others_cores"] is None
                                                           or after["others_cores"] <= a.max_others)
    res: dict[str, Any] = {
        **common.run_header(SCHEMA, argv),
        "setup": {"frames": a.frames, "repeats": a.repeats, "backend": a.backend, "rule": a.rule,
                  "voxel_m": voxel_m, "oasis_input": "Cartesian fan PNG (grey), as the public code reads it",
                  "gpumap_input": "polar uint8 (fan -> polar conversion timed apart: fan_to_polar_ms)",
                  "fan_to_polar_ms": fr.polar_ms, "max_load": a.max_load, "max_others": a.max_others},
        "before": before, "after": after, "passes": passes, "others_cores_during": during,
        "valid": bool(before["idle"] and quiet),
        **summarize(*([p["ms_per_frame"] for p in passes if p["side"] == s] for s in ("oasis", "gpumap")))}
    path = common.write_json(common.tagged_path(a.out, "peer_ratio_",
                                                a.tag or common.machine_tag(res["machine"])),
                             res, digits=4)
    print(f"gpumap {res['ratio_median']:.1f}x the public OASIS code (median of {a.repeats}; "
          f"{res['ratio_min']:.1f}-{res['ratio_max']:.1f}x); valid: {res['valid']}; wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
