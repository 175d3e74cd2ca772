"""The speed-against-error sweep's part of the report (``python -m bench`` results, schema
``gpumap-bench/``): per-machine tables, targets, findings and scaling."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from .common import OASIS_PUBLISHED_MS, PAPER_TABLE_I, TARGETS
from .common import load_results as _load_results
from .report_md import _f, _pct

BASELINE_LABELS = {
    "paper-numpy": "paper's six steps, plain NumPy (ours)",
    "oasis-rule": "OASIS rule (fnr 0.5) on gpumap footprints",
    "octomap": "OctoMap (pyoctomap), beam maxima at elevation 0",
}


def load_results(folder: Path) -> list[dict[str, Any]]:
    """Every bench JSON in ``folder`` (sorted: CPU runs first, then GPU runs)."""
    out = _load_results(folder, "*.json", "gpumap-bench/")
    return sorted(out, key=lambda d: (d["run"].get("gpu_only", False), d["_file"]))



def _device_label(res: dict, row: dict) -> str:
    dev = row.get("device", "")
    if _is_gpu(row):
        gp = res["machine"].get("gpus") or [dev]
        return gp[0].split(" (")[0]
    return f"{res['machine']['cpu_model']} ({res['machine']['cpu_count']} cores)"


def _is_gpu(row: dict) -> bool:
    return bool(row.get("on_gpu")) or row.get("backend", "") in ("warp-cuda", "opencl-gpu")


def _series(res: dict, row: dict) -> str:
    if row.get("kind") == "gpumap":
        s = f"gpumap {row['backend']} {row['method']}"
        if _is_gpu(row):
            s += f" [{_device_label(res, row)}]"
        return s
    return BASELINE_LABELS.get(row["kind"], row["kind"])


# ------------------------------------------------------------------------------ tables
def _machine_block(res: dict) -> list[str]:
    m, r = res["machine"], res["run"]
    v = m.get("versions", {})
    lines = [
        f"- **Machine**: {m['cpu_model']}, {m['cpu_count']} cores, {m.get('mem_total_gb', '?')} GB"
        + (f"; GPU: {', '.join(m['gpus'])}" if m.get("gpus") else "; no GPU"),
        f"- **Load average** (1/5/15 min) at start {m.get('load_avg_start')}, at end {m.get('load_avg_end')}"
        " (it counts the bench's own threads too)"
        + (
            f"; during the run other processes kept {m['cpu_share_during_run']['others_cores']:.2f} cores "
            f"busy on average and the hypervisor withheld {m['cpu_share_during_run']['steal_cores']:.2f} "
            f"(steal), the bench used {m['cpu_share_during_run']['bench_cores']:.2f}"
            if (m.get("cpu_share_during_run") or {}).get("others_cores") is not None
            else ""
        ),
        f"- **Versions**: gpumap {v.get('gpumap')}, numpy {v.get('numpy')}, warp-lang {v.get('warp-lang')}, "
        f"pyopencl {v.get('pyopencl')}, PoCL {v.get('pocl-binary-distribution')}, "
        f"pyoctomap {v.get('pyoctomap')}; {m.get('platform')}",
        f"- **Pings**: {r['pings']} pings of the tank trajectory (seed {r['seed']}, {r['ping_source']}), "
        f"{r['image_shape'][0]} bins x {r['image_shape'][1]} beams, {r['image_dtype']}; "
        f"occupied threshold {r['threshold']}; gpumap shadow_m {r.get('shadow_m', 0.0):g} m "
        "(0 = the paper's rule)",
        f"- **Warm-up**: {r['warmup_note']}",
        f"- **Timing**: {r['timing_note']}",
        f"- **Code**: commit `{(m.get('git') or {}).get('commit') or '?'}`"
        + (
            f", with uncommitted changes to {', '.join(m['git']['modified'])}"
            if (m.get("git") or {}).get("modified")
            else ", clean"
        ),
        f"- **Run**: `{' '.join(['python -m bench', *res.get('argv', [])])}`, {res['created']}, "
        f"{r['duration_s']:.0f} s; file `bench/results/{res['_file']}`",
    ]
    return lines


def _gpumap_table(res: dict) -> list[str]:
    rows = [r for r in res["rows"] if r.get("kind") == "gpumap"]
    out = [
        "| voxel | backend | method | images/s | median ms | p95 ms | FN | miss (seen) | FP | height err "
        "| holes (1 ping) | peak RSS MB | device MB | voxels in view | others' cores |",
        "|---:|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in sorted(rows, key=lambda r: (-r["voxel_size_m"], r["backend"], r["method"])):
        if "error" in r:
            out.append(
                f"| {r['voxel_size_m'] * 100:g} cm | {r['backend']} | {r['method']} | error: "
                f"`{r['error'][:80]}` |||||||||||"
            )
            continue
        note = (
            ""
            if "quality_from" not in r
            else f" (timed {r['pings_timed']} pings; quality = {r['quality_from']})"
        )
        out.append(
            f"| {r['voxel_size_m'] * 100:g} cm | {r['backend']}{note} | {r['method']} "
            f"| {_f(r['images_per_s'], '.1f')} | {_f(r['ms_median'], '.2f')} | {_f(r['ms_p95'], '.2f')} "
            f"| {_pct(r.get('false_negative_rate'))} "
            f"| {_pct(r.get('miss_rate_seen'))} | {_pct(r.get('false_positive_rate'))} "
            f"| {_f(r.get('height_error_mean_m') and 100 * r['height_error_mean_m'], '.1f')} cm "
            f"| {_pct(r.get('hole_fraction_single_ping'))} | {_f(r.get('peak_host_rss_mb'), '.0f')} "
            f"| {_f(r.get('device_mem_mb'), '.0f')} | {_f(r.get('voxels_in_view'), '.3g')} "
            f"| {_f(r.get('others_cores'), '.2f')} |"
        )
    return out


def _baseline_table(res: dict) -> list[str]:
    rows = [r for r in res["rows"] if r.get("kind") != "gpumap"]
    if not rows:
        return []
    best = {}
    for r in res["rows"]:
        if r.get("kind") == "gpumap" and "images_per_s" in r and "false_negative_rate" in r:
            k = r["voxel_size_m"]
            if k not in best or r["images_per_s"] > best[k]["images_per_s"]:
                best[k] = r
    out = [
        "| voxel | mapper | images/s | median ms | FN | miss (seen) | FP | height err | observed "
        "| published: paper Table I | published: OASIS code |",
        "|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for v in sorted({r["voxel_size_m"] for r in rows}, reverse=True):
        group = [best[v]] if v in best else []
        group += sorted((r for r in rows if r["voxel_size_m"] == v), key=lambda r: r["kind"])
        for r in group:
            name = (
                _series(res, r)
                if r.get("kind") != "gpumap"
                else f"**gpumap {r['backend']} {r['method']}** (fastest)"
            )
            if "error" in r:
                out.append(f"| {v * 100:g} cm | {name} | error: `{r['error'][:80]}` ||||||||")
                continue
            pub = PAPER_TABLE_I.get(v)
            oas = OASIS_PUBLISHED_MS.get(v)
            first = r is group[0]
            out.append(
                f"| {v * 100:g} cm | {name} | {_f(r['images_per_s'], '.1f')} | {_f(r['ms_median'], '.1f')} "
                f"| {_pct(r.get('false_negative_rate'))} | {_pct(r.get('miss_rate_seen'))} "
                f"| {_pct(r.get('false_positive_rate'))} "
                f"| {_f(r.get('height_error_mean_m') and 100 * r['height_error_mean_m'], '.1f')} cm "
                f"| {_pct(r.get('observed_fraction'))} "
                f"| {(f'{pub * 1e3:g} ms ({1 / pub:.2g} Hz)' if pub and first else '')} "
                f"| {(f'{oas:g} ms ({1e3 / oas:.2g} Hz)' if oas and first else '')} |"
            )
    return out


def _targets(results: list[dict]) -> list[str]:
    out = ["| target | best measured (configuration, machine) | images/s | met? |", "|---|---|---:|---|"]
    for dev, v, hz in TARGETS:
        cands = []
        for res in results:
            for r in res["rows"]:
                if r.get("kind") != "gpumap" or "images_per_s" not in r:
                    continue
                if abs(r["voxel_size_m"] - v) > 1e-9 or _is_gpu(r) != (dev == "gpu"):
                    continue
                cands.append((r["images_per_s"], r, res))
        label = f"{'CPU (this 2-core box)' if dev == 'cpu' else 'H100'}: {v * 100:g} cm at >= {hz:g} images/s"
        if not cands:
            how = "`python -m bench`" if dev == "cpu" else "`python -m bench --gpu-only` on the GPU box"
            out.append(f"| {label} | not measured yet (run {how}) | – | not yet measured |")
            continue
        ips, r, res = max(cands, key=lambda c: c[0])
        ok = ips >= hz
        out.append(
            f"| {label} | {r['backend']} {r['method']} on {_device_label(res, r)} | {ips:.1f} "
            f"| {'**met**' if ok else f'**not met** ({100 * ips / hz:.0f} % of target)'} |"
        )
    return out


def _image_fit(res: dict, backend: str) -> dict | None:
    """``ms = a + b * pixels`` over the image-size sweep of ``backend`` (None without data)."""
    from .scaling import linear_fit

    rs = [
        r
        for r in res.get("scaling", {}).get("image_size", [])
        if r.get("backend") == backend and "error" not in r
    ]
    if len(rs) < 2:
        return None
    f = linear_fit([r["pixels"] for r in rs], [r["ms_median"] for r in rs])
    return {"ms_fixed": f["intercept"], "ns_per_pixel": 1e6 * f["slope"], "r2": f["r2"]}


def _why(results: list[dict]) -> list[str]:
    """Data-driven reasons: fixed cost + per-voxel cost x voxels in view (linear fit); the image's share."""
    out = []
    for res in results:
        shape = res["run"]["image_shape"]
        pixels = shape[0] * shape[1]
        for f in res.get("scaling", {}).get("voxels_in_view_fit", []):
            rows = {round(v, 4): n for v, n in zip(f["voxel_size_m"], f["voxels_in_view"], strict=True)}
            parts = []
            for dev, v, hz in TARGETS:
                n = rows.get(round(v, 4))
                if n is None or (dev == "gpu") != _is_gpu(f):
                    continue
                ms = f["ms_fixed"] + f["ns_per_voxel"] * 1e-6 * n
                parts.append(
                    f"{v * 100:g} cm: {f['ms_fixed']:.2f} ms + {n:.3g} voxels x {f['ns_per_voxel']:.3g} ns "
                    f"= {ms:.2f} ms -> {1e3 / ms:.0f} images/s (target {hz:g})"
                )
            if not parts:
                continue
            line = f"- {f['backend']} {f['method']}: " + "; ".join(parts)
            im = _image_fit(res, f["backend"]) if f["method"] == "gather" else None
            if im is not None:
                line += (
                    f". Of the fixed part, the image costs {im['ns_per_pixel']:.3g} ns/pixel x {pixels} "
                    f"pixels = {im['ns_per_pixel'] * 1e-6 * pixels:.2f} ms per ping "
                    f"(image-size sweep, R² {im['r2']:.2f})"
                )
            out.append(line)
    return out


