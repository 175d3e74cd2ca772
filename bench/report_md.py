"""Markdown helpers of the benchmark report: number formatting, and keeping the sections of
``BENCHMARKS.md`` that other tools write (``bench.visibility``, ``bench.ekf_bench``) when the
report rewrites the file."""

from __future__ import annotations

import math
import re
from typing import Any

__all__ = ["_f", "_pct", "keep_foreign_sections"]


def _f(x: Any, fmt: str = ".3g", none: str = "–") -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return none
    if isinstance(x, bool):
        return "yes" if x else "no"
    return format(x, fmt)


def _pct(x: Any) -> str:
    return _f(None if x is None else 100.0 * x, ".1f") + ("" if x is None else " %")




_MARKED = re.compile(r"<!-- begin:(?P<name>[\w-]+) -->.*?<!-- end:(?P=name) -->", re.S)


def keep_foreign_sections(old: str, generated: str) -> str:
    """``generated`` followed by what of ``old`` the report does not write itself.

    Kept verbatim, in their order in ``old``: every block between ``<!-- begin:NAME -->`` and
    ``<!-- end:NAME -->`` markers (e.g. the EKF engineer's), and every ``## `` section whose
    heading ``generated`` does not have (e.g. the visibility section of issue #10). A marked
    block that ``generated`` already holds is not repeated.
    """
    blocks = [m.group(0) for m in _MARKED.finditer(old) if m.group(0).split(" -->")[0] not in generated]
    rest = _MARKED.sub("\0", old)  # placeholders keep the blocks' places
    own = {line.strip() for line in generated.splitlines() if line.startswith("## ")}
    kept: list[str] = []
    section: list[str] | None = None
    fence = False
    for line in rest.splitlines():
        if line.startswith("```"):
            fence = not fence
        if line.startswith("## ") and not fence:
            if section is not None:
                kept.append("\n".join(section))
            section = None if line.strip() in own else [line]
            continue
        if section is not None:
            section.append(line)
        elif "\0" in line:  # a marked block outside any kept section
            kept.append(line)
    if section is not None:
        kept.append("\n".join(section))
    out = generated.rstrip("\n")
    for chunk in kept:
        while "\0" in chunk and blocks:
            chunk = chunk.replace("\0", blocks.pop(0), 1)
        chunk = chunk.replace("\0", "")
        if chunk.strip():
            out += "\n\n" + chunk.strip("\n")
    for b in blocks:  # marked blocks whose place was in a section the report rewrites
        out += "\n\n" + b
    return out + "\n"
