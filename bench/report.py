"""``python -m bench.report``: the results in ``bench/results`` -> ``BENCHMARKS.md`` and its plots.

One module per concern: :mod:`bench.report_sweep` (the speed-against-error sweep of
``python -m bench``, every ``gpumap-bench/`` JSON, merged across machines),
:mod:`bench.report_plots` (its PNG plots), :mod:`bench.report_speed` (latency and throughput on
the real tank frames, ``speed_*.json`` of ``python -m bench.speed``) and :mod:`bench.report_md`
(formatting, and keeping what others write into ``BENCHMARKS.md``: sections the report does not
generate, such as the visibility section of ``bench.visibility``, and blocks between
``<!-- begin:NAME -->`` / ``<!-- end:NAME -->`` markers, such as the EKF section, are carried
over verbatim).

    python -m bench.report [--results bench/results] [--out BENCHMARKS.md]
"""

from __future__ import annotations

import os
from pathlib import Path

from .common import bench_parser
from .report_md import keep_foreign_sections
from .report_plots import _plots
from .report_speed import load_speed, render_speed
from .report_sweep import load_results, render_sweep


def render(folder: Path, out: Path) -> str:
    """The new ``BENCHMARKS.md`` text (and the plots, written next to the results)."""
    results = load_results(folder)
    speed = load_speed(folder)
    if not results and not speed:
        raise SystemExit(f"no bench results in {folder}; run `python -m bench` or `bench.speed` first")
    plots = _plots(results, folder) if results else []
    prefix = os.path.relpath(folder, out.parent or ".") + "/"
    text = render_sweep(results, plots, prefix) if results else "# Benchmarks\n"
    if speed:
        text = text.rstrip("\n") + "\n\n" + render_speed(speed)
    old = out.read_text() if out.is_file() else ""
    return keep_foreign_sections(old, text)


def main(argv: list[str] | None = None) -> int:
    ap = bench_parser("report", __doc__)
    ap.add_argument("--results", type=Path, default=Path("bench/results"),
                    help="folder of results files (default bench/results)")
    ap.add_argument("--out", type=Path, default=Path("BENCHMARKS.md"), help="the file to write")
    a = ap.parse_args(argv)
    a.out.write_text(render(a.results, a.out))
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
