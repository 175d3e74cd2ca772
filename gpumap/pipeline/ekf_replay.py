"""``gpumap replay RECORDING --ekf --odometry-noise TRANS_M ROT_RAD``: the EKF on real pings.

The recording's poses are the reference. Odometry is made from them by the drift model of
:func:`gpumap.ekf.loop.drifting_odometry` (seeded, ``--seed``), run through
:func:`gpumap.ekf.loop.run_ekf_loop` (returns found in each image, associated, fused), and the
pings are mapped three times on one grid: at the recorded poses, at the odometry's and at the
EKF's. :func:`run_ekf_replay` returns the figures; the command (:mod:`gpumap.commands.replay`) writes

- ``summary.json``: the usual replay summary of the EKF-pose map, plus an ``ekf`` section:
  the drift model, pose errors of odometry and EKF against the recorded poses (position and
  heading: mean, RMS, max, final), how much it trusted the pings (``trust``: returns fused
  with a pose correction, into their features only, gated; share of pings that corrected the
  pose; windowed NIS, see :mod:`gpumap.ekf.guard`), how much it trusted the scan registration
  (``registration``, :func:`registration_summary`), each map against the recorded-pose map (occupied voxels
  that disagree, FN and FP), the tracks and their lifetimes, and milliseconds per ping;
- ``map.npz`` / ``occupied.ply`` / ``views.png``: the EKF-pose map;
- ``ekf_paths.png``: recorded, odometry and EKF paths over the recorded-pose map's height map,
  and the errors along the run; ``ekf_measurements.png``: a ping with its returns, coloured
  by what the tracker made of them, and the confirmed features' predictions.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np

from gpumap.core.params import MapperParams

__all__ = ["compare_maps", "posed_frames", "registration_summary", "run_ekf_replay", "track_consistency",
           "trust_summary"]


def compare_maps(ref: np.ndarray, test: np.ndarray, threshold: float) -> dict:
    """How a map differs from a reference map on the same grid, read at ``threshold``.

    A voxel is occupied when its value is ``>= threshold``; unknown (NaN) is not occupied, so
    leaving voxels unknown cannot make a map look closer.

    Returns
    -------
    dict
        ``ref_occupied``, ``test_occupied``, ``disagree`` (occupied in exactly one),
        ``disagree_fraction`` (of those occupied in either), ``fn`` (occupied in the reference,
        not in the map) and ``fn_rate`` (of the reference's), ``fp`` (occupied in the map, not
        in the reference) and ``fp_rate`` (of the map's).
    """
    a = np.isfinite(ref) & (ref >= threshold)
    b = np.isfinite(test) & (test >= threshold)
    fn = int((a & ~b).sum())
    fp = int((b & ~a).sum())
    union = int((a | b).sum())
    na, nb = int(a.sum()), int(b.sum())
    return {"ref_occupied": na, "test_occupied": nb, "disagree": fn + fp,
            "disagree_fraction": (fn + fp) / union if union else 0.0,
            "fn": fn, "fn_rate": fn / na if na else 0.0, "fp": fp, "fp_rate": fp / nb if nb else 0.0}


def track_consistency(loop, T_ref: np.ndarray, gate_prob: float = 0.999) -> dict:
    """How well each confirmed track's returns agree with one fixed point, seen from reference poses.

    For every track ever confirmed, the point that best explains all its returns from the
    reference poses (recorded poses on real data) is found by Gauss-Newton from five starts
    along the first return's elevation arc; a return is *consistent* when its NIS (2 dof, with
    the detector's covariance) at that point is within the chi-square gate. On real data this
    stands in for association precision: an association error, or a return that is no fixed
    scatterer (a glint sliding along a surface), shows as inconsistent returns.

    Returns
    -------
    dict
        ``tracks``, ``returns``, ``consistent_fraction`` (returns), ``tracks_all_consistent``.
    """
    from gpumap.ekf._checks import _chi2_2dof
    from gpumap.ekf.measurement import _observe_batch, spherical_point, wrap_angle

    gate = _chi2_2dof(gate_prob)
    n_ret = n_ok = n_tr = n_tr_ok = 0
    for t in loop.tracker.tracks.values():
        if t.confirmed_at is None or len(t.returns) < 2:
            continue
        pk = np.array([p for p, _ in t.returns])
        js = [j for _, j in t.returns]
        z = np.array([[loop.measurements[p].ranges_m[j], loop.measurements[p].bearings_rad[j]]
                      for p, j in t.returns])
        Rinv = np.linalg.inv(np.stack([loop.measurements[p].covs[j] for p, j in zip(pk, js, strict=True)]))
        T = T_ref[pk]
        best = None
        vf = loop.tracker.spec.vfov_rad
        for el in np.linspace(-0.4, 0.4, 5) * vf:
            q, _ = spherical_point(np.array([z[0, 0], z[0, 1], el]))
            lw = T[0, :3, :3] @ q + T[0, :3, 3]
            for _ in range(15):
                zz = np.empty((len(pk), 2))
                H = np.empty((len(pk), 2, 3))
                for i in range(len(pk)):
                    zi, _, Hl, _, _ = _observe_batch(T[i, :3, :3], T[i, :3, 3], lw[None])
                    zz[i], H[i] = zi[0], Hl[0]
                nu = z - zz
                nu[:, 1] = wrap_angle(nu[:, 1])
                A = np.einsum("nki,nkl,nlj->ij", H, Rinv, H)
                b = np.einsum("nki,nkl,nl->i", H, Rinv, nu)
                dx = np.linalg.lstsq(A + 1e-9 * np.eye(3), b, rcond=None)[0]
                lw = lw + dx
                if np.linalg.norm(dx) < 1e-7:
                    break
            d2 = np.einsum("nk,nkl,nl->n", nu, Rinv, nu)
            if best is None or d2.sum() < best.sum():
                best = d2
        n_tr += 1
        n_ret += len(best)
        n_ok += int((best <= gate).sum())
        n_tr_ok += bool(np.all(best <= gate))
    return {"tracks": n_tr, "returns": n_ret, "consistent_fraction": n_ok / n_ret if n_ret else None,
            "tracks_all_consistent": n_tr_ok / n_tr if n_tr else None}


def trust_summary(loop) -> dict:
    """How much the EKF trusted the pings with the pose (the guard's counters, per ping and per return).

    Returns
    -------
    dict
        ``guard`` (bool: whether the filter had one), ``returns`` (found), ``paired`` (with a
        confirmed track), ``fused_with_pose`` / ``fused_features_only`` (returns fused while the
        guard trusted the pings / as Schmidt updates of their feature only), ``gated`` (paired
        returns refused by the EKF's per-return chi-square gate), ``pings_trusted_share`` and
        ``pings_pose_corrected_share`` (pings whose update was allowed to, and did, move the
        pose), ``window_nis_per_dof`` (median and last, per ping) and the guard's own summary.
    """
    ekf = loop.tracker.ekf
    n = len(loop.steps)
    paired = int(sum(len(s.confirmed_hits) + len(s.refused) for s in loop.steps))
    corrected = np.array([bool(s.confirmed_hits) for s in loop.steps]) & loop.trusted
    wn = loop.window_nis[np.isfinite(loop.window_nis)] if loop.window_nis is not None else np.zeros(0)
    out = {"guard": ekf.guard is not None, "pings": n,
           "returns": int(sum(len(m) for m in loop.measurements)), "paired": paired,
           "pings_trusted_share": float(np.mean(loop.trusted)),
           "pings_pose_corrected_share": float(corrected.mean()) if n else 0.0,
           "window_nis_per_dof": {"median": float(np.median(wn)) if wn.size else None,
                                  "last": float(wn[-1]) if wn.size else None}}
    if ekf.guard is not None:
        g = ekf.guard.summary()
        out.update({"fused_with_pose": g["fused_with_pose"], "fused_features_only": g["fused_features_only"],
                    "gated": g["gated"], "guard_state": g})
    else:
        fused = int(sum(len(s.confirmed_hits) for s in loop.steps))
        out.update({"fused_with_pose": fused, "fused_features_only": 0,
                    "gated": int(sum(len(s.refused) for s in loop.steps))})
    return out


def registration_summary(registrar) -> dict:
    """How much the EKF trusted the scan registration (:mod:`gpumap.ekf.registration`).

    Returns
    -------
    dict
        ``used`` (bool); with it, per ping: ``registered`` (a step registration was found),
        ``fused`` / ``fused_share`` (it corrected the odometry step), ``gated`` (refused by its
        chi-square gate), ``distrusted`` (refused while the NIS window was out of its band),
        ``nis_per_dof_median``, and the revisits of stored pings (``revisits`` found,
        ``revisits_fused``, ``revisits_gated``).
    """
    if registrar is None:
        return {"used": False}
    return {"used": True, "keep": registrar.keep, "step": registrar.step, "revisit": registrar.revisit,
            **registrar.stats.to_dict()}


def _map(spec, grid, images, poses, backend, threshold, rule):
    from gpumap import MinMaxMapper
    from gpumap.core.feed import feed

    m = MinMaxMapper(spec, grid, backend, MapperParams(rule=rule, threshold=threshold))
    feed(m, zip(images, poses, strict=True))
    return m


def posed_frames(recording, stride: int = 1, max_frames: int | None = None,
                 frames: tuple[int, int | None] | None = None) -> tuple[list, np.ndarray, object]:
    """(images, poses (n, 4, 4) float64, spec) of a recording's frames that carry a pose and the
    first frame's sonar spec: every ``stride``-th of frames ``start <= i < stop`` (``frames``),
    at most ``max_frames``."""
    images, poses, spec = [], [], None
    k = 0
    f0, f1 = (0, None) if frames is None else frames
    for i, fr in enumerate(recording):
        if f1 is not None and i >= f1:
            break
        if i < f0 or (i - f0) % max(1, int(stride)) or fr.T_W_S is None:
            continue
        if spec is None:
            spec = fr.spec
        if fr.spec != spec:
            continue
        images.append(np.array(fr.image))
        poses.append(np.asarray(fr.T_W_S, dtype=np.float64))
        k += 1
        if max_frames is not None and k >= max_frames:
            break
    return images, (np.stack(poses) if poses else np.zeros((0, 4, 4))), spec


def run_ekf_replay(recording, *, odometry_noise: tuple[float, float] = (0.005, 0.005), seed: int = 0,
                   voxel_size_m: float = 0.05, grid=None, backend: str = "auto",
                   threshold: float = 0.4, rule: str | None = None, stride: int = 1,
                   max_frames: int | None = None, progress: bool = True, detector=None,
                   ekf_kwargs: dict | None = None, tracker_kwargs: dict | None = None,
                   guard=True, frames: tuple[int, int | None] | None = None, registration=False) -> dict:
    """Run the EKF loop on a posed recording and compare it with the recorded poses.

    Parameters
    ----------
    recording : gpumap.io.Recording
        Frames with ``T_W_S`` (frames without a pose are skipped).
    odometry_noise : (float, float)
        Per-step drift, translation metres and rotation radians per axis.
    seed : int
        Seed of the drift.
    voxel_size_m, grid, backend, threshold, rule
        The maps (``grid`` None: :func:`gpumap.pipeline.replay.auto_grid` of the recorded poses).
    stride, max_frames : int
        Every ``stride``-th posed frame, at most ``max_frames``.
    detector, ekf_kwargs, tracker_kwargs
        Passed to :func:`gpumap.ekf.loop.run_ekf_loop`.
    guard : bool or TrustGuard, default True
        The filter's innovation-consistency guard (:mod:`gpumap.ekf.guard`): True a default
        :class:`~gpumap.ekf.guard.TrustGuard` (the pings correct the pose only while their
        innovations are consistent; otherwise the pose follows odometry), False none (the plain
        EKF, which on the real tank ends worse than odometry).
    frames : (int, int or None), optional
        Only recording frames ``start <= i < stop`` (indices in the recording, before
        ``stride``); the run starts from the recorded pose of the first one kept.
    registration : bool or ScanRegistrar, default False
        Revisits of stored pings, found by their first returns (at ``threshold``), verified by
        their images' agreement, fused against the drift since and kept in a pose graph behind
        the filter (:mod:`gpumap.ekf.registration`): True a default
        :class:`~gpumap.ekf.registrar.ScanRegistrar`, False none (the default). On the full
        real tank run it about halves the mean position error where the run revisits places and
        was never worse than odometry on frames 0-799 nor on 800-1222 alone, but on one whole run
        of ten (drift 0.02, seed 2) it ended at 1.04x odometry's position error, so it stays
        off (``bench/results/ekf_pose.json``).

    Returns
    -------
    dict
        ``summary`` (JSON-ready figures, see the module docstring), ``loop``
        (:class:`~gpumap.ekf.loop.LoopResult`), ``T_rec``, ``T_odo``, ``maps`` (name ->
        mapper: ``recorded``, ``odometry``, ``ekf``), ``images``, ``spec``, ``grid``.
    """
    from gpumap.ekf.loop import drifting_odometry, motion_cov, pose_errors, run_ekf_loop
    from gpumap.spec import auto_grid

    st, sr = (float(v) for v in odometry_noise)
    images, T_rec, spec = posed_frames(recording, stride, max_frames, frames)
    if len(images) < 2:
        raise ValueError(f"Expected at least 2 posed frames for --ekf, but {recording.path} gave "
                         f"{len(images)}")
    U, T_odo = drifting_odometry(T_rec, st, sr, seed)
    Q = motion_cov(st, sr)
    t0 = time.perf_counter()
    from gpumap.ekf.guard import TrustGuard

    ekw = dict(ekf_kwargs or {})
    if isinstance(guard, TrustGuard):
        ekw["guard"] = guard
    elif guard:
        ekw.setdefault("guard", TrustGuard())
    from gpumap.ekf.registrar import ScanRegistrar

    registrar = registration if isinstance(registration, ScanRegistrar) else (
        ScanRegistrar(spec, threshold=threshold) if registration else None)
    loop = run_ekf_loop(images, U, T_rec[0], spec, odometry_cov=Q, detector=detector,
                        ekf_kwargs=ekw, tracker_kwargs=tracker_kwargs, registrar=registrar,
                        progress=progress)
    t_loop = time.perf_counter() - t0
    if grid is None:
        grid = auto_grid(spec, list(T_rec), voxel_size_m)
    maps, map_s = {}, {}
    for name, T in (("recorded", T_rec), ("odometry", T_odo), ("ekf", loop.poses)):
        tm = time.perf_counter()
        maps[name] = _map(spec, grid, images, list(T), backend, threshold, rule)
        map_s[name] = time.perf_counter() - tm
    vals = {n: m.values() for n, m in maps.items()}
    e_odo, e_ekf = pose_errors(T_odo, T_rec), pose_errors(loop.poses, T_rec)
    series = {"odometry": e_odo.pop("_series"), "ekf": e_ekf.pop("_series")}
    n_meas = int(sum(len(m) for m in loop.measurements))
    fused = int(sum(len(s.confirmed_hits) for s in loop.steps))
    ms_total = loop.ms_detect + loop.ms_track
    from gpumap.lie import se3_inverse, se3_log

    steps = np.array([se3_log(se3_inverse(T_rec[k - 1]) @ T_rec[k]) for k in range(1, len(T_rec))])
    summary = {
        "frames": len(images),
        "recorded_step_median": {
            "translation_m": float(np.median(np.linalg.norm(steps[:, :3], axis=1))),
            "rotation_deg": float(np.degrees(np.median(np.linalg.norm(steps[:, 3:], axis=1))))},
        "drift_model": {"trans_sigma_m": st, "rot_sigma_rad": sr, "seed": int(seed),
                        "text": "U_k = T_{k-1}^-1 T_k Exp(w_k), w_k ~ N(0, diag(s_t^2 I3, s_r^2 I3)) per "
                                "step, chained from the first recorded pose"},
        "pose_error": {"odometry": e_odo, "ekf": e_ekf},
        "ratio_ekf_to_odometry": {
            "position_mean": e_ekf["position_m"]["mean"] / max(e_odo["position_m"]["mean"], 1e-12),
            "heading_mean": e_ekf["heading_rad"]["mean"] / max(e_odo["heading_rad"]["mean"], 1e-12)},
        "map_vs_recorded": {n: compare_maps(vals["recorded"], vals[n], threshold)
                            for n in ("odometry", "ekf")},
        "threshold": float(threshold),
        "measurements": {"returns": n_meas, "per_ping_mean": n_meas / len(images), "fused": fused},
        "trust": trust_summary(loop),
        "registration": registration_summary(registrar),
        "tracks": loop.tracker.lifetimes(),
        "track_consistency_recorded_poses": track_consistency(loop, T_rec),
        "ms_per_ping": {"detect_mean": float(loop.ms_detect.mean()),
                        "track_ekf_mean": float(loop.ms_track.mean()),
                        "total_mean": float(ms_total.mean()), "total_p95": float(np.percentile(ms_total, 95)),
                        "loop_seconds": t_loop, "map_seconds": map_s, "loadavg": list(os.getloadavg()),
                        "note": "host CPU, loaded by other processes"},
    }
    return {"summary": summary, "loop": loop, "T_rec": T_rec, "T_odo": T_odo, "maps": maps,
            "values": vals, "series": series, "images": images, "spec": spec, "grid": grid}


def paths_picture(res: dict, out: Path, title: str = "") -> None:
    """Recorded, odometry and EKF paths over the recorded-pose map (top-down), and the errors."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    grid, v = res["grid"], res["values"]["recorded"]
    thr = res["summary"]["threshold"]
    occ = np.isfinite(v) & (v >= thr)
    z = grid.min_corner_m[2] + (np.arange(v.shape[2]) + 0.5) * grid.voxel_size_m
    top = np.where(occ.any(axis=2), z[np.argmax(np.where(occ, z[None, None, :], -np.inf), axis=2)], np.nan)
    fig, ax = plt.subplots(1, 2, figsize=(13, 5.5), gridspec_kw={"width_ratios": [1.2, 1]})
    ext = [grid.min_corner_m[0], grid.max_corner_m[0], grid.min_corner_m[1], grid.max_corner_m[1]]
    im = ax[0].imshow(top.T, origin="lower", extent=ext, cmap="viridis")
    fig.colorbar(im, ax=ax[0], label="top of occupied voxels, z (m)", shrink=0.8)
    for name, T, c in (("recorded", res["T_rec"], "w"), ("odometry", res["T_odo"], "tab:red"),
                       ("EKF", res["loop"].poses, "tab:orange")):
        ax[0].plot(T[:, 0, 3], T[:, 1, 3], "-o", color=c, ms=2, lw=1.2, label=name)
    xy = np.concatenate([res["T_rec"][:, :2, 3], res["T_odo"][:, :2, 3], res["loop"].poses[:, :2, 3]])
    ax[0].set_xlim(xy[:, 0].min() - 0.8, xy[:, 0].max() + 0.8)
    ax[0].set_ylim(xy[:, 1].min() - 0.8, xy[:, 1].max() + 0.8)
    ax[0].set_xlabel("x (m)")
    ax[0].set_ylabel("y (m)")
    ax[0].legend(loc="upper right", fontsize=8, facecolor="0.7")
    ax[0].set_title(f"paths over the recorded-pose map {title}".strip(), fontsize=10)
    s = res["series"]
    ax2 = ax[1].twinx()
    for name, c in (("odometry", "tab:red"), ("ekf", "tab:orange")):
        ax[1].plot(100 * s[name]["position_m"], color=c, label=f"{name} position (cm)")
        ax2.plot(np.degrees(s[name]["heading_rad"]), color=c, ls="--", label=f"{name} heading (deg)")
    ax[1].set_xlabel("ping")
    ax[1].set_ylabel("position error (cm), solid")
    ax2.set_ylabel("heading error (deg), dashed")
    ax[1].legend(loc="upper left", fontsize=8)
    ax2.legend(loc="upper center", fontsize=8)
    d = res["summary"]["drift_model"]
    ax[1].set_title(f"error vs recorded poses (drift {d['trans_sigma_m']:g} m, {d['rot_sigma_rad']:g} rad "
                    f"per step, seed {d['seed']})", fontsize=10)
    fig.tight_layout()
    fig.savefig(out, dpi=90)
    plt.close(fig)


def measurements_picture(res: dict, out: Path, ping: int | None = None) -> int:
    """One ping with its returns (by what the tracker made of them) and the features' predictions.

    Returns the ping drawn (default: the one with the most fused returns, then the most returns).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    loop = res["loop"]
    if ping is None:
        score = [(len(s.confirmed_hits), len(m)) for s, m in zip(loop.steps, loop.measurements, strict=True)]
        ping = int(max(range(len(score)), key=lambda k: score[k]))
    img = np.asarray(res["images"][ping], dtype=np.float32)
    if img.dtype == np.uint8:
        img = img / 255.0
    m, st = loop.measurements[ping], loop.steps[ping]
    fig, ax = plt.subplots(figsize=(9, 7))
    vmax = max(float(np.percentile(img, 99.5)), 1e-3)
    ax.imshow(img, origin="lower", aspect="auto", cmap="gray", vmin=0, vmax=vmax)
    kinds = {"fused into the EKF": ([j for j in st.confirmed_hits.values()], "lime"),
             "tentative track": ([j for i, j in st.tentative_hits.items()] +
                                 [int(j) for j in np.flatnonzero(np.isin(st.labels, st.started))], "orange"),
             "refused / ambiguous": ([j for j in range(len(m)) if st.labels[j] < 0], "red")}
    for name, (js, c) in kinds.items():
        js = sorted(set(js))
        if js:
            ax.plot(m.beams[js], m.bins[js] - 0.5, "+", color=c, ms=14, mew=2, label=f"{name} ({len(js)})")
    for i, j in st.confirmed_hits.items():
        ax.annotate(str(i), (m.beams[j], m.bins[j] - 0.5), color="lime", fontsize=8, xytext=(5, 5),
                    textcoords="offset points")
    ax.set_xlabel("beam")
    ax.set_ylabel("range bin")
    ax.set_title(f"ping {ping}: {len(m)} compact returns found (+), ids of the EKF's features", fontsize=10)
    ax.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    fig.savefig(out, dpi=90)
    plt.close(fig)
    return ping


