"""The min-max occupancy mapper: the public entry point of gpumap.

One :class:`MinMaxMapper` serves a fixed box and an open world. Its map lives in *blocks* of
``B x B x Bz`` voxels on the backend's device: a *pool* of slots (per voxel
float32 ``min_all``, and for the evidence and visible rules float32 ``bright`` and uint64 ``count``
(two packed view counts): 16 bytes; 4 for the plain rule) and a dense coarse *index* of int32
slots, one per block of a box (``-1`` = no block; 4 bytes per 512 voxels). Every kernel
addresses a voxel through the index: its block's slot times its size plus its place in the
block (an O(1) read: no hash, no probing, nothing OpenCL 1.2 lacks), in one kernel family for
every storage (``gpumap.kernels.minmax``).

- **A bounded box** (a :class:`~gpumap.GridSpec`): every block of the box is allocated up front
  and the index is the identity, so a ping costs no block search (the dense grid's speed).
- **On demand** (a :class:`~gpumap.SparseSpec`, bounded or not, or ``sparse=True``): per ping
  the host finds, vectorised in NumPy over the (i, j) *block columns* of the ping's box, the
  z-range of blocks that the field of view can reach (the kernels' ``column_range`` bound,
  widened to a block column's footprint and padded against float32 rounding, so it is
  conservative), gives new blocks a slot (the pool grows by 1.5x) and grows an unbounded map's
  index when pings leave it. The kernels flag any observed voxel that found no block (``err``,
  :meth:`MinMaxMapper.check`): the tests check it never happens. Each block carries a "seen"
  byte set by the kernels; before the pool grows, and before reads and saves, blocks no ping
  observed are freed. ``max_bytes`` bounds the pool plus the index: a ping that needs more
  raises :class:`MapMemoryError` before it changes the map (``evict=None``), or with
  ``evict="farthest"`` frees the blocks farthest from the sonar that the ping does not touch.

Both give the same values, bit for bit, wherever both have voxels: the same per-voxel code runs
on the same voxel centres. Considered and not chosen: Warp's NanoVDB volumes (CUDA only, one
value type per tree, a tree walk per voxel), and an open-addressing hash on the device (would
lift the coarse index's one limit, that it spans the box of everything mapped: a 10 km transit
at 5 cm needs a 2 GB index; not needed for a survey area).
"""

from __future__ import annotations

import functools
import json
import logging
import math
import os
import struct
import threading
import tokenize
import zipfile
import zlib
from pathlib import Path

import numpy as np

from gpumap.atomic import atomic_write
from gpumap.backends import AUTO_ORDER, BACKENDS, Backend, GridTooLargeError, make_backend
from gpumap.backends import available_backends as _available
from gpumap.errors import (
    BackendUnavailableError,
    FormatError,
    LimitError,
    check_carve_views,
    check_finite_scalar,
    check_pose,
)
from gpumap.geometry import BRIGHT_SHARE, RULES, SHARE_Z, make_template_S, pose_pad_m, static_params
from gpumap.memory import STATE_BYTES
from gpumap.pings import PingPrints, read_prints
from gpumap.spec import _MAX_VOXEL_INDEX, GridSpec, SonarSpec, SparseSpec, _vec3

__all__ = ["MapMemoryError", "MinMaxMapper", "available_backends"]

log = logging.getLogger("gpumap")

METHODS = ("gather", "template")
_ONE_BITS = np.uint32(0x3F800000)  # the bits of float32 1.0
FILE_FORMAT = "gpumap.MinMaxMapper"
# 5: the evidence rule (``count`` uint64: clear dark and bright views; bright_share, share_z);
# 4: blocks (``blocks`` and per-block arrays) for every storage; 3: the optional confidence layer
# (confirmed); 2: the visible rule's evidence (bright, count) and the rule; 1 to 3 are dense
# arrays over the grid, and still load, as do files of the former SparseMinMaxMapper
FILE_VERSION = 5
SPARSE_FILE_FORMAT = "gpumap.SparseMinMaxMapper"  # written until version 4 took its place
BLOCK = 8  # voxels per block edge of a bounded box (a SparseSpec says its own)
GROWTH = 1.5  # an on-demand pool grows by this factor (at least to what a ping needs)
_CANDIDATE_GROUP = 8  # pings per vectorised block test
_MAX_INDEX_BLOCKS = 2**31 - 1
_MAX_BOX_VOXELS = 2**31 - 1
_MAX_POOL_VOXELS = 2**31 - 1  # kernels address the pool with int32


_ANNOUNCED: set[tuple[str, str]] = set()  # the (backend, device) pairs "auto" has logged in this process


class MapMemoryError(GridTooLargeError):
    """A ping (or a spec) needs more memory than the cap or the device allows; the map is unchanged."""


def available_backends() -> list[str]:
    """Backends that run on this machine, in the order ``backend="auto"`` tries them."""
    return _available()


def rule_values(rule: str, min_all: np.ndarray, bright, count, carve_views: int, bright_share: float,
                share_z: float) -> np.ndarray:
    """A map's values from its per-voxel state, by ``rule`` (:mod:`gpumap.reference`)."""
    from gpumap.reference import evidence_values, visible_values

    if rule == "visible":
        return visible_values(min_all, bright, count, carve_views)
    if rule == "evidence":
        return evidence_values(min_all, bright, count, bright_share, share_z)
    return min_all


def _free_memory_bytes(name: str) -> int | None:
    """Best guess of the memory a grid may take on the backend ``name`` (None if unknown)."""
    try:
        if name in ("numpy", "warp-cpu") or name.startswith("opencl"):
            with open("/proc/meminfo") as f:
                for line in f:
                    if line.startswith("MemAvailable:"):
                        return int(line.split()[1]) * 1024
        if name == "warp-cuda":
            from gpumap.backends import _warp

            wp, _ = _warp()  # initialised quietly, as the backend does
            return int(wp.get_device("cuda:0").free_memory)
    except Exception:  # the check is advisory; the allocation itself still fails loudly
        return None
    return None


def _check_pose_cov(pose_cov: object) -> np.ndarray:
    """(6, 6) finite, symmetric, positive semi-definite float64, or raise saying what came."""
    if isinstance(pose_cov, np.ma.MaskedArray):
        raise TypeError("Expected a plain array for 'pose_cov', but got a masked array")
    C = np.asarray(pose_cov)
    if C.shape != (6, 6) or C.dtype.kind not in "fiu":
        raise ValueError(f"Expected pose_cov of shape (6, 6) real, but got {C.shape} {C.dtype}")
    C = C.astype(np.float64)
    scale = max(1.0, float(np.abs(C).max())) if np.all(np.isfinite(C)) else np.inf
    if not np.isfinite(scale) or not np.allclose(C, C.T, rtol=0.0, atol=1e-9 * scale):
        raise ValueError("Expected a finite, symmetric pose_cov, but got one that is not")
    C = 0.5 * (C + C.T)
    if np.linalg.eigvalsh(C)[0] < -1e-12 * scale:
        raise ValueError("Expected a positive semi-definite pose_cov, but it has a negative eigenvalue")
    return C


def _check_poses(Ts: np.ndarray) -> np.ndarray:
    """(B, 4, 4) float64 copy of ``Ts`` after :func:`gpumap.errors.check_pose`'s checks, in
    whole-array form; the first pose that fails is handed to check_pose for its message."""
    if np.iscomplexobj(Ts) or Ts.dtype.kind not in "fiub":
        raise TypeError(f"Expected real entries in 'T_W_S', but got dtype {Ts.dtype}")
    a = np.array(Ts, dtype=np.float64)
    if a.shape[0] == 0:
        return a
    atol = 1e-5
    R = a[:, :3, :3]
    G = np.einsum("bki,bkj->bij", R, R) - np.eye(3)
    c0, c1, c2 = R[:, :, 0], R[:, :, 1], R[:, :, 2]
    det = np.einsum("bi,bi->b", np.cross(c0, c1), c2)
    with np.errstate(invalid="ignore"):
        bad = (
            ~np.isfinite(a).all(axis=(1, 2))
            | (np.abs(a[:, 3] - (0.0, 0.0, 0.0, 1.0)) > atol).any(axis=1)
            | (np.abs(G).max(axis=(1, 2)) > atol)
            | (det < 0)
        )
    for k in np.flatnonzero(bad):  # raises with check_pose's message (or the pose passes)
        a[k] = check_pose(Ts[k], f"T_W_S[{k}]")
    return a


def _evidence_empty(n: int) -> tuple[np.ndarray, np.ndarray]:
    return np.full(n, np.inf, dtype=np.float32), np.zeros(n, dtype=np.uint8)


