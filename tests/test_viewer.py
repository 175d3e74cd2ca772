"""The live view (viser, in headless Chromium) and mapping recordings (read back ping by ping)."""

from __future__ import annotations

import base64
import importlib.util
import io
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest
from conftest import DATA, needs_data

from gpumap.layers.confidence import with_confidence
from gpumap.spec import GridSpec, SonarSpec
from gpumap.viewer.recording import MapDiff, Recorder, read_recording

HAVE_VISER = importlib.util.find_spec("viser") is not None
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
needs_viser = pytest.mark.skipif(not HAVE_VISER, reason="viser not installed: pip install -e '.[viewer]'")
needs_chromium = pytest.mark.skipif(CHROMIUM is None, reason="no headless Chromium here "
                                    "(Debian: apt-get install chromium)")


def _replay_diffs(rec) -> np.ndarray:
    """The occupied voxels' quantised values after applying every recorded change, flat uint8."""
    q = np.zeros(rec.grid.n_voxels, np.uint8)
    for p in rec.pings():
        if p.set_idx is not None:
            q[p.clear_idx] = 0
            q[p.set_idx] = p.set_val
    return q


def _quantised(values: np.ndarray, thr: float) -> np.ndarray:
    v = values.ravel()
    occ = np.isfinite(v) & (v >= thr)
    q = np.zeros(v.shape, np.uint8)
    q[occ] = np.clip(np.rint(v[occ] * 255), 1, 255)
    return q


def test_recording_round_trip(tmp_path):
    """Random maps over 23 pings: the recorded changes rebuild every sampled map exactly."""
    rng = np.random.default_rng(1)
    spec = SonarSpec.uniform(n_beams=16, n_bins=20)
    grid = GridSpec((0, 0, 0), (0.4, 0.3, 0.2), 0.05)
    maps = []
    with Recorder(tmp_path / "r.gpumap-rec", spec, grid, threshold=0.3, map_every=5, title="t") as r:
        for _k in range(23):
            v = rng.random(grid.shape).astype(np.float32)
            v[rng.random(grid.shape) < 0.4] = np.nan
            maps.append(v)
            r.ping(rng.random((20, 16)).astype(np.float32), np.eye(4), values=v)
        r.add("path_true", np.zeros((23, 3)))
    rec = read_recording(tmp_path / "r.gpumap-rec")
    assert rec.n_pings == 23 and rec.meta["title"] == "t"
    assert rec.spec == spec and rec.grid.shape == grid.shape
    pings = list(rec.pings())
    assert [p.index for p in pings] == list(range(23))
    assert pings[3].image.dtype == np.uint8 and pings[3].image.shape == (20, 16)
    sampled = [p.index for p in pings if p.set_idx is not None]
    assert sampled == [0, 5, 10, 15, 20]  # the close() sample of ping 22 needs values: see below
    q = np.zeros(grid.n_voxels, np.uint8)
    for p in pings:
        if p.set_idx is not None:
            q[p.clear_idx] = 0
            q[p.set_idx] = p.set_val
            np.testing.assert_array_equal(q, _quantised(maps[p.index], 0.3))
    assert rec.extras["path_true"].shape == (23, 3)


def test_recording_closes_with_final_map_and_aborts_cleanly(tmp_path):
    spec = SonarSpec.uniform(n_beams=8, n_bins=8)
    grid = GridSpec((0, 0, 0), (0.2, 0.2, 0.2), 0.05)
    v = np.full(grid.shape, 0.5, np.float32)
    r = Recorder(tmp_path / "a.rec", spec, grid, threshold=0.3, map_every=100)
    for _ in range(3):
        r.ping(np.zeros((8, 8), np.uint8), np.eye(4))
    r.close(values=v)
    rec = read_recording(tmp_path / "a.rec")
    np.testing.assert_array_equal(_replay_diffs(rec), _quantised(v, 0.3))
    # an aborted recording leaves the old file as it was, and no temporary file
    r = Recorder(tmp_path / "a.rec", spec, grid, threshold=0.3)
    r.ping(np.zeros((8, 8), np.uint8), np.eye(4))
    r.abort()
    assert read_recording(tmp_path / "a.rec").n_pings == 3
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.rec"]
    with pytest.raises(ValueError, match="gpumap recording"):
        (tmp_path / "bad.rec").write_bytes(b"not a zip")
        read_recording(tmp_path / "bad.rec")


