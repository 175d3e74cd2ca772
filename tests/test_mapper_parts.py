"""The mapper's parts on their own: the block storage (gpumap.core.storage), the integrator
(gpumap.core.integrator) and the value rule (gpumap.core.rules), without a MinMaxMapper; and the imports
among the mapper's modules, which close no circle (a lazy import inside a function counts too).
"""

from __future__ import annotations

import numpy as np
import pytest
from test_architecture import _cycle, _graph
from test_mapper import GRID, SPEC, T_A

import gpumap
from gpumap.core.integrator import Integrator
from gpumap.core.rules import ValueRule, combine_into
from gpumap.core.storage import BlockStorage, MapMemoryError
from gpumap.geometry import ping_params

PLAIN = ValueRule("plain", 2, 0.2, 1.645)

#: The modules of the mapper and its parts, its backends, and the modules beside them.
MAPPER_MODULES = (
    "gpumap.core.mapper",
    "gpumap.core.sparse",
    "gpumap.core.storage",
    "gpumap.core.integrator",
    "gpumap.core.rules",
    "gpumap.layers.confidence",
    "gpumap.layers.viewgain",
    "gpumap.core.mapfile",
    "gpumap.core.mapstate",
    "gpumap.core.merge",
    "gpumap.memory",
    "gpumap.backends",
    "gpumap.backends.base",
    "gpumap.backends.numpy_backend",
    "gpumap.backends.tables",
    "gpumap.backends.warp_backend",
    "gpumap.backends.opencl_backend",
)


def _reaches(g: dict[str, set[str]], a: str, b: str) -> bool:
    seen, todo = {a}, [a]
    while todo:
        for n in g[todo.pop()]:
            if n == b:
                return True
            if n not in seen:
                seen.add(n)
                todo.append(n)
    return False


def test_the_mapper_modules_import_no_circle():
    g = _graph()  # tests/test_architecture.py's: lazy imports and gpumap's lazy names count
    for m in MAPPER_MODULES:
        assert m in g, m
    sub = {m: g[m] & set(MAPPER_MODULES) for m in MAPPER_MODULES}
    assert _cycle(sub) is None, " -> ".join(_cycle(sub) or [])
    # merge builds on the mapper, never the other way round (they used to import each other)
    assert _reaches(g, "gpumap.core.merge", "gpumap.core.mapper")
    assert not _reaches(g, "gpumap.core.mapper", "gpumap.core.merge")
    # the parts sit below the facade
    for part in (
        "gpumap.core.storage",
        "gpumap.core.integrator",
        "gpumap.core.mapfile",
        "gpumap.core.mapstate",
    ):
        assert _reaches(g, "gpumap.core.mapper", part) and not _reaches(g, part, "gpumap.core.mapper"), part


def _blocks(st: BlockStorage, n: int, seed: int) -> np.ndarray:
    return np.random.default_rng(seed).random((n, st.BV)).astype(np.float32)


def test_block_storage_on_demand_puts_combines_reads_and_clears():
    st = BlockStorage(SPEC, gpumap.SparseSpec(0.1, block=4), PLAIN, "numpy", initial_blocks=1)
    assert (st.B, st.Bz, st.BV) == (4, 4, 64) and st.empty and not st.used.any()
    coords = np.array([[3, -1, 2], [0, 0, 0], [-5, 0, 0]], np.int64)
    a = _blocks(st, 3, 0)
    st.put_blocks(coords, {"min_all": a}, combine=False)  # grows the pool and the index
    assert not st.empty and st.backend.cap >= 3 and int(st.used.sum()) == 3
    got, data = st.blocks()
    order = np.lexsort((coords[:, 2], coords[:, 1], coords[:, 0]))
    np.testing.assert_array_equal(got, coords[order])  # lexicographic
    np.testing.assert_array_equal(data["min_all"], a[order])
    np.testing.assert_array_equal(data["values"], a[order])  # the plain rule's values are min_all
    b = _blocks(st, 1, 1)
    st.put_blocks(coords[1:2], {"min_all": b}, combine=True)  # merged: the min of both
    _, data = st.blocks()
    np.testing.assert_array_equal(data["min_all"][1], np.minimum(a[1], b[0]))
    # a dense box over one block and its unknown neighbour
    i0, i1 = np.array([0, 0, 0]), np.array([7, 3, 3])
    box = st.dense(i0, i1, ("values",))["values"]
    assert box.shape == (8, 4, 4) and np.isinf(box[4:]).all()
    np.testing.assert_array_equal(box[:4].ravel(), np.minimum(a[1], b[0]))
    assert st.grid.shape == ((5 + 3 + 1) * 4, 2 * 4, 3 * 4)  # the box of the blocks
    st.clear()
    assert st.empty and not st.used.any() and len(st.free) == st.backend.cap


