"""Compute backends: where map values live and how a ping is applied to them.

Each backend holds one map as a pool of blocks of ``B x B x Bz`` voxels and a coarse index over
them (:class:`Backend`: float32 values, ``+inf`` = unknown) and applies
``integrate(params, image, method)`` to it. ``numpy`` is the reference
(:mod:`gpumap.reference`); ``warp-cpu``/``warp-cuda`` and ``opencl`` run the kernels in
``gpumap.kernels`` (``minmax.py`` and its twin ``minmax.cl``). Everything a ping needs on
the device is allocated once, in the constructor; programs are compiled once per process
(Warp caches modules on disk, OpenCL programs are cached per context).
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import logging
import os
import sys
import threading
from importlib import resources

import numpy as np

from gpumap.errors import BackendUnavailableError
from gpumap.geometry import MAX_TABLE_LEVELS, PING_DTYPE, beam_lut, beam_tan_edges
from gpumap.spec import SonarSpec

log = logging.getLogger("gpumap")

BACKENDS = ("numpy", "warp-cpu", "warp-cuda", "opencl", "opencl-gpu", "opencl-cpu")
AUTO_ORDER = ("warp-cuda", "opencl-gpu", "opencl-cpu", "warp-cpu", "numpy")


def table_size(spec: SonarSpec) -> int:
    """Floats in a per-ping max table: its levels plus two scratch planes."""
    return (min(spec.n_beams.bit_length(), MAX_TABLE_LEVELS) + 2) * spec.n_bins * spec.n_beams


U8_SCALE = np.float32(1.0 / 255.0)  # 8-bit pings: intensity = byte * U8_SCALE, on every backend
# Image upload slots: the host may prepare this many pings ahead of the device.
N_SLOTS = 4
GPU_CHUNK = 16  # voxels of a column per gather thread on GPUs
#: Threads a CPU backend's gather may use (warp-cpu splits its launch; PoCL uses every core).
CPU_THREADS = min(2, os.cpu_count() or 1)
CPU_CHUNK = 1 << 30  # on CPUs, the whole column


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


#: Threads that fill a GPU batch's staging buffer, and the bytes from which they are used.
COPY_THREADS = max(1, min(4, (os.cpu_count() or 1) // 2))
COPY_SPLIT_BYTES = 4 << 20


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
        if not fold or not _fold_in_batches(params, n_threads):
            for b in range(params.shape[0]):
                self.integrate(params[b, ...], images[b], method, int(n_threads[b]))
            return
        _check_rule(params[0, ...], self.visible)
        params["chunk"] = self.chunk
        for b0, b1 in _union_groups(params, n_threads):
            self._launch_batch(params[b0:b1], images[b0:b1], n_threads[b0:b1])

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


class NumpyBackend(Backend):
    """The oracle: :mod:`gpumap.reference`'s per-voxel code, addressed through the index as the
    kernels are."""

    name = "numpy"
    device = "cpu (NumPy reference)"

    def __init__(self, spec, template_S, use_table=None, *, visible=False, B=8, Bz=None, cap=0):
        self._setup_pool(visible, B, Bz)
        self.buf = np.empty(spec.image_shape, np.float32)
        self.edges = beam_tan_edges(spec)
        self.template = template_S
        self.grid = np.empty(0, np.float32)
        self.bright = np.empty(0, np.float32) if visible else None
        self.count = np.empty(0, np.uint64) if visible else None
        self.seen = np.empty(0, np.uint8)
        self.index = np.empty(0, np.int32)
        self.err = 0
        self.grow(cap)

    def grow(self, cap):
        n = (cap - self.cap) * self.BV
        self.grid = np.concatenate([self.grid, np.full(n, np.inf, np.float32)])
        if self.visible:
            self.bright = np.concatenate([self.bright, np.full(n, np.inf, np.float32)])
            self.count = np.concatenate([self.count, np.zeros(n, np.uint64)])
        self.seen = np.concatenate([self.seen, np.zeros(cap - self.cap, np.uint8)])
        self.cap = cap

    def _upload_index(self, flat):
        self.index = flat.copy()

    def set_blocks(self, slots, lins):
        live = slots[slots >= 0].astype(np.int64)
        a = (live[:, None] * self.BV + np.arange(self.BV)).ravel()
        self.grid[a] = np.inf
        if self.visible:
            self.bright[a] = np.inf
            self.count[a] = 0
        self.seen[live] = 0
        self.index[lins] = slots

    def _address(self, idx: np.ndarray) -> np.ndarray:
        """(m, 3) voxel indices -> (m,) pool addresses (-1: no block), marking blocks seen."""
        B, Bz = self.B, self.Bz
        rel = idx - self.blk_lo.astype(np.int64)
        b = rel // np.array([B, B, Bz])
        inside = np.all((rel >= 0) & (b < self.blk_n), axis=1)
        slot = np.full(len(idx), -1, np.int64)
        nb = self.blk_n.astype(np.int64)
        slot[inside] = self.index[(b[inside, 0] * nb[1] + b[inside, 1]) * nb[2] + b[inside, 2]]
        ok = slot >= 0
        w = rel - b * np.array([B, B, Bz])
        out = np.where(ok, slot * self.BV + (w[:, 0] * B + w[:, 1]) * Bz + w[:, 2], -1)
        self.seen[slot[ok]] = 1
        return out

    def integrate(self, params, image, method, n_threads):
        from gpumap import reference

        _check_rule(params, self.visible)
        if image.dtype == np.uint8:
            image = np.multiply(image, U8_SCALE, out=self.buf)
        self._block_params(params)
        if method == "gather":
            state = (self.bright, self.count) if self.visible else None
            if not reference.integrate_gather(params, image, self.edges, self.grid, state, self._address):
                self.err = 1
        else:
            reference.integrate_template(params, image, self.edges, self.template, self.grid, self._address)

    def read(self):
        if not self.visible:
            return self.grid.copy(), None, None
        return self.grid.copy(), self.bright.copy(), self.count.copy()

    def write(self, grid, bright, count):
        self.grid[...] = grid
        if self.visible:
            self.bright[...] = bright
            self.count[...] = count

    def read_blocks(self, slots):  # the pool is host memory: only these blocks are copied, by rows
        rows = np.asarray(slots, np.int64)
        if not self.visible:
            return self.grid.reshape(-1, self.BV)[rows], None, None
        return tuple(a.reshape(-1, self.BV)[rows] for a in (self.grid, self.bright, self.count))

    def write_blocks(self, slots, grid, bright, count):  # in place, by rows
        rows = np.asarray(slots, np.int64)
        self.grid.reshape(-1, self.BV)[rows] = np.asarray(grid).reshape(-1, self.BV)
        if self.visible:
            self.bright.reshape(-1, self.BV)[rows] = np.asarray(bright).reshape(-1, self.BV)
            self.count.reshape(-1, self.BV)[rows] = np.asarray(count).reshape(-1, self.BV)
        self.seen[rows] = 1

    def read_seen(self):
        return self.seen.copy()

    def _write_seen(self, seen):
        self.seen[...] = seen

    def read_err(self):
        return self.err


# ----------------------------------------------------------------------------- Warp
@functools.cache
def _warp():
    try:
        import warp as wp
    except Exception as e:  # pragma: no cover - depends on the machine
        raise BackendUnavailableError(f"warp-lang cannot be imported: {e!r}") from e
    wp.config.log_level = wp.LOG_WARNING  # no banner on import
    wp.config.enable_backward = False  # no adjoints: halves compile time
    # Without a CUDA driver Warp's native code prints "Could not find or load the NVIDIA CUDA
    # driver" on stderr at init, on every command of a CPU machine: keep it quiet there (asking
    # for warp-cuda by name still says why it cannot run, see WarpBackend).
    with _native_stderr_quiet(not cuda_driver_loadable()):
        wp.init()
    from gpumap.kernels import minmax

    return wp, minmax


@functools.cache
def cuda_driver_loadable() -> bool:
    """Whether the NVIDIA CUDA driver library can be loaded here (Warp needs it for warp-cuda)."""
    for name in ("nvcuda.dll",) if os.name == "nt" else ("libcuda.so.1", "libcuda.so"):
        try:
            ctypes.CDLL(name)
            return True
        except OSError:
            continue
    return False


@contextlib.contextmanager
def _native_stderr_quiet(quiet: bool):
    """Send what native code writes to file descriptor 2 to /dev/null while inside (if ``quiet``)."""
    if not quiet:
        yield
        return
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 2)
            try:
                yield
            finally:
                os.dup2(saved, 2)
    finally:
        os.close(saved)


def _warp_params(minmax, p: np.ndarray):
    """A Warp ``PingParams`` holding the PING_DTYPE record ``p``.

    Every field of both is 4 bytes, in the same order, so the struct's ctypes image is the
    record byte for byte: one copy fills it (the sizes are checked; a drift raises).
    """
    s = minmax.PingParams()
    if ctypes.sizeof(s._ctype) != PING_DTYPE.itemsize:
        raise RuntimeError(
            f"PingParams is {ctypes.sizeof(s._ctype)} bytes in Warp but {PING_DTYPE.itemsize} in "
            "PING_DTYPE: the two layouts have drifted apart"
        )
    ctypes.memmove(ctypes.addressof(s._ctype), p.ctypes.data, PING_DTYPE.itemsize)
    return s


def build_table_host(
    image: np.ndarray,
    win: int,
    n_levels: int,
    table: np.ndarray,
    rows: np.ndarray,
    scratch: np.ndarray | None = None,
    pool=None,
) -> None:
    """The per-ping max table in NumPy (CPUs): what ``build_bin_window`` and
    ``build_beam_levels`` make, in a dozen whole-image passes instead of a strided walk.

    ``table`` is (n_levels, n_bins, n_beams) float32, written in place; ``rows`` (n_bins,)
    int: for each bin i, ``max(min(i + win - 1, n_bins - 1) - 2^k + 1, i)`` with ``2^k`` the
    largest power of two <= win (:func:`table_rows`). A uint8 ``image`` is maximised as bytes
    in ``scratch`` (same shape as ``table``, uint8; a quarter of the memory traffic) and then
    scaled: ``byte * U8_SCALE`` is monotonic, so the max of the scaled bytes is the scaled max.
    With a ``pool`` (an executor with a free worker) the passes run on two threads: level 0 by
    halves of the beams, the beam levels by halves of the bins (NumPy releases the GIL).
    Maxima are exact, so the values are the kernels' bit for bit.
    """
    lv = table if image.dtype != np.uint8 else scratch
    n, nj = image.shape

    def bins(c0: int, c1: int) -> None:  # level 0 of beams [c0, c1)
        s = lv[0, :, c0:c1]
        s[...] = image[:, c0:c1]
        w = 1
        while 2 * w <= win:  # s[i] = max over bins [i, i + 2w - 1] (clipped)
            np.maximum(s[: n - w], s[w:], out=s[: n - w])
            w *= 2
        # two overlapping spans of w cover [i, min(i + win - 1, n - 1)]
        np.maximum(s, s[rows], out=s)

    def beams(r0: int, r1: int) -> None:  # levels 1.. of bins [r0, r1), then the scaling
        step = 1
        for k in range(1, n_levels):  # beam spans of 2^k (clipped at the last beam)
            prev, cur = lv[k - 1, r0:r1], lv[k, r0:r1]
            np.maximum(prev[:, :-step], prev[:, step:], out=cur[:, :-step])
            np.maximum(prev[:, -step:], prev[:, -1:], out=cur[:, -step:])
            step *= 2
        if lv is not table:
            np.multiply(lv[:, r0:r1], U8_SCALE, out=table[:, r0:r1])

    if pool is None:
        bins(0, nj)
        beams(0, n)
        return
    for fn, size in ((bins, nj), (beams, n)):
        fut = pool.submit(fn, size // 2, size)
        try:
            fn(0, size // 2)
        finally:
            fut.result()


def table_rows(n_bins: int, win: int) -> np.ndarray:
    """The second read of :func:`build_table_host`'s level 0, per bin."""
    w = 1 << (max(1, win).bit_length() - 1)
    i = np.arange(n_bins)
    return np.maximum(np.minimum(i + win - 1, n_bins - 1) - w + 1, i)


