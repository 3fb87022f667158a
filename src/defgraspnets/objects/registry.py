"""Registry of named objects: procedural primitives and real-world meshes, and named object sets.

``get_object(name)`` returns an :class:`ObjectModel` (closed surface in metres, centroid at the
origin, plus category, source, license and dimensions); ``tet_mesh(name, ...)`` its cached
tetrahedralization. Object sets by name (also as Hydra configs ``configs/objects/<set>.yaml``):

- ``"ci_small"``: three small primitives that mesh in a few seconds (tests, README demo);
- ``"primitives"``: all procedural primitives (:data:`~defgraspnets.objects.primitives.PRIMITIVES`);
- ``"real"``: the real-world meshes (:data:`~defgraspnets.objects.real.REAL_OBJECTS`; their source
  packages are optional);
- ``"all"``: primitives then real objects.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np
import trimesh

from .primitives import CATEGORIES, DEFAULT_EDGE_LENGTH, PRIMITIVES
from .real import REAL_OBJECTS, load_real_object
from .tetmesh import tetrahedralize

__all__ = ["OBJECT_SETS", "SOURCES", "ObjectModel", "get_object", "list_objects", "object_set", "tet_mesh"]

SOURCES = ("primitive", "real")
PRIMITIVE_LICENSE = "MIT (defgraspnets, procedurally generated)"
OBJECT_SETS = ("ci_small", "primitives", "real", "all")
_CI_SMALL = ("ellipsoid_20x20x20", "cylinder_r20_h40", "cuboid_30x30x30")


@dataclass
class ObjectModel:
    """A deformable object's geometry and provenance.

    Attributes:
        name: registry name.
        surface: closed, outward-oriented triangle surface, volume centroid at the origin [m].
        category: geometric category (primitives) or kind (real objects: fruit, food, container, toy).
        source: ``"primitive"`` or ``"real"``.
        license: license of the geometry.
        dims: (3,) bounding-box side lengths [m].
        volume: enclosed volume [m^3]: exact for primitives (the smooth shape), of the mesh otherwise.
        metadata: builder parameters (primitives) or package, version, path, file hash, scale (real).
    """

    name: str
    surface: trimesh.Trimesh
    category: str
    source: str
    license: str
    dims: np.ndarray
    volume: float
    metadata: dict = field(default_factory=dict)


def list_objects(category: str | None = None, source: str | None = None) -> list[str]:
    """Names of the registered objects, optionally of one ``category`` and/or ``source``."""
    if source is not None and source not in SOURCES:
        raise ValueError(f"unknown source {source!r}; choose from {', '.join(SOURCES)}")
    real_categories = sorted({s.category for s in REAL_OBJECTS.values()})
    if category is not None and category not in CATEGORIES and category not in real_categories:
        raise ValueError(
            f"unknown category {category!r}; primitives: {', '.join(CATEGORIES)}; "
            f"real: {', '.join(real_categories)}"
        )
    names = []
    if source in (None, "primitive"):
        names += [n for n, s in PRIMITIVES.items() if category in (None, s.category)]
    if source in (None, "real"):
        names += [n for n, s in REAL_OBJECTS.items() if category in (None, s.category)]
    return names


def object_set(name: str) -> list[str]:
    """Object names of a named set: ``ci_small``, ``primitives``, ``real`` or ``all``."""
    if name == "ci_small":
        return list(_CI_SMALL)
    if name == "primitives":
        return list_objects(source="primitive")
    if name == "real":
        return list_objects(source="real")
    if name == "all":
        return list_objects()
    raise KeyError(f"unknown object set {name!r}; choose from {', '.join(OBJECT_SETS)}")


@lru_cache(maxsize=128)
def _build(name: str, edge_length: float) -> ObjectModel:
    if name in PRIMITIVES:
        spec = PRIMITIVES[name]
        mesh, volume = spec.build(edge_length)
        return ObjectModel(
            name, mesh, spec.category, "primitive", PRIMITIVE_LICENSE, np.asarray(mesh.extents), volume,
            {"params": dict(spec.params), "edge_length": edge_length},
        )  # fmt: skip
    spec = REAL_OBJECTS[name]
    mesh, meta = load_real_object(name)
    return ObjectModel(
        name, mesh, spec.category, "real", spec.license, np.asarray(mesh.extents), float(mesh.volume), meta
    )


def get_object(name: str, edge_length: float = DEFAULT_EDGE_LENGTH) -> ObjectModel:
    """The object ``name`` (a fresh copy; primitives tessellated at ``edge_length`` [m]).

    Raises:
        KeyError: unknown name (the message lists the sets to choose from);
        MissingAssetPackageError: a real object's source package is not installed;
        ObjectMeshError: its file cannot be repaired into a closed manifold.
    """
    if not isinstance(name, str):
        raise TypeError(
            f"object name must be a string (see defgraspnets.objects.list_objects()), got {name!r}"
        )
    if name not in PRIMITIVES and name not in REAL_OBJECTS:
        close = [n for n in list_objects() if name.split("_")[0] in n][:5]
        hint = f"; similar: {', '.join(close)}" if close else ""
        raise KeyError(
            f"unknown object {name!r}: not among the {len(PRIMITIVES)} primitives or "
            f"{len(REAL_OBJECTS)} real "
            f"objects (see defgraspnets.objects.list_objects()){hint}"
        )
    model = _build(name, float(edge_length))
    return ObjectModel(
        model.name, model.surface.copy(), model.category, model.source, model.license, model.dims.copy(),
        model.volume, dict(model.metadata),
    )  # fmt: skip


def tet_mesh(name: str, target_nodes: int = 1000, mesher: str = "ftetwild", cache_dir=None, **kwargs):
    """The tetrahedral mesh of object ``name`` with about ``target_nodes`` vertices (cached on disk).

    See :func:`~defgraspnets.objects.tetmesh.tetrahedralize` for ``mesher``, ``cache_dir`` and the
    other keyword arguments.
    """
    return tetrahedralize(
        get_object(name).surface,
        target_nodes=target_nodes,
        mesher=mesher,
        cache_dir=cache_dir,
        name=name,
        **kwargs,
    )
