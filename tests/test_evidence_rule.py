"""The evidence rule (the default): view counts on every backend, its decision, saturation, merges.

References share no code with the kernels or the rule's decision: the counts come from the
view-by-view fold of test_visibility (single-ping plain maps and a running max for the clear
test), the decision from the binomial score test written out by hand.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from test_mapper import GRID, SPEC, T_A, centres_S
from test_visibility import THR, _fold_views, _random_pings
from test_visibility import _run as _run_rule

import gpumap
from gpumap.core.merge import MapState, map_state
from gpumap.core.params import MapperParams
from gpumap.reference import evidence_occupied, pack_counts, split_counts

TOP = 2**32 - 1  # where each of the two counts stops


def _run(backend, pings, rule="evidence"):
    """test_visibility's mapper of the pings (threshold THR), under this file's rule by default."""
    return _run_rule(backend, pings, rule)


@pytest.fixture(scope="module")
def folded():
    pings = _random_pings(8, 3)
    return pings, _fold_views(pings)[0]


def test_counts_match_their_definition_view_by_view(backend, folded):
    """Every backend's bright and clear-dark view counts equal the views folded one by one."""
    pings, want = folded
    ev = _run(backend, pings).evidence()
    np.testing.assert_array_equal(ev["min_all"], want["min_all"])
    np.testing.assert_array_equal(ev["bright"], want["bright"])
    np.testing.assert_array_equal(ev["count"], want["dark_views"])
    np.testing.assert_array_equal(ev["hits"], want["bright_views"])
    assert want["dark_views"].max() >= 4 and want["bright_views"].max() >= 3  # the test can tell


def test_backends_agree_bitwise_with_the_reference(other_backend, folded):
    pings = folded[0]
    ref, got = _run("numpy", pings), _run(other_backend, pings)
    for k, a in ref.evidence().items():
        np.testing.assert_array_equal(got.evidence()[k], a, err_msg=k)
    np.testing.assert_array_equal(got.raw_values(), ref.raw_values())


def test_values_follow_the_decision(backend, folded):
    """Occupied (value >= threshold) exactly where the decision holds; unknown where unobserved.
    (Read-time knobs set so that 8 pings free voxels seen bright: share_z 0, bright_share 0.9.)"""
    m = _run(backend, folded[0])
    m.share_z, m.bright_share = 0.0, 0.9
    ev, v = m.evidence(), m.values()
    occ = evidence_occupied(ev["count"], ev["hits"], m.bright_share, m.share_z)
    np.testing.assert_array_equal(np.isfinite(v) & (v >= THR), occ)
    np.testing.assert_array_equal(np.isnan(v), ~np.isfinite(ev["min_all"]))
    assert occ.sum() > 100 and ((ev["hits"] > 0) & ~occ).sum() > 20  # both sides of the decision


def _wilson_upper(k: int, n: int, z: float) -> float:
    """The Wilson score interval's upper end for k successes in n trials (the textbook form)."""
    s = k / n
    return (s + z * z / (2 * n) + z * math.sqrt(s * (1 - s) / n + z * z / (4 * n * n))) / (1 + z * z / n)


@pytest.mark.parametrize(("p", "z"), [(0.5, 1.645), (0.2, 1.0), (0.8, 2.33), (0.5, 0.0)])
def test_decision_is_the_wilson_bound_at_every_count(p, z):
    """Occupied exactly where some view was bright and the Wilson upper bound of the bright share
    reaches bright_share (ties, within 1e-9, left out: float rounding may go either way)."""
    k, n = np.meshgrid(np.arange(0, 120), np.arange(1, 120), indexing="ij")
    ok = k <= n
    k, n = k[ok], n[ok]
    got = evidence_occupied(n - k, k, p, z)
    upper = np.array([_wilson_upper(int(a), int(b), z) for a, b in zip(k, n, strict=True)])
    sure = np.abs(upper - p) > 1e-9
    np.testing.assert_array_equal(got[sure], ((k > 0) & (upper >= p))[sure])
    assert (~sure).sum() < 100 and got.any() and (~got[k > 0]).any()
    assert not evidence_occupied(np.array([5]), np.array([0]), p, z).any()  # never bright: free


