"""EKF front-end bench (issue #23): measurements found in pings, association, the EKF loop.

    .venv/bin/python -m bench.frontend [--seeds 5] [--out bench/results] [--no-progress]

Writes ``OUT/frontend.json``: ``sim`` (the tracker's EKF on the simulator's returns without ids against
the true-id EKF), ``sim_detector``, ``real_tank`` (bench/README.md tells more).
"""

from __future__ import annotations

import json
import math
import sys
import time
import warnings
from collections import Counter
from pathlib import Path

import numpy as np

from . import common
from .common import Section, bench_parser, load_average, oasis_tank_dir, render_pings, write_json

NOISES = (0.005, 0.02)
RANGE_SIGMA_M = 0.01
BEARING_SIGMA_RAD = math.radians(0.3)


def _dvl_hook(sc, pings, rng):
    """``before_update(k, ekf)`` fusing the scene's DVL as ``gpumap demo`` does (None without one)."""
    from gpumap.sim.demo import DVL_RANGE_SIGMA_M, SAND_ROUGHNESS_M, _dvl_rays_S, _seabed_roughness
    from gpumap.sim.dvl import DVLSimulator
    from gpumap.sim.scenes import SURVEY, TANK, mounts, survey_mounts

    from gpumap.lie import se3_inverse

    if sc.name not in ("tank", "survey"):
        return None
    dvl = DVLSimulator(sc)
    if sc.name == "tank":
        (A, B), floor_d, rough = mounts(), float(TANK["floor_z_m"]), SAND_ROUGHNESS_M
    else:
        (A, B), floor_d = survey_mounts(), float(SURVEY["floor_z_m"])
        rough = _seabed_roughness(sc, floor_d)
    T_S_D, n_W = se3_inverse(A) @ B, np.array([0.0, 0.0, 1.0])
    ranges = [dvl.ranges(p.T_W_S @ T_S_D) for p in pings]
    ranges = [r + rng.normal(0, DVL_RANGE_SIGMA_M, r.shape) for r in ranges]

    def hook(k, ekf):
        r = ranges[k]
        o, u = _dvl_rays_S(ekf.pose, T_S_D, dvl._rays_D)
        cos_inc = np.abs((u @ ekf.pose[:3, :3].T)[:, 2])
        for j in np.flatnonzero(np.isfinite(r) & (cos_inc > 0.1)):
            s_j = math.hypot(DVL_RANGE_SIGMA_M, rough / cos_inc[j])
            ekf.update_plane_ranges(o[j:j + 1], u[j:j + 1], r[j:j + 1], n_W, floor_d, s_j)

    return hook


