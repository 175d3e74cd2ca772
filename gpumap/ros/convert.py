"""ROS 2 messages to and from gpumap's arrays (message packages are imported lazily).

Every ``*_from_msg`` function checks what came and raises :class:`BadMessage` (a
``ValueError`` carrying the counting ``reason``) saying what was expected and what came.
"""

from __future__ import annotations

import array
import math

import numpy as np

from gpumap.limits import MAX_POSITION_M
from gpumap.spec import GridSpec

__all__ = [
    "ENCODINGS",
    "BadMessage",
    "MarkerBlocks",
    "cloud_confirmed",
    "cloud_msg",
    "cloud_points",
    "image_from_msg",
    "image_msg",
    "pose_array_msg",
    "occupancy_grid_msg",
    "occupied_cloud",
    "pose_from_msg",
    "pose_msg_fields",
    "project_obstacles",
    "stamp_ns",
    "stamp_of",
    "transform_from_pose",
]

#: Image encodings the node takes: name -> (dtype, bytes per pixel).
ENCODINGS = {"mono8": (np.uint8, 1), "8UC1": (np.uint8, 1), "mono16": (np.uint16, 2),
             "16UC1": (np.uint16, 2), "32FC1": (np.float32, 4)}


class BadMessage(ValueError):
    """A message refused at the boundary; ``reason`` is the counter it goes to."""

    def __init__(self, reason: str, text: str) -> None:
        super().__init__(text)
        self.reason = reason


