"""``python -m bench.rules_real``: every mapping rule on the real OASIS tank, into a results file.

:func:`gpumap.pipeline.replay.run_rule_comparison` of ``shared/data/oasis_tank`` at 5 cm (the evidence
rule beside the plain one, and where they differ), kept with the machine in
``bench/results/rules_real_tank.json`` (the README's paragraph on the rules comes from it). ~10 s.
"""

from __future__ import annotations

from pathlib import Path

from .common import bench_parser, oasis_tank_dir, run_header, write_json


def main(argv: list[str] | None = None) -> int:
    ap = bench_parser("rules_real", __doc__, out="bench/results", voxel=0.05, backend="auto")
    ap.add_argument("--data", type=Path, default=None, help="the oasis_tank folder (default: shared/data)")
    a = ap.parse_args(argv)
    data = a.data or oasis_tank_dir()
    if data is None:
        raise SystemExit("bench.rules_real: shared/data/oasis_tank not found; pass --data")
    res = {**run_header("gpumap-rules-real/1", argv),
           "command": f"python -m bench.rules_real --voxel {a.voxel} --backend {a.backend}",
           "voxel_size_m": a.voxel, "rule_comparison": rule_comparison(data, a.voxel, a.backend)}
    print(f"wrote {write_json(a.out / 'rules_real_tank.json', res, digits=4)}")
    return 0


def rule_comparison(data: Path, voxel_m: float, backend: str) -> dict:
    """The comparison of every rule on the fan folder ``data`` at ``voxel_m`` (the evidence rule first)."""
    from gpumap.io import open_recording
    from gpumap.pipeline.replay import DEFAULT_THRESHOLD, run_rule_comparison

    _, cmp_ = run_rule_comparison(open_recording(data), threshold=DEFAULT_THRESHOLD, rule="evidence",
                                  voxel_size_m=voxel_m, backend=backend, progress=False)
    return cmp_


if __name__ == "__main__":
    raise SystemExit(main())
