"""One place that states the limits: how much gpumap will allocate for what a file declares.

Every reader checks a size it finds in a file (a payload length, a decompressed size, an
image's rows and columns, a vertex count) against a budget here, and against the bytes the
file still has, *before* it allocates, reads or inflates anything of that size. A small
hostile file therefore costs a small amount of memory and time and ends in a
:class:`~gpumap.errors.LimitError` (a :class:`~gpumap.errors.FormatError`, a ``ValueError``)
that names the field, the declared size and the budget.

The budgets are far above what real sonars produce (the largest image in ``shared/data`` is
a 398 x 722 fan picture, 0.29 Mpixel; an Oculus message is at most about 0.6 MB) and low
enough that one frame, with the few float32 working copies a reader makes of it, stays well
under :data:`MEMORY_TARGET_BYTES`. They are module constants: a program that really needs
more can raise one (``gpumap.limits.MAX_IMAGE_PIXELS = ...``) before opening a file; readers
read them at call time.
"""

from __future__ import annotations

import math
import operator

from gpumap.errors import FormatError, LimitError

__all__ = [
    "MAX_CSV_BYTES",
    "MAX_DEFLATE_RATIO",
    "MAX_GRID_VOXELS",
    "MAX_HEADER_BYTES",
    "MAX_IMAGE_PIXELS",
    "MAX_ITEM_BYTES",
    "MAX_MAP_META_BYTES",
    "MAX_PLY_HEADER_BYTES",
    "MAX_PLY_PROPERTIES",
    "MAX_PLY_VERTICES",
    "MAX_POSITION_M",
    "MAX_RANGE_M",
    "MAX_TABLE_BYTES",
    "MIN_BIN_SIZE_M",
    "MEMORY_TARGET_BYTES",
    "check_geometry",
    "check_size",
    "declared_product",
]

MEMORY_TARGET_BYTES = 1 << 30
"""1 GiB: the most that refusing (or reading one frame of) any file may cost; what the fuzz
suite enforces with ``RLIMIT_AS`` on top of the interpreter's own footprint."""

MAX_ITEM_BYTES = 64 << 20
"""64 MiB: the largest single item a file may declare -- an Oculus message (``16 +
payloadSize``), a ``.oculus`` log item's stored payload and its inflated ``originalSize``,
an ARIS frame (``1024 + beams * samples``)."""

MAX_HEADER_BYTES = 64 << 10
"""64 KiB: the largest header a file may declare for itself (the ``.oculus`` file and item
``sizeHeader`` fields)."""

MAX_IMAGE_PIXELS = 1 << 24
"""16.8 Mpixel: the largest image a reader decodes -- a ping's ``n_bins * n_beams`` (Oculus
``nRanges * nBeams``, ARIS ``samples * beams``) and a fan PNG's ``width * height``, read
from the header before the pixels are decoded (64 MiB as float32)."""

MAX_CSV_BYTES = 64 << 20
"""64 MiB: the largest pose table (CSV) read into memory. Rows are stored compactly as they
are parsed: a table this size of the shortest rows (1.6 M poses) peaks at ~340 MB (measured,
interpreter included) and takes ~8 s on one core -- work in proportion to the file."""

MAX_TABLE_BYTES = 1 << 20
"""1 MiB: the largest beam angle table (an ARIS has at most 1,024 beams; the SDK's 128-beam
table with four columns is 3.6 KB). Read beside a recording, so it is bounded on its own."""

MAX_PLY_HEADER_BYTES = 64 << 10
"""64 KiB: the longest PLY header (``ply`` to ``end_header``)."""

MAX_PLY_PROPERTIES = 64
"""The most vertex properties a PLY may declare."""

MAX_PLY_VERTICES = 1 << 28
"""268 M: the most vertices a PLY may declare (the vertex data must also be in the file:
binary files are checked byte for byte, ASCII files against the bytes left)."""

