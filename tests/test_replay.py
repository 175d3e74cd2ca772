"""gpumap replay end to end, ROS bags written here with rosbags' writer, and the OASIS convention."""

from __future__ import annotations

import io
import json
import math
from pathlib import Path

import numpy as np
import pytest
from conftest import DATA, needs_data

import gpumap
from gpumap.commands.replay import main
from gpumap.io import open_recording, read_ply
from gpumap.io.fan import FanGeometry, open_fan_folder
from gpumap.io.oculus import encode_simple_ping
from gpumap.pipeline.replay import otsu_threshold, run_replay, run_rule_comparison
from gpumap.spec import auto_grid


# ------------------------------------------------------------------ replay on real data
@needs_data
def test_replay_oasis_writes_map_ply_pictures(tmp_path: Path, capsys) -> None:
    out = tmp_path / "out"
    rc = main([str(DATA / "oasis_tank"), "--stride", "4", "--out", str(out), "--no-progress",
               "--voxel-size", "0.08", "--threshold", "0.4", "--backend", "numpy"])
    assert rc == 0
    text = capsys.readouterr().out
    assert "images/s" in text
    s = json.loads((out / "summary.json").read_text())
    assert s["frames"] == 31 and s["images_per_s"] > 0 and s["threshold"] == 0.4
    assert s["occupied_voxels"] > 100
    for name in ("map.npz", "occupied.ply", "views.png", "floor_slice.png"):
        assert (out / name).stat().st_size > 0, name
    ply = read_ply(out / "occupied.ply")
    assert ply["x"].shape[0] == s["occupied_voxels"] and ply["intensity"].min() >= 0.4
    import gpumap

    m = gpumap.MinMaxMapper.load(out / "map.npz")
    assert m.grid.voxel_size_m == 0.08


def _meta(path: Path) -> dict:
    with np.load(path, allow_pickle=False) as z:
        return json.loads(str(z["meta"]))


