"""``python -m bench.readme``: the README's figures, written from the results files.

    python -m bench.readme            # rewrite the marked blocks of README.md and docs/guide.md
    python -m bench.readme --check    # exit 1 if a block differs from what the files give
"""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path
from typing import Any

from . import common
from .common import bench_parser

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"
JUDGED = ("agreement", "phantom_rate", "missing_rate")


def _load(name: str) -> dict[str, Any] | None:
    p = RESULTS / name
    return json.loads(p.read_text()) if p.is_file() else None


def _n(x: float) -> str:
    return f"{x:,.0f}" if x >= 100 else f"{x:.3g}"


def _pct(x: float) -> str:
    return f"{100 * x:.1f} %"


def _voxel(v: float) -> str:
    """A voxel edge as the README writes it: whole centimetres in cm, else mm."""
    return f"{v * 100:g} cm" if abs(v * 100 - round(v * 100)) < 1e-9 else f"{v * 1000:g} mm"


def _bench_rate(d: dict, backend: str, voxel_m: float) -> float | None:
    return next((r["images_per_s"] for r in d["rows"] if r.get("kind") == "gpumap" and r["backend"] == backend
                 and r["method"] == "gather" and r["shadow_m"] == 0
                 and abs(r["voxel_size_m"] - voxel_m) < 1e-9), None)


def _rates(d: dict, *cells: tuple[str, float]) -> str:
    return " / ".join(_n(_bench_rate(d, b, v)) for b, v in cells)


