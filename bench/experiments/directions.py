"""Evidence per view direction: views that resolve elevation count on their own.

A sonar cannot tell elevation within its vertical aperture: one ping paints every voxel at a
surface's range and azimuth bright, across the whole aperture (the stretch). Views whose fan
plane is tilted differently resolve that elevation: there the stretch lies in front of the
surface's return (a clear dark view) or off it. Pooled over every view, such a voxel is bright in
most views from the directions that cannot resolve it and dark in the few that can, so a pooled
share keeps it; counted per direction, the resolving direction rejects it on its own.

The direction of a view is the sonar's elevation axis ``z_S`` in the world (``T_W_S[:3, 2]``),
without its sign (a sonar rolled by 180 degrees resolves the same elevation). Views fall into
:data:`N_CLASSES` fixed classes, by the nearest of six axes through opposite vertices of an
icosahedron (evenly spread over the directions, about 63 degrees apart): a fixed function of the
pose, so classes are the same online, in any order and on any machine, and maps of disjoint pings
merge exactly class by class.

:class:`DirectionalEvidence` keeps one evidence map per class (the same kernels, so every backend
gives the same counts bit for bit); :func:`directional_occupied` decides. A voxel is occupied when
some view saw it bright and **no class's views show**, at confidence ``share_z`` (the one-sided
binomial score test of :func:`gpumap.reference.evidence_occupied`, here also for a class that never
saw the voxel bright), that it is bright in fewer than ``bright_share`` of them. Memory: a class map
holds the evidence rule's 16 bytes per voxel of the blocks its views touch (at most
``N_CLASSES`` x 16 bytes per voxel where every class looks).
"""

from __future__ import annotations

import numpy as np

from gpumap.core.params import MapperParams
from gpumap.errors import check_pose
from gpumap.reference import share_keeps

__all__ = ["AXES", "N_CLASSES", "DirectionalEvidence", "direction_classes", "directional_occupied"]

_PHI = (1.0 + 5.0**0.5) / 2.0
#: (6, 3) unit axes, sign-free: the direction classes' centres.
AXES = np.array([[0, 1, _PHI], [0, -1, _PHI], [1, _PHI, 0], [-1, _PHI, 0], [_PHI, 0, 1], [-_PHI, 0, 1]],
                dtype=np.float64)
AXES /= np.linalg.norm(AXES, axis=1, keepdims=True)
N_CLASSES = len(AXES)


def direction_classes(T_W_S: np.ndarray) -> np.ndarray:
    """(B,) int64 direction class of each pose ((B, 4, 4) or (4, 4) float64 ``T_W_S``): the axis of
    :data:`AXES` nearest to the elevation axis ``T_W_S[:3, 2]``, sign-free (ties: the lower index)."""
    T = np.asarray(T_W_S, dtype=np.float64)
    z = T[..., :3, 2].reshape(-1, 3)
    return np.argmax(np.abs(z @ AXES.T), axis=1)


def directional_occupied(dark: np.ndarray, hits: np.ndarray, bright_share: float,
                         share_z: float) -> np.ndarray:
    """The directional decision (module docstring). ``dark``, ``hits``: (C, ...) clear dark and bright
    views per class and voxel; returns bool (...): ever bright in some class, and no class rejects
    ``share >= bright_share`` by the one-sided score test at ``share_z`` (a class with no clear view
    never rejects; a tie keeps)."""
    d = np.asarray(dark)
    h = np.asarray(hits)
    if d.shape != h.shape or d.ndim < 1:
        raise ValueError(f"Expected dark and hits of one shape (C, ...), but got {d.shape} and {h.shape}")
    p, z = float(bright_share), float(share_z)
    out = (h > 0).any(axis=0)
    idx = np.flatnonzero(out)  # the test runs on the ever-bright voxels only
    k = h.reshape(h.shape[0], -1)[:, idx].astype(np.float64)
    n = k + d.reshape(d.shape[0], -1)[:, idx]
    share = np.divide(k, n, out=np.ones_like(k), where=n > 0)
    keeps = share_keeps(share, n, p, z)
    out.reshape(-1)[idx] = keeps.all(axis=0)
    return out


