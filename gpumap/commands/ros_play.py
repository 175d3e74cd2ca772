"""``gpumap ros-play``: publish a recording as the ROS 2 node's sonar topics (``sonar/pose``,
``sonar/image``) at its recorded rate or faster, or write the node's parameter file for it
([ros] extra)."""

from __future__ import annotations

import sys
import time

from gpumap.commands.common import (
    ArgumentParser,
    backend_name,
    nonnegative_float,
    output_file,
    positive_float,
    positive_int,
    refuse_without,
    unit_interval,
)
from gpumap.ros import split_ros_args, start_ros_cli
from gpumap.ros.node import PARAMETERS
from gpumap.ros.play import open_playable, pose_msg, write_params

__all__ = ["main"]


def _parser():
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


def main(argv: list[str] | None = None) -> int:
    """``gpumap ros-play``: publish the recording, then exit 0."""
    argv = list(sys.argv[1:] if argv is None else argv)
    ours, ros_args = split_ros_args(argv)
    p = _parser()
    a = p.parse_args(ours)
    refuse_without(p, "--write-params", a.write_params is not None,
                   {"--voxel-size": a.voxel_size is not None, "--threshold": a.threshold is not None,
                    "--backend": a.backend is not None})
    play = open_playable(a.recording, static=a.static, stride=a.stride, max_frames=a.max_frames)
    if a.write_params is not None:
        thr = PARAMETERS["threshold"][0] if a.threshold is None else a.threshold
        out = write_params(a.write_params, play, voxel_size_m=a.voxel_size, threshold=thr,
                           backend=a.backend or "auto", world_frame=a.world_frame, pose_type=a.pose_type)
        print(f"wrote {out} (start the node with: gpumap ros --params-file {out})")
        return 0

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
            pub_pose.publish(pose_msg(a.pose_type, fr.T_W_S, stamp, a.world_frame, a.sonar_frame))
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