def test_map_diff_reports_changes_only():
    d = MapDiff(0.5)
    v = np.array([np.nan, 0.2, 0.6, 0.9], np.float32)
    s, val, c = d.update(v)
    assert s.tolist() == [2, 3] and val.tolist() == [153, 230] and c.tolist() == []
    v2 = np.array([0.7, 0.2, 0.1, 0.9], np.float32)
    s, val, c = d.update(v2)
    assert s.tolist() == [0] and c.tolist() == [2]


def test_view_flag_without_viser_is_one_line(monkeypatch, capsys):
    from gpumap.commands import demo

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda n, *a: None if n == "viser" else real(n, *a))
    with pytest.raises(SystemExit) as e:
        demo.main(["--view", "--pings", "2"])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "pip install 'gpumap[viewer]'" in err


@needs_data
def test_replay_record_holds_every_ping(tmp_path):
    from gpumap.commands.replay import main
    from gpumap.core.mapper import MinMaxMapper

    rec_path = tmp_path / "tank.gpumap-rec"
    assert main([str(DATA / "oasis_tank"), "--voxel-size", "0.08", "--max-frames", "12", "--no-progress",
                 "--no-pictures", "--out", str(tmp_path / "out"), "--record", str(rec_path)]) == 0
    rec = read_recording(rec_path)
    assert rec.n_pings == 12 and len(list(rec.pings())) == 12
    m = MinMaxMapper.load(tmp_path / "out" / "map.npz", backend="numpy")
    # the recorded changes add up to the map that replay saved
    np.testing.assert_array_equal(_replay_diffs(rec), _quantised(m.values(), rec.meta["threshold"]))


