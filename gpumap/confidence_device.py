"""The confidence layer's per-ping pass on a map's device: the kernels of ``gpumap.kernels.confidence``
(Warp) and their twin ``confidence.cl`` (OpenCL), launched after the ping's update on the map's own
stream or queue, reading the map's pool where it lives (no read of the map to the host).

:class:`DeviceConfidence` keeps the layer's two arrays on the device (``confirmed`` uint8 and
``arcs`` uint16, flat over the grid in C order, as :class:`gpumap.confidence.ConfidenceLayer`
keeps them on the host) and gives them the same values as :func:`gpumap.confidence.confirm_ping`,
the NumPy reference, bit for bit (the tests compare every backend with it). The ``numpy`` backend
keeps running the reference itself.
"""

from __future__ import annotations

import functools
import math
import threading
from importlib import resources

import numpy as np

from gpumap.geometry import PING_DTYPE

__all__ = ["DeviceConfidence", "pass_scalars"]

#: Beams per thread of the per-beam running counts on CPUs (rows read a run of this many floats;
#: GPUs take one beam a thread, their reads coalesce across threads).
GROUP_CPU = 64
_CL_PROGRAMS: dict[int, object] = {}
_CL_LOCK = threading.Lock()
_KERNELS = ("lit_cols", "prefix_cols", "conf_voxels", "conf_candidates")


def pass_scalars(spec, params: np.ndarray, half_rad: float, tube_m: float, value_rule) -> dict:
    """The pass's scalar arguments: cos and sin of the rivals' half aperture and the tube (float32,
    as :func:`gpumap.confidence.confirm_ping` rounds them), the column walk's widened range and slab
    (float32, padded outwards: they only bound the walk), and the value rule's options (the evidence
    test's ``p_min`` and right-hand side ``z^2 p_min (1 - p_min)`` in float64, in the reference's order)."""
    rho = float(params["rho"])
    rmax_c = (spec.range_max_m + rho) * (1.0 + 1e-4) + 1e-4
    slab_c = ((rho + rmax_c * math.sin(half_rad)) / math.cos(half_rad)) * (1.0 + 1e-4) + 1e-4
    p, z = float(value_rule.bright_share), float(value_rule.share_z)
    return {
        "cos_hv": np.float32(np.cos(half_rad)), "sin_hv": np.float32(np.sin(half_rad)),
        "tube": np.float32(tube_m), "rmax_c": np.float32(rmax_c), "slab_c": np.float32(slab_c),
        "carve_views": np.int32(value_rule.carve_views), "p_min": np.float64(p),
        "rhs": np.float64(z * z * p * (1.0 - p)),
    }


