"""``gpumap ros``: a ROS 2 node that maps live sonar pings (needs the ``[ros]`` extra).

Usage::

    gpumap ros [--params-file FILE] [--ros-args ...]

Everything after ``--ros-args`` goes to ROS as usual (``-p name:=value``, ``-r from:=to``,
``--params-file``, ``--log-level``); ``--params-file FILE`` before it is short for
``--ros-args --params-file FILE``. The node is named ``gpumap``.

Subscribes (relative names: remap them with ``-r``):

- ``sonar/image`` (``sensor_msgs/Image``, sensor-data QoS: best effort): the polar image
  ``(n_bins, n_beams)`` (rows = range bins, ascending; columns = beams in ascending azimuth),
  ``mono8``, ``mono16`` or ``32FC1`` (in [0, 1]); with ``image_layout: fan`` a Cartesian fan
  picture whose geometry the ``fan_*`` parameters name, converted to polar on arrival.
- ``sonar/pose`` (``geometry_msgs/PoseStamped``, or ``nav_msgs/Odometry`` with
  ``pose_type: odometry``; reliable): ``T_W_S``, the sonar's pose in ``world_frame``.

- ``sonar/images_sent`` (``std_msgs/UInt64``, reliable, transient-local; optional): how many
  images a publisher sent, said at its end (``gpumap ros-play`` does): those after the last
  one that arrived are counted as ``dropped['lost_at_stream_end']``.

Publishes (in ``world_frame``): ``~/occupied_cloud`` (``sensor_msgs/PointCloud2``, fields
x, y, z, value: every voxel with value >= ``threshold``; with ``confidence: true`` also
``confirmed``, uint8 at offset 16 of 20-byte points: 1 where some view resolved the voxel in
elevation, 0 where it is only consistent with the pings, see :mod:`gpumap.layers.confidence`),
``~/occupied_markers``
(``visualization_msgs/MarkerArray``, a cube list per 16^3-voxel block, only changed blocks;
all of them again when a new subscriber appears), ``~/projected_map``
(``nav_msgs/OccupancyGrid``: 100 where a voxel in ``band_z_m`` is occupied, 0 observed, -1
unknown), all three reliable and transient-local (a late subscriber gets the latest); the
cloud's stamp is the newest ping in it. ``/diagnostics`` (``diagnostic_msgs/DiagnosticArray``,
every ``diagnostics_period_s``): ping rate, latency p50/p99 (arrival to published cloud),
queue, received/integrated, rejected, skipped and dropped by reason, backend, map memory.

With ``surface: true`` (default false) the surface layer (:mod:`gpumap.layers.surface`) is kept too, on a
thread of its own (:class:`gpumap.ros.surface_worker.LiveSurfaceWorker`), and updated as often as the machine
allows, each update taking every ping mapped meanwhile: ``~/surface_cloud`` (``PointCloud2``, x, y,
z, value 1 per surface voxel; stamped with the newest ping it covers) and ``~/surface_markers``,
reliable and transient-local; each is the offline layer
(:func:`gpumap.layers.surface_live.surface_from_mapper`)
of the pings it covers. ``/diagnostics`` then adds ``surface_pings`` (covered), ``surface_waiting``
(mapped, not yet in it), ``surface_age_s`` (how long the oldest of those has waited since it arrived),
``surface_latency_max_s``, ``surface_update_s`` (the last update's seconds), ``surface_updates`` and
``surface_voxels``. The layer keeps every ping (its memory and its updates grow with the run) unless
``surface_max_pings`` bounds it to the newest ones. Its thread shares the interpreter (and its lock)
with the message callbacks: on a 2-core CPU with the numpy backend, the real tank's 25 Hz images
overflowed the default ``image_queue_depth`` of 10 (images lost in the middleware, counted), which a
deeper queue absorbs; a process of its own would not need one.

With ``distance: true`` (default false) the node keeps the distance field of the safe map
(:mod:`gpumap.layers.distance`, on the mapper's backend; :class:`gpumap.ros.distance_pub.LiveDistance`):
with each map publication the worker updates it from the same read of the map (only what the new pings
changed: the result equals a full recomputation) and, only when that changed it, publishes
``~/distance_slice`` (an organised ``PointCloud2``, ny rows of nx voxels, float32 x, y, z, distance: the
layer of voxels holding ``distance_slice_z_m``) and ``~/distance_cloud`` (unordered ``PointCloud2``,
the same fields: the free voxels within ``distance_cloud_radius_m`` of an obstacle, nvblox's ESDF cloud),
both reliable and transient-local, stamped as the occupied cloud. Distances are metres to the nearest
obstacle voxel centre (0 at obstacles), obstacles being the occupied voxels and, with
``distance_unknown_is_obstacle`` (default true), the unknown ones; ``distance_max_m`` caps them.
``/diagnostics`` then adds ``distance_updates``, ``distance_changes``, ``distance_kind``,
``distance_update_s`` (the last update's seconds) and ``distance_seconds`` (all updates'). In the
node's process a planner queries the field directly: ``node.distance.distance_at(points_W)``,
``node.distance.gradient_at(points_W)`` and ``node.distance.block(center_m, half_extent_m)`` hold the
field's lock (never a field half updated); ``node.distance_field`` is the
:class:`~gpumap.layers.distance.DistanceField` itself (hold ``node.distance.lock`` around its use).
Both are None with ``distance: false``.

Services (``std_srvs/Trigger``): ``~/save_map`` writes ``save_path`` atomically: with the surface
layer, both layers in one file (the safe map's values and the surface layer of every ping mapped so
far: :func:`gpumap.layers.refined_map.load_refined`, ``gpumap view/export --layer surface|safe`` read it);
with ``surface: false`` the map file of ``gpumap replay`` (``MinMaxMapper.load`` reads it).
``~/reset`` forgets the map (and the surface layer's pings).
Ctrl-C (or SIGTERM) drains the queue, saves when ``save_on_exit`` is true, and exits 0.

Parameters (``ros2 param``-style, from ``--params-file`` YAML or ``-p``); the sonar comes from
``sonar_spec_file`` (a JSON or YAML file with ``SonarSpec.to_dict()``'s keys, as
``gpumap ros-play --write-params`` also writes inline) or from ``range_min_m``,
``range_max_m``, ``n_bins``, ``vfov_deg`` and ``bearings_deg`` (or ``hfov_deg`` + ``n_beams``
for evenly spaced beams). See :data:`PARAMETERS` for every name, default and meaning.
"""

