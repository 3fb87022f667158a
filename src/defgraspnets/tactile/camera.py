"""Time-of-flight depth camera inside the sensor, looking up at the inner membrane surface.

The thesis's sensor images the inside of its membrane with a pmd CamBoard pico flexx (§2.2), which
returns an organized point cloud of 224 x 171 pixels (§3.4: the wrench CNN input is "a 171 x 224
organized point cloud ... an array of depth measurements"). The camera here is an ideal pinhole on
the sensor axis at the sensor-frame origin with the sensor frame's orientation (camera axes =
force-torque axes, thesis §3.3), so camera frame = sensor frame. Pixel ``(v, u)`` (row, column)
sees along the ray

    d(u, v) = ((u - c_x) / f_x, (v - c_y) / f_y, 1),          x = o + s d,  s >= 0,

and reports the first hit on the inner membrane surface (a Warp BVH ray cast,
``wp.mesh_query_ray``, one thread per pixel): the point ``x`` in the camera frame and the depth
``z = x_z`` (the z image of the pmd Royale SDK, not the radial range). Rays that miss the membrane
leave the cavity through the rim and end on the housing, whose interior is painted matte black to
absorb them (thesis §2.2): NaN, as the real camera reports no valid depth there.

Intrinsics (:data:`PICO_FLEXX`): 224 x 171 pixels; focal length f = 215.89 px from the pico flexx
used as NASA Astrobee's hazard camera (``astrobee/config/robots/bumble.config``, ``haz_cam``
``intrinsic_matrix``, github.com/nasa/astrobee); principal point at the image centre (that
calibration has (114.1, 86.5), an individual-unit offset of ~2 px) and no lens distortion (the
simulated image is the rectified one). The resulting field of view is 54.8 deg x 43.2 deg; the pmd
datasheet quotes 62 deg x 45 deg, which includes the lens's barrel distortion.

Noise (:class:`ToFNoise`): ToF depth noise grows with distance; the pico flexx datasheet quotes a
depth resolution of <= 1 % of the distance (0.5-4 m, 5 fps) and <= 2 % (0.1-1 m, 45 fps). The model
adds zero-mean Gaussian noise along each ray, ``r' = r + (sigma_0 + sigma_rel r) eps``, default
``sigma_rel = 1 %``, ``sigma_0 = 0``. Multipath, flying pixels and motion artefacts are not modelled.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

__all__ = ["PICO_FLEXX", "CameraError", "CameraIntrinsics", "DepthCamera", "DepthFrame", "ToFNoise"]


class CameraError(ValueError):
    """Invalid camera parameters or render inputs."""


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics in pixels; image size ``(height, width)``.

    Args:
        width, height: image size [px].
        fx, fy: focal lengths [px].
        cx, cy: principal point [px] (pixel centres at integer coordinates).
        min_range, max_range: the camera's working range in depth z [m]; returns outside are NaN.
    """

    width: int = 224
    height: int = 171
    fx: float = 215.88697
    fy: float = 215.88697
    cx: float = 111.5
    cy: float = 85.0
    min_range: float = 0.0
    max_range: float = 4.0

    def __post_init__(self):
        if (
            int(self.width) != self.width
            or int(self.height) != self.height
            or min(self.width, self.height) < 1
        ):
            raise CameraError(f"image size must be positive integers, got {self.width} x {self.height}")
        for name in ("fx", "fy", "cx", "cy", "min_range", "max_range"):
            if not np.isfinite(getattr(self, name)):
                raise CameraError(f"{name} must be finite, got {getattr(self, name)!r}")
        if self.fx <= 0 or self.fy <= 0:
            raise CameraError(f"focal lengths must be > 0 px, got fx={self.fx}, fy={self.fy}")
        if not 0.0 <= self.min_range < self.max_range:
            raise CameraError(f"need 0 <= min_range < max_range, got {self.min_range}, {self.max_range}")

    @property
    def shape(self) -> tuple[int, int]:
        """(height, width) of the images [px]."""
        return (int(self.height), int(self.width))

    @property
    def field_of_view(self) -> tuple[float, float]:
        """(horizontal, vertical) full field of view [rad] of the undistorted pinhole."""
        return (2 * np.arctan(self.width / 2 / self.fx), 2 * np.arctan(self.height / 2 / self.fy))

    def ray_directions(self) -> np.ndarray:
        """(H, W, 3) ray directions ``((u - cx)/fx, (v - cy)/fy, 1)`` (unit z component)."""
        v, u = np.meshgrid(np.arange(self.height), np.arange(self.width), indexing="ij")
        return np.stack([(u - self.cx) / self.fx, (v - self.cy) / self.fy, np.ones_like(u, float)], axis=-1)

    def scaled(self, factor: float) -> CameraIntrinsics:
        """The same optics at ``factor`` times the resolution (for fast tests and previews)."""
        w, h = max(1, round(self.width * factor)), max(1, round(self.height * factor))
        sx, sy = w / self.width, h / self.height
        return CameraIntrinsics(
            w,
            h,
            self.fx * sx,
            self.fy * sy,
            (self.cx + 0.5) * sx - 0.5,
            (self.cy + 0.5) * sy - 0.5,
            self.min_range,
            self.max_range,
        )


