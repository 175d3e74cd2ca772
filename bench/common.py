"""Shared helpers of every benchmark: command line, machine description and load check, timing
loops, the scenes' pings and the real tank, results files and marked Markdown blocks.

A benchmark module under ``bench/`` builds its parser with :func:`bench_parser`, reads its
inputs with :func:`oasis_tank_dir` / :func:`render_pings` / :func:`load_ping_arrays`, times a
mapper with :func:`warm_up`, :func:`synced_ms` and :func:`stream_rate`, describes the machine
with :func:`machine_info` (and :func:`idle_check` where a figure needs an idle machine), and
writes its results with :func:`run_header` and :func:`write_json` (or :func:`merge_json` for a
file of sections). ``python -m bench NAME`` runs any of them (:mod:`bench.__main__`).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "OASIS_PUBLISHED_MS",
    "PAPER_TABLE_I",
    "SONAR_RATE_HZ",
    "TARGETS",
    "CpuShare",
    "PeakRSS",
    "bench_parser",
    "compact",
    "gl_renderer",
    "idle_check",
    "load_average",
    "load_ping_arrays",
    "load_results",
    "machine_info",
    "machine_tag",
    "mark_load",
    "merge_json",
    "oasis_full_dir",
    "oasis_tank_dir",
    "pooled_others",
    "put_block",
    "quantize",
    "render_pings",
    "run_header",
    "slug",
    "spread",
    "stream_rate",
    "synced_ms",
    "tagged_path",
    "warm_up",
    "write_json",
    "write_section",
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


def machine_tag(info: dict[str, Any], gpu: bool = False, model: bool = False) -> str:
    """A results file's default stem from :func:`machine_info` ``info``: ``gpu_<first GPU>`` for a
    GPU run (where there is one), else ``cpu_<cores>c`` (``model``: ``cpu_<model>_<cores>c``)."""
    if gpu and info.get("gpus"):
        return "gpu_" + slug(info["gpus"][0].split(" (")[0])
    return f"cpu_{slug(info['cpu_model']) + '_' if model else ''}{info['cpu_count']}c"


def mark_load(info: dict[str, Any], share: CpuShare) -> None:
    """Record in ``info`` (a :func:`machine_info`) how loaded the machine was over a run: the
    load average at its end and the cores others took meanwhile (``share``, already exited)."""
    info["load_avg_end"] = load_average()
    info["cpu_share_during_run"] = {
        "others_cores": share.others_cores,
        "steal_cores": share.steal_cores,
        "bench_cores": share.own_cores,
        "note": "average cores busy with other processes / withheld by the hypervisor / used by the bench "
        "(from /proc/stat and getrusage)",
    }


def gl_renderer() -> str:
    """The OpenGL renderer of the current context (Mesa llvmpipe on a CPU-only machine)."""
    try:
        from OpenGL.GL import GL_RENDERER, glGetString

        s = glGetString(GL_RENDERER)
        return s.decode() if isinstance(s, bytes) else str(s)
    except Exception as e:  # informative only
        return f"unknown ({type(e).__name__})"


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


# ------------------------------------------------------------------------------ command line
def bench_parser(module: str, doc: str | None) -> argparse.ArgumentParser:
    """The parser of ``python -m bench.<module>``: that program name, the docstring's first line."""
    return argparse.ArgumentParser(prog=f"python -m bench.{module}", description=help_line(doc))


# ------------------------------------------------------------------------------ load check
def idle_check(max_load: float, max_others: float, sample_s: float = 2.0,
               load: list[float] | None = None) -> dict[str, Any]:
    """The machine's load now: 1-minute load average (``load``, default :func:`load_average`)
    and the cores other processes keep busy over ``sample_s`` seconds; ``idle`` when both are
    within the limits. A bench that needs an idle machine refuses to start when it is not
    (exit status 3), or runs on request and marks its results ``"valid": false``
    (:mod:`bench.peer_ratio`)."""
    load = load_average() if load is None else load
    with CpuShare() as share:
        time.sleep(sample_s)
    others = share.others_cores
    ok_load = load is None or load[0] <= max_load
    ok_others = others is None or others <= max_others
    return {"load_avg": load, "others_cores": others, "idle": bool(ok_load and ok_others)}


def pooled_others(passes: list[dict[str, Any]]) -> float | None:
    """Cores other processes kept busy over all ``passes`` together: their CPU seconds
    (``others_cores * wall_s`` per pass) over the passes' wall seconds; None without samples."""
    got = [p for p in passes if p.get("others_cores") is not None and p.get("wall_s")]
    wall = sum(p["wall_s"] for p in got)
    if not got or wall <= 0:
        return None
    return sum(p["others_cores"] * p["wall_s"] for p in got) / wall


