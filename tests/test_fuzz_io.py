"""Fuzz every reader with mutated copies of the real recordings in ../shared/data (issue #12).

Each case takes a real file (or one derived from real data: the ``.oculus`` logs and the
ROS bag wrap the real Oculus pings, the PLY holds the real tank poses' positions), applies
a few mutations -- byte flips, truncations, inserted and deleted spans, header fields
overwritten with extreme values (0, 1, maxima, 2^31, NaN, inf, ...), PNG header fields
with their CRC fixed, CSV and PLY tokens replaced -- and reads it to the end through
``open_recording`` (or ``read_ply``). The property: the reader either yields frames that
pass the frame checks (float32, the spec's shape, finite, in [0, 1], finite poses and
times) and then stops or raises gpumap's :class:`~gpumap.errors.FormatError` -- never any
other exception.

Every case runs in a child process (one, reused; started fresh after a kill) whose
address space is capped with ``RLIMIT_AS`` at its own footprint plus
``gpumap.limits.MEMORY_TARGET_BYTES`` (1 GiB), so a reader that tries to allocate what a
file declares fails with ``MemoryError`` (a failure here) instead of taking the machine;
each case must also finish within ``TIME_CAP_S`` (1 s) of CPU-bound work, or the child is
killed and the case fails.

Budget: ``derandomize=True`` (a fixed seed per test, no example database), a fixed
``max_examples`` per reader (``GPUMAP_FUZZ_EXAMPLES`` scales it for longer local runs;
default 1.0 = about 1,100 cases, ~35 s on 2 cores). Skipped when ../shared/data is absent.
"""

from __future__ import annotations

import io
import math
import multiprocessing as mp
import os
import struct
import time
import traceback
import zlib
from pathlib import Path

import numpy as np
import pytest
from conftest import DATA, needs_data
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

pytestmark = needs_data

TIME_CAP_S = 1.0
SCALE = float(os.environ.get("GPUMAP_FUZZ_EXAMPLES", "1.0"))


def _examples(n: int) -> int:
    return max(1, int(round(n * SCALE)))


