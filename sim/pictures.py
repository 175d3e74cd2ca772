"""The demo's pictures: the map beside the simulator's truth (:func:`demo_pictures`)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from gpumap.io.pictures import (
    _block_any,
    _block_max,
    _camera_for,
    _picture_factor,
    colour_voxels,
    exposed_faces_mesh,
    grid_origin,
    height_map,
    render_voxels,
)

__all__ = ["demo_pictures"]


def demo_pictures(
    out: Any, grid: Any, values: np.ndarray, truth: Any, threshold: float, rule: str, title: str = "",
    detectable: np.ndarray | None = None,
) -> list[str]:
    """Write ``map_vs_truth.png``, ``height_map.png`` and ``errors_by_object.png`` into ``out``.

    The map and the truth are drawn from one viewpoint over the voxels the pings observed:
    the map's occupied voxels (shaded boxes, coloured by height), the truth's surface
    voxels coloured by object. Per object, with the definitions of ``metrics.json``
    (:mod:`gpumap.sim.metrics`): the miss rate (of its voxels some ping could detect,
    ``detectable`` (nx, ny, nz) bool, default every surface voxel, the share the map does not
    call occupied) and the phantom voxels (more than one voxel from any true surface, called
    occupied) whose nearest true surface is that object's.
    """
    import matplotlib
    from gpumap.sim.metrics import miss_by_object, phantom_far

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from scipy import ndimage

    out = Path(out)
    vs = float(grid.voxel_size_m)
    o = grid_origin(grid)
    seen = np.isfinite(values)
    occ = seen & (np.nan_to_num(values, nan=-1.0) >= threshold)
    tsurf = truth.surface & seen
    names = list(truth.names)
    idx = np.argwhere(tsurf | occ)
    if len(idx):
        lo, hi = o + idx.min(0) * vs - vs, o + idx.max(0) * vs + vs
    else:
        lo, hi = np.asarray(grid.min_corner_m), np.asarray(grid.max_corner_m)
    zlo, zhi = float(lo[2]), float(hi[2])
    eye, target = _camera_for(lo, hi)
    # large maps (the survey) are drawn from coarser voxels, each occupied if any of its
    # fine voxels is: the picture keeps every surface, its memory stays bounded
    f = _picture_factor(occ.size)
    r_occ, r_tsurf, r_label = _block_any(occ, f), _block_any(tsurf, f), _block_max(truth.label, f)
    r_vs, r_o = vs * f, o + 0.5 * (f - 1) * vs
    col_map = colour_voxels(None, r_occ, "height", zlo, zhi, z0_m=r_o[2], voxel_m=r_vs)
    tab = matplotlib.colormaps["tab10"](np.arange(10))[:, :3].astype(np.float32)
    col_truth = tab[np.clip(r_label, 0, None) % 10]
    size = (900, 640)
    img_map = render_voxels([exposed_faces_mesh(r_occ, col_map, r_o, r_vs)], eye, target, size)
    img_truth = render_voxels([exposed_faces_mesh(r_tsurf, col_truth, r_o, r_vs)], eye, target, size)
    del col_map, col_truth

    fig = plt.figure(figsize=(13, 5.4), dpi=90)
    gs = fig.add_gridspec(1, 3, width_ratios=(1, 1, 0.035), wspace=0.03)
    for j, (img, head) in enumerate(
        (
            (
                img_map,
                f"map ({rule} rule): {int(occ.sum())} occupied voxels "
                f"(value >= {threshold:g}), colour = height",
            ),
            (img_truth, f"truth: {int(tsurf.sum())} surface voxels the pings observed, colour = object"),
        )
    ):
        ax = fig.add_subplot(gs[0, j])
        ax.imshow(img)
        ax.set_axis_off()
        ax.set_title(head, fontsize=10)
    handles = [
        matplotlib.patches.Patch(color=tab[i % 10], label=n)
        for i, n in enumerate(names)
        if np.any(truth.label[tsurf] == i)
    ]
    fig.axes[1].legend(handles=handles, loc="lower right", fontsize=8, frameon=True, ncol=2)
    cax = fig.add_subplot(gs[0, 2])
    sm = matplotlib.cm.ScalarMappable(norm=matplotlib.colors.Normalize(zlo, zhi), cmap="turbo")
    fig.colorbar(sm, cax=cax, label="height z (m)")
    fig.suptitle(f"{title}same viewpoint, {vs * 100:g} cm voxels", fontsize=11)
    fig.subplots_adjust(left=0.01, right=0.94, top=0.9, bottom=0.02)
    fig.savefig(out / "map_vs_truth.png")
    plt.close(fig)

    # top-down height maps, one colour scale
    hm_map = height_map(occ, o[2], vs)
    hm_truth = height_map(tsurf, o[2], vs)
    fig, axs = plt.subplots(1, 2, figsize=(12, 4.8), dpi=90, sharey=True)
    ext = (
        grid.min_corner_m[0],
        grid.min_corner_m[0] + grid.shape[0] * vs,
        grid.min_corner_m[1],
        grid.min_corner_m[1] + grid.shape[1] * vs,
    )
    cmap = matplotlib.colormaps["turbo"].with_extremes(bad="#d9d9d9")
    im = None
    for ax, hm, head in (
        (axs[0], hm_map, "map: top of the highest occupied voxel"),
        (axs[1], hm_truth, "truth: top of the observed surface"),
    ):
        im = ax.imshow(
            hm.T, origin="lower", extent=ext, cmap=cmap, vmin=zlo, vmax=zhi, interpolation="nearest"
        )
        ax.set_title(head, fontsize=10)
        ax.set_xlabel("x (m)")
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
    axs[0].set_ylabel("y (m)")
    fig.colorbar(im, ax=axs, label="height z (m)  (grey: nothing occupied)", shrink=0.9)
    fig.suptitle(f"{title}height seen from above", fontsize=11)
    fig.savefig(out / "height_map.png", bbox_inches="tight")
    plt.close(fig)

    # misses and phantoms per object, as metrics.json counts them
    det = truth.surface if detectable is None else np.asarray(detectable).reshape(truth.surface.shape)
    fp = phantom_far(values, truth, threshold)
    _, near = ndimage.distance_transform_edt(~truth.surface, return_indices=True)
    fp_label = truth.label[tuple(n[fp] for n in near)]
    rows = [
        (n, 100.0 * missed / of, of, int(np.sum(fp_label == names.index(n))))
        for n, (missed, of) in miss_by_object(values, truth, threshold, det).items()
    ]
    fig, axs = plt.subplots(1, 2, figsize=(12, 4.2), dpi=90)
    y = np.arange(len(rows))
    colours = [tab[names.index(r[0]) % 10] for r in rows]
    axs[0].barh(y, [r[1] for r in rows], color=colours)
    for k, r in enumerate(rows):
        axs[0].text(r[1] + 1, k, f"{r[1]:.1f} % of {r[2]}", va="center", fontsize=8)
    axs[0].set(
        yticks=y,
        yticklabels=[r[0] for r in rows],
        xlim=(0, 110),
        xlabel="% of the surface voxels some ping could detect\n"
        "that the map does not call occupied (free or unknown)",
        title="missed (metrics.json: miss_rate_by_object)",
    )
    axs[0].invert_yaxis()
    axs[1].barh(y, [r[3] for r in rows], color=colours)
    for k, r in enumerate(rows):
        axs[1].text(r[3], k, f" {r[3]}", va="center", fontsize=8)
    axs[1].set(
        yticks=y,
        yticklabels=[],
        xlabel="voxels called occupied more than one voxel from any\n"
        "true surface, counted by the nearest object",
        title="phantom voxels (metrics.json: false_positive_rate_far)",
    )
    axs[1].invert_yaxis()
    fig.suptitle(f"{title}errors per object ({rule} rule, value >= {threshold:g})", fontsize=11)
    fig.tight_layout()
    fig.savefig(out / "errors_by_object.png")
    plt.close(fig)
    return ["map_vs_truth.png", "height_map.png", "errors_by_object.png"]
