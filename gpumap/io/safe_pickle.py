"""Read the pickles that public sonar datasets ship, without running them.

Two public layouts keep their data in Python pickles: the OASIS tank run's ``son_poses.pkl``
(a list of 4 x 4 nested lists of floats) and HoloOcean recordings' ``Data/NNN.pkl`` (a dict of
NumPy arrays: the polar image and a 4 x 4 pose). A pickle is a program: ``pickle.load`` calls
whatever globals the file names, so a hostile file runs code the moment it is opened.
:func:`load_pickle` reads only what those files hold and refuses everything else, *before*
calling it.

What is accepted
----------------
- Containers and plain values built by the pickle machine itself: ``dict``, ``list``,
  ``tuple``, ``set``, ``frozenset``, ``str``, ``bytes``, ``bytearray``, ``int``, ``float``,
  ``bool``, ``None``.
- NumPy arrays, dtypes and scalars of boolean, integer, float or complex type, through the
  few globals NumPy's own pickles name (``numpy.core``/``numpy._core`` ``multiarray._reconstruct``,
  ``multiarray.scalar``, ``numeric._frombuffer``, ``numpy.ndarray``, ``numpy.dtype``) and the
  helpers the protocols 0-2 use for bytes and sets (``_codecs.encode`` with ``latin1`` only,
  ``builtins.bytes/bytearray/set/frozenset``). Each is replaced by a checking stand-in: the
  real ``numpy.ndarray`` class is never handed to the file (so it cannot be instantiated
  with a chosen shape), a dtype must be a plain ``b``/``i``/``u``/``f``/``c`` type (no
  object, structured, string or datetime dtypes), an array's state must match its bytes.

What is refused
---------------
Any other global (``os.system``, ``builtins.eval``, ``builtins.getattr``, ``numpy.memmap``,
``copyreg._reconstructor``, a dotted name such as ``numpy.ndarray.__subclasses__`` ...), the
object-building opcodes (``INST``, ``OBJ``, ``NEWOBJ``, ``NEWOBJ_EX``), persistent ids,
out-of-band buffers, and ``BUILD`` on anything but an array or a dtype: one-line
:class:`~gpumap.errors.FormatError` that names the global or opcode, raised when the file
asks for it, so nothing it names is ever called. A truncated or corrupt pickle is a
:class:`~gpumap.errors.FormatError` too, never another exception.

Budgets: a file of at most :data:`MAX_PICKLE_BYTES` and :data:`MAX_PICKLE_OPCODES` opcodes
(counted by a first pass that builds nothing), so what a small file can make the loader
allocate stays small. The loader is the pure-Python unpickler of the standard library
(``pickle._Unpickler``, whose memo is a dict: the C unpickler grows a memo array to any index
a file names, gigabytes for a few bytes).
"""

from __future__ import annotations

import io
import os
import pickle
import pickletools
import re
from typing import Any

import numpy as np

from gpumap.errors import FormatError, LimitError
from gpumap.limits import check_size

__all__ = ["MAX_PICKLE_BYTES", "MAX_PICKLE_OPCODES", "load_pickle"]

MAX_PICKLE_BYTES = 16 << 20
"""16 MiB: the largest pickle read (a HoloOcean frame of a 1024 x 1024 float32 image is 4 MiB;
the OASIS tank's 1,223 poses are 166 kB). Budgets are module constants, read at call time."""

MAX_PICKLE_OPCODES = 1_000_000
"""The most opcodes a pickle may hold; bounds the objects it builds and the time it takes. The
OASIS poses take 38,000 (31 a pose as nested lists: 1 M is 32,000 poses; an array of poses takes
a handful); the worst file within it (a million empty lists, 1 MB) costs about 2.6 s of CPU and
175 MB (measured on the shared 2-core machine)."""

_WHAT = "only containers and NumPy arrays, dtypes and scalars"
# dtype strings NumPy's pickles use for the plain numeric types (byte order comes in the state)
_DTYPE_STR = re.compile(r"[<>|=]?(?:b1|\?|[iu][1248]|f[248]|c(?:8|16))")
_KINDS = "biufc"


