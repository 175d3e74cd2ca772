"""The map's options as one checked, typed value (:class:`MapperParams`), and the layer protocol.

A :class:`~gpumap.MinMaxMapper` takes a sonar spec, a grid, a backend and one
:class:`MapperParams`; every option is checked once, when the params are made, so a bad value is
refused before anything is allocated. The read-time options of the rules (``carve_views``,
``bright_share``, ``share_z``) may still be changed on a mapper afterwards
(:attr:`gpumap.MinMaxMapper.value_rule`); the params keep what the map was made with.

:class:`Layer` is what a layer (confidence, view gain, surface estimate, distance field, a viewer)
implements to follow a map: :meth:`gpumap.MinMaxMapper.attach` binds it, and the mapper calls it
after each update. The core never imports a layer.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np

from gpumap.errors import check_carve_views, check_finite_scalar
from gpumap.geometry import BRIGHT_SHARE, RULES, SHARE_Z

__all__ = ["METHODS", "Layer", "MapperParams"]

#: How a ping finds the voxels it can see: every voxel of the fan's box, or the paper's voxel template.
METHODS = ("gather", "template")


def _positive_int(v: object, name: str) -> int:
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v <= 0:
        raise ValueError(f"Expected {name} to be a positive integer, but got {v!r}")
    return int(v)


@dataclass(frozen=True)
class MapperParams:
    """Every option of a min-max map, checked when made (``ValueError``/``TypeError`` otherwise).

    Parameters
    ----------
    method : str
        ``"gather"`` (default: every voxel of the field of view's bounding box, no holes) or
        ``"template"`` (the paper's six steps on a voxel template: may leave holes; a bounded
        GridSpec and the plain rule only).
    rule : str or None
        How views combine: ``"evidence"``, ``"visible"`` or ``"plain"`` (the paper's min over
        views), see :class:`gpumap.MinMaxMapper`; None (default) picks ``"evidence"`` for the
        gather method and ``"plain"`` for the template method. Resolved when made: ``rule`` is never
        None afterwards.
    threshold : float
        Intensity in (0, 1] from which a view counts as bright (default 0.1).
    shadow_m : float
        Acoustic-shadow allowance behind a strong return, metres, >= 0 (default 0: the paper's min-max).
    carve_views : int
        Visible rule: clear dark views (1..255) that carve a voxel once seen bright (default 2).
    bright_share : float
        Evidence rule: the share of bright views, in (0, 1], below which a voxel is free once the
        views show it (default :data:`gpumap.geometry.BRIGHT_SHARE`).
    share_z : float
        Evidence rule: the one-sided normal quantile, in [0, 10], of the confidence that frees a
        voxel (default :data:`gpumap.geometry.SHARE_Z`).
    footprint_max : str
        ``"auto"``, ``"table"`` or ``"loop"``: how kernels take the max over a footprint (a speed
        knob; the values are identical).
    sparse : bool or None
        True: blocks on demand even for a GridSpec; None (default): on demand for a SparseSpec only.
    max_bytes : int or None
        On demand only: cap on the block pool plus the coarse index, bytes (None: the device's).
    evict : None or "farthest"
        On demand only: what a ping past ``max_bytes`` does (None: raise, map unchanged).
    initial_blocks : int
        On demand only: pool slots allocated up front (default 64; grows by 1.5x).
    """

    method: str = "gather"
    rule: str | None = None
    threshold: float = 0.1
    shadow_m: float = 0.0
    carve_views: int = 2
    bright_share: float = BRIGHT_SHARE
    share_z: float = SHARE_Z
    footprint_max: str = "auto"
    sparse: bool | None = None
    max_bytes: int | None = None
    evict: str | None = None
    initial_blocks: int = 64

    def __post_init__(self) -> None:
        put = object.__setattr__  # frozen: the checked values replace the given ones once, here
        if self.method not in METHODS:
            raise ValueError(f"Expected method to be one of {METHODS}, but got {self.method!r}")
        rule = self.rule
        if rule is None:
            rule = "evidence" if self.method == "gather" else "plain"
        if rule not in RULES:
            raise ValueError(f"Expected rule to be one of {RULES} (or None), but got {rule!r}")
        if rule != "plain" and self.method != "gather":
            raise ValueError(
                f"Expected method='gather' with rule={rule!r} (the template method's duplicate "
                f"points cannot count views once), but got method={self.method!r}; use rule='plain' with it"
            )
        put(self, "rule", rule)
        thr = check_finite_scalar(self.threshold, "threshold")
        if not 0.0 < thr <= 1.0:
            raise ValueError(f"Expected threshold in (0, 1], but got {thr}")
        put(self, "threshold", thr)
        shadow = check_finite_scalar(self.shadow_m, "shadow_m")
        if shadow < 0:
            raise ValueError(f"Expected shadow_m >= 0, but got {shadow}")
        put(self, "shadow_m", shadow)
        put(self, "carve_views", check_carve_views(self.carve_views))
        p = check_finite_scalar(self.bright_share, "bright_share")
        if not 0.0 < p <= 1.0:
            raise ValueError(f"Expected bright_share in (0, 1], but got {p}")
        put(self, "bright_share", p)
        z = check_finite_scalar(self.share_z, "share_z")
        if not 0.0 <= z <= 10.0:
            raise ValueError(f"Expected share_z in [0, 10], but got {z}")
        put(self, "share_z", z)
        if self.footprint_max not in ("auto", "table", "loop"):
            raise ValueError(
                f"Expected footprint_max to be 'auto', 'table' or 'loop', but got {self.footprint_max!r}")
        if self.sparse not in (None, True, False):
            raise TypeError(f"Expected None or a bool for 'sparse', but got {self.sparse!r}")
        if self.evict not in (None, "farthest"):
            raise ValueError(f"Expected evict to be None or 'farthest', but got {self.evict!r}")
        if self.max_bytes is not None:
            put(self, "max_bytes", _positive_int(self.max_bytes, "max_bytes"))
        put(self, "initial_blocks", _positive_int(self.initial_blocks, "initial_blocks"))

    def replace(self, **changes: Any) -> MapperParams:
        """A copy with ``changes`` (checked again)."""
        return dataclasses.replace(self, **changes)


@runtime_checkable
class Layer(Protocol):
    """What a layer implements to follow a map (:meth:`gpumap.MinMaxMapper.attach`).

    ``name``: a short unique name (the map file keeps a layer's arrays under it). ``per_ping``: True
    when the layer must see the map after each ping (the mapper then applies a batch one ping at a
    time: the same map, bit for bit); False when it works on whole batches.
    """

    name: str
    per_ping: bool

    def attached(self, mapper) -> None:
        """Called once by ``attach``: check the map suits the layer (raise ``ValueError`` if not)
        and take any arrays a loaded map file kept for it (``mapper.layer_state.get(name)``)."""

    def after_ping(self, mapper, image: np.ndarray, T_W_S: np.ndarray, pad_m: float, params) -> None:
        """After one ping's update, under the map's lock (``per_ping`` layers): the checked image,
        pose, footprint pad and the ping's record."""

    def after_batch(self, mapper, images: np.ndarray, T_W_S: np.ndarray) -> None:
        """After a batch of pings (``(B, n_bins, n_beams)`` images as the mapper took them, ``(B, 4, 4)``
        poses), under the map's lock; a per-ping layer gets it too, after its pings."""

    def reset(self) -> None:
        """The map forgot every ping (:meth:`gpumap.MinMaxMapper.reset`)."""

    def file_arrays(self) -> dict[str, np.ndarray]:
        """Arrays over the grid, ``(nx*ny*nz,)`` uint8/uint16, that the map file keeps for this layer."""
