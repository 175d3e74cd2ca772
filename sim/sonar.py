"""Synthetic imaging sonar: polar images rendered from meshes with pyrender.

How a ping is made (:meth:`SonarSimulator.ping`)
------------------------------------------------
1. **Sampling the field of view.** ``n_cameras`` pinhole cameras share the sonar's origin
   and split the horizontal aperture into equal azimuth sectors (130 deg -> 3 x 43.3 deg).
   Their pixels are spaced ``azimuth_step_rad`` across (default: half the narrowest beam
   cell) and ``elevation_step_rad`` up (default 0.1 deg), so each pixel is one ray. Every
   pixel's azimuth, elevation, beam, solid angle and beam-pattern weight are fixed in the
   sonar frame and computed once; a ping only renders depth and reads ranges off it.
2. **Visibility.** The depth buffer gives the first surface along each ray: occlusion and
   acoustic shadows are real. Pixels whose range falls outside ``[range_min, range_max)``
   (blanking inside ``range_min``) or whose elevation is outside ``+-vertical_extent *
   vfov/2`` are dropped (the nominal aperture is the -3 dB width; the beam pattern goes on
   falling beyond it).
3. **Surface properties.** The scene is drawn flat-shaded with each face coloured by its
   world normal (R, G = ``(n_x + 1) / 2``, ``(n_y + 1) / 2`` with the normal flipped to
   ``n_z >= 0``; only ``|n . ray|`` matters) and its material (B = reflectivity byte).
4. **Backscatter per ray** (``e`` in :meth:`ping`)::

       e = Omega_px * rho * |cos(theta_inc)|**k * B(phi) * L(r)

   ``Omega_px`` the pixel's solid angle (sr), ``rho`` and ``k`` the material's
   reflectivity and incidence exponent (:class:`~.scenes.Material`; Lambertian-like
   ``cos**k``), ``B(phi) = 0.5 ** ((phi / (vfov / 2)) ** 2)`` the two-way vertical beam
   pattern (-3 dB at the aperture's edge), ``L(r) = (r_ref / r) ** spreading_exponent *
   10 ** (-2 * absorption_db_per_m * (r - r_ref) / 10)`` the loss left after the sonar's
   time-varied gain (TVG undoes most of the two-way spreading; by default ``r**-0.5`` is
   left, on top of the ``1/r`` that the elevation sum of a surface already carries) and
   two-way absorption (0.04 dB/m: fresh tank water at 1.2 MHz), normalised to 1 at
   ``r_ref = 1 m``.
5. **Image formation.** ``E[bin, beam] = sum(e) / beam_width``: energy per radian of
   azimuth summed over elevation, which is where the elevation ambiguity comes from. Then
   multiplicative speckle ``E *= Gamma(looks, 1 / looks)`` (mean 1), a soft-saturating
   display ``I = 1 - exp(-gain * E)``, an additive Rayleigh noise floor of scale
   ``noise_floor`` and clipping to [0, 1]. Noise is seeded by ``(seed, ping index)``, so
   a ping is reproducible whatever the order pings are made in.
6. **View-to-view variation** (opt-in, ``variation=``: :class:`~.variation.SonarVariation`).
   A real sonar at its own rate images a surface differently every ping; with a variation
   the ping is rendered from ``T_W_S @ exp(jitter)`` (the arm's pose error; the ping still
   reports ``T_W_S``), its energy is scaled by a per-ping log-normal gain (median
   ``gain_offset_db``; 0 for a dropped ping) and the speckle takes the variation's ``looks``
   and K-distribution texture::

       I = 1 - exp(-gain * g_ping * E * Gamma(looks', 1 / looks') * Gamma(nu, 1 / nu))

   The gain and the jitter are AR(1) series over the ping index (:func:`~.variation.ar1_series`),
   the texture and the dropouts have their own streams: still deterministic per
   ``(seed, ping index)``. Two parts are fixed rather than drawn per ping: a surface texture
   (each ray's ``e`` times :func:`~.variation.surface_texture` of its hit point: the same patch
   of surface is dim or bright in every ping) and an extra range loss
   (``10 ** (-range_loss_db_per_m * (r - 1) / 10)`` on each range bin); both are in
   ``clean_image`` too. ``clean_image`` is the image of the mean energy at the median gain
   (``gain_offset_db``), of the pose the ping was actually taken from.
   Without a variation (or with :meth:`SonarVariation.none`) pings are bit for bit as before.

Detectable ground truth (:func:`detected_points`)
-------------------------------------------------
A visible surface point (``Ping.points_W``: one per unoccluded ray) is not necessarily
*detectable*: at grazing incidence, far away or off the beam's axis its cell may be too
faint to stand out of the noise. Each ping therefore also keeps the noise-free image
``Ping.clean_image = 1 - exp(-gain * E)`` (the same display law on the mean energy: no
speckle, no noise floor) and, for each visible point, the cell its ray fell in
(``Ping.ray_bins``, ``Ping.ray_beams``, int16). :func:`detected_points` returns the
points whose cell in ``clean_image`` reaches a threshold (``Ping.detected_W`` at
:data:`OCCUPIED_THRESHOLD`): what an ideal detector could call occupied in this ping. A
cell is shared by every ray at its range and azimuth, so a faint point beside a bright
one at the same range and beam counts as detected: that is the elevation ambiguity the
mapper lives with too. Extra memory per ping: 4 bytes per ray plus one float32 image.

Intensity scale (what "occupied" means): with the defaults, sand at 1 m and 30-40 deg
grazing images at about 0.2-0.4, metal and rock facing the sonar at 0.6-1, walls near
normal incidence saturate, and empty water (speckle-free noise floor) has mean ~0.02 and
99.9th percentile ~0.06. :data:`OCCUPIED_THRESHOLD` = 0.1 sits between the two.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np

import gpumap
from gpumap.errors import check_pose

from .scenes import Scene
from .variation import (
    STREAM_DROPOUT,
    STREAM_GAIN,
    STREAM_JITTER,
    STREAM_TEXTURE,
    SonarVariation,
    ar1_series,
    surface_texture,
)

__all__ = ["SonarSimulator", "SonarVariation", "Ping", "OCCUPIED_THRESHOLD", "detected_points"]

#: Intensity from which a voxel is called occupied (see the module docstring).
OCCUPIED_THRESHOLD = 0.1


@dataclass
class Ping:
    """One simulated ping and its ground truth.

    Attributes
    ----------
    image : (n_bins, n_beams) float32
        Polar image in [0, 1].
    T_W_S : (4, 4) float64
        True sonar pose.
    points_W : (n, 3) float32
        Visible surface points (one per unoccluded ray in the field of view), world frame.
    feature_ids : (m,) int64
        Ids of the scene features visible in this ping (in the field of view, unoccluded).
    feature_ranges_m, feature_bearings_rad : (m,) float64
        Their true range and azimuth.
    clean_image : (n_bins, n_beams) float32 or None
        Noise-free image ``1 - exp(-gain * E)`` (no speckle, no noise floor; with a variation, at
        its median gain ``gain_offset_db`` and no per-ping spread); ``None`` when
        the ping was not made by :class:`SonarSimulator`.
    ray_bins, ray_beams : (n,) int16 or None
        Cell ``(bin, beam)`` of each visible point's ray (rows of ``points_W``; int32 for
        images of 32768 bins or beams or more).
    T_W_S_actual : (4, 4) float64 or None
        The pose the ping was actually taken from when the simulator's variation jitters
        poses (``points_W`` and the features are from it); None: ``T_W_S`` itself.
    dropped : bool
        The ping lost its echoes (a variation's dropout): its image is the noise floor only.
    """

    image: np.ndarray
    T_W_S: np.ndarray
    points_W: np.ndarray
    feature_ids: np.ndarray
    feature_ranges_m: np.ndarray
    feature_bearings_rad: np.ndarray
    clean_image: np.ndarray | None = None
    ray_bins: np.ndarray | None = None
    ray_beams: np.ndarray | None = None
    T_W_S_actual: np.ndarray | None = None
    dropped: bool = False

    @property
    def detected_W(self) -> np.ndarray:
        """(k, 3) float32 visible points whose noise-free cell reaches :data:`OCCUPIED_THRESHOLD`."""
        return detected_points(self, OCCUPIED_THRESHOLD)


def detected_points(ping: Ping, threshold: float = OCCUPIED_THRESHOLD) -> np.ndarray:
    """Visible surface points of ``ping`` whose cell in the noise-free image is ``>= threshold``.

    Parameters
    ----------
    ping : Ping
        Made by :meth:`SonarSimulator.ping` (it needs ``clean_image``, ``ray_bins`` and
        ``ray_beams``).
    threshold : float
        Intensity in [0, 1] on the display scale of ``ping.image``.

    Returns
    -------
    (k, 3) float32
        Rows of ``ping.points_W``, world frame, metres.
    """
    if ping.clean_image is None or ping.ray_bins is None or ping.ray_beams is None:
        raise ValueError(
            "Expected a ping with 'clean_image', 'ray_bins' and 'ray_beams' (made by SonarSimulator.ping), "
            "but got None"
        )
    cell = ping.clean_image[ping.ray_bins.astype(np.intp), ping.ray_beams.astype(np.intp)]
    return ping.points_W[cell >= np.float32(threshold)]


class SonarSimulator:
    """Renders polar sonar images of a :class:`~.scenes.Scene` from sonar poses.

    One instance owns one offscreen GL context (created here, freed by :meth:`close`).

    Parameters
    ----------
    scene : Scene
        Meshes, materials and features (``scene.sonar_spec`` unless ``spec`` is given).
    spec : gpumap.SonarSpec, optional
    seed : int
        Seed of the speckle and noise.
    n_cameras : int
        Pinhole cameras splitting the horizontal aperture (each must stay < 120 deg).
    azimuth_step_rad, elevation_step_rad : float, optional
        Ray spacing at the image centre; defaults: half the narrowest beam cell, 0.1 deg.
    gain : float
        Display gain on the elevation-integrated backscatter (sr per radian of azimuth).
    looks : float
        Speckle looks (shape of the Gamma speckle; larger is smoother).
    noise_floor : float
        Rayleigh scale of the additive noise, intensity units.
    spreading_exponent, absorption_db_per_m : float
        Range loss left after time-varied gain (see the module docstring). 0.04 dB/m is
        fresh water at 1.2 MHz; sea water is nearer 0.3 dB/m.
    vertical_extent : float
        Rays are cast out to ``vertical_extent * vfov / 2`` in elevation: the nominal
        aperture is the beam's -3 dB width, and a real beam still hears (weaker) echoes
        beyond it (1.5: down to -6.8 dB two-way at the last ray).
    variation : SonarVariation, optional
        View-to-view variation (speckle, per-ping gain, pose jitter, dropouts; see the
        module docstring); None or :meth:`SonarVariation.none`: none, the pings as always.
    """

    def __init__(
        self,
        scene: Scene,
        spec: gpumap.SonarSpec | None = None,
        seed: int = 0,
        n_cameras: int = 3,
        azimuth_step_rad: float | None = None,
        elevation_step_rad: float | None = None,
        gain: float = 400.0,
        looks: float = 4.0,
        noise_floor: float = 0.015,
        spreading_exponent: float = 0.5,
        absorption_db_per_m: float = 0.04,
        vertical_extent: float = 1.5,
        variation: SonarVariation | None = None,
    ) -> None:
        if variation is not None and not isinstance(variation, SonarVariation):
            raise TypeError(
                f"Expected a SonarVariation or None for 'variation', but got {type(variation).__name__}")
        self.variation = variation or SonarVariation.none()
        self._series: dict[int, np.ndarray] = {}
        self.scene = scene
        self.spec = spec or scene.sonar_spec
        self.seed = int(seed)
        self.gain = float(gain)
        self.looks = float(looks)
        self.noise_floor = float(noise_floor)
        self.spreading_exponent = float(spreading_exponent)
        self.absorption_db_per_m = float(absorption_db_per_m)
        self.vertical_extent = float(vertical_extent)
        sp = self.spec
        if n_cameras < 1 or sp.hfov_rad / n_cameras >= math.radians(120):
            raise ValueError(
                f"Expected n_cameras so that each covers < 120 deg of the {math.degrees(sp.hfov_rad):.1f} "
                f"deg aperture, but got n_cameras={n_cameras}"
            )
        beam_w = np.diff(sp.beam_edges_rad)
        self._beam_width = beam_w
        d_az = float(azimuth_step_rad or 0.5 * beam_w.min())
        d_el = float(elevation_step_rad or math.radians(0.1))
        self._setup_cameras(n_cameras, d_az, d_el)
        self._cell_dtype = np.int16 if max(sp.n_bins, sp.n_beams) < 2**15 else np.int32
        self._renderer = None
        self._build_gl_scene()

    # ------------------------------------------------------------------ set-up
    def _setup_cameras(self, n: int, d_az: float, d_el: float) -> None:
        sp = self.spec
        lo, hi = sp.beam_edges_rad[0], sp.beam_edges_rad[-1]
        edges = np.linspace(lo, hi, n + 1)
        half_w = 0.5 * (hi - lo) / n + 2 * d_az
        el_max = 0.5 * sp.vfov_rad * self.vertical_extent
        half_el = el_max + 2 * d_el
        tan_w = math.tan(half_w)
        tan_h = math.tan(half_el) / math.cos(half_w)  # elevation is lowest off-axis
        fx, fy = 1.0 / d_az, 1.0 / d_el
        W = int(math.ceil(2 * tan_w * fx))
        H = int(math.ceil(2 * tan_h * fy))
        self._W, self._H, self._fx, self._fy = W, H, fx, fy
        self._cx, self._cy = 0.5 * W, 0.5 * H
        u = (np.arange(W) + 0.5 - self._cx) / fx  # right
        v = -(np.arange(H) + 0.5 - self._cy) / fy  # up (row 0 is the top)
        U, V = np.meshgrid(u, v)  # (H, W)
        self._T_S_C = []
        self._pix = []  # per camera: flat pixel indices kept
        dirs, beams, weights, scale = [], [], [], []
        for k in range(n):
            yaw = 0.5 * (edges[k] + edges[k + 1])
            fwd = np.array([math.cos(yaw), math.sin(yaw), 0.0])
            up = np.array([0.0, 0.0, 1.0])
            right = np.cross(fwd, up)
            T = np.eye(4)
            T[:3, 0], T[:3, 1], T[:3, 2] = right, up, -fwd  # OpenGL camera: x right, y up, -z fwd
            self._T_S_C.append(T)
            d = U[..., None] * right + V[..., None] * up + fwd  # depth-1 point, sonar frame
            d = d.reshape(-1, 3)
            norm = np.linalg.norm(d, axis=1)
            az = np.arctan2(d[:, 1], d[:, 0])
            el = np.arctan2(d[:, 2], np.hypot(d[:, 0], d[:, 1]))
            last = k == n - 1
            keep = (az >= edges[k]) & ((az < edges[k + 1]) | (last & (az <= edges[k + 1])))
            keep &= np.abs(el) <= el_max
            idx = np.flatnonzero(keep)
            self._pix.append(idx)
            dirs.append(d[idx] / norm[idx, None])
            beams.append(sp.beam_index(az[idx]))
            omega = 1.0 / (fx * fy * norm[idx] ** 3)  # pixel solid angle, sr
            pattern = 0.5 ** ((el[idx] / (0.5 * sp.vfov_rad)) ** 2)
            weights.append(omega * pattern / self._beam_width[beams[-1]])
            scale.append(norm[idx])
        self._dir_S = np.concatenate(dirs)  # (P, 3) unit rays
        self._beam = np.concatenate(beams).astype(np.int64)
        self._w = np.concatenate(weights)  # Omega * B(phi) / beam width
        self._range_per_depth = np.concatenate(scale)
        self._n_rays = len(self._beam)

    def _build_gl_scene(self) -> None:
        os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
        import pyrender

        self._pyrender = pyrender
        mats = self.scene.materials
        used = sorted({o.material for o in self.scene.objects})
        byte_of: dict[str, int] = {}
        taken: set[int] = set()
        for name in used:
            b = int(round(255 * mats[name].reflectivity))
            while b in taken:
                b -= 1
            taken.add(b)
            byte_of[name] = b
        # Byte -> (reflectivity, k): blended edge pixels take the nearest material's k.
        keys = np.array([byte_of[n] for n in used])
        ks = np.array([mats[n].cos_exponent for n in used])
        allb = np.arange(256)
        self._refl_lut = (allb / 255.0).astype(np.float32)
        self._k_lut = ks[np.argmin(np.abs(allb[:, None] - keys[None, :]), axis=1)].astype(np.float32)

        positions, normals, colors = [], [], []
        for o in self.scene.objects:
            m = o.mesh
            n = np.array(m.face_normals, dtype=np.float64)
            n[n[:, 2] < 0] *= -1.0
            col = np.empty((len(m.faces), 4), np.float32)
            col[:, 0] = np.round((n[:, 0] + 1) * 127.5) / 255.0
            col[:, 1] = np.round((n[:, 1] + 1) * 127.5) / 255.0
            col[:, 2] = byte_of[o.material] / 255.0
            col[:, 3] = 1.0
            positions.append(np.asarray(m.vertices)[m.faces].reshape(-1, 3))
            colors.append(np.repeat(col, 3, axis=0))
            normals.append(np.repeat(np.asarray(m.face_normals), 3, axis=0))
        # pyrender's default material (opaque, white); giving one explicitly garbles FLAT colours.
        prim = pyrender.Primitive(
            positions=np.concatenate(positions).astype(np.float32),
            normals=np.concatenate(normals).astype(np.float32),
            color_0=np.concatenate(colors),
            mode=pyrender.constants.GLTF.TRIANGLES,
        )
        self._gl_scene = pyrender.Scene(bg_color=[0.5, 0.5, 0.0, 1.0], ambient_light=[1, 1, 1])
        self._gl_scene.add(pyrender.Mesh([prim]))
        cam = pyrender.IntrinsicsCamera(
            self._fx, self._fy, self._cx, self._cy, znear=0.02, zfar=self.spec.range_max_m * 1.5
        )
        self._cam_node = self._gl_scene.add(cam, pose=np.eye(4))

    @property
    def renderer(self):
        if self._renderer is None:
            self._renderer = self._pyrender.OffscreenRenderer(self._W, self._H)
        return self._renderer

    @property
    def rays_per_ping(self) -> int:
        return self._n_rays

    def close(self) -> None:
        """Free the GL context."""
        if self._renderer is not None:
            self._renderer.delete()
            self._renderer = None

    def __enter__(self) -> SonarSimulator:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ rendering
    def _render(self, T_W_S: np.ndarray) -> tuple[list[np.ndarray], list[np.ndarray]]:
        flags = self._pyrender.RenderFlags.FLAT
        colors, depths = [], []
        for T_S_C in self._T_S_C:
            self._gl_scene.set_pose(self._cam_node, T_W_S @ T_S_C)
            c, d = self.renderer.render(self._gl_scene, flags=flags)
            colors.append(c)
            depths.append(d)
        return colors, depths

    def ping(self, T_W_S: np.ndarray, index: int = 0) -> Ping:
        """Simulate one ping from sonar pose ``T_W_S`` ((4, 4) float).

        ``index`` seeds the noise together with the simulator's seed.
        """
        T_nominal = check_pose(T_W_S, "T_W_S")
        var = self.variation
        if not var.is_none and int(index) < 0:
            raise ValueError(
                f"Expected index >= 0 with a variation (it indexes the per-ping series), but got {index}")
        T = T_nominal @ self.jitter(int(index)) if var.has_jitter else T_nominal
        sp = self.spec
        colors, depths = self._render(T)
        col = np.concatenate([c.reshape(-1, 3)[p] for c, p in zip(colors, self._pix, strict=True)])
        dep = np.concatenate([d.reshape(-1)[p] for d, p in zip(depths, self._pix, strict=True)])
        r = dep.astype(np.float64) * self._range_per_depth
        hit = (dep > 0) & (r >= sp.range_min_m) & (r < sp.range_max_m)
        bins = sp.bin_index(r[hit])
        ok = bins >= 0
        hi = np.flatnonzero(hit)[ok]
        r, bins, col = r[hi], bins[ok], col[hi]
        d_S = self._dir_S[hi]
        R = T[:3, :3]
        nx = col[:, 0].astype(np.float32) / 127.5 - 1.0
        ny = col[:, 1].astype(np.float32) / 127.5 - 1.0
        nz = np.sqrt(np.maximum(0.0, 1.0 - nx * nx - ny * ny))
        n_S = np.stack([nx, ny, nz], 1) @ R.astype(np.float32)  # world normal into sonar frame
        cos_inc = np.abs(np.einsum("ij,ij->i", n_S, d_S.astype(np.float32)))
        rho = self._refl_lut[col[:, 2]]
        k = self._k_lut[col[:, 2]]
        r_ref = 1.0
        loss = (r_ref / r) ** self.spreading_exponent * 10.0 ** (
            -2.0 * self.absorption_db_per_m * (r - r_ref) / 10.0
        )
        e = self._w[hi] * rho * cos_inc**k * loss
        points_W = T[:3, 3] + (d_S * r[:, None]) @ R.T
        if var.surface_texture_db > 0.0:
            e = e * surface_texture(points_W, self.seed, var.surface_texture_db, var.surface_texture_m)
        E = np.bincount(bins * sp.n_beams + self._beam[hi], weights=e, minlength=sp.n_bins * sp.n_beams)
        E = E.reshape(sp.n_bins, sp.n_beams)
        if var.range_loss_db_per_m != 0.0:
            r_bin = sp.range_min_m + (np.arange(sp.n_bins) + 0.5) * sp.bin_size_m
            E = E * 10.0 ** (-var.range_loss_db_per_m * (r_bin - 1.0) / 10.0)[:, None]

        E_mean = E if var.gain_offset_db == 0.0 else E * 10.0 ** (var.gain_offset_db / 10.0)
        clean = (1.0 - np.exp(-self.gain * E_mean)).astype(np.float32)

        rng = np.random.default_rng([self.seed, int(index)])
        looks = self.looks if var.looks is None else var.looks
        speckle = rng.gamma(looks, 1.0 / looks, size=E.shape)
        dropped = False
        if not var.is_none:
            E = E * self.ping_gain(int(index))
            if math.isfinite(var.texture_shape):
                nu = var.texture_shape
                tex = np.random.default_rng([self.seed, int(index), STREAM_TEXTURE])
                E = E * tex.gamma(nu, 1.0 / nu, E.shape)
            dropped = self.is_dropped(int(index))
            if dropped:
                E = np.zeros_like(E)
        img = 1.0 - np.exp(-self.gain * E * speckle)
        img += rng.rayleigh(self.noise_floor, size=E.shape)
        img = np.clip(img, 0.0, 1.0).astype(np.float32)

        points_W = points_W.astype(np.float32)
        fid, fr, fb = self._visible_features(T, depths)
        return Ping(img, T_nominal, points_W, fid, fr, fb, clean_image=clean,
                    ray_bins=bins.astype(self._cell_dtype), ray_beams=self._beam[hi].astype(self._cell_dtype),
                    T_W_S_actual=T if var.has_jitter else None, dropped=dropped)

    def _ar1(self, stream: int, index: int, dim: int, rho: float) -> np.ndarray:
        """Row ``index`` of the variation's AR(1) series ``stream`` (cached, grown in blocks)."""
        x = self._series.get(stream)
        if x is None or len(x) <= index:
            x = ar1_series(self.seed, stream, max(index + 1, 2 * (0 if x is None else len(x))), dim, rho)
            self._series[stream] = x
        return x[index]

    def ping_gain(self, index: int) -> float:
        """The variation's gain on ping ``index``'s echo energy: log-normal, median
        ``10 ** (gain_offset_db / 10)`` (1 without a variation)."""
        v = self.variation
        if v.gain_sigma_db == 0.0:
            return 10.0 ** (v.gain_offset_db / 10.0)
        x = float(self._ar1(STREAM_GAIN, index, 1, v.gain_correlation)[0])
        return 10.0 ** ((v.gain_offset_db + v.gain_sigma_db * x) / 10.0)

    def is_dropped(self, index: int) -> bool:
        """Whether ping ``index`` loses its echoes (probability ``variation.dropout_prob``)."""
        p = self.variation.dropout_prob
        return p > 0.0 and bool(np.random.default_rng([self.seed, int(index), STREAM_DROPOUT]).random() < p)

    def jitter(self, index: int) -> np.ndarray:
        """(4, 4) float64 pose error of ping ``index`` in the sonar frame: the ping is taken from
        ``T_W_S @ jitter(index)`` (rotation ``exp`` of a vector of ``jitter_rotation_rad`` per axis,
        translation ``jitter_translation_m`` per axis; identity without jitter)."""
        v = self.variation
        out = np.eye(4)
        if not v.has_jitter:
            return out
        x = self._ar1(STREAM_JITTER, index, 6, v.jitter_correlation)
        from gpumap.lie import so3_exp

        out[:3, :3] = so3_exp(x[:3] * v.jitter_rotation_rad)
        out[:3, 3] = x[3:] * v.jitter_translation_m
        return out

    def _visible_features(
        self, T_W_S: np.ndarray, depths: list[np.ndarray], tol_m: float = 0.02
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        sc = self.scene
        if len(sc.features_W) == 0:
            return np.zeros(0, np.int64), np.zeros(0), np.zeros(0)
        p_S = (sc.features_W - T_W_S[:3, 3]) @ T_W_S[:3, :3]
        pol = self.spec.to_polar(p_S)
        vis = self.spec.in_fov(p_S)
        n = len(self._T_S_C)
        lo, hi = self.spec.beam_edges_rad[0], self.spec.beam_edges_rad[-1]
        cam = np.clip(np.floor((pol[:, 1] - lo) / (hi - lo) * n).astype(int), 0, n - 1)
        for i in np.flatnonzero(vis):
            T_S_C = self._T_S_C[cam[i]]
            q = T_S_C[:3, :3].T @ (p_S[i] - T_S_C[:3, 3])
            z = -q[2]
            u = int(np.floor(self._fx * q[0] / z + self._cx))
            v = int(np.floor(self._cy - self._fy * q[1] / z))
            D = depths[cam[i]]
            win = D[max(v - 1, 0) : v + 2, max(u - 1, 0) : u + 2]
            if win.size == 0:
                vis[i] = False
                continue
            # Depth of anything in front along the neighbouring rays; 0 means no surface.
            front = np.where(win > 0, win, np.inf).max()
            vis[i] = front >= z - tol_m
        idx = np.flatnonzero(vis)
        return sc.feature_ids[idx], pol[idx, 0], pol[idx, 1]
