"""The demo end to end on a coarse grid."""

from __future__ import annotations

import json

import gpumap
from gpumap.commands.demo import main


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
    # metrics.json keeps the scores a user reads (README: what the demo's numbers mean), no more
    rate_keys = {"miss_rate", "miss_rate_objects", "false_negative_rate_detectable",
                 "false_positive_rate_far", "free_carved_fraction", "observed_surface_fraction"}
    assert rate_keys <= set(m)
    scores = {k for k in m if k.startswith(("false_", "miss_", "object_"))}  # no other FN / miss fields
    assert scores == {k for k in rate_keys if k.startswith(("false_", "miss_"))} | {"miss_rate_by_object"}
    assert set(m["rules"]) == {"evidence", "visible", "plain"}
    ev, plain = m["rules"]["evidence"], m["rules"]["plain"]
    assert m["rule"] == "evidence" and all(ev[k] == m[k] for k in rate_keys)
    for rule in ("evidence", "visible"):
        vis = m["rules"][rule]
        for row in (vis, plain):
            assert all(0 <= row[k] <= 1 for k in rate_keys), row
        # Exact, by construction: an evidence or visible value is never below the plain one and the
        # rules observe the same voxels, so they miss no more, free no more water, and keep at
        # least as many phantoms.
        assert vis["observed_surface_fraction"] == plain["observed_surface_fraction"]
        assert vis["miss_rate"] <= plain["miss_rate"]
        assert vis["false_negative_rate_detectable"] <= plain["false_negative_rate_detectable"]
        assert vis["free_carved_fraction"] <= plain["free_carved_fraction"]
        assert vis["false_positive_rate_far"] >= plain["false_positive_rate_far"]
        # and what the rules are for: they miss strictly less of the small objects than the
        # paper's rule (measured at 6 cm, 10 pings: 0 % against 3 %)
        assert vis["miss_rate_objects"] < plain["miss_rate_objects"]
    # the per-object rates are the picture's (errors_by_object.png) and name every object
    assert set(m["miss_rate_by_object"]) >= {"sand", "walls", "rock", "pipe"}
    assert set(m["pose_noise"]["rows"]) == {"true", "odometry", "ekf", "ekf_cov"}
    assert gpumap.MinMaxMapper.load(out / "map.npz", backend="numpy").grid.shape == tuple(m["grid_shape"])
