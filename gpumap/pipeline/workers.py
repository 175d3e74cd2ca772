"""Map a recording in Dask workers and merge their maps: ``gpumap replay RECORDING --workers N``.

How the work is split: by pings, grouped by place. The client reads the recording once (the
readers are sequential streams) and hands each ping to one of N workers, in batches of
:data:`BATCH`; each worker keeps one mapper (a Dask *actor*: its map stays in the worker
between batches, on the worker's own backend) and integrates its batches as they come,
while the client reads the next ones. At the end every worker sends its map's state
(:class:`gpumap.core.merge.MapState`) and the client merges them (:func:`gpumap.core.merge.merge_maps`).
Every update is a min or a saturating count, so the merged map equals the map of one
process, bit for bit, whatever the split (:mod:`gpumap.core.merge`).

Which worker gets a ping (``split``): ``"space"`` (default) ranks the pings by where their
field of view's middle lies along the grid's longer horizontal axis and cuts the ranking
into N runs of equal counts, so each worker maps one stretch of the survey and the workers'
maps overlap only at the seams: a map sends only its blocks with an observed voxel, about one
map's worth in all. ``"pings"`` sends batches to each
worker in turn: the work stays even however the sonar moves, but every worker's map spans
the whole survey and N whole maps travel back.

Why not tiles of the grid (each worker a sub-grid): a sub-grid's voxel centres, computed
from its own origin in float32, round differently from the whole grid's, so tiles would not
give the one-process map bit for bit; every worker here maps on the whole grid's lattice.

What it costs: the client sends every ping once, and each worker's map comes back once (a
fixed cost per run that mapping must outweigh; ``bench/workers.py`` measures it). The
workers need gpumap installed, not the recording. Any Dask cluster works
(``scheduler="tcp://host:8786"``); without one, a :class:`distributed.LocalCluster` of N
single-threaded worker processes is started and closed again.
"""

from __future__ import annotations

import logging
import math
import os
import time
from collections import deque

import numpy as np

from gpumap.core.params import MapperParams
from gpumap.spec import GridSpec, SonarSpec

__all__ = ["BATCH", "run_replay_workers"]

log = logging.getLogger("gpumap")

#: Pings per batch sent to a worker (as :func:`gpumap.pipeline.replay.run_replay` batches them).
BATCH = 32
#: Batches a worker may have queued before the client waits for it (bounds the memory in flight).
QUEUED = 2
#: Seconds to wait for a given cluster's workers to join before saying how many it has.
WAIT_WORKERS_S = 30.0


def host_gpus() -> list[str]:
    """This process's NVIDIA GPUs, as ``CUDA_VISIBLE_DEVICES`` entries, found without starting CUDA
    (which reads that variable once, when it starts): the variable's own list when it is set, else
    one entry per GPU the driver lists in ``/proc/driver/nvidia/gpus`` (none without a driver)."""
    seen = os.environ.get("CUDA_VISIBLE_DEVICES")
    if seen is not None:
        return [d.strip() for d in seen.split(",") if d.strip() and d.strip() != "-1"]
    try:
        n = len(os.listdir("/proc/driver/nvidia/gpus"))
    except OSError:  # no driver files: ask nvidia-smi (a process of its own), if there is one
        import subprocess

        try:
            out = subprocess.run(["nvidia-smi", "-L"], capture_output=True, text=True, timeout=20).stdout
        except (OSError, subprocess.SubprocessError):
            return []
        n = sum(line.startswith("GPU ") for line in out.splitlines())
    return [str(k) for k in range(n)]


def pin_gpu(rank: int) -> str | None:
    """Give this process one GPU of its host, the ``rank``-th (modulo their count), by setting
    ``CUDA_VISIBLE_DEVICES`` before Warp or OpenCL start CUDA (NVIDIA's OpenCL honours it too);
    returns the entry, or None where the host has no GPU or CUDA already started here (then the
    variable, read once, would say nothing true)."""
    gpus = host_gpus()
    if not gpus or _cuda_started():
        return None
    os.environ["CUDA_VISIBLE_DEVICES"] = gpus[rank % len(gpus)]
    return os.environ["CUDA_VISIBLE_DEVICES"]


