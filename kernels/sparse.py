"""Block-sparse min-max kernels in NVIDIA Warp (device code only; twin: ``sparse.cl``).

The map lives in a pool of blocks of ``B^3`` voxels (``B`` = ``SparseSpec.block``), slot
``s`` holding voxels ``[s B^3, (s + 1) B^3)`` (local order ``(i, j, k)``, ``k`` fastest), and
a dense coarse *index* over the blocks of a box (int32 per block, -1 = no block), kept by
the host (``gpumap/sparse.py``). ``integrate_blocks`` is ``minmax.integrate_gather`` with
one indirection: the same threads over the ping's voxel box, the same per-voxel arithmetic
(``voxel_ping_value`` and ``update_voxel`` of ``minmax``, so values are bit for bit the
dense grid's), but a voxel's address is its block's slot times ``B^3`` plus its place in
the block. ``init_blocks`` fills newly allocated blocks with "never observed" and writes
their slots into the index (slot -1 frees a block).
"""

import warp as wp
from gpumap.kernels.minmax import PingParams, column_range, update_voxel, voxel_centre, voxel_ping_value

# As minmax: no FMA contraction, so the per-voxel arithmetic (compiled into this module) rounds
# exactly as the dense kernels' and the NumPy oracle's.
wp.set_module_options({"fuse_fp": False})


@wp.kernel
def integrate_blocks(
    P: PingParams,
    image: wp.array2d(dtype=float),
    tan_edges: wp.array(dtype=float),
    lut: wp.array(dtype=int),
    table: wp.array(dtype=float),
    first_bright: wp.array(dtype=int),
    index: wp.array(dtype=int),
    ilo: wp.vec3i,
    nbk: wp.vec3i,
    B: int,
    grid: wp.array(dtype=float),
    bright: wp.array(dtype=float),
    count: wp.array(dtype=wp.uint8),
    seen: wp.array(dtype=wp.uint8),
    err: wp.array(dtype=int),
):
    """One thread per chunk of an (i, j) column of the ping's voxel box, as the dense kernel.

    ``ilo``: the voxel index of the index box's first voxel; ``nbk``: the index box in
    blocks. An observed voxel whose block has no slot (the host's allocation was not
    conservative) or that lies outside the index box sets ``err[0]`` and is skipped.
    """
    tid = wp.tid()
    n_chunks = (P.box_n[2] + P.chunk - 1) // P.chunk
    col = tid // n_chunks
    c0 = P.box_lo[2] + (tid - col * n_chunks) * P.chunk
    i = P.box_lo[0] + col // P.box_n[1]
    j = P.box_lo[1] + col - (col // P.box_n[1]) * P.box_n[1]
    cx = P.origin[0] + (float(i) + 0.5) * P.voxel
    cy = P.origin[1] + (float(j) + 0.5) * P.voxel
    z = column_range(P, cx, cy)
    if z[0] > z[1]:
        return
    k0 = wp.max(c0, int(wp.ceil((z[0] - P.origin[2]) / P.voxel - 0.5)) - 1)
    k1 = wp.min(
        wp.min(c0 + P.chunk, P.box_lo[2] + P.box_n[2]) - 1,
        int(wp.floor((z[1] - P.origin[2]) / P.voxel - 0.5)) + 1,
    )
    ri = i - ilo[0]
    rj = j - ilo[1]
    bi = ri // B
    bj = rj // B
    col_ok = ri >= 0 and rj >= 0 and bi < nbk[0] and bj < nbk[1]
    colbase = (bi * nbk[1] + bj) * nbk[2]
    B3 = B * B * B
    within = ((ri - bi * B) * B + (rj - bj * B)) * B
    cur = int(-1)
    slot = int(-1)
    for k in range(k0, k1 + 1):
        vc = voxel_ping_value(P, voxel_centre(P, i, j, k), image, tan_edges, lut, table, first_bright)
        if vc[0] >= 0.0:
            rk = k - ilo[2]
            bk = int(-1)
            if rk >= 0:
                bk = rk // B
            if bk != cur:
                cur = bk
                slot = -1
                if col_ok and rk >= 0 and bk < nbk[2]:
                    slot = index[colbase + bk]
                if slot >= 0:
                    seen[slot] = wp.uint8(1)  # once per block a thread touches, not per voxel
            if slot < 0:
                err[0] = 1
            else:
                update_voxel(P, slot * B3 + within + rk - bk * B, vc, grid, bright, count)


@wp.kernel
def init_blocks(
    pairs: wp.array(dtype=int),
    n: int,
    B3: int,
    visible: int,
    unknown: float,
    index: wp.array(dtype=int),
    grid: wp.array(dtype=float),
    bright: wp.array(dtype=float),
    count: wp.array(dtype=wp.uint8),
    seen: wp.array(dtype=wp.uint8),
):
    """One thread per voxel of each of ``n`` listed blocks (``pairs``: n slots, then n index
    entries): slot ``pairs[b]`` becomes never observed (``unknown`` = +inf, no evidence) and
    ``index[pairs[n + b]] = pairs[b]`` (slot -1: the block is freed)."""
    tid = wp.tid()
    b = tid // B3
    v = tid - b * B3
    s = pairs[b]
    if s >= 0:
        a = s * B3 + v
        grid[a] = unknown
        if visible != 0:
            bright[a] = unknown
            count[a] = wp.uint8(0)
        if v == 0:
            seen[s] = wp.uint8(0)
    if v == 0:
        index[pairs[n + b]] = s
