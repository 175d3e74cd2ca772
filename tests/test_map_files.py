"""Map files: one format (version 5, blocks) for every storage, and the files earlier versions
wrote still load: dense arrays over the grid (versions 1 to 3, with and without the visible
rule's state and the confidence layer), the former SparseMinMaxMapper's block files and
version 4's blocks (the visible rule's uint8 dark count, no bright count).

The earlier layouts are written here by hand, member by member as those versions' ``save``
wrote them (their docstrings are the reference), from a map's public reads; loading them must
give that map back: values, evidence, confidence layer and ping count, bit for bit.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from maps import make_mapper
from test_mapper import GRID, SPEC
from test_visibility import _random_pings

import gpumap
from gpumap import SparseSpec
from gpumap.core.merge import load_map, map_state
from gpumap.core.params import MapperParams
from gpumap.layers.confidence import with_confidence

PINGS = _random_pings(4, 31)


def _mapped(grid=GRID, **kw) -> gpumap.MinMaxMapper:
    m = make_mapper(SPEC, grid, backend="numpy", threshold=0.1, **kw)
    for img, T in PINGS:
        m.integrate(img, T)
    return m


def _meta(m, version: int, **extra) -> dict:
    meta = {"format": "gpumap.MinMaxMapper", "version": version, "spec": SPEC.to_dict(),
            "grid": m.grid.to_dict(), "method": m.method, "shadow_m": m.shadow_m, "rule": m.rule,
            "threshold": m.threshold, "carve_views": m.carve_views, "n_integrated": m.n_integrated,
            "backend": "numpy", **extra}
    if version == 1:
        for k in ("rule", "threshold", "carve_views"):
            meta.pop(k)
    return meta


def _write(path, meta: dict, **arrays) -> None:
    np.savez_compressed(path, **arrays, meta=np.array(json.dumps(meta)))


def _same(a: gpumap.MinMaxMapper, b: gpumap.MinMaxMapper, hits: bool = True) -> None:
    """The same map; ``hits=False``: a file from before version 5 (no bright-view count)."""
    np.testing.assert_array_equal(a.raw_values(), b.raw_values())
    assert a.n_integrated == b.n_integrated and a.rule == b.rule and a.grid == b.grid
    if a.rule != "plain":
        for k, v in a.evidence().items():
            if hits or k != "hits":
                np.testing.assert_array_equal(v, b.evidence()[k], err_msg=k)
        if not hits:
            assert not a.evidence()["hits"].any()


def _old_evidence(m: gpumap.MinMaxMapper) -> dict:
    """The visible rule's state as files before version 5 held it: a uint8 dark count."""
    ev = m.evidence()
    return {"min_all": ev["min_all"], "bright": ev["bright"], "count": ev["count"].astype(np.uint8)}


@pytest.mark.parametrize("version", [1, 2, 3])
def test_dense_files_of_versions_1_to_3_load(tmp_path, version):
    rule = "plain" if version == 1 else "visible"
    m = _mapped(rule=rule, confidence=version == 3)
    arrays = {"values": m.raw_values()}
    if rule == "visible":
        arrays.update(_old_evidence(m))
    extra = {}
    if version == 3:
        arrays["confirmed"] = m.layer("confidence").confirmed.reshape(GRID.shape).copy()
        arrays["arcs"] = m.layer("confidence").arcs.reshape(GRID.shape).copy()
        extra["confidence"] = True
        assert (arrays["confirmed"] == 1).any()  # the layer holds something to get back
    _write(tmp_path / "old.npz", _meta(m, version, **extra), **arrays)
    for got in (gpumap.MinMaxMapper.load(tmp_path / "old.npz", backend="numpy"),
                load_map(tmp_path / "old.npz", backend="numpy")):
        _same(got, m, hits=False)
        if version == 3:
            np.testing.assert_array_equal(with_confidence(got).layer("confidence").states(),
                                          m.layer("confidence").states())


