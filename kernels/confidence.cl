// The confidence layer's per-ping pass in OpenCL C 1.2 (device code only; twin: confidence.py, whose
// docstring tells the launches). Same kernels, same arguments in the same order as the Warp twin (the
// beam look-up table's length, which Warp reads from the array, is P.lut_n here; work-items past a
// kernel's work size return).
// PingParams matches gpumap.geometry.PING_DTYPE field for field (a copy of minmax.cl's, so the two
// programs build on their own); beam_index_lo, the block addressing and the arc direction are copies of
// minmax.cl's and viewgain.cl's, with the same arithmetic. The evidence rule's test is float64.

// No FMA contraction: every device then rounds as the NumPy reference does, bit for bit.
#pragma OPENCL FP_CONTRACT OFF
#pragma OPENCL EXTENSION cl_khr_fp64 : enable

// PingParams, COUNT_LOW and arc_step: common.cl, which the host prepends.


// Largest beam j in [0, n_beams - 1] with tan_edges[j] <= t (0 when none): the look-up table's
// guess (clamped as a float, so any t is safe), settled by exact comparisons.
inline int beam_index_lo(float t, __global const float *tan_edges, __global const int *lut, const PingParams *P)
{
    float f = floor((t - P->tan_lo) * P->lut_scale);
    int m = 0;
    if (f >= (float)(P->lut_n - 1)) m = P->lut_n - 1;
    else if (f > 0.0f) m = (int)f;
    int j = lut[m];
    while (j < P->n_beams - 1 && tan_edges[j + 1] <= t) ++j;
    while (j > 0 && tan_edges[j] > t) --j;
    return j;
}

// First and last beam a sphere of radius w spans (gpumap.reference.beam_span).
inline int2 beam_span(float t, float h2, float w, __global const float *tan_edges, __global const int *lut,
                      const PingParams *P)
{
    int2 js = (int2)(0, P->n_beams - 1);
    float q = h2 - w * w;
    if (q > 0.0f) {
        float u = w / sqrt(q);
        float d0 = 1.0f + t * u, d1 = 1.0f - t * u;
        if (d0 > 0.0f) js.x = beam_index_lo((t - u) / d0, tan_edges, lut, P);
        if (d1 > 0.0f) js.y = beam_index_lo((t + u) / d1, tan_edges, lut, P);
    }
    return js;
}

// floor(x) clipped to [0, n_bins - 1] (clipped as a float: any x is safe).
inline int bin_clip(float x, int n_bins)
{
    float f = floor(x);
    if (f <= 0.0f) return 0;
    if (f >= (float)(n_bins - 1)) return n_bins - 1;
    return (int)f;
}

// The count over bins b0..b1 and beams j0..j1 of a table of per-row running counts (R[i w + j]: the count of
// bin i's beams < j, w = n_beams + 1), or the first partial sum past most (the caller asks whether it
// equals a number <= most).
inline int count_in(__global const int *R, int w, int b0, int b1, int j0, int j1, int most)
{
    int s = 0;
    for (int i = b0; i <= b1; ++i) {
        s += R[i * w + j1 + 1] - R[i * w + j0];
        if (s > most) return s;
    }
    return s;
}

// 1 when a cell of bins b0..b1 and beams j0..j1 is lit: L[i nw + j / 32] holds beam j's bit j % 32 of bin i.
inline int any_lit(__global const uint *L, int nw, int b0, int b1, int j0, int j1)
{
    int w0 = j0 >> 5, w1 = j1 >> 5;
    uint lo = 0xFFFFFFFFu << (uint)(j0 & 31);
    uint hi = 0xFFFFFFFFu >> (uint)(31 - (j1 & 31));
    for (int i = b0; i <= b1; ++i) {
        __global const uint *row = L + i * nw;
        if (w0 == w1) {
            if (row[w0] & lo & hi) return 1;
        } else {
            if ((row[w0] & lo) || (row[w1] & hi)) return 1;
            for (int w = w0 + 1; w < w1; ++w)
                if (row[w]) return 1;
        }
    }
    return 0;
}

