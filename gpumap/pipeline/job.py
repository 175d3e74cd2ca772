"""A replay as one typed job: a recording in, the output set out (what ``gpumap replay`` runs).

:class:`ReplayJob` holds every option of a replay, checked and typed (the command turns its flags
into one; a script makes one directly); :func:`run_job` opens the recording (the reader and its
options from :mod:`gpumap.io`), maps it through the one pipeline (:func:`gpumap.pipeline.replay.run_replay`,
or N mappers merged: :mod:`gpumap.pipeline.workers`, :mod:`gpumap.pipeline.gpu_threads`; or the EKF's
poses: :mod:`gpumap.pipeline.ekf_replay`), and writes the output set with one writer
(:func:`write_outputs`): ``map.npz``, ``surface.npz`` (the surface layer, when asked for),
``occupied.ply``, the pictures and ``summary.json``, replacing an earlier run's as one set.
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gpumap.io.pictures import save_pictures
from gpumap.io.ply import write_ply
from gpumap.spec import GridSpec

__all__ = ["EKF_OUTPUTS", "OUTPUTS", "EKFOptions", "ReplayJob", "run_ekf_job", "run_job", "write_outputs"]

#: Every file a replay can write into its output folder: one run's set replaces the last one's.
OUTPUTS = ("map.npz", "surface.npz", "occupied.ply", "views.png", "floor_slice.png", "rules.png",
           "summary.json")
#: Files the EKF replay writes besides those.
EKF_OUTPUTS = ("ekf_paths.png", "ekf_measurements.png")
#: What a memory refusal tells a replay's user to change.
REMEDY = "use a larger --voxel-size or a smaller --grid"


@dataclass(frozen=True)
class EKFOptions:
    """The EKF replay's options: odometry made from the recorded poses with drift of
    ``odometry_noise`` (per-step standard deviation per translation axis, m, and per rotation axis,
    rad), seeded by ``seed``; ``registration``: scans registered against the pings they revisit."""

    odometry_noise: tuple[float, float] = (0.005, 0.005)
    seed: int = 0
    registration: bool = False


@dataclass(frozen=True)
class ReplayJob:
    """Every option of one replay (``gpumap replay``'s flags, typed).

    ``threshold``: the occupied intensity the map is read at, in (0, 1], also the mapper's bright
    threshold; ``"auto"``: Otsu over the observed voxels (known only after the run: the mapper then
    uses :data:`gpumap.pipeline.replay.DEFAULT_THRESHOLD`). ``frames``: the recording's frames
    START:STOP:STEP before ``stride`` and ``max_frames``. ``workers``: N mappers merged (``in_process``:
    a thread per GPU of this process; else N Dask workers, on ``scheduler``'s cluster if given).
    ``ekf``: map with the EKF's poses (:class:`EKFOptions`) instead of the recorded ones.
    """

    path: Path
    out: Path
    voxel_size_m: float = 0.05
    backend: str = "auto"
    method: str = "gather"
    rule: str | None = None
    threshold: float | str = 0.4
    grid: GridSpec | None = None
    static: bool = False
    frames: slice | None = None
    stride: int = 1
    max_frames: int | None = None
    vfov_deg: float | None = None
    skip_bad_frames: bool = False
    surface: bool = False
    pictures: bool = True
    progress: bool = True
    workers: int | None = None
    scheduler: str | None = None
    in_process: bool = False
    ekf: EKFOptions | None = None
    layers: Sequence = field(default=(), compare=False)

    @property
    def mapper_threshold(self) -> float:
        from gpumap.pipeline.replay import DEFAULT_THRESHOLD

        return DEFAULT_THRESHOLD if self.threshold == "auto" else float(self.threshold)


def _open(job: ReplayJob, bad: list[str]):
    """The job's recording (its frames selected) and the stride still to apply."""
    from gpumap.io import open_recording, reader_options
    from gpumap.pipeline.replay import select_frames

    kwargs, stride = reader_options(job.path, vfov_deg=job.vfov_deg, stride=job.stride,
                                    on_bad=(lambda e: bad.append(str(e))) if job.skip_bad_frames else None,
                                    reader_stride=job.frames is None)
    rec = open_recording(job.path, **kwargs)
    if job.frames is not None:
        rec = select_frames(rec, job.frames)
    return rec, stride


def run_job(job: ReplayJob) -> tuple[dict, object]:
    """Map ``job``'s recording and write its output set into ``job.out``; ``(summary, mapper)``.

    ``job.ekf`` must be None (:func:`run_ekf_job` maps with the EKF's poses). ``job.layers`` (e.g. a
    live view) are attached to the mapper before the first ping (one process
    only). Raises ``ValueError`` (a :class:`gpumap.io.FormatError` among them) on bad input, before
    anything is written.
    """
    if job.ekf is not None:
        raise ValueError("Expected a job without EKF options for run_job, but it has them: run_ekf_job maps "
                         "with the EKF's poses")
    from gpumap.layers.surface_live import LiveSurface
    from gpumap.pipeline.replay import run_replay

    bad: list[str] = []
    rec, stride = _open(job, bad)
    rule = job.rule or ("evidence" if job.method == "gather" else "plain")
    kw = dict(voxel_size_m=job.voxel_size_m, backend=job.backend, method=job.method, static=job.static,
              stride=stride, max_frames=job.max_frames, progress=job.progress,
              threshold=job.mapper_threshold, grid=job.grid, rule=job.rule)
    positions: list = []
    surface = LiveSurface() if job.surface and not job.workers and rule == "evidence" else None
    if job.workers and job.in_process:  # N GPUs of this machine: a thread and a mapper each
        from gpumap.pipeline.gpu_threads import run_replay_threads

        mapper, stats = run_replay_threads(rec, workers=job.workers, positions=positions, **kw)
    elif job.workers:  # N Dask workers, each holding its own map, merged
        from gpumap.pipeline.workers import run_replay_workers

        mapper, stats = run_replay_workers(rec, workers=job.workers, scheduler=job.scheduler,
                                           positions=positions, **kw)
    else:
        layers = [*job.layers, *([surface] if surface is not None else [])]
        mapper, stats = run_replay(rec, positions=positions, layers=layers, memory_remedy=REMEDY, **kw)
    if job.skip_bad_frames:
        bad = list(dict.fromkeys(bad))  # a frame the grid's sizing pass read too is counted once
        stats["skipped_bad_frames"] = len(bad)
        stats["bad_frames"] = bad[:100]  # the first hundred errors, each naming its file
    layer = None
    if surface is not None and stats["frames"]:
        layer, stats["surface"] = _surface_summary(surface)
    elif job.surface:
        stats["surface"] = {"skipped": "the surface layer is built on the evidence rule's map from one "
                                       "process (not --workers, --rule evidence)"}
    write_outputs(job, mapper, stats, positions=np.asarray(positions).reshape(-1, 3) if positions else None,
                  surface=layer)
    return stats, mapper


def write_outputs(job: ReplayJob, mapper, stats: dict, *, positions: np.ndarray | None = None,
                  surface=None, values: np.ndarray | None = None, extra=None,
                  names: Sequence[str] = OUTPUTS) -> None:
    """The one writer of a replay's output set into ``job.out`` (all files appear together, or none):
    the map, the surface layer (``surface``), the occupied voxels as PLY, the pictures (``job.pictures``;
    ``positions``: the sonar's path drawn on them) and ``stats`` as ``summary.json``, to which the
    threshold and the voxel counts are added. ``extra(out)`` writes more files (of ``names``) first."""
    from gpumap.atomic import output_set
    from gpumap.pipeline.replay import otsu_threshold

    values = mapper.values() if values is None else values
    thr = otsu_threshold(values) if job.threshold == "auto" else float(job.threshold)
    occ = np.isfinite(values) & (values >= thr)
    stats["threshold"] = thr
    stats["occupied_voxels"] = int(occ.sum())
    stats["observed_voxels"] = int(np.isfinite(values).sum())
    with output_set(job.out, names) as out:
        mapper.save(out / "map.npz")
        if surface is not None:
            surface.save(out / "surface.npz", values, mapper.spec, float(mapper.threshold), "evidence")
        write_ply(out / "occupied.ply", mapper.grid.centers(np.argwhere(occ)), values[occ])
        if job.pictures:
            label = "EKF poses" if job.ekf is not None else f"{stats['rule']} rule"
            stats.update(
                save_pictures(
                    values,
                    mapper.grid,
                    thr,
                    out,
                    title=f"{Path(job.path).name} ({label})",
                    positions=positions,
                )
            )
        if extra is not None:
            extra(out)
        (out / "summary.json").write_text(json.dumps(stats, indent=2))


def _surface_summary(live) -> tuple:
    """(the surface layer of every ping :class:`~gpumap.layers.surface_live.LiveSurface` kept, its
    summary block)."""
    t0 = time.perf_counter()
    layer = live.update()
    t_update = time.perf_counter() - t0
    skip = ("candidates", "surface", "pings", "seconds", "warm", "pairs")
    return layer, {"seconds": live.seconds_add + t_update, "seconds_during_mapping": live.seconds_add,
                   "seconds_after_mapping": t_update, "pings": layer.stats["pings"],
                   "candidates": layer.stats["candidates"], "surface_voxels": int(layer.surface.sum()),
                   "pairs": layer.stats.get("pairs"),
                   "options": {k: v for k, v in layer.stats.items() if k not in skip}}


def run_ekf_job(job: ReplayJob) -> tuple[dict, object]:
    """The EKF replay of ``job`` (``job.ekf``: odometry made from the recorded poses with drift, the EKF
    on the pings, three maps: recorded, odometry and EKF poses) and its output set, the EKF's map as
    ``map.npz``; ``(summary, the EKF's mapper)``."""
    from gpumap.pipeline.ekf_replay import measurements_picture, paths_picture, run_ekf_replay

    if job.static:
        raise ValueError("Expected a recording with poses for --ekf (they are its reference), but got "
                         "--static")
    if job.layers:
        raise ValueError("Expected --ekf alone (it makes three maps of its own), but got it with --view "
                         "or --record")
    e = job.ekf
    if e is None:
        raise ValueError("Expected a job with EKF options (ReplayJob(ekf=EKFOptions(...))), but it has none")
    rec, stride = _open(job, [])
    thr = job.mapper_threshold
    t0 = time.perf_counter()
    res = run_ekf_replay(
        rec,
        odometry_noise=tuple(e.odometry_noise),
        seed=e.seed,
        voxel_size_m=job.voxel_size_m,
        grid=job.grid,
        backend=job.backend,
        threshold=thr,
        rule=job.rule,
        stride=stride,
        max_frames=job.max_frames,
        progress=job.progress,
        registration=e.registration,
    )
    mapper = res["maps"]["ekf"]
    s = res["summary"]
    stats = {"frames": s["frames"], "backend": mapper.backend, "rule": mapper.rule,
             "seconds_total": time.perf_counter() - t0, "grid": res["grid"].to_dict(),
             "grid_shape": list(res["grid"].shape), "skipped_no_pose": 0, "skipped_spec": 0, "ekf": s}
    stats["images_per_s"] = stats["frames"] / stats["seconds_total"]
    stats["integrate_per_s"] = stats["frames"] / max(s["ms_per_ping"]["map_seconds"]["ekf"], 1e-9)

    def extra(out: Path) -> None:
        if job.pictures:
            paths_picture(res, out / "ekf_paths.png", title=Path(job.path).name)
            stats["ekf"]["measurements_picture_ping"] = measurements_picture(
                res, out / "ekf_measurements.png"
            )

    # read at the mapper's threshold (no Otsu: the three maps are compared at one threshold)
    write_outputs(
        dataclasses.replace(job, threshold=thr),
        mapper,
        stats,
        positions=res["loop"].poses[:, :3, 3],
        values=res["values"]["ekf"],
        extra=extra,
        names=(*OUTPUTS, *EKF_OUTPUTS),
    )
    return stats, mapper
