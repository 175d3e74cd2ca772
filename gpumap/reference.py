"""Plain NumPy twin of every kernel in ``kernels/minmax``: the oracle the backends are tested against.

It follows the kernels' arithmetic step by step in float32 (same formulas, same order),
but finds the maximum over each footprint with a different algorithm (a 2-D sparse table
of range maxima instead of a loop over cells), so it checks the kernels rather than
copying them. It is also the ``numpy`` backend.

Per voxel centre ``c`` (world frame) and ping ``(image, T_W_S)``:

1. ``p = T_S_W c``; ``r = |p|``, ``h^2 = p_x^2 + p_y^2``, ``t = p_y / p_x`` (the tangent of
   the azimuth: the fan lies within +-90 deg, so comparing tangents replaces ``atan2``).
2. Observed when ``p_x > 0``, ``r_min <= r < r_max``, ``p_z^2 <= tan^2(vfov/2) h^2`` and
   ``t`` lies within the tangents of the fan's outer beam edges. Otherwise the voxel is
   left as it is.
3. Footprint: bins ``b0 = floor((r - near - r_min) / dr)`` to ``b0 + win - 1`` (``near =
   rho + shadow_m``; ``win = floor((rho + near) / dr) + 2``, the fixed height that always
   holds those bins; with ``shadow_m = 0`` at most one bin more than the sphere's),
   clipped to the image, and the beams holding
   azimuths ``theta -+ asin(rho / h)``, as tangents ``(t -+ u) / (1 +- t u)`` with
   ``u = rho / sqrt(h^2 - rho^2)`` (every beam when ``h <= rho``; the first or last beam
   when the sum passes +-90 deg), where ``rho`` is the voxel's bounding-sphere radius
   (:func:`gpumap.geometry.footprint_radius_m`).
4. Ping value = max of the image over the footprint.
5. Update, ``rule = "plain"`` (the paper): ``grid = min(grid, v)``.
   ``rule = "visible"`` keeps three numbers per voxel: ``grid = min(grid, v)`` over every
   view, ``bright = min(bright, v)`` over the views with ``v >= thr``, and ``count``, the
   carving evidence, raised only by *clear* dark views (``v < thr`` and no image cell
   ``>= thr`` nearer than the footprint, ``bins [0, b0)``, in the footprint's beams: nothing
   stood between the sonar and the voxel at any elevation): by 2 when ``v < thr_dark``, else
   by 1, saturating at 255. A dark view behind a return proves nothing (the voxel may lie in
   that return's acoustic shadow) and does not count. The map value is ``bright`` where the
   voxel was ever bright and ``count < CARVE_VIEWS``, else ``grid``
   (:func:`visible_values`).
"""

from __future__ import annotations

import functools

import numpy as np

__all__ = [
    "add_counts", "beam_index_lo", "evidence_occupied", "evidence_values",
    "integrate_gather", "integrate_template", "pack_counts", "share_keeps", "split_counts", "visible_values",
    "voxel_ping_values",
]

_F = np.float32


def beam_span(
    t: np.ndarray, h2: np.ndarray, w, edges: np.ndarray, n_beams: int
) -> tuple[np.ndarray, np.ndarray]:
    """First and last beam (inclusive) that a sphere of radius ``w`` spans, for centres at azimuth
    tangent ``t`` and squared horizontal distance ``h2`` (float32 arrays; ``edges`` as
    :func:`beam_index_lo` takes them). The sphere spans azimuths theta -+ asin(w / h); in tangents
    u = tan(asin(w / h)). A sphere that holds the axis, or whose edge passes 90 degrees, reaches
    the first or last beam."""
    q = h2 - w * w
    narrow = q > 0
    u = w / np.sqrt(np.where(narrow, q, _F(1)))
    d0 = _F(1) + t * u
    d1 = _F(1) - t * u
    ok0 = narrow & (d0 > 0)
    ok1 = narrow & (d1 > 0)
    j0 = np.where(ok0, beam_index_lo((t - u) / np.where(ok0, d0, _F(1)), edges), 0)
    j1 = np.where(ok1, beam_index_lo((t + u) / np.where(ok1, d1, _F(1)), edges), n_beams - 1)
    return j0, j1


