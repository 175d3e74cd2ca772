"""Map a recording: stream its pings through the min-max mapper (:func:`run_replay`), and
compare the rules on the same frames (:func:`replay_rules`, :func:`compare_rules`).

The library under ``gpumap replay`` (:mod:`gpumap.commands.replay`, which writes ``map.npz``,
``occupied.ply``, the pictures and ``summary.json``). ``rule`` picks how views combine
(``MinMaxMapper``'s ``rule``); the mapper counts a view as bright from ``threshold`` on.
:func:`run_rule_comparison` replays the same frames under every rule and says where the maps
differ (and draws ``rules.png``).
"""

from __future__ import annotations

import itertools
import math
import time
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np

from gpumap.core.params import MapperParams
from gpumap.geometry import RULES as GEOMETRY_RULES
from gpumap.spec import GridSpec, SonarSpec, auto_grid

__all__ = [
    "DEFAULT_THRESHOLD",
    "RULES",
    "auto_grid",
    "compare_rules",
    "otsu_threshold",
    "replay_rules",
    "run_replay",
    "run_rule_comparison",
    "grid_of_frames",
    "select_frames",
    "select_strided",
    "selected_poses",
]

#: Occupied intensity of ``gpumap replay`` (on the OASIS tank views agree above it); also the
#: mapper's bright threshold when the reading threshold is only known after the run (Otsu).
DEFAULT_THRESHOLD = 0.4
#: The mapper's rules, in the order the comparison shows them.
RULES = GEOMETRY_RULES


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
    rule: str | None = None,
    threshold: float = DEFAULT_THRESHOLD,
    positions: list | None = None,
    layers: Sequence = (),
    max_memory: int | None = None,
    maps_held: int = 1,
    memory_remedy: str | None = None,
) -> tuple[object, dict]:
    """Integrate every posed frame of ``recording``; return ``(mapper, stats)``.

    The frames are read and decoded on a thread of their own (:func:`gpumap.core.feed.prefetch`)
    while the mapper maps the ones before, and go to it in batches (:func:`gpumap.core.feed.feed`).

    Parameters
    ----------
    recording : gpumap.io.Recording
    voxel_size_m : float
        Used for the automatic grid when ``grid`` is None.
    backend : str
        The mapper's backend (``"auto"``: the fastest that works).
    method, rule, threshold
        The map's options (:class:`~gpumap.core.params.MapperParams`): ``rule`` None is the
        method's default (evidence for gather, plain for template); ``threshold`` the bright
        threshold (default :data:`DEFAULT_THRESHOLD`, at which ``gpumap replay`` reads the map).
    static : bool
        Map every frame at the identity pose (recordings without poses).
    stride, max_frames : int
        Use every ``stride``-th frame, at most ``max_frames`` of them.
    mapper_cls : type, optional
        Defaults to :class:`gpumap.MinMaxMapper`; called as ``mapper_cls(spec, grid, backend, params)``.
    positions : list, optional
        When given, the world position (3,) of every integrated ping is appended to it.
    layers : sequence of Layer
        Attached to the mapper once it is made (:meth:`gpumap.MinMaxMapper.attach`), before the
        first ping: the live view, the surface layer, ...; their time counts in ``seconds_total``.
    max_memory : int, optional
        Bytes the run may take at its peak (None: 90 % of the memory available). Checked with
        :func:`gpumap.memory.check_run_fits` before the mapper allocates the grid: a grid that
        would not fit raises :class:`~gpumap.backends.GridTooLargeError` (a ``ValueError``)
        saying how much it needs.
    maps_held : int
        Maps of this grid held at once, this one included (``replay_rules`` holds every rule's).
    memory_remedy : str, optional
        What the memory error tells the user to change (a command names its flags).

    Returns
    -------
    mapper : MinMaxMapper
    stats : dict
        ``frames`` integrated, ``skipped_no_pose``, ``skipped_spec``, ``seconds_setup``
        (creating the mapper), ``seconds_total`` (read + convert + integrate, after
        setup), ``seconds_integrate`` (inside the mapper's calls, the layers included),
        ``images_per_s`` (total) and ``integrate_per_s``, ``backend``, ``rule``,
        ``mapper_threshold``, ``grid``, ``grid_shape``.
    """
    from tqdm import tqdm

    from gpumap.core.feed import feed, prefetch

    if mapper_cls is None:
        from gpumap import MinMaxMapper as mapper_cls  # noqa: N813
    params = MapperParams(method=method, rule=rule, threshold=threshold)
    if not recording.has_poses and not static:
        note = getattr(recording, "pose_note", None)
        if note:  # poses that came, but not one per picture: --static would map them all at one pose
            raise ValueError(f"Expected a sonar pose for every ping of {recording.path}, but {note}")
        raise ValueError(
            f"Expected a recording with sonar poses, but {recording.path} ({recording.kind}) has "
            "none: mapping needs a pose per ping. Pass --static to map every ping at one fixed "
            "pose (identity)."
        )
    stride = max(1, int(stride))
    if grid is None:  # size the box from the poses: from the index if cheap, else one pass
        grid = grid_of_frames(recording, static=static, stride=stride, max_frames=max_frames,
                              voxel_size_m=voxel_size_m)
    from gpumap.memory import API_REMEDY, check_run_fits

    check_run_fits(grid.n_voxels, params.rule, backend, max_memory, maps=maps_held,
                   remedy=memory_remedy or API_REMEDY)

    total = recording.count()
    if total is not None:
        total = min(math.ceil(total / stride), max_frames or total)
    stats = {"frames": 0, "skipped_no_pose": 0, "skipped_spec": 0}
    eye = np.eye(4)
    frames = tqdm(prefetch(select_strided(recording, stride, max_frames)), total=total, unit="img",
                  disable=not progress, desc="replay")
    t0 = time.perf_counter()
    it = iter(frames)
    first = next(it, None)
    if first is None:
        frames.close()
        raise ValueError(f"Expected frames in {recording.path}, but it has none")
    ts = time.perf_counter()  # backend start-up (imports, compiling kernels) is timed apart
    mapper = mapper_cls(first.spec, grid, backend, params)
    for layer in layers:
        mapper.attach(layer)
    t_setup = time.perf_counter() - ts

    def posed() -> Iterator[tuple[np.ndarray, np.ndarray]]:
        for fr in itertools.chain([first], it):
            if fr.spec != mapper.spec:
                stats["skipped_spec"] += 1
                continue
            T = eye if static else fr.T_W_S
            if T is None:
                stats["skipped_no_pose"] += 1
                continue
            stats["frames"] += 1
            if positions is not None:
                positions.append(np.asarray(T, dtype=np.float64)[:3, 3].copy())
            yield fr.image, T

    fed = feed(mapper, posed(), batch=REPLAY_BATCH)
    frames.close()
    t1 = time.perf_counter()
    mapper.synchronize()
    t_end = time.perf_counter()
    n = stats["frames"]
    t_int = fed.seconds_integrate + (t_end - t1)
    t_total = t_end - t0 - t_setup
    stats.update(
        seconds_setup=t_setup,
        seconds_total=t_total,
        seconds_integrate=t_int,
        images_per_s=n / t_total if n else 0.0,
        integrate_per_s=n / t_int if n and t_int > 0 else 0.0,
        backend=mapper.backend,
        rule=mapper.rule,
        mapper_threshold=float(mapper.threshold),
        grid=grid.to_dict(),
        grid_shape=list(grid.shape),
    )
    return mapper, stats


