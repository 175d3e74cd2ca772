"""The ``gpumap`` command line: every flag checked before work, one-line errors, outputs as a set."""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import gpumap.sim.demo
import numpy as np
import pytest
from conftest import DATA, needs_data

import gpumap.commands.demo
import gpumap.commands.replay
import gpumap.pipeline.job
from gpumap import commands as cli
from gpumap.atomic import output_set
from gpumap.commands import common
from gpumap.errors import BackendUnavailableError
from gpumap.io import FormatError
from gpumap.io.oculus import encode_simple_ping

ROOT = Path(__file__).resolve().parents[1]


def _run(argv: list[str], capsys) -> tuple[int, list[str]]:
    """``gpumap ARGV`` in this process: (exit status, the lines it wrote to stderr)."""
    try:
        rc = cli.main(argv)
    except SystemExit as e:
        rc = e.code
    return rc, capsys.readouterr().err.splitlines()


@pytest.fixture
def no_work(monkeypatch):
    """Make the work behind every verb fail loudly: flags must be refused before it starts."""

    def started(*a, **k):
        raise AssertionError("work started before the flags were checked")

    monkeypatch.setattr(gpumap.commands.replay, "_replay", started)
    monkeypatch.setattr(gpumap.sim.demo, "run_demo", started)
    import bench.__main__

    monkeypatch.setattr(bench.__main__, "run", started)


A_FILE = "pyproject.toml"  # an existing file (the tests run from the repository root)

BAD_FLAGS = [
    ("replay", ["--threshold", "abc"], "--threshold"),
    ("replay", ["--threshold", "0"], "--threshold"),
    ("replay", ["--threshold", "1.5"], "--threshold"),
    ("replay", ["--threshold", "nan"], "--threshold"),
    ("replay", ["--voxel-size", "0"], "--voxel-size"),
    ("replay", ["--voxel-size", "-0.05"], "--voxel-size"),
    ("replay", ["--voxel-size", "inf"], "--voxel-size"),
    ("replay", ["--stride", "0"], "--stride"),
    ("replay", ["--stride", "1.5"], "--stride"),
    ("replay", ["--max-frames", "0"], "--max-frames"),
    ("replay", ["--grid", "1,2,3"], "--grid"),
    ("replay", ["--grid", "0,0,0,1,1,x"], "--grid"),
    ("replay", ["--grid", "1,0,0,0,1,1"], "--grid"),
    ("replay", ["--grid", "-1000,-1000,-1000,1000,1000,1000", "--voxel-size", "0.001"], "--grid"),
    ("replay", ["--vfov-deg", "200"], "--vfov-deg"),
    ("replay", ["--backend", "cuda9"], "--backend"),
    ("replay", ["--method", "fast"], "--method"),
    ("replay", ["--rule", "shadow"], "--rule"),
    ("replay", ["--method", "template", "--rule", "visible"], "--rule"),
    ("replay", ["--out", A_FILE], "--out"),
    ("replay", ["--out", f"{A_FILE}/sub"], "--out"),
    ("replay", ["--bogus"], "--bogus"),
    ("replay", ["--voxel", "0.1"], "--voxel"),  # abbreviations are unknown flags too
    ("replay", ["--seed", "3"], "--seed"),  # flags of --ekf without it: refused, not ignored
    ("replay", ["--odometry-noise", "0.01", "0.01"], "--odometry-noise"),
    ("ros-play", ["x", "--voxel-size", "0.1"], "--voxel-size"),  # flags of --write-params without it
    ("ros-play", ["x", "--backend", "numpy"], "--backend"),
    ("demo", ["--voxel-size", "0"], "--voxel-size"),
    ("demo", ["--voxel-size", "-1"], "--voxel-size"),
    ("demo", ["--pings", "0"], "--pings"),
    ("demo", ["--pings", "ten"], "--pings"),
    ("demo", ["--pose-noise", "-1"], "--pose-noise"),
    ("demo", ["--threshold", "abc"], "--threshold"),
    ("demo", ["--threshold", "2"], "--threshold"),
    ("demo", ["--backend", "gpu"], "--backend"),
    ("demo", ["--scene", "moon"], "--scene"),
    ("demo", ["--out", A_FILE], "--out"),
    ("demo", ["--bogus"], "--bogus"),
    ("bench", ["--pings", "0"], "--pings"),
    ("bench", ["--voxel", "0.03", "0"], "--voxel"),
    ("bench", ["--threshold", "abc"], "--threshold"),
    ("bench", ["--fnr", "2"], "--fnr"),
    ("bench", ["--numpy-cap", "0"], "--numpy-cap"),
    ("bench", ["--backend", "cuda9"], "--backend"),
    ("bench", ["--pings-from", "no/such/pings.npz"], "--pings-from"),
    ("bench", ["--out", A_FILE], "--out"),
    ("bench", ["--bogus"], "--bogus"),
    ("info", ["--bogus"], "--bogus"),
]


