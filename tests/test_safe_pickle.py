"""The restricted unpickler of the public datasets' pickles (gpumap.io.safe_pickle, issue 45).

Hostile pickles at every protocol (0-5) name globals that would run code or touch the file
system: each must be refused with a one-line FormatError naming the global, and the marker
file its payload would create must never appear; the same bytes through ``pickle.loads``
do create it (so the payloads are live, and the test can fail). What the datasets hold
(containers, numeric arrays, dtypes, scalars) must come back equal, at every protocol. A
hypothesis fuzz of truncated and mutated pickles must end in a value of those types or in
FormatError, never another exception.
"""

from __future__ import annotations

import builtins
import os
import pickle
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import gpumap.io.safe_pickle as sp
from gpumap.io import FormatError, LimitError, load_pickle

PROTOCOLS = range(pickle.HIGHEST_PROTOCOL + 1)
_MARKER: list[str] = []  # where _EvilArray's state writes, set by the test that uses it


class _Reduce:
    """Pickles as ``fn(*args)``: a hostile pickle's way to call a global."""

    def __init__(self, fn, args):
        self.fn, self.args = fn, args

    def __reduce__(self):
        return (self.fn, self.args)


class _EvilArray(np.ndarray):
    """An ndarray subclass whose unpickling runs code (NumPy pickles arrays as their own class)."""

    def __setstate__(self, state):
        Path(_MARKER[0]).touch()
        super().__setstate__(state)


class _EvilDict(dict):
    """A dict subclass whose unpickling runs code (its items, or its attributes' state)."""

    def __setitem__(self, k, v):
        Path(_MARKER[0]).touch()
        super().__setitem__(k, v)

    def __setstate__(self, state):
        Path(_MARKER[0]).touch()


def _evil_dict() -> _EvilDict:
    d = _EvilDict(a=1)
    d.x = 1  # protocols 0-1 rebuild a dict subclass with copyreg._reconstructor, then its state
    return d


def _hostile(marker: Path) -> dict[str, tuple[object, str | tuple[str, ...]]]:
    """name -> (object whose pickle runs a payload creating ``marker``, the global it names)."""
    cmd = f"touch {marker}"
    code = f"open({str(marker)!r}, 'w')"
    return {
        "os.system": (_Reduce(os.system, (cmd,)), "posix.system"),
        "builtins.eval": (_Reduce(builtins.eval, (code,)), ("builtins.eval", "__builtin__.eval")),
        "builtins.exec": (_Reduce(builtins.exec, (code,)), ("builtins.exec", "__builtin__.exec")),
        "builtins.open": (_Reduce(builtins.open, (str(marker), "w")), "io.open"),
        "numpy.memmap": (_Reduce(np.memmap, (str(marker), np.uint8, "w+", 0, (1,))), "numpy.memmap"),
        "ndarray subclass": (np.zeros(3).view(_EvilArray), "_EvilArray"),
        "dict subclass": (_evil_dict(), ("_EvilDict", "copy_reg._reconstructor")),
        "nested in data": ({"ImagingSonar": np.zeros((2, 2)), "PoseSensor": _Reduce(os.system, (cmd,))},
                           "posix.system"),
    }


@pytest.mark.parametrize("protocol", PROTOCOLS)
@pytest.mark.parametrize("name", sorted(_hostile(Path("x"))))
def test_hostile_pickles_are_refused_naming_the_global_and_nothing_runs(tmp_path, name, protocol):
    marker = tmp_path / "ran"
    _MARKER[:] = [str(marker)]
    obj, names = _hostile(marker)[name]
    data = pickle.dumps(obj, protocol=protocol)
    with pytest.raises(FormatError) as e:
        load_pickle(data)
    msg = str(e.value)
    assert "\n" not in msg and any(n in msg for n in ((names,) if isinstance(names, str) else names)), msg
    assert "refused, not run" in msg and not marker.exists()
    f = tmp_path / "evil.pkl"
    f.write_bytes(data)
    with pytest.raises(FormatError):
        load_pickle(f)
    assert not marker.exists()
    try:  # the control: the stock unpickler runs the payload
        pickle.loads(data)
    except Exception:
        pass
    assert marker.exists(), "the payload is not live: this case proves nothing"


def _text(s: str) -> bytes:
    """SHORT_BINUNICODE ``s``."""
    return b"\x8c" + bytes([len(s.encode())]) + s.encode()


