"""Map a recording on several GPUs of this machine, in this process, and merge the maps exactly.

``gpumap replay RECORDING --workers N`` on a machine with N GPUs (or more) and a GPU backend
takes this path (:func:`run_replay_threads`); a cluster of machines (``--scheduler``) takes the
Dask one (:mod:`gpumap.workers`).

How: one thread per device, each with its own :class:`~gpumap.MinMaxMapper` on its own device
(``device_index``: ``cuda:i`` on Warp, the i-th OpenCL GPU), fed batches of :data:`BATCH` pings
through a bounded queue by the client (this thread), which reads the recording once. The pings
are split as :mod:`gpumap.workers` splits them (``"space"``: each device maps one stretch of the
survey; ``"pings"``: batches to each device in turn). At the end each thread reads its map's
observed blocks (:func:`gpumap.mapstate.read_state`, while the others may still map), and the
first device's map takes the others' (:meth:`gpumap.MinMaxMapper.merge`: mins and saturating
counts, in place, only the blocks both hold read back): the map of one process, bit for bit,
on the first device. Nothing is pickled and no map leaves the process.

Why threads are enough: a batch's host work is short beside the GPU's (the kernels run without
the GIL), so N threads keep N GPUs busy; the same path runs N mappers on one CPU device (the
tests: CPU backends, ``device_index`` 0) with the one-process map, though not faster there.
"""

from __future__ import annotations

import itertools
import math
import queue
import threading
import time

import numpy as np

from gpumap.spec import GridSpec
from gpumap.workers import BATCH, _Batch, _poses_of, _space_owners, frame_pixels

__all__ = ["GPU_BACKENDS", "QUEUED", "run_replay_threads"]

#: Batches a device's queue holds before the client waits for it (bounds the frames in memory).
QUEUED = 4
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
                from gpumap.mapstate import read_state

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


def run_replay_threads(
    recording,
    *,
    workers: int,
    devices: list[int] | None = None,
    voxel_size_m: float = 0.05,
    backend: str = "auto",
    method: str = "gather",
    grid: GridSpec | None = None,
    static: bool = False,
    stride: int = 1,
    max_frames: int | None = None,
    progress: bool = True,
    rule: str | None = None,
    threshold: float = 0.4,
    positions: list | None = None,
    sparse: bool = False,
    split: str = "space",
) -> tuple[object, dict]:
    """:func:`gpumap.replay.run_replay` on ``workers`` devices of this machine, one thread and one
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
        ``"space"`` (default) or ``"pings"``, as :func:`gpumap.workers.run_replay_workers`.
    Other parameters: as :func:`gpumap.workers.run_replay_workers`.

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

    from gpumap.mapper import MinMaxMapper
    from gpumap.mapstate import merge_state

    if isinstance(workers, bool) or not isinstance(workers, (int, np.integer)) or workers < 1:
        raise ValueError(f"Expected workers to be a positive integer, but got {workers!r}")
    if split not in ("space", "pings"):
        raise ValueError(f"Expected split to be 'space' or 'pings', but got {split!r}")
    if not (recording.has_poses or static):
        raise ValueError(f"Expected sonar poses in {recording.path} ({recording.kind}) to map it, but it has "
                         "none (--static maps every ping at the identity pose)")
    if sparse and method != "gather":
        raise ValueError(f"Expected method='gather' with sparse=True, but got {method!r}")
    workers = int(workers)
    backend = _resolve_backend(backend)
    devs = _devices(backend, workers, devices)
    stride = max(1, int(stride))
    eye = np.eye(4)

    def frames():  # every stride-th frame, at most max_frames of them (as run_replay selects)
        stop = None if max_frames is None else max_frames * stride
        return itertools.islice(iter(recording), 0, stop, stride)

    t_wall = time.perf_counter()
    owners = None
    if static:
        if grid is None:
            from gpumap.spec import auto_grid

            grid = auto_grid(next(iter(recording)).spec, [eye], voxel_size_m)
    elif grid is None or split == "space":
        spec0, sel = _poses_of(recording, stride, max_frames, frames)
        if grid is None:
            from gpumap.spec import auto_grid

            posed = [T for T in sel if T is not None]
            if not posed:
                raise ValueError(f"Expected at least one posed frame in {recording.path}, but got none")
            grid = auto_grid(spec0, posed, voxel_size_m)
        if split == "space" and workers > 1:
            owners = _space_owners(spec0, sel, grid, workers)
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
        frame_iter = tqdm(frames(), total=total, unit="img", disable=not progress,
                          desc=f"replay x{workers} ({backend})")
        for i, fr in enumerate(frame_iter):
            if spec is None:  # the mappers, made here one after the other (the first frame's sonar)
                ts = time.perf_counter()
                spec = fr.spec
                mappers = [MinMaxMapper(spec, grid, backend=backend, method=method, rule=rule,
                                        threshold=threshold, sparse=bool(sparse), device_index=d)
                           for d in devs]  # a device that is not there raises here, before any thread
                lanes = [_Lane(m, keep=k == 0) for k, m in enumerate(mappers)]
                del mappers
                for lane in lanes:
                    lane.start()
                t_setup = time.perf_counter() - ts
            if fr.spec != spec:
                stats["skipped_spec"] += 1
                continue
            T = eye if static else fr.T_W_S
            if T is None:
                stats["skipped_no_pose"] += 1
                continue
            if owners is not None:
                w = int(owners[i]) if i < len(owners) else 0  # a frame the pose list missed
            else:
                w = (stats["frames"] // BATCH) % workers
            img = frame_pixels(fr)
            b = batches[w]
            if not b.fits(img):
                lanes[w].put(b.take())
            if b.add(img, T) == BATCH:
                lanes[w].put(b.take())
            stats["frames"] += 1
            if positions is not None:
                positions.append(np.asarray(T, dtype=np.float64)[:3, 3].copy())
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
    for lane in lanes[1:]:  # exact: mins and saturating counts (gpumap.merge)
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
