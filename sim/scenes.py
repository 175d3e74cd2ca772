"""Simulated scenes: meshes with materials, analytic insides, features and a trajectory.

A :class:`Scene` is data: a list of :class:`SceneObject` (a triangle mesh, a material name
and an analytic ``contains`` for ground truth), a material table, point features with
integer ids (for the EKF), the grid to map into, the sonar and DVL mounts and the poses
along the trajectory. Scenes are built by small seeded functions registered in
:data:`SCENES`; the same seed gives the same scene, to the bit.

World frame of the ``tank`` scene: origin at the arm's base, x forward (away from the
base, toward the objects), y left, z up. The grid is the paper's 4 x 3 x 1 m workspace,
``GridSpec((-2, -1.5, -0.5), (2, 1.5, 0.5), s)``.

World frame of the ``circle`` scene: origin above the middle of the objects, z up; sand
at about z = -0.3 m over a 3 x 3 m patch, grid ``GridSpec((-1.6, -1.6, -0.5), (1.6, 1.6,
0.5), s)``. The sonar circles the objects from five stations (pitch and roll sweeps at
each), so that every object's far side is in the acoustic shadow in some views and faces
the sonar in others: the scene for measuring the shadow problem of min-max mapping.

World frame of the ``survey`` scene: z up, z = 0 at the sea surface; a 50 x 20 m seabed
(``[-25, 25] x [-10, 10]``) about 4 m down, grid ``GridSpec((-25, -10, -4.6), (25, 10,
-1.6), s)`` (the seabed band, 5 cm in the demo). A vehicle flies a lawnmower at 1.5 m depth
with the sonar pitched 30 deg down and a downward DVL: the scene for large, mostly empty
maps (:func:`survey_scene`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import trimesh

import gpumap

__all__ = [
    "Material",
    "SceneObject",
    "Scene",
    "SCENES",
    "make_scene",
    "tank_scene",
    "circle_scene",
    "circle_trajectory",
    "survey_scene",
    "lawnmower_trajectory",
    "survey_mounts",
    "BACKGROUND_OBJECTS",
    "pose_from_xyz_ypr",
    "box_scene",
    "circle_orbit_trajectory",
    "long_run_scene",
    "tank_sweep_trajectory",
]


@dataclass(frozen=True)
class Material:
    """Acoustic surface properties.

    Parameters
    ----------
    reflectivity : float
        Backscatter strength at normal incidence, in (0, 1] (1 = bare metal).
    cos_exponent : float
        ``k`` of the incidence law ``cos(theta_inc)**k``: 1 is Lambertian (rough sand),
        larger is more specular (smooth metal returns mostly near normal incidence).
    """

    reflectivity: float
    cos_exponent: float


# Relative values, chosen so that the objects stand out over sand as in the paper's Fig. 2.
MATERIALS: dict[str, Material] = {
    "sand": Material(0.35, 1.0),
    "wall": Material(0.55, 1.5),
    "rock": Material(0.75, 1.2),
    "plastic": Material(0.65, 2.0),  # tool basket (coated lattice)
    "metal": Material(1.0, 2.5),  # chain, pipe
    "target": Material(1.0, 1.0),  # analytic test targets
}


@dataclass
class SceneObject:
    """One object: its mesh (world frame), material and analytic inside test.

    Parameters
    ----------
    name : str
        Unique name; metrics report per object under it.
    mesh : trimesh.Trimesh
        Surface in the world frame, metres.
    material : str
        Key into the scene's material table.
    contains : callable or None
        ``contains(p_W: (n, 3) float) -> (n,) bool``, the solid's interior (analytic), or
        ``None`` for objects treated as surfaces only.
    solid_bounds : (2, 3) float or None
        World box holding the solid where it reaches beyond the mesh (the sand's solid goes
        down to the grid's floor below its surface mesh); None: the mesh's bounds.
    """

    name: str
    mesh: trimesh.Trimesh
    material: str
    contains: Callable[[np.ndarray], np.ndarray] | None = None
    solid_bounds: np.ndarray | None = None

    @property
    def bounds(self) -> np.ndarray:
        """(2, 3) world box holding the solid (``solid_bounds``, else the mesh's bounds)."""
        return self.mesh.bounds if self.solid_bounds is None else np.asarray(self.solid_bounds, float)


#: Object names that are background rather than obstacles (the default complement of
#: :attr:`Scene.small_objects`).
BACKGROUND_OBJECTS: tuple[str, ...] = ("sand", "walls")


@dataclass
class Scene:
    """A scene with everything the simulator, the mapper and the metrics need.

    Attributes
    ----------
    objects : list of SceneObject
    materials : dict of str -> Material
    grid : gpumap.GridSpec
    sonar_spec : gpumap.SonarSpec
    T_W_S : (n, 4, 4) float64
        Sonar poses along the trajectory.
    T_W_D : (n, 4, 4) float64
        DVL poses along the trajectory (DVL frame: x along its axis).
    feature_ids : (m,) int64
    features_W : (m, 3) float64
        Point features (on surfaces) with their ids, world frame, metres.
    small_objects : tuple of str
        Names of the objects proper (obstacles: chain, rock, ...), as opposed to the
        background (sand, walls); metrics report "objects" rates over these. Default: every
        object whose name is not in :data:`BACKGROUND_OBJECTS`, taken at construction.
    seabed_z_m : callable or None
        ``seabed_z_m(x, y) -> z``: the analytic height of the sand's surface (world, metres,
        broadcasting arrays), where a scene defines one (``survey``); None otherwise.
    sonar_params : dict of str -> float
        Keyword arguments for :class:`~.sonar.SonarSimulator` that suit the scene (a survey
        sonar at 8 m runs more gain than a tank sonar at 2 m); empty: the defaults.
    """

    name: str
    objects: list[SceneObject]
    grid: gpumap.GridSpec
    sonar_spec: gpumap.SonarSpec
    T_W_S: np.ndarray
    T_W_D: np.ndarray
    feature_ids: np.ndarray
    features_W: np.ndarray
    materials: dict[str, Material] = field(default_factory=lambda: dict(MATERIALS))
    seed: int = 0
    small_objects: tuple[str, ...] | None = None
    seabed_z_m: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None
    sonar_params: dict[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.small_objects is None:
            self.small_objects = tuple(n for n in self.object_names if n not in BACKGROUND_OBJECTS)
        else:
            self.small_objects = tuple(self.small_objects)
            unknown = sorted(set(self.small_objects) - set(self.object_names))
            if unknown:
                raise ValueError(
                    f"Expected small_objects among the object names {self.object_names}, but got {unknown}"
                )

    @property
    def object_names(self) -> list[str]:
        return [o.name for o in self.objects]

    def object(self, name: str) -> SceneObject:
        for o in self.objects:
            if o.name == name:
                return o
        raise KeyError(f"Expected an object named one of {self.object_names}, but got {name!r}")


# ------------------------------------------------------------------------------ geometry helpers
def _rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def _rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1.0, 0], [-s, 0, c]])