class DeviceConfidence:
    """The layer's arrays and per-ping pass on ``backend`` (a Warp or OpenCL
    :class:`gpumap.backends.Backend` of a bounded grid of ``n_voxels`` voxels)."""

    def __init__(self, backend, spec, n_voxels: int) -> None:
        self.b = backend
        self.kind = "warp" if backend.name.startswith("warp") else "opencl"
        self.n_voxels = int(n_voxels)
        n_bins, n_beams = spec.image_shape
        self.n_bins, self.n_beams = n_bins, n_beams
        self.table_n = (n_bins + 1) * n_beams  # per-beam running counts, row by row
        self.cap = 0  # box voxels the candidate list and the cells hold
        if self.kind == "warp":
            self._init_warp()
        else:
            self._init_opencl()

    # ------------------------------------------------------------------ Warp
    def _init_warp(self) -> None:
        from gpumap.kernels import confidence as k

        b = self.b
        wp = b.wp
        self.wp, self.k = wp, k
        dev = b.dev
        self.gpu = bool(dev.is_cuda)
        self.confirmed = wp.zeros(self.n_voxels, dtype=wp.uint8, device=dev)
        self.arcs = wp.zeros(self.n_voxels, dtype=wp.uint16, device=dev)
        self.lit = wp.zeros(self.table_n, dtype=int, device=dev)
        self.rivals = wp.zeros(self.table_n, dtype=int, device=dev)
        self.n_cand = wp.zeros(1, dtype=int, device=dev)
        self.cand = wp.empty(0, dtype=int, device=dev)
        self.P = k.PingParams()
        self.group = 1 if self.gpu else GROUP_CPU
        wp.load_module(k, device=dev)

    def _warp_pass(self, params: np.ndarray, s: dict, n_cols: int, n_box: int) -> None:
        import ctypes

        wp, k, b = self.wp, self.k, self.b
        P = self.P
        if ctypes.sizeof(P._ctype) != PING_DTYPE.itemsize:
            raise RuntimeError("confidence PingParams and PING_DTYPE have drifted apart")
        ctypes.memmove(ctypes.addressof(P._ctype), params.ctypes.data, PING_DTYPE.itemsize)
        dev = b.dev
        if self.cap < n_box:
            self.cap = max(n_box, 2 * self.cap)
            self.cand = wp.empty(self.cap, dtype=int, device=dev)
            self.cells = wp.empty(self.cap, dtype=int, device=dev)
        pool = [b.edges, b.lut, b.index, b.grid, b.bright, b.count]
        g = self.group
        n_groups = -(-self.n_beams // g)
        # CPUs: the per-beam passes and the candidates in two halves on two threads (Warp's CPU
        # launches are serial and release the GIL; each half owns its beams or candidates)
        split = self._pool_split()
        self._halves(k.lit_cols, n_groups, [P, b.image, self.lit, self.rivals, self.n_cand, g], split)
        wp.launch(k.conf_voxels, dim=n_cols,
                  inputs=[P, *pool, self.lit, self.arcs, self.rivals, self.cells, self.cand, self.n_cand,
                          s["cos_hv"], s["sin_hv"], s["tube"], s["rmax_c"], s["slab_c"],
                          int(s["carve_views"]), s["p_min"], s["rhs"]], device=dev)
        self._halves(k.prefix_cols, n_groups, [P, self.rivals, g], split)
        n = n_box if self.gpu else int(self.n_cand.numpy()[0])
        if n:
            args = [P, b.edges, b.lut, self.lit, self.rivals, self.cells, self.cand, self.n_cand,
                    self.confirmed, s["tube"]]
            self._halves(k.conf_candidates, n, args, split)

    def _pool_split(self):
        """The CPU thread for the second half of a launch, or None (GPUs, one CPU thread)."""
        import gpumap.backends.base as base

        return None if self.gpu or base.CPU_THREADS < 2 else base._cpu_pool()

    def _halves(self, kernel, n: int, inputs: list, split) -> None:
        """Launch ``kernel`` over ``n`` threads (its last argument the first thread's number): on a
        CPU with a second thread, as two halves at once."""
        wp, dev = self.wp, self.b.dev
        if split is None or n < 2:
            wp.launch(kernel, dim=n, inputs=[*inputs, 0], device=dev)
            return
        h = n // 2
        fut = split.submit(wp.launch, kernel, dim=n - h, inputs=[*inputs, h], device=dev)
        try:
            wp.launch(kernel, dim=h, inputs=[*inputs, 0], device=dev)
        finally:
            fut.result()

    # ------------------------------------------------------------------ OpenCL
    def _init_opencl(self) -> None:
        b = self.b
        cl = b.cl
        self.cl = cl
        self.gpu = bool(b.is_gpu)
        key = id(b.ctx)
        with _CL_LOCK:
            if key not in _CL_PROGRAMS:
                src = resources.files("gpumap.kernels").joinpath("confidence.cl").read_text()
                try:
                    prg = cl.Program(b.ctx, src).build(options=["-cl-fp32-correctly-rounded-divide-sqrt"])
                except cl.Error:
                    prg = cl.Program(b.ctx, src).build()
                _CL_PROGRAMS[key] = prg
            prg = _CL_PROGRAMS[key]
        kern = functools.partial(cl.Kernel, prg)
        self.kernels = {name: kern(name) for name in _KERNELS}
        mf = cl.mem_flags
        q = b.queue

        def zeros(nbytes):
            buf = cl.Buffer(b.ctx, mf.READ_WRITE, size=max(4, int(nbytes)))
            cl.enqueue_fill_buffer(q, buf, np.uint8(0), 0, max(4, int(nbytes)))
            return buf

        self._zeros = zeros
        self.confirmed_buf = zeros(self.n_voxels)
        self.arcs_buf = zeros(2 * self.n_voxels)
        self.lit = zeros(4 * self.table_n)
        self.rivals = zeros(4 * self.table_n)
        self.n_cand = zeros(4)
        self.cand = zeros(4)
        self.cells = zeros(4)
        self.wg = 64
        self.group = 1 if self.gpu else GROUP_CPU
        q.finish()

    def _opencl_pass(self, params: np.ndarray, s: dict, n_cols: int, n_box: int) -> None:
        cl, b, K = self.cl, self.b, self.kernels
        q = b.queue
        if self.cap < n_box:
            self.cap = max(n_box, 2 * self.cap)
            self.cand = self._zeros(4 * self.cap)
            self.cells = self._zeros(4 * self.cap)
        from gpumap.backends.base import N_SLOTS

        image = b.images[(b.slot - 1) % N_SLOTS]  # the ping's image, as its update read it
        P = np.asarray(params, dtype=PING_DTYPE)
        wg = self.wg

        def gs(n):
            return (-(-int(n) // wg) * wg,)

        pool = (b.edges, b.lut, b.index, b.grid, b.bright, b.count)
        g = np.int32(self.group)
        n_groups = -(-self.n_beams // int(g))
        zero = np.int32(0)
        K["lit_cols"](q, gs(n_groups), (wg,), P, image, self.lit, self.rivals, self.n_cand, g, zero)
        K["conf_voxels"](q, gs(n_cols), (wg,), P, *pool, self.lit, self.arcs_buf, self.rivals, self.cells,
                         self.cand, self.n_cand, s["cos_hv"], s["sin_hv"], s["tube"], s["rmax_c"],
                         s["slab_c"], s["carve_views"], s["p_min"], s["rhs"])
        K["prefix_cols"](q, gs(n_groups), (wg,), P, self.rivals, g, zero)
        if self.gpu:
            n = n_box
        else:
            got = np.zeros(1, np.int32)
            cl.enqueue_copy(q, got, self.n_cand, is_blocking=True)
            n = int(got[0])
        if n:
            K["conf_candidates"](q, gs(n), (wg,), P, b.edges, b.lut, self.lit, self.rivals, self.cells,
                                 self.cand, self.n_cand, self.confirmed_buf, s["tube"], zero)
        q.flush()

    # ------------------------------------------------------------------ the layer
    def run(self, params: np.ndarray, scalars: dict) -> None:
        """The pass of one ping whose update the backend has queued: ``params`` its PING_DTYPE record
        (the rivals' box; block fields filled here), ``scalars`` :func:`pass_scalars`'s."""
        n = params["box_n"].astype(np.int64)
        n_cols = int(n[0] * n[1]) if n[2] > 0 else 0
        if n_cols == 0:
            return
        self.b._block_params(params)
        n_box = n_cols * int(n[2])
        if self.kind == "warp":
            self._warp_pass(params, scalars, n_cols, n_box)
        else:
            self._opencl_pass(params, scalars, n_cols, n_box)

    def download(self, confirmed: np.ndarray, arcs: np.ndarray) -> None:
        """Copy the device's arrays into the host's (``confirmed`` uint8, ``arcs`` uint16, (n,))."""
        if self.kind == "warp":
            self.b.synchronize()
            confirmed[...] = self.confirmed.numpy()
            arcs[...] = self.arcs.numpy()
            return
        q = self.b.queue
        self.cl.enqueue_copy(q, confirmed, self.confirmed_buf, is_blocking=True)
        self.cl.enqueue_copy(q, arcs, self.arcs_buf, is_blocking=True)

    def upload(self, confirmed: np.ndarray, arcs: np.ndarray) -> None:
        """Replace the device's arrays with the host's."""
        c = np.ascontiguousarray(confirmed, np.uint8)
        a = np.ascontiguousarray(arcs, np.uint16)
        if self.kind == "warp":
            wp, dev = self.wp, self.b.dev
            self.confirmed.assign(wp.array(c, dtype=wp.uint8, device=dev))
            self.arcs.assign(wp.array(a, dtype=wp.uint16, device=dev))
            return
        q = self.b.queue
        self.cl.enqueue_copy(q, self.confirmed_buf, c, is_blocking=True)
        self.cl.enqueue_copy(q, self.arcs_buf, a, is_blocking=True)
