"""``gpumap ros``: the ROS 2 node (:mod:`gpumap.ros.node`) that maps live sonar pings, run
until Ctrl-C or SIGTERM ([ros] extra)."""

from __future__ import annotations

import sys
import time

from gpumap.commands.common import ArgumentParser, existing_file
from gpumap.ros import split_ros_args, start_ros_cli
from gpumap.ros.launch import ros_arguments
from gpumap.ros.node import PARAMETERS, make_node

__all__ = ["main"]


def _parser():
    p = ArgumentParser(prog="gpumap ros", description=(
        "A ROS 2 node (named gpumap) that maps live sonar pings: subscribes sonar/image and sonar/pose, "
        "publishes ~/occupied_cloud, ~/occupied_markers, ~/projected_map and /diagnostics, serves "
        "~/save_map and ~/reset. Parameters go after --ros-args as in any ROS 2 node "
        "(-p name:=value, --params-file FILE); gpumap ros --list-params prints them all."))
    p.add_argument("--params-file", type=existing_file, default=None, metavar="FILE",
                   help="YAML parameter file, the same as --ros-args --params-file FILE")
    p.add_argument("--list-params", action="store_true",
                   help="print every parameter with its default and exit")
    return p


def main(argv: list[str] | None = None) -> int:
    """``gpumap ros``: run the node until Ctrl-C or SIGTERM."""
    argv = list(sys.argv[1:] if argv is None else argv)
    ours, ros_args = split_ros_args(argv)
    a = _parser().parse_args(ours)
    if a.list_params:
        for name, (default, desc) in PARAMETERS.items():
            print(f"{name} (default {default!r}): {desc}")
        return 0
    if not start_ros_cli("gpumap ros"):
        return 2
    import rclpy
    from rclpy.executors import ExternalShutdownException

    rclpy.init(args=["gpumap_ros", *ros_arguments(a.params_file, ros_args)])
    node = None
    try:
        node = make_node()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            t0 = time.monotonic()
            node.shutdown()
            s = node.diagnostics()
            print(f"gpumap ros: stopped after {s['integrated']} pings mapped; rejected {s['rejected']}, "
                  f"skipped {s['skipped']}, dropped {s['dropped']} (shutdown {time.monotonic() - t0:.2f} s)",
                  file=sys.stderr)
            node.destroy_node()
        rclpy.try_shutdown()
    return 0
