"""``python -m bench variation``: how much a surface voxel's views vary, real tank against simulator.

Real (``--data``, default the full-rate ``oasis_tank_full`` recording, frames 0-799 only: frames
800-1222 are held out): the surface voxels are those occupied (>= 0.4, the replay's threshold)
in the visible rule's map of every 10th frame at 5 cm; then every frame 0-799 is scored against
them with :class:`gpumap.sim.variation.VariationStats` (the footprint max as the mapper computes
it, per voxel and per view): the share of bright views per voxel (quantiles, histogram), by range
and by incidence (normals by PCA of the neighbouring surface voxels), the frame-to-frame
persistence of a voxel's bright/dark state and the per-ping gain.

Simulated: the tank swept at the sonar's rate (:func:`gpumap.sim.scenes.long_run_scene`, 5 cm),
pings quantized to uint8 as the Oculus delivers, scored the same way at the simulator's threshold
(0.1) against the truth's surface voxels chosen as the real ones are (occupied in the visible
rule's map of every 10th ping; those some ping could detect are reported too), once without
variation and once with :meth:`SonarVariation.real_tank`. ``--fit`` instead scores candidate
variations and
reports the one whose bright-share quantiles are nearest the real ones, in
``bench/results/variation_fit.json`` (the preset is then copied into
:data:`gpumap.sim.variation.REAL_TANK` by hand; the file says whether they agree).

Writes ``bench/results/variation_real.json`` and ``bench/results/variation_real.png``.
``--held-out`` instead measures the held-out frames 800-1222 the same way (nothing is tuned on
them) and sets them beside the simulated figures already in ``variation_real.json``:
``bench/results/variation_held_out.json``.
Takes ~3 min on 2 cores (``--fit``: ~1 min more per candidate).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from .common import CpuShare, bench_parser, mark_load, oasis_full_dir, quantize, run_header, write_json

SCHEMA = "gpumap-variation/1"
REAL_THRESHOLD = 0.4
VOXEL_M = 0.05
MIN_VIEWS = 10

#: ``--fit`` candidates: changes to :meth:`SonarVariation.real_tank` (each scored on the simulated sweep).
#: The preset came from rounds of this by hand (gain offset -14 to -20 dB, spread 4 to 7 dB, gain
#: correlation, jitter, looks); these are its neighbours (the preset itself first).
FIT_CANDIDATES: list[dict[str, float]] = [
    {},
    {"gain_correlation": 0.9},
    {"gain_offset_db": -18.0, "gain_sigma_db": 5.0},
    {"gain_offset_db": -16.0, "gain_sigma_db": 7.0},
    {"jitter_translation_m": 0.0, "jitter_rotation_rad": 0.0},
    {"looks": 2.0},
]

def measure_real(data: Path, frames: tuple[int, int], map_stride: int, backend: str,
                 progress: bool) -> tuple[dict, Any]:
    """The real recording's figures (frames ``[frames[0], frames[1])``) and its stats object."""
    from gpumap.sim.variation import VariationStats, surface_normals
    from tqdm import tqdm

    import gpumap
    import gpumap.io
    from gpumap.spec import auto_grid

    rec = gpumap.io.open_recording(data)
    poses = rec.poses()
    lo, hi = frames
    sel = [i for i in range(lo, hi) if poses[i] is not None]
    spec = next(iter(rec)).spec
    grid = auto_grid(spec, [poses[i] for i in sel[::map_stride]], VOXEL_M)
    mapper = gpumap.MinMaxMapper(spec, grid, backend=backend, rule="visible", threshold=REAL_THRESHOLD)
    images: dict[int, np.ndarray] = {}
    t0 = time.perf_counter()
    for i, fr in enumerate(tqdm(rec, total=hi, disable=not progress, desc="read")):
        if i >= hi:
            break
        if i in sel:
            images[i] = np.round(np.asarray(fr.image) * 255.0).astype(np.uint8)
    read_s = time.perf_counter() - t0
    for i in sel[::map_stride]:
        mapper.integrate(images[i], poses[i])
    mapper.synchronize()
    v = mapper.values()
    surf = np.isfinite(v) & (v >= REAL_THRESHOLD)
    idx = np.argwhere(surf)
    normals, flat = surface_normals(surf, idx)
    st = VariationStats(spec, grid, idx, normals, REAL_THRESHOLD)
    t0 = time.perf_counter()
    for i in tqdm(sel, disable=not progress, desc="score real"):
        st.add(images[i].astype(np.float32) / 255.0, poses[i])
    out = st.summary(MIN_VIEWS)
    out.update(frames=[lo, hi], map_frames=len(sel[::map_stride]), map_rule="visible",
               map_threshold=REAL_THRESHOLD, voxel_size_m=VOXEL_M, grid_shape=list(grid.shape),
               flatness_median=float(np.nanmedian(flat)), read_s=read_s, score_s=time.perf_counter() - t0)
    return out, st