def _cuda_started() -> bool:
    """Whether a backend may have started CUDA in this process: Warp started, or an OpenCL context
    made (gpumap's backends start them when first used)."""
    from gpumap.backends import opencl_backend, warp_backend

    return warp_backend._warp.cache_info().currsize > 0 or bool(opencl_backend._CL_SHARED)


def host_ranks(addrs: list[str]) -> list[int]:
    """Each worker's rank among the workers of its host (by address, in the given order): the GPU
    it takes there (:func:`pin_gpu`)."""
    from urllib.parse import urlsplit

    count: dict[str, int] = {}
    out = []
    for a in addrs:
        host = urlsplit(a if "://" in a else f"tcp://{a}").hostname or a
        out.append(count.get(host, 0))
        count[host] = out[-1] + 1
    return out


class MapperActor:
    """One worker's mapper (a Dask actor): integrates the batches it is sent, returns its state."""

    def __init__(self, spec: dict, grid: dict, options: dict, sparse: bool, cpu_threads: int | None,
                 gpu_rank: int | None = None) -> None:
        from gpumap.core.mapper import MinMaxMapper

        t0 = time.perf_counter()
        # one GPU per worker: chosen before the mapper starts its backend (and with it CUDA)
        self.gpu = pin_gpu(gpu_rank) if gpu_rank is not None else None
        if cpu_threads is not None:  # this worker process's CPU backends split gathers this many ways
            import gpumap.backends

            gpumap.backends.CPU_THREADS = int(cpu_threads)
        s, g = SonarSpec.from_dict(spec), GridSpec.from_dict(grid)
        opts = dict(options)
        backend = opts.pop("backend", "auto")
        self.mapper = MinMaxMapper(s, g, backend, MapperParams(sparse=bool(sparse), **opts))
        self.seconds_setup = time.perf_counter() - t0
        self.seconds_integrate = 0.0
        self.frames = 0

    def info(self) -> dict:
        return {"backend": self.mapper.backend, "device": self.mapper.device,
                "cuda_visible_devices": os.environ.get("CUDA_VISIBLE_DEVICES"), "gpu": self.gpu,
                "seconds_setup": self.seconds_setup}

    def integrate_batch(self, images: np.ndarray, poses: np.ndarray) -> int:
        """Integrate a batch: float32 frames, or uint8 ones that are exactly the frames x 255 (the
        mapper scales uint8 by the same float32 1/255, so the map is the same bit for bit)."""
        t0 = time.perf_counter()
        self.mapper.integrate_batch(images, poses)
        self.seconds_integrate += time.perf_counter() - t0
        self.frames += len(images)
        return self.frames

    def state(self, pack: bool):
        """The map's state for the wire (:func:`_pack`): its observed blocks, and with ``pack``
        its float arrays as bytes where that is lossless (a third of the bytes
        to send, for about ten passes over the arrays)."""
        from gpumap.core.merge import map_state

        t0 = time.perf_counter()
        st = map_state(self.mapper)  # waits for the device
        self.seconds_integrate += time.perf_counter() - t0
        t1 = time.perf_counter()
        packed = _pack(st, pack)
        info = {"frames": self.frames, "seconds_integrate": self.seconds_integrate,
                "seconds_pack": time.perf_counter() - t1, "state_mb": _nbytes(packed) / 1e6,
                "state_mb_unpacked": sum(a.nbytes for a in st.arrays.values()) / 1e6}
        return packed, info