def test_block_storage_put_past_max_bytes_raises_unchanged():
    st = BlockStorage(SPEC, gpumap.SparseSpec(0.1, block=4), PLAIN, "numpy", max_bytes=4000,
                      initial_blocks=1)
    st.put_blocks(np.zeros((1, 3), np.int64), {"min_all": _blocks(st, 1, 2)}, combine=False)
    before = st.blocks()
    many = np.stack([np.arange(40), np.zeros(40, int), np.zeros(40, int)], 1).astype(np.int64)
    with pytest.raises(MapMemoryError, match="max_bytes=4000"):
        st.put_blocks(many, {"min_all": _blocks(st, 40, 3)}, combine=True)
    after = st.blocks()
    np.testing.assert_array_equal(after[0], before[0])
    np.testing.assert_array_equal(after[1]["min_all"], before[1]["min_all"])


def test_a_bounded_storage_holds_every_block_in_slot_order():
    st = BlockStorage(SPEC, GRID, PLAIN, "numpy")
    nb = (-(-GRID.shape[0] // 8), -(-GRID.shape[1] // 8), 1)
    assert st.index.shape == nb and (st.B, st.Bz) == (8, GRID.shape[2]) and st.used.all()
    a = np.arange(int(np.prod(GRID.shape)), dtype=np.float32).reshape(GRID.shape) / 1e6
    st.write_box(a)
    np.testing.assert_array_equal(st.dense(*st.whole_box(), ("values",))["values"], a)
    np.testing.assert_array_equal(st.to_pool_order(a, np.inf).ravel()[: st.BV], st.blocks()[1]["min_all"][0])


def test_the_integrator_alone_makes_the_reference_ping_record():
    st = BlockStorage(SPEC, GRID, PLAIN, "numpy")
    it = Integrator(SPEC, st, "gather", None, 0.0, "plain", 0.1)
    P, n_threads = it.ping_params(T_A[None], np.zeros(1))
    ref = it.params.copy()
    n_cols = ping_params(ref, T_A, it.fov_pts_S, GRID)  # gpumap.geometry's one-ping version
    assert int(n_threads[0]) == n_cols > 0
    for name in ("R", "t", "A", "box_lo", "box_n", "rho", "near", "win"):
        np.testing.assert_array_equal(P[0][name], ref[name], err_msg=name)
    img = np.ones(SPEC.image_shape, np.float32)
    it.integrate(it.check_image(img), T_A, np.zeros(1))
    assert not st.empty and np.isfinite(st.blocks()[1]["min_all"]).sum() > 100
    with pytest.raises(ValueError, match="image of shape"):
        it.check_image(img[:-1])


def test_the_value_rule_checks_its_options_and_combines_states():
    r = ValueRule("visible", 2, 0.2, 1.645)
    with pytest.raises(ValueError, match="carve_views"):
        r.carve_views = 0
    with pytest.raises(ValueError, match="bright_share"):
        r.bright_share = 1.5
    with pytest.raises(ValueError, match="share_z"):
        r.share_z = -1.0
    assert (r.carve_views, r.bright_share, r.share_z) == (2, 0.2, 1.645)
    acc = {"min_all": np.array([0.5, np.inf], np.float32)}
    combine_into(acc, {"min_all": np.array([0.7, 0.2], np.float32)}, "plain")
    np.testing.assert_array_equal(acc["min_all"], np.array([0.5, 0.2], np.float32))
