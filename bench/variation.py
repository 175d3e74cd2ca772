"""``python -m bench variation``: how much a surface voxel's views vary, real tank against simulator.

Writes ``bench/results/variation_real.json`` and ``.png``; ``--fit``: ``variation_fit.json``;
``--held-out``: ``variation_held_out.json``. ~3 min on 2 cores (bench/README.md tells more).
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from gpumap.core.params import MapperParams

from . import common
from .common import CpuShare, Section, bench_parser, mark_load, oasis_full_dir, progress_bar, quantize

SCHEMA = "gpumap-variation/1"
REAL_THRESHOLD = 0.4
VOXEL_M = 0.05
MIN_VIEWS = 10
#: ``--fit`` candidates: changes to :meth:`SonarVariation.real_tank` (each scored on the simulated sweep
#: at every ``--fit-seeds`` seed). The preset came from rounds of this over about 200 candidates (the
#: surface texture's size and depth, the gain's spread and correlation, looks, gain offset, range loss,
#: dropouts); these are its neighbours (the preset itself first), and the earlier preset (``EARLIER``).
EARLIER: dict[str, float] = {
    "gain_offset_db": -17.0, "looks": 1.0, "gain_sigma_db": 6.0, "gain_correlation": 0.97,
    "dropout_prob": 0.02, "surface_texture_db": 0.0, "range_loss_db_per_m": 0.0}
FIT_CANDIDATES: list[dict[str, float]] = [
    {}, {"looks": 8.0}, {"looks": 2.0}, {"gain_sigma_db": 3.0}, {"gain_sigma_db": 4.0},
    {"surface_texture_db": 6.0}, {"surface_texture_db": 6.0, "gain_sigma_db": 3.0},
    {"surface_texture_m": 0.04}, {"surface_texture_db": 0.0},
    {"gain_offset_db": -20.0}, {"gain_offset_db": -16.0}, {"range_loss_db_per_m": 8.0},
    {"gain_correlation": 0.97}, {"dropout_prob": 0.02}, EARLIER]
FIT_SEEDS = (0, 1, 2)


def _surface(spec, grid, images, poses, keys, threshold: float, backend: str) -> np.ndarray:
    """Voxels occupied in the visible rule's map of pings ``keys``."""
    import gpumap

    m = gpumap.MinMaxMapper(spec, grid, backend, MapperParams(rule="visible", threshold=threshold))
    for k in keys:
        m.integrate(images[k], poses[k])
    m.synchronize()
    v = m.values()
    return np.isfinite(v) & (v >= threshold)


def _stats(spec, grid, idx, normals, threshold, images, poses, keys, progress: bool, desc: str):
    """:class:`VariationStats` of the voxels ``idx`` over the uint8 pings ``keys``."""
    from gpumap.sim.variation import VariationStats

    st = VariationStats(spec, grid, idx, normals, threshold)
    for k in progress_bar(keys, disable=not progress, desc=desc):
        st.add(images[k].astype(np.float32) / 255.0, poses[k])
    return st


def measure_real(data: Path, frames: tuple[int, int], map_stride: int, backend: str, progress: bool) -> dict:
    """The real recording's figures (frames ``[frames[0], frames[1])``)."""
    from gpumap.sim.variation import surface_normals

    import gpumap.io
    from gpumap.spec import auto_grid

    rec = gpumap.io.open_recording(data)
    poses, (lo, hi) = rec.poses(), frames
    sel = [i for i in range(lo, hi) if poses[i] is not None]
    spec = next(iter(rec)).spec
    grid = auto_grid(spec, [poses[i] for i in sel[::map_stride]], VOXEL_M)
    images: dict[int, np.ndarray] = {}
    t0 = time.perf_counter()
    for i, fr in enumerate(progress_bar(rec, total=hi, disable=not progress, desc="read")):
        if i >= hi:
            break
        if i in sel:
            images[i] = np.round(np.asarray(fr.image) * 255.0).astype(np.uint8)
    read_s = time.perf_counter() - t0
    surf = _surface(spec, grid, images, poses, sel[::map_stride], REAL_THRESHOLD, backend)
    idx = np.argwhere(surf)
    normals, flat = surface_normals(surf, idx)
    t0 = time.perf_counter()
    out = _stats(spec, grid, idx, normals, REAL_THRESHOLD, images, poses, sel, progress,
                 "score real").summary(
        MIN_VIEWS)
    out.update(frames=[lo, hi], map_frames=len(sel[::map_stride]), map_rule="visible",
               map_threshold=REAL_THRESHOLD, voxel_size_m=VOXEL_M, grid_shape=list(grid.shape),
               flatness_median=float(np.nanmedian(flat)), read_s=read_s, score_s=time.perf_counter() - t0)
    return out