def _rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])


def pose_from_xyz_ypr(xyz: np.ndarray, yaw: float, pitch_down: float, roll: float = 0.0) -> np.ndarray:
    """(4, 4) pose with ``R = Rz(yaw) Ry(pitch_down) Rx(roll)``; positive pitch tilts x down."""
    T = np.eye(4)
    T[:3, :3] = _rot_z(yaw) @ _rot_y(pitch_down) @ _rot_x(roll)
    T[:3, 3] = xyz
    return T


def _box(
    center: np.ndarray, size: np.ndarray, R: np.ndarray | None = None
) -> tuple[trimesh.Trimesh, Callable]:
    T = np.eye(4)
    T[:3, 3] = center
    if R is not None:
        T[:3, :3] = R
    mesh = trimesh.creation.box(extents=size, transform=T)
    return mesh, _box_contains(np.asarray(center, float), np.asarray(size, float), T[:3, :3])


def _box_contains(c: np.ndarray, size: np.ndarray, R: np.ndarray) -> Callable:
    half = 0.5 * size

    def contains(p: np.ndarray) -> np.ndarray:
        q = (np.asarray(p) - c) @ R
        return np.all(np.abs(q) <= half, axis=-1)

    return contains


def _merged(name: str, parts: list[tuple[trimesh.Trimesh, Callable]], material: str) -> SceneObject:
    mesh = trimesh.util.concatenate([m for m, _ in parts])
    return SceneObject(name, mesh, material, _union([f for _, f in parts]))


def _union(fns: list[Callable]) -> Callable:
    def contains(p: np.ndarray) -> np.ndarray:
        out = np.zeros(len(p), bool)
        for f in fns:
            out |= f(p)
        return out

    return contains


def _cylinder(p0: np.ndarray, p1: np.ndarray, radius: float, sections: int = 24):
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    mesh = trimesh.creation.cylinder(radius=radius, segment=np.stack([p0, p1]), sections=sections)
    axis = p1 - p0
    L = float(np.linalg.norm(axis))
    u = axis / L

    def contains(p: np.ndarray) -> np.ndarray:
        d = np.asarray(p) - p0
        t = d @ u
        radial = np.linalg.norm(d - t[:, None] * u, axis=1)
        return (t >= 0) & (t <= L) & (radial <= radius)

    return mesh, contains


def _torus(center: np.ndarray, R_major: float, r_minor: float, Rot: np.ndarray):
    T = np.eye(4)
    T[:3, :3] = Rot
    T[:3, 3] = center
    mesh = trimesh.creation.torus(R_major, r_minor, major_sections=20, minor_sections=8, transform=T)

    def contains(p: np.ndarray) -> np.ndarray:
        q = (np.asarray(p) - center) @ Rot  # torus axis is local z
        rho = np.hypot(q[:, 0], q[:, 1])
        return (rho - R_major) ** 2 + q[:, 2] ** 2 <= r_minor**2

    return mesh, contains


# ------------------------------------------------------------------------------ shared objects
def _sand_object(
    h: Callable[[np.ndarray, np.ndarray], np.ndarray],
    x_range: tuple[float, float],
    y_range: tuple[float, float],
    z_bottom: float,
    step_m: float = 0.025,
) -> SceneObject:
    """"sand": the height field ``z = h(x, y)`` over a rectangle, solid from ``z_bottom`` up to it."""
    x0, x1 = x_range
    y0, y1 = y_range
    xs = np.arange(x0, x1 + 1e-9, step_m)
    ys = np.arange(y0, y1 + 1e-9, step_m)
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    V = np.stack([X, Y, h(X, Y)], -1).reshape(-1, 3)
    nx_, ny_ = X.shape
    ii, jj = np.meshgrid(np.arange(nx_ - 1), np.arange(ny_ - 1), indexing="ij")
    a = (ii * ny_ + jj).ravel()
    b, c, d = a + ny_, a + ny_ + 1, a + 1
    F = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    sand = trimesh.Trimesh(V, F, process=False)

    def sand_contains(p: np.ndarray) -> np.ndarray:
        p = np.asarray(p)
        inside = (p[:, 0] >= x0) & (p[:, 0] <= x1) & (p[:, 1] >= y0) & (p[:, 1] <= y1)
        return inside & (p[:, 2] <= h(p[:, 0], p[:, 1])) & (p[:, 2] >= z_bottom)

    # the solid reaches down to z_bottom, far below its surface mesh: truth must test it all
    solid = np.array([[x0, y0, z_bottom], [x1, y1, float(V[:, 2].max())]])
    return SceneObject("sand", sand, "sand", sand_contains, solid)


def _rock_object(
    rng: np.random.Generator, rc: np.ndarray, radii: np.ndarray, name: str = "rock"
) -> SceneObject:
    """Star-shaped blob at ``rc``: semi-axes ``radii`` modulated by a few seeded smooth harmonics."""
    kdir = rng.normal(size=(5, 3))
    kph = rng.uniform(0, 2 * np.pi, 5)
    kamp = rng.uniform(0.03, 0.08, 5)
    Rrock = _rot_z(rng.uniform(0, np.pi))

    def bump(u: np.ndarray) -> np.ndarray:
        return 1.0 + np.sin(u @ kdir.T * 2.0 + kph) @ kamp

    ico = trimesh.creation.icosphere(subdivisions=3)
    u = ico.vertices / np.linalg.norm(ico.vertices, axis=1, keepdims=True)
    rock_V = rc + ((u * bump(u)[:, None]) * radii) @ Rrock.T
    rock = trimesh.Trimesh(rock_V, ico.faces, process=False)

    def rock_contains(p: np.ndarray) -> np.ndarray:
        q = ((np.asarray(p) - rc) @ Rrock) / radii
        n = np.linalg.norm(q, axis=1)
        uq = q / np.maximum(n, 1e-12)[:, None]
        return n <= bump(uq)

    return SceneObject(name, rock, "rock", rock_contains)


