// Min-max occupancy kernels in OpenCL C 1.2 (device code only; twin: minmax.py).
// Same arguments in the same order as the Warp kernels: ping parameters, image, tangents of the beam edges,
// beam look-up table, max table, first bright bin per beam, [template,] grid [, bright minimum, clear-dark
// count]. (Warp tells "no table" by an empty array; OpenCL, which has no empty buffers, by the extra
// use_table flag after the table.) PingParams matches gpumap.geometry.PING_DTYPE field for field.

// No FMA contraction: every device then rounds as the NumPy oracle does, bit for bit.
#pragma OPENCL FP_CONTRACT OFF

// PingParams, COUNT_LOW and arc_step: common.cl, which the host prepends.

// Largest beam j in [0, n_beams - 1] with tan_edges[j] <= t (0 when none), t = tan(azimuth). A
// uniform look-up table over the fan's tangents guesses within a step or two; exact comparisons
// with the edges settle it.
inline int beam_index_lo(float t, __global const float *tan_edges, __global const int *lut, int lut_n,
                         const PingParams *P)
{
    int j = lut[clamp((int)floor((t - P->tan_lo) * P->lut_scale), 0, lut_n - 1)];
    j += (j < P->n_beams - 1 && tan_edges[j + 1] <= t);  // the loop's usual single step, without a branch
    while (j < P->n_beams - 1 && tan_edges[j + 1] <= t) ++j;
    while (j > 0 && tan_edges[j] > t) --j;
    return j;
}

// Max image value over the footprint of the voxel centred at c (world); -1 if unobserved. *clear is
// set (visible and evidence rules, dark values < thr) to 1 when first_bright (per beam, the first bin
// >= thr) puts no return nearer than the footprint's first bin in any of its beams, else 0 (and 0 for
// bright values, whose update never reads it).
// Footprint: bins [b0, b0 + win - 1] x beams [j0, j1], reaching near = rho + shadow_m towards
// the sonar. With a max table (use_table) the
// max is two reads; without, a loop over the cells (faster on GPUs: no table to build).
inline float footprint_value(const PingParams *P, int first, int j0, int j1, __global const float *image,
                             __global const float *table, int use_table, __global const int *first_bright,
                             int *clear);
inline int view_clear(int j0, int j1, int b0, __global const int *first_bright);

inline float voxel_ping_value(const PingParams *P, float cx, float cy, float cz,
                              __global const float *image, __global const float *tan_edges,
                              __global const int *lut, __global const float *table, int use_table,
                              __global const int *first_bright, int *clear)
{
    *clear = 0;
    float x = P->A[0] * cx + P->A[1] * cy + P->A[2] * cz + P->b[0];
    float y = P->A[3] * cx + P->A[4] * cy + P->A[5] * cz + P->b[1];
    float z = P->A[6] * cx + P->A[7] * cy + P->A[8] * cz + P->b[2];
    if (x <= 0.0f) return -1.0f;  // the fan lies within +-90 deg of boresight
    float h2 = x * x + y * y;
    float r = sqrt(h2 + z * z);
    if (r < P->rmin || r >= P->rmax) return -1.0f;
    if (z * z > P->tan2_half_vfov * h2) return -1.0f;
    float t = y / x;  // tan(azimuth): monotonic over the fan, so no atan2 is needed
    if (t < P->tan_lo || t > P->tan_hi) return -1.0f;
    int first = (int)floor((r - P->near - P->rmin) * P->inv_dr);  // < 0 near the blanking range
    int j0 = 0, j1 = P->n_beams - 1;
    float q = h2 - P->rho * P->rho;
    if (q > 0.0f) {  // the sphere spans azimuths theta -+ asin(rho / h); in tangents:
        float u = P->rho / sqrt(q);  // tan(asin(rho / h))
        float d0 = 1.0f + t * u, d1 = 1.0f - t * u;
        if (d0 > 0.0f) j0 = beam_index_lo((t - u) / d0, tan_edges, lut, P->lut_n, P);
        if (d1 > 0.0f) j1 = beam_index_lo((t + u) / d1, tan_edges, lut, P->lut_n, P);
    }
    return footprint_value(P, first, j0, j1, image, table, use_table, first_bright, clear);
}

