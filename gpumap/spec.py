"""Static descriptions: the imaging sonar (:class:`SonarSpec`), the world grid (:class:`GridSpec`)
and a block-sparse world grid (:class:`SparseSpec`); :func:`auto_grid`, the grid that holds
the fields of view of a recording's poses.

Both are small immutable value types. They validate themselves once, at construction,
so everything downstream can trust them.

Conventions (see ``DESIGN.md``): sonar frame x forward, y left, z up; range ``r = |p|``,
azimuth ``theta = atan2(y, x)``, elevation ``phi = atan2(z, hypot(x, y))``. A polar image
is ``(n_bins, n_beams)``: bin ``i`` covers ``[range_min + i*dr, range_min + (i+1)*dr)``,
beam ``j`` is centred on ``bearings_rad[j]`` and its cell is bounded by the midpoints to
its neighbours (the outer edges mirror the first and last half-spacings).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np

from gpumap.errors import check_finite_scalar

__all__ = ["GridSpec", "SonarSpec", "SparseSpec", "auto_grid"]


@dataclass(frozen=True, eq=False)
class SonarSpec:
    """A multibeam imaging sonar's geometry.

    Parameters
    ----------
    range_min_m, range_max_m : float
        Range of the first bin's near edge and of the last bin's far edge, metres.
        Returns nearer than ``range_min_m`` (blanking) or from ``range_max_m`` on are not imaged.
    n_bins : int
        Number of range bins (image rows); bins are uniform, ``dr = (max - min) / n_bins``.
    bearings_rad : (n_beams,) float
        Beam centre azimuths, strictly ascending, radians. Any spacing (real sonars are
        not uniform); at least 2 beams.
    vfov_rad : float
        Full vertical aperture, radians; a point is seen when ``|elevation| <= vfov/2``.
    """

    range_min_m: float
    range_max_m: float
    n_bins: int
    bearings_rad: np.ndarray
    vfov_rad: float
    beam_edges_rad: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        rmin = check_finite_scalar(self.range_min_m, "range_min_m")
        rmax = check_finite_scalar(self.range_max_m, "range_max_m")
        if rmin < 0 or rmax <= rmin:
            raise ValueError(
                f"Expected 0 <= range_min_m < range_max_m, but got range_min_m={rmin}, range_max_m={rmax}"
            )
        if isinstance(self.n_bins, bool) or not isinstance(self.n_bins, (int, np.integer)):
            raise TypeError(f"Expected an integer for 'n_bins', but got {type(self.n_bins).__name__}")
        if self.n_bins < 1:
            raise ValueError(f"Expected n_bins >= 1, but got {self.n_bins}")
        b = np.asarray(self.bearings_rad, dtype=np.float64)
        if b.ndim != 1 or b.shape[0] < 2:
            raise ValueError(
                f"Expected a 1-D array of at least 2 bearings for 'bearings_rad', but got shape {b.shape}"
            )
        if not np.all(np.isfinite(b)):
            raise ValueError("Expected finite values in 'bearings_rad', but got NaN or inf")
        steps = np.diff(b)
        if np.any(steps <= 0):
            k = int(np.argmax(steps <= 0))
            raise ValueError(
                "Expected strictly ascending 'bearings_rad', but got "
                f"bearings_rad[{k}]={b[k]!r} >= bearings_rad[{k + 1}]={b[k + 1]!r}"
            )
        edges = np.empty(b.shape[0] + 1)
        edges[1:-1] = 0.5 * (b[1:] + b[:-1])
        edges[0] = b[0] - 0.5 * steps[0]
        edges[-1] = b[-1] + 0.5 * steps[-1]
        if edges[0] <= -math.pi / 2 or edges[-1] >= math.pi / 2:
            raise ValueError(
                "Expected the beam fan to lie within (-90, 90) deg of boresight, but its outer "
                f"edges are at {math.degrees(edges[0]):.3f} and {math.degrees(edges[-1]):.3f} deg"
            )
        vfov = check_finite_scalar(self.vfov_rad, "vfov_rad")
        if not 0 < vfov < math.pi:
            raise ValueError(f"Expected 0 < vfov_rad < pi, but got {vfov}")
        b.setflags(write=False)
        edges.setflags(write=False)
        object.__setattr__(self, "range_min_m", rmin)
        object.__setattr__(self, "range_max_m", rmax)
        object.__setattr__(self, "n_bins", int(self.n_bins))
        object.__setattr__(self, "bearings_rad", b)
        object.__setattr__(self, "vfov_rad", vfov)
        object.__setattr__(self, "beam_edges_rad", edges)

    @classmethod
    def uniform(
        cls,
        hfov_deg: float = 130.0,
        vfov_deg: float = 20.0,
        n_beams: int = 512,
        n_bins: int = 400,
        range_min_m: float = 0.1,
        range_max_m: float = 2.0,
    ) -> SonarSpec:
        """A sonar with ``n_beams`` evenly spaced beams whose cells tile ``hfov_deg`` exactly."""
        hfov = math.radians(check_finite_scalar(hfov_deg, "hfov_deg"))
        if not 0 < hfov < math.pi:
            raise ValueError(f"Expected 0 < hfov_deg < 180, but got {hfov_deg}")
        if int(n_beams) < 2:
            raise ValueError(f"Expected n_beams >= 2, but got {n_beams}")
        step = hfov / n_beams
        bearings = -hfov / 2 + step * (np.arange(n_beams) + 0.5)
        return cls(range_min_m, range_max_m, n_bins, bearings, math.radians(vfov_deg))

    # ---------------------------------------------------------------- derived values
    @property
    def n_beams(self) -> int:
        return int(self.bearings_rad.shape[0])

    @property
    def image_shape(self) -> tuple[int, int]:
        """``(n_bins, n_beams)``: the shape of a polar image."""
        return (self.n_bins, self.n_beams)

    @property
    def bin_size_m(self) -> float:
        return (self.range_max_m - self.range_min_m) / self.n_bins

    @property
    def hfov_rad(self) -> float:
        """Full horizontal aperture between the outer beam-cell edges, radians."""
        return float(self.beam_edges_rad[-1] - self.beam_edges_rad[0])

    @property
    def bin_centers_m(self) -> np.ndarray:
        """(n_bins,) float64 range of each bin's centre, metres."""
        return self.range_min_m + (np.arange(self.n_bins) + 0.5) * self.bin_size_m

    def to_polar(self, p_S: np.ndarray) -> np.ndarray:
        """(..., 3) sonar-frame points -> (..., 3) (range_m, azimuth_rad, elevation_rad)."""
        p = np.asarray(p_S, dtype=np.float64)
        r = np.linalg.norm(p, axis=-1)
        az = np.arctan2(p[..., 1], p[..., 0])
        el = np.arctan2(p[..., 2], np.hypot(p[..., 0], p[..., 1]))
        return np.stack([r, az, el], axis=-1)

    def in_fov(self, p_S: np.ndarray) -> np.ndarray:
        """(..., 3) sonar-frame points -> (...) bool: inside the imaged volume."""
        pol = self.to_polar(p_S)
        r, az, el = pol[..., 0], pol[..., 1], pol[..., 2]
        return (
            (r >= self.range_min_m)
            & (r < self.range_max_m)
            & (az >= self.beam_edges_rad[0])
            & (az <= self.beam_edges_rad[-1])
            & (np.abs(el) <= 0.5 * self.vfov_rad)
        )

    def bin_index(self, range_m: np.ndarray) -> np.ndarray:
        """Range (metres) -> integer bin, -1 outside ``[range_min, range_max)``."""
        r = np.asarray(range_m, dtype=np.float64)
        i = np.floor((r - self.range_min_m) / self.bin_size_m).astype(np.int64)
        return np.where((r >= self.range_min_m) & (r < self.range_max_m) & (i < self.n_bins), i, -1)

    def beam_index(self, azimuth_rad: np.ndarray) -> np.ndarray:
        """Azimuth (radians) -> integer beam whose cell holds it, -1 outside the fan."""
        a = np.asarray(azimuth_rad, dtype=np.float64)
        j = np.searchsorted(self.beam_edges_rad, a, side="right") - 1
        j = np.where(a == self.beam_edges_rad[-1], self.n_beams - 1, j)
        return np.where((j >= 0) & (j < self.n_beams), j, -1)

    def fov_corners_S(self, n_arc: int = 8) -> np.ndarray:
        """(m, 3) sonar-frame points whose axis-aligned box (in any frame) holds the field of view.

        Every imaged point lies on a segment from the origin to the outer sphere patch
        (range ``range_max``, the fan's azimuths and elevations), so the box of the origin
        and that patch holds the imaged volume. The patch is sampled on an ``n_arc`` grid and
        pushed out by ``1 / cos(step / 2)``, which turns the samples' chords into a polygon
        circumscribing the patch: the box is conservative by construction.
        """
        az = np.linspace(self.beam_edges_rad[0], self.beam_edges_rad[-1], n_arc + 1)
        n_el = max(2, n_arc // 4)
        el = np.linspace(-0.5 * self.vfov_rad, 0.5 * self.vfov_rad, n_el + 1)
        A, E = np.meshgrid(az, el, indexing="ij")
        dirs = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], -1).reshape(-1, 3)
        step = max(self.hfov_rad / n_arc, self.vfov_rad / n_el)
        grow = 1.0 / math.cos(0.5 * step)
        return np.concatenate([dirs * self.range_max_m * grow, np.zeros((1, 3))])

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, SonarSpec):
            return NotImplemented
        return (
            self.range_min_m == other.range_min_m
            and self.range_max_m == other.range_max_m
            and self.n_bins == other.n_bins
            and self.vfov_rad == other.vfov_rad
            and np.array_equal(self.bearings_rad, other.bearings_rad)
        )

    __hash__ = None  # type: ignore[assignment]

    def to_dict(self) -> dict:
        return {
            "range_min_m": self.range_min_m,
            "range_max_m": self.range_max_m,
            "n_bins": self.n_bins,
            "bearings_rad": self.bearings_rad.tolist(),
            "vfov_rad": self.vfov_rad,
        }

    @classmethod
    def from_dict(cls, d: dict) -> SonarSpec:
        return cls(
            d["range_min_m"], d["range_max_m"], int(d["n_bins"]), np.asarray(d["bearings_rad"]), d["vfov_rad"]
        )


