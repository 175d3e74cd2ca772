"""Workers (Dask): a recording mapped in N workers and merged is the one-process map, bit for bit.

Reference: :func:`gpumap.pipeline.replay.run_replay` in this process on the same frames and grid (itself
tested against the NumPy oracle); the cluster is a threads-only LocalCluster (fast to start).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import DATA, needs_data
from merged_maps import assert_same, tank

pytest.importorskip("distributed")

from distributed import Client, LocalCluster  # noqa: E402

import gpumap  # noqa: E402
from gpumap.commands.replay import main  # noqa: E402
from gpumap.pipeline.replay import run_replay  # noqa: E402
from gpumap.pipeline.workers import run_replay_workers  # noqa: E402


@pytest.fixture(scope="module")
def cluster():
    with LocalCluster(n_workers=3, threads_per_worker=1, processes=False,
                      dashboard_address=":0") as c:
        with Client(c) as client:
            yield c, client


@needs_data
@pytest.mark.parametrize("backend", ["numpy", "warp-cpu"])
@pytest.mark.parametrize("rule", ["evidence", "visible", "plain"])
def test_workers_equal_one_process_on_real_frames(cluster, backend, rule):
    if backend not in gpumap.available_backends():
        pytest.skip(f"{backend} is not available here")
    _, client = cluster
    rec = tank(3)
    kw = dict(voxel_size_m=0.06, backend=backend, rule=rule, progress=False)
    one, s1 = run_replay(rec, **kw)
    assert one.observed().sum() > 10_000
    pos: list = []
    for n, split in ((2, "space"), (3, "pings")):
        got, s = run_replay_workers(rec, workers=n, client=client, positions=pos if n == 2 else None,
                                    split=split, **kw)
        assert got.grid == one.grid and s["frames"] == s1["frames"] == 41
        assert s["workers"] == n and s["split"] == split
        # space: shares of equal work by place (every frame here sees about as much of the grid);
        # pings: batches of 32 in turn
        got_frames = sorted((p["frames"] for p in s["per_worker"]), reverse=True)
        if split == "space":
            assert sum(got_frames) == 41 and got_frames[0] - got_frames[1] <= 5
        else:
            assert got_frames == [32, 9, 0]
        assert_same(got, one)
    assert len(pos) == 41


@needs_data
def test_sparse_workers_equal_the_dense_one_process_map(cluster):
    _, client = cluster
    rec = tank(4)
    one, _ = run_replay(rec, voxel_size_m=0.06, backend="numpy", progress=False)
    got, s = run_replay_workers(rec, workers=2, client=client, voxel_size_m=0.06, backend="numpy",
                                progress=False, sparse=True)
    assert got.sparse is not None and got.grid == one.grid
    assert_same(got, one)


@needs_data
def test_replay_cli_workers_writes_the_same_map(cluster, tmp_path: Path, capsys):
    c, _ = cluster
    common = [str(DATA / "oasis_tank"), "--stride", "6", "--no-progress", "--no-pictures",
              "--voxel-size", "0.08", "--backend", "numpy"]
    assert main([*common, "--out", str(tmp_path / "one")]) == 0
    capsys.readouterr()
    assert main([*common, "--out", str(tmp_path / "w"), "--workers", "2",
                 "--scheduler", c.scheduler_address]) == 0
    assert "21 images in 2 Dask workers on numpy" in capsys.readouterr().out  # the line says how it ran
    a = gpumap.load_map(tmp_path / "one" / "map.npz", backend="numpy")
    b = gpumap.load_map(tmp_path / "w" / "map.npz", backend="numpy")
    assert_same(b, a)
    s = json.loads((tmp_path / "w" / "summary.json").read_text())
    assert s["workers"] == 2 and s["frames"] == 21 and s["scheduler"] == c.scheduler_address
    assert (tmp_path / "w" / "occupied.ply").read_bytes() == (tmp_path / "one" / "occupied.ply").read_bytes()


def test_worker_flags_are_checked_before_any_work(tmp_path: Path, capsys):
    out = str(tmp_path / "o")
    for argv, word in ((["--scheduler", "tcp://127.0.0.1:1"], "--workers"),
                       (["--workers", "2", "--ekf"], "--ekf"),
                       (["--workers", "0"], "--workers")):
        with pytest.raises(SystemExit) as e:
            main(["missing_recording", "--out", out, *argv])
        assert e.value.code == 2 and word in capsys.readouterr().err
    assert not Path(out).exists()


def test_simulated_byte_frames_travel_as_uint8_and_map_the_same(cluster):
    """Frames that are bytes / 255 (8-bit sonars) are sent as uint8; the map is still the same."""
    from test_mapper import SPEC
    from test_visibility import _random_pings

    from gpumap.backends import U8_SCALE
    from gpumap.io import Recording, SonarFrame
    from gpumap.pipeline.workers import _compact

    _, client = cluster
    frames = []
    for k, (img, T) in enumerate(_random_pings(70, 5)):  # dark water, then returns and shadows
        b = np.rint(img * 255).astype(np.uint8)
        frames.append(SonarFrame(np.multiply(b, U8_SCALE, dtype=np.float32), SPEC, float(k), T))
    imgs = np.stack([f.image for f in frames])
    assert _compact(imgs).dtype == np.uint8
    nudged = imgs.copy()
    nudged[0, 0, 0] = np.nextafter(nudged[0, 0, 0], np.float32(1))  # no longer a byte / 255
    assert _compact(nudged).dtype == np.float32
    rec = Recording("sim", "sim", lambda: iter(frames), True, count=lambda: len(frames))
    one, _ = run_replay(rec, voxel_size_m=0.07, backend="numpy", progress=False, threshold=0.1)
    got, s = run_replay_workers(rec, workers=3, client=client, voxel_size_m=0.07, backend="numpy",
                                progress=False, threshold=0.1, pack=True, split="pings")
    assert [p["frames"] for p in s["per_worker"]] == [32, 32, 6]
    # the maps of byte pings travel packed (uint8 + a bit per voxel for unknown)
    assert all(p["state_mb"] < 0.4 * p["state_mb_unpacked"] for p in s["per_worker"])
    assert one.evidence()["count"].max() >= 2
    assert_same(got, one)


def test_state_packing_is_exact_or_not_used():
    from gpumap.core.merge import MapState
    from gpumap.pipeline.workers import _pack, _unpack

    rng = np.random.default_rng(0)
    b = rng.integers(0, 256, (40, 512)).astype(np.uint8)
    byte = np.multiply(b, np.float32(1 / 255), dtype=np.float32)
    byte[rng.random(byte.shape) < 0.3] = np.inf
    other = byte.copy()
    other[3, 7] = np.float32(0.3)  # 0.3 is no byte / 255
    count = rng.integers(0, 256, byte.shape).astype(np.uint8)
    st = MapState("sparse", {}, 7, {"min_all": byte, "bright": other, "count": count})
    packed = _pack(st)
    kinds = {k: a[0] for k, a in packed[3].items()}
    assert kinds == {"min_all": "u8", "bright": "f32", "count": "bytes"}
    assert packed[3]["min_all"][3].size == np.isfinite(byte).sum()  # the observed entries only
    for ref, wire in ((st, packed), (st, _pack(st, pack=False))):
        back = _unpack(wire)
        assert back.n_integrated == ref.n_integrated and back.kind == ref.kind
        for k in ref.arrays:
            assert back.arrays[k].dtype == ref.arrays[k].dtype and back.arrays[k].shape == ref.arrays[k].shape
            assert back.arrays[k].tobytes() == ref.arrays[k].tobytes(), k


def test_space_split_cuts_the_ranking_into_runs_of_equal_work():
    """Frames ranked along the grid's long axis and cut where the work (voxels of each frame's
    box inside the grid) is even: frames looking mostly outside the grid weigh little, so their
    worker takes more of them; every worker's frames are one run of the ranking."""
    from gpumap.pipeline.workers import _space_owners

    spec = gpumap.SonarSpec.uniform(hfov_deg=120, vfov_deg=20, n_beams=64, n_bins=50,
                                    range_min_m=0.1, range_max_m=2.0)
    grid = gpumap.GridSpec((0.0, -2.0, -1.0), (20.0, 2.0, 1.0), 0.1)
    R = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])  # boresight down
    poses = []
    for x in np.linspace(1.0, 19.0, 40):
        T = np.eye(4)
        T[:3, :3] = R
        # the first half looks at the grid from just above it, the second from 1.5 m higher:
        # their fans reach into the grid's 1 m of height far less
        T[:3, 3] = (x, 0.0, 1.2 if x < 10 else 2.7)
        poses.append(T)
    owners = _space_owners(spec, poses, grid, 2)
    assert np.all(np.diff(owners) >= 0)  # runs along the axis, in order
    n0, n1 = np.bincount(owners, minlength=2)
    assert n1 > n0 + 5  # the light frames (high up) go together, more of them
    owners3 = _space_owners(spec, poses + [None], grid, 3)
    assert owners3[-1] == 0 and set(owners3[:-1]) == {0, 1, 2}



