"""The demo: simulate the tank, map it with the min-max filter, score it against truth
(:func:`run_demo`; the command is ``gpumap demo``, :mod:`gpumap.commands.demo`).

Writes to ``args.out``: ``metrics.json`` (scene, backend, voxel size, images, mapper time per
image, false-negative/positive rates, height errors, whether the pipe was found, and with
``--pose-noise`` one row per pose source), ``map.npz`` (the map, :meth:`MinMaxMapper.save`)
and pictures: ``sonar_image.png`` (a sample ping), ``map_vs_truth.png`` (the map's occupied
voxels coloured by intensity next to the truth) and ``error_by_views.png``.

``--pose-noise SIGMA`` maps the same pings three times: (a) at the true poses, (b) at
dead-reckoned poses whose every step carries Gaussian noise of SIGMA metres on each
translation axis and SIGMA radians on each rotation axis (drift), and (c) at the poses of
:class:`gpumap.ekf.SonarEKF` fed that odometry, the simulated (range, azimuth) features
with noise (1 cm, 0.3 deg), and the wrist DVL's four slant ranges to the tank floor (the
vertical information that features alone do not carry; see ``_ekf_poses``), and (d) at the
EKF poses with their covariance (``integrate(pose_cov=...)``: footprints grow with it).
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np

import gpumap
from gpumap.core.params import MapperParams
from gpumap.geometry import RULES

from .metrics import evaluate
from .scenes import Scene, make_scene
from .sonar import Ping, SonarSimulator
from .truth import Truth, ground_truth_masks, occupancy, points_to_voxels
from .variation import SonarVariation

__all__ = ["VARIATIONS", "run_demo"]

RANGE_SIGMA_M = 0.01
BEARING_SIGMA_RAD = math.radians(0.3)
#: Voxel edge (metres) of each scene when ``--voxel-size`` is not given; others take 0.03.
DEFAULT_VOXEL_M = {"survey": 0.05}
#: ``--variation`` names -> the simulated sonar's view-to-view variation.
VARIATIONS = {"none": SonarVariation.none, "real_tank": SonarVariation.real_tank}


def _progress(it, disable: bool, **kw):
    from tqdm import tqdm

    return tqdm(it, disable=disable, **kw)


def _map_pings(
    scene: Scene, truth: Truth, pings: list[Ping], seen_each: list[np.ndarray], poses: np.ndarray,
    backend: str, method: str, threshold: float, quiet: bool, label: str, curve: bool, shadow_m: float = 0.0,
    mapper: gpumap.MinMaxMapper | None = None, rule: str | None = None,
    detectable: np.ndarray | None = None, pose_covs: np.ndarray | None = None, on_ping=None,
    sparse: bool = False,
) -> tuple[gpumap.MinMaxMapper, list[float], list[dict]]:
    if mapper is None:
        mapper = build_mapper(scene, backend, method, _rule(rule, method), threshold, shadow_m, sparse=sparse)
    times, history = [], []
    seen = np.zeros(scene.grid.n_voxels, bool)
    curve_at = _curve_pings(len(pings), scene.grid.n_voxels) if curve else set()
    for k in _progress(range(len(pings)), quiet, desc=f"map ({label})", unit="ping"):
        t0 = time.perf_counter()
        mapper.integrate(pings[k].image, poses[k], None if pose_covs is None else pose_covs[k])
        mapper.synchronize()
        times.append(time.perf_counter() - t0)
        if on_ping is not None:  # the live view / recording (after the timing)
            on_ping(pings[k].image, poses[k], mapper)
        seen[seen_each[k]] = True
        if k in curve_at:
            ev = evaluate(mapper.values(), truth, threshold, seen.reshape(scene.grid.shape),
                          scene.grid.voxel_size_m, detectable=detectable)
            history.append({**ev.to_dict(), "pings": k + 1})
    return mapper, times, history


#: Above this many (pings x grid voxels) the error curve is scored after a dozen pings spread
#: over the run rather than after every ping (one score of the survey's 24 M voxels takes ~2 s).
CURVE_VOXEL_BUDGET = 1e9


def _curve_pings(n_pings: int, n_voxels: int) -> set[int]:
    """Indices of the pings after which the error curve is scored (always the first and last)."""
    if n_pings * n_voxels <= CURVE_VOXEL_BUDGET:
        return set(range(n_pings))
    return {int(i) for i in np.linspace(0, n_pings - 1, 12).round()}


def build_mapper(
    scene: Scene, backend: str, method: str, rule: str, threshold: float, shadow_m: float = 0.0,
    sparse: bool = False,
) -> gpumap.MinMaxMapper | gpumap.SparseMinMaxMapper:
    """The mapper every row of the demo integrates into (the one place that picks the storage).

    ``sparse=False``: a dense :class:`gpumap.MinMaxMapper` over ``scene.grid``; ``True``: a
    :class:`gpumap.SparseMinMaxMapper` bounded by the same box (its voxels are the grid's, so
    ``values()`` has the grid's shape and, where observed, the dense grid's values). What the
    demo reads from either: ``integrate``, ``synchronize``, ``values``, ``rule``, ``backend``,
    ``save`` and :func:`_memory_report`.
    """
    return gpumap.MinMaxMapper(
        scene.sonar_spec,
        scene.grid,
        backend,
        MapperParams(method=method, shadow_m=shadow_m, rule=rule, threshold=threshold, sparse=bool(sparse)),
    )


def _memory_report(mapper: gpumap.MinMaxMapper | gpumap.SparseMinMaxMapper, scene: Scene) -> dict:
    """Bytes the map holds next to what the voxels it observed need and the dense equivalents.

    ``map_bytes``: the dense mapper's per-voxel arrays, or the sparse mapper's pool and index
    (``total_bytes`` of :meth:`gpumap.SparseMinMaxMapper.memory_stats`, whose other figures
    come along under ``sparse``); ``observed_voxels``/``observed_bytes``: the voxels some
    ping observed and their bytes at the same cost per voxel (what an ideal sparse map
    would hold); ``dense_grid_bytes``: a dense grid over ``scene.grid``; for a
    scene with a seabed (``survey``), ``dense_water_column_bytes``: a dense grid over the
    grid's plan area from its floor up to the sea surface (z = 0), what a dense map needs
    without knowing where the seabed lies.
    """
    g = scene.grid
    bpv = mapper.bytes_per_voxel
    if mapper.sparse is not None:
        st = mapper.memory_stats()
        storage, map_bytes, observed = "sparse", int(st["total_bytes"]), int(st["observed_voxels"])
    else:
        storage, map_bytes = "dense", g.n_voxels * bpv
        observed = int(np.count_nonzero(np.isfinite(mapper.values())))
    rep = {"storage": storage, "bytes_per_voxel": bpv, "map_bytes": map_bytes,
           "observed_voxels": observed, "observed_bytes": observed * bpv,
           "dense_grid_voxels": g.n_voxels, "dense_grid_bytes": g.n_voxels * bpv}
    if storage == "sparse":
        rep["sparse"] = st
    if scene.seabed_z_m is not None and g.min_corner_m[2] < 0.0:
        s = g.voxel_size_m
        lo, hi = np.asarray(g.min_corner_m), np.asarray(g.max_corner_m)
        ext = [hi[0] - lo[0], hi[1] - lo[1], -lo[2]]
        n = int(np.prod([math.ceil(round(e / s, 9)) for e in ext]))
        rep.update(dense_water_column_voxels=n, dense_water_column_bytes=n * bpv)
    return rep


def _odometry(T_true: np.ndarray, sigma: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Noisy increments ``U_k`` (k >= 1) and the dead-reckoned poses from the true first pose."""
    from gpumap.lie import se3_exp, se3_inverse

    n = len(T_true)
    U = np.zeros((n, 4, 4))
    T = np.zeros((n, 4, 4))
    T[0] = T_true[0]
    U[0] = np.eye(4)
    for k in range(1, n):
        U[k] = se3_inverse(T_true[k - 1]) @ T_true[k] @ se3_exp(rng.normal(0.0, sigma, 6))
        T[k] = T[k - 1] @ U[k]
    return U, T


