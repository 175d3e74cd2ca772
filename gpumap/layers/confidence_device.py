"""The confidence layer's per-ping pass on a map's device: the kernels of ``gpumap.kernels.confidence``
(Warp) and their twin ``confidence.cl`` (OpenCL), launched after the ping's update on the map's own
stream or queue, reading the map's pool where it lives (no read of the map to the host).

:class:`DeviceConfidence` keeps the layer's two arrays on the device (``confirmed`` uint8 and
``arcs`` uint16, flat over the grid in C order, as :class:`gpumap.layers.confidence.ConfidenceLayer`
keeps them on the host) and gives them the same values as :func:`gpumap.layers.confidence.confirm_ping`,
the NumPy reference, bit for bit (the tests compare every backend with it). The ``numpy`` backend
keeps running the reference itself.
"""

from __future__ import annotations

import functools
import math

import numpy as np

from gpumap.geometry import PING_DTYPE

__all__ = ["DeviceConfidence", "pass_scalars"]

#: warp-cpu: walk the columns and the candidates in two parts on two threads. Off: on the 2-core
#: machine under other jobs' load (load average ~8) the real tank mapped with the layer in 0.575 s
#: one thread, 0.887 s two (0.381 s without the layer; best of 4, 123 pings, 5 cm): the handoffs and
#: the second rival table cost more than the second core gave.
CPU_SPLIT = False
_KERNELS = ("lit_bits", "conf_voxels", "prefix_rows", "conf_candidates")


def pass_scalars(spec, params: np.ndarray, half_rad: float, tube_m: float, value_rule) -> dict:
    """The pass's scalar arguments: cos and sin of the rivals' half aperture and the tube (float32,
    as :func:`gpumap.layers.confidence.confirm_ping` rounds them), the column walk's widened range and slab
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
        # the widest beam, radians, a hair wider: the candidates' shortcut (conf_candidates) counts beams
        # of at most this width within an angle
        "beam_max": np.float32(float(np.max(np.diff(spec.beam_edges_rad))) * (1.0 + 1e-3)),
    }


def ctypes_size(struct) -> int:
    """Bytes of a Warp struct instance's ctypes image."""
    import ctypes

    return ctypes.sizeof(struct._ctype)


def lit_bits_host(image: np.ndarray, thr: float, out: np.ndarray) -> None:
    """The ``lit_bits`` kernel in NumPy: ``image`` ((n_bins, n_beams) float32) cells ``>= thr`` as
    bits into ``out`` ((n_bins, 4 nw) uint8, the uint32 words' bytes; little-endian: beam j is bit
    j % 32 of word j // 32)."""
    lit = image >= np.float32(thr)
    pad = out.shape[1] * 8 - lit.shape[1]
    if pad:
        lit = np.pad(lit, ((0, 0), (0, pad)))
    out[...] = np.packbits(lit, axis=1, bitorder="little")


