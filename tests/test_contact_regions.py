"""Contact regions (thesis §2.3, Algorithm 1) on analytic organized clouds rendered by a pinhole camera."""

import numpy as np
import pytest
from scipy.ndimage import binary_erosion

from defgraspnets.tactile.contact_regions import (
    SurfaceType,
    classify_surface,
    compare_regions,
    deformed_points,
    integral_image_normals,
    pixel_areas,
    region_area,
    region_boundary,
    surface_curvature,
)


def pixel_rays(height: int, width: int, focal: float) -> np.ndarray:
    """Unit ray directions (H, W, 3) of a pinhole camera at the origin looking along +z."""
    r, c = np.mgrid[0:height, 0:width].astype(float)
    d = np.stack(
        [(c - (width - 1) / 2) / focal, (r - (height - 1) / 2) / focal, np.ones((height, width))], -1
    )
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def render_sphere(center, radius, height=160, width=200, focal=300.0):
    """Organized cloud of the camera-facing side of a sphere (NaN where the ray misses)."""
    u = pixel_rays(height, width, focal)
    b = u @ center
    disc = b**2 - center @ center + radius**2
    with np.errstate(invalid="ignore"):
        t = b - np.sqrt(disc)
    return u * t[..., None]


def dented_membrane(
    indent=True,
    height=160,
    width=160,
    focal=80.0,
    dome_radius=0.05,
    dome_z=0.01,
    indenter_radius=0.01,
    depth=0.005,
    fillet=0.003,
):
    """Inflated hemispherical membrane seen from the inside camera, optionally dented by a sphere.

    Axisymmetric about the optical axis. In the meridional plane (rho, z) the membrane profile is
    the indenter's near arc (contact, Type C), a convex fillet circle tangent to indenter and dome
    (deformed, not in contact), then the undeformed dome. Returns the cloud and the true contact mask.
    """
    u = pixel_rays(height, width, focal)
    psi = np.arccos(u[..., 2])
    e = np.stack([np.sin(psi), np.cos(psi)], -1)

    def hit(centre, rad, sign):
        b = e @ centre
        with np.errstate(invalid="ignore"):
            return b + sign * np.sqrt(b**2 - centre @ centre + rad**2)

    o = np.array([0.0, dome_z])
    t = hit(o, dome_radius, +1)
    truth = np.zeros((height, width), dtype=bool)
    if indent:
        p = np.array([0.0, dome_z + dome_radius + indenter_radius - depth])
        dist = p[1] - o[1]
        a, b = dome_radius - fillet, indenter_radius + fillet
        zf = (a**2 - b**2 + dist**2) / (2 * dist)
        f = np.array([np.sqrt(a**2 - zf**2), dome_z + zf])
        t_dome = o + dome_radius * (f - o) / a
        t_ind = p + indenter_radius * (f - p) / b
        psi_ind = np.arctan2(t_ind[0], t_ind[1])
        psi_dome = np.arctan2(t_dome[0], t_dome[1])
        t = np.where(
            psi < psi_ind, hit(p, indenter_radius, -1), np.where(psi < psi_dome, hit(f, fillet, +1), t)
        )
        truth = psi < psi_ind
    return u * t[..., None], truth


def angle_deg(a, b):
    return np.degrees(np.arccos(np.clip(np.einsum("...k,...k", a, b), -1, 1)))


# ----------------------------------------------------------------------------- normals


