"""gpumap on a ROS 2 vehicle: a node that maps live pings (``gpumap ros``) and a player that
publishes any recording gpumap reads as those topics (``gpumap ros-play``).

The ROS 2 wheels (Kilted, from PyPI) come with the ``[ros]`` extra:
``pip install 'gpumap[ros]'``. What does not need ROS is importable without it:

- :mod:`gpumap.ros.live`: the pose buffer (SE(3) interpolation at an image's stamp) and
  :class:`~gpumap.ros.live.LiveMapper`, the worker that integrates queued pings with
  ``integrate_batch`` and counts every ping it drops, skips or rejects, by reason;
- :mod:`gpumap.ros.convert`: ROS messages to and from arrays (images, poses, point clouds,
  the 2-D obstacle projection, marker blocks); it imports the message packages lazily.

:mod:`gpumap.ros.node` (the node) and :mod:`gpumap.ros.play` (the player's recordings) need
``rclpy``; the commands that run them are :mod:`gpumap.commands.ros` and
:mod:`gpumap.commands.ros_play`.
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["FASTDDS_PROFILE", "ROS_EXTRA_HINT", "require_ros", "split_ros_args", "start_ros_cli",
           "use_gpumap_fastdds_profile"]

#: Fast DDS profile for sonar-sized messages (a 32 MiB shared-memory segment; see the file).
FASTDDS_PROFILE = Path(__file__).with_name("fastdds_shm.xml")

#: What to run when the ROS 2 wheels are missing.
ROS_EXTRA_HINT = "pip install 'gpumap[ros]' (the ROS 2 Kilted wheels from PyPI)"


def require_ros() -> None:
    """Import ``rclpy`` and the message packages, or raise ImportError saying how to get them."""
    try:
        import diagnostic_msgs.msg  # noqa: F401
        import geometry_msgs.msg  # noqa: F401
        import nav_msgs.msg  # noqa: F401
        import rclpy  # noqa: F401
        import sensor_msgs.msg  # noqa: F401
        import std_srvs.srv  # noqa: F401
        import visualization_msgs.msg  # noqa: F401
    except ImportError as e:
        raise ImportError(f"gpumap's ROS 2 node needs the ROS 2 Python wheels: {ROS_EXTRA_HINT} "
                          f"(import failed: {e})") from e


def use_gpumap_fastdds_profile() -> str | None:
    """Point Fast DDS at :data:`FASTDDS_PROFILE` unless the user chose a profile or another RMW.

    Call before ``rclpy.init``. Returns the profile used, or None when left to the user
    (``FASTDDS_DEFAULT_PROFILES_FILE`` set, or ``RMW_IMPLEMENTATION`` not Fast DDS).
    """
    if os.environ.get("FASTDDS_DEFAULT_PROFILES_FILE") or os.environ.get("FASTRTPS_DEFAULT_PROFILES_FILE"):
        return None
    if os.environ.get("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp") != "rmw_fastrtps_cpp":
        return None
    os.environ["FASTDDS_DEFAULT_PROFILES_FILE"] = str(FASTDDS_PROFILE)
    return str(FASTDDS_PROFILE)


def start_ros_cli(prog: str) -> bool:
    """For a ROS command line (``gpumap ros``, ``gpumap ros-play``): check the ROS wheels and point
    Fast DDS at gpumap's profile. False, after a one-line error on stderr, when the wheels are
    missing (the command then exits 2)."""
    import sys

    try:
        require_ros()
    except ImportError as e:
        print(f"{prog}: error: {e}", file=sys.stderr)
        return False
    use_gpumap_fastdds_profile()
    return True


def split_ros_args(argv: list[str]) -> tuple[list[str], list[str]]:
    """``argv`` split at ``--ros-args``: (the command's own flags, the ROS arguments from
    ``--ros-args`` on)."""
    if "--ros-args" in argv:
        i = argv.index("--ros-args")
        return argv[:i], argv[i:]
    return argv, []
