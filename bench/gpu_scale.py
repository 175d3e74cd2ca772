"""GPU speed and scale in one run: one GPU (two source trees side by side), then 1 vs 2 GPU workers.

    python -m bench.gpu_scale --frames bench/results/tmp/oasis_polar.npz --old OLD_TREE \\
        --out bench/results/gpu_scale.json
    python -m bench.gpu_scale --frames ... --sections cpu --out bench/results/gpu_scale_cpu.json

Frames: the real tank sequence (123 uint8 polar frames with arm poses, the ``.npz`` that
``python -m bench.speed`` caches), on the OASIS box (2.4 x 2.4 x 1.3 m), default rule. Sections:

- ``single``: per source tree (``--old``: a checkout to compare with; this one), backend
  (warp-cuda, opencl-gpu), voxel size (1 cm, 5 mm) and variant of this tree's knobs, one fresh
  process each: batched throughput (``integrate_batch`` of ``--batch`` consecutive frames,
  wrapping round the sequence; ``--reps`` timed repetitions of ``--pings`` pings each, one
  synchronize per repetition), the host's share of a batch (the call's time without the wait),
  Warp's per-kernel GPU time, p50/p99 latency of ``integrate`` + ``synchronize`` per ping, and the
  map of the first ``--check`` frames, batched, compared with the NumPy oracle bit for bit. Two
  GPUs: warp-cuda runs on GPU 0 and opencl-gpu on GPU 1 at the same time (old and new of a
  backend on the same card).
- ``workers``: :func:`gpumap.pipeline.workers.run_replay_workers` with 1 and 2 workers (one GPU each) and
  :func:`gpumap.pipeline.replay.run_replay` in one process, on the frames repeated ``--repeat`` times
  (a recording of float32 frames that keep their bytes, so the client sends uint8), after a cold
  warm-up; and the client alone (reading and batching the frames, no mapping): if the client is
  the limit, this says so. The first run checks the merged map equals the one-process map.
- ``threads``: :func:`gpumap.pipeline.gpu_threads.run_replay_threads` on 1 and 2 GPUs of this process (a
  thread and a mapper per GPU, the maps merged in place) against one plain process, per
  ``--thread-runs`` entry (backend, voxel size, warm runs), on the frames repeated ``--repeat``
  times; the cold run checks every merged map equals the one-process map bit for bit. Runs before
  ``workers`` when both are asked for.
- ``cpu``: the workers' overhead on the CPU backend (2 workers against one process, the same
  cores), ``--reps`` runs, median; needs an idle machine to mean anything (the load is recorded
  before and after every run, and the section says whether the machine was idle).

Writes ``--out`` (JSON) as it goes: machine, GPUs, load, every row and its spread.
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

if __package__:  # python -m bench.gpu_scale (a worker runs this file as a script: no bench import)
    from .common import Section, bench_parser, load_average, machine_info, tree_cpu_s, write_json

#: The OASIS configuration's grid box (configs/base.yaml of the public code), metres.
BOX = ((-0.5, -1.2, -0.5), (1.9, 1.2, 0.8))
VOXELS = (0.01, 0.005)
#: Variants of this tree: (name, knobs on gpumap.backends, environment).
VARIANTS = {  # knobs of this tree (the first GPU run also timed a thread per chunk of a column,
    # since removed, and Warp without the register cap: bench/results/gpu_scale_variants.json)
    "uncapped": ({}, {"GPUMAP_GPU_MAX_REGISTERS": "0"}),
    "warp-batched-5mm": ({"BATCH_BOX_VOXELS_MAX": 10**12}, {}),
    "opencl-per-ping-5mm": ({"OPENCL_BATCH_BOX_VOXELS_MAX": 16_000_000}, {}),
    "as-shipped": ({}, {}),
}


def _frames(path: Path):
    import gpumap

    with np.load(path) as z:
        spec = gpumap.SonarSpec.from_dict(json.loads(str(z["spec"])))
        return z["imgs"], z["T"], spec


def _digest(arrays: dict) -> str:
    h = hashlib.sha256()
    for k in sorted(arrays):
        h.update(k.encode())
        h.update(np.ascontiguousarray(arrays[k]).tobytes())
    return h.hexdigest()[:16]


def _state(m) -> dict:
    out = {"values": m.raw_values()}
    if m.rule != "plain":
        out.update(m.evidence())
    return out


# ------------------------------------------------------------------------------ one process per row
def _worker(a) -> None:
    """One row of the single-GPU section, in this process (gpumap from PYTHONPATH); prints JSON."""
    import gpumap
    import gpumap.backends

    for kv in a.knob:
        name, value = kv.split("=", 1)
        setattr(gpumap.backends, name, value if not value.lstrip("-").isdigit() else int(value))
    imgs, poses, spec = _frames(a.frames)
    grid = gpumap.GridSpec(*BOX, a.voxel)
    n, B = len(imgs), a.batch
    # batches of B consecutive frames wrapping round the run, as contiguous views of one array (a
    # caller's batch: no copy of the frames inside the timed loop)
    ext = np.ascontiguousarray(imgs[np.arange(n + B) % n])
    ext_T = np.ascontiguousarray(poses[np.arange(n + B) % n])
    order = [slice(s0, s0 + B) for s0 in (np.arange(0, n * B, B) % n).tolist()]
    t0 = time.perf_counter()
    m = gpumap.MinMaxMapper(spec, grid, backend=a.backend)
    m.integrate_batch(ext[order[0]], ext_T[order[0]])  # compile / load, buffers
    m.synchronize()
    row = {"backend": m.backend, "device": m.device, "rule": m.rule, "voxel_m": a.voxel, "batch": B,
           "grid_shape": list(grid.shape), "setup_s": time.perf_counter() - t0,
           "gpumap_file": gpumap.__file__, "cuda_visible_devices": os.environ.get("CUDA_VISIBLE_DEVICES")}
    per_rep = max(1, a.pings // B)
    rates, host_ms, c = [], [], 0
    for _ in range(a.reps):
        t = time.perf_counter()
        for _ in range(per_rep):
            ks = order[c % len(order)]
            c += 1
            th = time.perf_counter()
            m.integrate_batch(ext[ks], ext_T[ks])
            host_ms.append(1e3 * (time.perf_counter() - th))
        m.synchronize()
        rates.append(per_rep * B / (time.perf_counter() - t))
    row["pings_per_s"] = _spread(rates)
    row["host_ms_per_batch"] = _spread(host_ms)  # the call without waiting for the GPU
    # the host's own work: a call made with the device idle (synchronized before it), so that it
    # never waits for a slot; wall and the calling thread's CPU time, microseconds a ping
    idle_us, idle_cpu_us = [], []
    for _ in range(a.host_calls):
        ks = order[c % len(order)]
        c += 1
        m.synchronize()
        th, tc = time.perf_counter(), time.thread_time()
        m.integrate_batch(ext[ks], ext_T[ks])
        idle_us.append(1e6 * (time.perf_counter() - th) / B)
        idle_cpu_us.append(1e6 * (time.thread_time() - tc) / B)
    m.synchronize()
    row["host_idle_us_per_ping"] = _spread(idle_us)
    row["host_idle_cpu_us_per_ping"] = _spread(idle_cpu_us)
    row["gpu_ms_per_batch_wall"] = 1e3 * B / float(np.median(rates))
    row["timed_pings"] = per_rep * B * a.reps
    row["digest_after_timing"] = _digest(_state(m))
    if a.profile and m.backend == "warp-cuda":
        import warp as wp

        wp.timing_begin(cuda_filter=wp.TIMING_ALL)
        for _ in range(per_rep):
            ks = order[c % len(order)]
            c += 1
            m.integrate_batch(ext[ks], ext_T[ks])
        m.synchronize()
        prof: dict = {}
        for r in wp.timing_end():
            name = r.name.split("forward kernel ")[-1].rsplit("_", 1)[0]
            prof[name] = prof.get(name, 0.0) + 1e3 * r.elapsed / (per_rep * B)
        row["gpu_us_per_ping"] = prof
    if a.latency:
        ms = []
        for k in range(a.latency):
            t = time.perf_counter()
            m.integrate(imgs[k % n], poses[k % n])
            m.synchronize()
            ms.append(1e3 * (time.perf_counter() - t))
        q = np.asarray(ms)
        row["latency_ms"] = {"p50": float(np.percentile(q, 50)), "p99": float(np.percentile(q, 99)),
                             "max": float(q.max()), "n": int(q.size)}
    if a.check:
        mc = gpumap.MinMaxMapper(spec, grid, backend=a.backend)
        mc.integrate_batch(imgs[: a.check], poses[: a.check])
        st = _state(mc)
        row["check_frames"] = a.check
        row["check_digest"] = _digest(st)
        if a.dump:
            np.savez(a.dump, **st)
    print("ROW " + json.dumps(row), flush=True)


def _cpu_rate_worker(a) -> None:
    """One run of the cpu_rate section in this process: every frame once, in order, into a fresh
    map (``integrate_batch`` of ``--batch`` frames; CPU backends apply them one by one) after the
    kernels are built; wall and process CPU time (every thread's: PoCL's workers too); prints JSON."""
    import gpumap

    imgs, poses, spec = _frames(a.frames)
    grid = gpumap.GridSpec(*BOX, a.voxel)
    warm = gpumap.MinMaxMapper(spec, grid, backend=a.backend)  # the program built, its caches warm
    warm.integrate_batch(imgs[:2], poses[:2])
    warm.synchronize()
    del warm
    m = gpumap.MinMaxMapper(spec, grid, backend=a.backend)
    load = load_average_now()
    t, c = time.perf_counter(), time.process_time()
    for s0 in range(0, len(imgs), a.batch):
        m.integrate_batch(imgs[s0 : s0 + a.batch], poses[s0 : s0 + a.batch])
    m.synchronize()
    wall, cpu = time.perf_counter() - t, time.process_time() - c
    row = {"backend": m.backend, "device": m.device, "rule": m.rule, "voxel_m": a.voxel, "frames": len(imgs),
           "pings_per_s": len(imgs) / wall, "cpu_ms_per_ping": 1e3 * cpu / len(imgs), "load_before": load,
           "load_after": load_average_now(), "digest": _digest(_state(m)), "gpumap_file": gpumap.__file__}
    print("ROW " + json.dumps(row), flush=True)


def load_average_now() -> list[float]:
    return [round(x, 2) for x in os.getloadavg()]


def cpu_rate(a, res: dict, save) -> None:
    """The cpu_rate section: ``--cpu-backend`` at ``--cpu-voxel`` on this machine's CPU, every frame once
    per run, ``--reps`` runs of each tree in turn (old, new, old, ...), each in a fresh process."""
    tmp = Path(tempfile.mkdtemp(prefix="gpu_scale_cpu_"))
    trees = {"new": _package(Path(__file__).resolve().parents[1], tmp / "new")}
    if a.old:
        trees = {"old": _package(Path(a.old).resolve(), tmp / "old"), **trees}
    args = ["--cpu-rate-worker", "--frames", str(Path(a.frames).resolve()), "--backend", a.cpu_backend,
            "--voxel", str(a.cpu_voxel), "--batch", "8"]
    sec = {"backend": a.cpu_backend, "voxel_m": a.cpu_voxel, "reps": a.reps, "rows": []}
    res["cpu_rate"] = sec
    for rep in range(a.reps):
        for tree, path in trees.items():
            row = _run_row(path, args, {}, a.row_timeout * 4)
            row.update(tree=tree, rep=rep)
            sec["rows"].append(row)
            save()
            print(f"cpu_rate {tree} rep {rep}: {row.get('pings_per_s')} pings/s, "
                  f"{row.get('cpu_ms_per_ping')} ms CPU a ping, load {row.get('load_before')} "
                  f"{row.get('error', '')[-300:]}", flush=True)
    summ = {}
    for tree in trees:
        rows = [r for r in sec["rows"] if r["tree"] == tree and "error" not in r]
        if rows:
            summ[tree] = {"pings_per_s": _spread([r["pings_per_s"] for r in rows]),
                          "cpu_ms_per_ping": _spread([r["cpu_ms_per_ping"] for r in rows]),
                          "digests": sorted({r["digest"] for r in rows})}
    if "old" in summ and "new" in summ:
        o, n = summ["old"], summ["new"]
        summ["cpu_old_over_new"] = o["cpu_ms_per_ping"]["median"] / n["cpu_ms_per_ping"]["median"]
        summ["same_map"] = o["digests"] == n["digests"] and len(n["digests"]) == 1
    loads = [r["load_before"][0] for r in sec["rows"] if "load_before" in r]
    summ["load_before_max"] = max(loads) if loads else None
    sec["summary"] = summ
    save()


def _oracle(a) -> None:
    """The NumPy oracle's map of the first ``--check`` frames at ``--voxel`` into ``--dump``."""
    import gpumap

    imgs, poses, spec = _frames(a.frames)
    m = gpumap.MinMaxMapper(spec, gpumap.GridSpec(*BOX, a.voxel), backend="numpy")
    m.integrate_batch(imgs[: a.check], poses[: a.check])
    st = _state(m)
    np.savez(a.dump, **st)
    row = {"voxel_m": a.voxel, "check_frames": a.check, "digest": _digest(st)}
    print("ROW " + json.dumps(row), flush=True)