def test_the_same_share_over_more_views_decides_more():
    """At a share of 0.3 bright views (below bright_share 0.5, set here), 3 of 10 are not enough to free a
    voxel at 95 %, 30 of 100 are; a share of 0.7 stays occupied however many views come."""
    dark, hits = np.array([7, 70, 3, 30, 300, 3000]), np.array([3, 30, 7, 70, 700, 7000])
    occ = evidence_occupied(dark, hits, 0.5, 1.645)
    np.testing.assert_array_equal(occ, [True, False, True, True, True, True])


def test_the_readme_says_how_many_clear_dark_views_free_a_voxel_seen_bright_once():
    """The guide's figure (docs/guide.md), from the decision at the default settings: the first count of clear
    dark views at which one bright view no longer keeps a voxel."""
    from pathlib import Path

    from gpumap.geometry import BRIGHT_SHARE, SHARE_Z

    n = next(d for d in range(1, 1000)
             if not evidence_occupied(np.array([d]), np.array([1]), BRIGHT_SHARE, SHARE_Z)[0])
    readme = " ".join((Path(__file__).resolve().parents[1] / "docs" / "guide.md").read_text().split())
    assert f"a voxel seen bright once needs {n} clear dark views" in readme, n


def _band_pings(shares: dict[float, float], n: int):
    """``n`` pings from one pose of bands at the given ranges (m) that are bright (0.7) in a
    share of the pings, spread evenly (ping k is bright when floor((k + 1) share) passes an
    integer), and speckle-dark (0.08, below the threshold, above its half) in the rest; nothing in
    front of the nearest. Returns the pings and each band's voxels."""
    r = np.linalg.norm(centres_S(T_A), axis=1)
    pings, bands = [], {}
    rows = {}
    for rng_m in shares:
        b = SPEC.bin_index(np.array([rng_m - 0.03, rng_m + 0.03]))
        rows[rng_m] = slice(int(b[0]), int(b[1]) + 1)
        bands[rng_m] = (r > rng_m - 0.02) & (r < rng_m + 0.02)
    for k in range(n):
        img = np.zeros(SPEC.image_shape, np.float32)
        for rng_m, share in shares.items():
            img[rows[rng_m]] = 0.7 if math.floor((k + 1) * share) > math.floor(k * share) else 0.08
        pings.append((img, T_A))
    return pings, bands


def test_a_surface_bright_in_most_views_stays_while_a_rarely_bright_one_goes(backend):
    """Two bands seen over and over from one pose: one bright in 10 % of the pings (the elevation
    stretch of something else), in front of one bright in 70 % (a surface with speckle). After 12
    pings the evidence rule keeps both (too few views to free either at 95 %); after 240 it keeps
    the surface and frees the stretch (a share of 0.1, below bright_share 0.2). The visible rule
    loses the surface as the pings add up."""
    shares = {0.8: 0.7, 0.55: 0.1}
    for n, keep_rare in ((12, True), (240, False)):
        pings, bands = _band_pings(shares, n)
        m = _run(backend, pings)
        v = m.values().ravel()
        surface, rare = (bands[r] & np.isfinite(v) for r in shares)
        assert surface.sum() > 20 and rare.sum() > 20
        assert np.all(v[surface] >= THR), f"the surface went after {n} pings"
        assert np.all((v[rare] >= THR) == keep_rare), f"the rarely bright band after {n} pings"
    vis = _run(backend, pings, "visible").values().ravel()
    assert np.all(vis[surface] < THR)  # what the default rule must not do: the test can fail


def _preloaded(backend, dark: int, hits: int,
               brightness: float = 0.7) -> tuple[gpumap.MinMaxMapper, np.ndarray]:
    """A map whose observed voxels hold ``dark`` clear dark and ``hits`` bright views (a state
    merged into a fresh map), and the mask of those voxels. Its one ping is a bright range bin of
    ``brightness`` (maps holding the very same ping do not merge)."""
    img = np.zeros(SPEC.image_shape, np.float32)
    img[SPEC.bin_index(np.array([0.8]))[0]] = brightness
    seed = _run("numpy", [(img, T_A)])
    st = map_state(seed)
    counts = np.where(np.isfinite(st.arrays["min_all"]), pack_counts(dark, hits), np.uint64(0))
    m = gpumap.MinMaxMapper(SPEC, GRID, backend, MapperParams(threshold=THR))
    m.merge(MapState(st.kind, st.options, 1, {**st.arrays, "count": counts.astype(np.uint64)}))
    return m, np.isfinite(seed.raw_values())


