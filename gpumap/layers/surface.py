"""The surface layer: every bright cell of every training ping explained by one voxel of the evidence map.

An imaging sonar measures range and azimuth but not elevation: a bright cell (range cell, beam) of
a ping says that *something* lies on its **elevation arc** (the points at that range and azimuth,
anywhere in the vertical aperture). Every occupancy rule built from such pings, the evidence rule
included, marks the whole arc wherever the other views cannot prove it empty: phantoms in front of
surfaces. The surface layer keeps the evidence rule's occupied voxels as *candidates* (it never
calls a voxel the evidence rule carved or never observed) and asks each bright cell of each
training ping to be explained by **exactly one** of them.

1. **Cells.** Per ping, each candidate spans the cells its own width covers: range cells of
   ``cell_m`` (half a voxel) within half an edge of its centre's range, and the beams its width
   spans in azimuth (neighbouring voxels tile the fan; a voxel's wider footprint sphere, which the
   mapper takes its max over, would let every range neighbour claim the same cells). The arc is
   taken ``aperture_scale`` times wider than the nominal aperture: the nominal vertical aperture is
   the -3 dB width and a bright surface just outside it still returns (measured on the simulator:
   the first bright bin lies 1.5-3 voxels nearer than any surface inside the nominal fan), so a
   voxel there may explain the cell rather than one in the water inside the fan.
2. **First returns.** A candidate that lies, inside a training ping's nominal fan, more than
   ``front_tolerance_m`` nearer than its beam's first bright bin (clear water there in that ping;
   a beam without any return counts as clear only in a ping that returns on at least
   ``live_ping_share`` of its beams, not in a dim or dropped one) in more than
   ``max_front_share`` of the pings whose fan holds it, takes no part.
3. **Weights** by expectation-maximisation (the emission-tomography update, bright cells as the
   data): each bright cell shares its one unit of explanation among the candidates spanning it in
   proportion to their weights; a candidate's new weight is what it collected over every ping
   divided by the cells it spans in every ping that sees it, dark ones included. A voxel that is
   bright wherever it is seen gathers weight; one on the arcs of other surfaces only by chance
   loses it to them.
4. **Votes.** Each bright cell of each ping goes to the heaviest candidate spanning it (ties by
   index: exactly one); a candidate winning a cell of a ping gets that ping's vote. With
   ``passes`` > 1 every later pass drops, per ping, the candidates lying more than
   ``occlusion_m`` behind a previous winner of the same beam and elevation cell (its acoustic
   shadow) and runs 3-4 again.
5. The **surface** is the candidates with at least ``min_votes`` votes, grown by ``band_voxels``
   (26-neighbourhood) into the candidates that step 2 kept: a voxelised surface crosses one to
   three voxels per column while each cell elects one, so a band of one voxel gives the surface
   its thickness without reaching the phantoms further out on the arcs.

Use: :func:`surface_from_mapper` (a mapper and the pings it integrated), :func:`surface_from_evidence`
(the evidence rule's decision and the pings), :func:`surface_from_frames` (pings streamed once, e.g.
from a recording), :class:`LiveSurface` (a live mapper's layer: pings added per batch as the mapper
integrates them, the layer updated whenever wanted; ``gpumap replay`` and the ROS node use it). The
candidates come through the mapper's own decision (:func:`map_candidates`), so the layer follows
whatever it decides. :meth:`SurfaceLayer.save` writes the layer beside the
safe map as a refined map file (``gpumap view`` / ``gpumap export --layer surface|safe`` read it).

What it gets and misses (``python -m bench.surface``): on the simulated scenes it keeps the
objects (FN of the objects' detectable surfaces 0.4-1.9 %) and halves the evidence map's far
phantoms, but stays above half the visible rule's on the tank and the side sweep, and object tops
remain 1-10 voxels high where the views never separate the elevations; with the real tank's ping
to ping variation the candidates' weights are too noisy and it misses half the surfaces. Everything
here is NumPy. :func:`_layer` is the plain version (every cell of every voxel listed, a loop over the
pings per step): the oracle. :class:`_Pairs` (what :class:`LiveSurface` runs) works out each (ping,
voxel) once and runs steps 3-4 over every ping at once, adding the same numbers in the same order, so
its layer is the oracle's bit for bit; its memory is 17 bytes per (ping, voxel, bright cell) pair
(about 30 million on the real tank's 1,223 pings at 5 cm) and an update's passes are linear in them
(``python -m bench surface_rate``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np

from gpumap.geometry import beam_tan_edges
from gpumap.reference import _F, beam_span
from gpumap.spec import GridSpec, SonarSpec

__all__ = ["SURFACE_LEVEL", "SurfaceLayer", "SurfaceOptions", "surface_from_evidence", "surface_from_frames"]

#: The surface layer's values are 1 (surface) or 0: occupied from this level.
SURFACE_LEVEL = 0.5


@dataclass(frozen=True)
class SurfaceOptions:
    """Settings of the surface layer (module docstring, steps 1-5). The defaults were chosen on the
    real tank's frames 0-599 judged on 600-799 (never on the held-out frames 800-1222) and checked
    on the simulated side, tank and circle scenes (``python -m bench.surface``).

    passes : int
        Voting passes; every pass after the first drops the candidates occluded by the previous
        pass's surface (1: no occlusion test; measured: the test costs the side sweep's objects).
    iterations : int
        Expectation-maximisation steps per pass (0: every candidate weighs the same).
    min_votes : int
        Votes a candidate needs to be surface.
    aperture_scale : float
        The arc's elevation extent over the nominal vertical aperture (>= 1).
    cell_m : float or None
        Range cell of the vote, metres (None: half a voxel). The beams are the sonar's own.
    occlusion_m : float or None
        A winner occludes a candidate of the same beam and elevation cell when it lies more than
        this nearer, metres (None: two voxels).
    elevation_cells : int
        Elevation cells across the arc's aperture for the occlusion test.
    max_front_share : float
        Largest share of the pings holding a candidate in their nominal fan in which it may lie in
        front of the first return (1: no such test).
    band_voxels : int
        Voxels (26-neighbourhood steps) the winners grow into the kept candidates (0: winners only).
    front_tolerance_m : float or None
        How much nearer than the first return counts as in front, metres (None: one voxel).
    live_ping_share : float
        A beam without a return counts as clear water (every voxel in its fan in front) only in a
        ping with a return in at least this share of its beams; in a dimmer ping (a low gain, a
        dropped ping: real sonars vary ping to ping) it says nothing.
    """

    passes: int = 1
    iterations: int = 5
    min_votes: int = 1
    aperture_scale: float = 1.5
    cell_m: float | None = None
    occlusion_m: float | None = None
    elevation_cells: int = 48
    max_front_share: float = 0.25
    band_voxels: int = 1
    front_tolerance_m: float | None = None
    live_ping_share: float = 0.1

    def to_dict(self) -> dict:
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}

    def __post_init__(self) -> None:
        for name in ("passes", "min_votes", "elevation_cells", "iterations", "band_voxels"):
            v = getattr(self, name)
            low = 0 if name in ("iterations", "band_voxels") else 1
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < low:
                raise ValueError(f"Expected an integer >= {low} for {name!r}, but got {v!r}")
        if not (np.isfinite(self.aperture_scale) and self.aperture_scale >= 1.0):
            raise ValueError(f"Expected aperture_scale >= 1, but got {self.aperture_scale}")
        for name in ("max_front_share", "live_ping_share"):
            if not (0.0 <= getattr(self, name) <= 1.0):
                raise ValueError(f"Expected {name} in [0, 1], but got {getattr(self, name)}")
        for name in ("cell_m", "occlusion_m", "front_tolerance_m"):
            v = getattr(self, name)
            if v is not None and not (np.isfinite(v) and v > 0):
                raise ValueError(f"Expected {name} > 0 (metres) or None, but got {v}")


@dataclass
class SurfaceLayer:
    """The surface layer of a map over ``grid``.

    surface : (nx, ny, nz) bool
        Surface voxels (a subset of ``candidates``).
    candidates : (nx, ny, nz) bool
        The evidence rule's occupied voxels the layer chose from.
    observed : (nx, ny, nz) bool
        Voxels some view observed (the safe map's observed set): the layer calls the others unknown.
    votes : (nx, ny, nz) uint32
        Pings whose arcs the voxel won (last pass).
    views, bright_views : (nx, ny, nz) uint32
        Views observing each candidate, and of them the bright ones (0 off the candidates).
    grid : GridSpec
    stats : dict
        Counts and settings (JSON-ready).
    """

    surface: np.ndarray
    candidates: np.ndarray
    observed: np.ndarray
    votes: np.ndarray
    views: np.ndarray
    bright_views: np.ndarray
    grid: GridSpec
    stats: dict = field(default_factory=dict)

    def values(self) -> np.ndarray:
        """(nx, ny, nz) float32 map values: 1 surface, 0 observed and not surface, NaN never observed
        (occupied from :data:`SURFACE_LEVEL`, as :func:`gpumap.sim.metrics.evaluate` and
        :func:`gpumap.layers.first_return.first_return_score` read maps)."""
        out = np.where(self.observed, np.float32(0.0), np.float32(np.nan)).astype(np.float32)
        out[self.surface] = 1.0
        return out

    def to_refined(self, map_values: np.ndarray, spec: SonarSpec, threshold: float, rule: str = "evidence"):
        """The two layers as a :class:`gpumap.layers.refined_map.RefineResult`: ``occupancy`` the surface
        layer
        (:meth:`values`), ``map_values`` the safe map's values ((nx, ny, nz) float32, NaN unknown, occupied
        from ``threshold``), so that the refined map file's readers (``gpumap view``, ``gpumap export``,
        :func:`gpumap.layers.refined_map.load_refined`) show either (``--layer surface|safe``)."""
        from gpumap.layers.refined_map import RefineResult

        v = np.asarray(map_values, np.float32)
        if v.shape != self.surface.shape:
            raise ValueError(f"Expected map_values of shape {self.surface.shape}, but got {v.shape}")
        occ = self.values()
        share = np.where(self.views > 0, self.bright_views / np.maximum(self.views, 1), np.nan)
        return RefineResult(occ, share.astype(np.float32), np.full(occ.shape, np.nan, np.float32),
                            self.candidates & ~self.surface, np.zeros(occ.shape, bool), 1.0, 0.0, [],
                            {"method": "surface", **self.stats}, field=occ, threshold=float(threshold),
                            rule=rule, map_values=v, spec=spec, grid=self.grid)

    def save(self, path, map_values: np.ndarray, spec: SonarSpec, threshold: float, rule: str = "evidence"):
        """Write both layers as a refined map file (:meth:`to_refined`, then
        :meth:`gpumap.layers.refined_map.RefineResult.save`); returns its path."""
        return self.to_refined(map_values, spec, threshold, rule).save(path)


# ------------------------------------------------------------------------------ per ping geometry
def _check(images: np.ndarray, poses: np.ndarray, spec: SonarSpec) -> tuple[np.ndarray, np.ndarray]:
    images = np.asarray(images)
    poses = np.asarray(poses, np.float64)
    if images.ndim != 3 or images.shape[1:] != spec.image_shape:
        raise ValueError(f"Expected images of shape (n, {spec.image_shape[0]}, {spec.image_shape[1]}), "
                         f"but got {images.shape}")
    if poses.shape != (len(images), 4, 4):
        raise ValueError(f"Expected poses of shape ({len(images)}, 4, 4), but got {poses.shape}")
    if images.dtype not in (np.uint8, np.float32, np.float64):
        raise TypeError(f"Expected images of dtype uint8, float32 or float64, but got {images.dtype}")
    if not np.all(np.isfinite(poses)):
        raise ValueError("Expected finite poses, but got NaN or inf")
    return images, poses


def _lit_cells(image: np.ndarray, spec: SonarSpec, threshold: float, cell_m: float) -> np.ndarray:
    """(n_cells, n_beams) bool: range cells of ``cell_m`` (from ``range_min``) holding a bin ``>=
    threshold`` (uint8 images compared after scaling by 1/255, as the mapper does)."""
    n_cells = int(np.ceil((spec.range_max_m - spec.range_min_m) / cell_m)) + 1
    img = image.astype(_F) * _F(1.0 / 255.0) if image.dtype == np.uint8 else np.asarray(image, _F)
    b, j = np.nonzero(img >= np.float32(threshold))
    lit = np.zeros((n_cells, spec.n_beams), bool)
    lit[((b + 0.5) * spec.bin_size_m / cell_m).astype(np.int64), j] = True
    return lit


@dataclass
class _View:
    """One ping's view of the candidates (those within the arc's aperture): their index, range,
    elevation, centre beam and the bright cells they span (``pair`` into ``cand``, flat ``cell``)."""

    cand: np.ndarray  # (k,) int32 candidate index
    r: np.ndarray | None  # (k,) float32 range, m (None: not kept, no occlusion test)
    elev: np.ndarray | None  # (k,) float32 elevation, rad
    j0: np.ndarray | None  # (k,) int32 beams the voxel spans (its own width)
    j1: np.ndarray | None
    n_cells: np.ndarray  # (k,) int32 cells the voxel spans
    pair: np.ndarray  # (p,) int32 into cand
    cell: np.ndarray  # (p,) int32 flat (range cell, beam)
    front: np.ndarray | None  # (k,) bool: in the nominal fan and nearer than its beam's first return


def _in_sonar(T_W_S: np.ndarray, centres_W: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """x, y, z (k,) float64 each: ``centres_W`` ((k, 3)) in the sonar frame, ``R^T (c - t)``, written out
    element by element so that a voxel's coordinates never depend on which other voxels came with it
    (a matrix product's kernel may sum in another order for another number of rows)."""
    T = np.asarray(T_W_S, np.float64)
    d0, d1, d2 = (centres_W[:, i] - T[i, 3] for i in range(3))
    return tuple(d0 * T[0, a] + d1 * T[1, a] + d2 * T[2, a] for a in range(3))


def _geometry(spec: SonarSpec, edges: np.ndarray, T_W_S: np.ndarray, centres_W: np.ndarray, n_rc: int,
              half_m: float, cell_m: float, half_elev_rad: float, first_m: np.ndarray, front_tol_m: float):
    """The voxels within the arc's aperture in one ping (module docstring, steps 1-2): their index
    ``k`` into ``centres_W``, range, elevation, the beams ``j0..j1`` and range cells ``c0..c1`` their
    width spans, and whether they lie in the nominal fan nearer than their beam's first return.

    A cheap test (ahead of the sonar, inside its range and its aperture's slab, with a margin)
    drops most voxels first; the exact tests then run on the rest, each voxel's numbers the same."""
    x, y, z = _in_sonar(T_W_S, centres_W)
    h2 = x * x + y * y
    near = (x > 0) & (h2 + z * z < (spec.range_max_m * (1.0 + 1e-6)) ** 2)
    if half_elev_rad < 1.5:  # the aperture's slab, |z| <= tan(half) h, with a margin
        lim = np.tan(half_elev_rad) * (1.0 + 1e-6)
        near &= z * z <= lim * lim * h2 + 1e-12
    k = np.flatnonzero(near)
    x, y, z, h2 = x[k], y[k], z[k], h2[k]
    r = np.sqrt(h2 + z ** 2)
    elev = np.arctan2(z, np.sqrt(h2))
    t = y / x
    tan_e = np.tan(np.asarray(spec.beam_edges_rad, np.float64))
    ok = ((r >= spec.range_min_m) & (r < spec.range_max_m) & (np.abs(elev) <= half_elev_rad)
          & (t >= tan_e[0]) & (t <= tan_e[-1]))
    sel = np.flatnonzero(ok)
    k, r, elev = k[sel], r[sel], elev[sel]
    j0, j1 = beam_span(t[sel].astype(_F), h2[sel].astype(_F), _F(half_m), edges, spec.n_beams)
    c0 = np.clip(((r - half_m - spec.range_min_m) / cell_m).astype(np.int64), 0, n_rc - 1)
    c1 = np.clip(((r + half_m - spec.range_min_m) / cell_m).astype(np.int64), 0, n_rc - 1)
    first = first_m[(j0 + j1) // 2]  # inf: no return (open water), nan: says nothing (a dim ping)
    front = (np.abs(elev) <= 0.5 * spec.vfov_rad) & (r < first - front_tol_m)
    return k, r, elev, j0.astype(np.int64), j1.astype(np.int64), c0, c1, front


def _view(spec: SonarSpec, edges: np.ndarray, T_W_S: np.ndarray, centres_W: np.ndarray, lit: np.ndarray,
          half_m: float, cell_m: float, half_elev_rad: float, first_m: np.ndarray, front_tol_m: float
          ) -> _View:
    """The candidates' geometry in one ping and the bright cells each spans (module docstring, step 2):
    in range ``[r - half_m, r + half_m]`` (range cells of ``cell_m``) and the beams its width ``2 half_m``
    spans in azimuth, for the voxels within ``+-half_elev_rad`` of the fan's plane. Every cell of every
    voxel is listed, then the dark ones dropped: the plain version :class:`_Pairs` is checked against."""
    n_rc = lit.shape[0]
    k, r, elev, j0, j1, c0, c1, front = _geometry(spec, edges, T_W_S, centres_W, n_rc, half_m, cell_m,
                                                  half_elev_rad, first_m, front_tol_m)
    nc, nj = c1 - c0 + 1, j1 - j0 + 1
    tot = nc * nj
    pair = np.repeat(np.arange(len(k)), tot)
    off = np.arange(int(tot.sum())) - np.repeat(np.cumsum(tot) - tot, tot)
    cc = c0[pair] + off // nj[pair]
    jj = j0[pair] + off % nj[pair]
    keep = lit[cc, jj]
    return _View(k.astype(np.int32), r.astype(_F), elev.astype(_F), j0.astype(np.int32),
                 j1.astype(np.int32), tot.astype(np.int32), pair[keep].astype(np.int32),
                 (cc * spec.n_beams + jj)[keep].astype(np.int32), front)


def _bright_pairs(lit: np.ndarray, n_rc: int, n_beams: int, j0: np.ndarray, j1: np.ndarray, c0: np.ndarray,
                  c1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The bright cells each voxel spans, found without listing its dark ones: ``lit`` holds one
    ping's bright cells (sorted flat (range cell, beam) indices), so those in a range cell's beams
    ``j0..j1`` are one run of it, whose ends a table of running counts per range cell gives. Returns
    (voxel (p,), index into ``lit`` (p,)), voxel by voxel and cell by cell in flat order, as
    :func:`_view` lists them."""
    k = len(j0)
    rows = int((c1 - c0).max()) + 1 if k else 0
    mask = np.zeros(n_rc * n_beams, np.int32)
    mask[lit] = 1
    run = np.zeros((n_rc, n_beams + 1), np.int64)
    np.cumsum(mask.reshape(n_rc, n_beams), axis=1, out=run[:, 1:])
    before = np.concatenate([[0], np.cumsum(run[:, -1])[:-1]])  # bright cells in the earlier range cells
    cc = np.minimum(c0[:, None] + np.arange(rows)[None, :], n_rc - 1)  # (k, rows)
    lo = before[cc] + run[cc, j0[:, None]]
    cnt = np.where(c0[:, None] + np.arange(rows)[None, :] <= c1[:, None],
                   before[cc] + run[cc, j1[:, None] + 1] - lo, 0).reshape(-1)
    n = int(cnt.sum())
    start = np.cumsum(cnt) - cnt
    which = np.repeat(np.arange(cnt.size), cnt)
    at = lo.reshape(-1)[which] + (np.arange(n) - start[which])
    return which // max(rows, 1), at


def _occluded(view: _View, surface: np.ndarray, n_beams: int, half_elev_rad: float, n_elev: int,
              occlusion_m: float, half_m: float) -> np.ndarray:
    """(k,) bool over the view's candidates: lying more than ``occlusion_m`` behind a ``surface``
    voxel ((m,) bool over every candidate) of the same beam and elevation cell (``n_elev`` cells
    across ``+-half_elev_rad``; each surface voxel fills the cells its width, ``2 half_m``, spans)."""
    depth = np.full((n_elev, n_beams), np.inf)
    occ = np.flatnonzero(surface[view.cand])
    scale = n_elev / (2.0 * half_elev_rad)
    if len(occ):
        r = view.r[occ].astype(np.float64)
        e = view.elev[occ].astype(np.float64) + half_elev_rad
        e_lo = np.clip(((e - half_m / r) * scale).astype(np.int64), 0, n_elev - 1)
        e_hi = np.clip(((e + half_m / r) * scale).astype(np.int64), 0, n_elev - 1)
        j0, j1 = view.j0[occ].astype(np.int64), view.j1[occ].astype(np.int64)
        ne, nj = e_hi - e_lo + 1, j1 - j0 + 1
        tot = ne * nj
        pair = np.repeat(np.arange(len(occ)), tot)
        off = np.arange(int(tot.sum())) - np.repeat(np.cumsum(tot) - tot, tot)
        np.minimum.at(depth, (e_lo[pair] + off // nj[pair], j0[pair] + off % nj[pair]), r[pair])
    e = np.clip(((view.elev + half_elev_rad) * scale).astype(np.int64), 0, n_elev - 1)
    jc = (view.j0.astype(np.int64) + view.j1) // 2
    return depth[e, jc] < view.r - occlusion_m


def _explain(views: list[_View], n: int, n_cells: int, occluders: np.ndarray | None, spec: SonarSpec,
             half_elev_rad: float, n_elev: int, occlusion_m: float, half_m: float, iterations: int,
             alive: np.ndarray, w0: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One pass: weights by expectation-maximisation, then the votes (module docstring, steps 3-4).

    Returns (weights (n,) float64, votes (n,) uint32, bright views (n,) uint32)."""
    keep = []
    sens = np.zeros(n)
    bright = np.zeros(n, np.uint32)
    for v in views:
        ok = np.ones(len(v.cand), bool) if occluders is None else ~_occluded(
            v, occluders, spec.n_beams, half_elev_rad, n_elev, occlusion_m, half_m)
        ok &= alive[v.cand]
        sens += np.bincount(v.cand[ok], weights=v.n_cells[ok], minlength=n)
        m = ok[v.pair]
        cand = v.cand[v.pair[m]]
        bright[np.unique(cand)] += 1
        keep.append((cand, v.cell[m]))
    w = np.where(bright > 0, 1.0 if w0 is None else w0, 0.0)
    for _ in range(int(iterations)):
        acc = np.zeros(n)
        for cand, cell in keep:
            den = np.bincount(cell, weights=w[cand], minlength=n_cells)
            acc += np.bincount(cand, weights=w[cand] / np.where(den[cell] > 0, den[cell], 1.0), minlength=n)
        w = acc / np.maximum(sens, 1.0)
    votes = np.zeros(n, np.uint32)
    # strict order for the hard assignment: weight, then index
    rank = np.empty(n, np.int64)
    rank[np.lexsort((np.arange(n), w))] = np.arange(1, n + 1)
    for cand, cell in keep:
        if not len(cand):
            continue
        best = np.zeros(n_cells, np.int64)
        np.maximum.at(best, cell, rank[cand])
        votes[np.unique(cand[best[cell] == rank[cand]])] += 1
    return w, votes, bright


# ------------------------------------------------------------------------------ the layer
def surface_from_evidence(
    candidates: np.ndarray,
    observed: np.ndarray,
    grid: GridSpec,
    spec: SonarSpec,
    images: np.ndarray,
    poses: np.ndarray,
    threshold: float,
    options: SurfaceOptions | None = None,
) -> SurfaceLayer:
    """The surface layer of an evidence map from the pings that built it.

    Parameters
    ----------
    candidates : (nx, ny, nz) bool
        The evidence rule's occupied voxels (:func:`gpumap.reference.evidence_occupied`).
    observed : (nx, ny, nz) bool
        Voxels the map observed.
    grid : GridSpec
        The map's grid.
    spec : SonarSpec
    images : (n, n_bins, n_beams) uint8 (scaled by 1/255) or float32 in [0, 1]
        The training pings (those the map integrated).
    poses : (n, 4, 4) float64
        Their ``T_W_S``.
    threshold : float
        Bright intensity, the map's threshold.
    options : SurfaceOptions, optional

    Returns
    -------
    SurfaceLayer
    """
    images, poses = _check(images, poses, spec)
    return surface_from_frames(candidates, observed, grid, spec, zip(images, poses, strict=True), threshold,
                               options)


def surface_from_frames(
    candidates: np.ndarray,
    observed: np.ndarray,
    grid: GridSpec,
    spec: SonarSpec,
    frames: Iterable[tuple[np.ndarray, np.ndarray]],
    threshold: float,
    options: SurfaceOptions | None = None,
) -> SurfaceLayer:
    """:func:`surface_from_evidence` of ``frames``, (image (n_bins, n_beams), ``T_W_S`` (4, 4)) pairs
    read once each (a recording streamed from disk: only the cells each ping lights are kept)."""
    import time

    opts = options or SurfaceOptions()
    cand = np.asarray(candidates)
    obs = np.asarray(observed)
    shape = tuple(grid.shape)
    for name, a in (("candidates", cand), ("observed", obs)):
        if a.shape != shape or a.dtype != bool:
            raise ValueError(f"Expected a bool array of the grid's shape {shape} for {name!r}, but got "
                             f"{a.dtype} {a.shape}")
    if not (np.isfinite(threshold) and 0.0 < threshold <= 1.0):
        raise ValueError(f"Expected threshold in (0, 1], but got {threshold}")
    t0 = time.perf_counter()
    cell_m = opts.cell_m or 0.5 * grid.voxel_size_m
    pings = [_prepare(img, T, spec, threshold, cell_m, opts.live_ping_share) for img, T in frames]
    layer, _ = _layer(cand, obs, grid, spec, pings, opts)
    layer.stats["seconds"] = time.perf_counter() - t0
    return layer


@dataclass
class _PingCells:
    """What the layer keeps of one ping: its bright cells (flat (range cell, beam) indices, int32),
    each beam's first return (float32, m; inf none, NaN says nothing: a dim ping) and ``T_W_S``."""

    lit: np.ndarray
    first: np.ndarray
    T_W_S: np.ndarray


def _prepare(image: np.ndarray, T_W_S: np.ndarray, spec: SonarSpec, threshold: float, cell_m: float,
             live_ping_share: float) -> _PingCells:
    from gpumap.layers.first_return import measured_first_returns

    img, T = _check(np.asarray(image)[None], np.asarray(T_W_S, np.float64)[None], spec)
    img, T = img[0], T[0]
    lit = np.flatnonzero(_lit_cells(img, spec, threshold, cell_m)).astype(np.int32)
    fimg = img.astype(_F) * _F(1.0 / 255.0) if img.dtype == np.uint8 else np.asarray(img, _F)
    first = measured_first_returns(fimg, spec, threshold)
    if np.isfinite(first).mean() < live_ping_share:  # a dim or dropped ping: its empty beams
        first = np.where(np.isfinite(first), first, np.nan)  # say nothing about the water
    return _PingCells(lit, first.astype(np.float32), T)


def _scales(grid: GridSpec, spec: SonarSpec, opts: SurfaceOptions) -> dict:
    """The layer's lengths and sizes from the grid, the sonar and the options."""
    s = grid.voxel_size_m
    cell_m = opts.cell_m or 0.5 * s
    n_rc = int(np.ceil((spec.range_max_m - spec.range_min_m) / cell_m)) + 1
    return {"half": 0.5 * s, "cell_m": cell_m, "occl_m": opts.occlusion_m or 2.0 * s,
            "front_tol": opts.front_tolerance_m or s, "half_el": 0.5 * spec.vfov_rad * opts.aperture_scale,
            "n_rc": n_rc, "n_cells": n_rc * spec.n_beams}


def _layer(cand: np.ndarray, obs: np.ndarray, grid: GridSpec, spec: SonarSpec, pings: list[_PingCells],
           opts: SurfaceOptions, w0: np.ndarray | None = None) -> tuple[SurfaceLayer, np.ndarray]:
    """The layer of candidates ``cand`` from prepared pings (steps 1-5); also the weights (n,) of the
    candidates in ``np.argwhere(cand)`` order. ``w0``: starting weights in that order (warm start)."""
    idx = np.argwhere(cand)
    n = len(idx)
    centres = np.asarray(grid.min_corner_m, np.float64) + (idx + 0.5) * grid.voxel_size_m
    sc = _scales(grid, spec, opts)
    half, half_el, n_rc, n_cells = sc["half"], sc["half_el"], sc["n_rc"], sc["n_cells"]
    edges = beam_tan_edges(spec)
    keep_geometry = int(opts.passes) > 1  # the occlusion test needs each view's ranges and angles
    views = []
    seen = np.zeros(n, np.uint32)
    fan = np.zeros(n, np.uint32)  # pings whose nominal fan holds the candidate
    front = np.zeros(n, np.uint32)  # ... and in which it lies in front of the first return
    for pc in pings:
        lit = np.zeros(n_cells, bool)
        lit[pc.lit] = True
        v = _view(spec, edges, pc.T_W_S, centres, lit.reshape(n_rc, spec.n_beams), half, sc["cell_m"],
                  half_el, pc.first, sc["front_tol"])
        seen[v.cand] += 1
        fan[v.cand[np.abs(v.elev) <= 0.5 * spec.vfov_rad]] += 1
        front[v.cand[v.front]] += 1
        if not keep_geometry:
            v = dataclasses.replace(v, r=None, elev=None, j0=None, j1=None, front=None)
        views.append(v)
    alive = front <= opts.max_front_share * np.maximum(fan, 1)
    occluders = None
    votes = np.zeros(n, np.uint32)
    bright = np.zeros(n, np.uint32)
    weight = np.zeros(n)
    for _ in range(int(opts.passes)):
        weight, votes, bright = _explain(views, n, n_cells, occluders, spec, half_el,
                                         int(opts.elevation_cells), sc["occl_m"], half, int(opts.iterations),
                                         alive, w0)
        occluders = votes >= opts.min_votes
    return _finish(cand, obs, grid, idx, alive, votes, seen, bright, opts, len(pings), sc), weight


def _finish(cand: np.ndarray, obs: np.ndarray, grid: GridSpec, idx: np.ndarray, alive: np.ndarray,
            votes: np.ndarray, seen: np.ndarray, bright: np.ndarray, opts: SurfaceOptions, n_pings: int,
            sc: dict) -> SurfaceLayer:
    """Step 5: the winners grown into the kept candidates; the layer with its per-voxel counts."""
    shape = tuple(grid.shape)
    n = len(idx)
    surf = np.zeros(shape, bool)
    if n:
        surf[tuple(idx[votes >= opts.min_votes].T)] = True
    if opts.band_voxels and n:
        from scipy import ndimage

        ok = np.zeros(shape, bool)
        ok[tuple(idx[alive].T)] = True
        grown = ndimage.binary_dilation(surf, np.ones((3, 3, 3), bool), iterations=int(opts.band_voxels))
        surf |= ok & grown
    out = {}
    for name, a in (("votes", votes), ("views", seen), ("bright_views", bright)):
        full = np.zeros(shape, np.uint32)
        full[tuple(idx.T)] = a
        out[name] = full
    stats = {"candidates": int(n), "surface": int(surf.sum()), "pings": n_pings, "seconds": 0.0,
             **opts.to_dict(), "cell_m": sc["cell_m"], "occlusion_m": sc["occl_m"]}
    return SurfaceLayer(surf, cand.copy(), obs.copy(), out["votes"], out["views"], out["bright_views"], grid,
                        stats)
