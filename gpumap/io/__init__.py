"""Sonar recordings in, maps out: readers that stream :class:`SonarFrame` objects, and PLY export.

``open_recording(path)`` decides the reader by content (magic bytes), then checks that a
telling file extension agrees (a mismatch is a :class:`FormatError` saying both):

- a directory with ``metadata.yaml`` (ROS 2 bag) -> :func:`open_rosbag`
- a directory with fan PNGs (``sonar/*.png``) and ``sonar_poses.csv`` -> :func:`open_fan_folder`
- a file starting ``#ROSBAG V2.0`` (ROS 1, ``.bag``), ``\\x89MCAP0`` (``.mcap``) or
  ``SQLite format 3`` (``.db3``) -> :func:`open_rosbag`
- a file starting ``DDF`` (``.aris``, ``.ddf``) -> :func:`open_aris`
- a file starting with the ``.oculus`` log magic ``0x11223344`` (``.oculus``) -> :func:`open_oculus_log`
- a file starting with the Oculus message id ``0x4f53`` -> :func:`open_oculus_raw`

One error family: every reader raises :class:`FormatError` (a ``ValueError``; its
``offset`` is the byte where the problem is, when one applies) for anything wrong with a
file, and :class:`LimitError` (a ``FormatError``) when a size the file declares is beyond
a budget of :mod:`gpumap.limits` -- checked before allocating. Library errors (Pillow,
rosbags, zlib, csv) are wrapped, never passed through. A path that does not exist is a
``FileNotFoundError``. Every reader yields a frame only once it is fully read and
validated, so a truncated or corrupt file gives its whole frames, then the error.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from gpumap.errors import MissingFileError
from gpumap.io.aris import open_aris, write_aris
from gpumap.io.fan import FanGeometry, fan_to_polar, open_fan_folder, polar_to_fan
from gpumap.io.frame import FormatError, LimitError, Recording, SonarFrame
from gpumap.io.octomap import write_octomap_bt as write_octomap_bt  # OctoMap .bt export (issue #14)
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
    "LimitError",
    "MissingFileError",
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
    "sniff",
    "write_aris",
    "write_oculus_log",
    "write_ply",
]


def open_rosbag(path: str | os.PathLike, **kwargs: Any) -> Recording:
    """See :func:`gpumap.io.rosbag.open_rosbag` (imported lazily: it needs ``rosbags``)."""
    from gpumap.io.rosbag import open_rosbag as _open

    return _open(path, **kwargs)


# (kind, magic at byte 0, name for messages); the first match decides
_MAGIC: tuple[tuple[str, bytes, str], ...] = (
    ("ros1", b"#ROSBAG V2.0", "a ROS 1 bag ('#ROSBAG V2.0')"),
    ("mcap", b"\x89MCAP0\r\n", "an MCAP file (ROS 2 bag)"),
    ("db3", b"SQLite format 3\x00", "an SQLite file (ROS 2 .db3 bag)"),
    ("aris", b"DDF", "an ARIS/DIDSON file ('DDF')"),
    ("oculus-log", (0x11223344).to_bytes(4, "little"), "a ViewPoint .oculus log (0x11223344)"),
    ("oculus-raw", (0x4F53).to_bytes(2, "little"), "Oculus network messages (0x4f53)"),
    ("png", b"\x89PNG\r\n\x1a\n", "a PNG picture"),
)
_BY_EXTENSION = {".bag": "ros1", ".mcap": "mcap", ".db3": "db3", ".aris": "aris", ".ddf": "aris",
                 ".oculus": "oculus-log", ".png": "png"}


def sniff(path: str | os.PathLike) -> str | None:
    """The kind of recording a file holds, from its first bytes (``None`` if not recognised).

    One of ``"ros1"``, ``"mcap"``, ``"db3"``, ``"aris"``, ``"oculus-log"``, ``"oculus-raw"``,
    ``"png"``.
    """
    with open(path, "rb") as f:
        head = f.read(16)
    for kind, magic, _name in _MAGIC:
        if head.startswith(magic):
            return kind
    return None


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
        If the format is not recognised (the message lists what was looked for), or the
        file's extension names another format than its content.
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
    if not p.is_file():  # a FIFO would block the read below; a device has no end
        raise FormatError("expected a regular file or a folder, but this is neither (a pipe, "
                          "socket or device)", path=str(p))
    with open(p, "rb") as f:
        head = f.read(16)
    kind = sniff(p)
    names = {k: n for k, _m, n in _MAGIC}
    claimed = _BY_EXTENSION.get(p.suffix.lower())
    if kind is None:
        looked = "; ".join(n for _k, _m, n in _MAGIC)
        if claimed is not None:
            raise FormatError(f"expected {names[claimed]} as the extension {p.suffix!r} says, but the "
                              f"file starts with {head[:8]!r}", offset=0, path=str(p))
        raise FormatError(f"expected a recording ({looked}), but the file starts with {head[:8]!r}",
                          offset=0, path=str(p))
    if claimed is not None and claimed != kind:
        raise FormatError(f"expected {names[claimed]} as the extension {p.suffix!r} says, but the "
                          f"content is {names[kind]} (starts with {head[:8]!r}): rename the file",
                          offset=0, path=str(p))
    if kind == "png":
        raise FormatError("expected a recording, but this is a single PNG picture: open the folder "
                          "of fan pictures (with sonar_poses.csv) instead", offset=0, path=str(p))
    if kind == "ros1" and p.suffix != ".bag":
        raise FormatError("expected a ROS 1 bag to be named '*.bag' (the bag library picks its "
                          f"reader by extension), but it is named {p.name!r}: rename it", offset=0,
                          path=str(p))
    if kind in ("ros1", "mcap", "db3"):
        return open_rosbag(p, **kwargs)
    if kind == "aris":
        return open_aris(p, **kwargs)
    if kind == "oculus-log":
        return open_oculus_log(p, **kwargs)
    return open_oculus_raw(p, **kwargs)
