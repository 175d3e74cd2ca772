"""The confidence layer and the view gain (issue 20): analytic scenes, the NumPy reference on
every backend, the candidate generator's bounds, persistence and bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest

import gpumap
from gpumap.core.params import MapperParams
from gpumap.layers.confidence import ConfidenceLayer, with_confidence
from gpumap.layers.viewgain import (
    PAIR_STEPS,
    _fov,
    candidate_poses,
    gain_points,
    next_best_views,
    poses_to_rows,
    view_gain_reference,
)

SPEC = gpumap.SonarSpec.uniform(hfov_deg=60, vfov_deg=20, n_beams=64, n_bins=100, range_min_m=0.1,
                                range_max_m=1.5)
GRID = gpumap.GridSpec((-0.5, -0.5, -0.5), (0.5, 0.5, 0.5), 0.05)
TARGET = np.array([0.025, 0.025, 0.025])  # a voxel centre


def _rx(a: float) -> np.ndarray:
    T = np.eye(4)
    c, s = math.cos(a), math.sin(a)
    T[1:3, 1:3] = [[c, -s], [s, c]]
    return T


def _look_at_target(roll_rad: float = 0.0) -> np.ndarray:
    """Sonar 0.8 m before the target on -x, level, boresight +x through it, rolled about it."""
    T = np.eye(4)
    T[:3, 3] = TARGET - [0.8, 0.0, 0.0]
    return T @ _rx(roll_rad)


def _echo_image(T_W_S: np.ndarray) -> np.ndarray:
    """A dark image with one bright cell: the target's (range bin, beam) in this view."""
    p = np.linalg.inv(T_W_S) @ np.append(TARGET, 1.0)
    r = np.linalg.norm(p[:3])
    img = np.zeros(SPEC.image_shape, np.float32)
    img[SPEC.bin_index(r), SPEC.beam_index(math.atan2(p[1], p[0]))] = 0.9
    return img


def _target_index() -> tuple[int, int, int]:
    return tuple(int(i) for i in np.floor((TARGET - GRID.min_corner_m) / GRID.voxel_size_m))


def test_one_view_confirms_nothing_a_rolled_view_confirms_the_echo(backend):
    """A point reflector seen level: its echo could come from any voxel of the elevation arc, so
    nothing is confirmed (the whole arc is the stretch). Rolled 90 deg, the arc lies sideways,
    across the voxels the first view carved: the target alone stays occupied and is confirmed.
    The visible rule: one clear dark view carves (the evidence rule needs several)."""
    m = with_confidence(gpumap.MinMaxMapper(SPEC, GRID, backend, MapperParams(rule="visible")))
    T1 = _look_at_target()
    m.integrate(_echo_image(T1), T1)
    c1 = m.layer("confidence").states()
    assert (c1 == 2).sum() >= 5  # the arc: several voxels stacked in elevation, all occupied
    assert not (c1 == 3).any()
    T2 = _look_at_target(math.pi / 2)
    m.integrate(_echo_image(T2), T2)
    c2 = m.layer("confidence").states()
    i0 = np.array(_target_index())
    assert c2[tuple(i0)] == 3
    occ = np.argwhere(c2 >= 2)
    assert np.abs(occ - i0).max() <= 1  # the stretch is gone: only the target and its footprint's
    # confidence only labels: the values are those of a mapper without the layer
    plain = gpumap.MinMaxMapper(SPEC, GRID, backend, MapperParams(rule="visible"))
    plain.integrate(_echo_image(T1), T1)
    plain.integrate(_echo_image(T2), T2)
    np.testing.assert_array_equal(plain.raw_values(), m.raw_values())


def test_confirmed_flag_never_frees_and_batch_equals_sequence(backend):
    T1, T2 = _look_at_target(), _look_at_target(math.pi / 2)
    imgs = np.stack([_echo_image(T1), _echo_image(T2)])
    a = with_confidence(gpumap.MinMaxMapper(SPEC, GRID, backend=backend))
    a.integrate_batch(imgs, np.stack([T1, T2]))
    b = with_confidence(gpumap.MinMaxMapper(SPEC, GRID, backend="numpy"))
    b.integrate(imgs[0], T1)
    b.integrate(imgs[1], T2)
    np.testing.assert_array_equal(a.layer("confidence").states(), b.layer("confidence").states())
    c = a.layer("confidence").states()
    v = a.values()
    occupied = np.isfinite(v) & (v >= a.threshold)
    np.testing.assert_array_equal(occupied, c >= 2)  # occupied <=> (un)confirmed: none freed


