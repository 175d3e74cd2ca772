"""``gpumap export MAP.npz OUT.bt|OUT.ply``: a saved map as OctoMap ``.bt`` or as a ``.ply`` cloud.

The command lives here, beside :mod:`gpumap.cli`, so that the readers and writers of
:mod:`gpumap.io` never import the command line (no ``cli`` <-> ``io.octomap`` cycle).
"""

from __future__ import annotations

import json

import numpy as np

from gpumap.cli import ArgumentParser, existing_file, output_file, unit_interval

__all__ = ["main"]


def _parser() -> ArgumentParser:
    p = ArgumentParser(prog="gpumap export",
                       description="write a saved map (map.npz) as OctoMap .bt (RViz, octovis) or .ply")
    p.add_argument("map", type=existing_file, help="a map file written by gpumap (map.npz, dense or sparse)")
    p.add_argument("out", type=output_file,
                   help="output: NAME.bt (OctoMap binary tree: occupied, free, unknown) or NAME.ply "
                        "(occupied voxel centres with their value as 'intensity')")
    p.add_argument("--threshold", type=unit_interval, default=None,
                   help="occupied if value >= this (default: the map's own threshold)")
    return p


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``gpumap export MAP.npz OUT.bt|OUT.ply``; returns the exit status."""
    from gpumap.io.octomap import write_octomap_bt
    from gpumap.io.ply import write_ply
    from gpumap.merge import load_map

    p = _parser()
    a = p.parse_args(argv)
    suffix = a.out.suffix.lower()
    if suffix not in (".bt", ".ply"):
        p.error(f"argument out: Expected a name ending .bt or .ply, but got {str(a.out)!r}")
    mapper = load_map(a.map, backend="numpy")
    thr = float(mapper.threshold if a.threshold is None else a.threshold)
    a.out.parent.mkdir(parents=True, exist_ok=True)
    if suffix == ".bt":
        info = write_octomap_bt(a.out, mapper, threshold=thr)
    else:
        v = mapper.values()
        occ = np.isfinite(v) & (v >= thr)
        write_ply(a.out, mapper.grid.centers(np.argwhere(occ)), v[occ])
        info = {"path": str(a.out), "occupied_cells": int(occ.sum())}
    print(json.dumps({**info, "threshold": thr}))
    return 0
