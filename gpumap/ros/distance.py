"""ROS 2 messages of the distance field (:mod:`gpumap.layers.distance`); message packages are imported lazily.

Two views of a field, as the node publishes them after an update that changed it:

- :func:`slice_message`: the horizontal layer of voxels at a height, as an *organised*
  ``sensor_msgs/PointCloud2`` (``height`` = ny rows of y, ``width`` = nx columns of x, the grid's own
  layout) with float32 fields ``x, y, z, distance``. A PointCloud2 rather than a
  ``nav_msgs/OccupancyGrid``: the grid's int8 cells (0..100, -1) would quantise metres to a scale the
  reader must be told, and have no value for "farther than the cap" or "no obstacle" (``inf``); the
  cloud carries the field's float32 metres exactly, RViz colours it by its ``distance`` channel, and
  the organised layout lets a reader take it back as an (ny, nx) image.
- :func:`cloud_message`: the voxels within ``radius_m`` of an obstacle, as an unordered
  ``sensor_msgs/PointCloud2`` with float32 ``x, y, z, distance`` (nvblox's ESDF cloud).

Both take the field as :meth:`DistanceField.field` gives it (metres, 0 at obstacles, negative inside
them for a signed field) and its grid; ``stamp`` is integer nanoseconds or a
``builtin_interfaces/Time``.
"""

from __future__ import annotations

import array

import numpy as np

from gpumap.errors import check_finite_scalar
from gpumap.ros.convert import stamp_of
from gpumap.spec import GridSpec

__all__ = ["DISTANCE_DTYPE", "cloud_arrays", "cloud_message", "slice_index", "slice_message"]

#: A point of both clouds: x, y, z (metres, in the grid's frame) and the distance (metres).
DISTANCE_DTYPE = np.dtype({"names": ["x", "y", "z", "distance"], "formats": ["<f4"] * 4,
                           "offsets": [0, 4, 8, 12], "itemsize": 16})


def _check(field: np.ndarray, grid: GridSpec) -> np.ndarray:
    if not isinstance(grid, GridSpec):
        raise TypeError(f"Expected a gpumap.GridSpec for 'grid', but got {type(grid).__name__}")
    f = np.asarray(field)
    if f.shape != grid.shape:
        raise ValueError(f"Expected a field of the grid's shape {grid.shape}, but got {f.shape}")
    return f


def _stamp(stamp):
    if isinstance(stamp, (int, np.integer)) and not isinstance(stamp, bool):
        return stamp_of(int(stamp))
    if hasattr(stamp, "sec") and hasattr(stamp, "nanosec"):
        return stamp
    raise TypeError(f"Expected integer nanoseconds or a builtin_interfaces/Time for 'stamp', but got "
                    f"{type(stamp).__name__}")


def _cloud(rec: np.ndarray, height: int, width: int, frame_id: str, stamp):
    from sensor_msgs.msg import PointCloud2, PointField

    m = PointCloud2()
    m.header.stamp = _stamp(stamp)
    m.header.frame_id = str(frame_id)
    m.height, m.width = int(height), int(width)
    m.fields = [PointField(name=n, offset=4 * i, datatype=PointField.FLOAT32, count=1)
                for i, n in enumerate(DISTANCE_DTYPE.names)]
    m.is_bigendian = False
    m.point_step = DISTANCE_DTYPE.itemsize
    m.row_step = DISTANCE_DTYPE.itemsize * int(width)
    m.is_dense = bool(np.isfinite(rec["distance"]).all())
    m.data = array.array("B", rec.tobytes())
    return m


def slice_index(grid: GridSpec, z_m: float) -> int:
    """The layer ``k`` of ``grid`` whose voxels hold height ``z_m`` (metres, world frame); ``ValueError``
    outside the grid."""
    z = check_finite_scalar(z_m, "z_m")
    s, z0, nz = grid.voxel_size_m, grid.min_corner_m[2], grid.shape[2]
    k = int(np.floor((z - z0) / s))
    if not 0 <= k < nz:
        raise ValueError(f"Expected z_m within the grid's voxels, {z0:.4g} to {z0 + nz * s:.4g} m, but got "
                         f"{z}")
    return k


def slice_message(field: np.ndarray, grid: GridSpec, z_m: float, frame_id: str, stamp):
    """``sensor_msgs/PointCloud2`` of the field's horizontal layer holding height ``z_m``: organised,
    ``height`` ny (row ``j``: y), ``width`` nx (column ``i``: x), every voxel of the layer at its centre
    (``z`` the layer's centre height) with its ``distance`` (metres; ``inf`` where the grid has no obstacle,
    then ``is_dense`` is False)."""
    f = _check(field, grid)
    k = slice_index(grid, z_m)
    nx, ny, _ = grid.shape
    s, lo = grid.voxel_size_m, np.asarray(grid.min_corner_m)
    rec = np.zeros((ny, nx), DISTANCE_DTYPE)
    rec["x"] = (lo[0] + (np.arange(nx) + 0.5) * s)[None, :]
    rec["y"] = (lo[1] + (np.arange(ny) + 0.5) * s)[:, None]
    rec["z"] = lo[2] + (k + 0.5) * s
    rec["distance"] = f[:, :, k].T
    return _cloud(rec, ny, nx, frame_id, stamp)


def cloud_arrays(field: np.ndarray, grid: GridSpec, radius_m: float, include_obstacles: bool = False
                 ) -> tuple[np.ndarray, np.ndarray]:
    """The content of :func:`cloud_message`: (N, 3) float64 centres and (N,) float32 distances of the
    voxels with ``0 < distance <= radius_m`` (free voxels within the radius of an obstacle), in C order;
    with ``include_obstacles`` also the obstacle voxels (0, or within ``radius_m`` of free space when the
    field is signed: ``-radius_m <= distance <= 0``)."""
    f = _check(field, grid)
    r = check_finite_scalar(radius_m, "radius_m")
    if r < 0:
        raise ValueError(f"Expected radius_m >= 0, but got {r}")
    keep = (f <= np.float32(r)) & ((f >= -np.float32(r)) if include_obstacles else (f > 0))
    idx = np.argwhere(keep)
    return grid.centers(idx), f[keep].astype(np.float32)


def cloud_message(field: np.ndarray, grid: GridSpec, radius_m: float, frame_id: str, stamp, *,
                  include_obstacles: bool = False):
    """Unordered ``sensor_msgs/PointCloud2`` (``height`` 1) with float32 ``x, y, z, distance`` of the voxels
    :func:`cloud_arrays` selects (nvblox's ESDF cloud: the band around obstacles a planner cares about)."""
    pts, d = cloud_arrays(field, grid, radius_m, include_obstacles)
    rec = np.zeros(len(d), DISTANCE_DTYPE)
    for i, n in enumerate("xyz"):
        rec[n] = pts[:, i]
    rec["distance"] = d
    return _cloud(rec, 1, len(d), frame_id, stamp)