@needs_data
def test_asking_more_workers_than_the_cluster_has_says_how_many(cluster, monkeypatch):
    import gpumap.pipeline.workers

    monkeypatch.setattr(gpumap.pipeline.workers, "WAIT_WORKERS_S", 0.2)
    _, client = cluster
    with pytest.raises(ValueError, match="Expected 5 Dask workers, but the cluster has 3"):
        run_replay_workers(tank(6), workers=5, client=client, voxel_size_m=0.06, backend="numpy",
                           progress=False)


def test_one_gpu_per_worker_by_rank_on_its_host(monkeypatch):
    """--workers over the GPUs of a machine: a worker's rank among the workers of its host picks its
    GPU (modulo the host's GPUs), set in CUDA_VISIBLE_DEVICES before CUDA starts; a host without GPUs
    leaves the variable alone."""
    from gpumap.pipeline import workers

    addrs = ["tcp://10.0.0.2:4001", "tcp://10.0.0.1:4000", "tcp://10.0.0.2:4002", "tcp://10.0.0.1:4003",
             "inproc://10.0.0.9/1/2"]
    assert workers.host_ranks(addrs) == [0, 0, 1, 1, 0]
    monkeypatch.setattr(workers, "_cuda_started", lambda: False)
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "2,3")  # the GPUs this process may use
    assert workers.host_gpus() == ["2", "3"]
    assert workers.pin_gpu(3) == "3"
    import os

    assert os.environ["CUDA_VISIBLE_DEVICES"] == "3"
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "")  # none
    assert workers.host_gpus() == [] and workers.pin_gpu(0) is None
    monkeypatch.delenv("CUDA_VISIBLE_DEVICES")
    monkeypatch.setattr(workers.os, "listdir", lambda p: ["0000:1b:00.0", "0000:43:00.0"])
    assert workers.host_gpus() == ["0", "1"]
    assert workers.pin_gpu(1) == "1"
    monkeypatch.setattr(workers, "_cuda_started", lambda: True)  # too late: the variable says nothing
    monkeypatch.delenv("CUDA_VISIBLE_DEVICES")
    assert workers.pin_gpu(0) is None and "CUDA_VISIBLE_DEVICES" not in os.environ
    with pytest.raises(ValueError, match="gpus"):
        run_replay_workers(None, workers=1, gpus="all", static=True)


