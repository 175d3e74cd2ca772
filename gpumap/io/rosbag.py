"""ROS 1 / ROS 2 bags through ``rosbags`` (no ROS install): sonar images plus poses.

Image topics (found by message type unless ``image_topic`` is given):

- ``marine_acoustic_msgs/ProjectedSonarImage``: ``beam_directions`` are unit vectors in the
  message's sonar frame (z forward, x up, so y points to starboard), hence
  ``azimuth = atan2(-y, z)``; ``ranges`` are bin *centres* and must be evenly spaced;
  ``image.data`` is sample-major (``index = sample * beam_count + beam``) with ``dtype``
  one of the ``SonarImageData.DTYPE_*`` codes (integers scaled by their maximum, floats
  taken as they are and clipped to [0, 1]).
- ``sonar_oculus/OculusPing``: ``ping`` is a ``sensor_msgs/CompressedImage`` (PNG/JPEG) of
  ``num_ranges x num_beams``, ``bearings`` in 1/100 degree positive to starboard (as in
  the Oculus messages: azimuth = -bearing, columns reversed), ``range_resolution`` in
  metres (row ``i`` covers ``[i, i + 1) * range_resolution``).

Poses: a ``geometry_msgs/PoseStamped`` topic (the pose of the sonar, or of a body with
``T_B_S`` given) or TF (``tf2_msgs/TFMessage`` on ``/tf`` and ``/tf_static``) holding the
direct transform ``world_frame -> sonar_frame`` (no chaining). Each image gets the pose
interpolated at its header stamp (linear in position, slerp in rotation); images
bracketed by poses more than ``max_pose_gap_s`` apart, or that far outside the pose time
span, get ``T_W_S = None`` (replay skips and counts them).

The vertical aperture is not in either message: ``vfov_deg`` (default 20) is a parameter.

Errors: whatever the bag library raises on a damaged bag (its own ``ReaderError``,
``AnyReaderError`` and ``SerdeError``, and the ``struct``/``KeyError``/... that a corrupt
record can provoke) comes out as :class:`~gpumap.errors.FormatError` naming the bag and
what was being read; a damaged message names its index on the topic. Image sizes are
checked against ``gpumap.limits.MAX_IMAGE_PIXELS`` before a picture is decoded; poses must
be finite with a non-zero quaternion.
For bags that do not store message definitions (ROS 2 sqlite3), the definitions below
are registered; ``OculusFire`` is our reading of the driver's fire message and only needs
to match the bag when the bag carries no definitions.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TypeVar

import numpy as np

from gpumap import limits
from gpumap.io.fan import read_grey_png
from gpumap.io.frame import FormatError, LimitError, Recording, SonarFrame
from gpumap.limits import check_size, declared_product
from gpumap.spec import SonarSpec

_R = TypeVar("_R")


def _bag_call(fn: Callable[[], _R], what: str, path: str) -> _R:
    """Run one call into the bag library; its exceptions become gpumap's ``FormatError``."""
    try:
        return fn()
    except FormatError:
        raise
    except MemoryError:
        raise LimitError(f"expected {what} to fit in memory, but the bag declares a record too large "
                         "to allocate", path=path) from None
    except Exception as e:  # the library's own errors and whatever a corrupt record provokes
        raise FormatError(f"expected {what}, but the bag library failed: {type(e).__name__}: {e}",
                          path=path) from None

__all__ = ["MSG_DEFINITIONS", "make_typestore", "open_rosbag"]

MSG_DEFINITIONS: dict[str, str] = {
    "marine_acoustic_msgs/msg/PingInfo": (
        "float32 frequency\nfloat32 sound_speed\nfloat32[] tx_beamwidths\nfloat32[] rx_beamwidths\n"
    ),
    "marine_acoustic_msgs/msg/SonarImageData": (
        "bool is_bigendian\nuint32 DTYPE_UINT8=0\nuint32 DTYPE_INT8=1\nuint32 DTYPE_UINT16=2\n"
        "uint32 DTYPE_INT16=3\nuint32 DTYPE_UINT32=4\nuint32 DTYPE_INT32=5\nuint32 DTYPE_UINT64=6\n"
        "uint32 DTYPE_INT64=7\nuint32 DTYPE_FLOAT32=8\nuint32 DTYPE_FLOAT64=9\nuint32 dtype\n"
        "uint32 beam_count\nuint8[] data\n"
    ),
    "marine_acoustic_msgs/msg/ProjectedSonarImage": (
        "std_msgs/Header header\nmarine_acoustic_msgs/PingInfo ping_info\n"
        "geometry_msgs/Vector3[] beam_directions\nfloat32[] ranges\n"
        "marine_acoustic_msgs/SonarImageData image\n"
    ),
    "sonar_oculus/msg/OculusFire": (
        "std_msgs/Header header\nuint8 mode\nuint8 gamma\nuint8 flags\nfloat64 range\n"
        "float64 gain\nfloat64 speed_of_sound\nfloat64 salinity\n"
    ),
    "sonar_oculus/msg/OculusPing": (
        "std_msgs/Header header\nsonar_oculus/OculusFire fire_msg\nuint32 ping_id\n"
        "uint16 part_number\nuint32 start_time\nint16[] bearings\nfloat64 range_resolution\n"
        "uint32 num_ranges\nuint32 num_beams\nsensor_msgs/CompressedImage ping\n"
    ),
}
PSI = "marine_acoustic_msgs/msg/ProjectedSonarImage"
OCULUS_PING = "sonar_oculus/msg/OculusPing"
POSE = "geometry_msgs/msg/PoseStamped"
TF = "tf2_msgs/msg/TFMessage"
_DTYPES = {0: "u1", 1: "i1", 2: "u2", 3: "i2", 4: "u4", 5: "i4", 6: "u8", 7: "i8", 8: "f4", 9: "f8"}


