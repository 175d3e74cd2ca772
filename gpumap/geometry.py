"""Host-side geometry shared by every backend: per-ping parameters and the voxel template.

Everything a kernel needs for one ping is packed into :class:`PingParams` (a flat float32 /
int32 record with one layout for NumPy, Warp and OpenCL), so the kernels take the same few
arguments in the same order on every backend.
"""

from __future__ import annotations

import math

import numpy as np

from gpumap.spec import GridSpec, SonarSpec

__all__ = [
    "BRIGHT_SHARE",
    "CARVE_VIEWS",
    "FOOTPRINT_PAD_M",
    "PING_DTYPE",
    "RULES",
    "SHARE_Z",
    "footprint_radius_m",
    "make_template_S",
    "ping_params",
    "pose_pad_m",
    "set_footprint_pad",
]

# The footprint is the voxel's bounding sphere, padded to absorb float32 rounding of the
# world->sonar transform (|p| <= ~5 m gives errors of a few 1e-7 m): the padding keeps the
# footprint conservative on every backend and costs at most one extra cell, rarely.
FOOTPRINT_PAD_M = 1e-5
_HALF_DIAG = math.sqrt(3.0) / 2.0

# One record per ping; all fields 4 bytes so C, Warp and NumPy agree on the layout.
PING_DTYPE = np.dtype(
    [
        ("A", np.float32, (9,)),  # rotation of T_S_W, row-major
        ("b", np.float32, (3,)),  # translation of T_S_W
        ("R", np.float32, (9,)),  # rotation of T_W_S, row-major (template method)
        ("t", np.float32, (3,)),  # translation of T_W_S
        ("origin", np.float32, (3,)),  # grid min corner, m
        ("voxel", np.float32),  # voxel edge, m
        ("rmin", np.float32),
        ("rmax", np.float32),
        ("inv_dr", np.float32),  # 1 / bin size, 1/m
        ("tan2_half_vfov", np.float32),  # tan(vfov / 2)^2
        ("tan_lo", np.float32),  # tangents of the fan's outer azimuth edges
        ("tan_hi", np.float32),
        ("rho", np.float32),  # footprint (bounding-sphere) radius, m
        ("dims", np.int32, (3,)),  # grid (nx, ny, nz)
        ("box_lo", np.int32, (3,)),  # first voxel index of the gather box
        ("box_n", np.int32, (3,)),  # gather box size per axis
        ("n_bins", np.int32),
        ("n_beams", np.int32),
        ("n_points", np.int32),  # template points (template method)
        ("win", np.int32),  # footprint height in bins, floor(2 rho / dr) + 2 (<= n_bins)
        ("n_levels", np.int32),  # beam levels of the max table
        ("lut_scale", np.float32),  # beam look-up table entries per radian
        ("lut_n", np.int32),  # beam look-up table entries
        ("wedge", np.float32, (4,)),  # (-sin lo, cos lo, sin hi, -cos hi): azimuth half-planes
        ("slab", np.float32),  # r_max sin(vfov / 2), bound on |z| in the sonar frame
        ("chunk", np.int32),  # voxels of a column per gather thread (set by the backend)
        ("near", np.float32),  # rho + shadow_m: how far the footprint reaches towards the sonar
        ("thr", np.float32),  # occupied intensity: a footprint max >= thr is a bright view
        ("thr_dark", np.float32),  # a clear view below this counts twice towards carving (thr / 2)
        ("rule", np.int32),  # 0: the paper's plain min; 1: visibility-aware (see gpumap.core.mapper)
        ("blk_lo", np.int32, (3,)),  # voxel index of the block index's first voxel (set by the backend)
        ("blk_n", np.int32, (3,)),  # the block index's extent, in blocks
        ("blk", np.int32),  # a block's edge along x and y, voxels (B)
        ("blk_z", np.int32),  # a block's edge along z, voxels (Bz)
    ]
)


def footprint_radius_m(voxel_size_m: float) -> float:
    """Radius of a voxel's footprint sphere: half the cube diagonal plus rounding pad."""
    return _HALF_DIAG * voxel_size_m * (1.0 + 1e-5) + FOOTPRINT_PAD_M


