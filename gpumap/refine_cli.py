"""``gpumap refine``: map a recording with the visible rule, then refine the map so that its
rendered pings match the measured ones (issue 19; the method is in :mod:`gpumap.refine`).

    gpumap refine /path/to/oasis_tank --voxel-size 0.03 --out refine_out

Writes ``refined.npz`` (``occupancy`` and ``confidence`` (nx, ny, nz) float32, NaN unknown,
``reflectivity``, ``visible`` (the visible rule's map), ``carved`` and ``raised`` masks, the grid
as ``min_corner_m`` / ``voxel_size_m``) and ``refine.json`` (timings, fitted gain and floor,
constraint counts, options) into ``--out``.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from gpumap.cli import (
    BACKEND_HELP,
    ArgumentParser,
    backend_name,
    error_line,
    output_dir,
    output_set,
    positive_float,
    positive_int,
    unit_interval,
    user_errors,
)

OUTPUTS = ("refined.npz", "refined.ply", "refine.json")


def _device(text: str) -> str:
    """``auto``, ``cpu``, ``cuda`` or ``cuda:N`` (checked before any work)."""
    import argparse

    if text in ("auto", "cpu", "cuda") or (text.startswith("cuda:") and text[5:].isdigit()):
        return text
    raise argparse.ArgumentTypeError(f"Expected auto, cpu, cuda or cuda:N, but got {text!r}")


def _parser() -> ArgumentParser:
    from gpumap.refine import RefineOptions
    from gpumap.replay import DEFAULT_THRESHOLD

    d = RefineOptions()
    ap = ArgumentParser(prog="gpumap refine",
                        description="map a recording with the visible rule, then refine "
                        "the map so that pings rendered from it match the measured ones")
    ap.add_argument("path", help="recording with poses: Oculus .raw/.oculus, ARIS .aris, fan folder, ROS bag")
    ap.add_argument("--voxel-size", type=positive_float, default=0.05, help="metres (default 0.05)")
    ap.add_argument(
        "--threshold",
        type=unit_interval,
        default=DEFAULT_THRESHOLD,
        help=f"the visible mapper's bright threshold, in (0, 1] (default {DEFAULT_THRESHOLD})",
    )
    ap.add_argument("--backend", type=backend_name, default="auto",
                    help=f"the visible map's backend, {BACKEND_HELP}")
    ap.add_argument(
        "--device",
        default="auto",
        type=_device,
        help="where the refinement runs: auto (CUDA if Warp finds it, else CPU), cpu, cuda, cuda:N",
    )
    ap.add_argument("--stride", type=positive_int, default=1, help="use every N-th frame")
    ap.add_argument("--max-frames", type=positive_int, default=None, help="use at most this many frames")
    ap.add_argument(
        "--iterations",
        type=positive_int,
        default=d.iterations,
        help=f"optimiser steps (default {d.iterations})",
    )
    ap.add_argument(
        "--pings-per-step",
        type=positive_int,
        default=d.pings_per_step,
        help=f"pings rendered per step (default {d.pings_per_step})",
    )
    ap.add_argument(
        "--out",
        type=output_dir,
        default="refine_out",
        help="output folder (default refine_out); its files are replaced as one set",
    )
    ap.add_argument("--no-progress", action="store_true", help="no progress bars")
    return ap


def load_frames(
    path: str, stride: int = 1, max_frames: int | None = None
) -> tuple[object, np.ndarray, np.ndarray]:
    """(spec, images (N, n_bins, n_beams) float32, poses (N, 4, 4)) of a recording's posed frames
    (every ``stride``-th, at most ``max_frames``; frames of another sonar geometry are skipped)."""
    from gpumap.io import open_recording

    rec = open_recording(path)
    spec, images, poses = None, [], []
    for i, fr in enumerate(rec):
        if i % stride or fr.T_W_S is None:
            continue
        spec = spec or fr.spec
        if fr.spec != spec:
            continue
        images.append(np.asarray(fr.image, np.float32))
        poses.append(np.asarray(fr.T_W_S, np.float64))
        if max_frames is not None and len(images) >= max_frames:
            break
    if not images:
        raise ValueError(f"Expected a recording with sonar poses (refine needs one per ping), but {path} "
                         "has no posed frames")
    return spec, np.stack(images), np.stack(poses)


def main(argv: list[str] | None = None) -> int:
    a = _parser().parse_args(argv)
    import gpumap
    from gpumap.refine import RefineOptions, refine
    from gpumap.replay import auto_grid

    try:
        from gpumap.render import _init_warp

        _init_warp(a.device)  # a missing CUDA device is said before the frames are read and mapped
        spec, images, poses = load_frames(a.path, a.stride, a.max_frames)
        grid = auto_grid(spec, list(poses), a.voxel_size,
                         remedy="use a larger --voxel-size, or fewer frames (--stride, --max-frames)")
        mapper = gpumap.MinMaxMapper(spec, grid, backend=a.backend, rule="visible", threshold=a.threshold)
        mapper.integrate_batch(images, poses)
        opts = RefineOptions(iterations=a.iterations, pings_per_step=a.pings_per_step)
        res = refine(mapper, images, poses, options=opts, device=a.device, progress=not a.no_progress)
    except user_errors() as e:
        print(error_line("gpumap refine", e), file=sys.stderr)
        return 2
    summary = {
        "frames": len(images),
        "grid_shape": list(grid.shape),
        "grid": grid.to_dict(),
        "mapper_backend": mapper.backend,
        "threshold": a.threshold,
        "gain": res.gain,
        "floor": res.floor,
        "visible_occupied": int(np.sum(np.nan_to_num(mapper.values(), nan=-1.0) >= a.threshold)),
        "refined_occupied": int(res.occupied().sum()),
        **res.stats,
        "loss_first_last": [res.history[0], res.history[-1]],
    }
    with output_set(a.out, OUTPUTS) as out:
        np.savez_compressed(
            Path(out) / "refined.npz",
            occupancy=res.occupancy,
            confidence=res.confidence,
            reflectivity=res.reflectivity,
            visible=mapper.values(),
            carved=res.carved,
            raised=res.raised,
            min_corner_m=np.asarray(grid.min_corner_m),
            voxel_size_m=np.float64(grid.voxel_size_m),
        )
        from gpumap.io.ply import write_ply

        occ = res.occupied()  # the refined surface for any point-cloud viewer (gpumap view reads maps only)
        write_ply(Path(out) / "refined.ply", grid.centers(np.argwhere(occ)), res.confidence[occ])
        (Path(out) / "refine.json").write_text(json.dumps(summary, indent=1, default=float))
    print(
        f"gpumap refine: {len(images)} pings, {summary['visible_occupied']} voxels occupied in the visible "
        f"map, {summary['refined_occupied']} refined, {res.stats['seconds']:.1f} s on {res.stats['device']}; "
        f"wrote {', '.join(OUTPUTS)} to {a.out}/"
    )
    return 0
