"""integrate(pose_cov=...): footprints grow with pose uncertainty and stay conservative, every backend."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import pose, rot_y, rot_z
from scipy.spatial.transform import Rotation
from test_mapper import GRID, SPEC, T_A

import gpumap
from gpumap.core.params import MapperParams

RNG = np.random.default_rng(21)
SIGMA_T, SIGMA_R = 0.01, 0.004  # m, rad
COV = np.diag([SIGMA_T**2] * 3 + [SIGMA_R**2] * 3)


def _ping(backend, img, T, **kw):
    m = gpumap.MinMaxMapper(SPEC, GRID, backend, MapperParams(rule="plain"))
    m.integrate(img, T, **kw)
    return m.raw_values().ravel()


def test_zero_covariance_changes_nothing(backend):
    img = (RNG.random(SPEC.image_shape) ** 4).astype(np.float32)
    zero = _ping(backend, img, T_A, pose_cov=np.zeros((6, 6)))
    np.testing.assert_array_equal(zero, _ping(backend, img, T_A))


def test_padded_value_covers_every_pose_within_the_bound(backend):
    """For poses T_A Exp(delta) with |delta_t| <= 2 sigma_t and |delta_theta| <= 2 sigma_r, each
    voxel's ping value at the perturbed pose is <= its value at T_A with pose_cov (2 sigmas)."""
    img = (RNG.random(SPEC.image_shape) ** 12).astype(np.float32)  # spiky: footprints matter
    padded = _ping(backend, img, T_A, pose_cov=COV, pose_sigmas=2.0)
    plain = _ping(backend, img, T_A)
    obs = np.isfinite(padded)
    assert np.all(padded[obs] >= plain[obs]) and np.mean(padded[obs] > plain[obs]) > 0.05
    needed = False  # without the padding some perturbed pose does see a brighter footprint
    for _ in range(12):
        u = RNG.normal(size=6)
        t = u[:3] / np.linalg.norm(u[:3]) * 2 * SIGMA_T * RNG.uniform(0.5, 1.0)
        phi = u[3:] / np.linalg.norm(u[3:]) * 2 * SIGMA_R * RNG.uniform(0.5, 1.0)
        D = np.eye(4)
        D[:3, :3] = Rotation.from_rotvec(phi).as_matrix()
        D[:3, 3] = t
        moved = _ping(backend, img, T_A @ D)
        both = obs & np.isfinite(moved)
        assert both.sum() > 1000
        assert np.all(moved[both] <= padded[both]), "a pose inside the bound sees a brighter footprint"
        needed |= bool(np.any(moved[both] > plain[both]))
    assert needed


def test_larger_uncertainty_never_lowers_a_value(backend):
    img = (RNG.random(SPEC.image_shape) ** 6).astype(np.float32)
    T = pose(rot_z(0.2) @ rot_y(-0.1), (0.05, 0.0, 0.02))
    a = _ping(backend, img, T, pose_cov=COV)
    b = _ping(backend, img, T, pose_cov=4 * COV)
    obs = np.isfinite(a)
    np.testing.assert_array_equal(obs, np.isfinite(b))  # what is observed follows the nominal pose
    assert np.all(b[obs] >= a[obs])


def test_bad_pose_cov_is_refused_and_leaves_the_map_untouched():
    m = gpumap.MinMaxMapper(SPEC, GRID, backend="numpy")
    img = np.zeros(SPEC.image_shape, np.float32)
    before = m.raw_values()
    bad_asym = np.eye(6) * 1e-4
    bad_asym[0, 1] = 1e-3
    for bad, msg in [
        (np.eye(5), "shape"),
        (np.full((6, 6), np.nan), "finite"),
        (bad_asym, "symmetric"),
        (-np.eye(6), "semi-definite"),
    ]:
        with pytest.raises(ValueError, match=msg):
            m.integrate(img, T_A, pose_cov=bad)
    with pytest.raises(ValueError, match="pose_sigmas"):
        m.integrate(img, T_A, pose_cov=COV, pose_sigmas=-1.0)
    np.testing.assert_array_equal(m.raw_values(), before)
    assert m.n_integrated == 0