// The max over the footprint of bins [max(first, 0), first + win - 1] x beams [j0, j1] (the second half
// of voxel_ping_value), and *clear as voxel_ping_value sets it.
inline float footprint_value(const PingParams *P, int first, int j0, int j1, __global const float *image,
                             __global const float *table, int use_table, __global const int *first_bright,
                             int *clear)
{
    *clear = 0;
    int b0 = max(first, 0);
    int b1 = min(first + P->win - 1, P->n_bins - 1);
    float v = 0.0f;
    if (use_table && first >= 0) {  // two reads (more near the apex)
        // the largest level k < n_levels with 2^k <= the span (0 for spans of 1 beam or none)
        int span = j1 - j0 + 1;
        int k = span > 1 ? min(31 - (int)clz(span), P->n_levels - 1) : 0;
        int w = 1 << k;
        __global const float *t = table + ((size_t)k * P->n_bins + b0) * P->n_beams;
        v = t[j1 - w + 1];
        for (int jj = j0; jj <= j1 - w + 1; jj += w) v = fmax(v, t[jj]);
    } else {
        for (int i = b0; i <= b1; ++i) {
            __global const float *row = image + (size_t)i * P->n_beams;
            for (int j = j0; j <= j1; ++j) v = fmax(v, row[j]);
        }
    }
    if (P->rule != 0 && v < P->thr) *clear = view_clear(j0, j1, b0, first_bright);  // only a dark
    return v;  // view's count reads clear (update_voxel)
}

// 1 when no beam j0..j1 has a return (first_bright) nearer than bin b0, else 0.
inline int view_clear(int j0, int j1, int b0, __global const int *first_bright)
{
    for (int jj = j0; jj <= j1; ++jj) {
        if (first_bright[jj] < b0) return 0;
    }
    return 1;
}

// One work-item per pixel: an 8-bit image to float32 intensities, dst = src * scale (1/255).
__kernel void convert_u8(__global const uchar *src, const float scale, __global float *dst, const int n)
{
    int c = get_global_id(0);
    if (c < n) dst[c] = (float)src[c] * scale;
}

// One work-item per beam j: level 0 of the max table, table[0, i, j] = max of image over bins
// [i, i + win - 1] (clipped), by van Herk / Gil-Werman: prefix and suffix maxima in blocks of
// win bins (kept in the two scratch levels after the table), 3 ops per cell.
__kernel void build_bin_window(const PingParams P, __global const float *image,
                               __global float *table)
{
    int j = get_global_id(0);
    if (j >= P.n_beams) return;
    int nb = P.n_beams;
    size_t plane = (size_t)P.n_bins * nb;
    __global float *pre = table + P.n_levels * plane;
    __global float *suf = pre + plane;
    for (int i = 0; i < P.n_bins; ++i) {
        float v = image[(size_t)i * nb + j];
        if (i % P.win != 0) v = fmax(v, pre[(size_t)(i - 1) * nb + j]);
        pre[(size_t)i * nb + j] = v;
    }
    for (int i = P.n_bins - 1; i >= 0; --i) {
        float v = image[(size_t)i * nb + j];
        if ((i + 1) % P.win != 0 && i + 1 < P.n_bins) v = fmax(v, suf[(size_t)(i + 1) * nb + j]);
        suf[(size_t)i * nb + j] = v;
    }
    for (int i = 0; i < P.n_bins; ++i) {
        int e = min(i + P.win - 1, P.n_bins - 1);
        float v = suf[(size_t)i * nb + j];
        if (e / P.win != i / P.win) v = fmax(v, pre[(size_t)e * nb + j]);  // reaches the next block
        table[(size_t)i * nb + j] = v;
    }
}

// One work-item per beam j: the first bin whose intensity is >= thr (n_bins if none).
__kernel void find_first_bright(const PingParams P, __global const float *image, __global int *first_bright)
{
    int j = get_global_id(0);
    if (j >= P.n_beams) return;
    int f = P.n_bins;
    for (int i = 0; i < P.n_bins; ++i) {
        if (image[(size_t)i * P.n_beams + j] >= P.thr) { f = i; break; }
    }
    first_bright[j] = f;
}

// One work-item per beam: no bright bin yet (n_bins); find_first_bright_cells lowers it.
__kernel void first_bright_init(const PingParams P, __global int *first_bright)
{
    int j = get_global_id(0);
    if (j < P.n_beams) first_bright[j] = P.n_bins;
}

// GPU twin of find_first_bright: one work-item per cell, an atomic min per bright cell (the
// minimum is the same in any order: deterministic).
__kernel void find_first_bright_cells(const PingParams P, __global const float *image,
                                      __global int *first_bright)
{
    int c = get_global_id(0);
    if (c >= P.n_bins * P.n_beams) return;
    if (image[c] >= P.thr) atomic_min(first_bright + c % P.n_beams, c / P.n_beams);
}