#: DVL (Water Linked A50) slant-range noise per beam, metres.
DVL_RANGE_SIGMA_M = 0.01
#: RMS height of the tank's sand about its mean level (``TANK["floor_z_m"]``): the four ripples
#: of ``scenes._sand_height_fn`` (amplitudes 4, 3, 6, 5 mm), ``sqrt(sum(a^2) / 2)``. Along a
#: beam it becomes range noise ``/ |cos(incidence)|``.
SAND_ROUGHNESS_M = 0.0066


def _dvl_rays_S(T_W_S: np.ndarray, T_S_D: np.ndarray, rays_D: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Origin and direction (sonar frame) of each DVL beam's leading edge over a level floor.

    A beam's range is its nearest hit among the rays of its cone (``rays_D (4, k, 3)``, axis
    and edge): over a flat floor that is the ray closest to straight down at ``T_W_S``.
    """
    u_S = rays_D @ T_S_D[:3, :3].T  # (4, k, 3)
    down = -(u_S @ T_W_S[:3, :3].T)[..., 2]  # cosine to the downward vertical
    pick = np.argmax(down, axis=1)
    u = u_S[np.arange(u_S.shape[0]), pick]
    return np.broadcast_to(T_S_D[:3, 3], u.shape).copy(), u / np.linalg.norm(u, axis=1, keepdims=True)


def _ekf_poses(scene: Scene, pings: list[Ping], U: np.ndarray, sigma: float,
               rng: np.random.Generator, landmarks_out: dict | None = None) -> tuple[np.ndarray, np.ndarray]:
    """EKF poses from odometry, the (range, azimuth) features and, in the tank and the survey, the DVL.

    The tank's DVL (four A50 beams, wrist mount of :func:`~.scenes.mounts`) is simulated at
    the true pose with ``DVL_RANGE_SIGMA_M`` noise and fused as ranges to the floor plane
    ``z = TANK["floor_z_m"]`` (-0.42 m, the sand's mean level), each beam with variance
    ``DVL_RANGE_SIGMA_M^2 + (SAND_ROUGHNESS_M / cos(incidence))^2``. Beams hitting an object
    on the sand fail the filter's gate; those with no return (NaN) are skipped. The survey's
    downward DVL (:func:`~.scenes.survey_mounts`) is fused the same way against the plane
    ``z = SURVEY["floor_z_m"]`` (-4 m) with the seabed's RMS height about it in place of
    ``SAND_ROUGHNESS_M`` (:func:`_seabed_roughness`: its undulation, ~0.12 m). Returns the
    poses (n, 4, 4) and their covariances (n, 6, 6); a ``landmarks_out`` dict
    also gets the final features: ``points`` (m, 3) world metres, ``covs`` (m, 3, 3).
    """
    from gpumap.ekf import SonarEKF

    from .dvl import DVLSimulator
    from .scenes import SURVEY, TANK, mounts, survey_mounts

    Q = np.eye(6) * sigma**2
    # Iterated feature updates (3 passes): with the DVL holding the tilt, relinearising the
    # features' returns lowers the map's FN in the tank (0.198 -> 0.190 at 0.005 noise).
    ekf = SonarEKF(scene.T_W_S[0], np.eye(6) * 1e-8, range_sigma_m=RANGE_SIGMA_M,
                   bearing_sigma_rad=BEARING_SIGMA_RAD, vfov_rad=scene.sonar_spec.vfov_rad, iterations=3)
    dvl = DVLSimulator(scene) if scene.name in ("tank", "survey") else None
    if dvl is not None:
        from gpumap.lie import se3_inverse

        floor_n = np.array([0.0, 0.0, 1.0])
        if scene.name == "tank":
            T_wrist_S, T_wrist_D = mounts()
            T_S_D = se3_inverse(T_wrist_S) @ T_wrist_D
            floor_d, roughness = float(TANK["floor_z_m"]), SAND_ROUGHNESS_M
        else:  # the survey vehicle's downward DVL over the seabed's mean level
            T_V_S, T_V_D = survey_mounts()
            T_S_D = se3_inverse(T_V_S) @ T_V_D
            floor_d = float(SURVEY["floor_z_m"])
            roughness = _seabed_roughness(scene, floor_d)
    out = np.zeros((len(pings), 4, 4))
    covs = np.zeros((len(pings), 6, 6))
    for k, p in enumerate(pings):
        if k > 0:
            ekf.predict(U[k], Q)
        if dvl is not None:
            r = dvl.ranges(p.T_W_S @ T_S_D)
            r = r + rng.normal(0, DVL_RANGE_SIGMA_M, r.shape)
            o, u = _dvl_rays_S(ekf.pose, T_S_D, dvl._rays_D)
            cos_inc = np.abs((u @ ekf.pose[:3, :3].T)[:, 2])
            for j in np.flatnonzero(np.isfinite(r) & (cos_inc > 0.1)):
                s_j = math.hypot(DVL_RANGE_SIGMA_M, roughness / cos_inc[j])
                ekf.update_plane_ranges(o[j:j + 1], u[j:j + 1], r[j:j + 1], floor_n, floor_d, s_j)
        if len(p.feature_ids):
            r = p.feature_ranges_m + rng.normal(0, RANGE_SIGMA_M, len(p.feature_ids))
            b = p.feature_bearings_rad + rng.normal(0, BEARING_SIGMA_RAD, len(p.feature_ids))
            ekf.update(p.feature_ids, r, b)
        out[k] = ekf.pose
        covs[k] = ekf.pose_cov
    if landmarks_out is not None:  # the final features in the world and their covariances (live view)
        ids = ekf.landmark_ids
        world = ekf.landmarks
        landmarks_out["points"] = np.array([world[i] for i in ids]).reshape(-1, 3)
        landmarks_out["covs"] = np.array([ekf.landmark_cov(i) for i in ids]).reshape(-1, 3, 3)
    return out, covs


def _seabed_roughness(scene: Scene, z0: float, step_m: float = 0.1) -> float:
    """RMS height (metres) of ``scene.seabed_z_m`` about the level ``z0`` over the grid's plan area."""
    g = scene.grid
    x = np.arange(g.min_corner_m[0], g.max_corner_m[0], step_m)
    y = np.arange(g.min_corner_m[1], g.max_corner_m[1], step_m)
    X, Y = np.meshgrid(x, y, indexing="ij")
    return float(np.sqrt(np.mean((scene.seabed_z_m(X, Y) - z0) ** 2)))


def _pose_error(T_est: np.ndarray, T_true: np.ndarray) -> dict:
    dt = np.linalg.norm(T_est[:, :3, 3] - T_true[:, :3, 3], axis=1)
    R = np.einsum("nji,njk->nik", T_est[:, :3, :3], T_true[:, :3, :3])
    ang = np.degrees(np.arccos(np.clip((np.trace(R, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    return {"translation_error_mean_m": float(dt.mean()), "translation_error_max_m": float(dt.max()),
            "rotation_error_mean_deg": float(ang.mean())}


#: The scores metrics.json keeps (its glossary: README, "What the demo's numbers mean"; the
#: definitions: gpumap.sim.metrics). One row per rule and per pose source holds them too.
_SUMMARY_KEYS = (
    "miss_rate", "miss_rate_objects", "false_negative_rate_detectable", "false_positive_rate_far",
    "free_carved_fraction", "observed_surface_fraction", "pipe_found",
)
#: ... and for the main map also these
_DETAIL_KEYS = ("miss_rate_by_object", "height_error_m")


def _summary(ev: dict) -> dict:
    return {k: ev[k] for k in _SUMMARY_KEYS}


def _rule(rule: str | None, method: str) -> str:
    """The other rules need the gather method: the template method keeps the paper's rule."""
    return "plain" if method == "template" else (rule or "evidence")


def run_demo(args: argparse.Namespace, open_view=None) -> dict:
    """Run the demo for parsed ``args``; returns the metrics written to ``metrics.json``.

    ``open_view(spec, grid, threshold, title)``, when given, returns the live view / recording of the
    mapping at true poses (``ping``, ``add_points``, ``finish``: :class:`gpumap.viewer.session.Session`,
    which the command opens) or None; it is appended to ``args.view_sessions`` (the caller serves it
    on after the outputs are written). The simulator never imports the viewer.
    """
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    quiet = bool(args.no_progress)
    t_start = time.perf_counter()
    voxel_m = DEFAULT_VOXEL_M.get(args.scene, 0.03) if args.voxel_size is None else args.voxel_size
    scene = make_scene(args.scene, voxel_size_m=voxel_m, seed=args.seed)
    n = len(scene.T_W_S)
    sel = np.arange(n)
    if args.pings is not None:
        sel = np.unique(np.linspace(0, n - 1, args.pings).round().astype(int))
    T_true = scene.T_W_S[sel]
    # fail before minutes of simulation if the backend cannot run here (it also compiles the kernels)
    rule = _rule(args.rule, args.method)
    sparse = bool(getattr(args, "sparse", False))
    first = build_mapper(scene, args.backend, args.method, rule, args.threshold, args.shadow_m, sparse=sparse)
    truth = occupancy(scene, seed=args.seed)

    t0 = time.perf_counter()
    pings, seen_each = [], []
    variation = VARIATIONS[getattr(args, "variation", "none")]()
    with SonarSimulator(scene, seed=args.seed, variation=variation, **scene.sonar_params) as sim:
        for i, k in enumerate(_progress(sel, quiet, desc="simulate", unit="ping")):
            p = sim.ping(scene.T_W_S[k], int(k))
            pings.append(p)
            seen_each.append(points_to_voxels(p.points_W, scene.grid))
            if i == 0 or k == sel[len(sel) // 2]:
                sample = p
    sim_s = time.perf_counter() - t0
    _, detectable = ground_truth_masks(pings, scene.grid, args.threshold)
    session = _view_session(open_view, args, scene, truth, detectable, getattr(args, "view_sessions", None))

    mapper, times, history = _map_pings(scene, truth, pings, seen_each, T_true, args.backend, args.method,
                                        args.threshold, quiet, "true poses", curve=True,
                                        shadow_m=args.shadow_m, mapper=first, detectable=detectable,
                                        on_ping=None if session is None else session.ping)
    final = history[-1]
    # the other rules on the same pings, side by side
    rules = {rule: {**_summary(final), "height_error_m": final["height_error_m"],
                    "ms_per_image": 1e3 * float(np.mean(times[1:] if len(times) > 1 else times))}}
    others = [r for r in RULES if r != rule] if args.method == "gather" else []
    evidence_mapper = mapper if rule == "evidence" else None
    for other in others:
        m_o, t_o, _ = _map_pings(scene, truth, pings, seen_each, T_true, args.backend, args.method,
                                 args.threshold, quiet, f"{other} rule", curve=False, shadow_m=args.shadow_m,
                                 rule=other, sparse=sparse)
        if other == "evidence":
            evidence_mapper = m_o
        ev_o = _final_eval(m_o, scene, truth, seen_each, args.threshold, detectable, full=True)
        rules[other] = {**_summary(ev_o), "height_error_m": ev_o["height_error_m"],
                        "ms_per_image": 1e3 * float(np.mean(t_o[1:] if len(t_o) > 1 else t_o))}
    metrics = {
        "scene": scene.name,
        "backend": mapper.backend,
        "method": args.method,
        "rule": rule,
        "voxel_size_m": scene.grid.voxel_size_m,
        "grid_shape": list(scene.grid.shape),
        "images": len(pings),
        "threshold": args.threshold,
        "shadow_m": args.shadow_m,
        "variation": {"name": getattr(args, "variation", "none"), **variation.to_dict()},
        "ms_per_image": 1e3 * float(np.mean(times[1:] if len(times) > 1 else times)),
        "ms_per_image_first": 1e3 * times[0],
        "sim_ms_per_image": 1e3 * sim_s / len(pings),
        **{k: final[k] for k in _SUMMARY_KEYS + _DETAIL_KEYS},
        "height_error_first_view_m": history[0]["height_error_m"],
        "rules": rules,
        "memory": _memory_report(mapper, scene),
    }
    mapper.save(out / "map.npz")
    if getattr(args, "surface", True) and evidence_mapper is not None:
        metrics["surface"] = _surface_layer(out, scene, truth, pings, T_true, seen_each, evidence_mapper,
                                            args.threshold, detectable)

    if args.pose_noise is not None:
        rng = np.random.default_rng([args.seed, 7])
        U, T_odo = _odometry(T_true, float(args.pose_noise), rng)
        rows = {"true": {**_summary(final), **_pose_error(T_true, T_true)}}
        m_odo, _, _ = _map_pings(scene, truth, pings, seen_each, T_odo, args.backend, args.method,
                                 args.threshold, quiet, "odometry", curve=False, shadow_m=args.shadow_m,
                                 rule=rule, sparse=sparse)
        rows["odometry"] = {**_final_eval(m_odo, scene, truth, seen_each, args.threshold, detectable),
                            **_pose_error(T_odo, T_true)}
        try:
            landmarks: dict | None = {} if session is not None else None
            T_ekf, C_ekf = _ekf_poses(scene, pings, U, float(args.pose_noise), rng, landmarks_out=landmarks)
        except ImportError as e:  # the EKF module is optional for the demo
            rows["ekf"] = {"error": f"gpumap.ekf unavailable: {e}"}
        else:
            m_ekf, _, _ = _map_pings(scene, truth, pings, seen_each, T_ekf, args.backend, args.method,
                                     args.threshold, quiet, "EKF", curve=False, shadow_m=args.shadow_m,
                                     rule=rule, sparse=sparse)
            rows["ekf"] = {**_final_eval(m_ekf, scene, truth, seen_each, args.threshold, detectable),
                           **_pose_error(T_ekf, T_true)}
            # the same poses with their covariance: footprints grow with the uncertainty
            m_cov, _, _ = _map_pings(scene, truth, pings, seen_each, T_ekf, args.backend, args.method,
                                     args.threshold, quiet, "EKF + covariance", curve=False,
                                     shadow_m=args.shadow_m, rule=rule, pose_covs=C_ekf, sparse=sparse)
            rows["ekf_cov"] = {**_final_eval(m_cov, scene, truth, seen_each, args.threshold, detectable),
                               **_pose_error(T_ekf, T_true)}
        metrics["pose_noise"] = {"sigma": float(args.pose_noise), "rows": rows}
        if session is not None:
            session.add_path("true", T_true[:, :3, 3], (40, 160, 40))
            session.add_path("odometry", T_odo[:, :3, 3], (140, 140, 140))
            if "error" not in rows["ekf"]:
                session.add_path("ekf", T_ekf[:, :3, 3], (40, 90, 230))
                if landmarks and len(landmarks["points"]):
                    session.add_landmarks(landmarks["points"][:200], landmarks["covs"][:200])
    plan_view = session if getattr(args, "plan", 0) else None  # the planned views go on in the view
    if session is not None and plan_view is None:
        session.finish(mapper)

    _figures(out, scene, truth, mapper, sample, history, args.threshold, detectable)
    if getattr(args, "plan", 0):
        from .plan_demo import run_plan

        last: list = [mapper]

        def on_plan_ping(image, T_W_S, m) -> None:
            last[0] = m
            plan_view.ping(image, T_W_S, m)

        metrics["plan"] = run_plan(scene, pings, T_true, truth, args.plan, args.backend, args.threshold,
                                   args.seed, quiet, out, on_ping=None if plan_view is None else on_plan_ping)
        if plan_view is not None:  # the planned map, its confidence layer shown (confirmed / unconfirmed)
            plan_view.finish(last[0])
    metrics["demo_s"] = time.perf_counter() - t_start
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2, default=_jsonable))
    return metrics


def _view_session(open_view, args: argparse.Namespace, scene: Scene, truth: Truth, detectable: np.ndarray,
                  sessions: list | None):
    """The live view / recording of the true-pose mapping, with the truth beside the map; or None."""
    if open_view is None:
        return None
    session = open_view(scene.sonar_spec, scene.grid, args.threshold,
                        f"gpumap demo ({scene.name}, {scene.grid.voxel_size_m * 100:g} cm)")
    if session is None:
        return None
    if sessions is not None:
        sessions.append(session)
    import matplotlib

    g = scene.grid
    idx = np.argwhere(truth.surface & detectable.reshape(g.shape))
    shift = np.array([np.asarray(g.max_corner_m)[0] - np.asarray(g.min_corner_m)[0] + 0.3, 0.0, 0.0])
    tab = (matplotlib.colormaps["tab10"](np.arange(10))[:, :3] * 255).astype(np.uint8)
    session.add_points("truth", g.centers(idx) + shift, tab[truth.label[tuple(idx.T)] % 10])
    return session


def _surface_layer(out: Path, scene: Scene, truth: Truth, pings: list[Ping], poses: np.ndarray,
                   seen_each: list[np.ndarray], evidence_mapper, threshold: float,
                   detectable: np.ndarray) -> dict:
    """The surface layer (:mod:`gpumap.layers.surface`) of the evidence map, written beside the safe map as
    ``surface.npz`` (a two-layer refined map file: ``gpumap view/export --layer surface|safe``);
    returns its figures for ``metrics.json`` (scored as the rules are, occupied from 0.5)."""
    from gpumap.layers.surface import SURFACE_LEVEL
    from gpumap.layers.surface_live import surface_from_mapper

    t0 = time.perf_counter()
    images = np.stack([p.image for p in pings]).astype(np.float32)
    layer = surface_from_mapper(evidence_mapper, images, poses)
    seconds = time.perf_counter() - t0
    layer.save(out / "surface.npz", evidence_mapper.values(), scene.sonar_spec, threshold, "evidence")
    skip = ("candidates", "surface", "pings", "seconds")
    row = {"seconds": seconds, "candidates": layer.stats["candidates"],
           "surface_voxels": int(layer.surface.sum()),
           "options": {k: v for k, v in layer.stats.items() if k not in skip}}
    if tuple(layer.grid.shape) == tuple(scene.grid.shape):
        seen = np.zeros(scene.grid.n_voxels, bool)
        for s in seen_each:
            seen[s] = True
        ev = evaluate(layer.values(), truth, SURFACE_LEVEL, seen.reshape(scene.grid.shape),
                      scene.grid.voxel_size_m, detectable=detectable).to_dict()
        row.update({**_summary(ev), "height_error_m": ev["height_error_m"]})
    return row


def _final_eval(mapper, scene: Scene, truth: Truth, seen_each: list[np.ndarray], threshold: float,
                detectable: np.ndarray | None = None, full: bool = False) -> dict:
    seen = np.zeros(scene.grid.n_voxels, bool)
    for s in seen_each:
        seen[s] = True
    ev = evaluate(mapper.values(), truth, threshold, seen.reshape(scene.grid.shape), scene.grid.voxel_size_m,
                  detectable=detectable)
    return ev.to_dict() if full else _summary(ev.to_dict())


def _jsonable(o):
    if isinstance(o, np.generic):
        return o.item()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def _figures(out: Path, scene: Scene, truth: Truth, mapper, sample: Ping, history: list[dict],
             threshold: float, detectable: np.ndarray) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sp = scene.sonar_spec
    # Sample ping: polar and fan.
    fig, ax = plt.subplots(1, 2, figsize=(12, 4.5))
    ext = [math.degrees(sp.beam_edges_rad[0]), math.degrees(sp.beam_edges_rad[-1]),
           sp.range_min_m, sp.range_max_m]
    ax[0].imshow(sample.image, origin="lower", aspect="auto", extent=ext, cmap="copper", vmin=0, vmax=1)
    ax[0].set(xlabel="azimuth (deg)", ylabel="range (m)", title="simulated ping (polar)")
    rr = np.linspace(sp.range_min_m, sp.range_max_m, sp.n_bins + 1)
    R, A = np.meshgrid(rr, sp.beam_edges_rad, indexing="ij")
    ax[1].pcolormesh(-R * np.sin(A), R * np.cos(A), sample.image, cmap="copper", vmin=0, vmax=1,
                     shading="flat")
    ax[1].set(aspect="equal", xlabel="right (m)", ylabel="forward (m)", title="fan view")
    fig.tight_layout()
    fig.savefig(out / "sonar_image.png", dpi=90)
    plt.close(fig)

    # Map vs truth from one viewpoint (shaded voxels, pyrender offscreen), top-down height maps,
    # and false negatives / positives per object (gpumap.io.pictures).
    from .pictures import demo_pictures

    demo_pictures(out, scene.grid, mapper.values(), truth, threshold, mapper.rule, title=f"{scene.name}: ",
                  detectable=detectable)

    # Error by view count.
    k = np.array([h.get("pings", i + 1) for i, h in enumerate(history)])
    fig, ax = plt.subplots(1, 2, figsize=(12, 4.5))
    for key, words in (("miss_rate", "missed: detectable surface not called occupied"),
                       ("miss_rate_objects", "missed, small objects only"),
                       ("false_positive_rate_far", "phantom: water > 1 voxel from a surface called occupied"),
                       ("free_carved_fraction", "water called free (carved)")):
        ax[0].plot(k, [h[key] for h in history], label=words)
    ax[0].set(xlabel="pings integrated", ylabel="rate", ylim=(0, 1), title="occupancy errors")
    ax[0].legend(fontsize=8)
    for name in history[-1]["height_error_m"]:
        ax[1].plot(k, [h["height_error_m"].get(name, np.nan) for h in history], label=name)
    ax[1].axhline(0, color="k", lw=0.5)
    ax[1].set(xlabel="pings integrated", ylabel="map top - truth top (m)",
              title="height error (elevation stretch)")
    ax[1].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "error_by_views.png", dpi=90)
    plt.close(fig)
