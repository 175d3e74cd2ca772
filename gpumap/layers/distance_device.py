"""The exact squared Euclidean distance transform of a voxel box, on a backend (the distance field's
transform; the layer itself: :mod:`gpumap.layers.distance`).

Every runner takes a box's obstacle mask and gives, per voxel, the squared distance in voxel units to
the nearest obstacle voxel centre (int32; :data:`INF` where none lies within ``cap2``), the same
integers on every backend:

- ``numpy``: SciPy's exact feature transform (``scipy.ndimage.distance_transform_edt`` in voxel units:
  the distances are square roots of integer sums, so squaring and rounding gives those integers back);
- ``warp-cpu`` / ``warp-cuda`` and ``opencl-cpu`` / ``opencl-gpu`` / ``opencl``: the kernels of
  ``gpumap.kernels.distance`` (``distance.py`` and its twin ``distance.cl``): the separable lower
  envelope of parabolas in integer arithmetic, one thread per line, three launches.

:func:`edt_reference` is the kernels' NumPy twin (each pass a brute-force minimum over its line), for
tests on small boxes. A backend asked for by name runs there or raises
:class:`~gpumap.errors.BackendUnavailableError`; it never falls back.
"""

from __future__ import annotations

import numpy as np

from gpumap.errors import BackendUnavailableError

__all__ = ["AXES", "INF", "Cascade", "Transform", "check_box_dims", "edt_reference", "make_transform"]

#: The kernels' "no obstacle within reach" (``gpumap.kernels.distance.INF``).
INF = 2**31 - 1
#: Names a transform runs on (``opencl`` resolves to the GPU if there is one, else the CPU).
NAMES = ("numpy", "warp-cpu", "warp-cuda", "opencl", "opencl-gpu", "opencl-cpu")


def check_box_dims(shape) -> None:
    """Raise ``ValueError`` unless a box of ``shape`` keeps every squared distance below :data:`INF`."""
    if sum(int(n) ** 2 for n in shape) >= INF:
        raise ValueError(f"Expected a grid with n0^2 + n1^2 + n2^2 < 2^31 - 1 (int32 squared distances), but "
                         f"got shape {tuple(int(n) for n in shape)}")


def edt_reference(mask: np.ndarray, cap2: int = INF - 1, invert: bool = False) -> np.ndarray:
    """The kernels in NumPy: (n0, n1, n2) int32 squared distances (voxel units) from every voxel to the
    nearest voxel with ``mask`` true (false with ``invert``), :data:`INF` where none lies within
    ``cap2``. The same three passes (along axis 2, 1, 0; values above ``cap2`` dropped after each), each
    a brute-force minimum over its line: O(n) per voxel, for small boxes."""
    obst = np.asarray(mask, bool) != bool(invert)
    big = np.int64(1) << 40
    f = np.where(obst, 0, big).astype(np.int64)
    for axis in (2, 1, 0):
        g = np.moveaxis(f, axis, -1)
        n = g.shape[-1]
        q = np.arange(n, dtype=np.int64)
        d = (q[:, None] - q[None, :]) ** 2  # (q, p)
        out = np.min(g[..., None, :] + d, axis=-1)
        out = np.where(out > cap2, big, out)
        f = np.moveaxis(out, -1, axis)
    return np.where(f >= big, INF, f).astype(np.int32)


class Transform:
    """The transform on one backend: ``transform(mask, cap2, inverts)`` -> one (n0, n1, n2) int32 array
    of squared distances per entry of ``inverts`` (False: to the nearest ``mask`` voxel; True: to the
    nearest voxel outside it). Device runners also keep a transform up to date line by line
    (:class:`Cascade`, ``incremental`` True)."""

    name: str
    device: str
    incremental = False

    def __call__(self, mask: np.ndarray, cap2: int, inverts=(False,)) -> list[np.ndarray]:
        m = np.ascontiguousarray(mask, dtype=bool)
        if m.ndim != 3 or 0 in m.shape:
            raise ValueError(f"Expected a non-empty 3-D mask, but got shape {m.shape}")
        check_box_dims(m.shape)
        return [self._run(m, int(cap2), bool(inv)) for inv in inverts]

    def _run(self, mask: np.ndarray, cap2: int, invert: bool) -> np.ndarray:
        """Device runners: a full transform on a cascade kept for the next call of the same box."""
        key = (mask.shape, cap2, invert)
        shots = self.__dict__.setdefault("_shots", {})
        if key not in shots:
            if len(shots) >= 2:  # a box and its inverse at most
                shots.clear()
            shots[key] = Cascade(self, mask.shape, cap2, invert)
        c = shots[key]
        c.full(mask)
        return np.array(c.d2())


