"""The refined map: what :func:`gpumap.layers.refine.refine` returns (:class:`RefineResult`), its file,
and the two quantities it keeps apart.

- the **field** ``o`` in [0, 1] (:attr:`RefineResult.field`): what the renderer takes;
- the **occupancy** ``1 - exp(-kappa o)`` (:attr:`RefineResult.occupancy`): a probability,
  occupied from :data:`OCCUPIED_LEVEL` on; :func:`field_from_occupancy` and
  :func:`occupancy_from_field` convert.

A refined map file (:meth:`RefineResult.save`, ``gpumap refine``'s ``refined.npz``) is read back
by :func:`load_refined` and recognised by :func:`is_refined_file` (``gpumap view``,
``gpumap export``). The method itself is described in :mod:`gpumap.layers.refine`.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from dataclasses import field as _dc_field
from pathlib import Path

import numpy as np

from gpumap.spec import GridSpec, SonarSpec

__all__ = [
    "RefineResult",
    "load_refined",
    "is_refined_file",
    "layers_file",
    "SURFACE_FILE",
    "field_from_occupancy",
    "occupancy_from_field",
    "OCCUPIED_LEVEL",
    "REFINED_FORMAT",
    "REFINED_VERSION",
]

#: Refined occupancy from which a voxel is called occupied.
OCCUPIED_LEVEL = 0.5
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


@dataclass
class RefineResult:
    """What :func:`~gpumap.layers.refine.refine` returns (and :func:`load_refined` reads back).

    Attributes
    ----------
    occupancy : (nx, ny, nz) float32
        Refined occupancy ``1 - exp(-kappa o)`` in [0, 1): the share of the sound a one-voxel
        layer of the fitted field stops (a probability, not the field: see :attr:`field`); NaN
        where no ping observed the voxel; occupied from :data:`OCCUPIED_LEVEL` on.
    confidence : (nx, ny, nz) float32
        In [0, 1], NaN unobserved (see :mod:`gpumap.layers.refine`).
    reflectivity : (nx, ny, nz) float32
        The fitted reflectivity (meaningful where the occupancy is high).
    carved, raised : (nx, ny, nz) bool
        Voxels held free by the first hard constraint (:func:`~gpumap.layers.refine.carved_voxels`); voxels
        raised by
        the second.
    gain, floor : float
        The fitted display gain and noise floor.
    history : list of float
        Loss per step (data + smoothness, per ping).
    stats : dict
        ``seconds``, ``device`` and ``device_reason`` (:func:`~gpumap.layers.refine.pick_device`),
        ``unexplained_cells``, ``raised_voxels``, ``carved_voxels``, ``movable_voxels``, the
        options and model.
    field : (nx, ny, nz) float32 or None
        The field ``o`` in [0, 1] that the renderer takes (:func:`~gpumap.layers.refine.render_map`), NaN
        unobserved;
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


#: The two-layer file ``gpumap demo`` and ``gpumap replay`` write beside ``map.npz``
#: (:mod:`gpumap.layers.surface`: the surface layer and the evidence map, as a refined map file).
SURFACE_FILE = "surface.npz"


def layers_file(path: str | os.PathLike) -> Path | None:
    """The file holding the two layers of the map at ``path``: ``path`` itself when it is a refined
    map file, else the :data:`SURFACE_FILE` beside it when that is one, else None."""
    p = Path(path)
    if is_refined_file(p):
        return p
    side = p.with_name(SURFACE_FILE)
    return side if side != p and is_refined_file(side) else None


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

