"""``python -m bench.peer_ratio``: gpumap against the public OASIS code, measured fairly.

Both sides map the same real tank frames (``shared/data/oasis_tank``, frames 1..N after one
warm-up frame) at the OASIS voxel size (5.03 cm), one after the other, ``--repeats`` times in
turn (OASIS, gpumap, OASIS, gpumap, ...), so that a change of load hits both. Per frame:
the public code's ``SonarVoxelGrid.update_voxel_grid`` on its own input (the Cartesian fan
PNG, grey); gpumap's ``integrate`` + ``synchronize`` on the polar uint8 image (the fan ->
polar conversion, timed once by ``bench.speed``'s loader, is reported beside it).

Fairness: the public code is multithreaded NumPy/Open3D and slows down far more than gpumap
when other processes hold cores. So the run checks the machine before, during and after:

- before: the 1-minute load average must be at most ``--max-load`` (default 0.3) and the
  cores other processes keep busy (sampled over 2 s from /proc/stat) at most
  ``--max-others`` (default 0.2); otherwise the run is refused (exit status 3) unless
  ``--allow-loaded``, which runs it and marks the results ``"valid": false``;
- during: each timed pass records the cores other processes kept busy (``others_cores``); the
  run is valid when, pooled over all passes (other processes' CPU seconds over the passes'
  wall seconds), they stayed under ``--max-others``. Pooled, not per pass: a gpumap pass lasts
  ~25 ms, and /proc/stat counts in 10 ms ticks, so one pass alone reads 0 or ~0.4-0.8 cores of
  "others" from a single tick of a shell;
- after: other processes' cores again (2 s sample); the load average is recorded but not
  required, since the run's own minute of work raises it.

The results file (``bench/results/peer_ratio_<tag>.json``) holds every repeat's ms per frame
for both sides, the ratio per repeat, their median and spread (min-max), the load figures,
and ``valid`` (idle before, quiet during and after). Only a valid run
is a headline: BENCHMARKS.md and the README's summary quote it, with its spread.

    python -m bench.peer_ratio --oasis-src /path/to/oasis_iros          # on an idle machine
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import numpy as np

import gpumap

from .common import (
    CpuShare,
    bench_parser,
    load_average,
    machine_tag,
    pooled_others,
    run_header,
    spread,
    synced_ms,
    tagged_path,
    write_json,
)
from .common import idle_check as _idle_check
from .speed import CACHE, OASIS_RES_M, Frames, _import_oasis, load_frames, oasis_frame_ms, oasis_grid

SCHEMA = "gpumap-peer-ratio/1"


__all__ = ["idle_check", "main", "pooled_others", "summarize", "time_gpumap", "time_oasis_pass"]


def idle_check(max_load: float, max_others: float, sample_s: float = 2.0) -> dict[str, Any]:
    """:func:`bench.common.idle_check` with this module's :func:`load_average` (what a test replaces)."""
    return _idle_check(max_load, max_others, sample_s, load=load_average())


def summarize(oasis_ms: list[float], gpumap_ms: list[float]) -> dict[str, Any]:
    """Per-repeat ratio (OASIS ms / gpumap ms per frame), its median and its spread."""
    r = np.asarray(oasis_ms, float) / np.asarray(gpumap_ms, float)
    return {
        "oasis_ms_per_frame": spread(oasis_ms),
        "gpumap_ms_per_frame": spread(gpumap_ms),
        "ratio_per_repeat": r.tolist(),
        **{f"ratio_{k}": x for k, x in spread(r).items()},
    }


def time_gpumap(fr: Frames, backend: str, rule: str, voxel_m: float, n: int) -> float:
    """Mean ms per frame of ``integrate`` + ``synchronize`` over frames 1..n (frame 0 warms up)."""
    grid = oasis_grid(voxel_m)
    warm = gpumap.MinMaxMapper(fr.spec, grid, backend=backend, rule=rule)
    warm.integrate(fr.images[0], fr.poses[0])
    warm.synchronize()
    m = gpumap.MinMaxMapper(fr.spec, grid, backend=backend, rule=rule)
    return float(np.mean(synced_ms(m, fr.images, fr.poses, n, start=1)))


def time_oasis_pass(cls, fr: Frames, downsample: int, n: int) -> float:
    """Mean ms per frame of the public ``update_voxel_grid`` over frames 1..n (frame 0 warms up)."""
    return float(np.mean(oasis_frame_ms(cls, fr, downsample, n)[0]))


