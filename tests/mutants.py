"""Mutation check of the mapping rule: each mutant must make a test fail on its backend.

Not part of the default test run (pytest collects ``test_*.py`` only); run it by hand or in a
slow, optional CI job::

    python tests/mutants.py                    # every mutant, every CPU backend here
    python tests/mutants.py --backends numpy warp-cpu --only dark-counts-once
    python tests/mutants.py --list

For each mutant and backend the script copies the package into a temporary folder in its
installed layout (``gpumap/``, ``gpumap/kernels``, ``gpumap/sim``), applies the mutation to
that backend's code (``gpumap/reference.py`` for ``numpy``, ``kernels/minmax.py`` for
``warp-cpu``, ``kernels/minmax.cl`` for ``opencl-cpu``), and runs the mutant's test files
there with ``GPUMAP_TEST_BACKENDS=<backend>``, so only that backend's tests run and a test
that compares a backend with the (unmutated) reference cannot be what kills a ``numpy``
mutant. A mutant survives when those tests pass. The checkout itself is never modified.
The unmutated copy runs the same tests first on each backend and must pass them (else exit 2).
Exit status 0 when every mutant died on every backend tried, 1 otherwise.
"""

from __future__ import annotations

import argparse
import os
import shlex
import shutil
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: backend -> the file (relative to the checkout) that holds its rule
FILES = {"numpy": "gpumap/reference.py", "warp-cpu": "kernels/minmax.py", "opencl-cpu": "kernels/minmax.cl"}


@dataclass(frozen=True)
class Mutant:
    name: str
    what: str
    #: backend -> [(old, new), ...]: every occurrence of old (one at least) in that backend's file
    edits: dict[str, list[tuple[str, str]]]
    tests: tuple[str, ...] = ("tests/test_visibility.py",)
    extra: dict[str, str] = field(default_factory=dict)
    #: host code that every backend shares (e.g. bench/experiments/calibration.py): mutated there instead of
    # the
    #: backend's file of FILES, once (under the "numpy" key)
    file: str | None = None