def summary_rows() -> list[tuple[str, str, str]]:
    """(what, figure, results file) for the README's summary table."""
    rows: list[tuple[str, str, str]] = []
    cpu, f = _load("cpu_amd-epyc_2c.json"), "cpu_amd-epyc_2c.json"
    if cpu:
        # the speed sweep ran before the visible rule existed: its rows are the plain rule's
        rows.append(("Simulated tank pings mapped per second, plain rule, 2-core CPU "
                     "(opencl-cpu / warp-cpu), 3 cm", _rates(cpu, ("opencl-cpu", 0.03), ("warp-cpu", 0.03)),
                     f))
        rows.append(("... the same at 1 cm", _rates(cpu, ("opencl-cpu", 0.01), ("warp-cpu", 0.01)), f))
    gpu, f = _load("gpu_nvidia-h100-80gb-hbm3.json"), "gpu_nvidia-h100-80gb-hbm3.json"
    if gpu:
        rows.append(("... on an H100 (warp-cuda), 3 cm / 1 cm",
                     _rates(gpu, ("warp-cuda", 0.03), ("warp-cuda", 0.01)), f))
    sp, f = _load("speed_gpu_nvidia-h100-80gb-hbm3.json"), "speed_gpu_nvidia-h100-80gb-hbm3.json"
    if sp:
        r = next(r for r in sp["rows"] if r["backend"] == "warp-cuda" and r["voxel_m"] == 0.01
                 and r["rule"] == "visible")
        rows.append(("Real tank frames, H100 warp-cuda, 1 cm, default rule: p99 latency per frame",
                     f"{r['latency']['p99_ms']:.2f} ms", f))
    gs = _load("gpu_scale.json")
    if gs:
        new = {(r["backend"], r["voxel_m"]): r["pings_per_s"]["median"] for r in gs["single"]
               if r["tree"] == "new" and r["variant"] == "as-shipped"}
        cells = [_n(new[(b, v)]) for v in (0.01, 0.005) for b in ("opencl-gpu", "warp-cuda") if (b, v) in new]
        rows.append(("Real tank frames on an H100, default rule, batched: pings/s opencl-gpu / warp-cuda at "
                     "1 cm, then 5 mm (bit for bit with the oracle)", " / ".join(cells[:2]) + ", "
                     + " / ".join(cells[2:]), "gpu_scale.json"))
        w = gs.get("workers")
        if w:
            from .gpu_scale import warm_medians

            m = warm_medians(w, "map_s")
            rows.append((f"... GPU workers ({w['voxel_m'] * 1000:g} mm, {w['frames']:,} pings): 2 GPUs over "
                         "1, mapping phase / end to end (the maps' transfer and merge included)",
                         f"{m[1] / m[2]:.2f}x / {w['summary']['speedup_2_over_1']:.2f}x", "gpu_scale.json"))
    h2 = _load("gpu_scale_h200.json")
    if h2:
        new = {(r["backend_asked"], r["voxel_m"]): r for r in h2["single"]
               if r["tree"] == "new" and "error" not in r}
        order = [(b, v) for v in (0.01, 0.005) for b in ("opencl-gpu", "warp-cuda") if (b, v) in new]
        if order:
            oracle = " (bit for bit with the oracle)" if all(new[k].get("oracle_equal") for k in order) else (
                " (NOT equal to the oracle)")
            rows.append(("Real tank frames on one H200 after issue 38's host path, default rule, batches of "
                         "64: pings/s " + ", ".join(f"{b} {_voxel(v)}" for b, v in order)
                         + "; host microseconds a ping (device idle)" + oracle,
                         " / ".join(_n(new[k]["pings_per_s"]["median"]) for k in order) + "; "
                         + " / ".join(f"{new[k]['host_idle_us_per_ping']['median']:.1f}" for k in order),
                         "gpu_scale_h200.json"))
    cr = _load("gpu_scale_cpu_rate.json")
    if cr:
        c = cr["cpu_rate"]
        sm = c["summary"]
        old_ms, new_ms = sm["old"]["cpu_ms_per_ping"]["median"], sm["new"]["cpu_ms_per_ping"]["median"]
        rows.append((f"2-core CPU, {c['backend']}, {_voxel(c['voxel_m'])}, default rule, real tank "
                     "frames: CPU time a ping before / after issue 38 (medians; the same map bytes"
                     + ("" if sm["same_map"] else ": NOT") + ")", f"{old_ms:.1f} / {new_ms:.1f} ms",
                     "gpu_scale_cpu_rate.json"))
    cw = _load("gpu_scale_cpu.json")
    if cw and cw["cpu_overhead"]["summary"].get("idle"):
        cs = cw["cpu_overhead"]["summary"]
        rows.append(("... 2 Dask workers against one process on the same idle 2-core CPU (warp-cpu, 2 cm): "
                     "time, median of 5 runs (negative: the workers are faster)",
                     f"{100 * cs['w2_over_one']:+.0f} %", "gpu_scale_cpu.json"))
    vis = _load("visibility.json")
    by = {r["rule"]: r for r in (vis or {"rows": []})["rows"]
          if r["scene"] == "tank" and r["voxel_size_m"] == 0.03}
    if {"visible", "plain"} <= set(by):
        for what, key in (("Simulated tank, 3 cm: missed (visible rule / paper's plain rule)", "miss_rate"),
                          ("... missed of the small objects", "miss_rate_objects"),
                          ("... phantom: water more than a voxel from a surface called occupied",
                           "false_positive_rate_far")):
            rows.append((what, f"{_pct(by['visible'][key])} / {_pct(by['plain'][key])}", "visibility.json"))
    rr = _load("rules_real_tank.json")
    if rr:
        c = rr["rule_comparison"]["rules"]
        names = [r for r in ("evidence", "visible", "plain") if r in c]
        rows.append((f"Real tank (every 10th frame), 5 cm: occupied voxels ({' / '.join(names)} rule), same "
                     "observed voxels", " / ".join(f"{c[r]['occupied_voxels']:,}" for r in names),
                     "rules_real_tank.json"))
    rate = _load("rate_real.json")
    if rate:
        occ = rate["rules"]["evidence"]["occupied_common"]
        rows.append(("Real tank run at the sonar's rate, frames 0-799, 5 cm, default rule: occupied voxels "
                     "mapping every 10th / 3rd / every frame (same observed region)",
                     " / ".join(f"{occ[k]:,}" for k in ("every_10", "every_3", "every_1")), "rate_real.json"))
        for rule in ("evidence", "visible"):
            r = rate["rules"][rule]
            rows.append((f"... held-out frames 800-1222, first returns the {rule} map agrees with / "
                         "phantoms in front / misses: every 10th, every frame",
                         ", ".join(" / ".join(_pct(j[k]) for k in JUDGED)
                                   for j in (r["every_10"]["judge"], r["every_1"]["judge"])),
                         "rate_real.json"))
    su = _load("surface.json")
    if su and su.get("real"):
        h = su["real"]["held_out"]["maps"]
        rows.append(("... held-out frames 800-1222 (frames 0-799 mapped), first returns agreed / phantoms in "
                     "front / missed: surface layer, visible map",
                     ", ".join(" / ".join(_pct(h[m][k]) for k in JUDGED) for m in ("surface", "visible")),
                     "surface.json"))
    rf = _load("real_frontier.json")
    if rf:
        default = [r for r in rf["rows"] if r.get("default")][:1]
        oasis = {r["options"]["variant"]: r for r in rf["rows"] if r["kind"] == "oasis"}
        surface = [r for r in rf["rows"] if r["kind"] == "surface"][:1]
        for key, picks, what in (
                ("judge", [*default, *[oasis[v] for v in ("every",) if v in oasis], *surface],
                 "frames 0-799 at full rate, whole map"),
                ("judge_box", [*default, *[oasis[v] for v in ("as-published",) if v in oasis]],
                 "every map cut to the public code's configured box (issue 36's comparison)")):
            if picks:
                said = {"every": "public OASIS code fed every frame", "as-published": "public OASIS code as "
                        "published (its 1 cm frame skip, its box)"}
                names = ", ".join(f"default map ({r['rule']})" if r.get("default")
                                  else said.get(r["options"].get("variant"), r["name"]) for r in picks)
                rows.append((f"... the same judge beside the public OASIS code (its update unmodified), "
                             f"{what}, first returns agreed / phantoms in front / missed: {names}",
                             ", ".join(" / ".join(_pct(r[key][k]) for k in JUDGED) for r in picks),
                             "real_frontier.json"))
    sr = _load("surface_rate.json")
    if sr and sr.get("streams"):
        r = sr["streams"][0]
        load = (r.get("load_avg_before") or ["?"])[0]
        rows.append((f"... the live surface layer, the full run played at {r['hz']:g} Hz on the "
                     f"2-core CPU ({r['backend']}, load {load}): layer age median / max, its work a ping",
                     f"{r['age_s']['median']:.1f} s / {r['age_s']['max']:.1f} s, "
                     f"{r['surface_ms_per_ping']:.0f} ms", "surface_rate.json"))
        if sr.get("replay"):
            rows.append(("... `gpumap replay` of the full run writing both layers over the safe layer alone "
                         f"(paired runs, load {load} at the start)", f"{sr['replay']['ratio_median']:.2f}x",
                         "surface_rate.json"))
    cf = _load("confidence.json")
    if cf:
        secs = cf.get("sections", {})
        cells = [f"{b} {r['ratio']:.2f}x" for sec in ("cpu", "gpu")
                 for b, r in secs.get(sec, {}).get("rows", {}).items()]
        cpu_rows = secs.get("cpu", {}).get("rows", {}).values()
        cpu_load = max((r["loadavg_start"][0] for r in cpu_rows), default="?")
        rows.append((f"Confidence layer on the device (issue 37): mapping the real tank (123 pings, 5 cm) "
                     "with the layer over without, best of 3 each in one run; the 2-core CPU (load "
                     f"{cpu_load} at the start), then the GPU", ", ".join(cells), "confidence.json"))
    dc = _load("decision.json")
    if dc:
        def cells(labels: tuple[str, ...], var: str, key: str) -> str:
            def one(lb: str, sc: str) -> str:
                return _pct(next(r[key] for r in dc["sim"]
                                 if (r["label"], r["scene"], r["variation"]) == (lb, sc, var)))
            return ", ".join(f"{sc} " + " / ".join(one(lb, sc) for lb in labels) for sc in ("tank", "circle"))

        cal = "calibrated, miss cost 10"
        rows.append(("Simulated tank and circle without variation, 40 pings, 3 cm: far water called "
                     "occupied, the evidence rule's default decision / calibrated (retired: "
                     "bench/experiments, miss cost 10) / visible rule",
                     cells(("share 0.2 (default)", cal, "visible rule"), "none", "false_positive_rate_far"),
                     "decision.json"))
        rows.append(("... with the real tank's variation: objects missed, default / calibrated / the floor "
                     "no rule can beat (voxels never bright)",
                     cells(("share 0.2 (default)", cal, "ever bright (floor)"), "real_tank",
                           "miss_rate_objects"),
                     "decision.json"))
    lr = _load("long_run.json")
    if lr:
        cells = [f"{name} {rule} {_pct(sc['curves'][rule][0]['miss_rate_objects'])} / "
                 f"{_pct(sc['curves'][rule][-1]['miss_rate_objects'])}"
                 for name, sc in lr["scenes"].items() for rule in ("evidence",
                                                                   "visible") if sc["curves"].get(rule)]
        first, last = lr["checkpoints"][0], lr["checkpoints"][-1]
        rows.append((f"Simulated tank and circle, {last} pings with the real sonar's variation, 3 cm: "
                     f"objects missed after {first} / {last} pings", ", ".join(cells), "long_run.json"))
    ekf = _load("ekf_real.json")
    if ekf:
        def worst(variant: str, key: str) -> float:
            return max(v[key] for k, v in ekf["summary"].items() if k.split("|")[0] == variant)

        g, p = ((worst(v, "ratio_position_max"), worst(v, "ratio_heading_max")) for v in ("guarded", "plain"))
        rows.append(("Real tank run at the sonar's rate, EKF pose error over odometry's, worst of 5 seeds, "
                     "2 drifts, dev / held-out / whole run: guarded (default) position / heading, "
                     "unguarded position / heading",
                     f"{g[0]:.3f} / {g[1]:.3f}, {p[0]:.2f} / {p[1]:.2f}", "ekf_real.json"))
    reg = _load("ekf_registration.json")
    if reg:
        full = [reg["summary"][k] for k in sorted(reg["summary"])
                if k.startswith("replay|") and k.endswith("|full")]
        rows.append(("... with revisits unverified, as #29 built them (replaced by the verified ones), whole "
                     "run, drifts 0.005 / 0.02: position mean of 5 seeds, then the worst seed's position / "
                     "heading",
                     ", ".join(f"{c['ratio_position_mean']:.2f}" for c in full) + "; "
                     + ", ".join(f"{c['ratio_position_max']:.2f} / {c['ratio_heading_max']:.2f}"
                                 for c in full), "ekf_registration.json"))
    pose = _load("ekf_pose.json")
    if pose:
        sm = pose["summary"]

        def worst_of(src: str, key: str) -> float:
            return max(c[src][key] for c in sm.values())

        full = [sm[k] for k in sorted(sm, key=lambda k: float(k.split("|")[0])) if k.endswith("|full")]
        rows.append(("... with `--ekf-registration` since #39 (revisits verified by their images, a pose "
                     "graph behind the filter; off by default): "
                     "worst of 5 seeds, 2 drifts, dev / held-out / whole run, position / heading; whole run, "
                     "drifts 0.005 / 0.02, mean position: EKF, pose graph",
                     f"{worst_of('ekf', 'ratio_position_max'):.2f} / "
                     f"{worst_of('ekf', 'ratio_heading_max'):.2f}; "
                     + ", ".join(f"{c['ekf']['ratio_position_mean']:.2f}" for c in full) + "; "
                     + ", ".join(f"{c['graph']['ratio_position_mean']:.2f}" for c in full), "ekf_pose.json"))
        ms = pose.get("maps_summary") or {}
        if ms:
            rows.append(("... frames 0-799 mapped at each pose source, held-out first returns agreed, drifts "
                         "0.005 / 0.02: odometry, EKF, pose graph, recorded poses",
                         "; ".join(", ".join(_pct(ms[d][k]["agreement_mean"])
                                             for k in ("odometry", "ekf", "graph", "recorded"))
                                   for d in sorted(ms, key=float)), "ekf_pose.json"))
    valid = [json.loads(p.read_text()) | {"_file": p.name} for p in sorted(RESULTS.glob("peer_ratio_*.json"))]
    valid = [d for d in valid if d.get("valid")]
    if valid:
        d, st = valid[-1], valid[-1]["setup"]
        rows.append((f"Speed against the public OASIS code, same real frames, {st['voxel_m'] * 100:.1f} cm, "
                     f"idle machine ({st['backend']}, {st['rule']} rule)",
                     f"{d['ratio_median']:.0f}x ({d['ratio_min']:.0f}-{d['ratio_max']:.0f}x over "
                     f"{len(d['ratio_per_repeat'])} repeats)", d["_file"]))
    else:
        rows.append(("Speed against the public OASIS code, same real frames, 5 cm",
                     "not yet measured on an idle machine (python -m bench.peer_ratio)", "peer_ratio_*.json"))
    return rows


