"""Next best view: the gain of a candidate sonar pose, candidate poses, and a greedy planner.

**What the view gain counts.** For a candidate pose ``T_W_S`` (no image: the view has not been
taken), from the map alone:

``gain = settle + unknown_weight * unknown``

- ``settle``: the *unconfirmed* occupied voxels (:mod:`gpumap.layers.confidence`) the candidate
  observes (centre in its field of view, as :meth:`~gpumap.MinMaxMapper.integrate` decides it)
  along an elevation arc that could settle them: the arc's direction at the voxel is the
  derivative of the sonar-frame point with respect to elevation, ``(-x z, -y z, x^2 + y^2)`` in
  the sonar frame, taken to the world and rounded to the nearest of the 13 neighbour pairs
  (per axis the sign of the component where it exceeds half the direction's length). The
  voxel counts when (a) both its neighbours of that pair are known free (map value ``< thr``;
  outside the grid is not): a bright echo confirms it, a dark clear view carves it; or (b) it
  touches known-free space (one of its 26 neighbours is free) and no ping so far observed it
  along that pair's direction: the new arc crosses the old ones, whose stretch it can carve.
  Each ping's arc direction at every voxel it observes is recorded by the mapper's confidence
  pass (a 13-bit mask per voxel). Voxels no view can settle (neither) are not counted.
- ``unknown``: the never-observed voxels whose block of ``BLOCK`` x ``BLOCK`` x ``BLOCK`` voxels
  has its centre in the candidate's field of view (each block counts its unknown voxels):
  what the view would observe for the first time, at block resolution.

Both totals are integers summed exactly (int32 atomics on the devices), so every backend gives
the NumPy reference's gains bit for bit (the float32 arithmetic of the per-point tests is the
same, without FMA contraction). Occlusion is not modelled: a voxel behind a not-free voxel in
the candidate's beams counts as a voxel in the open.

:func:`candidate_poses` proposes poses around a pose within given offsets (a wrist's joint
limits); :func:`next_best_views` scores candidates around anchor poses against a map and ranks
them (what ``gpumap plan`` writes and the ROS node's ``~/plan_views`` publishes), and
:func:`plan_views` runs the greedy loop: score the candidates, take the best, have the caller take
and integrate its ping, repeat.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable

import numpy as np

from gpumap.errors import check_finite_scalar

__all__ = [
    "BLOCK",
    "ViewGainPoints",
    "candidate_poses",
    "gain_points",
    "next_best_views",
    "plan_views",
    "view_gain_reference",
]

_F = np.float32
#: Edge of the blocks that stand for unknown voxels in the gain, voxels.
BLOCK = 4
#: Points per device thread: GPUs want many threads, CPUs few.
GPU_TILE = 512
CPU_TILE = 1 << 30


#: The 13 neighbour pairs (+-step) of a voxel, in the order of their bits: the steps whose first
#: non-zero component is positive, in C order of (si + 1, sj + 1, sk + 1).
PAIR_STEPS = np.array([s for s in np.ndindex(3, 3, 3) if s > (1, 1, 1)]) - 1


def confidence_of(mapper):
    """The confidence layer attached to ``mapper`` (:class:`gpumap.layers.confidence.ConfidenceLayer`);
    ``ValueError`` when it has none (view gains are scored against it)."""
    try:
        return mapper.layer("confidence")
    except KeyError:
        raise ValueError("Expected a map with its confidence layer attached (mapper.attach("
                         "ConfidenceLayer()) or gpumap.layers.confidence.with_confidence(mapper)), but it "
                         "has none") from None



class ViewGainPoints:
    """What the view gain reads from the map (built once per map state by :func:`gain_points`).

    Attributes
    ----------
    points : (M, 3) float32 world centres, metres: first the unconfirmed occupied voxels that
        some view could settle, then the blocks holding unknown voxels.
    pairs : (M,) int32: for a voxel, bit ``b`` set when a view whose elevation arc at the voxel
        runs along ``+-PAIR_STEPS[b]`` would settle it (both those neighbours known free, or a
        direction no ping has observed it along while it touches free space); -1 for a block.
    weight : (M,) int32: 1 for a voxel, the unknown voxels of a block.
    """

    def __init__(self, points, pairs, weight):
        self.points, self.pairs, self.weight = points, pairs, weight


def arc_bits(A: np.ndarray, x: np.ndarray, y: np.ndarray, z: np.ndarray, h2: np.ndarray) -> np.ndarray:
    """(m,) int64 pair bit (0..12) of the elevation arc's direction at sonar-frame points
    ``x, y, z`` (float32, ``h2 = x^2 + y^2``) of a ping whose ``A`` (3, 3) float32 maps world
    to sonar: the kernels' arithmetic, in the same float32 order."""
    ex, ey, ez = -(x * z), -(y * z), h2
    wx = A[0, 0] * ex + A[1, 0] * ey + A[2, 0] * ez
    wy = A[0, 1] * ex + A[1, 1] * ey + A[2, 1] * ez
    wz = A[0, 2] * ex + A[1, 2] * ey + A[2, 2] * ez
    n2 = wx * wx + wy * wy + wz * wz

    def step(d):
        return np.where(_F(4) * d * d > n2, np.where(d > 0, 1, -1), 0)

    m = (step(wx) + 1) * 9 + (step(wy) + 1) * 3 + (step(wz) + 1)
    return np.maximum(m, 26 - m) - 14


