"""The pose the vehicle trusts on the full real tank run: verified revisits and a pose graph (#39).

The recording's poses are the reference; odometry is made from them with the drift of
:func:`gpumap.ekf.loop.drifting_odometry` (per-step sigma ``d`` m and ``d`` rad, seeded), as in
``bench.ekf_real``. Per drift, seed and slice (``dev``: frames ``0 .. split-1``, the only ones
used to choose a setting; ``heldout``: ``split .. end``, started from the recorded pose at
``split``; ``full``), pose error over odometry's (mean position, mean heading) of:

- ``ekf``: what ``gpumap replay --ekf --ekf-registration`` runs: the guarded EKF on point returns plus
  the default :class:`gpumap.ekf.registrar.ScanRegistrar` (revisits, each verified by its
  image's agreement before it is fused, and its pose graph: the ping of each solve is put
  where the graph says);
- ``graph``: the pose graph (:func:`gpumap.ekf.posegraph.run_pose_graph`) over the odometry and
  the registrar's verified revisits, solved as the pings come; its poses after the last solve
  (every pose uses every closure);
- ``graph_online``: the graph's latest pose as each ping came (what a vehicle had then).

The maps: per drift and seed, frames ``0 .. split-1`` mapped (evidence rule, ``--voxel``) at each
pose source's poses of the full run (odometry, EKF, graph, recorded), each judged by the
held-out frames' first returns at their recorded poses
(:func:`gpumap.layers.first_return.first_return_score`): the share of beams whose first return the
map puts within a voxel of where the sonar measured it.

Costs are milliseconds per ping on this machine's CPU, per part, under the load averages
recorded with them (2 cores shared with other work).

Run::

    nice .venv/bin/python -m bench ekf_pose --no-progress     # writes bench/results/ekf_pose.json
"""

from __future__ import annotations

import time
import warnings
from pathlib import Path

import numpy as np

from gpumap.core.params import MapperParams
from gpumap.ekf.frontend import PointDetector, PointMeasurements
from gpumap.ekf.guard import TrustGuard
from gpumap.ekf.loop import drifting_odometry, motion_cov, pose_errors, run_ekf_loop
from gpumap.ekf.posegraph import run_pose_graph
from gpumap.ekf.registrar import ScanRegistrar
from gpumap.ekf.registration import image_descriptor
from gpumap.io import open_recording
from gpumap.layers.first_return import measured_first_returns
from gpumap.pipeline.ekf_replay import posed_frames, registration_summary

from .common import Section, bench_parser, compact, load_average, oasis_full_dir, run_header, write_json

THRESHOLD = 0.4
SOURCES = ("ekf", "graph", "graph_online")


def _ratios(T_est: np.ndarray, T_odo: np.ndarray, T_rec: np.ndarray) -> dict:
    eo, ee = pose_errors(T_odo, T_rec), pose_errors(T_est, T_rec)
    return {"position_mean_m": ee["position_m"]["mean"], "heading_mean_rad": ee["heading_rad"]["mean"],
            "ratio_position": ee["position_m"]["mean"] / max(eo["position_m"]["mean"], 1e-12),
            "ratio_heading": ee["heading_rad"]["mean"] / max(eo["heading_rad"]["mean"], 1e-12)}


