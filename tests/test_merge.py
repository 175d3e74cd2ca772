"""merge: maps built from disjoint sets of pings combine into the map of all the pings, bit for bit.

Reference: one mapper of the same kind and backend that integrated every ping (itself tested
against the NumPy oracle and brute force elsewhere); splits are random, of simulated pings
(random returns and shadows, test_visibility) and of the real OASIS tank frames.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import DATA, needs_data, pose, rot_y
from maps import make_mapper
from test_mapper import GRID, SPEC
from test_visibility import _random_pings

import gpumap
from gpumap import MapMemoryError, SparseMinMaxMapper, SparseSpec
from gpumap.core.merge import MapState, load_map, map_state, merge_maps
from gpumap.core.params import MapperParams
from gpumap.layers.confidence import with_confidence

S = GRID.voxel_size_m
BOUNDED = SparseSpec(S, (GRID.min_corner_m, GRID.max_corner_m))
UNBOUNDED = SparseSpec(S, origin_m=GRID.min_corner_m)


def _dense(backend, pings, rule="evidence", spec=SPEC, grid=GRID, **kw):
    m = make_mapper(spec, grid, backend=backend, rule=rule, threshold=0.1, **kw)
    for img, T in pings:
        m.integrate(img, T)
    return m


def _sparse(backend, pings, sparse=BOUNDED, rule="evidence", spec=SPEC, **kw):
    m = make_mapper(spec, sparse, backend=backend, rule=rule, threshold=0.1, initial_blocks=2, **kw,
                    cls=SparseMinMaxMapper)
    for img, T in pings:
        m.integrate(img, T)
    return m


def _split(n: int, parts: int, rng) -> list[np.ndarray]:
    """A random partition of range(n) into ``parts`` non-empty sets (each kept in order)."""
    lab = np.concatenate([np.arange(parts), rng.integers(0, parts, n - parts)])
    rng.shuffle(lab)
    return [np.flatnonzero(lab == k) for k in range(parts)]


def _state(m) -> dict:
    """Everything a map says: values, observed, the rule's evidence (counts included), the ping count."""
    out = {"values": m.raw_values(), "observed": m.observed(), "n": m.n_integrated}
    if m.rule != "plain":
        out.update(m.evidence())
    if m.sparse is not None:
        m.memory_stats()
        out["blocks"] = sorted(tuple(c) for c in m.storage.coords[m.storage.used])
    return out