def gain_points(raw_values: np.ndarray, confirmed: np.ndarray, threshold: float, grid,
                arcs: np.ndarray | None = None) -> ViewGainPoints:
    """The points the gain tests, from the map's raw values ((nx, ny, nz) float32, ``+inf``
    unknown), the confirmed flags ((nx, ny, nz) bool), the threshold and the arc directions each
    voxel was observed along ((n,) uint16 bit masks, None: none recorded)."""
    v = raw_values
    thr = np.float32(threshold)
    occ = np.isfinite(v) & (v >= thr)
    free = np.pad(np.isfinite(v) & (v < thr), 1)  # outside the grid: not known free
    unc = occ & ~confirmed
    n = v.shape
    mask = np.zeros(n, np.int32)
    touches = np.zeros(n, bool)
    for b, (si, sj, sk) in enumerate(PAIR_STEPS):
        fwd = free[1 + si: 1 + si + n[0], 1 + sj: 1 + sj + n[1], 1 + sk: 1 + sk + n[2]]
        bwd = free[1 - si: 1 - si + n[0], 1 - sj: 1 - sj + n[1], 1 - sk: 1 - sk + n[2]]
        mask |= (fwd & bwd).astype(np.int32) << b
        touches |= fwd | bwd
    if arcs is not None:  # directions no view has used at the voxel, where it touches free space
        new = (~arcs.reshape(n).astype(np.int32)) & 0x1FFF
        mask = np.where(touches, mask | new, mask)
    # a voxel with no free pair can be settled by no view: it adds nothing to any gain
    ii = np.argwhere(unc & (mask != 0))
    p_unc = grid.min_corner_m + (ii + 0.5) * grid.voxel_size_m
    unknown = np.isinf(v)
    nb = [-(-d // BLOCK) for d in v.shape]
    pad = np.zeros([n * BLOCK for n in nb], np.int32)
    pad[: v.shape[0], : v.shape[1], : v.shape[2]] = unknown
    counts = pad.reshape(nb[0], BLOCK, nb[1], BLOCK, nb[2], BLOCK).sum(axis=(1, 3, 5))
    blocks = np.argwhere(counts > 0)
    p_blk = grid.min_corner_m + (blocks * BLOCK + 0.5 * BLOCK) * grid.voxel_size_m
    points = np.ascontiguousarray(np.concatenate([p_unc, p_blk]), dtype=np.float32)
    pairs = np.concatenate([mask[tuple(ii.T)], np.full(len(blocks), -1)]).astype(np.int32)
    weight = np.concatenate([np.ones(len(ii), np.int64), counts[tuple(blocks.T)]]).astype(np.int32)
    return ViewGainPoints(points, pairs, weight)


def _fov(params: np.ndarray) -> tuple[float, float, float, float, float]:
    return tuple(float(np.float32(params[k])) for k in ("rmin", "rmax", "tan2_half_vfov", "tan_lo", "tan_hi"))


def poses_to_rows(Ts: np.ndarray) -> np.ndarray:
    """(K, 4, 4) float64 checked poses -> (K, 12) float32 rows of ``A = R^T`` and ``b = -R^T t``,
    rounded as :meth:`gpumap.core.integrator.Integrator.ping_params` rounds a ping's."""
    R = Ts[:, :3, :3]
    t = Ts[:, :3, 3]
    out = np.empty((Ts.shape[0], 12), np.float32)
    out[:, :9] = R.transpose(0, 2, 1).reshape(-1, 9)
    out[:, 9:] = -(R[:, 0, :] * t[:, 0:1] + R[:, 1, :] * t[:, 1:2] + R[:, 2, :] * t[:, 2:3])
    return out


def view_gain_reference(
    rows: np.ndarray, pts: ViewGainPoints, fov: tuple[float, float, float, float, float]
) -> tuple[np.ndarray, np.ndarray]:
    """NumPy twin of the ``view_gain`` kernels: (settle, unknown) int64 totals per candidate.

    ``rows`` (K, 12) float32 from :func:`poses_to_rows`; ``fov`` (r_min, r_max, tan^2 of half
    the vertical aperture, tangents of the fan's edges) as float32 values.
    """
    rmin, rmax, tan2, tlo, thi = (_F(f) for f in fov)
    K = rows.shape[0]
    settle = np.zeros(K, np.int64)
    unknown = np.zeros(K, np.int64)
    p = pts.points
    is_blk = pts.pairs < 0
    # the pair of each step, from a table (the kernels compute it)
    bit_of = np.full((3, 3, 3), -1, np.int64)
    for b, st in enumerate(PAIR_STEPS):
        bit_of[tuple(st + 1)] = b
        bit_of[tuple(1 - st)] = b

    def step(d, n2):
        return np.where(_F(4) * d * d > n2, np.where(d > 0, 1, -1), 0)

    with np.errstate(divide="ignore", invalid="ignore"):
        for c in range(K):
            a = rows[c]
            x = a[0] * p[:, 0] + a[1] * p[:, 1] + a[2] * p[:, 2] + a[9]
            y = a[3] * p[:, 0] + a[4] * p[:, 1] + a[5] * p[:, 2] + a[10]
            z = a[6] * p[:, 0] + a[7] * p[:, 1] + a[8] * p[:, 2] + a[11]
            h2 = x * x + y * y
            r = np.sqrt(h2 + z * z)
            t = y / x
            seen = (x > 0) & (r >= rmin) & (r < rmax) & (z * z <= tan2 * h2) & (t >= tlo) & (t <= thi)
            unknown[c] = int(pts.weight[seen & is_blk].sum())
            m = seen & ~is_blk
            if not m.any():
                continue
            xm, ym, zm, hm = x[m], y[m], z[m], h2[m]
            ex, ey, ez = -(xm * zm), -(ym * zm), hm
            wx = a[0] * ex + a[3] * ey + a[6] * ez
            wy = a[1] * ex + a[4] * ey + a[7] * ez
            wz = a[2] * ex + a[5] * ey + a[8] * ez
            n2 = wx * wx + wy * wy + wz * wz
            si, sj, sk = step(wx, n2), step(wy, n2), step(wz, n2)
            ok = (pts.pairs[m] >> bit_of[si + 1, sj + 1, sk + 1]) & 1 == 1
            settle[c] = int(pts.weight[m][ok].sum())
    return settle, unknown


# ------------------------------------------------------------------ device runners
_CL_PROGRAMS: dict[int, object] = {}  # context -> the built kernel
_CL_LOCK = threading.Lock()


class GainRunner:
    """Runs the view-gain kernel on a mapper's backend (numpy, Warp or OpenCL), never another."""

    def __init__(self, backend) -> None:
        self.backend = backend
        name = backend.name
        self.kind = "numpy" if name == "numpy" else ("warp" if name.startswith("warp") else "opencl")

    def __call__(self, rows: np.ndarray, pts: ViewGainPoints, fov) -> tuple[np.ndarray, np.ndarray]:
        if self.kind == "numpy" or rows.shape[0] == 0 or pts.points.shape[0] == 0:
            return view_gain_reference(rows, pts, fov)
        if self.kind == "warp":
            return self._warp(rows, pts, fov)
        return self._opencl(rows, pts, fov)

    def _warp(self, rows, pts, fov):
        b = self.backend
        wp = b.wp
        from gpumap.kernels import viewgain

        K, M = rows.shape[0], pts.points.shape[0]
        tile = GPU_TILE if b.dev.is_cuda else CPU_TILE
        n_tiles = -(-M // min(tile, M))
        with wp.ScopedDevice(b.dev):
            settle = wp.zeros(K, dtype=int)
            unknown = wp.zeros(K, dtype=int)
            wp.launch(
                viewgain.view_gain,
                dim=(K, n_tiles),
                inputs=[
                    wp.array(rows, dtype=float),
                    wp.array(pts.points, dtype=wp.vec3),
                    wp.array(pts.pairs, dtype=int),
                    wp.array(pts.weight, dtype=int),
                    *(float(f) for f in fov),
                    int(min(tile, M)),
                    settle,
                    unknown,
                ],
            )
            return settle.numpy().astype(np.int64), unknown.numpy().astype(np.int64)

    def _opencl(self, rows, pts, fov):
        b = self.backend
        cl = b.cl
        key = id(b.ctx)
        with _CL_LOCK:
            if key not in _CL_PROGRAMS:
                from gpumap.backends.opencl_backend import extra_program

                _CL_PROGRAMS[key] = cl.Kernel(extra_program(b.ctx, "viewgain"), "view_gain")
                _CL_PROGRAMS[key].set_scalar_arg_dtypes(
                    [None] * 4 + [np.float32] * 5 + [np.int32] * 2 + [None] * 2)
            k = _CL_PROGRAMS[key]
        K, M = rows.shape[0], pts.points.shape[0]
        tile = GPU_TILE if b.is_gpu else max(256, -(-M // 8))
        n_tiles = -(-M // tile)
        mf = cl.mem_flags
        q = b.queue

        def buf(a):
            return cl.Buffer(b.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=np.ascontiguousarray(a))

        out = np.zeros(K, np.int32)
        settle = cl.Buffer(b.ctx, mf.READ_WRITE | mf.COPY_HOST_PTR, hostbuf=out)
        unknown = cl.Buffer(b.ctx, mf.READ_WRITE | mf.COPY_HOST_PTR, hostbuf=out)
        with _CL_LOCK:  # a kernel object's arguments are shared state: set and enqueue as one
            k(q, (K, n_tiles), None, buf(rows), buf(pts.points), buf(pts.pairs), buf(pts.weight),
              *fov, M, tile, settle, unknown)
        s = np.empty(K, np.int32)
        u = np.empty(K, np.int32)
        cl.enqueue_copy(q, s, settle)
        cl.enqueue_copy(q, u, unknown)
        q.finish()
        return s.astype(np.int64), u.astype(np.int64)


# ------------------------------------------------------------------ candidates and planner
def _rot(axis: int, a: np.ndarray) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    R = np.zeros(a.shape + (3, 3))
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    R[..., axis, axis] = 1.0
    R[..., i, i] = c
    R[..., j, j] = c
    R[..., i, j] = -s
    R[..., j, i] = s
    return R


def _bounds(b, name: str) -> tuple[float, float]:
    try:
        lo, hi = (check_finite_scalar(x, name) for x in b)
    except (TypeError, ValueError) as e:
        raise ValueError(f"Expected (low, high) finite numbers for {name!r}, but got {b!r}") from e
    if lo > hi:
        raise ValueError(f"Expected low <= high for {name!r}, but got {b!r}")
    return lo, hi


def candidate_poses(
    T_W_S: np.ndarray,
    n: int,
    *,
    roll_rad: tuple[float, float] = (-math.radians(45), math.radians(45)),
    pitch_rad: tuple[float, float] = (-math.radians(15), math.radians(15)),
    yaw_rad: tuple[float, float] = (-math.radians(20), math.radians(20)),
    offset_m: tuple[float, float] = (-0.1, 0.1),
    seed: int = 0,
) -> np.ndarray:
    """(n, 4, 4) float64 candidate sonar poses around ``T_W_S`` (4, 4), within the given offsets.

    Each candidate is ``T_W_S @ Trans(d) @ Rz(yaw) @ Ry(pitch) @ Rx(roll)`` in the sonar frame
    (roll about the boresight x, pitch about y, positive down, yaw about z, ``d`` a translation
    with each axis in ``offset_m``), each offset drawn uniformly within its bounds (radians,
    metres) from ``seed``. The first candidate is ``T_W_S`` itself. Bounds such as a wrist's joint
    limits keep the candidates reachable; (0, 0) fixes that offset.
    """
    T = np.asarray(T_W_S, dtype=np.float64)
    if T.shape != (4, 4):
        raise ValueError(f"Expected T_W_S of shape (4, 4), but got {T.shape}")
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise ValueError(f"Expected a positive integer n, but got {n!r}")
    bounds = [_bounds(b, nm) for b, nm in ((roll_rad, "roll_rad"), (pitch_rad, "pitch_rad"),
                                            (yaw_rad, "yaw_rad"), (offset_m, "offset_m"))]
    rng = np.random.default_rng(seed)
    u = rng.random((n, 6))
    lo = np.array([bounds[0][0], bounds[1][0], bounds[2][0]] + [bounds[3][0]] * 3)
    hi = np.array([bounds[0][1], bounds[1][1], bounds[2][1]] + [bounds[3][1]] * 3)
    x = lo + (hi - lo) * u
    x[0] = 0.0
    R = _rot(2, x[:, 2]) @ _rot(1, x[:, 1]) @ _rot(0, x[:, 0])
    D = np.tile(np.eye(4), (n, 1, 1))
    D[:, :3, :3] = R
    D[:, :3, 3] = x[:, 3:]
    return T @ D


def plan_views(
    mapper,
    candidates: Callable[[int], np.ndarray],
    take_ping: Callable[[np.ndarray], np.ndarray],
    n_views: int,
    unknown_weight: float = 0.0,
) -> list[dict]:
    """Greedy next-best-view loop: ``n_views`` times, score ``candidates(i)`` ((K, 4, 4) poses),
    take the best, get its ping from ``take_ping(T_W_S)`` and integrate it into ``mapper`` (a
    :class:`gpumap.MinMaxMapper` with ``confidence=True``). Returns one record per view: ``T_W_S``,
    ``gain`` and the index of the chosen candidate. ``unknown_weight`` (default 0: resolve what
    the map holds; views that look at unseen volume add new stretch, see ``bench/results/nbv.json``)
    is passed to :meth:`~gpumap.MinMaxMapper.view_gain`."""
    out = []
    for i in range(n_views):
        Ts = candidates(i)
        g = confidence_of(mapper).gains(Ts, unknown_weight=unknown_weight)
        k = int(np.argmax(g))
        image = take_ping(Ts[k])
        mapper.integrate(image, Ts[k])
        out.append({"T_W_S": Ts[k], "gain": float(g[k]), "candidate": k})
    return out


def next_best_views(
    mapper,
    anchors: np.ndarray,
    *,
    views: int = 5,
    candidates: int = 2000,
    roll_rad: tuple[float, float] = (-math.radians(45), math.radians(45)),
    pitch_rad: tuple[float, float] = (-math.radians(15), math.radians(15)),
    yaw_rad: tuple[float, float] = (-math.radians(20), math.radians(20)),
    offset_m: tuple[float, float] = (-0.1, 0.1),
    unknown_weight: float = 0.0,
    seed: int = 0,
) -> tuple[list[dict], int]:
    """The ``views`` best of ``candidates`` poses drawn around ``anchors``, by view gain.

    Parameters
    ----------
    mapper : gpumap.MinMaxMapper
        A map with its confidence layer (``confidence=True``); it is read, never changed.
    anchors : (A, 4, 4) or (4, 4) float
        ``T_W_S`` poses the vehicle can hold; ``ceil(candidates / A)`` candidates are drawn
        around each (:func:`candidate_poses`, seed ``seed * 1009 + a`` for anchor ``a``, within
        the wrist's limits ``roll_rad``, ``pitch_rad``, ``yaw_rad`` (radians) and ``offset_m``
        (metres, each axis)), the first ``candidates`` of them scored.
    unknown_weight : float
        Weight of an unknown voxel against an unconfirmed one (:meth:`~gpumap.MinMaxMapper.view_gain`).

    Returns
    -------
    views : list of dict
        Best first (ties: the earlier candidate): ``T_W_S`` ((4, 4) float64), ``gain``,
        ``candidate`` (its index) and ``anchor`` (the index of the anchor it was drawn around).
    n_candidates : int
        The candidates scored.
    """
    A = np.asarray(anchors, dtype=np.float64)
    A = A[None] if A.shape == (4, 4) else A
    if A.ndim != 3 or A.shape[1:] != (4, 4) or len(A) == 0:
        raise ValueError(f"Expected anchors of shape (A, 4, 4) with A >= 1, or (4, 4), but got {A.shape}")
    for name, v in (("views", views), ("candidates", candidates)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
            raise ValueError(f"Expected a positive integer {name}, but got {v!r}")
    per = -(-int(candidates) // len(A))
    C = np.concatenate([candidate_poses(T, per, seed=seed * 1009 + i, roll_rad=roll_rad, pitch_rad=pitch_rad,
                                        yaw_rad=yaw_rad, offset_m=offset_m)
                        for i, T in enumerate(A)])[: int(candidates)]
    anchor_of = np.repeat(np.arange(len(A)), per)[: len(C)]
    g = confidence_of(mapper).gains(C, unknown_weight=unknown_weight)
    best = np.argsort(-g, kind="stable")[: int(views)]
    return [{"T_W_S": C[k], "gain": float(g[k]), "candidate": int(k), "anchor": int(anchor_of[k])}
            for k in best], len(C)
