"""The EKF on the full real tank run at the sonar's own rate: EKF against odometry, per variant (issue 29).

    .venv/bin/python -m bench ekf_real --out bench/results      # writes ekf_real.json
"""

from __future__ import annotations

import dataclasses
import time
import warnings
from pathlib import Path

import numpy as np

from gpumap.ekf.frontend import PointDetector
from gpumap.ekf.guard import TrustGuard
from gpumap.ekf.loop import drifting_odometry, motion_cov, pose_errors, run_ekf_loop
from gpumap.io import open_recording
from gpumap.pipeline.ekf_replay import posed_frames, trust_summary

from .common import bench_parser, compact, load_average, oasis_full_dir, run_header, write_json

#: Variant -> (keyword arguments of the filter, made fresh per run; factor on the detector's covariances).
VARIANTS = {"plain": (lambda: {}, 1.0), "guarded": (lambda: {"guard": TrustGuard()}, 1.0),
            "plain_r4": (lambda: {}, 4.0), "guarded_r4": (lambda: {"guard": TrustGuard()}, 4.0)}


def one_run(meas: list, T_rec: np.ndarray, spec, drift: float, seed: int, variant: str) -> dict:
    """One EKF run on the given slice (its first recorded pose is the start)."""
    U, T_odo = drifting_odometry(T_rec, drift, drift, seed)
    make, cov_scale = VARIANTS[variant]
    if cov_scale != 1.0:
        meas = [dataclasses.replace(m, covs=m.covs * cov_scale) for m in meas]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # the NIS monitor's warnings
        t0 = time.perf_counter()
        loop = run_ekf_loop([None] * len(T_rec), U, T_rec[0], spec, odometry_cov=motion_cov(drift, drift),
                            measure=lambda k, _img: meas[k], ekf_kwargs=make())
        wall = time.perf_counter() - t0
    eo, ee = pose_errors(T_odo, T_rec), pose_errors(loop.poses, T_rec)
    tr = trust_summary(loop)
    tr.pop("guard_state", None)
    means = {name: {"position_mean_m": e["position_m"]["mean"], "heading_mean_rad": e["heading_rad"]["mean"]}
             for name, e in (("odometry", eo), ("ekf", ee))}
    return {"frames": len(T_rec), **means,
            "ratio_position": ee["position_m"]["mean"] / max(eo["position_m"]["mean"], 1e-12),
            "ratio_heading": ee["heading_rad"]["mean"] / max(eo["heading_rad"]["mean"], 1e-12), "trust": tr,
            "ms_per_ping_track_ekf": {"mean": float(loop.ms_track.mean()),
                                      "p95": float(np.percentile(loop.ms_track, 95))}, "wall_s": wall}


def _table(runs: list[dict]) -> dict:
    """Per (variant, drift, slice): ratios over the seeds (mean, max) and the per-seed lists."""
    out: dict = {}
    for r in runs:
        out.setdefault(f"{r['variant']}|{r['drift']}|{r['slice']}", []).append(r)
    summ = {}
    for key, rs in out.items():
        rp, rh = [r["ratio_position"] for r in rs], [r["ratio_heading"] for r in rs]
        summ[key] = {"seeds": [r["seed"] for r in rs], "ratio_position": rp, "ratio_heading": rh,
                     "ratio_position_mean": float(np.mean(rp)), "ratio_position_max": float(np.max(rp)),
                     "ratio_heading_mean": float(np.mean(rh)), "ratio_heading_max": float(np.max(rh)),
                     "pose_corrected_share_mean":
                         float(np.mean([r["trust"]["pings_pose_corrected_share"] for r in rs])),
                     "ms_per_ping_track_ekf_mean": float(np.mean([r["ms_per_ping_track_ekf"]["mean"]
                                                                  for r in rs]))}
    return summ