def _assert_same(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for k in a:
        if isinstance(a[k], np.ndarray):
            assert a[k].dtype == b[k].dtype, k
            np.testing.assert_array_equal(a[k], b[k], err_msg=k)
        else:
            assert a[k] == b[k], k


# ------------------------------------------------------------------------------ exact merges
@pytest.mark.parametrize("rule", ["evidence", "visible", "plain"])
def test_dense_random_splits_equal_one_mapper(backend, rule):
    rng = np.random.default_rng(7)
    pings = _random_pings(8, 11)
    ref = _state(_dense(backend, pings, rule))
    assert ref["observed"].sum() > 1000
    if rule != "plain":  # both evidence paths exercised, or the test proves little
        assert ref["count"].max() >= 2 and np.isfinite(ref["bright"]).sum() > 100
        assert ref["hits"].max() >= 2
    for parts in (2, 3):
        idx = _split(len(pings), parts, rng)
        maps = [_dense(backend, [pings[i] for i in ix], rule) for ix in idx]
        first = maps[0]
        for m in maps[1:]:
            first.merge(m)
        _assert_same(_state(first), ref)
        # merge_maps leaves its inputs alone and gives the same map
        maps2 = [_dense(backend, [pings[i] for i in ix], rule) for ix in idx]
        before = _state(maps2[1])
        _assert_same(_state(merge_maps(maps2, backend=backend)), ref)
        _assert_same(_state(maps2[1]), before)


@pytest.mark.parametrize("rule", ["evidence", "visible", "plain"])
@pytest.mark.parametrize("space", ["bounded", "unbounded"])
def test_sparse_random_splits_equal_one_mapper(backend, rule, space):
    rng = np.random.default_rng(3)
    sp = BOUNDED if space == "bounded" else UNBOUNDED
    pings = _random_pings(7, 5)
    one = _sparse(backend, pings, sp, rule)
    ref = _state(one)
    idx = _split(len(pings), 3, rng)
    maps = [_sparse(backend, [pings[i] for i in ix], sp, rule) for ix in idx]
    # parts cover different blocks: the merge both adds blocks and combines shared ones
    blocks = [set(_state(m)["blocks"]) for m in maps]
    assert blocks[0] != blocks[1] and blocks[0] & blocks[1]
    maps[1].merge(maps[0])
    maps[1].merge(maps[2])
    _assert_same(_state(maps[1]), ref)
    maps[1].check()
    # and it equals the dense map where both have voxels (bounded: everywhere)
    if space == "bounded":
        np.testing.assert_array_equal(maps[1].raw_values(), _dense(backend, pings, rule).raw_values())


def test_count_saturates_as_one_mapper_does():
    """Visible rule: 140 clear dark views (2 each) saturate the count at 255; two halves of 70 must too.

    Each ping a little darker than the last: maps holding the very same ping (image and pose)
    are refused by the merge (test_hardening), so the halves need pings of their own."""
    T = pose(rot_y(0.1), (0.0, 0.0, 0.0))
    pings = [(np.full(SPEC.image_shape, 0.01 - 1e-5 * k, np.float32), T) for k in range(140)]
    one = _dense("numpy", pings, "visible")
    assert one.evidence()["count"].max() == 255
    a, b = _dense("numpy", pings[:70], "visible"), _dense("numpy", pings[70:], "visible")
    assert a.evidence()["count"].max() == 140
    a.merge(b)
    _assert_same(_state(a), _state(one))


def test_files_and_states_merge_too(tmp_path):
    pings = _random_pings(6, 2)
    ref = _state(_dense("numpy", pings))
    p1 = _dense("numpy", pings[:2]).save(tmp_path / "a.npz")
    p2 = _dense("numpy", pings[2:4]).save(tmp_path / "b.npz")
    st = map_state(_dense("numpy", pings[4:]))
    m = merge_maps([p1, p2, st], backend="numpy")
    _assert_same(_state(m), ref)
    sp = _sparse("numpy", pings[:3]).save(tmp_path / "s.npz")
    assert load_map(sp, backend="numpy").sparse == _sparse("numpy", []).sparse
    assert isinstance(load_map(p1, backend="numpy"), gpumap.MinMaxMapper)
    s = load_map(sp, backend="numpy")
    s.merge(_sparse("numpy", pings[3:]))
    _assert_same(_state(s), _state(_sparse("numpy", pings)))


@needs_data
@pytest.mark.parametrize("kind", ["dense-evidence", "dense-visible", "dense-plain", "sparse-evidence"])
def test_real_tank_pings_random_split(backend, kind):
    from gpumap.io import open_fan_folder
    from gpumap.spec import auto_grid

    frames = list(open_fan_folder(DATA / "oasis_tank", stride=4))
    pings = [(f.image, f.T_W_S) for f in frames]
    spec = frames[0].spec
    grid = auto_grid(spec, [T for _, T in pings], 0.06)
    rule = kind.split("-")[1]

    def make(ps):
        if kind.startswith("sparse"):
            m = SparseMinMaxMapper(
                spec,
                SparseSpec(0.06, origin_m=grid.min_corner_m),
                backend,
                MapperParams(rule=rule, threshold=0.4),
            )
        else:
            m = gpumap.MinMaxMapper(spec, grid, backend, MapperParams(rule=rule, threshold=0.4))
        m.integrate_batch(np.stack([p[0] for p in ps]), np.stack([p[1] for p in ps]))
        return m

    ref = _state(make(pings))
    assert ref["observed"].sum() > 10_000
    idx = _split(len(pings), 3, np.random.default_rng(1))
    merged = merge_maps([map_state(make([pings[i] for i in ix])) for ix in idx], backend=backend)
    _assert_same(_state(merged), ref)


# ------------------------------------------------------------------------------ refusals
def test_mismatches_are_refused_and_leave_the_map_unchanged():
    pings = _random_pings(3, 1)
    m = _dense("numpy", pings[:2])
    before = _state(m)
    other_grid = gpumap.GridSpec(GRID.min_corner_m, GRID.max_corner_m, 0.08)
    cases = [
        (_dense("numpy", pings[2:], rule="plain"), "rule"),
        (_dense("numpy", pings[2:], grid=other_grid), "grid"),
        (gpumap.MinMaxMapper(SPEC, GRID, "numpy", MapperParams(threshold=0.2)), "threshold"),
        (gpumap.MinMaxMapper(SPEC, GRID, "numpy", MapperParams(threshold=0.1, carve_views=3)), "carve_views"),
        (gpumap.MinMaxMapper(SPEC, GRID, "numpy", MapperParams(threshold=0.1, shadow_m=0.02)), "shadow_m"),
        (
            gpumap.MinMaxMapper(
                gpumap.SonarSpec(0.15, 1.4, 60, SPEC.bearings_rad, SPEC.vfov_rad),
                GRID,
                "numpy",
                MapperParams(threshold=0.1),
            ),
            "spec",
        ),
        (_sparse("numpy", pings[2:]), "kind"),
    ]
    for other, word in cases:
        with pytest.raises(ValueError, match=word):
            m.merge(other)
        _assert_same(_state(m), before)
    with pytest.raises(ValueError, match="itself"):
        m.merge(m)
    with pytest.raises(TypeError, match="MinMaxMapper"):
        m.merge(42)
    st = map_state(_dense("numpy", pings[2:]))
    bad = MapState(st.kind, st.options, st.n_integrated, {**st.arrays, "count": st.arrays["count"][:-1]})
    with pytest.raises(ValueError, match="'count' of shape"):
        m.merge(bad)
    _assert_same(_state(m), before)
    # blocks outside the grid, or one block twice: refused, the map unchanged
    blocks = st.arrays["blocks"].copy()
    shifts = (np.array([m.storage.index.shape[0], 0, 0]), -np.array([0, 0, blocks[:, 2].max() + 1]))
    for bad_blocks in (*(blocks + d for d in shifts), np.concatenate([blocks[:1], blocks[:-1]])):
        with pytest.raises(ValueError, match="inside the map's bounds"):
            m.merge(MapState(st.kind, st.options, 1, {**st.arrays, "blocks": bad_blocks}))
        _assert_same(_state(m), before)
    with pytest.raises(ValueError, match="at least one"):
        merge_maps([])


def test_a_spec_mismatch_names_the_field_in_one_short_line():
    """Two sonars that differ in one field: the error names it (spec.n_bins), not the whole spec
    with its beam table (hundreds of numbers on one line, as gpumap merge printed it)."""
    m = gpumap.MinMaxMapper(SPEC, GRID, "numpy", MapperParams(threshold=0.1))
    fewer_bins = gpumap.SonarSpec(SPEC.range_min_m, SPEC.range_max_m, SPEC.n_bins - 1, SPEC.bearings_rad,
                                  SPEC.vfov_rad)
    with pytest.raises(ValueError, match=rf"same spec\.n_bins to merge, but got {SPEC.n_bins} and "
                                         rf"{SPEC.n_bins - 1}$"):
        m.merge(gpumap.MinMaxMapper(fewer_bins, GRID, "numpy", MapperParams(threshold=0.1)))
    bearings = np.asarray(SPEC.bearings_rad, dtype=np.float64).copy()
    bearings[-1] += 1e-3
    other_beams = gpumap.SonarSpec(SPEC.range_min_m, SPEC.range_max_m, SPEC.n_bins, bearings, SPEC.vfov_rad)
    with pytest.raises(ValueError, match=r"spec\.bearings_rad") as e:
        m.merge(gpumap.MinMaxMapper(other_beams, GRID, "numpy", MapperParams(threshold=0.1)))
    assert len(str(e.value)) < 300 and f"{len(bearings)} values" in str(e.value), str(e.value)


def test_sparse_merge_over_max_bytes_raises_unchanged():
    pings = _random_pings(4, 9)
    a = _sparse("numpy", pings[:1])
    b = _sparse("numpy", pings[1:])
    na, nb = len(_state(a)["blocks"]), len(_state(b)["blocks"])
    capped = SparseMinMaxMapper(
        SPEC,
        BOUNDED,
        "numpy",
        MapperParams(
            threshold=0.1,
            initial_blocks=1,
            max_bytes=a.storage.index.nbytes + (na + 1) * a.storage.block_bytes,
            evict="farthest",
        ),
    )
    capped.merge(a)  # fits
    before = _state(capped)
    assert nb > 1
    with pytest.raises(MapMemoryError, match="never evicts"):
        capped.merge(b)
    _assert_same(_state(capped), before)


def test_merge_command_writes_the_map_of_all_pings(tmp_path, capsys):
    import json

    from gpumap.commands import main

    pings = _random_pings(5, 8)
    parts = [_dense("numpy", pings[:3]).save(tmp_path / "a.npz"),
             _dense("numpy", pings[3:]).save(tmp_path / "b.npz")]
    assert main(["merge", str(tmp_path / "m.npz"), *map(str, parts)]) == 0
    assert json.loads(capsys.readouterr().out)["pings"] == 5
    _assert_same(_state(load_map(tmp_path / "m.npz", backend="numpy")), _state(_dense("numpy", pings)))
    # run again onto the file it wrote: replaced (it was refused as "a path under a folder")
    assert main(["merge", str(tmp_path / "m.npz"), str(parts[0])]) == 0
    assert json.loads(capsys.readouterr().out)["pings"] == 3
    # one map twice (by name, or a copy) would count its clear dark views twice: refused
    import shutil

    shutil.copy(parts[0], tmp_path / "copy.npz")
    for twice in ([parts[0], parts[1], parts[0]], [parts[0], tmp_path / "copy.npz"]):
        with pytest.raises(ValueError, match="same map as"):
            merge_maps(twice, backend="numpy")
        assert main(["merge", str(tmp_path / "y.npz"), *map(str, twice)]) == 2
        assert "same map as" in capsys.readouterr().err and not (tmp_path / "y.npz").exists()
    other = gpumap.MinMaxMapper(SPEC, GRID, "numpy", MapperParams(rule="plain")).save(tmp_path / "p.npz")
    assert main(["merge", str(tmp_path / "x.npz"), str(parts[0]), str(other)]) == 2
    assert "same rule" in capsys.readouterr().err and not (tmp_path / "x.npz").exists()


def test_export_reads_sparse_map_files_too(tmp_path, capsys):
    import json

    from gpumap.commands import main
    from gpumap.io import read_ply

    m = _sparse("numpy", _random_pings(3, 1))
    path = m.save(tmp_path / "s.npz")
    assert main(["export", str(path), str(tmp_path / "s.ply")]) == 0
    info = json.loads(capsys.readouterr().out)
    pts = m.occupied_points(0.1)
    assert info["occupied_cells"] == len(pts) > 100
    ply = read_ply(tmp_path / "s.ply")
    got = np.stack([ply["x"], ply["y"], ply["z"]], axis=1).astype(np.float64)
    np.testing.assert_allclose(np.sort(got, axis=0), np.sort(pts, axis=0), atol=1e-5)


def test_maps_with_the_confidence_layer_are_refused_unchanged():
    """The confidence layer depends on ping order (gpumap.layers.confidence): no merge can be exact."""
    spec = gpumap.SonarSpec.uniform(hfov_deg=60, vfov_deg=12, n_beams=16, n_bins=20, range_min_m=0.1,
                                    range_max_m=1.0)
    grid = gpumap.GridSpec((0.0, -0.5, -0.2), (1.0, 0.5, 0.2), 0.1)
    img = np.random.default_rng(3).random(spec.image_shape).astype(np.float32)
    a = with_confidence(gpumap.MinMaxMapper(spec, grid, backend="numpy"))
    b = with_confidence(gpumap.MinMaxMapper(spec, grid, backend="numpy"))
    plain_b = gpumap.MinMaxMapper(spec, grid, backend="numpy")
    for m in (a, b, plain_b):
        m.integrate(img, np.eye(4))
    before = a.raw_values().copy()
    for other in (b, plain_b):
        with pytest.raises(ValueError, match="confidence layer"):
            a.merge(other)
    with pytest.raises(ValueError, match="confidence layer"):
        plain_b.merge(b)
    np.testing.assert_array_equal(a.raw_values(), before)


def test_states_merged_one_after_the_other_into_a_new_map_both_count():
    """A new map takes the first state's blocks as they are (nothing to combine with) and must then
    combine the second with them, even when the states claim no pings (built by hand)."""
    pings = _random_pings(4, 29)
    a, b = map_state(_dense("numpy", pings[:2])), map_state(_dense("numpy", pings[2:]))
    ref = _state(merge_maps([a, b], backend="numpy"))
    m = gpumap.MinMaxMapper(SPEC, GRID, "numpy", MapperParams(threshold=0.1))
    for st in (a, b):
        m.merge(MapState(st.kind, st.options, 0, {k: v for k, v in st.arrays.items() if k != "pings"}))
    got = _state(m)
    assert got.pop("n") == 0 and ref.pop("n") == 4
    _assert_same(got, ref)


def test_template_method_maps_merge_exactly(backend):
    """The template kernels do not mark blocks seen: merging into a template map that took pings
    must still combine with every block (not overwrite), and its state must carry them all."""
    pings = _random_pings(6, 37)
    ref = _state(_dense(backend, pings, rule="plain", method="template"))
    assert ref["observed"].sum() > 500
    a = _dense(backend, pings[:3], rule="plain", method="template")
    b = _dense(backend, pings[3:], rule="plain", method="template")
    _assert_same(_state(merge_maps([a, b], backend=backend)), ref)
    a.merge(b)
    _assert_same(_state(a), ref)
