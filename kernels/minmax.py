"""Min-max occupancy kernels in NVIDIA Warp (device code only; twin: ``minmax.cl``).

``integrate_gather`` runs one thread per (i, j) column of the ping's voxel box,
``integrate_voxels_batch`` one per voxel of a batch's boxes (every ping folded in registers) and
``integrate_template`` one per template point; each voxel's centre goes to the sonar frame,
is tested against the field of view, and takes the image maximum over its footprint, which
min-updates the grid. ``build_bin_window`` and ``build_beam_levels`` build the per-ping max
table that CPUs read instead of looping over cells; ``find_first_bright`` the per-beam nearest
return that tells clear views for the visibility-aware rule. Arguments, in order: the ping
parameters, the image, the tangents of the beam edges, the beam look-up table, the max table
(empty: none), the first bright bin per beam (empty: plain rule), [the template,] the grid
[, the bright minimum and the clear-dark count (visible rule; empty otherwise)]. The host
(the ``gpumap/backends/`` package) owns arrays, devices and launches.
"""

import os

import warp as wp

from .common import COUNT_LOW, PingParams, beam_index_lo  # noqa: F401 (the backends read them here)

# No FMA contraction on GPUs: every backend then rounds as the NumPy oracle does, bit for bit.
wp.set_module_options({"fuse_fp": False})
#: Register cap of the per-voxel batch gather on CUDA (``GPUMAP_GPU_MAX_REGISTERS``, read at import;
#: default 64; 0: the compiler's choice, 95 registers): fewer registers, more threads in flight,
#: a few spilled to local memory. On an H100 (tank, default rule) 64 ran the kernel 1.2x faster
#: at 1 cm and 5 mm than the compiler's choice (bench/results/gpu_scale.json).
GATHER_MAX_REGISTERS = int(os.environ.get("GPUMAP_GPU_MAX_REGISTERS", "64") or 0) or None


@wp.func
def voxel_ping_value(
    P: PingParams,
    c: wp.vec3,
    image: wp.array2d(dtype=float),
    tan_edges: wp.array(dtype=float),
    lut: wp.array(dtype=int),
    table: wp.array(dtype=float),
    first_bright: wp.array(dtype=int),
) -> wp.vec2:
    """(max image value over the footprint of the voxel centred at c (world), clear); value -1
    if unobserved. For the visible and evidence rules and a dark value (< thr), clear is 1 when
    ``first_bright`` (per beam, the first bin >= thr) puts no return nearer than the footprint's
    first bin in any of its beams, else 0 (and 0 for bright values, whose update never reads it).

    The footprint is bins [b0, b0 + win - 1] x beams [j0, j1]: the smallest fixed-height
    window that always holds the bins of the voxel's bounding sphere (one extra bin at
    most), extended ``shadow_m`` towards the sonar (``near = rho + shadow_m``), by the
    beams the sphere spans. With a max table (non-empty ``table``) the max
    is two reads; without, a loop over the cells (faster on GPUs: no table to build).
    """
    unseen = wp.vec2(-1.0, 0.0)
    x = P.A[0, 0] * c[0] + P.A[0, 1] * c[1] + P.A[0, 2] * c[2] + P.b[0]
    y = P.A[1, 0] * c[0] + P.A[1, 1] * c[1] + P.A[1, 2] * c[2] + P.b[1]
    z = P.A[2, 0] * c[0] + P.A[2, 1] * c[1] + P.A[2, 2] * c[2] + P.b[2]
    if x <= 0.0:  # the fan lies within +-90 deg of boresight
        return unseen
    h2 = x * x + y * y
    r = wp.sqrt(h2 + z * z)
    if r < P.rmin or r >= P.rmax:
        return unseen
    if z * z > P.tan2_half_vfov * h2:
        return unseen
    t = y / x  # tan(azimuth): monotonic over the fan, so no atan2 is needed
    if t < P.tan_lo or t > P.tan_hi:
        return unseen
    first = int(wp.floor((r - P.near - P.rmin) * P.inv_dr))  # may be < 0 near the blanking range
    b0 = wp.max(first, 0)
    b1 = wp.min(first + P.win - 1, P.n_bins - 1)
    j0 = int(0)
    j1 = P.n_beams - 1
    q = h2 - P.rho * P.rho
    if q > 0.0:  # the sphere spans azimuths theta -+ asin(rho / h); in tangents:
        u = P.rho / wp.sqrt(q)  # tan(asin(rho / h))
        d0 = 1.0 + t * u
        d1 = 1.0 - t * u
        if d0 > 0.0:  # else theta - dtheta is past -90 deg: from the first beam
            j0 = beam_index_lo((t - u) / d0, tan_edges, lut, P)
        if d1 > 0.0:
            j1 = beam_index_lo((t + u) / d1, tan_edges, lut, P)
    v = float(0.0)
    if table.shape[0] > 0 and first >= 0:  # the max table: two reads (more near the apex)
        k = int(0)
        while (2 << k) <= j1 - j0 + 1 and k + 1 < P.n_levels:
            k += 1
        w = 1 << k
        base = (k * P.n_bins + b0) * P.n_beams
        v = table[base + j1 - w + 1]
        jj = j0
        while jj <= j1 - w + 1:
            v = wp.max(v, table[base + jj])
            jj += w
    else:
        for i in range(b0, b1 + 1):
            for j in range(j0, j1 + 1):
                v = wp.max(v, image[i, j])
    # clear matters only to a dark view's count (update_voxel): looked up only then
    clear = float(0.0)
    if P.rule != 0 and v < P.thr:
        clear = float(1.0)
        for jj in range(j0, j1 + 1):
            if first_bright[jj] < b0:
                clear = 0.0
                break
    return wp.vec2(v, clear)