@pytest.mark.parametrize(("verb", "args", "flag"), BAD_FLAGS,
                         ids=[f"{v}{''.join(a)}" for v, a, _ in BAD_FLAGS])
def test_bad_flag_exits_2_with_one_line_naming_it(verb, args, flag, tmp_path, capsys, no_work,
                                                  monkeypatch) -> None:
    monkeypatch.chdir(ROOT)
    path = [str(tmp_path)] if verb == "replay" else []  # an existing path: only the flags are wrong
    rc, err = _run([verb, *path, *args], capsys)
    assert rc == 2, err
    assert len(err) == 1, err
    assert flag in err[0] and err[0].startswith(f"gpumap {verb}: error:"), err
    assert "Traceback" not in err[0]
    assert Path(A_FILE).is_file()


def test_good_flags_pass_the_checks(tmp_path, capsys, no_work) -> None:
    """The validators take what the commands always took (the work itself is stubbed out)."""
    out = str(tmp_path / "o")
    argv = ["replay", "x", "--threshold", "auto", "--grid=-1,-1,-1,1,1,1", "--stride", "3",
            "--voxel-size", "0.1", "--backend", "numpy", "--vfov-deg", "12", "--out", out]
    with pytest.raises(AssertionError, match="work started"):
        cli.main(argv)
    with pytest.raises(AssertionError, match="work started"):
        cli.main(["demo", "--pose-noise", "0", "--pings", "3", "--threshold", "1", "--out", out])
    assert capsys.readouterr().err == "" and os.listdir(tmp_path) == []


def test_cli_process_prints_one_line_and_no_traceback(tmp_path: Path) -> None:
    """The real entry point, in a child process: stderr is exactly one line."""
    for args in (["replay", str(tmp_path), "--stride", "0"], ["demo", "--pings", "0"], ["nope"],
                 ["replay", str(tmp_path / "missing"), "--out", str(tmp_path / "o")]):
        r = subprocess.run([sys.executable, "-m", "gpumap.commands", *args], capture_output=True, text=True,
                           cwd=ROOT, timeout=60)
        assert r.returncode == 2, (args, r.stderr)
        lines = r.stderr.strip().splitlines()
        assert len(lines) == 1 and "Traceback" not in r.stderr, (args, r.stderr)
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("exc", [ValueError("bad value"), TypeError("bad type"),
                                 BackendUnavailableError("no CUDA here"), FormatError("bad byte 12"),
                                 FileNotFoundError("no file")])
def test_gpumap_errors_become_one_line(exc, tmp_path, capsys, monkeypatch) -> None:
    def fail(*a, **k):
        raise exc

    out = tmp_path / "o"
    monkeypatch.setattr(gpumap.commands.replay, "_replay", fail)
    monkeypatch.setattr(gpumap.sim.demo, "run_demo", fail)
    for verb, path in (("replay", [str(tmp_path)]), ("demo", [])):
        rc, err = _run([verb, *path, "--out", str(out)], capsys)
        assert rc == 2 and len(err) == 1, err
        assert err[0].startswith(f"gpumap {verb}: ") and str(exc) in err[0], err
        assert ("format error" in err[0]) == isinstance(exc, FormatError)
        assert not out.exists() and os.listdir(tmp_path) == []  # nothing written, nothing left


