"""Blueprint Subsea Oculus: simple-ping messages (v1 and v2) and ViewPoint ``.oculus`` logs.

Implemented from the public description of the layouts (README of ``shared/data/oculus``,
the message structs published with the Oculus SDK and the log-file structs described by
open-source drivers); no vendor code. Everything is little-endian and packed.

Simple-ping message (``msgId`` 35)
----------------------------------
- header, 16 B: ``uint16 oculusId (0x4f53), srcDeviceId, dstDeviceId, msgId, msgVersion;
  uint32 payloadSize; uint16 spare``. The message is ``16 + payloadSize`` bytes.
- v0/v1 (``msgVersion`` 0 or 1): fire message (``uint8 masterMode, pingRate, networkSpeed,
  gammaCorrection, flags; float64 range, gainPercent, speedOfSound, salinity``), then
  ``uint32 pingId, status; float64 frequency, temperature, pressure, speedOfSoundUsed;
  uint32 pingStartTime; uint8 dataSize; float64 rangeResolution; uint16 nRanges, nBeams;
  uint32 imageOffset, imageSize, messageSize`` -- 122 bytes.
- v2 (``msgVersion`` 2): the fire message gains ``uint32 extFlags, reserved[8]`` (ends at
  89), then ``uint32 pingId, status; float64 frequency, temperature, pressure, heading,
  pitch, roll, speedOfSoundUsed, pingStartTime (s since power-up); uint8 dataSize;
  float64 rangeResolution; uint16 nRanges, nBeams; uint32 spare[4], imageOffset,
  imageSize, messageSize`` -- 202 bytes.
- ``int16 bearings[nBeams]`` (1/100 degree) follow the fixed part; the image is ``nRanges``
  rows of ``nBeams`` samples (``dataSize`` 0/1/3 = 8/16/32-bit unsigned) at ``imageOffset``
  from the message start. When ``imageSize == nRanges * (4 + nBeams * bytes)`` every row
  starts with a ``uint32`` gain word (fire-message flag bit 2); the words are kept in
  ``frame.meta["gains"]``, the samples are returned as sent (not divided by the gain).

Conventions at this edge
------------------------
- Oculus bearings are positive to starboard (the vendor display draws negative bearings
  on the left, i.e. port). gpumap azimuth is positive to port (y left), so
  ``azimuth = -bearing`` and the columns are reversed to ascending azimuth. The uneven
  bearing table is kept as it is.
- Row ``i`` covers ranges ``[i, i + 1) * rangeResolution``: ``range_min_m = 0``,
  ``range_max_m = nRanges * rangeResolution``.
- The message carries no vertical aperture; ``vfov_deg`` (default 20 deg, the aperture
  quoted for the M750d, M1200d and M3000d in their low-frequency modes) is a parameter.
  The high-frequency modes of these models are narrower: pass your datasheet's value.
- ``msgVersion`` 24-bit samples (``dataSize`` 2) are refused.

ViewPoint ``.oculus`` log
-------------------------
A file header (48 B, naturally aligned C struct: ``uint32 fileHeader = 0x11223344,
sizeHeader; char source[16]; uint16 version, encryption; <4 pad>; int64 key;
float64 time``) followed by items, each an item header (40 B: ``uint32 itemHeader =
0xaabbccdd, sizeHeader; uint16 type, version; <4 pad>; float64 time (s since epoch);
uint16 compression; <2 pad>; uint32 originalSize, payloadSize; <4 pad>``) and
``payloadSize`` bytes. ``sizeHeader`` gives where the payload starts. Type 10 items hold
one Oculus network message; ``compression`` 1 is Qt's ``qCompress`` (a big-endian uint32
of the uncompressed size, then a zlib stream). Other item types are skipped. Encrypted
logs are refused. The item time is the frame's ``timestamp_s``.

Budgets (:mod:`gpumap.limits`)
------------------------------
Every size a file declares is checked before anything of that size is read, allocated or
inflated: a message (``16 + payloadSize``) and a log item's stored and inflated sizes
against ``MAX_ITEM_BYTES`` and against the bytes left in the file, header sizes against
``MAX_HEADER_BYTES``, ``nRanges * nBeams`` against ``MAX_IMAGE_PIXELS``. A compressed item
must declare the same size twice (``originalSize`` and the ``qCompress`` prefix); it is
inflated with its output bounded by that size, so a small file can never inflate to more
than it declares, and a stream that holds more (or less) is refused.
"""

