"""Sonar recordings in, maps out: readers that stream :class:`SonarFrame` objects, and PLY export.

``open_recording(path)`` decides the reader by content (magic bytes), then checks that a
telling file extension agrees (a mismatch is a :class:`FormatError` saying both):

- a directory with ``metadata.yaml`` (ROS 2 bag) -> :func:`open_rosbag`
- a directory with ``Config.json`` and ``Data/`` (HoloOcean layout: NeuSIS, AONeuS) ->
  :func:`open_holoocean`
- a directory with fan PNGs (``sonar/*.png``) and ``sonar_poses.csv`` -> :func:`open_fan_folder`
- a directory with ``sonar/*.png`` and ``son_poses.pkl`` (the public OASIS tank folder as its
  authors ship it), or a clone's root with one ``data/<name>/son_poses.pkl`` ->
  :func:`open_oasis_folder`
- a file starting ``#ROSBAG V2.0`` (ROS 1, ``.bag``), ``\\x89MCAP0`` (``.mcap``) or
  ``SQLite format 3`` (``.db3``) -> :func:`open_rosbag`
- a file starting ``DDF`` (``.aris``, ``.ddf``) -> :func:`open_aris`
- a file starting with the ``.oculus`` log magic ``0x11223344`` (``.oculus``) -> :func:`open_oculus_log`
- a file starting with the Oculus message id ``0x4f53`` -> :func:`open_oculus_raw`

:func:`recording_kind` answers which of these a path is without opening it, and
:func:`reader_options` turns a command's generic options (mirrored fans, vertical aperture,
stride, skipping bad frames) into the keyword arguments of the reader it picks.

Pickles (OASIS poses, HoloOcean frames) are read by :func:`gpumap.io.safe_pickle.load_pickle`,
which accepts containers and numeric arrays only and refuses anything else without running it.

One error family: every reader raises :class:`FormatError` (a ``ValueError``; its
``offset`` is the byte where the problem is, when one applies) for anything wrong with a
file, and :class:`LimitError` (a ``FormatError``) when a size the file declares is beyond
a budget of :mod:`gpumap.limits` -- checked before allocating. Library errors (Pillow,
rosbags, zlib, csv) are wrapped, never passed through. A path that does not exist is a
``FileNotFoundError``. Every reader yields a frame only once it is fully read and
validated, so a truncated or corrupt file gives its whole frames, then the error.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

from gpumap.errors import MissingFileError
from gpumap.io.aris import open_aris, write_aris
from gpumap.io.fan import FanGeometry, fan_to_polar, open_fan_folder, polar_to_fan
from gpumap.io.frame import FormatError, LimitError, Recording, SonarFrame
from gpumap.io.holoocean import open_holoocean
from gpumap.io.oasis import open_oasis_folder
from gpumap.io.octomap import write_octomap_bt as write_octomap_bt  # OctoMap .bt export (issue #14)
from gpumap.io.oculus import (
    decode_message,
    encode_simple_ping,
    open_oculus_log,
    open_oculus_raw,
    write_oculus_log,
)
from gpumap.io.ply import read_ply, write_ply
from gpumap.io.safe_pickle import load_pickle
from gpumap.spec import SonarSpec

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
    "load_pickle",
    "open_aris",
    "open_fan_folder",
    "open_holoocean",
    "open_oasis_folder",
    "open_oculus_log",
    "open_oculus_raw",
    "open_recording",
    "open_rosbag",
    "polar_to_fan",
    "read_ply",
    "reader_options",
    "recording_kind",
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
        kind = recording_kind(p)
        if kind == "rosbag":
            return open_rosbag(p, **kwargs)
        if kind == "holoocean":
            return open_holoocean(p, **kwargs)
        if kind == "oasis":
            return open_oasis_folder(_oasis_root(p), **kwargs)
        return open_fan_folder(p, **kwargs)
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


FOLDER_KINDS = ("rosbag", "holoocean", "oasis", "fan-folder")
"""What :func:`recording_kind` calls a folder; a file is one of :func:`sniff`'s kinds."""
FAN_KINDS = ("fan-folder", "oasis")
"""The kinds whose pings are Cartesian fan pictures (``flip_lr``/``flip_ud`` apply)."""
SKIPPABLE_KINDS = ("fan-folder", "oasis", "holoocean")
"""The kinds made of one file per frame: a bad frame can be skipped (``on_bad``), and the
reader itself can stride over frames without reading them."""


def _oasis_root(p: Path) -> Path:
    """The folder holding ``son_poses.pkl``: ``p`` itself, or a clone root's one ``data/<name>/``."""
    from gpumap.io.oasis import POSES_FILE

    if (p / POSES_FILE).is_file():
        return p
    data = p / "data"
    found = sorted(d for d in data.iterdir() if (d / POSES_FILE).is_file()) if data.is_dir() else []
    if len(found) != 1:
        raise FormatError(f"expected one data/<name>/{POSES_FILE} in a clone of the OASIS repository, "
                          f"but found {len(found)}: open the dataset's folder itself", path=str(p))
    return found[0]