def test_integral_image_normals_match_analytic_sphere():
    center, radius = np.array([0.01, -0.005, 0.25]), 0.05
    cloud = render_sphere(center, radius)
    valid = np.isfinite(cloud[..., 0])
    assert 2000 < valid.sum() < valid.size  # the sphere fills part of the image
    normals = integral_image_normals(cloud, window_radius=3)
    analytic = (cloud - center) / radius  # outward normals face the camera on the visible side
    # pixels whose whole window is valid and that are not grazing (silhouette) views
    win = binary_erosion(valid, np.ones((9, 9), dtype=bool), border_value=0)
    view = -cloud / np.linalg.norm(cloud, axis=-1, keepdims=True)
    inner = win & (np.einsum("ijk,ijk->ij", np.nan_to_num(analytic), np.nan_to_num(view)) > 0.5)
    err = angle_deg(normals[inner], analytic[inner])
    assert inner.sum() > 1500
    assert np.median(err) < 0.2
    assert err.max() < 1.0
    # every valid pixel gets a normal facing the camera (border pixels use a clipped window)
    assert np.isfinite(normals[valid]).all()
    assert (np.einsum("ij,ij->i", normals[valid], -cloud[valid]) > 0).all()
    assert np.isnan(normals[~valid]).all()


def test_normals_face_the_viewpoint_and_handle_nan_holes():
    cloud = render_sphere(np.array([0.0, 0.0, 0.3]), 0.08, 60, 60, 100.0)
    holed = cloud.copy()
    holed[25:28, 25:28] = np.nan  # a hole of invalid returns inside the object
    n = integral_image_normals(holed, window_radius=2)
    ok = np.isfinite(holed[..., 0])
    assert np.isfinite(n[ok]).all() and np.isnan(n[~ok]).all()
    away = integral_image_normals(cloud, window_radius=2, viewpoint=(0.0, 0.0, 1.0))
    ok = np.isfinite(cloud[..., 0])
    assert (away[ok][:, 2] > 0).all()  # viewpoint behind the sphere flips the normals


def test_bad_clouds_are_rejected():
    with pytest.raises(ValueError, match=r"\(H, W, 3\)"):
        integral_image_normals(np.zeros((10, 10)))
    with pytest.raises(ValueError, match="no valid"):
        integral_image_normals(np.full((5, 5, 3), np.nan))
    with pytest.raises(ValueError, match="window_radius"):
        integral_image_normals(np.ones((5, 5, 3)), window_radius=0)
    with pytest.raises(ValueError, match="same shape"):
        classify_surface(np.ones((5, 5, 3)), np.ones((6, 5, 3)))
    with pytest.raises(ValueError, match="offset"):
        surface_curvature(np.ones((5, 5, 3)), np.ones((5, 5, 3)), 0)


# ----------------------------------------------------------------------------- curvature and classification


def test_curvature_sign_changes_where_a_sphere_dents_the_convex_membrane():
    reference, _ = dented_membrane(indent=False)
    cloud, truth = dented_membrane()
    p = 3
    kx0, ky0 = surface_curvature(reference, integral_image_normals(reference, 2), p)
    # the undeformed convex membrane has kappa < 0 everywhere: no false contact before contact
    assert np.nanmax(kx0) < 0 and np.nanmax(ky0) < 0
    # analytic value on the dome: kappa = -|x - y|^2 / R
    c = reference.shape[0] // 2
    chord = np.linalg.norm(reference[c, c - p] - reference[c, c + p])
    assert kx0[c, c] == pytest.approx(-(chord**2) / 0.05, rel=0.02)
    kx, ky = surface_curvature(cloud, integral_image_normals(cloud, 2), p)
    assert kx[c, c] > 0 and ky[c, c] > 0  # membrane wrapped on the indenter
    chord = np.linalg.norm(cloud[c, c - p] - cloud[c, c + p])
    assert kx[c, c] == pytest.approx(chord**2 / 0.01, rel=0.05)
    assert kx[c, 5] < 0 and ky[5, c] < 0  # far from the dent