# ------------------------------------------------------------------------------ the tank
def _sand_height_fn(rng: np.random.Generator, z0: float) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    """Seeded smooth sand surface: ripples of a few mm plus low bumps of about 1 cm."""
    k = rng.uniform(6.0, 14.0, size=(4, 2)) * rng.choice([-1, 1], size=(4, 2))
    ph = rng.uniform(0, 2 * np.pi, 4)
    amp = np.array([0.004, 0.003, 0.006, 0.005])

    def h(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        z = np.full(np.broadcast(x, y).shape, z0)
        for i in range(4):
            z = z + amp[i] * np.sin(k[i, 0] * x + k[i, 1] * y + ph[i])
        return z

    return h


TANK = {
    "floor_z_m": -0.42,  # mean sand surface
    "rim_z_m": 0.18,  # 0.6 m deep tank
    "x_back_m": -0.9,
    "x_front_m": 1.75,  # inner faces of the walls
    "y_half_m": 1.3,
    "wall_m": 0.08,  # wall thickness
}


def tank_scene(seed: int = 0, voxel_size_m: float = 0.03, n_pitch: int = 16, n_move: int = 24) -> Scene:
    """The paper's test tank (Sections III-IV) inside the 4 x 3 x 1 m workspace.

    A 0.6 m deep tank (sand floor at z = -0.42 m, rim at +0.18 m, inner walls at
    x = -0.9 / 1.75 m and y = +-1.3 m) holding a chain of 14 torus links, a rock (a seeded,
    star-shaped blob of about 28 x 22 x 18 cm), a tool basket (open lattice box of
    40 x 30 x 20 cm of 1 cm bars) and a thin metal pipe (2.5 cm across, 0.8 m long) lying on
    the sand. The arm's base is at the origin; the sonar sits on the wrist pitched 12.8 deg
    down and the DVL 60 deg down (paper, Fig. 1). The trajectory first pitches the sonar in
    place (``n_pitch`` pings from 12.8 to 52.8 deg down), then moves the wrist along an arc
    across the tank while pitching and yawing toward the objects (``n_move`` pings).
    """
    rng = np.random.default_rng(seed)
    t = TANK
    z_rim, z_floor = t["rim_z_m"], t["floor_z_m"]
    x0, x1, yh, w = t["x_back_m"], t["x_front_m"], t["y_half_m"], t["wall_m"]
    grid = gpumap.GridSpec((-2.0, -1.5, -0.5), (2.0, 1.5, 0.5), voxel_size_m)
    zb = grid.min_corner_m[2]
    objects: list[SceneObject] = []

    # Sand floor: a height field over the tank's inside; solid below the surface.
    h = _sand_height_fn(rng, z_floor)
    objects.append(_sand_object(h, (x0, x1), (-yh, yh), zb - 1.0))

    # Walls from below the grid up to the rim.
    zc, zh = 0.5 * (z_rim + zb - 0.1), z_rim - (zb - 0.1)
    walls = [
        ((x1 + w / 2, 0, zc), (w, 2 * yh + 2 * w, zh)),
        ((x0 - w / 2, 0, zc), (w, 2 * yh + 2 * w, zh)),
        ((0.5 * (x0 + x1), yh + w / 2, zc), (x1 - x0, w, zh)),
        ((0.5 * (x0 + x1), -yh - w / 2, zc), (x1 - x0, w, zh)),
    ]
    parts = [_box(np.array(cc), np.array(sz)) for cc, sz in walls]
    objects.append(_merged("walls", parts, "wall"))

    # Chain: links alternate flat / upright along a gentle S-curve on the sand.
    R_link, r_link, n_links = 0.025, 0.006, 14
    pitch_link = 2 * (R_link - r_link)
    s = np.arange(n_links) * pitch_link
    path = np.stack([0.75 + 0.85 * s, -0.55 + 0.25 * s + 0.05 * np.sin(6 * s)], 1)
    tang = np.gradient(path, axis=0)
    parts = []
    for i in range(n_links):
        yaw = math.atan2(tang[i, 1], tang[i, 0])
        if i % 2 == 0:  # flat: torus axis z, stretched along the path by the yaw
            Rot = _rot_z(yaw)
            zc_ = float(h(path[i, 0], path[i, 1])) + r_link
        else:  # upright: torus axis horizontal, perpendicular to the path
            Rot = _rot_z(yaw) @ _rot_x(math.pi / 2)
            zc_ = float(h(path[i, 0], path[i, 1])) + R_link + r_link - 0.004
        parts.append(_torus(np.array([path[i, 0], path[i, 1], zc_]), R_link, r_link, Rot))
    objects.append(_merged("chain", parts, "metal"))

    # Rock: star-shaped blob, radius modulated by a few seeded smooth harmonics.
    rock = _rock_object(rng, np.array([1.05, 0.32, z_floor + 0.06]), np.array([0.14, 0.11, 0.09]))
    rock_V = rock.mesh.vertices
    objects.append(rock)

    # Tool basket: open-top lattice box of 1 cm bars.
    bc = np.array([0.62, 0.55, float(h(0.62, 0.55))])
    L, W, H, bar = 0.40, 0.30, 0.20, 0.01
    Rb = _rot_z(math.radians(15))
    bars = []
    for x in np.linspace(-L / 2, L / 2, 5):  # posts and ribs on the long sides
        for y in (-W / 2, W / 2):
            bars.append(((x, y, H / 2), (bar, bar, H)))
    for y in np.linspace(-W / 2, W / 2, 4)[1:-1]:  # ribs on the short sides
        for x in (-L / 2, L / 2):
            bars.append(((x, y, H / 2), (bar, bar, H)))
    for z in (bar / 2, H / 2, H - bar / 2):  # horizontal rims
        for y in (-W / 2, W / 2):
            bars.append(((0, y, z), (L + bar, bar, bar)))
        for x in (-L / 2, L / 2):
            bars.append(((x, 0, z), (bar, W + bar, bar)))
    for y in np.linspace(-W / 2, W / 2, 4)[1:-1]:  # bottom mesh
        bars.append(((0, y, bar / 2), (L, bar, bar)))
    parts = [_box(bc + Rb @ np.array(cc), np.array(sz), Rb) for cc, sz in bars]
    objects.append(_merged("basket", parts, "plastic"))

    # Thin metal pipe lying on the sand: the hard case for false negatives.
    r_pipe = 0.0125
    pa, pb = np.array([1.30, -0.30]), np.array([1.42, 0.48])
    za = float(h(*pa)) + r_pipe
    zb_ = float(h(*pb)) + r_pipe
    p0, p1 = np.array([*pa, za]), np.array([*pb, zb_])
    pipe, pipe_contains = _cylinder(p0, p1, r_pipe)
    objects.append(SceneObject("pipe", pipe, "metal", pipe_contains))

    # Features (on surfaces): basket corners, pipe ends, rock extremes, upright chain link
    # tops, the front wall's rim and its foot.
    feats = []
    for x in (-L / 2 - bar / 2, L / 2 + bar / 2):
        for y in (-W / 2 - bar / 2, W / 2 + bar / 2):
            for z in (0.0, H):
                feats.append(bc + Rb @ np.array([x, y, z]))
    feats += [p0 + [0, 0, r_pipe], p1 + [0, 0, r_pipe], 0.5 * (p0 + p1) + [0, 0, r_pipe]]
    for dirv in ([0, 0, 1], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0]):
        feats.append(rock_V[int(np.argmax(rock_V @ np.array(dirv, float)))])
    for i in range(1, n_links, 2):
        feats.append(np.array([path[i, 0], path[i, 1], float(h(*path[i])) + 2 * R_link + r_link - 0.004]))
    for y in (-0.9, -0.45, 0.0, 0.45, 0.9):
        feats.append(np.array([x1, y, z_rim]))
        feats.append(np.array([x1, y, float(h(x1, y))]))
    features_W = np.array(feats, dtype=np.float64)
    feature_ids = np.arange(len(features_W), dtype=np.int64) + 100

    T_W_S, T_W_D = _tank_trajectory(n_pitch, n_move)
    spec = gpumap.SonarSpec.uniform(hfov_deg=130, vfov_deg=20, n_beams=512, n_bins=400,
                                    range_min_m=0.1, range_max_m=2.0)
    return Scene("tank", objects, grid, spec, T_W_S, T_W_D, feature_ids, features_W, seed=seed,
                 small_objects=("chain", "rock", "basket", "pipe"))


