"""bench/: one runner (python -m bench NAME) over every benchmark, and the helpers they share."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
from gpumap.bench import __main__ as runner
from gpumap.bench import common

BENCH = Path(runner.__file__).resolve().parent  # bench/ in a checkout, gpumap/bench installed


def test_the_runner_lists_every_benchmark_module(capsys):
    """Every module of bench/ with a main() is a name of python -m bench, and every name runs one."""
    with_main = {p.stem for p in BENCH.glob("*.py")
                 if re.search(r"^def main\(", p.read_text(), re.M) and p.stem != "__main__"}
    assert set(runner.BENCHMARKS) == with_main
    assert runner.main(["--list"]) == 0
    listed = capsys.readouterr().out
    for name in with_main:
        assert re.search(rf"^  {name} +\S", listed, re.M), name


@pytest.mark.parametrize("name", sorted(set(runner.BENCHMARKS) - {"sweep"}))
def test_the_runner_hands_the_arguments_to_the_named_benchmark(name, monkeypatch):
    import importlib

    mod = importlib.import_module(f"gpumap.bench.{name}")
    got = []
    monkeypatch.setattr(mod, "main", lambda argv: got.append(argv) or 7)
    assert runner.main([name, "--x", "1"]) == 7 and got == [["--x", "1"]]


def test_without_a_name_the_runner_runs_the_sweep_and_refuses_unknown_names(monkeypatch, tmp_path, capsys):
    seen = []
    result = {"tag": "t", "run": {"duration_s": 0}}
    monkeypatch.setattr(runner, "run", lambda args: seen.append(args) or result)
    assert runner.main(["--pings", "3", "--out", str(tmp_path)]) == 0
    assert runner.main(["sweep", "--pings", "4", "--out", str(tmp_path)]) == 0
    assert [a.pings for a in seen] == [3, 4]
    assert json.loads((tmp_path / "t.json").read_text())["tag"] == "t"
    assert runner.main(["no-such-bench"]) == 2 and "unknown benchmark" in capsys.readouterr().err
    assert len(seen) == 2


class FakeMapper:
    """Records what the timing helpers call, in order."""

    def __init__(self) -> None:
        self.calls: list[tuple] = []

    def integrate(self, image, pose) -> None:
        self.calls.append(("integrate", int(image[0]), int(pose[0])))

    def integrate_batch(self, images, poses) -> None:
        self.calls.append(("batch", [int(i[0]) for i in images]))

    def synchronize(self) -> None:
        self.calls.append(("sync",))

    def reset(self) -> None:
        self.calls.append(("reset",))


IMAGES = [np.array([k]) for k in range(5)]
POSES = [np.array([10 + k]) for k in range(5)]


def test_warm_up_integrates_then_forgets():
    m = FakeMapper()
    common.warm_up(m, IMAGES, POSES, 7)
    ints = [c for c in m.calls if c[0] == "integrate"]
    assert [c[1] for c in ints] == [0, 1, 2, 3, 4, 0, 1] and all(c[2] == c[1] + 10 for c in ints)
    assert m.calls[len(ints):] == [("sync",), ("reset",), ("sync",)]


def test_synced_ms_waits_for_every_ping_and_cycles_through_the_pings():
    m = FakeMapper()
    ms = common.synced_ms(m, IMAGES, POSES, 6, start=3)
    assert len(ms) == 6 and all(x >= 0 for x in ms)
    assert m.calls == [c for k in range(3, 9) for c in (("integrate", k % 5, 10 + k % 5), ("sync",))]
    assert len(common.synced_ms(FakeMapper(), IMAGES, POSES)) == 5


def test_stream_rate_synchronizes_once_at_the_end():
    m = FakeMapper()
    assert common.stream_rate(m, IMAGES, POSES, 12) > 0
    assert [c[0] for c in m.calls] == ["integrate"] * 12 + ["sync"]
    assert [c[1] for c in m.calls[:12]] == [k % 5 for k in range(12)]
    m = FakeMapper()
    common.stream_rate(m, np.stack(IMAGES), np.stack(POSES), batch=2)
    assert m.calls == [("batch", [0, 1]), ("batch", [2, 3]), ("batch", [4]), ("sync",)]


def test_spread():
    assert common.spread([3.0, 1.0, 2.0, 10.0]) == {"median": 2.5, "min": 1.0, "max": 10.0}


def test_idle_check_flags_a_loaded_machine():
    assert not common.idle_check(0.3, 100.0, sample_s=0.01, load=[1.2, 1.0, 0.9])["idle"]
    ok = common.idle_check(0.3, 100.0, sample_s=0.01, load=[0.1, 0.1, 0.1])
    assert ok["idle"] and ok["load_avg"] == [0.1, 0.1, 0.1]


def test_write_json_rounds_on_request_and_leaves_no_partial_file(tmp_path):
    doc = {"a": np.float32(1.23456789), "b": [np.int64(3), 2.0 / 3.0], "c": float("nan")}
    p = common.write_json(tmp_path / "sub" / "r.json", doc, digits=3)
    assert json.loads(p.read_text()) == {"a": 1.23, "b": [3, 0.667], "c": None}
    common.write_json(p, {"x": np.float64(0.1234567)}, indent=None)
    assert json.loads(p.read_text()) == {"x": 0.1234567}
    assert [q.name for q in p.parent.iterdir()] == ["r.json"]


def test_merge_json_keeps_the_other_sections(tmp_path):
    p = tmp_path / "m.json"
    common.merge_json(p, ["speed", "cpu"], {"rows": [1]}, schema="s/1")
    common.merge_json(p, ["speed", "gpu"], {"rows": [2]})
    common.merge_json(p, ["quality"], {"q": 1})
    want = {"schema": "s/1", "speed": {"cpu": {"rows": [1]}, "gpu": {"rows": [2]}}, "quality": {"q": 1}}
    assert json.loads(p.read_text()) == want


def test_put_block_replaces_only_between_the_markers(tmp_path):
    b, e = "<!-- begin:x -->", "<!-- end:x -->"
    p = tmp_path / "B.md"
    p.write_text(f"# T\n\nbefore\n\n{b}\nold\nlines\n{e}\n\n## Next\nafter\n")
    common.put_block(p, b, e, "new\n")
    assert p.read_text() == f"# T\n\nbefore\n\n{b}\nnew\n{e}\n\n## Next\nafter\n"
    q = tmp_path / "C.md"
    q.write_text("# T\n\n## Old section\nold text\n\n## Keep\nkept\n")
    common.put_block(q, b, e, "## Old section\nnew text", section="## Old section")
    assert q.read_text() == f"# T\n\n{b}\n## Old section\nnew text\n{e}\n\n## Keep\nkept\n"
    r = tmp_path / "D.md"
    r.write_text("# T\n")
    common.put_block(r, b, e, "x")
    assert r.read_text() == f"# T\n\n{b}\nx\n{e}\n"


def test_ping_files_under_either_name(tmp_path):
    imgs, poses = np.zeros((2, 3, 4), np.uint8), np.tile(np.eye(4), (2, 1, 1))
    np.savez(tmp_path / "a.npz", images=imgs, poses=poses)
    np.savez(tmp_path / "b.npz", imgs=imgs + 1, T=poses)
    np.savez(tmp_path / "c.npz", x=imgs)
    assert np.array_equal(common.load_ping_arrays(tmp_path / "a.npz")[0], imgs)
    assert np.array_equal(common.load_ping_arrays(tmp_path / "b.npz")[0], imgs + 1)
    with pytest.raises(ValueError, match="images and poses"):
        common.load_ping_arrays(tmp_path / "c.npz")


def test_load_results_reads_one_schema_and_passes_over_broken_files(tmp_path):
    (tmp_path / "speed_a.json").write_text(json.dumps({"schema": "gpumap-speed/1", "v": 1}))
    (tmp_path / "speed_b.json").write_text("{not json")
    (tmp_path / "speed_c.json").write_text(json.dumps({"schema": "gpumap-bench/1"}))
    (tmp_path / "other.json").write_text(json.dumps({"schema": "gpumap-speed/1"}))
    got = common.load_results(tmp_path, "speed_*.json", "gpumap-speed/")
    assert [(d["_file"], d["v"]) for d in got] == [("speed_a.json", 1)]


def test_tagged_path_is_file_name_safe(tmp_path):
    got = common.tagged_path(tmp_path, "speed_", "GPU NVIDIA H100/80GB")
    assert got == tmp_path / "speed_gpu-nvidia-h100-80gb.json"
