"""Parallel-jaw gripper geometry, collision checks and analytic finger joint states."""

import numpy as np
import pytest
import torch
import trimesh
from scipy.spatial.transform import Rotation

from defgraspnets.grasp import FRANKA_HAND, finger_closing_distances, sample_antipodal_grasps
from defgraspnets.objects import get_object
from defgraspnets.objects.queries import winding_numbers

G = FRANKA_HAND
Q = G.max_finger_opening


def _pose(rotation=None, translation=(0.0, 0.0, 0.0)):
    T = np.eye(4)
    if rotation is not None:
        T[:3, :3] = rotation
    T[:3, 3] = translation
    return T


def _random_poses(n, seed, scale=0.0):
    rng = np.random.default_rng(seed)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.random(n, random_state=seed).as_matrix()
    T[:, :3, 3] = rng.normal(size=(n, 3)) * scale
    return T


@pytest.fixture(scope="module")
def sphere():
    return trimesh.creation.icosphere(4, radius=0.03)  # centrally symmetric


def test_franka_dimensions():
    assert Q == 0.04 and G.max_width == pytest.approx(0.08)
    a, b = G.contact_half_extents
    assert 2 * (a + G.pad_edge_radius) == pytest.approx(0.0175) and 2 * (
        b + G.pad_edge_radius
    ) == pytest.approx(0.0177)


def test_pad_mesh_has_flat_contact_face():
    v, f = G.pad_mesh
    pad = trimesh.Trimesh(v, f, process=False)
    assert pad.is_watertight and pad.is_winding_consistent and pad.volume > 0
    w, th, ln = G.pad_size
    np.testing.assert_allclose(pad.bounds, [[-w / 2, -th, -ln / 2], [w / 2, 0.0, ln / 2]], atol=1e-15)
    # the contact face is the plane y = 0; its vertices fill the flat rectangle exactly
    on_face = np.abs(v[:, 1]) < 1e-15
    a, b = G.contact_half_extents
    assert np.abs(v[on_face, 0]).max() == pytest.approx(a) and np.abs(v[on_face, 2]).max() == pytest.approx(b)
    face_normals = pad.face_normals[np.all(on_face[f], axis=1)]
    np.testing.assert_allclose(face_normals, np.tile([0, 1, 0], (len(face_normals), 1)), atol=1e-12)
    assert len(face_normals) >= 32  # the face is tessellated (graph nodes, contact resolution)


def test_finger_frames_meshes_and_contact_faces():
    pose = _random_poses(1, 3, 0.05)[0]
    opening = (0.03, 0.015)
    faces = G.contact_faces(pose, opening)
    R, t = pose[:3, :3], pose[:3, 3]
    np.testing.assert_allclose(faces[0].center, t + 0.03 * R[:, 1], atol=1e-15)
    np.testing.assert_allclose(faces[1].center, t - 0.015 * R[:, 1], atol=1e-15)
    np.testing.assert_allclose(faces[0].normal, -R[:, 1], atol=1e-15)  # left closes towards -y
    np.testing.assert_allclose(faces[1].normal, R[:, 1], atol=1e-15)
    for face in faces:
        np.testing.assert_allclose(face.axis_v, R[:, 2], atol=1e-15)  # along the approach direction
        assert np.dot(np.cross(face.axis_u, face.normal), face.axis_v) == pytest.approx(1.0)  # right-handed
    meshes = G.finger_meshes(pose, opening)
    for (v, _), face in zip(meshes, faces):
        depth = (v - face.center) @ face.normal  # pad material lies behind its contact face
        assert depth.max() == pytest.approx(0.0, abs=1e-15) and depth.min() == pytest.approx(-G.pad_size[1])
        assert np.abs((v - face.center) @ face.axis_u).max() == pytest.approx(G.pad_size[0] / 2)
    open_faces = G.contact_faces()
    assert np.linalg.norm(open_faces[0].center - open_faces[1].center) == pytest.approx(0.08)


def test_invalid_opening_and_pose():
    with pytest.raises(ValueError, match="finger openings"):
        G.finger_transforms((0.05, 0.01))
    with pytest.raises(ValueError, match="proper rotation"):
        G.finger_meshes(np.diag([1.0, 1.0, -1.0, 1.0]))
    with pytest.raises(ValueError, match="non-finite"):
        G.finger_poses(np.full((4, 4), np.nan))


def _sphere_box_distance(center, box):
    return np.linalg.norm(np.maximum(np.abs(center - box.center) - box.half_extents, 0.0))


