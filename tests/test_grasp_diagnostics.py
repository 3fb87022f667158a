"""The squeeze-state diagnostics (defgraspnets.grasp.diagnostics) against states whose answer is known."""

import numpy as np
import pytest

from defgraspnets import fem
from defgraspnets.grasp.diagnostics import (
    deformation_jacobians,
    rigid_turn,
    squeeze_state_geometry,
    travel_controlled_path,
)
from defgraspnets.grasp.sampler import sample_antipodal_grasps
from defgraspnets.grasp.squeeze import FINGER_NAMES, finger_contact_poses

SIZE = np.array([0.03, 0.025, 0.035])


@pytest.fixture(scope="module")
def box_and_grasp():
    mesh = fem.TetMesh.box(size=SIZE, divisions=(4, 3, 5), origin=-SIZE / 2)
    return mesh, sample_antipodal_grasps(mesh, num_grasps=1, seed=0)


def _rotation(axis, angle):
    k = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def test_volume_ratios_and_rigid_turn_of_known_motions(box_and_grasp):
    mesh, _ = box_and_grasp
    np.testing.assert_allclose(deformation_jacobians(mesh, 1.2 * mesh.points), 1.2**3, rtol=1e-12)
    squashed = mesh.points * [1.0, 0.5, 1.0]
    np.testing.assert_allclose(deformation_jacobians(mesh, squashed), 0.5, rtol=1e-12)
    flipped = mesh.points * [1.0, -1.0, 1.0]  # a mirror image: every tet inverted
    assert np.all(deformation_jacobians(mesh, flipped) < 0)
    axis = np.array([1.0, 2.0, -0.5])
    moved = mesh.points @ _rotation(axis, np.radians(30.0)).T + [0.01, -0.02, 0.005]
    angle, found = rigid_turn(mesh, moved)
    assert np.degrees(angle) == pytest.approx(30.0, abs=1e-9)
    np.testing.assert_allclose(found, axis / np.linalg.norm(axis), atol=1e-9)
    np.testing.assert_allclose(deformation_jacobians(mesh, moved), 1.0, rtol=1e-12)  # rigid: no volume change
    with pytest.raises(ValueError, match="points must be"):
        deformation_jacobians(mesh, mesh.points[:-1])


def test_a_rigid_slide_across_the_grasp_axis_reads_as_drift_and_slip(box_and_grasp):
    mesh, grasp = box_and_grasp
    poses = finger_contact_poses(grasp)[0]
    closing = poses[0, :3, 1]
    across = np.cross(closing, [0.3, 0.5, 0.8])
    across *= 1.5e-3 / np.linalg.norm(across)  # 1.5 mm across the grasp axis
    S = len(mesh.surface_vertices)
    all_touch = {name: np.ones(S) for name in FINGER_NAMES}
    g = squeeze_state_geometry(mesh, np.tile(across, (mesh.num_vertices, 1)), poses, 2e-4, all_touch, 0.5)
    assert g["drift_mm"] == pytest.approx(1.5, rel=1e-9)
    assert g["turn_deg"] == pytest.approx(0.0, abs=1e-6)
    assert g["min_J"] == pytest.approx(1.0, rel=1e-12) and g["tets_J_below_0.2"] == 0
    assert g["gap_mm"] == pytest.approx(g["gap0_mm"] - 0.4, rel=1e-12)
    for pad in g["pads"]:
        assert pad["contacts"] == S and pad["normal_force"] == pytest.approx(S)
        assert pad["slip_mean_mm"] == pytest.approx(1.5, rel=1e-9) and pad["slip_max_mm"] == pytest.approx(
            1.5
        )
    at_rest = squeeze_state_geometry(
        mesh, np.zeros_like(mesh.points), poses, 0.0, {n: np.zeros(S) for n in FINGER_NAMES}, 0.5
    )
    assert (
        at_rest["drift_mm"] == 0.0 and at_rest["turn_deg"] == 0.0 and at_rest["gap_mm"] == at_rest["gap0_mm"]
    )
    assert all(p["contacts"] == 0 and p["slip_max_mm"] == 0.0 for p in at_rest["pads"])
    with pytest.raises(ValueError, match="one force per surface vertex"):
        squeeze_state_geometry(
            mesh, np.zeros_like(mesh.points), poses, 0.0, {n: np.zeros(3) for n in FINGER_NAMES}, 0.5
        )


def test_travel_controlled_squeeze_force_grows_with_travel(box_and_grasp):
    mesh, grasp = box_and_grasp
    material = fem.Material(1e5, 0.3, 1000.0, model="neohookean")
    rows = travel_controlled_path(mesh, grasp, material, [1e-4, 2e-4, 4e-4])
    assert [r["status"] for r in rows] == [0, 0, 0]
    np.testing.assert_allclose([r["travel_mm"] for r in rows], [0.1, 0.2, 0.4], rtol=1e-6)
    forces = [r["force"] for r in rows]
    assert 0.0 < forces[0] < forces[1] < forces[2]