SONAR_MOUNT_PITCH_DEG = 12.8  # paper, Fig. 1
DVL_MOUNT_PITCH_DEG = 60.0


def mounts() -> tuple[np.ndarray, np.ndarray]:
    """``(T_wrist_S, T_wrist_D)``: sonar and DVL on the wrist (wrist x forward, level)."""
    T_wrist_S = pose_from_xyz_ypr(np.array([0.06, 0.0, 0.0]), 0.0, math.radians(SONAR_MOUNT_PITCH_DEG))
    T_wrist_D = pose_from_xyz_ypr(np.array([0.02, 0.0, -0.06]), 0.0, math.radians(DVL_MOUNT_PITCH_DEG))
    return T_wrist_S, T_wrist_D


def _tank_trajectory(n_pitch: int, n_move: int) -> tuple[np.ndarray, np.ndarray]:
    T_wrist_S, T_wrist_D = mounts()
    wrists = []
    home = np.array([0.15, 0.0, 0.05])
    for a in np.linspace(0.0, 40.0, n_pitch):  # pitch in place
        wrists.append(pose_from_xyz_ypr(home, 0.0, math.radians(a)))
    target = np.array([1.05, 0.0])
    for s in np.linspace(0.0, 1.0, n_move):  # arc across the tank, lower, looking at the objects
        y = -0.55 + 1.1 * s
        x = 0.25 + 0.15 * math.sin(math.pi * s)
        z = 0.05 - 0.15 * math.sin(math.pi * s)
        yaw = math.atan2(target[1] - y, target[0] - x)
        pitch = math.radians(12.0 + 14.0 * (0.5 + 0.5 * math.cos(3 * math.pi * s)))
        wrists.append(pose_from_xyz_ypr(np.array([x, y, z]), yaw, pitch))
    W = np.array(wrists)
    return W @ T_wrist_S, W @ T_wrist_D


# ------------------------------------------------------------------------------ circling the objects
CIRCLE = {
    "floor_z_m": -0.3,  # mean sand surface
    "sand_half_m": 1.5,  # sand over [-1.5, 1.5]^2
}


def circle_scene(
    seed: int = 0,
    voxel_size_m: float = 0.03,
    n_stations: int = 5,
    n_pitch: int = 7,
    n_roll: int = 5,
    radius_m: float = 1.2,
    height_m: float = 0.4,
    pitch_deg: tuple[float, float] = (10.0, 40.0),
    roll_deg: float = 20.0,
) -> Scene:
    """Objects on sand seen from ``n_stations`` sides: the acoustic-shadow test scene.

    A 3 x 3 m patch of sand (mean surface z = -0.3 m, seeded ripples, solid below) holds,
    within about 0.45 m of the origin: a "box" of 30 x 20 x 25 cm (yawed 25 deg, sunk
    1 cm), a "rock" (seeded star-shaped blob of about 26 x 20 x 16 cm, partly buried), a
    thin metal "pipe" (2.8 cm across, 0.8 m long) lying on the sand and an upright "post"
    (8 cm across, 35 cm tall). The sonar visits ``n_stations`` stations evenly spaced on a
    circle of ``radius_m`` around the origin, ``height_m`` above the mean sand, yawed to
    look at the origin (the first station is at -y, the stations then go counter-clockwise).
    At each it sweeps the pitch over ``pitch_deg`` (``n_pitch`` pings, level) and then the
    roll over ``+-roll_deg`` (``n_roll`` pings, pitched down to the origin), so with five
    stations every object is seen from opposite sides (144 deg apart) and its far side is
    in the acoustic shadow in some views and faces the sonar in others. ``T_W_D`` equals
    ``T_W_S`` (no DVL in this scene). The seed sets the sand ripples and the rock's shape.
    """
    if n_stations < 1 or n_pitch < 1 or n_roll < 0:
        raise ValueError(
            f"Expected n_stations >= 1, n_pitch >= 1 and n_roll >= 0, but got n_stations={n_stations}, "
            f"n_pitch={n_pitch}, n_roll={n_roll}"
        )
    rng = np.random.default_rng(seed)
    z_floor, half = CIRCLE["floor_z_m"], CIRCLE["sand_half_m"]
    grid = gpumap.GridSpec((-1.6, -1.6, -0.5), (1.6, 1.6, 0.5), voxel_size_m)
    h = _sand_height_fn(rng, z_floor)
    objects = [_sand_object(h, (-half, half), (-half, half), grid.min_corner_m[2] - 1.0)]

    def ground(xy: np.ndarray) -> float:
        return float(h(xy[0], xy[1]))

    # Box: 30 x 20 x 25 cm, yawed, its bottom 1 cm into the sand.
    box_c, box_size, box_R = np.array([0.30, 0.25]), np.array([0.30, 0.20, 0.25]), _rot_z(math.radians(25))
    box_bottom = ground(box_c) - 0.01
    box_center = np.array([*box_c, box_bottom + 0.5 * box_size[2]])
    mesh, contains = _box(box_center, box_size, box_R)
    objects.append(SceneObject("box", mesh, "plastic", contains))

    # Rock: a blob about a third buried.
    rock_c = np.array([-0.35, 0.20])
    rock = _rock_object(rng, np.array([*rock_c, ground(rock_c) + 0.05]), np.array([0.13, 0.10, 0.08]))
    objects.append(rock)

    # Pipe: 2.8 cm across, 0.8 m long, lying on the sand.
    r_pipe, pipe_c, pipe_yaw = 0.014, np.array([0.0, -0.25]), math.radians(10)
    u = 0.4 * np.array([math.cos(pipe_yaw), math.sin(pipe_yaw)])
    pa, pb = pipe_c - u, pipe_c + u
    p0, p1 = np.array([*pa, ground(pa) + r_pipe]), np.array([*pb, ground(pb) + r_pipe])
    mesh, contains = _cylinder(p0, p1, r_pipe)
    objects.append(SceneObject("pipe", mesh, "metal", contains))

    # Post: upright cylinder from 5 cm under the sand to 35 cm above it.
    r_post, post_c, post_h = 0.04, np.array([-0.05, 0.12]), 0.35
    post_top = np.array([*post_c, ground(post_c) + post_h])
    mesh, contains = _cylinder(post_top - [0, 0, post_h + 0.05], post_top, r_post)
    objects.append(SceneObject("post", mesh, "plastic", contains))

    # Features on surfaces: box corners (top, and where the vertical edges meet the sand),
    # pipe ends and middle (top), rock extremes, the post's top centre and rim.
    feats = []
    for x in (-0.5, 0.5):
        for y in (-0.5, 0.5):
            top = box_center + box_R @ (box_size * np.array([x, y, 0.5]))
            feats.append(top)
            feats.append(np.array([*top[:2], max(ground(top[:2]), box_bottom)]))
    feats += [p0 + [0, 0, r_pipe], p1 + [0, 0, r_pipe], 0.5 * (p0 + p1) + [0, 0, r_pipe]]
    rock_V = rock.mesh.vertices
    for dirv in ([0, 0, 1], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0]):
        feats.append(rock_V[int(np.argmax(rock_V @ np.array(dirv, float)))])
    feats.append(post_top)
    for a in np.arange(4) * (math.pi / 2):
        feats.append(post_top + r_post * np.array([math.cos(a), math.sin(a), 0.0]))
    features_W = np.array(feats, dtype=np.float64)
    feature_ids = np.arange(len(features_W), dtype=np.int64) + 100

    T_W_S = circle_trajectory(n_stations, n_pitch, n_roll, radius_m, z_floor + height_m, pitch_deg, roll_deg)
    spec = gpumap.SonarSpec.uniform(hfov_deg=130, vfov_deg=20, n_beams=512, n_bins=400,
                                    range_min_m=0.1, range_max_m=2.0)
    return Scene("circle", objects, grid, spec, T_W_S, T_W_S.copy(), feature_ids, features_W, seed=seed,
                 small_objects=("box", "rock", "pipe", "post"))