# ------------------------------------------------------------------------------ timing
def warm_up(m: Any, images: Sequence[np.ndarray], poses: Sequence[np.ndarray], n: int) -> None:
    """Integrate pings ``0..n-1`` into mapper ``m`` (kernel compile, caches), synchronize, then
    ``reset`` it: the warm-up pings are in no figure and in no map."""
    for k in range(n):
        m.integrate(images[k % len(images)], poses[k % len(poses)])
    m.synchronize()
    m.reset()
    m.synchronize()


def synced_ms(m: Any, images: Sequence[np.ndarray], poses: Sequence[np.ndarray], n: int | None = None,
              start: int = 0) -> list[float]:
    """Milliseconds of ``integrate`` + ``synchronize`` for each of ``n`` pings (default: every
    ping once), ping ``(start + k) % len(images)``: what a vehicle waits per ping."""
    n = len(images) if n is None else n
    out = []
    for k in range(start, start + n):
        t = time.perf_counter()
        m.integrate(images[k % len(images)], poses[k % len(poses)])
        m.synchronize()
        out.append(1e3 * (time.perf_counter() - t))
    return out


def stream_rate(m: Any, images: Sequence[np.ndarray], poses: Sequence[np.ndarray], n: int | None = None,
                batch: int = 1) -> float:
    """Images per second of ``n`` pings (default: every ping once) handed over back to back, one
    ``synchronize`` at the end (what a stream of pings sees); ``batch`` > 1: ``integrate_batch``
    of that many pings at a time (then ``n`` is every ping once)."""
    t = time.perf_counter()
    if batch > 1:
        n = len(images)
        for k in range(0, n, batch):
            m.integrate_batch(images[k : k + batch], poses[k : k + batch])
    else:
        n = len(images) if n is None else n
        for k in range(n):
            m.integrate(images[k % len(images)], poses[k % len(poses)])
    m.synchronize()
    return n / (time.perf_counter() - t)


def spread(values: Sequence[float]) -> dict[str, float]:
    """Median, min and max of repeated measurements (the spread a figure is quoted with)."""
    a = np.asarray(values, float)
    return {"median": float(np.median(a)), "min": float(a.min()), "max": float(a.max())}


# ------------------------------------------------------------------------------ inputs
def oasis_tank_dir() -> Path | None:
    """``shared/data/oasis_tank`` (the real Oculus M3000d tank recording) beside the checkout, as
    CI has it, or above it; None where it is not there."""
    for up in Path(__file__).resolve().parents:
        for cand in (up / "shared" / "data" / "oasis_tank", up.parent / "shared" / "data" / "oasis_tank"):
            if (cand / "sonar_poses.csv").is_file():
                return cand
    return None


def oasis_full_dir() -> Path | None:
    """The full-rate OASIS tank recording (``oasis_tank_full/`` with ``sonar/*.png``, written by
    ``shared/data/oasis_tank_full/get_images.sh``) beside the checkout or above it; None where
    its images are not there (``shared/data/oasis_tank_full`` itself holds only the poses)."""
    for up in Path(__file__).resolve().parents:
        for cand in (up / "oasis_tank_full", up / "shared" / "data" / "oasis_tank_full"):
            if (cand / "sonar_poses.csv").is_file() and (cand / "sonar").is_dir():
                return cand
    return None


def quantize(image: np.ndarray) -> np.ndarray:
    """A simulated intensity image (float in [0, 1]) as the Oculus delivers it: uint8, rounded."""
    return np.round(np.asarray(image) * 255.0).astype(np.uint8)


def render_pings(scene: Any, *, seed: int = 0, select: Sequence[int] | None = None, scene_sonar: bool = True,
                 progress: bool = False, desc: str | None = None, variation: Any = None) -> list:
    """The simulator's pings of ``scene`` (a :class:`gpumap.sim.scenes.Scene`) at its trajectory's
    poses ``T_W_S`` (all, or the indices ``select``); ``scene_sonar``: with the scene's own
    simulator settings (``scene.sonar_params``, e.g. the survey's gain), as ``gpumap demo`` does;
    ``variation``: a :class:`gpumap.sim.variation.SonarVariation` (None: none)."""
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    from gpumap.sim.sonar import SonarSimulator
    from tqdm import tqdm

    sel = range(len(scene.T_W_S)) if select is None else select
    extra = scene.sonar_params if scene_sonar else {}
    with SonarSimulator(scene, seed=seed, variation=variation, **extra) as sim:
        return [sim.ping(scene.T_W_S[k], int(k))
                for k in tqdm(sel, desc=desc or "simulate", unit="ping", disable=not progress)]