class DeviceConfidence:
    """The layer's arrays and per-ping pass on ``backend`` (a Warp or OpenCL
    :class:`gpumap.backends.Backend` of a bounded grid of ``n_voxels`` voxels)."""

    def __init__(self, backend, spec, n_voxels: int) -> None:
        self.b = backend
        self.kind = "warp" if backend.name.startswith("warp") else "opencl"
        self.n_voxels = int(n_voxels)
        n_bins, n_beams = spec.image_shape
        self.n_bins, self.n_beams = n_bins, n_beams
        self.n_words = n_bins * ((n_beams + 31) // 32)  # the lit cells, a bit each
        self.table_n = n_bins * n_beams  # the rivals per cell (all zeros between pings)
        self.running_n = n_bins * (n_beams + 1)  # their running counts along each bin's beams
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
        self.lit = wp.zeros(self.n_words, dtype=wp.uint32, device=dev)
        self.n_cand = wp.zeros(2, dtype=int, device=dev)
        # CPUs: a rival table for each of the two threads (their atomics are plain adds)
        self.rivals = wp.zeros(self.table_n * (1 if self.gpu else 2), dtype=int, device=dev)
        self.running = wp.zeros(self.running_n, dtype=int, device=dev)
        if not self.gpu:  # CPUs: the whole-image passes in NumPy, on the arrays themselves
            n_bins, n_beams = self.n_bins, self.n_beams
            self.lit_np = self.lit.numpy().view(np.uint8).reshape(n_bins, -1)
            self.rivals_np = self.rivals.numpy().reshape(2, n_bins, n_beams)
            self.running_np = self.running.numpy().reshape(n_bins, n_beams + 1)
            self.n_cand_np = self.n_cand.numpy()
        self.cand = wp.empty(0, dtype=int, device=dev)
        self.steps = wp.empty(0, dtype=int, device=dev)
        self.cells = wp.empty(0, dtype=int, device=dev)
        self._cmds = None
        wp.load_module(k, device=dev)

    def _warp_pass(self, params: np.ndarray, s: dict, n_cols: int, n_box: int) -> None:
        import ctypes

        wp, b = self.wp, self.b
        dev = b.dev
        if self.cap < n_box:
            self.cap = max(n_box, 2 * self.cap)
            self.cand = wp.empty(2 * self.cap, dtype=int, device=dev)  # two lists (CPUs: one a thread)
            self.steps = wp.empty(2 * self.cap, dtype=int, device=dev)
            self.cells = wp.empty(self.cap, dtype=int, device=dev)
        # recorded again when the arrays or the rule's options change; the walk's bounds (which the
        # footprint pad of a pose covariance moves) are set on the recorded launches
        key = (self.cap, id(b.grid), id(b.index),
               *(v for n, v in s.items() if n not in ("rmax_c", "slab_c")))
        if self._cmds is None or self._cmds[0] != key:
            self._cmds = (key, self._record(s))
        cmds = self._cmds[1]
        bounds = (float(s["rmax_c"]), float(s["slab_c"]))
        if self._bounds != bounds:
            for cmd in cmds["conf_voxels"]:
                cmd.set_param_by_name("rmax_c", bounds[0])
                cmd.set_param_by_name("slab_c", bounds[1])
            self._bounds = bounds
        # the recorded launches hold the struct's memory: one copy gives them the ping
        ctypes.memmove(self._P_addr, params.ctypes.data, PING_DTYPE.itemsize)
        va, vb = cmds["conf_voxels"]
        ca, cb = cmds["conf_candidates"]
        if self.gpu:
            cmds["lit_bits"].launch()
            va.set_dim(n_cols)
            va.launch()
            cmds["prefix_rows"].launch()
            ca.set_dim(n_box)
            ca.launch()
            return
        # CPUs: the whole-image passes in NumPy (Warp's CPU code takes ~4 ns a cell there, NumPy a
        # tenth of that); the columns, then the candidates, in two parts on two threads (Warp's CPU
        # launches are serial and release the GIL; each part owns its columns and adds to its own
        # rival table and candidate list)
        lit_bits_host(b.image_np, float(params["thr"]), self.lit_np)
        self.n_cand_np[:] = 0
        split = self._pool_split()
        two = split is not None and n_cols >= 16
        h = n_cols // 2 if two else n_cols
        va.set_dim(h)
        if two:
            vb.set_param_by_name("offset", h)
            vb.set_dim(n_cols - h)
        self._both(va, vb if two else None, split)
        r0, r1 = self.rivals_np
        if two:
            np.add(r0, r1, out=r0)
            r1[...] = 0
        np.cumsum(r0, axis=1, out=self.running_np[:, 1:])
        r0[...] = 0  # all zeros again for the next ping
        n0, n1 = (int(x) for x in self.n_cand_np)
        ca.set_dim(n0)
        cb.set_dim(n1)
        self._both(ca if n0 else None, cb if n1 else None, split)

    @staticmethod
    def _both(a, b, split) -> None:
        """Launch recorded commands ``a`` and ``b`` (None: not that one), ``b`` on ``split``'s thread."""
        if b is None or split is None:
            for c in (a, b):
                if c is not None:
                    c.launch()
            return
        fut = split.submit(b.launch)
        try:
            if a is not None:
                a.launch()
        finally:
            fut.result()

    def _record(self, s: dict) -> dict:
        """Every launch of the pass recorded once (``record_cmd``) on this pass's arrays and scalars."""
        import ctypes

        wp, k, b = self.wp, self.k, self.b
        P = k.PingParams()
        if ctypes_size(P) != PING_DTYPE.itemsize:
            raise RuntimeError("confidence PingParams and PING_DTYPE have drifted apart")
        self._P, self._P_addr = P, ctypes.addressof(P._ctype)
        self._bounds = (float(s["rmax_c"]), float(s["slab_c"]))
        rec = {"device": b.dev, "record_cmd": True}
        pool = [b.edges, b.lut, b.index, b.grid, b.bright, b.count]
        voxel_args = [P, *pool, self.arcs, self.rivals, self.cells, self.cand, self.steps, self.n_cand,
                      s["cos_hv"], s["sin_hv"], s["tube"], s["rmax_c"], s["slab_c"], int(s["carve_views"]),
                      s["p_min"], s["rhs"], 0]
        cand_args = [P, b.edges, b.lut, self.lit, self.running, self.cells, self.cand, self.steps,
                     self.n_cand, self.confirmed, s["tube"], s["beam_max"], 0]
        n = self.n_bins
        stride = self.cap
        return {
            "lit_bits": wp.launch(k.lit_bits, dim=self.n_words,
                                  inputs=[P, b.image, self.lit, self.rivals, self.n_cand, 0], **rec),
            "conf_voxels": tuple(wp.launch(k.conf_voxels, dim=1, inputs=[*voxel_args, part, stride], **rec)
                                 for part in (0, 1)),
            "prefix_rows": wp.launch(k.prefix_rows, dim=n, inputs=[P, self.rivals, self.running, 0], **rec),
            "conf_candidates": tuple(wp.launch(k.conf_candidates, dim=1, inputs=[*cand_args, part, stride],
                                               **rec) for part in (0, 1)),
        }

    def _pool_split(self):
        """The CPU thread for the second part of a launch, or None (GPUs, one CPU thread, or
        :data:`CPU_SPLIT` off)."""
        import gpumap.backends.base as base

        return None if self.gpu or not CPU_SPLIT or base.CPU_THREADS < 2 else base._cpu_pool()

    # ------------------------------------------------------------------ OpenCL
    def _init_opencl(self) -> None:
        b = self.b
        cl = b.cl
        self.cl = cl
        self.gpu = bool(b.is_gpu)
        from gpumap.backends.opencl_backend import extra_program

        prg = extra_program(b.ctx, "confidence")
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
        self.lit = zeros(4 * self.n_words)
        self.rivals = zeros(4 * self.table_n)
        self.running = zeros(4 * self.running_n)
        self.n_cand = zeros(8)
        self.cand = zeros(4)
        self.steps = zeros(4)
        self.cells = zeros(4)
        self.wg = 64
        q.finish()

    def _opencl_pass(self, params: np.ndarray, s: dict, n_cols: int, n_box: int) -> None:
        b, K = self.b, self.kernels
        q = b.queue
        if self.cap < n_box:
            self.cap = max(n_box, 2 * self.cap)
            self.cand = self._zeros(4 * self.cap)
            self.steps = self._zeros(4 * self.cap)
            self.cells = self._zeros(4 * self.cap)
        from gpumap.backends.base import N_SLOTS

        image = b.images[(b.slot - 1) % N_SLOTS]  # the ping's image, as its update read it
        P = np.asarray(params, dtype=PING_DTYPE)
        wg = self.wg

        def gs(n):
            return (-(-int(n) // wg) * wg,)

        pool = (b.edges, b.lut, b.index, b.grid, b.bright, b.count)
        zero = np.int32(0)
        K["lit_bits"](q, gs(self.n_words), (wg,), P, image, self.lit, self.rivals, self.n_cand, zero)
        K["conf_voxels"](q, gs(n_cols), (wg,), P, *pool, self.arcs_buf, self.rivals, self.cells, self.cand,
                         self.steps, self.n_cand, s["cos_hv"], s["sin_hv"], s["tube"], s["rmax_c"],
                         s["slab_c"], s["carve_views"],
                         s["p_min"], s["rhs"], zero, zero, np.int32(self.cap))
        K["prefix_rows"](q, gs(self.n_bins), (wg,), P, self.rivals, self.running, zero)
        # a work-item per box voxel, those past the list's length return at once: the host never
        # waits for the device (a read of the list's length would)
        n = n_box
        if n:
            K["conf_candidates"](q, gs(n), (wg,), P, b.edges, b.lut, self.lit, self.running, self.cells,
                                 self.cand, self.steps, self.n_cand, self.confirmed_buf, s["tube"],
                                 s["beam_max"], zero,
                                 zero, np.int32(self.cap))
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
