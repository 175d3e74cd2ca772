"""The generative surface fit (gpumap.layers.surface_fit) on analytic scenes.

The pings are made here by an independent brute-force renderer (points sampled on the true surface,
each adding ``area cos(incidence) / r^2`` times the beam pattern and the range loss to its sonar cell),
not by the fit's own voxel model; the candidates are the true voxels among phantoms stacked on their
elevation arcs, as the safe map keeps them.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from gpumap.layers.surface_fit import FitOptions, SurfaceFit, _transmittance, fit_candidates
from gpumap.spec import GridSpec, SonarSpec

SPEC = SonarSpec.uniform(hfov_deg=60, vfov_deg=20, n_beams=64, n_bins=120, range_min_m=0.2, range_max_m=2.0)
GRID = GridSpec((-0.1, -0.6, -0.7), (1.9, 0.6, 0.3), 0.04)
GAIN = 60.0
#: the fit told the surfaces' incidence law (k = 0: the renderer's); the other settings are the defaults
FIT = FitOptions(cos_exponent=0.0)


def _pose(xyz, pitch_down_deg: float) -> np.ndarray:
    """Sonar at ``xyz`` looking along +x, pitched down (sonar frame: x forward, y left, z up)."""
    a = math.radians(pitch_down_deg)
    T = np.eye(4)
    T[:3, :3] = np.array([[math.cos(a), 0.0, math.sin(a)], [0.0, 1.0, 0.0], [-math.sin(a), 0.0, math.cos(a)]])
    T[:3, 3] = xyz
    return T


def _render(points: np.ndarray, normals: np.ndarray, area: float, poses: np.ndarray, noise: float = 0.0,
            seed: int = 0, floor: float = 0.01) -> np.ndarray:
    """(n, n_bins, n_beams) float32 pings of surface samples (no occlusion: one convex surface)."""
    rng = np.random.default_rng(seed)
    out = []
    beam_w = np.diff(SPEC.beam_edges_rad)
    for T in poses:
        q = (points - T[:3, 3]) @ T[:3, :3]
        r = np.linalg.norm(q, axis=1)
        az = np.arctan2(q[:, 1], q[:, 0])
        el = np.arctan2(q[:, 2], np.hypot(q[:, 0], q[:, 1]))
        b, j = SPEC.bin_index(r), SPEC.beam_index(az)
        ok = (b >= 0) & (j >= 0) & (np.abs(el) <= 0.75 * SPEC.vfov_rad) & (q[:, 0] > 0)
        cos = np.abs(np.einsum("ij,ij->i", normals, (points - T[:3, 3]) / r[:, None]))
        # a sample's solid angle, area cos / r^2 (a surface of incidence exponent k = 0: FIT's law)
        e = area * cos / r**2 * 0.5 ** ((2 * el / SPEC.vfov_rad) ** 2) * r**-0.5 * 10 ** (-0.008 * (r - 1))
        E = np.zeros(SPEC.image_shape)
        np.add.at(E, (b[ok], j[ok]), e[ok] / beam_w[j[ok]])
        img = 1.0 - np.exp(-GAIN * E) + floor + noise * rng.random(E.shape)
        out.append(np.clip(img, 0, 1).astype(np.float32))
    return np.stack(out)


def _plate(z_m: float, step: float = 0.003) -> tuple[np.ndarray, np.ndarray, float]:
    xs, ys = np.arange(0.7, 1.5, step), np.arange(-0.3, 0.3, step)
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    p = np.stack([X.ravel(), Y.ravel(), np.full(X.size, z_m)], 1)
    return p, np.tile([0.0, 0.0, 1.0], (len(p), 1)), step * step


def _voxels_of(points: np.ndarray) -> np.ndarray:
    m = np.zeros(GRID.shape, bool)
    i = GRID.index_of(points)
    m[tuple(i.T)] = True
    return m


def _stack(mask: np.ndarray, below: int, above: int) -> np.ndarray:
    """The voxels of ``mask`` and those ``below`` / ``above`` them in z (phantom layers)."""
    out = mask.copy()
    for k in range(1, below + 1):
        out[:, :, :-k] |= mask[:, :, k:]
    for k in range(1, above + 1):
        out[:, :, k:] |= mask[:, :, :-k]
    return out


PLATE_Z = -0.42  # inside voxel layer 7 of the grid (-0.42 - -0.7) / 0.04 = 7.0 -> voxels 7


@pytest.fixture(scope="module")
def plate_fit() -> tuple[SurfaceFit, np.ndarray, int]:
    pts, nrm, area = _plate(PLATE_Z + 0.02)  # the middle of voxel layer 7
    true = _voxels_of(pts)
    k0 = int(np.argwhere(true)[:, 2][0])
    cand = _stack(true, 3, 3)
    poses = np.stack([_pose((0.0, 0.0, 0.1), 25.0), _pose((0.0, 0.0, -0.2), 12.0)])  # two elevations
    images = _render(pts, nrm, area, poses, noise=0.02)
    fit = fit_candidates(cand, np.ones(GRID.shape, bool), GRID, SPEC, images, poses, 0.1, FIT)
    return fit, true, k0


def test_a_flat_plate_seen_from_two_elevations_lies_at_its_height(plate_fit) -> None:
    fit, true, k0 = plate_fit
    assert fit.surface.sum() > 0.5 * true.sum()
    z = np.argwhere(fit.surface)[:, 2]
    assert np.bincount(z).argmax() == k0
    assert np.mean(np.abs(z - k0) <= 1) >= 0.9  # the phantom layers 2-3 voxels off are explained away
    # most of the plate is found, and the fit's weight sits on the plate's layer, not above or below
    assert (fit.surface & true).sum() >= 0.6 * true.sum()
    w = fit.weight.sum(axis=(0, 1))
    assert w.argmax() == k0 and w[k0] > 2 * max(w[k0 - 3], w[k0 + 3], w[k0 - 2], w[k0 + 2])


def test_weights_are_non_negative_and_only_candidates_are_claimed(plate_fit) -> None:
    fit, _, _ = plate_fit
    assert np.all(fit.weight >= 0) and np.all(np.isfinite(fit.weight))
    assert not np.any((fit.surface | fit.undecided) & ~fit.candidates)
    assert not np.any(fit.weight[~fit.candidates])
    assert not np.any(fit.surface & fit.undecided)
    sure = fit.sure[fit.candidates]
    assert np.all((sure >= 0) & (sure < 1)) and np.all(np.isnan(fit.sure[~fit.candidates]))
    assert np.array_equal(fit.surface, fit.candidates & (fit.sure >= 0.5) & (fit.pings >= 2))
    v = fit.values()
    assert np.all(v[fit.surface] == 1.0) and np.all(v[fit.undecided] == 0.5)


def test_the_decision_does_not_depend_on_the_display_gain() -> None:
    """Twice the gain doubles every energy (no noise, no saturation): twice the weights, and (the data's
    scale of a surface doubling too, up to the cells the threshold calls bright) the same surface."""
    pts, nrm, area = _plate(PLATE_Z + 0.02)
    cand = _stack(_voxels_of(pts), 2, 2)
    poses = np.stack([_pose((0.0, 0.0, 0.1), 25.0), _pose((0.0, 0.0, -0.2), 12.0)])
    one = _render(pts, nrm, area, poses, floor=0.0)
    two = _render(pts, nrm, 2.0 * area, poses, floor=0.0)
    a = fit_candidates(cand, cand, GRID, SPEC, one, poses, 0.05, FIT)
    b = fit_candidates(cand, cand, GRID, SPEC, two, poses, 0.05, FIT)
    assert a.surface.sum() > 100
    # (the normals come from the weights over x_ref, and x_ref from the cells the threshold calls bright)
    np.testing.assert_allclose(b.weight[a.candidates], 2 * a.weight[a.candidates], rtol=0.01,
                               atol=1e-4 * a.x_ref)
    assert b.x_ref == pytest.approx(2 * a.x_ref, rel=0.25)
    assert (a.surface & b.surface).sum() >= 0.9 * (a.surface | b.surface).sum()


def test_the_model_explains_two_views_of_the_plate_with_one_gain() -> None:
    """With the plate's own voxels as the only candidates, the two views (other heights, ranges,
    elevations and incidences) are explained with equal gains: the model's beam pattern, range loss,
    solid angle and incidence are the renderer's physics (a wrong one leaves a gain to take it up)."""
    pts, nrm, area = _plate(PLATE_Z + 0.02)
    true = _voxels_of(pts)
    poses = np.stack([_pose((0.0, 0.0, 0.1), 25.0), _pose((0.0, 0.0, -0.2), 12.0)])
    images = _render(pts, nrm, area, poses, floor=0.0)
    fit = fit_candidates(true, true, GRID, SPEC, images, poses, 0.05, FIT)
    assert fit.gains[1] / fit.gains[0] == pytest.approx(1.0, abs=0.05)
    assert fit.surface.sum() >= 0.9 * true.sum()