def stamp_ns(stamp) -> int:
    """``builtin_interfaces/Time`` -> integer nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def stamp_of(t_ns: int):
    """Integer nanoseconds -> ``builtin_interfaces/Time``."""
    from builtin_interfaces.msg import Time

    sec, nsec = divmod(int(t_ns), 1_000_000_000)
    return Time(sec=sec, nanosec=nsec)


# ---------------------------------------------------------------------------- images
def image_from_msg(msg, shape: tuple[int, int]) -> np.ndarray:
    """A ``sensor_msgs/Image`` as a ``shape`` array: uint8 for 8-bit, float32 in [0, 1] otherwise.

    ``mono16`` is scaled by 1/65535; ``32FC1`` must already be in [0, 1] and finite. Rows
    may be padded (``step``), either byte order.

    Raises
    ------
    BadMessage
        ``image_encoding`` (not mono8, mono16 or 32FC1), ``image_size`` (height, width, step
        or data length off) or ``image_values`` (NaN, inf, or outside [0, 1]).
    """
    enc = msg.encoding
    if enc not in ENCODINGS:
        raise BadMessage("image_encoding",
                         f"Expected an image encoding of mono8, mono16 or 32FC1, but got {enc!r}")
    dt, nb = ENCODINGS[enc]
    h, w = int(msg.height), int(msg.width)
    if (h, w) != tuple(shape):
        raise BadMessage("image_size", f"Expected an image of {shape[0]} x {shape[1]} (height x width), but "
                         f"got {h} x {w}")
    step = int(msg.step)
    n = len(msg.data)
    if step < w * nb or n != step * h:
        raise BadMessage("image_size", f"Expected step >= {w * nb} and {h} * step bytes of data, but got "
                         f"step {step} and {n} bytes")
    raw = np.frombuffer(msg.data, dtype=np.uint8).reshape(h, step)[:, : w * nb]
    a = np.ascontiguousarray(raw).view(np.dtype(dt).newbyteorder(">" if msg.is_bigendian else "<"))
    a = a.reshape(h, w)
    if dt is np.uint8:
        return a
    if dt is np.uint16:
        return a.astype(np.float32) / np.float32(65535.0)
    a = a.astype(np.float32)
    if not np.all(np.isfinite(a)) or a.min() < 0.0 or a.max() > 1.0:
        bad = int(np.count_nonzero(~np.isfinite(a) | (a < 0) | (a > 1)))
        raise BadMessage("image_values", f"Expected 32FC1 intensities in [0, 1], but {bad} pixels are NaN, "
                         "inf or outside")
    return a


def image_msg(image: np.ndarray, t_ns: int, frame_id: str, encoding: str = "auto"):
    """A ``sensor_msgs/Image`` of a polar image (uint8 -> mono8, float -> 32FC1 unless told).

    ``encoding`` ``"mono8"`` quantises a float image as ``rint(255 x)``, ``"mono16"`` as
    ``rint(65535 x)``.
    """
    from sensor_msgs.msg import Image

    img = np.asarray(image)
    if encoding == "auto":
        encoding = "mono8" if img.dtype == np.uint8 else "32FC1"
    if encoding not in ("mono8", "mono16", "32FC1"):
        raise ValueError(f"Expected encoding 'auto', 'mono8', 'mono16' or '32FC1', but got {encoding!r}")
    if encoding == "mono8":
        a = img if img.dtype == np.uint8 else np.rint(np.clip(img, 0, 1) * 255.0).astype(np.uint8)
    elif encoding == "mono16":
        f = img.astype(np.float64) / (255.0 if img.dtype == np.uint8 else 1.0)
        a = np.rint(np.clip(f, 0, 1) * 65535.0).astype("<u2")
    else:
        a = (img.astype(np.float32) / np.float32(255.0) if img.dtype == np.uint8 else img).astype("<f4")
    a = np.ascontiguousarray(a)
    m = Image()
    m.header.stamp = stamp_of(t_ns)
    m.header.frame_id = frame_id
    m.height, m.width = int(a.shape[0]), int(a.shape[1])
    m.encoding = encoding
    m.is_bigendian = 0
    m.step = int(a.shape[1] * a.itemsize)
    m.data = array.array("B", a.tobytes())
    return m


# ---------------------------------------------------------------------------- poses
def transform_from_pose(position, orientation, quat_tol: float = 1e-3) -> np.ndarray:
    """``geometry_msgs/Point`` + ``Quaternion`` -> (4, 4) float64 ``T_W_S``.

    The quaternion is normalised after the check (so the rotation is orthonormal).

    Raises
    ------
    BadMessage
        ``pose_nonfinite`` (NaN or inf anywhere), ``pose_out_of_range`` (a coordinate beyond
        ``gpumap.limits.MAX_POSITION_M``) or ``pose_not_unit_quaternion`` (norm off 1 by more
        than ``quat_tol``: not a rotation).
    """
    p = np.array([position.x, position.y, position.z], dtype=np.float64)
    q = np.array([orientation.x, orientation.y, orientation.z, orientation.w], dtype=np.float64)
    if not (np.all(np.isfinite(p)) and np.all(np.isfinite(q))):
        raise BadMessage("pose_nonfinite", f"Expected a finite pose, but got position {p.tolist()} and "
                         f"quaternion (x, y, z, w) {q.tolist()}")
    if np.abs(p).max() > MAX_POSITION_M:
        raise BadMessage("pose_out_of_range", f"Expected a position within {MAX_POSITION_M:g} m of the "
                         f"origin (gpumap.limits.MAX_POSITION_M), but got {p.tolist()}")
    n = float(np.linalg.norm(q))
    if abs(n - 1.0) > quat_tol:
        raise BadMessage("pose_not_unit_quaternion", f"Expected a unit quaternion (a rotation), but its norm "
                         f"is {n:.6g}")
    x, y, z, w = q / n
    R = np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = p
    return T


def pose_from_msg(msg, world_frame: str) -> tuple[int, np.ndarray]:
    """``(stamp_ns, T_W_S)`` of a ``geometry_msgs/PoseStamped`` or ``nav_msgs/Odometry``.

    Raises
    ------
    BadMessage
        ``pose_frame`` (``header.frame_id`` is not ``world_frame``), or those of
        :func:`transform_from_pose`.
    """
    if msg.header.frame_id != world_frame:
        raise BadMessage("pose_frame", f"Expected a pose in frame {world_frame!r}, but got frame "
                         f"{msg.header.frame_id!r}")
    pose = msg.pose.pose if hasattr(msg, "child_frame_id") else msg.pose
    return stamp_ns(msg.header.stamp), transform_from_pose(pose.position, pose.orientation)


def pose_msg_fields(T_W_S: np.ndarray) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """``((x, y, z), (qx, qy, qz, qw))`` of a rigid transform (Shepperd's method, ``qw >= 0``)."""
    T = np.asarray(T_W_S, dtype=np.float64)
    R = T[:3, :3]
    tr = R[0, 0] + R[1, 1] + R[2, 2]
    if tr > 0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = (
            (R[2, 1] - R[1, 2]) / s,
            (R[0, 2] - R[2, 0]) / s,
            (R[1, 0] - R[0, 1]) / s,
            0.25 * s,
        )
    else:
        i = int(np.argmax([R[0, 0], R[1, 1], R[2, 2]]))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(max(1.0 + R[i, i] - R[j, j] - R[k, k], 0.0))
        v = [0.0, 0.0, 0.0]
        v[i] = 0.25 * s
        v[j] = (R[j, i] + R[i, j]) / s
        v[k] = (R[k, i] + R[i, k]) / s
        w = (R[k, j] - R[j, k]) / s
        q = (v[0], v[1], v[2], w)
        if w < 0:
            q = tuple(-c for c in q)
    n = math.sqrt(sum(c * c for c in q))
    q = tuple(float(c / n) for c in q)
    return (float(T[0, 3]), float(T[1, 3]), float(T[2, 3])), q  # type: ignore[return-value]

def pose_array_msg(poses_T_W_S, t_ns: int, world_frame: str):
    """``geometry_msgs/PoseArray`` of the ``(4, 4)`` transforms ``poses_T_W_S`` (in order), stamped
    ``t_ns`` in ``world_frame``."""
    from geometry_msgs.msg import Pose, PoseArray

    m = PoseArray()
    m.header.stamp = stamp_of(t_ns)
    m.header.frame_id = world_frame
    for T in poses_T_W_S:
        (x, y, z), (qx, qy, qz, qw) = pose_msg_fields(T)
        p = Pose()
        p.position.x, p.position.y, p.position.z = x, y, z
        p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w = qx, qy, qz, qw
        m.poses.append(p)
    return m


# ---------------------------------------------------------------------------- map outputs
_CLOUD_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("value", "<f4")])
#: With the confidence layer: a uint8 ``confirmed`` after value, padded to 20 bytes (4-byte aligned).
_CLOUD_CONF_DTYPE = np.dtype({"names": ["x", "y", "z", "value", "confirmed"],
                              "formats": ["<f4", "<f4", "<f4", "<f4", "u1"],
                              "offsets": [0, 4, 8, 12, 16], "itemsize": 20})


