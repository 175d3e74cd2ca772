"""Block-sparse min-max maps: memory only for the blocks a ping has observed.

:class:`SparseMinMaxMapper` has :class:`~gpumap.MinMaxMapper`'s methods and semantics
(never observed = unknown; the same visible and plain rules; every backend) over an
unbounded world, or a :class:`SparseSpec` box, but allocates its voxels in blocks of
``B^3`` (``B = 8``: 512 voxels) only where pings look. Where both exist its values equal the
dense grid's bit for bit: the kernels run the dense kernels' per-voxel code
(``minmax.voxel_ping_value`` / ``update_voxel``) on the same voxel centres.

Design (what was chosen and why)
--------------------------------
Two candidates were weighed:

- **Warp's NanoVDB volumes** (``wp.Volume.allocate_by_tiles``, in-place rebuild since 1.16):
  a tree that grows where tiles are listed. But ``allocate_by_tiles`` runs on CUDA only, so
  ``warp-cpu`` and every OpenCL device would need a second design anyway; a volume holds one
  value type (float, vec3, int32 or index), so the visible rule's float + float + uint8 per
  voxel would be three trees or an index grid with side arrays; and a tree walk per voxel
  costs more than the dense grid's single address computation.
- **A host-kept block table** (chosen): a dense coarse *index* of int32 slots, one per
  ``B^3`` block of the map's box (``-1`` = no block; 4 bytes per 512 voxels, 1/1,152 of the
  dense visible-rule grid, grown by the host when an unbounded map's pings leave it), and a
  *pool* of blocks (per slot ``B^3`` float32 ``min_all``, and for the visible rule float32
  ``bright`` and uint8 ``count``: 9 bytes per voxel; 4 for the plain rule) grown by 1.5x.
  Per ping the host finds, vectorised in NumPy over the (i, j) *block columns* of the ping's
  box, the z-range of blocks that the field of view can reach (the dense kernels'
  ``column_range`` bound, widened to a block column's footprint and padded against float32
  rounding, so it is conservative), gives new blocks a slot, and launches one kernel to
  initialise them and one to integrate: the dense gather over the ping's voxel box, with a
  voxel's address looked up through the index (an O(1) read: no hash, no probing, nothing
  OpenCL 1.2 lacks). The same code serves Warp (CPU and CUDA), OpenCL and the NumPy oracle.
  The kernel flags any observed voxel that found no block (``err``): the tests check it
  never happens. An open-addressing hash on device would lift the coarse index's one
  limit, that it spans the box of everything mapped (a 10 km diagonal transit at 5 cm
  needs a 2 GB index): not needed for a survey area, left for later.

The conservative block test can allocate a block whose voxels no ping observes in the
end (the fan's edge grazes it). Each block carries a "seen" byte set by the kernel;
before the pool grows, and before :meth:`memory_stats` and :meth:`save`, blocks never seen
are freed, so the map holds only blocks with an observed voxel.

Memory cap: ``max_bytes`` bounds the pool plus the index. A ping that needs more raises
:class:`MapMemoryError` before it changes the map (``evict=None``, default), or with
``evict="farthest"`` frees the blocks farthest from the sonar that the ping does not touch
(their voxels become unknown again) until the new blocks fit.
"""

from __future__ import annotations

import ctypes
import functools
import json
import math
import os
import threading
import zipfile
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np

from gpumap.atomic import atomic_write
from gpumap.backends import (
    AUTO_ORDER,
    BACKENDS,
    CPU_CHUNK,
    GPU_CHUNK,
    N_SLOTS,
    U8_SCALE,
    opencl_host_table,
    table_size,
    warp_host_table,
    warp_launch_halves,
    warp_upload_image,
)
from gpumap.errors import BackendUnavailableError, check_carve_views, check_finite_scalar, check_pose
from gpumap.geometry import (
    MAX_TABLE_LEVELS,
    PING_DTYPE,
    RULES,
    beam_lut,
    beam_tan_edges,
    pose_pad_m,
    set_footprint_pad,
    static_params,
)
from gpumap.spec import GridSpec, SonarSpec

__all__ = ["MapMemoryError", "SparseMinMaxMapper", "SparseSpec"]

FILE_FORMAT = "gpumap.SparseMinMaxMapper"
FILE_VERSION = 1
GROWTH = 1.5  # the pool grows by this factor (at least to what a ping needs)
_CANDIDATE_GROUP = 8  # pings per vectorised block test in integrate_batch
_MAX_INDEX_BLOCKS = 2**31 - 1
# voxel indices stay well inside int32 (kernels add block offsets to them)
_MAX_VOXEL_INDEX = 2**30
_MAX_BOX_VOXELS = 2**31 - 1


class MapMemoryError(ValueError):
    """A ping (or a spec) needs more memory than the cap or the device allows; the map is unchanged."""


@dataclass(frozen=True)
class SparseSpec:
    """A block-sparse world grid of cubic voxels.

    Parameters
    ----------
    voxel_size_m : float
        Edge of a cubic voxel, metres.
    bounds : ((3,), (3,)) float or None
        Optional box ``[min, max)`` in the world frame, metres: voxels outside it are never
        mapped, and its min corner is the grid origin (so the map lines up with
        ``GridSpec(min, max, voxel_size_m)`` voxel for voxel). None (default): unbounded, the
        origin at ``origin_m``.
    block : int
        Voxels per block edge (2..32, default 8: blocks of 512 voxels).
    origin_m : (3,) float
        Grid origin of an unbounded map (voxel ``(i, j, k)`` is centred at
        ``origin + (idx + 0.5) * voxel_size_m``, indices may be negative). Default (0, 0, 0);
        must be left out with ``bounds``.
    """

    voxel_size_m: float
    bounds: tuple | None = None
    block: int = 8
    origin_m: tuple | None = None

    def __post_init__(self) -> None:
        s = check_finite_scalar(self.voxel_size_m, "voxel_size_m")
        if s <= 0:
            raise ValueError(f"Expected voxel_size_m > 0, but got {s}")
        b = self.block
        if isinstance(b, bool) or not isinstance(b, (int, np.integer)) or not 2 <= b <= 32:
            raise ValueError(f"Expected block to be an integer in 2..32, but got {b!r}")
        object.__setattr__(self, "voxel_size_m", s)
        object.__setattr__(self, "block", int(b))
        if self.bounds is not None:
            if self.origin_m is not None:
                raise ValueError("Expected origin_m to be left out with bounds (the origin is bounds' min)")
            try:
                lo, hi = self.bounds
            except (TypeError, ValueError) as e:
                raise ValueError(
                    f"Expected bounds as (min_corner_m, max_corner_m), but got {self.bounds!r}"
                ) from e
            lo, hi = _vec3(lo, "bounds[0]"), _vec3(hi, "bounds[1]")
            if any(h <= lo_ for lo_, h in zip(lo, hi, strict=True)):
                raise ValueError(f"Expected bounds with max > min on every axis, but got {lo} and {hi}")
            object.__setattr__(self, "bounds", (lo, hi))
            shape = self.shape
            if max(shape) > _MAX_VOXEL_INDEX:
                raise ValueError(
                    f"Expected at most {_MAX_VOXEL_INDEX} voxels per axis, but bounds {lo}-{hi} at "
                    f"voxel_size_m={s} give {shape}"
                )
        else:
            o = (0.0, 0.0, 0.0) if self.origin_m is None else _vec3(self.origin_m, "origin_m")
            object.__setattr__(self, "origin_m", o)

    @property
    def origin(self) -> tuple[float, float, float]:
        """The grid origin, metres: ``bounds[0]``, or ``origin_m`` for an unbounded map."""
        return self.bounds[0] if self.bounds is not None else self.origin_m

    @property
    def shape(self) -> tuple[int, int, int] | None:
        """Voxels per axis inside ``bounds`` (as :class:`GridSpec` counts them), None if unbounded."""
        if self.bounds is None:
            return None
        s = self.voxel_size_m
        lo, hi = self.bounds
        return tuple(int(math.ceil(round((h - a) / s, 9))) for a, h in zip(lo, hi, strict=True))

    @property
    def grid(self) -> GridSpec | None:
        """The dense :class:`GridSpec` over ``bounds`` (None if unbounded; raises if too large)."""
        return None if self.bounds is None else GridSpec(self.bounds[0], self.bounds[1], self.voxel_size_m)

    def to_dict(self) -> dict:
        return {
            "voxel_size_m": self.voxel_size_m,
            "bounds": None if self.bounds is None else [list(self.bounds[0]), list(self.bounds[1])],
            "block": self.block,
            "origin_m": None if self.bounds is not None else list(self.origin_m),
        }

    @classmethod
    def from_dict(cls, d: dict) -> SparseSpec:
        b = d["bounds"]
        return cls(
            d["voxel_size_m"],
            None if b is None else (tuple(b[0]), tuple(b[1])),
            int(d["block"]),
            None if b is not None else tuple(d["origin_m"]),
        )


def _vec3(v: object, name: str) -> tuple[float, float, float]:
    a = np.asarray(v, dtype=np.float64)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ValueError(f"Expected 3 finite values for '{name}', but got {v!r}")
    return (float(a[0]), float(a[1]), float(a[2]))


# ----------------------------------------------------------------------------- backends
class _Backend:
    """The block pool and the coarse index on one device. Slots hold ``B^3`` voxels each."""

    name: str
    device: str

    def grow(self, cap: int) -> None:
        """Make room for ``cap`` slots, keeping the first ``self.cap``."""
        raise NotImplementedError

    def set_index(self, index: np.ndarray) -> None:
        """Replace the whole coarse index with ``index`` ((n,) int32)."""
        raise NotImplementedError

    def set_blocks(self, slots: np.ndarray, lins: np.ndarray) -> None:
        """index[lins] = slots; each slot >= 0 becomes a never-observed block (seen 0)."""
        raise NotImplementedError

    def integrate(self, params, image, n_cols, ilo, nbk) -> None:
        raise NotImplementedError

    def read(self) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
        """Copies of the pool: min_all (cap B^3,) float32, bright and count (visible rule)."""
        raise NotImplementedError

    def write_blocks(self, slots, grid, bright, count) -> None:
        """Blocks ``slots`` take these values ((n, B^3) each) and are marked seen."""
        raise NotImplementedError

    def read_seen(self) -> np.ndarray:
        raise NotImplementedError

    def read_err(self) -> int:
        raise NotImplementedError

    def synchronize(self) -> None:
        pass