def recording_kind(path: str | os.PathLike) -> str:
    """Which reader :func:`open_recording` would use for ``path``, from its contents (nothing decoded).

    Parameters
    ----------
    path : path-like
        File or folder.

    Returns
    -------
    str
        For a folder: ``"rosbag"`` (``metadata.yaml``), ``"holoocean"`` (``Config.json`` and
        ``Data/``), ``"fan-folder"`` (PNGs in ``sonar/`` or the folder itself; chosen over
        ``"oasis"`` when ``sonar_poses.csv`` is there), ``"oasis"`` (``son_poses.pkl`` beside
        ``sonar/``, or a clone's root with one ``data/<name>/son_poses.pkl``). For a file: the
        kind :func:`sniff` reads from its first bytes (``"ros1"``, ``"mcap"``, ``"db3"``,
        ``"aris"``, ``"oculus-log"``, ``"oculus-raw"``, ``"png"``).

    Raises
    ------
    FormatError
        If it is none of these (the message lists what was looked for).
    FileNotFoundError
        If ``path`` does not exist.
    """
    from gpumap.io.holoocean import CONFIG_FILE, DATA_DIR
    from gpumap.io.oasis import POSES_FILE

    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"Expected a recording at {p}, but nothing is there")
    if p.is_dir():
        if (p / "metadata.yaml").is_file():
            return "rosbag"
        if (p / CONFIG_FILE).is_file() and (p / DATA_DIR).is_dir():
            return "holoocean"
        if (p / "sonar_poses.csv").is_file():
            return "fan-folder"
        if (p / POSES_FILE).is_file() or (p / "data").is_dir() and any(
                (d / POSES_FILE).is_file() for d in (p / "data").iterdir()):
            return "oasis"
        img_dir = p / "sonar" if (p / "sonar").is_dir() else p
        if any(f.suffix.lower() == ".png" for f in img_dir.iterdir()):
            return "fan-folder"
        raise FormatError("expected a ROS 2 bag (metadata.yaml), a HoloOcean dataset (Config.json and "
                          "Data/), the OASIS tank folder (sonar/ and son_poses.pkl) or a folder of fan "
                          "PNGs, but found none of these", path=str(p))
    if not p.is_file():
        raise FormatError("expected a regular file or a folder, but this is neither (a pipe, socket or "
                          "device)", path=str(p))
    kind = sniff(p)
    if kind is None:
        with open(p, "rb") as f:
            head = f.read(8)
        looked = "; ".join(n for _k, _m, n in _MAGIC)
        raise FormatError(f"expected a recording ({looked}), but the file starts with {head!r}", offset=0,
                          path=str(p))
    return kind


def reader_options(
    path: str | os.PathLike,
    *,
    flip_lr: bool = False,
    flip_ud: bool = False,
    vfov_deg: float | None = None,
    stride: int = 1,
    on_bad=None,
    reader_stride: bool = True,
) -> tuple[dict[str, Any], int]:
    """The reader's keyword arguments for a command's generic options, and the stride left to apply.

    Parameters
    ----------
    path : path-like
        The recording (its kind is :func:`recording_kind`'s).
    flip_lr, flip_ud : bool
        Mirror fan pictures left-right / up-down (fan kinds only).
    vfov_deg : float, optional
        Vertical aperture, degrees, instead of the recording's own (every kind).
    stride : int
        Use every ``stride``-th frame.
    on_bad : callable, optional
        ``on_bad(error)`` for a frame that cannot be read, which is then skipped (kinds with one
        file per frame only: :data:`SKIPPABLE_KINDS`).
    reader_stride : bool
        Let the reader apply ``stride`` where it can skip frames unread (False when the caller
        selects frames first and strides after).

    Returns
    -------
    kwargs : dict
        For ``open_recording(path, **kwargs)``.
    stride : int
        The stride the caller still applies to the frames (1 when the reader took it).

    Raises
    ------
    ValueError
        If an option does not apply to this kind (the message names both).
    FormatError, FileNotFoundError
        As :func:`recording_kind`.
    """
    from gpumap.io.fan import OASIS_SPEC, FanGeometry

    kind = recording_kind(path)
    kwargs: dict[str, Any] = {}
    if (flip_lr or flip_ud) and kind not in FAN_KINDS:
        raise ValueError(f"Expected flip_lr/flip_ud only for fan pictures ({', '.join(FAN_KINDS)}), "
                         f"but {path} is {kind!r}")
    if on_bad is not None and kind not in SKIPPABLE_KINDS:
        raise ValueError(f"Expected a recording of one file per frame ({', '.join(SKIPPABLE_KINDS)}) to skip "
                         f"bad frames one by one, but {path} is {kind!r}")
    if kind in FAN_KINDS:
        if flip_lr or flip_ud:
            kwargs["geom"] = FanGeometry(flip_lr=bool(flip_lr), flip_ud=bool(flip_ud))
        if vfov_deg is not None:
            kwargs["spec"] = SonarSpec(OASIS_SPEC.range_min_m, OASIS_SPEC.range_max_m, OASIS_SPEC.n_bins,
                                       OASIS_SPEC.bearings_rad, math.radians(vfov_deg))
    elif vfov_deg is not None:
        kwargs["vfov_deg"] = vfov_deg
    if on_bad is not None:
        kwargs["on_bad"] = on_bad
    if kind in SKIPPABLE_KINDS and reader_stride:
        kwargs["stride"] = stride
        stride = 1
    return kwargs, stride
