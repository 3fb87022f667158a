"""TetMesh: geometry, boundary, masses, and clear errors for broken meshes."""

import numpy as np
import pytest

from defgraspnets.fem import MeshError, TetMesh

UNIT_TET = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=float)


def test_box_geometry_and_boundary():
    m = TetMesh.box(size=(0.02, 0.03, 0.04), divisions=(2, 3, 4))
    assert m.volume == pytest.approx(0.02 * 0.03 * 0.04, rel=1e-12)
    assert np.all(m.volumes > 0)
    # boundary: closed, outward, total area of the box
    surf = m.surface_trimesh()
    assert surf.is_watertight
    assert m.vertex_areas.sum() == pytest.approx(2 * (0.02 * 0.03 + 0.02 * 0.04 + 0.03 * 0.04), rel=1e-12)
    c = m.points[m.surface_faces].mean(axis=1) - m.points.mean(axis=0)
    assert np.all(np.einsum("ij,ij->i", m.face_normals(), c) > 0)
    # interior vertices: (2-1)(3-1)(4-1) = 6
    assert m.num_vertices - len(m.surface_vertices) == 6
    # lumped masses sum to the total mass, centroid at the box centre
    assert m.vertex_masses(1000.0).sum() == pytest.approx(1000.0 * m.volume, rel=1e-12)
    np.testing.assert_allclose(m.center_of_mass(), [0.01, 0.015, 0.02], atol=1e-15)
    # every tet edge appears once; Euler characteristic of a ball-like tet mesh: V - E + F - T = 1
    faces = np.unique(
        np.sort(m.tets[:, [[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]]].reshape(-1, 3), axis=1), axis=0
    )
    assert m.num_vertices - len(m.edges) + len(faces) - m.num_tets == 1


def test_rest_shape_inverse_maps_edges_to_identity():
    m = TetMesh.box(divisions=(1, 1, 1))
    d = np.transpose(m.points[m.tets[:, 1:]] - m.points[m.tets[:, :1]], (0, 2, 1))
    np.testing.assert_allclose(d @ m.rest_shape_inverse, np.broadcast_to(np.eye(3), d.shape), atol=1e-12)


def test_vtu_round_trip(tmp_path):
    m = TetMesh.box(divisions=(2, 2, 2))
    vm = np.arange(m.num_vertices, dtype=float)
    m.save(tmp_path / "box.vtu", point_data={"von_mises": vm})
    back = TetMesh.load(tmp_path / "box.vtu")
    np.testing.assert_array_equal(back.tets, m.tets)
    np.testing.assert_allclose(back.points, m.points)
    import meshio

    np.testing.assert_allclose(meshio.read(tmp_path / "box.vtu").point_data["von_mises"], vm)


@pytest.mark.parametrize(
    "points, tets, message",
    [
        (np.vstack([UNIT_TET[:3], [np.nan, 0, 1]]), [[0, 1, 2, 3]], "non-finite"),
        (np.vstack([UNIT_TET[:3], [np.inf, 0, 1]]), [[0, 1, 2, 3]], "non-finite"),
        (UNIT_TET, [[0, 1, 2, 4]], "outside"),
        (UNIT_TET, [[0, 1, 2, -1]], "outside"),
        (UNIT_TET, [[0, 1, 1, 3]], "repeat a vertex"),
        (np.vstack([UNIT_TET, [5, 5, 5]]), [[0, 1, 2, 3]], "not used by any tet"),
        (UNIT_TET, [[0, 2, 1, 3]], "inverted"),
        (np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0.5, 0.5, 1e-9]]), [[0, 1, 2, 3]], "degenerate"),
        (UNIT_TET, [[0, 1, 2]], r"shape \(M, 4\)"),
        (UNIT_TET[:, :2], [[0, 1, 2, 3]], r"shape \(N, 3\)"),
        (UNIT_TET, [[0, 1, 2, 3.5]], "integers"),
        ("abc", [[0, 1, 2, 3]], r"points must be an \(N, 3\) array of numbers"),
        ([["0", "0", "x"]] * 4, [[0, 1, 2, 3]], "array of numbers"),
    ],
)
def test_broken_meshes_are_rejected_with_a_clear_error(points, tets, message):
    with pytest.raises(MeshError, match=message):
        TetMesh(points, tets)