#: The pmd CamBoard pico flexx as modelled here (see the module docstring for the sources).
PICO_FLEXX = CameraIntrinsics()


@dataclass(frozen=True)
class ToFNoise:
    """Depth-dependent Gaussian ToF noise along each ray: ``sigma(r) = sigma_0 + sigma_rel * r``.

    Args:
        relative_sigma: sigma_rel, fraction of the range (datasheet: <= 1 %).
        absolute_sigma: sigma_0 [m].
        seed: seed of the default generator (reproducible noise); a generator passed to
            :meth:`DepthCamera.render` overrides it.
    """

    relative_sigma: float = 0.01
    absolute_sigma: float = 0.0
    seed: int | None = 0

    def __post_init__(self):
        for name in ("relative_sigma", "absolute_sigma"):
            value = getattr(self, name)
            if not np.isfinite(value) or value < 0:
                raise CameraError(f"ToFNoise.{name} must be finite and >= 0, got {value!r}")

    def sigma(self, range_m: np.ndarray) -> np.ndarray:
        """Noise standard deviation [m] at range ``range_m`` [m]."""
        return self.absolute_sigma + self.relative_sigma * np.asarray(range_m)


@dataclass(frozen=True)
class DepthFrame:
    """One camera reading (all in the camera frame, metres, NaN where no return).

    Attributes:
        depth: (H, W) float32 depth z [m].
        points: (H, W, 3) float32 organized point cloud [m].
        face: (H, W) int32 index of the hit triangle, -1 where none.
    """

    depth: np.ndarray
    points: np.ndarray
    face: np.ndarray

    @property
    def valid(self) -> np.ndarray:
        """(H, W) bool: pixels with a return."""
        return np.isfinite(self.depth)


@wp.kernel
def cast_pixel_rays(
    mesh: wp.uint64,
    origin: wp.vec3,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    min_range: float,
    max_range: float,
    depth: wp.array2d(dtype=float),
    points: wp.array2d(dtype=wp.vec3),
    face: wp.array2d(dtype=wp.int32),
):
    """First hit of each pixel's ray with the surface: depth z, point, face (NaN / -1 on a miss)."""
    v, u = wp.tid()
    direction = wp.normalize(wp.vec3((float(u) - cx) / fx, (float(v) - cy) / fy, 1.0))
    nan = wp.nan
    depth[v, u] = nan
    points[v, u] = wp.vec3(nan, nan, nan)
    face[v, u] = -1
    hit = wp.mesh_query_ray(mesh, origin, direction, 1.0e3)
    if hit.result:
        p = direction * hit.t
        if p[2] >= min_range and p[2] <= max_range:
            depth[v, u] = p[2]
            points[v, u] = p
            face[v, u] = hit.face