// Column (i, j) in the block index (minmax.cl's voxel_address's work that k leaves alone): (1 if the index spans it else
// 0, the index entry of its first block, the offset of its voxels in a block).
inline int3 column_of(const PingParams *P, int i, int j)
{
    int B = P->blk;
    int ri = i - P->blk_lo[0], rj = j - P->blk_lo[1];
    if (ri < 0 || rj < 0) return (int3)(0, 0, 0);
    int bi = ri / B, bj = rj / B;
    if (bi >= P->blk_n[0] || bj >= P->blk_n[1]) return (int3)(0, 0, 0);
    return (int3)(1, (bi * P->blk_n[1] + bj) * P->blk_n[2], ((ri - bi * B) * B + (rj - bj * B)) * P->blk_z);
}

// minmax.cl's voxel_address of voxel k of a column (col: column_of; -1: no block); a bounded box's column is
// one block (no division).
inline int column_address(const PingParams *P, __global const int *index, int3 col, int k)
{
    int rk = k - P->blk_lo[2];
    if (col.x == 0 || rk < 0) return -1;
    int Bz = P->blk_z;
    int bk = rk >= Bz ? rk / Bz : 0;
    if (bk >= P->blk_n[2]) return -1;
    int slot = index[col.y + bk];
    if (slot < 0) return -1;
    return slot * P->blk * P->blk * Bz + col.z + rk - bk * Bz;
}

// 1 when the map value at pool address a (-1: no block, unknown) is >= thr or unknown (the rule's
// value; the evidence test in float64 in the reference's order), else 0.
inline int not_free(const PingParams *P, int a, __global const float *grid, __global const float *bright,
                    __global const ulong *count, int carve_views, double p_min, double rhs)
{
    if (a < 0) return 1;
    float v = grid[a];
    if (P->rule != 0) {
        float b = bright[a];
        if (isfinite(b)) {
            ulong c = count[a];
            int keep = 0;
            if (P->rule == 1) {
                keep = (c & COUNT_LOW) < (ulong)carve_views;
            } else {
                ulong hits = c >> 32;
                if (hits > 0UL) {
                    double k = (double)hits;
                    double n = k + (double)(c & COUNT_LOW);
                    double share = k / n;
                    double d = p_min - share;
                    double dd = d * d;
                    double lhs = dd * n;
                    keep = share >= p_min || lhs <= rhs;
                }
            }
            if (keep) v = b;
        }
    }
    return v >= P->thr ? 1 : 0;
}


// 1 when the voxel at (r, h^2, t) is bright in the ping (a lit cell in its footprint: the mapping's
// bins and beams) and a lit cell lies within tube of its centre (the echo).
inline int echo_lit(const PingParams *P, float r, float h2, float t, __global const uint *lit,
                    __global const float *tan_edges, __global const int *lut, float tube)
{
    int nb = P->n_bins;
    int first = (int)floor((r - P->near - P->rmin) * P->inv_dr);
    int b0 = max(first, 0);
    int b1 = min(first + P->win - 1, nb - 1);
    int2 js = beam_span(t, h2, P->rho, tan_edges, lut, P);
    if (!any_lit(lit, (P->n_beams + 31) / 32, b0, b1, js.x, js.y)) return 0;
    b0 = bin_clip((r - tube - P->rmin) * P->inv_dr, nb);
    b1 = bin_clip((r + tube - P->rmin) * P->inv_dr, nb);
    js = beam_span(t, h2, tube, tan_edges, lut, P);
    if (!any_lit(lit, (P->n_beams + 31) / 32, b0, b1, js.x, js.y)) return 0;
    return 1;
}

