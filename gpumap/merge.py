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

What is *not* mergeable exactly: a :class:`~gpumap.SparseMinMaxMapper` that *evicted* blocks
(``max_bytes`` with ``evict="farthest"``) has forgotten what its pings said about them, and
which blocks a single mapper would have evicted depends on the order and on where the sonar
was when the cap was reached; merging such maps combines what each still holds, exactly, but
is not the map of one run. ``merge`` itself never evicts: a merge that would pass the target's
``max_bytes`` raises :class:`~gpumap.MapMemoryError` with the map unchanged. The sparse map's
pool layout (which slot holds which block) depends on the order but is not part of the map:
reads and files list blocks in coordinate order.

Maps merge when they have the same kind (dense or sparse), sonar spec, grid (or sparse spec),
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

_COUNT_MAX = 255


@dataclass(frozen=True, eq=False)
class MapState:
    """What a map holds, as plain NumPy arrays and JSON-able options (picklable: it is what
    workers send back).

    Parameters
    ----------
    kind : str
        ``"dense"`` (:class:`~gpumap.MinMaxMapper`) or ``"sparse"`` (:class:`~gpumap.SparseMinMaxMapper`).
    options : dict
        ``spec`` (``SonarSpec.to_dict()``), ``grid`` (``GridSpec.to_dict()``, dense) or
        ``sparse`` (``SparseSpec.to_dict()``), ``method``, ``shadow_m``, ``rule``, ``threshold``,
        ``carve_views``.
    n_integrated : int
        Pings the map has integrated.
    arrays : dict
        ``min_all`` float32 (``+inf`` never observed), and for the visible rule ``bright``
        float32 and ``count`` uint8: dense ``(n_voxels,)`` in C order; sparse ``(n, B^3)``
        per block, with ``blocks`` ``(n, 3)`` int64 block coordinates (lexicographic order).
    box : tuple or None
        Dense only: ``((i0, i1), (j0, j1), (k0, k1))``, the arrays cover just this box of the
        grid (C order, ``(i1 - i0) (j1 - j0) (k1 - k0)`` voxels); outside it the state is the
        empty one (never observed). None: the whole grid.
    """

    kind: str
    options: dict
    n_integrated: int
    arrays: dict = field(repr=False)
    box: tuple | None = None


def _options(mapper) -> tuple[str, dict]:
    from gpumap.mapper import MinMaxMapper
    from gpumap.sparse import SparseMinMaxMapper

    if isinstance(mapper, MinMaxMapper):
        kind, space = "dense", {"grid": mapper.grid.to_dict()}
    elif isinstance(mapper, SparseMinMaxMapper):
        kind, space = "sparse", {"sparse": mapper.sparse.to_dict()}
    else:
        raise TypeError(
            f"Expected a gpumap.MinMaxMapper, gpumap.SparseMinMaxMapper, MapState or a map file's path, "
            f"but got {type(mapper).__name__}"
        )
    return kind, {
        "spec": mapper.spec.to_dict(),
        **space,
        "method": mapper.method,
        "shadow_m": float(mapper.shadow_m),
        "rule": mapper.rule,
        "threshold": float(mapper.threshold),
        "carve_views": int(mapper.carve_views),
        "confidence": getattr(mapper, "_confirmed", None) is not None,
    }


def map_state(mapper) -> MapState:
    """A copy of ``mapper``'s state (see :class:`MapState`); waits for queued pings first."""
    kind, opts = _options(mapper)
    visible = mapper.rule == "visible"
    with mapper._lock:
        if kind == "dense":
            mapper.synchronize()
            arrays = {"min_all": mapper._backend.read()}
            if visible:
                arrays["bright"], arrays["count"] = mapper._backend.read_evidence()
        else:
            mapper.synchronize()
            mapper._settle()  # blocks no ping observed are freed: only observed blocks travel
            coords, data = mapper._blocks()
            arrays = {"blocks": coords.astype(np.int64), "min_all": data["min_all"]}
            if visible:
                arrays["bright"], arrays["count"] = data["bright"], data["count"]
        n = int(mapper.n_integrated)
    return MapState(kind, opts, n, arrays)


def _same(kind: str, opts: dict, other: MapState) -> None:
    """Raise ValueError naming the first option that differs between a map and ``other``."""
    if kind != other.kind:
        raise ValueError(
            f"Expected maps of the same kind to merge, but got a {kind} map and a {other.kind} map "
            "(merge dense with dense and sparse with sparse)"
        )
    for key in ("spec", "grid", "sparse", "method", "shadow_m", "rule", "threshold", "carve_views"):
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


def _combine_into(acc: dict, b: dict, visible: bool) -> None:
    """``acc`` (arrays or views, e.g. a box of the grid) becomes the merge of itself and ``b``
    (the same voxels, any shape of the same size), in place."""
    shape = acc["min_all"].shape
    np.minimum(acc["min_all"], b["min_all"].reshape(shape), out=acc["min_all"])
    if visible:
        np.minimum(acc["bright"], b["bright"].reshape(shape), out=acc["bright"])
        c = acc["count"].astype(np.uint16)
        c += b["count"].reshape(shape)
        np.minimum(c, _COUNT_MAX, out=c)
        acc["count"][...] = c