def circle_trajectory(
    n_stations: int,
    n_pitch: int,
    n_roll: int,
    radius_m: float,
    z_m: float,
    pitch_deg: tuple[float, float] = (10.0, 40.0),
    roll_deg: float = 20.0,
) -> np.ndarray:
    """(n_stations * (n_pitch + n_roll), 4, 4) sonar poses circling the origin at height ``z_m``.

    Station ``s`` is at azimuth ``-90 + 360 s / n_stations`` deg (the first at -y), yawed
    toward the z axis. It first pitches from ``pitch_deg[0]`` to ``pitch_deg[1]`` down
    (level), then rolls from ``-roll_deg`` to ``+roll_deg`` pitched down to the point of
    the mean sand below the origin (``atan2(z_m + 0.3, radius_m)``).
    """
    poses = []
    look_down = math.atan2(z_m - CIRCLE["floor_z_m"], radius_m)
    for k in range(n_stations):
        a = math.radians(-90.0) + 2 * math.pi * k / n_stations
        xyz = np.array([radius_m * math.cos(a), radius_m * math.sin(a), z_m])
        yaw = a + math.pi
        for p in np.linspace(*pitch_deg, n_pitch):
            poses.append(pose_from_xyz_ypr(xyz, yaw, math.radians(p)))
        for r in np.linspace(-roll_deg, roll_deg, n_roll):
            poses.append(pose_from_xyz_ypr(xyz, yaw, look_down, math.radians(r)))
    return np.array(poses)


# ------------------------------------------------------------------------------ long runs at a sonar's rate
def tank_sweep_trajectory(n_pings: int, pass_pings: int = 200,
                          nod_pings: int = 20) -> tuple[np.ndarray, np.ndarray]:
    """``(T_W_S, T_W_D)``, (n_pings, 4, 4) each: the arm sweeping the tank at a sonar's own rate.

    The wrist goes back and forth along the arc of :func:`tank_scene`'s trajectory (one pass
    every ``pass_pings`` pings: about 6 mm per ping, as the real OASIS arm between frames),
    yawed toward the objects, while nodding its pitch between 12 and 26 deg with a period of
    ``nod_pings`` pings (about 1.7 deg per ping): a path that keeps looking at the scene for as
    long as it runs.
    """
    if n_pings < 1 or pass_pings < 2 or nod_pings < 2:
        raise ValueError(f"Expected n_pings >= 1, pass_pings >= 2 and nod_pings >= 2, but got {n_pings}, "
                         f"{pass_pings}, {nod_pings}")
    T_wrist_S, T_wrist_D = mounts()
    target = np.array([1.05, 0.0])
    wrists = []
    for k in range(n_pings):
        u = (k / pass_pings) % 2.0
        s = u if u <= 1.0 else 2.0 - u  # triangle wave over the arc
        y = -0.55 + 1.1 * s
        x = 0.25 + 0.15 * math.sin(math.pi * s)
        z = 0.05 - 0.15 * math.sin(math.pi * s)
        yaw = math.atan2(target[1] - y, target[0] - x)
        pitch = math.radians(12.0 + 14.0 * (0.5 + 0.5 * math.cos(2 * math.pi * k / nod_pings)))
        wrists.append(pose_from_xyz_ypr(np.array([x, y, z]), yaw, pitch))
    W = np.array(wrists)
    return W @ T_wrist_S, W @ T_wrist_D


def circle_orbit_trajectory(n_pings: int, n_orbits: float = 2.0, radius_m: float = 1.2, height_m: float = 0.4,
                            nod_pings: int = 30, roll_pings: int = 70) -> np.ndarray:
    """(n_pings, 4, 4) sonar poses orbiting :func:`circle_scene`'s objects at a sonar's rate.

    ``n_orbits`` turns of a circle of ``radius_m`` around the origin, ``height_m`` above the
    mean sand, yawed at the origin, the pitch nodding between 10 and 40 deg down (period
    ``nod_pings``) and the roll swinging +-10 deg (period ``roll_pings``): every object is seen
    from every side, again and again.
    """
    if n_pings < 1 or n_orbits <= 0:
        raise ValueError(f"Expected n_pings >= 1 and n_orbits > 0, but got {n_pings}, {n_orbits}")
    z = CIRCLE["floor_z_m"] + height_m
    poses = []
    for k in range(n_pings):
        a = math.radians(-90.0) + 2 * math.pi * n_orbits * k / n_pings
        xyz = np.array([radius_m * math.cos(a), radius_m * math.sin(a), z])
        pitch = 25.0 - 15.0 * math.cos(2 * math.pi * k / nod_pings)
        roll = 10.0 * math.sin(2 * math.pi * k / roll_pings)
        poses.append(pose_from_xyz_ypr(xyz, a + math.pi, math.radians(pitch), math.radians(roll)))
    return np.array(poses)


