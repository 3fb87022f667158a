"""The 7 grasp features of DefGraspSim (thesis §6.6, Table 6.2), measured once the grasp force F_p is reached
and before any loading, as pure functions on arrays (SI units, object frame).

A finger's *contact patch* is the set of object surface vertices it presses on (normal contact force > 0);
its *centre* is the force-weighted mean ``c_f = sum_i N_i x_i / sum_i N_i`` of their deformed positions.
With ``n_f`` the finger's closing direction (contact-face normal), ``x_com`` the object's centre of mass
(mass-weighted mean of the deformed vertices) and ``e_z`` the global vertical:

====================  ==============================================================================
``pure_dist`` [m]     ``|c_f - x_com|``, averaged over the two fingers
``perp_dist`` [m]     distance of ``x_com`` from the line of action ``c_f + s n_f`` of the finger's
                      squeezing force, ``|(I - n_f n_f^T)(x_com - c_f)|``, averaged over the fingers
``num_contacts``      contact vertices per finger, averaged over the fingers
``edge_dist`` [m]     distance from the finger pad's distal edge (the fingertip side, finger-frame
                      ``z = L/2``, L the pad length) to ``c_f`` along the finger, ``L/2 - z_f(c_f)``,
                      averaged over the fingers
``squeeze_dist`` [m]  change of the finger separation from first contact to F_p, ``2 t`` (both
                      fingers travel ``t`` along their closing directions)
``gripper_sep`` [m]   finger separation at F_p, ``w_0 - 2 t`` (``w_0`` at first contact)
``grav_align`` [rad]  angle between the fingers' closing axis and the global vertical,
                      ``arccos |n_f . e_z|`` in [0, pi/2] (the axis is unsigned: the fingers face
                      each other); 0 = squeezing vertically, pi/2 = horizontally
====================  ==============================================================================
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "FEATURE_NAMES",
    "center_of_mass",
    "contact_patch_centers",
    "contact_patch_lengths",
    "grasp_features",
]

FEATURE_NAMES = (
    "pure_dist",
    "perp_dist",
    "num_contacts",
    "edge_dist",
    "squeeze_dist",
    "gripper_sep",
    "grav_align",
)


def _forces(normal_forces) -> np.ndarray:
    f = np.asarray(normal_forces, dtype=np.float64)
    if f.ndim != 3 or f.shape[1] != 2:
        raise ValueError(f"normal_forces must have shape (G, 2, S) (two fingers), got {f.shape}")
    if not np.all(np.isfinite(f)) or np.any(f < 0):
        raise ValueError("normal contact forces must be finite and >= 0 [N]")
    return f


def center_of_mass(points, masses) -> np.ndarray:
    """(G, 3) mass-weighted mean ``sum_i m_i x_i / sum_i m_i`` of (G, N, 3) positions [m]."""
    x = np.asarray(points, dtype=np.float64)
    m = np.asarray(masses, dtype=np.float64)
    if x.ndim != 3 or x.shape[-1] != 3 or m.shape != x.shape[1:2]:
        raise ValueError(f"points (G, N, 3) and masses (N,) do not match: {x.shape}, {m.shape}")
    if np.any(m < 0) or m.sum() <= 0:
        raise ValueError("masses must be >= 0 with a positive total [kg]")
    return np.einsum("n,gnj->gj", m, x) / m.sum()


def contact_patch_centers(surface_points, normal_forces) -> np.ndarray:
    """(G, 2, 3) force-weighted centre of each finger's contact patch [m]; NaN for a finger without contact.

    Args:
        surface_points: (G, S, 3) deformed positions of the object's surface vertices.
        normal_forces: (G, 2, S) normal contact force of each finger on each surface vertex [N].
    """
    f = _forces(normal_forces)
    x = np.asarray(surface_points, dtype=np.float64)
    if x.shape != (f.shape[0], f.shape[2], 3):
        raise ValueError(f"surface_points must have shape {(f.shape[0], f.shape[2], 3)}, got {x.shape}")
    total = f.sum(axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        c = np.einsum("gfs,gsj->gfj", f, x) / total[..., None]
    c[total <= 0] = np.nan
    return c


def contact_patch_lengths(surface_points, normal_forces, finger_frames) -> np.ndarray:
    """(G, 2) largest distance between two contact vertices of a finger, measured in the plane of its
    contact face (the normal component removed) [m]; 0 for a patch of one vertex or none.

    Args:
        surface_points: (G, S, 3); normal_forces: (G, 2, S) [N]; finger_frames: (G, 2, 4, 4) finger frames
            in the object frame (local +y is the contact-face normal).
    """
    f = _forces(normal_forces)
    x = np.asarray(surface_points, dtype=np.float64)
    frames = np.asarray(finger_frames, dtype=np.float64)
    if frames.shape != (f.shape[0], 2, 4, 4):
        raise ValueError(f"finger_frames must have shape {(f.shape[0], 2, 4, 4)}, got {frames.shape}")
    out = np.zeros(f.shape[:2])
    for g in range(f.shape[0]):
        for k in range(2):
            p = x[g, f[g, k] > 0]
            if len(p) < 2:
                continue
            n = frames[g, k, :3, 1]
            p = p - np.outer(p @ n, n)
            out[g, k] = np.linalg.norm(p[:, None] - p[None], axis=-1).max()
    return out


def grasp_features(
    surface_points,
    normal_forces,
    points,
    masses,
    finger_frames,
    travel,
    contact_separation,
    pad_length: float,
    vertical=(0.0, 0.0, 1.0),
) -> dict[str, np.ndarray]:
    """The 7 features of Table 6.2 for G grasps at the grasp force (see the module docstring).

    Args:
        surface_points: (G, S, 3) deformed surface vertex positions [m].
        normal_forces: (G, 2, S) normal contact force of each finger per surface vertex [N].
        points: (G, N, 3) deformed positions of all vertices [m]; masses: (N,) lumped masses [kg].
        finger_frames: (G, 2, 4, 4) finger frames at first contact (object frame; local +y = closing
            direction, local +z towards the fingertip).
        travel: (G,) travel of each finger from first contact along its closing direction [m].
        contact_separation: (G,) finger separation at first contact [m].
        pad_length: the pad's length along the finger (local z) [m].
        vertical: the global up direction in the object frame.

    Returns:
        name -> (G,) array, names as :data:`FEATURE_NAMES`; features of a grasp in which a finger touches
        nothing are NaN (distances) or count zero contacts.
    """
    f = _forces(normal_forces)
    G = f.shape[0]
    frames = np.asarray(finger_frames, dtype=np.float64)
    t = np.asarray(travel, dtype=np.float64)
    w0 = np.asarray(contact_separation, dtype=np.float64)
    if t.shape != (G,) or w0.shape != (G,):
        raise ValueError(f"travel and contact_separation must have shape ({G},), got {t.shape}, {w0.shape}")
    if not (np.isfinite(pad_length) and pad_length > 0):
        raise ValueError(f"pad_length must be a positive length [m], got {pad_length!r}")
    up = np.asarray(vertical, dtype=np.float64)
    if up.shape != (3,) or not np.linalg.norm(up) > 0:
        raise ValueError(f"vertical must be a non-zero 3-vector, got {vertical!r}")
    up = up / np.linalg.norm(up)

    centers = contact_patch_centers(surface_points, f)  # (G, 2, 3)
    com = center_of_mass(points, masses)  # (G, 3)
    normals = frames[:, :, :3, 1]  # closing directions (G, 2, 3)
    r = com[:, None, :] - centers
    perp = r - np.einsum("gfj,gfj->gf", r, normals)[..., None] * normals
    # patch centre in the finger frame: z runs along the finger towards its tip
    z_local = np.einsum("gfj,gfj->gf", centers - frames[:, :, :3, 3], frames[:, :, :3, 2])
    axis = normals[:, 1]  # the right finger closes along +y of the gripper: the grasp axis
    return {
        "pure_dist": np.linalg.norm(r, axis=-1).mean(axis=1),
        "perp_dist": np.linalg.norm(perp, axis=-1).mean(axis=1),
        "num_contacts": (f > 0).sum(axis=-1).mean(axis=1).astype(np.float64),
        "edge_dist": (pad_length / 2.0 - z_local).mean(axis=1),
        "squeeze_dist": 2.0 * t,
        "gripper_sep": w0 - 2.0 * t,
        "grav_align": np.arccos(np.clip(np.abs(axis @ up), 0.0, 1.0)),
    }
