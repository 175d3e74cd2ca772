"""``python -m bench [NAME] [options]``: run any benchmark of ``bench/`` by name.

    python -m bench --list                 # the benchmarks, one line each
    python -m bench speed --gpu ...        # the same as python -m bench.speed --gpu ...
    python -m bench [options]              # the speed-against-error sweep (python -m bench sweep)
"""

from __future__ import annotations

import argparse
import importlib
import sys

from .sweep import _parser as _sweep_parser
from .sweep import run, write_result

#: Every benchmark and report tool ``python -m bench NAME`` runs: module name -> one line.
BENCHMARKS: dict[str, str] = {
    "ab": "two source trees timed side by side: a bounded map's speed, alternating runs in one session",
    "sweep": "speed against error on the simulated tank: every backend, voxel size, method and baseline",
    "speed": "latency and throughput on the real OASIS tank frames and the public OASIS code beside it; "
             "--synthetic, --gpu-check",
    "peer_ratio": "gpumap against the public OASIS code, in turn, refused on a loaded machine",
    "sparse": "sparse against dense maps: memory and images/s on the tank and survey pings",
    "memory": "peak memory of gpumap replay against the grid's voxels, per backend and rule",
    "workers": "the survey mapped by one process against N Dask workers on the same cores",
    "visibility": "the visible rule against the plain min-max rule: errors and speed (tank, circle)",
    "rules_real": "both mapping rules on the real OASIS tank (gpumap replay --compare-rules)",
    "decision": "the evidence rule's decisions (share test, calibrated view model): simulated scenes, "
                "real dev frames",
    "rate_real": "every rule on the full real tank run at the sonar's rate, judged by held-out first returns",
    "real_frontier": "every rule, the surface layer and the public OASIS reconstruction on real held-out "
                     "first returns: phantoms against misses",
    "oasis_public": "the public OASIS code's reconstruction of given frames, run in its own environment "
                    "(real_frontier runs it)",
    "variation": "how often a surface voxel's views are bright: the real full-rate tank and the simulator",
    "long_run": "every mapping rule over up to 1,000 simulated pings with realistic variation: FN and far FP",
    "refine": "plain, visible and refined maps against truth and on held-out pings",
    "ekf_registration": "the EKF with scan registration on the full real tank run: dev, held-out, full",
    "gpu_scale": "one GPU (two source trees side by side) and 1 vs 2 GPU workers, with the oracle check",
    "surface": "the surface layer against the visible and evidence maps: simulated truth, real first returns",
    "surface_rate": "the live surface layer at the sonar's rate on the full real run; replay with both",
    "nbv": "next best views: planned against rolled and random views; view_gain speed",
    "confidence": "the confidence layer's cost on the device: mapping the real tank with and without it",
    "ekf_bench": "the EKF on the prism simulation (NEES, odometry sweep, update cost; --vs-batch)",
    "ekf_real": "the EKF on the full real tank: EKF/odometry per variant, drift, seed; dev and held-out",
    "ekf_pose": "verified revisits in the EKF and a pose graph on the full real tank; maps per pose source",
    "frontend": "the EKF front end: detection, association and the EKF loop, simulated and real",
    "viewer_cost": "what the live view and the recorder cost gpumap replay of the real tank",
    "distance": "the distance field of the safe map on the real tank beside SciPy: full, local block, "
                "incremental",
    "ros_bench": "the ROS 2 node's sustained rates and latency over Fast DDS on the real tank (--distance: "
                 "with the distance field off and on)",
    "parity": "every map of the real tank frames on every backend here against NumPy's, bit for bit (GPUs)",
    "pipeline_rate": "the replay pipeline's stages alone and together: decode, map from memory, replay",
    "report": "the results files -> BENCHMARKS.md and its plots (--check compares only)",
    "readme": "the README's figures, written from the results files (--check compares only)",
}


def _parser() -> argparse.ArgumentParser:
    """The sweep's parser (``gpumap bench`` checks its flags with it) plus ``--list``."""
    p = _sweep_parser()
    p.add_argument("--list", action="store_true",
                   help="list the benchmarks python -m bench NAME runs, one line each, and exit")
    return p


def listing() -> str:
    """What ``--list`` prints: each name and its line."""
    width = max(map(len, BENCHMARKS))
    return "\n".join(["python -m bench NAME [options]   (python -m bench NAME --help for its options)", ""]
                     + [f"  {name:<{width}}  {line}" for name, line in BENCHMARKS.items()])


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``python -m bench`` and ``gpumap bench``."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] in BENCHMARKS and argv[0] != "sweep":
        return int(importlib.import_module(f".{argv[0]}", __package__).main(argv[1:]) or 0)
    if argv and argv[0] == "sweep":
        argv = argv[1:]
    elif argv and not argv[0].startswith("-"):
        print(f"python -m bench: error: unknown benchmark {argv[0]!r}: expected one of "
              f"{', '.join(BENCHMARKS)} (python -m bench --list)", file=sys.stderr)
        return 2
    args = _parser().parse_args(argv)
    if args.list:
        print(listing())
        return 0
    args.argv = argv
    write_result(run(args), args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
