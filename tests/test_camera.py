"""Depth camera: analytic hemisphere + cylinder images, dents, refits, noise, bad inputs."""

import numpy as np
import pytest

from defgraspnets.tactile.camera import PICO_FLEXX, CameraError, CameraIntrinsics, DepthCamera, ToFNoise
from defgraspnets.tactile.membrane import build_membrane


@pytest.fixture(scope="module")
def sensor():
    return build_membrane(cap_divisions=16)


@pytest.fixture(scope="module")
def reference(sensor):
    return DepthCamera().reference(sensor)


def analytic_depth(k: CameraIntrinsics, dims) -> tuple[np.ndarray, np.ndarray]:
    """Exact depth of the inner cavity (cylinder r = R below z_eq, sphere above), and the hit radius.

    A pixel ray x = s (a, b, 1) from the origin has radius rho z at height z, rho = |(a, b)|: it hits the
    skirt at z = R / rho if z_rim <= z <= z_eq, passes outside the rim (NaN) if R / rho < z_rim, and
    otherwise leaves through the hemisphere |x - (0, 0, z_eq)| = R at the far root
    z = (z_eq + sqrt(z_eq^2 - (rho^2 + 1)(z_eq^2 - R^2))) / (rho^2 + 1).
    """
    d = k.ray_directions()
    rho = np.hypot(d[..., 0], d[..., 1])
    r, z_rim, z_eq = dims.inner_radius, dims.z_rim, dims.z_equator
    with np.errstate(divide="ignore", invalid="ignore"):
        z_cyl = r / rho
        a = rho**2 + 1
        z_sph = (z_eq + np.sqrt(np.maximum(z_eq**2 - a * (z_eq**2 - r**2), 0.0))) / a
    z = np.where(z_cyl >= z_eq, z_sph, z_cyl)
    z = np.where(z_cyl < z_rim, np.nan, z)
    return z, rho * z


def test_pico_flexx_intrinsics():
    assert PICO_FLEXX.shape == (171, 224)
    h_fov, v_fov = np.degrees(PICO_FLEXX.field_of_view)
    assert 50 < h_fov < 62 and 40 < v_fov < 45  # undistorted pinhole inside the datasheet's 62 x 45 deg
    half = PICO_FLEXX.scaled(0.5)
    assert half.shape == (86, 112)
    np.testing.assert_allclose(
        np.degrees(half.field_of_view), np.degrees(PICO_FLEXX.field_of_view), rtol=0.01
    )
    with pytest.raises(CameraError, match="focal"):
        CameraIntrinsics(fx=0.0)


def test_undeformed_image_matches_analytic_cavity(sensor, reference):
    k, dims = PICO_FLEXX, sensor.dimensions
    z, _ = analytic_depth(k, dims)
    frame = reference
    assert frame.depth.shape == (171, 224) and frame.points.shape == (171, 224, 3)
    assert frame.depth.dtype == np.float32
    # validity agrees except for rays grazing the rim (the rim is a 64-gon inscribed in the circle)
    d = k.ray_directions()
    rim_radius = np.hypot(d[..., 0], d[..., 1]) * dims.z_rim
    sagitta = dims.inner_radius * (1 - np.cos(np.pi / 64))
    mismatch = np.isfinite(z) != frame.valid
    assert np.all(np.abs(rim_radius[mismatch] - dims.inner_radius) <= 1.01 * sagitta)
    assert frame.valid.mean() > 0.7
    both = np.isfinite(z) & frame.valid
    err = np.abs(frame.depth - z)[both]
    assert err.max() < 4e-4 and np.median(err) < 1.5e-4  # [m], second-order discretization error
    # ... which shrinks ~4x when the element size halves
    fine = DepthCamera(k.scaled(0.25)).reference(build_membrane(cap_divisions=32))
    coarse = DepthCamera(k.scaled(0.25)).reference(build_membrane(cap_divisions=8))
    z4, _ = analytic_depth(k.scaled(0.25), dims)
    err_fine, err_coarse = (np.nanmax(np.abs(f.depth - z4)) for f in (fine, coarse))
    assert err_fine < err_coarse / 3
    # organized point cloud: on the pixel rays, z = depth, NaN together
    np.testing.assert_allclose(frame.points[..., 2], frame.depth, rtol=1e-6)
    np.testing.assert_allclose(frame.points[..., 0][both] / frame.depth[both], d[..., 0][both], atol=1e-6)
    assert np.all(np.isnan(frame.points[~frame.valid])) and np.all(frame.face[~frame.valid] == -1)


