"""NumPy twin of the ping model's forward pass (:mod:`gpumap.kernels.render`).

The same float32 operations in the same order, vectorised; the test oracle of
:class:`gpumap.layers.render.PingRenderer`. Not bit for bit: Warp's ``exp``/``pow`` and NumPy's differ
in the last ulp, and the kernels sum a beam's elevation rays with atomics in no fixed order, so
the two agree to float32 rounding (about 1e-6 relative), not exactly.
"""

from __future__ import annotations

import numpy as np

from gpumap.layers.render import PingRenderer

__all__ = ["energy_reference"]

f32 = np.float32


def _trilinear_with_gradient(field: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Value and gradient (per voxel unit) of the voxel-centred trilinear field at ``u`` (n, 3)."""
    fl = np.floor(u)
    i0 = fl.astype(np.int64)
    w = (u - fl).astype(f32)
    pad = np.pad(field, 1)  # zeros outside the grid
    shape = np.array(field.shape)
    idx = np.clip(i0 + 1, 0, shape + 1)  # into the padded array; farther out reads zeros
    inside = np.all((i0 + 1 >= 0) & (i0 + 1 <= shape), axis=1)

    def at(dx: int, dy: int, dz: int) -> np.ndarray:
        ii = np.clip(idx + (dx, dy, dz), 0, shape + 1)
        v = pad[ii[:, 0], ii[:, 1], ii[:, 2]]
        return np.where(inside, v, f32(0.0))

    a, b, c = w[:, 0], w[:, 1], w[:, 2]
    o = {(x, y, z): at(x, y, z) for x in (0, 1) for y in (0, 1) for z in (0, 1)}
    one = f32(1.0)
    c00 = o[0, 0, 0] * (one - a) + o[1, 0, 0] * a
    c10 = o[0, 1, 0] * (one - a) + o[1, 1, 0] * a
    c01 = o[0, 0, 1] * (one - a) + o[1, 0, 1] * a
    c11 = o[0, 1, 1] * (one - a) + o[1, 1, 1] * a
    c0 = c00 * (one - b) + c10 * b
    c1 = c01 * (one - b) + c11 * b
    val = c0 * (one - c) + c1 * c
    gz = c1 - c0
    gy = (c10 - c00) * (one - c) + (c11 - c01) * c
    x0 = (o[0, 0, 0] * (one - b) + o[0, 1, 0] * b) * (one - c) + (o[0, 0, 1] * (one - b) + o[0, 1, 1] * b) * c
    x1 = (o[1, 0, 0] * (one - b) + o[1, 1, 0] * b) * (one - c) + (o[1, 0, 1] * (one - b) + o[1, 1, 1] * b) * c
    return val, np.stack([x1 - x0, gy, gz], 1)


def energy_reference(renderer: PingRenderer, occupancy: np.ndarray, reflectivity: np.ndarray,
                     poses: np.ndarray) -> np.ndarray:
    """``renderer.energy(occupancy, reflectivity, poses)`` in NumPy: (B, n_range, n_beam_cells) float32."""
    g, m = renderer.grid, renderer.model
    occ = renderer._check_field(occupancy, "occupancy")
    refl = renderer._check_field(reflectivity, "reflectivity")
    P = renderer._check_poses(poses)
    inv_h = f32(1.0 / g.voxel_size_m)
    origin = np.asarray(g.min_corner_m, f32)
    dirs = renderer.ray_dir_S.astype(f32)
    wray = renderer.ray_weight.astype(f32)
    n_s = renderer.n_range
    r = f32(renderer.spec.range_min_m) + (np.arange(n_s, dtype=f32) + f32(0.5)) * f32(renderer.step_m)
    out = np.zeros((len(P), n_s, renderer.n_beam_cells), f32)
    for p, T in enumerate(P):
        R, t = T[:3, :3].astype(f32), T[:3, 3].astype(f32)
        d = dirs @ R.T  # (rays, 3)
        x = t[None, None, :] + d[:, None, :] * r[None, :, None]  # (rays, samples, 3)
        u = (x - origin) * inv_h - f32(0.5)
        val, grad = _trilinear_with_gradient(occ, u.reshape(-1, 3))
        rho, _ = _trilinear_with_gradient(refl, u.reshape(-1, 3))
        grad = grad * inv_h
        dd = np.repeat(d, n_s, axis=0)
        dot = np.einsum("ij,ij->i", dd, grad)
        delta = f32(0.1) * inv_h
        cos2 = dot * dot / (np.einsum("ij,ij->i", grad, grad) + delta * delta)
        shade = np.power(cos2 + f32(1e-4), f32(0.5 * m.cos_exponent))
        rr = np.tile(r, len(d))
        loss = np.power(rr, f32(-m.spreading_exponent)) * np.power(
            f32(10.0), f32(-0.2 * m.absorption_db_per_m) * (rr - f32(1.0)))
        alpha = (f32(1.0) - np.exp(-f32(m.kappa) * val * f32(renderer.step_m) * inv_h)).reshape(len(d), n_s)
        emit = (np.repeat(wray, n_s) * loss * rho * shade).reshape(len(d), n_s)
        trans = np.cumprod(np.concatenate([np.ones((len(d), 1), f32), f32(1.0) - alpha[:, :-1]], 1), axis=1,
                           dtype=f32)
        e = trans * alpha * emit  # (rays, samples)
        np.add.at(out[p].T, renderer.ray_beam, e)
    return out
