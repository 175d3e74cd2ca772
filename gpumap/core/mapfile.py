"""Map files: :meth:`gpumap.MinMaxMapper.save` and ``load``, the format and its versions.

A map file is an ``.npz`` (written atomically) holding the map in blocks and a JSON ``meta``:
format :data:`FILE_FORMAT`, version :data:`FILE_VERSION`. Every version still loads: 5 (the
evidence rule: ``count`` uint64, clear dark and bright views; ``bright_share``, ``share_z``),
4 (blocks, ``blocks`` and per-block arrays, for every storage), 3 (the optional confidence layer,
``confirmed``), 2 (the visible rule's evidence ``bright``, ``count`` and the rule); 1 to 3 are
dense arrays over the grid, and files of the former ``SparseMinMaxMapper``
(:data:`SPARSE_FILE_FORMAT`) load too. A file is checked before anything large is read or
allocated (:func:`load`), so a small or damaged file cannot make it allocate gigabytes.
"""

from __future__ import annotations

import json
import os
import struct
import tokenize
import zipfile
import zlib
from pathlib import Path

import numpy as np

import gpumap.memory as memory
from gpumap.atomic import atomic_write
from gpumap.core.integrator import METHODS
from gpumap.core.params import MapperParams
from gpumap.core.rules import rule_values
from gpumap.core.storage import BLOCK, local_offsets
from gpumap.errors import FormatError, LimitError
from gpumap.geometry import BRIGHT_SHARE, RULES, SHARE_Z
from gpumap.pings import read_prints
from gpumap.spec import _MAX_VOXEL_INDEX, GridSpec, SonarSpec, SparseSpec

__all__ = ["FILE_FORMAT", "FILE_VERSION", "SPARSE_FILE_FORMAT", "file_format", "load", "load_map", "save"]

FILE_FORMAT = "gpumap.MinMaxMapper"
# 5: the evidence rule (``count`` uint64: clear dark and bright views; bright_share, share_z);
# 4: blocks (``blocks`` and per-block arrays) for every storage; 3: the optional confidence layer
# (confirmed); 2: the visible rule's evidence (bright, count) and the rule; 1 to 3 are dense
# arrays over the grid, and still load, as do files of the former SparseMinMaxMapper
FILE_VERSION = 5
SPARSE_FILE_FORMAT = "gpumap.SparseMinMaxMapper"  # written until version 4 took its place


