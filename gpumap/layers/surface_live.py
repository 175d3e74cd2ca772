"""The surface layer of a live map: every (ping, voxel) worked out once (:class:`_Pairs`), updated per batch
(:class:`LiveSurface`), and the layer of a mapper (:func:`surface_from_mapper`); the oracle and the
method are in :mod:`gpumap.layers.surface`.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterable

import numpy as np

from gpumap.geometry import beam_tan_edges
from gpumap.layers.surface import (
    SurfaceLayer,
    SurfaceOptions,
    _bright_pairs,
    _check,
    _finish,
    _geometry,
    _in_sonar,
    _layer,
    _PingCells,
    _prepare,
    _scales,
    surface_from_evidence,
    surface_from_frames,
)
from gpumap.spec import GridSpec, SonarSpec

__all__ = ["LiveSurface", "map_candidates", "surface_from_mapper"]


class _Pairs:
    """Every kept ping's view of every voxel that has ever been a candidate, each (ping, voxel) worked
    out once (module docstring, steps 1-2), and the passes of steps 3-4 over all of them without a
    loop over the pings: what :class:`LiveSurface` updates with (one pass, no occlusion test).

    Per voxel, sums over the pings viewed: views, views in the nominal fan, views in front of the
    first return, cells spanned, pings in which it spans a bright cell. Per (ping, voxel, bright cell)
    a pair: the voxel and the cell's *slot* (every ping's bright cells numbered one after the other),
    kept sorted by (ping, voxel, cell): the order :func:`_explain` visits them in, so that every sum
    of steps 3-4 adds the same numbers in the same order and the layer equals :func:`_layer`'s bit for
    bit. A voxel that stops being a candidate keeps its pairs (masked out), so it comes back for free.
    """

    def __init__(self, grid: GridSpec, spec: SonarSpec, opts: SurfaceOptions) -> None:
        self.grid, self.spec, self.opts = grid, spec, opts
        self.sc = _scales(grid, spec, opts)
        self.edges = beam_tan_edges(spec)
        n_vox = grid.n_voxels
        self.viewed = np.zeros(n_vox, bool)
        self.seen, self.fan, self.front, self.bright = (np.zeros(n_vox, np.uint32) for _ in range(4))
        self.sens = np.zeros(n_vox, np.int64)
        self.key = np.zeros(0, np.int64)  # (ping * n_vox + voxel) * n_cells + cell: the sort order
        self.vox = np.zeros(0, np.int32)
        self.slot = np.zeros(0, np.int32)
        self.start = np.zeros(0, bool)  # the pair opens a (ping, voxel) run
        self.slot0: list[int] = [0]  # first slot of each ping viewed; the next ping's after the last
        self.n_pings = 0  # pings viewed (the first n of those kept)

    #: Voxels per edge of the groups a ping tests first (:meth:`_near`).
    GROUP = 8

    def _voxels(self, vox: np.ndarray) -> dict:
        """Voxels ``vox`` (sorted flat indices) with their centres, grouped in cubes of :attr:`GROUP`
        voxels: each group's centre and, in group order, where its voxels lie in ``vox``."""
        idx = np.stack(np.unravel_index(vox, self.grid.shape), axis=1)
        s, lo = self.grid.voxel_size_m, np.asarray(self.grid.min_corner_m, np.float64)
        g = idx // self.GROUP
        gid = np.ravel_multi_index(tuple(g.T), tuple(-(-np.asarray(self.grid.shape) // self.GROUP)))
        order = np.argsort(gid, kind="stable")
        ids, first = np.unique(gid[order], return_index=True)
        gidx = np.stack(np.unravel_index(ids, tuple(-(-np.asarray(self.grid.shape) // self.GROUP))), axis=1)
        return {"vox": vox, "centres": lo + (idx + 0.5) * s, "order": order,
                "bounds": np.r_[first, len(vox)], "gcentres": lo + (gidx + 0.5) * self.GROUP * s}

    def _near(self, T_W_S: np.ndarray, vs: dict) -> np.ndarray:
        """Indices into ``vs["vox"]`` (ascending) of the voxels in groups that may meet the ping's arc:
        a group's bounding sphere ahead of the sonar, within its range and within reach of the aperture's
        slab (the exact tests follow, voxel by voxel)."""
        rad = 0.5 * np.sqrt(3.0) * self.GROUP * self.grid.voxel_size_m + self.sc["half"]
        x, y, z = _in_sonar(T_W_S, vs["gcentres"])
        h = np.sqrt(x * x + y * y)
        half = self.sc["half_el"]
        ok = (x > -rad) & (h * h + z * z < (self.spec.range_max_m + rad) ** 2)
        if half < 1.5:  # the distance to the slab's cone, in the group's meridian plane
            ok &= np.abs(z) - np.tan(half) * h <= rad / np.cos(half) + 1e-9
        g = np.flatnonzero(ok)
        b = vs["bounds"]
        n = b[g + 1] - b[g]
        at = np.repeat(b[g] - np.cumsum(n) + n, n) + np.arange(int(n.sum()))
        keep = np.zeros(len(vs["vox"]), bool)  # back to ascending order without a sort
        keep[vs["order"][at]] = True
        return np.flatnonzero(keep)

    def _view(self, p: int, pc: _PingCells, vs: dict, sign: int = 1):
        """Ping ``p``'s view of the voxels of ``vs`` (:meth:`_voxels`): the sums go in (``sign`` -1: out
        again, and no pairs), the pairs come out."""
        sc, spec = self.sc, self.spec
        near = self._near(pc.T_W_S, vs)
        k, _, elev, j0, j1, c0, c1, front = _geometry(spec, self.edges, pc.T_W_S, vs["centres"][near],
                                                      sc["n_rc"], sc["half"], sc["cell_m"], sc["half_el"],
                                                      pc.first, sc["front_tol"])
        v = vs["vox"][near[k]]
        one = np.uint32(1)
        add = np.add if sign > 0 else np.subtract  # a ping sees a voxel once: no repeated index
        self.seen[v] = add(self.seen[v], one)
        f = v[np.abs(elev) <= 0.5 * spec.vfov_rad]
        self.fan[f] = add(self.fan[f], one)
        self.front[v[front]] = add(self.front[v[front]], one)
        self.sens[v] = add(self.sens[v], (c1 - c0 + 1) * (j1 - j0 + 1))
        which, at = _bright_pairs(pc.lit, sc["n_rc"], spec.n_beams, j0, j1, c0, c1)
        pv = v[which]
        if len(pv):
            b = pv[np.r_[True, pv[1:] != pv[:-1]]]
            self.bright[b] = add(self.bright[b], one)
        if sign < 0:
            return None
        cell = pc.lit[at].astype(np.int64)
        key = (p * self.grid.n_voxels + pv.astype(np.int64)) * sc["n_cells"] + cell
        start = np.ones(len(pv), bool)
        start[1:] = pv[1:] != pv[:-1]
        return key, pv.astype(np.int32), (self.slot0[p] + at).astype(np.int32), start

    def add_views(self, pings: list[_PingCells], cand_flat: np.ndarray) -> None:
        """View the voxels that are candidates for the first time in every ping viewed before, and the
        pings not viewed yet (from ``pings``, those kept so far) in every voxel ever a candidate."""
        new = cand_flat[~self.viewed[cand_flat]]
        if len(new) and self.n_pings:
            vs = self._voxels(new)
            parts = [self._view(p, pings[p], vs) for p in range(self.n_pings)]
            key = np.concatenate([q[0] for q in parts])
            order = np.argsort(key, kind="stable")
            at = np.searchsorted(self.key, key[order])
            self.key = np.insert(self.key, at, key[order])
            self.vox = np.insert(self.vox, at, np.concatenate([q[1] for q in parts])[order])
            self.slot = np.insert(self.slot, at, np.concatenate([q[2] for q in parts])[order])
            self.start = np.insert(self.start, at, np.concatenate([q[3] for q in parts])[order])
        self.viewed[new] = True
        if self.n_pings < len(pings):
            slots = self.slot0[-1] + sum(len(pc.lit) for pc in pings[self.n_pings:])
            if slots >= 2**31 or (len(pings) * self.grid.n_voxels + 1) * self.sc["n_cells"] >= 2**62:
                raise ValueError(f"Expected fewer pings for the live surface layer's indices, but got "
                                 f"{len(pings)} pings of {slots} bright cells")
            vs = self._voxels(np.flatnonzero(self.viewed))
            parts = [self.key], [self.vox], [self.slot], [self.start]
            for p in range(self.n_pings, len(pings)):
                self.slot0.append(self.slot0[-1] + len(pings[p].lit))
                for lst, a in zip(parts, self._view(p, pings[p], vs), strict=True):
                    lst.append(a)
            self.n_pings = len(pings)
            self.key, self.vox, self.slot, self.start = (np.concatenate(lst) for lst in parts)

    def drop(self, pings: list[_PingCells]) -> None:
        """Forget the first ``len(pings)`` pings viewed (``pings``: those same pings): their sums come out
        (each ping's view worked out again, exactly as it went in) and their pairs, the first ones held,
        are cut off; the pings after them are numbered from 0."""
        m = len(pings)
        if m == 0:
            return
        if m > self.n_pings:
            raise ValueError(f"Expected at most the {self.n_pings} pings viewed to drop, but got {m}")
        vs = self._voxels(np.flatnonzero(self.viewed))
        for p, pc in enumerate(pings):
            self._view(p, pc, vs, sign=-1)
        cut = m * self.grid.n_voxels * self.sc["n_cells"]
        i = int(np.searchsorted(self.key, cut))
        self.key = self.key[i:] - cut
        self.vox, self.start = self.vox[i:], self.start[i:]
        self.slot = self.slot[i:] - np.int32(self.slot0[m])
        self.slot0 = [x - self.slot0[m] for x in self.slot0[m:]]
        self.n_pings -= m

    def explain(self, cand_flat: np.ndarray, w0: np.ndarray | None):
        """Steps 3-4 over the candidates ``cand_flat`` (sorted flat indices, all viewed): (alive (n,),
        weights (n,), votes (n,) uint32, views (n,) uint32, bright views (n,) uint32)."""
        opts, n = self.opts, len(cand_flat)
        fan, front = self.fan[cand_flat], self.front[cand_flat]
        alive = front <= opts.max_front_share * np.maximum(fan, 1)
        pos = np.full(self.grid.n_voxels, -1, np.int64)
        pos[cand_flat[alive]] = np.flatnonzero(alive)
        c = pos[self.vox]
        ok = c >= 0
        # a voxel's pairs of a ping stay or go together: the runs that stay are still runs
        c, s, first = c[ok], self.slot[ok].astype(np.int64), self.start[ok]
        seg = np.cumsum(first) - 1  # (ping, voxel) runs, in order
        seg_c = c[first]
        bright = np.where(alive, self.bright[cand_flat], 0).astype(np.uint32)
        sens = np.where(alive, self.sens[cand_flat], 0).astype(np.float64)
        n_slots = self.slot0[self.n_pings]
        w = np.where(bright > 0, 1.0 if w0 is None else w0, 0.0)
        q = np.empty(len(c))
        for _ in range(int(opts.iterations)):
            wc = w[c]
            den = np.bincount(s, weights=wc, minlength=n_slots)[s]
            # a cell no weight reaches holds only weightless pairs: 0, as 0 / 1 gives
            q.fill(0.0)
            np.divide(wc, den, out=q, where=den > 0)
            per = np.bincount(seg, weights=q, minlength=len(seg_c))
            w = np.bincount(seg_c, weights=per, minlength=n) / np.maximum(sens, 1.0)
        rank = np.empty(n, np.int64)
        rank[np.lexsort((np.arange(n), w))] = np.arange(1, n + 1)
        rc = rank[c]
        best = np.zeros(n_slots, np.int64)
        np.maximum.at(best, s, rc)
        won = seg[best[s] == rc]  # sorted: each run once
        won = won[np.r_[True, won[1:] != won[:-1]]] if len(won) else won
        votes = np.bincount(seg_c[won], minlength=n).astype(np.uint32)
        return alive, w, votes, self.seen[cand_flat].copy(), bright


def map_candidates(mapper) -> tuple[np.ndarray, np.ndarray]:
    """(candidates, observed), (nx, ny, nz) bool each, of a mapper with view counts (``rule="evidence"``
    or ``"visible"``): the voxels the evidence rule's decision calls occupied, as the mapper's
    :attr:`~gpumap.MinMaxMapper.value_rule` decides them now (its settings and decision, read-time:
    the layer follows whatever it decides), and those some ping observed."""
    ev = mapper.evidence()
    return mapper.value_rule.occupied(ev["count"], ev["hits"]), np.isfinite(ev["min_all"])


class LiveSurface:
    """The surface layer of a live mapper, updated per batch of pings.

    ``add(images, poses)`` after (or with) the mapper's own ``integrate_batch`` keeps what the layer
    needs of each ping (its bright cells and first returns: a few kB, not the image);
    :meth:`update` builds the layer from the mapper's map now (:func:`map_candidates`). Each
    (ping, voxel) is worked out once, the first update after both are there (:class:`_Pairs`), and
    every update runs steps 3-4 over all kept pings at once: an update equals
    :func:`surface_from_mapper` of the same pings on the same map, voxel for voxel, and its cost
    grows with the pings (their bright cells' pairs), as the mapper's memory does not.

    It is also a layer (:meth:`gpumap.MinMaxMapper.attach`): attached, it is fed every batch the
    mapper integrates (``LiveSurface()`` then takes its mapper when attached).

    Parameters
    ----------
    mapper : gpumap.MinMaxMapper or None
        A bounded mapper with ``rule="evidence"`` (or ``"visible"``); None: the one it is attached to.
    options : SurfaceOptions, optional
        With ``passes`` > 1 (the occlusion test) every update views every ping again (the plain path).
    warm_start : bool
        Start the weights from the last update's (new candidates at 1): a few iterations per update
        carry the weights on across updates, but the layer is then no longer the offline one.
    max_pings : int or None
        Keep the newest this many pings at most (None: all): an update then drops the oldest and is
        the offline layer of the newest ``max_pings`` pings on the map of every ping, and the layer's
        memory (its pairs) stops growing with the run.
    """

    name = "surface"
    per_ping = False

    def __init__(self, mapper=None, options: SurfaceOptions | None = None, warm_start: bool = False,
                 max_pings: int | None = None) -> None:
        if max_pings is not None and (isinstance(max_pings, bool) or max_pings < 1
                                      or not isinstance(max_pings, (int, np.integer))):
            raise ValueError(f"Expected max_pings to be a positive integer or None, but got {max_pings!r}")
        self.options = options or SurfaceOptions()
        self.warm_start = bool(warm_start)
        self.max_pings = None if max_pings is None else int(max_pings)
        self.mapper = None
        #: Seconds spent keeping the pings the mapper handed over (attached: during its batches).
        self.seconds_add = 0.0
        if mapper is not None:
            self._bind(mapper)

    def attached(self, mapper) -> None:
        """Follow ``mapper`` (:meth:`gpumap.MinMaxMapper.attach`)."""
        if self.mapper is None:
            self._bind(mapper)
        elif self.mapper is not mapper:
            raise ValueError("Expected the mapper this surface layer was made for, but got another")

    def after_batch(self, mapper, images: np.ndarray, T_W_S: np.ndarray) -> None:
        """Keep what the layer needs of the pings the mapper just integrated."""
        t0 = time.perf_counter()
        self.add(images, T_W_S)
        self.seconds_add += time.perf_counter() - t0

    def _bind(self, mapper) -> None:
        if getattr(mapper, "rule", None) not in ("evidence", "visible"):
            raise ValueError(f"Expected a mapper with rule='evidence' or 'visible', but got "
                             f"{getattr(mapper, 'rule', None)!r}")
        if getattr(mapper, "sparse", None) is not None:
            raise ValueError("Expected a bounded mapper (a GridSpec with all blocks) for the live surface "
                             "layer, but it allocates blocks on demand")
        self.mapper = mapper
        self._lock = threading.Lock()  # the list of pings, between add() and an update's drop
        self._pings: list[_PingCells] = []
        self._dropped = 0  # pings dropped from the front (max_pings): the list starts at this one
        self._weights: np.ndarray | None = None  # per voxel, NaN where never a candidate
        self._pairs = _Pairs(mapper.grid, mapper.spec, self.options) if self.options.passes == 1 else None
        self.layer: SurfaceLayer | None = None

    @property
    def n_pings(self) -> int:
        """Pings held (added and not dropped)."""
        return len(self._pings)

    @property
    def n_added(self) -> int:
        """Pings ever added (the held ones are the last :attr:`n_pings` of them)."""
        return self._dropped + len(self._pings)

    @property
    def n_pairs(self) -> int:
        """(ping, voxel, bright cell) pairs held (the layer's memory: 17 bytes each)."""
        return 0 if self._pairs is None else len(self._pairs.key)

    def add(self, images: np.ndarray, poses: np.ndarray) -> None:
        """Keep pings ``images`` ((n, n_bins, n_beams) uint8 or float32 in [0, 1]) at ``poses``
        ((n, 4, 4) ``T_W_S``), those the mapper integrated (any thread; in the order they were)."""
        images, poses = _check(images, poses, self.mapper.spec)
        cell_m = self.options.cell_m or 0.5 * self.mapper.grid.voxel_size_m
        new = [_prepare(i, T, self.mapper.spec, self.mapper.threshold, cell_m, self.options.live_ping_share)
               for i, T in zip(images, poses, strict=True)]
        with self._lock:
            self._pings += new

    def snapshot(self) -> tuple[np.ndarray, np.ndarray, int]:
        """(candidates, observed, :attr:`n_added`): the map now and how many pings it holds, for
        :meth:`update` on another thread; take it while nothing integrates or adds (a live mapper's
        lock), so that the map and the pings match."""
        cand, obs = map_candidates(self.mapper)
        return cand, obs, self.n_added

    def reset(self) -> None:
        """Forget every ping (with the mapper's own ``reset``)."""
        with self._lock:
            self._pings, self._dropped = [], 0
        self._weights = None
        if self._pairs is not None:
            self._pairs = _Pairs(self.mapper.grid, self.mapper.spec, self.options)
        self.layer = None

    def update(self, snapshot: tuple[np.ndarray, np.ndarray, int] | None = None) -> SurfaceLayer:
        """The layer of every ping kept so far over the mapper's map now (or of the first pings of a
        :meth:`snapshot` over its map)."""
        import time

        t0 = time.perf_counter()
        m = self.mapper
        cand, obs, n_added = snapshot if snapshot is not None else self.snapshot()
        pairs = self._pairs  # one object for the whole update, even if reset meanwhile
        with self._lock:
            old = 0 if self.max_pings is None else max(0, n_added - self._dropped - self.max_pings)
            if old:  # the oldest go: out of the sums and pairs where viewed, then off the list
                if pairs is not None:
                    pairs.drop(self._pings[:min(old, pairs.n_pings)])
                self._pings, self._dropped = self._pings[old:], self._dropped + old
            pings = self._pings[:n_added - self._dropped]
        flat = np.flatnonzero(cand)
        w0 = None
        if self.warm_start and self._weights is not None:
            w0 = np.nan_to_num(self._weights[flat], nan=1.0)
        if pairs is None:
            layer, w = _layer(cand, obs, m.grid, m.spec, pings, self.options, w0)
        else:
            pairs.add_views(pings, flat)
            alive, w, votes, seen, bright = pairs.explain(flat, w0)
            layer = _finish(cand, obs, m.grid, np.argwhere(cand), alive, votes, seen, bright, self.options,
                            len(pings), pairs.sc)
            layer.stats["pairs"] = len(pairs.key)
        if self.warm_start:
            self._weights = np.full(m.grid.n_voxels, np.nan)
            self._weights[flat] = w
        layer.stats["seconds"] = time.perf_counter() - t0
        layer.stats["warm"] = w0 is not None
        layer.stats["first_ping"] = n_added - len(pings)  # of those ever added, from 0
        self.layer = layer
        return layer


def surface_from_mapper(mapper, images: np.ndarray | None = None, poses: np.ndarray | None = None,
                        options: SurfaceOptions | None = None,
                        frames: Iterable[tuple[np.ndarray, np.ndarray]] | None = None) -> SurfaceLayer:
    """The surface layer of a :class:`gpumap.MinMaxMapper` with ``rule="evidence"`` or ``"visible"``
    (candidates: the evidence rule's occupied voxels by the mapper's decision,
    :meth:`gpumap.core.rules.ValueRule.occupied`; its grid, spec and threshold) from the pings it
    integrated: ``images`` and ``poses`` as :func:`surface_from_evidence` takes them, or ``frames`` as
    :func:`surface_from_frames` does."""
    if (frames is None) == (images is None and poses is None):
        raise ValueError("Expected either images and poses or frames, but got "
                         + ("both" if frames is not None else "neither"))
    cand, obs = map_candidates(mapper)
    if frames is None:
        return surface_from_evidence(cand, obs, mapper.grid, mapper.spec, images, poses, mapper.threshold,
                                     options)
    return surface_from_frames(cand, obs, mapper.grid, mapper.spec, frames, mapper.threshold, options)
