"""The min-max occupancy mapper: the public entry point of gpumap."""

from __future__ import annotations

import json
import logging
import os
import struct
import threading
import tokenize
import zipfile
import zlib
from pathlib import Path

import numpy as np

from gpumap.atomic import atomic_write
from gpumap.backends import AUTO_ORDER, BACKENDS, Backend, GridTooLargeError, make_backend
from gpumap.backends import available_backends as _available
from gpumap.errors import (
    BackendUnavailableError,
    FormatError,
    LimitError,
    check_carve_views,
    check_finite_scalar,
    check_pose,
)
from gpumap.geometry import RULES, make_template_S, pose_pad_m, static_params
from gpumap.spec import GridSpec, SonarSpec

__all__ = ["MinMaxMapper", "available_backends"]

log = logging.getLogger("gpumap")

METHODS = ("gather", "template")
_ONE_BITS = np.uint32(0x3F800000)  # the bits of float32 1.0
FILE_FORMAT = "gpumap.MinMaxMapper"
FILE_VERSION = 3  # 3: the optional confidence layer (confirmed); 2: the visible rule's evidence
# (bright, count) and the rule; 1 and 2 still load


def available_backends() -> list[str]:
    """Backends that run on this machine, in the order ``backend="auto"`` tries them."""
    return _available()


def _free_memory_bytes(name: str) -> int | None:
    """Best guess of the memory a grid may take on the backend ``name`` (None if unknown)."""
    try:
        if name in ("numpy", "warp-cpu") or name.startswith("opencl"):
            with open("/proc/meminfo") as f:
                for line in f:
                    if line.startswith("MemAvailable:"):
                        return int(line.split()[1]) * 1024
        if name == "warp-cuda":
            from gpumap.backends import _warp

            wp, _ = _warp()  # initialised quietly, as the backend does
            return int(wp.get_device("cuda:0").free_memory)
    except Exception:  # the check is advisory; the allocation itself still fails loudly
        return None
    return None


def _check_pose_cov(pose_cov: object) -> np.ndarray:
    """(6, 6) finite, symmetric, positive semi-definite float64, or raise saying what came."""
    if isinstance(pose_cov, np.ma.MaskedArray):
        raise TypeError("Expected a plain array for 'pose_cov', but got a masked array")
    C = np.asarray(pose_cov)
    if C.shape != (6, 6) or C.dtype.kind not in "fiu":
        raise ValueError(f"Expected pose_cov of shape (6, 6) real, but got {C.shape} {C.dtype}")
    C = C.astype(np.float64)
    scale = max(1.0, float(np.abs(C).max())) if np.all(np.isfinite(C)) else np.inf
    if not np.isfinite(scale) or not np.allclose(C, C.T, rtol=0.0, atol=1e-9 * scale):
        raise ValueError("Expected a finite, symmetric pose_cov, but got one that is not")
    C = 0.5 * (C + C.T)
    if np.linalg.eigvalsh(C)[0] < -1e-12 * scale:
        raise ValueError("Expected a positive semi-definite pose_cov, but it has a negative eigenvalue")
    return C


def _check_poses(Ts: np.ndarray) -> np.ndarray:
    """(B, 4, 4) float64 copy of ``Ts`` after :func:`gpumap.errors.check_pose`'s checks, in
    whole-array form; the first pose that fails is handed to check_pose for its message."""
    if np.iscomplexobj(Ts) or Ts.dtype.kind not in "fiub":
        raise TypeError(f"Expected real entries in 'T_W_S', but got dtype {Ts.dtype}")
    a = np.array(Ts, dtype=np.float64)
    if a.shape[0] == 0:
        return a
    atol = 1e-5
    R = a[:, :3, :3]
    G = np.einsum("bki,bkj->bij", R, R) - np.eye(3)
    c0, c1, c2 = R[:, :, 0], R[:, :, 1], R[:, :, 2]
    det = np.einsum("bi,bi->b", np.cross(c0, c1), c2)
    with np.errstate(invalid="ignore"):
        bad = (
            ~np.isfinite(a).all(axis=(1, 2))
            | (np.abs(a[:, 3] - (0.0, 0.0, 0.0, 1.0)) > atol).any(axis=1)
            | (np.abs(G).max(axis=(1, 2)) > atol)
            | (det < 0)
        )
    for k in np.flatnonzero(bad):  # raises with check_pose's message (or the pose passes)
        a[k] = check_pose(Ts[k], f"T_W_S[{k}]")
    return a


def _evidence_empty(n: int) -> tuple[np.ndarray, np.ndarray]:
    return np.full(n, np.inf, dtype=np.float32), np.zeros(n, dtype=np.uint8)


