"""PLY point cloud export (written by hand: ASCII or binary little-endian)."""

from __future__ import annotations

import os

import numpy as np

__all__ = ["read_ply", "write_ply"]


def write_ply(
    path: str | os.PathLike,
    points: np.ndarray,
    intensity: np.ndarray | None = None,
    *,
    binary: bool = True,
) -> None:
    """Write points (and an optional per-point intensity) as a PLY file.

    Parameters
    ----------
    path : path-like
        Output file.
    points : (n, 3) float
        Positions, metres; stored as float32 ``x y z``.
    intensity : (n,) float, optional
        Stored as a float32 ``intensity`` property.
    binary : bool
        ``binary_little_endian 1.0`` (default) or ``ascii 1.0``.
    """
    p = np.asarray(points, dtype=np.float32)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"Expected (n, 3) points, but got shape {p.shape}")
    cols = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if intensity is not None:
        v = np.asarray(intensity, dtype=np.float32).reshape(-1)
        if v.shape[0] != p.shape[0]:
            raise ValueError(f"Expected {p.shape[0]} intensities, but got {v.shape[0]}")
        cols.append(("intensity", "<f4"))
    rec = np.empty(p.shape[0], dtype=cols)
    rec["x"], rec["y"], rec["z"] = p[:, 0], p[:, 1], p[:, 2]
    if intensity is not None:
        rec["intensity"] = v
    header = ["ply", f"format {'binary_little_endian' if binary else 'ascii'} 1.0",
              "comment gpumap occupied voxel centres", f"element vertex {p.shape[0]}"]
    header += [f"property float {name}" for name, _ in cols]
    header.append("end_header")
    with open(path, "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        if binary:
            f.write(rec.tobytes())
        else:
            flat = np.stack([rec[name] for name, _ in cols], axis=1)
            np.savetxt(f, flat, fmt="%.9g")


def read_ply(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Read back a PLY written by :func:`write_ply` (float vertex properties only)."""
    with open(path, "rb") as f:
        if f.readline().strip() != b"ply":
            raise ValueError(f"Expected a PLY file, but {path} does not start with 'ply'")
        fmt, n, names = None, 0, []
        while True:
            line = f.readline()
            if not line:
                raise ValueError(f"Expected 'end_header' in {path}, but the file ended")
            w = line.split()
            if w[:1] == [b"format"]:
                fmt = w[1].decode()
            elif w[:2] == [b"element", b"vertex"]:
                n = int(w[2])
            elif w[:1] == [b"property"]:
                if w[1] != b"float":
                    raise ValueError(f"Expected float properties, but got {line!r}")
                names.append(w[2].decode())
            elif w[:1] == [b"end_header"]:
                break
        if fmt == "binary_little_endian":
            rec = np.frombuffer(f.read(4 * len(names) * n), dtype=[(k, "<f4") for k in names])
            return {k: rec[k].copy() for k in names}
        if fmt == "ascii":
            a = np.loadtxt(f, dtype=np.float32, ndmin=2).reshape(n, len(names))
            return {k: a[:, i] for i, k in enumerate(names)}
        raise ValueError(f"Expected an ascii or binary_little_endian PLY, but got {fmt}")
