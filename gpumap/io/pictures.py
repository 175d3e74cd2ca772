"""Pictures people read: voxel maps shaded in 3-D (pyrender, offscreen), height maps, per-object errors.

Needs only gpumap's own dependencies (pyrender with EGL, matplotlib), not the ``[viewer]``
extra. Used by ``gpumap demo`` and ``gpumap replay`` for their PNGs (:func:`save_pictures`: a
map's ``views.png`` and ``floor_slice.png``).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["exposed_faces_mesh", "height_map", "look_at", "render_voxels", "save_pictures"]

# the six face directions and the four corners of each face (unit cube centred at 0)
_DIRS = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]])
_LIGHT = np.array([0.35, -0.55, 0.76]) / np.linalg.norm([0.35, -0.55, 0.76])


def _face_corners(d: np.ndarray) -> np.ndarray:
    axis = int(np.flatnonzero(d)[0])
    s = int(d[axis])
    u, v = [a for a in range(3) if a != axis]
    quad = []
    for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
        c = np.zeros(3)
        c[axis] = 0.5 * s
        c[u], c[v] = 0.5 * a, 0.5 * b
        quad.append(c)
    quad = np.array(quad)
    n = np.cross(quad[1] - quad[0], quad[2] - quad[0])
    return quad if np.dot(n, d) > 0 else quad[::-1]


def exposed_faces_mesh(
    occ: np.ndarray, colors: np.ndarray, origin: np.ndarray, voxel_m: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The faces of occupied voxels that touch a non-occupied one, as a flat-shaded mesh.

    Parameters
    ----------
    occ : (nx, ny, nz) bool
    colors : (nx, ny, nz, 3) uint8 or float in [0, 1]
        Colour of each voxel (read where ``occ``).
    origin : (3,)
        World position of voxel (0, 0, 0)'s centre.
    voxel_m : float

    Returns
    -------
    positions (V, 3) float32, normals (V, 3) float32, colours (V, 4) float32, faces (F, 3) uint32.
    """
    pad = np.pad(occ, 1)
    pos, nrm, col, tri = [], [], [], []
    n = 0
    cf = colors.astype(np.float32) / (255.0 if colors.dtype == np.uint8 else 1.0)
    for d in _DIRS:
        nb = pad[
            1 + d[0] : pad.shape[0] - 1 + d[0],
            1 + d[1] : pad.shape[1] - 1 + d[1],
            1 + d[2] : pad.shape[2] - 1 + d[2],
        ]
        idx = np.argwhere(occ & ~nb)
        if len(idx) == 0:
            continue
        c = origin + idx * voxel_m
        quad = _face_corners(d) * voxel_m
        p = (c[:, None, :] + quad[None]).reshape(-1, 3)
        pos.append(p)
        nrm.append(np.broadcast_to(d.astype(np.float32), p.shape))
        # Lambert shading baked into the colours (rendered unlit): a key light from above,
        # front and left, so that the six face directions each get their own brightness
        shade = 0.42 + 0.58 * max(0.0, float(np.dot(d, _LIGHT)))
        k = np.repeat(cf[tuple(idx.T)] * shade, 4, axis=0)
        col.append(np.concatenate([k[:, :3], np.ones((len(k), 1), np.float32)], 1))
        base = n + 4 * np.arange(len(idx))[:, None]
        tri.append(np.concatenate([base + [0, 1, 2], base + [0, 2, 3]]))
        n += len(p)
    if not pos:
        z = np.zeros((0, 3), np.float32)
        return z, z, np.zeros((0, 4), np.float32), np.zeros((0, 3), np.uint32)
    return (
        np.concatenate(pos).astype(np.float32),
        np.concatenate(nrm).astype(np.float32),
        np.concatenate(col),
        np.concatenate(tri).astype(np.uint32),
    )