@needs_data
def test_frames_carrying_their_bytes_are_sent_as_bytes(cluster):
    """A reader that keeps a frame's bytes (meta FRAME_BYTES, image == bytes / 255 in float32) has
    the client send those (a quarter of the data, no pass to find them): the same map."""
    from gpumap.backends import U8_SCALE
    from gpumap.io import Recording, SonarFrame
    from gpumap.pipeline.workers import FRAME_BYTES

    _, client = cluster
    src = list(tank(6))
    u8 = [np.round(f.image * 255).astype(np.uint8) for f in src]
    flt = [np.multiply(b, U8_SCALE, dtype=np.float32) for b in u8]

    def frames(with_bytes: bool):
        return [SonarFrame(flt[i], f.spec, None, f.T_W_S, {FRAME_BYTES: u8[i]} if with_bytes else {})
                for i, f in enumerate(src)]

    recs = [Recording("tank", "arrays", lambda w=w: iter(frames(w)), True, count=lambda: len(src))
            for w in (False, True)]
    kw = dict(voxel_size_m=0.06, backend="numpy", progress=False)
    one, _ = run_replay(recs[0], **kw)
    for rec in recs:
        got, s = run_replay_workers(rec, workers=2, client=client, **kw)
        assert s["frames"] == len(src)
        assert_same(got, one)
