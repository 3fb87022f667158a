"""The membrane sensor on the FEM engine: inflation, pole indentation, wrench balance, closed capsule, flat
indenters."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from defgraspnets.tactile.camera import PICO_FLEXX
from defgraspnets.tactile.indenters import (
    BoxIndenter,
    CapsuleIndenter,
    IndenterError,
    Pose,
    RingIndenter,
    SphereIndenter,
    WorkspaceError,
)
from defgraspnets.tactile.membrane import ATMOSPHERIC_PRESSURE, PVState, build_membrane
from defgraspnets.tactile.sensor import Indentation, MembraneSimulator, fem_shape

GAUGE = 2000.0  # Pa: inflates the coarse membrane by ~5 mm at the pole
SPHERE = SphereIndenter(radius=0.01)  # the 20 mm contact sphere of thesis §2.3


@pytest.fixture(scope="module")
def sensor():
    return build_membrane(cap_divisions=8, layers=2)


def _gas(sensor, gauge=GAUGE):
    return PVState(ATMOSPHERIC_PRESSURE + gauge, sensor.cavity_volume + sensor.dimensions.housing_volume)


@pytest.fixture(scope="module")
def coarse_sensor():
    """The cap-4 membrane (~18 mm between vertices): for the stream tests' wide indenters, whose point is
    the bookkeeping of paths through problems, not the membrane's resolution."""
    return build_membrane(cap_divisions=4, layers=2)


@pytest.fixture(scope="module")
def open_sim(sensor):
    return MembraneSimulator(
        sensor,
        SPHERE,
        _gas(sensor),
        closed=False,
        batch_size=2,
        friction=0.5,
        intrinsics=PICO_FLEXX.scaled(0.25),
    )


def _pole_height(sensor, positions):
    return positions[sensor.inner_vertices, 2].max()


def test_small_inflation_obeys_clapeyron_and_lifts_the_rim_by_p_times_its_area(sensor):
    p = 100.0  # Pa: linear regime
    sim = MembraneSimulator(sensor, SPHERE, _gas(sensor, p), batch_size=1, intrinsics=None)
    eq, ref = sim.inflated, sim.reference
    dv = eq.cavity_volume[0] - sensor.cavity_volume
    rise = _pole_height(sensor, ref.positions) - _pole_height(sensor, sensor.mesh.points)
    assert dv > 0 and rise > 0
    # Clapeyron: elastic energy = (1/2) p dV for a linear response
    assert eq.strain_energy[0] == pytest.approx(0.5 * p * dv, rel=0.02)
    # the gas lifts the membrane with p A_rim; the clamp holds it down; nothing reaches the base
    np.testing.assert_allclose(ref.rim_force, [0, 0, p * sim.rim_area], atol=1e-6 * p * sim.rim_area)
    assert sim.rim_area == pytest.approx(np.pi * sensor.dimensions.inner_radius**2, rel=0.02)
    assert np.abs(ref.base_wrench).max() < 1e-6 * p * sim.rim_area
    assert ref.gauge_pressure == p
    # the pole rise grows with pressure (same sensor, 20x the pressure)
    big = MembraneSimulator(sensor, SPHERE, _gas(sensor, 20 * p), batch_size=1, intrinsics=None).reference
    assert _pole_height(sensor, big.positions) - _pole_height(sensor, sensor.mesh.points) > 15 * rise


