"""``gpumap ros-play RECORDING``: publish any recording gpumap reads as the node's topics.

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
import sys
import time
import zipfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gpumap.spec import GridSpec, SonarSpec

__all__ = ["PlayFrame", "Playable", "main", "open_playable", "write_params"]


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
    box holding every field of view (``gpumap.replay.auto_grid``). Returns the YAML's path.
    """
    from gpumap.atomic import atomic_write
    from gpumap.replay import auto_grid

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


def _parser():
    from gpumap.cli import (
        ArgumentParser,
        backend_name,
        nonnegative_float,
        output_file,
        positive_float,
        positive_int,
        unit_interval,
    )

    p = ArgumentParser(prog="gpumap ros-play", description=(
        "Publish a recording gpumap reads (fan folder + poses, Oculus, ARIS, ROS bag, .gpumap-rec) as "
        "sonar/pose and sonar/image for gpumap ros, at its recorded rate or faster. ROS options go after "
        "--ros-args (for example -r sonar/image:=/my/image)."))
    p.add_argument("recording", help="the recording: a file or a folder")
    p.add_argument("--rate", type=positive_float, default=1.0,
                   help="play this many times faster than recorded (default 1)")
    p.add_argument("--hz", type=positive_float, default=10.0,
                   help="ping rate when the recording has no times (default 10), times --rate")
    p.add_argument("--encoding", default="auto", choices=["auto", "mono8", "mono16", "32FC1"],
                   help="image encoding: auto is mono8 for 8-bit pings and 32FC1 (lossless) for the rest")
    p.add_argument("--pose-type", default="pose_stamped", choices=["pose_stamped", "odometry"],
                   help="publish poses as geometry_msgs/PoseStamped or nav_msgs/Odometry")
    p.add_argument("--world-frame", default="map", help="frame_id of the poses (default map)")
    p.add_argument("--sonar-frame", default="sonar", help="frame_id of the images (default sonar)")
    p.add_argument("--stride", type=positive_int, default=1, help="publish every N-th ping")
    p.add_argument("--max-frames", type=positive_int, default=None, help="publish at most N pings")
    p.add_argument("--static", action="store_true", help="publish pings without a pose at the identity pose")
    p.add_argument("--preload", action="store_true",
                   help="read and convert every ping before playing (memory: all images), so that reading "
                   "the recording does not limit the rate")
    p.add_argument("--wait-subscribers", type=nonnegative_float, default=10.0, metavar="S",
                   help="wait up to S seconds for a subscriber on both topics before playing (default 10)")
    p.add_argument("--write-params", type=output_file, default=None, metavar="FILE",
                   help="write the node's parameter file for this recording and exit (no ROS needed)")
    p.add_argument("--voxel-size", type=positive_float, default=None,
                   help="with --write-params: the grid's voxel edge in metres (default 0.05 or the "
                   "recording's)")
    p.add_argument("--threshold", type=unit_interval, default=None,
                   help="with --write-params: the node's occupied threshold (default the node's, 0.4)")
    p.add_argument("--backend", type=backend_name, default=None,
                   help="with --write-params: the node's backend (default auto)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    return p


def _pose_msg(pose_type: str, T: np.ndarray, stamp, world_frame: str, sonar_frame: str):
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


def main(argv: list[str] | None = None) -> int:
    """``gpumap ros-play``: publish the recording, then exit 0."""
    from gpumap.ros.node import _split_ros_args

    argv = list(sys.argv[1:] if argv is None else argv)
    ours, ros_args = _split_ros_args(argv)
    p = _parser()
    a = p.parse_args(ours)
    from gpumap.cli import refuse_without

    refuse_without(p, "--write-params", a.write_params is not None,
                   {"--voxel-size": a.voxel_size is not None, "--threshold": a.threshold is not None,
                    "--backend": a.backend is not None})
    play = open_playable(a.recording, static=a.static, stride=a.stride, max_frames=a.max_frames)
    if a.write_params is not None:
        from gpumap.ros.node import PARAMETERS

        thr = PARAMETERS["threshold"][0] if a.threshold is None else a.threshold
        out = write_params(a.write_params, play, voxel_size_m=a.voxel_size, threshold=thr,
                           backend=a.backend or "auto", world_frame=a.world_frame, pose_type=a.pose_type)
        print(f"wrote {out} (start the node with: gpumap ros --params-file {out})")
        return 0

    from gpumap.ros import start_ros_cli

    if not start_ros_cli("gpumap ros-play"):
        return 2
    import rclpy
    from geometry_msgs.msg import PoseStamped
    from nav_msgs.msg import Odometry
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    from rclpy.signals import SignalHandlerOptions
    from sensor_msgs.msg import Image
    from std_msgs.msg import UInt64
    from tqdm import tqdm

    from gpumap.ros.convert import image_msg, stamp_of

    # Ctrl-C is a KeyboardInterrupt here (gpumap's one line, exit 130), not a shutdown behind our back
    rclpy.init(args=["gpumap_ros_play", *ros_args], signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node("gpumap_ros_play")
    try:
        sensor = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT,
                            durability=DurabilityPolicy.VOLATILE, history=HistoryPolicy.KEEP_LAST)
        reliable = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                              durability=DurabilityPolicy.VOLATILE, history=HistoryPolicy.KEEP_LAST)
        pub_img = node.create_publisher(Image, "sonar/image", sensor)
        pub_pose = node.create_publisher(Odometry if a.pose_type == "odometry" else PoseStamped,
                                         "sonar/pose", reliable)
        # how many images went out, said once at the end (reliable, kept for a late reader): the node
        # counts those that never reached it after its last one (dropped.lost_at_stream_end)
        pub_sent = node.create_publisher(UInt64, "sonar/images_sent", QoSProfile(
            depth=10, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL,
            history=HistoryPolicy.KEEP_LAST))
        deadline = time.monotonic() + a.wait_subscribers
        while time.monotonic() < deadline and (pub_img.get_subscription_count() == 0
                                               or pub_pose.get_subscription_count() == 0):
            time.sleep(0.05)
        if pub_img.get_subscription_count() == 0:
            node.get_logger().warning(f"no subscriber on {pub_img.topic_name} after {a.wait_subscribers} s: "
                                      "playing anyway")
        else:
            time.sleep(0.3)  # both ends of the match settle before the first best-effort image
        clock = node.get_clock()
        t0_rec = None
        n = 0
        period = 1.0 / (a.hz * a.rate)
        frames = list(play.frames()) if a.preload else play.frames()
        t0_wall = time.monotonic()
        for fr in tqdm(frames, total=play.count, unit="ping", disable=a.no_progress, desc="ros-play"):
            if fr.t_s is not None and t0_rec is None:
                t0_rec = fr.t_s
            due = t0_wall + ((fr.t_s - t0_rec) / a.rate if fr.t_s is not None and t0_rec is not None
                             else n * period)
            wait = due - time.monotonic()
            if wait > 0:
                time.sleep(wait)
            now_ns = clock.now().nanoseconds
            stamp = stamp_of(now_ns)
            pub_pose.publish(_pose_msg(a.pose_type, fr.T_W_S, stamp, a.world_frame, a.sonar_frame))
            pub_img.publish(image_msg(fr.image, now_ns, a.sonar_frame, a.encoding))
            n += 1
        dt = time.monotonic() - t0_wall
        pub_sent.publish(UInt64(data=n))
        time.sleep(0.5)  # let the last messages leave before the publishers go
        print(f"gpumap ros-play: published {n} pings in {dt:.2f} s ({n / max(dt, 1e-9):.1f} /s); left out "
              f"{play.skipped}", file=sys.stderr)
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0
