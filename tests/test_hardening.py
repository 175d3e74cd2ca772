"""What a careless user and a hostile wire found (issue 31): each fix, checked by what it promises."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import DATA, needs_data
from test_mapper import GRID, SPEC
from test_visibility import _random_pings

import gpumap
from gpumap.core.merge import load_map, merge_maps
from gpumap.core.params import MapperParams


def _map(pings, backend="numpy"):
    m = gpumap.MinMaxMapper(SPEC, GRID, backend, MapperParams(threshold=0.1))
    for img, T in pings:
        m.integrate(img, T)
    return m


# ------------------------------------------------------------------ 2. merging maps that share pings
def test_maps_sharing_pings_are_refused_naming_the_files_and_the_count(tmp_path) -> None:
    pings = _random_pings(6, 3)
    full, half, other = _map(pings), _map(pings[:3]), _map(pings[3:])
    full.save(tmp_path / "full.npz")
    half.save(tmp_path / "half.npz")
    other.save(tmp_path / "other.npz")
    with pytest.raises(ValueError, match=r"half\.npz.* and .*full\.npz.* share 3 pings"):
        merge_maps([tmp_path / "full.npz", tmp_path / "half.npz"], backend="numpy")
    # disjoint halves still merge, and the merged map knows all six pings
    m = merge_maps([tmp_path / "half.npz", tmp_path / "other.npz"], backend="numpy")
    assert m.n_integrated == 6 and len(m.pings) == 6
    np.testing.assert_array_equal(m.raw_values(), full.raw_values())
    # so a merged map then refuses a map of one of its pings, and the fingerprints survive a file
    m.save(tmp_path / "merged.npz")
    assert len(load_map(tmp_path / "merged.npz", backend="numpy").pings) == 6
    with pytest.raises(ValueError, match="share 1 pings"):
        merge_maps([tmp_path / "merged.npz", _map(pings[4:5])], backend="numpy")


def test_fingerprints_follow_the_ping_not_the_call(tmp_path) -> None:
    """integrate and integrate_batch, uint8 or not: the same ping has the same fingerprint; another
    pose or image another; reset forgets them."""
    pings = _random_pings(3, 4)
    a = _map(pings)
    b = gpumap.MinMaxMapper(SPEC, GRID, "numpy", MapperParams(threshold=0.1))
    b.integrate_batch(np.stack([p[0] for p in pings]), np.stack([p[1] for p in pings]))
    np.testing.assert_array_equal(a.pings.array(), b.pings.array())
    assert len(set(a.pings.array().tolist())) == 3
    moved = pings[0][1].copy()
    moved[0, 3] += 1e-3
    c = _map([(pings[0][0], moved)])
    assert a.pings.shared(c.pings.array()) == 0
    a.reset()
    assert len(a.pings) == 0


@needs_data
def test_replay_frames_split_a_recording_that_merge_then_joins(tmp_path) -> None:
    """gpumap replay --frames: two halves of the OASIS tank merge into the whole; the whole and a
    half do not."""
    rec = str(DATA / "oasis_tank")
    common = ["--max-frames", "6", "--voxel-size", "0.1", "--backend", "numpy", "--no-pictures",
              "--no-progress", "--grid=-1,-2,-1.6,2.5,2.2,1.4"]
    from gpumap.commands import main

    assert main(["replay", rec, "--frames", "0:12:2", "--out", str(tmp_path / "full"), *common]) == 0
    assert main(["replay", rec, "--frames", "0:6:2", "--out", str(tmp_path / "a"), *common]) == 0
    assert main(["replay", rec, "--frames", "6:12:2", "--out", str(tmp_path / "b"), *common]) == 0
    assert json.loads((tmp_path / "a" / "summary.json").read_text())["frames"] == 3
    full = load_map(tmp_path / "full" / "map.npz", backend="numpy")
    out = tmp_path / "m.npz"
    assert main(["merge", str(out), str(tmp_path / "a" / "map.npz"), str(tmp_path / "b" / "map.npz")]) == 0
    np.testing.assert_array_equal(load_map(out, backend="numpy").raw_values(), full.raw_values())
    r = subprocess.run([sys.executable, "-m", "gpumap.commands", "merge", str(out),
                        str(tmp_path / "full" / "map.npz"), str(tmp_path / "a" / "map.npz")],
                       capture_output=True, text=True)
    assert r.returncode == 2, r.stderr
    assert "share 3 pings" in r.stderr and "full" in r.stderr and "Traceback" not in r.stderr


@pytest.mark.parametrize("bad", ["5", "3:2", "-1:4", "1:4:0", "a:b", "1:2:3:4"])
def test_replay_frames_refuses_what_is_not_a_range(bad, capsys) -> None:
    from gpumap.commands import main

    with pytest.raises(SystemExit) as e:
        main(["replay", "nowhere", "--frames", bad])
    assert e.value.code == 2
    assert "--frames" in capsys.readouterr().err


# ------------------------------------------------------------------ 1. memory: honest model, bounded
def test_replay_pictures_colour_the_occupied_box_not_the_grid(tmp_path, monkeypatch) -> None:
    """views.png colours and meshes only the occupied voxels' box (colour_voxels takes ~60 bytes a
    voxel: over a 864 M-voxel grid that alone was 50 GB), with the same geometry in the world."""
    import gpumap.io.pictures as render

    grid = gpumap.GridSpec((0.0, 0.0, 0.0), (10.0, 10.0, 5.0), 0.05)
    values = np.full(grid.shape, np.nan, np.float32)
    values[90:110, 95:100, 10:14] = 0.8
    seen = {}
    colour, faces = render.colour_voxels, render.exposed_faces_mesh

    def colour_voxels(v, occ, *a, **k):
        seen["colour"] = v.shape
        return colour(v, occ, *a, **k)

    def exposed_faces_mesh(occ, col, origin, vs):
        seen["mesh"] = faces(occ, col, origin, vs)
        return seen["mesh"]

    monkeypatch.setattr(render, "colour_voxels", colour_voxels)
    monkeypatch.setattr(render, "exposed_faces_mesh", exposed_faces_mesh)
    monkeypatch.setattr(render, "render_voxels", lambda *a, **k: np.zeros((4, 4, 3), np.uint8))
    render.replay_views(tmp_path / "views.png", values, grid, 0.4)
    assert seen["colour"] == (20, 5, 4)
    pos = seen["mesh"][0]
    np.testing.assert_allclose(pos.min(0), [4.5, 4.75, 0.5], atol=1e-5)  # the box's faces, in metres
    np.testing.assert_allclose(pos.max(0), [5.5, 5.0, 0.7], atol=1e-5)


# ------------------------------------------------------------------ 3. the ROS node
def _live():
    from test_ros import SMALL_GRID, SMALL_SPEC, _small_pings

    from gpumap.ros.live import LiveMapper

    m = gpumap.MinMaxMapper(SMALL_SPEC, SMALL_GRID, backend="numpy")
    return LiveMapper(m, queue_size=64), _small_pings(4)


def test_one_image_from_the_near_future_does_not_refuse_the_pings_after_it() -> None:
    live, (imgs, _) = _live()
    s = 1_000_000_000
    now = 100 * s
    assert live.add_ping(now, imgs[0], now)
    assert live.add_ping(now + 9 * s // 10, imgs[1], now + s // 100)  # 0.9 s ahead of the clock
    for k in range(1, 18):  # the next 17 good pings, at 20 Hz, all before the bad stamp
        assert live.add_ping(now + k * s // 20, imgs[2], now + k * s // 20), k
    assert not live.rejected
    assert not live.add_ping(now + 9 * s // 10, imgs[1], now + s)  # the same stamp again: refused
    assert not live.add_ping(now + s // 20, imgs[2], now + s)  # and an old one
    assert live.rejected == {"image_out_of_order": 2}


def test_diagnostics_level_follows_the_share_of_messages_lost() -> None:
    from gpumap.ros.live import health

    def st(received, rejected=0, dropped=0):
        return {"received": received, "integrated": received - rejected, "skipped": {},
                "rejected": {"image_values": rejected}, "dropped": {"middleware_lost": dropped}}

    assert health(None, st(100))[0] == "OK"
    assert health(st(100), st(200, rejected=1))[0] == "OK"  # 1 % of the period
    level, text = health(st(100), st(200, rejected=30))
    assert level == "WARN" and "30 of 100" in text
    assert health(st(100), st(140, dropped=60))[0] == "ERROR"  # 60 of the 100 that came were lost
    assert health(st(100, rejected=50), st(200, rejected=50))[0] == "OK"  # an old burst is over
    assert health(None, st(10), RuntimeError("boom"))[0] == "ERROR"


def test_absurd_finite_poses_are_refused() -> None:
    from types import SimpleNamespace

    from gpumap import limits
    from gpumap.errors import _MAX_POSITION_M, check_pose
    from gpumap.ros.convert import BadMessage, transform_from_pose

    assert limits.MAX_POSITION_M == _MAX_POSITION_M
    T = np.eye(4)
    T[0, 3] = 1e200
    with pytest.raises(ValueError, match="1e\\+200"):
        check_pose(T)
    with pytest.raises(BadMessage) as e:
        transform_from_pose(SimpleNamespace(x=1e200, y=0.0, z=0.0),
                            SimpleNamespace(x=0.0, y=0.0, z=0.0, w=1.0))
    assert e.value.reason == "pose_out_of_range"
    m = gpumap.MinMaxMapper(SPEC, GRID, backend="numpy")
    with pytest.raises(ValueError, match="position"):
        m.integrate(np.zeros(SPEC.image_shape, np.float32), T)
    assert m.n_integrated == 0


def test_user_parameters_win_over_the_params_file(tmp_path) -> None:
    pytest.importorskip("rclpy")
    import rclpy

    from gpumap.ros.launch import ros_arguments

    f = tmp_path / "node.yaml"
    f.write_text("/**:\n  ros__parameters:\n    voxel_size_m: 0.05\n    backend: opencl\n")
    args = ros_arguments(f, ["--ros-args", "-p", "backend:=numpy", "-p", "voxel_size_m:=0.1"])
    ctx = rclpy.Context()
    rclpy.init(args=["gpumap_ros", *args], context=ctx)
    try:
        node = rclpy.create_node("gpumap", context=ctx)
        assert node.declare_parameter("voxel_size_m", 0.2).value == 0.1
        assert node.declare_parameter("backend", "auto").value == "numpy"
        node.destroy_node()
    finally:
        rclpy.shutdown(context=ctx)
    assert ros_arguments(f, []) == ["--ros-args", "--params-file", str(f)]


# ------------------------------------------------------------------ 4. messages name only what exists
def _flags(parser) -> set[str]:
    return {o for act in parser._actions for o in act.option_strings}


@needs_data
def test_refine_grid_error_names_only_refine_flags(capsys) -> None:
    import re

    from gpumap.commands import main
    from gpumap.commands.refine import _parser

    rc = main(["refine", str(DATA / "oasis_tank"), "--voxel-size", "0.002", "--max-frames", "3",
               "--no-progress", "--out", "/nonexistent-never-written"])
    err = capsys.readouterr().err
    assert rc == 2 and "automatic grid" in err, err
    named = set(re.findall(r"--[a-z][a-z-]+", err))
    assert named and named <= _flags(_parser()), named - _flags(_parser())


def test_view_without_the_viewer_names_no_flag_it_lacks(monkeypatch, capsys, tmp_path) -> None:
    import importlib.util

    from gpumap.commands import view as vcli

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name, *a: None if name == "viser" else real(name, *a))
    (tmp_path / "map.npz").write_bytes(b"")
    with pytest.raises(SystemExit) as e:
        vcli.main([str(tmp_path / "map.npz")])
    err = capsys.readouterr().err
    assert e.value.code == 2 and "pip install 'gpumap[viewer]'" in err and "--view:" not in err
    assert "after the run" not in vcli._parser().format_help()


@pytest.mark.parametrize("content", [b"not a zip at all", None])
def test_export_and_merge_say_what_is_wrong_with_a_map_file_in_words(content, tmp_path) -> None:
    import zipfile

    bad = tmp_path / "bad.npz"
    if content is None:  # a zip archive without gpumap's metadata
        with zipfile.ZipFile(bad, "w") as z:
            z.writestr("x.npy", b"1")
    else:
        bad.write_bytes(content)
    for argv in (["export", str(bad), str(tmp_path / "o.ply")], ["merge", str(tmp_path / "o.npz"), str(bad)]):
        r = subprocess.run([sys.executable, "-m", "gpumap.commands", *argv], capture_output=True, text=True)
        assert r.returncode == 2, r.stderr
        assert "Expected a gpumap map file" in r.stderr
        for raw in ("BadZipFile(", "KeyError(", "Traceback"):
            assert raw not in r.stderr, r.stderr


# ------------------------------------------------------------------ 5. silent or unhelpful
def _tank_copy(tmp_path, n=6):
    """The first ``n`` pictures of the OASIS tank and the pose table, in a folder of their own."""
    import shutil

    src = DATA / "oasis_tank"
    dst = tmp_path / "tank"
    (dst / "sonar").mkdir(parents=True)
    for f in sorted((src / "sonar").glob("*.png"))[:n]:
        shutil.copy(f, dst / "sonar" / f.name)
    shutil.copy(src / "sonar_poses.csv", dst / "sonar_poses.csv")
    return dst


_QUICK = ["--voxel-size", "0.1", "--backend", "numpy", "--no-pictures", "--no-progress"]


@needs_data
def test_a_grid_no_ping_sees_warns_and_exits_3(tmp_path, capsys) -> None:
    from gpumap.commands import main

    rc = main(["replay", str(_tank_copy(tmp_path, 3)), "--grid=100,100,100,101,101,101", *_QUICK,
               "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert rc == 3 and "no ping observed any voxel" in err and "--grid" in err
    assert json.loads((tmp_path / "out" / "summary.json").read_text())["observed_voxels"] == 0


@needs_data
def test_skip_bad_frames_skips_a_truncated_picture_and_counts_it(tmp_path, capsys) -> None:
    from gpumap.commands import main

    tank = _tank_copy(tmp_path)
    bad = sorted((tank / "sonar").glob("*.png"))[2]
    bad.write_bytes(bad.read_bytes()[: bad.stat().st_size // 2])
    assert main(["replay", str(tank), *_QUICK, "--out", str(tmp_path / "a")]) == 2
    assert bad.name in capsys.readouterr().err
    assert main(["replay", str(tank), *_QUICK, "--skip-bad-frames", "--out", str(tmp_path / "b")]) == 0
    out, err = capsys.readouterr()
    s = json.loads((tmp_path / "b" / "summary.json").read_text())
    assert s["frames"] == 5 and s["skipped_bad_frames"] == 1 and bad.name in s["bad_frames"][0]
    assert "skipped 1 unreadable frames" in out and bad.name in err


def test_bench_ends_with_what_it_keeps_up_with_and_names_its_folder(tmp_path, capsys) -> None:
    from gpumap.bench.sweep import write_result

    def row(backend, v, rate, kind="gpumap"):
        return {"kind": kind, "backend": backend, "method": "gather", "voxel_size_m": v, "images_per_s": rate}

    rows = [row("opencl-cpu", 0.05, 25.0), row("numpy", 0.05, 3.0), row("numpy", 0.03, 4.0),
            row("", 0.03, 900.0, kind="octomap")]
    write_result({"tag": "t", "rows": rows, "run": {"duration_s": 1.0}}, tmp_path / "res")
    out = capsys.readouterr().out
    assert str(tmp_path / "res") in out
    five = next(line for line in out.splitlines() if line.lstrip().startswith("5.0 cm"))
    assert "opencl-cpu" in five and "25.0" in five and "20 Hz" in five and "not 40 Hz" in five
    three = next(line for line in out.splitlines() if line.lstrip().startswith("3.0 cm"))
    assert "none of 5 Hz" in three


def test_auto_names_its_backend_once_a_process(monkeypatch, caplog) -> None:
    import logging

    import gpumap.core.mapper

    monkeypatch.setattr(gpumap.core.mapper, "_ANNOUNCED", set())
    with caplog.at_level(logging.INFO, logger="gpumap"):
        for _ in range(3):
            gpumap.MinMaxMapper(SPEC, GRID)
    said = [r for r in caplog.records if r.levelno == logging.INFO and "backend" in r.getMessage()]
    assert len(said) == 1


def test_images_lost_after_the_last_one_delivered_are_counted() -> None:
    pytest.importorskip("rclpy")
    from gpumap.ros.launch import lost_at_stream_end

    a, b = bytes(range(12)), bytes(range(1, 13))  # two participants (publishing processes)
    last = {a + b"\x00\x00\x01\x03": 117, b + b"\x00\x00\x01\x03": 40}
    assert lost_at_stream_end({}, last) == 0  # nobody said how many they sent
    assert lost_at_stream_end({a: 123}, last) == 6  # 118..123 never came
    assert lost_at_stream_end({a: 123, b: 40}, last) == 6
    assert lost_at_stream_end({bytes(12): 5}, last) == 5  # a publisher none of whose images came


# ------------------------------------------------------------------ 6. a fast suite
def test_a_run_restricted_to_some_backends_starts_no_other() -> None:
    """tests/mutants.py runs the suite's rule tests 21 times, each on one backend
    (GPUMAP_TEST_BACKENDS): conftest then probes that backend only, not Warp and OpenCL every time
    (starting Warp and building the OpenCL kernels took ~4 s of each run)."""
    code = ("import sys; sys.path.insert(0, 'tests'); import conftest; "
            "print(conftest._AVAILABLE, 'warp' in sys.modules, 'pyopencl' in sys.modules)")
    env = {**os.environ, "GPUMAP_TEST_BACKENDS": "numpy"}
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                       cwd=str(Path(__file__).resolve().parents[1]))
    assert r.stdout.split() == ["['numpy']", "False", "False"], r.stdout + r.stderr
