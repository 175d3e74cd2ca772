"""The fit of refinement: its settings (:class:`RefineOptions`), the Warp arrays and the
projected Adam step over the loss of :mod:`gpumap.layers.refine` (``_Fit``), and the display law's
starting gain and floor (``_calibrate``).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from gpumap.layers.render import PingRenderer

__all__ = ["RefineOptions"]


@dataclass(frozen=True)
class RefineOptions:
    """Settings of :func:`~gpumap.layers.refine.refine` (the same defaults on every scene).

    Attributes
    ----------
    iterations : int
        Adam steps.
    pings_per_step : int
        Training pings rendered per step (drawn at random, without replacement within a pass).
    learning_rate : float
        Adam step of occupancy and reflectivity (units of [0, 1] per step).
    huber_delta : float
        Residual (intensity) beyond which the loss grows linearly: speckle and unmodelled echoes
        do not dominate.
    smoothness : float
        Weight of the squared neighbour differences of the field, per pair of movable voxels,
        against the data term summed over a ping's rendered cells (default 0: off).
    sparsity : float
        Weight of the field's sum over movable voxels: explain the pings with as little matter
        as they need (a phantom voxel that no echo needs decays to empty).
    power : float
        The loss compares ``(intensity + 1e-3) ** power``: 0.5 (square roots) lets a dim grazing
        surface weigh nearly as much as a bright one; 1 compares intensities.
    init_occupancy : float
        Starting field value ``o`` of the voxels the visible map calls occupied (others start at
        0); ``o = 0.5`` stops ``1 - exp(-kappa / 2)`` = 86 % of the sound in one voxel.
    seed : int
        Seed of the ping order.
    """

    iterations: int = 300
    pings_per_step: int = 8
    learning_rate: float = 0.08
    huber_delta: float = 0.1
    smoothness: float = 0.0
    init_occupancy: float = 0.5
    sparsity: float = 3e-4
    power: float = 0.5
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("iterations", "pings_per_step"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
                raise ValueError(f"Expected a positive integer for {name!r}, but got {v!r}")
        for name in ("learning_rate", "huber_delta"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"Expected a finite {name!r} > 0, but got {v!r}")
        for name in ("smoothness", "sparsity"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"Expected a finite {name!r} >= 0, but got {v!r}")
        if not (isinstance(self.power, (int, float)) and 0 < self.power <= 1):
            raise ValueError(f"Expected 'power' in (0, 1], but got {self.power!r}")
        if not 0 <= self.init_occupancy <= 1:
            raise ValueError(f"Expected 'init_occupancy' in [0, 1], but got {self.init_occupancy!r}")

    def to_dict(self) -> dict:
        return asdict(self)


# ---------------------------------------------------------------------- the optimiser
class _Fit:
    """Warp arrays of one fit: the field, its bounds and Adam moments, the measured images."""

    def __init__(
        self,
        renderer: PingRenderer,
        occ0: np.ndarray,
        upper: np.ndarray,
        refl0: np.ndarray,
        measured: np.ndarray,
        log_gain: float,
        floor: float,
    ) -> None:
        r = renderer
        wp, dev = r._wp, r.device
        self.r, self.wp, self.dev = r, wp, dev
        self.occ = wp.array(occ0.astype(np.float32), dtype=wp.float32, device=dev, requires_grad=True)
        self.refl = wp.array(refl0.astype(np.float32), dtype=wp.float32, device=dev, requires_grad=True)
        self.glob = wp.array(
            np.array([log_gain, floor], np.float32), dtype=wp.float32, device=dev, requires_grad=True
        )
        self.active = wp.array((upper > 0).astype(np.uint8), dtype=wp.uint8, device=dev)
        n = occ0.size
        self.bounds = {
            "occ": (
                wp.zeros(n, dtype=wp.float32, device=dev),
                wp.array(upper.reshape(-1).astype(np.float32), dtype=wp.float32, device=dev),
            ),
            "refl": (
                wp.full(n, 0.05, dtype=wp.float32, device=dev),
                wp.full(n, 1.0, dtype=wp.float32, device=dev),
            ),
            "glob": (
                wp.array([-5.0, 0.0], dtype=wp.float32, device=dev),
                wp.array([15.0, 0.5], dtype=wp.float32, device=dev),
            ),
        }
        self.moments = {
            k: (
                wp.zeros(len(b[0]), dtype=wp.float32, device=dev),
                wp.zeros(len(b[0]), dtype=wp.float32, device=dev),
            )
            for k, b in self.bounds.items()
        }
        self.measured = measured  # host (N, nr, nb) float32
        self.ones = None
        self.t = 0

    def step_loss(self, idx: np.ndarray, opts: RefineOptions, lrs: dict[str, float] | None = None) -> float:
        """One forward + backward over pings ``idx``; an Adam step on the arrays named in ``lrs``."""
        wp, r, dev, kr = self.wp, self.r, self.dev, self.r._kr
        B = len(idx)
        R, t = r._pose_arrays(self.poses[idx])
        tape = wp.Tape()
        E = r.record_energy(tape, self.occ, self.refl, R, t, B)
        meas = wp.array(self.measured[idx], dtype=wp.float32, device=dev)
        if self.ones is None or self.ones.shape[0] != B:
            self.ones = wp.ones(E.shape, dtype=wp.float32, device=dev)
        loss = wp.zeros(1, dtype=wp.float32, device=dev, requires_grad=True)
        pred = wp.zeros(E.shape, dtype=wp.float32, device=dev, requires_grad=True)
        with tape:
            wp.launch(
                kr.image_loss,
                dim=E.shape,
                device=dev,
                inputs=[E, meas, self.ones, self.glob, float(opts.huber_delta), 1.0 / B, float(opts.power)],
                outputs=[pred, loss],
            )
            if opts.smoothness > 0 or opts.sparsity > 0:
                wp.launch(
                    kr.smoothness,
                    dim=self.occ.shape,
                    device=dev,
                    inputs=[self.occ, self.active, float(opts.smoothness), float(opts.sparsity)],
                    outputs=[loss],
                )
        tape.backward(loss)
        value = float(loss.numpy()[0])
        if lrs:
            self.t += 1
            b1, b2 = 0.9, 0.999
            arrays = {"occ": self.occ, "refl": self.refl, "glob": self.glob}
            for name, lr in lrs.items():
                a = arrays[name]
                m, v = self.moments[name]
                lo, hi = self.bounds[name]
                wp.launch(
                    kr.adam_project,
                    dim=len(m),
                    device=dev,
                    inputs=[
                        a.flatten(),
                        a.grad.flatten(),
                        m,
                        v,
                        lo,
                        hi,
                        float(lr),
                        b1,
                        b2,
                        1.0 - b1**self.t,
                        1.0 - b2**self.t,
                    ],
                )
        tape.zero()
        return value


def _calibrate(
    r: PingRenderer,
    occ: np.ndarray,
    refl: np.ndarray,
    measured: np.ndarray,
    poses: np.ndarray,
    delta: float,
    n: int = 16,
) -> tuple[float, float]:
    """(log gain, floor) of the display law for a field, from ``n`` evenly spread pings.

    The floor is the median measured intensity (most cells are water). The gain conserves energy:
    the measured energy ``-log(1 - I')`` (``I' = (I - floor) / (1 - floor)`` clipped to
    [0, 0.99]) summed over every cell, over the field's summed rendered energy. Where a map puts a
    surface at the wrong range or elevation the sums still agree, so a stretched map does not drag
    the gain down as a least-squares fit would. ``delta`` is unused (kept for the signature).
    """
    del delta
    sel = np.unique(np.linspace(0, len(poses) - 1, min(n, len(poses))).round().astype(int))
    E = r.energy(occ, refl, poses[sel])
    M = measured[sel]
    floor = float(np.median(M))
    ip = np.clip((M - floor) / (1.0 - floor), 0.0, 0.99)
    e_meas = float(-np.log1p(-ip).sum())
    e_model = float(E.sum())
    if e_model <= 0 or e_meas <= 0:
        return 0.0, floor
    return float(np.clip(math.log(e_meas / e_model), -5.0, 15.0)), floor

