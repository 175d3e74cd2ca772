"""A generative surface fit (issue 43): the pings' intensities explained by the safe map's occupied voxels.

An imaging sonar's cell (range, beam) sums the echoes of its elevation arc; this layer fits that sum.
Each candidate voxel ``i`` (the safe map's occupied voxels, ``mapper.values() >= threshold``: the fit
never claims a voxel the pings proved empty or never saw) carries a weight ``x_i >= 0`` (reflectivity
times area, display units), and the coarse cell ``c`` of ping ``p`` is modelled as

    y_pc = g_p * sum_i a_pi f_pic x_i + b_p

- ``y_pc``: the cell's energy, the display law undone (``-ln(1 - I)`` of every sonar cell, averaged
  over cells of about half a voxel); a cell with a saturated sonar cell is a lower bound (censored).
- ``a_pi = B(phi) L(r) / r^2 [c_inc T_pi]``: the two-way vertical beam pattern ``0.5 ** ((2 phi /
  vfov)^2) + side_lobe_level`` out to ``aperture_scale * vfov / 2`` (:class:`gpumap.layers.render.PingModel`'s
  stated pattern: a voxel outside the nominal fan still returns), the range loss left after
  time-varied gain ``r^-n 10^(-2 a (r - 1) / 10)``, a voxel's solid angle ``1 / r^2``, the incidence
  term ``(cos^2 + 1e-4)^((k + 1) / 2)`` (projected area and Lambert's law) with the normals of the
  current estimate (blended by planarity with its hemisphere mean); optionally the transmittance
  ``T_pi``, the product of ``1 - alpha_u`` over the candidates more than ``occlusion_m`` nearer in the
  same (beam, elevation) ray cell, ``alpha_u`` their surface level.
- ``f_pic``: where in its width (``+-h/2`` in range and azimuth) the voxel's echo falls in that ping (a
  surface crosses a voxel somewhere: its echo is a line at a sub-voxel range; with a fixed box, walls
  seen near normal incidence lose their weight), fitted with the weights, mixed with the box.
- ``g_p`` a per-ping gain (geometric mean 1), ``b_p`` the ping's floor (median energy of its dark cells).

The fit is the expectation-maximisation of this Poisson-like model (MLEM / Richardson-Lucy with real
intensities): each cell's energy is shared among its entries in proportion to their prediction; a
weight becomes what it collected over its sensitivity (dark cells blame it). Weights stay ``>= 0``.
The pings alone leave a stack of voxels across a surface nearly interchangeable (the EM spreads the
weight over it); the **thin-surface prior** keeps, every ``thin_every`` iterations, the heaviest
(smoothed) voxel along the local normal and lowers the others by a rising power of their ratio to it.

The decision is on the data's own scale of a surface, ``x_ref`` (the weight that alone makes the
median bright cell from the median entry of a bright cell): **how sure** ``x / (x + surface_level
x_ref)``; the **surface** is ``x >= surface_level x_ref``; **undecided** ``undecided_level x_ref <= x``
below that, and the candidates in fewer than ``min_pings`` pings; the rest is explained away (the safe
map still keeps it). Measured (``python -m bench.experiments.surface_fit``): the incidence term helps
once the thin prior has cleaned the estimate its normals come from (tank F 0.67 -> 0.70, circle 0.56 ->
0.69); the occlusion with opacities from the estimate does not (a phantom in front that the estimate
still holds shadows the surface behind it: tank F 0.14), so it is off. NumPy only.
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
    """Settings of the surface fit (module docstring). The ping model's constants are
    :class:`gpumap.layers.render.PingModel`'s; the decision levels were chosen on the simulated tank alone.

    iterations : int
        EM iterations.
    adaptive_profile, profile_mix : bool, float
        Fit where in its width each voxel's echo falls, per ping (False: the fixed box), mixed with the
        box by ``profile_mix`` in [0, 1] after every iteration.
    aperture_scale : float
        The candidates' elevation extent over the nominal vertical aperture (>= 1).
    side_lobe_level, spreading_exponent, absorption_db_per_m, per_ping_gain : float, float, float, bool
        The beam pattern's floor, the range loss; whether to fit a gain per ping.
    incidence, occlusion, first_update, update_every : bool, bool, int, int
        The incidence term (normals from the estimate) and the occlusion (opacities from it), updated
        from iteration ``first_update`` every ``update_every`` (measured: the first helps; the second
        does not: off).
    cos_exponent, occlusion_m : float, float or None
        ``k`` of the incidence law; a voxel occludes those more than ``occlusion_m`` metres behind it
        (None: two voxels).
    thin_radius, thin_power, thin_every, thin_smooth, thin_ramp : int, float, int, int, float
        The thin-surface prior: every ``thin_every`` iterations each weight is multiplied by
        ``(s / m)^(p * planarity)``, ``s`` the weight smoothed over ``thin_smooth`` voxels (a cube), ``m``
        the largest ``s`` within ``thin_radius`` voxels along the local normal (from the weights within
        ``thin_radius + 1`` voxels), ``p`` rising from ``thin_power`` to ``thin_power * (1 +
        thin_ramp)`` over the iterations (0 radius: off).
    surface_level, undecided_level, min_pings : float, float, int
        Weight over ``x_ref`` from which a candidate is surface / undecided; pings a candidate must be
        in (within the aperture) for a decision.
    """

    iterations: int = 100
    adaptive_profile: bool = True
    profile_mix: float = 0.3
    aperture_scale: float = 1.5
    side_lobe_level: float = 0.01
    spreading_exponent: float = 0.5
    absorption_db_per_m: float = 0.04
    per_ping_gain: bool = True
    incidence: bool = True
    occlusion: bool = False
    cos_exponent: float = 1.0
    occlusion_m: float | None = None
    update_every: int = 25
    first_update: int = 25
    thin_radius: int = 4
    thin_power: float = 1.0
    thin_every: int = 10
    thin_smooth: int = 3
    thin_ramp: float = 7.0
    surface_level: float = 0.02
    undecided_level: float = 0.005
    min_pings: int = 2

    def __post_init__(self) -> None:
        for name, low in (("iterations", 0), ("update_every", 1), ("first_update", 0), ("min_pings", 1),
                          ("thin_radius", 0), ("thin_every", 1), ("thin_smooth", 1)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < low:
                raise ValueError(f"Expected an integer >= {low} for {name!r}, but got {v!r}")
        if not (np.isfinite(self.aperture_scale) and self.aperture_scale >= 1.0):
            raise ValueError(f"Expected aperture_scale >= 1, but got {self.aperture_scale}")
        for name in ("side_lobe_level", "spreading_exponent", "absorption_db_per_m", "cos_exponent",
                     "thin_power", "thin_ramp"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f"Expected {name} >= 0, but got {v}")
        if not 0.0 <= self.profile_mix <= 1.0:
            raise ValueError(f"Expected profile_mix in [0, 1], but got {self.profile_mix}")
        if not (0.0 < self.undecided_level <= self.surface_level and np.isfinite(self.surface_level)):
            raise ValueError(f"Expected 0 < undecided_level <= surface_level, but got {self.undecided_level} "
                             f"and {self.surface_level}")
        if self.occlusion_m is not None and not (np.isfinite(self.occlusion_m) and self.occlusion_m > 0):
            raise ValueError(f"Expected occlusion_m > 0 (metres) or None, but got {self.occlusion_m}")

    def to_dict(self) -> dict:
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}


@dataclass
class SurfaceFit:
    """The fit over ``grid`` (arrays (nx, ny, nz)).

    surface : bool
        What is there: candidates with ``sure >= 0.5`` in at least ``min_pings`` pings.
    undecided : bool
        Candidates the fit cannot decide (the safe map keeps them: an arm must still avoid them).
    candidates, observed : bool
        The safe map's occupied voxels the fit chose from, and the voxels it observed.
    sure : float32
        How sure the fit is that the voxel is surface, in [0, 1); NaN off the candidates.
    weight : float32
        Fitted weight ``x`` (>= 0; 0 off the candidates), display-energy units.
    pings : uint16
        Pings whose aperture holds the voxel.
    grid : GridSpec
    x_ref : float
        The data's weight of a surface (module docstring).
    gains : (n_pings,) float64
    stats : dict
        Counts, seconds and settings (JSON-ready).
    """

    surface: np.ndarray
    undecided: np.ndarray
    candidates: np.ndarray
    observed: np.ndarray
    sure: np.ndarray
    weight: np.ndarray
    pings: np.ndarray
    grid: GridSpec
    x_ref: float
    gains: np.ndarray
    stats: dict = field(default_factory=dict)

    def values(self) -> np.ndarray:
        """(nx, ny, nz) float32: 1 surface, 0.5 undecided, 0 observed otherwise, NaN never observed
        (occupied from 0.75: the surface; from 0.5: the surface and the undecided)."""
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
    return np.asarray(edges, np.float64)[np.r_[np.arange(0, len(edges) - 1, stride), len(edges) - 1]]


def _energy(image: np.ndarray, threshold: float, bin_stride: int, beam_stride: int
            ) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
    """One ping's coarse energy ((n_rc, n_bc) float64, ``-ln(1 - I)`` averaged over each coarse cell),
    its censored cells (bool: a saturated sonar cell), its floor (the median energy of the cells below
    ``threshold``; 0 if none) and its bright cells (bool: a sonar cell ``>= threshold``)."""
    img = np.asarray(image, np.float64) * (1.0 / 255.0 if image.dtype == np.uint8 else 1.0)
    cap = 1.0 - 0.5 / 255.0
    e = -np.log1p(-np.minimum(np.clip(img, 0.0, 1.0), cap))
    dark = img < threshold
    floor = float(np.median(e[dark])) if dark.any() else 0.0
    rb, cb = np.arange(0, img.shape[0], bin_stride), np.arange(0, img.shape[1], beam_stride)

    def pool(a: np.ndarray) -> np.ndarray:
        return np.add.reduceat(np.add.reduceat(a, rb, axis=0), cb, axis=1)

    n = np.diff(np.r_[rb, img.shape[0]])[:, None] * np.diff(np.r_[cb, img.shape[1]])[None, :]
    return pool(e) / n, pool((img >= cap).astype(np.int32)) > 0, floor, pool((~dark).astype(np.int32)) > 0


def _check(images: np.ndarray, poses: np.ndarray, spec: SonarSpec) -> tuple[np.ndarray, np.ndarray]:
    images, poses = np.asarray(images), np.asarray(poses, np.float64)
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


def _product(na: np.ndarray, nb: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each row's ``na`` x ``nb`` combinations of two lists: (row, index into each list)."""
    a0, b0 = np.cumsum(na) - na, np.cumsum(nb) - nb
    tot = na * nb
    row = np.repeat(np.arange(len(na)), tot)
    off = np.arange(int(tot.sum())) - np.repeat(np.cumsum(tot) - tot, tot)
    nbr = np.maximum(nb[row], 1)
    return row, a0[row] + off // nbr, b0[row] + off % nbr