// One work-item per word of a bin row (from offset): the row's lit cells (>= thr) as bits, lit[i nw + j / 32]
// bit j % 32, and the rival counts of those cells zeroed; work-item 0 also empties the candidate lists.
__kernel void lit_bits(const PingParams P, __global const float *image, __global uint *lit, __global int *rivals,
                       __global int *n_cand, const int offset)
{
    int q = get_global_id(0) + offset;
    int nw = (P.n_beams + 31) / 32;
    if (q >= P.n_bins * nw) return;
    int i = q / nw, w = q - i * nw;
    __global const float *im = image + (size_t)i * P.n_beams;
    uint word = 0;
    __global int *riv = rivals + (size_t)i * P.n_beams;
    for (int j = w * 32; j < min(w * 32 + 32, P.n_beams); ++j) {
        if (im[j] >= P.thr) word |= 1u << (uint)(j - w * 32);
        riv[j] = 0;
    }
    lit[q] = word;
    if (q == 0) { n_cand[0] = 0; n_cand[1] = 0; }
}

// One work-item per bin row i (from offset): running[i, j] = the rivals of bin i's beams < j (n_beams + 1 a row).
__kernel void prefix_rows(const PingParams P, __global const int *rivals, __global int *running, const int offset)
{
    int i = get_global_id(0) + offset;
    if (i >= P.n_bins) return;
    int w = P.n_beams + 1;
    __global const int *raw = rivals + i * P.n_beams;
    __global int *run = running + i * w;
    int s = 0;
    run[0] = 0;
    for (int j = 0; j < P.n_beams; ++j) {
        s += raw[j];
        run[j + 1] = s;
    }
}