#: Pings a GPU folds per launch (more are split); buffers grow to the largest batch seen.
BATCH_MAX = 64
#: Pings whose boxes hold more voxels than this on average go one launch each: at that size
#: a launch's fixed cost is small, and one launch per ping ran faster on an H100 (5 mm, tank).
BATCH_BOX_VOXELS_MAX = 16_000_000


def _fold_in_batches(params: np.ndarray, n_threads: np.ndarray) -> bool:
    """Whether the batch kernels pay off for these pings (see BATCH_BOX_VOXELS_MAX)."""
    live = n_threads > 0
    if not live.any():
        return False
    vol = np.prod(params["box_n"][live].astype(np.float64), axis=1)
    return float(vol.mean()) <= BATCH_BOX_VOXELS_MAX


def _union_groups(params: np.ndarray, n_threads: np.ndarray, slack: float = 2.0) -> list[tuple[int, int]]:
    """Split a batch into runs of pings whose boxes' union box holds at most ``slack`` times
    the voxels of the boxes themselves (far-apart pings would make threads walk empty space)."""
    lo = params["box_lo"].astype(np.int64)
    hi = lo + params["box_n"].astype(np.int64)
    vol = np.where(n_threads > 0, np.prod(hi - lo, axis=1), 0)
    out, start = [], 0
    ulo, uhi, total = None, None, 0
    for b in range(params.shape[0]):
        if vol[b] == 0:
            continue
        nlo = lo[b] if ulo is None else np.minimum(ulo, lo[b])
        nhi = hi[b] if uhi is None else np.maximum(uhi, hi[b])
        if ulo is not None and (np.prod(nhi - nlo) > slack * (total + vol[b]) or b - start >= BATCH_MAX):
            out.append((start, b))
            start, nlo, nhi, total = b, lo[b], hi[b], 0
        ulo, uhi, total = nlo, nhi, total + vol[b]
    if ulo is not None:
        out.append((start, params.shape[0]))
    return out


