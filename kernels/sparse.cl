// Block-sparse min-max kernels in OpenCL C 1.2 (device code only; twin: sparse.py). Compiled after
// minmax.cl in one program (it uses PingParams, column_range, voxel_ping_value and update_voxel from
// there, so every voxel's arithmetic is the dense kernel's). Blocks of B^3 voxels live in a pool (slot s:
// voxels [s B^3, (s + 1) B^3), local order (i, j, k), k fastest); a dense coarse index over the blocks of
// a box (int per block, -1 none) maps a block to its slot.

// One work-item per chunk of an (i, j) column of the ping's voxel box, as integrate_gather. ilo: voxel
// index of the index box's first voxel; nb: the index box in blocks. An observed voxel with no block
// sets err[0] and is skipped.
__kernel void integrate_blocks(const PingParams P, __global const float *image,
                               __global const float *tan_edges, __global const int *lut,
                               __global const float *table, int use_table,
                               __global const int *first_bright, __global const int *index,
                               int ilo0, int ilo1, int ilo2, int nb0, int nb1, int nb2, int B,
                               __global float *grid, __global float *bright, __global uchar *count,
                               __global uchar *seen, __global int *err)
{
    int tid = get_global_id(0);
    int n_chunks = (P.box_n[2] + P.chunk - 1) / P.chunk;
    if (tid >= P.box_n[0] * P.box_n[1] * n_chunks) return;
    int col = tid / n_chunks;
    int c0 = P.box_lo[2] + (tid % n_chunks) * P.chunk;
    int i = P.box_lo[0] + col / P.box_n[1];
    int j = P.box_lo[1] + col % P.box_n[1];
    float cx = P.origin[0] + ((float)i + 0.5f) * P.voxel;
    float cy = P.origin[1] + ((float)j + 0.5f) * P.voxel;
    float z0, z1;
    column_range(&P, cx, cy, &z0, &z1);
    if (z0 > z1) return;
    int k0 = max(c0, (int)ceil((z0 - P.origin[2]) / P.voxel - 0.5f) - 1);
    int k1 = min(min(c0 + P.chunk, P.box_lo[2] + P.box_n[2]) - 1,
                 (int)floor((z1 - P.origin[2]) / P.voxel - 0.5f) + 1);
    int ri = i - ilo0, rj = j - ilo1;
    int bi = ri / B, bj = rj / B;
    int col_ok = ri >= 0 && rj >= 0 && bi < nb0 && bj < nb1;
    size_t colbase = ((size_t)bi * nb1 + bj) * nb2;
    size_t B3 = (size_t)B * B * B;
    int within = ((ri - bi * B) * B + (rj - bj * B)) * B;
    int cur = -1, slot = -1;
    for (int k = k0; k <= k1; ++k) {
        float cz = P.origin[2] + ((float)k + 0.5f) * P.voxel;
        int clear;
        float v = voxel_ping_value(&P, cx, cy, cz, image, tan_edges, lut, table, use_table, first_bright,
                                   &clear);
        if (v >= 0.0f) {
            int rk = k - ilo2;
            int bk = rk >= 0 ? rk / B : -1;
            if (bk != cur) {
                cur = bk;
                slot = (col_ok && rk >= 0 && bk < nb2) ? index[colbase + bk] : -1;
                if (slot >= 0) seen[slot] = 1;  // once per block a work-item touches, not per voxel
            }
            if (slot < 0) {
                err[0] = 1;
            } else {
                update_voxel(&P, (size_t)slot * B3 + within + rk - bk * B, v, clear, grid, bright, count);
            }
        }
    }
}

// One work-item per voxel of each of n listed blocks (pairs: n slots, then n index entries): slot pairs[b]
// becomes never observed (unknown = +inf, no evidence) and index[pairs[n + b]] = pairs[b] (-1: freed).
__kernel void init_blocks(__global const int *pairs, int n, int B3, int visible, float unknown,
                          __global int *index, __global float *grid, __global float *bright,
                          __global uchar *count, __global uchar *seen)
{
    int tid = get_global_id(0);
    if (tid >= n * B3) return;
    int b = tid / B3, v = tid % B3;
    int s = pairs[b];
    if (s >= 0) {
        size_t a = (size_t)s * B3 + v;
        grid[a] = unknown;
        if (visible) { bright[a] = unknown; count[a] = 0; }
        if (v == 0) seen[s] = 0;
    }
    if (v == 0) index[pairs[n + b]] = s;
}