# hand-made opcode streams: tricks that no pickler writes
_CRAFTED = {
    # getattr(__import__('os'), 'system')('echo') in protocol 0 text
    "getattr chain": (b"cbuiltins\ngetattr\n(cbuiltins\n__import__\n(Vos\ntRVsystem\ntR(Vecho\ntR.",
                      "builtins.getattr"),
    "dotted name": (b"\x80\x04" + _text("numpy") + _text("ndarray.__subclasses__") + b"\x93)R.",
                    "numpy.ndarray.__subclasses__"),
    "copyreg": (b"\x80\x02ccopyreg\n_reconstructor\n.", "copyreg._reconstructor"),
    "NEWOBJ of ndarray": (b"\x80\x02cnumpy\nndarray\nJ\x00\xe1\xf5\x05\x85\x85\x81.", "NEWOBJ"),
    "ndarray called": (b"\x80\x02cnumpy\nndarray\nJ\x00\xe1\xf5\x05\x85R.", "calls numpy.ndarray"),
    "BUILD on a dict": (b"\x80\x02}}b.", "BUILD"),
    "reconstruct a dtype": (b"\x80\x02cnumpy.core.multiarray\n_reconstruct\ncnumpy\ndtype\n"
                            b"K\x00\x85C\x01b\x87R.", "_reconstruct"),
    # a float dtype whose state sets NPY_ITEM_HASOBJECT: its array's bytes would be read as pointers
    "dtype flags": (pickle.dumps(np.zeros(2)).replace(b"J\xff\xff\xff\xffJ\xff\xff\xff\xffK\x00t",
                                                      b"J\xff\xff\xff\xffJ\xff\xff\xff\xffK\x01t"),
                    "sets a dtype's state to (3, '<', None, None, None, -1, -1, 1)"),
    "persistent id": (b"\x80\x02K\x01Q.", "BINPERSID"),
    "object dtype": (pickle.dumps(np.array([1, "a"], dtype=object)), "dtype('O"),
    "structured dtype": (pickle.dumps(np.zeros(2, dtype=[("a", "f4")])), "numpy.dtype('V4'"),
    "string array": (pickle.dumps(np.array(["ab"])), "numpy.dtype('U2'"),
    "codec": (b"c_codecs\nencode\n(Vx\nVzlib\ntR.", "_codecs.encode(..., 'zlib')"),
}


@pytest.mark.parametrize("name", sorted(_CRAFTED))
def test_crafted_tricks_are_refused_in_one_line(name):
    data, says = _CRAFTED[name]
    with pytest.raises(FormatError) as e:
        load_pickle(data)
    msg = str(e.value)
    assert "\n" not in msg and says in msg, msg


def _dataset_objects() -> dict[str, object]:
    rng = np.random.default_rng(7)
    return {
        "holoocean": {"ImagingSonar": rng.integers(0, 255, (8, 6)).astype(np.uint8),
                      "PoseSensor": np.eye(4, dtype=np.float32), "t": 1.25},
        "oasis": [np.eye(4).tolist(), [[0.5, -0.25, 0, 1], [0, 1, 0, 2], [1, 0, 0, 3], [0, 0, 0, 1]]],
        "arrays": {"f8": rng.normal(size=(3, 2)), "fortran": np.asfortranarray(rng.normal(size=(2, 3))),
                   "be": np.arange(4, dtype=">i4"), "c16": np.array([1 + 2j]), "b": np.array([True, False]),
                   "u2": np.arange(5, dtype=np.uint16), "empty": np.zeros((0, 3)), "scalar": np.float32(2.5),
                   "i8": np.int64(-3), "bool": np.bool_(True)},
        "plain": [None, True, 3, 2.5, "text", b"raw", b"", bytearray(b"ba"), (1, (2,)), {1, 2},
                  frozenset({"a"}), {"k": [1.0]}],
    }


def _same(a: object, b: object) -> bool:
    if isinstance(a, np.ndarray):
        return (type(b) is np.ndarray and a.shape == b.shape and a.dtype.newbyteorder("=") ==
                b.dtype.newbyteorder("=") and np.array_equal(a, b) and b.flags.writeable)
    if isinstance(a, np.generic):
        return type(a) is type(b) and a == b
    if isinstance(a, dict):
        return type(b) is dict and a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)):
        return type(a) is type(b) and len(a) == len(b) and all(map(_same, a, b))
    return type(a) is type(b) and a == b


