"""``gpumap replay``: stream a recording through the min-max mapper and write what it built.

Usage::

    gpumap replay PATH [--voxel-size 0.05] [--backend auto] [--method gather] [--out DIR]
                       [--grid auto|xmin,ymin,zmin,xmax,ymax,zmax] [--threshold 0.4|auto]
                       [--static] [--stride N] [--max-frames N] [--vfov-deg D]
                       [--flip-lr] [--flip-ud] [--no-pictures]

Writes into ``--out`` (default ``replay_out/``): ``map.npz`` (``MinMaxMapper.save``),
``occupied.ply`` (occupied voxel centres with their value as ``intensity``), ``views.png``
(3-D render from three viewpoints), ``floor_slice.png`` (horizontal slice through the
densest low layer: the floor) and ``summary.json``; prints images/s.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from gpumap.spec import GridSpec, SonarSpec

__all__ = ["auto_grid", "main", "otsu_threshold", "run_replay"]


def auto_grid(spec: SonarSpec, poses: Sequence[np.ndarray], voxel_size_m: float,
              max_voxels: int = 200_000_000) -> GridSpec:
    """The box holding every field of view of ``spec`` at ``poses``, padded by one voxel.

    Parameters
    ----------
    spec : SonarSpec
    poses : sequence of (4, 4) float
        ``T_W_S`` of every ping.
    voxel_size_m : float
    max_voxels : int
        Refuse boxes larger than this (the message says which ``--grid`` to pass instead).
    """
    c = spec.fov_corners_S()
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    for T in poses:
        w = c @ np.asarray(T)[:3, :3].T + np.asarray(T)[:3, 3]
        lo = np.minimum(lo, w.min(0))
        hi = np.maximum(hi, w.max(0))
    lo -= voxel_size_m
    hi += voxel_size_m
    n = np.ceil((hi - lo) / voxel_size_m)
    if float(np.prod(n)) > max_voxels:
        raise ValueError(
            f"Expected an automatic grid of at most {max_voxels} voxels, but the fields of view "
            f"span {np.round(lo, 2).tolist()}..{np.round(hi, 2).tolist()} m = {n.astype(int).tolist()}"
            f" voxels at {voxel_size_m} m: pass --grid or a larger --voxel-size"
        )
    return GridSpec(tuple(lo), tuple(hi), voxel_size_m)


def otsu_threshold(values: np.ndarray, bins: int = 256) -> float:
    """Otsu's threshold of the finite values in ``values`` (in [0, 1])."""
    v = values[np.isfinite(values)]
    if v.size == 0:
        return 0.5
    h, e = np.histogram(v, bins=bins, range=(0.0, 1.0))
    p = h.astype(np.float64) / h.sum()
    mids = 0.5 * (e[1:] + e[:-1])
    w0 = np.cumsum(p)
    m0 = np.cumsum(p * mids)
    mt = m0[-1]
    with np.errstate(divide="ignore", invalid="ignore"):
        sb = (mt * w0 - m0) ** 2 / (w0 * (1 - w0))
    sb[~np.isfinite(sb)] = -1
    return float(e[int(np.argmax(sb)) + 1])


