"""What every ``gpumap`` subcommand shares (the commands themselves: :mod:`gpumap.commands`):

- :class:`ArgumentParser` (argparse with one-line errors, exit status 2) and the ``type=``
  validators (:func:`positive_float`, :func:`unit_interval`, :func:`output_dir`, ...), so
  that every flag is checked before any work starts;
- :func:`user_errors` and :func:`error_line`: gpumap's own errors and bad input become one
  line on stderr and exit status 2; anything else keeps its traceback;
- the option groups several commands carry (the live view: :func:`add_view_args`).

A command's outputs are written as one set by :func:`gpumap.atomic.output_set`.
"""

from __future__ import annotations

import argparse
import importlib.util
import math
import os
from collections.abc import Callable
from pathlib import Path
from typing import NoReturn

__all__ = [
    "ArgumentParser",
    "add_view_args",
    "backend_name",
    "check_view_args",
    "error_line",
    "existing_file",
    "frame_range",
    "grid_box",
    "memory_size",
    "nonnegative_float",
    "nonnegative_int",
    "one_line",
    "output_dir",
    "output_file",
    "parser_error",
    "positive_float",
    "positive_int",
    "probability",
    "refuse_without",
    "threshold_or_auto",
    "unit_interval",
    "user_errors",
    "vfov_deg",
]



# ------------------------------------------------------------------------------ parsing
#: Help lines of the options several subcommands share (one wording everywhere).
BACKEND_HELP = ("where to map: auto (the fastest here, named in the output), numpy, warp-cpu, warp-cuda, "
                "opencl, opencl-gpu or opencl-cpu (see gpumap info)")
METHOD_HELP = ("gather (every voxel in the field of view, the default) or template (the paper's voxel "
               "template; leaves holes, plain rule only)")

def one_line(text: str) -> str:
    return " ".join(str(text).split())


class ArgumentParser(argparse.ArgumentParser):
    """``argparse.ArgumentParser`` whose errors are one line: ``prog: error: message``, exit 2.

    Abbreviated long options are refused (``allow_abbrev=False``): a flag is spelt in full
    or it is unknown.
    """

    def __init__(self, *args, **kwargs) -> None:
        kwargs.setdefault("allow_abbrev", False)
        super().__init__(*args, **kwargs)

    def error(self, message: str) -> NoReturn:
        parser_error(self, message)


def parser_error(parser: argparse.ArgumentParser, message: str) -> NoReturn:
    parser.exit(2, f"{parser.prog}: error: {one_line(message)} (see {parser.prog} --help)\n")


def refuse_without(parser: argparse.ArgumentParser, needed: str, present: bool,
                   given: dict[str, bool]) -> None:
    """Exit 2 (one line) for the first flag of ``given`` that is on while ``needed`` is absent: a
    flag that only works with another is never silently ignored."""
    if present:
        return
    for flag, on in given.items():
        if on:
            parser.error(f"argument {flag}: Expected {needed} with it, but {needed} is missing")


def _number(text: str) -> float:
    try:
        v = float(text)
    except (TypeError, ValueError):
        raise argparse.ArgumentTypeError(f"Expected a number, but got {text!r}") from None
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"Expected a finite number, but got {text!r}")
    return v


def _whole(text: str) -> int:
    try:
        return int(text)
    except (TypeError, ValueError):
        raise argparse.ArgumentTypeError(f"Expected a whole number, but got {text!r}") from None


def _bounded(name: str, parse: Callable[[str], float], ok: Callable[[float], bool], want: str, doc: str):
    """A ``type=`` validator named ``name``: ``parse`` the text, then refuse values ``ok`` rejects,
    saying ``want``."""

    def check(text: str):
        v = parse(text)
        if not ok(v):
            raise argparse.ArgumentTypeError(f"Expected {want}, but got {text!r}")
        return v

    check.__name__ = check.__qualname__ = name
    check.__doc__ = doc
    return check


positive_float = _bounded("positive_float", _number, lambda v: v > 0, "a number > 0",
                          "A finite number > 0 (``--voxel-size``).")
nonnegative_float = _bounded("nonnegative_float", _number, lambda v: v >= 0, "a number >= 0",
                             "A finite number >= 0 (``--pose-noise``, ``--shadow-m``).")
unit_interval = _bounded("unit_interval", _number, lambda v: 0.0 < v <= 1.0, "a number in (0, 1]",
                         "A number in (0, 1] (an occupied threshold).")
probability = _bounded("probability", _number, lambda v: 0.0 <= v <= 1.0, "a number in [0, 1]",
                       "A number in [0, 1].")
positive_int = _bounded("positive_int", _whole, lambda v: v >= 1, "a whole number >= 1",
                        "A whole number >= 1 (``--stride``, ``--pings``, ``--max-frames``).")
