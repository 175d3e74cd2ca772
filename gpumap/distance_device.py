"""The exact squared Euclidean distance transform of a voxel box, on a backend (the distance field's
transform; the layer itself: :mod:`gpumap.distance`).

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

__all__ = ["INF", "Transform", "check_box_dims", "edt_reference", "make_transform"]

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
    nearest voxel outside it)."""

    name: str
    device: str

    def __call__(self, mask: np.ndarray, cap2: int, inverts=(False,)) -> list[np.ndarray]:
        m = np.ascontiguousarray(mask, dtype=bool)
        if m.ndim != 3 or 0 in m.shape:
            raise ValueError(f"Expected a non-empty 3-D mask, but got shape {m.shape}")
        check_box_dims(m.shape)
        return [self._run(m, int(cap2), bool(inv)) for inv in inverts]

    def _run(self, mask: np.ndarray, cap2: int, invert: bool) -> np.ndarray:
        raise NotImplementedError


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


class WarpTransform(Transform):
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
        self.cap = 0
        wp.load_module(k, device=self.dev)

    def _grow(self, n: int) -> None:
        if n <= self.cap:
            return
        wp, dev = self.wp, self.dev
        self.mask = wp.empty(n, dtype=wp.uint8, device=dev)
        self.a, self.b, self.scratch = (wp.empty(n, dtype=int, device=dev) for _ in range(3))
        self.cap = n

    def _launch(self, kernel, shape, axis: int, inputs_head: list, inputs_tail: list) -> None:
        """One pass over the lines along ``axis``; on CPUs split in two halves on two threads (Warp's
        CPU launches are serial and release the interpreter; each line is one thread's own)."""
        wp = self.wp
        n_lines = _lines(shape, axis)
        one = self.dev.is_cuda or self.base.CPU_THREADS < 2 or n_lines < 64
        split = None if one else self.base._cpu_pool()
        args = [*inputs_head, *(int(s) for s in shape), axis, *inputs_tail]
        if split is None:
            wp.launch(kernel, dim=n_lines, inputs=[*args, 0, n_lines], device=self.dev)
            return
        h = n_lines // 2
        fut = split.submit(wp.launch, kernel, dim=n_lines - h, inputs=[*args, h, n_lines], device=self.dev)
        try:
            wp.launch(kernel, dim=h, inputs=[*args, 0, n_lines], device=self.dev)
        finally:
            fut.result()

    def _run(self, mask, cap2, invert):
        wp, k = self.wp, self.k
        n = mask.size
        self._grow(n)
        host = wp.array(mask.reshape(-1).view(np.uint8), dtype=wp.uint8, device="cpu")
        wp.copy(self.mask, host, count=n)
        a, b, s = self.a, self.b, self.scratch
        self._launch(k.edt_first_pass, mask.shape, 2, [self.mask], [cap2, int(invert), a])
        self._launch(k.edt_parabola_pass, mask.shape, 1, [a], [cap2, s, b])
        self._launch(k.edt_parabola_pass, mask.shape, 0, [b], [cap2, s, a])
        out = np.empty(n, np.int32)
        dst = wp.array(out, dtype=int, device="cpu", copy=False)
        wp.copy(dst, a, count=n)
        wp.synchronize_device(self.dev)
        return out.reshape(mask.shape)


class OpenCLTransform(Transform):
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
        self.k_first = cl.Kernel(prg, "edt_first_pass")
        self.k_first.set_scalar_arg_dtypes([None, i32, i32, i32, i32, i32, i32, None, i32, i32])
        self.k_par = cl.Kernel(prg, "edt_parabola_pass")
        self.k_par.set_scalar_arg_dtypes([None, i32, i32, i32, i32, i32, None, None, i32, i32])
        self.cap = 0

    def _grow(self, n: int) -> None:
        if n <= self.cap:
            return
        cl, mf = self.cl, self.cl.mem_flags
        self.mask = cl.Buffer(self.ctx, mf.READ_ONLY, size=max(4, n))
        self.a, self.b, self.scratch = (cl.Buffer(self.ctx, mf.READ_WRITE, size=4 * n) for _ in range(3))
        self.cap = n

    def _enqueue(self, kernel, shape, axis: int, head: list, tail: list) -> None:
        n_lines = _lines(shape, axis)
        # whole work-groups of one fixed size (PoCL builds a kernel per work-group size it meets); the
        # items past the last line return
        wg = 64 if self.is_gpu else 8
        gs = (-(-n_lines // wg) * wg,)
        kernel(self.queue, gs, (wg,), *head, *(int(s) for s in shape), axis, *tail, 0, n_lines)

    def _run(self, mask, cap2, invert):
        cl = self.cl
        n = mask.size
        self._grow(n)
        cl.enqueue_copy(self.queue, self.mask, mask.reshape(-1).view(np.uint8), is_blocking=False)
        a, b, s = self.a, self.b, self.scratch
        self._enqueue(self.k_first, mask.shape, 2, [self.mask], [cap2, int(invert), a])
        self._enqueue(self.k_par, mask.shape, 1, [a], [cap2, s, b])
        self._enqueue(self.k_par, mask.shape, 0, [b], [cap2, s, a])
        out = np.empty(n, np.int32)
        cl.enqueue_copy(self.queue, out, a, is_blocking=True)
        return out.reshape(mask.shape)


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
