"""``python -m bench.report``: the results in ``bench/results`` -> ``BENCHMARKS.md`` and its plots.

    python -m bench.report [--results bench/results] [--out BENCHMARKS.md]
    python -m bench.report --check      # exit 1 if BENCHMARKS.md differs from what the files give

The head (the sweep and the real-frame speed) is written here; what others wrote is kept verbatim, and
every benchmark's marked block (its ``Section``) is rendered anew from its results file.
"""

from __future__ import annotations

import importlib
import os
import re
import sys
from pathlib import Path
from typing import Any

from . import common
from .common import GPU_BACKENDS, OASIS_PUBLISHED_MS, PAPER_TABLE_I, SONAR_RATE_HZ, TARGETS, bench_parser
from .common import fnum as _f
from .common import pct as _pct

#: The benchmarks whose blocks the report renders from their results files, in this order.
SECTION_MODULES = ("ab", "ekf_bench", "frontend", "nbv", "confidence", "rate_real", "variation", "long_run",
                   "surface", "surface_rate", "gpu_scale", "ekf_registration", "ekf_pose", "decision",
                   "real_frontier", "distance", "pipeline_rate")
BASELINE_LABELS = {"paper-numpy": "paper's six steps, plain NumPy (ours)",
                   "oasis-rule": "OASIS rule (fnr 0.5) on gpumap footprints",
                   "octomap": "OctoMap (pyoctomap), beam maxima at elevation 0"}


# ------------------------------------------------------------------------------ the sweep
def load_sweep(folder: Path) -> list[dict[str, Any]]:
    """Every bench JSON in ``folder`` (sorted: CPU runs first, then GPU runs)."""
    return sorted(common.load_results(folder, "*.json", "gpumap-bench/"),
                  key=lambda d: (d["run"].get("gpu_only", False), d["_file"]))


def _is_gpu(row: dict) -> bool:
    return bool(row.get("on_gpu")) or row.get("backend", "") in GPU_BACKENDS


def _device_label(res: dict, row: dict) -> str:
    if _is_gpu(row):
        return (res["machine"].get("gpus") or [row.get("device", "")])[0].split(" (")[0]
    return f"{res['machine']['cpu_model']} ({res['machine']['cpu_count']} cores)"


def _series(res: dict, row: dict) -> str:
    if row.get("kind") == "gpumap":
        gpu = f" [{_device_label(res, row)}]" if _is_gpu(row) else ""
        return f"gpumap {row['backend']} {row['method']}{gpu}"
    return BASELINE_LABELS.get(row["kind"], row["kind"])


def _machine_block(res: dict) -> list[str]:
    m, r = res["machine"], res["run"]
    v, share, git = m.get("versions", {}), m.get("cpu_share_during_run") or {}, m.get("git") or {}
    during = (f"; during the run other processes kept {share['others_cores']:.2f} cores busy on average and "
              f"the hypervisor withheld {share['steal_cores']:.2f} (steal), the bench used "
              f"{share['bench_cores']:.2f}" if share.get("others_cores") is not None else "")
    return [
        f"- **Machine**: {m['cpu_model']}, {m['cpu_count']} cores, {m.get('mem_total_gb', '?')} GB"
        + (f"; GPU: {', '.join(m['gpus'])}" if m.get("gpus") else "; no GPU"),
        f"- **Load average** (1/5/15 min) at start {m.get('load_avg_start')}, at end {m.get('load_avg_end')}"
        " (it counts the bench's own threads too)" + during,
        f"- **Versions**: gpumap {v.get('gpumap')}, numpy {v.get('numpy')}, warp-lang {v.get('warp-lang')}, "
        f"pyopencl {v.get('pyopencl')}, PoCL {v.get('pocl-binary-distribution')}, "
        f"pyoctomap {v.get('pyoctomap')}; {m.get('platform')}",
        f"- **Pings**: {r['pings']} pings of the tank trajectory (seed {r['seed']}, {r['ping_source']}), "
        f"{r['image_shape'][0]} bins x {r['image_shape'][1]} beams, {r['image_dtype']}; "
        f"occupied threshold {r['threshold']}; gpumap shadow_m {r.get('shadow_m', 0.0):g} m "
        "(0 = the paper's rule)",
        f"- **Warm-up**: {r['warmup_note']}",
        f"- **Timing**: {r['timing_note']}",
        f"- **Code**: commit `{git.get('commit') or '?'}`"
        + (f", with uncommitted changes to {', '.join(git['modified'])}" if git.get("modified")
           else ", clean"),
        f"- **Run**: `{' '.join(['python -m bench', *res.get('argv', [])])}`, {res['created']}, "
        f"{r['duration_s']:.0f} s; file `bench/results/{res['_file']}`",
    ]


