"""``gpumap replay``: stream a recording through the min-max mapper and write what it built.

Usage::

    gpumap replay PATH [--voxel-size 0.05] [--backend auto] [--method gather] [--out DIR]
                       [--grid auto|xmin,ymin,zmin,xmax,ymax,zmax] [--threshold 0.4|auto]
                       [--static] [--frames A:B] [--stride N] [--max-frames N] [--vfov-deg D]
                       [--rule evidence|visible|plain] [--surface] [--no-pictures]

Writes into ``--out`` (default ``replay_out/``): ``map.npz`` (``MinMaxMapper.save``),
``surface.npz`` (``--surface``, evidence rule: the surface layer of :mod:`gpumap.layers.surface` beside
the safe map, a two-layer file ``gpumap view/export --layer surface|safe`` read),
``occupied.ply`` (occupied voxel centres with their value as ``intensity``), ``views.png``
(3-D render from three viewpoints), ``floor_slice.png`` (horizontal slice through the
densest low layer: the floor) and ``summary.json``; prints images/s.
The files are written into a temporary folder and replace an earlier run's as one set
(:func:`gpumap.atomic.output_set`): an interrupted run leaves the old set or the new one, whole.
Every flag is checked before the recording is read (bad ones exit with status 2 and one line).

``--rule`` picks how views combine (``MinMaxMapper``'s ``rule``); the mapper counts a view
as bright from ``--threshold`` on. The rules side by side on one recording:
:func:`gpumap.pipeline.replay.run_rule_comparison` (``python -m bench rules_real``).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from gpumap.commands.common import (
    BACKEND_HELP,
    METHOD_HELP,
    ArgumentParser,
    add_view_args,
    backend_name,
    check_view_args,
    error_line,
    frame_range,
    grid_box,
    nonnegative_float,
    nonnegative_int,
    output_dir,
    positive_float,
    positive_int,
    refuse_without,
    threshold_or_auto,
    user_errors,
    vfov_deg,
)
from gpumap.pipeline.job import OUTPUTS, REMEDY, EKFOptions, ReplayJob, run_ekf_job, run_job
from gpumap.pipeline.replay import (
    DEFAULT_THRESHOLD,
    RULES,
)
from gpumap.spec import GridSpec

__all__ = ["EMPTY_MAP_STATUS", "OUTPUTS", "main"]

def _parser() -> ArgumentParser:
    ap = ArgumentParser(prog="gpumap replay",
                        description="stream a recording through the min-max mapper and write what it built")
    ap.add_argument("path", help="recording: Oculus .raw/.oculus, ARIS .aris, fan folder, ROS bag, the "
                                 "OASIS tank folder (sonar/ + son_poses.pkl), a HoloOcean dataset "
                                 "(Config.json + Data/)")
    ap.add_argument("--voxel-size", type=positive_float, default=0.05, help="metres (default 0.05)")
    ap.add_argument("--backend", type=backend_name, default="auto",
                    help=BACKEND_HELP)
    ap.add_argument("--method", default="gather", choices=["gather", "template"],
                    help=METHOD_HELP)
    ap.add_argument("--out", type=output_dir, default="replay_out",
                    help="output folder (default replay_out); its files are replaced as one set")
    ap.add_argument("--grid", type=grid_box, default="auto",
                    help="auto or xmin,ymin,zmin,xmax,ymax,zmax (m); write --grid=-1,... when it "
                         "starts with a minus sign")
    ap.add_argument("--threshold", type=threshold_or_auto, default=DEFAULT_THRESHOLD,
                    help=f"occupied if value >= this, in (0, 1] (default {DEFAULT_THRESHOLD}; on the "
                         "OASIS tank views agree above it), also the mapper's bright threshold (its "
                         "'threshold': from it a view counts as bright); 'auto' = Otsu over "
                         "observed voxels, known only after the run, so the mapper then uses "
                         f"{DEFAULT_THRESHOLD}")
    ap.add_argument("--rule", default=None, choices=list(RULES),
                    help="how views combine: 'evidence' (default; occupied unless the clear views "
                         "show, at 95 %% confidence, that the voxel is bright in fewer than a fifth "
                         "of them: holds however many pings come), 'visible' (carved by 2 clear dark "
                         "views) or "
                         "'plain' (the paper's min over views: a ping carves its acoustic shadow). "
                         "--method template supports only 'plain' and defaults to it")
    ap.add_argument("--static", action="store_true",
                    help="map every ping at one fixed (identity) pose: for pose-less recordings")
    ap.add_argument("--frames", type=frame_range, default=None, metavar="START:STOP[:STEP]",
                    help="only the recording's frames START to STOP-1 (counted from 0, every STEP-th; "
                         "START or STOP may be left out), before --stride and --max-frames: split a "
                         "recording into maps of disjoint pings that gpumap merge can join")
    ap.add_argument("--skip-bad-frames", action="store_true",
                    help="fan folders, the OASIS folder, HoloOcean datasets: skip a frame that cannot be "
                         "read (truncated, corrupt) instead of stopping; each is counted in the printed line "
                         "and in summary.json")
    ap.add_argument("--stride", type=positive_int, default=1, help="use every N-th frame")
    ap.add_argument("--max-frames", type=positive_int, default=None,
                    help="stop after this many frames (after --stride); default all")
    ap.add_argument("--vfov-deg", type=vfov_deg, default=None, help="vertical aperture override")
    ap.add_argument("--no-pictures", action="store_true",
                    help="write the map and summary only, not views.png and floor_slice.png")
    ap.add_argument(
        "--surface",
        action="store_true",
        help="also compute the surface layer (gpumap.layers.surface, evidence rule only; NumPy on "
        "the host: minutes at 1 cm), written beside map.npz as surface.npz (gpumap "
        "view/export --layer surface|safe; its figures in summary.json's 'surface' block)",
    )
    ap.add_argument("--no-progress", action="store_true", help="no progress bar")
    # the old spelling, still accepted (not shown): one spelling for the same idea across commands
    ap.add_argument("--quiet", dest="no_progress", action="store_true", help=argparse.SUPPRESS)
    add_worker_args(ap)
    add_view_args(ap)
    add_ekf_args(ap)
    return ap


REPLAY_REMEDY = REMEDY


def _parse(argv: list[str] | None) -> tuple[argparse.Namespace, GridSpec | None]:
    """Parse and check every flag, alone and together, before any work; exit 2 on a bad one."""
    ap = _parser()
    a = ap.parse_args(argv)
    check_view_args(ap, a)
    check_worker_args(ap, a)
    check_ekf_args(ap, a)
    if a.frames is not None and a.ekf:
        ap.error("argument --frames: Expected it without --ekf (the EKF replay reads the whole "
                 "recording), but got both")
    if a.method == "template" and a.rule not in (None, "plain"):
        ap.error("argument --rule: Expected rule='plain' with --method template (the template "
                 f"method's duplicate points cannot count views once), but got --rule {a.rule}")
    grid = None
    if a.grid is not None:
        try:
            grid = GridSpec(a.grid[:3], a.grid[3:], a.voxel_size)
        except ValueError as e:
            ap.error(f"argument --grid: {e}")
    return a, grid


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``gpumap replay``; returns the process exit status.

    Bad flags exit with status 2 (``SystemExit``) before anything is read; bad input found
    later (an unreadable recording, no poses, a backend that cannot run, a grid that would not
    fit in memory) prints one line and returns 2. A run in which no ping observed any voxel of
    the grid writes its outputs, warns, and returns :data:`EMPTY_MAP_STATUS` (3). The outputs
    replace those in ``--out`` as one set, only once all are written.
    """
    a, grid = _parse(argv)
    a.view_sessions = []  # the live view / recording, if asked for (gpumap.viewer)
    try:
        stats, grid_out = _replay(a, grid)
    except user_errors() as e:
        for s in a.view_sessions:
            s.abort()
        print(error_line("gpumap replay", e) + _skip_hint(a, e), file=sys.stderr)
        return 2
    except BaseException:
        for s in a.view_sessions:
            s.abort()
        raise
    thr = stats["threshold"]
    if stats.get("mode") == "threads":  # gpumap.pipeline.gpu_threads: N devices of this process
        how = (f"{stats['frames']} images in-process on {stats['workers']} devices of {stats['backend']} "
               f"(one thread each, devices {stats['devices']}, {stats['split']} split) in "
               f"{stats['seconds_wall']:.2f} s wall, of which {stats['seconds_setup']:.2f} s making the "
               f"mappers and {stats['seconds_merge']:.2f} s merging the maps")
    elif stats.get("workers"):  # gpumap.pipeline.workers: say so, and the wall time with the cluster's start
        how = (f"{stats['frames']} images in {stats['workers']} Dask workers on {stats['backend']} "
               f"({stats['split']} split) in {stats['seconds_wall']:.2f} s wall, of which "
               f"{stats['seconds_cluster']:.2f} s starting the cluster and "
               f"{stats['seconds_gather'] + stats['seconds_merge']:.2f} s gathering and merging the maps")
    else:
        how = (f"{stats['frames']} images on {stats['backend']} in "
               f"{stats['seconds_total']:.2f} s: {stats['images_per_s']:.1f} images/s overall "
               f"(read + convert + integrate), {stats['integrate_per_s']:.1f} images/s counting only "
               f"the time spent in integrate() (device kernels overlap the reading)")
    print(f"gpumap replay: {how}; "
          f"grid {tuple(stats['grid_shape'])} at {grid_out.voxel_size_m} m; "
          f"{stats['occupied_voxels']} occupied (>= {thr:.3f}, {stats['rule']} rule) of "
          f"{stats['observed_voxels']} observed voxels"
          + (f"; skipped {stats['skipped_bad_frames']} unreadable frames" if stats.get("skipped_bad_frames")
             else "") + f"; wrote {a.out}/")
    if "surface_voxels" in stats.get("surface", {}):
        sf = stats["surface"]
        print(f"gpumap replay: surface layer {sf['surface_voxels']} voxels of {sf['candidates']} occupied "
              f"({sf['seconds']:.1f} s; surface.npz, gpumap view/export --layer surface|safe)")
    if stats["skipped_no_pose"] or stats["skipped_spec"]:
        print(f"gpumap replay: skipped {stats['skipped_no_pose']} frames without a pose and "
              f"{stats['skipped_spec']} whose sonar geometry differs from the first",
              file=sys.stderr)
    if stats.get("skipped_bad_frames"):
        print(f"gpumap replay: skipped {stats['skipped_bad_frames']} frames that could not be read "
              f"(--skip-bad-frames; the first: {stats['bad_frames'][0]}); summary.json lists them",
              file=sys.stderr)
    for s in a.view_sessions:
        s.serve()
    if stats["observed_voxels"] == 0:
        # the outputs are written (summary.json says what was mapped where), but an empty map is
        # almost always a --grid that misses the pings or wrong poses: a script must not carry on
        print(f"gpumap replay: warning: no ping observed any voxel of the grid "
              f"{tuple(stats['grid_shape'])} ({stats['frames']} pings mapped): check --grid against "
              f"the sonar's positions and its range (exit status {EMPTY_MAP_STATUS})", file=sys.stderr)
        return EMPTY_MAP_STATUS
    return 0