def static_params(
    spec: SonarSpec, grid: GridSpec, shadow_m: float = 0.0, rule: str = "plain", threshold: float = 0.1
) -> np.ndarray:
    """A PING_DTYPE record with the fields that do not change between pings filled in.

    ``shadow_m`` extends every footprint that far towards the sonar; ``rule`` and
    ``threshold`` select the update (see MinMaxMapper).
    """
    p = np.zeros((), dtype=PING_DTYPE)
    p["origin"] = grid.min_corner_m
    p["voxel"] = grid.voxel_size_m
    p["rmin"] = spec.range_min_m
    p["rmax"] = spec.range_max_m
    p["inv_dr"] = 1.0 / spec.bin_size_m
    p["tan2_half_vfov"] = math.tan(0.5 * spec.vfov_rad) ** 2
    tan_edges = beam_tan_edges(spec)
    p["tan_lo"] = tan_edges[0]
    p["tan_hi"] = tan_edges[-1]
    p["rho"] = footprint_radius_m(grid.voxel_size_m)
    p["dims"] = grid.shape
    p["n_bins"] = spec.n_bins
    p["n_beams"] = spec.n_beams
    # The sphere's bins [floor(a), floor(a + 2 rho/dr)] number at most floor(2 rho/dr) + 2:
    # a fixed window of that height from the first bin always holds them, one bin extra at most.
    p["near"] = float(p["rho"]) + shadow_m
    p["win"] = min(
        int(math.floor((float(p["rho"]) + float(p["near"])) * float(p["inv_dr"]))) + 2, spec.n_bins
    )
    p["n_levels"] = min(spec.n_beams.bit_length(), MAX_TABLE_LEVELS)
    p["lut_n"] = _lut_size(spec)
    p["lut_scale"] = p["lut_n"] / (p["tan_hi"] - p["tan_lo"])
    lo, hi = float(spec.beam_edges_rad[0]), float(spec.beam_edges_rad[-1])
    p["wedge"] = (-math.sin(lo), math.cos(lo), math.sin(hi), -math.cos(hi))
    # a hair wider than the aperture: the slab only bounds the column walk
    p["chunk"] = 1 << 30
    p["slab"] = spec.range_max_m * math.sin(0.5 * spec.vfov_rad) * (1 + 1e-4) + 1e-5
    p["thr"] = threshold
    p["thr_dark"] = np.float32(threshold) * np.float32(0.5)
    p["rule"] = RULES.index(rule)
    return p


#: Update rules, in the order of PING_DTYPE's ``rule`` codes.
RULES = ("plain", "visible", "evidence")
#: Clear dark views that carve a voxel once seen bright (a view darker than thr_dark counts twice).
CARVE_VIEWS = 2
#: Evidence rule: a voxel is free once its views show, at confidence SHARE_Z (a one-sided normal
#: quantile), that it is bright in fewer than BRIGHT_SHARE of its clear views.
BRIGHT_SHARE = 0.2
SHARE_Z = 1.645


def pose_pad_m(pose_cov: np.ndarray, range_max_m: float, sigmas: float) -> float:
    """How far a voxel's sonar-frame position may move under pose uncertainty, metres.

    ``pose_cov`` is (6, 6) over (translation m, rotation vector rad) of a right perturbation
    ``T_W_S = T_hat @ Exp(delta)`` (:mod:`gpumap.ekf`'s convention). A world point at range
    ``r`` moves in the sonar frame by ``-delta_t - delta_theta x p``, at most
    ``|delta_t| + r |delta_theta|``; each norm is bounded at ``sigmas`` standard deviations
    along its worst direction (the square root of the block's largest eigenvalue, times
    ``sqrt(3)`` so that the bound holds for the 3-D norm, not one axis), at ``r = r_max``.
    """
    ev_t = float(np.linalg.eigvalsh(pose_cov[:3, :3])[-1])
    ev_r = float(np.linalg.eigvalsh(pose_cov[3:, 3:])[-1])
    k = sigmas * math.sqrt(3.0)
    return k * (math.sqrt(max(ev_t, 0.0)) + range_max_m * math.sqrt(max(ev_r, 0.0)))


def set_footprint_pad(params: np.ndarray, rho0: float, near0: float, pad_m: float) -> None:
    """Grow this ping's footprint by ``pad_m`` (radius and reach towards the sonar) in place."""
    params["rho"] = rho0 + pad_m
    params["near"] = near0 + pad_m
    win = int(math.floor((float(params["rho"]) + float(params["near"])) * float(params["inv_dr"]))) + 2
    params["win"] = min(win, int(params["n_bins"]))


