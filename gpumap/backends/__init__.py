"""Compute backends: where map values live and how a ping is applied to them.

Each backend holds one map as a pool of blocks of ``B x B x Bz`` voxels and a coarse index over
them (:class:`Backend`: float32 values, ``+inf`` = unknown) and applies
``integrate(params, image, method)`` to it. ``numpy`` is the reference
(:mod:`gpumap.reference`); ``warp-cpu``/``warp-cuda`` and ``opencl`` run the kernels in
``gpumap.kernels`` (``minmax.py`` and its twin ``minmax.cl``). Everything a ping needs on
the device is allocated once, in the constructor; programs are compiled once per process
(Warp caches modules on disk, OpenCL programs are cached per context).

One module per concern: :mod:`~gpumap.backends.base` (the :class:`Backend` interface, names,
constants and the knobs a run may turn), :mod:`~gpumap.backends.numpy_backend`,
:mod:`~gpumap.backends.warp_backend`, :mod:`~gpumap.backends.opencl_backend` and
:mod:`~gpumap.backends.tables` (the per-ping max table built on the host). This package
names them all, builds a backend by name (:func:`make_backend`) and says which run here
(:func:`available_backends`). Setting a knob of :data:`~gpumap.backends.base.TUNABLES` here
(``gpumap.backends.CPU_THREADS = 1``) sets it where the backends read it.
"""

from __future__ import annotations

import logging
import os
import sys
import types

import numpy as np

from gpumap.backends import base, opencl_backend, tables, warp_backend
from gpumap.backends.base import AUTO_ORDER, BACKENDS, N_SLOTS, TUNABLES, U8_SCALE, Backend, GridTooLargeError
from gpumap.backends.numpy_backend import NumpyBackend
from gpumap.backends.opencl_backend import OpenCLBackend, opencl_devices, usable_opencl_device
from gpumap.backends.tables import build_table_host, opencl_host_table, table_rows, table_size
from gpumap.backends.warp_backend import WarpBackend, cuda_driver_loadable
from gpumap.errors import BackendUnavailableError
from gpumap.spec import SonarSpec

# more names of the one module this package was, importable from here as they were (gpumap's
# modules and tests import some of the private ones)
warp_host_table = tables.warp_host_table
warp_launch_halves, warp_upload_image = warp_backend.warp_launch_halves, warp_backend.warp_upload_image
_warp, _warp_params = warp_backend._warp, warp_backend._warp_params
_opencl, _opencl_context = opencl_backend._opencl, opencl_backend._opencl_context
_union_groups = base._union_groups

__all__ = [
    "AUTO_ORDER", "BACKENDS", "BATCH_BOX_VOXELS_MAX", "BATCH_MAX", "COPY_SPLIT_BYTES",
    "COPY_THREADS", "CPU_CHUNK", "CPU_THREADS", "GPU_CHUNK", "N_SLOTS", "OPENCL_BATCH_BOX_VOXELS_MAX",
    "TUNABLES", "U8_SCALE", "Backend",
    "GridTooLargeError", "NumpyBackend", "OpenCLBackend", "WarpBackend", "available_backends",
    "build_table_host", "cuda_driver_loadable", "make_backend", "opencl_devices", "opencl_host_table",
    "table_rows", "table_size", "usable_opencl_device", "warp_host_table", "warp_launch_halves",
    "warp_upload_image",
]

log = logging.getLogger("gpumap")


def make_backend(
    name: str,
    spec: SonarSpec,
    template_S: np.ndarray | None = None,
    use_table: bool | None = None,
    *,
    visible: bool = False,
    B: int = 8,
    Bz: int | None = None,
    cap: int = 0,
    device_index: int | None = None,
) -> Backend:
    """Build the backend called ``name`` (never another one; raises if it cannot run) with a pool
    of ``cap`` blocks of ``B x B x Bz`` voxels (``Bz`` default ``B``; grown later with
    :meth:`Backend.grow`).

    ``use_table`` picks how kernels take the max over a footprint: a per-ping max table
    (True), a loop over cells (False), or the faster for the device (None: table on CPUs).
    ``visible`` keeps the visible rule's per-voxel evidence (5 more bytes per voxel).
    ``device_index`` (None: the backend's first) picks the device: ``warp-cuda`` runs on
    ``cuda:<device_index>``, ``opencl-gpu`` / ``opencl-cpu`` / ``opencl`` on that device of
    :func:`opencl_devices` of their kind (GPUs first); ``numpy`` and ``warp-cpu`` have device 0
    only. An index the backend does not have here raises ``ValueError``, never another device.
    """
    args = (spec, template_S, use_table)
    kw = {"visible": visible, "B": B, "Bz": Bz, "cap": cap}
    if name == "numpy":
        base.check_device_index(device_index, 1, name)
        return NumpyBackend(*args, **kw)
    if name in ("warp-cpu", "warp-cuda"):
        return WarpBackend(*args, device=name.split("-")[1], device_index=device_index, **kw)
    if name in ("opencl", "opencl-gpu", "opencl-cpu"):
        kind = {"opencl": "any", "opencl-gpu": "gpu", "opencl-cpu": "cpu"}[name]
        return OpenCLBackend(*args, kind=kind, device_index=device_index, **kw)
    raise ValueError(f"Expected backend to be 'auto' or one of {BACKENDS}, but got {name!r}")


def available_backends(among=None) -> list[str]:
    """Backends that can run on this machine, fastest first (the order ``auto`` tries); ``among``
    (names): probe only those (starting Warp or building the OpenCL kernels takes seconds)."""
    out = []
    for name in AUTO_ORDER:
        if among is not None and name not in among:
            continue
        try:
            if name == "warp-cuda":
                wp, _ = warp_backend._warp()
                ok = wp.is_cuda_available()
            elif name.startswith("opencl"):
                ok = opencl_backend.usable_opencl_device(name.split("-")[1]) is not None
            elif name == "warp-cpu":
                warp_backend._warp()
                ok = True
            else:
                ok = True
        except BackendUnavailableError:
            ok = False
        if ok:
            out.append(name)
    if os.environ.get("GPUMAP_DEBUG"):
        log.debug("available backends: %s", out)
    return out


class _Package(types.ModuleType):
    """This package, as a module whose knobs (:data:`~gpumap.backends.base.TUNABLES`) are
    :mod:`~gpumap.backends.base`'s, never a copy: ``gpumap.backends.CPU_THREADS = 1`` (as
    :mod:`gpumap.pipeline.workers` and ``bench/ab.py`` set it; tests patch the others) sets
    ``gpumap.backends.base.CPU_THREADS``, where the backends read it when they need it."""


def _knob(name: str) -> property:
    return property(lambda _: getattr(base, name), lambda _, value: setattr(base, name, value),
                    doc=f"``gpumap.backends.base.{name}``")


for _name in TUNABLES:
    setattr(_Package, _name, _knob(_name))
sys.modules[__name__].__class__ = _Package
