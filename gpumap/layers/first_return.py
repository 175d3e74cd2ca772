"""A geometric judge of a map against pings it did not see: measured first returns, no intensity model.

For each beam of a held-out ping, the sonar measures its *first return*: the nearest range bin
whose intensity reaches the threshold. The map predicts one too: the nearest occupied voxel
in that beam's fan (a voxel is in the fan of every beam that its own width, half an edge on
either side of its centre, spans in azimuth, within the range window and the vertical
aperture: neighbouring voxels tile a fan, and no voxel counts in beams it does not reach). Per
beam with a measured return:

- **hit**: the map's nearest occupied voxel centre lies within ``tol_voxels`` voxels of the
  measured range;
- **phantom in front**: it lies nearer than that (the map claims an obstacle where the sonar
  sees clear water);
- **missing**: it lies farther, or the fan holds no occupied voxel (the map lost the surface, or
  never observed it: unknown voxels count as missing, so leaving a region unknown never looks
  better).

Beams without a measured return are counted apart (``empty_beams``; ``empty_phantom``: of them,
those whose fan holds an occupied voxel). Nothing here reads the map's intensities, so a map
fitted through a ping model gains nothing from it.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from gpumap.spec import GridSpec, SonarSpec

__all__ = ["FirstReturnScore", "first_bright_bins", "first_return_score", "map_first_returns",
           "measured_first_returns"]


@dataclass(frozen=True)
class FirstReturnScore:
    """Counts of beams, over every judged ping (module docstring)."""

    beams: int  # beams with a measured return
    hits: int
    phantom_front: int
    missing: int
    empty_beams: int  # beams without a measured return
    empty_phantom: int  # ... whose fan holds an occupied voxel

    @property
    def agreement(self) -> float:
        """Share of beams with a return whose map range agrees (hits / beams)."""
        return self.hits / self.beams if self.beams else float("nan")

    @property
    def phantom_rate(self) -> float:
        """Share of beams with a return that the map blocks in front of it."""
        return self.phantom_front / self.beams if self.beams else float("nan")

    @property
    def missing_rate(self) -> float:
        return self.missing / self.beams if self.beams else float("nan")

    def __add__(self, other: FirstReturnScore) -> FirstReturnScore:
        return FirstReturnScore(*(a + b for a, b in zip(self.as_tuple(), other.as_tuple(), strict=True)))

    def as_tuple(self) -> tuple[int, ...]:
        return (self.beams, self.hits, self.phantom_front, self.missing, self.empty_beams, self.empty_phantom)

    def to_dict(self) -> dict:
        return {"beams": self.beams, "hits": self.hits, "phantom_front": self.phantom_front,
                "missing": self.missing, "empty_beams": self.empty_beams, "empty_phantom": self.empty_phantom,
                "agreement": self.agreement, "phantom_rate": self.phantom_rate,
                "missing_rate": self.missing_rate}


def first_bright_bins(image: np.ndarray, threshold: float) -> np.ndarray:
    """(n_beams,) int: the nearest bin of each beam whose intensity is ``>= threshold`` (compared
    in float32, as the kernels do), -1 where the beam has none. ``image``: (n_bins, n_beams)."""
    b = np.asarray(image) >= np.float32(threshold)
    return np.where(b.any(axis=0), np.argmax(b, axis=0), -1)


def measured_first_returns(image: np.ndarray, spec: SonarSpec, threshold: float) -> np.ndarray:
    """(n_beams,) float64: range of each beam's first bin ``>= threshold`` (bin centre, metres);
    ``inf`` where the beam has none. ``image`` is (n_bins, n_beams) in [0, 1]."""
    img = np.asarray(image)
    if img.shape != spec.image_shape:
        raise ValueError(f"Expected an image of shape {spec.image_shape}, but got {img.shape}")
    first = first_bright_bins(img, threshold)
    dr = (spec.range_max_m - spec.range_min_m) / spec.n_bins
    return np.where(first >= 0, spec.range_min_m + (first + 0.5) * dr, np.inf)


def map_first_returns(centres_W: np.ndarray, T_W_S: np.ndarray, spec: SonarSpec, voxel_size_m: float
                      ) -> np.ndarray:
    """(n_beams,) float64: range of the nearest of ``centres_W`` ((m, 3) occupied voxel centres,
    world frame, metres) in each beam's fan at pose ``T_W_S``; ``inf`` where none lies there."""
    T = np.asarray(T_W_S, np.float64)
    p = (np.asarray(centres_W, np.float64) - T[:3, 3]) @ T[:3, :3]  # sonar frame
    out = np.full(spec.n_beams, np.inf)
    if not len(p):
        return out
    rho = 0.5 * voxel_size_m
    h = np.hypot(p[:, 0], p[:, 1])
    r = np.sqrt(h * h + p[:, 2] ** 2)
    # the voxel, half an edge around its centre, meets the field of view: range window, vertical
    # aperture, fan
    elev = np.arctan2(np.abs(p[:, 2]), h)
    d_el = np.arcsin(np.clip(rho / np.maximum(r, 1e-9), 0.0, 1.0))
    az = np.arctan2(p[:, 1], p[:, 0])
    d_az = np.arcsin(np.clip(rho / np.maximum(h, 1e-9), 0.0, 1.0))
    edges = np.asarray(spec.beam_edges_rad, np.float64)
    ok = (p[:, 0] > 0) & (r >= spec.range_min_m) & (r < spec.range_max_m) & (
        elev - d_el <= 0.5 * spec.vfov_rad) & (az + d_az >= edges[0]) & (az - d_az <= edges[-1])
    if not ok.any():
        return out
    r, az, d_az = r[ok], az[ok], d_az[ok]
    j0 = np.clip(np.searchsorted(edges, az - d_az, side="right") - 1, 0, spec.n_beams - 1)
    j1 = np.clip(np.searchsorted(edges, az + d_az, side="right") - 1, 0, spec.n_beams - 1)
    order = np.argsort(-r)  # nearest last: a plain fancy-index write keeps the last one
    r, j0, j1 = r[order], j0[order], j1[order]
    span = j1 - j0
    for d in range(int(span.max()) + 1):
        m = span >= d
        np.minimum.at(out, j0[m] + d, r[m])
    return out


