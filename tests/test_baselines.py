"""The benchmark's baselines do what they claim (bench/baselines.py). No timing here."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

import gpumap

# bench/ lives beside the package in the checkout, not in the wheel; until pyproject sets
# pytest's pythonpath = ["."], put the repository root on the path for it.
_ROOT = str(Path(__file__).resolve().parents[1])
if _ROOT not in sys.path:
    sys.path.insert(0, _ROOT)

from bench.baselines import (  # noqa: E402
    OasisRule,
    OctoMapBaseline,
    PaperSixSteps,
    oasis_occupied,
    paper_template_S,
    rect_max,
)
from gpumap.core.params import MapperParams  # noqa: E402


def _spec() -> gpumap.SonarSpec:
    return gpumap.SonarSpec.uniform(hfov_deg=130, vfov_deg=20, n_beams=128, n_bins=100,
                                    range_min_m=0.1, range_max_m=2.0)


def _grid(voxel: float = 0.05) -> gpumap.GridSpec:
    return gpumap.GridSpec((-0.5, -1.25, -0.4), (2.0, 1.25, 0.4), voxel)


def _pose(pitch_rad: float = 0.0, yaw_rad: float = 0.0, t=(0.0, 0.0, 0.0)) -> np.ndarray:
    cp, sp, cy, sy = math.cos(pitch_rad), math.sin(pitch_rad), math.cos(yaw_rad), math.sin(yaw_rad)
    T = np.eye(4)
    Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    T[:3, :3] = Rz @ np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    T[:3, 3] = t
    return T


def _fast_backend() -> str:
    return next((b for b in gpumap.available_backends() if b != "numpy"), "numpy")


# ------------------------------------------------------------------------------ OASIS
def test_oasis_rule_fnr_zero_is_every_view_must_hit():
    rng = np.random.default_rng(0)
    obs = rng.integers(0, 12, size=5000)
    hits = np.minimum(obs, rng.integers(0, 13, size=5000))
    strict = (obs > 0) & (hits == obs)
    assert np.array_equal(oasis_occupied(hits, obs, 0.0), strict)
    # the limit fnr -> 0+ reaches the same decision once fnr < 1 / max(observations)
    assert np.array_equal(oasis_occupied(hits, obs, 1e-6), strict)
    # fnr 0.5: more than half of the views hit
    assert np.array_equal(oasis_occupied(hits, obs, 0.5), 2 * hits > obs)
    with pytest.raises(ValueError):
        oasis_occupied(hits, obs, 1.0)


def test_oasis_rule_fnr_zero_equals_thresholded_min_max_map():
    spec, grid, thr = _spec(), _grid(0.05), 0.3
    rng = np.random.default_rng(1)
    images = [(rng.random(spec.image_shape, dtype=np.float32) ** 4) for _ in range(4)]
    poses = [_pose(math.radians(p), math.radians(y)) for p, y in ((15, 0), (25, 10), (10, -15), (30, 5))]
    rule = OasisRule(spec, grid, threshold=thr, fnr=0.0, backend="numpy")
    mm = gpumap.MinMaxMapper(spec, grid, "numpy", MapperParams(rule="plain"))
    for im, T in zip(images, poses, strict=True):
        rule.integrate(im, T)
        mm.integrate(im, T)
    v = mm.values()
    assert np.array_equal(rule.observations > 0, ~np.isnan(v))
    assert np.array_equal(rule.occupied(), np.nan_to_num(v, nan=-1) >= np.float32(thr))
    # a looser rule calls at least as much occupied
    assert np.all(rule.occupied(0.5) >= rule.occupied())


# ------------------------------------------------------------------------------ paper, plain NumPy
def test_paper_template_obeys_the_papers_constraints():
    spec = _spec()
    P = paper_template_S(spec, 0.05).astype(np.float64)
    assert len(P) > 1000
    assert np.all(np.linalg.norm(P, axis=1) < spec.range_max_m)
    assert np.all(np.abs(np.arctan(P[:, 1] / P[:, 0])) < spec.hfov_rad / 2)
    assert np.all(np.abs(np.arctan(P[:, 2] / P[:, 0])) < spec.vfov_rad / 2)
    np.testing.assert_allclose(P / 0.05, np.round(P / 0.05), atol=1e-4)  # on the voxel lattice


def test_rect_max_matches_brute_force():
    rng = np.random.default_rng(2)
    img = rng.random((60, 40), dtype=np.float32)
    b0 = rng.integers(0, 60, 500)
    b1 = np.minimum(59, b0 + rng.integers(0, 25, 500))
    j0 = rng.integers(0, 40, 500)
    j1 = np.minimum(39, j0 + rng.integers(0, 40, 500))
    want = np.array([img[a:b + 1, c:d + 1].max() for a, b, c, d in zip(b0, b1, j0, j1, strict=True)])
    np.testing.assert_array_equal(rect_max(img, b0, b1, j0, j1, budget=2000), want)


def test_paper_steps_agree_with_gpumap_template_on_a_range_ring():
    """A bright range ring: both give 1 or the background except near the ring's edges (sampling)."""
    spec, grid = _spec(), _grid(0.05)
    img = np.full(spec.image_shape, 0.1, np.float32)
    ring = (spec.bin_centers_m >= 1.0) & (spec.bin_centers_m < 1.2)
    img[ring] = 1.0
    T = _pose(math.radians(20), t=(0.0, 0.0, 0.2))
    paper = PaperSixSteps(spec, grid)
    paper.integrate(img, T)
    ours = gpumap.MinMaxMapper(spec, grid, "numpy", MapperParams(method="template"))
    ours.integrate(img, T)
    a, b = paper.values(), ours.values()
    both = ~np.isnan(a) & ~np.isnan(b)
    assert both.sum() > 0.8 * min((~np.isnan(a)).sum(), (~np.isnan(b)).sum())
    assert set(np.unique(a[both])) <= {np.float32(0.1), np.float32(1.0)}
    differ = both & (a != b)
    # where they differ the voxel straddles a ring edge: within a voxel's half diagonal plus a bin
    c = grid.centers(np.argwhere(differ))
    r = np.linalg.norm((c - T[:3, 3]) @ T[:3, :3], axis=1)
    edge = np.minimum(np.abs(r - 1.0), np.abs(r - 1.2))
    assert np.all(edge <= math.sqrt(3) / 2 * grid.voxel_size_m + 2 * spec.bin_size_m)
    assert differ.sum() < 0.1 * both.sum()
    # voxels well inside the ring are 1 in both
    ci = grid.centers(np.argwhere(both))
    ri = np.linalg.norm((ci - T[:3, 3]) @ T[:3, :3], axis=1)
    inside = (ri > 1.0 + grid.voxel_size_m) & (ri < 1.2 - grid.voxel_size_m)
    assert inside.any()
    assert np.all(a[both][inside] == 1.0) and np.all(b[both][inside] == 1.0)


