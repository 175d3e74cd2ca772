"""``gpumap export MAP OUT.bt|OUT.ply|OUT.npz``: a saved map as OctoMap ``.bt`` or as a ``.ply`` cloud; its
distance field as ``.ply`` or ``.npz``.

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

``--layer distance`` writes the distance field of the safe map (of a map file, or of a refined file's
``safe`` layer; :class:`gpumap.layers.distance.DistanceField`): for every voxel centre the Euclidean
distance, metres, to the nearest obstacle voxel centre (0 at obstacles), obstacles being the occupied
voxels (value ``>=`` the threshold) and, unless ``--unknown-free``, the unknown ones; ``--max-distance-m``
caps it. ``OUT.npz`` holds the whole field: ``distance_m`` ``(nx, ny, nz)`` float32 over the map's grid
(voxel ``(i, j, k)`` centred at ``min_corner_m + (ijk + 0.5) * voxel_size_m``), ``min_corner_m``,
``max_corner_m``, ``voxel_size_m``, ``threshold``, ``unknown_is_obstacle``, ``max_distance_m`` (NaN:
none); ``OUT.ply`` the free voxels within ``--radius-m`` of an obstacle (nvblox's ESDF cloud): their
centres ``x y z`` and ``distance``, float32.

The command lives here, above the library, so that the readers and writers of
:mod:`gpumap.io` never import the command line (no ``commands`` <-> ``io.octomap`` cycle).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from gpumap.commands.common import (
    ArgumentParser,
    existing_file,
    nonnegative_float,
    output_file,
    positive_float,
    unit_interval,
)

__all__ = ["LAYERS", "main"]

#: The layers of a refined map file.
LAYERS = ("surface", "safe")
#: What ``--layer`` takes: a refined map file's layers, and the distance field of any map's safe layer.
LAYER_CHOICES = (*LAYERS, "distance")


def _parser() -> ArgumentParser:
    p = ArgumentParser(prog="gpumap export",
                       description="write a saved map (map.npz) or a refined map (refined.npz) as OctoMap "
                       ".bt (RViz, octovis) or .ply, or its distance field (--layer distance) as .ply or "
                       ".npz")
    p.add_argument("map", type=existing_file,
                   help="a map file written by gpumap (map.npz, dense or sparse) or by gpumap refine "
                   "(refined.npz)")
    p.add_argument("out", type=output_file,
                   help="output: NAME.bt (OctoMap binary tree: occupied, free, unknown) or NAME.ply "
                        "(occupied voxel centres with their value as 'intensity'); with --layer distance "
                        "NAME.ply (free voxel centres within --radius-m of an obstacle, with their "
                        "'distance') or NAME.npz (the whole field and its grid)")
    p.add_argument("--threshold", type=unit_interval, default=None,
                   help="occupied if value >= this (default: the map's own threshold; map.npz only)")
    p.add_argument("--layer", choices=LAYER_CHOICES, default=None,
                   help="refined.npz / surface.npz (or a map.npz with surface.npz beside it) only: surface "
                        "(refined occupancy or surface layer >= 0.5) or safe (the map's occupied voxels) "
                        "into OUT (default: both, into NAME.surface.EXT and NAME.safe.EXT); any map: "
                        "distance (the distance field of the safe map, metres to the nearest obstacle)")
    p.add_argument("--radius-m", type=nonnegative_float, default=0.5,
                   help="--layer distance into NAME.ply: the free voxels within this distance of an "
                        "obstacle, metres (default 0.5)")
    p.add_argument("--unknown-free", action="store_true",
                   help="--layer distance: count never-observed voxels as free (default: as obstacles, the "
                        "safe choice for a planner)")
    p.add_argument("--max-distance-m", type=positive_float, default=None,
                   help="--layer distance: cap the field at this distance, metres (default: no cap)")
    return p


class _SafeMap:
    """A safe layer as :class:`~gpumap.layers.distance.DistanceField` reads a map."""

    backend = "numpy"

    def __init__(self, values: np.ndarray, grid, threshold: float) -> None:
        self._values, self.grid, self.threshold = values, grid, threshold

    def values(self) -> np.ndarray:
        return self._values


def _write_distance(p, a, out: Path, values: np.ndarray, grid, thr: float) -> dict:
    """The distance field of the safe layer ``values`` (occupied from ``thr``) as ``out`` (.ply or .npz)."""
    from gpumap.atomic import atomic_write
    from gpumap.layers.distance import DistanceField

    cap = a.max_distance_m
    if out.suffix.lower() == ".ply" and cap is not None and a.radius_m > cap:
        p.error(f"argument --radius-m: Expected at most --max-distance-m ({cap:g} m: farther voxels all read "
                f"the cap), but got {a.radius_m:g}")
    unknown = not a.unknown_free
    df = DistanceField(_SafeMap(values, grid, thr), unknown_is_obstacle=unknown, max_distance_m=cap)
    field = df.field()
    info = {"layer": "distance", "path": str(out), "threshold": thr, "unknown_is_obstacle": unknown,
            "max_distance_m": cap, "grid_shape": list(grid.shape), "voxel_size_m": grid.voxel_size_m}
    if out.suffix.lower() == ".npz":
        with atomic_write(out) as f:
            np.savez_compressed(f, distance_m=field, min_corner_m=np.asarray(grid.min_corner_m),
                                max_corner_m=np.asarray(grid.max_corner_m), voxel_size_m=grid.voxel_size_m,
                                threshold=thr, unknown_is_obstacle=unknown,
                                max_distance_m=np.nan if cap is None else cap)
        return {**info, "obstacle_voxels": int(df.obstacles().sum())}
    keep = (field > 0) & (field <= np.float32(a.radius_m))  # as the node's ~/distance_cloud
    centres, d = grid.centers(np.argwhere(keep)), field[keep]
    rec = np.empty(len(d), [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("distance", "<f4")])
    for i, n in enumerate("xyz"):
        rec[n] = centres[:, i]
    rec["distance"] = d
    head = ["ply", "format binary_little_endian 1.0",
            f"comment gpumap distance field: free voxel centres within {a.radius_m:g} m of an obstacle",
            f"element vertex {len(d)}", *(f"property float {n}" for n in rec.dtype.names), "end_header", ""]
    with atomic_write(out) as f:
        f.write("\n".join(head).encode("ascii"))
        f.write(rec.tobytes())
    return {**info, "radius_m": a.radius_m, "voxels": len(d)}


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
    if a.layer == "distance":
        if suffix not in (".ply", ".npz"):
            p.error(f"argument out: Expected a name ending .ply or .npz with --layer distance, but got "
                    f"{str(a.out)!r}")
    elif suffix not in (".bt", ".ply"):
        p.error(f"argument out: Expected a name ending .bt or .ply, but got {str(a.out)!r}")
    else:
        for flag, given in (("--radius-m", a.radius_m != 0.5), ("--unknown-free", a.unknown_free),
                            ("--max-distance-m", a.max_distance_m is not None)):
            if given:
                p.error(f"argument {flag}: Expected it with --layer distance only, but --layer is "
                        f"{a.layer or 'not given'}")
    a.out.parent.mkdir(parents=True, exist_ok=True)
    if a.layer == "distance":
        if is_refined_file(a.map):  # its safe layer
            if a.threshold is not None:
                p.error("argument --threshold: Expected no --threshold with a refined map (its safe layer "
                        f"keeps the map's), but got {a.threshold}")
            res = load_refined(a.map)
            values, grid, thr = res.map_values, res.grid, float(res.threshold)
        else:
            mapper = load_map(a.map, backend="numpy")
            values, grid = mapper.values(), mapper.grid
            thr = float(mapper.threshold if a.threshold is None else a.threshold)
        print(json.dumps(_write_distance(p, a, a.out, values, grid, thr)))
        return 0
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
