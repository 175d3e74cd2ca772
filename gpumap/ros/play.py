"""A recording as the ROS 2 node's topics: what ``gpumap ros-play RECORDING`` publishes
(:mod:`gpumap.commands.ros_play`).

Usage::

    gpumap ros-play RECORDING [--rate 1] [--hz 10] [--encoding auto] [--stride N]
                    [--max-frames N] [--static] [--preload]
                    [--write-params FILE [--voxel-size M]]
                    [--ros-args ...]

Reads the recording with gpumap's own readers (``gpumap.io.open_recording``: the OASIS fan
folder, Oculus ``.raw``/``.oculus``, ARIS, ROS 1/2 bags; and ``.gpumap-rec`` files of
``gpumap demo --record``), and publishes every posed ping as ``sonar/pose``
(``geometry_msgs/PoseStamped``, or ``nav_msgs/Odometry`` with ``--pose-type odometry``) then
``sonar/image`` (``sensor_msgs/Image``, the polar image: ``32FC1`` for float images, ``mono8``
for 8-bit ones, so the node gets the values the offline mapper gets) with one stamp, at the
recorded rate times ``--rate`` (``--hz`` when the recording has no times). Stamps are the
wall clock when each ping is sent (so latencies can be read against it), spaced as recorded.

``--write-params FILE`` writes the node's parameter file for this recording (the sonar as a
JSON spec beside it, the grid that holds every field of view at ``--voxel-size``) and exits:
``gpumap ros --params-file FILE`` then maps what ``gpumap ros-play`` sends.
"""

from __future__ import annotations

import json
import math
import zipfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gpumap.spec import GridSpec, SonarSpec

__all__ = ["PlayFrame", "Playable", "open_playable", "pose_msg", "write_params"]


@dataclass
class PlayFrame:
    """One ping to publish: polar image (uint8 or float32 in [0, 1]), pose, recorded time."""

    image: np.ndarray
    T_W_S: np.ndarray
    t_s: float | None


@dataclass
class Playable:
    """A recording ready to play: its sonar, the recorded grid if any, its posed frames."""

    path: str
    spec: SonarSpec
    grid: GridSpec | None
    frames: Callable[[], Iterator[PlayFrame]]
    count: int | None
    skipped: dict


def _is_map_recording(p: Path) -> bool:
    if not p.is_file() or not zipfile.is_zipfile(p):
        return False
    with zipfile.ZipFile(p) as zf:
        return "meta.json" in zf.namelist()


def open_playable(path: str | Path, *, static: bool = False, stride: int = 1,
                  max_frames: int | None = None) -> Playable:
    """Open ``path`` with gpumap's readers; frames without a pose are left out (counted in
    ``skipped['no_pose']``) unless ``static`` (identity pose), frames of another sonar
    geometry than the first are left out (``skipped['other_spec']``)."""
    p = Path(path)
    skipped = {"no_pose": 0, "other_spec": 0}
    if _is_map_recording(p):
        from gpumap.viewer.recording import read_recording

        rec = read_recording(p)

        def raw() -> Iterator[tuple[np.ndarray, np.ndarray | None, float | None, SonarSpec]]:
            for ping in rec.pings():
                yield ping.image, ping.T_W_S, None, rec.spec

        spec, grid, count = rec.spec, rec.grid, rec.n_pings
    else:
        from gpumap.io import open_recording

        recording = open_recording(p)
        if not recording.has_poses and not static:
            raise ValueError(f"Expected a recording with sonar poses, but {p} ({recording.kind}) has none: "
                             "pass --static to publish every ping at the identity pose")
        first = next(iter(recording), None)
        if first is None:
            raise ValueError(f"Expected frames in {p}, but it has none")

        def raw() -> Iterator[tuple[np.ndarray, np.ndarray | None, float | None, SonarSpec]]:
            for fr in recording:
                yield fr.image, fr.T_W_S, fr.timestamp_s, fr.spec

        spec, grid, count = first.spec, None, recording.count()

    def frames() -> Iterator[PlayFrame]:
        for k in skipped:
            skipped[k] = 0
        n = 0
        for i, (img, T, t, sp) in enumerate(raw()):
            if i % stride:
                continue
            if max_frames is not None and n >= max_frames:
                return
            if sp != spec:
                skipped["other_spec"] += 1
                continue
            if static:
                T = np.eye(4)
            if T is None:
                skipped["no_pose"] += 1
                continue
            n += 1
            yield PlayFrame(img, np.asarray(T, dtype=np.float64), t)

    if count is not None:
        count = math.ceil(count / stride)
        if max_frames is not None:
            count = min(count, max_frames)
    return Playable(str(p), spec, grid, frames, count, skipped)


def write_params(path: str | Path, play: Playable, *, voxel_size_m: float | None, threshold: float,
                 backend: str, world_frame: str, pose_type: str) -> Path:
    """Write the node's parameter YAML for ``play`` (and ``<path>.sonar.json``, the exact sonar).

    The grid is the recording's own (``.gpumap-rec``) unless ``voxel_size_m`` is given, else the
    box holding every field of view (``gpumap.pipeline.replay.auto_grid``). Returns the YAML's path.
    """
    from gpumap.atomic import atomic_write
    from gpumap.spec import auto_grid

    grid = play.grid
    if grid is None or voxel_size_m is not None:
        poses = [f.T_W_S for f in play.frames()]
        if not poses:
            raise ValueError(f"Expected posed frames in {play.path}, but got none")
        grid = auto_grid(play.spec, poses, 0.05 if voxel_size_m is None else voxel_size_m,
                         remedy="use a larger --voxel-size, or fewer frames (--stride, --max-frames)")
    path = Path(path)
    spec_path = path.with_name(path.name + ".sonar.json")
    with atomic_write(spec_path) as f:
        f.write(json.dumps(play.spec.to_dict()).encode())
    values = {
        "sonar_spec_file": str(spec_path.resolve()),
        "grid_min_m": list(grid.min_corner_m),
        "grid_max_m": list(grid.max_corner_m),
        "voxel_size_m": grid.voxel_size_m,
        "threshold": threshold,
        "backend": backend,
        "world_frame": world_frame,
        "pose_type": pose_type,
    }
    lines = [f"# gpumap ros parameters for {play.path} (written by gpumap ros-play --write-params)",
             "/**:", "  ros__parameters:"]
    lines += [f"    {k}: {json.dumps(v)}" for k, v in values.items()]
    with atomic_write(path) as f:
        f.write(("\n".join(lines) + "\n").encode())
    return path


def pose_msg(pose_type: str, T: np.ndarray, stamp, world_frame: str, sonar_frame: str):
    from gpumap.ros.convert import pose_msg_fields

    (x, y, z), (qx, qy, qz, qw) = pose_msg_fields(T)
    if pose_type == "odometry":
        from nav_msgs.msg import Odometry

        m = Odometry()
        m.child_frame_id = sonar_frame
        pose = m.pose.pose
    else:
        from geometry_msgs.msg import PoseStamped

        m = PoseStamped()
        pose = m.pose
    m.header.stamp = stamp
    m.header.frame_id = world_frame
    pose.position.x, pose.position.y, pose.position.z = x, y, z
    pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w = qx, qy, qz, qw
    return m