// Fold one view (value v, clear) into voxel idx: the plain min, and for the visible and evidence rules
// the bright min and the view counts (see gpumap.reference). count packs clear dark views (low 32 bits)
// and bright views (high 32 bits), each saturating on its own (the visible rule's dark count at 255).
// The packed view counts c after one view (v, clear) under the visible or evidence rule: a bright view
// raises the bright count, a clear dark one the dark count (the visible rule's by 2 below thr_dark, to
// 255), each saturating.
inline ulong counted(const PingParams *P, float v, int clear, ulong c)
{
    if (v >= P->thr) return c < 0xFFFFFFFF00000000UL ? c + 0x100000000UL : c;
    if (!clear) return c;
    ulong dark = c & 0xFFFFFFFFUL;
    ulong cap = P->rule == 1 ? 255UL : 0xFFFFFFFFUL;
    ulong step = (P->rule == 1 && v < P->thr_dark) ? 2UL : 1UL;
    return dark < cap ? (c - dark) + min(dark + step, cap) : c;
}

inline void update_voxel(const PingParams *P, size_t idx, float v, int clear, __global float *grid,
                         __global float *bright, __global ulong *count)
{
    if (v < grid[idx]) grid[idx] = v;  // a write only where the value falls (memory traffic bounds it)
    if (P->rule != 0) {  // count is read only where it may change (a dark view behind a return leaves it)
        if (v >= P->thr && v < bright[idx]) bright[idx] = v;
        if (v >= P->thr || clear) {
            ulong c = count[idx], n = counted(P, v, clear, c);
            if (n != c) count[idx] = n;
        }
    }
}

// One work-item per bin row i: table[k, i, j] = max of level 0 over beams [j, j + 2^k - 1]
// (clipped), for 0 < k < n_levels.
__kernel void build_beam_levels(const PingParams P, __global float *table)
{
    int i = get_global_id(0);
    if (i >= P.n_bins) return;
    int step = 1;
    for (int k = 1; k < P.n_levels; ++k, step *= 2) {
        __global float *cur = table + ((size_t)k * P.n_bins + i) * P.n_beams;
        __global const float *prev = cur - (size_t)P.n_bins * P.n_beams;
        for (int j = 0; j < P.n_beams; ++j) cur[j] = fmax(prev[j], prev[min(j + step, P.n_beams - 1)]);
    }
}

// GPU twin of build_bin_window: one work-item per cell (i, j), win reads each.
__kernel void build_bin_window_cells(const PingParams P, __global const float *image,
                                     __global float *table)
{
    int c = get_global_id(0);
    if (c >= P.n_bins * P.n_beams) return;
    int i = c / P.n_beams, j = c % P.n_beams;
    float v = 0.0f;
    for (int b = i; b < min(i + P.win, P.n_bins); ++b) v = fmax(v, image[(size_t)b * P.n_beams + j]);
    table[c] = v;
}

// GPU twin of build_beam_levels: one work-item per cell (i, j), reading level 0 only
// (2^(n_levels - 1) reads), so every level comes from one launch.
__kernel void build_beam_levels_cells(const PingParams P, __global float *table)
{
    int c = get_global_id(0);
    if (c >= P.n_bins * P.n_beams) return;
    int i = c / P.n_beams, j = c % P.n_beams;
    __global const float *row = table + (size_t)i * P.n_beams;
    float v = row[j];
    for (int k = 1, w = 1; k < P.n_levels; ++k, w *= 2) {
        for (int jj = w; jj < 2 * w; ++jj) v = fmax(v, row[min(j + jj, P.n_beams - 1)]);
        table[((size_t)k * P.n_bins + i) * P.n_beams + j] = v;
    }
}

// Intersect the interval [*lo, *hi] with {z : alpha + beta z >= 0}.
inline void clip_linear(float *lo, float *hi, float alpha, float beta)
{
    if (fabs(beta) < 1.0e-12f) {
        if (alpha < 0.0f) { *lo = 1.0f; *hi = -1.0f; }
        return;
    }
    float zc = -alpha / beta;
    if (beta > 0.0f) *lo = fmax(*lo, zc); else *hi = fmin(*hi, zc);
}