def measure_sim(n_pings: int, variation: Any, seed: int, backend: str, progress: bool) -> dict:
    """The tank swept at the sonar's rate (uint8 pings), scored as the real run is (simulator threshold)."""
    from gpumap.sim.scenes import long_run_scene
    from gpumap.sim.sonar import OCCUPIED_THRESHOLD as THR
    from gpumap.sim.sonar import SonarSimulator
    from gpumap.sim.truth import detected_points, occupancy, points_to_voxels
    from gpumap.sim.variation import surface_normals

    scene = long_run_scene("tank", n_pings, VOXEL_M, seed=seed)
    grid, truth, images = scene.grid, occupancy(scene, seed=seed), []
    det = np.zeros(grid.n_voxels, bool)
    t0 = time.perf_counter()
    with SonarSimulator(scene, seed=seed, variation=variation, **scene.sonar_params) as sim:
        for k in progress_bar(range(n_pings), disable=not progress, desc="simulate"):
            p = sim.ping(scene.T_W_S[k], k)
            images.append(quantize(p.image))
            det[points_to_voxels(detected_points(p, THR), grid)] = True
    sim_s = time.perf_counter() - t0
    surf = truth.surface & det.reshape(grid.shape)
    mapped = _surface(scene.sonar_spec, grid, images, scene.T_W_S, range(0, n_pings, 10), THR, backend)
    mapped &= truth.surface
    idx = np.argwhere(surf | mapped)
    normals, _ = surface_normals(truth.surface, idx)
    st = _stats(scene.sonar_spec, grid, idx, normals, THR, images, scene.T_W_S, range(n_pings), progress,
                "score sim")
    out, det = (st.summary(MIN_VIEWS, subset=m[tuple(idx.T)]) for m in (mapped, surf))
    out["detectable_selected"] = {k: det[k] for k in ("surface_voxels", "bright_share",
                                                      "bright_share_all_observed_views")}
    out.update(pings=n_pings, voxel_size_m=VOXEL_M,
               surface="truth surface voxels occupied in the visible rule's map of every 10th ping (as the "
                       "real surface is chosen); detectable_selected: truth surface voxels some ping's "
                       "noise-free image (at the variation's median gain) shows bright", sim_s=sim_s)
    return out


def quantile_distance(a: dict, b: dict) -> float:
    """Mean absolute difference of the bright-share quantiles 10/25/50/75/90 of two measurements,
    over both shares (of the clear views, of every view observing the voxel)."""
    return float(np.mean([abs(a[key]["quantiles"][k] - b[key]["quantiles"][k])
                          for key in ("bright_share",
                                      "bright_share_all_observed_views") for k in a[key]["quantiles"]]))


def _pooled_distance(a: dict, b: dict, key: str) -> float:
    """Mean absolute difference of the pooled bright fractions of two measurements over the bins of
    ``key`` (``by_range`` or ``by_incidence``) that both have views in."""
    d = [abs(x["pooled_bright"] - y["pooled_bright"]) for x, y in zip(a[key], b[key], strict=True)
         if x["pooled_bright"] is not None and y["pooled_bright"] is not None
         and np.isfinite(x["pooled_bright"]) and np.isfinite(y["pooled_bright"])]
    return float(np.mean(d)) if d else float("nan")


def compare(real: dict, sim: dict) -> dict:
    """How far a simulated measurement is from the real one: the headline figures
    (:func:`gpumap.sim.variation.headline`) as sim / real ratios, the bright-share quantile distance
    and the pooled bright fractions' distances by range and incidence; ``score`` (what ``--fit``
    minimises) is ``|ln ratio|`` of both headline figures plus the three distances."""
    from gpumap.sim.variation import headline

    hr, hs = headline(real), headline(sim)
    ratio = {k: hs[k] / hr[k] for k in hr}
    out = {"ratio": ratio, "within_20pct": {k: bool(abs(v - 1.0) <= 0.2) for k, v in ratio.items()},
           "quantile_distance": quantile_distance(real, sim),
           "by_range_distance": _pooled_distance(real, sim, "by_range"),
           "by_incidence_distance": _pooled_distance(real, sim, "by_incidence")}
    logs = [abs(float(np.log(v))) if v > 0 else float("inf") for v in ratio.values()]
    out["score"] = float(sum(logs) + out["quantile_distance"] + out["by_range_distance"]
                         + out["by_incidence_distance"])
    return out


