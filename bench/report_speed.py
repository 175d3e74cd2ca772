"""The speed section of the report (``python -m bench.speed`` results, ``speed_*.json``): latency
and throughput per backend on the real tank frames, the public OASIS code in the same run, and
the targets of issue #13."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from .common import load_results
from .report_md import _f

HEADING = "## Speed on the real tank frames (issue #13)"
GPU_BACKENDS = ("warp-cuda", "opencl-gpu")


def load_speed(folder: Path) -> list[dict[str, Any]]:
    """Every ``speed_*.json`` in ``folder`` (CPU runs first)."""
    out = load_results(folder, "speed_*.json", "gpumap-speed/")
    return sorted(out, key=lambda d: (bool(d["machine"].get("gpus")), d["_file"]))


def _cm(v: float) -> str:
    return f"{v * 100:.3g} cm"


def _machine(res: dict) -> str:
    m = res["machine"]
    on_gpu = any(r.get("backend") in GPU_BACKENDS for r in res["rows"])
    what = m["gpus"][0] if on_gpu and m.get("gpus") else f"{m['cpu_model']}, {m['cpu_count']} cores"
    load = m.get("load_avg_start")
    git = m.get("git", {})
    dirty = f" (+{len(git['modified'])} modified files)" if git.get("modified") else ""
    # a device's copy of the tree carries no trustworthy git state: the commit only where run here
    commit = "" if on_gpu else f", commit `{(git.get('commit') or '?')[:10]}`{dirty}"
    return (f"**{what}** (`{res['_file']}`, {res['created']}, load average at start "
            f"{_f(load[0] if load else None)}{commit})")


def _row_table(res: dict) -> list[str]:
    hz = ("10", "20", "40")
    L = [
        "| backend | voxel | rule | p50 ms | p99 ms | max ms | img/s sequential | img/s batched | "
        "free at 10 / 20 / 40 Hz (p99) | batch = sequential | other processes (cores) |",
        "|---|---:|---|---:|---:|---:|---:|---:|---|---|---:|",
    ]
    for r in res["rows"]:
        if "error" in r:
            L.append(f"| {r['backend']} | {_cm(r['voxel_m'])} | {r['rule']} | error: `{r['error'][:80]}` "
                     "| | | | | | | |")
            continue
        lat = r["latency"]
        free = " / ".join(f"{100 * r['free_at_hz'][h]:.0f} %" for h in hz)
        diff = r.get("batch_vs_sequential_diff")
        same = "–" if diff is None else ("bit for bit" if diff == 0 else f"{diff} voxels differ")
        L.append(
            f"| {r['backend']} | {_cm(r['voxel_m'])} | {r['rule']} | {_f(lat['p50_ms'])} "
            f"| {_f(lat['p99_ms'])} "
            f"| {_f(lat['max_ms'])} | {_f(r['img_per_s'], '.0f')} | {_f(r.get('img_per_s_batched'), '.0f')} "
            f"| {free} | {same} | {_f(r.get('others_cores'), '.2f')} |"
        )
    return L


def _oasis_lines(res: dict) -> list[str]:
    L = []
    for o in res.get("oasis_public", []):
        if "error" in o:
            L.append(f"- public OASIS code, downsample {o['downsample']}: error `{o['error'][:120]}`")
            continue
        v = o["voxel_m"]
        same = [r for r in res["rows"] if "error" not in r and abs(r["voxel_m"] - v) < 1e-9]
        best = max(same, key=lambda r: r["img_per_s"], default=None)
        ratio = ""
        if best is not None:
            ratio = (f"; gpumap {best['backend']} ({best['rule']}) {best['img_per_s']:.0f} img/s, "
                     f"p50 {best['latency']['p50_ms']:.2f} ms: **{best['img_per_s'] / o['img_per_s']:.0f}x**")
        L.append(f"- public OASIS code at {_cm(v)} (downsample {o['downsample']}, "
                 f"{o['template_points']} template points): {o['latency']['p50_ms']:.1f} ms per frame p50, "
                 f"{o['img_per_s']:.1f} img/s over {o['latency']['n']} frames{ratio}")
    return L


def _best(results: list[dict], gpu: bool, voxel: float, key: str) -> tuple[float | None, dict | None]:
    rows = [(r, res) for res in results for r in res["rows"]
            if "error" not in r and (r["backend"] in GPU_BACKENDS) == gpu
            and abs(r["voxel_m"] - voxel) < 2e-4]
    rows = [(r, res) for r, res in rows if r.get(key) is not None]
    if not rows:
        return None, None
    r, _ = max(rows, key=lambda x: x[0][key])
    return r[key], r


def _targets(results: list[dict]) -> list[str]:
    """One line per target of issue #13, with the value of every run (file) that measured it:
    on a shared machine the runs differ, and the table shows each rather than the best."""
    L = ["| target | measured (each run) | met |", "|---|---|---|"]

    def line(name: str, goal: float, fmt: str, per_run: list[tuple[str, float, dict]],
             le: bool = False) -> None:
        if not per_run:
            L.append(f"| {name} | not measured | – |")
            return
        ok = [v <= goal if le else v >= goal for _, v, _ in per_run]
        vals = "; ".join(f"{format(v, fmt)} ({r['backend']}, {r['rule']}; `{f}`)" for f, v, r in per_run)
        met = "yes" if all(ok) else "**no**" if not any(ok) else f"in {sum(ok)} of {len(ok)} runs"
        L.append(f"| {name} | {vals} | {met} |")

    def each(gpu: bool, voxel: float, key: str) -> list[tuple[str, float, dict]]:
        out = []
        for res in results:
            v, r = _best([res], gpu, voxel, key)
            if v is not None:
                out.append((res["_file"], v, r))
        return out

    ratios = []
    for res in results:
        for o in res.get("oasis_public", []):
            if "error" in o or abs(o["voxel_m"] - 0.05) > 0.002:
                continue
            same = [r for r in res["rows"] if "error" not in r and abs(r["voxel_m"] - o["voxel_m"]) < 1e-9]
            if same:
                best = max(same, key=lambda r: r["img_per_s"])
                ratios.append((res["_file"], best["img_per_s"] / o["img_per_s"], best))
    line("2-core CPU, 5 cm: >= 50x the public OASIS code (same run)", 50, ".0f", ratios)
    line("2-core CPU, 3 cm: >= 150 img/s", 150, ".0f", each(False, 0.0302, "img_per_s"))
    line("2-core CPU, 1 cm: >= 15 img/s", 15, ".1f", each(False, 0.01, "img_per_s"))
    line("H100, 1 cm, batched, upload included: >= 20,000 img/s", 20000, ".0f",
         each(True, 0.01, "img_per_s_batched"))
    fine = []
    for res in results:
        cands = [(k, *_best([res], True, 0.005, k)) for k in ("img_per_s_batched", "img_per_s")]
        cands = [c for c in cands if c[1] is not None]
        if cands:
            _, v, r = max(cands, key=lambda c: c[1])
            fine.append((res["_file"], v, r))
    line("H100, 5 mm: >= 5,000 img/s (batched or sequential)", 5000, ".0f", fine)
    p99 = []
    for res in results:
        rows = [x for x in res["rows"]
                if "error" not in x and x["backend"] in GPU_BACKENDS and abs(x["voxel_m"] - 0.01) < 1e-9]
        if rows:
            x = min(rows, key=lambda x: x["latency"]["p99_ms"])
            p99.append((res["_file"], x["latency"]["p99_ms"], x))
    line("H100, 1 cm, sequential latency p99 <= 1 ms", 1.0, ".2f", p99, le=True)
    return L


def render_speed(results: list[dict]) -> str:
    """The section (empty string without results)."""
    if not results:
        return ""
    L = [
        HEADING,
        "",
        "Generated from `bench/results/speed_*.json` (`python -m bench.speed`). The frames are the **real** "
        "OASIS tank recording (`shared/data/oasis_tank`, Oculus M3000d, 398 bins x 512 beams, arm poses), "
        "converted once from the Cartesian PNGs to polar uint8 by gpumap's reader; the grid is the public "
        "OASIS configuration's box (2.4 x 2.4 x 1.3 m). **Latency** = `integrate` + `synchronize` per frame "
        "(what a vehicle waits); **free at N Hz** = the share of each ping period left at p99; **img/s "
        "sequential** = frames back to back, one synchronize at the end; **img/s batched** = "
        "`integrate_batch` of 64 frames, upload included; **batch = sequential**: the batched map against "
        "one `integrate` per frame on that backend (values and visible-rule evidence, compared as bits).",
        "",
        "### Targets",
        "",
        *_targets(results),
        "",
    ]
    for res in results:
        L += [f"### {_machine(res)}", ""]
        fr = res.get("frames", {})
        if fr.get("fan_to_polar_ms") and not res["machine"].get("gpus"):
            L += [f"Reading a PNG and converting it to polar (gpumap's reader, when the frames were cached; "
                  f"not in any figure below): {fr['fan_to_polar_ms']:.1f} ms per frame.", ""]
        ol = _oasis_lines(res)
        if ol:
            L += ol + [""]
        L += _row_table(res) + [""]
        if res.get("oracle_diff_5cm"):
            d = res["oracle_diff_5cm"]
            L += ["Against the NumPy oracle, 20 frames at 5 cm (voxels whose value differs, of about 30,000 "
                  "observed): " + ", ".join(f"{k} {v}" for k, v in d.items()), ""]
        prof = [r for r in res["rows"] if r.get("gpu_us_per_ping")]
        if prof:
            L += ["GPU time per frame of a batch (Warp's timing, microseconds): "
                  + "; ".join(f"{_cm(r['voxel_m'])} {r['rule']}: " + ", ".join(
                      f"{k.replace('forward kernel ', '').rsplit('_', 1)[0]} {v:.1f}"
                      for k, v in r["gpu_us_per_ping"].items()) for r in prof), ""]
    L += [
        "```",
        "python -m bench.speed --oasis-src /path/to/oasis_iros   # CPU (frames cached in bench/results/tmp)",
        "python -m bench.speed --gpu --frames-from bench/results/tmp/oasis_polar64.npz --out DIR   # GPU box",
        "python -m bench.report",
        "```",
    ]
    return "\n".join(L) + "\n"