// World z-interval of the column (cx, cy) that can hold imaged points: the column cut by the
// range sphere, the azimuth half-planes and the elevation slab, all of which contain the field
// of view. A relaxation, so conservative; the per-voxel test stays exact.
inline void column_range(const PingParams *P, float cx, float cy, float *lo, float *hi)
{
    float dx = cx - P->t[0], dy = cy - P->t[1];
    float q = P->rmax * P->rmax - dx * dx - dy * dy;
    if (q <= 0.0f) { *lo = 1.0f; *hi = -1.0f; return; }
    float w = sqrt(q);
    *lo = P->t[2] - w;
    *hi = P->t[2] + w;
    float p0x = P->A[0] * cx + P->A[1] * cy + P->b[0];
    float p0y = P->A[3] * cx + P->A[4] * cy + P->b[1];
    float p0z = P->A[6] * cx + P->A[7] * cy + P->b[2];
    float ax = P->A[2], ay = P->A[5], az = P->A[8];
    clip_linear(lo, hi, P->wedge[0] * p0x + P->wedge[1] * p0y, P->wedge[0] * ax + P->wedge[1] * ay);
    clip_linear(lo, hi, P->wedge[2] * p0x + P->wedge[3] * p0y, P->wedge[2] * ax + P->wedge[3] * ay);
    clip_linear(lo, hi, P->slab - p0z, -az);
    clip_linear(lo, hi, P->slab + p0z, az);
}

// Column (i, j) in the block index: whether the index spans it, the index entry of its first block, and
// the offset of its voxels in a block. Blocks of 8 (the default) use shifts.
typedef struct { int ok; size_t base; long within; } BlockColumn;

inline BlockColumn block_column(const PingParams *P, int i, int j)
{
    BlockColumn c = {0, 0, 0};
    int B = P->blk;
    int ri = i - P->blk_lo[0], rj = j - P->blk_lo[1];
    if (ri < 0 || rj < 0) return c;
    int bi = B == 8 ? ri >> 3 : ri / B, bj = B == 8 ? rj >> 3 : rj / B;
    if (bi >= P->blk_n[0] || bj >= P->blk_n[1]) return c;
    c.ok = 1;
    c.base = ((size_t)bi * P->blk_n[1] + bj) * P->blk_n[2];
    c.within = (long)((ri - bi * B) * B + (rj - bj * B)) * P->blk_z;
    return c;
}

// Fold one ping into the voxels c0..c1 of column (i, j) that the column's range can hold.
// Storage address of voxel (i, j, k): its block's slot (through the index) times the block's voxels
// (B B Bz) plus its place in the block (local order i, j, k, k fastest); -1 when it has no block.
inline long voxel_address(const PingParams *P, __global const int *index, int i, int j, int k)
{
    int B = P->blk, Bz = P->blk_z;
    int ri = i - P->blk_lo[0], rj = j - P->blk_lo[1], rk = k - P->blk_lo[2];
    if (ri < 0 || rj < 0 || rk < 0) return -1;
    int bi = ri / B, bj = rj / B, bk = rk / Bz;
    if (bi >= P->blk_n[0] || bj >= P->blk_n[1] || bk >= P->blk_n[2]) return -1;
    int slot = index[((size_t)bi * P->blk_n[1] + bj) * P->blk_n[2] + bk];
    if (slot < 0) return -1;
    return (long)slot * B * B * Bz + ((ri - bi * B) * B + (rj - bj * B)) * Bz + rk - bk * Bz;
}

#ifdef GPUMAP_CPU_VECTORS
// beam_index_lo of eight tangents t where mask (else the value none): the table's guess and its usual
// single step as vector operations; a lane that needs more steps takes beam_index_lo's loops.
inline int8 beam_index_lo8(float8 t, int8 mask, __global const float *tan_edges, __global const int *lut,
                           const PingParams *P, int none)
{
    float8 tt = select((float8)(P->tan_lo), t, mask);  // masked lanes: a tangent inside the table
    int8 m = clamp(convert_int8(floor((tt - P->tan_lo) * P->lut_scale)), 0, P->lut_n - 1);
    int ms[8], js[8];
    float ts[8];
    vstore8(m, 0, ms);
    vstore8(tt, 0, ts);
    for (int l = 0; l < 8; ++l) {
        int j = lut[ms[l]];
        j += (j < P->n_beams - 1 && tan_edges[j + 1] <= ts[l]);
        // settled when neither loop of beam_index_lo would move it
        if ((j < P->n_beams - 1 && tan_edges[j + 1] <= ts[l]) || (j > 0 && tan_edges[j] > ts[l]))
            j = beam_index_lo(ts[l], tan_edges, lut, P->lut_n, P);
        js[l] = j;
    }
    return select((int8)(none), vload8(0, js), mask);
}