#: ``SonarFrame.meta`` key of a frame's own bytes, where its reader has them: ``image`` is exactly
#: ``image_u8 * gpumap.backends.U8_SCALE`` (float32). The client then sends the bytes as they are
#: (a quarter of the float32 frame, and no pass to find them: :func:`_compact`).
FRAME_BYTES = "image_u8"


def frame_pixels(fr) -> np.ndarray:
    """What the client sends of frame ``fr``: its bytes (:data:`FRAME_BYTES`) where its reader
    kept them and they have the frame's shape, else its float32 image."""
    u8 = fr.meta.get(FRAME_BYTES) if isinstance(fr.meta, dict) else None
    if isinstance(u8, np.ndarray) and u8.dtype == np.uint8 and u8.shape == fr.image.shape:
        return u8
    return fr.image


class _Batch:
    """A worker's next batch, filled in place: each frame copied once, into the array that is sent
    (the reader may reuse its buffers), and a new array per batch (Dask may still be sending the
    last one)."""

    def __init__(self) -> None:
        self.images: np.ndarray | None = None
        self.poses = np.empty((BATCH, 4, 4))
        self.n = 0

    def fits(self, img: np.ndarray) -> bool:
        """Whether ``img`` may join (same dtype and shape as the frames already in)."""
        a = self.images
        return self.n == 0 or (a.dtype == img.dtype and a.shape[1:] == img.shape)

    def add(self, img: np.ndarray, T) -> int:
        if self.images is None or not (self.images.dtype == img.dtype and self.images.shape[1:] == img.shape):
            self.images = np.empty((BATCH, *img.shape), img.dtype)
        self.images[self.n] = img
        self.poses[self.n] = np.asarray(T, np.float64)
        self.n += 1
        return self.n

    def take(self) -> tuple[np.ndarray, np.ndarray]:
        out = self.images[: self.n], self.poses[: self.n].copy()
        self.images, self.n = None, 0
        return out


def _compact(images: np.ndarray) -> np.ndarray:
    """``images`` as uint8 when that is lossless for the mapper (every value is a byte times
    the mapper's float32 1/255, as the 8-bit sonars' frames are): a quarter of the bytes to send."""
    from gpumap.backends import U8_SCALE

    if images.dtype != np.float32:
        return images
    b = np.rint(images * np.float32(255.0))
    if images.size and not (b.min() >= 0 and b.max() <= 255):
        return images
    u8 = b.astype(np.uint8)
    return u8 if np.array_equal(np.multiply(u8, U8_SCALE, dtype=np.float32), images) else images


def _pack(st, pack: bool = True) -> tuple:
    """A :class:`~gpumap.core.merge.MapState` for the wire; :func:`_unpack` restores it exactly.

    ``pack``: each per-voxel array travels as its non-empty entries (``+inf`` floats and 0 counts
    are empty: most of a block's voxels) and a bit per voxel saying which; float entries that
    are all bytes times the mapper's float32 1/255 (always so for 8-bit pings: a ping's value is
    the max of image cells, the map's the min of those) travel as those bytes. Kinds: ``"u8"``
    (such bytes), ``"f32"`` (other floats), ``"bytes"`` (counts, in their own dtype); ``"raw"``: as it is.
    """
    arrays: dict = {}
    for k, v in st.arrays.items():
        if not pack or k == "blocks" or v.dtype not in (np.float32, np.uint8, np.uint64):
            arrays[k] = ("raw", v)
            continue
        keep = np.isfinite(v) if v.dtype == np.float32 else v != 0
        vals = v[keep]
        kind = "bytes"
        if v.dtype == np.float32:
            vals = _compact(vals)
            kind = "u8" if vals.dtype == np.uint8 else "f32"
        arrays[k] = (kind, v.shape, np.packbits(keep.ravel()), vals)
    return st.kind, st.options, st.n_integrated, arrays