def _scaling(res: dict) -> list[str]:
    s = res.get("scaling", {})
    out = []
    fits = s.get("voxels_in_view_fit", [])
    if fits:
        out += [
            "",
            "Time per image against voxels in view (a ping's observed voxels, mean of 4 pings), "
            "least squares `ms = a + b * voxels` over the voxel sizes:",
            "",
            "| backend | method | a (ms) | b (ns/voxel) | R² | log-log slope |",
            "|---|---|---:|---:|---:|---:|",
        ]
        for f in fits:
            out.append(
                f"| {f['backend']} | {f['method']} | {f['ms_fixed']:.3g} | {f['ns_per_voxel']:.3g} "
                f"| {f['r2']:.3f} | {f['loglog_slope']:.2f} |"
            )
    im = [r for r in s.get("image_size", []) if "error" not in r]
    if im:
        sizes = sorted({(r["n_bins"], r["n_beams"]) for r in im}, key=lambda x: x[0] * x[1])
        backs = sorted({r["backend"] for r in im})
        out += [
            "",
            f"Median ms per image against image size (bins x beams), {im[0]['voxel_size_m'] * 100:g} cm, "
            f"{im[0]['method']}, synthetic speckle:",
            "",
            "| backend | " + " | ".join(f"{a}x{b}" for a, b in sizes) + " |",
            "|---|" + "---:|" * len(sizes),
        ]
        for b in backs:
            cells = []
            for sz in sizes:
                r = next((r for r in im if r["backend"] == b and (r["n_bins"], r["n_beams"]) == sz), None)
                cells.append(_f(r and r["ms_median"], ".2f"))
            out.append(f"| {b} | " + " | ".join(cells) + " |")
    ekf = s.get("ekf", [])
    one = {r["n_features"]: r for r in s.get("ekf_one_blas_thread", [])}
    if ekf:
        out += [
            "",
            "EKF (`gpumap.ekf.SonarEKF`) cost against features in the state (every feature re-observed "
            "each update; `bench.ekf_bench._time_updates`), with NumPy's default BLAS threads and with one "
            "(`OPENBLAS_NUM_THREADS=1`, in a subprocess):",
            "",
            "| features | state dim | predict µs | update µs | predict µs, 1 thread | update µs, 1 thread |",
            "|---:|---:|---:|---:|---:|---:|",
        ]
        for r in ekf:
            o = one.get(r["n_features"], {})
            out.append(
                f"| {r['n_features']} | {r['state_dim']} | {r['predict_us_median']:.0f} "
                f"| {r['update_us_median']:.0f} | {_f(o.get('predict_us_median'), '.0f')} "
                f"| {_f(o.get('update_us_median'), '.0f')} |"
            )
        out.append(
            f"\nlog-log slope of update cost vs state dimension: {ekf[0]['loglog_slope_vs_state_dim']:.2f} "
            "(dense covariance: 2-3 expected once the state is large; on a loaded 2-core box OpenBLAS's "
            "threads can cost more than they save, compare the two columns)."
        )
    sim = s.get("simulator")
    if sim:
        out += [
            "",
            f"Simulator (`gpumap.sim` pyrender sonar, {sim['rays_per_ping']} rays per ping, GL renderer "
            f"`{sim['gl_renderer']}`): **{sim['images_per_s']:.1f} images/s** "
            f"(median {sim['ms_per_image_median']:.0f} ms per image; first ping, {sim['init_s']:.1f} s, "
            "excluded).",
        ]
    return out