def save(mapper, path: str | os.PathLike) -> Path:
    """Write ``mapper``'s map to ``path`` (see :meth:`gpumap.MinMaxMapper.save`); the path written."""
    path = Path(path)
    if path.suffix != ".npz":
        path = path.with_suffix(path.suffix + ".npz") if path.suffix else path.with_suffix(".npz")
    st = mapper.storage
    # the layers' arrays the file keeps (the confidence layer's, today: its name is the file's key)
    layer = next((x for x in mapper.layers if x.name == "confidence"), None)
    B, Bz = st.B, st.Bz
    with st.lock:  # one consistent snapshot, even while other threads integrate
        st.synchronize()
        st.settle()
        coords, data = st.blocks()
        keep = np.isfinite(data["min_all"]).any(axis=1)
        arrays = {"blocks": coords[keep].astype(np.int32), "values": data["values"][keep]}
        if st.stateful:
            arrays.update({k: data[k][keep] for k in ("min_all", "bright", "count")})
        if layer is not None:
            shape = mapper.grid.shape
            for k, a in layer.file_arrays().items():
                arrays[k] = st.to_pool_order(a.reshape(shape), 0)[keep]
        n_integrated = mapper.n_integrated
        arrays["pings"] = mapper.pings.array()
    arrays = {k: v if k in ("blocks", "pings") else v.reshape(-1, B, B, Bz) for k, v in arrays.items()}
    meta = {
        "format": FILE_FORMAT,
        "version": FILE_VERSION,
        "spec": mapper.spec.to_dict(),
        "grid": mapper.grid.to_dict() if mapper.sparse is None else None,
        "sparse": None if mapper.sparse is None else mapper.sparse.to_dict(),
        "block": [B, B, Bz],
        "method": mapper.method,
        "shadow_m": mapper.shadow_m,
        "rule": mapper.rule,
        "threshold": mapper.threshold,
        "carve_views": mapper.carve_views,
        "bright_share": mapper.bright_share,
        "share_z": mapper.share_z,
        "n_integrated": n_integrated,
        "backend": mapper.backend,
        "confidence": layer is not None,
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(path) as f:
        np.savez_compressed(f, **arrays, meta=np.array(json.dumps(meta)))
    return path


def load(cls, path: str | os.PathLike, backend: str = "auto", kw: dict | None = None, *,
         on_demand: bool = False):
    """A ``cls`` (:class:`gpumap.MinMaxMapper` or a subclass) holding the map of the file at ``path``
    (any version, and the former ``SparseMinMaxMapper.save``) on ``backend``; ``kw``: more
    constructor options (``max_bytes``, ``evict`` for a map on demand); ``on_demand``: ``cls``
    holds only maps on demand (a bounded grid's file is refused).

    Everything is checked before anything large is read or allocated, and raises
    :class:`~gpumap.errors.FormatError` (see :meth:`gpumap.MinMaxMapper.load`).
    """
    kw = {} if kw is None else kw
    path = Path(path)
    try:
        with zipfile.ZipFile(path) as zf:
            members = {i.filename: i for i in zf.infolist()}
            if "meta.npy" not in members or not {"values.npy", "blocks.npy"} & set(members):
                raise FormatError(
                    f"Expected a gpumap map file with 'meta' and 'blocks' (or 'meta' and 'values', "
                    f"versions 1 to 3), but {path} has "
                    f"{sorted(n.removesuffix('.npy') for n in members)}"
                )
            headers = {
                n: _npy_header(zf, info, path) for n, info in members.items() if n.endswith(".npy")
            }
            if members["meta.npy"].file_size > _META_MAX_BYTES:
                raise FormatError(
                    f"Expected map metadata under {_META_MAX_BYTES} bytes in {path}, "
                    f"but it declares {members['meta.npy'].file_size}"
                )
            with zf.open("meta.npy") as f:
                meta = json.loads(str(np.lib.format.read_array(f, allow_pickle=False)))
            spec, space, opts, n_integrated, dense_file = _check_meta(meta, path)
            # before version 5 'count' was the visible rule's uint8 dark count
            count_dt = np.uint64 if meta.get("version") == FILE_VERSION else np.uint8
            prints = read_prints(zf, members, headers, n_integrated, path)
            if on_demand and not isinstance(space, SparseSpec):
                raise FormatError(f"Expected a sparse map file (blocks on demand) for {cls.__name__}, "
                                  f"but {path} holds a map of a bounded grid: load it with MinMaxMapper")
            names = ("values", "min_all", "bright", "count") if opts["rule"] != "plain" else ("values",)
            if opts["confidence"]:
                names = (*names, "confirmed", "arcs")
            if dense_file:  # versions 1 to 3: arrays over the grid
                n_blocks, shape = None, space.shape
            else:
                bshape, bdt = headers.get("blocks.npy", (None, None))
                if bshape is None or len(bshape) != 2 or bshape[1] != 3 or bdt != np.dtype(np.int32):
                    raise FormatError(
                        f"Expected 'blocks' of shape (n, 3) int32 in {path}, but got "
                        f"{'nothing' if bshape is None else f'{bshape} {bdt}'}"
                    )
                if isinstance(space, SparseSpec):
                    B, Bz = space.block, space.block
                else:  # as a mapper of this grid lays its blocks out
                    B, Bz = BLOCK, int(space.shape[2])
                if meta.get("block", [B, B, Bz]) != [B, B, Bz]:
                    raise FormatError(f"Expected blocks of {[B, B, Bz]} voxels in {path}, but its "
                                      f"metadata says {meta.get('block')!r}")
                n_blocks = bshape[0]
                shape = (n_blocks, B, B, Bz)
            for name in names:
                dt = {"count": count_dt, "confirmed": np.uint8, "arcs": np.uint16}.get(name, np.float32)
                got, dtype = headers.get(f"{name}.npy", (None, None))
                if got != shape or dtype != np.dtype(dt):
                    raise FormatError(
                        f"Expected '{name}' of shape {shape} {np.dtype(dt)} in {path}, "
                        f"but got {'nothing' if got is None else f'{got} {dtype}'}"
                    )
            size = {"count": 8, "confirmed": 1, "arcs": 2}
            need = sum(int(np.prod(shape)) * size.get(n, 4) for n in names)
            free = memory.free_memory_bytes("numpy")
            if free is not None and 2 * need > free:
                raise LimitError(
                    f"Expected a map that fits in memory, but {path} holds {need / 2**30:.2f} GiB "
                    f"(twice that while loading) and {free / 2**30:.2f} GiB are free"
                )
            arrays = {}
            for name in (*names, *(() if dense_file else ("blocks",))):
                with zf.open(f"{name}.npy") as f:
                    arrays[name] = np.lib.format.read_array(f, allow_pickle=False)
            if "count" in arrays:  # the packed view counts (an old file's dark count, no bright count)
                arrays["count"] = arrays["count"].astype(np.uint64)
    except (OSError, EOFError, zipfile.BadZipFile, json.JSONDecodeError, UnicodeDecodeError,
            zlib.error, tokenize.TokenError, SyntaxError, NotImplementedError, struct.error) as e:
        # damaged deflate data, a damaged .npy header dict, an unknown zip compression
        raise FormatError(
            f"Expected a gpumap map file (.npz) at {path}, but it cannot be read "
            f"({type(e).__name__}: {e})"
        ) from e
    if dense_file:
        _check_map_values(arrays, opts, path)
        m = _made(cls, spec, space, backend, opts, kw)
        with m.storage.lock:
            if opts["rule"] != "plain":
                m.storage.write_box(arrays["min_all"], arrays["bright"], arrays["count"])
            else:
                m.storage.write_box(arrays["values"])
            _restore(m, arrays if opts["confidence"] else None, n_integrated, prints)
        return m
    coords = arrays.pop("blocks").astype(np.int64)
    n = len(coords)
    bs = np.array([B, B, Bz], np.int64)
    flat = {k: v.reshape(n, B * B * Bz) for k, v in arrays.items()}
    _check_map_values(flat, opts, path)
    if n and len(np.unique(coords, axis=0)) != n:
        raise FormatError(f"Expected each block once in {path}, but some repeat")
    if np.abs(coords).max(initial=0) * max(B, Bz) > _MAX_VOXEL_INDEX - 2 * max(B, Bz):
        raise FormatError(f"Expected block coordinates within +-{_MAX_VOXEL_INDEX // B - 2} in {path}")
    obs = np.isfinite(flat["min_all" if opts["rule"] != "plain" else "values"])
    if not obs.any(axis=1).all():
        raise FormatError(f"Expected every block in {path} to hold an observed voxel, but some hold none")
    dims = space.shape
    if dims is not None and n:
        idx = coords[:, None, :] * bs + local_offsets(B, Bz)[None]
        outside = np.any((idx < 0) | (idx >= np.asarray(dims)), axis=2)
        if np.any(outside & obs) or np.any(coords < 0) or np.any(coords * bs >= np.asarray(dims)):
            raise FormatError(
                f"Expected observed voxels only inside the bounds in {path}, but some lie outside"
            )
    if isinstance(space, SparseSpec):
        kw = {"initial_blocks": max(1, n), **kw}
    m = _made(cls, spec, space, backend, opts, kw)
    src = {"min_all": flat["min_all" if opts["rule"] != "plain" else "values"]}
    if opts["rule"] != "plain":
        src["bright"], src["count"] = flat["bright"], flat["count"]
    st = m.storage
    with st.lock:
        st.put_blocks(coords, src, combine=False)
        layer = None
        if opts["confidence"]:  # host arrays over the grid, from the file's blocks
            layer = st.dense(*st.whole_box(), ("confirmed", "arcs"), blocks=(coords, flat))
        _restore(m, layer, n_integrated, prints)
    return m


def _made(cls, spec, space, backend: str, opts: dict, kw: dict):
    """The empty map a file's options describe, on ``backend`` (``kw``: more :class:`MapperParams`
    fields, e.g. ``max_bytes``, ``evict``; ``device_index``)."""
    kw = dict(kw)
    device_index = kw.pop("device_index", None)
    fields = {k: v for k, v in opts.items() if k != "confidence"}
    return cls(spec, space, backend, MapperParams(**fields, **kw), device_index=device_index)


def _restore(m, layer: dict | None, n_integrated: int, prints) -> None:
    """A loaded map's layer arrays (``layer``: the confidence layer's ``confirmed`` and ``arcs`` over
    the grid, or None: kept in ``m.layer_state`` until such a layer attaches), ping count and ping
    fingerprints."""
    if layer is not None:
        m.layer_state["confidence"] = {k: np.asarray(layer[k]).ravel().copy() for k in ("confirmed", "arcs")}
    m.n_integrated = n_integrated
    m.pings = prints



def load_map(cls, path: str | os.PathLike, backend: str = "auto"):
    """``cls.load(path, backend)`` (``cls``: :class:`gpumap.MinMaxMapper`) for a file that is there
    and says it is a map file (:func:`gpumap.core.merge.load_map`)."""
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"Expected a map file at {p}, but nothing is there")
    fmt = file_format(p)
    if fmt not in (FILE_FORMAT, SPARSE_FILE_FORMAT):
        raise FormatError(f"Expected format {FILE_FORMAT!r} or {SPARSE_FILE_FORMAT!r} in {p}, "
                          f"but got {fmt!r}")
    return cls.load(p, backend=backend)