def test_collisions_match_analytic_sphere(sphere):
    boxes = G.collision_boxes()
    names = [b.name for b in boxes]
    assert names == ["left_pad", "left_link", "right_pad", "right_link", "hand"]
    hand = boxes[-1]
    assert hand.center[2] + hand.half_extents[2] == pytest.approx(-0.0374)  # 103.4 mm - 66 mm behind the TCP
    rng = np.random.default_rng(5)
    poses = _random_poses(300, 5)
    poses[:, :3, 3] = rng.uniform(-0.09, 0.09, (300, 3))
    result = G.collisions(sphere, poses)
    # analytic: box b overlaps the ball iff the ball centre is within R of the box; the mesh is
    # inscribed (0.9995 R < r < R), so skip the ambiguous shell
    for T, row in zip(poses, result):
        c = -T[:3, :3].T @ T[:3, 3]  # sphere centre in the gripper frame
        for box, hit in zip(boxes, row):
            d = _sphere_box_distance(c, box)
            if d < 0.0299 or d > 0.0301:
                assert hit == (d < 0.03), (box.name, d)
    assert result.any(axis=0).all() and not result.all()  # every part hit at least once, not always


def test_box_fully_inside_object_collides():
    big = trimesh.creation.box((0.2, 0.2, 0.2))
    hits = G.collisions(big, np.eye(4))[0]
    assert hits.all()  # pads and links are inside (no surface crossing), the hand crosses the surface


def test_centred_sphere_symmetric_closing(sphere):
    poses = _random_poses(20, 7)
    c, touch = finger_closing_distances(sphere.vertices, poses, faces=sphere.faces)
    assert touch.all()
    np.testing.assert_allclose(c[:, 0], c[:, 1], atol=1e-12)  # central symmetry of mesh and gripper
    assert np.all(c >= Q - 0.03 - 1e-12) and np.all(c <= Q - 0.03 * 0.995)  # inscribed polyhedron
    # offset along the closing axis by delta: the left finger travels 2 delta more than the right one
    delta = 0.004
    shifted = poses.copy()
    shifted[:, :3, 3] = delta * poses[:, :3, 1]
    c2, _ = finger_closing_distances(sphere.vertices, shifted, faces=sphere.faces)
    np.testing.assert_allclose(c2[:, 0] - c2[:, 1], 2 * delta, atol=4e-4)


def test_cylinder_closing_matches_radius():
    obj = get_object("cylinder_r20_h80")  # axis z, radius 20 mm, even segment count
    poses = np.tile(np.eye(4), (8, 1, 1))
    angles = np.linspace(0, np.pi, 8, endpoint=False)
    for T, a in zip(poses, angles):  # close across the axis, approach along the axis
        T[:3, :3] = Rotation.from_euler("z", a).as_matrix()
    c, touch = finger_closing_distances(obj.surface.vertices, poses, faces=obj.surface.faces)
    assert touch.all()
    np.testing.assert_allclose(c, Q - 0.02, atol=5e-5)  # chord error of the tessellation
    np.testing.assert_allclose(c[:, 0], c[:, 1], atol=1e-12)


def test_no_contact_and_out_of_reach(sphere):
    far = _pose(translation=(0.2, 0.0, 0.0))  # object beside the pads
    c, touch = finger_closing_distances(sphere.vertices, far, faces=sphere.faces)
    assert not touch.any() and np.all(c == Q)
    # a small ball between the right finger and the mid-plane is out of the left finger's travel
    ball = trimesh.creation.icosphere(3, radius=0.015)
    offset = _pose(translation=(0.0, 0.02, 0.0))  # ball centre at y_g = -0.02, top at -0.005
    c, touch = finger_closing_distances(ball.vertices, offset, faces=ball.faces)
    assert touch.tolist() == [False, True] and c[0] == Q
    assert c[1] == pytest.approx(Q - 0.035, abs=1e-12)  # a vertex of the icosphere lies on -y


def test_exact_contact_never_later_than_vertex_projection():
    obj = get_object("cone_rb30_rt10_h30")
    poses = _random_poses(64, 11, 0.01)
    c_exact, t_exact = finger_closing_distances(obj.surface.vertices, poses, faces=obj.surface.faces)
    c_vert, t_vert = finger_closing_distances(obj.surface.vertices, poses)
    assert np.all(c_exact <= c_vert + 1e-15) and np.all(t_exact | ~t_vert)
    assert (c_vert - c_exact).max() > 1e-5  # the polyhedral faces matter between vertices