# ------------------------------------------------------------------------------ the document
CAVEATS = [
    "- The CPU is a shared 2-core VM. Each run records the load average and, for the run and for every row, "
    "the cores other processes kept busy (*others' cores*: /proc/stat busy time minus the bench's own CPU "
    "time); a row with others' cores near 1 lost about half the machine and its speed is pessimistic.",
    "- The timed code is the commit recorded in each machine section; gpumap's kernels change often, so "
    "compare rows of one run, not rows of runs at different commits.",
    "- Pings are quantized to uint8 (what the Oculus delivers) and handed to `integrate()` as uint8; every "
    "configuration and machine gets the same bytes (`--save-pings` / `--pings-from`).",
    "- The **OASIS rule** row is our implementation of the published rule on gpumap's footprints (so only "
    "the decision rule differs); its speed is not the OASIS code's. The OASIS code's speed is the figure "
    "published in issue 6, labelled as such.",
    "- The **paper's six steps** row is our plain-NumPy reading of Section II-B (voxel template, `round` to "
    "the nearest voxel, max over the bins x beams rectangle spanned by the voxel's 8 projected corners, "
    "min update); the paper's Table I times are its own (machine not stated, rendering in the loop).",
    "- **OctoMap** is fed each beam's strongest return at elevation 0, as it is used with imaging sonars; it "
    "observes only a thin slice, so its FN (which counts observed voxels only) flatters it: read its "
    "*miss (seen)* column.",
    "- **FN** counts seen obstacle voxels that the map observed but calls free; sand and walls seen at "
    "grazing incidence, or lost behind a brighter return in a later view, are what min-max gets wrong; "
    "`false_negative_rate_objects` (chain, rock, basket, pipe only) is in the JSON.",
    "- numpy rows at <= 2 cm are timed on a few pings (capped, said in the row); their map quality is the "
    "other backends' (same algorithm, tested to agree).",
]


