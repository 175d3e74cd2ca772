"""The node's distance field (:class:`LiveDistance`): updated with each map publication, published only
when it changed, queried from the same process meanwhile.

The mapping worker (:class:`gpumap.ros.live.LiveMapper`) calls the node's ``on_publish`` after the pings
it mapped; there the node reads the map once (``values()``, between two integrations), publishes its
clouds, then hands the same values to :meth:`LiveDistance.refresh`: the field's incremental
:meth:`~gpumap.layers.distance.DistanceField.update` of that map (equal to a full recomputation), and,
when that changed a voxel, the field to publish (:meth:`LiveDistance.messages`: the slice and the
cloud of :mod:`gpumap.ros.distance`). The field and the occupied cloud published beside it are of the
same map.

Queries from other threads (a planner in the node's process) go through :meth:`LiveDistance.distance_at`,
:meth:`gradient_at` and :meth:`block`, which hold :attr:`LiveDistance.lock` so that they never read a
field half updated; :attr:`LiveDistance.field` is the :class:`~gpumap.layers.distance.DistanceField`
itself (hold ``lock`` around its methods). Nothing here needs ROS but :meth:`messages`.
"""

from __future__ import annotations

import threading

import numpy as np

from gpumap.errors import check_finite_scalar
from gpumap.layers.distance import DistanceField
from gpumap.ros.distance import cloud_message, slice_index, slice_message
from gpumap.spec import GridSpec

__all__ = ["LiveDistance"]


class LiveDistance:
    """The distance field of a live map, with the options of the node's ``distance_*`` parameters.

    Parameters
    ----------
    mapper : MinMaxMapper
        The live map (its grid fixed: a :class:`~gpumap.GridSpec`).
    slice_z_m : float or None
        Height of the published slice, metres in the world frame (the layer of voxels holding it);
        None: the grid's middle layer. ``ValueError`` outside the grid.
    cloud_radius_m : float
        The cloud holds the free voxels with ``0 < distance <= cloud_radius_m`` (metres, >= 0).
    unknown_is_obstacle : bool
        Never-observed voxels count as obstacles (default True).
    max_distance_m : float or None
        The field's truncation radius, metres (None: exact everywhere).
    backend : str or None
        Where the transform runs (None: the mapper's backend).

    The constructor computes the field of the map as it is (a full transform).
    """

    def __init__(self, mapper, *, slice_z_m: float | None = None, cloud_radius_m: float = 0.5,
                 unknown_is_obstacle: bool = True, max_distance_m: float | None = None,
                 backend: str | None = None) -> None:
        grid: GridSpec = mapper.grid
        if slice_z_m is None:
            slice_z_m = grid.min_corner_m[2] + (grid.shape[2] // 2 + 0.5) * grid.voxel_size_m
        self.slice_z_m = float(slice_z_m)
        self.slice_k = slice_index(grid, self.slice_z_m)  # ValueError outside the grid, before any work
        self.cloud_radius_m = check_finite_scalar(cloud_radius_m, "cloud_radius_m")
        if self.cloud_radius_m < 0:
            raise ValueError(f"Expected cloud_radius_m >= 0, but got {cloud_radius_m}")
        #: held while the field changes; hold it around any use of :attr:`field` from another thread
        self.lock = threading.Lock()
        #: the :class:`~gpumap.layers.distance.DistanceField` (updated in place)
        self.field = DistanceField(mapper, unknown_is_obstacle=unknown_is_obstacle,
                                   max_distance_m=max_distance_m, backend=backend)
        self.updates = 0  # refresh calls
        self.changes = 0  # of them, those that changed the field (each published)
        self.seconds = 0.0  # their updates' seconds, summed
        self.last: dict = dict(self.field.last_update)

    # ------------------------------------------------------------------ the worker's side
    def refresh(self, values: np.ndarray | None = None) -> np.ndarray | None:
        """Update the field from the map (``values``: its ``values()`` as just read, or None to read
        them); returns a copy of the field ((nx, ny, nz) float32 metres) when the update changed the
        obstacles (then publish it), else None (nothing to publish)."""
        with self.lock:
            self.field.update(values=values)
            self.updates += 1
            self.last = dict(self.field.last_update)
            self.seconds += float(self.last.get("seconds", 0.0))
            if self.last["kind"] == "none":
                return None
            self.changes += 1
            return self.field.field()

    def messages(self, field: np.ndarray, stamp_ns: int, frame_id: str):
        """``(slice, cloud)``: the two ``sensor_msgs/PointCloud2`` of ``field`` (a :meth:`refresh` result)
        that the node publishes on ``~/distance_slice`` and ``~/distance_cloud``
        (:func:`gpumap.ros.distance.slice_message`, :func:`~gpumap.ros.distance.cloud_message`)."""
        grid = self.field.grid
        return (slice_message(field, grid, self.slice_z_m, frame_id, stamp_ns),
                cloud_message(field, grid, self.cloud_radius_m, frame_id, stamp_ns))

    def stats(self) -> dict:
        """``distance_updates`` (refreshes), ``distance_changes`` (of them, published), the last one's
        ``distance_kind`` (``"full"``, ``"incremental"``, ``"none"``), ``distance_changed_voxels``
        (obstacle voxels that changed), ``distance_update_s`` (its seconds) and ``distance_seconds`` (every
        refresh's update, summed)."""
        with self.lock:
            last = self.last
            return {"distance_updates": self.updates, "distance_changes": self.changes,
                    "distance_kind": last.get("kind"), "distance_changed_voxels": last.get("changed") or 0,
                    "distance_update_s": float(last.get("seconds", 0.0)), "distance_seconds": self.seconds}

    # ------------------------------------------------------------------ queries, any thread
    def distance_at(self, points_W) -> np.ndarray:
        """:meth:`DistanceField.distance_at` of the field as last updated: (N, 3) world points, metres
        -> (N,) float64 metres."""
        with self.lock:
            return self.field.distance_at(points_W)

    def gradient_at(self, points_W) -> np.ndarray:
        """:meth:`DistanceField.gradient_at`: (N, 3) world points -> (N, 3) float64, per metre."""
        with self.lock:
            return self.field.gradient_at(points_W)

    def block(self, center_m, half_extent_m) -> tuple[GridSpec, np.ndarray]:
        """:meth:`DistanceField.block`: the box's grid and its (bx, by, bz) float32 field, metres."""
        with self.lock:
            return self.field.block(center_m, half_extent_m)
