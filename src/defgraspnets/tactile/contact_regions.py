"""Contact regions of the tactile membrane from an organized point cloud (thesis §2.3, Algorithm 1).

The interior depth camera images the membrane as an *organized* point cloud ``P`` of shape
(H, W, 3) [m] in the camera frame: pixel (row r, column c) holds the 3D point seen along that
pixel's ray, or NaN where the camera has no valid return. Every surface element is one of

- **Type A** — undeformed: the element keeps its pre-contact position,
- **Type B** — deformed, not in contact: moved, but held only by membrane tension,
- **Type C** — deformed and in contact with the obstacle.

Deformation is decided by comparison with the undeformed reference cloud ``P_0`` (same camera,
same pixels): a pixel is deformed when ``|P(r, c) - P_0(r, c)| > deformation_threshold`` [m].
B and C are told apart by the sign of the local curvature signal of eq. (2.1) (Ito et al.),

    kappa(x, y) = < x - y, n(x) - n(y) >                                         (2.1)

evaluated on the two surface curves through the element along the image axes, between the
neighbours at pixel offset ``p`` (Algorithm 1)::

    x_neighbors <- (c - p, r), (c + p, r);   y_neighbors <- (c, r - p), (c, r + p)
    if ISUNDEFORMED(c, r): return A
    elif CONVEXITY(x_neighbors) >= 0 or CONVEXITY(y_neighbors) >= 0: return C
    else: return B

``kappa`` has units of metres (a length times a difference of unit vectors). With the normals
oriented toward the camera (inside the membrane), a convex membrane — the undeformed inflated
hemisphere — has ``kappa = -|x - y|^2 / R < 0``, while membrane pressed onto a convex obstacle of
radius ``r`` follows the obstacle and has ``kappa = +|x - y|^2 / r > 0``: the sign change marks
external load. ``curvature_threshold`` (default 0 m, the thesis's test) can demand a margin.

Normals are estimated like PCL's ``IntegralImageNormalEstimation`` with the
``AVERAGE_3D_GRADIENT`` method: central differences of the cloud along the image columns and
rows, summed over a rectangular window with integral images (finite differences only), and
the normal is the cross product of the two summed gradients, flipped toward the viewpoint.

Areas come from the organized structure: a pixel covers the parallelogram spanned by half the
distances to its neighbours along both image axes, ``dA = |dP/dc x dP/dr|``.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

import numpy as np
from scipy.spatial import cKDTree

__all__ = [
    "RegionComparison",
    "SurfaceClassification",
    "SurfaceType",
    "classify_surface",
    "compare_regions",
    "deformed_points",
    "integral_image_normals",
    "pixel_areas",
    "region_area",
    "region_boundary",
    "surface_curvature",
]


class SurfaceType(IntEnum):
    """Per-pixel label of Algorithm 1 (stored as ``int8`` in label images)."""

    INVALID = -1  # no valid return in the cloud or the reference, or curvature undefined
    UNDEFORMED = 0  # Type A
    DEFORMED_FREE = 1  # Type B: deformed, not in contact
    CONTACT = 2  # Type C: deformed and in contact


# ----------------------------------------------------------------------------- validation


def _organized_cloud(cloud: np.ndarray, name: str = "cloud") -> np.ndarray:
    """Return ``cloud`` as float64 (H, W, 3); a pixel with any non-finite coordinate becomes all-NaN."""
    arr = np.asarray(cloud, dtype=np.float64)
    if arr.ndim != 3 or arr.shape[2] != 3:
        raise ValueError(f"{name} must be an organized point cloud of shape (H, W, 3), got {arr.shape}")
    if arr.shape[0] < 3 or arr.shape[1] < 3:
        raise ValueError(f"{name} must be at least 3 x 3 pixels, got {arr.shape[:2]}")
    bad = ~np.isfinite(arr).all(axis=2)
    if bad.all():
        raise ValueError(f"{name} has no valid (finite) pixel")
    if bad.any():
        arr = arr.copy()
        arr[bad] = np.nan
    return arr


def _mask(mask: np.ndarray, shape: tuple[int, int], name: str) -> np.ndarray:
    m = np.asarray(mask)
    if m.shape != shape:
        raise ValueError(f"{name} must have the image shape {shape}, got {m.shape}")
    if m.dtype != np.bool_:
        raise ValueError(f"{name} must be a boolean mask, got dtype {m.dtype}")
    return m


# ----------------------------------------------------------------------------- normals


def _box_sum(values: np.ndarray, half_rows: int, half_cols: int) -> np.ndarray:
    """Sum of ``values`` (H, W, ...) over the window ``[r-hr, r+hr] x [c-hc, c+hc]`` clipped to the image.

    Uses a zero-padded integral image ``I[r, c] = sum(values[:r, :c])``, so each window sum costs
    four look-ups regardless of the window size.
    """
    h, w = values.shape[:2]
    integral = np.zeros((h + 1, w + 1) + values.shape[2:], dtype=np.float64)
    integral[1:, 1:] = values.cumsum(axis=0).cumsum(axis=1)
    r = np.arange(h)
    c = np.arange(w)
    r0 = np.clip(r - half_rows, 0, h)[:, None]
    r1 = np.clip(r + half_rows + 1, 0, h)[:, None]
    c0 = np.clip(c - half_cols, 0, w)[None, :]
    c1 = np.clip(c + half_cols + 1, 0, w)[None, :]
    return integral[r1, c1] - integral[r0, c1] - integral[r1, c0] + integral[r0, c0]


def _central_difference(cloud: np.ndarray, axis: int, max_depth_change: float | None) -> np.ndarray:
    """``P(i+1) - P(i-1)`` along image ``axis`` (0 rows, 1 columns); NaN at borders and across gaps."""
    diff = np.full_like(cloud, np.nan)
    if axis == 1:
        diff[:, 1:-1] = cloud[:, 2:] - cloud[:, :-2]
    else:
        diff[1:-1, :] = cloud[2:, :] - cloud[:-2, :]
    if max_depth_change is not None:
        with np.errstate(invalid="ignore"):
            diff[np.abs(diff[..., 2]) > max_depth_change] = np.nan
    return diff


def integral_image_normals(
    cloud: np.ndarray,
    window_radius: int = 3,
    viewpoint: np.ndarray | tuple[float, float, float] = (0.0, 0.0, 0.0),
    max_depth_change: float | None = None,
) -> np.ndarray:
    """Unit surface normals of an organized cloud by integral images (PCL ``AVERAGE_3D_GRADIENT``).

    For every pixel the central differences ``D_c = P(r, c+1) - P(r, c-1)`` and
    ``D_r = P(r+1, c) - P(r-1, c)`` are summed over the ``(2 h + 1) x (2 h + 1)`` window
    (``h = window_radius``) clipped to the image, skipping differences that touch an invalid
    pixel; the normal is ``n = (sum D_r) x (sum D_c)`` normalized and flipped so that
    ``<n, viewpoint - P> > 0``. Border pixels use the valid part of their window.

    Args:
        cloud: (H, W, 3) organized point cloud [m]; NaN marks invalid pixels.
        window_radius: half-size ``h`` of the smoothing window [pixels], >= 1.
        viewpoint: (3,) point the normals face [m], the camera centre by default.
        max_depth_change: if given, differences whose z component exceeds it [m] are treated
            as depth discontinuities and excluded (PCL's max depth change).

    Returns:
        (H, W, 3) unit normals; NaN at invalid pixels and where the window holds no valid
        difference along one of the axes.
    """
    p = _organized_cloud(cloud)
    if int(window_radius) != window_radius or window_radius < 1:
        raise ValueError(f"window_radius must be an integer >= 1 pixel, got {window_radius}")
    h = int(window_radius)
    vp = np.asarray(viewpoint, dtype=np.float64)
    if vp.shape != (3,) or not np.isfinite(vp).all():
        raise ValueError(f"viewpoint must be a finite (3,) point, got {viewpoint!r}")
    if max_depth_change is not None and not max_depth_change > 0:
        raise ValueError(f"max_depth_change must be > 0 m, got {max_depth_change}")

    sums = []
    for axis in (1, 0):
        diff = _central_difference(p, axis, max_depth_change)
        finite = np.isfinite(diff).all(axis=2)
        summed = _box_sum(np.where(finite[..., None], diff, 0.0), h, h)
        count = _box_sum(finite.astype(np.float64), h, h)
        summed[count < 0.5] = np.nan
        sums.append(summed)
    grad_c, grad_r = sums
    normal = np.cross(grad_r, grad_c)
    norm = np.linalg.norm(normal, axis=2, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        normal = normal / norm
    normal[~(norm[..., 0] > 0)] = np.nan
    facing = np.einsum("ijk,ijk->ij", normal, vp - p)
    normal[facing < 0] *= -1.0
    normal[np.isnan(p[..., 0])] = np.nan
    return normal


# ----------------------------------------------------------------------------- curvature


def _shift(a: np.ndarray, rows: int, cols: int) -> np.ndarray:
    """``out[r, c] = a[r + rows, c + cols]``, NaN outside the image."""
    out = np.full_like(a, np.nan)
    h, w = a.shape[:2]
    dst_r = slice(max(0, -rows), min(h, h - rows))
    dst_c = slice(max(0, -cols), min(w, w - cols))
    src_r = slice(max(0, rows), min(h, h + rows))
    src_c = slice(max(0, cols), min(w, w + cols))
    out[dst_r, dst_c] = a[src_r, src_c]
    return out


def surface_curvature(cloud: np.ndarray, normals: np.ndarray, offset: int) -> tuple[np.ndarray, np.ndarray]:
    """Curvature signal of eq. (2.1) along both image axes at pixel offset ``p``.

    ``kappa_x(r, c) = < P(r, c-p) - P(r, c+p), n(r, c-p) - n(r, c+p) >`` (image columns) and
    ``kappa_y(r, c) = < P(r-p, c) - P(r+p, c), n(r-p, c) - n(r+p, c) >`` (image rows).

    Args:
        cloud: (H, W, 3) organized point cloud [m].
        normals: (H, W, 3) unit normals, oriented consistently (e.g. toward the camera).
        offset: ``p`` [pixels], >= 1; sets the size of the surface element.

    Returns:
        ``(kappa_x, kappa_y)``, each (H, W) [m]; NaN where a neighbour is outside the image or invalid.
    """
    p = _organized_cloud(cloud)
    n = np.asarray(normals, dtype=np.float64)
    if n.shape != p.shape:
        raise ValueError(f"normals must have the cloud's shape {p.shape}, got {n.shape}")
    if int(offset) != offset or offset < 1:
        raise ValueError(f"offset p must be an integer >= 1 pixel, got {offset}")
    k = int(offset)
    kappas = []
    for dr, dc in ((0, k), (k, 0)):
        dx = _shift(p, -dr, -dc) - _shift(p, dr, dc)
        dn = _shift(n, -dr, -dc) - _shift(n, dr, dc)
        kappas.append(np.einsum("ijk,ijk->ij", dx, dn))
    return kappas[0], kappas[1]


# ----------------------------------------------------------------------------- classification


@dataclass(frozen=True)
class SurfaceClassification:
    """Result of Algorithm 1 on one organized cloud.

    Attributes:
        labels: (H, W) int8 :class:`SurfaceType` values.
        displacement: (H, W) ``|P - P_0|`` [m] against the undeformed reference.
        normals: (H, W, 3) unit normals facing the camera.
        kappa_x, kappa_y: (H, W) curvature signals of eq. (2.1) along image columns / rows [m].
    """

    labels: np.ndarray
    displacement: np.ndarray
    normals: np.ndarray
    kappa_x: np.ndarray
    kappa_y: np.ndarray

    @property
    def contact_mask(self) -> np.ndarray:
        """Type C pixels."""
        return self.labels == SurfaceType.CONTACT

    @property
    def deformed_mask(self) -> np.ndarray:
        """Type B or C pixels."""
        return (self.labels == SurfaceType.CONTACT) | (self.labels == SurfaceType.DEFORMED_FREE)

    @property
    def undeformed_mask(self) -> np.ndarray:
        """Type A pixels."""
        return self.labels == SurfaceType.UNDEFORMED


def _displacement(cloud: np.ndarray, reference_cloud: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    p = _organized_cloud(cloud)
    p0 = _organized_cloud(reference_cloud, "reference_cloud")
    if p.shape != p0.shape:
        raise ValueError(f"cloud {p.shape} and reference_cloud {p0.shape} must have the same shape")
    return p, np.linalg.norm(p - p0, axis=2)


def classify_surface(
    cloud: np.ndarray,
    reference_cloud: np.ndarray,
    offset: int = 10,
    deformation_threshold: float = 1.0e-3,
    curvature_threshold: float = 0.0,
    window_radius: int = 3,
    viewpoint: np.ndarray | tuple[float, float, float] = (0.0, 0.0, 0.0),
    max_depth_change: float | None = None,
) -> SurfaceClassification:
    """Classify every pixel of the membrane cloud as Type A, B or C (Algorithm 1).

    A pixel is **A** when ``|P - P_0| <= deformation_threshold``; otherwise **C** when
    ``kappa_x >= curvature_threshold`` or ``kappa_y >= curvature_threshold`` (eq. 2.1 at offset
    ``p``, normals toward ``viewpoint``), else **B**. A deformed pixel whose two curvature
    signals are both undefined (neighbours outside the image or invalid) is
    :attr:`SurfaceType.INVALID`, as is any pixel invalid in either cloud; when only one is
    defined, that one decides.

    Args:
        cloud: (H, W, 3) deformed membrane cloud [m], camera frame.
        reference_cloud: (H, W, 3) undeformed membrane cloud [m] from the same camera.
        offset: ``p`` [pixels]; the thesis used ``p = 10`` on the 224 x 171 pico flexx images,
            chosen so that the pre-contact membrane has no false Type C pixel.
        deformation_threshold: displacement above which a pixel is deformed [m] (~ depth noise).
        curvature_threshold: ``kappa`` at or above which a curve counts as concave [m]; 0 in the thesis.
        window_radius: half-size of the normal-estimation window [pixels].
        viewpoint: the point normals face [m] (camera centre).
        max_depth_change: optional depth-discontinuity limit for the normals [m].
    """
    p, disp = _displacement(cloud, reference_cloud)
    if not deformation_threshold >= 0:
        raise ValueError(f"deformation_threshold must be >= 0 m, got {deformation_threshold}")
    if not np.isfinite(curvature_threshold):
        raise ValueError(f"curvature_threshold must be finite, got {curvature_threshold}")
    normals = integral_image_normals(p, window_radius, viewpoint, max_depth_change)
    kx, ky = surface_curvature(p, normals, offset)

    labels = np.full(p.shape[:2], SurfaceType.INVALID, dtype=np.int8)
    valid = np.isfinite(disp)
    undeformed = valid & (disp <= deformation_threshold)
    deformed = valid & ~undeformed
    with np.errstate(invalid="ignore"):
        concave = (kx >= curvature_threshold) | (ky >= curvature_threshold)
    curvature_known = np.isfinite(kx) | np.isfinite(ky)
    labels[undeformed] = SurfaceType.UNDEFORMED
    labels[deformed & curvature_known & concave] = SurfaceType.CONTACT
    labels[deformed & curvature_known & ~concave] = SurfaceType.DEFORMED_FREE
    return SurfaceClassification(labels, disp, normals, kx, ky)


def deformed_points(
    cloud: np.ndarray, reference_cloud: np.ndarray, deformation_threshold: float = 1.0e-3
) -> np.ndarray:
    """Points of the cloud displaced by more than ``deformation_threshold`` [m] from the reference.

    This is the "deformed point cloud" (Type B and C) used by the contour-following controller
    (ch. 4) and the tactile features (§5.3). Returns (N, 3) [m] in the camera frame; N may be 0.
    """
    p, disp = _displacement(cloud, reference_cloud)
    if not deformation_threshold >= 0:
        raise ValueError(f"deformation_threshold must be >= 0 m, got {deformation_threshold}")
    with np.errstate(invalid="ignore"):
        return p[disp > deformation_threshold]


# ----------------------------------------------------------------------------- areas


def pixel_areas(cloud: np.ndarray) -> np.ndarray:
    """Surface area covered by each pixel of an organized cloud [m^2].

    ``dA = |t_c x t_r|`` with the tangents ``t_c = dP/dc`` and ``t_r = dP/dr`` per pixel step,
    the mean of the forward and backward differences where both exist (central difference),
    the one that exists at borders and next to invalid pixels. For a fronto-parallel plane at
    depth z seen by a pinhole camera with focal lengths (f_x, f_y) [pixels], ``dA = z^2 / (f_x f_y)``.

    Returns:
        (H, W) areas; NaN at invalid pixels and where an axis has no valid neighbour.
    """
    p = _organized_cloud(cloud)
    tangents = []
    for rows, cols in ((0, 1), (1, 0)):
        forward = _shift(p, rows, cols) - p
        backward = p - _shift(p, -rows, -cols)
        stacked = np.stack([forward, backward])
        ok = np.isfinite(stacked).all(axis=3)
        count = ok.sum(axis=0)
        total = np.where(ok[..., None], stacked, 0.0).sum(axis=0)
        with np.errstate(invalid="ignore", divide="ignore"):
            t = total / count[..., None]
        t[count == 0] = np.nan
        tangents.append(t)
    return np.linalg.norm(np.cross(tangents[0], tangents[1]), axis=2)


def region_area(cloud: np.ndarray, mask: np.ndarray) -> float:
    """Area of the surface region ``mask`` of an organized cloud [m^2] (sum of :func:`pixel_areas`).

    Pixels whose area is undefined (isolated pixels) contribute nothing.
    """
    areas = pixel_areas(cloud)
    m = _mask(mask, areas.shape, "mask")
    return float(np.nansum(areas[m]))


# ----------------------------------------------------------------------------- region comparison


def region_boundary(mask: np.ndarray) -> np.ndarray:
    """Boundary pixels of a boolean region: in ``mask`` with a 4-neighbour outside it (or off-image)."""
    m = np.asarray(mask)
    if m.ndim != 2 or m.dtype != np.bool_:
        raise ValueError(f"mask must be a 2D boolean image, got shape {m.shape} dtype {m.dtype}")
    padded = np.pad(m, 1, constant_values=False)
    interior = (
        padded[1:-1, 1:-1] & padded[:-2, 1:-1] & padded[2:, 1:-1] & padded[1:-1, :-2] & padded[1:-1, 2:]
    )
    return m & ~interior


@dataclass(frozen=True)
class RegionComparison:
    """Agreement of an estimated contact region with the true one on the same organized cloud.

    Attributes:
        iou: intersection over union of the pixel masks.
        mean_boundary_distance: symmetric mean distance between the two boundaries [m]: the
            average of the mean distance from each estimated boundary point to the nearest true
            boundary point and vice versa.
        max_boundary_distance: symmetric Hausdorff distance between the boundaries [m] (the
            thesis's "maximum boundary detection error").
        estimated_area, true_area: region areas [m^2].
    """

    iou: float
    mean_boundary_distance: float
    max_boundary_distance: float
    estimated_area: float
    true_area: float


def compare_regions(cloud: np.ndarray, estimated_mask: np.ndarray, true_mask: np.ndarray) -> RegionComparison:
    """Boundary error and IoU of an estimated region against ground truth, distances in 3D [m].

    Boundary pixels (see :func:`region_boundary`) are lifted to their cloud points. When the
    estimate is empty but the truth is not, the boundary distances are ``inf`` and IoU is 0.

    Raises:
        ValueError: if the true region is empty or a mask covers invalid pixels.
    """
    p = _organized_cloud(cloud)
    shape = p.shape[:2]
    est = _mask(estimated_mask, shape, "estimated_mask")
    true = _mask(true_mask, shape, "true_mask")
    if not true.any():
        raise ValueError("true_mask is empty: nothing to compare against")
    invalid = np.isnan(p[..., 0])
    if (est & invalid).any() or (true & invalid).any():
        raise ValueError("a region mask covers invalid (NaN) pixels of the cloud")
    iou = float((est & true).sum() / (est | true).sum())
    areas = pixel_areas(p)
    est_area = float(np.nansum(areas[est]))
    true_area = float(np.nansum(areas[true]))
    if not est.any():
        return RegionComparison(iou, np.inf, np.inf, est_area, true_area)
    b_est = p[region_boundary(est)]
    b_true = p[region_boundary(true)]
    d_est_to_true, _ = cKDTree(b_true).query(b_est)
    d_true_to_est, _ = cKDTree(b_est).query(b_true)
    mean_d = 0.5 * (float(d_est_to_true.mean()) + float(d_true_to_est.mean()))
    max_d = max(float(d_est_to_true.max()), float(d_true_to_est.max()))
    return RegionComparison(iou, mean_d, max_d, est_area, true_area)