REPRODUCE = [
    "```",
    "python -m bench --save-pings bench/results/tmp/tank_pings.npz   # CPU sweep, ~5 min on 2 cores",
    "python -m bench --quick                                           # 5 and 3 cm, 16 pings, no scaling",
    "python -m bench.report                                            # this file and the plots",
    "# a GPU box without a renderer: the same pings (bench/results/tmp/ is git-ignored; carry the file)",
    "python -m bench --gpu-only --pings-from bench/results/tmp/tank_pings.npz --out DIR",
    "```",
    "",
    "The ping file (about 6 MB: 40 uint8 pings, their poses, the 5 mm cells the pings saw) is rebuilt "
    "bit for bit by the first command (seeded simulator). Ground truth is recomputed from the seeded scene "
    "on every machine (trimesh only). `--gpu-only` runs warp-cuda and opencl-gpu at 3, 1 and 0.5 cm, "
    "writes `gpu_<device>.json`; drop it in `bench/results/` and rerun the report.",
    "",
    "The H100 rows here came from the project's GPU machine (no package index there; see "
    "`../shared/device/README.md` for carrying warp-lang and pyopencl): install gpumap with "
    "`pip install --no-deps --no-build-isolation --target /tmp/gm .` (its setuptools is too old for an "
    "editable install that maps `kernels/` and `sim/` under `gpumap`), carry a trimesh wheel the same way, "
    "put `/tmp/gm` first on `PYTHONPATH` and the checkout after it, and run the `--gpu-only` command "
    "from outside the checkout, in two calls (`--voxel 0.03 0.01`, then `--voxel 0.005 --tag gpu_h100_5mm`).",
]


