"""The planner's pose-independent geometry: finger joint states (``SurfaceClosingDistances``, dense and
host-selected) and open-gripper collision checks (``OpenGripperCollisions``) against the reference
implementations (``finger_closing_distances``, ``ParallelJawGripper.collisions``), and the dense paths'
freedom from host synchronization."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation
from torch._subclasses.fake_tensor import FakeTensorMode

from defgraspnets.grasp.datagen import structured_box
from defgraspnets.grasp.gripper import FRANKA_HAND, SurfaceClosingDistances, finger_closing_distances
from defgraspnets.grasp.sampler import sample_antipodal_grasps
from defgraspnets.models.meshgraphnet import DefGraspNet
from defgraspnets.models.predictor import DefGraspNetsPredictor
from defgraspnets.objects import get_object
from defgraspnets.objects.queries import triangles_overlap_box
from defgraspnets.planning import PRESETS, GraspPlanner, perturb_pose
from defgraspnets.planning.planner import OpenGripperCollisions

pytestmark = pytest.mark.usefixtures("one_torch_thread")
Q = FRANKA_HAND.max_finger_opening


def _surface(mesh):
    """(vertices, faces) of a tet mesh's surface, vertices renumbered (as the planner holds them)."""
    surf = mesh.surface_vertices
    remap = np.full(mesh.num_vertices, -1, dtype=np.int64)
    remap[surf] = np.arange(len(surf))
    return mesh.points[surf], remap[mesh.surface_faces]


@pytest.fixture(scope="module")
def objects():
    box = structured_box((0.05, 0.05, 0.05), (10, 10, 12))  # the benchmark's 1573-vertex box
    ellipsoid = get_object("ellipsoid_40x25x15").surface
    cylinder = get_object("cylinder_r20_h40").surface
    return {
        "box": _surface(box),
        "ellipsoid": (np.asarray(ellipsoid.vertices), np.asarray(ellipsoid.faces)),
        "cylinder": (np.asarray(cylinder.vertices), np.asarray(cylinder.faces)),
    }


def _poses(V, F, n, seed):
    """Sampled antipodal grasps (pads parallel to faces: tied minima), the same tilted and shifted, and
    random poses around the object (partial and no contact)."""
    rng = np.random.default_rng(seed)
    sampled = sample_antipodal_grasps((V, F), n, seed=seed).poses
    moved = sampled.copy()
    moved[:, :3, :3] = moved[:, :3, :3] @ Rotation.from_rotvec(rng.normal(size=(n, 3)) * 0.05).as_matrix()
    moved[:, :3, 3] += rng.normal(size=(n, 3)) * 0.004
    rand = np.tile(np.eye(4), (n, 1, 1))
    rand[:, :3, :3] = Rotation.random(n, random_state=seed).as_matrix()
    rand[:, :3, 3] = V.mean(axis=0) + rng.normal(size=(n, 3)) * 0.03
    return np.concatenate([sampled, moved, rand])


# ---------------------------------------------------------------------------------------------- closing
@pytest.mark.parametrize("name", ["box", "ellipsoid", "cylinder"])
@pytest.mark.parametrize("dense", [True, False])
def test_closing_distances_match_the_reference(objects, name, dense):
    """Values, contact flags and autograd gradients w.r.t. the pose equal those of
    ``finger_closing_distances`` (float64), exact minimum and soft-min, with and without faces."""
    V, F = objects[name]
    n = 8 if name == "ellipsoid" else 12
    T = torch.tensor(_poses(V, F, n, seed=1))
    X = torch.tensor(V)
    for faces in (F, None):
        model = SurfaceClosingDistances(X, faces, dense=dense)
        assert model.dense == dense and model.device.type == "cpu" and model.dtype == torch.float64
        for temperature in (None, 2e-4):
            Tr = T.clone().requires_grad_(True)
            ref, ref_touch = finger_closing_distances(X, Tr, faces=faces, temperature=temperature)
            (ref_grad,) = torch.autograd.grad(ref.sum(), Tr)
            Tn = T.clone().requires_grad_(True)
            new, new_touch = model(Tn, temperature=temperature)
            (new_grad,) = torch.autograd.grad(new.sum(), Tn)
            torch.testing.assert_close(new, ref, rtol=0, atol=1e-12)
            assert torch.equal(new_touch, ref_touch)
            torch.testing.assert_close(new_grad, ref_grad, rtol=0, atol=1e-12)
            if temperature is None:
                assert torch.equal(new, ref)  # same candidates, same operations: bitwise
        assert ref_touch.any() and not ref_touch.all()  # contact and no contact both covered