def test_counts_saturate_at_2_to_the_32_minus_1_and_never_wrap(backend):
    """Voxels 2 views short of the limit on both counts, then 3 bright and 3 clear dark pings of
    them: each count stops at 2^32 - 1 (a vehicle in view of one voxel at 20 Hz for 6.8 years);
    neither wraps nor carries into the other, and the decision stands at the share it had."""
    m, seen = _preloaded(backend, TOP - 2, TOP - 2)
    img = np.zeros(SPEC.image_shape, np.float32)
    img[SPEC.bin_index(np.array([0.8]))[0]] = 0.7
    dark = np.zeros(SPEC.image_shape, np.float32)
    for ping in [img] * 3 + [dark] * 3:
        m.integrate(ping, T_A)
    ev = m.evidence()
    r = np.linalg.norm(centres_S(T_A), axis=1).reshape(GRID.shape)
    band = seen & (np.abs(r - 0.8) < 0.02)  # bright in the 3 bright pings, dark in the others
    before = np.isfinite(ev["min_all"]) & (r < 0.6)  # only clear dark views
    assert band.sum() > 20 and (before & seen).sum() > 20
    assert np.all(ev["hits"][band] == TOP) and np.all(ev["count"][band] == TOP)
    assert np.all(ev["count"][before & seen] == TOP) and np.all(ev["hits"][before & seen] == TOP - 2)
    v = m.values()
    assert np.all(v[band] >= THR)  # a share of one half, at 2^32 views: not below bright_share


def test_merged_counts_saturate_too():
    """Merging two maps near the limit stops each count at 2^32 - 1, as one mapper would."""
    a, seen = _preloaded("numpy", TOP - 5, 3)
    b, _ = _preloaded("numpy", 10, TOP - 1, brightness=0.6)
    a.merge(b)
    ev = a.evidence()
    assert np.all(ev["count"][seen] == TOP) and np.all(ev["hits"][seen] == TOP)
    c = split_counts(pack_counts(np.array([TOP]), np.array([TOP])))
    assert c[0][0] == TOP and c[1][0] == TOP


def test_disjoint_pings_merge_bit_for_bit_in_any_order(folded):
    pings = folded[0]
    ref = _run("numpy", pings)
    parts = [_run("numpy", pings[i::3]) for i in range(3)]
    for order in ((0, 1, 2), (2, 0, 1)):
        m = gpumap.MinMaxMapper(SPEC, GRID, "numpy", MapperParams(threshold=THR))
        for i in order:
            m.merge(map_state(parts[i]))
        for k, a in ref.evidence().items():
            np.testing.assert_array_equal(m.evidence()[k], a, err_msg=k)
        np.testing.assert_array_equal(m.raw_values(), ref.raw_values())


def test_options_are_checked_and_kept(tmp_path):
    for bad in (0.0, 1.5, math.nan, "half"):
        with pytest.raises((ValueError, TypeError), match="bright_share"):
            gpumap.MinMaxMapper(SPEC, GRID, "numpy", MapperParams(bright_share=bad))
    for bad in (-1.0, 11.0, math.inf):
        with pytest.raises(ValueError, match="share_z"):
            gpumap.MinMaxMapper(SPEC, GRID, "numpy", MapperParams(share_z=bad))
    m = gpumap.MinMaxMapper(SPEC, GRID, "numpy", MapperParams(bright_share=0.3, share_z=2.0))
    assert m.rule == "evidence"
    back = gpumap.MinMaxMapper.load(m.save(tmp_path / "m.npz"), backend="numpy")
    assert (back.bright_share, back.share_z) == (0.3, 2.0)
    other = gpumap.MinMaxMapper(SPEC, GRID, "numpy", MapperParams(bright_share=0.4))
    with pytest.raises(ValueError, match="bright_share"):
        m.merge(other)
