"""Cartesian fan images (a folder of PNGs + a poses CSV, e.g. OASIS tank) <-> polar images.

The fan convention is a parameter (:class:`FanGeometry`). For the OASIS tank data (the
default) the sensor apex is at the bottom centre of a 398 x 722 PNG, pixel = 2.0 / 398 m,
row ``apex_row - i`` holds forward distance ``x = i * pixel`` and column ``j`` holds
lateral ``y = (j - apex_col) * pixel``; ``theta = atan2(y, x)`` in the sonar frame.
``flip_lr`` mirrors the columns (``y -> -y``) and ``flip_ud`` mirrors the rows of the PNG
before that mapping; both exist to test the convention, not because the data needs them.

Conversion back to polar invents nothing: polar cell ``(i, j)`` is the bilinear sample
of the fan at the cell centre ``(r_i, theta_j)`` (``r_i`` the bin centre, ``theta_j`` the
beam's bearing). Samples whose 2x2 neighbourhood leaves the picture use the nearest
edge pixel within half a pixel and 0 beyond. Because the fan was itself rendered from a
polar image, the round trip ``polar -> fan -> polar`` is exact up to the two
interpolations; :func:`polar_to_fan` is provided to measure that (see the tests).
"""

from __future__ import annotations

import csv
import os
import re
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gpumap.io.frame import FormatError, Recording, SonarFrame
from gpumap.spec import SonarSpec

__all__ = ["FanGeometry", "fan_to_polar", "open_fan_folder", "polar_to_fan", "read_poses_csv"]