// CPUs (built with -DGPUMAP_CPU_VECTORS): voxels kb..kstop of column (cx, cy) eight at a time, the
// arithmetic of voxel_ping_value (sonar-frame point, range, aperture and azimuth tests, footprint
// bins, the beam span's tangents) on float8 vectors, then the footprint max and the update lane by
// lane for the observed voxels. Every vector operation rounds as its scalar twin (IEEE, no
// contraction), in the same order, so each voxel gets voxel_ping_value's value bit for bit.
// Returns 1 if any voxel is observed.
inline int gather_run8(const PingParams *P, float cx, float cy, int kb, int kstop, int slot, long base,
                       __global const float *image, __global const float *tan_edges, __global const int *lut,
                       __global const float *table, int use_table, __global const int *first_bright,
                       __global float *grid, __global float *bright, __global ulong *count)
{
    const float px = P->A[0] * cx + P->A[1] * cy;  // the scalar sums' first two terms, as they round
    const float py = P->A[3] * cx + P->A[4] * cy;
    const float pz = P->A[6] * cx + P->A[7] * cy;
    const float rho2 = P->rho * P->rho;
    const int8 lane = (int8)(0, 1, 2, 3, 4, 5, 6, 7);
    int hit = 0;
    for (int k = kb; k <= kstop; k += 8) {
        int8 kk = (int8)(k) + lane;
        float8 cz = (float8)(P->origin[2]) + (convert_float8(kk) + 0.5f) * P->voxel;
        float8 x = ((float8)(px) + P->A[2] * cz) + P->b[0];
        float8 y = ((float8)(py) + P->A[5] * cz) + P->b[1];
        float8 z = ((float8)(pz) + P->A[8] * cz) + P->b[2];
        float8 h2 = x * x + y * y;
        float8 r = sqrt(h2 + z * z);
        float8 t = y / x;
        // voxel_ping_value's rejections, negated as written there (so NaNs fall the same way)
        int8 ok = (kk <= (int8)(kstop)) & ~(x <= 0.0f) & ~((r < P->rmin) | (r >= P->rmax))
                  & ~(z * z > P->tan2_half_vfov * h2) & ~((t < P->tan_lo) | (t > P->tan_hi));
        if (!any(ok)) continue;
        float8 fl = floor((r - P->near - P->rmin) * P->inv_dr);
        int8 first = convert_int8(select((float8)(0.0f), fl, ok));  // masked lanes: 0, never out of range
        float8 q = h2 - rho2;
        float8 u = P->rho / sqrt(select((float8)(1.0f), q, q > 0.0f));
        float8 d0 = 1.0f + t * u, d1 = 1.0f - t * u;
        int8 w0 = ok & (q > 0.0f) & (d0 > 0.0f), w1 = ok & (q > 0.0f) & (d1 > 0.0f);
        float8 ta = (t - u) / select((float8)(1.0f), d0, w0);
        float8 tb = (t + u) / select((float8)(1.0f), d1, w1);
        int8 j0v = beam_index_lo8(ta, w0, tan_edges, lut, P, 0);
        int8 j1v = beam_index_lo8(tb, w1, tan_edges, lut, P, P->n_beams - 1);
        // footprint_value's table reads where two suffice (a span under twice its level's width; the
        // first bin in the table): entries a and b of the table, found for all lanes at once
        int8 span = j1v - j0v + 1;
        int8 lvl = select((int8)(0), min(31 - convert_int8(clz(span)), (int8)(P->n_levels - 1)), span > 1);
        int8 wv = (int8)(1) << lvl;
        int8 row = (lvl * P->n_bins + max(first, 0)) * P->n_beams;
        int8 two = ok & (first >= 0) & (span >= 1) & (span < 2 * wv) & (int8)(use_table ? -1 : 0);
        int oks[8], twos[8], firsts[8], j0s[8], j1s[8], as[8], bs[8];
        vstore8(ok, 0, oks);
        vstore8(two, 0, twos);
        vstore8(first, 0, firsts);
        vstore8(j0v, 0, j0s);
        vstore8(j1v, 0, j1s);
        vstore8(row + j1v - wv + 1, 0, as);
        vstore8(row + j0v, 0, bs);
        for (int l = 0; l < 8; ++l) {
            if (!oks[l]) continue;
            int j0 = j0s[l], j1 = j1s[l];
            int clear;
            float v;
            if (twos[l]) {
                v = fmax(table[as[l]], table[bs[l]]);
                clear = 0;
                if (P->rule != 0 && v < P->thr) clear = view_clear(j0, j1, max(firsts[l], 0), first_bright);
            } else {
                v = footprint_value(P, firsts[l], j0, j1, image, table, use_table, first_bright, &clear);
            }
            hit = 1;
            if (slot >= 0) update_voxel(P, (size_t)(base + k + l), v, clear, grid, bright, count);
        }
    }
    return hit;
}
#endif