from __future__ import annotations

import math
import os
import struct
import zlib
from collections.abc import Iterator, Sequence
from typing import BinaryIO

import numpy as np

from gpumap import limits
from gpumap.io.frame import FormatError, Recording, SonarFrame
from gpumap.limits import check_size, declared_product
from gpumap.spec import SonarSpec

__all__ = [
    "OCULUS_ID",
    "decode_message",
    "encode_simple_ping",
    "iter_oculus_log",
    "iter_raw_messages",
    "open_oculus_log",
    "open_oculus_raw",
    "write_oculus_log",
]

OCULUS_ID = 0x4F53
MSG_SIMPLE_PING = 35
LOG_FILE_MAGIC = 0x11223344
LOG_ITEM_MAGIC = 0xAABBCCDD
LOG_TYPE_OCULUS_SONAR = 10
DEFAULT_VFOV_DEG = 20.0

_HEADER = struct.Struct("<5HIH")  # 16 B
_FIRE1 = struct.Struct("<5B4d")  # 37 B at 16 -> 53
_PING1 = struct.Struct("<2I4dIBd2H3I")  # 69 B at 53 -> 122
_FIRE2 = struct.Struct("<5B4dI8I")  # 73 B at 16 -> 89
_PING2 = struct.Struct("<2I8dBd2H4I3I")  # 113 B at 89 -> 202
_FIXED1 = 16 + _FIRE1.size + _PING1.size
_FIXED2 = 16 + _FIRE2.size + _PING2.size
_SAMPLE_DTYPES = {0: np.dtype("<u1"), 1: np.dtype("<u2"), 3: np.dtype("<u4")}
_LOG_HEADER = struct.Struct("<2I16s2H4xqd")  # 48 B
_LOG_ITEM = struct.Struct("<2I2H4xdH2x2I4x")  # 40 B

assert _FIXED1 == 122 and _FIXED2 == 202  # layout self-check (constants, not user input)


def _fail(msg: str, offset: int, path: str | None) -> FormatError:
    return FormatError(msg, offset=offset, path=path)


