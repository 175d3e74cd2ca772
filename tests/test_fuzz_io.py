"""Fuzz every reader with mutated copies of the real recordings in ../shared/data (issue #12).

Each case takes a real file (or one derived from real data: the ``.oculus`` logs and the
ROS bag wrap the real Oculus pings, the PLY holds the real tank poses' positions), applies
a few mutations -- byte flips, truncations, inserted and deleted spans, header fields
overwritten with extreme values (0, 1, maxima, 2^31, NaN, inf, ...), PNG header fields
with their CRC fixed, CSV and PLY tokens replaced -- and reads it to the end through
``open_recording`` (or ``read_ply``). The property: the reader either yields frames that
pass the frame checks (float32, the spec's shape, finite, in [0, 1], finite poses and
times, a geometry within ``gpumap.limits``; the first frame must also integrate into a small
numpy map) and then stops or raises gpumap's :class:`~gpumap.errors.FormatError` -- never
any other exception.

Every case runs in a child process (one, reused; started fresh after a kill) whose
address space is capped with ``RLIMIT_AS`` at its own footprint plus
``gpumap.limits.MEMORY_TARGET_BYTES`` (1 GiB), so a reader that tries to allocate what a
file declares fails with ``MemoryError`` (a failure here) instead of taking the machine;
a case that ends in gpumap's error must cost under ``TIME_CAP_S`` (1 s) of the child's CPU
time, one that reads frames (and maps one) under ``WORK_CAP_S``; CPU time, not wall time, so
a busy machine does not fail the suite. A child that does not answer within ``HANG_S`` of
wall time is killed and the case fails.

``MinMaxMapper.load`` gets the same treatment on a saved map of real pings (members
mutated and the zip rebuilt). The hostile files of ``tests/test_io.py`` run in the same
capped child, their peak RSS measured by the kernel (``VmHWM``). Properties of the public
API built from drawn parameters (pose tables, PNGs of every colour type and depth, Oculus
messages, PLY round trips, any bytes under any name) know their answers independently.

Budget: ``derandomize=True`` (a fixed seed per test, no example database), a fixed
``max_examples`` per test (``GPUMAP_FUZZ_EXAMPLES`` scales them for longer local runs;
default 1.0 = about 3,400 cases: 57-92 s wall on 2 cores shared with other jobs (load
6-7), 22 s of CPU; 8x = 27,000 cases and 20x found nothing). The tests on mutated real
files skip, with the reason, when ../shared/data is absent; the others run anyway.
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
from conftest import DATA
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

TIME_CAP_S = 1.0  # CPU seconds to refuse a file (the "under a second")
WORK_CAP_S = 5.0  # CPU seconds to read a recording that yields frames and map its first
HANG_S = 60.0  # wall seconds without an answer: the child is killed
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
    from gpumap import limits

    if not (fr.spec.bin_size_m >= limits.MIN_BIN_SIZE_M and fr.spec.range_max_m <= limits.MAX_RANGE_M):
        return f"geometry beyond gpumap.limits: bins {fr.spec.bin_size_m} m, range {fr.spec.range_max_m} m"
    return None


def _map_one(fr) -> None:
    """What a user does next: integrate the frame (at its pose, or the origin) into a small map."""
    import gpumap

    grid = gpumap.GridSpec(min_corner_m=(-1, -1, -1), max_corner_m=(1, 1, 1), voxel_size_m=0.5)
    m = gpumap.MinMaxMapper(fr.spec, grid, backend="numpy")
    m.integrate(fr.image, fr.T_W_S if fr.T_W_S is not None else np.eye(4))
    v = m.values()
    if not np.all(np.isnan(v) | ((v >= 0) & (v <= 1))):
        raise AssertionError("the map holds values outside [0, 1]")


def _read_case(kind: str, root: Path) -> int:
    """Read the case to the end the way a user would; returns the number of frames."""
    from gpumap.io import open_recording, read_ply

    if kind == "__alloc__":  # harness self-test: the memory cap
        return int(np.ones(2**31, dtype=np.uint8).sum())
    if kind == "__sleep__":  # harness self-test: the time cap
        time.sleep(5.0)
        return 0
    if kind == "hostile":  # one of tests/test_io.py's hostile files, built before the cap
        name = (root / "name").read_text()
        read, _err = _HOSTILE[name]
        read()
        raise AssertionError(f"hostile file {name!r} was read without an error")
    if kind == "any":  # arbitrary bytes under an arbitrary name, through open_recording
        target = next(f for f in root.iterdir())
        kind = "open"
    if kind == "map":
        return _load_map(root / "map.npz")
    if kind == "ply":
        d = read_ply(root / "cloud.ply")
        n = {len(v) for v in d.values()}
        if len(n) > 1:
            raise AssertionError(f"read_ply returned columns of different lengths {n}")
        return 0
    if kind != "open":
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
        if n == 0:
            try:
                _map_one(fr)
            except Exception as e:  # a frame a reader yields must map
                raise AssertionError(f"frame 0 does not map: {type(e).__name__}: {e}") from e
        n += 1
    return n


class LoaderRefused(Exception):
    """``MinMaxMapper.load`` refused a file with its ``ValueError`` (its documented error)."""


def _load_map(path: Path) -> int:
    """Load a (mutated) saved map; what it accepts must be a map that saves and loads again."""
    import gpumap
    from gpumap.errors import FormatError

    try:
        m = gpumap.MinMaxMapper.load(path, backend="numpy")
    except FormatError:
        raise
    except ValueError as e:
        raise LoaderRefused(str(e)) from None
    v = m.values()
    if not np.all(np.isnan(v) | ((v >= 0) & (v <= 1))):
        raise AssertionError("the loaded map holds values outside [0, 1] and NaN")
    if m.rule == "visible":
        ev = m.evidence()
        if any(np.any(a < 0) for a in ev.values() if a.dtype.kind in "iu"):
            raise AssertionError("the loaded map holds negative counts")
    m.occupied_points(0.5)
    again = path.with_name("again.npz")
    m.save(again)
    np.testing.assert_array_equal(gpumap.MinMaxMapper.load(again, backend="numpy").values(), v)
    return int(np.isfinite(v).sum())


def _warm_up(files: dict[str, dict[str, bytes]], work: Path) -> None:
    """Read each real case once before the cap: lazy imports and caches are not the case's cost."""
    for kind, case in files.items():
        root = work / f"warm-{kind}"
        for rel, data in case.items():
            (root / rel).parent.mkdir(parents=True, exist_ok=True)
            (root / rel).write_bytes(data)
        _read_case(kind, root)


