"""Real-world object meshes shipped inside pip-installable packages.

No dataset is downloaded at run time: each mesh is a file inside the wheel of an installed package,
located with :func:`importlib.util.find_spec` (the package is *not* imported). If the package is
missing, :class:`MissingAssetPackageError` says which ``pip install`` provides it. Both source
packages are optional extras of defgraspnets:

==============  =========  ======  ==========================================================
pip package     version    size    objects (license)
==============  =========  ======  ==========================================================
``pybullet``    3.2.7      103 MB  ``pybullet_data``: rubber duck, Stanford bunny, soccer ball,
                                   torus (zlib; no runtime dependencies)
``robosuite``   1.5.2      157 MB  ``robosuite/models/assets/objects``: lemon, bread, milk carton,
                                   cereal box, soda can (MIT; the assets need only
                                   ``pip install --no-deps robosuite``)
==============  =========  ======  ==========================================================

**Asset directory**: on a machine without these packages (e.g. a GPU machine for the dataset run),
``$DEFGRASPNETS_ASSETS`` may name a directory holding copies of the files as
``<package>/<path in package>``, written by :func:`export_real_assets` (``python
scripts/export_real_assets.py out=DIR``) where the packages are installed; an installed package is
always preferred, and the file's SHA-256 is in the object's metadata either way.

Loading (:func:`load_real_object`): trimesh reads the file, :func:`repair_surface` merges seam
vertices, drops degenerate faces, closes small holes and orients the winding outward (or raises
:class:`ObjectMeshError`), the mesh is scaled from file units to a realistic size in metres, and its
volume centroid is moved to the origin. Files that cannot be made a closed manifold (e.g. robosuite's
``bottle.stl`` with non-manifold edges, pybullet's two-body ``mug.obj``) are not listed.
"""

from __future__ import annotations

import hashlib
import importlib.metadata
import importlib.util
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import trimesh

from .surface import ObjectMeshError, repair_surface

__all__ = [
    "ASSETS_ENV",
    "REAL_OBJECTS",
    "MissingAssetPackageError",
    "RealMeshSpec",
    "asset_path",
    "export_real_assets",
    "load_mesh_file",
    "load_real_object",
]


ASSETS_ENV = "DEFGRASPNETS_ASSETS"
"""Environment variable naming a directory of asset copies, ``<package>/<path in package>``."""


class MissingAssetPackageError(ModuleNotFoundError):
    """The pip package that ships an object's mesh file is not installed."""


@dataclass(frozen=True)
class RealMeshSpec:
    """Where a real-world mesh lives and how it is scaled.

    Attributes:
        name: registry name.
        category: coarse geometric/semantic class (fruit, food, container, toy).
        package: importable top-level package that contains the file (found without importing it).
        distribution: the pip distribution to install (``pip install <distribution>``).
        tested_version: the distribution version whose file was checked.
        path: file path inside the package directory.
        license: license of the distribution and, where known, the asset's origin.
        target_extent: the largest bounding-box side after scaling [m]; None keeps the file's units
            (already metres).
        description: what the object is.
    """

    name: str
    category: str
    package: str
    distribution: str
    tested_version: str
    path: str
    license: str
    target_extent: float | None
    description: str


_ROBOSUITE_LICENSE = (
    "MIT (robosuite, Stanford Vision and Learning Lab and UT Robot Perception and Learning Lab)"
)
_PYBULLET_LICENSE = "zlib (pybullet / Bullet Physics SDK)"

REAL_OBJECTS: dict[str, RealMeshSpec] = {
    s.name: s
    for s in [
        RealMeshSpec(
            "lemon", "fruit", "robosuite", "robosuite", "1.5.2",
            "models/assets/objects/meshes/lemon.stl", _ROBOSUITE_LICENSE, 0.065,
            "lemon, scaled to 65 mm long",
        ),
        RealMeshSpec(
            "bread_roll", "food", "robosuite", "robosuite", "1.5.2",
            "models/assets/objects/meshes/bread.stl", _ROBOSUITE_LICENSE, None,
            "bread roll, 60 x 50 x 60 mm as shipped",
        ),
        RealMeshSpec(
            "milk_carton", "container", "robosuite", "robosuite", "1.5.2",
            "models/assets/objects/meshes/milk.stl", _ROBOSUITE_LICENSE, None,
            "small milk carton, 44 x 44 x 160 mm as shipped",
        ),
        RealMeshSpec(
            "cereal_box", "container", "robosuite", "robosuite", "1.5.2",
            "models/assets/objects/meshes/cereal.stl", _ROBOSUITE_LICENSE, None,
            "cereal box, 100 x 30 x 150 mm as shipped",
        ),
        RealMeshSpec(
            "soda_can", "container", "robosuite", "robosuite", "1.5.2",
            "models/assets/objects/meshes/can.obj", _ROBOSUITE_LICENSE, None,
            "soda can, 50 mm diameter x 80 mm as shipped",
        ),
        RealMeshSpec(
            "rubber_duck", "toy", "pybullet_data", "pybullet", "3.2.7",
            "duck.obj", _PYBULLET_LICENSE + "; model: COLLADA 'duck' sample (Sony Comp. Entertainment)", 0.08,
            "rubber duck toy, scaled to 80 mm long",
        ),
        RealMeshSpec(
            "bunny", "toy", "pybullet_data", "pybullet", "3.2.7",
            "bunny.obj", _PYBULLET_LICENSE + "; model: Stanford 3D Scanning Repository bunny", 0.08,
            "Stanford bunny as a soft toy, scaled to 80 mm tall",
        ),
        RealMeshSpec(
            "foam_ball", "toy", "pybullet_data", "pybullet", "3.2.7",
            "soccerball.obj", _PYBULLET_LICENSE, 0.065,
            "soccer-ball mesh as a 65 mm foam ball",
        ),
        RealMeshSpec(
            "bagel", "food", "pybullet_data", "pybullet", "3.2.7",
            "torus/torus_textured.obj", _PYBULLET_LICENSE, 0.09,
            "torus mesh as a 90 mm bagel",
        ),
    ]
}  # fmt: skip
"""The real-world objects, by name."""