def simulate_sweep(n_pings: int, variation: Any, seed: int, progress: bool) -> dict[str, Any]:
    """The tank swept at the sonar's rate: uint8 pings, poses, truth and the surface to score."""
    from gpumap.sim.scenes import long_run_scene
    from gpumap.sim.sonar import OCCUPIED_THRESHOLD, SonarSimulator
    from gpumap.sim.truth import detected_points, occupancy, points_to_voxels
    from tqdm import tqdm

    scene = long_run_scene("tank", n_pings, VOXEL_M, seed=seed)
    truth = occupancy(scene, seed=seed)
    det = np.zeros(scene.grid.n_voxels, bool)
    images = []
    t0 = time.perf_counter()
    with SonarSimulator(scene, seed=seed, variation=variation, **scene.sonar_params) as sim:
        for k in tqdm(range(n_pings), disable=not progress, desc="simulate"):
            p = sim.ping(scene.T_W_S[k], k)
            images.append(quantize(p.image))
            det[points_to_voxels(detected_points(p, OCCUPIED_THRESHOLD), scene.grid)] = True
    return {"scene": scene, "truth": truth, "images": images, "detectable": det.reshape(scene.grid.shape),
            "sim_s": time.perf_counter() - t0}


def measure_sim(run: dict[str, Any], backend: str, progress: bool) -> tuple[dict, Any]:
    """Score a :func:`simulate_sweep` run as the real one is scored (simulator threshold)."""
    from gpumap.sim.sonar import OCCUPIED_THRESHOLD
    from gpumap.sim.variation import VariationStats, surface_normals
    from tqdm import tqdm

    import gpumap

    scene, truth, images = run["scene"], run["truth"], run["images"]
    grid, spec = scene.grid, scene.sonar_spec
    surf = truth.surface & run["detectable"]
    mapper = gpumap.MinMaxMapper(spec, grid, backend=backend, rule="visible", threshold=OCCUPIED_THRESHOLD)
    for k in range(0, len(images), 10):
        mapper.integrate(images[k], scene.T_W_S[k])
    mapper.synchronize()
    v = mapper.values()
    mapped = np.isfinite(v) & (v >= OCCUPIED_THRESHOLD) & truth.surface
    union = surf | mapped
    idx = np.argwhere(union)
    normals, _ = surface_normals(truth.surface, idx)
    st = VariationStats(spec, grid, idx, normals, OCCUPIED_THRESHOLD)
    for k in tqdm(range(len(images)), disable=not progress, desc="score sim"):
        st.add(images[k].astype(np.float32) / 255.0, scene.T_W_S[k])
    out = st.summary(MIN_VIEWS, subset=mapped[tuple(idx.T)])
    det = st.summary(MIN_VIEWS, subset=surf[tuple(idx.T)])
    out["detectable_selected"] = {k: det[k] for k in ("surface_voxels", "bright_share",
                                                      "bright_share_all_observed_views")}
    out.update(pings=len(images), voxel_size_m=VOXEL_M,
               surface="truth surface voxels occupied in the visible rule's map of every 10th ping (as the "
                       "real surface is chosen); detectable_selected: truth surface voxels some ping's "
                       "noise-free image (at the variation's median gain) shows bright",
               sim_s=run["sim_s"])
    return out, st


def quantile_distance(a: dict, b: dict) -> float:
    """Mean absolute difference of the bright-share quantiles 10/25/50/75/90 of two measurements,
    over both shares (of the clear views, of every view observing the voxel)."""
    d = []
    for key in ("bright_share", "bright_share_all_observed_views"):
        qa, qb = a[key]["quantiles"], b[key]["quantiles"]
        d += [abs(qa[k] - qb[k]) for k in qa]
    return float(np.mean(d))


def side_by_side(real: dict, sims: dict[str, dict]) -> dict:
    """Real and simulated bright-share quantiles, and pooled bright fractions by range / incidence."""
    out: dict[str, Any] = {"bright_share_quantiles": {"real": real["bright_share"]["quantiles"]}}
    for name, s in sims.items():
        out["bright_share_quantiles"][f"sim_{name}"] = s["bright_share"]["quantiles"]
    for key, label in (("by_range", "range_m"), ("by_incidence", "incidence_deg")):
        rows = []
        for b, row in enumerate(real[key]):
            r = {label: row[label], "real": row["pooled_bright"], "real_views": row["views"]}
            for name, s in sims.items():
                r[f"sim_{name}"] = s[key][b]["pooled_bright"]
                r[f"sim_{name}_views"] = s[key][b]["views"]
            rows.append(r)
        out[f"pooled_bright_{key}"] = rows
    out["persistence"] = {"real": real["persistence"],
                          **{f"sim_{n}": s["persistence"] for n, s in sims.items()}}
    return out


