"""In-process mappers (gpumap.pipeline.gpu_threads): N threads, N mappers, one merged map equal to one
process.

On a CPU machine the mappers share device 0 of CPU backends (numpy, warp-cpu, opencl-cpu): the
same code path as N GPUs (a queue and a thread per mapper, the merge in place), the same map.
Reference: :func:`gpumap.pipeline.replay.run_replay` on the same frames and grid. No timing here.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import DATA, needs_data
from merged_maps import assert_same, tank

import gpumap
from gpumap.commands.replay import main
from gpumap.pipeline.gpu_threads import run_replay_threads
from gpumap.pipeline.replay import run_replay


@needs_data
@pytest.mark.parametrize("backend", ["numpy", "warp-cpu", "opencl-cpu"])
@pytest.mark.parametrize("rule", ["evidence", "plain"])
def test_threads_equal_one_process_on_real_frames(backend, rule):
    if backend not in gpumap.available_backends():
        pytest.skip(f"{backend} is not available here")
    rec = tank(3)
    kw = dict(voxel_size_m=0.06, backend=backend, rule=rule, progress=False)
    one, s1 = run_replay(rec, **kw)
    assert one.observed().sum() > 10_000
    for n, split in ((1, "space"), (2, "space"), (3, "space"), (2, "pings"), (3, "pings")):
        pos: list = []
        got, s = run_replay_threads(rec, workers=n, split=split, positions=pos, **kw)
        assert got.grid == one.grid and got.backend == one.backend
        assert s["frames"] == s1["frames"] == 41 == len(pos) and s["mode"] == "threads"
        assert s["workers"] == n and s["devices"] == [0] * n  # CPU backends: every mapper on device 0
        frames = [p["frames"] for p in s["per_worker"]]
        assert sum(frames) == 41
        if split == "pings" and n > 1:
            assert frames[:2] == [32, 9]
        assert_same(got, one)


@needs_data
def test_sparse_threads_equal_the_dense_one_process_map():
    rec = tank(4)
    one, _ = run_replay(rec, voxel_size_m=0.06, backend="numpy", progress=False)
    got, s = run_replay_threads(rec, workers=2, voxel_size_m=0.06, backend="numpy", progress=False,
                                sparse=True)
    assert got.sparse is not None and got.grid == one.grid
    assert_same(got, one)


def test_a_device_index_the_backend_lacks_is_a_one_line_error():
    from test_mapper import GRID, SPEC

    for backend in ("numpy", "warp-cpu", "opencl-cpu"):
        if backend not in gpumap.available_backends():
            continue
        for bad in (99, -1, True, "1"):
            with pytest.raises(ValueError, match="device_index") as e:
                gpumap.MinMaxMapper(SPEC, GRID, backend=backend, device_index=bad)
            assert "\n" not in str(e.value)
        m = gpumap.MinMaxMapper(SPEC, GRID, backend=backend, device_index=0)  # its one device is fine
        assert m.backend == backend
    with pytest.raises(ValueError, match=r"numpy has here \(device 0 only\), but got 1"):
        gpumap.MinMaxMapper(SPEC, GRID, backend="numpy", device_index=1)


@needs_data
def test_threads_refuse_a_missing_device_and_stop_on_a_failed_mapper(monkeypatch):
    rec = tank(6)
    kw = dict(voxel_size_m=0.08, backend="numpy", progress=False)
    with pytest.raises(ValueError, match="device_index"):
        run_replay_threads(rec, workers=2, devices=[0, 3], **kw)
    with pytest.raises(ValueError, match="Expected 2 device indices"):
        run_replay_threads(rec, workers=2, devices=[0], **kw)

    def boom(self, images, poses):
        raise RuntimeError("the device went away")

    monkeypatch.setattr(gpumap.MinMaxMapper, "integrate_batch", boom)
    with pytest.raises(RuntimeError, match="the device went away"):
        run_replay_threads(rec, workers=2, **kw)


@needs_data
def test_replay_cli_workers_on_a_machine_with_enough_gpus_stays_in_process(tmp_path: Path, capsys,
                                                                          monkeypatch):
    import gpumap.pipeline.workers

    monkeypatch.setattr(gpumap.pipeline.workers, "host_gpus", lambda: ["0", "1"])  # as if on 2 GPUs
    backend = gpumap.available_backends()[0]  # what auto picks here: a CPU one on a CPU machine
    common = [str(DATA / "oasis_tank"), "--stride", "6", "--no-progress", "--no-pictures",
              "--voxel-size", "0.08", "--backend", "auto"]
    assert main([*common, "--out", str(tmp_path / "one")]) == 0
    capsys.readouterr()
    assert main([*common, "--out", str(tmp_path / "w"), "--workers", "2"]) == 0
    assert f"21 images in-process on 2 devices of {backend}" in capsys.readouterr().out
    a = gpumap.load_map(tmp_path / "one" / "map.npz", backend="numpy")
    b = gpumap.load_map(tmp_path / "w" / "map.npz", backend="numpy")
    assert_same(b, a)
    s = json.loads((tmp_path / "w" / "summary.json").read_text())
    assert s["workers"] == 2 and s["frames"] == 21 and s["mode"] == "threads"
    assert (tmp_path / "w" / "occupied.ply").read_bytes() == (tmp_path / "one" / "occupied.ply").read_bytes()


def test_replay_cli_picks_threads_only_for_gpu_backends_with_enough_gpus(monkeypatch):
    import argparse

    import gpumap.pipeline.workers
    from gpumap.commands.replay import _in_process

    def ns(**kw):
        return argparse.Namespace(**{"scheduler": None, "dask": False, "backend": "auto", "workers": 2, **kw})

    monkeypatch.setattr(gpumap.pipeline.workers, "host_gpus", lambda: ["0", "1"])
    assert all(_in_process(ns(backend=b)) for b in ("auto", "warp-cuda", "opencl-gpu", "opencl"))
    assert not _in_process(ns(workers=3))  # more workers than GPUs: Dask
    assert not _in_process(ns(scheduler="tcp://h:8786"))
    assert not _in_process(ns(backend="numpy")) and not _in_process(ns(backend="warp-cpu"))
    monkeypatch.setattr(gpumap.pipeline.workers, "host_gpus", lambda: [])
    assert not _in_process(ns())


@pytest.mark.parametrize("backend", ["numpy", "warp-cpu", "opencl-cpu"])
def test_blocks_move_by_runs_in_the_order_asked(backend):
    """read_blocks / write_blocks of some blocks (unsorted, in runs and apart) move exactly those."""
    if backend not in gpumap.available_backends():
        pytest.skip(f"{backend} is not available here")
    from test_mapper import SPEC

    from gpumap.backends import make_backend

    b = make_backend(backend, SPEC, visible=True, B=4, Bz=4, cap=12)
    rng = np.random.default_rng(3)
    slots = np.array([7, 2, 3, 4, 11, 0], np.int64)  # runs 0 | 2-4 | 7 | 11, asked out of order
    g = rng.random((6, b.BV), dtype=np.float32)
    br = rng.random((6, b.BV), dtype=np.float32)
    c = rng.integers(0, 2**63, (6, b.BV), dtype=np.uint64)
    before = b.read()
    b.write_blocks(slots, g, br, c)
    got = b.read_blocks(slots)
    for want, have in zip((g, br, c), got, strict=True):
        np.testing.assert_array_equal(have, want)
    after = b.read()
    others = np.setdiff1d(np.arange(12), slots)
    for x, y in zip(before, after, strict=True):  # the other blocks are as they were
        np.testing.assert_array_equal(x.reshape(12, -1)[others], y.reshape(12, -1)[others])
    assert b.read_seen()[slots].all() and not b.read_seen()[others].any()
    assert all(a.shape == (0, b.BV) for a in b.read_blocks(np.zeros(0, np.int64)))


@pytest.mark.parametrize("rule", ["evidence", "visible", "plain"])
def test_blocks_both_maps_observed_combine_in_chunks_as_in_one_call(rule, monkeypatch):
    import gpumap.pipeline.gpu_threads as gt
    from gpumap.core.rules import combine_into

    rng = np.random.default_rng(5)
    n, bv = 100, 64

    def arrays():
        out = {"min_all": rng.random((n, bv), dtype=np.float32)}
        if rule != "plain":
            out["bright"] = rng.random((n, bv), dtype=np.float32)
            out["count"] = rng.integers(0, 2**63, (n, bv), dtype=np.uint64)
        return out

    mine, theirs = arrays(), arrays()
    whole = {k: v.copy() for k, v in mine.items()}
    combine_into(whole, theirs, rule)
    monkeypatch.setattr(gt, "COMBINE_THREADS", 4)  # 4 chunks of 25 rows
    gt._combine_rows(mine, theirs, rule)
    for k in whole:
        np.testing.assert_array_equal(mine[k], whole[k], err_msg=k)


@needs_data
def test_dense_merge_block_by_block_equals_the_merge_of_states():
    from gpumap.pipeline.gpu_threads import merge_dense

    rec = tank(3)
    from gpumap.spec import auto_grid

    frames = [(f.image, f.T_W_S) for f in rec]
    spec = next(iter(rec)).spec
    grid = auto_grid(spec, [T for _, T in frames], 0.06)
    backend = "warp-cpu" if "warp-cpu" in gpumap.available_backends() else "numpy"
    maps = []
    for part in (frames[::2], frames[1::2]):  # every other frame: maps that overlap everywhere
        m = gpumap.MinMaxMapper(spec, grid, backend=backend)
        m.integrate_batch(np.stack([i for i, _ in part]), np.stack([T for _, T in part]))
        maps.append(m)
    want = gpumap.merge_maps(maps, backend="numpy")
    merge_dense(maps[0], maps[1])
    assert_same(maps[0], want)
    with pytest.raises(ValueError, match="different pings"):
        merge_dense(maps[0], want)