# A grid larger than this many voxels is refused outright, whatever memory there is.
_MAX_VOXELS = 2**31 - 1


@dataclass(frozen=True, eq=True)
class GridSpec:
    """A fixed, axis-aligned world grid of cubic voxels.

    Parameters
    ----------
    min_corner_m, max_corner_m : (3,) float
        Opposite corners of the box ``[min, max)`` in the world frame, metres.
    voxel_size_m : float
        Edge of a cubic voxel, metres. The grid has ``n = ceil((max - min) / size)``
        voxels per axis (the last one may reach past ``max_corner_m``).

    Voxel ``(i, j, k)`` has its centre at ``min_corner + (idx + 0.5) * voxel_size``; arrays
    over the grid are C-ordered ``(nx, ny, nz)``.
    """

    min_corner_m: tuple[float, float, float]
    max_corner_m: tuple[float, float, float]
    voxel_size_m: float

    def __post_init__(self) -> None:
        lo = _vec3(self.min_corner_m, "min_corner_m")
        hi = _vec3(self.max_corner_m, "max_corner_m")
        s = check_finite_scalar(self.voxel_size_m, "voxel_size_m")
        if s <= 0:
            raise ValueError(f"Expected voxel_size_m > 0, but got {s}")
        if any(h <= lo_ for lo_, h in zip(lo, hi, strict=True)):
            raise ValueError(
                f"Expected max_corner_m > min_corner_m on every axis (a non-empty box), but got "
                f"min_corner_m={lo} and max_corner_m={hi}"
            )
        object.__setattr__(self, "min_corner_m", lo)
        object.__setattr__(self, "max_corner_m", hi)
        object.__setattr__(self, "voxel_size_m", s)
        n = self.shape
        total = n[0] * n[1] * n[2]
        if total > _MAX_VOXELS:
            raise ValueError(
                f"Expected a grid of at most {_MAX_VOXELS} voxels, but voxel_size_m={s} over "
                f"{tuple(h - lo_ for lo_, h in zip(lo, hi, strict=True))} m gives {n} = {total} voxels "
                f"({total * 16 / 2**30:.1f} GiB with the default evidence rule's 16 bytes per voxel, "
                f"{total * 4 / 2**30:.1f} GiB with the plain rule's 4)"
            )

    @property
    def shape(self) -> tuple[int, int, int]:
        """``(nx, ny, nz)`` voxel counts."""
        s = self.voxel_size_m
        # Round before ceil so 4.0 / 0.01 = 400.00000000000006 gives 400, not 401.
        return tuple(
            int(math.ceil(round((h - lo) / s, 9)))
            for lo, h in zip(self.min_corner_m, self.max_corner_m, strict=True)
        )  # type: ignore[return-value]

    @property
    def n_voxels(self) -> int:
        nx, ny, nz = self.shape
        return nx * ny * nz

    @property
    def nbytes(self) -> int:
        """Bytes of one float32 value array over the grid."""
        return 4 * self.n_voxels

    def centers(self, idx: np.ndarray) -> np.ndarray:
        """(..., 3) integer indices -> (..., 3) float64 world centres, metres."""
        return np.asarray(self.min_corner_m) + (np.asarray(idx, dtype=np.float64) + 0.5) * self.voxel_size_m

    def index_of(self, p_W: np.ndarray) -> np.ndarray:
        """(..., 3) world points -> (..., 3) int64 index of the voxel holding each (may be out of range)."""
        q = (np.asarray(p_W, dtype=np.float64) - np.asarray(self.min_corner_m)) / self.voxel_size_m
        return np.floor(q).astype(np.int64)

    def all_centers(self) -> np.ndarray:
        """(nx, ny, nz, 3) float64 world centres of every voxel (allocates; for tests and small grids)."""
        nx, ny, nz = self.shape
        idx = np.stack(np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij"), -1)
        return self.centers(idx)

    def to_dict(self) -> dict:
        return {
            "min_corner_m": list(self.min_corner_m),
            "max_corner_m": list(self.max_corner_m),
            "voxel_size_m": self.voxel_size_m,
        }

    @classmethod
    def from_dict(cls, d: dict) -> GridSpec:
        return cls(tuple(d["min_corner_m"]), tuple(d["max_corner_m"]), d["voxel_size_m"])


def _vec3(v: object, name: str) -> tuple[float, float, float]:
    a = np.asarray(v, dtype=np.float64)
    if a.shape != (3,):
        raise ValueError(f"Expected 3 values for '{name}', but got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"Expected finite values for '{name}', but got {a.tolist()}")
    return (float(a[0]), float(a[1]), float(a[2]))


# voxel indices stay well inside int32 (kernels add block offsets to them)
_MAX_VOXEL_INDEX = 2**30


@dataclass(frozen=True)
class SparseSpec:
    """A block-sparse world grid of cubic voxels.

    Parameters
    ----------
    voxel_size_m : float
        Edge of a cubic voxel, metres.
    bounds : ((3,), (3,)) float or None
        Optional box ``[min, max)`` in the world frame, metres: voxels outside it are never
        mapped, and its min corner is the grid origin (so the map lines up with
        ``GridSpec(min, max, voxel_size_m)`` voxel for voxel). None (default): unbounded, the
        origin at ``origin_m``.
    block : int
        Voxels per block edge (2..32, default 8: blocks of 512 voxels).
    origin_m : (3,) float
        Grid origin of an unbounded map (voxel ``(i, j, k)`` is centred at
        ``origin + (idx + 0.5) * voxel_size_m``, indices may be negative). Default (0, 0, 0);
        must be left out with ``bounds``.
    """

    voxel_size_m: float
    bounds: tuple | None = None
    block: int = 8
    origin_m: tuple | None = None

    def __post_init__(self) -> None:
        s = check_finite_scalar(self.voxel_size_m, "voxel_size_m")
        if s <= 0:
            raise ValueError(f"Expected voxel_size_m > 0, but got {s}")
        b = self.block
        if isinstance(b, bool) or not isinstance(b, (int, np.integer)) or not 2 <= b <= 32:
            raise ValueError(f"Expected block to be an integer in 2..32, but got {b!r}")
        object.__setattr__(self, "voxel_size_m", s)
        object.__setattr__(self, "block", int(b))
        if self.bounds is not None:
            if self.origin_m is not None:
                raise ValueError("Expected origin_m to be left out with bounds (the origin is bounds' min)")
            try:
                lo, hi = self.bounds
            except (TypeError, ValueError) as e:
                raise ValueError(
                    f"Expected bounds as (min_corner_m, max_corner_m), but got {self.bounds!r}"
                ) from e
            lo, hi = _vec3(lo, "bounds[0]"), _vec3(hi, "bounds[1]")
            if any(h <= lo_ for lo_, h in zip(lo, hi, strict=True)):
                raise ValueError(f"Expected bounds with max > min on every axis, but got {lo} and {hi}")
            object.__setattr__(self, "bounds", (lo, hi))
            shape = self.shape
            if max(shape) > _MAX_VOXEL_INDEX:
                raise ValueError(
                    f"Expected at most {_MAX_VOXEL_INDEX} voxels per axis, but bounds {lo}-{hi} at "
                    f"voxel_size_m={s} give {shape}"
                )
        else:
            o = (0.0, 0.0, 0.0) if self.origin_m is None else _vec3(self.origin_m, "origin_m")
            object.__setattr__(self, "origin_m", o)

    @property
    def origin(self) -> tuple[float, float, float]:
        """The grid origin, metres: ``bounds[0]``, or ``origin_m`` for an unbounded map."""
        return self.bounds[0] if self.bounds is not None else self.origin_m

    @property
    def shape(self) -> tuple[int, int, int] | None:
        """Voxels per axis inside ``bounds`` (as :class:`GridSpec` counts them), None if unbounded."""
        if self.bounds is None:
            return None
        s = self.voxel_size_m
        lo, hi = self.bounds
        return tuple(int(math.ceil(round((h - a) / s, 9))) for a, h in zip(lo, hi, strict=True))

    @property
    def grid(self) -> GridSpec | None:
        """The dense :class:`GridSpec` over ``bounds`` (None if unbounded; raises if too large)."""
        return None if self.bounds is None else GridSpec(self.bounds[0], self.bounds[1], self.voxel_size_m)

    def to_dict(self) -> dict:
        return {
            "voxel_size_m": self.voxel_size_m,
            "bounds": None if self.bounds is None else [list(self.bounds[0]), list(self.bounds[1])],
            "block": self.block,
            "origin_m": None if self.bounds is not None else list(self.origin_m),
        }

    @classmethod
    def from_dict(cls, d: dict) -> SparseSpec:
        b = d["bounds"]
        return cls(
            d["voxel_size_m"],
            None if b is None else (tuple(b[0]), tuple(b[1])),
            int(d["block"]),
            None if b is not None else tuple(d["origin_m"]),
        )


def _vec3(v: object, name: str) -> tuple[float, float, float]:
    a = np.asarray(v, dtype=np.float64)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ValueError(f"Expected 3 finite values for '{name}', but got {v!r}")
    return (float(a[0]), float(a[1]), float(a[2]))


def auto_grid(spec: SonarSpec, poses: Iterable[np.ndarray], voxel_size_m: float,
              max_voxels: int = 200_000_000,
              remedy: str = "pass --grid or a larger --voxel-size") -> GridSpec:
    """The box holding every field of view of ``spec`` at ``poses``, padded by one voxel.

    Parameters
    ----------
    spec : SonarSpec
    poses : sequence of (4, 4) float
        ``T_W_S`` of every ping.
    voxel_size_m : float
    max_voxels : int
        Refuse boxes larger than this, saying ``remedy`` (what the caller can change: a command
        names its own flags).
    """
    c = spec.fov_corners_S()
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    for T in poses:
        w = c @ np.asarray(T)[:3, :3].T + np.asarray(T)[:3, 3]
        lo = np.minimum(lo, w.min(0))
        hi = np.maximum(hi, w.max(0))
    lo -= voxel_size_m
    hi += voxel_size_m
    n = np.ceil((hi - lo) / voxel_size_m)
    if float(np.prod(n)) > max_voxels:
        raise ValueError(
            f"Expected an automatic grid of at most {max_voxels} voxels, but the fields of view "
            f"span {np.round(lo, 2).tolist()}..{np.round(hi, 2).tolist()} m = {n.astype(int).tolist()}"
            f" voxels at {voxel_size_m} m: {remedy}"
        )
    return GridSpec(tuple(lo), tuple(hi), voxel_size_m)