def machine_of(name: str) -> str:
    """The machine a results file says it ran on, in a few words (its GPU, else its CPU and cores)."""
    d = _load(name.split(",")[0].strip()) if "*" not in name else None
    m = (d or {}).get("machine")
    if isinstance(m, dict):
        if m.get("gpus"):
            return str(m["gpus"][0]).split(" (")[0]
        if m.get("cpu_model"):
            return f"{m['cpu_model']}, {m.get('cpu_count', '?')} cores"
    if d and d.get("cpu"):
        return f"{d['cpu']}" + (f", {d['n_cpus']} cores" if d.get("n_cpus") else "")
    if d and isinstance(d.get("sections"), dict):  # one machine per section (e.g. the CPU, then a GPU's host)
        parts = [f"{x['cpu_model']}, {x.get('cpus', '?')} cores" for x in d["sections"].values()
                 if isinstance(x, dict) and x.get("cpu_model")]
        if parts:
            return "; ".join(dict.fromkeys(parts))
    return "see the file"


def summary_block() -> str:
    return "\n".join(["| what | figure | machine | results file (bench/results/) |", "|---|---|---|---|",
                      *(f"| {w} | {f} | {machine_of(s)} | `{s}` |" for w, f, s in summary_rows())])


#: The README's headline rows: the first summary row of each of these results files.
HEADLINE = ("cpu_amd-epyc_2c.json", "gpu_scale_h200.json", "rules_real_tank.json", "real_frontier.json",
            "decision.json", "long_run.json", "distance.json", "peer_ratio_cpu_2c.json")


