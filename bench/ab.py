"""Two source trees timed side by side: a bounded map's speed, in alternating runs of one session.

    python -m bench.ab --a /path/to/other/checkout --voxel-size 0.03 0.01 --backend opencl-cpu warp-cpu

Tree B is this checkout unless ``--b`` says otherwise; both must give the same map (a digest of its
values). Writes ``bench/results/ab_<tag>.json``; ``--report BENCHMARKS.md`` writes the table of every
such file there (bench/README.md tells more).
"""

from __future__ import annotations

import hashlib
import importlib.util
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from gpumap.core.params import MapperParams

if __package__:  # bench.ab; run as a script (the worker), only gpumap and the harness by path are imported
    from . import common
    from .common import CpuShare, Section, bench_parser, idle_check, refuse, run_header, spread, write_json

WARMUP = 3


def _package(tree: Path, into: Path) -> Path:
    """A folder that imports ``gpumap`` from ``tree`` (its gpumap/, kernels/, sim/ and bench/ as
    the installed package lays them out) by symbolic links."""
    pkg = into / "gpumap"
    pkg.mkdir(parents=True)
    for f in (tree / "gpumap").iterdir():
        if f.name not in ("kernels", "sim", "bench"):  # a tree may link them there itself
            (pkg / f.name).symlink_to(f.resolve())
    for sub in ("kernels", "sim", "bench"):
        (pkg / sub).symlink_to((tree / sub).resolve())
    return into


def _worker(job: dict) -> None:
    """One timed run in this process (this file run as a script: gpumap from the tree on
    PYTHONPATH, the synthetic tank from this file's harness, loaded by path); prints one JSON line."""
    spec_ = importlib.util.spec_from_file_location("bench_harness", Path(__file__).with_name("common.py"))
    c = sys.modules["bench_harness"] = importlib.util.module_from_spec(spec_)
    spec_.loader.exec_module(c)
    import gpumap

    if job["gpu_chunk"]:
        import gpumap.backends

        gpumap.backends.GPU_CHUNK = job["gpu_chunk"]
    n, batch, spec = job["images"], job["batch"], c.tank_spec()
    imgs, poses = c.speckle(spec, min(n, 16)), c.trajectory(n)
    m = gpumap.MinMaxMapper(spec, c.tank_grid(job["voxel"]), job["backend"],
                            MapperParams(**({"rule": job["rule"]} if job["rule"] else {})))
    for k in range(WARMUP):
        m.integrate(imgs[k], poses[k])
    m.synchronize()
    m.reset()
    stack = np.stack(imgs)
    t = time.perf_counter()
    for k0 in range(0, n, batch or 1):
        if batch:
            ks = np.arange(k0, min(n, k0 + batch))
            m.integrate_batch(stack[ks % len(imgs)], np.stack([poses[k] for k in ks]))
        else:
            m.integrate(imgs[k0 % len(imgs)], poses[k0])
    m.synchronize()
    dt = time.perf_counter() - t
    # digest min_all: the min over every view, which every rule keeps (trees whose default rules
    # differ: the same views were folded, though the rules then read them differently)
    v = m.evidence()["min_all"] if job["digest"] == "min_all" and m.rule != "plain" else m.raw_values()
    print(json.dumps({"images_per_s": n / dt, "backend": m.backend, "device": m.device,
                      "gpumap_file": gpumap.__file__, "observed": int(np.isfinite(v).sum()),
                      "digest": hashlib.sha256(v.tobytes()).hexdigest()[:16]}), flush=True)


def _run(root: Path, tree: Path, job: dict) -> dict:
    path = os.pathsep.join(x for x in (str(root), os.environ.get("PYTHONPATH")) if x)
    with CpuShare() as share:
        p = subprocess.run([sys.executable, "-P", str(Path(__file__).resolve()), "--worker", json.dumps(job)],
                           env={**os.environ, "PYTHONPATH": path}, cwd=root, capture_output=True, text=True,
                           timeout=3600)
    if p.returncode != 0:
        raise RuntimeError(f"{tree} {job['backend']} {job['voxel']}: {p.stderr.strip()[-2000:]}")
    out = json.loads(p.stdout.strip().splitlines()[-1])
    if not str(Path(out["gpumap_file"]).resolve()).startswith(str(tree.resolve())):
        raise RuntimeError(f"Expected gpumap imported from {tree}, but it came from {out['gpumap_file']}")
    return out | {"others_cores": share.others_cores}


def markdown(docs: list[tuple[str, dict]], folder: Path) -> str:
    """The BENCHMARKS.md block of ``ab_*.json`` results: one row per (file, voxel, backend)."""
    out = [common.template("ab")]
    for name, d in docs:
        for r in d["rows"]:
            same = "yes" if r.get("digest", "values") == "values" else "same views"
            a, b = r["a"]["images_per_s"], r["b"]["images_per_s"]
            out.append(f"| `{name}` | {r['device']} | {r['voxel_size_m'] * 100:g} cm | {r['backend']} | "
                       f"{r['images']} | {r['batch'] or '-'} | "
                       f"{a['median']:.1f} ({a['min']:.0f}-{a['max']:.0f}) | "
                       f"{b['median']:.1f} ({b['min']:.0f}-{b['max']:.0f}) | {r['b_over_a']:.3f} | "
                       f"{same if r['same_map'] else '**no**'} |")
    return "\n".join(out)