def _findings(results: list[dict]) -> list[str]:
    """One line per voxel size of the CPU run: gpumap's fastest row against each baseline."""
    out = []
    for res in results:
        if res["run"].get("gpu_only"):
            continue
        rows = res["rows"]
        for v in sorted({r["voxel_size_m"] for r in rows if r.get("kind") != "gpumap"}, reverse=True):
            g = [
                r
                for r in rows
                if r.get("kind") == "gpumap"
                and r["voxel_size_m"] == v
                and "quality_from" not in r
                and "images_per_s" in r
                and "false_negative_rate" in r
            ]
            if not g:
                continue
            best = max(g, key=lambda r: r["images_per_s"])
            parts = [
                f"gpumap {best['backend']} {best['method']} {best['images_per_s']:.0f} images/s, FN "
                f"{_pct(best['false_negative_rate'])}, FP {_pct(best['false_positive_rate'])}"
            ]
            for r in sorted(
                (
                    r
                    for r in rows
                    if r.get("kind") != "gpumap" and r["voxel_size_m"] == v and "images_per_s" in r
                ),
                key=lambda r: r["kind"],
            ):
                ratio = best["images_per_s"] / r["images_per_s"]
                if abs(ratio - 1) < 0.1:
                    rel = "about gpumap's speed"
                else:
                    rel = (
                        f"gpumap {ratio:.2g}x faster" if ratio > 1 else f"{1 / ratio:.2g}x faster than gpumap"
                    )
                parts.append(
                    f"{r['kind']} {r['images_per_s']:.3g} images/s ({rel}), "
                    f"FN {_pct(r['false_negative_rate'])}, miss {_pct(r['miss_rate_seen'])}, "
                    f"FP {_pct(r['false_positive_rate'])}"
                )
            if v in PAPER_TABLE_I:
                parts.append(f"paper Table I (published) {1 / PAPER_TABLE_I[v]:.2g} images/s")
            if v in OASIS_PUBLISHED_MS:
                parts.append(f"OASIS code (published) {1e3 / OASIS_PUBLISHED_MS[v]:.2g} images/s")
            out.append(f"- **{v * 100:g} cm**: " + "; ".join(parts) + ".")
    return out



