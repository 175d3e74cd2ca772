"""A map's contents as plain arrays (:class:`MapState`): read from a mapper, checked, and merged
into another through its block storage (:meth:`gpumap.core.storage.BlockStorage.put_blocks`).

This is the part of merging that works on one mapper at a time; :mod:`gpumap.core.merge` (which says
why merges are exact) builds on it: states of map files, new mappers, many maps.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field

import numpy as np

from gpumap.core.mapfile import load_map

__all__ = ["MapState", "as_state", "check_other", "merge_state", "not_a_map", "options_of", "prints_of",
           "read_state"]


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


def not_a_map(obj) -> TypeError:
    """The error for something given as a map that is none."""
    return TypeError(
        f"Expected a gpumap.MinMaxMapper, MapState or a map file's path, but got {type(obj).__name__}"
    )


def check_other(mapper, other) -> None:
    """Raise ValueError when the map to merge into ``mapper`` is ``mapper`` itself."""
    if other is mapper:
        raise ValueError(
            "Expected another map to merge, but got the mapper itself (its evidence would count twice)"
        )


def options_of(mapper) -> tuple[str, dict]:
    """A mapper's kind (``"dense"`` or ``"sparse"``) and options, as :class:`MapState` holds them."""
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
        "confidence": any(x.name == "confidence" for x in mapper.layers),
    }


def read_state(mapper) -> MapState:
    """A copy of ``mapper``'s state (see :class:`MapState`); waits for queued pings first."""
    kind, opts = options_of(mapper)
    st = mapper.storage
    with st.lock:
        st.synchronize()
        st.settle()  # on demand, blocks no ping observed are freed
        coords, data = st.blocks(values=False, seen_only=True)  # blocks that hold something
        keep = np.isfinite(data["min_all"]).any(axis=1)  # only observed blocks travel
        arrays = {"blocks": coords[keep].astype(np.int64), "min_all": data["min_all"][keep]}
        if mapper.rule != "plain":
            arrays["bright"], arrays["count"] = data["bright"][keep], data["count"][keep]
        arrays["pings"] = mapper.pings.array()
        n = int(mapper.n_integrated)
    return MapState(kind, opts, n, arrays)


def as_state(other, mapper_cls: type, backend: str = "numpy") -> MapState:
    """``other`` as a :class:`MapState`: itself, the state of a mapper (an instance of
    ``mapper_cls``, :class:`gpumap.MinMaxMapper`), or of the map file at a path (loaded onto
    ``backend``); raises ``TypeError`` for anything else."""
    if isinstance(other, MapState):
        return other
    if isinstance(other, (str, os.PathLike)):
        other = load_map(mapper_cls, other, backend)
    if not isinstance(other, mapper_cls):
        raise not_a_map(other)
    return read_state(other)


def merge_state(mapper, st: MapState) -> None:
    """Merge the state ``st`` into ``mapper``, in place (see :func:`gpumap.core.merge.merge_into`):
    raises ``ValueError`` for a state of another kind or options, or that shares pings with
    ``mapper``, and :class:`~gpumap.MapMemoryError` past ``max_bytes``; in every case before
    ``mapper`` changes."""
    kind, opts = options_of(mapper)
    if opts["confidence"] or st.options.get("confidence"):
        raise ValueError(
            "Expected maps without the confidence layer to merge, but got one made with confidence=True: "
            "a voxel is confirmed against what was known free when its ping came, so the layer depends "
            "on the order of the pings and merged maps could not hold it exactly"
        )
    _same(kind, opts, st)
    _check_arrays(st, mapper.storage)
    prints = prints_of(st)
    shared = mapper.pings.shared(prints)
    if shared:
        raise ValueError(
            f"Expected maps built from different pings, but the map to merge shares {shared} of its "
            f"{len(prints)} known pings with the map it goes into (merged, those pings would count twice)")
    storage = mapper.storage
    with storage.lock:
        # a map that nothing went into yet: the other's blocks are the merge (no read of the pool)
        storage.put_blocks(st.arrays["blocks"], st.arrays, combine=not storage.empty)
        mapper.n_integrated += int(st.n_integrated)
        mapper.pings.extend(prints)


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


def prints_of(st: MapState) -> np.ndarray:
    """The state's ping fingerprints, checked: ``(k,) uint64``, distinct, ``k <= n_integrated``."""
    p = st.arrays.get("pings")
    if p is None:
        return np.zeros(0, np.uint64)
    if not isinstance(p, np.ndarray) or p.ndim != 1 or p.dtype != np.uint64 or len(p) > st.n_integrated:
        got = f"{getattr(p, 'shape', '?')} {getattr(p, 'dtype', type(p).__name__)}"
        raise ValueError(f"Expected 'pings' of shape (k,) uint64 with k <= {st.n_integrated} pings in the "
                         f"map to merge, but got {got}")
    return p


def _check_arrays(st: MapState, storage) -> None:
    """The state's arrays have the shapes and dtypes its options say, and its blocks lie inside
    the bounds of ``storage`` (a :class:`~gpumap.core.storage.BlockStorage`; a MapState built by hand)."""
    names = ("min_all", "bright", "count") if st.options["rule"] != "plain" else ("min_all",)
    m = len(st.arrays.get("blocks", ()))
    want = {k: ((m, storage.BV), np.uint64 if k == "count" else np.float32) for k in names}
    want["blocks"] = ((m, 3), np.int64)
    for k, (shape, dt) in want.items():
        a = st.arrays.get(k)
        if not isinstance(a, np.ndarray) or a.shape != shape or a.dtype != dt:
            got = "nothing" if a is None else f"{getattr(a, 'shape', '?')} {getattr(a, 'dtype', '?')}"
            raise ValueError(
                f"Expected '{k}' of shape {shape} {np.dtype(dt)} in the map to merge, but got {got}"
            )
    c = st.arrays["blocks"]
    if m and (len(np.unique(c, axis=0)) != m or (storage.dims is not None and (
            np.any(c < 0) or np.any(c * storage.bs >= storage.dims)))):
        raise ValueError("Expected distinct blocks inside the map's bounds in the map to merge, but got "
                         "repeated blocks or blocks outside")
    n = st.n_integrated
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 0:
        raise ValueError(f"Expected a non-negative ping count in the map to merge, but got {n!r}")
