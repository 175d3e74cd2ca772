"""``gpumap refine``: the occupancy field that, rendered through the ping model, explains the pings.

Analysis by synthesis (issue 19). Start from the visible rule's map and evidence
(:meth:`gpumap.MinMaxMapper.evidence`), then minimise over a voxel field (``o >= 0`` per voxel,
trilinear; reflectivity ``rho``; one display gain and noise floor per recording)::

    mean over a batch of pings of  sum over rendered cells huber(t(render(o, rho)) - t(measured), delta)
        + sparsity * sum over movable voxels o_v
        + smoothness * sum over neighbouring movable voxel pairs (o_v - o_n)^2

with ``t(I) = (I + 1e-3) ** power`` (square roots by default), by Adam on random batches of
pings (projected onto the bounds below after every step), the
gradients from Warp's tape (:class:`gpumap.render.PingRenderer`; CPU or CUDA). The gain starts
where the measured and rendered energies agree, the floor at the median measured intensity.

The returned ``occupancy`` is ``1 - exp(-kappa o)``: the fraction of the sound a one-voxel layer
of the field stops; the refined map calls a voxel occupied from :data:`OCCUPIED_LEVEL` (0.5) on.

Hard constraints, exactly:

- **Never occupy a voxel that clear dark views carved.** A voxel whose clear dark evidence
  reaches the mapper's ``carve_views`` (``evidence()["count"] >= carve_views``: the visible rule
  would carve it even had it been seen bright) has ``o = 0`` throughout (upper bound 0 in the
  projected Adam step), as has every voxel no ping observed (its occupancy is NaN). Only the
  other observed voxels ("movable") change.
- **Never free a voxel that a bright clear view needs.** For every training ping and every beam,
  the nearest range bin with intensity ``>= threshold`` (the mapper's; nothing at or above it
  lies nearer in that beam, so its echo comes from that bin's elevation arc) keeps an occupied
  voxel (occupancy ``>= OCCUPIED_LEVEL``) among the movable voxels whose bounding sphere (radius
  ``sqrt(3)/2`` voxel) reaches that bin and beam within ``|elevation| <= vfov/2 +`` the sphere's
  angular radius. After the optimisation, where none is left, the one with the highest occupancy
  (ties: the lowest flat index) is raised to ``OCCUPIED_LEVEL``; :attr:`RefineResult.raised` marks
  them. Bins with no movable voxel at all (everything there carved) are counted in
  ``stats["unexplained_cells"]``.

``confidence`` is ``|2 occupancy - 1| * (1 - exp(-views / 4))`` with ``views`` the training pings
whose field of view holds the voxel's centre (a voxel few pings saw is not trusted whatever its
value).
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field

import numpy as np

from gpumap.render import PingModel, PingRenderer
from gpumap.spec import GridSpec, SonarSpec

__all__ = [
    "RefineOptions",
    "RefineResult",
    "refine",
    "render_map",
    "heldout_scores",
    "roc_auc",
    "OCCUPIED_LEVEL",
]

#: Refined occupancy from which a voxel is called occupied.
OCCUPIED_LEVEL = 0.5


@dataclass(frozen=True)
class RefineOptions:
    """Settings of :func:`refine` (the same defaults on every scene).

    Attributes
    ----------
    iterations : int
        Adam steps.
    pings_per_step : int
        Training pings rendered per step (drawn at random, without replacement within a pass).
    learning_rate : float
        Adam step of occupancy and reflectivity (units of [0, 1] per step).
    huber_delta : float
        Residual (intensity) beyond which the loss grows linearly: speckle and unmodelled echoes
        do not dominate.
    smoothness : float
        Weight of the squared neighbour differences of the field, per pair of movable voxels,
        against the data term summed over a ping's rendered cells (default 0: off).
    sparsity : float
        Weight of the field's sum over movable voxels: explain the pings with as little matter
        as they need (a phantom voxel that no echo needs decays to empty).
    power : float
        The loss compares ``(intensity + 1e-3) ** power``: 0.5 (square roots) lets a dim grazing
        surface weigh nearly as much as a bright one; 1 compares intensities.
    init_occupancy : float
        Starting field value ``o`` of the voxels the visible map calls occupied (others start at
        0); ``o = 0.5`` stops ``1 - exp(-kappa / 2)`` = 86 % of the sound in one voxel.
    seed : int
        Seed of the ping order.
    """

    iterations: int = 300
    pings_per_step: int = 8
    learning_rate: float = 0.08
    huber_delta: float = 0.1
    smoothness: float = 0.0
    init_occupancy: float = 0.5
    sparsity: float = 3e-4
    power: float = 0.5
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("iterations", "pings_per_step"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
                raise ValueError(f"Expected a positive integer for {name!r}, but got {v!r}")
        for name in ("learning_rate", "huber_delta"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"Expected a finite {name!r} > 0, but got {v!r}")
        for name in ("smoothness", "sparsity"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"Expected a finite {name!r} >= 0, but got {v!r}")
        if not (isinstance(self.power, (int, float)) and 0 < self.power <= 1):
            raise ValueError(f"Expected 'power' in (0, 1], but got {self.power!r}")
        if not 0 <= self.init_occupancy <= 1:
            raise ValueError(f"Expected 'init_occupancy' in [0, 1], but got {self.init_occupancy!r}")

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class RefineResult:
    """What :func:`refine` returns.

    Attributes
    ----------
    occupancy : (nx, ny, nz) float32
        Refined occupancy in [0, 1], NaN where no ping observed the voxel; occupied from
        :data:`OCCUPIED_LEVEL` on.
    confidence : (nx, ny, nz) float32
        In [0, 1], NaN unobserved (see the module docstring).
    reflectivity : (nx, ny, nz) float32
        The fitted reflectivity (meaningful where the occupancy is high).
    carved, raised : (nx, ny, nz) bool
        Voxels held free by the first hard constraint; voxels raised by the second.
    gain, floor : float
        The fitted display gain and noise floor.
    history : list of float
        Loss per step (data + smoothness, per ping).
    stats : dict
        ``seconds``, ``device``, ``unexplained_cells``, ``raised_voxels``, the options and model.
    """

    occupancy: np.ndarray
    confidence: np.ndarray
    reflectivity: np.ndarray
    carved: np.ndarray
    raised: np.ndarray
    gain: float
    floor: float
    history: list[float] = field(default_factory=list)
    stats: dict = field(default_factory=dict)

    def occupied(self) -> np.ndarray:
        """(nx, ny, nz) bool: observed voxels with occupancy ``>= OCCUPIED_LEVEL`` (the surfaces
        the fitted field puts where the pings need them: thin, and FN-prone, see the report)."""
        return np.nan_to_num(self.occupancy, nan=-1.0) >= OCCUPIED_LEVEL

    def banded(self, visible_values: np.ndarray, threshold: float, band_voxels: int = 1) -> np.ndarray:
        """(nx, ny, nz) bool: the visible map's occupied voxels (``visible_values >= threshold``)
        within ``band_voxels`` (26-neighbourhood steps) of a refined occupied voxel.

        The refined surfaces decide which of the visible rule's voxels stay: its phantoms away
        from every surface the pings need are dropped, and a surface keeps the visible rule's
        thickness there (a trilinear field sampled at half a voxel places a surface to about a
        voxel). 1 is the default the report's figures use on every scene.
        """
        from scipy import ndimage

        v = np.asarray(visible_values)
        if v.shape != self.occupancy.shape:
            raise ValueError(f"Expected visible_values of shape {self.occupancy.shape}, but got {v.shape}")
        if isinstance(band_voxels, bool) or not isinstance(band_voxels, (int, np.integer)) or band_voxels < 0:
            raise ValueError(f"Expected a non-negative integer for 'band_voxels', but got {band_voxels!r}")
        occ = self.occupied()
        if band_voxels > 0:
            occ = ndimage.binary_dilation(
                occ, structure=np.ones((3, 3, 3), bool), iterations=int(band_voxels)
            )
        return occ & (np.nan_to_num(v, nan=-np.inf) >= np.float32(threshold))


# ---------------------------------------------------------------------- checks
def _check_images_poses(
    spec: SonarSpec, images: np.ndarray, poses: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    a = np.asarray(images)
    if a.ndim != 3 or a.shape[1:] != spec.image_shape:
        raise ValueError(f"Expected images of shape (N, {spec.n_bins}, {spec.n_beams}), but got {a.shape}")
    if a.dtype != np.uint8:
        if a.dtype.kind != "f":
            raise TypeError(f"Expected uint8 or float images, but got dtype {a.dtype}")
        if not np.all(np.isfinite(a)) or a.min() < 0 or a.max() > 1:
            raise ValueError("Expected float images with finite values in [0, 1], but got values outside")
    P = PingRenderer._check_poses(poses)
    if len(P) != len(a):
        raise ValueError(f"Expected one pose per image ({len(a)}), but got {len(P)} poses")
    if len(a) == 0:
        raise ValueError("Expected at least one ping, but got none")
    return a, P


def _as_float(images: np.ndarray) -> np.ndarray:
    return (
        images.astype(np.float32) / np.float32(255.0)
        if images.dtype == np.uint8
        else images.astype(np.float32)
    )


# ---------------------------------------------------------------------- the optimiser
class _Fit:
    """Warp arrays of one fit: the field, its bounds and Adam moments, the measured images."""

    def __init__(
        self,
        renderer: PingRenderer,
        occ0: np.ndarray,
        upper: np.ndarray,
        refl0: np.ndarray,
        measured: np.ndarray,
        log_gain: float,
        floor: float,
    ) -> None:
        r = renderer
        wp, dev = r._wp, r.device
        self.r, self.wp, self.dev = r, wp, dev
        self.occ = wp.array(occ0.astype(np.float32), dtype=wp.float32, device=dev, requires_grad=True)
        self.refl = wp.array(refl0.astype(np.float32), dtype=wp.float32, device=dev, requires_grad=True)
        self.glob = wp.array(
            np.array([log_gain, floor], np.float32), dtype=wp.float32, device=dev, requires_grad=True
        )
        self.active = wp.array((upper > 0).astype(np.uint8), dtype=wp.uint8, device=dev)
        n = occ0.size
        self.bounds = {
            "occ": (
                wp.zeros(n, dtype=wp.float32, device=dev),
                wp.array(upper.reshape(-1).astype(np.float32), dtype=wp.float32, device=dev),
            ),
            "refl": (
                wp.full(n, 0.05, dtype=wp.float32, device=dev),
                wp.full(n, 1.0, dtype=wp.float32, device=dev),
            ),
            "glob": (
                wp.array([-5.0, 0.0], dtype=wp.float32, device=dev),
                wp.array([15.0, 0.5], dtype=wp.float32, device=dev),
            ),
        }
        self.moments = {
            k: (
                wp.zeros(len(b[0]), dtype=wp.float32, device=dev),
                wp.zeros(len(b[0]), dtype=wp.float32, device=dev),
            )
            for k, b in self.bounds.items()
        }
        self.measured = measured  # host (N, nr, nb) float32
        self.ones = None
        self.t = 0

    def step_loss(self, idx: np.ndarray, opts: RefineOptions, lrs: dict[str, float] | None = None) -> float:
        """One forward + backward over pings ``idx``; an Adam step on the arrays named in ``lrs``."""
        wp, r, dev, kr = self.wp, self.r, self.dev, self.r._kr
        B = len(idx)
        R, t = r._pose_arrays(self.poses[idx])
        tape = wp.Tape()
        E = r.record_energy(tape, self.occ, self.refl, R, t, B)
        meas = wp.array(self.measured[idx], dtype=wp.float32, device=dev)
        if self.ones is None or self.ones.shape[0] != B:
            self.ones = wp.ones(E.shape, dtype=wp.float32, device=dev)
        loss = wp.zeros(1, dtype=wp.float32, device=dev, requires_grad=True)
        pred = wp.zeros(E.shape, dtype=wp.float32, device=dev, requires_grad=True)
        with tape:
            wp.launch(
                kr.image_loss,
                dim=E.shape,
                device=dev,
                inputs=[E, meas, self.ones, self.glob, float(opts.huber_delta), 1.0 / B, float(opts.power)],
                outputs=[pred, loss],
            )
            if opts.smoothness > 0 or opts.sparsity > 0:
                wp.launch(
                    kr.smoothness,
                    dim=self.occ.shape,
                    device=dev,
                    inputs=[self.occ, self.active, float(opts.smoothness), float(opts.sparsity)],
                    outputs=[loss],
                )
        tape.backward(loss)
        value = float(loss.numpy()[0])
        if lrs:
            self.t += 1
            b1, b2 = 0.9, 0.999
            arrays = {"occ": self.occ, "refl": self.refl, "glob": self.glob}
            for name, lr in lrs.items():
                a = arrays[name]
                m, v = self.moments[name]
                lo, hi = self.bounds[name]
                wp.launch(
                    kr.adam_project,
                    dim=len(m),
                    device=dev,
                    inputs=[
                        a.flatten(),
                        a.grad.flatten(),
                        m,
                        v,
                        lo,
                        hi,
                        float(lr),
                        b1,
                        b2,
                        1.0 - b1**self.t,
                        1.0 - b2**self.t,
                    ],
                )
        tape.zero()
        return value


def _first_bright(img: np.ndarray, thr: float) -> np.ndarray:
    """(n_beams,) int: the nearest bin ``>= thr`` of each beam, -1 where none."""
    b = img >= np.float32(thr)
    first = np.argmax(b, axis=0)
    return np.where(b.any(axis=0), first, -1)


def _views_and_raise(
    spec: SonarSpec,
    grid: GridSpec,
    occ: np.ndarray,
    movable: np.ndarray,
    images: np.ndarray,
    poses: np.ndarray,
    thr: float,
) -> tuple[np.ndarray, np.ndarray, int]:
    """(views per voxel, voxels raised, cells with no movable voxel) of the second hard constraint."""
    flat_occ = occ.reshape(-1)  # modified in place (a view of occ)
    centres = grid.centers(np.argwhere(np.ones(grid.shape, bool)))
    views = np.zeros(grid.n_voxels, np.int32)
    raised = np.zeros(grid.n_voxels, bool)
    mov = movable.reshape(-1)
    rho = 0.5 * math.sqrt(3.0) * grid.voxel_size_m
    unexplained = 0
    for img, T in zip(images, poses, strict=True):
        p_S = (centres - T[:3, 3]) @ T[:3, :3]
        views += spec.in_fov(p_S)
        fb = _first_bright(_as_float(img), thr)
        cand = np.flatnonzero(mov)
        q = p_S[cand]
        r = np.linalg.norm(q, axis=1)
        el = np.arctan2(q[:, 2], np.hypot(q[:, 0], q[:, 1]))
        az = np.arctan2(q[:, 1], q[:, 0])
        ang = np.arcsin(np.clip(rho / np.maximum(r, 1e-9), 0, 1))
        ok = (
            (r + rho >= spec.range_min_m)
            & (r - rho < spec.range_max_m)
            & (np.abs(el) <= 0.5 * spec.vfov_rad + ang)
        )
        ok &= (az + ang >= spec.beam_edges_rad[0]) & (az - ang <= spec.beam_edges_rad[-1])
        cand, r, az, ang = cand[ok], r[ok], az[ok], ang[ok]
        if len(cand) == 0:
            unexplained += int((fb >= 0).sum())
            continue
        dr = spec.bin_size_m
        i0 = np.floor((r - rho - spec.range_min_m) / dr).astype(np.int64)
        i1 = np.floor((r + rho - spec.range_min_m) / dr).astype(np.int64)
        b0 = np.clip(np.searchsorted(spec.beam_edges_rad, az - ang, side="right") - 1, 0, spec.n_beams - 1)
        b1 = np.clip(np.searchsorted(spec.beam_edges_rad, az + ang, side="right") - 1, 0, spec.n_beams - 1)
        n_b = b1 - b0 + 1
        rep = np.repeat(np.arange(len(cand)), n_b)
        beam = b0[rep] + (np.arange(rep.size) - np.repeat(np.cumsum(n_b) - n_b, n_b))
        f = fb[beam]
        cover = (f >= 0) & (f >= i0[rep]) & (f <= i1[rep])
        vox, beam = cand[rep[cover]], beam[cover]
        need = np.flatnonzero(fb >= 0)
        has = np.zeros(spec.n_beams, bool)
        has[beam] = True
        unexplained += int((~has[need]).sum())
        if len(vox) == 0:
            continue
        val = flat_occ[vox]
        best = np.full(spec.n_beams, -1.0, np.float32)
        np.maximum.at(best, beam, val)
        short = has & (best < OCCUPIED_LEVEL)
        if not short.any():
            continue
        sel = short[beam] & (val == best[beam])
        order = np.lexsort((vox[sel], beam[sel]))  # per beam, the lowest voxel index among ties
        bsel, vsel = beam[sel][order], vox[sel][order]
        first = np.r_[True, bsel[1:] != bsel[:-1]]
        up = vsel[first]
        flat_occ[up] = np.float32(OCCUPIED_LEVEL)
        raised[up] = True
    return views.reshape(grid.shape), raised.reshape(grid.shape), unexplained


def _calibrate(
    r: PingRenderer,
    occ: np.ndarray,
    refl: np.ndarray,
    measured: np.ndarray,
    poses: np.ndarray,
    delta: float,
    n: int = 16,
) -> tuple[float, float]:
    """(log gain, floor) of the display law for a field, from ``n`` evenly spread pings.

    The floor is the median measured intensity (most cells are water). The gain conserves energy:
    the measured energy ``-log(1 - I')`` (``I' = (I - floor) / (1 - floor)`` clipped to
    [0, 0.99]) summed over every cell, over the field's summed rendered energy. Where a map puts a
    surface at the wrong range or elevation the sums still agree, so a stretched map does not drag
    the gain down as a least-squares fit would. ``delta`` is unused (kept for the signature).
    """
    del delta
    sel = np.unique(np.linspace(0, len(poses) - 1, min(n, len(poses))).round().astype(int))
    E = r.energy(occ, refl, poses[sel])
    M = measured[sel]
    floor = float(np.median(M))
    ip = np.clip((M - floor) / (1.0 - floor), 0.0, 0.99)
    e_meas = float(-np.log1p(-ip).sum())
    e_model = float(E.sum())
    if e_model <= 0 or e_meas <= 0:
        return 0.0, floor
    return float(np.clip(math.log(e_meas / e_model), -5.0, 15.0)), floor


def refine(
    mapper,
    images: np.ndarray,
    poses: np.ndarray,
    *,
    options: RefineOptions | None = None,
    model: PingModel | None = None,
    device: str = "auto",
    progress: bool = False,
) -> RefineResult:
    """Refine the visible map of ``mapper`` against the pings it was built from.

    Parameters
    ----------
    mapper : gpumap.MinMaxMapper
        With ``rule="visible"`` (its ``values()``, ``evidence()``, ``threshold`` and
        ``carve_views`` are read; the mapper is not changed).
    images : (N, n_bins, n_beams) uint8 or float32 in [0, 1]
        The training pings (the ones the map holds).
    poses : (N, 4, 4) float64
        Their ``T_W_S``.
    options : RefineOptions, optional
    model : PingModel, optional
    device : str
        ``"auto"``, ``"cpu"``, ``"cuda"`` or ``"cuda:N"`` (Warp); a named device never falls back.
    progress : bool
        A tqdm bar over the steps.
    """
    from gpumap.mapper import MinMaxMapper

    if not isinstance(mapper, MinMaxMapper):
        raise TypeError(f"Expected a gpumap.MinMaxMapper for 'mapper', but got {type(mapper).__name__}")
    if mapper.rule != "visible":
        raise ValueError(f"Expected a mapper with rule='visible', but its rule is {mapper.rule!r}")
    opts = options or RefineOptions()
    if not isinstance(opts, RefineOptions):
        raise TypeError(f"Expected RefineOptions for 'options', but got {type(opts).__name__}")
    spec, grid = mapper.spec, mapper.grid
    images, P = _check_images_poses(spec, images, poses)
    t0 = time.perf_counter()
    values = mapper.values()
    ev = mapper.evidence()
    thr = float(mapper.threshold)
    observed = np.isfinite(values)
    carved = observed & (ev["count"] >= mapper.carve_views)
    movable = observed & ~carved
    occ0 = np.where(movable & (np.nan_to_num(values, nan=-1.0) >= thr), opts.init_occupancy, 0.0).astype(
        np.float32
    )
    upper = movable.astype(np.float32)
    refl0 = np.full(grid.shape, 0.5, np.float32)

    r = PingRenderer(spec, grid, model, device=device)
    measured = r.coarsen(images)
    log_gain, floor = _calibrate(r, occ0, refl0, measured, P, opts.huber_delta)
    fit = _Fit(r, occ0, upper, refl0, measured, log_gain, floor)
    fit.poses = P

    rng = np.random.default_rng(opts.seed)
    order = np.empty(0, np.int64)
    history = []
    from tqdm import tqdm

    lrs = {"occ": opts.learning_rate, "refl": opts.learning_rate, "glob": 0.02}
    for _ in tqdm(range(opts.iterations), desc="refine", unit="step", disable=not progress):
        if len(order) < min(opts.pings_per_step, len(P)):
            order = np.concatenate([order, rng.permutation(len(P))])
        idx, order = order[: opts.pings_per_step], order[opts.pings_per_step :]
        history.append(fit.step_loss(np.sort(idx), opts, lrs))
    occ = fit.occ.numpy().astype(np.float32)
    refl = fit.refl.numpy().astype(np.float32)
    log_gain, floor = (float(x) for x in fit.glob.numpy())
    occ[~movable] = 0.0
    # occupancy = the stop probability of a one-voxel layer of the fitted field
    occ = (-np.expm1(-r.model.kappa * occ)).astype(np.float32)
    views, raised, unexplained = _views_and_raise(spec, grid, occ, movable, images, P, thr)
    conf = (np.abs(2.0 * occ - 1.0) * (1.0 - np.exp(-views / 4.0))).astype(np.float32)
    occ_out = np.where(observed, occ, np.nan).astype(np.float32)
    conf = np.where(observed, conf, np.nan).astype(np.float32)
    stats = {
        "seconds": time.perf_counter() - t0,
        "device": r.device,
        "unexplained_cells": unexplained,
        "raised_voxels": int(raised.sum()),
        "carved_voxels": int(carved.sum()),
        "movable_voxels": int(movable.sum()),
        "options": opts.to_dict(),
        "model": r.model.to_dict(),
        "render_cells": list(r.image_shape),
        "elevation_rays": r.n_elevations,
    }
    return RefineResult(occ_out, conf, refl, carved, raised, math.exp(log_gain), floor, history, stats)


# ---------------------------------------------------------------------- held-out prediction
def roc_auc(score: np.ndarray, label: np.ndarray) -> float:
    """Area under the ROC curve of ``score`` for boolean ``label`` (ties count half); NaN if one class."""
    s = np.asarray(score, np.float64).ravel()
    y = np.asarray(label, bool).ravel()
    n1, n0 = int(y.sum()), int((~y).sum())
    if n1 == 0 or n0 == 0:
        return float("nan")
    from scipy.stats import rankdata

    ranks = rankdata(s)
    return float((ranks[y].sum() - n1 * (n1 + 1) / 2) / (n1 * n0))


def render_map(
    renderer: PingRenderer,
    occupancy: np.ndarray,
    poses: np.ndarray,
    *,
    reflectivity=None,
    train_images: np.ndarray | None = None,
    train_poses: np.ndarray | None = None,
    gain: float | None = None,
    floor: float | None = None,
    delta: float = 0.1,
) -> tuple[np.ndarray, float, float]:
    """Rendered images of a map at ``poses``: ``(images, gain, floor)``.

    ``occupancy`` (nx, ny, nz) in [0, 1], NaN unknown (rendered empty). Without ``gain`` the
    display gain and floor are fitted on ``train_images`` / ``train_poses`` (as :func:`refine`
    calibrates), so every map is compared at its own best scale.
    """
    occ = np.nan_to_num(np.asarray(occupancy, np.float32), nan=0.0)
    refl = (
        np.full(occ.shape, 0.5, np.float32) if reflectivity is None else np.asarray(reflectivity, np.float32)
    )
    if gain is None:
        if train_images is None or train_poses is None:
            raise ValueError("Expected train_images and train_poses to fit the gain, but got None")
        lg, floor = _calibrate(
            renderer,
            occ,
            refl,
            renderer.coarsen(train_images),
            PingRenderer._check_poses(train_poses),
            delta,
            n=16,
        )
        gain = math.exp(lg)
    return renderer.render(occ, refl, poses, gain, floor or 0.0), float(gain), float(floor or 0.0)


def heldout_scores(predicted: np.ndarray, measured: np.ndarray, threshold: float) -> dict[str, float]:
    """Bright-cell prediction of held-out pings: ``roc_auc`` of the rendered intensity for the
    cells whose measured (cell-averaged) intensity is ``>= threshold``, the Pearson
    ``correlation`` of rendered and measured intensities, and the ``bright_fraction``."""
    p = np.asarray(predicted, np.float64).ravel()
    m = np.asarray(measured, np.float64).ravel()
    y = m >= threshold
    corr = float(np.corrcoef(p, m)[0, 1]) if p.std() > 0 and m.std() > 0 else float("nan")
    return {"roc_auc": roc_auc(p, y), "correlation": corr, "bright_fraction": float(y.mean())}