def look_at(eye: np.ndarray, target: np.ndarray, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera pose (4, 4), OpenGL convention (camera looks down its -z, y up)."""
    eye, target, up = (np.asarray(x, np.float64) for x in (eye, target, up))
    f = target - eye
    f /= np.linalg.norm(f)
    r = np.cross(f, up)
    if np.linalg.norm(r) < 1e-9:
        r = np.cross(f, [0.0, 1.0, 0.0])
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = r, u, -f, eye
    return T


def render_voxels(
    meshes: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]],
    eye: np.ndarray,
    target: np.ndarray,
    size: tuple[int, int] = (800, 600),
    yfov_deg: float = 40.0,
    lines: list[np.ndarray] | None = None,
    ortho_half_m: float | None = None,
) -> np.ndarray:
    """Render meshes of :func:`exposed_faces_mesh` offscreen; (h, w, 3) uint8 on white.

    ``lines``: optional polylines ((n, 3) metres) drawn dark grey (the sonar's path).
    ``ortho_half_m``: an orthographic camera of that half height instead of a perspective one.
    """
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    import pyrender

    scene = pyrender.Scene(bg_color=[1.0, 1.0, 1.0, 1.0], ambient_light=[0.45, 0.45, 0.45])
    for p, _nrm, c, f in meshes:
        if len(f) == 0:
            continue
        import trimesh

        tm = trimesh.Trimesh(
            vertices=p, faces=f, vertex_colors=(np.clip(c, 0, 1) * 255).astype(np.uint8), process=False
        )
        scene.add(pyrender.Mesh.from_trimesh(tm, smooth=False))
    for line in lines or []:
        pts = np.asarray(line, np.float32)
        if len(pts) >= 2:
            seg = np.stack([pts[:-1], pts[1:]], 1).reshape(-1, 3)
            prim = pyrender.Primitive(
                positions=seg, mode=1, color_0=np.tile([0.15, 0.15, 0.15, 1.0], (len(seg), 1))
            )
            scene.add(pyrender.Mesh([prim]))
    w, h = size
    if ortho_half_m is not None:
        cam = pyrender.OrthographicCamera(xmag=ortho_half_m * w / h, ymag=ortho_half_m)
    else:
        cam = pyrender.PerspectiveCamera(yfov=np.radians(yfov_deg), aspectRatio=w / h)
    pose = look_at(eye, target)
    scene.add(cam, pose=pose)
    key = pyrender.DirectionalLight(color=np.ones(3), intensity=2.6)
    scene.add(key, pose=look_at(eye + np.array([0.3, -0.4, 1.5]) * np.linalg.norm(eye - target), target))
    fill = pyrender.DirectionalLight(color=np.ones(3), intensity=0.9)
    scene.add(fill, pose=look_at(target + np.array([1.0, 1.0, 0.6]), target))
    r = pyrender.OffscreenRenderer(w, h)
    try:
        rgb, _ = r.render(scene, flags=pyrender.RenderFlags.FLAT)
    finally:
        r.delete()
    return np.asarray(rgb)[..., :3].copy()


def height_map(occ: np.ndarray, z0_m: float, voxel_m: float) -> np.ndarray:
    """(nx, ny) float: centre height (m) of the highest occupied voxel of each column, NaN if none."""
    nz = occ.shape[2]
    any_ = occ.any(axis=2)
    top = nz - 1 - np.argmax(occ[:, :, ::-1], axis=2)
    return np.where(any_, z0_m + (top + 0.5) * voxel_m, np.nan)


def colour_voxels(
    values: np.ndarray,
    occ: np.ndarray,
    by: str,
    lo: float,
    hi: float,
    cmap: str | None = None,
    z0_m: float = 0.0,
    voxel_m: float = 1.0,
) -> np.ndarray:
    """(nx, ny, nz, 3) float colours of a colour map over ``values`` (``by='value'``) or height."""
    import matplotlib

    if by == "height":
        k = np.arange(occ.shape[2])
        field = np.broadcast_to(z0_m + (k + 0.5) * voxel_m, occ.shape)
        cmap = cmap or "turbo"
    else:
        field = np.nan_to_num(values, nan=lo)
        cmap = cmap or "viridis"
    t = np.clip((field - lo) / max(hi - lo, 1e-9), 0, 1)
    return matplotlib.colormaps[cmap](t)[..., :3].astype(np.float32)


PICTURE_MAX_VOXELS = 4_000_000
"""Grids larger than this are drawn from voxels merged f x f x f (the smallest f that fits)."""


def _picture_factor(n_voxels: int) -> int:
    return max(1, int(np.ceil((n_voxels / PICTURE_MAX_VOXELS) ** (1 / 3) - 1e-9)))


def _blocks(a: np.ndarray, f: int, fill) -> np.ndarray:
    """``a`` padded with ``fill`` to multiples of ``f`` and viewed as (X, f, Y, f, Z, f)."""
    pad = [(0, -n % f) for n in a.shape]
    a = np.pad(a, pad, constant_values=fill)
    X, Y, Z = (n // f for n in a.shape)
    return a.reshape(X, f, Y, f, Z, f)


def _block_any(a: np.ndarray, f: int) -> np.ndarray:
    return a if f == 1 else _blocks(a, f, False).any(axis=(1, 3, 5))


def _block_max(a: np.ndarray, f: int) -> np.ndarray:
    return a if f == 1 else _blocks(a, f, np.iinfo(a.dtype).min).max(axis=(1, 3, 5))


def grid_origin(grid: Any) -> np.ndarray:
    return np.asarray(grid.min_corner_m, np.float64) + 0.5 * grid.voxel_size_m


def _camera_for(
    lo: np.ndarray, hi: np.ndarray, azim_deg: float = -60.0, elev_deg: float = 35.0, yfov_deg: float = 35.0
) -> tuple[np.ndarray, np.ndarray]:
    c = 0.5 * (lo + hi)
    radius = 0.5 * float(np.linalg.norm(hi - lo))
    dist = radius / np.sin(np.radians(yfov_deg) / 2) * 0.72
    a, e = np.radians(azim_deg), np.radians(elev_deg)
    d = np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
    return c + dist * d, c


def replay_views(
    path: Any,
    values: np.ndarray,
    grid: Any,
    threshold: float,
    title: str = "",
    positions: np.ndarray | None = None,
) -> None:
    """Write one PNG: the occupied voxels shaded in 3-D (colour = height) beside a top-down height map."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    vs = float(grid.voxel_size_m)
    o = grid_origin(grid)
    occ = np.isfinite(values) & (np.nan_to_num(values, nan=-1.0) >= threshold)
    idx = np.argwhere(occ)
    if len(idx):
        lo, hi = o + idx.min(0) * vs - vs, o + idx.max(0) * vs + vs
    else:
        lo, hi = np.asarray(grid.min_corner_m), np.asarray(grid.max_corner_m)
    zlo, zhi = float(lo[2]), float(hi[2])
    eye, target = _camera_for(lo, hi, azim_deg=-120.0, elev_deg=40.0)
    # colours and faces of the occupied voxels' box only: colour_voxels takes ~60 bytes a voxel, which
    # over the whole grid was most of a replay's peak memory (bench/memory.py)
    i0 = idx.min(0) if len(idx) else np.zeros(3, int)
    i1 = idx.max(0) + 1 if len(idx) else np.zeros(3, int)
    box = tuple(slice(int(a), int(b)) for a, b in zip(i0, i1, strict=True))
    o_box = o + i0 * vs
    col = colour_voxels(values[box], occ[box], "height", zlo, zhi, z0_m=o_box[2], voxel_m=vs)
    lines = [np.asarray(positions)] if positions is not None and len(positions) > 1 else None
    img = render_voxels([exposed_faces_mesh(occ[box], col, o_box, vs)], eye, target, (900, 680), lines=lines)
    fig = plt.figure(figsize=(13, 5.2), dpi=90)
    gs = fig.add_gridspec(1, 3, width_ratios=(1.25, 1, 0.04), wspace=0.12)
    ax = fig.add_subplot(gs[0, 0])
    ax.imshow(img)
    ax.set_axis_off()
    ax.set_title(
        f"{int(occ.sum())} occupied voxels (value >= {threshold:.2f}), shaded, colour = height"
        + ("; line = sonar path" if lines else ""),
        fontsize=9,
    )
    ax = fig.add_subplot(gs[0, 1])
    hm = height_map(occ, o[2], vs)
    ext = (
        grid.min_corner_m[0],
        grid.min_corner_m[0] + grid.shape[0] * vs,
        grid.min_corner_m[1],
        grid.min_corner_m[1] + grid.shape[1] * vs,
    )
    cmap = matplotlib.colormaps["turbo"].with_extremes(bad="#d9d9d9")
    im = ax.imshow(hm.T, origin="lower", extent=ext, cmap=cmap, vmin=zlo, vmax=zhi, interpolation="nearest")
    if positions is not None and len(positions):
        p = np.asarray(positions)
        ax.plot(p[:, 0], p[:, 1], "k-", lw=1.0, label="sonar path")
        ax.legend(loc="upper right", fontsize=8)
    ax.set(xlim=(lo[0], hi[0]), ylim=(lo[1], hi[1]), xlabel="x (m)", ylabel="y (m)", aspect="equal")
    ax.set_title("from above: top of the highest occupied voxel (grey: none)", fontsize=9)
    fig.colorbar(im, cax=fig.add_subplot(gs[0, 2]), label="height z (m)")
    fig.suptitle(f"{title}  {vs * 100:g} cm voxels", fontsize=11)
    fig.subplots_adjust(left=0.01, right=0.95, top=0.88, bottom=0.1)
    fig.savefig(path)
    plt.close(fig)


def save_pictures(values: np.ndarray, grid: Any, threshold: float, out: Path,
                  title: str = "", positions: np.ndarray | None = None) -> dict:
    """Write ``views.png`` (occupied voxels shaded in 3-D, colour = height, beside a top-down
    height map with a colour bar; ``positions`` (P, 3): the sonar's path) and ``floor_slice.png``.

    Returns
    -------
    dict
        ``floor_z_m`` (height of the slice) and the file names.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    occ = np.isfinite(values) & (values >= threshold)
    # the occupied voxels shaded in 3-D (pyrender offscreen) beside a top-down height map
    replay_views(out / "views.png", values, grid, threshold, title=title, positions=positions)

    # floor: the horizontal layer with the most occupied voxels in the lower half of the box
    counts = occ.sum(axis=(0, 1))
    nz = values.shape[2]
    k_floor = int(np.argmax(counts[: max(1, nz // 2)])) if counts.any() else nz // 4
    z = grid.min_corner_m[2] + (k_floor + 0.5) * grid.voxel_size_m
    fig, ax = plt.subplots(figsize=(5.5, 4.5), dpi=80)
    sl = values[:, :, k_floor].T
    cmap = matplotlib.colormaps["magma"].with_extremes(bad="#3060a0")
    lo, hi = grid.min_corner_m, grid.max_corner_m
    im = ax.imshow(sl, origin="lower", cmap=cmap, vmin=0, vmax=1,
                   extent=(lo[0], lo[0] + values.shape[0] * grid.voxel_size_m,
                           lo[1], lo[1] + values.shape[1] * grid.voxel_size_m))
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(f"slice z = {z:.3f} m (blue = never observed)", fontsize=9)
    fig.colorbar(im, ax=ax, label="min-max value")
    fig.tight_layout()
    fig.savefig(out / "floor_slice.png")
    plt.close(fig)
    del hi
    return {"floor_z_m": z, "pictures": ["views.png", "floor_slice.png"]}
