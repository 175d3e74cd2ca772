"""``python -m bench.rules_real``: both mapping rules on the real OASIS tank, into a results file.

``gpumap replay shared/data/oasis_tank --voxel-size 0.05 --compare-rules``, kept with the machine in
``bench/results/rules_real_tank.json`` (the README's paragraph on the rules comes from it). ~10 s.
"""

from __future__ import annotations

import json
import tempfile
from pathlib import Path

from .common import bench_parser, oasis_tank_dir, run_header, write_json


def main(argv: list[str] | None = None) -> int:
    ap = bench_parser("rules_real", __doc__, out="bench/results", voxel=0.05, backend="auto")
    ap.add_argument("--data", type=Path, default=None, help="the oasis_tank folder (default: shared/data)")
    a = ap.parse_args(argv)
    data = a.data or oasis_tank_dir()
    if data is None:
        raise SystemExit("bench.rules_real: shared/data/oasis_tank not found; pass --data")
    from gpumap.commands.replay import main as replay

    cmd = [str(data), "--voxel-size", str(a.voxel), "--compare-rules", "--backend", a.backend,
           "--no-progress", "--no-pictures"]
    with tempfile.TemporaryDirectory() as tmp:
        rc = replay([*cmd, "--out", tmp])
        if rc:
            return rc
        summary = json.loads((Path(tmp) / "summary.json").read_text())
    res = {**run_header("gpumap-rules-real/1", argv),
           "command": "gpumap replay " + " ".join(["shared/data/oasis_tank", *cmd[1:]]),
           "voxel_size_m": a.voxel, "rule_comparison": summary["rule_comparison"]}
    print(f"wrote {write_json(a.out / 'rules_real_tank.json', res, digits=4)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