// Fold one ping into the voxels c0..c1 of column (i, j) that the column's range can hold (col: its
// block_column, or ok = -1 to look it up here). Block by block
// along the column: one index read per block, then that block's voxels (contiguous) as a plain loop; a
// block with an observed voxel is marked seen. An observed voxel without a block sets err[0] and is
// skipped. A bounded box's blocks span the grid's height, so its columns run as one loop.
inline void gather_column(const PingParams *P, int i, int j, int c0, int c1, __global const float *image,
                          __global const float *tan_edges, __global const int *lut,
                          __global const float *table, int use_table, __global const int *first_bright,
                          __global const int *index, BlockColumn col, __global float *grid,
                          __global float *bright, __global ulong *count, __global uchar *seen, __global int *err)
{
    float cx = P->origin[0] + ((float)i + 0.5f) * P->voxel;
    float cy = P->origin[1] + ((float)j + 0.5f) * P->voxel;
    float z0, z1;
    column_range(P, cx, cy, &z0, &z1);
    if (z0 > z1) return;
    // voxel centres inside [z0, z1], padded by one voxel against rounding
    int k0 = max(c0, (int)ceil((z0 - P->origin[2]) / P->voxel - 0.5f) - 1);
    int k1 = min(c1, (int)floor((z1 - P->origin[2]) / P->voxel - 0.5f) + 1);
    int B = P->blk, Bz = P->blk_z;
    if (col.ok < 0) col = block_column(P, i, j);  // not given: look the column up now
    int col_ok = col.ok;
    size_t colbase = col.base;
    long within = col.within;
    for (int kb = k0; kb <= k1;) {
        int rk = kb - P->blk_lo[2];
        int slot = -1, kstop = min(k1, P->blk_lo[2] - 1);
        long base = 0;  // the block's slot * B B Bz + within - its first k
        if (rk >= 0) {
            int bk = rk < Bz ? 0 : rk / Bz;  // a bounded box's column is one block: no division
            kstop = min(k1, P->blk_lo[2] + bk * Bz + Bz - 1);
            if (col_ok && bk < P->blk_n[2]) slot = index[colbase + bk];
            base = (long)slot * B * B * Bz + within - (long)(P->blk_lo[2] + bk * Bz);
        }
        int hit = 0;
#ifdef GPUMAP_CPU_VECTORS
        hit = gather_run8(P, cx, cy, kb, kstop, slot, base, image, tan_edges, lut, table, use_table,
                          first_bright, grid, bright, count);
#else
        for (int k = kb; k <= kstop; ++k) {
            float cz = P->origin[2] + ((float)k + 0.5f) * P->voxel;
            int clear;
            float v = voxel_ping_value(P, cx, cy, cz, image, tan_edges, lut, table, use_table, first_bright,
                                       &clear);
            if (v >= 0.0f) {
                hit = 1;
                if (slot >= 0) update_voxel(P, (size_t)(base + k), v, clear, grid, bright, count);
            }
        }
#endif
        if (hit) {
            if (slot < 0) err[0] = 1;
            else if (!seen[slot]) seen[slot] = 1;  // a read, and a write only the first time
        }
        kb = kstop + 1;
    }
}

// One work-item per chunk of an (i, j) column of the ping's index box: it walks the chunk's
// voxels that the column's range can hold (contiguous in memory within a block).
__kernel void integrate_gather(const PingParams P, __global const float *image,
                               __global const float *tan_edges, __global const int *lut,
                               __global const float *table, int use_table,
                               __global const int *first_bright, __global const int *index,
                               __global float *grid, __global float *bright, __global ulong *count,
                               __global uchar *seen, __global int *err)
{
    int tid = get_global_id(0);
    int n_chunks = (P.box_n[2] + P.chunk - 1) / P.chunk;
    if (tid >= P.box_n[0] * P.box_n[1] * n_chunks) return;
    int col = tid / n_chunks;
    int c0 = P.box_lo[2] + (tid % n_chunks) * P.chunk;
    int c1 = min(c0 + P.chunk, P.box_lo[2] + P.box_n[2]) - 1;
    int i = P.box_lo[0] + col / P.box_n[1];
    int j = P.box_lo[1] + col % P.box_n[1];
    BlockColumn later = {-1, 0, 0};
    gather_column(&P, i, j, c0, c1, image, tan_edges, lut, table, use_table, first_bright, index, later, grid,
                  bright, count, seen, err);
}

