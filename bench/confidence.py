"""The confidence layer's cost: mapping the real tank frames with and without it, per backend.

    python -m bench.confidence                                  # CPU backends, section "cpu"
    python -m bench.confidence --backend warp-cuda opencl-gpu --section gpu --frames-from NPZ

The 123 real OASIS tank frames (``bench.speed``'s cache) on the OASIS box; per backend two mappers
(``confidence=False`` and ``True``) map the same pings, one ping a call (``integrate``, as a vehicle
maps), the two in turn ``--repeat`` times in one process; the best wall time of each (and the best
CPU time of the process, all threads, which other processes' load inflates less) and their ratio.
Each backend's layer and map are compared with the NumPy reference's (the ``numpy`` backend runs
``gpumap.layers.confidence.confirm_ping``) bit for bit. The machine's load is recorded around every row.
"""

from __future__ import annotations

import os
import platform
import time
from pathlib import Path

import numpy as np

import gpumap
from gpumap.layers.confidence import with_confidence

from . import common
from .common import CpuShare, Section, bench_parser, load_average, merge_json

WARMUP = 3


def _map_all(m: gpumap.MinMaxMapper, images: np.ndarray, poses: np.ndarray) -> tuple[float, float]:
    """Wall and process CPU seconds of mapping every ping into a fresh ``m``."""
    m.reset()
    m.synchronize()
    t, c = time.perf_counter(), time.process_time()
    for img, T in zip(images, poses, strict=True):
        m.integrate(img, T)
    m.synchronize()
    return time.perf_counter() - t, time.process_time() - c


def reference(fr, grid: gpumap.GridSpec) -> dict:
    """The NumPy reference's layer and values of every frame."""
    m = with_confidence(gpumap.MinMaxMapper(fr.spec, grid, backend="numpy"))
    for img, T in zip(fr.images, fr.poses, strict=True):
        m.integrate(img, T)
    lay = m.layer("confidence")
    return {"confirmed": lay.confirmed.copy(), "arcs": lay.arcs.copy(), "values": m.raw_values()}


def row(fr, grid: gpumap.GridSpec, backend: str, repeat: int, ref: dict | None) -> dict:
    """One backend: best wall and CPU seconds with and without the layer, their ratios, the check."""
    ms = {c: gpumap.MinMaxMapper(fr.spec, grid, backend) for c in (False, True)}
    with_confidence(ms[True])
    for m in ms.values():  # compile or load the kernels, allocate the buffers
        for img, T in zip(fr.images[:WARMUP], fr.poses[:WARMUP], strict=True):
            m.integrate(img, T)
        m.synchronize()
    wall = {False: [], True: []}
    cpu = {False: [], True: []}
    load_start = load_average()
    with CpuShare() as share:
        for _ in range(repeat):
            for c, m in ms.items():
                w, p = _map_all(m, fr.images, fr.poses)
                wall[c].append(w)
                cpu[c].append(p)
    out = {"device": ms[True].device, "pings": len(fr.images), "repeat": repeat,
           "map_s": min(wall[False]), "map_confidence_s": min(wall[True]),
           "map_cpu_s": min(cpu[False]), "map_confidence_cpu_s": min(cpu[True]),
           "wall_s_all": {"without": wall[False], "with": wall[True]},
           "loadavg_start": load_start, "loadavg_end": load_average(), "others_cores": share.others_cores}
    out["ratio"] = out["map_confidence_s"] / out["map_s"]
    out["cpu_ratio"] = out["map_confidence_cpu_s"] / out["map_cpu_s"]
    m = ms[True]  # after its last pass: the layer of every frame
    if ref is not None:
        lay = m.layer("confidence")
        out["confirmed_voxels"] = int(lay.confirmed.sum())
        out["layer_equal_to_reference"] = bool(np.array_equal(lay.confirmed, ref["confirmed"])
                                               and np.array_equal(lay.arcs, ref["arcs"]))
        out["values_equal_to_reference"] = bool(np.array_equal(m.raw_values().view(np.uint32),
                                                               ref["values"].view(np.uint32)))
    print(f"{backend:11s} {out['map_s']:.3f} s -> {out['map_confidence_s']:.3f} s with the layer: "
          f"{out['ratio']:.2f}x (CPU time {out['cpu_ratio']:.2f}x), equal to the reference: "
          f"{out.get('layer_equal_to_reference')}, load {out['loadavg_start']} -> {out['loadavg_end']}",
          flush=True)
    return out


def _git() -> dict:
    """The code timed: the checkout's commit, or on a copy without git the one GPUMAP_COMMIT names."""
    g = common._git_state()
    if not g.get("commit"):
        g = {"commit": os.environ.get("GPUMAP_COMMIT"), "copy": True}
    return g


def markdown(data: dict, folder: Path) -> str:
    """The BENCHMARKS.md block of a results file (every figure read from it)."""
    out = [common.template("confidence-intro"), "", common.template("confidence-head")]
    for sec, s in data.get("sections", {}).items():
        commit = (s.get("git") or {}).get("commit")
        run = f"{sec} ({commit[:7]})" if commit else sec
        for b, r in s["rows"].items():
            la = ", ".join(f"{x:.1f}" for x in (r["loadavg_start"] or []))
            eq = "yes" if r.get("layer_equal_to_reference") and r.get("values_equal_to_reference") else (
                "not checked" if "layer_equal_to_reference" not in r else "NO")
            out.append(f"| {run} | {b} | {r['device']} | {r['map_s']:.3f} | {r['map_confidence_s']:.3f} | "
                       f"**{r['ratio']:.2f}x** | {r['cpu_ratio']:.2f}x | {eq} | {la} |")
    return "\n".join(out)


SECTION = Section("confidence", "## The confidence layer on the device (issue 37)", "confidence.json",
                  markdown)


def main(argv: list[str] | None = None) -> int:
    p = bench_parser("confidence", __doc__, out="bench/results/confidence.json",
                     backend=("opencl-cpu", "warp-cpu"), voxel=0.05, report="confidence.json")
    p.add_argument("--section", default="cpu", help="key of the rows in the results file")
    p.add_argument("--repeat", type=int, default=3, help="timed passes of each mapper (best kept)")
    p.add_argument("--frames-from", type=Path, default=None,
                   help="the frames' cache (bench.speed's; default bench/results/tmp/oasis_polar.npz)")
    p.add_argument("--no-check", action="store_true", help="skip the comparison with the NumPy reference")
    a = p.parse_args(argv)
    if a.report is not None:  # the results file is --out itself
        SECTION.write(a.report, a.out.parent)
        return 0
    from .speed import CACHE, load_frames, oasis_grid

    fr = load_frames(a.frames_from or CACHE)
    grid = oasis_grid(a.voxel)
    ref = None if a.no_check else reference(fr, grid)
    rows = {b: row(fr, grid, b, a.repeat, ref) for b in a.backend}
    doc = {"machine": platform.node(), "cpus": os.cpu_count(), "cpu_model": common._cpu_model(),
           "voxel_size_m": a.voxel, "grid_shape": list(grid.shape), "created": common.now(),
           "git": _git(), "rows": rows}
    merge_json(a.out, ["sections", a.section], doc, schema="gpumap-bench-confidence/1")
    SECTION.write("BENCHMARKS.md", a.out.parent)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
