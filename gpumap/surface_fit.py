"""A generative surface fit (issue 43): the pings' intensities explained by the safe map's occupied voxels.

An imaging sonar's cell (range, beam) sums the echoes of its whole elevation arc. This layer fits that
sum. Each candidate voxel ``i`` (the safe map's occupied voxels, ``mapper.values() >= threshold``: the
fit never claims a voxel the pings proved empty or never saw) carries a weight ``x_i >= 0`` (its
reflectivity times area, in the display's units), and a ping's cell is modelled as

    y_pc = g_p * sum_i a_pci T_pi x_i + b_p

- ``y_pc``: the cell's energy, the display law undone (``-ln(1 - I)`` of every sonar cell, averaged
  over the coarse cell: ``bin_stride`` bins by ``beam_stride`` beams, about half a voxel each);
  cells with a saturated sonar cell give only a lower bound (censored).
- ``a_pci = f_pci B(phi) L(r) / r^2 c_inc``: the share ``f`` of the voxel's own width (``+-h/2`` in
  range and azimuth) falling in the cell, the two-way vertical beam pattern ``B(phi) = 0.5 **
  ((2 phi / vfov)^2) + side_lobe_level`` out to ``aperture_scale * vfov / 2`` (the stated pattern
  of :class:`gpumap.render.PingModel`; a voxel outside the nominal fan still returns), the range loss
  left after time-varied gain ``L(r) = r^-n 10^(-2 a (r - 1) / 10)``, the solid angle of a voxel
  ``1 / r^2``, and the incidence term ``c_inc = (cos^2 + 1e-4)^((k + 1) / 2)`` (projected area
  times the ``cos^k`` law) with the normal of the current surface estimate around the voxel.
- ``T_pi``: the transmittance of the ray from the sonar to the voxel in ping ``p``: the product of
  ``1 - alpha_u`` over the candidates ``u`` more than ``occlusion_m`` nearer in the same (beam,
  elevation) ray cell (each covers the cells its width spans), ``alpha_u`` their surface probability:
  a surface shadows what lies behind it, and a shadowed voxel is neither credited nor blamed by
  that ping.
- ``g_p``: a per-ping gain (real sonars vary ping to ping; geometric mean 1), ``b_p`` the ping's noise
  floor (the median energy of its dark cells).

The weights are fitted by the multiplicative EM update of emission tomography (MLEM,
Richardson-Lucy), ``x_i <- x_i sum_pc a T g y / yhat / sum_pc a T g``, which keeps ``x >= 0``,
credits a voxel with the share of each cell that its weight explains and blames it for the cells it
would brighten that stay dark. Every ``occlusion_every`` iterations the transmittances, the normals
and the surface probabilities are recomputed from the weights.

How sure (per voxel): in each cell that a voxel spans, its weight against the heaviest competitor's
(occlusion included), ``d = x_i T_pi / max_u x_u T_pu``; its **share** is the mean of ``d`` over
its cells weighted by their energy above the floor and the voxel's part in them. A voxel that
dominates the bright cells it spans has a share near 1, one whose cells other voxels explain near
0. **Thin surfaces**: a voxel whose share is at most ``thin_ratio`` of a neighbour's along its
estimated normal (26-neighbourhood) gives way to it (a surface voxelises one to three voxels thick;
the fit spreads a little of the surface's weight over its thickness). The **surface** is the
candidates with share ``>= surface_share``; **undecided** those in ``[undecided_share,
surface_share)`` and those with too little energy seen (``min_energy``); the rest the fit explained
away (the safe map still keeps them).

Use: :func:`fit_surface` (a mapper and the pings it integrated) or :func:`fit_candidates` (a
candidate mask, its grid, the sonar and the pings). Everything here is NumPy.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field

import numpy as np

from gpumap.spec import GridSpec, SonarSpec

__all__ = ["FitOptions", "SurfaceFit", "fit_candidates", "fit_surface"]


@dataclass(frozen=True)
class FitOptions:
    """Settings of the surface fit (module docstring). The model's constants are
    :class:`gpumap.render.PingModel`'s stated ones.

    iterations : int
        EM iterations.
    occlusion_every : int
        Iterations between updates of the transmittances, normals and shares (0: never: no
        occlusion, no incidence term).
    aperture_scale : float
        The candidates' elevation extent over the nominal vertical aperture (>= 1).
    side_lobe_level, spreading_exponent, absorption_db_per_m, cos_exponent : float
        The ping model's beam pattern floor, range loss and incidence law.
    incidence : bool
        Apply the incidence term (normals from the current estimate).
    occlusion_m : float or None
        A voxel occludes those more than this behind it (None: two voxels).
    per_ping_gain : bool
        Fit a gain per ping.
    surface_share, undecided_share : float
        Share from which a candidate is surface / undecided.
    thin_ratio : float
        A voxel whose share is at most this ratio of its neighbour's along the normal gives way (0: off).
    min_energy : float
        Least energy above the floor (summed over the voxel's part of its cells, in units of the
        median bright cell) for a decision; below it the candidate is undecided.
    """

    iterations: int = 40
    occlusion_every: int = 10
    aperture_scale: float = 1.5
    side_lobe_level: float = 0.01
    spreading_exponent: float = 0.5
    absorption_db_per_m: float = 0.04
    cos_exponent: float = 1.0
    incidence: bool = True
    occlusion_m: float | None = None
    per_ping_gain: bool = True
    surface_share: float = 0.5
    undecided_share: float = 0.2
    thin_ratio: float = 0.0
    min_energy: float = 0.5

    def __post_init__(self) -> None:
        for name in ("iterations", "occlusion_every"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 0:
                raise ValueError(f"Expected an integer >= 0 for {name!r}, but got {v!r}")
        if not (np.isfinite(self.aperture_scale) and self.aperture_scale >= 1.0):
            raise ValueError(f"Expected aperture_scale >= 1, but got {self.aperture_scale}")
        for name in ("side_lobe_level", "spreading_exponent", "absorption_db_per_m", "cos_exponent",
                     "min_energy"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f"Expected {name} >= 0, but got {v}")
        for name in ("surface_share", "undecided_share", "thin_ratio"):
            if not (0.0 <= getattr(self, name) <= 1.0):
                raise ValueError(f"Expected {name} in [0, 1], but got {getattr(self, name)}")
        if self.undecided_share > self.surface_share:
            raise ValueError(f"Expected undecided_share <= surface_share, but got {self.undecided_share} > "
                             f"{self.surface_share}")
        if self.occlusion_m is not None and not (np.isfinite(self.occlusion_m) and self.occlusion_m > 0):
            raise ValueError(f"Expected occlusion_m > 0 (metres) or None, but got {self.occlusion_m}")

    def to_dict(self) -> dict:
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}


@dataclass
class SurfaceFit:
    """The fit over ``grid`` (arrays (nx, ny, nz)).

    surface : bool
        What is there: candidates with share ``>= surface_share`` and enough energy seen.
    undecided : bool
        Candidates the fit cannot decide (the safe map keeps them; an arm must still avoid them).
    candidates : bool
        The safe map's occupied voxels the fit chose from.
    observed : bool
        Voxels the safe map observed.
    share : float32
        How sure, in [0, 1] (module docstring); NaN off the candidates.
    weight : float32
        Fitted weight ``x`` (>= 0; 0 off the candidates).
    energy : float32
        Energy above the floor the voxel's cells held, in units of the median bright cell.
    grid : GridSpec
    gains : (n_pings,) float64
        Per-ping gains.
    stats : dict
        Counts, seconds and settings (JSON-ready).
    """

    surface: np.ndarray
    undecided: np.ndarray
    candidates: np.ndarray
    observed: np.ndarray
    share: np.ndarray
    weight: np.ndarray
    energy: np.ndarray
    grid: GridSpec
    gains: np.ndarray
    stats: dict = field(default_factory=dict)

    def values(self) -> np.ndarray:
        """(nx, ny, nz) float32: 1 surface, 0.5 undecided, 0 observed otherwise, NaN never observed
        (the surface is occupied from 0.75, surface and undecided from 0.5)."""
        out = np.where(self.observed, np.float32(0.0), np.float32(np.nan)).astype(np.float32)
        out[self.undecided] = 0.5
        out[self.surface] = 1.0
        return out


# ------------------------------------------------------------------------------ the pings
def _strides(spec: SonarSpec, voxel_m: float) -> tuple[int, int]:
    """Sonar bins and beams per coarse cell: about half a voxel each (beams at mid range)."""
    r_mid = 0.5 * (spec.range_min_m + spec.range_max_m)
    d_theta = spec.hfov_rad / spec.n_beams
    return (max(1, int(math.floor(0.5 * voxel_m / spec.bin_size_m))),
            max(1, int(math.floor(0.5 * voxel_m / (r_mid * d_theta)))))


def _coarse_edges(edges: np.ndarray, stride: int) -> np.ndarray:
    n = len(edges) - 1
    return np.asarray(edges, np.float64)[np.r_[np.arange(0, n, stride), n]]


def _energy(image: np.ndarray, threshold: float, bin_stride: int, beam_stride: int
            ) -> tuple[np.ndarray, np.ndarray, float]:
    """One ping's coarse energy ((n_rc, n_bc) float64, ``-ln(1 - I)`` averaged over each coarse cell),
    its censored cells ((n_rc, n_bc) bool: a saturated sonar cell) and its floor (the median energy of
    the cells below ``threshold``; 0 if none)."""
    img = image.astype(np.float64) * (1.0 / 255.0) if image.dtype == np.uint8 else np.asarray(image, np.float64)
    cap = 1.0 - 0.5 / 255.0
    e = -np.log1p(-np.minimum(np.clip(img, 0.0, 1.0), cap))
    dark = img < threshold
    floor = float(np.median(e[dark])) if dark.any() else 0.0
    rb, cb = np.arange(0, img.shape[0], bin_stride), np.arange(0, img.shape[1], beam_stride)
    s = np.add.reduceat(np.add.reduceat(e, rb, axis=0), cb, axis=1)
    nr = np.diff(np.r_[rb, img.shape[0]])
    nc = np.diff(np.r_[cb, img.shape[1]])
    sat = np.add.reduceat(np.add.reduceat((img >= cap).astype(np.int32), rb, axis=0), cb, axis=1) > 0
    return s / (nr[:, None] * nc[None, :]), sat, floor


def _check(images: np.ndarray, poses: np.ndarray, spec: SonarSpec) -> tuple[np.ndarray, np.ndarray]:
    images = np.asarray(images)
    poses = np.asarray(poses, np.float64)
    if images.ndim != 3 or images.shape[1:] != spec.image_shape:
        raise ValueError(f"Expected images of shape (n, {spec.image_shape[0]}, {spec.image_shape[1]}), "
                         f"but got {images.shape}")
    if images.dtype not in (np.uint8, np.float32, np.float64):
        raise TypeError(f"Expected images of dtype uint8, float32 or float64, but got {images.dtype}")
    if poses.shape != (len(images), 4, 4):
        raise ValueError(f"Expected poses of shape ({len(images)}, 4, 4), but got {poses.shape}")
    if not np.all(np.isfinite(poses)):
        raise ValueError("Expected finite poses, but got NaN or inf")
    return images, poses


# ------------------------------------------------------------------------------ geometry
def _overlaps(lo: np.ndarray, hi: np.ndarray, edges: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cells of ``edges`` ((n + 1,) ascending) that the intervals ``[lo, hi]`` ((k,) each, hi > lo)
    overlap: (row (m,), cell (m,), overlap over the interval's length (m,)), row by row, cells
    ascending. Parts outside the edges are lost."""
    n = len(edges) - 1
    j0 = np.clip(np.searchsorted(edges, lo, side="right") - 1, 0, n - 1)
    j1 = np.clip(np.searchsorted(edges, hi, side="left") - 1, 0, n - 1)
    cnt = np.maximum(j1 - j0 + 1, 0)
    row = np.repeat(np.arange(len(lo)), cnt)
    cell = j0[row] + (np.arange(int(cnt.sum())) - np.repeat(np.cumsum(cnt) - cnt, cnt))
    part = np.minimum(hi[row], edges[cell + 1]) - np.maximum(lo[row], edges[cell])
    keep = part > 0
    return row[keep], cell[keep], part[keep] / (hi[row[keep]] - lo[row[keep]])


