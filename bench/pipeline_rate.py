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

from .common import bench_parser, oasis_tank_dir, run_header, write_json

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