def test_dent_changes_depth_only_inside_the_dent(sensor, reference):
    """Flatten the inner cap at z_pole - delta: depth becomes z_plane inside the dent, unchanged outside."""
    dims = sensor.dimensions
    delta = 0.008
    z_plane = dims.inner_pole[2] - delta
    dent_radius = np.sqrt(2 * dims.inner_radius * delta - delta**2)
    p = sensor.mesh.points.copy()
    inner = sensor.inner_vertices
    p[inner, 2] = np.minimum(p[inner, 2], z_plane)
    camera = DepthCamera()
    camera.reference(sensor)  # build the BVH on the rest shape, then refit to the dent
    dented = camera.render(*sensor.inner_surface(p))
    _, hit_radius = analytic_depth(PICO_FLEXX, dims)
    h = 2 * np.pi * dims.inner_radius / 64  # element size
    outside = reference.valid & (hit_radius > dent_radius + h)
    inside = reference.valid & (hit_radius < dent_radius - h)
    assert inside.sum() > 500 and outside.sum() > 5000
    np.testing.assert_array_equal(dented.depth[outside], reference.depth[outside])
    np.testing.assert_allclose(dented.depth[inside], z_plane, atol=1e-6)
    np.testing.assert_array_equal(dented.valid, reference.valid)
    changed = reference.valid & (dented.depth != reference.depth)
    assert changed.sum() >= inside.sum()
    assert np.all(hit_radius[changed] < dent_radius + h)
    assert np.all(dented.depth[changed] <= reference.depth[changed] + 1e-7)  # pushed towards the camera
    # the refit BVH gives the same image as a camera built on the dented surface directly
    fresh = DepthCamera().render(*sensor.inner_surface(p))
    np.testing.assert_array_equal(fresh.depth, dented.depth)


def test_noise_is_seeded_depth_dependent_and_along_rays(sensor, reference):
    noise = ToFNoise(relative_sigma=0.01, seed=7)
    a = DepthCamera(noise=noise).render(*sensor.inner_surface())
    b = DepthCamera(noise=noise).render(*sensor.inner_surface())
    c = DepthCamera(noise=ToFNoise(relative_sigma=0.01, seed=8)).render(*sensor.inner_surface())
    np.testing.assert_array_equal(a.depth, b.depth)
    assert not np.array_equal(a.depth, c.depth)
    v = reference.valid
    rel = a.depth[v] / reference.depth[v] - 1  # = relative range error along the ray
    assert abs(rel.std() - 0.01) < 0.001 and abs(rel.mean()) < 0.001
    cross = np.cross(a.points[v], reference.points[v])
    assert np.abs(cross).max() < 1e-7  # noisy points stay on their pixel rays
    np.testing.assert_array_equal(np.isfinite(a.depth), v)
    np.testing.assert_array_equal(DepthCamera(noise=noise).reference(sensor).depth, reference.depth)


def test_working_range_and_bad_inputs(sensor):
    near = DepthCamera(CameraIntrinsics(min_range=0.15).scaled(0.25)).reference(sensor)
    assert np.nanmin(near.depth) >= 0.15 and np.isnan(near.depth).any()
    camera = DepthCamera(PICO_FLEXX.scaled(0.25))
    with pytest.raises(CameraError, match="no surface"):
        camera.render()
    vertices, faces = sensor.inner_surface()
    bad = vertices.copy()
    bad[3, 1] = np.nan
    with pytest.raises(CameraError, match="NaN"):
        camera.render(bad, faces)
    with pytest.raises(CameraError, match="face indices"):
        camera.render(vertices, faces + len(vertices))
    with pytest.raises(CameraError, match="shape"):
        camera.render(vertices[:, :2], faces)
    with pytest.raises(CameraError, match="position"):
        DepthCamera(position=(0.0, np.nan, 0.0))