def test_closing_distances_float32_and_batch_shapes(objects):
    V, F = objects["cylinder"]
    T = _poses(V, F, 4, seed=2)
    ref, ref_touch = finger_closing_distances(
        torch.tensor(V, dtype=torch.float32), torch.tensor(T, dtype=torch.float32), faces=F
    )
    model = SurfaceClosingDistances(torch.tensor(V, dtype=torch.float32), F, dense=True)
    new, touch = model(T.reshape(3, 4, 4, 4))  # numpy poses: moved to the model's dtype
    assert new.dtype == torch.float32 and new.shape == (3, 4, 2) and touch.shape == (3, 4, 2)
    torch.testing.assert_close(new.reshape(-1, 2), ref, rtol=0, atol=1e-7)
    assert torch.equal(touch.reshape(-1, 2), ref_touch)
    with pytest.raises(ValueError, match="poses must have shape"):
        model(np.eye(3))
    with pytest.raises(ValueError, match="temperature"):
        model(T, temperature=0.0)
    with pytest.raises(ValueError, match="faces must be"):
        SurfaceClosingDistances(V, np.array([[0, 1, 10**6]]))


def test_dense_gradient_matches_central_differences(objects):
    V, F = objects["ellipsoid"]
    poses = _poses(V, F, 6, seed=3)[6:12]  # tilted: smooth points of the exact minimum
    model = SurfaceClosingDistances(torch.tensor(V), F, dense=True)
    T = torch.tensor(poses, requires_grad=True)
    closing, touches = model(T)
    assert touches.all()
    closing.sum().backward()
    eps = 1e-7
    for i, j in [(0, 3), (1, 3), (2, 3), (0, 1), (2, 0)]:
        plus, minus = poses.copy(), poses.copy()
        plus[:, i, j] += eps
        minus[:, i, j] -= eps
        fd = (model(plus)[0].sum(1) - model(minus)[0].sum(1)) / (2 * eps)
        np.testing.assert_allclose(T.grad[:, i, j].numpy(), fd.numpy(), atol=1e-5, rtol=1e-5)


# ---------------------------------------------------------------------------------------------- collisions
def test_dense_collisions_match_the_reference(objects):
    big = structured_box((0.3, 0.3, 0.3), (3, 3, 3))  # pads and links fit inside: winding-number path
    cases = {**objects, "big": _surface(big)}
    inside_only = 0
    for name, (V, F) in cases.items():
        n = {"ellipsoid": 8, "big": 8}.get(name, 16)
        poses = _poses(V, F, n, seed=4) if name != "big" else np.tile(np.eye(4), (n, 1, 1))
        if name == "big":
            poses[:, :3, :3] = Rotation.random(n, random_state=4).as_matrix()
            poses[:, :3, 3] = np.random.default_rng(4).normal(size=(n, 3)) * 0.05
        ref = FRANKA_HAND.collisions((V, F), poses)
        check = OpenGripperCollisions(FRANKA_HAND, V, F)
        new = check.collisions(torch.tensor(poses, dtype=torch.float32))  # cast to float64 inside
        assert new.dtype == torch.bool and np.array_equal(new.numpy(), ref), name
        assert np.array_equal(check(torch.tensor(poses)).numpy(), ref.any(axis=1))
        if name != "big":
            assert ref.any() and not ref.all(), name
        else:  # boxes inside the object without a surface triangle: the winding-number test
            xg = (
                np.einsum("nk,gkj->gnj", V, poses[:, :3, :3])
                - np.einsum("gk,gkj->gj", poses[:, :3, 3], poses[:, :3, :3])[:, None]
            )
            boxes = FRANKA_HAND.collision_boxes()
            crossed = np.array(
                [[triangles_overlap_box(x[F] - b.center, b.half_extents).any() for b in boxes] for x in xg]
            )
            inside_only = int((ref & ~crossed).sum())
    assert inside_only > 0