def one_run(ranges, desc, meas, T_rec, spec, drift: float, seed: int) -> dict:
    """The default EKF (guarded, verified revisits) and the pose graph on one slice."""
    U, T_odo = drifting_odometry(T_rec, drift, drift, seed)
    Q = motion_cov(drift, drift)
    reg = ScanRegistrar(spec, threshold=THRESHOLD, ranges=ranges, descriptors=desc)
    la0 = load_average()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        loop = run_ekf_loop([None] * len(T_rec), U, T_rec[0], spec, odometry_cov=Q,
                            measure=lambda k, _i: meas[k], registrar=reg, ekf_kwargs={"guard": TrustGuard()})
    gr = run_pose_graph(U, Q, T_rec[0], reg.closures)
    eo = pose_errors(T_odo, T_rec)
    out = {"frames": len(T_rec),
           "odometry": {"position_mean_m": eo["position_m"]["mean"],
                        "heading_mean_rad": eo["heading_rad"]["mean"]},
           "ekf": _ratios(loop.poses, T_odo, T_rec), "graph": _ratios(gr.poses, T_odo, T_rec),
           "graph_online": _ratios(gr.online, T_odo, T_rec),
           "registration": registration_summary(reg),
           "graph_stats": {"loops": gr.loops, "loops_rejected": gr.loops_rejected, "solves": gr.solves,
                           **gr.stats},
           "ms_per_ping": {"track_ekf_registration_mean": float(loop.ms_track.mean()),
                           "graph_mean": float(gr.ms_per_ping.mean()),
                           "graph_max": float(gr.ms_per_ping.max())},
           "load_avg": [la0, load_average()]}
    out["_poses"] = {"odometry": T_odo, "ekf": loop.poses, "graph": gr.poses}
    return out


def _table(runs: list[dict]) -> dict:
    groups: dict = {}
    for r in runs:
        groups.setdefault(f"{r['drift']}|{r['slice']}", []).append(r)
    out = {}
    for key, rs in groups.items():
        cell = {"seeds": [r["seed"] for r in rs]}
        for src in SOURCES:
            rp = [r[src]["ratio_position"] for r in rs]
            rh = [r[src]["ratio_heading"] for r in rs]
            cell[src] = {"ratio_position": rp, "ratio_heading": rh,
                         "ratio_position_mean": float(np.mean(rp)), "ratio_position_max": float(np.max(rp)),
                         "ratio_heading_mean": float(np.mean(rh)), "ratio_heading_max": float(np.max(rh))}
        cell["revisits_fused_mean"] = float(np.mean([r["registration"]["revisits_fused"] for r in rs]))
        cell["loops_mean"] = float(np.mean([r["graph_stats"]["loops"] for r in rs]))
        cell["ms_per_ping"] = {k: float(np.mean([r["ms_per_ping"][k] for r in rs]))
                               for k in rs[0]["ms_per_ping"]}
        out[key] = cell
    return out


def _maps(images, spec, poses: dict, split: int, voxel: float, backend: str) -> dict:
    """Frames 0..split-1 mapped at each pose set, judged by the held-out frames at the recorded poses."""
    from gpumap import MinMaxMapper
    from gpumap.layers.first_return import first_return_score
    from gpumap.spec import auto_grid

    T_rec = poses["recorded"]
    grid = auto_grid(spec, list(T_rec), voxel)
    out = {}
    for name, T in poses.items():
        t0 = time.perf_counter()
        m = MinMaxMapper(spec, grid, backend, MapperParams(threshold=THRESHOLD))
        for i in range(0, split, 32):
            j = min(i + 32, split)
            m.integrate_batch(np.stack(images[i:j]), np.asarray(T[i:j]))
        v = m.values()
        judged = ((images[i], T_rec[i]) for i in range(split, len(T_rec)))
        s = first_return_score(v, grid, THRESHOLD, judged, spec)
        out[name] = {**s.to_dict(), "seconds": time.perf_counter() - t0}
    return out