@dataclass
class _Pings:
    """Every (ping, candidate) pair within the aperture and its entries (coarse cells, sorted by cell)."""

    pair_vox: np.ndarray  # (P,) candidate index
    pair_ping: np.ndarray  # (P,) ping
    pair_r: np.ndarray  # (P,) range, m
    pair_az: np.ndarray  # (P,) azimuth, rad
    pair_el: np.ndarray  # (P,) elevation, rad
    pair_dir_W: np.ndarray  # (P, 3) unit ray from the sonar, world frame
    pair_up_W: np.ndarray  # (P, 3) the sonar's z axis, world frame
    pair_w0: np.ndarray  # (P,) beam pattern x range loss / r^2
    ent_pair: np.ndarray  # (E,) pair of each entry
    ent_cell: np.ndarray  # (E,) compact cell index
    ent_frac: np.ndarray  # (E,) share of the voxel's width in the cell
    y: np.ndarray  # (C,) cell energy
    censored: np.ndarray  # (C,) bool
    bright: np.ndarray  # (C,) bool: holds a sonar cell >= threshold
    cell_ping: np.ndarray  # (C,) ping
    floor: np.ndarray  # (n_pings,)


def _build(centres_W: np.ndarray, grid: GridSpec, spec: SonarSpec, images: np.ndarray, poses: np.ndarray,
           threshold: float, opts: FitOptions) -> _Pings:
    h = grid.voxel_size_m
    bs, gs = _strides(spec, h)
    r_edges = spec.range_min_m + spec.bin_size_m * np.r_[np.arange(0, spec.n_bins, bs), spec.n_bins]
    b_edges = _coarse_edges(spec.beam_edges_rad, gs)
    n_cell = (len(r_edges) - 1) * (len(b_edges) - 1)
    half_el = opts.aperture_scale * 0.5 * spec.vfov_rad
    keys = ("vox", "r", "az", "el", "dir", "up", "w0", "ecell", "efrac", "epair")
    parts: dict[str, list] = {k: [] for k in keys}
    ys, sats, lits, floors, counts = [], [], [], [], []
    n_pairs = 0
    for p, (image, T) in enumerate(zip(images, poses, strict=True)):
        y, sat, floor, lit = _energy(image, threshold, bs, gs)
        ys.append(y.reshape(-1))
        sats.append(sat.reshape(-1))
        lits.append(lit.reshape(-1))
        floors.append(floor)
        R, t = T[:3, :3], T[:3, 3]
        d = centres_W - t
        q = d @ R  # the sonar frame
        rh = np.hypot(q[:, 0], q[:, 1])
        r = np.sqrt(rh * rh + q[:, 2] ** 2)
        el = np.arctan2(q[:, 2], rh)
        az = np.arctan2(q[:, 1], q[:, 0])
        k = np.flatnonzero((q[:, 0] > 0) & (r >= spec.range_min_m) & (r < spec.range_max_m)
                           & (np.abs(el) <= half_el) & (az >= b_edges[0]) & (az <= b_edges[-1]))
        r, el, az, rh = r[k], el[k], az[k], rh[k]
        w_az = np.arctan2(0.5 * h, rh)
        rr, rc, rf = _overlaps(r - 0.5 * h, r + 0.5 * h, r_edges)
        br, bc, bf = _overlaps(az - w_az, az + w_az, b_edges)
        pair, ir, ib = _product(np.bincount(rr, minlength=len(k)), np.bincount(br, minlength=len(k)))
        pattern = 0.5 ** ((2.0 * el / spec.vfov_rad) ** 2) + opts.side_lobe_level
        loss = r ** -opts.spreading_exponent * 10.0 ** (-2.0 * opts.absorption_db_per_m * (r - 1.0) / 10.0)
        for key, v in (("vox", k), ("r", r), ("az", az), ("el", el), ("dir", d[k] / r[:, None]),
                       ("up", np.broadcast_to(R[:, 2], (len(k), 3))), ("w0", pattern * loss / (r * r)),
                       ("ecell", p * n_cell + rc[ir] * (len(b_edges) - 1) + bc[ib]),
                       ("efrac", rf[ir] * bf[ib]), ("epair", pair + n_pairs)):
            parts[key].append(v)
        counts.append(len(k))
        n_pairs += len(k)
    cat = {k: np.concatenate(v) for k, v in parts.items()}
    order = np.argsort(cat["ecell"], kind="stable")
    cells, inv = np.unique(cat["ecell"][order], return_inverse=True)
    ping_of, local = cells // n_cell, cells % n_cell

    def take(lst: list) -> np.ndarray:
        return np.stack(lst)[ping_of, local]

    return _Pings(cat["vox"].astype(np.int64), np.repeat(np.arange(len(images)), counts), cat["r"], cat["az"],
                  cat["el"], cat["dir"].reshape(-1, 3), cat["up"].reshape(-1, 3), cat["w0"],
                  cat["epair"][order].astype(np.int64), inv.astype(np.int64), cat["efrac"][order], take(ys),
                  take(sats), take(lits), ping_of.astype(np.int64), np.asarray(floors, np.float64))


