"""A run's live view and recording (:class:`Session`, behind ``--view``/``--record`` of ``demo``
and ``replay``), and what ``gpumap view PATH`` serves of a file.

:func:`view_map` serves a saved map (``map.npz``: its occupied voxels, coloured by value
or height, threshold adjustable) or a refined map (``refined.npz`` of ``gpumap refine``: its
``--layer surface``, the refined occupancy from 0.5, or ``--layer safe``, the map's occupied
voxels); :func:`view_recording` a recording (``*.gpumap-rec``: a ping slider and a play
button replay the run: images, pose, trajectory and the map as it was at that ping).
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["Session", "map_layer", "view_map", "view_recording"]


class Session:
    """The live view and/or the recording of one run (either may be off).

    Parameters
    ----------
    args : argparse.Namespace
        With the flags of :func:`add_view_args`.
    spec, grid, threshold, title
        The map being built.
    """

    def __init__(
        self, args: argparse.Namespace, spec: Any, grid: Any, threshold: float, title: str = "gpumap"
    ) -> None:
        self.viewer = None
        self.recorder = None
        self.hold = getattr(args, "view_hold", None)
        every = int(getattr(args, "view_every", 10) or 10)
        if getattr(args, "record", None) is not None:
            from gpumap.viewer.recording import Recorder

            self.recorder = Recorder(args.record, spec, grid, threshold, map_every=every, title=title)
        if getattr(args, "view", False):
            from gpumap.viewer.live import MapViewer

            self.viewer = MapViewer(
                spec, grid, threshold, host=args.view_host, port=args.view_port, title=title, map_every=every
            )
            print(
                f"gpumap: live view at {self.viewer.url} (bound to {args.view_host}:{self.viewer.port})",
                file=sys.stderr,
                flush=True,
            )

    @classmethod
    def open(
        cls, args: argparse.Namespace | None, spec: Any, grid: Any, threshold: float, title: str = "gpumap"
    ) -> Session | None:
        """A session, or None when neither ``--view`` nor ``--record`` was asked for."""
        if args is None or not (getattr(args, "view", False) or getattr(args, "record", None) is not None):
            return None
        return cls(args, spec, grid, threshold, title)

    def ping(self, image: np.ndarray, T_W_S: np.ndarray, mapper: Any) -> None:
        if self.recorder is not None:
            self.recorder.ping(image, T_W_S, mapper)
        if self.viewer is not None:
            self.viewer.ping(image, T_W_S, mapper)

    def add_points(self, name: str, points: np.ndarray, colors: np.ndarray) -> None:
        if self.recorder is not None:
            self.recorder.add(f"{name}_points", points)
            self.recorder.add(f"{name}_colors", colors)
        if self.viewer is not None:
            self.viewer.add_points(f"/{name}", points, colors)

    def add_path(self, name: str, positions: np.ndarray, color: tuple[int, int, int]) -> None:
        if self.recorder is not None:
            self.recorder.add(f"path_{name}", positions)
        if self.viewer is not None:
            self.viewer.add_path(name, positions, color)

    def add_landmarks(self, positions: np.ndarray, covs: np.ndarray | None) -> None:
        if self.recorder is not None:
            self.recorder.add("landmarks", positions)
            if covs is not None:
                self.recorder.add("landmark_covs", covs)
        if self.viewer is not None:
            self.viewer.add_landmarks(positions, covs)

    def finish(self, mapper: Any) -> None:
        """Close the recording (final map sampled) and show the final map."""
        if self.recorder is not None:
            path = self.recorder.close(mapper.values())
            print(f"gpumap: recorded {self.recorder.n_pings} pings to {path}", file=sys.stderr)
        if self.viewer is not None:
            self.viewer.finish(mapper)

    def abort(self) -> None:
        if self.recorder is not None:
            self.recorder.abort()
        if self.viewer is not None:
            self.viewer.close()
            self.viewer = None

    def serve(self) -> None:
        """Keep the view up after the run (``--view-hold`` seconds, or until Ctrl-C)."""
        if self.viewer is None:
            return
        if self.hold is None:
            print(f"gpumap: serving the view at {self.viewer.url} until Ctrl-C", file=sys.stderr, flush=True)
        else:
            print(
                f"gpumap: serving the view at {self.viewer.url} for {self.hold:g} s",
                file=sys.stderr,
                flush=True,
            )
        try:
            self.viewer.wait(self.hold)
        except KeyboardInterrupt:
            pass


class SessionLayer:
    """A :class:`Session` following a map (:meth:`gpumap.MinMaxMapper.attach`): ``make(mapper)`` opens
    it when attached (the map's sonar and grid known then); each ping, as the mapper integrates it,
    goes to the live view and the recording (``per_ping``: the view sees the map as each ping left it)."""

    name = "view"
    per_ping = True

    def __init__(self, make) -> None:
        self._make = make
        self.session: Session | None = None

    def attached(self, mapper: Any) -> None:
        self.session = self._make(mapper)

    def after_ping(self, mapper: Any, image: np.ndarray, T_W_S: np.ndarray, pad_m: float, params) -> None:
        self.session.ping(image, T_W_S, mapper)


def map_layer(path: str | Path, layer: str | None = None, threshold: float | None = None) -> dict[str, Any]:
    """What ``gpumap view`` shows of a map file: ``spec``, ``grid``, ``values`` ((nx, ny, nz)
    float32, NaN unknown), ``threshold``, ``confidence`` (the map's layer or None), ``n_pings``,
    ``layer`` (None for a map file).

    A refined map (:func:`gpumap.layers.refine.is_refined_file`: ``gpumap refine``'s ``refined.npz`` or the
    ``surface.npz`` of ``gpumap demo`` / ``replay``, :mod:`gpumap.layers.surface`) shows ``layer``
    ``"surface"`` (default: the refined occupancy or the surface layer, occupied from
    :data:`gpumap.layers.refine.OCCUPIED_LEVEL`) or ``"safe"`` (the map's values and threshold); a map
    file with ``layer`` given shows that layer of the ``surface.npz`` beside it
    (:func:`gpumap.layers.refined_map.layers_file`); without one it has one layer (``layer`` given raises
    ValueError).
    """
    from gpumap.layers.refine import OCCUPIED_LEVEL, is_refined_file, load_refined
    from gpumap.layers.refined_map import layers_file

    path = Path(path)
    two = path if is_refined_file(path) else (layers_file(path) if layer is not None else None)
    if two is not None:
        res = load_refined(two)
        layer = layer or "surface"
        if layer not in ("surface", "safe"):
            raise ValueError(f"Expected layer 'surface' or 'safe', but got {layer!r}")
        values, thr = ((res.occupancy, OCCUPIED_LEVEL) if layer == "surface"
                       else (res.map_values, float(res.threshold)))
        return {"spec": res.spec, "grid": res.grid, "values": values,
                "threshold": float(thr if threshold is None else threshold), "confidence": None,
                "n_pings": int(res.stats.get("frames", 0)), "layer": layer}
    if layer is not None:
        raise ValueError("Expected a refined map (gpumap refine's refined.npz) or a map with a surface.npz "
                         f"beside it (gpumap demo/replay) with a layer, but {path} is a map of one layer")
    from gpumap.core.mapper import MinMaxMapper
    from gpumap.viewer.live import mapper_confidence

    m = MinMaxMapper.load(path, backend="numpy")
    return {"spec": m.spec, "grid": m.grid, "values": m.values(),
            "threshold": float(m.threshold if threshold is None else threshold),
            "confidence": mapper_confidence(m),  # saved with its layer: unconfirmed voxels pale
            "n_pings": int(m.n_integrated), "layer": None}


def view_map(path: Path, a: argparse.Namespace) -> Any:
    """Serve the map file ``path`` (:func:`map_layer` of ``a.layer``, ``a.threshold``) at
    ``a.view_host``:``a.view_port``, with a threshold slider; the viewer."""
    from gpumap.viewer.live import MapViewer

    d = map_layer(path, getattr(a, "layer", None), a.threshold)
    thr, values, conf = d["threshold"], d["values"], d["confidence"]
    title = f"gpumap view {path.name}" + (f" ({d['layer']})" if d["layer"] else "")
    v = MapViewer(d["spec"], d["grid"], thr, host=a.view_host, port=a.view_port, title=title,
                  show_pings=False)  # a saved map holds no ping: no empty image panels
    v.set_values(values, conf)
    v.n_pings = d["n_pings"]
    v.finish()
    slider = v.server.gui.add_slider("occupied from", 0.01, 1.0, 0.01, thr)

    def _rethreshold(_e) -> None:
        v.threshold = float(slider.value)
        v.reset_map()
        v.set_values(values, conf)
        v.finish()

    slider.on_update(_rethreshold)
    return v


def view_recording(path: Path, a: argparse.Namespace) -> Any:
    """Serve the recording ``path`` (``--record``) at ``a.view_host``:``a.view_port``: a ping
    slider and a play button; the viewer."""
    from gpumap.viewer.live import MapViewer
    from gpumap.viewer.recording import read_recording

    rec = read_recording(path)
    thr = float(rec.meta["threshold"])
    v = MapViewer(
        rec.spec,
        rec.grid,
        thr,
        host=a.view_host,
        port=a.view_port,
        title=rec.meta.get("title") or f"gpumap view {path.name}",
    )
    pings = list(rec.pings())  # images are uint8: ~n_bins x n_beams bytes each
    if not pings:
        raise ValueError(f"Expected pings in {path}, but it holds none")
    ex = rec.extras
    for name in [k[: -len("_points")] for k in ex if k.endswith("_points")]:
        v.add_points(f"/{name}", ex[f"{name}_points"], ex.get(f"{name}_colors", (120, 120, 120)))
    colours = {"true": (40, 160, 40), "odometry": (140, 140, 140), "ekf": (40, 90, 230)}
    for k in [k for k in ex if k.startswith("path_")]:
        v.add_path(k[5:], ex[k], colours.get(k[5:], (200, 200, 0)))
    if "landmarks" in ex:
        v.add_landmarks(ex["landmarks"], ex.get("landmark_covs"))
    positions = np.array([p.T_W_S[:3, 3] for p in pings])
    state = {"at": -1}

    def show(k: int) -> None:
        with v._lock:
            if k < state["at"]:
                v.reset_map()
                state["at"] = -1
            for p in pings[state["at"] + 1 : k + 1]:
                if p.set_idx is not None:
                    v.apply_diff(p.set_idx, p.set_val, p.clear_idx)
            state["at"] = k
            v._positions = list(positions[: k + 1])
            n_occ = int(np.count_nonzero(v._q))
            v.show_ping(
                pings[k].image,
                pings[k].T_W_S,
                f"**ping {k + 1} / {len(pings)}**  \n{n_occ} occupied voxels (value >= {thr:g})",
            )

    gui = v.server.gui
    slider = gui.add_slider("ping", 1, len(pings), 1, len(pings))
    playing = gui.add_checkbox("play", False)
    slider.on_update(lambda _e: show(int(slider.value) - 1))

    def _play() -> None:
        while True:
            time.sleep(0.1)
            if playing.value:
                slider.value = int(slider.value) % len(pings) + 1

    threading.Thread(target=_play, daemon=True).start()
    show(len(pings) - 1)
    v.n_pings = len(pings)
    v.frame_content()
    return v


