"""Shared helpers of the benchmark: machine description, peak memory, published numbers, JSON rounding."""

from __future__ import annotations

import os
import platform
import re
import threading
import time
from typing import Any

import numpy as np

__all__ = [
    "OASIS_PUBLISHED_MS",
    "PAPER_TABLE_I",
    "SONAR_RATE_HZ",
    "TARGETS",
    "CpuShare",
    "PeakRSS",
    "compact",
    "load_average",
    "machine_info",
    "slug",
]

#: The paper's Table I (Phung et al.): voxel size (m) -> published seconds per image.
PAPER_TABLE_I: dict[float, float] = {0.06: 0.07, 0.05: 0.12, 0.04: 0.25, 0.03: 0.52, 0.02: 1.6, 0.01: 12.0}
#: Public OASIS code, ms per image on this project's 2-core CPU, as published in issue 6.
OASIS_PUBLISHED_MS: dict[float, float] = {0.05: 82.0, 0.03: 329.0, 0.01: 7200.0}
#: The Oculus M1200d's maximum ping rate (paper, Table I footnote).
SONAR_RATE_HZ = 10.0
#: Speed targets (issue 6): (device class, voxel size m, images/s).
TARGETS: list[tuple[str, float, float]] = [
    ("cpu", 0.03, 100.0),
    ("cpu", 0.01, 10.0),
    ("gpu", 0.01, 5000.0),
    ("gpu", 0.005, 1000.0),
]


def help_line(doc: str | None) -> str:
    """A module docstring's first line as a ``--help`` description: plain words, no reST backticks."""
    return (doc or "").strip().splitlines()[0].replace("``", "") if (doc or "").strip() else ""


def slug(text: str) -> str:
    """Lower-case file-name-safe form of ``text``."""
    return re.sub(r"[^a-z0-9]+", "-", text.lower()).strip("-")[:40] or "unknown"


def _cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def _version(mod: str) -> str | None:
    try:
        from importlib.metadata import version

        return version(mod)
    except Exception:
        return None


def load_average() -> list[float] | None:
    """1, 5 and 15 minute load averages (None where the system does not tell, e.g. some sandboxes)."""
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except OSError:
        return None


def machine_info() -> dict[str, Any]:
    """CPU model and cores, memory, GPU names, load average and package versions."""
    import gpumap

    info: dict[str, Any] = {
        "cpu_model": _cpu_model(),
        "cpu_count": os.cpu_count(),
        "affinity_cpus": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
        "platform": platform.platform(),
        "python": platform.python_version(),
        "load_avg_start": load_average(),
        "versions": {
            "gpumap": gpumap.__version__,
            "numpy": np.__version__,
            "warp-lang": _version("warp-lang"),
            "pyopencl": _version("pyopencl"),
            "pocl-binary-distribution": _version("pocl-binary-distribution"),
            "pyoctomap": _version("pyoctomap"),
            "scipy": _version("scipy"),
        },
        "backends": gpumap.available_backends(),
    }
    try:
        with open("/proc/meminfo") as f:
            info["mem_total_gb"] = round(int(f.readline().split()[1]) / 2**20, 1)
    except OSError:
        pass
    gpus = []
    try:
        import warp as wp

        for d in wp.get_cuda_devices():
            gpus.append(f"{d.name} ({d.total_memory / 2**30:.0f} GiB)")
    except Exception:
        pass
    info["gpus"] = gpus
    info["git"] = _git_state()
    return info


def _git_state() -> dict[str, Any]:
    """Commit of the checkout and the source files that differ from it (the code actually timed)."""
    import subprocess

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    try:
        head = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True, timeout=10
        )
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--", "gpumap", "kernels", "bench", "sim"],
            cwd=root,
            capture_output=True,
            text=True,
            timeout=10,
        )
    except (OSError, subprocess.SubprocessError):
        return {}
    return {
        "commit": head.stdout.strip() or None,
        "modified": [line[3:] for line in dirty.stdout.splitlines() if line.strip().endswith((".py", ".cl"))],
    }


class PeakRSS:
    """Context manager sampling this process's resident set size; ``.delta_mb`` is the peak rise.

    A background thread reads ``/proc/self/statm`` every ``interval_s``; the peak over the
    block minus the RSS at entry is what the block allocated at most (host memory).
    """

    def __init__(self, interval_s: float = 0.01) -> None:
        self.interval_s = interval_s
        self._page = os.sysconf("SC_PAGE_SIZE") if hasattr(os, "sysconf") else 4096
        self.start_b = 0
        self.peak_b = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def _rss(self) -> int:
        try:
            with open("/proc/self/statm") as f:
                return int(f.read().split()[1]) * self._page
        except OSError:
            return 0

    def _run(self) -> None:
        while not self._stop.is_set():
            self.peak_b = max(self.peak_b, self._rss())
            time.sleep(self.interval_s)

    def __enter__(self) -> PeakRSS:
        self.start_b = self.peak_b = self._rss()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        self.peak_b = max(self.peak_b, self._rss())

    @property
    def delta_mb(self) -> float:
        return (self.peak_b - self.start_b) / 2**20


class CpuShare:
    """Context manager: how many cores *other* processes (and the hypervisor) took during the block.

    From ``/proc/stat`` (busy and steal time of the whole machine) minus this process's own
    CPU time (``resource.getrusage``, all threads): ``others_cores`` is the average number
    of cores other processes kept busy, ``steal_cores`` the average the hypervisor withheld.
    """

    def __init__(self) -> None:
        self.others_cores: float | None = None
        self.steal_cores: float | None = None
        self.own_cores: float | None = None
        self.wall_s: float | None = None

    @staticmethod
    def _stat() -> tuple[float, float] | None:
        try:
            with open("/proc/stat") as f:
                v = [int(x) for x in f.readline().split()[1:]]
        except (OSError, ValueError):
            return None
        hz = os.sysconf("SC_CLK_TCK")
        busy = v[0] + v[1] + v[2] + v[5] + v[6]  # user nice system irq softirq (guest is inside user)
        steal = v[7] if len(v) > 7 else 0
        return busy / hz, steal / hz

    @staticmethod
    def _own() -> float:
        import resource

        r = resource.getrusage(resource.RUSAGE_SELF)
        c = resource.getrusage(resource.RUSAGE_CHILDREN)
        return r.ru_utime + r.ru_stime + c.ru_utime + c.ru_stime

    def __enter__(self) -> CpuShare:
        self._t0, self._s0, self._o0 = time.perf_counter(), self._stat(), self._own()
        return self

    def __exit__(self, *exc: object) -> None:
        wall = time.perf_counter() - self._t0
        self.wall_s = wall
        s1, own = self._stat(), self._own() - self._o0
        if self._s0 is None or s1 is None or wall <= 0:
            return
        self.own_cores = own / wall
        self.others_cores = max(0.0, (s1[0] - self._s0[0]) - own) / wall
        self.steal_cores = (s1[1] - self._s0[1]) / wall


def compact(obj: Any, digits: int = 4) -> Any:
    """``obj`` with floats rounded to ``digits`` significant digits and NumPy scalars made plain."""
    if isinstance(obj, dict):
        return {str(k): compact(v, digits) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [compact(v, digits) for v in obj]
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float):
        if not np.isfinite(obj):
            return None
        return float(f"{obj:.{digits}g}")
    return obj