@wp.func
def first_bright_bin(P: PingParams, image: wp.array2d(dtype=float), j: int) -> int:
    """The first bin of beam j whose intensity is >= thr (n_bins if none)."""
    f = P.n_bins
    i = int(0)
    while i < P.n_bins:
        if image[i, j] >= P.thr:
            f = i
            i = P.n_bins
        i += 1
    return f


@wp.kernel
def find_first_bright(P: PingParams, image: wp.array2d(dtype=float), first_bright: wp.array(dtype=int)):
    """One thread per beam j: the first bin whose intensity is >= thr (n_bins if none)."""
    j = wp.tid()
    first_bright[j] = first_bright_bin(P, image, j)


@wp.kernel
def first_bright_init(P: PingParams, first_bright: wp.array(dtype=int)):
    """One thread per beam: no bright bin yet (n_bins); find_first_bright_cells lowers it."""
    j = wp.tid()
    first_bright[j] = P.n_bins


@wp.kernel
def find_first_bright_cells(P: PingParams, image: wp.array2d(dtype=float), first_bright: wp.array(dtype=int)):
    """GPU twin of find_first_bright: one thread per cell, an atomic min per bright cell (the
    minimum is the same in any order: deterministic)."""
    i, j = wp.tid()
    if image[i, j] >= P.thr:
        wp.atomic_min(first_bright, j, i)


# ``count`` packs two view counts in a uint64: clear dark views in the low 32 bits, bright views
# in the high 32 bits. Each saturates on its own (the visible rule's dark count at 255, as it
# always did; every other count at 2^32 - 1: 6.8 years of a voxel in view at 20 Hz), so an
# update is a saturating add, which no order changes.
COUNT_HIGH_ONE = wp.constant(wp.uint64(0x100000000))
HITS_FULL = wp.constant(wp.uint64(0xFFFFFFFF00000000))  # count >= this: the bright count is full


@wp.func
def update_voxel(
    P: PingParams,
    idx: int,
    vc: wp.vec2,
    grid: wp.array(dtype=float),
    bright: wp.array(dtype=float),
    count: wp.array(dtype=wp.uint64),
):
    """Fold one view (value, clear) into voxel idx: the plain min, and for the visible and
    evidence rules the bright min and the view counts (see gpumap.reference)."""
    v = vc[0]
    if v < grid[idx]:  # a write only where the value falls (memory traffic, not arithmetic, bounds it)
        grid[idx] = v
    if P.rule != 0:  # count is read only where it may change (a dark view behind a return leaves it)
        if v >= P.thr and v < bright[idx]:
            bright[idx] = v
        if v >= P.thr or vc[1] > 0.0:
            c = count[idx]
            n = counted(P, v, vc[1], c)
            if n != c:
                count[idx] = n


