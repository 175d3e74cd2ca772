"""The node's parameters (:data:`PARAMETERS`: name -> default and description) and what is read
from them: the sonar's geometry, the rule and flags, the planner's limits, the distance field's
options."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from gpumap.spec import SonarSpec

__all__ = ["PARAMETERS", "distance_options", "plan_options", "sonar_spec_from_params"]


#: name -> (default, description). Lists of floats default to the empty list where "unset".
PARAMETERS: dict[str, tuple[object, str]] = {
    "world_frame": ("map", "frame of the poses and of every map output"),
    "pose_type": (
        "pose_stamped",
        "pose topic type: pose_stamped (geometry_msgs/PoseStamped) or odometry (nav_msgs/Odometry)",
    ),
    "image_layout": ("polar", "polar (n_bins x n_beams) or fan (a Cartesian fan picture, see fan_*)"),
    "fan_rows": (398, "fan picture height, pixels"),
    "fan_cols": (722, "fan picture width, pixels"),
    "fan_pixel_m": (2.0 / 398, "fan pixel edge, metres"),
    "fan_apex_row": (397.0, "row of the sonar in the fan picture"),
    "fan_apex_col": (361.0, "column of the sonar in the fan picture"),
    "fan_flip_lr": (False, "fan columns run right to left"),
    "fan_flip_ud": (False, "fan rows are mirrored"),
    "sonar_spec_file": (
        "",
        "JSON or YAML with range_min_m, range_max_m, n_bins, bearings_rad, vfov_rad "
        "(overrides the sonar parameters below)",
    ),
    "range_min_m": (0.1, "near edge of the first range bin, metres"),
    "range_max_m": (2.0, "far edge of the last range bin, metres"),
    "n_bins": (400, "range bins (image rows)"),
    "vfov_deg": (20.0, "vertical aperture, degrees"),
    "bearings_deg": ([], "beam azimuths, ascending, degrees (unset: hfov_deg and n_beams, evenly spaced)"),
    "hfov_deg": (130.0, "horizontal aperture for evenly spaced beams, degrees"),
    "n_beams": (512, "beams (image columns) for evenly spaced beams"),
    "grid_min_m": ([-2.0, -2.0, -1.0], "grid box lower corner x, y, z in world_frame, metres"),
    "grid_max_m": ([2.0, 2.0, 1.0], "grid box upper corner x, y, z in world_frame, metres"),
    "voxel_size_m": (0.05, "voxel edge, metres"),
    "backend": ("auto", "mapper backend: auto or a name of gpumap info (never falls back when named)"),
    "rule": ("evidence", "how views combine: evidence, visible or plain"),
    "threshold": (0.4, "occupied from this value on; also the mapper's bright threshold (as gpumap replay)"),
    "carve_views": (2, "visible rule: clear dark views that carve a voxel once seen bright"),
    "confidence": (
        False,
        "keep the confidence layer (MinMaxMapper(confidence=True)): the cloud gets a uint8 "
        "field confirmed, 1 where some view resolved the voxel in elevation, 0 where it is only "
        "consistent with the pings (the elevation stretch); costs a pass per ping on the host",
    ),
    "surface": (
        False,
        "keep the surface layer (gpumap.layers.surface: one voxel per bright cell, from the evidence "
        "or visible rule's occupied voxels) on a thread of its own: ~/surface_cloud and "
        "~/surface_markers, updated as often as the machine allows; ~/save_map then writes both "
        "layers in one file (gpumap view/export --layer surface|safe); needs rule evidence or "
        "visible. The thread shares the interpreter with the callbacks: on a small CPU raise "
        "image_queue_depth, or images are lost in the middleware",
    ),
    "surface_max_pings": (
        0,
        "the surface layer of the newest this many pings only, so that its memory "
        "(17 bytes per ping, voxel and bright cell: ~25k a ping on the real tank at 5 cm) "
        "and its updates stop growing with the run (0: every ping)",
    ),
    "distance": (
        False,
        "keep the distance field of the safe map (gpumap.layers.distance): with each map publication the "
        "worker updates it (only what the new pings changed) and, when that changed it, publishes "
        "~/distance_slice and ~/distance_cloud (PointCloud2, x, y, z, distance float32 metres)",
    ),
    "distance_slice_z_m": (
        [],
        "~/distance_slice: the horizontal layer of voxels holding this height, metres in world_frame "
        "(unset: the grid's middle layer)",
    ),
    "distance_cloud_radius_m": (
        0.5,
        "~/distance_cloud: the free voxels within this distance of an obstacle, metres (nvblox's ESDF "
        "cloud; at most distance_max_m when that is set)",
    ),
    "distance_unknown_is_obstacle": (
        True,
        "the distance field counts never-observed voxels as obstacles (the safe default) or, false, as free",
    ),
    "distance_max_m": (
        0.0,
        "truncation radius of the distance field, metres: farther distances read it, and updates reach "
        "at most that far from what changed (0: no cap, exact everywhere)",
    ),
    "queue_size": (32, "pings held at most; a new ping finding it full drops the oldest (counted)"),
    "max_batch": (16, "pings per integrate_batch call at most"),
    "pose_wait_s": (0.5, "how long a ping newer than every pose waits for one, seconds"),
    "max_pose_gap_s": (0.5, "poses further apart than this do not bracket a ping, seconds"),
    "pose_buffer": (2000, "poses kept for interpolation"),
    "max_future_s": (1.0, "a stamp later than the node's clock by more than this is refused, seconds"),
    "image_queue_depth": (10, "sensor-data QoS history depth of the image subscription"),
    "publish_period_s": (
        0.0,
        "the map outputs are published at most this often, seconds (0: after every "
        "batch the worker maps: a busy node publishes less often, a lone ping at once)",
    ),
    "markers_period_s": (
        1.0,
        "the RViz markers are published at most this often (only changed blocks), seconds",
    ),
    "diagnostics_period_s": (1.0, "period of /diagnostics, seconds"),
    "band_z_m": ([], "height band [z_min, z_max] of the obstacle projection, metres (unset: the whole grid)"),
    "plan_views": (
        5,
        "~/plan_views: poses published on ~/next_best_views, best first (needs confidence: true)",
    ),
    "plan_candidates": (500, "~/plan_views: candidate poses scored around the newest pose mapped"),
    "plan_max_roll_deg": (45.0, "~/plan_views: wrist roll about the boresight, +- degrees"),
    "plan_max_tilt_deg": (15.0, "~/plan_views: wrist pitch (tilt), +- degrees"),
    "plan_max_yaw_deg": (20.0, "~/plan_views: wrist yaw, +- degrees"),
    "plan_radius_m": (0.1, "~/plan_views: reach, each axis of the translation within +- this, metres"),
    "plan_unknown_weight": (0.0, "~/plan_views: weight of an unknown voxel against an unconfirmed one"),
    "save_path": ("gpumap_map.npz", "where ~/save_map (and save_on_exit) writes the map"),
    "save_on_exit": (False, "save the map to save_path when the node stops"),
}


def sonar_spec_from_params(p: dict) -> SonarSpec:
    """The sonar geometry from the node's parameter values (``sonar_spec_file`` first)."""
    f = str(p["sonar_spec_file"])
    if f:
        text = Path(f).read_text()
        try:
            d = json.loads(text)
        except json.JSONDecodeError:
            import yaml

            d = yaml.safe_load(text)
        try:
            return SonarSpec.from_dict(d)
        except (KeyError, TypeError) as e:
            raise ValueError(f"Expected {f} to hold range_min_m, range_max_m, n_bins, bearings_rad and "
                             f"vfov_rad, but reading it failed: {e!r}") from None
    bearings = list(p["bearings_deg"])
    if bearings:
        b = np.deg2rad(np.asarray(bearings, dtype=np.float64))
        return SonarSpec(float(p["range_min_m"]), float(p["range_max_m"]), int(p["n_bins"]), b,
                         math.radians(float(p["vfov_deg"])))
    return SonarSpec.uniform(hfov_deg=float(p["hfov_deg"]), vfov_deg=float(p["vfov_deg"]),
                             n_beams=int(p["n_beams"]), n_bins=int(p["n_bins"]),
                             range_min_m=float(p["range_min_m"]), range_max_m=float(p["range_max_m"]))


