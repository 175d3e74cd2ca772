"""Maps of ping segments, re-integrated only where corrected poses moved them, merged exactly.

Issue 39. A pose graph (:mod:`gpumap.ekf.posegraph`) moves old poses whenever it closes a loop;
re-mapping every ping at every solve would cost the whole run each time. Pings ``0 .. n-1`` are
split into segments of ``segment`` consecutive pings, each with a map of its own on the common
grid. :meth:`SegmentMaps.update` re-integrates only the segments whose poses moved by more
than ``tol_m`` / ``tol_rad`` since they were last mapped (and maps new ones); :meth:`values` is
the merge of every segment's map (:func:`gpumap.core.merge.merge_maps`), which is exactly, bit for
bit, the map of one mapper that integrated every ping at the segments' poses (maps of disjoint
pings merge exactly: every per-voxel update is a min or a saturating count).
"""

from __future__ import annotations

import numpy as np

from gpumap.core.feed import feed
from gpumap.core.params import MapperParams

__all__ = ["SegmentMaps"]


class SegmentMaps:
    """Per-segment maps of a run (module docstring).

    Parameters
    ----------
    spec : SonarSpec
    grid : GridSpec
        The common grid of every segment's map.
    segment : int
        Pings per segment.
    backend, threshold, rule
        Of each segment's :class:`~gpumap.MinMaxMapper`.
    tol_m, tol_rad : float
        A segment is re-integrated when any of its poses moved more than this (metres, default
        a quarter of a voxel; radians, default 0.005) since it was last mapped.
    """

    def __init__(self, spec, grid, *, segment: int = 50, backend: str = "auto", threshold: float = 0.4,
                 rule: str | None = None, tol_m: float | None = None, tol_rad: float = 0.005) -> None:
        if segment < 1:
            raise ValueError(f"Expected segment >= 1 pings, but got {segment}")
        self.spec, self.grid = spec, grid
        self.segment = int(segment)
        self.kw = {"backend": backend, "params": MapperParams(threshold=float(threshold), rule=rule)}
        self.tol_m = 0.25 * grid.voxel_size_m if tol_m is None else float(tol_m)
        self.tol_rad = float(tol_rad)
        self._maps: dict[int, object] = {}
        self._poses: dict[int, np.ndarray] = {}
        #: Segments integrated so far, counting re-integrations (each time a segment is mapped).
        self.integrations = 0

    def _moved(self, s: int, T: np.ndarray) -> bool:
        old = self._poses.get(s)
        if old is None or old.shape != T.shape:
            return True
        dp = np.linalg.norm(old[:, :3, 3] - T[:, :3, 3], axis=1).max()
        c = (np.einsum("nij,nij->n", old[:, :3, :3], T[:, :3, :3]) - 1.0) / 2.0
        da = float(np.arccos(np.clip(c, -1.0, 1.0)).max())
        return bool(dp > self.tol_m or da > self.tol_rad)

    def update(self, images, poses: np.ndarray) -> list[int]:
        """Map pings ``0 .. len(poses)-1`` at ``poses`` ((n, 4, 4)): (re-)integrate the segments whose
        poses moved (or that are new or grew); ``images[i]`` is ping ``i``. Returns the segments
        integrated."""
        from gpumap import MinMaxMapper

        T = np.asarray(poses, np.float64)
        if T.ndim != 3 or T.shape[1:] != (4, 4):
            raise ValueError(f"Expected poses of shape (n, 4, 4), but got {T.shape}")
        done = []
        for s in range(0, (len(T) + self.segment - 1) // self.segment):
            a, b = s * self.segment, min((s + 1) * self.segment, len(T))
            if not self._moved(s, T[a:b]):
                continue
            m = MinMaxMapper(self.spec, self.grid, **self.kw)
            feed(m, ((images[k], T[k]) for k in range(a, b)))
            self._maps[s], self._poses[s] = m, T[a:b].copy()
            self.integrations += 1
            done.append(s)
        return done

    def mapper(self):
        """A new mapper holding every segment's map, merged (:func:`gpumap.core.merge.merge_maps`)."""
        from gpumap.core.merge import merge_maps

        if not self._maps:
            raise ValueError("Expected at least one segment mapped (call update first), but got none")
        return merge_maps([self._maps[s] for s in sorted(self._maps)], backend=self.kw["backend"])

    def values(self) -> np.ndarray:
        """The merged map's values (NaN unknown), as :meth:`gpumap.MinMaxMapper.values`."""
        return self.mapper().values()