@wp.func
def counted(P: PingParams, v: float, clear: float, c: wp.uint64) -> wp.uint64:
    """The packed view counts ``c`` after one view (value v, clear) under the visible or evidence
    rule: a bright view raises the bright count, a clear dark one the dark count (the visible
    rule's by 2 below thr_dark, to 255), each saturating."""
    if v >= P.thr:
        if c < HITS_FULL:
            return c + COUNT_HIGH_ONE
        return c
    if clear > 0.0:
        dark = c & COUNT_LOW
        cap = COUNT_LOW
        step = wp.uint64(1)
        if P.rule == 1:
            cap = wp.uint64(255)
            if v < P.thr_dark:
                step = wp.uint64(2)
        if dark < cap:
            return (c - dark) + wp.min(dark + step, cap)
    return c


@wp.kernel
def convert_u8(src: wp.array2d(dtype=wp.uint8), scale: float, dst: wp.array2d(dtype=float)):
    """One thread per pixel: an 8-bit image to float32 intensities, dst = src * scale (1/255)."""
    i, j = wp.tid()
    dst[i, j] = float(src[i, j]) * scale


@wp.kernel
def build_bin_window(P: PingParams, image: wp.array2d(dtype=float), table: wp.array(dtype=float)):
    """One thread per beam j: level 0 of the max table, table[0, i, j] = max of image over
    bins [i, i + win - 1] (clipped), by van Herk / Gil-Werman: a prefix and a suffix max in
    blocks of win bins (kept in the two scratch levels after the table), 3 ops per cell."""
    j = wp.tid()
    nb = P.n_beams
    plane = P.n_bins * nb
    pre = P.n_levels * plane
    suf = pre + plane
    for i in range(P.n_bins):
        v = image[i, j]
        if i % P.win != 0:
            v = wp.max(v, table[pre + (i - 1) * nb + j])
        table[pre + i * nb + j] = v
    for ii in range(P.n_bins):
        i = P.n_bins - 1 - ii
        v = image[i, j]
        if (i + 1) % P.win != 0 and i + 1 < P.n_bins:
            v = wp.max(v, table[suf + (i + 1) * nb + j])
        table[suf + i * nb + j] = v
    for i in range(P.n_bins):
        e = wp.min(i + P.win - 1, P.n_bins - 1)
        v = table[suf + i * nb + j]
        if e // P.win != i // P.win:  # the window reaches into the next block
            v = wp.max(v, table[pre + e * nb + j])
        table[i * nb + j] = v


@wp.kernel
def build_beam_levels(P: PingParams, table: wp.array(dtype=float)):
    """One thread per bin row i: table[k, i, j] = max of level 0 over beams [j, j + 2^k - 1]
    (clipped), for 0 < k < n_levels."""
    i = wp.tid()
    step = int(1)
    for k in range(1, P.n_levels):
        cur = (k * P.n_bins + i) * P.n_beams
        prev = cur - P.n_bins * P.n_beams
        for j in range(P.n_beams):
            table[cur + j] = wp.max(table[prev + j], table[prev + wp.min(j + step, P.n_beams - 1)])
        step = step * 2


@wp.func
def bin_window_cell(
    P: PingParams, image: wp.array2d(dtype=float), table: wp.array(dtype=float), i: int, j: int
):
    v = float(0.0)
    for b in range(i, wp.min(i + P.win, P.n_bins)):
        v = wp.max(v, image[b, j])
    table[i * P.n_beams + j] = v


@wp.func
def beam_levels_cell(P: PingParams, table: wp.array(dtype=float), i: int, j: int):
    row = i * P.n_beams
    v = table[row + j]
    w = int(1)
    for k in range(1, P.n_levels):
        for jj in range(w, 2 * w):
            v = wp.max(v, table[row + wp.min(j + jj, P.n_beams - 1)])
        table[(k * P.n_bins + i) * P.n_beams + j] = v
        w = 2 * w


@wp.kernel
def build_bin_window_cells(P: PingParams, image: wp.array2d(dtype=float), table: wp.array(dtype=float)):
    """GPU twin of build_bin_window: one thread per cell (i, j), win reads each."""
    i, j = wp.tid()
    bin_window_cell(P, image, table, i, j)