def _sim_run(sc, pings, noise: float, seed: int, tracker_kwargs: dict | None = None) -> dict:
    """True-id EKF against the tracker EKF on the same odometry, returns and DVL."""
    from gpumap.ekf import SonarEKF
    from gpumap.ekf.frontend import PointMeasurements
    from gpumap.ekf.loop import EKF_DEFAULTS, drifting_odometry, motion_cov, pose_errors, run_ekf_loop

    T_true = np.stack([p.T_W_S for p in pings])
    U, T_odo = drifting_odometry(T_true, noise, noise, seed)
    Q, rng = motion_cov(noise, noise), np.random.default_rng([seed, 7])
    noisy = [(p.feature_ranges_m + rng.normal(0, RANGE_SIGMA_M, len(p.feature_ids)),
              p.feature_bearings_rad + rng.normal(0, BEARING_SIGMA_RAD, len(p.feature_ids))) for p in pings]
    perms = [rng.permutation(len(p.feature_ids)) for p in pings]
    truth = dict(zip(sc.feature_ids.tolist(), sc.features_W, strict=True))
    # the true-id EKF
    ekf = SonarEKF(T_true[0], np.zeros((6, 6)), **{**EKF_DEFAULTS, "vfov_rad": sc.sonar_spec.vfov_rad})
    hook = _dvl_hook(sc, pings, np.random.default_rng([seed, 11]))
    P_true_id = np.zeros_like(T_true)
    for k, p in enumerate(pings):
        if k:
            ekf.predict(U[k], Q)
        if hook:
            hook(k, ekf)
        if len(p.feature_ids):
            ekf.update(p.feature_ids, *noisy[k])
        P_true_id[k] = ekf.pose
    L_true_id = ekf.landmarks
    # the tracker's EKF: the same returns, shuffled, without ids, and the same DVL noise
    cov = np.diag([RANGE_SIGMA_M**2, BEARING_SIGMA_RAD**2])

    def measure(k, _img):
        q = perms[k]
        return PointMeasurements.from_arrays(noisy[k][0][q], noisy[k][1][q], np.tile(cov, (len(q), 1, 1)))

    res = run_ekf_loop([None] * len(pings), U, T_true[0], sc.sonar_spec, odometry_cov=Q, measure=measure,
                       before_update=_dvl_hook(sc, pings, np.random.default_rng([seed, 11])),
                       tracker_kwargs=tracker_kwargs)
    labels_true = [pings[k].feature_ids[perms[k]] for k in range(len(pings))]
    votes: dict[int, Counter] = {}
    for k, st in enumerate(res.steps):
        for j, t in enumerate(st.labels):
            votes.setdefault(int(t), Counter())[int(labels_true[k][j])] += 1
    owner = {t: c.most_common(1)[0][0] for t, c in votes.items()}
    confirmed = {t.id for t in res.tracker.tracks.values() if t.confirmed_at is not None}
    total = sum(len(x) for x in labels_true)
    tp_all = fp_all = tp_f = fp_f = 0
    for k, st in enumerate(res.steps):
        for j, t in enumerate(st.labels):
            if int(t) in confirmed:
                ok = owner[int(t)] == labels_true[k][j]
                tp_all, fp_all = tp_all + ok, fp_all + (not ok)
        for i, j in st.confirmed_hits.items():
            ok = owner[i] == labels_true[k][j]
            tp_f, fp_f = tp_f + ok, fp_f + (not ok)
    L = res.tracker.ekf.landmarks
    same = [i for i in L if owner[i] in L_true_id]
    f_trk = [float(np.linalg.norm(L[i] - truth[owner[i]])) for i in same]
    f_tid = [float(np.linalg.norm(L_true_id[owner[i]] - truth[owner[i]])) for i in same]
    e_tid, e_trk, e_odo = (pose_errors(P, T_true) for P in (P_true_id, res.poses, T_odo))
    return {
        "precision_all": tp_all / max(tp_all + fp_all, 1), "recall_all": tp_all / max(total, 1),
        "precision_fused": tp_f / max(tp_f + fp_f, 1), "recall_fused": tp_f / max(total, 1), "returns": total,
        **{f"{k}_mean_{u}": {"odometry": e_odo[f"{k}_{u}"]["mean"], "true_ids": e_tid[f"{k}_{u}"]["mean"],
                             "tracker": e_trk[f"{k}_{u}"]["mean"]}
           for k, u in (("position", "m"), ("heading", "rad"))},
        "feature_mean_m": {"true_ids": float(np.mean(f_tid)) if same else None,
                           "tracker": float(np.mean(f_trk)) if same else None, "features": len(same)},
        "tracks": res.tracker.lifetimes(), "ms_track_ekf_mean": float(res.ms_track.mean()),
    }


def _sim_detector(sc, pings, cells: float = 2.0) -> dict:
    """The detector on simulated images against the visible true features."""
    from gpumap.ekf.frontend import PointDetector

    sp = sc.sonar_spec
    det, step = PointDetector(sp), float(np.mean(np.diff(sp.bearings_rad)))
    found = visible = near = n_det = 0
    nees, ms = [], []
    for p in pings:
        t0 = time.perf_counter()
        m = det.detect(p.image)
        ms.append(1e3 * (time.perf_counter() - t0))
        n_det, visible = n_det + len(m), visible + len(p.feature_ids)
        if not len(m) or not len(p.feature_ids):
            continue
        d = np.hypot((m.ranges_m[:, None] - p.feature_ranges_m[None]) / sp.bin_size_m,
                     (m.bearings_rad[:, None] - p.feature_bearings_rad[None]) / step)
        found += int((d.min(axis=0) <= cells).sum())
        hit = d.min(axis=1) <= cells
        near += int(hit.sum())
        for j in np.flatnonzero(hit):
            f = int(np.argmin(d[j]))
            e = np.array([m.ranges_m[j] - p.feature_ranges_m[f],
                          m.bearings_rad[j] - p.feature_bearings_rad[f]])
            nees.append(float(e @ np.linalg.solve(m.covs[j], e)))
    return {"visible_features": visible, "found_within_2_cells": found,
            "found_fraction": found / max(visible, 1),
            "detections": n_det, "near_a_feature_fraction": near / max(n_det, 1),
            "nees_mean_2dof": float(np.mean(nees)) if nees else None,
            "nees_median_2dof": float(np.median(nees)) if nees else None,
            "ms_per_ping_mean": float(np.mean(ms)), "ms_per_ping_p95": float(np.percentile(ms, 95))}


