"""``python -m bench.surface``: the surface layer (gpumap.layers.surface) against the visible and evidence
maps.

Simulated scenes (true poses, 3 cm, the simulator's threshold 0.1): ``tank`` (the paper's 40
pings), ``circle`` (60 pings from five sides) and ``side`` (40 pitched pings from one side, no
roll: :func:`gpumap.sim.scenes.side_scene`), each with the simulator as it is (``none``) and with
the real tank's ping-to-ping variation (``real_tank``, :meth:`SonarVariation.real_tank`). Each map is
scored against the truth by :func:`gpumap.sim.metrics.evaluate` (FN on detectable surfaces, FN of
the objects, FP far from surfaces, miss rates where unknown counts as missed; object tops in
voxels): the visible and evidence maps at the threshold, the surface layer from 0.5.

The real OASIS tank (full run, 5 cm, threshold 0.4), judged by first returns
(:func:`gpumap.layers.first_return.first_return_score`): ``tune`` maps frames 0-599 and judges every 5th of
600-799 (where the layer's settings were chosen); ``held_out`` maps frames 0-799 and judges frames
800-1222, once, with those settings.

Speed (the layer's seconds on this machine) is recorded with the error, and the load before and
after each case. Writes ``bench/results/surface.json``::

    python -m bench.surface                       # everything (about 5 minutes on 2 cores)
    python -m bench.surface --cases side --variations none
    python -m bench.surface --report BENCHMARKS.md
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import numpy as np

from gpumap.core.params import MapperParams

from .common import Section, bench_parser, load_average, machine_info, oasis_full_dir, write_json

SIM_THRESHOLD = 0.1
REAL_THRESHOLD = 0.4
SIM_VOXEL_M, REAL_VOXEL_M = 0.03, 0.05
TUNE = ((0, 600), (600, 800, 5))
HELD = ((0, 800), (800, 1223, 1))
KEYS = ("false_negative_rate_detectable", "false_negative_rate_objects_detectable", "false_positive_rate_far",
        "miss_rate", "miss_rate_objects", "free_carved_fraction")


def _parser():
    p = bench_parser("surface", __doc__, out="bench/results", backend="auto", report="surface.json")
    p.add_argument("--cases", nargs="+", default=["tank", "circle", "side", "oasis"],
                   help="simulated scenes (tank, circle, side) and/or oasis (the real tank's full run)")
    p.add_argument("--variations", nargs="+", default=["none", "real_tank"], choices=["none", "real_tank"],
                   help="simulated sonar variations")
    p.add_argument("--data", type=Path, default=None, help="the full tank run (default: oasis_tank_full)")
    return p


def _score(values: np.ndarray, truth, threshold: float, seen, det, voxel: float) -> dict:
    from gpumap.sim.metrics import evaluate

    ev = evaluate(values, truth, threshold, seen, voxel, detectable=det).to_dict()
    out = {k: ev[k] for k in KEYS}
    out["top_error_voxels"] = {k: v / voxel for k, v in ev["height_error_m"].items()}
    return out


def sim_case(name: str, variation: str, backend: str) -> dict:
    """Render the scene, map it with the visible and evidence rules, build the surface layer, score."""
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    from gpumap.sim.metrics import ground_truth_masks
    from gpumap.sim.scenes import make_scene
    from gpumap.sim.sonar import SonarSimulator
    from gpumap.sim.truth import occupancy
    from gpumap.sim.variation import SonarVariation

    import gpumap
    from gpumap.layers.surface import SURFACE_LEVEL
    from gpumap.layers.surface_live import surface_from_mapper

    scene = make_scene(name, voxel_size_m=SIM_VOXEL_M, seed=0)
    var = SonarVariation.real_tank() if variation == "real_tank" else None
    with SonarSimulator(scene, seed=0, variation=var) as sim:
        pings = [sim.ping(scene.T_W_S[k], k) for k in range(len(scene.T_W_S))]
    images = np.stack([np.round(p.image * 255.0).astype(np.uint8) for p in pings])  # as the Oculus sends
    poses = scene.T_W_S
    truth = occupancy(scene, seed=0)
    seen, det = ground_truth_masks(pings, scene.grid, SIM_THRESHOLD)
    row = {"case": name, "variation": variation, "pings": len(pings), "voxel_size_m": SIM_VOXEL_M,
           "threshold": SIM_THRESHOLD, "load_before": load_average(), "maps": {}}
    mappers = {}
    for rule in ("visible", "evidence"):
        m = gpumap.MinMaxMapper(
            scene.sonar_spec, scene.grid, backend, MapperParams(rule=rule, threshold=SIM_THRESHOLD)
        )
        t0 = time.perf_counter()
        m.integrate_batch(images, poses)
        m.synchronize()
        mappers[rule] = m
        row["maps"][rule] = {**_score(m.values(), truth, SIM_THRESHOLD, seen, det, SIM_VOXEL_M),
                             "seconds": time.perf_counter() - t0}
    row["backend"] = mappers["evidence"].backend
    t0 = time.perf_counter()
    layer = surface_from_mapper(mappers["evidence"], images, poses)
    row["maps"]["surface"] = {**_score(layer.values(), truth, SURFACE_LEVEL, seen, det, SIM_VOXEL_M),
                              "seconds": time.perf_counter() - t0, "candidates": layer.stats["candidates"],
                              "surface_voxels": int(layer.surface.sum())}
    row["options"] = {k: v for k, v in layer.stats.items() if k not in ("candidates", "surface", "pings",
                                                                        "seconds")}
    row["load_after"] = load_average()
    return row


def _load_real(data: Path):
    from gpumap.io import open_recording

    rec = open_recording(data)
    images, poses, spec = [], [], None
    for f in rec:
        img = f.image
        images.append(img if img.dtype == np.uint8 else np.round(np.asarray(img) * 255.0).astype(np.uint8))
        poses.append(f.T_W_S)
        spec = f.spec
    return spec, np.stack(images), np.stack(poses)


def real_case(data: Path, backend: str) -> dict:
    """Frames mapped / judged by first returns, tune and held-out splits (module docstring)."""
    import gpumap
    from gpumap.layers.first_return import first_return_score
    from gpumap.layers.surface_live import surface_from_mapper
    from gpumap.spec import auto_grid

    spec, images, poses = _load_real(data)
    if len(images) < HELD[1][1]:
        raise SystemExit(f"bench.surface: expected the full run of {HELD[1][1]} frames, but {data} holds "
                         f"{len(images)}")
    grid = auto_grid(spec, poses, REAL_VOXEL_M)
    out = {"case": "oasis", "data": str(data), "voxel_size_m": REAL_VOXEL_M, "threshold": REAL_THRESHOLD,
           "grid_shape": list(grid.shape)}
    for split, ((m0, m1), (j0, j1, js)) in (("tune", TUNE), ("held_out", HELD)):
        load0 = load_average()
        train = np.arange(m0, m1)
        judge = range(j0, j1, js)

        def judged(values, thr, judge=judge):  # thr: the map's occupied level and the image's bright one
            frames = ((images[i] * np.float32(1.0 / 255.0), poses[i]) for i in judge)  # intensities in [0, 1]
            s = first_return_score(values, grid, thr, frames, spec)
            return s.to_dict()

        row = {"mapped_frames": [m0, m1], "judged_frames": [j0, j1, js], "load_before": load0, "maps": {}}
        for rule in ("visible", "evidence"):
            m = gpumap.MinMaxMapper(spec, grid, backend, MapperParams(rule=rule, threshold=REAL_THRESHOLD))
            t0 = time.perf_counter()
            for a in range(0, len(train), 64):
                m.integrate_batch(images[train[a:a + 64]], poses[train[a:a + 64]])
            m.synchronize()
            row["maps"][rule] = {"seconds": time.perf_counter() - t0, **judged(m.values(), REAL_THRESHOLD)}
            row["backend"] = m.backend
            if rule == "evidence":
                t0 = time.perf_counter()
                layer = surface_from_mapper(m, images[train], poses[train])
                row["maps"]["surface"] = {"seconds": time.perf_counter() - t0,
                                          "candidates": layer.stats["candidates"],
                                          "surface_voxels": int(layer.surface.sum()),
                                          # values 1 / 0: occupied from the image threshold too
                                          **judged(layer.values(), REAL_THRESHOLD)}
        row["load_after"] = load_average()
        out[split] = row
        print(f"oasis {split}: " + ", ".join(
            f"{k} agree {v['agreement']:.1%} phantom {v['phantom_rate']:.1%} missing {v['missing_rate']:.1%}"
            for k, v in row["maps"].items()), flush=True)
    return out


def main(argv: list[str] | None = None) -> int:
    a = _parser().parse_args(argv)
    if SECTION.reported(a):
        return 0
    t_start = time.perf_counter()
    res = {"schema": "gpumap-surface/1", "machine": machine_info(), "sim": [], "real": None}
    for case in a.cases:
        if case == "oasis":
            data = a.data or oasis_full_dir()
            if data is None:
                print("bench.surface: the full tank run was not found (oasis_tank_full); skipping oasis",
                      file=sys.stderr)
                continue
            res["real"] = real_case(Path(data), a.backend)
            continue
        for var in a.variations:
            row = sim_case(case, var, a.backend)
            res["sim"].append(row)
            print(f"{case} ({var}): " + "; ".join(
                f"{k} FN {v['false_negative_rate_detectable']:.1%} FN obj "
                f"{v['false_negative_rate_objects_detectable']:.1%} FP far {v['false_positive_rate_far']:.1%}"
                for k, v in row["maps"].items()), flush=True)
    res["seconds_total"] = time.perf_counter() - t_start
    res["load_end"] = load_average()
    path = write_json(Path(a.out) / "surface.json", res, digits=4)
    print(f"wrote {path} ({res['seconds_total']:.0f} s)")
    return 0


HEADING = "## The surface layer: one voxel per bright cell (issue #30)"


def markdown(res: dict, folder: Path) -> str:
    """The BENCHMARKS.md section of a ``surface.json``."""
    m = res["machine"]
    del folder
    out = [HEADING, "",
           f"`python -m bench.surface` ({m.get('cpu_model')} x{m.get('cpu_count')}, load "
           f"{m.get('load_avg_start')} at the start). Simulated scenes at 3 cm (threshold 0.1; FN on "
           "detectable surfaces, FN of the objects, FP far from surfaces, object tops: mean over columns "
           "of map top - true top, voxels):", "",
           "| scene | variation | map | FN | FN objects | FP far | tops (voxels) | seconds |",
           "|---|---|---|---|---|---|---|---|"]
    for row in res.get("sim", []):
        for name, x in row["maps"].items():
            tops = ", ".join(f"{k} {v:+.1f}" for k, v in x["top_error_voxels"].items()
                             if v is not None and v == v)
            out.append(f"| {row['case']} | {row['variation']} | {name} | "
                       f"{100 * x['false_negative_rate_detectable']:.1f} % | "
                       f"{100 * x['false_negative_rate_objects_detectable']:.1f} % | "
                       f"{100 * x['false_positive_rate_far']:.1f} % | {tops} | {x['seconds']:.2f} |")
    r = res.get("real")
    if r:
        out += ["", "Real tank (5 cm, threshold 0.4), first-return judge:", "",
                "| split | map | agrees | phantom in front | missing | seconds |",
                "|---|---|---|---|---|---|"]
        for split in ("tune", "held_out"):
            for name, x in r[split]["maps"].items():
                out.append(f"| {split} | {name} | {100 * x['agreement']:.1f} % | "
                           f"{100 * x['phantom_rate']:.1f} % | {100 * x['missing_rate']:.1f} % | "
                           f"{x['seconds']:.1f} |")
    return "\n".join(out)


SECTION = Section("surface", HEADING, "surface.json", markdown)

if __name__ == "__main__":
    raise SystemExit(main())
