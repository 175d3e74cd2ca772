"""The memory model (gpumap.memory): it covers what bench/memory.py measured, prices a rule from one
table, and gpumap replay refuses a grid that would not fit before allocating it, with the figure."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from conftest import DATA, needs_data

from gpumap import memory

RESULTS = Path(__file__).resolve().parents[1] / "bench" / "results" / "memory_cpu_2c.json"


def test_the_model_covers_every_measured_backend_and_rule() -> None:
    """For every backend and rule measured (with pictures, as gpumap replay runs by default, and
    without), the model's bytes a voxel are at least the steepest measured slope and not far above
    it, its fixed cost covers the measured ones, and its figure every peak measured."""
    res = json.loads(RESULTS.read_text())
    fits = res["fit"]
    assert {k.split("/")[0] for k in fits} >= {"numpy", "warp-cpu", "opencl-cpu"}
    assert {k.split("/")[1] for k in fits} >= {"plain", "visible", "evidence"}
    for rule in ("plain", "visible", "evidence"):  # the model's bytes a voxel: at least the steepest,
        # not far above
        steepest = max(f["bytes_per_voxel"] for k, f in fits.items() if k.split("/")[1] == rule)
        assert steepest <= memory.bytes_per_voxel(rule) <= 1.1 * steepest + 1, (rule, steepest)
    for key, f in fits.items():
        backend, rule = key.split("/")[:2]
        assert memory.run_bytes(0, rule, backend) >= (f["fixed_mib"] - f["worst_residual_mib"]) * 2**20, key
    for p in res["points"]:  # and every point measured
        assert p["rc"] == 0, p
        assert memory.run_bytes(p["voxels"], p["rule"], p["backend"]) >= p["peak_rss_bytes"], p


def test_a_rule_is_priced_from_its_state_bytes_alone(monkeypatch) -> None:
    monkeypatch.setitem(memory.STATE_BYTES, "evidence", 20)
    assert memory.bytes_per_voxel("evidence") == memory.STATE_COPIES * 20 + memory.EXTRA_BYTES
    bpv = memory.bytes_per_voxel
    assert bpv("evidence") > bpv("visible") > bpv("plain")
    with pytest.raises(ValueError, match="rule"):
        memory.bytes_per_voxel("nonsense")


def test_sizes_parse() -> None:
    assert memory.parse_size("auto") is None
    assert memory.parse_size("8G") == 8 << 30
    assert memory.parse_size("512MiB") == 512 << 20
    assert memory.parse_size("1.5g") == int(1.5 * (1 << 30))
    assert memory.parse_size("1000") == 1000
    for bad in ("", "-1G", "0", "8X", "lots"):
        with pytest.raises(ValueError, match="size"):
            memory.parse_size(bad)


def test_check_names_the_figure_and_the_cap() -> None:
    need = memory.run_bytes(864_000_000, "visible", "numpy")
    with pytest.raises(ValueError, match=r"864,000,000 voxels .* need about 36\.[0-9] GiB .*bytes a voxel.*"
                                         r"set the cap \(max_memory=\)"):
        memory.check_run_fits(864_000_000, "visible", "numpy", max_bytes=need - 1)
    assert memory.check_run_fits(864_000_000, "visible", "numpy", max_bytes=need) == need


@needs_data
def test_replay_refuses_a_grid_over_the_cap_before_mapping(tmp_path, capsys) -> None:
    from gpumap.commands import main

    out = tmp_path / "out"
    rc = main(["replay", str(DATA / "oasis_tank"), "--grid=-40,-40,-20,40,40,20",
               "--no-progress", "--out", str(out)])  # 2.048e9 voxels: over 30 GiB, more than this machine
    err = capsys.readouterr().err
    assert rc == 2 and "2,048,000,000 voxels" in err and "--voxel-size" in err
    assert not out.exists()
