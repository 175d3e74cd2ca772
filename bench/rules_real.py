"""``python -m bench.rules_real``: both mapping rules on the real OASIS tank, into a results file.

Runs ``gpumap replay shared/data/oasis_tank --voxel-size 0.05 --compare-rules`` (the README's
command; the threshold is the replay's default for the recording) and keeps its
``rule_comparison`` (occupied voxels per rule, those only the visible rule keeps, where they
lie) with the machine in ``bench/results/rules_real_tank.json``. The README's paragraph on
the two rules is generated from that file (``python -m bench.readme``). Takes ~10 s.
"""

from __future__ import annotations

import json
import tempfile
from pathlib import Path

from .common import bench_parser, oasis_tank_dir, run_header, write_json

SCHEMA = "gpumap-rules-real/1"


def main(argv: list[str] | None = None) -> int:
    ap = bench_parser("rules_real", __doc__)
    ap.add_argument("--data", type=Path, default=None, help="the oasis_tank folder (default: shared/data)")
    ap.add_argument("--voxel-size", type=float, default=0.05, help="metres (default 0.05, as in the README)")
    ap.add_argument("--backend", default="auto", help="gpumap backend (default auto)")
    ap.add_argument("--out", type=Path, default=Path("bench/results"), help="results folder")
    a = ap.parse_args(argv)
    data = a.data or oasis_tank_dir()
    if data is None:
        raise SystemExit("bench.rules_real: shared/data/oasis_tank not found; pass --data")
    from gpumap.commands.replay import main as replay

    cmd = [str(data), "--voxel-size", str(a.voxel_size), "--compare-rules", "--backend", a.backend,
           "--no-progress", "--no-pictures"]
    with tempfile.TemporaryDirectory() as tmp:
        rc = replay([*cmd, "--out", tmp])
        if rc:
            return rc
        summary = json.loads((Path(tmp) / "summary.json").read_text())
    res = {**run_header(SCHEMA, argv),
           "command": "gpumap replay " + " ".join(["shared/data/oasis_tank", *cmd[1:]]),
           "voxel_size_m": a.voxel_size, "rule_comparison": summary["rule_comparison"]}
    path = write_json(a.out / "rules_real_tank.json", res, digits=4)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
