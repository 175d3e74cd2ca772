"""View gain of candidate sonar poses in NVIDIA Warp (device code only; twin: ``viewgain.cl``).

``view_gain`` runs one thread per (candidate, tile of points). Each point is a voxel centre
(world frame) with a weight: an *unconfirmed* occupied voxel (its pair mask ``>= 0``: bit ``b``
set when a view whose elevation arc at the voxel runs along the neighbour pair ``b`` would
settle it, see ``pair_bit`` and ``gpumap.layers.viewgain``) counts towards the candidate's ``settle`` total
when the candidate observes it and its bit of the candidate's arc direction is set; a block of
*unknown* voxels (mask ``-1``) counts its weight towards ``unknown`` when the candidate observes
its centre. Totals are int32 atomics: exact and independent of the order in which threads
finish. Arguments, in order: candidate poses (K, 12) (rows of ``A = R_S_W``, then ``b``),
points, their pair masks, their weights, the field of view (r_min, r_max, tan^2 of half the
vertical aperture, tangents of the fan's edges), the tile length, and the outputs (settle,
unknown).
"""

import warp as wp

from .common import arc_step

# No FMA contraction: every device rounds as the NumPy reference does, bit for bit.
wp.set_module_options({"fuse_fp": False})


@wp.func
def pair_bit(si: int, sj: int, sk: int) -> int:
    """The bit of the neighbour pair (+-step) in a voxel's mask: 0..12."""
    m = (si + 1) * 9 + (sj + 1) * 3 + (sk + 1)
    return wp.max(m, 26 - m) - 14


@wp.kernel
def view_gain(
    poses: wp.array2d(dtype=float),
    points: wp.array(dtype=wp.vec3),
    pairs: wp.array(dtype=int),
    weight: wp.array(dtype=int),
    rmin: float,
    rmax: float,
    tan2_half_vfov: float,
    tan_lo: float,
    tan_hi: float,
    tile: int,
    settle: wp.array(dtype=int),
    unknown: wp.array(dtype=int),
):
    c, q = wp.tid()
    a00 = poses[c, 0]
    a01 = poses[c, 1]
    a02 = poses[c, 2]
    a10 = poses[c, 3]
    a11 = poses[c, 4]
    a12 = poses[c, 5]
    a20 = poses[c, 6]
    a21 = poses[c, 7]
    a22 = poses[c, 8]
    b0 = poses[c, 9]
    b1 = poses[c, 10]
    b2 = poses[c, 11]
    n = points.shape[0]
    first = q * tile
    last = wp.min(first + tile, n)
    n_settle = int(0)
    n_unknown = int(0)
    for m in range(first, last):
        p = points[m]
        x = a00 * p[0] + a01 * p[1] + a02 * p[2] + b0
        y = a10 * p[0] + a11 * p[1] + a12 * p[2] + b1
        z = a20 * p[0] + a21 * p[1] + a22 * p[2] + b2
        if x <= float(0.0):
            continue
        h2 = x * x + y * y
        r = wp.sqrt(h2 + z * z)
        t = y / x
        if r < rmin or r >= rmax or z * z > tan2_half_vfov * h2 or t < tan_lo or t > tan_hi:
            continue
        f = pairs[m]
        if f < 0:
            n_unknown += weight[m]
            continue
        # the elevation arc's direction at the voxel, sonar frame (-x z, -y z, h^2), to the world
        # (the transpose of A), and the neighbour step nearest to it
        ex = -(x * z)
        ey = -(y * z)
        ez = h2
        wx = a00 * ex + a10 * ey + a20 * ez
        wy = a01 * ex + a11 * ey + a21 * ez
        wz = a02 * ex + a12 * ey + a22 * ez
        n2 = wx * wx + wy * wy + wz * wz
        si = arc_step(wx, n2)
        sj = arc_step(wy, n2)
        sk = arc_step(wz, n2)
        if (f >> pair_bit(si, sj, sk)) & 1 == 1:
            n_settle += weight[m]
    if n_settle > 0:
        wp.atomic_add(settle, c, n_settle)
    if n_unknown > 0:
        wp.atomic_add(unknown, c, n_unknown)