@dataclass(frozen=True)
class FanGeometry:
    """Where the sonar frame lies in a Cartesian fan picture.

    Parameters
    ----------
    n_rows, n_cols : int
        Picture size, pixels.
    pixel_m : float
        Edge of a (square) pixel, metres.
    apex_row, apex_col : float
        Pixel coordinates of the sensor (row/column index; pixel centres at integers).
    flip_lr : bool
        Column ``j`` holds ``y = -(j - apex_col) * pixel`` instead of ``+``.
    flip_ud : bool
        Mirror the picture's rows before applying the convention.
    """

    n_rows: int = 398
    n_cols: int = 722
    pixel_m: float = 2.0 / 398
    apex_row: float = 397.0
    apex_col: float = 361.0
    flip_lr: bool = False
    flip_ud: bool = False

    def pixel_of(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Sonar-frame (x forward, y left) metres -> fractional (row, col) in the *stored* picture."""
        row = self.apex_row - np.asarray(x) / self.pixel_m
        col = self.apex_col + (-1.0 if self.flip_lr else 1.0) * np.asarray(y) / self.pixel_m
        if self.flip_ud:
            row = (self.n_rows - 1) - row
        return row, col


OASIS_SPEC = SonarSpec.uniform(hfov_deg=130.0, vfov_deg=20.0, n_beams=512, n_bins=398,
                               range_min_m=0.1, range_max_m=2.0)
"""The OASIS tank sonar (Oculus M3000d at 1.2 MHz) as its dataset config describes it."""


class _Bilinear:
    """Bilinear sampling of an ``(h, w)`` picture at fixed fractional ``(row, col)``, precomputed."""

    def __init__(self, shape: tuple[int, int], row: np.ndarray, col: np.ndarray) -> None:
        h, w = shape
        self.shape = (h, w)
        self.inside = (row >= -0.5) & (row <= h - 0.5) & (col >= -0.5) & (col <= w - 0.5)
        r = np.clip(row, 0.0, h - 1.0)
        c = np.clip(col, 0.0, w - 1.0)
        r0 = np.minimum(np.floor(r).astype(np.int64), h - 2)
        c0 = np.minimum(np.floor(c).astype(np.int64), w - 2)
        self.i00 = r0 * w + c0
        self.fr = (r - r0).astype(np.float32)
        self.fc = (c - c0).astype(np.float32)
        self.w = w

    def __call__(self, img: np.ndarray) -> np.ndarray:
        f = np.ascontiguousarray(img, dtype=np.float32).reshape(-1)
        i, w, fr, fc = self.i00, self.w, self.fr, self.fc
        a = f[i] * (1 - fc) + f[i + 1] * fc
        b = f[i + w] * (1 - fc) + f[i + w + 1] * fc
        out = a * (1 - fr) + b * fr
        return np.where(self.inside, out, np.float32(0.0)).astype(np.float32)


def _bilinear(img: np.ndarray, row: np.ndarray, col: np.ndarray) -> np.ndarray:
    return _Bilinear(img.shape, row, col)(img)


def _fan_sampler(spec: SonarSpec, geom: FanGeometry) -> _Bilinear:
    r = spec.bin_centers_m[:, None]
    th = spec.bearings_rad[None, :]
    row, col = geom.pixel_of(r * np.cos(th), r * np.sin(th))
    return _Bilinear((geom.n_rows, geom.n_cols), row, col)


def fan_to_polar(fan: np.ndarray, spec: SonarSpec, geom: FanGeometry) -> np.ndarray:
    """Sample a Cartesian fan at every polar cell centre.

    Parameters
    ----------
    fan : (n_rows, n_cols) float32
        Fan picture in ``[0, 1]``, stored orientation.
    spec : SonarSpec
        Target polar geometry.
    geom : FanGeometry
        The picture's convention.

    Returns
    -------
    (n_bins, n_beams) float32
        Bilinear samples at ``(bin centre, beam bearing)``.
    """
    f = np.asarray(fan, dtype=np.float32)
    if f.shape != (geom.n_rows, geom.n_cols):
        raise ValueError(f"Expected a fan of shape {(geom.n_rows, geom.n_cols)}, but got {f.shape}")
    return _fan_sampler(spec, geom)(f)


def polar_to_fan(polar: np.ndarray, spec: SonarSpec, geom: FanGeometry) -> np.ndarray:
    """Render a polar image as a Cartesian fan (bilinear in range and bearing; 0 outside).

    Parameters
    ----------
    polar : (n_bins, n_beams) float32
    spec : SonarSpec
    geom : FanGeometry

    Returns
    -------
    (n_rows, n_cols) float32
    """
    p = np.asarray(polar, dtype=np.float32)
    rows, cols = np.meshgrid(np.arange(geom.n_rows, dtype=np.float64),
                             np.arange(geom.n_cols, dtype=np.float64), indexing="ij")
    if geom.flip_ud:
        rows = (geom.n_rows - 1) - rows
    x = (geom.apex_row - rows) * geom.pixel_m
    y = (-1.0 if geom.flip_lr else 1.0) * (cols - geom.apex_col) * geom.pixel_m
    r = np.hypot(x, y)
    th = np.arctan2(y, x)
    fi = (r - spec.range_min_m) / spec.bin_size_m - 0.5
    b = spec.bearings_rad
    fj = np.interp(th, b, np.arange(b.size, dtype=np.float64))
    ok = ((r >= spec.range_min_m) & (r < spec.range_max_m) & (th >= spec.beam_edges_rad[0])
          & (th <= spec.beam_edges_rad[-1]))
    out = _bilinear(p, fi, fj)
    return np.where(ok, out, np.float32(0.0)).astype(np.float32)


def read_poses_csv(path: str | os.PathLike) -> dict[int, np.ndarray]:
    """``frame, T_W_S_00 .. T_W_S_33`` (row-major) -> {frame: (4, 4) float64}."""
    out: dict[int, np.ndarray] = {}
    p = str(path)
    with open(p, newline="") as f:
        rd = csv.reader(f)
        header = next(rd, None)
        if header is None or len(header) != 17 or header[0].strip() != "frame":
            raise FormatError(f"expected a header 'frame' + 16 matrix entries, but got {header}",
                              path=p)
        for line_no, row in enumerate(rd, start=2):
            if not row:
                continue
            if len(row) != 17:
                raise FormatError(f"line {line_no}: expected 17 fields, but got {len(row)}", path=p)
            try:
                k = int(row[0])
                T = np.array([float(v) for v in row[1:]], dtype=np.float64).reshape(4, 4)
            except ValueError as e:
                raise FormatError(f"line {line_no}: expected numbers, but {e}", path=p) from None
            if not np.all(np.isfinite(T)):
                raise FormatError(f"line {line_no}: expected finite pose entries", path=p)
            out[k] = T
    return out


_NUM = re.compile(r"(\d+)")


def open_fan_folder(
    folder: str | os.PathLike,
    *,
    spec: SonarSpec = OASIS_SPEC,
    geom: FanGeometry | None = None,
    poses: str | os.PathLike | None = None,
    image_dir: str = "sonar",
    stride: int = 1,
) -> Recording:
    """Open a folder of Cartesian fan PNGs with a poses CSV (OASIS tank layout by default).

    Parameters
    ----------
    folder : path-like
        Holds ``image_dir/`` (``*.png``, frame number in the name) and ``sonar_poses.csv``.
    spec : SonarSpec
        Polar geometry to sample (default: the OASIS M3000d config, 398 bins x 512 beams).
    geom : FanGeometry, optional
        The pictures' convention (default: OASIS, as documented).
    poses : path-like, optional
        Poses CSV (default ``folder/sonar_poses.csv``; frames without a pose get ``None``).
    stride : int
        Use every ``stride``-th picture.

    Notes
    -----
    Pictures are read lazily, one per frame; RGB pictures are averaged to grey; uint8 is
    scaled by 1/255 (16-bit by 1/65535).
    """
    from PIL import Image  # lazy: only this reader needs Pillow

    root = Path(folder)
    geom = geom or FanGeometry()
    img_dir = root / image_dir if (root / image_dir).is_dir() else root
    files = []
    for f in img_dir.iterdir():
        if f.suffix.lower() == ".png":
            m = _NUM.findall(f.stem)
            if m:
                files.append((int(m[-1]), f))
    if not files:
        raise FormatError(f"expected PNG fan pictures in {img_dir}, but found none", path=str(root))
    files.sort()
    files = files[:: max(1, int(stride))]
    pose_path = Path(poses) if poses is not None else root / "sonar_poses.csv"
    T = read_poses_csv(pose_path) if pose_path.is_file() else {}
    has_poses = bool(T) and all(k in T for k, _ in files)
    sampler = _fan_sampler(spec, geom)

    def frames() -> Iterator[SonarFrame]:
        for k, f in files:
            with Image.open(f) as im:
                a = np.asarray(im)
            if a.ndim == 3:
                a = a[..., :3].astype(np.float32).mean(axis=-1)
                scale = 255.0
            else:
                scale = 65535.0 if a.dtype == np.uint16 else 255.0
            fan = a.astype(np.float32) / np.float32(scale)
            if fan.shape != (geom.n_rows, geom.n_cols):
                raise FormatError(f"expected a {geom.n_rows} x {geom.n_cols} picture, but got "
                                  f"{fan.shape}", path=str(f))
            img = sampler(fan)
            yield SonarFrame(image=img, spec=spec, timestamp_s=None, T_W_S=T.get(k),
                             meta={"format": "fan", "frame": k, "file": str(f)})

    return Recording(str(root), "fan-folder", frames, has_poses=has_poses,
                     count=lambda: len(files), poses=lambda: [T.get(k) for k, _ in files])