def test_bugs_keep_their_traceback_and_ctrl_c_is_one_line(tmp_path, capsys, monkeypatch) -> None:
    def bug(*a, **k):
        raise RuntimeError("a bug")

    monkeypatch.setattr(gpumap.commands.replay, "_replay", bug)
    with pytest.raises(RuntimeError, match="a bug"):
        cli.main(["replay", str(tmp_path), "--out", str(tmp_path / "o")])

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(gpumap.commands.replay, "_replay", interrupted)
    rc, err = _run(["replay", str(tmp_path), "--out", str(tmp_path / "o")], capsys)
    assert rc == 130 and err == ["gpumap replay: interrupted"]


def test_corrupt_recording_is_one_format_error_line(tmp_path, capsys) -> None:
    p = tmp_path / "bad.raw"
    p.write_bytes(encode_simple_ping(np.zeros((10, 4), np.uint8), [-10, 0, 5, 10], 0.01)[:-3])
    out = tmp_path / "o"
    rc, err = _run(["replay", str(p), "--static", "--no-progress", "--out", str(out)], capsys)
    assert rc == 2 and len(err) == 1 and "format error" in err[0], err
    assert not out.exists()


# ------------------------------------------------------------------ --out onto a file
@pytest.mark.parametrize("verb", ["replay", "demo", "bench"])
def test_out_onto_a_file_is_refused_at_once(verb, tmp_path, capsys, monkeypatch) -> None:
    monkeypatch.chdir(ROOT)
    f = tmp_path / "taken"
    f.write_bytes(b"keep me")
    path = [str(DATA / "oasis_tank" if DATA else tmp_path)] if verb == "replay" else []
    t = time.perf_counter()
    rc, err = _run([verb, *path, "--out", str(f)], capsys)
    assert time.perf_counter() - t < 1.0
    assert rc == 2 and len(err) == 1 and "--out" in err[0] and "is a file" in err[0], err
    assert f.read_bytes() == b"keep me" and os.listdir(tmp_path) == ["taken"]


def test_output_set_refuses_a_file(tmp_path) -> None:
    f = tmp_path / "taken"
    f.write_bytes(b"x")
    with pytest.raises(ValueError, match="is a file"), output_set(f):
        pass
    assert f.read_bytes() == b"x"


# ------------------------------------------------------------------ replay outputs as a set
SMALL = ["--stride", "20", "--max-frames", "3", "--voxel-size", "0.1", "--backend", "numpy", "--no-progress",
         "--surface"]


def _snapshot(d: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(d.iterdir())}


@pytest.fixture(scope="module")
def previous(tmp_path_factory) -> tuple[Path, dict[str, bytes]]:
    """A complete replay output set (pictures included), made once for the module."""
    if DATA is None:
        pytest.skip("shared/data not found")
    out = tmp_path_factory.mktemp("previous") / "out"
    assert gpumap.commands.replay.main([str(DATA / "oasis_tank"), *SMALL, "--out", str(out)]) == 0
    snap = _snapshot(out)
    assert set(snap) == {"map.npz", "surface.npz", "occupied.ply", "views.png", "floor_slice.png",
                         "summary.json"}
    return out, snap


@pytest.fixture
def old_out(previous, tmp_path) -> Path:
    out = tmp_path / "out"
    shutil.copytree(previous[0], out)
    return out


def _replace_call(monkeypatch, out: Path, n: int, action) -> None:
    """Call ``action`` at the ``n``-th os.replace that moves a file INTO ``out`` (the swap)."""
    real = os.replace
    seen = []

    def replace(src, dst, *a, **k):
        if Path(dst).parent == out:
            seen.append(dst)
            if len(seen) == n:
                action()
        return real(src, dst, *a, **k)

    monkeypatch.setattr(os, "replace", replace)


def _interrupt():
    raise KeyboardInterrupt


def _ply_interrupted(*a, **k):
    raise KeyboardInterrupt


def _pictures_interrupted(*a, **k):
    raise KeyboardInterrupt


@needs_data
@pytest.mark.parametrize("step", ["after map.npz", "in the pictures", "before summary.json",
                                  "in the swap"])
