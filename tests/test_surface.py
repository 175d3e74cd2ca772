"""The surface layer users get (issue 30): gpumap.layers.refine from ``import gpumap``, refinement of the
evidence rule's maps and of saved maps, the threshold a result was made with, field vs occupancy,
a loud device choice, refined map files in ``gpumap view`` / ``export`` (``gpumap plan``:
test_plan_cli.py)."""

from __future__ import annotations

import json
import logging
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import DATA, needs_data
from maps import make_mapper

import gpumap
from gpumap.core.params import MapperParams

pytest.importorskip("warp")

ITERATIONS = 20


def _pose(x: float, y: float, z: float, yaw: float, pitch_deg: float) -> np.ndarray:
    from gpumap.sim.scenes import pose_from_xyz_ypr

    return pose_from_xyz_ypr([x, y, z], yaw, math.radians(pitch_deg))


@pytest.fixture(scope="module")
def scene():
    """A floor and a block seen from 8 poses, pings rendered by the ping model."""
    from gpumap.layers.render import PingRenderer

    spec = gpumap.SonarSpec.uniform(hfov_deg=90, n_beams=32, n_bins=60, range_min_m=0.1, range_max_m=1.6)
    grid = gpumap.GridSpec((-0.3, -0.8, -0.3), (1.5, 0.8, 0.6), 0.08)
    c = grid.centers(np.argwhere(np.ones(grid.shape, bool))).reshape(*grid.shape, 3)
    truth = (c[..., 2] > -0.26) & (c[..., 2] < -0.16)
    truth |= (np.abs(c[..., 0] - 0.8) < 0.12) & (np.abs(c[..., 1]) < 0.12) & (c[..., 2] < 0.05)
    poses = np.stack([_pose(x, y, 0.35, yaw, p) for x, y, yaw in ((-0.1, -0.4, 0.5), (-0.1, 0.4, -0.5))
                      for p in (15, 25, 35, 45)])
    r = PingRenderer(spec, grid, device="cpu")
    images = r.render(truth.astype(np.float32), np.full(grid.shape, 0.8, np.float32), poses, gain=400.0,
                      floor=0.02)
    return spec, grid, poses, images


def _mapper(scene, rule: str, **kw) -> gpumap.MinMaxMapper:
    spec, grid, poses, images = scene
    m = make_mapper(spec, grid, backend="numpy", rule=rule, threshold=0.1, **kw)
    m.integrate_batch(images, poses)
    return m


@pytest.fixture(scope="module")
def refined(scene):
    """(mapper, result) of the evidence rule's map refined for a few steps on the CPU."""
    from gpumap.layers.refine import RefineOptions, refine

    m = _mapper(scene, "evidence")
    _, _, poses, images = scene
    return m, refine(m, images, poses, options=RefineOptions(iterations=ITERATIONS), device="cpu")