def beam_tan_edges(spec: SonarSpec) -> np.ndarray:
    """(n_beams + 1,) float32 tangents of the beam-cell edges: kernels compare ``y / x`` with
    them instead of taking ``atan2`` (the fan lies within +-90 deg, where tan is monotonic)."""
    return np.tan(spec.beam_edges_rad).astype(np.float32)


# Look-up entries per beam: the table is uniform in tan(azimuth), where beams near the fan's
# edges are wider (sec^2), so it is sized for the narrowest, at boresight.
LUT_PER_BEAM = 4
# Beam levels of the per-ping max table: spans of up to 31 beams take two reads; wider ones
# (voxels near the apex) a few more. More levels cost more to build than they save.
MAX_TABLE_LEVELS = 5


def _lut_size(spec: SonarSpec) -> int:
    te = np.tan(spec.beam_edges_rad)
    return int(LUT_PER_BEAM * spec.n_beams * max(1.0, (te[-1] - te[0]) / spec.hfov_rad))


def beam_lut(spec: SonarSpec) -> np.ndarray:
    """(lut_n,) int32: the beam holding the start of each uniform bucket of tan(azimuth).

    Kernels start from this guess and settle the exact beam with at most a few comparisons
    against the edges, instead of a binary search's unpredictable branches.
    """
    te = beam_tan_edges(spec)
    n = _lut_size(spec)
    t = te[0] + (te[-1] - te[0]) * np.arange(n) / n
    j = np.searchsorted(te[:-1], t, side="right") - 1
    return np.clip(j, 0, spec.n_beams - 1).astype(np.int32)


def ping_params(params: np.ndarray, T_W_S: np.ndarray, fov_pts_S: np.ndarray, grid: GridSpec) -> int:
    """Fill the per-ping fields of ``params`` in place; return the gather box's (i, j) column count.

    ``fov_pts_S`` is :meth:`SonarSpec.fov_corners_S`: points whose box, padded by one voxel,
    contains every voxel centre the ping can see. (On the hot path: a few small array ops.)
    """
    R = T_W_S[:3, :3]
    t = T_W_S[:3, 3]
    Rt = R.T
    params["R"] = R.ravel()
    params["t"] = t
    params["A"] = Rt.ravel()
    params["b"] = -(Rt @ t)
    pts_W = fov_pts_S @ Rt
    s = grid.voxel_size_m
    q0 = (pts_W.min(axis=0) + t - grid.min_corner_m) / s
    q1 = (pts_W.max(axis=0) + t - grid.min_corner_m) / s
    lo = params["box_lo"]
    n = params["box_n"]
    for ax, dim in enumerate(grid.shape):
        i0 = min(max(math.floor(q0[ax]) - 1, 0), dim)
        i1 = min(max(math.floor(q1[ax]) + 1, -1), dim - 1)
        lo[ax] = i0
        n[ax] = max(i1 - i0 + 1, 0)
    return int(n[0]) * int(n[1]) if n[2] > 0 else 0


def make_template_S(spec: SonarSpec, voxel_size_m: float) -> np.ndarray:
    """The paper's voxel template: (m, 3) float32 sonar-frame points at voxel spacing in the FOV.

    A meshgrid at ``voxel_size_m`` spacing over ``x in [0, r_max]``, ``y, z`` in the
    symmetric box that holds the fan, with the origin on a grid point; only the points
    inside the field of view are kept (the paper's constraints a-c, with the field of
    view of :meth:`SonarSpec.in_fov`).
    """
    s = float(voxel_size_m)
    rmax = spec.range_max_m
    ymax = rmax * max(abs(math.sin(spec.beam_edges_rad[0])), abs(math.sin(spec.beam_edges_rad[-1])))
    zmax = rmax * math.sin(0.5 * spec.vfov_rad)
    xs = np.arange(0.0, rmax + s, s)
    ys = np.arange(-math.ceil(ymax / s), math.ceil(ymax / s) + 1) * s
    zs = np.arange(-math.ceil(zmax / s), math.ceil(zmax / s) + 1) * s
    out = []
    Y, Z = np.meshgrid(ys, zs, indexing="ij")
    for x in xs:  # slab by slab keeps the memory to one (ny, nz) plane
        P = np.stack([np.full_like(Y, x), Y, Z], -1).reshape(-1, 3)
        out.append(P[spec.in_fov(P)])
    return np.ascontiguousarray(np.concatenate(out), dtype=np.float32)