def test_interrupted_replay_leaves_the_previous_outputs(step, previous, old_out, monkeypatch,
                                                        tmp_path) -> None:
    if step == "after map.npz":
        monkeypatch.setattr(gpumap.pipeline.job, "write_ply", _ply_interrupted)
    elif step == "in the pictures":
        monkeypatch.setattr(gpumap.pipeline.job, "save_pictures", _pictures_interrupted)
    elif step == "before summary.json":  # the last file: everything else is written
        real = json.dumps

        def dumps(o, *a, **k):
            return _interrupt() if isinstance(o, dict) and "frames" in o else real(o, *a, **k)

        monkeypatch.setattr(json, "dumps", dumps)
    else:  # Ctrl-C half way through moving the new files in: every move is undone
        _replace_call(monkeypatch, old_out, 2, _interrupt)
    with pytest.raises(KeyboardInterrupt):
        gpumap.commands.replay.main([str(DATA / "oasis_tank"), *SMALL, "--threshold", "0.3",
                                     "--out", str(old_out)])
    assert _snapshot(old_out) == previous[1]  # byte-identical, no partial folder left inside
    assert os.listdir(tmp_path) == ["out"]


@pytest.fixture
def sigint(request):
    """Set SIGINT's Python handler to ``request.param`` for the test, and restore it after.

    The disposition a test process inherits is not Python's default everywhere: a job that a
    non-interactive shell starts in the background (``pytest &``, ``nohup``, many CI runners)
    inherits SIGINT *ignored*, and Python then installs no KeyboardInterrupt handler. A test of
    what Ctrl-C does must say which handler it means instead of assuming one.
    """
    if threading.current_thread() is not threading.main_thread():
        pytest.skip("signal handlers are set in the main thread only")
    old = signal.signal(signal.SIGINT, request.param)
    yield request.param
    signal.signal(signal.SIGINT, old)


@needs_data
@pytest.mark.parametrize("sigint", [signal.default_int_handler], indirect=True)
def test_ctrl_c_during_the_swap_waits_for_the_complete_new_set(old_out, monkeypatch, sigint) -> None:
    _replace_call(monkeypatch, old_out, 1, lambda: os.kill(os.getpid(), signal.SIGINT))
    with pytest.raises(KeyboardInterrupt):
        gpumap.commands.replay.main([str(DATA / "oasis_tank"), *SMALL, "--threshold", "0.3", "--no-pictures",
                            "--out", str(old_out)])
    s = json.loads((old_out / "summary.json").read_text())
    assert s["threshold"] == 0.3  # the new set, whole (and the old pictures gone with the old set)
    assert sorted(os.listdir(old_out)) == ["map.npz", "occupied.ply", "summary.json", "surface.npz"]


@needs_data
@pytest.mark.parametrize("sigint", [signal.SIG_IGN], indirect=True)
def test_an_ignored_ctrl_c_stays_ignored_through_the_swap(old_out, monkeypatch, sigint) -> None:
    """A process that ignores SIGINT (started in the background) still ignores it after the swap
    held it: the run completes, the new set is whole, and the disposition is still SIG_IGN."""
    _replace_call(monkeypatch, old_out, 1, lambda: os.kill(os.getpid(), signal.SIGINT))
    assert gpumap.commands.replay.main([str(DATA / "oasis_tank"), *SMALL, "--threshold", "0.3",
                                        "--no-pictures", "--out", str(old_out)]) == 0
    assert json.loads((old_out / "summary.json").read_text())["threshold"] == 0.3
    assert sorted(os.listdir(old_out)) == ["map.npz", "occupied.ply", "summary.json", "surface.npz"]
    assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN


@needs_data
def test_replay_replaces_the_whole_set_and_keeps_other_files(old_out, previous, capsys) -> None:
    (old_out / "notes.txt").write_text("mine")
    assert gpumap.commands.replay.main([str(DATA / "oasis_tank"), *SMALL, "--threshold", "0.3",
                                        "--no-pictures", "--out", str(old_out)]) == 0
    snap = _snapshot(old_out)
    # the old run's pictures do not outlive it; files that are not replay's stay
    assert set(snap) == {"map.npz", "surface.npz", "occupied.ply", "summary.json", "notes.txt"}
    assert snap["notes.txt"] == b"mine"
    assert snap["map.npz"] != previous[1]["map.npz"]
    assert json.loads(snap["summary.json"])["threshold"] == 0.3
    assert f"wrote {old_out}/" in capsys.readouterr().out


