"""Readers against the real recordings in ../shared/data, round trips, and corrupt files."""

from __future__ import annotations

import io
import math
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest
from conftest import DATA, needs_data

from gpumap.io import (
    FanGeometry,
    FormatError,
    decode_message,
    encode_simple_ping,
    fan_to_polar,
    open_aris,
    open_oculus_log,
    open_oculus_raw,
    open_recording,
    polar_to_fan,
    read_ply,
    write_aris,
    write_oculus_log,
    write_ply,
)
from gpumap.spec import SonarSpec

OCU1 = DATA / "oculus" / "one_ping_8bit.raw" if DATA else None
OCU3 = DATA / "oculus" / "three_pings_8bit.raw" if DATA else None
ARIS = DATA / "aris" / "sample.aris" if DATA else None
OASIS = DATA / "oasis_tank" if DATA else None


# ------------------------------------------------------------------ real Oculus pings
@needs_data
@pytest.mark.parametrize("name, count", [("one_ping_8bit.raw", 1), ("three_pings_8bit.raw", 3)])
def test_oculus_raw_fields(name: str, count: int) -> None:
    rec = open_recording(DATA / "oculus" / name)
    assert rec.kind == "oculus-raw" and not rec.has_poses
    frames = list(rec)
    assert len(frames) == count == rec.count()
    for k, fr in enumerate(frames):
        assert fr.image.shape == (703, 256) and fr.image.dtype == np.float32
        assert 0.0 <= fr.image.min() and fr.image.max() <= 1.0
        assert fr.spec.bin_size_m == pytest.approx(2.8422e-3, abs=1e-7)
        assert fr.spec.range_max_m == pytest.approx(703 * 2.8422e-3, abs=1e-4)
        b = np.rad2deg(fr.spec.bearings_rad)
        assert b[0] == pytest.approx(-30.0) and b[-1] == pytest.approx(30.0)
        steps = np.diff(fr.meta["bearings_cdeg"])
        assert steps.min() == 22 and steps.max() == 26  # uneven, table kept
        assert np.all(np.diff(b) > 0)
        assert fr.meta["ping_id"] == 415323 + k and fr.meta["gains"] is None
        assert fr.meta["bits"] == 8
        assert fr.spec.vfov_rad == pytest.approx(math.radians(20.0))


@needs_data
def test_oculus_columns_are_reversed_vendor_order() -> None:
    raw = OCU1.read_bytes()
    fr = next(iter(open_oculus_raw(OCU1)))
    vendor = np.frombuffer(raw, np.uint8, count=703 * 256, offset=2048).reshape(703, 256)
    np.testing.assert_array_equal(np.round(fr.image * 255).astype(np.uint8), vendor[:, ::-1])
    # vendor bearing +30 (starboard) becomes azimuth -30 (y right), column 0
    assert fr.meta["bearings_cdeg"][-1] == 3000
    assert math.degrees(fr.spec.bearings_rad[0]) == pytest.approx(-30.0)


# ------------------------------------------------------------------ Oculus round trips
def _bearings(n: int) -> np.ndarray:
    x = np.linspace(-1, 1, n)
    return np.round(6500 * np.sin(x * 1.1) / np.sin(1.1)).astype(np.int16)  # uneven


@pytest.mark.parametrize("version", [1, 2])
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.uint32])
@pytest.mark.parametrize("with_gains", [False, True])
def test_oculus_message_round_trip(version: int, dtype, with_gains: bool) -> None:
    rng = np.random.default_rng(0)
    samples = rng.integers(0, np.iinfo(dtype).max, size=(37, 21), dtype=dtype, endpoint=True)
    gains = rng.integers(1, 2**32 - 1, size=37, dtype=np.uint32) if with_gains else None
    b = _bearings(21)
    msg = encode_simple_ping(samples, b, 0.0125, version=version, gains=gains, ping_id=7,
                             ping_start_time=12.5)
    fr = decode_message(msg, vfov_deg=12.0)
    scale = np.iinfo(dtype).max
    back = np.round(fr.image.astype(np.float64) * scale).astype(np.uint64)
    if dtype != np.uint32:  # float32 holds 8 and 16-bit samples exactly
        np.testing.assert_array_equal(back, samples[:, ::-1])
    else:
        np.testing.assert_allclose(fr.image, samples[:, ::-1] / scale, rtol=1e-6)
    np.testing.assert_array_equal(fr.meta["bearings_cdeg"], b)
    np.testing.assert_allclose(np.rad2deg(fr.spec.bearings_rad), -b[::-1] / 100.0)
    assert fr.spec.n_bins == 37 and fr.spec.bin_size_m == pytest.approx(0.0125)
    assert fr.spec.vfov_rad == pytest.approx(math.radians(12.0))
    assert fr.meta["ping_id"] == 7 and fr.meta["format"].endswith(f"v{version}")
    if with_gains:
        np.testing.assert_array_equal(fr.meta["gains"], gains)
    else:
        assert fr.meta["gains"] is None
    if version == 2:
        assert fr.timestamp_s == 12.5


@pytest.mark.parametrize("compress", [True, False])
def test_oculus_log_round_trip(tmp_path: Path, compress: bool) -> None:
    rng = np.random.default_rng(1)
    imgs = [rng.integers(0, 65535, size=(50, 16), dtype=np.uint16) for _ in range(3)]
    gains = rng.integers(1, 1000, size=50, dtype=np.uint32)
    msgs = [encode_simple_ping(im, _bearings(16), 0.01, version=2, gains=gains, ping_id=i)
            for i, im in enumerate(imgs)]
    # a non-ping message between pings is skipped
    other = struct.pack("<5HIH", 0x4F53, 0, 0, 0x80, 0, 4, 0) + b"\0\0\0\0"
    path = tmp_path / "log.oculus"
    write_oculus_log(path, [msgs[0], other, msgs[1], msgs[2]], [10.0, 10.05, 10.1, 10.2],
                     compress=compress)
    rec = open_recording(path)
    assert rec.kind == "oculus-log" and rec.count() == 4  # type-10 items (3 pings + other)
    frames = list(rec)
    assert [f.meta["ping_id"] for f in frames] == [0, 1, 2]
    assert [f.timestamp_s for f in frames] == [10.0, 10.1, 10.2]
    for f, im in zip(frames, imgs, strict=True):
        np.testing.assert_array_equal(np.round(f.image * 65535).astype(np.uint16), im[:, ::-1])
        np.testing.assert_array_equal(f.meta["gains"], gains)


