"""Known object models: packaged YCB meshes, exact and voxel-cached signed distance."""
from .known_object import DEFAULT_SDF_PADDING, DEFAULT_SDF_RESOLUTION, KnownObject
from .registry import available, load
from .sdf_cache import VoxelSDF, cache_dir

__all__ = [
    "KnownObject",
    "VoxelSDF",
    "available",
    "cache_dir",
    "load",
    "DEFAULT_SDF_RESOLUTION",
    "DEFAULT_SDF_PADDING",
]
