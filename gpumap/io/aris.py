"""Sound Metrics ARIS ``.aris`` files (``DDF_05``), from the public aris-file-sdk layout.

Layout (little-endian)
----------------------
- File header, 1024 B: ``b"DDF\\x05"``, ``uint32 FrameCount`` at 4, ``NumRawBeams`` at 16,
  ``SamplesPerChannel`` at 24.
- Frame ``k`` starts at ``1024 + k * (1024 + beams * samples)``: a 1024-byte frame header,
  then ``samples`` rows of ``beams`` uint8 samples (row = sample = range, column = beam
  number when ``ReorderedSamples`` is 1).
- Frame header fields used: ``uint32 FrameIndex`` 0, ``uint64 FrameTime`` 4 (microseconds
  since the epoch), ``uint32 SamplePeriod`` 452 (us), ``float32 SoundSpeed`` 464 (m/s),
  ``uint32 SamplesPerBeam`` 468, ``SampleStartDelay`` 476 (us), ``LargeLens`` 480,
  ``SystemType`` 484 (0 = ARIS 1800, 1 = 3000, 2 = 1200), ``ReorderedSamples`` 516.

Conventions at this edge
------------------------
- Range of sample ``n`` is ``(SampleStartDelay + n * SamplePeriod) * 1e-6 * SoundSpeed / 2``;
  a sample is a point in time, so it is taken as its bin's *centre*
  (``range_min_m = r_0 - dr / 2``).
- Beam ``j``'s azimuth comes from the beam angle table (degrees, ``beam,center_deg,...``
  CSV as published with the SDK). Beam 0 is the right-most (starboard) beam and the SDK
  tables give it the most negative angle, so in gpumap's frame (y left, azimuth positive
  to port) the table angles are the azimuths as they are and the file's beam order is
  already ascending azimuth; the reader checks that and sorts the columns if a table is
  given the other way round (beam 0 must end up as the most negative azimuth).
- Tables are not copied into gpumap: pass ``beam_angles_deg`` or ``beam_table`` (a CSV), or
  let the reader find ``beam_angles_<name>.csv`` beside the file (``ARIS_Telephoto_48``
  when ``LargeLens`` is set, else ``ARIS1800_1200_48`` or ``ARIS3000_128`` by beam count).
- Vertical aperture: 14 deg (standard ARIS lens) by default; pass ``vfov_deg`` for others.
- Pose fields in the frame header are not used (they are zero/NaN in practice and their
  frame is vendor-specific): frames have ``T_W_S = None``.
- DIDSON ``DDF_03``/``DDF_04`` files use different header sizes and offsets and are refused.
- Budgets (:mod:`gpumap.limits`): ``beams * samples`` is checked against
  ``MAX_IMAGE_PIXELS`` and a frame (``1024 + beams * samples``) against ``MAX_ITEM_BYTES``
  when the file is opened, before any frame is read; frames are read one at a time and only
  whole frames that the file holds are read.
"""

from __future__ import annotations

import csv
import io
import math
import os
import struct
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np

from gpumap import limits
from gpumap.errors import MissingFileError
from gpumap.io.frame import FormatError, Recording, SonarFrame
from gpumap.limits import check_size, declared_product
from gpumap.spec import SonarSpec

__all__ = ["load_beam_table", "open_aris", "write_aris"]

FILE_HEADER = 1024
FRAME_HEADER = 1024
DEFAULT_VFOV_DEG = 14.0


