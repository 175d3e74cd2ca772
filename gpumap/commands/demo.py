"""``gpumap demo``: simulate the tank (or ``--scene``), map it, score the map against truth.

What it writes into ``--out``: :mod:`gpumap.sim.demo` (:func:`~gpumap.sim.demo.run_demo`).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from gpumap.atomic import output_set
from gpumap.commands.common import (
    BACKEND_HELP,
    METHOD_HELP,
    ArgumentParser,
    add_view_args,
    backend_name,
    check_view_args,
    error_line,
    nonnegative_float,
    output_dir,
    positive_float,
    positive_int,
    unit_interval,
    user_errors,
)
from gpumap.geometry import RULES
from gpumap.sim import demo as sim_demo
from gpumap.sim.scenes import SCENES
from gpumap.sim.sonar import OCCUPIED_THRESHOLD

__all__ = ["OUTPUTS", "main"]

VARIATIONS = sim_demo.VARIATIONS


def _parser() -> ArgumentParser:
    p = ArgumentParser(prog="gpumap demo", description=(
        "simulate the tank (or --scene), map it with the min-max filter, and score the map against truth"))
    p.add_argument("--scene", default="tank", choices=sorted(SCENES),
                   help="simulated scene: tank (the paper's), circle (four objects seen from five sides), "
                        "side (the circle's objects, 40 pitched pings from one side) or survey (a long "
                        "seabed strip); default tank")
    p.add_argument("--voxel-size", type=positive_float, default=None,
                   help="voxel edge, metres (default: 0.03; 0.05 for the survey scene)")
    p.add_argument("--backend", type=backend_name, default="auto",
                   help=BACKEND_HELP)
    p.add_argument("--method", default="gather", choices=["gather", "template"],
                   help=METHOD_HELP)
    p.add_argument("--out", type=output_dir, default="demo_out",
                   help="output folder; its files are replaced as one set")
    p.add_argument("--pose-noise", type=nonnegative_float, default=None, metavar="SIGMA",
                   help="odometry noise per step (m and rad); adds odometry and EKF rows")
    p.add_argument("--pings", type=positive_int, default=None,
                   help="use only this many pings (evenly spaced)")
    p.add_argument("--threshold", type=unit_interval, default=OCCUPIED_THRESHOLD,
                   help="occupied intensity, in (0, 1]")
    p.add_argument("--rule", default="evidence", choices=list(RULES),
                   help="how views combine: 'evidence' (occupied unless its clear views show it bright "
                        "in fewer than a fifth of them), 'visible' (carved by 2 clear dark views) or "
                        "'plain' (the paper's min); the other rules are always mapped too, for the "
                        "side-by-side 'rules' rows")
    p.add_argument("--variation", default="none", choices=sorted(VARIATIONS),
                   help="view-to-view variation of the simulated sonar: none (default) or real_tank "
                        "(speckle, per-ping gain, pose jitter, surface texture and range loss fitted to the "
                        "real tank run)")
    p.add_argument(
        "--no-surface",
        dest="surface",
        action="store_false",
        help="do not compute the surface layer (gpumap.layers.surface: one voxel of the evidence map per "
        "bright cell; by default written beside map.npz as surface.npz, its figures in "
        "metrics.json's 'surface' block)",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    add_view_args(p)
    # what the benchmarks vary (bench/): fixed here, read by gpumap.sim.demo.run_demo
    p.set_defaults(shadow_m=0.0, seed=0, sparse=False, plan=0)
    return p


#: Every file ``gpumap demo`` writes into ``--out``: one run's set replaces the last one's.
OUTPUTS = ("metrics.json", "map.npz", "surface.npz", "sonar_image.png", "map_vs_truth.png",
           "error_by_views.png", "height_map.png", "errors_by_object.png", "plan_curves.png",
           "plan_confidence.png", "plan_poses.png")


def _view_opener(args: argparse.Namespace):
    """``open_view`` for :func:`gpumap.sim.demo.run_demo`: the session of ``--view``/``--record``."""
    if not (getattr(args, "view", False) or getattr(args, "record", None) is not None):
        return None
    from gpumap.viewer.session import Session

    return lambda spec, grid, threshold, title: Session.open(args, spec, grid, threshold, title=title)


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``gpumap demo``; returns the exit status.

    Bad flags exit with status 2 (``SystemExit``) before any work; bad input found later (a
    backend that cannot run here) prints one line and returns 2. The outputs replace those
    in ``--out`` as one set, only once all are written.
    """
    parser = _parser()
    args = parser.parse_args(argv)
    check_view_args(parser, args)
    out = args.out
    sessions: list = []
    try:
        with output_set(out, OUTPUTS) as tmp:  # all of them appear in --out together, or none
            m = sim_demo.run_demo(argparse.Namespace(**{**vars(args), "out": tmp, "view_sessions": sessions}),
                                  open_view=_view_opener(args))
    except user_errors() as e:
        for s in sessions:
            s.abort()
        print(error_line("gpumap demo", e), file=sys.stderr)
        return 2
    except BaseException:
        for s in sessions:
            s.abort()
        raise
    print(json.dumps({k: m[k] for k in ("scene", "backend", "rule", "voxel_size_m", "images", "ms_per_image",
                                         "demo_s")}, indent=1))
    head = ("rule", "missed", "obj missed", "seen free", "phantom", "water free")
    print(f"{head[0]:8s} " + " ".join(f"{h:>10s}" for h in head[1:]) + " pipe found")
    rows = dict(m["rules"])
    if "miss_rate" in m.get("surface", {}):
        rows["surface"] = m["surface"]
    for name, row in rows.items():
        print(f"{name:8s} {row['miss_rate']:10.1%} {row['miss_rate_objects']:10.1%} "
              f"{row['false_negative_rate_detectable']:10.1%} {row['false_positive_rate_far']:10.1%} "
              f"{row['free_carved_fraction']:10.1%} {row['pipe_found']}")
    print("missed: surface voxels some ping could detect that the map does not call occupied (free or "
          "unknown); obj missed: the same for the small objects; seen free: detectable surface the map "
          "observed and calls free; phantom: water more than one voxel from a surface called occupied; "
          "water free: water voxels called free (metrics.json; README: what the numbers mean)")
    if "memory" in m:
        mem = m["memory"]
        dense = [f"dense grid {mem['dense_grid_bytes'] / 2**20:.1f} MiB"]
        if "dense_water_column_bytes" in mem:
            dense.append(f"dense to the surface {mem['dense_water_column_bytes'] / 2**20:.1f} MiB")
        print(f"map memory {mem['map_bytes'] / 2**20:.1f} MiB ({mem['storage']}); observed "
              f"{mem['observed_voxels']} voxels x {mem['bytes_per_voxel']} B = "
              f"{mem['observed_bytes'] / 2**20:.1f} MiB; " + "; ".join(dense))
    if "pose_noise" in m:
        for name, row in m["pose_noise"]["rows"].items():
            print(f"{name:9s} missed {row.get('miss_rate', float('nan')):.3f} "
                  f"phantom {row.get('false_positive_rate_far', float('nan')):.3f} "
                  f"pose err {row.get('translation_error_mean_m', float('nan')):.3f} m")
    if "plan" in m:
        from gpumap.sim.plan_demo import print_plan

        print_plan(m["plan"])
    written = [n for n in OUTPUTS if (Path(out) / n).exists()]
    print(f"wrote {', '.join(written)} to {Path(out).resolve()}")
    for s in sessions:
        s.serve()
    return 0