#: Exit status of ``gpumap replay`` when no ping observed any voxel of the grid (outputs written).
EMPTY_MAP_STATUS = 3


def _skip_hint(a: argparse.Namespace, e: BaseException) -> str:
    """What to add to the error of one unreadable frame of a folder: that --skip-bad-frames skips it."""
    from gpumap.io import SKIPPABLE_KINDS, FormatError, recording_kind

    where = getattr(e, "path", None)
    if a.skip_bad_frames or not isinstance(e, FormatError) or where is None or Path(where) == Path(a.path):
        return ""
    try:
        kind = recording_kind(a.path)
    except (OSError, ValueError):
        return ""
    return " (--skip-bad-frames skips frames that cannot be read)" if kind in SKIPPABLE_KINDS else ""


def _view_layer(a: argparse.Namespace, threshold: float):
    """The layer that feeds ``--view``/``--record`` (None without them): its session opens when it is
    attached to the mapper (the grid and the sonar known then)."""
    if not (getattr(a, "view", False) or getattr(a, "record", None) is not None):
        return None
    from gpumap.viewer.session import Session, SessionLayer

    def make(mapper):
        s = Session(a, mapper.spec, mapper.grid, threshold,
                    title=f"gpumap replay {Path(a.path).name} ({mapper.grid.voxel_size_m * 100:g} cm)")
        a.view_sessions.append(s)
        return s

    return SessionLayer(make)


