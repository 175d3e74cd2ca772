"""Map a recording on several GPUs of this machine, in this process, and merge the maps exactly.

``gpumap replay RECORDING --workers N`` on a machine with N GPUs (or more) and a GPU backend
takes this path (:func:`run_replay_threads`); a cluster of machines (``--scheduler``) takes the
Dask one (:mod:`gpumap.pipeline.workers`).

How: one thread per device, each with its own :class:`~gpumap.MinMaxMapper` on its own device
(``device_index``: ``cuda:i`` on Warp, the i-th OpenCL GPU), fed batches of :data:`BATCH` pings
through a bounded queue by the client (this thread), which reads the recording once. The pings
are split as :mod:`gpumap.pipeline.workers` splits them (``"space"``: each device maps one stretch of the
survey; ``"pings"``: batches to each device in turn). At the end the first device's map takes the
others' (:func:`merge_dense`, a bounded box: blocks only the other observed are copied device to
device where the backend can (Warp), blocks both observed are read and combined on the host in
threads (mins and saturating counts, :func:`gpumap.core.rules.combine_into`); on demand: each thread
reads its map's state and :meth:`gpumap.MinMaxMapper.merge` takes it): the map of one process,
bit for bit, on the first device. Nothing is pickled and no map leaves the process.

What it costs and gains (``bench/results/gpu_scale_threads.json``, 2 H200s, the tank's frames 60
times: 7,380 pings): one GPU in this path runs 2.0x (5 mm) and 4.4x (1 cm) faster than
:func:`gpumap.pipeline.replay.run_replay` (frames go as bytes, read by a thread of their own). Two GPUs
map in parallel, but each thread's host work per batch holds the GIL: the slower device's
integrate time was 2.1x shorter than one device's on OpenCL at 5 mm, 1.3x on Warp, and at 1 cm
both were bound by the host (no gain). That run merged through whole-pool copies (5.8 s at 5 mm:
each block read or write moved the whole map); the merge above (blocks by runs, the other map's
own blocks device to device, the shared ones combined in threads) is not yet measured on GPUs;
about 45 % of the observed blocks are observed by both maps on the tank. The same path runs N
mappers on one CPU device (the tests: CPU backends, ``device_index`` 0) with the one-process map.
"""

from __future__ import annotations

import math
import os
import queue
import threading
import time

import numpy as np

from gpumap.core.params import MapperParams
from gpumap.pipeline.workers import BATCH, _Batch, plan_replay, routed

__all__ = ["GPU_BACKENDS", "OPTIONS", "QUEUED", "merge_dense", "run_replay_threads"]

#: Batches a device's queue holds before the client waits for it (bounds the frames in memory).
QUEUED = 4
#: Threads that combine the blocks two maps both observed (at most; the CPU's cores, up to 16).
COMBINE_THREADS = min(16, os.cpu_count() or 1)
#: Backends whose devices are GPUs, one mapper per GPU (``"opencl"`` picks GPUs first).
GPU_BACKENDS = ("warp-cuda", "opencl-gpu", "opencl")


