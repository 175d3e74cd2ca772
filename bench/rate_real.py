"""``python -m bench rate_real``: the rules on the real tank run at the sonar's own rate.

Frames 0-799 of the full run mapped (every 10th, 3rd, every frame), frames 800-1222 held out and judged
by first returns. Writes ``bench/results/rate_real.json`` and ``rate_real.png``; ~10 min on 2 cores.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from gpumap.core.params import MapperParams

from . import common
from .common import Section, bench_parser, oasis_full_dir, progress_bar, run_header, write_json

SCHEMA = "gpumap-rate-real/1"
STRIDES = (10, 3, 1)
DEV, HELD = (0, 800), (800, 1223)
TUNE_MAP, TUNE_JUDGE = (0, 600), (600, 800)
SHARES = (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7)
ZS = (0.0, 1.0, 1.645, 2.33)
CHECKPOINTS = (25, 50, 100, 200, 400, 800)


def _load(path: Path, progress: bool):
    from gpumap.io import open_recording

    rec = open_recording(path)
    n = rec.count()
    frames = iter(rec)
    first = next(frames)
    images, poses = np.empty((n, *first.image.shape), np.float32), np.empty((n, 4, 4))
    images[0], poses[0] = first.image, first.T_W_S
    for i, f in enumerate(progress_bar(frames, total=n - 1, desc="read", disable=not progress), start=1):
        images[i], poses[i] = f.image, f.T_W_S
    return first.spec, images, poses


def _map(spec, grid, images, poses, frames, rule, backend, threshold, checkpoints=()):
    import gpumap

    m = gpumap.MinMaxMapper(spec, grid, backend, MapperParams(rule=rule, threshold=threshold))
    curve, idx, done, t0 = [], list(frames), 0, time.perf_counter()
    for cut in [*(c for c in checkpoints if c < len(idx)), len(idx)]:
        cut = min(cut, len(idx))
        for a in range(done, cut, 32):
            b = idx[a:min(a + 32, cut)]
            m.integrate_batch(images[b], poses[b])
        done = cut
        if cut in checkpoints:
            v = m.values()
            curve.append({"frames": cut, "occupied": int((v >= threshold).sum()),
                          "observed": int(np.isfinite(v).sum())})
    m.synchronize()
    return m, time.perf_counter() - t0, curve


def _judge(values, grid, threshold, images, poses, frames, spec):
    from gpumap.layers.first_return import first_return_score

    return first_return_score(values, grid, threshold, ((images[i], poses[i]) for i in frames), spec)


def main(argv: list[str] | None = None) -> int:
    ap = bench_parser("rate_real", __doc__, out="bench/results", voxel=0.05, backend="auto", progress=True,
                      report="rate_real.json")
    ap.add_argument("--data", type=Path, default=None,
                    help="the full run's recording folder (default: ../oasis_tank_full or shared/data)")
    ap.add_argument("--threshold", type=float, default=0.4, help="bright / occupied (default 0.4)")
    ap.add_argument("--judge-stride", type=int, default=1, help="judge every N-th held-out frame (default 1)")
    ap.add_argument("--no-tuning", action="store_true", help="skip the settings grid on frames 0-799")
    a = ap.parse_args(argv)
    if SECTION.reported(a):
        return 0
    data = a.data or oasis_full_dir()
    if data is None:
        raise SystemExit("bench.rate_real: the full tank run was not found; get it as shared/data/README.md "
                         "says (oasis_tank_full/get_images.sh) and pass --data")
    from gpumap.geometry import RULES
    from gpumap.reference import evidence_occupied
    from gpumap.spec import auto_grid

    t_start = time.perf_counter()
    spec, images, poses = _load(data, not a.no_progress)
    if len(images) < HELD[1]:
        raise SystemExit(f"bench.rate_real: expected the full run of {HELD[1]} frames, but {data} holds "
                         f"{len(images)}")
    grid, thr, held = auto_grid(spec, poses, a.voxel), a.threshold, range(HELD[0], HELD[1], a.judge_stride)
    res = {**run_header(SCHEMA, argv), "data": str(data), "voxel_size_m": a.voxel, "threshold": thr,
           "grid": grid.to_dict(), "dev_frames": list(DEV), "held_out_frames": list(HELD),
           "judged_frames": len(held), "rules": {}}
    backend, values = None, []
    for rule in RULES:
        res["rules"][rule] = {}
        for s in STRIDES:
            frames = range(DEV[0], DEV[1], s)
            m, secs, curve = _map(spec, grid, images, poses, frames, rule, a.backend, thr,
                                  CHECKPOINTS if s == 1 else ())
            backend, v = m.backend, m.values()
            score = _judge(v, grid, thr, images, poses, held, spec)
            values.append((rule, s, v))
            r = res["rules"][rule][f"every_{s}"] = {
                "frames": len(frames), "seconds": secs, "observed": int(np.isfinite(v).sum()),
                "occupied": int((v >= thr).sum()), "judge": score.to_dict(),
                                                    **({"curve": curve} if curve else {})}
            print(f"{rule:9s} every {s:2d}: occupied {r['occupied']:6d}, agreement {score.agreement:.1%}, "
                  f"phantom {score.phantom_rate:.1%}, missing {score.missing_rate:.1%}", flush=True)
    common = np.logical_and.reduce([np.isfinite(v) for _, _, v in values])
    for rule, r in res["rules"].items():
        occ = [int((common & (v >= thr)).sum()) for q, _, v in values if q == rule]
        r["occupied_common"] = dict(zip((f"every_{s}" for s in STRIDES), occ, strict=True))
        r["occupied_common_spread"] = max(occ) / max(1, min(occ)) - 1
    res["common_observed"], res["backend"] = int(common.sum()), backend
    if not a.no_tuning:
        tune = {s: _map(spec, grid, images, poses, range(*TUNE_MAP, s), "evidence", a.backend,
                        thr)[0].evidence()
                for s in STRIDES}
        judge, rows = range(TUNE_JUDGE[0], TUNE_JUDGE[1], 5), []
        for p in SHARES:
            for z in ZS:
                row = {"bright_share": p, "share_z": z}
                for s, ev in tune.items():
                    occ = evidence_occupied(ev["count"], ev["hits"], p, z)
                    vals = np.where(occ, 1.0, np.where(np.isfinite(ev["min_all"]), 0.0, np.inf))
                    sc = _judge(vals, grid, thr, images, poses, judge, spec)
                    row[f"every_{s}"] = {"occupied": int(occ.sum()), "agreement": sc.agreement,
                                         "phantom_rate": sc.phantom_rate, "missing_rate": sc.missing_rate}
                rows.append(row)
        res["tuning"] = {"mapped_frames": list(TUNE_MAP), "judged_frames": [*TUNE_JUDGE, 5], "rows": rows}
    res["seconds_total"] = time.perf_counter() - t_start
    path = write_json(a.out / "rate_real.json", res, digits=4)
    _picture(res, a.out / "rate_real.png")
    print(f"wrote {path} and rate_real.png ({res['seconds_total']:.0f} s); BENCHMARKS.md: "
          f"python -m bench rate_real --report BENCHMARKS.md")
    return 0


def markdown(res: dict, folder: Path) -> str:
    """The BENCHMARKS.md section of a ``rate_real.json``."""
    m = res["machine"]
    out = [common.template("rate-real", res=res, m=m, load=m.get("load_avg_start"))]
    for rule, r in res["rules"].items():
        for s in STRIDES:
            x = r[f"every_{s}"]
            j = x["judge"]
            rate = {10: "every 10th", 3: "every 3rd", 1: "every frame"}.get(s, f"every {s}")
            out.append(f"| {rule} | {rate} ({x['frames']}) | {x['occupied']:,} | "
                       f"{r['occupied_common'][f'every_{s}']:,} | "
                       f"{100 * j['agreement']:.1f} % | {100 * j['phantom_rate']:.1f} % | "
                       f"{100 * j['missing_rate']:.1f} % |")
    out += ["", "Spread of the occupied voxels over the three rates (common region, max / min - 1): "
            + ", ".join(f"{rule} {100 * r['occupied_common_spread']:.0f} %"
                        for rule, r in res["rules"].items()) + ".", "",
            f"![held-out first returns]({folder.as_posix()}/rate_real.png)"]
    t = res.get("tuning")
    if t:
        out += ["", common.template("rate-real-tuning", t=t, last_mapped=t["mapped_frames"][1] - 1,
                                    last_judged=t["judged_frames"][1] - 1)]
        for row in t["rows"]:
            f = row["every_1"]
            occ = " / ".join(f"{row[f'every_{s}']['occupied']:,}" for s in STRIDES)
            out.append(f"| {row['bright_share']:g} | {row['share_z']:g} | {100 * f['agreement']:.1f} % | "
                       f"{100 * f['phantom_rate']:.1f} % | {100 * f['missing_rate']:.1f} % | {occ} |")
    return "\n".join(out)


SECTION = Section("rate-real", "## The rules at the sonar's own rate: the full real tank run (issue #28)",
                  "rate_real.json", markdown)


def _picture(res: dict, path: Path) -> None:
    fig, (ax0, ax1) = common.pyplot().subplots(1, 2, figsize=(12, 4.4), dpi=90)
    colours = {"plain": "#1f77b4", "visible": "#d62728", "evidence": "#2ca02c"}
    for rule, r in res["rules"].items():
        c = r["every_1"].get("curve", [])
        ax0.plot([p["frames"] for p in c], [p["occupied"] for p in c], "o-", color=colours.get(rule),
                 label=rule)
    ax0.set(xscale="log", xlabel="frames mapped (frames 0-799 at the sonar's rate)", ylabel="occupied voxels",
            title="occupied voxels as pings accumulate")
    ax0.legend()
    width = 0.27
    for k, rule in enumerate(res["rules"]):
        r, x = res["rules"][rule], np.arange(len(STRIDES)) + (k - 1) * width
        agree = [r[f"every_{s}"]["judge"]["agreement"] for s in STRIDES]
        front = [r[f"every_{s}"]["judge"]["phantom_rate"] for s in STRIDES]
        ax1.bar(x, agree, width, color=colours.get(rule), label=f"{rule}: agree")
        ax1.bar(x, front, width, bottom=agree, color=colours.get(rule), alpha=0.35,
                label=f"{rule}: phantom in front")
    ax1.set_xticks(np.arange(len(STRIDES)), [f"every {s}" if s > 1 else "every frame" for s in STRIDES])
    ax1.set(ylabel="share of held-out beams with a return", title="first returns of held-out frames 800-1222",
            ylim=(0, 1.25))
    ax1.legend(fontsize=7, ncol=3, loc="upper center")
    common.save_figure(fig, path)


if __name__ == "__main__":
    raise SystemExit(main())