def load_beam_table(path: str | os.PathLike) -> np.ndarray:
    """Read a beam angle CSV (``beam,center_deg,...``) -> (n_beams,) float64 centre angles, degrees.

    The table must be at most ``gpumap.limits.MAX_TABLE_BYTES`` (checked before reading).

    Raises
    ------
    FormatError
        If the table is not such a CSV (columns, numbering 0..n-1, finite angles).
    LimitError
        If the file is larger than the budget.
    """
    ps = os.fspath(path)
    with open(ps, "rb") as f:
        check_size(os.fstat(f.fileno()).st_size, limits.MAX_TABLE_BYTES, "the beam angle table",
                   path=ps)
        raw = f.read(limits.MAX_TABLE_BYTES + 1)
    check_size(len(raw), limits.MAX_TABLE_BYTES, "the beam angle table", path=ps)  # grew meanwhile
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise FormatError(f"expected a UTF-8 beam angle CSV, but byte {e.start} is not", e.start,
                          ps) from None
    try:
        rd = csv.reader(io.StringIO(text, newline=""))
        names = [h.strip() for h in next(rd, None) or []]
        if "beam" not in names or "center_deg" not in names:
            raise FormatError(f"expected columns 'beam' and 'center_deg', but got {names}", path=ps)
        i_beam, i_ang = names.index("beam"), names.index("center_deg")
        beams: list[float] = []
        angles: list[float] = []
        for row in rd:
            if not row or all(not v.strip() for v in row):
                continue
            if len(row) != len(names):
                raise FormatError(f"line {rd.line_num}: expected {len(names)} fields, but got "
                                  f"{len(row)}", path=ps)
            try:
                beams.append(float(row[i_beam]))
                angles.append(float(row[i_ang]))
            except ValueError as e:
                raise FormatError(f"line {rd.line_num}: expected numbers, but {e}", path=ps) from None
    except csv.Error as e:
        raise FormatError(f"expected a beam angle CSV, but {e}", path=ps) from None
    beam_f = np.asarray(beams, dtype=np.float64)
    ang = np.asarray(angles, dtype=np.float64)
    n = len(beam_f)
    if n == 0 or not np.array_equal(np.sort(beam_f), np.arange(n)):
        raise FormatError(f"expected beams numbered 0..{n - 1}, but got {beam_f.tolist()[:8]}...",
                          path=ps)
    if not np.all(np.isfinite(ang)):
        raise FormatError("expected finite 'center_deg' angles, but got NaN or inf", path=ps)
    out = np.empty(n)
    out[beam_f.astype(np.int64)] = ang
    return out


def _table_name(n_beams: int, large_lens: int, system: int) -> str | None:
    if large_lens and n_beams == 48:
        return "ARIS_Telephoto_48"
    if n_beams == 48:
        return "ARIS1800_1200_48"
    if n_beams == 128:
        return "ARIS3000_128"
    return None


def _find_table(file: Path, name: str) -> Path | None:
    for d in (file.parent, file.parent / "aris", file.parent.parent):
        c = d / f"beam_angles_{name}.csv"
        if c.is_file():
            return c
    return None


