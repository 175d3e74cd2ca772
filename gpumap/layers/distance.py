"""The distance field of the safe map: how far the nearest obstacle is from a point, and which way.

**What the field holds.** For every voxel centre of :attr:`MinMaxMapper.grid`, the Euclidean distance
in metres to the nearest *obstacle* voxel centre: 0 at obstacles. Obstacles are the safe map's occupied
voxels (``values >= mapper.threshold``) and, by default, its unknown ones (``NaN``: never observed):
a planner then keeps its distance from what the sonar has not seen as well as from what it has seen
occupied (``unknown_is_obstacle=False`` counts them free). The transform is exact on the voxel grid:
squared distances in voxel units are integers computed exactly on every backend (NumPy/SciPy, Warp,
OpenCL: :mod:`gpumap.layers.distance_device`), then ``metres = sqrt(d2) * voxel_size_m`` in float32.

- ``max_distance_m`` truncates: distances above it read ``max_distance_m`` (and incremental updates
  reach at most that far from what changed). Without it, a grid with no obstacle reads ``+inf``
  everywhere; with it, ``max_distance_m``.
- ``signed=True`` also keeps the distance from each obstacle voxel centre to the nearest free one, as a
  negative value: ``field > 0`` free, ``< 0`` inside obstacles (never 0: the surface lies between an
  obstacle voxel at ``-s`` and a free one at ``+s``, ``s`` the voxel size, at best). A grid without a
  free voxel reads ``-inf`` (``-max_distance_m`` truncated).

**Incremental.** :meth:`DistanceField.update` reads the map, finds the voxels whose obstacle state
changed since the last update and recomputes only what they can have changed; the result equals a full
recomputation, voxel for voxel (the tests check it after every batch of a run).

- On the device backends (Warp, OpenCL) the transform's three passes (one per axis, one thread per line)
  stay on the device, and an update reruns only the lines whose input changed: the lines of the first
  pass through a changed voxel, then in each later pass the lines through a value the previous pass
  changed (each kernel flags them as it writes). Exact by construction: a line whose input is the same
  gives the same output.
- On the NumPy (SciPy) path, which transforms whole boxes only, a voxel ``q`` keeps its distance when
  ``d_old(q)`` (truncated) is below its distance to every changed voxel. The test runs on tiles of
  ``tile`` voxels (each tile's largest distance against a lower bound of its distance to the changed
  tiles); the affected tiles, grouped into boxes, are transformed with a margin wide enough for
  exactness (the truncation radius; without one, grown until every recomputed distance is certified: no
  voxel beyond the margin could be nearer). Where distances are long (unknown counted free, no cap)
  that is most of the grid, and the update runs whole.

**Queries.** :meth:`distance_at` and :meth:`gradient_at` interpolate the field trilinearly between voxel
centres (batched world points, metres; within half a voxel of the grid's faces the value is held
constant outwards); :meth:`block` gives the field of a box around a point. Points outside the grid's
voxels ``[min_corner, min_corner + shape * voxel_size)``, non-finite points and wrong shapes raise
``ValueError``/``TypeError`` with what was expected and what came.

The layer attaches to a mapper and reads only its public API (``values()``, ``grid``, ``threshold``,
``backend``); the map never imports it.
"""

from __future__ import annotations

import math
import time

import numpy as np

from gpumap.errors import check_finite_scalar
from gpumap.layers.distance_device import INF, Cascade, check_box_dims, make_transform
from gpumap.spec import GridSpec

__all__ = ["DistanceField", "cap_squared", "d2_to_metres", "trilinear"]

_SQRT3 = math.sqrt(3.0)


def cap_squared(max_distance_m: float | None, voxel_size_m: float) -> int:
    """The largest squared distance (voxel units) at most ``max_distance_m`` away: ``INF - 1`` (no cap)
    for None."""
    if max_distance_m is None:
        return INF - 1
    r = float(max_distance_m) / float(voxel_size_m)
    c = min(int(math.floor(r * r)), INF - 1)
    while c + 1 < INF - 1 and math.sqrt(c + 1) <= r:
        c += 1
    while c > 0 and math.sqrt(c) > r:
        c -= 1
    return c


