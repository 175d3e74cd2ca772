"""The record every reader yields (:class:`SonarFrame`), the recording handle and the format error.

Readers convert vendor layouts at the I/O edge: what leaves ``gpumap.io`` is always a polar
image ``(n_bins, n_beams)`` float32 in ``[0, 1]`` whose columns follow ``spec.bearings_rad``
in ascending azimuth (sonar frame x forward, y left, z up; ``theta = atan2(y, x)``).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from gpumap.errors import FormatError, LimitError
from gpumap.spec import SonarSpec

__all__ = ["FormatError", "LimitError", "Recording", "SonarFrame"]


@dataclass(frozen=True, eq=False)
class SonarFrame:
    """One fully read and validated sonar ping.

    Parameters
    ----------
    image : (n_bins, n_beams) float32
        Echo intensity in ``[0, 1]``; row = range bin (ascending), column = beam in the
        order of ``spec.bearings_rad`` (ascending azimuth).
    spec : SonarSpec
        Geometry of this ping (vendor sonars may change range between pings).
    timestamp_s : float or None
        Time of the ping, seconds (epoch where the format has one; see the reader).
    T_W_S : (4, 4) float64 or None
        Sonar pose (maps sonar-frame points to world), metres; ``None`` if unknown.
    meta : dict
        Format-specific extras (ping id, gain words, source offset, ...); never needed
        for mapping.
    """

    image: np.ndarray
    spec: SonarSpec
    timestamp_s: float | None = None
    T_W_S: np.ndarray | None = None
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        img = self.image
        if not isinstance(img, np.ndarray) or img.dtype != np.float32:
            raise TypeError(
                f"Expected a float32 ndarray for 'image', but got "
                f"{getattr(img, 'dtype', type(img).__name__)}"
            )
        if img.shape != self.spec.image_shape:
            raise ValueError(
                f"Expected image of shape {self.spec.image_shape} for 'image', but got {img.shape}"
            )
        if self.T_W_S is not None:
            T = np.asarray(self.T_W_S, dtype=np.float64)
            if T.shape != (4, 4):
                raise ValueError(f"Expected a (4, 4) transform for 'T_W_S', but got {T.shape}")
            object.__setattr__(self, "T_W_S", T)


class Recording:
    """A lazily streamed recording: iterate it to get :class:`SonarFrame` objects.

    Parameters
    ----------
    path : str
        Where the recording lives.
    kind : str
        Format name (``"oculus-raw"``, ``"oculus-log"``, ``"aris"``, ``"fan-folder"``, ``"rosbag"``).
    frames : callable
        Returns a fresh iterator of frames each time (so a recording can be read twice).
    has_poses : bool
        Whether frames carry ``T_W_S``.
    count : callable or None
        Cheap count of frames (headers only), for progress bars; ``None`` if unknown.
    poses : callable or None
        Cheap list of every frame's ``T_W_S`` (or ``None``) without decoding images, for
        sizing a grid before the pass that maps; ``None`` if the format cannot say cheaply.
    pose_note : str or None
        Where ``has_poses`` is False although the recording has some poses, or lacks the file
        that holds them: what came, for a message (``"sonar_poses.csv holds 103 poses for 123
        pictures; 20 pictures have none (the first: image_1030.png)"``); else ``None``.
    """

    def __init__(
        self,
        path: str,
        kind: str,
        frames: Callable[[], Iterator[SonarFrame]],
        has_poses: bool,
        count: Callable[[], int] | None = None,
        poses: Callable[[], list[np.ndarray | None]] | None = None,
        pose_note: str | None = None,
    ) -> None:
        self.path = str(path)
        self.pose_note = pose_note
        self.kind = kind
        self.has_poses = bool(has_poses)
        self._frames = frames
        self._count = count
        self._poses = poses

    def __iter__(self) -> Iterator[SonarFrame]:
        return self._frames()

    def count(self) -> int | None:
        """Number of frames, from headers only (``None`` if the format cannot say cheaply)."""
        return None if self._count is None else int(self._count())

    def poses(self) -> list[np.ndarray | None] | None:
        """Every frame's ``T_W_S`` in order, without reading images (``None`` if unknown)."""
        return None if self._poses is None else self._poses()

    def __repr__(self) -> str:
        return f"Recording(kind={self.kind!r}, path={self.path!r}, has_poses={self.has_poses})"


def decoder_threads() -> int:
    """Threads that decode a folder's pictures ahead of the mapper (``GPUMAP_DECODERS``, default half of
    this machine's cores, 1 to 8: PNG inflation and the fan's resampling release the interpreter). On one
    H200 host of 16 cores the real tank's replay at 1 cm went from 84-103 to 300-339 frames/s with 4 and
    376-393 with 8 (``bench/results/pipeline_rate_h200_decoders*.json``); on two cores one thread is
    fastest."""
    import os

    env = os.environ.get("GPUMAP_DECODERS", "")
    if env.strip():
        n = int(env)
        if n < 1:
            raise ValueError(f"Expected GPUMAP_DECODERS to be a positive integer, but got {env!r}")
        return n
    return max(1, min(8, (os.cpu_count() or 1) // 2))


def decoded_in_order(decode, items, threads: int | None = None, window: int | None = None):
    """``decode(item)`` of every item, in the items' order, computed by ``threads`` threads at most
    ``window`` items ahead (default twice the threads): the same results as a plain loop, sooner. An
    exception of ``decode`` is raised where its item comes, as the loop would; stopping early cancels
    what is queued."""
    from collections import deque
    from concurrent.futures import ThreadPoolExecutor

    threads = decoder_threads() if threads is None else int(threads)
    if threads <= 1:
        for x in items:
            yield decode(x)
        return
    window = 2 * threads if window is None else max(1, int(window))
    it = iter(items)
    with ThreadPoolExecutor(max_workers=threads, thread_name_prefix="gpumap-decode") as pool:
        queued: deque = deque()
        try:
            for x in it:
                queued.append(pool.submit(decode, x))
                if len(queued) >= window:
                    yield queued.popleft().result()
            while queued:
                yield queued.popleft().result()
        finally:
            for f in queued:
                f.cancel()


def frames_skipping_bad(decode, items, on_bad):
    """The frames ``decode(item)`` gives, decoded ahead in order (:func:`decoded_in_order`); ``decode``
    returns a :class:`FormatError` for an item it cannot read, which goes to ``on_bad(error)`` (then the
    frame is skipped) or, with ``on_bad`` None, is raised where it comes."""
    for fr in decoded_in_order(decode, items):
        if isinstance(fr, FormatError):
            if on_bad is None:
                raise fr
            on_bad(fr)
            continue
        yield fr

