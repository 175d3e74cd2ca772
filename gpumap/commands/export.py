"""``gpumap export MAP OUT.bt|OUT.ply``: a saved map as OctoMap ``.bt`` or as a ``.ply`` cloud.

``MAP`` is a map file (``map.npz``, :meth:`gpumap.MinMaxMapper.save`) or a refined map file
(``refined.npz``, what ``gpumap refine`` writes, :meth:`gpumap.layers.refine.RefineResult.save`; or
``surface.npz``, the surface layer ``gpumap demo`` and ``gpumap replay`` write beside ``map.npz``,
:mod:`gpumap.layers.surface`; ``MAP`` = that ``map.npz`` with ``--layer`` reads it). A refined file holds
two layers, exported apart:

- ``surface``: the refined occupancy, occupied from :data:`gpumap.layers.refine.OCCUPIED_LEVEL` (the thin
  surfaces the pings need; the value is the occupancy);
- ``safe``: the map's occupied voxels (value ``>=`` the map's threshold): the obstacle layer to
  keep a vehicle out of (a superset of the surface).

``--layer surface|safe`` writes that layer to ``OUT``; without it both are written, to
``NAME.surface.EXT`` and ``NAME.safe.EXT`` beside ``OUT``.

The command lives here, above the library, so that the readers and writers of
:mod:`gpumap.io` never import the command line (no ``commands`` <-> ``io.octomap`` cycle).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from gpumap.commands.common import ArgumentParser, existing_file, output_file, unit_interval

__all__ = ["LAYERS", "main"]

#: The layers of a refined map file.
LAYERS = ("surface", "safe")


def _parser() -> ArgumentParser:
    p = ArgumentParser(prog="gpumap export",
                       description="write a saved map (map.npz) or a refined map (refined.npz) as OctoMap "
                       ".bt (RViz, octovis) or .ply")
    p.add_argument("map", type=existing_file,
                   help="a map file written by gpumap (map.npz, dense or sparse) or by gpumap refine "
                   "(refined.npz)")
    p.add_argument("out", type=output_file,
                   help="output: NAME.bt (OctoMap binary tree: occupied, free, unknown) or NAME.ply "
                        "(occupied voxel centres with their value as 'intensity')")
    p.add_argument("--threshold", type=unit_interval, default=None,
                   help="occupied if value >= this (default: the map's own threshold; map.npz only)")
    p.add_argument("--layer", choices=LAYERS, default=None,
                   help="refined.npz / surface.npz (or a map.npz with surface.npz beside it) only: surface "
                        "(refined occupancy or surface layer >= 0.5) or safe (the map's occupied voxels) "
                        "into OUT (default: both, into NAME.surface.EXT and NAME.safe.EXT)")
    return p


def _write(out: Path, values: np.ndarray, grid, thr: float) -> dict:
    """``values`` (nx, ny, nz) float, NaN unknown, occupied from ``thr``, as ``out`` (.bt or .ply)."""
    from gpumap.io.octomap import write_octomap_bt
    from gpumap.io.ply import write_ply

    if out.suffix.lower() == ".bt":
        info = write_octomap_bt(out, values, grid, threshold=thr)
    else:
        occ = np.isfinite(values) & (values >= np.float32(thr))
        write_ply(out, grid.centers(np.argwhere(occ)), values[occ])
        info = {"path": str(out), "occupied_cells": int(occ.sum())}
    return {**info, "threshold": thr}


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``gpumap export MAP OUT.bt|OUT.ply``; returns the exit status."""
    from gpumap.core.merge import load_map
    from gpumap.layers.refine import OCCUPIED_LEVEL, is_refined_file, load_refined
    from gpumap.layers.refined_map import layers_file

    p = _parser()
    a = p.parse_args(argv)
    suffix = a.out.suffix.lower()
    if suffix not in (".bt", ".ply"):
        p.error(f"argument out: Expected a name ending .bt or .ply, but got {str(a.out)!r}")
    a.out.parent.mkdir(parents=True, exist_ok=True)
    two = a.map if is_refined_file(a.map) else (layers_file(a.map) if a.layer else None)
    if two is not None:
        if a.threshold is not None:
            p.error("argument --threshold: Expected no --threshold with a refined map (its layers keep "
                    f"their own: surface from {OCCUPIED_LEVEL}, safe from the map's), but got {a.threshold}")
        res = load_refined(two)
        layers = {"surface": (res.occupancy, OCCUPIED_LEVEL), "safe": (res.map_values, float(res.threshold))}
        names = [a.layer] if a.layer else list(LAYERS)
        infos = []
        for name in names:
            out = a.out if a.layer else a.out.with_name(f"{a.out.stem}.{name}{a.out.suffix}")
            values, thr = layers[name]
            infos.append({"layer": name, **_write(out, values, res.grid, thr)})
        print(json.dumps(infos[0] if a.layer else infos))
        return 0
    if a.layer is not None:
        p.error(f"argument --layer: Expected a refined map (gpumap refine's refined.npz) or a map with a "
                f"surface.npz beside it (gpumap demo/replay) with --layer, but {str(a.map)!r} is a map of "
                "one layer")
    mapper = load_map(a.map, backend="numpy")
    thr = float(mapper.threshold if a.threshold is None else a.threshold)
    if suffix == ".bt":
        from gpumap.io.octomap import write_octomap_bt

        info = {**write_octomap_bt(a.out, mapper, threshold=thr), "threshold": thr}
    else:
        info = _write(a.out, mapper.values(), mapper.grid, thr)
    print(json.dumps(info))
    return 0
