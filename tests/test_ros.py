"""The ROS 2 node (issue 22): pure parts against independent references, then the real thing.

The end-to-end tests start ``gpumap ros`` and ``gpumap ros-play`` as separate processes that
talk over Fast DDS on loopback (a random ROS_DOMAIN_ID, discovery limited to localhost, each
test in a namespace of its own), read the node's outputs with an in-process rclpy node, and
compare the published cloud with ``MinMaxMapper`` on the same pings, voxel for voxel.
Without the ROS 2 wheels they skip, except under CI (``CI`` set), where they must run.
"""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import DATA, needs_data, pose, rot_z
from maps import make_mapper

import gpumap
from gpumap.core.params import MapperParams
from gpumap.layers.confidence import with_confidence
from gpumap.ros.live import LiveMapper, PoseBuffer

try:
    import rclpy  # noqa: F401

    from gpumap.ros import require_ros

    require_ros()
    HAVE_ROS = True
    WHY = ""
except ImportError as e:  # pragma: no cover - depends on the install
    if os.environ.get("CI"):
        raise ImportError(f"CI must run the ROS 2 tests, but the ROS 2 wheels are not importable: {e}") from e
    HAVE_ROS = False
    WHY = f"the ROS 2 wheels are not installed (pip install -e '.[ros]'): {e}"

needs_ros = pytest.mark.skipif(not HAVE_ROS, reason=WHY)

TANK = None if DATA is None else DATA / "oasis_tank"


# ------------------------------------------------------------------------ pose buffer
def test_pose_buffer_interpolates_on_se3_and_reports_why_not():
    buf = PoseBuffer(max_poses=4, max_gap_s=0.5)
    # a pure rotation about z at a constant rate: at 30 % of the way the angle is 30 % of it
    assert buf.add(0, pose(np.eye(3), [0, 0, 0]))
    assert buf.add(400_000_000, pose(rot_z(0.8), [0, 0, 0]))
    st, T = buf.lookup(120_000_000)
    assert st == "ok"
    np.testing.assert_allclose(T[:3, :3], rot_z(0.24), atol=1e-12)
    np.testing.assert_allclose(T[:3, 3], 0, atol=1e-12)
    # a pure translation: linear in time
    assert buf.add(800_000_000, pose(rot_z(0.8), [0.4, -0.2, 0.1]))
    st, T = buf.lookup(700_000_000)
    np.testing.assert_allclose(T[:3, 3], [0.3, -0.15, 0.075], atol=1e-12)
    np.testing.assert_allclose(T[:3, :3], rot_z(0.8), atol=1e-12)
    # a stamp that is a pose's own: that pose, bit for bit
    T8 = pose(rot_z(0.8), [0.4, -0.2, 0.1])
    assert np.array_equal(buf.lookup(800_000_000)[1], T8)
    assert buf.lookup(900_000_000) == ("wait", None)  # newer than every pose
    assert not buf.add(800_000_000, T8)  # not after the newest: refused
    assert buf.add(2_000_000_000, T8)  # 1.2 s after the last: a gap
    assert buf.lookup(1_500_000_000)[0] == "pose_gap"
    buf.add(2_100_000_000, T8)  # the 5th pose: the oldest (t = 0) goes
    assert len(buf) == 4
    assert buf.lookup(100_000_000)[0] == "no_pose"


# ------------------------------------------------------------------------ live mapper
SMALL_SPEC = gpumap.SonarSpec.uniform(hfov_deg=90, vfov_deg=20, n_beams=32, n_bins=40,
                                      range_min_m=0.1, range_max_m=1.5)
SMALL_GRID = gpumap.GridSpec((-0.2, -1.2, -0.5), (1.6, 1.2, 0.5), 0.1)


