"""The live 3-D view (viser): sonar pose and field of view, ping images, trajectory, voxel map.

:class:`MapViewer` serves a viser scene (z up, metres, world frame = the map's) that any
browser reaching ``http://HOST:PORT`` opens. Per ping it is told the image, the pose and the
mapper; what it sends is throttled so that viewing never dominates the run:

- the sonar frame, its field-of-view wedge, the Cartesian fan laid in the sonar's plane, the
  polar and fan images in the side panel and the trajectory: at most every
  ``pose_interval_s`` (0.1 s) of wall time;
- the map: at most every ``map_interval_s`` (0.5 s) and every ``map_every`` pings; only the
  16^3-voxel blocks whose occupied voxels changed are sent again, each block one batched
  mesh of boxes coloured by value (viridis) or height (turbo);
- and both only while the time spent viewing stays within ``budget`` (5 %) of the wall
  time: an update that took ``dt`` holds the next one of its kind off for ``dt / budget``.

Scene tree: ``/map/b_I_J_K`` (blocks), ``/sonar`` (frame, ``/sonar/fov``, ``/sonar/fan``),
``/trajectory``, ``/truth`` (demo: the true surface beside the map), ``/paths/NAME`` and
``/landmarks`` (EKF rows), ``/grid_box``.
"""

from __future__ import annotations

import math
import threading
import time
from typing import Any

import numpy as np

from gpumap.viewer import require_viser
from gpumap.viewer.recording import MapDiff

__all__ = ["UNCONFIRMED_MODES", "MapViewer", "colormap_u8", "confidence_colours", "mapper_confidence",
           "rotation_to_wxyz"]

BLOCK = 16  # voxels per block edge: the unit of "changed blocks only"

#: How the live view draws occupied voxels that the confidence layer calls unconfirmed.
UNCONFIRMED_MODES = ("pale", "hidden", "as confirmed")
#: Share of white mixed into an unconfirmed voxel's colour in the ``"pale"`` mode.
PALE_MIX = 0.7


def confidence_colours(rgb: np.ndarray, confirmed: np.ndarray, mode: str = "pale"
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Colours of occupied voxels given the confidence layer.

    Parameters
    ----------
    rgb : (N, 3) uint8
        The voxels' colours (by value or height).
    confirmed : (N,) bool
        True where ``MinMaxMapper.layer("confidence").states()`` is 3 (confirmed), False where 2
        (unconfirmed).
    mode : one of :data:`UNCONFIRMED_MODES`
        ``"pale"``: unconfirmed voxels mixed with :data:`PALE_MIX` white, confirmed ones as
        given; ``"hidden"``: unconfirmed voxels not drawn; ``"as confirmed"``: no difference.

    Returns
    -------
    rgb (N, 3) uint8, and keep (N,) bool: the voxels to draw.
    """
    c = np.asarray(confirmed, bool)
    if rgb.shape != (c.size, 3):
        raise ValueError(f"Expected rgb of shape ({c.size}, 3), but got {rgb.shape}")
    if mode not in UNCONFIRMED_MODES:
        raise ValueError(f"Expected mode one of {UNCONFIRMED_MODES}, but got {mode!r}")
    out = np.array(rgb, np.uint8)
    keep = np.ones(c.size, bool)
    if mode == "pale":
        pale = rgb[~c].astype(np.float32) * (1 - PALE_MIX) + 255.0 * PALE_MIX
        out[~c] = np.clip(np.rint(pale), 0, 255).astype(np.uint8)
    elif mode == "hidden":
        keep = c.copy()
    return out, keep


def mapper_confidence(mapper: Any) -> np.ndarray | None:
    """``mapper.layer("confidence").states()`` when a confidence layer is attached, else None."""
    layers = getattr(mapper, "layers", ())
    conf = next((x for x in layers if getattr(x, "name", None) == "confidence"), None)
    return None if conf is None else conf.states()


def colormap_u8(name: str, n: int = 256) -> np.ndarray:
    """(n, 3) uint8 lookup table of a matplotlib colour map."""
    import matplotlib

    return (matplotlib.colormaps[name](np.linspace(0, 1, n))[:, :3] * 255).astype(np.uint8)


def rotation_to_wxyz(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of a rotation matrix (3, 3)."""
    R = np.asarray(R, np.float64)
    tr = R[0, 0] + R[1, 1] + R[2, 2]
    if tr > 0:
        s = math.sqrt(tr + 1.0) * 2
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = math.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2]) * 2
        q = [(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
    elif R[1, 1] > R[2, 2]:
        s = math.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2]) * 2
        q = [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s]
    else:
        s = math.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1]) * 2
        q = [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s]
    q = np.asarray(q)
    return q / np.linalg.norm(q)


