"""The README's figures stay true: each comes from a results file, and the real-tank one is re-measured."""

from __future__ import annotations

import json
import re
from pathlib import Path

from conftest import DATA, needs_data
from gpumap.bench import readme

ROOT = Path(__file__).resolve().parents[1]


def test_readme_blocks_are_what_the_results_files_give():
    text = (ROOT / "README.md").read_text()
    assert readme.render(text) == text, "README figures are stale: run python -m bench.readme"
    for name in readme.BLOCKS:
        block = re.search(rf"<!-- begin:{name} -->\n(.*?)<!-- end:{name} -->", text, re.S).group(1)
        assert re.search(r"\d", block), f"block {name} holds no figure"


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