class WarpBackend(Backend):
    def __init__(self, spec, template_S, use_table=None, device="cpu", *, visible=False, B=8, Bz=None, cap=0):
        n_bins, n_beams = spec.image_shape
        wp, minmax = _warp()
        if device == "cuda" and not wp.is_cuda_available():
            why = "" if cuda_driver_loadable() else " (the NVIDIA CUDA driver, libcuda, cannot be loaded)"
            raise BackendUnavailableError(f"warp-cuda needs a CUDA device, and Warp finds none here{why}")
        self._setup_pool(visible, B, Bz)
        self.wp, self.k = wp, minmax
        self.dev = wp.get_device("cuda:0" if device == "cuda" else "cpu")
        self.name = f"warp-{device}"
        self.device = f"{self.dev.alias} ({self.dev.name})"
        self.n_bins, self.n_beams = n_bins, n_beams
        with wp.ScopedDevice(self.dev):
            # the pool (grown below) and the index; the visible rule's evidence stays empty for
            # the plain rule (its kernels never touch it)
            self.grid = wp.empty(0, dtype=float)
            self.bright = wp.empty(0, dtype=float)
            self.count = wp.empty(0, dtype=wp.uint64)
            self.seen = wp.empty(0, dtype=wp.uint8)
            self.index = wp.full(1, value=-1, dtype=int)
            self.err = wp.zeros(1, dtype=int)
            self.first_bright = wp.zeros(n_beams, dtype=int)
            self.edges = wp.array(beam_tan_edges(spec), dtype=float)
            self.lut = wp.array(beam_lut(spec), dtype=int)
            self.image = wp.empty((n_bins, n_beams), dtype=float)
            self.template = wp.array(template_S, dtype=wp.vec3) if template_S is not None else None
            # The per-ping max table: two reads per voxel instead of a loop over cells.
            # Same answers either way; footprint_max="loop" turns it off.
            self.use_table = True if use_table is None else bool(use_table)
            # GPUs want short chunks of a column per thread (enough threads in flight);
            # CPUs a whole column per thread (fewest threads).
            self.chunk = GPU_CHUNK if self.dev.is_cuda else CPU_CHUNK
            n_table = table_size(spec) if self.use_table else 0
            self.table = wp.empty(n_table, dtype=float)
        # N_SLOTS page-locked staging buffers so the upload is a real async DMA on CUDA; a
        # buffer is refilled only after its previous copy has finished (event), so the
        # host can prepare ping k+1 while the GPU still works on ping k.
        self.staging = []
        self.events = []
        self._batch = None  # GPU batch buffers, allocated on the first batch
        self._pool = None
        # the visible rule's first bright bin per beam: a thread per cell on GPUs (512 serial
        # scans of a beam leave a GPU idle), per beam on CPUs; tests may set it on CPUs
        self.first_bright_cells = self.dev.is_cuda
        # fold a batch in a few launches (GPUs); CPUs loop over integrate (tests may set it
        # on warp-cpu to run the batch kernels there)
        self.batch_kernels = self.dev.is_cuda
        if self.dev.is_cuda:
            self.staging = [
                wp.empty((n_bins, n_beams), dtype=float, device="cpu", pinned=True) for _ in range(N_SLOTS)
            ]
            self.events = [None] * N_SLOTS
            self.staging_np = [a.numpy() for a in self.staging]
            # 8-bit pings travel as bytes (a quarter of the PCIe traffic), widened on the GPU
            self.staging_u8 = [
                wp.empty((n_bins, n_beams), dtype=wp.uint8, device="cpu", pinned=True) for _ in range(N_SLOTS)
            ]
            self.staging_u8_np = [a.numpy() for a in self.staging_u8]
            self.image_u8 = wp.empty((n_bins, n_beams), dtype=wp.uint8, device=self.dev)
            self.cmd_u8 = wp.launch(
                minmax.convert_u8,
                dim=(n_bins, n_beams),
                inputs=[self.image_u8, float(U8_SCALE), self.image],
                device=self.dev,
                record_cmd=True,
            )
        else:
            # CPUs: the max table in NumPy (whole-image passes), and the gather split in two
            # halves of the box's rows run on two threads (Warp's CPU kernels are serial; the
            # launch releases the GIL). Each half owns its voxels: the same map as one launch.
            if self.use_table:
                nl = min(n_beams.bit_length(), MAX_TABLE_LEVELS)
                self.table_np = self.table.numpy()[: nl * n_bins * n_beams].reshape(nl, n_bins, n_beams)
                self.table_u8 = np.empty(self.table_np.shape, np.uint8)
            self._rows = {}
            self._pool = _cpu_pool() if CPU_THREADS > 1 else None
        self.slot = 0
        self._cmds = None
        self._init_cmd = None
        self.istage, self.ievents, self.islot, self.ipairs = [None] * N_SLOTS, [None] * N_SLOTS, 0, None
        self.image_np = None if self.dev.is_cuda else self.image.numpy()
        self.grow(cap)
        wp.load_module(minmax, device=self.dev)  # compile (or load from cache) now, not on ping 1

    # ------------------------------------------------------------------ the pool
    def grow(self, cap):
        wp = self.wp
        n_old = self.cap * self.BV
        with wp.ScopedDevice(self.dev):
            names = [("grid", wp.full, np.inf, float), ("seen", wp.zeros, None, wp.uint8)]
            if self.visible:
                names += [("bright", wp.full, np.inf, float), ("count", wp.zeros, None, wp.uint64)]
            for name, make, fill, dt in names:
                n = cap if name == "seen" else cap * self.BV
                new = make(n, value=fill, dtype=dt) if fill is not None else make(n, dtype=dt)
                old_n = self.cap if name == "seen" else n_old
                if old_n:
                    wp.copy(new, getattr(self, name), count=old_n)
                setattr(self, name, new)
        self.cap = cap
        self._cmds = self._init_cmd = None  # recorded launches hold the old arrays

    def _upload_index(self, flat):
        self.index = self.wp.array(flat, dtype=int, device=self.dev)
        self._cmds = self._init_cmd = None

    def _stage_pairs(self, slots: np.ndarray, lins: np.ndarray):
        """(slots, lins) as one int32 device array: on CUDA through a ring of pinned buffers
        (an async copy, refilled only once its last copy is done), so the host never waits."""
        wp = self.wp
        n = len(slots)
        if not self.dev.is_cuda:
            return wp.array(np.concatenate([slots, lins]).astype(np.int32), dtype=int, device=self.dev)
        k = self.islot
        self.islot = (k + 1) % N_SLOTS
        if self.ievents[k] is not None:
            wp.synchronize_event(self.ievents[k])
        if self.istage[k] is None or self.istage[k].shape[0] < 2 * n:
            self.istage[k] = wp.empty(max(2 * n, 4096), dtype=int, device="cpu", pinned=True)
        host = self.istage[k].numpy()
        host[:n] = slots
        host[n : 2 * n] = lins
        if self.ipairs is None or self.ipairs.shape[0] < 2 * n:
            self.ipairs = wp.empty(max(2 * n, 4096), dtype=int, device=self.dev)
        wp.copy(self.ipairs, self.istage[k], count=2 * n)
        self.ievents[k] = wp.record_event()
        return self.ipairs

    def set_blocks(self, slots, lins):
        n = len(slots)
        if n == 0:
            return
        pairs = self._stage_pairs(slots, lins)
        if self._init_cmd is None or self._init_cmd[0] is not pairs:
            args = [pairs, n, self.BV, int(self.visible), float(np.inf), self.index, self.grid, self.bright,
                    self.count, self.seen]
            cmd = self.wp.launch(self.k.init_blocks, dim=n * self.BV, inputs=args, device=self.dev,
                                 record_cmd=True)
            self._init_cmd = (pairs, cmd)
        cmd = self._init_cmd[1]
        cmd.set_param_by_name("n", n)
        cmd.set_dim(n * self.BV)
        cmd.launch()

    def read(self):
        g = self.grid.numpy().copy()
        if not self.visible:
            return g, None, None
        return g, self.bright.numpy().copy(), self.count.numpy().copy()

    def write(self, grid, bright, count):
        wp, dev = self.wp, self.dev
        self.grid.assign(wp.array(np.ascontiguousarray(grid, np.float32), dtype=float, device=dev))
        if self.visible:
            self.bright.assign(wp.array(np.ascontiguousarray(bright, np.float32), dtype=float, device=dev))
            self.count.assign(wp.array(np.ascontiguousarray(count, np.uint64), dtype=wp.uint64, device=dev))

    def read_blocks(self, slots):
        if self.dev.is_cuda:
            return super().read_blocks(slots)
        rows = np.asarray(slots, np.int64)  # CPU arrays: rows straight from the pool, no whole copy
        if not self.visible:
            return self.grid.numpy().reshape(-1, self.BV)[rows], None, None
        return tuple(a.numpy().reshape(-1, self.BV)[rows] for a in (self.grid, self.bright, self.count))

    def read_seen(self):
        return self.seen.numpy().copy()

    def _write_seen(self, seen):
        self.seen.assign(self.wp.array(seen, dtype=self.wp.uint8, device=self.dev))

    def read_err(self):
        return int(self.err.numpy()[0])

    # ------------------------------------------------------------------ pings
    def integrate(self, params, image, method, n_threads):
        _check_rule(params, self.visible)
        if self.staging or not (method == "gather" and not n_threads):
            warp_upload_image(self, image)
        if method == "gather" and not n_threads:
            return
        params["chunk"] = self.chunk
        self._block_params(params)
        if self._cmds is None:
            self._record(params)
        # The recorded launches hold the struct's ctypes memory: refresh it in one copy.
        ctypes.memmove(self._P_addr, params.ctypes.data, PING_DTYPE.itemsize)
        for cmd in self._cmds["table"]:
            cmd.launch()
        if not self.dev.is_cuda and self.use_table:
            warp_host_table(self, params, image)
        cmd = self._cmds[method]
        if method != "gather":
            cmd.launch()
            return
        n_chunks = -(-int(params["box_n"][2]) // self.chunk)
        n0 = int(params["box_n"][0])
        if self._pool is None or self.dev.is_cuda or n0 < 2 or n_threads < 64:
            cmd.set_dim(n_threads * n_chunks)
            cmd.launch()
            return
        warp_launch_halves(self, params, cmd, self._cmd2, n_threads, n_chunks)

    def _record(self, params):
        """Record every launch once (``record_cmd``); a ping then only swaps the parameters.

        PingParams' fields are all 4 bytes in PING_DTYPE's order, so its ctypes image is
        byte for byte a PING_DTYPE record (checked here, once).
        """
        wp, k = self.wp, self.k
        P = _warp_params(k, params)
        if not (P._ctype.voxel == float(params["voxel"]) and P._ctype.chunk == int(params["chunk"])):
            raise RuntimeError("PingParams and PING_DTYPE disagree on the field layout")
        self._P = P
        self._P_addr = ctypes.addressof(P._ctype)
        rec = {"device": self.dev, "record_cmd": True}
        table = []
        if int(params["rule"]) != 0 and self.first_bright_cells:  # GPUs: a thread per cell
            nb, nj = int(params["n_bins"]), int(params["n_beams"])
            table += [
                wp.launch(k.first_bright_init, dim=nj, inputs=[P, self.first_bright], **rec),
                wp.launch(k.find_first_bright_cells, dim=(nb, nj), inputs=[P, self.image, self.first_bright],
                          **rec),
            ]
        elif int(params["rule"]) != 0:  # CPUs: a thread per beam, stopping at the first return
            table.append(
                wp.launch(
                    k.find_first_bright,
                    dim=int(params["n_beams"]),
                    inputs=[P, self.image, self.first_bright],
                    **rec,
                )
            )
        if self.use_table and self.dev.is_cuda:  # one thread per cell (CPUs: build_table_host)
            cells = (int(params["n_bins"]), int(params["n_beams"]))
            table += [
                wp.launch(k.build_bin_window_cells, dim=cells, inputs=[P, self.image, self.table], **rec),
                wp.launch(k.build_beam_levels_cells, dim=cells, inputs=[P, self.table], **rec),
            ]
        ping_args = [self.image, self.edges, self.lut, self.table, self.first_bright]
        gather_args = [*ping_args, self.index, self.grid, self.bright, self.count, self.seen, self.err]
        self._cmds = {
            "table": table,
            "gather": wp.launch(k.integrate_gather, dim=1, inputs=[P, *gather_args], **rec),
            "template": None
            if self.template is None
            else wp.launch(
                k.integrate_template,
                dim=self.template.shape[0],
                inputs=[P, *ping_args, self.template, self.index, self.grid, self.seen],
                **rec,
            ),
        }
        if not self.dev.is_cuda:  # the second half of a split gather has its own parameters
            self._P2 = _warp_params(k, params)
            self._P2_addr = ctypes.addressof(self._P2._ctype)
            self._cmd2 = wp.launch(k.integrate_gather, dim=1, inputs=[self._P2, *gather_args], **rec)

    # ------------------------------------------------------------------ batches (CUDA)
    def _batch_buffers(self, n: int) -> dict:
        """Device and pinned host buffers for up to ``n`` pings (grown to the next power of two)."""
        bb = self._batch
        if bb is not None and bb["cap"] >= n:
            return bb
        wp = self.wp
        pin = self.dev.is_cuda
        self.synchronize()  # old buffers may still be in flight
        cap = min(BATCH_MAX, 1 << (n - 1).bit_length())
        shape = (cap, self.n_bins, self.n_beams)
        n_table = self.table.shape[0]
        dev = self.dev
        bb = {
            "cap": cap,
            # two pinned host slots: batch k+1 is written while batch k's upload may run
            "host_u8": [wp.empty(shape, dtype=wp.uint8, device="cpu", pinned=pin) for _ in range(2)],
            "host_f": [wp.empty(shape, dtype=float, device="cpu", pinned=pin) for _ in range(2)],
            "host_P": [wp.empty(cap, dtype=self.k.PingParams, device="cpu", pinned=pin) for _ in range(2)],
            "host_box": [wp.empty((cap, 6), dtype=int, device="cpu", pinned=pin) for _ in range(2)],
            "boxes": wp.empty((cap, 6), dtype=int, device=dev),
            "events": [None, None],
            "slot": 0,
            "u8": wp.empty(shape, dtype=wp.uint8, device=dev),
            "images": wp.empty(shape, dtype=float, device=dev),
            "P": wp.empty(cap, dtype=self.k.PingParams, device=dev),
            "tables": wp.empty((cap, n_table), dtype=float, device=dev),
            "first_bright": wp.zeros((cap, self.n_beams), dtype=int, device=dev),
        }
        bb["host_u8_np"] = [a.numpy() for a in bb["host_u8"]]
        bb["host_f_np"] = [a.numpy() for a in bb["host_f"]]
        bb["host_box_np"] = [a.numpy() for a in bb["host_box"]]
        self._batch = bb
        return bb

    def _launch_batch(self, params, images, n_threads):
        wp, k = self.wp, self.k
        B = params.shape[0]
        self._block_params(params)
        bb = self._batch_buffers(B)
        s = bb["slot"]
        bb["slot"] = 1 - s
        if bb["events"][s] is not None:
            wp.synchronize_event(bb["events"][s])
        hp = bb["host_P"][s]
        ctypes.memmove(hp.ptr, params.ctypes.data, B * PING_DTYPE.itemsize)
        P = bb["P"][:B]
        wp.copy(P, hp[:B])
        hb = bb["host_box_np"][s]
        hb[:B, :3] = params["box_lo"]
        hb[:B, 3:] = params["box_n"]
        wp.copy(bb["boxes"], bb["host_box"][s], count=6 * B)
        imgs = bb["images"][:B]
        if images.dtype == np.uint8:
            _copy_rows(bb["host_u8_np"][s][:B], images)
            wp.copy(bb["u8"][:B], bb["host_u8"][s][:B])
            bb["events"][s] = wp.record_event() if self.dev.is_cuda else None
            wp.launch(k.convert_u8_batch, dim=images.shape, inputs=[bb["u8"][:B], float(U8_SCALE), imgs],
                      device=self.dev)
        else:
            _copy_rows(bb["host_f_np"][s][:B], images)
            wp.copy(imgs, bb["host_f"][s][:B])
            bb["events"][s] = wp.record_event() if self.dev.is_cuda else None
        fb = bb["first_bright"]  # (cap, ...): kernels index their B first rows only
        tables = bb["tables"]
        if int(params["rule"][0]) != 0:
            wp.launch(k.find_first_bright_batch, dim=(B, self.n_beams), inputs=[P, imgs, fb], device=self.dev)
        if self.use_table:
            cells = images.shape
            wp.launch(k.build_bin_window_cells_batch, dim=cells, inputs=[P, imgs, tables], device=self.dev)
            wp.launch(k.build_beam_levels_cells_batch, dim=cells, inputs=[P, tables], device=self.dev)
        live = n_threads > 0
        lo = params["box_lo"][live].min(axis=0)
        hi = (params["box_lo"] + params["box_n"])[live].max(axis=0)
        n = hi - lo
        n_chunks = -(-int(n[2]) // self.chunk)
        wp.launch(
            k.integrate_gather_batch,
            dim=int(n[0]) * int(n[1]) * n_chunks,
            inputs=[
                P, bb["boxes"], wp.vec3i(*lo.tolist()), wp.vec3i(*n.tolist()), self.chunk, imgs, self.edges,
                self.lut,
                tables, fb, self.index, self.grid, self.bright, self.count, self.seen, self.err,
            ],
            device=self.dev,
        )

    def synchronize(self) -> None:
        self.wp.synchronize_device(self.dev)


# ----------------------------------------------------------------------------- OpenCL
@functools.cache
def _opencl():
    try:
        import pyopencl as cl
    except Exception as e:  # pragma: no cover
        raise BackendUnavailableError(f"pyopencl cannot be imported: {e!r}") from e
    return cl


def opencl_devices(kind: str) -> list:
    """OpenCL devices of ``kind`` ('gpu', 'cpu' or 'any'), GPUs first."""
    cl = _opencl()
    try:
        platforms = cl.get_platforms()
    except cl.Error:
        return []
    out = []
    for p in platforms:
        try:
            devs = p.get_devices()
        except cl.Error:
            continue
        out.extend(devs)
    gpus = [d for d in out if d.type & cl.device_type.GPU]
    cpus = [d for d in out if not d.type & cl.device_type.GPU]
    return {"gpu": gpus, "cpu": cpus, "any": gpus + cpus}[kind]


# One context and one built program per OpenCL device, shared by every mapper on it: a
# context per mapper, kept alive by a program cache, leaked ~1.4 MB per mapper.
_CL_SHARED: dict[int, tuple] = {}
_CL_LOCK = threading.Lock()


def _opencl_context(device):
    """(context, program) for ``device``, built once per process."""
    cl = _opencl()
    key = int(device.int_ptr)
    with _CL_LOCK:
        if key not in _CL_SHARED:
            ctx = cl.Context([device])
            src = resources.files("gpumap.kernels").joinpath("minmax.cl").read_text()
            try:
                prg = cl.Program(ctx, src).build(options=["-cl-fp32-correctly-rounded-divide-sqrt"])
            except cl.Error:
                try:
                    prg = cl.Program(ctx, src).build()
                except cl.Error as e:  # a driver that cannot compile for its own device
                    raise BackendUnavailableError(
                        f"OpenCL cannot build gpumap's kernels for {device.name.strip()}: "
                        f"{' '.join(str(e).split())[:300]}"
                    ) from e
            _CL_SHARED[key] = (ctx, prg)
        return _CL_SHARED[key]


def usable_opencl_device(kind: str):
    """The first OpenCL device of ``kind`` ('gpu', 'cpu' or 'any', GPUs first) that builds gpumap's
    kernels. A machine can list several platforms for one device (PoCL from ``pyopencl[pocl]`` and
    the distribution's PoCL, say) of which only some compile for this processor: each is tried in
    order, and the error names every device that failed and why."""
    devs = opencl_devices(kind)
    if not devs:
        raise BackendUnavailableError(
            f"opencl{'' if kind == 'any' else '-' + kind} needs an OpenCL "
            f"{'device' if kind == 'any' else kind.upper() + ' device'}, and pyopencl finds none"
        )
    cl = _opencl()
    reasons = []
    for d in devs:
        try:
            _opencl_context(d)
        except BackendUnavailableError as e:
            reasons.append(str(e))
            continue
        except cl.Error as e:  # no context on this device at all
            reasons.append(f"OpenCL cannot open {d.name.strip()}: {' '.join(str(e).split())[:300]}")
            continue
        return d
    raise BackendUnavailableError("; ".join(reasons))


class OpenCLBackend(Backend):
    def __init__(self, spec, template_S, use_table=None, kind="any", *, visible=False, B=8, Bz=None, cap=0):
        n_bins, n_beams = spec.image_shape
        cl = _opencl()
        d = usable_opencl_device(kind)
        self._setup_pool(visible, B, Bz)
        self.cl = cl
        self.ctx, prg = _opencl_context(d)
        self._cl_device = d
        self.queue = cl.CommandQueue(self.ctx)
        self.is_gpu = bool(d.type & cl.device_type.GPU)
        # named as gpumap info and backend= name it: the device it runs on, not how it was asked for
        self.name = "opencl-gpu" if self.is_gpu else "opencl-cpu"
        self.device = f"{d.platform.name.strip()}: {d.name.strip()}"
        mf = self.mf = cl.mem_flags
        # the pool (grown below; one-element stand-ins for the plain rule's evidence: OpenCL has
        # no empty buffers, and its kernels never touch them), the index and the error flag
        self.grid = self.bright = self.count = self.seen = None
        self.index = self._buf(4)
        self.err = self._buf(4)
        cl.enqueue_fill_buffer(self.queue, self.err, np.int32(0), 0, 4)
        self.first_bright = cl.Buffer(self.ctx, mf.READ_WRITE, size=4 * n_beams)
        self.edges = cl.Buffer(self.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=beam_tan_edges(spec))
        self.lut = cl.Buffer(self.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=beam_lut(spec))
        # N_SLOTS image slots: the upload of ping k+1 overlaps the kernels of ping k; a host
        # staging slot is refilled only once its previous upload has finished (event).
        self.images = [cl.Buffer(self.ctx, mf.READ_ONLY, size=4 * n_bins * n_beams) for _ in range(N_SLOTS)]
        self.host = [np.empty((n_bins, n_beams), np.float32) for _ in range(N_SLOTS)]
        self.uploads = [None] * N_SLOTS
        self.images_u8 = [cl.Buffer(self.ctx, mf.READ_ONLY, size=n_bins * n_beams) for _ in range(N_SLOTS)]
        self.host_u8 = [np.empty((n_bins, n_beams), np.uint8) for _ in range(N_SLOTS)]
        self.slot = 0
        self.n_bins = n_bins
        # per-ping max table: two reads per voxel instead of a loop; same answers either way
        self.use_table = True if use_table is None else bool(use_table)
        self.table = cl.Buffer(self.ctx, mf.READ_WRITE | (0 if self.is_gpu else mf.ALLOC_HOST_PTR),
                               size=4 * max(1, table_size(spec) * self.use_table))
        self.n_levels = min(n_beams.bit_length(), MAX_TABLE_LEVELS)
        self._rows = {}
        self.table_u8 = None if self.is_gpu else np.empty((self.n_levels, n_bins, n_beams), np.uint8)
        self._pool = _cpu_pool() if CPU_THREADS > 1 and not self.is_gpu else None
        self._batch = None  # GPU batch buffers, allocated on the first batch
        self.batch_kernels = self.is_gpu
        self.template = None
        if template_S is not None:
            self.template = cl.Buffer(
                self.ctx,
                mf.READ_ONLY | mf.COPY_HOST_PTR,
                hostbuf=np.ascontiguousarray(template_S, np.float32),
            )
            self.n_points = template_S.shape[0]
        # GPUs want short chunks of a column per work-item (enough in flight); CPUs whole columns
        self.chunk = GPU_CHUNK if self.is_gpu else CPU_CHUNK
        # kernel objects hold their arguments: each mapper has its own (cl.Kernel, not
        # prg.name, which would hand out a new one on every access with a warning)
        k = functools.partial(cl.Kernel, prg)
        self.k_gather = k("integrate_gather")
        self.k_init = k("init_blocks")
        self.k_u8 = k("convert_u8")
        self.k_template = k("integrate_template")
        self.k_first = k("find_first_bright")
        self.k_first_init, self.k_first_cells = k("first_bright_init"), k("find_first_bright_cells")
        self.first_bright_cells = self.is_gpu  # as for Warp: a work-item per cell on GPUs
        if self.is_gpu:  # one work-item per cell
            self.k_window, self.k_levels = k("build_bin_window_cells"), k("build_beam_levels_cells")
        else:  # one per beam, then per row: fewest operations
            self.k_window, self.k_levels = k("build_bin_window"), k("build_beam_levels")
        self.n_beams = n_beams
        self.wg = 128
        self.ihost = [np.empty(4096, np.int32) for _ in range(N_SLOTS)]
        self.iuploads, self.islot, self.ipairs_n = [None] * N_SLOTS, 0, 4096
        self.ipairs = self._buf(4 * self.ipairs_n)
        self.grow(cap)

    # ------------------------------------------------------------------ the pool
    def _buf(self, nbytes: int):
        return self.cl.Buffer(self.ctx, self.mf.READ_WRITE, size=max(4, int(nbytes)))

    def grow(self, cap):
        cl, q = self.cl, self.queue
        n = cap * self.BV
        d = self._cl_device
        if 4 * n > d.max_mem_alloc_size:
            raise GridTooLargeError(
                f"Expected a map that fits in one OpenCL buffer, but {cap} blocks of {self.BV} voxels need "
                f"{4 * n / 2**30:.2f} GiB and {d.name.strip()} allows {d.max_mem_alloc_size / 2**30:.2f} GiB"
            )
        n_old = self.cap * self.BV
        arrays = [("grid", 4, np.float32(np.inf)), ("seen", 1 / self.BV, np.uint8(0))]
        if self.visible:
            arrays += [("bright", 4, np.float32(np.inf)), ("count", 8, np.uint64(0))]
        for name, per, fill in arrays:
            nb, ob = int(per * n), int(per * n_old)
            new = self._buf(nb)
            cl.enqueue_fill_buffer(q, new, fill, 0, -(-max(4, nb) // fill.itemsize) * fill.itemsize)
            if ob:
                cl.enqueue_copy(q, new, getattr(self, name), byte_count=ob)
            setattr(self, name, new)
        if not self.visible:
            self.bright, self.count = self._buf(4), self._buf(8)
        self.cap = cap
        q.finish()

    def _upload_index(self, flat):
        self.index = self._buf(flat.nbytes)
        self.cl.enqueue_copy(self.queue, self.index, flat, is_blocking=True)

    def set_blocks(self, slots, lins):
        n = len(slots)
        if n == 0:
            return
        # (slots, lins) in one buffer, uploaded without blocking from a ring of host arrays
        k = self.islot
        self.islot = (k + 1) % N_SLOTS
        if self.iuploads[k] is not None:
            self.iuploads[k].wait()
        if self.ihost[k].shape[0] < 2 * n:
            self.ihost[k] = np.empty(max(2 * n, 4096), np.int32)
        host = self.ihost[k]
        host[:n] = slots
        host[n : 2 * n] = lins
        if self.ipairs_n < 2 * n:
            self.ipairs_n = max(2 * n, 4096)
            self.ipairs = self._buf(4 * self.ipairs_n)
        self.iuploads[k] = self.cl.enqueue_copy(self.queue, self.ipairs, host[: 2 * n], is_blocking=False)
        gs = -(-(n * self.BV) // self.wg) * self.wg
        i32 = np.int32
        self.k_init(self.queue, (gs,), (self.wg,), self.ipairs, i32(n), i32(self.BV), i32(self.visible),
                    np.float32(np.inf), self.index, self.grid, self.bright, self.count, self.seen)

    def _read(self, buf, n, dt):
        out = np.empty(n, dt)
        if n:
            self.cl.enqueue_copy(self.queue, out, buf, is_blocking=True)
        return out

    def read(self):
        n = self.cap * self.BV
        g = self._read(self.grid, n, np.float32)
        if not self.visible:
            return g, None, None
        return g, self._read(self.bright, n, np.float32), self._read(self.count, n, np.uint64)

    def write(self, grid, bright, count):
        q = self.queue
        self.cl.enqueue_copy(q, self.grid, np.ascontiguousarray(grid, np.float32), is_blocking=True)
        if self.visible:
            self.cl.enqueue_copy(q, self.bright, np.ascontiguousarray(bright, np.float32), is_blocking=True)
            self.cl.enqueue_copy(q, self.count, np.ascontiguousarray(count, np.uint64), is_blocking=True)

    def read_seen(self):
        return self._read(self.seen, self.cap, np.uint8)

    def _write_seen(self, seen):
        self.cl.enqueue_copy(self.queue, self.seen, np.ascontiguousarray(seen, np.uint8), is_blocking=True)

    def read_err(self):
        return int(self._read(self.err, 1, np.int32)[0])

    # ------------------------------------------------------------------ pings
    def integrate(self, params, image, method, n_threads):
        cl = self.cl
        _check_rule(params, self.visible)
        # blocking: the caller may reuse `image` as soon as this returns
        s = self.slot
        self.slot = (s + 1) % N_SLOTS
        if self.uploads[s] is not None:
            self.uploads[s].wait()
        image_buf = self.images[s]
        if image.dtype == np.uint8:  # bytes travel, the device widens them
            np.copyto(self.host_u8[s], image)
            self.uploads[s] = cl.enqueue_copy(
                self.queue, self.images_u8[s], self.host_u8[s], is_blocking=False
            )
            n_px = self.n_bins * self.n_beams
            gs = -(-n_px // self.wg) * self.wg
            self.k_u8(self.queue, (gs,), (self.wg,), self.images_u8[s], U8_SCALE, image_buf, np.int32(n_px))
        else:
            np.copyto(self.host[s], image)
            self.uploads[s] = cl.enqueue_copy(self.queue, image_buf, self.host[s], is_blocking=False)
        params["chunk"] = self.chunk
        self._block_params(params)
        P = np.asarray(params, dtype=PING_DTYPE)
        if method == "gather" and not n_threads:
            return
        flag = np.int32(self.use_table)
        if int(params["rule"]) != 0 and self.first_bright_cells:
            gs = -(-self.n_beams // self.wg) * self.wg
            self.k_first_init(self.queue, (gs,), (self.wg,), P, self.first_bright)
            gs = -(-(self.n_bins * self.n_beams) // self.wg) * self.wg
            self.k_first_cells(self.queue, (gs,), (self.wg,), P, image_buf, self.first_bright)
        elif int(params["rule"]) != 0:
            gs = -(-self.n_beams // 16) * 16
            self.k_first(self.queue, (gs,), (16,), P, image_buf, self.first_bright)
        if self.use_table:
            if self.is_gpu:
                gs = -(-(self.n_bins * self.n_beams) // self.wg) * self.wg
                self.k_window(self.queue, (gs,), (self.wg,), P, image_buf, self.table)
                self.k_levels(self.queue, (gs,), (self.wg,), P, self.table)
            else:  # CPUs: whole-image NumPy passes into the mapped table (no copy)
                opencl_host_table(self, params, image)
        args = (P, image_buf, self.edges, self.lut, self.table, flag, self.first_bright)
        if method == "gather":
            n_threads *= -(-int(params["box_n"][2]) // self.chunk)
            if not n_threads:
                return
            gs = -(-n_threads // self.wg) * self.wg
            pool = (self.index, self.grid, self.bright, self.count, self.seen, self.err)
            self.k_gather(self.queue, (gs,), (self.wg,), *args, *pool)
        else:
            gs = -(-self.n_points // self.wg) * self.wg
            self.k_template(self.queue, (gs,), (self.wg,), *args, self.template, self.index, self.grid,
                            self.seen)
        self.queue.flush()

    # ------------------------------------------------------------------ batches (GPUs)
    def _batch_buffers(self, n: int) -> dict:
        bb = self._batch
        if bb is not None and bb["cap"] >= n:
            return bb
        cl = self.cl
        mf = cl.mem_flags
        self.queue.finish()  # old buffers may still be in flight
        cap = min(BATCH_MAX, 1 << (n - 1).bit_length())
        plane = self.n_bins * self.n_beams
        n_table = (self.n_levels + 2) * plane if self.use_table else 1

        def host(nbytes):  # page-locked where the driver offers it (ALLOC_HOST_PTR), mapped once
            buf = cl.Buffer(self.ctx, mf.READ_ONLY | mf.ALLOC_HOST_PTR, size=nbytes)
            arr, _ = cl.enqueue_map_buffer(self.queue, buf, cl.map_flags.WRITE, 0, (nbytes,), np.uint8)
            return buf, arr

        bb = {
            "cap": cap,
            "n_table": n_table,
            "host": [host(cap * (4 * plane + PING_DTYPE.itemsize)) for _ in range(2)],
            "uploads": [None, None],
            "slot": 0,
            "P": cl.Buffer(self.ctx, mf.READ_ONLY, size=cap * PING_DTYPE.itemsize),
            "u8": cl.Buffer(self.ctx, mf.READ_ONLY, size=cap * plane),
            "images": cl.Buffer(self.ctx, mf.READ_WRITE, size=4 * cap * plane),
            "tables": cl.Buffer(self.ctx, mf.READ_WRITE, size=4 * cap * n_table),
            "first_bright": cl.Buffer(self.ctx, mf.READ_WRITE, size=4 * cap * self.n_beams),
        }
        k = functools.partial(self.cl.Kernel, _opencl_context(self._cl_device)[1])
        for name in ("find_first_bright_batch", "build_bin_window_cells_batch",
                     "build_beam_levels_cells_batch", "integrate_gather_batch"):
            bb[name] = k(name)
        self._batch = bb
        return bb

    def _launch_batch(self, params, images, n_threads):
        cl = self.cl
        B = params.shape[0]
        self._block_params(params)
        bb = self._batch_buffers(B)
        s = bb["slot"]
        bb["slot"] = 1 - s
        if bb["uploads"][s] is not None:
            for ev in bb["uploads"][s]:
                ev.wait()
        buf, host = bb["host"][s]
        plane = self.n_bins * self.n_beams
        pb = B * PING_DTYPE.itemsize
        host[:pb] = params.view(np.uint8).reshape(-1)
        nb = images.nbytes
        _copy_rows(host[pb : pb + nb].reshape(B, -1), images.reshape(B, -1).view(np.uint8))
        q = self.queue
        ups = [cl.enqueue_copy(q, bb["P"], host[:pb], is_blocking=False)]
        img_dst = bb["u8"] if images.dtype == np.uint8 else bb["images"]
        ups.append(cl.enqueue_copy(q, img_dst, host[pb : pb + nb], is_blocking=False))
        bb["uploads"][s] = ups
        wg = self.wg
        i32 = np.int32
        if images.dtype == np.uint8:
            n_px = B * plane
            self.k_u8(q, (-(-n_px // wg) * wg,), (wg,), bb["u8"], U8_SCALE, bb["images"], i32(n_px))
        P = bb["P"]
        stride = i32(bb["n_table"])
        if int(params["rule"][0]) != 0:
            n = B * self.n_beams
            bb["find_first_bright_batch"](q, (-(-n // wg) * wg,), (wg,), P, i32(B), i32(self.n_beams),
                                          bb["images"], bb["first_bright"])
        if self.use_table:
            gs = (-(-(B * plane) // wg) * wg,)
            bb["build_bin_window_cells_batch"](q, gs, (wg,), P, i32(B), i32(plane), stride, bb["images"],
                                               bb["tables"])
            bb["build_beam_levels_cells_batch"](q, gs, (wg,), P, i32(B), i32(plane), stride, bb["tables"])
        live = n_threads > 0
        lo = params["box_lo"][live].min(axis=0)
        n = (params["box_lo"] + params["box_n"])[live].max(axis=0) - lo
        n_chunks = -(-int(n[2]) // self.chunk)
        total = int(n[0]) * int(n[1]) * n_chunks
        bb["integrate_gather_batch"](
            q, (-(-total // wg) * wg,), (wg,), P, i32(B), *(i32(x) for x in lo), *(i32(x) for x in n),
            i32(self.chunk), i32(plane), stride, bb["images"], self.edges, self.lut, bb["tables"],
            i32(self.use_table), bb["first_bright"], self.index, self.grid, self.bright, self.count,
            self.seen, self.err,
        )
        q.flush()

    def synchronize(self) -> None:
        self.queue.finish()


def make_backend(
    name: str,
    spec: SonarSpec,
    template_S: np.ndarray | None = None,
    use_table: bool | None = None,
    *,
    visible: bool = False,
    B: int = 8,
    Bz: int | None = None,
    cap: int = 0,
) -> Backend:
    """Build the backend called ``name`` (never another one; raises if it cannot run) with a pool
    of ``cap`` blocks of ``B x B x Bz`` voxels (``Bz`` default ``B``; grown later with
    :meth:`Backend.grow`).

    ``use_table`` picks how kernels take the max over a footprint: a per-ping max table
    (True), a loop over cells (False), or the faster for the device (None: table on CPUs).
    ``visible`` keeps the visible rule's per-voxel evidence (5 more bytes per voxel).
    """
    args = (spec, template_S, use_table)
    kw = {"visible": visible, "B": B, "Bz": Bz, "cap": cap}
    if name == "numpy":
        return NumpyBackend(*args, **kw)
    if name in ("warp-cpu", "warp-cuda"):
        return WarpBackend(*args, device=name.split("-")[1], **kw)
    if name in ("opencl", "opencl-gpu", "opencl-cpu"):
        kind = {"opencl": "any", "opencl-gpu": "gpu", "opencl-cpu": "cpu"}[name]
        return OpenCLBackend(*args, kind=kind, **kw)
    raise ValueError(f"Expected backend to be 'auto' or one of {BACKENDS}, but got {name!r}")


def available_backends(among=None) -> list[str]:
    """Backends that can run on this machine, fastest first (the order ``auto`` tries); ``among``
    (names): probe only those (starting Warp or building the OpenCL kernels takes seconds)."""
    out = []
    for name in AUTO_ORDER:
        if among is not None and name not in among:
            continue
        try:
            if name == "warp-cuda":
                wp, _ = _warp()
                ok = wp.is_cuda_available()
            elif name.startswith("opencl"):
                ok = usable_opencl_device(name.split("-")[1]) is not None
            elif name == "warp-cpu":
                _warp()
                ok = True
            else:
                ok = True
        except BackendUnavailableError:
            ok = False
        if ok:
            out.append(name)
    if os.environ.get("GPUMAP_DEBUG"):
        log.debug("available backends: %s", out)
    return out


def opencl_host_table(b, params, image) -> None:
    """CPU OpenCL devices: build ping ``params``' max table of ``image`` with whole-image NumPy
    passes straight into ``b.table`` mapped on the host (no copy); ``b`` is an OpenCL backend."""
    cl = b.cl
    win = int(params["win"])
    rows = b._rows.get(win)
    if rows is None:
        rows = b._rows[win] = table_rows(b.n_bins, win)
    shape = (b.n_levels, b.n_bins, b.n_beams)
    # in order: the map waits for the previous ping's kernels, which read the table
    tab, _ = cl.enqueue_map_buffer(
        b.queue, b.table, cl.map_flags.WRITE_INVALIDATE_REGION, 0, shape, np.float32
    )
    try:
        build_table_host(image, win, b.n_levels, tab, rows, b.table_u8, b._pool)
    finally:
        tab.base.release(b.queue)


def warp_upload_image(b, image) -> None:
    """Put ``image`` where ``b``'s kernels read it: on GPUs through a pinned staging slot (uint8
    widened on the device), on CPUs into the kernels' float32 image; ``b`` is a Warp backend."""
    wp = b.wp
    if b.staging:
        s = b.slot
        if b.events[s] is not None:
            wp.synchronize_event(b.events[s])
        if image.dtype == np.uint8:
            np.copyto(b.staging_u8_np[s], image)
            wp.copy(b.image_u8, b.staging_u8[s])
            b.events[s] = wp.record_event()
            b.cmd_u8.launch()
        else:
            np.copyto(b.staging_np[s], image)
            wp.copy(b.image, b.staging[s])
            b.events[s] = wp.record_event()
        b.slot = (s + 1) % N_SLOTS
    elif image.dtype == np.uint8:
        np.multiply(image, U8_SCALE, out=b.image_np)
    else:
        np.copyto(b.image_np, image)


def warp_host_table(b, params, image) -> None:
    """Warp on a CPU: ping ``params``' max table of ``image`` into ``b.table_np`` (NumPy passes,
    uint8 images read directly); ``b`` is a Warp backend."""
    win = int(params["win"])
    rows = b._rows.get(win)
    if rows is None:
        rows = b._rows[win] = table_rows(b.n_bins, win)
    src = image if image.dtype == np.uint8 else b.image_np
    build_table_host(src, win, b.table_np.shape[0], b.table_np, rows, b.table_u8, b._pool)


def warp_launch_halves(b, params, cmd, cmd2, n_threads: int, n_chunks: int) -> None:
    """Warp on a CPU: launch a gather over the box's rows in two halves, one per core (each
    owns its voxels; Warp's CPU kernels are serial and a launch releases the GIL). ``cmd`` and
    ``cmd2`` are recorded on ``b._P`` and ``b._P2``; ``n_threads`` is the box's column count."""
    n0 = int(params["box_n"][0])
    half = n0 // 2
    cols = n_threads // n0
    ctypes.memmove(b._P2_addr, params.ctypes.data, PING_DTYPE.itemsize)
    b._P._ctype.box_n[0] = half
    b._P2._ctype.box_lo[0] = int(params["box_lo"][0]) + half
    b._P2._ctype.box_n[0] = n0 - half
    cmd.set_dim(half * cols * n_chunks)
    cmd2.set_dim((n0 - half) * cols * n_chunks)
    fut = b._pool.submit(cmd2.launch)
    try:
        cmd.launch()
    finally:
        fut.result()