#: What a headline row that continues another in the full table is about.
CONTEXT = {"real_frontier.json": "Real tank run at the sonar's rate, 5 cm, held-out frames 800-1222 judged: "}


def headline_rows() -> list[tuple[str, str, str]]:
    """The README's few rows (:data:`HEADLINE`), each as the full table (docs/guide.md) words it."""
    seen: set[str] = set()
    rows = []
    for w, f, s in summary_rows():
        if s in HEADLINE and s not in seen:
            seen.add(s)
            if w.startswith("... "):  # a row that continues the one above it in the full table
                w = CONTEXT.get(s, "") + w.removeprefix("... ")
            rows.append((w, f, s))
    for name in ("distance.json", "distance_gpu.json"):
        d = _load(name)
        if d and name not in seen:
            rows.append((*distance_row(d)[:2], name))
    pr = _load("pipeline_rate_h200_decoders8.json")
    if pr:
        by = {r["backend"]: r for r in pr["rows"] if r["voxel_m"] == 0.01}
        order = [b for b in ("opencl-gpu", "warp-cuda") if b in by]
        rows.append(
            (
                "`gpumap replay`'s pipeline on the real tank's frames, 1 cm, 8 decoder threads: frames/s "
                "replayed, then mapped alone from memory, " + " / ".join(order),
                " / ".join(f"{by[b]['replay_frames_per_s']:,.0f}" for b in order)
                + "; "
                + " / ".join(f"{by[b]['in_memory_frames_per_s']:,.0f}" for b in order),
                "pipeline_rate_h200_decoders8.json",
            )
        )
    return rows


