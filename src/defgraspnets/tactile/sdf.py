"""Signed distance functions of rigid scene objects for the fast membrane model and the tactile scenes.

Every shape maps world points ``x`` (N, 3) [m] to the signed distance ``phi(x)`` [m] (negative inside
the solid) and its gradient ``grad phi(x)`` (unit outward normal of the nearest surface point):

- :class:`SphereSDF`: ``phi = |x - c| - r``;
- :class:`TubeSDF`: a tube of radius ``r`` around a polyline centre curve (straight pipe: two points;
  a curved 3-D pipe: a densely sampled spline), ``phi = min_k dist(x, segment_k) - r``; the ends are
  rounded (a capsule chain);
- :class:`BoxSDF`: an oriented box (half extents ``h``), exact ``phi = |max(q, 0)| + min(max_i q_i, 0)``
  with ``q = |R^T (x - c)| - h``;
- :class:`ComplementSDF`: ``-phi`` of another shape (the solid outside a free region, e.g. the inside
  of a bookcase: shelf board, back and side panels around an open box);
- :class:`BumpyCylinderSDF`: a limb-like cylinder of axis ``a`` through ``c`` whose radius carries a
  Gaussian bump, ``r(s) = r_0 + b exp(-(s - s_b)^2 / (2 w^2))``; ``phi ~ (rho - r(s)) / sqrt(1 + r'(s)^2)``
  (first-order distance to a surface of revolution, exact where ``r' = 0``);
- :class:`UnionSDF`: ``min`` of several shapes.

Gradients are analytic where cheap and otherwise central differences (step ``1e-6 m``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = [
    "BoxSDF",
    "BumpyCylinderSDF",
    "ComplementSDF",
    "SignedDistance",
    "SphereSDF",
    "TubeSDF",
    "UnionSDF",
]

_FD_STEP = 1.0e-6


def _points(x) -> np.ndarray:
    p = np.asarray(x, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {p.shape}")
    if not np.isfinite(p).all():
        raise ValueError("points contain non-finite coordinates")
    return p


def _vector(v, name: str) -> np.ndarray:
    a = np.asarray(v, dtype=np.float64)
    if a.shape != (3,) or not np.isfinite(a).all():
        raise ValueError(f"{name} must be a finite 3-vector, got {v!r}")
    return a


def _positive(value: float, name: str) -> float:
    if not (np.isscalar(value) and np.isfinite(value) and value > 0):
        raise ValueError(f"{name} must be a finite length > 0 m, got {value!r}")
    return float(value)


def _normalize(g: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(g, axis=1, keepdims=True)
    return g / np.where(n > 0, n, 1.0)


class SignedDistance:
    """Base class: ``distance(x)`` (N,) and ``evaluate(x) -> (phi, grad)``; grad by central differences."""

    def distance(self, points) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    def evaluate(self, points) -> tuple[np.ndarray, np.ndarray]:
        """``(phi (N,), unit gradient (N, 3))`` at world points (N, 3) [m]."""
        p = _points(points)
        phi = self.distance(p)
        grad = np.empty_like(p)
        for k in range(3):
            e = np.zeros(3)
            e[k] = _FD_STEP
            grad[:, k] = (self.distance(p + e) - self.distance(p - e)) / (2 * _FD_STEP)
        return phi, _normalize(grad)

    def __call__(self, points) -> np.ndarray:
        return self.distance(_points(points))


@dataclass(frozen=True)
class SphereSDF(SignedDistance):
    """Rigid sphere of ``radius`` [m] centred at ``center`` [m]."""

    center: tuple[float, float, float]
    radius: float

    def __post_init__(self):
        object.__setattr__(self, "center", tuple(_vector(self.center, "center")))
        _positive(self.radius, "radius")

    def distance(self, points) -> np.ndarray:
        return np.linalg.norm(_points(points) - np.asarray(self.center), axis=1) - self.radius

    def evaluate(self, points):
        d = _points(points) - np.asarray(self.center)
        r = np.linalg.norm(d, axis=1)
        return r - self.radius, _normalize(d)


@dataclass(frozen=True)
class TubeSDF(SignedDistance):
    """Tube of ``radius`` [m] around the polyline ``centerline`` (K >= 2 points, (K, 3) [m])."""

    centerline: np.ndarray
    radius: float
    _a: np.ndarray = field(init=False, repr=False)
    _d: np.ndarray = field(init=False, repr=False)
    _len2: np.ndarray = field(init=False, repr=False)

    def __post_init__(self):
        c = np.asarray(self.centerline, dtype=np.float64)
        if c.ndim != 2 or c.shape[1] != 3 or c.shape[0] < 2 or not np.isfinite(c).all():
            raise ValueError(f"centerline must be a finite (K >= 2, 3) polyline, got shape {c.shape}")
        d = np.diff(c, axis=0)
        len2 = (d**2).sum(axis=1)
        if (len2 <= 0).any():
            raise ValueError("centerline has repeated consecutive points")
        _positive(self.radius, "radius")
        object.__setattr__(self, "centerline", c)
        object.__setattr__(self, "_a", c[:-1])
        object.__setattr__(self, "_d", d)
        object.__setattr__(self, "_len2", len2)

    def closest_centerline_points(self, points) -> np.ndarray:
        """(N, 3) nearest points of the centre polyline."""
        p = _points(points)
        best = np.full(p.shape[0], np.inf)
        closest = np.zeros_like(p)
        chunk = 64  # segments per pass: bounded memory for long splines
        for s in range(0, self._a.shape[0], chunk):
            a, d, l2 = self._a[s : s + chunk], self._d[s : s + chunk], self._len2[s : s + chunk]
            t = np.clip(np.einsum("nkj,kj->nk", p[:, None, :] - a[None], d) / l2, 0.0, 1.0)
            q = a[None] + t[..., None] * d[None]
            dist2 = ((p[:, None, :] - q) ** 2).sum(axis=2)
            k = dist2.argmin(axis=1)
            better = dist2[np.arange(p.shape[0]), k] < best
            best[better] = dist2[np.arange(p.shape[0]), k][better]
            closest[better] = q[np.arange(p.shape[0]), k][better]
        return closest

    def distance(self, points) -> np.ndarray:
        p = _points(points)
        return np.linalg.norm(p - self.closest_centerline_points(p), axis=1) - self.radius

    def evaluate(self, points):
        p = _points(points)
        d = p - self.closest_centerline_points(p)
        return np.linalg.norm(d, axis=1) - self.radius, _normalize(d)


@dataclass(frozen=True)
class BoxSDF(SignedDistance):
    """Oriented box: centre [m], half extents [m] along the columns of ``rotation`` (world <- box)."""

    center: tuple[float, float, float]
    half_extents: tuple[float, float, float]
    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))

    def __post_init__(self):
        object.__setattr__(self, "center", tuple(_vector(self.center, "center")))
        h = _vector(self.half_extents, "half_extents")
        if (h <= 0).any():
            raise ValueError(f"half_extents must be > 0 m, got {self.half_extents!r}")
        r = np.asarray(self.rotation, dtype=np.float64)
        if r.shape != (3, 3) or not np.allclose(r.T @ r, np.eye(3), atol=1e-9) or np.linalg.det(r) < 0:
            raise ValueError("rotation must be a proper 3x3 rotation matrix")
        object.__setattr__(self, "half_extents", tuple(h))
        object.__setattr__(self, "rotation", r)

    def distance(self, points) -> np.ndarray:
        local = (_points(points) - np.asarray(self.center)) @ self.rotation
        q = np.abs(local) - np.asarray(self.half_extents)
        outside = np.linalg.norm(np.maximum(q, 0.0), axis=1)
        return outside + np.minimum(q.max(axis=1), 0.0)


@dataclass(frozen=True)
class ComplementSDF(SignedDistance):
    """The solid everywhere outside ``free`` (a free-space region): ``phi = -phi_free``."""

    free: SignedDistance

    def distance(self, points) -> np.ndarray:
        return -self.free.distance(points)

    def evaluate(self, points):
        phi, g = self.free.evaluate(points)
        return -phi, -g


@dataclass(frozen=True)
class BumpyCylinderSDF(SignedDistance):
    """Limb-like cylinder (axis ``axis`` through ``origin``) of radius ``r_0`` with a Gaussian bump.

    ``r(s) = radius + bump_height exp(-(s - bump_position)^2 / (2 bump_width^2))``, s the axial
    coordinate [m]; the limb is infinite along its axis.
    """

    origin: tuple[float, float, float]
    axis: tuple[float, float, float]
    radius: float
    bump_height: float
    bump_position: float
    bump_width: float

    def __post_init__(self):
        object.__setattr__(self, "origin", tuple(_vector(self.origin, "origin")))
        a = _vector(self.axis, "axis")
        if np.linalg.norm(a) == 0:
            raise ValueError("axis must be non-zero")
        object.__setattr__(self, "axis", tuple(a / np.linalg.norm(a)))
        _positive(self.radius, "radius")
        _positive(self.bump_width, "bump_width")
        if not np.isfinite(self.bump_height) or self.bump_height <= -self.radius:
            raise ValueError(f"bump_height must be finite and > -radius, got {self.bump_height!r}")
        if not np.isfinite(self.bump_position):
            raise ValueError("bump_position must be finite")

    def profile(self, s) -> tuple[np.ndarray, np.ndarray]:
        """Radius ``r(s)`` [m] and slope ``r'(s)`` along the axis."""
        s = np.asarray(s, dtype=np.float64)
        z = (s - self.bump_position) / self.bump_width
        bump = self.bump_height * np.exp(-0.5 * z**2)
        return self.radius + bump, -bump * z / self.bump_width

    def distance(self, points) -> np.ndarray:
        d = _points(points) - np.asarray(self.origin)
        a = np.asarray(self.axis)
        s = d @ a
        rho = np.linalg.norm(d - s[:, None] * a, axis=1)
        r, slope = self.profile(s)
        return (rho - r) / np.sqrt(1.0 + slope**2)


@dataclass(frozen=True)
class UnionSDF(SignedDistance):
    """Union of shapes: ``phi = min_k phi_k`` (gradient of the minimizing shape)."""

    shapes: tuple

    def __post_init__(self):
        if len(self.shapes) == 0 or not all(isinstance(s, SignedDistance) for s in self.shapes):
            raise ValueError("UnionSDF needs one or more SignedDistance shapes")
        object.__setattr__(self, "shapes", tuple(self.shapes))

    def distance(self, points) -> np.ndarray:
        p = _points(points)
        return np.min([s.distance(p) for s in self.shapes], axis=0)

    def evaluate(self, points):
        p = _points(points)
        results = [s.evaluate(p) for s in self.shapes]
        phis = np.stack([r[0] for r in results])
        k = phis.argmin(axis=0)
        idx = np.arange(p.shape[0])
        grads = np.stack([r[1] for r in results])
        return phis[k, idx], grads[k, idx]