# Limits of the map side, stated here with the others (gpumap.spec and gpumap.core.mapfile hold
# the values they enforce; tests/test_io.py checks that these agree with them).
MAX_GRID_VOXELS = 2**31 - 1
"""The most voxels a :class:`~gpumap.GridSpec` may have (int32 indexing on every backend)."""

MAX_MAP_META_BYTES = 1 << 20
"""1 MiB: the largest metadata member of a saved map."""

MAX_DEFLATE_RATIO = 1100
"""Deflate inflates at most ~1032 : 1; a member declaring more is refused before inflating."""


MIN_BIN_SIZE_M = 1e-5
"""10 um: the finest range bin a file may declare (imaging sonars resolve millimetres; a bin of
1e-300 m decoded fine and then overflowed the mapper's float32 ``1 / bin size``)."""

MAX_RANGE_M = 1e4
"""10 km: the farthest range a file may declare for a ping (``range_max_m``)."""

MAX_POSITION_M = 1e8
"""100,000 km: the farthest a sonar pose may lie from the world origin (each coordinate of its
translation). A finite but absurd pose (x = 1e200) overflowed the mapper's arithmetic and was
counted as mapped; every pose gpumap takes (``check_pose``, the ROS node's pose messages) is
refused beyond this, far past any survey (UTM northings stay under 1e7 m)."""


def check_geometry(spec, what: str = "the ping", *, offset: int | None = None,
                   path: str | None = None):
    """Refuse a sonar geometry read from a file whose bins or range are beyond the limits above.

    ``spec`` is a :class:`~gpumap.SonarSpec` (already valid as such); returned unchanged.

    Raises
    ------
    FormatError
        If ``spec.bin_size_m < MIN_BIN_SIZE_M`` or ``spec.range_max_m > MAX_RANGE_M``.
    """
    if not spec.bin_size_m >= MIN_BIN_SIZE_M:
        raise FormatError(f"expected range bins of at least {MIN_BIN_SIZE_M} m for {what} "
                          f"(gpumap.limits.MIN_BIN_SIZE_M), but they are {spec.bin_size_m:.3g} m",
                          offset, path)
    if not spec.range_max_m <= MAX_RANGE_M:
        raise FormatError(f"expected a range of at most {MAX_RANGE_M:g} m for {what} "
                          f"(gpumap.limits.MAX_RANGE_M), but it reaches {spec.range_max_m:.3g} m",
                          offset, path)
    return spec


def declared_product(*factors: int) -> int:
    """Exact product of sizes read from a file (Python ints: no overflow, unlike NumPy's)."""
    return math.prod(operator.index(f) for f in factors)


def check_size(
    declared: int,
    budget: int,
    what: str,
    *,
    available: int | None = None,
    unit: str = "bytes",
    offset: int | None = None,
    path: str | None = None,
) -> int:
    """Check a size a file declares against a budget (and what the file holds) before allocating.

    Parameters
    ----------
    declared : int
        The size, as the file states it (or a product of its fields, see
        :func:`declared_product`).
    budget : int
        The most gpumap allows for it (one of the constants above).
    what : str
        The field, for the message (``"payloadSize"``, ``"the fan picture"``).
    available : int, optional
        What the file still holds after the header (bytes); declaring more than that is a
        truncated or corrupt file.
    unit : str
        Unit of ``declared`` in the message.
    offset, path
        Where the field is, for the error.

    Returns
    -------
    int
        ``declared`` as a Python ``int``.

    Raises
    ------
    LimitError
        If ``declared > budget``.
    FormatError
        If ``declared`` is negative or more than ``available``.
    """
    n = operator.index(declared)
    if n < 0:
        raise FormatError(f"expected a size >= 0 for {what}, but got {n}", offset, path)
    if n > budget:
        raise LimitError(
            f"expected {what} of at most {budget:,} {unit} (gpumap.limits), but the file declares "
            f"{n:,}", offset, path,
        )
    if available is not None and n > available:
        raise FormatError(
            f"expected {what} of {n:,} {unit} as declared, but the file holds only {max(available, 0):,} "
            f"more bytes", offset, path,
        )
    return n