def _state_mapper(backend: str, values: np.ndarray) -> gpumap.MinMaxMapper:
    m = with_confidence(gpumap.MinMaxMapper(SPEC, GRID, backend, MapperParams(rule="plain")))
    pool = m.storage.to_pool_order(np.ascontiguousarray(values, np.float32), np.inf)  # a hand-made map state
    m.storage.backend.write(pool.ravel(), None, None)
    return m


def _bit(step) -> int:
    return int(np.flatnonzero((PAIR_STEPS == step).all(1) | (PAIR_STEPS == -np.array(step)).all(1))[0])


def test_gain_counts_a_voxel_whose_arc_neighbours_are_free():
    """Rule (a). One unconfirmed voxel in a column of occupied ones, free on its other sides,
    every arc direction already used (rule (b) off). Seen level, its elevation arc runs along the
    column (neighbours occupied): no gain. Rolled 90 deg, the arc runs across it, through free
    voxels: the view would settle it (gain 1 per observed voxel of the column)."""
    v = np.full(GRID.shape, np.float32(0.0))
    i, j, k = _target_index()
    v[i, j, :] = 0.5  # a vertical column of occupied voxels through the target
    m = _state_mapper("numpy", v)
    m.layer("confidence").arcs[:] = (1 << 13) - 1
    cand = np.stack([_look_at_target(), _look_at_target(math.pi / 2), _look_at_target(math.pi / 4)])
    g = m.layer("confidence").gains(cand, unknown_weight=0.0)
    n_col = GRID.shape[2]
    assert g[0] == 0
    # rolled 90 deg every observed voxel of the column has free arc neighbours
    T = cand[1]
    zs = GRID.min_corner_m[2] + (np.arange(n_col) + 0.5) * GRID.voxel_size_m
    P = np.stack([np.full(n_col, TARGET[0]), np.full(n_col, TARGET[1]), zs], -1)
    p_S = (P - T[:3, 3]) @ T[:3, :3]
    assert g[1] == SPEC.in_fov(p_S).sum() > 0
    # at 45 deg the nearest grid step of the arc is diagonal (y, z): across the column, free
    assert g[2] > 0


def test_gain_counts_a_new_arc_direction_next_to_free_space():
    """Rule (b). A wall facing the sonar (the plane x = const, occupied), free in front and behind:
    no arc along the wall has free neighbours (rule (a) never holds). Observed so far only along
    vertical arcs, the level view (vertical arcs) adds nothing, the rolled one (horizontal arcs,
    a new direction) counts every wall voxel it observes; once that direction is recorded too,
    nothing."""
    v = np.full(GRID.shape, np.float32(0.0))
    i, _, _ = _target_index()
    v[i, :, :] = 0.5
    m = _state_mapper("numpy", v)
    m.layer("confidence").arcs[:] = 1 << _bit((0, 0, 1))
    cand = np.stack([_look_at_target(), _look_at_target(math.pi / 2)])
    g = m.layer("confidence").gains(cand, unknown_weight=0.0)
    idx = np.argwhere(v > 0.1)
    c = np.asarray(GRID.min_corner_m) + (idx + 0.5) * GRID.voxel_size_m
    T = cand[1]
    seen = SPEC.in_fov((c - T[:3, 3]) @ T[:3, :3])
    assert g[0] == 0 and g[1] == seen.sum() > 10
    m.layer("confidence").arcs[:] |= 1 << _bit((0, 1, 0))
    assert (
        m.layer("confidence").gains(cand[1:], unknown_weight=0.0)[0] < 0.1 * seen.sum()
    )  # only arcs off the y step


def test_confidence_pass_records_the_arc_directions():
    m = with_confidence(gpumap.MinMaxMapper(SPEC, GRID, backend="numpy"))
    f = np.ravel_multi_index(_target_index(), GRID.shape)
    T1 = _look_at_target()
    m.integrate(_echo_image(T1), T1)
    assert m.layer("confidence").arcs[f] == 1 << _bit((0, 0, 1))  # level: the arc is vertical
    T2 = _look_at_target(math.pi / 2)
    m.integrate(_echo_image(T2), T2)
    assert m.layer("confidence").arcs[f] == (1 << _bit((0, 0, 1))) | (
        1 << _bit((0, 1, 0))
    )  # rolled: horizontal