def open_aris(
    path: str | os.PathLike,
    *,
    beam_angles_deg: Sequence[float] | np.ndarray | None = None,
    beam_table: str | os.PathLike | None = None,
    vfov_deg: float = DEFAULT_VFOV_DEG,
) -> Recording:
    """Open an ARIS file (no poses).

    Parameters
    ----------
    path : path-like
        The ``.aris`` file.
    beam_angles_deg : (n_beams,) float, optional
        Beam centre angles by beam number, degrees (beam 0 right-most).
    beam_table : path-like, optional
        CSV to read them from instead.
    vfov_deg : float
        Vertical aperture, degrees.

    Raises
    ------
    FormatError
        On a bad or unsupported header (at open) or a bad frame (when it is reached).
    MissingFileError
        If no beam table is given and none is found beside the file (a ``FormatError``
        and a ``FileNotFoundError``).
    """
    p = Path(path)
    with open(p, "rb") as f:
        head = f.read(FILE_HEADER)
        size = os.fstat(f.fileno()).st_size
    if len(head) < 4 or head[:3] != b"DDF":
        raise FormatError(f"expected ARIS magic b'DDF\\x05', but got {head[:4]!r}", 0, str(p))
    if head[3] in (3, 4):
        raise FormatError(f"expected an ARIS DDF_05 file, but got DIDSON DDF_0{head[3]}, whose "
                          "header layout differs (not supported)", 3, str(p))
    if head[3] != 5:
        raise FormatError(f"expected ARIS file version 5, but got {head[3]}", 3, str(p))
    if len(head) < FILE_HEADER:
        raise FormatError(f"expected a {FILE_HEADER}-byte file header, but the file has "
                          f"{len(head)} bytes", len(head), str(p))
    (frame_count,) = struct.unpack_from("<I", head, 4)
    (n_beams,) = struct.unpack_from("<I", head, 16)
    (n_samples,) = struct.unpack_from("<I", head, 24)
    if not (2 <= n_beams <= 1024) or not (1 <= n_samples <= 100_000):
        raise FormatError(f"expected 2..1024 beams and 1..100000 samples, but the header says "
                          f"{n_beams} beams x {n_samples} samples", 16, str(p))
    check_size(declared_product(n_beams, n_samples), limits.MAX_IMAGE_PIXELS,
               "a frame's image (NumRawBeams x SamplesPerChannel)", unit="pixels", offset=16,
               path=str(p))
    frame_size = check_size(FRAME_HEADER + n_beams * n_samples, limits.MAX_ITEM_BYTES,
                            "a frame (1024 + NumRawBeams x SamplesPerChannel)", offset=16, path=str(p))
    n_whole, rem = divmod(max(size - FILE_HEADER, 0), frame_size)

    if beam_angles_deg is None:
        if beam_table is None:
            # the lens flag is in the frame header: peek at the first frame if it is there
            large_lens = system = 0
            if size >= FILE_HEADER + FRAME_HEADER:
                with open(p, "rb") as f:
                    f.seek(FILE_HEADER + 480)
                    large_lens, system = struct.unpack("<2I", f.read(8))
            name = _table_name(n_beams, large_lens, system)
            found = _find_table(p, name) if name else None
            if found is None:
                raise MissingFileError(
                    f"expected a beam angle table for {n_beams} beams (beam_angles_{name}.csv "
                    f"beside the file), but found none: pass beam_angles_deg or beam_table",
                    path=str(p))
            beam_table = found
        beam_angles_deg = load_beam_table(beam_table)
    ang = np.asarray(beam_angles_deg, dtype=np.float64)
    if ang.shape != (n_beams,):
        raise FormatError(f"expected one beam angle per beam, {n_beams} as the file header says "
                          f"(NumRawBeams), but the table has shape {ang.shape}", 16, str(p))
    if not np.all(np.isfinite(ang)):
        raise ValueError("Expected finite beam angles, but got NaN or inf")
    if ang[0] > ang[-1]:  # a table given positive-to-starboard: beam 0 must be most negative
        ang = -ang
    order = np.argsort(ang, kind="stable")
    az = np.deg2rad(ang[order])
    vfov = math.radians(vfov_deg)
    ps = str(p)
    try:  # the table (and vfov) must make a sonar before any frame is read
        SonarSpec(0.0, 1.0, 1, az, vfov)
    except ValueError as e:
        raise FormatError(f"expected beam angles that make a valid sonar, but {e}", path=ps) from None

    def frames() -> Iterator[SonarFrame]:
        with open(p, "rb") as f:
            for k in range(n_whole):
                off = FILE_HEADER + k * frame_size
                f.seek(off)
                buf = f.read(frame_size)
                if len(buf) < frame_size:  # file changed under us
                    raise FormatError(f"expected frame {k} of {frame_size} bytes, but got "
                                      f"{len(buf)}", off + len(buf), ps)
                yield _decode_frame(buf, k, off, n_beams, n_samples, az, order, vfov, ps)
        if rem or n_whole < frame_count:
            off = FILE_HEADER + n_whole * frame_size
            raise FormatError(
                f"expected {frame_count} frames of {frame_size} bytes (header says so), but the "
                f"file ends {rem} bytes into frame {n_whole}",
                off + rem, ps,
            )

    return Recording(ps, "aris", frames, has_poses=False, count=lambda: n_whole)