# ------------------------------------------------------------------------------ normals, incidence, occlusion
def _normals(cand_idx: np.ndarray, weights: np.ndarray, shape: tuple[int, int, int], radius: int = 2
             ) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals ((n, 3), grid axes = world axes) of the weighted candidates' local plane (the
    least-variance direction of the weights within ``radius`` voxels, a cube) and its planarity ((n,)
    in [0, 1]: 1 - smallest / middle variance)."""
    from scipy import ndimage

    w = np.zeros(shape)
    w[tuple(cand_idx.T)] = weights
    o = np.arange(-radius, radius + 1, dtype=np.float64)
    one = np.ones_like(o)

    def moment(ks) -> np.ndarray:  # a separable box moment: one 1-D kernel per axis
        a = w
        for axis, k in enumerate(ks):
            a = ndimage.correlate1d(a, k, axis=axis, mode="constant")
        return a[tuple(cand_idx.T)]

    m0 = moment((one, one, one))
    unit = [tuple(o if b == a else one for b in range(3)) for a in range(3)]
    m1 = np.stack([moment(u) for u in unit], -1)
    m2 = np.empty((len(cand_idx), 3, 3))
    for a in range(3):
        for b in range(a, 3):
            ks = [one, one, one]
            ks[a] = o if a != b else o * o
            if a != b:
                ks[b] = o
            m2[:, a, b] = m2[:, b, a] = moment(ks)
    safe = np.maximum(m0, 1e-12)
    mu = m1 / safe[:, None]
    val, vec = np.linalg.eigh(m2 / safe[:, None, None] - mu[:, :, None] * mu[:, None, :])
    planar = np.where(m0 > 1e-12, np.clip(1.0 - val[:, 0] / np.maximum(val[:, 1], 1e-12), 0.0, 1.0), 0.0)
    return vec[:, :, 0], planar


def _incidence(pk: _Pings, normals: np.ndarray, planar: np.ndarray, k: float) -> np.ndarray:
    """(P,) incidence term ``(cos^2 + 1e-4)^((k + 1) / 2)`` of every pair, blended by planarity with its
    mean over a hemisphere, ``1 / (k + 2)``."""
    cos = np.abs(np.einsum("ij,ij->i", normals[pk.pair_vox], pk.pair_dir_W))
    lam = planar[pk.pair_vox]
    return lam * (cos * cos + 1e-4) ** (0.5 * (k + 1.0)) + (1.0 - lam) / (k + 2.0)


def _thin(idx: np.ndarray, x: np.ndarray, shape: tuple[int, int, int], radius: int, power: float,
          smooth: int = 1) -> np.ndarray:
    """The thin-surface prior's step: ``x (x / m)^(power * planarity)``, ``m`` the largest weight within
    ``radius`` voxels along each voxel's normal (the least-variance direction of the weights around it):
    of a stack of weighted voxels across a surface only the heaviest keeps its weight, and the EM
    steps after it move the rest of the stack's energy to where the pings need it."""
    top = np.quantile(x[x > 0], 0.9) if np.any(x > 0) else 1.0
    nrm, planar = _normals(idx, np.clip(x / top, 0.0, 1.0), shape, radius + 1)
    from scipy import ndimage

    dense = np.zeros(shape)
    dense[tuple(idx.T)] = x
    if smooth > 1:
        dense = ndimage.uniform_filter(dense, smooth, mode="constant")
    own = dense[tuple(idx.T)]
    hi = np.array(shape) - 1
    m = own.copy()
    for k in range(1, radius + 1):
        for sgn in (-1.0, 1.0):
            q = idx + np.rint(sgn * k * nrm).astype(np.int64)
            ok = np.all((q >= 0) & (q <= hi), axis=1)
            m[ok] = np.maximum(m[ok], dense[tuple(q[ok].T)])
    ratio = np.clip(np.divide(own, m, out=np.zeros_like(x), where=m > 0), 0.0, 1.0)
    return x * ratio ** (power * planar)