@pytest.mark.slow
def test_pole_indentation_is_axisymmetric_balanced_and_stiffening(open_sim, sensor):
    depths = (0.004, 0.008)
    readings = open_sim.indent([open_sim.pole_indentation(d) for d in depths])
    fz = []
    for r, d in zip(readings, depths):
        assert r.converged and r.depth_travel == d
        f = r.contact_force  # on the indenter: the membrane pushes it up
        fz.append(f[2])
        assert f[2] > 0
        # axisymmetric: no lateral force and no torque (up to the mesh's triangulation)
        assert np.hypot(f[0], f[1]) < 0.05 * f[2]
        assert np.linalg.norm(r.base_wrench[3:]) < 0.05 * f[2] * sensor.dimensions.outer_pole[2]
        # global equilibrium (to the solver's tolerance, 1e-5 of the largest force per component, summed
        # over the vertices): the base transmits minus the contact wrench ...
        np.testing.assert_allclose(r.base_wrench[:3], -f, rtol=0, atol=1e-3 * f[2])
        # ... while the clamp alone also carries the gas's lift p A_rim e_z
        gas_lift = np.array([0.0, 0.0, r.gauge_pressure * open_sim.rim_area])
        np.testing.assert_allclose(r.rim_force, -f + gas_lift, rtol=0, atol=1e-3 * f[2])
        # torque of the contact about the origin = minus the base torque
        c = r.indenter_position
        assert (
            np.abs(np.cross(c, f) + r.base_wrench[3:]).max() < 0.2 * np.linalg.norm(r.base_wrench[3:]) + 1e-4
        )
        # the camera sees the pole move towards it by about the indentation depth
        h, w = r.depth.depth.shape
        centre = (slice(h // 2 - 1, h // 2 + 1), slice(w // 2 - 1, w // 2 + 1))
        shift = np.nanmean(open_sim.reference_depth().depth[centre]) - np.nanmean(r.depth.depth[centre])
        assert 0.5 * d < shift < 1.2 * d
    assert fz[1] > 1.5 * fz[0]  # force grows with depth
    # the next call starts from the inflated membrane again
    again = open_sim.indent([open_sim.pole_indentation(depths[0])])[0]
    np.testing.assert_allclose(again.contact_force, readings[0].contact_force, rtol=1e-3, atol=1e-4)


@pytest.mark.slow
def test_paths_without_a_barrier_between_load_steps_give_the_same_readings(sensor):
    """indent_series lets each poke path go on to its next load step without waiting for the other (the
    default) or solves every step for both (barrier=True): the same readings, depth images included."""
    readings = {}
    for barrier in (True, False):
        # a fresh simulator each: a withdrawn membrane is not the inflated one bit for bit
        sim = MembraneSimulator(
            sensor, SPHERE, _gas(sensor), batch_size=2, friction=0.5, intrinsics=PICO_FLEXX.scaled(0.25)
        )
        pole = sim.pole_indentation(0.008)
        tilted = Indentation(Pose(pole.pose.position + [0.01, 0.005, 0.0]), 0.006, (0.3, 0.0, -1.0))
        readings[barrier] = sim.indent_series([pole, tilted], [0.5, 1.0], barrier=barrier)
    for with_barrier, without in zip(readings[True], readings[False], strict=True):
        for a, b in zip(with_barrier, without, strict=True):
            assert a.converged and b.converged
            np.testing.assert_array_equal(b.positions, a.positions)
            np.testing.assert_array_equal(b.contact_force, a.contact_force)
            np.testing.assert_array_equal(b.base_wrench, a.base_wrench)
            np.testing.assert_array_equal(b.depth.depth, a.depth.depth)
            assert b.depth_travel == a.depth_travel
    assert readings[False][1][1].contact_force[0] < -0.05  # N: the tilted poke pushes sideways


def _small_camera_sim(sensor, batch_size, indenter=SPHERE, friction=0.5):
    """An open sensor with a quarter-size camera (the stream tests build one per path to compare with)."""
    return MembraneSimulator(
        sensor,
        indenter,
        _gas(sensor),
        batch_size=batch_size,
        friction=friction,
        intrinsics=PICO_FLEXX.scaled(0.25),
    )


def test_a_stream_of_paths_through_a_smaller_batch_reads_as_each_path_alone(coarse_sensor):
    """indent_stream pushes three paths through two problems (the third starts where the first finished):
    each path's readings are those of a one-path batch, and the membrane is left at its inflated state (a 40
    mm sphere on the coarse membrane)."""

    def simulator(batch_size, friction=0.5):
        return _small_camera_sim(coarse_sensor, batch_size, SphereIndenter(radius=0.02), friction=friction)

    sim = simulator(2)
    pole = sim.pole_indentation(0.006)
    paths = [
        Indentation(Pose(pole.pose.position + [0.01, 0.005, 0.0]), 0.004, (0.3, 0.0, -1.0)),
        pole,
        sim.pole_indentation(0.003, pose_offset=(0.012, -0.008)),
    ]
    got, order = {}, []

    def on_readings(i, readings):
        order.append(i)
        got[i] = readings

    sim.indent_stream(paths, [0.5, 1.0], on_readings)
    assert sorted(order) == [0, 1, 2]
    for i, path in enumerate(paths):  # a fresh simulator each: a withdrawn membrane is not the inflated one
        expected = [level[0] for level in simulator(1).indent_series([path], [0.5, 1.0])]
        for a, b in zip(expected, got[i], strict=True):
            assert a.converged and b.converged
            np.testing.assert_array_equal(b.positions, a.positions)
            np.testing.assert_array_equal(b.base_wrench, a.base_wrench)
            np.testing.assert_array_equal(b.depth.depth, a.depth.depth)
            assert b.depth_travel == a.depth_travel
            np.testing.assert_array_equal(b.indenter_pose.to_array(), a.indenter_pose.to_array())
    # per-path friction: the third path starts on a problem whose last path had the same coefficient;
    # a path that never meets the membrane is handed to on_invalid and the others go on
    low, invalid = {}, []
    away = Indentation(Pose([0.3, 0.0, 0.16]), 0.004, (1.0, 0.0, 0.0))  # beside the sensor, moving off
    sim.indent_stream(
        [paths[0], away, paths[1], paths[2]],
        [1.0],
        lambda i, readings: low.__setitem__(i, readings[0]),
        friction=[0.2] * 4,
        on_invalid=lambda i, error: invalid.append((i, type(error))),
    )
    assert invalid == [(1, WorkspaceError)] and sorted(low) == [0, 2, 3]
    low = {0: low[0], 1: low[2], 2: low[3]}
    expected = simulator(1, friction=0.2).indent_series([paths[2]], [1.0])[0][0]
    np.testing.assert_array_equal(low[2].base_wrench, expected.base_wrench)
    assert not np.array_equal(low[0].base_wrench, got[0][1].base_wrench)  # the tilted poke slides
    # back at the inflated state: the next poke reads as on a fresh simulator
    again = sim.indent_series([paths[1]], [1.0])[0][0]
    np.testing.assert_array_equal(
        again.positions, simulator(2).indent_series([paths[1]], [1.0])[0][0].positions
    )
    with pytest.raises(ValueError, match="one sequence of levels per path"):
        sim.indent_stream(paths, [[1.0], [1.0]], on_readings)
    with pytest.raises(ValueError, match="friction must hold 3"):
        sim.indent_stream(paths, [1.0], on_readings, friction=[0.5])
    with pytest.raises(WorkspaceError, match="never touches"):
        sim.indent_stream([away], [1.0], on_readings)


def test_a_stream_of_press_and_move_paths_reads_as_each_path_alone(coarse_sensor):
    """press_and_move_stream: three forearm paths (two shears, one twist) through two problems read as
    press_and_move reads each path in a batch of one, bit for bit, poses included; bad motions are named."""
    forearm = CapsuleIndenter(radius=0.04, length=0.2)

    def simulator(batch_size):
        return _small_camera_sim(coarse_sensor, batch_size, forearm)

    sim = simulator(2)
    top = Pose(coarse_sensor.dimensions.outer_pole + [0.0, 0.0, forearm.radius + 0.01])
    press = Indentation(top, 0.005, (0.0, 0.0, -1.0))

    def motion(shift=(0.0, 0.0, 0.0), twist=0.0):
        m = np.eye(4)
        m[:3, :3] = Rotation.from_rotvec([0.0, 0.0, twist]).as_matrix()
        m[:3, 3] = shift
        return m

    motions = [
        np.stack([motion((0.003, 0.0, 0.0)), motion((0.006, 0.0, 0.0))]),  # along the forearm
        np.stack([motion((0.0, -0.004, 0.0))]),  # across it
        np.stack([motion(twist=0.2), motion(twist=0.4)]),  # a twist about the sensor axis
    ]
    got = {}
    sim.press_and_move_stream([press] * 3, motions, lambda i, readings: got.__setitem__(i, readings))
    assert sorted(got) == [0, 1, 2]
    for i, m in enumerate(motions):  # a fresh simulator each: a withdrawn membrane is not the inflated one
        expected = [level[0] for level in simulator(1).press_and_move([press], m[:, None])]
        assert len(got[i]) == len(expected) == len(m)
        for a, b in zip(expected, got[i], strict=True):
            assert a.converged and b.converged
            np.testing.assert_array_equal(b.positions, a.positions)
            np.testing.assert_array_equal(b.base_wrench, a.base_wrench)
            np.testing.assert_array_equal(b.depth.depth, a.depth.depth)
            np.testing.assert_array_equal(b.indenter_pose.to_array(), a.indenter_pose.to_array())
    # friction drags the sensor along each motion: +x and -y forces, a torque about +z for the twist
    assert got[0][1].base_wrench[0] > got[0][0].base_wrench[0] > 0
    assert got[1][0].base_wrench[1] < 0
    assert got[2][0].base_wrench[5] > 0 and got[2][1].base_wrench[5] > 0  # slipping from 0.2 rad on
    np.testing.assert_allclose(got[0][1].indenter_pose.position[0], top.position[0] + 0.006, atol=1e-12)
    with pytest.raises(ValueError, match="one sequence of motions per path"):
        sim.press_and_move_stream([press] * 2, motions, lambda i, r: None)
    with pytest.raises(ValueError, match=r"motions of path 0 must have shape \(L, 4, 4\)"):
        sim.press_and_move_stream([press], [np.eye(4)], lambda i, r: None)


def test_a_stream_of_paths_with_their_own_indenter_radii_reads_as_simulators_of_those_radii(sensor):
    """radius_scale: poke paths with spheres 2x and 0.8x as wide as the simulator's share one stream and
    read as simulators built with those spheres (bit for bit); the wider sphere pushes harder."""
    from dataclasses import replace

    def simulator(indenter, batch_size):
        return _small_camera_sim(sensor, batch_size, indenter)

    sim = simulator(SPHERE, 2)
    pole = sim.pole_indentation(0.01)
    scales = [2.0, 1.0, 0.8]
    got = {}
    sim.indent_stream([pole] * 3, [1.0], lambda i, r: got.__setitem__(i, r[0]), radius_scale=scales)
    for i, scale in enumerate(scales):
        scaled = replace(SPHERE, radius=SPHERE.radius * scale)
        expected = simulator(scaled, 1).indent_series([pole], [1.0])[0][0]
        assert got[i].converged
        np.testing.assert_array_equal(got[i].positions, expected.positions)
        np.testing.assert_array_equal(got[i].base_wrench, expected.base_wrench)
        np.testing.assert_array_equal(got[i].depth.depth, expected.depth.depth)
    # the 40 mm sphere presses more of the coarse membrane at the same depth (1.93 against 1.80 N)
    assert -got[0].base_wrench[2] > 1.05 * -got[1].base_wrench[2] > 0
    # the next stream at the simulator's own radius reads as before (the problems are back at it)
    again = {}
    sim.indent_stream([pole], [1.0], lambda i, r: again.__setitem__(i, r[0]))
    np.testing.assert_array_equal(again[0].base_wrench, got[1].base_wrench)
    with pytest.raises(ValueError, match="radius_scale must hold 3 finite factors > 0"):
        sim.indent_stream([pole] * 3, [1.0], lambda i, r: None, radius_scale=[1.0, 0.0, 1.0])


def test_closed_capsule_is_stiffer_than_open(sensor, open_sim):
    closed = MembraneSimulator(sensor, SPHERE, _gas(sensor), closed=True, batch_size=1, intrinsics=None)
    # sealed at the same PV: it inflates less than the regulated one (its pressure drops as it grows)
    assert 0 < closed.reference.gauge_pressure < GAUGE
    # so seal it at the open sensor's inflated state: same starting shape and pressure
    sealed_pv = (ATMOSPHERIC_PRESSURE + GAUGE) * open_sim.reference.gas_volume
    sealed = MembraneSimulator(
        sensor,
        SPHERE,
        PVState.from_pv(sealed_pv, open_sim.reference.gas_volume),
        closed=True,
        intrinsics=None,
    )
    assert sealed.reference.gauge_pressure == pytest.approx(GAUGE, rel=1e-3)
    d = 0.008
    f_open = open_sim.indent([open_sim.pole_indentation(d)], render=False)[0]
    f_closed = sealed.indent([sealed.pole_indentation(d)], render=False)[0]
    assert f_closed.converged and f_closed.gauge_pressure > GAUGE  # squeezed gas
    assert f_closed.gauge_pressure == pytest.approx(sealed_pv / f_closed.gas_volume - ATMOSPHERIC_PRESSURE)
    # the squeezed gas adds stiffness (a few % here: 8 mm displace little of the sensor's 1.1 l of gas)
    assert f_closed.contact_force[2] > 1.02 * f_open.contact_force[2]


def test_bad_indentations_are_rejected(open_sim):
    with pytest.raises(WorkspaceError, match="rim"):
        open_sim.indent([open_sim.pole_indentation(0.2)])  # would push the sphere below the clamped rim
    with pytest.raises(IndenterError):
        Pose((0.0, np.nan, 0.3))
    with pytest.raises(IndenterError, match="depth"):
        Indentation(Pose((0, 0, 0.3)), -0.001)
    with pytest.raises(IndenterError, match="direction"):
        Indentation(Pose((0, 0, 0.3)), 0.001, (0.0, 0.0, 0.0))
    with pytest.raises(WorkspaceError, match="never touches"):
        open_sim.indent([Indentation(Pose((0.3, 0.0, 0.3)), 0.001)])  # misses the sensor
    with pytest.raises(ValueError, match="1 to 2"):
        open_sim.indent([open_sim.pole_indentation(0.001)] * 3)
    # datagen/tactile.py friction=abc (was numpy's "ufunc 'isfinite' not supported")
    with pytest.raises(ValueError, match="friction must be finite and >= 0, got 'abc'"):
        MembraneSimulator(open_sim.sensor, SPHERE, _gas(open_sim.sensor), friction="abc")


def test_box_pressed_at_the_pole_pushes_back_axially_and_symmetrically(sensor):
    box = BoxIndenter(size_x=0.03, size_y=0.015, size_z=0.02)  # the Fig. 2.5 prism, face down
    # frictionless: with friction the tetrahedra's split of the mirror-symmetric vertex grid (not itself
    # symmetric) leaves ~1.5 % of lateral force (3 % for the sphere), which would hide a wrong body frame
    sim = MembraneSimulator(sensor, box, _gas(sensor), batch_size=2, friction=0.0, intrinsics=None)
    down = sim.pole_indentation(0.009)
    # first contact: the flat face reaches the highest point of the inflated membrane (its pole vertex)
    onset = sim.onset_travel(down)
    top = sim.reference.positions[sensor.outer_vertices, 2].max()
    assert down.pose.position[2] - onset - 0.5 * box.size_z == pytest.approx(top, abs=1e-9)
    # the same box turned upside down (half turn about y) presses with its other face: the same body
    flipped = Indentation(
        Pose.from_rotation(down.pose.position, Rotation.from_euler("y", 180, degrees=True)), 0.009
    )
    depths = np.array([0.003, 0.006, 0.009])
    levels = sim.indent_series([down, flipped], depths / depths[-1], render=False)
    fz = []
    for (r, r_flipped), d in zip(levels, depths):
        assert r.converged and r_flipped.converged and r.depth_travel == pytest.approx(d)
        f = r.contact_force  # on the box: the membrane pushes it up
        fz.append(f[2])
        # both symmetry planes of box and membrane (xz, yz): no lateral force, and the axial force acts
        # along the axis (measured: within 0.1 mm of it; the limit is 0.36 mm), so no torque
        assert np.hypot(f[0], f[1]) < 1e-6 * f[2]
        assert np.linalg.norm(r.base_wrench[3:]) < 2e-3 * f[2] * sensor.dimensions.outer_pole[2]
        np.testing.assert_allclose(r.base_wrench[:3], -f, rtol=0, atol=1e-3 * f[2])
        np.testing.assert_allclose(r_flipped.contact_force, f, rtol=0, atol=1e-4 * f[2])
    assert fz[0] > 0 and np.all(np.diff(fz) > 0)  # the axial force grows with depth
    # a box presses a face first (along its local z), a ring too: others have no FEM body frame
    with pytest.raises(IndenterError, match="local z"):
        sim.indent([Indentation(down.pose, 0.003, (1.0, 0.0, -1.0))])
    ring = RingIndenter(outer_radius=0.015, inner_radius=0.01, height=0.02)
    ring_sim = MembraneSimulator(sensor, ring, _gas(sensor), intrinsics=None)
    tilted = Pose.from_rotation((0.0, 0.0, 0.25), Rotation.from_euler("x", 90, degrees=True))
    with pytest.raises(IndenterError, match="local z"):
        ring_sim.indent([Indentation(tilted, 0.003)])


def test_unsupported_indenters_are_rejected(sensor):
    with pytest.raises(IndenterError, match="supports SphereIndenter, CapsuleIndenter, BoxIndenter"):
        MembraneSimulator(sensor, object(), _gas(sensor), intrinsics=None)
    with pytest.raises(IndenterError, match="supports"):
        fem_shape("sphere")


def test_default_c2_contact_onset_barely_moves_a_poke(sensor):
    """membrane_solver_options smooths the penalty's onset over 1 % of an element (it saves Newton
    iterations where contact patches slide); a pole poke's force moves by far less than the data's own
    accuracy against the plain C1 penalty."""
    import dataclasses

    from defgraspnets.tactile.sensor import membrane_solver_options

    default = membrane_solver_options("cpu")
    assert default.contact_smoothing > 0
    forces = []
    for options in (default, dataclasses.replace(default, contact_smoothing=0.0)):
        sim = MembraneSimulator(
            sensor, SPHERE, _gas(sensor), batch_size=1, intrinsics=None, options=options, device="cpu"
        )
        assert sim.solver.options.contact_smoothing == options.contact_smoothing
        r = sim.indent([sim.pole_indentation(0.006)], render=False)[0]
        assert r.converged
        forces.append(r.contact_force)
    assert forces[0][2] > 0.1  # N: a real poke
    np.testing.assert_allclose(forces[0], forces[1], rtol=0, atol=5e-3 * forces[1][2])


def test_membrane_solver_options_take_checked_overrides(sensor):
    """The datagen's `solver.*` keys reach the sensor's FEM options; None keeps the default, unknown or
    invalid options are rejected by name."""
    from defgraspnets.tactile.datasets import make_simulator
    from defgraspnets.tactile.sensor import membrane_solver_options

    base = membrane_solver_options("cpu")
    assert (base.linear_solver, base.rtol, base.contact_smoothing) == ("banded", 1e-5, 1e-2)
    tuned = membrane_solver_options("cpu", rtol=1e-6, contact_smoothing=None, linear_solver="dense")
    assert (tuned.linear_solver, tuned.rtol, tuned.contact_smoothing) == ("dense", 1e-6, 1e-2)
    with pytest.raises(TypeError, match="contact_smothing"):
        membrane_solver_options("cpu", contact_smothing=0.1)
    with pytest.raises(ValueError, match="contact_smoothing"):
        membrane_solver_options("cpu", contact_smoothing=1.5)
    # both simulators of a sealed sensor (open inflation, then sealed) use the given options
    options = membrane_solver_options("cpu", contact_smoothing=0.0)
    sim = make_simulator(sensor, SPHERE, 100.0, closed=True, intrinsics=None, options=options)
    assert sim.closed and sim.solver.options == options