@dataclass
class _Pings:
    """Every (ping, candidate) pair in view and its coarse cells, all pings at once."""

    pair_vox: np.ndarray  # (P,) candidate index
    pair_ping: np.ndarray  # (P,) ping
    pair_r: np.ndarray  # (P,) range, m
    pair_az: np.ndarray  # (P,) azimuth, rad
    pair_el: np.ndarray  # (P,) elevation, rad
    pair_dir_W: np.ndarray  # (P, 3) unit ray from the sonar, world frame
    pair_w0: np.ndarray  # (P,) beam pattern x range loss / r^2
    ent_pair: np.ndarray  # (E,) pair of each entry
    ent_cell: np.ndarray  # (E,) compact cell index
    ent_frac: np.ndarray  # (E,) share of the voxel's width in the cell
    y: np.ndarray  # (C,) cell energy
    censored: np.ndarray  # (C,) bool
    cell_ping: np.ndarray  # (C,) ping
    floor: np.ndarray  # (n_pings,)
    bright_unit: float  # median energy above the floor of the bright cells


def _build(centres_W: np.ndarray, grid: GridSpec, spec: SonarSpec, images: np.ndarray, poses: np.ndarray,
           threshold: float, opts: FitOptions) -> _Pings:
    h = grid.voxel_size_m
    bs, gs = _strides(spec, h)
    r_edges = spec.range_min_m + spec.bin_size_m * np.r_[np.arange(0, spec.n_bins, bs), spec.n_bins]
    b_edges = _coarse_edges(spec.beam_edges_rad, gs)
    n_rc, n_bc = len(r_edges) - 1, len(b_edges) - 1
    half_el = opts.aperture_scale * 0.5 * spec.vfov_rad
    parts: dict[str, list] = {k: [] for k in ("vox", "ping", "r", "az", "el", "dir", "w0", "epair", "ecell",
                                               "efrac")}
    ys, sats, floors, bright = [], [], [], []
    n_pairs = 0
    for p, (image, T) in enumerate(zip(images, poses, strict=True)):
        y, sat, floor = _energy(image, threshold, bs, gs)
        ys.append(y.reshape(-1))
        sats.append(sat.reshape(-1))
        floors.append(floor)
        img = image.astype(np.float64) / 255.0 if image.dtype == np.uint8 else image
        lit = np.add.reduceat(np.add.reduceat((img >= threshold).astype(np.int32),
                                              np.arange(0, spec.n_bins, bs), 0), np.arange(0, spec.n_beams, gs), 1)
        bright.append(y[lit > 0] - floor)
        R, t = T[:3, :3], T[:3, 3]
        d = centres_W - t
        q = d @ R  # sonar frame
        rh = np.hypot(q[:, 0], q[:, 1])
        r = np.sqrt(rh * rh + q[:, 2] ** 2)
        el = np.arctan2(q[:, 2], rh)
        az = np.arctan2(q[:, 1], q[:, 0])
        ok = ((q[:, 0] > 0) & (r >= spec.range_min_m) & (r < spec.range_max_m) & (np.abs(el) <= half_el)
              & (az >= spec.beam_edges_rad[0]) & (az <= spec.beam_edges_rad[-1]))
        k = np.flatnonzero(ok)
        r, el, az, rh = r[k], el[k], az[k], rh[k]
        w_az = np.arctan2(0.5 * h, rh)
        rr, rc, rf = _overlaps(r - 0.5 * h, r + 0.5 * h, r_edges)
        br, bc, bf = _overlaps(az - w_az, az + w_az, b_edges)
        nr = np.bincount(rr, minlength=len(k))
        nb = np.bincount(br, minlength=len(k))
        r0, b0 = np.cumsum(nr) - nr, np.cumsum(nb) - nb
        tot = nr * nb
        pair = np.repeat(np.arange(len(k)), tot)
        off = np.arange(int(tot.sum())) - np.repeat(np.cumsum(tot) - tot, tot)
        ir = r0[pair] + off // np.maximum(nb[pair], 1)
        ib = b0[pair] + off % np.maximum(nb[pair], 1)
        pattern = 0.5 ** ((2.0 * el / spec.vfov_rad) ** 2) + opts.side_lobe_level
        loss = r ** -opts.spreading_exponent * 10.0 ** (-2.0 * opts.absorption_db_per_m * (r - 1.0) / 10.0)
        parts["vox"].append(k)
        parts["ping"].append(np.full(len(k), p))
        parts["r"].append(r)
        parts["az"].append(az)
        parts["el"].append(el)
        parts["dir"].append(d[k] / r[:, None])
        parts["w0"].append(pattern * loss / (r * r))
        parts["epair"].append(pair + n_pairs)
        parts["ecell"].append(p * n_rc * n_bc + rc[ir] * n_bc + bc[ib])
        parts["efrac"].append(rf[ir] * bf[ib])
        n_pairs += len(k)
    cat = {k: np.concatenate(v) if v else np.zeros(0) for k, v in parts.items()}
    cells, inv = np.unique(cat["ecell"].astype(np.int64), return_inverse=True)
    y_all, sat_all = np.concatenate(ys), np.concatenate(sats)
    ping_of = cells // (n_rc * n_bc)
    local = cells % (n_rc * n_bc)
    y = y_all.reshape(len(images), -1)[ping_of, local]
    sat = sat_all.reshape(len(images), -1)[ping_of, local]
    b = np.concatenate(bright) if bright else np.zeros(0)
    unit = float(np.median(b[b > 0])) if np.any(b > 0) else 1.0
    return _Pings(cat["vox"].astype(np.int64), cat["ping"].astype(np.int64), cat["r"], cat["az"], cat["el"],
                  cat["dir"].reshape(-1, 3), cat["w0"], cat["epair"].astype(np.int64), inv.astype(np.int64),
                  cat["efrac"], y, sat, ping_of.astype(np.int64), np.asarray(floors, np.float64), unit)