class _Token:
    """Stands in for ``numpy.ndarray`` in a pickle: known to the array rebuild, callable by nothing."""

    __slots__ = ()

    def __repr__(self) -> str:
        return "numpy.ndarray"

    def __call__(self, *args: object, **kwargs: object) -> None:
        raise _refuse(f"it calls numpy.ndarray with {len(args)} arguments")


_NDARRAY = _Token()


def _refuse(message: str) -> FormatError:
    return FormatError(f"expected {_WHAT} in the pickle, but {message} (refused, not run)")


def _check_dtype(dt: object) -> np.dtype:
    if not isinstance(dt, np.dtype) or dt.kind not in _KINDS or dt.fields is not None \
            or dt.subdtype is not None or dt.hasobject:
        raise _refuse(f"it holds the dtype {dt!r}")
    return dt


def _dtype(obj: object, align: object = False, copy: object = True) -> np.dtype:
    # Python 3 pickles pass (spec, False, True), Python 2 ones (spec, 0, 1)
    if not isinstance(obj, str) or not _DTYPE_STR.fullmatch(obj) or type(align) not in (bool, int) or align:
        raise _refuse(f"it asks for numpy.dtype({obj!r}, align={align!r})")
    # a copy, as NumPy's own unpickling makes: BUILD then sets its byte order, and np.dtype('f4')
    # without copy is the shared instance every float32 array uses
    return _check_dtype(np.dtype(obj, align=False, copy=True))


def _shape(shape: object) -> tuple[int, ...]:
    if not isinstance(shape, tuple) or len(shape) > 32 or not all(
            type(n) is int and n >= 0 for n in shape):
        raise _refuse(f"it gives the array shape {shape!r}")
    return shape


def _nbytes(shape: tuple[int, ...], dt: np.dtype) -> int:
    n = dt.itemsize
    for k in shape:
        n *= k
    return n


def _reconstruct(cls: object, shape: object, typecode: object) -> np.ndarray:
    # NumPy pickles an array as _reconstruct(ndarray, (0,), b'b') and then BUILDs its state
    if cls is not _NDARRAY or shape != (0,) or typecode not in (b"b", "b"):
        raise _refuse(f"it rebuilds an array as _reconstruct({cls!r}, {shape!r}, {typecode!r})")
    return np.ndarray((0,), np.uint8)


def _scalar(dt: object, data: object) -> np.generic:
    dt = _check_dtype(dt)
    if isinstance(data, str):  # a Python 2 pickle read as latin-1 text
        data = data.encode("latin-1")
    if not isinstance(data, bytes) or len(data) != dt.itemsize:
        raise _refuse(f"it gives a {dt} scalar {type(data).__name__} data instead of {dt.itemsize} bytes")
    return np.frombuffer(data, dtype=dt)[0].copy()


def _frombuffer(buf: object, dt: object, shape: object, order: object) -> np.ndarray:
    dt = _check_dtype(dt)
    shp = _shape(shape)
    if isinstance(buf, pickle.PickleBuffer):
        buf = bytes(buf.raw())
    if not isinstance(buf, (bytes, bytearray)) or order not in ("C", "F"):
        raise _refuse(f"it rebuilds an array from a {type(buf).__name__} in order {order!r}")
    if len(buf) != _nbytes(shp, dt):
        raise FormatError(f"expected {_nbytes(shp, dt)} bytes for a {dt} array of shape {shp} in the "
                          f"pickle, but it holds {len(buf)}")
    return np.frombuffer(bytes(buf), dtype=dt).reshape(shp, order=order).copy(order="K")


def _encode(obj: object, encoding: object = "utf-8", errors: object = "strict") -> bytes:
    # protocols 0-2 store bytes as _codecs.encode(text, 'latin1')
    if not isinstance(obj, str) or encoding not in ("latin1", "latin-1") or errors != "strict":
        raise _refuse(f"it asks for _codecs.encode(..., {encoding!r})")
    return obj.encode("latin-1")


def _bytes(*args: object) -> bytes:
    if args:
        raise _refuse(f"it asks for bytes() of {len(args)} arguments")
    return b""


