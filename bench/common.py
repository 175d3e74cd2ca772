"""The one harness of every benchmark (bench/README.md tells the layout): command line, machine and
load, timing, inputs, results files, BENCHMARKS.md blocks and plots. It imports nothing of gpumap or
bench at load time: ``bench.ab``'s worker loads it by path beside a foreign source tree.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import re
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

#: The paper's Table I (Phung et al.): voxel size (m) -> published seconds per image.
PAPER_TABLE_I: dict[float, float] = {0.06: 0.07, 0.05: 0.12, 0.04: 0.25, 0.03: 0.52, 0.02: 1.6, 0.01: 12.0}
#: Public OASIS code, ms per image on this project's 2-core CPU, as published in issue 6.
OASIS_PUBLISHED_MS: dict[float, float] = {0.05: 82.0, 0.03: 329.0, 0.01: 7200.0}
#: The Oculus M1200d's maximum ping rate (paper, Table I footnote).
SONAR_RATE_HZ = 10.0
#: Speed targets (issue 6): (device class, voxel size m, images/s).
TARGETS: list[tuple[str, float, float]] = [
    ("cpu", 0.03, 100.0), ("cpu", 0.01, 10.0), ("gpu", 0.01, 5000.0), ("gpu", 0.005, 1000.0)]
GPU_BACKENDS = ("warp-cuda", "opencl-gpu")
#: Scratch inputs the benchmarks cache (git-ignored): ping files, converted frames, saved maps.
TMP = Path("bench/results/tmp")


# ------------------------------------------------------------------------------ machine and load
def slug(text: str) -> str:
    """Lower-case file-name-safe form of ``text``."""
    return re.sub(r"[^a-z0-9]+", "-", text.lower()).strip("-")[:40] or "unknown"


def _cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            model = next((ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name")), None)
    except OSError:
        model = None
    return model or platform.processor() or "unknown"


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
    """CPU model and cores, memory, GPU names, load average, package versions and the git state."""
    import gpumap

    pkgs = ("warp-lang", "pyopencl", "pocl-binary-distribution", "pyoctomap", "scipy")
    info: dict[str, Any] = {
        "cpu_model": _cpu_model(), "cpu_count": os.cpu_count(),
        "affinity_cpus": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
        "platform": platform.platform(), "python": platform.python_version(),
        "load_avg_start": load_average(),
        "versions": {"gpumap": gpumap.__version__, "numpy": np.__version__, **{p: _version(p) for p in pkgs}},
        "backends": gpumap.available_backends(),
    }
    try:
        with open("/proc/meminfo") as f:
            info["mem_total_gb"] = round(int(f.readline().split()[1]) / 2**20, 1)
    except OSError:
        pass
    try:
        import warp as wp

        info["gpus"] = [f"{d.name} ({d.total_memory / 2**30:.0f} GiB)" for d in wp.get_cuda_devices()]
    except Exception:
        info["gpus"] = []
    info["git"] = _git_state()
    return info


def _git_state() -> dict[str, Any]:
    """Commit of the checkout and the source files that differ from it (the code actually timed)."""
    import subprocess

    def git(*args: str) -> str:
        return subprocess.run(["git", *args], cwd=Path(__file__).resolve().parents[1], capture_output=True,
                              text=True, timeout=10).stdout

    try:
        head = git("rev-parse", "HEAD")
        dirty = git("status", "--porcelain", "--", "gpumap", "kernels", "bench", "sim")
    except (OSError, subprocess.SubprocessError):
        return {}
    return {"commit": head.strip() or None,
            "modified": [ln[3:] for ln in dirty.splitlines() if ln.strip().endswith((".py", ".cl"))]}


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
        "others_cores": share.others_cores, "steal_cores": share.steal_cores, "bench_cores": share.own_cores,
        "note": "average cores busy with other processes / withheld by the hypervisor / used by the bench "
        "(from /proc/stat and getrusage)"}


def gl_renderer() -> str:
    """The OpenGL renderer of the current context (Mesa llvmpipe on a CPU-only machine)."""
    try:
        from OpenGL.GL import GL_RENDERER, glGetString

        s = glGetString(GL_RENDERER)
        return s.decode() if isinstance(s, bytes) else str(s)
    except Exception as e:  # informative only
        return f"unknown ({type(e).__name__})"


class PeakRSS:
    """Context manager sampling this process's resident set size every ``interval_s`` (a thread
    reading ``/proc/self/statm``); ``.delta_mb`` is the peak rise over the block (host memory)."""

    def __init__(self, interval_s: float = 0.01) -> None:
        self.interval_s, self.start_b, self.peak_b = interval_s, 0, 0
        self._page = os.sysconf("SC_PAGE_SIZE") if hasattr(os, "sysconf") else 4096
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

    From ``/proc/stat`` (busy and steal time of the whole machine) minus this process's own CPU time
    (``resource.getrusage``, all threads): ``others_cores`` is the average number of cores other
    processes kept busy, ``steal_cores`` the average the hypervisor withheld.
    """

    def __init__(self) -> None:
        self.others_cores = self.steal_cores = self.own_cores = self.wall_s = None

    @staticmethod
    def _stat() -> tuple[float, float] | None:
        try:
            with open("/proc/stat") as f:
                v = [int(x) for x in f.readline().split()[1:]]
        except (OSError, ValueError):
            return None
        hz = os.sysconf("SC_CLK_TCK")  # busy: user nice system irq softirq (guest is inside user)
        return (v[0] + v[1] + v[2] + v[5] + v[6]) / hz, (v[7] if len(v) > 7 else 0) / hz

    @staticmethod
    def _own() -> float:
        import resource

        r, c = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
        return r.ru_utime + r.ru_stime + c.ru_utime + c.ru_stime

    def __enter__(self) -> CpuShare:
        self._t0, self._s0, self._o0 = time.perf_counter(), self._stat(), self._own()
        return self

    def __exit__(self, *exc: object) -> None:
        self.wall_s = wall = time.perf_counter() - self._t0
        s1, own = self._stat(), self._own() - self._o0
        if self._s0 is None or s1 is None or wall <= 0:
            return
        self.own_cores = own / wall
        self.others_cores = max(0.0, (s1[0] - self._s0[0]) - own) / wall
        self.steal_cores = (s1[1] - self._s0[1]) / wall


