"""``gpumap`` command line: the subcommands of :data:`COMMANDS` (``gpumap --help`` lists them).

Each subcommand lives with the code it drives and owns its own options; this module only
dispatches, so ``gpumap demo --help`` shows the demo's own help. It also holds what every
subcommand shares:

- :class:`ArgumentParser` (argparse with one-line errors, exit status 2) and the ``type=``
  validators (:func:`positive_float`, :func:`unit_interval`, :func:`output_dir`, ...), so
  that every flag is checked before any work starts;
- :func:`user_errors` and :func:`error_line`: gpumap's own errors and bad input become one
  line on stderr and exit status 2; anything else keeps its traceback;
- :func:`output_set`: a command's output files are written into a temporary folder and
  swapped in together, so an interrupted run leaves the old set or the complete new one.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import logging
import math
import os
import secrets
import shutil
import signal
import sys
import threading
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import NoReturn

__all__ = [
    "ArgumentParser",
    "backend_name",
    "error_line",
    "existing_file",
    "grid_box",
    "main",
    "nonnegative_float",
    "nonnegative_int",
    "output_dir",
    "output_file",
    "output_set",
    "positive_float",
    "positive_int",
    "probability",
    "refuse_without",
    "threshold_or_auto",
    "unit_interval",
    "user_errors",
    "vfov_deg",
]

COMMANDS = {
    "demo": ("gpumap.sim.demo", "simulate the tank scene, map it, and score the map against truth"),
    "replay": ("gpumap.replay", "map a real recording (Oculus, ARIS, fan images + poses, ROS bag)"),
    "view": ("gpumap.viewer.cli", "serve a saved or refined map or a recording in the browser view ([viewer] "
             "extra)"),
    "export": ("gpumap.export_cli", "write a saved or refined map as OctoMap .bt (RViz, octovis) or .ply"),
    "merge": ("gpumap.merge_cli", "merge saved maps of one grid built from different pings into one"),
    "ros": ("gpumap.ros.node", "a ROS 2 node that maps live sonar pings ([ros] extra)"),
    "ros-play": ("gpumap.ros.play", "publish a recording as the ROS 2 node's sonar topics ([ros] extra)"),
    "refine": ("gpumap.refine_cli", "fit a recording's map so that pings rendered from it match its pings"),
    "plan": ("gpumap.plan_cli", "next best sonar views for a saved map, from its confidence layer"),
    "bench": ("gpumap.bench.__main__", "speed against error sweep on this machine (results in --out)"),
    "info": ("gpumap.cli", "list the backends this machine can run"),
}


# ------------------------------------------------------------------------------ parsing
#: Help lines of the options several subcommands share (one wording everywhere).
BACKEND_HELP = ("where to map: auto (the fastest here, named in the output), numpy, warp-cpu, warp-cuda, "
                "opencl, opencl-gpu or opencl-cpu (see gpumap info)")
METHOD_HELP = ("gather (every voxel in the field of view, the default) or template (the paper's voxel "
               "template; leaves holes, plain rule only)")

def _one_line(text: str) -> str:
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
        _parser_error(self, message)


def _parser_error(parser: argparse.ArgumentParser, message: str) -> NoReturn:
    parser.exit(2, f"{parser.prog}: error: {_one_line(message)} (see {parser.prog} --help)\n")


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


def positive_float(text: str) -> float:
    """A finite number > 0 (``--voxel-size``)."""
    v = _number(text)
    if v <= 0:
        raise argparse.ArgumentTypeError(f"Expected a number > 0, but got {text!r}")
    return v


def nonnegative_float(text: str) -> float:
    """A finite number >= 0 (``--pose-noise``, ``--shadow-m``)."""
    v = _number(text)
    if v < 0:
        raise argparse.ArgumentTypeError(f"Expected a number >= 0, but got {text!r}")
    return v


def unit_interval(text: str) -> float:
    """A number in (0, 1] (an occupied threshold)."""
    v = _number(text)
    if not 0.0 < v <= 1.0:
        raise argparse.ArgumentTypeError(f"Expected a number in (0, 1], but got {text!r}")
    return v


def probability(text: str) -> float:
    """A number in [0, 1]."""
    v = _number(text)
    if not 0.0 <= v <= 1.0:
        raise argparse.ArgumentTypeError(f"Expected a number in [0, 1], but got {text!r}")
    return v


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


def positive_int(text: str) -> int:
    """A whole number >= 1 (``--stride``, ``--pings``, ``--max-frames``)."""
    v = _whole(text)
    if v < 1:
        raise argparse.ArgumentTypeError(f"Expected a whole number >= 1, but got {text!r}")
    return v


def nonnegative_int(text: str) -> int:
    """A whole number >= 0 (``--seed``)."""
    v = _whole(text)
    if v < 0:
        raise argparse.ArgumentTypeError(f"Expected a whole number >= 0, but got {text!r}")
    return v


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
    return f"{prog}: {kind}: {_one_line(str(e)) or type(e).__name__}"


# ------------------------------------------------------------------------------ outputs
@contextlib.contextmanager
def _signals_deferred() -> Iterator[None]:
    """Hold SIGINT (Ctrl-C) and SIGTERM until the block ends, then deliver them.

    Python runs signal handlers in the main thread whichever thread the signal hit, so
    swapping the handlers (not one thread's signal mask) holds them for the whole process.
    Off the main thread handlers cannot be set: there the block is not protected.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    got: list[int] = []
    old = {}
    for sig in (signal.SIGINT, signal.SIGTERM):
        if signal.getsignal(sig) is not None:  # None: a handler Python cannot restore
            old[sig] = signal.signal(sig, lambda signum, frame: got.append(signum))
    try:
        yield
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)
        for sig in dict.fromkeys(got):
            signal.raise_signal(sig)