class MinMaxMapper:
    """Min-max filtering occupancy map (Phung et al.), on a fixed world grid.

    For each ping, every grid voxel whose centre the sonar sees gets the maximum image
    intensity over its footprint (the cells its bounding sphere touches: conservative, so
    a thin bright object is never lost to sampling). Never-observed voxels stay unknown.

    How views combine (``rule``):

    - ``"visible"`` (default with ``method="gather"``): a dark view lowers a voxel only
      where it proves the voxel empty. A view is *clear* when no image cell
      ``>= threshold`` lies nearer than the voxel's footprint in the footprint's beams:
      nothing stood between the sonar and the voxel, at any elevation. A dark view behind
      a return proves nothing: the voxel may sit in that return's acoustic shadow, or be a
      surface seen at grazing incidence behind nearer parts of itself. A voxel ever seen
      bright (``>= threshold``) keeps the dimmest of its bright values until clear dark
      views carve it: ``carve_views`` (2) of them, one darker than ``threshold / 2``
      counting twice (speckle rarely darkens a seen surface that far). A voxel never seen
      bright takes the minimum over its views, as in the plain rule. Every update is a min
      or a count, so the map does not depend on the order of the pings. Costs 5 bytes per
      voxel more (a float32 and a uint8) and a per-beam scan of each ping.
    - ``"plain"``: the paper's rule: the minimum over all views. A ping carves voxels in its
      acoustic shadow, so surfaces seen from one side are erased by views from the other.

    Parameters
    ----------
    spec : SonarSpec
        The sonar's geometry.
    grid : GridSpec
        The world grid.
    backend : str
        ``"auto"`` (fastest that works, in the order warp-cuda, opencl on a GPU, opencl on
        a CPU (PoCL), warp-cpu, numpy; the choice is logged and kept in :attr:`backend`),
        or one of ``"numpy"``, ``"warp-cpu"``, ``"warp-cuda"``, ``"opencl"`` (GPU if there
        is one, else CPU), ``"opencl-gpu"``, ``"opencl-cpu"``. A named backend that cannot
        run raises :class:`gpumap.BackendUnavailableError`; it never falls back.
    method : str
        ``"gather"`` (every voxel of the field of view's bounding box, no holes) or
        ``"template"`` (the paper's six steps on a voxel template: may leave holes).
    shadow_m : float
        Acoustic-shadow allowance, metres (default 0: the paper's min-max). A strong return
        also counts for the voxels up to ``shadow_m`` behind it in its beams, so a ping does
        not carve the far side of a thin object it cannot see through (each footprint reaches
        ``shadow_m`` further towards the sonar). Trades false positives behind returns for
        fewer false negatives; think of it as the thinnest object the map must keep whole.
    footprint_max : str
        How kernels take the max over a footprint, a speed knob with identical results:
        ``"auto"``/``"table"`` (a per-ping max table, built in the way that suits the
        device, then two reads per voxel) or ``"loop"`` (a loop over the footprint's cells).
    rule : str or None
        ``"visible"`` or ``"plain"``, see above; None (default) picks ``"visible"`` for the
        gather method and ``"plain"`` for the template method (the paper's six steps with the
        paper's rule; ``"visible"`` needs ``method="gather"``).
    threshold : float
        Intensity in (0, 1] from which a view counts as bright (the visible rule's returns and
        shadows). Set it to the threshold you read the map at; lower is more conservative
        (more views count as bright, fewer carve). Default 0.1.
    carve_views : int
        Visible rule: the clear dark evidence that carves a voxel once seen bright, in views
        (one darker than ``threshold / 2`` counts twice). 2 (default) keeps a surface through
        one speckle-dark view; 1 carves more water and more weak surfaces (fewer false
        positives, more false negatives); larger is more conservative. Read-time only: it
        may be changed between pings (:attr:`carve_views`), in 1..255.
    confidence : bool
        Keep the confidence layer (:mod:`gpumap.confidence`): after each ping a separate pass
        marks the occupied voxels that view confirmed (resolved in elevation), read with
        :meth:`confidence`; :meth:`view_gain` scores candidate poses against it. Costs a byte
        per voxel on the host and one read of the map per ping. Default False.
    """

    def __init__(
        self,
        spec: SonarSpec,
        grid: GridSpec,
        backend: str = "auto",
        method: str = "gather",
        *,
        shadow_m: float = 0.0,
        footprint_max: str = "auto",
        rule: str | None = None,
        threshold: float = 0.1,
        carve_views: int = 2,
        confidence: bool = False,
    ) -> None:
        if not isinstance(spec, SonarSpec):
            raise TypeError(f"Expected a gpumap.SonarSpec for 'spec', but got {type(spec).__name__}")
        if not isinstance(grid, GridSpec):
            raise TypeError(f"Expected a gpumap.GridSpec for 'grid', but got {type(grid).__name__}")
        if method not in METHODS:
            raise ValueError(f"Expected method to be one of {METHODS}, but got {method!r}")
        if backend != "auto" and backend not in BACKENDS:
            raise ValueError(f"Expected backend to be 'auto' or one of {BACKENDS}, but got {backend!r}")
        if footprint_max not in ("auto", "table", "loop"):
            raise ValueError(
                f"Expected footprint_max to be 'auto', 'table' or 'loop', but got {footprint_max!r}"
            )
        if rule is None:
            rule = "visible" if method == "gather" else "plain"
        if rule not in RULES:
            raise ValueError(f"Expected rule to be one of {RULES} (or None), but got {rule!r}")
        if rule == "visible" and method != "gather":
            raise ValueError(
                f"Expected method='gather' with rule='visible' (the template method's duplicate "
                f"points cannot count views once), but got method={method!r}; use rule='plain' with it"
            )
        thr = check_finite_scalar(threshold, "threshold")
        if not 0.0 < thr <= 1.0:
            raise ValueError(f"Expected threshold in (0, 1], but got {thr}")
        self.rule = rule
        self.threshold = thr
        self.carve_views = carve_views
        self._use_table = None if footprint_max == "auto" else footprint_max == "table"
        self.spec = spec
        self.grid = grid
        self.method = method
        self.n_integrated = 0
        shadow = check_finite_scalar(shadow_m, "shadow_m")
        if shadow < 0:
            raise ValueError(f"Expected shadow_m >= 0, but got {shadow}")
        self.shadow_m = shadow
        self._params = static_params(spec, grid, shadow, rule, thr)
        self._rho0, self._near0 = float(self._params["rho"]), float(self._params["near"])
        self._fov_pts_S = spec.fov_corners_S()
        self._template = make_template_S(spec, grid.voxel_size_m) if method == "template" else None
        if self._template is not None:
            self._params["n_points"] = self._template.shape[0]
        self._staging = np.empty(spec.image_shape, dtype=np.float32)
        # One ping at a time: integrate, reads and writes hold this lock, so threads sharing a
        # mapper serialize (and, every update being a min or a count, get the map one thread
        # would have made).
        self._lock = threading.RLock()
        self._backend = self._make_backend(backend)
        if not isinstance(confidence, (bool, np.bool_)):
            raise TypeError(f"Expected a bool for 'confidence', but got {type(confidence).__name__}")
        self._confirmed = np.zeros(grid.n_voxels, np.uint8) if confidence else None
        # the elevation-arc directions (gpumap.nbv.PAIR_STEPS bits) each voxel was observed along
        self._arcs = np.zeros(grid.n_voxels, np.uint16) if confidence else None
        self._gain_runner = None
        # auto says what it picked; a backend asked for by name is what the caller already knows
        (log.info if backend == "auto" else log.debug)(
            "gpumap: backend %s on %s", self._backend.name, self._backend.device)

    def _make_backend(self, backend: str) -> Backend:
        names = AUTO_ORDER if backend == "auto" else (backend,)
        errors = []
        for name in names:
            need = self.grid.nbytes * (9 if self.rule == "visible" else 4) // 4
            free = _free_memory_bytes(name)
            if free is not None and need > free:
                msg = (
                    f"Expected a grid that fits in memory, but {self.grid.shape} voxels at "
                    f"voxel_size_m={self.grid.voxel_size_m} need {need / 2**30:.2f} GiB and "
                    f"{name} has {free / 2**30:.2f} GiB free"
                )
                if backend != "auto":
                    raise ValueError(msg)
                errors.append(f"{name}: {msg}")
                continue
            try:
                return make_backend(
                    name,
                    self.spec,
                    self.grid.n_voxels,
                    self._template,
                    self._use_table,
                    visible=self.rule == "visible",
                )
            except (BackendUnavailableError, GridTooLargeError) as e:
                if backend != "auto":
                    raise
                errors.append(f"{name}: {e}")
        raise BackendUnavailableError("No backend could run: " + "; ".join(errors))

    # ------------------------------------------------------------------ properties
    @property
    def backend(self) -> str:
        """The backend in use, as ``gpumap info`` names it: ``"warp-cuda"``, ``"warp-cpu"``,
        ``"opencl-gpu"``, ``"opencl-cpu"`` or ``"numpy"`` (``"auto"`` and ``"opencl"`` resolve to one)."""
        return self._backend.name

    @property
    def device(self) -> str:
        """The device the backend runs on, in words."""
        return self._backend.device

    # ------------------------------------------------------------------ update
    def _check_image(self, image: object) -> np.ndarray:
        """The image as C-contiguous uint8 (backends scale it by 1/255, GPUs after the upload)
        or float32 in [0, 1]: ``image`` itself when it already is, else a conversion in the
        mapper's staging buffer. Raises on anything else."""
        if not isinstance(image, np.ndarray):
            raise TypeError(f"Expected a numpy array for 'image', but got {type(image).__name__}")
        if isinstance(image, np.ma.MaskedArray):  # its data under the mask could be anything
            raise TypeError(
                "Expected a plain numpy array for 'image', but got a masked array: fill it first "
                "(image.filled(0.0) treats masked cells as no return)"
            )
        if image.shape != self.spec.image_shape:
            raise ValueError(
                f"Expected image of shape {self.spec.image_shape} (n_bins, n_beams) for 'image', "
                f"but got {image.shape}"
            )
        out = self._staging
        if image.dtype == np.uint8:  # every byte is a valid intensity; backends widen it
            return np.ascontiguousarray(image)
        if image.dtype == np.float32 and image.flags.c_contiguous:
            # One pass: as unsigned bits, every float in [+0, 1] is <= 0x3F800000, while
            # negatives (sign bit), NaN and inf are all above it.
            if image.view(np.uint32).max() <= _ONE_BITS:
                return image
        elif image.dtype not in (np.float32, np.float64):
            raise TypeError(f"Expected image of dtype float32 or uint8 for 'image', but got {image.dtype}")
        bad = ~np.isfinite(image)
        if bad.any():
            r, c = np.argwhere(bad)[0]
            raise ValueError(
                f"Expected finite intensities in 'image', but got {image[r, c]} at (bin {r}, beam {c})"
                f" and {int(bad.sum()) - 1} more"
            )
        lo, hi = image.min(), image.max()
        if not (lo >= 0.0 and hi <= 1.0):
            raise ValueError(f"Expected intensities in [0, 1] in 'image', but got range [{lo}, {hi}]")
        np.add(image, np.float32(0.0), out=out, casting="same_kind")  # -0.0 -> +0.0, float64 -> 32
        return out

    def integrate(
        self,
        image: np.ndarray,
        T_W_S: np.ndarray,
        pose_cov: np.ndarray | None = None,
        pose_sigmas: float = 2.0,
    ) -> None:
        """Fuse one ping into the map.

        Parameters
        ----------
        image : (n_bins, n_beams) float32 in [0, 1], or uint8 (scaled by 1/255)
            Polar image: row = range bin (ascending), column = beam (ascending azimuth).
        T_W_S : (4, 4) float
            Sonar pose: maps sonar-frame points to the world frame, metres.
        pose_cov : (6, 6) float, optional
            Uncertainty of ``T_W_S`` over (translation m, rotation vector rad), a right
            perturbation ``T_W_S = T_hat @ Exp(delta)`` as :attr:`gpumap.ekf.SonarEKF.pose_cov`
            gives it. Every footprint then grows by how far a voxel may move at
            ``pose_sigmas`` standard deviations (:func:`gpumap.geometry.pose_pad_m`), at the
            field of view's far edge: the map stays conservative (a voxel's ping value covers
            every pose within the bound) at the price of wider footprints.
        pose_sigmas : float
            The bound's width in standard deviations (default 2).

        Raises ``ValueError``/``TypeError`` on bad input, leaving the map untouched.
        """
        T = check_pose(T_W_S, "T_W_S")
        pads = np.zeros(1)
        with self._lock:  # the staging buffer is the mapper's own
            img = self._check_image(image)
            if pose_cov is not None:
                pads[0] = self._pose_pad(_check_pose_cov(pose_cov), pose_sigmas)
            params, n_threads = self._ping_params(T[None], pads)
            self._backend.integrate(params[0, ...], img, self.method, int(n_threads[0]))
            if self._confirmed is not None:
                self._confirm(T, pads[0], img)
            self.n_integrated += 1  # under the lock

    def _pose_pad(self, C: np.ndarray, pose_sigmas: float) -> float:
        k = check_finite_scalar(pose_sigmas, "pose_sigmas")
        if k < 0:
            raise ValueError(f"Expected pose_sigmas >= 0, but got {k}")
        return pose_pad_m(C, self.spec.range_max_m, k)

    def _ping_params(self, Ts: np.ndarray, pads: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(B,) PING_DTYPE records and gather column counts for checked poses ``Ts`` (B, 4, 4)
        and footprint pads (B,) m, in whole-array NumPy (the work of
        :func:`gpumap.geometry.ping_params` and :func:`~gpumap.geometry.set_footprint_pad`,
        vectorised: one code path for a ping and a batch, so both give the same records)."""
        B = Ts.shape[0]
        P = np.empty(B, dtype=self._params.dtype)
        P[...] = self._params
        R = Ts[:, :3, :3]
        t = Ts[:, :3, 3]
        Rt = R.transpose(0, 2, 1)
        P["R"] = R.reshape(B, 9)
        P["t"] = t
        P["A"] = Rt.reshape(B, 9)
        # -(R^T t), each entry summed in a fixed order
        P["b"] = -(R[:, 0, :] * t[:, 0:1] + R[:, 1, :] * t[:, 1:2] + R[:, 2, :] * t[:, 2:3])
        if np.any(pads != 0.0):
            P["rho"] = self._rho0 + pads
            P["near"] = self._near0 + pads
            win = np.floor((P["rho"].astype(np.float64) + P["near"]) * P["inv_dr"].astype(np.float64)) + 2
            P["win"] = np.minimum(win, self.spec.n_bins)
        pts = self._fov_pts_S  # (m, 3): the box, padded by a voxel, holds every visible centre
        W = (pts[None, :, 0:1] * Rt[:, None, 0, :] + pts[None, :, 1:2] * Rt[:, None, 1, :]
             + pts[None, :, 2:3] * Rt[:, None, 2, :])
        s = self.grid.voxel_size_m
        lo_m = np.asarray(self.grid.min_corner_m, dtype=np.float64)
        dims = np.asarray(self.grid.shape)
        q0 = (W.min(axis=1) + t - lo_m) / s
        q1 = (W.max(axis=1) + t - lo_m) / s
        i0 = np.minimum(np.maximum(np.floor(q0).astype(np.int64) - 1, 0), dims)
        i1 = np.minimum(np.maximum(np.floor(q1).astype(np.int64) + 1, -1), dims - 1)
        n = np.maximum(i1 - i0 + 1, 0)
        P["box_lo"] = i0
        P["box_n"] = n
        n_threads = np.where(n[:, 2] > 0, n[:, 0] * n[:, 1], 0)
        return P, n_threads

    def integrate_batch(
        self,
        images: np.ndarray,
        T_W_S: np.ndarray,
        pose_cov: np.ndarray | None = None,
        pose_sigmas: float = 2.0,
    ) -> None:
        """Fuse B pings into the map: the same map, bit for bit, as B calls of :meth:`integrate`.

        Every update is a minimum or a saturating count, so the order of the pings does not
        matter and the batch is exact for both rules. GPU backends upload the whole batch at
        once and fold it in a few launches (each thread owns its voxels and walks the pings:
        no atomics); CPU backends apply the pings one after the other.

        Parameters
        ----------
        images : (B, n_bins, n_beams) uint8 (scaled by 1/255) or float32/float64 in [0, 1]
            Polar images, as :meth:`integrate` takes one.
        T_W_S : (B, 4, 4) float
            Sonar poses, metres.
        pose_cov : (6, 6) or (B, 6, 6) float, optional
            Pose uncertainty, one for every ping or one per ping (see :meth:`integrate`).
        pose_sigmas : float
            The bound's width in standard deviations (default 2).

        Every ping is checked before any is applied: on bad input it raises
        ``ValueError``/``TypeError`` saying which ping, and the map is left untouched.
        """
        imgs = self._check_images(images)
        B = imgs.shape[0]
        if isinstance(T_W_S, np.ma.MaskedArray):
            raise TypeError("Expected a plain array for 'T_W_S', but got a masked array (fill it first)")
        Ts = np.asarray(T_W_S)
        if Ts.shape != (B, 4, 4):
            raise ValueError(
                f"Expected T_W_S of shape ({B}, 4, 4) for {B} images, but got {Ts.shape}"
            )
        Ts = _check_poses(Ts)
        pads = np.zeros(B)
        if pose_cov is not None:
            C = pose_cov if isinstance(pose_cov, np.ma.MaskedArray) else np.asarray(pose_cov)
            shape = getattr(C, "shape", None)
            if shape == (B, 6, 6) and B:
                covs = [_check_pose_cov(C[b]) for b in range(B)]
                pads = np.array([self._pose_pad(c, pose_sigmas) for c in covs])
            elif shape == (6, 6):
                pads[:] = self._pose_pad(_check_pose_cov(C), pose_sigmas)
            else:
                raise ValueError(f"Expected pose_cov of shape (6, 6) or ({B}, 6, 6), but got {shape}")
        if B == 0:
            return
        with self._lock:
            if self._confirmed is not None:  # the layer follows the pings in order: one at a time
                for b in range(B):
                    params, n_threads = self._ping_params(Ts[b:b + 1], pads[b:b + 1])
                    self._backend.integrate(params[0, ...], imgs[b], self.method, int(n_threads[0]))
                    self._confirm(Ts[b], pads[b], imgs[b])
                    self.n_integrated += 1
                return
            params, n_threads = self._ping_params(Ts, pads)
            self._backend.integrate_batch(params, imgs, self.method, n_threads)
            self.n_integrated += B

    def _check_images(self, images: object) -> np.ndarray:
        """(B, n_bins, n_beams) C-contiguous uint8 or float32 in [0, 1] (converted if needed)."""
        if not isinstance(images, np.ndarray):
            raise TypeError(f"Expected a numpy array for 'images', but got {type(images).__name__}")
        if isinstance(images, np.ma.MaskedArray):
            raise TypeError(
                "Expected a plain numpy array for 'images', but got a masked array: fill it first"
            )
        if images.ndim != 3 or images.shape[1:] != self.spec.image_shape:
            raise ValueError(
                f"Expected images of shape (B, {self.spec.image_shape[0]}, {self.spec.image_shape[1]}) "
                f"(pings, n_bins, n_beams) for 'images', but got {images.shape}"
            )
        if images.dtype == np.uint8:
            return np.ascontiguousarray(images)
        if images.dtype == np.float32 and images.flags.c_contiguous:
            if images.size == 0 or images.view(np.uint32).max() <= _ONE_BITS:  # see _check_image
                return images
        elif images.dtype not in (np.float32, np.float64):
            raise TypeError(f"Expected images of dtype float32 or uint8 for 'images', but got {images.dtype}")
        bad = ~np.isfinite(images)
        if bad.any():
            b, r, c = np.argwhere(bad)[0]
            raise ValueError(
                f"Expected finite intensities in 'images', but got {images[b, r, c]} at (ping {b}, bin {r}, "
                f"beam {c}) and {int(bad.sum()) - 1} more"
            )
        lo, hi = images.min(), images.max()
        if not (lo >= 0.0 and hi <= 1.0):
            b = int(np.argmax(((images < 0) | (images > 1)).reshape(images.shape[0], -1).any(1)))
            raise ValueError(
                f"Expected intensities in [0, 1] in 'images', but got range [{lo}, {hi}] (first at ping {b})"
            )
        out = np.empty(images.shape, np.float32)
        np.add(images, np.float32(0.0), out=out, casting="same_kind")  # -0.0 -> +0.0, float64 -> 32
        return out

    def synchronize(self) -> None:
        """Wait until every ping handed to :meth:`integrate` is in the grid (GPU backends run async)."""
        sync = getattr(self._backend, "synchronize", None)
        if sync is not None:
            with self._lock:
                sync()

    # ------------------------------------------------------------------ results
    def raw_values(self) -> np.ndarray:
        """(nx, ny, nz) float32 copy of the map values with ``+inf`` for never observed."""
        with self._lock:
            g = self._backend.read()
            if self.rule == "visible":
                from gpumap.reference import visible_values

                g = visible_values(g, *self._backend.read_evidence(), self.carve_views)
        return g.reshape(self.grid.shape)

    def values(self) -> np.ndarray:
        """(nx, ny, nz) float32 copy of the grid, ``NaN`` = never observed, else in [0, 1]."""
        v = self.raw_values()
        v[np.isinf(v)] = np.nan
        return v

    @property
    def carve_views(self) -> int:
        """Visible rule: clear dark views that carve a voxel once seen bright (see the class)."""
        return self._carve_views

    @carve_views.setter
    def carve_views(self, n: int) -> None:
        self._carve_views = check_carve_views(n)

    def evidence(self) -> dict[str, np.ndarray]:
        """The visible rule's per-voxel state, (nx, ny, nz) copies: ``min_all`` float32 (min over
        every view, ``+inf`` never observed), ``bright`` float32 (min over bright views, ``+inf``
        none) and ``count`` uint8 (clear dark evidence). Raises for the plain rule."""
        if self.rule != "visible":
            raise ValueError(
                f"Expected a mapper with rule='visible' for evidence(), but its rule is {self.rule!r}"
            )
        with self._lock:
            bright, count = self._backend.read_evidence()
            min_all = self._backend.read()
        shape = self.grid.shape
        return {"min_all": min_all.reshape(shape), "bright": bright.reshape(shape),
                "count": count.reshape(shape)}

    def observed(self) -> np.ndarray:
        """(nx, ny, nz) bool: voxels seen by at least one ping."""
        return np.isfinite(self.raw_values())

    def occupied_points(self, threshold: float) -> np.ndarray:
        """(N, 3) float64 world centres (metres) of observed voxels with value >= ``threshold``."""
        v = self.raw_values()
        idx = np.argwhere(np.isfinite(v) & (v >= np.float32(threshold)))
        return self.grid.centers(idx)

    # ------------------------------------------------------------------ confidence and view gain
    def _confirm(self, T: np.ndarray, pad: float, img: np.ndarray) -> None:
        """The confidence pass of one ping, after its update (see :mod:`gpumap.confidence`)."""
        from gpumap.confidence import APERTURE_MARGIN, TUBE_VOXELS, confirm_ping
        from gpumap.geometry import beam_tan_edges

        if img.dtype == np.uint8:
            from gpumap.backends import U8_SCALE

            img = img.astype(np.float32) * U8_SCALE
        if not hasattr(self, "_conf_static"):
            sp = self.spec
            half = min(0.5 * sp.vfov_rad * (1.0 + APERTURE_MARGIN), 0.49 * np.pi)
            wide = SonarSpec(sp.range_min_m, sp.range_max_m, sp.n_bins, sp.bearings_rad, 2.0 * half)
            self._conf_static = (beam_tan_edges(sp), half, wide.fov_corners_S())
        edges, half, pts = self._conf_static
        keep = self._fov_pts_S
        self._fov_pts_S = pts  # the box that holds the rivals (the widened aperture)
        try:
            params, _ = self._ping_params(T[None], np.array([pad]))
        finally:
            self._fov_pts_S = keep
        values = self._backend.read()
        if self.rule == "visible":
            from gpumap.reference import visible_values

            values = visible_values(values, *self._backend.read_evidence(), self.carve_views)
        flat = confirm_ping(params[0], img, edges, values, half, TUBE_VOXELS * self.grid.voxel_size_m,
                            self._arcs)
        self._confirmed[flat] = 1

    def confidence(self) -> np.ndarray:
        """(nx, ny, nz) uint8 state of each voxel: 0 unknown, 1 free, 2 occupied and unconfirmed
        (only consistent with the pings: the elevation stretch lives here), 3 occupied and
        confirmed (some view resolved it in elevation; see :mod:`gpumap.confidence` for the exact
        rule). Occupied means a value ``>= threshold``; confidence never changes a value, so it
        never turns an occupied voxel free. Needs ``confidence=True``."""
        if self._confirmed is None:
            raise ValueError("Expected a mapper made with confidence=True for confidence(), but it has none")
        with self._lock:
            v = self.raw_values().ravel()
            conf = self._confirmed.copy()
        out = np.where(np.isinf(v), 0, np.where(v < np.float32(self.threshold), 1, 2)).astype(np.uint8)
        out[(out == 2) & (conf == 1)] = 3
        return out.reshape(self.grid.shape)

    def view_gain(self, T_W_S_candidates: np.ndarray, unknown_weight: float = 1.0) -> np.ndarray:
        """(K,) float64 gain of each candidate sonar pose ((K, 4, 4) float), from the map alone.

        ``gain = settle + unknown_weight * unknown``: ``settle`` counts the unconfirmed occupied
        voxels the candidate observes along an elevation arc that could settle them: both
        neighbours along the arc known free (a bright echo would confirm them, a dark clear view
        carve them), or, next to free space, an arc direction no ping has observed them along;
        ``unknown`` the never-observed voxels in blocks of 4^3 whose centre it observes (exact
        rules in :mod:`gpumap.nbv`).
        Runs on the mapper's backend; every backend gives the NumPy reference's gains exactly.
        Needs ``confidence=True``. Raises on bad poses, with the map unchanged.
        """
        from gpumap.nbv import GainRunner, _fov, gain_points, poses_to_rows

        if self._confirmed is None:
            raise ValueError("Expected a mapper made with confidence=True for view_gain(), but it has none")
        w = check_finite_scalar(unknown_weight, "unknown_weight")
        if w < 0:
            raise ValueError(f"Expected unknown_weight >= 0, but got {w}")
        if isinstance(T_W_S_candidates, np.ma.MaskedArray):
            raise TypeError("Expected a plain array for 'T_W_S_candidates', but got a masked array")
        Ts = np.asarray(T_W_S_candidates)
        if Ts.ndim != 3 or Ts.shape[1:] != (4, 4):
            raise ValueError(f"Expected T_W_S_candidates of shape (K, 4, 4), but got {Ts.shape}")
        Ts = _check_poses(Ts)
        with self._lock:
            pts = gain_points(self.raw_values(), self._confirmed.reshape(self.grid.shape) == 1,
                              self.threshold, self.grid, self._arcs)
            if self._gain_runner is None:
                self._gain_runner = GainRunner(self._backend)
            settle, unknown = self._gain_runner(poses_to_rows(Ts), pts, _fov(self._params))
        return settle.astype(np.float64) + w * unknown.astype(np.float64)

    def reset(self) -> None:
        """Forget every ping: all voxels unknown again."""
        with self._lock:
            if self._confirmed is not None:
                self._confirmed[:] = 0
                self._arcs[:] = 0
            self._backend.write(np.full(self.grid.n_voxels, np.inf, dtype=np.float32))
            if self.rule == "visible":
                self._backend.write_evidence(*_evidence_empty(self.grid.n_voxels))
            self.n_integrated = 0

    def merge(self, other) -> None:
        """Add the pings of ``other`` (a map of the same grid and options built from other pings:
        a mapper, a :class:`gpumap.merge.MapState` or a map file) to this map, in place; the result
        equals one mapper that integrated all of them, bit for bit (:mod:`gpumap.merge`)."""
        from gpumap.merge import merge_into

        merge_into(self, other)

    # ------------------------------------------------------------------ persistence
    def save(self, path: str | os.PathLike) -> Path:
        """Write the map to ``path`` (.npz), atomically: a crash leaves the old file intact.

        Lossless: ``values``, the float32 map as :meth:`raw_values` gives it (``+inf``
        unknown); for the visible rule its state (``min_all`` and ``bright`` float32,
        ``count`` uint8); with the confidence layer ``confirmed`` uint8 and ``arcs`` uint16
        (the elevation-arc directions each voxel was observed along); both specs, the method,
        rule, threshold and the ping count, under a format name and version checked by
        :meth:`load`.
        """
        path = Path(path)
        if path.suffix != ".npz":
            path = path.with_suffix(path.suffix + ".npz") if path.suffix else path.with_suffix(".npz")
        with self._lock:  # one consistent snapshot, even while other threads integrate
            # 'values' is the map as values() reads it; the visible rule adds its state
            arrays = {"values": self.raw_values()}
            if self.rule == "visible":
                ev = self.evidence()
                arrays.update(min_all=ev["min_all"], bright=ev["bright"], count=ev["count"])
            if self._confirmed is not None:
                arrays["confirmed"] = self._confirmed.reshape(self.grid.shape).copy()
                arrays["arcs"] = self._arcs.reshape(self.grid.shape).copy()
            n_integrated = self.n_integrated
        meta = {
            "format": FILE_FORMAT,
            "version": FILE_VERSION,
            "spec": self.spec.to_dict(),
            "grid": self.grid.to_dict(),
            "method": self.method,
            "shadow_m": self.shadow_m,
            "rule": self.rule,
            "threshold": self.threshold,
            "carve_views": self.carve_views,
            "n_integrated": n_integrated,
            "backend": self.backend,
            "confidence": self._confirmed is not None,
        }
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_write(path) as f:
            np.savez_compressed(f, **arrays, meta=np.array(json.dumps(meta)))
        return path

    @classmethod
    def load(cls, path: str | os.PathLike, backend: str = "auto") -> MinMaxMapper:
        """Read a map written by :meth:`save` onto ``backend``.

        Checked before anything large is read or allocated: the metadata (format, version,
        every field's type and range), each array's declared shape and dtype against the
        grid, and each member's declared size against what its compressed bytes can hold
        (deflate inflates at most ~1,000 : 1), so a small file cannot make it allocate
        gigabytes. Then the values: finite in [0, 1] or ``+inf`` (never observed), and for the
        visible rule consistent with its state. Raises :class:`~gpumap.errors.FormatError` (a
        ``ValueError``; :class:`~gpumap.errors.LimitError` when the map would not fit in
        memory) saying what was expected and what came.
        """
        path = Path(path)
        try:
            with zipfile.ZipFile(path) as zf:
                members = {i.filename: i for i in zf.infolist()}
                if "meta.npy" not in members or "values.npy" not in members:
                    raise FormatError(
                        f"Expected a gpumap map file with 'meta' and 'values', but {path} has "
                        f"{sorted(n.removesuffix('.npy') for n in members)}"
                    )
                headers = {
                    n: _npy_header(zf, info, path) for n, info in members.items() if n.endswith(".npy")
                }
                if members["meta.npy"].file_size > _META_MAX_BYTES:
                    raise FormatError(
                        f"Expected map metadata under {_META_MAX_BYTES} bytes in {path}, "
                        f"but it declares {members['meta.npy'].file_size}"
                    )
                with zf.open("meta.npy") as f:
                    meta = json.loads(str(np.lib.format.read_array(f, allow_pickle=False)))
                spec, grid, opts, n_integrated = _check_meta(meta, path)
                names = ("values", "min_all", "bright", "count") if opts["rule"] == "visible" else ("values",)
                if opts["confidence"]:
                    names = (*names, "confirmed", "arcs")
                for name in names:
                    dt = {"count": np.uint8, "confirmed": np.uint8, "arcs": np.uint16}.get(
                        name, np.float32)
                    shape, dtype = headers.get(f"{name}.npy", (None, None))
                    if shape != grid.shape or dtype != np.dtype(dt):
                        raise FormatError(
                            f"Expected '{name}' of shape {grid.shape} {np.dtype(dt)} in {path}, "
                            f"but got {'nothing' if shape is None else f'{shape} {dtype}'}"
                        )
                size = {"count": 1, "confirmed": 1, "arcs": 2}
                need = sum(int(np.prod(grid.shape)) * size.get(n, 4) for n in names)
                free = _free_memory_bytes("numpy")
                if free is not None and 2 * need > free:
                    raise LimitError(
                        f"Expected a map that fits in memory, but {path} holds {need / 2**30:.2f} GiB "
                        f"(twice that while loading) and {free / 2**30:.2f} GiB are free"
                    )
                arrays = {}
                for name in names:
                    with zf.open(f"{name}.npy") as f:
                        arrays[name] = np.lib.format.read_array(f, allow_pickle=False)
        except (OSError, EOFError, zipfile.BadZipFile, json.JSONDecodeError, UnicodeDecodeError,
                zlib.error, tokenize.TokenError, SyntaxError, NotImplementedError, struct.error) as e:
            # damaged deflate data, a damaged .npy header dict, an unknown zip compression
            raise FormatError(
                f"Expected a gpumap map file (.npz) at {path}, but it cannot be read: {e!r}"
            ) from e
        _check_map_values(arrays, opts, path)
        m = cls(spec, grid, backend=backend, **opts)
        if opts["rule"] == "visible":
            m._backend.write_evidence(arrays["bright"].ravel(), arrays["count"].ravel())
            m._backend.write(arrays["min_all"].ravel())
        else:
            m._backend.write(arrays["values"].ravel())
        if opts["confidence"]:
            m._confirmed[:] = arrays["confirmed"].ravel()
            m._arcs[:] = arrays["arcs"].ravel()
        m.n_integrated = n_integrated
        return m


# Map metadata is a small JSON document; anything larger is not one of ours.
_META_MAX_BYTES = 1 << 20
# deflate's largest expansion is about 1032 : 1; a member that claims more is a bomb.
_DEFLATE_MAX_RATIO = 1100


def _npy_header(zf: zipfile.ZipFile, info: zipfile.ZipInfo, path: Path) -> tuple[tuple, np.dtype]:
    """(shape, dtype) of one .npy member from its header, checked against its sizes."""
    with zf.open(info) as f:
        version = np.lib.format.read_magic(f)
        if version == (1, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_1_0(f)
        elif version in ((2, 0), (3, 0)):
            shape, fortran, dtype = np.lib.format.read_array_header_2_0(f)
        else:
            raise FormatError(f"Expected .npy version 1-3 for {info.filename} in {path}, but got {version}")
        header_bytes = f.tell()
    data_bytes = -1 if dtype.hasobject else int(np.prod(shape, dtype=object)) * dtype.itemsize
    if data_bytes < 0 or fortran or info.file_size != header_bytes + data_bytes:
        raise FormatError(
            f"Expected {info.filename} in {path} to hold its declared {shape} {dtype} array "
            f"({header_bytes + max(data_bytes, 0)} bytes, C order), but the archive says {info.file_size}"
        )
    bomb = info.file_size > _DEFLATE_MAX_RATIO * info.compress_size + 4096
    if info.compress_type != zipfile.ZIP_STORED and bomb:
        raise FormatError(
            f"Expected {info.filename} in {path} to inflate at most {_DEFLATE_MAX_RATIO}:1, but it declares "
            f"{info.file_size} bytes from {info.compress_size}: refused before inflating"
        )
    return tuple(shape), dtype


def _check_meta(meta: object, path: Path) -> tuple[SonarSpec, GridSpec, dict, int]:
    """The specs, the constructor options and the ping count of a map file's metadata."""
    if not isinstance(meta, dict):
        raise FormatError(f"Expected a JSON object as map metadata in {path}, but got {type(meta).__name__}")
    if meta.get("format") != FILE_FORMAT:
        raise FormatError(f"Expected format {FILE_FORMAT!r} in {path}, but got {meta.get('format')!r}")
    if meta.get("version") not in (1, 2, FILE_VERSION):
        raise FormatError(
            f"Expected file version 1, 2 or {FILE_VERSION} in {path}, but got {meta.get('version')!r}"
        )
    try:
        spec = SonarSpec.from_dict(meta["spec"])
        grid = GridSpec.from_dict(meta["grid"])
    except (KeyError, TypeError, ValueError, OverflowError) as e:
        raise FormatError(
            f"Expected a sonar spec and a grid spec in the metadata of {path}, but: {e!r}"
        ) from e
    n = meta.get("n_integrated")
    if isinstance(n, bool) or not isinstance(n, int) or n < 0:
        raise FormatError(f"Expected a non-negative integer n_integrated in {path}, but got {n!r}")
    rule = meta.get("rule", "plain")  # version 1 maps are plain min-max
    opts = {
        "method": meta.get("method"),
        "shadow_m": meta.get("shadow_m", 0.0),
        "rule": rule,
        "threshold": meta.get("threshold", 0.1),
        "carve_views": meta.get("carve_views", 2),
        "confidence": meta.get("confidence", False),  # versions 1 and 2 have no confidence layer
    }
    if opts["method"] not in METHODS or rule not in RULES:
        raise FormatError(
            f"Expected method in {METHODS} and rule in {RULES} in {path}, but got "
            f"{opts['method']!r} and {rule!r}"
        )
    if not isinstance(opts["confidence"], bool):
        raise FormatError(f"Expected a bool for confidence in {path}, but got {opts['confidence']!r}")
    for key in ("shadow_m", "threshold"):
        if isinstance(opts[key], bool) or not isinstance(opts[key], (int, float)):
            raise FormatError(f"Expected a number for {key} in {path}, but got {opts[key]!r}")
    return spec, grid, opts, n


def _check_map_values(arrays: dict[str, np.ndarray], opts: dict, path: Path) -> None:
    """Values a map can hold: finite in [0, 1] or +inf; the visible rule's state consistent."""
    for name in ("values", "min_all", "bright"):
        if name not in arrays:
            continue
        a = arrays[name]
        fin = np.isfinite(a)
        bad = ~(fin | (a == np.inf)) | (fin & ((a < 0) | (a > 1)))
        if bad.any():
            i = np.unravel_index(int(np.argmax(bad)), a.shape)
            raise FormatError(
                f"Expected '{name}' in [0, 1] or +inf (never observed) in {path}, but got {a[i]} at "
                f"{tuple(int(x) for x in i)} and {int(bad.sum()) - 1} more"
            )
    if "confirmed" in arrays and np.any(arrays["confirmed"] > 1):
        raise FormatError(f"Expected 'confirmed' flags of 0 or 1 in {path}, but some are larger")
    if "arcs" in arrays and np.any(arrays["arcs"] >= 1 << 13):
        raise FormatError(f"Expected 13-bit 'arcs' masks in {path}, but some have higher bits")
    if opts["rule"] == "visible":
        from gpumap.reference import visible_values

        unseen = np.isinf(arrays["min_all"])
        if np.any(unseen & (np.isfinite(arrays["bright"]) | (arrays["count"] > 0))):
            raise FormatError(f"Expected no evidence on never-observed voxels in {path}, but some have it")
        cv = opts["carve_views"]
        if isinstance(cv, bool) or not isinstance(cv, int) or not 1 <= cv <= 255:
            raise FormatError(f"Expected carve_views in 1..255 in {path}, but got {cv!r}")
        if not np.array_equal(visible_values(arrays["min_all"], arrays["bright"], arrays["count"], cv),
                              arrays["values"]):
            raise FormatError(f"Expected 'values' in {path} to follow from its state, but they disagree")