def plot(path: Path, real: dict, sims: dict[str, dict]) -> None:
    """Histogram of the per-voxel bright share, and the pooled bright fraction by range and incidence."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 4, figsize=(20, 4.2))
    series = {"real tank (frames 0-799)": real, **{f"sim, {n}": s for n, s in sims.items()}}
    styles = ["k-", "C0--", "C1-", "C2:", "C3-."]
    for (name, d), st in zip(series.items(), styles, strict=False):
        h = d["bright_share"]["histogram"]
        centres = 0.5 * (np.array(h["edges"][:-1]) + np.array(h["edges"][1:]))
        q = d["bright_share"]["quantiles"]
        ax[0].plot(centres, h["fraction"], st, drawstyle="steps-mid",
                   label=f"{name}: median {q['q50']:.2f}, q10 {q['q10']:.2f}")
        h = d["bright_share_all_observed_views"]["histogram"]
        q = d["bright_share_all_observed_views"]["quantiles"]
        ax[1].plot(centres, h["fraction"], st, drawstyle="steps-mid",
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
    ax[0].legend(fontsize=7)
    ax[1].legend(fontsize=7)
    ax[3].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def held_out(a: Any, argv: list[str] | None) -> int:
    """``--held-out``: the real frames 800-1222, scored as frames 0-799 are, against the simulated
    figures already written to ``variation_real.json``."""
    import json

    data = a.data or oasis_full_dir()
    if data is None:
        raise SystemExit("bench.variation: oasis_tank_full (with sonar/*.png) not found; pass --data")
    prev = json.loads((a.out / "variation_real.json").read_text())
    head = run_header(SCHEMA, argv)
    t0 = time.perf_counter()
    import gpumap.io

    end = gpumap.io.open_recording(data).count()
    with CpuShare() as share:
        real, _ = measure_real(data, (800, end), 10, a.backend, not a.no_progress)
    mark_load(head["machine"], share)
    res = {**head, "command": "python -m bench variation " + " ".join(argv or []),
           "note": "held-out frames: measured only, never tuned on; the simulated figures are those of "
                   "variation_real.json (tuned on frames 0-799)",
           "real_held_out": {"data": str(data), **real},
           "real_tuning_frames": {k: prev["real"][k]
                                  for k in ("bright_share", "bright_share_all_observed_views")},
           "side_by_side": side_by_side(real, prev["sim"]),
           "distance_to_real": {n: quantile_distance(real, s) for n, s in prev["sim"].items()},
           "duration_s": time.perf_counter() - t0}
    path = write_json(a.out / "variation_held_out.json", res, digits=4)
    for k, v in res["side_by_side"]["bright_share_quantiles"].items():
        print(f"{k:>14}: " + "  ".join(f"{kk} {vv:.2f}" for kk, vv in v.items()))
    print(f"wrote {path}")
    return 0


BEGIN, END = "<!-- begin:variation -->", "<!-- end:variation -->"
SECTION = "## How real views vary, and the simulator beside them (issue #28)"


def markdown(res: dict, folder: Path) -> str:
    """The BENCHMARKS.md section of a ``variation_real.json``: real against simulated, side by side."""
    q = res["side_by_side"]["bright_share_quantiles"]
    per = res["side_by_side"]["persistence"]
    names = {"real": "real, frames 0-799", "sim_real_tank": "simulator, real_tank",
             "sim_none": "simulator, none"}
    out = [SECTION, "",
           f"`{res['command'].strip()}` ({res['created']}): per surface voxel, the share of its clear views "
           "that are bright (footprint max >= threshold), quantiles 10/25/50/75/90, and how a voxel's "
           "bright/dark state persists from one view to the next. Distance to the real quantiles: "
           + ", ".join(f"{k} {v:.3f}" for k, v in res["distance_to_real"].items()) + ".", "",
           "| | q10 | q25 | q50 | q75 | q90 | P(bright after bright) | P(dark after dark) |",
           "|---|---|---|---|---|---|---|---|"]
    for k, label in names.items():
        if k in q:
            row = q[k]
            p = per.get(k, {})
            cells = " | ".join(f"{row[c]:.2f}" for c in ("q10", "q25", "q50", "q75", "q90"))
            out.append(f"| {label} | {cells} | {p.get('p_bright_after_bright', float('nan')):.2f} | "
                       f"{p.get('p_dark_after_dark', float('nan')):.2f} |")
    out += ["", f"![bright share, real and simulated]({folder.as_posix()}/variation_real.png)"]
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    ap = bench_parser("variation", __doc__)
    ap.add_argument("--data", type=Path, default=None, help="the full-rate oasis_tank_full folder")
    ap.add_argument("--frames", type=int, nargs=2, default=(0, 800), metavar=("FIRST", "END"),
                    help="real frames [FIRST, END) (default 0 800; 800-1222 are held out, never tuned on)")
    ap.add_argument("--sim-pings", type=int, default=200,
                    help="simulated pings of the tank sweep (default 200)")
    ap.add_argument("--fit", action="store_true", help="also score the candidate variations (FIT_CANDIDATES)")
    ap.add_argument("--held-out", action="store_true",
                    help="measure the held-out real frames 800-1222 against the simulated figures of "
                         "variation_real.json (a check: nothing is tuned on them)")
    ap.add_argument("--backend", default="auto", help="gpumap backend of the surface maps (default auto)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=Path("bench/results"), help="results folder")
    ap.add_argument("--no-progress", action="store_true")
    ap.add_argument("--report", type=Path, metavar="BENCHMARKS_MD",
                    help="only write this benchmark's section of that file from --out/variation_real.json")
    a = ap.parse_args(argv)
    if a.report is not None:
        import sys

        from .common import write_section

        return write_section(a.report, a.out / "variation_real.json", sys.modules[__name__])
    if a.held_out:
        return held_out(a, argv)
    if a.frames[1] > 800:
        raise SystemExit("bench.variation: frames 800-1222 are held out; measure on frames below 800")
    data = a.data or oasis_full_dir()
    if data is None:
        raise SystemExit("bench.variation: oasis_tank_full (with sonar/*.png) not found; pass --data")
    from gpumap.sim.variation import REAL_TANK, SonarVariation

    progress = not a.no_progress
    head = run_header(SCHEMA, argv)
    t_start = time.perf_counter()
    with CpuShare() as share:
        real, _ = measure_real(data, tuple(a.frames), 10, a.backend, progress)
        sims: dict[str, dict] = {}
        for name, var in (() if a.fit else (("none", SonarVariation.none()),
                                            ("real_tank", SonarVariation.real_tank()))):
            run = simulate_sweep(a.sim_pings, var, a.seed, progress)
            sims[name], _ = measure_sim(run, a.backend, progress)
            sims[name]["variation"] = var.to_dict()
        fit = None
        if a.fit:
            rows = []
            for cand in FIT_CANDIDATES:
                var = SonarVariation(**{**REAL_TANK, **cand})
                s, _ = measure_sim(simulate_sweep(a.sim_pings, var, a.seed, progress), a.backend, progress)
                rows.append({"variation": var.to_dict(), "distance": quantile_distance(real, s),
                             "bright_share_quantiles": s["bright_share"]["quantiles"],
                             "persistence_lag1": s["persistence"].get("lag1_correlation")})
                print(f"fit {cand}: distance {rows[-1]['distance']:.3f}")
            best = min(rows, key=lambda r: r["distance"])
            fit = {"objective": "mean |quantile difference| of the bright share (of clear views and of all "
                                "observing views), quantiles 10/25/50/75/90",
                   "candidates": rows, "best": best["variation"],
                   "preset_is_best": best["variation"] == SonarVariation.real_tank().to_dict()}
    mark_load(head["machine"], share)
    if fit is not None:
        path = write_json(a.out / "variation_fit.json",
                          {**head, "command": "python -m bench variation " + " ".join(argv or []),
                           "real": {k: real[k] for k in ("bright_share", "bright_share_all_observed_views")},
                           "sim_pings": a.sim_pings, "fit": fit, "duration_s": time.perf_counter() - t_start},
                          digits=4)
        print(f"wrote {path}")
        return 0
    res = {**head,
           "command": "python -m bench variation " + " ".join(argv or []),
           "real": {"data": str(data), **real},
           "sim": sims,
           "side_by_side": side_by_side(real, sims),
           "distance_to_real": {n: quantile_distance(real, s) for n, s in sims.items()},
           "duration_s": time.perf_counter() - t_start}
    a.out.mkdir(parents=True, exist_ok=True)
    path = write_json(a.out / "variation_real.json", res, digits=4)
    plot(a.out / "variation_real.png", real, sims)
    q = res["side_by_side"]["bright_share_quantiles"]
    for k, v in q.items():
        print(f"{k:>14}: " + "  ".join(f"{kk} {vv:.2f}" for kk, vv in v.items()))
    print(f"wrote {path} in {res['duration_s']:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
