"""``python -m bench.pipeline_rate``: the replay pipeline's stages alone and together on the real tank frames.

Per backend and voxel size (the public OASIS code's box, 2.4 x 2.4 x 1.3 m): the frames decoded alone
(reading and converting the PNGs), mapped alone from memory (:func:`gpumap.core.feed.feed`, batches of 64,
the recording repeated ``--repeat`` times), and the whole replay (:func:`gpumap.pipeline.replay.run_replay`:
decoding on a thread of its own while the mapper maps), best of 3 each; the replay's share of its slowest
stage says whether the pipeline, not a stage, sets the pace. The replay's map is checked equal to the
in-memory one.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from .common import Section, bench_parser, oasis_tank_dir, run_header, write_json

BOX = ((-0.5, -1.2, -0.5), (1.9, 1.2, 0.8))


def _best(fn, n: int = 3) -> float:
    best = float("inf")
    for _ in range(n):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def main(argv: list[str] | None = None) -> int:
    ap = bench_parser("pipeline_rate", __doc__, out="bench/results/pipeline_rate.json", backend=(),
                      voxel=(0.01, 0.005))
    ap.add_argument("--data", type=Path, default=None, help="the oasis_tank folder (default: shared/data)")
    ap.add_argument("--repeat", type=int, default=20, help="the frames mapped this many times in memory")
    a = ap.parse_args(argv)
    import gpumap
    from gpumap.backends import available_backends
    from gpumap.core.feed import feed
    from gpumap.io import open_recording
    from gpumap.pipeline.replay import run_replay

    data = a.data or oasis_tank_dir()
    if data is None:
        raise SystemExit("bench.pipeline_rate: shared/data/oasis_tank not found; pass --data")
    rec = open_recording(data)
    spec = next(iter(rec)).spec
    frames: list = []
    t_dec = _best(lambda: frames.__setitem__(slice(None), [(np.array(f.image), f.T_W_S) for f in rec]))
    res = {**run_header("gpumap-pipeline-rate/1", argv), "frames": len(frames), "repeat": a.repeat,
           "decode_frames_per_s": len(frames) / t_dec, "rows": []}
    for vox in a.voxel:
        grid = gpumap.GridSpec(*BOX, vox)
        for be in a.backend or available_backends():
            m = gpumap.MinMaxMapper(spec, grid, be, gpumap.MapperParams(threshold=0.4))
            feed(m, frames[:64], batch=64)
            m.synchronize()

            def in_memory(m=m):
                m.reset()
                feed(m, frames * a.repeat, batch=64)
                m.synchronize()

            t_mem = _best(in_memory) / a.repeat
            out: dict = {}

            def replay(be=be, grid=grid, out=out):
                mm, _ = run_replay(rec, backend=be, grid=grid, progress=False, threshold=0.4)
                mm.synchronize()
                out["map"] = mm

            t_rep = _best(replay)
            m.reset()
            feed(m, frames, batch=64)
            slowest = max(t_dec, t_mem)
            row = {"voxel_m": vox, "backend": be, "grid_shape": list(grid.shape),
                   "in_memory_frames_per_s": len(frames) / t_mem, "replay_frames_per_s": len(frames) / t_rep,
                   "slowest_stage": "decode" if t_dec >= t_mem else "mapping",
                   "replay_over_slowest_stage": slowest / t_rep,
                   "same_map": bool(np.array_equal(out["map"].raw_values(), m.raw_values()))}
            res["rows"].append(row)
            print(row, flush=True)
            write_json(a.out, res)
    print(f"wrote {write_json(a.out, res)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())


def _machine(d: dict) -> str:
    m = d.get("machine", {})
    gpus = ", ".join(m.get("gpus") or []) or "no GPU"
    load = m.get("load_avg_start")
    return (f"{m.get('cpu_model', '?')}, {m.get('cpu_count', '?')} cores, {gpus}; load "
            f"{'/'.join(f'{x:.1f}' for x in load) if load else '?'} at the start")


def markdown(docs: list[tuple[str, dict]], folder: Path) -> str:
    """The BENCHMARKS.md block of every ``pipeline_rate*.json`` and ``parity*.json``."""
    out = [
        "`python -m bench.pipeline_rate` times the replay's stages alone and together on the real tank's 123",
        "frames (the public OASIS box); `python -m bench.parity` compares every map of the restructured",
        "tree on each backend with NumPy's. Decoders: `GPUMAP_DECODERS` (the threads that decode pictures",
        "ahead; default half the cores; `pipeline_rate_h200.json` ran before they existed: one thread).",
        "",
        "| results file | machine | voxel | backend | decode alone, frames/s | mapping from memory, frames/s "
        "| replay, frames/s | replay / slowest stage | same map |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for name, d in docs:
        if d.get("schema") != "gpumap-pipeline-rate/1":
            continue
        for r in d["rows"]:
            out.append(
                f"| `{name}` | {_machine(d)} | {r['voxel_m'] * 1000:g} mm | {r['backend']} | "
                f"{d['decode_frames_per_s']:,.0f} | {r['in_memory_frames_per_s']:,.0f} | "
                f"{r['replay_frames_per_s']:,.0f} | {r['replay_over_slowest_stage']:.2f} | {r['same_map']} |"
            )
    par = [(n, d) for n, d in docs if d.get("schema") == "gpumap-parity/1"]
    for name, d in par:
        n = len(d["rows"])
        out += [
            "",
            f"`{name}` ({_machine(d)}): {n} maps (every rule and method, 5 cm and 2 cm, "
            f"{d['frames']} frames, the confidence layer at 5 cm) on {', '.join(d['backends'])}: "
            + ("every one equal to NumPy's bit for bit." if d["all_equal"] else "NOT all equal to NumPy's."),
        ]
    return "\n".join(out)


SECTION = Section(
    "pipeline-rate",
    "## The replay pipeline's stages and the restructured tree's parity (issues 42, 46)",
    "*_h200*.json",
    markdown,
)
