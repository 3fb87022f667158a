"""Membrane mesh, enclosed gas volume, PV states, indenters and the indentation workspace."""

import numpy as np
import pytest

from defgraspnets.fem.mesh import TetMesh
from defgraspnets.tactile.indenters import (
    CONTACT_SPHERES,
    FINGERTIP,
    FOREARM,
    RECTANGULAR_PRISM,
    RING,
    BoxIndenter,
    ForearmCommand,
    IndenterError,
    PokeCommand,
    Pose,
    RingIndenter,
    SphereIndenter,
    WorkspaceError,
    check_workspace,
    forearm_grid,
    make_indenter,
    poke_grid,
)
from defgraspnets.tactile.membrane import (
    ATMOSPHERIC_PRESSURE,
    MembraneDimensions,
    MembraneError,
    PVState,
    build_membrane,
)


@pytest.fixture(scope="module")
def sensor():
    return build_membrane(cap_divisions=16, layers=2)


def _cap_and_skirt(sensor, vertices):
    z = sensor.mesh.points[vertices, 2]
    eq = sensor.dimensions.z_equator
    return vertices[z > eq + 1e-12], vertices[z < eq - 1e-12]


# --------------------------------------------------------------------------- geometry
def test_mesh_is_valid_tetmesh_with_thesis_dimensions(sensor):
    mesh, d = sensor.mesh, sensor.dimensions
    assert isinstance(mesh, TetMesh)
    assert np.all(mesh.volumes > 0)
    p = mesh.points
    # radii measured on the mesh: inner and outer surfaces of cap and skirt
    for layer_vertices, radius in ((sensor.inner_vertices, 0.047), (sensor.outer_vertices, 0.050)):
        cap, skirt = _cap_and_skirt(sensor, layer_vertices)
        np.testing.assert_allclose(np.linalg.norm(p[cap] - d.center, axis=1), radius, atol=1e-12)
        np.testing.assert_allclose(np.hypot(p[skirt, 0], p[skirt, 1]), radius, atol=1e-12)
    # thickness: every outer vertex is 3 mm from its inner vertex, through `layers` layers
    n_surf = len(sensor.inner_vertices)
    np.testing.assert_allclose(
        np.linalg.norm(p[n_surf * sensor.layers :] - p[:n_surf], axis=1), 0.003, atol=1e-12
    )
    assert sensor.layers == 2 and sensor.vertex_layer.max() == 2
    # skirt height and pole heights
    assert np.isclose(d.z_equator - p[:, 2].min(), 0.030, atol=1e-12)
    assert np.isclose(p[:, 2].min(), d.z_rim) and np.isclose(d.z_rim, 0.10)
    assert np.isclose(p[:, 2].max(), d.z_equator + 0.050, atol=1e-12)
    # solid volume of the shell against hemisphere shell + cylindrical tube
    shell = 2 / 3 * np.pi * (0.05**3 - 0.047**3) + np.pi * (0.05**2 - 0.047**2) * 0.03
    assert abs(mesh.volume / shell - 1) < 0.01


def test_no_degenerate_pole_and_reasonable_element_quality(sensor):
    p, t = sensor.mesh.points, sensor.mesh.tets
    edges = np.linalg.norm(p[t[:, [1, 2, 3, 2, 3, 3]]] - p[t[:, [0, 0, 0, 1, 1, 2]]], axis=2)
    quality = 6 * np.sqrt(2) * sensor.mesh.volumes / (edges**2).mean(axis=1) ** 1.5  # 1 = regular tet
    assert quality.min() > 0.2
    # the pole is an ordinary vertex of the cubed-sphere top face (4 quads), not the apex of a fan
    # of 4 * cap_divisions thin triangles as in a latitude-longitude sweep
    pole = np.argmin(np.linalg.norm(p - sensor.dimensions.inner_pole, axis=1))
    assert np.linalg.norm(p[pole] - sensor.dimensions.inner_pole) < 1e-12
    assert np.count_nonzero(np.any(sensor.inner_faces == pole, axis=1)) <= 8


