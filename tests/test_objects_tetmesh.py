"""Tetrahedralization: valid meshes near the target size, volume preserved, cache behaviour, errors."""

import os

import numpy as np
import pytest
import trimesh

from defgraspnets.fem import TetMesh
from defgraspnets.objects import ObjectMeshError, get_object, tet_mesh, tetrahedralize
from defgraspnets.objects import tetmesh as TM


def _check(tet: TetMesh, surface: trimesh.Trimesh, target: int, node_tol: float, vol_tol: float):
    assert isinstance(tet, TetMesh)
    assert abs(tet.num_vertices / target - 1) <= node_tol, tet.num_vertices
    assert abs(tet.volume / surface.volume - 1) <= vol_tol
    assert np.all(tet.volumes > 0)
    boundary = tet.surface_trimesh()
    boundary.remove_unreferenced_vertices()
    assert boundary.is_watertight and boundary.is_winding_consistent and boundary.volume > 0
    # the boundary follows the input surface (within a few element sizes' chord error)
    lo, hi = tet.bounding_box
    np.testing.assert_allclose(lo, surface.bounds[0], atol=2e-3)
    np.testing.assert_allclose(hi, surface.bounds[1], atol=2e-3)


def test_gmsh_meets_target_and_volume(tmp_path):
    obj = get_object("cylinder_r20_h40")
    tet = tetrahedralize(obj.surface, target_nodes=800, mesher="gmsh", cache_dir=tmp_path, name="cyl")
    _check(tet, obj.surface, 800, 0.25, 0.03)
    assert tet.name == "cyl"


