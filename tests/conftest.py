"""Shared fixtures: every mapper test runs on every backend this machine has."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

import gpumap
import gpumap.backends


def _find_data() -> Path | None:
    """The real recordings, ``shared/data`` beside the checkout (CI has it there)."""
    for up in Path(__file__).resolve().parents:
        for cand in (up / "shared" / "data", up.parent / "shared" / "data"):
            if (cand / "README.md").is_file():
                return cand
    return None


DATA = _find_data()
needs_data = pytest.mark.skipif(
    DATA is None, reason="shared/data (real recordings) not found beside the checkout (../shared/data)"
)

ALL_BACKENDS = ("numpy", "warp-cpu", "warp-cuda", "opencl-cpu", "opencl-gpu")
#: GPUMAP_TEST_BACKENDS="numpy,warp-cpu" runs the per-backend tests on those only (tests/mutants.py)
_ONLY = [b for b in os.environ.get("GPUMAP_TEST_BACKENDS", "").split(",") if b]
# probing every backend starts Warp and builds the OpenCL kernels (~4 s a process on 2 cores):
# a run restricted to some backends (each of tests/mutants.py's 21 runs) probes only those
_AVAILABLE = gpumap.backends.available_backends(_ONLY or None)
#: CI runs on a CPU machine that must have every CPU backend: a missing one fails the run (see
#: tests/test_backends_present.py) instead of skipping its tests. GPUMAP_REQUIRE_BACKENDS overrides.
_CI_BACKENDS = "numpy,warp-cpu,opencl-cpu" if os.environ.get("CI") else ""
REQUIRED_BACKENDS = [b for b in os.environ.get("GPUMAP_REQUIRE_BACKENDS", _CI_BACKENDS).split(",") if b]


def pytest_report_header(config):
    head = f"gpumap backends on this machine: {', '.join(_AVAILABLE)}"
    if _ONLY:
        head += f"; tests run on {', '.join(_ONLY)} only (GPUMAP_TEST_BACKENDS)"
    if REQUIRED_BACKENDS:
        head += f"; required: {', '.join(REQUIRED_BACKENDS)}"
    return head


@pytest.fixture(params=ALL_BACKENDS)
def backend(request) -> str:
    return _check(request.param)


@pytest.fixture(params=[b for b in ALL_BACKENDS if b != "numpy"])
def other_backend(request) -> str:
    """Every backend but numpy, the reference: for comparisons with gpumap.reference."""
    return _check(request.param)


def _check(name: str) -> str:
    if _ONLY and name not in _ONLY:
        pytest.skip(f"backend {name} is not in GPUMAP_TEST_BACKENDS")
    if name not in _AVAILABLE:
        pytest.skip(f"backend {name} is not available on this machine")
    return name


def rot_y(angle_rad: float) -> np.ndarray:
    """Rotation about +y (a positive angle pitches the boresight +x down towards -z)."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(angle_rad: float) -> np.ndarray:
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def pose(R: np.ndarray, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T