def test_oculus_log_layout_is_documented(tmp_path: Path) -> None:
    msg = encode_simple_ping(np.zeros((4, 3), np.uint8), [-100, 0, 100], 0.01)
    path = tmp_path / "a.oculus"
    write_oculus_log(path, [msg], [1.5], compress=True)
    raw = path.read_bytes()
    magic, size, src, ver, enc, _key, _t = struct.unpack_from("<2I16s2H4xqd", raw, 0)
    assert (magic, size, src.rstrip(b"\0"), ver, enc) == (0x11223344, 48, b"Oculus", 1, 0)
    imagic, isize, typ, _v, t, comp, orig, pay = struct.unpack_from("<2I2H4xdH2x2I4x", raw, 48)
    assert (imagic, isize, typ, t, comp, orig) == (0xAABBCCDD, 40, 10, 1.5, 1, len(msg))
    body = raw[88:88 + pay]
    assert struct.unpack(">I", body[:4])[0] == len(msg) and zlib.decompress(body[4:]) == msg


# ------------------------------------------------------------------ corrupt / truncated
def _truncation_points(fixed: int, n_beams: int, img_off: int, total: int) -> dict[str, int]:
    return {
        "in the message header": 9,
        "in the fixed ping header": fixed - 30,
        "in the bearings": fixed + n_beams,  # half the bearing table
        "between bearings and image": img_off - 1 if img_off > fixed + 2 * n_beams else img_off,
        "in the image": img_off + (total - img_off) // 2,
        "one byte short": total - 1,
    }


@needs_data
def test_truncated_oculus_files_are_rejected(tmp_path: Path) -> None:
    raw = OCU3.read_bytes()
    one = 182016
    for where, cut in _truncation_points(122, 256, 2048, one).items():
        for base in (0, one):  # inside the first message, and inside the second
            p = tmp_path / "cut.raw"
            p.write_bytes(raw[: base + cut])
            got = []
            with pytest.raises(FormatError) as e:
                for fr in open_oculus_raw(p):
                    got.append(fr)
            assert len(got) == base // one, where  # only whole pings before the cut
            assert e.value.offset is not None and e.value.offset <= base + cut, where
            assert "expected" in str(e.value) and f"byte {e.value.offset}" in str(e.value)


@needs_data
@pytest.mark.parametrize("offset, value, expect", [
    (0, b"\x00\x00", "0x4f53"),                       # oculusId
    (10, b"\x00\x00\x01\x00", "payloadSize"),         # payloadSize (too small)
    (8, b"\x07\x00", "msgVersion"),                    # msgVersion
    (97, b"\x05", "dataSize"),                         # dataSize
    (98, b"\x00" * 8, "rangeResolution"),              # rangeResolution = 0
    (114, b"\x01\x00\x00\x00", "imageSize"),           # imageSize
    (122 + 2 * 100, b"\x00\x80", "ascending bearings"),  # bearing -327.68 deg mid-table
    (118, b"\x00\x00\x00\x00", "messageSize"),
])
def test_corrupt_oculus_fields_are_rejected(tmp_path: Path, offset: int, value: bytes,
                                            expect: str) -> None:
    raw = bytearray(OCU1.read_bytes())
    raw[offset:offset + len(value)] = value
    p = tmp_path / "bad.raw"
    p.write_bytes(bytes(raw))
    with pytest.raises(FormatError, match=expect) as e:
        list(open_oculus_raw(p))
    assert e.value.offset is not None


def test_truncated_and_corrupt_oculus_log(tmp_path: Path) -> None:
    msg = encode_simple_ping(np.arange(60, dtype=np.uint8).reshape(20, 3), [-100, 5, 100], 0.01)
    path = tmp_path / "l.oculus"
    write_oculus_log(path, [msg, msg], [1.0, 2.0], compress=True)
    raw = path.read_bytes()
    item = (len(raw) - 48) // 2
    for cut in (20, 48 + 10, 48 + item - 3, 48 + item + 41):
        p = tmp_path / "cut.oculus"
        p.write_bytes(raw[:cut])
        with pytest.raises(FormatError, match="expected"):
            list(open_oculus_log(p))
    bad = bytearray(raw)
    bad[48 + 40 + 10] ^= 0xFF  # inside the zlib stream
    p = tmp_path / "bad.oculus"
    p.write_bytes(bytes(bad))
    with pytest.raises(FormatError, match="byte 48"):
        list(open_oculus_log(p))


# ------------------------------------------------------------------ ARIS
@needs_data
def test_aris_fields() -> None:
    rec = open_recording(ARIS)
    assert rec.kind == "aris" and rec.count() == 6 and not rec.has_poses
    frames = list(rec)
    assert len(frames) == 6
    for k, fr in enumerate(frames):
        assert fr.image.shape == (2000, 48)
        assert fr.meta["frame_index"] == k
        assert fr.spec.bin_centers_m[0] == pytest.approx(3.30, abs=0.005)
        assert fr.spec.bin_size_m == pytest.approx(0.01005, abs=1e-5)
        assert fr.spec.bin_centers_m[-1] == pytest.approx(23.4, abs=0.01)
        b = np.rad2deg(fr.spec.bearings_rad)
        assert b[0] == pytest.approx(-7.339) and b[-1] == pytest.approx(7.339)
        assert fr.timestamp_s == pytest.approx(1371198079.122519 + 0.1525 * k, abs=0.01)
    raw = ARIS.read_bytes()
    first = np.frombuffer(raw, np.uint8, count=96000, offset=2048).reshape(2000, 48)
    np.testing.assert_array_equal(np.round(frames[0].image * 255).astype(np.uint8), first)


def test_aris_round_trip(tmp_path: Path) -> None:
    rng = np.random.default_rng(2)
    imgs = [rng.integers(0, 256, size=(30, 8), dtype=np.uint8) for _ in range(2)]
    p = tmp_path / "x.aris"
    write_aris(p, imgs, sample_period_us=20, sample_start_delay_us=1000, sound_speed=1500.0)
    ang = np.linspace(-10, 10, 8)
    frames = list(open_aris(p, beam_angles_deg=ang))
    assert len(frames) == 2
    for f, im in zip(frames, imgs, strict=True):
        np.testing.assert_array_equal(np.round(f.image * 255).astype(np.uint8), im)
        assert f.spec.bin_centers_m[0] == pytest.approx(0.75)
        assert f.spec.bin_size_m == pytest.approx(0.015)
    # a table given positive-to-starboard is turned around so beam 0 stays right-most
    f = next(iter(open_aris(p, beam_angles_deg=-ang)))
    np.testing.assert_allclose(np.rad2deg(f.spec.bearings_rad), ang)