def decode_message(
    msg: bytes | memoryview,
    *,
    base: int = 0,
    path: str | None = None,
    vfov_deg: float = DEFAULT_VFOV_DEG,
    timestamp_s: float | None = None,
) -> SonarFrame | None:
    """Decode one complete Oculus network message.

    Parameters
    ----------
    msg : bytes
        Exactly one message: the 16-byte header and ``payloadSize`` bytes.
    base : int
        File offset of ``msg[0]``, for error messages.
    path : str, optional
        File name, for error messages.
    vfov_deg : float
        Vertical aperture to put in the spec, degrees.
    timestamp_s : float, optional
        Overrides the ping's own time (a log item's time). Otherwise v2 pings carry
        ``pingStartTime`` (seconds since sonar power-up) and v1 pings ``None``.

    Returns
    -------
    SonarFrame or None
        The ping, or ``None`` for a valid message that is not a simple-ping result.

    Raises
    ------
    FormatError
        If any field is inconsistent; the offset names the first bad byte found.
    """
    buf = memoryview(msg).cast("B") if not isinstance(msg, bytes) else msg
    n = len(buf)
    if n < 16:
        raise _fail(f"expected a 16-byte Oculus message header, but only {n} bytes remain", base, path)
    oid, _src, _dst, msg_id, version, payload, _spare = _HEADER.unpack_from(buf, 0)
    if oid != OCULUS_ID:
        raise _fail(f"expected Oculus message id 0x4f53, but got 0x{oid:04x}", base, path)
    if 16 + payload != n:
        raise _fail(
            f"expected a message of 16 + payloadSize = {16 + payload} bytes, but got {n}", base, path
        )
    if msg_id != MSG_SIMPLE_PING:
        return None
    if version in (0, 1):
        fixed = _FIXED1
        if n < fixed:
            raise _fail(f"expected a v{version} simple-ping fixed part of {fixed} bytes, but the "
                        f"message has {n}", base + n, path)
        fire = _FIRE1.unpack_from(buf, 16)
        (ping_id, status, freq, _temp, _press, sos_used, start_time, data_size, res,
         n_ranges, n_beams, img_off, img_size, msg_size) = _PING1.unpack_from(buf, 16 + _FIRE1.size)
        extra = {"ping_start_time_raw": int(start_time)}
        t = timestamp_s
    elif version == 2:
        fixed = _FIXED2
        if n < fixed:
            raise _fail(f"expected a v2 simple-ping fixed part of {fixed} bytes, but the message "
                        f"has {n}", base + n, path)
        fire = _FIRE2.unpack_from(buf, 16)
        (ping_id, status, freq, _temp, _press, heading, pitch, roll, sos_used, start_time,
         data_size, res, n_ranges, n_beams, _s0, _s1, _s2, _s3, img_off, img_size,
         msg_size) = _PING2.unpack_from(buf, 16 + _FIRE2.size)
        extra = {"heading_deg": heading, "pitch_deg": pitch, "roll_deg": roll,
                 "ping_start_time_s": start_time}
        t = timestamp_s if timestamp_s is not None else float(start_time)
    else:
        raise _fail(f"expected simple-ping msgVersion 0, 1 or 2, but got {version}", base + 8, path)
    flags = fire[4]
    # byte offsets of dataSize, rangeResolution and nRanges in this layout
    o_dsize = 97 if version != 2 else 161
    o_res, o_nr = o_dsize + 1, o_dsize + 9
    if msg_size != n:
        raise _fail(f"expected messageSize {n} (16 + payloadSize), but got {msg_size}",
                    base + fixed - 4, path)
    if data_size not in _SAMPLE_DTYPES:
        raise _fail(f"expected dataSize 0 (8 bit), 1 (16 bit) or 3 (32 bit), but got {data_size}",
                    base + o_dsize, path)
    if not (math.isfinite(res) and res > 0):
        raise _fail(f"expected a finite rangeResolution > 0 m, but got {res}", base + o_res, path)
    if n_ranges < 1 or n_beams < 2:
        raise _fail(f"expected nRanges >= 1 and nBeams >= 2, but got {n_ranges} x {n_beams}",
                    base + o_nr, path)
    check_size(declared_product(n_ranges, n_beams), limits.MAX_IMAGE_PIXELS, "nRanges x nBeams",
               unit="pixels", offset=base + o_nr, path=path)
    if t is not None and not math.isfinite(t):
        raise _fail(f"expected a finite ping time, but got {t}", base + o_dsize - 8, path)
    bear_end = fixed + 2 * n_beams
    if bear_end > n:
        raise _fail(f"expected {n_beams} bearings (int16) ending at message byte {bear_end}, "
                    f"but the message has {n} bytes", base + n, path)
    if img_off < bear_end:
        raise _fail(f"expected imageOffset >= {bear_end} (after the bearings), but got {img_off}",
                    base + fixed - 12, path)
    dt = _SAMPLE_DTYPES[data_size]
    plain = n_ranges * n_beams * dt.itemsize
    gained = n_ranges * (4 + n_beams * dt.itemsize)
    if img_size not in (plain, gained):
        raise _fail(f"expected imageSize {plain} ({n_ranges} x {n_beams} x {dt.itemsize} B) or "
                    f"{gained} (with a 4-byte gain word per row), but got {img_size}",
                    base + fixed - 8, path)
    if img_off + img_size > n:
        raise _fail(f"expected the image to end at message byte {img_off + img_size}, but the "
                    f"message has {n} bytes", base + n, path)
    bearings_cdeg = np.frombuffer(buf, dtype="<i2", count=n_beams, offset=fixed)
    steps = np.diff(bearings_cdeg.astype(np.int32))
    if np.any(steps <= 0):
        k = int(np.argmax(steps <= 0))
        raise _fail(f"expected strictly ascending bearings, but bearings[{k}]={bearings_cdeg[k]} "
                    f">= bearings[{k + 1}]={bearings_cdeg[k + 1]} (1/100 deg)",
                    base + fixed + 2 * (k + 1), path)
    raw = np.frombuffer(buf, dtype=np.uint8, count=img_size, offset=img_off)
    gains = None
    if img_size == gained and gained != plain:
        rows = raw.reshape(n_ranges, 4 + n_beams * dt.itemsize)
        gains = rows[:, :4].copy().view("<u4").reshape(n_ranges)
        samples = rows[:, 4:].copy().view(dt).reshape(n_ranges, n_beams)
    else:
        samples = raw.view(dt).reshape(n_ranges, n_beams)
    image = samples[:, ::-1].astype(np.float32)  # the one float copy: scaled in place
    np.divide(image, np.float32(np.iinfo(dt).max), out=image)
    az = -np.deg2rad(bearings_cdeg[::-1].astype(np.float64) / 100.0)
    try:
        spec = SonarSpec(0.0, n_ranges * res, int(n_ranges), az, math.radians(vfov_deg))
    except ValueError as e:
        raise _fail(f"expected a valid sonar geometry, but {e}", base + o_nr, path) from None
    limits.check_geometry(spec, "the ping (rangeResolution, nRanges)", offset=base + o_res, path=path)
    meta = {
        "format": f"oculus-simple-ping-v{version}",
        "ping_id": int(ping_id),
        "status": int(status),
        "flags": int(flags),
        "frequency_hz": float(freq),
        "speed_of_sound_used": float(sos_used),
        "range_resolution_m": float(res),
        "bits": 8 * dt.itemsize,
        "bearings_cdeg": bearings_cdeg.copy(),
        "gains": gains,
        "offset": base,
        **extra,
    }
    return SonarFrame(image=image, spec=spec, timestamp_s=t, meta=meta)


