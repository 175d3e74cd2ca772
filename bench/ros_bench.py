"""The ROS 2 node's rates over Fast DDS: ``python -m bench.ros_bench`` -> ``bench/results/ros.json``.

``--distance`` instead times the node with its distance field off and on (``-p distance:=true``, issue 44)
at each ``--rates`` rate, alternating, ``--repeat`` times each: the occupied cloud's latency as before,
and with the field on also the distance cloud's (``~/distance_cloud``: the first one whose stamp reaches
the ping's; the field is published only when it changed, so this is the wait until a field at least that
new is out) -> ``bench/results/distance_node.json`` (the distance section of BENCHMARKS.md shows it).
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from .common import bench_parser, load_average, machine_info, now, oasis_tank_dir, write_json


class Listener:
    """Reads one node's diagnostics, clouds (receipt time, stamp) and ping stamps (from sonar/pose)."""

    def __init__(self, ns: str, domain: int, distance: bool = False) -> None:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseStamped
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import PointCloud2

        from gpumap.ros.convert import stamp_ns

        self._stamp, self.ns, self.ctx = stamp_ns, ns, rclpy.Context()
        rclpy.init(context=self.ctx, domain_id=domain)
        self.node = rclpy.create_node("bench_listener", namespace=ns, context=self.ctx)
        self.ex = SingleThreadedExecutor(context=self.ctx)
        self.ex.add_node(self.node)
        self.diag: dict | None = None
        self.clouds: list[tuple[int, int]] = []  # (received ns, stamp ns)
        self.pings: list[int] = []
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.node.create_subscription(PointCloud2, f"{ns}/gpumap/occupied_cloud", self._on_cloud, latched)
        self.distance_clouds: list[tuple[int, int]] = []  # (received ns, stamp ns) of ~/distance_cloud
        if distance:
            self.node.create_subscription(
                PointCloud2, f"{ns}/gpumap/distance_cloud",
                lambda m: self.distance_clouds.append((time.time_ns(), stamp_ns(m.header.stamp))), latched)
        self.node.create_subscription(PoseStamped, f"{ns}/sonar/pose",
                                      lambda m: self.pings.append(stamp_ns(m.header.stamp)), 200)
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diag, 10)

    def _on_cloud(self, msg) -> None:
        self.clouds.append((time.time_ns(), self._stamp(msg.header.stamp)))

    def _on_diag(self, msg) -> None:
        for st in msg.status:
            if st.name == f"{self.ns}/gpumap: mapper":
                self.diag = {kv.key: kv.value for kv in st.values}

    def spin(self, seconds: float, until=None) -> bool:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.ex.spin_once(timeout_sec=0.02)
            if until is not None and until():
                return True
        return False

    def count(self, key: str) -> int:
        return int((self.diag or {}).get(key, 0))

    def latencies_ms(self, clouds: list[tuple[int, int]] | None = None) -> np.ndarray:
        """Per ping: first cloud (of ``clouds``, default the occupied ones) whose stamp reaches the ping's,
        received - sent."""
        clouds = self.clouds if clouds is None else clouds
        if not clouds:
            return np.array([])
        rec = np.array(clouds, dtype=np.int64)
        rec = rec[np.argsort(rec[:, 0], kind="stable")]
        hits = [np.flatnonzero(rec[:, 1] >= t) for t in self.pings]
        return np.array([(rec[h[0], 0] - t) * 1e-6 for h, t in zip(hits, self.pings, strict=True) if h.size])

    def close(self) -> None:
        import rclpy

        self.ex.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.ctx)