def _job(a: argparse.Namespace, grid: GridSpec | None) -> ReplayJob:
    """The typed job of parsed flags ``a`` (the flags stop here: the library gets the job)."""
    ekf = EKFOptions(tuple(a.odometry_noise), a.seed, bool(a.ekf_registration)) if a.ekf else None
    view = _view_layer(a, DEFAULT_THRESHOLD if a.threshold == "auto" else a.threshold)
    return ReplayJob(Path(a.path), Path(a.out), voxel_size_m=a.voxel_size, backend=a.backend, method=a.method,
                     rule=a.rule, threshold=a.threshold, grid=grid, static=a.static, frames=a.frames,
                     stride=a.stride, max_frames=a.max_frames, vfov_deg=a.vfov_deg,
                     skip_bad_frames=a.skip_bad_frames, surface=a.surface, pictures=not a.no_pictures,
                     progress=not a.no_progress, workers=a.workers, scheduler=a.scheduler,
                     in_process=bool(a.workers) and _in_process(a), ekf=ekf,
                     layers=() if view is None else (view,))


def _replay(a: argparse.Namespace, grid: GridSpec | None) -> tuple[dict, GridSpec]:
    """Map the recording of parsed flags ``a``; write the output set; ``(summary, grid)``."""
    job = _job(a, grid)
    stats, mapper = run_ekf_job(job) if job.ekf is not None else run_job(job)
    for s in a.view_sessions:
        s.finish(mapper)
    if a.ekf:
        _print_ekf(stats["ekf"])
    return stats, mapper.grid