def _read_exact(f: BinaryIO, n: int) -> bytes:
    out = f.read(n)
    return out if out is not None else b""


def iter_raw_messages(path: str | os.PathLike) -> Iterator[tuple[int, bytes]]:
    """Yield ``(file_offset, message_bytes)`` for each complete message of a raw stream.

    Raises
    ------
    FormatError
        At the first header that is not an Oculus header or a message cut short.
    """
    p = os.fspath(path)
    with open(p, "rb") as f:
        size = os.fstat(f.fileno()).st_size
        off = 0
        while True:
            hdr = _read_exact(f, 16)
            if not hdr:
                return
            if len(hdr) < 16:
                raise _fail(f"expected a 16-byte Oculus message header, but the file ends after "
                            f"{len(hdr)} bytes", off + len(hdr), p)
            oid, _s, _d, _m, _v, payload, _sp = _HEADER.unpack(hdr)
            if oid != OCULUS_ID:
                raise _fail(f"expected Oculus message id 0x4f53, but got 0x{oid:04x}", off, p)
            check_size(16 + payload, limits.MAX_ITEM_BYTES, "an Oculus message (16 + payloadSize)",
                       available=size - off, offset=off + 10, path=p)
            body = _read_exact(f, payload)
            if len(body) < payload:
                raise _fail(f"expected {payload} payload bytes for the message starting at byte "
                            f"{off}, but the file ends after {len(body)}", off + 16 + len(body), p)
            yield off, hdr + body
            off += 16 + payload


def open_oculus_raw(path: str | os.PathLike, *, vfov_deg: float = DEFAULT_VFOV_DEG) -> Recording:
    """Open a file of raw Oculus network messages, one after another (no poses).

    Parameters
    ----------
    path : path-like
        The file.
    vfov_deg : float
        Vertical aperture, degrees (see the module notes for defaults by model).
    """
    p = os.fspath(path)

    def frames() -> Iterator[SonarFrame]:
        for off, m in iter_raw_messages(p):
            fr = decode_message(m, base=off, path=p, vfov_deg=vfov_deg)
            if fr is not None:
                yield fr

    def count() -> int:
        k = 0
        with open(p, "rb") as f:
            size = os.fstat(f.fileno()).st_size
            off = 0
            while off + 16 <= size:
                f.seek(off)
                oid, _s, _d, mid, _v, payload, _sp = _HEADER.unpack(f.read(16))
                if oid != OCULUS_ID:
                    break
                k += mid == MSG_SIMPLE_PING
                off += 16 + payload
        return k

    return Recording(p, "oculus-raw", frames, has_poses=False, count=count)