def make_typestore(ros1: bool = False):
    """A ``rosbags`` typestore (Noetic or Humble) with the sonar message types registered."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    types: dict = {}
    for name, text in MSG_DEFINITIONS.items():
        types.update(get_types_from_msg(text, name))
    if "tf2_msgs/msg/TFMessage" not in ts.types:  # the Noetic store lacks it
        types.update(get_types_from_msg("geometry_msgs/TransformStamped[] transforms\n",
                                        "tf2_msgs/msg/TFMessage"))
    ts.register(types)
    return ts


def _stamp(msg, fallback_ns: int) -> float:
    h = getattr(msg, "header", None)
    if h is not None:
        s = h.stamp
        t = s.sec + 1e-9 * s.nanosec
        if t > 0:
            return float(t)
    return fallback_ns * 1e-9


def _T(q: tuple[float, float, float, float], p: tuple[float, float, float]) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    qa, pa = np.asarray(q, dtype=np.float64), np.asarray(p, dtype=np.float64)
    if not (np.all(np.isfinite(qa)) and np.all(np.isfinite(pa))):
        raise FormatError(f"expected a finite pose, but got position {pa.tolist()}, quaternion "
                          f"{qa.tolist()}")
    if not np.linalg.norm(qa) > 1e-9:
        raise FormatError(f"expected a non-zero quaternion, but got {qa.tolist()}")
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(q).as_matrix()
    T[:3, 3] = p
    return T


class _PoseTrack:
    def __init__(self, times: list[float], poses: list[np.ndarray], max_gap_s: float):
        order = np.argsort(times, kind="stable")
        self.t = np.asarray(times, dtype=np.float64)[order]
        self.T = np.asarray(poses, dtype=np.float64)[order]
        self.gap = max_gap_s

    def __call__(self, t: float) -> np.ndarray | None:
        from scipy.spatial.transform import Rotation, Slerp

        if len(self.t) == 0 or t < self.t[0] - self.gap or t > self.t[-1] + self.gap:
            return None
        if len(self.t) == 1 or t <= self.t[0]:
            return self.T[0].copy()
        if t >= self.t[-1]:
            return self.T[-1].copy()
        k = int(np.searchsorted(self.t, t, side="right"))
        t0, t1 = self.t[k - 1], self.t[k]
        if t1 - t0 > self.gap:
            return None  # inside a hole in the pose stream
        a = 0.0 if t1 == t0 else (t - t0) / (t1 - t0)
        out = np.eye(4)
        out[:3, 3] = (1 - a) * self.T[k - 1, :3, 3] + a * self.T[k, :3, 3]
        rots = Rotation.from_matrix(self.T[[k - 1, k], :3, :3])
        out[:3, :3] = Slerp([0.0, 1.0], rots)([a]).as_matrix()[0]
        return out


def _decode_psi(msg, vfov: float) -> tuple[np.ndarray, SonarSpec]:
    d = np.array([[v.x, v.y, v.z] for v in msg.beam_directions], dtype=np.float64).reshape(-1, 3)
    n_beams = int(msg.image.beam_count)
    if d.shape[0] != n_beams:
        raise FormatError(f"expected {n_beams} beam_directions, but got {d.shape[0]}")
    if not np.all(np.isfinite(d)):
        raise FormatError("expected finite beam_directions, but got NaN or inf")
    az = np.arctan2(-d[:, 1], d[:, 2])
    r = np.asarray(msg.ranges, dtype=np.float64)
    if r.size < 1:
        raise FormatError("expected at least one range, but 'ranges' is empty")
    if not np.all(np.isfinite(r)):
        raise FormatError("expected finite 'ranges', but got NaN or inf")
    check_size(declared_product(r.size, n_beams), limits.MAX_IMAGE_PIXELS, "ranges x beam_count",
               unit="pixels")
    dr = float(np.median(np.diff(r))) if r.size > 1 else 0.0
    if r.size > 1 and (dr <= 0 or np.max(np.abs(np.diff(r) - dr)) > 1e-3 * dr + 1e-6):
        raise FormatError("expected evenly spaced ascending 'ranges', but they are not")
    code = int(msg.image.dtype)
    if code not in _DTYPES:
        raise FormatError(f"expected SonarImageData.dtype 0..9, but got {code}")
    dt = np.dtype(("<" if not msg.image.is_bigendian else ">") + _DTYPES[code])
    raw = np.asarray(msg.image.data, dtype=np.uint8)
    if raw.size != r.size * n_beams * dt.itemsize:
        raise FormatError(f"expected {r.size} x {n_beams} x {dt.itemsize} = "
                          f"{r.size * n_beams * dt.itemsize} image bytes, but got {raw.size}")
    a = raw.view(dt).reshape(r.size, n_beams)
    if dt.kind in "ui":
        img = np.clip(a.astype(np.float64) / np.iinfo(dt).max, 0.0, 1.0)
    else:
        img = np.clip(np.nan_to_num(a.astype(np.float64)), 0.0, 1.0)
    order = np.argsort(az, kind="stable")
    lo = float(r[0] - dr / 2)
    hi = lo + r.size * dr
    if -1e-3 * dr < lo < 0.0:  # bins that start at 0 m, seen through float32 bin centres
        lo = 0.0
    spec = limits.check_geometry(SonarSpec(lo, float(hi), int(r.size), az[order], vfov),
                                 "the image ('ranges')")
    return np.ascontiguousarray(img[:, order], dtype=np.float32), spec


def _decode_oculus_ping(msg, vfov: float) -> tuple[np.ndarray, SonarSpec]:
    nr, nb = int(msg.num_ranges), int(msg.num_beams)
    check_size(declared_product(nr, nb), limits.MAX_IMAGE_PIXELS, "num_ranges x num_beams",
               unit="pixels")
    b = np.asarray(msg.bearings, dtype=np.int64)
    if b.size != nb:
        raise FormatError(f"expected {nb} bearings, but got {b.size}")
    res = float(msg.range_resolution)
    if not (math.isfinite(res) and res > 0):
        raise FormatError(f"expected a finite range_resolution > 0 m, but got {res}")
    # size from the picture's header first: PNG (or JPEG) of num_ranges x num_beams
    a = read_grey_png(bytes(np.asarray(msg.ping.data, dtype=np.uint8)), expected_shape=(nr, nb),
                      formats=("PNG", "JPEG"), path="the ping picture")
    az = -np.deg2rad(b[::-1] / 100.0)
    spec = limits.check_geometry(SonarSpec(0.0, nr * res, nr, az, vfov),
                                 "the ping (range_resolution, num_ranges)")
    return np.ascontiguousarray(a[:, ::-1]), spec


def _bag_messages(rd, conns, path: str) -> Iterator[tuple]:
    """``rd.messages(connections=conns)`` with the library's errors as ``FormatError``."""
    it = _bag_call(lambda: iter(rd.messages(connections=conns)), "the bag's messages", path)
    while True:
        item = _bag_call(lambda: next(it, None), "the next message record", path)
        if item is None:
            return
        yield item


