"""The demo end to end on a coarse grid."""

from __future__ import annotations

import json

import numpy as np
from gpumap.sim.demo import main


def test_demo_end_to_end(tmp_path):
    out = tmp_path / "demo"
    rc = main(["--voxel-size", "0.06", "--pings", "10", "--backend", "numpy", "--out", str(out),
               "--no-progress", "--pose-noise", "0.005"])
    assert rc == 0
    for name in ("metrics.json", "map.npz", "sonar_image.png", "map_vs_truth.png", "error_by_views.png"):
        assert (out / name).stat().st_size > 0, name
    m = json.loads((out / "metrics.json").read_text())
    assert m["scene"] == "tank" and m["backend"] == "numpy" and m["images"] == 10
    assert m["voxel_size_m"] == 0.06 and m["ms_per_image"] > 0
    # A garbage map (all free, all occupied, random) fails these bounds.
    assert m["false_negative_rate_objects"] < 0.3
    assert m["false_negative_rate"] < 0.5
    assert m["false_positive_rate"] < 0.8
    assert m["free_carved_fraction"] > 0.05
    # both rules side by side; the visible rule (default) misses fewer detectable surfaces
    vis, plain = m["rules"]["visible"], m["rules"]["plain"]
    assert m["rule"] == "visible"
    assert vis["false_negative_rate_detectable"] == m["false_negative_rate_detectable"]
    assert vis["miss_rate"] < plain["miss_rate"]
    assert vis["observed_surface_fraction"] == plain["observed_surface_fraction"]
    assert set(m["pose_noise"]["rows"]) == {"true", "odometry", "ekf", "ekf_cov"}
    with np.load(out / "map.npz") as z:
        assert z["values"].shape == tuple(m["grid_shape"])
