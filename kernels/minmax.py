"""Min-max occupancy kernels in NVIDIA Warp (device code only; twin: ``minmax.cl``).

One thread per voxel (``integrate_gather``) or per template point (``integrate_template``).
Each computes the voxel's centre in the sonar frame, tests it against the field of view,
takes the image maximum over the voxel's footprint and min-updates the grid. Arguments,
in order: the ping parameters, the image, the beam edges, [the template,] the grid.
The host module (``gpumap/_warp.py``) owns arrays, devices and launches.
"""

import warp as wp


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
    tan_half_vfov: float
    edge_lo: float
    edge_hi: float
    rho: float  # footprint radius, m
    dims: wp.vec3i  # grid (nx, ny, nz)
    box_lo: wp.vec3i  # gather box first index
    box_n: wp.vec3i  # gather box size
    n_bins: int
    n_beams: int
    n_points: int


@wp.func
def beam_index_lo(az: float, edges: wp.array(dtype=float), n_beams: int) -> int:
    """Largest beam j in [0, n_beams - 1] with edges[j] <= az (0 when none)."""
    lo = int(0)
    hi = n_beams - 1
    while lo < hi:
        mid = (lo + hi + 1) // 2
        if edges[mid] <= az:
            lo = mid
        else:
            hi = mid - 1
    return lo


@wp.func
def voxel_ping_value(
    P: PingParams, c: wp.vec3, image: wp.array2d(dtype=float), edges: wp.array(dtype=float)
) -> float:
    """Max image value over the footprint of the voxel centred at c (world); -1 if unobserved."""
    x = P.A[0, 0] * c[0] + P.A[0, 1] * c[1] + P.A[0, 2] * c[2] + P.b[0]
    y = P.A[1, 0] * c[0] + P.A[1, 1] * c[1] + P.A[1, 2] * c[2] + P.b[1]
    z = P.A[2, 0] * c[0] + P.A[2, 1] * c[1] + P.A[2, 2] * c[2] + P.b[2]
    h2 = x * x + y * y
    r = wp.sqrt(h2 + z * z)
    if r < P.rmin or r >= P.rmax:
        return -1.0
    h = wp.sqrt(h2)
    if wp.abs(z) > P.tan_half_vfov * h:
        return -1.0
    az = wp.atan2(y, x)
    if az < P.edge_lo or az > P.edge_hi:
        return -1.0
    b0 = wp.clamp(int(wp.floor((r - P.rho - P.rmin) * P.inv_dr)), 0, P.n_bins - 1)
    b1 = wp.clamp(int(wp.floor((r + P.rho - P.rmin) * P.inv_dr)), 0, P.n_bins - 1)
    j0 = int(0)
    j1 = P.n_beams - 1
    if h > P.rho:
        dth = wp.asin(P.rho / h)
        j0 = beam_index_lo(az - dth, edges, P.n_beams)
        j1 = beam_index_lo(az + dth, edges, P.n_beams)
    v = float(0.0)
    for i in range(b0, b1 + 1):
        for j in range(j0, j1 + 1):
            v = wp.max(v, image[i, j])
    return v


@wp.func
def voxel_centre(P: PingParams, i: int, j: int, k: int) -> wp.vec3:
    return wp.vec3(
        P.origin[0] + (float(i) + 0.5) * P.voxel,
        P.origin[1] + (float(j) + 0.5) * P.voxel,
        P.origin[2] + (float(k) + 0.5) * P.voxel,
    )


@wp.kernel
def integrate_gather(
    P: PingParams,
    image: wp.array2d(dtype=float),
    edges: wp.array(dtype=float),
    grid: wp.array(dtype=float),
):
    """One thread per voxel of the ping's index box (flattened, k fastest)."""
    tid = wp.tid()
    nyz = P.box_n[1] * P.box_n[2]
    i = P.box_lo[0] + tid // nyz
    rem = tid - (tid // nyz) * nyz
    j = P.box_lo[1] + rem // P.box_n[2]
    k = P.box_lo[2] + rem - (rem // P.box_n[2]) * P.box_n[2]
    v = voxel_ping_value(P, voxel_centre(P, i, j, k), image, edges)
    if v >= 0.0:
        idx = (i * P.dims[1] + j) * P.dims[2] + k
        grid[idx] = wp.min(grid[idx], v)


@wp.kernel
def integrate_template(
    P: PingParams,
    image: wp.array2d(dtype=float),
    edges: wp.array(dtype=float),
    template_S: wp.array(dtype=wp.vec3),
    grid: wp.array(dtype=float),
):
    """One thread per template point: the paper's steps 1-6."""
    tid = wp.tid()
    q = P.R * template_S[tid] + P.t  # step 1
    i = int(wp.floor((q[0] - P.origin[0]) / P.voxel))  # step 2
    j = int(wp.floor((q[1] - P.origin[1]) / P.voxel))
    k = int(wp.floor((q[2] - P.origin[2]) / P.voxel))
    if i < 0 or j < 0 or k < 0 or i >= P.dims[0] or j >= P.dims[1] or k >= P.dims[2]:
        return
    v = voxel_ping_value(P, voxel_centre(P, i, j, k), image, edges)  # steps 3-5
    if v >= 0.0:
        # step 6; several template points may land in one voxel: all carry the same value
        wp.atomic_min(grid, (i * P.dims[1] + j) * P.dims[2] + k, v)