def _unit_cube() -> tuple[np.ndarray, np.ndarray]:
    v = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)], np.float32)
    f = np.array(
        [
            [0, 2, 3],
            [0, 3, 1],
            [4, 5, 7],
            [4, 7, 6],
            [0, 1, 5],
            [0, 5, 4],
            [2, 6, 7],
            [2, 7, 3],
            [0, 4, 6],
            [0, 6, 2],
            [1, 3, 7],
            [1, 7, 5],
        ],
        np.uint32,
    )
    return v, f


def _fov_segments(spec: Any, n_arc: int = 24) -> np.ndarray:
    """(m, 2, 3) line segments outlining the field of view in the sonar frame."""
    az = np.linspace(spec.beam_edges_rad[0], spec.beam_edges_rad[-1], n_arc + 1)
    segs = []
    for el in (-0.5 * spec.vfov_rad, 0.0, 0.5 * spec.vfov_rad):
        for r in (spec.range_min_m, spec.range_max_m):
            p = r * np.stack(
                [np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.full_like(az, np.sin(el))], 1
            )
            segs += [np.stack([p[:-1], p[1:]], 1)]
    corners = []
    for a in (az[0], az[-1]):
        for el in (-0.5 * spec.vfov_rad, 0.5 * spec.vfov_rad):
            d = np.array([np.cos(el) * np.cos(a), np.cos(el) * np.sin(a), np.sin(el)])
            corners.append([spec.range_min_m * d, spec.range_max_m * d])
    segs.append(np.asarray(corners))
    return np.concatenate(segs).astype(np.float32)


def _box_segments(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    c = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)])
    p = lo + c * (hi - lo)
    e = [(0, 1), (2, 3), (4, 5), (6, 7), (0, 2), (1, 3), (4, 6), (5, 7), (0, 4), (1, 5), (2, 6), (3, 7)]
    return np.array([[p[a], p[b]] for a, b in e], np.float32)


