"""Input checks shared by the public API: each says what was expected and what came."""

from __future__ import annotations

import math

import numpy as np

__all__ = [
    "BackendUnavailableError",
    "FormatError",
    "LimitError",
    "MissingFileError",
    "check_carve_views",
    "check_finite_scalar",
    "check_pose",
]


class BackendUnavailableError(RuntimeError):
    """A backend asked for by name cannot run on this machine (the reason is in the message)."""


class FormatError(ValueError):
    """A file is truncated, corrupt, or not in the layout it claims (gpumap's reader error).

    Every reader in :mod:`gpumap.io` raises this (or :class:`LimitError`) for anything wrong
    with the bytes it was given, never a library's own exception; it is a ``ValueError``.

    Parameters
    ----------
    message : str
        What was expected and what came.
    offset : int or None
        Byte offset in the file (or in the decompressed item, as the message says) where
        the problem was found; ``None`` where a byte offset does not apply.
    path : str or None
        The file concerned.

    Attributes
    ----------
    offset, path
        As given (``str(error)`` starts with ``"<path>, byte <offset>: "`` when known).
    """

    def __init__(self, message: str, offset: int | None = None, path: str | None = None):
        where = []
        if path is not None:
            where.append(str(path))
        if offset is not None:
            where.append(f"byte {offset}")
        prefix = (", ".join(where) + ": ") if where else ""
        super().__init__(prefix + message)
        self.message = message
        self.offset = offset
        self.path = None if path is None else str(path)

    def __reduce__(self):  # picklable with its fields (multiprocessing, logging handlers)
        return (type(self), (self.message, self.offset, self.path))


class LimitError(FormatError):
    """A size that a file declares is beyond what gpumap will allocate for it.

    Raised *before* allocating or inflating: the message names the field, the declared size
    and the budget from :mod:`gpumap.limits`.
    """


class MissingFileError(FormatError, FileNotFoundError):
    """A file that a recording needs beside it (a beam angle table) is not there.

    Both a :class:`FormatError` and a ``FileNotFoundError``.
    """


def check_carve_views(n: object) -> int:
    """``n`` as an int if it is an integer in 1..255 (the visible rule's carve_views), else raise."""
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or not 1 <= n <= 255:
        raise ValueError(f"Expected carve_views to be an integer in 1..255, but got {n!r}")
    return int(n)


def check_finite_scalar(value: object, name: str) -> float:
    """Return ``value`` as a float, or raise if it is not a finite real number."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise TypeError(f"Expected a real number for '{name}', but got {type(value).__name__}")
    v = float(value)
    if not math.isfinite(v):
        raise ValueError(f"Expected a finite value for '{name}', but got {v}")
    return v


_MAX_POSITION_M = 1e8  # gpumap.limits.MAX_POSITION_M (limits imports this module; a test checks they agree)


def check_pose(T: object, name: str = "T_W_S", atol: float = 1e-5) -> np.ndarray:
    """Validate a 4x4 rigid transform and return it as a float64 array (a copy).

    Raises if the shape is wrong, any entry is NaN/inf, the last row is not ``[0, 0, 0, 1]``,
    or the rotation block is not orthonormal with determinant +1 (within ``atol``).
    """
    if isinstance(T, np.ma.MaskedArray):
        raise TypeError(f"Expected a plain array for '{name}', but got a masked array (fill it first)")
    if np.iscomplexobj(T):
        raise TypeError(f"Expected real entries in '{name}', but got complex dtype {np.asarray(T).dtype}")
    a = np.array(T, dtype=np.float64, copy=True)
    if a.shape != (4, 4):
        raise ValueError(f"Expected a (4, 4) transform for '{name}', but got shape {a.shape}")
    if not np.isfinite(a).all():
        raise ValueError(f"Expected finite entries in '{name}', but got NaN or inf")
    far = float(np.abs(a[:3, 3]).max())
    if far > _MAX_POSITION_M:
        raise ValueError(f"Expected a position within {_MAX_POSITION_M:g} m of the origin in '{name}' "
                         f"(gpumap.limits.MAX_POSITION_M), but got a coordinate of {far:.3g} m")
    r3 = a[3]
    if abs(r3[0]) > atol or abs(r3[1]) > atol or abs(r3[2]) > atol or abs(r3[3] - 1.0) > atol:
        raise ValueError(f"Expected the last row of '{name}' to be [0, 0, 0, 1], but got {r3.tolist()}")
    R = a[:3, :3]
    G = R.T @ R
    G[0, 0] -= 1.0
    G[1, 1] -= 1.0
    G[2, 2] -= 1.0
    err = float(np.abs(G).max())
    if err > atol:
        raise ValueError(
            f"Expected an orthonormal rotation in '{name}' (|R^T R - I| <= {atol}), but got error {err:.3g}"
        )
    # orthonormal columns: det = +1 exactly when the third column is the cross of the first two
    c0, c1, c2 = R[:, 0], R[:, 1], R[:, 2]
    det = (
        (c0[1] * c1[2] - c0[2] * c1[1]) * c2[0]
        + (c0[2] * c1[0] - c0[0] * c1[2]) * c2[1]
        + (c0[0] * c1[1] - c0[1] * c1[0]) * c2[2]
    )
    if det < 0:
        raise ValueError(f"Expected a right-handed rotation in '{name}' (det +1), but got det {det:.6f}")
    return a