def test_clamped_vertices_lie_on_the_rim(sensor):
    p, d = sensor.mesh.points, sensor.dimensions
    clamped = sensor.clamped_vertices
    np.testing.assert_allclose(p[clamped, 2], d.z_rim, atol=1e-12)
    r = np.hypot(p[clamped, 0], p[clamped, 1])
    assert np.all((r >= 0.047 - 1e-12) & (r <= 0.050 + 1e-12))
    assert len(clamped) == 4 * 16 * (sensor.layers + 1)  # the whole rim ring, every layer
    band = build_membrane(cap_divisions=8, clamp_band=0.01)
    z = band.mesh.points[band.clamped_vertices, 2]
    assert z.max() <= band.dimensions.z_rim + 0.01 + 1e-12 and z.max() > band.dimensions.z_rim


def test_surface_faces_are_oriented(sensor):
    p, d = sensor.mesh.points, sensor.dimensions
    for faces, sign in ((sensor.inner_faces, -1.0), (sensor.outer_faces, 1.0)):
        n = np.cross(p[faces[:, 1]] - p[faces[:, 0]], p[faces[:, 2]] - p[faces[:, 0]])
        c = p[faces].mean(axis=1)
        radial = np.where(c[:, 2:3] > d.z_equator, c - d.center, c * [1, 1, 0])
        assert np.all(sign * np.einsum("ij,ij->i", n, radial) > 0)
    assert set(np.unique(sensor.inner_faces)) == set(sensor.inner_vertices)


# --------------------------------------------------------------------------- gas volume
def test_enclosed_volume_matches_hemisphere_plus_cylinder(sensor):
    analytic = 2 / 3 * np.pi * 0.047**3 + np.pi * 0.047**2 * 0.030
    assert np.isclose(sensor.dimensions.cavity_volume, analytic)
    err16 = sensor.cavity_volume / analytic - 1
    err32 = build_membrane(cap_divisions=32).cavity_volume / analytic - 1
    assert -0.005 < err16 < 0  # inscribed polyhedron: slightly smaller
    assert abs(err32) < abs(err16) / 3  # second-order convergence to the analytic volume
    assert np.isclose(sensor.gas_volume(), sensor.cavity_volume + np.pi * 0.047**2 * 0.10)


@pytest.mark.parametrize("delta", [0.005, 0.02])
def test_deformed_volume_of_a_flattened_cap(sensor, delta):
    """Push the cap flat at z_pole - delta: the gas loses a spherical cap, pi delta^2 (3R - delta) / 3."""
    d = sensor.dimensions
    p = sensor.mesh.points.copy()
    z_plane = d.inner_pole[2] - delta
    inner = sensor.inner_vertices
    p[inner, 2] = np.minimum(p[inner, 2], z_plane)
    cap = np.pi * delta**2 * (3 * d.inner_radius - delta) / 3
    expected = d.cavity_volume - cap
    assert abs(sensor.enclosed_volume(p) / expected - 1) < 0.005
    assert abs((sensor.cavity_volume - sensor.enclosed_volume(p)) / cap - 1) < 0.01


def test_enclosed_volume_rejects_bad_configurations(sensor):
    p = sensor.mesh.points.copy()
    with pytest.raises(MembraneError, match="shape"):
        sensor.enclosed_volume(p[:-1])
    p_nan = p.copy()
    p_nan[5, 0] = np.nan
    with pytest.raises(MembraneError, match="NaN"):
        sensor.enclosed_volume(p_nan)
    p[sensor.rim_loop[0], 2] += 1e-3
    with pytest.raises(MembraneError, match="rim"):
        sensor.enclosed_volume(p)


def test_pv_state_isothermal_law():
    state = PVState.from_pv(70.0, 6.0e-4)
    assert np.isclose(state.pv, 70.0) and np.isclose(state.pressure, 70.0 / 6.0e-4)
    squeezed = state.isothermal(5.5e-4)
    assert np.isclose(squeezed.pv, state.pv) and squeezed.pressure > state.pressure
    assert PVState.free_air(6e-4).gauge_pressure == 0.0 and ATMOSPHERIC_PRESSURE == 101325.0
    with pytest.raises(MembraneError, match="pressure"):
        PVState(float("nan"), 1e-3)
    with pytest.raises(MembraneError, match="volume"):
        state.isothermal(0.0)