def _unpack(packed: tuple):
    from gpumap.backends import U8_SCALE
    from gpumap.core.merge import MapState

    kind, options, n, arrays = packed
    out = {}
    for k, a in arrays.items():
        if a[0] == "raw":
            out[k] = a[1]
            continue
        what, shape, bits, vals = a
        size = int(np.prod(shape))
        keep = np.unpackbits(bits, count=size).view(bool)
        if what == "bytes":
            v = np.zeros(size, vals.dtype)
        else:
            v = np.full(size, np.inf, np.float32)
            if what == "u8":
                vals = np.multiply(vals, U8_SCALE, dtype=np.float32)
        v[keep] = vals
        out[k] = v.reshape(shape)
    return MapState(kind, options, n, out)


def _nbytes(packed: tuple) -> int:
    return sum(x.nbytes for a in packed[3].values() for x in a[1:] if isinstance(x, np.ndarray))


def _space_owners(spec: SonarSpec, poses: list, grid: GridSpec, n: int) -> np.ndarray:
    """Worker of each selected frame for the space split: frames ranked by where their field of
    view's middle (half the range along the boresight) lies along the grid's longer horizontal
    axis, cut into ``n`` runs of equal work (each frame weighs the voxels of its field of view's
    bounding box inside the grid, what the gather walks: equal counts of frames that look at
    more or less of the grid would leave one worker waiting for the other); frames without a
    pose go to worker 0."""
    axis = 0 if grid.shape[0] >= grid.shape[1] else 1
    mid = 0.5 * (spec.range_min_m + spec.range_max_m)
    key = np.full(len(poses), -np.inf)
    cost = np.zeros(len(poses))
    corners = spec.fov_corners_S()
    lo, s, dims = np.asarray(grid.min_corner_m), grid.voxel_size_m, np.asarray(grid.shape)
    posed = np.array([T is not None for T in poses], bool)
    if posed.any():  # every posed frame at once (a loop over frames took 0.1 s per 7,000)
        T = np.stack([np.asarray(T, np.float64) for T in poses if T is not None])
        key[posed] = T[:, axis, 3] + mid * T[:, axis, 0]
        W = corners[None] @ T[:, :3, :3].transpose(0, 2, 1) + T[:, None, :3, 3]
        i0 = np.clip(np.floor((W.min(axis=1) - lo) / s) - 1, 0, dims)
        i1 = np.clip(np.floor((W.max(axis=1) - lo) / s) + 2, 0, dims)
        cost[posed] = np.prod(np.maximum(i1 - i0, 0), axis=1) + 1.0  # + 1: a frame costs something
    order = np.argsort(key, kind="stable")
    before = np.cumsum(cost[order]) - cost[order]  # the work ranked ahead of each frame
    owners = np.empty(len(poses), np.int64)
    owners[order] = np.minimum((before * n / max(cost.sum(), 1.0)).astype(np.int64), n - 1)
    return owners


def plan_replay(recording, *, workers: int, split: str, static: bool, stride: int, max_frames: int | None,
                grid: GridSpec | None, voxel_size_m: float, sparse: bool, method: str):
    """What a run of N mappers needs first (here and :mod:`gpumap.pipeline.gpu_threads`), its arguments
    checked: (``frames``, a function giving the selected frames as :func:`gpumap.pipeline.replay.run_replay`
    selects them; the grid, sized from every selected pose where None; the space split's owner
    of each selected frame, or None for the pings split)."""
    if isinstance(workers, bool) or not isinstance(workers, (int, np.integer)) or workers < 1:
        raise ValueError(f"Expected workers to be a positive integer, but got {workers!r}")
    if not (recording.has_poses or static):
        raise ValueError(f"Expected sonar poses in {recording.path} ({recording.kind}) to map it, but it has "
                         "none (--static maps every ping at the identity pose)")
    if sparse and method != "gather":
        raise ValueError(f"Expected method='gather' with sparse=True, but got {method!r}")
    if split not in ("space", "pings"):
        raise ValueError(f"Expected split to be 'space' or 'pings', but got {split!r}")
    from gpumap.pipeline.replay import grid_of_frames, select_strided, selected_poses

    stride = max(1, int(stride))

    def frames():  # the frames run_replay selects
        return select_strided(recording, stride, max_frames)

    selected = None  # every selected frame's pose, read once for the grid and the space split
    if not static and (grid is None or split == "space"):
        selected = selected_poses(recording, stride, max_frames)
        if selected[0] is None:
            raise ValueError(f"Expected frames in {recording.path}, but it has none")
    if grid is None:  # as run_replay sizes it: the box of every selected field of view
        grid = grid_of_frames(recording, static=static, stride=stride, max_frames=max_frames,
                              voxel_size_m=voxel_size_m, selected=selected)
    owners = None
    if split == "space" and not static:
        owners = _space_owners(*selected, grid, int(workers))
    return frames, grid, owners


