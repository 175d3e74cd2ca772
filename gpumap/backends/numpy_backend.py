"""The ``numpy`` backend: the oracle (:mod:`gpumap.reference`) behind the :class:`Backend`
interface, its pool in host memory."""

from __future__ import annotations

import numpy as np

from gpumap.backends.base import U8_SCALE, Backend, _check_rule
from gpumap.geometry import beam_tan_edges


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
