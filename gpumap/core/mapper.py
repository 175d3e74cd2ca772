"""The min-max occupancy mapper: the public entry point of gpumap.

One :class:`MinMaxMapper` serves a fixed box and an open world, as a facade over parts that each
own one concern (and are tested alone):

- :mod:`gpumap.core.storage` (:class:`~gpumap.core.storage.BlockStorage`): the map's blocks of voxels on
  the backend's device and the coarse index that finds them: all blocks of a bounded box up
  front (a :class:`~gpumap.GridSpec`: no per-ping block search, the dense grid's speed), or on
  demand (a :class:`~gpumap.SparseSpec`, bounded or not, or ``sparse=True``: memory grows with
  what the sonar has seen, under ``max_bytes``); reads, writes and dense boxes.
- :mod:`gpumap.core.integrator` (:class:`~gpumap.core.integrator.Integrator`): a ping's checks and record,
  the blocks it may observe (on demand), the kernels' launches (:mod:`gpumap.backends`).
- :mod:`gpumap.core.rules`: how the per-voxel state reads as values (the rule and its read-time
  options) and how two states merge.
- :mod:`gpumap.core.params`: the options (:class:`~gpumap.core.params.MapperParams`) and the layer
  protocol (:meth:`MinMaxMapper.attach`): layers follow the map, the map never imports them.
- :mod:`gpumap.core.mapfile`: map files (:meth:`MinMaxMapper.save`, :meth:`MinMaxMapper.load`),
  every format version; :mod:`gpumap.core.mapstate` and :mod:`gpumap.core.merge`: merging maps.

Both storages give the same values, bit for bit, wherever both have voxels: the same per-voxel
code runs on the same voxel centres.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from gpumap.backends import BACKENDS
from gpumap.backends import available_backends as _available
from gpumap.core.integrator import Integrator, check_pose_cov
from gpumap.core.mapfile import FILE_FORMAT, FILE_VERSION, SPARSE_FILE_FORMAT  # noqa: F401 (see below)
from gpumap.core.mapfile import load as load_file
from gpumap.core.mapfile import save as save_file
from gpumap.core.mapstate import as_state, check_other, merge_state
from gpumap.core.params import MapperParams
from gpumap.core.rules import ValueRule, rule_values  # noqa: F401 (see below)
from gpumap.core.storage import BLOCK, GROWTH, BlockStorage, MapMemoryError, local_offsets  # noqa: F401 (see below)
from gpumap.errors import check_finite_scalar, check_pose
from gpumap.geometry import make_template_S
from gpumap.pings import PingPrints
from gpumap.spec import GridSpec, SonarSpec, SparseSpec, _vec3

# FILE_FORMAT, FILE_VERSION, SPARSE_FILE_FORMAT, BLOCK, GROWTH and rule_values, imported above, stay
# names of this module, as they were before the mapper's parts had modules of their own.
__all__ = ["MapMemoryError", "MinMaxMapper", "available_backends"]

log = logging.getLogger("gpumap")

_ANNOUNCED: set[tuple[str, str]] = set()  # the (backend, device) pairs "auto" has logged in this process


def available_backends() -> list[str]:
    """Backends that run on this machine, in the order ``backend="auto"`` tries them."""
    return _available()


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
    params : MapperParams or None
        Every other option, checked when made (:class:`gpumap.core.params.MapperParams`: method,
        rule, threshold, shadow_m, carve_views, bright_share, share_z, footprint_max, and for blocks
        on demand sparse, max_bytes, evict, initial_blocks); None: the defaults.
    device_index : int or None
        Which device of the backend's kind the map lives on (None: the first): ``warp-cuda``
        on ``cuda:<device_index>``, ``opencl-gpu``/``opencl-cpu`` on that OpenCL device of their
        kind (:func:`gpumap.backends.opencl_devices`); ``numpy`` and ``warp-cpu`` have 0 only. An
        index the backend does not have raises ``ValueError``; never another device. Mappers on
        several GPUs of one process: :mod:`gpumap.pipeline.gpu_threads`.

    Layers (confidence, view gain, surface estimate, distance field, a live view) follow the map
    through :meth:`attach`; the map never imports them.
    """

    _on_demand = False  # a subclass that only holds maps on demand (gpumap.core.sparse.SparseMinMaxMapper)

    def __init__(
        self,
        spec: SonarSpec,
        grid: GridSpec | SparseSpec,
        backend: str = "auto",
        params: MapperParams | None = None,
        *,
        device_index: int | None = None,
    ) -> None:
        if not isinstance(spec, SonarSpec):
            raise TypeError(f"Expected a gpumap.SonarSpec for 'spec', but got {type(spec).__name__}")
        params = MapperParams() if params is None else params
        if not isinstance(params, MapperParams):
            raise TypeError(f"Expected a gpumap.MapperParams for 'params', but got {type(params).__name__}")
        sparse, method = params.sparse, params.method
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
        if backend != "auto" and backend not in BACKENDS:
            raise ValueError(f"Expected backend to be 'auto' or one of {BACKENDS}, but got {backend!r}")
        if space is not None and method != "gather":
            raise ValueError(
                "Expected method='gather' on a map that allocates blocks on demand (the template method "
                f"needs a bounded GridSpec), but got method={method!r}"
            )
        if space is None and (params.max_bytes is not None or params.evict is not None):
            raise ValueError("Expected max_bytes and evict only with blocks on demand (a SparseSpec or "
                             "sparse=True): a GridSpec's blocks are all allocated up front")
        #: The options the map was made with (:class:`~gpumap.core.params.MapperParams`).
        self.params = params
        self.spec, self.sparse = spec, space
        self.method, self.rule, self.threshold, self.shadow_m = method, params.rule, params.threshold, \
            params.shadow_m
        #: The rule with its read-time options (:class:`~gpumap.core.rules.ValueRule`: checks them when set).
        self.value_rule = ValueRule(params.rule, params.carve_views, params.bright_share, params.share_z)
        self.max_bytes, self.evict = params.max_bytes, params.evict
        self.n_integrated = 0
        self.pings = PingPrints()  # a fingerprint per integrated ping (gpumap.pings)
        #: Attached layers (:meth:`attach`), in the order they were attached.
        self.layers: list = []
        #: Arrays a loaded map file kept for layers not attached yet, by layer name (:meth:`attach`).
        self.layer_state: dict[str, dict[str, np.ndarray]] = {}
        template = make_template_S(spec, grid.voxel_size_m) if method == "template" else None
        fm = params.footprint_max
        #: The map's blocks (:class:`~gpumap.core.storage.BlockStorage`), its backend and its lock.
        self.storage = BlockStorage(spec, grid if space is None else space, self.value_rule, backend,
                                    template=template, use_table=None if fm == "auto" else fm == "table",
                                    max_bytes=self.max_bytes, evict=self.evict,
                                    initial_blocks=params.initial_blocks, device_index=device_index)
        st = self.storage
        self.B, self.Bz, self.BV, self.bytes_per_voxel = st.B, st.Bz, st.BV, st.bytes_per_voxel
        #: What applies pings to the storage (:class:`~gpumap.core.integrator.Integrator`).
        self.integrator = Integrator(spec, st, method, template, params.shadow_m, params.rule,
                                     params.threshold)
        # auto says what it picked, once a process (a command makes several mappers); a backend asked
        # for by name is what the caller already knows
        said = (st.backend.name, st.backend.device)
        (log.info if backend == "auto" and said not in _ANNOUNCED else log.debug)(
            "gpumap: backend %s on %s", st.backend.name, st.backend.device)
        _ANNOUNCED.add(said)

    # ------------------------------------------------------------------ layers
    def attach(self, layer):
        """Let ``layer`` (:class:`~gpumap.core.params.Layer`) follow this map from now on; returns it.

        The layer's ``attached(mapper)`` checks that the map suits it (and takes what a loaded map
        file kept for it); then the mapper calls ``after_ping`` after each ping (a ``per_ping``
        layer: batches are then applied one ping at a time, the same map bit for bit) and
        ``after_batch`` after each :meth:`integrate` / :meth:`integrate_batch`, under the map's
        lock, and ``reset`` on :meth:`reset`. One layer of a name per map."""
        name = getattr(layer, "name", None)
        if not isinstance(name, str) or not isinstance(getattr(layer, "per_ping", None), bool):
            raise TypeError(f"Expected a layer with a str 'name' and a bool 'per_ping', but got "
                            f"{type(layer).__name__}")
        if any(x.name == name for x in self.layers):
            raise ValueError(f"Expected one layer named {name!r} on a map, but one is attached already")
        with self.storage.lock:
            hook = getattr(layer, "attached", None)
            if hook is not None:
                hook(self)
            self.layers.append(layer)
        return layer

    def detach(self, layer) -> None:
        """Stop ``layer`` following this map (it keeps what it has)."""
        with self.storage.lock:
            self.layers.remove(layer)

    def layer(self, name: str):
        """The attached layer named ``name``; ``KeyError`` saying which are attached if none is."""
        for x in self.layers:
            if x.name == name:
                return x
        raise KeyError(f"Expected a layer named {name!r} attached to this map, but it has "
                       f"{[x.name for x in self.layers] or 'none'}")

    def _after_batch(self, imgs: np.ndarray, Ts: np.ndarray) -> None:
        for x in self.layers:
            hook = getattr(x, "after_batch", None)
            if hook is not None:
                hook(self, imgs, Ts)

    # ------------------------------------------------------------------ properties
    @property
    def backend(self) -> str:
        """The backend in use, as ``gpumap info`` names it: ``"warp-cuda"``, ``"warp-cpu"``,
        ``"opencl-gpu"``, ``"opencl-cpu"`` or ``"numpy"`` (``"auto"`` and ``"opencl"`` resolve to one)."""
        return self.storage.backend.name

    @property
    def device(self) -> str:
        """The device the backend runs on, in words."""
        return self.storage.backend.device

    @property
    def carve_views(self) -> int:
        """Visible rule: clear dark views that carve a voxel once seen bright (see the class)."""
        return self.value_rule.carve_views

    @carve_views.setter
    def carve_views(self, n: int) -> None:
        self.value_rule.carve_views = n

    @property
    def bright_share(self) -> float:
        """Evidence rule: the share of bright views below which a voxel is free (see the class)."""
        return self.value_rule.bright_share

    @bright_share.setter
    def bright_share(self, p: float) -> None:
        self.value_rule.bright_share = p

    @property
    def share_z(self) -> float:
        """Evidence rule: the one-sided normal quantile of the confidence that frees a voxel."""
        return self.value_rule.share_z

    @share_z.setter
    def share_z(self, z: float) -> None:
        self.value_rule.share_z = z

    @property
    def grid(self) -> GridSpec:
        """The :class:`GridSpec` that :meth:`values` covers: the box, or for an unbounded map the
        box of its blocks (one voxel at the origin while empty)."""
        return self.storage.grid

    @property
    def _params(self) -> np.ndarray:
        """The static ping record (:attr:`gpumap.core.integrator.Integrator.params`; ``bench/nbv.py``
        reads it)."""
        return self.integrator.params

    # ------------------------------------------------------------------ update
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
        with self.storage.lock:  # the integrator's staging buffer is the mapper's own
            img = self.integrator.check_image(image)
            if pose_cov is not None:
                pads[0] = self.integrator.pose_pad(check_pose_cov(pose_cov), pose_sigmas)
            params = self.integrator.integrate(img, T, pads)
            self.n_integrated += 1  # under the lock
            self.pings.add(img, T)
            for x in self.layers:
                if x.per_ping:
                    x.after_ping(self, img, T, float(pads[0]), params)
            if self.layers:
                self._after_batch(img[None], T[None])

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
        imgs, Ts, pads = self.integrator.check_batch(images, T_W_S, pose_cov, pose_sigmas)
        B = imgs.shape[0]
        if B == 0:
            return
        with self.storage.lock:
            steps = [x for x in self.layers if x.per_ping]
            if steps:  # these layers follow the pings in order: one at a time
                for b in range(B):
                    params = self.integrator.integrate(imgs[b], Ts[b], pads[b : b + 1])
                    self.n_integrated += 1
                    self.pings.add(imgs[b], Ts[b])
                    for x in steps:
                        x.after_ping(self, imgs[b], Ts[b], float(pads[b]), params)
            else:
                self.integrator.integrate_batch(imgs, Ts, pads)
                self.n_integrated += B
                self.pings.add_batch(imgs, Ts)
            if self.layers:
                self._after_batch(imgs, Ts)

    def synchronize(self) -> None:
        """Wait until every ping handed to :meth:`integrate` is in the map (GPU backends run async)."""
        self.storage.synchronize()

    def check(self) -> None:
        """Raise ``RuntimeError`` if a kernel found an observed voxel without a block (a bug:
        the host's block test must be conservative)."""
        self.storage.check()

    # ------------------------------------------------------------------ reading
    def raw_values(self) -> np.ndarray:
        """(nx, ny, nz) float32 copy of the map values over :attr:`grid`, ``+inf`` = never observed."""
        st = self.storage
        with st.lock:
            st.settle()
            return st.dense(*st.whole_box(), ("values",))["values"]

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

        if self.rule == "plain":
            raise ValueError(
                "Expected a mapper with rule='visible' or 'evidence' for evidence(), "
                f"but its rule is {self.rule!r}"
            )
        st = self.storage
        with st.lock:
            st.settle()
            out = st.dense(*st.whole_box(), ("min_all", "bright", "count"))
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
        st = self.storage
        s = st.voxel
        i0 = np.ceil((lo - st.origin) / s - 0.5).astype(np.int64)
        i1 = np.floor((hi - st.origin) / s - 0.5).astype(np.int64)
        if st.dims is not None:
            i0, i1 = np.maximum(i0, 0), np.minimum(i1, st.dims - 1)
        if np.any(i1 < i0):
            raise ValueError(
                f"Expected a box holding at least one voxel centre, but {lo.tolist()}-{hi.tolist()} "
                "holds none (inside the bounds)"
            )
        with st.lock:
            st.settle()
            v = st.dense(i0, i1, ("values",))["values"]
        v[np.isinf(v)] = np.nan
        return st.box_grid(i0, i1), v

    def occupied_points(self, threshold: float, center_m=None, radius_m: float | None = None) -> np.ndarray:
        """(N, 3) float64 world centres (metres) of observed voxels with value >= ``threshold``,
        in the grid's order (x index, then y, then z); with ``center_m`` ((3,) point, or a
        (4, 4) pose whose position is taken) and ``radius_m``, only those within that distance."""
        thr = np.float32(check_finite_scalar(threshold, "threshold"))
        st = self.storage
        with st.lock:
            st.settle()
            coords, data = st.blocks()
        bs, s = st.bs, st.voxel
        c = None
        if center_m is not None or radius_m is not None:
            if center_m is None or radius_m is None:
                raise ValueError("Expected center_m and radius_m together, or neither")
            a = np.asarray(center_m, np.float64)
            c = np.asarray(check_pose(a, "center_m")[:3, 3] if a.shape == (4, 4) else _vec3(a, "center_m"))
            r = check_finite_scalar(radius_m, "radius_m")
            if r < 0:
                raise ValueError(f"Expected radius_m >= 0, but got {r}")
            mid = st.origin + (coords + 0.5) * bs * s
            near = np.linalg.norm(mid - c, axis=1) <= r + float(np.linalg.norm(bs)) / 2 * s
            coords, vals = coords[near], data["values"][near]
        else:
            vals = data["values"]
        blk, loc = np.nonzero(np.isfinite(vals) & (vals >= thr))
        idx = coords[blk] * bs + local_offsets(st.B, st.Bz)[loc]
        idx = idx[np.lexsort((idx[:, 2], idx[:, 1], idx[:, 0]))]
        pts = st.origin + (idx + 0.5) * s
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
        return self.storage.memory_stats()

    # ------------------------------------------------------------------ reset, merge
    def reset(self) -> None:
        """Forget every ping: all voxels unknown again (on demand: no blocks; the pool keeps its size)."""
        with self.storage.lock:
            for x in self.layers:
                hook = getattr(x, "reset", None)
                if hook is not None:
                    hook()
            self.storage.clear()
            self.n_integrated = 0
            self.pings.clear()

    def merge(self, other) -> None:
        """Add the pings of ``other`` (a map of the same grid and options built from other pings:
        a mapper, a :class:`gpumap.core.merge.MapState` or a map file) to this map, in place; the result
        equals one mapper that integrated all of them, bit for bit (:mod:`gpumap.core.merge`). Never
        evicts: past ``max_bytes`` it raises :class:`MapMemoryError` with the map unchanged."""
        check_other(self, other)
        merge_state(self, as_state(other, MinMaxMapper))

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
        return save_file(self, path)

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
        return load_file(cls, path, backend, kw, on_demand=cls._on_demand)