def test_a_ping_with_another_gain_gets_its_gain() -> None:
    """The second ping, from the first one's pose, has three times its echoes (a real sonar's gain varies
    ping to ping): the fitted gains say so, and the plate still lies at its height. (The third view's
    gain also takes up what the model leaves out there, the incidence: not asserted.)"""
    pts, nrm, area = _plate(PLATE_Z + 0.02)
    true = _voxels_of(pts)
    k0 = int(np.argwhere(true)[:, 2][0])
    cand = _stack(true, 3, 3)
    poses = np.stack([_pose((0.0, 0.0, 0.1), 25.0), _pose((0.0, 0.0, 0.1), 25.0),
                      _pose((0.0, 0.0, -0.2), 12.0)])
    images = np.concatenate([_render(pts, nrm, area, poses[:1], floor=0.0),
                             _render(pts, nrm, 3.0 * area, poses[1:2], floor=0.0),
                             _render(pts, nrm, area, poses[2:], floor=0.0)])
    fit = fit_candidates(cand, cand, GRID, SPEC, images, poses, 0.05, FIT)
    assert fit.gains[1] / fit.gains[0] == pytest.approx(3.0, rel=0.05)
    z = np.argwhere(fit.surface)[:, 2]
    assert np.mean(np.abs(z - k0) <= 1) >= 0.9


