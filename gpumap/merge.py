"""Merge maps built from disjoint sets of pings: the map one mapper makes from all of them.

Every update a ping makes is a min or a count, per voxel, independent of the map's state:

- ``min_all`` (the plain rule's whole state; the visible rule's min over every view):
  ``min`` over views, so two maps combine with ``min``;
- ``bright`` (visible rule, the min over the views with ``v >= threshold``): ``min`` too;
- ``count`` (visible rule, clear dark evidence, +1 or +2 per view, saturating at 255): a
  saturating sum. Saturating addition of non-negative steps is associative and commutative
  (``min(min(a + x, 255) + y, 255) == min(a + x + y, 255)``), so two maps combine with
  ``min(count_a + count_b, 255)``.

Hence ``merge`` is exact, bit for bit, for any split of the pings and either rule: values,
``evidence()`` and ``observed()`` of the merged map equal those of one mapper that integrated
every ping (in any order; the ping count adds up). Nothing else in the visible rule's state
depends on the order: ``carve_views`` is applied when the map is read.

What is *not* mergeable exactly: a map on demand (:class:`~gpumap.SparseSpec`) that *evicted* blocks
(``max_bytes`` with ``evict="farthest"``) has forgotten what its pings said about them, and
which blocks a single mapper would have evicted depends on the order and on where the sonar
was when the cap was reached; merging such maps combines what each still holds, exactly, but
is not the map of one run. ``merge`` itself never evicts: a merge that would pass the target's
``max_bytes`` raises :class:`~gpumap.MapMemoryError` with the map unchanged. The pool layout
(which slot holds which block) depends on the order but is not part of the map: states, reads
and files list blocks in coordinate order, and only blocks with an observed voxel travel.

Maps merge when they have the same kind (dense: a bounded GridSpec; sparse: blocks on demand),
sonar spec, grid (or sparse spec),
method, ``shadow_m``, rule, ``threshold`` and ``carve_views``; anything else raises
``ValueError`` naming the first field that differs.
"""

from __future__ import annotations

import json
import os
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gpumap.errors import FormatError

__all__ = ["MapState", "load_map", "map_state", "merge_into", "merge_maps", "new_like"]



@dataclass(frozen=True, eq=False)
class MapState:
    """What a map holds, as plain NumPy arrays and JSON-able options (picklable: it is what
    workers send back).

    Parameters
    ----------
    kind : str
        ``"dense"`` (a bounded :class:`~gpumap.GridSpec`, every block allocated) or ``"sparse"``
        (blocks on demand, a :class:`~gpumap.SparseSpec`).
    options : dict
        ``spec`` (``SonarSpec.to_dict()``), ``grid`` (``GridSpec.to_dict()``, dense) or
        ``sparse`` (``SparseSpec.to_dict()``), ``method``, ``shadow_m``, ``rule``, ``threshold``,
        ``carve_views``, ``confidence``.
    n_integrated : int
        Pings the map has integrated.
    arrays : dict
        ``blocks`` ``(n, 3)`` int64 block coordinates (lexicographic order; only blocks with an
        observed voxel), and per block ``(n, B B Bz)`` ``min_all`` float32 (``+inf`` never
        observed) and for the visible rule ``bright`` float32 and ``count`` uint8; ``pings``
        ``(k,) uint64``, the fingerprints of the pings it knows (:mod:`gpumap.pings`; ``k`` may
        be less than ``n_integrated`` for maps of older files, absent in a state built by hand).
    """

    kind: str
    options: dict
    n_integrated: int
    arrays: dict = field(repr=False)


def _options(mapper) -> tuple[str, dict]:
    from gpumap.mapper import MinMaxMapper

    if not isinstance(mapper, MinMaxMapper):
        raise TypeError(
            f"Expected a gpumap.MinMaxMapper, MapState or a map file's path, but got {type(mapper).__name__}"
        )
    if mapper.sparse is None:
        kind, space = "dense", {"grid": mapper.grid.to_dict()}
    else:
        kind, space = "sparse", {"sparse": mapper.sparse.to_dict()}
    return kind, {
        "spec": mapper.spec.to_dict(),
        **space,
        "method": mapper.method,
        "shadow_m": float(mapper.shadow_m),
        "rule": mapper.rule,
        "threshold": float(mapper.threshold),
        "carve_views": int(mapper.carve_views),
        "bright_share": float(mapper.bright_share),
        "share_z": float(mapper.share_z),
        "confidence": getattr(mapper, "_confirmed", None) is not None,
    }


