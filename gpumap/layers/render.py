"""Rendering sonar pings from a voxel field, with gradients (issue 19).

:class:`PingModel` states the physics (opacity, incidence law, range loss, vertical beam pattern
with its side-lobe level); :class:`PingRenderer` owns the rays of one sonar on one grid and
launches the Warp kernels of :mod:`gpumap.kernels.render` (CPU or CUDA). The NumPy twin of the
forward pass is :mod:`gpumap.layers.render_reference`.

The field: per voxel an occupancy ``o`` in [0, 1] (trilinear between voxel centres, 0 outside
the grid) and a reflectivity ``rho``. A ray of azimuth ``theta`` and elevation ``phi`` stops in
range sample ``s`` with probability ``T_s alpha_s`` (``alpha_s = 1 - exp(-kappa o ds / h)``: a
one-voxel layer of ``o = 1`` stops ``1 - exp(-kappa)`` of what reaches it, whatever the sample
step), where it returns ``w(phi) L(r) rho (cos_inc^2 + 1e-4)^(k/2)`` with the incidence taken from
the field's gradient. A beam sums its elevation rays; the image is
``floor + (1 - floor) (1 - exp(-gain E))`` (the simulator's display law plus a noise floor).

Resolution. The renderer works on a coarser polar image than the sonar's: ``bin_stride`` range
bins and ``beam_stride`` beams to a cell (defaults: about half a voxel each at mid range), one
range sample per coarse bin and one azimuth ray per coarse beam (the mean bearing of its beams);
:meth:`PingRenderer.coarsen` averages measured images onto the same cells. Elevation rays are
spaced ``elevation_step_rad`` (default: one voxel at the maximum range) out to
``vertical_extent * vfov / 2``.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from gpumap.errors import BackendUnavailableError
from gpumap.spec import GridSpec, SonarSpec

__all__ = ["PingModel", "PingRenderer", "beam_pattern"]


@dataclass(frozen=True)
class PingModel:
    """The forward model's stated parameters (the same on every scene).

    Attributes
    ----------
    kappa : float
        Optical depth of a one-voxel layer of occupancy 1 (4: it stops 98 % of the sound).
    cos_exponent : float
        ``k`` of the incidence law ``|cos(theta_inc)|**k``.
    spreading_exponent, absorption_db_per_m : float
        Range loss left after time-varied gain, ``r**-n * 10**(-2 a (r - 1) / 10)`` (1 at 1 m).
    vertical_extent : float
        Elevation rays reach ``vertical_extent * vfov / 2`` (the -3 dB aperture is 1).
    side_lobe_level : float
        Two-way side-lobe floor of the vertical beam pattern, linear (0.01 = -20 dB), added to
        the main lobe ``0.5 ** ((2 phi / vfov) ** 2)`` out to the vertical extent.
    """

    kappa: float = 4.0
    cos_exponent: float = 1.0
    spreading_exponent: float = 0.5
    absorption_db_per_m: float = 0.04
    vertical_extent: float = 1.5
    side_lobe_level: float = 0.01

    def to_dict(self) -> dict:
        return asdict(self)


def beam_pattern(phi_rad: np.ndarray, vfov_rad: float, side_lobe_level: float) -> np.ndarray:
    """Two-way vertical beam pattern at elevations ``phi_rad``: main lobe (-3 dB at +-vfov/2)
    plus the side-lobe floor (linear power)."""
    phi = np.asarray(phi_rad, np.float64)
    return 0.5 ** ((2.0 * phi / vfov_rad) ** 2) + side_lobe_level


def _init_warp(device: str):
    from gpumap.backends import _warp

    wp, _ = _warp()
    from gpumap.kernels import render as kr

    if device not in ("cpu", "cuda", "auto") and not device.startswith("cuda:"):
        raise ValueError(f"Expected device 'auto', 'cpu', 'cuda' or 'cuda:N', but got {device!r}")
    if device == "auto":
        device = "cuda:0" if wp.is_cuda_available() else "cpu"
    elif device.startswith("cuda") and not wp.is_cuda_available():
        raise BackendUnavailableError(f"Expected a CUDA device for device={device!r}, but Warp finds none")
    return wp, kr, device


class PingRenderer:
    """Renders coarse polar images of a voxel field seen by one sonar, with gradients.

    Parameters
    ----------
    spec : SonarSpec
    grid : GridSpec
        The field's grid (the mapper's).
    model : PingModel
    bin_stride, beam_stride : int, optional
        Sonar bins / beams per rendered cell (defaults: half a voxel at mid range, at least 1).
    elevation_step_rad : float, optional
        Elevation ray spacing (default: one voxel at ``range_max_m``).
    device : str
        ``"auto"`` (CUDA if Warp finds it, else CPU; kept in :attr:`device`), ``"cpu"``,
        ``"cuda"`` or ``"cuda:N"``. A named device never falls back.
    """

    def __init__(
        self,
        spec: SonarSpec,
        grid: GridSpec,
        model: PingModel | None = None,
        bin_stride: int | None = None,
        beam_stride: int | None = None,
        elevation_step_rad: float | None = None,
        device: str = "auto",
    ) -> None:
        if not isinstance(spec, SonarSpec):
            raise TypeError(f"Expected a gpumap.SonarSpec for 'spec', but got {type(spec).__name__}")
        if not isinstance(grid, GridSpec):
            raise TypeError(f"Expected a gpumap.GridSpec for 'grid', but got {type(grid).__name__}")
        self.spec, self.grid = spec, grid
        self.model = model or PingModel()
        h = grid.voxel_size_m
        r_mid = 0.5 * (spec.range_min_m + spec.range_max_m)
        d_theta = spec.hfov_rad / spec.n_beams
        self.bin_stride = int(bin_stride or max(1, math.floor(0.5 * h / spec.bin_size_m)))
        self.beam_stride = int(beam_stride or max(1, math.floor(0.5 * h / (r_mid * d_theta))))
        for name, v, n in (("bin_stride", self.bin_stride, spec.n_bins), ("beam_stride", self.beam_stride,
                                                                          spec.n_beams)):
            if not 1 <= v <= n:
                raise ValueError(f"Expected {name} in 1..{n}, but got {v}")
        self.elevation_step_rad = float(elevation_step_rad or h / spec.range_max_m)
        if not 0 < self.elevation_step_rad < spec.vfov_rad:
            raise ValueError(f"Expected 0 < elevation_step_rad < vfov, but got {self.elevation_step_rad}")
        self.n_range = spec.n_bins // self.bin_stride
        self.n_beam_cells = spec.n_beams // self.beam_stride
        self.step_m = spec.bin_size_m * self.bin_stride
        self._build_rays()
        self._wp, self._kr, self.device = _init_warp(device)
        wp = self._wp
        self._dir = wp.array(self.ray_dir_S.astype(np.float32), dtype=wp.vec3, device=self.device)
        self._w = wp.array(self.ray_weight.astype(np.float32), dtype=wp.float32, device=self.device)
        self._beam = wp.array(self.ray_beam.astype(np.int32), dtype=wp.int32, device=self.device)

    # ------------------------------------------------------------------ geometry
    def _build_rays(self) -> None:
        sp, m = self.spec, self.model
        g = self.beam_stride
        theta = sp.bearings_rad[: self.n_beam_cells * g].reshape(self.n_beam_cells, g).mean(1)
        half = m.vertical_extent * 0.5 * sp.vfov_rad
        n_el = max(1, int(math.ceil(2 * half / self.elevation_step_rad)))
        d_phi = 2 * half / n_el
        phi = -half + d_phi * (np.arange(n_el) + 0.5)
        T, P = np.meshgrid(theta, phi, indexing="ij")  # (beam cells, elevations)
        d = np.stack([np.cos(P) * np.cos(T), np.cos(P) * np.sin(T), np.sin(P)], -1)
        self.ray_dir_S = d.reshape(-1, 3)
        w = np.cos(P) * d_phi * beam_pattern(P, sp.vfov_rad, m.side_lobe_level) / self.bin_stride
        self.ray_weight = w.reshape(-1)
        self.ray_beam = np.repeat(np.arange(self.n_beam_cells), n_el)
        self.n_elevations = n_el

    @property
    def n_rays(self) -> int:
        return int(self.ray_beam.shape[0])

    @property
    def image_shape(self) -> tuple[int, int]:
        """``(n_range, n_beam_cells)``: the shape of a rendered (coarse) image."""
        return (self.n_range, self.n_beam_cells)

    def coarsen(self, images: np.ndarray) -> np.ndarray:
        """Average sonar images ``(B, n_bins, n_beams)`` (float in [0, 1] or uint8) onto the
        rendered cells: ``(B, n_range, n_beam_cells)`` float32."""
        a = np.asarray(images)
        if a.ndim == 2:
            a = a[None]
        if a.ndim != 3 or a.shape[1:] != self.spec.image_shape:
            raise ValueError(
                f"Expected images of shape (B, {self.spec.n_bins}, {self.spec.n_beams}), but got {a.shape}"
            )
        x = a.astype(np.float32) / np.float32(255.0) if a.dtype == np.uint8 else a.astype(np.float32)
        nr, nb, s, g = self.n_range, self.n_beam_cells, self.bin_stride, self.beam_stride
        x = x[:, : nr * s, : nb * g].reshape(len(x), nr, s, nb, g)
        return x.mean(axis=(2, 4)).astype(np.float32)

    def _check_field(self, a: np.ndarray, name: str) -> np.ndarray:
        a = np.asarray(a)
        if a.shape != self.grid.shape or a.dtype.kind != "f":
            raise ValueError(f"Expected {name} of shape {self.grid.shape} float, but got {a.dtype} {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"Expected finite values in {name!r}, but got NaN or inf")
        return np.ascontiguousarray(a, dtype=np.float32)

    @staticmethod
    def _check_poses(poses: np.ndarray) -> np.ndarray:
        from gpumap.errors import check_pose

        P = np.asarray(poses, dtype=np.float64)
        if P.ndim == 2:
            P = P[None]
        if P.ndim != 3 or P.shape[1:] != (4, 4):
            raise ValueError(f"Expected poses of shape (B, 4, 4), but got {P.shape}")
        return np.stack([check_pose(T, f"poses[{i}]") for i, T in enumerate(P)]) if len(P) else P

    # ------------------------------------------------------------------ launches
    def _pose_arrays(self, P: np.ndarray):
        wp = self._wp
        R = wp.array(P[:, :3, :3].astype(np.float32), dtype=wp.mat33, device=self.device)
        t = wp.array(P[:, :3, 3].astype(np.float32), dtype=wp.vec3, device=self.device)
        return R, t

    def _launch_forward(self, occ, refl, R, t, B: int, grad: bool, tape=None):
        """alpha, emit, trans, energy arrays of a batch of B pings (energy (B, n_range, n_beam_cells)).

        With ``tape``, :func:`sample_field` is recorded on it and :func:`composite`'s hand-written
        adjoint after it (the tape replays in reverse: the adjoint fills alpha's and emit's
        gradients, then sample_field's adjoint carries them to ``occ`` and ``refl``)."""
        wp, kr, dev, m = self._wp, self._kr, self.device, self.model
        shape = (B, self.n_rays, self.n_range)
        alpha = wp.zeros(shape, dtype=wp.float32, device=dev, requires_grad=grad)
        emit = wp.zeros(shape, dtype=wp.float32, device=dev, requires_grad=grad)
        trans = wp.zeros(shape, dtype=wp.float32, device=dev)
        energy = wp.zeros((B, self.n_range, self.n_beam_cells), dtype=wp.float32, device=dev,
                          requires_grad=grad)
        g = self.grid
        inputs = [occ, refl, wp.vec3(*map(float, g.min_corner_m)), float(1.0 / g.voxel_size_m), R, t,
                  self._dir, self._w, float(self.spec.range_min_m), float(self.step_m), float(m.kappa),
                  float(m.cos_exponent), float(m.spreading_exponent), float(m.absorption_db_per_m)]
        if tape is not None:
            with tape:
                wp.launch(kr.sample_field, dim=shape, device=dev, inputs=inputs, outputs=[alpha, emit])
        else:
            wp.launch(kr.sample_field, dim=shape, device=dev, inputs=inputs, outputs=[alpha, emit])
        wp.launch(kr.composite, dim=(B, self.n_rays), device=dev, inputs=[alpha, emit, self._beam],
                  outputs=[trans, energy])
        if tape is not None:
            def backward():
                wp.launch(kr.composite_adjoint, dim=(B, self.n_rays), device=dev,
                          inputs=[alpha, emit, self._beam, trans, energy.grad],
                          outputs=[alpha.grad, emit.grad])

            tape.record_func(backward, [alpha, emit, energy])
        return alpha, emit, trans, energy

    def record_energy(self, tape, occ, refl, R, t, B: int):
        """Forward pass of a batch of ``B`` poses (Warp ``R`` mat33, ``t`` vec3 arrays) recorded on
        ``tape``; ``occ`` and ``refl`` are Warp (nx, ny, nz) arrays with gradients. Returns
        ``energy`` (B, n_range, n_beam_cells), whose gradient flows back to ``occ`` and ``refl``."""
        return self._launch_forward(occ, refl, R, t, B, grad=True, tape=tape)[3]

    def energy(self, occupancy: np.ndarray, reflectivity: np.ndarray, poses: np.ndarray,
               batch: int = 16) -> np.ndarray:
        """Elevation-summed energy ``E`` of each pose: ``(B, n_range, n_beam_cells)`` float32.

        ``occupancy``, ``reflectivity``: (nx, ny, nz) float, finite; ``poses``: (B, 4, 4) T_W_S.
        """
        wp = self._wp
        occ = wp.array(self._check_field(occupancy, "occupancy"), dtype=wp.float32, device=self.device)
        refl = wp.array(self._check_field(reflectivity, "reflectivity"), dtype=wp.float32, device=self.device)
        P = self._check_poses(poses)
        out = np.empty((len(P), self.n_range, self.n_beam_cells), np.float32)
        for b0 in range(0, len(P), batch):
            R, t = self._pose_arrays(P[b0 : b0 + batch])
            _, _, _, e = self._launch_forward(occ, refl, R, t, len(R), grad=False)
            out[b0 : b0 + len(R)] = e.numpy()
        return out

    def render(self, occupancy: np.ndarray, reflectivity: np.ndarray, poses: np.ndarray,
               gain: float, floor: float = 0.0, batch: int = 16) -> np.ndarray:
        """Rendered images ``floor + (1 - floor)(1 - exp(-gain E))``, (B, n_range, n_beam_cells) float32."""
        E = self.energy(occupancy, reflectivity, poses, batch)
        return (floor + (1.0 - floor) * (1.0 - np.exp(-np.float32(gain) * E))).astype(np.float32)
