"""What watching costs: ``gpumap replay`` of the real tank at 5 cm with and without the live view.

    python -m bench.viewer_cost [--data ../shared/data/oasis_tank] [--repeat 3]
"""

from __future__ import annotations

import argparse
import json
import shutil
import socket
import subprocess
import tempfile
import time
from pathlib import Path

from .common import bench_parser, load_average, machine_info, oasis_tank_dir, write_json


def _session_args(view: bool, record: Path | None, port: int) -> argparse.Namespace:
    return argparse.Namespace(view=view, view_host="127.0.0.1", view_port=port, view_every=10, view_hold=0.0,
                              record=record, path="oasis_tank", view_sessions=[])


def _browser(chromium: str, port: int, profile: Path, session) -> subprocess.Popen:
    """A headless Chromium on the view, connected and settled."""
    browser = subprocess.Popen([chromium, "--headless", "--no-sandbox", "--use-angle=swiftshader",
                                "--enable-unsafe-swiftshader", f"--user-data-dir={profile}",
                                "--remote-debugging-port=0", f"http://127.0.0.1:{port}"],
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    t_end = time.monotonic() + 30
    while not session.viewer.server.get_clients() and time.monotonic() < t_end:
        time.sleep(0.2)
    time.sleep(2.0)  # let the page settle before timing
    return browser


def main(argv: list[str] | None = None) -> int:
    from gpumap.io import open_recording
    from gpumap.pipeline.replay import run_replay
    from gpumap.viewer.session import Session, SessionLayer

    ap = bench_parser("viewer_cost", __doc__, out="bench/results/viewer_cost.json", voxel=0.05)
    ap.add_argument("--data", type=Path, default=None,
                    help="the oasis_tank folder (default: shared/data beside the checkout)")
    ap.add_argument("--repeat", type=int, default=3, help="runs of each mode, the best kept (default 3)")
    a = ap.parse_args(argv)
    a.data = a.data or oasis_tank_dir()
    if a.data is None:
        raise SystemExit("bench.viewer_cost: shared/data/oasis_tank not found; pass --data")
    rec = open_recording(a.data)
    warm, _ = run_replay(rec, voxel_size_m=a.voxel, progress=False)  # compile, size the grid
    grid, spec, thr, chromium = warm.grid, warm.spec, 0.4, shutil.which("chromium")
    rows: dict[str, list[float]] = {"none": [], "view_no_browser": [], "view": [], "record": []}
    cpu: dict[str, list[float]] = {k: [] for k in rows}
    extra: dict[str, dict] = {}
    tmp = Path(tempfile.mkdtemp(prefix="viewer-cost-"))
    try:
        for _ in range(a.repeat):
            for mode in rows:
                session = browser = None
                if mode.startswith("view"):
                    with socket.socket() as s:  # a free port
                        s.bind(("127.0.0.1", 0))
                        port = s.getsockname()[1]
                    session = Session(_session_args(True, None, port), spec, grid, thr, title="viewer_cost")
                    if chromium and mode == "view":
                        browser = _browser(chromium, port, tmp / "profile", session)
                elif mode == "record":
                    session = Session(_session_args(False, tmp / "run.gpumap-rec", 0), spec, grid, thr)
                c0 = time.process_time()
                layers = [] if session is None else [SessionLayer(lambda _m, s=session: s)]
                mapper, st = run_replay(rec, voxel_size_m=a.voxel, grid=grid, progress=False, layers=layers)
                if session is not None:
                    t0 = time.perf_counter()
                    session.finish(mapper)
                    st["seconds_total"] += time.perf_counter() - t0  # the final map and the file's close
                    if session.viewer is not None:
                        v = session.viewer
                        extra[mode] = {"browser_connected": len(v.server.get_clients()) > 0,
                                       "map_updates": v.map_updates,
                                       "seconds_viewing": round(v.seconds_viewing, 3),
                                       "pings": v.n_pings}
                        v.close()
                    if session.recorder is not None:
                        extra["record"] = {"bytes": (tmp / "run.gpumap-rec").stat().st_size,
                                           "pings": session.recorder.n_pings}
                cpu[mode].append(time.process_time() - c0)
                if browser is not None:
                    browser.terminate()
                    browser.wait(10)
                rows[mode].append(st["seconds_total"])
                extra.setdefault("frames", st["frames"])
                extra.setdefault("backend", st["backend"])
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    base = min(rows["none"])
    out = {
        "what": "gpumap replay of the OASIS tank with the live view / a recording, best of "
                f"{a.repeat} runs of seconds_total", "voxel_size_m": a.voxel, "frames": extra["frames"],
           "backend": extra["backend"],
        "seconds": {k: round(min(v), 3) for k, v in rows.items()},
        "seconds_all": {k: [round(x, 3) for x in v] for k, v in rows.items()},
        "overhead": {k: round(min(v) / base - 1.0, 3) for k, v in rows.items() if k != "none"},
        "cpu_seconds": {k: round(min(v), 3) for k, v in cpu.items()},
        "cpu_overhead": {k: round(min(v) / min(cpu["none"]) - 1.0, 3) for k, v in cpu.items() if k != "none"},
        "load_average": load_average(), "target_overhead": 0.20, "view": extra.get("view"),
        "view_no_browser": extra.get("view_no_browser"),
        "note": "the 2-core machine also runs the headless browser (SwiftShader software WebGL) in the "
                "'view' row; on the vehicle the browser runs on the operator's laptop, as in "
                "'view_no_browser' (the same messages are built and queued, nobody draws them)",
        "record": extra.get("record"), "machine": machine_info()}
    write_json(a.out, out, indent=2)
    keys = ("frames", "backend", "seconds", "overhead", "cpu_overhead", "load_average", "view", "record")
    print(json.dumps({k: out[k] for k in keys}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