def _empty_dense(n: int, visible: bool) -> dict:
    out = {"min_all": np.full(n, np.inf, np.float32)}
    if visible:
        out["bright"], out["count"] = np.full(n, np.inf, np.float32), np.zeros(n, np.uint8)
    return out


def _box_views(full: dict, shape: tuple, box: tuple | None) -> dict:
    """Views of the (n_voxels,) arrays ``full`` on ``box`` of a grid of ``shape`` (all if None)."""
    if box is None:
        return full
    sl = tuple(slice(a, b) for a, b in box)
    return {k: v.reshape(shape)[sl] for k, v in full.items()}


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
    visible = opts["rule"] == "visible"
    _check_arrays(st, mapper)
    if kind == "dense":
        _merge_dense(mapper, st, visible)
    else:
        _merge_sparse(mapper, st, visible)


def _check_arrays(st: MapState, mapper) -> None:
    """The state's arrays have the shapes and dtypes its options say (a MapState built by hand)."""
    names = ("min_all", "bright", "count") if st.options["rule"] == "visible" else ("min_all",)
    if st.kind == "sparse" and st.box is not None:
        raise ValueError(f"Expected no box with a sparse map's state (blocks say where), but got {st.box!r}")
    if st.kind == "dense":
        n = mapper.grid.n_voxels
        if st.box is not None:
            box = st.box
            ok = len(box) == 3 and all(
                0 <= int(a) <= int(b) <= d for (a, b), d in zip(box, mapper.grid.shape, strict=True)
            )
            if not ok:
                raise ValueError(f"Expected a box inside the grid {mapper.grid.shape}, but got {box!r}")
            n = int(np.prod([b - a for a, b in box]))
        want = {k: ((n,), np.uint8 if k == "count" else np.float32) for k in names}
    else:
        m = len(st.arrays.get("blocks", ()))
        B3 = mapper.B3
        want = {k: ((m, B3), np.uint8 if k == "count" else np.float32) for k in names}
        want["blocks"] = ((m, 3), np.int64)
    for k, (shape, dt) in want.items():
        a = st.arrays.get(k)
        if not isinstance(a, np.ndarray) or a.shape != shape or a.dtype != dt:
            got = "nothing" if a is None else f"{getattr(a, 'shape', '?')} {getattr(a, 'dtype', '?')}"
            raise ValueError(
                f"Expected '{k}' of shape {shape} {np.dtype(dt)} in the map to merge, but got {got}"
            )
    n = st.n_integrated
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 0:
        raise ValueError(f"Expected a non-negative ping count in the map to merge, but got {n!r}")


def _union_blocks(first: MapState, rest, like) -> MapState:
    """One sparse state holding the merge of ``first`` and the maps in ``rest`` (checked
    against ``first`` and ``like``, the mapper they go into): the union of their blocks, each
    block's arrays combined as :func:`_combine_into` combines voxels."""
    states = [first]
    for m in rest:
        st = _as_state(m)
        _same(first.kind, first.options, st)
        states.append(st)
    for st in states:
        _check_arrays(st, like)
    visible = first.options["rule"] == "visible"
    coords, inverse = np.unique(np.concatenate([st.arrays["blocks"] for st in states]), axis=0,
                                return_inverse=True)
    inverse = inverse.reshape(-1)
    acc = {k: v.reshape(len(coords), -1) for k, v in _empty_dense(len(coords) * like.B3, visible).items()}
    start = 0
    for st in states:
        rows = inverse[start : start + len(st.arrays["blocks"])]  # distinct within one map
        start += len(rows)
        part = {k: acc[k][rows] for k in acc}
        _combine_into(part, st.arrays, visible)
        for k in acc:
            acc[k][rows] = part[k]
    return MapState(first.kind, first.options, sum(int(st.n_integrated) for st in states),
                    {"blocks": coords.astype(np.int64), **acc})


def _merge_dense(mapper, st: MapState, visible: bool) -> None:
    with mapper._lock:
        mapper.synchronize()
        mine = {"min_all": mapper._backend.read()}  # copies: combined in place below
        if visible:
            mine["bright"], mine["count"] = mapper._backend.read_evidence()
        _combine_into(_box_views(mine, mapper.grid.shape, st.box), st.arrays, visible)
        if visible:
            mapper._backend.write_evidence(mine["bright"], mine["count"])
        mapper._backend.write(mine["min_all"])
        mapper.n_integrated += int(st.n_integrated)


