"""Ground truth: which voxels a scene occupies, and which of them the pings saw.

A voxel is occupied when a surface passes through it (the surface is sampled densely:
at least ``samples_per_voxel`` points per voxel edge, so a surface crossing a voxel lands
a sample in it except for slivers thinner than ``voxel / samples_per_voxel``) or when its
centre lies inside a solid (each object's analytic ``contains``).

What the pings could know (:func:`ground_truth_masks`): a voxel is *seen* when a visible
surface point of some ping (an unoccluded ray in the field of view) falls in it, and
*detectable* when a point whose noise-free image cell reaches the occupied threshold does
(:func:`~.sonar.detected_points`); detectable voxels are a subset of the seen ones.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
import trimesh

import gpumap

from .scenes import BACKGROUND_OBJECTS, Scene
from .sonar import OCCUPIED_THRESHOLD, Ping, detected_points

__all__ = ["Truth", "occupancy", "points_to_voxels", "ground_truth_masks"]


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
    small_objects : tuple of str, optional
        Names of the obstacles (the scene's :attr:`~.scenes.Scene.small_objects`); default:
        every name not in :data:`~.scenes.BACKGROUND_OBJECTS`.
    """

    occupied: np.ndarray
    surface: np.ndarray
    label: np.ndarray
    names: list[str]
    small_objects: tuple[str, ...] | None = None

    def __post_init__(self) -> None:
        if self.small_objects is None:
            self.small_objects = tuple(n for n in self.names if n not in BACKGROUND_OBJECTS)
        else:
            self.small_objects = tuple(self.small_objects)

    def mask(self, name: str) -> np.ndarray:
        return self.label == self.names.index(name)

    def objects_mask(self, names: Iterable[str] | None = None) -> np.ndarray:
        """(nx, ny, nz) bool: voxels labelled with one of ``names`` (default: the small objects)."""
        names = self.small_objects if names is None else tuple(names)
        return np.isin(self.label, [self.names.index(n) for n in names if n in self.names])


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
            blo = np.maximum(o.bounds[0], lo)
            bhi = np.minimum(o.bounds[1], hi)
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
                 [o.name for o in scene.objects], scene.small_objects)


def ground_truth_masks(
    pings: Iterable[Ping], grid: gpumap.GridSpec, threshold: float = OCCUPIED_THRESHOLD
) -> tuple[np.ndarray, np.ndarray]:
    """``(seen, detectable)``: (nx, ny, nz) bool masks of what some ping saw / could detect.

    Parameters
    ----------
    pings : iterable of Ping
        Made by :class:`~.sonar.SonarSimulator` (a generator will do: each ping is used once).
    grid : gpumap.GridSpec
    threshold : float
        Occupied threshold on the noise-free image (see :func:`~.sonar.detected_points`).

    Returns
    -------
    seen : (nx, ny, nz) bool
        Voxels holding a visible surface point of some ping.
    detectable : (nx, ny, nz) bool
        Voxels holding a visible point whose noise-free cell is ``>= threshold`` in that
        ping; a subset of ``seen``.
    """
    seen = np.zeros(grid.n_voxels, bool)
    detectable = np.zeros(grid.n_voxels, bool)
    for p in pings:
        seen[points_to_voxels(p.points_W, grid)] = True
        detectable[points_to_voxels(detected_points(p, threshold), grid)] = True
    return seen.reshape(grid.shape), detectable.reshape(grid.shape)


def _clip_mesh(mesh: trimesh.Trimesh, lo: np.ndarray, hi: np.ndarray) -> trimesh.Trimesh | None:
    """Faces of ``mesh`` whose box meets ``[lo, hi]`` (None if none)."""
    tri = mesh.triangles
    keep = np.all(tri.max(1) >= lo, axis=1) & np.all(tri.min(1) <= hi, axis=1)
    if not keep.any():
        return None
    return trimesh.Trimesh(mesh.vertices, mesh.faces[keep], process=False)