SECTION = Section("ab", "## One mapper over blocks: speed against the two mappers it replaced (issue #24)",
                  "ab_*.json", markdown) if __package__ else None


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--worker"]:
        _worker(json.loads(argv[1]))
        return 0
    ap = bench_parser("ab", __doc__, out="bench/results", voxel=[0.03, 0.01],
                      backend=["opencl-cpu", "warp-cpu"], tag="cpu", report="ab_*.json")
    ap.add_argument("--a", type=Path,
                    help="the other source tree (a checkout with gpumap/, kernels/, sim/, bench/)")
    ap.add_argument("--b", type=Path, default=Path.cwd(), help="the tree compared with it (default: here)")
    ap.add_argument("--images", type=int, default=0, help="pings per run (default 200 at >= 2 cm, else 60)")
    ap.add_argument("--batch", type=int, default=0,
                    help="hand pings over this many at a time (0: one by one)")
    ap.add_argument("--gpu-chunk", type=int, default=0,
                    help="voxels of a column per GPU thread in both trees (0: each tree's default)")
    ap.add_argument("--rounds", type=int, default=5, help="rounds (each runs every row once per tree)")
    ap.add_argument("--rule", default="", help="the mappers' rule in both trees (default: each tree's own)")
    ap.add_argument("--digest", choices=("values", "min_all"), default="values",
                    help="what must be the same in both trees: the map's values (default), or the min "
                         "over every view (trees whose default rules differ)")
    ap.add_argument("--max-load", type=float, default=0.5, help="refuse to start above this load average")
    ap.add_argument("--max-others", type=float, default=0.25,
                    help="cores other processes may take (at the start, and per run before it is marked)")
    ap.add_argument("--force", action="store_true", help="run on a loaded machine (results marked invalid)")
    a = ap.parse_args(argv)
    if SECTION.reported(a):
        return 0
    if a.a is None:
        ap.error("--a is required")
    start = idle_check(a.max_load, a.max_others)
    if not start["idle"] and not a.force:
        return refuse("bench.ab", start, (a.max_load, a.max_others), "--force")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        roots = {t: _package(getattr(a, t), Path(tmp) / t) for t in ("a", "b")}
        for voxel in a.voxel:
            for backend in a.backend:
                job = {"voxel": voxel, "backend": backend,
                       "images": a.images or (200 if voxel >= 0.02 else 60), "batch": a.batch,
                       "gpu_chunk": a.gpu_chunk, "digest": a.digest, "rule": a.rule}
                runs: dict[str, list] = {"a": [], "b": []}
                for r in range(a.rounds):
                    for t in ("a", "b") if r % 2 == 0 else ("b", "a"):
                        runs[t].append(_run(roots[t], getattr(a, t), job))
                row = {"voxel_size_m": voxel, "backend": backend, "images": job["images"], "batch": a.batch,
                       "gpu_chunk": a.gpu_chunk or "default", "digest": a.digest, "rule": a.rule or "default",
                       "device": runs["b"][0]["device"],
                       "same_map": len({x["digest"] for t in runs for x in runs[t]}) == 1,
                       "observed_voxels": runs["b"][0]["observed"]}
                for t in ("a", "b"):
                    ips = [x["images_per_s"] for x in runs[t]]
                    row[t] = {"images_per_s": spread(ips), "runs": ips,
                              "others_cores_max": max(x["others_cores"] or 0.0 for x in runs[t])}
                row["b_over_a"] = row["b"]["images_per_s"]["median"] / row["a"]["images_per_s"]["median"]
                row["quiet"] = all(row[t]["others_cores_max"] <= a.max_others for t in ("a", "b"))
                rows.append(row)
                keys = ("voxel_size_m", "backend", "b_over_a", "same_map", "quiet")
                medians = {t: round(row[t]["images_per_s"]["median"], 2) for t in ("a", "b")}
                print(json.dumps({k: row[k] for k in keys} | medians), flush=True)
                if not row["same_map"]:
                    print(f"bench.ab: the trees map differently at {voxel} m on {backend}", file=sys.stderr)
    doc = {**run_header("gpumap.bench.ab/1", argv), "idle_at_start": start, "valid": bool(start["idle"]),
           "trees": {t: str(getattr(a, t).resolve()) for t in ("a", "b")}, "warmup_pings": WARMUP,
           "rounds": a.rounds, "rows": rows}
    print(f"wrote {write_json(a.out / f'ab_{a.tag}.json', doc)}")
    return 0 if all(r["same_map"] for r in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