def test_ftetwild_meets_target_and_leaves_cwd_clean(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    obj = get_object("ellipsoid_20x20x20")
    tet = tetrahedralize(obj.surface, target_nodes=400, mesher="ftetwild", cache_dir=False)
    _check(tet, obj.surface, 400, 0.3, 0.04)
    assert os.listdir(tmp_path) == []  # fTetWild's __tracked_surface.stl went to a temporary directory
    assert os.getcwd() == str(tmp_path)


def test_cache_hit_returns_identical_mesh_without_remeshing(tmp_path, monkeypatch):
    first = tet_mesh("cuboid_30x30x30", target_nodes=300, mesher="gmsh", cache_dir=tmp_path)
    files = list(tmp_path.iterdir())
    assert len(files) == 1 and files[0].suffix == ".npz" and files[0].name.startswith("cuboid_30x30x30-")

    def forbidden(*args, **kwargs):
        raise AssertionError("re-meshed despite a cache entry")

    monkeypatch.setitem(TM._RUNNERS, "gmsh", forbidden)
    again = tet_mesh("cuboid_30x30x30", target_nodes=300, mesher="gmsh", cache_dir=tmp_path)
    np.testing.assert_array_equal(again.points, first.points)
    np.testing.assert_array_equal(again.tets, first.tets)
    # another setting is another entry (and here would need the mesher)
    with pytest.raises(AssertionError, match="re-meshed"):
        tet_mesh("cuboid_30x30x30", target_nodes=301, mesher="gmsh", cache_dir=tmp_path)
    # a corrupt entry is ignored and rewritten, never returned
    files[0].write_bytes(b"garbage")
    monkeypatch.undo()
    fresh = tet_mesh("cuboid_30x30x30", target_nodes=300, mesher="gmsh", cache_dir=tmp_path)
    assert fresh.num_vertices > 0
    assert sorted(p.suffix for p in tmp_path.iterdir()) == [".npz"]  # no temporary files left


def test_a_machine_without_the_mesher_uses_the_cache_of_any_mesher_version(tmp_path, monkeypatch, caplog):
    first = tet_mesh("cuboid_30x30x30", target_nodes=300, mesher="gmsh", cache_dir=tmp_path)

    def forbidden(*args, **kwargs):
        raise ModuleNotFoundError("the mesher is not installed here")

    monkeypatch.setitem(TM._RUNNERS, "gmsh", forbidden)
    monkeypatch.setattr(TM, "_mesher_version", lambda mesher: "unknown")
    with caplog.at_level("INFO", logger=TM._log.name):
        again = tet_mesh("cuboid_30x30x30", target_nodes=300, mesher="gmsh", cache_dir=tmp_path)
    np.testing.assert_array_equal(again.points, first.points)
    np.testing.assert_array_equal(again.tets, first.tets)
    assert "gmsh is not installed; using the cached mesh made with gmsh" in caplog.text
    # only the same surface with the same settings qualifies: other settings or another surface under the
    # same name would need the mesher
    with pytest.raises(ModuleNotFoundError):
        tet_mesh("cuboid_30x30x30", target_nodes=301, mesher="gmsh", cache_dir=tmp_path)
    other = get_object("cuboid_30x30x30").surface.copy()
    other.apply_scale(1.1)
    with pytest.raises(ModuleNotFoundError):
        tetrahedralize(other, target_nodes=300, mesher="gmsh", cache_dir=tmp_path, name="cuboid_30x30x30")
    assert len(list(tmp_path.iterdir())) == 1  # nothing written


def test_cache_dir_from_environment(tmp_path, monkeypatch):
    monkeypatch.setenv("DEFGRASPNETS_CACHE", str(tmp_path / "root"))
    assert TM.default_cache_dir() == tmp_path / "root" / "tetmeshes"
    tet_mesh("ellipsoid_20x20x20", target_nodes=250, mesher="gmsh")
    assert len(list((tmp_path / "root" / "tetmeshes").glob("ellipsoid_20x20x20-*.npz"))) == 1
    monkeypatch.delenv("DEFGRASPNETS_CACHE")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert TM.default_cache_dir() == tmp_path / "xdg" / "defgraspnets" / "tetmeshes"


def test_broken_inputs_raise_clear_errors(tmp_path):
    sphere = trimesh.creation.icosphere(2, radius=0.02)
    v = sphere.vertices.copy()
    v[0, 1] = np.nan
    with pytest.raises(ObjectMeshError, match="non-finite"):
        tetrahedralize((v, sphere.faces), cache_dir=False)
    open_surface = trimesh.Trimesh(sphere.vertices, sphere.faces[5:], process=False)
    with pytest.raises(ObjectMeshError, match="not watertight"):
        tetrahedralize(open_surface, cache_dir=False)
    with pytest.raises(KeyError, match="unknown mesher"):
        tetrahedralize(sphere, mesher="tetgen", cache_dir=False)
    with pytest.raises(KeyError, match="unknown gmsh options"):
        tetrahedralize(sphere, mesher="gmsh", epsilon_factor=0.1, cache_dir=False)
    with pytest.raises(ValueError, match="target_nodes"):
        tetrahedralize(sphere, target_nodes=2.5, cache_dir=False)
    with pytest.raises(KeyError, match="unknown object"):
        tet_mesh("no_such_object", cache_dir=tmp_path)


def test_volume_mismatch_is_reported(monkeypatch):
    # a mesher that loses part of the solid (here: returns a box 20 % smaller in each direction)
    obj = get_object("cuboid_30x30x30")

    def shrunken(mesh, edge_length, options):
        box = TetMesh.box(size=(0.024,) * 3, divisions=(4, 4, 4), origin=(-0.012,) * 3)
        return np.asarray(box.points), np.asarray(box.tets)

    monkeypatch.setitem(TM._RUNNERS, "gmsh", shrunken)
    with pytest.raises(ObjectMeshError, match=r"differs from the surface volume .* by -4[0-9]\.[0-9]%"):
        tetrahedralize(obj.surface, target_nodes=125, mesher="gmsh", cache_dir=False)


def test_pinched_tet_mesh_is_rejected(monkeypatch):
    # two tets sharing only an edge: valid elements, but the boundary is not a 2-manifold
    points = np.array(
        [[0, 0, 0], [0.01, 0, 0], [0, 0.01, 0], [0, 0, 0.01], [0, -0.01, 0], [0, 0, -0.01]], float
    )
    tets = np.array([[0, 1, 2, 3], [0, 1, 4, 5]])
    monkeypatch.setitem(TM._RUNNERS, "gmsh", lambda mesh, h, options: (points, tets))
    cube = trimesh.creation.box((0.02, 0.02, 0.02))
    with pytest.raises(ObjectMeshError, match="non-manifold edges.*touch along edges"):
        tetrahedralize(cube, target_nodes=6, mesher="gmsh", cache_dir=False, max_volume_error=1.0)