class NumpyTransform(Transform):
    name, device = "numpy", "cpu (SciPy)"

    def _run(self, mask, cap2, invert):
        from scipy import ndimage

        free = mask if invert else ~mask  # the voxels whose distance is asked for (non-zero for SciPy)
        if free.all():  # no obstacle at all
            return np.full(mask.shape, INF, np.int32)
        d = ndimage.distance_transform_edt(free)  # float64 square roots of integer sums, voxel units
        d *= d
        np.rint(d, out=d)
        d[d > cap2] = INF
        return d.astype(np.int32)


def _lines(shape, axis: int) -> int:
    n = 1
    for a, s in enumerate(shape):
        if a != axis:
            n *= int(s)
    return n


def _pass_args(src, shape, axis, cap2, invert, todo, scratch, out, marks, next_axis) -> list:
    """A pass's arguments in the kernels' order, up to (without) ``offset`` and ``n_lines``."""
    opt = [] if invert is None else [int(invert)]
    dims = [int(s) for s in shape]
    return [src, *dims, int(axis), int(cap2), *opt, todo, scratch, out, marks, int(next_axis)]


#: The axes of the three passes, in order (the first along the contiguous axis).
AXES = (2, 1, 0)


class Cascade:
    """One field's transform kept on a device runner (:class:`WarpTransform`, :class:`OpenCLTransform`)
    for a box of fixed ``shape``: the three passes' outputs stay there, so that :meth:`refresh` reruns
    only the lines whose input changed (each pass flags the next pass's lines through the values it
    changed), and the result always equals a full transform of the current mask.

    ``flags[p]`` is the byte-per-line ``todo`` of pass ``p`` (along ``AXES[p]``); ``flags[3]`` marks the
    lines of the last pass whose output changed."""

    def __init__(self, runner, shape, cap2: int, invert: bool) -> None:
        check_box_dims(shape)
        self.r, self.shape = runner, tuple(int(n) for n in shape)
        self.cap2, self.invert = int(cap2), bool(invert)
        self.n = int(np.prod(self.shape))
        self.n_lines = [_lines(self.shape, a) for a in (*AXES, AXES[-1])]
        self.bufs = runner.alloc(self.n, self.n_lines)
        self.host_flags = [np.zeros(n, np.uint8) for n in self.n_lines]
        self.fresh = False  # the device holds no transform yet

    def _passes(self) -> None:
        r, b, shp = self.r, self.bufs, self.shape
        r.launch("first", shp, AXES[0], b["mask"], self.cap2, int(self.invert), b["flags"][0], b["scratch"],
                 b["g"][0], b["flags"][1], AXES[1], self.n_lines[0])
        r.launch("parabola", shp, AXES[1], b["g"][0], self.cap2, None, b["flags"][1], b["scratch"], b["g"][1],
                 b["flags"][2], AXES[2], self.n_lines[1])
        r.launch("parabola", shp, AXES[2], b["g"][1], self.cap2, None, b["flags"][2], b["scratch"], b["g"][2],
                 b["flags"][3], AXES[2], self.n_lines[2])

    def full(self, mask: np.ndarray) -> int:
        """Transform the whole box for ``mask`` ((n0, n1, n2) bool); returns its voxels."""
        r, b = self.r, self.bufs
        r.upload(b["mask"], np.ascontiguousarray(mask, bool).reshape(-1).view(np.uint8))
        for p in range(3):
            r.fill(b["flags"][p], 1)
        self._passes()
        self._changed = None  # every line
        for p in range(4):
            r.fill(b["flags"][p], 0)
        self.fresh = True
        return self.n

    def refresh(self, mask: np.ndarray, changed: np.ndarray) -> int:
        """Bring the transform up to date with ``mask``, which differs from the last one at the flat
        indices ``changed``; returns the voxels the rerun lines hold, over three (a full transform's
        cost: the box's voxels)."""
        if not self.fresh:
            return self.full(mask)
        r, b, (_, n1, n2) = self.r, self.bufs, self.shape
        r.upload(b["mask"], np.ascontiguousarray(mask, bool).reshape(-1).view(np.uint8))
        f0 = self.host_flags[0]
        f0[...] = 0
        f0[np.asarray(changed, np.int64) // n2] = 1  # lines along axis 2: i n1 + j = flat // n2
        r.upload(b["flags"][0], f0)
        self._passes()
        for p in (1, 2, 3):
            r.download(self.host_flags[p], b["flags"][p])
            r.fill(b["flags"][p], 0)
        counts = [int(np.count_nonzero(f)) for f in self.host_flags]
        self._changed = self.host_flags[3].reshape(n1, n2) != 0
        lengths = [self.shape[a] for a in AXES]
        return -(-sum(c * n for c, n in zip(counts[:3], lengths, strict=True)) // 3)

    def changed_lines(self) -> np.ndarray | None:
        """(n1, n2) bool: the lines along axis 0 whose distances the last :meth:`refresh` changed (None
        after :meth:`full`: every line)."""
        return self._changed

    def d2(self) -> np.ndarray:
        """(n0, n1, n2) int32 squared distances of the current transform (on warp-cpu a view of the
        device array: valid until the next update)."""
        return self.r.read_d2(self.bufs).reshape(self.shape)


class WarpTransform(Transform):
    incremental = True

    def __init__(self, device: str, device_index: int | None) -> None:
        from gpumap.backends import base, warp_backend

        wp, _ = warp_backend._warp()
        if device == "cuda" and not wp.is_cuda_available():
            raise BackendUnavailableError("warp-cuda needs a CUDA device, and Warp finds none here")
        count = wp.get_cuda_device_count() if device == "cuda" else 1
        index = base.check_device_index(device_index, count, f"warp-{device}")
        from gpumap.kernels import distance as k

        self.wp, self.k, self.base = wp, k, base
        self.dev = wp.get_device(f"cuda:{index}" if device == "cuda" else "cpu")
        self.name, self.device = f"warp-{device}", f"{self.dev.alias} ({self.dev.name})"
        self.kernels = {"first": k.edt_first_pass, "parabola": k.edt_parabola_pass}
        wp.load_module(k, device=self.dev)

    def alloc(self, n: int, n_lines: list[int]) -> dict:
        wp, dev = self.wp, self.dev
        return {"mask": wp.zeros(n, dtype=wp.uint8, device=dev),
                "g": [wp.zeros(n, dtype=int, device=dev) for _ in range(3)],
                "scratch": wp.zeros(n, dtype=int, device=dev),
                "flags": [wp.zeros(m, dtype=wp.uint8, device=dev) for m in n_lines]}

    def upload(self, dst, src: np.ndarray) -> None:
        if self.dev.is_cpu:
            dst.numpy()[...] = src
        else:
            dst.assign(self.wp.array(src, dtype=dst.dtype, device="cpu"))

    def download(self, dst: np.ndarray, src) -> None:
        dst[...] = src.numpy()

    def fill(self, a, value: int) -> None:
        a.fill_(value)

    def read_d2(self, bufs) -> np.ndarray:
        self.wp.synchronize_device(self.dev)
        return bufs["g"][2].numpy()

    def launch(self, name: str, shape, axis: int, src, cap2: int, invert, todo, scratch, out, marks,
               next_axis: int, n_lines: int) -> None:
        """One pass over the lines along ``axis``; on CPUs split in two halves on two threads (Warp's
        CPU launches are serial and release the interpreter; each line is one thread's own, and the flags
        they share are only ever set to 1)."""
        wp, kernel = self.wp, self.kernels[name]
        args = _pass_args(src, shape, axis, cap2, invert, todo, scratch, out, marks, next_axis)
        one = self.dev.is_cuda or self.base.CPU_THREADS < 2 or n_lines < 64
        if one:
            wp.launch(kernel, dim=n_lines, inputs=[*args, 0, n_lines], device=self.dev)
            return
        # the flagged lines halved between the threads (the flags are host memory here)
        cum = np.cumsum(todo.numpy(), dtype=np.int64)
        h = int(np.searchsorted(cum, (int(cum[-1]) + 1) // 2)) + 1 if cum[-1] else n_lines
        if h >= n_lines:
            wp.launch(kernel, dim=n_lines, inputs=[*args, 0, n_lines], device=self.dev)
            return
        fut = self.base._cpu_pool().submit(wp.launch, kernel, dim=n_lines - h, inputs=[*args, h, n_lines],
                                           device=self.dev)
        try:
            wp.launch(kernel, dim=h, inputs=[*args, 0, n_lines], device=self.dev)
        finally:
            fut.result()



class OpenCLTransform(Transform):
    incremental = True

    def __init__(self, kind: str, device_index: int | None) -> None:
        from gpumap.backends import opencl_backend as ob

        cl = ob._opencl()
        d = ob.usable_opencl_device(kind, device_index)
        ctx, _ = ob._opencl_context(d)
        prg = ob.extra_program(ctx, "distance")
        self.cl, self.ctx = cl, ctx
        self.queue = cl.CommandQueue(ctx)
        self.is_gpu = bool(d.type & cl.device_type.GPU)
        self.name = "opencl-gpu" if self.is_gpu else "opencl-cpu"
        self.device = f"{d.platform.name.strip()}: {d.name.strip()}"
        i32 = np.int32
        # kernel objects hold their arguments: this runner's own
        first = cl.Kernel(prg, "edt_first_pass")
        first.set_scalar_arg_dtypes([None, *[i32] * 6, None, None, None, None, i32, i32, i32])
        par = cl.Kernel(prg, "edt_parabola_pass")
        par.set_scalar_arg_dtypes([None, *[i32] * 5, None, None, None, None, i32, i32, i32])
        self.kernels = {"first": first, "parabola": par}

    def alloc(self, n: int, n_lines: list[int]) -> dict:
        cl, mf = self.cl, self.cl.mem_flags

        def buf(nbytes):
            b = cl.Buffer(self.ctx, mf.READ_WRITE, size=max(4, int(nbytes)))
            cl.enqueue_fill_buffer(self.queue, b, np.uint8(0), 0, max(4, int(nbytes)))
            return b

        return {"mask": buf(n), "g": [buf(4 * n) for _ in range(3)], "scratch": buf(4 * n),
                "flags": [buf(m) for m in n_lines], "host": np.empty(n, np.int32), "n_lines": n_lines}

    def upload(self, dst, src: np.ndarray) -> None:
        self.cl.enqueue_copy(self.queue, dst, src, is_blocking=True)

    def download(self, dst: np.ndarray, src) -> None:
        self.cl.enqueue_copy(self.queue, dst, src, is_blocking=True)

    def fill(self, a, value: int) -> None:
        self.cl.enqueue_fill_buffer(self.queue, a, np.uint8(value), 0, a.size)

    def read_d2(self, bufs) -> np.ndarray:
        self.cl.enqueue_copy(self.queue, bufs["host"], bufs["g"][2], is_blocking=True)
        return bufs["host"]

    def launch(self, name: str, shape, axis: int, src, cap2: int, invert, todo, scratch, out, marks,
               next_axis: int, n_lines: int) -> None:
        # whole work-groups of one fixed size (PoCL builds a kernel per work-group size it meets); the
        # items past the last line return
        wg = 64 if self.is_gpu else 8
        gs = (-(-n_lines // wg) * wg,)
        args = [*_pass_args(src, shape, axis, cap2, invert, todo, scratch, out, marks, next_axis), 0, n_lines]
        self.kernels[name](self.queue, gs, (wg,), *args)



def make_transform(name: str, device_index: int | None = None) -> Transform:
    """The transform on backend ``name`` (one of :data:`NAMES`), on its device ``device_index`` (None:
    the first); raises :class:`~gpumap.errors.BackendUnavailableError` where it cannot run, never
    picking another."""
    if name == "numpy":
        from gpumap.backends import base

        base.check_device_index(device_index, 1, name)
        return NumpyTransform()
    if name in ("warp-cpu", "warp-cuda"):
        return WarpTransform(name.split("-")[1], device_index)
    if name in ("opencl", "opencl-gpu", "opencl-cpu"):
        kind = {"opencl": "any", "opencl-gpu": "gpu", "opencl-cpu": "cpu"}[name]
        return OpenCLTransform(kind, device_index)
    raise ValueError(f"Expected backend to be None or one of {NAMES}, but got {name!r}")
