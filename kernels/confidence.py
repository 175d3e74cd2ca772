"""The confidence layer's per-ping pass in NVIDIA Warp (device code only; twin: ``confidence.cl``).

One ping, after its update (the rules: ``gpumap.layers.confidence``; the NumPy reference:
``gpumap.layers.confidence.confirm_ping``), in four launches on one stream (the host,
``gpumap/layers/confidence_device.py``):

1. ``lit_bits``: one thread per 32 beams of a bin row: its lit cells (``>= thr``) as bits, and
   their rival counts zeroed.
2. ``conf_voxels``: one thread per (i, j) column of the ping's box, walking the column's voxels
   that the rivals' region can hold: each voxel the ping observes gets its elevation arc's bit in
   ``arcs``; each rival (not known free, in the widened field of view) adds one to its centre
   cell of the rival table (an int32 atomic: exact in any order) and keeps that cell in ``cells``
   (box order); each observed voxel that is not known free goes on the candidate list (an atomic
   counter) with its arc's neighbour pair.
3. ``prefix_rows``: one thread per bin row: the rivals' running counts along its beams.
4. ``conf_candidates``: one thread per candidate: no rival in its cells within tube + rho but
   itself and its neighbours (at most 27, so most are settled after a few reads), bright in this
   ping (a lit cell in its footprint) and the echo (a lit cell within ``tube``): ``confirmed = 1``
   (a flag: the same in any order).

On CPUs the host runs the two whole-image passes (1, 3) in NumPy, and each of two threads walks
half the columns into its own rival table and candidate list (``part``): Warp's CPU atomics are
plain adds. Arguments, in order: the ping parameters (``PingParams``,
``gpumap.geometry.PING_DTYPE`` field for field: a copy of ``minmax.PingParams``, kept here so the
two kernel families build on their own), then per kernel what it reads and writes, then its
scalars (cos and sin of the rivals' half aperture, the tube, the column walk's widened range and
slab, the value rule's options, the widest beam), then where a launch split over threads starts.
``beam_index_lo``, the block addressing and the arc direction are copies of ``minmax``/``viewgain``'s,
with the same arithmetic.
"""

import warp as wp

from .common import COUNT_LOW, PingParams, arc_step, beam_index_lo  # noqa: F401

# No FMA contraction: every device rounds as the NumPy reference does, bit for bit.
wp.set_module_options({"fuse_fp": False})


@wp.func
def beam_span(t: float, h2: float, w: float, tan_edges: wp.array(dtype=float), lut: wp.array(dtype=int),
              P: PingParams) -> wp.vec2i:
    """First and last beam a sphere of radius w spans (``gpumap.reference.beam_span``)."""
    j0 = int(0)
    j1 = P.n_beams - 1
    q = h2 - w * w
    if q > 0.0:
        u = w / wp.sqrt(q)
        d0 = 1.0 + t * u
        d1 = 1.0 - t * u
        if d0 > 0.0:
            j0 = beam_index_lo((t - u) / d0, tan_edges, lut, P)
        if d1 > 0.0:
            j1 = beam_index_lo((t + u) / d1, tan_edges, lut, P)
    return wp.vec2i(j0, j1)


@wp.func
def bin_clip(x: float, n_bins: int) -> int:
    """floor(x) clipped to [0, n_bins - 1] (clipped as a float: any x is safe)."""
    f = wp.floor(x)
    if f <= 0.0:
        return 0
    if f >= float(n_bins - 1):
        return n_bins - 1
    return int(f)


@wp.func
def count_in(R: wp.array(dtype=int), w: int, b0: int, b1: int, j0: int, j1: int, most: int) -> int:
    """The count over bins b0..b1 and beams j0..j1 of a table of per-row running counts
    (``R[i w + j]``: the count of bin i's beams < j, ``w = n_beams + 1``), or the first partial sum
    past ``most`` (the caller asks whether it equals a number <= most)."""
    s = int(0)
    for i in range(b0, b1 + 1):
        s += R[i * w + j1 + 1] - R[i * w + j0]
        if s > most:
            return s
    return s