def distance_row(d: dict) -> tuple[str, str, str]:
    """The distance field's headline: a full field of the real tank at 2 cm beside SciPy's, unknown as
    obstacle (best of the repeats), and the incremental update's cost over a full one (batches of 32)."""
    st = next(x for x in d["full"]["settings"] if x["unknown_is_obstacle"])
    be = [b for b in ("opencl-cpu", "warp-cpu", "opencl-gpu", "warp-cuda") if b in st["backends"]]
    inc = next((r for r in d["incremental"]["rows"] if r["backend"] == be[0] and r["unknown_is_obstacle"]
                and "max_distance_m" not in r), None)
    what = (f"Exact distance field of the real tank's safe map, {_voxel(d['full']['grid']['voxel_size_m'])}: "
            "seconds, SciPy / " + " / ".join(be))
    fig = " / ".join(f"{x:.3g}" for x in (st["scipy"]["best_s"], *(st["backends"][b]["transform"]["best_s"]
                                                                  for b in be)))
    if inc is not None:
        what += f"; an incremental update over a full one ({d['incremental']['batch']}-ping batches, {be[0]})"
        fig += f"; {inc['mean_ratio']:.2f}"
    return what, fig, "distance.json"


def headline_block() -> str:
    return "\n".join(["| what | figure | machine | results file |", "|---|---|---|---|",
                      *(f"| {w} | {f} | {machine_of(s)} | `{s}` |" for w, f, s in headline_rows())])


