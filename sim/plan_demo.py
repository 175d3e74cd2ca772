"""``gpumap demo --plan N``: after the scene's trajectory, N more views three ways, scored as they add up.

The three arms start from the same map (the trajectory's pings at true poses, with the confidence
layer) and each adds ``N`` pings:

- **planned**: the greedy next best view (:func:`gpumap.layers.viewgain.plan_views`): every step scores
  ``CANDIDATES`` candidate poses (:func:`gpumap.layers.viewgain.candidate_poses` around trajectory poses
  spread evenly over the path, offsets within :data:`WRIST_LIMITS`), takes the best, simulates
  its ping and integrates it;
- **rolled**: ``N`` trajectory poses spread evenly over the path, each rolled about the
  boresight by +-:data:`ROLL_DEG` in turn (a rule a user could follow without a planner);
- **random**: ``N`` candidates drawn from the same generator and limits as the planned arm's.

After every added ping each arm's map is scored with :func:`~.metrics.evaluate`
(``false_positive_rate_far``, ``false_negative_rate_objects_detectable``, the worst object's
height error), against the surfaces its own pings could detect. The final maps also report the
confidence layer: of the occupied voxels that are far from every surface (> 1 voxel, the FP far
voxels), the share that is unconfirmed; of the confirmed voxels, the share that is far.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np

import gpumap
from gpumap.core.params import MapperParams
from gpumap.layers.confidence import with_confidence
from gpumap.layers.viewgain import candidate_poses

from .metrics import evaluate
from .scenes import Scene
from .sonar import Ping, SonarSimulator
from .truth import Truth, ground_truth_masks

__all__ = ["CANDIDATES", "ROLL_DEG", "WRIST_LIMITS", "plan_outputs", "run_plan"]

#: Candidate poses scored per planned view (the same on every scene).
CANDIDATES = 2000
#: Trajectory poses the candidates are drawn around (spread evenly over the path).
ANCHORS = 20
#: Offsets of the candidates from a trajectory pose: a wrist's reach (radians, metres).
WRIST_LIMITS = {
    "roll_rad": (-math.radians(45), math.radians(45)),
    "pitch_rad": (-math.radians(15), math.radians(15)),
    "yaw_rad": (-math.radians(20), math.radians(20)),
    "offset_m": (-0.1, 0.1),
}
#: Roll of the evenly spread rolled views, degrees (alternating sign).
ROLL_DEG = 40.0
#: Weight of a never-observed voxel against an unconfirmed one in the planner's gain: 0, the
#: planner only resolves what the map holds (bench/results/nbv.json: with 1 it chases unseen
#: volume, and the new volume brings new stretch; the FP far rate falls, the phantom voxels grow).
UNKNOWN_WEIGHT = 0.0
ARMS = ("planned", "rolled", "random")


def plan_outputs() -> tuple[str, ...]:
    """The files ``--plan`` adds to the demo's output set."""
    return ("plan_curves.png", "plan_confidence.png", "plan_poses.png")


def _rx(a: float) -> np.ndarray:
    T = np.eye(4)
    c, s = math.cos(a), math.sin(a)
    T[1:3, 1:3] = [[c, -s], [s, c]]
    return T