def _spread(xs) -> dict:
    x = np.asarray(xs, float)
    return {"median": float(np.median(x)), "min": float(x.min()), "max": float(x.max()), "n": int(x.size)}


def _package(tree: Path, into: Path) -> Path:
    """A folder from which ``import gpumap`` finds ``tree``'s package in its installed layout."""
    pkg = into / "gpumap"
    pkg.mkdir(parents=True, exist_ok=True)
    for f in (tree / "gpumap").iterdir():
        if f.name not in ("kernels", "sim", "bench") and not (pkg / f.name).exists():
            (pkg / f.name).symlink_to(f.resolve())
    for sub in ("kernels", "sim", "bench"):
        if not (pkg / sub).exists():
            (pkg / sub).symlink_to((tree / sub).resolve())
    return into


def _pythonpath(first: Path) -> str:
    """``first`` ahead of this process's PYTHONPATH (where Warp, pyopencl and Dask may live)."""
    return os.pathsep.join(x for x in (str(first), os.environ.get("PYTHONPATH")) if x)


def _run_row(path_dir: Path, args: list[str], env_extra: dict, timeout: float) -> dict:
    env = {**os.environ, "PYTHONPATH": _pythonpath(path_dir), **env_extra}
    cmd = [sys.executable, "-P", str(Path(__file__).resolve()), *args]
    t = time.perf_counter()
    p = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=timeout)
    rows = [json.loads(x[4:]) for x in p.stdout.splitlines() if x.startswith("ROW ")]
    if p.returncode != 0 or not rows:
        return {"error": (p.stderr or p.stdout)[-1500:], "wall_s": time.perf_counter() - t}
    rows[0]["wall_s"] = time.perf_counter() - t
    return rows[0]


