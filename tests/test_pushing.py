"""Planar quasi-static pushing with an ellipsoidal limit surface (for thesis §5.5)."""

import numpy as np
import pytest

from defgraspnets.tactile.pushing import (
    Capsule,
    PushingModel,
    Rectangle,
    characteristic_length,
    contact_twist,
    push,
)

PRISM = Rectangle(half_length=0.0375, half_width=0.005)  # the 7.5 x 1 cm prism footprint


def contact_velocity(twist, point):
    return np.array([twist[0] - twist[2] * point[1], twist[1] + twist[2] * point[0]])


def test_characteristic_length_of_disc_and_square():
    assert characteristic_length(Capsule(0.02)) == pytest.approx(2 * 0.02 / 3, rel=1e-3)
    side = 0.04
    square = side / 6 * (np.sqrt(2) + np.log(1 + np.sqrt(2)))  # mean distance to the centre of a square
    assert characteristic_length(Rectangle(side / 2, side / 2)) == pytest.approx(square, rel=1e-3)


def test_footprint_geometry():
    point, normal, dist = PRISM.closest_boundary(np.array([0.05, 0.0]))
    assert (
        point == pytest.approx([0.0375, 0.0])
        and normal == pytest.approx([1.0, 0.0])
        and dist == pytest.approx(0.0125)
    )
    point, normal, dist = PRISM.closest_boundary(np.array([0.01, 0.001]))  # inside: nearest edge
    assert (
        point == pytest.approx([0.01, 0.005])
        and normal == pytest.approx([0.0, 1.0])
        and dist == pytest.approx(-0.004)
    )
    _, normal, dist = PRISM.closest_boundary(np.array([0.0375 + 0.003, 0.005 + 0.004]))  # corner
    assert normal == pytest.approx([0.6, 0.8]) and dist == pytest.approx(0.005)
    cap = Capsule(0.01, 0.02)
    point, normal, dist = cap.closest_boundary(np.array([[0.0, 0.03], [0.04, 0.0]]))
    assert point == pytest.approx(np.array([[0.0, 0.01], [0.03, 0.0]]))
    assert dist == pytest.approx([0.02, 0.01])


def test_sticking_contact_matches_lynch_closed_form():
    c, r = 0.015, np.array([0.01, -0.02])
    vp = np.array([0.1, 1.0])
    twist, mode = contact_twist(r, [0.0, 1.0], vp, c, pusher_friction=5.0)
    assert mode == "sticking"
    den = c**2 + r @ r
    vx = ((c**2 + r[0] ** 2) * vp[0] + r[0] * r[1] * vp[1]) / den
    vy = (r[0] * r[1] * vp[0] + (c**2 + r[1] ** 2) * vp[1]) / den
    assert twist == pytest.approx([vx, vy, (r[0] * vy - r[1] * vx) / c**2])
    assert contact_velocity(twist, r) == pytest.approx(vp)  # the contact point moves with the pusher


def test_sliding_contact_lies_on_the_friction_cone_edge():
    c, r, n, mu = 0.015, np.array([0.0, -0.02]), np.array([0.0, 1.0]), 0.2
    vp = np.array([1.0, 0.5])  # strongly tangential: outside the motion cone
    twist, mode = contact_twist(r, n, vp, c, mu)
    assert mode == "sliding"
    vc = contact_velocity(twist, r)
    assert vc @ n == pytest.approx(vp @ n)  # no penetration, no separation
    slip = vp - vc
    assert slip @ np.array([1.0, 0.0]) > 0  # the pusher slides forward relative to the object
    # the transmitted force is the cone edge opposing the slip: f = n + mu t with t along the slip
    f = np.array([mu, 1.0])
    expected = np.array([f[0], f[1], (r[0] * f[1] - r[1] * f[0]) / c**2])
    assert np.cross(twist, expected) == pytest.approx(
        np.zeros(3), abs=1e-9 * np.linalg.norm(twist) * np.linalg.norm(expected)
    )
    assert contact_twist(r, n, [1.0, -0.1], c, mu)[1] == "separating"