def first_return_score(values: np.ndarray, grid: GridSpec, threshold: float,
                       frames: Iterable[tuple[np.ndarray, np.ndarray]], spec: SonarSpec,
                       tol_voxels: float = 2.0) -> FirstReturnScore:
    """Judge a map (``values`` (nx, ny, nz) over ``grid``, occupied where ``>= threshold``;
    ``+inf``/NaN unknown) against ``frames``: (image (n_bins, n_beams) in [0, 1], ``T_W_S``
    (4, 4)) pairs the map did not integrate. See the module docstring."""
    v = np.asarray(values)
    if v.shape != tuple(grid.shape):
        raise ValueError(f"Expected values of the grid's shape {tuple(grid.shape)}, but got {v.shape}")
    occ = np.isfinite(v) & (v >= threshold)
    idx = np.argwhere(occ)
    centres = np.asarray(grid.min_corner_m) + (idx + 0.5) * grid.voxel_size_m
    tol = tol_voxels * grid.voxel_size_m
    total = FirstReturnScore(0, 0, 0, 0, 0, 0)
    for image, T in frames:
        meas = measured_first_returns(image, spec, threshold)
        pred = map_first_returns(centres, T, spec, grid.voxel_size_m)
        has = np.isfinite(meas)
        d = pred[has] - meas[has]
        hit = np.abs(d) <= tol
        front = d < -tol
        total = total + FirstReturnScore(
            int(has.sum()), int(hit.sum()), int(front.sum()), int((~hit & ~front).sum()),
            int((~has).sum()), int(np.isfinite(pred[~has]).sum()))
    return total
