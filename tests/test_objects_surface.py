"""Surface validation and repair: what is fixed, and what is rejected with a clear error."""

import numpy as np
import pytest
import trimesh

from defgraspnets.objects import ObjectMeshError, check_surface, repair_surface
from defgraspnets.objects.surface import as_trimesh, boundary_loops, surface_hash


def _box():
    return trimesh.creation.box((0.04, 0.03, 0.02))


def test_nan_vertices_rejected():
    m = _box()
    v = m.vertices.copy()
    v[3] = np.nan
    with pytest.raises(ObjectMeshError, match="non-finite"):
        repair_surface((v, m.faces), "nanbox")


def test_bad_shapes_rejected():
    with pytest.raises(ObjectMeshError, match="vertices must have shape"):
        as_trimesh((np.zeros((4, 2)), np.zeros((1, 3), int)))
    with pytest.raises(ObjectMeshError, match="face indices"):
        as_trimesh((np.zeros((4, 3)), np.array([[0, 1, 7]])))
    with pytest.raises(ObjectMeshError, match="expected a trimesh"):
        as_trimesh(42)


def test_inverted_winding_is_fixed():
    m = _box()
    inv = trimesh.Trimesh(m.vertices, m.faces[:, ::-1], process=False)
    assert inv.volume < 0
    with pytest.raises(ObjectMeshError, match="not positive"):
        check_surface(inv)
    fixed = repair_surface(inv)
    assert fixed.volume == pytest.approx(0.04 * 0.03 * 0.02)


def test_seam_duplicates_are_merged():
    m = trimesh.creation.icosphere(2, radius=0.03)
    # split every face into its own vertices, as texture seams in OBJ files do
    soup = trimesh.Trimesh(
        m.vertices[m.faces].reshape(-1, 3), np.arange(3 * len(m.faces)).reshape(-1, 3), process=False
    )
    assert not soup.is_watertight
    fixed = repair_surface(soup)
    assert len(fixed.vertices) == len(m.vertices) and fixed.is_watertight


def test_small_hole_filled_large_opening_rejected():
    m = trimesh.creation.icosphere(3, radius=0.03)
    small = trimesh.Trimesh(m.vertices, m.faces[1:], process=False)  # one missing triangle
    assert len(boundary_loops(small.faces)) == 1
    fixed = repair_surface(small)
    assert fixed.volume == pytest.approx(m.volume, rel=1e-3)
    # an open hemisphere-sized cut is not a hole to paper over
    keep = m.triangles_center[:, 2] < 0.01
    cup = trimesh.Trimesh(m.vertices, m.faces[keep], process=False)
    with pytest.raises(ObjectMeshError, match="not watertight"):
        repair_surface(cup, "cup")
    with pytest.raises(ObjectMeshError, match="not watertight"):
        repair_surface(small, fill_holes=False)


def test_zero_area_cap_triangles_are_flipped_away():
    # a square split into a cap: vertex 4 lies on the edge 0-2 of the top face
    m = _box()
    v = m.vertices.copy()
    top = np.nonzero(np.all(np.isclose(v[m.faces][:, :, 2], 0.01), axis=1))[0]
    f = m.faces.copy()
    a, b, c = f[top[0]]
    # put a new vertex in the middle of edge (a, b) and split face top[0] into a cap + a triangle
    mid = (v[a] + v[b]) / 2
    v = np.vstack([v, mid])
    k = len(v) - 1
    f = np.vstack(
        [np.delete(f, top[0], axis=0), [[a, k, c], [k, b, c], [a, b, k]]]
    )  # (a, b, k) has zero area
    mesh = trimesh.Trimesh(v, f, process=False)
    with pytest.raises(ObjectMeshError):
        check_surface(mesh)
    fixed = repair_surface(mesh)
    assert fixed.volume == pytest.approx(0.04 * 0.03 * 0.02, rel=1e-12)
    # a degenerate triangle (b, a, b) on the cap's long edge (as vertex merging leaves in robosuite's
    # handles.stl) is no flip partner: the cap still flips with its real neighbour, the triangle is dropped
    fixed = repair_surface(trimesh.Trimesh(v, np.vstack([f, [[b, a, b]]]), process=False))
    assert fixed.volume == pytest.approx(0.04 * 0.03 * 0.02, rel=1e-12)


def test_two_bodies_and_nonmanifold_rejected():
    a = trimesh.creation.box((0.02, 0.02, 0.02))
    b = trimesh.creation.box((0.02, 0.02, 0.02))
    b.apply_translation([0.05, 0, 0])
    with pytest.raises(ObjectMeshError, match="2 disconnected bodies"):
        repair_surface(trimesh.util.concatenate([a, b]))
    # three triangles on one edge: a fin glued to a box
    v = np.vstack([a.vertices, [[0.0, 0.0, 0.05]]])
    e = a.edges_unique[0]
    f = np.vstack([a.faces, [[e[0], e[1], len(v) - 1]]])
    with pytest.raises(ObjectMeshError, match="non-manifold"):
        repair_surface((v, f), "fin")


def test_surface_hash_changes_with_geometry_only():
    m = _box()
    assert surface_hash(m) == surface_hash(m.copy())
    moved = m.copy()
    moved.apply_translation([1e-6, 0, 0])
    assert surface_hash(moved) != surface_hash(m)
