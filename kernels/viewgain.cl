// View gain of candidate sonar poses in OpenCL C 1.2 (device code only; twin: viewgain.py).
// One work-item per (candidate, tile of points); same arguments in the same order as the Warp
// kernel: candidate poses (K, 12) (rows of A = R_S_W, then b), points (M, 3), pair masks (bit b: a
// view whose elevation arc runs along neighbour pair b would settle the voxel; -1: a block of
// unknown voxels), weights, the field of view
// (r_min, r_max, tan^2 half aperture, fan edge tangents), the point count (Warp reads it from the
// array), the tile length, and the int32 totals (settle, unknown), added atomically.

// No FMA contraction: every device rounds as the NumPy reference does, bit for bit.
#pragma OPENCL FP_CONTRACT OFF

// arc_step: common.cl, which the host prepends.

int pair_bit(int si, int sj, int sk) {
    const int m = (si + 1) * 9 + (sj + 1) * 3 + (sk + 1);
    return max(m, 26 - m) - 14;
}

__kernel void view_gain(
    __global const float *poses,
    __global const float *points,
    __global const int *pairs,
    __global const int *weight,
    float rmin, float rmax, float tan2_half_vfov, float tan_lo, float tan_hi,
    int n_points,
    int tile,
    __global int *settle,
    __global int *unknown)
{
    const int c = get_global_id(0);
    const int q = get_global_id(1);
    __global const float *P = poses + 12 * c;
    const float a00 = P[0], a01 = P[1], a02 = P[2];
    const float a10 = P[3], a11 = P[4], a12 = P[5];
    const float a20 = P[6], a21 = P[7], a22 = P[8];
    const float b0 = P[9], b1 = P[10], b2 = P[11];
    const int first = q * tile;
    const int last = min(first + tile, n_points);
    int n_settle = 0;
    int n_unknown = 0;
    for (int m = first; m < last; ++m) {
        const float px = points[3 * m], py = points[3 * m + 1], pz = points[3 * m + 2];
        const float x = a00 * px + a01 * py + a02 * pz + b0;
        const float y = a10 * px + a11 * py + a12 * pz + b1;
        const float z = a20 * px + a21 * py + a22 * pz + b2;
        if (x <= 0.0f) continue;
        const float h2 = x * x + y * y;
        const float r = sqrt(h2 + z * z);
        const float t = y / x;
        if (r < rmin || r >= rmax || z * z > tan2_half_vfov * h2 || t < tan_lo || t > tan_hi) continue;
        const int f = pairs[m];
        if (f < 0) {
            n_unknown += weight[m];
            continue;
        }
        const float ex = -(x * z);
        const float ey = -(y * z);
        const float ez = h2;
        const float wx = a00 * ex + a10 * ey + a20 * ez;
        const float wy = a01 * ex + a11 * ey + a21 * ez;
        const float wz = a02 * ex + a12 * ey + a22 * ez;
        const float n2 = wx * wx + wy * wy + wz * wz;
        const int si = arc_step(wx, n2), sj = arc_step(wy, n2), sk = arc_step(wz, n2);
        if ((f >> pair_bit(si, sj, sk)) & 1) {
            n_settle += weight[m];
        }
    }
    if (n_settle > 0) atomic_add(settle + c, n_settle);
    if (n_unknown > 0) atomic_add(unknown + c, n_unknown);
}
