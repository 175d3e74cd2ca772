"""The node's surface layer on a thread of its own (:class:`LiveSurfaceWorker`), beside
:class:`gpumap.ros.live.LiveMapper`."""

from __future__ import annotations

import collections
import threading
import time
from collections.abc import Callable

import numpy as np

from gpumap.ros.live import LiveMapper, QueuedPing

__all__ = ["LiveSurfaceWorker"]


class LiveSurfaceWorker:
    """Keep the surface layer (:class:`gpumap.layers.surface_live.LiveSurface`) of a :class:`LiveMapper`'s
    map up
    to date on a thread of its own, as often as the machine allows.

    The mapping worker hands it every batch it integrated (``live.on_batch``, under the map's lock);
    this thread then, again and again while pings are waiting: takes the map's occupied voxels and
    the pings it holds (under the lock, so the two agree), builds the layer of those pings on that
    map (outside the lock: mapping goes on meanwhile) and calls ``on_publish(layer, newest_stamp_ns)``.
    The layer of an update is :func:`gpumap.layers.surface_live.surface_from_mapper` of the same pings on the
    same map, voxel for voxel; an update's cost grows with the pings held, so updates come less often
    as the run goes on, each taking every ping that arrived meanwhile.

    Parameters
    ----------
    live : LiveMapper
        Its mapper must have ``rule="evidence"`` or ``"visible"``; its ``on_batch`` is taken.
    options : gpumap.layers.surface.SurfaceOptions, optional
    on_publish : callable, optional
        ``on_publish(layer, newest_stamp_ns)`` on this thread after each update.
    log : callable, optional
    clock : callable
        Monotonic seconds (as the live mapper's).
    max_pings : int, optional
        The layer of the newest this many pings only (:class:`gpumap.layers.surface_live.LiveSurface`): its
        memory
        and its updates' cost stop growing with the run.
    """

    def __init__(self, live: LiveMapper, options=None, on_publish=None,
                 log: Callable[[str], None] | None = None,
                 clock: Callable[[], float] = time.monotonic, max_pings: int | None = None) -> None:
        from gpumap.layers.surface_live import LiveSurface

        self.live = live
        self.surface = LiveSurface(live.mapper, options, max_pings=max_pings)
        self.on_publish = on_publish
        self._log = log or (lambda text: None)
        self._clock = clock
        self._cond = threading.Condition()
        self._stamps: list[int] = []  # per ping held: stamp and arrival, in the layer's order
        self._arrivals: list[float] = []
        self._stop = False
        self._thread: threading.Thread | None = None
        self.covered = 0  # pings the last published layer covers
        self.updates = 0
        self.last_update_s = float("nan")
        self.latencies_s: collections.deque[float] = collections.deque(maxlen=4000)  # arrival to published
        self.layer = None
        self.error: BaseException | None = None
        self._gen = 0  # bumped by reset: an update of the pings before it is dropped
        self._update_lock = threading.Lock()  # one update at a time (the thread's, or layer_now's)
        live.on_batch = self._added
        live.on_reset = self.reset

    def _added(self, pings: list[QueuedPing]) -> None:
        """The live mapper's ``on_batch`` (its worker thread, the map's lock held)."""
        self.surface.add(np.stack([p.image for p in pings]), np.stack([p.T_W_S for p in pings]))
        with self._cond:
            self._stamps += [p.stamp_ns for p in pings]
            self._arrivals += [p.arrived_s for p in pings]
            self._cond.notify()

    def start(self) -> None:
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="gpumap-surface", daemon=True)
            self._thread.start()

    def stop(self, timeout_s: float = 120.0) -> None:
        """Stop after one last update covering every ping held (call after the live mapper's stop)."""
        with self._cond:
            self._stop = True
            self._cond.notify()
        if self._thread is not None:
            self._thread.join(timeout_s)
            self._thread = None

    def reset(self) -> None:
        """Forget every ping (the live mapper's ``on_reset``: its map lock is held)."""
        with self._cond:
            self.surface.reset()
            self._stamps, self._arrivals = [], []
            self.covered = 0
            self.layer = None
            self._gen += 1

    def _run(self) -> None:
        try:
            while True:
                with self._cond:
                    while len(self._stamps) <= self.covered and not self._stop:
                        self._cond.wait(0.5)
                    if len(self._stamps) <= self.covered and self._stop:
                        break
                with self.live._map_lock, self._cond:
                    snap = self.surface.snapshot()
                    n, gen = snap[2], self._gen
                    newest = max(self._stamps[:n])
                    arrivals = self._arrivals[self.covered:n]
                t0 = self._clock()
                with self._update_lock:
                    layer = self.surface.update(snap)
                self.last_update_s = self._clock() - t0
                if gen != self._gen:  # reset meanwhile: these pings are gone
                    continue
                if self.on_publish is not None:
                    try:
                        self.on_publish(layer, newest)
                    except Exception as e:  # a publisher gone at shutdown must not stop the layer
                        self._log(f"publishing the surface layer failed: {e!r}")
                now = self._clock()
                with self._cond:
                    if gen == self._gen:  # not reset meanwhile
                        self.latencies_s.extend(now - a for a in arrivals)
                        self.covered, self.layer = n, layer
                        self.updates += 1
        except BaseException as e:  # noqa: BLE001 - kept for the node to report; never silent
            self.error = e
            self._log(f"the surface worker stopped: {e!r}")
            raise

    def layer_now(self):
        """(the layer of every ping mapped so far, the map's values (nx, ny, nz) float32 of the same
        moment): for saving both layers together; waits for an update in progress."""
        with self._update_lock:
            with self.live._map_lock, self._cond:
                snap = self.surface.snapshot()
                values = self.live.mapper.values()
                done = self.layer if self.layer is not None and snap[2] == self.covered else None
            # the last layer published is of this very map when no ping came since (after stop())
            return (done if done is not None else self.surface.update(snap)), values

    def stats(self) -> dict:
        """``surface_pings`` (pings the published layer holds: every ping mapped up to its newest, or the
        newest ``max_pings`` of them), ``surface_waiting`` (pings mapped, not yet in it),
        ``surface_age_s`` (how long the oldest of those has waited since it arrived; 0 when none waits),
        ``surface_latency_max_s`` (arrival to published, the worst over the last pings),
        ``surface_update_s`` (the last update's seconds), ``surface_updates``, ``surface_voxels``,
        ``surface_pairs``."""
        now = self._clock()
        with self._cond:
            held, cov = len(self._stamps), self.covered
            age = now - self._arrivals[cov] if held > cov else 0.0
            lat = max(self.latencies_s) if self.latencies_s else float("nan")
            voxels = int(self.layer.surface.sum()) if self.layer is not None else 0
            in_layer = self.layer.stats["pings"] if self.layer is not None else 0
        return {"surface_pings": in_layer, "surface_waiting": held - cov, "surface_age_s": age,
                "surface_latency_max_s": lat, "surface_update_s": self.last_update_s,
                "surface_updates": self.updates, "surface_voxels": voxels,
                "surface_pairs": self.surface.n_pairs}