# ------------------------------------------------------------------------------ --workers
def add_worker_args(ap) -> None:
    """``--workers`` and ``--scheduler`` on ``gpumap replay``'s parser."""
    ap.add_argument("--workers", type=positive_int, default=None,
                    help="map with N mappers (pings split among them by place, in batches of 32) and "
                         "merge their maps: the same map as one process, bit for bit. On a machine "
                         "with N GPUs and a GPU backend: in this process, one thread per GPU; else "
                         "(or with --scheduler) N Dask workers (needs the workers extra: "
                         "pip install 'gpumap[workers]')")
    ap.add_argument(
        "--scheduler",
        default=None,
        help="address of a running Dask scheduler (e.g. tcp://10.0.0.5:8786) whose "
        "workers map; default: start N local worker processes (needs --workers)",
    )


#: Backends whose ``--workers N`` run on one machine of N GPUs stays in this process
# (gpumap.pipeline.gpu_threads).
IN_PROCESS_BACKENDS = ("auto", "warp-cuda", "opencl-gpu", "opencl")


def _in_process(a) -> bool:
    """Whether ``--workers N`` maps in this process, a thread per GPU: no ``--scheduler``, a GPU
    backend (or auto) and at least N GPUs here (counted without starting CUDA)."""
    if a.scheduler is not None or a.backend not in IN_PROCESS_BACKENDS:
        return False
    from gpumap.pipeline.workers import host_gpus

    return len(host_gpus()) >= a.workers


def check_worker_args(ap, a) -> None:
    """Refuse flag combinations the worker run does not support (exit 2, before any work)."""
    if a.scheduler is not None and not a.workers:
        ap.error("argument --scheduler: Expected --workers N with it, but --workers is missing")
    if a.workers:
        for flag, on in (("--view", getattr(a, "view", False)),
                         ("--record", getattr(a, "record", None) is not None),
                         ("--ekf", getattr(a, "ekf", False))):
            if on:
                ap.error(f"argument --workers: Expected no {flag} with it (the workers' maps are only "
                         f"whole once merged), but got {flag}")


