"""EKF bench: the prism simulation of Mai et al. (Fig. 7, Fig. 8b) over many seeds, NEES
consistency, an odometry-noise sweep, and the cost of an update vs the number of features.

Run::

    .venv/bin/python -m bench.ekf_bench --out DIR [--seeds 50]

Writes ``DIR/ekf_bench.json`` and PNG figures (``ekf_fig7_pose_error.png``,
``ekf_fig8b_feature_error.png``, ``ekf_nees.png``, ``ekf_cost.png``, ``ekf_scene.png``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np
from gpumap.sim.prism import (
    PrismConfig,
    measure,
    pose_error,
    run_filter,
    run_odometry,
    simulate,
)
from scipy.stats import chi2
from tqdm import tqdm

from gpumap.ekf import SonarEKF
from gpumap.lie import se3_exp


def _prism_stats(cfg: PrismConfig, seeds: int, desc: str, bar: bool = True, init: str = "arc") -> dict:
    n = cfg.n_views
    pos_ekf = np.zeros((seeds, n))
    pos_odo = np.zeros((seeds, n))
    rot_ekf = np.zeros((seeds, n))
    rot_odo = np.zeros((seeds, n))
    roll_ekf = np.zeros((seeds, n))
    roll_odo = np.zeros((seeds, n))
    feat = np.zeros((seeds, n, 8))
    pose_nees = np.zeros((seeds, n))
    lm_nees = np.zeros((seeds, n))
    rejected = 0
    last = None
    for s in tqdm(range(seeds), desc=desc, disable=not bar, leave=False):
        run = simulate(s, cfg)
        tr = run_filter(run, init=init)
        To = run_odometry(run)
        for k in range(n):
            e = pose_error(tr.T_W_S[k], run.T_W_S[k])
            o = pose_error(To[k], run.T_W_S[k])
            pos_ekf[s, k] = np.linalg.norm(tr.T_W_S[k, :3, 3] - run.T_W_S[k, :3, 3])
            pos_odo[s, k] = np.linalg.norm(To[k, :3, 3] - run.T_W_S[k, :3, 3])
            rot_ekf[s, k] = np.linalg.norm(e[3:])
            rot_odo[s, k] = np.linalg.norm(o[3:])
            # The paper's psi (roll about the boresight) error, as in its Fig. 7(b).
            roll_ekf[s, k] = abs(e[3])
            roll_odo[s, k] = abs(o[3])
        feat[s] = np.linalg.norm(tr.landmarks - run.points_W[None], axis=2)
        pose_nees[s] = tr.pose_nees
        lm_nees[s] = tr.landmark_nees
        rejected += tr.rejected
        last = (run, tr)
    final = feat[:, -1].mean(axis=1)
    return dict(
        pos_ekf=pos_ekf, pos_odo=pos_odo, rot_ekf=rot_ekf, rot_odo=rot_odo,
        roll_ekf=roll_ekf, roll_odo=roll_odo, feat=feat, pose_nees=pose_nees, lm_nees=lm_nees,
        rejected=rejected, final=final, last=last,
    )


def _time_updates(n_features: int, reps: int, init: str = "arc") -> dict:
    """Median time of one predict and one update with all ``n_features`` re-observed."""
    rng = np.random.default_rng(0)
    pts = np.column_stack([
        rng.uniform(2.0, 4.0, n_features),
        rng.uniform(-1.0, 1.0, n_features),
        rng.uniform(-0.2, 0.2, n_features),
    ])
    ekf = SonarEKF(np.eye(4), np.zeros((6, 6)), range_sigma_m=0.003, bearing_sigma_rad=np.deg2rad(0.1),
                   vfov_rad=np.deg2rad(14.0), gate_prob=None, init=init)
    ids, r, b = measure(np.eye(4), pts, rng, 0.003, np.deg2rad(0.1))
    ekf.update(ids, r, b)
    U = se3_exp(np.array([0.001, 0.0, 0.0, 0.001, 0.0, 0.0]))
    Q = np.diag([1e-8] * 6)
    T = np.eye(4)
    t_up, t_pr = [], []
    for _ in range(reps):
        t0 = time.perf_counter()
        ekf.predict(U, Q)
        t1 = time.perf_counter()
        T = T @ U
        ids, r, b = measure(T, pts, rng, 0.003, np.deg2rad(0.1))
        t2 = time.perf_counter()
        ekf.update(ids, r, b)
        t3 = time.perf_counter()
        t_pr.append(t1 - t0)
        t_up.append(t3 - t2)
    return dict(n_features=n_features, observed=int(len(ids)), state_dim=6 + 3 * n_features,
                update_us_median=1e6 * float(np.median(t_up)), predict_us_median=1e6 * float(np.median(t_pr)))


def _band(dof: int, seeds: int, p: float = 0.95) -> tuple[float, float]:
    lo, hi = chi2.ppf([(1 - p) / 2, (1 + p) / 2], dof * seeds) / seeds
    return float(lo), float(hi)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True, type=Path, help="output folder for JSON and PNGs")
    ap.add_argument("--seeds", type=int, default=50)
    ap.add_argument("--sweep-seeds", type=int, default=20)
    ap.add_argument("--reps", type=int, default=200, help="timed updates per feature count")
    ap.add_argument("--init", default="arc", choices=["arc", "triangulate"],
                    help="feature initialisation of SonarEKF (init=)")
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)

    cfg = PrismConfig()
    st = _prism_stats(cfg, args.seeds, "prism seeds", init=args.init)
    S = args.seeds
    lo6, hi6 = _band(6, S)
    lo24, hi24 = _band(24, S)
    pose_nees_mean = np.nanmean(st["pose_nees"][:, 1:], axis=0)
    lm_nees_mean = st["lm_nees"].mean(axis=0)
    final = st["final"]

    # Odometry-noise sweep: feature height is held by odometry pitch (see sim/prism.py).
    sweep = []
    for scale in tqdm([0.25, 0.5, 1.0, 2.0, 5.0, 10.0], desc="odometry sweep", leave=False):
        c = dataclasses.replace(cfg, k_t=cfg.k_t * scale, k_r=cfg.k_r * scale,
                                k_rt_rad_per_m=cfg.k_rt_rad_per_m * scale)
        s2 = _prism_stats(c, args.sweep_seeds, f"x{scale}", bar=False, init=args.init)
        sweep.append(dict(odometry_noise_scale=scale, k_t=c.k_t, k_r=c.k_r,
                          final_feature_error_m_mean=float(s2["final"].mean()),
                          final_feature_error_m_std=float(s2["final"].std()),
                          final_position_error_m_ekf=float(s2["pos_ekf"][:, -1].mean()),
                          final_position_error_m_odometry=float(s2["pos_odo"][:, -1].mean())))

    counts = [8, 16, 32, 64, 100, 150, 200]
    timing = [_time_updates(n, args.reps, args.init) for n in tqdm(counts, desc="timing", leave=False)]

    summary = dict(
        config=dataclasses.asdict(cfg),
        seeds=S,
        init=args.init,
        final_feature_error_m=dict(mean=float(final.mean()), std=float(final.std()),
                                   median=float(np.median(final)), max=float(final.max())),
        final_feature_error_m_per_vertex=st["feat"][:, -1].mean(axis=0).tolist(),
        initial_feature_error_m_per_vertex=st["feat"][:, 0].mean(axis=0).tolist(),
        position_error_m_mean_per_view=dict(
            ekf=st["pos_ekf"].mean(0).tolist(), odometry=st["pos_odo"].mean(0).tolist()
        ),
        rotation_error_deg_mean_per_view=dict(ekf=np.rad2deg(st["rot_ekf"].mean(0)).tolist(),
                                              odometry=np.rad2deg(st["rot_odo"].mean(0)).tolist()),
        pose_nees=dict(mean_per_view=pose_nees_mean.tolist(), overall=float(pose_nees_mean.mean()),
                       band95=[lo6, hi6],
                       views_inside=int(((pose_nees_mean >= lo6) & (pose_nees_mean <= hi6)).sum()),
                       views=int(pose_nees_mean.size), dof=6),
        landmark_nees=dict(mean_per_view=lm_nees_mean.tolist(), final=float(lm_nees_mean[-1]),
                           band95=[lo24, hi24],
                           views_inside=int(((lm_nees_mean >= lo24) & (lm_nees_mean <= hi24)).sum()),
                           views=int(lm_nees_mean.size), dof=24,
                           note="anchored (r, az, el) coordinates: the filter's own Gaussian"),
        gated_returns=int(st["rejected"]),
        odometry_sweep=sweep,
        timing=timing,
    )
    (args.out / "ekf_bench.json").write_text(json.dumps(summary, indent=2))
    _figures(args.out, st, summary)
    print(json.dumps({k: summary[k] for k in ("final_feature_error_m", "gated_returns")}, indent=2))
    print(f"pose NEES mean {summary['pose_nees']['overall']:.2f} band95 [{lo6:.2f}, {hi6:.2f}], "
          f"{summary['pose_nees']['views_inside']}/{summary['pose_nees']['views']} views inside")
    print(f"landmark NEES final {lm_nees_mean[-1]:.2f} band95 [{lo24:.2f}, {hi24:.2f}], "
          f"{summary['landmark_nees']['views_inside']}/{summary['landmark_nees']['views']} views inside")
    for t in timing:
        print(f"{t['n_features']:4d} features: update {t['update_us_median']:8.1f} us, "
              f"predict {t['predict_us_median']:6.1f} us (median)")
    for s in sweep:
        print(f"odometry x{s['odometry_noise_scale']:<5}: final feature error "
              f"{s['final_feature_error_m_mean']:.4f} +- {s['final_feature_error_m_std']:.4f} m")
    return 0


def _figures(out: Path, st: dict, summary: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = st["pos_ekf"].shape[1]
    v = np.arange(n)

    def band(ax, x, a, color, label):
        m, lo, hi = a.mean(0), np.percentile(a, 25, axis=0), np.percentile(a, 75, axis=0)
        ax.plot(x, m, color=color, marker="o", ms=3, label=label)
        ax.fill_between(x, lo, hi, color=color, alpha=0.2)

    fig, axs = plt.subplots(1, 3, figsize=(15, 4))
    band(axs[0], v, 1000 * st["pos_ekf"], "C3", "EKF")
    band(axs[0], v, 1000 * st["pos_odo"], "C0", "odometry only")
    axs[0].set(xlabel="view", ylabel="position error [mm]", title="(a) camera position error")
    band(axs[1], v, np.rad2deg(st["roll_ekf"]), "C3", "EKF")
    band(axs[1], v, np.rad2deg(st["roll_odo"]), "C0", "odometry only")
    axs[1].set(xlabel="view", ylabel="|roll error| [deg]", title="(b) psi (roll about boresight) error")
    band(axs[2], v, np.rad2deg(st["rot_ekf"]), "C3", "EKF")
    band(axs[2], v, np.rad2deg(st["rot_odo"]), "C0", "odometry only")
    axs[2].set(xlabel="view", ylabel="rotation error angle [deg]", title="(c) full attitude error")
    for a in axs:
        a.legend()
        a.grid(alpha=0.3)
    n_seeds = st["feat"].shape[0]
    fig.suptitle(f"Prism simulation, mean and inter-quartile band over {n_seeds} seeds (cf. Fig. 7)")
    fig.tight_layout()
    fig.savefig(out / "ekf_fig7_pose_error.png", dpi=120)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(7, 4.5))
    labels = "PQRSTUVW"
    for i in range(8):
        ax.plot(v + 1, 1000 * st["feat"][:, :, i].mean(0), marker="o", ms=3, label=labels[i])
    ax.plot(v + 1, 1000 * st["feat"].mean((0, 2)), color="k", lw=2.5, label="mean")
    ax.set_yscale("log")
    ax.axhline(8, color="gray", ls="--", lw=1)
    ax.text(1, 8.5, "8 mm", color="gray")
    ax.set(xlabel="number of observations", ylabel="feature error [mm]",
           title=f"Feature error vs observations, mean over {st['feat'].shape[0]} seeds (cf. Fig. 8b)")
    ax.legend(ncol=3)
    ax.grid(alpha=0.3, which="both")
    fig.tight_layout()
    fig.savefig(out / "ekf_fig8b_feature_error.png", dpi=120)
    plt.close(fig)

    fig, axs = plt.subplots(1, 2, figsize=(12, 4))
    pn, ln = summary["pose_nees"], summary["landmark_nees"]
    axs[0].plot(v[1:], pn["mean_per_view"], "o-", color="C3")
    axs[0].axhspan(*pn["band95"], color="C2", alpha=0.2, label="95% band")
    axs[0].axhline(6, color="k", lw=0.8)
    axs[0].set(xlabel="view", ylabel="mean NEES", title="pose NEES (6 dof)")
    axs[1].plot(v, ln["mean_per_view"], "o-", color="C3")
    axs[1].axhspan(*ln["band95"], color="C2", alpha=0.2, label="95% band")
    axs[1].axhline(24, color="k", lw=0.8)
    axs[1].set(xlabel="view", ylabel="mean NEES", title="feature NEES (8 x 3 dof, anchored coords)")
    for a in axs:
        a.legend()
        a.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(out / "ekf_nees.png", dpi=120)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(6, 4))
    t = summary["timing"]
    nf = [d["n_features"] for d in t]
    ax.plot(nf, [d["update_us_median"] for d in t], "o-", label="update (all re-observed)")
    ax.plot(nf, [d["predict_us_median"] for d in t], "s-", label="predict")
    ax.set(xlabel="features in state", ylabel="median time [us]", title="EKF cost (CPU, NumPy)")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.legend()
    ax.grid(alpha=0.3, which="both")
    fig.tight_layout()
    fig.savefig(out / "ekf_cost.png", dpi=120)
    plt.close(fig)

    run, tr = st["last"]
    fig = plt.figure(figsize=(7, 6))
    ax = fig.add_subplot(projection="3d")
    P = run.points_W
    ax.scatter(*P.T, color="g", s=40, label="truth")
    ax.scatter(*tr.landmarks[0].T, color="b", marker="^", s=30, label="initial (elevation 0)")
    ax.scatter(*tr.landmarks[-1].T, color="r", s=15, label="EKF after 21 views")
    ax.plot(*run.T_W_S[:, :3, 3].T, "k.-", label="sonar path")
    ax.set(xlabel="x [m]", ylabel="y [m]", zlabel="z [m]", title="Prism scene, last seed (cf. Fig. 6 / 8a)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "ekf_scene.png", dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    raise SystemExit(main())
