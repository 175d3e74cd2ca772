"""What the node's launch needs outside the node: Fast DDS segment hints, the lost-message count at a
stream's end, the ROS arguments of a parameters file.
"""

from __future__ import annotations

__all__ = ["ros_arguments"]


FASTDDS_DEFAULT_SEGMENT_BYTES = 512 * 1024
FASTDDS_HINT = ("a publisher on Fast DDS's defaults (a 512 KiB shared-memory segment) loses most images "
                "larger than that; start it with FASTDDS_DEFAULT_PROFILES_FILE pointing at a profile with a "
                "larger segment (gpumap/ros/fastdds_shm.xml, as gpumap ros-play uses) or send mono8")


#: Bytes of a DDS GUID naming its participant: a node's publishers (ros-play's images and its count)
#: share them.
PARTICIPANT_PREFIX = 12


def lost_at_stream_end(sent: dict[bytes, int], last_seq: dict[bytes, int]) -> int:
    """Images a publisher said it sent (``sent``: participant prefix -> count, from
    ``sonar/images_sent``) after the last one that reached the node (``last_seq``: publisher gid ->
    the highest sequence number delivered; a publisher's first message is number 1)."""
    n = 0
    for prefix, count in sent.items():
        last = max((q for g, q in last_seq.items() if g[:PARTICIPANT_PREFIX] == prefix), default=0)
        n += max(0, count - last)
    return n


def ros_arguments(params_file, ros_args: list[str]) -> list[str]:
    """The ROS arguments: ``--params-file FILE`` (``gpumap ros --params-file``) first, then the
    user's ``--ros-args ...``, so that a ``-p name:=value`` given there wins over the file (ROS
    applies parameter sources in order, the last one winning)."""
    if params_file is None:
        return list(ros_args)
    return ["--ros-args", "--params-file", str(params_file), *ros_args[1:]]
