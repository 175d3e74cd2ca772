"""Block storage: a map's voxels in blocks on a backend, found through a dense coarse index.

A map lives in *blocks* of ``B x B x Bz`` voxels on the backend's device: a *pool* of slots (per
voxel float32 ``min_all``, and for the evidence and visible rules float32 ``bright`` and uint64
``count`` (two packed view counts): 16 bytes; 4 for the plain rule) and a dense coarse *index*
of int32 slots, one per block of a box (``-1`` = no block; 4 bytes per 512 voxels). Every kernel
addresses a voxel through the index: its block's slot times its size plus its place in the
block (an O(1) read: no hash, no probing, nothing OpenCL 1.2 lacks), in one kernel family for
every storage (``gpumap.kernels.minmax``).

- **A bounded box** (a :class:`~gpumap.GridSpec`): every block of the box is allocated up front
  and the index is the identity, so a ping costs no block search (the dense grid's speed).
- **On demand** (a :class:`~gpumap.SparseSpec`): blocks get a slot when a ping may observe them
  (:meth:`BlockStorage.allocate`, given the candidates that :mod:`gpumap.core.integrator` finds), the
  pool grows by :data:`GROWTH` and an unbounded map's index grows when pings leave it. Each
  block carries a "seen" byte set by the kernels; before the pool grows, and before reads and
  saves, blocks no ping observed are freed (:meth:`~BlockStorage.reclaim`). ``max_bytes``
  bounds the pool plus the index: what needs more raises :class:`MapMemoryError` before it
  changes the map (``evict=None``), or with ``evict="farthest"`` frees the blocks farthest from
  the sonar that the ping does not touch.

Considered and not chosen: Warp's NanoVDB volumes (CUDA only, one value type per tree, a tree
walk per voxel), and an open-addressing hash on the device (would lift the coarse index's one
limit, that it spans the box of everything mapped: a 10 km transit at 5 cm needs a 2 GB index;
not needed for a survey area).

Reads and writes go through the public methods here (:meth:`~BlockStorage.blocks`,
:meth:`~BlockStorage.put_blocks`, :meth:`~BlockStorage.dense`, ...); every one that touches the
pool holds :attr:`BlockStorage.lock`, the map's one lock.
"""

from __future__ import annotations

import functools
import math
import threading

import numpy as np

import gpumap.memory as memory
from gpumap.backends import AUTO_ORDER, Backend, GridTooLargeError, make_backend
from gpumap.core.rules import ValueRule, combine_into
from gpumap.errors import BackendUnavailableError
from gpumap.spec import GridSpec, SonarSpec, SparseSpec

__all__ = ["BLOCK", "GROWTH", "BlockStorage", "MapMemoryError", "local_offsets"]

BLOCK = 8  # voxels per block edge of a bounded box (a SparseSpec says its own)
GROWTH = 1.5  # an on-demand pool grows by this factor (at least to what a ping needs)
_MAX_INDEX_BLOCKS = 2**31 - 1
_MAX_BOX_VOXELS = 2**31 - 1
_MAX_POOL_VOXELS = 2**31 - 1  # kernels address the pool with int32
_STATE = ("min_all", "bright", "count")  # a block's arrays, as the backends read and write them


class MapMemoryError(GridTooLargeError):
    """A ping (or a spec) needs more memory than the cap or the device allows; the map is unchanged."""