def test_pushing_through_the_centre_translates_without_rotation():
    for shape in (Capsule(0.01, 0.02), PRISM):
        model = PushingModel(shape, pusher_radius=0.01, support_friction=0.4, normal_force=0.5)
        result = push(model, [0.0, 0.0, 0.0], [0.0, 0.05], [0.0, -0.06])
        gap = 0.05 - shape.extent[1] - 0.01
        assert result.in_contact and result.mode == "sticking"
        assert result.object_pose == pytest.approx([0.0, -(0.06 - gap), 0.0], abs=1e-9)
        assert result.contact_force == pytest.approx([0.0, -0.4 * 0.5])  # f_max = mu_s N opposing the motion
        along = push(model, [0.0, 0.0, 0.0], [0.08, 0.0], [-0.03, 0.0])
        assert along.object_pose[1:] == pytest.approx([0.0, 0.0], abs=1e-12)


@pytest.mark.parametrize("offset", [0.015, -0.015])
def test_off_centre_push_rotates_the_correct_way(offset):
    model = PushingModel(Capsule(0.01, 0.02), pusher_radius=0.01)
    result = push(model, [0.0, 0.0, 0.0], [offset, 0.05], [0.0, -0.06])  # 3 cm of pushing after contact
    # force -y applied at x = offset: moment x f_y < 0 for offset > 0, i.e. clockwise
    assert np.sign(result.object_pose[2]) == -np.sign(offset)
    assert abs(result.object_pose[2]) > 0.3
    assert result.object_pose[1] < -0.01
    mirror = push(model, [0.0, 0.0, 0.0], [-offset, 0.05], [0.0, -0.06])
    assert mirror.object_pose == pytest.approx(result.object_pose * [-1.0, 1.0, -1.0], abs=1e-12)


def test_frictionless_pusher_never_rotates_a_disc():
    model = PushingModel(Capsule(0.02), pusher_radius=0.01, pusher_friction=0.0)
    result = push(model, [0.0, 0.0, 0.0], [0.01, 0.05], [0.0, -0.05])
    assert result.object_pose[2] == pytest.approx(
        0.0, abs=1e-12
    )  # every contact force passes through the centre
    assert result.object_pose[0] < 0 and result.mode == "sliding"


def test_pushing_the_end_of_the_prism_turns_it_and_converges_with_the_substep():
    model = PushingModel(PRISM, pusher_radius=0.01, pusher_friction=0.5)
    coarse = push(model, [0.0, 0.0, 0.0], [0.03, 0.03], [0.0, -0.04], max_substep=5e-4)
    fine = push(model, [0.0, 0.0, 0.0], [0.03, 0.03], [0.0, -0.04], max_substep=1e-4)
    assert coarse.object_pose[2] < -0.3  # clockwise, substantially
    assert coarse.object_pose == pytest.approx(fine.object_pose, abs=2e-3)
    # no residual penetration
    rot = np.array(
        [
            [np.cos(fine.object_pose[2]), -np.sin(fine.object_pose[2])],
            [np.sin(fine.object_pose[2]), np.cos(fine.object_pose[2])],
        ]
    )
    local = rot.T @ (fine.pusher_center - fine.object_pose[:2])
    assert PRISM.closest_boundary(local)[2] >= 0.01 - 1e-9


def test_free_motion_separation_and_bad_input():
    model = PushingModel(Capsule(0.01), pusher_radius=0.01)
    away = push(model, [0.0, 0.0, 0.0], [0.0, 0.03], [0.0, 0.05])
    assert not away.in_contact and away.mode == "free"
    assert away.object_pose == pytest.approx([0.0, 0.0, 0.0])
    assert away.pusher_center == pytest.approx([0.0, 0.08])
    with pytest.raises(ValueError, match="inside the object"):
        push(model, [0.0, 0.0, 0.0], [0.0, 0.005], [0.0, -0.01])
    with pytest.raises(ValueError, match="pusher_radius"):
        PushingModel(Capsule(0.01), pusher_radius=0.0)
    with pytest.raises(ValueError, match="finite"):
        push(model, [0.0, np.nan, 0.0], [0.0, 0.05], [0.0, -0.01])
