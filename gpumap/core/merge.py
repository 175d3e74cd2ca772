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

import os
from pathlib import Path

import numpy as np

from gpumap.core.mapfile import load_map as load_file
from gpumap.core.mapper import MinMaxMapper
from gpumap.core.mapstate import MapState, as_state, check_other, not_a_map, prints_of, read_state
from gpumap.core.params import MapperParams
from gpumap.spec import GridSpec, SonarSpec, SparseSpec

__all__ = ["MapState", "load_map", "map_state", "merge_into", "merge_maps", "new_like"]


def map_state(mapper) -> MapState:
    """A copy of ``mapper``'s state (see :class:`MapState`); waits for queued pings first."""
    if not isinstance(mapper, MinMaxMapper):
        raise not_a_map(mapper)
    return read_state(mapper)


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


def merge_into(mapper, other) -> None:
    """Merge ``other`` (a mapper, a :class:`MapState` or a map file) into ``mapper``, in place.

    Afterwards ``mapper`` holds the map of its pings and ``other``'s, bit for bit as one mapper
    that integrated all of them (module docstring). Raises ``TypeError``/``ValueError`` for a
    map of another kind or options, or ``mapper`` itself, and
    :class:`~gpumap.MapMemoryError` when a sparse map would pass its ``max_bytes``; in every
    case before ``mapper`` changes.
    """
    check_other(mapper, other)
    if not isinstance(mapper, MinMaxMapper):
        raise not_a_map(mapper)
    mapper.merge(other)


# ------------------------------------------------------------------------------ files and many maps
def load_map(path: str | os.PathLike, backend: str = "auto"):
    """Load a map file written by :meth:`MinMaxMapper.save` (any version, either storage, or the
    former ``SparseMinMaxMapper.save``) onto ``backend``."""
    return load_file(MinMaxMapper, path, backend)


def new_like(state: MapState, backend: str = "auto", **kw):
    """An empty mapper with ``state``'s kind and options on ``backend`` (``kw``: a sparse map's
    ``max_bytes``, ``evict``, ``initial_blocks``)."""
    o = state.options
    spec = SonarSpec.from_dict(o["spec"])
    common = dict(method=o["method"], shadow_m=o["shadow_m"], rule=o["rule"], threshold=o["threshold"],
                  carve_views=o["carve_views"])
    if state.kind == "dense":
        return MinMaxMapper(spec, GridSpec.from_dict(o["grid"]), backend, MapperParams(**common))
    return MinMaxMapper(spec, SparseSpec.from_dict(o["sparse"]), backend, MapperParams(**common, **kw))


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
    first = as_state(src, MinMaxMapper)
    out = new_like(first, backend=backend, **kw)
    st = first
    seen: list[tuple[str, np.ndarray]] = []  # (name, ping fingerprints) of the maps merged so far
    while st is not None:  # one map at a time: only blocks that two maps hold are combined
        prints, name = prints_of(st), _name(src, len(seen))
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
        st = None if src is None else as_state(src, MinMaxMapper)
    return out


def _name(src, i: int) -> str:
    """How an error names a map to merge: its file, or its place in the list."""
    return repr(str(src)) if isinstance(src, (str, os.PathLike)) else f"map {i + 1}"