@needs_data
def test_truncated_and_corrupt_aris(tmp_path: Path) -> None:
    raw = ARIS.read_bytes()
    fs = 1024 + 96000
    cuts = {"file header": 500, "frame header": 1024 + 300, "image": 1024 + 1024 + 5000,
            "second frame": 1024 + fs + 10, "last byte": len(raw) - 1}
    for where, cut in cuts.items():
        p = tmp_path / "cut.aris"
        p.write_bytes(raw[:cut])
        got = []
        with pytest.raises(FormatError, match="expected") as e:
            for fr in open_aris(p, beam_table=DATA / "aris" / "beam_angles_ARIS_Telephoto_48.csv"):
                got.append(fr)
        assert len(got) == max(0, (cut - 1024) // fs), where
        assert e.value.offset is not None
    for off, val, expect in [(1024 + fs, b"\x09", "FrameIndex"), (3, b"\x04", "DDF_04"),
                             (1024 + 464, b"\0\0\0\0", "SoundSpeed")]:
        bad = bytearray(raw)
        bad[off:off + len(val)] = val
        p = tmp_path / "bad.aris"
        p.write_bytes(bytes(bad))
        with pytest.raises(FormatError, match=expect):
            list(open_aris(p, beam_table=DATA / "aris" / "beam_angles_ARIS_Telephoto_48.csv"))


def test_unknown_file_is_rejected(tmp_path: Path) -> None:
    p = tmp_path / "x.bin"
    p.write_bytes(b"hello world, not sonar")
    with pytest.raises(FormatError, match="expected a recording"):
        open_recording(p)


# ------------------------------------------------------------------ fan folder
@needs_data
def test_oasis_folder() -> None:
    rec = open_recording(OASIS)
    assert rec.kind == "fan-folder" and rec.has_poses and rec.count() == 123
    fr = next(iter(rec))
    assert fr.image.shape == (398, 512) and fr.T_W_S is not None
    np.testing.assert_allclose(fr.T_W_S[0], [0.697200845, -0.688577632, -0.199428750,
                                             0.190898336])
    assert fr.meta["frame"] == 0
    # nothing is invented: outside the picture's fan every polar cell is the (black) background
    assert 0.0 <= fr.image.min() and fr.image.max() <= 1.0


def test_fan_round_trip_bound() -> None:
    """polar -> fan -> polar loses only interpolation: exact on smooth images, bounded on edges."""
    spec = SonarSpec.uniform(hfov_deg=130, vfov_deg=20, n_beams=128, n_bins=100,
                             range_min_m=0.1, range_max_m=2.0)
    geom = FanGeometry(n_rows=400, n_cols=726, pixel_m=0.005, apex_row=399.0, apex_col=362.5)
    r = spec.bin_centers_m[:, None]
    th = spec.bearings_rad[None, :]
    smooth = (0.5 + 0.4 * np.sin(3 * r) * np.cos(2 * th)).astype(np.float32)
    back = fan_to_polar(polar_to_fan(smooth, spec, geom), spec, geom)
    inner = (slice(2, -2), slice(2, -2))  # away from the fan's outer edges
    err = np.abs(back - smooth)[inner]
    # measured: 1.5e-4 (bilinear twice, 5 mm pixels, 19 mm bins, 1 deg beams); bound 1e-3.
    # The outermost cells (half a cell from the fan's edge) mix in the black outside: up to
    # 0.24 there, which is why they are excluded.
    assert err.max() < 1e-3, err.max()
    # a single bright cell (worst case, a point target) keeps its place and most of its energy
    spot = np.zeros(spec.image_shape, np.float32)
    spot[60, 70] = 1.0
    b2 = fan_to_polar(polar_to_fan(spot, spec, geom), spec, geom)
    assert np.unravel_index(np.argmax(b2), b2.shape) == (60, 70)
    assert b2.max() >= 0.75 and b2.sum() == pytest.approx(1.0, abs=0.05)  # 0.83, 0.98


def test_fan_flip_options() -> None:
    spec = SonarSpec.uniform(hfov_deg=90, n_beams=64, n_bins=50, range_min_m=0.1,
                             range_max_m=1.0)
    g = FanGeometry(n_rows=201, n_cols=401, pixel_m=0.005, apex_row=200.0, apex_col=200.0)
    fan = np.zeros((201, 401), np.float32)
    fan[100:110, 250:260] = 1.0  # forward 0.5 m, to the left (+y) in the documented convention
    pol = fan_to_polar(fan, spec, g)
    j = np.argmax(pol.max(axis=0))
    assert spec.bearings_rad[j] > 0
    pol_lr = fan_to_polar(fan, spec, FanGeometry(**{**g.__dict__, "flip_lr": True}))
    assert spec.bearings_rad[np.argmax(pol_lr.max(axis=0))] < 0


# ------------------------------------------------------------------ PLY
@pytest.mark.parametrize("binary", [True, False])
def test_ply_round_trip(tmp_path: Path, binary: bool) -> None:
    rng = np.random.default_rng(3)
    pts = rng.normal(size=(100, 3)).astype(np.float32)
    val = rng.random(100).astype(np.float32)
    p = tmp_path / "a.ply"
    write_ply(p, pts, val, binary=binary)
    d = read_ply(p)
    np.testing.assert_allclose(np.stack([d["x"], d["y"], d["z"]], 1), pts, rtol=1e-6)
    np.testing.assert_allclose(d["intensity"], val, rtol=1e-6)
    head = p.read_bytes()[:200]
    assert head.startswith(b"ply\nformat " + (b"binary_little_endian" if binary else b"ascii"))


# ------------------------------------------------------------------ hostile files (issue #12)
# Builders are module-level so the fuzz suite can reuse them.
def zero_deflate(n_mib: int) -> bytes:
    """A zlib stream (header, no end) of ``n_mib`` MiB of zeros: ~1 KB per MiB."""
    c = zlib.compressobj(9)
    first = c.compress(bytes(1 << 20)) + c.flush(zlib.Z_FULL_FLUSH)
    block = c.compress(bytes(1 << 20)) + c.flush(zlib.Z_FULL_FLUSH)
    return first + block * (n_mib - 1)


def png_bytes(w: int, h: int, depth: int, ctype: int, idat: bytes, extra: bytes = b"") -> bytes:
    """A PNG from its parts (IHDR fields, compressed IDAT, extra chunks before IDAT)."""
    def chunk(t: bytes, d: bytes) -> bytes:
        return struct.pack(">I", len(d)) + t + d + struct.pack(">I", zlib.crc32(t + d) & 0xFFFFFFFF)

    ihdr = struct.pack(">IIBBBBB", w, h, depth, ctype, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + extra + chunk(b"IDAT", idat)
            + chunk(b"IEND", b""))


def png_chunk(t: bytes, d: bytes) -> bytes:
    return struct.pack(">I", len(d)) + t + d + struct.pack(">I", zlib.crc32(t + d) & 0xFFFFFFFF)


def _log_item(payload: bytes, orig: int, comp: int = 1, size_item: int = 40, t: float = 1.0) -> bytes:
    return struct.pack("<2I2H4xdH2x2I4x", 0xAABBCCDD, size_item, 10, 0, t, comp, orig,
                       len(payload)) + payload


def _log(items: bytes, size_header: int = 48) -> bytes:
    return struct.pack("<2I16s2H4xqd", 0x11223344, size_header, b"Oculus", 1, 0, 0, 0.0) + items


def _small_ping(version: int = 1) -> bytearray:
    return bytearray(encode_simple_ping(np.full((20, 8), 7, np.uint8),
                                        [-300, -200, -100, 0, 50, 100, 200, 300], 0.01,
                                        version=version))


def hostile_cases(tmp: Path) -> dict[str, tuple]:
    """name -> (callable that reads the file to the end, the gpumap error it must raise)."""
    from gpumap.io import LimitError, open_fan_folder
    from gpumap.io.fan import read_grey_png

    def put(name: str, data: bytes) -> Path:
        p = tmp / name
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(data)
        return p

    cases: dict[str, tuple] = {}
    msg = bytes(_small_ping())
    bomb = zero_deflate(2900)  # 3 MB that inflate to 2.9 GiB
    p = put("bomb.oculus", _log(_log_item(struct.pack(">I", 1000) + bomb, 1000)))
    cases["oculus log: 3 MB item declaring 1,000 B, inflating to 2.9 GiB"] = (
        lambda p=p: list(open_oculus_log(p)), FormatError)
    p = put("orig.oculus", _log(_log_item(struct.pack(">I", 2**32 - 1) + bomb[:5000], 2**32 - 1)))
    cases["oculus log: originalSize 4 GiB"] = (lambda p=p: list(open_oculus_log(p)), LimitError)
    item = bytearray(_log_item(msg, len(msg), comp=0))
    item[32:36] = struct.pack("<I", 2**32 - 1)
    p = put("payload.oculus", _log(bytes(item)))
    cases["oculus log: payloadSize 4 GiB"] = (lambda p=p: list(open_oculus_log(p)), LimitError)
    item = bytearray(_log_item(msg, len(msg), comp=0))
    item[4:8] = struct.pack("<I", 2**32 - 1)
    p = put("itemhead.oculus", _log(bytes(item)))
    cases["oculus log: item sizeHeader 4 GiB"] = (lambda p=p: list(open_oculus_log(p)), LimitError)
    p = put("filehead.oculus", _log(_log_item(msg, len(msg), comp=0), size_header=2**32 - 1))
    cases["oculus log: file sizeHeader 4 GiB"] = (lambda p=p: list(open_oculus_log(p)), LimitError)
    raw = _small_ping()
    raw[10:14] = struct.pack("<I", 2**32 - 16)
    p = put("payload.raw", bytes(raw))
    cases["oculus raw: payloadSize 4 GiB"] = (lambda p=p: list(open_oculus_raw(p)), LimitError)
    raw = _small_ping()
    raw[106:110] = struct.pack("<2H", 65535, 65535)
    p = put("dims.raw", bytes(raw))
    cases["oculus raw: 65535 x 65535 ping"] = (lambda p=p: list(open_oculus_raw(p)), LimitError)
    ang = np.linspace(-10, 10, 8)
    p = tmp / "big.aris"
    write_aris(p, [np.zeros((30, 8), np.uint8)] * 2)
    a = bytearray(p.read_bytes())
    a[16:20], a[24:28] = struct.pack("<I", 1024), struct.pack("<I", 100_000)
    p.write_bytes(bytes(a))
    cases["aris: 1024 beams x 100,000 samples"] = (
        lambda p=p: list(open_aris(p, beam_angles_deg=ang)), LimitError)
    a = bytearray(a)
    a[16:20], a[24:28], a[4:8] = struct.pack("<I", 8), struct.pack("<I", 30), struct.pack("<I", 2**32 - 1)
    p2 = put("count.aris", bytes(a))
    cases["aris: FrameCount 2^32 - 1"] = (lambda p=p2: list(open_aris(p, beam_angles_deg=ang)),
                                          FormatError)
    p = put("fan/sonar/image_0000.png", png_bytes(12000, 12000, 8, 0, zero_deflate(138)))
    cases["fan PNG: 12000 x 12000 (137 MiB of pixels)"] = (
        lambda p=p: read_grey_png(p, expected_shape=(398, 722)), LimitError)
    cases["fan folder: 12000 x 12000 picture"] = (lambda: list(open_fan_folder(tmp / "fan")), LimitError)
    p = put("huge.png", png_bytes(2**31 - 1, 2**31 - 1, 8, 0, zero_deflate(1)))
    cases["fan PNG: (2^31 - 1) x (2^31 - 1)"] = (lambda p=p: read_grey_png(p), LimitError)
    p = put("wide.png", png_bytes(723, 398, 8, 0, zero_deflate(1)))
    cases["fan PNG: 398 x 723, not the geometry's 398 x 722"] = (
        lambda p=p: read_grey_png(p, expected_shape=(398, 722)), FormatError)
    # a beam table found beside an ARIS file is read too: 16 MB of "1,2" rows took 0.9 GB, 12 s
    bt = tmp / "bt"
    bt.mkdir(exist_ok=True)
    write_aris(bt / "rec.aris", [np.zeros((30, 48), np.uint8)])
    (bt / "beam_angles_ARIS1800_1200_48.csv").write_bytes(b"beam,center_deg\n" + b"1,2\n" * 4_000_000)
    cases["aris: 16 MB beam angle table beside it"] = (lambda: list(open_recording(bt / "rec.aris")),
                                                       LimitError)
    p = put("poses/sonar_poses.csv", b"frame,")
    with open(p, "r+b") as f:
        f.truncate((64 << 20) + 1)  # sparse: the size is what is checked, before reading
    put("poses/sonar/image_0000.png", png_bytes(1, 1, 8, 0, zlib.compress(b"\0\0")))
    cases["fan folder: 64 MiB + 1 B pose table"] = (lambda: open_fan_folder(tmp / "poses"), LimitError)
    head = b"ply\nformat binary_little_endian 1.0\nelement vertex %d\nproperty float x\nend_header\n"
    p = put("huge.ply", head % 10**12 + bytes(64))
    cases["PLY: 10^12 vertices declared"] = (lambda p=p: read_ply(p), LimitError)
    p = put("short.ply", head % 10**8 + bytes(100))
    cases["PLY: 10^8 vertices declared, 100 bytes of data"] = (lambda p=p: read_ply(p), FormatError)
    p = put("ascii.ply", (head % 10**8).replace(b"binary_little_endian", b"ascii") + b"1\n" * 50)
    cases["PLY ascii: 10^8 vertices declared, 50 lines"] = (lambda p=p: read_ply(p), FormatError)
    return cases


def test_hostile_files_fail_fast_and_small(tmp_path: Path) -> None:
    """Every hostile file of issue #12 gives gpumap's error in < 1 s and far under 1 GB."""
    import time
    import tracemalloc

    from gpumap.limits import MEMORY_TARGET_BYTES

    for name, (read, err) in hostile_cases(tmp_path).items():
        tracemalloc.start()
        t0 = time.perf_counter()
        try:
            with pytest.raises(err) as e:
                read()
        finally:
            dt = time.perf_counter() - t0
            _cur, peak = tracemalloc.get_traced_memory()
            tracemalloc.stop()
        assert isinstance(e.value, FormatError) and "expected" in str(e.value), name
        assert dt < 1.0, (name, dt)
        assert peak < MEMORY_TARGET_BYTES // 16, (name, peak)  # measured: < 2 MB each


@pytest.mark.parametrize("res, match", [(1e-300, "range bins of at least"), (1e-320, "range bins"),
                                        (1e300, "range of at most"), (3000.0, "range of at most")])
def test_extreme_sonar_geometry_is_refused(res: float, match: str) -> None:
    """A ping whose rangeResolution is 1e-300 m decoded, then overflowed the mapper (1 / bin size
    to float32: OverflowError); geometry is now held to gpumap.limits at the reader."""
    from gpumap.limits import MAX_RANGE_M, MIN_BIN_SIZE_M

    msg = encode_simple_ping(np.zeros((5, 4), np.uint8), [-100, 0, 50, 100], res)
    with pytest.raises(FormatError, match=match) as e:
        decode_message(msg)
    assert e.value.offset == 162  # rangeResolution in the v2 layout (the default)
    fr = decode_message(encode_simple_ping(np.zeros((5, 4), np.uint8), [-100, 0, 50, 100], 2e-5))
    assert fr.spec.bin_size_m >= MIN_BIN_SIZE_M and fr.spec.range_max_m <= MAX_RANGE_M
    fr = decode_message(encode_simple_ping(np.zeros((5, 4), np.uint8), [-100, 0, 50, 100], 1999.0))
    assert fr.spec.range_max_m == pytest.approx(9995.0)


def test_oculus_log_inflation_is_exact(tmp_path: Path) -> None:
    msg = bytes(_small_ping(2))
    ok = struct.pack(">I", len(msg)) + zlib.compress(msg)
    p = tmp_path / "a.oculus"
    p.write_bytes(_log(_log_item(ok, len(msg))))
    assert len(list(open_oculus_log(p))) == 1
    bad = {
        "prefix differs": (struct.pack(">I", len(msg) + 1) + zlib.compress(msg), len(msg), "prefix"),
        "stream longer": (struct.pack(">I", len(msg) - 1) + zlib.compress(msg), len(msg) - 1,
                          "holds more"),
        "stream shorter": (struct.pack(">I", len(msg) + 1) + zlib.compress(msg), len(msg) + 1,
                           "gives"),
        "stream cut": (ok[:-6], len(msg), "cut short|failed"),
        "checksum": (ok[:-1] + bytes([ok[-1] ^ 1]), len(msg), "failed"),
    }
    for name, (payload, orig, match) in bad.items():
        p.write_bytes(_log(_log_item(payload, orig)))
        with pytest.raises(FormatError, match=match):
            list(open_oculus_log(p))
        assert name


def test_oculus_log_nonfinite_time_and_zero_header(tmp_path: Path) -> None:
    msg = bytes(_small_ping())
    p = tmp_path / "t.oculus"
    p.write_bytes(_log(_log_item(msg, len(msg), comp=0, t=float("nan"))))
    with pytest.raises(FormatError, match="finite item time"):
        list(open_oculus_log(p))
    # an item header of size 0 must not stall count()
    item = bytearray(_log_item(msg, len(msg), comp=0))
    item[4:8] = bytes(4)
    p.write_bytes(_log(bytes(item)))
    assert open_oculus_log(p).count() == 0
    with pytest.raises(FormatError, match="item header size"):
        list(open_oculus_log(p))


# ------------------------------------------------------------------ fan pictures of every PNG mode
def _pack_bits(vals: list[int], depth: int) -> bytes:
    bits = "".join(format(v, f"0{depth}b") for v in vals)
    bits += "0" * (-len(bits) % 8)
    return bytes(int(bits[i:i + 8], 2) for i in range(0, len(bits), 8))


def _png(w: int, h: int, depth: int, ctype: int, rows: list[bytes], extra: bytes = b"") -> bytes:
    return png_bytes(w, h, depth, ctype, zlib.compress(b"".join(b"\0" + r for r in rows)), extra)


def _luma(r, g, b):
    return (0.299 * np.asarray(r) + 0.587 * np.asarray(g) + 0.114 * np.asarray(b)) / 255.0


def _mode_cases() -> dict[str, tuple[bytes, np.ndarray, float]]:
    """name -> (PNG bytes, expected grey row, tolerance)."""
    v8 = [0, 1, 128, 255]
    v16 = [0, 1, 32768, 65535]
    pal = [(255, 0, 0), (0, 255, 0), (0, 0, 255), (10, 20, 30)]
    plte = png_chunk(b"PLTE", bytes(c for rgb in pal for c in rgb))
    out = {
        "1-bit": (_png(4, 1, 1, 0, [_pack_bits([0, 1, 1, 0], 1)]), np.array([0, 1, 1, 0.0]), 0),
        "2-bit grey": (_png(4, 1, 2, 0, [_pack_bits([0, 1, 2, 3], 2)]), np.array([0, 1, 2, 3]) / 3, 1e-6),
        "4-bit grey": (_png(4, 1, 4, 0, [_pack_bits([0, 1, 8, 15], 4)]), np.array([0, 1, 8, 15]) / 15,
                       1e-6),
        "8-bit grey (L)": (_png(4, 1, 8, 0, [bytes(v8)]), np.array(v8) / 255, 1e-7),
        "16-bit grey (I;16)": (_png(4, 1, 16, 0, [b"".join(struct.pack(">H", v) for v in v16)]),
                               np.array(v16) / 65535, 1e-7),
        "grey + alpha (LA), alpha ignored": (
            _png(4, 1, 8, 4, [b"".join(bytes([v, a]) for v, a in zip(v8, [0, 255, 7, 0], strict=True))]),
            np.array(v8) / 255, 1e-7),
        "16-bit grey + alpha": (
            _png(4, 1, 16, 4, [b"".join(struct.pack(">HH", v, 0) for v in v16)]),
            np.array([0, 0, 128, 255]) / 255, 1 / 255),
        "palette (P) by luminance": (
            _png(4, 1, 2, 3, [_pack_bits([0, 1, 2, 3], 2)], plte),
            _luma(*np.array(pal).T), 1 / 255),
        "palette + tRNS": (
            _png(4, 1, 8, 3, [bytes([3, 2, 1, 0])], plte + png_chunk(b"tRNS", bytes([0, 9, 255, 255]))),
            _luma(*np.array(pal[::-1]).T), 1 / 255),
        "RGB by luminance": (
            _png(4, 1, 8, 2, [bytes(c for rgb in pal for c in rgb)]), _luma(*np.array(pal).T), 1 / 255),
        "RGB grey stays exact": (
            _png(4, 1, 8, 2, [bytes(c for v in v8 for c in (v, v, v))]), np.array(v8) / 255, 1e-7),
        "RGBA, alpha ignored": (
            _png(4, 1, 8, 6, [bytes(c for rgb in pal for c in (*rgb, 0))]), _luma(*np.array(pal).T),
            1 / 255),
        "16-bit RGB": (_png(4, 1, 16, 2, [b"".join(struct.pack(">HHH", v, v, v) for v in v16)]),
                       np.array([0, 0, 128, 255]) / 255, 1 / 255),
    }
    return out


@pytest.mark.parametrize("name", list(_mode_cases()))
def test_fan_png_modes(tmp_path: Path, name: str) -> None:
    from gpumap.io.fan import read_grey_png

    data, expect, tol = _mode_cases()[name]
    p = tmp_path / "image_0000.png"
    p.write_bytes(data)
    a = read_grey_png(p, expected_shape=(1, 4))
    assert a.dtype == np.float32 and a.shape == (1, 4)
    assert np.all((a >= 0) & (a <= 1))
    np.testing.assert_allclose(a[0], expect, atol=tol + 1e-7)


def test_fan_folder_reads_palette_pictures(tmp_path: Path) -> None:
    """A palette picture is its grey levels, not its palette indices (the old misreading)."""
    from gpumap.io import open_fan_folder

    geom = FanGeometry(n_rows=40, n_cols=61, pixel_m=0.05, apex_row=39.0, apex_col=30.0)
    spec = SonarSpec.uniform(hfov_deg=90, n_beams=16, n_bins=20, range_min_m=0.1, range_max_m=1.9)
    grey = np.full((40, 61), 200, np.uint8)
    plte = png_chunk(b"PLTE", bytes([200, 200, 200]))  # index 0 -> grey 200
    rows = [bytes(61)] * 40
    (tmp_path / "sonar").mkdir()
    (tmp_path / "sonar" / "image_0000.png").write_bytes(_png(61, 40, 8, 3, rows, plte))
    (tmp_path / "sonar" / "image_0001.png").write_bytes(_png(61, 40, 8, 0, [r.tobytes() for r in grey]))
    a, b = (f.image for f in open_fan_folder(tmp_path, spec=spec, geom=geom))
    np.testing.assert_array_equal(a, b)
    assert a.max() == pytest.approx(200 / 255)


@pytest.mark.parametrize("damage", ["truncated", "bad IHDR CRC", "garbage IDAT", "not a PNG", "JPEG",
                                    "empty", "bad bit depth"])
def test_corrupt_png_is_a_format_error(tmp_path: Path, damage: str) -> None:
    from PIL import Image

    from gpumap.io.fan import read_grey_png

    good = _png(8, 4, 8, 0, [bytes(range(8))] * 4)
    data = {
        "truncated": good[:-30],
        "bad IHDR CRC": good[:29] + bytes([good[29] ^ 1]) + good[30:],
        "garbage IDAT": png_bytes(8, 4, 8, 0, b"\x78\x9c" + bytes(range(200, 240))),
        "not a PNG": b"hello, world" * 10,
        "empty": b"",
        "bad bit depth": png_bytes(8, 4, 3, 0, zlib.compress(bytes(40))),
    }.get(damage)
    if damage == "JPEG":
        buf = io.BytesIO()
        Image.fromarray(np.zeros((4, 8), np.uint8)).save(buf, format="JPEG")
        data = buf.getvalue()
    p = tmp_path / "image_0000.png"
    p.write_bytes(data)
    with pytest.raises(FormatError, match="expected"):
        read_grey_png(p, expected_shape=(4, 8))


# ------------------------------------------------------------------ pose tables
_HEAD = "frame," + ",".join(f"T_W_S_{i}{j}" for i in range(4) for j in range(4))
_EYE = ",".join(str(v) for v in np.eye(4).reshape(-1))


@pytest.mark.parametrize("rows, match", [
    ([f"0,{_EYE}", f"10,{_EYE}", f"10,{_EYE}"], "frame 10 is also on line 3"),
    ([f"0,{_EYE}", f"20,{_EYE}", f"10,{_EYE}"], "ascending order.*frame 10 comes after frame 20"),
    ([f"0,{_EYE}", "1," + _EYE.replace("1.0", "nan", 1)], "line 3: expected finite"),
    ([f"0,{_EYE}", "1," + _EYE.replace("0.0", "inf", 1)], "line 3: expected finite"),
    ([f"0,{_EYE}", "1," + _EYE.replace("1.0", "2.0", 1)], "line 3: .*orthonormal"),
    ([f"0,{_EYE}", f"1,{_EYE},7"], "line 3: expected 17 fields"),
    ([f"x,{_EYE}"], "line 2: expected numbers"),
    ([f"-1,{_EYE}"], "frame number >= 0"),
    # a frame beyond int64 was an OverflowError when the table became an array
    ([f"0,{_EYE}", f"99999999999999999999,{_EYE}"], "frame number >= 0 and <= 9223372036854775807"),
    ([f"1_000,{_EYE}"], "not a decimal integer"),  # int() takes these, a CSV should not
    (["\u0663," + _EYE], "not a decimal integer"),  # an Arabic-Indic 3
])
def test_pose_table_is_checked(tmp_path: Path, rows: list[str], match: str) -> None:
    from gpumap.io.fan import read_poses_csv

    p = tmp_path / "sonar_poses.csv"
    p.write_text("\n".join([_HEAD, *rows]) + "\n")
    with pytest.raises(FormatError, match=match):
        read_poses_csv(p)


def test_pose_table_time_column(tmp_path: Path) -> None:
    from gpumap.io.fan import read_pose_table

    head = _HEAD.replace("frame,", "frame,time_s,")
    p = tmp_path / "sonar_poses.csv"
    p.write_text("\n".join([head, f"0,10.0,{_EYE}", f"5,10.5,{_EYE}"]) + "\n")
    frames, times, T = read_pose_table(p)
    assert frames.tolist() == [0, 5] and times.tolist() == [10.0, 10.5] and T.shape == (2, 4, 4)
    for rows, match in [([f"0,10.0,{_EYE}", f"5,10.0,{_EYE}"], "time_s to increase"),
                        ([f"0,nan,{_EYE}"], "finite time_s")]:
        p.write_text("\n".join([head, *rows]) + "\n")
        with pytest.raises(FormatError, match=match):
            read_pose_table(p)
    for text, match in [(b"\xff\xfe\x00garbage", "UTF-8"), (b"frame,a,b\n", "header"),
                        (b"", "header"), (_HEAD.encode() + b"\n0,\x00" + b",0" * 15, "line 2|NUL")]:
        p.write_bytes(text)
        with pytest.raises(FormatError, match=match):
            read_pose_table(p)


@needs_data
def test_real_pose_table_passes_the_checks() -> None:
    from gpumap.io.fan import read_pose_table

    frames, times, T = read_pose_table(OASIS / "sonar_poses.csv")
    assert len(frames) == 123 and times is None and np.all(np.diff(frames) > 0)


def test_fan_folder_refuses_two_pictures_of_one_frame(tmp_path: Path) -> None:
    from gpumap.io import open_fan_folder

    (tmp_path / "sonar").mkdir()
    for name in ("image_10.png", "image_010.png"):
        (tmp_path / "sonar" / name).write_bytes(_png(4, 1, 8, 0, [bytes(4)]))
    with pytest.raises(FormatError, match="both frame 10"):
        open_fan_folder(tmp_path)
    (tmp_path / "sonar" / "image_010.png").unlink()
    assert open_fan_folder(tmp_path).count() == 1
    for bad in (0, -1, 1.5, True):
        with pytest.raises(ValueError, match="stride >= 1"):
            open_fan_folder(tmp_path, stride=bad)
    import os

    os.mkfifo(tmp_path / "sonar" / "image_0001.png")  # decoding it would block for ever
    with pytest.raises(FormatError, match="regular files"):
        open_fan_folder(tmp_path)


# ------------------------------------------------------------------ PLY checks and atomic writes
def test_ply_cut_on_a_record_boundary_is_refused(tmp_path: Path) -> None:
    p = tmp_path / "a.ply"
    write_ply(p, np.ones((10, 3)), np.zeros(10))
    raw = p.read_bytes()
    for cut, match in [(len(raw) - 16, "cut short"), (len(raw) - 3, "cut short")]:
        p.write_bytes(raw[:cut])
        with pytest.raises(FormatError, match=match):
            read_ply(p)
    p.write_bytes(raw + bytes(16))
    with pytest.raises(FormatError, match="left over"):
        read_ply(p)
    write_ply(p, np.ones((10, 3)), binary=False)
    raw = p.read_bytes()
    p.write_bytes(raw[: raw.rindex(b"1 1 1\n")])  # one whole line short
    with pytest.raises(FormatError, match="expected 10"):
        read_ply(p)


_PLY_HEAD = "ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\nend_header\n"


@pytest.mark.parametrize("header, match", [
    ("plx\n", "starting 'ply'"),
    ("ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\n", "end_header"),
    (_PLY_HEAD.replace("1.0", "2.0"), "format"),
    (_PLY_HEAD.replace("binary_little_endian", "utf8"), "format"),
    (_PLY_HEAD.replace("vertex 1", "vertex abc"), "integer element count"),
    (_PLY_HEAD.replace("vertex 1", "vertex -5"), "count >= 0"),
    (_PLY_HEAD.replace("vertex 1", "vertex"), "element <name> <count>"),
    (_PLY_HEAD.replace("float x", "quaternion x"), "PLY type"),
    (_PLY_HEAD.replace("float x", "float"), "property <type> <name>"),
    (_PLY_HEAD.replace("float x", "list uchar int idx"), "list property"),
    (_PLY_HEAD.replace("property float x\n", "property float x\nproperty float x\n"), "repeats"),
    (_PLY_HEAD.replace("element vertex 1\n", "property float y\nelement vertex 1\n"), "'element' before"),
    (_PLY_HEAD.replace("end_header", "element face 3\nend_header"), "only a vertex element"),
    (_PLY_HEAD.replace("element vertex 1\nproperty float x\n", "element face 0\n"), "element vertex"),
    (_PLY_HEAD.replace("format", "frobnicate"), "header keyword"),
    (_PLY_HEAD.replace("end_header", "comment \xe9\nend_header"), "ASCII header"),
    ("ply\n" + "comment x\n" * 20000, "end_header"),
])
def test_malformed_ply_headers(tmp_path: Path, header: str, match: str) -> None:
    p = tmp_path / "bad.ply"
    p.write_bytes(header.encode("latin-1") + bytes(4))
    with pytest.raises(FormatError, match=match):
        read_ply(p)


def test_ply_types_and_ascii_values(tmp_path: Path) -> None:
    p = tmp_path / "t.ply"
    head = ("ply\nformat binary_big_endian 1.0\nelement vertex 2\nproperty double x\n"
            "property uchar c\nproperty int i\nelement face 0\nproperty list uchar int idx\nend_header\n")
    rec = np.array([(1.5, 7, -3), (2.5, 255, 4)], dtype=[("x", ">f8"), ("c", "u1"), ("i", ">i4")])
    p.write_bytes(head.encode() + rec.tobytes())
    d = read_ply(p)
    assert d["x"].tolist() == [1.5, 2.5] and d["c"].tolist() == [7, 255] and d["i"].tolist() == [-3, 4]
    assert d["x"].dtype == np.float64 and d["c"].dtype == np.uint8
    head = "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty uchar c\nend_header\n"
    p.write_text(head + "1.5 7\n2.5 255\n")
    d = read_ply(p)
    assert d["c"].tolist() == [7, 255] and d["x"].dtype == np.float32
    for body, match in [("1.5 7\n2.5 256\n", "0..255"), ("1.5 7\n2.5 1.5\n", "integer"),
                        ("1.5 7\n2.5\n", "numbers"), ("1.5 7\nabc 1\n", "numbers"),
                        ("1.5 7\x0c2.5 255\n", "expected 2 vertex lines")]:  # a form feed is no newline
        p.write_text(head + body)
        with pytest.raises(FormatError, match=match):
            read_ply(p)


def test_write_ply_is_atomic(tmp_path: Path, monkeypatch) -> None:
    import os

    p = tmp_path / "a.ply"
    write_ply(p, np.zeros((5, 3)))
    p.chmod(0o640)
    before = p.read_bytes()

    def boom(fd):
        raise OSError("disk full")

    monkeypatch.setattr(os, "fsync", boom)
    with pytest.raises(OSError, match="disk full"):
        write_ply(p, np.ones((500, 3)))
    monkeypatch.undo()
    assert p.read_bytes() == before and sorted(x.name for x in tmp_path.iterdir()) == ["a.ply"]
    write_ply(p, np.ones((7, 3)))
    assert len(read_ply(p)["x"]) == 7 and (p.stat().st_mode & 0o777) == 0o640
    with pytest.raises(TypeError, match="complex"):
        write_ply(p, np.ones((2, 3), np.complex64))


# ------------------------------------------------------------------ content before extension
def test_open_recording_decides_by_content(tmp_path: Path) -> None:
    rng = np.random.default_rng(7)
    aris = tmp_path / "rec.bin"
    write_aris(aris, [rng.integers(0, 255, (30, 48), dtype=np.uint8)])
    (tmp_path / "beam_angles_ARIS1800_1200_48.csv").write_text(
        "beam,center_deg\n" + "".join(f"{k},{-12 + 0.5 * k}\n" for k in range(48)))
    assert open_recording(aris).kind == "aris"  # no telling extension: content decides
    raw = tmp_path / "ping.dat"
    raw.write_bytes(bytes(_small_ping()))
    assert open_recording(raw).kind == "oculus-raw"
    for name, data, match in [
        ("x.oculus", aris.read_bytes(), "extension '.oculus' says.*content is an ARIS"),
        ("x.aris", raw.read_bytes(), "extension '.aris' says.*Oculus network messages"),
        ("x.bag", raw.read_bytes(), "ROS 1 bag"),
        ("x.aris", b"nothing like ARIS", "extension '.aris' says, but the file starts"),
        ("x.bag.dat", b"#ROSBAG V2.0\n" + bytes(20), "named '\\*.bag'"),
        ("pic.png", _png(4, 1, 8, 0, [bytes(4)]), "single PNG"),
        ("empty", b"", "expected a recording"),
    ]:
        p = tmp_path / name
        p.write_bytes(data)
        with pytest.raises(FormatError, match=match):
            open_recording(p)


def test_open_recording_refuses_pipes_and_devices(tmp_path: Path) -> None:
    import os

    fifo = tmp_path / "rec.oculus"
    os.mkfifo(fifo)  # reading it would block for ever
    for p in (fifo, Path("/dev/zero")):
        with pytest.raises(FormatError, match="regular file"):
            open_recording(p)


def test_corrupt_ros_bag_is_a_format_error(tmp_path: Path) -> None:
    p = tmp_path / "broken.bag"
    p.write_bytes(b"#ROSBAG V2.0\n" + bytes(range(256)) * 8)
    with pytest.raises(FormatError, match="bag"):
        open_recording(p)
    d = tmp_path / "bag2"
    d.mkdir()
    (d / "metadata.yaml").write_text("rosbag2_bagfile_information: {version: 9, storage_identifier: x}\n")
    with pytest.raises(FormatError, match="bag"):
        open_recording(d)


def tiny_bag(path: Path, *, n_images: int = 2, data_len: int | None = None,
             pose_x: float | None = None) -> None:
    """A ROS 1 bag: 3 PoseStamped (x = 0, 0.1, 0.2 m at 10, 11, 12 s) and ProjectedSonarImages
    at 10.5, 11.5 s of 20 ranges (bin centres ``(i + 0.5) * 5 cm``, float32) x 8 beams."""
    pytest.importorskip("rosbags")
    from rosbags.rosbag1 import Writer

    from gpumap.io.rosbag import PSI, make_typestore

    ts = make_typestore(ros1=True)
    T = ts.types
    Header, Time = T["std_msgs/msg/Header"], T["builtin_interfaces/msg/Time"]
    with Writer(path) as w:
        ci = w.add_connection("/sonar/image", PSI, typestore=ts)
        cp = w.add_connection("/sonar/pose", "geometry_msgs/msg/PoseStamped", typestore=ts)
        for k in range(3):
            msg = T["geometry_msgs/msg/PoseStamped"](
                header=Header(seq=k, stamp=Time(sec=10 + k, nanosec=0), frame_id="world"),
                pose=T["geometry_msgs/msg/Pose"](
                    position=T["geometry_msgs/msg/Point"](x=0.1 * k if pose_x is None else pose_x,
                                                          y=0.0, z=0.0),
                    orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)))
            w.write(cp, (10 + k) * 10**9, ts.serialize_ros1(msg, "geometry_msgs/msg/PoseStamped"))
        az = np.linspace(-0.5, 0.5, 8)
        dirs = [T["geometry_msgs/msg/Vector3"](x=0.0, y=float(-math.sin(a)), z=float(math.cos(a)))
                for a in az]
        for k in range(n_images):
            data = np.full(20 * 8, 9 * (k + 1), np.uint8)[:data_len]
            msg = T[PSI](
                header=Header(seq=k, stamp=Time(sec=10 + k, nanosec=500_000_000), frame_id="sonar"),
                ping_info=T["marine_acoustic_msgs/msg/PingInfo"](
                    frequency=1e6, sound_speed=1500.0, tx_beamwidths=np.zeros(0, np.float32),
                    rx_beamwidths=np.zeros(0, np.float32)),
                beam_directions=dirs, ranges=((np.arange(20) + 0.5) * 0.05).astype(np.float32),
                image=T["marine_acoustic_msgs/msg/SonarImageData"](
                    is_bigendian=False, dtype=0, beam_count=8, data=data))
            w.write(ci, int((10.5 + k) * 1e9), ts.serialize_ros1(msg, PSI))


