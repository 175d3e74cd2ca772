"""``gpumap plan MAP``: the next best views for a saved map, from its confidence layer.

    gpumap plan map.npz --pose 0.5,0,0.3,0,20,0 --views 5 --max-roll-deg 45 --out plan.json
    gpumap plan map.npz --recording /path/to/oasis_tank --stride 12

Candidates are drawn around anchor poses (``--pose`` given, or the recording's poses spread
evenly over it, ``--anchors`` of them) within a wrist's reach (:func:`gpumap.layers.viewgain.candidate_poses`:
roll about the boresight within ``--max-roll-deg``, pitch within ``--max-tilt-deg``, yaw within
``--max-yaw-deg``, each axis of the translation within ``--radius-m``) and scored by the map's view
gain (:meth:`gpumap.MinMaxMapper.view_gain`: the unconfirmed occupied voxels a view could settle,
plus ``--unknown-weight`` times the unknown ones it would see). The ``--views`` best candidates
are written, best first: each gain is against the saved map as it is (the planner cannot take the
pings, so gains do not account for one another: take the first view, map it, plan again).

The map needs its confidence layer (a mapper made with ``confidence=True``). A map saved without
it gets it rebuilt when ``--recording`` is given: the recording's frames (``--stride``,
``--max-frames``, as the map was built) are mapped again with the layer, on the map's grid, rule
and threshold, and must give the saved map's values exactly. Writes ``--out`` (default
``plan.json``: ``views``, each ``T_W_S`` as a 4x4 list, ``gain``, ``candidate``; the limits and
settings) and prints a short table. An anchor that starts with a minus sign is written
``--pose=-1,0,0.5,0,20,0``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np

from gpumap.commands.common import (
    BACKEND_HELP,
    ArgumentParser,
    backend_name,
    existing_file,
    nonnegative_float,
    nonnegative_int,
    output_file,
    positive_int,
)
from gpumap.layers.confidence import ConfidenceLayer, with_confidence

__all__ = ["main", "pose_from_xyz_ypr_deg", "ypr_deg"]


def _pose_arg(text: str) -> np.ndarray:
    """``x,y,z,yaw_deg,pitch_deg,roll_deg`` -> (4, 4) ``T_W_S``."""
    try:
        v = [float(x) for x in text.split(",")]
    except ValueError:
        v = []
    if len(v) != 6 or not all(math.isfinite(x) for x in v):
        raise argparse.ArgumentTypeError(f"Expected six finite numbers x,y,z,yaw_deg,pitch_deg,roll_deg, but "
                                         f"got {text!r}")
    return pose_from_xyz_ypr_deg(v[:3], *v[3:])


def _degrees(limit: float) -> Callable[[str], float]:
    def parse(text: str) -> float:
        v = nonnegative_float(text)
        if v > limit:
            raise argparse.ArgumentTypeError(f"Expected degrees in [0, {limit:g}], but got {text!r}")
        return v

    return parse


def pose_from_xyz_ypr_deg(xyz_m, yaw_deg: float, pitch_deg: float, roll_deg: float) -> np.ndarray:
    """(4, 4) ``T_W_S`` at ``xyz_m`` with ``R = Rz(yaw) Ry(pitch) Rx(roll)`` (pitch positive down,
    as :func:`gpumap.layers.viewgain.candidate_poses` turns a candidate)."""
    y, p, r = (math.radians(a) for a in (yaw_deg, pitch_deg, roll_deg))
    cy, sy, cp, sp, cr, sr = math.cos(y), math.sin(y), math.cos(p), math.sin(p), math.cos(r), math.sin(r)
    Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    Rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    T = np.eye(4)
    T[:3, :3] = Rz @ Ry @ Rx
    T[:3, 3] = np.asarray(xyz_m, np.float64)
    return T


def ypr_deg(T: np.ndarray) -> tuple[float, float, float]:
    """(yaw, pitch, roll) degrees of ``T``'s rotation ``Rz(yaw) Ry(pitch) Rx(roll)``."""
    R = np.asarray(T)[:3, :3]
    return (math.degrees(math.atan2(R[1, 0], R[0, 0])),
            math.degrees(math.asin(max(-1.0, min(1.0, -R[2, 0])))),
            math.degrees(math.atan2(R[2, 1], R[2, 2])))


def _parser() -> ArgumentParser:
    p = ArgumentParser(prog="gpumap plan",
                       description="next best views for a saved map, from its confidence layer")
    p.add_argument("map", type=existing_file, help="a map file (map.npz) with its confidence layer, or any "
                   "map with --recording to rebuild the layer")
    p.add_argument("--pose", type=_pose_arg, action="append", default=None, metavar="X,Y,Z,YAW,PITCH,ROLL",
                   help="an anchor pose (metres, degrees; pitch positive down), repeatable")
    p.add_argument("--recording", default=None, metavar="PATH",
                   help="the map's recording: its poses are the anchors (unless --pose), and a map "
                   "without the confidence layer gets it rebuilt from its frames")
    p.add_argument("--stride", type=positive_int, default=1, help="with --recording: every N-th frame")
    p.add_argument("--max-frames", type=positive_int, default=None, help="with --recording: at most N frames")
    p.add_argument("--anchors", type=positive_int, default=20,
                   help="recording poses the candidates are drawn around, spread evenly (default 20)")
    p.add_argument("--views", type=positive_int, default=5, help="best views to write (default 5)")
    p.add_argument("--candidates", type=positive_int, default=2000, help="candidates scored (default 2000)")
    p.add_argument("--max-roll-deg", type=_degrees(180), default=45.0,
                   help="wrist roll about the boresight, +- degrees (default 45)")
    p.add_argument("--max-tilt-deg", type=_degrees(90), default=15.0,
                   help="wrist pitch (tilt), +- degrees (default 15)")
    p.add_argument("--max-yaw-deg", type=_degrees(180), default=20.0,
                   help="wrist yaw, +- degrees (default 20)")
    p.add_argument("--radius-m", type=nonnegative_float, default=0.1,
                   help="reach: each axis of the translation within +- this, metres (default 0.1)")
    p.add_argument("--unknown-weight", type=nonnegative_float, default=0.0,
                   help="weight of an unknown voxel against an unconfirmed one (default 0: settle what the "
                   "map holds)")
    p.add_argument("--seed", type=nonnegative_int, default=0, help="seed of the candidates")
    p.add_argument("--backend", type=backend_name, default="auto", help=f"where to score, {BACKEND_HELP}")
    p.add_argument("--out", type=output_file, default=Path("plan.json"), help="default plan.json")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    return p


