"""The distribution installs everything under the one import name ``gpumap``."""

from __future__ import annotations

import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("wheel")
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "wheel",
            "--no-deps",
            "--no-build-isolation",
            "-q",
            "-w",
            str(out),
            str(ROOT),
        ],
        capture_output=True,
        text=True,
    )
    # setuptools and wheel come with the [test] extra: a wheel that does not build is a failure
    assert r.returncode == 0, f"pip wheel failed ({r.returncode}): {r.stderr[-2000:]}"
    (whl,) = out.glob("gpumap-*.whl")
    return whl


def test_wheel_has_only_gpumap_at_top_level(wheel):
    names = zipfile.ZipFile(wheel).namelist()
    top = {n.split("/")[0] for n in names}
    assert {t for t in top if not t.endswith(".dist-info")} == {"gpumap"}
    for need in (
        "gpumap/kernels/minmax.py",
        "gpumap/kernels/minmax.cl",
        "gpumap/sim/sonar.py",
        "gpumap/io/oculus.py",
        "gpumap/core/mapper.py",
        "gpumap/backends/__init__.py",
        "gpumap/backends/warp_backend.py",
        "gpumap/backends/opencl_backend.py",
    ):
        assert need in names, need
    assert not any("/tests/" in n or n.startswith("bench/") for n in names)


def test_opencl_source_is_package_data():
    from importlib import resources

    src = resources.files("gpumap.kernels").joinpath("minmax.cl").read_text()
    assert "__kernel void integrate_gather" in src
