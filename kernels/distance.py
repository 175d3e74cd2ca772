"""Exact Euclidean distance transform of a voxel box in NVIDIA Warp (device code only; twin: ``distance.cl``).

The separable squared-distance transform of Felzenszwalb and Huttenlocher (the lower envelope of
parabolas), in integer arithmetic so that every device gives the same squared distances, bit for bit
(the host, ``gpumap/layers/distance_device.py``, turns them into metres). A box of ``n0 x n1 x n2`` voxels, C
order (``n2`` fastest), runs three launches, one per axis, one thread per 1-D line of the box:

1. ``edt_first_pass``: the squared distance along the line to the nearest obstacle voxel of the line
   (``mask != 0``, or ``== 0`` with ``invert``: the distance to the nearest free voxel), by a forward
   and a backward sweep.
2. ``edt_parabola_pass`` (twice, on the two other axes): ``d(q) = min_p (q - p)^2 + f(p)`` over the
   line's finite ``f``, by the lower envelope of the parabolas rooted at those ``p``. The envelope's
   breakpoints are compared as exact fractions (int64 cross products), never rounded; the stack of
   the envelope's parabolas lives in ``scratch`` at the line's own positions (a buffer the size of
   the box), so any line length is exact.

Incremental by lines: a thread runs only if its line's ``todo`` flag is set; it overwrites its line of
the output in place and, where a value changes, sets the flag (``marks``) of the line through that voxel
along ``next_axis``: the lines the next pass must run. Lines whose input did not change keep their
output, so the three stored passes always equal a full transform of the current mask.

Squared distances are voxel units; ``INF`` (2^31 - 1) stands for "no obstacle within reach": a line
without one, or any value above ``cap2`` (the truncation radius squared: a partial sum above it can only
grow, so dropping it changes no distance at or below the radius). The host keeps
``n0^2 + n1^2 + n2^2 < INF`` so no finite value overflows int32.

Arguments, in order: the input (``mask``, or the previous pass's ``src``), the box (``n0, n1, n2``),
the axis of the lines, ``cap2``, (``invert``,) the lines to run (``todo``, a byte per line), the
``scratch`` buffer, the output, the next pass's flags (``marks``) and its axis, then where a launch split
over CPU threads starts (``offset``) and how many lines there are.
"""

import warp as wp

INF = wp.constant(2147483647)


@wp.func
def line_of(t: int, n0: int, n1: int, n2: int, axis: int) -> wp.vec3i:
    """Line ``t`` of the box along ``axis``: (its first voxel's flat index, the stride between its
    voxels, its length). Lines are numbered in C order of the two other axes."""
    if axis == 0:
        return wp.vec3i(t, n1 * n2, n0)
    if axis == 1:
        i = t // n2
        return wp.vec3i(i * n1 * n2 + (t - i * n2), n2, n1)
    return wp.vec3i(t * n2, 1, n2)


@wp.func
def line_through(a: int, n0: int, n1: int, n2: int, axis: int) -> int:
    """The number of the line along ``axis`` through the voxel of flat index ``a``."""
    i = a // (n1 * n2)
    r = a - i * n1 * n2
    j = r // n2
    k = r - j * n2
    if axis == 0:
        return j * n2 + k
    if axis == 1:
        return i * n2 + k
    return i * n1 + j


@wp.func
def lifted(f: wp.array(dtype=int), base: int, stride: int, p: int) -> wp.int64:
    """``f(p) + p^2``: the parabola rooted at ``p`` lifted so that two of them meet where a line does."""
    return wp.int64(f[base + p * stride]) + wp.int64(p) * wp.int64(p)


@wp.func
def put(out: wp.array(dtype=int), a: int, v: int, marks: wp.array(dtype=wp.uint8), n0: int, n1: int,
        n2: int, next_axis: int):
    """``out[a] = v``, flagging the next pass's line through ``a`` when the value changes."""
    if out[a] != v:
        out[a] = v
        marks[line_through(a, n0, n1, n2, next_axis)] = wp.uint8(1)


