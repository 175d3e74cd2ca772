"""bench.peer_ratio: a loaded machine is refused (or its run marked not valid), the spread is reported."""

from __future__ import annotations

import pytest
from gpumap.bench import common, peer_ratio


def test_ratio_per_repeat_median_and_spread():
    s = peer_ratio.summarize([40.0, 42.0, 60.0], [2.0, 2.1, 2.0])
    assert s["ratio_per_repeat"] == pytest.approx([20.0, 20.0, 30.0])
    assert (s["ratio_median"], s["ratio_min"], s["ratio_max"]) == pytest.approx((20.0, 20.0, 30.0))
    assert s["oasis_ms_per_frame"] == {"median": 42.0, "min": 40.0, "max": 60.0}


def test_idle_check_reads_the_load_average(monkeypatch):
    monkeypatch.setattr(common, "load_average", lambda: [1.6, 1.5, 1.4])
    busy = peer_ratio.idle_check(max_load=0.3, max_others=100.0, sample_s=0.01)
    assert busy["load_avg"] == [1.6, 1.5, 1.4] and not busy["idle"]
    monkeypatch.setattr(common, "load_average", lambda: [0.1, 0.1, 0.1])
    assert peer_ratio.idle_check(max_load=0.3, max_others=100.0, sample_s=0.01)["idle"]


def test_a_loaded_machine_is_refused_before_any_work(monkeypatch, tmp_path, capsys):
    monkeypatch.setattr(peer_ratio, "idle_check",
                        lambda *a, **k: {"load_avg": [1.6, 1.5, 1.4], "others_cores": 1.6, "idle": False})
    monkeypatch.setattr(peer_ratio, "load_frames", lambda *a: pytest.fail("work started on a loaded machine"))
    rc = peer_ratio.main(["--oasis-src", str(tmp_path), "--out", str(tmp_path / "out")])
    assert rc == 3 and "not idle" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_others_are_pooled_over_the_passes_by_wall_time():
    """One 25 ms pass that caught a shell's 10 ms tick reads ~0.4 cores; pooled with minute-long
    passes it weighs by its wall time, and a pass without a sample is left out."""
    passes = [{"others_cores": 0.0, "wall_s": 30.0}, {"others_cores": 0.4, "wall_s": 0.025},
              {"others_cores": None, "wall_s": 1.0}, {"others_cores": 0.3, "wall_s": 30.0}]
    assert peer_ratio.pooled_others(passes) == pytest.approx((0.4 * 0.025 + 0.3 * 30.0) / 60.025)
    assert peer_ratio.pooled_others([{"others_cores": None, "wall_s": 1.0}]) is None