class DirectionalEvidence:
    """One evidence map per view-direction class (module docstring), fed beside a mapper.

    Parameters
    ----------
    spec, grid, backend, threshold
        As :class:`gpumap.MinMaxMapper` takes them (the class maps use ``rule="evidence"``).
    **kw
        Further :class:`gpumap.MinMaxMapper` options (``sparse``, ``max_bytes``, ...).
    """

    def __init__(self, spec, grid, backend: str = "auto", threshold: float = 0.1, **kw) -> None:
        from gpumap.core.mapper import MinMaxMapper

        self._make = lambda: MinMaxMapper(spec, grid, backend,
                                          MapperParams(rule="evidence", threshold=threshold, **kw))
        self.maps: dict[int, MinMaxMapper] = {}  # class -> its map, made when its first view comes
        self.spec, self.threshold = spec, threshold
        self.backend = self._map(0).backend if backend == "auto" else backend

    @property
    def _grid_shape(self) -> tuple[int, int, int]:
        return self._map(min(self.maps, default=0)).grid.shape

    def _map(self, c: int):
        if c not in self.maps:
            self.maps[c] = self._make()
        return self.maps[c]

    def integrate(self, image: np.ndarray, T_W_S: np.ndarray) -> None:
        """One ping, into its class's map (``image`` and ``T_W_S`` as :meth:`MinMaxMapper.integrate`)."""
        T = check_pose(T_W_S, "T_W_S")
        self._map(int(direction_classes(T)[0])).integrate(image, T)

    def integrate_batch(self, images: np.ndarray, T_W_S: np.ndarray) -> None:
        """B pings ((B, n_bins, n_beams), (B, 4, 4)), each into its class's map (the same counts as B
        calls of :meth:`integrate`)."""
        T = np.asarray(T_W_S, dtype=np.float64)
        if T.ndim != 3 or T.shape[1:] != (4, 4) or len(T) != len(images):
            raise ValueError(f"Expected T_W_S of shape ({len(images)}, 4, 4), but got {T.shape}")
        cls = direction_classes(T)
        for c in np.unique(cls):
            sel = np.flatnonzero(cls == c)
            self._map(int(c)).integrate_batch(np.asarray(images)[sel], T[sel])

    def counts(self) -> tuple[np.ndarray, np.ndarray]:
        """(N_CLASSES, nx, ny, nz) uint32 clear dark views and bright views per class over the grid."""
        dark = np.zeros((N_CLASSES, *self._grid_shape), np.uint32)
        hits = np.zeros_like(dark)
        for c, m in self.maps.items():
            ev = m.evidence()
            dark[c], hits[c] = ev["count"], ev["hits"]
        return dark, hits

    def occupied(self, bright_share: float, share_z: float) -> np.ndarray:
        """(nx, ny, nz) bool: :func:`directional_occupied` of :meth:`counts`."""
        return directional_occupied(*self.counts(), bright_share, share_z)

    def values(self, mapper) -> np.ndarray:
        """``mapper``'s values (an evidence map of the same pings) read by the directional decision at
        its ``bright_share`` and ``share_z``: its dimmest bright view where occupied, else its min over
        views, ``NaN`` never observed."""
        ev = mapper.evidence()
        occ = self.occupied(mapper.bright_share, mapper.share_z)
        out = np.where(occ, ev["bright"], ev["min_all"]).astype(np.float32)
        out[np.isinf(out)] = np.nan
        return out

    def merge(self, other: DirectionalEvidence) -> None:
        """Fold ``other`` (the same grid, disjoint pings) in, class by class: exact (gpumap.core.merge)."""
        from gpumap.core.merge import merge_into

        for c, m in other.maps.items():
            merge_into(self._map(c), m)

    def memory_bytes(self) -> int:
        """Bytes the class maps hold (each :meth:`MinMaxMapper.memory_stats` ``block_bytes``)."""
        return int(sum(m.memory_stats()["block_bytes"] for m in self.maps.values()))