def routed(frame_iter, owners, workers: int, static: bool, stats: dict, positions: list | None, start):
    """Each frame to map as (mapper, pixels, T_W_S): the frame's place's mapper (``owners``) or
    :data:`BATCH` frames to each in turn; ``start(spec)`` is called at the first frame (its sonar
    is the run's), frames of another sonar or without a pose are counted in ``stats`` and skipped."""
    eye = np.eye(4)
    spec = None
    for i, fr in enumerate(frame_iter):
        if spec is None:
            spec = fr.spec
            start(spec)
        T = eye if static else fr.T_W_S
        if fr.spec != spec or T is None:  # another sonar's frame, or one without a pose
            stats["skipped_spec" if fr.spec != spec else "skipped_no_pose"] += 1
            continue
        if owners is not None:
            w = int(owners[i]) if i < len(owners) else 0  # a frame the pose list missed
        else:
            w = (stats["frames"] // BATCH) % workers
        yield w, frame_pixels(fr), T
        stats["frames"] += 1
        if positions is not None:
            positions.append(np.asarray(T, dtype=np.float64)[:3, 3].copy())


def _client(workers: int, scheduler: str | None, processes: bool):
    """(client, cluster or None): a client of the scheduler at ``scheduler`` or of a new
    LocalCluster of ``workers`` single-threaded workers."""
    try:
        from distributed import Client, LocalCluster
    except ImportError as e:
        raise ImportError(
            "Expected Dask distributed for --workers, but it is not installed: "
            "pip install 'gpumap[workers]'"
        ) from e
    # Dask's own start/stop chatter (INFO) is not the user's business; its warnings still show
    for name in ("distributed", "tornado"):
        logging.getLogger(name).setLevel(logging.WARNING)
    if scheduler is not None:
        client = Client(scheduler, timeout="30s")
        try:
            client.wait_for_workers(workers, timeout=60)
        except Exception as e:
            n = len(client.ncores())
            client.close()
            raise ValueError(
                f"Expected {workers} workers at the scheduler {scheduler}, but {n} came within 60 s"
            ) from e
        return client, None
    cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=processes,
                           dashboard_address=":0", silence_logs=logging.CRITICAL)
    return Client(cluster), cluster


