"""``python -m bench.parity``: every map of the real tank frames on every backend here equals NumPy's, bit for
bit.

The restructured tree's whole mapping path (``MinMaxMapper`` with ``MapperParams``, ``integrate_batch``
then ``integrate``, the confidence layer attached) on the first 60 frames of ``shared/data/oasis_tank``
at 5 cm and 2 cm, every rule and both methods: the values, the evidence counts and the confidence
layer's states and arcs hashed per backend and compared with the NumPy oracle's. Run it on a GPU
machine (``warp-cuda``, ``opencl-gpu``); CPU backends are checked by the tests. Seconds a row.
"""

from __future__ import annotations

import hashlib
import time
from pathlib import Path

import numpy as np

from .common import bench_parser, oasis_tank_dir, run_header, write_json

CASES = (("evidence", "gather"), ("visible", "gather"), ("plain", "gather"), ("plain", "template"))


def _h(a: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(a).tobytes()).hexdigest()[:16]


def fingerprints(spec, grid, imgs, Ts, backend: str, rule: str, method: str, confidence: bool) -> dict:
    """Hashes of one map built on ``backend`` (a batch, then ping by ping), its counts and its layer."""
    from gpumap import MapperParams, MinMaxMapper
    from gpumap.layers.confidence import ConfidenceLayer

    m = MinMaxMapper(spec, grid, backend, MapperParams(rule=rule, threshold=0.4, method=method))
    conf = m.attach(ConfidenceLayer()) if confidence else None
    half = len(imgs) * 2 // 3
    t0 = time.perf_counter()
    m.integrate_batch(imgs[:half], Ts[:half])
    for i in range(half, len(imgs)):
        m.integrate(imgs[i], Ts[i])
    m.synchronize()
    out = {"values": _h(m.raw_values()), "seconds": round(time.perf_counter() - t0, 3)}
    if rule != "plain":
        ev = m.evidence()
        out["counts"] = _h(np.stack([ev["count"], ev["hits"]]))
    if conf is not None:
        out["confidence"] = _h(conf.states()) + _h(conf.arcs)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = bench_parser("parity", __doc__, out="bench/results/parity.json", backend=())
    ap.add_argument("--data", type=Path, default=None, help="the oasis_tank folder (default: shared/data)")
    ap.add_argument("--frames", type=int, default=60, help="frames used (default 60)")
    a = ap.parse_args(argv)
    from gpumap.backends import available_backends
    from gpumap.io import open_recording
    from gpumap.spec import auto_grid

    data = a.data or oasis_tank_dir()
    if data is None:
        raise SystemExit("bench.parity: shared/data/oasis_tank not found; pass --data")
    frames = [f for _, f in zip(range(a.frames), open_recording(data), strict=False)]
    spec = frames[0].spec
    imgs, Ts = np.stack([f.image for f in frames]), np.stack([f.T_W_S for f in frames])
    backends = [b for b in (a.backend or available_backends()) if b != "numpy"]
    res = {**run_header("gpumap-parity/1", argv), "frames": len(frames), "backends": backends, "rows": []}
    for vox in (0.05, 0.02):
        grid = auto_grid(spec, Ts, vox)
        for rule, method in CASES:
            conf = vox == 0.05 and method == "gather"
            row = {"voxel_m": vox, "rule": rule, "method": method, "confidence_layer": conf,
                   "numpy": fingerprints(spec, grid, imgs, Ts, "numpy", rule, method, conf)}
            for b in backends:
                row[b] = fingerprints(spec, grid, imgs, Ts, b, rule, method, conf)
            ref = {k: v for k, v in row["numpy"].items() if k != "seconds"}
            row["equal"] = {b: {k: v for k, v in row[b].items() if k != "seconds"} == ref for b in backends}
            res["rows"].append(row)
            print(vox, rule, method, row["equal"], flush=True)
    res["all_equal"] = all(all(r["equal"].values()) for r in res["rows"])
    print(f"wrote {write_json(a.out, res)}: {'every map equal' if res['all_equal'] else 'DIFFERENCES'}")
    return 0 if res["all_equal"] else 1


if __name__ == "__main__":
    raise SystemExit(main())
