"""Mapping recordings: every ping's image and pose, and the map's changes, on one ping timeline.

``gpumap demo --record FILE`` and ``gpumap replay --record FILE`` write one; ``gpumap view
FILE`` plays it back in the browser view with a ping slider. Writing needs nothing beyond
NumPy (no viewer): the vehicle can record while nobody watches, the laptop views it later.

The file is a zip (``.gpumap-rec``; NumPy ``.npy`` members; images stored, the rest
deflated) written as the run goes and swapped into place atomically when it closes
(:func:`gpumap.atomic.atomic_write`):

- ``meta.json``: format name and version, the sonar and grid specs, the occupied threshold,
  ``n_pings``, ``title`` and any extras (truth, paths, landmarks are arrays below);
- ``ping/NNNNNN/image.npy`` (uint8 ``(n_bins, n_beams)``, the polar image quantised to 0..255)
  and ``ping/NNNNNN/T_W_S.npy`` (float64 ``(4, 4)``) for every ping ``NNNNNN`` = 0, 1, ...;
- ``ping/NNNNNN/set_idx.npy`` (int64 flat voxel indices, C order), ``set_val.npy`` (uint8,
  value x 255) and ``clear_idx.npy`` at the pings where the map was sampled (every
  ``map_every`` pings and the last): the voxels that became occupied or changed value,
  and those no longer occupied, since the previous sample;
- ``extra/NAME.npy``: arrays the run adds (``truth_points``, ``path_true``, ...).
"""

from __future__ import annotations

import io
import json
import os
import queue
import threading
import zipfile
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from gpumap.atomic import atomic_write

__all__ = ["FORMAT", "VERSION", "MapRecording", "Recorder", "RecordedPing", "read_recording"]

FORMAT = "gpumap-recording"
VERSION = 1


def _to_u8(image: np.ndarray) -> np.ndarray:
    a = np.asarray(image)
    if a.dtype == np.uint8:
        return a
    return np.clip(np.rint(np.nan_to_num(a.astype(np.float32)) * 255.0), 0, 255).astype(np.uint8)


