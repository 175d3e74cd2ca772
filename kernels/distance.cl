// Exact Euclidean distance transform of a voxel box in OpenCL C 1.2 (device code only; twin: distance.py).
// The separable squared-distance transform of Felzenszwalb and Huttenlocher in integer arithmetic, one
// work-item per 1-D line of an n0 x n1 x n2 box (C order): edt_first_pass (the squared distance along
// the line to its nearest obstacle voxel, mask != 0, or mask == 0 with invert), then edt_parabola_pass
// on each other axis (the lower envelope of parabolas; breakpoints compared as exact fractions with
// 64-bit cross products; the envelope's stack in scratch at the line's own positions). A work-item runs
// only if its line's todo byte is set, overwrites its line in place and flags (marks) the line along
// next_axis through every voxel whose value changed. INF (2^31 - 1): no obstacle within reach, or a
// value above cap2. Same arguments in the same order as the Warp kernels: the input, the box, the axis,
// cap2, (invert,) todo, scratch, the output, marks and next_axis, the first line (offset) and the number
// of lines (work-items past it return).

#define EDT_INF 2147483647

int3 line_of(int t, int n0, int n1, int n2, int axis) {
    if (axis == 0) return (int3)(t, n1 * n2, n0);
    if (axis == 1) {
        const int i = t / n2;
        return (int3)(i * n1 * n2 + (t - i * n2), n2, n1);
    }
    return (int3)(t * n2, 1, n2);
}

int line_through(int a, int n0, int n1, int n2, int axis) {
    const int i = a / (n1 * n2);
    const int r = a - i * n1 * n2;
    const int j = r / n2;
    const int k = r - j * n2;
    if (axis == 0) return j * n2 + k;
    if (axis == 1) return i * n2 + k;
    return i * n1 + j;
}

long lifted(__global const int *f, int base, int stride, int p) {
    return (long)f[base + p * stride] + (long)p * (long)p;
}

void put(__global int *out, int a, int v, __global uchar *marks, int n0, int n1, int n2, int next_axis) {
    if (out[a] != v) {
        out[a] = v;
        marks[line_through(a, n0, n1, n2, next_axis)] = 1;
    }
}

__kernel void edt_first_pass(
    __global const uchar *mask,
    int n0, int n1, int n2, int axis, int cap2, int invert,
    __global const uchar *todo,
    __global int *scratch,
    __global int *d2,
    __global uchar *marks, int next_axis,
    int offset, int n_lines)
{
    const int t = (int)get_global_id(0) + offset;
    if (t >= n_lines || todo[t] == 0) return;
    const int3 L = line_of(t, n0, n1, n2, axis);
    const int base = L.x, stride = L.y, n = L.z;
    int last = -1;
    for (int q = 0; q < n; ++q) {
        const int a = base + q * stride;
        const int hit = mask[a] != 0 ? 1 : 0;
        if (hit != invert) last = q;
        scratch[a] = last >= 0 ? q - last : EDT_INF;
    }
    int nxt = -1;
    for (int q = n - 1; q >= 0; --q) {
        const int a = base + q * stride;
        const int hit = mask[a] != 0 ? 1 : 0;
        if (hit != invert) nxt = q;
        int d = scratch[a];
        if (nxt >= 0 && nxt - q < d) d = nxt - q;
        const int v = (d < EDT_INF && d * d <= cap2) ? d * d : EDT_INF;
        put(d2, a, v, marks, n0, n1, n2, next_axis);
    }
}

__kernel void edt_parabola_pass(
    __global const int *src,
    int n0, int n1, int n2, int axis, int cap2,
    __global const uchar *todo,
    __global int *scratch,
    __global int *dst,
    __global uchar *marks, int next_axis,
    int offset, int n_lines)
{
    const int t = (int)get_global_id(0) + offset;
    if (t >= n_lines || todo[t] == 0) return;
    const int3 L = line_of(t, n0, n1, n2, axis);
    const int base = L.x, stride = L.y, n = L.z;
    int k = -1;
    for (int q = 0; q < n; ++q) {
        if (src[base + q * stride] >= EDT_INF) continue;
        const long Fq = lifted(src, base, stride, q);
        while (k >= 1) {
            const int p = scratch[base + k * stride];
            const int r = scratch[base + (k - 1) * stride];
            const long Fp = lifted(src, base, stride, p);
            const long Fr = lifted(src, base, stride, r);
            if ((Fq - Fp) * (long)(p - r) <= (Fp - Fr) * (long)(q - p)) {
                --k;
            } else {
                break;
            }
        }
        ++k;
        scratch[base + k * stride] = q;
    }
    if (k < 0) {
        for (int q = 0; q < n; ++q) put(dst, base + q * stride, EDT_INF, marks, n0, n1, n2, next_axis);
        return;
    }
    int j = 0;
    int vj = scratch[base];
    long Fj = lifted(src, base, stride, vj);
    for (int q = 0; q < n; ++q) {
        while (j < k) {
            const int vn = scratch[base + (j + 1) * stride];
            const long Fn = lifted(src, base, stride, vn);
            if (Fn - Fj < (long)(2 * q) * (long)(vn - vj)) {
                ++j;
                vj = vn;
                Fj = Fn;
            } else {
                break;
            }
        }
        const int e = q - vj;
        const long d = (long)e * (long)e + (long)src[base + vj * stride];
        put(dst, base + q * stride, d <= (long)cap2 ? (int)d : EDT_INF, marks, n0, n1, n2, next_axis);
    }
}
