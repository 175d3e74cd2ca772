"""The two hard constraints of refinement, exactly as :mod:`gpumap.layers.refine` states them.

- :func:`carved_voxels`: the voxels clear dark views carved, which refinement never occupies;
- :func:`_views_and_raise`: after the fit, every beam's nearest bright bin keeps an occupied
  voxel (the highest one there is raised to :data:`~gpumap.layers.refined_map.OCCUPIED_LEVEL`), and
  the views per voxel that the confidence needs.
"""

from __future__ import annotations

import math

import numpy as np

from gpumap.layers.first_return import first_bright_bins
from gpumap.layers.refined_map import OCCUPIED_LEVEL
from gpumap.spec import GridSpec, SonarSpec

__all__ = ["REFINE_RULES", "carved_voxels"]

#: Rules whose maps keep the evidence refinement reads (:meth:`gpumap.MinMaxMapper.evidence`).
REFINE_RULES = ("evidence", "visible")


def _as_float(images: np.ndarray) -> np.ndarray:
    return (
        images.astype(np.float32) / np.float32(255.0)
        if images.dtype == np.uint8
        else images.astype(np.float32)
    )


def carved_voxels(
    rule: str,
    evidence: dict[str, np.ndarray],
    *,
    carve_views: int = 2,
    bright_share: float = 0.5,
    share_z: float = 1.645,
) -> np.ndarray:
    """(nx, ny, nz) bool: the voxels refinement must never occupy (the first hard constraint).

    Parameters
    ----------
    rule : str
        ``"visible"`` or ``"evidence"`` (the rules that keep evidence; others raise).
    evidence : dict
        :meth:`gpumap.MinMaxMapper.evidence` of the map: ``min_all`` float32 (``+inf`` never
        observed), ``count`` uint32 (clear dark views), ``hits`` uint32 (bright views).
    carve_views : int
        Visible rule: the mapper's ``carve_views``.
    bright_share, share_z : float
        Evidence rule: the mapper's settings (:func:`gpumap.reference.evidence_occupied`).

    Returns
    -------
    (nx, ny, nz) bool
        Visible rule: observed and ``count >= carve_views``. Evidence rule: observed, at least one
        clear view (``count + hits > 0``) and not ``evidence_occupied(count, hits, bright_share,
        share_z)``: seen bright yet shown at ``share_z`` to be bright in fewer than
        ``bright_share`` of its views, or never bright with clear dark views. A voxel observed only
        by dark views behind a return (shadow: no clear view) is not carved.
    """
    from gpumap.reference import evidence_occupied

    if rule not in REFINE_RULES:
        raise ValueError(f"Expected a map of rule {' or '.join(map(repr, REFINE_RULES))} (rules that keep "
                         f"evidence), but its rule is {rule!r}")
    observed = np.isfinite(evidence["min_all"])
    dark = np.asarray(evidence["count"])
    if rule == "visible":
        return observed & (dark >= carve_views)
    hits = np.asarray(evidence["hits"])
    clear = (dark.astype(np.uint64) + hits.astype(np.uint64)) > 0
    return observed & clear & ~evidence_occupied(dark, hits, float(bright_share), float(share_z))


def _views_and_raise(
    spec: SonarSpec,
    grid: GridSpec,
    occ: np.ndarray,
    movable: np.ndarray,
    images: np.ndarray,
    poses: np.ndarray,
    thr: float,
) -> tuple[np.ndarray, np.ndarray, int]:
    """(views per voxel, voxels raised, cells with no movable voxel) of the second hard constraint."""
    flat_occ = occ.reshape(-1)  # modified in place (a view of occ)
    centres = grid.centers(np.argwhere(np.ones(grid.shape, bool)))
    views = np.zeros(grid.n_voxels, np.int32)
    raised = np.zeros(grid.n_voxels, bool)
    mov = movable.reshape(-1)
    rho = 0.5 * math.sqrt(3.0) * grid.voxel_size_m
    unexplained = 0
    for img, T in zip(images, poses, strict=True):
        p_S = (centres - T[:3, 3]) @ T[:3, :3]
        views += spec.in_fov(p_S)
        fb = first_bright_bins(_as_float(img), thr)
        cand = np.flatnonzero(mov)
        q = p_S[cand]
        r = np.linalg.norm(q, axis=1)
        el = np.arctan2(q[:, 2], np.hypot(q[:, 0], q[:, 1]))
        az = np.arctan2(q[:, 1], q[:, 0])
        ang = np.arcsin(np.clip(rho / np.maximum(r, 1e-9), 0, 1))
        ok = (
            (r + rho >= spec.range_min_m)
            & (r - rho < spec.range_max_m)
            & (np.abs(el) <= 0.5 * spec.vfov_rad + ang)
        )
        ok &= (az + ang >= spec.beam_edges_rad[0]) & (az - ang <= spec.beam_edges_rad[-1])
        cand, r, az, ang = cand[ok], r[ok], az[ok], ang[ok]
        if len(cand) == 0:
            unexplained += int((fb >= 0).sum())
            continue
        dr = spec.bin_size_m
        i0 = np.floor((r - rho - spec.range_min_m) / dr).astype(np.int64)
        i1 = np.floor((r + rho - spec.range_min_m) / dr).astype(np.int64)
        b0 = np.clip(np.searchsorted(spec.beam_edges_rad, az - ang, side="right") - 1, 0, spec.n_beams - 1)
        b1 = np.clip(np.searchsorted(spec.beam_edges_rad, az + ang, side="right") - 1, 0, spec.n_beams - 1)
        n_b = b1 - b0 + 1
        rep = np.repeat(np.arange(len(cand)), n_b)
        beam = b0[rep] + (np.arange(rep.size) - np.repeat(np.cumsum(n_b) - n_b, n_b))
        f = fb[beam]
        cover = (f >= 0) & (f >= i0[rep]) & (f <= i1[rep])
        vox, beam = cand[rep[cover]], beam[cover]
        need = np.flatnonzero(fb >= 0)
        has = np.zeros(spec.n_beams, bool)
        has[beam] = True
        unexplained += int((~has[need]).sum())
        if len(vox) == 0:
            continue
        val = flat_occ[vox]
        best = np.full(spec.n_beams, -1.0, np.float32)
        np.maximum.at(best, beam, val)
        short = has & (best < OCCUPIED_LEVEL)
        if not short.any():
            continue
        sel = short[beam] & (val == best[beam])
        order = np.lexsort((vox[sel], beam[sel]))  # per beam, the lowest voxel index among ties
        bsel, vsel = beam[sel][order], vox[sel][order]
        first = np.r_[True, bsel[1:] != bsel[:-1]]
        up = vsel[first]
        flat_occ[up] = np.float32(OCCUPIED_LEVEL)
        raised[up] = True
    return views.reshape(grid.shape), raised.reshape(grid.shape), unexplained