def _real(path: str, seeds: int, progress: bool) -> list[dict]:
    from gpumap.io import open_recording
    from gpumap.pipeline.ekf_replay import run_ekf_replay

    rows = []
    keys = ("pose_error", "ratio_ekf_to_odometry", "map_vs_recorded", "measurements", "tracks",
            "track_consistency_recorded_poses", "recorded_step_median", "ms_per_ping", "frames")
    for noise in NOISES:
        for seed in range(seeds):
            s = run_ekf_replay(open_recording(path), odometry_noise=(noise, noise), seed=seed,
                               backend="warp-cpu", progress=False)["summary"]
            rows.append({"noise": noise, "seed": seed, **{k: s[k] for k in keys}})
            if progress:
                r = s["ratio_ekf_to_odometry"]
                print(f"real tank noise {noise} seed {seed}: EKF/odometry position {r['position_mean']:.2f}, "
                      f"heading {r['heading_mean']:.2f}", file=sys.stderr)
    return rows


def _summarise(rows: list[dict], keyf) -> dict | None:
    vals = [v for v in map(keyf, rows) if v is not None]
    if not vals:
        return None
    return {"mean": float(np.mean(vals)), "min": float(np.min(vals)), "max": float(np.max(vals))}


def _ratio(key: str, unit: str):
    return lambda r: r[f"{key}_mean_{unit}"]["tracker"] / r[f"{key}_mean_{unit}"]["true_ids"]


SIM_SUMMARY = {k: (lambda r, k=k: r[k])
               for k in ("precision_all", "recall_all", "precision_fused", "recall_fused")}
SIM_SUMMARY |= {"pose_ratio_tracker_to_true_ids": _ratio("position", "m"),
                "heading_ratio_tracker_to_true_ids": _ratio("heading", "rad"),
                "feature_ratio_tracker_to_true_ids": lambda r: (r["feature_mean_m"]["tracker"]
                                                                / r["feature_mean_m"]["true_ids"])
                if r["feature_mean_m"]["tracker"] is not None else None}
REAL_SUMMARY = {"position_ratio": lambda r: r["ratio_ekf_to_odometry"]["position_mean"],
                "heading_ratio": lambda r: r["ratio_ekf_to_odometry"]["heading_mean"],
                "map_disagree_odometry": lambda r: r["map_vs_recorded"]["odometry"]["disagree"],
                "map_disagree_ekf": lambda r: r["map_vs_recorded"]["ekf"]["disagree"],
                "ms_per_ping": lambda r: r["ms_per_ping"]["total_mean"],
                "track_consistency": lambda r: r["track_consistency_recorded_poses"]["consistent_fraction"]}


