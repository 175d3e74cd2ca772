"""The batched host path (issue 38): a batch's fingerprints, ping records and launch groups come
from whole-array passes, and each equals what the per-ping code makes, value for value."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import gpumap
import gpumap.backends
from gpumap.geometry import PING_DTYPE, ping_params
from gpumap.pings import ping_print, ping_prints

SPEC = gpumap.SonarSpec(0.1, 2.0, 64, np.linspace(-0.6, 0.6, 48), np.deg2rad(20.0))
GRID = gpumap.GridSpec((-1.0, -1.2, -0.6), (1.4, 1.2, 0.7), 0.05)


def _poses(n: int, seed: int, spread_m: float = 1.0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.random(n, random_state=seed).as_matrix()
    T[:, :3, 3] = rng.normal(0.0, spread_m, (n, 3))
    return T


@pytest.mark.parametrize("dtype", [np.uint8, np.float32])
@pytest.mark.parametrize("shape", [(64, 48), (398, 512), (3, 5)])
def test_a_batch_of_fingerprints_equals_one_print_per_ping(dtype, shape):
    rng = np.random.default_rng(3)
    imgs = rng.integers(0, 256, (7, *shape)).astype(dtype)
    if dtype == np.float32:
        imgs /= 255.0
    T = _poses(7, 4)
    got = ping_prints(imgs, T)
    assert got.dtype == np.uint64 and got.shape == (7,)
    np.testing.assert_array_equal(got, [ping_print(i, t) for i, t in zip(imgs, T, strict=True)])
    assert ping_prints(imgs[:0], T[:0]).shape == (0,)


def test_a_mapper_keeps_the_same_prints_for_a_batch_and_for_single_pings():
    rng = np.random.default_rng(5)
    imgs = rng.integers(0, 256, (6, *SPEC.image_shape)).astype(np.uint8)
    T = _poses(6, 6, 0.2)
    a = gpumap.MinMaxMapper(SPEC, GRID, backend="numpy")
    b = gpumap.MinMaxMapper(SPEC, GRID, backend="numpy")
    a.integrate_batch(imgs, T)
    for i, t in zip(imgs, T, strict=True):
        b.integrate(i, t)
    np.testing.assert_array_equal(a.pings.array(), b.pings.array())


@pytest.mark.parametrize("sparse", [False, True])
def test_the_batch_records_equal_the_one_ping_geometry(sparse):
    """Integrator.ping_params over a batch (poses anywhere, some far outside the box, with and
    without footprint pads) against gpumap.geometry.ping_params one ping at a time."""
    space = gpumap.SparseSpec(0.05, origin_m=(-1.0, -1.2, -0.6)) if sparse else GRID
    m = gpumap.MinMaxMapper(SPEC, space, backend="numpy")
    it = m.integrator
    T = _poses(40, 8, 1.5)
    pads = np.where(np.arange(40) % 3 == 0, 0.0, 0.004 * np.arange(40))
    P, n_threads = it.ping_params(T, pads)
    P2, _ = it.ping_params(T[:5], pads[:5])  # a smaller batch after a larger one: the same rows
    assert P2.tobytes() == P[:5].tobytes()
    static = it.params.copy()
    it.params["thr"] = 0.375  # a static field changed later reaches every record
    assert (it.ping_params(T[:3], pads[:3])[0]["thr"] == np.float32(0.375)).all()
    it.params[...] = static
    for b in range(40):
        one, _ = it.ping_params(T[b : b + 1], pads[b : b + 1])
        assert one.tobytes() == P[b : b + 1].tobytes(), b
    if sparse:
        return
    for b in np.flatnonzero(pads == 0.0):
        ref = it.params.copy()
        n_cols = ping_params(ref, T[b], it.fov_pts_S, GRID)
        assert int(n_threads[b]) == n_cols
        for name in ("R", "t", "A", "b", "box_lo", "box_n"):
            np.testing.assert_array_equal(P[b][name], ref[name], err_msg=f"{name} of ping {b}")


def _groups_loop(params, n_threads, slack=2.0):
    """The greedy split as a plain loop over the pings (the reference)."""
    lo = params["box_lo"].astype(np.int64)
    hi = lo + params["box_n"].astype(np.int64)
    out, start, ulo, uhi, total = [], 0, None, None, 0
    for b in range(len(params)):
        vol = int(np.prod(hi[b] - lo[b])) if n_threads[b] > 0 else 0
        if vol == 0:
            continue
        if ulo is None:
            nlo, nhi = lo[b], hi[b]
        else:
            nlo, nhi = np.minimum(ulo, lo[b]), np.maximum(uhi, hi[b])
            if np.prod(nhi - nlo) > slack * (total + vol) or b - start >= gpumap.backends.BATCH_MAX:
                out.append((start, b))
                start, nlo, nhi, total = b, lo[b], hi[b], 0
        ulo, uhi, total = nlo, nhi, total + vol
    if ulo is not None:
        out.append((start, len(params)))
    return out


@pytest.mark.parametrize("batch_max", [64, 5, 1])
def test_launch_groups_equal_the_greedy_loop(monkeypatch, batch_max):
    monkeypatch.setattr(gpumap.backends, "BATCH_MAX", batch_max)
    rng = np.random.default_rng(batch_max)
    for _ in range(300):
        B = int(rng.integers(1, 90))
        P = np.zeros(B, PING_DTYPE)
        scale = int(rng.choice([4, 40, 400]))
        P["box_lo"] = rng.integers(-scale, scale, (B, 3))
        P["box_n"] = rng.integers(0, scale, (B, 3)) * (rng.random((B, 1)) > 0.1)
        n_threads = np.where(P["box_n"][:, 2] > 0, P["box_n"][:, 0] * P["box_n"][:, 1], 0)
        n_threads[rng.random(B) < 0.1] = 0
        assert gpumap.backends._union_groups(P, n_threads) == _groups_loop(P, n_threads)