@pytest.mark.parametrize("protocol", PROTOCOLS)
@pytest.mark.parametrize("name", sorted(_dataset_objects()))
def test_what_the_datasets_hold_comes_back_equal(name, protocol):
    obj = _dataset_objects()[name]
    assert _same(obj, load_pickle(pickle.dumps(obj, protocol=protocol)))


def test_numpy_1x_names_and_python_2_text_are_read():
    # the AONeuS frames name numpy.core.multiarray (NumPy 1.x); NumPy 2 writes numpy._core
    data = pickle.dumps({"a": np.arange(3.0)}, protocol=2).replace(b"numpy._core", b"numpy.core")
    assert b"numpy.core.multiarray" in data
    np.testing.assert_array_equal(load_pickle(data)["a"], np.arange(3.0))
    # a Python 2 pickle: SHORT_BINSTRING data read as latin-1, the __builtin__ module name
    py2 = (b"\x80\x02cnumpy.core.multiarray\n_reconstruct\ncnumpy\nndarray\nK\x00\x85U\x01b\x87R"
           b"(K\x01K\x02\x85cnumpy\ndtype\nU\x02u1K\x00K\x01\x87R(K\x03U\x01|NNNJ\xff\xff\xff\xffJ\xff"
           b"\xff\xff\xffK\x00tb\x89U\x02\x07\xfftb.")
    np.testing.assert_array_equal(load_pickle(py2), np.array([7, 255], np.uint8))
    assert load_pickle(b"c__builtin__\nset\n(]K\x01atR.") == {1}


def test_budgets_refuse_before_building_and_a_far_memo_index_costs_nothing(monkeypatch, tmp_path):
    big = pickle.dumps(list(range(1000)), protocol=4)
    monkeypatch.setattr(sp, "MAX_PICKLE_BYTES", 100)
    with pytest.raises(LimitError, match="at most 100 bytes"):
        load_pickle(big)
    monkeypatch.setattr(sp, "MAX_PICKLE_BYTES", 1 << 20)
    monkeypatch.setattr(sp, "MAX_PICKLE_OPCODES", 500)
    with pytest.raises(LimitError, match="at most 500 opcodes"):
        load_pickle(big)
    # LONG_BINPUT at index 2^31 - 1: the C unpickler would grow its memo array to 16 GiB
    assert load_pickle(b"\x80\x04Nr\xff\xff\xff\x7f.") is None
    with pytest.raises(FileNotFoundError):
        load_pickle(tmp_path / "none.pkl")


_SEEDS = [pickle.dumps(o, protocol=p) for o in _dataset_objects().values() for p in PROTOCOLS]
_ALLOWED = (type(None), bool, int, float, complex, str, bytes, bytearray, list, tuple, set, frozenset, dict)


def _only_allowed(x: object) -> None:
    seen, todo = set(), [x]
    while todo:
        y = todo.pop()
        if id(y) in seen:
            continue
        seen.add(id(y))
        if type(y) is np.ndarray or isinstance(y, np.generic):
            assert y.dtype.kind in "biufc" and not y.dtype.hasobject
        else:
            assert type(y) in _ALLOWED, type(y)
            if isinstance(y, dict):
                todo += [*y.keys(), *y.values()]
            elif isinstance(y, (list, tuple, set, frozenset)):
                todo += list(y)


@st.composite
def _mutated(draw) -> bytes:
    data = bytearray(draw(st.sampled_from(_SEEDS)))
    for _ in range(draw(st.integers(1, 4))):
        op = draw(st.sampled_from(["truncate", "flip", "insert", "delete", "byte"]))
        i = draw(st.integers(0, max(len(data) - 1, 0)))
        if op == "truncate":
            del data[i:]
        elif op == "flip" and data:
            data[i] ^= 1 << draw(st.integers(0, 7))
        elif op == "byte" and data:
            data[i] = draw(st.integers(0, 255))
        elif op == "insert":
            data[i:i] = draw(st.binary(min_size=1, max_size=8))
        elif op == "delete":
            del data[i:i + draw(st.integers(1, 8))]
    return bytes(data)


@settings(max_examples=600, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.too_slow])
@given(_mutated())
def test_fuzz_truncated_and_mutated_pickles_give_values_or_format_error(data):
    try:
        out = load_pickle(data)
    except FormatError as e:
        assert "\n" not in str(e)
        return
    _only_allowed(out)
