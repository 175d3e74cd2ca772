"""gpumap: min-max occupancy mapping from imaging sonar, on GPU and CPU.

The public API::

    spec = gpumap.SonarSpec.uniform(hfov_deg=130, vfov_deg=20, n_beams=512, n_bins=400)
    grid = gpumap.GridSpec((-2, -1.5, -0.5), (2, 1.5, 0.5), voxel_size_m=0.03)
    mapper = gpumap.MinMaxMapper(spec, grid, "auto", gpumap.MapperParams(threshold=0.1))
    mapper.integrate(image, T_W_S)
    mapper.values()  # (nx, ny, nz) float32, NaN = never observed
    field = gpumap.DistanceField(mapper)  # metres to the nearest obstacle (unknown counts as one)
    field.update(); field.distance_at(points_W)
    res = gpumap.refine(mapper, images, poses)  # the surfaces the pings need (gpumap.layers.refine)
    res = gpumap.refine_saved("map.npz", "recording.oculus")  # the same from a saved map
"""

from gpumap.errors import BackendUnavailableError
from gpumap.spec import GridSpec, SonarSpec, SparseSpec

__all__ = ["BackendUnavailableError", "DistanceField", "GridSpec", "MapMemoryError", "MapperParams",
           "MinMaxMapper", "RefineOptions", "RefineResult", "SonarSpec", "SparseMinMaxMapper", "SparseSpec",
           "available_backends", "load_map", "merge_maps", "refine", "refine_saved"]
__version__ = "0.1.0"


def __getattr__(name: str):  # lazy: importing gpumap must not import warp or pyopencl
    if name in ("MinMaxMapper", "available_backends", "MapMemoryError"):
        from gpumap.core import mapper

        return getattr(mapper, name)
    if name == "MapperParams":
        from gpumap.core import params

        return params.MapperParams
    if name == "DistanceField":
        from gpumap.layers import distance

        return distance.DistanceField
    if name == "SparseMinMaxMapper":
        from gpumap.core import sparse

        return sparse.SparseMinMaxMapper
    if name in ("merge_maps", "load_map"):
        from gpumap.core import merge

        return getattr(merge, name)
    if name == "refine":  # the module, callable as its function refine() (see gpumap.layers.refine)
        import importlib

        return importlib.import_module("gpumap.layers.refine")
    if name in ("RefineOptions", "RefineResult", "refine_saved"):
        import importlib

        return getattr(importlib.import_module("gpumap.layers.refine"), name)
    raise AttributeError(f"module 'gpumap' has no attribute {name!r}")