def run_once(tank: Path, params: Path, hz: float, domain: int, n_pings: int, tmp: Path,
             node_args: tuple[str, ...] = ()) -> dict:
    """One fresh node (``node_args``: more ``-p name:=value``), one play of the tank at ``hz``; what the
    node and the listener saw."""
    ns = f"/bench{os.getpid()}_{int(hz)}_{time.monotonic_ns() % 10**6}"
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               PYTHONUNBUFFERED="1")
    base = [sys.executable, "-m", "gpumap.commands"]
    nlog = open(tmp / "node.log", "w")  # noqa: SIM115
    node = subprocess.Popen([*base, "ros", "--params-file", str(params), "--ros-args", "-r", f"__ns:={ns}",
                             "-p", "diagnostics_period_s:=0.25", *node_args], stdout=nlog,
                            stderr=subprocess.STDOUT, env=env, start_new_session=True)
    distance = "distance:=true" in node_args
    lis = Listener(ns, domain, distance)
    try:
        if not lis.spin(90, lambda: lis.diag is not None):
            raise RuntimeError(f"the node did not start: {(tmp / 'node.log').read_text()[-2000:]}")
        load0 = load_average() or []
        play = subprocess.Popen([*base, "ros-play", str(tank), "--hz", str(hz), "--no-progress", "--preload",
                                 "--ros-args", "-r", f"__ns:={ns}"], stdout=subprocess.PIPE,
                                stderr=subprocess.STDOUT, env=env, text=True, start_new_session=True)
        while play.poll() is None:
            lis.spin(0.1)
        m = re.search(r"published (\d+) pings in ([\d.]+) s", play.stdout.read())

        def lost(d: dict, prefixes: tuple) -> dict:
            return {k: int(v) for k, v in d.items() if k.startswith(prefixes)}

        lis.spin(30, lambda: lis.count("queue") == 0 and lis.count("pings_integrated")
                 + sum(lost(lis.diag or {}, ("dropped", "skipped")).values()) >= lis.count("pings_received"))
        lis.spin(1.0)
        d, lat = dict(lis.diag or {}), lis.latencies_ms()
        gone, integrated = lost(d, ("dropped.", "skipped.", "rejected.")), int(d.get("pings_integrated", 0))
        pct = {q: round(float(np.percentile(lat, q)), 1) if lat.size else None for q in (50, 99)}
        extra = {}
        if distance:
            dl = lis.latencies_ms(lis.distance_clouds)
            dp = {q: round(float(np.percentile(dl, q)), 1) if dl.size else None for q in (50, 99)}
            extra = {"distance_clouds": len(lis.distance_clouds), "distance_latency_pings": int(dl.size),
                     "distance_latency_ms_p50": dp[50], "distance_latency_ms_p99": dp[99],
                     **{k: d.get(k) for k in ("distance_updates", "distance_changes", "distance_update_s",
                                              "distance_seconds")}}
        return {"requested_hz": hz, "node_args": list(node_args), "published": int(m.group(1)) if m else None,
                "play_seconds": float(m.group(2)) if m else None,
                "achieved_hz": round(int(m.group(1)) / float(m.group(2)), 1) if m else None,
                "integrated": integrated, "lost": gone, "sustained": integrated == n_pings and not gone,
                "latency_ms_p50": pct[50], "latency_ms_p99": pct[99], "latency_pings": int(lat.size),
                "node_latency_ms_p50": float(d.get("latency_p50_ms", "nan")),
                "node_latency_ms_p99": float(d.get("latency_p99_ms", "nan")), "backend": d.get("backend"),
                "load_avg": [*load0, *(load_average() or [])], **extra}
    finally:
        lis.close()
        if node.poll() is None:
            node.send_signal(signal.SIGINT)
            try:
                node.wait(30)
            except subprocess.TimeoutExpired:
                node.kill()
        nlog.close()