def d2_to_metres(d2: np.ndarray, voxel_size_m: float, cap2: int, max_distance_m: float | None) -> np.ndarray:
    """Squared voxel distances (int32, ``INF`` none within reach) -> float32 metres: ``sqrt(d2) * s`` in
    float32, ``max_distance_m`` above ``cap2`` (``+inf`` without a cap)."""
    out = np.sqrt(d2.astype(np.float32)) * np.float32(voxel_size_m)
    far = d2 > cap2
    if max_distance_m is None:
        out[far] = np.inf
    else:
        top = np.float32(max_distance_m)
        np.minimum(out, top, out=out)
        out[far] = top
    return out


def _real(a: np.ndarray) -> bool:
    return a.dtype != object and (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer))


def _points(points_W, grid: GridSpec, name: str = "points_W") -> np.ndarray:
    """``points_W`` checked: (N, 3) finite real world points inside the grid's voxels, as float64."""
    a = np.asarray(points_W)
    if not _real(a):
        raise TypeError(f"Expected real numbers for '{name}', but got dtype {a.dtype}")
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"Expected '{name}' of shape (N, 3), but got {a.shape}")
    p = a.astype(np.float64)
    bad = ~np.isfinite(p).all(axis=1)
    if bad.any():
        i = int(np.argmax(bad))
        raise ValueError(f"Expected finite '{name}', but {int(bad.sum())} rows are not (first: row {i}, "
                         f"{p[i].tolist()})")
    lo = np.asarray(grid.min_corner_m)
    hi = lo + np.asarray(grid.shape) * grid.voxel_size_m
    out = ((p < lo) | (p >= hi)).any(axis=1)
    if out.any():
        i = int(np.argmax(out))
        raise ValueError(f"Expected '{name}' inside the grid's voxels {np.round(lo, 4).tolist()} to "
                         f"{np.round(hi, 4).tolist()} m, but {int(out.sum())} of {len(p)} are outside "
                         f"(first: row {i}, {p[i].tolist()})")
    return p


def trilinear(field: np.ndarray, grid: GridSpec, points_W: np.ndarray, gradient: bool = False):
    """Trilinear interpolation of ``field`` ((nx, ny, nz) over ``grid``'s voxel centres) at world points.

    ``points_W``: (N, 3) float64 inside the grid's voxels (unchecked here). Returns (N,) float64, and
    with ``gradient`` also the (N, 3) gradient of the interpolant (per metre; 0 along an axis within half
    a voxel of the grid's faces, where the value is held constant). A field that is not finite
    everywhere (``+-inf``: no obstacle or no free voxel at all) gives its value and a zero gradient."""
    f = np.asarray(field)
    p = np.asarray(points_W, np.float64)
    first = float(f.flat[0])
    if not math.isfinite(first):
        v = np.full(len(p), first)
        return (v, np.zeros((len(p), 3))) if gradient else v
    n = np.asarray(f.shape)
    s = grid.voxel_size_m
    c = (p - np.asarray(grid.min_corner_m)) / s - 0.5
    i0 = np.clip(np.floor(c), 0, np.maximum(n - 2, 0)).astype(np.int64)
    inside = (c >= 0) & (c <= n - 1)  # between the first and last centre along each axis
    t = np.where(inside, np.clip(c - i0, 0.0, 1.0), np.where(c < 0, 0.0, 1.0))
    t = np.where(n > 1, t, 0.0)
    i1 = np.minimum(i0 + 1, n - 1)
    val = np.zeros(len(p))
    grad = np.zeros((len(p), 3)) if gradient else None
    for corner in np.ndindex(2, 2, 2):
        idx = [np.where(corner[a], i1[:, a], i0[:, a]) for a in range(3)]
        fc = f[idx[0], idx[1], idx[2]].astype(np.float64)
        w = [np.where(corner[a], t[:, a], 1.0 - t[:, a]) for a in range(3)]
        val += w[0] * w[1] * w[2] * fc
        if gradient:
            sign = [1.0 if corner[a] else -1.0 for a in range(3)]
            grad[:, 0] += sign[0] * w[1] * w[2] * fc
            grad[:, 1] += sign[1] * w[0] * w[2] * fc
            grad[:, 2] += sign[2] * w[0] * w[1] * fc
    if not gradient:
        return val
    grad *= np.where(inside & (n > 1), 1.0 / s, 0.0)
    return val, grad