def tree_cpu_s(root: int | None = None) -> tuple[float, float] | None:
    """(CPU seconds the whole machine was busy, CPU seconds of process ``root`` (default: this one)
    and every process below it, the dead ones it waited for included), from /proc; None where
    /proc cannot say. The difference between two calls is what *other* processes took: unlike
    :class:`CpuShare`, worker processes that this one started count as its own."""
    root = os.getpid() if root is None else root
    hz = os.sysconf("SC_CLK_TCK")
    machine = CpuShare._stat()  # (busy, steal) seconds of the whole machine
    if machine is None:
        return None
    try:
        kids: dict[int, list[int]] = {}
        cpu: dict[int, float] = {}
        for d in os.listdir("/proc"):
            if not d.isdigit():
                continue
            try:
                with open(f"/proc/{d}/stat") as f:
                    st = f.read().rsplit(")", 1)[1].split()
            except OSError:
                continue
            kids.setdefault(int(st[1]), []).append(int(d))
            cpu[int(d)] = sum(int(x) for x in st[11:15]) / hz  # utime stime cutime cstime
    except (OSError, ValueError):
        return None
    mine, todo = {root}, [root]
    while todo:
        for k in kids.get(todo.pop(), []):
            if k not in mine:
                mine.add(k)
                todo.append(k)
    return machine[0], sum(cpu.get(p, 0.0) for p in mine)


def idle_check(max_load: float, max_others: float, sample_s: float = 2.0,
               load: list[float] | None = None) -> dict[str, Any]:
    """The machine's load now: 1-minute load average (``load``, default :func:`load_average`) and the
    cores other processes keep busy over ``sample_s`` seconds; ``idle`` when both are within the
    limits. A bench that needs an idle machine refuses to start when it is not (exit status 3,
    :func:`refuse`), or runs on request and marks its results ``"valid": false``."""
    load = load_average() if load is None else load
    with CpuShare() as share:
        time.sleep(sample_s)
    others = share.others_cores
    ok = (load is None or load[0] <= max_load) and (others is None or others <= max_others)
    return {"load_avg": load, "others_cores": others, "idle": bool(ok)}