def test_oriented_and_compacted_repair():
    m = TetMesh.oriented(UNIT_TET, [[0, 2, 1, 3]])
    assert m.volume == pytest.approx(1 / 6)
    m = TetMesh.compacted(np.vstack([[9, 9, 9], UNIT_TET]), [[1, 2, 3, 4]])
    assert m.num_vertices == 4


def test_missing_file_is_a_clear_error(tmp_path):
    with pytest.raises(FileNotFoundError, match="not found"):
        TetMesh.load(tmp_path / "nope.vtu")


@pytest.mark.parametrize("suffix", [".vtu", ".msh", ".vtk"])
def test_unreadable_file_is_a_mesh_error_naming_it(tmp_path, suffix):
    # meshio's .vtu reader calls sys.exit on a malformed file: that must not end the caller's process
    path = tmp_path / f"broken{suffix}"
    path.write_text("not a mesh\n")
    with pytest.raises(MeshError, match=f"broken\\{suffix}: not a readable tet mesh file"):
        TetMesh.load(path)
    with pytest.raises(MeshError, match="not a file"):
        TetMesh.load(tmp_path)


def test_structured_box_is_conforming_and_mirror_symmetric():
    m = TetMesh.box(size=(2.0, 2.0, 2.0), divisions=(4, 4, 2), origin=(-1.0, -1.0, -1.0))
    # conforming: every interior face is shared by exactly two tets (boundary = the 6 box faces)
    assert m.vertex_areas.sum() == pytest.approx(24.0)
    for axis in range(3):
        mirrored = m.points.copy()
        mirrored[:, axis] *= -1
        # the set of tets (as vertex coordinate sets) is invariant under the reflection
        ref = {tuple(sorted(map(tuple, np.round(mirrored[t], 9)))) for t in m.tets}
        own = {tuple(sorted(map(tuple, np.round(m.points[t], 9)))) for t in m.tets}
        assert ref == own


def _two_boxes():
    b = TetMesh.box(size=(1.0, 1.0, 1.0), divisions=(2, 2, 2))
    n = b.num_vertices
    return TetMesh(np.vstack([b.points, b.points + [2.0, 0.0, 0.0]]), np.vstack([b.tets, b.tets + n])), n


def test_surface_vertices_inside_finds_an_object_passing_through_itself():
    """Two unit boxes of one mesh (a stand-in for the walls of a ring squeezed flat, which pass through each
    other with no self-contact): apart or face to face nothing is inside; pushed 0.3 into each other, the
    second box's surface vertices within the first are found, and only those."""
    two, n = _two_boxes()
    assert two.surface_vertices_inside(two.points).size == 0
    x = two.points.copy()
    x[n:] -= [1.0, 0.13, 0.07]  # face to face (touching)
    assert two.surface_vertices_inside(x).size == 0
    x = two.points.copy()
    x[n:] -= [1.7, 0.13, 0.07]
    inside = two.surface_vertices_inside(x)
    # each box's surface vertices strictly within the other box, and only those
    lo, hi = np.zeros(3), np.ones(3)
    shifted_lo, shifted_hi = lo + [0.3, -0.13, -0.07], hi + [0.3, -0.13, -0.07]
    eps = 1e-9
    expected = [
        v
        for v in two.surface_vertices
        if (v >= n and np.all((x[v] > lo + eps) & (x[v] < hi - eps)))
        or (v < n and np.all((x[v] > shifted_lo + eps) & (x[v] < shifted_hi - eps)))
    ]
    assert len(expected) > 4 and any(v >= n for v in expected) and any(v < n for v in expected)
    np.testing.assert_array_equal(inside, expected)
    with pytest.raises(ValueError, match="points"):
        two.surface_vertices_inside(x[:5])
