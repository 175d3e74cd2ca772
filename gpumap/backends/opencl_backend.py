"""The ``opencl-gpu`` and ``opencl-cpu`` backends: the kernels of ``gpumap/kernels/minmax.cl`` run by
PyOpenCL, on the first device of the kind asked for that builds them; one context and program
per device, shared by every mapper on it.
"""

from __future__ import annotations

import functools
import os
import threading
from importlib import resources

import numpy as np

import gpumap.backends.base as base
from gpumap.backends.base import (
    N_SLOTS,
    U8_SCALE,
    Backend,
    GridTooLargeError,
    _check_rule,
    _copy_rows,
    _cpu_pool,
    check_device_index,
)
from gpumap.backends.tables import opencl_host_table, table_size
from gpumap.errors import BackendUnavailableError
from gpumap.geometry import MAX_TABLE_LEVELS, PING_DTYPE, beam_lut, beam_tan_edges


@functools.cache
def _opencl():
    try:
        import pyopencl as cl
    except Exception as e:  # pragma: no cover
        raise BackendUnavailableError(f"pyopencl cannot be imported: {e!r}") from e
    return cl


def _same_arg(a, b) -> bool:
    """Whether kernel arguments ``a`` and ``b`` are the same: the same object, or equal NumPy scalars
    of one type (records and other arrays count as new: a batch's ping record always is)."""
    return a is b or (type(a) is type(b) and isinstance(a, np.number) and a == b)


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


def program_source(name: str) -> str:
    """The OpenCL source of ``gpumap.kernels/<name>.cl`` as it is built: the shared definitions of
    ``common.cl`` (the ping record, the count mask, the arc step: one copy for every program) first."""
    k = resources.files("gpumap.kernels")
    return k.joinpath("common.cl").read_text() + "\n" + k.joinpath(f"{name}.cl").read_text()


def _opencl_context(device):
    """(context, program) for ``device``, built once per process."""
    cl = _opencl()
    key = int(device.int_ptr)
    with _CL_LOCK:
        if key not in _CL_SHARED:
            ctx = cl.Context([device])
            src = program_source("minmax")
            opts = ["-cl-fp32-correctly-rounded-divide-sqrt"]
            if not device.type & cl.device_type.GPU:  # a column's voxels eight at a time (gather_run8)
                opts.append("-DGPUMAP_CPU_VECTORS")
            regs = int(os.environ.get("GPUMAP_GPU_MAX_REGISTERS", "0") or 0)
            if regs and "cl_nv_compiler_options" in device.extensions:  # as kernels/minmax.py caps Warp's
                opts.append(f"-cl-nv-maxrregcount={regs}")
            try:
                prg = cl.Program(ctx, src).build(options=opts)
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


_CL_EXTRA: dict[tuple[int, str], object] = {}


def extra_program(ctx, name: str):
    """The program of ``gpumap.kernels/<name>.cl`` (a kernel module beside minmax.cl: viewgain,
    confidence) for the context ``ctx``, built once per context and name, correctly rounded division and
    square root asked for, without them where the driver refuses the option."""
    cl = _opencl()
    key = (id(ctx), name)
    with _CL_LOCK:
        if key not in _CL_EXTRA:
            src = program_source(name)
            prg = cl.Program(ctx, src)
            try:
                _CL_EXTRA[key] = prg.build(options=["-cl-fp32-correctly-rounded-divide-sqrt"])
            except cl.Error:
                _CL_EXTRA[key] = cl.Program(ctx, src).build()
        return _CL_EXTRA[key]


