"""PLY point clouds (written by hand): ASCII or binary, one ``vertex`` element of scalar properties.

:func:`write_ply` writes atomically (a temporary file beside the target, flushed and
fsynced, then renamed over it): an interrupted or failed write leaves the old file, or
none, never a partial one.

:func:`read_ply` checks the whole header before reading data: format ``ascii``,
``binary_little_endian`` or ``binary_big_endian`` 1.0; one ``vertex`` element (other
elements only with count 0) of scalar properties of the PLY types (``char``/``int8`` ..
``double``/``float64``; list properties refused); the vertex count against
``gpumap.limits.MAX_PLY_VERTICES`` and against the bytes the file holds. Binary vertex
data must fill the rest of the file exactly (a file cut on a record boundary, or with
bytes left over, is refused); ASCII data must be exactly ``count`` lines of one number
per property. Anything else is a :class:`~gpumap.errors.FormatError` with its byte offset.
"""

from __future__ import annotations

import os

import numpy as np

from gpumap import limits
from gpumap.atomic import atomic_write
from gpumap.errors import FormatError
from gpumap.limits import check_size

__all__ = ["read_ply", "write_ply"]

_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
_FORMATS = {"ascii": None, "binary_little_endian": "<", "binary_big_endian": ">"}


def write_ply(
    path: str | os.PathLike,
    points: np.ndarray,
    intensity: np.ndarray | None = None,
    *,
    binary: bool = True,
) -> None:
    """Write points (and an optional per-point intensity) as a PLY file, atomically.

    Parameters
    ----------
    path : path-like
        Output file (replaced in one step; its directory must exist).
    points : (n, 3) float
        Positions, metres; stored as float32 ``x y z``.
    intensity : (n,) float, optional
        Stored as a float32 ``intensity`` property.
    binary : bool
        ``binary_little_endian 1.0`` (default) or ``ascii 1.0``.
    """
    for name, a in (("points", points), ("intensity", intensity)):
        if a is not None and np.iscomplexobj(a):
            raise TypeError(f"Expected real values for '{name}', but got complex dtype {np.asarray(a).dtype}")
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
    with atomic_write(path) as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        if binary:
            f.write(rec.tobytes())
        else:
            flat = np.stack([rec[name] for name, _ in cols], axis=1)
            np.savetxt(f, flat, fmt="%.9g")


def _read_header(f, path: str, size: int) -> tuple[str, int, list[tuple[str, str]], int]:
    """-> (format, vertex count, [(name, dtype code)], byte offset of the data)."""
    head = f.read(min(size, limits.MAX_PLY_HEADER_BYTES))
    first = head.split(b"\n", 1)[0].rstrip(b"\r")
    if first != b"ply":
        raise FormatError(f"expected a PLY file starting 'ply', but it starts {head[:8]!r}", 0, path)
    fmt = None
    elements: list[list] = []  # [name, count, [(prop name, dtype)], offset]
    pos = 0
    while True:
        nl = head.find(b"\n", pos)
        if nl < 0:
            if len(head) >= limits.MAX_PLY_HEADER_BYTES:
                raise FormatError(f"expected 'end_header' within {limits.MAX_PLY_HEADER_BYTES} bytes "
                                  "(gpumap.limits.MAX_PLY_HEADER_BYTES), but found none", pos, path)
            raise FormatError("expected 'end_header', but the file ends inside the header", len(head),
                              path)
        raw = head[pos:nl].rstrip(b"\r")
        at, pos = pos, nl + 1
        try:
            line = raw.decode("ascii")
        except UnicodeDecodeError:
            raise FormatError(f"expected an ASCII header line, but got {raw[:40]!r}", at, path) from None
        w = line.split()
        if not w or w[0] in ("ply", "comment", "obj_info"):
            if w[:1] == ["ply"] and at != 0:
                raise FormatError("expected 'ply' only on the first line", at, path)
            continue
        key = w[0]
        if key == "end_header":
            break
        if key == "format":
            if fmt is not None or len(w) != 3 or w[1] not in _FORMATS or w[2] != "1.0":
                raise FormatError(f"expected one 'format ascii|binary_little_endian|binary_big_endian "
                                  f"1.0' line, but got {line!r}", at, path)
            fmt = w[1]
        elif key == "element":
            if len(w) != 3:
                raise FormatError(f"expected 'element <name> <count>', but got {line!r}", at, path)
            try:
                count = int(w[2])
            except ValueError:
                raise FormatError(f"expected an integer element count, but got {w[2]!r}", at,
                                  path) from None
            if count < 0:
                raise FormatError(f"expected an element count >= 0, but got {count}", at, path)
            if any(e[0] == w[1] for e in elements):
                raise FormatError(f"expected one element {w[1]!r}, but it is declared twice", at, path)
            elements.append([w[1], count, [], at])
        elif key == "property":
            if not elements:
                raise FormatError(f"expected 'element' before {line!r}", at, path)
            el = elements[-1]
            if len(w) >= 2 and w[1] == "list":
                if el[0] == "vertex" or el[1] > 0:
                    raise FormatError(f"expected scalar properties, but got a list property {line!r} "
                                      f"in element {el[0]!r} with {el[1]} entries", at, path)
                continue
            if len(w) != 3 or w[1] not in _TYPES:
                raise FormatError(f"expected 'property <type> <name>' with a PLY type "
                                  f"({', '.join(sorted(_TYPES))}), but got {line!r}", at, path)
            if any(n == w[2] for n, _ in el[2]):
                raise FormatError(f"expected distinct property names, but {w[2]!r} repeats", at, path)
            el[2].append((w[2], _TYPES[w[1]]))
        else:
            raise FormatError(f"expected a PLY header keyword (format, element, property, comment, "
                              f"end_header), but got {line!r}", at, path)
    if fmt is None:
        raise FormatError("expected a 'format' line in the header, but found none", pos, path)
    vertex = None
    for name, count, props, at in elements:
        if name == "vertex":
            vertex = (count, props, at)
        elif count:
            raise FormatError(f"expected only a vertex element (others with count 0), but element "
                              f"{name!r} has {count}", at, path)
    if vertex is None:
        raise FormatError("expected an 'element vertex' line, but found none", pos, path)
    count, props, at = vertex
    if not props and count:
        raise FormatError("expected vertex properties, but the vertex element has none", at, path)
    if len(props) > limits.MAX_PLY_PROPERTIES:
        raise FormatError(f"expected at most {limits.MAX_PLY_PROPERTIES} vertex properties "
                          f"(gpumap.limits), but got {len(props)}", at, path)
    check_size(count, limits.MAX_PLY_VERTICES, "element vertex", unit="vertices", offset=at, path=path)
    return fmt, count, props, pos