@wp.kernel
def edt_first_pass(
    mask: wp.array(dtype=wp.uint8),
    n0: int,
    n1: int,
    n2: int,
    axis: int,
    cap2: int,
    invert: int,
    todo: wp.array(dtype=wp.uint8),
    scratch: wp.array(dtype=int),
    d2: wp.array(dtype=int),
    marks: wp.array(dtype=wp.uint8),
    next_axis: int,
    offset: int,
    n_lines: int,
):
    """One thread per line along ``axis`` flagged in ``todo``: squared distance to the line's nearest
    obstacle voxel (``mask != 0``; ``invert``: ``mask == 0``), ``INF`` without one or above ``cap2``."""
    t = wp.tid() + offset
    if t >= n_lines:
        return
    if todo[t] == wp.uint8(0):
        return
    L = line_of(t, n0, n1, n2, axis)
    base = L[0]
    stride = L[1]
    n = L[2]
    last = int(-1)  # forward: the distance back to the last obstacle, in scratch
    for q in range(n):
        a = base + q * stride
        hit = int(0)
        if mask[a] != wp.uint8(0):
            hit = 1
        if hit != invert:
            last = q
        if last >= 0:
            scratch[a] = q - last
        else:
            scratch[a] = INF
    nxt = int(-1)
    for r in range(n):
        q = n - 1 - r
        a = base + q * stride
        hit = int(0)
        if mask[a] != wp.uint8(0):
            hit = 1
        if hit != invert:
            nxt = q
        d = scratch[a]
        if nxt >= 0 and nxt - q < d:
            d = nxt - q
        v = INF
        if d < INF:
            if d * d <= cap2:
                v = d * d
        put(d2, a, v, marks, n0, n1, n2, next_axis)


@wp.kernel
def edt_parabola_pass(
    src: wp.array(dtype=int),
    n0: int,
    n1: int,
    n2: int,
    axis: int,
    cap2: int,
    todo: wp.array(dtype=wp.uint8),
    scratch: wp.array(dtype=int),
    dst: wp.array(dtype=int),
    marks: wp.array(dtype=wp.uint8),
    next_axis: int,
    offset: int,
    n_lines: int,
):
    """One thread per line along ``axis`` flagged in ``todo``: ``dst(q) = min_p (q - p)^2 + src(p)``
    over the line's finite ``src``, ``INF`` where none or above ``cap2`` (the lower envelope, exact)."""
    t = wp.tid() + offset
    if t >= n_lines:
        return
    if todo[t] == wp.uint8(0):
        return
    L = line_of(t, n0, n1, n2, axis)
    base = L[0]
    stride = L[1]
    n = L[2]
    # the envelope: scratch[base + j stride] for j = 0..k holds the roots, left to right
    k = int(-1)
    for q in range(n):
        if src[base + q * stride] < INF:
            Fq = lifted(src, base, stride, q)
            while k >= 1:
                p = scratch[base + k * stride]
                r = scratch[base + (k - 1) * stride]
                Fp = lifted(src, base, stride, p)
                Fr = lifted(src, base, stride, r)
                # q's parabola passes below p's before p's starts (below r's): p is hidden
                if (Fq - Fp) * wp.int64(p - r) <= (Fp - Fr) * wp.int64(q - p):
                    k -= 1
                else:
                    break
            k += 1
            scratch[base + k * stride] = q
    if k < 0:
        for q in range(n):
            put(dst, base + q * stride, INF, marks, n0, n1, n2, next_axis)
        return
    j = int(0)
    vj = scratch[base]
    Fj = lifted(src, base, stride, vj)
    for q in range(n):
        while j < k:
            vn = scratch[base + (j + 1) * stride]
            Fn = lifted(src, base, stride, vn)
            # the next parabola starts at or before q (its breakpoint (Fn - Fj) / 2 (vn - vj) < q)
            if Fn - Fj < wp.int64(2 * q) * wp.int64(vn - vj):
                j += 1
                vj = vn
                Fj = Fn
            else:
                break
        e = q - vj
        d = wp.int64(e * e) + wp.int64(src[base + vj * stride])
        v = INF
        if d <= wp.int64(cap2):
            v = int(d)
        put(dst, base + q * stride, v, marks, n0, n1, n2, next_axis)