def test_torch_numpy_and_batch_shapes(sphere):
    poses = _random_poses(6, 13, 0.005).reshape(2, 3, 4, 4)
    c_np, t_np = finger_closing_distances(sphere.vertices, poses, faces=sphere.faces)
    assert c_np.shape == (2, 3, 2) and t_np.shape == (2, 3, 2) and isinstance(c_np, np.ndarray)
    c_t, t_t = finger_closing_distances(
        torch.tensor(sphere.vertices), torch.tensor(poses), faces=sphere.faces
    )
    assert torch.is_tensor(c_t) and c_t.dtype == torch.float64
    np.testing.assert_allclose(c_t.numpy(), c_np, atol=1e-15)
    c32, _ = finger_closing_distances(
        torch.tensor(sphere.vertices, dtype=torch.float32), torch.tensor(poses, dtype=torch.float32)
    )
    assert c32.dtype == torch.float32


@pytest.mark.parametrize("temperature", [None, 5e-4])
def test_gradient_matches_finite_differences(temperature):
    obj = get_object("torus_R30_r10")
    V, F = obj.surface.vertices, obj.surface.faces
    poses = sample_antipodal_grasps(obj.surface, 12, seed=3).poses
    # sampled grasps put the pads parallel to a mesh face: the min over the tied face vertices has a
    # kink in the rotation. Tilt the grasps slightly to evaluate derivatives at smooth points.
    tilt = Rotation.from_rotvec(np.random.default_rng(0).normal(size=(12, 3)) * 0.05).as_matrix()
    poses[:, :3, :3] = poses[:, :3, :3] @ tilt
    T = torch.tensor(poses, requires_grad=True)
    c, touch = finger_closing_distances(torch.tensor(V), T, faces=F, temperature=temperature)
    assert touch.all()
    c.sum().backward()
    grad = T.grad.numpy()
    eps = 1e-7
    for i, j in [(0, 3), (1, 3), (2, 3), (0, 1), (2, 0)]:  # translation and two rotation entries
        plus, minus = poses.copy(), poses.copy()
        plus[:, i, j] += eps
        minus[:, i, j] -= eps
        cp, _ = finger_closing_distances(V, plus, faces=F, temperature=temperature)
        cm, _ = finger_closing_distances(V, minus, faces=F, temperature=temperature)
        fd = (cp.sum(axis=1) - cm.sum(axis=1)) / (2 * eps)
        # soft-min: candidates entering the set (far above the minimum) add jumps of ~exp(-gap / tau)
        tol = 1e-5 if temperature is None else 1e-3
        np.testing.assert_allclose(grad[:, i, j], fd, atol=tol, rtol=tol)
    assert np.abs(grad[:, :3, 3]).max() > 0.1  # translation changes the contact distances


def test_soft_min_bounds(sphere):
    poses = _random_poses(10, 19)
    exact, _ = finger_closing_distances(sphere.vertices, poses, faces=sphere.faces)
    for tau in (1e-3, 1e-4, 1e-6):
        soft, _ = finger_closing_distances(sphere.vertices, poses, faces=sphere.faces, temperature=tau)
        n = len(sphere.vertices) * 10  # generous count of candidates
        assert np.all(soft <= exact + 1e-15) and np.all(soft >= exact - tau * np.log(n + 1))
    np.testing.assert_allclose(soft, exact, atol=1e-4)


def test_bad_inputs(sphere):
    with pytest.raises(ValueError, match="points must have shape"):
        finger_closing_distances(np.zeros((5, 2)), np.eye(4))
    with pytest.raises(ValueError, match="non-finite"):
        finger_closing_distances(np.full((5, 3), np.nan), np.eye(4))
    with pytest.raises(ValueError, match="poses must have shape"):
        finger_closing_distances(sphere.vertices, np.eye(3))
    with pytest.raises(ValueError, match="temperature"):
        finger_closing_distances(sphere.vertices, np.eye(4), temperature=0.0)
    with pytest.raises(ValueError, match="faces must be"):
        finger_closing_distances(sphere.vertices, np.eye(4), faces=np.array([[0, 1, 10**6]]))


def test_winding_of_pads_consistent_with_collision():
    # an object vertex inside a closed pad has winding number 1 with respect to the pad mesh
    v, f = G.finger_meshes(np.eye(4))[0]
    inside = np.array([[0.0, 0.04 + 0.007, 0.0]])
    assert winding_numbers(inside, v[f])[0] == pytest.approx(1.0)