def main(argv: list[str] | None = None) -> int:
    ap = bench_parser("ekf_pose", __doc__, out="bench/results", voxel=0.05, backend="auto", progress=True)
    ap.add_argument("--report", type=Path, default=None, metavar="BENCHMARKS_MD",
                    help="only write this benchmark's section of that file from --out")
    ap.add_argument("--data", type=Path, default=None, help="the full real tank run (default: "
                    "oasis_tank_full beside the checkout)")
    ap.add_argument("--name", default="ekf_pose", help="results file stem")
    ap.add_argument("--drifts", type=float, nargs="+", default=[0.005, 0.02])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    ap.add_argument("--split", type=int, default=800, help="first held-out frame (default 800)")
    ap.add_argument("--slices", nargs="+", default=["dev", "heldout", "full"],
                    choices=["dev", "heldout", "full"])
    ap.add_argument("--no-maps", action="store_true", help="skip the maps and their held-out judgement")
    ap.add_argument("--submaps", action="store_true",
                    help="instead: the pose graph's map of frames 0..split-1 kept as segment maps "
                         "re-mapped at each solve (gpumap.ekf.submaps), first drift and seed only; "
                         "writes NAME_submaps.json")
    ap.add_argument("--segment", type=int, default=50, help="pings per segment map (default 50)")
    ap.add_argument("--cost", type=int, default=None, metavar="REPEATS",
                    help="instead: the cost per ping of each part on the whole run (first drift and "
                         "seed), wall and CPU time, best of REPEATS; writes NAME_cost.json")
    ap.add_argument("--frontier", type=float, nargs="*", default=None, metavar="NCC",
                    help="instead: the EKF's ratios with each of these min_image_ncc values (and the "
                         "default one without point returns), on --slices dev and full; writes "
                         "NAME_frontier.json")
    a = ap.parse_args(argv)
    if SECTION.reported(a):
        return 0
    if a.submaps:
        return submaps_main(a, argv)
    if a.frontier is not None:
        return frontier_main(a, argv)
    if a.cost is not None:
        return cost_main(a, argv)
    doc = run_header("gpumap.bench.ekf_pose/1", argv)
    data = a.data or oasis_full_dir()
    if data is None:
        raise SystemExit("bench.ekf_pose: the full tank run was not found; pass --data")
    images, T_all, spec = posed_frames(open_recording(data))
    n = len(T_all)
    cost = {}
    t0 = time.perf_counter()
    ranges = np.stack([measured_first_returns(im, spec, THRESHOLD) for im in images])
    cost["first_returns"] = 1e3 * (time.perf_counter() - t0) / n
    t0 = time.perf_counter()
    desc = np.stack([image_descriptor(im) for im in images])
    cost["image_descriptor"] = 1e3 * (time.perf_counter() - t0) / n
    det = PointDetector(spec)
    t0 = time.perf_counter()
    meas = [det.detect(im) for im in images]
    cost["point_detector"] = 1e3 * (time.perf_counter() - t0) / n
    cost["load_avg"] = load_average()
    slices = {"dev": (0, min(a.split, n)), "heldout": (min(a.split, n), n), "full": (0, n)}
    runs, maps = [], {}
    for drift in a.drifts:
        for seed in a.seeds:
            for name in a.slices:
                s0, s1 = slices[name]
                r = one_run(ranges[s0:s1], desc[s0:s1], meas[s0:s1], T_all[s0:s1], spec, drift, seed)
                poses = r.pop("_poses")
                r.update({"drift": drift, "seed": seed, "slice": name, "frame_range": [s0, s1]})
                runs.append(r)
                print(f"drift {drift:g} seed {seed} {name:>7}: " + "; ".join(
                    f"{src} position x{r[src]['ratio_position']:.3f} heading x{r[src]['ratio_heading']:.3f}"
                    for src in SOURCES) + f"; revisits fused {r['registration']['revisits_fused']}, "
                    f"graph loops {r['graph_stats']['loops']} "
                    f"({r['graph_stats']['loops_rejected']} rejected); "
                    f"{r['ms_per_ping']['track_ekf_registration_mean']:.1f} + "
                    f"{r['ms_per_ping']['graph_mean']:.1f} ms/ping (load {r['load_avg'][0]})", flush=True)
                if name == "full" and not a.no_maps:
                    t0 = time.perf_counter()
                    m = _maps(images, spec, {"recorded": T_all, **poses}, slices["dev"][1], a.voxel,
                              a.backend)
                    maps.setdefault(str(drift), {})[str(seed)] = m
                    print(f"  maps of frames 0-{slices['dev'][1] - 1} judged by the held-out first returns: "
                          + ", ".join(f"{k} {100 * v['agreement']:.1f} %" for k, v in m.items())
                          + f" ({time.perf_counter() - t0:.0f} s)", flush=True)
    map_summary = {}
    for drift, per_seed in maps.items():
        map_summary[drift] = {src: {"agreement": [m[src]["agreement"] for m in per_seed.values()],
                                    "agreement_mean": float(np.mean([m[src]["agreement"]
                                                                     for m in per_seed.values()]))}
                              for src in ("odometry", "ekf", "graph", "recorded")}
    doc.update({
        "data": str(data), "frames": n, "split": a.split, "slices": {k: list(v) for k, v in slices.items()},
        "threshold": THRESHOLD, "voxel_m": a.voxel,
        "registrar": {"place_threshold": ScanRegistrar(spec).place_threshold,
                      "min_image_ncc": ScanRegistrar(spec).min_image_ncc},
        "drift_model": "U_k = T_{k-1}^-1 T_k Exp(w_k), w_k ~ N(0, diag(d^2 I3, d^2 I3)), d = drift "
                       "(m and rad per step), seeded; chained from the slice's first recorded pose",
        "ms_per_ping_once": cost, "load_avg_end": load_average(),
        "cost_note": "ms per ping on this machine's CPU under the load averages recorded with each run "
                     "(2 cores shared with other work); track + EKF + registration timed together per ping, "
                     "the pose graph (nodes, edges, solves) apart",
        "summary": _table(runs), "maps": maps, "maps_summary": map_summary, "runs": runs,
    })
    path = write_json(a.out / f"{a.name}.json", compact(doc, 5))
    print(f"wrote {path}")
    return 0