def run_replay(
    recording,
    *,
    voxel_size_m: float = 0.05,
    backend: str = "auto",
    method: str = "gather",
    grid: GridSpec | None = None,
    static: bool = False,
    stride: int = 1,
    max_frames: int | None = None,
    progress: bool = True,
    mapper_cls=None,
) -> tuple[object, dict]:
    """Integrate every posed frame of ``recording``; return ``(mapper, stats)``.

    Parameters
    ----------
    recording : gpumap.io.Recording
    voxel_size_m : float
        Used for the automatic grid when ``grid`` is None.
    static : bool
        Map every frame at the identity pose (recordings without poses).
    stride, max_frames : int
        Use every ``stride``-th frame, at most ``max_frames`` of them.
    mapper_cls : type, optional
        Defaults to :class:`gpumap.MinMaxMapper`.

    Returns
    -------
    mapper : MinMaxMapper
    stats : dict
        ``frames`` integrated, ``skipped_no_pose``, ``skipped_spec``, ``seconds_setup``
        (creating the mapper), ``seconds_total`` (read + convert + integrate, after
        setup), ``seconds_integrate``, ``images_per_s`` (total) and
        ``integrate_per_s``, ``backend``.
    """
    from tqdm import tqdm

    if mapper_cls is None:
        from gpumap import MinMaxMapper as mapper_cls  # noqa: N813
    if not recording.has_poses and not static:
        raise ValueError(
            f"Expected a recording with sonar poses, but {recording.path} ({recording.kind}) has "
            "none: mapping needs a pose per ping. Pass --static to map every ping at one fixed "
            "pose (identity)."
        )
    stride = max(1, int(stride))
    eye = np.eye(4)

    def selected():
        k = 0
        for i, fr in enumerate(recording):
            if i % stride:
                continue
            if max_frames is not None and k >= max_frames:
                return
            k += 1
            yield fr

    if grid is None:  # size the box from the poses: from the index if cheap, else one pass
        poses, spec0 = [], None
        cheap = None if static else recording.poses()
        if cheap is not None:
            sel = cheap[::stride][:max_frames]
            poses = [T for T in sel if T is not None]
            spec0 = next(iter(recording)).spec
        for fr in ([] if cheap is not None else selected()):
            spec0 = spec0 or fr.spec
            if static:
                poses = [eye]
                break
            if fr.T_W_S is not None and fr.spec == spec0:
                poses.append(fr.T_W_S)
        if spec0 is None or not poses:
            raise ValueError(f"Expected at least one posed frame in {recording.path}, but got none")
        grid = auto_grid(spec0, poses, voxel_size_m)

    total = recording.count()
    if total is not None:
        total = min(math.ceil(total / stride), max_frames or total)
    mapper = None
    stats = {"frames": 0, "skipped_no_pose": 0, "skipped_spec": 0}
    t_int = 0.0
    t0 = time.perf_counter()
    t_setup = 0.0
    for fr in tqdm(selected(), total=total, unit="img", disable=not progress, desc="replay"):
        if mapper is None:  # backend start-up (imports, compiling kernels) is timed apart
            ts = time.perf_counter()
            mapper = mapper_cls(fr.spec, grid, backend=backend, method=method)
            t_setup = time.perf_counter() - ts
        if fr.spec != mapper.spec:
            stats["skipped_spec"] += 1
            continue
        T = eye if static else fr.T_W_S
        if T is None:
            stats["skipped_no_pose"] += 1
            continue
        t1 = time.perf_counter()
        mapper.integrate(fr.image, T)
        t_int += time.perf_counter() - t1
        stats["frames"] += 1
    if mapper is None:
        raise ValueError(f"Expected frames in {recording.path}, but it has none")
    t1 = time.perf_counter()
    if hasattr(mapper, "synchronize"):
        mapper.synchronize()
    t_end = time.perf_counter()
    t_int += t_end - t1
    n = stats["frames"]
    t_total = t_end - t0 - t_setup
    stats.update(
        seconds_setup=t_setup,
        seconds_total=t_total,
        seconds_integrate=t_int,
        images_per_s=n / t_total if n else 0.0,
        integrate_per_s=n / t_int if n and t_int > 0 else 0.0,
        backend=mapper.backend,
        grid=grid.to_dict(),
        grid_shape=list(grid.shape),
    )
    return mapper, stats


def _parse_grid(text: str, voxel: float) -> GridSpec | None:
    if text == "auto":
        return None
    try:
        v = [float(x) for x in text.split(",")]
    except ValueError:
        v = []
    if len(v) != 6:
        raise ValueError(f"Expected --grid auto or xmin,ymin,zmin,xmax,ymax,zmax, but got {text!r}")
    return GridSpec(tuple(v[:3]), tuple(v[3:]), voxel)


