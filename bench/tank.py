"""The benchmark's data: the simulated tank pings (rendered once) and ground truth per voxel size.

Pings are rendered once per run and handed, unchanged, to every configuration. They are
quantized to uint8, the format the Oculus delivers (the mapper scales uint8 by 1/255 at
its boundary), which also keeps a saved ping file small (about 8 MB for the 40 pings of
the tank trajectory) so a machine that cannot render (the GPU box) can load them with
``--pings-from``.

Ground truth needs only the scene's meshes (trimesh), never the renderer: it is rebuilt
from the scene seed on any machine. Which truth voxels a ping actually saw (a visible
surface point fell in them) is carried in the ping file as the union of 5 mm cells that
held a visible point; every benchmark voxel size (0.5-6 cm) is a whole multiple of 5 mm on
the same grid origin, so each such cell lies in exactly one benchmark voxel.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

import gpumap

from .common import gl_renderer

__all__ = ["SEEN_CELL_M", "TankPings", "VoxelTruth", "load_pings", "simulate_tank", "voxel_truth"]

#: Edge of the cells that record which surface points the pings saw, metres.
SEEN_CELL_M = 0.005


@dataclass
class TankPings:
    """Simulated pings of the tank scene, ready to feed every configuration.

    Attributes
    ----------
    images : (n, n_bins, n_beams) uint8
    poses : (n, 4, 4) float64
        True sonar poses ``T_W_S``.
    seen_cells : (m, 3) int32
        Indices (on a grid of :data:`SEEN_CELL_M` cells from the scene grid's min corner) of
        the cells holding a visible surface point of some ping.
    meta : dict
        Scene name, seed, ping indices along the trajectory, simulator speed and renderer.
    """

    images: np.ndarray
    poses: np.ndarray
    seen_cells: np.ndarray
    meta: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.images.shape[0])

    def save(self, path: str | os.PathLike) -> Path:
        """Write the pings to ``path`` (.npz, compressed)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(
            path,
            images=self.images,
            poses=self.poses,
            seen_cells=self.seen_cells,
            meta=np.array(json.dumps(self.meta)),
        )
        return path


def load_pings(path: str | os.PathLike) -> TankPings:
    """Read pings written by :meth:`TankPings.save`."""
    with np.load(path, allow_pickle=False) as z:
        missing = {"images", "poses", "seen_cells", "meta"} - set(z.files)
        if missing:
            raise ValueError(f"Expected a bench ping file with {sorted(missing)}, but {path} has {z.files}")
        out = TankPings(z["images"], z["poses"], z["seen_cells"], json.loads(str(z["meta"])))
    if out.images.dtype != np.uint8 or out.images.ndim != 3:
        raise ValueError(
            f"Expected (n, bins, beams) uint8 images in {path}, but got {out.images.shape} {out.images.dtype}"
        )
    out.meta["loaded_from"] = str(path)
    return out


def simulate_tank(n_pings: int | None = None, seed: int = 0, progress: bool = True) -> TankPings:
    """Render the tank trajectory's pings (all of them, or ``n_pings`` evenly spaced).

    The simulator's speed (images/s after the first ping, which builds the GL context) and
    the GL renderer are recorded in ``meta``.
    """
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    from gpumap.sim.scenes import make_scene
    from gpumap.sim.sonar import SonarSimulator
    from tqdm import tqdm

    scene = make_scene("tank", seed=seed)
    n_all = len(scene.T_W_S)
    sel = np.arange(n_all)
    if n_pings is not None and n_pings < n_all:
        sel = np.unique(np.linspace(0, n_all - 1, n_pings).round().astype(int))
    images, cells = [], []
    lo = np.asarray(scene.grid.min_corner_m)
    t_first = time.perf_counter()
    gl = "unknown"
    with SonarSimulator(scene, seed=seed) as sim:
        times = []
        for i, k in enumerate(tqdm(sel, desc="simulate tank", unit="ping", disable=not progress)):
            t0 = time.perf_counter()
            p = sim.ping(scene.T_W_S[k], int(k))
            times.append(time.perf_counter() - t0)
            if i == 0:
                init_s = time.perf_counter() - t_first
                gl = gl_renderer()
            images.append(np.round(p.image * 255.0).astype(np.uint8))
            cells.append(np.unique(np.floor((p.points_W - lo) / SEEN_CELL_M).astype(np.int32), axis=0))
        rays = int(sim.rays_per_ping)
    seen = np.unique(np.concatenate(cells), axis=0)
    t = np.array(times[1:] if len(times) > 1 else times)
    meta = {
        "scene": "tank",
        "seed": seed,
        "ping_indices": sel.tolist(),
        "pings_in_trajectory": n_all,
        "image_shape": list(scene.sonar_spec.image_shape),
        "quantized": "uint8 (intensity * 255, rounded)",
        "sim": {
            "images_per_s": float(1.0 / t.mean()),
            "ms_per_image_median": float(1e3 * np.median(t)),
            "init_s": float(init_s),
            "rays_per_ping": rays,
            "gl_renderer": gl,
            "note": "pyrender sonar simulator, first ping (GL context) excluded",
        },
    }
    return TankPings(np.stack(images), scene.T_W_S[sel].copy(), seen, meta)


@dataclass
class VoxelTruth:
    """The scene, its ground truth and the seen mask on one voxel size's grid."""

    scene: object
    truth: object
    seen: np.ndarray
    truth_s: float


def voxel_truth(voxel_size_m: float, seen_cells: np.ndarray, seed: int = 0) -> VoxelTruth:
    """Ground truth of the tank on the ``voxel_size_m`` grid, and the voxels the pings saw."""
    from gpumap.sim.scenes import make_scene
    from gpumap.sim.truth import occupancy, points_to_voxels

    t0 = time.perf_counter()
    scene = make_scene("tank", voxel_size_m=voxel_size_m, seed=seed)
    truth = occupancy(scene, seed=seed)
    grid: gpumap.GridSpec = scene.grid
    seen = np.zeros(grid.shape, bool)
    ratio = round(voxel_size_m / SEEN_CELL_M)
    if ratio >= 1 and abs(ratio * SEEN_CELL_M - voxel_size_m) < 1e-9:
        idx = seen_cells // ratio
        ok = np.all((idx >= 0) & (idx < np.array(grid.shape)), axis=1)
        seen[tuple(idx[ok].T)] = True
    else:  # not nested: use the cell centres (off by at most half a cell at voxel faces)
        c = np.asarray(grid.min_corner_m) + (seen_cells + 0.5) * SEEN_CELL_M
        seen.reshape(-1)[points_to_voxels(c, grid)] = True
    return VoxelTruth(scene, truth, seen, time.perf_counter() - t0)