def _fit_one(args: tuple) -> dict:
    """One candidate at one seed (a worker of ``--fit``)."""
    cand, seed, n_pings, backend = args
    from gpumap.sim.variation import REAL_TANK, SonarVariation

    return measure_sim(n_pings, SonarVariation(**{**REAL_TANK, **cand}), seed, backend, False)


def side_by_side(real: dict, sims: dict[str, dict]) -> dict:
    """Real and simulated bright-share quantiles, and pooled bright fractions by range / incidence."""
    out: dict[str, Any] = {"bright_share_quantiles": {"real": real["bright_share"]["quantiles"], **{
        f"sim_{name}": s["bright_share"]["quantiles"] for name, s in sims.items()}}}
    for key, label in (("by_range", "range_m"), ("by_incidence", "incidence_deg")):
        rows = []
        for b, row in enumerate(real[key]):
            r = {label: row[label], "real": row["pooled_bright"], "real_views": row["views"]}
            for name, s in sims.items():
                r |= {f"sim_{name}": s[key][b]["pooled_bright"], f"sim_{name}_views": s[key][b]["views"]}
            rows.append(r)
        out[f"pooled_bright_{key}"] = rows
    sim_persistence = {f"sim_{n}": s["persistence"] for n, s in sims.items()}
    out["persistence"] = {"real": real["persistence"], **sim_persistence}
    from gpumap.sim.variation import headline

    out["headline"] = {"real": headline(real), **{f"sim_{n}": headline(s) for n, s in sims.items()}}
    out["compare"] = {f"sim_{n}": compare(real, s) for n, s in sims.items()}
    return out


def plot(path: Path, real: dict, sims: dict[str, dict]) -> None:
    """Histogram of the per-voxel bright share, and the pooled bright fraction by range and incidence."""
    fig, ax = common.pyplot().subplots(1, 4, figsize=(20, 4.2))
    series = {"real tank (frames 0-799)": real, **{f"sim, {n}": s for n, s in sims.items()}}
    for (name, d), st in zip(series.items(), ["k-", "C0--", "C1-", "C2:", "C3-."], strict=False):
        for a, key in ((ax[0], "bright_share"), (ax[1], "bright_share_all_observed_views")):
            h, q = d[key]["histogram"], d[key]["quantiles"]
            centres = 0.5 * (np.array(h["edges"][:-1]) + np.array(h["edges"][1:]))
            a.plot(centres, h["fraction"], st, drawstyle="steps-mid",
                   label=f"{name}: median {q['q50']:.2f}, q10 {q['q10']:.2f}")
        for a, key, label in ((ax[2], "by_range", "range_m"), (ax[3], "by_incidence", "incidence_deg")):
            x = [0.5 * (r[label][0] + r[label][1]) for r in d[key]]
            a.plot(x, [r["pooled_bright"] for r in d[key]], st + "o" if st[-1] != "o" else st, label=name)
    ax[0].set(xlabel="share of a surface voxel's clear views that are bright", ylabel="fraction of voxels",
              title="per-voxel bright share")
    ax[1].set(xlabel="share of all the views observing a surface voxel that are bright",
              ylabel="fraction of voxels", title="per-voxel bright share, shadowed views too")
    ax[2].set(xlabel="range (m)", ylabel="bright views / clear views", title="by range", ylim=(0, 1))
    ax[3].set(xlabel="incidence (deg from the normal)", ylabel="bright views / clear views",
              title="by incidence", ylim=(0, 1))
    for a in (ax[0], ax[1], ax[3]):
        a.legend(fontsize=7)
    common.save_figure(fig, path, dpi=110)


