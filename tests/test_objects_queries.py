"""Exact surface queries checked against analytic geometry (sphere, box) and brute force."""

import numpy as np
import pytest
import trimesh

from defgraspnets.objects import queries as Q


@pytest.fixture(scope="module")
def sphere():
    return trimesh.creation.icosphere(4, radius=0.03)


def test_ray_hits_on_sphere(sphere):
    rng = np.random.default_rng(0)
    d = rng.normal(size=(300, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = rng.uniform(-0.01, 0.01, (300, 3))  # inside: every ray exits once
    t, f = Q.first_ray_hits(o, d, sphere.triangles)
    assert np.all(f >= 0)
    hit = o + t[:, None] * d
    r = np.linalg.norm(hit, axis=1)
    assert np.all(r <= 0.03 + 1e-12) and np.all(r >= 0.03 * 0.998)  # on the inscribed polyhedron
    bary = trimesh.triangles.points_to_barycentric(sphere.triangles[f], hit)
    assert np.all(bary > -1e-9)  # the hit lies on the reported triangle
    assert np.all(np.einsum("ij,ij->i", sphere.face_normals[f], d) > 0)  # leaving through the surface
    # from outside pointing away: no hit
    t, f = Q.first_ray_hits(np.full((5, 3), 0.1), np.ones((5, 3)), sphere.triangles)
    assert np.all(f == -1) and np.all(np.isinf(t))


def test_winding_numbers_inside_outside(sphere):
    rng = np.random.default_rng(1)
    p = rng.uniform(-0.05, 0.05, (800, 3))
    r = np.linalg.norm(p, axis=1)
    w = Q.winding_numbers(p, sphere.triangles)
    clear = np.abs(r - 0.03) > 1e-4
    np.testing.assert_allclose(w[clear], (r[clear] < 0.03).astype(float), atol=1e-9)
    np.testing.assert_array_equal(Q.contains(p[clear], sphere.triangles), r[clear] < 0.03)


def test_closest_points_match_brute_force_and_sphere(sphere):
    rng = np.random.default_rng(2)
    p = rng.normal(size=(200, 3)) * 0.03
    cp, d, f = Q.closest_points(p, sphere.triangles)
    # analytic: the polyhedron lies within [r_in, R] of the centre
    r = np.linalg.norm(p, axis=1)
    assert np.all(np.abs(d - np.abs(r - 0.03)) < 2e-4)
    # brute force over every triangle, and the reported point is on the reported triangle
    tri = sphere.triangles
    brute = Q._closest_on_triangles(p[:, None], tri[None, :, 0], tri[None, :, 1], tri[None, :, 2])
    db = np.linalg.norm(brute - p[:, None], axis=2).min(axis=1)
    np.testing.assert_allclose(d, db, atol=1e-15)
    bary = trimesh.triangles.points_to_barycentric(tri[f], cp)
    assert np.all(bary > -1e-9)
    sd = Q.signed_distances(p, sphere.triangles)
    np.testing.assert_array_equal(sd < 0, Q.contains(p, sphere.triangles))


def test_closest_point_regions_on_one_triangle():
    tri = np.array([[[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]])
    pts = np.array([[-1, -1, 0.5], [2, -0.5, 0], [0.25, 0.25, 3], [0.8, 0.8, 0], [-0.5, 0.5, 0]])
    expect = np.array([[0, 0, 0], [1, 0, 0], [0.25, 0.25, 0], [0.5, 0.5, 0], [0, 0.5, 0]])
    cp, d, _ = Q.closest_points(pts, tri)
    np.testing.assert_allclose(cp, expect, atol=1e-15)


def test_triangle_box_overlap_against_sampling():
    rng = np.random.default_rng(3)
    tri = rng.uniform(-1, 1, (5000, 3, 3))
    h = np.array([0.3, 0.5, 0.2])
    ov = Q.triangles_overlap_box(tri, h)
    u = rng.uniform(size=(5000, 300, 2))
    flip = u.sum(-1) > 1
    u[flip] = 1 - u[flip]
    pts = (
        tri[:, None, 0]
        + u[..., :1] * (tri[:, None, 1] - tri[:, None, 0])
        + u[..., 1:] * (tri[:, None, 2] - tri[:, None, 0])
    )
    sampled = np.all(np.abs(pts) <= h, axis=-1).any(axis=1)
    assert np.all(ov[sampled])  # a sampled point inside implies overlap
    # separated by a plane: all vertices beyond one box face never overlap
    far = tri.copy()
    far[..., 0] += 3.0
    assert not Q.triangles_overlap_box(far, h).any()
    # a large triangle slicing through the box centre without vertices or edges inside
    big = np.array([[[-10, -10, 0.0], [10, -10, 0.0], [0, 10, 0.0]]])
    assert Q.triangles_overlap_box(big, h).all()
