"""Maps that allocate blocks where pings look: the former ``SparseMinMaxMapper``'s names.

One :class:`gpumap.MinMaxMapper` now serves every storage (see :mod:`gpumap.core.mapper`): given a
:class:`SparseSpec` (or ``sparse=True``) it allocates its blocks on demand. The names below stay
for code written against the earlier API.
"""

from __future__ import annotations

from gpumap.core.mapper import FILE_FORMAT, MapMemoryError, MinMaxMapper
from gpumap.core.params import MapperParams
from gpumap.spec import SonarSpec, SparseSpec

__all__ = ["FILE_FORMAT", "MapMemoryError", "SparseMinMaxMapper", "SparseSpec"]


class SparseMinMaxMapper(MinMaxMapper):
    """``MinMaxMapper(spec, sparse, ...)`` for a :class:`SparseSpec` ``sparse``: the same mapper,
    under the name and signature it had when it was a class of its own."""

    _on_demand = True

    def __init__(self, spec: SonarSpec, sparse: SparseSpec, backend: str = "auto",
                 params: MapperParams | None = None, *, device_index: int | None = None) -> None:
        if not isinstance(sparse, SparseSpec):
            raise TypeError(f"Expected a gpumap.SparseSpec for 'sparse', but got {type(sparse).__name__}")
        params = MapperParams() if params is None else params
        if getattr(params, "method", "gather") != "gather":
            raise ValueError(
                f"Expected method='gather' (the sparse map has no template method), but got {params.method!r}"
            )
        super().__init__(spec, sparse, backend, params, device_index=device_index)
