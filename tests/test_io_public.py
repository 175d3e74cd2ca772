"""The public datasets as their authors ship them (issue 45): the OASIS tank folder, HoloOcean layouts.

- OASIS: a few of the real tank PNGs (``../shared/data/oasis_tank``) with a ``son_poses.pkl``
  written here in the authors' layout (a pickled list of 4 x 4 nested lists); the poses must
  equal ``sonar_poses.csv`` and the images the fan reader's, and mutated copies (counts, NaN,
  shapes, hostile pickles) must be refused in one line.
- HoloOcean: synthetic ``Config.json`` + ``Data/NNN.pkl`` folders. A point target is rendered
  into polar images the way HoloOcean's own source bins returns (Unreal's left-handed frame in
  centimetres, ``az = atan2(-y, x)`` in degrees, ``int((r - RangeMin) / RangeRes)``), from
  views rolled against each other so their elevation arcs cross; mapped with
  ``MinMaxMapper`` through the reader, the brightest voxels must sit on the target, and the
  same images with a flipped axis must not.
- The restricted unpickler is tested in ``tests/test_safe_pickle.py``.
"""

from __future__ import annotations

import json
import math
import pickle
import shutil
from pathlib import Path

import numpy as np
import pytest
from conftest import DATA, needs_data
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gpumap import GridSpec, MinMaxMapper
from gpumap.core.params import MapperParams
from gpumap.io import (
    FormatError,
    open_fan_folder,
    open_recording,
    reader_options,
    recording_kind,
)
from gpumap.io.fan import read_pose_table
from gpumap.io.holoocean import read_holoocean_config

FRAMES = (0, 10, 20, 30, 40)  # pictures of ../shared/data/oasis_tank (every 10th of the run)


class _Reduce:
    """Pickles as ``fn(*args)``: how a hostile pickle names a global to run."""

    def __init__(self, fn, args):
        self.fn, self.args = fn, args

    def __reduce__(self):
        return (self.fn, self.args)


def _one_line(e: pytest.ExceptionInfo) -> str:
    text = str(e.value)
    assert "\n" not in text, text
    return text


# ---------------------------------------------------------------- OASIS as shipped
def _csv_poses() -> dict[int, np.ndarray]:
    fr, _t, T = read_pose_table(DATA / "oasis_tank" / "sonar_poses.csv")
    return {int(k): T[i] for i, k in enumerate(fr)}


def _oasis_clone(root: Path, poses: object | None = None, *, frames=FRAMES) -> Path:
    """``root/data/tank``: the real PNGs of ``frames`` and a son_poses.pkl in the authors' layout."""
    tank = root / "data" / "tank"
    (tank / "sonar").mkdir(parents=True)
    for k in frames:
        name = f"image_{k:04d}.png"
        shutil.copy(DATA / "oasis_tank" / "sonar" / name, tank / "sonar" / name)
    if poses is None:  # as the authors wrote it: a list of 4 x 4 nested lists of floats, protocol 4
        csv = _csv_poses()
        poses = [csv[k].tolist() for k in frames]
    (tank / "son_poses.pkl").write_bytes(pickle.dumps(poses, protocol=4))
    return tank


@needs_data
def test_oasis_folder_as_shipped_gives_the_csv_poses_and_the_fan_readers_images(tmp_path):
    tank = _oasis_clone(tmp_path)
    csv = _csv_poses()
    assert recording_kind(tank) == recording_kind(tmp_path) == "oasis"
    for where in (tank, tmp_path):  # the tank folder, and the clone's root
        rec = open_recording(where)
        assert rec.kind == "oasis" and rec.has_poses and rec.count() == len(FRAMES)
        poses = rec.poses()
        frames = list(rec)
        for i, (k, f) in enumerate(zip(FRAMES, frames, strict=True)):
            np.testing.assert_array_equal(f.T_W_S, csv[k])  # the pickled floats are the CSV's
            np.testing.assert_array_equal(poses[i], csv[k])
            assert f.meta["frame"] == i and Path(f.meta["file"]).name == f"image_{k:04d}.png"
    ref = {f.meta["frame"]: f for f in open_fan_folder(DATA / "oasis_tank")}
    for k, f in zip(FRAMES, frames, strict=True):
        np.testing.assert_array_equal(f.image, ref[k].image)
        assert f.spec == ref[k].spec