@wp.kernel
def build_beam_levels_cells(P: PingParams, table: wp.array(dtype=float)):
    """GPU twin of build_beam_levels: one thread per cell (i, j), reading level 0 only
    (2^(n_levels - 1) reads), so every level comes from one launch."""
    i, j = wp.tid()
    beam_levels_cell(P, table, i, j)


@wp.func
def voxel_centre(P: PingParams, i: int, j: int, k: int) -> wp.vec3:
    return wp.vec3(
        P.origin[0] + (float(i) + 0.5) * P.voxel,
        P.origin[1] + (float(j) + 0.5) * P.voxel,
        P.origin[2] + (float(k) + 0.5) * P.voxel,
    )


@wp.func
def clip_linear(z: wp.vec2, alpha: float, beta: float) -> wp.vec2:
    """Intersect the interval z with {z : alpha + beta z >= 0}."""
    if wp.abs(beta) < 1.0e-12:
        if alpha < 0.0:
            return wp.vec2(1.0, -1.0)  # empty
        return z
    zc = -alpha / beta
    if beta > 0.0:
        return wp.vec2(wp.max(z[0], zc), z[1])
    return wp.vec2(z[0], wp.min(z[1], zc))


@wp.func
def column_range(P: PingParams, cx: float, cy: float) -> wp.vec2:
    """World z-interval of the column (cx, cy) that can hold imaged points: the column cut by
    the range sphere, the azimuth half-planes and the elevation slab, all of which contain
    the field of view. A relaxation, so conservative; the per-voxel test stays exact."""
    dx = cx - P.t[0]
    dy = cy - P.t[1]
    q = P.rmax * P.rmax - dx * dx - dy * dy
    if q <= 0.0:
        return wp.vec2(1.0, -1.0)
    w = wp.sqrt(q)
    z = wp.vec2(P.t[2] - w, P.t[2] + w)
    # sonar-frame point at world height zw: p0 + zw * a
    p0x = P.A[0, 0] * cx + P.A[0, 1] * cy + P.b[0]
    p0y = P.A[1, 0] * cx + P.A[1, 1] * cy + P.b[1]
    p0z = P.A[2, 0] * cx + P.A[2, 1] * cy + P.b[2]
    ax = P.A[0, 2]
    ay = P.A[1, 2]
    az = P.A[2, 2]
    z = clip_linear(z, P.wedge[0] * p0x + P.wedge[1] * p0y, P.wedge[0] * ax + P.wedge[1] * ay)
    z = clip_linear(z, P.wedge[2] * p0x + P.wedge[3] * p0y, P.wedge[2] * ax + P.wedge[3] * ay)
    z = clip_linear(z, P.slab - p0z, -az)
    z = clip_linear(z, P.slab + p0z, az)
    return z


@wp.func
def voxel_address(P: PingParams, index: wp.array(dtype=int), i: int, j: int, k: int) -> int:
    """Storage address of voxel (i, j, k): its block's slot (through the index) times the block's
    voxels (B B Bz) plus its place in the block (local order i, j, k, k fastest); -1 when it has
    no block."""
    B = P.blk
    Bz = P.blk_z
    ri = i - P.blk_lo[0]
    rj = j - P.blk_lo[1]
    rk = k - P.blk_lo[2]
    if ri < 0 or rj < 0 or rk < 0:
        return -1
    bi = ri // B
    bj = rj // B
    bk = rk // Bz
    if bi >= P.blk_n[0] or bj >= P.blk_n[1] or bk >= P.blk_n[2]:
        return -1
    slot = index[(bi * P.blk_n[1] + bj) * P.blk_n[2] + bk]
    if slot < 0:
        return -1
    return slot * B * B * Bz + ((ri - bi * B) * B + (rj - bj * B)) * Bz + rk - bk * Bz


@wp.func
def block_column(P: PingParams, i: int, j: int) -> wp.vec3i:
    """Column (i, j) in the block index: (1 if the index spans it else 0, the index entry of its
    first block, the offset of its voxels in a block)."""
    B = P.blk
    ri = i - P.blk_lo[0]
    rj = j - P.blk_lo[1]
    bi = ri // B
    bj = rj // B
    ok = int(0)
    if ri >= 0 and rj >= 0 and bi < P.blk_n[0] and bj < P.blk_n[1]:
        ok = 1
    return wp.vec3i(ok, (bi * P.blk_n[1] + bj) * P.blk_n[2], ((ri - bi * B) * B + (rj - bj * B)) * P.blk_z)


