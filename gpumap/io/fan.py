"""Cartesian fan images (a folder of PNGs + a poses CSV, e.g. OASIS tank) <-> polar images.

The fan convention is a parameter (:class:`FanGeometry`). For the OASIS tank data (the
default) the sensor apex is at the bottom centre of a 398 x 722 PNG, pixel = 2.0 / 398 m,
row ``apex_row - i`` holds forward distance ``x = i * pixel`` and column ``j`` holds
lateral ``y = (j - apex_col) * pixel``; ``theta = atan2(y, x)`` in the sonar frame.
``flip_lr`` mirrors the columns (``y -> -y``) and ``flip_ud`` mirrors the rows of the PNG
before that mapping; both exist to test the convention, not because the data needs them.

Conversion back to polar invents nothing: polar cell ``(i, j)`` is the bilinear sample
of the fan at the cell centre ``(r_i, theta_j)`` (``r_i`` the bin centre, ``theta_j`` the
beam's bearing). Samples whose 2x2 neighbourhood leaves the picture use the nearest
edge pixel within half a pixel and 0 beyond. Because the fan was itself rendered from a
polar image, the round trip ``polar -> fan -> polar`` is exact up to the two
interpolations; :func:`polar_to_fan` is provided to measure that (see the tests).

Pictures (:func:`read_grey_png`)
--------------------------------
A picture's size is read from its header and checked (against ``gpumap.limits.
MAX_IMAGE_PIXELS`` and against the fan geometry) before a pixel is decoded. Every PNG
mode becomes grey in ``[0, 1]``: 1-bit as 0/1; 2, 4 and 8-bit grey (``L``) by 1/255;
16-bit grey (``I;16``) by 1/65535; palette (``P``) through the palette's luminance;
``RGB`` through luminance (ITU-R 601-2: ``0.299 R + 0.587 G + 0.114 B``, which leaves a
grey picture stored as RGB unchanged); the alpha of ``LA``, ``PA`` and ``RGBA`` is ignored
(the fan's samples are the colour). A file that is not a PNG, or a corrupt one, is a
:class:`~gpumap.errors.FormatError`.

Pose table (:func:`read_pose_table`)
------------------------------------
``frame,T_W_S_00,...,T_W_S_33`` (row-major 4x4, maps sonar-frame points to world,
metres), optionally ``frame,time_s,T_W_S_00,...``: one row per frame, frames strictly
ascending (time runs forward; a duplicate frame is refused, naming it), times (when given)
finite and strictly ascending, every pose finite and rigid.
"""

from __future__ import annotations

import bisect
import csv
import io
import math
import os
import re
import struct
import zlib
from array import array
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gpumap import limits
from gpumap.errors import check_pose
from gpumap.io.frame import FormatError, LimitError, Recording, SonarFrame, frames_skipping_bad
from gpumap.limits import check_size, declared_product
from gpumap.spec import SonarSpec

__all__ = [
    "FanGeometry",
    "fan_to_polar",
    "open_fan_folder",
    "polar_to_fan",
    "read_grey_png",
    "read_pose_table",
    "read_poses_csv",
]