@functools.cache
def local_offsets(B: int, Bz: int) -> np.ndarray:
    """(B B Bz, 3) int64 local voxel offsets of a block, in storage order."""
    a = np.arange(B * B * Bz)
    return np.stack([a // (B * Bz), (a // Bz) % B, a % Bz], axis=1)


class BlockStorage:
    """The blocks of one map: which exist (the coarse index), where they live (a pool of slots on
    a backend) and what they hold.

    Parameters
    ----------
    spec : SonarSpec
        The sonar (the backend's per-ping buffers).
    box : GridSpec or SparseSpec
        A GridSpec: every block of the box, allocated up front, blocks ``BLOCK x BLOCK`` columns of
        the grid's height. A SparseSpec: blocks (cubes of its edge) allocated on demand.
    value_rule : ValueRule
        The rule whose state the blocks keep (``bright`` and ``count`` for all but ``"plain"``),
        and how the state reads as values.
    backend : str
        A backend name, or ``"auto"`` (the first of :data:`gpumap.backends.AUTO_ORDER` that runs
        and fits).
    template : (n, 3) float or None
        The template method's voxel template (handed to the backend).
    use_table : bool or None
        How the backend's kernels take a footprint's max (see :func:`gpumap.backends.make_backend`).
    max_bytes, evict, initial_blocks
        On demand: the cap on pool plus index, what passing it does, the slots made up front.
    device_index : int, optional
        The backend's device (:func:`gpumap.backends.make_backend`); None: its first.
    """

    def __init__(self, spec: SonarSpec, box: GridSpec | SparseSpec, value_rule: ValueRule,
                 backend: str = "auto", *, template: np.ndarray | None = None, use_table: bool | None = None,
                 max_bytes: int | None = None, evict: str | None = None, initial_blocks: int = 64,
                 device_index: int | None = None) -> None:
        space = box if isinstance(box, SparseSpec) else None
        self.device_index = device_index
        self.sparse = space
        self.value_rule = value_rule
        self.rule = value_rule.rule
        self.max_bytes = max_bytes
        self.evict = evict
        self.empty = True  # no ping, merge or load has gone into the map since it was made or cleared
        self.stateful = self.rule != "plain"  # the visible and evidence rules keep bright and count
        # a bounded box's blocks are BLOCK x BLOCK columns of the grid's height (one index read per
        # column in the kernels, which then walk contiguous voxels: the dense grid's speed); blocks
        # on demand are cubes of the SparseSpec's edge
        B = BLOCK if space is None else space.block
        Bz = int(box.shape[2]) if space is None else B
        self.B, self.Bz, self.BV = B, Bz, B * B * Bz
        self.bs = np.array([B, B, Bz], np.int64)
        self.bytes_per_voxel = memory.STATE_BYTES[self.rule]  # gpumap.memory's one table of the rules' state
        self.block_bytes = self.BV * self.bytes_per_voxel + 1  # + the seen byte
        if space is None:
            self._grid = box
            self.voxel, self.origin = box.voxel_size_m, np.asarray(box.min_corner_m, np.float64)
            self.dims = np.asarray(box.shape, np.int64)
        else:
            self._grid = None  # the bounds' grid, or the box of the blocks (see the property)
            self.voxel, self.origin = space.voxel_size_m, np.asarray(space.origin, np.float64)
            self.dims = None if space.bounds is None else np.asarray(space.shape, np.int64)
        # One ping at a time: integrate, reads and writes hold this lock, so threads sharing a
        # mapper serialize (and, every update being a min or a count, get the map one thread
        # would have made).
        self.lock = threading.RLock()
        # the coarse index: block (lo_b + (a, b, c)) -> slot, -1 none
        self.lo_b = np.zeros(3, np.int64)
        nb = np.zeros(3, np.int64) if self.dims is None else -(-self.dims // self.bs)
        if self.dims is not None:
            self._check_index_size(nb, "the bounds")
        n_blocks = int(np.prod(nb))
        if space is None:  # every block of the box, slot = index entry (the identity)
            if n_blocks * self.BV > _MAX_POOL_VOXELS:
                raise GridTooLargeError(
                    f"Expected at most {_MAX_POOL_VOXELS} voxels in the grid's blocks, but {box.shape} "
                    f"voxels take {n_blocks} blocks of {B} x {B} x {Bz}"
                )
            self.index = np.arange(n_blocks, dtype=np.int32).reshape(tuple(int(x) for x in nb))
            cap = n_blocks
            self.coords = self.unravel(np.arange(n_blocks))
            self.used = np.ones(cap, bool)
            self.free = np.zeros(0, np.int64)
        else:
            self.index = np.full(tuple(int(x) for x in nb), -1, np.int32)
            cap = int(initial_blocks)
            if self.max_bytes is not None:
                cap = max(1, min(cap, (self.max_bytes - self.index.nbytes) // self.block_bytes))
            self.coords = np.zeros((cap, 3), np.int64)
            self.used = np.zeros(cap, bool)
            self.free = np.arange(cap - 1, -1, -1, dtype=np.int64)  # a stack: pop from the end
        self.backend = self._make_backend(backend, cap, spec, template, use_table)
        self.backend.set_index(self.index, self.lo_b * self.bs)

    # ------------------------------------------------------------------ setup
    def _check_index_size(self, nb: np.ndarray, what: str) -> None:
        n = int(np.prod(nb))
        need = 4 * n
        if n > _MAX_INDEX_BLOCKS:
            raise MapMemoryError(
                f"Expected at most {_MAX_INDEX_BLOCKS} blocks in the coarse index, but {what} span "
                f"{tuple(int(x) for x in nb)} blocks of {self.BV} voxels"
            )
        if self.max_bytes is not None and need + self.block_bytes > self.max_bytes:
            raise MapMemoryError(
                f"Expected the coarse index of {what} to fit under max_bytes={self.max_bytes}, but it "
                f"needs {need} bytes ({tuple(int(x) for x in nb)} blocks) plus at least one block of "
                f"{self.block_bytes}"
            )
        free = memory.free_memory_bytes("numpy")
        if free is not None and 2 * need > free:
            raise MapMemoryError(
                f"Expected a coarse index that fits in memory, but {what} need {need / 2**30:.2f} GiB "
                f"(twice that while growing) and {free / 2**30:.2f} GiB are free"
            )

    def _make_backend(self, backend: str, cap: int, spec: SonarSpec, template: np.ndarray | None,
                      use_table: bool | None) -> Backend:
        names = AUTO_ORDER if backend == "auto" else (backend,)
        errors = []
        for name in names:
            need = cap * self.BV * self.bytes_per_voxel
            free = memory.free_memory_bytes(name, self.device_index)
            if self.sparse is None and free is not None and need > free:
                msg = (
                    f"Expected a grid that fits in memory, but {self._grid.shape} voxels at "
                    f"voxel_size_m={self._grid.voxel_size_m} need {need / 2**30:.2f} GiB and "
                    f"{name} has {free / 2**30:.2f} GiB free ({self.bytes_per_voxel} bytes a voxel, "
                    f"in blocks of {self.B} x {self.B} x {self.Bz})"
                )
                if backend != "auto":
                    raise ValueError(msg)
                errors.append(f"{name}: {msg}")
                continue
            try:
                return make_backend(name, spec, template, use_table, visible=self.stateful,
                                    B=self.B, Bz=self.Bz, cap=cap, device_index=self.device_index)
            except (BackendUnavailableError, GridTooLargeError) as e:
                if backend != "auto":
                    raise
                errors.append(f"{name}: {e}")
        raise BackendUnavailableError("No backend could run: " + "; ".join(errors))

    @property
    def grid(self) -> GridSpec:
        """The :class:`GridSpec` that dense reads cover: the box, or for an unbounded map the box
        of its blocks (one voxel at the origin while empty)."""
        if self._grid is not None:
            return self._grid
        if self.dims is not None:
            return self.sparse.grid
        with self.lock:
            self.settle()
            i0, i1 = self.whole_box()
        return self.box_grid(i0, i1)

    # ------------------------------------------------------------------ the index
    def unravel(self, lins: np.ndarray) -> np.ndarray:
        """(m,) index entries -> (m, 3) int64 block coordinates."""
        nb = self.index.shape
        return np.stack([lins // (nb[1] * nb[2]), (lins // nb[2]) % nb[1], lins % nb[2]], axis=1) + self.lo_b

    def lins(self, coords: np.ndarray) -> np.ndarray:
        """(m, 3) block coordinates (inside the index) -> (m,) entries of the flattened index."""
        r = coords - self.lo_b
        nb = self.index.shape
        return (r[:, 0] * nb[1] + r[:, 1]) * nb[2] + r[:, 2]

    def ensure_index(self, need_lo: np.ndarray, need_hi: np.ndarray) -> None:
        """Grow an unbounded map's coarse index to hold blocks need_lo..need_hi (inclusive)."""
        cur_lo = self.lo_b
        cur_hi = self.lo_b + np.asarray(self.index.shape) - 1
        if self.index.size and np.all(need_lo >= cur_lo) and np.all(need_hi <= cur_hi):
            return
        if self.index.size == 0:
            new_lo, new_hi = need_lo - 2, need_hi + 2
        else:
            ext = cur_hi - cur_lo + 1
            margin = np.maximum(4, ext // 2)
            new_lo = np.where(need_lo < cur_lo, np.minimum(need_lo, cur_lo - margin), cur_lo)
            new_hi = np.where(need_hi > cur_hi, np.maximum(need_hi, cur_hi + margin), cur_hi)
        nb = new_hi - new_lo + 1
        self._check_index_size(nb, "the pings so far")
        if self.max_bytes is not None:
            used = self.backend.cap * self.block_bytes + 4 * int(np.prod(nb))
            if used > self.max_bytes:
                raise MapMemoryError(
                    f"Expected the map to stay under max_bytes={self.max_bytes}, but its coarse index must "
                    f"grow to {tuple(int(x) for x in nb)} blocks ({4 * int(np.prod(nb))} bytes) beside a "
                    f"pool of {self.backend.cap * self.block_bytes} bytes"
                )
        new = np.full(tuple(int(x) for x in nb), -1, np.int32)
        if self.index.size:
            a = cur_lo - new_lo
            e = a + np.asarray(self.index.shape)
            new[a[0] : e[0], a[1] : e[1], a[2] : e[2]] = self.index
        self.index, self.lo_b = new, new_lo
        self.backend.set_index(new, new_lo * self.bs)

    # ------------------------------------------------------------------ the pool
    def allocate(self, lins: np.ndarray, sonar_t: np.ndarray) -> None:
        """Give every candidate block (index entries ``lins``, repeats allowed) without one a
        slot (growing, reclaiming or evicting; ``sonar_t`` (3,): where the sonar is, for
        ``evict="farthest"``)."""
        if len(lins) == 0:
            return
        flat = self.index.reshape(-1)
        new_lins = np.unique(lins[flat[lins] < 0])
        if len(new_lins) > len(self.free):
            self.reclaim()
            new_lins = np.unique(lins[flat[lins] < 0])
            if len(new_lins) > len(self.free):
                self._grow(len(new_lins) - len(self.free), lins, sonar_t)
        n_new = len(new_lins)
        if n_new == 0:
            return
        slots = self._take_slots(n_new)
        flat[new_lins] = slots
        self.coords[slots] = self.unravel(new_lins)
        self.used[slots] = True
        self.backend.set_blocks(slots, new_lins)

    def _take_slots(self, n: int) -> np.ndarray:
        """Pop ``n`` free slots (the stack's top, in order)."""
        k = len(self.free) - n
        slots = self.free[k:][::-1]
        self.free = self.free[:k]
        return slots

    def _grow(self, more: int, keep_lins: np.ndarray, sonar_t: np.ndarray) -> None:
        cap = self.backend.cap
        want = max(cap + more, int(math.ceil(cap * GROWTH)))
        if self.max_bytes is not None:
            limit = (self.max_bytes - self.index.nbytes) // self.block_bytes
            if want > limit:
                want = max(cap + more, limit)
            if want > limit:
                if self.evict == "farthest":
                    self._evict(more - (limit - cap), keep_lins, sonar_t)
                    if limit > cap:
                        self.grow_to(limit)
                    return
                raise MapMemoryError(
                    f"Expected the map to stay under max_bytes={self.max_bytes}, but this ping needs "
                    f"{cap + more} blocks of {self.block_bytes} bytes ({(cap + more) * self.block_bytes} "
                    f"bytes) plus a {self.index.nbytes}-byte index; the map is unchanged "
                    f"(raise max_bytes or pass evict='farthest')"
                )
        self.grow_to(want)

    def grow_to(self, cap: int) -> None:
        """Make the pool ``cap`` slots (new ones free); raises :class:`MapMemoryError`, the pool
        unchanged, when the device cannot."""
        old = self.backend.cap
        if cap <= old:
            return
        try:
            self.backend.grow(cap)
        except MapMemoryError:
            raise
        except Exception as e:  # the device's allocation failed: the old pool is still in place
            raise MapMemoryError(
                f"Expected the device to hold {cap} blocks ({cap * self.block_bytes / 2**30:.2f} GiB), "
                f"but growing the pool failed: {e}"
            ) from e
        self.coords = np.concatenate([self.coords, np.zeros((cap - old, 3), np.int64)])
        self.used = np.concatenate([self.used, np.zeros(cap - old, bool)])
        self.free = np.concatenate([np.arange(cap - 1, old - 1, -1, dtype=np.int64), self.free])

    def free_slots(self, slots: np.ndarray) -> None:
        """Free the blocks in ``slots``: their voxels become unknown, their slots reusable."""
        if len(slots) == 0:
            return
        lins = self.lins(self.coords[slots])
        self.index.reshape(-1)[lins] = -1
        self.used[slots] = False
        self.free = np.concatenate([self.free, slots[::-1]])
        self.backend.set_blocks(np.full(len(slots), -1, np.int32), lins.astype(np.int32))

    def reclaim(self) -> None:
        """Free blocks that no ping has observed a voxel of (allocated by the conservative test);
        a bounded box keeps all of its blocks."""
        if self.sparse is None:
            return
        seen = self.backend.read_seen()
        dead = np.flatnonzero(self.used & (seen[: len(self.used)] == 0))
        self.free_slots(dead)

    def _evict(self, n: int, keep_lins: np.ndarray, sonar_t: np.ndarray) -> None:
        used = np.flatnonzero(self.used)
        keep = np.isin(self.lins(self.coords[used]), keep_lins)
        cand = used[~keep]
        if len(cand) < n:
            raise MapMemoryError(
                f"Expected max_bytes={self.max_bytes} to hold at least one ping's blocks, but this ping "
                f"alone needs {int(keep.sum()) + n} blocks and {len(cand)} others can be evicted"
            )
        c = self.origin + (self.coords[cand] + 0.5) * self.bs * self.voxel
        d = np.linalg.norm(c - sonar_t, axis=1)
        self.free_slots(cand[np.argsort(-d, kind="stable")[:n]])

    def clear(self) -> None:
        """Every voxel unknown again (on demand: no blocks; the pool keeps its size)."""
        with self.lock:
            if self.sparse is None:  # every block back to never observed, the index unchanged
                slots = np.arange(self.backend.cap, dtype=np.int32)
                self.backend.set_blocks(slots, slots)
            else:
                self.free_slots(np.flatnonzero(self.used))
            self.empty = True

    # ------------------------------------------------------------------ the device
    def synchronize(self) -> None:
        """Wait until every ping handed to the backend is in the pool (GPU backends run async)."""
        with self.lock:
            self.backend.synchronize()

    def check(self) -> None:
        """Raise ``RuntimeError`` if a kernel found an observed voxel without a block (a bug:
        the host's block test must be conservative)."""
        with self.lock:
            if self.backend.read_err():
                raise RuntimeError(
                    "gpumap: an observed voxel had no block (non-conservative block test)"
                )

    def settle(self) -> None:
        """Before a read: raise on a kernel error, free blocks no ping has observed."""
        self.check()
        self.reclaim()

    # ------------------------------------------------------------------ reading and writing blocks
    def holding(self, slots: np.ndarray) -> np.ndarray:
        """(n,) bool: which of ``slots`` hold something (an observed, merged or loaded voxel: the
        seen flag, set by every kernel, merge and load)."""
        return self.backend.read_seen()[slots] != 0

    def blocks(self, values: bool = True, seen_only: bool = False
               ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """Used blocks' coords (n, 3) int64 (lexicographic order) and their (n, B B Bz) arrays:
        ``min_all``, ``values`` (unless ``values`` is False) and for the visible rule ``bright``
        and ``count``. ``seen_only``: only the blocks that hold something (observed, merged or
        loaded: the seen flag), read block by block."""
        self.check()
        keep = self.used & self.holding(np.arange(len(self.used))) if seen_only else self.used
        if self.sparse is None and keep.all():  # every block, slot = index entry: the pool as it is
            coords = self.coords
            arrays = [None if a is None else a.reshape(-1, self.BV) for a in self.backend.read()]
        else:
            slots = np.flatnonzero(keep)
            coords = self.coords[slots]
            if self.sparse is not None:  # slot order is coordinate order only for a bounded box
                order = np.lexsort((coords[:, 2], coords[:, 1], coords[:, 0]))
                slots, coords = slots[order], coords[order]
            arrays = self.backend.read_blocks(slots)
        out = dict(zip(_STATE, arrays, strict=True))
        if not self.stateful:
            del out["bright"], out["count"]
        if self.stateful and values:
            out["values"] = self.value_rule.values(out["min_all"], out["bright"], out["count"])
        elif values:
            out["values"] = out["min_all"]
        return coords, out

    def put_blocks(self, coords: np.ndarray, arrays: dict, combine: bool) -> None:
        """Blocks ``coords`` ((n, 3) int64, distinct, inside the bounds) take ``arrays``
        (``min_all`` and for the visible rule ``bright``, ``count``: (n, B B Bz) each), merged with
        what they hold when ``combine`` (:func:`gpumap.core.rules.combine_into`). Allocates missing
        blocks (never evicts); raises :class:`MapMemoryError` past ``max_bytes``, unchanged."""
        if not len(coords):
            return
        with self.lock:
            self.synchronize()
            self.settle()
            if self.dims is None:  # an unbounded map's index must span the blocks
                self.ensure_index(coords.min(axis=0), coords.max(axis=0))
            lins = self.lins(coords)
            flat = self.index.reshape(-1)
            new = flat[lins] < 0
            n_new = int(new.sum())
            short = n_new - len(self.free)
            if short > 0:
                cap = self.backend.cap + short
                if self.max_bytes is not None:
                    need = cap * self.block_bytes + self.index.nbytes
                    if need > self.max_bytes:
                        raise MapMemoryError(
                            f"Expected the map to stay under max_bytes={self.max_bytes}, but it needs {cap} "
                            f"blocks of {self.block_bytes} bytes plus a {self.index.nbytes}-byte index "
                            f"({need} bytes); the map is unchanged (merge never evicts)"
                        )
                self.grow_to(cap)
            if n_new:
                slots_new = self._take_slots(n_new)
                flat[lins[new]] = slots_new
                self.coords[slots_new] = coords[new]
                self.used[slots_new] = True
                self.backend.set_blocks(slots_new.astype(np.int32), lins[new].astype(np.int32))
            slots = flat[lins].astype(np.int64)
            names = _STATE if self.stateful else ("min_all",)
            mine = {k: arrays[k] for k in names}
            if combine and n_new < len(coords):
                # only blocks that already hold something are read and combined (a block never observed,
                # merged or loaded has seen 0); the others take the arrays as they are
                held = self.holding(slots)
                if held.any():
                    part = dict(zip(_STATE, self.backend.read_blocks(slots[held]), strict=True))
                    part = {k: part[k] for k in names}
                    combine_into(part, {k: v[held] for k, v in mine.items()}, self.rule)
                    self.backend.write_blocks(slots[held], part["min_all"], part.get("bright"),
                                              part.get("count"))
                    slots, mine = slots[~held], {k: v[~held] for k, v in mine.items()}
            self.backend.write_blocks(slots, mine["min_all"], mine.get("bright"), mine.get("count"))
            self.empty = False

    def write_box(self, min_all: np.ndarray, bright: np.ndarray | None = None,
                  count: np.ndarray | None = None) -> None:
        """A bounded box's whole state from (nx, ny, nz) arrays (``min_all``, and for the rules
        that keep them ``bright`` and ``count``), every block marked as holding something (merges
        combine with them)."""
        with self.lock:
            pool = [None if a is None else self.to_pool_order(a, 0 if a is count else np.inf).ravel()
                    for a in (min_all, bright, count)]
            self.backend.write(*pool)
            self.backend._write_seen(np.ones(self.backend.cap, np.uint8))
            self.empty = False

    # ------------------------------------------------------------------ boxes of voxels
    def whole_box(self) -> tuple[np.ndarray, np.ndarray]:
        """Voxel indices (first, last) of the bounds, or of the box of the blocks."""
        if self.dims is not None:
            return np.zeros(3, np.int64), self.dims - 1
        used = np.flatnonzero(self.used)
        if len(used) == 0:
            return np.zeros(3, np.int64), np.zeros(3, np.int64)
        c = self.coords[used]
        return c.min(axis=0) * self.bs, (c.max(axis=0) + 1) * self.bs - 1

    def box_grid(self, i0: np.ndarray, i1: np.ndarray) -> GridSpec:
        """The :class:`GridSpec` of voxel indices i0..i1 (inclusive)."""
        s = self.voxel
        return GridSpec(tuple(self.origin + i0 * s), tuple(self.origin + (i1 + 1) * s), s)

    def dense(self, i0: np.ndarray, i1: np.ndarray, names: tuple[str, ...],
              blocks: tuple | None = None) -> dict[str, np.ndarray]:
        """Arrays over voxel indices i0..i1 (inclusive): +inf / 0 where no block (``blocks``:
        :meth:`blocks`' result, read here if None)."""
        shape = tuple(int(x) for x in i1 - i0 + 1)
        if min(shape) <= 0:
            return {n: np.zeros((0, 0, 0), np.uint64 if n == "count" else np.float32) for n in names}
        if int(np.prod(shape)) > _MAX_BOX_VOXELS:
            raise ValueError(f"Expected a box of at most {_MAX_BOX_VOXELS} voxels, but got {shape}")
        coords, data = self.blocks() if blocks is None else blocks
        B, Bz, bs = self.B, self.Bz, self.bs
        b0, b1 = i0 // bs, i1 // bs
        nb = tuple(int(x) for x in b1 - b0 + 1)
        sel = np.all((coords >= b0) & (coords <= b1), axis=1)
        r = coords[sel] - b0
        whole = len(r) == int(np.prod(nb))  # every block of the box, in coordinate order
        out = {}
        for n in names:
            dt = data[n].dtype  # where no block: +inf for values, 0 for counts and flags
            fill = np.inf if dt.kind == "f" else 0
            if whole:
                V = data[n][sel].reshape(*nb, B, B, Bz)
            else:
                V = np.full((*nb, B, B, Bz), fill, dt)
                V[r[:, 0], r[:, 1], r[:, 2]] = data[n][sel].reshape(-1, B, B, Bz)
            V = V.transpose(0, 3, 1, 4, 2, 5).reshape(*(x * e for x, e in zip(nb, bs, strict=True)))
            a = i0 - b0 * bs
            out[n] = np.ascontiguousarray(
                V[a[0] : a[0] + shape[0], a[1] : a[1] + shape[1], a[2] : a[2] + shape[2]]
            )
        return out

    def to_pool_order(self, a: np.ndarray, fill) -> np.ndarray:
        """A bounded box's (nx, ny, nz) array as (n_blocks, B B Bz) in slot order (``fill`` past the box)."""
        B, Bz = self.B, self.Bz
        nb = self.index.shape
        V = np.full((nb[0] * B, nb[1] * B, nb[2] * Bz), fill, a.dtype)
        V[: a.shape[0], : a.shape[1], : a.shape[2]] = a
        return np.ascontiguousarray(
            V.reshape(nb[0], B, nb[1], B, nb[2], Bz).transpose(0, 2, 4, 1, 3, 5)).reshape(-1, self.BV)

    def memory_stats(self) -> dict:
        """Blocks and bytes (see :meth:`gpumap.MinMaxMapper.memory_stats`)."""
        with self.lock:
            self.synchronize()
            self.reclaim()
            coords, data = self.blocks()
            n_obs = int(np.isfinite(data["min_all"]).sum())
            i0, i1 = self.whole_box()
            n = len(coords)
            bpv = self.bytes_per_voxel
            cap = self.backend.cap
            dense = int(np.prod(i1 - i0 + 1)) * bpv if n or self.dims is not None else 0
            return {
                "blocks": n,
                "block_size": self.B if self.Bz == self.B else [self.B, self.B, self.Bz],
                "observed_voxels": n_obs,
                "bytes_per_voxel": bpv,
                "block_bytes": n * self.BV * bpv,
                "observed_bytes": n_obs * bpv,
                "block_over_observed": (n * self.BV / n_obs) if n_obs else None,
                "pool_blocks": cap,
                "pool_bytes": cap * self.block_bytes,
                "index_bytes": int(self.index.nbytes),
                "total_bytes": cap * self.block_bytes + int(self.index.nbytes),
                "dense_bytes": dense,
            }
