"""``gpumap plan MAP`` (issue 30): the next best views of a saved map, from its confidence layer."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import DATA, needs_data

import gpumap
from gpumap.core.params import MapperParams
from gpumap.layers.confidence import with_confidence


def test_plan_writes_the_best_views_within_the_wrist_limits(tmp_path: Path, capsys) -> None:
    """A point reflector seen level (test_nbv): its elevation arc is unconfirmed, and a rolled view
    settles it. The plan's gains are the map's own gains of the written poses, best first, and every
    pose lies within the limits around its anchor."""
    from gpumap.commands import main
    from gpumap.commands.plan import pose_from_xyz_ypr_deg, ypr_deg

    spec = gpumap.SonarSpec.uniform(hfov_deg=60, vfov_deg=20, n_beams=64, n_bins=100, range_min_m=0.1,
                                    range_max_m=1.5)
    grid = gpumap.GridSpec((-0.5, -0.5, -0.5), (0.5, 0.5, 0.5), 0.05)
    target = np.array([0.025, 0.025, 0.025])
    T = pose_from_xyz_ypr_deg(target - [0.8, 0, 0], 0, 0, 0)
    img = np.zeros(spec.image_shape, np.float32)
    img[spec.bin_index(0.8), spec.beam_index(0.0)] = 0.9
    m = with_confidence(gpumap.MinMaxMapper(spec, grid, "numpy", MapperParams(rule="visible")))
    m.integrate(img, T)
    mp = m.save(tmp_path / "map.npz")
    out = tmp_path / "plan.json"
    pose = ",".join(str(x) for x in (*T[:3, 3], 0, 0, 0))
    assert main(["plan", str(mp), f"--pose={pose}", "--views", "3", "--candidates", "300",
                 "--max-roll-deg", "60", "--max-tilt-deg", "5", "--max-yaw-deg", "3", "--radius-m", "0.02",
                 "--backend", "numpy", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    plan = json.loads(out.read_text())
    assert len(plan["views"]) == 3 and len(printed.splitlines()) == 4
    Ts = np.array([v["T_W_S"] for v in plan["views"]])
    gains = [v["gain"] for v in plan["views"]]
    np.testing.assert_allclose(m.layer("confidence").gains(Ts, unknown_weight=0.0), gains)
    assert gains == sorted(gains, reverse=True) and gains[0] > 0
    for Tc in Ts:
        D = np.linalg.inv(T) @ Tc
        yaw, pitch, roll = ypr_deg(D)
        assert abs(roll) <= 60 + 1e-6 and abs(pitch) <= 5 + 1e-6 and abs(yaw) <= 3 + 1e-6
        assert np.all(np.abs(D[:3, 3]) <= 0.02 + 1e-9)
    assert abs(ypr_deg(np.linalg.inv(T) @ Ts[0])[2]) > 10  # the best view rolls
    # no rolling allowed: no view settles the arc
    assert main(["plan", str(mp), f"--pose={pose}", "--views", "1", "--candidates", "50",
                 "--max-roll-deg", "0", "--max-tilt-deg", "0", "--max-yaw-deg", "0", "--radius-m", "0",
                 "--backend", "numpy", "--out", str(out)]) == 0
    assert json.loads(out.read_text())["views"][0]["gain"] == 0


def test_plan_says_what_is_missing(tmp_path: Path, capsys) -> None:
    from gpumap.commands import main

    spec = gpumap.SonarSpec.uniform(n_beams=8, n_bins=10)
    m = gpumap.MinMaxMapper(spec, gpumap.GridSpec((0, -1, -1), (2, 1, 1), 0.2), backend="numpy")
    m.integrate(np.zeros(spec.image_shape, np.float32), np.eye(4))
    mp = m.save(tmp_path / "map.npz")
    with pytest.raises(SystemExit):
        main(["plan", str(mp)])
    assert "--pose or --recording" in capsys.readouterr().err
    assert main(["plan", str(mp), "--pose", "0,0,0,0,0,0", "--out", str(tmp_path / "p.json")]) == 2
    assert "confidence layer" in capsys.readouterr().err


@needs_data
def test_plan_rebuilds_the_layer_from_the_maps_own_frames(tmp_path: Path, capsys) -> None:
    """A map saved without the layer: its recording's frames rebuild it (the same values, exactly)
    and the anchors are the recording's poses; other frames are refused."""
    from gpumap.commands import main
    from gpumap.layers.refine import recording_frames
    from gpumap.spec import auto_grid

    rec = DATA / "oasis_tank"
    spec, images, poses = recording_frames(rec, 12)
    m = gpumap.MinMaxMapper(spec, auto_grid(spec, list(poses), 0.12), "numpy", MapperParams(threshold=0.4))
    m.integrate_batch(images, poses)
    mp = m.save(tmp_path / "map.npz")
    out = tmp_path / "plan.json"
    assert main(["plan", str(mp), "--recording", str(rec), "--stride", "12", "--anchors", "4", "--candidates",
                 "40", "--views", "2", "--backend", "numpy", "--no-progress", "--out", str(out)]) == 0
    plan = json.loads(out.read_text())
    assert plan["rebuilt_confidence"] and len(plan["views"]) == 2
    np.testing.assert_allclose(plan["anchors"][0], poses[0])
    capsys.readouterr()
    assert main(["plan", str(mp), "--recording", str(rec), "--stride", "13", "--backend", "numpy",
                 "--no-progress", "--out", str(out)]) == 2
    assert "rebuild" in capsys.readouterr().err
