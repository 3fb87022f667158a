"""Antipodal grasp sampling for a parallel-jaw gripper (Eppner et al.; thesis §6.4 and §7.4).

For a closed object surface with outward normals ``n``:

1. draw surface points ``p`` uniformly by area (a triangle with probability proportional to its area,
   then uniform barycentric coordinates);
2. the inward normal defines the grasp axis ``a = -n(p)``; a ray from ``p`` along ``a`` leaves the
   solid at the opposite contact ``p' = p + w a``, ``w`` is the grasp width. Eppner's sampler takes
   the first surface hit (for a hollow object: a grasp of its wall, one finger in the cavity); with
   ``opposite="both"`` (default) the last hit along the ray is a second candidate when it differs
   (a grasp that spans the cavity, e.g. squeezing a tube or a ring across);
3. friction-cone test with Coulomb friction ``mu``: both contact normals must lie within the cone
   half-angle ``atan(mu)`` of the axis, ``angle(-n(p), a) <= atan(mu)`` and ``angle(n(p'), a) <= atan(mu)``;
4. ``k`` rotations (default 4) regularly spaced about each axis, ``phi_j = phi_0 + 2 pi j / k`` with a
   random offset ``phi_0``, give the approach directions; the gripper is centred at ``(p + p')/2``
   with its closing axis y along ``a`` (the left finger at +y touches ``p'``, the right one ``p``);
5. reject grasps wider than the gripper's opening (``w > 2 q_max - 2 * clearance``), grasps whose fully
   open gripper (pads, finger links, hand) overlaps the object, and grasps in which a finger would
   touch nothing; keep the analytic finger closing distances (``gripper.finger_closing_distances``).

Sampling is reproducible: all randomness comes from ``numpy.random.default_rng(seed)``.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import numpy as np
from tqdm.auto import tqdm

from defgraspnets.objects.queries import first_ray_hits
from defgraspnets.objects.surface import as_trimesh, check_surface

from .gripper import FRANKA_HAND, ParallelJawGripper, finger_closing_distances

__all__ = ["GraspSet", "grasp_frames", "sample_antipodal_grasps"]


@dataclass
class GraspSet:
    """G grasps on one object, all in the object frame [m, rad].

    Attributes:
        poses: (G, 4, 4) gripper poses (gripper frame in object frame, see ``grasp.gripper``).
        contact_points: (G, 2, 3) contact of the left finger (index 0, at +y) and of the right finger.
        contact_normals: (G, 2, 3) outward unit surface normals at the two contacts.
        axes: (G, 3) unit grasp axes = gripper +y, from the right contact to the left one.
        angles: (G,) rotation of the approach direction about the axis [rad].
        widths: (G,) distance between the two contacts [m].
        closing_distances: (G, 2) analytic finger joint states: travel of each finger from fully open
            to first contact [m].
        axis_ids: (G,) id of the sampled grasp axis and exit each grasp came from (its rotations
            share it): ``2 * (index of the sampled surface point) + far_side``.
        far_side: (G,) True where the left contact is the ray's last exit rather than its first (the
            grasp spans a cavity or gap of the object).
        friction_coefficient: the mu of the friction-cone test.
        seed: the random seed.
        stats: counts of candidates and of each rejection reason.
    """

    poses: np.ndarray
    contact_points: np.ndarray
    contact_normals: np.ndarray
    axes: np.ndarray
    angles: np.ndarray
    widths: np.ndarray
    closing_distances: np.ndarray
    axis_ids: np.ndarray
    far_side: np.ndarray
    friction_coefficient: float
    seed: int | None
    stats: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.poses)

    def __getitem__(self, index) -> GraspSet:
        """A subset (index: int, slice, array of indices or boolean mask)."""
        idx = np.atleast_1d(np.arange(len(self))[index])
        return GraspSet(
            self.poses[idx],
            self.contact_points[idx],
            self.contact_normals[idx],
            self.axes[idx],
            self.angles[idx],
            self.widths[idx],
            self.closing_distances[idx],
            self.axis_ids[idx],
            self.far_side[idx],
            self.friction_coefficient,
            self.seed,
            dict(self.stats),
        )

    def finger_openings(self, gripper: ParallelJawGripper = FRANKA_HAND) -> np.ndarray:
        """(G, 2) finger positions at first contact, ``q_max - closing`` [m]."""
        return gripper.max_finger_opening - self.closing_distances

    def as_dict(self) -> dict[str, np.ndarray]:
        """Arrays by name (for HDF5 / npz storage)."""
        return {
            "poses": self.poses,
            "contact_points": self.contact_points,
            "contact_normals": self.contact_normals,
            "axes": self.axes,
            "angles": self.angles,
            "widths": self.widths,
            "closing_distances": self.closing_distances,
            "axis_ids": self.axis_ids,
            "far_side": self.far_side,
        }


def _perpendicular(axis: np.ndarray) -> np.ndarray:
    """(N, 3) unit vectors perpendicular to unit ``axis`` (built from the least aligned world axis)."""
    world = np.eye(3)[np.argmin(np.abs(axis), axis=1)]
    e = np.cross(axis, world)
    return e / np.linalg.norm(e, axis=1, keepdims=True)


def grasp_frames(centers, axes, angles) -> np.ndarray:
    """(N, 4, 4) gripper poses with origin ``centers``, closing axis +y = ``axes`` and the approach +z
    rotated by ``angles`` about the axis from a reference perpendicular direction."""
    a = np.asarray(axes, dtype=np.float64)
    a = a / np.linalg.norm(a, axis=1, keepdims=True)
    e1 = _perpendicular(a)
    e2 = np.cross(a, e1)
    ang = np.asarray(angles, dtype=np.float64)[:, None]
    z = np.cos(ang) * e1 + np.sin(ang) * e2
    x = np.cross(a, z)
    T = np.tile(np.eye(4), (len(a), 1, 1))
    T[:, :3, 0], T[:, :3, 1], T[:, :3, 2] = x, a, z
    T[:, :3, 3] = centers
    return T


def sample_antipodal_grasps(
    surface,
    num_grasps: int = 100,
    gripper: ParallelJawGripper = FRANKA_HAND,
    friction_coefficient: float = 0.7,
    rotations_per_axis: int = 4,
    seed: int | None = 0,
    clearance: float = 0.0,
    max_candidates: int | None = None,
    opposite: str = "both",
    exact_contact: bool = True,
    progress: bool = False,
) -> GraspSet:
    """Sample up to ``num_grasps`` collision-free antipodal grasps on a closed surface.

    Args:
        surface: closed, outward-oriented object surface in the object frame (trimesh.Trimesh,
            (vertices, faces) or a TetMesh, whose boundary is used: the surface the simulator sees).
        num_grasps: grasps to return (grasps from the same axis are consecutive).
        gripper: the parallel-jaw gripper.
        friction_coefficient: Coulomb mu; contact normals must lie within ``atan(mu)`` of the axis.
        rotations_per_axis: approach directions regularly spaced about each grasp axis.
        seed: random seed (None: fresh entropy, not reproducible).
        clearance: required free space around the open gripper and on each side of the contacts [m].
        max_candidates: give up after this many sampled surface points (default ``50 * num_grasps``).
        opposite: which exit of the ray along the inward normal is the opposite contact: ``"first"``
            (Eppner et al.), ``"last"``, or ``"both"`` (both, when they differ).
        exact_contact: closing distances of the flat faces against the polyhedral surface (True) or the
            thesis' vertex projection (False).
        progress: show a tqdm progress bar.

    Returns:
        A :class:`GraspSet`; it holds fewer than ``num_grasps`` grasps (with a warning) if the candidate
        budget ran out.

    Raises:
        ObjectMeshError: if the surface is not closed and consistently oriented.
        ValueError: for a non-positive ``num_grasps``, ``friction_coefficient`` or ``rotations_per_axis``.
    """
    if num_grasps <= 0 or rotations_per_axis <= 0:
        raise ValueError("num_grasps and rotations_per_axis must be positive")
    if not friction_coefficient > 0:
        raise ValueError(f"friction_coefficient must be positive, got {friction_coefficient}")
    if opposite not in ("first", "last", "both"):
        raise ValueError(f"opposite must be 'first', 'last' or 'both', got {opposite!r}")
    if hasattr(surface, "surface_trimesh"):  # a TetMesh: sample on its boundary
        surface = surface.surface_trimesh()
    mesh = as_trimesh(surface, "grasp sampling surface")
    mesh.remove_unreferenced_vertices()  # e.g. the interior vertices of a tet mesh boundary
    check_surface(mesh, "grasp sampling surface")
    V, F = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    tri = V[F]
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area2 = np.linalg.norm(normals, axis=1)
    normals = normals / area2[:, None]
    prob = area2 / area2.sum()
    cos_cone = math.cos(math.atan(friction_coefficient))
    max_width = gripper.max_width - 2 * clearance
    scale = float(np.ptp(V, axis=0).max())
    rng = np.random.default_rng(seed)
    max_candidates = 50 * num_grasps if max_candidates is None else max_candidates

    stats = dict(candidates=0, no_exit=0, friction=0, too_wide=0, collision=0, no_contact=0)
    kept: dict[str, list] = {k: [] for k in ("T", "cp", "cn", "ax", "ang", "w", "c", "id", "far")}
    n_kept = 0
    bar = tqdm(total=num_grasps, desc="antipodal grasps", unit="grasp", disable=not progress, leave=False)
    while n_kept < num_grasps and stats["candidates"] < max_candidates:
        batch = min(max(16, 2 * math.ceil((num_grasps - n_kept) / rotations_per_axis)), max_candidates)
        batch = min(batch, max_candidates - stats["candidates"])
        axis_offset = stats["candidates"]
        stats["candidates"] += batch
        # 1) area-weighted surface points
        fi = rng.choice(len(F), size=batch, p=prob)
        r1, r2 = rng.random(batch), rng.random(batch)
        flip = r1 + r2 > 1
        r1[flip], r2[flip] = 1 - r1[flip], 1 - r2[flip]
        p = tri[fi, 0] + r1[:, None] * (tri[fi, 1] - tri[fi, 0]) + r2[:, None] * (tri[fi, 2] - tri[fi, 0])
        phi0 = rng.random(batch) * (2 * math.pi / rotations_per_axis)
        # 2) opposite contact(s) along the inward normal: first and/or last exit of the ray
        axis = -normals[fi]
        point_of = np.arange(batch)  # candidate -> sampled point
        t_hit, f_hit = first_ray_hits(p, axis, tri, t_min=1e-9 * scale, last=opposite == "last")
        far = np.full(batch, opposite == "last")
        if opposite == "both":
            t_last, f_last = first_ray_hits(p, axis, tri, t_min=1e-9 * scale, last=True)
            extra = np.nonzero(np.isfinite(t_last) & (t_last > t_hit + 1e-9 * scale))[0]
            point_of = np.concatenate([point_of, extra])
            t_hit, f_hit = np.concatenate([t_hit, t_last[extra]]), np.concatenate([f_hit, f_last[extra]])
            far = np.concatenate([far, np.ones(len(extra), dtype=bool)])
        fi, p, phi0, axis = fi[point_of], p[point_of], phi0[point_of], axis[point_of]
        ok = np.isfinite(t_hit)
        stats["no_exit"] += int((~ok).sum())
        f_hit = np.where(ok, f_hit, 0)
        # 3) friction cones (the axis equals the inward normal at p, tested for generality)
        n_exit = normals[f_hit]
        in_cone = (np.einsum("ij,ij->i", n_exit, axis) >= cos_cone) & (
            np.einsum("ij,ij->i", -normals[fi], axis) >= cos_cone
        )
        stats["friction"] += int((ok & ~in_cone).sum())
        ok &= in_cone
        width = np.where(ok, t_hit, np.inf)
        wide = ok & (width > max_width)
        stats["too_wide"] += int(wide.sum())
        ok &= ~wide
        idx = np.nonzero(ok)[0]
        if not len(idx):
            continue
        q_pt = p[idx] + width[idx, None] * axis[idx]
        # 4) rotations about each axis
        k = rotations_per_axis
        rep = np.repeat(idx, k)
        angles = (np.repeat(phi0[idx], k) + np.tile(np.arange(k), len(idx)) * 2 * math.pi / k) % (2 * math.pi)
        centers = 0.5 * (np.repeat(p[idx], k, 0) + np.repeat(q_pt, k, 0))
        poses = grasp_frames(centers, axis[rep], angles)
        # 5) collisions of the open gripper and finger contact
        free = ~gripper.collides(mesh, poses, clearance=clearance)
        stats["collision"] += int((~free).sum())
        closing, touches = finger_closing_distances(V, poses, gripper, faces=F if exact_contact else None)
        good = free & touches.all(axis=1)
        stats["no_contact"] += int((free & ~touches.all(axis=1)).sum())
        sel = np.nonzero(good)[0][: num_grasps - n_kept]
        if not len(sel):
            continue
        src = rep[sel]
        kept["T"].append(poses[sel])
        kept["cp"].append(np.stack([np.repeat(q_pt, k, 0)[sel], p[src]], axis=1))
        kept["cn"].append(np.stack([n_exit[src], normals[fi[src]]], axis=1))
        kept["ax"].append(axis[src])
        kept["ang"].append(angles[sel])
        kept["w"].append(width[src])
        kept["c"].append(closing[sel])
        kept["id"].append(2 * (axis_offset + point_of[src]) + far[src])
        kept["far"].append(far[src])
        n_kept += len(sel)
        bar.update(len(sel))
    bar.close()
    if n_kept < num_grasps:
        warnings.warn(
            f"antipodal sampler found {n_kept} of {num_grasps} grasps in {stats['candidates']} candidates "
            f"(rejections: {stats})",
            stacklevel=2,
        )

    def cat(key, shape):
        return np.concatenate(kept[key]) if kept[key] else np.zeros((0, *shape))

    ids = cat("id", ())
    return GraspSet(
        poses=cat("T", (4, 4)),
        contact_points=cat("cp", (2, 3)),
        contact_normals=cat("cn", (2, 3)),
        axes=cat("ax", (3,)),
        angles=cat("ang", ()),
        widths=cat("w", ()),
        closing_distances=cat("c", (2,)),
        axis_ids=ids.astype(np.int64),
        far_side=cat("far", ()).astype(bool),
        friction_coefficient=float(friction_coefficient),
        seed=seed,
        stats=stats,
    )
