r"""Chamfer distance between object surfaces (thesis Table 7.1, column ``d_C``).

For point sets ``A`` and ``B`` sampled uniformly (area-weighted) on two surfaces,

    d_C(A, B) = 1/2 ( mean_{a in A} min_{b in B} |a - b|  +  mean_{b in B} min_{a in A} |a - b| )   [m]

Each surface is expressed in its own object frame translated to its area centroid (no rotation alignment),
so ``d_C`` compares shapes and sizes, as the thesis uses it to measure how similar a test object is to the
training objects. ``nearest_training_object`` returns ``min_j d_C(test, train_j)``.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from scipy.spatial import cKDTree

__all__ = ["chamfer_distance", "nearest_training_object", "surface_samples"]


def surface_samples(
    points: np.ndarray, faces: np.ndarray, count: int = 4096, seed: int = 0, center: bool = True
) -> np.ndarray:
    """(count, 3) points sampled uniformly by area on the triangle surface ``(points (N, 3), faces (F, 3))``.

    ``center`` translates the samples so that the area centroid is at the origin.
    """
    p = np.asarray(points, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    if f.ndim != 2 or f.shape[1] != 3 or not len(f):
        raise ValueError(f"faces must be a non-empty (F, 3) array, got shape {f.shape}")
    a, b, c = p[f[:, 0]], p[f[:, 1]], p[f[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    if not area.sum() > 0:
        raise ValueError("surface has zero area")
    rng = np.random.default_rng(seed)
    tri = rng.choice(len(f), size=count, p=area / area.sum())
    u, v = rng.random(count), rng.random(count)
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    x = a[tri] + u[:, None] * (b[tri] - a[tri]) + v[:, None] * (c[tri] - a[tri])
    if center:
        centroid = ((a + b + c) / 3 * area[:, None]).sum(0) / area.sum()
        x = x - centroid
    return x


def chamfer_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Symmetric mean nearest-neighbour distance between point sets a (n, 3) and b (m, 3) [m]."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    dab = cKDTree(b).query(a)[0]
    dba = cKDTree(a).query(b)[0]
    return float(0.5 * (dab.mean() + dba.mean()))


def nearest_training_object(test: np.ndarray, train: Mapping[str, np.ndarray]) -> tuple[str, float]:
    """``(name, d_C)`` of the training object whose samples are closest to the ``test`` samples."""
    if not train:
        raise ValueError("no training objects to compare with")
    dist = {name: chamfer_distance(test, pts) for name, pts in train.items()}
    best = min(dist, key=dist.get)
    return best, dist[best]
