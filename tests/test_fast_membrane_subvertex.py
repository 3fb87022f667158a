"""Sub-vertex contact of the fast membrane model (defgraspnets.tactile.fast_membrane)."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from defgraspnets.tactile.contour_sim import build_fast_simulation, pole_height
from defgraspnets.tactile.fast_membrane import (
    FastMembrane,
    least_distance_multipliers,
    negative_area_fraction,
    subdivision_points,
)
from defgraspnets.tactile.sdf import BoxSDF, SphereSDF, TubeSDF, UnionSDF


@pytest.fixture(scope="module")
def sim():
    return build_fast_simulation(cap_divisions=12, camera_scale=0.5)


def _model(sim, samples, **kw):
    m = sim.model
    return FastMembrane(m.sensor, m.reference, m.calibration, contact_samples_per_face=samples, **kw)


@pytest.mark.parametrize("n", [1, 2, 3, 4])
def test_subdivision_points_partition_the_triangle(n):
    bary, share, sub = subdivision_points(n)
    assert bary.shape == ((n + 1) * (n + 2) // 2, 3) and sub.shape == (n * n, 3)
    np.testing.assert_allclose(bary.sum(axis=1), 1.0)
    assert (bary[:3].max(axis=1) == 1.0).all()  # corners first
    assert share.sum() == pytest.approx(1.0)
    # every sub-triangle has area 1 / n^2 of the triangle (barycentric determinant)
    a, b, c = bary[sub[:, 0]], bary[sub[:, 1]], bary[sub[:, 2]]
    det = np.abs(np.cross(b[:, :2] - a[:, :2], c[:, :2] - a[:, :2]))
    np.testing.assert_allclose(det, 1.0 / n**2)
    with pytest.raises(ValueError):
        subdivision_points(0)


def test_negative_area_fraction_is_exact_and_continuous():
    assert negative_area_fraction([[1.0, 2.0, 3.0], [-1.0, -2.0, -3.0]]).tolist() == [0.0, 1.0]
    # one corner at -1, two at +1: the zero line halves the two edges, a quarter of the triangle
    assert negative_area_fraction([-1.0, 1.0, 1.0]) == pytest.approx(0.25)
    assert negative_area_fraction([-1.0, -1.0, 1.0]) == pytest.approx(0.75)
    # continuous as a corner crosses zero
    eps = 1e-9
    assert negative_area_fraction([-eps, 1.0, 1.0]) == pytest.approx(0.0, abs=1e-12)
    assert negative_area_fraction([-1.0, -eps, 1.0]) == pytest.approx(0.5, abs=1e-6)
    assert negative_area_fraction([-1.0, eps, 1.0]) == pytest.approx(0.5, abs=1e-6)


def test_least_distance_multipliers_solve_a_small_program():
    # min |z|^2 / 2 s.t. z1 >= 1, z1 + z2 >= 3: the projection of 0 on z1 + z2 = 3, (1.5, 1.5)
    e = np.array([[1.0, 0.0], [1.0, 1.0]])
    lam = least_distance_multipliers(e, np.array([1.0, 3.0]))
    np.testing.assert_allclose(e.T @ lam, [1.5, 1.5], atol=1e-12)
    np.testing.assert_allclose(lam, [0.0, 1.5], atol=1e-12)
    assert least_distance_multipliers(e, np.array([-1.0, 0.0])).tolist() == [0.0, 0.0]
    with pytest.raises(ValueError, match="infeasible"):
        least_distance_multipliers(np.array([[1.0], [-1.0]]), np.array([1.0, 1.0]))


def test_vertex_wise_option_reproduces_the_previous_model(sim):
    """``contact_samples_per_face=0`` (the default) is the model as it was before the sub-vertex contact:
    reference numbers computed with the previous code (commit 512ab08) on the same scenes."""
    assert sim.model.contact_samples_per_face == 0
    top = pole_height(sim)
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_euler("xyz", [5, -3, 20], degrees=True).as_matrix()
    pose[:3, 3] = [0.001, -0.002, 0.0005]
    pipe = TubeSDF(np.array([[-0.06, 0.002, top + 0.00235], [0.06, -0.001, top + 0.00235]]), 0.00635)
    sphere_and_box = UnionSDF(
        (SphereSDF((0.003, 0, top + 0.007), 0.01), BoxSDF((0.0, 0.02, top), (0.004, 0.004, 0.003)))
    )
    expected = [
        (0.32023466294170705, 1.0399749416454152e-06, 0.00022012054871010424, 5, 411.5299031708158),
        (0.056033957879087604, 1.4121285565578748e-07, 4.5143794134530994e-05, 1, 411.6350214985049),
    ]
    for scene, (force, volume, area, columns, checksum) in zip((pipe, sphere_and_box), expected):
        st = sim.model.solve(scene, pose)
        assert st.normal_force == pytest.approx(force, rel=1e-9)
        assert st.displaced_volume == pytest.approx(volume, rel=1e-9)
        assert st.contact_area == pytest.approx(area, rel=1e-9)
        assert int(st.contact_columns.sum()) == columns
        assert float(np.abs(st.positions).sum()) == pytest.approx(checksum, rel=1e-12)
        assert st.column_load is None


def test_rejects_bad_contact_options(sim):
    for bad in (-3, 4, 5, 9):
        with pytest.raises(ValueError, match="contact_samples_per_face"):
            _model(sim, bad)
    with pytest.raises(ValueError):
        _model(sim, 6, contact_margin=-1.0)


def _face_between_vertices(model):
    """A triangle near the pole: its outer centroid and unit outward normal (sensor frame)."""
    faces = model.sensor.inner_faces
    centroid = model.outer_reference[faces].mean(axis=1)
    k = int(np.argmax(centroid[:, 2]))
    x = model.outer_reference[faces[k]]
    n = np.cross(x[1] - x[0], x[2] - x[0])
    n /= np.linalg.norm(n)
    return faces[k], centroid[k], n if n[2] > 0 else -n


def test_a_small_sphere_between_vertices_is_felt_only_by_sub_vertex_contact(sim):
    cols, c, n = _face_between_vertices(sim.model)
    r, press = 0.003, 0.0005
    scene = SphereSDF(tuple(c + (r - press) * n), r)
    assert (scene.distance(sim.model.outer_reference) > 0).all()  # no vertex touches it
    old = sim.model.solve(scene, np.eye(4))
    assert not old.in_contact and old.normal_force == 0.0
    new = _model(sim, 10).solve(scene, np.eye(4))
    assert new.in_contact and new.normal_force > 0
    assert set(np.flatnonzero(new.contact_columns)) >= set(cols.tolist())  # the triangle's columns carry it
    assert new.residual_penetration < 2e-5
    # the membrane pushes the sphere outward, along the triangle's normal
    assert new.contact_force @ n == pytest.approx(new.normal_force, rel=0.02)
    # thickness preserved: every column moves rigidly
    s = sim.model.num_columns
    u = new.positions - sim.model.reference
    np.testing.assert_allclose(u[:s], u[2 * s :], atol=1e-12)


def test_sphere_on_the_axis_force_grows_continuously_and_stays_axial(sim):
    """The vertex-wise contact's force jumps (and here even drops) as a ring of vertices enters the contact
    and leans sideways when the ring enters unevenly; the sub-vertex contact's does neither."""
    top = pole_height(sim)
    depths = np.linspace(0.0002, 0.005, 25)

    def series(model):
        forces, lateral = [], []
        for d in depths:
            st = model.solve(SphereSDF((0.0, 0.0, top + 0.01 - d), 0.01), np.eye(4))
            forces.append(st.normal_force)
            lateral.append(np.linalg.norm(st.contact_force[:2]) / st.normal_force)
        return np.diff(forces), max(lateral)

    inc_new, lateral_new = series(_model(sim, 10))
    assert (inc_new > 0).all()
    assert inc_new.max() < 2.0 * np.median(inc_new)
    assert lateral_new < 0.02
    inc_old, lateral_old = series(sim.model)
    assert inc_old.max() > 2.0 * np.median(inc_old) or (inc_old <= 0).any()
    assert lateral_old > lateral_new