def _merge_sparse(mapper, st: MapState, visible: bool) -> None:
    from gpumap.sparse import MapMemoryError

    coords = st.arrays["blocks"]
    B3 = mapper.B3
    with mapper._lock:
        mapper.synchronize()
        mapper._settle()
        if len(coords):
            if mapper._dims is None:  # an unbounded map's index must span the other's blocks
                mapper._ensure_index(coords.min(axis=0), coords.max(axis=0))
            lins = mapper._lins(coords)
            flat = mapper._index.reshape(-1)
            new = flat[lins] < 0
            n_new = int(new.sum())
            short = n_new - len(mapper._free)
            if short > 0:
                cap = mapper._backend.cap + short
                if mapper.max_bytes is not None:
                    need = cap * mapper._block_bytes + mapper._index.nbytes
                    if need > mapper.max_bytes:
                        raise MapMemoryError(
                            f"Expected the merged map to stay under max_bytes={mapper.max_bytes}, but it "
                            f"needs {cap} blocks of {mapper._block_bytes} bytes plus a {mapper._index.nbytes}"
                            f"-byte index ({need} bytes); the map is unchanged (merge never evicts)"
                        )
                mapper._grow_to(cap)
            if n_new:
                k = len(mapper._free) - n_new
                slots_new = mapper._free[k:][::-1]
                mapper._free = mapper._free[:k]
                flat[lins[new]] = slots_new
                mapper._coords[slots_new] = coords[new]
                mapper._used[slots_new] = True
                mapper._backend.set_blocks(slots_new.astype(np.int32), lins[new].astype(np.int32))
            slots = flat[lins].astype(np.int64)
            if n_new == len(coords):  # every block is new (empty): the merge is the other's arrays
                mine = st.arrays
            else:
                g, b, c = mapper._backend.read()
                addr = slots[:, None] * B3 + np.arange(B3)
                mine = {"min_all": g[addr]}
                if visible:
                    mine["bright"], mine["count"] = b[addr], c[addr]
                _combine_into(mine, st.arrays, visible)  # mine: copies (fancy indexing)
            mapper._backend.write_blocks(slots, mine["min_all"], mine.get("bright"), mine.get("count"))
        mapper.n_integrated += int(st.n_integrated)


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
    except (OSError, KeyError, EOFError, zipfile.BadZipFile, json.JSONDecodeError, UnicodeDecodeError,
            ValueError) as e:
        if isinstance(e, FormatError):
            raise
        raise FormatError(f"Expected a gpumap map file (.npz with 'meta') at {path}, but: {e!r}") from e
    fmt = meta.get("format") if isinstance(meta, dict) else None
    if not isinstance(fmt, str):
        raise FormatError(f"Expected a 'format' in the metadata of {path}, but got {fmt!r}")
    return fmt


def load_map(path: str | os.PathLike, backend: str = "auto"):
    """Load a map file written by :meth:`MinMaxMapper.save` or :meth:`SparseMinMaxMapper.save`,
    whichever it is (its metadata says), onto ``backend``."""
    from gpumap.mapper import FILE_FORMAT as DENSE
    from gpumap.mapper import MinMaxMapper
    from gpumap.sparse import FILE_FORMAT as SPARSE
    from gpumap.sparse import SparseMinMaxMapper

    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"Expected a map file at {p}, but nothing is there")
    fmt = _file_format(p)
    if fmt == DENSE:
        return MinMaxMapper.load(p, backend=backend)
    if fmt == SPARSE:
        return SparseMinMaxMapper.load(p, backend=backend)
    raise FormatError(f"Expected format {DENSE!r} or {SPARSE!r} in {p}, but got {fmt!r}")


def new_like(state: MapState, backend: str = "auto", **kw):
    """An empty mapper with ``state``'s kind and options on ``backend`` (``kw``: a sparse map's
    ``max_bytes``, ``evict``, ``initial_blocks``)."""
    from gpumap.mapper import MinMaxMapper
    from gpumap.sparse import SparseMinMaxMapper, SparseSpec
    from gpumap.spec import GridSpec, SonarSpec

    o = state.options
    spec = SonarSpec.from_dict(o["spec"])
    common = dict(shadow_m=o["shadow_m"], rule=o["rule"], threshold=o["threshold"],
                  carve_views=o["carve_views"])
    if state.kind == "dense":
        grid = GridSpec.from_dict(o["grid"])
        return MinMaxMapper(spec, grid, backend=backend, method=o["method"], **common)
    return SparseMinMaxMapper(spec, SparseSpec.from_dict(o["sparse"]), backend=backend, **common, **kw)


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
        first = _as_state(next(it))
    except StopIteration:
        raise ValueError("Expected at least one map to merge, but got none") from None
    out = new_like(first, backend=backend, **kw)
    if first.kind == "sparse":
        merge_into(out, _union_blocks(first, it, out))  # the blocks merged here, written once
        return out
    # dense: combine the arrays here (in place, one pass per map over its box), write the map once
    visible = out.rule == "visible"
    shape = out.grid.shape
    acc = _empty_dense(out.grid.n_voxels, visible)
    n = 0
    st = first
    while st is not None:
        _same(first.kind, first.options, st)
        _check_arrays(st, out)
        _combine_into(_box_views(acc, shape, st.box), st.arrays, visible)
        n += int(st.n_integrated)
        nxt = next(it, None)
        st = None if nxt is None else _as_state(nxt)
    with out._lock:
        if visible:
            out._backend.write_evidence(acc["bright"], acc["count"])
        out._backend.write(acc["min_all"])
        out.n_integrated = n
    return out
