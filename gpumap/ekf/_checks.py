"""Argument checks and chi-square quantiles shared by the EKF's modules (private)."""

from __future__ import annotations

import math

import numpy as np


def _check_cov(C: object, n: int, name: str) -> np.ndarray:
    a = np.array(C, dtype=np.float64, copy=True)
    if a.shape != (n, n):
        raise ValueError(f"Expected a ({n}, {n}) covariance for '{name}', but got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"Expected finite entries in '{name}', but got NaN or inf")
    scale = max(float(np.abs(a).max()), 1e-300)
    if float(np.abs(a - a.T).max()) > 1e-9 * scale:
        raise ValueError(f"Expected a symmetric matrix for '{name}', but got asymmetry "
                         f"{float(np.abs(a - a.T).max()):.3g}")
    a = 0.5 * (a + a.T)
    lam = float(np.linalg.eigvalsh(a).min())
    if lam < -1e-12 * scale:
        raise ValueError(f"Expected a positive semi-definite matrix for '{name}', but got "
                         f"smallest eigenvalue {lam:.3g}")
    return a


def _real_array(v: object, name: str) -> np.ndarray:
    """``v`` as a float64 copy, or TypeError if it does not hold real numbers."""
    a = np.asarray(v)
    if a.dtype == object or not np.issubdtype(a.dtype, np.number) or np.issubdtype(
        a.dtype, np.complexfloating
    ):
        raise TypeError(f"Expected real numbers in '{name}', but got dtype {a.dtype}")
    return np.array(a, dtype=np.float64, copy=True)


def _check_vector(v: object, m: int | None, name: str) -> np.ndarray:
    a = _real_array(v, name)
    if a.ndim != 1 or (m is not None and a.shape[0] != m):
        want = f"({m},)" if m is not None else "(m,)"
        raise ValueError(f"Expected shape {want} for '{name}', but got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"Expected finite values in '{name}', but got NaN or inf")
    return a


def _check_matrix3(v: object, m: int | None, name: str) -> np.ndarray:
    a = _real_array(v, name)
    if a.ndim != 2 or a.shape[1] != 3 or (m is not None and a.shape[0] != m):
        want = f"({m}, 3)" if m is not None else "(m, 3)"
        raise ValueError(f"Expected shape {want} for '{name}', but got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"Expected finite values in '{name}', but got NaN or inf")
    return a


def _check_ids(ids: object) -> list[int]:
    a = np.asarray(ids)
    if a.ndim != 1:
        raise ValueError(f"Expected a 1-D sequence of integer ids for 'ids', but got shape {a.shape}")
    if a.size and not np.issubdtype(a.dtype, np.integer):
        raise TypeError(f"Expected integer ids for 'ids', but got dtype {a.dtype}")
    out = [int(i) for i in a]
    if len(set(out)) != len(out):
        dup = sorted({i for i in out if out.count(i) > 1})
        raise ValueError(f"Expected each id at most once per update in 'ids', but got repeats {dup}")
    return out


def _chi2_quantile(prob: float, dof: int) -> float:
    """Chi-square quantile (``dof >= 1``)."""
    from scipy.stats import chi2

    return float(chi2.ppf(prob, dof))


def _chi2_2dof(prob: float) -> float:
    # Chi-square with 2 dof is exponential: P(X <= x) = 1 - exp(-x/2).
    return -2.0 * math.log1p(-prob)