def map_state(mapper) -> MapState:
    """A copy of ``mapper``'s state (see :class:`MapState`); waits for queued pings first."""
    kind, opts = _options(mapper)
    with mapper._lock:
        mapper.synchronize()
        mapper._settle()  # on demand, blocks no ping observed are freed
        coords, data = mapper._blocks(values=False, seen_only=True)  # blocks that hold something
        keep = np.isfinite(data["min_all"]).any(axis=1)  # only observed blocks travel
        arrays = {"blocks": coords[keep].astype(np.int64), "min_all": data["min_all"][keep]}
        if mapper.rule != "plain":
            arrays["bright"], arrays["count"] = data["bright"][keep], data["count"][keep]
        arrays["pings"] = mapper.pings.array()
        n = int(mapper.n_integrated)
    return MapState(kind, opts, n, arrays)


def _same(kind: str, opts: dict, other: MapState) -> None:
    """Raise ValueError naming the first option that differs between a map and ``other``."""
    if kind != other.kind:
        raise ValueError(
            f"Expected maps of the same kind to merge, but got a {kind} map and a {other.kind} map "
            "(merge dense with dense and sparse with sparse)"
        )
    for key in ("spec", "grid", "sparse", "method", "shadow_m", "rule", "threshold", "carve_views",
                "bright_share", "share_z"):
        a, b = opts.get(key), other.options.get(key)
        if a != b:
            if isinstance(a, dict) and isinstance(b, dict):  # name the field inside (spec.n_bins, ...)
                sub = next(k for k in (*a, *(k for k in b if k not in a)) if a.get(k) != b.get(k))
                key, a, b = f"{key}.{sub}", a.get(sub), b.get(sub)
            raise ValueError(f"Expected maps with the same {key} to merge, "
                             f"but got {_short(a)} and {_short(b)}")


def _short(value) -> str:
    """``repr(value)``, but a long table as its length and ends (an error stays one readable line)."""
    if isinstance(value, (list, tuple)) and len(value) > 6:
        return f"{len(value)} values from {value[0]!r} to {value[-1]!r}"
    return repr(value)


def _distinct_files(maps):
    """Yield ``maps``; raise ValueError when two of them are one map file (the same path, or the
    same bytes): a map merged with itself counts its clear dark views twice, a wrong map."""
    import hashlib

    seen: dict[int, list[Path]] = {}  # file size -> the files of that size so far
    digests: dict[Path, bytes] = {}

    def digest(path: Path) -> bytes:
        if path not in digests:
            h = hashlib.sha256()
            with open(path, "rb") as f:
                for chunk in iter(lambda: f.read(1 << 20), b""):
                    h.update(chunk)
            digests[path] = h.digest()
        return digests[path]

    for m in maps:
        if isinstance(m, (str, os.PathLike)) and Path(m).is_file():
            p = Path(m).resolve()
            size = p.stat().st_size
            for q in seen.get(size, []):
                if q == p or digest(q) == digest(p):
                    raise ValueError(
                        f"Expected map files built from different pings, but {str(m)!r} is the same map as "
                        f"{str(q)!r} (a map merged with itself counts its clear dark views twice)"
                    )
            seen.setdefault(size, []).append(p)
        yield m


def _as_state(other, backend: str = "numpy") -> MapState:
    if isinstance(other, MapState):
        return other
    if isinstance(other, (str, os.PathLike)):
        return map_state(load_map(other, backend=backend))
    return map_state(other)


def _combine_into(acc: dict, b: dict, rule: str) -> None:
    """``acc`` (arrays or views, e.g. a box of the grid) becomes the merge of itself and ``b``
    (the same voxels, any shape of the same size), in place: mins of the mins, and for the rules
    that keep view state (all but ``"plain"``) saturating sums of the view counts
    (:func:`gpumap.reference.add_counts`)."""
    from gpumap.reference import add_counts

    shape = acc["min_all"].shape
    np.minimum(acc["min_all"], b["min_all"].reshape(shape), out=acc["min_all"])
    if rule != "plain":
        np.minimum(acc["bright"], b["bright"].reshape(shape), out=acc["bright"])
        acc["count"][...] = add_counts(acc["count"], b["count"].reshape(shape), rule)