def occupied_cloud(values: np.ndarray, grid: GridSpec, threshold: float,
                   confidence: np.ndarray | None = None
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """The cloud's content: every voxel with value ``>= threshold``, in C order.

    Parameters
    ----------
    values : (nx, ny, nz) float32
        Map values (NaN or +inf unknown), as ``MinMaxMapper.values()`` gives them.
    confidence : (nx, ny, nz) uint8, optional
        ``MinMaxMapper.layer("confidence").states()`` of the same map (0 unknown, 1 free, 2 occupied
        unconfirmed, 3 occupied confirmed); its occupied set must be the one of ``values``.

    Returns
    -------
    centres_m (N, 3) float64, values (N,) float32, confirmed (N,) uint8 (1 confirmed, 0
    unconfirmed) or None without ``confidence``.
    """
    occ = np.isfinite(values) & (values >= np.float32(threshold))
    idx = np.argwhere(occ)
    if confidence is None:
        return grid.centers(idx), values[occ], None
    conf = np.asarray(confidence)
    if conf.shape != values.shape:
        raise ValueError(f"Expected a confidence layer of shape {values.shape}, but got {conf.shape}")
    c = conf[occ]
    if c.size and c.min() < 2:
        raise ValueError(f"Expected the confidence layer to call every occupied voxel 2 or 3, but "
                         f"{int((c < 2).sum())} of {c.size} are {sorted(set(c[c < 2].tolist()))}")
    n_occ_conf = int(np.count_nonzero(conf >= 2))
    if n_occ_conf != c.size:
        raise ValueError(f"Expected the confidence layer's occupied voxels to be the {c.size} of the "
                         f"values, but it has {n_occ_conf}")
    return grid.centers(idx), values[occ], (c == 3).astype(np.uint8)


def cloud_msg(points_m: np.ndarray, values: np.ndarray, t_ns: int, frame_id: str,
              confirmed: np.ndarray | None = None):
    """``sensor_msgs/PointCloud2`` with float32 fields x, y, z (metres) and value, unordered;
    with ``confirmed`` also a uint8 field ``confirmed`` (20 bytes a point).

    Parameters
    ----------
    points_m : (N, 3) float
        Voxel centres in ``frame_id``.
    values : (N,) float
        Their min-max values.
    confirmed : (N,) bool or uint8, optional
        1 where the confidence layer calls the voxel confirmed, 0 unconfirmed.
    """
    from sensor_msgs.msg import PointCloud2, PointField

    n = int(points_m.shape[0])
    dt = _CLOUD_DTYPE if confirmed is None else _CLOUD_CONF_DTYPE
    rec = np.zeros(n, dtype=dt)  # zeros: the padding bytes go out as 0, not as leftovers
    for i, name in enumerate("xyz"):
        rec[name] = points_m[:, i]
    rec["value"] = values
    fields = [PointField(name=nm, offset=4 * i, datatype=PointField.FLOAT32, count=1)
              for i, nm in enumerate(("x", "y", "z", "value"))]
    if confirmed is not None:
        c = np.asarray(confirmed)
        if c.shape != (n,):
            raise ValueError(f"Expected confirmed of shape ({n},), but got {c.shape}")
        rec["confirmed"] = c != 0
        fields.append(PointField(name="confirmed", offset=16, datatype=PointField.UINT8, count=1))
    m = PointCloud2()
    m.header.stamp = stamp_of(t_ns)
    m.header.frame_id = frame_id
    m.height, m.width = 1, n
    m.fields = fields
    m.is_bigendian = False
    m.point_step = dt.itemsize
    m.row_step = dt.itemsize * n
    m.is_dense = True
    m.data = array.array("B", rec.tobytes())
    return m


def _cloud_rec(msg) -> np.ndarray:
    names = [f.name for f in msg.fields]
    for dt in (_CLOUD_DTYPE, _CLOUD_CONF_DTYPE):
        if names == list(dt.names) and msg.point_step == dt.itemsize:
            return np.frombuffer(msg.data, dtype=dt)
    raise ValueError(f"Expected fields x, y, z, value of 16 bytes per point (or x, y, z, value, confirmed "
                     f"of 20), but got {names} of {msg.point_step}")


def cloud_points(msg) -> np.ndarray:
    """(N, 4) float32 (x, y, z, value) of a cloud written by :func:`cloud_msg`."""
    rec = _cloud_rec(msg)
    return np.stack([rec["x"], rec["y"], rec["z"], rec["value"]], axis=1)


def cloud_confirmed(msg) -> np.ndarray | None:
    """(N,) uint8 ``confirmed`` field of a cloud written by :func:`cloud_msg` (None without it)."""
    rec = _cloud_rec(msg)
    return np.array(rec["confirmed"]) if "confirmed" in rec.dtype.names else None


def project_obstacles(values: np.ndarray, grid: GridSpec, threshold: float,
                      band_z_m: tuple[float, float] | None = None) -> np.ndarray:
    """(ny, nx) int8 obstacle map over a height band, as ``nav_msgs/OccupancyGrid`` stores it.

    A cell is 100 when a voxel of its column with centre height in ``band_z_m`` (inclusive;
    None: the whole grid) has value >= ``threshold``, 0 when such a voxel is observed and
    none is occupied, -1 when none is observed. Row ``j`` is ``y``, column ``i`` is ``x``.
    """
    nz = values.shape[2]
    zc = grid.min_corner_m[2] + (np.arange(nz) + 0.5) * grid.voxel_size_m
    sel = np.ones(nz, bool) if band_z_m is None else (zc >= band_z_m[0]) & (zc <= band_z_m[1])
    v = values[:, :, sel]
    obs = np.isfinite(v)
    occ = obs & (v >= np.float32(threshold))
    out = np.full(values.shape[:2], -1, dtype=np.int8)
    out[obs.any(axis=2)] = 0
    out[occ.any(axis=2)] = 100
    return np.ascontiguousarray(out.T)


def occupancy_grid_msg(cells: np.ndarray, grid: GridSpec, band_z_m: tuple[float, float] | None,
                       t_ns: int, frame_id: str):
    """``nav_msgs/OccupancyGrid`` of :func:`project_obstacles`'s cells (origin at the grid's
    min corner, at the band's lower height)."""
    from nav_msgs.msg import OccupancyGrid

    m = OccupancyGrid()
    m.header.stamp = stamp_of(t_ns)
    m.header.frame_id = frame_id
    m.info.map_load_time = m.header.stamp
    m.info.resolution = float(grid.voxel_size_m)
    m.info.height, m.info.width = int(cells.shape[0]), int(cells.shape[1])
    m.info.origin.position.x = float(grid.min_corner_m[0])
    m.info.origin.position.y = float(grid.min_corner_m[1])
    m.info.origin.position.z = float(grid.min_corner_m[2] if band_z_m is None else band_z_m[0])
    m.info.origin.orientation.w = 1.0
    m.data = array.array("b", cells.astype(np.int8).tobytes())
    return m


class MarkerBlocks:
    """RViz cube lists of the occupied voxels, one marker per block of ``block``^3 voxels.

    :meth:`update` returns only the blocks whose occupied set changed since the last call
    (an emptied block comes back with no points: delete its marker), as the live view
    re-sends only changed blocks. Given the confidence layer (``confirmed``), a block whose
    voxels' confirmed flags changed is re-sent too, and :meth:`msg` draws its unconfirmed
    voxels pale (mixed with :data:`gpumap.viewer.live.PALE_MIX` white, as the live view does).
    """

    def __init__(self, grid: GridSpec, threshold: float, block: int = 16) -> None:
        self.grid = grid
        self.threshold = np.float32(threshold)
        self.block = int(block)
        nx, ny, nz = grid.shape
        self._nb = tuple(-(-n // self.block) for n in (nx, ny, nz))
        i, j, k = np.meshgrid(np.arange(nx) // self.block, np.arange(ny) // self.block,
                              np.arange(nz) // self.block, indexing="ij")
        self._block_of = np.ravel_multi_index((i, j, k), self._nb).ravel().astype(np.int32)
        self._prev = np.zeros(grid.n_voxels, dtype=bool)
        self._prev_conf = np.zeros(grid.n_voxels, dtype=bool)
        #: per block of the last :meth:`update`, the confirmed flag of each returned centre
        #: (absent without a confidence layer)
        self.confirmed: dict[int, np.ndarray] = {}

    def reset(self) -> None:
        self._prev[:] = False
        self._prev_conf[:] = False
        self.confirmed = {}

    def update(self, values: np.ndarray, full: bool = False,
               confirmed: np.ndarray | None = None) -> list[tuple[int, np.ndarray]]:
        """``[(block_id, centres (M, 3) float64)]`` for every changed block (all with ``full``).

        ``confirmed``: ``MinMaxMapper.layer("confidence").states() == 3``, any shape of ``values``' size, or
        None
        (no layer); with it, :attr:`confirmed` holds each returned block's flags."""
        v = values.ravel()
        occ = np.isfinite(v) & (v >= self.threshold)
        conf = np.zeros_like(occ) if confirmed is None else np.asarray(confirmed, bool).ravel()
        if conf.shape != occ.shape:
            raise ValueError(f"Expected confirmed flags for {occ.size} voxels, but got {conf.size}")
        conf = conf & occ
        if full:
            blocks = np.unique(np.concatenate([self._block_of[occ], self._block_of[self._prev]]))
        else:
            blocks = np.unique(self._block_of[(occ != self._prev) | (conf != self._prev_conf)])
        self._prev, self._prev_conf = occ, conf
        self.confirmed = {}
        if blocks.size == 0:
            return []
        idx = np.flatnonzero(occ)
        ob = self._block_of[idx]
        order = np.argsort(ob, kind="stable")
        idx, ob = idx[order], ob[order]
        lo = np.searchsorted(ob, blocks, "left")
        hi = np.searchsorted(ob, blocks, "right")
        out = []
        for b, a, c in zip(blocks.tolist(), lo.tolist(), hi.tolist(), strict=True):
            ijk = np.stack(np.unravel_index(idx[a:c], self.grid.shape), axis=1)
            out.append((b, self.grid.centers(ijk)))
            if confirmed is not None:
                self.confirmed[b] = conf[idx[a:c]]
        return out

    def msg(self, changed: list[tuple[int, np.ndarray]], t_ns: int, frame_id: str, ns: str = "gpumap"):
        """A ``visualization_msgs/MarkerArray``: a CUBE_LIST per changed block (DELETE if empty),
        coloured by height over the grid's z range; with the confidence layer given to
        :meth:`update`, unconfirmed voxels pale."""
        import matplotlib
        from geometry_msgs.msg import Point
        from std_msgs.msg import ColorRGBA
        from visualization_msgs.msg import Marker, MarkerArray

        from gpumap.viewer.live import PALE_MIX

        cmap = matplotlib.colormaps["viridis"]
        z0, z1 = self.grid.min_corner_m[2], self.grid.max_corner_m[2]
        arr = MarkerArray()
        stamp = stamp_of(t_ns)
        for b, pts in changed:
            mk = Marker()
            mk.header.stamp = stamp
            mk.header.frame_id = frame_id
            mk.ns = ns
            mk.id = int(b)
            if pts.shape[0] == 0:
                mk.action = Marker.DELETE
                arr.markers.append(mk)
                continue
            mk.type = Marker.CUBE_LIST
            mk.action = Marker.ADD
            mk.pose.orientation.w = 1.0
            s = float(self.grid.voxel_size_m)
            mk.scale.x = mk.scale.y = mk.scale.z = s
            mk.color.a = 1.0
            rgba = cmap(np.clip((pts[:, 2] - z0) / max(z1 - z0, 1e-9), 0, 1))
            flags = self.confirmed.get(b)
            if flags is not None:
                rgba[~flags, :3] = (1 - PALE_MIX) * rgba[~flags, :3] + PALE_MIX
            mk.points = [Point(x=float(x), y=float(y), z=float(z)) for x, y, z in pts]
            mk.colors = [ColorRGBA(r=float(c[0]), g=float(c[1]), b=float(c[2]), a=1.0) for c in rgba]
            arr.markers.append(mk)
        return arr