# ---------------------------------------------------------------------- 1. import gpumap
def test_refine_is_part_of_import_gpumap() -> None:
    """``gpumap.refine(...)``, ``gpumap.RefineOptions``, ``gpumap.RefineResult``,
    ``gpumap.refine_saved``: from ``import gpumap`` alone, without Warp imported, and the same
    after the module ``gpumap.layers.refine`` was imported by name."""
    code = ("import sys, gpumap; f = gpumap.refine; o = gpumap.RefineOptions(iterations=3); "
            "print(callable(f), o.iterations, gpumap.RefineResult.__name__, callable(gpumap.refine_saved), "
            "'warp' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["True", "3", "RefineResult", "True", "False"], out
    import gpumap.layers.refine as mod

    assert callable(gpumap.refine) and gpumap.RefineOptions is mod.RefineOptions
    assert gpumap.RefineResult is mod.RefineResult and gpumap.refine_saved is mod.refine_saved
    assert {"refine", "refine_saved", "RefineOptions", "RefineResult"} <= set(gpumap.__all__)
    from gpumap import RefineOptions, refine  # noqa: F401

    assert callable(refine)


def test_gpumap_refine_calls_refine(scene, refined) -> None:
    """``gpumap.refine(mapper, images, poses, ...)`` is :func:`gpumap.layers.refine.refine`: the same
    result."""
    from gpumap.layers.refine import RefineOptions

    m, res = refined
    _, _, poses, images = scene
    again = gpumap.refine(m, images, poses, options=RefineOptions(iterations=ITERATIONS), device="cpu")
    np.testing.assert_array_equal(again.occupancy, res.occupancy)


# ---------------------------------------------------------------------- 2. the evidence rule
def _wilson_occupied(dark: int, hits: int, p: float, z: float) -> bool:
    """The evidence rule's decision, from the Wilson score upper bound, scalar by scalar."""
    n = dark + hits
    if hits == 0:
        return False
    s = hits / n
    upper = (s + z * z / (2 * n) + z * math.sqrt(s * (1 - s) / n + z * z / (4 * n * n))) / (1 + z * z / n)
    return upper >= p - 1e-12


def test_carved_voxels_of_the_evidence_rule_brute_force() -> None:
    """carved = observed, some clear view, and the rule calls it free: checked count by count
    against the Wilson bound, and against the map itself (a carved voxel reads free)."""
    from gpumap.layers.refine import carved_voxels

    dark, hits = np.meshgrid(np.arange(12, dtype=np.uint32), np.arange(12, dtype=np.uint32), indexing="ij")
    dark, hits = dark[..., None], hits[..., None]
    observed = np.ones(dark.shape, bool)
    observed[0, 0] = False  # no view at all: unknown
    observed[1, 1] = True
    min_all = np.where(observed, 0.05, np.inf).astype(np.float32)
    ev = {"min_all": min_all, "bright": np.full(dark.shape, np.inf, np.float32), "count": dark, "hits": hits}
    for p, z in ((0.5, 1.645), (0.3, 1.0), (0.5, 0.0)):
        got = carved_voxels("evidence", ev, bright_share=p, share_z=z)
        for i in range(12):
            for j in range(12):
                want = bool(observed[i, j, 0]) and (i + j > 0) and not _wilson_occupied(i, j, p, z)
                assert got[i, j, 0] == want, (i, j, p, z)
    # observed with no clear view (only shadowed dark views): not carved, it may be a surface
    shadow = {**ev, "count": np.zeros_like(dark), "hits": np.zeros_like(hits)}
    assert not carved_voxels("evidence", shadow).any()
    with pytest.raises(ValueError, match="'plain'"):
        carved_voxels("plain", ev)


def test_refine_takes_the_evidence_rule(scene, refined) -> None:
    from gpumap.layers.refine import carved_voxels

    m, res = refined
    ev = m.evidence()
    want = carved_voxels("evidence", ev, bright_share=m.bright_share, share_z=m.share_z)
    np.testing.assert_array_equal(res.carved, want)
    v = m.values()
    assert want.any()
    # the rule's free voxels with clear views, never its occupied ones
    assert not np.any(want & (np.nan_to_num(v, nan=-1) >= m.threshold))
    free_clear = np.isfinite(v) & (v < m.threshold) & ((ev["count"].astype(np.int64) + ev["hits"]) > 0)
    np.testing.assert_array_equal(want, free_clear)
    assert np.all(res.occupancy[want] == 0) and np.all(np.isnan(res.occupancy[np.isnan(v)]))
    assert res.rule == "evidence" and res.threshold == pytest.approx(0.1) and res.stats["rule"] == "evidence"
    # a mapper with other settings of the rule carves other voxels
    m2 = _mapper(scene, "evidence", bright_share=0.9)
    more = carved_voxels("evidence", m2.evidence(), bright_share=0.9, share_z=m2.share_z)
    assert np.all(more >= want) and more.sum() > want.sum()


def test_refine_still_takes_the_visible_rule_and_refuses_plain(scene) -> None:
    from gpumap.layers.refine import RefineOptions, refine

    _, _, poses, images = scene
    m = _mapper(scene, "visible")
    res = refine(m, images, poses, options=RefineOptions(iterations=2), device="cpu")
    want = np.isfinite(m.values()) & (m.evidence()["count"] >= m.carve_views)
    np.testing.assert_array_equal(res.carved, want)
    with pytest.raises(ValueError, match="'plain'"):
        refine(_mapper(scene, "plain"), images, poses, device="cpu")


# ---------------------------------------------------------------------- 3. saved maps
def test_refine_a_saved_map(scene, refined, tmp_path: Path) -> None:
    from gpumap.layers.refine import RefineOptions, refine, refine_saved

    m, res = refined
    _, _, poses, images = scene
    path = m.save(tmp_path / "map.npz")
    opts = RefineOptions(iterations=ITERATIONS)
    for got in (refine_saved(path, (images, poses), options=opts, device="cpu"),
                refine(path, images, poses, options=opts, device="cpu")):
        np.testing.assert_array_equal(got.occupancy, res.occupancy)
        np.testing.assert_array_equal(got.carved, res.carved)
        assert got.rule == "evidence" and got.threshold == res.threshold
    got = refine_saved(path, (images, poses), options=opts, device="cpu")
    assert got.stats["pings_in_map"] == len(images)
    # pings the map never saw: the wrong recording, said before any work
    with pytest.raises(ValueError, match="none of the"):
        refine_saved(path, (images[:, ::-1].copy(), poses), device="cpu")


# ---------------------------------------------------------------------- 4. threshold, names
def test_banded_uses_the_threshold_of_the_result(refined) -> None:
    m, res = refined
    v = m.values()
    np.testing.assert_array_equal(res.banded(), res.banded(v, 0.1, 1))
    np.testing.assert_array_equal(res.map_values, v)
    np.testing.assert_array_equal(res.safe(), np.nan_to_num(v, nan=-1) >= 0.1)
    with pytest.raises(ValueError, match=r"threshold=0\.1 .*but got 0\.2"):
        res.banded(v, 0.2)
    with pytest.raises(ValueError, match="but got 0.05"):
        res.banded(threshold=0.05)


def test_field_and_occupancy_are_named_apart(scene, refined) -> None:
    """``res.field`` is what the renderer takes, ``res.occupancy = 1 - exp(-kappa field)``; render_map
    takes ``field`` (``occupancy=`` is its deprecated former name, same meaning)."""
    from gpumap.layers.refine import field_from_occupancy, occupancy_from_field, render_map
    from gpumap.layers.render import PingModel, PingRenderer

    m, res = refined
    spec, grid, poses, images = scene
    kappa = PingModel().kappa
    obs = np.isfinite(res.occupancy)
    np.testing.assert_array_equal(np.isfinite(res.field), obs)
    np.testing.assert_allclose(occupancy_from_field(res.field, kappa)[obs], res.occupancy[obs], atol=1e-6)
    np.testing.assert_allclose(field_from_occupancy(res.occupancy, kappa)[obs], res.field[obs], atol=1e-5)
    assert np.nanmax(res.field) <= 1 and np.nanmin(res.field) >= 0
    assert np.all(res.field[res.raised] > 0)  # raised voxels' field follows their occupancy
    r = PingRenderer(spec, grid, device="cpu")
    want, _, _ = render_map(r, res.field, poses[:2], reflectivity=res.reflectivity, gain=res.gain,
                            floor=res.floor)
    np.testing.assert_allclose(
        want, r.render(np.nan_to_num(res.field), res.reflectivity, poses[:2], res.gain, res.floor), atol=1e-6)
    with pytest.warns(DeprecationWarning, match="field"):
        old, _, _ = render_map(r, occupancy=res.field, poses=poses[:2], reflectivity=res.reflectivity,
                               gain=res.gain, floor=res.floor)
    np.testing.assert_array_equal(old, want)


def test_refined_file_round_trip(refined, tmp_path: Path) -> None:
    from gpumap.layers.refine import is_refined_file, load_refined

    m, res = refined
    path = res.save(tmp_path / "refined.npz")
    assert is_refined_file(path) and not is_refined_file(m.save(tmp_path / "map.npz"))
    back = load_refined(path)
    for k in ("occupancy", "confidence", "field", "reflectivity", "carved", "raised", "map_values"):
        np.testing.assert_array_equal(getattr(back, k), getattr(res, k), err_msg=k)
    assert (back.threshold, back.rule, back.grid, back.spec) == (res.threshold, res.rule, res.grid, res.spec)
    np.testing.assert_array_equal(back.banded(), res.banded())
    from gpumap.errors import FormatError

    with pytest.raises(FormatError, match="gpumap-refined"):
        load_refined(tmp_path / "map.npz")


# ---------------------------------------------------------------------- 5. loud device choice
def test_device_auto_says_what_it_took_and_why(refined, caplog) -> None:
    from gpumap.backends import _warp
    from gpumap.errors import BackendUnavailableError
    from gpumap.layers.refine import pick_device

    wp = _warp()[0]
    n = wp.get_cuda_device_count() if wp.is_cuda_available() else 0
    with caplog.at_level(logging.INFO, logger="gpumap.layers.refine"):
        dev, why = pick_device("auto")
    assert dev == ("cuda:0" if n else "cpu")
    assert ("CUDA device" in why) and ("no CUDA" in why) == (n == 0)
    assert any(dev in r.getMessage() and why in r.getMessage() for r in caplog.records)
    with pytest.raises(BackendUnavailableError, match="cuda:9"):
        pick_device("cuda:9")
    with pytest.raises(ValueError, match="'gpu'"):
        pick_device("gpu")
    _, res = refined
    assert res.stats["device"] == "cpu" and res.stats["device_reason"] == "named"


def test_map_frames_shows_progress_and_makes_the_same_map(scene, capsys) -> None:
    from gpumap.layers.refine import MAP_CHUNK, map_frames

    spec, grid, poses, images = scene
    imgs = np.concatenate([images] * 3)  # more than one chunk
    Ps = np.concatenate([poses] * 3)
    assert len(imgs) > MAP_CHUNK
    one = gpumap.MinMaxMapper(spec, grid, backend="numpy")
    one.integrate_batch(imgs, Ps)
    m = gpumap.MinMaxMapper(spec, grid, backend="numpy")
    map_frames(m, imgs, Ps, progress=True)
    assert "map: 100%" in capsys.readouterr().err
    np.testing.assert_array_equal(m.raw_values(), one.raw_values())
    m.reset()
    map_frames(m, imgs, Ps, progress=False)
    assert "map:" not in capsys.readouterr().err


# ---------------------------------------------------------------------- 6. view and export
def _ply_points(path: Path) -> np.ndarray:
    from gpumap.io import read_ply

    p = read_ply(path)
    return np.stack([p["x"], p["y"], p["z"]], 1)


def test_export_writes_the_layers_of_a_refined_map(refined, tmp_path: Path, capsys) -> None:
    from gpumap.commands import main

    m, res = refined
    path = res.save(tmp_path / "refined.npz")
    assert main(["export", str(path), str(tmp_path / "out.ply")]) == 0
    infos = json.loads(capsys.readouterr().out)
    assert [i["layer"] for i in infos] == ["surface", "safe"]
    for layer, mask in (("surface", res.occupied()), ("safe", res.safe())):
        pts = _ply_points(tmp_path / f"out.{layer}.ply")
        assert len(pts) == mask.sum() > 0
        np.testing.assert_allclose(pts, res.grid.centers(np.argwhere(mask)), atol=1e-5)
    assert res.occupied().sum() != res.safe().sum()
    assert main(["export", str(path), str(tmp_path / "safe.bt"), "--layer", "safe"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["layer"] == "safe" and info["occupied_cells"] == res.safe().sum()
    # a map file has one layer; a refined one keeps its layers' thresholds
    mp = m.save(tmp_path / "map.npz")
    with pytest.raises(SystemExit) as e:
        main(["export", str(mp), str(tmp_path / "m.ply"), "--layer", "safe"])
    assert e.value.code == 2 and "refined map" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["export", str(path), str(tmp_path / "m.ply"), "--threshold", "0.3"])
    assert "--threshold" in capsys.readouterr().err


def test_view_reads_the_layers_of_a_refined_map(refined, tmp_path: Path) -> None:
    from gpumap.layers.refine import OCCUPIED_LEVEL
    from gpumap.viewer.session import map_layer

    m, res = refined
    path = res.save(tmp_path / "refined.npz")
    d = map_layer(path)
    assert d["layer"] == "surface" and d["threshold"] == OCCUPIED_LEVEL and d["grid"] == m.grid
    np.testing.assert_array_equal(d["values"], res.occupancy)
    d = map_layer(path, "safe")
    assert d["threshold"] == pytest.approx(m.threshold) and d["spec"] == m.spec
    np.testing.assert_array_equal(d["values"], m.values())
    mp = m.save(tmp_path / "map.npz")
    np.testing.assert_array_equal(map_layer(mp)["values"], m.values())
    with pytest.raises(ValueError, match="refined map"):
        map_layer(mp, "safe")


# ---------------------------------------------------------------------- 3. the CLI from a saved map
@needs_data
def test_cli_refines_a_saved_map_and_says_what_it_wrote(tmp_path: Path, capsys) -> None:
    from gpumap.commands import main
    from gpumap.layers.refine import load_refined, recording_frames
    from gpumap.spec import auto_grid

    rec = DATA / "oasis_tank"
    spec, images, poses = recording_frames(rec, 12)
    m = gpumap.MinMaxMapper(spec, auto_grid(spec, list(poses), 0.12), "numpy", MapperParams(threshold=0.3))
    m.integrate_batch(images, poses)
    mp = m.save(tmp_path / "map.npz")
    out = tmp_path / "out"
    assert main(["refine", str(rec), "--map", str(mp), "--stride", "12", "--iterations", "2", "--device",
                 "cpu", "--backend", "numpy", "--out", str(out)]) == 0
    cap = capsys.readouterr()
    assert f"wrote refined.npz, refined.ply, refine.json to {out}/" in cap.out
    assert "refine (cpu): 100%" in cap.err  # the progress bar, on by default
    res = load_refined(out / "refined.npz")
    assert res.grid == m.grid and res.rule == "evidence" and res.threshold == pytest.approx(0.3)
    np.testing.assert_array_equal(res.map_values, m.values())
    s = json.loads((out / "refine.json").read_text())
    assert s["pings_in_map"] == s["frames"] == len(images) and s["device"] == "cpu"
    # the map's grid, rule and threshold: never overridden silently
    with pytest.raises(SystemExit):
        main(["refine", str(rec), "--map", str(mp), "--threshold", "0.2", "--out", str(out)])
    assert "--threshold" in capsys.readouterr().err


def test_gpumap_view_serves_either_layer_of_a_refined_map(refined, tmp_path: Path) -> None:
    pytest.importorskip("viser")
    from gpumap.commands.view import _parser
    from gpumap.viewer.session import view_map as _view_map

    _, res = refined
    path = res.save(tmp_path / "refined.npz")
    for layer, mask in (("surface", res.occupied()), ("safe", res.safe())):
        v = _view_map(path, _parser().parse_args([str(path), "--view-port", "0", "--layer", layer]))
        try:
            assert np.count_nonzero(v._q) == mask.sum() > 0, layer
        finally:
            v.close()