def merge_into(mapper, other) -> None:
    """Merge ``other`` (a mapper, a :class:`MapState` or a map file) into ``mapper``, in place.

    Afterwards ``mapper`` holds the map of its pings and ``other``'s, bit for bit as one mapper
    that integrated all of them (module docstring). Raises ``TypeError``/``ValueError`` for a
    map of another kind or options, or ``mapper`` itself, and
    :class:`~gpumap.MapMemoryError` when a sparse map would pass its ``max_bytes``; in every
    case before ``mapper`` changes.
    """
    if other is mapper:
        raise ValueError(
            "Expected another map to merge, but got the mapper itself (its evidence would count twice)"
        )
    kind, opts = _options(mapper)
    st = _as_state(other)
    if opts["confidence"] or st.options.get("confidence"):
        raise ValueError(
            "Expected maps without the confidence layer to merge, but got one made with confidence=True: "
            "a voxel is confirmed against what was known free when its ping came, so the layer depends "
            "on the order of the pings and merged maps could not hold it exactly"
        )
    _same(kind, opts, st)
    _check_arrays(st, mapper)
    prints = _prints(st)
    shared = mapper.pings.shared(prints)
    if shared:
        raise ValueError(
            f"Expected maps built from different pings, but the map to merge shares {shared} of its "
            f"{len(prints)} known pings with the map it goes into (merged, those pings would count twice)")
    with mapper._lock:
        # a map that nothing went into yet: the other's blocks are the merge (no read of the pool)
        mapper._put_blocks(st.arrays["blocks"], st.arrays, combine=not mapper._empty)
        mapper.n_integrated += int(st.n_integrated)
        mapper.pings.extend(prints)


def _prints(st: MapState) -> np.ndarray:
    """The state's ping fingerprints, checked: ``(k,) uint64``, distinct, ``k <= n_integrated``."""
    p = st.arrays.get("pings")
    if p is None:
        return np.zeros(0, np.uint64)
    if not isinstance(p, np.ndarray) or p.ndim != 1 or p.dtype != np.uint64 or len(p) > st.n_integrated:
        got = f"{getattr(p, 'shape', '?')} {getattr(p, 'dtype', type(p).__name__)}"
        raise ValueError(f"Expected 'pings' of shape (k,) uint64 with k <= {st.n_integrated} pings in the "
                         f"map to merge, but got {got}")
    return p


def _check_arrays(st: MapState, mapper) -> None:
    """The state's arrays have the shapes and dtypes its options say, and its blocks lie inside
    ``mapper``'s bounds (a MapState built by hand)."""
    names = ("min_all", "bright", "count") if st.options["rule"] != "plain" else ("min_all",)
    m = len(st.arrays.get("blocks", ()))
    want = {k: ((m, mapper.BV), np.uint64 if k == "count" else np.float32) for k in names}
    want["blocks"] = ((m, 3), np.int64)
    for k, (shape, dt) in want.items():
        a = st.arrays.get(k)
        if not isinstance(a, np.ndarray) or a.shape != shape or a.dtype != dt:
            got = "nothing" if a is None else f"{getattr(a, 'shape', '?')} {getattr(a, 'dtype', '?')}"
            raise ValueError(
                f"Expected '{k}' of shape {shape} {np.dtype(dt)} in the map to merge, but got {got}"
            )
    c = st.arrays["blocks"]
    if m and (len(np.unique(c, axis=0)) != m or (mapper._dims is not None and (
            np.any(c < 0) or np.any(c * mapper._bs >= mapper._dims)))):
        raise ValueError("Expected distinct blocks inside the map's bounds in the map to merge, but got "
                         "repeated blocks or blocks outside")
    n = st.n_integrated
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 0:
        raise ValueError(f"Expected a non-negative ping count in the map to merge, but got {n!r}")


