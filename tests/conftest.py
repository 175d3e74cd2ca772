"""Shared fixtures: every mapper test runs on every backend this machine has."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import gpumap


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
_AVAILABLE = gpumap.available_backends()


def pytest_report_header(config):
    return f"gpumap backends on this machine: {', '.join(_AVAILABLE)}"


@pytest.fixture(params=ALL_BACKENDS)
def backend(request) -> str:
    if request.param not in _AVAILABLE:
        pytest.skip(f"backend {request.param} is not available on this machine")
    return request.param


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
