"""``gpumap view PATH``: serve a saved map, a refined map or a recording in the browser view.

A saved map (``map.npz``: its occupied voxels, coloured by value or height, threshold
adjustable), a refined map (``refined.npz`` of ``gpumap refine``: ``--layer surface`` or
``--layer safe``) or a recording (``*.gpumap-rec``: a ping slider and a play button); see
:mod:`gpumap.viewer.session`.
"""

from __future__ import annotations

import argparse
import sys
import zipfile
from pathlib import Path

from gpumap.commands.common import (
    ArgumentParser,
    add_view_args,
    check_view_args,
    existing_file,
    unit_interval,
)
from gpumap.viewer.session import view_map, view_recording

__all__ = ["main"]


def _parser() -> argparse.ArgumentParser:
    p = ArgumentParser(
        prog="gpumap view",
        description="serve a saved map (map.npz) or a recording (--record FILE) in the browser view",
    )
    p.add_argument("path", type=existing_file,
                   help="map.npz (gpumap demo/replay), refined.npz (gpumap refine) or a recording")
    p.add_argument(
        "--threshold",
        type=unit_interval,
        default=None,
        help="occupied if value >= this (default: the map's own threshold; a refined map's surface: 0.5)",
    )
    p.add_argument("--layer", choices=("surface", "safe"), default=None,
                   help="refined.npz / surface.npz (or a map.npz with surface.npz beside it) only: surface "
                   "(the refined occupancy or surface layer, the default) or safe (the map's occupied "
                   "voxels)")
    add_view_args(p, record=False, live=False)
    return p


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``gpumap view PATH``; returns the exit status."""
    p = _parser()
    a = p.parse_args(argv)
    a.view = True
    check_view_args(p, a)
    path = Path(a.path)
    try:
        with zipfile.ZipFile(path) as zf:
            names = set(zf.namelist())
    except zipfile.BadZipFile:
        raise ValueError(f"Expected a map (map.npz) or a gpumap recording, but {path} is not a zip") from None
    if "meta.json" in names and a.layer is not None:
        p.error("argument --layer: Expected a refined map (gpumap refine's refined.npz) with --layer, but "
                f"{str(path)!r} is a recording")
    v = view_recording(path, a) if "meta.json" in names else view_map(path, a)
    print(
        f"gpumap view: serving {path} at {v.url} "
        + ("until Ctrl-C" if a.view_hold is None else f"for {a.view_hold:g} s"),
        file=sys.stderr,
        flush=True,
    )
    try:
        v.wait(a.view_hold)
    except KeyboardInterrupt:
        pass
    return 0