def _bytearray(*args: object) -> bytearray:
    if len(args) > 1 or (args and not isinstance(args[0], bytes)):
        raise _refuse("it asks for bytearray() of something other than bytes")
    return bytearray(*args)


def _items(what: str, args: tuple) -> list:
    if len(args) > 1 or (args and type(args[0]) not in (list, tuple)):
        raise _refuse(f"it asks for {what}() of something other than a list")
    return list(args[0]) if args else []


def _set(*args: object) -> set:
    return set(_items("set", args))


def _frozenset(*args: object) -> frozenset:
    return frozenset(_items("frozenset", args))


_GLOBALS: dict[tuple[str, str], object] = {("numpy", "ndarray"): _NDARRAY, ("numpy", "dtype"): _dtype,
                                           ("_codecs", "encode"): _encode, ("builtins", "bytes"): _bytes,
                                           ("builtins", "bytearray"): _bytearray, ("builtins", "set"): _set,
                                           ("builtins", "frozenset"): _frozenset}
for _core in ("numpy.core", "numpy._core"):
    _GLOBALS[(f"{_core}.multiarray", "_reconstruct")] = _reconstruct
    _GLOBALS[(f"{_core}.multiarray", "scalar")] = _scalar
    _GLOBALS[(f"{_core}.numeric", "_frombuffer")] = _frombuffer


def _build_array(a: np.ndarray, state: object) -> None:
    # ndarray state: (version, shape, dtype, is_fortran, raw bytes); version-less (shape, ...) is older
    if not isinstance(state, tuple) or len(state) not in (4, 5):
        raise _refuse(f"it sets an array's state to a {type(state).__name__}")
    shape, dt, fortran, raw = state[-4:]
    shp, dt = _shape(shape), _check_dtype(dt)
    if isinstance(raw, str):  # a Python 2 pickle read as latin-1 text
        raw = raw.encode("latin-1")
        state = (*state[:-1], raw)
    if type(fortran) not in (bool, int) or fortran not in (0, 1) or not isinstance(raw, (bytes, bytearray)):
        raise _refuse("it sets an array's data to something other than bytes")
    if len(raw) != _nbytes(shp, dt):
        raise FormatError(f"expected {_nbytes(shp, dt)} bytes for a {dt} array of shape {shp} in the "
                          f"pickle, but it holds {len(raw)}")
    a.__setstate__(state)


def _build_dtype(dt: np.dtype, state: object) -> None:
    # dtype state: (3, byte order, subarray, names, fields, itemsize, alignment, flags); a plain
    # numeric dtype has no subarray, names or fields, and -1, -1, 0 for the rest. Anything else is
    # refused before NumPy sees it: the flags alone can mark a float dtype as holding objects
    # (NPY_ITEM_HASOBJECT), and the raw bytes of an array of it would be read as pointers.
    if not isinstance(state, tuple) or len(state) != 8 or state[0] != 3 or not isinstance(state[1], str) \
            or state[1] not in ("<", ">", "|", "=") or state[2:] != (None, None, None, -1, -1, 0) \
            or any(type(v) is not int for v in (state[0], *state[5:])):
        raise _refuse(f"it sets a dtype's state to {state!r}"[:200])
    dt.__setstate__(state)
    _check_dtype(dt)


def _load_build(self: _SafeUnpickler) -> None:
    state = self.stack.pop()
    inst = self.stack[-1]
    if type(inst) is np.ndarray:
        _build_array(inst, state)
    elif isinstance(inst, np.dtype):
        _build_dtype(inst, state)
    else:
        raise _refuse(f"it sets the state of a {type(inst).__name__} (BUILD)")


def _refuse_opcode(name: str):
    def load(self: _SafeUnpickler) -> None:
        raise _refuse(f"it builds an object with the opcode {name}")

    return load


_DISPATCH = dict(pickle._Unpickler.dispatch)
_DISPATCH[pickle.BUILD[0]] = _load_build
for _op in ("INST", "OBJ", "NEWOBJ", "NEWOBJ_EX", "PERSID", "BINPERSID", "NEXT_BUFFER", "READONLY_BUFFER"):
    _DISPATCH[getattr(pickle, _op)[0]] = _refuse_opcode(_op)


