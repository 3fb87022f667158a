"""The membrane sensor with sub-vertex contact (MembraneSimulator(contact_subdivisions=n)): the 1 cm fingertip
pokes the coarse (cap 8) membrane between its vertices."""

import numpy as np
import pytest

from defgraspnets.tactile.indenters import Pose, SphereIndenter, WorkspaceError
from defgraspnets.tactile.membrane import ATMOSPHERIC_PRESSURE, PVState, build_membrane
from defgraspnets.tactile.sensor import Indentation, MembraneSimulator


def _simulator(sensor, **kwargs):
    gas = PVState(ATMOSPHERIC_PRESSURE + 1500.0, sensor.cavity_volume + sensor.dimensions.housing_volume)
    return MembraneSimulator(
        sensor, SphereIndenter(radius=0.005), gas, closed=True, intrinsics=None, device="cpu", **kwargs
    )


def _radial(sensor, point, depth):
    """A poke towards the dome's centre through ``point``."""
    c = sensor.dimensions.center
    d = (point - c) / np.linalg.norm(point - c)
    return Indentation(Pose(tuple(c + (sensor.dimensions.outer_radius + 0.03) * d)), depth, tuple(-d))


def test_the_fingertip_between_the_vertices_of_the_coarse_membrane_is_caught_by_samples():
    """Vertex contact: the 10 mm sphere aimed at the midpoint of a pole edge of the cap-8 membrane passes
    between the two vertices (no onset). With the points of the 2-subdivision it touches, pushes back with
    a force of the order of a poke at the pole (measured 1.38 x at 5 mm: the element is stiffer in its
    middle than at a vertex), and a poke at the pole vertex is the vertex contact's (samples change nothing
    where a vertex carries the load)."""
    sensor = build_membrane(cap_divisions=8, layers=2)
    p = sensor.mesh.points
    outer = sensor.outer_vertices
    pole = outer[np.argmin(np.linalg.norm(p[outer] - sensor.dimensions.outer_pole, axis=1))]
    face = sensor.outer_faces[np.any(sensor.outer_faces == pole, axis=1)][0]
    other = next(v for v in face if v != pole)
    edge = 0.5 * (p[pole] + p[other])
    depth = 0.005

    plain = _simulator(sensor)
    with pytest.raises(WorkspaceError, match="never touches"):
        plain.indent([_radial(sensor, edge, depth)], render=False)
    at_pole = plain.indent([_radial(sensor, p[pole], depth)], render=False)[0]

    sampled = _simulator(sensor, contact_subdivisions=2)
    assert sampled.solver.options.contact_subdivisions == 2
    assert sampled.solver.num_contact_points > 3 * plain.solver.num_contact_points
    pole_2, edge_2 = (sampled.indent([_radial(sensor, x, depth)], render=False)[0] for x in (p[pole], edge))
    assert at_pole.converged and pole_2.converged and edge_2.converged
    f_pole, f_pole_2, f_edge = (np.linalg.norm(r.contact_force) for r in (at_pole, pole_2, edge_2))
    assert f_pole_2 == pytest.approx(f_pole, rel=0.01)
    assert 1.0 < f_edge / f_pole < 1.6