def render_sweep(results: list[dict], plots: list[str], plot_prefix: str) -> str:
    L = [
        "# Benchmarks: speed against error",
        "",
        "Generated by `python -m bench.report` from `bench/results/*.json` (do not edit by hand; rerun "
        "`python -m bench` and then the report). Every row maps **the same simulated tank pings** "
        "(`gpumap.sim`, the paper's 4 x 3 x 1 m workspace, 0.6 m tank with chain, rock, basket, thin pipe) "
        "and is scored against ground truth with `gpumap.sim.metrics.evaluate`.",
        "",
        "Columns: **FN** = seen obstacle voxels the map observed but called free (the safety number); "
        "**miss (seen)** = seen obstacle voxels not called occupied whether observed or not (fair to maps "
        "that observe little, like OctoMap); **FP** = free voxels called occupied; **height err** = mean "
        "over objects of (map top - truth top), the elevation stretch; **holes (1 ping)** = voxels the "
        "gather method observes in one ping that the template method misses; **peak RSS** = rise of the "
        "process's "
        "resident memory during the row; **device MB** = GPU memory the backend reported in use.",
        "",
        "## Targets",
        "",
        *_targets(results),
        "",
    ]
    why = _why(results)
    if why:
        L += [
            "Why, from the linear cost model (fixed cost + per-voxel cost x voxels in view, fitted below):",
            "",
            *why,
            "",
        ]
    L += [
        "Published figures, labelled as such and not re-measured: the paper's Table I (its own machine: "
        + ", ".join(f"{v * 100:g} cm {s:g} s" for v, s in sorted(PAPER_TABLE_I.items(), reverse=True))
        + " per image) and the public OASIS code on this project's CPU as published in issue 6 ("
        + ", ".join(f"{v * 100:g} cm {ms:g} ms" for v, ms in sorted(OASIS_PUBLISHED_MS.items(), reverse=True))
        + ").",
        "",
    ]
    fnd = _findings(results)
    if fnd:
        L += ["## Where each stands (same pings, this run)", "", *fnd, ""]
    for p in plots:
        L += [f"![{p}]({plot_prefix}{p})", ""]
    L += ["## Caveats", "", *CAVEATS, ""]
    L += ["## Reproduce", "", *REPRODUCE, ""]
    for res in results:
        L += [f"## {res['tag']}", "", *_machine_block(res), "", "### gpumap", "", *_gpumap_table(res), ""]
        bt = _baseline_table(res)
        if bt:
            L += [
                "### Baselines on the same pings",
                "",
                "The fastest gpumap row of each voxel size first; the paper's Table I and the OASIS code's "
                "published times on the first line of each voxel size.",
                "",
                *bt,
                "",
            ]
            notes = sorted({(r["kind"], r.get("note", "")) for r in res["rows"] if r.get("kind") != "gpumap"})
            L += [f"- `{k}`: {n}" for k, n in notes] + [""]
        sc = _scaling(res)
        if sc:
            L += ["### Scaling", *sc, ""]
    return "\n".join(L).rstrip() + "\n"