#: Frames per ``integrate_batch`` call of :func:`run_replay`.
REPLAY_BATCH = 32


def replay_rules(recording, *, rules: Sequence[str] = RULES, grid: GridSpec | None = None,
                 positions: list | None = None, **kwargs) -> dict[str, tuple[object, dict]]:
    """Replay ``recording`` once per rule in ``rules``, on one grid; ``{rule: (mapper, stats)}``.

    ``kwargs`` go to :func:`run_replay` (``threshold`` included: every rule's mapper gets the
    same bright threshold). The recording is read once per rule, so no frames are held in
    memory; the first run sizes the grid (unless ``grid`` is given) and fills ``positions``.
    """
    out: dict[str, tuple[object, dict]] = {}
    for rule in rules:
        mapper, stats = run_replay(recording, grid=grid, rule=rule,
                                   maps_held=len(out) + 1, positions=positions if not out else None,
                                   **kwargs)
        grid = mapper.grid
        out[rule] = (mapper, stats)
    return out


def _quantiles(x: np.ndarray, q=(10, 50, 90)) -> list[float] | None:
    return [round(float(v), 3) for v in np.percentile(x, q)] if x.size else None


def compare_rules(values: dict[str, np.ndarray], grid: GridSpec, threshold: float,
                  positions: np.ndarray | None = None, picture: Path | None = None,
                  title: str = "", rule: str | None = None) -> dict:
    """Compare the map of the paper's plain rule with that of ``rule``, read at ``threshold``.

    Parameters
    ----------
    values : dict
        ``{"plain": values, rule: values, ...}``, the ``MinMaxMapper.values()`` of the same
        frames on the same grid (NaN = never observed), for ``"plain"`` and one or more of the
        other rules (each gets its counts under ``rules``).
    grid : GridSpec
    threshold : float
        Occupied if value >= this.
    positions : (P, 3) float, optional
        Sonar positions (world), for the range of the differing voxels from the sonar.
    picture : Path, optional
        Where to write the side-by-side picture (PNG).
    rule : str, optional
        The rule compared with plain in detail (default ``"evidence"`` when given, else
        ``"visible"``).

    Returns
    -------
    dict
        ``threshold``; ``rule`` (the one compared); ``rules`` (per rule given:
        ``occupied_voxels``, ``observed_voxels``); ``observed_equal`` (both rules observe the
        same voxels, as they should); ``occupied_both``; ``rule_only`` (occupied under
        ``rule``, free under plain: the plain rule carved them, as a dark view in their acoustic
        shadow or at grazing incidence does) and ``plain_only`` (the reverse: always 0, see
        next); ``rule_ge_plain`` (every observed voxel's value under ``rule`` >= its plain
        value: the visible and evidence rules' value is either the min over all views, the
        plain value, or the dimmest bright view, which is no lower; so plain-occupied implies
        occupied under either at any reading threshold);
        ``where``: quantiles (10/50/90 %) and histograms of the range from the nearest sonar
        position and of the height, for the voxels only visible calls occupied and for those
        both call occupied, the plain values of the former, the floor height and the
        fractions of each group below, at (+-0.25 m) and above the floor; ``text``, a
        sentence on where the differences lie; ``picture`` (file name) when written.
    """
    if rule is None:
        rule = "evidence" if "evidence" in values else "visible"
    if "plain" not in values or rule not in values or rule == "plain":
        raise ValueError(f"Expected the plain rule's values and those of another rule ({rule!r}), "
                         f"but got rules {sorted(values)}")
    vp, vv = values["plain"], values[rule]
    for r, v in values.items():
        if v.shape != grid.shape:
            raise ValueError(f"Expected maps of shape {grid.shape}, but the {r} rule's is {v.shape}")
    thr = float(threshold)
    obs = {r: np.isfinite(v) for r, v in values.items()}
    occ = {r: obs[r] & (values[r] >= np.float32(thr)) for r in values}
    both_obs = obs["plain"] & obs[rule]
    vis_only = occ[rule] & ~occ["plain"]
    plain_only = occ["plain"] & ~occ[rule]
    both = occ["plain"] & occ[rule]
    res: dict = {
        "threshold": thr,
        "rule": rule,
        "rules": {r: {"occupied_voxels": int(occ[r].sum()), "observed_voxels": int(obs[r].sum())}
                  for r in RULES if r in values},
        "observed_equal": bool(np.array_equal(obs["plain"], obs[rule])),
        "occupied_both": int(both.sum()),
        "rule_only": int(vis_only.sum()),
        "plain_only": int(plain_only.sum()),
        "rule_ge_plain": bool(np.all(vv[both_obs] >= vp[both_obs])),
    }

    # where the differences lie: range from the nearest sonar position, height
    pts = {k: grid.centers(np.argwhere(m)) for k, m in
           (("rule_only", vis_only), ("plain_only", plain_only), ("both", both))}
    where: dict = {}
    dist: dict[str, np.ndarray] = {}
    if positions is not None and len(positions):
        from scipy.spatial import cKDTree

        tree = cKDTree(np.asarray(positions, dtype=np.float64).reshape(-1, 3))
        dist = {k: tree.query(p)[0] if len(p) else np.zeros(0) for k, p in pts.items()}
        r_max = max(float(d.max()) for d in dist.values() if d.size) if any(
            d.size for d in dist.values()) else 1.0
        edges = np.arange(0.0, r_max + 0.25, 0.25)
        where["range_from_sonar_m"] = {k: _quantiles(d) for k, d in dist.items()}
        where["range_histogram"] = {"edges_m": [round(float(e), 3) for e in edges],
                                    **{k: np.histogram(d, edges)[0].tolist() for k, d in dist.items()}}
    z = {k: p[:, 2] for k, p in pts.items()}
    z_lo, z_hi = grid.min_corner_m[2], grid.max_corner_m[2]
    zedges = np.arange(z_lo, z_hi + 0.2, 0.2)
    where["height_m"] = {k: _quantiles(v) for k, v in z.items()}
    where["height_histogram"] = {"edges_m": [round(float(e), 3) for e in zedges],
                                 **{k: np.histogram(v, zedges)[0].tolist() for k, v in z.items()}}
    where["plain_value_of_rule_only"] = _quantiles(vp[vis_only])
    # the floor: the horizontal layer with the most voxels occupied under either rule, low half
    union = occ["plain"] | occ[rule]
    counts = union.sum(axis=(0, 1))
    nz = grid.shape[2]
    k_floor = int(np.argmax(counts[: max(1, nz // 2)]))
    floor_z = grid.min_corner_m[2] + (k_floor + 0.5) * grid.voxel_size_m
    where["floor_z_m"] = round(float(floor_z), 3)
    near = 0.25  # metres: "at the floor"
    frac = {k: {"below": float(np.mean(v < floor_z - near)),
                "at": float(np.mean(np.abs(v - floor_z) <= near)),
                "above": float(np.mean(v > floor_z + near))} if v.size else None
            for k, v in z.items()}
    where["fraction_vs_floor_0.25m"] = {
        k: ({b: round(x, 3) for b, x in f.items()} if f is not None else None) for k, f in frac.items()
    }
    if positions is not None and len(positions):
        where["sonar_height_m"] = _quantiles(np.asarray(positions)[:, 2], (0, 50, 100))
    res["where"] = where
    res["text"] = _where_text(res, where, frac)
    if picture is not None:
        _rules_picture(values, occ, vis_only, plain_only, both, dist, z, zedges, floor_z, grid,
                       thr, Path(picture), title, rule)
        res["picture"] = Path(picture).name
    return res


def _where_text(res: dict, where: dict, frac: dict) -> str:
    rule = res["rule"]
    others = ", ".join(f"{r} {c['occupied_voxels']}" for r, c in res["rules"].items())
    t = (f"occupied voxels: {others}; {res['rule_only']} occupied only under "
         f"{rule} (plain carved them), {res['plain_only']} only under plain; observed voxels "
         f"{'identical' if res['observed_equal'] else 'DIFFER'} "
         f"({res['rules'][rule]['observed_voxels']}).")
    if not res["rule_only"]:
        return t
    pv = where["plain_value_of_rule_only"]
    t += f" Plain lowered those to a median {pv[1]:.2f} (10-90 %: {pv[0]:.2f}-{pv[2]:.2f})."
    r = where.get("range_from_sonar_m")
    if r and r["both"]:
        t += (f" They lie {r['rule_only'][1]:.2f} m (median; 10-90 %: {r['rule_only'][0]:.2f}"
              f"-{r['rule_only'][2]:.2f}) from the nearest sonar position, against "
              f"{r['both'][1]:.2f} m for voxels both rules keep.")
    h = where["height_m"]
    if h["both"]:
        fv, fb = frac["rule_only"], frac["both"]
        t += (f" Heights: median z {h['rule_only'][1]:.2f} m against {h['both'][1]:.2f} m; "
              f"relative to the floor (z {where['floor_z_m']:.2f} m, +-0.25 m): {fv['below']:.0%} "
              f"below, {fv['at']:.0%} at, {fv['above']:.0%} above it, against {fb['below']:.0%}, "
              f"{fb['at']:.0%}, {fb['above']:.0%} of the voxels both keep.")
    return t


def _rules_picture(values, occ, vis_only, plain_only, both, dist, z, zedges, floor_z, grid, thr,
                   path: Path, title: str, rule: str = "visible") -> None:
    """Plain and ``rule``'s maps from one viewpoint, one colour scale; their difference; histograms."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    union = occ["plain"] | occ[rule]
    idx_u = np.argwhere(union)
    if idx_u.size:  # frame the occupied voxels of either map (one box for every panel)
        lo = grid.centers(idx_u.min(0)) - grid.voxel_size_m
        hi = grid.centers(idx_u.max(0)) + grid.voxel_size_m
    else:
        lo, hi = np.asarray(grid.min_corner_m), np.asarray(grid.max_corner_m)
    rng = np.random.default_rng(0)

    def cloud(mask, cap=50_000):
        idx = np.argwhere(mask)
        if len(idx) > cap:  # thin uniformly (same seed for every panel)
            idx = idx[np.sort(rng.choice(len(idx), cap, replace=False))]
        return idx

    fig = plt.figure(figsize=(15, 7.6), dpi=80)
    gs = fig.add_gridspec(2, 4, width_ratios=(1, 1, 1, 0.85), hspace=0.12, wspace=0.05)
    views = [(28, -60, "oblique"), (89.9, -90, "top")]
    sc = None
    for row, (elev, azim, vname) in enumerate(views):
        for col, name in enumerate(("plain", rule, "difference")):
            ax = fig.add_subplot(gs[row, col], projection="3d")
            if name in values:
                idx = cloud(occ[name])
                p = grid.centers(idx)
                v = values[name][tuple(idx.T)]
                sc = ax.scatter(p[:, 0], p[:, 1], p[:, 2], c=v, s=1.2, cmap="viridis", vmin=thr,
                                vmax=1.0, depthshade=False, linewidths=0)
                head = f"{name}: {int(occ[name].sum())} occupied"
            else:
                # one scatter, so that matplotlib sorts every group's points by depth together
                kinds = ((both, "#9a9a9a", "both"), (vis_only, "#d62728", f"{rule} only"),
                         (plain_only, "#1f77b4", "plain only"))
                idx = [cloud(m) for m, _, _ in kinds]
                p = grid.centers(np.concatenate(idx)) if sum(map(len, idx)) else np.zeros((0, 3))
                col = np.concatenate([np.repeat([matplotlib.colors.to_rgba(c)], len(i), 0)
                                      for i, (_, c, _) in zip(idx, kinds, strict=True)])
                ax.scatter(p[:, 0], p[:, 1], p[:, 2], c=col, s=1.2, depthshade=False, linewidths=0)
                head = "difference"
                if row == 0:
                    for m, c, lab in kinds:
                        ax.scatter([], [], [], c=c, s=1.2, label=f"{lab} ({int(m.sum())})")
                    ax.legend(loc="upper left", fontsize=7, markerscale=6, frameon=False)
            ax.view_init(elev=elev, azim=azim)
            ax.set_title(f"{head} ({vname})", fontsize=9)
            for lab, setter in (("x", ax.set_xlabel), ("y", ax.set_ylabel), ("z", ax.set_zlabel)):
                setter(f"{lab} [m]", fontsize=7, labelpad=-2)
            ax.tick_params(labelsize=6, pad=0)
            ax.set_xlim(lo[0], hi[0])
            ax.set_ylim(lo[1], hi[1])
            ax.set_zlim(lo[2], hi[2])
            ax.set_box_aspect(tuple(hi - lo))
            if row == 1:
                ax.set_zticks([])
                ax.set_zlabel("")
    if sc is not None:
        cax = fig.add_axes((0.05, 0.08, 0.012, 0.35))
        fig.colorbar(sc, cax=cax, label="min-max value")
        cax.yaxis.set_label_position("left")
        cax.yaxis.tick_left()

    groups = (("both", "0.55"), ("rule_only", "#d62728"), ("plain_only", "#1f77b4"))
    ax = fig.add_subplot(gs[0, 3])
    if dist:
        edges = np.arange(0.0, max(float(d.max()) for d in dist.values() if d.size) + 0.1, 0.1) \
            if any(d.size for d in dist.values()) else np.arange(0, 1.1, 0.1)
        for k, colour in groups:
            if dist[k].size:
                ax.hist(dist[k], edges, histtype="step", color=colour, lw=1.5,
                        label=k.replace("rule", rule).replace("_", " "))
        ax.set_xlabel("range from the nearest sonar position [m]", fontsize=8)
        ax.legend(fontsize=7, frameon=False)
    ax.set_ylabel("occupied voxels", fontsize=8)
    ax.yaxis.tick_right()
    ax.yaxis.set_label_position("right")
    ax.tick_params(labelsize=7)
    ax = fig.add_subplot(gs[1, 3])
    for k, colour in groups:
        if z[k].size:
            ax.hist(z[k], zedges, histtype="step", color=colour, lw=1.5, orientation="horizontal",
                    label=k.replace("rule", rule).replace("_", " "))
    ax.axhline(floor_z, color="k", ls=":", lw=1, label=f"floor (z {floor_z:.2f} m)")
    ax.legend(fontsize=7, frameon=False, loc="upper right")
    ax.set_ylabel("height z [m]", fontsize=8)
    ax.yaxis.tick_right()
    ax.yaxis.set_label_position("right")
    ax.set_xlabel("occupied voxels", fontsize=8)
    ax.tick_params(labelsize=7)
    fig.suptitle(f"{title}  plain vs {rule} rule, occupied = value >= {thr:.2f}, "
                 f"{grid.voxel_size_m * 100:g} cm voxels", fontsize=11)
    fig.subplots_adjust(left=0.07, right=0.955, top=0.93, bottom=0.06)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)


def run_rule_comparison(recording, *, threshold: float = DEFAULT_THRESHOLD, rule: str = "evidence",
                        picture: str | Path | None = None, title: str = "",
                        **kwargs) -> tuple[dict[str, tuple[object, dict]], dict]:
    """Replay ``recording`` under every rule (mapper threshold = ``threshold``) and compare ``rule``
    with the others (:func:`compare_rules`: ``rule`` beside the plain rule, and where they differ).

    ``kwargs`` go to :func:`run_replay`; ``rule`` is mapped first (it sizes the grid). Returns
    ``({rule: (mapper, stats)}, comparison)``, the comparison as :func:`compare_rules` gives it with
    ``runs`` (each rule's frames, backend and rates) added.
    """
    positions: list = []
    order = (rule, *[r for r in RULES if r != rule])
    runs = replay_rules(recording, rules=order, threshold=threshold, positions=positions, **kwargs)
    grid = runs[rule][0].grid
    values = {r: m.values() for r, (m, _) in runs.items()}
    cmp_ = compare_rules(values, grid, threshold, np.asarray(positions).reshape(-1, 3),
                         None if picture is None else Path(picture), title=title,
                         rule=None if rule == "plain" else rule)
    cmp_["runs"] = {r: {k: st[k] for k in ("frames", "backend", "seconds_total", "images_per_s",
                                           "integrate_per_s")} for r, (_, st) in runs.items()}
    return runs, cmp_


def select_strided(recording, stride: int = 1, max_frames: int | None = None) -> Iterator:
    """The frames :func:`run_replay` reads of ``recording``: every ``stride``-th, at most
    ``max_frames`` of them (before any is skipped for a missing pose or another sonar geometry)."""
    k = 0
    for i, fr in enumerate(recording):
        if i % stride:
            continue
        if max_frames is not None and k >= max_frames:
            return
        k += 1
        yield fr


def selected_poses(recording, stride: int = 1,
                   max_frames: int | None = None) -> tuple[SonarSpec | None, list]:
    """(the first frame's sonar, ``T_W_S`` or None of every frame :func:`select_strided` selects, in
    order): from the recording's cheap pose list when it has one, else from one pass over the
    frames (frames of another sonar than the first count as None); (None, []) for no frame."""
    cheap = recording.poses()
    if cheap is not None:
        return next(iter(recording)).spec, list(cheap[::stride][:max_frames])
    poses, spec0 = [], None
    for fr in select_strided(recording, stride, max_frames):
        spec0 = spec0 or fr.spec
        poses.append(fr.T_W_S if fr.spec == spec0 else None)
    return spec0, poses


def grid_of_frames(recording, *, static: bool, stride: int, max_frames: int | None,
                   voxel_size_m: float, selected: tuple | None = None) -> GridSpec:
    """The grid :func:`run_replay` maps on when it is given none: the box of the selected frames'
    fields of view (:func:`gpumap.spec.auto_grid`; ``static``: the first frame's at the identity).
    ``selected``: :func:`selected_poses`' result where the caller has it already."""
    if static:
        first = next(iter(recording), None)
        spec0, posed = (None, []) if first is None else (first.spec, [np.eye(4)])
    else:
        spec0, sel = selected or selected_poses(recording, stride, max_frames)
        posed = [T for T in sel if T is not None]
    if spec0 is None or not posed:
        raise ValueError(f"Expected at least one posed frame in {recording.path}, but got none")
    return auto_grid(spec0, posed, voxel_size_m)


def select_frames(recording, frames: slice):
    """The frames of ``recording`` whose indices are in ``frames`` (``slice(start, stop, step)``,
    start and stop >= 0), as a :class:`~gpumap.io.Recording` (``gpumap replay --frames``)."""
    from gpumap.io.frame import Recording

    rec = recording
    n = rec.count()
    if n is not None and len(range(n)[frames]) == 0:
        stop = "" if frames.stop is None else frames.stop
        raise ValueError(f"Expected --frames to pick some of the {n} frames of {rec.path}, but "
                         f"{frames.start or 0}:{stop} picks none (frames are counted from 0)")
    return Recording(
        rec.path, rec.kind, lambda: itertools.islice(iter(rec), frames.start, frames.stop, frames.step),
        rec.has_poses,
        count=None if n is None else lambda: len(range(rec.count())[frames]),
        poses=None if rec._poses is None else lambda: list(rec.poses())[frames],
        pose_note=getattr(rec, "pose_note", None),
    )
