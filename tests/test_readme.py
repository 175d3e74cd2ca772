"""The README's figures stay true: each comes from a results file, and the real-tank one is re-measured."""

from __future__ import annotations

import json
import re
from pathlib import Path

from conftest import DATA, needs_data
from gpumap.bench import readme

ROOT = Path(__file__).resolve().parents[1]


def test_readme_blocks_are_what_the_results_files_give():
    for rel, names in readme.FILES.items():
        text = (ROOT / rel).read_text()
        assert readme.render(text, names) == text, f"{rel} figures are stale: run python -m bench.readme"
        for name in names:
            block = re.search(rf"<!-- begin:{name} -->\n(.*?)<!-- end:{name} -->", text, re.S).group(1)
            assert re.search(r"\d", block), f"block {name} of {rel} holds no figure"


def test_the_readme_is_short_and_starts_with_its_two_commands():
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) <= 200
    assert "pip install -e . && .venv/bin/gpumap demo" in text
    assert 'pip install -e ".[test]" && .venv/bin/python -m pytest -q' in text
    assert '-e ".[test]"' in (ROOT / ".ci" / "run").read_text()  # CI installs the same extra


def test_every_figure_row_names_its_machine_and_an_existing_results_file():
    for rel in readme.FILES:
        text = (ROOT / rel).read_text()
        for row in re.findall(r"^\| (.+) \| `([^`]+\.json)` \|$", text, re.M):
            cells, name = row
            if "*" in name:
                continue
            assert (ROOT / "bench" / "results" / name).is_file(), name
            assert cells.split(" | ")[-1] != "see the file", f"{rel}: {name} names no machine"


def test_the_machine_of_a_results_file_is_its_gpu_or_cpu():
    assert readme.machine_of("gpu_scale_h200.json") == "NVIDIA H200"
    assert readme.machine_of("cpu_amd-epyc_2c.json") == "AMD EPYC, 2 cores"
    assert readme.machine_of("no_such_file.json") == "see the file"


def test_links_between_the_readme_and_the_guide_resolve():
    for rel in ("README.md", "docs/guide.md"):
        base = (ROOT / rel).parent
        for target in re.findall(r"\]\(([^)#:]+\.(?:md|png))", (ROOT / rel).read_text()):
            assert (base / target).is_file(), f"{rel} links to {target}, which is not there"


def test_benchmarks_md_is_what_the_results_files_give(monkeypatch):
    """Every generated part of BENCHMARKS.md (the sweep, the real-frame speed, each benchmark's block)
    comes from bench/results: rendering it anew, without plots, gives the committed file byte for byte."""
    from gpumap.bench import report

    monkeypatch.chdir(ROOT)  # the blocks link their plots by the results folder's path from here
    assert report.main(["--check"]) == 0, "BENCHMARKS.md is stale: run python -m bench.report"


def test_readme_quotes_no_peer_ratio_without_a_valid_idle_run():
    """The 95x / 46x of two loaded runs are not a headline; only a valid bench.peer_ratio run is."""
    text = (ROOT / "README.md").read_text()
    valid = [json.loads(p.read_text()) for p in (ROOT / "bench" / "results").glob("peer_ratio_*.json")]
    valid = [d for d in valid if d.get("valid")]
    if not valid:
        assert not re.search(r"\b(95|46) ?[x×]", text)
        assert "not yet measured on an idle machine" in text


@needs_data
def test_rules_on_the_real_tank_match_a_fresh_replay(tmp_path):
    """The compare-rules figures of the README (rules_real_tank.json) are what the code gives now."""
    from bench.rules_real import rule_comparison

    want = json.loads((ROOT / "bench" / "results" / "rules_real_tank.json").read_text())["rule_comparison"]
    got = rule_comparison(DATA / "oasis_tank", 0.05, "auto")
    for k in ("rule", "rules", "occupied_both", "rule_only", "plain_only", "observed_equal"):
        assert got[k] == want[k], k