def _choice(p: dict, name: str, allowed: tuple[str, ...]) -> str:
    v = str(p[name])
    if v not in allowed:
        raise ValueError(f"Expected parameter {name} to be one of {', '.join(allowed)}, but got {v!r}")
    return v


def _flag(p: dict, name: str) -> bool:
    v = p[name]
    if not isinstance(v, bool):
        raise ValueError(f"Expected parameter {name} to be true or false, but got {v!r}")
    return v


def plan_options(p: dict) -> dict:
    """Keyword arguments of :func:`gpumap.layers.viewgain.next_best_views` from the node's ``plan_*``
    parameters (checked: counts positive, limits in degrees within their ranges, reach >= 0)."""
    views, cands = p["plan_views"], p["plan_candidates"]
    for name, v in (("plan_views", views), ("plan_candidates", cands)):
        if isinstance(v, bool) or not isinstance(v, int) or v < 1:
            raise ValueError(f"Expected parameter {name} to be a positive integer, but got {v!r}")
    lim = {}
    for name, key, top in (("plan_max_roll_deg", "roll_rad", 180.0),
                           ("plan_max_tilt_deg", "pitch_rad", 90.0),
                           ("plan_max_yaw_deg", "yaw_rad", 180.0)):
        d = float(p[name])
        if not 0.0 <= d <= top:
            raise ValueError(f"Expected parameter {name} in [0, {top:g}] degrees, but got {p[name]!r}")
        lim[key] = (-math.radians(d), math.radians(d))
    r, w = float(p["plan_radius_m"]), float(p["plan_unknown_weight"])
    if not (r >= 0.0 and math.isfinite(r)) or not (w >= 0.0 and math.isfinite(w)):
        raise ValueError("Expected plan_radius_m and plan_unknown_weight >= 0, but got "
                         f"{p['plan_radius_m']!r} and {p['plan_unknown_weight']!r}")
    return {"views": views, "candidates": cands, "offset_m": (-r, r), "unknown_weight": w, **lim}