@needs_data
def test_oasis_stride_and_the_project_csv_taking_precedence(tmp_path):
    tank = _oasis_clone(tmp_path)
    rec = open_recording(tank, stride=2)
    assert [f.meta["frame"] for f in rec] == [0, 2, 4] and rec.count() == 3
    shutil.copy(DATA / "oasis_tank" / "sonar_poses.csv", tank / "sonar_poses.csv")
    assert recording_kind(tank) == "fan-folder"  # the project's table, not the pickle
    assert [f.meta["frame"] for f in open_recording(tank)] == list(FRAMES)


@needs_data
def test_fan_folder_says_how_many_poses_came_for_how_many_pictures(tmp_path):
    tank = _oasis_clone(tmp_path)
    (tank / "son_poses.pkl").unlink()
    rec = open_recording(tank)
    assert rec.kind == "fan-folder" and not rec.has_poses
    assert rec.pose_note == "sonar_poses.csv is not there: none of the 5 pictures has a pose"
    lines = (DATA / "oasis_tank" / "sonar_poses.csv").read_text().splitlines()
    keep = [lines[0]] + [ln for ln in lines[1:] if int(ln.split(",")[0]) in (0, 30, 40)]
    (tank / "sonar_poses.csv").write_text("\n".join(keep) + "\n")
    rec = open_recording(tank)
    assert not rec.has_poses and rec.pose_note == (
        "sonar_poses.csv holds 3 poses for 5 pictures; 2 pictures have none (the first: image_0010.png)")
    assert open_fan_folder(DATA / "oasis_tank").pose_note is None


def _mutated_poses() -> dict[str, tuple[object, str]]:
    """The mutated pose lists, each with what its refusal says (the cases exist without the data too:
    collection must not need it)."""
    if DATA is None:
        good = [np.eye(4).tolist() for _ in FRAMES]
    else:
        csv = _csv_poses()
        good = [csv[k].tolist() for k in FRAMES]
    nan = list(good)
    nan[2] = [[math.nan] * 4] + good[2][1:]
    skew = list(good)
    skew[1] = (np.array(good[1]) * 1.1).tolist()
    skew[1][3] = [0.0, 0.0, 0.0, 1.0]
    return {
        "one pose short": (good[:4], "holds 4 poses for 5 pictures"),
        "one pose more": (good + good[:1], "holds 6 poses for 5 pictures"),
        "NaN pose": (nan, "pose 2 (of 5)"),
        "3 x 4 pose": (good[:3] + [good[3][:3]] + good[4:],
                       "pose 3 (of 5) to be 4 x 4, but it has shape (3, 4)"),
        "not rigid": (skew, "pose 1 (of 5)"),
        "a dict": ({"poses": good}, "expected a list of 4 x 4 poses, but the pickle holds a dict"),
        "a string pose": (good[:2] + ["abcd"] + good[3:], "pose 2 (of 5)"),
    }


@needs_data
@pytest.mark.parametrize("case", sorted(_mutated_poses()))
def test_oasis_mutated_poses_are_refused_in_one_line_saying_what_came(tmp_path, case):
    poses, says = _mutated_poses()[case]
    tank = _oasis_clone(tmp_path, poses)
    with pytest.raises(FormatError) as e:
        list(open_recording(tank))
    assert says in _one_line(e)


@needs_data
def test_oasis_hostile_pose_pickle_is_refused_without_running(tmp_path):
    import os

    marker = tmp_path / "ran"
    tank = _oasis_clone(tmp_path, _Reduce(os.system, (f"touch {marker}",)))
    with pytest.raises(FormatError) as e:
        open_recording(tank)
    assert "system" in _one_line(e) and "refused" in str(e.value)
    assert not marker.exists()
    pickle.loads((tank / "son_poses.pkl").read_bytes())  # the same bytes, unpickled as usual, do run
    assert marker.exists()