def run_replay_workers(
    recording,
    *,
    workers: int,
    scheduler: str | None = None,
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
    processes: bool = True,
    client=None,
    cpu_threads: int | None = None,
    pack: bool | None = None,
    split: str = "space",
    gpus: str = "auto",
) -> tuple[object, dict]:
    """:func:`gpumap.pipeline.replay.run_replay` in ``workers`` Dask workers: the same map, bit for bit.

    Parameters
    ----------
    recording : gpumap.io.Recording
        Read here, by the client; the workers get the pings.
    workers : int
        Workers to map in (each one mapper on ``backend``, one batch at a time).
    scheduler : str, optional
        Address of a running Dask scheduler (e.g. ``"tcp://10.0.0.5:8786"``); its first
        ``workers`` workers are used. None: a LocalCluster of ``workers`` processes
        (``processes=False``: threads of this process, for tests).
    gpus : str
        ``"auto"`` (default): each worker maps on one GPU of its host, the one of its rank among
        the workers there (modulo the host's GPUs: :func:`pin_gpu`), so N workers on a machine of
        N GPUs use all of them; ``"none"``: workers keep the devices they see.
    split : str
        ``"space"`` (default): each worker gets the pings that look at its part of the grid
        (pings ranked by where their field of view's middle lies along the grid's longer
        horizontal axis, cut into runs of equal counts), so that the workers' maps barely
        overlap and little more than one map's worth travels back; ``"pings"``: batches of
        :data:`BATCH` to each worker in turn (every worker's map spans the whole survey, but
        the work stays even however the sonar moves). Needs every ping's pose first (the
        recording's pose list, or one more pass over a recording without one); ``static``
        runs split by pings.
    sparse : bool
        Workers keep maps with blocks on demand (``sparse=True``), bounded by the grid (each sends
        only the blocks its pings observed); the result is then a sparse map.
    client : distributed.Client, optional
        Use this client (and its cluster) instead; left open.
    cpu_threads : int, optional
        Threads each worker's CPU backend splits a gather into (``gpumap.backends.CPU_THREADS``,
        set in the worker process: use it with worker processes only). None: the default (2).
    pack : bool, optional
        Workers send their maps packed (:func:`_pack`, lossless: the observed entries only, bytes
        where the values are bytes / 255; about a seventh of the bytes on the survey), at the cost
        of a few passes over the arrays in each worker. None (default): packed.
    Other parameters: as :func:`gpumap.pipeline.replay.run_replay` (``grid`` None: sized from every
    selected pose, before mapping).

    Returns
    -------
    mapper : MinMaxMapper
        The merged map, on the NumPy backend (it is read and written, not integrated).
    stats : dict
        ``run_replay``'s keys, plus ``workers``, ``scheduler``, ``seconds_cluster`` (starting
        the cluster or connecting), ``seconds_map`` (reading and mapping, until every worker
        is done), ``seconds_gather`` (the workers' states to the client), ``seconds_merge``,
        ``per_worker`` (frames, backend, setup and integrate seconds) and
        ``seconds_wall`` (everything, the cluster included).
    """
    from tqdm import tqdm

    from gpumap.core.merge import merge_maps

    if gpus not in ("auto", "none"):
        raise ValueError(f"Expected gpus to be 'auto' or 'none', but got {gpus!r}")
    t_wall = time.perf_counter()
    frames, grid, owners = plan_replay(recording, workers=workers, split=split, static=static, stride=stride,
                                       max_frames=max_frames, grid=grid, voxel_size_m=voxel_size_m,
                                       sparse=sparse, method=method)
    stride = max(1, int(stride))
    rule = rule or ("evidence" if method == "gather" else "plain")
    options = {"backend": backend, "method": method, "rule": rule, "threshold": threshold}
    t0 = time.perf_counter()
    own = client is None
    cluster = None
    if own:
        client, cluster = _client(int(workers), scheduler, processes)
    seconds_cluster = time.perf_counter() - t0
    try:
        try:  # a cluster that is still starting its workers gets a while to do so
            client.wait_for_workers(int(workers), timeout=WAIT_WORKERS_S)
        except (TimeoutError, OSError):
            pass
        addrs = sorted(client.ncores())[: int(workers)]  # a fresh ask (scheduler_info may be cached)
        if len(addrs) < workers:
            raise ValueError(f"Expected {workers} Dask workers, but the cluster has {len(addrs)}")
        total = recording.count()
        if total is not None:
            total = min(math.ceil(total / stride), max_frames or total)
        stats = {"frames": 0, "skipped_no_pose": 0, "skipped_spec": 0}
        actors: list = []
        infos: list = []
        pending: list[deque] = [deque() for _ in addrs]
        spec = None
        batches = [_Batch() for _ in addrs]
        t_map = time.perf_counter()
        t_setup = 0.0

        def send(w: int) -> None:
            q = pending[w]
            while len(q) >= QUEUED:
                q.popleft().result()
            images, poses = batches[w].take()
            q.append(actors[w].integrate_batch(_compact(images), poses))

        frame_iter = tqdm(frames(), total=total, unit="img", disable=not progress,
                          desc=f"replay x{len(addrs)}")
        def start(sp) -> None:  # the actors, at the first frame (its sonar is the run's)
            nonlocal spec, actors, infos, t_setup
            ts = time.perf_counter()
            spec = sp
            args = (spec.to_dict(), grid.to_dict(), options, sparse, cpu_threads)
            ranks = host_ranks(addrs) if gpus == "auto" else [None] * len(addrs)
            futs = [client.submit(MapperActor, *args, r, workers=[a], allow_other_workers=False,
                                  actor=True, pure=False) for a, r in zip(addrs, ranks, strict=True)]
            actors = [f.result() for f in futs]
            infos = [a.info().result() for a in actors]  # a backend that cannot run raises here
            t_setup = time.perf_counter() - ts

        # space: the worker of the frame's place; pings: BATCH frames to each worker in turn
        for w, img, T in routed(frame_iter, owners, len(addrs), static, stats, positions, start):
            if not batches[w].fits(img):
                send(w)
            if batches[w].add(img, T) == BATCH:
                send(w)
        if spec is None:
            raise ValueError(f"Expected frames in {recording.path}, but it has none")
        for w, batch in enumerate(batches):
            if batch.n:
                send(w)
        for q in pending:
            while q:
                q.popleft().result()
        seconds_map = time.perf_counter() - t_map - t_setup
        t1 = time.perf_counter()
        if pack is None:  # the observed entries only: cheaper to pack than to send, even on one host
            pack = True
        futs = [a.state(bool(pack)) for a in actors]  # every worker sends at once
        results: list = []
        seconds_gather = 0.0  # waiting for states; the rest of the time after t1 is merging

        def states():  # each state as it comes: merged while the next ones still travel
            nonlocal seconds_gather
            for f in futs:
                t = time.perf_counter()
                results.append(f.result())
                seconds_gather += time.perf_counter() - t
                yield _unpack(results[-1][0])

        quiet = logging.getLogger("gpumap")  # the merged map's NumPy backend is no news to the user
        level = quiet.level
        quiet.setLevel(logging.WARNING)
        try:
            mapper = merge_maps(states(), backend="numpy")  # one at a time
        finally:
            quiet.setLevel(level)
        seconds_merge = time.perf_counter() - t1 - seconds_gather
    finally:
        if own:
            client.close()
            if cluster is not None:
                cluster.close()
    n = stats["frames"]
    t_total = seconds_map + seconds_gather + seconds_merge
    per = [{**info, **extra} for info, (_, extra) in zip(infos, results, strict=True)]
    stats.update(
        seconds_setup=t_setup,
        seconds_total=t_total,
        seconds_integrate=max(p["seconds_integrate"] for p in per),
        images_per_s=n / t_total if n else 0.0,
        integrate_per_s=n / max(p["seconds_integrate"] for p in per) if n else 0.0,
        backend=infos[0]["backend"],
        rule=rule,
        mapper_threshold=float(threshold),
        grid=grid.to_dict(),
        grid_shape=list(grid.shape),
        workers=len(addrs),
        split="space" if owners is not None else "pings",
        scheduler=scheduler or "LocalCluster",
        seconds_cluster=seconds_cluster,
        seconds_map=seconds_map,
        seconds_gather=seconds_gather,
        seconds_merge=seconds_merge,
        seconds_wall=time.perf_counter() - t_wall,
        per_worker=per,
    )
    return mapper, stats
