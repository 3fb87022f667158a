"""Real-world meshes from pip packages: located without import, repaired, scaled, clear errors."""

import importlib.util
from pathlib import Path

import numpy as np
import pytest
import trimesh

from defgraspnets.objects import REAL_OBJECTS, MissingAssetPackageError, ObjectMeshError, load_mesh_file
from defgraspnets.objects import real as R


def _installed(package):
    return importlib.util.find_spec(package) is not None


def test_specs_are_complete():
    assert len(REAL_OBJECTS) >= 8
    for spec in REAL_OBJECTS.values():
        assert spec.license and spec.tested_version and spec.distribution and spec.path
        assert spec.target_extent is None or 0.03 < spec.target_extent < 0.2


def test_missing_package_names_the_pip_install(monkeypatch):
    real_find_spec = importlib.util.find_spec

    def fake_find_spec(name, *args, **kwargs):
        return None if name in ("robosuite", "pybullet_data") else real_find_spec(name, *args, **kwargs)

    monkeypatch.setattr(importlib.util, "find_spec", fake_find_spec)
    with pytest.raises(MissingAssetPackageError, match="pip install pybullet") as err:
        R.load_real_object("rubber_duck")
    assert isinstance(err.value, ModuleNotFoundError)
    with pytest.raises(MissingAssetPackageError, match="pip install robosuite --no-deps"):
        R.load_real_object("lemon")
    with pytest.raises(KeyError, match="unknown real object"):
        R.load_real_object("banana")


def test_load_mesh_file_scales_centres_and_repairs(tmp_path):
    box = trimesh.creation.box((40.0, 30.0, 20.0))  # millimetres, as many CAD exports
    box.apply_translation([100.0, 5.0, 0.0])
    soup = trimesh.Trimesh(
        box.vertices[box.faces].reshape(-1, 3), np.arange(36).reshape(-1, 3), process=False
    )
    path = tmp_path / "box.stl"
    soup.export(path)
    mesh, scale = load_mesh_file(path, scale=1e-3)
    assert scale == 1e-3 and mesh.is_watertight
    np.testing.assert_allclose(mesh.extents, [0.04, 0.03, 0.02], rtol=1e-6)
    np.testing.assert_allclose(mesh.center_mass, 0.0, atol=1e-12)
    mesh, scale = load_mesh_file(path, target_extent=0.08)
    assert mesh.extents.max() == pytest.approx(0.08)


def test_unreadable_and_open_files_raise(tmp_path):
    with pytest.raises(FileNotFoundError, match="not found"):
        load_mesh_file(tmp_path / "nope.obj")
    bad = tmp_path / "bad.obj"
    bad.write_text("this is not a mesh\n")
    with pytest.raises(ObjectMeshError):
        load_mesh_file(bad)
    sphere = trimesh.creation.icosphere(3, radius=0.03)
    open_cup = trimesh.Trimesh(
        sphere.vertices, sphere.faces[sphere.triangles_center[:, 2] < 0.0], process=False
    )
    path = tmp_path / "cup.ply"
    open_cup.export(path)
    with pytest.raises(ObjectMeshError, match="not watertight"):
        load_mesh_file(path)


@pytest.mark.parametrize("name", sorted(REAL_OBJECTS))
def test_real_objects_load_when_installed(name):
    spec = REAL_OBJECTS[name]
    if not _installed(spec.package):
        pytest.skip(f"{spec.distribution} not installed")
    mesh, meta = R.load_real_object(name)
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0 and mesh.body_count == 1
    np.testing.assert_allclose(mesh.center_mass, 0.0, atol=1e-7)
    ext = np.sort(mesh.extents)
    assert 0.01 < ext[0] < 0.075 and ext[2] < 0.2  # graspable across its thinnest side
    if spec.target_extent is not None:
        assert ext[2] == pytest.approx(spec.target_extent)
    assert meta["version"] and len(meta["file_sha256"]) == 64 and meta["path_in_package"] == spec.path


