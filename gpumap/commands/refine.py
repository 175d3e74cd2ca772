"""``gpumap refine``: map a recording (or take its saved map), then refine the map so that its
rendered pings match the measured ones (issue 19; the method is in :mod:`gpumap.layers.refine`).

    gpumap refine /path/to/oasis_tank --voxel-size 0.03 --out refine_out
    gpumap refine /path/to/oasis_tank --map replay_out/map.npz --out refine_out

With ``--map`` the saved map's grid, rule and threshold are used (``gpumap replay``'s
``map.npz``; pass the ``--stride`` / ``--max-frames`` it was built with), and its pings are
checked against the recording's (fingerprints); without, the recording is mapped first (rule
``--rule``, evidence by default). The device is said before any work (``--device auto`` says
which it took and why). Writes ``refined.npz`` (a refined map file,
:meth:`gpumap.layers.refine.RefineResult.save`: ``occupancy``, ``confidence``, ``field``,
``reflectivity`` and the map's ``values``, NaN unknown, the ``carved`` and ``raised`` masks, the
sonar, grid, rule and threshold; ``gpumap view`` and ``gpumap export`` read it), ``refined.ply``
(the refined occupied voxels' centres, confidence as intensity) and ``refine.json`` (timings,
device, fitted gain and floor, constraint counts, options) into ``--out``, and says so.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from gpumap.atomic import output_set
from gpumap.commands.common import (
    BACKEND_HELP,
    ArgumentParser,
    backend_name,
    error_line,
    existing_file,
    output_dir,
    positive_float,
    positive_int,
    unit_interval,
    user_errors,
)
from gpumap.core.params import MapperParams

OUTPUTS = ("refined.npz", "refined.ply", "refine.json")


def _device(text: str) -> str:
    """``auto``, ``cpu``, ``cuda`` or ``cuda:N`` (checked before any work)."""
    import argparse

    if text in ("auto", "cpu", "cuda") or (text.startswith("cuda:") and text[5:].isdigit()):
        return text
    raise argparse.ArgumentTypeError(f"Expected auto, cpu, cuda or cuda:N, but got {text!r}")


def _parser() -> ArgumentParser:
    from gpumap.layers.refine import REFINE_RULES, RefineOptions
    from gpumap.pipeline.replay import DEFAULT_THRESHOLD

    d = RefineOptions()
    ap = ArgumentParser(prog="gpumap refine",
                        description="map a recording (or take its saved map, --map), then refine "
                        "the map so that pings rendered from it match the measured ones")
    ap.add_argument("path", help="recording with poses: Oculus .raw/.oculus, ARIS .aris, fan folder, ROS bag")
    ap.add_argument("--map", type=existing_file, default=None, metavar="MAP.npz",
                    help="start from this saved map of the recording (gpumap replay's map.npz): its grid, "
                    "rule and threshold; pass the --stride/--max-frames it was built with")
    ap.add_argument("--voxel-size", type=positive_float, default=None,
                    help="metres (default 0.05; not with --map)")
    ap.add_argument(
        "--threshold",
        type=unit_interval,
        default=None,
        help=f"the mapper's bright threshold, in (0, 1] (default {DEFAULT_THRESHOLD}; not with --map)",
    )
    ap.add_argument("--rule", choices=REFINE_RULES, default=None,
                    help="the mapper's rule (default evidence, the mapper's default; not with --map)")
    ap.add_argument("--backend", type=backend_name, default="auto",
                    help=f"the map's backend, {BACKEND_HELP}")
    ap.add_argument(
        "--device",
        default="auto",
        type=_device,
        help="where the refinement runs: auto (CUDA if Warp finds it, else CPU; says which and why), "
        "cpu, cuda, cuda:N (a named device that cannot run is an error)",
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


def main(argv: list[str] | None = None) -> int:
    p = _parser()
    a = p.parse_args(argv)
    if a.map is not None:
        for flag, v in (("--voxel-size", a.voxel_size), ("--threshold", a.threshold), ("--rule", a.rule)):
            if v is not None:
                p.error(f"argument {flag}: Expected no {flag} with --map (the saved map's grid, rule and "
                        f"threshold are used), but got {v}")
    import gpumap
    from gpumap.layers.refine import (
        RefineOptions,
        map_frames,
        pick_device,
        recording_frames,
        refine,
        refine_saved,
    )
    from gpumap.pipeline.replay import DEFAULT_THRESHOLD
    from gpumap.spec import auto_grid

    progress = not a.no_progress
    try:
        # the device is said (and a missing one refused) before the frames are read and mapped
        device, why = pick_device(a.device)
        opts = RefineOptions(iterations=a.iterations, pings_per_step=a.pings_per_step)
        if a.map is not None:
            mapper = gpumap.load_map(a.map, backend=a.backend)
            res = refine_saved(mapper, a.path, stride=a.stride, max_frames=a.max_frames, options=opts,
                               device=device, progress=progress)
        else:
            spec, images, poses = recording_frames(a.path, a.stride, a.max_frames, progress)
            grid = auto_grid(spec, list(poses), a.voxel_size or 0.05,
                             remedy="use a larger --voxel-size, or fewer frames (--stride, --max-frames)")
            mapper = gpumap.MinMaxMapper(
                spec,
                grid,
                a.backend,
                MapperParams(rule=a.rule or "evidence", threshold=a.threshold or DEFAULT_THRESHOLD),
            )
            map_frames(mapper, images, poses, progress)
            res = refine(mapper, images, poses, options=opts, device=device, progress=progress)
    except user_errors() as e:
        print(error_line("gpumap refine", e), file=sys.stderr)
        return 2
    res.stats["device_reason"] = why
    n_frames = int(res.stats["frames"])
    grid = res.grid
    summary = {
        "frames": n_frames,
        "map": None if a.map is None else str(a.map),
        "grid_shape": list(grid.shape),
        "grid": grid.to_dict(),
        "mapper_backend": mapper.backend,
        "gain": res.gain,
        "floor": res.floor,
        "map_occupied": int(res.safe().sum()),
        "refined_occupied": int(res.occupied().sum()),
        **res.stats,
        "loss_first_last": [res.history[0], res.history[-1]],
    }
    with output_set(a.out, OUTPUTS) as out:
        res.save(Path(out) / "refined.npz")
        from gpumap.io.ply import write_ply

        occ = res.occupied()  # the refined surface for any point-cloud viewer
        write_ply(Path(out) / "refined.ply", grid.centers(np.argwhere(occ)), res.confidence[occ])
        (Path(out) / "refine.json").write_text(json.dumps(summary, indent=1, default=float))
    print(
        f"gpumap refine: {n_frames} pings, {summary['map_occupied']} voxels occupied in the {res.rule} "
        f"map, {summary['refined_occupied']} refined, {res.stats['seconds']:.1f} s on {res.stats['device']}"
    )
    print(f"gpumap refine: wrote {', '.join(OUTPUTS)} to {a.out}/")
    return 0