def _metres(p: dict, name: str) -> float:
    v = p[name]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise ValueError(f"Expected parameter {name} to be a finite number of metres, but got {v!r}")
    return float(v)


def distance_options(p: dict) -> dict | None:
    """Keyword arguments of :class:`gpumap.ros.distance_pub.LiveDistance` from the node's ``distance_*``
    parameters, or None with ``distance: false``: ``slice_z_m`` (float, or None for the grid's middle
    layer), ``cloud_radius_m`` (>= 0), ``unknown_is_obstacle`` and ``max_distance_m`` (> 0, or None for
    ``distance_max_m: 0``). Checked: a radius beyond the cap is refused (every voxel beyond the cap
    reads the cap, so the cloud would hold them all)."""
    if not _flag(p, "distance"):
        return None
    z = p["distance_slice_z_m"]
    if isinstance(z, (list, tuple)) and not z:
        slice_z = None
    else:
        slice_z = _metres(p, "distance_slice_z_m")
    radius, cap = _metres(p, "distance_cloud_radius_m"), _metres(p, "distance_max_m")
    if radius < 0 or cap < 0:
        raise ValueError(f"Expected distance_cloud_radius_m >= 0 and distance_max_m >= 0 (0: no cap), but "
                         f"got {p['distance_cloud_radius_m']!r} and {p['distance_max_m']!r}")
    if cap and radius > cap:
        raise ValueError(f"Expected distance_cloud_radius_m <= distance_max_m ({cap} m: farther voxels all "
                         f"read the cap), but got {radius} m")
    return {"slice_z_m": slice_z, "cloud_radius_m": radius,
            "unknown_is_obstacle": _flag(p, "distance_unknown_is_obstacle"), "max_distance_m": cap or None}