# ---------------------------------------------------------------------------------------------- planner
def _net():
    torch.manual_seed(0)
    net = DefGraspNet(latent=8, num_blocks=1)
    for norm in net.normalizers:  # placeholder statistics: geometry only
        norm.accumulate(torch.randn(16, norm.dim, dtype=torch.float64))
        norm.finalize()
    return net


@pytest.fixture(scope="module")
def planner_parts():
    box = structured_box((0.03, 0.03, 0.03), (4, 4, 4))
    return DefGraspNetsPredictor(_net(), 0.005, precision="fp64"), box


def test_planner_geometry_strategies_agree(planner_parts):
    predictor, box = planner_parts
    poses = _poses(*_surface(box), 6, seed=5)
    planners = [
        GraspPlanner(predictor, box, 2e5, PRESETS["min_max_stress"], dense_geometry=d) for d in (False, True)
    ]
    assert [p.dense_geometry for p in planners] == [False, True]
    (c0, t0), (c1, t1) = (p.closing_distances(torch.tensor(poses)) for p in planners)
    assert torch.equal(c0, c1) and torch.equal(t0, t1)
    assert np.array_equal(planners[0].collides(poses), planners[1].collides(poses))
    assert planners[1]._collides(torch.tensor(poses)).dtype == torch.bool


def test_dense_fingers_stage_has_no_host_work(planner_parts):
    """The dense finger joint states, the predictor's finger poses and the collision check run on fake
    tensors (shapes only): no .item(), .cpu(), .numpy() or data-dependent shapes."""
    predictor, box = planner_parts
    planner = GraspPlanner(
        predictor, box, 2e5, PRESETS["min_max_stress"], closing_temperature=1e-4, dense_geometry=True
    )
    T = torch.tensor(_poses(*_surface(box), 4, seed=6))
    closing, _ = planner.closing_distances(T, exact=False)
    predictor.finger_state(fingers=planner.fingers, gripper_pose=T, closing_distance=closing)  # warm caches
    with FakeTensorMode(allow_non_fake_inputs=True) as mode:
        Tf = mode.from_tensor(T)
        for exact in (True, False):
            closing, touches = planner.closing_distances(Tf, exact=exact)
            assert closing.shape == touches.shape == (12, 2)
        fv, cd, _ = predictor.finger_state(fingers=planner.fingers, gripper_pose=Tf, closing_distance=closing)
        assert fv.shape[:2] == (12, 2) and cd.shape == (12, 2, 3)
        assert planner._collides(Tf).shape == (12,)
    sparse = GraspPlanner(predictor, box, 2e5, PRESETS["min_max_stress"], dense_geometry=False)
    with FakeTensorMode(allow_non_fake_inputs=True) as mode, pytest.raises(RuntimeError):
        sparse.closing_distances(mode.from_tensor(T))  # the host-selected path does read values


@pytest.mark.gpu
def test_dense_fingers_stage_does_not_synchronize_cuda(planner_parts):
    box = planner_parts[1]
    predictor = DefGraspNetsPredictor(_net(), 0.005, device="cuda")
    planner = GraspPlanner(predictor, box, 2e5, PRESETS["min_max_stress"])
    assert planner.dense_geometry
    T = torch.tensor(_poses(*_surface(box), 4, seed=6), dtype=torch.float32, device="cuda")
    xi = torch.zeros(len(T), 6, device="cuda", requires_grad=True)
    closing, _ = planner.closing_distances(T, exact=False)
    predictor.finger_state(fingers=planner.fingers, gripper_pose=T, closing_distance=closing)  # warm caches
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        closing, _ = planner.closing_distances(perturb_pose(T, xi), exact=False)
        predictor.finger_state(fingers=planner.fingers, gripper_pose=T, closing_distance=closing)
        closing.sum().backward()
        planner._collides(T)
    finally:
        torch.cuda.set_sync_debug_mode("default")
    ref, _ = finger_closing_distances(planner.surface_points, T, faces=planner.surface_faces)
    torch.testing.assert_close(planner.closing_distances(T)[0], ref, rtol=0, atol=1e-6)