def _transmittance(pk: _Pings, alpha: np.ndarray, spec: SonarSpec, h: float, occlusion_m: float,
                   aperture_scale: float, normals: np.ndarray | None = None,
                   planar: np.ndarray | None = None) -> np.ndarray:
    """(P,) transmittance of every pair: ``prod (1 - alpha_u)`` over the candidates ``u`` of the same ping
    more than ``occlusion_m`` nearer whose width covers the pair's (beam, elevation) ray cell. A voxel's
    width is its cube's or, with ``normals`` ((n, 3)), the disk of diameter ``h`` across them seen from
    the sonar (a floor seen at grazing incidence does not shadow itself), blended by ``planar``."""
    _, gs = _strides(spec, h)
    b_edges = _coarse_edges(spec.beam_edges_rad, gs)
    n_b = len(b_edges) - 1
    half_el = aperture_scale * 0.5 * spec.vfov_rad
    n_e = max(1, int(math.ceil(2.0 * half_el / float(np.mean(np.diff(b_edges))))))
    e_edges = np.linspace(-half_el, half_el, n_e + 1)
    a_u = alpha[pk.pair_vox]
    occ = np.flatnonzero(a_u > 0.02)
    if len(occ) == 0:
        return np.ones(len(pk.pair_vox))
    r, el, az = pk.pair_r[occ], pk.pair_el[occ], pk.pair_az[occ]
    s_az, s_el = np.full(len(occ), 0.5 * h), np.full(len(occ), 0.5 * h)
    if normals is not None:
        u, up = pk.pair_dir_W[occ], pk.pair_up_W[occ]
        e_el = up - np.einsum("ij,ij->i", up, u)[:, None] * u
        e_el /= np.maximum(np.linalg.norm(e_el, axis=1, keepdims=True), 1e-12)
        nv, lam = normals[pk.pair_vox[occ]], planar[pk.pair_vox[occ]]
        for arr, e in ((s_az, np.cross(e_el, u)), (s_el, e_el)):
            c = np.einsum("ij,ij->i", nv, e)
            arr[:] = lam * 0.5 * h * np.sqrt(np.maximum(1.0 - c * c, 0.0)) + (1.0 - lam) * arr
    w_az, w_el = np.arctan2(s_az, r * np.cos(el)), np.arctan2(s_el, r)
    ar, ac, _ = _overlaps(az - w_az, az + w_az, b_edges)
    er, ec, _ = _overlaps(el - w_el, el + w_el, e_edges)
    row, ia, ie = _product(np.bincount(ar, minlength=len(occ)), np.bincount(er, minlength=len(occ)))
    span = 2.0 * spec.range_max_m + occlusion_m + 1.0
    ray = (pk.pair_ping[occ][row] * n_b + ac[ia]) * n_e + ec[ie]
    key = ray * span + r[row]
    order = np.argsort(key, kind="stable")
    key = key[order]
    cum = np.r_[0.0, np.cumsum(np.log1p(-np.minimum(a_u[occ][row][order], 0.999)))]
    jc = np.clip(np.searchsorted(b_edges, pk.pair_az, side="right") - 1, 0, n_b - 1)
    ec_ = np.clip(np.searchsorted(e_edges, pk.pair_el, side="right") - 1, 0, n_e - 1)
    ray_c = (pk.pair_ping * n_b + jc) * n_e + ec_
    lo = np.searchsorted(key, ray_c * span, side="left")
    hi = np.searchsorted(key, ray_c * span + (pk.pair_r - occlusion_m), side="left")
    return np.exp(cum[np.maximum(hi, lo)] - cum[lo])