def refuse(prog: str, check: dict[str, Any], limits: tuple[float, float], flag: str) -> int:
    """Say that ``prog`` will not time on a machine that :func:`idle_check` found busy; exit status 3."""
    print(f"{prog}: refused: the machine is not idle (1-minute load {check['load_avg']}, other processes "
          f"busy on {check['others_cores']} cores; limits {limits[0]} and {limits[1]}); wait, or pass {flag} "
          "to record a run marked not valid", file=sys.stderr)
    return 3


def pooled_others(passes: list[dict[str, Any]]) -> float | None:
    """Cores other processes kept busy over all ``passes`` together: their CPU seconds
    (``others_cores * wall_s`` per pass) over the passes' wall seconds; None without samples."""
    got = [p for p in passes if p.get("others_cores") is not None and p.get("wall_s")]
    wall = sum(p["wall_s"] for p in got)
    return sum(p["others_cores"] * p["wall_s"] for p in got) / wall if got and wall > 0 else None


def compact(obj: Any, digits: int = 4) -> Any:
    """``obj`` with floats rounded to ``digits`` significant digits and NumPy scalars made plain."""
    if isinstance(obj, dict):
        return {str(k): compact(v, digits) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [compact(v, digits) for v in obj]
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float):
        return float(f"{obj:.{digits}g}") if np.isfinite(obj) else None
    return obj


# ------------------------------------------------------------------------------ command line
def help_line(doc: str | None) -> str:
    """A module docstring's first line as a ``--help`` description: plain words, no reST backticks."""
    return (doc or "").strip().splitlines()[0].replace("``", "") if (doc or "").strip() else ""


def bench_parser(module: str, doc: str | None, *, prog: str | None = None, out: str | None = None,
                 backend: str | Sequence[str] | None = None, voxel: float | Sequence[float] | None = None,
                 seed: int | None = None, progress: bool = False, tag: str | bool | None = None,
                 report: str | None = None) -> argparse.ArgumentParser:
    """The parser of ``python -m bench.<module>`` (description: the docstring's first line) with the
    common flags asked for by keyword, each with its default:

    - ``out``: ``--out`` (a results folder, or file where the default has a suffix);
    - ``backend``: ``--backend`` (a sequence: several; an empty one: default every backend here);
    - ``voxel``: ``--voxel-size``/``--voxel`` (``args.voxel``; a sequence: several, ``--voxel-sizes`` too);
    - ``seed``: ``--seed``; ``progress``: ``--no-progress``; ``tag``: ``--tag`` (results file stem);
    - ``report``: ``--report BENCHMARKS_MD``, only write the benchmark's :class:`Section` of that file
      from the results file ``report`` in --out (:meth:`Section.reported` does it).
    """
    ap = argparse.ArgumentParser(prog=prog or f"python -m bench.{module}", description=help_line(doc))
    if out is not None:
        ap.add_argument("--out", type=Path, default=Path(out),
                        help=f"results {'file' if Path(out).suffix else 'folder'} (default {out})")
    if backend is not None:
        many = not isinstance(backend, str)
        ap.add_argument("--backend", nargs="+" if many else None,
                        default=(list(backend) or None) if many else backend,
                        help=f"gpumap backend{'s' if many else ''} (default "
                        f"{(' '.join(backend) or 'every one available here') if many else backend})")
    if voxel is not None:
        many = not isinstance(voxel, (int, float))
        ap.add_argument("--voxel-size", "--voxel", *(["--voxel-sizes"] if many else []), dest="voxel",
                        type=float, nargs="+" if many else None,
                        default=(list(voxel) or None) if many else voxel,
                        help=f"voxel edge{'s' if many else ''}, metres (default "
                        f"{(' '.join(map(str, voxel)) or 'by target') if many else voxel})")
    if seed is not None:
        ap.add_argument("--seed", type=int, default=seed, help=f"random seed (default {seed})")
    if progress:
        ap.add_argument("--no-progress", action="store_true", help="no progress bars")
    if tag is not None:
        ap.add_argument("--tag", default=tag or None,
                        help=f"results file stem (default {tag or 'from the machine'})")
    if report is not None:
        ap.add_argument("--report", type=Path, metavar="BENCHMARKS_MD",
                        help=f"only write this benchmark's section of that file from {report} in --out")
    return ap