# ------------------------------------------------------------------ demo outputs as a set
def _fake_demo(files: dict[str, bytes], fail: bool):
    def run_demo(args, open_view=None):
        for name, data in files.items():
            (Path(args.out) / name).write_bytes(data)
            if fail:
                raise KeyboardInterrupt
        return {"scene": "tank", "backend": "numpy", "rule": "visible", "voxel_size_m": 0.1, "images": 1,
                "ms_per_image": 1.0, "demo_s": 1.0, "rules": {}}

    return run_demo


def test_interrupted_demo_leaves_the_previous_outputs(tmp_path, monkeypatch, capsys) -> None:
    out = tmp_path / "demo"
    old = {name: f"old {name}".encode() for name in gpumap.commands.demo.OUTPUTS}
    monkeypatch.setattr(gpumap.sim.demo, "run_demo", _fake_demo(old, fail=False))
    assert gpumap.commands.demo.main(["--out", str(out), "--no-progress"]) == 0
    assert _snapshot(out) == old
    new = {name: f"new {name}".encode() for name in gpumap.commands.demo.OUTPUTS}
    monkeypatch.setattr(gpumap.sim.demo, "run_demo", _fake_demo(new, fail=True))
    with pytest.raises(KeyboardInterrupt):
        gpumap.commands.demo.main(["--out", str(out), "--no-progress"])
    assert _snapshot(out) == old and os.listdir(tmp_path) == ["demo"]
    monkeypatch.setattr(gpumap.sim.demo, "run_demo", _fake_demo(new, fail=False))
    assert gpumap.commands.demo.main(["--out", str(out), "--no-progress"]) == 0
    assert _snapshot(out) == new
    capsys.readouterr()


def _parsers():
    import gpumap.bench.__main__ as bench

    import gpumap.commands.export
    import gpumap.commands.merge
    import gpumap.commands.plan
    import gpumap.commands.refine
    import gpumap.commands.ros
    import gpumap.commands.ros_play
    import gpumap.commands.view

    c = gpumap.commands
    return {"demo": c.demo._parser(), "replay": c.replay._parser(), "view": c.view._parser(),
            "export": c.export._parser(), "merge": c.merge._parser(), "refine": c.refine._parser(),
            "plan": c.plan._parser(), "bench": bench._parser(), "ros": c.ros._parser(),
            "ros-play": c.ros_play._parser()}


def test_every_option_has_a_plain_help_line() -> None:
    """Each option of each subcommand says what it does, in plain words (no reST backticks), and
    the same idea has one spelling: --no-progress turns progress bars off everywhere."""
    parsers = _parsers()
    assert set(parsers) | {"info"} == set(cli.COMMANDS)
    missing, rst = [], []
    for verb, p in parsers.items():
        for act in p._actions:
            if act.help == argparse.SUPPRESS or isinstance(act, argparse._HelpAction):
                continue
            name = f"gpumap {verb} {'/'.join(act.option_strings) or act.dest}"
            if not (act.help or "").strip():
                missing.append(name)
            if "`" in (act.help or ""):
                rst.append(name)
        # the description too
        if "`" in (p.description or ""):
            rst.append(f"gpumap {verb} (description)")
        opts = {o for a in p._actions if a.help != argparse.SUPPRESS for o in a.option_strings}
        assert "--quiet" not in opts, f"gpumap {verb}: progress bars go off with --no-progress"
        if any(o.startswith("--voxel") for o in opts):  # one spelling of the voxel edge too
            assert "--voxel-size" in opts, f"gpumap {verb}: the voxel edge is --voxel-size"
        if verb in ("demo", "replay", "bench"):
            assert "--no-progress" in opts, verb
    assert not missing, f"options without help: {missing}"
    assert not rst, f"help with reStructuredText backticks: {rst}"