def single(a, res: dict, save) -> None:
    """The single-GPU section: rows of (tree, backend, voxel, variant), two lanes on two GPUs."""
    tmp = Path(tempfile.mkdtemp(prefix="gpu_scale_"))
    trees = {"new": _package(Path(__file__).resolve().parents[1], tmp / "new")}
    if a.old:
        trees["old"] = _package(Path(a.old).resolve(), tmp / "old")
    base = ["--worker", "--frames", str(Path(a.frames).resolve()), "--batch", str(a.batch), "--reps",
            str(a.reps), "--host-calls", str(a.host_calls)]
    # the oracle maps, on the CPU while the GPUs work
    oracles = {}
    for v in a.voxels:
        k = a.check if v >= 0.01 else max(2, a.check // 4)
        dump = tmp / f"oracle_{v}.npz"
        cmd = [sys.executable, "-P", str(Path(__file__).resolve()), "--oracle", "--frames",
               str(Path(a.frames).resolve()), "--voxel", str(v), "--check", str(k), "--dump", str(dump)]
        oracles[v] = (subprocess.Popen(cmd, env={**os.environ, "PYTHONPATH": _pythonpath(trees["new"])},
                                       stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True), dump, k)
    n_gpu = max(1, len(res.get("gpus", [])))
    lanes: dict[str, list] = {b: [] for b in a.backends}
    for backend in lanes:
        for v in a.voxels:
            jobs = [("old", "as-shipped")] if "old" in trees else []
            jobs += [("new", x) for x in (a.variants or VARIANTS)]
            for tree, variant in jobs:
                knobs, env = VARIANTS[variant]
                fine = v < 0.01  # 5 mm: a quarter of the pings and checked frames, a third of the latency
                pings = a.pings // 4 if fine else a.pings
                k = max(2, a.check // 4) if fine else a.check
                tag = f"{tree}_{variant}_{backend}_{v}"
                args = [*base, "--backend", backend, "--voxel", str(v), "--pings", str(pings),
                        "--check", str(k), "--dump", str(tmp / f"{tag}.npz"),
                        "--latency", str(a.latency // 3 if fine else a.latency), "--profile"]
                for kk, vv in knobs.items():
                    args += ["--knob", f"{kk}={vv}"]
                lanes[backend].append((tag, tree, variant, args, env, tmp / f"{tag}.npz", v))
    rows = res.setdefault("single", [])
    lock = threading.Lock()

    def lane(backend: str, gpu: int) -> None:
        for tag, tree, variant, args, env, dump, v in lanes[backend]:
            env = {**env, "CUDA_VISIBLE_DEVICES": str(gpu)}
            row = _run_row(trees[tree], args, env, a.row_timeout)
            row.update(tree=tree, variant=variant, knobs=VARIANTS[variant][0], env=VARIANTS[variant][1],
                       gpu_index=gpu, dump=str(dump), voxel_m=v, backend_asked=backend)
            with lock:
                rows.append(row)
                save()
            print(f"{tag}: {row.get('pings_per_s', {}).get('median')} pings/s, "
                  f"p99 {row.get('latency_ms', {}).get('p99')} ms {row.get('error', '')[-300:]}", flush=True)

    if n_gpu >= 2:
        ts = [threading.Thread(target=lane, args=(b, g)) for g, b in enumerate(lanes)]
        for t in ts:
            t.start()
        for t in ts:
            t.join()
    else:
        for b in lanes:
            lane(b, 0)
    # bit for bit with the oracle
    out = res.setdefault("oracle", {})
    for v, (p, dump, k) in oracles.items():
        try:
            so, se = p.communicate(timeout=a.row_timeout * 2)
        except subprocess.TimeoutExpired:
            p.kill()
            out[str(v)] = {"error": "oracle timed out"}
            continue
        if p.returncode != 0:
            out[str(v)] = {"error": se[-1500:]}
            continue
        out[str(v)] = {**json.loads(so.splitlines()[-1][4:]), "frames": k}
        ref = None
        for row in rows:
            if row.get("voxel_m") != v or "error" in row or not Path(row["dump"]).is_file():
                continue
            row["oracle_equal"] = row.get("check_digest") == out[str(v)]["digest"]
            if row["oracle_equal"]:  # the same digest of every array: no need to count
                row["oracle_diff_bytes"] = 0
                continue
            if ref is None:
                with np.load(dump) as z:
                    ref = {x: z[x] for x in z.files}
            with np.load(row["dump"]) as z:
                got = {x: z[x] for x in z.files}
            diff = sum(int((np.asarray(got[x]).view(np.uint8) != np.asarray(ref[x]).view(np.uint8)).sum())
                       for x in ref) if got.keys() == ref.keys() else -1
            row["oracle_diff_bytes"] = diff
    save()


# ------------------------------------------------------------------------------ workers
def _recording(imgs, poses, spec, repeat: int):
    """The frames ``repeat`` times as a recording of float32 frames that keep their bytes."""
    from gpumap.backends import U8_SCALE
    from gpumap.io import Recording, SonarFrame
    from gpumap.pipeline.workers import FRAME_BYTES

    flt = [np.multiply(b, U8_SCALE, dtype=np.float32) for b in imgs]
    # each repeat 0.1 mm further along x: the same work, but pings of their own (maps that share a
    # ping would count it twice when merged, and gpumap.core.merge refuses them)
    Ts = [T.copy() for _ in range(repeat) for T in poses]
    for r in range(repeat):
        for T in Ts[r * len(imgs) : (r + 1) * len(imgs)]:
            T[0, 3] += 1e-4 * r

    def frames():
        for i, T in enumerate(Ts):
            k = i % len(imgs)
            yield SonarFrame(flt[k], spec, None, T, {FRAME_BYTES: imgs[k]})

    return Recording("tank-arrays", "arrays", frames, True, count=lambda: len(Ts), poses=lambda: list(Ts))


def _client_only(rec) -> float:
    """Frames per second the client reads and batches (as run_replay_workers does), mapping none."""
    from gpumap.pipeline.workers import BATCH, frame_pixels

    t = time.perf_counter()
    n = 0
    buf = None
    for fr in rec:
        img = frame_pixels(fr)
        if buf is None:
            buf = np.empty((BATCH, *img.shape), img.dtype)
        buf[n % BATCH] = img
        n += 1
    return n / (time.perf_counter() - t)


def workers_section(a, res: dict, save, name: str, backend: str, voxel: float, n_workers: list[int],
                    reps: int) -> None:
    import logging

    from distributed import Client, LocalCluster

    import gpumap
    from gpumap.pipeline.replay import run_replay
    from gpumap.pipeline.workers import run_replay_workers

    load_at_start = load_average()  # before this section loads anything or starts a worker
    # the worker processes import this checkout's gpumap (as this process does)
    os.environ["PYTHONPATH"] = _pythonpath(Path(gpumap.__file__).resolve().parents[1])
    imgs, poses, spec = _frames(a.frames)
    rec = _recording(imgs, poses, spec, a.repeat)
    grid = gpumap.GridSpec(*BOX, voxel)
    kw = dict(backend=backend, grid=grid, progress=False)
    sec = {"backend": backend, "voxel_m": voxel, "frames": a.repeat * len(imgs), "repeat": a.repeat,
           "load_at_start": load_at_start,
           "workers": n_workers, "rows": [], "client_only_frames_per_s": _spread([_client_only(rec)
                                                                                  for _ in range(3)])}
    res[name] = sec
    tc = time.perf_counter()
    cluster = LocalCluster(n_workers=max(n_workers), threads_per_worker=1, processes=True,
                           dashboard_address=":0", silence_logs=logging.CRITICAL)
    client = Client(cluster)
    sec["seconds_cluster_start"] = time.perf_counter() - tc
    try:
        for rep in range(reps + 1):  # rep 0: the workers start their backends (cold)
            row: dict = {"rep": rep, "cold": rep == 0, "load_before": load_average()}
            c0, t0_rep = tree_cpu_s(), time.perf_counter()
            t = time.perf_counter()
            one, s1 = run_replay(rec, **kw)
            row["one_s"] = time.perf_counter() - t
            for nw in n_workers:
                t = time.perf_counter()
                got, sw = run_replay_workers(rec, workers=nw, client=client, **kw)
                row[f"w{nw}_s"] = time.perf_counter() - t
                row[f"w{nw}_map_s"] = sw["seconds_map"]
                row[f"w{nw}_gather_merge_s"] = sw["seconds_gather"] + sw["seconds_merge"]
                row[f"w{nw}_per_worker"] = [{k: w.get(k) for k in ("frames", "seconds_integrate", "device",
                                                                   "cuda_visible_devices", "gpu")}
                                            for w in sw["per_worker"]]
                if rep <= 1:
                    a_, b_ = _state(one), _state(got)
                    row[f"w{nw}_equal_one_process"] = bool(
                        a_.keys() == b_.keys() and all(np.array_equal(a_[k], b_[k]) for k in a_))
                del got
            row["load_after"] = load_average()
            c1 = tree_cpu_s()
            if c0 and c1:  # the cores other processes (not this run's workers) kept busy meanwhile
                wall = time.perf_counter() - t0_rep
                row["others_cores"] = max(0.0, (c1[0] - c0[0]) - (c1[1] - c0[1])) / wall
            del one
            sec["rows"].append(row)
            save()
            short = {k: v for k, v in row.items() if not k.endswith("per_worker")}
            print(name, json.dumps(short), flush=True)
    finally:
        client.close()
        cluster.close()
    warm = [r for r in sec["rows"] if not r["cold"]] or sec["rows"]
    summ = {"one_s": _spread([r["one_s"] for r in warm])}
    for nw in n_workers:
        summ[f"w{nw}_s"] = _spread([r[f"w{nw}_s"] for r in warm])
        summ[f"w{nw}_frames_per_s"] = sec["frames"] / summ[f"w{nw}_s"]["median"]
        summ[f"w{nw}_over_one"] = summ[f"w{nw}_s"]["median"] / summ["one_s"]["median"] - 1.0
    if 1 in n_workers and 2 in n_workers:
        summ["speedup_2_over_1"] = summ["w1_s"]["median"] / summ["w2_s"]["median"]
    # idle: before the section no more than a quarter of the cores busy (a load average: later ones
    # count this run's own work), and during every warm run other processes (not this run's own
    # workers) kept at most a tenth of a core busy
    first = sec["load_at_start"]
    others = [r.get("others_cores") for r in warm]
    summ["others_cores_max"] = max(others) if others and None not in others else None
    summ["idle"] = bool(first) and first[0] < 0.25 * (os.cpu_count() or 1) and (
        summ["others_cores_max"] is not None and summ["others_cores_max"] <= 0.1)
    sec["summary"] = summ
    save()


def threads_section(a, res: dict, save, name: str, backend: str, voxel: float, n_gpus: list[int],
                    reps: int) -> None:
    """In-process GPUs (:func:`gpumap.pipeline.gpu_threads.run_replay_threads`, a thread and a mapper per GPU,
    the maps merged in place) against one process (:func:`gpumap.pipeline.replay.run_replay`), on the frames
    repeated ``--repeat`` times: ``reps`` warm runs after a cold one (which compiles and checks that
    every merged map equals the one-process map bit for bit)."""
    import gpumap
    from gpumap.pipeline.gpu_threads import run_replay_threads
    from gpumap.pipeline.replay import run_replay

    imgs, poses, spec = _frames(a.frames)
    rec = _recording(imgs, poses, spec, a.repeat)
    grid = gpumap.GridSpec(*BOX, voxel)
    kw = dict(backend=backend, grid=grid, progress=False)
    sec = {"backend": backend, "voxel_m": voxel, "frames": a.repeat * len(imgs), "repeat": a.repeat,
           "gpus": n_gpus, "grid_shape": list(grid.shape), "rows": [],
           "client_only_frames_per_s": _spread([_client_only(rec) for _ in range(2)])}
    res[name] = sec
    for rep in range(reps + 1):  # rep 0: kernels compiled / loaded on every device (cold)
        row: dict = {"rep": rep, "cold": rep == 0, "load_before": load_average()}
        t = time.perf_counter()
        one, s1 = run_replay(rec, **kw)
        one.synchronize()
        row["one_s"] = time.perf_counter() - t
        row["one_map_s"] = s1["seconds_total"]
        ref = _state(one) if rep == 0 else None
        del one
        for n in n_gpus:
            t = time.perf_counter()
            got, st = run_replay_threads(rec, workers=n, **kw)
            got.synchronize()
            row[f"t{n}_s"] = time.perf_counter() - t
            for k in ("seconds_setup", "seconds_map", "seconds_merge"):
                row[f"t{n}_{k[8:]}_s"] = st[k]
            row[f"t{n}_per_worker"] = st["per_worker"]
            if ref is not None:
                b_ = _state(got)
                row[f"t{n}_equal_one_process"] = bool(
                    ref.keys() == b_.keys() and all(np.array_equal(ref[k], b_[k]) for k in ref))
                del b_
            del got
        row["load_after"] = load_average()
        sec["rows"].append(row)
        save()
        short = {k: v for k, v in row.items() if not k.endswith("per_worker")}
        print(name, json.dumps(short), flush=True)
    warm = [r for r in sec["rows"] if not r["cold"]] or sec["rows"]
    summ = {"one_s": _spread([r["one_s"] for r in warm]),
            "one_map_s": _spread([r["one_map_s"] for r in warm])}
    for n in n_gpus:
        for k in ("s", "map_s", "merge_s", "setup_s"):
            summ[f"t{n}_{k}"] = _spread([r[f"t{n}_{k}"] for r in warm])
        summ[f"t{n}_frames_per_s"] = sec["frames"] / summ[f"t{n}_s"]["median"]
        summ[f"t{n}_speedup_over_one_process"] = summ["one_s"]["median"] / summ[f"t{n}_s"]["median"]
    if 1 in n_gpus and 2 in n_gpus:
        summ["speedup_2_over_1"] = summ["t1_s"]["median"] / summ["t2_s"]["median"]
        summ["map_speedup_2_over_1"] = summ["t1_map_s"]["median"] / summ["t2_map_s"]["median"]
    checks = [r[k] for r in sec["rows"] for k in r if k.endswith("_equal_one_process")]
    summ["all_equal_one_process"] = bool(checks) and all(checks)
    sec["summary"] = summ
    save()


def _gpu_names() -> list[str]:
    try:
        p = subprocess.run(["nvidia-smi", "--query-gpu=name,pci.bus_id", "--format=csv,noheader"],
                           capture_output=True, text=True, timeout=30)
        return [x.strip() for x in p.stdout.splitlines() if x.strip()]
    except (OSError, subprocess.SubprocessError):
        return []


def main(argv: list[str] | None = None) -> int:
    import argparse

    p = bench_parser("gpu_scale", __doc__) if __package__ else argparse.ArgumentParser()
    p.add_argument("--frames", type=Path, default=Path("bench/results/tmp/oasis_polar.npz"))
    p.add_argument("--old", default=None, help="a checkout to time beside this one (single, cpu_rate)")
    p.add_argument("--old-label", default=None, help="what --old is (a commit, say), kept in the results")
    p.add_argument("--sections", nargs="+", default=["single", "workers"],
                   choices=["single", "workers", "threads", "cpu", "cpu_rate"])
    p.add_argument("--thread-runs", nargs="+", default=["warp-cuda:0.005:3", "warp-cuda:0.01:3"],
                   metavar="BACKEND:VOXEL:REPS", help="threads section: its runs, in order")
    p.add_argument("--out", type=Path, default=Path("bench/results/gpu_scale.json"))
    p.add_argument("--batch", type=int, default=64)
    p.add_argument("--reps", type=int, default=5)
    p.add_argument("--pings", type=int, default=3200,
                   help="pings per timed repetition at 1 cm (5 mm: a quarter)")
    p.add_argument("--latency", type=int, default=300,
                   help="synchronised pings for the latency (5 mm: a third)")
    p.add_argument("--check", type=int, default=16, help="frames compared with the oracle at 1 cm (5 mm: 4)")
    p.add_argument("--repeat", type=int, default=120, help="workers: the frames repeated this many times")
    p.add_argument("--worker-voxel", type=float, default=0.005)
    p.add_argument("--backends", nargs="+", default=["warp-cuda", "opencl-gpu"],
                   help="single section: one lane each (on GPU 0, 1, ... where there are several)")
    p.add_argument("--voxels", type=float, nargs="+", default=list(VOXELS))
    p.add_argument("--variants", nargs="+", default=None, choices=list(VARIANTS),
                   help="this tree's variants to time (default: every one)")
    p.add_argument("--worker-reps", type=int, default=3, help="warm runs of the workers section")
    p.add_argument("--row-timeout", type=float, default=240.0)
    p.add_argument("--cpu-backend", default="opencl-cpu", help="cpu_rate section: the backend")
    p.add_argument("--cpu-voxel", type=float, default=0.01, help="cpu_rate section: the voxel, m")
    p.add_argument("--host-calls", type=int, default=20,
                   help="single section: batches timed with the device idle (the host's own work)")
    # one row in this process (internal)
    p.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--oracle", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--cpu-rate-worker", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--backend", default="warp-cuda", help=argparse.SUPPRESS)
    p.add_argument("--voxel", type=float, default=0.01, help=argparse.SUPPRESS)
    p.add_argument("--knob", action="append", default=[], help=argparse.SUPPRESS)
    p.add_argument("--dump", default=None, help=argparse.SUPPRESS)
    p.add_argument("--profile", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--report", type=Path, default=None, metavar="BENCHMARKS_MD",
                   help="only write this benchmark's section of that file from --out")
    a = p.parse_args(argv)
    if a.report is not None:
        SECTION.write(a.report, Path(a.out).parent)
        return 0
    if a.worker:
        _worker(a)
        return 0
    if a.oracle:
        _oracle(a)
        return 0
    if a.cpu_rate_worker:
        _cpu_rate_worker(a)
        return 0
    res = {"schema": "gpumap-bench-gpu-scale/1", "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
           "command": "python -m bench.gpu_scale " + " ".join(argv if argv is not None else sys.argv[1:]),
           "machine": machine_info(), "gpus": _gpu_names(), "load_start": load_average(), "old": a.old_label,
           "frames": {"source": "shared/data/oasis_tank (real Oculus M3000d, every 10th frame, arm poses)",
                      "grid_box_m": BOX}}
    t0 = time.time()

    def save() -> None:
        res["duration_s"] = time.time() - t0
        res["load_now"] = load_average()
        write_json(a.out, res, digits=5)

    save()
    if "cpu_rate" in a.sections:
        cpu_rate(a, res, save)
    if "single" in a.sections:
        single(a, res, save)
    if "threads" in a.sections:
        n = [1, 2] if len(res["gpus"]) >= 2 else [1]
        for run in a.thread_runs:
            backend, voxel, reps = run.split(":")
            name = f"threads_{backend}_{float(voxel) * 1000:g}mm"
            try:
                threads_section(a, res, save, name, backend, float(voxel), n, int(reps))
            except Exception:  # recorded: the rest of the run still counts
                import traceback

                res[f"{name}_error"] = traceback.format_exc()[-3000:]
                save()
    if "workers" in a.sections:
        n = [1, 2] if len(res["gpus"]) >= 2 else [1]
        try:
            workers_section(a, res, save, "workers", "warp-cuda", a.worker_voxel, n, a.worker_reps)
        except Exception as e:  # recorded: the rest of the run still counts
            res["workers_error"] = repr(e)
            save()
    if "cpu" in a.sections:
        import gpumap.backends

        try:
            workers_section(a, res, save, "cpu_overhead", "warp-cpu", 0.02, [2], a.reps)
            res["cpu_overhead"]["note"] = (
                "workers' overhead on this machine's CPU (warp-cpu, 2 threads per mapper in both): "
                f"valid only where summary.idle is true (CPU_THREADS={gpumap.backends.CPU_THREADS})")
        except Exception as e:
            res["cpu_overhead_error"] = repr(e)
        save()
    print(f"wrote {a.out}")
    return 0


def warm_medians(w: dict, what: str) -> dict[int, float]:
    """Workers section ``w``: {workers: median of ``w{workers}_{what}`` over its warm runs}."""
    warm = [r for r in w["rows"] if not r.get("cold")]
    return {n: float(np.median([r[f"w{n}_{what}"] for r in warm])) for n in w["workers"]}


def _med(x: dict) -> str:
    return f"{x['median']:,.0f} ({x['min']:,.0f}-{x['max']:,.0f})"


def markdown(res: dict, folder: Path) -> str:
    """The BENCHMARKS.md block of ``gpu_scale.json``: one GPU, old tree against new, then 1 and 2
    GPU workers; and ``gpu_scale_threads.json`` beside it (the in-process path), if there."""
    folder = Path(folder)
    gpus = ", ".join(res["gpus"])
    out = ["## GPU speed and GPU workers (issue #33)", "",
           f"`{res['command']}` on {len(res['gpus'])} GPUs ({gpus}), load {res['load_start'][0]:.2f} at the "
           "start; the real tank's frames, default (evidence) rule, batches of 64. Old and new trees of a "
           "backend on the same card, in turn; pings/s median (min-max) of 5 repetitions; p99: "
           "`integrate` + `synchronize` of one ping; oracle: the batched map of the first frames against "
           "the NumPy reference, bit for bit.", "",
           "| backend | voxel | old pings/s | new pings/s | new / old | p99 ms (new) | equals the oracle |",
           "|---|---|---|---|---|---|---|"]
    rows = {(r["tree"], r["backend"], r["voxel_m"]): r for r in res["single"] if r["variant"] == "as-shipped"}
    for (tree, backend, voxel), new in rows.items():
        old = rows.get(("old", backend, voxel))
        if tree != "new" or old is None:
            continue
        ratio = new["pings_per_s"]["median"] / old["pings_per_s"]["median"]
        equal = "yes" if new["oracle_equal"] and old["oracle_equal"] else "NO"
        out.append(f"| {backend} | {voxel * 1000:g} mm | {_med(old['pings_per_s'])} | "
                   f"{_med(new['pings_per_s'])} | {ratio:.2f}x | {new['latency_ms']['p99']:.2f} | {equal} |")
    out += h200_lines(folder) + cpu_rate_lines(folder)
    w = res.get("workers")
    if w:
        s, rows_w = w["summary"], w["rows"]
        warm = [r for r in rows_w if not r.get("cold")]
        maps, merge = warm_medians(w, "map_s"), warm_medians(w, "gather_merge_s")
        checks = [r[k] for r in rows_w for k in ("w1_equal_one_process", "w2_equal_one_process") if k in r]
        same = bool(checks) and all(checks)
        out += ["", f"Workers ({w['backend']}, {w['voxel_m'] * 1000:g} mm, the tank's frames {w['repeat']} "
                f"times: {w['frames']:,} pings; {len(warm)} warm runs, medians): one process "
                f"{s['one_s']['median']:.2f} s; 1 worker {s['w1_s']['median']:.2f} s (mapping "
                f"{maps[1]:.2f} s, gathering and merging its map {merge[1]:.2f} s); 2 workers on 2 GPUs "
                f"{s['w2_s']['median']:.2f} s (mapping {maps[2]:.2f} s, {maps[1] / maps[2]:.2f}x the mapping "
                f"of one; gathering and merging {merge[2]:.2f} s). End to end 2 workers run "
                f"{s['speedup_2_over_1']:.2f}x one worker: the maps' way back and their merge dominate. "
                f"Merged maps {'equal' if same else 'DIFFER from'} the one-process map. The client alone "
                f"reads and batches {w['client_only_frames_per_s']['median']:,.0f} frames/s."]
    cpu_file = folder / "gpu_scale_cpu.json"
    if cpu_file.exists():
        c = json.loads(cpu_file.read_text())
        cs = c["cpu_overhead"]["summary"]
        first = c["cpu_overhead"]["load_at_start"][0]
        out += ["", f"Workers on the CPU (`{c['command']}`; {c['machine']['cpu_model']}, "
                f"{c['machine']['cpu_count']} cores, warp-cpu at 2 cm, the tank's frames "
                f"{c['cpu_overhead']['repeat']} times): one process {_sec(cs['one_s'])} s, 2 Dask workers on "
                f"the same cores {_sec(cs['w2_s'])} s, median (min-max) of {cs['one_s']['n']} warm runs: "
                f"{100 * cs['w2_over_one']:+.0f} % (negative: the workers are faster; the client reads "
                f"while they map). Load {first:.2f} before the runs; other processes kept at most "
                f"{cs['others_cores_max']:.3f} cores busy during a run; "
                + ("an idle machine." if cs["idle"] else "**not an idle machine: not a valid figure**.")]
    th = folder / "gpu_scale_threads.json"
    if th.exists():
        t = json.loads(th.read_text())
        out += ["", "In one process, a thread and a mapper per GPU (`gpumap replay --workers N` on a machine "
                f"with N GPUs; {', '.join(t['gpus'])}; `{t['command']}`): seconds, median (min-max) of the "
                "warm runs; the merged maps equal the one-process map where the last column says so. "
                + t.get("note", ""), "",
                "| backend | voxel | one process | 1 GPU | 2 GPUs: total | mapping | merge | 2 over 1 "
                "| equal |", "|---|---|---|---|---|---|---|---|---|"]
        for key in sorted(k for k in t if k.startswith("threads_")):
            r, sm = t[key], t[key]["summary"]
            equal = "yes" if sm["all_equal_one_process"] else "NO"
            out.append(f"| {r['backend']} | {r['voxel_m'] * 1000:g} mm | {_sec(sm['one_s'])} | "
                       f"{_sec(sm['t1_s'])} | {_sec(sm['t2_s'])} | {_sec(sm['t2_map_s'])} | "
                       f"{_sec(sm['t2_merge_s'])} | {sm['speedup_2_over_1']:.2f}x | {equal} |")
    return "\n".join(out)


def h200_lines(folder: Path) -> list[str]:
    """Lines of the block from ``gpu_scale_h200.json`` (issue 38: the host path on one H200), if there."""
    f = Path(folder) / "gpu_scale_h200.json"
    if not f.exists():
        return []
    res = json.loads(f.read_text())
    out = ["", f"One H200 after the host path of issue 38 (`gpu_scale_h200.json`; `{res['command']}`; "
           f"{', '.join(res['gpus'])}; old: {res.get('old') or 'the --old tree'}): pings/s median "
           "(min-max) of 5 repetitions of batches of 64; host: microseconds a ping of an `integrate_batch` "
           "call made with the device idle (wall, and the calling thread's CPU time), median of the calls; "
           "oracle: the batched map of the first frames against the NumPy reference, bit for bit.",
           "", "| backend | voxel | old pings/s | new pings/s | new / old | host us a ping, old -> new (CPU) "
           "| p99 ms (new) | equals the oracle |", "|---|---|---|---|---|---|---|---|"]
    rows = {(r["tree"], r["backend_asked"], r["voxel_m"]): r for r in res["single"] if "error" not in r}
    for (tree, backend, voxel), new in rows.items():
        old = rows.get(("old", backend, voxel))
        if tree != "new" or old is None:
            continue
        ratio = new["pings_per_s"]["median"] / old["pings_per_s"]["median"]
        equal = "yes" if new.get("oracle_equal") and old.get("oracle_equal") else "NO"
        ho, hn = old["host_idle_us_per_ping"]["median"], new["host_idle_us_per_ping"]["median"]
        hc = new["host_idle_cpu_us_per_ping"]["median"]
        out.append(f"| {backend} | {voxel * 1000:g} mm | {_med(old['pings_per_s'])} | "
                   f"{_med(new['pings_per_s'])} | {ratio:.2f}x | {ho:.1f} -> {hn:.1f} ({hc:.1f}) | "
                   f"{new['latency_ms']['p99']:.2f} | {equal} |")
    errors = [f"{r['tree']} {r.get('backend_asked')} {r.get('voxel_m')}" for r in res["single"]
              if "error" in r]
    if errors:
        out += ["", f"Rows that failed: {', '.join(errors)} (their errors are in the file)."]
    return out


def cpu_rate_lines(folder: Path) -> list[str]:
    """Lines of the block from ``gpu_scale_cpu_rate.json`` (the CPU path at 1 cm), if there."""
    f = Path(folder) / "gpu_scale_cpu_rate.json"
    if not f.exists():
        return []
    res = json.loads(f.read_text())
    c = res["cpu_rate"]
    s, m = c["summary"], res["machine"]
    o, n = s["old"], s["new"]
    return ["", f"The CPU path (`gpu_scale_cpu_rate.json`; `{res['command']}`; {m['cpu_model']}, "
            f"{m['cpu_count']} cores; old: {res.get('old') or 'the --old tree'}): {c['backend']} at "
            f"{c['voxel_m'] * 100:g} cm, default rule, every real tank frame once per run (a fresh process "
            f"each), {c['reps']} runs of each tree in turn. CPU time a ping (every thread's) old "
            f"{_sec(o['cpu_ms_per_ping'])} ms, new {_sec(n['cpu_ms_per_ping'])} ms: "
            f"{s['cpu_old_over_new']:.2f}x less; pings/s old {_sec(o['pings_per_s'])}, new "
            f"{_sec(n['pings_per_s'])}, on a machine other sessions loaded (load average up to "
            f"{s['load_before_max']:.1f} on {m['cpu_count']} cores before a run: wall rates are a share of "
            f"the cores, not the idle rate). The maps of both trees are "
            + ("the same bytes." if s["same_map"] else "**not the same bytes**.")]


def _sec(x: dict) -> str:
    return f"{x['median']:.2f} ({x['min']:.2f}-{x['max']:.2f})" if x["n"] > 1 else f"{x['median']:.2f}"


if __package__:
    SECTION = Section("gpu-scale", "## GPU speed and GPU workers (issue #33)", "gpu_scale.json", markdown)

if __name__ == "__main__":
    raise SystemExit(main())