class _Lane(threading.Thread):
    """One device's thread: integrates the batches of its queue into its mapper, then reads the
    map's state (``keep``: the map stays whole instead, the one the others merge into)."""

    def __init__(self, mapper, keep: bool) -> None:
        super().__init__(daemon=True, name=f"gpumap-{mapper.backend}-{mapper.device}")
        self.mapper, self.keep = mapper, keep
        self.device = mapper.device
        self.q: queue.Queue = queue.Queue(maxsize=QUEUED)
        self.error: BaseException | None = None
        self.state = None
        self.frames = 0
        self.seconds_integrate = 0.0
        self.seconds_state = 0.0

    def run(self) -> None:
        while True:
            item = self.q.get()
            if item is None:
                break
            if self.error is not None:  # failed: drain, so the client never waits on a full queue
                continue
            try:
                t = time.perf_counter()
                self.mapper.integrate_batch(*item)
                self.seconds_integrate += time.perf_counter() - t
                self.frames += len(item[0])
            except BaseException as e:  # noqa: BLE001 - handed to the client thread
                self.error = e
        if self.error is not None:
            return
        try:
            t = time.perf_counter()
            self.mapper.synchronize()
            self.seconds_integrate += time.perf_counter() - t
            if not self.keep:
                from gpumap.core.mapstate import read_state

                t = time.perf_counter()
                self.state = read_state(self.mapper)
                self.mapper = None  # its device memory goes now
                self.seconds_state = time.perf_counter() - t
        except BaseException as e:  # noqa: BLE001
            self.error = e

    def put(self, item) -> None:
        """Queue ``item`` for this device, waiting while the queue is full; raises the thread's
        error if it failed."""
        while True:
            if self.error is not None:
                raise self.error
            try:
                self.q.put(item, timeout=0.2)
                return
            except queue.Full:
                if not self.is_alive():
                    raise RuntimeError(f"the mapping thread {self.name} stopped") from self.error


def merge_dense(mapper, other) -> None:
    """Merge ``other`` into ``mapper``, in place: two maps of one bounded box (the same grid, so the
    same block in the same slot) and options, made by this module from disjoint pings. Blocks only
    ``other`` observed are copied (device to device where the backend can: Warp), blocks both
    observed are combined on the host (:func:`gpumap.core.rules.combine_into`, as every merge does),
    the others stay: the map :meth:`gpumap.MinMaxMapper.merge` makes, bit for bit, without reading
    either whole map."""
    from gpumap.core.mapstate import options_of

    if mapper.sparse is not None or other.sparse is not None or options_of(mapper) != options_of(other):
        raise ValueError("Expected two maps of one bounded box and the same options to merge block by block")
    shared = mapper.pings.shared(other.pings.array())
    if shared:
        raise ValueError(f"Expected maps built from different pings, but they share {shared}")
    a, b = mapper.storage, other.storage
    with a.lock, b.lock:
        a.synchronize()
        b.synchronize()
        seen_a, seen_b = a.backend.read_seen() != 0, b.backend.read_seen() != 0
        a.backend.copy_blocks_from(b.backend, np.flatnonzero(seen_b & ~seen_a))
        both = np.flatnonzero(seen_b & seen_a)
        if len(both):
            names = ("min_all", "bright", "count")
            mine = dict(zip(names, a.backend.read_blocks(both), strict=True))
            theirs = dict(zip(names, b.backend.read_blocks(both), strict=True))
            if mapper.rule == "plain":
                mine, theirs = {"min_all": mine["min_all"]}, {"min_all": theirs["min_all"]}
            _combine_rows(mine, theirs, mapper.rule)
            a.backend.write_blocks(both, mine["min_all"], mine.get("bright"), mine.get("count"))
        a.empty = a.empty and not seen_b.any()
        mapper.n_integrated += int(other.n_integrated)
        mapper.pings.extend(other.pings.array())


