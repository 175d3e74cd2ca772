"""Map metrics against hand counts on tiny hand-made truths."""

from __future__ import annotations

import math

import numpy as np
import pytest
from gpumap.sim.metrics import evaluate, fn_fp_curve
from gpumap.sim.truth import Truth

NAN = math.nan
CURVE_KEYS = ("false_negative_rate_detectable", "false_negative_rate_all",
              "false_negative_rate_objects_detectable", "false_positive_rate_far",
              "miss_rate", "miss_rate_objects")


def _line(x) -> np.ndarray:
    """Eight voxels in a row along x: shape (8, 1, 1)."""
    return np.asarray(x).reshape(8, 1, 1)


@pytest.fixture
def case():
    # Voxels 0-2 sand, 3-5 a rock, 6-7 water.
    occupied = _line([1, 1, 1, 1, 1, 1, 0, 0]).astype(bool)
    label = _line([0, 0, 0, 1, 1, 1, -1, -1]).astype(np.int16)
    truth = Truth(occupied, occupied.copy(), label, ["sand", "rock"])
    seen = _line([1, 1, 0, 1, 1, 1, 0, 0]).astype(bool)
    detectable = _line([1, 0, 0, 1, 1, 0, 0, 0]).astype(bool)
    #                 occ  free unk  free unk  occ  occ  free   (threshold 0.1)
    values = _line([0.5, 0.05, NAN, 0.02, NAN, 0.9, 0.3, 0.01]).astype(np.float32)
    return truth, values, seen, detectable


def test_truth_small_objects_default_to_non_background(case):
    truth = case[0]
    assert truth.small_objects == ("rock",)
    assert np.array_equal(truth.objects_mask(), truth.mask("rock"))


def test_new_rates_match_hand_counts(case):
    truth, values, seen, detectable = case
    ev = evaluate(values, truth, 0.1, seen, detectable=detectable)
    # occupied & detectable & observed = {0, 3}; called free: {3}.
    assert ev.false_negative_rate_detectable == 1 / 2
    # ... of the rock: {3}; free: {3}.
    assert ev.false_negative_rate_objects_detectable == 1.0
    # occupied & detectable = {0, 3, 4}; not called occupied: {3 (free), 4 (unknown)}.
    assert ev.miss_rate == 2 / 3
    assert ev.miss_rate_objects == 2 / 2
    # seen = {0, 1, 3, 4, 5}; observed: {0, 1, 3, 5}.
    assert ev.observed_surface_fraction == 4 / 5
    # The old rates keep their meaning: seen & observed occupied = {0, 1, 3, 5}, free {1, 3}.
    assert ev.false_negative_rate == 2 / 4
    assert ev.false_negative_rate_objects == 1 / 2  # {3, 5}
    assert ev.false_positive_rate == 1 / 2  # water observed {6, 7}, occupied {6}
    assert ev.false_positive_rate_far == 0.0  # 6 touches the rock; {7} is free
    assert ev.object_recall == {"rock": 1 / 2}


def test_detectable_defaults_to_seen(case):
    truth, values, seen, _ = case
    ev = evaluate(values, truth, 0.1, seen)
    assert ev.false_negative_rate_detectable == ev.false_negative_rate == 2 / 4
    assert ev.miss_rate == 3 / 5  # {1 free, 3 free, 4 unknown} of {0, 1, 3, 4, 5}
    assert ev.miss_rate_objects == 2 / 3  # {3, 4} of {3, 4, 5}
    # An explicit objects tuple overrides the truth's.
    both = evaluate(values, truth, 0.1, seen, objects=("sand", "rock"))
    assert both.miss_rate_objects == both.miss_rate


def test_bad_masks_are_refused(case):
    truth, values, seen, detectable = case
    with pytest.raises(ValueError, match="detectable"):
        evaluate(values, truth, 0.1, seen, detectable=detectable[:4])
    with pytest.raises(ValueError, match="seen"):
        evaluate(values, truth, 0.1, seen.astype(np.float32))


def test_fn_fp_curve_is_evaluate_at_each_threshold(case):
    truth, values, seen, detectable = case
    th = np.array([0.0, 0.01, 0.1, 0.3, 0.5, 0.9, 1.1])
    curve = fn_fp_curve(values, truth, th, seen, detectable)
    assert np.array_equal(curve["threshold"], th)
    for i, t in enumerate(th):
        ev = evaluate(values, truth, float(t), seen, detectable=detectable).to_dict()
        for k in CURVE_KEYS:
            np.testing.assert_equal(curve[k][i], ev[k], err_msg=f"{k} at {t}")
    # Raising the threshold never lowers FN nor raises FP.
    assert np.all(np.diff(curve["false_negative_rate_detectable"]) >= 0)
    assert np.all(np.diff(curve["false_positive_rate_far"]) <= 0)


def test_miss_rate_bounds_the_false_negative_rate():
    rng = np.random.default_rng(0)
    shape = (6, 5, 4)
    occupied = rng.random(shape) < 0.5
    label = np.where(occupied, rng.integers(0, 3, shape), -1).astype(np.int16)
    truth = Truth(occupied, occupied.copy(), label, ["sand", "walls", "thing"])
    assert truth.small_objects == ("thing",)
    seen = occupied & (rng.random(shape) < 0.8)
    detectable = seen & (rng.random(shape) < 0.7)
    values = rng.random(shape).astype(np.float32)
    full = evaluate(values, truth, 0.4, seen, detectable=detectable)
    # With nothing unknown a miss is a false negative.
    assert full.miss_rate == full.false_negative_rate_detectable
    assert full.observed_surface_fraction == 1.0
    values[rng.random(shape) < 0.3] = np.nan
    ev = evaluate(values, truth, 0.4, seen, detectable=detectable)
    # Unknown voxels only add to misses: (free + unknown) / (observed + unknown) >= free / observed.
    assert ev.miss_rate >= ev.false_negative_rate_detectable
    assert ev.miss_rate_objects >= ev.false_negative_rate_objects_detectable
    n = (occupied & detectable).sum()
    called = (occupied & detectable & (np.nan_to_num(values, nan=-1) >= 0.4)).sum()
    assert ev.miss_rate == (n - called) / n


def test_per_object_misses_and_phantoms_add_up_to_the_rates(case):
    """The picture's per-object counts (errors_by_object.png) are the rates' own: hand counts,
    and summed over objects they give miss_rate and the false-positive rate (far)."""
    from gpumap.sim.metrics import miss_by_object, phantom_far

    truth, values, seen, detectable = case
    ev = evaluate(values, truth, 0.1, seen, detectable=detectable)
    per = miss_by_object(values, truth, 0.1, detectable)
    # sand: detectable {0}, occupied -> 0 missed; rock: detectable {3, 4}: free and unknown
    assert per == {"sand": (0, 1), "rock": (2, 2)}
    assert ev.miss_rate_by_object == {"sand": 0.0, "rock": 1.0}
    assert sum(m for m, _ in per.values()) / sum(d for _, d in per.values()) == ev.miss_rate
    # a phantom far from every surface: water voxel 7 called occupied
    far_values = values.copy()
    far_values[7] = 0.5
    ph = phantom_far(far_values, truth, 0.1)
    assert ph.ravel().tolist() == [False] * 7 + [True]
    # the rate's denominator: observed voxels more than one voxel from the truth, here {7} alone
    assert evaluate(far_values, truth, 0.1, seen, detectable=detectable).false_positive_rate_far == ph.sum()