def load_ping_arrays(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """(images, poses) of a ping file: :mod:`bench.tank`'s names (images, poses) or the older
    (imgs, T)."""
    with np.load(path, allow_pickle=False) as z:
        if "images" in z.files:
            return z["images"], z["poses"]
        if "imgs" in z.files:
            return z["imgs"], z["T"]
        raise ValueError(f"Expected a ping file with images and poses (or imgs and T), but {path} "
                         f"has {z.files}")


# ------------------------------------------------------------------------------ results
def run_header(schema: str | None, argv: Sequence[str] | None) -> dict[str, Any]:
    """The first keys of a results file: schema, creation time, the bench's arguments and
    :func:`machine_info` (load average at the start included)."""
    import sys

    head: dict[str, Any] = {} if schema is None else {"schema": schema}
    head["created"] = time.strftime("%Y-%m-%dT%H:%M:%S%z")
    head["argv"] = list(sys.argv[1:] if argv is None else argv)
    head["machine"] = machine_info()
    return head


def write_json(path: str | os.PathLike, doc: Any, *, indent: int | None = 1,
               digits: int | None = None) -> Path:
    """Write ``doc`` to ``path`` as JSON (its folder made; written whole, then renamed, so that an
    interrupted run leaves the old file). ``digits``: floats rounded to that many significant
    digits (:func:`compact`); NumPy scalars are written as numbers either way."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if digits is not None:
        doc = compact(doc, digits)
    seps = (",", ":") if indent is None else None
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(doc, indent=indent, separators=seps, default=float) + "\n")
    os.replace(tmp, path)
    return path


def merge_json(path: str | os.PathLike, keys: Sequence[str], value: Any, **top: Any) -> dict:
    """Put ``value`` at ``doc[keys[0]][keys[1]]...`` of the results file ``path`` (other sections
    kept), set the top-level ``top`` keys, write it back (indent 1) and return it."""
    path = Path(path)
    doc = json.loads(path.read_text()) if path.is_file() else {}
    doc.update(top)
    d = doc
    for k in keys[:-1]:
        d = d.setdefault(k, {})
    d[keys[-1]] = value
    write_json(path, doc)
    return doc


def load_results(folder: str | os.PathLike, pattern: str, schema: str) -> list[dict[str, Any]]:
    """Every results file ``folder/pattern`` whose ``schema`` starts with ``schema``, by file name,
    each with its name under ``_file`` (files that do not parse are passed over)."""
    out = []
    for p in sorted(Path(folder).glob(pattern)):
        try:
            d = json.loads(p.read_text())
        except (OSError, json.JSONDecodeError):
            continue
        if isinstance(d, dict) and str(d.get("schema", "")).startswith(schema):
            d["_file"] = p.name
            out.append(d)
    return out


def tagged_path(out: str | os.PathLike, prefix: str, tag: str) -> Path:
    """``out/<prefix><tag>.json`` with ``tag`` lower-cased and made file-name safe."""
    return Path(out) / f"{prefix}{''.join(c if c.isalnum() or c in '-_' else '-' for c in tag.lower())}.json"


def write_section(report: str | os.PathLike, results: str | os.PathLike, module: Any) -> int:
    """A benchmark's ``--report``: its section of the Markdown file ``report``, rendered by
    ``module.markdown(results_doc, results_folder)`` between ``module.BEGIN`` and ``module.END``
    (the ``## `` section ``module.SECTION`` where the markers are missing). Returns 0."""
    res = json.loads(Path(results).read_text())
    put_block(report, module.BEGIN, module.END, module.markdown(res, Path(results).parent),
              section=module.SECTION)
    print(f"wrote the {Path(results).stem} section of {report}")
    return 0


def put_block(path: str | os.PathLike, begin: str, end: str, body: str, section: str | None = None) -> None:
    """Replace the block of Markdown file ``path`` between the marker lines ``begin`` and ``end``
    with ``body`` (markers kept, what follows the end marker untouched); without markers, the
    ``## `` section headed ``section`` (to the next ``## `` heading) becomes the block, else the
    block is appended."""
    path = Path(path)
    old = path.read_text() if path.exists() else ""
    block = f"{begin}\n{body.strip(chr(10))}\n{end}"
    i, j = old.find(begin), old.find(end)
    if i >= 0 and j > i:
        new = old[:i] + block + old[j + len(end) :]
    elif section is not None and (i := old.find(section)) >= 0:
        j = old.find("\n## ", i + len(section))
        new = old[:i] + block + ("\n" if j < 0 else "\n\n" + old[j + 1 :])
    else:
        new = old.rstrip("\n") + "\n\n" + block + "\n"
    path.write_text(new)