@functools.cache
def _local(B: int, Bz: int) -> np.ndarray:
    """(B B Bz, 3) int64 local voxel offsets of a block, in storage order."""
    a = np.arange(B * B * Bz)
    return np.stack([a // (B * Bz), (a // Bz) % B, a % Bz], axis=1)


class MinMaxMapper:
    """Min-max filtering occupancy map (Phung et al.), on a bounded grid or an open world.

    For each ping, every voxel whose centre the sonar sees gets the maximum image intensity
    over its footprint (the cells its bounding sphere touches: conservative, so a thin bright
    object is never lost to sampling). Never-observed voxels stay unknown.

    How views combine (``rule``). A view is *clear* when no image cell ``>= threshold`` lies
    nearer than the voxel's footprint in the footprint's beams: nothing stood between the sonar
    and the voxel, at any elevation. A dark view behind a return proves nothing: the voxel may
    sit in that return's acoustic shadow, or be a surface seen at grazing incidence behind
    nearer parts of itself.

    - ``"evidence"`` (default with ``method="gather"``): per voxel, the number of bright views
      (``>= threshold``) and of clear dark views. A voxel is occupied when some view saw it
      bright and its views do not show, at confidence ``share_z`` (a one-sided normal quantile;
      1.645: 95 %), that it is bright in fewer than ``bright_share`` (0.2) of them (the Wilson
      score upper bound of the bright share is at least ``bright_share``); free when no view saw it
      bright, or when they do show it; unknown when no view observed it. The decision rests on
      a proportion, so it converges as views accumulate instead of drifting towards "free" as a
      min over views does: a real surface, bright in most but not all of its views (speckle,
      gain, pose error, grazing incidence), stays occupied however long the sonar looks, while
      water that the elevation aperture painted bright now and then is carved once enough
      clear views show it dark. The two counts are 32-bit and saturate on their own at
      2^32 - 1 (6.8 years of one voxel in view at 20 Hz); at the limit the count stops and the
      decision keeps the share it had. An occupied voxel's value is its dimmest bright view,
      a free one's the minimum over its views. Every update is a min or a saturating count,
      so the map does not depend on the order of the pings and merges exactly. 12 bytes per
      voxel more than the plain rule (a float32 and a uint64) and a per-beam scan of each ping.
    - ``"visible"``: a voxel ever seen bright keeps the dimmest of its bright values until
      clear dark views carve it: ``carve_views`` (2) of them, one darker than
      ``threshold / 2`` counting twice. A fixed count of dark views: the longer the sonar
      looks, the more of a real surface's normal speckle-dark views add up and carve it
      (kept by name, to measure that). A voxel never seen bright takes the minimum over its
      views, as in the plain rule.
    - ``"plain"``: the paper's rule: the minimum over all views. A ping carves voxels in its
      acoustic shadow, so surfaces seen from one side are erased by views from the other.

    Storage (module docstring): blocks of voxels, all of a bounded box up front, or
    allocated where pings look; the values are the same either way.

    Parameters
    ----------
    spec : SonarSpec
        The sonar's geometry.
    grid : GridSpec or SparseSpec
        The world grid. A :class:`~gpumap.GridSpec` (a bounded box) has every block allocated
        up front: no per-ping block search, the fastest. A :class:`~gpumap.SparseSpec` (an
        optional box, a block size and an origin) allocates blocks where pings look, so memory
        grows with what the sonar has seen (:meth:`memory_stats`).
    backend : str
        ``"auto"`` (fastest that works, in the order warp-cuda, opencl on a GPU, opencl on
        a CPU (PoCL), warp-cpu, numpy; the choice is logged and kept in :attr:`backend`),
        or one of ``"numpy"``, ``"warp-cpu"``, ``"warp-cuda"``, ``"opencl"`` (GPU if there
        is one, else CPU), ``"opencl-gpu"``, ``"opencl-cpu"``. A named backend that cannot
        run raises :class:`gpumap.BackendUnavailableError`; it never falls back.
    method : str
        ``"gather"`` (every voxel of the field of view's bounding box, no holes) or
        ``"template"`` (the paper's six steps on a voxel template: may leave holes; a
        bounded GridSpec only).
    shadow_m : float
        Acoustic-shadow allowance, metres (default 0: the paper's min-max). A strong return
        also counts for the voxels up to ``shadow_m`` behind it in its beams, so a ping does
        not carve the far side of a thin object it cannot see through (each footprint reaches
        ``shadow_m`` further towards the sonar). Trades false positives behind returns for
        fewer false negatives; think of it as the thinnest object the map must keep whole.
    footprint_max : str
        How kernels take the max over a footprint, a speed knob with identical results:
        ``"auto"``/``"table"`` (a per-ping max table, built in the way that suits the
        device, then two reads per voxel) or ``"loop"`` (a loop over the footprint's cells).
    rule : str or None
        ``"evidence"``, ``"visible"`` or ``"plain"``, see above; None (default) picks
        ``"evidence"`` for the gather method and ``"plain"`` for the template method (the
        paper's six steps with the paper's rule; the others need ``method="gather"``).
    threshold : float
        Intensity in (0, 1] from which a view counts as bright (the visible rule's returns and
        shadows). Set it to the threshold you read the map at; lower is more conservative
        (more views count as bright, fewer carve). Default 0.1.
    carve_views : int
        Visible rule: the clear dark evidence that carves a voxel once seen bright, in views
        (one darker than ``threshold / 2`` counts twice). 2 (default) keeps a surface through
        one speckle-dark view; 1 carves more water and more weak surfaces (fewer false
        positives, more false negatives); larger is more conservative. Read-time only: it
        may be changed between pings (:attr:`carve_views`), in 1..255.
    bright_share : float
        Evidence rule: the share of bright views, in (0, 1], below which a voxel is free once
        the views show it (default :data:`gpumap.geometry.BRIGHT_SHARE`, 0.2: chosen so that no
        simulated object erodes over 1,000 pings with the real sonar's view-to-view variation;
        0.5 keeps fewer phantoms on the real tank but loses a third of the objects seen from
        all sides, ``bench.long_run``). Read-time only.
    share_z : float
        Evidence rule: how sure the views must be before they free a voxel, as a one-sided
        normal quantile in [0, 10] (default :data:`gpumap.geometry.SHARE_Z`, 1.645: 95 %);
        larger keeps more voxels occupied on few views. Read-time only.
    confidence : bool
        Keep the confidence layer (:mod:`gpumap.confidence`; a bounded GridSpec only): after
        each ping a separate pass marks the occupied voxels that view confirmed (resolved in
        elevation), read with :meth:`confidence`; :meth:`view_gain` scores candidate poses
        against it. Costs a byte per voxel on the host and one read of the map per ping.
        Default False.
    sparse : bool or None
        True: allocate blocks on demand even for a GridSpec (its box bounds the map). None
        (default): on demand for a SparseSpec, all blocks for a GridSpec.
    max_bytes : int or None
        On demand only: cap on the block pool plus the coarse index, bytes (None: what the
        device allows).
    evict : None or "farthest"
        On demand only: what a ping that would pass ``max_bytes`` does. None raises
        :class:`MapMemoryError` with the map unchanged; ``"farthest"`` frees the blocks
        farthest from the sonar (block centre to the sonar's position) that the ping does not
        reach, which become unknown.
    initial_blocks : int
        On demand only: pool slots allocated up front (default 64; the pool grows by 1.5x).
    """

    _on_demand = False  # a subclass that only holds maps on demand (gpumap.sparse.SparseMinMaxMapper)

    def __init__(
        self,
        spec: SonarSpec,
        grid: GridSpec | SparseSpec,
        backend: str = "auto",
        method: str = "gather",
        *,
        shadow_m: float = 0.0,
        footprint_max: str = "auto",
        rule: str | None = None,
        threshold: float = 0.1,
        carve_views: int = 2,
        bright_share: float = BRIGHT_SHARE,
        share_z: float = SHARE_Z,
        confidence: bool = False,
        sparse: bool | None = None,
        max_bytes: int | None = None,
        evict: str | None = None,
        initial_blocks: int = 64,
    ) -> None:
        if not isinstance(spec, SonarSpec):
            raise TypeError(f"Expected a gpumap.SonarSpec for 'spec', but got {type(spec).__name__}")
        if sparse not in (None, True, False):
            raise TypeError(f"Expected None or a bool for 'sparse', but got {sparse!r}")
        if isinstance(grid, GridSpec):
            space = SparseSpec(grid.voxel_size_m, (grid.min_corner_m, grid.max_corner_m)) if sparse else None
        elif isinstance(grid, SparseSpec):
            if sparse is False:
                raise ValueError("Expected sparse=None or True with a SparseSpec (it allocates on demand), "
                                 "but got sparse=False; pass its box as a GridSpec for a dense map")
            space = grid
        else:
            raise TypeError(
                f"Expected a gpumap.GridSpec or gpumap.SparseSpec for 'grid', but got {type(grid).__name__}")
        if method not in METHODS:
            raise ValueError(f"Expected method to be one of {METHODS}, but got {method!r}")
        if backend != "auto" and backend not in BACKENDS:
            raise ValueError(f"Expected backend to be 'auto' or one of {BACKENDS}, but got {backend!r}")
        if footprint_max not in ("auto", "table", "loop"):
            raise ValueError(
                f"Expected footprint_max to be 'auto', 'table' or 'loop', but got {footprint_max!r}"
            )
        if rule is None:
            rule = "evidence" if method == "gather" else "plain"
        if rule not in RULES:
            raise ValueError(f"Expected rule to be one of {RULES} (or None), but got {rule!r}")
        if rule != "plain" and method != "gather":
            raise ValueError(
                f"Expected method='gather' with rule={rule!r} (the template method's duplicate "
                f"points cannot count views once), but got method={method!r}; use rule='plain' with it"
            )
        thr = check_finite_scalar(threshold, "threshold")
        if not 0.0 < thr <= 1.0:
            raise ValueError(f"Expected threshold in (0, 1], but got {thr}")
        shadow = check_finite_scalar(shadow_m, "shadow_m")
        if shadow < 0:
            raise ValueError(f"Expected shadow_m >= 0, but got {shadow}")
        if not isinstance(confidence, (bool, np.bool_)):
            raise TypeError(f"Expected a bool for 'confidence', but got {type(confidence).__name__}")
        if space is not None and (method != "gather" or confidence):
            raise ValueError(
                "Expected method='gather' and no confidence layer on a map that allocates blocks on demand "
                f"(the template method and the confidence layer need a bounded GridSpec), but got "
                f"method={method!r}, confidence={bool(confidence)}"
            )
        if evict not in (None, "farthest"):
            raise ValueError(f"Expected evict to be None or 'farthest', but got {evict!r}")
        if max_bytes is not None and (
            isinstance(max_bytes, bool) or not isinstance(max_bytes, (int, np.integer)) or max_bytes <= 0
        ):
            raise ValueError(f"Expected max_bytes to be a positive integer or None, but got {max_bytes!r}")
        if isinstance(initial_blocks, bool) or not isinstance(initial_blocks, (int, np.integer)) \
                or initial_blocks < 1:
            raise ValueError(f"Expected initial_blocks to be a positive integer, but got {initial_blocks!r}")
        if space is None and (max_bytes is not None or evict is not None):
            raise ValueError("Expected max_bytes and evict only with blocks on demand (a SparseSpec or "
                             "sparse=True): a GridSpec's blocks are all allocated up front")
        self.spec, self.sparse = spec, space
        self.method, self.rule, self.threshold, self.shadow_m = method, rule, thr, shadow
        self.carve_views = carve_views
        self.bright_share = bright_share
        self.share_z = share_z
        self._use_table = None if footprint_max == "auto" else footprint_max == "table"
        self.max_bytes = None if max_bytes is None else int(max_bytes)
        self.evict = evict
        self.n_integrated = 0
        self.pings = PingPrints()  # a fingerprint per integrated ping (gpumap.pings)
        self._empty = True  # no ping, merge or load has gone into the map since it was made or reset
        self._stateful = rule != "plain"  # the visible and evidence rules keep bright and count
        # a bounded box's blocks are BLOCK x BLOCK columns of the grid's height (one index read per
        # column in the kernels, which then walk contiguous voxels: the dense grid's speed); blocks
        # on demand are cubes of the SparseSpec's edge
        B = BLOCK if space is None else space.block
        Bz = int(grid.shape[2]) if space is None else B
        self.B, self.Bz, self.BV = B, Bz, B * B * Bz
        self._bs = np.array([B, B, Bz], np.int64)
        self.bytes_per_voxel = STATE_BYTES[rule]  # gpumap.memory's one table of the rules' state
        self._block_bytes = self.BV * self.bytes_per_voxel + 1  # + the seen byte
        if space is None:
            self._grid = grid
            self._voxel, self._origin = grid.voxel_size_m, np.asarray(grid.min_corner_m, np.float64)
            self._dims = np.asarray(grid.shape, np.int64)
            pgrid = grid
        else:
            self._grid = None  # the bounds' grid, or the box of the blocks (see the property)
            self._voxel, self._origin = space.voxel_size_m, np.asarray(space.origin, np.float64)
            self._dims = None if space.bounds is None else np.asarray(space.shape, np.int64)
            o, s = space.origin, space.voxel_size_m
            pgrid = GridSpec(o, tuple(x + B * s for x in o), s)
        self._params = static_params(spec, pgrid, shadow, rule, thr)
        self._rho0, self._near0 = float(self._params["rho"]), float(self._params["near"])
        self._fov_pts_S = spec.fov_corners_S()
        self._template = make_template_S(spec, grid.voxel_size_m) if method == "template" else None
        if self._template is not None:
            self._params["n_points"] = self._template.shape[0]
        self._staging = np.empty(spec.image_shape, dtype=np.float32)
        # One ping at a time: integrate, reads and writes hold this lock, so threads sharing a
        # mapper serialize (and, every update being a min or a count, get the map one thread
        # would have made).
        self._lock = threading.RLock()
        # the coarse index: block (lo_b + (a, b, c)) -> slot, -1 none
        self._lo_b = np.zeros(3, np.int64)
        nb = np.zeros(3, np.int64) if self._dims is None else -(-self._dims // self._bs)
        if self._dims is not None:
            self._check_index_size(nb, "the bounds")
        n_blocks = int(np.prod(nb))
        if space is None:  # every block of the box, slot = index entry (the identity)
            if n_blocks * self.BV > _MAX_POOL_VOXELS:
                raise GridTooLargeError(
                    f"Expected at most {_MAX_POOL_VOXELS} voxels in the grid's blocks, but {grid.shape} "
                    f"voxels take {n_blocks} blocks of {B} x {B} x {Bz}"
                )
            self._index = np.arange(n_blocks, dtype=np.int32).reshape(tuple(int(x) for x in nb))
            cap = n_blocks
            self._coords = self._unravel(np.arange(n_blocks))
            self._used = np.ones(cap, bool)
            self._free = np.zeros(0, np.int64)
        else:
            self._index = np.full(tuple(int(x) for x in nb), -1, np.int32)
            cap = int(initial_blocks)
            if self.max_bytes is not None:
                cap = max(1, min(cap, (self.max_bytes - self._index.nbytes) // self._block_bytes))
            self._coords = np.zeros((cap, 3), np.int64)
            self._used = np.zeros(cap, bool)
            self._free = np.arange(cap - 1, -1, -1, dtype=np.int64)  # a stack: pop from the end
        self._backend = self._make_backend(backend, cap)
        self._backend.set_index(self._index, self._lo_b * self._bs)
        n_vox = 0 if space is not None or not confidence else grid.n_voxels
        self._confirmed = np.zeros(n_vox, np.uint8) if confidence else None
        # the elevation-arc directions (gpumap.nbv.PAIR_STEPS bits) each voxel was observed along
        self._arcs = np.zeros(n_vox, np.uint16) if confidence else None
        self._gain_runner = None
        # auto says what it picked, once a process (a command makes several mappers); a backend asked
        # for by name is what the caller already knows
        said = (self._backend.name, self._backend.device)
        (log.info if backend == "auto" and said not in _ANNOUNCED else log.debug)(
            "gpumap: backend %s on %s", self._backend.name, self._backend.device)
        _ANNOUNCED.add(said)

    # ------------------------------------------------------------------ setup
    def _check_index_size(self, nb: np.ndarray, what: str) -> None:
        n = int(np.prod(nb))
        need = 4 * n
        if n > _MAX_INDEX_BLOCKS:
            raise MapMemoryError(
                f"Expected at most {_MAX_INDEX_BLOCKS} blocks in the coarse index, but {what} span "
                f"{tuple(int(x) for x in nb)} blocks of {self.BV} voxels"
            )
        if self.max_bytes is not None and need + self._block_bytes > self.max_bytes:
            raise MapMemoryError(
                f"Expected the coarse index of {what} to fit under max_bytes={self.max_bytes}, but it "
                f"needs {need} bytes ({tuple(int(x) for x in nb)} blocks) plus at least one block of "
                f"{self._block_bytes}"
            )
        free = _free_memory_bytes("numpy")
        if free is not None and 2 * need > free:
            raise MapMemoryError(
                f"Expected a coarse index that fits in memory, but {what} need {need / 2**30:.2f} GiB "
                f"(twice that while growing) and {free / 2**30:.2f} GiB are free"
            )

    def _make_backend(self, backend: str, cap: int) -> Backend:
        names = AUTO_ORDER if backend == "auto" else (backend,)
        errors = []
        for name in names:
            need = cap * self.BV * self.bytes_per_voxel
            free = _free_memory_bytes(name)
            if self.sparse is None and free is not None and need > free:
                msg = (
                    f"Expected a grid that fits in memory, but {self.grid.shape} voxels at "
                    f"voxel_size_m={self.grid.voxel_size_m} need {need / 2**30:.2f} GiB and "
                    f"{name} has {free / 2**30:.2f} GiB free ({self.bytes_per_voxel} bytes a voxel, "
                    f"in blocks of {self.B} x {self.B} x {self.Bz})"
                )
                if backend != "auto":
                    raise ValueError(msg)
                errors.append(f"{name}: {msg}")
                continue
            try:
                return make_backend(name, self.spec, self._template, self._use_table, visible=self._stateful,
                                    B=self.B, Bz=self.Bz, cap=cap)
            except (BackendUnavailableError, GridTooLargeError) as e:
                if backend != "auto":
                    raise
                errors.append(f"{name}: {e}")
        raise BackendUnavailableError("No backend could run: " + "; ".join(errors))

    # ------------------------------------------------------------------ properties
    @property
    def backend(self) -> str:
        """The backend in use, as ``gpumap info`` names it: ``"warp-cuda"``, ``"warp-cpu"``,
        ``"opencl-gpu"``, ``"opencl-cpu"`` or ``"numpy"`` (``"auto"`` and ``"opencl"`` resolve to one)."""
        return self._backend.name

    @property
    def device(self) -> str:
        """The device the backend runs on, in words."""
        return self._backend.device

    @property
    def carve_views(self) -> int:
        """Visible rule: clear dark views that carve a voxel once seen bright (see the class)."""
        return self._carve_views

    @carve_views.setter
    def carve_views(self, n: int) -> None:
        self._carve_views = check_carve_views(n)

    @property
    def bright_share(self) -> float:
        """Evidence rule: the share of bright views below which a voxel is free (see the class)."""
        return self._bright_share

    @bright_share.setter
    def bright_share(self, p: float) -> None:
        p = check_finite_scalar(p, "bright_share")
        if not 0.0 < p <= 1.0:
            raise ValueError(f"Expected bright_share in (0, 1], but got {p}")
        self._bright_share = p

    @property
    def share_z(self) -> float:
        """Evidence rule: the one-sided normal quantile of the confidence that frees a voxel."""
        return self._share_z

    @share_z.setter
    def share_z(self, z: float) -> None:
        z = check_finite_scalar(z, "share_z")
        if not 0.0 <= z <= 10.0:
            raise ValueError(f"Expected share_z in [0, 10], but got {z}")
        self._share_z = z

    def _rule_values(self, min_all: np.ndarray, bright, count) -> np.ndarray:
        """The map's values from its state, by the rule (the plain rule's are ``min_all``)."""
        return rule_values(self.rule, min_all, bright, count, self.carve_views, self.bright_share,
                           self.share_z)

    @property
    def grid(self) -> GridSpec:
        """The :class:`GridSpec` that :meth:`values` covers: the box, or for an unbounded map the
        box of its blocks (one voxel at the origin while empty)."""
        if self._grid is not None:
            return self._grid
        if self._dims is not None:
            return self.sparse.grid
        with self._lock:
            self._settle()
            i0, i1 = self._whole_box()
        return self._box_grid(i0, i1)

    # ------------------------------------------------------------------ update
    def _check_image(self, image: object) -> np.ndarray:
        """The image as C-contiguous uint8 (backends scale it by 1/255, GPUs after the upload)
        or float32 in [0, 1]: ``image`` itself when it already is, else a conversion in the
        mapper's staging buffer. Raises on anything else."""
        if not isinstance(image, np.ndarray):
            raise TypeError(f"Expected a numpy array for 'image', but got {type(image).__name__}")
        if isinstance(image, np.ma.MaskedArray):  # its data under the mask could be anything
            raise TypeError(
                "Expected a plain numpy array for 'image', but got a masked array: fill it first "
                "(image.filled(0.0) treats masked cells as no return)"
            )
        if image.shape != self.spec.image_shape:
            raise ValueError(
                f"Expected image of shape {self.spec.image_shape} (n_bins, n_beams) for 'image', "
                f"but got {image.shape}"
            )
        out = self._staging
        if image.dtype == np.uint8:  # every byte is a valid intensity; backends widen it
            return np.ascontiguousarray(image)
        if image.dtype == np.float32 and image.flags.c_contiguous:
            # One pass: as unsigned bits, every float in [+0, 1] is <= 0x3F800000, while
            # negatives (sign bit), NaN and inf are all above it.
            if image.view(np.uint32).max() <= _ONE_BITS:
                return image
        elif image.dtype not in (np.float32, np.float64):
            raise TypeError(f"Expected image of dtype float32 or uint8 for 'image', but got {image.dtype}")
        bad = ~np.isfinite(image)
        if bad.any():
            r, c = np.argwhere(bad)[0]
            raise ValueError(
                f"Expected finite intensities in 'image', but got {image[r, c]} at (bin {r}, beam {c})"
                f" and {int(bad.sum()) - 1} more"
            )
        lo, hi = image.min(), image.max()
        if not (lo >= 0.0 and hi <= 1.0):
            raise ValueError(f"Expected intensities in [0, 1] in 'image', but got range [{lo}, {hi}]")
        np.add(image, np.float32(0.0), out=out, casting="same_kind")  # -0.0 -> +0.0, float64 -> 32
        return out

    def integrate(
        self,
        image: np.ndarray,
        T_W_S: np.ndarray,
        pose_cov: np.ndarray | None = None,
        pose_sigmas: float = 2.0,
    ) -> None:
        """Fuse one ping into the map.

        Parameters
        ----------
        image : (n_bins, n_beams) float32 in [0, 1], or uint8 (scaled by 1/255)
            Polar image: row = range bin (ascending), column = beam (ascending azimuth).
        T_W_S : (4, 4) float
            Sonar pose: maps sonar-frame points to the world frame, metres.
        pose_cov : (6, 6) float, optional
            Uncertainty of ``T_W_S`` over (translation m, rotation vector rad), a right
            perturbation ``T_W_S = T_hat @ Exp(delta)`` as :attr:`gpumap.ekf.SonarEKF.pose_cov`
            gives it. Every footprint then grows by how far a voxel may move at
            ``pose_sigmas`` standard deviations (:func:`gpumap.geometry.pose_pad_m`), at the
            field of view's far edge: the map stays conservative (a voxel's ping value covers
            every pose within the bound) at the price of wider footprints.
        pose_sigmas : float
            The bound's width in standard deviations (default 2).

        Raises ``ValueError``/``TypeError`` on bad input, and on demand :class:`MapMemoryError`
        when the new blocks would pass ``max_bytes`` (``evict=None``) or the device's memory; in
        every case before the map changes.
        """
        T = check_pose(T_W_S, "T_W_S")
        pads = np.zeros(1)
        with self._lock:  # the staging buffer is the mapper's own
            img = self._check_image(image)
            if pose_cov is not None:
                pads[0] = self._pose_pad(_check_pose_cov(pose_cov), pose_sigmas)
            params, n_threads = self._ping_params(T[None], pads)
            self._prepare(params, T[None], n_threads)
            self._empty = False
            self._backend.integrate(params[0, ...], img, self.method, int(n_threads[0]))
            if self._confirmed is not None:
                self._confirm(T, pads[0], img)
            self.n_integrated += 1  # under the lock
            self.pings.add(img, T)

    def _pose_pad(self, C: np.ndarray, pose_sigmas: float) -> float:
        k = check_finite_scalar(pose_sigmas, "pose_sigmas")
        if k < 0:
            raise ValueError(f"Expected pose_sigmas >= 0, but got {k}")
        return pose_pad_m(C, self.spec.range_max_m, k)

    def _ping_params(self, Ts: np.ndarray, pads: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(B,) PING_DTYPE records and gather column counts for checked poses ``Ts`` (B, 4, 4)
        and footprint pads (B,) m, in whole-array NumPy (the work of
        :func:`gpumap.geometry.ping_params` and :func:`~gpumap.geometry.set_footprint_pad`,
        vectorised: one code path for a ping and a batch, and for every storage, so all give
        the same records). An unbounded map's boxes are not clipped; a pose whose box would
        leave int32 voxel indices raises ``ValueError``."""
        B = Ts.shape[0]
        P = np.empty(B, dtype=self._params.dtype)
        P[...] = self._params
        R = Ts[:, :3, :3]
        t = Ts[:, :3, 3]
        Rt = R.transpose(0, 2, 1)
        P["R"] = R.reshape(B, 9)
        P["t"] = t
        P["A"] = Rt.reshape(B, 9)
        # -(R^T t), each entry summed in a fixed order
        P["b"] = -(R[:, 0, :] * t[:, 0:1] + R[:, 1, :] * t[:, 1:2] + R[:, 2, :] * t[:, 2:3])
        if np.any(pads != 0.0):
            P["rho"] = self._rho0 + pads
            P["near"] = self._near0 + pads
            win = np.floor((P["rho"].astype(np.float64) + P["near"]) * P["inv_dr"].astype(np.float64)) + 2
            P["win"] = np.minimum(win, self.spec.n_bins)
        pts = self._fov_pts_S  # (m, 3): the box, padded by a voxel, holds every visible centre
        W = (pts[None, :, 0:1] * Rt[:, None, 0, :] + pts[None, :, 1:2] * Rt[:, None, 1, :]
             + pts[None, :, 2:3] * Rt[:, None, 2, :])
        s = self._voxel
        q0 = (W.min(axis=1) + t - self._origin) / s
        q1 = (W.max(axis=1) + t - self._origin) / s
        dims = self._dims
        if dims is None:
            far = np.maximum(np.abs(q0).max(axis=1), np.abs(q1).max(axis=1)) > _MAX_VOXEL_INDEX - 2 * self.B
            if far.any():
                k = int(np.argmax(far))
                raise ValueError(
                    f"Expected a sonar pose within {(_MAX_VOXEL_INDEX - 2 * self.B) * s:.4g} m of the map "
                    f"origin {tuple(self._origin)} (voxel indices fit in int32), but T_W_S[{k}] puts it at "
                    f"{t[k].tolist()}"
                )
            i0 = np.floor(q0).astype(np.int64) - 1
            i1 = np.floor(q1).astype(np.int64) + 1
        else:
            i0 = np.minimum(np.maximum(np.floor(q0).astype(np.int64) - 1, 0), dims)
            i1 = np.minimum(np.maximum(np.floor(q1).astype(np.int64) + 1, -1), dims - 1)
        n = np.maximum(i1 - i0 + 1, 0)
        P["box_lo"] = i0
        P["box_n"] = n
        n_threads = np.where(n[:, 2] > 0, n[:, 0] * n[:, 1], 0)
        return P, n_threads

    def integrate_batch(
        self,
        images: np.ndarray,
        T_W_S: np.ndarray,
        pose_cov: np.ndarray | None = None,
        pose_sigmas: float = 2.0,
    ) -> None:
        """Fuse B pings into the map: the same map, bit for bit, as B calls of :meth:`integrate`.

        Every update is a minimum or a saturating count, so the order of the pings does not
        matter and the batch is exact for both rules. GPU backends upload the whole batch at
        once and fold it in a few launches (each thread owns its voxels and walks the pings:
        no atomics); CPU backends apply the pings one after the other. On demand, the blocks
        of all B pings are found (vectorised over the batch) and allocated first.

        Parameters
        ----------
        images : (B, n_bins, n_beams) uint8 (scaled by 1/255) or float32/float64 in [0, 1]
            Polar images, as :meth:`integrate` takes one.
        T_W_S : (B, 4, 4) float
            Sonar poses, metres.
        pose_cov : (6, 6) or (B, 6, 6) float, optional
            Pose uncertainty, one for every ping or one per ping (see :meth:`integrate`).
        pose_sigmas : float
            The bound's width in standard deviations (default 2).

        Every ping is checked, and every block allocated, before any is applied: on bad input
        it raises ``ValueError``/``TypeError`` saying which ping (or :class:`MapMemoryError`),
        and the map is left untouched.
        """
        imgs = self._check_images(images)
        B = imgs.shape[0]
        if isinstance(T_W_S, np.ma.MaskedArray):
            raise TypeError("Expected a plain array for 'T_W_S', but got a masked array (fill it first)")
        Ts = np.asarray(T_W_S)
        if Ts.shape != (B, 4, 4):
            raise ValueError(
                f"Expected T_W_S of shape ({B}, 4, 4) for {B} images, but got {Ts.shape}"
            )
        Ts = _check_poses(Ts)
        pads = np.zeros(B)
        if pose_cov is not None:
            C = pose_cov if isinstance(pose_cov, np.ma.MaskedArray) else np.asarray(pose_cov)
            shape = getattr(C, "shape", None)
            if shape == (B, 6, 6) and B:
                covs = [_check_pose_cov(C[b]) for b in range(B)]
                pads = np.array([self._pose_pad(c, pose_sigmas) for c in covs])
            elif shape == (6, 6):
                pads[:] = self._pose_pad(_check_pose_cov(C), pose_sigmas)
            else:
                raise ValueError(f"Expected pose_cov of shape (6, 6) or ({B}, 6, 6), but got {shape}")
        if B == 0:
            return
        with self._lock:
            if self._confirmed is not None:  # the layer follows the pings in order: one at a time
                self._empty = False
                for b in range(B):
                    params, n_threads = self._ping_params(Ts[b:b + 1], pads[b:b + 1])
                    self._backend.integrate(params[0, ...], imgs[b], self.method, int(n_threads[0]))
                    self._confirm(Ts[b], pads[b], imgs[b])
                    self.n_integrated += 1
                    self.pings.add(imgs[b], Ts[b])
                return
            params, n_threads = self._ping_params(Ts, pads)
            self._prepare(params, Ts, n_threads)
            self._empty = False
            self._backend.integrate_batch(params, imgs, self.method, n_threads)
            self.n_integrated += B
            self.pings.add_batch(imgs, Ts)

    def _check_images(self, images: object) -> np.ndarray:
        """(B, n_bins, n_beams) C-contiguous uint8 or float32 in [0, 1] (converted if needed)."""
        if not isinstance(images, np.ndarray):
            raise TypeError(f"Expected a numpy array for 'images', but got {type(images).__name__}")
        if isinstance(images, np.ma.MaskedArray):
            raise TypeError(
                "Expected a plain numpy array for 'images', but got a masked array: fill it first"
            )
        if images.ndim != 3 or images.shape[1:] != self.spec.image_shape:
            raise ValueError(
                f"Expected images of shape (B, {self.spec.image_shape[0]}, {self.spec.image_shape[1]}) "
                f"(pings, n_bins, n_beams) for 'images', but got {images.shape}"
            )
        if images.dtype == np.uint8:
            return np.ascontiguousarray(images)
        if images.dtype == np.float32 and images.flags.c_contiguous:
            if images.size == 0 or images.view(np.uint32).max() <= _ONE_BITS:  # see _check_image
                return images
        elif images.dtype not in (np.float32, np.float64):
            raise TypeError(f"Expected images of dtype float32 or uint8 for 'images', but got {images.dtype}")
        bad = ~np.isfinite(images)
        if bad.any():
            b, r, c = np.argwhere(bad)[0]
            raise ValueError(
                f"Expected finite intensities in 'images', but got {images[b, r, c]} at (ping {b}, bin {r}, "
                f"beam {c}) and {int(bad.sum()) - 1} more"
            )
        lo, hi = images.min(), images.max()
        if not (lo >= 0.0 and hi <= 1.0):
            b = int(np.argmax(((images < 0) | (images > 1)).reshape(images.shape[0], -1).any(1)))
            raise ValueError(
                f"Expected intensities in [0, 1] in 'images', but got range [{lo}, {hi}] (first at ping {b})"
            )
        out = np.empty(images.shape, np.float32)
        np.add(images, np.float32(0.0), out=out, casting="same_kind")  # -0.0 -> +0.0, float64 -> 32
        return out

    def _prepare(self, params: np.ndarray, Ts: np.ndarray, n_threads: np.ndarray) -> None:
        """On demand: give every block the pings (records ``params``, poses ``Ts``) may observe a
        voxel of a slot, before any of them is applied (raises with the map unchanged)."""
        if self.sparse is None:
            return
        live = n_threads > 0
        if not live.any():
            return
        lo = params["box_lo"][live].astype(np.int64)
        hi = lo + params["box_n"][live].astype(np.int64) - 1
        if self._dims is None:  # the kernels read the index over the whole box
            self._ensure_index(lo.min(axis=0) // self.B, hi.max(axis=0) // self.B)
        Tl = Ts[live]
        # the block test runs on the union box of a group of pings: small groups keep far-apart
        # pings from making it walk empty columns
        g = _CANDIDATE_GROUP
        lins = [self._candidate_lins(lo[i : i + g], hi[i : i + g], Tl[i : i + g])
                for i in range(0, len(Tl), g)]
        self._allocate(np.concatenate(lins), Tl[-1, :3, 3])

    def _candidate_lins(self, lo: np.ndarray, hi: np.ndarray, Ts: np.ndarray) -> np.ndarray:
        """Index entries (int64, into the flattened coarse index; repeats across pings) of the
        blocks that may hold a voxel centre one of the pings observes: per block column of a
        ping's voxel box (``lo``..``hi``, (P, 3) each), the z-range that its field of view's
        range sphere, azimuth half-planes, elevation slab and ``x > 0`` allow anywhere in the
        column (float64, padded against float32 rounding), as blocks. Vectorised over the P
        pings on the block columns of their union box. The index must cover every box."""
        B, s = self.B, self._voxel
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
        self._backend.set_index(new, new_lo * self._bs)

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
        """Free blocks that no ping has observed a voxel of (allocated by the conservative test);
        a bounded box keeps all of its blocks."""
        if self.sparse is None:
            return
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
        c = self._origin + (self._coords[cand] + 0.5) * self._bs * self._voxel
        d = np.linalg.norm(c - sonar_t, axis=1)
        self._free_slots(cand[np.argsort(-d, kind="stable")[:n]])

    def synchronize(self) -> None:
        """Wait until every ping handed to :meth:`integrate` is in the map (GPU backends run async)."""
        with self._lock:
            self._backend.synchronize()

    def check(self) -> None:
        """Raise ``RuntimeError`` if a kernel found an observed voxel without a block (a bug:
        the host's block test must be conservative)."""
        with self._lock:
            if self._backend.read_err():
                raise RuntimeError(
                    "gpumap: an observed voxel had no block (non-conservative block test)"
                )

    # ------------------------------------------------------------------ reading
    def _settle(self) -> None:
        """Before a read: raise on a kernel error, free blocks no ping has observed."""
        self.check()
        self._reclaim()

    def _blocks(self, values: bool = True, seen_only: bool = False
                ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """Used blocks' coords (n, 3) int64 (lexicographic order) and their (n, B B Bz) arrays:
        ``min_all``, ``values`` (unless ``values`` is False) and for the visible rule ``bright``
        and ``count``. ``seen_only``: only the blocks that hold something (observed, merged or
        loaded: the seen flag), read block by block."""
        self.check()
        keep = self._used & self._holding(np.arange(len(self._used))) if seen_only else self._used
        if self.sparse is None and keep.all():  # every block, slot = index entry: the pool as it is
            coords = self._coords
            arrays = [None if a is None else a.reshape(-1, self.BV) for a in self._backend.read()]
        else:
            slots = np.flatnonzero(keep)
            coords = self._coords[slots]
            if self.sparse is not None:  # slot order is coordinate order only for a bounded box
                order = np.lexsort((coords[:, 2], coords[:, 1], coords[:, 0]))
                slots, coords = slots[order], coords[order]
            arrays = self._backend.read_blocks(slots)
        out = dict(zip(("min_all", "bright", "count"), arrays, strict=True))
        if not self._stateful:
            del out["bright"], out["count"]
        if self._stateful and values:
            out["values"] = self._rule_values(out["min_all"], out["bright"], out["count"])
        elif values:
            out["values"] = out["min_all"]
        return coords, out

    def _holding(self, slots: np.ndarray) -> np.ndarray:
        """(n,) bool: which of ``slots`` hold something (an observed, merged or loaded voxel: the
        seen flag, set by every kernel, merge and load)."""
        return self._backend.read_seen()[slots] != 0

    def _whole_box(self) -> tuple[np.ndarray, np.ndarray]:
        if self._dims is not None:
            return np.zeros(3, np.int64), self._dims - 1
        used = np.flatnonzero(self._used)
        if len(used) == 0:
            return np.zeros(3, np.int64), np.zeros(3, np.int64)
        c = self._coords[used]
        return c.min(axis=0) * self._bs, (c.max(axis=0) + 1) * self._bs - 1

    def _box_grid(self, i0: np.ndarray, i1: np.ndarray) -> GridSpec:
        s = self._voxel
        return GridSpec(tuple(self._origin + i0 * s), tuple(self._origin + (i1 + 1) * s), s)

    def _dense(self, i0: np.ndarray, i1: np.ndarray, names: tuple[str, ...],
               blocks: tuple | None = None) -> dict[str, np.ndarray]:
        """Arrays over voxel indices i0..i1 (inclusive): +inf / 0 where no block (``blocks``:
        :meth:`_blocks`' result, read here if None)."""
        shape = tuple(int(x) for x in i1 - i0 + 1)
        if min(shape) <= 0:
            return {n: np.zeros((0, 0, 0), np.uint64 if n == "count" else np.float32) for n in names}
        if int(np.prod(shape)) > _MAX_BOX_VOXELS:
            raise ValueError(f"Expected a box of at most {_MAX_BOX_VOXELS} voxels, but got {shape}")
        coords, data = self._blocks() if blocks is None else blocks
        B, Bz, bs = self.B, self.Bz, self._bs
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

    def _to_pool_order(self, a: np.ndarray, fill) -> np.ndarray:
        """A bounded box's (nx, ny, nz) array as (n_blocks, B B Bz) in slot order (``fill`` past the box)."""
        B, Bz = self.B, self.Bz
        nb = self._index.shape
        V = np.full((nb[0] * B, nb[1] * B, nb[2] * Bz), fill, a.dtype)
        V[: a.shape[0], : a.shape[1], : a.shape[2]] = a
        return np.ascontiguousarray(
            V.reshape(nb[0], B, nb[1], B, nb[2], Bz).transpose(0, 2, 4, 1, 3, 5)).reshape(-1, self.BV)

    def raw_values(self) -> np.ndarray:
        """(nx, ny, nz) float32 copy of the map values over :attr:`grid`, ``+inf`` = never observed."""
        with self._lock:
            self._settle()
            return self._dense(*self._whole_box(), ("values",))["values"]

    def values(self) -> np.ndarray:
        """(nx, ny, nz) float32 copy over :attr:`grid`, ``NaN`` = never observed, else in [0, 1]."""
        v = self.raw_values()
        v[np.isinf(v)] = np.nan
        return v

    def evidence(self) -> dict[str, np.ndarray]:
        """The visible or evidence rule's per-voxel state over :attr:`grid`, (nx, ny, nz) copies:
        ``min_all`` float32 (min over every view, ``+inf`` never observed), ``bright`` float32
        (min over bright views, ``+inf`` none), ``count`` uint32 (clear dark views; the visible
        rule's weighted and stopping at 255) and ``hits`` uint32 (bright views). Raises for the
        plain rule."""
        from gpumap.reference import split_counts

        if not self._stateful:
            raise ValueError(
                "Expected a mapper with rule='visible' or 'evidence' for evidence(), "
                f"but its rule is {self.rule!r}"
            )
        with self._lock:
            self._settle()
            out = self._dense(*self._whole_box(), ("min_all", "bright", "count"))
        out["count"], out["hits"] = split_counts(out["count"])
        return out

    def observed(self) -> np.ndarray:
        """(nx, ny, nz) bool over :attr:`grid`: voxels seen by at least one ping."""
        return np.isfinite(self.raw_values())

    def values_in_box(self, lo_m, hi_m) -> tuple[GridSpec, np.ndarray]:
        """Values of the voxels whose centres lie in the world box ``[lo_m, hi_m]`` (metres).

        Returns the box's :class:`GridSpec` (its voxels are the map's) and its (nx, ny, nz)
        float32 values, ``NaN`` = never observed."""
        lo, hi = np.asarray(_vec3(lo_m, "lo_m")), np.asarray(_vec3(hi_m, "hi_m"))
        if np.any(hi < lo):
            raise ValueError(f"Expected hi_m >= lo_m on every axis, but got {lo.tolist()} and {hi.tolist()}")
        s = self._voxel
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
        in the grid's order (x index, then y, then z); with ``center_m`` ((3,) point, or a
        (4, 4) pose whose position is taken) and ``radius_m``, only those within that distance."""
        thr = np.float32(check_finite_scalar(threshold, "threshold"))
        with self._lock:
            self._settle()
            coords, data = self._blocks()
        bs, s = self._bs, self._voxel
        c = None
        if center_m is not None or radius_m is not None:
            if center_m is None or radius_m is None:
                raise ValueError("Expected center_m and radius_m together, or neither")
            a = np.asarray(center_m, np.float64)
            c = np.asarray(check_pose(a, "center_m")[:3, 3] if a.shape == (4, 4) else _vec3(a, "center_m"))
            r = check_finite_scalar(radius_m, "radius_m")
            if r < 0:
                raise ValueError(f"Expected radius_m >= 0, but got {r}")
            mid = self._origin + (coords + 0.5) * bs * s
            near = np.linalg.norm(mid - c, axis=1) <= r + float(np.linalg.norm(bs)) / 2 * s
            coords, vals = coords[near], data["values"][near]
        else:
            vals = data["values"]
        blk, loc = np.nonzero(np.isfinite(vals) & (vals >= thr))
        idx = coords[blk] * bs + _local(self.B, self.Bz)[loc]
        idx = idx[np.lexsort((idx[:, 2], idx[:, 1], idx[:, 0]))]
        pts = self._origin + (idx + 0.5) * s
        if c is not None:
            pts = pts[np.linalg.norm(pts - c, axis=1) <= r]
        return pts

    def memory_stats(self) -> dict:
        """Blocks and bytes (on demand, never-observed blocks are freed first).

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
                "block_size": self.B if self.Bz == self.B else [self.B, self.B, self.Bz],
                "observed_voxels": n_obs,
                "bytes_per_voxel": bpv,
                "block_bytes": n * self.BV * bpv,
                "observed_bytes": n_obs * bpv,
                "block_over_observed": (n * self.BV / n_obs) if n_obs else None,
                "pool_blocks": cap,
                "pool_bytes": cap * self._block_bytes,
                "index_bytes": int(self._index.nbytes),
                "total_bytes": cap * self._block_bytes + int(self._index.nbytes),
                "dense_bytes": dense,
            }

    # ------------------------------------------------------------------ confidence and view gain
    def _need_confidence(self, what: str) -> None:
        if self.sparse is not None:
            raise NotImplementedError(
                f"Expected a gpumap.MinMaxMapper on a GridSpec with confidence=True for {what}(); a map that "
                "allocates blocks on demand has no confidence layer yet"
            )
        if self._confirmed is None:
            raise ValueError(f"Expected a mapper made with confidence=True for {what}(), but it has none")

    def _confirm(self, T: np.ndarray, pad: float, img: np.ndarray) -> None:
        """The confidence pass of one ping, after its update (see :mod:`gpumap.confidence`)."""
        from gpumap.confidence import APERTURE_MARGIN, TUBE_VOXELS, confirm_ping
        from gpumap.geometry import beam_tan_edges

        if img.dtype == np.uint8:
            from gpumap.backends import U8_SCALE

            img = img.astype(np.float32) * U8_SCALE
        if not hasattr(self, "_conf_static"):
            sp = self.spec
            half = min(0.5 * sp.vfov_rad * (1.0 + APERTURE_MARGIN), 0.49 * np.pi)
            wide = SonarSpec(sp.range_min_m, sp.range_max_m, sp.n_bins, sp.bearings_rad, 2.0 * half)
            self._conf_static = (beam_tan_edges(sp), half, wide.fov_corners_S())
        edges, half, pts = self._conf_static
        keep = self._fov_pts_S
        self._fov_pts_S = pts  # the box that holds the rivals (the widened aperture)
        try:
            params, _ = self._ping_params(T[None], np.array([pad]))
        finally:
            self._fov_pts_S = keep
        values = self.raw_values().ravel()
        flat = confirm_ping(params[0], img, edges, values, half, TUBE_VOXELS * self.grid.voxel_size_m,
                            self._arcs)
        self._confirmed[flat] = 1

    def confidence(self) -> np.ndarray:
        """(nx, ny, nz) uint8 state of each voxel: 0 unknown, 1 free, 2 occupied and unconfirmed
        (only consistent with the pings: the elevation stretch lives here), 3 occupied and
        confirmed (some view resolved it in elevation; see :mod:`gpumap.confidence` for the exact
        rule). Occupied means a value ``>= threshold``; confidence never changes a value, so it
        never turns an occupied voxel free. Needs ``confidence=True``."""
        self._need_confidence("confidence")
        with self._lock:
            v = self.raw_values().ravel()
            conf = self._confirmed.copy()
        out = np.where(np.isinf(v), 0, np.where(v < np.float32(self.threshold), 1, 2)).astype(np.uint8)
        out[(out == 2) & (conf == 1)] = 3
        return out.reshape(self.grid.shape)

    def view_gain(self, T_W_S_candidates: np.ndarray, unknown_weight: float = 1.0) -> np.ndarray:
        """(K,) float64 gain of each candidate sonar pose ((K, 4, 4) float), from the map alone.

        ``gain = settle + unknown_weight * unknown``: ``settle`` counts the unconfirmed occupied
        voxels the candidate observes along an elevation arc that could settle them: both
        neighbours along the arc known free (a bright echo would confirm them, a dark clear view
        carve them), or, next to free space, an arc direction no ping has observed them along;
        ``unknown`` the never-observed voxels in blocks of 4^3 whose centre it observes (exact
        rules in :mod:`gpumap.nbv`).
        Runs on the mapper's backend; every backend gives the NumPy reference's gains exactly.
        Needs ``confidence=True``. Raises on bad poses, with the map unchanged.
        """
        from gpumap.nbv import GainRunner, _fov, gain_points, poses_to_rows

        self._need_confidence("view_gain")
        w = check_finite_scalar(unknown_weight, "unknown_weight")
        if w < 0:
            raise ValueError(f"Expected unknown_weight >= 0, but got {w}")
        if isinstance(T_W_S_candidates, np.ma.MaskedArray):
            raise TypeError("Expected a plain array for 'T_W_S_candidates', but got a masked array")
        Ts = np.asarray(T_W_S_candidates)
        if Ts.ndim != 3 or Ts.shape[1:] != (4, 4):
            raise ValueError(f"Expected T_W_S_candidates of shape (K, 4, 4), but got {Ts.shape}")
        Ts = _check_poses(Ts)
        with self._lock:
            pts = gain_points(self.raw_values(), self._confirmed.reshape(self.grid.shape) == 1,
                              self.threshold, self.grid, self._arcs)
            if self._gain_runner is None:
                self._gain_runner = GainRunner(self._backend)
            settle, unknown = self._gain_runner(poses_to_rows(Ts), pts, _fov(self._params))
        return settle.astype(np.float64) + w * unknown.astype(np.float64)

    # ------------------------------------------------------------------ reset, merge
    def reset(self) -> None:
        """Forget every ping: all voxels unknown again (on demand: no blocks; the pool keeps its size)."""
        with self._lock:
            if self._confirmed is not None:
                self._confirmed[:] = 0
                self._arcs[:] = 0
            if self.sparse is None:  # every block back to never observed, the index unchanged
                slots = np.arange(self._backend.cap, dtype=np.int32)
                self._backend.set_blocks(slots, slots)
            else:
                self._free_slots(np.flatnonzero(self._used))
            self.n_integrated = 0
            self.pings.clear()
            self._empty = True

    def merge(self, other) -> None:
        """Add the pings of ``other`` (a map of the same grid and options built from other pings:
        a mapper, a :class:`gpumap.merge.MapState` or a map file) to this map, in place; the result
        equals one mapper that integrated all of them, bit for bit (:mod:`gpumap.merge`). Never
        evicts: past ``max_bytes`` it raises :class:`MapMemoryError` with the map unchanged."""
        from gpumap.merge import merge_into

        merge_into(self, other)

    def _put_blocks(self, coords: np.ndarray, arrays: dict, combine: bool) -> None:
        """Blocks ``coords`` ((n, 3) int64, distinct, inside the bounds) take ``arrays``
        (``min_all`` and for the visible rule ``bright``, ``count``: (n, B B Bz) each), merged with
        what they hold when ``combine`` (:func:`gpumap.merge._combine_into`). Allocates missing
        blocks (never evicts); raises :class:`MapMemoryError` past ``max_bytes``, unchanged."""
        from gpumap.merge import _combine_into

        if not len(coords):
            return
        self.synchronize()
        self._settle()
        if self._dims is None:  # an unbounded map's index must span the blocks
            self._ensure_index(coords.min(axis=0), coords.max(axis=0))
        lins = self._lins(coords)
        flat = self._index.reshape(-1)
        new = flat[lins] < 0
        n_new = int(new.sum())
        short = n_new - len(self._free)
        if short > 0:
            cap = self._backend.cap + short
            if self.max_bytes is not None:
                need = cap * self._block_bytes + self._index.nbytes
                if need > self.max_bytes:
                    raise MapMemoryError(
                        f"Expected the map to stay under max_bytes={self.max_bytes}, but it needs {cap} "
                        f"blocks of {self._block_bytes} bytes plus a {self._index.nbytes}-byte index "
                        f"({need} bytes); the map is unchanged (merge never evicts)"
                    )
            self._grow_to(cap)
        if n_new:
            k = len(self._free) - n_new
            slots_new = self._free[k:][::-1]
            self._free = self._free[:k]
            flat[lins[new]] = slots_new
            self._coords[slots_new] = coords[new]
            self._used[slots_new] = True
            self._backend.set_blocks(slots_new.astype(np.int32), lins[new].astype(np.int32))
        slots = flat[lins].astype(np.int64)
        names = ("min_all", "bright", "count") if self._stateful else ("min_all",)
        mine = {k: arrays[k] for k in names}
        if combine and n_new < len(coords):
            # only blocks that already hold something are read and combined (a block never observed,
            # merged or loaded has seen 0); the others take the arrays as they are
            held = self._holding(slots)
            if held.any():
                part = dict(zip(("min_all", "bright", "count"), self._backend.read_blocks(slots[held]),
                                strict=True))
                part = {k: part[k] for k in names}
                _combine_into(part, {k: v[held] for k, v in mine.items()}, self.rule)
                self._backend.write_blocks(slots[held], part["min_all"], part.get("bright"),
                                           part.get("count"))
                slots, mine = slots[~held], {k: v[~held] for k, v in mine.items()}
        self._backend.write_blocks(slots, mine["min_all"], mine.get("bright"), mine.get("count"))
        self._empty = False

    # ------------------------------------------------------------------ persistence
    def save(self, path: str | os.PathLike) -> Path:
        """Write the map to ``path`` (.npz), atomically: a crash leaves the old file intact.

        Lossless, in blocks (format version 4, for every storage): ``blocks`` (n, 3) int32 block
        coordinates (lexicographic; only blocks with an observed voxel), ``values`` (n, B, B, Bz)
        float32, the map as :meth:`raw_values` gives it (``+inf`` unknown); for the visible rule
        its state (``min_all`` and ``bright`` float32, ``count`` uint8); with the confidence
        layer ``confirmed`` uint8 and ``arcs`` uint16; ``meta`` (JSON): the sonar spec, the
        ``grid`` (a bounded box) or the ``sparse`` spec (on demand), the method, rule,
        threshold, carve_views, shadow_m and the ping count, under a format name and version
        checked by :meth:`load`; ``pings`` (n,) uint64, the pings' fingerprints (:mod:`gpumap.pings`).
        """
        path = Path(path)
        if path.suffix != ".npz":
            path = path.with_suffix(path.suffix + ".npz") if path.suffix else path.with_suffix(".npz")
        B, Bz = self.B, self.Bz
        with self._lock:  # one consistent snapshot, even while other threads integrate
            self.synchronize()
            self._settle()
            coords, data = self._blocks()
            keep = np.isfinite(data["min_all"]).any(axis=1)
            arrays = {"blocks": coords[keep].astype(np.int32), "values": data["values"][keep]}
            if self._stateful:
                arrays.update({k: data[k][keep] for k in ("min_all", "bright", "count")})
            if self._confirmed is not None:
                shape = self.grid.shape
                arrays["confirmed"] = self._to_pool_order(self._confirmed.reshape(shape), 0)[keep]
                arrays["arcs"] = self._to_pool_order(self._arcs.reshape(shape), 0)[keep]
            n_integrated = self.n_integrated
            arrays["pings"] = self.pings.array()
        arrays = {k: v if k in ("blocks", "pings") else v.reshape(-1, B, B, Bz) for k, v in arrays.items()}
        meta = {
            "format": FILE_FORMAT,
            "version": FILE_VERSION,
            "spec": self.spec.to_dict(),
            "grid": self.grid.to_dict() if self.sparse is None else None,
            "sparse": None if self.sparse is None else self.sparse.to_dict(),
            "block": [B, B, Bz],
            "method": self.method,
            "shadow_m": self.shadow_m,
            "rule": self.rule,
            "threshold": self.threshold,
            "carve_views": self.carve_views,
            "bright_share": self.bright_share,
            "share_z": self.share_z,
            "n_integrated": n_integrated,
            "backend": self.backend,
            "confidence": self._confirmed is not None,
        }
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_write(path) as f:
            np.savez_compressed(f, **arrays, meta=np.array(json.dumps(meta)))
        return path

    @classmethod
    def load(cls, path: str | os.PathLike, backend: str = "auto", **kw) -> MinMaxMapper:
        """Read a map written by :meth:`save` (any version, and the former
        ``SparseMinMaxMapper.save``) onto ``backend``; ``kw``: ``max_bytes``, ``evict`` for a
        map on demand.

        Checked before anything large is read or allocated: the metadata (format, version,
        every field's type and range), each array's declared shape and dtype, and each
        member's declared size against what its compressed bytes can hold (deflate inflates at
        most ~1,000 : 1), so a small file cannot make it allocate gigabytes. Then the blocks
        (unique, inside the bounds, each with an observed voxel) and the values: finite in
        [0, 1] or ``+inf`` (never observed), and for the visible rule consistent with its
        state. Raises :class:`~gpumap.errors.FormatError` (a ``ValueError``;
        :class:`~gpumap.errors.LimitError` when the map would not fit in memory) saying what
        was expected and what came.
        """
        path = Path(path)
        try:
            with zipfile.ZipFile(path) as zf:
                members = {i.filename: i for i in zf.infolist()}
                if "meta.npy" not in members or not {"values.npy", "blocks.npy"} & set(members):
                    raise FormatError(
                        f"Expected a gpumap map file with 'meta' and 'blocks' (or 'meta' and 'values', "
                        f"versions 1 to 3), but {path} has "
                        f"{sorted(n.removesuffix('.npy') for n in members)}"
                    )
                headers = {
                    n: _npy_header(zf, info, path) for n, info in members.items() if n.endswith(".npy")
                }
                if members["meta.npy"].file_size > _META_MAX_BYTES:
                    raise FormatError(
                        f"Expected map metadata under {_META_MAX_BYTES} bytes in {path}, "
                        f"but it declares {members['meta.npy'].file_size}"
                    )
                with zf.open("meta.npy") as f:
                    meta = json.loads(str(np.lib.format.read_array(f, allow_pickle=False)))
                spec, space, opts, n_integrated, dense_file = _check_meta(meta, path)
                # before version 5 'count' was the visible rule's uint8 dark count
                count_dt = np.uint64 if meta.get("version") == FILE_VERSION else np.uint8
                prints = read_prints(zf, members, headers, n_integrated, path)
                if cls._on_demand and not isinstance(space, SparseSpec):
                    raise FormatError(f"Expected a sparse map file (blocks on demand) for {cls.__name__}, "
                                      f"but {path} holds a map of a bounded grid: load it with MinMaxMapper")
                names = ("values", "min_all", "bright", "count") if opts["rule"] != "plain" else ("values",)
                if opts["confidence"]:
                    names = (*names, "confirmed", "arcs")
                if dense_file:  # versions 1 to 3: arrays over the grid
                    n_blocks, shape = None, space.shape
                else:
                    bshape, bdt = headers.get("blocks.npy", (None, None))
                    if bshape is None or len(bshape) != 2 or bshape[1] != 3 or bdt != np.dtype(np.int32):
                        raise FormatError(
                            f"Expected 'blocks' of shape (n, 3) int32 in {path}, but got "
                            f"{'nothing' if bshape is None else f'{bshape} {bdt}'}"
                        )
                    if isinstance(space, SparseSpec):
                        B, Bz = space.block, space.block
                    else:  # as a mapper of this grid lays its blocks out
                        B, Bz = BLOCK, int(space.shape[2])
                    if meta.get("block", [B, B, Bz]) != [B, B, Bz]:
                        raise FormatError(f"Expected blocks of {[B, B, Bz]} voxels in {path}, but its "
                                          f"metadata says {meta.get('block')!r}")
                    n_blocks = bshape[0]
                    shape = (n_blocks, B, B, Bz)
                for name in names:
                    dt = {"count": count_dt, "confirmed": np.uint8, "arcs": np.uint16}.get(name, np.float32)
                    got, dtype = headers.get(f"{name}.npy", (None, None))
                    if got != shape or dtype != np.dtype(dt):
                        raise FormatError(
                            f"Expected '{name}' of shape {shape} {np.dtype(dt)} in {path}, "
                            f"but got {'nothing' if got is None else f'{got} {dtype}'}"
                        )
                size = {"count": 8, "confirmed": 1, "arcs": 2}
                need = sum(int(np.prod(shape)) * size.get(n, 4) for n in names)
                free = _free_memory_bytes("numpy")
                if free is not None and 2 * need > free:
                    raise LimitError(
                        f"Expected a map that fits in memory, but {path} holds {need / 2**30:.2f} GiB "
                        f"(twice that while loading) and {free / 2**30:.2f} GiB are free"
                    )
                arrays = {}
                for name in (*names, *(() if dense_file else ("blocks",))):
                    with zf.open(f"{name}.npy") as f:
                        arrays[name] = np.lib.format.read_array(f, allow_pickle=False)
                if "count" in arrays:  # the packed view counts (an old file's dark count, no bright count)
                    arrays["count"] = arrays["count"].astype(np.uint64)
        except (OSError, EOFError, zipfile.BadZipFile, json.JSONDecodeError, UnicodeDecodeError,
                zlib.error, tokenize.TokenError, SyntaxError, NotImplementedError, struct.error) as e:
            # damaged deflate data, a damaged .npy header dict, an unknown zip compression
            raise FormatError(
                f"Expected a gpumap map file (.npz) at {path}, but it cannot be read "
                f"({type(e).__name__}: {e})"
            ) from e
        if dense_file:
            _check_map_values(arrays, opts, path)
            m = cls(spec, space, backend=backend, **opts, **kw)
            pool = {k: m._to_pool_order(arrays[k], 0 if k == "count" else np.inf).ravel()
                    for k in (("min_all", "bright", "count") if opts["rule"] != "plain" else ("values",))}
            with m._lock:
                grid = pool["min_all"] if opts["rule"] != "plain" else pool["values"]
                m._backend.write(grid, pool.get("bright"), pool.get("count"))
                m._backend._write_seen(np.ones(m._backend.cap, np.uint8))  # merges combine with them
                m._empty = False
                if opts["confidence"]:
                    m._confirmed[:] = arrays["confirmed"].ravel()
                    m._arcs[:] = arrays["arcs"].ravel()
                m.n_integrated = n_integrated
                m.pings = prints
            return m
        coords = arrays.pop("blocks").astype(np.int64)
        n = len(coords)
        bs = np.array([B, B, Bz], np.int64)
        flat = {k: v.reshape(n, B * B * Bz) for k, v in arrays.items()}
        _check_map_values(flat, opts, path)
        if n and len(np.unique(coords, axis=0)) != n:
            raise FormatError(f"Expected each block once in {path}, but some repeat")
        if np.abs(coords).max(initial=0) * max(B, Bz) > _MAX_VOXEL_INDEX - 2 * max(B, Bz):
            raise FormatError(f"Expected block coordinates within +-{_MAX_VOXEL_INDEX // B - 2} in {path}")
        obs = np.isfinite(flat["min_all" if opts["rule"] != "plain" else "values"])
        if not obs.any(axis=1).all():
            raise FormatError(f"Expected every block in {path} to hold an observed voxel, but some hold none")
        dims = space.shape
        if dims is not None and n:
            idx = coords[:, None, :] * bs + _local(B, Bz)[None]
            outside = np.any((idx < 0) | (idx >= np.asarray(dims)), axis=2)
            if np.any(outside & obs) or np.any(coords < 0) or np.any(coords * bs >= np.asarray(dims)):
                raise FormatError(
                    f"Expected observed voxels only inside the bounds in {path}, but some lie outside"
                )
        if isinstance(space, SparseSpec):
            kw = {"initial_blocks": max(1, n), **kw}
        m = cls(spec, space, backend=backend, **opts, **kw)
        src = {"min_all": flat["min_all" if opts["rule"] != "plain" else "values"]}
        if opts["rule"] != "plain":
            src["bright"], src["count"] = flat["bright"], flat["count"]
        with m._lock:
            m._put_blocks(coords, src, combine=False)
            if opts["confidence"]:  # host arrays over the grid, from the file's blocks
                layer = m._dense(*m._whole_box(), ("confirmed", "arcs"), blocks=(coords, flat))
                m._confirmed[:] = layer["confirmed"].ravel()
                m._arcs[:] = layer["arcs"].ravel()
            m.n_integrated = n_integrated
            m.pings = prints
        return m


# Map metadata is a small JSON document; anything larger is not one of ours.
_META_MAX_BYTES = 1 << 20
# deflate's largest expansion is about 1032 : 1; a member that claims more is a bomb.
_DEFLATE_MAX_RATIO = 1100


def _npy_header(zf: zipfile.ZipFile, info: zipfile.ZipInfo, path: Path) -> tuple[tuple, np.dtype]:
    """(shape, dtype) of one .npy member from its header, checked against its sizes."""
    with zf.open(info) as f:
        version = np.lib.format.read_magic(f)
        if version == (1, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_1_0(f)
        elif version in ((2, 0), (3, 0)):
            shape, fortran, dtype = np.lib.format.read_array_header_2_0(f)
        else:
            raise FormatError(f"Expected .npy version 1-3 for {info.filename} in {path}, but got {version}")
        header_bytes = f.tell()
    data_bytes = -1 if dtype.hasobject else int(np.prod(shape, dtype=object)) * dtype.itemsize
    if data_bytes < 0 or fortran or info.file_size != header_bytes + data_bytes:
        raise FormatError(
            f"Expected {info.filename} in {path} to hold its declared {shape} {dtype} array "
            f"({header_bytes + max(data_bytes, 0)} bytes, C order), but the archive says {info.file_size}"
        )
    bomb = info.file_size > _DEFLATE_MAX_RATIO * info.compress_size + 4096
    if info.compress_type != zipfile.ZIP_STORED and bomb:
        raise FormatError(
            f"Expected {info.filename} in {path} to inflate at most {_DEFLATE_MAX_RATIO}:1, but it declares "
            f"{info.file_size} bytes from {info.compress_size}: refused before inflating"
        )
    return tuple(shape), dtype


def _check_meta(meta: object, path: Path) -> tuple[SonarSpec, GridSpec | SparseSpec, dict, int, bool]:
    """The sonar spec, the grid (a GridSpec, or a SparseSpec for a map on demand), the constructor
    options, the ping count of a map file's metadata, and whether it holds dense arrays over the
    grid (versions 1 to 3) rather than blocks."""
    if not isinstance(meta, dict):
        raise FormatError(f"Expected a JSON object as map metadata in {path}, but got {type(meta).__name__}")
    fmt, version = meta.get("format"), meta.get("version")
    if fmt not in (FILE_FORMAT, SPARSE_FILE_FORMAT):
        raise FormatError(f"Expected format {FILE_FORMAT!r} in {path}, but got {fmt!r}")
    if (fmt == FILE_FORMAT and version not in (1, 2, 3, 4, FILE_VERSION)) or (
            fmt == SPARSE_FILE_FORMAT and version != 1):
        raise FormatError(
            f"Expected file version 1 to {FILE_VERSION} in {path} ({fmt}), but got {version!r}"
        )
    sparse_file = fmt == SPARSE_FILE_FORMAT or (
        version in (4, FILE_VERSION) and meta.get("sparse") is not None)
    try:
        spec = SonarSpec.from_dict(meta["spec"])
        space = SparseSpec.from_dict(meta["sparse"]) if sparse_file else GridSpec.from_dict(meta["grid"])
    except (KeyError, TypeError, ValueError, OverflowError, IndexError) as e:
        raise FormatError(
            f"Expected a sonar spec and a grid spec (a sparse spec on demand) in the metadata of {path}, "
            f"but: {e!r}"
        ) from e
    n = meta.get("n_integrated")
    if isinstance(n, bool) or not isinstance(n, int) or n < 0:
        raise FormatError(f"Expected a non-negative integer n_integrated in {path}, but got {n!r}")
    rule = meta.get("rule", "plain")  # version 1 maps are plain min-max
    opts = {
        "method": meta.get("method"),
        "shadow_m": meta.get("shadow_m", 0.0),
        "rule": rule,
        "threshold": meta.get("threshold", 0.1),
        "carve_views": meta.get("carve_views", 2),
        "bright_share": meta.get("bright_share", BRIGHT_SHARE),
        "share_z": meta.get("share_z", SHARE_Z),
        "confidence": meta.get("confidence", False),  # versions 1 and 2 have no confidence layer
    }
    if opts["method"] not in METHODS or rule not in RULES or (sparse_file and opts["method"] != "gather"):
        raise FormatError(
            f"Expected method in {METHODS} ('gather' on demand) and rule in {RULES} in {path}, but got "
            f"{opts['method']!r} and {rule!r}"
        )
    if not isinstance(opts["confidence"], bool) or (sparse_file and opts["confidence"]):
        raise FormatError(f"Expected a bool for confidence (False on demand) in {path}, but got "
                          f"{opts['confidence']!r}")
    for key in ("shadow_m", "threshold"):
        if isinstance(opts[key], bool) or not isinstance(opts[key], (int, float)):
            raise FormatError(f"Expected a number for {key} in {path}, but got {opts[key]!r}")
    cv = opts["carve_views"]
    if isinstance(cv, bool) or not isinstance(cv, int) or not 1 <= cv <= 255:
        raise FormatError(f"Expected carve_views in 1..255 in {path}, but got {cv!r}")
    p, z = opts["bright_share"], opts["share_z"]
    if any(isinstance(x, bool) or not isinstance(x, (int, float)) for x in (p, z)) or not (
            0.0 < p <= 1.0 and 0.0 <= z <= 10.0):
        raise FormatError(f"Expected bright_share in (0, 1] and share_z in [0, 10] in {path}, but got "
                          f"{p!r} and {z!r}")
    return spec, space, opts, n, fmt == FILE_FORMAT and version not in (4, FILE_VERSION)


def _check_map_values(arrays: dict[str, np.ndarray], opts: dict, path: Path) -> None:
    """Values a map can hold: finite in [0, 1] or +inf; the visible rule's state consistent."""
    for name in ("values", "min_all", "bright"):
        if name not in arrays:
            continue
        a = arrays[name]
        fin = np.isfinite(a)
        bad = ~(fin | (a == np.inf)) | (fin & ((a < 0) | (a > 1)))
        if bad.any():
            i = np.unravel_index(int(np.argmax(bad)), a.shape)
            raise FormatError(
                f"Expected '{name}' in [0, 1] or +inf (never observed) in {path}, but got {a[i]} at "
                f"{tuple(int(x) for x in i)} and {int(bad.sum()) - 1} more"
            )
    if "confirmed" in arrays and np.any(arrays["confirmed"] > 1):
        raise FormatError(f"Expected 'confirmed' flags of 0 or 1 in {path}, but some are larger")
    if "arcs" in arrays and np.any(arrays["arcs"] >= 1 << 13):
        raise FormatError(f"Expected 13-bit 'arcs' masks in {path}, but some have higher bits")
    if opts["rule"] != "plain":
        unseen = np.isinf(arrays["min_all"])
        if np.any(unseen & (np.isfinite(arrays["bright"]) | (arrays["count"] > 0))):
            raise FormatError(f"Expected no evidence on never-observed voxels in {path}, but some have it")
        want = rule_values(opts["rule"], arrays["min_all"], arrays["bright"], arrays["count"],
                           opts["carve_views"], opts["bright_share"], opts["share_z"])
        if not np.array_equal(want, arrays["values"]):
            raise FormatError(f"Expected 'values' in {path} to follow from its state, but they disagree")