class FanRenderer:
    """Polar image -> Cartesian fan (nearest cell), by a table computed once; RGBA uint8."""

    def __init__(self, spec: Any, height_px: int = 160) -> None:
        r_max = spec.range_max_m
        half = max(abs(spec.beam_edges_rad[0]), abs(spec.beam_edges_rad[-1]))
        y_half = r_max * math.sin(min(half, math.pi / 2))
        x_lo = min(0.0, r_max * math.cos(min(half, math.pi)))
        self.extent_m = (x_lo, r_max, -y_half, y_half)  # forward min, max; left min, max
        px = (r_max - x_lo) / height_px
        w = max(2, int(math.ceil(2 * y_half / px)))
        rows, cols = np.meshgrid(np.arange(height_px), np.arange(w), indexing="ij")
        x = r_max - (rows + 0.5) * px  # top row = far forward
        y = y_half - (cols + 0.5) * px  # left column = sonar's left (+y)
        r = np.hypot(x, y)
        th = np.arctan2(y, x)
        b = np.floor((r - spec.range_min_m) / spec.bin_size_m).astype(np.int64)
        j = np.searchsorted(spec.beam_edges_rad, th, side="right") - 1
        self.ok = (b >= 0) & (b < spec.n_bins) & (j >= 0) & (j < spec.n_beams)
        self.b = np.where(self.ok, b, 0)
        self.j = np.where(self.ok, j, 0)
        self.lut = colormap_u8("copper")

    def __call__(self, image_u8: np.ndarray) -> np.ndarray:
        v = image_u8[self.b, self.j]
        rgb = self.lut[v]
        # dark water is see-through in the 3-D view (the voxels behind the fan stay visible)
        a = np.where(self.ok, 70 + (v.astype(np.uint16) * 185) // 255, 0).astype(np.uint8)
        return np.concatenate([rgb, a[..., None]], -1)


def to_u8(image: np.ndarray) -> np.ndarray:
    a = np.asarray(image)
    if a.dtype == np.uint8:
        return a
    return np.clip(np.rint(np.nan_to_num(a.astype(np.float32)) * 255.0), 0, 255).astype(np.uint8)


class MapViewer:
    """A viser server showing one map being built (or played back).

    Parameters
    ----------
    spec : SonarSpec
    grid : GridSpec
    threshold : float
        Occupied if value >= this.
    host, port : str, int
        Bind address (``127.0.0.1``: this machine only; ``0.0.0.0``: every interface) and port.
    title : str
    map_every : int
        Refresh the map at most every this many pings ...
    map_interval_s, pose_interval_s : float
        ... and at most this often (wall time); images, pose and trajectory at most every
        ``pose_interval_s``.
    color_by : {"value", "height"}
    show_pings : bool
        Side panels for the current ping's polar and fan images (False for a saved map, which
        has no pings to show).
    budget : float
        Largest share of the wall time that viewing may take (see the module doc).
    """

    def __init__(
        self,
        spec: Any,
        grid: Any,
        threshold: float,
        *,
        host: str = "127.0.0.1",
        port: int = 8080,
        title: str = "gpumap",
        map_every: int = 10,
        map_interval_s: float = 0.5,
        pose_interval_s: float = 0.1,
        color_by: str = "height",
        budget: float = 0.05,
        show_pings: bool = True,
    ) -> None:
        viser = require_viser()
        self.spec, self.grid, self.threshold = spec, grid, float(threshold)
        self.map_every = max(1, int(map_every))
        self.map_interval_s, self.pose_interval_s = float(map_interval_s), float(pose_interval_s)
        self.server = viser.ViserServer(host=host, port=port, label=title, verbose=False)
        self.host, self.port = host, int(self.server.get_port())
        self._lock = threading.RLock()
        self._diff = MapDiff(threshold)
        self._q = np.zeros(grid.n_voxels, np.uint8)  # quantised value of occupied voxels, 0 = not
        self._conf: np.ndarray | None = None  # (n_voxels,) bool confirmed, once a layer came
        self._unconfirmed = None  # the GUI dropdown, made with the first layer
        self._blocks: dict[tuple[int, int, int], Any] = {}
        self._positions: list[np.ndarray] = []
        self.budget = float(budget)
        self._next_pose = -math.inf  # perf_counter time before which no pose/image update is sent
        self._next_map = -math.inf
        self.seconds_viewing = 0.0
        self._last_map_ping = -(10**9)
        self.n_pings = 0
        self.map_updates = 0
        self._fan = FanRenderer(spec, height_px=120)
        self._lut_img = colormap_u8("copper")
        self._cube = _unit_cube()
        self._color_by = color_by
        lo, hi = np.asarray(grid.min_corner_m, float), np.asarray(grid.max_corner_m, float)
        self._lo, self._hi = lo, hi

        sc = self.server.scene
        sc.set_up_direction("+z")
        sc.add_line_segments("/grid_box", _box_segments(lo, hi), colors=(150, 150, 150), line_width=1.0)
        sc.add_frame("/world", axes_length=0.2, axes_radius=0.006)
        self._map_root = sc.add_frame("/map", show_axes=False)  # the voxel blocks hang below it
        self._sonar = sc.add_frame("/sonar", axes_length=0.15, axes_radius=0.006, visible=False)
        sc.add_line_segments("/sonar/fov", _fov_segments(spec), colors=(255, 200, 40), line_width=2.0)
        x0, x1, y0, y1 = self._fan.extent_m
        self._fan_node = None
        self._fan_pose = dict(
            wxyz=rotation_to_wxyz(np.array([[0, 1, 0], [-1, 0, 0], [0, 0, 1.0]])),
            position=(0.5 * (x0 + x1), 0.5 * (y0 + y1), 0.0),
            render_width=y1 - y0,
            render_height=x1 - x0,
        )
        self._traj = None
        self._frame = [lo.copy(), hi.copy()]
        self._included: list[tuple[np.ndarray, np.ndarray]] = []

        @self.server.on_client_connect
        def _(client) -> None:
            self.aim(client)

        gui = self.server.gui
        self._status = gui.add_markdown(f"**{title}**  \nwaiting for the first ping")
        self._color = gui.add_dropdown("colour voxels by", ("value", "height"), initial_value=color_by)
        self._color.on_update(lambda _e: self._recolour())
        self._show = gui.add_checkbox("show voxels", True)

        @self._show.on_update
        def _(_e) -> None:  # hide the map to see what it hides: EKF landmarks, the truth's objects
            self._map_root.visible = bool(self._show.value)

        self._polar_gui = self._fan_gui = None
        if show_pings:
            blank = np.zeros((spec.n_bins // 4 or 1, spec.n_beams // 4 or 1, 3), np.uint8)
            self._polar_gui = gui.add_image(
                blank, label="ping (polar: range up, beams across)", format="jpeg"
            )
            self._fan_gui = gui.add_image(
                self._fan(np.zeros((spec.n_bins, spec.n_beams), np.uint8))[..., :3],
                label="ping (fan)",
                format="jpeg",
            )

    # ------------------------------------------------------------------ the map
    @property
    def url(self) -> str:
        host = "127.0.0.1" if self.host in ("0.0.0.0", "::", "") else self.host
        return f"http://{host}:{self.port}"

    def _colors(self, flat_idx: np.ndarray, q: np.ndarray) -> np.ndarray:
        if self._color.value == "height":
            k = flat_idx % self.grid.shape[2]
            t = (k + 0.5) / max(1, self.grid.shape[2])
            return colormap_u8("turbo")[np.clip((t * 255).astype(int), 0, 255)]
        lo = int(round(self.threshold * 255))
        t = (q.astype(np.float32) - lo) / max(1, 255 - lo)
        return colormap_u8("viridis")[np.clip((t * 255).astype(int), 0, 255)]

    def _send_block(self, key: tuple[int, int, int]) -> None:
        nx, ny, nz = self.grid.shape
        i0, j0, k0 = (key[0] * BLOCK, key[1] * BLOCK, key[2] * BLOCK)
        sub = self._q.reshape(nx, ny, nz)[i0 : i0 + BLOCK, j0 : j0 + BLOCK, k0 : k0 + BLOCK]
        loc = np.argwhere(sub > 0)
        name = f"/map/b_{key[0]}_{key[1]}_{key[2]}"
        old = self._blocks.pop(key, None)
        if old is not None:
            old.remove()
        if len(loc) == 0:
            return
        idx = loc + (i0, j0, k0)
        q = sub[tuple(loc.T)]
        flat = np.ravel_multi_index(tuple(idx.T), self.grid.shape)
        colors = self._colors(flat, q)
        if self._conf is not None:
            colors, keep = confidence_colours(colors, self._conf[flat], str(self._unconfirmed.value))
            idx, colors = idx[keep], colors[keep]
            if len(idx) == 0:
                return
        pos = self.grid.centers(idx).astype(np.float32)
        wxyz = np.broadcast_to(np.array([1, 0, 0, 0], np.float32), (len(idx), 4))
        v, f = self._cube
        self._blocks[key] = self.server.scene.add_batched_meshes_simple(
            name,
            v * np.float32(self.grid.voxel_size_m * 0.96),
            f,
            wxyz,
            pos,
            batched_colors=colors,
            lod="off",
            material="toon5",
            flat_shading=True,
            cast_shadow=False,
            receive_shadow=False,
        )

    def apply_diff(self, set_idx: np.ndarray, set_val: np.ndarray, clear_idx: np.ndarray,
                   touched_idx: np.ndarray | None = None) -> int:
        """Apply a map change (flat indices, uint8 values); re-send the changed blocks; their count.
        ``touched_idx``: more voxels whose look changed (their confidence)."""
        with self._lock:
            self._q[clear_idx] = 0
            self._q[set_idx] = set_val
            extra = [] if touched_idx is None else [np.asarray(touched_idx, set_idx.dtype)]
            changed = np.concatenate([set_idx, clear_idx, *extra])
            if changed.size == 0:
                return 0
            ijk = np.stack(np.unravel_index(changed, self.grid.shape), 1) // BLOCK
            keys = {tuple(int(x) for x in r) for r in np.unique(ijk, axis=0)}
            for key in keys:
                self._send_block(key)
            self.map_updates += 1
            return len(keys)

    def set_values(self, values: np.ndarray, confidence: np.ndarray | None = None) -> int:
        """Show the map ``values`` ((nx, ny, nz) float, NaN unknown): only changed blocks are sent.

        ``confidence``: the map's layer ((nx, ny, nz) uint8, ``MinMaxMapper.layer("confidence").states()``);
        from the first one on, unconfirmed occupied voxels are drawn as the GUI's "unconfirmed
        occupied voxels" choice says (pale by default), confirmed ones in full colour.
        """
        with self._lock:
            touched = None
            if confidence is not None:
                conf = np.asarray(confidence)
                if conf.shape != tuple(self.grid.shape):
                    raise ValueError(f"Expected a confidence layer of shape {tuple(self.grid.shape)}, but "
                                     f"got {conf.shape}")
                new = conf.ravel() == 3
                if self._conf is None:
                    self._add_confidence_gui()
                    touched = np.flatnonzero(self._q)  # every block shown so far changes look
                else:
                    touched = np.flatnonzero(new != self._conf)
                self._conf = new
            return self.apply_diff(*self._diff.update(values), touched)

    def _add_confidence_gui(self) -> None:
        gui = self.server.gui
        gui.add_markdown("**confidence**: full colour = confirmed (a view resolved the voxel in "
                         "elevation); pale = unconfirmed (only consistent with the pings: the "
                         "elevation stretch)")
        self._unconfirmed = gui.add_dropdown("unconfirmed occupied voxels", UNCONFIRMED_MODES,
                                             initial_value="pale")
        self._unconfirmed.on_update(lambda _e: self._recolour())

    def reset_map(self) -> None:
        with self._lock:
            for h in self._blocks.values():
                h.remove()
            self._blocks.clear()
            self._q[:] = 0
            self._diff = MapDiff(self.threshold)

    def _recolour(self) -> None:
        with self._lock:  # every block with an occupied voxel (a hidden one may have no handle)
            ijk = np.stack(np.unravel_index(np.flatnonzero(self._q), self.grid.shape), 1) // BLOCK
            keys = {tuple(int(x) for x in r) for r in np.unique(ijk, axis=0)} | set(self._blocks)
            for key in keys:
                self._send_block(key)

    # ------------------------------------------------------------------ per ping
    def show_ping(self, image: np.ndarray, T_W_S: np.ndarray, text: str = "") -> None:
        """Show one ping now: pose, field of view, fan, images, trajectory (no throttling)."""
        with self._lock:
            u8 = to_u8(image)
            T = np.asarray(T_W_S, np.float64)
            self._sonar.wxyz = rotation_to_wxyz(T[:3, :3])
            self._sonar.position = T[:3, 3]
            self._sonar.visible = True
            fan = self._fan(u8)
            if self._fan_node is None:
                self._fan_node = self.server.scene.add_image(
                    "/sonar/fan", fan, format="png", **self._fan_pose
                )
            else:
                self._fan_node.image = fan
            if self._polar_gui is not None:
                step = max(1, u8.shape[0] // 200)  # the panel shows ~300 px: no need for every bin
                self._polar_gui.image = self._lut_img[u8[::-step, ::step]]  # far range at the top
                self._fan_gui.image = fan[..., :3]
            if len(self._positions) >= 2:
                p = np.asarray(self._positions, np.float32)
                segs = np.stack([p[:-1], p[1:]], 1)
                if self._traj is None:
                    self._traj = self.server.scene.add_line_segments(
                        "/trajectory", segs, colors=(230, 60, 60), line_width=2.0
                    )
                else:
                    self._traj.points = segs
            if text:
                self._status.content = text

    def ping(self, image: np.ndarray, T_W_S: np.ndarray, mapper: Any = None, *, force: bool = False) -> None:
        """One ping of a live run: throttled updates of pose, images and map (see the module doc)."""
        k = self.n_pings
        self.n_pings += 1
        self._positions.append(np.asarray(T_W_S, np.float64)[:3, 3].copy())
        now = time.perf_counter()
        if force or now >= self._next_pose:
            n_occ = int(np.count_nonzero(self._q))
            self.show_ping(
                image,
                T_W_S,
                f"**ping {k + 1}**  \n{n_occ} occupied voxels "
                f"(value >= {self.threshold:g}) at {self.grid.voxel_size_m * 100:g} cm",
            )
            t = time.perf_counter()
            self.seconds_viewing += t - now
            self._next_pose = t + max(self.pose_interval_s - (t - now), (t - now) / self.budget)
            now = t
        if mapper is not None and (
            force or (k - self._last_map_ping >= self.map_every and now >= self._next_map)
        ):
            self._last_map_ping = k
            self.set_values(mapper.values(), mapper_confidence(mapper))
            t = time.perf_counter()
            self.seconds_viewing += t - now
            self._next_map = t + max(self.map_interval_s - (t - now), (t - now) / self.budget)

    def finish(self, mapper: Any = None, values: np.ndarray | None = None) -> None:
        """Show the final map and last ping state."""
        conf = None
        if values is None and mapper is not None:
            values, conf = mapper.values(), mapper_confidence(mapper)
        if values is not None:
            self.set_values(values, conf)
        self.frame_content()
        n_occ = int(np.count_nonzero(self._q))
        self._status.content = (
            f"**done: {self.n_pings} pings**  \n{n_occ} occupied voxels "
            f"(value >= {self.threshold:g}) at {self.grid.voxel_size_m * 100:g} cm"
        )

    def include(self, points: np.ndarray) -> None:
        """Widen the box that a newly connected browser's first view frames to hold ``points``."""
        p = np.asarray(points, np.float64).reshape(-1, 3)
        if len(p):
            self._frame = [np.minimum(self._frame[0], p.min(0)), np.maximum(self._frame[1], p.max(0))]
            self._included.append((p.min(0), p.max(0)))

    def frame_content(self) -> None:
        """Frame what there is to see (occupied voxels, the path, included points), not the whole grid."""
        boxes = list(self._included)
        idx = np.flatnonzero(self._q)
        if idx.size:
            c = self.grid.centers(np.stack(np.unravel_index(idx, self.grid.shape), 1))
            boxes.append((c.min(0), c.max(0)))
        if self._positions:
            p = np.asarray(self._positions)
            boxes.append((p.min(0), p.max(0)))
        if boxes:
            vs = self.grid.voxel_size_m
            self._frame = [np.min([b[0] for b in boxes], 0) - vs, np.max([b[1] for b in boxes], 0) + vs]

    def aim(self, client: Any) -> None:
        """Point ``client``'s camera at the framed box, from above and in front (z up)."""
        lo, hi = self._frame
        center = 0.5 * (lo + hi)
        span = float(np.max(hi - lo))
        d = np.array([-0.35, -1.0, 0.9])
        client.camera.up_direction = (0.0, 0.0, 1.0)
        client.camera.position = tuple(center + d / np.linalg.norm(d) * 0.95 * span)
        client.camera.look_at = tuple(center)

    # ------------------------------------------------------------------ extras
    def add_points(self, name: str, points: np.ndarray, colors: Any, size: float | None = None) -> None:
        """A point cloud (``(n, 3)`` metres) such as the demo's truth, drawn as squares one voxel wide."""
        self.include(points)
        self.server.scene.add_point_cloud(
            name,
            np.asarray(points, np.float32),
            colors,
            point_size=float(size or self.grid.voxel_size_m),
            point_shape="square",
        )

    def add_path(self, name: str, positions: np.ndarray, color: tuple[int, int, int]) -> None:
        """A polyline (``(n, 3)`` metres), e.g. the odometry or EKF path."""
        p = np.asarray(positions, np.float32)
        if len(p) >= 2:
            self.server.scene.add_line_segments(
                f"/paths/{name}", np.stack([p[:-1], p[1:]], 1), colors=color, line_width=2.0
            )

    def add_landmarks(
        self, positions: np.ndarray, covs: np.ndarray | None = None, sigmas: float = 3.0
    ) -> None:
        """EKF landmarks (``(n, 3)``) and, given ``covs`` ``(n, 3, 3)``, their ``sigmas``-sigma ellipsoids."""
        p = np.asarray(positions, np.float64).reshape(-1, 3)
        self.server.scene.add_point_cloud(
            "/landmarks/points", p.astype(np.float32), (255, 40, 200), point_size=0.02, point_shape="circle"
        )
        if covs is None:
            return
        for i, (c, C) in enumerate(zip(p, np.asarray(covs), strict=True)):
            w, V = np.linalg.eigh(0.5 * (C + C.T))
            if np.linalg.det(V) < 0:
                V[:, 0] = -V[:, 0]
            r = sigmas * np.sqrt(np.clip(w, 1e-12, None))
            self.server.scene.add_icosphere(
                f"/landmarks/ellipsoid_{i}",
                radius=1.0,
                color=(255, 40, 200),
                opacity=0.35,
                subdivisions=2,
                wxyz=rotation_to_wxyz(V),
                position=tuple(c),
                scale=tuple(float(x) for x in r),
            )

    def wait(self, seconds: float | None = None) -> None:
        """Keep serving for ``seconds`` (None: until Ctrl-C), then stop the server."""
        try:
            if seconds is None:
                while True:
                    time.sleep(3600)
            else:
                time.sleep(max(0.0, seconds))
        finally:
            self.close()

    def close(self) -> None:
        self.server.stop()
