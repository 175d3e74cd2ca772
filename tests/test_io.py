"""Readers against the real recordings in ../shared/data, round trips, and corrupt files."""

from __future__ import annotations

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
