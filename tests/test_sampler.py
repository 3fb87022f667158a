"""Antipodal sampler: antipodal in the friction cone, collision-free when open, pads touch after closing."""

import math
import time

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from defgraspnets.grasp import FRANKA_HAND, ParallelJawGripper, sample_antipodal_grasps
from defgraspnets.objects import ObjectMeshError, get_object, tet_mesh
from defgraspnets.objects.queries import closest_points, triangles_overlap_box, winding_numbers

G = FRANKA_HAND


@pytest.fixture(
    scope="module", params=["torus_R30_r10", "cone_rb30_rt0_h60", "cuboid_60x40x20", "annulus_ro25_ri20_h80"]
)
def sampled(request):
    surface = get_object(request.param).surface
    return surface, sample_antipodal_grasps(surface, 40, seed=1)


def test_reproducible_with_seed():
    surface = get_object("capsule_r20_l40").surface
    a = sample_antipodal_grasps(surface, 20, seed=7)
    b = sample_antipodal_grasps(surface, 20, seed=7)
    c = sample_antipodal_grasps(surface, 20, seed=8)
    for key, value in a.as_dict().items():
        np.testing.assert_array_equal(value, b.as_dict()[key])
    assert not np.allclose(a.poses, c.poses)


def test_grasp_frames_and_antipodal_contacts(sampled):
    surface, gs = sampled
    assert len(gs) == 40
    R = gs.poses[:, :3, :3]
    np.testing.assert_allclose(R @ R.transpose(0, 2, 1), np.tile(np.eye(3), (len(gs), 1, 1)), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    np.testing.assert_allclose(R[:, :, 1], gs.axes, atol=1e-15)  # closing axis = gripper y
    left, right = gs.contact_points[:, 0], gs.contact_points[:, 1]
    np.testing.assert_allclose(gs.poses[:, :3, 3], (left + right) / 2, atol=1e-15)  # centred
    np.testing.assert_allclose(left - right, gs.widths[:, None] * gs.axes, atol=1e-12)  # left at +y
    assert np.all(gs.widths > 0) and np.all(gs.widths <= G.max_width)
    # both contacts lie on the surface, with the stored outward normals of their triangles
    _, dist, face = closest_points(gs.contact_points.reshape(-1, 3), surface.triangles)
    assert dist.max() < 1e-12
    # friction cones: the finger pushes along -n at each contact, within atan(mu) of the axis
    cos_cone = math.cos(math.atan(0.7))
    assert np.all(np.einsum("ij,ij->i", gs.contact_normals[:, 0], gs.axes) >= cos_cone - 1e-12)
    assert np.all(np.einsum("ij,ij->i", gs.contact_normals[:, 1], -gs.axes) >= cos_cone - 1e-12)
    # first-exit grasps: the segment between the contacts lies inside the solid; far-side grasps span
    # a gap (the ray leaves and re-enters the solid between the contacts)
    near = ~gs.far_side
    mid = (left[near] + right[near]) / 2
    assert np.all(winding_numbers(mid, surface.triangles) > 0.5)
    far = np.nonzero(gs.far_side)[0][:10]
    t = np.linspace(0, 1, 41)[1:-1, None, None]
    samples = right[far] + t * (left[far] - right[far])  # (39, K, 3) along each segment
    inside = winding_numbers(samples.reshape(-1, 3), surface.triangles).reshape(len(t), -1) > 0.5
    assert not inside.all(axis=0).any()


def test_rotations_regularly_spaced_about_each_axis(sampled):
    _, gs = sampled
    for axis_id in np.unique(gs.axis_ids):
        sel = gs.axis_ids == axis_id
        assert sel.sum() <= 4
        np.testing.assert_allclose(gs.axes[sel] - gs.axes[sel][0], 0.0, atol=1e-15)
        steps = np.diff(np.sort(gs.angles[sel])) / (np.pi / 2)
        np.testing.assert_allclose(steps, np.round(steps), atol=1e-9)
        z = gs.poses[sel][:, :3, 2]
        np.testing.assert_allclose(z @ gs.axes[sel][0], 0.0, atol=1e-12)  # approach perpendicular to axis


def _segments_hit_box(p0, p1, lo, hi):
    """Slab test: does segment p0-p1 meet the box [lo, hi]?  (N,) bool."""
    d = p1 - p0
    with np.errstate(divide="ignore", invalid="ignore"):
        t0 = (lo - p0) / d
        t1 = (hi - p0) / d
    tmin = np.where(d == 0, np.where((p0 >= lo) & (p0 <= hi), -np.inf, np.inf), np.minimum(t0, t1))
    tmax = np.where(d == 0, np.where((p0 >= lo) & (p0 <= hi), np.inf, -np.inf), np.maximum(t0, t1))
    enter = np.maximum(tmin.max(axis=1), 0.0)
    leave = np.minimum(tmax.min(axis=1), 1.0)
    return enter <= leave


def test_open_gripper_is_collision_free_independent_check(sampled):
    """Object edges never cross a gripper box, and no box lies inside the object."""
    surface, gs = sampled
    V, E = surface.vertices, surface.edges_unique
    for T in gs.poses:
        xg = (V - T[:3, 3]) @ T[:3, :3]
        for box in G.collision_boxes():
            lo, hi = box.center - box.half_extents, box.center + box.half_extents
            assert not _segments_hit_box(xg[E[:, 0]], xg[E[:, 1]], lo, hi).any(), box.name
            # box edges do not pierce the surface either: its 8 corners are all outside the object
            corners = box.corners() @ T[:3, :3].T + T[:3, 3]
            assert np.all(winding_numbers(corners, surface.triangles) < 0.5), box.name


def test_sphere_grasps_clear_analytically():
    surface = get_object("ellipsoid_30x30x30").surface  # ball of radius 30 mm
    gs = sample_antipodal_grasps(surface, 40, seed=2)
    for T in gs.poses:
        c = -T[:3, :3].T @ T[:3, 3]  # ball centre in the gripper frame
        for box in G.collision_boxes():
            gap = np.linalg.norm(np.maximum(np.abs(c - box.center) - box.half_extents, 0.0))
            assert gap >= 0.03 * 0.998 - 1e-12, box.name  # inscribed mesh: r >= 0.998 R
    # all grasps pass through the centre: both fingers travel q_max - R
    np.testing.assert_allclose(gs.closing_distances, G.max_finger_opening - 0.03, atol=2e-4)
    np.testing.assert_allclose(gs.widths, 0.06, atol=4e-4)


def _penetration(points, triangles) -> float:
    """Largest depth of ``points`` inside the closed surface (0 if none is inside).

    Points on the surface (touching contact) have ill-defined winding numbers, hence the distance."""
    inside = winding_numbers(points, triangles) > 0.5
    if not inside.any():
        return 0.0
    return float(closest_points(points[inside], triangles)[1].max())


def test_pads_just_touch_after_closing(sampled):
    """At the analytic joint states each pad touches the object and does not penetrate it.

    Independent checks: the object's densely sampled surface comes within sampling resolution of the
    pad's contact face; no object vertex lies inside a closed pad mesh; no pad vertex lies inside the
    object beyond round-off.
    """
    surface, gs = sampled
    tree = cKDTree(trimesh.sample.sample_surface(surface, 100_000, seed=0)[0])
    spacing = math.sqrt(surface.area / 100_000)
    a, b = G.contact_half_extents
    s, t = np.meshgrid(np.linspace(-a, a, 31), np.linspace(-b, b, 31))
    for k in range(0, len(gs), 5):
        opening = G.opening_from_closing(gs.closing_distances[k])
        faces = G.contact_faces(gs.poses[k], opening)
        meshes = G.finger_meshes(gs.poses[k], opening)
        for face, (pv, pf) in zip(faces, meshes):
            grid = face.center + s.reshape(-1, 1) * face.axis_u + t.reshape(-1, 1) * face.axis_v
            gap, _ = tree.query(grid)
            assert gap.min() < 3 * spacing  # touches (within sampling resolution)
            near = np.linalg.norm(surface.vertices - face.center, axis=1) < 0.02  # the pad is 18 mm wide
            front = (pv - face.center) @ face.normal > -2 * G.pad_edge_radius  # face and rounded rim
            assert _penetration(surface.vertices[near], pv[pf]) < 1e-9  # no object vertex inside the pad
            assert _penetration(pv[front], surface.triangles) < 1.5e-5  # at most the rim's chord error


def test_flat_pad_closing_equals_swept_box_first_contact(sampled):
    """Independent exact check: bisection on the travel at which the (flat, sharp-edged) pad box
    first overlaps an object triangle (separating-axis test) gives the same closing distance."""
    surface, gs = sampled
    flat = ParallelJawGripper(pad_edge_radius=0.0)
    closing, touches = flat.closing_distances(surface.vertices, gs.poses[:8], faces=surface.faces)
    assert touches.all()
    w, th, ln = flat.pad_size
    q = flat.max_finger_opening
    for T, c in zip(gs.poses[:8], closing):
        xg = (surface.triangles - T[:3, 3]) @ T[:3, :3]  # (F, 3, 3) in the gripper frame
        for i, s in enumerate((1.0, -1.0)):
            # finger coordinates (u, v, d): d = travel at which the pad face reaches the point
            uvd = np.stack([-s * xg[..., 0], xg[..., 2], q - s * xg[..., 1]], axis=-1)

            def overlaps(
                travel, uvd=uvd
            ):  # volume swept by the pad: |u| <= w/2, |v| <= ln/2, -th <= d <= travel
                centre, half = (travel - th) / 2, (travel + th) / 2
                return triangles_overlap_box(uvd - [0.0, 0.0, centre], [w / 2, ln / 2, half]).any()

            lo, hi = 0.0, q
            assert not overlaps(lo) and overlaps(hi)
            for _ in range(45):
                mid = 0.5 * (lo + hi)
                lo, hi = (lo, mid) if overlaps(mid) else (mid, hi)
            assert c[i] == pytest.approx(hi, abs=1e-9)


def test_far_side_grasps_span_tubes():
    # a tall thin-walled tube: wall grasps need a finger inside the 40 mm bore and mostly collide;
    # far-side contacts squeeze the tube across its 50 mm diameter
    surface = get_object("annulus_ro25_ri20_h80").surface
    gs = sample_antipodal_grasps(surface, 24, seed=0, opposite="both")
    assert len(gs) == 24 and gs.far_side.all()
    np.testing.assert_allclose(gs.widths, 0.05, atol=1e-3)
    with pytest.warns(UserWarning, match="found"):
        first = sample_antipodal_grasps(surface, 24, seed=0, opposite="first", max_candidates=100)
    assert len(first) < 24 and not first.far_side.any()
    with pytest.raises(ValueError, match="opposite"):
        sample_antipodal_grasps(surface, 4, opposite="middle")


def test_small_friction_coefficient_is_stricter():
    surface = get_object("cone_rb30_rt0_h60").surface
    loose = sample_antipodal_grasps(surface, 40, seed=4, friction_coefficient=0.7)
    strict = sample_antipodal_grasps(surface, 40, seed=4, friction_coefficient=0.1)
    cos_strict = math.cos(math.atan(0.1))
    assert np.all(np.einsum("ij,ij->i", strict.contact_normals[:, 0], strict.axes) >= cos_strict - 1e-12)
    assert (
        strict.stats["friction"] / strict.stats["candidates"]
        > loose.stats["friction"] / loose.stats["candidates"]
    )


def test_tet_mesh_input_and_speed(tmp_path):
    tet = tet_mesh("cylinder_r20_h40", target_nodes=400, mesher="gmsh", cache_dir=tmp_path)
    gs = sample_antipodal_grasps(tet, 20, seed=0)
    assert len(gs) == 20
    _, dist, _ = closest_points(gs.contact_points.reshape(-1, 3), tet.points[tet.surface_faces])
    assert dist.max() < 1e-12  # the contacts lie on the tet mesh boundary
    surface = get_object("torus_R25_r8").surface
    assert 1000 < len(surface.faces) < 4000
    start = time.perf_counter()
    gs = sample_antipodal_grasps(surface, 100, seed=0)
    assert len(gs) == 100 and time.perf_counter() - start < 15.0  # a few seconds on one CPU core


def test_budget_exhaustion_warns_and_errors():
    surface = get_object("cuboid_30x30x30").surface
    with pytest.warns(UserWarning, match="found .* of 50 grasps"):
        gs = sample_antipodal_grasps(surface, 50, seed=0, max_candidates=3)
    assert len(gs) <= 12 and gs.stats["candidates"] == 3
    assert len(gs[:2]) == min(2, len(gs))
    with pytest.raises(ValueError):
        sample_antipodal_grasps(surface, 0)
    with pytest.raises(ValueError):
        sample_antipodal_grasps(surface, 10, friction_coefficient=0.0)
    sphere = trimesh.creation.icosphere(2, radius=0.03)
    with pytest.raises(ObjectMeshError, match="not watertight"):
        sample_antipodal_grasps(trimesh.Trimesh(sphere.vertices, sphere.faces[3:], process=False), 10)