// One work-item per voxel of each of n listed blocks of bv voxels (pairs: n slots, then n index entries):
// slot pairs[b] becomes never observed (unknown = +inf, no evidence) and index[pairs[n + b]] = pairs[b]
// (-1: freed).
__kernel void init_blocks(__global const int *pairs, int n, int bv, int visible, float unknown,
                          __global int *index, __global float *grid, __global float *bright,
                          __global ulong *count, __global uchar *seen)
{
    int tid = get_global_id(0);
    if (tid >= n * bv) return;
    int b = tid / bv, v = tid % bv;
    int s = pairs[b];
    if (s >= 0) {
        size_t a = (size_t)s * bv + v;
        grid[a] = unknown;
        if (visible) { bright[a] = unknown; count[a] = 0; }
        if (v == 0) seen[s] = 0;
    }
    if (v == 0) index[pairs[n + b]] = s;
}

// ---------------------------------------------------------------------------------------- batches
// B pings in one launch per step (twins of minmax.py's *_batch kernels): ping b's image, max table
// and first bright bins start at b * plane, b * table_stride and b * n_beams. Each gather work-item
// owns one voxel and folds ping 0, 1, ... into it: no atomics, the same grid as B launches.

__kernel void find_first_bright_batch(__global const PingParams *Ps, const int n_pings, const int n_beams,
                                      __global const float *images, __global int *first_bright)
{
    int c = get_global_id(0);
    if (c >= n_pings * n_beams) return;
    int b = c / n_beams, j = c % n_beams;
    PingParams P = Ps[b];
    __global const float *image = images + (size_t)b * P.n_bins * P.n_beams;
    int f = P.n_bins;
    for (int i = 0; i < P.n_bins; ++i) {
        if (image[(size_t)i * P.n_beams + j] >= P.thr) { f = i; break; }
    }
    first_bright[c] = f;
}

__kernel void build_bin_window_cells_batch(__global const PingParams *Ps, const int n_pings, const int plane,
                                           const int table_stride, __global const float *images,
                                           __global float *tables)
{
    int g = get_global_id(0);
    if (g >= n_pings * plane) return;
    int b = g / plane, c = g % plane;
    const int n_bins = Ps[b].n_bins, n_beams = Ps[b].n_beams, win = Ps[b].win;
    __global const float *image = images + (size_t)b * plane;
    int i = c / n_beams, j = c % n_beams;
    float v = 0.0f;
    for (int r = i; r < min(i + win, n_bins); ++r) v = fmax(v, image[(size_t)r * n_beams + j]);
    tables[(size_t)b * table_stride + c] = v;
}

__kernel void build_beam_levels_cells_batch(__global const PingParams *Ps, const int n_pings, const int plane,
                                            const int table_stride, __global float *tables)
{
    int g = get_global_id(0);
    if (g >= n_pings * plane) return;
    int b = g / plane, c = g % plane;
    const int n_bins = Ps[b].n_bins, n_beams = Ps[b].n_beams, n_levels = Ps[b].n_levels;
    __global float *table = tables + (size_t)b * table_stride;
    int i = c / n_beams, j = c % n_beams;
    __global const float *row = table + (size_t)i * n_beams;
    float v = row[j];
    for (int k = 1, w = 1; k < n_levels; ++k, w *= 2) {
        for (int jj = w; jj < 2 * w; ++jj) v = fmax(v, row[min(j + jj, n_beams - 1)]);
        table[((size_t)k * n_bins + i) * n_beams + j] = v;
    }
}