def test_algorithm1_recovers_the_contact_region_of_a_spherical_dent():
    reference, _ = dented_membrane(indent=False)
    cloud, truth = dented_membrane()
    result = classify_surface(cloud, reference, offset=3, deformation_threshold=1e-4, window_radius=2)
    labels = result.labels
    assert labels.dtype == np.int8
    assert set(np.unique(labels)) <= {int(s) for s in SurfaceType}
    # everything outside the deformed zone is A; deformed pixels are B or C
    assert (labels[result.displacement <= 1e-4] == SurfaceType.UNDEFORMED).all()
    assert (labels[truth] != SurfaceType.UNDEFORMED).all()
    assert (labels == SurfaceType.DEFORMED_FREE).sum() > 0  # the convex fillet (Type B) exists
    comparison = compare_regions(cloud, result.contact_mask, truth)
    assert comparison.iou > 0.7
    # the thesis reports ~3 mm maximum boundary error for spherical obstacles
    assert comparison.mean_boundary_distance < 1.5e-3
    assert comparison.max_boundary_distance < 3.0e-3
    assert comparison.estimated_area == pytest.approx(comparison.true_area, rel=0.4)
    # the core of the true contact is always found
    core = truth.copy()
    for _ in range(3):
        core &= ~region_boundary(core)
    assert result.contact_mask[core].all()


def test_undeformed_membrane_is_all_type_a():
    reference, _ = dented_membrane(indent=False)
    result = classify_surface(reference, reference, offset=3, deformation_threshold=1e-4)
    assert (result.labels == SurfaceType.UNDEFORMED).all()
    assert deformed_points(reference, reference).shape == (0, 3)


def test_invalid_pixels_are_labelled_invalid():
    reference, _ = dented_membrane(indent=False, height=40, width=40, focal=20.0)
    cloud, _ = dented_membrane(height=40, width=40, focal=20.0)
    cloud[0, 0] = np.nan
    result = classify_surface(cloud, reference, offset=2, deformation_threshold=1e-4)
    assert result.labels[0, 0] == SurfaceType.INVALID
    pts = deformed_points(cloud, reference, 1e-4)
    assert pts.shape[0] == result.deformed_mask.sum()


# ----------------------------------------------------------------------------- areas and comparison


def test_pixel_area_of_a_fronto_parallel_plane():
    focal, z = 250.0, 0.2
    u = pixel_rays(30, 40, focal)
    plane = u * (z / u[..., 2])[..., None]
    areas = pixel_areas(plane)
    assert np.allclose(areas, z**2 / focal**2, rtol=1e-9)
    assert region_area(plane, np.ones((30, 40), dtype=bool)) == pytest.approx(1200 * z**2 / focal**2)


def test_contact_area_matches_the_spherical_cap():
    cloud, truth = dented_membrane(height=240, width=240, focal=120.0)
    # analytic cap of the indenter inside the contact circle
    r, depth, rad, fillet = 0.01, 0.005, 0.05, 0.003
    dist = rad + r - depth
    a, b = rad - fillet, r + fillet
    zf = (a**2 - b**2 + dist**2) / (2 * dist)
    rho_f = np.sqrt(a**2 - zf**2)
    cos_cap = (dist - zf) / b  # angle at the indenter centre between the axis and the tangent point
    cap = 2 * np.pi * r**2 * (1 - cos_cap)
    assert rho_f > 0
    assert region_area(cloud, truth) == pytest.approx(cap, rel=0.02)


def test_compare_regions_reports_distance_between_boundaries():
    focal, z = 100.0, 0.1
    u = pixel_rays(50, 50, focal)
    plane = u * (z / u[..., 2])[..., None]
    truth = np.zeros((50, 50), dtype=bool)
    truth[10:30, 10:30] = True
    shifted = np.roll(truth, 2, axis=1)
    cmp = compare_regions(plane, shifted, truth)
    spacing = z / focal
    assert cmp.iou == pytest.approx(18 * 20 / (22 * 20))
    assert cmp.max_boundary_distance == pytest.approx(2 * spacing, rel=0.01)
    assert 0 < cmp.mean_boundary_distance < 2 * spacing
    same = compare_regions(plane, truth, truth)
    assert same.iou == 1.0 and same.max_boundary_distance == 0.0
    empty = compare_regions(plane, np.zeros_like(truth), truth)
    assert empty.iou == 0.0 and empty.mean_boundary_distance == np.inf
    with pytest.raises(ValueError, match="empty"):
        compare_regions(plane, truth, np.zeros_like(truth))
