"""Integration: a ping's record for the kernels, the blocks it may observe, and the launches that
fold it into a map's blocks (:class:`Integrator`), with the checks of its inputs at the boundary.

Per ping the host builds a :data:`gpumap.geometry.PING_DTYPE` record (pose, field of view, the
box of voxels it may see, footprint pads) in whole-array NumPy, one code path for a ping and a
batch and for every storage, so all give the same records. On demand it then finds, vectorised
over the (i, j) *block columns* of the ping's box, the z-range of blocks that the field of view
can reach (the kernels' ``column_range`` bound, widened to a block column's footprint and padded
against float32 rounding, so it is conservative), and has the storage give them slots
(:meth:`gpumap.core.storage.BlockStorage.allocate`). The kernels flag any observed voxel that found no
block (:meth:`gpumap.core.storage.BlockStorage.check`): the tests check it never happens.
"""

from __future__ import annotations

import math

import numpy as np

from gpumap.core.storage import BlockStorage
from gpumap.errors import check_finite_scalar, check_pose
from gpumap.geometry import pose_pad_m, static_params
from gpumap.spec import _MAX_VOXEL_INDEX, GridSpec, SonarSpec

__all__ = ["METHODS", "Integrator", "check_pose_cov", "check_poses"]

METHODS = ("gather", "template")
_ONE_BITS = np.uint32(0x3F800000)  # the bits of float32 1.0
_CANDIDATE_GROUP = 8  # pings per vectorised block test


def check_pose_cov(pose_cov: object) -> np.ndarray:
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


def check_poses(Ts: np.ndarray) -> np.ndarray:
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