// One work-item per voxel of the union box (lo, n), k fastest (a warp walks a column's contiguous voxels):
// it folds ping 0, 1, ... into the voxel, each ping only within that ping's box. The voxel's values live
// in private memory from its first view and are written once, where they changed. P0 (ping 0's
// parameters, a kernel argument) gives every field the batch's pings share; Ps[b] only the ones that
// differ (pose, footprint), so few registers stay live.
__kernel void integrate_voxels_batch(const PingParams P0, __global const PingParams *Ps, const int n_pings,
                                     const int lo0, const int lo1, const int lo2, const int n0, const int n1,
                                     const int n2, const int plane, const int table_stride,
                                     __global const float *images, __global const float *tan_edges,
                                     __global const int *lut, __global const float *tables, int use_table,
                                     __global const int *first_bright, __global const int *index,
                                     __global float *grid, __global float *bright, __global ulong *count,
                                     __global uchar *seen, __global int *err)
{
    int tid = get_global_id(0);
    if (tid >= n0 * n1 * n2) return;
    int col = tid / n2;
    int k = lo2 + tid % n2;
    int i = lo0 + col / n1;
    int j = lo1 + col % n1;
    float cx = P0.origin[0] + ((float)i + 0.5f) * P0.voxel;
    float cy = P0.origin[1] + ((float)j + 0.5f) * P0.voxel;
    float cz = P0.origin[2] + ((float)k + 0.5f) * P0.voxel;
    long a = -1;
    int hit = 0;
    float g0 = 0.0f, g = 0.0f, br0 = 0.0f, br = 0.0f;
    ulong c0 = 0, c = 0;
    for (int b = 0; b < n_pings; ++b) {
        __global const PingParams *Q = Ps + b;
        if (i < Q->box_lo[0] || i >= Q->box_lo[0] + Q->box_n[0] || j < Q->box_lo[1] ||
            j >= Q->box_lo[1] + Q->box_n[1] || k < Q->box_lo[2] || k >= Q->box_lo[2] + Q->box_n[2])
            continue;
        PingParams P = P0;
        for (int e = 0; e < 9; ++e) P.A[e] = Q->A[e];
        for (int e = 0; e < 3; ++e) P.b[e] = Q->b[e];
        P.rho = Q->rho;
        P.near = Q->near;
        P.win = Q->win;
        int clear;
        float v = voxel_ping_value(&P, cx, cy, cz, images + (size_t)b * plane, tan_edges, lut,
                                   tables + (size_t)b * table_stride, use_table,
                                   first_bright + (size_t)b * P0.n_beams, &clear);
        if (v < 0.0f) continue;
        if (!hit) {  // the first view: find the voxel and read its values
            hit = 1;
            a = voxel_address(&P0, index, i, j, k);
            if (a >= 0) {
                g0 = g = grid[a];
                if (P0.rule != 0) { br0 = br = bright[a]; c0 = c = count[a]; }
            }
        }
        if (a < 0) continue;
        if (v < g) g = v;
        if (P0.rule != 0) {
            if (v >= P0.thr && v < br) br = v;
            c = counted(&P, v, clear, c);
        }
    }
    if (!hit) return;
    if (a < 0) { err[0] = 1; return; }
    if (g < g0) grid[a] = g;
    if (br < br0) bright[a] = br;
    if (c != c0) count[a] = c;
    long slot = a / ((long)P0.blk * P0.blk * P0.blk_z);
    if (!seen[slot]) seen[slot] = 1;
}

// One work-item per template point: the paper's steps 1-6.
__kernel void integrate_template(const PingParams P, __global const float *image,
                                 __global const float *tan_edges, __global const int *lut,
                                 __global const float *table, int use_table,
                                 __global const int *first_bright, __global const float *template_S,
                                 __global const int *index, __global float *grid, __global uchar *seen)
{
    int tid = get_global_id(0);
    if (tid >= P.n_points) return;
    float px = template_S[3 * tid], py = template_S[3 * tid + 1], pz = template_S[3 * tid + 2];
    float qx = P.R[0] * px + P.R[1] * py + P.R[2] * pz + P.t[0];  // step 1
    float qy = P.R[3] * px + P.R[4] * py + P.R[5] * pz + P.t[1];
    float qz = P.R[6] * px + P.R[7] * py + P.R[8] * pz + P.t[2];
    int i = (int)floor((qx - P.origin[0]) / P.voxel);  // step 2
    int j = (int)floor((qy - P.origin[1]) / P.voxel);
    int k = (int)floor((qz - P.origin[2]) / P.voxel);
    if (i < 0 || j < 0 || k < 0 || i >= P.dims[0] || j >= P.dims[1] || k >= P.dims[2]) return;
    float cx = P.origin[0] + ((float)i + 0.5f) * P.voxel;  // step 3
    float cy = P.origin[1] + ((float)j + 0.5f) * P.voxel;
    float cz = P.origin[2] + ((float)k + 0.5f) * P.voxel;
    int clear;
    float v = voxel_ping_value(&P, cx, cy, cz, image, tan_edges, lut, table, use_table, first_bright,
                               &clear);  // steps 4-5
    if (v >= 0.0f) {
        // step 6; grid values are >= 0 (or +inf), whose IEEE bits order like ints
        long idx = voxel_address(&P, index, i, j, k);
        if (idx >= 0) {
            atomic_min((volatile __global int *)(grid + idx), as_int(v));
            seen[idx / ((long)P.blk * P.blk * P.blk_z)] = 1;  // its block holds an observed voxel
        }
    }
}