nonnegative_int = _bounded("nonnegative_int", _whole, lambda v: v >= 0, "a whole number >= 0",
                           "A whole number >= 0 (``--seed``).")


def threshold_or_auto(text: str) -> float | str:
    """``'auto'`` or a number in (0, 1] (``gpumap replay --threshold``)."""
    if text.strip().lower() == "auto":
        return "auto"
    try:
        return unit_interval(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(
            f"Expected a number in (0, 1] or 'auto', but got {text!r}"
        ) from None


def vfov_deg(text: str) -> float:
    """A vertical aperture in degrees, in (0, 180)."""
    v = _number(text)
    if not 0.0 < v < 180.0:
        raise argparse.ArgumentTypeError(f"Expected degrees in (0, 180), but got {text!r}")
    return v


def grid_box(text: str) -> tuple[float, ...] | None:
    """``'auto'`` (None) or ``xmin,ymin,zmin,xmax,ymax,zmax`` in metres, min < max per axis."""
    if text.strip().lower() == "auto":
        return None
    want = "'auto' or six numbers xmin,ymin,zmin,xmax,ymax,zmax"
    try:
        v = tuple(float(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"Expected {want}, but got {text!r}") from None
    if len(v) != 6 or not all(math.isfinite(x) for x in v):
        raise argparse.ArgumentTypeError(f"Expected {want} (finite), but got {text!r}")
    if any(v[i + 3] <= v[i] for i in range(3)):
        raise argparse.ArgumentTypeError(f"Expected min < max on every axis, but got {text!r}")
    return v


def backend_name(text: str) -> str:
    """``'auto'`` or a backend name of :mod:`gpumap.backends` (whether it runs here is checked later)."""
    from gpumap.backends import BACKENDS

    if text == "auto" or text in BACKENDS:
        return text
    raise argparse.ArgumentTypeError(
        f"Expected 'auto' or one of {', '.join(BACKENDS)}, but got {text!r}"
    )


def _writable_ancestor(p: Path) -> None:
    """Raise unless the nearest existing ancestor of ``p`` is a folder this process can write in."""
    q = p.absolute()
    while not q.exists() and not q.is_symlink() and q != q.parent:
        q = q.parent
    if not q.is_dir():
        raise argparse.ArgumentTypeError(f"Expected a path under a folder, but {str(q)!r} is a file")
    if not os.access(q, os.W_OK | os.X_OK):
        raise argparse.ArgumentTypeError(f"Expected a folder this user can write in, but got {str(q)!r}")


def output_dir(text: str) -> Path:
    """An output folder: an existing one, or one that can be created (never an existing file)."""
    if not text:
        raise argparse.ArgumentTypeError("Expected a folder, but got ''")
    p = Path(text)
    if (p.exists() or p.is_symlink()) and not p.is_dir():
        raise argparse.ArgumentTypeError(f"Expected a folder, but {text!r} is a file")
    _writable_ancestor(p)
    return p


def output_file(text: str) -> Path:
    """A file to write: not an existing folder, under a folder that exists or can be created."""
    if not text:
        raise argparse.ArgumentTypeError("Expected a file name, but got ''")
    p = Path(text)
    if p.is_dir():
        raise argparse.ArgumentTypeError(f"Expected a file, but {text!r} is a folder")
    _writable_ancestor(p.parent)  # an existing file is replaced: what counts is its folder
    return p


def existing_file(text: str) -> Path:
    """A file that exists and can be read."""
    p = Path(text)
    if not p.is_file():
        what = "a folder" if p.is_dir() else "not there"
        raise argparse.ArgumentTypeError(f"Expected an existing file, but {text!r} is {what}")
    if not os.access(p, os.R_OK):
        raise argparse.ArgumentTypeError(f"Expected a readable file, but cannot read {text!r}")
    return p


def memory_size(text: str) -> int | None:
    """``--max-memory``: ``auto`` (None) or a size such as ``8G``, in bytes."""
    from gpumap.memory import parse_size

    try:
        return parse_size(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def frame_range(text: str) -> slice:
    """``START:STOP[:STEP]`` (whole numbers, START >= 0, STOP > START, STEP >= 1; START or STOP
    may be empty) as a ``slice`` (``--frames``)."""
    want = "START:STOP or START:STOP:STEP (whole numbers, START >= 0, STOP > START, STEP >= 1)"
    parts = text.split(":")
    if len(parts) not in (2, 3):
        raise argparse.ArgumentTypeError(f"Expected {want}, but got {text!r}")
    try:
        start, stop, step = (int(x) if x.strip() else None for x in (*parts, "")[:3])
    except ValueError:
        raise argparse.ArgumentTypeError(f"Expected {want}, but got {text!r}") from None
    start = start or 0
    if start < 0 or (stop is not None and stop <= start) or (step is not None and step < 1):
        raise argparse.ArgumentTypeError(f"Expected {want}, but got {text!r}")
    return slice(start, stop, step)


# ------------------------------------------------------------------------------ the live view
def _port(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"Expected a port number, but got {text!r}") from None
    if not 0 <= v <= 65535:
        raise argparse.ArgumentTypeError(f"Expected a port in 0..65535 (0 = any free one), but got {text!r}")
    return v


def _seconds(text: str) -> float:
    return nonnegative_float(text)


def _address(text: str) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    if not sep:
        host, port = text, "8080"
    return host or "127.0.0.1", _port(port)


def add_view_args(p: argparse.ArgumentParser, record: bool = True, live: bool = True) -> None:
    """``--view [HOST:PORT]``, ``--view-hold`` and ``--record`` (``live=False``, for ``gpumap view``:
    ``--view-host``, ``--view-port`` and ``--view-hold``; it always serves, and a saved map or a
    recording has no pings arriving to refresh on). A live view refreshes the map's voxels at most
    every 10 pings and twice a second (``view_every`` on the parsed flags: :func:`settle_view_args`)."""
    extra = "(optional extra: pip install 'gpumap[viewer]')"
    g = p.add_argument_group(f"live view {extra}" if live else f"view {extra}")
    if live:
        g.add_argument(
            "--view", nargs="?", const=("127.0.0.1", 8080), default=None, type=_address,
            metavar="HOST:PORT",
            help="serve a live 3-D view of the map as it grows (open the printed address in a browser); "
                 "default 127.0.0.1:8080 (this machine only; 0.0.0.0:PORT lets another machine connect, "
                 "port 0 any free one)",
        )
    else:
        g.add_argument("--view-host", default="127.0.0.1", metavar="ADDR",
                       help="address the view binds to (default 127.0.0.1: this machine only; 0.0.0.0 "
                            "lets another machine, e.g. the ship's laptop, connect)")
        g.add_argument("--view-port", type=_port, default=8080, metavar="PORT", help="default 8080")
    g.add_argument(
        "--view-hold",
        type=_seconds,
        default=None,
        metavar="SECONDS",
        help=("after the run, keep serving this long (default: until Ctrl-C)" if live else
              "serve this long, then exit (default: until Ctrl-C)"),
    )
    if record:
        g.add_argument(
            "--record",
            type=output_file,
            default=None,
            metavar="FILE",
            help="keep a recording (pings, poses, the map's changes; no viewer needed) that "
            "'gpumap view FILE' plays back",
        )


def settle_view_args(a: argparse.Namespace) -> None:
    """After parsing ``--view [HOST:PORT]``: ``a.view`` a bool, ``a.view_host``, ``a.view_port`` and
    ``a.view_every`` (10) set, as :class:`gpumap.viewer.session.Session` reads them."""
    addr = getattr(a, "view", None)
    a.view_host, a.view_port = addr if addr else ("127.0.0.1", 8080)
    a.view = addr is not None
    a.view_every = 10


def check_view_args(p: argparse.ArgumentParser, a: argparse.Namespace) -> None:
    """Refuse ``--view`` up front (one line, exit 2) when viser is not installed."""
    from gpumap.viewer import MISSING_VIEWER

    if hasattr(a, "view") and not isinstance(a.view, bool):  # --view [HOST:PORT] as parsed
        settle_view_args(a)
    if getattr(a, "view", False) and importlib.util.find_spec("viser") is None:
        # gpumap view always serves: it has no --view flag to name
        has_flag = any("--view" in act.option_strings for act in p._actions)
        p.error(f"argument --view: {MISSING_VIEWER}" if has_flag else MISSING_VIEWER)


# ------------------------------------------------------------------------------ errors
def user_errors() -> tuple[type[BaseException], ...]:
    """Exceptions that mean bad input or a machine that cannot do it: one line, exit 2.

    ``ValueError`` (``gpumap.io.FormatError`` and gpumap's other checks derive from it),
    ``TypeError``, :class:`gpumap.errors.BackendUnavailableError` and the ``OSError`` of a
    path that is missing or cannot be used. Anything else is a bug: it keeps its traceback.
    """
    from gpumap.errors import BackendUnavailableError

    errs: list[type[BaseException]] = [ValueError, TypeError, BackendUnavailableError, FileNotFoundError,
                                       NotADirectoryError, IsADirectoryError, PermissionError]
    fmt = _format_error()
    if fmt is not None:
        errs.append(fmt)
    return tuple(errs)


def _format_error() -> type[BaseException] | None:
    try:  # lazily: gpumap.io pulls in the readers
        from gpumap.io import FormatError
    except ImportError:
        return None
    return FormatError


def error_line(prog: str, e: BaseException) -> str:
    """``prog: error: message`` on one line (``format error`` for a malformed file)."""
    fmt = _format_error()
    kind = "format error" if fmt is not None and isinstance(e, fmt) else "error"
    return f"{prog}: {kind}: {one_line(str(e)) or type(e).__name__}"