def _exists(p: Path) -> bool:
    return p.exists() or p.is_symlink()


def _commit(tmp: Path, out: Path, names: Iterable[str]) -> None:
    """Swap the files of ``tmp`` into ``out`` as one set; remove stale ``names`` left in ``out``.

    ``out`` absent: one rename of the folder. ``out`` present: the old files (of the new set
    and of ``names``) move aside into ``tmp``, then the new ones move in, with SIGINT and
    SIGTERM held; any failure moves every file back where it was.
    """
    with _signals_deferred():
        if not _exists(out):
            try:
                os.rename(tmp, out)
                return
            except OSError:
                if not _exists(out):
                    raise
                # someone made ``out`` meanwhile: swap file by file below
        new = sorted(e.name for e in os.scandir(tmp))
        aside = tmp / ".old"
        aside.mkdir()
        moves: list[tuple[Path, Path]] = []
        try:
            for name in sorted(set(new) | set(names)):
                if _exists(out / name):
                    os.replace(out / name, aside / name)
                    moves.append((out / name, aside / name))
            for name in new:
                os.replace(tmp / name, out / name)
                moves.append((tmp / name, out / name))
        except BaseException:
            for src, dst in reversed(moves):
                os.replace(dst, src)
            raise
        shutil.rmtree(tmp, ignore_errors=True)


def _new_folder(parent: Path, prefix: str) -> Path:
    """A new, empty folder ``parent/prefix<random>`` with the usual permissions (umask; not 0700)."""
    for _ in range(100):
        p = parent / f"{prefix}{secrets.token_hex(4)}"
        try:
            p.mkdir()
        except FileExistsError:
            continue
        return p
    raise FileExistsError(f"Expected to create a temporary folder in {parent}, but every name was taken")


@contextlib.contextmanager
def output_set(out: str | os.PathLike, names: Iterable[str] = ()) -> Iterator[Path]:
    """Write a command's outputs as a set: yield a temporary folder, swap it into ``out`` on success.

    Everything written into the yielded folder appears in ``out`` together when the block
    ends without an exception; an exception (``KeyboardInterrupt`` included) anywhere before
    leaves ``out`` exactly as it was. ``names`` are every file the command can write: those
    of an older run that this run did not write are removed with the swap, so ``out`` never
    mixes two runs. The temporary folder lives beside ``out`` (inside it when ``out``
    already exists), on the same file system, and is removed in every case.

    Raises
    ------
    ValueError
        ``out`` exists and is not a folder.
    """
    out = Path(out)
    if _exists(out) and not out.is_dir():
        raise ValueError(f"Expected an output folder, but {str(out)!r} is a file")
    if out.is_dir():
        tmp = _new_folder(out, ".gpumap-partial-")
    else:
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = _new_folder(out.parent, f".{out.name}.partial-")
    try:
        yield tmp
        _commit(tmp, out, names)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


