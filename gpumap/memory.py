"""How much memory mapping a grid takes, measured, and the check made before allocating it.

The mapper's per-voxel *state* is what each rule keeps (:data:`STATE_BYTES`: float32 values for
the plain rule; for the visible and evidence rules also their counts). A run takes more than its state at
its peak: the map read back as float32 values, the occupied and observed masks, the arrays
``save`` gathers (a second copy of the state, and the values once more), the backend's own
buffers. ``bench/memory.py`` measures the peak resident set of ``gpumap replay`` for boxes of
7 to 32 M voxels, per backend and rule, with and without the pictures; on the 2-core CPU
(``bench/results/memory_cpu_2c.json``) the cost of a voxel more (the slope between the two
largest boxes) is at most 16.0 bytes for the plain rule and 44.7 for the visible and evidence
rules (16 bytes of state each) on every backend (without pictures: with them, at these sizes,
the pictures set the peak and the slope is lower), which

    peak bytes  =  FIXED_BYTES[backend]  +  voxels * (STATE_COPIES * STATE_BYTES[rule] + EXTRA_BYTES)

covers (16.1 and 44.9 bytes a voxel), with a fixed cost above every measured one. A rule
that keeps more state per voxel is priced from its entry in :data:`STATE_BYTES`
alone (the one table to change when a rule's arrays change), and :func:`run_bytes` is what
``gpumap replay`` checks, before the mapper allocates anything, against the memory the machine
has available (``MemAvailable``), less :data:`HEADROOM`, or against ``--max-memory``. The
mapper itself checks its state alone against the device's free memory
(:func:`free_memory_bytes`) when it allocates.
"""

from __future__ import annotations

import re

__all__ = [
    "EXTRA_BYTES",
    "FIXED_BYTES",
    "HEADROOM",
    "STATE_BYTES",
    "STATE_COPIES",
    "available_bytes",
    "bytes_per_voxel",
    "check_run_fits",
    "free_memory_bytes",
    "parse_size",
    "run_bytes",
]

#: Bytes of per-voxel state each rule keeps in the mapper (its arrays over the grid's blocks).
STATE_BYTES: dict[str, int] = {"plain": 4, "visible": 16, "evidence": 16}

#: Copies of the state a run holds at its peak (the mapper's, and ``save``'s gathered blocks),
#: and the bytes per voxel beyond them (float32 values read back, the boolean masks), fitted to
#: the measured slopes of every backend and rule (``tests/test_memory.py`` checks they cover them).
STATE_COPIES = 2.4
EXTRA_BYTES = 6.5

#: Measured fixed cost of a run per backend (interpreter, libraries, compiled kernels), bytes.
FIXED_BYTES: dict[str, int] = {"numpy": 400 << 20, "warp-cpu": 560 << 20, "opencl-cpu": 560 << 20}
_FIXED_OTHER = 600 << 20  # GPU backends and anything unmeasured: the largest above, rounded up

#: Share of the available memory a run may plan to take (the rest is left to the machine).
HEADROOM = 0.9

#: Where the figures come from (named in the error).
SOURCE = "bench/results/memory_cpu_2c.json"


def bytes_per_voxel(rule: str) -> float:
    """Peak bytes a run takes per voxel of its grid under ``rule`` (see the module docstring)."""
    if rule not in STATE_BYTES:
        raise ValueError(f"Expected a rule of {', '.join(STATE_BYTES)}, but got {rule!r}")
    return STATE_COPIES * STATE_BYTES[rule] + EXTRA_BYTES


def run_bytes(n_voxels: int, rule: str, backend: str = "auto", maps: int = 1) -> int:
    """Peak bytes of mapping a grid of ``n_voxels`` with ``rule`` on ``backend`` (``"auto"``: the
    most of any backend), ``maps`` such maps held at once (``--compare-rules`` holds two)."""
    fixed = FIXED_BYTES.get(backend, _FIXED_OTHER)
    return int(fixed + maps * n_voxels * bytes_per_voxel(rule))


def available_bytes() -> int | None:
    """``MemAvailable`` of ``/proc/meminfo`` (None where there is none)."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        return None
    return None


def free_memory_bytes(backend: str, device_index: int | None = None) -> int | None:
    """Best guess of the memory a map may take on the backend ``backend`` (None if unknown): the
    machine's available memory for CPU backends, the free memory of GPU ``device_index`` (0 if
    None) for ``warp-cuda``."""
    try:
        if backend in ("numpy", "warp-cpu") or backend.startswith("opencl"):
            return available_bytes()
        if backend == "warp-cuda":
            from gpumap.backends import _warp

            wp, _ = _warp()  # initialised quietly, as the backend does
            return int(wp.get_device(f"cuda:{int(device_index or 0)}").free_memory)
    except Exception:  # the check is advisory; the allocation itself still fails loudly
        return None
    return None


#: What to change, as the error says it to a caller of the API (commands pass their flags).
API_REMEDY = "use a larger voxel size or a smaller grid, or set the cap (max_memory=)"


def check_run_fits(n_voxels: int, rule: str, backend: str = "auto", max_bytes: int | None = None,
                   maps: int = 1, what: str = "the grid", remedy: str = API_REMEDY) -> int:
    """Raise :class:`~gpumap.backends.GridTooLargeError` (a ``ValueError``) unless a run on
    ``n_voxels`` fits under ``max_bytes`` (None: :data:`HEADROOM` of the available memory);
    return the bytes it is expected to take. The message gives the figure, how it was reckoned
    and what to change."""
    from gpumap.backends import GridTooLargeError

    need = run_bytes(n_voxels, rule, backend, maps)
    if max_bytes is None:
        avail = available_bytes()
        if avail is None:
            return need
        cap, whose = int(HEADROOM * avail), f"{HEADROOM:.0%} of the {avail / 2**30:.1f} GiB available"
    else:
        cap, whose = int(max_bytes), f"{max_bytes / 2**30:.2f} GiB (the cap asked for)"
    if need > cap:
        held = f" x {maps} maps" if maps > 1 else ""
        raise GridTooLargeError(
            f"Expected {what} to fit in memory, but {n_voxels:,} voxels ({rule} rule, {backend}) need "
            f"about {need / 2**30:.1f} GiB ({bytes_per_voxel(rule):.1f} bytes a voxel{held}, measured in "
            f"{SOURCE}, plus {run_bytes(0, rule, backend) / 2**30:.1f} GiB fixed) and the cap is {whose}: "
            f"{remedy}")
    return need


_UNITS = {"": 1, "b": 1, "k": 1 << 10, "m": 1 << 20, "g": 1 << 30, "t": 1 << 40}


def parse_size(text: str) -> int | None:
    """``'8G'``, ``'512M'``, ``'1.5GiB'``, ``'2000000000'`` (bytes) -> bytes; ``'auto'`` -> None."""
    t = text.strip().lower()
    if t == "auto":
        return None
    m = re.fullmatch(r"([0-9]*\.?[0-9]+)\s*([kmgt]?)(?:i?b)?", t)
    if not m or float(m.group(1)) <= 0:
        raise ValueError(f"Expected 'auto' or a size such as 8G, 512M or 1.5GiB, but got {text!r}")
    return int(float(m.group(1)) * _UNITS[m.group(2)])