def _timed(fn):
    w, c = time.perf_counter(), time.process_time()
    out = fn()
    return out, time.perf_counter() - w, time.process_time() - c


def cost_main(a, argv) -> int:
    """``--cost``: milliseconds per ping of each part, wall and CPU (this process's), best of N."""
    doc = run_header("gpumap.bench.ekf_pose_cost/1", argv)
    data = a.data or oasis_full_dir()
    images, T, spec = posed_frames(open_recording(data))
    n, drift, seed = len(T), a.drifts[0], a.seeds[0]
    U, _ = drifting_odometry(T, drift, drift, seed)
    Q = motion_cov(drift, drift)
    det = PointDetector(spec)
    best: dict = {}

    def keep(name, wall, cpu):
        w, c = 1e3 * wall / n, 1e3 * cpu / n
        old = best.get(name)
        best[name] = {"wall_ms": min(w, old["wall_ms"]) if old else w,
                      "cpu_ms": min(c, old["cpu_ms"]) if old else c}

    for _ in range(max(1, a.cost)):
        la = load_average()
        meas, w, c = _timed(lambda: [det.detect(im) for im in images])
        keep("point_detector", w, c)
        ranges, w, c = _timed(lambda: np.stack([measured_first_returns(im, spec, THRESHOLD)
                                                 for im in images]))
        keep("first_returns", w, c)
        desc, w, c = _timed(lambda: np.stack([image_descriptor(im) for im in images]))
        keep("image_descriptor", w, c)
        for name, kw in (("tracker_ekf", None), ("tracker_ekf_registration_graph", {})):
            def loop(kw=kw, meas=meas, ranges=ranges, desc=desc):
                reg = None if kw is None else ScanRegistrar(spec, threshold=THRESHOLD, ranges=ranges,
                                                             descriptors=desc, **kw)
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", RuntimeWarning)
                    run_ekf_loop([None] * n, U, T[0], spec, odometry_cov=Q,
                                 measure=lambda i, _im: meas[i], registrar=reg,
                                 ekf_kwargs={"guard": TrustGuard()})
                return reg
            reg, w, c = _timed(loop)
            keep(name, w, c)
        best.setdefault("load_avg", []).append([la, load_average()])
        print("cost so far (best, ms per ping wall / CPU): " + ", ".join(
            f"{k} {v['wall_ms']:.2f} / {v['cpu_ms']:.2f}" for k, v in best.items() if k != "load_avg"),
            flush=True)
    parts = ("point_detector", "first_returns", "image_descriptor", "tracker_ekf_registration_graph")
    doc.update({"data": str(data), "frames": n, "drift": drift, "seed": seed, "repeats": a.cost,
                "best": best,
                "total_default_cpu_ms": float(sum(best[p]["cpu_ms"] for p in parts)),
                "total_default_wall_ms": float(sum(best[p]["wall_ms"] for p in parts)),
                "note": "wall and CPU time of this process per ping over the whole run, best of the repeats; "
                        "the machine's 2 cores were shared with other work (load averages recorded)"})
    path = write_json(a.out / f"{a.name}_cost.json", compact(doc, 5))
    print(f"wrote {path}")
    return 0