class Integrator:
    """Applies pings to one :class:`~gpumap.core.storage.BlockStorage` with one method and rule.

    Parameters
    ----------
    spec : SonarSpec
        The sonar's geometry.
    storage : BlockStorage
        The blocks the pings go into (their backend runs the kernels).
    method : str
        ``"gather"`` or ``"template"`` (see :class:`gpumap.MinMaxMapper`).
    template : (n, 3) float or None
        The template method's voxel template (:func:`gpumap.geometry.make_template_S`).
    shadow_m, rule, threshold
        The static parameters of every ping (:func:`gpumap.geometry.static_params`).
    """

    def __init__(self, spec: SonarSpec, storage: BlockStorage, method: str, template: np.ndarray | None,
                 shadow_m: float, rule: str, threshold: float) -> None:
        self.spec, self.storage, self.method, self.template = spec, storage, method, template
        if storage.sparse is None:
            pgrid = storage.grid
        else:  # voxel indices count from the SparseSpec's origin: a grid of one block there
            o, s = storage.sparse.origin, storage.sparse.voxel_size_m
            pgrid = GridSpec(o, tuple(x + storage.B * s for x in o), s)
        self.params = static_params(spec, pgrid, shadow_m, rule, threshold)
        self._rho0, self._near0 = float(self.params["rho"]), float(self.params["near"])
        self.fov_pts_S = spec.fov_corners_S()
        if template is not None:
            self.params["n_points"] = template.shape[0]
        self._staging = np.empty(spec.image_shape, dtype=np.float32)
        self._P_rows = self.params[None].copy()  # the static record, repeated (ping_params)

    # ------------------------------------------------------------------ inputs
    def check_image(self, image: object) -> np.ndarray:
        """The image as C-contiguous uint8 (backends scale it by 1/255, GPUs after the upload)
        or float32 in [0, 1]: ``image`` itself when it already is, else a conversion in the
        integrator's staging buffer (hold the storage's lock). Raises on anything else."""
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

    def check_images(self, images: object) -> np.ndarray:
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
            if images.size == 0 or images.view(np.uint32).max() <= _ONE_BITS:  # see check_image
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

    def check_batch(self, images: object, T_W_S: object, pose_cov: object, pose_sigmas: float
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """A batch's checked images (:meth:`check_images`), poses (B, 4, 4) float64 and
        footprint pads (B,) m (from ``pose_cov``: (6, 6) for every ping or (B, 6, 6))."""
        imgs = self.check_images(images)
        B = imgs.shape[0]
        if isinstance(T_W_S, np.ma.MaskedArray):
            raise TypeError("Expected a plain array for 'T_W_S', but got a masked array (fill it first)")
        Ts = np.asarray(T_W_S)
        if Ts.shape != (B, 4, 4):
            raise ValueError(
                f"Expected T_W_S of shape ({B}, 4, 4) for {B} images, but got {Ts.shape}"
            )
        Ts = check_poses(Ts)
        pads = np.zeros(B)
        if pose_cov is not None:
            C = pose_cov if isinstance(pose_cov, np.ma.MaskedArray) else np.asarray(pose_cov)
            shape = getattr(C, "shape", None)
            if shape == (B, 6, 6) and B:
                covs = [check_pose_cov(C[b]) for b in range(B)]
                pads = np.array([self.pose_pad(c, pose_sigmas) for c in covs])
            elif shape == (6, 6):
                pads[:] = self.pose_pad(check_pose_cov(C), pose_sigmas)
            else:
                raise ValueError(f"Expected pose_cov of shape (6, 6) or ({B}, 6, 6), but got {shape}")
        return imgs, Ts, pads

    def pose_pad(self, C: np.ndarray, pose_sigmas: float) -> float:
        """The footprint pad, m, of a checked pose covariance ``C`` at ``pose_sigmas``
        (:func:`gpumap.geometry.pose_pad_m`)."""
        k = check_finite_scalar(pose_sigmas, "pose_sigmas")
        if k < 0:
            raise ValueError(f"Expected pose_sigmas >= 0, but got {k}")
        return pose_pad_m(C, self.spec.range_max_m, k)

    # ------------------------------------------------------------------ pings
    def integrate(self, img: np.ndarray, T: np.ndarray, pads: np.ndarray) -> np.ndarray:
        """Fold one checked ping (image, pose (4, 4), pad (1,) m) into the storage (hold its lock);
        returns its (1,) PING_DTYPE record (the confidence pass reuses it)."""
        params, n_threads = self.ping_params(T[None], pads)
        self.prepare(params, T[None], n_threads)
        self.storage.empty = False
        self.storage.backend.integrate(params[0, ...], img, self.method, int(n_threads[0]))
        return params

    def integrate_batch(self, imgs: np.ndarray, Ts: np.ndarray, pads: np.ndarray) -> None:
        """Fold B checked pings into the storage, the blocks of all of them allocated first (hold
        its lock)."""
        params, n_threads = self.ping_params(Ts, pads)
        self.prepare(params, Ts, n_threads)
        self.storage.empty = False
        self.storage.backend.integrate_batch(params, imgs, self.method, n_threads)

    def ping_params(self, Ts: np.ndarray, pads: np.ndarray, fov_pts: np.ndarray | None = None
                    ) -> tuple[np.ndarray, np.ndarray]:
        """(B,) PING_DTYPE records and gather column counts for checked poses ``Ts`` (B, 4, 4)
        and footprint pads (B,) m, in whole-array NumPy (the work of
        :func:`gpumap.geometry.ping_params` and :func:`~gpumap.geometry.set_footprint_pad`,
        vectorised: one code path for a ping and a batch, and for every storage, so all give
        the same records). ``fov_pts`` ((m, 3), default the field of view's corners): the points
        whose box, padded by a voxel, bounds the voxels. An unbounded map's boxes are not
        clipped; a pose whose box would leave int32 voxel indices raises ``ValueError``."""
        B = Ts.shape[0]
        # rows of the static record, copied (a broadcast of a record is slow); remade if it changed
        if self._P_rows.shape[0] < B or self._P_rows[:1].tobytes() != self.params.tobytes():
            self._P_rows = np.repeat(self.params[None], max(B, 2 * self._P_rows.shape[0]))
        P = self._P_rows[:B].copy()
        R = Ts[:, :3, :3]
        t = Ts[:, :3, 3]
        Rt = R.transpose(0, 2, 1)
        P["R"] = R.reshape(B, 9)
        P["t"] = t
        P["A"] = Rt.reshape(B, 9)
        # -(R^T t), each entry summed in a fixed order
        P["b"] = -(R[:, 0, :] * t[:, 0:1] + R[:, 1, :] * t[:, 1:2] + R[:, 2, :] * t[:, 2:3])
        if pads.any():
            P["rho"] = self._rho0 + pads
            P["near"] = self._near0 + pads
            win = np.floor((P["rho"].astype(np.float64) + P["near"]) * P["inv_dr"].astype(np.float64)) + 2
            P["win"] = np.minimum(win, self.spec.n_bins)
        # the box of the points, padded by a voxel, holds every visible centre
        pts = self.fov_pts_S if fov_pts is None else fov_pts
        # (B, 3, m): axis e of every point in the world's orientation, summed over k in order
        W = (Rt[:, 0, :, None] * pts[None, None, :, 0] + Rt[:, 1, :, None] * pts[None, None, :, 1]
             + Rt[:, 2, :, None] * pts[None, None, :, 2])
        st = self.storage
        s = st.voxel
        q0 = (W.min(axis=2) + t - st.origin) / s
        q1 = (W.max(axis=2) + t - st.origin) / s
        dims = st.dims
        if dims is None:
            far = np.maximum(np.abs(q0).max(axis=1), np.abs(q1).max(axis=1)) > _MAX_VOXEL_INDEX - 2 * st.B
            if far.any():
                k = int(np.argmax(far))
                raise ValueError(
                    f"Expected a sonar pose within {(_MAX_VOXEL_INDEX - 2 * st.B) * s:.4g} m of the map "
                    f"origin {tuple(st.origin)} (voxel indices fit in int32), but T_W_S[{k}] puts it at "
                    f"{t[k].tolist()}"
                )
            i0 = np.floor(q0).astype(np.int64) - 1
            i1 = np.floor(q1).astype(np.int64) + 1
        else:
            i0 = np.minimum(np.maximum(np.floor(q0).astype(np.int64) - 1, 0), dims)
            i1 = np.minimum(np.maximum(np.floor(q1).astype(np.int64) + 1, -1), dims - 1)
        n = np.maximum(i1 - i0 + 1, 0)
        P["box_lo"] = i0
        P["box_n"] = n
        n_threads = np.where(n[:, 2] > 0, n[:, 0] * n[:, 1], 0)
        return P, n_threads

    # ------------------------------------------------------------------ blocks on demand
    def prepare(self, params: np.ndarray, Ts: np.ndarray, n_threads: np.ndarray) -> None:
        """On demand: give every block the pings (records ``params``, poses ``Ts``) may observe a
        voxel of a slot, before any of them is applied (raises with the map unchanged)."""
        st = self.storage
        if st.sparse is None:
            return
        live = n_threads > 0
        if not live.any():
            return
        lo = params["box_lo"][live].astype(np.int64)
        hi = lo + params["box_n"][live].astype(np.int64) - 1
        if st.dims is None:  # the kernels read the index over the whole box
            st.ensure_index(lo.min(axis=0) // st.B, hi.max(axis=0) // st.B)
        Tl = Ts[live]
        # the block test runs on the union box of a group of pings: small groups keep far-apart
        # pings from making it walk empty columns
        g = _CANDIDATE_GROUP
        lins = [self.candidate_lins(lo[i : i + g], hi[i : i + g], Tl[i : i + g])
                for i in range(0, len(Tl), g)]
        st.allocate(np.concatenate(lins), Tl[-1, :3, 3])

    def candidate_lins(self, lo: np.ndarray, hi: np.ndarray, Ts: np.ndarray) -> np.ndarray:
        """Index entries (int64, into the flattened coarse index; repeats across pings) of the
        blocks that may hold a voxel centre one of the pings observes: per block column of a
        ping's voxel box (``lo``..``hi``, (P, 3) each), the z-range that its field of view's
        range sphere, azimuth half-planes, elevation slab and ``x > 0`` allow anywhere in the
        column (float64, padded against float32 rounding), as blocks. Vectorised over the P
        pings on the block columns of their union box. The index must cover every box."""
        st = self.storage
        B, s = st.B, st.voxel
        o = st.origin
        b0, b1 = lo // B, hi // B  # (P, 3)
        bx = np.arange(b0[:, 0].min(), b1[:, 0].max() + 1)
        by = np.arange(b0[:, 1].min(), b1[:, 1].max() + 1)
        cx = (o[0] + (bx + 0.5) * (B * s))[None, :, None]  # (1, nx, 1)
        cy = (o[1] + (by + 0.5) * (B * s))[None, None, :]  # (1, 1, ny)
        t = Ts[:, :3, 3]  # (P, 3)
        A = np.transpose(Ts[:, :3, :3], (0, 2, 1))  # rotation of T_S_W
        bb = -np.einsum("pij,pj->pi", A, t)
        rmax = self.spec.range_max_m
        pad = 1e-4 * (1.0 + rmax + np.abs(t).max(axis=1)) + 0.01 * s  # (P,)
        hd = B * s / math.sqrt(2.0) + pad  # the column's voxel centres lie within hd of (cx, cy)
        t3 = t[:, :, None, None]
        dmin = np.maximum(np.hypot(cx - t3[:, 0], cy - t3[:, 1]) - hd[:, None, None], 0.0)
        q = ((rmax + pad) ** 2)[:, None, None] - dmin * dmin
        ok = q > 0
        w = np.sqrt(np.maximum(q, 0.0))
        z0, z1 = t3[:, 2] - w, t3[:, 2] + w
        wd = self.params["wedge"].astype(np.float64)
        slab = float(self.params["slab"])
        # g . w + g0 >= 0 for some w in the column at height z: alpha(column) + beta z >= 0
        G = np.stack(
            [
                wd[0] * A[:, 0] + wd[1] * A[:, 1],
                wd[2] * A[:, 0] + wd[3] * A[:, 1],
                -A[:, 2],
                A[:, 2],
                A[:, 0],
            ],
            axis=1,
        )  # (P, 5, 3)
        g0 = np.stack(
            [
                wd[0] * bb[:, 0] + wd[1] * bb[:, 1],
                wd[2] * bb[:, 0] + wd[3] * bb[:, 1],
                slab - bb[:, 2],
                slab + bb[:, 2],
                bb[:, 0],
            ],
            axis=1,
        )  # (P, 5)
        base = g0 + hd[:, None] * np.hypot(G[..., 0], G[..., 1]) + pad[:, None]
        alpha = (
            base[..., None, None] + G[..., 0, None, None] * cx[:, None] + G[..., 1, None, None] * cy[:, None]
        )
        beta = G[..., 2]  # (P, 5)
        up, down = beta > 1e-12, beta < -1e-12
        level = ~(up | down)
        zc = -alpha / np.where(level, 1.0, beta)[..., None, None]
        z0 = np.maximum(z0, np.where(up[..., None, None], zc, -np.inf).max(axis=1))
        z1 = np.minimum(z1, np.where(down[..., None, None], zc, np.inf).min(axis=1))
        if level.any():
            ok &= np.where(level[..., None, None], alpha >= 0, True).all(axis=1)
        # the ping's own box: columns outside it and voxels above or below it hold nothing
        ok &= ((bx[None, :] >= b0[:, 0, None]) & (bx[None, :] <= b1[:, 0, None]))[:, :, None]
        ok &= ((by[None, :] >= b0[:, 1, None]) & (by[None, :] <= b1[:, 1, None]))[:, None, :]
        k0 = np.maximum(np.floor((z0 - o[2]) / s - 0.5).astype(np.int64) - 1, lo[:, 2, None, None])
        k1 = np.minimum(np.ceil((z1 - o[2]) / s - 0.5).astype(np.int64) + 1, hi[:, 2, None, None])
        ok &= k0 <= k1
        bz0 = k0 // B
        n = np.where(ok, k1 // B - bz0 + 1, 0).ravel()
        nb = st.index.shape
        lb = st.lo_b
        col = (
            (((bx - lb[0])[:, None] * nb[1] + (by - lb[1])[None, :]) * nb[2])[None] + (bz0 - lb[2])
        ).ravel()
        return np.repeat(col - (np.cumsum(n) - n), n) + np.arange(int(n.sum()))