@wp.func
def gather_column(
    P: PingParams,
    i: int,
    j: int,
    c0: int,
    c1: int,
    image: wp.array2d(dtype=float),
    tan_edges: wp.array(dtype=float),
    lut: wp.array(dtype=int),
    table: wp.array(dtype=float),
    first_bright: wp.array(dtype=int),
    index: wp.array(dtype=int),
    col: wp.vec3i,
    grid: wp.array(dtype=float),
    bright: wp.array(dtype=float),
    count: wp.array(dtype=wp.uint64),
    seen: wp.array(dtype=wp.uint8),
    err: wp.array(dtype=int),
):
    """Fold one ping into the voxels c0..c1 of column (i, j) that the column's range can hold
    (``col``: :func:`block_column` of the column, or ``(-1, 0, 0)`` to look it up here).

    Block by block along the column: one index read per block, then that block's voxels
    (contiguous in memory) as a plain loop; a block with an observed voxel is marked seen. An
    observed voxel without a block (the host's allocation was not conservative) sets err[0]
    and is skipped. A bounded box's blocks span the grid's height, so its columns run as one
    loop."""
    cx = P.origin[0] + (float(i) + 0.5) * P.voxel
    cy = P.origin[1] + (float(j) + 0.5) * P.voxel
    z = column_range(P, cx, cy)
    if z[0] <= z[1]:
        # voxel centres inside [z0, z1], padded by one voxel against rounding
        k0 = wp.max(c0, int(wp.ceil((z[0] - P.origin[2]) / P.voxel - 0.5)) - 1)
        k1 = wp.min(c1, int(wp.floor((z[1] - P.origin[2]) / P.voxel - 0.5)) + 1)
        B = P.blk
        Bz = P.blk_z
        bc = col
        if bc[0] < 0:  # not given: look the column up now (only columns the ping can reach)
            bc = block_column(P, i, j)
        col_ok = bc[0] != 0
        colbase = bc[1]
        within = bc[2]
        kb = k0
        while kb <= k1:
            rk = kb - P.blk_lo[2]
            slot = int(-1)
            base = int(0)  # the block's slot * B B Bz + within - its first k
            kstop = wp.min(k1, P.blk_lo[2] - 1)
            if rk >= 0:
                bk = int(0)  # a bounded box's column is one block: no division
                if rk >= Bz:
                    bk = rk // Bz
                kstop = wp.min(k1, P.blk_lo[2] + bk * Bz + Bz - 1)
                if col_ok and bk < P.blk_n[2]:
                    slot = index[colbase + bk]
                base = slot * B * B * Bz + within - (P.blk_lo[2] + bk * Bz)
            hit = int(0)
            for k in range(kb, kstop + 1):
                vc = voxel_ping_value(P, voxel_centre(P, i, j, k), image, tan_edges, lut, table, first_bright)
                if vc[0] >= 0.0:
                    hit = 1
                    if slot >= 0:
                        update_voxel(P, base + k, vc, grid, bright, count)
            if hit != 0:
                if slot < 0:
                    err[0] = 1
                elif seen[slot] == wp.uint8(0):  # a read, and a write only the first time
                    seen[slot] = wp.uint8(1)
            kb = kstop + 1


