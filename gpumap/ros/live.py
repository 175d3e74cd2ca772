"""Live mapping without ROS: a bounded pose buffer and the worker that integrates queued pings.

The ROS node (:mod:`gpumap.ros.node`) only converts messages and hands them here; everything
that decides what reaches the map lives in this module, so it is the same whatever carries
the pings.

What happens to a ping (stamp ``t``, a polar image):

1. :meth:`LiveMapper.add_ping` refuses a stamp not after the last accepted ping's
   (``rejected['image_out_of_order']``) and queues the ping. A ping stamped ahead of the
   receiver's clock (``now_ns``; within the node's ``max_future_s``, else the node refuses it)
   is mapped but does not become the mark later pings must pass: one image stamped 0.9 s
   ahead no longer gets the next second of good pings refused as out of order (a stamp
   already accepted is still refused). The queue holds at most
   ``queue_size`` pings: when a new ping finds it full, the **oldest** queued ping is dropped
   (``dropped['queue_full']``), so the map follows the vehicle's latest view and the queue's
   latency stays bounded. Nothing else is ever dropped, and every drop is counted.
2. The worker thread takes queued pings in stamp order. A ping whose pose is known is
   interpolated on SE(3) at ``t`` from the two buffered poses that bracket it
   (:meth:`PoseBuffer.lookup`; a pose with stamp exactly ``t`` is used as it is). A ping newer
   than every buffered pose waits, at most ``pose_wait_s`` after it arrived, then is skipped
   (``skipped['pose_timeout']``); pings behind it wait with it, so they stay in order. A ping
   whose bracketing poses are more than ``max_pose_gap_s`` apart is skipped
   (``skipped['pose_gap']``), one older than every buffered pose too (``skipped['no_pose']``).
3. The ready pings (at most ``max_batch``) go to the mapper in one ``integrate_batch`` call;
   ``on_publish`` is called from the worker (at most every ``publish_period_s``, and as soon
   as that period has passed after the last change), never from the caller of ``add_*``.

The ``add_*`` methods only take a short lock and append: they never wait for the mapper.
Each kind of rejection, skip and drop is logged once (the first time), then only counted.
"""

from __future__ import annotations

import bisect
import collections
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from gpumap.lie import se3_exp, se3_inverse, se3_log

__all__ = ["LiveMapper", "PoseBuffer", "QueuedPing", "interpolate_pose"]


def interpolate_pose(T0: np.ndarray, T1: np.ndarray, s: float) -> np.ndarray:
    """The pose a fraction ``s`` in [0, 1] of the way from ``T0`` to ``T1`` on SE(3).

    ``T0 @ Exp(s * Log(T0^-1 @ T1))``: constant twist between the two (a screw motion).
    ``s = 0`` gives ``T0`` and ``s = 1`` gives ``T1`` up to rounding; the rotation of the
    result is orthonormal to rounding.

    Parameters
    ----------
    T0, T1 : (4, 4) float64
        ``T_W_S`` at the two bracketing stamps.
    s : float
    """
    d = se3_log(se3_inverse(T0) @ T1)
    return np.asarray(T0, dtype=np.float64) @ se3_exp(float(s) * d)


class PoseBuffer:
    """The last ``max_poses`` sonar poses, by stamp (integer nanoseconds), in stamp order.

    Parameters
    ----------
    max_poses : int
        How many poses are kept (the oldest go first).
    max_gap_s : float
        Two poses further apart than this do not bracket a ping (a gap in the pose stream).
    """

    def __init__(self, max_poses: int = 2000, max_gap_s: float = 0.5) -> None:
        if int(max_poses) < 2:
            raise ValueError(f"Expected max_poses >= 2, but got {max_poses}")
        if not (max_gap_s > 0 and math.isfinite(max_gap_s)):
            raise ValueError(f"Expected max_gap_s > 0 (seconds), but got {max_gap_s}")
        self.max_poses = int(max_poses)
        self.max_gap_ns = int(round(float(max_gap_s) * 1e9))
        self._t: list[int] = []
        self._T: list[np.ndarray] = []

    def __len__(self) -> int:
        return len(self._t)

    @property
    def newest_ns(self) -> int | None:
        return self._t[-1] if self._t else None

    def add(self, stamp_ns: int, T_W_S: np.ndarray) -> bool:
        """Append a pose; False (and nothing kept) if ``stamp_ns`` is not after the newest."""
        if self._t and stamp_ns <= self._t[-1]:
            return False
        self._t.append(int(stamp_ns))
        self._T.append(np.array(T_W_S, dtype=np.float64))
        if len(self._t) > self.max_poses:
            del self._t[0], self._T[0]
        return True

    def lookup(self, stamp_ns: int) -> tuple[str, np.ndarray | None]:
        """``(status, T_W_S)`` at ``stamp_ns``.

        ``status`` is ``"ok"`` (with the pose), ``"wait"`` (newer than every pose held),
        ``"pose_gap"`` (the bracketing poses are more than ``max_gap_s`` apart) or
        ``"no_pose"`` (older than every pose held).
        """
        t = self._t
        if not t or stamp_ns > t[-1]:
            return "wait", None
        i = bisect.bisect_left(t, stamp_ns)
        if t[i] == stamp_ns:
            return "ok", self._T[i].copy()
        if i == 0:
            return "no_pose", None
        t0, t1 = t[i - 1], t[i]
        if t1 - t0 > self.max_gap_ns:
            return "pose_gap", None
        return "ok", interpolate_pose(self._T[i - 1], self._T[i], (stamp_ns - t0) / (t1 - t0))

    def clear(self) -> None:
        self._t.clear()
        self._T.clear()