def test_prism_contact_area_follows_a_small_yaw_continuously(sim):
    """A 1 cm wide box face pressed 4 mm: the contact area (phi interpolated on the sub-triangles) changes
    with the yaw in small steps, where the vertex-wise area (whole lumped vertex areas) is constant or
    jumps."""
    top = pole_height(sim)

    def areas(model):
        out = []
        for yaw in np.linspace(0.0, 6.0, 13):
            rot = Rotation.from_euler("z", yaw, degrees=True).as_matrix()
            box = BoxSDF((0.0, 0.0015, top + 0.01 - 0.004), (0.0375, 0.005, 0.01), rot)
            out.append(model.solve(box, np.eye(4)).contact_area)
        return np.array(out)

    new = areas(_model(sim, 10))
    steps = np.abs(np.diff(new))
    assert (steps > 0).all()  # every yaw step changes it
    assert steps.max() < 0.02 * new.mean()  # and by small amounts
    old = np.abs(np.diff(areas(sim.model)))
    assert (old == 0).any() or old.max() > 0.02 * new.mean()


def _mirror_columns(model) -> np.ndarray:
    """Column index of each column's mirror image about the plane x = 0 (by the mesh at rest)."""
    from scipy.spatial import cKDTree

    rest = model.sensor.mesh.points[: model.num_columns]
    dist, idx = cKDTree(rest).query(rest * [-1.0, 1.0, 1.0])
    assert dist.max() < 1e-12
    return idx


def test_mirror_symmetric_membrane_responds_to_a_mirrored_press_with_the_mirrored_deformation():
    """A box pressed 4 mm off the axis at a 5 deg yaw, and its mirror image about x = 0 (x -> -x, yaw -> -5
    deg): on the mirror-symmetric mesh the fast model's deformed inner surfaces (inflated reference plus
    column displacements) are each other's mirror images to round-off; on the default mesh (every skirt
    rectangle cut along the same diagonal: already its FEM inflation is asymmetric) they are not."""
    errors = {}
    for symmetric in (True, False):
        sim = build_fast_simulation(cap_divisions=12, camera_scale=0.5, mirror_symmetric=symmetric)
        model, top = sim.model, pole_height(sim)
        shapes = []
        for sign in (1.0, -1.0):
            rot = Rotation.from_euler("z", sign * 5.0, degrees=True).as_matrix()
            box = BoxSDF((sign * 0.006, 0.004, top + 0.01 - 0.004), (0.0375, 0.005, 0.01), rot)
            u = model.solve(box, np.eye(4)).column_displacement
            assert np.abs(u).max() > 1e-3
            shapes.append(model.inner_reference + u)
        mirrored = shapes[1][_mirror_columns(model)] * [-1.0, 1.0, 1.0]
        errors[symmetric] = np.abs(mirrored - shapes[0]).max()
    assert errors[True] < 1e-12  # [m]
    assert errors[False] > 1e-5