def test_build_rejects_bad_resolution():
    with pytest.raises(MembraneError, match="layers"):
        build_membrane(layers=1)
    with pytest.raises(MembraneError, match="even"):
        build_membrane(cap_divisions=7)
    with pytest.raises(MembraneError, match="clamp_band"):
        build_membrane(clamp_band=-0.001)
    with pytest.raises(MembraneError, match="inner_radius"):
        MembraneDimensions(inner_radius=float("nan"))


# --------------------------------------------------------------------------- indenters
def test_analytic_signed_distances():
    sphere = SphereIndenter(radius=0.01, pose=Pose([0.0, 0.0, 0.2]))
    np.testing.assert_allclose(sphere.signed_distance([[0, 0, 0.2], [0.03, 0, 0.2]]), [-0.01, 0.02])
    box = BoxIndenter(size_x=0.02, size_y=0.04, size_z=0.06)
    np.testing.assert_allclose(
        box.signed_distance([[0.03, 0, 0], [0, 0, 0], [0.02, 0.03, 0]]), [0.02, -0.01, np.hypot(0.01, 0.01)]
    )
    ring = RingIndenter(outer_radius=0.02, inner_radius=0.01, height=0.01)
    np.testing.assert_allclose(
        ring.signed_distance([[0, 0, 0], [0.015, 0, 0], [0, 0.015, 0.015]]), [0.01, -0.005, 0.01]
    )
    np.testing.assert_allclose(FOREARM.signed_distance([[0.05, 0, 0.1], [0.2, 0, 0]]), [0.06, 0.06])
    # the meshes sample the analytic surfaces, at any pose
    pose = Pose([0.01, -0.02, 0.25], [0.3, -0.2, 0.1, 0.9])
    for ind in (FINGERTIP, FOREARM, RECTANGULAR_PRISM, RING, *CONTACT_SPHERES.values()):
        posed = ind.with_pose(pose)
        mesh = posed.trimesh()
        assert mesh.is_watertight
        assert np.abs(posed.signed_distance(mesh.vertices)).max() < 1e-9
        assert posed.lowest_z() <= mesh.vertices[:, 2].min() + 1e-9
    assert make_indenter("sphere", radius=0.015).radius == 0.015
    with pytest.raises(IndenterError, match="unknown indenter kind"):
        make_indenter("cone")


def test_nan_and_invalid_poses_raise():
    with pytest.raises(IndenterError, match="NaN"):
        Pose([0.0, np.nan, 0.1])
    with pytest.raises(IndenterError, match="NaN"):
        Pose.from_array([0, 0, 0.1, 0, 0, 0, np.nan])
    with pytest.raises(IndenterError, match="unit"):
        Pose([0, 0, 0.1], [0, 0, 0, 0])
    with pytest.raises(IndenterError, match="radius"):
        SphereIndenter(radius=-0.01)
    with pytest.raises(IndenterError, match="finite"):
        PokeCommand(np.nan, 0.01, 0.0, 0.01)
    with pytest.raises(IndenterError, match="twist"):
        ForearmCommand(0.01, twist=1.2)


def test_thesis_poke_grid_is_inside_the_workspace():
    dims = MembraneDimensions()
    grid = poke_grid()
    assert len(grid) == 10_000
    for cmd in grid[::37]:
        pose = cmd.indenter_pose(dims, FINGERTIP)
        # the sphere starts tangent to the outer surface and ends `depth` along the direction
        start = pose.position - cmd.depth * cmd.direction()
        assert np.isclose(np.linalg.norm(start - dims.center), dims.outer_radius + FINGERTIP.radius)
    pole = PokeCommand(0.0, 0.0, 0.0, 0.01).indenter_pose(dims, FINGERTIP)
    np.testing.assert_allclose(pole.position, dims.outer_pole + [0, 0, 0.005 - 0.01], atol=1e-15)
    assert len(forearm_grid()) == 1962


