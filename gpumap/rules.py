"""How a map's per-voxel state reads as values, and how two states of a voxel merge, by rule.

The update a ping makes is per rule (the kernels, :mod:`gpumap.reference`); what is read from
the state afterwards is here: :func:`rule_values` (a voxel's value from ``min_all``, ``bright``
and ``count``), :class:`ValueRule` (the rule with its read-time options, checked when set: they
may change between pings without touching the state) and :func:`combine_into` (the merge of
two states of the same voxels: mins of the mins, saturating sums of the view counts, so maps
of disjoint pings merge exactly, :mod:`gpumap.merge`).
"""

from __future__ import annotations

import numpy as np

from gpumap.errors import check_carve_views, check_finite_scalar
from gpumap.geometry import DECISIONS, MISS_COST

__all__ = ["ValueRule", "check_decision", "check_miss_cost", "combine_into", "rule_values"]


def rule_values(rule: str, min_all: np.ndarray, bright, count, carve_views: int, bright_share: float,
                share_z: float, decision: str = "share", miss_cost: float = MISS_COST) -> np.ndarray:
    """A map's values from its per-voxel state, by ``rule`` (:mod:`gpumap.reference`); the evidence
    rule decides by ``decision`` (``"share"``: the share test at ``bright_share``, ``share_z``;
    ``"calibrated"``: :mod:`gpumap.calibration` at ``miss_cost``, fitted to this state's counts)."""
    from gpumap.reference import calibrated_values, evidence_values, visible_values

    if rule == "visible":
        return visible_values(min_all, bright, count, carve_views)
    if rule == "evidence":
        if decision == "calibrated":
            return calibrated_values(min_all, bright, count, miss_cost)
        return evidence_values(min_all, bright, count, bright_share, share_z)
    return min_all


def check_decision(d: object) -> str:
    """``d`` if it is one of :data:`~gpumap.geometry.DECISIONS`, else raise."""
    if d not in DECISIONS:
        raise ValueError(f"Expected decision to be one of {DECISIONS}, but got {d!r}")
    return str(d)


def check_miss_cost(c: object) -> float:
    """``c`` as a float if it is a finite number in [1e-6, 1e12], else raise."""
    c = check_finite_scalar(c, "miss_cost")
    if not 1e-6 <= c <= 1e12:
        raise ValueError(f"Expected miss_cost in [1e-6, 1e12] (phantoms one avoided miss is worth), "
                         f"but got {c}")
    return c


def _check_bright_share(p: object) -> float:
    p = check_finite_scalar(p, "bright_share")
    if not 0.0 < p <= 1.0:
        raise ValueError(f"Expected bright_share in (0, 1], but got {p}")
    return p


def _check_share_z(z: object) -> float:
    z = check_finite_scalar(z, "share_z")
    if not 0.0 <= z <= 10.0:
        raise ValueError(f"Expected share_z in [0, 10], but got {z}")
    return z


def _option(name: str, check, doc: str) -> property:
    """A read-time option of :class:`ValueRule`, ``check``-ed whenever it is set."""
    return property(lambda self: getattr(self, f"_{name}"),
                    lambda self, value: setattr(self, f"_{name}", check(value)), doc=doc)


class ValueRule:
    """A rule (``"evidence"``, ``"visible"`` or ``"plain"``) with its read-time options, each
    checked when it is set (see :class:`gpumap.MinMaxMapper` for their meaning)."""

    carve_views = _option("carve_views", check_carve_views,
                          "Visible rule: clear dark views that carve a voxel once seen bright, in 1..255.")
    bright_share = _option("bright_share", _check_bright_share,
                           "Evidence rule: the share of bright views, in (0, 1], below which a voxel is "
                           "free.")
    share_z = _option("share_z", _check_share_z, "Evidence rule: the one-sided normal quantile, in [0, 10], "
                      "of the confidence that frees a voxel.")
    decision = _option("decision", check_decision, "Evidence rule: how the view counts decide, one of "
                       "DECISIONS (``share``: the share test; ``calibrated``: gpumap.calibration).")
    miss_cost = _option("miss_cost", check_miss_cost, "Evidence rule, calibrated decision: the phantom "
                        "voxels one avoided miss is worth.")

    def __init__(self, rule: str, carve_views: int, bright_share: float, share_z: float,
                 decision: str = "share", miss_cost: float = MISS_COST) -> None:
        self.rule = rule
        self.carve_views = carve_views
        self.bright_share = bright_share
        self.share_z = share_z
        self.decision = decision
        self.miss_cost = miss_cost

    def values(self, min_all: np.ndarray, bright, count) -> np.ndarray:
        """The values of a state (the plain rule's are ``min_all`` itself)."""
        return rule_values(self.rule, min_all, bright, count, self.carve_views, self.bright_share,
                           self.share_z, self.decision, self.miss_cost)

    def occupied(self, dark: np.ndarray, hits: np.ndarray) -> np.ndarray:
        """The evidence rule's decision on view counts (``dark``, ``hits``: clear dark and bright views
        per voxel, any shape): bool of their shape, True where the rule calls a voxel occupied."""
        from gpumap.calibration import calibrated_occupied
        from gpumap.reference import evidence_occupied

        if self.decision == "calibrated":
            return calibrated_occupied(dark, hits, self.miss_cost)
        return evidence_occupied(dark, hits, self.bright_share, self.share_z)


def combine_into(acc: dict, b: dict, rule: str) -> None:
    """``acc`` (arrays or views, e.g. a box of the grid) becomes the merge of itself and ``b``
    (the same voxels, any shape of the same size), in place: mins of the mins, and for the rules
    that keep view state (all but ``"plain"``) saturating sums of the view counts
    (:func:`gpumap.reference.add_counts`)."""
    from gpumap.reference import add_counts

    shape = acc["min_all"].shape
    np.minimum(acc["min_all"], b["min_all"].reshape(shape), out=acc["min_all"])
    if rule != "plain":
        np.minimum(acc["bright"], b["bright"].reshape(shape), out=acc["bright"])
        acc["count"][...] = add_counts(acc["count"], b["count"].reshape(shape), rule)
