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
For bags that do not store message definitions (ROS 2 sqlite3), the definitions below
are registered; ``OculusFire`` is our reading of the driver's fire message and only needs
to match the bag when the bag carries no definitions.
"""

from __future__ import annotations

import io
import math
import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from gpumap.io.frame import FormatError, Recording, SonarFrame
from gpumap.spec import SonarSpec

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
    d = np.array([[v.x, v.y, v.z] for v in msg.beam_directions], dtype=np.float64)
    n_beams = int(msg.image.beam_count)
    if d.shape[0] != n_beams:
        raise FormatError(f"expected {n_beams} beam_directions, but got {d.shape[0]}")
    az = np.arctan2(-d[:, 1], d[:, 2])
    r = np.asarray(msg.ranges, dtype=np.float64)
    if r.size < 1:
        raise FormatError("expected at least one range, but 'ranges' is empty")
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
    spec = SonarSpec(float(r[0] - dr / 2), float(r[0] - dr / 2 + r.size * dr), int(r.size),
                     az[order], vfov)
    return np.ascontiguousarray(img[:, order], dtype=np.float32), spec


def _decode_oculus_ping(msg, vfov: float) -> tuple[np.ndarray, SonarSpec]:
    from PIL import Image

    nr, nb = int(msg.num_ranges), int(msg.num_beams)
    b = np.asarray(msg.bearings, dtype=np.int64)
    if b.size != nb:
        raise FormatError(f"expected {nb} bearings, but got {b.size}")
    with Image.open(io.BytesIO(bytes(np.asarray(msg.ping.data, dtype=np.uint8)))) as im:
        a = np.asarray(im)
    if a.ndim == 3:
        a = a[..., 0]
    if a.shape != (nr, nb):
        raise FormatError(f"expected a {nr} x {nb} ping image, but got {a.shape}")
    scale = 65535.0 if a.dtype == np.uint16 else 255.0
    az = -np.deg2rad(b[::-1] / 100.0)
    res = float(msg.range_resolution)
    spec = SonarSpec(0.0, nr * res, nr, az, vfov)
    return (a[:, ::-1].astype(np.float32) / np.float32(scale)), spec


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
    ts = make_typestore(ros1=p.suffix == ".bag")
    vfov = math.radians(vfov_deg)
    with AnyReader([p], default_typestore=ts) as rd:
        conns = rd.connections
        img_conns = [c for c in conns if (c.topic == image_topic if image_topic
                                          else c.msgtype in (PSI, OCULUS_PING))]
        if len({c.topic for c in img_conns}) != 1:
            raise FormatError(
                f"expected exactly one sonar image topic ({PSI} or {OCULUS_PING}), but found "
                f"{sorted({c.topic for c in img_conns}) or 'none'} among "
                f"{sorted({(c.topic, c.msgtype) for c in conns})}: pass image_topic",
                path=str(p))
        img_topic = img_conns[0].topic
        pose_conns = [c for c in conns if (c.topic == pose_topic if pose_topic
                                           else c.msgtype == POSE)]
        tf_conns = [c for c in conns if c.msgtype == TF]
        times: list[float] = []
        poses: list[np.ndarray] = []
        if len({c.topic for c in pose_conns}) == 1 and (pose_topic or world_frame is None):
            for c, t, raw in rd.messages(connections=pose_conns):
                m = rd.deserialize(raw, c.msgtype)
                o, q = m.pose.position, m.pose.orientation
                times.append(_stamp(m, t))
                poses.append(_T((q.x, q.y, q.z, q.w), (o.x, o.y, o.z)))
        elif world_frame is not None and tf_conns:
            if sonar_frame is None:
                for c, _t, raw in rd.messages(connections=img_conns):
                    sonar_frame = rd.deserialize(raw, c.msgtype).header.frame_id
                    break
            for c, t, raw in rd.messages(connections=tf_conns):
                for tr in rd.deserialize(raw, c.msgtype).transforms:
                    if tr.header.frame_id == world_frame and tr.child_frame_id == sonar_frame:
                        r, q = tr.transform.translation, tr.transform.rotation
                        times.append(_stamp(tr, t))
                        poses.append(_T((q.x, q.y, q.z, q.w), (r.x, r.y, r.z)))
            if not poses:
                raise FormatError(f"expected TF transforms {world_frame} -> {sonar_frame}, but "
                                  "the bag has none (only direct transforms are used)", path=str(p))
        n_images = sum(c.msgcount for c in img_conns)
    if T_B_S is not None:
        E = np.asarray(T_B_S, dtype=np.float64)
        poses = [T @ E for T in poses]
    track = _PoseTrack(times, poses, max_pose_gap_s) if poses else None

    def frames() -> Iterator[SonarFrame]:
        with AnyReader([p], default_typestore=ts) as rd2:
            cs = [c for c in rd2.connections if c.topic == img_topic]
            for k, (c, t, raw) in enumerate(rd2.messages(connections=cs)):
                m = rd2.deserialize(raw, c.msgtype)
                try:
                    img, spec = (_decode_psi(m, vfov) if c.msgtype == PSI
                                 else _decode_oculus_ping(m, vfov))
                except (FormatError, ValueError) as e:
                    raise FormatError(f"message {k} on {img_topic}: {e}", path=str(p)) from None
                stamp = _stamp(m, t)
                yield SonarFrame(image=img, spec=spec, timestamp_s=stamp,
                                 T_W_S=track(stamp) if track else None,
                                 meta={"format": c.msgtype, "topic": img_topic, "index": k})

    return Recording(str(p), "rosbag", frames, has_poses=track is not None,
                     count=lambda: n_images)