def _with_layer(mapper, a: argparse.Namespace, frames) -> tuple[object, bool]:
    """``mapper`` if it keeps the confidence layer, else one rebuilt from the recording's frames."""
    if "confidence" in mapper.layer_state:  # a map file that kept the layer: it takes its arrays back
        mapper.attach(ConfidenceLayer())
    if any(x.name == "confidence" for x in mapper.layers):
        return mapper, False
    if frames is None:
        raise ValueError("Expected a map with its confidence layer (a mapper made with confidence=True), "
                         f"but {a.map} has none: pass --recording (its frames rebuild the layer)")
    import gpumap
    from gpumap.layers.refine import map_frames

    spec, images, poses = frames
    if spec != mapper.spec:
        raise ValueError(f"Expected a recording of the map's sonar geometry, but {a.recording} is of another")
    params = mapper.params.replace(carve_views=mapper.carve_views, bright_share=mapper.bright_share,
                                   share_z=mapper.share_z)
    m = with_confidence(gpumap.MinMaxMapper(mapper.spec, mapper.grid, a.backend, params))
    map_frames(m, images, poses, progress=not a.no_progress)
    if not np.array_equal(m.raw_values(), mapper.raw_values()):
        raise ValueError(f"Expected the frames of {a.recording} (--stride {a.stride}, --max-frames "
                         f"{a.max_frames}) to rebuild {a.map}, but the map they make differs: pass the "
                         "frames the map was built from")
    return m, True


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``gpumap plan MAP``; returns the exit status."""
    p = _parser()
    a = p.parse_args(argv)
    if a.pose is None and a.recording is None:
        p.error("argument --pose: Expected --pose or --recording (the candidates are drawn around poses "
                "the vehicle can reach), but got neither")
    from gpumap.core.merge import load_map
    from gpumap.layers.refine import recording_frames
    from gpumap.layers.viewgain import next_best_views

    mapper = load_map(a.map, backend=a.backend)
    frames = (recording_frames(a.recording, a.stride, a.max_frames, progress=not a.no_progress)
              if a.recording is not None else None)
    mapper, rebuilt = _with_layer(mapper, a, frames)
    if a.pose is not None:
        anchors = np.stack(a.pose)
    else:
        P = frames[2]
        anchors = P[np.unique(np.linspace(0, len(P) - 1, min(a.anchors, len(P))).round().astype(int))]
    limits = {"roll_rad": (-math.radians(a.max_roll_deg), math.radians(a.max_roll_deg)),
              "pitch_rad": (-math.radians(a.max_tilt_deg), math.radians(a.max_tilt_deg)),
              "yaw_rad": (-math.radians(a.max_yaw_deg), math.radians(a.max_yaw_deg)),
              "offset_m": (-a.radius_m, a.radius_m)}
    best, n = next_best_views(mapper, anchors, views=a.views, candidates=a.candidates,
                              unknown_weight=a.unknown_weight, seed=a.seed, **limits)
    views = [{**v, "T_W_S": v["T_W_S"].tolist()} for v in best]
    plan = {"map": str(a.map), "views": views, "candidates": n, "anchors": anchors.tolist(),
            "limits": {"max_roll_deg": a.max_roll_deg, "max_tilt_deg": a.max_tilt_deg,
                       "max_yaw_deg": a.max_yaw_deg, "radius_m": a.radius_m},
            "unknown_weight": a.unknown_weight, "seed": a.seed, "rebuilt_confidence": rebuilt,
            "note": "each gain is against the saved map; take the first view, map it, plan again"}
    a.out.parent.mkdir(parents=True, exist_ok=True)
    from gpumap.atomic import atomic_write

    with atomic_write(a.out) as f:
        f.write(json.dumps(plan, indent=1).encode())
    print(f"{'view':>4s} {'x':>7s} {'y':>7s} {'z':>7s} {'yaw':>6s} {'pitch':>6s} {'roll':>6s} {'gain':>8s}")
    for i, v in enumerate(views):
        T = np.asarray(v["T_W_S"])
        yaw, pitch, roll = ypr_deg(T)
        print(f"{i + 1:4d} {T[0, 3]:7.3f} {T[1, 3]:7.3f} {T[2, 3]:7.3f} {yaw:6.1f} {pitch:6.1f} {roll:6.1f} "
              f"{v['gain']:8.0f}")
    print(f"gpumap plan: {n} candidates around {len(anchors)} poses; wrote {a.out}", file=sys.stderr)
    return 0
