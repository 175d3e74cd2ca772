"""``gpumap refine``: the occupancy field that, rendered through the ping model, explains the pings.

Analysis by synthesis (issue 19). Start from a map that keeps evidence (the evidence rule, the
default, or the visible rule; :meth:`gpumap.MinMaxMapper.evidence`), live or saved
(:func:`refine_saved`), then minimise over a voxel field (``o >= 0`` per voxel,
trilinear; reflectivity ``rho``; one display gain and noise floor per recording)::

    mean over a batch of pings of  sum over rendered cells huber(t(render(o, rho)) - t(measured), delta)
        + sparsity * sum over movable voxels o_v
        + smoothness * sum over neighbouring movable voxel pairs (o_v - o_n)^2

with ``t(I) = (I + 1e-3) ** power`` (square roots by default), by Adam on random batches of
pings (projected onto the bounds below after every step), the
gradients from Warp's tape (:class:`gpumap.layers.render.PingRenderer`; CPU or CUDA). The gain starts
where the measured and rendered energies agree, the floor at the median measured intensity.

Two names for two quantities, kept apart everywhere:

- the **field** ``o`` in [0, 1] (:attr:`RefineResult.field`): what the renderer takes
  (:func:`render_map`'s ``field``, :meth:`gpumap.layers.render.PingRenderer.render`'s occupancy);
- the **occupancy** ``1 - exp(-kappa o)`` (:attr:`RefineResult.occupancy`): the fraction of the
  sound a one-voxel layer of the field stops, a probability; the refined map calls a voxel
  occupied from :data:`OCCUPIED_LEVEL` (0.5) on. :func:`field_from_occupancy` and
  :func:`occupancy_from_field` convert (``kappa`` of the :class:`~gpumap.layers.render.PingModel`).

Hard constraints, exactly:

- **Never occupy a voxel that clear dark views carved** (:func:`carved_voxels`). Visible rule:
  a voxel whose clear dark evidence reaches the mapper's ``carve_views``
  (``evidence()["count"] >= carve_views``: the rule would carve it even had it been seen
  bright). Evidence rule: an observed voxel with at least one clear view (``count + hits > 0``)
  that the rule calls free (``not evidence_occupied(count, hits, bright_share, share_z)``, the
  mapper's settings): seen bright but shown at ``share_z`` to be bright in fewer than
  ``bright_share`` of its views, or never bright with clear dark views. An observed voxel with no
  clear view at all (only dark views behind a return: shadow) is not carved. A carved voxel has
  ``o = 0`` throughout (upper bound 0 in the projected Adam step), as has every voxel no ping
  observed (its occupancy is NaN). Only the other observed voxels ("movable") change.
- **Never free a voxel that a bright clear view needs.** For every training ping and every beam,
  the nearest range bin with intensity ``>= threshold`` (the mapper's; nothing at or above it
  lies nearer in that beam, so its echo comes from that bin's elevation arc) keeps an occupied
  voxel (occupancy ``>= OCCUPIED_LEVEL``) among the movable voxels whose bounding sphere (radius
  ``sqrt(3)/2`` voxel) reaches that bin and beam within ``|elevation| <= vfov/2 +`` the sphere's
  angular radius. After the optimisation, where none is left, the one with the highest occupancy
  (ties: the lowest flat index) is raised to ``OCCUPIED_LEVEL``; :attr:`RefineResult.raised` marks
  them. Bins with no movable voxel at all (everything there carved) are counted in
  ``stats["unexplained_cells"]``.

``confidence`` is ``|2 occupancy - 1| * (1 - exp(-views / 4))`` with ``views`` the training pings
whose field of view holds the voxel's centre (a voxel few pings saw is not trusted whatever its
value).

Modules (every public name of them is importable from here): this one (:func:`refine`,
:func:`refine_saved`, the pings they read, the device), :mod:`gpumap.layers.refine_fit`
(:class:`RefineOptions`, the Warp arrays and projected Adam step of the loss, the display law's
starting gain and floor), :mod:`gpumap.layers.refine_constraints` (the two hard constraints),
:mod:`gpumap.layers.refined_map` (:class:`RefineResult`, its file, field and occupancy) and
:mod:`gpumap.layers.refine_heldout` (held-out prediction: :func:`render_map`, :func:`heldout_scores`).
"""

