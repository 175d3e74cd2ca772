"""The mutants of the update rule die on every CPU backend, in CI (issue 21).

``tests/mutants.py`` applies each mutant (a very dark view counting once, the blocking test off
by a bin, bright or a return compared strictly, the count wrapping instead of saturating, the
footprint a bin short) to a temporary copy of the package, per backend, and runs the tests that
guard the rule there; it first checks that the unmutated copy passes. The 21 runs go two at a
time (``--jobs``), each probing only its backend (conftest).
The two slowest scene tests are left out of each inner run (they kill none of these mutants
that the others do not).
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from conftest import _AVAILABLE

CPU_BACKENDS = [b for b in ("numpy", "warp-cpu", "opencl-cpu") if b in _AVAILABLE]


def test_every_mutant_of_the_rule_is_killed_on_every_cpu_backend() -> None:
    script = Path(__file__).with_name("mutants.py")
    r = subprocess.run(
        [sys.executable, str(script), "--backends", *CPU_BACKENDS,
         "--pytest-args", "-k 'not box and not free_water'"],
        capture_output=True, text=True, timeout=1200,
    )
    out = r.stdout + r.stderr
    assert r.returncode == 0 and "every mutant killed on every backend tried" in out, out[-4000:]
    for b in CPU_BACKENDS:
        assert f"(baseline: no mutant)      {b:<11} passes" in out, out[-4000:]
