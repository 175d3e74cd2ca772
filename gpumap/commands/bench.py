"""``gpumap bench``: the speed-against-error sweep of :mod:`gpumap.bench` on this machine.

The sweep's own flags are checked first with stricter types (one line, exit 2), so a bad value
is refused before the sweep starts.
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable

from gpumap.commands.common import (
    backend_name,
    existing_file,
    nonnegative_float,
    nonnegative_int,
    output_dir,
    output_file,
    parser_error,
    positive_float,
    positive_int,
    probability,
    unit_interval,
)

__all__ = ["main"]

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
    p.error = lambda message: parser_error(p, message)
    for act in p._actions:
        for opt in act.option_strings:
            if opt in _BENCH_TYPES:
                act.type = _BENCH_TYPES[opt]
    p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    try:
        mod = importlib.import_module("gpumap.bench.__main__")
    except ModuleNotFoundError as e:
        if not (e.name or "").startswith("gpumap.bench"):
            raise
        print("gpumap bench: error: this gpumap was installed without its benchmark "
              "(gpumap.bench): reinstall it (pip install gpumap, or pip install -e . in a "
              "checkout, where `python -m bench` also runs it)", file=sys.stderr)
        return 2
    argv = list(argv or [])
    _check_bench_flags(mod, argv)
    return int(mod.main(argv) or 0)