# ------------------------------------------------------------------------------ commands
def info(argv: list[str] | None = None) -> int:
    ArgumentParser(prog="gpumap info", description=COMMANDS["info"][1]).parse_args(argv)
    import gpumap
    from gpumap.backends import make_backend

    spec = gpumap.SonarSpec.uniform(n_beams=4, n_bins=4)
    print(f"gpumap {gpumap.__version__}")
    works = []
    for name in gpumap.available_backends():
        try:
            b = make_backend(name, spec)
        except gpumap.BackendUnavailableError as e:  # a device is there, but it cannot run gpumap
            print(f"  {name:<11} cannot run: {_one_line(e)}")
            continue
        works.append(b.name)
        print(f"  {b.name:<11} {b.device}")
    print(f"auto picks: {works[0]}")
    return 0


#: Stricter ``type=`` for ``bench/__main__.py``'s flags (applied to its parser by option string:
#: flags it no longer has are skipped), so that ``gpumap bench`` refuses bad values before the sweep.
_BENCH_TYPES: dict[str, Callable[[str], object]] = {
    "--voxel-size": positive_float,
    "--voxel": positive_float,
    "--backend": backend_name,
    "--pings": positive_int,
    "--pings-from": existing_file,
    "--save-pings": output_file,
    "--numpy-cap": positive_int,
    "--threshold": unit_interval,
    "--fnr": probability,
    "--shadow-m": nonnegative_float,
    "--seed": nonnegative_int,
    "--out": output_dir,
}


def _check_bench_flags(mod, argv: list[str]) -> None:
    """Parse ``argv`` with the bench's own parser, its types made strict and its errors one line."""
    make = getattr(mod, "_parser", None)
    if make is None:
        return
    p = make()
    p.error = lambda message: _parser_error(p, message)
    for act in p._actions:
        for opt in act.option_strings:
            if opt in _BENCH_TYPES:
                act.type = _BENCH_TYPES[opt]
    p.parse_args(argv)


def _usage() -> str:
    lines = ["usage: gpumap COMMAND [options]   (gpumap COMMAND --help for its options)", "", "commands:"]
    lines += [f"  {k:<8} {v[1]}" for k, v in COMMANDS.items()]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv:
        print(_usage(), file=sys.stderr)
        return 2
    if argv[0] in ("-h", "--help"):
        print(_usage())
        return 0
    cmd, rest = argv[0], argv[1:]
    if cmd not in COMMANDS:
        print(f"gpumap: error: unknown command {cmd!r}: expected one of {', '.join(COMMANDS)} "
              "(see gpumap --help)", file=sys.stderr)
        return 2
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    logging.getLogger("OpenGL").setLevel(logging.WARNING)  # not "No OpenGL_accelerate module loaded"
    prog = f"gpumap {cmd}"
    try:
        if cmd == "info":
            return info(rest)
        try:
            mod = importlib.import_module(COMMANDS[cmd][0])
        except ModuleNotFoundError as e:
            if cmd == "bench" and (e.name or "").startswith("gpumap.bench"):
                print("gpumap bench: error: this gpumap was installed without its benchmark "
                      "(gpumap.bench): reinstall it (pip install gpumap, or pip install -e . in a "
                      "checkout, where `python -m bench` also runs it)", file=sys.stderr)
                return 2
            raise
        if cmd == "bench":
            _check_bench_flags(mod, rest)
        return int(mod.main(rest) or 0)
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130
    except user_errors() as e:  # bad input or machine: say it in one line, no traceback
        print(error_line(prog, e), file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