@dataclass
class QueuedPing:
    """A ping waiting for its pose or for the mapper."""

    stamp_ns: int
    image: np.ndarray  # (n_bins, n_beams) uint8 or float32 in [0, 1]
    arrived_s: float  # monotonic clock when it arrived
    T_W_S: np.ndarray | None = field(default=None, repr=False)


#: /diagnostics goes WARN when more than this share of the messages that came in one period were
#: lost (rejected, skipped or dropped: every reason), ERROR above :data:`ERROR_FRACTION` (or when the
#: worker stopped).
WARN_FRACTION = 0.05
ERROR_FRACTION = 0.5


def health(prev: dict | None, now: dict, error: BaseException | None = None) -> tuple[str, str]:
    """``(level, message)`` of ``/diagnostics`` from two :meth:`LiveMapper.stats` (the last period's and
    this one's; ``prev`` None: since the start): ``"OK"``, ``"WARN"`` or ``"ERROR"`` by the share of
    the period's messages that were lost (images received or lost in the middleware, and poses
    refused), see :data:`WARN_FRACTION`."""
    def lost(s: dict | None) -> int:
        return 0 if s is None else sum(sum(s[k].values()) for k in ("rejected", "skipped", "dropped"))

    def came(s: dict | None) -> int:
        return 0 if s is None else s["received"] + s["dropped"].get("middleware_lost", 0)

    d_lost, d_came = lost(now) - lost(prev), came(now) - came(prev)
    share = d_lost / max(d_came, 1)
    gone = sum(now["dropped"].values()) + sum(now["skipped"].values())
    total = (f"{now['integrated']} pings mapped, {gone} dropped or skipped, "
             f"{sum(now['rejected'].values())} messages rejected")
    if error is not None:
        return "ERROR", f"worker stopped: {error!r}; {total}"
    if not d_lost:
        return "OK", total
    level = "ERROR" if share > ERROR_FRACTION else "WARN" if share > WARN_FRACTION else "OK"
    return level, f"{d_lost} of {d_came} messages lost in the last period ({share:.0%}); {total}"