def test_paper_steps_take_the_minimum_over_views():
    spec, grid = _spec(), _grid(0.05)
    T = _pose(math.radians(20))
    paper = PaperSixSteps(spec, grid)
    paper.integrate(np.full(spec.image_shape, 0.8, np.float32), T)
    paper.integrate(np.full(spec.image_shape, 51, np.uint8), T)  # 0.2 as uint8
    paper.integrate(np.full(spec.image_shape, 0.9, np.float32), T)
    v = paper.values()
    np.testing.assert_allclose(v[~np.isnan(v)], 0.2, atol=1e-6)


# ------------------------------------------------------------------------------ OctoMap
def test_octomap_marks_the_wall_hit_occupied_and_the_ray_free():
    pytest.importorskip("pyoctomap")
    spec, grid = _spec(), _grid(0.05)
    img = np.full(spec.image_shape, 0.02, np.float32)
    wall_bin = int((1.5 - spec.range_min_m) / spec.bin_size_m)
    img[wall_bin] = 0.9  # a wall 1.5 m ahead across every beam
    om = OctoMapBaseline(spec, grid, threshold=0.1)
    pts = om.beam_points_W(img, np.eye(4))
    assert pts.shape == (spec.n_beams, 3)
    np.testing.assert_allclose(np.linalg.norm(pts, axis=1), spec.bin_centers_m[wall_bin], atol=1e-9)
    np.testing.assert_allclose(pts[:, 2], 0.0, atol=1e-12)  # elevation 0
    for _ in range(3):
        om.integrate(img, np.eye(4))
    v = om.values()

    def at(p):
        return v[tuple(grid.index_of(np.array([p]))[0])]

    assert at((spec.bin_centers_m[wall_bin], 0.01, 0.01)) == 1.0  # the hit
    assert at((0.75, 0.01, 0.01)) == 0.0  # the ray through the water
    assert np.isnan(at((0.75, 0.01, 0.3)))  # off the elevation-0 plane: never touched
    # beams below the threshold add nothing
    om2 = OctoMapBaseline(spec, grid, threshold=0.95)
    om2.integrate(img, np.eye(4))
    assert np.all(np.isnan(om2.values()))


def test_oasis_rule_runs_on_a_compiled_backend_too():
    spec, grid = _spec(), _grid(0.1)
    rng = np.random.default_rng(3)
    img = rng.random(spec.image_shape, dtype=np.float32)
    a = OasisRule(spec, grid, threshold=0.5, backend="numpy")
    b = OasisRule(spec, grid, threshold=0.5, backend=_fast_backend())
    for r in (a, b):
        r.integrate(img, _pose(math.radians(20)))
    assert np.array_equal(a.observations, b.observations)
    assert np.array_equal(a.hits, b.hits)