def test_unrepairable_shipped_mesh_is_rejected():
    if not _installed("robosuite"):
        pytest.skip("robosuite not installed")
    spec = R.RealMeshSpec("bottle", "container", "robosuite", "robosuite", "1.5.2",
                          "models/assets/objects/meshes/bottle.stl", "MIT", None, "bottle")  # fmt: skip
    with pytest.raises(ObjectMeshError, match="non-manifold"):
        load_mesh_file(R.asset_path(spec), "bottle")


def test_an_asset_directory_serves_a_machine_without_the_packages(tmp_path, monkeypatch):
    """export_real_assets copies the files out of the installed packages; where the packages are
    missing, $DEFGRASPNETS_ASSETS serves the same objects from those copies (same bytes, same mesh)."""
    import hashlib
    import types

    site = tmp_path / "site"
    duck = site / "pybullet_data" / "duck.obj"
    lemon = site / "robosuite" / "models/assets/objects/meshes/lemon.stl"
    for path, shape in (
        (duck, trimesh.creation.icosphere(2, 30.0)),
        (lemon, trimesh.creation.capsule(40.0, 15.0)),
    ):
        path.parent.mkdir(parents=True)
        shape.export(path)
    real_find_spec = importlib.util.find_spec
    installed = {"pybullet_data": True, "robosuite": True}

    def fake_find_spec(name, *args, **kwargs):
        if name in installed:
            return (
                types.SimpleNamespace(submodule_search_locations=[str(site / name)])
                if installed[name]
                else None
            )
        return real_find_spec(name, *args, **kwargs)

    monkeypatch.setattr(importlib.util, "find_spec", fake_find_spec)
    monkeypatch.delenv(R.ASSETS_ENV, raising=False)
    from_packages = {n: R.load_real_object(n) for n in ("rubber_duck", "lemon")}
    written = R.export_real_assets(tmp_path / "assets", ["rubber_duck", "lemon"])
    assert written == [
        tmp_path / "assets/pybullet_data/duck.obj",
        tmp_path / "assets/robosuite" / lemon.relative_to(site / "robosuite"),
    ]
    assert [p.read_bytes() for p in written] == [duck.read_bytes(), lemon.read_bytes()]
    assert not list((tmp_path / "assets").rglob("*.partial"))

    installed.update(pybullet_data=False, robosuite=False)  # another machine: no packages
    with pytest.raises(MissingAssetPackageError, match=R.ASSETS_ENV):
        R.load_real_object("rubber_duck")
    with pytest.raises(MissingAssetPackageError, match="export_real_assets"):
        R.export_real_assets(tmp_path / "more", ["lemon"])
    monkeypatch.setenv(R.ASSETS_ENV, str(tmp_path / "assets"))
    for name, (mesh, meta) in from_packages.items():
        copy, copy_meta = R.load_real_object(name)
        np.testing.assert_array_equal(copy.vertices, mesh.vertices)
        np.testing.assert_array_equal(copy.faces, mesh.faces)
        assert copy_meta["file_sha256"] == meta["file_sha256"]
        assert (
            copy_meta["file_sha256"]
            == hashlib.sha256(Path(written[0 if name == "rubber_duck" else 1]).read_bytes()).hexdigest()
        )
    assert max(from_packages["rubber_duck"][0].extents) == pytest.approx(0.08)
    with pytest.raises(MissingAssetPackageError, match="has no pybullet_data/bunny.obj"):
        R.load_real_object("bunny")  # not exported
    with pytest.raises(KeyError, match="unknown real objects"):
        R.export_real_assets(tmp_path / "assets", ["banana"])


def test_export_script_rejects_unknown_keys_and_names(tmp_path):
    import subprocess
    import sys

    script = Path(__file__).resolve().parents[1] / "scripts" / "export_real_assets.py"
    bad_key = subprocess.run(
        [sys.executable, str(script), "bogus=1"], capture_output=True, text=True, cwd=tmp_path
    )
    assert bad_key.returncode != 0 and "bogus" in bad_key.stderr
    bad_name = subprocess.run(
        [sys.executable, str(script), f"out={tmp_path / 'a'}", "names=[banana]"],
        capture_output=True,
        text=True,
        cwd=tmp_path,
    )
    assert bad_name.returncode != 0 and "unknown real objects ['banana']" in bad_name.stderr
    assert not (tmp_path / "a").exists()