MUTANTS = [
    Mutant(
        "dark-counts-once",
        "a clear view darker than threshold/2 adds 1 to the carving count instead of 2",
        {
            "numpy": [('np.where(v < params["thr_dark"], 2, 1)', 'np.where(v < params["thr_dark"], 1, 1)')],
            "warp-cpu": [("step = wp.uint64(2)", "step = wp.uint64(1)")],
            "opencl-cpu": [("v < P->thr_dark) ? 2UL : 1UL", "v < P->thr_dark) ? 1UL : 1UL")],
        },
    ),
    Mutant(
        "blocked-b0-minus-1",
        "a view counts as blocked only by a return before bin b0 - 1 (first_bright < b0 - 1)",
        {
            # the reference finds blocking returns over bins [0, b0) by another route: rows b0 - 1
            "numpy": [("some = b0 > 0", "some = b0 > 1"), ("rows = b0[some] - 1", "rows = b0[some] - 2")],
            "warp-cpu": [("if first_bright[jj] < b0:", "if first_bright[jj] < b0 - 1:")],
            "opencl-cpu": [("if (first_bright[jj] < b0)", "if (first_bright[jj] < b0 - 1)")],
        },
    ),
    Mutant(
        "bright-strictly-above",
        "a view is bright only when v > threshold (not v >= threshold)",
        {
            "numpy": [("lit = v >= thr", "lit = v > thr")],
            # every bright test (the count, the bright minimum, the per-voxel batch kernel) and the
            # dark side's complement (clear is looked up for dark views only)
            "warp-cpu": [("v >= P.thr", "v > P.thr"),
                         ("P.rule != 0 and v < P.thr:", "P.rule != 0 and v <= P.thr:")],
            "opencl-cpu": [("v >= P->thr", "v > P->thr"), ("v >= P0.thr", "v > P0.thr"),
                           ("P->rule != 0 && v < P->thr)", "P->rule != 0 && v <= P->thr)")],
        },
    ),
    Mutant(
        "return-strictly-above",
        "a return (first bright bin) needs a cell > threshold (not >= threshold)",
        {
            "numpy": [('is_clear[seen] = front < params["thr"]', 'is_clear[seen] = front <= params["thr"]')],
            "warp-cpu": [
                ("        if image[i, j] >= P.thr:\n            f = i",
                 "        if image[i, j] > P.thr:\n            f = i"),
                ("    if image[i, j] >= P.thr:\n        wp.atomic_min",
                 "    if image[i, j] > P.thr:\n        wp.atomic_min"),
            ],
            "opencl-cpu": [
                # first_bright_bin and its batch twin (the per-cell GPU builder is not used on CPUs)
                ("+ j] >= P.thr) { f = i; break; }", "+ j] > P.thr) { f = i; break; }"),
            ],
        },
    ),
    Mutant(
        "count-not-saturating",
        "the visible rule's carving count wraps at 256 instead of saturating at 255",
        {
            "numpy": [("grown = np.minimum(dark.astype(np.int64) + step, cap)",
                       "grown = (dark.astype(np.int64) + step) % (cap + 1)"),
                      ("clear_dark & (dark < cap)", "clear_dark")],
            "warp-cpu": [("        if dark < cap:\n            return (c - dark) + wp.min(dark + step, cap)",
                          "        if dark <= cap:\n"
                          "            return (c - dark) + (dark + step) % (cap + wp.uint64(1))")],
            "opencl-cpu": [("return dark < cap ? (c - dark) + min(dark + step, cap) : c;",
                            "return (c - dark) + (dark + step) % (cap + 1UL);")],
        },
    ),
    Mutant(
        "bright-count-wraps",
        "the 32-bit bright-view count wraps at 2^32 (carries out of the word) instead of saturating",
        {
            "numpy": [("np.minimum(hits.astype(np.int64) + 1, COUNT_MAX)", "(hits.astype(np.int64) + 1)")],
            "warp-cpu": [("        if c < HITS_FULL:", "        if c <= COUNT_LOW | HITS_FULL:")],
            "opencl-cpu": [("c < 0xFFFFFFFF00000000UL ?", "c <= 0xFFFFFFFFFFFFFFFFUL ?")],
        },
        tests=("tests/test_evidence_rule.py",),
    ),
    Mutant(
        "dark-count-carries",
        "the 32-bit clear-dark count of the evidence rule carries into the bright count at 2^32",
        {
            "numpy": [("grown = np.minimum(dark.astype(np.int64) + step, cap)",
                       "grown = dark.astype(np.int64) + step"), ("clear_dark & (dark < cap)", "clear_dark")],
            "warp-cpu": [("        if dark < cap:\n            return (c - dark) + wp.min(dark + step, cap)",
                          "        if dark <= cap:\n            return (c - dark) + dark + step")],
            "opencl-cpu": [("return dark < cap ? (c - dark) + min(dark + step, cap) : c;",
                            "return (c - dark) + dark + step;")],
        },
        tests=("tests/test_evidence_rule.py",),
    ),
    Mutant(
        "occluded-view-counts-dark",
        "a dark view behind a return counts as clear dark evidence (the blocking test ignored)",
        {
            "numpy": [("clear_dark = clear & ~lit", "clear_dark = ~lit")],
            "warp-cpu": [("    if clear > 0.0:\n", "    if clear >= 0.0:\n"),
                         ("or vc[1] > 0.0:", "or vc[1] >= 0.0:")],
            "opencl-cpu": [("if (!clear) return c;", ""), ("if (v >= P->thr || clear) {", "if (1) {")],
        },
        tests=("tests/test_evidence_rule.py",),
    ),
    Mutant(
        "decision-ignores-view-count",
        "the evidence rule decides on the bright share alone, not its confidence over the views",
        # the decision is host code that every backend shares: mutated once, in gpumap/reference.py
        {"numpy": [("    return (share >= p_min) | near", "    return share >= p_min")]},
        tests=("tests/test_evidence_rule.py",),
    ),
    Mutant(
        "calibrated-ignores-cost",
        "the calibrated decision keeps a voxel at even posterior odds whatever the miss cost",
        {"numpy": [("keep = surface_log_odds(model, k, n) >= -np.log(miss_cost)",
                    "keep = surface_log_odds(model, k, n) >= 0.0")]},
        tests=("tests/test_calibration.py",), file="bench/experiments/calibration.py",
    ),
    Mutant(
        "calibrated-not-monotone",
        "the calibrated decision frees a voxel that a pair of the same n with fewer bright views keeps",
        {"numpy": [("out.reshape(-1)[idx] = ((csum - before) > 0)[inverse]",
                    "out.reshape(-1)[idx] = keep[inverse]")]},
        tests=("tests/test_calibration.py",), file="bench/experiments/calibration.py",
    ),
    Mutant(
        "calibrated-untruncated",
        "the view model's classes are not truncated to the ever-bright voxels it is fitted to",
        {"numpy": [("return (_log_bb(k, n, a, b, log_binom) - np.log1p(-p0),",
                    "return (_log_bb(k, n, a, b, log_binom),")]},
        tests=("tests/test_calibration.py",), file="bench/experiments/calibration.py",
    ),
    Mutant(
        "calibrated-fits-on-no-evidence",
        "the view model is fitted however few ever-bright voxels have a clear dark view",
        {"numpy": [("if float(w[n > k].sum()) < MIN_FIT_VOXELS:", "if False:")]},
        tests=("tests/test_calibration.py",), file="bench/experiments/calibration.py",
    ),
    Mutant(
        "directional-dark-class-ignored",
        "a direction class that never saw a voxel bright cannot reject it, however many clear views",
        {"numpy": [("share = np.divide(k, n, out=np.ones_like(k), where=n > 0)",
                    "share = np.divide(k, n, out=np.ones_like(k), where=k > 0)")]},
        tests=("tests/test_directions.py",), file="bench/experiments/directions.py",
    ),
    Mutant(
        "directional-any-class-keeps",
        "one direction class that keeps a voxel overrules the classes that reject it",
        {"numpy": [("out.reshape(-1)[idx] = keeps.all(axis=0)", "out.reshape(-1)[idx] = keeps.any(axis=0)")]},
        tests=("tests/test_directions.py",), file="bench/experiments/directions.py",
    ),
    Mutant(
        "directional-signed-classes",
        "views rolled by 180 degrees fall in another direction class",
        {"numpy": [("np.argmax(np.abs(z @ AXES.T), axis=1)", "np.argmax(z @ AXES.T, axis=1)")]},
        tests=("tests/test_directions.py",), file="bench/experiments/directions.py",
    ),
    Mutant(
        "footprint-one-bin-short",
        "the footprint window ends one bin early (b0 + win - 2)",
        {
            "numpy": [('b1 = np.minimum(first + int(params["win"]) - 1, n_bins - 1)',
                       'b1 = np.minimum(first + int(params["win"]) - 2, n_bins - 1)')],
            "warp-cpu": [("b1 = wp.min(first + P.win - 1, P.n_bins - 1)",
                          "b1 = wp.min(first + P.win - 2, P.n_bins - 1)")],
            "opencl-cpu": [("min(first + P->win - 1, P->n_bins - 1)",
                            "min(first + P->win - 2, P->n_bins - 1)")],
        },
        tests=("tests/test_mapper.py",),
    ),
]