def _sort_entries(pk: _Pings) -> None:
    """Entries sorted by cell (in place): each cell's entries one run, for maxima over cells."""
    order = np.argsort(pk.ent_cell, kind="stable")
    pk.ent_cell, pk.ent_pair, pk.ent_frac = pk.ent_cell[order], pk.ent_pair[order], pk.ent_frac[order]


# ------------------------------------------------------------------------------ occlusion, normals, share
def _transmittance(pk: _Pings, alpha: np.ndarray, spec: SonarSpec, h: float, opts: FitOptions) -> np.ndarray:
    """(P,) transmittance of every pair: ``prod (1 - alpha_u)`` over the candidates ``u`` of the same ping
    more than ``occlusion_m`` nearer whose width covers the pair's (beam, elevation) ray cell."""
    tol = 2.0 * h if opts.occlusion_m is None else opts.occlusion_m
    _, gs = _strides(spec, h)
    b_edges = _coarse_edges(spec.beam_edges_rad, gs)
    n_b = len(b_edges) - 1
    half_el = opts.aperture_scale * 0.5 * spec.vfov_rad
    step = float(np.mean(np.diff(b_edges)))
    n_e = max(1, int(math.ceil(2.0 * half_el / step)))
    e_edges = np.linspace(-half_el, half_el, n_e + 1)
    n_ray = n_b * n_e
    a_u = alpha[pk.pair_vox]
    occ = np.flatnonzero(a_u > 0.02)
    T = np.ones(len(pk.pair_vox))
    if len(occ) == 0:
        return T
    r = pk.pair_r[occ]
    w_az = np.arctan2(0.5 * h, r * np.cos(pk.pair_el[occ]))
    w_el = np.arctan2(0.5 * h, r)
    ar, ac, _ = _overlaps(pk.pair_az[occ] - w_az, pk.pair_az[occ] + w_az, b_edges)
    er, ec, _ = _overlaps(pk.pair_el[occ] - w_el, pk.pair_el[occ] + w_el, e_edges)
    na, ne = np.bincount(ar, minlength=len(occ)), np.bincount(er, minlength=len(occ))
    a0, e0 = np.cumsum(na) - na, np.cumsum(ne) - ne
    tot = na * ne
    row = np.repeat(np.arange(len(occ)), tot)
    off = np.arange(int(tot.sum())) - np.repeat(np.cumsum(tot) - tot, tot)
    ia = a0[row] + off // np.maximum(ne[row], 1)
    ie = e0[row] + off % np.maximum(ne[row], 1)
    span = 2.0 * spec.range_max_m + tol + 1.0
    ray = pk.pair_ping[occ][row] * n_ray + ac[ia] * n_e + ec[ie]
    key = ray * span + r[row]
    order = np.argsort(key, kind="stable")
    key = key[order]
    logt = np.log1p(-np.minimum(a_u[occ][row][order], 0.999))
    cum = np.r_[0.0, np.cumsum(logt)]
    jc = np.clip(np.searchsorted(b_edges, pk.pair_az, side="right") - 1, 0, n_b - 1)
    ecc = np.clip(np.searchsorted(e_edges, pk.pair_el, side="right") - 1, 0, n_e - 1)
    ray_c = pk.pair_ping * n_ray + jc * n_e + ecc
    lo = np.searchsorted(key, ray_c * span, side="left")
    hi = np.searchsorted(key, ray_c * span + (pk.pair_r - tol), side="left")
    return np.exp(cum[np.maximum(hi, lo)] - cum[lo])