def _small_pings(n: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    imgs = (rng.random((n, *SMALL_SPEC.image_shape)) ** 4 * 255).astype(np.uint8)
    Ts = np.stack([pose(rot_z(0.1 * k - 0.3), [0.02 * k, 0, 0.05]) for k in range(n)])
    return imgs, Ts


class FakeClock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def test_live_mapper_counts_drops_and_skips_and_maps_what_it_keeps():
    imgs, Ts = _small_pings(8)
    clock = FakeClock()
    m = gpumap.MinMaxMapper(SMALL_SPEC, SMALL_GRID, backend="numpy")
    live = LiveMapper(m, queue_size=3, max_batch=4, pose_wait_s=0.5, clock=clock)
    s = 1_000_000_000
    for k in range(8):  # poses for all but ping 7, at the pings' own stamps
        if k != 7:
            live.add_pose(k * s, Ts[k])
    for k in range(6):  # 6 pings into a queue of 3, worker not running: the 3 oldest go
        assert live.add_ping(k * s, imgs[k])
    assert live.dropped == {"queue_full": 3}
    assert not live.add_ping(2 * s, imgs[2])  # not after the last accepted stamp
    assert live.rejected == {"image_out_of_order": 1}
    assert not live.add_ping(9 * s, imgs[0][:-1])
    assert live.rejected["image_size"] == 1
    live.add_ping(7 * s, imgs[7])  # no pose will come for it: queue full again, ping 3 goes
    assert live.dropped == {"queue_full": 4}
    live.start()
    deadline = time.monotonic() + 10
    while (live.integrated < 2 or live.stats()["queue"] != 1) and time.monotonic() < deadline:
        time.sleep(0.01)
    assert live.integrated == 2 and live.stats()["queue"] == 1  # 4, 5 mapped; 7 waits for its pose
    clock.t = 0.6  # past pose_wait_s
    live.stop(drain=True)
    assert live.skipped == {"pose_timeout": 1}
    ref = gpumap.MinMaxMapper(SMALL_SPEC, SMALL_GRID, backend="numpy")
    ref.integrate_batch(imgs[4:6], Ts[4:6])
    assert np.array_equal(m.raw_values(), ref.raw_values(), equal_nan=True)


def _surface_worker_run(seed: int, max_batch: int, **kw):
    """12 small pings, one a second of stamps, through a LiveMapper and a LiveSurfaceWorker (``kw``), both
    stopped at the end: (images, poses, mapper, live mapper, worker, published (layer, stamp) pairs,
    nanoseconds a ping)."""
    from gpumap.ros.surface_worker import LiveSurfaceWorker

    imgs, Ts = _small_pings(12, seed=seed)
    m = gpumap.MinMaxMapper(SMALL_SPEC, SMALL_GRID, "numpy", MapperParams(threshold=0.4))
    published = []
    live = LiveMapper(m, queue_size=64, max_batch=max_batch)
    surf = LiveSurfaceWorker(live, on_publish=lambda layer, t: published.append((layer, t)), **kw)
    s = 1_000_000_000
    for k in range(12):
        live.add_pose(k * s, Ts[k])
    live.start()
    surf.start()
    for k in range(12):
        live.add_ping(k * s, imgs[k])
        time.sleep(0.01)
    live.stop(drain=True)
    surf.stop()
    return imgs, Ts, m, live, surf, published, s


def test_live_surface_worker_publishes_the_offline_layer_of_the_pings_mapped():
    """The surface worker follows the live mapper on its own thread: every layer it publishes is the
    offline layer of the pings it says it covers, on the map of those pings; the last covers them all;
    a reset forgets them; layer_now gives both layers of one moment."""
    from gpumap.layers.surface_live import surface_from_mapper

    imgs, Ts, m, live, surf, published, s = _surface_worker_run(3, 3)
    assert surf.error is None and published
    st = surf.stats()
    assert st["surface_pings"] == 12 and st["surface_waiting"] == 0 and st["surface_age_s"] == 0.0
    for layer, t in published:
        n = layer.stats["pings"]
        assert t == (n - 1) * s  # stamped with the newest ping it covers
        ref = gpumap.MinMaxMapper(SMALL_SPEC, SMALL_GRID, "numpy", MapperParams(threshold=0.4))
        ref.integrate_batch(imgs[:n], Ts[:n])
        off = surface_from_mapper(ref, imgs[:n], Ts[:n])
        assert np.array_equal(layer.surface, off.surface) and np.array_equal(layer.votes, off.votes)
    assert published[-1][0].stats["pings"] == 12 and published[-1][0].surface.any()
    layer, values = surf.layer_now()
    assert np.array_equal(layer.surface, published[-1][0].surface)
    assert np.array_equal(values, m.values(), equal_nan=True)
    live.reset()
    assert surf.stats()["surface_pings"] == 0 and surf.surface.n_pings == 0


def test_live_surface_worker_with_a_window_publishes_the_newest_pings_layer():
    """max_pings: every published layer is the offline layer of the newest pings it holds, on the map
    of every ping mapped up to then."""
    from gpumap.layers.surface_live import surface_from_mapper

    imgs, Ts, m, live, surf, published, s = _surface_worker_run(4, 2, max_pings=5)
    assert surf.error is None and published[-1][1] == 11 * s
    for layer, t in published:
        n, lo = t // s + 1, layer.stats["first_ping"]
        assert lo == max(0, n - 5) and layer.stats["pings"] == n - lo
        ref = gpumap.MinMaxMapper(SMALL_SPEC, SMALL_GRID, "numpy", MapperParams(threshold=0.4))
        ref.integrate_batch(imgs[:n], Ts[:n])
        off = surface_from_mapper(ref, imgs[lo:n], Ts[lo:n])
        assert np.array_equal(layer.surface, off.surface) and np.array_equal(layer.votes, off.votes)
    assert surf.stats()["surface_pings"] == 5


# ------------------------------------------------------------------------ conversions
@needs_ros
@pytest.mark.parametrize("encoding", ["mono8", "mono16", "32FC1"])
def test_image_messages_round_trip_and_bad_ones_say_why(encoding):
    from gpumap.ros.convert import BadMessage, image_from_msg, image_msg

    rng = np.random.default_rng(1)
    u8 = rng.integers(0, 256, SMALL_SPEC.image_shape, dtype=np.uint8)
    f = u8.astype(np.float32) / np.float32(255)
    msg = image_msg(u8 if encoding == "mono8" else f, 5, "sonar", encoding)
    got = image_from_msg(msg, SMALL_SPEC.image_shape)
    if encoding == "mono8":
        assert got.dtype == np.uint8 and np.array_equal(got, u8)
    elif encoding == "mono16":
        assert np.array_equal(got, (np.rint(f.astype(np.float64) * 65535) / 65535).astype(np.float32))
    else:
        assert np.array_equal(got, f)
    # padded rows and big-endian data read the same
    a = np.asarray(got if encoding != "mono16" else np.rint(f.astype(np.float64) * 65535))
    dt = {"mono8": ">u1", "mono16": ">u2", "32FC1": ">f4"}[encoding]
    rows = np.zeros((a.shape[0], a.shape[1] * np.dtype(dt).itemsize + 3), np.uint8)
    rows[:, : a.shape[1] * np.dtype(dt).itemsize] = a.astype(dt).view(np.uint8).reshape(a.shape[0], -1)
    msg.is_bigendian, msg.step = 1, rows.shape[1]
    msg.data = rows.tobytes()
    assert np.array_equal(image_from_msg(msg, SMALL_SPEC.image_shape), got)
    with pytest.raises(BadMessage, match="40 x 32") as e:
        image_from_msg(msg, (41, 32))
    assert e.value.reason == "image_size"
    msg.encoding = "rgb8"
    with pytest.raises(BadMessage, match="rgb8") as e:
        image_from_msg(msg, SMALL_SPEC.image_shape)
    assert e.value.reason == "image_encoding"
    bad = f.copy()
    bad[3, 4] = np.nan
    with pytest.raises(BadMessage, match="1 pixels") as e:
        image_from_msg(image_msg(bad, 5, "sonar", "32FC1"), SMALL_SPEC.image_shape)
    assert e.value.reason == "image_values"


@needs_ros
def test_pose_messages_round_trip_and_bad_ones_say_why():
    from geometry_msgs.msg import Point, Quaternion
    from scipy.spatial.transform import Rotation

    from gpumap.ros.convert import BadMessage, pose_msg_fields, transform_from_pose

    for k, R in enumerate(Rotation.random(50, random_state=3).as_matrix()):
        T = pose(R, [k, -1.5, 0.25])
        (x, y, z), q = pose_msg_fields(T)
        np.testing.assert_allclose(np.abs(q), np.abs(Rotation.from_matrix(R).as_quat()), atol=1e-12)
        back = transform_from_pose(Point(x=x, y=y, z=z), Quaternion(x=q[0], y=q[1], z=q[2], w=q[3]))
        np.testing.assert_allclose(back, T, atol=1e-12)
    with pytest.raises(BadMessage, match="finite") as e:
        transform_from_pose(Point(x=math.nan), Quaternion())
    assert e.value.reason == "pose_nonfinite"
    with pytest.raises(BadMessage, match="norm is 2") as e:
        transform_from_pose(Point(), Quaternion(x=0.0, y=0.0, z=0.0, w=2.0))
    assert e.value.reason == "pose_not_unit_quaternion"


def test_obstacle_projection_and_marker_blocks_against_brute_force():
    from gpumap.ros.convert import MarkerBlocks, project_obstacles

    grid = gpumap.GridSpec((0, 0, 0), (3.7, 2.1, 1.0), 0.1)  # 37 x 21 x 10: blocks cut unevenly
    rng = np.random.default_rng(2)
    v = rng.random(grid.shape).astype(np.float32)
    v[rng.random(grid.shape) < 0.5] = np.nan
    band = (0.3, 0.62)
    cells = project_obstacles(v, grid, 0.9, band)
    nx, ny, nz = grid.shape
    for i in range(nx):
        for j in range(ny):
            col = [v[i, j, k] for k in range(nz) if band[0] <= 0.05 + 0.1 * k <= band[1]]
            want = 100 if any(x >= 0.9 for x in col if x == x) else (0 if any(x == x for x in col) else -1)
            assert cells[j, i] == want, (i, j)
    blocks = MarkerBlocks(grid, 0.9, block=8)
    first = blocks.update(v)
    pts = np.concatenate([p for _, p in first])
    occ = grid.centers(np.argwhere(np.isfinite(v) & (v >= 0.9)))
    assert sorted(map(tuple, pts.round(9))) == sorted(map(tuple, occ.round(9)))
    assert blocks.update(v) == []  # nothing changed: nothing to send
    w = v.copy()
    w[20, 3, 9] = 1.0  # one voxel in block (2, 0, 1)
    w[v >= 0.9] = np.where(np.arange(int((v >= 0.9).sum())) == 0, 0.0, 1.0)  # and one emptied
    changed = blocks.update(w)
    touched = {np.ravel_multi_index((i // 8, j // 8, k // 8), (5, 3, 2))
               for i, j, k in np.argwhere((np.isfinite(w) & (w >= 0.9)) != (np.isfinite(v) & (v >= 0.9)))}
    assert {b for b, _ in changed} == touched and len(touched) <= 2


def _assert_cloud_confidence(centres, vals, confirmed, mapper) -> tuple[int, int]:
    """Brute force, voxel by voxel: the cloud is the occupied set, confirmed == (confidence == 3)."""
    conf = mapper.layer("confidence").states()
    v = mapper.values()
    grid = mapper.grid
    got = {}
    for p, x, c in zip(centres, vals, confirmed, strict=True):
        ijk = tuple(int(round(q)) for q in (p - np.asarray(grid.min_corner_m)) / grid.voxel_size_m - 0.5)
        assert ijk not in got
        assert x == v[ijk]
        got[ijk] = int(c)
    nx, ny, nz = grid.shape
    for i in range(nx):
        for j in range(ny):
            for k in range(nz):
                if conf[i, j, k] >= 2:
                    assert got.pop((i, j, k)) == (1 if conf[i, j, k] == 3 else 0), (i, j, k)
    assert not got  # nothing in the cloud that the layer does not call occupied
    return int((conf == 3).sum()), int((conf == 2).sum())


def test_cloud_confirmed_field_is_the_mappers_confidence_layer():
    """The node's cloud content with confidence on, on the analytic point reflector of
    test_nbv: a level view (the whole arc unconfirmed), then a rolled one (the echo confirmed)."""
    from test_nbv import _echo_image, _look_at_target

    from gpumap.ros.convert import occupied_cloud

    m = with_confidence(
        gpumap.MinMaxMapper(
            gpumap.SonarSpec.uniform(
                hfov_deg=60, vfov_deg=20, n_beams=64, n_bins=100, range_min_m=0.1, range_max_m=1.5
            ),
            gpumap.GridSpec((-0.5, -0.5, -0.5), (0.5, 0.5, 0.5), 0.05),
            "numpy",
            MapperParams(rule="visible"),
        )
    )  # one clear view carves
    seen = []
    for roll in (0.0, math.pi / 2, math.pi / 4):
        T = _look_at_target(roll)
        m.integrate(_echo_image(T), T)
        centres, vals, confirmed = occupied_cloud(
            m.values(), m.grid, m.threshold, m.layer("confidence").states()
        )
        assert confirmed.dtype == np.uint8
        seen.append(_assert_cloud_confidence(centres, vals, confirmed, m))
    assert seen[0][0] == 0 and seen[0][1] >= 5  # one view: the stretch, nothing confirmed
    assert seen[1][0] >= 1  # rolled: the echo confirmed
    # without the layer: the same points, no field; a layer that disagrees with the values is refused
    c2, v2, none = occupied_cloud(m.values(), m.grid, m.threshold)
    assert none is None and np.array_equal(c2, centres) and np.array_equal(v2, vals)
    bad = m.layer("confidence").states()
    bad[bad >= 2] = 1
    with pytest.raises(ValueError, match="occupied voxel"):
        occupied_cloud(m.values(), m.grid, m.threshold, bad)


@needs_ros
def test_cloud_message_with_and_without_the_confirmed_field():
    from sensor_msgs.msg import PointField

    from gpumap.ros.convert import cloud_confirmed, cloud_msg, cloud_points

    rng = np.random.default_rng(5)
    pts = rng.normal(size=(7, 3))
    val = rng.random(7).astype(np.float32)
    conf = (rng.random(7) < 0.5).astype(np.uint8)
    m = cloud_msg(pts, val, 3_000_000_001, "map", conf)
    assert [(f.name, f.offset, f.datatype) for f in m.fields] == [
        ("x", 0, PointField.FLOAT32), ("y", 4, PointField.FLOAT32), ("z", 8, PointField.FLOAT32),
        ("value", 12, PointField.FLOAT32), ("confirmed", 16, PointField.UINT8)]
    assert m.point_step == 20 and m.row_step == 140 and len(m.data) == 140
    raw = np.frombuffer(bytes(m.data), np.uint8).reshape(7, 20)
    assert np.array_equal(raw[:, 16], conf) and not raw[:, 17:].any()  # padding zeroed
    np.testing.assert_array_equal(cloud_points(m), np.column_stack([pts.astype(np.float32), val]))
    assert np.array_equal(cloud_confirmed(m), conf)
    plain = cloud_msg(pts, val, 3_000_000_001, "map")
    assert plain.point_step == 16 and cloud_confirmed(plain) is None
    np.testing.assert_array_equal(cloud_points(plain), cloud_points(m))
    with pytest.raises(ValueError, match=r"confirmed of shape \(7,\)"):
        cloud_msg(pts, val, 0, "map", conf[:-1])


# ------------------------------------------------------------------------ over DDS
def _env(ns_domain: int) -> dict:
    env = dict(os.environ)
    env.update(ROS_DOMAIN_ID=str(ns_domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               PYTHONUNBUFFERED="1")
    env.pop("ROS_STATIC_PEERS", None)
    return env


DOMAIN = 1 + (os.getpid() % 100)  # one domain per test session; namespaces split the tests


class Probe:
    """An in-process ROS node that reads the mapping node's outputs and calls its services."""

    def __init__(self, ns: str) -> None:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import PointCloud2

        from gpumap.ros import use_gpumap_fastdds_profile

        self._old_env = {k: os.environ.get(k) for k in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE",
                                                        "FASTDDS_DEFAULT_PROFILES_FILE")}
        os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
        use_gpumap_fastdds_profile()
        self.ns = ns
        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx, domain_id=DOMAIN)
        self.node = rclpy.create_node("probe", namespace=ns, context=self.ctx)
        self.ex = SingleThreadedExecutor(context=self.ctx)
        self.ex.add_node(self.node)
        self.clouds: list = []
        self.diag: dict | None = None
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.node.create_subscription(PointCloud2, f"{ns}/gpumap/occupied_cloud", self.clouds.append, latched)
        self.surface: list = []
        self.node.create_subscription(PointCloud2, f"{ns}/gpumap/surface_cloud", self.surface.append, latched)
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diag, 10)

    def _on_diag(self, msg) -> None:
        for st in msg.status:
            if st.name == f"{self.ns}/gpumap: mapper":
                self.diag = {kv.key: kv.value for kv in st.values}

    def spin_until(self, pred, timeout_s: float, what: str) -> None:
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            self.ex.spin_once(timeout_sec=0.05)
            if pred():
                return
        raise AssertionError(f"timed out after {timeout_s} s waiting for {what}; last diagnostics "
                             f"{self.diag}")

    def spin_for(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.ex.spin_once(timeout_sec=0.02)

    def count(self, key: str) -> int:
        return int((self.diag or {}).get(key, 0))

    def call(self, service: str) -> tuple[bool, str]:
        from std_srvs.srv import Trigger

        cli = self.node.create_client(Trigger, f"{self.ns}/gpumap/{service}")
        assert cli.wait_for_service(timeout_sec=10), f"no {service} service"
        fut = cli.call_async(Trigger.Request())
        self.spin_until(fut.done, 20, f"the {service} service")
        return fut.result().success, fut.result().message

    def close(self) -> None:
        self.ex.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.ctx)
        for k, v in self._old_env.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _gpumap(*args: str, ns: str, log: Path) -> subprocess.Popen:
    ours = [a for a in args if a != "--ros-args"]
    ros = ["--ros-args", "-r", f"__ns:={ns}"]
    if "--ros-args" in args:
        i = args.index("--ros-args")
        ours, ros = list(args[:i]), ros + list(args[i + 1:])
    f = open(log, "w")  # noqa: SIM115 - closed with the process
    return subprocess.Popen([sys.executable, "-m", "gpumap.commands", *ours, *ros], stdout=f,
                            stderr=subprocess.STDOUT, env=_env(DOMAIN), start_new_session=True)


def _stop(p: subprocess.Popen, sig=signal.SIGINT, timeout_s: float = 20) -> int | None:
    if p.poll() is None:
        p.send_signal(sig)
        try:
            p.wait(timeout_s)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(5)
            return None
    return p.returncode


@pytest.fixture
def ros_session(tmp_path):
    """``start(name, *args)`` starts a gpumap process; all are stopped (and their logs shown) at the end."""
    procs: list[tuple[subprocess.Popen, Path]] = []
    probes: list[Probe] = []
    ns = f"/t{os.getpid()}_{len(os.listdir(tmp_path))}_{time.monotonic_ns() % 100000}"

    def start(name: str, *args: str) -> subprocess.Popen:
        log = tmp_path / f"{name}.log"
        p = _gpumap(*args, ns=ns, log=log)
        procs.append((p, log))
        return p

    def probe() -> Probe:
        pr = Probe(ns)
        probes.append(pr)
        return pr

    start.ns, start.probe, start.logs = ns, probe, procs
    yield start
    for pr in probes:
        pr.close()
    for p, log in procs:
        _stop(p, signal.SIGKILL if p.poll() is None and p.args[3] == "ros-play" else signal.SIGINT)
        if p.returncode not in (0, -9):
            print(f"--- {log.name} (exit {p.returncode}) ---\n{log.read_text()[-3000:]}")


def _cloud_ijk(msg, grid) -> tuple[np.ndarray, np.ndarray]:
    from gpumap.ros.convert import cloud_points

    pts = cloud_points(msg)
    ijk = np.rint((pts[:, :3].astype(np.float64) - np.asarray(grid.min_corner_m)) / grid.voxel_size_m - 0.5)
    return ijk.astype(np.int64), pts[:, 3]


def _assert_cloud_is_map(msg, mapper, threshold: float) -> int:
    """The cloud's voxels and values are exactly the mapper's occupied set at ``threshold``."""
    ijk, val = _cloud_ijk(msg, mapper.grid)
    v = mapper.raw_values()
    occ = np.isfinite(v) & (v >= np.float32(threshold))
    got = np.zeros_like(occ)
    got[tuple(ijk.T)] = True
    assert len(ijk) == int(occ.sum()) and np.array_equal(got, occ), (
        f"cloud has {len(ijk)} voxels, the offline map {int(occ.sum())}; "
        f"{int((got & ~occ).sum())} only in the cloud, {int((occ & ~got).sum())} only offline")
    assert np.array_equal(val, v[tuple(ijk.T)])
    return int(occ.sum())


def _wire_pose(T):
    """The pose as the node gets it from the wire (quaternion and back)."""
    from geometry_msgs.msg import Point, Quaternion

    from gpumap.ros.convert import pose_msg_fields, transform_from_pose

    (x, y, z), q = pose_msg_fields(T)
    return transform_from_pose(Point(x=x, y=y, z=z), Quaternion(x=q[0], y=q[1], z=q[2], w=q[3]))


def _offline(play, grid, frames, threshold=0.4, wire=True, confidence=False):
    """``MinMaxMapper`` on ``frames``: with the poses as the wire carries them, or as recorded."""
    m = make_mapper(play.spec, grid, backend="numpy", threshold=threshold, confidence=confidence)
    for f in frames:
        m.integrate(f.image, _wire_pose(f.T_W_S) if wire else f.T_W_S)
    return m


def _offline_surface(mapper, frames, wire=True):
    """The surface layer of ``mapper`` (which integrated ``frames`` in order) from the same pings."""
    from gpumap.layers.surface_live import surface_from_mapper

    return surface_from_mapper(mapper, frames=((f.image, _wire_pose(f.T_W_S) if wire else f.T_W_S)
                                               for f in frames))


def _assert_cloud_is_layer(msg, layer) -> int:
    """The surface cloud's voxels are exactly the layer's surface voxels (value 1 each)."""
    ijk, val = _cloud_ijk(msg, layer.grid)
    got = np.zeros(layer.surface.shape, bool)
    got[tuple(ijk.T)] = True
    n = int(layer.surface.sum())
    assert len(ijk) == n and np.array_equal(got, layer.surface), (
        f"surface cloud has {len(ijk)} voxels, the offline layer {n}; {int((got & ~layer.surface).sum())} "
        f"only in the cloud, {int((layer.surface & ~got).sum())} only offline")
    assert np.all(val == 1.0)
    return n


def _grid_of(params: Path) -> gpumap.GridSpec:
    import json

    vals = {}
    for line in params.read_text().splitlines():
        if ":" in line and line.startswith("    "):
            k, v = line.strip().split(":", 1)
            vals[k] = json.loads(v)
    return gpumap.GridSpec(tuple(vals["grid_min_m"]), tuple(vals["grid_max_m"]), vals["voxel_size_m"])


NODE_TEST_ARGS = ("-p", "diagnostics_period_s:=0.2", "-p", "publish_period_s:=0.05")


@needs_ros
@needs_data
def test_real_tank_over_dds_equals_the_offline_map(ros_session, tmp_path):
    """Node and ros-play as two processes: 123 real tank pings at 25 Hz, cloud == offline map."""
    from gpumap.ros.play import open_playable, write_params

    play = open_playable(TANK)
    params = write_params(tmp_path / "tank.yaml", play, voxel_size_m=0.05, threshold=0.4, backend="numpy",
                          world_frame="map", pose_type="pose_stamped")
    saved = tmp_path / "saved.npz"
    node = ros_session("node", "ros", "--params-file", str(params), "--ros-args", *NODE_TEST_ARGS,
                       "-p", f"save_path:={saved}", "-p", "save_on_exit:=true",
                       "-p", "queue_size:=200",  # the numpy backend maps ~30/s here: queue, drop nothing
                       # the surface layer's thread shares the interpreter with the callbacks: on 2 loaded
                       # cores the default 10 images of the subscription overflow (middleware_lost)
                       "-p", "surface:=true", "-p", "image_queue_depth:=200")
    probe, frames = _play_all(ros_session, play, TANK, 25, 120)
    probe.spin_for(0.5)  # the last cloud
    assert not any(k.startswith(("dropped", "skipped", "rejected")) for k in probe.diag), probe.diag
    # the recorded poses, not the wire's: the quaternion round trip moves them by ~1e-9 m, and the
    # cloud is still gpumap replay's map of the tank (replay's grid is the same auto grid)
    ref = _offline(play, _grid_of(params), frames, wire=False)
    n = _assert_cloud_is_map(probe.clouds[-1], ref, 0.4)
    assert n > 10_000  # the tank's walls and floor, not an empty map
    # the surface layer: its last cloud covers every ping, and is the offline layer of them
    probe.spin_until(lambda: probe.count("surface_pings") == len(frames) and probe.surface
                     and probe.surface[-1].header.stamp == probe.clouds[-1].header.stamp, 120,
                     "the surface layer of every ping")
    off = _offline_surface(ref, frames, wire=False)
    assert _assert_cloud_is_layer(probe.surface[-1], off) > 1000
    assert node.poll() is None
    assert _stop(node) == 0  # Ctrl-C: clean exit, both layers saved on exit in one file
    from gpumap.layers.refined_map import load_refined

    back = load_refined(saved)
    assert np.array_equal(back.map_values, ref.values(), equal_nan=True)
    assert np.array_equal(back.occupancy, off.values(), equal_nan=True)


def _play_all(ros_session, play, recording: Path, hz: int, timeout_s: float):
    """Wait for the node's first diagnostics, play ``recording`` at ``hz`` with ros-play, and wait
    until the node has mapped every one of ``play``'s frames; ``(probe, frames)``."""
    probe = ros_session.probe()
    probe.spin_until(lambda: probe.diag is not None, 60, "the node's first diagnostics")
    player = ros_session("play", "ros-play", str(recording), "--hz", str(hz), "--no-progress")
    player.wait(timeout_s)
    assert player.returncode == 0
    frames = list(play.frames())
    probe.spin_until(lambda: probe.count("pings_integrated") == len(frames) and probe.count("queue") == 0,
                     60, "every ping mapped")
    return probe, frames


@pytest.fixture(scope="module")
def sim_recording(tmp_path_factory) -> Path:
    """A simulated run (the tank scene, 12 pings), recorded as gpumap demo --record does."""
    from gpumap.sim.scenes import make_scene
    from gpumap.sim.sonar import SonarSimulator

    from gpumap.viewer.recording import Recorder

    scene = make_scene("tank", voxel_size_m=0.06, n_pitch=4, n_move=8)
    path = tmp_path_factory.mktemp("sim") / "tank.gpumap-rec"
    with SonarSimulator(scene, seed=0) as sim, Recorder(path, scene.sonar_spec, scene.grid, 0.4) as rec:
        for k, T in enumerate(scene.T_W_S):
            rec.ping(sim.ping(T, k).image, T)
    return path


@needs_ros
def test_simulated_run_and_a_player_that_dies(ros_session, tmp_path, sim_recording):
    """A player killed mid-run: the node lives on with the pings it got; reset; the full run
    then maps to the offline map, voxel for voxel."""
    from gpumap.ros.play import open_playable, write_params

    play = open_playable(sim_recording)
    params = write_params(tmp_path / "sim.yaml", play, voxel_size_m=None, threshold=0.4, backend="numpy",
                          world_frame="map", pose_type="odometry")
    node = ros_session("node", "ros", "--params-file", str(params), "--ros-args", *NODE_TEST_ARGS)
    probe = ros_session.probe()
    probe.spin_until(lambda: probe.diag is not None, 60, "the node's first diagnostics")
    player = ros_session("play-killed", "ros-play", str(sim_recording), "--hz", "8",
                         "--pose-type", "odometry", "--no-progress")
    probe.spin_until(lambda: probe.count("pings_integrated") >= 3, 60, "three pings mapped")
    player.send_signal(signal.SIGKILL)
    player.wait(10)
    probe.spin_for(1.5)  # what was in flight lands, and whatever lost its pose times out
    k = probe.count("pings_integrated")
    frames = list(play.frames())
    assert 3 <= k < len(frames)
    assert probe.count("skipped.pose_timeout") <= 1 and probe.count("queue") == 0
    assert node.poll() is None  # alive and still publishing
    t = probe.diag
    probe.spin_until(lambda: probe.diag is not t, 5, "diagnostics after the player died")
    _assert_cloud_is_map(probe.clouds[-1], _offline(play, play.grid, frames[:k]), 0.4)

    assert probe.call("reset") == (True, "map reset: every voxel unknown")
    probe.spin_until(lambda: probe.clouds[-1].width == 0, 10, "the empty cloud after the reset")
    player = ros_session("play", "ros-play", str(sim_recording), "--hz", "20", "--pose-type", "odometry",
                         "--no-progress")
    player.wait(60)
    assert player.returncode == 0
    probe.spin_until(lambda: probe.count("pings_integrated") == k + len(frames) and probe.count("queue") == 0,
                     60, "the second run mapped")
    probe.spin_for(0.4)
    assert probe.count("dropped.middleware_lost") == 0
    _assert_cloud_is_map(probe.clouds[-1], _offline(play, play.grid, frames), 0.4)


@needs_ros
def test_confidence_on_the_wire_is_the_offline_layer(ros_session, tmp_path, sim_recording):
    """confidence:=true: the node's cloud carries confirmed, voxel for voxel the offline layer."""
    from gpumap.ros.convert import cloud_confirmed, cloud_points
    from gpumap.ros.play import open_playable, write_params

    play = open_playable(sim_recording)
    params = write_params(tmp_path / "sim.yaml", play, voxel_size_m=None, threshold=0.4, backend="numpy",
                          world_frame="map", pose_type="pose_stamped")
    ros_session("node", "ros", "--params-file", str(params), "--ros-args", *NODE_TEST_ARGS,
                "-p", "confidence:=true")
    probe, frames = _play_all(ros_session, play, sim_recording, 20, 60)
    probe.spin_for(0.4)
    ref = _offline(play, play.grid, frames, confidence=True)
    msg = probe.clouds[-1]
    _assert_cloud_is_map(msg, ref, 0.4)
    conf = cloud_confirmed(msg)
    assert conf is not None and set(np.unique(conf).tolist()) <= {0, 1}
    counts = _assert_cloud_confidence(cloud_points(msg)[:, :3].astype(np.float64), cloud_points(msg)[:, 3],
                                      conf, ref)
    assert counts[0] > 0 and counts[1] > 0  # both kinds on the wire (139 and 4856 here)


@needs_ros
def test_surface_layer_on_the_wire_is_the_offline_layer(ros_session, tmp_path, sim_recording):
    """The second cloud: after a simulated run at 20 Hz, the last surface cloud covers every ping
    (/diagnostics says so, with its age) and equals the offline layer of them, voxel for voxel;
    ~/save_map writes both layers in one file; ~/reset empties the layer too."""
    from gpumap.layers.refined_map import load_refined
    from gpumap.ros.play import open_playable, write_params

    play = open_playable(sim_recording)
    params = write_params(tmp_path / "sim.yaml", play, voxel_size_m=None, threshold=0.4, backend="numpy",
                          world_frame="map", pose_type="pose_stamped")
    saved = tmp_path / "both.npz"
    ros_session("node", "ros", "--params-file", str(params), "--ros-args", *NODE_TEST_ARGS,
                "-p", f"save_path:={saved}", "-p", "surface:=true", "-p", "image_queue_depth:=100")
    probe, frames = _play_all(ros_session, play, sim_recording, 20, 60)
    probe.spin_until(lambda: probe.count("surface_pings") == len(frames) and probe.surface
                     and probe.surface[-1].header.stamp == probe.clouds[-1].header.stamp, 60,
                     "the surface layer of every ping")
    assert probe.count("surface_waiting") == 0 and float(probe.diag["surface_age_s"]) == 0.0
    assert float(probe.diag["surface_update_s"]) > 0 and probe.count("surface_updates") >= 1
    ref = _offline(play, play.grid, frames)
    off = _offline_surface(ref, frames)
    n = _assert_cloud_is_layer(probe.surface[-1], off)
    assert n > 100 and probe.count("surface_voxels") == n
    ok, path = probe.call("save_map")
    assert ok and Path(path) == saved
    back = load_refined(saved)
    assert np.array_equal(back.map_values, ref.values(), equal_nan=True)
    assert np.array_equal(back.occupancy, off.values(), equal_nan=True)
    assert probe.call("reset")[0]
    probe.spin_until(lambda: probe.surface[-1].width == 0, 10, "the empty surface cloud after the reset")


@needs_ros
def test_bad_input_on_the_wire_is_counted_and_leaves_the_map_alone(ros_session, tmp_path, sim_recording):
    """Every row of the issue's bad-input table, sent by a test publisher to a live node."""
    from geometry_msgs.msg import PoseStamped
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Image

    from gpumap.ros.convert import image_msg, pose_msg_fields, stamp_of
    from gpumap.ros.play import open_playable, write_params

    play = open_playable(sim_recording)
    frames = list(play.frames())[:7]
    params = write_params(tmp_path / "sim.yaml", play, voxel_size_m=None, threshold=0.4, backend="numpy",
                          world_frame="map", pose_type="pose_stamped")
    saved = tmp_path / "map.npz"  # without the surface layer: the map file MinMaxMapper.load reads
    node = ros_session("node", "ros", "--params-file", str(params), "--ros-args", *NODE_TEST_ARGS,
                       "-p", f"save_path:={saved}")
    probe = ros_session.probe()
    n = probe.node
    pub_img = n.create_publisher(Image, "sonar/image",
                                 QoSProfile(depth=50, reliability=ReliabilityPolicy.BEST_EFFORT))
    pub_pose = n.create_publisher(PoseStamped, "sonar/pose", 100)
    probe.spin_until(lambda: probe.diag is not None and pub_img.get_subscription_count() > 0
                     and pub_pose.get_subscription_count() > 0, 60, "the node")
    probe.spin_for(0.3)
    sent = 0

    def pose(t_ns, T, q=None, frame="map"):
        m = PoseStamped()
        m.header.stamp, m.header.frame_id = stamp_of(t_ns), frame
        (m.pose.position.x, m.pose.position.y, m.pose.position.z), qq = pose_msg_fields(T)
        qq = q or qq
        o = m.pose.orientation
        o.x, o.y, o.z, o.w = qq
        pub_pose.publish(m)

    def image(t_ns, img, **fields):
        nonlocal sent
        m = image_msg(img, t_ns, "sonar")
        for k, v in fields.items():
            setattr(m, k, v)
        pub_img.publish(m)
        sent += 1
        probe.spin_for(0.01)

    s = 1_000_000_000
    base = n.get_clock().now().nanoseconds - 60 * s
    nan_T = frames[0].T_W_S.copy()
    nan_T[0, 3] = np.nan
    for k, fr in enumerate(frames):
        t = base + k * s
        if k == 1:
            pose(t - s // 2, nan_T)  # NaN pose
            pose(t - s // 3, fr.T_W_S, q=(0.0, 0.0, 0.0, 2.0))  # not a rotation
            pose(t - s // 4, fr.T_W_S, frame="odom")  # another frame
        pose(t, fr.T_W_S)
        image(t, fr.image)
        if k == 2:
            image(t + s // 10, fr.image, encoding="rgb8")  # wrong encoding
            small = image_msg(fr.image[:-1], t + s // 5, "sonar")  # wrong size
            pub_img.publish(small)
            sent += 1
        if k == 3:
            image(t - s // 2, fr.image)  # out of order
            pose(t - s // 2, fr.T_W_S)
        if k == 4:
            future = n.get_clock().now().nanoseconds + 100 * s
            image(future, fr.image)  # from the future
            pose(future, fr.T_W_S)
        if k == 5:  # a pose gap of 0.8 s around an image
            pose(t + s // 10, fr.T_W_S)
            pose(t + 9 * s // 10, frames[6].T_W_S)
            image(t + s // 2, fr.image)
    t_end = base + len(frames) * s
    image(t_end, frames[0].image)  # its pose publisher "died": no pose ever comes
    probe.spin_until(lambda: probe.count("skipped.pose_timeout") == 1, 20, "the orphan ping to time out")
    # a flood: 120 pings (one view repeated) as fast as this process sends
    flood = 120
    stamps = [t_end + s + i * 1_000_000 for i in range(flood)] + [t_end + s + flood * 1_000_000]
    for i, t in enumerate(stamps):  # the poses first, paced: the flood is of images
        pose(t, frames[0].T_W_S)
        if i % 20 == 0:
            probe.spin_for(0.02)
    probe.spin_for(0.3)
    m = image_msg(frames[0].image, 0, "sonar")
    for t in stamps[:-1]:
        m.header.stamp = stamp_of(t)
        pub_img.publish(m)
        sent += 1
    # one more after a pause, so that a gap in the sequence numbers shows any flood ping the
    # middleware lost at the end
    probe.spin_for(0.5)
    flood += 1
    image(stamps[-1], frames[0].image)
    probe.spin_until(lambda: probe.count("pings_received") + probe.count("dropped.middleware_lost") == sent
                     and probe.count("queue") == 0, 60, "the flood to settle")
    probe.spin_for(0.5)
    d = probe.diag
    want = {"rejected.image_encoding": 1, "rejected.image_size": 1, "rejected.pose_nonfinite": 1,
            "rejected.pose_not_unit_quaternion": 1, "rejected.pose_frame": 1,
            "rejected.image_out_of_order": 1,
            "rejected.pose_out_of_order": 1, "rejected.image_from_future": 1, "rejected.pose_from_future": 1,
            "skipped.pose_gap": 1, "skipped.pose_timeout": 1}
    assert {k: int(d.get(k, 0)) for k in want} == want, d
    n_flood = probe.count("pings_integrated") - len(frames)
    # the flood overran the node (its queue, or the subscription's before it), and said so
    assert probe.count("dropped.queue_full") + probe.count("dropped.middleware_lost") > 0
    assert n_flood + probe.count("dropped.queue_full") + probe.count("dropped.middleware_lost") == flood, d
    assert n_flood >= 1 and node.poll() is None
    ref = _offline(play, play.grid, frames + [frames[0]] * n_flood)
    _assert_cloud_is_map(probe.clouds[-1], ref, 0.4)
    assert probe.call("save_map") == (True, str(saved))  # the service writes the same map
    assert np.array_equal(gpumap.MinMaxMapper.load(saved, backend="numpy").raw_values(), ref.raw_values())


@needs_ros
@needs_data
def test_a_cartesian_fan_on_the_wire_maps_as_the_fan_reader_reads_it():
    """image_layout: fan with the OASIS geometry: the node queues the polar image the fan reader
    makes from the same picture (mono8 fan on the wire, converted on arrival)."""
    import rclpy

    from gpumap.io import open_recording
    from gpumap.io.fan import OASIS_SPEC, read_grey_png
    from gpumap.ros.convert import image_msg
    from gpumap.ros.node import make_node

    first = next(iter(open_recording(TANK)))
    fan_u8 = np.rint(read_grey_png(first.meta["file"]) * 255).astype(np.uint8)
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=DOMAIN, args=[
        "x", "--ros-args", "-p", "image_layout:=fan", "-p", "backend:=numpy", "-p", "n_bins:=398",
        "-p", "hfov_deg:=130.0", "-p", "n_beams:=512", "-r", f"__ns:=/fan{os.getpid()}"])
    try:
        node = make_node(context=ctx)
        assert node.spec == OASIS_SPEC
        node._on_image(image_msg(fan_u8, node.get_clock().now().nanoseconds, "sonar"), {})
        queued = node.live._pending[0].image
        assert queued.dtype == np.float32 and np.array_equal(queued, first.image)
        small = image_msg(fan_u8[:-1], node.get_clock().now().nanoseconds + 1, "sonar")
        node._on_image(small, {})
        assert node.live.rejected == {"image_size": 1}
        node.live.stop(drain=False)
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=ctx)


def test_callbacks_never_wait_for_the_mapper():
    """add_ping/add_pose return at once while the mapper is busy (here: its lock is held)."""
    imgs, Ts = _small_pings(4)
    m = gpumap.MinMaxMapper(SMALL_SPEC, SMALL_GRID, backend="numpy")
    live = LiveMapper(m, queue_size=8)
    live.start()
    with live._map_lock:  # the worker is stuck in the mapper
        live.add_pose(0, Ts[0])
        live.add_ping(0, imgs[0])
        time.sleep(0.2)  # the worker has taken ping 0 and waits for the mapper
        t0 = time.perf_counter()
        for k in range(1, 4):
            live.add_pose(k, Ts[k])
            assert live.add_ping(k, imgs[k])
        assert time.perf_counter() - t0 < 0.05
        assert live.integrated == 0 and live.stats()["queue"] == 4
    live.stop(drain=True)
    assert live.integrated == 4


def test_marker_blocks_carry_the_confidence_layer():
    """Flags aligned with each block's centres (brute force); a block whose flags alone changed is
    re-sent; unconfirmed cubes are drawn pale (the live view's PALE_MIX), confirmed ones as before."""
    from gpumap.ros.convert import MarkerBlocks
    from gpumap.viewer.live import PALE_MIX

    grid = gpumap.GridSpec((0, 0, 0), (3.7, 2.1, 1.0), 0.1)
    rng = np.random.default_rng(5)
    v = rng.random(grid.shape).astype(np.float32)
    occ = v >= 0.9
    conf = occ & (rng.random(grid.shape) < 0.5)
    blocks = MarkerBlocks(grid, 0.9, block=8)
    first = blocks.update(v, confirmed=conf)
    want = {tuple(np.round(c, 9)): bool(f)
            for c, f in zip(grid.centers(np.argwhere(occ)), conf[occ], strict=True)}
    got = {tuple(np.round(c, 9)): bool(f)
           for b, pts in first for c, f in zip(pts, blocks.confirmed[b], strict=True)}
    assert got == want
    assert blocks.update(v, confirmed=conf) == []
    conf2 = conf.copy()
    i, j, k = np.argwhere(occ)[0]
    conf2[i, j, k] = not conf2[i, j, k]  # only a flag changes
    changed = blocks.update(v, confirmed=conf2)
    assert [b for b, _ in changed] == [np.ravel_multi_index((i // 8, j // 8, k // 8), (5, 3, 2))]
    pytest.importorskip("rclpy")
    b, pts = changed[0]
    flags = blocks.confirmed[b]
    assert flags.any() and not flags.all()
    mk = blocks.msg(changed, 0, "map").markers[0]
    plain = MarkerBlocks(grid, 0.9, block=8)
    plain.update(v)
    ref = plain.msg([(b, pts)], 0, "map").markers[0]
    for c, r, f in zip(mk.colors, ref.colors, flags, strict=True):
        rgb, rgb0 = np.array([c.r, c.g, c.b]), np.array([r.r, r.g, r.b])
        np.testing.assert_allclose(rgb, rgb0 if f else (1 - PALE_MIX) * rgb0 + PALE_MIX, rtol=1e-6)


def test_live_mapper_plans_around_the_newest_ping_mapped():
    """next_best_views of the live map: refused before a ping and without the confidence layer;
    then nbv.next_best_views around the pose of the newest ping by stamp (pings mapped out of
    their arrival order are never newer than it)."""
    from gpumap.layers.viewgain import next_best_views

    imgs, Ts = _small_pings(5)
    m = with_confidence(gpumap.MinMaxMapper(SMALL_SPEC, SMALL_GRID, backend="numpy"))
    live = LiveMapper(m, queue_size=8, max_batch=2)
    with pytest.raises(ValueError, match="no ping has been mapped"):
        live.next_best_views(views=2, candidates=20)
    for k in range(5):
        live.add_pose(k, Ts[k])
        live.add_ping(k, imgs[k])
    live.start()
    live.stop(drain=True)
    assert live.integrated == 5
    np.testing.assert_array_equal(live.newest_pose, Ts[4])
    got, n = live.next_best_views(views=3, candidates=40, seed=2)
    want, _ = next_best_views(m, Ts[4], views=3, candidates=40, seed=2)
    assert n == 40 and [v["candidate"] for v in got] == [v["candidate"] for v in want]
    plain = LiveMapper(gpumap.MinMaxMapper(SMALL_SPEC, SMALL_GRID, backend="numpy"))
    plain.newest_pose = Ts[0]
    with pytest.raises(ValueError, match="confidence"):
        plain.next_best_views(views=1, candidates=5)


def test_plan_parameters_become_the_planners_limits_or_say_what_is_wrong():
    from gpumap.ros.node import PARAMETERS, plan_options

    p = {k: v for k, (v, _) in PARAMETERS.items()}
    kw = plan_options(p)
    assert kw["views"] == p["plan_views"] and kw["candidates"] == p["plan_candidates"]
    assert kw["roll_rad"] == (-math.radians(45.0), math.radians(45.0))
    assert kw["pitch_rad"] == (-math.radians(15.0), math.radians(15.0))
    assert kw["yaw_rad"] == (-math.radians(20.0), math.radians(20.0)) and kw["offset_m"] == (-0.1, 0.1)
    for name, bad in (("plan_views", 0), ("plan_candidates", 2.5), ("plan_max_tilt_deg", 95.0),
                      ("plan_max_roll_deg", -1.0), ("plan_radius_m", -0.1),
                      ("plan_unknown_weight", math.inf)):
        with pytest.raises(ValueError, match=name):
            plan_options({**p, name: bad})


@needs_ros
def test_plan_views_service_publishes_the_best_views_as_a_pose_array():
    """In process: a node with the confidence layer maps pings, ~/plan_views publishes the views
    nbv.next_best_views ranks (poses round-trip through the message); without the layer it says
    how to turn it on."""
    import rclpy
    from std_srvs.srv import Trigger

    from gpumap.layers.viewgain import next_best_views
    from gpumap.ros.convert import transform_from_pose
    from gpumap.ros.node import make_node

    imgs, Ts = _small_pings(4)
    for confidence in ("true", "false"):
        ctx = rclpy.Context()
        rclpy.init(context=ctx, domain_id=DOMAIN, args=[
            "x", "--ros-args", "-p", "backend:=numpy", "-p", f"confidence:={confidence}",
            "-p", "plan_views:=3", "-p", "plan_candidates:=60", "-p", "plan_unknown_weight:=1.0",
            "-p", "range_max_m:=1.0",
            "-p", "n_bins:=50", "-p", "n_beams:=32", "-p", "hfov_deg:=60.0",
            "-r", f"__ns:=/plan{os.getpid()}{confidence}"])
        try:
            node = make_node(context=ctx)
            node.live.stop(drain=False)  # mapped here, in this thread
            node.mapper.integrate_batch(np.stack([np.zeros(node.spec.image_shape, np.float32)] * 4), Ts)
            node.live.newest_pose = Ts[3]
            sent = []
            node.pub_views.publish = sent.append
            r = node._on_plan(Trigger.Request(), Trigger.Response())
            if confidence == "false":
                assert not r.success and "confidence:=true" in r.message and not sent
            else:
                want, _ = next_best_views(node.mapper, Ts[3], **node.plan_kw)
                assert r.success and len(sent) == 1 and len(sent[0].poses) == 3, r.message
                assert want[0]["gain"] > want[-1]["gain"] > 0  # unknown voxels count: gains differ
                assert sent[0].header.frame_id == "map"
                for p, v in zip(sent[0].poses, want, strict=True):
                    np.testing.assert_allclose(transform_from_pose(p.position, p.orientation), v["T_W_S"],
                                               atol=1e-9)
            node.destroy_node()
        finally:
            rclpy.try_shutdown(context=ctx)


# ------------------------------------------------------------------------ the distance field (issue 44)
def _edt_m(values: np.ndarray, threshold: float, voxel: float, unknown_is_obstacle: bool = True,
           cap: float | None = None) -> np.ndarray:
    """SciPy's distance, metres, from each voxel centre to the nearest obstacle centre of ``values``
    (occupied from ``threshold``; NaN unknown, an obstacle or free)."""
    from scipy import ndimage

    obst = values >= np.float32(threshold)
    if unknown_is_obstacle:
        obst |= np.isnan(values)
    d = np.full(values.shape, np.inf) if not obst.any() else ndimage.distance_transform_edt(~obst,
                                                                                            sampling=voxel)
    return d if cap is None else np.minimum(d, cap)


def _distance_points(msg) -> np.ndarray:
    """A distance PointCloud2 read back by hand: (height, width) records of float32 x, y, z, distance."""
    assert [f.name for f in msg.fields] == ["x", "y", "z", "distance"] and msg.point_step == 16
    assert all(f.datatype == 7 and f.offset == 4 * i and f.count == 1 for i, f in enumerate(msg.fields))
    dt = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("distance", "<f4")])
    return np.frombuffer(bytes(msg.data), dt).reshape(msg.height, msg.width)


@pytest.mark.parametrize("unknown_is_obstacle", [True, False])
def test_live_distance_follows_the_live_map_and_publishes_only_changes(backend, unknown_is_obstacle):
    """The node's worker path without ROS: after every publication of the live map the field is SciPy's
    distance transform of that map (the values the cloud was made from); a ping that changes nothing
    publishes nothing; a reset publishes the field of the empty map; queries in the meantime read the
    field under its lock."""
    from gpumap.ros.distance_pub import LiveDistance

    imgs, Ts = _small_pings(9, seed=2)
    m = gpumap.MinMaxMapper(SMALL_SPEC, SMALL_GRID, "numpy", MapperParams(threshold=0.4))
    ld = LiveDistance(m, unknown_is_obstacle=unknown_is_obstacle, backend=backend, cloud_radius_m=0.3)
    published: list = []
    live: LiveMapper | None = None

    def on_publish(newest_ns: int) -> None:
        values = live.values()
        f = ld.refresh(values)
        if f is not None:
            published.append((newest_ns, f, values))

    live = LiveMapper(m, queue_size=64, max_batch=2, on_publish=on_publish)
    s = 1_000_000_000
    for k in range(9):
        live.add_pose(k * s, Ts[k])
    live.start()
    for k in range(8):
        live.add_ping(k * s, imgs[k])
        time.sleep(0.01)
    live.stop(drain=True)
    assert live.error is None and live.integrated == 8 and published
    assert ld.changes == len(published) <= ld.updates
    for _, f, values in published:
        assert f.dtype == np.float32 and f.shape == SMALL_GRID.shape
        np.testing.assert_allclose(f, _edt_m(values, 0.4, 0.1, unknown_is_obstacle), rtol=0, atol=1e-5)
    assert published[-1][0] == 7 * s and np.array_equal(published[-1][2], m.values(), equal_nan=True)
    # queries: the field at voxel centres is the field itself (trilinear), the gradient points away
    idx = np.argwhere(np.isfinite(published[-1][1]))[::7]
    np.testing.assert_allclose(ld.distance_at(SMALL_GRID.centers(idx)), published[-1][1][tuple(idx.T)],
                               rtol=0, atol=1e-9)
    assert ld.gradient_at(SMALL_GRID.centers(idx)).shape == (len(idx), 3)

    # a ping far outside the grid changes no voxel: mapped, published as a map, no distance message
    n, updates = len(published), ld.updates
    far = LiveMapper(m, on_publish=on_publish)
    far.add_pose(0, pose(np.eye(3), [50.0, 0, 0]))
    far.add_ping(0, imgs[8])
    far.start()
    far.stop(drain=True)
    assert far.integrated == 1 and ld.updates == updates + 1 and len(published) == n
    st = ld.stats()
    assert st["distance_kind"] == "none" and st["distance_updates"] == ld.updates
    assert 0 < st["distance_update_s"] <= st["distance_seconds"]

    live.reset()
    on_publish(8 * s)
    assert len(published) == n + 1
    empty = published[-1][1]
    assert np.all(empty == 0) if unknown_is_obstacle else np.all(np.isinf(empty))
    with pytest.raises(ValueError, match="inside the grid"):
        ld.distance_at([[100.0, 0.0, 0.0]])


def test_distance_parameters_become_the_fields_options_or_say_what_is_wrong():
    from gpumap.ros.distance_pub import LiveDistance
    from gpumap.ros.params import PARAMETERS, distance_options

    p = {k: v for k, (v, _) in PARAMETERS.items()}
    assert distance_options(p) is None  # off by default
    on = {**p, "distance": True}
    assert distance_options(on) == {"slice_z_m": None, "cloud_radius_m": 0.5, "unknown_is_obstacle": True,
                                    "max_distance_m": None}
    kw = distance_options({**on, "distance_slice_z_m": 0, "distance_max_m": 0.8,
                           "distance_unknown_is_obstacle": False, "distance_cloud_radius_m": 0.25})
    assert kw == {"slice_z_m": 0.0, "cloud_radius_m": 0.25, "unknown_is_obstacle": False,
                  "max_distance_m": 0.8}
    for name, bad, what in (("distance", "yes", "true or false"),
                            ("distance_unknown_is_obstacle", 1, "true or false"),
                            ("distance_cloud_radius_m", -0.1, ">= 0"), ("distance_max_m", -1.0, ">= 0"),
                            ("distance_slice_z_m", [0.1, 0.2], "finite number"),
                            ("distance_cloud_radius_m", math.nan, "finite number")):
        with pytest.raises(ValueError, match=what):
            distance_options({**on, name: bad})
    with pytest.raises(ValueError, match="distance_cloud_radius_m <= distance_max_m"):
        distance_options({**on, "distance_max_m": 0.3, "distance_cloud_radius_m": 0.5})
    m = gpumap.MinMaxMapper(SMALL_SPEC, SMALL_GRID, "numpy")
    ld = LiveDistance(m)  # the middle layer: k = nz // 2, its centre height
    assert ld.slice_k == 5 and ld.slice_z_m == pytest.approx(0.05)
    assert LiveDistance(m, slice_z_m=-0.45).slice_k == 0
    with pytest.raises(ValueError, match="z_m within"):
        LiveDistance(m, slice_z_m=0.5)  # the grid's top face: outside its voxels


@needs_ros
def test_node_publishes_the_distance_field_of_the_map_it_publishes():
    """In process (the worker's publication called here): with distance:=true the node publishes the
    slice at distance_slice_z_m and the cloud within distance_cloud_radius_m of SciPy's field of the
    map, only when the map's obstacles changed; /diagnostics counts the updates; node.distance answers
    queries; without the parameter there is no field."""
    import rclpy

    from gpumap.ros.node import make_node

    imgs, Ts = _small_pings(4, seed=5)
    for on in ("true", "false"):
        ctx = rclpy.Context()
        rclpy.init(context=ctx, domain_id=DOMAIN, args=[
            "x", "--ros-args", "-p", "backend:=numpy", "-p", f"distance:={on}", "-p", "threshold:=0.4",
            "-p", "range_max_m:=1.0", "-p", "n_bins:=40", "-p", "n_beams:=32", "-p", "hfov_deg:=90.0",
            "-p", "grid_min_m:=[-0.2, -1.0, -0.3]", "-p", "grid_max_m:=[1.2, 1.0, 0.3]",
            "-p", "voxel_size_m:=0.05", "-p", "distance_slice_z_m:=0.07",
            "-p", "distance_cloud_radius_m:=0.2", "-p", "distance_unknown_is_obstacle:=false",
            "-r", f"__ns:=/dist{os.getpid()}{on}"])
        try:
            node = make_node(context=ctx)
            node.live.stop(drain=False)  # mapped here, in this thread
            if on == "false":
                assert node.distance is None and node.distance_field is None
                assert not any(k.startswith("distance") for k in node.diagnostics())
                node.destroy_node()
                continue
            sent: list = []
            node.pub_dist_slice.publish = lambda msg, sent=sent: sent.append(("slice", msg))
            node.pub_dist_cloud.publish = lambda msg, sent=sent: sent.append(("cloud", msg))
            grid = node.grid
            for k in range(2):
                node.mapper.integrate_batch(imgs[2 * k:2 * k + 2], Ts[2 * k:2 * k + 2])
                node._publish_map(1_000_000_000 * (k + 1))
                assert [kind for kind, _ in sent] == ["slice", "cloud"] * (k + 1)
                want = _edt_m(node.mapper.values(), 0.4, 0.05, unknown_is_obstacle=False)
                sl, cl = sent[-2][1], sent[-1][1]
                for msg in (sl, cl):
                    assert msg.header.frame_id == "map" and msg.header.stamp.sec == k + 1
                rec = _distance_points(sl)  # layer 7: z in [0.05, 0.1)
                assert rec.shape == (grid.shape[1], grid.shape[0])
                np.testing.assert_allclose(rec["distance"], want[:, :, 7].T, rtol=0, atol=1e-5)
                np.testing.assert_allclose(rec["z"], -0.3 + 7.5 * 0.05, atol=1e-6)
                pts = _distance_points(cl)[0]
                ijk = np.rint((np.stack([pts[n] for n in "xyz"], 1) - np.asarray(grid.min_corner_m))
                              / 0.05 - 0.5).astype(int)
                got = np.zeros(grid.shape, bool)
                got[tuple(ijk.T)] = True
                band = (want > 0) & (want <= 0.2 + 1e-6)
                assert len(pts) == int(band.sum()) > 0 and np.array_equal(got, band)
                np.testing.assert_allclose(pts["distance"], want[tuple(ijk.T)], rtol=0, atol=1e-5)
            node._publish_map(3_000_000_000)  # the map did not change: no distance message
            assert len(sent) == 4
            d = node.diagnostics()
            assert d["distance_updates"] == 3 and d["distance_changes"] == 2 and d["distance_kind"] == "none"
            c = grid.centers(np.array([[3, 4, 7], [10, 20, 2]]))
            with node.distance.lock:
                at = node.distance_field.field()[[3, 10], [4, 20], [7, 2]]
            np.testing.assert_allclose(node.distance.distance_at(c), at, rtol=0, atol=1e-9)
            node.destroy_node()
        finally:
            rclpy.try_shutdown(context=ctx)


@needs_ros
def test_distance_field_on_the_wire_is_scipys_of_the_offline_map(ros_session, tmp_path, sim_recording):
    """Node and ros-play as two processes, distance:=true: nothing is published before a ping is mapped;
    then the last slice and cloud a subscriber gets are SciPy's distance field of the offline map of the
    same pings (unknown voxels as obstacles), stamped as one publication."""
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import PointCloud2

    from gpumap.ros.play import open_playable, write_params

    play = open_playable(sim_recording)
    params = write_params(tmp_path / "sim.yaml", play, voxel_size_m=None, threshold=0.4, backend="numpy",
                          world_frame="map", pose_type="pose_stamped")
    grid = play.grid
    z = grid.min_corner_m[2] + (grid.shape[2] // 3 + 0.5) * grid.voxel_size_m
    ros_session("node", "ros", "--params-file", str(params), "--ros-args", *NODE_TEST_ARGS,
                "-p", "distance:=true", "-p", f"distance_slice_z_m:={z}",
                "-p", "distance_cloud_radius_m:=0.3")
    probe = ros_session.probe()
    slices: list = []
    clouds: list = []
    latched = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
    ns = ros_session.ns
    probe.node.create_subscription(PointCloud2, f"{ns}/gpumap/distance_slice", slices.append, latched)
    probe.node.create_subscription(PointCloud2, f"{ns}/gpumap/distance_cloud", clouds.append, latched)
    probe.spin_until(lambda: probe.diag is not None, 60, "the node's first diagnostics")
    assert probe.count("distance_changes") == 0 and not clouds  # nothing mapped: nothing published
    player = ros_session("play", "ros-play", str(sim_recording), "--hz", "20", "--no-progress")
    player.wait(60)
    assert player.returncode == 0
    frames = list(play.frames())
    probe.spin_until(lambda: probe.count("pings_integrated") == len(frames) and probe.count("queue") == 0,
                     60, "every ping mapped")
    probe.spin_for(0.5)  # the last publication, and the diagnostics after it
    n = probe.count("distance_changes")
    assert 1 <= n <= probe.count("distance_updates")
    assert 1 <= len(clouds) <= n and len(slices) == len(clouds)  # a latched depth of 1: the newest survive
    assert slices[-1].header.stamp == clouds[-1].header.stamp
    ref = _offline(play, grid, frames)
    want = _edt_m(ref.values(), 0.4, grid.voxel_size_m, unknown_is_obstacle=True)
    k = grid.shape[2] // 3
    np.testing.assert_allclose(_distance_points(slices[-1])["distance"], want[:, :, k].T, rtol=0, atol=1e-5)
    pts = _distance_points(clouds[-1])[0]
    ijk = np.rint((np.stack([pts[c] for c in "xyz"], 1) - np.asarray(grid.min_corner_m)) / grid.voxel_size_m
                  - 0.5).astype(int)
    band = (want > 0) & (want <= 0.3 + 1e-6)
    got = np.zeros(grid.shape, bool)
    got[tuple(ijk.T)] = True
    assert len(pts) == int(band.sum()) > 0 and np.array_equal(got, band)
    np.testing.assert_allclose(pts["distance"], want[tuple(ijk.T)], rtol=0, atol=1e-5)