class LiveMapper:
    """Feed a mapper from a live stream of pings and poses on a worker thread.

    Parameters
    ----------
    mapper : MinMaxMapper
        Any mapper with ``integrate_batch``; its images' shape is ``mapper.spec.image_shape``.
    queue_size : int
        Pings held at most (waiting for a pose or for the mapper); a new ping finding the
        queue full drops the oldest (counted as ``dropped['queue_full']``).
    max_batch : int
        Pings per ``integrate_batch`` call at most.
    pose_wait_s : float
        How long a ping newer than every pose waits for one (then ``skipped['pose_timeout']``).
    max_pose_gap_s : float
        Poses further apart than this do not bracket a ping (``skipped['pose_gap']``).
    pose_buffer : int
        Poses kept.
    publish_period_s : float
        ``on_publish`` runs at most this often (and once this long after the last change). 0
        (default): after every batch, so latency is one batch's work, and a busy worker, whose
        batches grow, publishes less often. A period phase-locks with a steady ping rate: at 10 Hz
        and 0.1 s each ping may wait most of a period for its slot.
    on_publish : callable, optional
        ``on_publish(newest_stamp_ns)`` on the worker thread after pings were integrated;
        read the map there (``mapper.values()``).
    on_batch : callable, optional
        ``on_batch(pings)`` (the :class:`QueuedPing` s just integrated, in order, with their
        ``T_W_S``) on the worker thread, still holding the map's lock: another layer built from the
        same pings (:class:`LiveSurfaceWorker`) sees them in the order the map did, and a reader
        holding the lock sees the map and that layer's pings agree.
    log : callable, optional
        ``log(text)`` for the first occurrence of every rejection, skip and drop reason.
    clock : callable
        Monotonic seconds (for waits and latencies).
    """

    def __init__(
        self,
        mapper,
        *,
        queue_size: int = 32,
        max_batch: int = 16,
        pose_wait_s: float = 0.5,
        max_pose_gap_s: float = 0.5,
        pose_buffer: int = 2000,
        publish_period_s: float = 0.0,
        on_publish: Callable[[int], None] | None = None,
        on_batch: Callable[[list[QueuedPing]], None] | None = None,
        log: Callable[[str], None] | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        for name, v in (("queue_size", queue_size), ("max_batch", max_batch)):
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
                raise ValueError(f"Expected an integer {name} >= 1, but got {v!r}")
        for name, v in (("pose_wait_s", pose_wait_s), ("publish_period_s", publish_period_s)):
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"Expected {name} >= 0 (seconds), but got {v!r}")
        self.mapper = mapper
        self.image_shape = tuple(mapper.spec.image_shape)
        self.queue_size = int(queue_size)
        self.max_batch = int(max_batch)
        self.pose_wait_s = float(pose_wait_s)
        self.publish_period_s = float(publish_period_s)
        self.poses = PoseBuffer(pose_buffer, max_pose_gap_s)
        self.on_publish = on_publish
        self.on_batch = on_batch
        self.on_reset: Callable[[], None] | None = None  # called by reset, the map's lock held
        self._log = log or (lambda text: None)
        self._clock = clock
        self._cond = threading.Condition()
        self._map_lock = threading.Lock()  # integrate / reset / save / reads of the map
        self._pending: collections.deque[QueuedPing] = collections.deque()
        self._in_flight = 0  # pings taken from the queue, in the mapper now
        self._last_ping_ns: int | None = None  # the newest accepted stamp not ahead of the clock
        self._ahead: collections.deque[int] = collections.deque(maxlen=64)  # accepted, ahead of it
        self._stop = False
        self._thread: threading.Thread | None = None
        self._logged: set[str] = set()
        self.received = 0
        self.integrated = 0
        self.rejected: collections.Counter[str] = collections.Counter()
        self.skipped: collections.Counter[str] = collections.Counter()
        self.dropped: collections.Counter[str] = collections.Counter()
        self.publish_errors = 0
        self._unpublished: list[float] = []  # arrival times of integrated, not yet published pings
        self._newest_ns: int | None = None
        #: ``T_W_S`` (4, 4) of the newest ping mapped (by stamp), None before the first
        self.newest_pose: np.ndarray | None = None
        self._last_pub = -math.inf
        self.latencies_s: collections.deque[float] = collections.deque(maxlen=2000)
        self._done_times: collections.deque[float] = collections.deque(maxlen=4000)
        self.error: BaseException | None = None

    # ------------------------------------------------------------------ input (any thread)
    def _once(self, key: str, text: str) -> None:
        if key not in self._logged:
            self._logged.add(key)
            self._log(f"{text} [logged once; every one is counted as {key} in /diagnostics]")

    def reject(self, reason: str, detail: str = "") -> None:
        """Count a message refused at the boundary (bad input) under ``reason``."""
        with self._cond:
            self.rejected[reason] += 1
        self._once(f"rejected.{reason}", f"rejected a message ({reason}): {detail}")

    def drop(self, reason: str, n: int = 1, detail: str = "") -> None:
        """Count ``n`` good pings lost before the map (``middleware_lost``, ``queue_full``)."""
        if n <= 0:
            return
        with self._cond:
            self.dropped[reason] += int(n)
        self._once(f"dropped.{reason}", f"dropped {n} ping(s) ({reason}): {detail}")

    def _skip(self, reason: str, p: QueuedPing) -> None:
        self.skipped[reason] += 1  # caller holds self._cond
        self._once(f"skipped.{reason}", f"skipped the ping stamped {p.stamp_ns * 1e-9:.6f} s ({reason})")

    def count_received(self) -> None:
        """Count an image message that reached the node (before any check)."""
        with self._cond:
            self.received += 1

    def add_pose(self, stamp_ns: int, T_W_S: np.ndarray) -> bool:
        """Buffer a checked pose; False if its stamp is not after the newest (counted)."""
        with self._cond:
            ok = self.poses.add(stamp_ns, T_W_S)
            if ok:
                self._cond.notify()
        if not ok:
            self.reject("pose_out_of_order", f"pose stamped {stamp_ns * 1e-9:.6f} s is not after "
                        f"the newest buffered pose ({self.poses.newest_ns * 1e-9:.6f} s)")
        return ok

    def add_ping(self, stamp_ns: int, image: np.ndarray, now_ns: int | None = None) -> bool:
        """Queue a checked polar image (uint8 or float32 in [0, 1]); never waits for the mapper.

        Returns False when refused: the stamp is not after the last accepted ping's
        (``rejected['image_out_of_order']``), or the shape is not the sonar's
        (``rejected['image_size']``). ``now_ns``: the receiver's clock; a stamp after it is
        accepted without moving the mark later stamps must pass (module docstring).
        """
        if tuple(image.shape) != self.image_shape:
            self.reject("image_size", f"expected a polar image of shape {self.image_shape}, but got "
                        f"{tuple(image.shape)}")
            return False
        dropped = None
        with self._cond:
            if (self._last_ping_ns is not None and stamp_ns <= self._last_ping_ns) or stamp_ns in self._ahead:
                last = self._last_ping_ns if stamp_ns not in self._ahead else int(stamp_ns)
                ok = False
            else:
                ok = True
                if now_ns is not None and stamp_ns > now_ns:
                    self._ahead.append(int(stamp_ns))
                else:
                    self._last_ping_ns = int(stamp_ns)
                self._pending.append(QueuedPing(int(stamp_ns), image, self._clock()))
                if len(self._pending) > self.queue_size:
                    dropped = self._pending.popleft()
                self._cond.notify()
        if not ok:
            self.reject("image_out_of_order", f"image stamped {stamp_ns * 1e-9:.6f} s is not after the "
                        f"last accepted image ({last * 1e-9:.6f} s)")
            return False
        if dropped is not None:
            self.drop("queue_full", 1, f"the mapper is behind: {self.queue_size} pings were queued, the "
                      "oldest goes")
        return True

    # ------------------------------------------------------------------ worker
    def start(self) -> None:
        """Start the worker thread."""
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="gpumap-live", daemon=True)
            self._thread.start()

    def stop(self, drain: bool = True, timeout_s: float = 30.0) -> None:
        """Stop the worker; with ``drain`` it first integrates (or skips, counted) what is queued."""
        with self._cond:
            self._stop = True
            if not drain:
                n = len(self._pending)
                self._pending.clear()
            else:
                n = 0
            self._cond.notify()
        if n:
            self.drop("shutdown", n, "queued when the node stopped without draining")
        if self._thread is not None:
            self._thread.join(timeout_s)
            self._thread = None

    def _take(self) -> list[QueuedPing]:
        """The pings ready for the mapper, in order (caller holds ``self._cond``)."""
        ready: list[QueuedPing] = []
        now = self._clock()
        while self._pending and len(ready) < self.max_batch:
            p = self._pending[0]
            status, T = self.poses.lookup(p.stamp_ns)
            if status == "ok":
                p.T_W_S = T
                ready.append(self._pending.popleft())
            elif status == "wait":
                if now - p.arrived_s < self.pose_wait_s:
                    break
                self._pending.popleft()
                self._skip("pose_timeout", p)
            else:
                self._pending.popleft()
                self._skip(status, p)
        return ready

    def _integrate(self, ready: list[QueuedPing]) -> None:
        """Integrate ``ready`` in runs of one dtype; a run the mapper refuses goes ping by ping."""
        i = 0
        while i < len(ready):
            j = i + 1
            while j < len(ready) and ready[j].image.dtype == ready[i].image.dtype:
                j += 1
            run = ready[i:j]
            try:
                with self._map_lock:
                    self.mapper.integrate_batch(np.stack([p.image for p in run]),
                                                np.stack([p.T_W_S for p in run]))
                    if self.on_batch is not None:
                        self.on_batch(run)
                done = run
            except (ValueError, TypeError):  # the map is unchanged: find the ping it refuses
                done = []
                for p in run:
                    try:
                        with self._map_lock:
                            self.mapper.integrate(p.image, p.T_W_S)
                            if self.on_batch is not None:
                                self.on_batch([p])
                        done.append(p)
                    except (ValueError, TypeError) as e:
                        self.reject("mapper_refused", str(e))
            now = self._clock()
            with self._cond:
                self.integrated += len(done)
                self._unpublished.extend(p.arrived_s for p in done)
                self._done_times.extend([now] * len(done))
                if done:
                    last = max(done, key=lambda p: p.stamp_ns)
                    if self._newest_ns is None or last.stamp_ns >= self._newest_ns:
                        self.newest_pose = last.T_W_S
                    self._newest_ns = max(self._newest_ns or 0, last.stamp_ns)
            i = j

    def _publish(self) -> None:
        with self._cond:
            arrivals, self._unpublished = self._unpublished, []
            newest = self._newest_ns
        self._last_pub = self._clock()
        if self.on_publish is not None and newest is not None:
            try:
                self.on_publish(newest)
            except Exception as e:  # a publisher gone at shutdown must not kill the worker
                self.publish_errors += 1
                self._once("publish_error", f"publishing the map failed: {e!r}")
                return
        now = self._clock()
        self.latencies_s.extend(now - a for a in arrivals)

    def _run(self) -> None:
        try:
            while True:
                with self._cond:
                    ready = self._take()
                    if not ready:
                        if self._stop and not self._pending:
                            break
                        due = self._unpublished and self._clock() - self._last_pub >= self.publish_period_s
                        if not due:
                            wait = 0.05
                            if self._unpublished:
                                wait = max(0.0, self._last_pub + self.publish_period_s - self._clock())
                            self._cond.wait(min(wait, 0.05) if self._pending else wait)
                            continue
                    self._in_flight = len(ready)
                if ready:
                    self._integrate(ready)
                    with self._cond:
                        self._in_flight = 0
                if self._unpublished and self._clock() - self._last_pub >= self.publish_period_s:
                    self._publish()
            if self._unpublished:
                self._publish()
        except BaseException as e:  # noqa: BLE001 - kept for the node to report; never silent
            self.error = e
            self._log(f"the mapping worker stopped: {e!r}")
            raise

    # ------------------------------------------------------------------ map access
    def reset(self) -> None:
        """Forget the map (every voxel unknown); the queue, poses and counters stay."""
        with self._map_lock:
            self.mapper.reset()
            if self.on_reset is not None:
                self.on_reset()

    def save(self, path) -> object:
        """``mapper.save(path)`` (atomic) between two integrations; returns the path written."""
        with self._map_lock:
            return self.mapper.save(path)

    def next_best_views(self, **kwargs) -> tuple[list[dict], int]:
        """:func:`gpumap.layers.viewgain.next_best_views` around the newest pose mapped, between two
        integrations (``kwargs`` go to it); raises ValueError before the first ping or without
        the confidence layer."""
        from gpumap.layers.viewgain import next_best_views

        with self._map_lock:
            if self.newest_pose is None:
                raise ValueError("Expected a mapped ping to plan around, but no ping has been mapped yet")
            return next_best_views(self.mapper, self.newest_pose, **kwargs)

    def values(self) -> np.ndarray:
        """``mapper.values()`` between two integrations."""
        with self._map_lock:
            return self.mapper.values()

    def values_and_confidence(self, confidence: bool) -> tuple[np.ndarray, np.ndarray | None]:
        """``(mapper.values(), mapper.layer("confidence").states())`` of the same map, between two
        integrations;
        ``(values, None)`` when ``confidence`` is false (the mapper needs ``confidence=True``
        otherwise)."""
        with self._map_lock:
            return self.mapper.values(), (self.mapper.layer("confidence").states() if confidence else None)

    def stats(self, window_s: float = 5.0) -> dict:
        """Counters and rates: ``received`` (image messages that reached the node), ``integrated``,
        ``queue`` (waiting or being integrated), ``rejected``/``skipped``/``dropped`` by reason,
        ``ping_rate_hz`` (integrated over the last ``window_s``), ``latency_p50_ms`` and
        ``latency_p99_ms`` (arrival to published map), ``poses``."""
        now = self._clock()
        with self._cond:
            lat = np.array(self.latencies_s, dtype=np.float64)
            recent = sum(1 for t in self._done_times if now - t <= window_s)
            out = {
                "received": self.received,
                "integrated": self.integrated,
                "queue": len(self._pending) + self._in_flight,
                "poses": len(self.poses),
                "rejected": dict(self.rejected),
                "skipped": dict(self.skipped),
                "dropped": dict(self.dropped),
                "publish_errors": self.publish_errors,
            }
        out["ping_rate_hz"] = recent / window_s
        out["latency_p50_ms"] = float(np.percentile(lat, 50) * 1e3) if lat.size else float("nan")
        out["latency_p99_ms"] = float(np.percentile(lat, 99) * 1e3) if lat.size else float("nan")
        return out
