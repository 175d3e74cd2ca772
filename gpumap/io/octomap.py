"""OctoMap ``.bt`` export: the map as RViz's OctoMap plugin and ``octovis`` open it.

A ``.bt`` file is OctoMap's compact binary occupancy tree (``OcTree::writeBinary``): a text
header (``id OcTree``, ``size`` = number of tree nodes, ``res`` = leaf edge in metres) and the
tree depth first, two bytes per inner node holding two bits per child (``00`` unknown,
``01`` free leaf, ``10`` occupied leaf, ``11`` inner node; the low bit of each pair is
"free or inner", the high bit "occupied or inner"). Three states survive: occupied
(value >= ``threshold``), free (observed, value below it) and unknown (never observed, NaN:
no node). Eight siblings of one state are merged into their parent, as OctoMap prunes.

OctoMap's leaves sit on a lattice fixed at the world origin (cell ``k`` spans
``[k res, (k + 1) res)`` on each axis, 16 levels deep, so ``|coordinate| < 32768 res``). A
gpumap voxel becomes the OctoMap cell that holds its centre: where the grid's
``min_corner_m`` is not a multiple of the voxel size, the map moves by less than half a
voxel per axis (``octomap_offset_m`` says by how much).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from gpumap.atomic import atomic_write

__all__ = ["TREE_DEPTH", "octomap_offset_m", "octree_nodes", "write_octomap_bt"]

#: OctoMap's tree depth: keys are 16-bit per axis, the world spans ``+-32768 * res``.
TREE_DEPTH = 16
_KEY_ORIGIN = 1 << (TREE_DEPTH - 1)  # 32768: the key of the cell starting at coordinate 0
_FREE, _OCCUPIED, _INNER = 1, 2, 3  # two-bit child codes as written (bit 0: free|inner, bit 1: occ|inner)
_HEADER = ("# Octomap OcTree binary file\n"
           "# (written by gpumap: occupied = min-max value >= {thr:g}, free = observed below it, "
           "unknown = never observed)\n"
           "id OcTree\nsize {size}\nres {res!r}\ndata\n")


def _values_and_grid(mapper_or_values: Any, grid: Any) -> tuple[np.ndarray, Any]:
    if hasattr(mapper_or_values, "values") and callable(mapper_or_values.values):
        grid = mapper_or_values.grid if grid is None else grid
        values = mapper_or_values.values()
    else:
        values = mapper_or_values
    if grid is None:
        raise TypeError("Expected a GridSpec with a values array (or a mapper, which has one), but got "
                        "grid=None")
    values = np.asarray(values)
    if values.ndim != 3 or tuple(values.shape) != tuple(grid.shape):
        raise ValueError(f"Expected values of the grid's shape {tuple(grid.shape)}, but got "
                         f"{values.shape}")
    if not np.issubdtype(values.dtype, np.floating):
        raise TypeError(f"Expected floating values (NaN = never observed), but got {values.dtype}")
    return values, grid


def _keys(grid: Any, shape: tuple[int, int, int]) -> tuple[np.ndarray, np.ndarray]:
    """OctoMap key of voxel index 0 on each axis (int64 (3,)) and the resolution (float)."""
    res = float(grid.voxel_size_m)
    c0 = np.asarray(grid.min_corner_m, np.float64) + 0.5 * res  # centre of voxel (0, 0, 0)
    k0 = np.floor(c0 / res).astype(np.int64) + _KEY_ORIGIN
    k1 = k0 + np.asarray(shape, np.int64) - 1
    if (k0 < 0).any() or (k1 >= 2 * _KEY_ORIGIN).any():
        raise ValueError(f"Expected a grid within OctoMap's +-{_KEY_ORIGIN} voxels of the origin "
                         f"(+-{_KEY_ORIGIN * res:g} m at {res:g} m), but it spans "
                         f"{list(grid.min_corner_m)}..{list(grid.max_corner_m)} m")
    return k0, np.float64(res)


def octomap_offset_m(grid: Any) -> np.ndarray:
    """How far (metres, (3,) float64) the OctoMap cells' centres lie from the grid's voxel centres."""
    k0, res = _keys(grid, (1, 1, 1))
    c0 = np.asarray(grid.min_corner_m, np.float64) + 0.5 * res
    return (k0 - _KEY_ORIGIN + 0.5) * res - c0


def _morton(keys: np.ndarray, depth: int) -> np.ndarray:
    """Child-index path of nodes at ``depth`` (keys (n, 3) of that depth), root first, as uint64.

    At each level the child index is ``x + 2 y + 4 z`` of that level's key bits (OctoMap's
    ``computeChildIdx``); the path is padded with zeros to the leaf depth so that sorting
    ``(path, depth)`` gives the depth-first pre-order OctoMap writes.
    """
    code = np.zeros(len(keys), np.uint64)
    for lvl in range(depth):  # lvl 0: the root's child index
        bit = depth - 1 - lvl
        pos = (((keys[:, 0] >> bit) & 1) | (((keys[:, 1] >> bit) & 1) << 1)
               | (((keys[:, 2] >> bit) & 1) << 2)).astype(np.uint64)
        code |= pos << np.uint64(3 * (TREE_DEPTH - 1 - lvl))
    return code


def octree_nodes(occupied: np.ndarray, free: np.ndarray) -> tuple[int, bytes, dict]:
    """Build OctoMap's pruned tree over leaf keys; returns ``(n_nodes, data bytes, counts)``.

    Parameters
    ----------
    occupied, free : (n, 3) int64
        Leaf keys (depth 16) of occupied and of free cells; none in both.

    Returns
    -------
    n_nodes : int
        Every node of the tree (root, inner nodes and leaves): the header's ``size``.
    data : bytes
        The depth-first node bytes of ``OcTree::writeBinaryData``.
    counts : dict
        ``leaves``, ``inner`` (root included) and ``occupied_cells`` / ``free_cells`` (depth-16 cells).
    """
    keys = np.concatenate([occupied, free]).astype(np.int64).reshape(-1, 3)
    state = np.concatenate([np.full(len(occupied), _OCCUPIED, np.uint8),
                            np.full(len(free), _FREE, np.uint8)])
    counts = {"occupied_cells": int(len(occupied)), "free_cells": int(len(free)), "leaves": 0, "inner": 0}
    if len(keys) == 0:
        return 0, b"", counts
    inner_paths, inner_depths, inner_bytes = [], [], []
    n_leaves = 0
    # nodes of the current level: keys, state (free/occupied leaf or inner)
    for depth in range(TREE_DEPTH, 0, -1):
        parent = keys >> 1
        child = ((keys[:, 0] & 1) | ((keys[:, 1] & 1) << 1) | ((keys[:, 2] & 1) << 2)).astype(np.int64)
        pid = (parent[:, 0] << 32) | (parent[:, 1] << 16) | parent[:, 2]
        order = np.argsort(pid, kind="stable")
        pid, child, state, parent = pid[order], child[order], state[order], parent[order]
        first = np.r_[True, pid[1:] != pid[:-1]]
        group = np.cumsum(first) - 1
        n_par = int(group[-1]) + 1
        codes = np.zeros((n_par, 8), np.uint8)
        codes[group, child] = state
        par_keys = parent[first]
        # OctoMap prunes 8 equal leaf children into one leaf (the root is always inner)
        same = (codes == codes[:, :1]).all(1) & (codes[:, 0] != _INNER) & (depth > 1)
        n_leaves += int(np.count_nonzero(codes[~same] == _FREE) + np.count_nonzero(codes[~same] == _OCCUPIED))
        inner = ~same
        w = np.array([1, 4, 16, 64], np.uint32)
        b = np.stack([(codes[inner, :4] * w).sum(1), (codes[inner, 4:] * w).sum(1)], 1).astype(np.uint8)
        inner_paths.append(_morton(par_keys[inner], depth - 1))
        inner_depths.append(np.full(int(inner.sum()), depth - 1, np.uint8))
        inner_bytes.append(b)
        keys = par_keys
        state = np.where(same, codes[:, 0], _INNER).astype(np.uint8)
    paths = np.concatenate(inner_paths)
    depths = np.concatenate(inner_depths)
    data = np.concatenate(inner_bytes)
    order = np.lexsort((depths, paths))  # pre-order: by path, a parent before its child 0
    counts.update(leaves=n_leaves, inner=len(paths))
    return len(paths) + n_leaves, data[order].tobytes(), counts


def write_octomap_bt(path: str | os.PathLike, mapper_or_values: Any, grid: Any = None,
                     threshold: float = 0.1) -> dict:
    """Write a map as an OctoMap binary tree (``.bt``), atomically.

    Parameters
    ----------
    path : path-like
        The ``.bt`` file (replaced whole, or left as it was on any error).
    mapper_or_values : MinMaxMapper or (nx, ny, nz) float array
        A mapper (its ``values()`` and ``grid``) or its values, NaN = never observed.
    grid : GridSpec, optional
        Needed with a values array; a mapper's own grid otherwise.
    threshold : float
        Occupied if value >= this, free if observed and below it.

    Returns
    -------
    dict
        ``path``, ``resolution_m``, ``nodes`` (the header's size), ``occupied_cells`` and
        ``free_cells`` (voxels written), ``leaves`` after pruning, ``bytes`` and
        ``offset_m`` (:func:`octomap_offset_m`).

    Raises
    ------
    ValueError
        Values not of the grid's shape, a non-finite threshold, or a grid beyond OctoMap's
        16-level key range.
    """
    values, grid = _values_and_grid(mapper_or_values, grid)
    threshold = float(threshold)
    if not np.isfinite(threshold):
        raise ValueError(f"Expected a finite threshold, but got {threshold}")
    k0, res = _keys(grid, values.shape)
    seen = np.isfinite(values)
    occ = seen & (values >= threshold)
    occ_keys = np.argwhere(occ) + k0
    free_keys = np.argwhere(seen & ~occ) + k0
    n_nodes, data, counts = octree_nodes(occ_keys, free_keys)
    head = _HEADER.format(thr=threshold, size=n_nodes, res=float(res)).encode("ascii")
    p = Path(path)
    with atomic_write(p) as f:
        f.write(head)
        f.write(data)
    return {"path": str(p), "resolution_m": float(res), "nodes": n_nodes, **counts,
            "bytes": len(head) + len(data), "offset_m": octomap_offset_m(grid).tolist()}