from __future__ import annotations

import math
import sys
import threading
import time

import numpy as np

from gpumap.core.params import MapperParams
from gpumap.layers.confidence import ConfidenceLayer
from gpumap.ros import require_ros
from gpumap.ros.convert import (
    BadMessage,
    MarkerBlocks,
    cloud_msg,
    image_from_msg,
    occupancy_grid_msg,
    occupied_cloud,
    pose_array_msg,
    pose_from_msg,
    project_obstacles,
    stamp_ns,
)
from gpumap.ros.launch import (
    FASTDDS_DEFAULT_SEGMENT_BYTES,
    FASTDDS_HINT,
    PARTICIPANT_PREFIX,
    lost_at_stream_end,
)
from gpumap.ros.live import LiveMapper, health
from gpumap.ros.params import (
    PARAMETERS,
    _choice,
    _flag,
    distance_options,
    plan_options,
    sonar_spec_from_params,
)
from gpumap.spec import GridSpec

__all__ = ["NODE_NAME", "PARAMETERS", "make_node", "sonar_spec_from_params"]

NODE_NAME = "gpumap"


def make_node(node_name: str = NODE_NAME, context=None):
    """Create the mapping node (rclpy must be initialised); raises ValueError on bad parameters.

    With ``distance: true``, a planner in the same process queries the live distance field beside the
    node (the worker keeps it up to date meanwhile)::

        node = make_node()
        d = node.distance.distance_at(points_W)      # (N, 3) world metres -> (N,) metres, under its lock
        g = node.distance.gradient_at(points_W)      # (N, 3) per metre
        with node.distance.lock:                     # anything else of the DistanceField itself
            f = node.distance_field.field()

    ``node.distance`` (:class:`gpumap.ros.distance_pub.LiveDistance`) and ``node.distance_field``
    (:class:`gpumap.layers.distance.DistanceField`) are None with ``distance: false``.
    """
    require_ros()
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
    from geometry_msgs.msg import PoseArray, PoseStamped
    from nav_msgs.msg import OccupancyGrid, Odometry
    from rcl_interfaces.msg import ParameterDescriptor
    from rclpy.node import Node
    from rclpy.qos import (
        DurabilityPolicy,
        HistoryPolicy,
        QoSProfile,
        ReliabilityPolicy,
    )
    from sensor_msgs.msg import Image, PointCloud2
    from std_srvs.srv import Trigger
    from visualization_msgs.msg import MarkerArray

    import gpumap
    from gpumap.io.fan import FanGeometry, fan_to_polar

    class GpumapNode(Node):
        def __init__(self) -> None:
            super().__init__(node_name, context=context)
            for name, (default, desc) in PARAMETERS.items():
                # dynamic typing: YAML's 1 and 1.0, [1, 2] and [1.0, 2.0] are both accepted (checked below)
                self.declare_parameter(name, default,
                                       ParameterDescriptor(description=desc, dynamic_typing=True))
            p = {name: self.get_parameter(name).value for name in PARAMETERS}
            self.p = p
            self.plan_kw = plan_options(p)  # checked before anything is allocated
            dist_kw = distance_options(p)
            self.world_frame = str(p["world_frame"])
            pose_type = _choice(p, "pose_type", ("pose_stamped", "odometry"))
            self.layout = _choice(p, "image_layout", ("polar", "fan"))
            self.spec = sonar_spec_from_params(p)
            lo, hi = list(p["grid_min_m"]), list(p["grid_max_m"])
            if len(lo) != 3 or len(hi) != 3:
                raise ValueError(f"Expected grid_min_m and grid_max_m of 3 numbers each, but got {lo} and "
                                 f"{hi}")
            self.grid = GridSpec(tuple(lo), tuple(hi), float(p["voxel_size_m"]))
            band = list(p["band_z_m"])
            if band and (len(band) != 2 or not band[0] <= band[1]):
                raise ValueError(f"Expected band_z_m as [z_min, z_max] with z_min <= z_max, but got {band}")
            self.band = (float(band[0]), float(band[1])) if band else None
            self.threshold = float(p["threshold"])
            self.max_future_ns = int(float(p["max_future_s"]) * 1e9)
            if self.layout == "fan":
                self.geom = FanGeometry(int(p["fan_rows"]), int(p["fan_cols"]), float(p["fan_pixel_m"]),
                                        float(p["fan_apex_row"]), float(p["fan_apex_col"]),
                                        bool(p["fan_flip_lr"]), bool(p["fan_flip_ud"]))
                self.in_shape = (self.geom.n_rows, self.geom.n_cols)
            else:
                self.in_shape = self.spec.image_shape
            self.mapper = gpumap.MinMaxMapper(
                self.spec, self.grid, str(p["backend"]),
                MapperParams(rule=_choice(p, "rule", ("evidence", "visible", "plain")),
                             threshold=self.threshold, carve_views=int(p["carve_views"])))
            self.confidence = _flag(p, "confidence")
            if self.confidence:
                self.mapper.attach(ConfidenceLayer())
            self.surface = _flag(p, "surface")
            if self.surface and self.mapper.rule == "plain":
                raise ValueError("Expected rule evidence or visible with surface:=true (the surface layer "
                                 "chooses from their occupied voxels), but got rule plain: set "
                                 "surface:=false")
            # the mapper's bytes per voxel (4 plain, 16 with the view state) [+ confirmed (1) and
            # arcs (2), confidence]
            self.map_bytes = self.grid.n_voxels * (self.mapper.bytes_per_voxel
                                                   + (3 if self.confidence else 0))
            #: the distance field and its lock (None without distance: true; module docstring)
            self.distance = None
            if dist_kw is not None:
                from gpumap.ros.distance_pub import LiveDistance

                self.distance = LiveDistance(self.mapper, **dist_kw)
            self.distance_field = None if self.distance is None else self.distance.field
            log = self.get_logger()
            self.live = LiveMapper(
                self.mapper, queue_size=int(p["queue_size"]), max_batch=int(p["max_batch"]),
                pose_wait_s=float(p["pose_wait_s"]), max_pose_gap_s=float(p["max_pose_gap_s"]),
                pose_buffer=int(p["pose_buffer"]), publish_period_s=float(p["publish_period_s"]),
                on_publish=self._publish_map, log=log.warning)
            self.blocks = MarkerBlocks(self.grid, self.threshold)
            self.surf = None
            if self.surface:
                from gpumap.layers.surface import SURFACE_LEVEL
                from gpumap.ros.surface_worker import LiveSurfaceWorker

                n = p["surface_max_pings"]
                if isinstance(n, bool) or not isinstance(n, int) or n < 0:
                    raise ValueError(f"Expected parameter surface_max_pings to be an integer >= 0, but got "
                                     f"{n!r}")
                self.surf = LiveSurfaceWorker(self.live, on_publish=self._publish_surface, log=log.warning,
                                              max_pings=n or None)
                self.surf_blocks = MarkerBlocks(self.grid, SURFACE_LEVEL)
                self._surf_marker_subs = 0
            self._marker_subs = 0
            self._markers_at = -math.inf
            self._markers_stale: tuple[int, np.ndarray, np.ndarray | None] | None = None
            self.markers_period_s = float(p["markers_period_s"])
            self._publish_lock = threading.Lock()

            latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                                 durability=DurabilityPolicy.TRANSIENT_LOCAL, history=HistoryPolicy.KEEP_LAST)
            self.pub_cloud = self.create_publisher(PointCloud2, "~/occupied_cloud", latched)
            self.pub_markers = self.create_publisher(MarkerArray, "~/occupied_markers", latched)
            self.pub_grid = self.create_publisher(OccupancyGrid, "~/projected_map", latched)
            self.pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
            if self.surface:
                self.pub_surface = self.create_publisher(PointCloud2, "~/surface_cloud", latched)
                self.pub_surface_markers = self.create_publisher(MarkerArray, "~/surface_markers", latched)
            if self.distance is not None:
                self.pub_dist_slice = self.create_publisher(PointCloud2, "~/distance_slice", latched)
                self.pub_dist_cloud = self.create_publisher(PointCloud2, "~/distance_cloud", latched)
            self._diag_types = (DiagnosticArray, DiagnosticStatus, KeyValue)

            sensor = QoSProfile(depth=int(p["image_queue_depth"]), reliability=ReliabilityPolicy.BEST_EFFORT,
                                durability=DurabilityPolicy.VOLATILE, history=HistoryPolicy.KEEP_LAST)
            # images lost before this node are found from the gaps in each publisher's sequence
            # numbers (the transport's, the subscription queue's overflow, ...): counted, never silent
            self._last_seq: dict[bytes, int] = {}
            self.sub_image = self.create_subscription(Image, "sonar/image", self._on_image, sensor)
            # images lost after the last one delivered leave no gap: a publisher that says how many it
            # sent (gpumap ros-play does, at its end) lets them be counted (dropped.lost_at_stream_end)
            self._sent: dict[bytes, int] = {}
            from std_msgs.msg import UInt64

            sent_qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                                  durability=DurabilityPolicy.TRANSIENT_LOCAL,
                                  history=HistoryPolicy.KEEP_LAST)
            self.sub_sent = self.create_subscription(UInt64, "sonar/images_sent", self._on_sent, sent_qos)
            pose_qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                                  durability=DurabilityPolicy.VOLATILE, history=HistoryPolicy.KEEP_LAST)
            self.sub_pose = self.create_subscription(Odometry if pose_type == "odometry" else PoseStamped,
                                                     "sonar/pose", self._on_pose, pose_qos)
            self._diag_prev: dict | None = None  # the counters at the last /diagnostics, for its rates
            self.srv_save = self.create_service(Trigger, "~/save_map", self._on_save)
            self.srv_reset = self.create_service(Trigger, "~/reset", self._on_reset)
            self.pub_views = self.create_publisher(PoseArray, "~/next_best_views", latched)
            self.srv_plan = self.create_service(Trigger, "~/plan_views", self._on_plan)
            self.timer_diag = self.create_timer(float(p["diagnostics_period_s"]), self._publish_diagnostics)
            self.live.start()
            if self.surf is not None:
                self.surf.start()
            log.info(f"mapping {self.spec.image_shape} {self.layout} images on {self.sub_image.topic_name} "
                     f"with poses on {self.sub_pose.topic_name} into a {self.grid.shape} grid of "
                     f"{self.grid.voxel_size_m} m ({self.mapper.backend} on {self.mapper.device}); "
                     f"cloud on {self.pub_cloud.topic_name}")
            big = 4 * self.spec.image_shape[0] * self.spec.image_shape[1]
            if big > FASTDDS_DEFAULT_SEGMENT_BYTES:
                log.info(f"a 32FC1 image of this sonar is {big:,} bytes: {FASTDDS_HINT}")

        # ------------------------------------------------------------ callbacks: never block
        def _now_ns(self) -> int:
            return self.get_clock().now().nanoseconds

        def _on_image(self, msg, info) -> None:  # two arguments: rclpy passes the message info
            self.live.count_received()
            seq = info.get("publication_sequence_number") if info else None
            if seq:
                gid = bytes(info["publisher_gid"]["data"])
                last = self._last_seq.get(gid)
                self._last_seq[gid] = max(seq, last or 0)
                if last is not None and seq > last + 1:
                    hint = f"; {FASTDDS_HINT}" if len(msg.data) > FASTDDS_DEFAULT_SEGMENT_BYTES else ""
                    self.live.drop("middleware_lost", seq - last - 1,
                                   "images published but never delivered to this node (a gap in the "
                                   "publisher's sequence numbers: the transport or the subscription queue "
                                   f"lost them){hint}")
            t = stamp_ns(msg.header.stamp)
            if t > self._now_ns() + self.max_future_ns:
                self.live.reject("image_from_future", f"image stamped {t * 1e-9:.3f} s, more than "
                                 f"{self.max_future_ns * 1e-9} s after the node's clock")
                return
            try:
                img = image_from_msg(msg, self.in_shape)
                if self.layout == "fan":
                    if img.dtype == np.uint8:
                        img = img.astype(np.float32) / np.float32(255.0)
                    img = np.clip(fan_to_polar(img, self.spec, self.geom), 0.0, 1.0)
            except BadMessage as e:
                self.live.reject(e.reason, str(e))
                return
            self.live.add_ping(t, img, self._now_ns())

        def _on_sent(self, msg, info) -> None:
            gid = bytes(info["publisher_gid"]["data"]) if info else b""
            self._sent[gid[:PARTICIPANT_PREFIX]] = int(msg.data)

        def _on_pose(self, msg) -> None:
            try:
                t, T = pose_from_msg(msg, self.world_frame)
            except BadMessage as e:
                self.live.reject(e.reason, str(e))
                return
            if t > self._now_ns() + self.max_future_ns:
                self.live.reject("pose_from_future", f"pose stamped {t * 1e-9:.3f} s, more than "
                                 f"{self.max_future_ns * 1e-9} s after the node's clock")
                return
            self.live.add_pose(t, T)

        # ------------------------------------------------------------ worker thread
        def _publish_map(self, newest_ns: int) -> None:
            with self._publish_lock:
                values, conf = self.live.values_and_confidence(self.confidence)
                centres, vals, confirmed = occupied_cloud(values, self.grid, self.threshold, conf)
                self.pub_cloud.publish(cloud_msg(centres, vals, newest_ns, self.world_frame, confirmed))
                subs = self.pub_markers.get_subscription_count()
                full = subs > self._marker_subs
                now = time.monotonic()
                self._markers_stale = (newest_ns, values, conf)
                if subs and (full or now - self._markers_at >= self.markers_period_s):
                    self._publish_markers(subs, full)
                cells = project_obstacles(values, self.grid, self.threshold, self.band)
                self.pub_grid.publish(occupancy_grid_msg(cells, self.grid, self.band, newest_ns,
                                                         self.world_frame))
                if self.distance is not None:  # the same read of the map: the field of that cloud's map
                    field = self.distance.refresh(values)
                    if field is not None:  # only when the update changed it
                        sl, cl = self.distance.messages(field, newest_ns, self.world_frame)
                        self.pub_dist_slice.publish(sl)
                        self.pub_dist_cloud.publish(cl)

        def _publish_surface(self, layer, newest_ns: int) -> None:
            """The surface worker's ``on_publish``: the layer's voxels as a cloud (value 1) and markers."""
            from gpumap.layers.surface import SURFACE_LEVEL

            values = layer.values()
            centres, vals, _ = occupied_cloud(values, self.grid, SURFACE_LEVEL)
            self.pub_surface.publish(cloud_msg(centres, vals, newest_ns, self.world_frame))
            subs = self.pub_surface_markers.get_subscription_count()
            if subs:
                changed = self.surf_blocks.update(values, full=subs > self._surf_marker_subs)
                self._surf_marker_subs = subs
                if changed:
                    msg = self.surf_blocks.msg(changed, newest_ns, self.world_frame, ns="gpumap_surface")
                    self.pub_surface_markers.publish(msg)

        def _publish_markers(self, subs: int, full: bool) -> None:
            # one Point per voxel in Python: the costly output, so at most every markers_period_s
            # (and once more, from the diagnostics timer, when the map has stopped changing)
            newest_ns, values, conf = self._markers_stale
            self._markers_stale = None
            self._marker_subs, self._markers_at = subs, time.monotonic()
            changed = self.blocks.update(values, full=full, confirmed=None if conf is None else conf == 3)
            if changed:
                self.pub_markers.publish(self.blocks.msg(changed, newest_ns, self.world_frame))

        # ------------------------------------------------------------ services, diagnostics
        def _save(self) -> str:
            """Write ``save_path``: the map file, or with the surface layer both layers in one file (the
            layer of every ping mapped so far, on the same map)."""
            if self.surf is None:
                return str(self.live.save(str(self.p["save_path"])))
            layer, values = self.surf.layer_now()
            path = layer.save(str(self.p["save_path"]), values, self.spec, self.threshold, self.mapper.rule)
            return str(path)

        def _on_save(self, request, response):
            try:
                path = self._save()
                response.success, response.message = True, str(path)
            except (OSError, ValueError) as e:
                response.success, response.message = False, f"saving failed: {e}"
            return response

        def _on_plan(self, request, response):
            """Score candidates around the newest pose mapped; publish the best on
            ~/next_best_views (a PoseArray, best first, in world_frame)."""
            if not self.confidence:
                response.success = False
                response.message = ("planning needs the confidence layer: start the node with "
                                    "-p confidence:=true")
                return response
            try:
                views, n = self.live.next_best_views(**self.plan_kw)
            except ValueError as e:
                response.success, response.message = False, str(e)
                return response
            self.pub_views.publish(pose_array_msg([v["T_W_S"] for v in views], self._now_ns(),
                                                  self.world_frame))
            response.success = True
            response.message = (f"{len(views)} views of {n} candidates on {self.pub_views.topic_name}, gains "
                                + ", ".join(f"{v['gain']:.0f}" for v in views))
            return response

        def _on_reset(self, request, response):
            with self._publish_lock:
                self.live.reset()  # the surface layer's pings too (its worker is the live mapper's on_reset)
                self.blocks.reset()
                self._marker_subs = 0
                self._markers_stale = None
            self._publish_map(self._now_ns())  # subscribers see the empty map at once
            if self.surf is not None:
                from gpumap.ros.convert import cloud_msg as _cloud

                self.surf_blocks.reset()
                self._surf_marker_subs = 0
                self.pub_surface.publish(_cloud(np.zeros((0, 3)), np.zeros(0, np.float32), self._now_ns(),
                                                self.world_frame))
            response.success, response.message = True, "map reset: every voxel unknown"
            return response

        def diagnostics(self) -> dict:
            s = self.live.stats()
            end = lost_at_stream_end(self._sent, self._last_seq)
            if end:
                s["dropped"]["lost_at_stream_end"] = end
            s.update(backend=self.mapper.backend, device=self.mapper.device, map_bytes=self.map_bytes,
                     grid_shape=list(self.grid.shape), voxel_size_m=self.grid.voxel_size_m,
                     threshold=self.threshold)
            if self.surf is not None:
                s.update(self.surf.stats())
            if self.distance is not None:
                s.update(self.distance.stats())
            return s

        def _publish_diagnostics(self) -> None:
            stale = self._markers_stale is not None
            if stale and time.monotonic() - self._markers_at >= self.markers_period_s:
                with self._publish_lock:
                    subs = self.pub_markers.get_subscription_count()
                    if self._markers_stale is not None and subs:
                        self._publish_markers(subs, subs > self._marker_subs)
            DiagnosticArray, DiagnosticStatus, KeyValue = self._diag_types
            s = self.diagnostics()
            st = DiagnosticStatus()
            st.name = f"{self.get_fully_qualified_name()}: mapper"
            st.hardware_id = f"{s['backend']} ({s['device']})"
            level, st.message = health(self._diag_prev, s, self.live.error)
            self._diag_prev = s
            st.level = {"OK": DiagnosticStatus.OK, "WARN": DiagnosticStatus.WARN,
                        "ERROR": DiagnosticStatus.ERROR}[level]
            if s["dropped"].get("middleware_lost") and 4 * self.spec.image_shape[0] * \
                    self.spec.image_shape[1] > FASTDDS_DEFAULT_SEGMENT_BYTES:
                st.message += f"; images lost in the middleware: {FASTDDS_HINT}"

            kv = [("pings_received", s["received"]), ("pings_integrated", s["integrated"]),
                  ("ping_rate_hz", f"{s['ping_rate_hz']:.2f}"),
                  ("latency_p50_ms", f"{s['latency_p50_ms']:.2f}"),
                  ("latency_p99_ms", f"{s['latency_p99_ms']:.2f}"), ("queue", s["queue"]),
                  ("poses_buffered", s["poses"]), ("backend", s["backend"]), ("map_bytes", s["map_bytes"])]
            if self.surf is not None:
                kv += [("surface_pings", s["surface_pings"]), ("surface_waiting", s["surface_waiting"]),
                       ("surface_age_s", f"{s['surface_age_s']:.3f}"),
                       ("surface_latency_max_s", f"{s['surface_latency_max_s']:.3f}"),
                       ("surface_update_s", f"{s['surface_update_s']:.3f}"),
                       ("surface_updates", s["surface_updates"]), ("surface_voxels", s["surface_voxels"])]
            if self.distance is not None:
                kv += [(k, s[k]) for k in ("distance_updates", "distance_changes", "distance_kind")]
                kv += [("distance_update_s", f"{s['distance_update_s']:.4f}"),
                       ("distance_seconds", f"{s['distance_seconds']:.3f}")]
            for kind in ("rejected", "skipped", "dropped"):
                kv += [(f"{kind}.{k}", v) for k, v in sorted(s[kind].items())]
            st.values = [KeyValue(key=k, value=str(v)) for k, v in kv]
            arr = DiagnosticArray()
            arr.header.stamp = self.get_clock().now().to_msg()
            arr.status = [st]
            self.pub_diag.publish(arr)

        def shutdown(self, save: bool | None = None) -> None:
            """Drain the queue, publish the last map, save when asked."""
            self.live.stop(drain=True)
            if self.surf is not None:
                self.surf.stop()  # one last update: the layer of every ping mapped
            if save if save is not None else bool(self.p["save_on_exit"]):
                path = self._save()
                print(f"gpumap ros: map saved to {path}", file=sys.stderr)  # ROS logging may be down

    return GpumapNode()


#: Fast DDS's default shared-memory segment (512 KiB): a larger message through it is often lost.