# ---------------------------------------------------------------- ViewPoint .oculus logs
def iter_oculus_log(path: str | os.PathLike) -> Iterator[tuple[int, int, float, bytes]]:
    """Yield ``(file_offset, type, time_s, payload)`` for each item of a ``.oculus`` log.

    Compressed payloads are inflated and their size checked against ``originalSize``.

    Raises
    ------
    FormatError
        On a bad magic, an encrypted log, a truncated header or payload, or a payload that
        does not inflate to ``originalSize`` bytes.
    """
    p = os.fspath(path)
    with open(p, "rb") as f:
        size = os.fstat(f.fileno()).st_size
        head = _read_exact(f, _LOG_HEADER.size)
        if len(head) < _LOG_HEADER.size:
            raise _fail(f"expected a {_LOG_HEADER.size}-byte .oculus file header, but the file has "
                        f"{len(head)} bytes", len(head), p)
        magic, size_header, _src, _ver, encryption, _key, _t = _LOG_HEADER.unpack(head)
        if magic != LOG_FILE_MAGIC:
            raise _fail(f"expected .oculus file magic 0x11223344, but got 0x{magic:08x}", 0, p)
        if size_header < _LOG_HEADER.size:
            raise _fail(f"expected a file header size >= {_LOG_HEADER.size}, but got {size_header}",
                        4, p)
        check_size(size_header, limits.MAX_HEADER_BYTES, "the file header (sizeHeader)",
                   available=size, offset=4, path=p)
        if encryption != 0:
            raise _fail(f"expected an unencrypted log (encryption 0), but got {encryption}", 26, p)
        f.seek(size_header)
        off = size_header
        while True:
            ih = _read_exact(f, _LOG_ITEM.size)
            if not ih:
                return
            if len(ih) < _LOG_ITEM.size:
                raise _fail(f"expected a {_LOG_ITEM.size}-byte item header, but the file ends after "
                            f"{len(ih)} bytes", off + len(ih), p)
            magic, size_item, typ, _v, t, comp, orig, payload = _LOG_ITEM.unpack(ih)
            if magic != LOG_ITEM_MAGIC:
                raise _fail(f"expected item magic 0xaabbccdd, but got 0x{magic:08x}", off, p)
            if size_item < _LOG_ITEM.size:
                raise _fail(f"expected an item header size >= {_LOG_ITEM.size}, but got {size_item}",
                            off + 4, p)
            check_size(size_item, limits.MAX_HEADER_BYTES, "an item header (sizeHeader)",
                       available=size - off, offset=off + 4, path=p)
            if not math.isfinite(t):
                raise _fail(f"expected a finite item time, but got {t}", off + 16, p)
            start = off + size_item
            if comp not in (0, 1):
                raise _fail(f"expected compression 0 (none) or 1 (qCompress), but got {comp}",
                            off + 24, p)
            # both sizes before reading a byte of the payload
            check_size(payload, limits.MAX_ITEM_BYTES, f"the payload (payloadSize) of the item at byte {off}",
                       available=size - start, offset=off + 32, path=p)
            check_size(orig, limits.MAX_ITEM_BYTES,
                       f"the inflated item (originalSize) of the item at byte {off}",
                       offset=off + 28, path=p)
            if size_item > _LOG_ITEM.size:
                f.read(size_item - _LOG_ITEM.size)  # in the file: checked just above
            data = _read_exact(f, payload)
            if len(data) < payload:  # the file shrank under us
                raise _fail(f"expected {payload} payload bytes for the item at byte {off}, but the "
                            f"file ends after {len(data)}", start + len(data), p)
            if comp == 1:
                if payload < 4:
                    raise _fail(f"expected a qCompress payload (4-byte size + zlib), but got "
                                f"{payload} bytes", start, p)
                (declared,) = struct.unpack_from(">I", data, 0)
                if declared != orig:
                    raise _fail(f"expected the qCompress size prefix to equal originalSize {orig}, "
                                f"but it says {declared}", start, p)
                data = _inflate_exact(data, orig, start, off, p)
            elif orig != payload:
                raise _fail(f"expected originalSize == payloadSize for an uncompressed item, but "
                            f"got {orig} and {payload}", off + 28, p)
            yield off, typ, t, data
            off = start + payload