def _candidates(T_traj: np.ndarray, step: int, seed: int) -> np.ndarray:
    anchors = np.unique(np.linspace(0, len(T_traj) - 1, min(ANCHORS, len(T_traj))).round().astype(int))
    per = -(-CANDIDATES // len(anchors))
    out = [candidate_poses(T_traj[a], per, seed=(seed * 1_000_003 + step) * 1009 + int(a), **WRIST_LIMITS)
           for a in anchors]
    return np.concatenate(out)[:CANDIDATES]


def _score(mapper, truth: Truth, pings: list[Ping], grid, threshold: float, far: np.ndarray) -> dict:
    seen, det = ground_truth_masks(pings, grid, threshold)
    v = mapper.values()
    ev = evaluate(v, truth, threshold, seen, grid.voxel_size_m, detectable=det).to_dict()
    tops = [h for h in ev["height_error_m"].values() if np.isfinite(h)]
    return {"pings": len(pings), "false_positive_rate_far": ev["false_positive_rate_far"],
            # the same voxels as a count: a view that only adds observed free water lowers the
            # rate, not this
            "false_positive_far_voxels": int(np.count_nonzero(far & (np.nan_to_num(v, nan=-1) >= threshold))),
            "false_negative_rate_objects_detectable": ev["false_negative_rate_objects_detectable"],
            "false_negative_rate_detectable": ev["false_negative_rate_detectable"],
            "worst_object_top_m": max(tops) if tops else float("nan"),
            "height_error_m": ev["height_error_m"]}


def confidence_report(mapper, truth: Truth) -> dict:
    """How the confidence layer splits the occupied voxels (see the module docstring)."""
    from scipy import ndimage

    c = mapper.layer("confidence").states()
    near = ndimage.binary_dilation(truth.occupied, structure=np.ones((3, 3, 3), bool))
    far = ~near
    conf, unconf = c == 3, c == 2
    n_far_occ = int(((conf | unconf) & far).sum())
    return {
        "confirmed_voxels": int(conf.sum()),
        "unconfirmed_voxels": int(unconf.sum()),
        "confirmed_far_fraction": float((conf & far).sum() / max(1, conf.sum())),
        "unconfirmed_far_fraction": float((unconf & far).sum() / max(1, unconf.sum())),
        "far_occupied_voxels": n_far_occ,
        "far_occupied_unconfirmed_fraction": float((unconf & far).sum() / max(1, n_far_occ)),
        "occupied_truth_confirmed_fraction": float((conf & truth.occupied).sum()
                                                   / max(1, ((conf | unconf) & truth.occupied).sum())),
    }


def run_plan(scene: Scene, pings: list[Ping], T_traj: np.ndarray, truth: Truth, n_plan: int, backend: str,
             threshold: float, seed: int, quiet: bool, out: Path,
             unknown_weight: float = UNKNOWN_WEIGHT, on_ping=None) -> dict:
    """Run the three arms; write the pictures into ``out``; return the ``plan`` block of metrics.json.

    ``on_ping(image, T_W_S, mapper)``: called after each planned view is integrated (the live
    view; the mapper keeps the confidence layer)."""
    from scipy import ndimage
    from tqdm import tqdm

    far = ~ndimage.binary_dilation(truth.occupied, structure=np.ones((3, 3, 3), bool))
    t0 = time.perf_counter()
    images = np.stack([p.image for p in pings])
    arms: dict[str, dict] = {}
    with SonarSimulator(scene, seed=seed, **scene.sonar_params) as sim:
        for arm in ARMS:
            m = with_confidence(
                gpumap.MinMaxMapper(scene.sonar_spec, scene.grid, backend, MapperParams(threshold=threshold))
            )
            m.integrate_batch(images, T_traj)
            all_pings = list(pings)
            curve = [_score(m, truth, all_pings, scene.grid, threshold, far)]
            poses, gains = [], []
            if arm == "rolled":
                sel = np.linspace(0, len(T_traj) - 1, n_plan).round().astype(int) if n_plan else []
                fixed = [T_traj[k] @ _rx(math.radians(ROLL_DEG if i % 2 else -ROLL_DEG))
                         for i, k in enumerate(sel)]
            elif arm == "random":
                rng = np.random.default_rng([seed, 99])
                fixed = []
                for i in range(n_plan):
                    C = _candidates(T_traj, 10_000 + i, seed)
                    fixed.append(C[int(rng.integers(len(C)))])
            for i in tqdm(range(n_plan), disable=quiet, desc=f"plan ({arm})", unit="view"):
                if arm == "planned":
                    C = _candidates(T_traj, i, seed)
                    g = m.layer("confidence").gains(C, unknown_weight=unknown_weight)
                    k = int(np.argmax(g))
                    T = C[k]
                    gains.append(float(g[k]))
                else:
                    T = fixed[i]
                p = sim.ping(T, 100_000 * (ARMS.index(arm) + 1) + i)
                m.integrate(p.image, T)
                if on_ping is not None and arm == "planned":
                    on_ping(p.image, T, m)
                all_pings.append(p)
                poses.append(T)
                curve.append(_score(m, truth, all_pings, scene.grid, threshold, far))
            arms[arm] = {"curve": curve, "poses": [T.tolist() for T in poses], "gains": gains,
                         "confidence": confidence_report(m, truth)}
            if arm == "planned":
                planned_mapper = m
    _pictures(out, scene, truth, planned_mapper, T_traj, arms, threshold)
    return {"n_plan": n_plan, "candidates_per_view": CANDIDATES, "wrist_limits": {
        k: list(v) for k, v in WRIST_LIMITS.items()}, "roll_deg": ROLL_DEG, "unknown_weight": unknown_weight,
        "arms": arms, "plan_s": time.perf_counter() - t0}


def _pictures(out: Path, scene: Scene, truth: Truth, mapper, T_traj: np.ndarray, arms: dict,
              threshold: float) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    # Curves: FP far, FN objects, worst object top against pings, per arm.
    fig, ax = plt.subplots(1, 3, figsize=(15, 4.2))
    keys = (("false_positive_rate_far", "FP far"), ("false_negative_rate_objects_detectable", "FN objects"),
            ("worst_object_top_m", "worst object top - truth (m)"))
    colours = {"planned": "tab:red", "rolled": "tab:blue", "random": "tab:green"}
    for a, (key, label) in zip(ax, keys, strict=True):
        for arm, rec in arms.items():
            a.plot([c["pings"] for c in rec["curve"]], [c[key] for c in rec["curve"]], "o-", ms=3,
                   color=colours[arm], label=arm)
        a.set(xlabel="pings", ylabel=label, title=label)
        a.grid(alpha=0.3)
    ax[0].legend()
    fig.suptitle(f"{scene.name}: the trajectory's {len(T_traj)} pings, then planned / evenly rolled / "
                 "random views")
    fig.tight_layout()
    fig.savefig(out / "plan_curves.png", dpi=90)
    plt.close(fig)

    # Confidence layer: top-down, per column the top occupied voxel's state; side view too.
    c = mapper.layer("confidence").states()
    g = scene.grid
    occ = c >= 2
    nz = c.shape[2]
    top = np.where(occ.any(2), nz - 1 - np.argmax(occ[:, :, ::-1], axis=2), -1)
    conf_cnt = (c == 3).sum(2)
    unc_cnt = (c == 2).sum(2)
    ext = [g.min_corner_m[0], g.max_corner_m[0], g.min_corner_m[1], g.max_corner_m[1]]
    fig, ax = plt.subplots(1, 3, figsize=(16, 4.8))
    z_top = np.where(top >= 0, g.min_corner_m[2] + (top + 0.5) * g.voxel_size_m, np.nan)
    im = ax[0].imshow(z_top.T, origin="lower", extent=ext, cmap="viridis")
    fig.colorbar(im, ax=ax[0], label="top occupied z (m)")
    ax[0].set(title="map: top occupied voxel", xlabel="x (m)", ylabel="y (m)")
    im = ax[1].imshow(np.where(unc_cnt > 0, unc_cnt, np.nan).T, origin="lower", extent=ext, cmap="magma_r")
    fig.colorbar(im, ax=ax[1], label="voxels per column")
    ax[1].set(title="unconfirmed occupied (soft obstacles)", xlabel="x (m)")
    im = ax[2].imshow(np.where(conf_cnt > 0, conf_cnt, np.nan).T, origin="lower", extent=ext, cmap="Greens")
    fig.colorbar(im, ax=ax[2], label="voxels per column")
    ax[2].set(title="confirmed occupied (elevation resolved)", xlabel="x (m)")
    fig.suptitle(f"{scene.name}: confidence layer after the planned views")
    fig.tight_layout()
    fig.savefig(out / "plan_confidence.png", dpi=90)
    plt.close(fig)

    # Chosen poses over the truth's height map.
    T = truth.occupied
    k_top = nz - 0.5 - np.argmax(T[:, :, ::-1], axis=2)
    tz = np.where(T.any(2), g.min_corner_m[2] + k_top * g.voxel_size_m, np.nan)
    fig, ax = plt.subplots(figsize=(8, 6.5))
    ax.imshow(tz.T, origin="lower", extent=ext, cmap="gray")
    ax.plot(T_traj[:, 0, 3], T_traj[:, 1, 3], ".", color="0.6", label="trajectory")
    for arm, rec in arms.items():
        P = np.array(rec["poses"]).reshape(-1, 4, 4)
        if not len(P):
            continue
        ax.quiver(P[:, 0, 3], P[:, 1, 3], P[:, 0, 0], P[:, 1, 0], color=colours[arm], angles="xy",
                  scale_units="xy", scale=1.0 / (0.15 * (ext[1] - ext[0])), width=0.004, label=arm)
        roll = np.degrees(np.arctan2(P[:, 2, 1], P[:, 2, 2]))
        if arm == "planned":
            for i, (x, y, r) in enumerate(zip(P[:, 0, 3], P[:, 1, 3], roll, strict=True)):
                ax.annotate(f"{i + 1}: roll {r:+.0f}", (x, y), fontsize=7, color=colours[arm])
    ax.set(title=f"{scene.name}: views added (arrows: boresight in plan)", xlabel="x (m)", ylabel="y (m)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "plan_poses.png", dpi=90)
    plt.close(fig)


def print_plan(plan: dict) -> None:
    """The plan block's last rows, one per arm, and the confidence split of the planned map."""
    print(f"{'views':8s} {'pings':>5s} {'FP far':>7s} {'FN obj':>7s} {'worst top':>9s}")
    for arm, rec in plan["arms"].items():
        c = rec["curve"][-1]
        print(f"{arm:8s} {c['pings']:5d} {c['false_positive_rate_far']:7.3f} "
              f"{c['false_negative_rate_objects_detectable']:7.3f} {c['worst_object_top_m']:+9.3f}")
    cr = plan["arms"]["planned"]["confidence"]
    print(f"confidence (planned): {cr['confirmed_voxels']} confirmed "
          f"({100 * cr['confirmed_far_fraction']:.1f} % far from surfaces), {cr['unconfirmed_voxels']} "
          "unconfirmed; the unconfirmed layer holds "
          f"{100 * cr['far_occupied_unconfirmed_fraction']:.1f} % of the far occupied voxels")