def _parser() -> argparse.ArgumentParser:
    ap = bench_parser("peer_ratio", __doc__)
    ap.add_argument("--oasis-src", type=Path, required=True,
                    help="checkout of the public OASIS code (chaos-whoi/oasis_iros; opencv and open3d "
                         "importable)")
    ap.add_argument("--frames", type=int, default=20, help="frames timed per pass (default 20)")
    ap.add_argument("--repeats", type=int, default=5, help="passes of each side, taken in turn (default 5)")
    ap.add_argument("--backend", default="opencl", help="gpumap backend (default opencl: PoCL on a CPU)")
    ap.add_argument("--rule", default="visible", help="gpumap rule (default visible, the default rule)")
    ap.add_argument("--downsample", type=int, default=10,
                    help="OASIS image downsample factor: voxel = factor x 2 m / 398 (default 10: 5.03 cm)")
    ap.add_argument("--max-load", type=float, default=0.3, help="largest 1-minute load average to start")
    ap.add_argument("--max-others", type=float, default=0.2,
                    help="largest number of cores other processes may keep busy, before and during")
    ap.add_argument("--allow-loaded", action="store_true",
                    help="run on a loaded machine anyway; the results are marked not valid")
    ap.add_argument("--frames-from", type=Path, default=None, help="cached frames (.npz) of bench.speed")
    ap.add_argument("--out", type=Path, default=Path("bench/results"), help="results folder")
    ap.add_argument("--tag", default=None, help="result file stem (default: from the machine)")
    return ap


def main(argv: list[str] | None = None) -> int:
    a = _parser().parse_args(argv)
    before = idle_check(a.max_load, a.max_others)
    print(f"before: load {before['load_avg']}, other processes {before['others_cores']} cores", flush=True)
    if not before["idle"] and not a.allow_loaded:
        print(f"bench.peer_ratio: refused: the machine is not idle (1-minute load {before['load_avg']}, "
              f"other processes busy on {before['others_cores']} cores; limits {a.max_load} and "
              f"{a.max_others}); wait, or pass --allow-loaded to record a run marked not valid",
              file=sys.stderr)
        return 3
    fr = load_frames(a.frames_from or CACHE)
    if len(fr.pngs) < a.frames + 1 or len(fr.images) < a.frames + 1:
        raise SystemExit(f"bench.peer_ratio: need {a.frames + 1} frames with their fan PNGs, "
                         f"got {len(fr.pngs)}")
    cls = _import_oasis(a.oasis_src)
    voxel_m = a.downsample * OASIS_RES_M
    passes = []
    for r in range(a.repeats):
        for side in ("oasis", "gpumap"):
            with CpuShare() as share:
                if side == "oasis":
                    ms = time_oasis_pass(cls, fr, a.downsample, a.frames)
                else:
                    ms = time_gpumap(fr, a.backend, a.rule, voxel_m, a.frames)
            passes.append({"repeat": r, "side": side, "ms_per_frame": ms, "others_cores": share.others_cores,
                           "own_cores": share.own_cores, "wall_s": share.wall_s})
            print(f"repeat {r} {side}: {ms:.2f} ms/frame (others {share.others_cores})", flush=True)
    after = idle_check(a.max_load, a.max_others)
    others_during = pooled_others(passes)
    quiet_passes = others_during is None or others_during <= a.max_others
    quiet_after = after["others_cores"] is None or after["others_cores"] <= a.max_others
    res: dict[str, Any] = {
        **run_header(SCHEMA, argv),
        "setup": {"frames": a.frames, "repeats": a.repeats, "backend": a.backend, "rule": a.rule,
                  "voxel_m": voxel_m, "oasis_input": "Cartesian fan PNG (grey), as the public code reads it",
                  "gpumap_input": "polar uint8 (fan -> polar conversion timed apart: fan_to_polar_ms)",
                  "fan_to_polar_ms": fr.polar_ms, "max_load": a.max_load, "max_others": a.max_others},
        "before": before, "after": after, "passes": passes, "others_cores_during": others_during,
        "valid": bool(before["idle"] and quiet_passes and quiet_after),
        **summarize([p["ms_per_frame"] for p in passes if p["side"] == "oasis"],
                    [p["ms_per_frame"] for p in passes if p["side"] == "gpumap"]),
    }
    tag = a.tag or machine_tag(res["machine"])
    path = write_json(tagged_path(a.out, "peer_ratio_", tag), res, digits=4)
    print(f"gpumap {res['ratio_median']:.1f}x the public OASIS code (median of {a.repeats}; "
          f"{res['ratio_min']:.1f}-{res['ratio_max']:.1f}x); valid: {res['valid']}; wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
