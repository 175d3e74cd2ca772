"""Point measurements found in a polar sonar image: compact bright returns with a covariance.

:class:`PointDetector` finds returns that are bright against their surroundings *and*
compact (a point-like scatterer: a corner, a rod end, a small object), in the image's own
polar frame, and measures each one's range and azimuth below the cell size:

1. **Smoothing** with a ``smooth_cells`` box (speckle is one cell wide; a point's echo spans
   a few cells in range and beam).
2. **Adaptive threshold (CFAR-style)**: the local background mean ``mu`` and spread ``sd`` of
   the smoothed image over a ``background_cells`` window; a cell is a candidate when it is a
   local maximum (non-maximum suppression over ``nms_cells``), ``(s - mu) / sd >= k_sigma``
   and ``s >= min_intensity``.
3. **Compactness**: on an ellipse of ``ring_cells`` semi-axes around the peak, no sample may
   rise above the background by more than ``ring_ratio`` of the peak's own rise. A line or
   an arc (a wall, the floor's leading edge) through the peak crosses that ring twice at
   about the peak's brightness and is refused; a blob larger than the ring is refused too.
4. **Sub-cell position**: a parabola through the peak and its two neighbours, along range
   and along beams (offsets clipped to half a cell); the beam offset is mapped to azimuth
   through the sonar's own bearing table (beams may be unevenly spaced).
5. **Covariance**: independent range and azimuth errors,
   ``sigma = cell * sqrt(base_cells^2 + (1 / snr)^2)`` with ``snr = (s - mu) / sd`` and
   ``cell`` the bin size (range) or the local beam spacing (azimuth). ``base_cells`` (default
   0.5 cell) covers what the image cannot tell: where on a finite scatterer the echo peaks,
   and the parabola's own bias; the ``1/snr`` term widens faint returns. The model is
   checked, not assumed: ``bench/frontend.py`` reports the detections' normalised errors
   against the simulator's true features.

Everything here is NumPy/SciPy on the host; one 398 x 512 ping costs a few milliseconds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from gpumap.errors import check_finite_scalar
from gpumap.spec import SonarSpec

__all__ = ["PointDetector", "PointMeasurements"]


@dataclass(frozen=True)
class PointMeasurements:
    """Point-like returns found in one polar image (rows: measurements, strongest first).

    Attributes
    ----------
    ranges_m : (m,) float64
        Range of each return, metres.
    bearings_rad : (m,) float64
        Azimuth ``atan2(y, x)`` in the sonar frame, radians.
    covs : (m, 2, 2) float64
        Covariance of ``(range m, azimuth rad)``.
    bins, beams : (m,) float64
        Sub-cell image position: fractional row (bin ``i`` spans ``[i, i + 1)``, its centre at
        ``i + 0.5``) and fractional column (beam ``j``'s bearing at ``j``).
    snr : (m,) float64
        ``(s - mu) / sd`` of the smoothed peak against its background.
    intensity : (m,) float64
        Smoothed peak intensity in [0, 1].
    """

    ranges_m: np.ndarray
    bearings_rad: np.ndarray
    covs: np.ndarray
    bins: np.ndarray
    beams: np.ndarray
    snr: np.ndarray
    intensity: np.ndarray

    def __len__(self) -> int:
        return int(self.ranges_m.shape[0])

    def take(self, idx: np.ndarray) -> PointMeasurements:
        """The measurements at ``idx`` (any NumPy index), as a new object."""
        return PointMeasurements(*(np.asarray(getattr(self, f))[idx] for f in _FIELDS))

    @staticmethod
    def empty() -> PointMeasurements:
        z = np.zeros(0)
        return PointMeasurements(z, z, np.zeros((0, 2, 2)), z, z, z, z)

    @staticmethod
    def from_arrays(ranges_m: np.ndarray, bearings_rad: np.ndarray, covs: np.ndarray) -> PointMeasurements:
        """Measurements from another source (e.g. a simulator's features), image fields NaN."""
        r = np.asarray(ranges_m, dtype=np.float64).reshape(-1)
        b = np.asarray(bearings_rad, dtype=np.float64).reshape(-1)
        c = np.asarray(covs, dtype=np.float64)
        if b.shape != r.shape or c.shape != (r.shape[0], 2, 2):
            raise ValueError(f"Expected ranges (m,), bearings (m,) and covs (m, 2, 2) with one m, but got "
                             f"{r.shape}, {b.shape} and {c.shape}")
        nan = np.full(r.shape, np.nan)
        return PointMeasurements(r, b, c, nan, nan, nan, nan)


_FIELDS = ("ranges_m", "bearings_rad", "covs", "bins", "beams", "snr", "intensity")


def _pair(v: object, name: str, lo: float, integer: bool) -> tuple:
    a = np.broadcast_to(np.asarray(v), (2,))
    try:
        out = tuple(int(x) if integer else float(x) for x in a)
    except (TypeError, ValueError):
        raise TypeError(f"Expected a number or a pair of numbers for '{name}', but got {v!r}") from None
    if integer and any(float(x) != int(x) for x in a):
        raise ValueError(f"Expected whole numbers for '{name}', but got {v!r}")
    if not all(math.isfinite(x) and x >= lo for x in out):
        raise ValueError(f"Expected '{name}' >= {lo} (range, beams), but got {v!r}")
    return out


class PointDetector:
    """CFAR-style detector of compact bright returns in polar images of one sonar.

    Parameters
    ----------
    spec : SonarSpec
        The sonar whose images :meth:`detect` reads (``(n_bins, n_beams)``).
    k_sigma : float, default 4.0
        Detection threshold: peak above the local background by this many local spreads.
    min_intensity : float, default 0.15
        Absolute floor on the smoothed peak, in [0, 1].
    smooth_cells : int or (int, int), default 3
        Box smoothing (range bins, beams); odd.
    background_cells : int or (int, int), default 31
        Window of the local background statistics (range bins, beams).
    nms_cells : int or (int, int), default 9
        Non-maximum suppression window (range bins, beams): two returns closer than half of
        it in both directions are reported once.
    ring_cells : float or (float, float), default 5.0
        Semi-axes (bins, beams) of the compactness ring.
    ring_ratio : float, default 0.5
        Most a ring sample may rise above the background, as a fraction of the peak's rise.
    base_cells : float, default 0.5
        Floor of each error standard deviation, in cells (see the module docstring).
    max_points : int, default 32
        At most this many returns per ping, the highest ``snr`` first.
    """

    def __init__(
        self,
        spec: SonarSpec,
        *,
        k_sigma: float = 4.0,
        min_intensity: float = 0.15,
        smooth_cells: int | tuple[int, int] = 3,
        background_cells: int | tuple[int, int] = 31,
        nms_cells: int | tuple[int, int] = 9,
        ring_cells: float | tuple[float, float] = 5.0,
        ring_ratio: float = 0.5,
        base_cells: float = 0.5,
        max_points: int = 32,
    ) -> None:
        if not isinstance(spec, SonarSpec):
            raise TypeError(f"Expected a SonarSpec for 'spec', but got {type(spec).__name__}")
        self.spec = spec
        self.k_sigma = check_finite_scalar(k_sigma, "k_sigma")
        self.min_intensity = check_finite_scalar(min_intensity, "min_intensity")
        self.ring_ratio = check_finite_scalar(ring_ratio, "ring_ratio")
        self.base_cells = check_finite_scalar(base_cells, "base_cells")
        if self.k_sigma <= 0 or not 0 <= self.min_intensity <= 1 or not 0 < self.ring_ratio <= 1 \
                or self.base_cells <= 0:
            raise ValueError(f"Expected k_sigma > 0, 0 <= min_intensity <= 1, 0 < ring_ratio <= 1 and "
                             f"base_cells > 0, but got {self.k_sigma}, {self.min_intensity}, "
                             f"{self.ring_ratio} and {self.base_cells}")
        self.smooth_cells = _pair(smooth_cells, "smooth_cells", 1, True)
        self.background_cells = _pair(background_cells, "background_cells", 3, True)
        self.nms_cells = _pair(nms_cells, "nms_cells", 1, True)
        self.ring_cells = _pair(ring_cells, "ring_cells", 1.0, False)
        if isinstance(max_points, bool) or not isinstance(max_points, (int, np.integer)) or max_points < 1:
            raise ValueError(f"Expected an integer max_points >= 1, but got {max_points!r}")
        self.max_points = int(max_points)
        t = np.linspace(0.0, 2.0 * np.pi, 24, endpoint=False)
        rb, rj = self.ring_cells
        self._ring = np.stack([np.rint(rb * np.cos(t)), np.rint(rj * np.sin(t))], axis=1).astype(np.int64)
        b = spec.bearings_rad
        # local beam spacing at each (fractional) beam, for the azimuth's cell size
        self._beam_step = np.gradient(b) if b.size > 1 else np.array([spec.hfov_rad])

    def _image(self, image: object) -> np.ndarray:
        a = np.asarray(image)
        if a.shape != self.spec.image_shape:
            raise ValueError(f"Expected an image of shape {self.spec.image_shape} (n_bins, n_beams) for "
                             f"'image', but got {a.shape}")
        if a.dtype == np.uint8:
            return a.astype(np.float32) * np.float32(1.0 / 255.0)
        if a.dtype not in (np.float32, np.float64):
            raise TypeError(f"Expected a float32, float64 or uint8 image, but got dtype {a.dtype}")
        a = a.astype(np.float32, copy=False)
        if not np.all(np.isfinite(a)):
            raise ValueError("Expected finite pixels in 'image', but got NaN or inf")
        return a

    def detect(self, image: np.ndarray) -> PointMeasurements:
        """Compact bright returns of one ping.

        Parameters
        ----------
        image : (n_bins, n_beams) float32/float64 in [0, 1], or uint8
            Polar image of ``spec``.

        Returns
        -------
        PointMeasurements
            Strongest (highest ``snr``) first, at most ``max_points``.
        """
        img = self._image(image)
        s = ndimage.uniform_filter(img, size=self.smooth_cells, mode="nearest")
        bg = self.background_cells
        mu = ndimage.uniform_filter(s, size=bg, mode="reflect")
        m2 = ndimage.uniform_filter(s * s, size=bg, mode="reflect")
        sd = np.sqrt(np.maximum(m2 - mu * mu, 1e-12))
        z = (s - mu) / sd
        ii, jj = np.nonzero((z >= self.k_sigma) & (s >= self.min_intensity))
        nb, nbeam = s.shape
        # non-maximum suppression at the candidates only (the same as comparing with a maximum
        # filter over nms_cells with edge replication, at a fraction of its cost)
        hb, hj = self.nms_cells[0] // 2, self.nms_cells[1] // 2
        ob = np.arange(-hb, self.nms_cells[0] - hb)
        oj = np.arange(-hj, self.nms_cells[1] - hj)
        peak = np.ones(ii.size, bool)
        for a in range(0, ii.size, 4096):
            ci, cj = ii[a:a + 4096], jj[a:a + 4096]
            bi = np.clip(ci[:, None, None] + ob[None, :, None], 0, nb - 1)
            bj = np.clip(cj[:, None, None] + oj[None, None, :], 0, nbeam - 1)
            peak[a:a + 4096] = s[bi, bj].reshape(ci.size, -1).max(axis=1) <= s[ci, cj]
        ii, jj = ii[peak], jj[peak]
        # not on the image's edge (the parabola needs both neighbours)
        ok = (ii > 0) & (ii < nb - 1) & (jj > 0) & (jj < nbeam - 1)
        ii, jj = ii[ok], jj[ok]
        if ii.size == 0:
            return PointMeasurements.empty()
        sp, mp = s[ii, jj], mu[ii, jj]
        ri = np.clip(ii[:, None] + self._ring[None, :, 0], 0, nb - 1)
        rj = np.clip(jj[:, None] + self._ring[None, :, 1], 0, nbeam - 1)
        ring_max = s[ri, rj].max(axis=1)
        compact = ring_max - mp <= self.ring_ratio * (sp - mp)
        ii, jj = ii[compact], jj[compact]
        if ii.size == 0:
            return PointMeasurements.empty()
        zz = z[ii, jj]
        order = np.argsort(-zz, kind="stable")[: self.max_points]
        ii, jj, zz = ii[order], jj[order], zz[order]
        c = s[ii, jj].astype(np.float64)
        di = _vertex(s[ii - 1, jj].astype(np.float64), c, s[ii + 1, jj].astype(np.float64))
        dj = _vertex(s[ii, jj - 1].astype(np.float64), c, s[ii, jj + 1].astype(np.float64))
        sp = self.spec
        dr = sp.bin_size_m
        fbin = ii + 0.5 + di
        fbeam = jj + dj
        rng = sp.range_min_m + fbin * dr
        brg = np.interp(fbeam, np.arange(sp.n_beams), sp.bearings_rad)
        step = np.abs(np.interp(fbeam, np.arange(sp.n_beams), self._beam_step))
        f2 = self.base_cells**2 + 1.0 / np.maximum(zz, 1e-6) ** 2
        covs = np.zeros((ii.size, 2, 2))
        covs[:, 0, 0] = dr * dr * f2
        covs[:, 1, 1] = step * step * f2
        return PointMeasurements(rng, brg, covs, fbin, fbeam, zz.astype(np.float64), c)


def _vertex(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Offset of the vertex of the parabola through ``(-1, a), (0, b), (1, c)``, in [-0.5, 0.5]."""
    den = a - 2.0 * b + c
    d = np.where(den < 0, 0.5 * (a - c) / np.where(den < 0, den, -1.0), 0.0)
    return np.clip(d, -0.5, 0.5)
