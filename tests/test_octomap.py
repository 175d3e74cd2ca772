"""OctoMap ``.bt`` export: read back by an independent decoder of the format and by OctoMap itself."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest

from gpumap.io.octomap import TREE_DEPTH, write_octomap_bt
from gpumap.spec import GridSpec

HAVE_PYOCTOMAP = importlib.util.find_spec("pyoctomap") is not None
needs_pyoctomap = pytest.mark.skipif(not HAVE_PYOCTOMAP,
                                     reason="pyoctomap (OctoMap's Python bindings) not installed: "
                                            "pip install -e '.[test]'")


def _decode_bt(data: bytes) -> tuple[float, int, dict[tuple[int, int, int], int]]:
    """Decode a .bt file by the format's definition: ``(res, size, {key16: 1 free | 2 occupied})``.

    Written from OctoMap's ``readBinaryNode``: per inner node two bytes, child ``i``'s bits
    ``2i`` (free or inner) and ``2i + 1`` (occupied or inner) of byte ``i // 4``; child
    index ``x + 2 y + 4 z`` of the key bits at that level. Pruned leaves are expanded.
    """
    lines = []
    pos = 0
    while True:
        end = data.index(b"\n", pos)
        lines.append(data[pos:end].decode())
        pos = end + 1
        if lines[-1] == "data":
            break
    assert lines[0].startswith("# Octomap OcTree binary file")
    head = dict(line.split(" ", 1) for line in lines if not line.startswith("#") and " " in line)
    assert head["id"] == "OcTree"
    res, size = float(head["res"]), int(head["size"])
    body = data[pos:]
    cells: dict[tuple[int, int, int], int] = {}
    nodes = 0
    stack_pos = [0]

    def node(key: tuple[int, int, int], depth: int) -> None:
        nonlocal nodes
        nodes += 1
        b = body[stack_pos[0]:stack_pos[0] + 2]
        stack_pos[0] += 2
        kids = []
        for i in range(8):
            bits = (b[i // 4] >> (2 * (i % 4))) & 3
            ck = tuple(2 * k + ((i >> a) & 1) for a, k in enumerate(key))
            kids.append((bits, ck))
        for bits, ck in kids:
            if bits == 0:
                continue
            if bits == 3:
                node(ck, depth + 1)
                continue
            nodes += 1
            span = 1 << (TREE_DEPTH - depth - 1)
            r = range(span)
            for dx in r:
                for dy in r:
                    for dz in r:
                        cells[(ck[0] * span + dx, ck[1] * span + dy, ck[2] * span + dz)] = bits
    if size:
        node((0, 0, 0), 0)
        assert stack_pos[0] == len(body), "trailing bytes after the tree"
    assert nodes == size
    return res, size, cells


def _expected(values: np.ndarray, grid: GridSpec, thr: float) -> dict[tuple[int, int, int], int]:
    """Key of every observed voxel: the OctoMap cell holding its centre (floor(c / res) + 32768)."""
    idx = np.argwhere(np.isfinite(values))
    keys = np.floor(grid.centers(idx) / grid.voxel_size_m + 1e-9).astype(int) + (1 << 15)
    v = values[tuple(idx.T)]
    return {tuple(k): (2 if x >= thr else 1) for k, x in zip(keys.tolist(), v, strict=True)}


@pytest.mark.parametrize("corner", [(-0.4, -0.2, -0.1), (-0.33, 0.07, 1.01)])
def test_bt_holds_every_voxel_state(tmp_path, corner):
    rng = np.random.default_rng(3)
    grid = GridSpec(corner, (corner[0] + 0.7, corner[1] + 0.45, corner[2] + 0.3), 0.05)
    v = rng.random(grid.shape).astype(np.float32)
    v[rng.random(grid.shape) < 0.3] = np.nan  # unknown: no node
    v[:8, :8, :4] = 0.0  # a block OctoMap prunes into one free leaf (when aligned)
    info = write_octomap_bt(tmp_path / "m.bt", v, grid, threshold=0.5)
    res, size, cells = _decode_bt((tmp_path / "m.bt").read_bytes())
    assert res == pytest.approx(0.05)
    assert size == info["nodes"]
    assert cells == _expected(v, grid, 0.5)
    assert info["occupied_cells"] == int(np.sum(v >= 0.5))
    assert info["free_cells"] == int(np.sum(v < 0.5))
    assert np.all(np.abs(info["offset_m"]) <= 0.025 + 1e-9)


def test_bt_prunes_uniform_blocks(tmp_path):
    grid = GridSpec((0, 0, 0), (0.8, 0.8, 0.8), 0.1)  # 8^3 voxels, keys 32768..32775: one aligned block
    v = np.zeros(grid.shape, np.float32)
    info = write_octomap_bt(tmp_path / "free.bt", v, grid, threshold=0.5)
    # 8^3 free cells collapse into one leaf at depth 13, under a chain of 13 inner nodes
    assert info["leaves"] == 1 and info["inner"] == 13
    _, _, cells = _decode_bt((tmp_path / "free.bt").read_bytes())
    assert len(cells) == 512 and set(cells.values()) == {1}


def test_bt_empty_map_and_bad_input(tmp_path):
    grid = GridSpec((0, 0, 0), (0.3, 0.3, 0.3), 0.1)
    info = write_octomap_bt(tmp_path / "e.bt", np.full(grid.shape, np.nan, np.float32), grid)
    assert info["nodes"] == 0
    assert _decode_bt((tmp_path / "e.bt").read_bytes())[2] == {}
    with pytest.raises(ValueError, match="grid's shape"):
        write_octomap_bt(tmp_path / "x.bt", np.zeros((2, 2, 2), np.float32), grid)
    with pytest.raises(TypeError, match="floating"):
        write_octomap_bt(tmp_path / "x.bt", np.zeros(grid.shape, np.uint8), grid)
    far = GridSpec((4000.0, 0, 0), (4000.3, 0.3, 0.3), 0.1)  # beyond 32768 * 0.1 m
    with pytest.raises(ValueError, match="OctoMap"):
        write_octomap_bt(tmp_path / "x.bt", np.zeros(far.shape, np.float32), far)
    assert not (tmp_path / "x.bt").exists()


@pytest.fixture(scope="module")
def demo_map(tmp_path_factory):
    from gpumap.commands.demo import main

    out = tmp_path_factory.mktemp("demo")
    assert main(["--voxel-size", "0.06", "--pings", "4", "--backend", "numpy", "--out", str(out),
                 "--no-progress"]) == 0
    return out / "map.npz"


@needs_pyoctomap
def test_demo_map_bt_loads_in_octomap(demo_map, tmp_path, capsys):
    import pyoctomap

    from gpumap.commands import main
    from gpumap.core.mapper import MinMaxMapper

    m = MinMaxMapper.load(demo_map, backend="numpy")
    v = m.values()
    thr = m.threshold
    want_occ = int(np.sum(np.isfinite(v) & (v >= thr)))
    want_free = int(np.sum(np.isfinite(v) & (v < thr)))
    assert want_occ > 100 and want_free > 100
    assert main(["export", str(demo_map), str(tmp_path / "demo.bt")]) == 0
    tree = pyoctomap.OcTree(0.1)
    assert tree.readBinary(str(tmp_path / "demo.bt"))
    assert tree.getResolution() == pytest.approx(m.grid.voxel_size_m)
    occ = free = 0
    for leaf in tree.begin_leafs():
        n = round(leaf.getSize() / m.grid.voxel_size_m) ** 3
        if tree.isNodeOccupied(leaf):
            occ += n
        else:
            free += n
    assert (occ, free) == (want_occ, want_free)
    # and each occupied voxel's centre (shifted onto OctoMap's lattice) finds an occupied leaf
    from gpumap.io.octomap import octomap_offset_m

    idx = np.argwhere(np.isfinite(v) & (v >= thr))[::50]
    off = octomap_offset_m(m.grid)
    for c in m.grid.centers(idx) + off:
        leaf = tree.search(c.tolist())
        assert leaf is not None and tree.isNodeOccupied(leaf)


def test_export_verb_refuses_other_suffix(demo_map, tmp_path, capsys):
    from gpumap.commands import main

    with pytest.raises(SystemExit) as e:
        main(["export", str(demo_map), str(tmp_path / "m.txt")])
    assert e.value.code == 2
    assert ".bt or .ply" in capsys.readouterr().err
    assert main(["export", str(demo_map), str(tmp_path / "m.ply")]) == 0