def test_ros_bag_errors_are_format_errors(tmp_path: Path) -> None:
    """A bag cut anywhere, a short image, a NaN pose: gpumap's error naming what, never a
    rosbags/struct traceback; the intact bag reads (bins starting at 0 m despite float32)."""
    p = tmp_path / "a.bag"
    tiny_bag(p)
    frames = list(open_recording(p))
    assert len(frames) == 2 and frames[0].spec.range_min_m == 0.0  # was a -6e-9 m refusal
    assert frames[0].spec.range_max_m == pytest.approx(1.0)
    np.testing.assert_allclose(frames[0].T_W_S[:3, 3], [0.05, 0, 0], atol=1e-12)  # interpolated
    assert frames[1].image.max() == pytest.approx(18 / 255)
    raw = p.read_bytes()
    q = tmp_path / "cut.bag"
    for cut in range(13, len(raw), max(1, len(raw) // 80)):
        q.write_bytes(raw[:cut])
        with pytest.raises(FormatError, match="expected|bag"):
            list(open_recording(q))
    q.unlink()
    tiny_bag(q, data_len=100)
    with pytest.raises(FormatError, match="message 0 on /sonar/image: expected 20 x 8 x 1 = 160"):
        list(open_recording(q))
    q.unlink()
    tiny_bag(q, pose_x=float("nan"))
    with pytest.raises(FormatError, match="pose message 0 on /sonar/pose: expected a finite pose"):
        open_recording(q)


def test_errors_are_one_family() -> None:
    import pickle

    import gpumap.errors
    import gpumap.io
    from gpumap.io import LimitError

    assert gpumap.io.FormatError is gpumap.errors.FormatError and issubclass(FormatError, ValueError)
    assert issubclass(LimitError, FormatError)
    e = pickle.loads(pickle.dumps(LimitError("expected less", offset=12, path="f")))
    assert type(e) is LimitError and (e.offset, e.path) == (12, "f")
    assert str(e) == "f, byte 12: expected less"


def test_limits_agree_with_the_map_side() -> None:
    """gpumap.limits states the map-side limits too; they must match what spec/mapper enforce."""
    import gpumap.core.mapfile
    import gpumap.spec
    from gpumap import limits

    for mod, name, ours in [(gpumap.spec, "_MAX_VOXELS", limits.MAX_GRID_VOXELS),
                            (gpumap.core.mapfile, "_META_MAX_BYTES", limits.MAX_MAP_META_BYTES),
                            (gpumap.core.mapfile, "_DEFLATE_MAX_RATIO", limits.MAX_DEFLATE_RATIO)]:
        theirs = getattr(mod, name)  # a limit that moved must be followed here, not skipped
        if theirs is not ours:
            assert theirs == ours, (mod.__name__, name)
    with pytest.raises(LimitErrorT := limits.LimitError, match="at most 10"):
        limits.check_size(11, 10, "x")
    with pytest.raises(FormatError, match="holds only 3"):
        limits.check_size(5, 10, "x", available=3)
    assert limits.check_size(np.uint32(5), 10, "x") == 5 and LimitErrorT is not FormatError