def long_run_scene(name: str, n_pings: int, voxel_size_m: float = 0.03, seed: int = 0) -> Scene:
    """The ``tank`` or ``circle`` scene with a trajectory of ``n_pings`` pings at a sonar's rate
    (:func:`tank_sweep_trajectory`, :func:`circle_orbit_trajectory`) instead of its short one."""
    if name == "tank":
        scene = tank_scene(seed=seed, voxel_size_m=voxel_size_m)
        T_W_S, T_W_D = tank_sweep_trajectory(n_pings)
    elif name == "circle":
        scene = circle_scene(seed=seed, voxel_size_m=voxel_size_m)
        T_W_S = circle_orbit_trajectory(n_pings)
        T_W_D = T_W_S.copy()
    else:
        raise ValueError(f"Expected a scene name in ['circle', 'tank'] for a long run, but got {name!r}")
    return dataclasses.replace(scene, T_W_S=T_W_S, T_W_D=T_W_D)


# ------------------------------------------------------------------------------ a seabed survey
SURVEY = {
    "x_half_m": 25.0,  # seabed over [-25, 25] x [-10, 10]
    "y_half_m": 10.0,
    "floor_z_m": -4.0,  # mean seabed: 4 m of water below the surface at z = 0
    "vehicle_z_m": -1.5,  # 2.5 m above the mean seabed
    "sonar_pitch_deg": 30.0,  # below horizontal
    "mesh_step_m": 0.1,  # heightfield vertex spacing: 501 x 201 vertices, 200,000 triangles
}


