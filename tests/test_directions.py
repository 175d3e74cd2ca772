"""Evidence per view direction (gpumap.bench.experiments.directions) against independent references: the
nearest axis
by angle, the score test written out per class and voxel, and the pooled evidence map of the same
pings (the classes' counts must add up to it exactly)."""

from __future__ import annotations

import numpy as np
import pytest
from gpumap.bench.experiments.directions import (
    AXES,
    N_CLASSES,
    DirectionalEvidence,
    direction_classes,
    directional_occupied,
)
from test_mapper import GRID, SPEC
from test_visibility import THR, _random_pings

import gpumap
from gpumap.core.params import MapperParams


def _rot(axis: int, a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    i, j = [k for k in range(3) if k != axis]
    R = np.eye(4)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


def _rolled_pings(n=10, seed=3):
    """test_visibility's pings, every other one rolled about its boresight by +-0.35 rad, so that
    their elevation axes fall in several classes."""
    out = []
    for i, (img, T) in enumerate(_random_pings(n, seed)):
        out.append((img, T @ _rot(0, (0.35, -0.35, 0.0)[i % 3])))
    return out


def test_classes_are_the_nearest_axis_whatever_the_sign():
    rng = np.random.default_rng(0)
    q = rng.normal(size=(500, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T  # random rotations from unit quaternions
    R = np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
                  np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
                  np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], 1)
    T = np.tile(np.eye(4), (500, 1, 1))
    T[:, :3, :3] = R
    angle = np.arccos(np.clip(np.abs(R[:, :, 2] @ AXES.T), 0, 1))  # the elevation axis to each axis
    np.testing.assert_array_equal(direction_classes(T), np.argmin(angle, axis=1))
    flipped = T.copy()
    flipped[:, :3, 1:3] *= -1  # rolled by 180 degrees: the same elevation axis, the other sign
    np.testing.assert_array_equal(direction_classes(flipped), direction_classes(T))
    assert len(np.unique(direction_classes(T))) == N_CLASSES
    one = np.eye(4)
    one[:3, :3] = R[0]
    assert direction_classes(one).shape == (1,)


def _score_keeps(k, n, p, z):
    if n == 0:
        return True
    share = k / n
    return share >= p or (p - share) ** 2 * n <= z * z * p * (1 - p)


@pytest.mark.parametrize("p, z", [(0.2, 1.645), (0.5, 0.0), (0.35, 2.33)])
def test_decision_equals_the_score_test_class_by_class(p, z):
    rng = np.random.default_rng(1)
    hits = rng.integers(0, 6, (4, 300)) * (rng.random((4, 300)) < 0.6)
    dark = rng.integers(0, 25, (4, 300)) * (rng.random((4, 300)) < 0.7)
    want = np.array([hits[:, v].sum() > 0 and all(_score_keeps(hits[c, v], hits[c, v] + dark[c, v], p, z)
                                                  for c in range(4)) for v in range(300)])
    got = directional_occupied(dark.astype(np.uint32), hits.astype(np.uint32), p, z)
    np.testing.assert_array_equal(got, want)
    assert want.any() and not want.all()


def test_a_resolving_direction_carves_what_the_pooled_share_keeps():
    """The stretch: bright in all 6 views of one direction, dark in all 12 clear views of another
    (pooled share 1/3: kept at 0.2); a surface: bright in most views of both."""
    from gpumap.reference import evidence_occupied

    dark = np.array([[0, 1], [12, 2]], np.uint32)  # (class, voxel): voxel 0 the stretch, 1 a surface
    hits = np.array([[6, 5], [0, 9]], np.uint32)
    assert evidence_occupied(dark.sum(0), hits.sum(0), 0.2, 1.645).tolist() == [True, True]
    assert directional_occupied(dark, hits, 0.2, 1.645).tolist() == [False, True]


def test_class_counts_add_up_to_the_pooled_map_on_every_backend(backend):
    pings = _rolled_pings()
    assert len(np.unique(direction_classes(np.stack([T for _, T in pings])))) >= 2
    d = DirectionalEvidence(SPEC, GRID, backend=backend, threshold=THR)
    for img, T in pings:
        d.integrate(img, T)
    pooled = gpumap.MinMaxMapper(SPEC, GRID, backend, MapperParams(rule="evidence", threshold=THR))
    for img, T in pings:
        pooled.integrate(img, T)
    dark, hits = d.counts()
    ev = pooled.evidence()
    np.testing.assert_array_equal(dark.sum(0, dtype=np.uint64), ev["count"])
    np.testing.assert_array_equal(hits.sum(0, dtype=np.uint64), ev["hits"])
    assert (hits.sum(0) > 0).any() and (hits > 0).sum(0).max() >= 2  # some voxel bright in two classes
    # a batch gives the same counts, and so does the merge of two halves
    b = DirectionalEvidence(SPEC, GRID, backend=backend, threshold=THR)
    b.integrate_batch(np.stack([i for i, _ in pings]), np.stack([T for _, T in pings]))
    h1 = DirectionalEvidence(SPEC, GRID, backend=backend, threshold=THR)
    h2 = DirectionalEvidence(SPEC, GRID, backend=backend, threshold=THR)
    for i, (img, T) in enumerate(pings):
        (h1 if i % 2 else h2).integrate(img, T)
    h1.merge(h2)
    for other in (b, h1):
        od, oh = other.counts()
        np.testing.assert_array_equal(od, dark)
        np.testing.assert_array_equal(oh, hits)
    # values: the pooled map's bright value where the directional decision keeps a voxel
    occ = directional_occupied(dark, hits, pooled.bright_share, pooled.share_z)
    v = d.values(pooled)
    np.testing.assert_array_equal(v[occ], ev["bright"][occ])
    np.testing.assert_array_equal(np.isnan(v), np.isinf(ev["min_all"]))


def test_bad_input_says_what_was_expected():
    d = DirectionalEvidence(SPEC, GRID, backend="numpy", threshold=THR)
    img, T = _random_pings(1, 0)[0]
    with pytest.raises(ValueError, match=r"T_W_S of shape \(2, 4, 4\)"):
        d.integrate_batch(np.stack([img, img]), T)
    with pytest.raises(ValueError, match="one shape"):
        directional_occupied(np.zeros((2, 3)), np.zeros((3, 2)), 0.2, 1.645)
    assert not any(m.n_integrated for m in d.maps.values())