@wp.func
def any_lit(L: wp.array(dtype=wp.uint32), nw: int, b0: int, b1: int, j0: int, j1: int) -> int:
    """1 when a cell of bins b0..b1 and beams j0..j1 is lit: ``L[i nw + j // 32]`` holds beam j's bit
    ``j % 32`` of bin i."""
    w0 = j0 >> 5
    w1 = j1 >> 5
    lo = wp.uint32(0xFFFFFFFF) << wp.uint32(j0 & 31)
    hi = wp.uint32(0xFFFFFFFF) >> wp.uint32(31 - (j1 & 31))
    for i in range(b0, b1 + 1):
        row = i * nw
        if w0 == w1:
            if (L[row + w0] & lo & hi) != wp.uint32(0):
                return 1
        else:
            if (L[row + w0] & lo) != wp.uint32(0) or (L[row + w1] & hi) != wp.uint32(0):
                return 1
            for w in range(w0 + 1, w1):
                if L[row + w] != wp.uint32(0):
                    return 1
    return 0


@wp.func
def column_of(P: PingParams, i: int, j: int) -> wp.vec3i:
    """Column (i, j) in the block index (``minmax.voxel_address``'s work that k leaves alone): (1 if the
    index spans it else 0, the index entry of its first block, the offset of its voxels in a block)."""
    B = P.blk
    ri = i - P.blk_lo[0]
    rj = j - P.blk_lo[1]
    if ri < 0 or rj < 0:
        return wp.vec3i(0, 0, 0)
    bi = ri // B
    bj = rj // B
    if bi >= P.blk_n[0] or bj >= P.blk_n[1]:
        return wp.vec3i(0, 0, 0)
    return wp.vec3i(1, (bi * P.blk_n[1] + bj) * P.blk_n[2], ((ri - bi * B) * B + (rj - bj * B)) * P.blk_z)


@wp.func
def column_address(P: PingParams, index: wp.array(dtype=int), col: wp.vec3i, k: int) -> int:
    """``minmax.voxel_address`` of voxel k of a column (``col``: :func:`column_of`; -1: no block); a
    bounded box's column is one block (no division)."""
    rk = k - P.blk_lo[2]
    if col[0] == 0 or rk < 0:
        return -1
    Bz = P.blk_z
    bk = int(0)
    if rk >= Bz:
        bk = rk // Bz
    if bk >= P.blk_n[2]:
        return -1
    slot = index[col[1] + bk]
    if slot < 0:
        return -1
    return slot * P.blk * P.blk * Bz + col[2] + rk - bk * Bz


@wp.func
def not_free(
    P: PingParams,
    a: int,
    grid: wp.array(dtype=float),
    bright: wp.array(dtype=float),
    count: wp.array(dtype=wp.uint64),
    carve_views: int,
    p_min: wp.float64,
    rhs: wp.float64,
) -> int:
    """1 when the map value of pool address a (-1: no block, unknown) is >= thr or unknown: the
    rule's value (``gpumap.reference.visible_values`` / ``evidence_values``, the evidence test in
    float64 in the reference's order), else 0."""
    if a < 0:
        return 1
    v = grid[a]
    if P.rule != 0:
        b = bright[a]
        if wp.isfinite(b):
            c = count[a]
            keep = int(0)
            if P.rule == 1:
                if (c & COUNT_LOW) < wp.uint64(carve_views):
                    keep = 1
            else:
                hits = c >> wp.uint64(32)
                if hits > wp.uint64(0):
                    k = wp.float64(hits)
                    n = k + wp.float64(c & COUNT_LOW)
                    share = k / n
                    d = p_min - share
                    if share >= p_min or d * d * n <= rhs:
                        keep = 1
            if keep != 0:
                v = b
    if v >= P.thr:
        return 1
    return 0