from __future__ import annotations

import logging
import math
import os
import sys
import time
import types

import numpy as np

from gpumap.errors import BackendUnavailableError
from gpumap.layers.refine_constraints import REFINE_RULES, _views_and_raise, carved_voxels
from gpumap.layers.refine_fit import RefineOptions, _calibrate, _Fit
from gpumap.layers.refine_heldout import heldout_scores, render_map, roc_auc
from gpumap.layers.refined_map import (
    OCCUPIED_LEVEL,
    REFINED_FORMAT,
    SURFACE_FILE,
    RefineResult,
    field_from_occupancy,
    is_refined_file,
    layers_file,
    load_refined,
    occupancy_from_field,
)
from gpumap.layers.refined_map import REFINED_VERSION as REFINED_VERSION  # kept importable from here
from gpumap.layers.render import PingModel, PingRenderer
from gpumap.spec import SonarSpec

__all__ = [
    "RefineOptions",
    "RefineResult",
    "refine",
    "refine_saved",
    "carved_voxels",
    "pick_device",
    "recording_frames",
    "map_frames",
    "load_refined",
    "is_refined_file",
    "layers_file",
    "SURFACE_FILE",
    "field_from_occupancy",
    "occupancy_from_field",
    "render_map",
    "heldout_scores",
    "roc_auc",
    "OCCUPIED_LEVEL",
    "REFINED_FORMAT",
]

log = logging.getLogger(__name__)


