"""Sonar recordings in, maps out: readers that stream :class:`SonarFrame` objects, and PLY export.

``open_recording(path)`` sniffs the format:

- a directory with fan PNGs (``sonar/*.png``) and ``sonar_poses.csv`` -> :func:`open_fan_folder`
- a ROS 1 ``.bag``, a ROS 2 bag directory (``metadata.yaml``) or ``.mcap`` -> :func:`open_rosbag`
- a file starting ``DDF`` -> :func:`open_aris`
- a file starting with the ``.oculus`` log magic ``0x11223344`` -> :func:`open_oculus_log`
- a file starting with the Oculus message id ``0x4f53`` -> :func:`open_oculus_raw`

Every reader yields a frame only once it is fully read and validated; a truncated or
corrupt file raises :class:`FormatError` (a ``ValueError``) naming the byte offset.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from gpumap.io.aris import open_aris, write_aris
from gpumap.io.fan import FanGeometry, fan_to_polar, open_fan_folder, polar_to_fan
from gpumap.io.frame import FormatError, Recording, SonarFrame
from gpumap.io.oculus import (
    decode_message,
    encode_simple_ping,
    open_oculus_log,
    open_oculus_raw,
    write_oculus_log,
)
from gpumap.io.ply import read_ply, write_ply

__all__ = [
    "FanGeometry",
    "FormatError",
    "Recording",
    "SonarFrame",
    "decode_message",
    "encode_simple_ping",
    "fan_to_polar",
    "open_aris",
    "open_fan_folder",
    "open_oculus_log",
    "open_oculus_raw",
    "open_recording",
    "open_rosbag",
    "polar_to_fan",
    "read_ply",
    "write_aris",
    "write_oculus_log",
    "write_ply",
]


def open_rosbag(path: str | os.PathLike, **kwargs: Any) -> Recording:
    """See :func:`gpumap.io.rosbag.open_rosbag` (imported lazily: it needs ``rosbags``)."""
    from gpumap.io.rosbag import open_rosbag as _open

    return _open(path, **kwargs)


def open_recording(path: str | os.PathLike, **kwargs: Any) -> Recording:
    """Open any supported recording, choosing the reader from its contents.

    Parameters
    ----------
    path : path-like
        File or directory.
    **kwargs
        Passed to the reader (e.g. ``vfov_deg``, ``geom``, ``image_topic``).

    Raises
    ------
    FormatError
        If the format is not recognised (the message lists what was looked for).
    FileNotFoundError
        If ``path`` does not exist.
    """
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"Expected a recording at {p}, but nothing is there")
    if p.is_dir():
        if (p / "metadata.yaml").is_file():
            return open_rosbag(p, **kwargs)
        img_dir = p / "sonar" if (p / "sonar").is_dir() else p
        if any(f.suffix.lower() == ".png" for f in img_dir.iterdir()):
            return open_fan_folder(p, **kwargs)
        raise FormatError("expected a ROS 2 bag (metadata.yaml) or a folder of fan PNGs, but "
                          "found neither", path=str(p))
    with open(p, "rb") as f:
        head = f.read(16)
    if head.startswith(b"#ROSBAG") or p.suffix in (".bag", ".mcap", ".db3"):
        return open_rosbag(p, **kwargs)
    if head[:3] == b"DDF":
        return open_aris(p, **kwargs)
    if head[:4] == (0x11223344).to_bytes(4, "little"):
        return open_oculus_log(p, **kwargs)
    if head[:2] == (0x4F53).to_bytes(2, "little"):
        return open_oculus_raw(p, **kwargs)
    raise FormatError(
        f"expected a recording (Oculus messages 'SO', .oculus log 0x11223344, ARIS 'DDF', ROS "
        f"bag), but the file starts with {head[:8]!r}", offset=0, path=str(p)
    )