def main(argv: list[str] | None = None) -> int:
    ap = bench_parser("ros_bench", __doc__, out="bench/results/ros.json", backend="auto",
                      voxel=[0.05, 0.03])
    ap.add_argument("--rates", type=float, nargs="+", default=[10, 20, 40, 80, 160, 320],
                    help="play rates to try, pings per second (10: the latency figures)")
    ap.add_argument("--note", default="", help="a remark stored with the results")
    ap.add_argument("--distance", action="store_true",
                    help="time the node with the distance field off and on (module docstring) into "
                         "bench/results/distance_node.json unless --out says otherwise")
    ap.add_argument("--repeat", type=int, default=2, help="--distance: plays of each setting per rate")
    a = ap.parse_args(argv)
    if a.distance and a.out == Path("bench/results/ros.json"):
        a.out = Path("bench/results/distance_node.json")
    tank = oasis_tank_dir()
    if tank is None:
        raise SystemExit("bench.ros_bench: shared/data/oasis_tank not found beside the checkout")
    from gpumap.ros import use_gpumap_fastdds_profile
    from gpumap.ros.play import open_playable, write_params

    use_gpumap_fastdds_profile()
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    domain, play, info = 101 - os.getpid() % 50, open_playable(tank), machine_info()
    res: dict = {"what": "gpumap ros + gpumap ros-play over Fast DDS on loopback, real OASIS tank (123 "
                         "pings, 32FC1 398 x 512), one fresh node per run; latency = first cloud holding the "
                         "ping received by a third process - ping sent by ros-play",
                 "cpu": info["cpu_model"], "n_cpus": info["cpu_count"], "machine": info, "note": a.note,
                 "loaded": "shared machine: other engineers' jobs ran beside it (load_avg per run: 1, 5, 15 "
                           "min before the play, then after)", "runs": {}}
    if a.distance:
        return _distance_runs(a, tank, play, domain, info)
    with tempfile.TemporaryDirectory() as tmp:
        for vs in a.voxel:
            params = write_params(Path(tmp) / f"tank_{vs}.yaml", play, voxel_size_m=vs, threshold=0.4,
                                  backend=a.backend, world_frame="map", pose_type="pose_stamped")
            rows, fails = [], 0
            for hz in a.rates:
                r = run_once(tank, params, hz, domain, play.count, Path(tmp))
                print(json.dumps({"voxel_size_m": vs, **r}), flush=True)
                rows.append(r)
                fails = 0 if r["sustained"] else fails + 1
                if fails >= 2:
                    break
            ok = [r["achieved_hz"] for r in rows if r["sustained"]]
            rec = next((r for r in rows if r["requested_hz"] == 10), None)
            lat = None if rec is None else [rec["latency_ms_p50"], rec["latency_ms_p99"]]
            res["runs"][f"{vs}"] = {"rows": rows, "max_sustained_achieved_hz": max(ok) if ok else None,
                                    "latency_at_10hz_ms": lat}
    write_json(a.out, res)
    print(f"wrote {a.out}")
    return 0


def _distance_runs(a, tank: Path, play, domain: int, info: dict) -> int:
    """``--distance``: per voxel size and rate, ``--repeat`` plays with the field off and on, alternating."""
    from gpumap.ros.play import write_params

    res: dict = {"schema": "gpumap-distance-node/1", "created": now(), "argv": list(sys.argv[1:]),
                 "what": "gpumap ros + gpumap ros-play over Fast DDS on loopback, real OASIS tank (123 "
                         "pings, 32FC1 398 x 512), one fresh node per play, the distance field off and on "
                         "(distance:=true, its other parameters at their defaults), alternating; latency = "
                         "first cloud holding the ping received by a third process - ping sent by ros-play",
                 "machine": info, "note": a.note, "backend": a.backend, "runs": []}
    with tempfile.TemporaryDirectory() as tmp:
        for vs in a.voxel:
            params = write_params(Path(tmp) / f"tank_{vs}.yaml", play, voxel_size_m=vs, threshold=0.4,
                                  backend=a.backend, world_frame="map", pose_type="pose_stamped")
            for hz in a.rates:
                for k in range(a.repeat):
                    for on in (False, True):
                        args = ("-p", "distance:=true") if on else ()
                        r = run_once(tank, params, hz, domain, play.count, Path(tmp), args)
                        r.update(voxel_size_m=vs, distance=on, repeat=k)
                        print(json.dumps(r), flush=True)
                        res["runs"].append(r)
    write_json(a.out, res)
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