@wp.kernel
def integrate_gather(
    P: PingParams,
    image: wp.array2d(dtype=float),
    tan_edges: wp.array(dtype=float),
    lut: wp.array(dtype=int),
    table: wp.array(dtype=float),
    first_bright: wp.array(dtype=int),
    index: wp.array(dtype=int),
    grid: wp.array(dtype=float),
    bright: wp.array(dtype=float),
    count: wp.array(dtype=wp.uint64),
    seen: wp.array(dtype=wp.uint8),
    err: wp.array(dtype=int),
):
    """One thread per chunk of an (i, j) column of the ping's index box: it walks the chunk's
    voxels that the column's range can hold (contiguous in memory within a block)."""
    tid = wp.tid()
    n_chunks = (P.box_n[2] + P.chunk - 1) // P.chunk
    col = tid // n_chunks
    c0 = P.box_lo[2] + (tid - col * n_chunks) * P.chunk
    i = P.box_lo[0] + col // P.box_n[1]
    j = P.box_lo[1] + col - (col // P.box_n[1]) * P.box_n[1]
    c1 = wp.min(c0 + P.chunk, P.box_lo[2] + P.box_n[2]) - 1
    gather_column(
        P, i, j, c0, c1, image, tan_edges, lut, table, first_bright, index, wp.vec3i(-1, 0, 0), grid, bright,
        count, seen, err,
    )


@wp.kernel
def init_blocks(
    pairs: wp.array(dtype=int),
    n: int,
    bv: int,
    visible: int,
    unknown: float,
    index: wp.array(dtype=int),
    grid: wp.array(dtype=float),
    bright: wp.array(dtype=float),
    count: wp.array(dtype=wp.uint64),
    seen: wp.array(dtype=wp.uint8),
):
    """One thread per voxel of each of ``n`` listed blocks of ``bv`` voxels (``pairs``: n slots,
    then n index entries): slot ``pairs[b]`` becomes never observed (``unknown`` = +inf, no evidence) and
    ``index[pairs[n + b]] = pairs[b]`` (slot -1: the block is freed)."""
    tid = wp.tid()
    b = tid // bv
    v = tid - b * bv
    s = pairs[b]
    if s >= 0:
        a = s * bv + v
        grid[a] = unknown
        if visible != 0:
            bright[a] = unknown
            count[a] = wp.uint64(0)
        if v == 0:
            seen[s] = wp.uint8(0)
    if v == 0:
        index[pairs[n + b]] = s


# ----------------------------------------------------------------------------- batches
# A batch of B pings in one launch per step. Each gather thread owns one voxel of the union of the
# pings' boxes and folds every ping into it in turn: no atomics, and every voxel sees exactly the
# views B sequential launches would give it, so the map is the same bit for bit (each update is a
# min or a saturating count, which no order changes).


@wp.kernel
def convert_u8_batch(src: wp.array3d(dtype=wp.uint8), scale: float, dst: wp.array3d(dtype=float)):
    """One thread per pixel of every ping: dst = src * scale."""
    b, i, j = wp.tid()
    dst[b, i, j] = float(src[b, i, j]) * scale


@wp.kernel
def find_first_bright_batch(
    Ps: wp.array(dtype=PingParams), images: wp.array3d(dtype=float), first_bright: wp.array2d(dtype=int)
):
    """One thread per (ping, beam): find_first_bright for every ping."""
    b, j = wp.tid()
    first_bright[b, j] = first_bright_bin(Ps[b], images[b], j)


@wp.kernel
def build_bin_window_cells_batch(
    Ps: wp.array(dtype=PingParams), images: wp.array3d(dtype=float), tables: wp.array2d(dtype=float)
):
    """One thread per (ping, cell): build_bin_window_cells for every ping."""
    b, i, j = wp.tid()
    bin_window_cell(Ps[b], images[b], tables[b], i, j)


@wp.kernel
def build_beam_levels_cells_batch(Ps: wp.array(dtype=PingParams), tables: wp.array2d(dtype=float)):
    """One thread per (ping, cell): build_beam_levels_cells for every ping."""
    b, i, j = wp.tid()
    beam_levels_cell(Ps[b], tables[b], i, j)


@wp.func
def ping_of(P0: PingParams, Ps: wp.array(dtype=PingParams), b: int) -> PingParams:
    """Ping b's parameters: ``P0`` (ping 0's, a kernel argument: read from constant memory where it
    is used) with the fields that differ between a batch's pings (pose, footprint) read from Ps[b]."""
    P = P0
    P.A = Ps[b].A
    P.b = Ps[b].b
    P.rho = Ps[b].rho
    P.near = Ps[b].near
    P.win = Ps[b].win
    return P


@wp.kernel(cuda_max_registers=GATHER_MAX_REGISTERS)
def integrate_voxels_batch(
    P0: PingParams,
    Ps: wp.array(dtype=PingParams),
    boxes: wp.array2d(dtype=int),
    box_lo: wp.vec3i,
    box_n: wp.vec3i,
    images: wp.array3d(dtype=float),
    tan_edges: wp.array(dtype=float),
    lut: wp.array(dtype=int),
    tables: wp.array2d(dtype=float),
    first_bright: wp.array2d(dtype=int),
    index: wp.array(dtype=int),
    grid: wp.array(dtype=float),
    bright: wp.array(dtype=float),
    count: wp.array(dtype=wp.uint64),
    seen: wp.array(dtype=wp.uint8),
    err: wp.array(dtype=int),
):
    """One thread per voxel of the union box (box_lo, box_n), k fastest (a warp walks a column's
    contiguous voxels): it folds ping 0, 1, ... into the voxel, each ping only within that ping's
    box (``boxes[b]``). The voxel's values live in registers from its first view and are written
    once, where they changed; a ping's parameters are read only while that ping is folded, so
    few registers stay live. (A thread per chunk of a column walking each ping's column range, as
    integrate_gather does for one ping, held a whole ping's parameters in registers and ran 1.2-1.5x
    slower on an H100: bench/results/gpu_scale_variants.json.)"""
    tid = wp.tid()
    col = tid // box_n[2]
    k = box_lo[2] + tid - col * box_n[2]
    i = box_lo[0] + col // box_n[1]
    j = box_lo[1] + col - (col // box_n[1]) * box_n[1]
    c = voxel_centre(P0, i, j, k)
    a = int(-1)
    hit = int(0)
    g0 = float(0.0)
    g = float(0.0)
    br0 = float(0.0)
    br = float(0.0)
    n0 = wp.uint64(0)
    n = wp.uint64(0)
    for b in range(Ps.shape[0]):
        inside = i >= boxes[b, 0] and i < boxes[b, 0] + boxes[b, 3] and j >= boxes[b, 1]
        if inside and j < boxes[b, 1] + boxes[b, 4] and k >= boxes[b, 2] and k < boxes[b, 2] + boxes[b, 5]:
            P = ping_of(P0, Ps, b)
            vc = voxel_ping_value(P, c, images[b], tan_edges, lut, tables[b], first_bright[b])
            v = vc[0]
            if v >= 0.0:
                if hit == 0:  # the first view: find the voxel and read its values
                    hit = 1
                    a = voxel_address(P, index, i, j, k)
                    if a >= 0:
                        g0 = grid[a]
                        g = g0
                        if P.rule != 0:
                            br0 = bright[a]
                            br = br0
                            n0 = count[a]
                            n = n0
                if a >= 0:
                    if v < g:
                        g = v
                    if P.rule != 0:
                        if v >= P.thr and v < br:
                            br = v
                        n = counted(P, v, vc[1], n)
    if hit != 0:
        if a < 0:
            err[0] = 1
        else:
            if g < g0:
                grid[a] = g
            if br < br0:
                bright[a] = br
            if n != n0:
                count[a] = n
            slot = a // (P0.blk * P0.blk * P0.blk_z)
            if seen[slot] == wp.uint8(0):
                seen[slot] = wp.uint8(1)


@wp.kernel
def integrate_template(
    P: PingParams,
    image: wp.array2d(dtype=float),
    tan_edges: wp.array(dtype=float),
    lut: wp.array(dtype=int),
    table: wp.array(dtype=float),
    first_bright: wp.array(dtype=int),
    template_S: wp.array(dtype=wp.vec3),
    index: wp.array(dtype=int),
    grid: wp.array(dtype=float),
    seen: wp.array(dtype=wp.uint8),
):
    """One thread per template point: the paper's steps 1-6."""
    tid = wp.tid()
    q = P.R * template_S[tid] + P.t  # step 1
    i = int(wp.floor((q[0] - P.origin[0]) / P.voxel))  # step 2
    j = int(wp.floor((q[1] - P.origin[1]) / P.voxel))
    k = int(wp.floor((q[2] - P.origin[2]) / P.voxel))
    if i < 0 or j < 0 or k < 0 or i >= P.dims[0] or j >= P.dims[1] or k >= P.dims[2]:
        return
    v = voxel_ping_value(P, voxel_centre(P, i, j, k), image, tan_edges, lut, table, first_bright)[0]  # 3-5
    if v >= 0.0:
        # step 6; several template points may land in one voxel: all carry the same value
        a = voxel_address(P, index, i, j, k)
        if a >= 0:
            wp.atomic_min(grid, a, v)
            seen[a // (P.blk * P.blk * P.blk_z)] = wp.uint8(1)  # its block holds an observed voxel