# ------------------------------------------------------------------------------ files and many maps
def _file_format(path: Path) -> str:
    """The ``format`` field of a map file's metadata (before anything large is read)."""
    from gpumap.mapper import _META_MAX_BYTES

    try:
        with zipfile.ZipFile(path) as zf:
            info = zf.getinfo("meta.npy")
            if info.file_size > _META_MAX_BYTES:
                raise FormatError(f"Expected map metadata under {_META_MAX_BYTES} bytes in {path}")
            with zf.open(info) as f:
                meta = json.loads(str(np.lib.format.read_array(f, allow_pickle=False)))
    except zipfile.BadZipFile:
        raise FormatError(f"Expected a gpumap map file (.npz: a zip archive) at {path}, but it is not a zip "
                          "archive (a truncated or damaged file, or another kind of file)") from None
    except KeyError:
        raise FormatError(f"Expected a gpumap map file (.npz with 'meta') at {path}, but it has no 'meta' "
                          "member: a .npz that gpumap did not write") from None
    except (OSError, EOFError, json.JSONDecodeError, UnicodeDecodeError, ValueError) as e:
        if isinstance(e, FormatError):
            raise
        raise FormatError(f"Expected a gpumap map file (.npz with 'meta') at {path}, but its metadata cannot "
                          f"be read ({type(e).__name__}: {e})") from e
    fmt = meta.get("format") if isinstance(meta, dict) else None
    if not isinstance(fmt, str):
        raise FormatError(f"Expected a 'format' in the metadata of {path}, but got {fmt!r}")
    return fmt


def load_map(path: str | os.PathLike, backend: str = "auto"):
    """Load a map file written by :meth:`MinMaxMapper.save` (any version, either storage, or the
    former ``SparseMinMaxMapper.save``) onto ``backend``."""
    from gpumap.mapper import FILE_FORMAT, SPARSE_FILE_FORMAT, MinMaxMapper

    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"Expected a map file at {p}, but nothing is there")
    fmt = _file_format(p)
    if fmt not in (FILE_FORMAT, SPARSE_FILE_FORMAT):
        raise FormatError(f"Expected format {FILE_FORMAT!r} or {SPARSE_FILE_FORMAT!r} in {p}, "
                          f"but got {fmt!r}")
    return MinMaxMapper.load(p, backend=backend)


def new_like(state: MapState, backend: str = "auto", **kw):
    """An empty mapper with ``state``'s kind and options on ``backend`` (``kw``: a sparse map's
    ``max_bytes``, ``evict``, ``initial_blocks``)."""
    from gpumap.mapper import MinMaxMapper
    from gpumap.spec import GridSpec, SonarSpec, SparseSpec

    o = state.options
    spec = SonarSpec.from_dict(o["spec"])
    common = dict(method=o["method"], shadow_m=o["shadow_m"], rule=o["rule"], threshold=o["threshold"],
                  carve_views=o["carve_views"])
    if state.kind == "dense":
        return MinMaxMapper(spec, GridSpec.from_dict(o["grid"]), backend=backend, **common)
    return MinMaxMapper(spec, SparseSpec.from_dict(o["sparse"]), backend=backend, **common, **kw)


def merge_maps(maps, backend: str = "auto", **kw):
    """A new mapper holding the merge of ``maps`` (mappers, :class:`MapState` objects or map
    files, all of the same kind and options; any iterable: one map is held at a time beside
    the result), on ``backend``; ``maps`` are left as they were.

    Equal bit for bit to one mapper that integrated every ping of every map (see the module
    docstring). Raises ``ValueError`` for no maps, maps that differ or one map file given twice,
    and what :func:`merge_into` raises.
    """
    it = _distinct_files(maps)
    try:
        src = next(it)
    except StopIteration:
        raise ValueError("Expected at least one map to merge, but got none") from None
    first = _as_state(src)
    out = new_like(first, backend=backend, **kw)
    st = first
    seen: list[tuple[str, np.ndarray]] = []  # (name, ping fingerprints) of the maps merged so far
    while st is not None:  # one map at a time: only blocks that two maps hold are combined
        prints, name = _prints(st), _name(src, len(seen))
        for other, theirs in seen:
            n = int(np.isin(prints, theirs).sum())
            if n:
                raise ValueError(
                    f"Expected maps built from different pings, but {name} and {other} share {n} pings "
                    f"({name} has {st.n_integrated}, {other} {len(theirs)} known): merged, those pings "
                    "would count twice; merge maps of disjoint frames (gpumap replay --frames)")
        merge_into(out, st)
        seen.append((name, prints))
        src = next(it, None)
        st = None if src is None else _as_state(src)
    return out


def _name(src, i: int) -> str:
    """How an error names a map to merge: its file, or its place in the list."""
    return repr(str(src)) if isinstance(src, (str, os.PathLike)) else f"map {i + 1}"