@needs_data
def test_oasis_corrupt_picture_ends_or_is_skipped_and_truncated_pickle_is_refused(tmp_path):
    tank = _oasis_clone(tmp_path)
    pic = tank / "sonar" / "image_0020.png"
    pic.write_bytes(pic.read_bytes()[:500])
    frames = []
    with pytest.raises(FormatError) as e:
        frames.extend(open_recording(tank))
    assert "image_0020.png" in _one_line(e) and len(frames) == 2
    bad: list[str] = []
    kw, stride = reader_options(tank, on_bad=lambda err: bad.append(str(err)))
    assert [f.meta["frame"] for f in open_recording(tank, **kw)] == [0, 1, 3, 4] and len(bad) == 1
    data = (tank / "son_poses.pkl").read_bytes()
    (tank / "son_poses.pkl").write_bytes(data[: len(data) // 2])
    with pytest.raises(FormatError) as e:
        open_recording(tank)
    assert "corrupt or truncated" in _one_line(e)


# ---------------------------------------------------------------- HoloOcean layout
SONAR_CFG = {"RangeBins": 100, "AzimuthBins": 64, "RangeMin": 0.5, "RangeMax": 3.0, "InitOctreeRange": 50,
             "Elevation": 20.0, "Azimuth": 60.0, "AddSigma": 0.15, "MultSigma": 0.2, "MultiPath": True}


def _config(sonar: dict | None = None, pose_mount: dict | None = None, extra: dict | None = None) -> dict:
    """A scenario in the layout of AONeuS's ``Config.json`` (pose sensor on the sonar's mount)."""
    mount = {"socket": "SonarSocket", "rotation": [0, 45, 0]}
    return {"simple_denoise": False, "ds_factor": 1.0, "name": "HoveringImagingSonar",
            "world": "SimpleUnderwater", "main_agent": "auv0", **(extra or {}),
            "agents": [{"agent_name": "auv0", "agent_type": "HoveringAUV", "sensors": [
                {"sensor_type": "OrientationSensor"},
                {"sensor_type": "PoseSensor", **(mount if pose_mount is None else pose_mount)},
                {"sensor_type": "IMUSensor", "socket": "IMUSocket", "Hz": 200},
                {"sensor_type": "ImagingSonar", **mount, "Hz": 10,
                 "configuration": SONAR_CFG if sonar is None else sonar}],
                "location": [-18, 16, -22], "rotation": [0.0, 0.0, 130.0]}]}


def _write_holoocean(root: Path, states: list, config: dict | None = None, protocol: int = 4) -> Path:
    (root / "Data").mkdir(parents=True)
    (root / "Config.json").write_text(json.dumps(config or _config(), indent=4))
    for i, s in enumerate(states):
        (root / "Data" / f"{i:03d}.pkl").write_bytes(pickle.dumps(s, protocol=protocol))
    return root


def _flip(v: np.ndarray) -> np.ndarray:
    """HoloOcean's client frame (right-handed, y left) <-> Unreal's (left-handed, y right)."""
    return np.array([v[0], -v[1], v[2]])


def _look_at(position: np.ndarray, aim: np.ndarray, roll_deg: float) -> np.ndarray:
    """``T_W_S`` (columns forward, left, up) of a sonar at ``position`` looking at ``aim``, rolled."""
    fwd = (aim - position) / np.linalg.norm(aim - position)
    left = np.cross([0.0, 0.0, 1.0], fwd)
    left /= np.linalg.norm(left)
    up = np.cross(fwd, left)
    c, s = math.cos(math.radians(roll_deg)), math.sin(math.radians(roll_deg))
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = fwd, c * left + s * up, -s * left + c * up, position
    return T


def _render_holoocean(T_W_S: np.ndarray, target_W: np.ndarray, cfg: dict) -> tuple[np.ndarray, tuple]:
    """The ImagingSonar image of one point target as HoloOcean bins it, and the cell (row, column).

    In Unreal's terms, as ``HolodeckSonar.cpp``/``ImagingSonar.cpp`` do: the sensor's forward,
    right and up axes (``Right = -Left``, y flipped), centimetres, ``az = atan2(-Y, X)`` in
    degrees from ``-Azimuth/2``, elevation the polar angle from up within ``90 -+ Elevation/2``.
    """
    fwd_ue, right_ue, up_ue = _flip(T_W_S[:3, 0]), _flip(-T_W_S[:3, 1]), _flip(T_W_S[:3, 2])
    d = _flip(target_W) * 100.0 - _flip(T_W_S[:3, 3]) * 100.0
    x, y, z = d @ fwd_ue, d @ right_ue, d @ up_ue
    r = math.sqrt(x * x + y * y + z * z)
    az = math.degrees(math.atan2(-y, x))
    elev = math.degrees(math.atan2(math.hypot(x, y), z))
    r_min, r_max = cfg["RangeMin"] * 100, cfg["RangeMax"] * 100
    assert r_min < r < r_max and abs(az) < cfg["Azimuth"] / 2 and abs(elev - 90) < cfg["Elevation"] / 2
    i = int((r - r_min) / ((r_max - r_min) / cfg["RangeBins"]))
    j = int((az + cfg["Azimuth"] / 2) / (cfg["Azimuth"] / cfg["AzimuthBins"]))
    img = np.zeros((cfg["RangeBins"], cfg["AzimuthBins"]), np.float32)
    img[i, j] = 1.0
    return img, (i, j)


TARGET = np.array([1.0, 0.5, -0.3])
VIEWS = ((np.array([-0.9, 0.1, -0.2]), 0.0), (np.array([0.8, 2.3, -0.1]), 90.0),
         (np.array([-0.4, 2.0, 0.5]), 45.0))  # (position, roll): elevation arcs that cross


def _views() -> list[np.ndarray]:
    aim = TARGET + np.array([0.08, -0.12, 0.05])  # off boresight: a flipped axis moves the return
    return [_look_at(p, aim, roll) for p, roll in VIEWS]


def _bright_centroid(root: Path, transform=lambda img: img) -> tuple[float, np.ndarray]:
    """Map the recording's frames (images through ``transform``); the map's maximum and where it is."""
    grid = GridSpec(tuple(TARGET - 0.2), tuple(TARGET + 0.2), voxel_size_m=0.02)
    rec = open_recording(root)
    mapper = None
    for f in rec:
        mapper = mapper or MinMaxMapper(f.spec, grid, "numpy", MapperParams(rule="plain"))
        mapper.integrate(transform(f.image), f.T_W_S)
    v = mapper.values()
    assert np.isfinite(v).all()  # every voxel is in every view: the min runs over all three
    top = np.argwhere(v >= v.max() - 1e-6)
    return float(v.max()), grid.centers(top).mean(axis=0)


def test_holoocean_views_put_a_point_target_at_one_world_point(tmp_path):
    poses = _views()
    states, cells = [], []
    for T in poses:
        img, cell = _render_holoocean(T, TARGET, SONAR_CFG)
        states.append({"PoseSensor": T.astype(np.float32), "ImagingSonar": (img * 255).astype(np.uint8)})
        cells.append(cell)
    root = _write_holoocean(tmp_path / "ds", states)
    assert recording_kind(root) == "holoocean"
    frames = list(open_recording(root))
    for f, T, (i, j) in zip(frames, poses, cells, strict=True):
        p_S = (np.linalg.inv(f.T_W_S) @ np.append(TARGET, 1.0))[:3]
        r, az, _el = f.spec.to_polar(p_S[None])[0]
        assert (int(f.spec.bin_index(np.array([r]))[0]), int(f.spec.beam_index(np.array([az]))[0])) == (i, j)
        np.testing.assert_allclose(f.T_W_S, T, atol=1e-6)
        assert f.image[i, j] == 1.0 and f.image.sum() == 1.0
    peak, at = _bright_centroid(root)
    assert peak == 1.0 and np.linalg.norm(at - TARGET) < 0.03, (peak, at)
    # the same images read with an axis flipped do not meet at the target: the check can fail
    for flip in (lambda img: img[:, ::-1].copy(), lambda img: img[::-1].copy()):
        peak, at = _bright_centroid(root, flip)
        assert peak < 1.0 or np.linalg.norm(at - TARGET) > 0.1, (peak, at)


def test_holoocean_config_geometry_is_holooceans_binning(tmp_path):
    """The spec's beam and bin of a return: HoloOcean's ``int((az + A/2) / res)``, ``int((r - r0) / res)``."""
    root = _write_holoocean(tmp_path / "ds", [])
    son = read_holoocean_config(root / "Config.json")
    spec = son.spec
    assert spec.image_shape == (100, 64) and (son.image_key, son.pose_key) == ("ImagingSonar", "PoseSensor")
    assert son.config["ds_factor"] == 1.0 and math.isclose(spec.vfov_rad, math.radians(20.0))
    rng = np.random.default_rng(3)
    az = rng.uniform(-29.99, 29.99, 2000)
    r = rng.uniform(0.5, 2.999, 2000)
    np.testing.assert_array_equal(spec.beam_index(np.radians(az)), np.floor((az + 30.0) / (60.0 / 64)))
    np.testing.assert_array_equal(spec.bin_index(r), np.floor((r - 0.5) / 0.025))
    # the resolution form: int(span / res) bins of that resolution, from -Azimuth/2
    cfg = {**{k: v for k, v in SONAR_CFG.items() if k not in ("RangeBins", "AzimuthBins")},
           "RangeRes": 0.03, "AzimuthRes": 0.7}
    (root / "Config.json").write_text(json.dumps(_config(cfg)))
    spec = read_holoocean_config(root / "Config.json").spec
    assert spec.image_shape == (83, 85) and math.isclose(spec.range_max_m, 0.5 + 83 * 0.03)
    az = az[az < -30.0 + 85 * 0.7]  # beyond the last whole bin HoloOcean folds returns into it
    np.testing.assert_array_equal(spec.beam_index(np.radians(az)), np.floor((az + 30.0) / 0.7))


def test_holoocean_intensities_times_protocols_and_bins_from_the_image(tmp_path):
    T = _views()[0]
    img = np.linspace(-0.5, 1.5, 6400, dtype=np.float32).reshape(100, 64)
    for p in range(6):
        root = _write_holoocean(tmp_path / f"p{p}", [{"PoseSensor": T, "ImagingSonar": img, "t": 0.5 + p}],
                                protocol=p)
        (f,) = open_recording(root)
        np.testing.assert_array_equal(f.image, np.clip(img, 0, 1))
        assert f.image.dtype == np.float32 and f.timestamp_s == 0.5 + p
    u16 = (np.arange(6400) * 10).astype(np.uint16).reshape(100, 64)
    cfg = {k: v for k, v in SONAR_CFG.items() if k not in ("RangeBins", "AzimuthBins")}
    root = _write_holoocean(tmp_path / "u16", [{"PoseSensor": T, "ImagingSonar": u16}], _config(cfg))
    (f,) = open_recording(root)  # no bin counts in the config: the image's shape decides
    assert f.spec.image_shape == (100, 64)
    np.testing.assert_allclose(f.image, u16 / 65535.0, rtol=1e-6)


def _holo_mutations() -> dict[str, tuple[list | None, dict | None, str]]:
    T = _views()[0].astype(np.float32)
    img = np.zeros((100, 64), np.uint8)
    ok = {"PoseSensor": T, "ImagingSonar": img}
    nan = T.copy()
    nan[0, 3] = np.nan
    return {
        "transposed image": ([ok, {**ok, "ImagingSonar": img.T.copy()}], None,
                             "expected a 'ImagingSonar' image of (100, 64) (RangeBins x AzimuthBins from "
                             "Config.json), but it is (64, 100)"),
        "missing image key": ([ok, {"PoseSensor": T}], None,
                              "expected the reading 'ImagingSonar' (its sensor's name in Config.json), but "
                              "the frame has only ['PoseSensor']"),
        "missing pose key": ([ok, {"ImagingSonar": img}], None, "expected the reading 'PoseSensor'"),
        "NaN pose": ([ok, {**ok, "PoseSensor": nan}], None, "finite entries in 'PoseSensor'"),
        "3 x 4 pose": ([ok, {**ok, "PoseSensor": T[:3]}], None, "4 x 4 pose, but it has shape (3, 4)"),
        "scaled pose": ([ok, {**ok, "PoseSensor": np.diag([2, 2, 2, 1]).astype(np.float32)}], None,
                        "orthonormal rotation"),
        "a list": ([ok, [img, T]], None, "expected a dict of sensor readings (HoloOcean's state), but the "
                                         "pickle holds a list"),
        "int64 image": ([ok, {**ok, "ImagingSonar": img.astype(np.int64)}], None,
                        "uint8, uint16 or float 'ImagingSonar' image, but it is int64"),
        "NaN image": ([ok, {**ok, "ImagingSonar": np.full((100, 64), np.nan, np.float32)}], None,
                      "finite intensities"),
        "no RangeMax": ([ok], _config({k: v for k, v in SONAR_CFG.items() if k != "RangeMax"}),
                        "expected RangeMax in the ImagingSonar configuration of Config.json, but it has "
                        "only"),
        "degrees as text": ([ok], _config({**SONAR_CFG, "Azimuth": "60"}),
                            "expected Azimuth in the ImagingSonar configuration to be a finite number, "
                            "but got '60'"),
        "no sonar": ([ok], {"agents": [{"sensors": [{"sensor_type": "PoseSensor"}]}]},
                     "expected an ImagingSonar among the agents' sensors, but found ['PoseSensor']"),
        "pose sensor elsewhere": ([ok], _config(pose_mount={"socket": "IMUSocket"}),
                                  "expected the PoseSensor on the sonar's mount"),
        "inverted range": ([ok], _config({**SONAR_CFG, "RangeMin": 3.5}), "0 <= RangeMin < RangeMax"),
    }


@pytest.mark.parametrize("case", sorted(_holo_mutations()))
def test_holoocean_mutated_folders_are_refused_in_one_line_saying_what_came(tmp_path, case):
    states, cfg, says = _holo_mutations()[case]
    root = _write_holoocean(tmp_path / "ds", states, cfg)
    with pytest.raises(FormatError) as e:
        list(open_recording(root))
    assert says in _one_line(e)
    if len(states) > 1:  # a bad frame alone: skipped with on_bad, the others kept
        bad: list[str] = []
        kw, _stride = reader_options(root, on_bad=lambda err: bad.append(str(err)))
        assert [f.meta["frame"] for f in open_recording(root, **kw)] == [0] and len(bad) == 1


def test_holoocean_json_garbage_hostile_frames_and_a_sonar_offset(tmp_path):
    import os

    T = _views()[0]
    ok = {"PoseSensor": T, "ImagingSonar": np.zeros((100, 64), np.uint8)}
    root = _write_holoocean(tmp_path / "ds", [ok, ok])
    marker = tmp_path / "ran"
    (root / "Data" / "001.pkl").write_bytes(pickle.dumps(_Reduce(os.system, (f"touch {marker}",))))
    with pytest.raises(FormatError) as e:
        list(open_recording(root))
    assert "001.pkl" in _one_line(e) and "posix.system" in str(e.value) and not marker.exists()
    (root / "Data" / "001.pkl").write_bytes(pickle.dumps(ok)[:-40])
    with pytest.raises(FormatError) as e:
        list(open_recording(root))
    assert "corrupt or truncated" in _one_line(e)
    (root / "Data" / "1.pkl").write_bytes(pickle.dumps(ok))
    with pytest.raises(FormatError, match="are both frame 1"):
        open_recording(root)
    (root / "Data" / "1.pkl").unlink()
    (root / "Config.json").write_text('{"agents": [')
    with pytest.raises(FormatError) as e:
        open_recording(root)
    assert "expected JSON" in _one_line(e)
    # a pose sensor mounted apart from the sonar: refused, unless T_P_S says where the sonar is
    (root / "Data" / "001.pkl").write_bytes(pickle.dumps(ok))
    (root / "Config.json").write_text(json.dumps(_config(pose_mount={"socket": "IMUSocket"})))
    T_P_S = _look_at(np.array([0.1, 0.0, -0.05]), np.array([1.0, 0.0, -0.5]), 0.0)
    frames = list(open_recording(root, T_P_S=T_P_S))
    np.testing.assert_allclose(frames[0].T_W_S, T @ T_P_S, atol=1e-12)


# ---------------------------------------------------------------- kinds and options
@needs_data
def test_recording_kind_and_reader_options_for_each_layout(tmp_path):
    holo = _write_holoocean(tmp_path / "holo", [{"PoseSensor": _views()[0],
                                                 "ImagingSonar": np.zeros((100, 64), np.uint8)}])
    tank = _oasis_clone(tmp_path / "clone")
    fan = DATA / "oasis_tank"
    aris = DATA / "aris" / "sample.aris"
    kinds = [recording_kind(p) for p in (holo, tank, fan, aris)]
    assert kinds == ["holoocean", "oasis", "fan-folder", "aris"]
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(FormatError) as e:
        recording_kind(empty)
    assert "HoloOcean dataset (Config.json and Data/)" in _one_line(e)
    kw, stride = reader_options(tank, flip_lr=True, vfov_deg=12.0, stride=3)
    assert stride == 1 and kw["stride"] == 3 and kw["geom"].flip_lr
    assert math.isclose(kw["spec"].vfov_rad, math.radians(12.0))
    f = next(iter(open_recording(tank, **kw)))
    assert math.isclose(f.spec.vfov_rad, math.radians(12.0))
    kw, stride = reader_options(holo, vfov_deg=14.0, stride=2, reader_stride=False)
    assert kw == {"vfov_deg": 14.0} and stride == 2
    assert math.isclose(next(iter(open_recording(holo, **kw))).spec.vfov_rad, math.radians(14.0))
    kw, stride = reader_options(aris, vfov_deg=14.0, stride=2)
    assert kw == {"vfov_deg": 14.0} and stride == 2  # the caller strides a single-file recording
    with pytest.raises(ValueError, match="fan pictures"):
        reader_options(holo, flip_lr=True)
    with pytest.raises(ValueError, match="one file per frame"):
        reader_options(aris, on_bad=print)


# ---------------------------------------------------------------- fuzz of the files as read
def _mutate(data: bytes, draw) -> bytes:
    b = bytearray(data)
    for _ in range(draw(st.integers(1, 3))):
        i = draw(st.integers(0, max(len(b) - 1, 0)))
        op = draw(st.sampled_from(["truncate", "byte", "insert", "delete"]))
        if op == "truncate":
            del b[i:]
        elif op == "byte" and b:
            b[i] = draw(st.integers(0, 255))
        elif op == "insert":
            b[i:i] = draw(st.binary(min_size=1, max_size=6))
        else:
            del b[i:i + draw(st.integers(1, 6))]
    return bytes(b)


def _check_read(root: Path) -> None:
    """Read to the end: frames that pass the frame checks, then the end or a one-line FormatError."""
    try:
        for f in open_recording(root):
            assert f.image.dtype == np.float32 and np.isfinite(f.image).all()
            assert f.image.min() >= 0.0 and f.image.max() <= 1.0 and np.isfinite(f.T_W_S).all()
    except FormatError as e:
        assert "\n" not in str(e)


@settings(max_examples=150, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(data=st.data(), which=st.sampled_from(["frame", "config"]), protocol=st.sampled_from([0, 2, 4, 5]))
def test_fuzz_mutated_holoocean_frames_and_configs_end_in_frames_or_format_error(tmp_path_factory, data,
                                                                                  which, protocol):
    root = tmp_path_factory.mktemp("holo")
    T = _views()[0].astype(np.float32)
    img = (np.arange(6400) % 251).astype(np.uint8).reshape(100, 64)
    _write_holoocean(root, [{"PoseSensor": T, "ImagingSonar": img, "t": 2.0}], protocol=protocol)
    target = root / ("Data/000.pkl" if which == "frame" else "Config.json")
    target.write_bytes(_mutate(target.read_bytes(), data.draw))
    _check_read(root)


@needs_data
@settings(max_examples=60, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(data=st.data())
def test_fuzz_mutated_oasis_pose_pickles_end_in_frames_or_format_error(tmp_path_factory, data):
    root = _oasis_clone(tmp_path_factory.mktemp("oasis"), frames=FRAMES[:2])
    pkl = root / "son_poses.pkl"
    pkl.write_bytes(_mutate(pkl.read_bytes(), data.draw))
    _check_read(root)