def rules_real_block() -> str:
    d = _load("rules_real_tank.json")
    if d is None:
        return "(run `python -m bench.rules_real` to measure this)"
    c = d["rule_comparison"]
    rule, w = c["rule"], c["where"]
    vo, rng = w["fraction_vs_floor_0.25m"]["rule_only"], w["range_from_sonar_m"]
    vis, pl = c["rules"][rule], c["rules"]["plain"]
    others = ", ".join(f"the {r} rule {x['occupied_voxels']:,}" for r, x in c["rules"].items()
                       if r not in ("plain", rule))
    return common.template("readme-rules-real", same="exactly the same" if c["observed_equal"] else
                           "not the same", vis=vis, pl=pl, rule=rule, others=others, c=c, rng=rng,
                           **{k: 100 * vo[k] for k in ("at", "below", "above")})


#: The generated blocks of each file: the README's headline, the guide's full table and rules paragraph.
FILES = {"README.md": ("readme-headline",), "docs/guide.md": ("readme-summary", "readme-rules-real")}
BLOCKS = {"readme-headline": headline_block, "readme-summary": summary_block,
          "readme-rules-real": rules_real_block}


def render(text: str, names=None) -> str:
    """``text`` with its marked blocks (``names``, default every known one) rendered anew from the
    results files."""
    for name in BLOCKS if names is None else names:
        make = BLOCKS[name]
        pat = re.compile(rf"(<!-- begin:{name} -->\n)(?:.*?\n)?(<!-- end:{name} -->)", re.S)
        if not pat.search(text):
            raise ValueError(f"Expected a <!-- begin:{name} --> ... <!-- end:{name} --> block in the README")
        text = pat.sub(lambda m, make=make: m.group(1) + make() + "\n" + m.group(2), text)
    return text


def main(argv: list[str] | None = None) -> int:
    ap = bench_parser("readme", __doc__)
    ap.add_argument("--check", action="store_true", help="only compare; exit 1 when a block is stale")
    a = ap.parse_args(argv)
    stale = 0
    for rel, names in FILES.items():
        path = ROOT / rel
        old = path.read_text()
        new = render(old, names)
        if a.check and new != old:
            print(f"{path}: figures differ from bench/results (run python -m bench.readme)", file=sys.stderr)
            stale = 1
        elif new != old:
            path.write_text(new)
            print(f"updated {path}")
    return stale


if __name__ == "__main__":
    raise SystemExit(main())
