"""Baselines that gpumap is measured against, fed the same pings (bench/README.md tells how each is
built): :class:`PaperSixSteps` (Phung et al., Section II-B, in plain NumPy), :class:`OasisRule` (the
public OASIS hit/observation rule on gpumap's footprints) and :class:`OctoMapBaseline` (pyoctomap fed
each beam's strongest return at elevation 0)."""

from __future__ import annotations

import math

import numpy as np

import gpumap
from gpumap.core.params import MapperParams

__all__ = ["OasisRule", "OctoMapBaseline", "PaperSixSteps", "oasis_occupied", "paper_template_S"]

_F = np.float32


def _as_float_image(image: np.ndarray) -> np.ndarray:
    return image.astype(_F) * _F(1.0 / 255.0) if image.dtype == np.uint8 else np.asarray(image, dtype=_F)


# ------------------------------------------------------------------------------ paper, plain NumPy
def paper_template_S(spec: gpumap.SonarSpec, voxel_size_m: float) -> np.ndarray:
    """(m, 3) float32 voxel template in the sonar frame, with the paper's constraints a-c: a meshgrid at
    the voxel spacing over ``x in [0, r]``, ``|y| <= r sin(hfov/2)``, ``|z| <= r sin(vfov/2)``, keeping
    points with (a) ``|p| < r``, (b) ``|atan(y/x)| < hfov/2`` and (c) ``|atan(z/x)| < vfov/2``."""
    s, r = float(voxel_size_m), spec.range_max_m
    half_h, half_v = 0.5 * spec.hfov_rad, 0.5 * spec.vfov_rad
    ny, nz = math.ceil(r * math.sin(half_h) / s), math.ceil(r * math.sin(half_v) / s)
    X, Y, Z = np.meshgrid(np.arange(0.0, r + s, s), np.arange(-ny, ny + 1) * s, np.arange(-nz, nz + 1) * s,
                          indexing="ij")
    P = np.stack([X.ravel(), Y.ravel(), Z.ravel()], 1)
    x = P[:, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        keep = ((np.linalg.norm(P, axis=1) < r) & (x > 0) & (np.abs(np.arctan(P[:, 1] / x)) < half_h)
                & (np.abs(np.arctan(P[:, 2] / x)) < half_v))
    return np.ascontiguousarray(P[keep], dtype=_F)


def rect_max(image: np.ndarray, b0: np.ndarray, b1: np.ndarray, j0: np.ndarray, j1: np.ndarray,
             budget: int = 1 << 22) -> np.ndarray:
    """Max of ``image`` over each inclusive rectangle ``[b0, b1] x [j0, j1]`` (plain NumPy).

    Rectangles are sorted by area and processed in chunks, each chunk looping over the offsets of its
    own largest rectangle (offsets past a rectangle's end re-read its last cell), so a few wide
    footprints near the sonar do not make every voxel pay for them.
    """
    n = b0.shape[0]
    out = np.empty(n, dtype=_F)
    hb, wj = b1 - b0 + 1, j1 - j0 + 1
    order = np.argsort(hb * wj, kind="stable")
    area, start = (hb * wj)[order], 0
    while start < n:  # grow the chunk while chunk_len * max_area stays within the budget
        a = int(area[min(n - 1, start + 1023)])
        stop = max(min(n, start + max(1024, budget // max(a, 1))), start + 1)
        sel = order[start:stop]
        cb0, cb1, cj0, cj1 = b0[sel], b1[sel], j0[sel], j1[sel]
        acc = np.full(sel.shape[0], -np.inf, dtype=_F)
        for db in range(int(hb[sel].max())):
            rows = np.minimum(cb0 + db, cb1)
            for dj in range(int(wj[sel].max())):
                np.maximum(acc, image[rows, np.minimum(cj0 + dj, cj1)], out=acc)
        out[sel] = acc
        start = stop
    return out


class PaperSixSteps:
    """The paper's min-max filter in plain NumPy, as a user would write it from its text: a voxel
    template in the sonar frame built once, then per ping (1) template to world, (2) nearest grid voxel
    index (``round``; invalid ones dropped), (3) back to the voxel centres, (4) to the sonar frame, (5)
    max intensity over the bins x beams rectangle the voxel's 8 projected corners span, (6) update with
    the *minimum* (the method the paper names; its Step 6 formula reads ``max(M, I)``). Field-of-view
    constraints are the paper's own, not gpumap's."""

    _CORNERS = np.array([[i, j, k] for i in (-0.5, 0.5) for j in (-0.5, 0.5) for k in (-0.5, 0.5)])

    def __init__(self, spec: gpumap.SonarSpec, grid: gpumap.GridSpec) -> None:
        self.spec, self.grid = spec, grid
        self.template_S = paper_template_S(spec, grid.voxel_size_m).astype(np.float64)
        self.grid_values = np.full(grid.shape, np.inf, dtype=_F)  # +inf = uninitialised
        self._edges = np.asarray(spec.beam_edges_rad, dtype=np.float64)
        self._c0 = np.asarray(grid.min_corner_m) + 0.5 * grid.voxel_size_m  # centre of voxel (0, 0, 0)

    def integrate(self, image: np.ndarray, T_W_S: np.ndarray) -> None:
        """Fuse one ping ((n_bins, n_beams) float in [0, 1] or uint8) at pose ``T_W_S``."""
        img, sp, s, edges = _as_float_image(image), self.spec, self.grid.voxel_size_m, self._edges
        R, t = T_W_S[:3, :3], T_W_S[:3, 3]
        q = np.round((self.template_S @ R.T + t - self._c0) / s).astype(np.int64)  # steps 1-2
        q = q[np.all((q >= 0) & (q < np.array(self.grid.shape)), axis=1)]
        c_S = (self._c0 + q * s - t) @ R  # steps 3-4
        corners = c_S[:, None, :] + (self._CORNERS * s) @ R  # step 5: world-axis cube corners, sonar frame
        rng, az = np.linalg.norm(corners, axis=2), np.arctan2(corners[..., 1], corners[..., 0])
        r_lo, r_hi, a_lo, a_hi = rng.min(1), rng.max(1), az.min(1), az.max(1)
        wrap = (a_hi - a_lo) > math.pi  # voxel around the sonar's origin: every beam
        a_lo, a_hi = np.where(wrap, edges[0], a_lo), np.where(wrap, edges[-1], a_hi)
        ok = (r_hi >= sp.range_min_m) & (r_lo < sp.range_max_m) & (a_hi >= edges[0]) & (a_lo <= edges[-1])
        q, r_lo, r_hi, a_lo, a_hi = q[ok], r_lo[ok], r_hi[ok], a_lo[ok], a_hi[ok]

        def bins(r):
            return np.clip(np.floor((r - sp.range_min_m) / sp.bin_size_m).astype(np.int64), 0, sp.n_bins - 1)

        def beams(a):
            return np.clip(np.searchsorted(edges, a, side="right") - 1, 0, sp.n_beams - 1)

        value = rect_max(img, bins(r_lo), bins(r_hi), beams(a_lo), beams(a_hi))
        idx = (q[:, 0], q[:, 1], q[:, 2])  # step 6: min-max update (duplicates carry the same value)
        self.grid_values[idx] = np.minimum(self.grid_values[idx], value)

    def values(self) -> np.ndarray:
        """(nx, ny, nz) float32 copy, NaN = never observed."""
        v = self.grid_values.copy()
        v[np.isinf(v)] = np.nan
        return v


# ------------------------------------------------------------------------------ OASIS rule
def oasis_occupied(hits: np.ndarray, observations: np.ndarray, fnr: float) -> np.ndarray:
    """OASIS decision: occupied when ``hits / observations > 1 - fnr``. ``fnr = 0`` is taken as the
    limit ``fnr -> 0+``: occupied when every observation hit (strict min-max thresholding).
    Never-observed voxels are not occupied."""
    if not 0.0 <= fnr < 1.0:
        raise ValueError(f"Expected 0 <= fnr < 1, but got {fnr}")
    h, o = np.asarray(hits, dtype=np.int64), np.asarray(observations, dtype=np.int64)
    return (o > 0) & (h == o) if fnr == 0.0 else h > (1.0 - fnr) * o


class OasisRule:
    """Hit / observation counting with the OASIS decision rule, on gpumap's footprints: each ping goes
    into a fresh gpumap grid (``backend``, ``method``) for its per-voxel footprint maximum; a voxel is
    observed when that grid observes it, and hit when the maximum reaches ``threshold``."""

    def __init__(self, spec: gpumap.SonarSpec, grid: gpumap.GridSpec, threshold: float = 0.1,
                 fnr: float = 0.5, backend: str = "auto", method: str = "gather") -> None:
        self.threshold, self.fnr, self.grid = float(threshold), float(fnr), grid
        self.mapper = gpumap.MinMaxMapper(spec, grid, backend, MapperParams(method=method, rule="plain"))
        self.hits = np.zeros(grid.shape, dtype=np.uint16)
        self.observations = np.zeros(grid.shape, dtype=np.uint16)

    def integrate(self, image: np.ndarray, T_W_S: np.ndarray) -> None:
        """Count one ping's observations and hits."""
        self.mapper.reset()
        self.mapper.integrate(image, T_W_S)
        v = self.mapper.raw_values()
        seen = np.isfinite(v)
        self.observations += seen
        self.hits += seen & (v >= np.float32(self.threshold))

    def occupied(self, fnr: float | None = None) -> np.ndarray:
        """(nx, ny, nz) bool, with this rule's ``fnr`` unless another is given."""
        return oasis_occupied(self.hits, self.observations, self.fnr if fnr is None else fnr)

    def values(self, fnr: float | None = None) -> np.ndarray:
        """(nx, ny, nz) float32: 1 occupied, 0 free, NaN never observed (score at threshold 0.5)."""
        v = self.occupied(fnr).astype(_F)
        v[self.observations == 0] = np.nan
        return v


# ------------------------------------------------------------------------------ OctoMap
class OctoMapBaseline:
    """OctoMap as it is used with imaging sonars: each beam's strongest return at or above
    ``threshold`` becomes a point at elevation 0, inserted with rays from the sonar origin; the octree
    is aligned with the benchmark grid, so its leaves are the grid's voxels. ``prob_hit`` /
    ``prob_miss``: OctoMap's sensor model (its defaults, 0.7 / 0.4, when not given)."""

    def __init__(self, spec: gpumap.SonarSpec, grid: gpumap.GridSpec, threshold: float = 0.1,
                 prob_hit: float | None = None, prob_miss: float | None = None) -> None:
        import pyoctomap  # optional dependency: fails here, at first use, with the original error

        self.spec, self.grid, self.threshold = spec, grid, float(threshold)
        self.tree = pyoctomap.OcTree(float(grid.voxel_size_m))
        if prob_hit is not None:
            self.tree.setProbHit(prob_hit)
        if prob_miss is not None:
            self.tree.setProbMiss(prob_miss)
        self._shift = -np.asarray(grid.min_corner_m, dtype=np.float64)
        b = np.asarray(spec.bearings_rad)
        self._dirs_S = np.stack([np.cos(b), np.sin(b), np.zeros_like(b)], 1)
        self._ranges = spec.bin_centers_m

    def beam_points_W(self, image: np.ndarray, T_W_S: np.ndarray) -> np.ndarray:
        """(m, 3) world points: each beam's strongest return above the threshold, elevation 0."""
        img = _as_float_image(image)
        j = np.argmax(img, axis=0)
        keep = img[j, np.arange(img.shape[1])] >= self.threshold
        return (self._ranges[j[keep], None] * self._dirs_S[keep]) @ T_W_S[:3, :3].T + T_W_S[:3, 3]

    def integrate(self, image: np.ndarray, T_W_S: np.ndarray) -> None:
        """Insert one ping's beam points with rays from the sonar origin."""
        pts = self.beam_points_W(image, T_W_S)
        if len(pts):
            self.tree.insertPointCloud(np.ascontiguousarray(pts + self._shift),
                                       np.asarray(T_W_S[:3, 3] + self._shift, dtype=np.float64),
                                       max_range=float(self.spec.range_max_m))

    def values(self) -> np.ndarray:
        """(nx, ny, nz) float32 on the benchmark grid: 1 occupied, 0 free, NaN unknown."""
        out = np.full(self.grid.shape, np.nan, dtype=_F)
        res, dims = self.grid.voxel_size_m, np.array(self.grid.shape)
        for leaf in self.tree.begin_leafs():
            c, size = np.asarray(leaf.getCoordinate(), dtype=np.float64), float(leaf.getSize())
            lo = np.round((c - 0.5 * size) / res).astype(np.int64)
            lo, hi = np.maximum(lo, 0), np.minimum(lo + int(round(size / res)), dims)
            if np.all(hi > lo):
                occ = self.tree.isNodeOccupied(leaf.current_node)
                out[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]] = 1.0 if occ else 0.0
        return out
