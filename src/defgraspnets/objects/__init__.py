"""Object geometry: procedural primitives, real-world meshes shipped by pip packages,
tetrahedralization with a disk cache."""

from .primitives import CATEGORIES, PRIMITIVES, PrimitiveSpec, build_primitive
from .real import (
    ASSETS_ENV,
    REAL_OBJECTS,
    MissingAssetPackageError,
    RealMeshSpec,
    export_real_assets,
    load_mesh_file,
    load_real_object,
)
from .registry import OBJECT_SETS, SOURCES, ObjectModel, get_object, list_objects, object_set, tet_mesh
from .surface import ObjectMeshError, check_surface, repair_surface
from .tetmesh import MESHERS, default_cache_dir, tetrahedralize

__all__ = [
    "ASSETS_ENV",
    "CATEGORIES",
    "MESHERS",
    "OBJECT_SETS",
    "PRIMITIVES",
    "REAL_OBJECTS",
    "SOURCES",
    "MissingAssetPackageError",
    "ObjectMeshError",
    "ObjectModel",
    "PrimitiveSpec",
    "RealMeshSpec",
    "build_primitive",
    "check_surface",
    "default_cache_dir",
    "export_real_assets",
    "get_object",
    "list_objects",
    "load_mesh_file",
    "load_real_object",
    "object_set",
    "repair_surface",
    "tet_mesh",
    "tetrahedralize",
]
