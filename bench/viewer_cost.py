"""What watching costs: ``gpumap replay`` of the real tank at 5 cm with and without the live view.

Runs the OASIS tank frames (``shared/data/oasis_tank``) through :func:`gpumap.replay.run_replay`
at 5 cm on the default backend, alternating: no view; ``--view`` served with a headless
Chromium connected (when Debian's ``chromium`` is installed; otherwise nobody watching);
``--record``. Each row is the best of ``--repeat`` runs of ``seconds_total`` (read + convert +
integrate + viewing, after the mapper's set-up), and of the process's CPU seconds (all its
threads: PoCL's, viser's, the recorder's; not the browser's), steadier than wall time on a
shared machine. Writes ``bench/results/viewer_cost.json``.

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

RESULTS = Path(__file__).resolve().parent / "results" / "viewer_cost.json"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _session_args(view: bool, record: Path | None, port: int) -> argparse.Namespace:
    return argparse.Namespace(view=view, view_host="127.0.0.1", view_port=port, view_every=10, view_hold=0.0,
                              record=record, path="oasis_tank", view_sessions=[])


def main(argv: list[str] | None = None) -> int:
    from gpumap.io import open_recording
    from gpumap.replay import run_replay
    from gpumap.viewer.session import Session

    ap = bench_parser("viewer_cost", __doc__)
    ap.add_argument("--data", type=Path, default=None,
                    help="the oasis_tank folder (default: shared/data beside the checkout)")
    ap.add_argument("--voxel-size", type=float, default=0.05, help="metres (default 0.05)")
    ap.add_argument("--repeat", type=int, default=3, help="runs of each mode, the best kept (default 3)")
    ap.add_argument("--out", type=Path, default=RESULTS, help="results file")
    a = ap.parse_args(argv)
    if a.data is None:
        a.data = oasis_tank_dir()
        if a.data is None:
            raise SystemExit("bench.viewer_cost: shared/data/oasis_tank not found; pass --data")

    rec = open_recording(a.data)
    warm, _ = run_replay(rec, voxel_size_m=a.voxel_size, progress=False)  # compile, size the grid
    grid, spec, thr = warm.grid, warm.spec, 0.4
    chromium = shutil.which("chromium")
    rows: dict[str, list[float]] = {"none": [], "view_no_browser": [], "view": [], "record": []}
    cpu: dict[str, list[float]] = {k: [] for k in rows}
    extra: dict[str, dict] = {}
    tmp = Path(tempfile.mkdtemp(prefix="viewer-cost-"))
    try:
        for _ in range(a.repeat):
            for mode in rows:
                session = None
                browser = None
                if mode.startswith("view"):
                    port = _free_port()
                    session = Session(_session_args(True, None, port), spec, grid, thr, title="viewer_cost")
                    if chromium and mode == "view":
                        browser = subprocess.Popen(
                            [chromium, "--headless", "--no-sandbox", "--use-angle=swiftshader",
                             "--enable-unsafe-swiftshader", f"--user-data-dir={tmp / 'profile'}",
                             "--remote-debugging-port=0", f"http://127.0.0.1:{port}"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
                        t_end = time.monotonic() + 30
                        while not session.viewer.server.get_clients() and time.monotonic() < t_end:
                            time.sleep(0.2)
                        time.sleep(2.0)  # let the page settle before timing
                elif mode == "record":
                    session = Session(_session_args(False, tmp / "run.gpumap-rec", 0), spec, grid, thr)
                c0 = time.process_time()
                mapper, st = run_replay(rec, voxel_size_m=a.voxel_size, grid=grid, progress=False,
                                        on_ping=None if session is None else session.ping)
                if session is not None:
                    t0 = time.perf_counter()
                    session.finish(mapper)
                    st["seconds_total"] += time.perf_counter() - t0  # the final map and the file's close
                    if session.viewer is not None:
                        extra[mode] = {"browser_connected": len(session.viewer.server.get_clients()) > 0,
                                       "map_updates": session.viewer.map_updates,
                                       "seconds_viewing": round(session.viewer.seconds_viewing, 3),
                                       "pings": session.viewer.n_pings}
                        session.viewer.close()
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
                f"{a.repeat} runs of seconds_total",
        "voxel_size_m": a.voxel_size,
        "frames": extra["frames"],
        "backend": extra["backend"],
        "seconds": {k: round(min(v), 3) for k, v in rows.items()},
        "seconds_all": {k: [round(x, 3) for x in v] for k, v in rows.items()},
        "overhead": {k: round(min(v) / base - 1.0, 3) for k, v in rows.items() if k != "none"},
        "cpu_seconds": {k: round(min(v), 3) for k, v in cpu.items()},
        "cpu_overhead": {k: round(min(v) / min(cpu["none"]) - 1.0, 3) for k, v in cpu.items() if k != "none"},
        "load_average": load_average(),
        "target_overhead": 0.20,
        "view": extra.get("view"),
        "view_no_browser": extra.get("view_no_browser"),
        "note": "the 2-core machine also runs the headless browser (SwiftShader software WebGL) in the "
                "'view' row; on the vehicle the browser runs on the operator's laptop, as in "
                "'view_no_browser' (the same messages are built and queued, nobody draws them)",
        "record": extra.get("record"),
        "machine": machine_info(),
    }
    write_json(a.out, out, indent=2)
    keys = ("frames", "backend", "seconds", "overhead", "cpu_overhead", "load_average", "view", "record")
    print(json.dumps({k: out[k] for k in keys}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