def _seabed_height_fns(
    rng: np.random.Generator, z0: float
) -> tuple[Callable[[np.ndarray, np.ndarray], np.ndarray], Callable[[np.ndarray, np.ndarray], np.ndarray]]:
    """Seeded seabed ``(h, h_smooth)``: undulations of about 0.25 m plus sand ripples.

    ``h_smooth`` is the undulating floor alone (four long waves, 12-30 m, amplitudes 12, 8, 6
    and 5 cm); ``h`` adds ripples: crests roughly across a seeded direction, 0.6-0.9 m apart,
    3 cm high with a slowly varying height and a gently sinuous crest line, plus a 1 cm
    cross ripple of 0.45 m.
    """
    lam = rng.uniform(12.0, 30.0, 4)
    ang = rng.uniform(0.0, 2 * np.pi, 4)
    k_long = (2 * np.pi / lam)[:, None] * np.stack([np.cos(ang), np.sin(ang)], 1)
    ph_long = rng.uniform(0, 2 * np.pi, 4)
    amp_long = np.array([0.12, 0.08, 0.06, 0.05])
    crest = rng.uniform(0.0, np.pi)
    k_rip = 2 * np.pi / rng.uniform(0.6, 0.9)
    u_rip = np.array([np.cos(crest), np.sin(crest)])
    u_cross = np.array([-u_rip[1], u_rip[0]])
    k_cross = 2 * np.pi / 0.45
    ph_rip = rng.uniform(0, 2 * np.pi, 4)

    def h_smooth(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
        z = np.full(np.broadcast(x, y).shape, z0)
        for i in range(4):
            z = z + amp_long[i] * np.sin(k_long[i, 0] * x + k_long[i, 1] * y + ph_long[i])
        return z

    def h(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
        a = x * u_rip[0] + y * u_rip[1]  # across the crests
        b = x * u_cross[0] + y * u_cross[1]  # along them
        wiggle = 0.6 * np.sin(0.35 * b + ph_rip[0])  # sinuous crest lines
        height = 0.03 * (0.75 + 0.25 * np.sin(0.2 * b + 0.13 * a + ph_rip[1]))
        z = h_smooth(x, y) + height * np.sin(k_rip * a + wiggle + ph_rip[2])
        return z + 0.01 * np.sin(k_cross * b + 0.3 * a + ph_rip[3])

    return h, h_smooth


def _union_culled(parts: list[tuple[trimesh.Trimesh, Callable]], pad_m: float = 1e-6) -> Callable:
    """Union of the parts' ``contains``, each tested only on the points inside its mesh's box.

    For objects made of many small parts spread over a large area (rocks, pipeline
    segments), where :func:`_union` would test every part on every point of the whole box.
    """
    boxes = [(m.bounds[0] - pad_m, m.bounds[1] + pad_m) for m, _ in parts]
    fns = [f for _, f in parts]

    def contains(p: np.ndarray) -> np.ndarray:
        p = np.asarray(p)
        out = np.zeros(len(p), bool)
        for (lo, hi), f in zip(boxes, fns, strict=True):
            idx = np.flatnonzero(np.all((p >= lo) & (p <= hi), axis=1))
            if len(idx):
                out[idx] |= f(p[idx])
        return out

    return contains


def survey_scene(
    seed: int = 0,
    voxel_size_m: float = 0.05,
    n_lines: int = 4,
    line_spacing_m: float = 5.0,
    line_half_m: float = 22.0,
    ping_spacing_m: float = 1.0,
    n_rocks: int = 14,
    wobble_deg: float = 1.5,
) -> Scene:
    """A vehicle surveys 50 x 20 m of seabed in a lawnmower pattern: the large-map scene.

    World frame: z up, z = 0 at the sea surface; the seabed covers ``[-25, 25] x [-10, 10]``
    m at a mean depth of 4 m (``SURVEY["floor_z_m"]``), undulating by about 0.25 m with
    3 cm sand ripples (seeded, :func:`_seabed_height_fns`; a heightfield mesh at 10 cm, solid
    down to below the grid). On it: ``n_rocks`` seeded star-shaped rocks of 0.4-1.4 m, partly
    buried, merged into one object "rocks"; a pipeline "pipe" of 30 cm diameter across the
    whole area (straight in plan, following the seabed's undulation in 2.4 m segments, its
    lower 7-11 cm buried); and a "wreck": a hull box of 7 x 2.4 x 1.3 m (yawed 35 deg, rolled
    5 deg, sunk 0.3 m) with a deckhouse of 2.2 x 1.6 x 0.6 m, its top about 1.6 m above the
    seabed. Objects are placed at fixed spots; the seed sets the seabed and the rocks.

    The vehicle flies at 1.5 m depth (about 2.5 m altitude) along ``n_lines`` lines parallel
    to x, ``line_spacing_m`` apart and centred on y = 0, over ``x in [-line_half_m,
    line_half_m]``, alternating direction, joined by half-circle turns; a ping every
    ``ping_spacing_m`` of path (200 pings with the defaults), with a gentle roll and pitch
    wobble of ``wobble_deg``. The sonar (130 x 20 deg, 512 beams, 400 bins over 0.5-8 m)
    looks ahead pitched 30 deg down, so each line sees a band about 12 m wide and the bands
    of neighbouring lines overlap. The DVL looks straight down (``T_W_D``: its x axis to
    -z). The grid is the seabed band ``[-25, 25] x [-10, 10] x [-4.6, -1.6]`` m (the
    water above the vehicle's path and the rock far below the seabed hold nothing the sonar
    can see). ``Scene.seabed_z_m`` is the seabed's analytic height.
    """
    if n_lines < 1 or line_spacing_m <= 0 or line_half_m <= 0 or ping_spacing_m <= 0 or n_rocks < 0:
        raise ValueError(
            f"Expected n_lines >= 1, line_spacing_m > 0, line_half_m > 0, ping_spacing_m > 0 and "
            f"n_rocks >= 0, but got n_lines={n_lines}, line_spacing_m={line_spacing_m}, "
            f"line_half_m={line_half_m}, ping_spacing_m={ping_spacing_m}, n_rocks={n_rocks}"
        )
    c = SURVEY
    xh, yh, z0 = c["x_half_m"], c["y_half_m"], c["floor_z_m"]
    rng = np.random.default_rng(seed)
    grid = gpumap.GridSpec((-xh, -yh, z0 - 0.6), (xh, yh, c["vehicle_z_m"] - 0.1), voxel_size_m)
    h, h_smooth = _seabed_height_fns(rng, z0)
    objects = [_sand_object(h, (-xh, xh), (-yh, yh), grid.min_corner_m[2] - 1.0, step_m=c["mesh_step_m"])]

    # Wreck: a hull box, yawed and listing, sunk 0.3 m, with a deckhouse aft of the middle.
    wc = np.array([7.0, -3.0])
    hull_size, sink = np.array([7.0, 2.4, 1.3]), 0.3
    R_w = _rot_z(math.radians(35.0)) @ _rot_x(math.radians(5.0))
    hull_c = np.array([*wc, float(h_smooth(*wc)) - sink + 0.5 * hull_size[2]])
    house_size = np.array([2.2, 1.6, 0.6])
    house_c = hull_c + R_w @ np.array([-1.4, 0.0, 0.5 * (hull_size[2] + house_size[2])])
    wreck = _merged("wreck", [_box(hull_c, hull_size, R_w), _box(house_c, house_size, R_w)], "metal")
    objects.append(wreck)

    # Pipeline: straight in plan across the area, its axis 8 cm above the smooth seabed.
    r_pipe = 0.15
    pa, pb = np.array([-xh + 0.5, 6.0]), np.array([xh - 0.5, -1.0])
    n_seg = int(math.ceil(np.linalg.norm(pb - pa) / 2.4))
    knots = [pa + (pb - pa) * t for t in np.linspace(0.0, 1.0, n_seg + 1)]
    axis = [np.array([*q, float(h_smooth(*q)) + r_pipe - 0.07]) for q in knots]
    parts = [_cylinder(axis[i], axis[i + 1], r_pipe, sections=16) for i in range(n_seg)]
    mesh = trimesh.util.concatenate([m for m, _ in parts])
    objects.append(SceneObject("pipe", mesh, "metal", _union_culled(parts)))

    # Rocks: seeded spots at least 2 m from the wreck's footprint and the pipeline, 1.5 m apart.
    d_pipe = pb - pa
    d_pipe = d_pipe / np.linalg.norm(d_pipe)
    rocks, centres = [], []
    while len(rocks) < n_rocks:
        q = rng.uniform([-xh + 1.5, -yh + 1.5], [xh - 1.5, yh - 1.5])
        off = q - pa
        if abs(off[0] * d_pipe[1] - off[1] * d_pipe[0]) < 2.0 + r_pipe:
            continue
        local = (R_w[:2, :2].T @ (q - wc))
        if np.all(np.abs(local) < 0.5 * hull_size[:2] + 2.0):
            continue
        if any(np.linalg.norm(q - p) < 1.5 for p in centres):
            continue
        radii = rng.uniform(0.2, 0.7) * np.array([1.0, rng.uniform(0.6, 1.0), rng.uniform(0.45, 0.8)])
        rock = _rock_object(rng, np.array([*q, float(h(*q)) + 0.3 * radii[2]]), radii)
        rocks.append(rock)
        centres.append(q)
    if rocks:
        mesh = trimesh.util.concatenate([r.mesh for r in rocks])
        culled = _union_culled([(r.mesh, r.contains) for r in rocks], pad_m=0.05)
        objects.append(SceneObject("rocks", mesh, "rock", culled))

    # Features on surfaces: the hull's and deckhouse's top corners, the pipeline's top every
    # fourth knot, each rock's top.
    feats = []
    for cc, size in ((hull_c, hull_size), (house_c, house_size)):
        for sx in (-0.5, 0.5):
            for sy in (-0.5, 0.5):
                feats.append(cc + R_w @ (size * np.array([sx, sy, 0.5])))
    feats += [a + [0, 0, r_pipe] for a in axis[::4]]
    for r in rocks:
        V = r.mesh.vertices
        feats.append(V[int(np.argmax(V[:, 2]))])
    features_W = np.array(feats, dtype=np.float64)
    feature_ids = np.arange(len(features_W), dtype=np.int64) + 100

    T_W_V = lawnmower_trajectory(n_lines, line_spacing_m, line_half_m, ping_spacing_m, c["vehicle_z_m"],
                                 wobble_deg)
    T_V_S, T_V_D = survey_mounts()
    spec = gpumap.SonarSpec.uniform(hfov_deg=130, vfov_deg=20, n_beams=512, n_bins=400,
                                    range_min_m=0.5, range_max_m=8.0)
    return Scene("survey", objects, grid, spec, T_W_V @ T_V_S, T_W_V @ T_V_D, feature_ids, features_W,
                 seed=seed, small_objects=("wreck", "pipe", "rocks") if rocks else ("wreck", "pipe"),
                 seabed_z_m=h, sonar_params=dict(SURVEY_SONAR))


#: Simulator settings of the survey sonar (see :attr:`Scene.sonar_params`): more gain than the
#: tank's 2 m sonar (returns from 4-8 m are weaker: the elevation sum falls as 1/r) and the
#: absorption of sea water.
SURVEY_SONAR: dict[str, float] = {"gain": 6000.0, "absorption_db_per_m": 0.3}


def survey_mounts() -> tuple[np.ndarray, np.ndarray]:
    """``(T_V_S, T_V_D)``: sonar and DVL on the survey vehicle (V: x forward, y left, z up).

    The sonar sits at the bow (0.6 m ahead, 0.1 m below the vehicle's origin) pitched
    ``SURVEY["sonar_pitch_deg"]`` down; the DVL 0.2 m below the origin looking straight down.
    """
    T_V_S = pose_from_xyz_ypr(np.array([0.6, 0.0, -0.1]), 0.0, math.radians(SURVEY["sonar_pitch_deg"]))
    T_V_D = pose_from_xyz_ypr(np.array([0.0, 0.0, -0.2]), 0.0, math.pi / 2)
    return T_V_S, T_V_D


def lawnmower_trajectory(
    n_lines: int,
    line_spacing_m: float,
    line_half_m: float,
    ping_spacing_m: float,
    z_m: float,
    wobble_deg: float = 0.0,
) -> np.ndarray:
    """(n, 4, 4) vehicle poses ``T_W_V`` along a lawnmower pattern at depth ``z_m``.

    Line ``i`` runs along x over ``[-line_half_m, line_half_m]`` at ``y = (i - (n_lines -
    1) / 2) * line_spacing_m``, the first toward +x and the next ones alternating; a
    half-circle of radius ``line_spacing_m / 2`` beyond each line's end joins it to the
    next. Poses are taken every ``ping_spacing_m`` of path length from the first line's
    start, heading along the path (yaw = the path's tangent), with roll ``wobble_deg *
    sin(2 pi s / 7.3 m)`` and pitch ``0.6 wobble_deg * sin(2 pi s / 11.9 m)`` (s the path
    length; positive pitch is nose down).
    """
    R = 0.5 * line_spacing_m
    L = 2.0 * line_half_m
    ys = (np.arange(n_lines) - 0.5 * (n_lines - 1)) * line_spacing_m
    seg_len = [L if i % 2 == 0 else math.pi * R for i in range(2 * n_lines - 1)]
    ends = np.cumsum(seg_len)
    s_all = np.arange(0.0, ends[-1] + 1e-9, ping_spacing_m)
    poses = []
    for s in s_all:
        j = min(int(np.searchsorted(ends, s, side="right")), len(seg_len) - 1)
        u = s - (ends[j] - seg_len[j])
        line = j // 2
        sign = 1.0 if line % 2 == 0 else -1.0  # direction of travel of line `line`
        if j % 2 == 0:  # straight line
            x, y, yaw = sign * (-line_half_m + u), ys[line], 0.0 if sign > 0 else math.pi
        else:  # half-circle to line + 1 (toward +y): counter-clockwise after a +x line, else clockwise
            a = u / R
            cx, cy = sign * line_half_m, ys[line] + R
            x = cx + sign * R * math.sin(a)
            y = cy - R * math.cos(a)
            yaw = a if sign > 0 else math.pi - a
        roll = math.radians(wobble_deg) * math.sin(2 * math.pi * s / 7.3)
        pitch = 0.6 * math.radians(wobble_deg) * math.sin(2 * math.pi * s / 11.9)
        poses.append(pose_from_xyz_ypr(np.array([x, y, z_m]), yaw, pitch, roll))
    return np.array(poses)


# ------------------------------------------------------------------------------ analytic test scene
def box_scene(
    boxes: list[tuple[tuple[float, float, float], tuple[float, float, float]]],
    T_W_S: np.ndarray | None = None,
    material: str = "target",
    spec: gpumap.SonarSpec | None = None,
    voxel_size_m: float = 0.03,
) -> Scene:
    """A scene of axis-aligned boxes ``(center, size)`` for analytic tests."""
    objs = []
    for i, (cc, sz) in enumerate(boxes):
        m, f = _box(np.array(cc, float), np.array(sz, float))
        objs.append(SceneObject(f"box{i}", m, material, f))
    T = np.eye(4)[None] if T_W_S is None else np.asarray(T_W_S, float).reshape(-1, 4, 4)
    grid = gpumap.GridSpec((-2.0, -1.5, -0.5), (2.0, 1.5, 0.5), voxel_size_m)
    spec = spec or gpumap.SonarSpec.uniform()
    return Scene("boxes", objs, grid, spec, T, T, np.zeros(0, np.int64), np.zeros((0, 3)))


# ------------------------------------------------------------------------------ one side only
def side_sweep_trajectory(n_pings: int = 40, y_m: float = -1.2, x_span_m: tuple[float, float] = (-0.6, 0.6),
                          height_m: float = 0.4, pitch_deg: tuple[float, float] = (10.0, 40.0),
                          nod_pings: int = 8) -> np.ndarray:
    """(n_pings, 4, 4) sonar poses sweeping :func:`circle_scene`'s objects from one side only.

    The sonar moves along a straight line at ``y = y_m`` from ``x_span_m[0]`` to ``x_span_m[1]``,
    ``height_m`` above the mean sand, always yawed along +y (towards the objects, no yaw to
    follow them), pitched down between ``pitch_deg`` (a cosine nod with a period of ``nod_pings``
    pings), never rolled: the objects' far sides are never seen and every elevation arc is
    crossed only by views from one side.
    """
    if n_pings < 1 or nod_pings < 2:
        raise ValueError(f"Expected n_pings >= 1 and nod_pings >= 2, but got {n_pings}, {nod_pings}")
    z = CIRCLE["floor_z_m"] + height_m
    p0, p1 = pitch_deg
    poses = []
    for k in range(n_pings):
        s = k / max(1, n_pings - 1)
        x = x_span_m[0] + (x_span_m[1] - x_span_m[0]) * s
        pitch = p0 + (p1 - p0) * (0.5 - 0.5 * math.cos(2 * math.pi * k / nod_pings))
        poses.append(pose_from_xyz_ypr(np.array([x, y_m, z]), math.pi / 2, math.radians(pitch)))
    return np.array(poses)


def side_scene(seed: int = 0, voxel_size_m: float = 0.03, n_pings: int = 40) -> Scene:
    """:func:`circle_scene`'s objects and sand seen by :func:`side_sweep_trajectory` (40 pitched
    pings from one side, no roll): the scene where a surface estimate cannot lean on views
    from the other side."""
    base = circle_scene(seed=seed, voxel_size_m=voxel_size_m)
    T = side_sweep_trajectory(n_pings)
    return dataclasses.replace(base, name="side", T_W_S=T, T_W_D=T.copy())


SCENES: dict[str, Callable[..., Scene]] = {
    "tank": tank_scene, "circle": circle_scene, "survey": survey_scene, "side": side_scene,
}


def make_scene(name: str, **kw) -> Scene:
    """Build a registered scene by name (``tank``, ``circle``, ``survey``, ``side``; the EKF-only prism
    case lives in :mod:`gpumap.sim.prism`, it renders no scene)."""
    if name not in SCENES:
        raise ValueError(f"Expected a scene name in {sorted(SCENES)}, but got {name!r}")
    return SCENES[name](**kw)