def prism_section(seeds: list[int], slide: float = 0.5) -> dict:
    """The prism simulation (:mod:`gpumap.sim.prism`) with 150 views and odometry drift ``k_t = 0.1``,
    ``k_r = 0.05`` (the tests' run), known associations; ``sliding``: every vertex measured at ``p +
    slide (t_k - t_0)``, moving with the sonar as a glint on a wall does. EKF/odometry mean position
    error per seed, plain and guarded."""
    from gpumap.sim.prism import PrismConfig, position_ratio, simulate

    cfg = PrismConfig(n_views=150, k_t=0.1, k_r=0.05)
    out: dict = {"config": {"n_views": 150, "k_t": 0.1, "k_r": 0.05, "slide": slide}}
    for case in ("consistent", "sliding"):
        for variant in ("plain", "guarded"):
            ratios, pose_updates = [], []
            for seed in seeds:
                g = TrustGuard() if variant == "guarded" else None
                s = slide if case == "sliding" else 0.0
                ratios.append(position_ratio(simulate(seed, cfg), g, s, seed)[0])
                pose_updates.append(0 if g is None else g.pose_updates)
            out[f"{case}|{variant}"] = {"seeds": seeds, "ratio_position": ratios,
                                        "ratio_position_mean": float(np.mean(ratios)),
                                        "pose_updates": pose_updates}
            print(f"prism {case:>10} {variant:>7}: position x{np.round(ratios, 3).tolist()} (EKF/odometry)",
                  flush=True)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = bench_parser("ekf_real", __doc__, out="bench/results")
    ap.add_argument("--data", type=Path, default=None,
                    help="the full real tank run (fan PNGs + sonar_poses.csv; "
                    "default: oasis_tank_full beside the checkout)")
    ap.add_argument("--name", default="ekf_real", help="results file stem (default ekf_real)")
    ap.add_argument("--drifts", type=float, nargs="+", default=[0.005, 0.02],
                    help="odometry drifts, m and rad a step")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4], help="drift seeds")
    ap.add_argument("--variants", nargs="+", default=["plain", "guarded"], choices=list(VARIANTS),
                    help="EKF variants")
    ap.add_argument("--split", type=int, default=800, help="first held-out frame (default 800)")
    ap.add_argument("--slices", nargs="+", default=["dev", "heldout", "full"],
                    choices=["dev", "heldout", "full"],
                    help="slices of the run")
    ap.add_argument("--no-prism", action="store_true", help="skip the simulated prism section")
    a = ap.parse_args(argv)
    doc = run_header("gpumap.bench.ekf_real/1", argv)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        prism = None if a.no_prism else prism_section(a.seeds)
    data, t0 = a.data or oasis_full_dir(), time.perf_counter()
    if data is None:
        raise SystemExit("bench.ekf_real: the full tank run was not found; get it as shared/data/README.md "
                         "says (oasis_tank_full/get_images.sh) and pass --data")
    images, T_all, spec = posed_frames(open_recording(data))
    t_load, det, t0 = time.perf_counter() - t0, PointDetector(spec), time.perf_counter()
    meas = [det.detect(im) for im in images]
    ms_detect, n = 1e3 * (time.perf_counter() - t0) / len(images), len(T_all)
    del images
    slices, runs = {"dev": (0, min(a.split, n)), "heldout": (min(a.split, n), n), "full": (0, n)}, []
    for variant in a.variants:
        for drift in a.drifts:
            for seed in a.seeds:
                for name in a.slices:
                    s0, s1 = slices[name]
                    if s1 - s0 < 2:
                        continue
                    r = one_run(meas[s0:s1], T_all[s0:s1], spec, drift, seed, variant)
                    r.update({"variant": variant, "drift": drift, "seed": seed, "slice": name,
                              "frame_range": [s0, s1]})
                    runs.append(r)
                    print(f"{variant:>8} drift {drift:g} seed {seed} {name:>7}: "
                          f"position x{r['ratio_position']:.3f} heading x{r['ratio_heading']:.3f} "
                          "(EKF/odometry), pose corrected at "
                          f"{100 * r['trust']['pings_pose_corrected_share']:.0f} % of pings, "
                          f"{r['ms_per_ping_track_ekf']['mean']:.1f} ms/ping", flush=True)
    doc.update({
        "data": str(data), "frames": n, "split": a.split, "slices": {k: list(v) for k, v in slices.items()},
        "drift_model": "U_k = T_{k-1}^-1 T_k Exp(w_k), w_k ~ N(0, diag(d^2 I3, d^2 I3)), d = drift (m and "
                       "rad per step), seeded; chained from the slice's first recorded pose",
        "load_seconds": t_load, "ms_per_ping_detect": ms_detect, "load_avg_end": load_average(),
        "cost_note": "ms per ping on this machine's CPU under the load averages recorded at start and end (2 "
                     "cores shared with other work); detect is timed once per ping, track + EKF per run",
        "summary": _table(runs), "prism": prism, "runs": runs})
    print(f"wrote {write_json(a.out / f'{a.name}.json', compact(doc, 5))}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
