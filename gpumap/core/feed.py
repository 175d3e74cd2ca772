"""The one loop that feeds pings to a mapper: frames in, batches to the mapper, layers updated.

Every driver (``gpumap replay`` with or without the EKF, the demo, refine, the EKF's submaps, the
node's worker) hands its pings to :func:`feed`: it groups them into batches for
:meth:`gpumap.MinMaxMapper.integrate_batch` (one upload and a few launches on a GPU; the same map,
bit for bit, as one call per ping), keeps the pings' order, and the map's attached layers
(:meth:`gpumap.MinMaxMapper.attach`) follow each batch. :func:`prefetch` reads and decodes the
next frames on a thread of their own while the mapper works on the last ones, so a recording's
decoder and the mapper overlap.
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["BATCH", "FeedStats", "feed", "prefetch"]

#: Pings per :meth:`~gpumap.MinMaxMapper.integrate_batch` call.
BATCH = 32


@dataclass
class FeedStats:
    """What :func:`feed` did: ``pings`` integrated, ``batches`` (calls to the mapper), and
    ``seconds_integrate`` (inside the mapper's calls, the layers' work included)."""

    pings: int = 0
    batches: int = 0
    seconds_integrate: float = 0.0


def _parts(item: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(image, T_W_S, pose_cov or None) of a frame (``.image``, ``.T_W_S``) or a tuple."""
    if isinstance(item, tuple):
        image, T = item[0], item[1]
        cov = item[2] if len(item) > 2 else None
        return image, T, cov
    return item.image, item.T_W_S, getattr(item, "pose_cov", None)


def feed(mapper, pings: Iterable[Any], *, batch: int = BATCH,
         after: Callable[[int, np.ndarray, np.ndarray], None] | None = None) -> FeedStats:
    """Integrate every ping of ``pings`` into ``mapper``, in order, ``batch`` at a time.

    Parameters
    ----------
    mapper : gpumap.MinMaxMapper
        The map (its attached layers follow every batch).
    pings : iterable
        Frames with ``.image`` ((n_bins, n_beams) uint8 or float in [0, 1]) and ``.T_W_S``
        ((4, 4) float, metres), or tuples ``(image, T_W_S)`` / ``(image, T_W_S, pose_cov)``
        (``pose_cov`` (6, 6) or None). Images are copied (a reader may reuse its buffer).
    batch : int
        Pings per call; 1 integrates one ping a call (:meth:`~gpumap.MinMaxMapper.integrate`).
        A batch also ends where the images' dtype changes or a ping with a pose covariance comes.
    after : callable, optional
        ``after(k, image, T_W_S)`` once ping ``k`` (counted from 0) is in the map; with it the
        pings go one at a time.

    Returns
    -------
    FeedStats
    """
    if isinstance(batch, bool) or not isinstance(batch, int) or batch < 1:
        raise ValueError(f"Expected batch to be a positive integer, but got {batch!r}")
    if after is not None:
        batch = 1
    stats = FeedStats()
    images: list[np.ndarray] = []
    poses: list[np.ndarray] = []

    def flush() -> None:
        t0 = time.perf_counter()
        if len(images) == 1:
            mapper.integrate(images[0], poses[0])
        else:
            mapper.integrate_batch(np.stack(images), np.stack(poses))
        stats.seconds_integrate += time.perf_counter() - t0
        stats.batches += 1
        images.clear()
        poses.clear()

    for item in pings:
        image, T, cov = _parts(item)
        if cov is not None:  # its own call: a per-ping pose bound
            if images:
                flush()
            t0 = time.perf_counter()
            mapper.integrate(image, T, cov)
            stats.seconds_integrate += time.perf_counter() - t0
            stats.batches += 1
        else:
            if images and np.asarray(image).dtype != images[0].dtype:
                flush()
            images.append(np.array(image))
            poses.append(np.asarray(T, np.float64))
            if len(images) >= batch:
                flush()
        if after is not None:
            after(stats.pings, image, T)
        stats.pings += 1
    if images:
        flush()
    return stats


_DONE = object()


def prefetch(items: Iterable[Any], depth: int = 2 * BATCH) -> Iterator[Any]:
    """``items`` as they come, read ahead by up to ``depth`` on a thread of their own: the reading
    and decoding of a recording overlaps the mapping of the frames before. An error of the reader
    is raised here, at the item where it happened; stopping early stops the reader."""
    q: queue.Queue = queue.Queue(maxsize=max(1, int(depth)))
    stop = threading.Event()

    def read() -> None:
        try:
            for x in items:
                while not stop.is_set():
                    try:
                        q.put((x, None), timeout=0.1)
                        break
                    except queue.Full:
                        continue
                if stop.is_set():
                    return
            q.put((_DONE, None))
        except BaseException as e:  # handed to the consumer, raised there
            q.put((_DONE, e))

    t = threading.Thread(target=read, name="gpumap-prefetch", daemon=True)
    t.start()
    try:
        while True:
            x, err = q.get()
            if x is _DONE:
                if err is not None:
                    raise err
                return
            yield x
    finally:
        stop.set()
        while t.is_alive():  # free the reader if it waits on a full queue
            try:
                q.get_nowait()
            except queue.Empty:
                t.join(0.05)