def frontier_main(a, argv) -> int:
    """``--frontier``: how much mean gain each verification threshold buys for how much worst case."""
    doc = run_header("gpumap.bench.ekf_pose_frontier/1", argv)
    data = a.data or oasis_full_dir()
    images, T_all, spec = posed_frames(open_recording(data))
    n = len(T_all)
    ranges = np.stack([measured_first_returns(im, spec, THRESHOLD) for im in images])
    desc = np.stack([image_descriptor(im) for im in images])
    det = PointDetector(spec)
    meas = [det.detect(im) for im in images]
    del images
    slices = {"dev": (0, min(a.split, n)), "full": (0, n)}
    slices = {k: v for k, v in slices.items() if k in a.slices} or slices
    values = a.frontier or [0.95, 0.97, 0.99]
    settings = {f"ncc {v:g}": {"min_image_ncc": v} for v in values}
    settings["ncc 0.97, no point returns"] = {"_points": False}
    z = np.zeros(0)
    empty = PointMeasurements(z, z, np.zeros((0, 2, 2)), z, z, z, z)
    out = {}
    for label, kw in settings.items():
        for drift in a.drifts:
            for name, (s0, s1) in slices.items():
                rp, rh = [], []
                for seed in a.seeds:
                    U, T_odo = drifting_odometry(T_all[s0:s1], drift, drift, seed)
                    reg = ScanRegistrar(spec, threshold=THRESHOLD, ranges=ranges[s0:s1],
                                        descriptors=desc[s0:s1],
                                        **{k: v for k, v in kw.items() if k[0] != "_"})
                    points = kw.get("_points", True)
                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore", RuntimeWarning)
                        loop = run_ekf_loop([None] * (s1 - s0), U, T_all[s0], spec,
                                            odometry_cov=motion_cov(drift, drift),
                                            measure=(lambda k, _i, s0=s0: meas[s0 + k]) if points
                                            else (lambda k, _i: empty), registrar=reg,
                                            ekf_kwargs={"guard": TrustGuard()} if points else None)
                    r = _ratios(loop.poses, T_odo, T_all[s0:s1])
                    rp.append(r["ratio_position"])
                    rh.append(r["ratio_heading"])
                out[f"{label}|{drift}|{name}"] = {"setting": kw, "ratio_position": rp, "ratio_heading": rh,
                                                  "ratio_position_mean": float(np.mean(rp)),
                                                  "worst": float(max(max(rp), max(rh)))}
                print(f"{label:>18} drift {drift:g} {name:>4}: position mean x{np.mean(rp):.3f}, worst of "
                      f"position and heading x{max(max(rp), max(rh)):.3f}", flush=True)
    doc.update({"data": str(data), "frames": n, "seeds": a.seeds, "drifts": a.drifts, "split": a.split,
                "frontier": out, "load_avg_end": load_average()})
    path = write_json(a.out / f"{a.name}_frontier.json", compact(doc, 5))
    print(f"wrote {path}")
    return 0