// One work-item per (i, j) column of the box from column offset (see confidence.py): arcs, the rivals'
// counts, each box voxel's rival cell (cells, box order: bin n_beams + beam, -1 not a rival) and the
// candidates; part: the rival table (part n_bins n_beams on) and candidate list (cand[part stride:], its
// length n_cand[part]) it adds to (OpenCL runs part 0 only).
__kernel void conf_voxels(const PingParams P, __global const float *tan_edges, __global const int *lut,
                          __global const int *index, __global const float *grid, __global const float *bright,
                          __global const ulong *count, __global ushort *arcs, __global int *rivals,
                          __global int *cells, __global int *cand, __global int *steps, __global int *n_cand,
                          const float cos_hv, const float sin_hv, const float tube, const float rmax_c,
                          const float slab_c, const int carve_views, const double p_min, const double rhs,
                          const int offset, const int part, const int stride)
{
    int col = get_global_id(0) + offset;
    if (col >= P.box_n[0] * P.box_n[1]) return;
    const PingParams *Q = &P;
    int n2b = P.box_n[2];
    int i = P.box_lo[0] + col / P.box_n[1];
    int j = P.box_lo[1] + col - (col / P.box_n[1]) * P.box_n[1];
    float cx = P.origin[0] + ((float)i + 0.5f) * P.voxel;
    float cy = P.origin[1] + ((float)j + 0.5f) * P.voxel;
    // the z-range of the column the rivals' region can hold, padded by a voxel (a relaxation)
    int k0 = P.box_lo[2], k1 = k0 - 1;
    float dx = cx - P.t[0], dy = cy - P.t[1];
    float q = rmax_c * rmax_c - dx * dx - dy * dy;
    if (q > 0.0f) {
        float hw = sqrt(q);
        float z0 = P.t[2] - hw, z1 = P.t[2] + hw;
        float p0x = P.A[0] * cx + P.A[1] * cy + P.b[0];
        float p0y = P.A[3] * cx + P.A[4] * cy + P.b[1];
        float p0z = P.A[6] * cx + P.A[7] * cy + P.b[2];
        float pad = 1.0e-4f * (1.0f + rmax_c);  // loosens each half-space against rounding (never tightens)
        for (int h = 0; h < 4; ++h) {
            float alpha, beta;
            if (h == 0) {
                alpha = P.wedge[0] * p0x + P.wedge[1] * p0y;
                beta = P.wedge[0] * P.A[2] + P.wedge[1] * P.A[5];
            } else if (h == 1) {
                alpha = P.wedge[2] * p0x + P.wedge[3] * p0y;
                beta = P.wedge[2] * P.A[2] + P.wedge[3] * P.A[5];
            } else if (h == 2) {
                alpha = slab_c - p0z;
                beta = -P.A[8];
            } else {
                alpha = slab_c + p0z;
                beta = P.A[8];
            }
            alpha = alpha + pad;
            if (fabs(beta) < 1.0e-12f) {
                if (alpha < 0.0f) z1 = z0 - 1.0f;
            } else if (beta > 0.0f) {
                z0 = fmax(z0, -alpha / beta);
            } else {
                z1 = fmin(z1, -alpha / beta);
            }
        }
        if (z0 <= z1) {
            k0 = max(P.box_lo[2], (int)ceil((z0 - P.origin[2]) / P.voxel - 0.5f) - 1);
            k1 = min(P.box_lo[2] + n2b - 1, (int)floor((z1 - P.origin[2]) / P.voxel - 0.5f) + 1);
        }
    }
    int nb = P.n_bins;
    int ny = P.dims[1], nz = P.dims[2];
    __global int *out = cells + (size_t)col * n2b - P.box_lo[2];
    int3 colb = column_of(Q, i, j);
    for (int k = P.box_lo[2]; k < P.box_lo[2] + n2b; ++k) {
        int cell = -1;
        if (k >= k0 && k <= k1) {
            float cz = P.origin[2] + ((float)k + 0.5f) * P.voxel;
            float x = P.A[0] * cx + P.A[1] * cy + P.A[2] * cz + P.b[0];
            float y = P.A[3] * cx + P.A[4] * cy + P.A[5] * cz + P.b[1];
            float z = P.A[6] * cx + P.A[7] * cy + P.A[8] * cz + P.b[2];
            float t = y / x;
            if (x > 0.0f && t >= P.tan_lo && t <= P.tan_hi) {
                float h2 = x * x + y * y;
                float r = sqrt(h2 + z * z);
                int seen = r >= P.rmin && r < P.rmax && z * z <= P.tan2_half_vfov * h2;
                int near = r >= P.rmin - P.rho && r < P.rmax + P.rho
                           && fabs(z) * cos_hv - sqrt(h2) * sin_hv <= P.rho;
                int flat = (i * ny + j) * nz + k;
                int bit = 0;
                if (seen) {  // the elevation arc's direction (-x z, -y z, h^2) to the world, its pair bit
                    float ex = -(x * z), ey = -(y * z), ez = h2;
                    float wx = P.A[0] * ex + P.A[3] * ey + P.A[6] * ez;
                    float wy = P.A[1] * ex + P.A[4] * ey + P.A[7] * ez;
                    float wz = P.A[2] * ex + P.A[5] * ey + P.A[8] * ez;
                    float n2 = wx * wx + wy * wy + wz * wz;
                    int m = (arc_step(wx, n2) + 1) * 9 + (arc_step(wy, n2) + 1) * 3 + (arc_step(wz, n2) + 1);
                    bit = max(m, 26 - m) - 14;
                    arcs[flat] = (ushort)(arcs[flat] | (ushort)(1 << bit));
                }
                if ((seen || near) && not_free(Q, column_address(Q, index, colb, k), grid, bright, count,
                                               carve_views, p_min, rhs)) {
                    if (near) {
                        int cb = bin_clip((r - P.rmin) * P.inv_dr, nb);
                        int cj = beam_index_lo(t, tan_edges, lut, Q);
                        cell = cb * P.n_beams + cj;
                        atomic_add(&rivals[part * P.n_bins * P.n_beams + cell], 1);
                    }
                    if (seen) {  // a candidate, with its elevation arc's neighbour pair
                        int c = part * stride + atomic_inc(&n_cand[part]);
                        cand[c] = flat;
                        steps[c] = bit;
                    }
                }
            }
        }
        out[k] = cell;
    }
}