def _decode_frame(buf: bytes, k: int, off: int, n_beams: int, n_samples: int, az: np.ndarray,
                  order: np.ndarray, vfov: float, path: str) -> SonarFrame:
    (index,) = struct.unpack_from("<I", buf, 0)
    (t_us,) = struct.unpack_from("<Q", buf, 4)
    (period,) = struct.unpack_from("<I", buf, 452)
    (c,) = struct.unpack_from("<f", buf, 464)
    (spb,) = struct.unpack_from("<I", buf, 468)
    (delay,) = struct.unpack_from("<I", buf, 476)
    (reordered,) = struct.unpack_from("<I", buf, 516)
    if index != k:
        raise FormatError(f"expected FrameIndex {k}, but got {index}", off, path)
    if spb != n_samples:
        raise FormatError(f"expected SamplesPerBeam {n_samples} (file header), but got {spb}",
                          off + 468, path)
    if not (math.isfinite(c) and 1300.0 <= c <= 1700.0):
        raise FormatError(f"expected a SoundSpeed in 1300..1700 m/s, but got {c}", off + 464, path)
    if period == 0:
        raise FormatError("expected SamplePeriod > 0 us, but got 0", off + 452, path)
    if reordered != 1:
        raise FormatError(f"expected ReorderedSamples 1 (samples in beam order), but got "
                          f"{reordered}", off + 516, path)
    dr = period * 1e-6 * c / 2.0
    r0 = delay * 1e-6 * c / 2.0
    try:
        spec = SonarSpec(max(r0 - dr / 2.0, 0.0), r0 - dr / 2.0 + n_samples * dr, n_samples, az, vfov)
    except ValueError as e:
        raise FormatError(f"expected a valid sonar geometry from SamplePeriod {period} us, "
                          f"SampleStartDelay {delay} us and the beam table, but {e}", off + 452,
                          path) from None
    limits.check_geometry(spec, f"frame {k} (SamplePeriod, SampleStartDelay, SoundSpeed)",
                          offset=off + 452, path=path)
    data = np.frombuffer(buf, dtype=np.uint8, count=n_beams * n_samples, offset=FRAME_HEADER)
    img = data.reshape(n_samples, n_beams)[:, order].astype(np.float32)
    np.divide(img, np.float32(255.0), out=img)
    meta = {"format": "aris", "frame_index": int(index), "offset": off,
            "sound_speed": float(c), "sample_period_us": int(period),
            "sample_start_delay_us": int(delay), "first_sample_m": r0}
    return SonarFrame(image=img, spec=spec, timestamp_s=t_us * 1e-6, meta=meta)


def write_aris(
    path: str | os.PathLike,
    images: Sequence[np.ndarray],
    *,
    sample_period_us: int = 14,
    sample_start_delay_us: int = 4593,
    sound_speed: float = 1435.93,
    frame_time_us: Sequence[int] | None = None,
    large_lens: int = 0,
    system_type: int = 2,
) -> None:
    """Write uint8 ``(samples, beams)`` images (beam-number column order) as a minimal ARIS file.

    Only the fields this reader uses are filled; the rest is zero. For tests and fixtures.
    """
    imgs = [np.asarray(i) for i in images]
    if not imgs or any(i.dtype != np.uint8 or i.ndim != 2 or i.shape != imgs[0].shape
                       for i in imgs):
        raise ValueError("Expected one or more uint8 images of one 2-D shape")
    n_samples, n_beams = imgs[0].shape
    head = bytearray(FILE_HEADER)
    head[0:4] = b"DDF\x05"
    struct.pack_into("<I", head, 4, len(imgs))
    struct.pack_into("<I", head, 16, n_beams)
    struct.pack_into("<I", head, 24, n_samples)
    with open(path, "wb") as f:
        f.write(head)
        for k, img in enumerate(imgs):
            fh = bytearray(FRAME_HEADER)
            struct.pack_into("<I", fh, 0, k)
            t = frame_time_us[k] if frame_time_us is not None else k * 100_000
            struct.pack_into("<Q", fh, 4, int(t))
            struct.pack_into("<I", fh, 452, sample_period_us)
            struct.pack_into("<f", fh, 464, sound_speed)
            struct.pack_into("<I", fh, 468, n_samples)
            struct.pack_into("<I", fh, 476, sample_start_delay_us)
            struct.pack_into("<I", fh, 480, large_lens)
            struct.pack_into("<I", fh, 484, system_type)
            struct.pack_into("<I", fh, 516, 1)
            f.write(fh)
            f.write(np.ascontiguousarray(img).tobytes())
