"""The per-ping max table built on the host: whole-image NumPy passes for CPU devices (Warp on
a CPU, OpenCL on PoCL), the same table the GPU kernels build, bit for bit.
"""

from __future__ import annotations

import numpy as np

from gpumap.backends.base import U8_SCALE
from gpumap.geometry import MAX_TABLE_LEVELS
from gpumap.spec import SonarSpec


def table_size(spec: SonarSpec) -> int:
    """Floats in a per-ping max table: its levels plus two scratch planes."""
    return (min(spec.n_beams.bit_length(), MAX_TABLE_LEVELS) + 2) * spec.n_bins * spec.n_beams


def build_table_host(
    image: np.ndarray,
    win: int,
    n_levels: int,
    table: np.ndarray,
    rows: np.ndarray,
    scratch: np.ndarray | None = None,
    pool=None,
) -> None:
    """The per-ping max table in NumPy (CPUs): what ``build_bin_window`` and
    ``build_beam_levels`` make, in a dozen whole-image passes instead of a strided walk.

    ``table`` is (n_levels, n_bins, n_beams) float32, written in place; ``rows`` (n_bins,)
    int: for each bin i, ``max(min(i + win - 1, n_bins - 1) - 2^k + 1, i)`` with ``2^k`` the
    largest power of two <= win (:func:`table_rows`). A uint8 ``image`` is maximised as bytes
    in ``scratch`` (same shape as ``table``, uint8; a quarter of the memory traffic) and then
    scaled: ``byte * U8_SCALE`` is monotonic, so the max of the scaled bytes is the scaled max.
    With a ``pool`` (an executor with a free worker) the passes run on two threads: level 0 by
    halves of the beams, the beam levels by halves of the bins (NumPy releases the GIL).
    Maxima are exact, so the values are the kernels' bit for bit.
    """
    lv = table if image.dtype != np.uint8 else scratch
    n, nj = image.shape

    def bins(c0: int, c1: int) -> None:  # level 0 of beams [c0, c1)
        s = lv[0, :, c0:c1]
        s[...] = image[:, c0:c1]
        w = 1
        while 2 * w <= win:  # s[i] = max over bins [i, i + 2w - 1] (clipped)
            np.maximum(s[: n - w], s[w:], out=s[: n - w])
            w *= 2
        # two overlapping spans of w cover [i, min(i + win - 1, n - 1)]
        np.maximum(s, s[rows], out=s)

    def beams(r0: int, r1: int) -> None:  # levels 1.. of bins [r0, r1), then the scaling
        step = 1
        for k in range(1, n_levels):  # beam spans of 2^k (clipped at the last beam)
            prev, cur = lv[k - 1, r0:r1], lv[k, r0:r1]
            np.maximum(prev[:, :-step], prev[:, step:], out=cur[:, :-step])
            np.maximum(prev[:, -step:], prev[:, -1:], out=cur[:, -step:])
            step *= 2
        if lv is not table:
            np.multiply(lv[:, r0:r1], U8_SCALE, out=table[:, r0:r1])

    if pool is None:
        bins(0, nj)
        beams(0, n)
        return
    for fn, size in ((bins, nj), (beams, n)):
        fut = pool.submit(fn, size // 2, size)
        try:
            fn(0, size // 2)
        finally:
            fut.result()


def table_rows(n_bins: int, win: int) -> np.ndarray:
    """The second read of :func:`build_table_host`'s level 0, per bin."""
    w = 1 << (max(1, win).bit_length() - 1)
    i = np.arange(n_bins)
    return np.maximum(np.minimum(i + win - 1, n_bins - 1) - w + 1, i)


def opencl_host_table(b, params, image) -> None:
    """CPU OpenCL devices: build ping ``params``' max table of ``image`` with whole-image NumPy
    passes straight into ``b.table`` mapped on the host (no copy); ``b`` is an OpenCL backend."""
    cl = b.cl
    win = int(params["win"])
    rows = b._rows.get(win)
    if rows is None:
        rows = b._rows[win] = table_rows(b.n_bins, win)
    shape = (b.n_levels, b.n_bins, b.n_beams)
    # in order: the map waits for the previous ping's kernels, which read the table
    tab, _ = cl.enqueue_map_buffer(
        b.queue, b.table, cl.map_flags.WRITE_INVALIDATE_REGION, 0, shape, np.float32
    )
    try:
        build_table_host(image, win, b.n_levels, tab, rows, b.table_u8, b._pool)
    finally:
        tab.base.release(b.queue)


def warp_host_table(b, params, image) -> None:
    """Warp on a CPU: ping ``params``' max table of ``image`` into ``b.table_np`` (NumPy passes,
    uint8 images read directly); ``b`` is a Warp backend."""
    win = int(params["win"])
    rows = b._rows.get(win)
    if rows is None:
        rows = b._rows[win] = table_rows(b.n_bins, win)
    src = image if image.dtype == np.uint8 else b.image_np
    build_table_host(src, win, b.table_np.shape[0], b.table_np, rows, b.table_u8, b._pool)