def submaps_main(a, argv) -> int:
    """``--submaps``: the graph's map kept as segment maps, re-mapped where each solve moved them."""
    from gpumap.ekf.submaps import SegmentMaps
    from gpumap.layers.first_return import first_return_score
    from gpumap.spec import auto_grid

    doc = run_header("gpumap.bench.ekf_pose_submaps/1", argv)
    data = a.data or oasis_full_dir()
    images, T_all, spec = posed_frames(open_recording(data))
    split, drift, seed = min(a.split, len(T_all)), a.drifts[0], a.seeds[0]
    ranges = np.stack([measured_first_returns(im, spec, THRESHOLD) for im in images[:split]])
    desc = np.stack([image_descriptor(im) for im in images[:split]])
    det = PointDetector(spec)
    meas = [det.detect(im) for im in images[:split]]
    T = T_all[:split]
    U, T_odo = drifting_odometry(T, drift, drift, seed)
    Q = motion_cov(drift, drift)
    reg = ScanRegistrar(spec, threshold=THRESHOLD, ranges=ranges, descriptors=desc)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        run_ekf_loop([None] * split, U, T[0], spec, odometry_cov=Q, measure=lambda k, _i: meas[k],
                     registrar=reg, ekf_kwargs={"guard": TrustGuard()})
    grid = auto_grid(spec, list(T_all), a.voxel)
    sm = SegmentMaps(spec, grid, segment=a.segment, backend=a.backend, threshold=THRESHOLD)
    per_solve = []

    def on_solve(k, poses):
        t0 = time.perf_counter()
        done = sm.update(images, poses)
        per_solve.append({"ping": int(k), "segments": len(done), "of": (k + a.segment) // a.segment,
                          "seconds": time.perf_counter() - t0})

    la0 = load_average()
    gr = run_pose_graph(U, Q, T[0], reg.closures, on_solve=on_solve)
    t0 = time.perf_counter()
    sm.update(images, gr.poses)  # the pings after the last solve
    t_last = time.perf_counter() - t0
    t0 = time.perf_counter()
    vals = sm.values()
    t_merge = time.perf_counter() - t0
    judged = ((images[i], T_all[i]) for i in range(split, len(T_all)))
    score = first_return_score(vals, grid, THRESHOLD, judged, spec)
    segs = (split + a.segment - 1) // a.segment
    doc.update({"data": str(data), "frames_mapped": split, "drift": drift, "seed": seed, "segment": a.segment,
                "segments": segs, "solves": gr.solves, "per_solve": per_solve,
                "segment_integrations": sm.integrations,
                "full_remap_integrations": sum(p["of"] for p in per_solve) + segs,
                "seconds_remap_total": sum(p["seconds"] for p in per_solve) + t_last,
                "seconds_merge": t_merge,
                "heldout_first_returns": score.to_dict(), "load_avg": [la0, load_average()],
                "note": "segments re-mapped at each solve where the solution moved any pose by more than a "
                        "quarter voxel or 0.005 rad, plus those that gained pings; the merged map equals one "
                        "mapper's of every ping at the poses each segment was last mapped with "
                        "(tests/test_ekf_posegraph.py)"})
    path = write_json(a.out / f"{a.name}_submaps.json", compact(doc, 5))
    print(f"segment maps: {sm.integrations} segment integrations over {gr.solves} solves (re-mapping every "
          f"segment each time: {doc['full_remap_integrations']}); held-out agreement "
          f"{100 * score.agreement:.1f} %; wrote {path}")
    return 0