# ------------------------------------------------------------------------------ the fit
def _fit(cand: np.ndarray, grid: GridSpec, spec: SonarSpec, images: np.ndarray, poses: np.ndarray,
         threshold: float, opts: FitOptions) -> dict:
    """The EM fit (module docstring) of the candidates ``cand`` ((nx, ny, nz) bool)."""
    from scipy import sparse

    t0 = time.perf_counter()
    idx = np.argwhere(cand)
    n = len(idx)
    pk = _build(grid.centers(idx), grid, spec, images, poses, threshold, opts)
    n_p, n_pair, n_c = len(images), len(pk.pair_vox), len(pk.y)
    runs = np.flatnonzero(np.r_[True, pk.ent_cell[1:] != pk.ent_cell[:-1]])[:len(pk.y)]
    vox_e = pk.pair_vox[pk.ent_pair]
    A = sparse.csr_matrix((pk.ent_frac.copy(), vox_e, np.r_[runs, len(vox_e)]), shape=(n_c, n))
    t_build = time.perf_counter() - t0
    floor_c = pk.floor[pk.cell_ping]
    f = pk.ent_frac.copy()
    f_sum = np.bincount(pk.ent_pair, weights=f, minlength=n_pair)
    g = np.ones(n_p)
    inc, trans = np.ones(n_pair), np.ones(n_pair)
    pair_a = pk.pair_w0.copy()
    excess = np.maximum(pk.y - floor_c, 0.0)
    x = np.full(n, excess.sum() / max(float(np.sum(pair_a * f_sum)), 1e-300))
    occ_m = 2.0 * grid.voxel_size_m if opts.occlusion_m is None else opts.occlusion_m
    for it in range(int(opts.iterations)):
        if (opts.incidence or opts.occlusion) and it >= opts.first_update and it % opts.update_every == 0:
            A.data[:] = pair_a[pk.ent_pair] * f  # (the first: every candidate alike, normals of their shape)
            level = np.clip(x / max(_x_ref(pk, A, g, excess), 1e-300) / opts.surface_level, 0.0, 1.0)
            nrm, planar = _normals(idx, level, grid.shape)
            if opts.incidence:
                inc = _incidence(pk, nrm, planar, opts.cos_exponent)
            if opts.occlusion:
                trans = _transmittance(pk, level, spec, grid.voxel_size_m, occ_m, opts.aperture_scale, nrm,
                                       planar)
            new_a = pk.pair_w0 * inc * trans
            old_s = np.bincount(pk.pair_vox, weights=pair_a * f_sum * g[pk.pair_ping], minlength=n)
            new_s = np.bincount(pk.pair_vox, weights=new_a * f_sum * g[pk.pair_ping], minlength=n)
            x = np.where(new_s > 0, x * old_s / np.maximum(new_s, 1e-300), 0.0)  # the prediction stays
            pair_a = new_a
        A.data[:] = pair_a[pk.ent_pair] * f
        gc = g[pk.cell_ping]
        sig = A @ x
        yhat = gc * sig + floor_c
        ratio = np.divide(pk.y, yhat, out=np.ones_like(yhat), where=yhat > 0)
        ratio = np.where(pk.censored, np.maximum(ratio, 1.0), ratio)
        q = A.data * x[vox_e] * (gc * ratio)[pk.ent_cell]
        sens = np.bincount(pk.pair_vox, weights=pair_a * f_sum * g[pk.pair_ping], minlength=n)
        x = np.divide(np.bincount(vox_e, weights=q, minlength=n), sens, out=np.zeros(n), where=sens > 0)
        if opts.adaptive_profile:
            qp = np.bincount(pk.ent_pair, weights=q, minlength=n_pair)[pk.ent_pair]
            f = np.where(qp > 0, q / np.where(qp > 0, qp, 1.0) * f_sum[pk.ent_pair], f)
            if opts.profile_mix > 0:
                f = (1.0 - opts.profile_mix) * f + opts.profile_mix * pk.ent_frac
        if opts.per_ping_gain:
            s_den = np.bincount(pk.cell_ping, weights=sig, minlength=n_p)
            s_num = np.bincount(pk.cell_ping, weights=sig * ratio, minlength=n_p)
            g = g * np.divide(s_num, s_den, out=np.ones(n_p), where=s_den > 0)
            pos = g > 0
            if pos.any():
                scale = math.exp(float(np.mean(np.log(g[pos]))))
                g, x = g / scale, x * scale
        if opts.thin_radius and (it + 1) % opts.thin_every == 0 and it + 1 < opts.iterations:
            ramp = 1.0 + opts.thin_ramp * (it + 1) / opts.iterations
            x = _thin(idx, x, grid.shape, opts.thin_radius, opts.thin_power * ramp, opts.thin_smooth)
    A.data[:] = pair_a[pk.ent_pair] * f
    x_ref = _x_ref(pk, A, g, excess)
    yhat = g[pk.cell_ping] * (A @ x) + floor_c
    stats = {"candidates": n, "pairs": n_pair, "entries": len(vox_e), "cells": n_c, "build_seconds": t_build,
             "rms_cells": float(np.sqrt(np.mean((yhat - pk.y) ** 2))) if n_c else 0.0, "x_ref": x_ref}
    return {"x": x, "x_ref": x_ref, "pings": np.bincount(pk.pair_vox, minlength=n), "gains": g, "idx": idx,
            "stats": stats, "pk": pk, "A": A, "yhat": yhat}