def read_ply(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Read a PLY point cloud (as :func:`write_ply` writes; layout checks in the module notes).

    Returns
    -------
    dict of str to (n,) ndarray
        One array per vertex property, in its declared type (``float`` -> float32).

    Raises
    ------
    FormatError
        If the header is malformed or unsupported, the vertex count is beyond
        ``gpumap.limits.MAX_PLY_VERTICES``, or the data is short, long or unreadable.
    """
    ps = os.fspath(path)
    with open(ps, "rb") as f:
        size = os.fstat(f.fileno()).st_size
        fmt, n, props, start = _read_header(f, ps, size)
        f.seek(start)
        left = size - start
        order = _FORMATS[fmt]
        if order is not None:
            dt = np.dtype([(k, order + c) for k, c in props])
            need = n * dt.itemsize
            if left != need:
                raise FormatError(
                    f"expected {n} vertices x {dt.itemsize} bytes = {need} bytes of vertex data after "
                    f"the header, but the file has {left}"
                    + (" (cut short)" if left < need else " (bytes left over)"),
                    start + min(left, need), ps)
            rec = np.frombuffer(f.read(need), dtype=dt, count=n)
            return {k: rec[k].astype(np.dtype(c), copy=True) for k, c in props}
        # ASCII: each value needs a character and a separator
        n_props = len(props)
        if n and 2 * n * n_props > left + 1:
            raise FormatError(f"expected {n} lines of {n_props} numbers after the header, but only "
                              f"{left} bytes follow", size, ps)
        text = f.read(left)
    try:
        # lines end at "\n" only (str.splitlines would also split at form feeds and the like)
        lines = [ln.rstrip("\r") for ln in text.decode("ascii").split("\n")]
    except UnicodeDecodeError as e:
        raise FormatError(f"expected ASCII vertex data, but byte {start + e.start} is not",
                          start + e.start, ps) from None
    while lines and not lines[-1].strip():
        lines.pop()
    if len(lines) != n:
        raise FormatError(f"expected {n} vertex lines after the header (element vertex), but got "
                          f"{len(lines)}", size, ps)
    if n == 0:
        return {k: np.empty(0, dtype=np.dtype(c)) for k, c in props}
    try:
        a = np.loadtxt(lines, dtype=np.float64, ndmin=2, comments=None)
    except ValueError as e:
        raise FormatError(f"expected {n} lines of {n_props} numbers after the header, but {e}", None,
                          ps) from None
    if a.shape != (n, n_props):
        raise FormatError(f"expected {n} lines of {n_props} numbers after the header, but got "
                          f"{a.shape[0]} lines of {a.shape[1]}", None, ps)
    out = {}
    for j, (k, c) in enumerate(props):
        col = a[:, j]
        dt = np.dtype(c)
        if dt.kind in "iu":
            info = np.iinfo(dt)
            bad = ~((col == np.round(col)) & (col >= info.min) & (col <= info.max))
            if bad.any():
                i = int(np.argmax(bad))
                raise FormatError(f"vertex {i}: expected an integer in {info.min}..{info.max} for "
                                  f"{k!r} ({c}), but got {col[i]}", None, ps)
        out[k] = col.astype(dt)
    return out