@wp.func
def echo_lit(
    P: PingParams,
    r: float,
    h2: float,
    t: float,
    lit: wp.array(dtype=wp.uint32),
    tan_edges: wp.array(dtype=float),
    lut: wp.array(dtype=int),
    tube: float,
) -> int:
    """1 when the voxel at (r, h^2, t) is bright in the ping (a lit cell in its footprint: the
    mapping's bins and beams) and a lit cell lies within ``tube`` of its centre (the echo)."""
    nb = P.n_bins
    first = int(wp.floor((r - P.near - P.rmin) * P.inv_dr))
    b0 = wp.max(first, 0)
    b1 = wp.min(first + P.win - 1, nb - 1)
    js = beam_span(t, h2, P.rho, tan_edges, lut, P)
    if any_lit(lit, (P.n_beams + 31) // 32, b0, b1, js[0], js[1]) == 0:
        return 0
    b0 = bin_clip((r - tube - P.rmin) * P.inv_dr, nb)
    b1 = bin_clip((r + tube - P.rmin) * P.inv_dr, nb)
    js = beam_span(t, h2, tube, tan_edges, lut, P)
    if any_lit(lit, (P.n_beams + 31) // 32, b0, b1, js[0], js[1]) == 0:
        return 0
    return 1


@wp.kernel
def lit_bits(P: PingParams, image: wp.array2d(dtype=float), lit: wp.array(dtype=wp.uint32),
             rivals: wp.array(dtype=int), n_cand: wp.array(dtype=int), offset: int):
    """One thread per word of a bin row (``offset``: the first word, a launch split over threads):
    the row's lit cells (>= thr) as bits, ``lit[i nw + j // 32]`` bit ``j % 32``, and the rival
    counts of those cells zeroed; thread 0 also empties the candidate lists."""
    q = wp.tid() + offset
    nw = (P.n_beams + 31) // 32
    i = q // nw
    w = q - i * nw
    word = wp.uint32(0)
    for j in range(w * 32, wp.min(w * 32 + 32, P.n_beams)):
        if image[i, j] >= P.thr:
            word = word | (wp.uint32(1) << wp.uint32(j - w * 32))
        rivals[i * P.n_beams + j] = 0
    lit[q] = word
    if q == 0:
        n_cand[0] = 0
        n_cand[1] = 0


@wp.kernel
def prefix_rows(P: PingParams, rivals: wp.array(dtype=int), running: wp.array(dtype=int), offset: int):
    """One thread per bin row i (from ``offset``): ``running[i, j]`` = the rivals of bin i's beams < j
    (``n_beams + 1`` a row)."""
    i = wp.tid() + offset
    w = P.n_beams + 1
    s = int(0)
    running[i * w] = 0
    for j in range(P.n_beams):
        s += rivals[i * P.n_beams + j]
        running[i * w + j + 1] = s


@wp.kernel
def conf_voxels(
    P: PingParams,
    tan_edges: wp.array(dtype=float),
    lut: wp.array(dtype=int),
    index: wp.array(dtype=int),
    grid: wp.array(dtype=float),
    bright: wp.array(dtype=float),
    count: wp.array(dtype=wp.uint64),
    arcs: wp.array(dtype=wp.uint16),
    rivals: wp.array(dtype=int),
    cells: wp.array(dtype=int),
    cand: wp.array(dtype=int),
    steps: wp.array(dtype=int),
    n_cand: wp.array(dtype=int),
    cos_hv: float,
    sin_hv: float,
    tube: float,
    rmax_c: float,
    slab_c: float,
    carve_views: int,
    p_min: wp.float64,
    rhs: wp.float64,
    offset: int,
    part: int,
    stride: int,
):
    """One thread per (i, j) column of the box (from column ``offset``), over the column's voxels
    (see the module): arcs, the rivals' counts, each box voxel's rival cell (``cells``, box order:
    bin n_beams + beam, -1 not a rival) and the candidates (observed, not known free), each with the
    neighbour pair its elevation arc runs along (``steps``, the bit of ``arcs``). ``part``: which
    rival table (``part`` n_bins n_beams on) and candidate list (``cand[part stride:]``, its length
    ``n_cand[part]``) the thread adds to (a launch split over CPU threads, whose atomics are plain adds:
    each part its own; GPUs part 0)."""
    col = wp.tid() + offset
    n2b = P.box_n[2]
    i = P.box_lo[0] + col // P.box_n[1]
    j = P.box_lo[1] + col - (col // P.box_n[1]) * P.box_n[1]
    cx = P.origin[0] + (float(i) + 0.5) * P.voxel
    cy = P.origin[1] + (float(j) + 0.5) * P.voxel
    # the z-range of the column that the rivals' region (range < rmax_c, |z_S| < slab_c, the fan's
    # wedge) can hold, padded by a voxel: a relaxation, the per-voxel tests stay exact
    k0 = P.box_lo[2]
    k1 = k0 - 1
    dx = cx - P.t[0]
    dy = cy - P.t[1]
    q = rmax_c * rmax_c - dx * dx - dy * dy
    if q > 0.0:
        hw = wp.sqrt(q)
        z0 = P.t[2] - hw
        z1 = P.t[2] + hw
        p0x = P.A[0, 0] * cx + P.A[0, 1] * cy + P.b[0]
        p0y = P.A[1, 0] * cx + P.A[1, 1] * cy + P.b[1]
        p0z = P.A[2, 0] * cx + P.A[2, 1] * cy + P.b[2]
        pad = 1.0e-4 * (1.0 + rmax_c)  # loosens each half-space against rounding (never tightens)
        for h in range(4):
            alpha = float(0.0)
            beta = float(0.0)
            if h == 0:
                alpha = P.wedge[0] * p0x + P.wedge[1] * p0y
                beta = P.wedge[0] * P.A[0, 2] + P.wedge[1] * P.A[1, 2]
            elif h == 1:
                alpha = P.wedge[2] * p0x + P.wedge[3] * p0y
                beta = P.wedge[2] * P.A[0, 2] + P.wedge[3] * P.A[1, 2]
            elif h == 2:
                alpha = slab_c - p0z
                beta = -P.A[2, 2]
            else:
                alpha = slab_c + p0z
                beta = P.A[2, 2]
            alpha = alpha + pad
            if wp.abs(beta) < 1.0e-12:
                if alpha < 0.0:
                    z1 = z0 - 1.0
            elif beta > 0.0:
                z0 = wp.max(z0, -alpha / beta)
            else:
                z1 = wp.min(z1, -alpha / beta)
        if z0 <= z1:
            k0 = wp.max(P.box_lo[2], int(wp.ceil((z0 - P.origin[2]) / P.voxel - 0.5)) - 1)
            k1 = wp.min(P.box_lo[2] + n2b - 1, int(wp.floor((z1 - P.origin[2]) / P.voxel - 0.5)) + 1)
    nb = P.n_bins
    ny = P.dims[1]
    nz = P.dims[2]
    base = col * n2b - P.box_lo[2]
    colb = column_of(P, i, j)
    for k in range(P.box_lo[2], P.box_lo[2] + n2b):
        cell = int(-1)
        if k >= k0 and k <= k1:
            cz = P.origin[2] + (float(k) + 0.5) * P.voxel
            x = P.A[0, 0] * cx + P.A[0, 1] * cy + P.A[0, 2] * cz + P.b[0]
            y = P.A[1, 0] * cx + P.A[1, 1] * cy + P.A[1, 2] * cz + P.b[1]
            z = P.A[2, 0] * cx + P.A[2, 1] * cy + P.A[2, 2] * cz + P.b[2]
            t = y / x
            if x > 0.0 and t >= P.tan_lo and t <= P.tan_hi:
                h2 = x * x + y * y
                r = wp.sqrt(h2 + z * z)
                seen = r >= P.rmin and r < P.rmax and z * z <= P.tan2_half_vfov * h2
                near = (r >= P.rmin - P.rho and r < P.rmax + P.rho
                        and wp.abs(z) * cos_hv - wp.sqrt(h2) * sin_hv <= P.rho)
                flat = (i * ny + j) * nz + k
                bit = int(0)
                if seen:
                    # the elevation arc's direction (-x z, -y z, h^2) to the world, its pair bit
                    ex = -(x * z)
                    ey = -(y * z)
                    ez = h2
                    wx = P.A[0, 0] * ex + P.A[1, 0] * ey + P.A[2, 0] * ez
                    wy = P.A[0, 1] * ex + P.A[1, 1] * ey + P.A[2, 1] * ez
                    wz = P.A[0, 2] * ex + P.A[1, 2] * ey + P.A[2, 2] * ez
                    n2 = wx * wx + wy * wy + wz * wz
                    m = (arc_step(wx, n2) + 1) * 9 + (arc_step(wy, n2) + 1) * 3 + (arc_step(wz, n2) + 1)
                    bit = wp.max(m, 26 - m) - 14
                    arcs[flat] = arcs[flat] | wp.uint16(1 << bit)
                if seen or near:
                    a = column_address(P, index, colb, k)
                    if not_free(P, a, grid, bright, count, carve_views, p_min, rhs) != 0:
                        if near:
                            cb = bin_clip((r - P.rmin) * P.inv_dr, nb)
                            cj = beam_index_lo(t, tan_edges, lut, P)
                            cell = cb * P.n_beams + cj
                            wp.atomic_add(rivals, part * P.n_bins * P.n_beams + cell, 1)
                        if seen:  # a candidate, with its elevation arc's neighbour pair
                            c = part * stride + wp.atomic_add(n_cand, part, 1)
                            cand[c] = flat
                            steps[c] = bit
        cells[base + k] = cell


@wp.kernel
def conf_candidates(
    P: PingParams,
    tan_edges: wp.array(dtype=float),
    lut: wp.array(dtype=int),
    lit: wp.array(dtype=wp.uint32),
    running: wp.array(dtype=int),
    cells: wp.array(dtype=int),
    cand: wp.array(dtype=int),
    steps: wp.array(dtype=int),
    n_cand: wp.array(dtype=int),
    confirmed: wp.array(dtype=wp.uint8),
    tube: float,
    beam_max: float,
    offset: int,
    part: int,
    stride: int,
):
    """One thread per candidate of list ``part`` (``cand[part stride:]``, from ``offset``; threads
    past its length return): confirmed when the rivals whose centre cell lies within tube + rho of
    it are itself and its neighbours in the box."""
    c = wp.tid() + offset
    if c >= n_cand[part]:
        return
    c = part * stride + c
    flat = cand[c]
    ny = P.dims[1]
    nz = P.dims[2]
    i = flat // (ny * nz)
    j = (flat // nz) - i * ny
    k = flat - (i * ny + j) * nz
    li = i - P.box_lo[0]
    lj = j - P.box_lo[1]
    lk = k - P.box_lo[2]
    cx = P.origin[0] + (float(i) + 0.5) * P.voxel
    cy = P.origin[1] + (float(j) + 0.5) * P.voxel
    cz = P.origin[2] + (float(k) + 0.5) * P.voxel
    x = P.A[0, 0] * cx + P.A[0, 1] * cy + P.A[0, 2] * cz + P.b[0]
    y = P.A[1, 0] * cx + P.A[1, 1] * cy + P.A[1, 2] * cz + P.b[1]
    z = P.A[2, 0] * cx + P.A[2, 1] * cy + P.A[2, 2] * cz + P.b[2]
    h2 = x * x + y * y
    r = wp.sqrt(h2 + z * z)
    t = y / x
    nb = P.n_bins
    wide = tube + P.rho
    # First a few reads that settle most candidates: a rival two or three steps along the arc (not a
    # neighbour) whose cell lies within kb bins and mb beams of the voxel's own lies within its cells
    # within wide (kb, mb: two bins and two of the widest beams short of wide, far more than any
    # rounding), so it rules the voxel out without the exact cells.
    own_cell = cells[(li * P.box_n[1] + lj) * P.box_n[2] + lk]
    kb = int(wide * P.inv_dr) - 2
    mb = int(-1)
    hb = wp.sqrt(h2) * beam_max
    if hb > 0.0:
        mb = int(wp.min(wide / hb, 1.0e6)) - 2
    if own_cell >= 0 and kb >= 0 and mb >= 0:
        ob = own_cell // P.n_beams
        oj = own_cell - ob * P.n_beams
        m = steps[c] + 14
        si = m // 9 - 1
        sj = (m // 3) % 3 - 1
        sk = m % 3 - 1
        for e in range(4):
            d = e - 3
            if e >= 2:
                d = e
            qi = li + d * si
            qj = lj + d * sj
            qk = lk + d * sk
            qin = qi >= 0 and qi < P.box_n[0] and qj >= 0 and qj < P.box_n[1]
            if qin and qk >= 0 and qk < P.box_n[2]:
                pc = cells[(qi * P.box_n[1] + qj) * P.box_n[2] + qk]
                if pc >= 0:
                    pcb = pc // P.n_beams
                    if wp.abs(pcb - ob) <= kb and wp.abs(pc - pcb * P.n_beams - oj) <= mb:
                        return
    b0 = bin_clip((r - wide - P.rmin) * P.inv_dr, nb)
    b1 = bin_clip((r + wide - P.rmin) * P.inv_dr, nb)
    js = beam_span(t, h2, wide, tan_edges, lut, P)
    j0 = js[0]
    j1 = js[1]
    total = count_in(running, P.n_beams + 1, b0, b1, j0, j1, 27)
    if total > 27:  # more than the voxel and its 26 neighbours could be
        return
    if echo_lit(P, r, h2, t, lit, tan_edges, lut, tube) == 0:
        return
    own = int(0)
    for di in range(-1, 2):
        for dj in range(-1, 2):
            for dk in range(-1, 2):
                ii = li + di
                jj = lj + dj
                kk = lk + dk
                inside = ii >= 0 and ii < P.box_n[0] and jj >= 0 and jj < P.box_n[1]
                if inside and kk >= 0 and kk < P.box_n[2]:
                    cell = cells[(ii * P.box_n[1] + jj) * P.box_n[2] + kk]
                    if cell >= 0:
                        cb = cell // P.n_beams
                        cj = cell - cb * P.n_beams
                        if cb >= b0 and cb <= b1 and cj >= j0 and cj <= j1:
                            own += 1
    if total == own:
        confirmed[flat] = wp.uint8(1)
