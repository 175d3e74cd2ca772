"""Atomic file writes: a reader sees the old file or the complete new one, never a part.

:func:`output_set` does the same for a set of files (a command's outputs): they appear in the
output folder together, replacing an older run's, or not at all.

:func:`atomic_write` writes into a temporary file beside the target, flushes it to disk,
gives it the target's permissions (or, for a new file, ``0o666`` less the umask, as
``open()`` would) and renames it over the target. On any error, ``KeyboardInterrupt``
included, the temporary file is removed and the target is untouched.
"""

from __future__ import annotations

import contextlib
import os
import secrets
import shutil
import signal
import tempfile
import threading
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import BinaryIO

__all__ = ["atomic_write", "new_file_mode", "output_set"]


def new_file_mode() -> int:
    """``0o666`` less the process umask, read without changing it (Linux), else ``0o644``."""
    try:
        with open("/proc/self/status", "rb") as f:
            for line in f:
                if line.startswith(b"Umask:"):
                    return 0o666 & ~int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    return 0o644


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike) -> Iterator[BinaryIO]:
    """Open a binary file that replaces ``path`` only when the ``with`` block ends cleanly."""
    target = Path(path)
    try:
        mode = target.stat().st_mode & 0o7777
    except OSError:
        mode = new_file_mode()
    fd, tmp = tempfile.mkstemp(dir=target.parent, prefix=target.name + ".", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, mode)
        os.replace(tmp, target)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


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