def test_a_one_voxel_target_among_its_arcs() -> None:
    """A small bright cube seen from three heights; the candidates are its voxel's whole column."""
    c = np.array([1.04, 0.02, -0.20])  # the centre of voxel (28, 15, 12)
    g = np.linspace(-0.015, 0.015, 6)
    faces = []
    for axis in range(3):  # a 3 cm cube's faces, sampled
        A, B = np.meshgrid(g, g, indexing="ij")
        for sgn in (-1, 1):
            p = np.zeros((A.size, 3))
            p[:, [a for a in range(3) if a != axis]] = np.stack([A.ravel(), B.ravel()], 1)
            p[:, axis] = sgn * 0.015
            n = np.zeros((A.size, 3))
            n[:, axis] = sgn
            faces.append((c + p, n))
    pts = np.concatenate([f[0] for f in faces])
    nrm = np.concatenate([f[1] for f in faces])
    area = (0.03 / 6) ** 2
    target = GRID.index_of(c)
    cand = np.zeros(GRID.shape, bool)
    cand[target[0], target[1], :] = True  # the column through the target: every height a candidate
    poses = np.stack([_pose((0.0, 0.0, z), p) for z, p in ((0.1, 18.0), (-0.1, 8.0), (-0.3, -2.0))])
    images = _render(pts, nrm, area * 40.0, poses)  # a strong reflector
    fit = fit_candidates(cand, np.ones(GRID.shape, bool), GRID, SPEC, images, poses, 0.1, FIT)
    col = fit.weight[target[0], target[1], :]
    assert col.argmax() == target[2]
    assert fit.surface[tuple(target)]
    assert fit.surface.sum() <= 3  # the target and at most its two neighbours in the column
    assert col[target[2]] > 5 * np.delete(col, [target[2] - 1, target[2], target[2] + 1]).max()


def test_occlusion_shadows_what_lies_behind() -> None:
    """Two candidates on one ray: the nearer, opaque, shadows the farther; not the other way round."""
    from gpumap.layers.surface_fit import _build

    T = _pose((0.0, 0.0, 0.0), 0.0)
    centres = np.array([[0.82, 0.02, 0.02], [1.42, 0.02, 0.02], [1.42, 0.42, 0.02]])
    images = np.zeros((1, *SPEC.image_shape), np.float32)
    pk = _build(centres, GRID, SPEC, images, T[None], 0.1, FitOptions())
    t = _transmittance(pk, np.array([1.0, 1.0, 1.0]), SPEC, 0.04, 0.08, 1.5)
    by = dict(zip(pk.pair_vox.tolist(), t.tolist(), strict=True))
    assert by[0] == pytest.approx(1.0) and by[2] == pytest.approx(1.0)  # nothing in front of them
    assert by[1] < 0.01  # behind the first one, on its ray
    half = _transmittance(pk, np.array([0.5, 1.0, 1.0]), SPEC, 0.04, 0.08, 1.5)
    assert dict(zip(pk.pair_vox.tolist(), half.tolist(), strict=True))[1] == pytest.approx(0.5)


def test_inputs_are_checked() -> None:
    cand = np.zeros(GRID.shape, bool)
    images = np.zeros((1, *SPEC.image_shape), np.float32)
    poses = np.eye(4)[None]
    with pytest.raises(ValueError, match="candidates of shape"):
        fit_candidates(cand[:-1], cand, GRID, SPEC, images, poses, 0.1)
    with pytest.raises(ValueError, match="within the observed"):
        fit_candidates(~cand, cand, GRID, SPEC, images, poses, 0.1)
    with pytest.raises(ValueError, match="images of shape"):
        fit_candidates(cand, cand, GRID, SPEC, images[:, :-1], poses, 0.1)
    with pytest.raises(ValueError, match="poses of shape"):
        fit_candidates(cand, cand, GRID, SPEC, images, np.eye(4)[None].repeat(2, 0), 0.1)
    with pytest.raises(ValueError, match="threshold"):
        fit_candidates(cand, cand, GRID, SPEC, images, poses, 0.0)
    with pytest.raises(TypeError, match="GridSpec"):
        fit_candidates(cand, cand, "grid", SPEC, images, poses, 0.1)
    with pytest.raises(TypeError, match="dtype"):
        fit_candidates(cand, cand, GRID, SPEC, images.astype(np.int16), poses, 0.1)
    for bad in ({"iterations": -1}, {"aperture_scale": 0.5}, {"undecided_level": 0.5},
                {"occlusion_m": 0.0}, {"min_pings": 0}):
        with pytest.raises(ValueError):
            FitOptions(**bad)
    empty = fit_candidates(cand, cand, GRID, SPEC, images, poses, 0.1)
    assert not empty.surface.any() and not empty.undecided.any()