def progress_bar(it: Any = None, **kw: Any) -> Any:
    """A tqdm bar (``disable=True``: none)."""
    from tqdm import tqdm

    return tqdm(it, **kw)


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
    out = []
    for k in range(start, start + (len(images) if n is None else n)):
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
    n = len(images) if n is None or batch > 1 else n
    if batch > 1:
        for k in range(0, n, batch):
            m.integrate_batch(images[k : k + batch], poses[k : k + batch])
    else:
        for k in range(n):
            m.integrate(images[k % len(images)], poses[k % len(poses)])
    m.synchronize()
    return n / (time.perf_counter() - t)


def spread(values: Sequence[float]) -> dict[str, float]:
    """Median, min and max of repeated measurements (the spread a figure is quoted with)."""
    a = np.asarray(values, float)
    return {"median": float(np.median(a)), "min": float(a.min()), "max": float(a.max())}


def linear_fit(x: Sequence[float], y: Sequence[float]) -> dict[str, float]:
    """Least-squares ``y = a + b x`` with R^2, and the log-log slope (1 = linear growth)."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    (a, b), *_ = np.linalg.lstsq(np.stack([np.ones_like(x), x], 1), y, rcond=None)
    ss_res, ss_tot = float(np.sum((y - (a + b * x)) ** 2)), float(np.sum((y - y.mean()) ** 2))
    ok = (x > 0) & (y > 0)
    slope = float(np.polyfit(np.log(x[ok]), np.log(y[ok]), 1)[0]) if ok.sum() >= 2 else float("nan")
    return {"intercept": float(a), "slope": float(b), "r2": 1.0 - ss_res / ss_tot if ss_tot > 0 else 1.0,
            "loglog_slope": slope}


# ------------------------------------------------------------------------------ inputs
def _data_dir(name: str, need: str = "sonar_poses.csv") -> Path | None:
    """The first folder ``name`` (a path relative to a folder above this file, or to its parent) with the
    recording's poses and ``need``."""
    for up in Path(__file__).resolve().parents:
        for cand in (up / name, up.parent / name):
            if (cand / "sonar_poses.csv").is_file() and (cand / need).exists():
                return cand
    return None


def oasis_tank_dir() -> Path | None:
    """``shared/data/oasis_tank`` (the real Oculus M3000d tank recording) beside the checkout, as
    CI has it, or above it; None where it is not there."""
    return _data_dir("shared/data/oasis_tank")


def oasis_full_dir() -> Path | None:
    """The full-rate OASIS tank recording (``oasis_tank_full/`` with ``sonar/*.png``, written by
    ``shared/data/oasis_tank_full/get_images.sh``) beside the checkout or above it; None where its
    images are not there (``shared/data/oasis_tank_full`` itself holds only the poses)."""
    full = _data_dir("oasis_tank_full", need="sonar")
    return full or _data_dir("shared/data/oasis_tank_full", need="sonar")


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

    sel = range(len(scene.T_W_S)) if select is None else select
    extra = scene.sonar_params if scene_sonar else {}
    with SonarSimulator(scene, seed=seed, variation=variation, **extra) as s:
        return [s.ping(scene.T_W_S[k], int(k))
                for k in progress_bar(sel, desc=desc or "simulate", unit="ping", disable=not progress)]


def simulate(name: str, seed: int, progress: bool) -> tuple[list, np.ndarray, np.ndarray, float]:
    """Every ping of scene ``name``'s trajectory (the simulator's own settings): (pings, uint8
    images, poses, simulator images/s)."""
    from gpumap.sim.scenes import make_scene

    scene = make_scene(name, seed=seed)
    t0 = time.perf_counter()
    pings = render_pings(scene, seed=seed, scene_sonar=False, progress=progress, desc=f"simulate {name}")
    rate = len(pings) / (time.perf_counter() - t0)
    return pings, np.stack([quantize(p.image) for p in pings]), scene.T_W_S.copy(), rate


