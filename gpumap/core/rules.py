"""How a map's per-voxel state reads as values, and how two states of a voxel merge, by rule.

The update a ping makes is per rule (the kernels, :mod:`gpumap.reference`); what is read from
the state afterwards is here: :func:`rule_values` (a voxel's value from ``min_all``, ``bright``
and ``count``), :class:`ValueRule` (the rule with its read-time options, checked when set: they
may change between pings without touching the state) and :func:`combine_into` (the merge of
two states of the same voxels: mins of the mins, saturating sums of the view counts, so maps
of disjoint pings merge exactly, :mod:`gpumap.core.merge`).
"""

from __future__ import annotations

import numpy as np

from gpumap.errors import check_carve_views, check_finite_scalar

__all__ = ["ValueRule", "combine_into", "rule_values"]


def rule_values(rule: str, min_all: np.ndarray, bright, count, carve_views: int, bright_share: float,
                share_z: float) -> np.ndarray:
    """A map's values from its per-voxel state, by ``rule`` (:mod:`gpumap.reference`); the evidence
    rule decides by the share test at ``bright_share``, ``share_z``."""
    from gpumap.reference import evidence_values, visible_values

    if rule == "visible":
        return visible_values(min_all, bright, count, carve_views)
    if rule == "evidence":
        return evidence_values(min_all, bright, count, bright_share, share_z)
    return min_all


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

    def __init__(self, rule: str, carve_views: int, bright_share: float, share_z: float) -> None:
        self.rule = rule
        self.carve_views = carve_views
        self.bright_share = bright_share
        self.share_z = share_z

    def values(self, min_all: np.ndarray, bright, count) -> np.ndarray:
        """The values of a state (the plain rule's are ``min_all`` itself)."""
        return rule_values(self.rule, min_all, bright, count, self.carve_views, self.bright_share,
                           self.share_z)

    def occupied(self, dark: np.ndarray, hits: np.ndarray) -> np.ndarray:
        """The evidence rule's decision on view counts (``dark``, ``hits``: clear dark and bright views
        per voxel, any shape): bool of their shape, True where the rule calls a voxel occupied."""
        from gpumap.reference import evidence_occupied

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