def _combine_rows(mine: dict, theirs: dict, rule: str) -> None:
    """:func:`gpumap.core.rules.combine_into` of (n, BV) blocks, in chunks of rows on threads (NumPy
    releases the GIL; every voxel is combined once, by itself: the same arrays as one call)."""
    from concurrent.futures import ThreadPoolExecutor

    from gpumap.core.rules import combine_into

    n = len(mine["min_all"])
    k = max(1, min(COMBINE_THREADS, n // 16))
    cuts = np.linspace(0, n, k + 1).astype(int)

    def part(i: int) -> None:
        sl = slice(cuts[i], cuts[i + 1])
        combine_into({x: v[sl] for x, v in mine.items()}, {x: v[sl] for x, v in theirs.items()}, rule)

    if k == 1:
        part(0)
        return
    with ThreadPoolExecutor(k, thread_name_prefix="gpumap-merge") as pool:
        list(pool.map(part, range(k)))


def _devices(backend: str, workers: int, devices) -> list[int]:
    """The device index of each of ``workers`` mappers: ``devices`` as given (checked by the
    backends when the mappers are made), else 0, 1, ... on GPU backends and 0 on CPU ones."""
    if devices is not None:
        devices = [int(d) for d in devices]
        if len(devices) != workers:
            raise ValueError(f"Expected {workers} device indices (one per worker), but got {len(devices)}")
        return devices
    return list(range(workers)) if backend in GPU_BACKENDS else [0] * workers


def _resolve_backend(backend: str) -> str:
    """``backend``, with ``"auto"`` resolved to the first that runs here (its device count matters)."""
    if backend != "auto":
        return backend
    from gpumap.backends import available_backends

    return available_backends()[0]


#: The options :func:`run_replay_threads` takes beside its own, and their defaults (those of
#: :func:`gpumap.pipeline.workers.run_replay_workers`).
OPTIONS = {"voxel_size_m": 0.05, "backend": "auto", "method": "gather", "grid": None, "static": False,
           "stride": 1, "max_frames": None, "progress": True, "rule": None, "threshold": 0.4,
           "positions": None, "sparse": False}


def run_replay_threads(recording, *, workers: int, devices: list[int] | None = None, split: str = "space",
                       **options) -> tuple[object, dict]:
    """:func:`gpumap.pipeline.replay.run_replay` on ``workers`` devices of this machine, one thread and one
    mapper each: the same map, bit for bit (module docstring).

    Parameters
    ----------
    workers : int
        Mappers (threads), one per device.
    devices : list of int, optional
        Each mapper's ``device_index`` (:class:`~gpumap.MinMaxMapper`); None: ``0 .. workers-1``
        on a GPU backend (:data:`GPU_BACKENDS`, ``"auto"`` resolved first), device 0 for every
        mapper on a CPU one. An index the backend does not have raises ``ValueError``.
    split : str
        ``"space"`` (default) or ``"pings"``, as :func:`gpumap.pipeline.workers.run_replay_workers`.
    **options
        :data:`OPTIONS` (``voxel_size_m``, ``backend``, ``method``, ``grid``, ``static``,
        ``stride``, ``max_frames``, ``progress``, ``rule``, ``threshold``, ``positions``,
        ``sparse``): as :func:`gpumap.pipeline.workers.run_replay_workers`; any other raises ``TypeError``.

    Returns
    -------
    mapper : MinMaxMapper
        The merged map, on the first device's backend.
    stats : dict
        ``run_replay``'s keys, plus ``workers``, ``devices``, ``split``, ``mode`` (``"threads"``),
        ``seconds_setup`` (making the mappers), ``seconds_map`` (reading and mapping until every
        device is done), ``seconds_merge`` (the others' maps into the first, after the mapping),
        ``per_worker`` (frames, device, integrate and state-read seconds) and ``seconds_wall``.
    """
    from tqdm import tqdm

    from gpumap.core.mapper import MinMaxMapper
    from gpumap.core.mapstate import merge_state

    unknown = sorted(set(options) - set(OPTIONS))
    if unknown:
        raise TypeError(f"Expected options among {sorted(OPTIONS)}, but got {unknown}")
    o = {**OPTIONS, **options}
    backend, method, grid, static, stride, max_frames, rule, threshold, positions, sparse = (
        o[k] for k in ("backend", "method", "grid", "static", "stride", "max_frames", "rule", "threshold",
                       "positions", "sparse"))
    voxel_size_m = o["voxel_size_m"]
    t_wall = time.perf_counter()
    frames, grid, owners = plan_replay(recording, workers=workers, split=split, static=static, stride=stride,
                                       max_frames=max_frames, grid=grid, voxel_size_m=voxel_size_m,
                                       sparse=sparse, method=method)
    if int(workers) == 1:
        owners = None  # one mapper: every frame is its own
    workers = int(workers)
    backend = _resolve_backend(backend)
    devs = _devices(backend, workers, devices)
    stride = max(1, int(stride))
    rule = rule or ("evidence" if method == "gather" else "plain")
    total = recording.count()
    if total is not None:
        total = min(math.ceil(total / stride), max_frames or total)
    stats = {"frames": 0, "skipped_no_pose": 0, "skipped_spec": 0}
    lanes: list[_Lane] = []
    batches = [_Batch() for _ in range(workers)]
    spec = None
    t_setup = 0.0
    t_map = time.perf_counter()
    try:
        frame_iter = tqdm(frames(), total=total, unit="img", disable=not o["progress"],
                          desc=f"replay x{workers} ({backend})")

        def start(sp) -> None:  # the mappers, made one after the other at the first frame (its sonar)
            nonlocal spec, lanes, t_setup
            ts = time.perf_counter()
            spec = sp
            mappers = [
                MinMaxMapper(
                    spec,
                    grid,
                    backend,
                    MapperParams(method=method, rule=rule, threshold=threshold, sparse=bool(sparse)),
                    device_index=d,
                )
                for d in devs
            ]  # a device that is not there raises here, before any thread
            # a bounded box: every map kept whole, merged block by block (merge_dense); on demand
            # (each map its own block layout) every map but the first hands over its state
            lanes = [_Lane(m, keep=k == 0 or not sparse) for k, m in enumerate(mappers)]
            del mappers
            for lane in lanes:
                lane.start()
            t_setup = time.perf_counter() - ts

        for w, img, T in routed(frame_iter, owners, workers, static, stats, positions, start):
            b = batches[w]
            if not b.fits(img):
                lanes[w].put(b.take())
            if b.add(img, T) == BATCH:
                lanes[w].put(b.take())
        if spec is None:
            raise ValueError(f"Expected frames in {recording.path}, but it has none")
        for w, b in enumerate(batches):
            if b.n:
                lanes[w].put(b.take())
    finally:
        for lane in lanes:  # every thread ends (a failed run too)
            while lane.is_alive():
                try:
                    lane.q.put(None, timeout=0.2)
                    break
                except queue.Full:
                    continue
        for lane in lanes:
            lane.join()
    for lane in lanes:
        if lane.error is not None:
            raise lane.error
    seconds_map = time.perf_counter() - t_map - t_setup
    t1 = time.perf_counter()
    mapper = lanes[0].mapper
    for lane in lanes[1:]:  # exact: mins and saturating counts (gpumap.core.merge)
        if lane.state is None:  # a bounded box: block by block (merge_dense)
            merge_dense(mapper, lane.mapper)
            lane.mapper = None
        else:
            merge_state(mapper, lane.state)
            lane.state = None
    mapper.synchronize()
    seconds_merge = time.perf_counter() - t1
    n = stats["frames"]
    t_total = seconds_map + seconds_merge
    per = [{"frames": ln.frames, "device_index": d, "device": ln.device,
            "seconds_integrate": ln.seconds_integrate, "seconds_state": ln.seconds_state}
           for ln, d in zip(lanes, devs, strict=True)]
    slowest = max(p["seconds_integrate"] for p in per)
    stats.update(
        seconds_setup=t_setup,
        seconds_total=t_total,
        seconds_integrate=slowest,
        images_per_s=n / t_total if n else 0.0,
        integrate_per_s=n / slowest if n and slowest else 0.0,
        backend=mapper.backend,
        device=mapper.device,
        rule=rule,
        mapper_threshold=float(threshold),
        grid=grid.to_dict(),
        grid_shape=list(grid.shape),
        workers=workers,
        devices=devs,
        split="space" if owners is not None else "pings",
        mode="threads",
        seconds_map=seconds_map,
        seconds_merge=seconds_merge,
        seconds_wall=time.perf_counter() - t_wall,
        per_worker=per,
    )
    return mapper, stats