def _old_blocks(m: gpumap.MinMaxMapper) -> dict:
    """A visible-rule map's blocks as block files before version 5 held them (uint8 dark count)."""
    from gpumap.reference import split_counts, visible_values

    st = map_state(m)
    B, Bz = m.B, m.Bz
    arrays = {"blocks": st.arrays["blocks"].astype(np.int32)}
    for k in ("min_all", "bright"):
        arrays[k] = st.arrays[k].reshape(-1, B, B, Bz)
    arrays["count"] = split_counts(st.arrays["count"])[0].astype(np.uint8).reshape(-1, B, B, Bz)
    arrays["values"] = visible_values(arrays["min_all"], arrays["bright"], arrays["count"], m.carve_views)
    return arrays


def test_former_sparse_files_load(tmp_path):
    m = _mapped(grid=SparseSpec(GRID.voxel_size_m, origin_m=GRID.min_corner_m), rule="visible")
    meta = {"format": "gpumap.SparseMinMaxMapper", "version": 1, "spec": SPEC.to_dict(),
            "sparse": m.sparse.to_dict(), "method": "gather", "shadow_m": 0.0, "rule": "visible",
            "threshold": 0.1, "carve_views": 2, "n_integrated": m.n_integrated, "backend": "numpy"}
    _write(tmp_path / "old.npz", meta, **_old_blocks(m))
    got = load_map(tmp_path / "old.npz", backend="numpy")
    assert got.sparse == m.sparse
    _same(got, m, hits=False)
    assert gpumap.SparseMinMaxMapper.load(tmp_path / "old.npz", backend="numpy").sparse == m.sparse


@pytest.mark.parametrize("sparse", [False, True])
def test_version_4_block_files_load(tmp_path, sparse):
    m = _mapped(rule="visible", sparse=sparse or None)
    meta = {**_meta(m, 4), "block": [m.B, m.B, m.Bz], "confidence": False}
    if sparse:
        meta.pop("grid")
        meta["sparse"] = m.sparse.to_dict()
    _write(tmp_path / "v4.npz", meta, **_old_blocks(m))
    got = gpumap.MinMaxMapper.load(tmp_path / "v4.npz", backend="numpy")
    assert (got.sparse is None) == (not sparse) and got.rule == "visible"
    _same(got, m, hits=False)


@pytest.mark.parametrize("sparse", [False, True])
def test_version_5_round_trip_holds_only_observed_blocks(tmp_path, sparse):
    m = _mapped(confidence=not sparse, sparse=sparse or None)
    assert m.rule == "evidence"
    path = m.save(tmp_path / "m.npz")
    with np.load(path) as z:
        blocks, values = z["blocks"], z["values"]
        assert json.loads(str(z["meta"]))["version"] == 5
        assert z["count"].dtype == np.uint64
    assert 0 < len(blocks) < int(np.prod(m.storage.index.shape))  # only blocks with an observed voxel
    assert np.isfinite(values.reshape(len(blocks), -1)).any(axis=1).all()
    got = gpumap.MinMaxMapper.load(path, backend="numpy")
    assert (got.sparse is None) == (not sparse)
    _same(got, m)
    if not sparse:
        np.testing.assert_array_equal(with_confidence(got).layer("confidence").states(),
                                      m.layer("confidence").states())


def test_a_bounded_box_allocates_every_block_up_front_and_never_searches(monkeypatch):
    """A GridSpec map holds every block of the box from the start (columns of 8 x 8 voxels by the
    grid's height, slot = index entry) and integrates without the per-ping block search."""
    m = gpumap.MinMaxMapper(SPEC, GRID, "numpy", MapperParams(threshold=0.1))
    nb = (-(-GRID.shape[0] // 8), -(-GRID.shape[1] // 8), 1)
    assert m.storage.index.shape == nb and (m.B, m.Bz) == (8, GRID.shape[2])
    np.testing.assert_array_equal(m.storage.index.ravel(), np.arange(int(np.prod(nb))))
    assert m.memory_stats()["pool_blocks"] == int(np.prod(nb))

    def searched(*a, **k):
        raise AssertionError("a bounded box searched for blocks")

    from gpumap.core.integrator import Integrator
    from gpumap.core.storage import BlockStorage

    monkeypatch.setattr(Integrator, "candidate_lins", searched)
    monkeypatch.setattr(BlockStorage, "allocate", searched)
    for img, T in PINGS:
        m.integrate(img, T)
    imgs = np.stack([img for img, _ in PINGS])
    m.integrate_batch(imgs, np.stack([T for _, T in PINGS]))
    assert np.isfinite(m.raw_values()).sum() > 1000
