"""The 7 grasp performance metrics of DefGraspSim (thesis §6.5), as pure functions on arrays (SI units).

1. **Pickup success** (bool): the object is held by friction under its own weight
   (:func:`defgraspnets.grasp.experiments.run_pickup` decides it; :func:`performance_metrics` reports it).
2. **Stress** [Pa]: the largest element von Mises stress after pickup,
   ``sigma_vm = sqrt(3/2 s:s)``, ``s = sigma - tr(sigma) I / 3`` (:func:`von_mises_stress`).
3. **Deformation** [m]: the largest node displacement from rest to the picked-up state with the best rigid
   transform removed, ``max_i |x_i - (R X_i + t)|``, ``(R, t) = argmin sum_i m_i |x_i - R X_i - t|^2``
   (mass-weighted Kabsch, :func:`best_rigid_transform`).
4. **Strain energy** [J]: ``U = sum_e V_e Psi(F_e)``, the elastic energy of the FEM engine's co-rotated
   model after pickup (``Equilibrium.strain_energy``); for small strains it is the thesis' integral of
   ``sigma : epsilon / 2`` over the volume.
5. **Linear instability** [m/s^2]: the mean over the test directions of the linear acceleration at which
   the grasp is lost (:func:`instability`).
6. **Angular instability** [rad/s^2]: the same for angular accelerations about the test axes.
7. **Deformation controllability** [m]: the largest rigid-removed deformation over all reorientation
   states (:func:`deformation_controllability`).
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "best_rigid_transform",
    "deformation_controllability",
    "instability",
    "max_deformation",
    "max_von_mises_stress",
    "performance_metrics",
    "rigid_removed_deformation",
    "rigid_removed_displacement",
    "undo_rigid_motion",
    "von_mises_stress",
]


def _points(value, name: str) -> np.ndarray:
    p = np.asarray(value, dtype=np.float64)
    if p.ndim < 2 or p.shape[-1] != 3:
        raise ValueError(f"{name} must have shape (..., N, 3), got {p.shape}")
    if not np.all(np.isfinite(p)):
        raise ValueError(f"{name} must be finite")
    return p


def von_mises_stress(stress) -> np.ndarray:
    """Von Mises stress of (..., 3, 3) stress tensors [Pa]: ``sqrt(3/2 s:s)``, ``s`` the deviator of the
    symmetric part."""
    s = np.asarray(stress, dtype=np.float64)
    if s.shape[-2:] != (3, 3):
        raise ValueError(f"stress must have shape (..., 3, 3), got {s.shape}")
    s = 0.5 * (s + np.swapaxes(s, -1, -2))
    dev = s - np.trace(s, axis1=-2, axis2=-1)[..., None, None] * np.eye(3) / 3.0
    return np.sqrt(1.5 * np.einsum("...ij,...ij->...", dev, dev))


def max_von_mises_stress(stress) -> np.ndarray:
    """(...) largest von Mises stress over the K elements (or vertices) of (..., K, 3, 3) stresses [Pa]."""
    vm = von_mises_stress(stress)
    if vm.ndim < 1 or vm.shape[-1] == 0:
        raise ValueError("max_von_mises_stress needs at least one stress tensor per problem")
    return vm.max(axis=-1)


def best_rigid_transform(rest, deformed, weights=None) -> tuple[np.ndarray, np.ndarray]:
    """The rigid transform that best maps ``rest`` onto ``deformed`` points (weighted Kabsch).

    Minimizes ``sum_i w_i |x_i - (R X_i + t)|^2`` over rotations R (det R = +1) and translations t:
    with weighted centroids ``X_c``, ``x_c`` and ``H = sum_i w_i (X_i - X_c)(x_i - x_c)^T = U S V^T``,
    ``R = V diag(1, 1, det(V U^T)) U^T`` and ``t = x_c - R X_c``.

    Args:
        rest: (N, 3) rest positions X [m].
        deformed: (..., N, 3) deformed positions x [m] (any leading batch shape).
        weights: (N,) non-negative weights (e.g. lumped vertex masses); default: equal.

    Returns:
        R (..., 3, 3) and t (..., 3).
    """
    X = _points(rest, "rest")
    x = _points(deformed, "deformed")
    if X.ndim != 2 or x.shape[-2:] != X.shape:
        raise ValueError(f"deformed points {x.shape} do not match the rest points {X.shape}")
    n = len(X)
    w = np.ones(n) if weights is None else np.asarray(weights, dtype=np.float64)
    if w.shape != (n,) or not np.all(np.isfinite(w)) or np.any(w < 0) or w.sum() <= 0:
        raise ValueError(f"weights must be {n} non-negative finite numbers with a positive sum")
    w = w / w.sum()
    Xc = w @ X
    xc = np.einsum("i,...ij->...j", w, x)
    H = np.einsum("i,ij,...ik->...jk", w, X - Xc, x - xc[..., None, :])
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.swapaxes(Vt, -1, -2) @ np.swapaxes(U, -1, -2)))
    d = np.where(d == 0, 1.0, d)
    D = np.broadcast_to(np.eye(3), H.shape).copy()
    D[..., 2, 2] = d
    R = np.swapaxes(Vt, -1, -2) @ D @ np.swapaxes(U, -1, -2)
    t = xc - np.einsum("...ij,j->...i", R, Xc)
    return R, t


def undo_rigid_motion(points, R, t) -> np.ndarray:
    """(..., M, 3) points mapped back by the inverse of ``x = R X + t``: ``R^T (x - t)`` (R (..., 3, 3),
    t (..., 3) as from :func:`best_rigid_transform`)."""
    x = np.asarray(points, dtype=np.float64)
    return np.einsum("...ji,...nj->...ni", R, x - np.asarray(t)[..., None, :])


def rigid_removed_displacement(rest, deformed, weights=None) -> np.ndarray:
    """(..., N, 3) displacement field with the best rigid motion removed, in the rest frame:
    ``R^T (x_i - t) - X_i`` [m] (:func:`best_rigid_transform`); its norm is ``|x_i - (R X_i + t)|``."""
    R, t = best_rigid_transform(rest, deformed, weights)
    return undo_rigid_motion(deformed, R, t) - np.asarray(rest, dtype=np.float64)


def rigid_removed_deformation(rest, deformed, weights=None) -> np.ndarray:
    """(..., N) per-node deformation with the best rigid motion removed, ``|x_i - (R X_i + t)|`` [m]
    (:func:`best_rigid_transform`)."""
    return np.linalg.norm(rigid_removed_displacement(rest, deformed, weights), axis=-1)


def max_deformation(rest, deformed, weights=None) -> np.ndarray:
    """(...) the deformation metric: ``max_i |x_i - (R X_i + t)|`` [m] (:func:`rigid_removed_deformation`)."""
    return rigid_removed_deformation(rest, deformed, weights).max(axis=-1)


def instability(thresholds, limit: float) -> np.ndarray:
    """Linear or angular instability: the mean over D test directions of the acceleration at which the
    grasp is lost, ``(1 / D) sum_d a*_d`` [m/s^2 or rad/s^2].

    Args:
        thresholds: (..., D) loss-of-grasp accelerations, each in [0, ``limit``]; a direction in which the
            grasp survived the whole test counts as ``limit`` (the thesis caps the test there). NaN marks a
            direction that could not be tested (the grasp never formed); it is left out of the mean, and a
            problem with no tested direction gives NaN.
        limit: the largest acceleration tested (50 m/s^2 and 1000 rad/s^2 in the thesis).
    """
    a = np.asarray(thresholds, dtype=np.float64)
    if not (np.isfinite(limit) and limit > 0):
        raise ValueError(f"the acceleration limit must be positive, got {limit!r}")
    if a.ndim < 1 or a.shape[-1] == 0:
        raise ValueError("instability needs at least one direction")
    tested = ~np.isnan(a)
    if np.any(a[tested] < 0) or np.any(a[tested] > limit * (1 + 1e-12)):
        raise ValueError(f"thresholds must lie in [0, {limit}], got {a[tested].min()}..{a[tested].max()}")
    count = tested.sum(axis=-1)
    total = np.where(tested, a, 0.0).sum(axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, total / np.maximum(count, 1), np.nan)


def deformation_controllability(rest, deformed_states, weights=None) -> np.ndarray:
    """Deformation controllability: the largest rigid-removed deformation over all reorientation states,
    ``max_k max_i |x_ki - (R_k X_i + t_k)|`` [m].

    Args:
        rest: (N, 3) rest positions.
        deformed_states: (..., K, N, 3) positions in the K reorientation states; states whose positions
            contain NaN (not reached: the grasp was lost before) are left out; all NaN gives NaN.
        weights: (N,) weights of the rigid fit (lumped masses).
    """
    x = np.asarray(deformed_states, dtype=np.float64)
    if x.ndim < 3:
        raise ValueError(f"deformed_states must have shape (..., K, N, 3), got {x.shape}")
    reached = np.all(np.isfinite(x), axis=(-1, -2))
    safe = np.where(reached[..., None, None], x, np.asarray(rest, dtype=np.float64))
    d = max_deformation(rest, safe, weights)
    d = np.where(reached, d, -np.inf).max(axis=-1)
    return np.where(np.isfinite(d), d, np.nan)


def performance_metrics(
    pickup_success: bool,
    stress_pa: float,
    deformation_m: float,
    strain_energy_j: float,
    linear_instability: float,
    angular_instability: float,
    controllability_m: float,
) -> dict:
    """The 7 metrics of one grasp as a JSON-ready dict (keys name the quantity and its unit); metrics of
    a failed pickup are None (the thesis records fields only for successful pickups)."""

    def num(v):
        v = float(v)
        return v if np.isfinite(v) else None

    ok = bool(pickup_success)
    return {
        "pickup_success": ok,
        "max_von_mises_stress_pa": num(stress_pa) if ok else None,
        "max_deformation_m": num(deformation_m) if ok else None,
        "strain_energy_j": num(strain_energy_j) if ok else None,
        "linear_instability_m_s2": num(linear_instability),
        "angular_instability_rad_s2": num(angular_instability),
        "deformation_controllability_m": num(controllability_m),
    }