# ---------------------------------------------------------------------- the page in Chromium
def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _chromium_page(url: str, wait_s: float, size=(1280, 800), done=None) -> tuple[bytes, list[str]]:
    """Open ``url`` in headless Chromium over the DevTools protocol: (PNG screenshot, console errors).

    Screenshots are taken every 2 s after the first 4 s until ``done(png)`` holds or ``wait_s``
    has passed (a loaded 2-core machine renders slowly in software); the last one comes back.
    """
    from websockets.sync.client import connect

    profile = tempfile.mkdtemp(prefix="gpumap-chromium-")
    proc = subprocess.Popen(
        [CHROMIUM, "--headless", "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
         "--remote-debugging-port=0", f"--user-data-dir={profile}", f"--window-size={size[0]},{size[1]}",
         "--no-first-run", "about:blank"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        port_file = Path(profile) / "DevToolsActivePort"
        for _ in range(200):
            if port_file.exists() and port_file.read_text().strip():
                break
            time.sleep(0.1)
        port = int(port_file.read_text().split()[0])
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=10) as r:
            ws_url = next(t["webSocketDebuggerUrl"] for t in json.load(r) if t["type"] == "page")
        errors: list[str] = []
        with connect(ws_url, max_size=None, open_timeout=10) as ws:
            ids = iter(range(1, 10**6))

            def call(method: str, **params) -> dict:
                i = next(ids)
                ws.send(json.dumps({"id": i, "method": method, "params": params}))
                while True:
                    msg = json.loads(ws.recv(timeout=30))
                    if msg.get("id") == i:
                        return msg.get("result", {})
                    note(msg)

            def note(msg: dict) -> None:
                m, p = msg.get("method"), msg.get("params", {})
                if m == "Runtime.consoleAPICalled" and p.get("type") in ("error", "assert"):
                    errors.append("console.error: " + " ".join(str(a.get("value", a.get("description")))
                                                               for a in p.get("args", [])))
                elif m == "Runtime.exceptionThrown":
                    errors.append("exception: " + json.dumps(p.get("exceptionDetails", {}))[:300])
                elif m == "Log.entryAdded" and p.get("entry", {}).get("level") == "error":
                    errors.append("log: " + p["entry"].get("text", "") + " " + p["entry"].get("url", ""))

            for dom in ("Runtime", "Log", "Page"):
                call(f"{dom}.enable")
            call("Page.navigate", url=url)
            t_end = time.monotonic() + wait_s
            t_shot = time.monotonic() + 4.0
            while True:
                try:
                    note(json.loads(ws.recv(timeout=max(0.05, min(t_end, t_shot) - time.monotonic()))))
                except TimeoutError:
                    pass
                if time.monotonic() >= t_shot or time.monotonic() >= t_end:
                    png = base64.b64decode(call("Page.captureScreenshot", format="png")["data"])
                    if time.monotonic() >= t_end or (done is not None and done(png)):
                        break
                    t_shot = time.monotonic() + 2.0
        return png, errors
    finally:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
        shutil.rmtree(profile, ignore_errors=True)


def _start(cmd: list[str], ready: str, timeout_s: float = 240) -> tuple[subprocess.Popen, list[str]]:
    """Start ``cmd``; wait until its stderr prints ``ready`` (the lines read so far come back)."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env)
    lines: list[str] = []
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        line = proc.stderr.readline()
        if not line:
            if proc.poll() is not None:
                break
            continue
        lines.append(line)
        if ready in line:
            return proc, lines
    proc.kill()
    raise AssertionError(f"Expected {ready!r} from {cmd}, but got:\n{''.join(lines)}")


def _stop(proc: subprocess.Popen) -> None:
    proc.send_signal(signal.SIGINT)
    try:
        proc.wait(15)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def _map_pixels(png: bytes) -> tuple[float, int]:
    """(fraction of the 3-D area unlike its background, its strongly coloured pixels)."""
    from PIL import Image

    a = np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(np.int16)
    scene = a[:, : int(a.shape[1] * 0.7)]  # the side panel sits on the right
    bg = np.median(scene.reshape(-1, 3), axis=0)
    differs = np.abs(scene - bg).sum(-1) > 40
    sat = scene.max(-1) - scene.min(-1)
    return float(differs.mean()), int(np.count_nonzero(sat > 60))


def _looks_rendered(png: bytes) -> bool:
    differs, coloured = _map_pixels(png)
    return differs > 0.03 and coloured > 2000


@needs_viser
@needs_chromium
def test_demo_view_renders_in_chromium_and_records(tmp_path):
    port = _free_port()
    rec_path = tmp_path / "demo.gpumap-rec"
    n = 6
    proc, _ = _start([sys.executable, "-m", "gpumap.commands", "demo", "--voxel-size", "0.08",
                      "--pings", str(n), "--backend", "numpy", "--no-progress",
                      "--out", str(tmp_path / "out"), "--view", f"127.0.0.1:{port}",
                      "--view-hold", "120", "--record", str(rec_path)], ready="serving the view")
    try:
        png, errors = _chromium_page(f"http://127.0.0.1:{port}", wait_s=60, done=_looks_rendered)
    finally:
        _stop(proc)
    (tmp_path / "shot.png").write_bytes(png)
    assert errors == [], errors
    differs, coloured = _map_pixels(png)
    assert differs > 0.03, f"the 3-D view looks blank: {differs:.3%} of it differs from the background"
    assert coloured > 2000, f"expected the coloured voxels of the map, but found {coloured} coloured pixels"
    rec = read_recording(rec_path)
    assert rec.n_pings == n and len(list(rec.pings())) == n
    assert "truth_points" in rec.extras


@needs_viser
@needs_chromium
def test_view_saved_map_in_chromium(tmp_path):
    from gpumap.commands.demo import main

    assert main(["--voxel-size", "0.08", "--pings", "3", "--backend", "numpy", "--no-progress",
                 "--out", str(tmp_path / "out")]) == 0
    port = _free_port()
    proc, _ = _start([sys.executable, "-m", "gpumap.commands", "view", str(tmp_path / "out" / "map.npz"),
                      "--view-port", str(port), "--view-hold", "120"], ready="serving")
    try:
        png, errors = _chromium_page(f"http://127.0.0.1:{port}", wait_s=60, done=_looks_rendered)
    finally:
        _stop(proc)
    assert errors == [], errors
    differs, coloured = _map_pixels(png)
    assert differs > 0.03 and coloured > 2000, (differs, coloured)


def test_demo_record_with_pose_noise_keeps_paths_and_landmarks(tmp_path):
    """No viewer needed to record; the EKF rows add the three paths and the landmarks with covariances."""
    from gpumap.commands.demo import main

    rec_path = tmp_path / "pn.gpumap-rec"
    assert main(["--voxel-size", "0.1", "--pings", "5", "--backend", "numpy", "--no-progress",
                 "--pose-noise", "0.005", "--out", str(tmp_path / "out"), "--record", str(rec_path)]) == 0
    rec = read_recording(rec_path)
    assert rec.n_pings == 5
    poses = np.array([p.T_W_S for p in rec.pings()])
    np.testing.assert_allclose(rec.extras["path_true"], poses[:, :3, 3])  # the true poses were mapped
    for name in ("path_odometry", "path_ekf"):
        assert rec.extras[name].shape == (5, 3)
    pts, covs = rec.extras["landmarks"], rec.extras["landmark_covs"]
    assert len(pts) > 0 and covs.shape == (len(pts), 3, 3)
    np.testing.assert_allclose(covs, covs.transpose(0, 2, 1), atol=1e-12)
    assert np.all(np.linalg.eigvalsh(covs) > 0)


@needs_viser
def test_saved_map_view_shows_no_empty_ping_panels(tmp_path):
    """gpumap view MAP.npz: a saved map has no ping, so the view has no polar / fan image panels
    (a recording's view keeps them)."""
    import gpumap
    from gpumap.commands.view import _parser
    from gpumap.viewer.session import view_map as _view_map

    spec = gpumap.SonarSpec.uniform(hfov_deg=60, vfov_deg=12, n_beams=16, n_bins=20, range_min_m=0.1,
                                    range_max_m=1.0)
    m = gpumap.MinMaxMapper(spec, gpumap.GridSpec((0.0, -0.5, -0.2), (1.0, 0.5, 0.2), 0.1), backend="numpy")
    m.integrate(np.full(spec.image_shape, 0.5, np.float32), np.eye(4))
    path = m.save(tmp_path / "map.npz")
    v = _view_map(path, _parser().parse_args([str(path), "--view-port", "0"]))
    try:
        assert v._polar_gui is None and v._fan_gui is None
        assert np.count_nonzero(v._q) > 0  # the map itself is shown
    finally:
        v.close()


# ------------------------------------------------------------------------ the confidence layer
def _pale(rgb: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(rgb.astype(np.float64) * 0.3 + 255 * 0.7), 0, 255).astype(np.uint8)


def test_confidence_colours_follow_the_layer():
    from gpumap.viewer.live import confidence_colours

    rng = np.random.default_rng(3)
    rgb = rng.integers(0, 256, (50, 3)).astype(np.uint8)
    conf = rng.random(50) < 0.4
    out, keep = confidence_colours(rgb, conf, "pale")
    for i in range(50):  # voxel by voxel: confirmed as given, unconfirmed mixed with 70 % white
        want = rgb[i] if conf[i] else _pale(rgb[i])
        assert keep[i] and np.array_equal(out[i], want), i
    out, keep = confidence_colours(rgb, conf, "hidden")
    assert np.array_equal(keep, conf) and np.array_equal(out[conf], rgb[conf])
    out, keep = confidence_colours(rgb, conf, "as confirmed")
    assert keep.all() and np.array_equal(out, rgb)
    with pytest.raises(ValueError, match="mode one of"):
        confidence_colours(rgb, conf, "faint")


def _drawn(v, grid) -> dict:
    """{(i, j, k): rgb} of every voxel box the viewer has sent."""
    out = {}
    for h in v._blocks.values():
        pos = np.asarray(h.batched_positions, np.float64)
        ijk = np.rint((pos - np.asarray(grid.min_corner_m)) / grid.voxel_size_m - 0.5).astype(int)
        for p, c in zip(ijk, np.asarray(h.batched_colors), strict=True):
            out[tuple(int(x) for x in p)] = c.astype(np.uint8)
    return out


@needs_viser
def test_live_view_draws_unconfirmed_voxels_pale_or_hides_them():
    """The analytic point reflector (test_nbv): a level view leaves the whole arc unconfirmed, a
    rolled one confirms the echo; what the view sends is checked voxel by voxel against the layer."""
    import math

    from test_nbv import GRID, SPEC, _echo_image, _look_at_target

    import gpumap
    from gpumap.core.params import MapperParams
    from gpumap.viewer.live import MapViewer, colormap_u8

    # the visible rule: two clear views confirm the echo there (the drawing is what is tested here; under
    # the evidence rule the two views leave every voxel of the arc unconfirmed)
    m = with_confidence(gpumap.MinMaxMapper(SPEC, GRID, "numpy", MapperParams(rule="visible")))
    v = MapViewer(SPEC, GRID, m.threshold, port=_free_port(), show_pings=False)
    turbo = colormap_u8("turbo")
    nz = GRID.shape[2]

    def height_rgb(k: int) -> np.ndarray:
        return turbo[min(255, max(0, int((k + 0.5) / nz * 255)))]

    def check(mode: str) -> tuple[int, int]:
        conf = m.layer("confidence").states()
        got = _drawn(v, GRID)
        shown = conf == 3 if mode == "hidden" else conf >= 2
        want = {tuple(int(x) for x in ijk) for ijk in np.argwhere(shown)}
        assert set(got) == want
        for ijk, c in got.items():
            base = height_rgb(ijk[2])
            assert np.array_equal(c, base if conf[ijk] == 3 or mode == "as confirmed" else _pale(base)), ijk
        return int((conf == 3).sum()), int((conf == 2).sum())

    try:
        n = []
        for roll in (0.0, math.pi / 2, math.pi / 4):
            T = _look_at_target(roll)
            m.integrate(_echo_image(T), T)
            v.ping(_echo_image(T), T, m, force=True)  # only the changed blocks are sent again
            n.append(check("pale"))
        assert n[0][0] == 0 and n[0][1] >= 5 and n[1][0] >= 1  # both kinds were drawn
        for mode in ("hidden", "as confirmed", "pale"):
            v._unconfirmed.value = mode
            v._recolour()
            check(mode)
    finally:
        v.close()
    # a layer that changes while the values do not: the blocks are sent again all the same
    v = MapViewer(SPEC, GRID, m.threshold, port=_free_port(), show_pings=False)
    try:
        values, conf = m.values(), m.layer("confidence").states()
        v.set_values(values)  # no layer yet: every occupied voxel in full colour
        assert all(np.array_equal(c, height_rgb(ijk[2])) for ijk, c in _drawn(v, GRID).items())
        v.set_values(values, conf)
        check("pale")
        flip = conf.copy()
        flip[conf >= 2] = 5 - conf[conf >= 2]  # confirmed <-> unconfirmed
        v.set_values(values, flip)
        got = _drawn(v, GRID)
        assert set(got) == {tuple(int(x) for x in i) for i in np.argwhere(conf >= 2)}
        for ijk, c in got.items():
            base = height_rgb(ijk[2])
            assert np.array_equal(c, base if flip[ijk] == 3 else _pale(base)), ijk
    finally:
        v.close()