def markdown(res: dict, folder: Path) -> str:
    """The BENCHMARKS.md block of ``ekf_pose.json`` (and ``ekf_pose_submaps.json`` beside it, if there)."""
    s = res["summary"]
    drifts = sorted({float(k.split("|")[0]) for k in s})
    seeds = s[next(iter(s))]["seeds"]
    names = {"ekf": "EKF, verified revisits (`--ekf-registration`)", "graph": "pose graph",
             "graph_online": "pose graph, online"}
    out = [HEADING, "",
           f"`python -m bench ekf_pose` ({res['machine']['cpu_model']}, load "
           f"{res['machine']['load_avg_start'][0]:.1f} at the start): the full real run's "
           f"{res['frames']} frames, "
           f"odometry drifting by the given sigma per step (m and rad), seeds {', '.join(map(str, seeds))}; "
           "pose error over odometry's, mean / worst seed (below 1: better than odometry). Frames 0-799 "
           "(dev) chose every setting; 800-1222 (held-out) were replayed from the recorded pose at 800 "
           "(they revisit nothing of their own, so nothing there can correct the pose).", "",
           "| pose | drift | position dev | held-out | full | heading dev | held-out | full |",
           "|---|---|---|---|---|---|---|---|"]
    for src in SOURCES:
        for d in drifts:
            cells = [s.get(f"{d}|{sl}") for sl in ("dev", "heldout", "full")]
            if not all(cells):
                continue
            pos = [f"{c[src]['ratio_position_mean']:.2f} / {c[src]['ratio_position_max']:.2f}" for c in cells]
            hd = [f"{c[src]['ratio_heading_mean']:.2f} / {c[src]['ratio_heading_max']:.2f}" for c in cells]
            out.append(f"| {names[src]} | {d:g} | " + " | ".join(pos + hd) + " |")
    ms = res.get("maps_summary") or {}
    if ms:
        out += ["", "Frames 0-799 mapped at each pose source's poses (5 cm, evidence rule), judged by the "
                "held-out frames' first returns at their recorded poses: share of beams the map agrees with, "
                "mean of the seeds.", "", "| drift | odometry | EKF | pose graph | recorded poses |",
                "|---|---|---|---|---|"]
        for d in sorted(ms, key=float):
            out.append(f"| {float(d):g} | " + " | ".join(
                f"{100 * ms[d][k]['agreement_mean']:.1f} %" for k in ("odometry", "ekf", "graph", "recorded"))
                + " |")
    sub = folder / "ekf_pose_submaps.json"
    if sub.exists():
        import json

        d = json.loads(sub.read_text())
        out += ["", "Re-integrating the map from corrected poses (`python -m bench ekf_pose --submaps`, "
                f"drift {d['drift']:g}, seed {d['seed']}, frames 0-{d['frames_mapped'] - 1} in "
                f"{d['segments']} segments of {d['segment']} pings): over the graph's {d['solves']} solves, "
                f"{d['segment_integrations']} "
                f"segment maps were (re-)integrated where a solve moved their poses, against "
                f"{d['full_remap_integrations']} to re-map every segment each time "
                f"({d['seconds_remap_total']:.0f} s in all, load {d['load_avg'][0][0]:.1f}); merging them "
                f"took {d['seconds_merge']:.1f} s and gives exactly one mapper's map of every ping at the "
                "poses each segment was last mapped with, each within a quarter voxel and 0.005 rad of the "
                "final ones (held-out first returns agreed: "
                f"{100 * d['heldout_first_returns']['agreement']:.1f} %; the whole run's graph poses mapped "
                "at once, same drift and seed, above: "
                f"{100 * res['maps'][str(d['drift'])][str(d['seed'])]['graph']['agreement']:.1f} %)."]
    co = folder / "ekf_pose_cost.json"
    if co.exists():
        import json

        d = json.loads(co.read_text())
        b = d["best"]
        names = {"point_detector": "point detector", "first_returns": "first returns",
                 "image_descriptor": "image descriptor", "tracker_ekf": "tracker + EKF without registration",
                 "tracker_ekf_registration_graph": "tracker + EKF + verified revisits + pose graph"}
        la = [x[0][0] for x in b["load_avg"]]
        out += ["", f"Cost per ping, part by part (`python -m bench ekf_pose --cost {d['repeats']}`: the "
                f"whole run, drift {d['drift']:g}, seed {d['seed']}, best of {d['repeats']}; "
                f"{res['machine']['cpu_model']}, 2 cores shared with other work, load "
                f"{min(la):.1f}-{max(la):.1f}). CPU time is this process's, the fairer figure on a loaded "
                "machine.",
                "", "| part | wall ms | CPU ms |", "|---|---|---|"]
        out += [f"| {names[k]} | {b[k]['wall_ms']:.2f} | {b[k]['cpu_ms']:.2f} |" for k in names if k in b]
        out.append("| total with `--ekf-registration` (detector, first returns, descriptor, tracker + EKF + "
                   f"revisits + graph) | {d['total_default_wall_ms']:.2f} | "
                   f"{d['total_default_cpu_ms']:.2f} |")
    fr = folder / "ekf_pose_frontier.json"
    if fr.exists():
        import json

        f = json.loads(fr.read_text())["frontier"]
        labels = list(dict.fromkeys(k.split("|")[0] for k in f))
        cols = sorted({tuple(k.split("|")[1:]) for k in f}, key=lambda t: (t[1] != "dev", float(t[0])))
        out += ["", "The frontier (`python -m bench ekf_pose --frontier`): the EKF with each verification "
                "threshold (`min_image_ncc`; the default 0.97 was chosen on dev), mean position ratio / "
                "worst seed's position or heading ratio, 5 seeds. The worst case is no monotone function of "
                "the threshold: it is set by where the pose stands when the revisits end and by the "
                "unrevisited 420 frames after them, where odometry's own drift may happen to shrink.", "",
                "| revisits | " + " | ".join(f"{sl} {float(d):g}" for d, sl in cols) + " |",
                "|---" * (len(cols) + 1) + "|"]
        main = [s.get(f"{d}|{sl}") for d, sl in cols]
        if all(main):
            out.append("| ncc 0.97 (the setting above) | " + " | ".join(
                f"{c['ekf']['ratio_position_mean']:.2f} / "
                f"{max(c['ekf']['ratio_position_max'], c['ekf']['ratio_heading_max']):.2f}"
                for c in main) + " |")
        for lab in labels:
            out.append(f"| {lab} | " + " | ".join(
                f"{f[f'{lab}|{d}|{sl}']['ratio_position_mean']:.2f} / {f[f'{lab}|{d}|{sl}']['worst']:.2f}"
                for d, sl in cols) + " |")
    c = res["ms_per_ping_once"]
    full = [s[f"{d}|full"] for d in drifts if f"{d}|full" in s]
    if full:
        tr = np.mean([f["ms_per_ping"]["track_ekf_registration_mean"] for f in full])
        gm = np.mean([f["ms_per_ping"]["graph_mean"] for f in full])
        gx = max(f["ms_per_ping"]["graph_max"] for f in full)
        out += ["", "Cost per ping on the whole run, this CPU, loaded by other work (load "
                f"{c['load_avg'][0]:.1f} to {res['load_avg_end'][0]:.1f}): point detector "
                f"{c['point_detector']:.1f} ms, first returns {c['first_returns']:.2f} ms, image descriptor "
                f"{c['image_descriptor']:.2f} ms, tracker + EKF + registration with its pose graph "
                f"{tr:.1f} ms; the pose graph alone, run apart, {gm:.1f} ms on average (its slowest ping, "
                f"a solve, {gx:.0f} ms: a back end can solve beside the pings)."]
    return "\n".join(out)


HEADING = "## The pose the vehicle trusts: verified revisits and a pose graph (issue #39)"
SECTION = Section("ekf-pose", HEADING, "ekf_pose.json", markdown)

if __name__ == "__main__":
    raise SystemExit(main())