def test_indentation_beyond_the_rim_raises():
    dims = MembraneDimensions()
    with pytest.raises(WorkspaceError, match="rim"):
        PokeCommand(0.0, 0.045, 0.0, 0.01).indenter_pose(dims, FINGERTIP)  # contact beyond 4 cm
    with pytest.raises(WorkspaceError, match="rim"):
        # straight down from 4 cm through the whole sensor: the sphere ends below the rim plane
        PokeCommand(0.0, 0.04, 0.0, 0.08).indenter_pose(dims, FINGERTIP, max_contact_radius=0.05)
    with pytest.raises(WorkspaceError, match="rim"):
        check_workspace(RING.with_pose(Pose([0.0, 0.0, dims.z_rim])), dims)
    check_workspace(RING.with_pose(Pose([0.0, 0.0, dims.z_rim + 0.0101])), dims)
    with pytest.raises(WorkspaceError, match="outer radius"):
        ForearmCommand(0.06).indenter_pose(dims, FOREARM)


def test_forearm_pose_follows_the_device_motion():
    dims = MembraneDimensions()
    pose = ForearmCommand(0.01).indenter_pose(dims, FOREARM)
    assert np.isclose(FOREARM.with_pose(pose).lowest_z(), dims.outer_pole[2] - 0.01)
    sheared = ForearmCommand(0.01, shear_direction=np.pi / 2, shear_distance=0.01).indenter_pose(
        dims, FOREARM
    )
    np.testing.assert_allclose(sheared.position - pose.position, [0, -0.01, 0], atol=1e-15)
    twisted = ForearmCommand(0.01, twist=np.pi / 6).indenter_pose(dims, FOREARM)
    axis = twisted.rotation.apply([1.0, 0, 0])
    np.testing.assert_allclose(axis, [np.cos(np.pi / 6), -np.sin(np.pi / 6), 0], atol=1e-12)


@pytest.mark.parametrize("divisions", [4, 12, 20])
def test_mirror_symmetric_split_maps_the_inner_surface_onto_itself(divisions):
    """With ``mirror_symmetric`` every inner triangle's mirror image about x = 0 and about y = 0 is an inner
    triangle too (the cap's shorter-diagonal split already is; the skirt's rectangles are cut by quadrant);
    the default cuts every skirt rectangle along the same diagonal, which neither mirror keeps."""
    from scipy.spatial import cKDTree

    for symmetric in (True, False):
        sensor = build_membrane(cap_divisions=divisions, mirror_symmetric=symmetric)
        points, faces = sensor.mesh.points, sensor.inner_faces
        triangles = set(map(tuple, np.sort(faces, axis=1)))
        for mirror in ([-1.0, 1.0, 1.0], [1.0, -1.0, 1.0]):
            dist, image = cKDTree(points).query(points * mirror)
            assert dist.max() < 1e-12
            kept = np.mean([tuple(t) in triangles for t in np.sort(image[faces], axis=1)])
            assert kept == 1.0 if symmetric else kept < 0.9


def test_mirror_average_is_the_mirror_symmetric_part_of_a_field():
    """mirror_average of noisy positions is symmetric under both mirrors, idempotent, leaves the (symmetric)
    rest positions unchanged, and refuses NaN or a wrong shape."""
    from scipy.spatial import cKDTree

    from defgraspnets.tactile.membrane import mirror_average

    sensor = build_membrane(cap_divisions=8, mirror_symmetric=True)
    rest = sensor.mesh.points
    noisy = rest + np.random.default_rng(0).normal(scale=1e-4, size=rest.shape)
    sym = mirror_average(sensor, noisy)
    assert np.abs(sym - noisy).max() > 1e-5
    for mirror in ([-1.0, 1.0, 1.0], [1.0, -1.0, 1.0]):
        image = cKDTree(rest).query(rest * mirror)[1]
        np.testing.assert_allclose(sym[image] * mirror, sym, rtol=0, atol=1e-15)
    np.testing.assert_allclose(mirror_average(sensor, sym), sym, rtol=0, atol=1e-15)
    np.testing.assert_allclose(mirror_average(sensor, rest), rest, rtol=0, atol=1e-15)
    bad = noisy.copy()
    bad[3, 1] = np.nan
    with pytest.raises(MembraneError, match="finite"):
        mirror_average(sensor, bad)
    with pytest.raises(MembraneError, match="shape"):
        mirror_average(sensor, noisy[:-1])