class _NumpyBackend(_Backend):
    """The oracle: :mod:`gpumap.reference`'s per-voxel code over the ping's box, then the
    same index look-up as the kernels."""

    name = "numpy"
    device = "cpu (NumPy reference)"

    def __init__(self, spec: SonarSpec, visible: bool, B: int, cap: int) -> None:
        self.B, self.B3, self.visible = B, B**3, visible
        self.cap = 0
        self.grid = np.empty(0, np.float32)
        self.bright = np.empty(0, np.float32) if visible else None
        self.count = np.empty(0, np.uint8) if visible else None
        self.seen = np.empty(0, np.uint8)
        self.index = np.empty(0, np.int32)
        self.err = 0
        self.edges = beam_tan_edges(spec)
        self.buf = np.empty(spec.image_shape, np.float32)
        self.grow(cap)

    def grow(self, cap):
        n = (cap - self.cap) * self.B3
        self.grid = np.concatenate([self.grid, np.full(n, np.inf, np.float32)])
        if self.visible:
            self.bright = np.concatenate([self.bright, np.full(n, np.inf, np.float32)])
            self.count = np.concatenate([self.count, np.zeros(n, np.uint8)])
        self.seen = np.concatenate([self.seen, np.zeros(cap - self.cap, np.uint8)])
        self.cap = cap

    def set_index(self, index):
        self.index = np.array(index, np.int32)

    def set_blocks(self, slots, lins):
        live = slots[slots >= 0].astype(np.int64)
        a = (live[:, None] * self.B3 + np.arange(self.B3)).ravel()
        self.grid[a] = np.inf
        if self.visible:
            self.bright[a] = np.inf
            self.count[a] = 0
        self.seen[live] = 0
        self.index[lins] = slots

    def integrate(self, params, image, n_cols, ilo, nbk):
        from gpumap import reference

        if image.dtype == np.uint8:
            image = np.multiply(image, U8_SCALE, out=self.buf)
        lo = params["box_lo"].astype(np.int64)
        n = params["box_n"].astype(np.int64)
        B = self.B
        ilo = np.asarray(ilo, np.int64)
        nbk = np.asarray(nbk, np.int64)
        slab = max(1, int(4_000_000 // max(1, n[0] * n[1])))
        II, JJ = np.meshgrid(np.arange(n[0]) + lo[0], np.arange(n[1]) + lo[1], indexing="ij")
        II, JJ = II.ravel(), JJ.ravel()
        for k0 in range(0, int(n[2]), slab):
            ks = np.arange(k0, min(int(n[2]), k0 + slab)) + lo[2]
            idx = np.stack([np.repeat(II, ks.size), np.repeat(JJ, ks.size), np.tile(ks, II.size)], axis=-1)
            c = params["origin"] + (idx.astype(np.float32) + np.float32(0.5)) * params["voxel"]
            v, clear = reference.voxel_ping_values(params, image, self.edges, c, clear=True)
            m = v >= 0
            rel = idx[m] - ilo
            b = rel // B
            inside = np.all((rel >= 0) & (b < nbk), axis=1)
            slot = np.full(rel.shape[0], -1, np.int64)
            lin = (b[inside, 0] * nbk[1] + b[inside, 1]) * nbk[2] + b[inside, 2]
            slot[inside] = self.index[lin]
            ok = slot >= 0
            if not ok.all():
                self.err = 1
            w = rel[ok] - b[ok] * B
            addr = slot[ok] * self.B3 + (w[:, 0] * B + w[:, 1]) * B + w[:, 2]
            vv = v[m][ok]
            self.grid[addr] = np.minimum(self.grid[addr], vv)
            if self.visible:
                reference._update_visible(params, vv, clear[m][ok], addr, self.bright, self.count)
            self.seen[slot[ok]] = 1

    def read(self):
        return (
            self.grid.copy(),
            None if not self.visible else self.bright.copy(),
            None if not self.visible else self.count.copy(),
        )

    def write_blocks(self, slots, grid, bright, count):
        addr = (slots[:, None] * self.B3 + np.arange(self.B3)).ravel()
        self.grid[addr] = grid.ravel()
        if self.visible:
            self.bright[addr] = bright.ravel()
            self.count[addr] = count.ravel()
        self.seen[slots] = 1

    def read_seen(self):
        return self.seen.copy()

    def read_err(self):
        return self.err


def _params_struct(minmax, p):
    from gpumap.backends import _warp_params

    return _warp_params(minmax, p)


class _WarpBackend(_Backend):
    def __init__(self, spec: SonarSpec, visible: bool, B: int, cap: int, device: str) -> None:
        from gpumap.backends import _warp

        wp, minmax = _warp()
        if device == "cuda" and not wp.is_cuda_available():
            raise BackendUnavailableError("warp-cuda needs a CUDA device, and Warp finds none here")
        from gpumap.kernels import sparse as ks

        self.wp, self.k, self.ks = wp, minmax, ks
        self.dev = wp.get_device("cuda:0" if device == "cuda" else "cpu")
        self.name = f"warp-{device}"
        self.device = f"{self.dev.alias} ({self.dev.name})"
        self.B, self.B3, self.visible = B, B**3, visible
        n_bins, n_beams = spec.image_shape
        self.n_bins, self.n_beams = n_bins, n_beams
        with wp.ScopedDevice(self.dev):
            self.cap = 0
            self.grid = wp.empty(0, dtype=float)
            self.bright = wp.empty(0, dtype=float)
            self.count = wp.empty(0, dtype=wp.uint8)
            self.seen = wp.empty(0, dtype=wp.uint8)
            self.index = wp.full(1, value=-1, dtype=int)
            self.err = wp.zeros(1, dtype=int)
            self.first_bright = wp.zeros(n_beams, dtype=int)
            self.edges = wp.array(beam_tan_edges(spec), dtype=float)
            self.lut = wp.array(beam_lut(spec), dtype=int)
            self.image = wp.empty((n_bins, n_beams), dtype=float)
            self.table = wp.empty(table_size(spec), dtype=float)
            self.image_u8 = wp.empty((n_bins, n_beams), dtype=wp.uint8)
        self.chunk = GPU_CHUNK if self.dev.is_cuda else CPU_CHUNK
        self.staging, self.events, self.slot = [], [], 0
        if self.dev.is_cuda:
            self.staging = [
                wp.empty((n_bins, n_beams), dtype=float, device="cpu", pinned=True) for _ in range(N_SLOTS)
            ]
            self.staging_u8 = [
                wp.empty((n_bins, n_beams), dtype=wp.uint8, device="cpu", pinned=True) for _ in range(N_SLOTS)
            ]
            self.staging_np = [a.numpy() for a in self.staging]
            self.staging_u8_np = [a.numpy() for a in self.staging_u8]
            self.events = [None] * N_SLOTS
            self.cmd_u8 = wp.launch(
                minmax.convert_u8,
                dim=(n_bins, n_beams),
                inputs=[self.image_u8, float(U8_SCALE), self.image],
                device=self.dev,
                record_cmd=True,
            )
        self.istage, self.ievents, self.islot, self.ipairs = [None] * N_SLOTS, [None] * N_SLOTS, 0, None
        self.image_np = None if self.dev.is_cuda else self.image.numpy()
        if not self.dev.is_cuda:  # CPUs: the max table in NumPy, the gather on two threads
            from gpumap.backends import CPU_THREADS, _cpu_pool

            nl = min(n_beams.bit_length(), MAX_TABLE_LEVELS)
            self.table_np = self.table.numpy()[: nl * n_bins * n_beams].reshape(nl, n_bins, n_beams)
            self.table_u8 = np.empty(self.table_np.shape, np.uint8)
            self._rows = {}
            self._pool = _cpu_pool() if CPU_THREADS > 1 else None
        self._P = None
        self._cmds = None
        self._gather = None
        self._init_cmd = None
        self.grow(cap)
        wp.load_module(minmax, device=self.dev)
        wp.load_module(ks, device=self.dev)

    def grow(self, cap):
        wp = self.wp
        n_old = self.cap * self.B3
        with wp.ScopedDevice(self.dev):
            grid = wp.full(cap * self.B3, value=np.inf, dtype=float)
            seen = wp.zeros(cap, dtype=wp.uint8)
            if n_old:
                wp.copy(grid, self.grid, count=n_old)
                wp.copy(seen, self.seen, count=self.cap)
            self.grid, self.seen = grid, seen
            if self.visible:
                bright = wp.full(cap * self.B3, value=np.inf, dtype=float)
                count = wp.zeros(cap * self.B3, dtype=wp.uint8)
                if n_old:
                    wp.copy(bright, self.bright, count=n_old)
                    wp.copy(count, self.count, count=n_old)
                self.bright, self.count = bright, count
        self.cap = cap
        self._gather = None
        self._init_cmd = None

    def set_index(self, index):
        self.index = self.wp.array(np.ascontiguousarray(index, np.int32), dtype=int, device=self.dev)
        self._gather = None
        self._init_cmd = None

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
        wp = self.wp
        n = len(slots)
        if n == 0:
            return
        pairs = self._stage_pairs(slots, lins)
        if self._init_cmd is None or self._init_cmd[0] is not pairs:
            args = [
                pairs,
                n,
                self.B3,
                int(self.visible),
                float(np.inf),
                self.index,
                self.grid,
                self.bright,
                self.count,
                self.seen,
            ]
            cmd = wp.launch(
                self.ks.init_blocks, dim=n * self.B3, inputs=args, device=self.dev, record_cmd=True
            )
            self._init_cmd = (pairs, cmd)
        cmd = self._init_cmd[1]
        cmd.set_param_by_name("n", n)
        cmd.set_dim(n * self.B3)
        cmd.launch()

    def integrate(self, params, image, n_cols, ilo, nbk):
        wp, k = self.wp, self.k
        warp_upload_image(self, image)
        params["chunk"] = self.chunk
        if self._P is None:
            self._P = _params_struct(k, params)
            self._P2 = _params_struct(k, params)  # CPUs: the second half of the box's rows
            self._P_addr = ctypes.addressof(self._P._ctype)
            self._P2_addr = ctypes.addressof(self._P2._ctype)
            P = self._P
            rec = {"device": self.dev, "record_cmd": True}
            cmds = []
            if int(params["rule"]) == 1:
                cmds.append(
                    wp.launch(
                        k.find_first_bright,
                        dim=self.n_beams,
                        inputs=[P, self.image, self.first_bright],
                        **rec,
                    )
                )
            if self.dev.is_cuda:  # one thread per cell; CPUs build the table in NumPy (build_table_host)
                cells = (self.n_bins, self.n_beams)
                cmds += [
                    wp.launch(k.build_bin_window_cells, dim=cells, inputs=[P, self.image, self.table], **rec),
                    wp.launch(k.build_beam_levels_cells, dim=cells, inputs=[P, self.table], **rec),
                ]
            self._cmds = cmds
        ctypes.memmove(self._P_addr, params.ctypes.data, PING_DTYPE.itemsize)
        key = (tuple(int(x) for x in ilo), tuple(int(x) for x in nbk))
        if self._gather is None or self._gather[0] != key:

            def rec_gather(P):
                return wp.launch(
                    self.ks.integrate_blocks,
                    dim=1,
                    inputs=[
                        P,
                        self.image,
                        self.edges,
                        self.lut,
                        self.table,
                        self.first_bright,
                        self.index,
                        wp.vec3i(*key[0]),
                        wp.vec3i(*key[1]),
                        self.B,
                        self.grid,
                        self.bright,
                        self.count,
                        self.seen,
                        self.err,
                    ],
                    device=self.dev,
                    record_cmd=True,
                )

            self._gather = (key, rec_gather(self._P), None if self.dev.is_cuda else rec_gather(self._P2))
        for cmd in self._cmds:
            cmd.launch()
        if not self.dev.is_cuda:
            warp_host_table(self, params, image)
        _, cmd, cmd2 = self._gather
        n_chunks = -(-int(params["box_n"][2]) // self.chunk)
        n0 = int(params["box_n"][0])
        if cmd2 is None or self._pool is None or n0 < 2 or n_cols < 64:
            cmd.set_dim(n_cols * n_chunks)
            cmd.launch()
            return
        # CPUs: two halves of the box's rows, one per core (each owns its voxels; Warp's CPU
        # kernels are serial and a launch releases the GIL)
        warp_launch_halves(self, params, cmd, cmd2, n_cols, n_chunks)

    def read(self):
        g = self.grid.numpy().copy()
        if not self.visible:
            return g, None, None
        return g, self.bright.numpy().copy(), self.count.numpy().copy()

    def write_blocks(self, slots, grid, bright, count):
        wp = self.wp
        g, b, c = self.read()
        seen = self.seen.numpy().copy()
        addr = (slots[:, None] * self.B3 + np.arange(self.B3)).ravel()
        g[addr] = grid.ravel()
        self.grid.assign(wp.array(g, dtype=float, device=self.dev))
        if self.visible:
            b[addr] = bright.ravel()
            c[addr] = count.ravel()
            self.bright.assign(wp.array(b, dtype=float, device=self.dev))
            self.count.assign(wp.array(c, dtype=wp.uint8, device=self.dev))
        seen[slots] = 1
        self.seen.assign(wp.array(seen, dtype=wp.uint8, device=self.dev))

    def read_seen(self):
        return self.seen.numpy().copy()

    def read_err(self):
        return int(self.err.numpy()[0])

    def synchronize(self):
        self.wp.synchronize_device(self.dev)


_CL_PROGRAMS: dict[int, object] = {}
_CL_LOCK = threading.Lock()


def _cl_program(device):
    """(context, program of minmax.cl + sparse.cl) for ``device``, built once per process."""
    from gpumap.backends import _opencl, _opencl_context

    cl = _opencl()
    ctx, _ = _opencl_context(device)
    key = int(device.int_ptr)
    with _CL_LOCK:
        if key not in _CL_PROGRAMS:
            kd = resources.files("gpumap.kernels")
            src = kd.joinpath("minmax.cl").read_text() + "\n" + kd.joinpath("sparse.cl").read_text()
            try:
                prg = cl.Program(ctx, src).build(options=["-cl-fp32-correctly-rounded-divide-sqrt"])
            except cl.Error:
                prg = cl.Program(ctx, src).build()
            _CL_PROGRAMS[key] = prg
        return ctx, _CL_PROGRAMS[key]


class _OpenCLBackend(_Backend):
    def __init__(self, spec: SonarSpec, visible: bool, B: int, cap: int, kind: str) -> None:
        from gpumap.backends import _opencl, usable_opencl_device

        cl = _opencl()
        d = usable_opencl_device(kind)
        self.cl, self.d = cl, d
        self.ctx, prg = _cl_program(d)
        self.queue = cl.CommandQueue(self.ctx)
        self.is_gpu = bool(d.type & cl.device_type.GPU)
        # named as gpumap info and backend= name it: the device it runs on, not how it was asked for
        self.name = "opencl-gpu" if self.is_gpu else "opencl-cpu"
        self.device = f"{d.platform.name.strip()}: {d.name.strip()}"
        self.B, self.B3, self.visible = B, B**3, visible
        n_bins, n_beams = spec.image_shape
        self.n_bins, self.n_beams = n_bins, n_beams
        mf = cl.mem_flags
        self.mf = mf
        self.cap = 0
        self.grid = self.bright = self.count = self.seen = None
        self.index = self._buf(4)
        self.err = self._buf(4)
        cl.enqueue_fill_buffer(self.queue, self.err, np.int32(0), 0, 4)
        self.first_bright = self._buf(4 * n_beams)
        self.edges = cl.Buffer(self.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=beam_tan_edges(spec))
        self.lut = cl.Buffer(self.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=beam_lut(spec))
        self.images = [self._buf(4 * n_bins * n_beams) for _ in range(N_SLOTS)]
        self.images_u8 = [self._buf(n_bins * n_beams) for _ in range(N_SLOTS)]
        self.host = [np.empty((n_bins, n_beams), np.float32) for _ in range(N_SLOTS)]
        self.host_u8 = [np.empty((n_bins, n_beams), np.uint8) for _ in range(N_SLOTS)]
        self.uploads = [None] * N_SLOTS
        self.slot = 0
        # CPUs: the max table built in NumPy straight into the mapped buffer (as the dense backend)
        flags = self.mf.READ_WRITE | (0 if d.type & cl.device_type.GPU else self.mf.ALLOC_HOST_PTR)
        self.table = cl.Buffer(self.ctx, flags, size=4 * table_size(spec))
        self.n_levels = min(n_beams.bit_length(), MAX_TABLE_LEVELS)
        self.table_u8 = np.empty((self.n_levels, n_bins, n_beams), np.uint8)
        self._rows = {}
        from gpumap.backends import CPU_THREADS, _cpu_pool

        self._pool = _cpu_pool() if CPU_THREADS > 1 else None
        self.chunk = GPU_CHUNK if self.is_gpu else CPU_CHUNK
        k = functools.partial(cl.Kernel, prg)
        self.k_gather, self.k_init, self.k_u8, self.k_first = (
            k("integrate_blocks"),
            k("init_blocks"),
            k("convert_u8"),
            k("find_first_bright"),
        )
        if self.is_gpu:
            self.k_window, self.k_levels = k("build_bin_window_cells"), k("build_beam_levels_cells")
        else:
            self.k_window, self.k_levels = k("build_bin_window"), k("build_beam_levels")
        self.wg = 128
        self.ihost = [np.empty(4096, np.int32) for _ in range(N_SLOTS)]
        self.iuploads, self.islot, self.ipairs_n = [None] * N_SLOTS, 0, 4096
        self.ipairs = self._buf(4 * self.ipairs_n)
        self.grow(cap)

    def _buf(self, nbytes: int):
        return self.cl.Buffer(self.ctx, self.mf.READ_WRITE, size=max(4, int(nbytes)))

    def grow(self, cap):
        cl, q = self.cl, self.queue
        n = cap * self.B3
        if 4 * n > self.d.max_mem_alloc_size:
            raise MapMemoryError(
                f"Expected a block pool that fits in one OpenCL buffer, but {cap} blocks need "
                f"{4 * n / 2**30:.2f} GiB and {self.d.name.strip()} allows "
                f"{self.d.max_mem_alloc_size / 2**30:.2f} GiB"
            )
        n_old = self.cap * self.B3
        arrays = [("grid", 4, np.float32(np.inf)), ("seen", 1 / self.B3, np.uint8(0))]
        if self.visible:
            arrays += [("bright", 4, np.float32(np.inf)), ("count", 1, np.uint8(0))]
        for name, per, fill in arrays:
            nb, ob = int(per * n), int(per * n_old)
            new = self._buf(nb)
            cl.enqueue_fill_buffer(q, new, fill, 0, -(-max(4, nb) // fill.itemsize) * fill.itemsize)
            if ob:
                cl.enqueue_copy(q, new, getattr(self, name), byte_count=ob)
            setattr(self, name, new)
        if not self.visible:
            self.bright, self.count = self._buf(4), self._buf(4)
        self.cap = cap
        q.finish()

    def set_index(self, index):
        a = np.ascontiguousarray(index, np.int32)
        self.index = self._buf(a.nbytes)
        self.cl.enqueue_copy(self.queue, self.index, a, is_blocking=True)

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
        gs = -(-(n * self.B3) // self.wg) * self.wg
        i32 = np.int32
        self.k_init(
            self.queue,
            (gs,),
            (self.wg,),
            self.ipairs,
            i32(n),
            i32(self.B3),
            i32(self.visible),
            np.float32(np.inf),
            self.index,
            self.grid,
            self.bright,
            self.count,
            self.seen,
        )

    def integrate(self, params, image, n_cols, ilo, nbk):
        cl = self.cl
        s = self.slot
        self.slot = (s + 1) % N_SLOTS
        if self.uploads[s] is not None:
            self.uploads[s].wait()
        image_buf = self.images[s]
        if image.dtype == np.uint8:
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
        P = np.asarray(params, dtype=PING_DTYPE)
        if int(params["rule"]) == 1:
            gs = -(-self.n_beams // 16) * 16
            self.k_first(self.queue, (gs,), (16,), P, image_buf, self.first_bright)
        if self.is_gpu:
            gs = -(-(self.n_bins * self.n_beams) // self.wg) * self.wg
            self.k_window(self.queue, (gs,), (self.wg,), P, image_buf, self.table)
            self.k_levels(self.queue, (gs,), (self.wg,), P, self.table)
        else:
            opencl_host_table(self, params, image)
        n = n_cols * -(-int(params["box_n"][2]) // self.chunk)
        gs = -(-n // self.wg) * self.wg
        i32 = np.int32
        self.k_gather(
            self.queue,
            (gs,),
            (self.wg,),
            P,
            image_buf,
            self.edges,
            self.lut,
            self.table,
            i32(1),
            self.first_bright,
            self.index,
            *(i32(x) for x in ilo),
            *(i32(x) for x in nbk),
            i32(self.B),
            self.grid,
            self.bright,
            self.count,
            self.seen,
            self.err,
        )
        self.queue.flush()

    def _read(self, buf, n, dt):
        out = np.empty(n, dt)
        if n:
            self.cl.enqueue_copy(self.queue, out, buf, is_blocking=True)
        return out

    def read(self):
        n = self.cap * self.B3
        g = self._read(self.grid, n, np.float32)
        if not self.visible:
            return g, None, None
        return g, self._read(self.bright, n, np.float32), self._read(self.count, n, np.uint8)

    def write_blocks(self, slots, grid, bright, count):
        g, b, c = self.read()
        seen = self.read_seen()
        addr = (slots[:, None] * self.B3 + np.arange(self.B3)).ravel()
        g[addr] = grid.ravel()
        q = self.queue
        self.cl.enqueue_copy(q, self.grid, g, is_blocking=True)
        if self.visible:
            b[addr] = bright.ravel()
            c[addr] = count.ravel()
            self.cl.enqueue_copy(q, self.bright, b, is_blocking=True)
            self.cl.enqueue_copy(q, self.count, c, is_blocking=True)
        seen[slots] = 1
        self.cl.enqueue_copy(q, self.seen, seen, is_blocking=True)

    def read_seen(self):
        return self._read(self.seen, self.cap, np.uint8)

    def read_err(self):
        return int(self._read(self.err, 1, np.int32)[0])

    def synchronize(self):
        self.queue.finish()


def _make_backend(name: str, spec: SonarSpec, visible: bool, B: int, cap: int) -> _Backend:
    if name == "numpy":
        return _NumpyBackend(spec, visible, B, cap)
    if name in ("warp-cpu", "warp-cuda"):
        return _WarpBackend(spec, visible, B, cap, name.split("-")[1])
    if name in ("opencl", "opencl-gpu", "opencl-cpu"):
        kind = {"opencl": "any", "opencl-gpu": "gpu", "opencl-cpu": "cpu"}[name]
        return _OpenCLBackend(spec, visible, B, cap, kind)
    raise ValueError(f"Expected backend to be 'auto' or one of {BACKENDS}, but got {name!r}")


# ----------------------------------------------------------------------------- the mapper
class SparseMinMaxMapper:
    """Min-max occupancy map stored in blocks allocated where pings look.

    The same update as :class:`gpumap.MinMaxMapper` with ``method="gather"`` (see there for
    ``rule``, ``threshold``, ``carve_views``, ``shadow_m`` and ``backend``), on a
    :class:`SparseSpec` instead of a fixed :class:`~gpumap.GridSpec`: identical values
    wherever both have voxels. Memory grows with what the sonar has seen (see
    :meth:`memory_stats`); the module docstring says how.

    Extra parameters
    ----------------
    max_bytes : int or None
        Cap on the block pool plus the coarse index, bytes (None: what the device allows).
    evict : None or "farthest"
        What a ping that would pass ``max_bytes`` does: None raises :class:`MapMemoryError`
        with the map unchanged; ``"farthest"`` frees the blocks farthest from the sonar (block
        centre to the sonar's position) that the ping does not reach, which become unknown.
    initial_blocks : int
        Pool slots allocated up front (default 64; the pool grows by 1.5x as needed).
    """

    def __init__(
        self,
        spec: SonarSpec,
        sparse: SparseSpec,
        backend: str = "auto",
        method: str = "gather",
        *,
        shadow_m: float = 0.0,
        rule: str | None = None,
        threshold: float = 0.1,
        carve_views: int = 2,
        max_bytes: int | None = None,
        evict: str | None = None,
        initial_blocks: int = 64,
    ) -> None:
        if not isinstance(spec, SonarSpec):
            raise TypeError(f"Expected a gpumap.SonarSpec for 'spec', but got {type(spec).__name__}")
        if not isinstance(sparse, SparseSpec):
            raise TypeError(f"Expected a gpumap.SparseSpec for 'sparse', but got {type(sparse).__name__}")
        if method != "gather":
            raise ValueError(
                f"Expected method='gather' (the sparse map has no template method), but got {method!r}"
            )
        if backend != "auto" and backend not in BACKENDS:
            raise ValueError(f"Expected backend to be 'auto' or one of {BACKENDS}, but got {backend!r}")
        rule = "visible" if rule is None else rule
        if rule not in RULES:
            raise ValueError(f"Expected rule to be one of {RULES} (or None), but got {rule!r}")
        thr = check_finite_scalar(threshold, "threshold")
        if not 0.0 < thr <= 1.0:
            raise ValueError(f"Expected threshold in (0, 1], but got {thr}")
        shadow = check_finite_scalar(shadow_m, "shadow_m")
        if shadow < 0:
            raise ValueError(f"Expected shadow_m >= 0, but got {shadow}")
        if evict not in (None, "farthest"):
            raise ValueError(f"Expected evict to be None or 'farthest', but got {evict!r}")
        if max_bytes is not None and (
            isinstance(max_bytes, bool) or not isinstance(max_bytes, (int, np.integer)) or max_bytes <= 0
        ):
            raise ValueError(f"Expected max_bytes to be a positive integer or None, but got {max_bytes!r}")
        if (
            isinstance(initial_blocks, bool)
            or not isinstance(initial_blocks, (int, np.integer))
            or initial_blocks < 1
        ):
            raise ValueError(f"Expected initial_blocks to be a positive integer, but got {initial_blocks!r}")
        self.spec, self.sparse = spec, sparse
        self.method, self.rule, self.threshold, self.shadow_m = "gather", rule, thr, shadow
        self.carve_views = carve_views
        self.max_bytes = None if max_bytes is None else int(max_bytes)
        self.evict = evict
        self.n_integrated = 0
        B = sparse.block
        self.B, self.B3 = B, B**3
        self._visible = rule == "visible"
        self.bytes_per_voxel = 9 if self._visible else 4
        self._block_bytes = self.B3 * self.bytes_per_voxel + 1  # + the seen byte
        s = sparse.voxel_size_m
        self._origin = np.asarray(sparse.origin, np.float64)
        o = sparse.origin
        self._params = static_params(spec, GridSpec(o, tuple(x + B * s for x in o), s), shadow, rule, thr)
        self._rho0, self._near0 = float(self._params["rho"]), float(self._params["near"])
        self._fov_pts_S = spec.fov_corners_S()
        self._staging = np.empty(spec.image_shape, dtype=np.float32)
        self._lock = threading.RLock()
        # the coarse index: block (lo_b + (a, b, c)) -> slot, -1 none
        if sparse.bounds is not None:
            self._dims = np.asarray(sparse.shape, np.int64)
            nb = -(-self._dims // B)
            self._check_index_size(nb, "the bounds")
        else:
            self._dims = None
            nb = np.zeros(3, np.int64)
        self._lo_b = np.zeros(3, np.int64)
        self._index = np.full(tuple(int(x) for x in nb), -1, np.int32)
        cap = int(initial_blocks)
        if self.max_bytes is not None:
            cap = max(1, min(cap, (self.max_bytes - self._index.nbytes) // self._block_bytes))
        self._coords = np.zeros((cap, 3), np.int64)
        self._used = np.zeros(cap, bool)
        self._free = np.arange(cap - 1, -1, -1, dtype=np.int64)  # a stack: pop from the end
        self._backend = self._make_backend(backend, cap)
        self._backend.set_index(self._index.ravel())

    # ------------------------------------------------------------------ setup
    def _check_index_size(self, nb: np.ndarray, what: str) -> None:
        n = int(np.prod(nb))
        need = 4 * n
        if n > _MAX_INDEX_BLOCKS:
            raise MapMemoryError(
                f"Expected at most {_MAX_INDEX_BLOCKS} blocks in the coarse index, but {what} span "
                f"{tuple(int(x) for x in nb)} blocks of {self.B}^3 voxels"
            )
        if self.max_bytes is not None and need + self._block_bytes > self.max_bytes:
            raise MapMemoryError(
                f"Expected the coarse index of {what} to fit under max_bytes={self.max_bytes}, but it "
                f"needs {need} bytes ({tuple(int(x) for x in nb)} blocks) plus at least one block of "
                f"{self._block_bytes}"
            )
        from gpumap.mapper import _free_memory_bytes

        free = _free_memory_bytes("numpy")
        if free is not None and 2 * need > free:
            raise MapMemoryError(
                f"Expected a coarse index that fits in memory, but {what} need {need / 2**30:.2f} GiB "
                f"(twice that while growing) and {free / 2**30:.2f} GiB are free"
            )

    def _make_backend(self, backend: str, cap: int) -> _Backend:
        names = AUTO_ORDER if backend == "auto" else (backend,)
        errors = []
        for name in names:
            try:
                return _make_backend(name, self.spec, self._visible, self.B, cap)
            except BackendUnavailableError as e:
                if backend != "auto":
                    raise
                errors.append(f"{name}: {e}")
        raise BackendUnavailableError("No backend could run: " + "; ".join(errors))

    @property
    def backend(self) -> str:
        """The backend in use, as ``gpumap info`` names it: ``"warp-cuda"``, ``"warp-cpu"``,
        ``"opencl-gpu"``, ``"opencl-cpu"`` or ``"numpy"`` (``"auto"`` and ``"opencl"`` resolve to one)."""
        return self._backend.name

    @property
    def device(self) -> str:
        return self._backend.device

    @property
    def carve_views(self) -> int:
        """Visible rule: clear dark views that carve a voxel once seen bright (see MinMaxMapper)."""
        return self._carve_views

    @carve_views.setter
    def carve_views(self, n: int) -> None:
        self._carve_views = check_carve_views(n)

    # ------------------------------------------------------------------ integrate
    def integrate(
        self,
        image: np.ndarray,
        T_W_S: np.ndarray,
        pose_cov: np.ndarray | None = None,
        pose_sigmas: float = 2.0,
    ) -> None:
        """Fuse one ping (see :meth:`gpumap.MinMaxMapper.integrate`). New blocks are allocated
        where the ping can observe a voxel. Raises ``ValueError``/``TypeError`` on bad input and
        :class:`MapMemoryError` when the blocks would pass ``max_bytes`` (``evict=None``) or
        the device's memory, in every case before the map changes."""
        from gpumap.mapper import MinMaxMapper

        T = check_pose(T_W_S, "T_W_S")
        with self._lock:
            img = MinMaxMapper._check_image(self, image)
            self._integrate_many([img], [T], [self._pad_of(pose_cov, pose_sigmas)])

    def integrate_batch(
        self,
        images: np.ndarray,
        T_W_S: np.ndarray,
        pose_cov: np.ndarray | None = None,
        pose_sigmas: float = 2.0,
    ) -> None:
        """Fuse B pings: the map of B calls of :meth:`integrate`, bit for bit (see
        :meth:`gpumap.MinMaxMapper.integrate_batch` for the arguments), with the host's block
        test vectorised over the batch and the new blocks of all B pings allocated at once.
        Every ping's image, pose and covariance is checked, and every block allocated, before
        any ping is applied: on bad input (``ValueError``/``TypeError`` naming the ping) or a
        :class:`MapMemoryError` the map is unchanged."""
        from gpumap.mapper import MinMaxMapper

        if not isinstance(images, np.ndarray) or images.ndim != 3:
            raise ValueError(f"Expected images of shape (B, n_bins, n_beams), but got {np.shape(images)}")
        Ts = np.asarray(T_W_S)
        if Ts.shape != (images.shape[0], 4, 4):
            raise ValueError(f"Expected T_W_S of shape ({images.shape[0]}, 4, 4), but got {Ts.shape}")
        covs = [None] * len(Ts)
        if pose_cov is not None:
            C = np.asarray(pose_cov)
            covs = [C] * len(Ts) if C.shape == (6, 6) else list(C)
            if len(covs) != len(Ts):
                raise ValueError(f"Expected pose_cov of shape (6, 6) or ({len(Ts)}, 6, 6), but got {C.shape}")
        with self._lock:
            poses, pads = [], []
            for k in range(len(Ts)):
                try:
                    poses.append(check_pose(Ts[k], "T_W_S"))
                    MinMaxMapper._check_image(self, images[k])
                    pads.append(self._pad_of(covs[k], pose_sigmas))
                except (ValueError, TypeError) as e:
                    raise type(e)(f"ping {k} of the batch: {e}") from e
            self._integrate_many(images, poses, pads, recheck=True)

    def _pad_of(self, pose_cov, pose_sigmas: float) -> float:
        from gpumap.mapper import _check_pose_cov

        if pose_cov is None:
            return 0.0
        C = _check_pose_cov(pose_cov)
        k = check_finite_scalar(pose_sigmas, "pose_sigmas")
        if k < 0:
            raise ValueError(f"Expected pose_sigmas >= 0, but got {k}")
        return pose_pad_m(C, self.spec.range_max_m, k)

    def _integrate_many(self, imgs, Ts: list, pads: list, recheck: bool = False) -> None:
        """Allocate the blocks of every ping, then apply them in order (checked input)."""
        from gpumap.mapper import MinMaxMapper

        ps, ncols = [], []
        for T, pad in zip(Ts, pads, strict=True):
            p = self._params.copy()
            if pad:
                set_footprint_pad(p, self._rho0, self._near0, pad)
            ncols.append(self._fill_ping(p, T))  # raises on a pose too far out, before any change
            ps.append(p)
        live = [k for k in range(len(ps)) if ncols[k]]
        if live:
            lo = np.array([ps[k]["box_lo"] for k in live], np.int64)
            hi = lo + np.array([ps[k]["box_n"] for k in live], np.int64) - 1
            if self._dims is None:  # the kernel reads the index over the whole box
                self._ensure_index(lo.min(axis=0) // self.B, hi.max(axis=0) // self.B)
            Tl = np.stack([Ts[k] for k in live])
            # the block test runs on the union box of a group of pings: small groups keep far-apart
            # pings from making it walk empty columns
            g = _CANDIDATE_GROUP
            lins = [
                self._candidate_lins(lo[i : i + g], hi[i : i + g], Tl[i : i + g])
                for i in range(0, len(live), g)
            ]
            self._allocate(np.concatenate(lins), Tl[-1, :3, 3])
        ilo = self._lo_b * self.B
        nbk = np.asarray(self._index.shape)
        for k, p in enumerate(ps):
            if ncols[k]:
                img = MinMaxMapper._check_image(self, imgs[k]) if recheck else imgs[k]
                self._backend.integrate(p, img, ncols[k], ilo, nbk)
            self.n_integrated += 1

    def _fill_ping(self, p: np.ndarray, T: np.ndarray) -> int:
        """Pose fields and the voxel box of one ping (as :func:`gpumap.geometry.ping_params`,
        unclipped for an unbounded map); returns the box's (i, j) column count."""
        R, t = T[:3, :3], T[:3, 3]
        Rt = R.T
        p["R"] = R.ravel()
        p["t"] = t
        p["A"] = Rt.ravel()
        p["b"] = -(Rt @ t)
        pts = self._fov_pts_S @ Rt
        s = self.sparse.voxel_size_m
        q0 = (pts.min(axis=0) + t - self._origin) / s
        q1 = (pts.max(axis=0) + t - self._origin) / s
        if max(np.abs(q0).max(), np.abs(q1).max()) > _MAX_VOXEL_INDEX - 2 * self.B:
            raise ValueError(
                f"Expected a sonar pose within {(_MAX_VOXEL_INDEX - 2 * self.B) * s:.4g} m of the map origin "
                f"{tuple(self._origin)} (voxel indices fit in int32), but T_W_S puts it at {t.tolist()}"
            )
        for ax in range(3):
            i0 = math.floor(q0[ax]) - 1
            i1 = math.floor(q1[ax]) + 1
            if self._dims is not None:
                dim = int(self._dims[ax])
                i0 = min(max(i0, 0), dim)
                i1 = min(max(i1, -1), dim - 1)
            p["box_lo"][ax] = i0
            p["box_n"][ax] = max(i1 - i0 + 1, 0)
        n = p["box_n"]
        return int(n[0]) * int(n[1]) if n[2] > 0 else 0

    def _candidate_lins(self, lo: np.ndarray, hi: np.ndarray, Ts: np.ndarray) -> np.ndarray:
        """Index entries (int64, into the flattened coarse index; repeats across pings) of the
        blocks that may hold a voxel centre one of the pings observes: per block column of a
        ping's voxel box (``lo``..``hi``, (P, 3) each), the z-range that its field of view's
        range sphere, azimuth half-planes, elevation slab and ``x > 0`` allow anywhere in the
        column (float64, padded against float32 rounding), as blocks. Vectorised over the P
        pings on the block columns of their union box. The index must cover every box."""
        B, s = self.B, self.sparse.voxel_size_m
        o = self._origin
        b0, b1 = lo // B, hi // B  # (P, 3)
        bx = np.arange(b0[:, 0].min(), b1[:, 0].max() + 1)
        by = np.arange(b0[:, 1].min(), b1[:, 1].max() + 1)
        cx = (o[0] + (bx + 0.5) * (B * s))[None, :, None]  # (1, nx, 1)
        cy = (o[1] + (by + 0.5) * (B * s))[None, None, :]  # (1, 1, ny)
        t = Ts[:, :3, 3]  # (P, 3)
        A = np.transpose(Ts[:, :3, :3], (0, 2, 1))  # rotation of T_S_W
        bb = -np.einsum("pij,pj->pi", A, t)
        rmax = self.spec.range_max_m
        pad = 1e-4 * (1.0 + rmax + np.abs(t).max(axis=1)) + 0.01 * s  # (P,)
        hd = B * s / math.sqrt(2.0) + pad  # the column's voxel centres lie within hd of (cx, cy)
        t3 = t[:, :, None, None]
        dmin = np.maximum(np.hypot(cx - t3[:, 0], cy - t3[:, 1]) - hd[:, None, None], 0.0)
        q = ((rmax + pad) ** 2)[:, None, None] - dmin * dmin
        ok = q > 0
        w = np.sqrt(np.maximum(q, 0.0))
        z0, z1 = t3[:, 2] - w, t3[:, 2] + w
        wd = self._params["wedge"].astype(np.float64)
        slab = float(self._params["slab"])
        # g . w + g0 >= 0 for some w in the column at height z: alpha(column) + beta z >= 0
        G = np.stack(
            [
                wd[0] * A[:, 0] + wd[1] * A[:, 1],
                wd[2] * A[:, 0] + wd[3] * A[:, 1],
                -A[:, 2],
                A[:, 2],
                A[:, 0],
            ],
            axis=1,
        )  # (P, 5, 3)
        g0 = np.stack(
            [
                wd[0] * bb[:, 0] + wd[1] * bb[:, 1],
                wd[2] * bb[:, 0] + wd[3] * bb[:, 1],
                slab - bb[:, 2],
                slab + bb[:, 2],
                bb[:, 0],
            ],
            axis=1,
        )  # (P, 5)
        base = g0 + hd[:, None] * np.hypot(G[..., 0], G[..., 1]) + pad[:, None]
        alpha = (
            base[..., None, None] + G[..., 0, None, None] * cx[:, None] + G[..., 1, None, None] * cy[:, None]
        )
        beta = G[..., 2]  # (P, 5)
        up, down = beta > 1e-12, beta < -1e-12
        level = ~(up | down)
        zc = -alpha / np.where(level, 1.0, beta)[..., None, None]
        z0 = np.maximum(z0, np.where(up[..., None, None], zc, -np.inf).max(axis=1))
        z1 = np.minimum(z1, np.where(down[..., None, None], zc, np.inf).min(axis=1))
        if level.any():
            ok &= np.where(level[..., None, None], alpha >= 0, True).all(axis=1)
        # the ping's own box: columns outside it and voxels above or below it hold nothing
        ok &= ((bx[None, :] >= b0[:, 0, None]) & (bx[None, :] <= b1[:, 0, None]))[:, :, None]
        ok &= ((by[None, :] >= b0[:, 1, None]) & (by[None, :] <= b1[:, 1, None]))[:, None, :]
        k0 = np.maximum(np.floor((z0 - o[2]) / s - 0.5).astype(np.int64) - 1, lo[:, 2, None, None])
        k1 = np.minimum(np.ceil((z1 - o[2]) / s - 0.5).astype(np.int64) + 1, hi[:, 2, None, None])
        ok &= k0 <= k1
        bz0 = k0 // B
        n = np.where(ok, k1 // B - bz0 + 1, 0).ravel()
        nb = self._index.shape
        lb = self._lo_b
        col = (
            (((bx - lb[0])[:, None] * nb[1] + (by - lb[1])[None, :]) * nb[2])[None] + (bz0 - lb[2])
        ).ravel()
        return np.repeat(col - (np.cumsum(n) - n), n) + np.arange(int(n.sum()))

    def _unravel(self, lins: np.ndarray) -> np.ndarray:
        """(m,) index entries -> (m, 3) int64 block coordinates."""
        nb = self._index.shape
        return np.stack([lins // (nb[1] * nb[2]), (lins // nb[2]) % nb[1], lins % nb[2]], axis=1) + self._lo_b

    def _ensure_index(self, need_lo: np.ndarray, need_hi: np.ndarray) -> None:
        """Grow an unbounded map's coarse index to hold blocks need_lo..need_hi (inclusive)."""
        cur_lo = self._lo_b
        cur_hi = self._lo_b + np.asarray(self._index.shape) - 1
        if self._index.size and np.all(need_lo >= cur_lo) and np.all(need_hi <= cur_hi):
            return
        if self._index.size == 0:
            new_lo, new_hi = need_lo - 2, need_hi + 2
        else:
            ext = cur_hi - cur_lo + 1
            margin = np.maximum(4, ext // 2)
            new_lo = np.where(need_lo < cur_lo, np.minimum(need_lo, cur_lo - margin), cur_lo)
            new_hi = np.where(need_hi > cur_hi, np.maximum(need_hi, cur_hi + margin), cur_hi)
        nb = new_hi - new_lo + 1
        self._check_index_size(nb, "the pings so far")
        if self.max_bytes is not None:
            used = self._backend.cap * self._block_bytes + 4 * int(np.prod(nb))
            if used > self.max_bytes:
                raise MapMemoryError(
                    f"Expected the map to stay under max_bytes={self.max_bytes}, but its coarse index must "
                    f"grow to {tuple(int(x) for x in nb)} blocks ({4 * int(np.prod(nb))} bytes) beside a "
                    f"pool of {self._backend.cap * self._block_bytes} bytes"
                )
        new = np.full(tuple(int(x) for x in nb), -1, np.int32)
        if self._index.size:
            a = cur_lo - new_lo
            e = a + np.asarray(self._index.shape)
            new[a[0] : e[0], a[1] : e[1], a[2] : e[2]] = self._index
        self._index, self._lo_b = new, new_lo
        self._backend.set_index(new.ravel())

    def _lins(self, coords: np.ndarray) -> np.ndarray:
        r = coords - self._lo_b
        nb = self._index.shape
        return (r[:, 0] * nb[1] + r[:, 1]) * nb[2] + r[:, 2]

    def _allocate(self, lins: np.ndarray, sonar_t: np.ndarray) -> None:
        """Give every candidate block (index entries ``lins``, repeats allowed) without one a
        slot (growing, reclaiming or evicting)."""
        if len(lins) == 0:
            return
        flat = self._index.reshape(-1)
        new_lins = np.unique(lins[flat[lins] < 0])
        if len(new_lins) > len(self._free):
            self._reclaim()
            new_lins = np.unique(lins[flat[lins] < 0])
            if len(new_lins) > len(self._free):
                self._grow(len(new_lins) - len(self._free), lins, sonar_t)
        n_new = len(new_lins)
        if n_new == 0:
            return
        k = len(self._free) - n_new
        slots = self._free[k:][::-1]
        self._free = self._free[:k]
        flat[new_lins] = slots
        self._coords[slots] = self._unravel(new_lins)
        self._used[slots] = True
        self._backend.set_blocks(slots, new_lins)

    def _grow(self, more: int, keep_lins: np.ndarray, sonar_t: np.ndarray) -> None:
        cap = self._backend.cap
        want = max(cap + more, int(math.ceil(cap * GROWTH)))
        if self.max_bytes is not None:
            limit = (self.max_bytes - self._index.nbytes) // self._block_bytes
            if want > limit:
                want = max(cap + more, limit)
            if want > limit:
                if self.evict == "farthest":
                    self._evict(more - (limit - cap), keep_lins, sonar_t)
                    if limit > cap:
                        self._grow_to(limit)
                    return
                raise MapMemoryError(
                    f"Expected the map to stay under max_bytes={self.max_bytes}, but this ping needs "
                    f"{cap + more} blocks of {self._block_bytes} bytes ({(cap + more) * self._block_bytes} "
                    f"bytes) plus a {self._index.nbytes}-byte index; the map is unchanged "
                    f"(raise max_bytes or pass evict='farthest')"
                )
        self._grow_to(want)

    def _grow_to(self, cap: int) -> None:
        old = self._backend.cap
        if cap <= old:
            return
        try:
            self._backend.grow(cap)
        except MapMemoryError:
            raise
        except Exception as e:  # the device's allocation failed: the old pool is still in place
            raise MapMemoryError(
                f"Expected the device to hold {cap} blocks ({cap * self._block_bytes / 2**30:.2f} GiB), "
                f"but growing the pool failed: {e}"
            ) from e
        self._coords = np.concatenate([self._coords, np.zeros((cap - old, 3), np.int64)])
        self._used = np.concatenate([self._used, np.zeros(cap - old, bool)])
        self._free = np.concatenate([np.arange(cap - 1, old - 1, -1, dtype=np.int64), self._free])

    def _free_slots(self, slots: np.ndarray) -> None:
        if len(slots) == 0:
            return
        lins = self._lins(self._coords[slots])
        self._index.reshape(-1)[lins] = -1
        self._used[slots] = False
        self._free = np.concatenate([self._free, slots[::-1]])
        self._backend.set_blocks(np.full(len(slots), -1, np.int32), lins.astype(np.int32))

    def _reclaim(self) -> None:
        """Free blocks that no ping has observed a voxel of (allocated by the conservative test)."""
        seen = self._backend.read_seen()
        dead = np.flatnonzero(self._used & (seen[: len(self._used)] == 0))
        self._free_slots(dead)

    def _evict(self, n: int, keep_lins: np.ndarray, sonar_t: np.ndarray) -> None:
        used = np.flatnonzero(self._used)
        keep = np.isin(self._lins(self._coords[used]), keep_lins)
        cand = used[~keep]
        if len(cand) < n:
            raise MapMemoryError(
                f"Expected max_bytes={self.max_bytes} to hold at least one ping's blocks, but this ping "
                f"alone needs {int(keep.sum()) + n} blocks and {len(cand)} others can be evicted"
            )
        c = self._origin + (self._coords[cand] + 0.5) * self.B * self.sparse.voxel_size_m
        d = np.linalg.norm(c - sonar_t, axis=1)
        self._free_slots(cand[np.argsort(-d, kind="stable")[:n]])

    def synchronize(self) -> None:
        """Wait until every ping handed to :meth:`integrate` is in the map."""
        with self._lock:
            self._backend.synchronize()

    def check(self) -> None:
        """Raise ``RuntimeError`` if a kernel found an observed voxel without a block (a bug:
        the host's block test must be conservative)."""
        with self._lock:
            if self._backend.read_err():
                raise RuntimeError(
                    "gpumap.sparse: an observed voxel had no block (non-conservative block test)"
                )

    # ------------------------------------------------------------------ reading
    def _settle(self) -> None:
        """Before a read: raise on a kernel error, free blocks no ping has observed."""
        self.check()
        self._reclaim()

    def _blocks(self) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """Used blocks' coords (n, 3) int64 (lexicographic order) and their (n, B^3) arrays."""
        self.check()
        g, b, c = self._backend.read()
        used = np.flatnonzero(self._used)
        coords = self._coords[used]
        order = np.lexsort((coords[:, 2], coords[:, 1], coords[:, 0]))
        used, coords = used[order], coords[order]
        B3 = self.B3
        take = (used[:, None] * B3 + np.arange(B3)).reshape(-1)
        out = {"min_all": g[take].reshape(-1, B3)}
        if self._visible:
            from gpumap.reference import visible_values

            out["bright"] = b[take].reshape(-1, B3)
            out["count"] = c[take].reshape(-1, B3)
            out["values"] = visible_values(out["min_all"], out["bright"], out["count"], self.carve_views)
        else:
            out["values"] = out["min_all"]
        return coords, out

    @property
    def grid(self) -> GridSpec:
        """The dense :class:`GridSpec` that :meth:`values` covers: the bounds, or for an
        unbounded map the box of its blocks (one voxel at the origin while empty)."""
        if self.sparse.bounds is not None:
            return self.sparse.grid
        with self._lock:
            self._settle()
            i0, i1 = self._whole_box()
        return self._box_grid(i0, i1)

    def _whole_box(self) -> tuple[np.ndarray, np.ndarray]:
        if self._dims is not None:
            return np.zeros(3, np.int64), self._dims - 1
        used = np.flatnonzero(self._used)
        if len(used) == 0:
            return np.zeros(3, np.int64), np.zeros(3, np.int64)
        c = self._coords[used]
        return c.min(axis=0) * self.B, (c.max(axis=0) + 1) * self.B - 1

    def _box_grid(self, i0: np.ndarray, i1: np.ndarray) -> GridSpec:
        s = self.sparse.voxel_size_m
        return GridSpec(tuple(self._origin + i0 * s), tuple(self._origin + (i1 + 1) * s), s)

    def _dense(self, i0: np.ndarray, i1: np.ndarray, names: tuple[str, ...]) -> dict[str, np.ndarray]:
        """Arrays over voxel indices i0..i1 (inclusive): +inf / 0 where no block."""
        shape = tuple(int(x) for x in i1 - i0 + 1)
        if min(shape) <= 0:
            return {n: np.zeros((0, 0, 0), np.uint8 if n == "count" else np.float32) for n in names}
        if int(np.prod(shape)) > _MAX_BOX_VOXELS:
            raise ValueError(f"Expected a box of at most {_MAX_BOX_VOXELS} voxels, but got {shape}")
        coords, data = self._blocks()
        B = self.B
        b0, b1 = i0 // B, i1 // B
        nb = b1 - b0 + 1
        sel = np.all((coords >= b0) & (coords <= b1), axis=1)
        r = coords[sel] - b0
        out = {}
        for n in names:
            dt, fill = (np.uint8, 0) if n == "count" else (np.float32, np.inf)
            V = np.full((*(int(x) for x in nb), B, B, B), fill, dt)
            V[r[:, 0], r[:, 1], r[:, 2]] = data[n][sel].reshape(-1, B, B, B)
            V = V.transpose(0, 3, 1, 4, 2, 5).reshape(*(int(x) * B for x in nb))
            a = i0 - b0 * B
            out[n] = np.ascontiguousarray(
                V[a[0] : a[0] + shape[0], a[1] : a[1] + shape[1], a[2] : a[2] + shape[2]]
            )
        return out

    def raw_values(self) -> np.ndarray:
        """Map values over :attr:`grid`, float32 with ``+inf`` for never observed."""
        with self._lock:
            self._settle()
            return self._dense(*self._whole_box(), ("values",))["values"]

    def values(self) -> np.ndarray:
        """(nx, ny, nz) float32 over :attr:`grid`: ``NaN`` = never observed, else in [0, 1]."""
        v = self.raw_values()
        v[np.isinf(v)] = np.nan
        return v

    def confidence(self) -> np.ndarray:
        """Not yet on sparse maps: the confidence layer lives on :class:`gpumap.MinMaxMapper`."""
        raise NotImplementedError(
            "Expected a dense gpumap.MinMaxMapper(confidence=True) for confidence(); the sparse mapper "
            "has no confidence layer yet"
        )

    def view_gain(self, T_W_S_candidates: np.ndarray, unknown_weight: float = 1.0) -> np.ndarray:
        """Not yet on sparse maps: see :meth:`gpumap.MinMaxMapper.view_gain`."""
        raise NotImplementedError(
            "Expected a dense gpumap.MinMaxMapper(confidence=True) for view_gain(); the sparse mapper "
            "has no confidence layer yet"
        )

    def observed(self) -> np.ndarray:
        """(nx, ny, nz) bool over :attr:`grid`: voxels seen by at least one ping."""
        return np.isfinite(self.raw_values())

    def evidence(self) -> dict[str, np.ndarray]:
        """The visible rule's state over :attr:`grid` (see :meth:`gpumap.MinMaxMapper.evidence`)."""
        if not self._visible:
            raise ValueError(
                f"Expected a mapper with rule='visible' for evidence(), but its rule is {self.rule!r}"
            )
        with self._lock:
            self._settle()
            return self._dense(*self._whole_box(), ("min_all", "bright", "count"))

    def values_in_box(self, lo_m, hi_m) -> tuple[GridSpec, np.ndarray]:
        """Values of the voxels whose centres lie in the world box ``[lo_m, hi_m]`` (metres).

        Returns the box's :class:`GridSpec` (its voxels are the map's) and its (nx, ny, nz)
        float32 values, ``NaN`` = never observed."""
        lo, hi = np.asarray(_vec3(lo_m, "lo_m")), np.asarray(_vec3(hi_m, "hi_m"))
        if np.any(hi < lo):
            raise ValueError(f"Expected hi_m >= lo_m on every axis, but got {lo.tolist()} and {hi.tolist()}")
        s = self.sparse.voxel_size_m
        i0 = np.ceil((lo - self._origin) / s - 0.5).astype(np.int64)
        i1 = np.floor((hi - self._origin) / s - 0.5).astype(np.int64)
        if self._dims is not None:
            i0, i1 = np.maximum(i0, 0), np.minimum(i1, self._dims - 1)
        if np.any(i1 < i0):
            raise ValueError(
                f"Expected a box holding at least one voxel centre, but {lo.tolist()}-{hi.tolist()} "
                "holds none (inside the bounds)"
            )
        with self._lock:
            self._settle()
            v = self._dense(i0, i1, ("values",))["values"]
        v[np.isinf(v)] = np.nan
        return self._box_grid(i0, i1), v

    def occupied_points(self, threshold: float, center_m=None, radius_m: float | None = None) -> np.ndarray:
        """(N, 3) float64 world centres (metres) of observed voxels with value >= ``threshold``,
        in the dense grid's order (x index, then y, then z); with ``center_m`` ((3,) point, or a
        (4, 4) pose whose position is taken) and ``radius_m``, only those within that distance."""
        thr = np.float32(check_finite_scalar(threshold, "threshold"))
        with self._lock:
            self._settle()
            coords, data = self._blocks()
        B, s = self.B, self.sparse.voxel_size_m
        c = None
        if center_m is not None or radius_m is not None:
            if center_m is None or radius_m is None:
                raise ValueError("Expected center_m and radius_m together, or neither")
            a = np.asarray(center_m, np.float64)
            c = np.asarray(check_pose(a, "center_m")[:3, 3] if a.shape == (4, 4) else _vec3(a, "center_m"))
            r = check_finite_scalar(radius_m, "radius_m")
            if r < 0:
                raise ValueError(f"Expected radius_m >= 0, but got {r}")
            mid = self._origin + (coords + 0.5) * B * s
            near = np.linalg.norm(mid - c, axis=1) <= r + math.sqrt(3) / 2 * B * s
            coords, vals = coords[near], data["values"][near]
        else:
            vals = data["values"]
        blk, loc = np.nonzero(np.isfinite(vals) & (vals >= thr))
        w = np.stack([loc // (B * B), (loc // B) % B, loc % B], axis=1)
        idx = coords[blk] * B + w
        idx = idx[np.lexsort((idx[:, 2], idx[:, 1], idx[:, 0]))]
        pts = self._origin + (idx + 0.5) * s
        if c is not None:
            pts = pts[np.linalg.norm(pts - c, axis=1) <= r]
        return pts

    def memory_stats(self) -> dict:
        """Blocks and bytes (never-observed blocks are freed first).

        ``blocks``; ``observed_voxels``; ``bytes_per_voxel`` (9 visible rule, 4 plain);
        ``block_bytes`` (blocks x voxels per block x bytes per voxel); ``observed_bytes``
        (observed voxels x bytes per voxel) and their ratio ``block_over_observed``;
        ``pool_bytes`` (the allocated pool, spare slots included, +1 byte per slot);
        ``index_bytes``; ``total_bytes`` (pool + index); ``dense_bytes``: a dense grid over the
        same box (the bounds, or the box of the blocks) at the same bytes per voxel."""
        with self._lock:
            self.synchronize()
            self._reclaim()
            coords, data = self._blocks()
            n_obs = int(np.isfinite(data["min_all"]).sum())
            i0, i1 = self._whole_box()
            n = len(coords)
            bpv = self.bytes_per_voxel
            cap = self._backend.cap
            dense = int(np.prod(i1 - i0 + 1)) * bpv if n or self._dims is not None else 0
            return {
                "blocks": n,
                "block_size": self.B,
                "observed_voxels": n_obs,
                "bytes_per_voxel": bpv,
                "block_bytes": n * self.B3 * bpv,
                "observed_bytes": n_obs * bpv,
                "block_over_observed": (n * self.B3 / n_obs) if n_obs else None,
                "pool_blocks": cap,
                "pool_bytes": cap * self._block_bytes,
                "index_bytes": int(self._index.nbytes),
                "total_bytes": cap * self._block_bytes + int(self._index.nbytes),
                "dense_bytes": dense,
            }

    def reset(self) -> None:
        """Forget every ping: no blocks (the pool keeps its size)."""
        with self._lock:
            self._free_slots(np.flatnonzero(self._used))
            self.n_integrated = 0

    def merge(self, other) -> None:
        """Add the pings of ``other`` (a sparse map of the same spec and options) to this map, in
        place, bit for bit as one mapper of all the pings; never evicts (:mod:`gpumap.merge`)."""
        from gpumap.merge import merge_into

        merge_into(self, other)

    # ------------------------------------------------------------------ persistence
    def save(self, path: str | os.PathLike) -> Path:
        """Write the map to ``path`` (.npz) atomically; lossless.

        Members: ``blocks`` (n, 3) int32 block coordinates (lexicographic), ``values`` (n, B,
        B, B) float32 (+inf never observed) and for the visible rule ``min_all``, ``bright``
        (float32) and ``count`` (uint8) of the same shape; ``meta`` (JSON: format, version,
        both specs, rule, threshold, carve_views, shadow_m, ping count). Only blocks with an
        observed voxel are written.
        """
        path = Path(path)
        if path.suffix != ".npz":
            path = path.with_suffix(path.suffix + ".npz") if path.suffix else path.with_suffix(".npz")
        B = self.B
        with self._lock:
            self.synchronize()
            self._reclaim()
            coords, data = self._blocks()
            n_integrated = self.n_integrated
        arrays = {"blocks": coords.astype(np.int32), "values": data["values"].reshape(-1, B, B, B)}
        if self._visible:
            for k in ("min_all", "bright", "count"):
                arrays[k] = data[k].reshape(-1, B, B, B)
        meta = {
            "format": FILE_FORMAT,
            "version": FILE_VERSION,
            "spec": self.spec.to_dict(),
            "sparse": self.sparse.to_dict(),
            "method": "gather",
            "shadow_m": self.shadow_m,
            "rule": self.rule,
            "threshold": self.threshold,
            "carve_views": self.carve_views,
            "n_integrated": n_integrated,
            "backend": self.backend,
        }
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_write(path) as f:
            np.savez_compressed(f, **arrays, meta=np.array(json.dumps(meta)))
        return path

    @classmethod
    def load(cls, path: str | os.PathLike, backend: str = "auto", **kw) -> SparseMinMaxMapper:
        """Read a map written by :meth:`save` onto ``backend`` (``kw``: ``max_bytes``, ``evict``).

        Checked before anything large is read: the metadata (format, version, specs, options),
        each member's declared shape and dtype and its inflation ratio (as
        :meth:`gpumap.MinMaxMapper.load`); then the blocks (unique, inside the bounds, each
        with an observed voxel, voxels outside the bounds never observed) and the values
        (finite in [0, 1] or +inf, the visible state consistent). Raises ``ValueError``.
        """
        from gpumap.mapper import _META_MAX_BYTES, _check_map_values, _free_memory_bytes, _npy_header

        path = Path(path)
        try:
            with zipfile.ZipFile(path) as zf:
                members = {i.filename: i for i in zf.infolist()}
                if "meta.npy" not in members or "blocks.npy" not in members:
                    raise ValueError(
                        f"Expected a gpumap sparse map file with 'meta' and 'blocks', but {path} has "
                        f"{sorted(n.removesuffix('.npy') for n in members)}"
                    )
                headers = {n: _npy_header(zf, i, path) for n, i in members.items() if n.endswith(".npy")}
                if members["meta.npy"].file_size > _META_MAX_BYTES:
                    raise ValueError(f"Expected map metadata under {_META_MAX_BYTES} bytes in {path}")
                with zf.open("meta.npy") as f:
                    meta = json.loads(str(np.lib.format.read_array(f, allow_pickle=False)))
                spec, sparse, opts, n_int = _check_sparse_meta(meta, path)
                B = sparse.block
                bshape, bdt = headers["blocks.npy"]
                if len(bshape) != 2 or bshape[1] != 3 or bdt != np.dtype(np.int32):
                    raise ValueError(
                        f"Expected 'blocks' of shape (n, 3) int32 in {path}, but got {bshape} {bdt}"
                    )
                n = bshape[0]
                names = ("values", "min_all", "bright", "count") if opts["rule"] == "visible" else ("values",)
                for name in names:
                    dt = np.dtype(np.uint8 if name == "count" else np.float32)
                    shape, dtype = headers.get(f"{name}.npy", (None, None))
                    if shape != (n, B, B, B) or dtype != dt:
                        raise ValueError(
                            f"Expected '{name}' of shape {(n, B, B, B)} {dt} in {path}, but got "
                            f"{'nothing' if shape is None else f'{shape} {dtype}'}"
                        )
                need = n * B**3 * (9 if opts["rule"] == "visible" else 4) + 4 * n * B**3
                free = _free_memory_bytes("numpy")
                if free is not None and 2 * need > free:
                    raise ValueError(
                        f"Expected a map that fits in memory, but {path} holds {need / 2**30:.2f} GiB "
                        f"and {free / 2**30:.2f} GiB are free"
                    )
                arrays = {}
                for name in ("blocks", *names):
                    with zf.open(f"{name}.npy") as f:
                        arrays[name] = np.lib.format.read_array(f, allow_pickle=False)
        except (OSError, EOFError, zipfile.BadZipFile, json.JSONDecodeError, UnicodeDecodeError) as e:
            raise ValueError(
                f"Expected a gpumap sparse map file (.npz) at {path}, but it cannot be read: {e}"
            ) from e
        coords = arrays["blocks"].astype(np.int64)
        if n and len(np.unique(coords, axis=0)) != n:
            raise ValueError(f"Expected each block once in {path}, but some repeat")
        if np.abs(coords).max(initial=0) * B > _MAX_VOXEL_INDEX - 2 * B:
            raise ValueError(f"Expected block coordinates within +-{_MAX_VOXEL_INDEX // B - 2} in {path}")
        flat = {k: v.reshape(n, -1) for k, v in arrays.items() if k != "blocks"}
        _check_map_values(flat, opts, path)
        obs = np.isfinite(flat["min_all" if opts["rule"] == "visible" else "values"])
        if not obs.any(axis=1).all():
            raise ValueError(f"Expected every block in {path} to hold an observed voxel, but some hold none")
        if sparse.bounds is not None and n:
            idx = (coords[:, None, :] * B + _local(B)[None]).reshape(n, -1, 3)
            outside = np.any((idx < 0) | (idx >= np.asarray(sparse.shape)), axis=2)
            if np.any(outside & obs):
                raise ValueError(
                    f"Expected observed voxels only inside the bounds in {path}, but some lie outside"
                )
        m = cls(spec, sparse, backend=backend, initial_blocks=max(1, n), **opts, **kw)
        with m._lock:
            if n:
                if sparse.bounds is None:
                    m._ensure_index(coords.min(axis=0), coords.max(axis=0))
                lins = m._lins(coords)
                if n > len(m._free):
                    m._grow_to(m._backend.cap + n - len(m._free))
                slots = m._free[len(m._free) - n :][::-1]
                m._free = m._free[: len(m._free) - n]
                m._index.reshape(-1)[lins] = slots
                m._coords[slots] = coords
                m._used[slots] = True
                m._backend.set_blocks(slots.astype(np.int32), lins.astype(np.int32))
                src = flat["min_all"] if opts["rule"] == "visible" else flat["values"]
                m._backend.write_blocks(slots, src, flat.get("bright"), flat.get("count"))
            m.n_integrated = n_int
        return m


@functools.cache
def _local(B: int) -> np.ndarray:
    """(B^3, 3) int64 local voxel offsets of a block, in storage order."""
    a = np.arange(B**3)
    return np.stack([a // (B * B), (a // B) % B, a % B], axis=1)


def _check_sparse_meta(meta: object, path: Path) -> tuple[SonarSpec, SparseSpec, dict, int]:
    if not isinstance(meta, dict):
        raise ValueError(f"Expected a JSON object as map metadata in {path}, but got {type(meta).__name__}")
    if meta.get("format") != FILE_FORMAT:
        raise ValueError(f"Expected format {FILE_FORMAT!r} in {path}, but got {meta.get('format')!r}")
    if meta.get("version") != FILE_VERSION:
        raise ValueError(f"Expected file version {FILE_VERSION} in {path}, but got {meta.get('version')!r}")
    try:
        spec = SonarSpec.from_dict(meta["spec"])
        sparse = SparseSpec.from_dict(meta["sparse"])
    except (KeyError, TypeError, ValueError, OverflowError, IndexError) as e:
        raise ValueError(
            f"Expected a sonar spec and a sparse spec in the metadata of {path}, but: {e!r}"
        ) from e
    n = meta.get("n_integrated")
    if isinstance(n, bool) or not isinstance(n, int) or n < 0:
        raise ValueError(f"Expected a non-negative integer n_integrated in {path}, but got {n!r}")
    opts = {k: meta.get(k) for k in ("shadow_m", "rule", "threshold", "carve_views")}
    if opts["rule"] not in RULES or meta.get("method") != "gather":
        raise ValueError(
            f"Expected rule in {RULES} and method 'gather' in {path}, but got {opts['rule']!r}, "
            f"{meta.get('method')!r}"
        )
    for key in ("shadow_m", "threshold"):
        if isinstance(opts[key], bool) or not isinstance(opts[key], (int, float)):
            raise ValueError(f"Expected a number for {key} in {path}, but got {opts[key]!r}")
    cv = opts["carve_views"]
    if isinstance(cv, bool) or not isinstance(cv, int) or not 1 <= cv <= 255:
        raise ValueError(f"Expected carve_views in 1..255 in {path}, but got {cv!r}")
    return spec, sparse, opts, n
