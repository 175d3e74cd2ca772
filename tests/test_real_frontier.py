"""bench.real_frontier's pieces that need neither the real run nor the public code: the resampling of
another grid onto ours (against brute force), the public code's frame skip, and the row options."""

from __future__ import annotations

import numpy as np
import pytest

import gpumap
from bench.oasis_public import fed_frames
from bench.real_frontier import Row, parse_row, resample_to_grid, split_options


def _brute(occ, obs, origin, vs, grid):
    """For each destination voxel, search every source voxel for the one whose box holds its centre."""
    out = np.full(grid.shape, np.nan, np.float32)
    lo, s = np.asarray(grid.min_corner_m), grid.voxel_size_m
    src = np.argwhere(np.ones(occ.shape, bool))
    src_lo = np.asarray(origin) + src * vs
    for d in np.ndindex(*grid.shape):
        c = lo + (np.asarray(d) + 0.5) * s
        inside = np.all((src_lo <= c) & (c < src_lo + vs), axis=1)
        hit = src[inside]
        assert len(hit) <= 1  # boxes tile space: at most one holds a point
        if len(hit):
            i = tuple(hit[0])
            out[d] = 1.0 if occ[i] else 0.0 if obs[i] else np.nan
    return out


@pytest.mark.parametrize(("origin", "vs", "shape", "lo", "dst_vs", "dst_hi"), [
    # OASIS's case: the same origin, 5.025 cm onto 5 cm
    ((0.0, 0.0, 0.0), 0.05025, (9, 7, 5), (0.0, 0.0, 0.0), 0.05, (0.42, 0.31, 0.2)),
    # shifted, partly outside the source
    ((-0.13, 0.02, -0.3), 0.07, (6, 5, 8), (-0.2, -0.05, -0.25), 0.045, (0.3, 0.33, 0.2)),
    ((0.0, 0.0, 0.0), 0.03, (10, 10, 10), (0.0, 0.0, 0.0), 0.06, (0.3, 0.3, 0.3)),  # coarser destination
])
def test_resample_matches_brute_force(origin, vs, shape, lo, dst_vs, dst_hi):
    rng = np.random.default_rng(7)
    obs = rng.random(shape) < 0.7
    occ = obs & (rng.random(shape) < 0.4)
    grid = gpumap.GridSpec(lo, dst_hi, dst_vs)
    got = resample_to_grid(occ, obs, origin, vs, grid)
    want = _brute(occ, obs, origin, vs, grid)
    assert got.shape == grid.shape and got.dtype == np.float32
    np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
    np.testing.assert_array_equal(got[~np.isnan(got)], want[~np.isnan(want)])
    assert (got == 1).any() and (got == 0).any()  # the cases exercise every state


def test_resample_identity_on_the_same_grid():
    rng = np.random.default_rng(1)
    obs = rng.random((4, 5, 6)) < 0.5
    occ = obs & (rng.random((4, 5, 6)) < 0.5)
    grid = gpumap.GridSpec((1.0, 2.0, 3.0), (1.4, 2.5, 3.6), 0.1)
    got = resample_to_grid(occ, obs, (1.0, 2.0, 3.0), 0.1, grid)
    np.testing.assert_array_equal(got == 1, occ)
    np.testing.assert_array_equal(np.isnan(got), ~obs)


def test_resample_refuses_bad_input():
    grid = gpumap.GridSpec((0, 0, 0), (1, 1, 1), 0.5)
    obs = np.zeros((2, 2, 2), bool)
    with pytest.raises(ValueError, match="observed"):
        resample_to_grid(~obs, obs, (0, 0, 0), 0.5, grid)
    with pytest.raises(ValueError, match="shape"):
        resample_to_grid(obs, np.zeros((2, 2), bool), (0, 0, 0), 0.5, grid)


def test_fed_frames_skips_as_reconstruct_py():
    x = np.array([0.0, 0.004, 0.008, 0.012, 0.05, 0.055, 0.0])  # metres along x
    poses = np.repeat(np.eye(4)[None], len(x), axis=0)
    poses[:, 0, 3] = x
    # the distance is to the last frame fed, not to the previous frame
    assert fed_frames(poses, 0.01) == [0, 3, 4, 6]
    assert fed_frames(poses, 0.0) == list(range(len(x)))


def test_rows_and_their_options():
    r = parse_row("evidence:bright_share=0.35,share_z=1")
    assert r == Row("evidence", {"bright_share": 0.35, "share_z": 1})
    assert r.name == "evidence (bright_share=0.35, share_z=1)"
    build, read = split_options({"bright_share": 0.5, "shadow_m": 0.05})
    assert build == {"shadow_m": 0.05} and read == {"bright_share": 0.5}
    with pytest.raises(ValueError, match="no_such_option"):
        split_options({"no_such_option": 1})
    with pytest.raises(ValueError, match="RULE:NAME=VALUE"):
        parse_row("evidence:bright_share")


def test_centres_in_box_matches_brute_force():
    from bench.real_frontier import centres_in_box

    grid = gpumap.GridSpec((-0.3, -0.2, -0.1), (0.4, 0.3, 0.35), 0.05)
    lo, hi = (-0.12, 0.0, 0.05), (0.21, 0.17, 0.5)
    got = centres_in_box(grid, lo, hi)
    want = np.zeros(grid.shape, bool)
    for idx in np.ndindex(*grid.shape):
        c = np.asarray(grid.min_corner_m) + (np.asarray(idx) + 0.5) * grid.voxel_size_m
        want[idx] = bool(np.all((c >= lo) & (c < hi)))
    np.testing.assert_array_equal(got, want)
    assert want.any() and not want.all()