_HOSTILE: dict = {}


def _rss_peak_reset() -> bool:
    """Reset the kernel's peak-RSS mark (VmHWM) of this process; False where not allowed."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def _rss_kib(field: str) -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    return -1


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
        from test_io import hostile_cases  # tests/ is on the path the parent passes down

        (work / "hostile").mkdir()
        _HOSTILE.update(hostile_cases(work / "hostile"))
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
            t0, w0 = time.process_time(), time.perf_counter()
            peak = -1
            try:
                for rel, data in case.items():
                    (root / rel).parent.mkdir(parents=True, exist_ok=True)
                    (root / rel).write_bytes(data)
                base = _rss_kib("VmRSS")
                measured = _rss_peak_reset()
                t0, w0 = time.process_time(), time.perf_counter()
                try:
                    n = _read_case(kind, root)
                finally:
                    if measured:
                        peak = max(0, _rss_kib("VmHWM") - base) * 1024
                out = ("frames", n, "")
            except (FormatError, LoaderRefused) as e:
                out = ("gpumap-error", type(e).__name__, str(e)[:300])
            except BaseException as e:  # noqa: BLE001 - everything else is the finding
                out = ("other", type(e).__name__, traceback.format_exc()[-3000:])
            dt, wall = time.process_time() - t0, time.perf_counter() - w0
            shutil.rmtree(root, ignore_errors=True)
            conn.send((*out, dt, peak, wall))
    finally:
        shutil.rmtree(work, ignore_errors=True)


class CappedRunner:
    """One child process under RLIMIT_AS that reads cases; killed and restarted on a time-out."""

    def __init__(self, warm: dict, mem_cap: int) -> None:
        self.ctx = mp.get_context("spawn")  # a fresh interpreter: no threads or GPU contexts forked
        self.warm, self.mem_cap = warm, mem_cap
        self.proc = None
        self.cap_info = None
        self.last_peak_bytes = -1  # the last case's peak RSS above the child's own (-1: unknown)
        self.last_wall_s = math.inf  # the last case's wall time
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

    def run(self, kind: str, case: dict[str, bytes], hang_s: float = HANG_S) -> tuple:
        """-> (status, detail, message, CPU seconds); status 'frames', 'gpumap-error', 'other',
        'timeout' (no answer within ``hang_s`` wall seconds) or 'died'."""
        try:
            self.conn.send((kind, case))
            self.last_peak_bytes, self.last_wall_s = -1, math.inf
            if not self.conn.poll(hang_s):
                self._restart()
                return ("timeout", "", f"no answer within {hang_s} s", math.inf)
            *out, self.last_peak_bytes, self.last_wall_s = self.conn.recv()
            return tuple(out)
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

    if DATA is None:
        pytest.skip("shared/data (real recordings) not found beside the checkout (../shared/data)")
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
    # a map of four real tank pings, as save() writes it, and its members for mutation
    import zipfile

    import gpumap
    from gpumap.io import open_fan_folder

    frames = list(open_fan_folder(DATA / "oasis_tank", stride=40))
    grid = gpumap.GridSpec(min_corner_m=(-0.5, -1.5, -1.0), max_corner_m=(2.5, 1.5, 0.5),
                           voxel_size_m=0.1)
    m = gpumap.MinMaxMapper(frames[0].spec, grid, backend="numpy")
    for fr in frames:
        m.integrate(fr.image, fr.T_W_S)
    m.save(tmp / "map.npz")
    with zipfile.ZipFile(tmp / "map.npz") as z:
        members = {i.filename: z.read(i) for i in z.infolist()}
    out["map"] = {"files": {"map.npz": (tmp / "map.npz").read_bytes()}, "fields": [],
                  "members": members}
    return out


def _kind(name: str) -> str:
    return {"oculus-log-plain": "oculus-log", "fan-csv": "fan", "ply-bin": "ply",
            "ply-ascii": "ply"}.get(name, name)


@pytest.fixture(scope="module")
def runner(request):
    """The capped child; warmed up on the real files when they are there (works without)."""
    from gpumap.limits import MEMORY_TARGET_BYTES

    warm = {}
    if DATA is not None:
        seeds = request.getfixturevalue("seeds")
        warm = {_kind(k): v["files"] for k, v in seeds.items()
                if k in ("oculus-raw", "oculus-log", "aris", "fan", "ply-bin", "rosbag", "map")}
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
    cap = TIME_CAP_S if status == "gpumap-error" else WORK_CAP_S
    assert dt < cap, f"{name}: took {dt:.2f} s of CPU (cap {cap} s); {status} {detail} {message}"


def _fuzz_one(runner, seeds, name: str, target: str, muts) -> None:
    seed = seeds[name]
    case = dict(seed["files"])
    case[target] = mutate(case[target], muts, seed["fields"], bool(seed.get("text")))
    _check(runner, name, _kind(name), case)


# ------------------------------------------------------------------ the harness itself
def test_harness_reads_the_real_files_and_enforces_its_caps(runner, seeds) -> None:
    expect = {"oculus-raw": 3, "oculus-log": 2, "oculus-log-plain": 2, "aris": 6, "fan": 1,
              "fan-csv": 1, "ply-bin": 0, "ply-ascii": 0, "rosbag": 2, "map": 4304}
    for name, n in expect.items():
        status, detail, message, dt = runner.run(_kind(name), seeds[name]["files"])
        assert (status, detail) == ("frames", n), (name, status, detail, message)
        assert dt < WORK_CAP_S / 2, (name, dt)
    # the caps are real: 2 GiB cannot be had, and a hang is cut off (the child is replaced)
    status, detail, _m, _dt = runner.run("__alloc__", {})
    assert (status, detail) in (("other", "MemoryError"), ("died", "-9")), (status, detail)
    assert runner.run("__sleep__", {}, hang_s=2.0)[0] == "timeout"
    assert runner.run("aris", seeds["aris"]["files"])[:2] == ("frames", 6)
    vm, cap = runner.cap_info
    assert cap - vm <= 1 << 30


# ------------------------------------------------------------------ one property per reader
@_fuzz_settings(320)
@given(muts=MUTATIONS)
def test_fuzz_oculus_raw(runner, seeds, muts) -> None:
    _fuzz_one(runner, seeds, "oculus-raw", "rec.raw", muts)


@_fuzz_settings(240)
@given(muts=MUTATIONS)
def test_fuzz_oculus_log_compressed(runner, seeds, muts) -> None:
    _fuzz_one(runner, seeds, "oculus-log", "rec.oculus", muts)


@_fuzz_settings(240)
@given(muts=MUTATIONS)
def test_fuzz_oculus_log_plain(runner, seeds, muts) -> None:
    _fuzz_one(runner, seeds, "oculus-log-plain", "rec.oculus", muts)


@_fuzz_settings(320)
@given(muts=MUTATIONS)
def test_fuzz_aris(runner, seeds, muts) -> None:
    _fuzz_one(runner, seeds, "aris", "rec.aris", muts)


@_fuzz_settings(320)
@given(muts=MUTATIONS)
def test_fuzz_fan_png(runner, seeds, muts) -> None:
    _fuzz_one(runner, seeds, "fan", "sonar/image_0000.png", muts)


@_fuzz_settings(240)
@given(muts=MUTATIONS)
def test_fuzz_fan_pose_table(runner, seeds, muts) -> None:
    _fuzz_one(runner, seeds, "fan-csv", "sonar_poses.csv", muts)


@_fuzz_settings(200)
@given(muts=MUTATIONS, binary=st.booleans())
def test_fuzz_ply(runner, seeds, muts, binary) -> None:
    _fuzz_one(runner, seeds, "ply-bin" if binary else "ply-ascii", "cloud.ply", muts)


@_fuzz_settings(160)
@given(muts=MUTATIONS)
def test_fuzz_rosbag(runner, seeds, muts) -> None:
    _fuzz_one(runner, seeds, "rosbag", "rec.bag", muts)


# ------------------------------------------------------------------ hostile files, in the capped child
def test_hostile_files_in_the_capped_child(runner, tmp_path) -> None:
    """Each hostile file of issue #12 (tests/test_io.py) again, now under RLIMIT_AS (1 GiB) in
    the child, with its peak RSS measured by the kernel (VmHWM, C allocations included):
    gpumap's own error, in under a second, costing far less than 1 GiB."""
    from test_io import hostile_cases

    from gpumap.limits import MEMORY_TARGET_BYTES

    cases = hostile_cases(tmp_path)  # only for the names and the errors; the child has its own
    peaks = {}
    for name, (_read, err) in cases.items():
        status, detail, message, dt = runner.run("hostile", {"name": name.encode()})
        assert (status, detail) == ("gpumap-error", err.__name__), (name, status, detail, message)
        assert "expected" in message, (name, message)
        assert dt < TIME_CAP_S, (name, dt)
        peaks[name] = runner.last_peak_bytes
    known = {k: v for k, v in peaks.items() if v >= 0}
    # measured: 0-15 MiB above the child's own footprint (most: the fan folder's sampler tables)
    assert all(v < MEMORY_TARGET_BYTES // 16 for v in known.values()), known


# ------------------------------------------------------------------ the public API, by construction
# These build their inputs from parameters Hypothesis draws and know the answer independently:
# valid inputs must give exactly that answer, inputs made invalid on purpose must give
# gpumap's error. Sizes are bounded by construction, so they run in this process.
def _rigid(q: tuple[float, float, float, float], t: tuple[float, float, float]) -> np.ndarray:
    w, x, y, z = np.asarray(q) / np.linalg.norm(q)
    R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                  [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                  [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


_unit = st.floats(-1.0, 1.0, allow_nan=False)
_quat = st.tuples(_unit, _unit, _unit, _unit).map(lambda q: q if np.linalg.norm(q) > 0.1 else (1.0, *q[1:]))
_trans = st.tuples(*[st.floats(-1e3, 1e3, allow_nan=False)] * 3)
_FRAME_DAMAGE = ["-1", "x", "1_0", "99999999999999999999", "", "1.5", "dup", "back"]
_TIME_DAMAGE = ["nan", "inf", "-inf", "same", "back", "abc"]
_POSE_DAMAGE = ["nan", "inf", "1e400", "abc", "skew", "mirror", "last row", "missing", "extra"]
_row = st.fixed_dictionaries({
    "step": st.integers(1, 10**6), "dt": st.floats(1e-3, 1e3), "q": _quat, "t": _trans,
    "damage": st.one_of(st.none(), st.none(), st.none(),
                        st.tuples(st.just("frame"), st.sampled_from(_FRAME_DAMAGE)),
                        st.tuples(st.just("time"), st.sampled_from(_TIME_DAMAGE)),
                        st.tuples(st.just("pose"), st.sampled_from(_POSE_DAMAGE),
                                  st.integers(0, 15))),
})


def _pose_table_text(rows: list[dict], with_time: bool, start: int) -> tuple[str, bool, tuple]:
    """-> (CSV text, whether it is valid, (frames, times, T) it holds when valid)."""
    head = "frame," + ("time_s," if with_time else "") + ",".join(
        f"T_W_S_{i}{j}" for i in range(4) for j in range(4))
    lines, frames, times, Ts = [head], [], [], []
    valid, k, t = True, start, 1.7e9
    for i, r in enumerate(rows):
        k, t = (k + r["step"] if i else k), t + r["dt"]
        T = _rigid(r["q"], r["t"])
        fcell, tcell = str(k), repr(t)
        cells = [repr(float(v)) for v in T.reshape(-1)]
        d = r["damage"]
        if d and d[0] == "time" and not with_time:
            d = None
        if d and d[0] == "frame" and d[1] in ("dup", "back") and not frames:
            d = None
        if d:
            valid = False
            if d[0] == "frame":
                fcell = {"dup": str(frames[-1] if frames else 0),
                         "back": str(frames[-1] - 1 if frames else 0)}.get(d[1], d[1])
            elif d[0] == "time":
                tcell = {"same": repr(times[-1]) if times else "nan",
                         "back": repr(times[-1] - 0.5) if times else "nan"}.get(d[1], d[1])
                if d[1] in ("same", "back") and not times:
                    tcell = "nan"
            else:
                kind, j = d[1], d[2]
                if kind in ("nan", "inf", "1e400", "abc"):
                    cells[j] = kind
                elif kind == "skew":  # one rotation or translation entry off by 0.5
                    m = j % 12 if j % 4 != 3 else 0
                    m = m if m % 4 != 3 else m - 1
                    cells[m] = repr(float(T.reshape(-1)[m]) + 0.5)
                elif kind == "mirror":
                    for m in (0, 4, 8):  # negate the first column: det -1
                        cells[m] = repr(-float(T.reshape(-1)[m]))
                elif kind == "last row":
                    cells[12 + j % 4] = "0.5" if j % 4 != 3 else "2.0"
                elif kind == "missing":
                    del cells[j]
                else:
                    cells.insert(j, "0.0")
        lines.append(",".join([fcell, *([tcell] if with_time else []), *cells]))
        frames.append(k)
        times.append(t)
        Ts.append(T)
    return "\n".join(lines) + "\n", valid, (frames, times, Ts)


@_fuzz_settings(200)
@given(rows=st.lists(_row, min_size=0, max_size=6), with_time=st.booleans(),
       start=st.integers(0, 2**40))
def test_pose_table_property(rows, with_time, start) -> None:
    """read_pose_table: a valid table comes back exactly; a table damaged anywhere (frame,
    time or pose) is refused with gpumap's error."""
    import tempfile

    from gpumap.errors import FormatError
    from gpumap.io.fan import read_pose_table

    text, valid, (frames, times, Ts) = _pose_table_text(rows, with_time, start)
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "sonar_poses.csv"
        p.write_text(text)
        if not valid:
            with pytest.raises(FormatError):
                read_pose_table(p)
            return
        f, t, T = read_pose_table(p)
    assert f.dtype == np.int64 and f.tolist() == frames
    assert (t is None) == (not with_time)
    if with_time:
        assert t.tolist() == times
    assert T.shape == (len(rows), 4, 4)
    np.testing.assert_array_equal(T, np.asarray(Ts).reshape(-1, 4, 4))  # repr round-trips exactly


# (colour type, bit depths): every mode the PNG standard allows
_PNG_MODES = [(0, (1, 2, 4, 8, 16)), (2, (8, 16)), (3, (1, 2, 4, 8)), (4, (8, 16)), (6, (8, 16))]
_png_mode = st.sampled_from([(c, d) for c, ds in _PNG_MODES for d in ds])


def _luma(rgb: np.ndarray) -> np.ndarray:
    return rgb[..., 0] * 0.299 + rgb[..., 1] * 0.587 + rgb[..., 2] * 0.114


def _encode_png(ctype: int, depth: int, px: np.ndarray, palette: np.ndarray | None) -> bytes:
    """A PNG from samples (h, w, channels) of ``depth`` bits: rows packed MSB first, filter 0."""
    from test_io import png_bytes, png_chunk

    h, w, _c = px.shape
    rows = []
    for y in range(h):
        v = px[y].reshape(-1)
        if depth == 16:
            raw = v.astype(">u2").tobytes()
        elif depth == 8:
            raw = v.astype(np.uint8).tobytes()
        else:
            bits = np.unpackbits(v.astype(np.uint8)[:, None], axis=1)[:, 8 - depth:].reshape(-1)
            raw = np.packbits(bits).tobytes()
        rows.append(b"\0" + raw)
    extra = b""
    if palette is not None:
        extra = png_chunk(b"PLTE", palette.astype(np.uint8).tobytes())
    return png_bytes(w, h, depth, ctype, zlib.compress(b"".join(rows)), extra)


@_fuzz_settings(200)
@given(mode=_png_mode, w=st.integers(1, 13), h=st.integers(1, 9), seed=st.integers(0, 2**32 - 1))
def test_png_modes_property(mode, w, h, seed) -> None:
    """read_grey_png on every PNG colour type and bit depth, random sizes and pixels: the grey
    levels an independent reading of the samples gives (grey / max, palette and RGB by luma,
    alpha ignored), within one 8-bit step where Pillow reduces to 8 bits."""
    from gpumap.io.fan import read_grey_png

    ctype, depth = mode
    rng = np.random.default_rng(seed)
    top = (1 << depth) - 1
    channels = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}[ctype]
    px = rng.integers(0, top, size=(h, w, channels), endpoint=True)
    palette = None
    if ctype == 3:
        palette = rng.integers(0, 255, size=(top + 1, 3), endpoint=True)
    got = read_grey_png(_encode_png(ctype, depth, px, palette), expected_shape=(h, w))
    assert got.dtype == np.float32 and got.shape == (h, w) and got.flags.c_contiguous
    if ctype == 0:  # grey: exact
        expect, tol = px[..., 0] / top, 1e-6
    elif ctype == 4:  # grey + alpha: the grey (16 bit reduced to 8)
        expect, tol = px[..., 0] / top, (1 / 255 if depth == 16 else 1e-6)
    elif ctype == 3:
        expect, tol = _luma(palette[px[..., 0]]) / 255, 1 / 255 + 1e-6
    else:  # RGB / RGBA: luma of the colour
        expect, tol = _luma(px[..., :3] / top), (2 / 255 if depth == 16 else 1 / 255) + 1e-6
    np.testing.assert_allclose(got, expect, atol=tol, rtol=0)


_sample_dtype = st.sampled_from([np.uint8, np.uint16, np.uint32])


@_fuzz_settings(200)
@given(dtype=_sample_dtype, n_ranges=st.integers(1, 40), bearings=st.sets(
    st.integers(-4400, 4400), min_size=2, max_size=24), version=st.sampled_from([1, 2]),
    gains=st.booleans(), pad=st.integers(0, 64), res=st.floats(1e-4, 1.0), seed=st.integers(0, 2**32 - 1),
    damage=st.lists(st.tuples(st.integers(0, 400), st.integers(0, 2**32 - 1), st.sampled_from([1, 2, 4, 8])),
                    max_size=3))
def test_oculus_message_property(dtype, n_ranges, bearings, version, gains, pad, res, seed,
                                 damage) -> None:
    """encode_simple_ping -> decode_message gives the samples back exactly (columns reversed,
    azimuth = -bearing; bearings within +-44 deg so the fan's edges stay inside +-90); the
    same message with header bytes overwritten decodes to a frame that passes the frame
    checks, or gpumap's error -- nothing else."""
    from gpumap.errors import FormatError
    from gpumap.io import decode_message, encode_simple_ping
    from gpumap.io.oculus import _FIXED1, _FIXED2

    rng = np.random.default_rng(seed)
    b = np.array(sorted(bearings), dtype=np.int16)
    top = np.iinfo(dtype).max
    samples = rng.integers(0, top, size=(n_ranges, b.size), dtype=dtype, endpoint=True)
    g = rng.integers(0, 2**32 - 1, size=n_ranges, dtype=np.uint32) if gains else None
    fixed = _FIXED2 if version == 2 else _FIXED1
    msg = encode_simple_ping(samples, b, res, version=version, gains=g, ping_id=int(seed % 2**32),
                             ping_start_time=seed % 1000 / 7.0, image_offset=fixed + 2 * b.size + pad)
    fr = decode_message(msg)
    assert _frame_problem(fr) is None
    if dtype is np.uint32:
        np.testing.assert_allclose(fr.image, samples[:, ::-1] / top, rtol=1e-6)
    else:
        np.testing.assert_array_equal(np.round(fr.image.astype(np.float64) * top), samples[:, ::-1])
    np.testing.assert_array_equal(fr.meta["bearings_cdeg"], b)
    np.testing.assert_allclose(fr.spec.bearings_rad, -np.deg2rad(b[::-1] / 100.0))
    assert fr.spec.n_bins == n_ranges and fr.spec.range_max_m == pytest.approx(n_ranges * res)
    assert (fr.meta["gains"] is None) == (not gains)
    if gains:
        np.testing.assert_array_equal(fr.meta["gains"], g)
    bad = bytearray(msg)
    for off, val, size in damage:
        off %= max(1, min(len(bad), fixed + 2 * b.size) - size + 1)
        bad[off:off + size] = (val % (1 << (8 * size))).to_bytes(size, "little")
    try:
        fr2 = decode_message(bytes(bad))
    except FormatError:
        return
    assert fr2 is None or _frame_problem(fr2) is None, _frame_problem(fr2)


_f32 = st.floats(width=32, allow_nan=True, allow_infinity=True)


@_fuzz_settings(150)
@given(points=st.lists(st.tuples(_f32, _f32, _f32), max_size=40), with_intensity=st.booleans(),
       binary=st.booleans(), data=st.data())
def test_ply_round_trip_property(points, with_intensity, binary, data) -> None:
    """write_ply -> read_ply returns every float32 exactly (NaN and inf included), ASCII or binary."""
    import tempfile

    from gpumap.io import read_ply, write_ply

    P = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    v = None
    if with_intensity:
        v = np.asarray(data.draw(st.lists(_f32, min_size=len(P), max_size=len(P))), dtype=np.float32)
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "c.ply"
        write_ply(p, P, v, binary=binary)
        got = read_ply(p)
    assert sorted(got) == sorted(["x", "y", "z"] + (["intensity"] if with_intensity else []))
    for j, k in enumerate("xyz"):
        assert got[k].dtype == np.float32
        np.testing.assert_array_equal(got[k], P[:, j])
    if with_intensity:
        np.testing.assert_array_equal(got["intensity"], v)


_MAGICS = [b"", b"#ROSBAG V2.0\n", b"\x89MCAP0\r\n", b"SQLite format 3\x00", b"DDF\x05",
           (0x11223344).to_bytes(4, "little"), (0x4F53).to_bytes(2, "little"), b"\x89PNG\r\n\x1a\n"]
_NAMES = ["rec.bag", "rec.mcap", "rec.db3", "rec.aris", "rec.ddf", "rec.oculus", "rec.png", "rec.raw",
          "rec"]


@_fuzz_settings(200)
@given(magic=st.sampled_from(_MAGICS), name=st.sampled_from(_NAMES),
       body=st.binary(max_size=3000))
def test_open_recording_on_any_bytes(runner, magic, name, body) -> None:
    """open_recording on any small file under any telling name, read to the end in the capped
    child: frames that pass the checks, or gpumap's error."""
    _check(runner, f"any {name}", "any", {name: magic + body})


@_fuzz_settings(200)
@given(member=st.integers(0, 10), muts=MUTATIONS, stored=st.booleans())
def test_fuzz_saved_map(runner, seeds, member, muts, stored) -> None:
    """MinMaxMapper.load on a real map (four tank pings) with one member mutated -- its npy
    header text and data -- and the zip rebuilt (so the damage gets past the zip's CRC), or
    the zip itself mutated: its ValueError, or a map that holds only possible values and
    saves and loads again to the same values."""
    import zipfile

    seed = seeds["map"]
    names = list(seed["members"])
    buf = io.BytesIO()
    if member < len(names):
        with zipfile.ZipFile(buf, "w", zipfile.ZIP_STORED if stored else zipfile.ZIP_DEFLATED,
                             compresslevel=1) as z:
            for n, data in seed["members"].items():
                z.writestr(n, mutate(data, muts, [], True) if n == names[member] else data)
        data = buf.getvalue()
    else:
        data = mutate(seed["files"]["map.npz"], muts, [], False)
    _check(runner, "map", "map", {"map.npz": data})