def _layout(dst: Path) -> None:
    """Copy the package in its installed layout, with the tests and pyproject.toml, into dst."""
    ign = shutil.ignore_patterns("__pycache__", "*.pyc")
    shutil.copytree(ROOT / "gpumap", dst / "gpumap", ignore=ign)
    for src, name in (("kernels", "kernels"), ("sim", "sim"), ("bench", "bench")):
        shutil.copytree(ROOT / src, dst / "gpumap" / name, ignore=ign)
    shutil.copytree(ROOT / "tests", dst / "tests", ignore=ign)
    for name in ("pyproject.toml", "README.md", "docs/guide.md"):  # tests read the README's claims too
        (dst / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(ROOT / name, dst / name)


def _installed_path(rel: str) -> str:
    for top in ("kernels/", "sim/", "bench/"):
        if rel.startswith(top):
            return "gpumap/" + rel
    return rel


def apply(text: str, edits: list[tuple[str, str]], where: str) -> str:
    for old, new in edits:
        if old not in text:
            raise SystemExit(f"mutant text not found in {where} (the code changed?): {old!r}")
        text = text.replace(old, new)
    return text


def run_one(m: Mutant | None, backend: str, timeout_s: float, verbose: bool, tests: tuple[str, ...],
            pytest_args: list[str]) -> tuple[str, float, str]:
    """('killed' | 'survived' | 'error', seconds, last lines of pytest's output); ``m`` None runs
    the unmutated copy (the baseline, which must survive)."""
    rel = (m.file if m is not None and m.file else None) or FILES[backend]
    with tempfile.TemporaryDirectory(prefix=f"mutant-{m.name if m else 'baseline'}-") as tmp:
        dst = Path(tmp)
        _layout(dst)
        if m is not None:
            target = dst / _installed_path(rel)
            target.write_text(apply(target.read_text(), m.edits[backend], rel))
        path = os.pathsep.join(p for p in (str(dst), os.environ.get("PYTHONPATH", "")) if p)
        env = dict(os.environ, GPUMAP_TEST_BACKENDS=backend, PYTHONPATH=path, PYTHONDONTWRITEBYTECODE="1")
        env.pop("CI", None)  # the backend check of CI is not what this run is about
        probe = "import gpumap.kernels as k, gpumap.reference as r; print(k.__path__[0], r.__file__)"
        where = subprocess.run([sys.executable, "-c", probe], cwd=dst, env=env, capture_output=True,
                               text=True)
        if not all(w.startswith(str(dst)) for w in where.stdout.split()) or where.returncode:
            raise SystemExit(f"the copy in {dst} is not what imports: {where.stdout}{where.stderr}")
        cmd = [sys.executable, "-m", "pytest", "-q", "-x", "-p", "no:cacheprovider", *pytest_args, *tests]
        t0 = time.perf_counter()
        try:
            r = subprocess.run(cmd, cwd=dst, env=env, capture_output=True, text=True, timeout=timeout_s)
        except subprocess.TimeoutExpired:
            return "error", time.perf_counter() - t0, "timed out"
        dt = time.perf_counter() - t0
        out = (r.stdout + r.stderr).strip().splitlines()
        # a failing baseline names its failing tests even when not verbose
        failed = [line for line in out if line.startswith(("FAILED", "ERROR"))] if m is None else []
        tail = "\n".join(out[-12:] if verbose else [*failed, *out[-1:]])
        if r.returncode == 1:
            return "killed", dt, tail
        if r.returncode == 0:
            return "survived", dt, tail
        return "error", dt, tail


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--backends", nargs="+", default=list(FILES), choices=list(FILES),
                    help="backends whose code is mutated (default: all three CPU backends)")
    ap.add_argument("--only", nargs="+", default=None, help="run only these mutants (by name)")
    ap.add_argument("--list", action="store_true", help="list the mutants and exit")
    ap.add_argument("--timeout", type=float, default=600.0, help="seconds allowed per mutant and backend")
    ap.add_argument("-v", "--verbose", action="store_true", help="show the end of each pytest run")
    ap.add_argument("--jobs", type=int, default=min(2, os.cpu_count() or 1),
                    help="runs at a time (default: 2, or 1 on one core); each run is its own process")
    ap.add_argument("--pytest-args", default="",
                    help="more pytest arguments, one string, e.g. \"-k 'not box'\" where pyrender is missing")
    a = ap.parse_args(argv)
    chosen = [m for m in MUTANTS if a.only is None or m.name in a.only]
    if a.only and len(chosen) != len(a.only):
        ap.error(f"unknown mutant in {a.only}; known: {[m.name for m in MUTANTS]}")
    if a.list:
        for m in chosen:
            print(f"{m.name}: {m.what} (tests: {', '.join(m.tests)})")
        return 0
    extra = shlex.split(a.pytest_args)
    survived = 0
    # each run is a pytest process of its own on its own copy: up to --jobs of them at once (they
    # wait on one core each), results printed in order
    pool = ThreadPoolExecutor(max(1, a.jobs))
    # the unmutated copy must pass the same tests on each backend, or a kill means nothing
    tests = tuple(sorted({t for m in chosen for t in m.tests}))
    runs = [pool.submit(run_one, None, b, a.timeout, a.verbose, tests, extra) for b in a.backends]
    for b, fut in zip(a.backends, runs, strict=True):
        status, dt, tail = fut.result()
        print(f"{'(baseline: no mutant)':26s} {b:11s} {'passes' if status == 'survived' else status:8s} "
              f"{dt:6.1f} s  {tail if a.verbose or status != 'survived' else tail[:90]}", flush=True)
        if status != "survived":
            print(f"the tests fail on {b} without any mutant: fix that first")
            pool.shutdown(cancel_futures=True)
            return 2
    todo = [(m, b) for m in chosen for b in a.backends if b in m.edits]  # host code: numpy's run only
    runs = [pool.submit(run_one, m, b, a.timeout, a.verbose, m.tests, extra) for m, b in todo]
    for (m, b), fut in zip(todo, runs, strict=True):
        status, dt, tail = fut.result()
        survived += status != "killed"
        shown = tail if a.verbose else tail[:90]
        print(f"{m.name:26s} {b:11s} {status:8s} {dt:6.1f} s  {shown}", flush=True)
    pool.shutdown()
    print(f"{survived} of {len(todo)} mutant runs not killed" if survived
          else "every mutant killed on every backend tried")
    return 1 if survived else 0


if __name__ == "__main__":
    sys.exit(main())
