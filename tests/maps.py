"""Tests' shorthand for a map with options given as keywords (the API takes one MapperParams)."""

from __future__ import annotations

import gpumap
from gpumap.core.params import MapperParams
from gpumap.layers.confidence import ConfidenceLayer


def make_mapper(spec, grid, backend: str = "auto", *, cls=None, confidence: bool = False,
                device_index: int | None = None, **options) -> gpumap.MinMaxMapper:
    """``cls(spec, grid, backend, MapperParams(**options))`` (default :class:`gpumap.MinMaxMapper`),
    with a :class:`ConfidenceLayer` attached when ``confidence``."""
    if not isinstance(confidence, bool):
        raise TypeError(f"Expected a bool for 'confidence', but got {type(confidence).__name__}")
    cls = gpumap.MinMaxMapper if cls is None else cls
    m = cls(spec, grid, backend, MapperParams(**options), device_index=device_index)
    if confidence:
        m.attach(ConfidenceLayer())
    return m


def run_demo(argv: list[str], out, **overrides) -> dict:
    """``gpumap demo ARGV --out OUT`` with the benchmarks' knobs ``overrides`` (``plan``, ``sparse``,
    ``seed``, ``shadow_m``: fixed on the command line) set: the metrics it writes."""
    import argparse

    from gpumap.sim.demo import run_demo as run

    from gpumap.commands.demo import _parser

    args = _parser().parse_args([*argv, "--out", str(out)])
    return run(argparse.Namespace(**{**vars(args), **overrides, "view_sessions": []}))