def markdown(d: dict, folder: Path | None = None) -> str:
    """The BENCHMARKS.md block of a ``frontend.json``."""
    def pc(x):
        return "–" if x is None else f"{100 * x:.1f} %"

    def mm(x):
        return "–" if x is None else f"{x['mean']:.2f} ({x['min']:.2f}–{x['max']:.2f})"

    rates = ("precision_all", "recall_all", "precision_fused", "recall_fused")
    ratios = ("pose", "heading", "feature")
    sim = [f"| {v['scene']}, {v['noise']} | " + " | ".join(pc(v["summary"][k]["mean"]) for k in rates) + " | "
           + " | ".join(mm(v["summary"][f"{k}_ratio_tracker_to_true_ids"]) for k in ratios) + " |"
           for v in d["sim"].values()]
    det = [f"| {name} | {v['visible_features']} | {pc(v['found_fraction'])} | {v['detections']} "
           f"| {pc(v['near_a_feature_fraction'])} | "
           f"{'–' if v['nees_mean_2dof'] is None else format(v['nees_mean_2dof'], '.1f')} | "
           f"{v['ms_per_ping_mean']:.1f}, {v['ms_per_ping_p95']:.1f} |"
           for name, v in d["sim_detector"].items()]
    real = [f"| {noise} | {mm(v['position_ratio'])} | {mm(v['heading_ratio'])} "
            f"| {v['map_disagree_odometry']['mean']:.0f} | {v['map_disagree_ekf']['mean']:.0f} "
            f"| {mm(v.get('track_consistency'))} | {mm(v['ms_per_ping'])} |"
            for noise, v in d["real_tank"]["summary"].items()]
    r0 = d["real_tank"]["runs"][0]
    st = r0.get("recorded_step_median")
    steps = "" if not st else (
        f"\n\nThe tank's frames are every 10th of the recording: the arm moves a median "
        f"{100 * st['translation_m']:.1f} cm and {st['rotation_deg']:.0f} deg between them, and the "
        f"detector finds {r0['measurements']['per_ping_mean']:.1f} compact returns per ping.")
    return common.template("frontend", date=d["date"], seconds=d["seconds"], command=d["command"],
                           drift_model=d["drift_model"], load0=d["loadavg_start"][0],
                           load1=d["loadavg_end"][0], sim="\n".join(sim), detector="\n".join(det),
                           real="\n".join(real), steps=steps)


SECTION = Section("frontend", "## The EKF on real pings: front-end, association, loop (issue #23)",
                  "frontend.json", markdown)


def main(argv: list[str] | None = None) -> int:
    ap = bench_parser("frontend", __doc__, out="bench/results", progress=True, report="frontend.json")
    ap.add_argument("--seeds", type=int, default=5, help="drift seeds per scene and noise level (default 5)")
    ap.add_argument("--data", default=None,
                    help="the real tank recording (default: shared/data/oasis_tank beside the checkout)")
    ap.add_argument("--scenes", nargs="+", default=["tank", "survey"],
                    help="simulated scenes (default tank survey)")
    ap.add_argument("--benchmarks", type=Path, default=None,
                    help="also write the results as a block of this Markdown file (BENCHMARKS.md)")
    a = ap.parse_args(argv)
    if SECTION.reported(a):
        return 0
    from gpumap.sim.scenes import make_scene

    a.data = a.data or str(oasis_tank_dir() or "../shared/data/oasis_tank")
    warnings.simplefilter("ignore", RuntimeWarning)  # the EKF's NIS monitor; its figures are kept below
    t_start = time.time()
    out: dict = {"schema": "gpumap-frontend/1",
                 "command": "python -m bench.frontend " + " ".join(sys.argv[1:] if argv is None else argv),
                 "date": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "loadavg_start": load_average(),
                 "drift_model": "per step U_k = T_{k-1}^-1 T_k Exp(w), w ~ N(0, s^2 I6): s m on each "
                                "translation axis and s rad on each rotation axis", "sim": {},
                 "sim_detector": {}}
    for name in a.scenes:
        sc = make_scene(name)
        pings = render_pings(sc, scene_sonar=False)
        out["sim_detector"][name] = _sim_detector(sc, pings)
        for noise in NOISES:
            rows = [_sim_run(sc, pings, noise, seed) for seed in range(a.seeds)]
            summ = {k: _summarise(rows, f) for k, f in SIM_SUMMARY.items()}
            out["sim"][f"{name}_{noise}"] = {"scene": name, "noise": noise, "seeds": a.seeds,
                                             "summary": summ, "runs": rows}
            if not a.no_progress:
                means = {k: v and round(v["mean"], 3) for k, v in summ.items()}
                print(f"sim {name} noise {noise}: " + json.dumps(means), file=sys.stderr)
    rows = _real(a.data, a.seeds, not a.no_progress)
    by_noise = {f"{n}": [r for r in rows if r["noise"] == n] for n in NOISES}
    summary = {n: {k: _summarise(rs, f) for k, f in REAL_SUMMARY.items()} for n, rs in by_noise.items()}
    out["real_tank"] = {"runs": rows, "summary": summary}
    out["loadavg_end"], out["seconds"] = load_average(), time.time() - t_start
    write_json(a.out / "frontend.json", out)
    if a.benchmarks is not None:
        SECTION.write(a.benchmarks, a.out)
    print(f"wrote {a.out / 'frontend.json'} in {out['seconds']:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