def _tile_max(d2: np.ndarray, tile: int, cap2: int) -> np.ndarray:
    """Per tile of ``tile``^3 voxels (the last ones clipped): the largest ``min(d2, cap2)``, int64."""
    n = d2.shape
    nt = [-(-a // tile) for a in n]
    pad = [(0, t * tile - a) for a, t in zip(n, nt, strict=True)]
    a = np.pad(np.minimum(d2, cap2), pad) if any(p[1] for p in pad) else np.minimum(d2, cap2)
    return a.reshape(nt[0], tile, nt[1], tile, nt[2], tile).max(axis=(1, 3, 5)).astype(np.int64)


class DistanceField:
    """The Euclidean distance field of a mapper's safe map, kept up to date with :meth:`update`.

    Parameters
    ----------
    mapper : MinMaxMapper
        The map (read through ``values()``, ``grid``, ``threshold`` and ``backend`` only).
    unknown_is_obstacle : bool
        Count never-observed voxels as obstacles (default True: the safe choice for a planner).
    max_distance_m : float or None
        Truncation radius, metres (> 0): distances above it read it. None (default): exact everywhere.
    signed : bool
        Also the distance inside obstacles to the nearest free voxel centre, negative (twice the work).
    backend : str or None
        Where the transform runs: None (default) the mapper's backend; or one of ``"numpy"``
        (SciPy), ``"warp-cpu"``, ``"warp-cuda"``, ``"opencl"``, ``"opencl-gpu"``, ``"opencl-cpu"``. A
        named backend that cannot run raises :class:`gpumap.BackendUnavailableError`; never another.
    device_index : int or None
        That backend's device (None: the first).
    tile : int
        Edge of the tiles of the NumPy path's incremental test, voxels (default 8).

    The constructor computes the field of the map as it is (a full transform). Attributes:
    :attr:`backend` (the transform's backend, resolved), :attr:`grid` (the field's grid: the mapper's
    at the last update) and :attr:`last_update` (what the last update did: ``kind`` ``"full"``,
    ``"incremental"`` or ``"none"``, ``changed`` voxels, ``boxes``, ``transformed`` voxels, ``retries``
    of a margin, ``seconds``).
    """

    def __init__(self, mapper, *, unknown_is_obstacle: bool = True, max_distance_m: float | None = None,
                 signed: bool = False, backend: str | None = None, device_index: int | None = None,
                 tile: int = 8) -> None:
        for attr in ("values", "grid", "threshold", "backend"):
            if not hasattr(mapper, attr):
                raise TypeError(f"Expected a gpumap.MinMaxMapper for 'mapper' (with {attr!r}), but got "
                                f"{type(mapper).__name__}")
        for name, v in (("unknown_is_obstacle", unknown_is_obstacle), ("signed", signed)):
            if not isinstance(v, (bool, np.bool_)):
                raise TypeError(f"Expected a bool for {name!r}, but got {type(v).__name__}")
        if max_distance_m is not None:
            max_distance_m = check_finite_scalar(max_distance_m, "max_distance_m")
            if max_distance_m <= 0:
                raise ValueError(f"Expected max_distance_m > 0 or None, but got {max_distance_m}")
        if isinstance(tile, bool) or not isinstance(tile, (int, np.integer)) or not 1 <= tile <= 256:
            raise ValueError(f"Expected tile to be an integer in 1..256, but got {tile!r}")
        if backend is not None and not isinstance(backend, str):
            raise TypeError(f"Expected None or a backend name for 'backend', but got "
                            f"{type(backend).__name__}")
        self.mapper = mapper
        self.unknown_is_obstacle, self.signed = bool(unknown_is_obstacle), bool(signed)
        self.max_distance_m, self.tile = max_distance_m, int(tile)
        self._transform = make_transform(mapper.backend if backend is None else backend, device_index)
        self.backend = self._transform.name
        self.last_update: dict = {}
        self._grid: GridSpec | None = None
        self.update()

    # ------------------------------------------------------------------ state
    @property
    def grid(self) -> GridSpec:
        """The :class:`~gpumap.GridSpec` the field covers (the mapper's grid at the last update)."""
        return self._grid

    def _obstacles(self, values: np.ndarray) -> np.ndarray:
        occ = values >= np.float32(self.mapper.threshold)  # NaN compares false
        if self.unknown_is_obstacle:
            occ |= np.isnan(values)
        return occ

    def _inverts(self) -> tuple[bool, ...]:
        return (False, True) if self.signed else (False,)

    def update(self, full: bool = False, values: np.ndarray | None = None) -> int:
        """Bring the field up to date with the map; returns how many voxels the transform ran over (the
        recomputed boxes with their margins; 0 when no obstacle changed; every voxel for a full pass).

        Recomputes only where the obstacles that changed since the last update can have moved a
        distance (module docstring), or everything when the grid changed or ``full`` is set; either way
        the field equals a full recomputation. On an error the field stays as it was.

        ``values``: the map's ``mapper.values()`` ((nx, ny, nz) float32 over ``mapper.grid``, NaN unknown)
        as the caller has just read them, to save a second read (the ROS node reads them once for its
        clouds and the field: both then show the same map); None (default) reads them."""
        t0 = time.perf_counter()
        grid = self.mapper.grid
        if values is None:
            values = self.mapper.values()
        else:
            values = np.asarray(values)
            if values.dtype != np.float32:
                raise TypeError(f"Expected float32 'values' (mapper.values()), but got dtype {values.dtype}")
            if values.shape != tuple(grid.shape):
                raise ValueError(f"Expected 'values' of the map's grid shape {tuple(grid.shape)}, but got "
                                 f"{values.shape}")
        mask = self._obstacles(values)
        if full or self._grid is None or grid != self._grid:
            n = self._full(grid, mask)
            self.last_update = {"kind": "full", "changed": None, "boxes": 1, "transformed": n, "retries": 0}
        else:
            n = self._incremental(mask)
        self.last_update["seconds"] = time.perf_counter() - t0
        return n

    def _full(self, grid: GridSpec, mask: np.ndarray) -> int:
        check_box_dims(grid.shape)
        cap2 = cap_squared(self.max_distance_m, grid.voxel_size_m)
        tr = self._transform
        if tr.incremental:  # the passes stay on the device, rerun line by line later
            cascades = [Cascade(tr, mask.shape, cap2, inv) for inv in self._inverts()]
            for c in cascades:
                c.full(mask)
            d2, tmax = [c.d2() for c in cascades], None
        else:
            cascades, d2 = None, tr(mask, cap2, self._inverts())
            tmax = np.maximum.reduce([_tile_max(d, self.tile, cap2) for d in d2])
        metres = self._metres(d2, grid.voxel_size_m, cap2)
        # commit (nothing above changed the field)
        self._grid, self._cap2, self._mask = grid, cap2, mask
        self._cascades, self._d2, self._tmax, self._field = cascades, None if cascades else d2, tmax, metres
        return int(mask.size)

    def _metres(self, d2: list[np.ndarray], voxel: float, cap2: int) -> np.ndarray:
        out = d2_to_metres(d2[0], voxel, cap2, self.max_distance_m)
        if self.signed:
            out -= d2_to_metres(d2[1], voxel, cap2, self.max_distance_m)
        return out

    def _affected_boxes(self, changed: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
        """Boxes (voxel ranges ``[lo, hi)``, tile-aligned) holding every voxel whose distance the
        ``changed`` voxels (flat indices) can have moved."""
        from scipy import ndimage

        T, shape = self.tile, self._mask.shape
        nt = self._tmax.shape
        ct = np.zeros(nt, bool)
        ijk = np.unravel_index(changed, shape)
        ct[ijk[0] // T, ijk[1] // T, ijk[2] // T] = True
        # a lower bound of each tile's distance (voxels) to the nearest changed voxel: centre distance to
        # the nearest changed tile, less the two tiles' half diagonals
        lb = np.maximum(ndimage.distance_transform_edt(~ct) * T - (T - 1) * _SQRT3, 0.0) if not ct.all() \
            else np.zeros(nt)
        hit = ct | (np.sqrt(self._tmax.astype(np.float64)) >= lb - 1e-6)
        labels, _ = ndimage.label(hit, structure=np.ones((3, 3, 3), bool))
        boxes = []
        for sl in ndimage.find_objects(labels):
            lo = np.array([s.start * T for s in sl])
            hi = np.minimum(np.array([s.stop * T for s in sl]), shape)
            boxes.append((lo, hi))
        return _merge_boxes(boxes, self._margin_guess(), shape)

    def _margin_guess(self) -> int:
        if self.max_distance_m is not None:
            return math.isqrt(self._cap2)
        return 0

    def _first_margin(self, lo: np.ndarray, hi: np.ndarray) -> int:
        """The margin (voxels) a box ``[lo, hi)`` is first transformed with: the truncation radius (always
        enough), or without one a guess, checked afterwards: the largest old distance in the box's tiles,
        and a tile."""
        if self.max_distance_m is not None:
            return self._margin_guess()
        T = self.tile
        tm = self._tmax[tuple(slice(a // T, -(-b // T)) for a, b in zip(lo, hi, strict=True))]
        return int(math.isqrt(int(tm.max()))) + 1 + T

    def _incremental(self, mask: np.ndarray) -> int:
        changed = np.flatnonzero(mask != self._mask)
        if not changed.size:
            self.last_update = {"kind": "none", "changed": 0, "boxes": 0, "transformed": 0, "retries": 0}
            self._mask = mask
            return 0
        if self._cascades is not None:
            return self._by_lines(mask, changed)
        boxes = self._affected_boxes(changed)
        shape = np.asarray(mask.shape)
        results, work, retries = [], 0, 0
        for lo, hi in boxes:
            m = self._first_margin(lo, hi)
            while True:
                ilo, ihi = np.maximum(lo - m, 0), np.minimum(hi + m, shape)
                work += int(np.prod(ihi - ilo))
                if work >= mask.size:  # no cheaper than a full pass
                    n = self._full(self._grid, mask)
                    self.last_update = {"kind": "full", "changed": int(changed.size), "boxes": len(boxes),
                                        "transformed": n, "retries": retries}
                    return n
                sub = tuple(slice(a, b) for a, b in zip(ilo, ihi, strict=True))
                d2 = self._transform(mask[sub], self._cap2, self._inverts())
                inner = tuple(slice(a - c, b - c) for a, b, c in zip(lo, hi, ilo, strict=True))
                d2 = [d[inner] for d in d2]
                # the margin actually left on each side that is not the grid's face
                sides = [int(x) for x in np.concatenate([(lo - ilo)[ilo > 0], (ihi - hi)[ihi < shape]])]
                if self.max_distance_m is not None or not sides:
                    break
                top = (min(sides) + 1) ** 2  # nothing outside the margin is nearer than this
                if all(int(d.max()) <= top for d in d2):
                    break
                m, retries = 2 * m + 1, retries + 1
            results.append((lo, hi, d2))
        # commit: the boxes' new distances, their tiles' maxima, their metres
        voxel = self._grid.voxel_size_m
        T = self.tile
        for lo, hi, d2 in results:
            sub = tuple(slice(a, b) for a, b in zip(lo, hi, strict=True))
            for old, new in zip(self._d2, d2, strict=True):
                old[sub] = new
            tsub = tuple(slice(a // T, -(-b // T)) for a, b in zip(lo, hi, strict=True))
            self._tmax[tsub] = np.maximum.reduce([_tile_max(d, T, self._cap2) for d in d2])
            self._field[sub] = self._metres(d2, voxel, self._cap2)
        self._mask = mask
        self.last_update = {"kind": "incremental", "changed": int(changed.size), "boxes": len(results),
                            "transformed": work, "retries": retries}
        return work

    def _by_lines(self, mask: np.ndarray, changed: np.ndarray) -> int:
        """The device backends' update: each field's passes rerun on the lines whose input changed."""
        work = sum(c.refresh(mask, changed) for c in self._cascades) // len(self._cascades)
        lines = np.logical_or.reduce([c.changed_lines() for c in self._cascades])
        jj, kk = np.nonzero(lines)
        if jj.size:
            d2 = [c.d2()[:, jj, kk] for c in self._cascades]
            self._field[:, jj, kk] = self._metres(d2, self._grid.voxel_size_m, self._cap2)
        self._mask = mask
        self.last_update = {"kind": "incremental", "changed": int(changed.size), "boxes": 0,
                            "transformed": work, "retries": 0, "lines_changed": int(jj.size)}
        return work

    # ------------------------------------------------------------------ reading
    def field(self) -> np.ndarray:
        """(nx, ny, nz) float32 copy over :attr:`grid`, metres: distance to the nearest obstacle voxel
        centre, 0 at obstacles (negative inside them with ``signed``); ``+inf`` where the grid has no
        obstacle (``max_distance_m`` with a cap)."""
        return self._field.copy()

    def obstacles(self) -> np.ndarray:
        """(nx, ny, nz) bool copy: the obstacle voxels the field was computed from."""
        return self._mask.copy()

    def distance_at(self, points_W) -> np.ndarray:
        """(N,) float64 distance, metres, at world points ``points_W`` ((N, 3) float, metres, inside the
        grid's voxels): the field interpolated trilinearly between voxel centres."""
        return trilinear(self._field, self._grid, _points(points_W, self._grid))

    def gradient_at(self, points_W) -> np.ndarray:
        """(N, 3) float64 gradient of :meth:`distance_at` (metres per metre: pointing away from the
        nearest obstacles, length about 1 in free space; 0 where the field is flat: beyond a cap, inside
        one voxel of a plateau, or along an axis within half a voxel of the grid's faces)."""
        return trilinear(self._field, self._grid, _points(points_W, self._grid), gradient=True)[1]

    def block(self, center_m, half_extent_m) -> tuple[GridSpec, np.ndarray]:
        """The field of the voxels whose centres lie within ``half_extent_m`` (a float or (3,) floats,
        metres, >= 0) of ``center_m`` ((3,) world point) on every axis, clipped to the grid: the box's
        :class:`~gpumap.GridSpec` (its voxels are the field's) and its (bx, by, bz) float32 copy."""
        ca = np.asarray(center_m)
        if ca.shape != (3,):
            raise ValueError(f"Expected 'center_m' of shape (3,), but got {ca.shape}")
        c = _points(ca[None, :], self._grid, "center_m")[0]
        ha = np.asarray(half_extent_m)
        if not _real(ha):
            raise TypeError(f"Expected real numbers for 'half_extent_m', but got dtype {ha.dtype}")
        if ha.shape not in ((), (3,)):
            raise ValueError(f"Expected a float or 3 floats for 'half_extent_m', but got shape {ha.shape}")
        h = np.broadcast_to(ha.astype(np.float64), (3,))
        if not np.isfinite(h).all() or (h < 0).any():
            raise ValueError(f"Expected finite half_extent_m >= 0, but got {h.tolist()}")
        g = self._grid
        s, lo0, n = g.voxel_size_m, np.asarray(g.min_corner_m), np.asarray(g.shape)
        i0 = np.maximum(np.ceil((c - h - lo0) / s - 0.5).astype(np.int64), 0)
        i1 = np.minimum(np.floor((c + h - lo0) / s - 0.5).astype(np.int64), n - 1)
        i0 = np.minimum(i0, i1)  # a box thinner than a voxel keeps the voxel holding the centre
        box = GridSpec(tuple(lo0 + i0 * s), tuple(lo0 + (i1 + 1) * s), s)
        sub = tuple(slice(a, b + 1) for a, b in zip(i0, i1, strict=True))
        return box, self._field[sub].copy()


def _merge_boxes(boxes, margin: int, shape) -> list[tuple[np.ndarray, np.ndarray]]:
    """Merge boxes whose margined union costs no more voxels than the two apart (overlapping boxes
    would be transformed twice)."""
    shape = np.asarray(shape)

    def vol(lo, hi):
        return float(np.prod(np.minimum(hi + margin, shape) - np.maximum(lo - margin, 0)))

    boxes = list(boxes)
    merged = True
    while merged and len(boxes) > 1:
        merged = False
        for a in range(len(boxes)):
            for b in range(a + 1, len(boxes)):
                (la, ha), (lb, hb) = boxes[a], boxes[b]
                lo, hi = np.minimum(la, lb), np.maximum(ha, hb)
                if vol(lo, hi) <= vol(la, ha) + vol(lb, hb):
                    boxes[a] = (lo, hi)
                    del boxes[b]
                    merged = True
                    break
            if merged:
                break
    return boxes