// One work-item per candidate of list part (from offset; those past its length return): confirmed when the
// rivals whose centre cell lies within tube + rho of it are itself and its neighbours in the box.
__kernel void conf_candidates(const PingParams P, __global const float *tan_edges, __global const int *lut,
                              __global const uint *lit, __global const int *running, __global const int *cells,
                              __global const int *cand, __global const int *steps,
                              __global const int *n_cand, __global uchar *confirmed, const float tube,
                              const float beam_max,
                              const int offset, const int part, const int stride)
{
    int c = get_global_id(0) + offset;
    if (c >= n_cand[part]) return;
    const PingParams *Q = &P;
    c = part * stride + c;
    int flat = cand[c];
    int ny = P.dims[1], nz = P.dims[2];
    int i = flat / (ny * nz);
    int j = flat / nz - i * ny;
    int k = flat - (i * ny + j) * nz;
    int li = i - P.box_lo[0], lj = j - P.box_lo[1], lk = k - P.box_lo[2];
    float cx = P.origin[0] + ((float)i + 0.5f) * P.voxel;
    float cy = P.origin[1] + ((float)j + 0.5f) * P.voxel;
    float cz = P.origin[2] + ((float)k + 0.5f) * P.voxel;
    float x = P.A[0] * cx + P.A[1] * cy + P.A[2] * cz + P.b[0];
    float y = P.A[3] * cx + P.A[4] * cy + P.A[5] * cz + P.b[1];
    float z = P.A[6] * cx + P.A[7] * cy + P.A[8] * cz + P.b[2];
    float h2 = x * x + y * y;
    float r = sqrt(h2 + z * z);
    float t = y / x;
    int nb = P.n_bins;
    float wide = tube + P.rho;
    // First a few reads that settle most candidates (see confidence.py): a rival two or three steps along the
    // arc whose cell lies within kb bins and mb beams of the voxel's own lies within its cells within wide.
    int own_cell = cells[(li * P.box_n[1] + lj) * P.box_n[2] + lk];
    int kb = (int)(wide * P.inv_dr) - 2;
    int mb = -1;
    float hb = sqrt(h2) * beam_max;
    if (hb > 0.0f) mb = (int)fmin(wide / hb, 1.0e6f) - 2;
    if (own_cell >= 0 && kb >= 0 && mb >= 0) {
        int ob = own_cell / P.n_beams, oj = own_cell - ob * P.n_beams;
        int m = steps[c] + 14;
        int si = m / 9 - 1, sj = (m / 3) % 3 - 1, sk = m % 3 - 1;
        for (int e = 0; e < 4; ++e) {
            int d = e >= 2 ? e : e - 3;
            int qi = li + d * si, qj = lj + d * sj, qk = lk + d * sk;
            if (qi < 0 || qi >= P.box_n[0] || qj < 0 || qj >= P.box_n[1] || qk < 0 || qk >= P.box_n[2]) continue;
            int pc = cells[(qi * P.box_n[1] + qj) * P.box_n[2] + qk];
            if (pc < 0) continue;
            int pcb = pc / P.n_beams;
            if (abs(pcb - ob) <= kb && abs(pc - pcb * P.n_beams - oj) <= mb) return;
        }
    }
    int b0 = bin_clip((r - wide - P.rmin) * P.inv_dr, nb);
    int b1 = bin_clip((r + wide - P.rmin) * P.inv_dr, nb);
    int2 js = beam_span(t, h2, wide, tan_edges, lut, Q);
    int j0 = js.x, j1 = js.y;
    int total = count_in(running, P.n_beams + 1, b0, b1, j0, j1, 27);
    if (total > 27) return;  // more than the voxel and its 26 neighbours could be
    if (!echo_lit(Q, r, h2, t, lit, tan_edges, lut, tube)) return;
    int own = 0;
    for (int di = -1; di <= 1; ++di)
        for (int dj = -1; dj <= 1; ++dj)
            for (int dk = -1; dk <= 1; ++dk) {
                int ii = li + di, jj = lj + dj, kk = lk + dk;
                if (ii < 0 || ii >= P.box_n[0] || jj < 0 || jj >= P.box_n[1] || kk < 0 || kk >= P.box_n[2]) continue;
                int cell = cells[(ii * P.box_n[1] + jj) * P.box_n[2] + kk];
                if (cell < 0) continue;
                int cb = cell / P.n_beams, cj = cell - cb * P.n_beams;
                if (cb >= b0 && cb <= b1 && cj >= j0 && cj <= j1) ++own;
            }
    if (total == own) confirmed[flat] = 1;
}