def file_format(path: Path) -> str:
    """The ``format`` field of a map file's metadata (before anything large is read)."""
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

# Map metadata is a small JSON document; anything larger is not one of ours.
_META_MAX_BYTES = 1 << 20
# deflate's largest expansion is about 1032 : 1; a member that claims more is a bomb.
_DEFLATE_MAX_RATIO = 1100


def _npy_header(zf: zipfile.ZipFile, info: zipfile.ZipInfo, path: Path) -> tuple[tuple, np.dtype]:
    """(shape, dtype) of one .npy member from its header, checked against its sizes."""
    with zf.open(info) as f:
        version = np.lib.format.read_magic(f)
        if version == (1, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_1_0(f)
        elif version in ((2, 0), (3, 0)):
            shape, fortran, dtype = np.lib.format.read_array_header_2_0(f)
        else:
            raise FormatError(f"Expected .npy version 1-3 for {info.filename} in {path}, but got {version}")
        header_bytes = f.tell()
    data_bytes = -1 if dtype.hasobject else int(np.prod(shape, dtype=object)) * dtype.itemsize
    if data_bytes < 0 or fortran or info.file_size != header_bytes + data_bytes:
        raise FormatError(
            f"Expected {info.filename} in {path} to hold its declared {shape} {dtype} array "
            f"({header_bytes + max(data_bytes, 0)} bytes, C order), but the archive says {info.file_size}"
        )
    bomb = info.file_size > _DEFLATE_MAX_RATIO * info.compress_size + 4096
    if info.compress_type != zipfile.ZIP_STORED and bomb:
        raise FormatError(
            f"Expected {info.filename} in {path} to inflate at most {_DEFLATE_MAX_RATIO}:1, but it declares "
            f"{info.file_size} bytes from {info.compress_size}: refused before inflating"
        )
    return tuple(shape), dtype


def _check_meta(meta: object, path: Path) -> tuple[SonarSpec, GridSpec | SparseSpec, dict, int, bool]:
    """The sonar spec, the grid (a GridSpec, or a SparseSpec for a map on demand), the constructor
    options, the ping count of a map file's metadata, and whether it holds dense arrays over the
    grid (versions 1 to 3) rather than blocks."""
    if not isinstance(meta, dict):
        raise FormatError(f"Expected a JSON object as map metadata in {path}, but got {type(meta).__name__}")
    fmt, version = meta.get("format"), meta.get("version")
    if fmt not in (FILE_FORMAT, SPARSE_FILE_FORMAT):
        raise FormatError(f"Expected format {FILE_FORMAT!r} in {path}, but got {fmt!r}")
    if (fmt == FILE_FORMAT and version not in (1, 2, 3, 4, FILE_VERSION)) or (
            fmt == SPARSE_FILE_FORMAT and version != 1):
        raise FormatError(
            f"Expected file version 1 to {FILE_VERSION} in {path} ({fmt}), but got {version!r}"
        )
    sparse_file = fmt == SPARSE_FILE_FORMAT or (
        version in (4, FILE_VERSION) and meta.get("sparse") is not None)
    try:
        spec = SonarSpec.from_dict(meta["spec"])
        space = SparseSpec.from_dict(meta["sparse"]) if sparse_file else GridSpec.from_dict(meta["grid"])
    except (KeyError, TypeError, ValueError, OverflowError, IndexError) as e:
        raise FormatError(
            f"Expected a sonar spec and a grid spec (a sparse spec on demand) in the metadata of {path}, "
            f"but: {e!r}"
        ) from e
    n = meta.get("n_integrated")
    if isinstance(n, bool) or not isinstance(n, int) or n < 0:
        raise FormatError(f"Expected a non-negative integer n_integrated in {path}, but got {n!r}")
    rule = meta.get("rule", "plain")  # version 1 maps are plain min-max
    opts = {
        "method": meta.get("method"),
        "shadow_m": meta.get("shadow_m", 0.0),
        "rule": rule,
        "threshold": meta.get("threshold", 0.1),
        "carve_views": meta.get("carve_views", 2),
        "bright_share": meta.get("bright_share", BRIGHT_SHARE),
        "share_z": meta.get("share_z", SHARE_Z),
        "confidence": meta.get("confidence", False),  # versions 1 and 2 have no confidence layer
    }
    if opts["method"] not in METHODS or rule not in RULES or (sparse_file and opts["method"] != "gather"):
        raise FormatError(
            f"Expected method in {METHODS} ('gather' on demand) and rule in {RULES} in {path}, but got "
            f"{opts['method']!r} and {rule!r}"
        )
    if not isinstance(opts["confidence"], bool) or (sparse_file and opts["confidence"]):
        raise FormatError(f"Expected a bool for confidence (False on demand) in {path}, but got "
                          f"{opts['confidence']!r}")
    for key in ("shadow_m", "threshold"):
        if isinstance(opts[key], bool) or not isinstance(opts[key], (int, float)):
            raise FormatError(f"Expected a number for {key} in {path}, but got {opts[key]!r}")
    cv = opts["carve_views"]
    if isinstance(cv, bool) or not isinstance(cv, int) or not 1 <= cv <= 255:
        raise FormatError(f"Expected carve_views in 1..255 in {path}, but got {cv!r}")
    p, z = opts["bright_share"], opts["share_z"]
    if any(isinstance(x, bool) or not isinstance(x, (int, float)) for x in (p, z)) or not (
            0.0 < p <= 1.0 and 0.0 <= z <= 10.0):
        raise FormatError(f"Expected bright_share in (0, 1] and share_z in [0, 10] in {path}, but got "
                          f"{p!r} and {z!r}")
    if meta.get("decision", "share") != "share":  # the calibrated decision, retired (bench/experiments)
        raise FormatError(f"Expected a map of the share decision in {path}, but it was written with "
                          f"decision={meta.get('decision')!r}, which gpumap no longer reads")
    return spec, space, opts, n, fmt == FILE_FORMAT and version not in (4, FILE_VERSION)


def _check_map_values(arrays: dict[str, np.ndarray], opts: dict, path: Path) -> None:
    """Values a map can hold: finite in [0, 1] or +inf; the visible rule's state consistent."""
    for name in ("values", "min_all", "bright"):
        if name not in arrays:
            continue
        a = arrays[name]
        fin = np.isfinite(a)
        bad = ~(fin | (a == np.inf)) | (fin & ((a < 0) | (a > 1)))
        if bad.any():
            i = np.unravel_index(int(np.argmax(bad)), a.shape)
            raise FormatError(
                f"Expected '{name}' in [0, 1] or +inf (never observed) in {path}, but got {a[i]} at "
                f"{tuple(int(x) for x in i)} and {int(bad.sum()) - 1} more"
            )
    if "confirmed" in arrays and np.any(arrays["confirmed"] > 1):
        raise FormatError(f"Expected 'confirmed' flags of 0 or 1 in {path}, but some are larger")
    if "arcs" in arrays and np.any(arrays["arcs"] >= 1 << 13):
        raise FormatError(f"Expected 13-bit 'arcs' masks in {path}, but some have higher bits")
    if opts["rule"] != "plain":
        unseen = np.isinf(arrays["min_all"])
        if np.any(unseen & (np.isfinite(arrays["bright"]) | (arrays["count"] > 0))):
            raise FormatError(f"Expected no evidence on never-observed voxels in {path}, but some have it")
        want = rule_values(opts["rule"], arrays["min_all"], arrays["bright"], arrays["count"],
                           opts["carve_views"], opts["bright_share"], opts["share_z"])
        if not np.array_equal(want, arrays["values"]):
            raise FormatError(f"Expected 'values' in {path} to follow from its state, but they disagree")
