"""What every backend shares: the :class:`Backend` interface, the backends' names, the
constants of the image and block layouts, and the knobs a run may turn.

The knobs (:data:`TUNABLES`: how GPUs and CPUs split a gather, how a batch is folded and
staged) are read from this module when a backend or a batch needs them, so setting one on
:mod:`gpumap.backends` (which sets it here) changes what later work does.
"""

from __future__ import annotations

import functools
import os

import numpy as np

BACKENDS = ("numpy", "warp-cpu", "warp-cuda", "opencl", "opencl-gpu", "opencl-cpu")
AUTO_ORDER = ("warp-cuda", "opencl-gpu", "opencl-cpu", "warp-cpu", "numpy")

U8_SCALE = np.float32(1.0 / 255.0)  # 8-bit pings: intensity = byte * U8_SCALE, on every backend
# Image upload slots: the host may prepare this many pings ahead of the device.
N_SLOTS = 4
GPU_CHUNK = 16  # voxels of a column per gather thread on GPUs
#: Threads a CPU backend's gather may use (warp-cpu splits its launch; PoCL uses every core).
CPU_THREADS = min(2, os.cpu_count() or 1)
CPU_CHUNK = 1 << 30  # on CPUs, the whole column

#: Pings a GPU folds per launch (more are split); buffers grow to the largest batch seen.
BATCH_MAX = 64
#: Pings whose boxes hold more voxels than this on average go one launch each: at that size
#: a launch's fixed cost is small, and one launch per ping ran faster on an H100 (5 mm, tank:
#: Warp's per-voxel batch kernel 357 us per ping against its per-ping gather's 299 us,
#: bench/results/gpu_scale.json). OpenCL's per-voxel batch kernel ran faster than one launch per
#: ping there (4.5k pings/s against 2.5k): its backend reads OPENCL_BATCH_BOX_VOXELS_MAX instead.
BATCH_BOX_VOXELS_MAX = 16_000_000
OPENCL_BATCH_BOX_VOXELS_MAX = 1 << 40