def markdown(res: dict, folder: Path) -> str:
    """The BENCHMARKS.md section of a ``variation_real.json``: real against simulated, side by side."""
    sbs = res["side_by_side"]
    q, per, head = sbs["bright_share_quantiles"], sbs["persistence"], sbs.get("headline", {})
    names = {"real": "real, frames 0-799", "sim_real_tank": "simulator, real_tank",
             "sim_none": "simulator, none"}
    cmp = sbs.get("compare", {})
    distances = "; ".join(
        f"{k.removeprefix('sim_')}: quantiles {c['quantile_distance']:.3f}, "
        f"by range {c['by_range_distance']:.3f}, by incidence {c['by_incidence_distance']:.3f}"
        for k, c in cmp.items()) or ", ".join(
        f"{k} {v:.3f}" for k, v in res["distance_to_real"].items())
    out = [common.template("variation", command=res["command"].strip(), res=res, distances=distances)]
    for k, label in names.items():
        if k in q:
            p, h = per.get(k, {}), head.get(k, {})
            cells = " | ".join(f"{q[k][c]:.2f}" for c in ("q10", "q25", "q50", "q75", "q90"))
            out.append(f"| {label} | {cells} | {p.get('p_bright_after_bright', float('nan')):.2f} | "
                       f"{p.get('p_dark_after_dark', float('nan')):.2f} | "
                       f"{common.fnum(h.get('per_ping_spread'), '.2f')} | "
                       f"{common.fnum(h.get('persistence'), '.2f')} |")
    out += ["", f"![bright share, real and simulated]({folder.as_posix()}/variation_real.png)"]
    return "\n".join(out)


SECTION = Section("variation", "## How real views vary, and the simulator beside them (issue #28)",
                  "variation_real.json", markdown)