def _normals(cand_idx: np.ndarray, weights: np.ndarray, shape: tuple[int, int, int]
             ) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals ((n, 3), grid axes) of the weighted candidates' local plane (the least-variance
    direction of the weights within two voxels) and its planarity ((n,) in [0, 1])."""
    from scipy import ndimage

    w = np.zeros(shape)
    w[tuple(cand_idx.T)] = weights
    o = np.arange(-2, 3, dtype=np.float64)
    ker = [o[:, None, None] * np.ones((1, 5, 5)), o[None, :, None] * np.ones((5, 1, 5)),
           o[None, None, :] * np.ones((5, 5, 1))]
    sl = tuple(cand_idx.T)
    m0 = ndimage.correlate(w, np.ones((5, 5, 5)), mode="constant")[sl]
    m1 = np.stack([ndimage.correlate(w, k, mode="constant")[sl] for k in ker], -1)
    m2 = np.empty((len(cand_idx), 3, 3))
    for a in range(3):
        for b in range(a, 3):
            m2[:, a, b] = m2[:, b, a] = ndimage.correlate(w, ker[a] * ker[b], mode="constant")[sl]
    safe = np.maximum(m0, 1e-12)
    mu = m1 / safe[:, None]
    cov = m2 / safe[:, None, None] - mu[:, :, None] * mu[:, None, :]
    val, vec = np.linalg.eigh(cov)
    planar = np.where(m0 > 1e-12, np.clip(1.0 - val[:, 0] / np.maximum(val[:, 1], 1e-12), 0.0, 1.0), 0.0)
    return vec[:, :, 0], planar


def _incidence(pk: _Pings, normals: np.ndarray, planar: np.ndarray, k: float) -> np.ndarray:
    """(P,) incidence term ``(cos^2 + 1e-4)^((k + 1) / 2)`` of every pair, blended with its mean over a
    hemisphere, ``1 / (k + 2)``, where the neighbourhood is no plane."""
    cos = np.abs(np.einsum("ij,ij->i", normals[pk.pair_vox], pk.pair_dir_W))
    c = (cos * cos + 1e-4) ** (0.5 * (k + 1.0))
    lam = planar[pk.pair_vox]
    return lam * c + (1.0 - lam) / (k + 2.0)


def _cell_runs(pk: _Pings) -> np.ndarray:
    return np.flatnonzero(np.r_[True, pk.ent_cell[1:] != pk.ent_cell[:-1]])


def _share(pk: _Pings, x: np.ndarray, T: np.ndarray, pair_a: np.ndarray, n: int, runs: np.ndarray
           ) -> tuple[np.ndarray, np.ndarray]:
    """(share (n,), energy (n,)) of the candidates (module docstring)."""
    vox = pk.pair_vox[pk.ent_pair]
    xt = x[vox] * T[pk.ent_pair]
    mx = np.maximum.reduceat(xt, runs) if len(xt) else np.zeros(0)
    cell_of_run = pk.ent_cell[runs]
    best = np.zeros(len(pk.y))
    best[cell_of_run] = mx
    b = best[pk.ent_cell]
    d = np.divide(xt, b, out=np.zeros_like(xt), where=b > 0)
    excess = np.maximum(pk.y - pk.floor[pk.cell_ping], 0.0)[pk.ent_cell]
    w = pk.ent_frac * pair_a[pk.ent_pair] * excess
    sw = np.bincount(vox, weights=w, minlength=n)
    share = np.divide(np.bincount(vox, weights=w * d, minlength=n), sw, out=np.zeros(n), where=sw > 0)
    energy = np.bincount(vox, weights=pk.ent_frac * T[pk.ent_pair] * excess, minlength=n) / pk.bright_unit
    return share, energy


# ------------------------------------------------------------------------------ the fit
def _fit(cand: np.ndarray, grid: GridSpec, spec: SonarSpec, images: np.ndarray, poses: np.ndarray,
         threshold: float, opts: FitOptions) -> tuple[dict, np.ndarray]:
    t0 = time.perf_counter()
    idx = np.argwhere(cand)
    n = len(idx)
    centres = grid.centers(idx)
    pk = _build(centres, grid, spec, images, poses, threshold, opts)
    _sort_entries(pk)
    runs = _cell_runs(pk)
    t_build = time.perf_counter() - t0
    n_p = len(images)
    h = grid.voxel_size_m
    vox_e = pk.pair_vox[pk.ent_pair]
    g = np.ones(n_p)
    T = np.ones(len(pk.pair_vox))
    inc = np.ones(len(pk.pair_vox))
    excess = np.maximum(pk.y - pk.floor[pk.cell_ping], 0.0)
    a0 = pk.ent_frac * pk.pair_w0[pk.ent_pair]
    s0 = np.bincount(pk.ent_cell, weights=a0, minlength=len(pk.y))
    x = np.full(n, excess.sum() / max(s0.sum(), 1e-300))
    share = np.zeros(n)
    for it in range(int(opts.iterations)):
        if opts.occlusion_every and it > 0 and it % opts.occlusion_every == 0:
            pair_a = pk.pair_w0 * inc * T
            share, _ = _share(pk, x, T, pair_a, n, runs)
            T = _transmittance(pk, share, spec, h, opts)
            if opts.incidence:
                nrm, planar = _normals(idx, share, grid.shape)
                inc = _incidence(pk, nrm, planar, opts.cos_exponent)
        pair_a = pk.pair_w0 * inc * T
        a = pk.ent_frac * pair_a[pk.ent_pair]
        gc = g[pk.cell_ping]
        sig = np.bincount(pk.ent_cell, weights=a * x[vox_e], minlength=len(pk.y))
        yhat = gc * sig + pk.floor[pk.cell_ping]
        ratio = np.divide(pk.y, yhat, out=np.ones_like(yhat), where=yhat > 0)
        ratio = np.where(pk.censored, np.maximum(ratio, 1.0), ratio)
        gr = (gc * ratio)[pk.ent_cell]
        num = np.bincount(vox_e, weights=a * gr, minlength=n)
        den = np.bincount(vox_e, weights=a * gc[pk.ent_cell], minlength=n)
        x = np.divide(x * num, den, out=np.zeros(n), where=den > 0)
        if opts.per_ping_gain:
            s_num = np.bincount(pk.cell_ping, weights=sig * ratio, minlength=n_p)
            s_den = np.bincount(pk.cell_ping, weights=sig, minlength=n_p)
            g = np.where(s_den > 0, g * np.divide(s_num, s_den, out=np.ones(n_p), where=s_den > 0), g)
            pos = g > 0
            if pos.any():
                scale = math.exp(float(np.mean(np.log(g[pos]))))
                g, x = g / scale, x * scale
    pair_a = pk.pair_w0 * inc * T
    share, energy = _share(pk, x, T, pair_a, n, runs)
    yhat = g[pk.cell_ping] * np.bincount(pk.ent_cell, weights=pk.ent_frac * pair_a[pk.ent_pair] * x[vox_e],
                                         minlength=len(pk.y)) + pk.floor[pk.cell_ping]
    stats = {"candidates": n, "pairs": len(pk.pair_vox), "entries": len(pk.ent_cell), "cells": len(pk.y),
             "build_seconds": t_build, "rms_cells": float(np.sqrt(np.mean((yhat - pk.y) ** 2))),
             "bright_unit": pk.bright_unit}
    return {"x": x, "share": share, "energy": energy, "gains": g, "idx": idx, "stats": stats}, yhat


def fit_candidates(candidates: np.ndarray, observed: np.ndarray, grid: GridSpec, spec: SonarSpec,
                   images: np.ndarray, poses: np.ndarray, threshold: float,
                   options: FitOptions | None = None) -> SurfaceFit:
    """The surface fit of the candidate voxels from the pings.

    Parameters
    ----------
    candidates : (nx, ny, nz) bool
        The voxels that may be surface (the safe map's occupied ones).
    observed : (nx, ny, nz) bool
        Voxels the safe map observed (a superset of ``candidates``).
    grid : GridSpec
    spec : SonarSpec
    images : (n, n_bins, n_beams) uint8 or float
        The pings, intensities in [0, 1] (uint8 scaled by 1/255).
    poses : (n, 4, 4) float
        ``T_W_S`` of each ping.
    threshold : float
        The safe map's occupied intensity (cells below it give the noise floor).
    options : FitOptions, optional

    Returns
    -------
    SurfaceFit
    """
    t0 = time.perf_counter()
    opts = options or FitOptions()
    if not isinstance(grid, GridSpec):
        raise TypeError(f"Expected a gpumap.GridSpec for 'grid', but got {type(grid).__name__}")
    if not isinstance(spec, SonarSpec):
        raise TypeError(f"Expected a gpumap.SonarSpec for 'spec', but got {type(spec).__name__}")
    cand = np.asarray(candidates)
    obs = np.asarray(observed)
    for name, a in (("candidates", cand), ("observed", obs)):
        if a.shape != grid.shape or a.dtype != bool:
            raise ValueError(f"Expected {name} of shape {grid.shape} bool, but got {a.dtype} {a.shape}")
    if np.any(cand & ~obs):
        raise ValueError("Expected candidates within the observed voxels, but some were never observed")
    if not (np.isfinite(threshold) and 0.0 < threshold <= 1.0):
        raise ValueError(f"Expected threshold in (0, 1], but got {threshold}")
    images, poses = _check(images, poses, spec)
    res, _ = _fit(cand, grid, spec, images, poses, float(threshold), opts)
    sl = tuple(res["idx"].T)
    share = np.full(grid.shape, np.nan, np.float32)
    share[sl] = res["share"]
    weight = np.zeros(grid.shape, np.float32)
    weight[sl] = res["x"]
    energy = np.zeros(grid.shape, np.float32)
    energy[sl] = res["energy"]
    enough = cand & (energy >= opts.min_energy)
    s = np.nan_to_num(share, nan=0.0)
    surface = enough & (s >= opts.surface_share)
    undecided = cand & ~surface & ((s >= opts.undecided_share) | ~enough)
    stats = {**res["stats"], "surface": int(surface.sum()), "undecided": int(undecided.sum()),
             "pings": len(images), "seconds": time.perf_counter() - t0, "options": opts.to_dict()}
    return SurfaceFit(surface, undecided, cand.copy(), obs.copy(), share, weight, energy, grid, res["gains"],
                      stats)


def fit_surface(mapper, images: np.ndarray, poses: np.ndarray, options: FitOptions | None = None) -> SurfaceFit:
    """The surface fit of a :class:`gpumap.MinMaxMapper` from the pings it integrated: candidates
    ``mapper.values() >= mapper.threshold`` (its grid, sonar and threshold; :func:`fit_candidates`)."""
    v = mapper.values()
    cand = np.nan_to_num(v, nan=-np.inf) >= mapper.threshold
    return fit_candidates(cand, np.isfinite(v), mapper.grid, mapper.spec, images, poses, mapper.threshold,
                          options)