def asset_path(spec: RealMeshSpec) -> Path:
    """Path of the mesh file inside its installed package.

    Raises:
        MissingAssetPackageError: if the package is not installed (names the ``pip install``).
        FileNotFoundError: if the package is installed but lacks the file (another version).
    """
    found = importlib.util.find_spec(spec.package)
    if found is None or not found.submodule_search_locations:
        copies = os.environ.get(ASSETS_ENV)
        if copies:
            path = Path(copies).expanduser() / spec.package / spec.path
            if path.is_file():
                return path
        raise MissingAssetPackageError(
            f"real object {spec.name!r} needs the mesh file {spec.path} from the package {spec.package!r}, "
            f"which is not installed: pip install {spec.distribution}"
            + (" --no-deps  (only the asset files are used)" if spec.distribution == "robosuite" else "")
            + f", or set {ASSETS_ENV} to a directory of copies (export_real_assets)"
            + (f"; {ASSETS_ENV}={copies} has no {spec.package}/{spec.path}" if copies else ""),
            name=spec.package,
        )
    for root in found.submodule_search_locations:
        path = Path(root) / spec.path
        if path.is_file():
            return path
    raise FileNotFoundError(
        f"real object {spec.name!r}: {spec.path} not found in the installed package {spec.package!r} "
        f"({', '.join(found.submodule_search_locations)}); it was checked with {spec.distribution} "
        f"{spec.tested_version}"
    )


def export_real_assets(out_dir, names=None) -> list[Path]:
    """Copy the mesh files of the real objects ``names`` (None: all) from their installed packages to
    ``out_dir/<package>/<path in package>``, the layout ``$DEFGRASPNETS_ASSETS`` reads (module
    docstring). Each file is written to a temporary name and renamed, so a stopped export leaves no
    partial file.

    Returns:
        the written paths, in the order of ``names``.
    Raises:
        KeyError: unknown name; MissingAssetPackageError / FileNotFoundError: as :func:`asset_path`.
    """
    names = sorted(REAL_OBJECTS) if names is None else list(names)
    unknown = [n for n in names if n not in REAL_OBJECTS]
    if unknown:
        raise KeyError(f"unknown real objects {unknown}; known: {', '.join(sorted(REAL_OBJECTS))}")
    out_dir = Path(out_dir)
    written = []
    for name in names:
        spec = REAL_OBJECTS[name]
        source = asset_path(spec)
        target = out_dir / spec.package / spec.path
        if source.resolve() != target.resolve():
            target.parent.mkdir(parents=True, exist_ok=True)
            partial = target.with_name(target.name + ".partial")
            shutil.copyfile(source, partial)
            os.replace(partial, target)
        written.append(target)
    return written


def _distribution_version(distribution: str) -> str | None:
    try:
        return importlib.metadata.version(distribution)
    except importlib.metadata.PackageNotFoundError:
        return None


def load_mesh_file(path, name: str | None = None, target_extent: float | None = None, scale: float = 1.0):
    """Load, repair, scale and centre a closed surface from any format trimesh reads.

    The mesh is scaled by ``scale`` (file units to metres), or, if ``target_extent`` is given, so that
    its largest bounding-box side equals ``target_extent`` [m]; then translated so that its volume
    centroid is the origin.

    Returns:
        (mesh, scale factor applied).
    Raises:
        FileNotFoundError: missing file; ObjectMeshError: unreadable, empty or unrepairable surface.
    """
    path = Path(path)
    name = name or path.stem
    if not path.is_file():
        raise FileNotFoundError(f"{name}: mesh file not found: {path}")
    try:
        loaded = trimesh.load(path, force="mesh", process=False, skip_materials=True)
    except Exception as exc:  # trimesh raises many types for malformed files
        raise ObjectMeshError(f"{name}: trimesh could not read {path}: {exc}") from exc
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise ObjectMeshError(f"{name}: {path} holds no triangles")
    mesh = repair_surface(loaded, name)
    if target_extent is not None:
        if not target_extent > 0:
            raise ValueError(f"{name}: target_extent must be positive, got {target_extent}")
        scale = target_extent / float(mesh.extents.max())
    mesh.apply_scale(scale)
    mesh.apply_translation(-mesh.center_mass)
    return mesh, float(scale)


def load_real_object(name: str) -> tuple[trimesh.Trimesh, dict]:
    """The repaired, scaled surface of real object ``name`` and its provenance metadata.

    Raises:
        KeyError: unknown name; MissingAssetPackageError: source package not installed;
        ObjectMeshError: the file cannot be made a closed manifold.
    """
    if name not in REAL_OBJECTS:
        raise KeyError(f"unknown real object {name!r}; known: {', '.join(sorted(REAL_OBJECTS))}")
    spec = REAL_OBJECTS[name]
    path = asset_path(spec)
    mesh, scale = load_mesh_file(path, name, target_extent=spec.target_extent)
    meta = {
        "package": spec.package,
        "distribution": spec.distribution,
        "version": _distribution_version(spec.distribution),
        "tested_version": spec.tested_version,
        "path_in_package": spec.path,
        "file_sha256": hashlib.sha256(path.read_bytes()).hexdigest(),
        "license": spec.license,
        "scale": scale,
        "description": spec.description,
    }
    return mesh, meta