@needs_data
def test_replay_rule_and_threshold_reach_the_mapper(tmp_path: Path) -> None:
    common = [str(DATA / "oasis_tank"), "--stride", "12", "--no-progress", "--no-pictures",
              "--voxel-size", "0.1", "--backend", "numpy"]
    for extra, rule, thr in (([], "evidence", 0.4), (["--rule", "plain"], "plain", 0.4),
                             (["--rule", "visible", "--threshold", "0.3"], "visible", 0.3)):
        out = tmp_path / "_".join(["r", *extra]).replace("-", "")
        assert main([*common, "--out", str(out), *extra]) == 0
        meta = _meta(out / "map.npz")
        assert (meta["rule"], meta["threshold"]) == (rule, pytest.approx(thr)), extra
        s = json.loads((out / "summary.json").read_text())
        assert (s["rule"], s["mapper_threshold"], s["threshold"]) == (rule, pytest.approx(thr), thr)
    # Otsu's threshold is known only after the run: the mapper counts bright from 0.4
    out = tmp_path / "auto"
    assert main([*common, "--out", str(out), "--threshold", "auto"]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert _meta(out / "map.npz")["threshold"] == pytest.approx(0.4)
    assert s["mapper_threshold"] == pytest.approx(0.4) and 0 < s["threshold"] < 1


def test_replay_rejects_bad_rule_settings(tmp_path: Path, capsys) -> None:
    with pytest.raises(SystemExit):
        main(["x", "--rule", "shadow"])
    bag = tmp_path / "bag2"
    _write_ros2_psi(bag, n=2)
    out = str(tmp_path / "o")
    # flags that do not go together are refused while parsing, before the recording is read
    with pytest.raises(SystemExit) as e:
        main([str(bag), "--out", out, "--no-progress", "--method", "template", "--rule", "visible"])
    assert e.value.code == 2 and "rule='plain'" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        main([str(bag), "--out", out, "--no-progress", "--threshold", "abc"])
    assert e.value.code == 2 and "--threshold" in capsys.readouterr().err
    assert not Path(out).exists()
    # the template method alone picks the plain rule
    assert main([str(bag), "--out", out, "--no-progress", "--no-pictures", "--method", "template",
                 "--backend", "numpy"]) == 0
    assert _meta(Path(out) / "map.npz")["rule"] == "plain"


@needs_data
def test_rules_on_real_frames_observe_alike_and_plain_occupied_stays_occupied(tmp_path: Path) -> None:
    """Every rule observes the same voxels; a voxel plain calls occupied (all its views bright)
    has the same value under the visible and evidence rules, so it is occupied there too; they
    only keep more."""
    rec = open_fan_folder(DATA / "oasis_tank", stride=3)
    runs, c = run_rule_comparison(rec, threshold=0.4, voxel_size_m=0.08, backend="numpy",
                                  progress=False)
    mp, sp = runs["plain"]
    assert set(runs) == {"plain", "visible", "evidence"} and sp["frames"] == 41
    vp = mp.values()
    obs = np.isfinite(vp)
    occ_p = obs & (vp >= np.float32(0.4))
    assert occ_p.sum() > 100
    for rule in ("visible", "evidence"):
        mv, sv = runs[rule]
        assert sv["rule"] == mv.rule == rule and sv["frames"] == 41 and mp.grid == mv.grid
        vv = mv.values()
        np.testing.assert_array_equal(np.isfinite(vp), np.isfinite(vv))
        occ_v = obs & (vv >= np.float32(0.4))
        assert not (occ_p & ~occ_v).any()  # plain-occupied => occupied under the rule
        assert np.all(vv[obs] >= vp[obs])  # the rule only ever keeps a bright value plain lowers
        kept = obs & (vv != vp)
        assert kept.any() and np.all(vv[kept] >= np.float32(0.4))
        np.testing.assert_array_equal(vv[occ_p], vp[occ_p])  # all views bright: same value
        # the rule's min over every view is the plain map, bit for bit
        saved = gpumap.MinMaxMapper.load(mv.save(tmp_path / f"{rule}.npz"), backend="numpy")
        np.testing.assert_array_equal(saved.evidence()["min_all"], mp.raw_values())
        assert c["rules"][rule]["occupied_voxels"] == int(occ_v.sum())
        assert c["rules"][rule]["observed_voxels"] == obs.sum()
    occ_v = obs & (runs["evidence"][0].values() >= np.float32(0.4))
    assert c["rule"] == "evidence" and c["observed_equal"] and c["rule_ge_plain"] and c["plain_only"] == 0
    assert c["rules"]["plain"]["occupied_voxels"] == int(occ_p.sum())
    assert c["rule_only"] == int((occ_v & ~occ_p).sum()) > 0
    assert c["occupied_both"] == int(occ_p.sum())
    assert c["rules"]["plain"]["observed_voxels"] == obs.sum()
    w = c["where"]
    assert sum(w["range_histogram"]["rule_only"]) == c["rule_only"]
    assert sum(w["height_histogram"]["both"]) == c["occupied_both"]
    assert "plain carved them" in c["text"]


@needs_data
def test_rule_comparison_writes_picture_and_figures(tmp_path: Path) -> None:
    from gpumap.io import open_recording
    from gpumap.pipeline.replay import DEFAULT_THRESHOLD, run_rule_comparison

    out = tmp_path / "out"
    assert main([str(DATA / "oasis_tank"), "--stride", "6", "--out", str(out), "--no-progress",
                 "--voxel-size", "0.1", "--backend", "numpy"]) == 0
    s = json.loads((out / "summary.json").read_text())
    runs, c = run_rule_comparison(open_recording(DATA / "oasis_tank", stride=6), threshold=DEFAULT_THRESHOLD,
                                  picture=tmp_path / "rules.png", voxel_size_m=0.1, backend="numpy",
                                  progress=False)
    assert s["rule"] == c["rule"] == "evidence" and c["picture"] == "rules.png"
    assert (tmp_path / "rules.png").stat().st_size > 10_000
    assert c["rules"]["evidence"]["occupied_voxels"] == s["occupied_voxels"]  # the command's map
    assert c["observed_equal"] and c["plain_only"] == 0 and c["rule_only"] > 0
    assert set(c["runs"]) == {"plain", "visible", "evidence"} and c["runs"]["plain"]["frames"] == s["frames"]
    assert _meta(out / "map.npz")["rule"] == "evidence"


@needs_data
def test_replay_refuses_recordings_without_poses(tmp_path: Path, capsys) -> None:
    path = DATA / "oculus" / "three_pings_8bit.raw"
    assert main([str(path), "--out", str(tmp_path / "a"), "--no-progress"]) == 2
    assert "mapping needs a pose" in capsys.readouterr().err
    assert main([str(path), "--static", "--out", str(tmp_path / "b"), "--no-progress",
                 "--no-pictures", "--voxel-size", "0.05", "--backend", "numpy"]) == 0
    s = json.loads((tmp_path / "b" / "summary.json").read_text())
    assert s["frames"] == 3 and s["observed_voxels"] > 0


def test_replay_reports_format_errors(tmp_path: Path, capsys) -> None:
    p = tmp_path / "bad.raw"
    p.write_bytes(encode_simple_ping(np.zeros((10, 4), np.uint8), [-10, 0, 5, 10], 0.01)[:-3])
    assert main([str(p), "--static", "--out", str(tmp_path / "o"), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "format error" in err and "byte" in err


def test_otsu_threshold_splits_two_modes() -> None:
    v = np.concatenate([np.full(1000, 0.1), np.full(100, 0.8), [np.nan]])
    assert 0.1 < otsu_threshold(v) <= 0.8


# ------------------------------------------------------------------ ROS bags
def _pose(t: float) -> tuple[np.ndarray, np.ndarray]:
    """Sonar moving along x and turning about z: (position, quaternion xyzw)."""
    yaw = 0.2 * t
    return np.array([0.5 * t, 0.1, -0.3]), np.array([0, 0, math.sin(yaw / 2), math.cos(yaw / 2)])


def _ros_types(ts):
    return (ts.types["std_msgs/msg/Header"], ts.types["builtin_interfaces/msg/Time"])


def _write_ros2_psi(path: Path, n: int = 4) -> list[np.ndarray]:
    from rosbags.rosbag2 import Writer

    from gpumap.io.rosbag import PSI, make_typestore

    ts = make_typestore(ros1=False)
    Header, Time = _ros_types(ts)
    PSIm = ts.types[PSI]
    Info = ts.types["marine_acoustic_msgs/msg/PingInfo"]
    Data = ts.types["marine_acoustic_msgs/msg/SonarImageData"]
    V3 = ts.types["geometry_msgs/msg/Vector3"]
    PS = ts.types["geometry_msgs/msg/PoseStamped"]
    Pose = ts.types["geometry_msgs/msg/Pose"]
    Pt = ts.types["geometry_msgs/msg/Point"]
    Q = ts.types["geometry_msgs/msg/Quaternion"]
    az = np.deg2rad(np.linspace(-45, 45, 24) + np.linspace(0, 1, 24) ** 2)  # uneven
    # message frame: z forward, x up, y starboard  ->  y_msg = -sin(az)
    dirs = [V3(x=0.0, y=float(-math.sin(a)), z=float(math.cos(a))) for a in az]
    ranges = (0.2 + 0.01 * (np.arange(60) + 0.5)).astype(np.float32)
    rng = np.random.default_rng(5)
    imgs = []
    with Writer(path, version=9) as w:
        ci = w.add_connection("/sonar/image", PSI, typestore=ts)
        cp = w.add_connection("/sonar/pose", "geometry_msgs/msg/PoseStamped", typestore=ts)
        for k in range(2 * n + 1):  # poses at twice the image rate, bracketing the images
            t = 0.5 * k
            p, q = _pose(t)
            msg = PS(header=Header(stamp=Time(sec=int(t), nanosec=int((t % 1) * 1e9)),
                                   frame_id="world"),
                     pose=Pose(position=Pt(x=p[0], y=p[1], z=p[2]),
                               orientation=Q(x=q[0], y=q[1], z=q[2], w=q[3])))
            w.write(cp, int(t * 1e9), ts.serialize_cdr(msg, "geometry_msgs/msg/PoseStamped"))
        for k in range(n):
            t = 0.25 + 1.0 * k
            img = rng.integers(0, 65535, size=(60, 24), dtype=np.uint16)
            imgs.append(img)
            msg = PSIm(
                header=Header(stamp=Time(sec=int(t), nanosec=int((t % 1) * 1e9)), frame_id="sonar"),
                ping_info=Info(frequency=1.2e6, sound_speed=1500.0,
                               tx_beamwidths=np.zeros(0, np.float32),
                               rx_beamwidths=np.zeros(0, np.float32)),
                beam_directions=dirs, ranges=ranges,
                image=Data(is_bigendian=False, dtype=2, beam_count=24,
                           data=img.astype("<u2").view(np.uint8).reshape(-1)))
            w.write(ci, int(t * 1e9), ts.serialize_cdr(msg, PSI))
    return imgs


def test_ros2_projected_sonar_image_with_pose_topic(tmp_path: Path) -> None:
    from scipy.spatial.transform import Rotation

    bag = tmp_path / "bag2"
    imgs = _write_ros2_psi(bag)
    rec = open_recording(bag)
    assert rec.kind == "rosbag" and rec.has_poses and rec.count() == 4
    frames = list(rec)
    assert len(frames) == 4
    for k, (f, img) in enumerate(zip(frames, imgs, strict=True)):
        # columns were already in ascending azimuth (beam 0 = starboard)
        np.testing.assert_array_equal(np.round(f.image * 65535).astype(np.uint16), img)
        b = np.rad2deg(f.spec.bearings_rad)
        assert b[0] == pytest.approx(-45.0, abs=1e-4) and b[-1] == pytest.approx(46.0, abs=1e-4)
        assert f.spec.bin_centers_m[0] == pytest.approx(0.205, abs=1e-6)
        t = 0.25 + k
        assert f.timestamp_s == pytest.approx(t)
        p, q = _pose(t)  # linear motion + constant yaw rate: interpolation is exact
        np.testing.assert_allclose(f.T_W_S[:3, 3], p, atol=1e-9)
        np.testing.assert_allclose(f.T_W_S[:3, :3], Rotation.from_quat(q).as_matrix(), atol=1e-9)


def test_ros1_oculus_ping_with_tf(tmp_path: Path) -> None:
    from PIL import Image
    from rosbags.rosbag1 import Writer

    from gpumap.io.rosbag import OCULUS_PING, make_typestore

    ts = make_typestore(ros1=True)
    Header, Time = _ros_types(ts)
    Ping = ts.types[OCULUS_PING]
    Fire = ts.types["sonar_oculus/msg/OculusFire"]
    CI = ts.types["sensor_msgs/msg/CompressedImage"]
    TFM = ts.types["tf2_msgs/msg/TFMessage"]
    TS = ts.types["geometry_msgs/msg/TransformStamped"]
    Tr = ts.types["geometry_msgs/msg/Transform"]
    V3 = ts.types["geometry_msgs/msg/Vector3"]
    Q = ts.types["geometry_msgs/msg/Quaternion"]
    bearings = np.array([-3000, -2900, -2750, -2500, 0, 2500, 2750, 2900, 3000], np.int16)
    rng = np.random.default_rng(6)
    imgs = []
    bag = tmp_path / "ping.bag"
    with Writer(bag) as w:
        ci = w.add_connection("/sonar_oculus_node/ping", OCULUS_PING, typestore=ts)
        ct = w.add_connection("/tf", "tf2_msgs/msg/TFMessage", typestore=ts)
        for k in range(3):
            t = 1.0 + k
            p, q = _pose(t)
            st = Time(sec=int(t), nanosec=0)
            tf = TFM(transforms=[
                TS(header=Header(seq=0, stamp=st, frame_id="odom"), child_frame_id="base",
                   transform=Tr(translation=V3(x=9.0, y=9.0, z=9.0), rotation=Q(x=0, y=0, z=0, w=1))),
                TS(header=Header(seq=0, stamp=st, frame_id="world"), child_frame_id="sonar",
                   transform=Tr(translation=V3(x=p[0], y=p[1], z=p[2]),
                                rotation=Q(x=q[0], y=q[1], z=q[2], w=q[3])))])
            w.write(ct, int(t * 1e9) - 1000, ts.serialize_ros1(tf, "tf2_msgs/msg/TFMessage"))
            img = rng.integers(0, 256, size=(40, 9), dtype=np.uint8)
            imgs.append(img)
            buf = io.BytesIO()
            Image.fromarray(img).save(buf, format="PNG")
            msg = Ping(header=Header(seq=k, stamp=st, frame_id="sonar"),
                       fire_msg=Fire(header=Header(seq=0, stamp=st, frame_id=""), mode=1, gamma=127,
                                     flags=25, range=2.0, gain=50.0, speed_of_sound=1500.0,
                                     salinity=0.0),
                       ping_id=k, part_number=0, start_time=0, bearings=bearings,
                       range_resolution=0.05, num_ranges=40, num_beams=9,
                       ping=CI(header=Header(seq=0, stamp=st, frame_id=""), format="png",
                               data=np.frombuffer(buf.getvalue(), np.uint8)))
            w.write(ci, int(t * 1e9), ts.serialize_ros1(msg, OCULUS_PING))
    rec = open_recording(bag, world_frame="world")
    assert rec.has_poses
    frames = list(rec)
    assert len(frames) == 3
    for k, (f, img) in enumerate(zip(frames, imgs, strict=True)):
        np.testing.assert_array_equal(np.round(f.image * 255).astype(np.uint8), img[:, ::-1])
        np.testing.assert_allclose(np.rad2deg(f.spec.bearings_rad), -bearings[::-1] / 100.0)
        assert f.spec.range_max_m == pytest.approx(2.0)
        np.testing.assert_allclose(f.T_W_S[:3, 3], _pose(1.0 + k)[0], atol=1e-9)
    # no world frame and no PoseStamped: no poses, and replay refuses
    rec2 = open_recording(bag)
    assert not rec2.has_poses
    with pytest.raises(ValueError, match="mapping needs a pose"):
        run_replay(rec2, progress=False)


def test_replay_on_a_ros2_bag(tmp_path: Path) -> None:
    bag = tmp_path / "bag2"
    _write_ros2_psi(bag, n=3)
    out = tmp_path / "out"
    assert main([str(bag), "--out", str(out), "--no-progress", "--no-pictures",
                 "--voxel-size", "0.05", "--backend", "numpy"]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["frames"] == 3 and s["backend"] == "numpy"


# ------------------------------------------------------------------ OASIS image convention
@needs_data
def test_oasis_documented_convention_beats_mirrored() -> None:
    """Views agree under the documented convention: more voxels survive the min over views.

    The plain rule's min over views is the consistency test; the visible rule keeps a bright
    value that a view from elsewhere disagrees with, so it cannot tell the conventions apart."""
    counts = {}
    for name, geom in [("documented", FanGeometry()), ("flip_lr", FanGeometry(flip_lr=True))]:
        rec = open_fan_folder(DATA / "oasis_tank", geom=geom, stride=3)
        frames = list(rec)
        grid = auto_grid(frames[0].spec, [f.T_W_S for f in frames], 0.08)
        mapper, _ = run_replay(frames_recording(rec, frames), grid=grid, progress=False,
                               backend="numpy", rule="plain")
        v = mapper.values()
        counts[name] = int((v[np.isfinite(v)] >= 0.4).sum())
    assert counts["documented"] > 1.3 * counts["flip_lr"], counts


def frames_recording(rec, frames):
    from gpumap.io.frame import Recording

    return Recording(rec.path, rec.kind, lambda: iter(frames), rec.has_poses, lambda: len(frames))