# ---------------------------------------------------------------------- checks
def _check_images_poses(
    spec: SonarSpec, images: np.ndarray, poses: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    a = np.asarray(images)
    if a.ndim != 3 or a.shape[1:] != spec.image_shape:
        raise ValueError(f"Expected images of shape (N, {spec.n_bins}, {spec.n_beams}), but got {a.shape}")
    if a.dtype != np.uint8:
        if a.dtype.kind != "f":
            raise TypeError(f"Expected uint8 or float images, but got dtype {a.dtype}")
        if not np.all(np.isfinite(a)) or a.min() < 0 or a.max() > 1:
            raise ValueError("Expected float images with finite values in [0, 1], but got values outside")
    P = PingRenderer._check_poses(poses)
    if len(P) != len(a):
        raise ValueError(f"Expected one pose per image ({len(a)}), but got {len(P)} poses")
    if len(a) == 0:
        raise ValueError("Expected at least one ping, but got none")
    return a, P


def pick_device(device: str = "auto") -> tuple[str, str]:
    """``(device, why)``: the Warp device refinement runs on, and why, logged at INFO.

    ``"auto"`` takes ``cuda:0`` when Warp finds a CUDA device, else the CPU, and says so (on the
    CPU a fine grid takes long: minutes per 100 steps at 3 cm on two cores). A named device
    (``"cpu"``, ``"cuda"``, ``"cuda:N"``) is used or raises
    :class:`~gpumap.errors.BackendUnavailableError` (no CUDA device, or no device N); it never falls
    back. Anything else raises ``ValueError``.
    """
    if not isinstance(device, str) or not (
        device in ("auto", "cpu", "cuda") or (device.startswith("cuda:") and device[5:].isdigit())
    ):
        raise ValueError(f"Expected device 'auto', 'cpu', 'cuda' or 'cuda:N', but got {device!r}")
    from gpumap.backends import _warp

    wp, _ = _warp()
    n_cuda = wp.get_cuda_device_count() if wp.is_cuda_available() else 0
    if device == "auto":
        if n_cuda:
            dev, why = "cuda:0", f"auto: Warp finds {n_cuda} CUDA device(s); took cuda:0"
        else:
            dev, why = "cpu", ("auto: Warp finds no CUDA device, so the CPU (slow on fine grids: "
                               "pass --device cuda on a machine with one)")
    elif device == "cpu":
        dev, why = "cpu", "named"
    else:
        k = 0 if device == "cuda" else int(device[5:])
        if k >= n_cuda:
            raise BackendUnavailableError(
                f"Expected a CUDA device for device={device!r}, but Warp finds "
                + (f"{n_cuda} (cuda:0..cuda:{n_cuda - 1})" if n_cuda else "none")
            )
        dev, why = f"cuda:{k}", "named"
    # auto says what it took at INFO; a named device is what the caller asked for
    log.log(logging.INFO if device == "auto" else logging.DEBUG, "gpumap refine: device %s (%s)", dev, why)
    return dev, why


def _map_of(mapper):
    """A :class:`gpumap.MinMaxMapper` from ``mapper`` (itself, or a map file's path, loaded)."""
    from gpumap.core.mapper import MinMaxMapper

    if isinstance(mapper, (str, os.PathLike)):
        from gpumap.core.merge import load_map

        return load_map(mapper, backend="numpy")
    if not isinstance(mapper, MinMaxMapper):
        raise TypeError(f"Expected a gpumap.MinMaxMapper or a map file's path for 'mapper', but got "
                        f"{type(mapper).__name__}")
    return mapper


def refine(
    mapper,
    images: np.ndarray,
    poses: np.ndarray,
    *,
    options: RefineOptions | None = None,
    model: PingModel | None = None,
    device: str = "auto",
    progress: bool = False,
) -> RefineResult:
    """Refine the map of ``mapper`` against the pings it was built from.

    Parameters
    ----------
    mapper : gpumap.MinMaxMapper or path-like
        A map of rule ``"evidence"`` (the default) or ``"visible"``, live or a saved map file
        (:meth:`~gpumap.MinMaxMapper.save`; see also :func:`refine_saved`). Its ``values()``,
        ``evidence()``, ``threshold``, ``carve_views``, ``bright_share`` and ``share_z`` are read;
        the mapper is not changed.
    images : (N, n_bins, n_beams) uint8 or float32 in [0, 1]
        The training pings (the ones the map holds).
    poses : (N, 4, 4) float64
        Their ``T_W_S``.
    options : RefineOptions, optional
    model : PingModel, optional
    device : str
        ``"auto"``, ``"cpu"``, ``"cuda"`` or ``"cuda:N"`` (Warp): see :func:`pick_device`; the
        choice and why are logged and kept in ``stats["device"]``, ``stats["device_reason"]``.
    progress : bool
        A tqdm bar over the steps.
    """
    mapper = _map_of(mapper)
    if mapper.rule not in REFINE_RULES:
        raise ValueError(f"Expected a mapper with rule='evidence' or rule='visible' (rules that keep "
                         f"evidence), but its rule is {mapper.rule!r}")
    opts = options or RefineOptions()
    if not isinstance(opts, RefineOptions):
        raise TypeError(f"Expected RefineOptions for 'options', but got {type(opts).__name__}")
    spec, grid = mapper.spec, mapper.grid
    images, P = _check_images_poses(spec, images, poses)
    dev, why = pick_device(device)
    t0 = time.perf_counter()
    values = mapper.values()
    ev = mapper.evidence()
    thr = float(mapper.threshold)
    observed = np.isfinite(values)
    carved = carved_voxels(mapper.rule, ev, carve_views=mapper.carve_views,
                           bright_share=mapper.bright_share, share_z=mapper.share_z)
    movable = observed & ~carved
    occ0 = np.where(movable & (np.nan_to_num(values, nan=-1.0) >= thr), opts.init_occupancy, 0.0).astype(
        np.float32
    )
    upper = movable.astype(np.float32)
    refl0 = np.full(grid.shape, 0.5, np.float32)

    r = PingRenderer(spec, grid, model, device=dev)
    measured = r.coarsen(images)
    log_gain, floor = _calibrate(r, occ0, refl0, measured, P, opts.huber_delta)
    fit = _Fit(r, occ0, upper, refl0, measured, log_gain, floor)
    fit.poses = P

    rng = np.random.default_rng(opts.seed)
    order = np.empty(0, np.int64)
    history = []
    from tqdm import tqdm

    lrs = {"occ": opts.learning_rate, "refl": opts.learning_rate, "glob": 0.02}
    for _ in tqdm(range(opts.iterations), desc=f"refine ({dev})", unit="step", disable=not progress):
        if len(order) < min(opts.pings_per_step, len(P)):
            order = np.concatenate([order, rng.permutation(len(P))])
        idx, order = order[: opts.pings_per_step], order[opts.pings_per_step :]
        history.append(fit.step_loss(np.sort(idx), opts, lrs))
    occ = fit.occ.numpy().astype(np.float32)
    refl = fit.refl.numpy().astype(np.float32)
    log_gain, floor = (float(x) for x in fit.glob.numpy())
    occ[~movable] = 0.0
    # occupancy = the stop probability of a one-voxel layer of the fitted field
    occ = occupancy_from_field(occ, r.model.kappa)
    views, raised, unexplained = _views_and_raise(spec, grid, occ, movable, images, P, thr)
    conf = (np.abs(2.0 * occ - 1.0) * (1.0 - np.exp(-views / 4.0))).astype(np.float32)
    occ_out = np.where(observed, occ, np.nan).astype(np.float32)
    conf = np.where(observed, conf, np.nan).astype(np.float32)
    # the field after the raise: the one whose occupancy is occ_out
    fld = np.where(observed, np.minimum(field_from_occupancy(occ, r.model.kappa), 1.0), np.nan)
    stats = {
        "seconds": time.perf_counter() - t0,
        "device": r.device,
        "device_reason": why,
        "rule": mapper.rule,
        "threshold": thr,
        "frames": len(P),
        "unexplained_cells": unexplained,
        "raised_voxels": int(raised.sum()),
        "carved_voxels": int(carved.sum()),
        "movable_voxels": int(movable.sum()),
        "options": opts.to_dict(),
        "model": r.model.to_dict(),
        "render_cells": list(r.image_shape),
        "elevation_rays": r.n_elevations,
    }
    return RefineResult(occ_out, conf, refl, carved, raised, math.exp(log_gain), floor, history, stats,
                        field=fld.astype(np.float32), threshold=thr, rule=mapper.rule, map_values=values,
                        spec=spec, grid=grid)


def recording_frames(
    path: str | os.PathLike, stride: int = 1, max_frames: int | None = None, progress: bool = False
) -> tuple[SonarSpec, np.ndarray, np.ndarray]:
    """(spec, images (N, n_bins, n_beams), poses (N, 4, 4) float64) of a recording's posed frames
    (every ``stride``-th, at most ``max_frames``; frames of another sonar geometry are skipped).

    The images keep the recording's dtype (uint8 or float32, as the mapper took them, so that
    their fingerprints match a map built from them; float32 if the dtypes are mixed).
    """
    from tqdm import tqdm

    from gpumap.io import open_recording

    rec = open_recording(str(path))
    spec, images, poses = None, [], []
    for i, fr in enumerate(tqdm(rec, desc="read", unit="frame", disable=not progress)):
        if i % stride or fr.T_W_S is None:
            continue
        spec = spec or fr.spec
        if fr.spec != spec:
            continue
        img = np.array(fr.image)  # a copy: a reader may reuse its buffer
        images.append(img if img.dtype == np.uint8 else img.astype(np.float32))
        poses.append(np.asarray(fr.T_W_S, np.float64))
        if max_frames is not None and len(images) >= max_frames:
            break
    if not images:
        raise ValueError(f"Expected a recording with sonar poses (refine needs one per ping), but {path} "
                         "has no posed frames")
    if len({a.dtype for a in images}) > 1:
        images = [a.astype(np.float32) / 255 if a.dtype == np.uint8 else a for a in images]
    return spec, np.stack(images), np.stack(poses)


#: Pings per integrate_batch call in :func:`map_frames` (the progress bar's step; the map is the same).
MAP_CHUNK = 16


def map_frames(mapper, images: np.ndarray, poses: np.ndarray, progress: bool = False) -> None:
    """Integrate ``images`` at ``poses`` into ``mapper``, :data:`MAP_CHUNK` at a time, with a
    progress bar (the same map as one call: every update is a min or a count)."""
    from tqdm import tqdm

    from gpumap.core.feed import feed

    pings = zip(images, poses, strict=True)
    feed(
        mapper, tqdm(pings, total=len(images), desc="map", unit="ping", disable=not progress), batch=MAP_CHUNK
    )


def refine_saved(
    map_path: str | os.PathLike,
    recording,
    *,
    stride: int = 1,
    max_frames: int | None = None,
    options: RefineOptions | None = None,
    model: PingModel | None = None,
    device: str = "auto",
    progress: bool = False,
) -> RefineResult:
    """Refine a saved map (:meth:`gpumap.MinMaxMapper.save`, ``gpumap replay``'s ``map.npz``)
    against its recording: its grid, rule, threshold and evidence come from the file.

    Parameters
    ----------
    map_path : path-like
        The map file (rule ``"evidence"`` or ``"visible"``).
    recording : path-like or (images, poses)
        A recording with poses (:func:`gpumap.io.open_recording`: read with ``stride`` and
        ``max_frames``), or the pings themselves, ``(N, n_bins, n_beams)`` and ``(N, 4, 4)``.
    stride, max_frames : int
        Which frames of a recording path (as ``gpumap replay`` read them for the map).
    options, model, device, progress
        As :func:`refine`.

    Raises
    ------
    ValueError
        A recording of another sonar geometry than the map's; pings of which none is one the map
        holds (the map keeps a fingerprint of each, :mod:`gpumap.pings`): the wrong recording.
        ``stats["pings_in_map"]`` counts the pings the map holds (None for a map file without
        fingerprints).
    """
    from gpumap.pings import ping_print

    mapper = _map_of(map_path)
    if isinstance(recording, (str, os.PathLike)):
        spec, images, poses = recording_frames(recording, stride, max_frames, progress)
        if spec != mapper.spec:
            raise ValueError(f"Expected a recording of the map's sonar ({mapper.spec.n_bins} bins x "
                             f"{mapper.spec.n_beams} beams, ...), but {recording} is of another geometry")
    else:
        try:
            images, poses = recording
        except (TypeError, ValueError):
            raise TypeError("Expected a recording path or a pair (images, poses) for 'recording', but got "
                            f"{type(recording).__name__}") from None
    images, poses = _check_images_poses(mapper.spec, images, poses)
    known = mapper.pings.array()
    held = None
    if len(known):
        prints = np.array(
            [ping_print(im if im.dtype == np.uint8 else np.ascontiguousarray(im, np.float32), T)
             for im, T in zip(images, poses, strict=True)], np.uint64)
        held = int(np.isin(prints, known).sum())
        if held == 0:
            raise ValueError(f"Expected the pings {map_path} was built from, but none of the {len(images)} "
                             "given is one it holds (another recording, stride or frame range?)")
        if held < len(images):
            log.warning("gpumap refine: %d of the %d pings are not in %s (the map did not see them)",
                        len(images) - held, len(images), map_path)
    res = refine(mapper, images, poses, options=options, model=model, device=device, progress=progress)
    res.stats["pings_in_map"] = held
    res.stats["map_path"] = str(map_path)
    return res


class _CallableModule(types.ModuleType):
    """``gpumap.layers.refine`` is this module and the function: ``gpumap.refine(mapper, images, poses)``
    calls :func:`refine` whether or not ``gpumap.layers.refine`` (the module) was imported by name."""

    def __call__(self, *args, **kwargs) -> RefineResult:
        return refine(*args, **kwargs)


sys.modules[__name__].__class__ = _CallableModule