def _fuzz_settings(n: int):
    return settings(max_examples=_examples(n), deadline=None, derandomize=True, database=None,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


# ------------------------------------------------------------------ the capped child process
def _frame_problem(fr) -> str | None:
    """What is wrong with a frame a reader yielded (None when it passes the checks)."""
    from gpumap.io import SonarFrame

    if not isinstance(fr, SonarFrame):
        return f"yielded {type(fr).__name__}, not a SonarFrame"
    img = fr.image
    if not isinstance(img, np.ndarray) or img.dtype != np.float32 or img.ndim != 2:
        return f"image is {type(img).__name__} {getattr(img, 'dtype', '')}, not 2-D float32"
    if img.shape != fr.spec.image_shape:
        return f"image shape {img.shape} != spec {fr.spec.image_shape}"
    if not np.all(np.isfinite(img)):
        return "image has NaN or inf"
    if img.size and (img.min() < 0.0 or img.max() > 1.0):
        return f"image values {img.min()}..{img.max()} outside [0, 1]"
    if fr.T_W_S is not None and (fr.T_W_S.shape != (4, 4) or not np.all(np.isfinite(fr.T_W_S))):
        return "T_W_S is not a finite 4x4"
    if fr.timestamp_s is not None and not math.isfinite(fr.timestamp_s):
        return f"timestamp {fr.timestamp_s} is not finite"
    return None


def _read_case(kind: str, root: Path) -> int:
    """Read the case to the end the way a user would; returns the number of frames."""
    from gpumap.io import open_recording, read_ply

    if kind == "__alloc__":  # harness self-test: the memory cap
        return int(np.ones(2**31, dtype=np.uint8).sum())
    if kind == "__sleep__":  # harness self-test: the time cap
        time.sleep(3 * TIME_CAP_S + 5.0)
        return 0
    if kind == "ply":
        d = read_ply(root / "cloud.ply")
        n = {len(v) for v in d.values()}
        if len(n) > 1:
            raise AssertionError(f"read_ply returned columns of different lengths {n}")
        return 0
    target = {"fan": root, "aris": root / "rec.aris", "oculus-raw": root / "rec.raw",
              "oculus-log": root / "rec.oculus", "rosbag": root / "rec.bag"}[kind]
    rec = open_recording(target)
    rec.count()
    rec.poses()
    n = 0
    for fr in rec:
        problem = _frame_problem(fr)
        if problem:
            raise AssertionError(f"frame {n}: {problem}")
        n += 1
    return n


def _warm_up(files: dict[str, dict[str, bytes]], work: Path) -> None:
    """Read each real case once before the cap: lazy imports and caches are not the case's cost."""
    for kind, case in files.items():
        root = work / f"warm-{kind}"
        for rel, data in case.items():
            (root / rel).parent.mkdir(parents=True, exist_ok=True)
            (root / rel).write_bytes(data)
        _read_case(kind, root)


def _worker_main(conn, mem_cap: int, warm: dict) -> None:
    import resource
    import shutil
    import tempfile

    import gpumap.io
    import gpumap.io.rosbag  # noqa: F401  (imports before the cap)
    from gpumap.errors import FormatError

    work = Path(tempfile.mkdtemp(prefix="gpumap-fuzz-"))
    try:
        _warm_up(warm, work)
        vm = int(Path("/proc/self/statm").read_text().split()[0]) * os.sysconf("SC_PAGE_SIZE")
        _soft, hard = resource.getrlimit(resource.RLIMIT_AS)
        cap = vm + mem_cap
        if hard != resource.RLIM_INFINITY:
            cap = min(cap, hard)
        resource.setrlimit(resource.RLIMIT_AS, (cap, hard))
        conn.send(("ready", vm, cap))
        k = 0
        while True:
            job = conn.recv()
            if job is None:
                return
            kind, case = job
            k += 1
            root = work / f"case{k}"
            t0 = time.perf_counter()
            try:
                for rel, data in case.items():
                    (root / rel).parent.mkdir(parents=True, exist_ok=True)
                    (root / rel).write_bytes(data)
                t0 = time.perf_counter()
                n = _read_case(kind, root)
                out = ("frames", n, "")
            except FormatError as e:
                out = ("gpumap-error", type(e).__name__, str(e)[:300])
            except BaseException as e:  # noqa: BLE001 - everything else is the finding
                out = ("other", type(e).__name__, traceback.format_exc()[-3000:])
            dt = time.perf_counter() - t0
            shutil.rmtree(root, ignore_errors=True)
            conn.send((*out, dt))
    finally:
        shutil.rmtree(work, ignore_errors=True)


class CappedRunner:
    """One child process under RLIMIT_AS that reads cases; killed and restarted on a time-out."""

    def __init__(self, warm: dict, mem_cap: int) -> None:
        self.ctx = mp.get_context("spawn")  # a fresh interpreter: no threads or GPU contexts forked
        self.warm, self.mem_cap = warm, mem_cap
        self.proc = None
        self.cap_info = None
        self._start()

    def _start(self) -> None:
        parent, child = self.ctx.Pipe()
        saved = {k: os.environ.get(k) for k in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS")}
        os.environ.update(OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1")
        try:
            self.proc = self.ctx.Process(target=_worker_main, args=(child, self.mem_cap, self.warm),
                                         daemon=True)
            self.proc.start()
        finally:
            for k, v in saved.items():
                if v is None:
                    os.environ.pop(k, None)
                else:
                    os.environ[k] = v
        child.close()
        self.conn = parent
        if not parent.poll(120):
            raise RuntimeError("the fuzz worker did not start within 120 s")
        msg = parent.recv()
        assert msg[0] == "ready", msg
        self.cap_info = msg[1:]

    def run(self, kind: str, case: dict[str, bytes]) -> tuple:
        """-> (status, detail, message, seconds); status 'frames', 'gpumap-error', 'other',
        'timeout' or 'died'."""
        try:
            self.conn.send((kind, case))
            if not self.conn.poll(2 * TIME_CAP_S + 2.0):
                self._restart()
                return ("timeout", "", f"no answer within {2 * TIME_CAP_S + 2.0} s", math.inf)
            return self.conn.recv()
        except (EOFError, BrokenPipeError, ConnectionResetError):
            code = self.proc.exitcode
            self._restart()
            return ("died", str(code), "the child process died (memory cap or crash)", math.inf)

    def _restart(self) -> None:
        self.proc.kill()
        self.proc.join(10)
        self._start()

    def close(self) -> None:
        try:
            self.conn.send(None)
        except (BrokenPipeError, OSError):
            pass
        self.proc.join(10)
        if self.proc.is_alive():
            self.proc.kill()


# ------------------------------------------------------------------ seed files (real data)
def _log_item_offsets(raw: bytes) -> list[int]:
    out, off = [], struct.unpack_from("<I", raw, 4)[0]
    while off + 40 <= len(raw):
        out.append(off)
        (size_item,) = struct.unpack_from("<I", raw, off + 4)
        (payload,) = struct.unpack_from("<I", raw, off + 32)
        off += size_item + payload
    return out


def _ros1_bag(path: Path, raw_pings: bytes) -> None:
    """A ROS 1 bag of the real Oculus pings as ProjectedSonarImage, with PoseStamped poses."""
    from rosbags.rosbag1 import Writer

    from gpumap.io import decode_message
    from gpumap.io.oculus import iter_raw_messages
    from gpumap.io.rosbag import PSI, make_typestore

    tmp = path.with_suffix(".raw")
    tmp.write_bytes(raw_pings)
    frames = [decode_message(m) for _o, m in iter_raw_messages(tmp)]
    tmp.unlink()
    ts = make_typestore(ros1=True)
    T = ts.types
    Header, Time = T["std_msgs/msg/Header"], T["builtin_interfaces/msg/Time"]
    with Writer(path) as w:
        ci = w.add_connection("/sonar/image", PSI, typestore=ts)
        cp = w.add_connection("/sonar/pose", "geometry_msgs/msg/PoseStamped", typestore=ts)
        for k in range(4):
            st_ = Time(sec=10 + k, nanosec=0)
            msg = T["geometry_msgs/msg/PoseStamped"](
                header=Header(seq=k, stamp=st_, frame_id="world"),
                pose=T["geometry_msgs/msg/Pose"](
                    position=T["geometry_msgs/msg/Point"](x=0.1 * k, y=0.0, z=0.0),
                    orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)))
            w.write(cp, (10 + k) * 10**9, ts.serialize_ros1(msg, "geometry_msgs/msg/PoseStamped"))
        for k, fr in enumerate(frames[:2]):
            img = np.round(fr.image[::4] * 255).astype(np.uint8)  # every 4th range: a smaller bag
            az = fr.spec.bearings_rad
            dirs = [T["geometry_msgs/msg/Vector3"](x=0.0, y=float(-math.sin(a)), z=float(math.cos(a)))
                    for a in az]
            ranges = ((np.arange(img.shape[0]) + 0.5) * 4 * fr.spec.bin_size_m).astype(np.float32)
            msg = T[PSI](
                header=Header(seq=k, stamp=Time(sec=10 + k, nanosec=500_000_000), frame_id="sonar"),
                ping_info=T["marine_acoustic_msgs/msg/PingInfo"](
                    frequency=2.1e6, sound_speed=1490.0, tx_beamwidths=np.zeros(0, np.float32),
                    rx_beamwidths=np.zeros(0, np.float32)),
                beam_directions=dirs, ranges=ranges,
                image=T["marine_acoustic_msgs/msg/SonarImageData"](
                    is_bigendian=False, dtype=0, beam_count=img.shape[1], data=img.reshape(-1)))
            w.write(ci, int((10.5 + k) * 1e9), ts.serialize_ros1(msg, PSI))


class _Seeds(dict):
    """The seed files (kept out of Hypothesis' reports: they are megabytes)."""

    def __repr__(self) -> str:
        return f"<seed files: {', '.join(self)}>"


@pytest.fixture(scope="module")
def seeds(tmp_path_factory) -> dict:
    """kind -> {files: {relative path: bytes}, fields: [...], tokens: [...]} from the real data."""
    from gpumap.io import write_oculus_log, write_ply
    from gpumap.io.oculus import iter_raw_messages

    tmp = tmp_path_factory.mktemp("seeds")
    out = _Seeds()
    raw3 = (DATA / "oculus" / "three_pings_8bit.raw").read_bytes()
    msg_len = 16 + struct.unpack_from("<I", raw3, 10)[0]
    ping_fields = [(0, "<H"), (6, "<H"), (8, "<H"), (10, "<I"), (20, "B"), (21, "<d"), (93, "<I"),
                   (97, "B"), (98, "<d"), (106, "<H"), (108, "<H"), (110, "<I"), (114, "<I"),
                   (118, "<I"), (122, "<h"), (122 + 254, "<h"), (122 + 510, "<h")]
    out["oculus-raw"] = {"files": {"rec.raw": raw3},
                         "fields": [(b + o, f) for b in (0, msg_len) for o, f in ping_fields]}
    msgs = [m for _o, m in iter_raw_messages(DATA / "oculus" / "three_pings_8bit.raw")]
    for name, comp in (("rec.oculus", True), ("plain.oculus", False)):
        p = tmp / name
        write_oculus_log(p, msgs[:2], [1.7e9, 1.7e9 + 0.1], compress=comp)
        raw = p.read_bytes()
        items = _log_item_offsets(raw)
        fields = [(0, "<I"), (4, "<I"), (24, "<H"), (26, "<H")]
        for it in items:
            fields += [(it, "<I"), (it + 4, "<I"), (it + 8, "<H"), (it + 16, "<d"), (it + 24, "<H"),
                       (it + 28, "<I"), (it + 32, "<I")]
            if comp:
                fields += [(it + 40, ">I")]
            else:
                fields += [(it + 40 + o, f) for o, f in ping_fields]
        out["oculus-log" + ("" if comp else "-plain")] = {"files": {"rec.oculus": raw}, "fields": fields}
    aris = (DATA / "aris" / "sample.aris").read_bytes()
    tables = {f.name: f.read_bytes() for f in (DATA / "aris").glob("beam_angles_*.csv")}
    fs = 1024 + 96000
    frame_fields = [(0, "<I"), (4, "<Q"), (452, "<I"), (464, "<f"), (468, "<I"), (476, "<I"),
                    (480, "<I"), (484, "<I"), (516, "<I")]
    out["aris"] = {"files": {"rec.aris": aris, **tables},
                   "fields": [(3, "B"), (4, "<I"), (16, "<I"), (24, "<I")]
                   + [(1024 + k * fs + o, f) for k in (0, 1, 5) for o, f in frame_fields]}
    png = (DATA / "oasis_tank" / "sonar" / "image_0000.png").read_bytes()
    poses = (DATA / "oasis_tank" / "sonar_poses.csv").read_bytes()
    chunk_len_fields, i = [], 8
    while i + 8 <= len(png) and len(chunk_len_fields) < 6:
        chunk_len_fields.append((i, ">I"))
        i += 12 + struct.unpack_from(">I", png, i)[0]
    out["fan"] = {"files": {"sonar/image_0000.png": png, "sonar_poses.csv": poses},
                  "fields": [(16, ">I!"), (20, ">I!"), (24, "B!"), (25, "B!"), (26, "B!"), (27, "B!"),
                             (28, "B!"), *chunk_len_fields]}
    # the pose table alone, with a small picture (cheap to decode) beside it
    small = io.BytesIO()
    from PIL import Image

    with Image.open(io.BytesIO(png)) as im:
        im.save(small, format="PNG", compress_level=1)
    out["fan-csv"] = {"files": {"sonar/image_0000.png": small.getvalue(), "sonar_poses.csv": poses},
                      "fields": [], "text": "sonar_poses.csv"}
    T = np.loadtxt(io.BytesIO(poses), delimiter=",", skiprows=1)[:, 1:].reshape(-1, 4, 4)
    for binary in (True, False):
        p = tmp / "cloud.ply"
        write_ply(p, T[:, :3, 3], T[:, 0, 0], binary=binary)
        out["ply-bin" if binary else "ply-ascii"] = {"files": {"cloud.ply": p.read_bytes()},
                                                     "fields": [], "text": "cloud.ply"}
    bag = tmp / "rec.bag"
    _ros1_bag(bag, raw3)
    out["rosbag"] = {"files": {"rec.bag": bag.read_bytes()}, "fields": []}
    return out


def _kind(name: str) -> str:
    return {"oculus-log-plain": "oculus-log", "fan-csv": "fan", "ply-bin": "ply",
            "ply-ascii": "ply"}.get(name, name)


@pytest.fixture(scope="module")
def runner(seeds):
    from gpumap.limits import MEMORY_TARGET_BYTES

    warm = {_kind(k): v["files"] for k, v in seeds.items() if k in ("oculus-raw", "oculus-log", "aris",
                                                                   "fan", "ply-bin", "rosbag")}
    r = CappedRunner(warm, MEMORY_TARGET_BYTES)
    yield r
    r.close()


# ------------------------------------------------------------------ mutations
_INT_EXTREMES = [0, 1, 2, 3, 7, 255, 256, 65535, 65536, 2**31 - 1, 2**31, 2**32 - 1, 2**32 - 16,
                 2**63 - 1, 2**64 - 1, -1, -(2**31), 100_000, 1_000_000]
_FLOAT_EXTREMES = [0.0, -0.0, 1.0, -1.0, 1e-320, 1e-9, 1e9, 1e308, -1e308, math.inf, -math.inf,
                   math.nan, 3.4e38]
_TOKENS = [b"", b"0", b"-1", b"1", b"10", b"nan", b"inf", b"-inf", b"1e400", b"x", b"99999999999999999999",
           b"0.5", b"2.0", b"float", b"double", b"list", b"uchar", b"vertex", b"face", b"\xff\xfe",
           b"\x00", b",", b"\n", b"1,2", b"end_header", b"binary_big_endian", b"ascii"]

_pos = st.one_of(st.integers(0, 2048), st.integers(0, 2**31), st.integers(-4096, -1))
_mutation = st.one_of(
    st.tuples(st.just("flip"), _pos, st.integers(1, 255)),
    st.tuples(st.just("cut"), _pos),
    st.tuples(st.just("insert"), _pos, st.binary(min_size=1, max_size=48)),
    st.tuples(st.just("delete"), _pos, st.integers(1, 5000)),
    st.tuples(st.just("field"), st.integers(0, 10**6), st.integers(0, 10**6), st.booleans()),
    st.tuples(st.just("field"), st.integers(0, 10**6), st.integers(0, 10**6), st.booleans()),
    st.tuples(st.just("token"), st.integers(0, 10**6), st.integers(0, 10**6)),
)
MUTATIONS = st.lists(_mutation, min_size=1, max_size=4)


def _at(pos: int, n: int) -> int:
    if n == 0:
        return 0
    return pos % n if pos >= 0 else max(0, n + pos)


def _put_field(b: bytearray, off: int, fmt: str, pick: int, jitter: bool) -> None:
    """Overwrite a header field with an extreme value (``fmt`` a struct code; ``!`` = fix IHDR CRC)."""
    fix_crc = fmt.endswith("!")
    fmt = fmt.rstrip("!")
    size = struct.calcsize(fmt)
    if off + size > len(b):
        return
    code = fmt[-1]
    if code in "fd":
        v = _FLOAT_EXTREMES[pick % len(_FLOAT_EXTREMES)]
        if code == "f" and math.isfinite(v) and abs(v) > 3.4e38:
            v = math.copysign(3.4e38, v)
    else:
        v = _INT_EXTREMES[pick % len(_INT_EXTREMES)] + ((pick % 7) - 3 if jitter else 0)
        bits = 8 * size
        if code.isupper():  # unsigned: wrap into the field
            v %= 1 << bits
        else:
            v = ((v + (1 << (bits - 1))) % (1 << bits)) - (1 << (bits - 1))
    struct.pack_into(fmt, b, off, v)
    if fix_crc and len(b) >= 33:  # keep the IHDR chunk's CRC valid, so the header is believed
        struct.pack_into(">I", b, 29, zlib.crc32(bytes(b[12:29])) & 0xFFFFFFFF)


def _token_spans(b: bytes) -> list[tuple[int, int]]:
    """Spans of fields in a text file (split on whitespace and commas), in the first 64 KB."""
    spans, start = [], None
    for i, c in enumerate(b[:65536]):
        if c in b" \t\r\n,":
            if start is not None:
                spans.append((start, i))
                start = None
        elif start is None:
            start = i
    if start is not None:
        spans.append((start, min(len(b), 65536)))
    return spans


def mutate(data: bytes, muts: list[tuple], fields: list[tuple[int, str]], text: bool) -> bytes:
    b = bytearray(data)
    for m in muts:
        n = len(b)
        if m[0] == "flip" and n:
            b[_at(m[1], n)] ^= m[2]
        elif m[0] == "cut":
            del b[_at(m[1], n + 1):]
        elif m[0] == "insert":
            i = _at(m[1], n + 1)
            b[i:i] = m[2]
        elif m[0] == "delete" and n:
            i = _at(m[1], n)
            del b[i:i + m[2]]
        elif m[0] == "field" and fields:
            off, fmt = fields[m[1] % len(fields)]
            _put_field(b, off, fmt, m[2], m[3])
        elif m[0] == "token" and text:
            spans = _token_spans(bytes(b))
            if spans:
                s, e = spans[m[1] % len(spans)]
                b[s:e] = _TOKENS[m[2] % len(_TOKENS)]
    return bytes(b)


def _check(runner: CappedRunner, name: str, kind: str, case: dict[str, bytes]) -> None:
    status, detail, message, dt = runner.run(kind, case)
    event(f"{name}: {status} {detail}".strip())
    sizes = {k: len(v) for k, v in case.items()}
    assert status in ("frames", "gpumap-error"), f"{name}: {status} {detail}\n{message}\n(sizes {sizes})"
    assert dt < TIME_CAP_S, f"{name}: took {dt:.2f} s (cap {TIME_CAP_S} s); {status} {detail} {message}"


def _fuzz_one(runner, seeds, name: str, target: str, muts) -> None:
    seed = seeds[name]
    case = dict(seed["files"])
    case[target] = mutate(case[target], muts, seed["fields"], bool(seed.get("text")))
    _check(runner, name, _kind(name), case)


# ------------------------------------------------------------------ the harness itself
def test_harness_reads_the_real_files_and_enforces_its_caps(runner, seeds) -> None:
    expect = {"oculus-raw": 3, "oculus-log": 2, "oculus-log-plain": 2, "aris": 6, "fan": 1,
              "fan-csv": 1, "ply-bin": 0, "ply-ascii": 0, "rosbag": 2}
    for name, n in expect.items():
        status, detail, message, dt = runner.run(_kind(name), seeds[name]["files"])
        assert (status, detail) == ("frames", n), (name, status, detail, message)
        assert dt < TIME_CAP_S / 2, (name, dt)
    # the caps are real: 2 GiB cannot be had, and a hang is cut off (the child is replaced)
    status, detail, _m, _dt = runner.run("__alloc__", {})
    assert (status, detail) in (("other", "MemoryError"), ("died", "-9")), (status, detail)
    assert runner.run("__sleep__", {})[0] == "timeout"
    assert runner.run("aris", seeds["aris"]["files"])[:2] == ("frames", 6)
    vm, cap = runner.cap_info
    assert cap - vm <= 1 << 30


# ------------------------------------------------------------------ one property per reader
@_fuzz_settings(160)
@given(muts=MUTATIONS)
def test_fuzz_oculus_raw(runner, seeds, muts) -> None:
    _fuzz_one(runner, seeds, "oculus-raw", "rec.raw", muts)


@_fuzz_settings(120)
@given(muts=MUTATIONS)
def test_fuzz_oculus_log_compressed(runner, seeds, muts) -> None:
    _fuzz_one(runner, seeds, "oculus-log", "rec.oculus", muts)


@_fuzz_settings(120)
@given(muts=MUTATIONS)
def test_fuzz_oculus_log_plain(runner, seeds, muts) -> None:
    _fuzz_one(runner, seeds, "oculus-log-plain", "rec.oculus", muts)


@_fuzz_settings(160)
@given(muts=MUTATIONS)
def test_fuzz_aris(runner, seeds, muts) -> None:
    _fuzz_one(runner, seeds, "aris", "rec.aris", muts)


@_fuzz_settings(160)
@given(muts=MUTATIONS)
def test_fuzz_fan_png(runner, seeds, muts) -> None:
    _fuzz_one(runner, seeds, "fan", "sonar/image_0000.png", muts)


@_fuzz_settings(120)
@given(muts=MUTATIONS)
def test_fuzz_fan_pose_table(runner, seeds, muts) -> None:
    _fuzz_one(runner, seeds, "fan-csv", "sonar_poses.csv", muts)


@_fuzz_settings(100)
@given(muts=MUTATIONS, binary=st.booleans())
def test_fuzz_ply(runner, seeds, muts, binary) -> None:
    _fuzz_one(runner, seeds, "ply-bin" if binary else "ply-ascii", "cloud.ply", muts)


@_fuzz_settings(80)
@given(muts=MUTATIONS)
def test_fuzz_rosbag(runner, seeds, muts) -> None:
    _fuzz_one(runner, seeds, "rosbag", "rec.bag", muts)
