"""The public OASIS reconstruction (chaos-whoi/oasis_iros), run unmodified in its own environment.

    OASIS_PYTHON bench/oasis_public.py --oasis-src SRC --job JOB.npz --out GRID.npz

``OASIS_PYTHON`` is an interpreter where the public code's own dependencies import (open3d, opencv,
Pillow, tqdm, matplotlib: its ``environment.yaml``); nothing of gpumap is imported here, so this module
runs there as it is. ``bench.real_frontier`` writes the job and reads the grid back.

The job (``.npz``): ``pngs`` (the fan PNG paths, as the public loader reads them: ``PIL.Image.open(p)
.convert("L")``), ``poses`` ((n, 4, 4) float64 ``T_W_S``, the same poses gpumap maps with),
``downsample`` (the public code's image downsample factor: its voxel is ``downsample * 2.0 / 398`` m),
``grid_origin`` and ``grid_size`` (metres: the box, as ``voxel_grid_origin`` / ``voxel_grid_size`` of
its config), ``min_pose_delta`` (metres; 0 feeds every frame, 0.01 skips frames as its
``reconstruct.py`` does: a frame whose position moved less than that since the last fed one).

Each fed frame goes through the public ``SonarVoxelGrid.update_voxel_grid`` as it is: its per-range
adaptive detection (``preprocess_sonar_image``: background from the first ``empty_ranges`` rows, per
range row a window mean / std, a pixel detected at ``occupancy_threshold`` standard deviations), its
max downsample, its voxel template, and its counts (a voxel is in its ``voxel_grid`` while more than
``1 - false_negative_rate`` = 50 % of the views that reached it detected it). The grid written back:
``occupied`` ((k, 3) int: the ``voxel_grid``'s voxel indices, the authors' reconstruction),
``obs_count`` / ``occ_count`` (their per-voxel counts), ``occ_ratio`` (-1 where never observed), the
box (``origin``, ``voxel_size``, ``shape``), ``fed`` (the frame numbers fed) and ``ms_per_frame``.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
import types
from pathlib import Path
from typing import Any

import numpy as np

#: The public configs/base.yaml values the mapping reads (sonar, detection, counts), as its loader
#: passes them to ``SonarVoxelGrid``; the box and the downsample factor come from the job.
BASE_SONAR = {"min_range": 0.1, "max_range": 2.0, "h_fov": 2.26892803, "v_fov": 0.34906585,
              "num_beams": 512, "num_ranges": 398, "polar_img": False}
BASE_FILTERING = {"range_window": 20, "empty_ranges": 10, "occupancy_threshold": 1,
                  "false_negative_rate": 0.5}
BASE_BOX = ((-0.5, -1.2, -0.5), (2.4, 2.4, 1.3))  # voxel_grid_origin, voxel_grid_size (metres)


def import_oasis(src: Path) -> type:
    """The public code's ``SonarVoxelGrid`` class from a checkout at ``src``. open3d imports its
    plotly/dash helpers at import time; the mapping never uses them, so where dash is missing an
    empty stand-in module takes its place."""
    try:
        import dash  # noqa: F401
    except ImportError:
        class _Stub(types.ModuleType):
            def __getattr__(self, name: str) -> Any:
                if name.startswith("__"):
                    raise AttributeError(name)
                sub = sys.modules[f"{self.__name__}.{name}"] = _Stub(f"{self.__name__}.{name}")
                return sub

            def __call__(self, *a: Any, **k: Any) -> Any:
                return self

        for name in ("dash", "dash.html", "dash.dcc"):
            sys.modules.setdefault(name, _Stub(name))
    sys.path.insert(0, str(src))
    from sonar_reconstruction.sonar_voxel_grid import SonarVoxelGrid  # type: ignore[import-not-found]

    return SonarVoxelGrid


def oasis_mapper(cls: type, downsample: int, origin=BASE_BOX[0], size=BASE_BOX[1]) -> Any:
    """A public ``SonarVoxelGrid`` with the configs/base.yaml values and the box ``origin`` / ``size``
    (metres), built as its constructor builds it but without its two render windows (not part of the
    mapping; they need a display)."""
    import open3d as o3d  # type: ignore[import-not-found]
    from sonar_reconstruction.polar_remapper import PolarRemapper  # type: ignore[import-not-found]

    g = cls.__new__(cls)
    g.sonar_params = {**BASE_SONAR, "range_resolution": BASE_SONAR["max_range"] / BASE_SONAR["num_ranges"],
                      "downsample_factor": int(downsample)}
    g.voxel_grid_params = {"grid_size": np.array(size, float), "grid_origin": np.array(origin, float),
                           "default_color": np.array([1, 0, 0])}
    g.filtering_params = dict(BASE_FILTERING)
    g.occ_ratio_thresh = 1 - g.filtering_params["false_negative_rate"]
    vg = g.voxel_grid_params
    vg["voxel_size"] = g.sonar_params["range_resolution"] * int(downsample)
    vg["voxel_radius"] = vg["voxel_size"] * math.sqrt(2)
    g.voxel_template = g.compute_voxel_template()
    g.voxel_grid = o3d.geometry.VoxelGrid()
    g.voxel_grid.origin, g.voxel_grid.voxel_size = vg["grid_origin"], vg["voxel_size"]
    shape = (vg["grid_size"] / vg["voxel_size"] + 1).astype(int)
    g.obs_count, g.occ_count, g.occ_ratio = np.zeros(shape), np.zeros(shape), -np.ones(shape)
    g.remapper = PolarRemapper(g.sonar_params)
    return g


def fed_frames(poses: np.ndarray, min_pose_delta: float) -> list[int]:
    """The frames the public ``reconstruct.py`` feeds: the first, then each whose position moved at
    least ``min_pose_delta`` metres since the last one fed (0: every frame)."""
    fed: list[int] = []
    for k, T in enumerate(poses):
        if fed and float(np.linalg.norm(T[:3, 3] - poses[fed[-1]][:3, 3])) < min_pose_delta:
            continue
        fed.append(k)
    return fed


def run(src: Path, pngs: list[str], poses: np.ndarray, downsample: int, origin, size,
        min_pose_delta: float = 0.0, progress: bool = True) -> dict[str, np.ndarray]:
    """Feed the frames to the public code; its final grid (module docstring)."""
    from PIL import Image

    cls = import_oasis(src)
    g = oasis_mapper(cls, downsample, origin, size)
    fed, ms = fed_frames(poses, min_pose_delta), []
    for n, k in enumerate(fed):
        fan = np.array(Image.open(pngs[k]).convert("L"))  # as utils/dataset_utils.load_data reads it
        t = time.perf_counter()
        g.update_voxel_grid(fan, np.asarray(poses[k], float))
        ms.append(1e3 * (time.perf_counter() - t))
        if progress and (n + 1) % 100 == 0:
            print(f"oasis_public: {n + 1}/{len(fed)} frames, {np.mean(ms):.0f} ms per frame", flush=True)
    occupied = np.array([v.grid_index for v in g.voxel_grid.get_voxels()], dtype=np.int64).reshape(-1, 3)
    vg = g.voxel_grid_params
    return {"occupied": occupied, "obs_count": g.obs_count.astype(np.int32),
            "occ_count": g.occ_count.astype(np.int32), "occ_ratio": g.occ_ratio.astype(np.float32),
            "origin": np.asarray(vg["grid_origin"], float), "voxel_size": np.float64(vg["voxel_size"]),
            "shape": np.array(g.obs_count.shape), "occ_ratio_thresh": np.float64(g.occ_ratio_thresh),
            "fed": np.array(fed), "ms_per_frame": np.array(ms)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python bench/oasis_public.py", description=__doc__.split("\n")[0])
    ap.add_argument("--oasis-src", type=Path, required=True, help="checkout of chaos-whoi/oasis_iros")
    ap.add_argument("--job", type=Path, required=True, help="the frames, poses and box (.npz, docstring)")
    ap.add_argument("--out", type=Path, required=True, help="where the grid goes (.npz)")
    ap.add_argument("--no-progress", action="store_true")
    a = ap.parse_args(argv)
    with np.load(a.job) as z:
        job = {k: z[k] for k in z.files}
    if len(job["pngs"]) != len(job["poses"]):
        raise SystemExit(f"oasis_public: expected one pose per PNG, but got {len(job['pngs'])} PNGs and "
                         f"{len(job['poses'])} poses")
    t0 = time.perf_counter()
    out = run(a.oasis_src, [str(p) for p in job["pngs"]], job["poses"], int(job["downsample"]),
              job["grid_origin"], job["grid_size"], float(job["min_pose_delta"]), not a.no_progress)
    import cv2  # type: ignore[import-not-found]
    import open3d as o3d  # type: ignore[import-not-found]

    out["seconds"] = np.float64(time.perf_counter() - t0)
    out["versions"] = np.array(f"python {sys.version.split()[0]}, open3d {o3d.__version__}, "
                               f"opencv {cv2.__version__}, numpy {np.__version__}")
    a.out.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(a.out, **out)
    print(f"oasis_public: fed {len(out['fed'])} frames, {len(out['occupied'])} occupied voxels, "
          f"{out['seconds']:.0f} s; wrote {a.out}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