class DepthCamera:
    """Ray-casting ToF camera at ``position`` (sensor frame), axes aligned with the sensor frame.

    The Warp mesh of the target surface is built once per topology and refit (``mesh.refit()``)
    when only the vertex positions change, as between the steps of a deformation.

    Args:
        intrinsics: pinhole model (default :data:`PICO_FLEXX`).
        position: (3,) optical centre in the sensor frame [m] (default: the origin).
        noise: optional :class:`ToFNoise`; None renders exact depths.
        device: Warp device, ``"cpu"`` or ``"cuda"`` / ``"cuda:0"`` (same code); None = Warp's default.
    """

    def __init__(
        self,
        intrinsics: CameraIntrinsics = PICO_FLEXX,
        position=(0.0, 0.0, 0.0),
        noise: ToFNoise | None = None,
        device: str | None = None,
    ):
        self.intrinsics = intrinsics
        self.position = np.asarray(position, dtype=np.float64)
        if self.position.shape != (3,) or not np.all(np.isfinite(self.position)):
            raise CameraError(f"camera position must be a finite (3,) vector, got {position!r}")
        self.noise = noise
        self.device = wp.get_device(device)
        self._rng = np.random.default_rng(None if noise is None else noise.seed)
        self._mesh: wp.Mesh | None = None
        self._faces: np.ndarray | None = None
        h, w = intrinsics.shape
        self._depth = wp.empty((h, w), dtype=float, device=self.device)
        self._points = wp.empty((h, w), dtype=wp.vec3, device=self.device)
        self._face = wp.empty((h, w), dtype=wp.int32, device=self.device)

    # ------------------------------------------------------------------ surface
    def set_surface(self, vertices, faces) -> None:
        """Set the target triangle surface (sensor frame [m]); refits if the topology is unchanged."""
        v = np.asarray(vertices, dtype=np.float64)
        f = np.asarray(faces)
        if v.ndim != 2 or v.shape[1] != 3 or len(v) < 3:
            raise CameraError(f"vertices must have shape (N >= 3, 3), got {v.shape}")
        if not np.all(np.isfinite(v)):
            raise CameraError("vertices contain NaN or inf")
        if f.ndim != 2 or f.shape[1] != 3 or len(f) < 1 or not np.issubdtype(f.dtype, np.integer):
            raise CameraError(f"faces must be an integer array of shape (F >= 1, 3), got {f.dtype} {f.shape}")
        if f.min() < 0 or f.max() >= len(v):
            raise CameraError(f"face indices must lie in [0, {len(v)}), got [{f.min()}, {f.max()}]")
        points = wp.array((v - self.position).astype(np.float32), dtype=wp.vec3, device=self.device)
        same = (
            self._mesh is not None
            and self._faces is not None
            and self._faces.shape == f.shape
            and self._mesh.points.shape[0] == len(v)
            and np.array_equal(self._faces, f)
        )
        if same:
            wp.copy(self._mesh.points, points)
            self._mesh.refit()
        else:
            indices = wp.array(f.astype(np.int32).ravel(), dtype=wp.int32, device=self.device)
            self._mesh = wp.Mesh(points=points, indices=indices)
            self._faces = f.copy()

    # ------------------------------------------------------------------ render
    def render(
        self, vertices=None, faces=None, rng: np.random.Generator | None = None, noisy: bool = True
    ) -> DepthFrame:
        """Render one frame of the surface ``(vertices, faces)`` (or the last one set).

        Args:
            vertices: (N, 3) surface vertex positions in the sensor frame [m].
            faces: (F, 3) triangles; may be omitted when only the vertices changed.
            rng: generator for the noise (default: the camera's own, seeded by ``noise.seed``).
            noisy: apply the camera's noise model (if it has one).
        """
        if vertices is not None:
            if faces is None and self._faces is None:
                raise CameraError("the first render needs faces as well as vertices")
            self.set_surface(vertices, self._faces if faces is None else faces)
        elif faces is not None:
            raise CameraError("faces given without vertices")
        if self._mesh is None:
            raise CameraError("no surface to image: pass vertices and faces (e.g. sensor.inner_surface())")
        k = self.intrinsics
        wp.launch(
            cast_pixel_rays,
            dim=k.shape,
            inputs=[
                self._mesh.id,
                wp.vec3(0.0, 0.0, 0.0),
                k.fx,
                k.fy,
                k.cx,
                k.cy,
                k.min_range,
                k.max_range,
            ],
            outputs=[self._depth, self._points, self._face],
            device=self.device,
        )
        depth, points, face = (
            self._depth.numpy().copy(),
            self._points.numpy().copy(),
            self._face.numpy().copy(),
        )
        if noisy and self.noise is not None:
            depth, points = self._add_noise(depth, points, self._rng if rng is None else rng)
        return DepthFrame(depth=depth, points=points, face=face)

    def _add_noise(self, depth, points, rng):
        valid = np.isfinite(depth)
        r = np.linalg.norm(points[valid], axis=1)
        r_noisy = r + self.noise.sigma(r) * rng.standard_normal(r.shape)
        scale = (r_noisy / r).astype(np.float32)
        depth, points = depth.copy(), points.copy()
        depth[valid] *= scale
        points[valid] *= scale[:, None]
        return depth, points

    def reference(self, sensor, points=None) -> DepthFrame:
        """Noise-free reading of ``sensor``'s inner surface at vertex positions ``points``.

        With ``points=None`` this is the undeformed (neutral, free air) membrane; for a pressurized
        PV state pass the FEM-inflated vertex positions. Its depth image is the reference against
        which contact deformations are normalized (:mod:`defgraspnets.data.tactile_datamodule`).
        """
        vertices, faces = sensor.inner_surface(points)
        return self.render(vertices, faces, noisy=False)
