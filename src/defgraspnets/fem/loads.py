"""Body loads: gravity and d'Alembert inertial loads of an accelerating frame.

The object is simulated in the frame that holds it (e.g. the gripper frame). If that frame moves with
linear acceleration a and angular acceleration alpha about the point c, and gravity is g, every
material point X feels the body force density

    b(X) = rho (g - a - alpha x (X - c) - omega x (omega x (X - c)))

(d'Alembert). Loads are lumped to the vertices, f_i = m_i b(X_i) / rho with m_i the lumped mass, and
are dead loads: they are evaluated at the rest positions X (small-rotation assumption), so the
potential is -sum_i f_i . u_i. The angular velocity term is included for completeness (zero in
quasi-static ramps started from rest).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["BodyLoad", "STANDARD_GRAVITY"]

STANDARD_GRAVITY = 9.80665  # m/s^2


def _as_batch_vec3(value, batch_size: int, name: str) -> np.ndarray:
    v = np.asarray(value, dtype=np.float64)
    if v.shape == (3,):
        v = np.broadcast_to(v, (batch_size, 3))
    if v.shape != (batch_size, 3):
        raise ValueError(f"BodyLoad.{name} must have shape (3,) or ({batch_size}, 3), got {v.shape}")
    if not np.all(np.isfinite(v)):
        raise ValueError(f"BodyLoad.{name} must be finite, got {value!r}")
    return np.array(v)


@dataclass(frozen=True)
class BodyLoad:
    """Gravity and frame accelerations (object frame, SI units); each may be (3,) or per problem (B, 3).

    Args:
        gravity: g [m/s^2], e.g. (0, 0, -9.80665).
        linear_acceleration: a of the holding frame [m/s^2].
        angular_acceleration: alpha of the holding frame [rad/s^2].
        angular_velocity: omega of the holding frame [rad/s].
        rotation_center: c, the point the frame rotates about [m].
    """

    gravity: object = (0.0, 0.0, 0.0)
    linear_acceleration: object = (0.0, 0.0, 0.0)
    angular_acceleration: object = (0.0, 0.0, 0.0)
    angular_velocity: object = (0.0, 0.0, 0.0)
    rotation_center: object = (0.0, 0.0, 0.0)

    @classmethod
    def none(cls) -> BodyLoad:
        return cls()

    def arrays(self, batch_size: int) -> dict[str, np.ndarray]:
        """Each field as a (B, 3) float64 array."""
        names = (
            "gravity",
            "linear_acceleration",
            "angular_acceleration",
            "angular_velocity",
            "rotation_center",
        )
        return {n: _as_batch_vec3(getattr(self, n), batch_size, n) for n in names}

    def nodal_forces(self, rest_points: np.ndarray, masses: np.ndarray, batch_size: int) -> np.ndarray:
        """(B, N, 3) lumped forces f_i = m_i (g - a - alpha x r - omega x (omega x r)), r = X_i - c [N].

        ``masses``: (N,) lumped vertex masses, or (B, N) when the problems differ in density."""
        masses = np.broadcast_to(np.asarray(masses, dtype=np.float64), (batch_size, len(rest_points)))
        p = self.arrays(batch_size)
        r = rest_points[None, :, :] - p["rotation_center"][:, None, :]
        w = p["angular_velocity"][:, None, :]
        acc = (
            p["gravity"][:, None, :]
            - p["linear_acceleration"][:, None, :]
            - np.cross(p["angular_acceleration"][:, None, :], r)
            - np.cross(w, np.cross(w, r))
        )
        return masses[:, :, None] * acc

    def interpolate(self, other: BodyLoad, fraction: float, batch_size: int) -> BodyLoad:
        """The load a fraction of the way from ``self`` to ``other`` (linear in every field)."""
        a, b = self.arrays(batch_size), other.arrays(batch_size)
        return BodyLoad(**{k: a[k] + fraction * (b[k] - a[k]) for k in a})