class _SafeUnpickler(pickle._Unpickler):  # the pure-Python unpickler: its memo is a dict
    dispatch = _DISPATCH

    def find_class(self, module: str, name: str) -> object:
        # never imports: only the stand-ins above, by exact (module, name)
        key = ("builtins" if module == "__builtin__" else module, name)
        if key not in _GLOBALS:
            raise _refuse(f"it asks for the global {module}.{name}"[:300])
        return _GLOBALS[key]


_SCALARS = (type(None), bool, int, float, complex, str, bytes, bytearray)


def _check_tree(root: object) -> None:
    """Every object reachable from ``root`` is a container, plain value or checked NumPy object."""
    seen: set[int] = set()
    todo = [root]
    while todo:
        x = todo.pop()
        if id(x) in seen:
            continue
        seen.add(id(x))
        t = type(x)
        if t in _SCALARS:
            continue
        if t in (list, tuple, set, frozenset):
            todo.extend(x)
        elif t is dict:
            todo.extend(x.keys())
            todo.extend(x.values())
        elif t is np.ndarray:
            _check_dtype(x.dtype)
        elif isinstance(x, np.generic) and type(x) is np.dtype(t).type:
            _check_dtype(x.dtype)
        elif isinstance(x, np.dtype):
            _check_dtype(x)
        else:
            raise _refuse(f"it holds a {t.__module__}.{t.__qualname__}")


def _one_line(e: BaseException) -> str:
    text = " ".join(str(e).split())
    return f"{type(e).__name__}: {text[:200]}" if text else type(e).__name__


def load_pickle(source: str | os.PathLike | bytes, *, path: str | None = None) -> Any:
    """Unpickle a file of containers and NumPy arrays without running anything it names.

    Parameters
    ----------
    source : path-like or bytes
        The pickle file, or its bytes.
    path : str, optional
        Name for error messages when ``source`` is bytes.

    Returns
    -------
    object
        What the pickle holds: nested ``dict``/``list``/``tuple``/``set`` of plain values and
        NumPy arrays (each a fresh, writable ``numpy.ndarray`` of a numeric dtype), dtypes
        and scalars.

    Raises
    ------
    FormatError
        Naming the global or opcode refused (before it is called), or saying how the bytes
        are corrupt or truncated; one line.
    LimitError
        If the file is larger than :data:`MAX_PICKLE_BYTES` or holds more than
        :data:`MAX_PICKLE_OPCODES` opcodes.
    FileNotFoundError
        If the file does not exist.
    """
    name = path if path is not None else (None if isinstance(source, (bytes, bytearray))
                                          else os.fspath(source))
    if isinstance(source, (bytes, bytearray)):
        data = bytes(source)
        check_size(len(data), MAX_PICKLE_BYTES, "the pickle", path=name)
    else:
        with open(source, "rb") as f:
            check_size(os.fstat(f.fileno()).st_size, MAX_PICKLE_BYTES, "the pickle", path=name)
            data = f.read(MAX_PICKLE_BYTES + 1)
        check_size(len(data), MAX_PICKLE_BYTES, "the pickle", path=name)  # it grew meanwhile
    try:
        n_ops = 0
        for _op, _arg, _pos in pickletools.genops(data):  # structure only: builds nothing
            n_ops += 1
            if n_ops > MAX_PICKLE_OPCODES:
                raise LimitError(f"expected a pickle of at most {MAX_PICKLE_OPCODES:,} opcodes "
                                 "(gpumap.io.safe_pickle.MAX_PICKLE_OPCODES), but it holds more",
                                 _pos, name)
        obj = _SafeUnpickler(io.BytesIO(data), fix_imports=False, encoding="latin1").load()
        _check_tree(obj)
    except FormatError as e:
        if e.path is None and name is not None:
            raise type(e)(e.message, e.offset, name) from None
        raise
    except Exception as e:  # the pickle machine's errors on corrupt bytes come in many types
        raise FormatError(f"expected a complete pickle of {_WHAT}, but it is corrupt or truncated "
                          f"({_one_line(e)})", None, name) from None
    return obj