def main(argv: list[str] | None = None) -> int:
    ap = bench_parser("variation", __doc__, out="bench/results", backend="auto", seed=0, progress=True,
                      report="variation_real.json")
    ap.add_argument("--data", type=Path, default=None, help="the full-rate oasis_tank_full folder")
    ap.add_argument("--frames", type=int, nargs=2, default=(0, 800), metavar=("FIRST", "END"),
                    help="real frames [FIRST, END) (default 0 800; 800-1222 are held out, never tuned on)")
    ap.add_argument("--sim-pings", type=int, default=200,
                    help="simulated pings of the tank sweep (default 200)")
    ap.add_argument("--fit", action="store_true",
                    help="score the candidate variations (FIT_CANDIDATES) instead; writes variation_fit.json")
    ap.add_argument("--fit-seeds", type=int, nargs="+", default=list(FIT_SEEDS),
                    help=f"--fit: simulator seeds each candidate is scored at (default {FIT_SEEDS})")
    ap.add_argument("--jobs", type=int, default=1, help="--fit: candidates simulated at once (processes)")
    ap.add_argument("--real-from", type=Path, default=None,
                    help="--fit: take the real figures from this variation_real.json (the same frames) "
                         "instead of reading the recording")
    ap.add_argument("--held-out", action="store_true",
                    help="measure the held-out real frames 800-1222 against the simulated figures of "
                         "variation_real.json (a check: nothing is tuned on them)")
    a = ap.parse_args(argv)
    if SECTION.reported(a):
        return 0
    if a.frames[1] > 800 and not a.held_out:
        raise SystemExit("bench.variation: frames 800-1222 are held out; measure on frames below 800")
    data = a.data or oasis_full_dir()
    if data is None and a.real_from is None:
        raise SystemExit("bench.variation: oasis_tank_full (with sonar/*.png) not found; pass --data")
    if a.real_from is not None and not a.fit:
        raise SystemExit("bench.variation: --real-from goes with --fit")
    from gpumap.sim.variation import REAL_TANK, SonarVariation

    import gpumap.io

    progress, head, t_start = not a.no_progress, common.run_header(SCHEMA, argv), time.perf_counter()
    head["command"] = "python -m bench variation " + " ".join(argv or [])
    prev = json.loads((a.out / "variation_real.json").read_text()) if a.held_out else None
    frames = (800, gpumap.io.open_recording(data).count()) if a.held_out else tuple(a.frames)
    with CpuShare() as share:
        if a.real_from is not None:
            real = json.loads(a.real_from.read_text())["real"]
            if tuple(real["frames"]) != frames:
                raise SystemExit(f"bench.variation: {a.real_from} holds frames {real['frames']}, "
                                 f"not {list(frames)}")
        else:
            real = measure_real(data, frames, 10, a.backend, progress)
        sims: dict[str, dict] = {}
        for name, var in () if a.fit or a.held_out else (("none", SonarVariation.none()),
                                                         ("real_tank", SonarVariation.real_tank())):
            sims[name] = measure_sim(a.sim_pings, var, a.seed, a.backend,
                                     progress) | {"variation": var.to_dict()}
        rows = []
        if a.fit:
            jobs = [(cand, seed, a.sim_pings, a.backend) for cand in FIT_CANDIDATES for seed in a.fit_seeds]
            if a.jobs > 1:
                import multiprocessing

                with multiprocessing.get_context("spawn").Pool(a.jobs) as pool:
                    sims_fit = pool.map(_fit_one, jobs)
            else:
                sims_fit = [_fit_one(j) for j in progress_bar(jobs, disable=not progress, desc="fit")]
            from gpumap.sim.variation import headline

            k = len(a.fit_seeds)
            for i, cand in enumerate(FIT_CANDIDATES):
                per_seed = sims_fit[i * k:(i + 1) * k]
                cmps = [compare(real, s) for s in per_seed]
                rows.append({
                    "change": cand, "variation": SonarVariation(**{**REAL_TANK, **cand}).to_dict(),
                    "score": float(np.mean([c["score"] for c in cmps])),
                    "score_se": (float(np.std([c["score"] for c in cmps], ddof=1) / np.sqrt(k))
                                 if k > 1 else None),
                    "mean": {key: float(np.mean([c[key] for c in cmps])) for key in (
                        "quantile_distance", "by_range_distance", "by_incidence_distance")}
                    | {f"{h}_ratio": float(np.mean([c["ratio"][h] for c in cmps])) for h in cmps[0]["ratio"]},
                    "per_seed": [{"seed": seed, **headline(s), **c,
                                  "bright_share_quantiles": s["bright_share"]["quantiles"],
                                  "voxels_scored": s["voxels_scored"]}
                        for seed, s, c in zip(a.fit_seeds, per_seed, cmps, strict=True)]})
                se = common.fnum(rows[-1]["score_se"], ".3f")
                print(f"fit {cand}: score {rows[-1]['score']:.3f} +- {se}  " + "  ".join(
                    f"{key} {v:.3f}" for key, v in rows[-1]["mean"].items()))
    mark_load(head["machine"], share)
    shares = {k: real[k] for k in ("bright_share", "bright_share_all_observed_views")}
    if a.fit:
        best = min(rows, key=lambda r: r["score"])
        fit = {"objective": "mean over the seeds of compare()'s score: |ln(sim / real)| of the "
                            "per-ping spread and of the persistence, plus the mean |quantile difference| of "
                            "the bright share (quantiles 10/25/50/75/90 of the share of clear views and of "
                            "all observing views), plus the mean |difference| of the pooled bright fraction "
                            "by range and by incidence",
               "definitions": {
                   "per_ping_spread": "ping_gain.bright_cells_log_sd: SD over pings of ln(1 + bright "
                                      "cells in the ping's image)",
                   "persistence": "persistence.lag1_correlation: phi coefficient of a surface voxel's "
                                  "bright/dark state over consecutive views that both see it clearly, pooled "
                                  "over voxels"},
               "seeds": list(a.fit_seeds), "candidates": rows, "best": best["variation"],
               "preset_is_best": best["variation"] == SonarVariation.real_tank().to_dict()}
        from gpumap.sim.variation import headline

        res = {**head, "real": shares | {"headline": headline(real), "frames": real.get("frames")},
               "real_from": str(a.real_from) if a.real_from else None, "sim_pings": a.sim_pings, "fit": fit}
        name = "variation_fit.json"
    elif a.held_out:
        res = {**head,
               "note": "held-out frames: measured only, never tuned on; the simulated figures are those "
               "of variation_real.json (tuned on frames 0-799)", "real_held_out": {"data": str(data), **real},
               "real_tuning_frames": {k: prev["real"][k] for k in shares},
               "side_by_side": side_by_side(real, prev["sim"]),
               "distance_to_real": {n: quantile_distance(real, s) for n, s in prev["sim"].items()}}
        name = "variation_held_out.json"
    else:
        res = {**head, "real": {"data": str(data), **real}, "sim": sims,
               "side_by_side": side_by_side(real, sims),
               "distance_to_real": {n: quantile_distance(real, s) for n, s in sims.items()}}
        name = "variation_real.json"
        plot(a.out / "variation_real.png", real, sims)
    path = common.write_json(a.out / name, res | {"duration_s": time.perf_counter() - t_start}, digits=4)
    for k, v in res.get("side_by_side", {}).get("bright_share_quantiles", {}).items():
        print(f"{k:>14}: " + "  ".join(f"{kk} {vv:.2f}" for kk, vv in v.items()))
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