def render_survey(path: Path, voxel_size_m: float = 0.05) -> Path:
    """Render the survey scene's 200 pings (uint8) to ``path`` (.npz: images, poses, meta)."""
    from gpumap.sim.scenes import make_scene

    scene = make_scene("survey", voxel_size_m=voxel_size_m)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, images=np.array([quantize(p.image) for p in render_pings(scene)]),
                        poses=np.asarray(scene.T_W_S),
                        meta=np.array(json.dumps({"scene": "survey", "seed": 0})))
    return path


def load_ping_arrays(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """(images, poses) of a ping file: names images and poses, or the older imgs and T."""
    with np.load(path, allow_pickle=False) as z:
        for a, b in (("images", "poses"), ("imgs", "T")):
            if a in z.files:
                return z[a], z[b]
        raise ValueError(f"Expected a ping file with images and poses (or imgs and T), but {path} has "
                         f"{z.files}")


# The synthetic tank of the paper's set-up (130 x 20 deg, 512 beams x 400 bins, 0.1-2 m, a 4 x 3 x 1 m
# grid), along a wrist trajectory, with sparse speckled pings (each different: no cache flatters a
# backend): bench.ab, the sweep's image-size scaling and bench.speed --synthetic / --gpu-check.
def tank_spec(n_beams: int = 512, n_bins: int = 400) -> Any:
    import gpumap

    return gpumap.SonarSpec.uniform(hfov_deg=130, vfov_deg=20, n_beams=n_beams, n_bins=n_bins,
                                    range_min_m=0.1, range_max_m=2.0)


def tank_grid(voxel_size_m: float) -> Any:
    import gpumap

    return gpumap.GridSpec((-2.0, -1.5, -0.5), (2.0, 1.5, 0.5), voxel_size_m)


def trajectory(n: int) -> list[np.ndarray]:
    """Sonar poses: pitch sweep in place (first half), then a lateral wrist move."""
    out = []
    for k in range(n):
        u = k / max(1, n - 1)
        pitch = np.deg2rad(12.8 + (25 * np.sin(np.pi * 2 * u) if u < 0.5 else 0))
        yaw = 0.3 * np.sin(2 * np.pi * u)
        cp, sp, cy, sy = np.cos(pitch), np.sin(pitch), np.cos(yaw), np.sin(yaw)
        T = np.eye(4)
        Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
        T[:3, :3] = Rz @ np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
        T[:3, 3] = (-1.4, 0.0 if u < 0.5 else 0.8 * (u - 0.5), 0.35)
        out.append(T)
    return out


def speckle(spec: Any, n: int, seed: int = 0) -> list[np.ndarray]:
    """``n`` sparse speckled float32 pings of ``spec``'s image shape."""
    rng = np.random.default_rng(seed)
    return [(rng.random(spec.image_shape, dtype=np.float32) ** 6) for _ in range(n)]


# ------------------------------------------------------------------------------ results
def run_header(schema: str | None, argv: Sequence[str] | None) -> dict[str, Any]:
    """The first keys of a results file: schema, creation time, the bench's arguments and
    :func:`machine_info` (load average at the start included)."""
    head: dict[str, Any] = {} if schema is None else {"schema": schema}
    return head | {"created": now(), "argv": list(sys.argv[1:] if argv is None else argv),
                   "machine": machine_info()}


def now() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%S%z")


def write_json(path: str | os.PathLike, doc: Any, *, indent: int | None = 1,
               digits: int | None = None) -> Path:
    """Write ``doc`` to ``path`` as JSON (its folder made; written whole, then renamed, so that an
    interrupted run leaves the old file). ``digits``: floats rounded to that many significant
    digits (:func:`compact`); NumPy scalars are written as numbers either way."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    doc = doc if digits is None else compact(doc, digits)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(doc, indent=indent, separators=(",", ":") if indent is None else None,
                              default=float) + "\n")
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
            out.append(d | {"_file": p.name})
    return out


def tagged_path(out: str | os.PathLike, prefix: str, tag: str) -> Path:
    """``out/<prefix><tag>.json`` with ``tag`` lower-cased and made file-name safe."""
    return Path(out) / f"{prefix}{''.join(c if c.isalnum() or c in '-_' else '-' for c in tag.lower())}.json"


# ------------------------------------------------------------------------------ BENCHMARKS.md
@dataclass(frozen=True)
class Section:
    """A benchmark's block of BENCHMARKS.md, between ``<!-- begin:NAME -->`` and ``<!-- end:NAME -->``,
    rendered by ``markdown(results, folder)`` from the results file ``results`` of a folder (a glob
    pattern: the list of (file name, doc) of every match). ``heading``: its ``## `` line, the
    section that becomes the block where the markers are missing."""

    name: str
    heading: str
    results: str
    markdown: Callable[[Any, Path], str]

    def render(self, folder: str | os.PathLike) -> str:
        folder = Path(folder)
        if any(c in self.results for c in "*?["):
            docs = [(p.name, json.loads(p.read_text())) for p in sorted(folder.glob(self.results))]
            return self.markdown(docs, folder)
        return self.markdown(json.loads((folder / self.results).read_text()), folder)

    def put(self, text: str, folder: str | os.PathLike) -> str:
        """``text`` (a whole Markdown file) with this block rendered anew."""
        return put_text(text, f"<!-- begin:{self.name} -->", f"<!-- end:{self.name} -->", self.render(folder),
                        self.heading)

    def write(self, path: str | os.PathLike, folder: str | os.PathLike) -> None:
        path = Path(path)
        path.write_text(self.put(path.read_text() if path.exists() else "", folder))
        print(f"wrote the {self.name} section of {path}")

    def reported(self, a: argparse.Namespace) -> bool:
        """Whether ``--report`` asked only for this block (then written from the results in ``a.out``)."""
        if getattr(a, "report", None) is None:
            return False
        self.write(a.report, a.out)
        return True


def put_text(old: str, begin: str, end: str, body: str, section: str | None = None) -> str:
    """``old`` with the block between the marker lines ``begin`` and ``end`` replaced by ``body``
    (markers kept, what follows the end marker untouched); without markers, the ``## `` section
    headed ``section`` (to the next ``## `` heading) becomes the block, else the block is appended."""
    block = f"{begin}\n{body.strip(chr(10))}\n{end}"
    i, j = old.find(begin), old.find(end)
    if i >= 0 and j > i:
        return old[:i] + block + old[j + len(end) :]
    if section is not None and (i := old.find(section)) >= 0:
        j = old.find("\n## ", i + len(section))
        return old[:i] + block + ("\n" if j < 0 else "\n\n" + old[j + 1 :])
    return old.rstrip("\n") + "\n\n" + block + "\n"


def put_block(path: str | os.PathLike, begin: str, end: str, body: str, section: str | None = None) -> None:
    """:func:`put_text` on the Markdown file ``path``."""
    path = Path(path)
    path.write_text(put_text(path.read_text() if path.exists() else "", begin, end, body, section))


TEMPLATES = Path(__file__).with_name("templates.md")


def template(name: str, **values: Any) -> str:
    """The fixed text of a generated block, ``<!-- template:NAME -->`` of bench/templates.md (to the next
    such line, without its last newline), with ``values`` filled in by ``str.format``: the wording lives
    there, the figures come from the results files."""
    text = TEMPLATES.read_text().split(f"<!-- template:{name} -->\n", 1)[1].split("\n<!-- template:", 1)[0]
    return text.rstrip("\n").format_map(values)


def fnum(x: Any, fmt: str = ".3g", none: str = "–") -> str:
    """A table cell: ``x`` formatted, ``none`` for None or not finite, yes/no for a bool."""
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return none
    if isinstance(x, bool):
        return "yes" if x else "no"
    return format(x, fmt)


def pct(x: Any) -> str:
    """A fraction as a percentage with one decimal (``–`` for None)."""
    return fnum(None if x is None else 100.0 * x, ".1f") + ("" if x is None else " %")


# ------------------------------------------------------------------------------ plots
def pyplot() -> Any:
    """matplotlib.pyplot on the Agg backend (no display)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig: Any, path: str | os.PathLike, dpi: float | None = None) -> None:
    """Lay out ``fig``, write it to ``path`` (its folder made) and close it."""
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    pyplot().close(fig)
