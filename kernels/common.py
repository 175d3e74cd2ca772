"""Device definitions every Warp kernel module of gpumap shares (device code only; twin: common.cl).

One copy of the ping record (:class:`PingParams`, ``gpumap.geometry.PING_DTYPE`` field for field),
the beam search (:func:`beam_index_lo`), the packed view counts' mask and the elevation-arc step
(:func:`arc_step`), imported by ``minmax``, ``confidence`` and ``viewgain``.
"""

import warp as wp

# No FMA contraction: every device rounds as the NumPy reference does, bit for bit.
wp.set_module_options({"fuse_fp": False})

#: The packed view counts: clear dark views in the low 32 bits, bright views in the high 32.
COUNT_LOW = wp.constant(wp.uint64(0xFFFFFFFF))


@wp.struct
class PingParams:
    A: wp.mat33  # rotation of T_S_W
    b: wp.vec3  # translation of T_S_W
    R: wp.mat33  # rotation of T_W_S
    t: wp.vec3  # translation of T_W_S
    origin: wp.vec3  # grid min corner, m
    voxel: float  # voxel edge, m
    rmin: float
    rmax: float
    inv_dr: float
    tan2_half_vfov: float  # tan(vfov / 2)^2
    tan_lo: float  # tangents of the fan's outer azimuth edges
    tan_hi: float
    rho: float  # footprint radius, m
    dims: wp.vec3i  # grid (nx, ny, nz)
    box_lo: wp.vec3i  # gather box first index
    box_n: wp.vec3i  # gather box size
    n_bins: int
    n_beams: int
    n_points: int
    win: int  # footprint height in bins: floor(2 rho / dr) + 2, at most n_bins
    n_levels: int  # beam levels of the max table (spans up to 2^n_levels - 1 in two reads)
    lut_scale: float  # beam look-up table entries per radian
    lut_n: int  # beam look-up table entries
    wedge: wp.vec4  # (-sin lo, cos lo, sin hi, -cos hi): the fan's azimuth half-planes, n . (x, y) >= 0
    slab: float  # r_max sin(vfov / 2): |z| of any imaged point in the sonar frame is below it
    chunk: int  # voxels of a column per gather thread (GPUs: a few, for threads in flight; CPUs: all)
    near: float  # rho + shadow_m: the footprint reaches this far towards the sonar, m
    thr: float  # occupied intensity: a footprint max >= thr is a bright view
    thr_dark: float  # visible rule: a clear view darker than this counts twice towards carving
    rule: int  # 0: plain min; 1: visible (bright min, clear-dark count); 2: evidence (view counts)
    blk_lo: wp.vec3i  # voxel index of the block index's first voxel
    blk_n: wp.vec3i  # the block index's extent, in blocks
    blk: int  # a block's edge along x and y, voxels (B)
    blk_z: int  # a block's edge along z, voxels (Bz)


@wp.func
def beam_index_lo(t: float, tan_edges: wp.array(dtype=float), lut: wp.array(dtype=int), P: PingParams) -> int:
    """Largest beam j in [0, n_beams - 1] with tan_edges[j] <= t (0 when none), t = tan(azimuth).

    A uniform look-up table over the fan's tangents gives a guess within a step or two (clamped as a
    float, so any t is safe); exact comparisons with the edges then settle it, so the answer is a
    binary search's.
    """
    f = wp.floor((t - P.tan_lo) * P.lut_scale)
    m = int(0)
    if f >= float(lut.shape[0] - 1):
        m = lut.shape[0] - 1
    elif f > 0.0:
        m = int(f)
    j = lut[m]
    while j < P.n_beams - 1 and tan_edges[j + 1] <= t:
        j += 1
    while j > 0 and tan_edges[j] > t:
        j -= 1
    return j


@wp.func
def arc_step(d: float, n2: float) -> int:
    """-1, 0 or 1: the sign of ``d`` where ``4 d^2 > n2`` (|d| above half the vector's norm)."""
    if float(4.0) * d * d > n2:
        if d > float(0.0):
            return 1
        return -1
    return 0