class MapDiff:
    """Occupied voxels between samples of a map: what changed since the last :meth:`update`.

    Parameters
    ----------
    threshold : float
        Occupied if value >= this.
    """

    def __init__(self, threshold: float) -> None:
        self.threshold = float(threshold)
        self._val: np.ndarray | None = None  # uint8 quantised value, 0 = not occupied

    def update(self, values: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(set_idx, set_val, clear_idx)`` of ``values`` ((nx, ny, nz) float, NaN unknown) against the last.

        ``set_idx`` (int64) and ``set_val`` (uint8 >= 1, value x 255): occupied voxels new or
        with a changed quantised value; ``clear_idx``: voxels occupied before and not now.
        """
        v = np.asarray(values).ravel()
        occ = np.isfinite(v) & (v >= self.threshold)
        q = np.zeros(v.shape, np.uint8)
        q[occ] = np.clip(np.rint(v[occ] * 255.0), 1, 255).astype(np.uint8)
        if self._val is None:
            self._val = np.zeros_like(q)
        changed = np.flatnonzero(q != self._val)
        set_idx = changed[q[changed] > 0]
        clear_idx = changed[q[changed] == 0]
        self._val = q
        return set_idx.astype(np.int64), q[set_idx], clear_idx.astype(np.int64)

    @property
    def occupied(self) -> tuple[np.ndarray, np.ndarray]:
        """Flat indices (int64) and quantised values (uint8) of the occupied voxels now."""
        if self._val is None:
            return np.zeros(0, np.int64), np.zeros(0, np.uint8)
        idx = np.flatnonzero(self._val)
        return idx, self._val[idx]


class Recorder:
    """Write a mapping recording (see the module doc) ping by ping.

    Parameters
    ----------
    path : path-like
        The file; it appears (or is replaced) only when :meth:`close` succeeds.
    spec : SonarSpec
    grid : GridSpec
    threshold : float
        Occupied if value >= this.
    map_every : int
        Sample the map every this many pings (and always at the last, on close).
    title : str
    """

    def __init__(
        self,
        path: str | os.PathLike,
        spec: Any,
        grid: Any,
        threshold: float,
        map_every: int = 10,
        title: str = "",
    ) -> None:
        if int(map_every) < 1:
            raise ValueError(f"Expected map_every >= 1, but got {map_every}")
        self.path = Path(path)
        self.spec, self.grid, self.threshold = spec, grid, float(threshold)
        self.map_every = int(map_every)
        self.title = title
        self.n_pings = 0
        self._diff = MapDiff(threshold)
        self._extras: dict[str, np.ndarray] = {}
        self._last_mapper: Any = None
        self._last_sampled = -1
        self._ctx = atomic_write(self.path)
        self._file = self._ctx.__enter__()
        self._zip = zipfile.ZipFile(self._file, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=1)
        self._closed = False
        # compressing and writing happen on a thread of their own (zlib releases the GIL): the
        # mapping loop only copies the image and, when a sample is due, the map's values
        self._jobs: queue.Queue = queue.Queue(maxsize=256)
        self._error: BaseException | None = None
        self._writer = threading.Thread(target=self._write_loop, name="gpumap-recorder", daemon=True)
        self._writer.start()

    def _write_loop(self) -> None:
        while True:
            job = self._jobs.get()
            if job is None:
                return
            if self._error is not None:
                continue
            try:
                job()
            except BaseException as e:  # reported by close()
                self._error = e

    def _check(self) -> None:
        if self._error is not None:
            raise RuntimeError(
                f"Expected to write the recording {self.path}, but: {self._error}"
            ) from self._error

    def _write(self, name: str, a: np.ndarray) -> None:
        buf = io.BytesIO()
        np.save(buf, np.ascontiguousarray(a), allow_pickle=False)
        # images are stored as they are (deflating speckled sonar pings costs more CPU than the
        # mapper and saves ~half); the map's changes and the metadata are deflated
        kind = zipfile.ZIP_STORED if name.endswith("/image.npy") else zipfile.ZIP_DEFLATED
        self._zip.writestr(name, buf.getvalue(), compress_type=kind)

    def _put(self, name: str, a: np.ndarray) -> None:
        self._check()
        a = np.array(a, copy=True)
        self._jobs.put(lambda: self._write(name, a))

    def _drain(self) -> None:
        if self._writer.is_alive():
            self._jobs.put(None)
            self._writer.join()

    def ping(
        self, image: np.ndarray, T_W_S: np.ndarray, mapper: Any = None, values: np.ndarray | None = None
    ) -> None:
        """Record one ping; sample the map (``mapper.values()`` or ``values``) when it is due."""
        k = self.n_pings
        self._put(f"ping/{k:06d}/image.npy", _to_u8(image))
        self._put(f"ping/{k:06d}/T_W_S.npy", np.asarray(T_W_S, np.float64).reshape(4, 4))
        self.n_pings += 1
        self._last_mapper = mapper
        if (mapper is not None or values is not None) and (k % self.map_every == 0):
            self._sample(k, mapper.values() if values is None else values)

    def _sample(self, k: int, values: np.ndarray) -> None:
        self._check()
        v = np.array(values, dtype=np.float32, copy=True)

        def job() -> None:
            set_idx, set_val, clear_idx = self._diff.update(v)
            self._write(f"ping/{k:06d}/set_idx.npy", set_idx)
            self._write(f"ping/{k:06d}/set_val.npy", set_val)
            self._write(f"ping/{k:06d}/clear_idx.npy", clear_idx)

        self._jobs.put(job)
        self._last_sampled = k

    def add(self, name: str, array: np.ndarray) -> None:
        """Keep an extra array (``truth_points``, ``path_ekf``, ...), written on close."""
        if not name.isidentifier():
            raise ValueError(f"Expected an identifier for the extra's name, but got {name!r}")
        self._extras[name] = np.asarray(array)

    def close(self, values: np.ndarray | None = None) -> Path:
        """Sample the final map (``values`` or the last mapper's), write the metadata, publish the file."""
        if self._closed:
            return self.path
        try:
            last = self.n_pings - 1
            if last >= 0 and self._last_sampled != last:
                if values is None and self._last_mapper is not None:
                    values = self._last_mapper.values()
                if values is not None:
                    self._sample(last, values)
            for name, a in self._extras.items():
                self._put(f"extra/{name}.npy", a)
            self._drain()
            self._check()
            meta = {
                "format": FORMAT,
                "version": VERSION,
                "spec": self.spec.to_dict(),
                "grid": self.grid.to_dict(),
                "threshold": self.threshold,
                "n_pings": self.n_pings,
                "map_every": self.map_every,
                "title": self.title,
                "extras": sorted(self._extras),
            }
            self._zip.writestr("meta.json", json.dumps(meta))
            self._zip.close()
        except BaseException as e:
            self._closed = True
            self._drain()
            self._zip.close()
            self._ctx.__exit__(type(e), e, e.__traceback__)
            raise
        self._closed = True
        self._ctx.__exit__(None, None, None)
        return self.path

    def abort(self) -> None:
        """Drop the recording: the file is left as it was."""
        if self._closed:
            return
        self._closed = True
        self._drain()
        self._zip.close()
        err = RuntimeError("recording aborted")
        try:
            self._ctx.__exit__(RuntimeError, err, None)
        except RuntimeError:
            pass

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, et, e, tb) -> None:
        if et is None:
            self.close()
        else:
            self.abort()


@dataclass
class RecordedPing:
    """One ping of a recording: ``image`` uint8 (n_bins, n_beams), ``T_W_S`` (4, 4) float64,
    and the map's change at this ping (``set_idx``/``set_val``/``clear_idx``) or None."""

    index: int
    image: np.ndarray
    T_W_S: np.ndarray
    set_idx: np.ndarray | None = None
    set_val: np.ndarray | None = None
    clear_idx: np.ndarray | None = None


@dataclass
class MapRecording:
    """A recording opened by :func:`read_recording` (pings are read lazily)."""

    path: Path
    meta: dict
    spec: Any
    grid: Any
    extras: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def n_pings(self) -> int:
        return int(self.meta["n_pings"])

    def _load(self, zf: zipfile.ZipFile, name: str) -> np.ndarray | None:
        try:
            with zf.open(name) as f:
                return np.load(io.BytesIO(f.read()), allow_pickle=False)
        except KeyError:
            return None

    def pings(self) -> Iterator[RecordedPing]:
        """Every ping in order."""
        with zipfile.ZipFile(self.path) as zf:
            for k in range(self.n_pings):
                pre = f"ping/{k:06d}/"
                img = self._load(zf, pre + "image.npy")
                T = self._load(zf, pre + "T_W_S.npy")
                if img is None or T is None:
                    raise ValueError(f"Expected ping {k} of {self.n_pings} in {self.path}, but it is missing")
                yield RecordedPing(
                    k,
                    img,
                    T,
                    self._load(zf, pre + "set_idx.npy"),
                    self._load(zf, pre + "set_val.npy"),
                    self._load(zf, pre + "clear_idx.npy"),
                )


def read_recording(path: str | os.PathLike) -> MapRecording:
    """Open a recording written by :class:`Recorder`; raises ``ValueError`` if it is not one."""
    from gpumap.spec import GridSpec, SonarSpec

    p = Path(path)
    try:
        with zipfile.ZipFile(p) as zf:
            meta = json.loads(zf.read("meta.json"))
            if meta.get("format") != FORMAT or meta.get("version") != VERSION:
                raise ValueError(
                    f"Expected a {FORMAT} v{VERSION} file, but {p} says "
                    f"{meta.get('format')!r} v{meta.get('version')!r}"
                )
            rec = MapRecording(p, meta, SonarSpec.from_dict(meta["spec"]), GridSpec.from_dict(meta["grid"]))
            for name in meta.get("extras", []):
                a = rec._load(zf, f"extra/{name}.npy")
                if a is not None:
                    rec.extras[name] = a
    except (zipfile.BadZipFile, KeyError, json.JSONDecodeError) as e:
        raise ValueError(
            f"Expected a gpumap recording (zip with meta.json), but {p} is not one: {e}"
        ) from None
    return rec