def open_rosbag(
    path: str | os.PathLike,
    *,
    image_topic: str | None = None,
    pose_topic: str | None = None,
    world_frame: str | None = None,
    sonar_frame: str | None = None,
    T_B_S: np.ndarray | None = None,
    vfov_deg: float = 20.0,
    max_pose_gap_s: float = 1.0,
) -> Recording:
    """Open a ROS 1 ``.bag`` or ROS 2 bag (directory / ``.mcap``) holding sonar images.

    Parameters
    ----------
    path : path-like
    image_topic : str, optional
        Default: the only ProjectedSonarImage or OculusPing topic.
    pose_topic : str, optional
        PoseStamped topic; default: the only one, else TF when ``world_frame`` is given.
    world_frame, sonar_frame : str, optional
        TF frames (``sonar_frame`` defaults to the images' ``header.frame_id``).
    T_B_S : (4, 4) float, optional
        Fixed sonar pose in the frame the pose topic tracks: ``T_W_S = T_W_B @ T_B_S``.
    vfov_deg : float
        Vertical aperture, degrees.
    max_pose_gap_s : float
        Largest gap between the two poses bracketing an image (and largest distance
        before the first or after the last pose) for which a pose is interpolated.
    """
    from rosbags.highlevel import AnyReader

    p = Path(path)
    ps = str(p)
    if not p.exists():
        raise FileNotFoundError(f"Expected a ROS bag at {p}, but nothing is there")
    ts = make_typestore(ros1=p.suffix == ".bag")
    vfov = math.radians(vfov_deg)
    rd = _bag_call(lambda: AnyReader([p], default_typestore=ts), "a ROS bag", ps)
    _bag_call(rd.open, "a readable ROS bag (header, index and connections)", ps)
    try:
        conns = rd.connections
        img_conns = [c for c in conns if (c.topic == image_topic if image_topic
                                          else c.msgtype in (PSI, OCULUS_PING))]
        if len({c.topic for c in img_conns}) != 1:
            raise FormatError(
                f"expected exactly one sonar image topic ({PSI} or {OCULUS_PING}), but found "
                f"{sorted({c.topic for c in img_conns}) or 'none'} among "
                f"{sorted({(c.topic, c.msgtype) for c in conns})}: pass image_topic",
                path=ps)
        img_topic = img_conns[0].topic
        pose_conns = [c for c in conns if (c.topic == pose_topic if pose_topic
                                           else c.msgtype == POSE)]
        tf_conns = [c for c in conns if c.msgtype == TF]
        times: list[float] = []
        poses: list[np.ndarray] = []
        if len({c.topic for c in pose_conns}) == 1 and (pose_topic or world_frame is None):
            for k, (c, t, raw) in enumerate(_bag_messages(rd, pose_conns, ps)):
                m = _bag_call(lambda c=c, raw=raw: rd.deserialize(raw, c.msgtype),
                              f"pose message {k} on {c.topic}", ps)
                try:
                    o, q = m.pose.position, m.pose.orientation
                    poses.append(_T((q.x, q.y, q.z, q.w), (o.x, o.y, o.z)))
                except (FormatError, AttributeError) as e:
                    raise FormatError(f"pose message {k} on {c.topic}: {e}", path=ps) from None
                times.append(_stamp(m, t))
        elif world_frame is not None and tf_conns:
            if sonar_frame is None:
                for c, _t, raw in _bag_messages(rd, img_conns, ps):
                    sonar_frame = _bag_call(lambda c=c, raw=raw: rd.deserialize(raw, c.msgtype),
                                            f"the first message on {c.topic}", ps).header.frame_id
                    break
            for k, (c, t, raw) in enumerate(_bag_messages(rd, tf_conns, ps)):
                msg = _bag_call(lambda c=c, raw=raw: rd.deserialize(raw, c.msgtype),
                                f"TF message {k} on {c.topic}", ps)
                for tr in msg.transforms:
                    if tr.header.frame_id == world_frame and tr.child_frame_id == sonar_frame:
                        r, q = tr.transform.translation, tr.transform.rotation
                        try:
                            poses.append(_T((q.x, q.y, q.z, q.w), (r.x, r.y, r.z)))
                        except FormatError as e:
                            raise FormatError(f"TF message {k} on {c.topic}: {e}", path=ps) from None
                        times.append(_stamp(tr, t))
            if not poses:
                raise FormatError(f"expected TF transforms {world_frame} -> {sonar_frame}, but "
                                  "the bag has none (only direct transforms are used)", path=ps)
        n_images = sum(c.msgcount for c in img_conns)
    finally:
        _bag_call(rd.close, "to close the bag", ps)
    if T_B_S is not None:
        E = np.asarray(T_B_S, dtype=np.float64)
        poses = [T @ E for T in poses]
    track = _PoseTrack(times, poses, max_pose_gap_s) if poses else None

    def frames() -> Iterator[SonarFrame]:
        rd2 = _bag_call(lambda: AnyReader([p], default_typestore=ts), "a ROS bag", ps)
        _bag_call(rd2.open, "a readable ROS bag", ps)
        try:
            cs = [c for c in rd2.connections if c.topic == img_topic]
            for k, (c, t, raw) in enumerate(_bag_messages(rd2, cs, ps)):
                m = _bag_call(lambda c=c, raw=raw: rd2.deserialize(raw, c.msgtype),
                              f"message {k} on {img_topic}", ps)
                try:
                    img, spec = (_decode_psi(m, vfov) if c.msgtype == PSI
                                 else _decode_oculus_ping(m, vfov))
                except LimitError as e:
                    raise LimitError(f"message {k} on {img_topic}: {e}", path=ps) from None
                except (FormatError, ValueError, AttributeError, TypeError) as e:
                    raise FormatError(f"message {k} on {img_topic}: {e}", path=ps) from None
                stamp = _stamp(m, t)
                yield SonarFrame(image=img, spec=spec, timestamp_s=stamp,
                                 T_W_S=track(stamp) if track else None,
                                 meta={"format": c.msgtype, "topic": img_topic, "index": k})
        finally:
            _bag_call(rd2.close, "to close the bag", ps)

    return Recording(str(p), "rosbag", frames, has_poses=track is not None,
                     count=lambda: n_images)