def beam_index_lo(t: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Largest beam ``j`` in ``[0, n_beams - 1]`` with ``edges[j] <= t`` (0 when none)."""
    n_beams = edges.shape[0] - 1
    j = np.searchsorted(edges[:n_beams], t, side="right") - 1
    return np.clip(j, 0, n_beams - 1)


class _RangeMax:
    """O(1) maximum over any cell rectangle of one image, after O(N log N) preparation."""

    def __init__(self, image: np.ndarray, max_bin_span: int) -> None:
        self.levels: list[list[np.ndarray]] = []
        rows = image
        kb = 0
        while True:
            cols = [rows]
            w = 1
            while 2 * w <= image.shape[1]:
                prev = cols[-1]
                cols.append(np.maximum(prev[:, :-w], prev[:, w:]))
                w *= 2
            self.levels.append(cols)
            h = 1 << kb
            if 2 * h > min(max_bin_span, image.shape[0]):
                break
            rows = np.maximum(rows[:-h], rows[h:])
            kb += 1

    def query(self, b0: np.ndarray, b1: np.ndarray, j0: np.ndarray, j1: np.ndarray) -> np.ndarray:
        nb = b1 - b0 + 1
        nj = j1 - j0 + 1
        kb = np.floor(np.log2(nb)).astype(np.int64)
        kj = np.floor(np.log2(nj)).astype(np.int64)
        out = np.empty(b0.shape, dtype=_F)
        for a in np.unique(kb):
            ma = kb == a
            for c in np.unique(kj[ma]):
                m = ma & (kj == c)
                tab = self.levels[a][c]
                bb0, bb1 = b0[m], b1[m] - (1 << a) + 1
                jj0, jj1 = j0[m], j1[m] - (1 << c) + 1
                out[m] = np.maximum(
                    np.maximum(tab[bb0, jj0], tab[bb0, jj1]), np.maximum(tab[bb1, jj0], tab[bb1, jj1])
                )
        return out


def voxel_ping_values(
    params: np.ndarray, image: np.ndarray, edges: np.ndarray, centres_W: np.ndarray, clear: bool = False
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Ping value of each voxel centre, -1 where the ping does not observe it.

    With ``clear=True`` also (m,) bool: the view is clear (no image cell ``>= thr`` in the
    footprint's beams nearer than its first bin).

    Parameters
    ----------
    params : PING_DTYPE record (see :mod:`gpumap.geometry`), per-ping fields filled.
    image : (n_bins, n_beams) float32 in [0, 1].
    edges : (n_beams + 1,) float32 tangents of the beam-cell edges (:func:`gpumap.geometry.beam_tan_edges`).
    centres_W : (m, 3) float32 voxel centres, world frame, metres.

    Returns
    -------
    (m,) float32
    """
    A = params["A"].reshape(3, 3)
    b = params["b"]
    c = centres_W
    x = A[0, 0] * c[:, 0] + A[0, 1] * c[:, 1] + A[0, 2] * c[:, 2] + b[0]
    y = A[1, 0] * c[:, 0] + A[1, 1] * c[:, 1] + A[1, 2] * c[:, 2] + b[1]
    z = A[2, 0] * c[:, 0] + A[2, 1] * c[:, 1] + A[2, 2] * c[:, 2] + b[2]
    h2 = x * x + y * y
    r = np.sqrt(h2 + z * z)
    pos = x > 0
    t = y / np.where(pos, x, _F(1))
    seen = (
        pos
        & (r >= params["rmin"])
        & (r < params["rmax"])
        & (z * z <= params["tan2_half_vfov"] * h2)
        & (t >= params["tan_lo"])
        & (t <= params["tan_hi"])
    )
    out = np.full(c.shape[0], -1.0, dtype=_F)
    is_clear = np.zeros(c.shape[0], bool)
    if not seen.any():
        return (out, is_clear) if clear else out
    r, h2, t = r[seen], h2[seen], t[seen]
    rho = params["rho"]
    rmin = params["rmin"]
    inv_dr = params["inv_dr"]
    n_bins = int(params["n_bins"])
    n_beams = int(params["n_beams"])
    first = np.floor((r - params["near"] - rmin) * inv_dr).astype(np.int64)  # < 0 near blanking
    b0 = np.maximum(first, 0)
    b1 = np.minimum(first + int(params["win"]) - 1, n_bins - 1)
    j0, j1 = beam_span(t, h2, rho, edges, n_beams)
    out[seen] = _RangeMax(image, int(params["win"])).query(b0, b1, j0, j1)
    if not clear:
        return out
    # Nearest-return test by another route than the kernels' per-beam first bright bin: the
    # largest cell over bins [0, b0) and the footprint's beams, from a running max along range.
    ahead = np.maximum.accumulate(image, axis=0)
    front = np.zeros(b0.shape, _F)
    some = b0 > 0
    if some.any():
        rows = b0[some] - 1
        front[some] = _RangeMax(ahead, 1).query(rows, rows, j0[some], j1[some])
    is_clear[seen] = front < params["thr"]
    return out, is_clear


def _centres(params: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """(m, 3) int voxel indices -> (m, 3) float32 centres, as the kernels compute them."""
    return params["origin"] + (idx.astype(_F) + _F(0.5)) * params["voxel"]


COUNT_LOW = np.uint64(0xFFFFFFFF)  # the low 32 bits of ``count``: clear dark views
COUNT_MAX = 0xFFFFFFFF  # each of the two counts saturates here (the visible rule's dark count at 255)


def split_counts(count: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``count`` (uint64, as the kernels pack it) -> (clear dark views, bright views), uint32 each."""
    c = np.asarray(count, dtype=np.uint64)
    return (c & COUNT_LOW).astype(np.uint32), (c >> np.uint64(32)).astype(np.uint32)


def pack_counts(dark: np.ndarray, hits: np.ndarray) -> np.ndarray:
    """Inverse of :func:`split_counts`: uint64 with ``hits`` in the high and ``dark`` in the low 32 bits."""
    return (np.asarray(hits, np.uint64) << np.uint64(32)) | np.asarray(dark, np.uint64)


def _update_state(
    params: np.ndarray,
    v: np.ndarray,
    clear: np.ndarray,
    flat: np.ndarray,
    bright: np.ndarray,
    count: np.ndarray,
) -> None:
    """The visible and evidence rules' state: ``bright`` and ``count`` at voxels ``flat``, in place."""
    thr = params["thr"]
    lit = v >= thr
    bright[flat[lit]] = np.minimum(bright[flat[lit]], v[lit])
    dark, hits = split_counts(count[flat])
    hits = np.where(lit, np.minimum(hits.astype(np.int64) + 1, COUNT_MAX), hits)
    clear_dark = clear & ~lit
    if int(params["rule"]) == 1:  # visible: a very dark view counts twice, the count stops at 255
        step, cap = np.where(v < params["thr_dark"], 2, 1), 255
    else:
        step, cap = 1, COUNT_MAX
    grown = np.minimum(dark.astype(np.int64) + step, cap)
    dark = np.where(clear_dark & (dark < cap), grown, dark)
    count[flat] = pack_counts(dark, hits)


def add_counts(a: np.ndarray, b: np.ndarray, rule: str) -> np.ndarray:
    """Two packed ``count`` arrays (uint64) merged: each half summed, saturating where the kernels
    saturate it (the visible rule's dark count at 255, every other count at 2^32 - 1). Saturating
    sums do not depend on the order, so disjoint pings merge bit for bit."""
    da, ha = split_counts(a)
    db, hb = split_counts(b)
    cap = 255 if rule == "visible" else COUNT_MAX
    dark = np.minimum(da.astype(np.uint64) + db, np.uint64(cap))
    hits = np.minimum(ha.astype(np.uint64) + hb, np.uint64(COUNT_MAX))
    return pack_counts(dark, hits)


def visible_values(
    grid: np.ndarray, bright: np.ndarray, count: np.ndarray, carve_views: int | None = None
) -> np.ndarray:
    """Map values of the visible rule: ``bright`` where the voxel was bright in some view and
    its clear dark evidence (the low half of ``count``) is below ``carve_views`` (default
    :data:`~gpumap.geometry.CARVE_VIEWS`), else ``grid`` (the min over every view; ``+inf``
    never observed)."""
    from gpumap.geometry import CARVE_VIEWS

    cv = CARVE_VIEWS if carve_views is None else carve_views
    return _bright_where(grid, bright, count, lambda c: (c & COUNT_LOW) < cv)


def _bright_where(grid: np.ndarray, bright: np.ndarray, count: np.ndarray, keeps) -> np.ndarray:
    """``grid`` with ``bright`` where a voxel was ever bright and ``keeps`` (packed counts of those
    voxels -> bool) holds. It looks at the voxels ever bright only: a map's read costs no
    temporaries over the whole grid."""
    out = np.array(grid, dtype=np.float32, copy=True)
    flat_b = np.asarray(bright).reshape(-1)
    idx = np.flatnonzero(np.isfinite(flat_b))
    keep = idx[keeps(np.asarray(count).reshape(-1)[idx])]
    out.reshape(-1)[keep] = flat_b[keep]
    return out


def evidence_occupied(dark: np.ndarray, hits: np.ndarray, p_min: float, z: float) -> np.ndarray:
    """The evidence rule's decision: a voxel is occupied when some view saw it bright and the
    views do not show, at confidence ``z`` (one-sided normal quantile), that its share of bright
    views is below ``p_min``: the one-sided binomial score test of ``share >= p_min`` does not
    reject, ``share >= p_min`` or ``(p_min - share)^2 n <= z^2 p_min (1 - p_min)`` with
    ``share = hits / n``, ``n = hits + dark`` (the same as: the Wilson score upper bound of the
    share is at least ``p_min``; a tie keeps the voxel). Unknown, free and occupied stay apart: no
    view, no bright view, or this test."""
    h = np.asarray(hits)
    out = h > 0
    idx = np.flatnonzero(out)  # the test runs on the voxels ever bright only (lean on memory)
    k = h.reshape(-1)[idx].astype(np.float64)
    n = k + np.asarray(dark).reshape(-1)[idx]
    out.reshape(-1)[idx] = share_keeps(k / n, n, p_min, z)
    return out


def share_keeps(share: np.ndarray, n: np.ndarray, p_min: float, z: float) -> np.ndarray:
    """True where the one-sided binomial score test at ``z`` does not reject ``share >= p_min`` for a
    ``share`` of bright views among ``n`` (:func:`evidence_occupied`): ``share >= p_min`` or
    ``(p_min - share)^2 n <= z^2 p_min (1 - p_min)``; a tie keeps."""
    near = (p_min - share) ** 2 * n <= z * z * p_min * (1.0 - p_min)
    return (share >= p_min) | near


def evidence_values(
    grid: np.ndarray, bright: np.ndarray, count: np.ndarray, p_min: float, z: float
) -> np.ndarray:
    """Map values of the evidence rule: ``bright`` (the min over the bright views, at least the
    threshold) where :func:`evidence_occupied` holds, else ``grid`` (the min over every view:
    below the threshold wherever a clear dark view came, ``+inf`` never observed)."""
    return _bright_where(grid, bright, count, lambda c: evidence_occupied(*split_counts(c), p_min, z))


def integrate_gather(
    params: np.ndarray,
    image: np.ndarray,
    edges: np.ndarray,
    grid: np.ndarray,
    state: tuple[np.ndarray, np.ndarray] | None = None,
    address=None,
) -> bool:
    """Gather method: every voxel of the ping's box, min-updated in ``grid`` ((n,) float32) in place.

    ``state``: ``(bright (n,) float32, count (n,) uint64)``, the visible or evidence rule's state (None:
    the plain rule). ``address``: (m, 3) int64 voxel indices -> (m,) int64 places in ``grid``
    (-1: nowhere); default the dense row-major grid of ``params["dims"]``. Returns False if an
    observed voxel had no place (it is skipped), else True.
    """
    lo = params["box_lo"].astype(np.int64)
    n = params["box_n"].astype(np.int64)
    if n.prod() == 0:
        return True
    address = address or functools.partial(_dense_address, params["dims"].astype(np.int64))
    complete = True
    # z-slabs keep the temporaries small for fine grids
    slab = max(1, int(4_000_000 // max(1, n[0] * n[1])))
    II, JJ = np.meshgrid(np.arange(n[0]) + lo[0], np.arange(n[1]) + lo[1], indexing="ij")
    II, JJ = II.ravel(), JJ.ravel()
    for k0 in range(0, int(n[2]), slab):
        ks = np.arange(k0, min(int(n[2]), k0 + slab)) + lo[2]
        idx = np.stack([np.repeat(II, ks.size), np.repeat(JJ, ks.size), np.tile(ks, II.size)], axis=-1)
        if state is None:
            v = voxel_ping_values(params, image, edges, _centres(params, idx))
        else:
            v, clear = voxel_ping_values(params, image, edges, _centres(params, idx), clear=True)
        m = v >= 0
        flat = address(idx[m])
        ok = flat >= 0
        complete &= bool(ok.all())
        flat, vm = flat[ok], v[m][ok]
        grid[flat] = np.minimum(grid[flat], vm)
        if state is not None:
            _update_state(params, vm, clear[m][ok], flat, *state)
    return complete


def _dense_address(dims: np.ndarray, idx: np.ndarray) -> np.ndarray:
    return (idx[:, 0] * dims[1] + idx[:, 1]) * dims[2] + idx[:, 2]


def integrate_template(
    params: np.ndarray,
    image: np.ndarray,
    edges: np.ndarray,
    template_S: np.ndarray,
    grid: np.ndarray,
    address=None,
) -> None:
    """The paper's six steps on a voxel template ((m, 3) float32, sonar frame); ``grid`` in place
    (``address`` as for :func:`integrate_gather`)."""
    R = params["R"].reshape(3, 3)
    t = params["t"]
    p = template_S
    # Step 1: template to world
    wx = R[0, 0] * p[:, 0] + R[0, 1] * p[:, 1] + R[0, 2] * p[:, 2] + t[0]
    wy = R[1, 0] * p[:, 0] + R[1, 1] * p[:, 1] + R[1, 2] * p[:, 2] + t[1]
    wz = R[2, 0] * p[:, 0] + R[2, 1] * p[:, 1] + R[2, 2] * p[:, 2] + t[2]
    # Step 2: nearest grid voxel (the one whose cube holds the point), drop those outside
    o = params["origin"]
    s = params["voxel"]
    idx = np.stack(
        [np.floor((wx - o[0]) / s), np.floor((wy - o[1]) / s), np.floor((wz - o[2]) / s)], -1
    ).astype(np.int64)
    dims = params["dims"].astype(np.int64)
    ok = np.all((idx >= 0) & (idx < dims), axis=1)
    idx = idx[ok]
    # Steps 3-5: back to the voxel centre, to the sonar frame, max over the footprint
    v = voxel_ping_values(params, image, edges, _centres(params, idx))
    m = v >= 0
    flat = (address or functools.partial(_dense_address, dims))(idx[m])
    ok = flat >= 0
    flat, vm = flat[ok], v[m][ok]
    # Step 6: min update (duplicates of a voxel carry the same value)
    np.minimum.at(grid, flat, vm)
