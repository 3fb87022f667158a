"""Procedural primitives: closed surfaces with the analytic volumes of the shapes they discretize."""

import math

import numpy as np
import pytest

from defgraspnets.objects import CATEGORIES, PRIMITIVES, ObjectMeshError, check_surface
from defgraspnets.objects import primitives as P


@pytest.fixture(scope="module")
def built():
    return {name: spec.build() for name, spec in PRIMITIVES.items()}


def test_catalogue_size_and_categories():
    assert len(PRIMITIVES) >= 60
    cats = {s.category for s in PRIMITIVES.values()}
    assert cats == set(CATEGORIES) and len(cats) >= 6
    for c in CATEGORIES:  # several instances per category, with different dimensions
        params = [repr(s.params) for s in PRIMITIVES.values() if s.category == c]
        assert len(params) >= 6 and len(set(params)) == len(params)


def test_all_primitives_closed_centred_and_graspable(built):
    for name, (mesh, volume) in built.items():
        check_surface(mesh, name)  # closed, manifold, one body, outward
        assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0, name
        np.testing.assert_allclose(mesh.center_mass, 0.0, atol=1e-9, err_msg=name)
        ext = np.sort(mesh.extents)
        # realistic object sizes, graspable by an 80 mm parallel-jaw gripper across the thinnest side
        assert 0.005 <= ext[0] <= 0.07 and ext[2] <= 0.13, (name, ext)
        # the inscribed polyhedron is slightly smaller than the smooth shape (chord error ~ 1 %)
        assert -0.02 < mesh.volume / volume - 1 < 1e-9, (name, mesh.volume / volume - 1)


def test_profile_volume_matches_closed_forms():
    # cylinder without rounding: pi R^2 H
    prof = P.rounded_profile([(0, 0), (0.03, 0), (0.03, 0.05), (0, 0.05)], [0, 0, 0, 0])
    assert P.profile_volume(prof) == pytest.approx(math.pi * 0.03**2 * 0.05, rel=1e-12)
    # cylinder with rim fillets r: remove the two corner regions by Pappus
    R, H, r = 0.03, 0.05, 0.006
    prof = P.rounded_profile([(0, 0), (R, 0), (R, H), (0, H)], [0, r, r, 0])
    area_corner = r * r * (1 - math.pi / 4)
    rho_corner = (r * r * (R - r / 2) - math.pi * r * r / 4 * (R - r + 4 * r / (3 * math.pi))) / area_corner
    expected = math.pi * R * R * H - 2 * 2 * math.pi * rho_corner * area_corner
    assert P.profile_volume(prof) == pytest.approx(expected, rel=1e-12)
    # capsule, torus, annulus
    _, v = P.capsule(0.02, 0.05)
    assert v == pytest.approx(math.pi * 0.02**2 * 0.05 + 4 / 3 * math.pi * 0.02**3, rel=1e-9)
    _, v = P.torus(0.03, 0.01)
    assert v == pytest.approx(2 * math.pi**2 * 0.03 * 0.01**2, rel=1e-12)
    _, v = P.annulus(0.03, 0.02, 0.04, edge_radius=0.0)
    assert v == pytest.approx(math.pi * (0.03**2 - 0.02**2) * 0.04, rel=1e-12)
    # frustum without rounding: pi H (R1^2 + R1 R2 + R2^2) / 3
    _, v = P.cone(0.03, 0.01, 0.05)
    assert v == pytest.approx(math.pi * 0.05 * (0.03**2 + 0.03 * 0.01 + 0.01**2) / 3, rel=1e-12)


@pytest.mark.parametrize(
    "mesh_and_volume, exact",
    [
        (lambda: P.ellipsoid((0.04, 0.025, 0.015)), 4 / 3 * math.pi * 0.04 * 0.025 * 0.015),
        (lambda: P.torus(0.035, 0.012), 2 * math.pi**2 * 0.035 * 0.012**2),
        (lambda: P.capsule(0.015, 0.06), math.pi * 0.015**2 * 0.06 + 4 / 3 * math.pi * 0.015**3),
        (lambda: P.cylinder(0.025, 0.06), math.pi * 0.025**2 * 0.06),
        (lambda: P.cuboid((0.05, 0.03, 0.02)), 0.05 * 0.03 * 0.02),
    ],
)
def test_mesh_volume_close_to_closed_form(mesh_and_volume, exact):
    mesh, v = mesh_and_volume()
    assert v == pytest.approx(exact, rel=1e-9)
    assert mesh.volume == pytest.approx(exact, rel=0.015)


def test_rounded_box_volume_is_steiner_formula_and_mesh_has_flat_faces():
    size, r = (0.06, 0.04, 0.02), 0.004
    mesh, v = P.cuboid(size, r)
    a = np.array(size) - 2 * r
    steiner = a.prod() + 2 * r * (a[0] * a[1] + a[1] * a[2] + a[0] * a[2]) + math.pi * r * r * a.sum()
    steiner += 4 / 3 * math.pi * r**3
    assert v == pytest.approx(steiner, rel=1e-12)
    assert mesh.volume == pytest.approx(v, rel=0.005)
    np.testing.assert_allclose(mesh.extents, size, atol=1e-12)
    # every vertex lies on the rounded box: distance to the inner box is r or it sits on a flat face
    c = np.array(size) / 2 - r
    d = np.linalg.norm(mesh.vertices - np.clip(mesh.vertices, -c, c), axis=1)
    np.testing.assert_allclose(d, r, atol=1e-12)


def test_fillet_geometry_is_tangent_and_on_circle():
    R, H, r = 0.03, 0.05, 0.006
    prof = P.rounded_profile([(0, 0), (R, 0), (R, H), (0, H)], [0, r, r, 0])
    pts = prof.sample(0.001)
    assert pts[0, 0] == 0 and pts[-1, 0] == 0  # open profile from pole to pole
    assert pts[:, 0].max() == pytest.approx(R) and pts[:, 1].max() == pytest.approx(H)
    corner = (pts[:, 0] > R - r) & (pts[:, 1] > H - r)
    dist = np.hypot(pts[corner, 0] - (R - r), pts[corner, 1] - (H - r))
    np.testing.assert_allclose(dist, r, atol=1e-12)
    cone_mesh, _ = P.cone(0.03, 0.0, 0.06, edge_radius=0.004, tip_radius=0.005)
    check_surface(cone_mesh)


@pytest.mark.parametrize(
    "build",
    [
        lambda: P.cylinder(0.02, -0.01),
        lambda: P.cylinder(float("nan"), 0.05),
        lambda: P.annulus(0.02, 0.03, 0.02),
        lambda: P.torus(0.01, 0.02),
        lambda: P.cone(0.03, 0.0, 0.05),  # sharp tip
        lambda: P.cylinder(0.02, 0.01, edge_radius=0.008),  # fillets overlap on the 10 mm side
        lambda: P.cuboid((0.02, 0.02, 0.02), edge_radius=0.015),
    ],
)
def test_bad_dimensions_raise(build):
    with pytest.raises(ObjectMeshError):
        build()


def test_unknown_category():
    with pytest.raises(KeyError, match="unknown primitive category"):
        P.build_primitive("pyramid", size=1)
