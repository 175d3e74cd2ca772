"""``gpumap merge OUT.npz MAP.npz MAP.npz ...``: maps of the same spec built from different pings, as one.

The maps (dense or sparse, all of one kind and options) may come from different runs or
machines; the merged map equals one run over all their pings, bit for bit (:mod:`gpumap.core.merge`).
"""

from __future__ import annotations

import json

from gpumap.commands.common import ArgumentParser, existing_file, output_file

__all__ = ["main"]


def _parser() -> ArgumentParser:
    p = ArgumentParser(prog="gpumap merge",
                       description="merge map files of the same grid and options built from different pings")
    p.add_argument("out", type=output_file, help="the merged map file to write (.npz; replaced atomically)")
    p.add_argument("maps", type=existing_file, nargs="+",
                   help="map files written by gpumap (map.npz), all dense or all sparse, same options")
    return p


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``gpumap merge``; returns the exit status."""
    from gpumap.core.merge import merge_maps

    a = _parser().parse_args(argv)
    m = merge_maps(a.maps, backend="numpy")
    path = m.save(a.out)
    obs = int(m.observed().sum())
    print(json.dumps({"path": str(path), "maps": len(a.maps), "pings": m.n_integrated,
                      "observed_voxels": obs}))
    return 0