def test_an_output_file_that_exists_is_replaced_not_refused(tmp_path) -> None:
    """gpumap export/merge run twice onto one name, --record or --write-params onto an old file:
    the file is replaced; refused only where its folder cannot hold it."""
    f = tmp_path / "map.bt"
    f.write_bytes(b"old")
    assert common.output_file(str(f)) == f
    with pytest.raises(argparse.ArgumentTypeError, match="is a file"):
        common.output_file(str(f / "inside.bt"))
    with pytest.raises(argparse.ArgumentTypeError, match="is a folder"):
        common.output_file(str(tmp_path))


def test_third_party_info_logs_stay_quiet() -> None:
    """gpumap logs its own lines at INFO; PyOpenGL's "No OpenGL_accelerate module loaded" (INFO, on
    every replay and demo) is not one of them."""
    import logging

    root, level = logging.getLogger(), logging.getLogger().level
    root.setLevel(logging.INFO)  # as gpumap's basicConfig leaves it outside pytest
    try:
        assert cli.main(["info"]) == 0
        assert logging.getLogger("gpumap").isEnabledFor(logging.INFO)
        assert not logging.getLogger("OpenGL.acceleratesupport").isEnabledFor(logging.INFO)
    finally:
        root.setLevel(level)


def test_view_offers_only_what_applies_to_a_saved_map() -> None:
    opts = {o for a in _parsers()["view"]._actions for o in a.option_strings}
    assert {"--view-host", "--view-port", "--view-hold", "--threshold"} <= opts
    assert not opts & {"--view", "--view-every", "--record"}, opts


def test_info_names_backends_as_mappers_do_and_no_cuda_warning_on_a_cpu_machine(capsys) -> None:
    """gpumap info lists each backend under the name MinMaxMapper(...).backend reports; without a
    CUDA driver, Warp's 'could not find the NVIDIA CUDA driver' line is not printed (a fresh process)."""
    import gpumap
    from gpumap.backends import cuda_driver_loadable

    assert cli.main(["info"]) == 0
    out = capsys.readouterr().out.splitlines()
    listed = [ln.split()[0] for ln in out if ln.startswith("  ") and "cannot run" not in ln]
    assert listed and out[-1] == f"auto picks: {listed[0]}"
    spec = gpumap.SonarSpec.uniform(n_beams=4, n_bins=4)
    grid = gpumap.GridSpec((0, 0, 0), (1, 1, 1), 0.5)
    for name in listed:
        assert gpumap.MinMaxMapper(spec, grid, backend=name).backend == name
    assert gpumap.MinMaxMapper(spec, grid).backend == listed[0]
    if cuda_driver_loadable():
        pytest.skip("this machine has a CUDA driver: Warp has nothing to warn about")
    r = subprocess.run([sys.executable, "-m", "gpumap.commands", "info"], capture_output=True, text=True,
                       cwd=ROOT, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "CUDA driver" not in r.stderr + r.stdout, r.stderr


BENCH_SCRIPTS = ("ekf_bench", "frontend", "ab", "peer_ratio", "readme", "refine", "report",
                 "ros_bench", "rules_real", "sparse", "speed", "viewer_cost", "visibility",
                 "workers", "variation", "long_run")


@pytest.mark.parametrize("name", BENCH_SCRIPTS)
def test_bench_scripts_help_is_plain_words(name, capsys) -> None:
    """python -m bench.NAME --help (the README and BENCHMARKS.md tell users to run them): exit 0
    before any work, no reStructuredText backticks in what it prints."""
    import importlib

    mod = importlib.import_module(f"bench.{name}")
    with pytest.raises(SystemExit) as e:
        mod.main(["--help"])
    out = capsys.readouterr().out
    assert e.value.code == 0 and out.startswith("usage:"), out[:200]
    assert "`" not in out, f"python -m bench.{name} --help: {[ln for ln in out.splitlines() if '`' in ln]}"
    if re.search(r"--voxel\b(?!-)", out):  # one spelling of the voxel edge, as in gpumap's commands
        assert "--voxel-size" in out, f"python -m bench.{name}: the voxel edge is --voxel-size"