def test_gain_counts_unknown_blocks():
    """An empty map: every voxel is unknown; the gain counts the unknown voxels of the blocks
    whose centre lies in the field of view (brute force with the spec's own field-of-view test)."""
    m = with_confidence(gpumap.MinMaxMapper(SPEC, GRID, backend="numpy"))
    Ts = candidate_poses(_look_at_target(), 6, seed=3)
    g = m.layer("confidence").gains(Ts)
    s = GRID.voxel_size_m
    nb = [-(-n // 4) for n in GRID.shape]
    idx = np.argwhere(np.ones(nb, bool))
    centres = np.asarray(GRID.min_corner_m) + (idx * 4 + 2.0) * s
    n_in = np.minimum(4, np.asarray(GRID.shape) - idx * 4).prod(1)
    for T, gi in zip(Ts, g, strict=True):
        p_S = (centres - T[:3, 3]) @ T[:3, :3]
        assert gi == n_in[SPEC.in_fov(p_S)].sum()


def test_view_gain_matches_reference_on_every_backend(backend):
    """A map after a few noisy pings; many candidates; exact equality with the NumPy reference."""
    rng = np.random.default_rng(5)
    m = with_confidence(gpumap.MinMaxMapper(SPEC, GRID, backend=backend))
    for _ in range(6):
        T = _look_at_target(rng.uniform(-1.5, 1.5))
        img = np.where(rng.random(SPEC.image_shape) < 0.003, 0.8, 0.02).astype(np.float32)
        m.integrate(img, T)
    Ts = np.concatenate([candidate_poses(_look_at_target(), 150, seed=s) for s in range(2)])
    g = m.layer("confidence").gains(Ts, unknown_weight=0.5)
    pts = gain_points(
        m.raw_values(), m.layer("confidence").states() == 3, m.threshold, GRID, m.layer("confidence").arcs
    )
    settle, unknown = view_gain_reference(poses_to_rows(Ts), pts, _fov(m.integrator.params))
    assert (settle > 0).any() and (unknown > 0).any()
    np.testing.assert_array_equal(g, settle + 0.5 * unknown)


def _noisy_map() -> gpumap.MinMaxMapper:
    rng = np.random.default_rng(5)
    m = with_confidence(gpumap.MinMaxMapper(SPEC, GRID, backend="numpy"))
    for _ in range(6):
        img = np.where(rng.random(SPEC.image_shape) < 0.003, 0.8, 0.02).astype(np.float32)
        m.integrate(img, _look_at_target(rng.uniform(-1.5, 1.5)))
    return m


def test_next_best_views_are_the_best_candidates_around_each_anchor():
    """Brute force: the same candidates drawn around each anchor by candidate_poses, scored by
    view_gain, ranked (stable): the views are the top of that ranking, with their anchors."""
    m = _noisy_map()
    anchors = np.stack([_look_at_target(0.0), _look_at_target(0.7)])
    lim = dict(roll_rad=(-0.6, 0.6), pitch_rad=(-0.2, 0.2), yaw_rad=(-0.3, 0.3), offset_m=(-0.05, 0.05))
    before = m.raw_values()
    views, n = next_best_views(m, anchors, views=4, candidates=301, unknown_weight=0.5, seed=3, **lim)
    per = 151  # ceil(301 / 2): the last anchor's draw is cut to fill 301
    C = np.concatenate([candidate_poses(T, per, seed=3 * 1009 + a, **lim)
                        for a, T in enumerate(anchors)])[:301]
    g = m.layer("confidence").gains(C, unknown_weight=0.5)
    want = sorted(range(len(C)), key=lambda k: (-g[k], k))[:4]
    assert n == 301 and [v["candidate"] for v in views] == want
    assert [v["gain"] for v in views] == [float(g[k]) for k in want] and views[0]["gain"] > 0
    assert [v["anchor"] for v in views] == [int(k >= per) for k in want]
    for v in views:
        np.testing.assert_array_equal(v["T_W_S"], C[v["candidate"]])
    np.testing.assert_array_equal(m.raw_values(), before)  # the map is only read
    one, _ = next_best_views(m, anchors[0], views=2, candidates=10, **lim)  # a single (4, 4) anchor
    assert len(one) == 2 and {v["anchor"] for v in one} == {0}
    for bad in (np.eye(3), np.zeros((0, 4, 4))):
        with pytest.raises(ValueError, match="anchors"):
            next_best_views(m, bad)
    with pytest.raises(ValueError, match="positive integer views"):
        next_best_views(m, anchors, views=0)


def test_pair_steps_cover_each_neighbour_pair_once():
    s = {tuple(x) for x in PAIR_STEPS} | {tuple(-x) for x in PAIR_STEPS}
    assert len(PAIR_STEPS) == 13 and len(s) == 26 and (0, 0, 0) not in s


def test_candidates_stay_within_their_bounds():
    T0 = _look_at_target(0.3)
    lim = dict(roll_rad=(-0.5, 0.2), pitch_rad=(-0.1, 0.3), yaw_rad=(0.0, 0.4), offset_m=(-0.05, 0.02))
    C = candidate_poses(T0, 300, seed=1, **lim)
    np.testing.assert_allclose(C[0], T0)
    D = np.linalg.inv(T0) @ C
    R = D[:, :3, :3]
    yaw = np.arctan2(R[:, 1, 0], R[:, 0, 0])
    pitch = -np.arcsin(np.clip(R[:, 2, 0], -1, 1))
    roll = np.arctan2(R[:, 2, 1], R[:, 2, 2])
    for name, a in (("roll_rad", roll), ("pitch_rad", pitch), ("yaw_rad", yaw)):
        lo, hi = lim[name]
        assert a[1:].min() >= lo - 1e-9 and a[1:].max() <= hi + 1e-9
        assert a[1:].max() - a[1:].min() > 0.8 * (hi - lo)  # the range is used
    t = D[:, :3, 3]
    assert t.min() >= -0.05 - 1e-12 and t.max() <= 0.02 + 1e-12
    with pytest.raises(ValueError, match="roll_rad"):
        candidate_poses(T0, 3, roll_rad=(0.2, -0.2))


def test_confidence_saved_and_loaded(tmp_path):
    m = with_confidence(gpumap.MinMaxMapper(SPEC, GRID, backend="numpy"))
    for roll in (0.0, math.pi / 2):
        T = _look_at_target(roll)
        m.integrate(_echo_image(T), T)
    p = m.save(tmp_path / "m.npz")
    back = gpumap.MinMaxMapper.load(p, backend="numpy")
    assert "confidence" in back.layer_state  # kept for the layer until one attaches
    with_confidence(back)
    np.testing.assert_array_equal(back.layer("confidence").states(), m.layer("confidence").states())
    np.testing.assert_array_equal(back.layer("confidence").arcs, m.layer("confidence").arcs)
    assert m.layer("confidence").arcs.any()
    # a map without the layer still saves and loads without it
    n = gpumap.MinMaxMapper(SPEC, GRID, backend="numpy")
    n.integrate(_echo_image(T), T)
    back = gpumap.MinMaxMapper.load(n.save(tmp_path / "n.npz"), backend="numpy")
    assert "confidence" not in back.layer_state
    with pytest.raises(KeyError, match="confidence"):
        back.layer("confidence")
    with_confidence(back)  # attaches, starts empty
    assert not back.layer("confidence").confirmed.any()


def test_bad_input_raises_and_changes_nothing():
    m = with_confidence(gpumap.MinMaxMapper(SPEC, GRID, backend="numpy"))
    T = _look_at_target()
    m.integrate(_echo_image(T), T)
    before = m.layer("confidence").states()
    with pytest.raises(ValueError, match=r"\(K, 4, 4\)"):
        m.layer("confidence").gains(np.eye(4))
    bad = np.stack([T, T])
    bad[1, :3, :3] *= 2.0
    with pytest.raises(ValueError):
        m.layer("confidence").gains(bad)
    with pytest.raises(ValueError, match="unknown_weight"):
        m.layer("confidence").gains(bad[:1], unknown_weight=-1.0)
    with pytest.raises(KeyError, match="confidence"):
        gpumap.MinMaxMapper(SPEC, GRID, backend="numpy").layer("confidence")
    with pytest.raises(ValueError, match="attached"):
        ConfidenceLayer().gains(bad[:1])
    with pytest.raises(ValueError, match="one layer named"):
        m.attach(ConfidenceLayer())
    with pytest.raises(TypeError, match="name"):
        m.attach(object())
    np.testing.assert_array_equal(m.layer("confidence").states(), before)


def test_sparse_mapper_says_it_has_no_confidence_layer():
    m = gpumap.SparseMinMaxMapper(SPEC, gpumap.SparseSpec(0.05), backend="numpy")
    with pytest.raises(ValueError, match="on demand"):
        m.attach(ConfidenceLayer())
    assert m.layers == []


def test_demo_plan_writes_three_arms(tmp_path):
    """``gpumap demo --plan`` end to end on a coarse grid: three arms, one curve row per ping."""
    import json

    from maps import run_demo

    out = tmp_path / "demo"
    run_demo(["--voxel-size", "0.06", "--pings", "5", "--backend", "numpy", "--no-progress"], out, plan=2)
    for name in ("plan_curves.png", "plan_confidence.png", "plan_poses.png"):
        assert (out / name).stat().st_size > 0, name
    plan = json.loads((out / "metrics.json").read_text())["plan"]
    assert set(plan["arms"]) == {"planned", "rolled", "random"}
    for rec in plan["arms"].values():
        assert [c["pings"] for c in rec["curve"]] == [5, 6, 7]
        assert len(rec["poses"]) == 2
        assert rec["curve"][0] == plan["arms"]["planned"]["curve"][0]  # the same start
    assert len(plan["arms"]["planned"]["gains"]) == 2 and min(plan["arms"]["planned"]["gains"]) > 0
