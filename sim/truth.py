"""Ground truth: which voxels a scene occupies, and which of them the pings saw.

A voxel is occupied when a surface passes through it (the surface is sampled densely:
at least ``samples_per_voxel`` points per voxel edge, so a surface crossing a voxel lands
a sample in it except for slivers thinner than ``voxel / samples_per_voxel``) or when its
centre lies inside a solid (each object's analytic ``contains``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

import gpumap

from .scenes import Scene

__all__ = ["Truth", "occupancy", "points_to_voxels"]


@dataclass
class Truth:
    """Ground-truth occupancy of a scene on a grid.

    Attributes
    ----------
    occupied : (nx, ny, nz) bool
        Voxels touching a surface or inside a solid.
    surface : (nx, ny, nz) bool
        Voxels a surface passes through.
    label : (nx, ny, nz) int16
        Index into ``names`` of the object owning the voxel (small objects win over the
        sand and walls where they share a voxel), -1 for free voxels.
    names : list of str
    """

    occupied: np.ndarray
    surface: np.ndarray
    label: np.ndarray
    names: list[str]

    def mask(self, name: str) -> np.ndarray:
        return self.label == self.names.index(name)


def points_to_voxels(points_W: np.ndarray, grid: gpumap.GridSpec) -> np.ndarray:
    """(n, 3) world points -> (m,) unique flat (C-order) indices of the voxels holding them."""
    idx = grid.index_of(np.asarray(points_W, np.float64))
    shape = np.array(grid.shape)
    ok = np.all((idx >= 0) & (idx < shape), axis=1)
    return np.unique(np.ravel_multi_index(idx[ok].T, grid.shape))


def occupancy(scene: Scene, grid: gpumap.GridSpec | None = None, samples_per_voxel: int = 4,
              seed: int = 0) -> Truth:
    """Ground-truth :class:`Truth` of ``scene`` on ``grid`` (default: the scene's grid)."""
    grid = grid or scene.grid
    shape = grid.shape
    n = int(np.prod(shape))
    label = np.full(n, -1, np.int16)
    surface = np.zeros(n, bool)
    inside = np.zeros(n, bool)
    spacing = grid.voxel_size_m / samples_per_voxel
    rng = np.random.default_rng(seed)
    lo = np.asarray(grid.min_corner_m)
    hi = lo + np.asarray(shape) * grid.voxel_size_m
    # Large background objects first so small objects overwrite the shared voxels' label.
    order = sorted(range(len(scene.objects)), key=lambda i: -scene.objects[i].mesh.area)
    for i in order:
        o = scene.objects[i]
        m = _clip_mesh(o.mesh, lo, hi)
        if m is not None:
            count = int(np.ceil(m.area / spacing**2)) + 1
            pts, _ = trimesh.sample.sample_surface(m, count, seed=rng)
            # Vertices too: thin parts (1 cm bars) keep their edges.
            pts = np.concatenate([pts, m.vertices])
            vox = points_to_voxels(pts, grid)
            surface[vox] = True
            label[vox] = i
        if o.contains is not None:
            blo = np.maximum(o.mesh.bounds[0], lo)
            bhi = np.minimum(o.mesh.bounds[1], hi)
            if np.any(bhi <= blo):
                continue
            i0 = np.clip(grid.index_of(blo), 0, np.array(shape) - 1)
            i1 = np.clip(grid.index_of(bhi), 0, np.array(shape) - 1)
            ax = [np.arange(a, b + 1) for a, b in zip(i0, i1, strict=True)]
            idx = np.stack([a.ravel() for a in np.meshgrid(*ax, indexing="ij")], 1)
            c = grid.centers(idx)
            ins = o.contains(c)
            flat = np.ravel_multi_index(idx[ins].T, shape)
            inside[flat] = True
            label[flat[label[flat] < 0]] = i
    occ = surface | inside
    return Truth(occ.reshape(shape), surface.reshape(shape), label.reshape(shape),
                 [o.name for o in scene.objects])


def _clip_mesh(mesh: trimesh.Trimesh, lo: np.ndarray, hi: np.ndarray) -> trimesh.Trimesh | None:
    """Faces of ``mesh`` whose box meets ``[lo, hi]`` (None if none)."""
    tri = mesh.triangles
    keep = np.all(tri.max(1) >= lo, axis=1) & np.all(tri.min(1) <= hi, axis=1)
    if not keep.any():
        return None
    return trimesh.Trimesh(mesh.vertices, mesh.faces[keep], process=False)
