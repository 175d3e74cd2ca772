"""``gpumap refine``: the occupancy field that, rendered through the ping model, explains the pings.

Analysis by synthesis (issue 19). Start from a map that keeps evidence (the evidence rule, the
default, or the visible rule; :meth:`gpumap.MinMaxMapper.evidence`), live or saved
(:func:`refine_saved`), then minimise over a voxel field (``o >= 0`` per voxel,
trilinear; reflectivity ``rho``; one display gain and noise floor per recording)::

    mean over a batch of pings of  sum over rendered cells huber(t(render(o, rho)) - t(measured), delta)
        + sparsity * sum over movable voxels o_v
        + smoothness * sum over neighbouring movable voxel pairs (o_v - o_n)^2

with ``t(I) = (I + 1e-3) ** power`` (square roots by default), by Adam on random batches of
pings (projected onto the bounds below after every step), the
gradients from Warp's tape (:class:`gpumap.render.PingRenderer`; CPU or CUDA). The gain starts
where the measured and rendered energies agree, the floor at the median measured intensity.

Two names for two quantities, kept apart everywhere:

- the **field** ``o`` in [0, 1] (:attr:`RefineResult.field`): what the renderer takes
  (:func:`render_map`'s ``field``, :meth:`gpumap.render.PingRenderer.render`'s occupancy);
- the **occupancy** ``1 - exp(-kappa o)`` (:attr:`RefineResult.occupancy`): the fraction of the
  sound a one-voxel layer of the field stops, a probability; the refined map calls a voxel
  occupied from :data:`OCCUPIED_LEVEL` (0.5) on. :func:`field_from_occupancy` and
  :func:`occupancy_from_field` convert (``kappa`` of the :class:`~gpumap.render.PingModel`).

Hard constraints, exactly:

- **Never occupy a voxel that clear dark views carved** (:func:`carved_voxels`). Visible rule:
  a voxel whose clear dark evidence reaches the mapper's ``carve_views``
  (``evidence()["count"] >= carve_views``: the rule would carve it even had it been seen
  bright). Evidence rule: an observed voxel with at least one clear view (``count + hits > 0``)
  that the rule calls free (``not evidence_occupied(count, hits, bright_share, share_z)``, the
  mapper's settings): seen bright but shown at ``share_z`` to be bright in fewer than
  ``bright_share`` of its views, or never bright with clear dark views. An observed voxel with no
  clear view at all (only dark views behind a return: shadow) is not carved. A carved voxel has
  ``o = 0`` throughout (upper bound 0 in the projected Adam step), as has every voxel no ping
  observed (its occupancy is NaN). Only the other observed voxels ("movable") change.
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

import json
import logging
import math
import os
import sys
import time
import types
import warnings
from dataclasses import asdict, dataclass
from dataclasses import field as _dc_field
from pathlib import Path

import numpy as np

from gpumap.errors import BackendUnavailableError
from gpumap.first_return import first_bright_bins
from gpumap.render import PingModel, PingRenderer
from gpumap.spec import GridSpec, SonarSpec

__all__ = [
    "RefineOptions",
    "RefineResult",
    "refine",
    "refine_saved",
    "carved_voxels",
    "pick_device",
    "recording_frames",
    "map_frames",
    "load_refined",
    "is_refined_file",
    "field_from_occupancy",
    "occupancy_from_field",
    "render_map",
    "heldout_scores",
    "roc_auc",
    "OCCUPIED_LEVEL",
    "REFINED_FORMAT",
]

log = logging.getLogger(__name__)

#: Refined occupancy from which a voxel is called occupied.
OCCUPIED_LEVEL = 0.5
#: Rules whose maps keep the evidence refinement reads (:meth:`gpumap.MinMaxMapper.evidence`).
REFINE_RULES = ("evidence", "visible")
#: ``format`` in the metadata of a refined map file (:meth:`RefineResult.save`).
REFINED_FORMAT = "gpumap-refined"
REFINED_VERSION = 1


def occupancy_from_field(field_o: np.ndarray, kappa: float) -> np.ndarray:
    """Occupancy ``1 - exp(-kappa o)`` (the share of the sound a one-voxel layer stops, in
    [0, 1)) of field values ``o`` ((nx, ny, nz) float, NaN kept); float32."""
    o = np.asarray(field_o, np.float32)
    return (-np.expm1(-np.float32(kappa) * o)).astype(np.float32)


def field_from_occupancy(occupancy: np.ndarray, kappa: float) -> np.ndarray:
    """Inverse of :func:`occupancy_from_field`: field values ``o = -log(1 - occupancy) / kappa``
    (occupancy in [0, 1), NaN kept; an occupancy of 1 gives ``inf``); float32."""
    q = np.asarray(occupancy, np.float64)
    with np.errstate(divide="ignore"):
        return (-np.log1p(-q) / float(kappa)).astype(np.float32)


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
    """What :func:`refine` returns (and :func:`load_refined` reads back).

    Attributes
    ----------
    occupancy : (nx, ny, nz) float32
        Refined occupancy ``1 - exp(-kappa o)`` in [0, 1): the share of the sound a one-voxel
        layer of the fitted field stops (a probability, not the field: see :attr:`field`); NaN
        where no ping observed the voxel; occupied from :data:`OCCUPIED_LEVEL` on.
    confidence : (nx, ny, nz) float32
        In [0, 1], NaN unobserved (see the module docstring).
    reflectivity : (nx, ny, nz) float32
        The fitted reflectivity (meaningful where the occupancy is high).
    carved, raised : (nx, ny, nz) bool
        Voxels held free by the first hard constraint (:func:`carved_voxels`); voxels raised by
        the second.
    gain, floor : float
        The fitted display gain and noise floor.
    history : list of float
        Loss per step (data + smoothness, per ping).
    stats : dict
        ``seconds``, ``device`` and ``device_reason`` (:func:`pick_device`),
        ``unexplained_cells``, ``raised_voxels``, ``carved_voxels``, ``movable_voxels``, the
        options and model.
    field : (nx, ny, nz) float32 or None
        The field ``o`` in [0, 1] that the renderer takes (:func:`render_map`), NaN unobserved;
        ``occupancy == occupancy_from_field(field, kappa)``. Render a result with
        ``render_map(renderer, res.field, poses, reflectivity=res.reflectivity, gain=res.gain,
        floor=res.floor)``, never with ``res.occupancy``.
    threshold : float or None
        The map's bright threshold the result was made with (:meth:`banded` uses it).
    rule : str or None
        The map's rule (``"evidence"`` or ``"visible"``).
    map_values : (nx, ny, nz) float32 or None
        The map's values (NaN unknown): the safe obstacle layer is ``map_values >= threshold``
        (:meth:`safe`).
    spec : SonarSpec or None
    grid : GridSpec or None
        The sonar and grid of the map.
    """

    occupancy: np.ndarray
    confidence: np.ndarray
    reflectivity: np.ndarray
    carved: np.ndarray
    raised: np.ndarray
    gain: float
    floor: float
    history: list[float] = _dc_field(default_factory=list)
    stats: dict = _dc_field(default_factory=dict)
    field: np.ndarray | None = None
    threshold: float | None = None
    rule: str | None = None
    map_values: np.ndarray | None = None
    spec: SonarSpec | None = None
    grid: GridSpec | None = None

    def occupied(self) -> np.ndarray:
        """(nx, ny, nz) bool: observed voxels with occupancy ``>= OCCUPIED_LEVEL`` (the surfaces
        the fitted field puts where the pings need them: thin, and FN-prone, see the report)."""
        return np.nan_to_num(self.occupancy, nan=-1.0) >= OCCUPIED_LEVEL

    def safe(self) -> np.ndarray:
        """(nx, ny, nz) bool: the map's occupied voxels (``map_values >= threshold``), the safe
        obstacle layer (a superset of what the pings need; keep a vehicle out of it)."""
        if self.map_values is None or self.threshold is None:
            raise ValueError("Expected a result that holds the map's values and threshold for safe(), "
                             "but this one has none (made by hand?)")
        return np.nan_to_num(self.map_values, nan=-np.inf) >= np.float32(self.threshold)

    def banded(self, map_values: np.ndarray | None = None, threshold: float | None = None,
               band_voxels: int = 1) -> np.ndarray:
        """(nx, ny, nz) bool: the map's occupied voxels (``map_values >= threshold``) within
        ``band_voxels`` (26-neighbourhood steps) of a refined occupied voxel.

        The refined surfaces decide which of the map's voxels stay: its phantoms away from every
        surface the pings need are dropped, and a surface keeps the map's thickness there (a
        trilinear field sampled at half a voxel places a surface to about a voxel). 1 is the
        default the report's figures use on every scene.

        Parameters
        ----------
        map_values : (nx, ny, nz) float, optional
            The map's values (NaN unknown); default :attr:`map_values`, those the result was
            made from.
        threshold : float, optional
            Default :attr:`threshold`, the one the result was made with. Given, it must equal it
            (a map read at another threshold has other constraints): else ``ValueError``.
        band_voxels : int
        """
        from scipy import ndimage

        if threshold is None:
            if self.threshold is None:
                raise ValueError("Expected a threshold for banded() (this result holds none), but got None")
            threshold = self.threshold
        elif self.threshold is not None and np.float32(threshold) != np.float32(self.threshold):
            raise ValueError(
                f"Expected threshold={self.threshold:g} (the one this result was made with) or none, "
                f"but got {threshold!r}: refine again to read the map at another threshold"
            )
        if map_values is None:
            if self.map_values is None:
                raise ValueError("Expected map_values for banded() (this result holds none), but got None")
            map_values = self.map_values
        v = np.asarray(map_values)
        if v.shape != self.occupancy.shape:
            raise ValueError(f"Expected map_values of shape {self.occupancy.shape}, but got {v.shape}")
        if isinstance(band_voxels, bool) or not isinstance(band_voxels, (int, np.integer)) or band_voxels < 0:
            raise ValueError(f"Expected a non-negative integer for 'band_voxels', but got {band_voxels!r}")
        occ = self.occupied()
        if band_voxels > 0:
            occ = ndimage.binary_dilation(
                occ, structure=np.ones((3, 3, 3), bool), iterations=int(band_voxels)
            )
        return occ & (np.nan_to_num(v, nan=-np.inf) >= np.float32(threshold))

    def save(self, path: str | os.PathLike) -> Path:
        """Write the result as a refined map file (.npz), atomically; what ``gpumap refine``
        writes and ``gpumap view`` / ``gpumap export`` / :func:`load_refined` read.

        Members: ``occupancy``, ``confidence``, ``field``, ``reflectivity`` and ``values`` (the
        map's) (nx, ny, nz) float32, NaN unknown; ``carved``, ``raised`` bool; ``min_corner_m``,
        ``voxel_size_m``; ``meta`` (JSON: ``format`` :data:`REFINED_FORMAT`, ``version``, the
        sonar ``spec``, the ``grid``, ``rule``, ``threshold``, ``occupied_level``, ``gain``,
        ``floor``, ``stats``).
        """
        from gpumap.atomic import atomic_write

        if self.spec is None or self.grid is None or self.threshold is None or self.map_values is None:
            raise ValueError("Expected a result with its spec, grid, threshold and map_values to save, "
                             "but some are None (made by hand?)")
        path = Path(path)
        if path.suffix != ".npz":
            path = path.with_name(path.name + ".npz")
        meta = {
            "format": REFINED_FORMAT,
            "version": REFINED_VERSION,
            "spec": self.spec.to_dict(),
            "grid": self.grid.to_dict(),
            "rule": self.rule,
            "threshold": float(self.threshold),
            "occupied_level": OCCUPIED_LEVEL,
            "gain": float(self.gain),
            "floor": float(self.floor),
            "stats": self.stats,
        }
        fld = self.field if self.field is not None else np.full(self.occupancy.shape, np.nan, np.float32)
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_write(path) as f:
            np.savez_compressed(
                f,
                occupancy=self.occupancy.astype(np.float32),
                confidence=self.confidence.astype(np.float32),
                field=np.asarray(fld, np.float32),
                reflectivity=self.reflectivity.astype(np.float32),
                values=np.asarray(self.map_values, np.float32),
                carved=self.carved.astype(bool),
                raised=self.raised.astype(bool),
                min_corner_m=np.asarray(self.grid.min_corner_m, np.float64),
                voxel_size_m=np.float64(self.grid.voxel_size_m),
                meta=np.array(json.dumps(meta, default=float)),
            )
        return path


def _read_meta(path: Path) -> dict | None:
    """The JSON ``meta`` member of an .npz file, or None when it has none or is not an npz."""
    import zipfile

    try:
        with zipfile.ZipFile(path) as zf:
            if "meta.npy" not in zf.namelist():
                return None
            with zf.open("meta.npy") as f:
                m = np.lib.format.read_array(f, allow_pickle=False)
    except (zipfile.BadZipFile, ValueError, OSError):
        return None
    try:
        meta = json.loads(str(m[()]))
    except (TypeError, ValueError):
        return None
    return meta if isinstance(meta, dict) else None


def is_refined_file(path: str | os.PathLike) -> bool:
    """True when ``path`` is a refined map file (:meth:`RefineResult.save`, ``gpumap refine``)."""
    p = Path(path)
    meta = _read_meta(p) if p.is_file() else None
    return meta is not None and meta.get("format") == REFINED_FORMAT


def load_refined(path: str | os.PathLike) -> RefineResult:
    """Read a refined map file written by :meth:`RefineResult.save` (``gpumap refine``'s
    ``refined.npz``). ``history`` is empty (not saved). Raises ``FormatError`` (a ``ValueError``)
    saying what was expected and what came."""
    from gpumap.errors import FormatError

    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"Expected a refined map file at {p}, but nothing is there")
    meta = _read_meta(p)
    if meta is None or meta.get("format") != REFINED_FORMAT:
        got = "no metadata" if meta is None else f"format {meta.get('format')!r}"
        raise FormatError(f"Expected a refined map (format {REFINED_FORMAT!r}, written by gpumap refine) "
                          f"in {p}, but it has {got} (a refined.npz of an older gpumap: refine again)")
    if meta.get("version") != REFINED_VERSION:
        raise FormatError(f"Expected version {REFINED_VERSION} in {p}, but got {meta.get('version')!r}")
    try:
        spec = SonarSpec.from_dict(meta["spec"])
        grid = GridSpec.from_dict(meta["grid"])
        thr = float(meta["threshold"])
    except (KeyError, TypeError, ValueError) as e:
        raise FormatError(f"Expected spec, grid and threshold in the metadata of {p}, but: {e}") from None
    with np.load(p, allow_pickle=False) as z:
        arrays = {}
        for k in ("occupancy", "confidence", "field", "reflectivity", "values", "carved", "raised"):
            if k not in z:
                raise FormatError(f"Expected a member {k!r} in {p}, but it has none")
            a = z[k]
            if a.shape != grid.shape:
                raise FormatError(f"Expected {k!r} of shape {grid.shape} in {p}, but got {a.shape}")
            arrays[k] = a
    return RefineResult(
        arrays["occupancy"].astype(np.float32), arrays["confidence"].astype(np.float32),
        arrays["reflectivity"].astype(np.float32), arrays["carved"].astype(bool),
        arrays["raised"].astype(bool),
        float(meta.get("gain", 1.0)), float(meta.get("floor", 0.0)), [], dict(meta.get("stats") or {}),
        field=arrays["field"].astype(np.float32), threshold=thr, rule=meta.get("rule"),
        map_values=arrays["values"].astype(np.float32), spec=spec, grid=grid,
    )


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
        fb = first_bright_bins(_as_float(img), thr)
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


def carved_voxels(
    rule: str,
    evidence: dict[str, np.ndarray],
    *,
    carve_views: int = 2,
    bright_share: float = 0.5,
    share_z: float = 1.645,
) -> np.ndarray:
    """(nx, ny, nz) bool: the voxels refinement must never occupy (the first hard constraint).

    Parameters
    ----------
    rule : str
        ``"visible"`` or ``"evidence"`` (the rules that keep evidence; others raise).
    evidence : dict
        :meth:`gpumap.MinMaxMapper.evidence` of the map: ``min_all`` float32 (``+inf`` never
        observed), ``count`` uint32 (clear dark views), ``hits`` uint32 (bright views).
    carve_views : int
        Visible rule: the mapper's ``carve_views``.
    bright_share, share_z : float
        Evidence rule: the mapper's settings (:func:`gpumap.reference.evidence_occupied`).

    Returns
    -------
    (nx, ny, nz) bool
        Visible rule: observed and ``count >= carve_views``. Evidence rule: observed, at least one
        clear view (``count + hits > 0``) and not ``evidence_occupied(count, hits, bright_share,
        share_z)``: seen bright yet shown at ``share_z`` to be bright in fewer than
        ``bright_share`` of its views, or never bright with clear dark views. A voxel observed only
        by dark views behind a return (shadow: no clear view) is not carved.
    """
    from gpumap.reference import evidence_occupied

    if rule not in REFINE_RULES:
        raise ValueError(f"Expected a map of rule {' or '.join(map(repr, REFINE_RULES))} (rules that keep "
                         f"evidence), but its rule is {rule!r}")
    observed = np.isfinite(evidence["min_all"])
    dark = np.asarray(evidence["count"])
    if rule == "visible":
        return observed & (dark >= carve_views)
    hits = np.asarray(evidence["hits"])
    clear = (dark.astype(np.uint64) + hits.astype(np.uint64)) > 0
    return observed & clear & ~evidence_occupied(dark, hits, float(bright_share), float(share_z))


def pick_device(device: str = "auto") -> tuple[str, str]:
    """``(device, why)``: the Warp device refinement runs on, and why, logged at INFO.

    ``"auto"`` takes ``cuda:0`` when Warp finds a CUDA device, else the CPU, and says so (on the
    CPU a fine grid takes long: minutes per 100 steps at 3 cm on two cores). A named device
    (``"cpu"``, ``"cuda"``, ``"cuda:N"``) is used or raises
    :class:`~gpumap.errors.BackendUnavailableError` (no CUDA device, or no device N); it never falls
    back. Anything else raises ``ValueError``.
    """
    if not isinstance(device, str) or not (
        device in ("auto", "cpu", "cuda") or (device.startswith("cuda:") and device[5:].isdigit())
    ):
        raise ValueError(f"Expected device 'auto', 'cpu', 'cuda' or 'cuda:N', but got {device!r}")
    from gpumap.backends import _warp

    wp, _ = _warp()
    n_cuda = wp.get_cuda_device_count() if wp.is_cuda_available() else 0
    if device == "auto":
        if n_cuda:
            dev, why = "cuda:0", f"auto: Warp finds {n_cuda} CUDA device(s); took cuda:0"
        else:
            dev, why = "cpu", ("auto: Warp finds no CUDA device, so the CPU (slow on fine grids: "
                               "pass --device cuda on a machine with one)")
    elif device == "cpu":
        dev, why = "cpu", "named"
    else:
        k = 0 if device == "cuda" else int(device[5:])
        if k >= n_cuda:
            raise BackendUnavailableError(
                f"Expected a CUDA device for device={device!r}, but Warp finds "
                + (f"{n_cuda} (cuda:0..cuda:{n_cuda - 1})" if n_cuda else "none")
            )
        dev, why = f"cuda:{k}", "named"
    # auto says what it took at INFO; a named device is what the caller asked for
    log.log(logging.INFO if device == "auto" else logging.DEBUG, "gpumap refine: device %s (%s)", dev, why)
    return dev, why


def _map_of(mapper):
    """A :class:`gpumap.MinMaxMapper` from ``mapper`` (itself, or a map file's path, loaded)."""
    from gpumap.mapper import MinMaxMapper

    if isinstance(mapper, (str, os.PathLike)):
        from gpumap.merge import load_map

        return load_map(mapper, backend="numpy")
    if not isinstance(mapper, MinMaxMapper):
        raise TypeError(f"Expected a gpumap.MinMaxMapper or a map file's path for 'mapper', but got "
                        f"{type(mapper).__name__}")
    return mapper


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
    """Refine the map of ``mapper`` against the pings it was built from.

    Parameters
    ----------
    mapper : gpumap.MinMaxMapper or path-like
        A map of rule ``"evidence"`` (the default) or ``"visible"``, live or a saved map file
        (:meth:`~gpumap.MinMaxMapper.save`; see also :func:`refine_saved`). Its ``values()``,
        ``evidence()``, ``threshold``, ``carve_views``, ``bright_share`` and ``share_z`` are read;
        the mapper is not changed.
    images : (N, n_bins, n_beams) uint8 or float32 in [0, 1]
        The training pings (the ones the map holds).
    poses : (N, 4, 4) float64
        Their ``T_W_S``.
    options : RefineOptions, optional
    model : PingModel, optional
    device : str
        ``"auto"``, ``"cpu"``, ``"cuda"`` or ``"cuda:N"`` (Warp): see :func:`pick_device`; the
        choice and why are logged and kept in ``stats["device"]``, ``stats["device_reason"]``.
    progress : bool
        A tqdm bar over the steps.
    """
    mapper = _map_of(mapper)
    if mapper.rule not in REFINE_RULES:
        raise ValueError(f"Expected a mapper with rule='evidence' or rule='visible' (rules that keep "
                         f"evidence), but its rule is {mapper.rule!r}")
    opts = options or RefineOptions()
    if not isinstance(opts, RefineOptions):
        raise TypeError(f"Expected RefineOptions for 'options', but got {type(opts).__name__}")
    spec, grid = mapper.spec, mapper.grid
    images, P = _check_images_poses(spec, images, poses)
    dev, why = pick_device(device)
    t0 = time.perf_counter()
    values = mapper.values()
    ev = mapper.evidence()
    thr = float(mapper.threshold)
    observed = np.isfinite(values)
    carved = carved_voxels(mapper.rule, ev, carve_views=mapper.carve_views,
                           bright_share=mapper.bright_share, share_z=mapper.share_z)
    movable = observed & ~carved
    occ0 = np.where(movable & (np.nan_to_num(values, nan=-1.0) >= thr), opts.init_occupancy, 0.0).astype(
        np.float32
    )
    upper = movable.astype(np.float32)
    refl0 = np.full(grid.shape, 0.5, np.float32)

    r = PingRenderer(spec, grid, model, device=dev)
    measured = r.coarsen(images)
    log_gain, floor = _calibrate(r, occ0, refl0, measured, P, opts.huber_delta)
    fit = _Fit(r, occ0, upper, refl0, measured, log_gain, floor)
    fit.poses = P

    rng = np.random.default_rng(opts.seed)
    order = np.empty(0, np.int64)
    history = []
    from tqdm import tqdm

    lrs = {"occ": opts.learning_rate, "refl": opts.learning_rate, "glob": 0.02}
    for _ in tqdm(range(opts.iterations), desc=f"refine ({dev})", unit="step", disable=not progress):
        if len(order) < min(opts.pings_per_step, len(P)):
            order = np.concatenate([order, rng.permutation(len(P))])
        idx, order = order[: opts.pings_per_step], order[opts.pings_per_step :]
        history.append(fit.step_loss(np.sort(idx), opts, lrs))
    occ = fit.occ.numpy().astype(np.float32)
    refl = fit.refl.numpy().astype(np.float32)
    log_gain, floor = (float(x) for x in fit.glob.numpy())
    occ[~movable] = 0.0
    # occupancy = the stop probability of a one-voxel layer of the fitted field
    occ = occupancy_from_field(occ, r.model.kappa)
    views, raised, unexplained = _views_and_raise(spec, grid, occ, movable, images, P, thr)
    conf = (np.abs(2.0 * occ - 1.0) * (1.0 - np.exp(-views / 4.0))).astype(np.float32)
    occ_out = np.where(observed, occ, np.nan).astype(np.float32)
    conf = np.where(observed, conf, np.nan).astype(np.float32)
    # the field after the raise: the one whose occupancy is occ_out
    fld = np.where(observed, np.minimum(field_from_occupancy(occ, r.model.kappa), 1.0), np.nan)
    stats = {
        "seconds": time.perf_counter() - t0,
        "device": r.device,
        "device_reason": why,
        "rule": mapper.rule,
        "threshold": thr,
        "frames": len(P),
        "unexplained_cells": unexplained,
        "raised_voxels": int(raised.sum()),
        "carved_voxels": int(carved.sum()),
        "movable_voxels": int(movable.sum()),
        "options": opts.to_dict(),
        "model": r.model.to_dict(),
        "render_cells": list(r.image_shape),
        "elevation_rays": r.n_elevations,
    }
    return RefineResult(occ_out, conf, refl, carved, raised, math.exp(log_gain), floor, history, stats,
                        field=fld.astype(np.float32), threshold=thr, rule=mapper.rule, map_values=values,
                        spec=spec, grid=grid)


def recording_frames(
    path: str | os.PathLike, stride: int = 1, max_frames: int | None = None, progress: bool = False
) -> tuple[SonarSpec, np.ndarray, np.ndarray]:
    """(spec, images (N, n_bins, n_beams), poses (N, 4, 4) float64) of a recording's posed frames
    (every ``stride``-th, at most ``max_frames``; frames of another sonar geometry are skipped).

    The images keep the recording's dtype (uint8 or float32, as the mapper took them, so that
    their fingerprints match a map built from them; float32 if the dtypes are mixed).
    """
    from tqdm import tqdm

    from gpumap.io import open_recording

    rec = open_recording(str(path))
    spec, images, poses = None, [], []
    for i, fr in enumerate(tqdm(rec, desc="read", unit="frame", disable=not progress)):
        if i % stride or fr.T_W_S is None:
            continue
        spec = spec or fr.spec
        if fr.spec != spec:
            continue
        img = np.array(fr.image)  # a copy: a reader may reuse its buffer
        images.append(img if img.dtype == np.uint8 else img.astype(np.float32))
        poses.append(np.asarray(fr.T_W_S, np.float64))
        if max_frames is not None and len(images) >= max_frames:
            break
    if not images:
        raise ValueError(f"Expected a recording with sonar poses (refine needs one per ping), but {path} "
                         "has no posed frames")
    if len({a.dtype for a in images}) > 1:
        images = [a.astype(np.float32) / 255 if a.dtype == np.uint8 else a for a in images]
    return spec, np.stack(images), np.stack(poses)


#: Pings per integrate_batch call in :func:`map_frames` (the progress bar's step; the map is the same).
MAP_CHUNK = 16


def map_frames(mapper, images: np.ndarray, poses: np.ndarray, progress: bool = False) -> None:
    """Integrate ``images`` at ``poses`` into ``mapper``, :data:`MAP_CHUNK` at a time, with a
    progress bar (the same map as one call: every update is a min or a count)."""
    from tqdm import tqdm

    with tqdm(total=len(images), desc="map", unit="ping", disable=not progress) as bar:
        for i in range(0, len(images), MAP_CHUNK):
            mapper.integrate_batch(images[i: i + MAP_CHUNK], poses[i: i + MAP_CHUNK])
            bar.update(len(images[i: i + MAP_CHUNK]))


def refine_saved(
    map_path: str | os.PathLike,
    recording,
    *,
    stride: int = 1,
    max_frames: int | None = None,
    options: RefineOptions | None = None,
    model: PingModel | None = None,
    device: str = "auto",
    progress: bool = False,
) -> RefineResult:
    """Refine a saved map (:meth:`gpumap.MinMaxMapper.save`, ``gpumap replay``'s ``map.npz``)
    against its recording: its grid, rule, threshold and evidence come from the file.

    Parameters
    ----------
    map_path : path-like
        The map file (rule ``"evidence"`` or ``"visible"``).
    recording : path-like or (images, poses)
        A recording with poses (:func:`gpumap.io.open_recording`: read with ``stride`` and
        ``max_frames``), or the pings themselves, ``(N, n_bins, n_beams)`` and ``(N, 4, 4)``.
    stride, max_frames : int
        Which frames of a recording path (as ``gpumap replay`` read them for the map).
    options, model, device, progress
        As :func:`refine`.

    Raises
    ------
    ValueError
        A recording of another sonar geometry than the map's; pings of which none is one the map
        holds (the map keeps a fingerprint of each, :mod:`gpumap.pings`): the wrong recording.
        ``stats["pings_in_map"]`` counts the pings the map holds (None for a map file without
        fingerprints).
    """
    from gpumap.pings import ping_print

    mapper = _map_of(map_path)
    if isinstance(recording, (str, os.PathLike)):
        spec, images, poses = recording_frames(recording, stride, max_frames, progress)
        if spec != mapper.spec:
            raise ValueError(f"Expected a recording of the map's sonar ({mapper.spec.n_bins} bins x "
                             f"{mapper.spec.n_beams} beams, ...), but {recording} is of another geometry")
    else:
        try:
            images, poses = recording
        except (TypeError, ValueError):
            raise TypeError("Expected a recording path or a pair (images, poses) for 'recording', but got "
                            f"{type(recording).__name__}") from None
    images, poses = _check_images_poses(mapper.spec, images, poses)
    known = mapper.pings.array()
    held = None
    if len(known):
        prints = np.array(
            [ping_print(im if im.dtype == np.uint8 else np.ascontiguousarray(im, np.float32), T)
             for im, T in zip(images, poses, strict=True)], np.uint64)
        held = int(np.isin(prints, known).sum())
        if held == 0:
            raise ValueError(f"Expected the pings {map_path} was built from, but none of the {len(images)} "
                             "given is one it holds (another recording, stride or frame range?)")
        if held < len(images):
            log.warning("gpumap refine: %d of the %d pings are not in %s (the map did not see them)",
                        len(images) - held, len(images), map_path)
    res = refine(mapper, images, poses, options=options, model=model, device=device, progress=progress)
    res.stats["pings_in_map"] = held
    res.stats["map_path"] = str(map_path)
    return res


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
    field: np.ndarray | None = None,
    poses: np.ndarray | None = None,
    *,
    reflectivity=None,
    train_images: np.ndarray | None = None,
    train_poses: np.ndarray | None = None,
    gain: float | None = None,
    floor: float | None = None,
    delta: float = 0.1,
    occupancy: np.ndarray | None = None,
) -> tuple[np.ndarray, float, float]:
    """Rendered images of a map at ``poses``: ``(images, gain, floor)``.

    ``field`` (nx, ny, nz) float in [0, 1], NaN unknown (rendered empty): the field ``o`` the
    renderer takes, e.g. :attr:`RefineResult.field`, or a 0/1 map. Not
    :attr:`RefineResult.occupancy` (``1 - exp(-kappa o)``, a probability):
    :func:`field_from_occupancy` converts. ``occupancy=`` is the former name of ``field`` (same
    meaning, deprecated). Without ``gain`` the display gain and floor are fitted on
    ``train_images`` / ``train_poses`` (as :func:`refine` calibrates), so every map is compared at
    its own best scale.
    """
    if occupancy is not None:
        if field is not None:
            raise TypeError("Expected 'field' or its former name 'occupancy', but got both")
        warnings.warn("render_map(occupancy=...) is deprecated: the argument is the field o "
                      "(RefineResult.field), pass it as field=", DeprecationWarning, stacklevel=2)
        field = occupancy
    if field is None or poses is None:
        raise TypeError("Expected 'field' and 'poses' for render_map, but got None")
    occ = np.nan_to_num(np.asarray(field, np.float32), nan=0.0)
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


class _CallableModule(types.ModuleType):
    """``gpumap.refine`` is this module and the function: ``gpumap.refine(mapper, images, poses)``
    calls :func:`refine` whether or not ``gpumap.refine`` (the module) was imported by name."""

    def __call__(self, *args, **kwargs) -> RefineResult:
        return refine(*args, **kwargs)


sys.modules[__name__].__class__ = _CallableModule