def usable_opencl_device(kind: str, index: int | None = None):
    """The first OpenCL device of ``kind`` ('gpu', 'cpu' or 'any', GPUs first) that builds gpumap's
    kernels. A machine can list several platforms for one device (PoCL from ``pyopencl[pocl]`` and
    the distribution's PoCL, say) of which only some compile for this processor: each is tried in
    order, and the error names every device that failed and why. ``index``: the ``index``-th device
    of ``kind`` as :func:`opencl_devices` lists them, and no other (``ValueError`` past the last)."""
    devs = opencl_devices(kind)
    name = f"opencl{'' if kind == 'any' else '-' + kind}"
    if not devs:
        raise BackendUnavailableError(
            f"{name} needs an OpenCL "
            f"{'device' if kind == 'any' else kind.upper() + ' device'}, and pyopencl finds none"
        )
    if index is not None:
        devs = [devs[check_device_index(index, len(devs), name)]]
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
    batch_box_knob = "OPENCL_BATCH_BOX_VOXELS_MAX"

    def __init__(self, spec, template_S, use_table=None, kind="any", *, visible=False, B=8, Bz=None, cap=0,
                 device_index=None):
        n_bins, n_beams = spec.image_shape
        cl = _opencl()
        d = usable_opencl_device(kind, device_index)
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
        self._pool = _cpu_pool() if base.CPU_THREADS > 1 and not self.is_gpu else None
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
        self.chunk = base.GPU_CHUNK if self.is_gpu else base.CPU_CHUNK
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
        if self._batch is not None:  # the batch kernels' arguments name the old pool
            self._batch["args"] = {}

    def _upload_index(self, flat):
        self.index = self._buf(flat.nbytes)
        if self._batch is not None:
            self._batch["args"] = {}
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

    def read_blocks(self, slots):  # by runs of consecutive slots: those blocks only cross the bus
        return self._read_runs(slots)

    def write_blocks(self, slots, grid, bright, count):
        self._write_runs(slots, grid, bright, count)

    def _copy_out(self, name, offset, out):
        self.cl.enqueue_copy(self.queue, out, getattr(self, name), src_offset=offset * out.itemsize,
                             is_blocking=False)

    def _copy_in(self, name, offset, src):
        self.cl.enqueue_copy(self.queue, getattr(self, name), src, dst_offset=offset * src.itemsize,
                             is_blocking=False)

    def _copies_done(self):
        self.queue.finish()

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
        cap = min(base.BATCH_MAX, 1 << (n - 1).bit_length())
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
            # two device slots for the parameters and bytes (see _launch_batch); "done": the last
            # kernels that read each
            "P": [cl.Buffer(self.ctx, mf.READ_ONLY, size=cap * PING_DTYPE.itemsize) for _ in range(2)],
            "u8": [cl.Buffer(self.ctx, mf.READ_ONLY, size=cap * plane) for _ in range(2)],
            "done": [None, None],
            "upload_queue": cl.CommandQueue(self.ctx),
            "images": cl.Buffer(self.ctx, mf.READ_WRITE, size=4 * cap * plane),
            "tables": cl.Buffer(self.ctx, mf.READ_WRITE, size=4 * cap * n_table),
            "first_bright": cl.Buffer(self.ctx, mf.READ_WRITE, size=4 * cap * self.n_beams),
        }
        k = functools.partial(self.cl.Kernel, _opencl_context(self._cl_device)[1])
        for name in ("find_first_bright_batch", "build_bin_window_cells_batch",
                     "build_beam_levels_cells_batch", "integrate_voxels_batch", "convert_u8"):
            bb[name] = k(name)  # the batch's own kernel objects: their arguments stay set (_enqueue)
        bb["args"] = {}
        self._batch = bb
        return bb

    def _enqueue(self, bb: dict, name: str, n: int, args: tuple, wait_for=None):
        """Launch batch kernel ``name`` on ``n`` work-items (rounded up to work-groups), setting only
        the arguments that changed since its last launch (a kernel object keeps its arguments: most
        of a batch's stay the same buffers and sizes); returns the event."""
        kern = bb[name]
        last = bb["args"].get(name)
        for i, a in enumerate(args):
            if last is None or not _same_arg(last[i], a):
                kern.set_arg(i, a)
        bb["args"][name] = args
        wg = self.wg
        return self.cl.enqueue_nd_range_kernel(self.queue, kern, (-(-n // wg) * wg,), (wg,),
                                               wait_for=wait_for)

    def _launch_batch(self, params, images, n_threads):
        cl = self.cl
        B, bb, s = self._next_batch(params)
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
        u8 = images.dtype == np.uint8
        # Uploads into device slot s on their own queue, after the kernels that last read that slot
        # (the float images' one buffer: after the batch before too), so that batch k+1's upload
        # overlaps batch k's kernels; the kernels wait for them.
        up = bb["upload_queue"]
        after = [e for e in (bb["done"][s], None if u8 else bb["done"][1 - s]) if e is not None]
        P = bb["P"][s]
        img_dst = bb["u8"][s] if u8 else bb["images"]
        ups = [cl.enqueue_copy(up, P, host[:pb], is_blocking=False, wait_for=after),
               cl.enqueue_copy(up, img_dst, host[pb : pb + nb], is_blocking=False, wait_for=after)]
        up.flush()
        bb["uploads"][s] = ups
        i32 = np.int32
        if u8:
            n_px = B * plane
            self._enqueue(bb, "convert_u8", n_px, (img_dst, U8_SCALE, bb["images"], i32(n_px)), wait_for=ups)
        else:
            cl.enqueue_barrier(q, wait_for=ups)
        stride = i32(bb["n_table"])
        if int(params["rule"][0]) != 0:
            self._enqueue(bb, "find_first_bright_batch", B * self.n_beams,
                          (P, i32(B), i32(self.n_beams), bb["images"], bb["first_bright"]))
        if self.use_table:
            self._enqueue(bb, "build_bin_window_cells_batch", B * plane,
                          (P, i32(B), i32(plane), stride, bb["images"], bb["tables"]))
            self._enqueue(bb, "build_beam_levels_cells_batch", B * plane,
                          (P, i32(B), i32(plane), stride, bb["tables"]))
        live = n_threads > 0
        lo = params["box_lo"][live].min(axis=0).tolist()
        n = ((params["box_lo"] + params["box_n"])[live].max(axis=0) - lo).tolist()
        pool = (self.index, self.grid, self.bright, self.count, self.seen, self.err)
        # a work-item per voxel of the union box; ping 0's parameters as an argument
        bb["done"][s] = self._enqueue(
            bb, "integrate_voxels_batch", n[0] * n[1] * n[2],
            (np.asarray(params[0, ...], dtype=PING_DTYPE), P, i32(B), *(i32(x) for x in lo),
             *(i32(x) for x in n), i32(plane), stride, bb["images"], self.edges, self.lut, bb["tables"],
             i32(self.use_table), bb["first_bright"], *pool),
        )
        q.flush()

    def synchronize(self) -> None:
        self.queue.finish()
        if self._batch is not None:
            self._batch["upload_queue"].finish()