def _height(r: dict) -> str:
    return _f(r.get("height_error_mean_m") and 100 * r["height_error_mean_m"], ".1f")


def _gpumap_table(res: dict) -> list[str]:
    out = ["| voxel | backend | method | images/s | median ms | p95 ms | FN | miss (seen) | FP | height err "
           "| holes (1 ping) | peak RSS MB | device MB | voxels in view | others' cores |",
           "|---:|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    rows = [r for r in res["rows"] if r.get("kind") == "gpumap"]
    for r in sorted(rows, key=lambda r: (-r["voxel_size_m"], r["backend"], r["method"])):
        if "error" in r:
            out.append(f"| {r['voxel_size_m'] * 100:g} cm | {r['backend']} | {r['method']} | error: "
                       f"`{r['error'][:80]}` |||||||||||")
            continue
        note = ("" if "quality_from" not in r
                else f" (timed {r['pings_timed']} pings; quality = {r['quality_from']})")
        out.append(
            f"| {r['voxel_size_m'] * 100:g} cm | {r['backend']}{note} | {r['method']} "
            f"| {_f(r['images_per_s'], '.1f')} | {_f(r['ms_median'], '.2f')} | {_f(r['ms_p95'], '.2f')} "
            f"| {_pct(r.get('false_negative_rate'))} | {_pct(r.get('miss_rate_seen'))} "
            f"| {_pct(r.get('false_positive_rate'))} | {_height(r)} cm "
            f"| {_pct(r.get('hole_fraction_single_ping'))} "
            f"| {_f(r.get('peak_host_rss_mb'), '.0f')} | {_f(r.get('device_mem_mb'), '.0f')} "
            f"| {_f(r.get('voxels_in_view'), '.3g')} | {_f(r.get('others_cores'), '.2f')} |")
    return out


def _fastest(rows: list[dict]) -> dict[float, dict]:
    """Per voxel size, the fastest scored gpumap row."""
    best: dict[float, dict] = {}
    for r in rows:
        if r.get("kind") == "gpumap" and "images_per_s" in r and "false_negative_rate" in r:
            if r["voxel_size_m"] not in best or r["images_per_s"] > best[r["voxel_size_m"]]["images_per_s"]:
                best[r["voxel_size_m"]] = r
    return best


def _baseline_table(res: dict) -> list[str]:
    rows = [r for r in res["rows"] if r.get("kind") != "gpumap"]
    if not rows:
        return []
    best = _fastest(res["rows"])
    out = ["| voxel | mapper | images/s | median ms | FN | miss (seen) | FP | height err | observed "
           "| published: paper Table I | published: OASIS code |",
           "|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for v in sorted({r["voxel_size_m"] for r in rows}, reverse=True):
        others = sorted((r for r in rows if r["voxel_size_m"] == v), key=lambda r: r["kind"])
        group = ([best[v]] if v in best else []) + others
        for r in group:
            name = (_series(res, r) if r.get("kind") != "gpumap"
                    else f"**gpumap {r['backend']} {r['method']}** (fastest)")
            if "error" in r:
                out.append(f"| {v * 100:g} cm | {name} | error: `{r['error'][:80]}` ||||||||")
                continue
            pub, oas, first = PAPER_TABLE_I.get(v), OASIS_PUBLISHED_MS.get(v), r is group[0]
            out.append(
                f"| {v * 100:g} cm | {name} | {_f(r['images_per_s'], '.1f')} | {_f(r['ms_median'], '.1f')} "
                f"| {_pct(r.get('false_negative_rate'))} | {_pct(r.get('miss_rate_seen'))} "
                f"| {_pct(r.get('false_positive_rate'))} | {_height(r)} cm "
                f"| {_pct(r.get('observed_fraction'))} "
                f"| {(f'{pub * 1e3:g} ms ({1 / pub:.2g} Hz)' if pub and first else '')} "
                f"| {(f'{oas:g} ms ({1e3 / oas:.2g} Hz)' if oas and first else '')} |")
    return out


def sweep_targets(results: list[dict]) -> list[str]:
    out = ["| target | best measured (configuration, machine) | images/s | met? |", "|---|---|---:|---|"]
    for dev, v, hz in TARGETS:
        cands = [(r["images_per_s"], r, res) for res in results for r in res["rows"]
                 if r.get("kind") == "gpumap" and "images_per_s" in r and abs(r["voxel_size_m"] - v) <= 1e-9
                 and _is_gpu(r) == (dev == "gpu")]
        label = f"{'CPU (this 2-core box)' if dev == 'cpu' else 'H100'}: {v * 100:g} cm at >= {hz:g} images/s"
        if not cands:
            how = "`python -m bench`" if dev == "cpu" else "`python -m bench --gpu-only` on the GPU box"
            out.append(f"| {label} | not measured yet (run {how}) | – | not yet measured |")
            continue
        ips, r, res = max(cands, key=lambda c: c[0])
        out.append(f"| {label} | {r['backend']} {r['method']} on {_device_label(res, r)} | {ips:.1f} "
                   f"| {'**met**' if ips >= hz else f'**not met** ({100 * ips / hz:.0f} % of target)'} |")
    return out


def _image_fit(res: dict, backend: str) -> dict | None:
    """``ms = a + b * pixels`` over the image-size sweep of ``backend`` (None without data)."""
    rs = [r for r in res.get("scaling", {}).get("image_size", [])
          if r.get("backend") == backend and "error" not in r]
    if len(rs) < 2:
        return None
    f = common.linear_fit([r["pixels"] for r in rs], [r["ms_median"] for r in rs])
    return {"ms_fixed": f["intercept"], "ns_per_pixel": 1e6 * f["slope"], "r2": f["r2"]}


def _why(results: list[dict]) -> list[str]:
    """Data-driven reasons: fixed cost + per-voxel cost x voxels in view (linear fit); the image's share."""
    out = []
    for res in results:
        pixels = res["run"]["image_shape"][0] * res["run"]["image_shape"][1]
        for f in res.get("scaling", {}).get("voxels_in_view_fit", []):
            rows = {round(v, 4): n for v, n in zip(f["voxel_size_m"], f["voxels_in_view"], strict=True)}
            parts = []
            for dev, v, hz in TARGETS:
                n = rows.get(round(v, 4))
                if n is None or (dev == "gpu") != _is_gpu(f):
                    continue
                ms = f["ms_fixed"] + f["ns_per_voxel"] * 1e-6 * n
                parts.append(f"{v * 100:g} cm: {f['ms_fixed']:.2f} ms + {n:.3g} voxels x "
                             f"{f['ns_per_voxel']:.3g} ns = {ms:.2f} ms -> {1e3 / ms:.0f} images/s "
                             f"(target {hz:g})")
            if not parts:
                continue
            line = f"- {f['backend']} {f['method']}: " + "; ".join(parts)
            im = _image_fit(res, f["backend"]) if f["method"] == "gather" else None
            if im is not None:
                line += (f". Of the fixed part, the image costs {im['ns_per_pixel']:.3g} ns/pixel x {pixels} "
                         f"pixels = {im['ns_per_pixel'] * 1e-6 * pixels:.2f} ms per ping "
                         f"(image-size sweep, R² {im['r2']:.2f})")
            out.append(line)
    return out


def _scaling(res: dict) -> list[str]:
    s, out = res.get("scaling", {}), []
    if s.get("voxels_in_view_fit"):
        out += ["", "Time per image against voxels in view (a ping's observed voxels, mean of 4 pings), "
                "least squares `ms = a + b * voxels` over the voxel sizes:", "",
                "| backend | method | a (ms) | b (ns/voxel) | R² | log-log slope |",
                "|---|---|---:|---:|---:|---:|"]
        out += [f"| {f['backend']} | {f['method']} | {f['ms_fixed']:.3g} | {f['ns_per_voxel']:.3g} "
                f"| {f['r2']:.3f} | {f['loglog_slope']:.2f} |" for f in s["voxels_in_view_fit"]]
    im = [r for r in s.get("image_size", []) if "error" not in r]
    if im:
        sizes = sorted({(r["n_bins"], r["n_beams"]) for r in im}, key=lambda x: x[0] * x[1])
        out += ["", "Median ms per image against image size (bins x beams), "
                f"{im[0]['voxel_size_m'] * 100:g} cm, {im[0]['method']}, synthetic speckle:", "",
                "| backend | " + " | ".join(f"{a}x{b}" for a, b in sizes) + " |",
                "|---|" + "---:|" * len(sizes)]
        for b in sorted({r["backend"] for r in im}):
            cells = [next((r for r in im if r["backend"] == b and (r["n_bins"], r["n_beams"]) == sz), None)
                     for sz in sizes]
            out.append(f"| {b} | " + " | ".join(_f(r and r["ms_median"], ".2f") for r in cells) + " |")
    ekf, one = s.get("ekf", []), {r["n_features"]: r for r in s.get("ekf_one_blas_thread", [])}
    if ekf:
        out += ["", "EKF (`gpumap.ekf.SonarEKF`) cost against features in the state (every feature "
                "re-observed each update; `bench.ekf_bench._time_updates`), with NumPy's default BLAS "
                "threads and with one (`OPENBLAS_NUM_THREADS=1`, in a subprocess):", "",
                "| features | state dim | predict µs | update µs | predict µs, 1 thread "
                "| update µs, 1 thread |",
                "|---:|---:|---:|---:|---:|---:|"]
        for r in ekf:
            o = one.get(r["n_features"], {})
            out.append(f"| {r['n_features']} | {r['state_dim']} | {r['predict_us_median']:.0f} "
                       f"| {r['update_us_median']:.0f} | {_f(o.get('predict_us_median'), '.0f')} "
                       f"| {_f(o.get('update_us_median'), '.0f')} |")
        out.append("\nlog-log slope of update cost vs state dimension: "
                   f"{ekf[0]['loglog_slope_vs_state_dim']:.2f} (dense covariance: 2-3 expected once the "
                   "state is large; on a loaded 2-core box OpenBLAS's threads can cost more than they save, "
                   "compare the two columns).")
    sim = s.get("simulator")
    if sim:
        out += ["", f"Simulator (`gpumap.sim` pyrender sonar, {sim['rays_per_ping']} rays per ping, GL "
                f"renderer `{sim['gl_renderer']}`): **{sim['images_per_s']:.1f} images/s** "
                f"(median {sim['ms_per_image_median']:.0f} ms per image; first ping, {sim['init_s']:.1f} s, "
                "excluded)."]
    return out


def _findings(results: list[dict]) -> list[str]:
    """One line per voxel size of the CPU run: gpumap's fastest row against each baseline."""
    out = []
    for res in (res for res in results if not res["run"].get("gpu_only")):
        rows = res["rows"]
        for v in sorted({r["voxel_size_m"] for r in rows if r.get("kind") != "gpumap"}, reverse=True):
            g = [r for r in rows if r.get("kind") == "gpumap" and r["voxel_size_m"] == v
                 and "quality_from" not in r and "images_per_s" in r and "false_negative_rate" in r]
            if not g:
                continue
            best = max(g, key=lambda r: r["images_per_s"])
            parts = [f"gpumap {best['backend']} {best['method']} {best['images_per_s']:.0f} images/s, FN "
                     f"{_pct(best['false_negative_rate'])}, FP {_pct(best['false_positive_rate'])}"]
            for r in sorted((r for r in rows if r.get("kind") != "gpumap" and r["voxel_size_m"] == v
                             and "images_per_s" in r), key=lambda r: r["kind"]):
                ratio = best["images_per_s"] / r["images_per_s"]
                rel = ("about gpumap's speed" if abs(ratio - 1) < 0.1 else f"gpumap {ratio:.2g}x faster"
                       if ratio > 1 else f"{1 / ratio:.2g}x faster than gpumap")
                parts.append(f"{r['kind']} {r['images_per_s']:.3g} images/s ({rel}), "
                             f"FN {_pct(r['false_negative_rate'])}, miss {_pct(r['miss_rate_seen'])}, "
                             f"FP {_pct(r['false_positive_rate'])}")
            if v in PAPER_TABLE_I:
                parts.append(f"paper Table I (published) {1 / PAPER_TABLE_I[v]:.2g} images/s")
            if v in OASIS_PUBLISHED_MS:
                parts.append(f"OASIS code (published) {1e3 / OASIS_PUBLISHED_MS[v]:.2g} images/s")
            out.append(f"- **{v * 100:g} cm**: " + "; ".join(parts) + ".")
    return out


def render_sweep(results: list[dict], plots: list[str], plot_prefix: str) -> str:
    L = [common.template("sweep-intro"), "", *sweep_targets(results), ""]
    why = _why(results)
    if why:
        L += ["Why, from the linear cost model (fixed cost + per-voxel cost x voxels in view, fitted below):",
              "", *why, ""]
    L += ["Published figures, labelled as such and not re-measured: the paper's Table I (its own machine: "
          + ", ".join(f"{v * 100:g} cm {s:g} s" for v, s in sorted(PAPER_TABLE_I.items(), reverse=True))
          + " per image) and the public OASIS code on this project's CPU as published in issue 6 ("
          + ", ".join(f"{v * 100:g} cm {ms:g} ms"
                      for v, ms in sorted(OASIS_PUBLISHED_MS.items(), reverse=True))
          + ").", ""]
    fnd = _findings(results)
    if fnd:
        L += ["## Where each stands (same pings, this run)", "", *fnd, ""]
    for p in plots:
        L += [f"![{p}]({plot_prefix}{p})", ""]
    L += [common.template("sweep-caveats"), ""]
    for res in results:
        L += [f"## {res['tag']}", "", *_machine_block(res), "", "### gpumap", "", *_gpumap_table(res), ""]
        bt = _baseline_table(res)
        if bt:
            L += ["### Baselines on the same pings", "",
                  "The fastest gpumap row of each voxel size first; the paper's Table I and the OASIS code's "
                  "published times on the first line of each voxel size.", "", *bt, ""]
            notes = sorted({(r["kind"], r.get("note", "")) for r in res["rows"] if r.get("kind") != "gpumap"})
            L += [f"- `{k}`: {n}" for k, n in notes] + [""]
        sc = _scaling(res)
        if sc:
            L += ["### Scaling", *sc, ""]
    return "\n".join(L).rstrip() + "\n"


def plots(results: list[dict], out_dir: Path, draw: bool = True) -> list[str]:
    """The sweep's plots (PNG in ``out_dir``): speed against false negatives, images/s against voxel
    size, scaling; their file names (``draw=False``: only the names)."""
    sc = [res.get("scaling", {}) for res in results]
    fits = [f for s in sc for f in s.get("voxels_in_view_fit", [])]
    ims = [r for s in sc for r in s.get("image_size", []) if "error" not in r]
    ekf = [r for s in sc for r in s.get("ekf", [])]
    names = ["speed_vs_fn.png", "hz_vs_voxel.png"] + (["scaling.png"] if fits or ims or ekf else [])
    if not draw:
        return names
    import matplotlib.ticker
    import numpy as np

    plt = common.pyplot()
    markers = {0.06: "o", 0.05: "s", 0.04: "^", 0.03: "D", 0.02: "v", 0.01: "P", 0.005: "*"}
    series: dict[str, list] = {}
    for res in results:
        for r in res["rows"]:
            if "images_per_s" in r and r.get("false_negative_rate") is not None and "quality_from" not in r:
                series.setdefault(_series(res, r), []).append(r)
    series = {k: sorted(rs, key=lambda r: r["voxel_size_m"]) for k, rs in sorted(series.items())}
    cmap = plt.get_cmap("tab20")
    fig, ax = plt.subplots(figsize=(9, 5.5))  # 1. speed against false negatives
    for i, (name, rs) in enumerate(series.items()):
        c = cmap(i % 20)
        x, y = [r["images_per_s"] for r in rs], [100 * r["false_negative_rate"] for r in rs]
        ax.plot(x, y, "-", color=c, lw=0.8, alpha=0.6)
        for xi, yi, r in zip(x, y, rs, strict=True):
            ax.plot(xi, yi, markers.get(r["voxel_size_m"], "x"), color=c, ms=6)
        ax.plot([], [], "-", color=c, label=name)
    for v, mk in markers.items():
        ax.plot([], [], mk, color="gray", label=f"{v * 100:g} cm")
    ax.axvline(SONAR_RATE_HZ, color="k", ls="--", lw=0.8)
    ax.set(xscale="log", xlabel="images per second (log)", ylabel="false-negative rate (%)",
           title="Speed against false negatives, same tank pings")
    ax.legend(fontsize=6.5, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    common.save_figure(fig, out_dir / names[0], dpi=75)
    fig, ax = plt.subplots(figsize=(9, 5.5))  # 2. images/s against voxel size, against Table I
    for i, (name, rs) in enumerate(series.items()):
        ax.plot([100 * r["voxel_size_m"] for r in rs], [r["images_per_s"] for r in rs], "o-",
                color=cmap(i % 20), ms=4, lw=1, label=name)
    for r in (r for res in results for r in res["rows"] if "quality_from" in r):  # capped numpy rows
        ax.plot(100 * r["voxel_size_m"], r["images_per_s"], "x", color="gray", ms=5)
    tv, ov = sorted(PAPER_TABLE_I), sorted(OASIS_PUBLISHED_MS)
    ax.plot([100 * v for v in tv], [1 / PAPER_TABLE_I[v] for v in tv], "k-s", lw=2, ms=5,
            label="paper Table I (published)")
    ax.plot([100 * v for v in ov], [1e3 / OASIS_PUBLISHED_MS[v] for v in ov], "k:^", lw=1.5, ms=5,
            label="OASIS code (published, issue 6)")
    ax.axhline(SONAR_RATE_HZ, color="r", ls="--", lw=1, label="10 Hz sonar rate")
    for dev, v, hz in TARGETS:
        ax.plot(100 * v, hz, "*", color="gold" if dev == "cpu" else "lime", ms=14, mec="k",
                label=f"target {dev.upper()}" if (dev, v) in (("cpu", 0.03), ("gpu", 0.01)) else None)
    ax.set(xscale="log", yscale="log", xlabel="voxel size (cm, log)", ylabel="images per second (log)",
           title="Update rate against voxel size")
    ax.invert_xaxis()
    ax.set_xticks([6, 5, 4, 3, 2, 1, 0.5], ["6", "5", "4", "3", "2", "1", "0.5"])
    ax.xaxis.set_minor_locator(matplotlib.ticker.NullLocator())
    ax.legend(fontsize=6.5, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    common.save_figure(fig, out_dir / names[1], dpi=75)
    if len(names) < 3:
        return names
    fig, axs = plt.subplots(1, 3, figsize=(13, 4))  # 3. scaling
    for i, f in enumerate(fits):
        x, c = np.array(f["voxels_in_view"]), cmap(i % 20)
        axs[0].plot(x, f["ms_median"], "o", color=c, ms=4, label=f"{f['backend']} {f['method']}")
        xx = np.linspace(x.min(), x.max(), 50)
        axs[0].plot(xx, f["ms_fixed"] + f["ns_per_voxel"] * 1e-6 * xx, "-", color=c, lw=0.8)
    axs[0].set(xscale="log", yscale="log", xlabel="voxels in view per ping", ylabel="median ms per image",
               title="cost vs voxels in view (lines: linear fit)")
    if fits:
        axs[0].legend(fontsize=6)
    groups: dict[str, list] = {}
    for r in ims:
        groups.setdefault(f"{r['backend']}" + (" [GPU]" if _is_gpu(r) else ""), []).append(r)
    for name, rs in sorted(groups.items()):
        rs = sorted(rs, key=lambda r: r["pixels"])
        axs[1].plot([r["pixels"] for r in rs], [r["ms_median"] for r in rs], "o-", ms=4, label=name)
    axs[1].set(xscale="log", yscale="log", xlabel="pixels per image (bins x beams)", ylabel="median ms",
               title="cost vs image size (3 cm, gather)")
    axs[1].legend(fontsize=6)
    if ekf:
        nf = [r["n_features"] for r in ekf]
        axs[2].plot(nf, [r["update_us_median"] for r in ekf], "o-", label="update")
        axs[2].plot(nf, [r["predict_us_median"] for r in ekf], "s-", label="predict")
        one = [r for s in sc for r in s.get("ekf_one_blas_thread", [])]
        if one:
            axs[2].plot([r["n_features"] for r in one], [r["update_us_median"] for r in one], "o--",
                        label="update, 1 BLAS thread")
        axs[2].set(xscale="log", yscale="log", xlabel="features in the state", ylabel="µs",
                   title="EKF cost vs features")
        axs[2].legend(fontsize=7)
    for a in axs:
        a.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        a.yaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    common.save_figure(fig, out_dir / names[2], dpi=70)
    return names


# ------------------------------------------------------------------------------ speed on the real frames
def load_speed(folder: Path) -> list[dict[str, Any]]:
    """Every ``speed_*.json`` in ``folder`` (CPU runs first)."""
    return sorted(common.load_results(folder, "speed_*.json", "gpumap-speed/"),
                  key=lambda d: (bool(d["machine"].get("gpus")), d["_file"]))


def _cm(v: float) -> str:
    return f"{v * 100:.3g} cm"


def _ok(res: dict) -> list[dict]:
    return [r for r in res["rows"] if "error" not in r]


def _machine(res: dict) -> str:
    m, git = res["machine"], res["machine"].get("git", {})
    on_gpu = any(r.get("backend") in GPU_BACKENDS for r in res["rows"])
    what = m["gpus"][0] if on_gpu and m.get("gpus") else f"{m['cpu_model']}, {m['cpu_count']} cores"
    load = m.get("load_avg_start")
    dirty = f" (+{len(git['modified'])} modified files)" if git.get("modified") else ""
    # a device's copy of the tree carries no trustworthy git state: the commit only where run here
    commit = "" if on_gpu else f", commit `{(git.get('commit') or '?')[:10]}`{dirty}"
    return (f"**{what}** (`{res['_file']}`, {res['created']}, load average at start "
            f"{_f(load[0] if load else None)}{commit})")


def _row_table(res: dict) -> list[str]:
    L = ["| backend | voxel | rule | p50 ms | p99 ms | max ms | img/s sequential | img/s batched | "
         "free at 10 / 20 / 40 Hz (p99) | batch = sequential | other processes (cores) |",
         "|---|---:|---|---:|---:|---:|---:|---:|---|---|---:|"]
    for r in res["rows"]:
        if "error" in r:
            L.append(f"| {r['backend']} | {_cm(r['voxel_m'])} | {r['rule']} | error: `{r['error'][:80]}` "
                     "| | | | | | | |")
            continue
        lat, diff = r["latency"], r.get("batch_vs_sequential_diff")
        free = " / ".join(f"{100 * r['free_at_hz'][h]:.0f} %" for h in ("10", "20", "40"))
        same = "–" if diff is None else ("bit for bit" if diff == 0 else f"{diff} voxels differ")
        L.append(f"| {r['backend']} | {_cm(r['voxel_m'])} | {r['rule']} | {_f(lat['p50_ms'])} "
                 f"| {_f(lat['p99_ms'])} | {_f(lat['max_ms'])} | {_f(r['img_per_s'], '.0f')} "
                 f"| {_f(r.get('img_per_s_batched'), '.0f')} | {free} | {same} "
                 f"| {_f(r.get('others_cores'), '.2f')} |")
    return L


def _oasis_best(res: dict, o: dict) -> dict | None:
    """The fastest gpumap row of ``res`` at the voxel size of its public OASIS row ``o``."""
    return max((r for r in _ok(res) if abs(r["voxel_m"] - o["voxel_m"]) < 1e-9), key=lambda r: r["img_per_s"],
               default=None)


def _oasis_lines(res: dict) -> list[str]:
    L = []
    for o in res.get("oasis_public", []):
        if "error" in o:
            L.append(f"- public OASIS code, downsample {o['downsample']}: error `{o['error'][:120]}`")
            continue
        best, ratio = _oasis_best(res, o), ""
        if best is not None:
            ratio = (f"; gpumap {best['backend']} ({best['rule']}) {best['img_per_s']:.0f} img/s, "
                     f"p50 {best['latency']['p50_ms']:.2f} ms: **{best['img_per_s'] / o['img_per_s']:.0f}x**")
        L.append(f"- public OASIS code at {_cm(o['voxel_m'])} (downsample {o['downsample']}, "
                 f"{o['template_points']} template points): {o['latency']['p50_ms']:.1f} ms per frame p50, "
                 f"{o['img_per_s']:.1f} img/s over {o['latency']['n']} frames{ratio}")
    return L


def _best(res: dict, gpu: bool, voxel: float, key: str) -> tuple[float | None, dict | None]:
    rows = [r for r in _ok(res) if (r["backend"] in GPU_BACKENDS) == gpu and abs(r["voxel_m"] - voxel) < 2e-4
            and r.get(key) is not None]
    r = max(rows, key=lambda r: r[key], default=None)
    return (None, None) if r is None else (r[key], r)


def speed_targets(results: list[dict]) -> list[str]:
    """One line per target of issue #13, with the value of every run (file) that measured it:
    on a shared machine the runs differ, and the table shows each rather than the best."""
    L = ["| target | measured (each run) | met |", "|---|---|---|"]

    def line(name: str, goal: float, fmt: str, per_run: list, le: bool = False) -> None:
        if not per_run:
            L.append(f"| {name} | not measured | – |")
            return
        ok = [v <= goal if le else v >= goal for _, v, _ in per_run]
        vals = "; ".join(f"{format(v, fmt)} ({r['backend']}, {r['rule']}; `{f}`)" for f, v, r in per_run)
        met = "yes" if all(ok) else "**no**" if not any(ok) else f"in {sum(ok)} of {len(ok)} runs"
        L.append(f"| {name} | {vals} | {met} |")

    def each(gpu: bool, voxel: float, *keys: str) -> list:
        out = []
        for res in results:
            cands = [c for c in (_best(res, gpu, voxel, k) for k in keys) if c[0] is not None]
            if cands:
                out.append((res["_file"], *max(cands, key=lambda c: c[0])))
        return out

    ratios = [(res["_file"], best["img_per_s"] / o["img_per_s"], best) for res in results
              for o in res.get("oasis_public", []) if "error" not in o and abs(o["voxel_m"] - 0.05) <= 0.002
              for best in [_oasis_best(res, o)] if best is not None]
    line("2-core CPU, 5 cm: >= 50x the public OASIS code (same run)", 50, ".0f", ratios)
    line("2-core CPU, 3 cm: >= 150 img/s", 150, ".0f", each(False, 0.0302, "img_per_s"))
    line("2-core CPU, 1 cm: >= 15 img/s", 15, ".1f", each(False, 0.01, "img_per_s"))
    line("H100, 1 cm, batched, upload included: >= 20,000 img/s", 20000, ".0f",
         each(True, 0.01, "img_per_s_batched"))
    line("H100, 5 mm: >= 5,000 img/s (batched or sequential)", 5000, ".0f",
         each(True, 0.005, "img_per_s_batched", "img_per_s"))
    p99 = []
    for res in results:
        rows = [x for x in _ok(res) if x["backend"] in GPU_BACKENDS and abs(x["voxel_m"] - 0.01) < 1e-9]
        if rows:
            x = min(rows, key=lambda x: x["latency"]["p99_ms"])
            p99.append((res["_file"], x["latency"]["p99_ms"], x))
    line("H100, 1 cm, sequential latency p99 <= 1 ms", 1.0, ".2f", p99, le=True)
    return L


def render_speed(results: list[dict]) -> str:
    """The section (empty string without results)."""
    if not results:
        return ""
    L = [common.template("speed-intro"), "", *speed_targets(results), ""]
    for res in results:
        L += [f"### {_machine(res)}", ""]
        fr = res.get("frames", {})
        if fr.get("fan_to_polar_ms") and not res["machine"].get("gpus"):
            L += [f"Reading a PNG and converting it to polar (gpumap's reader, when the frames were cached; "
                  f"not in any figure below): {fr['fan_to_polar_ms']:.1f} ms per frame.", ""]
        ol = _oasis_lines(res)
        L += (ol + [""] if ol else []) + _row_table(res) + [""]
        if res.get("oracle_diff_5cm"):
            L += ["Against the NumPy oracle, 20 frames at 5 cm (voxels whose value differs, of about 30,000 "
                  "observed): " + ", ".join(f"{k} {v}" for k, v in res["oracle_diff_5cm"].items()), ""]
        prof = [r for r in res["rows"] if r.get("gpu_us_per_ping")]
        if prof:
            L += ["GPU time per frame of a batch (Warp's timing, microseconds): "
                  + "; ".join(f"{_cm(r['voxel_m'])} {r['rule']}: " + ", ".join(
                      f"{k.replace('forward kernel ', '').rsplit('_', 1)[0]} {v:.1f}"
                      for k, v in r["gpu_us_per_ping"].items()) for r in prof), ""]
    L.append(common.template("speed-tail"))
    return "\n".join(L) + "\n"


# ------------------------------------------------------------------------------ the file
_MARKED = re.compile(r"<!-- begin:(?P<name>[\w-]+) -->.*?<!-- end:(?P=name) -->", re.S)


def keep_foreign_sections(old: str, generated: str) -> str:
    """``generated`` followed by what of ``old`` the report does not write itself.

    Kept verbatim, in their order in ``old``: every block between ``<!-- begin:NAME -->`` and
    ``<!-- end:NAME -->`` markers, and every ``## `` section whose heading ``generated`` does not
    have (e.g. the visibility section of issue #10). A marked block that ``generated`` already holds
    is not repeated.
    """
    blocks = [m.group(0) for m in _MARKED.finditer(old) if m.group(0).split(" -->")[0] not in generated]
    own = {line.strip() for line in generated.splitlines() if line.startswith("## ")}
    kept: list[str] = []
    section: list[str] | None = None
    fence = False
    for line in _MARKED.sub("\0", old).splitlines():  # placeholders keep the blocks' places
        fence ^= line.startswith("```")
        if line.startswith("## ") and not fence:
            if section is not None:
                kept.append("\n".join(section))
            section = None if line.strip() in own else [line]
        elif section is not None:
            section.append(line)
        elif "\0" in line:  # a marked block outside any kept section
            kept.append(line)
    if section is not None:
        kept.append("\n".join(section))
    out = generated.rstrip("\n")
    for chunk in kept:
        while "\0" in chunk and blocks:
            chunk = chunk.replace("\0", blocks.pop(0), 1)
        chunk = chunk.replace("\0", "")
        if chunk.strip():
            out += "\n\n" + chunk.strip("\n")
    for b in blocks:  # marked blocks whose place was in a section the report rewrites
        out += "\n\n" + b
    return out + "\n"


def render(folder: Path, out: Path, draw: bool = True) -> str:
    """The new ``BENCHMARKS.md`` text (and, ``draw``, the plots, written next to the results)."""
    results, speed = load_sweep(folder), load_speed(folder)
    if not results and not speed:
        raise SystemExit(f"no bench results in {folder}; run `python -m bench` or `bench.speed` first")
    names = plots(results, folder, draw) if results else []
    prefix = os.path.relpath(folder, out.parent or ".") + "/"
    text = render_sweep(results, names, prefix) if results else "# Benchmarks\n"
    if speed:
        text = text.rstrip("\n") + "\n\n" + render_speed(speed)
    text = keep_foreign_sections(out.read_text() if out.is_file() else "", text)
    for name in SECTION_MODULES:
        sec = importlib.import_module(f".{name}", __package__).SECTION
        if (folder / sec.results).is_file() or any(folder.glob(sec.results)):
            text = sec.put(text, folder)
    return text


def main(argv: list[str] | None = None) -> int:
    ap = bench_parser("report", __doc__, out="BENCHMARKS.md")
    ap.add_argument("--results", type=Path, default=Path("bench/results"),
                    help="folder of results files (default bench/results)")
    ap.add_argument("--check", action="store_true",
                    help="only compare (no plots); exit 1 when the file is stale")
    ap.add_argument("--no-plots", action="store_true", help="write the file but leave the plots as they are")
    a = ap.parse_args(argv)
    new = render(a.results, a.out, draw=not (a.check or a.no_plots))
    if a.check:
        if new != (a.out.read_text() if a.out.is_file() else ""):
            print(f"{a.out}: differs from what {a.results} gives (run python -m bench.report)",
                  file=sys.stderr)
            return 1
        return 0
    a.out.write_text(new)
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