# ------------------------------------------------------------------------------ --ekf
def add_ekf_args(ap: argparse.ArgumentParser) -> None:
    """The replay's EKF options."""
    ap.add_argument("--ekf", action="store_true",
                    help="run the EKF on the pings: odometry made from the recorded poses with "
                         "drift (--odometry-noise), point returns found in the images and "
                         "associated; map with the EKF's poses and compare with the recorded-pose "
                         "map (writes ekf_paths.png, ekf_measurements.png, an 'ekf' summary section)")
    ap.add_argument("--odometry-noise", type=nonnegative_float, nargs=2, default=None,
                    metavar=("TRANS_M", "ROT_RAD"),
                    help="with --ekf: standard deviation of each odometry step's error per "
                         "translation axis (metres) and per rotation axis (radians) (default "
                         "0.005 0.005, the demo's --pose-noise 0.005)")
    ap.add_argument("--seed", type=nonnegative_int, default=None,
                    help="with --ekf: seed of the odometry drift (default 0)")
    ap.add_argument("--ekf-registration", action="store_true",
                    help="with --ekf: register each ping against the pings it revisits "
                         "(gpumap.ekf.registration), each revisit verified by its image, with a pose "
                         "graph behind the filter: on the real tank about half odometry's position "
                         "error where the run revisits places, but on one run of ten it ended worse "
                         "than odometry, so it is off by default (BENCHMARKS.md, ekf_pose.json)")


def check_ekf_args(ap: argparse.ArgumentParser, a: argparse.Namespace) -> None:
    """--odometry-noise and --seed only with --ekf (exit 2, before any work); fill their defaults."""
    refuse_without(ap, "--ekf", a.ekf, {"--odometry-noise": a.odometry_noise is not None,
                                         "--seed": a.seed is not None,
                                         "--ekf-registration": bool(getattr(a, "ekf_registration", False))})
    a.odometry_noise = (0.005, 0.005) if a.odometry_noise is None else a.odometry_noise
    a.seed = 0 if a.seed is None else a.seed


def _two_decimals(v: float | None) -> str:
    return "-" if v is None else f"{v:.2f}"


def _registration_line(r: dict) -> str:
    if not r["used"]:
        return "scan registration off"
    return (f"scan registration corrected {100 * r['fused_share']:.0f} % of steps "
            f"({r['gated']} gated, {r['distrusted']} distrusted), {r['revisits_fused']} revisits fused "
            f"({r.get('revisits_unverified', 0)} refused: images disagreed)")


def _print_ekf(s: dict) -> None:
    """The EKF replay's line (its summary block ``s``)."""
    e, o = s["pose_error"]["ekf"], s["pose_error"]["odometry"]
    tr = s["trust"]
    mo, me = s["map_vs_recorded"]["odometry"], s["map_vs_recorded"]["ekf"]
    print(f"gpumap replay --ekf: position error mean {100 * o['position_m']['mean']:.1f} cm (odometry) "
          f"-> {100 * e['position_m']['mean']:.1f} cm (EKF), heading "
          f"{np.degrees(o['heading_rad']['mean']):.2f} -> {np.degrees(e['heading_rad']['mean']):.2f} deg; "
          f"map vs recorded-pose map, voxels disagreeing {mo['disagree']} (odometry) -> "
          f"{me['disagree']} (EKF); {s['tracks']['confirmed']} tracks confirmed; "
          f"trust in the pings: {tr['fused_with_pose']} returns fused with the pose, "
          f"{tr['fused_features_only']} into their features only, {tr['gated']} gated, "
          f"{100 * tr['pings_pose_corrected_share']:.0f} % of pings corrected the pose, windowed NIS per dof "
          f"{_two_decimals(tr['window_nis_per_dof']['median'])} (median); "
          f"{_registration_line(s['registration'])}; "
          f"{s['ms_per_ping']['total_mean']:.1f} ms per ping (front-end + EKF)")