def _inflate_exact(data: bytes, size: int, start: int, item: int, path: str) -> bytes:
    """Inflate a ``qCompress`` payload (4-byte prefix, zlib) to exactly ``size`` bytes, never more."""
    stream = memoryview(data)[4:]
    if size == 0 and len(stream) == 0:  # qCompress of nothing is the bare prefix
        return b""
    d = zlib.decompressobj()
    where = f"the compressed item at byte {item}"
    try:
        # one byte more than declared tells "too long"; short of that limit zlib consumes all
        # the input, so a complete stream has reached its end (and checked its Adler-32)
        out = d.decompress(stream, size + 1)
    except zlib.error as e:
        raise _fail(f"expected a zlib stream in {where}, but inflating failed ({e})", start + 4,
                    path) from None
    if len(out) > size:
        raise _fail(f"expected {where} to inflate to {size} bytes (originalSize), but it holds more",
                    start + 4, path)
    if len(out) < size or not d.eof:
        raise _fail(f"expected {where} to inflate to {size} bytes (originalSize) and end, but it "
                    f"gives {len(out)} bytes{'' if d.eof else ' and is cut short'}", start + 4, path)
    return out


def open_oculus_log(path: str | os.PathLike, *, vfov_deg: float = DEFAULT_VFOV_DEG) -> Recording:
    """Open a ViewPoint ``.oculus`` log; frames carry the item time (epoch seconds), no poses."""
    p = os.fspath(path)

    def frames() -> Iterator[SonarFrame]:
        for off, typ, t, data in iter_oculus_log(p):
            if typ != LOG_TYPE_OCULUS_SONAR:
                continue
            try:
                fr = decode_message(data, base=0, vfov_deg=vfov_deg, timestamp_s=t)
            except FormatError as e:
                raise FormatError(f"in the Oculus message of the item at byte {off}: {e}",
                                  offset=off, path=p) from None
            if fr is not None:
                fr.meta["offset"] = off
                yield fr

    def count() -> int:
        k = 0
        with open(p, "rb") as f:
            size = os.fstat(f.fileno()).st_size
            head = f.read(_LOG_HEADER.size)
            if len(head) < _LOG_HEADER.size:
                return 0
            off = _LOG_HEADER.unpack(head)[1]
            while off + _LOG_ITEM.size <= size:
                f.seek(off)
                magic, size_item, typ, _v, _t, _c, _o, payload = _LOG_ITEM.unpack(
                    f.read(_LOG_ITEM.size))
                if magic != LOG_ITEM_MAGIC or size_item < _LOG_ITEM.size:
                    break
                k += typ == LOG_TYPE_OCULUS_SONAR
                off += size_item + payload
        return k

    return Recording(p, "oculus-log", frames, has_poses=False, count=count)