#: Threads that fill a GPU batch's staging buffer, and the bytes from which they are used.
COPY_THREADS = max(1, min(4, (os.cpu_count() or 1) // 2))
COPY_SPLIT_BYTES = 4 << 20

#: The knobs above that a run may set (on this module, or on :mod:`gpumap.backends`, which
#: passes them on): read here when they are used, never copied.
TUNABLES = ("GPU_CHUNK", "CPU_CHUNK", "CPU_THREADS", "BATCH_MAX", "BATCH_BOX_VOXELS_MAX",
            "OPENCL_BATCH_BOX_VOXELS_MAX", "COPY_THREADS", "COPY_SPLIT_BYTES")


def block_runs(slots) -> tuple[np.ndarray | None, np.ndarray, np.ndarray, np.ndarray]:
    """``slots`` sorted and cut into runs of consecutive slots: (order, or None where ``slots`` are
    sorted already; the sorted slots; each run's first and past-last position in them)."""
    s = np.asarray(slots, np.int64).reshape(-1)
    order = None
    if len(s) > 1 and np.any(s[1:] < s[:-1]):
        order = np.argsort(s, kind="stable")
        s = s[order]
    if not len(s):
        return None, s, np.zeros(0, np.int64), np.zeros(0, np.int64)
    cut = np.flatnonzero(np.diff(s) != 1) + 1
    starts = np.concatenate([[0], cut]).astype(np.int64)
    return order, s, starts, np.concatenate([cut, [len(s)]]).astype(np.int64)


def check_device_index(index, count: int, backend: str) -> int:
    """``index`` (None: 0) checked against the ``count`` devices ``backend`` can run on here: the
    device a backend takes, never another (a ``ValueError`` names what there is)."""
    if index is None:
        return 0
    if isinstance(index, bool) or not isinstance(index, (int, np.integer)) or index < 0:
        raise ValueError(f"Expected device_index to be a non-negative integer or None, but got {index!r}")
    if index >= count:
        have = f"devices 0 to {count - 1}" if count > 1 else "device 0 only" if count else "no device"
        raise ValueError(f"Expected a device_index that {backend} has here ({have}), but got {int(index)}")
    return int(index)


@functools.cache
def _cpu_pool():
    """One worker thread, shared by every warp-cpu mapper, for the second half of a gather."""
    from concurrent.futures import ThreadPoolExecutor

    return ThreadPoolExecutor(1, thread_name_prefix="gpumap-cpu")


@functools.cache
def _copy_pool():
    """Threads for filling page-locked staging buffers (NumPy copies release the GIL)."""
    from concurrent.futures import ThreadPoolExecutor

    return ThreadPoolExecutor(COPY_THREADS, thread_name_prefix="gpumap-copy")


def _copy_rows(dst: np.ndarray, src: np.ndarray) -> None:
    """``dst[...] = src`` along the first axis, on COPY_THREADS threads when it is large."""
    n = src.shape[0]
    if COPY_THREADS < 2 or src.nbytes < COPY_SPLIT_BYTES or n < 2:
        np.copyto(dst, src)
        return
    cuts = np.linspace(0, n, min(n, COPY_THREADS) + 1).astype(int)
    pool = _copy_pool()
    futs = [pool.submit(np.copyto, dst[a:b], src[a:b]) for a, b in zip(cuts[:-1], cuts[1:], strict=True)]
    for f in futs:
        f.result()


class GridTooLargeError(ValueError):
    """The map does not fit in the memory a backend can allocate (the message says how much)."""


class Backend:
    """Owns one mapper's map storage and the per-ping device buffers.

    The map lives in a *pool* of ``cap`` blocks of ``V = B B Bz`` voxels (slot ``s`` holds voxels
    ``[s V, (s + 1) V)``, local order ``(i, j, k)``, ``k`` fastest): ``grid`` float32
    (the min over every view, ``+inf`` never observed), and for the visible and evidence rules
    ``bright`` float32 and ``count`` uint64 (two packed view counts), plus a ``seen`` byte per
    slot. A dense coarse *index* (int32 per block of a box, -1 none) maps a block to its slot;
    the kernels address every voxel through it (:func:`gpumap.kernels.minmax.gather_column`).
    The host (the mapper) decides which blocks exist: all of a bounded box up front, or those a
    ping can reach.
    """

    name: str
    device: str
    #: The knob of this module that caps the boxes a batch kernel folds (see BATCH_BOX_VOXELS_MAX).
    batch_box_knob = "BATCH_BOX_VOXELS_MAX"

    def _setup_pool(self, visible: bool, B: int, Bz: int | None) -> None:
        Bz = B if Bz is None else Bz
        self.visible, self.B, self.Bz, self.BV = visible, B, Bz, B * B * Bz
        self.cap = 0
        self.blk_lo = np.zeros(3, np.int32)
        self.blk_n = np.zeros(3, np.int32)

    def _block_params(self, params: np.ndarray) -> None:
        params["blk_lo"] = self.blk_lo
        params["blk_n"] = self.blk_n
        params["blk"] = self.B
        params["blk_z"] = self.Bz

    def grow(self, cap: int) -> None:
        """Make room for ``cap`` slots (new ones never observed), keeping the first ``self.cap``."""
        raise NotImplementedError

    def set_index(self, index: np.ndarray, lo_voxel: np.ndarray) -> None:
        """Replace the coarse index with ``index`` ((n0, n1, n2) int32 slots, -1 none) whose first
        block starts at voxel ``lo_voxel`` ((3,) int)."""
        self.blk_lo = np.asarray(lo_voxel, np.int32).copy()
        self.blk_n = np.asarray(index.shape, np.int32)
        self._upload_index(np.ascontiguousarray(index, np.int32).ravel())

    def _upload_index(self, flat: np.ndarray) -> None:
        raise NotImplementedError

    def set_blocks(self, slots: np.ndarray, lins: np.ndarray) -> None:
        """``index[lins] = slots`` ((n,) int32 each); each slot >= 0 becomes a never-observed
        block (seen 0); slot -1 frees the entry."""
        raise NotImplementedError

    def integrate(self, params: np.ndarray, image: np.ndarray, method: str, n_threads: int) -> None:
        """Apply one ping. ``image`` is (n_bins, n_beams) uint8 or float32 in [0, 1]."""
        raise NotImplementedError

    def integrate_batch(
        self, params: np.ndarray, images: np.ndarray, method: str, n_threads: np.ndarray
    ) -> None:
        """Apply B pings: ``params`` (B,) PING_DTYPE, ``images`` (B, n_bins, n_beams) uint8 or
        float32, ``n_threads`` (B,) ints. The same map as B calls of :meth:`integrate`: with
        ``batch_kernels`` (GPUs; tests may set it on warp-cpu) groups of pings whose boxes overlap
        go to ``_launch_batch``, else the pings are applied one by one."""
        # batch_kernels: only backends with a _launch_batch have it
        fold = getattr(self, "batch_kernels", False) and method == "gather"
        if not fold or not _fold_in_batches(params, n_threads, globals()[self.batch_box_knob]):
            for b in range(params.shape[0]):
                self.integrate(params[b, ...], images[b], method, int(n_threads[b]))
            return
        _check_rule(params[0, ...], self.visible)
        params["chunk"] = self.chunk
        for b0, b1 in _union_groups(params, n_threads):
            self._launch_batch(params[b0:b1], images[b0:b1], n_threads[b0:b1])

    def _next_batch(self, params: np.ndarray) -> tuple[int, dict, int]:
        """For a batch of ``params`` (block fields filled here): its size, the batch buffers
        (``_batch_buffers``) and the host slot it fills (batch k+1's while batch k's upload may
        still run)."""
        B = params.shape[0]
        self._block_params(params)
        bb = self._batch_buffers(B)
        s = bb["slot"]
        bb["slot"] = 1 - s
        return B, bb, s

    def read(self) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
        """Copies of the pool: ``grid`` (cap B B Bz,) float32, ``bright`` and ``count`` (visible
        rule; None for the plain rule)."""
        raise NotImplementedError

    def write(self, grid: np.ndarray, bright: np.ndarray | None, count: np.ndarray | None) -> None:
        """Replace the whole pool (arrays as :meth:`read` gives them)."""
        raise NotImplementedError

    def read_blocks(self, slots: np.ndarray) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
        """Copies of blocks ``slots``: ``grid`` and for the visible rule ``bright`` and ``count``,
        (n, B B Bz) each (None for the plain rule)."""
        rows = np.asarray(slots, np.int64)
        return tuple(None if a is None else a.reshape(-1, self.BV)[rows] for a in self.read())

    def write_blocks(self, slots: np.ndarray, grid, bright, count) -> None:
        """Blocks ``slots`` take these values ((n, B B Bz) each) and are marked seen."""
        g, b, c = self.read()
        rows = np.asarray(slots, np.int64)
        g.reshape(-1, self.BV)[rows] = np.asarray(grid).reshape(-1, self.BV)
        if self.visible:
            b.reshape(-1, self.BV)[rows] = np.asarray(bright).reshape(-1, self.BV)
            c.reshape(-1, self.BV)[rows] = np.asarray(count).reshape(-1, self.BV)
        seen = self.read_seen()
        seen[slots] = 1
        self.write(g, b, c)
        self._write_seen(seen)

    # Blocks by runs of consecutive slots (device backends: _copy_out / _copy_in move one run, so a
    # read or write of some blocks moves those blocks only, never the whole pool)
    def _pool_arrays(self) -> tuple[str, ...]:
        return ("grid", "bright", "count") if self.visible else ("grid",)

    def _read_runs(self, slots: np.ndarray) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
        order, ss, starts, ends = block_runs(slots)
        out = []
        for name, dt in zip(("grid", "bright", "count"), (np.float32, np.float32, np.uint64), strict=True):
            if name not in self._pool_arrays():
                out.append(None)
                continue
            got = np.empty((len(ss), self.BV), dt)
            for a, b in zip(starts.tolist(), ends.tolist(), strict=True):
                self._copy_out(name, int(ss[a]) * self.BV, got[a:b].reshape(-1))
            self._copies_done()
            if order is not None:  # back to the order asked for
                back = np.empty_like(got)
                back[order] = got
                got = back
            out.append(got)
        return tuple(out)

    def _write_runs(self, slots: np.ndarray, grid, bright, count) -> None:
        order, ss, starts, ends = block_runs(slots)
        for name, a_, dt in zip(("grid", "bright", "count"), (grid, bright, count),
                                (np.float32, np.float32, np.uint64), strict=True):
            if name not in self._pool_arrays():
                continue
            src = np.asarray(a_, dt).reshape(-1, self.BV)
            src = np.ascontiguousarray(src if order is None else src[order])
            for a, b in zip(starts.tolist(), ends.tolist(), strict=True):
                self._copy_in(name, int(ss[a]) * self.BV, src[a:b].reshape(-1))
            self._copies_done()
        seen = self.read_seen()
        seen[np.asarray(slots, np.int64)] = 1
        self._write_seen(seen)

    def copy_blocks_from(self, other: Backend, slots: np.ndarray) -> None:
        """Blocks ``slots`` of ``other`` (a backend of the same block shape and rule) become the
        same slots here, marked seen; through the host (Warp: device to device)."""
        self.write_blocks(slots, *other.read_blocks(slots))

    def _copy_out(self, name: str, offset: int, out: np.ndarray) -> None:
        """Copy ``len(out)`` values of pool array ``name`` from element ``offset`` into ``out``."""
        raise NotImplementedError

    def _copy_in(self, name: str, offset: int, src: np.ndarray) -> None:
        """Copy ``src`` into pool array ``name`` from element ``offset`` (``src`` kept until done)."""
        raise NotImplementedError

    def _copies_done(self) -> None:
        """Wait for the copies of ``_copy_out`` / ``_copy_in`` queued so far."""
        self.synchronize()

    def read_seen(self) -> np.ndarray:
        """(cap,) uint8 copy: 1 where a kernel has observed a voxel of the slot's block."""
        raise NotImplementedError

    def _write_seen(self, seen: np.ndarray) -> None:
        raise NotImplementedError

    def read_err(self) -> int:
        """1 if a kernel met an observed voxel without a block (a bug), else 0."""
        raise NotImplementedError

    def synchronize(self) -> None:
        pass


def _check_rule(params: np.ndarray, visible: bool) -> None:
    """A backend built without the visible rule's evidence must never run its update (the
    kernels would write past one-element stand-in buffers)."""
    if int(params["rule"]) != 0 and not visible:
        raise ValueError(
            "Expected a backend built with visible=True for rule='visible' or 'evidence' parameters")


def _fold_in_batches(params: np.ndarray, n_threads: np.ndarray, box_max: float) -> bool:
    """Whether the batch kernels pay off for these pings (boxes of ``box_max`` voxels at most on
    average: see BATCH_BOX_VOXELS_MAX)."""
    live = n_threads > 0
    if not live.any():
        return False
    vol = np.prod(params["box_n"][live].astype(np.float64), axis=1)
    return float(vol.mean()) <= box_max


def _union_groups(params: np.ndarray, n_threads: np.ndarray, slack: float = 2.0) -> list[tuple[int, int]]:
    """Split a batch into runs of pings whose boxes' union box holds at most ``slack`` times
    the voxels of the boxes themselves (far-apart pings would make threads walk empty space), and
    at most BATCH_MAX pings. Greedy from the first ping, as a loop over the pings would cut them,
    in whole-array passes: one per run (a batch of nearby pings is one run)."""
    lo = params["box_lo"].astype(np.int64)
    hi = lo + params["box_n"].astype(np.int64)
    live = np.flatnonzero((n_threads > 0) & (np.prod(hi - lo, axis=1) > 0))
    if not live.size:
        return []
    vol = np.prod(hi[live] - lo[live], axis=1).astype(np.float64)
    out, start, i = [], 0, 0  # i: the run's first live ping (in live)
    while True:
        # the union box and the boxes' voxels of live pings i, i+1, ..., as each joins the run
        ulo = np.minimum.accumulate(lo[live[i:]], axis=0)
        uhi = np.maximum.accumulate(hi[live[i:]], axis=0)
        span = np.prod((uhi - ulo).astype(np.float64), axis=1)
        cut = (span > slack * np.cumsum(vol[i:])) | (live[i:] - start >= BATCH_MAX)
        cut[0] = False  # a run's first ping always joins it
        k = int(np.argmax(cut))
        if not cut[k]:
            out.append((start, params.shape[0]))
            return out
        b = int(live[i + k])
        out.append((start, b))
        start, i = b, i + k
