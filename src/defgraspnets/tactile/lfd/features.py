"""Tactile input features and action outputs for learning from demonstration (thesis §5.3).

From the deformed part of the membrane cloud (points displaced from the undeformed reading,
see :func:`defgraspnets.tactile.contact_regions.deformed_points`) the features are

- the centroid ``c`` (3) [m],
- the principal variances ``lambda_1 >= lambda_2 >= lambda_3`` (3) [m^2] — eigenvalues of the
  population covariance of the points,
- the principal vectors ``e_1, e_2, e_3`` (3 each) — the matching unit eigenvectors,

all expressed in the **world** frame. With ``weights`` (one non-negative weight per point, e.g. its
indentation beyond the contact-core cut, :class:`~defgraspnets.tactile.contour_sim.TactileSimulation`
``point_weighting="depth"``) the centroid and covariance are the weighted mean and the weighted population
covariance ``sum w (x - c)(x - c)^T / sum w``; without (None) every point counts once.

Sign convention: each principal vector is flipped so that its element of largest magnitude is positive
(the first such element on ties).

No contact (fewer than ``min_points`` deformed points): the centroid is the camera-frame origin
and the principal vectors are the camera-frame axes x, y, z, both transformed to the world (so
they carry the end-effector pose, as the thesis intends), and the variances are zero. The
default axes are *not* sign-flipped: flipping would discard part of that pose information.

Actions are the 6D end-effector velocity in the world frame, ``[v, omega]`` [m/s, rad/s],
from time-adjacent poses: ``v = (p_{t+1} - p_t)/dt``, ``omega = log(R_{t+1} R_t^T)/dt``.

Before learning, every input and output dimension is normalized linearly to [0, 1] with the
ranges of the demonstration data (:class:`MinMaxNormalizer`, whose ranges are stored so that
execution uses the same map).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from defgraspnets.fem.bodies import check_rigid_transform

__all__ = [
    "FEATURE_SIZES",
    "MinMaxNormalizer",
    "TactileFeatures",
    "demonstration_observations",
    "end_effector_velocity",
    "feature_matrix",
    "orient_principal_vectors",
    "tactile_features",
]

#: Size of each named feature block, in the order used by :meth:`TactileFeatures.vector`.
FEATURE_SIZES = {"centroid": 3, "principal_variances": 3, "e1": 3, "e2": 3, "e3": 3}


def orient_principal_vectors(vectors: np.ndarray) -> np.ndarray:
    """Flip each row vector so that its element of largest magnitude is positive (§5.3)."""
    v = np.asarray(vectors, dtype=np.float64)
    idx = np.abs(v).argmax(axis=-1)
    sign = np.sign(np.take_along_axis(v, idx[..., None], axis=-1))
    sign[sign == 0] = 1.0
    return v * sign


@dataclass(frozen=True)
class TactileFeatures:
    """§5.3 features of one tactile reading, world frame.

    Attributes:
        centroid: (3,) [m].
        principal_variances: (3,) descending [m^2].
        principal_vectors: (3, 3), row k is ``e_{k+1}``.
        in_contact: False when the defaults were used.
        n_points: number of deformed points.
    """

    centroid: np.ndarray
    principal_variances: np.ndarray
    principal_vectors: np.ndarray
    in_contact: bool
    n_points: int

    @property
    def e1(self) -> np.ndarray:
        return self.principal_vectors[0]

    @property
    def e2(self) -> np.ndarray:
        return self.principal_vectors[1]

    @property
    def e3(self) -> np.ndarray:
        return self.principal_vectors[2]

    def vector(self, names: Sequence[str] = ("centroid", "principal_variances", "e1")) -> np.ndarray:
        """Concatenate named blocks (keys of :data:`FEATURE_SIZES`).

        The thesis uses ``("principal_variances", "e1")`` for edge following and
        ``("centroid", "principal_variances", "e1")`` for mixed manipulation.
        """
        if len(names) == 0:
            raise ValueError("names must not be empty")
        blocks = []
        for name in names:
            if name not in FEATURE_SIZES:
                raise ValueError(f"unknown feature {name!r}; choose from {sorted(FEATURE_SIZES)}")
            blocks.append(np.asarray(getattr(self, name)))
        return np.concatenate(blocks)


def tactile_features(deformed_points, sensor_pose, min_points: int = 3, weights=None) -> TactileFeatures:
    """Features of one reading from its deformed points (N, 3) in the sensor (camera) frame [m].

    Args:
        deformed_points: (N, 3) points, N may be 0.
        sensor_pose: (4, 4) world <- sensor transform.
        min_points: fewer points than this counts as no contact (defaults are returned).
        weights: (N,) non-negative point weights, or None (each point counts once). Weights summing to 0
            count as no contact.
    """
    pose = check_rigid_transform(sensor_pose, "sensor_pose", single=True)
    rot, pos = pose[:3, :3], pose[:3, 3]
    p = np.asarray(deformed_points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"deformed_points must have shape (N, 3), got {p.shape}")
    if not np.isfinite(p).all():
        raise ValueError("deformed_points contain non-finite coordinates")
    if min_points < 1:
        raise ValueError(f"min_points must be >= 1, got {min_points}")
    n = p.shape[0]
    if weights is not None:
        w = np.asarray(weights, dtype=np.float64)
        if w.shape != (n,):
            raise ValueError(f"weights must have shape ({n},), got {w.shape}")
        if not (np.isfinite(w).all() and (w >= 0).all()):
            raise ValueError("weights must be finite and >= 0")
    if n < min_points or (weights is not None and not w.sum() > 0):
        return TactileFeatures(pos.copy(), np.zeros(3), rot.T.copy(), False, n)
    world = p @ rot.T + pos
    if weights is None:
        centroid = world.mean(axis=0)
        diff = world - centroid
        cov = diff.T @ diff / n
    else:
        w = w / w.sum()
        centroid = w @ world
        diff = world - centroid
        cov = (diff * w[:, None]).T @ diff
    values, vectors = np.linalg.eigh(cov)
    order = np.argsort(values)[::-1]
    variances = np.clip(values[order], 0.0, None)
    return TactileFeatures(centroid, variances, orient_principal_vectors(vectors[:, order].T), True, n)


def feature_matrix(
    features: Sequence[TactileFeatures], names: Sequence[str] = ("centroid", "principal_variances", "e1")
) -> np.ndarray:
    """Stack :meth:`TactileFeatures.vector` of a demonstration into (T, D)."""
    if len(features) == 0:
        raise ValueError("features must not be empty")
    return np.stack([f.vector(names) for f in features])


def end_effector_velocity(poses, dt: float) -> np.ndarray:
    """World-frame twists ``[v, omega]`` (T-1, 6) from T poses (T, 4, 4) sampled every ``dt`` [s]."""
    t = np.asarray(poses, dtype=np.float64)
    if t.ndim != 3 or t.shape[1:] != (4, 4) or t.shape[0] < 2:
        raise ValueError(f"poses must have shape (T, 4, 4) with T >= 2, got {t.shape}")
    if not dt > 0:
        raise ValueError(f"dt must be > 0 s, got {dt}")
    for k in range(t.shape[0]):
        check_rigid_transform(t[k], f"poses[{k}]", single=True)
    v = np.diff(t[:, :3, 3], axis=0) / dt
    rel = t[1:, :3, :3] @ np.swapaxes(t[:-1, :3, :3], 1, 2)
    omega = Rotation.from_matrix(rel).as_rotvec() / dt
    return np.concatenate([v, omega], axis=1)


def demonstration_observations(inputs, poses, dt: float) -> np.ndarray:
    """Observations ``o_t = [S_t, A_t]`` (T-1, D + 6) of one demonstration (§5.2).

    ``A_t`` is the velocity from pose t to t + 1, so the last input (which has no following
    pose) is dropped.
    """
    s = np.asarray(inputs, dtype=np.float64)
    if s.ndim != 2:
        raise ValueError(f"inputs must have shape (T, D), got {s.shape}")
    a = end_effector_velocity(poses, dt)
    if s.shape[0] != a.shape[0] + 1:
        raise ValueError(f"{s.shape[0]} inputs but {a.shape[0] + 1} poses")
    return np.concatenate([s[:-1], a], axis=1)


@dataclass(frozen=True)
class MinMaxNormalizer:
    """Per-dimension linear map of the demonstration data ranges onto [0, 1].

    ``x_n = (x - minimum) / (maximum - minimum)``; a dimension that is constant in the data maps
    to 0 (its range is treated as 1). Values outside the fitted range map outside [0, 1].

    Attributes:
        minimum, maximum: (D,) ranges of the fitted data.
    """

    minimum: np.ndarray
    maximum: np.ndarray

    @classmethod
    def fit(cls, data) -> MinMaxNormalizer:
        x = np.asarray(data, dtype=np.float64)
        if x.ndim != 2 or x.shape[0] == 0:
            raise ValueError(f"data must have shape (n, D) with n >= 1, got {x.shape}")
        if not np.isfinite(x).all():
            raise ValueError("data contain non-finite values")
        return cls(x.min(axis=0), x.max(axis=0))

    @property
    def scale(self) -> np.ndarray:
        span = self.maximum - self.minimum
        return np.where(span > 0, span, 1.0)

    def _check(self, x) -> np.ndarray:
        a = np.asarray(x, dtype=np.float64)
        if a.shape[-1] != self.minimum.size:
            raise ValueError(f"expected {self.minimum.size} dimensions, got {a.shape[-1]}")
        return a

    def transform(self, x) -> np.ndarray:
        return (self._check(x) - self.minimum) / self.scale

    def inverse_transform(self, x) -> np.ndarray:
        return self._check(x) * self.scale + self.minimum

    def to_dict(self) -> dict[str, list[float]]:
        return {"minimum": self.minimum.tolist(), "maximum": self.maximum.tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> MinMaxNormalizer:
        lo = np.asarray(d["minimum"], dtype=np.float64)
        hi = np.asarray(d["maximum"], dtype=np.float64)
        if lo.shape != hi.shape or lo.ndim != 1 or (hi < lo).any():
            raise ValueError("minimum and maximum must be equal-length vectors with maximum >= minimum")
        return cls(lo, hi)
