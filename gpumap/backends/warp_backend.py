"""The ``warp-cpu`` and ``warp-cuda`` backends: the kernels of ``gpumap.kernels.minmax`` run by
NVIDIA Warp, launches recorded once and replayed per ping; on CUDA, images staged through
page-locked buffers so the host prepares the next ping while the GPU works.
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import os
import sys

import numpy as np

import gpumap.backends.base as base
from gpumap.backends.base import N_SLOTS, U8_SCALE, Backend, _check_rule, _copy_rows, _cpu_pool
from gpumap.backends.tables import table_size, warp_host_table
from gpumap.errors import BackendUnavailableError
from gpumap.geometry import MAX_TABLE_LEVELS, PING_DTYPE, beam_lut, beam_tan_edges


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


class WarpBackend(Backend):
    def __init__(self, spec, template_S, use_table=None, device="cpu", *, visible=False, B=8, Bz=None, cap=0,
                 device_index=None):
        n_bins, n_beams = spec.image_shape
        wp, minmax = _warp()
        if device == "cuda" and not wp.is_cuda_available():
            why = "" if cuda_driver_loadable() else " (the NVIDIA CUDA driver, libcuda, cannot be loaded)"
            raise BackendUnavailableError(f"warp-cuda needs a CUDA device, and Warp finds none here{why}")
        # the device_index-th CUDA device (warp-cuda), never another; warp-cpu has one device, index 0
        count = wp.get_cuda_device_count() if device == "cuda" else 1
        index = base.check_device_index(device_index, count, f"warp-{device}")
        self._setup_pool(visible, B, Bz)
        self.wp, self.k = wp, minmax
        self.dev = wp.get_device(f"cuda:{index}" if device == "cuda" else "cpu")
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
            self.chunk = base.GPU_CHUNK if self.dev.is_cuda else base.CPU_CHUNK
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
            self._pool = _cpu_pool() if base.CPU_THREADS > 1 else None
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
        # explicit devices, not ScopedDevice (Warp's default device is one for every thread, and
        # mappers on other GPUs may grow at the same time: gpumap.pipeline.gpu_threads)
        dev = self.dev
        names = [("grid", wp.full, np.inf, float), ("seen", wp.zeros, None, wp.uint8)]
        if self.visible:
            names += [("bright", wp.full, np.inf, float), ("count", wp.zeros, None, wp.uint64)]
        for name, make, fill, dt in names:
            n = cap if name == "seen" else cap * self.BV
            kw = {"dtype": dt, "device": dev} if fill is None else {"value": fill, "dtype": dt, "device": dev}
            new = make(n, **kw)
            old_n = self.cap if name == "seen" else n_old
            if old_n:
                wp.copy(new, getattr(self, name), count=old_n)
            setattr(self, name, new)
        self.cap = cap
        self._forget_launches()  # recorded launches hold the old arrays

    def _forget_launches(self) -> None:
        self._cmds = self._init_cmd = None
        if self._batch is not None:
            self._batch["views"] = {}

    def _upload_index(self, flat):
        self.index = self.wp.array(flat, dtype=int, device=self.dev)
        self._forget_launches()

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
        self.ievents[k] = wp.get_stream(self.dev).record_event()
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

    def read_blocks(self, slots):  # by runs of consecutive slots: those blocks only cross the bus
        return self._read_runs(slots)

    def write_blocks(self, slots, grid, bright, count):
        self._write_runs(slots, grid, bright, count)

    def copy_blocks_from(self, other, slots):
        if not isinstance(other, WarpBackend):
            return super().copy_blocks_from(other, slots)
        _, ss, starts, ends = base.block_runs(slots)
        try:  # device to device (another GPU: peer copies), by runs of consecutive slots
            for name in self._pool_arrays():
                dst, src = getattr(self, name), getattr(other, name)
                for a, b in zip(starts.tolist(), ends.tolist(), strict=True):
                    off = int(ss[a]) * self.BV
                    self.wp.copy(dst, src, dest_offset=off, src_offset=off, count=(b - a) * self.BV)
            other.synchronize()
            self.synchronize()
        except Exception:  # a pair of devices Warp cannot copy between: through the host (the same blocks)
            self.synchronize()
            return super().copy_blocks_from(other, slots)
        seen = self.read_seen()
        seen[ss] = 1
        self._write_seen(seen)

    def _copy_out(self, name, offset, out):
        arr = getattr(self, name)
        host = self.wp.array(out, dtype=arr.dtype, device="cpu", copy=False)
        self.wp.copy(host, arr, dest_offset=0, src_offset=offset, count=len(out))

    def _copy_in(self, name, offset, src):
        arr = getattr(self, name)
        host = self.wp.array(src, dtype=arr.dtype, device="cpu", copy=False)
        self.wp.copy(arr, host, dest_offset=offset, src_offset=0, count=len(src))

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
        cap = min(base.BATCH_MAX, 1 << (n - 1).bit_length())
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
            "events": [None, None],  # per host slot: its uploads are done
            "slot": 0,
            # two device slots for the parameters, boxes and bytes: batch k+1's upload (on the copy
            # stream) overlaps batch k's kernels, and waits only for the kernels that last read its
            # slot (event "done")
            "boxes": [wp.empty((cap, 6), dtype=int, device=dev) for _ in range(2)],
            "P": [wp.empty(cap, dtype=self.k.PingParams, device=dev) for _ in range(2)],
            "u8": [wp.empty(shape, dtype=wp.uint8, device=dev) for _ in range(2)],
            "done": [None, None],
            "copy_stream": wp.Stream(dev) if dev.is_cuda else None,
            "images": wp.empty(shape, dtype=float, device=dev),
            "tables": wp.empty((cap, n_table), dtype=float, device=dev),
            "first_bright": wp.zeros((cap, self.n_beams), dtype=int, device=dev),
        }
        bb["host_u8_np"] = [a.numpy() for a in bb["host_u8"]]
        bb["host_f_np"] = [a.numpy() for a in bb["host_f"]]
        bb["host_box_np"] = [a.numpy() for a in bb["host_box"]]
        bb["views"] = {}  # _batch_views
        self._batch = bb
        return bb

    def _batch_views(self, bb: dict, s: int, B: int, u8: bool) -> dict:
        """Batch buffers' views for host slot ``s`` and ``B`` pings, and the batch's launches recorded
        on them (``record_cmd``): made once, then a batch only refreshes the parameters that change
        (the union box, ping 0's record). Dropped when the pool or the index is replaced."""
        key = (s, B, u8)
        v = bb["views"].get(key)
        if v is not None:
            return v
        wp, k, dev = self.wp, self.k, self.dev
        P, imgs = bb["P"][s][:B], bb["images"][:B]
        v = {"P": P, "hp": bb["host_P"][s][:B], "imgs": imgs,
             "host_img": (bb["host_u8"] if u8 else bb["host_f"])[s][:B],
             "dev_img": bb["u8"][s][:B] if u8 else imgs}
        rec = {"device": dev, "record_cmd": True}
        shape = (B, self.n_bins, self.n_beams)
        cmds = []
        v["convert"] = wp.launch(k.convert_u8_batch, dim=shape, inputs=[v["dev_img"], float(U8_SCALE), imgs],
                                 **rec) if u8 else None
        fb, tables = bb["first_bright"], bb["tables"]  # (cap, ...): kernels index their B first rows only
        v["first"] = wp.launch(k.find_first_bright_batch, dim=(B, self.n_beams), inputs=[P, imgs, fb], **rec)
        if self.use_table:
            cmds += [wp.launch(k.build_bin_window_cells_batch, dim=shape, inputs=[P, imgs, tables], **rec),
                     wp.launch(k.build_beam_levels_cells_batch, dim=shape, inputs=[P, tables], **rec)]
        v["table"] = cmds
        if bb.get("P0") is None:  # ping 0's record as a kernel argument (constant memory): refreshed in place
            bb["P0"] = _warp_params(k, np.zeros((), PING_DTYPE))
            bb["P0_addr"] = ctypes.addressof(bb["P0"]._ctype)
        pool = [self.index, self.grid, self.bright, self.count, self.seen, self.err]
        v["gather"] = wp.launch(
            k.integrate_voxels_batch, dim=1,
            inputs=[bb["P0"], P, bb["boxes"][s], wp.vec3i(0, 0, 0), wp.vec3i(0, 0, 0), imgs, self.edges,
                    self.lut, tables, fb, *pool],
            block_dim=128,  # a heavy kernel: more blocks fit the registers left
            **rec)
        bb["views"][key] = v
        return v

    def _launch_batch(self, params, images, n_threads):
        wp = self.wp
        B, bb, s = self._next_batch(params)
        if bb["events"][s] is not None:  # host slot s: its last uploads are done
            wp.synchronize_event(bb["events"][s])
        u8 = images.dtype == np.uint8
        v = self._batch_views(bb, s, B, u8)
        ctypes.memmove(v["hp"].ptr, params.ctypes.data, B * PING_DTYPE.itemsize)
        hb = bb["host_box_np"][s]
        hb[:B, :3] = params["box_lo"]
        hb[:B, 3:] = params["box_n"]
        _copy_rows((bb["host_u8_np"] if u8 else bb["host_f_np"])[s][:B], images)
        # Uploads into device slot s on the copy stream (CUDA), after the kernels that last read that
        # slot: batch k+1's upload overlaps batch k's kernels. The float images have one device
        # buffer: their upload also waits for the batch before.
        cs = bb["copy_stream"]
        if cs is not None:
            for ev in (bb["done"][s], None if u8 else bb["done"][1 - s]):
                if ev is not None:
                    cs.wait_event(ev)
        wp.copy(v["P"], v["hp"], stream=cs)
        wp.copy(bb["boxes"][s], bb["host_box"][s], count=6 * B, stream=cs)
        wp.copy(v["dev_img"], v["host_img"], stream=cs)
        if cs is not None:
            bb["events"][s] = cs.record_event()
            wp.get_stream(self.dev).wait_event(bb["events"][s])
        if u8:
            v["convert"].launch()
        if int(params["rule"][0]) != 0:
            v["first"].launch()
        for cmd in v["table"]:
            cmd.launch()
        live = n_threads > 0
        lo = params["box_lo"][live].min(axis=0)
        hi = (params["box_lo"] + params["box_n"])[live].max(axis=0)
        n = (hi - lo).tolist()
        # a thread per voxel of the union box; ping 0's parameters as an argument (constant memory)
        ctypes.memmove(bb["P0_addr"], params[:1].ctypes.data, PING_DTYPE.itemsize)
        g = v["gather"]
        g.set_param_by_name("box_lo", wp.vec3i(*lo.tolist()))
        g.set_param_by_name("box_n", wp.vec3i(*n))
        g.set_dim(n[0] * n[1] * n[2])
        g.launch()
        if cs is not None:  # device slot s is free again once these kernels are done
            bb["done"][s] = wp.get_stream(self.dev).record_event()

    def synchronize(self) -> None:
        self.wp.synchronize_device(self.dev)


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
            b.events[s] = wp.get_stream(b.dev).record_event()
            b.cmd_u8.launch()
        else:
            np.copyto(b.staging_np[s], image)
            wp.copy(b.image, b.staging[s])
            b.events[s] = wp.get_stream(b.dev).record_event()
        b.slot = (s + 1) % N_SLOTS
    elif image.dtype == np.uint8:
        np.multiply(image, U8_SCALE, out=b.image_np)
    else:
        np.copyto(b.image_np, image)


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