def _x_ref(pk: _Pings, A, g: np.ndarray, excess: np.ndarray) -> float:
    """The weight that alone makes the median bright cell's energy above the floor from the median entry
    of a bright cell (the data's scale of a surface; 1 without a bright cell)."""
    b = pk.bright & (excess > 0)
    ent = b[pk.ent_cell]
    a = A.data * g[pk.cell_ping][pk.ent_cell]
    med = float(np.median(a[ent])) if ent.any() else 0.0
    return float(np.median(excess[b])) / med if med > 0 else 1.0


def fit_candidates(candidates: np.ndarray, observed: np.ndarray, grid: GridSpec, spec: SonarSpec,
                   images: np.ndarray, poses: np.ndarray, threshold: float,
                   options: FitOptions | None = None) -> SurfaceFit:
    """The surface fit of the candidate voxels from the pings.

    Parameters
    ----------
    candidates, observed : (nx, ny, nz) bool
        The voxels that may be surface (the safe map's occupied ones), and those the safe map observed.
    grid : GridSpec
    spec : SonarSpec
    images, poses : (n, n_bins, n_beams) uint8, float32 or float64; (n, 4, 4) float
        The pings, intensities in [0, 1] (uint8 scaled by 1/255), and their ``T_W_S``.
    threshold : float
        The safe map's occupied intensity, in (0, 1] (cells below it give the noise floor).
    options : FitOptions, optional

    Returns
    -------
    SurfaceFit
    """
    t0 = time.perf_counter()
    opts = options or FitOptions()
    if not isinstance(options, FitOptions | None):
        raise TypeError(f"Expected a FitOptions or None for 'options', but got {type(options).__name__}")
    if not isinstance(grid, GridSpec):
        raise TypeError(f"Expected a gpumap.GridSpec for 'grid', but got {type(grid).__name__}")
    if not isinstance(spec, SonarSpec):
        raise TypeError(f"Expected a gpumap.SonarSpec for 'spec', but got {type(spec).__name__}")
    cand, obs = np.asarray(candidates), np.asarray(observed)
    for name, a in (("candidates", cand), ("observed", obs)):
        if a.shape != grid.shape or a.dtype != bool:
            raise ValueError(f"Expected {name} of shape {grid.shape} bool, but got {a.dtype} {a.shape}")
    if np.any(cand & ~obs):
        raise ValueError(f"Expected candidates within the observed voxels, but {int(np.sum(cand & ~obs))} "
                         "were never observed")
    if not (np.isfinite(threshold) and 0.0 < threshold <= 1.0):
        raise ValueError(f"Expected threshold in (0, 1], but got {threshold}")
    images, poses = _check(images, poses, spec)
    res = _fit(cand, grid, spec, images, poses, float(threshold), opts)
    sl = tuple(res["idx"].T)

    def put(values: np.ndarray, fill, dtype) -> np.ndarray:
        out = np.full(grid.shape, fill, dtype)
        out[sl] = values
        return out

    level = res["x"] / res["x_ref"]
    big = float(np.finfo(np.float32).max)
    sure = put(level / (level + opts.surface_level), np.nan, np.float32)
    weight = put(np.minimum(res["x"], big), 0, np.float32)
    pings = put(np.minimum(res["pings"], np.iinfo(np.uint16).max), 0, np.uint16)
    enough, lv = put(res["pings"] >= opts.min_pings, False, bool), put(level, 0.0, np.float64)
    surface = enough & (lv >= opts.surface_level)
    undecided = cand & ~surface & (~enough | (lv >= opts.undecided_level))
    stats = {**res["stats"], "surface": int(surface.sum()), "undecided": int(undecided.sum()),
             "pings": len(images), "seconds": time.perf_counter() - t0, "options": opts.to_dict()}
    return SurfaceFit(surface, undecided, cand.copy(), obs.copy(), sure, weight, pings, grid, res["x_ref"],
                      res["gains"], stats)


def fit_surface(mapper, images: np.ndarray, poses: np.ndarray,
                options: FitOptions | None = None) -> SurfaceFit:
    """The surface fit of a :class:`gpumap.MinMaxMapper` from the pings it integrated: candidates
    ``mapper.values() >= mapper.threshold`` over its grid, with its sonar and threshold
    (:func:`fit_candidates`)."""
    v = mapper.values()
    cand = np.nan_to_num(v, nan=-np.inf) >= mapper.threshold
    return fit_candidates(cand, np.isfinite(v), mapper.grid, mapper.spec, images, poses, mapper.threshold,
                          options)