def save_pictures(values: np.ndarray, grid: GridSpec, threshold: float, out: Path,
                  title: str = "") -> dict:
    """Write ``views.png`` (occupied voxels from three viewpoints) and ``floor_slice.png``.

    Returns
    -------
    dict
        ``floor_z_m`` (height of the slice) and the file names.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    occ = np.isfinite(values) & (values >= threshold)
    idx = np.argwhere(occ)
    pts = grid.centers(idx)
    val = values[occ]
    if pts.shape[0] > 60_000:  # keep the render light: strongest voxels first
        keep = np.argsort(val)[-60_000:]
        pts, val = pts[keep], val[keep]
    fig = plt.figure(figsize=(12, 4.2), dpi=80)
    views = [(25, -60, "oblique"), (89, -90, "top (x right, y up)"), (0, -90, "side (x-z)")]
    for k, (elev, azim, name) in enumerate(views):
        ax = fig.add_subplot(1, 3, k + 1, projection="3d")
        ax.scatter(pts[:, 0], pts[:, 1], pts[:, 2], c=val, s=1.5, cmap="viridis",
                   vmin=threshold, vmax=1.0, depthshade=False, linewidths=0)
        ax.view_init(elev=elev, azim=azim)
        ax.set_title(name, fontsize=9)
        ax.set_xlabel("x [m]", fontsize=7)
        ax.set_ylabel("y [m]", fontsize=7)
        ax.set_zlabel("z [m]", fontsize=7)
        ax.tick_params(labelsize=6)
        lo, hi = np.asarray(grid.min_corner_m), np.asarray(grid.max_corner_m)
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
        ax.set_zlim(lo[2], hi[2])
        ax.set_box_aspect(tuple(hi - lo))
    fig.suptitle(f"{title}  occupied voxels (value >= {threshold:.2f}): {occ.sum()}", fontsize=10)
    fig.tight_layout()
    fig.savefig(out / "views.png")
    plt.close(fig)

    # floor: the horizontal layer with the most occupied voxels in the lower half of the box
    counts = occ.sum(axis=(0, 1))
    nz = values.shape[2]
    k_floor = int(np.argmax(counts[: max(1, nz // 2)])) if counts.any() else nz // 4
    z = grid.min_corner_m[2] + (k_floor + 0.5) * grid.voxel_size_m
    fig, ax = plt.subplots(figsize=(5.5, 4.5), dpi=80)
    sl = values[:, :, k_floor].T
    cmap = matplotlib.colormaps["magma"].with_extremes(bad="#3060a0")
    lo, hi = grid.min_corner_m, grid.max_corner_m
    im = ax.imshow(sl, origin="lower", cmap=cmap, vmin=0, vmax=1,
                   extent=(lo[0], lo[0] + values.shape[0] * grid.voxel_size_m,
                           lo[1], lo[1] + values.shape[1] * grid.voxel_size_m))
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(f"slice z = {z:.3f} m (blue = never observed)", fontsize=9)
    fig.colorbar(im, ax=ax, label="min-max value")
    fig.tight_layout()
    fig.savefig(out / "floor_slice.png")
    plt.close(fig)
    del hi
    return {"floor_z_m": z, "pictures": ["views.png", "floor_slice.png"]}


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``gpumap replay``; returns the process exit status."""
    ap = argparse.ArgumentParser(prog="gpumap replay", description=__doc__.splitlines()[0])
    ap.add_argument("path", help="recording: Oculus .raw/.oculus, ARIS .aris, fan folder, ROS bag")
    ap.add_argument("--voxel-size", type=float, default=0.05, help="metres (default 0.05)")
    ap.add_argument("--backend", default="auto")
    ap.add_argument("--method", default="gather", choices=["gather", "template"])
    ap.add_argument("--out", default="replay_out", help="output folder (default replay_out)")
    ap.add_argument("--grid", default="auto", help="auto or xmin,ymin,zmin,xmax,ymax,zmax (m)")
    ap.add_argument("--threshold", default="0.4",
                    help="occupied if value >= this (default 0.4; on the OASIS tank views agree "
                         "above it); 'auto' = Otsu over observed voxels")
    ap.add_argument("--static", action="store_true",
                    help="map every ping at one fixed (identity) pose: for pose-less recordings")
    ap.add_argument("--stride", type=int, default=1, help="use every N-th frame")
    ap.add_argument("--max-frames", type=int, default=None)
    ap.add_argument("--vfov-deg", type=float, default=None, help="vertical aperture override")
    ap.add_argument("--flip-lr", action="store_true", help="fan folders: mirror columns")
    ap.add_argument("--flip-ud", action="store_true", help="fan folders: mirror rows")
    ap.add_argument("--no-pictures", action="store_true")
    ap.add_argument("--quiet", action="store_true", help="no progress bar")
    a = ap.parse_args(argv)

    from gpumap.io import FormatError, open_recording

    kwargs: dict = {}
    try:
        p = Path(a.path)
        if a.flip_lr or a.flip_ud or (a.vfov_deg is not None and p.is_dir()
                                      and not (p / "metadata.yaml").exists()):
            from gpumap.io.fan import OASIS_SPEC, FanGeometry

            kwargs["geom"] = FanGeometry(flip_lr=a.flip_lr, flip_ud=a.flip_ud)
            if a.vfov_deg is not None:
                kwargs["spec"] = SonarSpec(OASIS_SPEC.range_min_m, OASIS_SPEC.range_max_m,
                                           OASIS_SPEC.n_bins, OASIS_SPEC.bearings_rad,
                                           math.radians(a.vfov_deg))
        elif a.vfov_deg is not None:
            kwargs["vfov_deg"] = a.vfov_deg
        stride = a.stride
        if p.is_dir() and not (p / "metadata.yaml").exists():
            kwargs["stride"] = stride  # the fan reader skips pictures without decoding them
            stride = 1
        rec = open_recording(a.path, **kwargs)
        grid = _parse_grid(a.grid, a.voxel_size)
        mapper, stats = run_replay(rec, voxel_size_m=a.voxel_size, backend=a.backend,
                                   method=a.method, grid=grid, static=a.static, stride=stride,
                                   max_frames=a.max_frames, progress=not a.quiet)
    except (ValueError, FileNotFoundError) as e:  # FormatError is a ValueError
        kind = "format error" if isinstance(e, FormatError) else "error"
        print(f"gpumap replay: {kind}: {e}", file=sys.stderr)
        return 2
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    values = mapper.values()
    thr = otsu_threshold(values) if a.threshold == "auto" else float(a.threshold)
    mapper.save(out / "map.npz")
    occ = np.isfinite(values) & (values >= thr)
    from gpumap.io.ply import write_ply

    write_ply(out / "occupied.ply", mapper.grid.centers(np.argwhere(occ)), values[occ])
    stats["threshold"] = thr
    stats["occupied_voxels"] = int(occ.sum())
    stats["observed_voxels"] = int(np.isfinite(values).sum())
    if not a.no_pictures:
        stats.update(save_pictures(values, mapper.grid, thr, out, title=Path(a.path).name))
    (out / "summary.json").write_text(json.dumps(stats, indent=2))
    print(f"gpumap replay: {stats['frames']} images on {stats['backend']} in "
          f"{stats['seconds_total']:.2f} s: {stats['images_per_s']:.1f} images/s overall "
          f"(read + convert + integrate), {stats['integrate_per_s']:.1f} images/s counting only "
          f"the time spent in integrate() (device kernels overlap the reading); "
          f"grid {tuple(stats['grid_shape'])} at {mapper.grid.voxel_size_m} m; "
          f"{stats['occupied_voxels']} occupied (>= {thr:.3f}) of {stats['observed_voxels']} "
          f"observed voxels; wrote {out}/")
    if stats["skipped_no_pose"] or stats["skipped_spec"]:
        print(f"gpumap replay: skipped {stats['skipped_no_pose']} frames without a pose and "
              f"{stats['skipped_spec']} whose sonar geometry differs from the first",
              file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