@dataclass(frozen=True)
class FanGeometry:
    """Where the sonar frame lies in a Cartesian fan picture.

    Parameters
    ----------
    n_rows, n_cols : int
        Picture size, pixels.
    pixel_m : float
        Edge of a (square) pixel, metres.
    apex_row, apex_col : float
        Pixel coordinates of the sensor (row/column index; pixel centres at integers).
    flip_lr : bool
        Column ``j`` holds ``y = -(j - apex_col) * pixel`` instead of ``+``.
    flip_ud : bool
        Mirror the picture's rows before applying the convention.
    """

    n_rows: int = 398
    n_cols: int = 722
    pixel_m: float = 2.0 / 398
    apex_row: float = 397.0
    apex_col: float = 361.0
    flip_lr: bool = False
    flip_ud: bool = False

    def pixel_of(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Sonar-frame (x forward, y left) metres -> fractional (row, col) in the *stored* picture."""
        row = self.apex_row - np.asarray(x) / self.pixel_m
        col = self.apex_col + (-1.0 if self.flip_lr else 1.0) * np.asarray(y) / self.pixel_m
        if self.flip_ud:
            row = (self.n_rows - 1) - row
        return row, col


OASIS_SPEC = SonarSpec.uniform(hfov_deg=130.0, vfov_deg=20.0, n_beams=512, n_bins=398,
                               range_min_m=0.1, range_max_m=2.0)
"""The OASIS tank sonar (Oculus M3000d at 1.2 MHz) as its dataset config describes it."""


class _Bilinear:
    """Bilinear sampling of an ``(h, w)`` picture at fixed fractional ``(row, col)``, precomputed."""

    def __init__(self, shape: tuple[int, int], row: np.ndarray, col: np.ndarray) -> None:
        h, w = shape
        self.shape = (h, w)
        self.inside = (row >= -0.5) & (row <= h - 0.5) & (col >= -0.5) & (col <= w - 0.5)
        r = np.clip(row, 0.0, h - 1.0)
        c = np.clip(col, 0.0, w - 1.0)
        r0 = np.minimum(np.floor(r).astype(np.int64), h - 2)
        c0 = np.minimum(np.floor(c).astype(np.int64), w - 2)
        self.i00 = r0 * w + c0
        self.fr = (r - r0).astype(np.float32)
        self.fc = (c - c0).astype(np.float32)
        self.w = w

    def __call__(self, img: np.ndarray) -> np.ndarray:
        f = np.ascontiguousarray(img, dtype=np.float32).reshape(-1)
        i, w, fr, fc = self.i00, self.w, self.fr, self.fc
        a = f[i] * (1 - fc) + f[i + 1] * fc
        b = f[i + w] * (1 - fc) + f[i + w + 1] * fc
        out = a * (1 - fr) + b * fr
        return np.where(self.inside, out, np.float32(0.0)).astype(np.float32)


def _bilinear(img: np.ndarray, row: np.ndarray, col: np.ndarray) -> np.ndarray:
    return _Bilinear(img.shape, row, col)(img)


def _fan_sampler(spec: SonarSpec, geom: FanGeometry) -> _Bilinear:
    r = spec.bin_centers_m[:, None]
    th = spec.bearings_rad[None, :]
    row, col = geom.pixel_of(r * np.cos(th), r * np.sin(th))
    return _Bilinear((geom.n_rows, geom.n_cols), row, col)


def fan_to_polar(fan: np.ndarray, spec: SonarSpec, geom: FanGeometry) -> np.ndarray:
    """Sample a Cartesian fan at every polar cell centre.

    Parameters
    ----------
    fan : (n_rows, n_cols) float32
        Fan picture in ``[0, 1]``, stored orientation.
    spec : SonarSpec
        Target polar geometry.
    geom : FanGeometry
        The picture's convention.

    Returns
    -------
    (n_bins, n_beams) float32
        Bilinear samples at ``(bin centre, beam bearing)``.
    """
    f = np.asarray(fan, dtype=np.float32)
    if f.shape != (geom.n_rows, geom.n_cols):
        raise ValueError(f"Expected a fan of shape {(geom.n_rows, geom.n_cols)}, but got {f.shape}")
    return _fan_sampler(spec, geom)(f)


def polar_to_fan(polar: np.ndarray, spec: SonarSpec, geom: FanGeometry) -> np.ndarray:
    """Render a polar image as a Cartesian fan (bilinear in range and bearing; 0 outside).

    Parameters
    ----------
    polar : (n_bins, n_beams) float32
    spec : SonarSpec
    geom : FanGeometry

    Returns
    -------
    (n_rows, n_cols) float32
    """
    p = np.asarray(polar, dtype=np.float32)
    rows, cols = np.meshgrid(np.arange(geom.n_rows, dtype=np.float64),
                             np.arange(geom.n_cols, dtype=np.float64), indexing="ij")
    if geom.flip_ud:
        rows = (geom.n_rows - 1) - rows
    x = (geom.apex_row - rows) * geom.pixel_m
    y = (-1.0 if geom.flip_lr else 1.0) * (cols - geom.apex_col) * geom.pixel_m
    r = np.hypot(x, y)
    th = np.arctan2(y, x)
    fi = (r - spec.range_min_m) / spec.bin_size_m - 0.5
    b = spec.bearings_rad
    fj = np.interp(th, b, np.arange(b.size, dtype=np.float64))
    ok = ((r >= spec.range_min_m) & (r < spec.range_max_m) & (th >= spec.beam_edges_rad[0])
          & (th <= spec.beam_edges_rad[-1]))
    out = _bilinear(p, fi, fj)
    return np.where(ok, out, np.float32(0.0)).astype(np.float32)


# ---------------------------------------------------------------- pictures
_GREY_8 = ("L",)
_GREY_16 = ("I;16", "I;16B", "I;16L", "I;16N")
_VIA_LUMA = ("P", "PA", "RGB", "RGBA", "RGBX", "RGBa")
_WITH_GREY_ALPHA = ("LA", "La")
_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
_PIL_ERRORS = (OSError, SyntaxError, ValueError, EOFError, struct.error, zlib.error, IndexError,
               KeyError, TypeError)


def _check_png_chunks(data: bytes, name: str | None) -> None:
    """Refuse a PNG whose size (IHDR) is beyond budget or whose chunks do not fit in the file."""
    n = len(data)
    if n >= 24 and data[12:16] == b"IHDR":
        # the size is in the first chunk: refuse a bomb before Pillow parses anything
        w, h = struct.unpack_from(">II", data, 16)
        check_size(declared_product(w, h), limits.MAX_IMAGE_PIXELS, f"the picture ({w} x {h})",
                   unit="pixels", offset=16, path=name)
    i = len(_PNG_MAGIC)
    while i + 8 <= n:
        (length,) = struct.unpack_from(">I", data, i)
        kind = data[i + 4:i + 8]
        if length > 2**31 - 1 or i + 12 + length > n:
            raise FormatError(f"expected PNG chunk {kind!r} of {length} bytes (+ 12) to fit in the "
                              f"file, but {n - i} bytes are left", i, name)
        i += 12 + length
        if kind == b"IEND":
            return


def read_grey_png(
    source: str | os.PathLike | bytes,
    *,
    expected_shape: tuple[int, int] | None = None,
    formats: tuple[str, ...] = ("PNG",),
    path: str | None = None,
) -> np.ndarray:
    """Decode a picture to grey float32 in ``[0, 1]``, checking its size before decoding.

    Parameters
    ----------
    source : path-like or bytes
        The file, or its bytes.
    expected_shape : (rows, cols), optional
        The size the picture must have; checked from the header, before decoding.
    formats : tuple of str
        Pillow formats accepted (default PNG only).
    path : str, optional
        Name for error messages when ``source`` is bytes.

    Returns
    -------
    (rows, cols) float32
        Grey levels (see the module notes for each mode).

    Raises
    ------
    LimitError
        If the header declares more than ``gpumap.limits.MAX_IMAGE_PIXELS`` pixels.
    FormatError
        If it is not such a picture, is corrupt or truncated, has an unsupported mode, or
        is not ``expected_shape``.
    """
    from PIL import Image  # lazy: only the picture readers need Pillow

    name = path if path is not None else (None if isinstance(source, bytes) else os.fspath(source))
    fmt = "/".join(formats)
    if isinstance(source, bytes):
        data = source
    else:
        with open(source, "rb") as f:
            check_size(os.fstat(f.fileno()).st_size, limits.MAX_ITEM_BYTES, "the picture file",
                       path=name)
            data = f.read()
    if data.startswith(_PNG_MAGIC):
        _check_png_chunks(data, name)
    try:
        # from memory: a length field Pillow believes can never make it allocate more than the file
        im = Image.open(io.BytesIO(data), formats=list(formats))
    except (Image.DecompressionBombError, Image.DecompressionBombWarning) as e:
        raise LimitError(f"expected a {fmt} picture within Pillow's decompression-bomb limit, but "
                         f"{e}", 0, name) from None
    except FileNotFoundError:
        raise
    except _PIL_ERRORS as e:
        raise FormatError(f"expected a {fmt} picture, but Pillow cannot open it ({e})", 0,
                          name) from None
    with im:
        w, h = im.size
        # the header's size, before a pixel is decoded
        check_size(declared_product(w, h), limits.MAX_IMAGE_PIXELS,
                   f"the picture ({w} x {h})", unit="pixels", offset=16, path=name)
        if expected_shape is not None and (h, w) != tuple(expected_shape):
            raise FormatError(f"expected a {expected_shape[0]} x {expected_shape[1]} picture (rows x "
                              f"columns), but its header says {h} x {w}", 16, name)
        mode = im.mode
        try:
            if mode == "1":
                a = np.asarray(im, dtype=np.float32)  # bool -> 0 / 1
            elif mode in _GREY_8:
                a = np.asarray(im, dtype=np.float32) / np.float32(255.0)
            elif mode in _GREY_16:
                a = np.asarray(im).astype(np.float32) / np.float32(65535.0)
            elif mode == "I":
                raw = np.asarray(im)
                if raw.size and (raw.min() < 0 or raw.max() > 65535):
                    raise FormatError(f"expected 16-bit grey levels in mode I, but got "
                                      f"{raw.min()}..{raw.max()}", None, name)
                a = raw.astype(np.float32) / np.float32(65535.0)
            elif mode in _WITH_GREY_ALPHA:
                a = np.asarray(im.getchannel(0), dtype=np.float32) / np.float32(255.0)
            elif mode in _VIA_LUMA:
                if mode in ("P", "PA"):  # the palette's colours (transparency dropped below)
                    im = im.convert("RGBA")
                a = np.asarray(im.convert("L"), dtype=np.float32) / np.float32(255.0)
            else:
                raise FormatError(f"expected a grey, palette, grey+alpha, RGB or RGBA picture, but "
                                  f"got Pillow mode {mode!r}", None, name)
        except (Image.DecompressionBombError, Image.DecompressionBombWarning) as e:
            raise LimitError(f"expected a picture within Pillow's decompression-bomb limit, but {e}",
                             0, name) from None
        except _PIL_ERRORS as e:
            if isinstance(e, FormatError):
                raise
            raise FormatError(f"expected a complete {fmt} picture, but decoding failed ({e})", None,
                              name) from None
    if a.shape != (h, w):
        raise FormatError(f"expected {h} x {w} decoded pixels, but got {a.shape}", None, name)
    return np.ascontiguousarray(a, dtype=np.float32)


# ---------------------------------------------------------------- pose table
_MAT = [f"T_W_S_{i}{j}" for i in range(4) for j in range(4)]
_INT = re.compile(r"[+-]?[0-9]{1,30}")  # ASCII digits only (int() also takes "1_0" and "\u0663")
_MAX_FRAME = 2**63 - 1  # frames are returned as int64


def read_pose_table(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """Read a pose table (layout in the module notes) and check it.

    The file must be at most ``gpumap.limits.MAX_CSV_BYTES``; rows are stored compactly
    (136 bytes each) as they are parsed and the poses checked together at the end, so the
    largest table costs a few hundred MB, not gigabytes.

    Returns
    -------
    frames : (n,) int64
        Strictly ascending frame numbers.
    times_s : (n,) float64 or None
        Strictly ascending times, seconds, when the table has a ``time_s`` column.
    T_W_S : (n, 4, 4) float64
        Rigid, finite poses.

    Raises
    ------
    FormatError
        Naming the line (and the frame) of the problem: wrong header or field count, a
        field that is not a number, a duplicate frame, frames or times out of order, a
        non-finite or non-rigid pose (the first such line of each kind).
    LimitError
        If the file is larger than ``gpumap.limits.MAX_CSV_BYTES``.
    """
    p = os.fspath(path)
    with open(p, "rb") as fb:
        check_size(os.fstat(fb.fileno()).st_size, limits.MAX_CSV_BYTES, "the pose table", path=p)
        raw = fb.read(limits.MAX_CSV_BYTES + 1)
    check_size(len(raw), limits.MAX_CSV_BYTES, "the pose table", path=p)  # it grew meanwhile
    try:
        return _parse_pose_table(io.TextIOWrapper(io.BytesIO(raw), encoding="utf-8-sig", newline=""), p)
    except UnicodeDecodeError:
        try:
            raw.decode("utf-8-sig")
            at = None
        except UnicodeDecodeError as e:
            at = e.start
        raise FormatError(f"expected a UTF-8 text table, but byte {at} is not", at, p) from None
    except csv.Error as e:
        raise FormatError(f"expected a CSV table, but {e}", path=p) from None


def _parse_pose_table(text: io.TextIOBase, p: str) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    frames = array("q")
    lines = array("q")
    times = array("d")
    vals_all = array("d")
    rd = csv.reader(text)
    header = [h.strip() for h in next(rd, None) or []]
    with_time = len(header) == 18 and header[1] == "time_s"
    if header[:1] != ["frame"] or header[1 + with_time:] != _MAT:
        raise FormatError(f"expected a header 'frame', optionally 'time_s', then {_MAT[0]} .. "
                          f"{_MAT[-1]}, but got {header}", path=p)
    n_fields = 17 + with_time
    isfinite = math.isfinite
    for row in rd:
        line_no = rd.line_num
        if not row or all(not v.strip() for v in row):
            continue
        if len(row) != n_fields:
            raise FormatError(f"line {line_no}: expected {n_fields} fields, but got {len(row)}", path=p)
        cell = row[0].strip()
        if not _INT.fullmatch(cell):
            raise FormatError(f"line {line_no}: expected numbers, but the frame is {cell[:30]!r} "
                              "(not a decimal integer)", path=p)
        k = int(cell)
        try:
            vals = [float(v) for v in row[1:]]
        except ValueError as e:
            raise FormatError(f"line {line_no}: expected numbers, but {e}", path=p) from None
        if not 0 <= k <= _MAX_FRAME:
            raise FormatError(f"line {line_no}: expected a frame number >= 0 and <= {_MAX_FRAME}, "
                              f"but got {cell[:30]}", path=p)
        if frames and k <= frames[-1]:
            i = bisect.bisect_left(frames, k)  # frames so far are strictly ascending
            if i < len(frames) and frames[i] == k:
                raise FormatError(f"line {line_no}: expected one pose per frame, but frame {k} is "
                                  f"also on line {lines[i]} (duplicate frame)", path=p)
            raise FormatError(f"line {line_no}: expected frames in ascending order (time runs "
                              f"forward), but frame {k} comes after frame {frames[-1]} on line "
                              f"{lines[-1]}", path=p)
        if with_time:
            t = vals.pop(0)
            if not isfinite(t):
                raise FormatError(f"line {line_no}: expected a finite time_s for frame {k}, but "
                                  f"got {t}", path=p)
            if times and t <= times[-1]:
                raise FormatError(f"line {line_no}: expected time_s to increase, but frame {k} "
                                  f"has {t} after {times[-1]} (frame {frames[-1]})", path=p)
            times.append(t)
        if not all(isfinite(v) for v in vals):
            raise FormatError(f"line {line_no}: expected finite pose entries for frame {k}, but "
                              "got NaN or inf", path=p)
        frames.append(k)
        lines.append(line_no)
        vals_all.extend(vals)
    # the parsed values themselves, no copy (the array's buffer stays with the result)
    T = np.frombuffer(vals_all, dtype=np.float64).reshape(-1, 4, 4) if vals_all else np.zeros((0, 4, 4))
    # rigid, checked in blocks (bounded temporaries); a row that is not clearly fine is
    # judged by check_pose itself, whose message and tolerance it gets
    for b0 in range(0, len(T), 1 << 16):
        Tb = T[b0:b0 + (1 << 16)]
        R = Tb[:, :3, :3]
        G = np.einsum("nji,njk->nik", R, R) - np.eye(3)
        det = np.einsum("ni,ni->n", np.cross(R[:, :, 0], R[:, :, 1]), R[:, :, 2])
        last = np.abs(Tb[:, 3] - np.array([0.0, 0.0, 0.0, 1.0])).max(axis=1)
        suspect = (np.abs(G).max(axis=(1, 2)) > 0.5e-5) | (last > 0.5e-5) | (det < 0.5)
        for i in b0 + np.flatnonzero(suspect):
            try:
                check_pose(T[i], f"T_W_S of frame {frames[i]}")
            except ValueError as e:
                raise FormatError(f"line {lines[i]}: {e}", path=p) from None
    return (np.frombuffer(frames, dtype=np.int64).copy() if frames else np.zeros(0, np.int64),
            np.frombuffer(times, dtype=np.float64).copy() if with_time and times else
            (np.zeros(0) if with_time else None), T)


def read_poses_csv(path: str | os.PathLike) -> dict[int, np.ndarray]:
    """``frame, T_W_S_00 .. T_W_S_33`` (row-major) -> {frame: (4, 4) float64}; see :func:`read_pose_table`."""
    frames, _t, T = read_pose_table(path)
    return {int(k): T[i] for i, k in enumerate(frames)}


_NUM = re.compile(r"([0-9]+)")


def open_fan_folder(
    folder: str | os.PathLike,
    *,
    spec: SonarSpec = OASIS_SPEC,
    geom: FanGeometry | None = None,
    poses: str | os.PathLike | None = None,
    image_dir: str = "sonar",
    stride: int = 1,
    on_bad=None,
) -> Recording:
    """Open a folder of Cartesian fan PNGs with a poses CSV (OASIS tank layout by default).

    Parameters
    ----------
    folder : path-like
        Holds ``image_dir/`` (``*.png``, frame number in the name) and ``sonar_poses.csv``.
    spec : SonarSpec
        Polar geometry to sample (default: the OASIS M3000d config, 398 bins x 512 beams).
    geom : FanGeometry, optional
        The pictures' convention (default: OASIS, as documented).
    poses : path-like, optional
        Poses CSV (default ``folder/sonar_poses.csv``; frames without a pose get ``None``).
    stride : int
        Use every ``stride``-th picture.
    on_bad : callable, optional
        ``on_bad(error)`` for a picture that cannot be read (a :class:`FormatError`: truncated,
        corrupt, the wrong size), which is then skipped (``gpumap replay --skip-bad-frames``);
        None (default): the error ends the iteration.

    Notes
    -----
    Pictures are read lazily, one per frame, each checked from its header (size) before it
    is decoded; every PNG mode becomes grey in [0, 1] (see :func:`read_grey_png`). The pose
    table is read and checked when the folder is opened (:func:`read_pose_table`); with a
    ``time_s`` column frames carry it as ``timestamp_s``.

    Raises
    ------
    FormatError
        If there are no pictures, two pictures have the same frame number, or the pose
        table is malformed (at open); if a picture is corrupt or the wrong size (when it is
        reached).
    """
    root = Path(folder)
    geom = geom or FanGeometry()
    img_dir = root / image_dir if (root / image_dir).is_dir() else root
    by_frame: dict[int, Path] = {}
    for f in sorted(img_dir.iterdir()):
        if f.suffix.lower() == ".png":
            if not f.is_file():
                raise FormatError(f"expected fan pictures to be regular files, but {f.name} is not "
                                  "(a folder, pipe or device)", path=str(img_dir))
            m = _NUM.findall(f.stem)
            if m:
                k = int(m[-1])
                if k in by_frame:
                    raise FormatError(f"expected one picture per frame number, but {by_frame[k].name} "
                                      f"and {f.name} are both frame {k}", path=str(img_dir))
                by_frame[k] = f
    if not by_frame:
        raise FormatError(f"expected PNG fan pictures in {img_dir}, but found none", path=str(root))
    if isinstance(stride, bool) or not isinstance(stride, (int, np.integer)) or stride < 1:
        raise ValueError(f"Expected an integer stride >= 1, but got {stride!r}")
    files = sorted(by_frame.items())[:: int(stride)]
    pose_path = Path(poses) if poses is not None else root / "sonar_poses.csv"
    T: dict[int, np.ndarray] = {}
    t_of: dict[int, float] = {}
    if pose_path.is_file():
        fr, ts, Ts = read_pose_table(pose_path)
        T = {int(k): Ts[i] for i, k in enumerate(fr)}
        if ts is not None:
            t_of = {int(k): float(ts[i]) for i, k in enumerate(fr)}
    missing = [f for k, f in files if k not in T]
    has_poses = bool(T) and not missing
    note = None
    if not pose_path.is_file():
        note = f"{pose_path.name} is not there: none of the {len(files)} pictures has a pose"
    elif missing:
        note = (f"{pose_path.name} holds {len(T)} poses for {len(files)} pictures; {len(missing)} "
                f"pictures have none (the first: {missing[0].name})")
    sampler = _fan_sampler(spec, geom)
    shape = (geom.n_rows, geom.n_cols)

    def decode(kf):
        k, f = kf
        try:
            img = sampler(read_grey_png(f, expected_shape=shape))
        except FormatError as e:
            return e
        np.clip(img, 0.0, 1.0, out=img)  # a convex mix of [0, 1] values, less float32 rounding
        return SonarFrame(image=img, spec=spec, timestamp_s=t_of.get(k), T_W_S=T.get(k),
                          meta={"format": "fan", "frame": k, "file": str(f)})

    def frames() -> Iterator[SonarFrame]:
        return frames_skipping_bad(decode, files, on_bad)  # decoded ahead on a few threads, in order

    return Recording(str(root), "fan-folder", frames, has_poses=has_poses,
                     count=lambda: len(files), poses=lambda: [T.get(k) for k, _ in files],
                     pose_note=note)