# ---------------------------------------------------------------- writers (tests, fixtures)
def encode_simple_ping(
    samples: np.ndarray,
    bearings_cdeg: Sequence[int] | np.ndarray,
    range_resolution_m: float,
    *,
    version: int = 2,
    gains: np.ndarray | None = None,
    ping_id: int = 0,
    frequency_hz: float = 1.2e6,
    speed_of_sound: float = 1500.0,
    ping_start_time: float = 0.0,
    image_offset: int | None = None,
) -> bytes:
    """Encode a simple-ping result message (the inverse of :func:`decode_message`).

    Parameters
    ----------
    samples : (n_ranges, n_beams) uint8, uint16 or uint32
        Samples in the vendor's column order (ascending bearing).
    bearings_cdeg : (n_beams,) int
        Beam bearings, 1/100 degree, positive to starboard.
    range_resolution_m : float
        Range of one row, metres.
    version : {1, 2}
        Message layout.
    gains : (n_ranges,) uint32, optional
        Per-row gain words; when given each row is prefixed with its word (flag bit 2 set).
    image_offset : int, optional
        Where the image starts; default right after the bearings.

    Returns
    -------
    bytes
        One complete message.
    """
    s = np.asarray(samples)
    code = {np.dtype(np.uint8): 0, np.dtype(np.uint16): 1, np.dtype(np.uint32): 3}.get(s.dtype)
    if code is None or s.ndim != 2:
        raise TypeError(f"Expected a 2-D uint8/uint16/uint32 array for 'samples', but got "
                        f"{s.dtype} with shape {s.shape}")
    n_ranges, n_beams = s.shape
    b = np.asarray(bearings_cdeg, dtype="<i2")
    if b.shape != (n_beams,):
        raise ValueError(f"Expected {n_beams} bearings, but got shape {b.shape}")
    if version not in (1, 2):
        raise ValueError(f"Expected version 1 or 2, but got {version}")
    fixed = _FIXED2 if version == 2 else _FIXED1
    img_off = fixed + 2 * n_beams if image_offset is None else int(image_offset)
    rows = s.astype(s.dtype.newbyteorder("<")).reshape(n_ranges, -1).view(np.uint8)
    if gains is not None:
        g = np.asarray(gains, dtype="<u4").reshape(n_ranges, 1).view(np.uint8)
        rows = np.concatenate([g, rows.reshape(n_ranges, -1)], axis=1)
    image = rows.tobytes()
    msg_size = img_off + len(image)
    flags = 0x01 | (0x02 if code == 1 else 0) | (0x04 if gains is not None else 0) | 0x08
    head = _HEADER.pack(OCULUS_ID, 0, 0, MSG_SIMPLE_PING, version, msg_size - 16, 0)
    rng = n_ranges * range_resolution_m
    if version == 2:
        fire = _FIRE2.pack(1, 0, 0, 0, flags, rng, 50.0, speed_of_sound, 0.0, 0, *([0] * 8))
        tail = _PING2.pack(ping_id, 0, frequency_hz, 0.0, 0.0, 0.0, 0.0, 0.0, speed_of_sound,
                           ping_start_time, code, range_resolution_m, n_ranges, n_beams,
                           0, 0, 0, 0, img_off, len(image), msg_size)
    else:
        fire = _FIRE1.pack(1, 0, 0, 0, flags, rng, 50.0, speed_of_sound, 0.0)
        tail = _PING1.pack(ping_id, 0, frequency_hz, 0.0, 0.0, speed_of_sound,
                           int(ping_start_time) & 0xFFFFFFFF, code, range_resolution_m,
                           n_ranges, n_beams, img_off, len(image), msg_size)
    out = bytearray(msg_size)
    out[0:fixed] = head + fire + tail
    out[fixed:fixed + 2 * n_beams] = b.tobytes()
    out[img_off:] = image
    return bytes(out)


def write_oculus_log(
    path: str | os.PathLike,
    messages: Sequence[bytes],
    times_s: Sequence[float],
    *,
    compress: bool = True,
    file_time_s: float = 0.0,
) -> None:
    """Write Oculus messages as a ViewPoint ``.oculus`` log (layout in the module notes).

    Parameters
    ----------
    path : path-like
        Output file.
    messages : sequence of bytes
        Complete Oculus messages, each stored as one type-10 item.
    times_s : sequence of float
        Item times, seconds since the epoch.
    compress : bool
        Store payloads ``qCompress``-ed (compression 1).
    """
    if len(messages) != len(times_s):
        raise ValueError(f"Expected one time per message, but got {len(times_s)} times for "
                         f"{len(messages)} messages")
    with open(path, "wb") as f:
        f.write(_LOG_HEADER.pack(LOG_FILE_MAGIC, _LOG_HEADER.size, b"Oculus", 1, 0, 0,
                                 float(file_time_s)))
        for m, t in zip(messages, times_s, strict=True):
            data = bytes(m)
            if compress:
                payload = struct.pack(">I", len(data)) + zlib.compress(data, 1)
            else:
                payload = data
            f.write(_LOG_ITEM.pack(LOG_ITEM_MAGIC, _LOG_ITEM.size, LOG_TYPE_OCULUS_SONAR, 0,
                                   float(t), 1 if compress else 0, len(data), len(payload)))
            f.write(payload)
