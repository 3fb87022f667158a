"""A Franka-like parallel-jaw gripper with its specialized features removed (thesis §6.4).

Frames and conventions (SI units, metres):

- **Gripper frame** G: origin midway between the two finger pads at the centre of their contact faces
  (the Franka hand's tool centre point, 0.1034 m from the flange); **+z is the approach direction**
  (the fingers point along +z, the hand body lies at z < 0); **y is the closing axis**; x = y cross z
  runs across the width of the pads.
- **Pose** ``T`` (4, 4): gripper in object frame, ``p_object = R p_gripper + t``.
- **Fingers**: index 0 is the *left* finger at +y, closing towards -y; index 1 is the *right* finger at
  -y, closing towards +y. The finger position ``q_i`` (the Franka finger joint value) is the distance
  of finger i's contact face from the mid-plane y = 0: ``q in [0, q_max]``, ``q_max = 0.04`` m (fully
  open, 0.08 m between the pads). The **closing distance** (the thesis' analytic finger joint state,
  §7.5) is ``c_i = q_max - q_i``, how far finger i has travelled from fully open.
- **Finger frame** F_i: origin at the centre of finger i's contact face, local +y is the contact-face
  normal (the closing direction, pointing at the object), local +z = gripper +z (towards the tip),
  local x = y cross z. The right finger's frame is the gripper frame shifted to y = -q; the left one is
  also rotated by pi about z.

Geometry (source: the Franka Emika ``franka_description`` meshes as shipped in ``pybullet_data``
(``franka_panda/meshes/visual/finger.obj``, ``collision/hand.obj``, ``panda.urdf``; Apache-2.0) and
robosuite's ``panda_gripper.xml``; measured with trimesh):

- finger joint origin at 0.0584 m from the flange, TCP at 0.1034 m (Franka "F_T_EE");
- flat fingertip (pad) contact face 17.5 mm wide (x) and 17.7 mm long (z), centred on the TCP, the
  fingertip 14.4 mm thick; the ridges of the real fingertip are removed. Modelled as a box with
  1 mm rounded edges; the flat contact rectangle is therefore 15.5 mm x 15.7 mm;
- behind the pad the finger (21 mm wide) is recessed by >= 11.6 mm from the contact plane down to the
  hand (a collision box, not part of the contact geometry);
- hand body: 63.2 mm (x) x 208 mm (y) x 91.9 mm (z) box from 37.4 mm to 129.3 mm behind the TCP.

Only the pads are contact geometry (they are what the FEM squeezes with, and what the multigraph's
gripper nodes are); the proximal finger links and the hand are boxes for collision checks of the
open gripper.
"""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
import torch

from defgraspnets.objects.primitives import rounded_box_mesh
from defgraspnets.objects.queries import triangles_overlap_box, winding_numbers
from defgraspnets.objects.surface import as_trimesh

__all__ = [
    "FRANKA_HAND",
    "Box",
    "ContactFace",
    "ParallelJawGripper",
    "SurfaceClosingDistances",
    "finger_closing_distances",
]

LEFT, RIGHT = 0, 1
_SIGNS = (1.0, -1.0)  # finger i sits at y = _SIGNS[i] * q_i
_RIM_SECTIONS = (0.2, 0.4, 0.6, 0.8, 0.95)  # planes through the pad's rim, as fractions of its width


@dataclass(frozen=True, eq=False)
class Box:
    """An axis-aligned box in the gripper frame: ``|x - center| <= half_extents`` componentwise [m]."""

    name: str
    center: np.ndarray
    half_extents: np.ndarray

    def corners(self) -> np.ndarray:
        """(8, 3) corner points."""
        s = np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], dtype=np.float64)
        return self.center + s * self.half_extents


@dataclass(frozen=True, eq=False)
class ContactFace:
    """The flat contact rectangle of a finger pad: points ``center + s u + t v``, ``|s| <= a``, ``|t| <= b``.

    ``normal`` is the closing direction (pointing from the pad towards the object), ``axis_u`` runs
    across the pad width and ``axis_v`` along the finger (towards its tip); ``half_extents = (a, b)``.
    """

    center: np.ndarray
    normal: np.ndarray
    axis_u: np.ndarray
    axis_v: np.ndarray
    half_extents: np.ndarray

    def corners(self) -> np.ndarray:
        """(4, 3) corners, counter-clockwise seen from the object (against the normal)."""
        a, b = self.half_extents
        s = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=np.float64)
        return self.center + (s[:, :1] * a) * self.axis_u + (s[:, 1:] * b) * self.axis_v

    def transformed(self, pose) -> ContactFace:
        """The same face expressed in another frame (``pose`` maps this frame into it)."""
        pose = np.asarray(pose, dtype=np.float64)
        R, t = pose[:3, :3], pose[:3, 3]
        return ContactFace(
            R @ self.center + t, R @ self.normal, R @ self.axis_u, R @ self.axis_v, self.half_extents
        )


def _check_pose(pose) -> np.ndarray:
    pose = np.asarray(pose, dtype=np.float64)
    if pose.shape[-2:] != (4, 4):
        raise ValueError(f"a pose must be a (4, 4) homogeneous transform, got shape {pose.shape}")
    if not np.isfinite(pose).all():
        raise ValueError("pose contains non-finite values")
    R = pose[..., :3, :3]
    err = np.abs(np.swapaxes(R, -1, -2) @ R - np.eye(3)).max()
    if err > 1e-6 or np.any(np.linalg.det(R) < 0):
        raise ValueError(f"pose rotation is not a proper rotation (|R^T R - I| = {err:.2e})")
    return pose


@dataclass(frozen=True)
class ParallelJawGripper:
    """A parallel-jaw gripper: two box-shaped finger pads with a flat contact face, proximal finger
    links and a hand body (all dimensions in metres; defaults are the Franka hand, see module doc).

    Args:
        max_finger_opening: ``q_max``, the largest distance of a contact face from the mid-plane.
        pad_size: pad (width along x, thickness along the normal, length along z).
        pad_edge_radius: fillet radius of the pad edges; the flat contact rectangle has half extents
            ``(width/2 - r, length/2 - r)``.
        pad_mesh_edge_length: target edge length of the pad triangle mesh.
        link_width, link_recess, link_thickness, link_z_range: the proximal finger link box: full width
            along x; offset of its inner face behind the contact plane; its thickness; its z extent.
        hand_center, hand_half_extents: the hand-body box in the gripper frame.
    """

    max_finger_opening: float = 0.04
    pad_size: tuple[float, float, float] = (0.0175, 0.0144, 0.0177)
    pad_edge_radius: float = 0.001
    pad_mesh_edge_length: float = 0.0025
    link_width: float = 0.021
    link_recess: float = 0.0116
    link_thickness: float = 0.0147
    link_z_range: tuple[float, float] = (-0.045, -0.00885)
    hand_center: tuple[float, float, float] = (0.0, 0.0, -0.08335)
    hand_half_extents: tuple[float, float, float] = (0.0316, 0.104, 0.04595)
    name: str = field(default="franka_hand")

    def __post_init__(self):
        w, th, ln = self.pad_size
        if min(w, th, ln) <= 0 or not 0 <= self.pad_edge_radius < min(w, ln) / 2:
            raise ValueError(
                f"{self.name}: invalid pad size {self.pad_size} / edge radius {self.pad_edge_radius}"
            )
        if self.max_finger_opening <= 0:
            raise ValueError(f"{self.name}: max_finger_opening must be positive")

    # ------------------------------------------------------------------ finger kinematics
    @property
    def max_width(self) -> float:
        """Largest distance between the two contact faces, ``2 q_max`` [m]."""
        return 2.0 * self.max_finger_opening

    @property
    def contact_half_extents(self) -> np.ndarray:
        """(a, b): half width (along u = +-x) and half length (along v = z) of the flat contact rectangle."""
        r = self.pad_edge_radius
        return np.array([self.pad_size[0] / 2 - r, self.pad_size[2] / 2 - r])

    def _opening(self, opening) -> np.ndarray:
        q = np.full(2, self.max_finger_opening) if opening is None else np.asarray(opening, dtype=np.float64)
        q = np.broadcast_to(q, (2,)).astype(np.float64)
        if np.any(q < -1e-12) or np.any(q > self.max_finger_opening + 1e-12) or not np.isfinite(q).all():
            raise ValueError(f"finger openings must lie in [0, {self.max_finger_opening}] m, got {q}")
        return q

    def opening_from_closing(self, closing) -> np.ndarray:
        """Finger positions ``q_i = q_max - c_i`` from closing distances ``c_i``."""
        return self.max_finger_opening - np.asarray(closing, dtype=np.float64)

    def finger_transforms(self, opening=None) -> np.ndarray:
        """(2, 4, 4) finger frames F_i in the gripper frame at finger positions ``opening`` (default open)."""
        q = self._opening(opening)
        T = np.tile(np.eye(4), (2, 1, 1))
        T[LEFT, :3, :3] = np.diag([-1.0, -1.0, 1.0])  # rotated by pi about z: local +y = gripper -y
        T[LEFT, 1, 3] = q[LEFT]
        T[RIGHT, 1, 3] = -q[RIGHT]
        return T

    def finger_poses(self, pose, opening=None) -> np.ndarray:
        """(2, 4, 4) finger frames in the object frame for gripper ``pose`` (gripper in object frame)."""
        return _check_pose(pose) @ self.finger_transforms(opening)

    @cached_property
    def pad_mesh(self) -> tuple[np.ndarray, np.ndarray]:
        """(vertices (V, 3), faces (F, 3)) of one pad in its finger frame: contact face on local y = 0
        (outward normal +y), pad body at -thickness <= y <= 0."""
        w, th, ln = self.pad_size
        mesh = rounded_box_mesh((w, th, ln), self.pad_edge_radius, self.pad_mesh_edge_length)
        v = np.asarray(mesh.vertices) + [0.0, -th / 2, 0.0]
        v.setflags(write=False)
        f = np.asarray(mesh.faces, dtype=np.int64)
        f.setflags(write=False)
        return v, f

    def finger_meshes(self, pose=None, opening=None) -> list[tuple[np.ndarray, np.ndarray]]:
        """[(vertices, faces), (vertices, faces)] of the left and right pads in the object frame
        (in the gripper frame if ``pose`` is None) at finger positions ``opening`` (default: open)."""
        v, f = self.pad_mesh
        T = self.finger_transforms(opening)
        if pose is not None:
            T = _check_pose(pose) @ T
        return [(v @ Ti[:3, :3].T + Ti[:3, 3], f.copy()) for Ti in T]

    def contact_faces(self, pose=None, opening=None) -> list[ContactFace]:
        """Left and right flat contact rectangles in the object frame (gripper frame if ``pose`` is None)."""
        a_b = self.contact_half_extents
        faces = []
        for Ti in self.finger_transforms(opening):
            face = ContactFace(Ti[:3, 3].copy(), Ti[:3, 1].copy(), Ti[:3, 0].copy(), Ti[:3, 2].copy(), a_b)
            faces.append(face if pose is None else face.transformed(_check_pose(pose)))
        return faces

    def collision_boxes(self, opening=None, clearance: float = 0.0) -> list[Box]:
        """Boxes in the gripper frame covering the pads, the proximal finger links and the hand body,
        each grown by ``clearance`` [m]."""
        q = self._opening(opening)
        w, th, ln = self.pad_size
        z0, z1 = self.link_z_range
        boxes = []
        for i, side in ((LEFT, "left"), (RIGHT, "right")):
            s = _SIGNS[i]
            boxes.append(
                Box(f"{side}_pad", np.array([0.0, s * (q[i] + th / 2), 0.0]), np.array([w, th, ln]) / 2)
            )
            y_link = s * (q[i] + self.link_recess + self.link_thickness / 2)
            boxes.append(
                Box(
                    f"{side}_link",
                    np.array([0.0, y_link, (z0 + z1) / 2]),
                    np.array([self.link_width / 2, self.link_thickness / 2, (z1 - z0) / 2]),
                )
            )
        boxes.append(
            Box("hand", np.asarray(self.hand_center, float), np.asarray(self.hand_half_extents, float))
        )
        if clearance:
            boxes = [Box(b.name, b.center, b.half_extents + clearance) for b in boxes]
        return boxes

    # ------------------------------------------------------------------ collision check
    def collisions(self, surface, poses, opening=None, clearance: float = 0.0, chunk: int = 32) -> np.ndarray:
        """(G, B) True where collision box b of the gripper at pose g overlaps the solid object.

        A box overlaps the closed object surface if one of its triangles intersects the box
        (separating-axis test) or if the box lies entirely inside the object (generalized winding
        number of the box centre > 1/2). Box order as in :meth:`collision_boxes`.

        Args:
            surface: closed object surface (trimesh.Trimesh or (vertices, faces)) in the object frame.
            poses: (G, 4, 4) or (4, 4) gripper poses in the object frame.
            opening: finger positions (default fully open).
            clearance: grow every box by this margin [m].
        """
        mesh = as_trimesh(surface)
        V, F = np.asarray(mesh.vertices), np.asarray(mesh.faces)
        poses = _check_pose(poses).reshape(-1, 4, 4)
        boxes = self.collision_boxes(opening, clearance)
        result = np.zeros((len(poses), len(boxes)), dtype=bool)
        # a triangle that meets a box has all its vertices within the longest edge of the box
        max_edge = float(np.linalg.norm(V[F] - V[F[:, [1, 2, 0]]], axis=2).max())
        need_inside = []  # (pose index, box index) pairs to test by winding number
        for start in range(0, len(poses), chunk):
            P = poses[start : start + chunk]
            R, t = P[:, :3, :3], P[:, :3, 3]
            xg = np.einsum("nk,gkj->gnj", V, R) - np.einsum("gk,gkj->gj", t, R)[:, None]  # (g, V, 3)
            lo, hi = xg.min(axis=1), xg.max(axis=1)  # object AABB in the gripper frame
            for b, box in enumerate(boxes):
                h = box.half_extents
                overlap_aabb = np.all(lo <= box.center + h, axis=-1) & np.all(hi >= box.center - h, axis=-1)
                for g in np.nonzero(overlap_aabb)[0]:
                    local = xg[g] - box.center
                    near = np.all(np.abs(local) <= h + max_edge, axis=-1)
                    fi = np.nonzero(near[F].all(axis=1))[0]
                    if len(fi) and triangles_overlap_box(local[F[fi]], h).any():
                        result[start + g, b] = True
                    elif np.all(lo[g] <= box.center) and np.all(hi[g] >= box.center):
                        need_inside.append((start + g, b))
        if need_inside:
            gi, bi = np.array(need_inside).T
            centres = np.stack([boxes[b].center for b in bi])
            points = np.einsum("gij,gj->gi", poses[gi, :3, :3], centres) + poses[gi, :3, 3]
            inside = winding_numbers(points, V[F]) > 0.5
            result[gi[inside], bi[inside]] = True
        return result

    def collides(self, surface, poses, opening=None, clearance: float = 0.0) -> np.ndarray:
        """(G,) True where any part of the gripper (pads, finger links, hand) overlaps the object."""
        return self.collisions(surface, poses, opening, clearance).any(axis=1)

    # ------------------------------------------------------------------ analytic finger joint states
    def closing_distances(self, points, poses, faces=None, temperature: float | None = None):
        """See :func:`finger_closing_distances` (with this gripper)."""
        return finger_closing_distances(points, poses, self, faces=faces, temperature=temperature)


FRANKA_HAND = ParallelJawGripper()
"""The default gripper: Franka hand dimensions, specialized features removed."""


def finger_closing_distances(
    points,
    poses,
    gripper: ParallelJawGripper = FRANKA_HAND,
    faces=None,
    temperature: float | None = None,
):
    """Analytic finger joint states (thesis §7.5): how far each finger closes from fully open to touch.

    The object's surface points are expressed in the gripper frame, ``x_g = R^T (x - t)``, and in each
    finger's contact-face coordinates ``(u, v, d)``: ``u``, ``v`` in the face plane, ``d`` the distance
    in front of the *fully open* face along its normal (``d = q_max - y_g`` for the left finger,
    ``q_max + y_g`` for the right). The vertices whose projection falls inside the flat contact
    rectangle (``|u| <= a``, ``|v| <= b``) and that lie in front of it (``d >= 0``) are the thesis'
    candidates; the closing distance is

        c_i = min(q_max, min_candidates d).

    Two refinements make ``c_i`` the first contact with the actual pad:

    - the pad's rounded rim (fillet radius ``r`` around the rectangle): a vertex at in-plane distance
      ``s <= r`` outside the rectangle meets the rim after ``d + r - sqrt(r^2 - s^2)``;
    - with ``faces`` given, the points where the surface's edges cross the four side planes of the
      rectangle's prism and where the prism's four corner lines pierce its triangles are candidates
      too, so the flat face's first contact with the polyhedral surface is exact (a linear function
      over the clipped triangles is minimal at such points). Without ``faces`` the flat face can
      overlap the surface between vertices by up to the mesh's chord error.

    The rim is resolved at the vertices and at edge crossings of planes through it at 20, 40, 60, 80
    and 95 % of its width; between these sections the fillet is in effect replaced by its chords, so
    an object surface can overlap it by at most that chord error (about 5-15 micrometres for the
    1 mm fillet).

    ``c_i`` is a differentiable (piecewise-smooth) function of the pose: the set of candidates is held
    fixed and gradients flow through their coordinates. Where several candidates tie (a pad parallel
    to a mesh face, as in sampled antipodal grasps) it has a kink in the rotation and autograd returns
    the mean of the tied subgradients; the derivative in translation is unaffected. ``temperature``
    (in metres) replaces the exact minimum by the smooth soft-min
    ``-tau log(sum exp(-d/tau) + exp(-q_max/tau))``, which lies within ``tau log(n + 1)`` below the
    exact value and spreads the gradient over the nearly-closest points.

    Args:
        points: (N, 3) object surface vertices in the object frame [m] (numpy or torch).
        poses: (..., 4, 4) gripper poses in the object frame (numpy or torch, may require grad).
        gripper: the gripper (contact rectangle and ``q_max``).
        faces: optional (F, 3) triangle indices into ``points`` for the exact polyhedral contact.
        temperature: optional soft-min temperature [m]; None for the exact minimum.
    Returns:
        closing: (..., 2) closing distances of the left and right finger [m], in ``[0, q_max]``.
        touches: (..., 2) bool, whether the finger reaches the object within its travel (False: the
            finger would close fully without contact and ``closing = q_max``).
        Both are numpy arrays when neither ``points`` nor ``poses`` is a torch tensor.
    """
    as_numpy = not (torch.is_tensor(points) or torch.is_tensor(poses))
    if as_numpy:
        # NumPy callers need no autograd; the many small sparse ops below run fastest on one thread
        # (and avoid intra-op thread stalls when the cores are shared with other processes).
        with _torch_threads(1):
            closing, touches = finger_closing_distances(
                # (copies: a read-only array, e.g. a mesh's points, would make torch warn on every call)
                torch.from_numpy(np.array(points, dtype=np.float64)),
                torch.from_numpy(np.array(poses, dtype=np.float64)),
                gripper,
                faces,
                temperature,
            )
        return closing.numpy(), touches.numpy()
    ref = points if torch.is_tensor(points) else poses if torch.is_tensor(poses) else None
    dtype = ref.dtype if ref is not None and ref.is_floating_point() else torch.float64
    device = ref.device if ref is not None else None
    X = torch.as_tensor(points, dtype=dtype, device=device)
    T = torch.as_tensor(poses, dtype=dtype, device=device)
    if X.ndim != 2 or X.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {tuple(X.shape)}")
    if T.shape[-2:] != (4, 4):
        raise ValueError(f"poses must have shape (..., 4, 4), got {tuple(T.shape)}")
    if not bool(torch.isfinite(X).all()):
        raise ValueError("points contain non-finite values")
    if temperature is not None and not temperature > 0:
        raise ValueError(f"temperature must be positive (metres) or None, got {temperature}")
    batch_shape = T.shape[:-2]
    T = T.reshape(-1, 4, 4)
    R, t = T[:, :3, :3], T[:, :3, 3]
    xg = torch.einsum("bki,bnk->bni", R, X[None] - t[:, None, :])  # (B, N, 3) = (X - t) R
    a, b = (float(v) for v in gripper.contact_half_extents)
    q = float(gripper.max_finger_opening)

    # Which (pose, element) pairs can produce a candidate is decided once, without gradients, in
    # NumPy; |u| = |x_g| and v = z_g are the same for both fingers. An edge or triangle that crosses
    # the rectangle's prism boundary has all its vertices within the longest edge of the rectangle.
    xn = xg.detach().cpu().numpy()
    ax, az = np.abs(xn[..., 0]), np.abs(xn[..., 2])
    rim = float(gripper.pad_edge_radius)
    sparse = {"vertex": np.nonzero((ax <= a + rim) & (az <= b + rim))}
    if faces is not None:
        Fn = np.asarray(faces, dtype=np.int64)
        if Fn.ndim != 2 or Fn.shape[1] != 3 or Fn.min() < 0 or Fn.max() >= len(X):
            raise ValueError(f"faces must be (F, 3) indices into the {len(X)} points")
        En = _surface_edges(Fn)
        Xn = X.detach().cpu().numpy()
        max_edge = float(np.linalg.norm(Xn[En[:, 0]] - Xn[En[:, 1]], axis=1).max()) * (1 + 1e-9)
        near = (ax <= a + rim + max_edge) & (az <= b + rim + max_edge)
        be, ee = np.nonzero(near[:, En[:, 0]] & near[:, En[:, 1]])
        bf, ff = np.nonzero(near[:, Fn[:, 0]] & near[:, Fn[:, 1]] & near[:, Fn[:, 2]])
        sparse["edge"] = (be, En[ee])
        sparse["face"] = (bf, Fn[ff])
    index = {k: tuple(torch.as_tensor(x, device=X.device) for x in v) for k, v in sparse.items()}

    closing, touches = [], []
    for i in (LEFT, RIGHT):
        s = _SIGNS[i]
        # contact-face coordinates: left finger u = -x_g, right u = +x_g; v = z_g; d in front of the open face
        flip = torch.tensor([-s, 1.0, -s], dtype=xg.dtype, device=xg.device)
        offset = torch.tensor([0.0, 0.0, q], dtype=xg.dtype, device=xg.device)

        def uvd(bi, ni, flip=flip, offset=offset):
            return xg[bi, ni][..., [0, 2, 1]] * flip + offset  # (..., 3): u, v, d

        vals, owner = _candidates(uvd, index, a, b, rim)
        touches.append(
            torch.zeros(len(T), dtype=torch.bool, device=X.device).index_fill(0, owner[vals <= q], True)
        )
        closing.append(_reduce_min(vals, owner, len(T), q, temperature))
    closing = torch.stack(closing, dim=-1).reshape(*batch_shape, 2)
    touches = torch.stack(touches, dim=-1).reshape(*batch_shape, 2)
    return closing, touches


def _surface_edges(faces: np.ndarray) -> np.ndarray:
    """(E, 2) unique undirected edges (sorted vertex pairs) of triangles (F, 3)."""
    return np.unique(np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1), axis=0)


def _section_offsets(rim: float) -> list[float]:
    """Offsets beyond the contact rectangle's sides of the planes that section the pad front: the sides
    themselves and, with a rounded rim, planes through it (:data:`_RIM_SECTIONS`)."""
    return [0.0] + ([rim * f for f in _RIM_SECTIONS] if rim > 0 else [])


@contextmanager
def _torch_threads(n: int):
    """Temporarily run torch's intra-op parallelism on ``n`` threads."""
    previous = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


def _candidates(uvd, index: dict, a: float, b: float, rim: float = 0.0):
    """Candidate contact distances of one finger and the batch index each belongs to.

    ``uvd(batch_idx, vertex_idx)`` gives the face coordinates (u, v) and the distance d in front of
    the open face of surface vertices (with gradients). ``index`` holds the (pose, element) pairs to
    examine: ``vertex`` (B_k, N_k) points in the projection of the pad's front (rectangle grown by
    ``rim``); optionally ``edge`` (B_k, (K, 2) vertex ids) and ``face`` (B_k, (K, 3)). Candidates are

    - vertices in front of the flat rectangle (distance d), and in front of the pad's rounded rim:
      at distance ``s`` (<= rim) outside the rectangle the fillet of radius ``rim`` is recessed by
      ``rim - sqrt(rim^2 - s^2)``, so such a vertex is reached after ``d`` plus that recess;
    - crossings of edges with the prism's side planes ``u = +-a`` and ``v = +-b`` (and with planes
      through the rim, at 20, 40, 60, 80 and 95 % of its width, as samples of edge-fillet contact),
      and the points where the corner lines ``(+-a, +-b)`` pierce triangles;

    each kept if not behind the pad surface (distance >= 0).
    """

    def pad_distance(p):
        """Travel until the pad surface reaches points p (K, 3), and whether p faces the pad front."""
        su = torch.clamp(p[:, 0].abs() - a, min=0.0)
        sv = torch.clamp(p[:, 1].abs() - b, min=0.0)
        s2 = su * su + sv * sv
        on_rim = s2 > 0
        if rim > 0:
            recess = rim - torch.sqrt(torch.clamp(rim * rim - s2, min=0.0))
            dist = p[:, 2] + torch.where(on_rim, recess, torch.zeros_like(recess))
            return dist, (s2 <= rim * rim) & (dist >= 0)
        return p[:, 2], ~on_rim & (p[:, 2] >= 0)

    bi, ni = index["vertex"]
    dist, keep = pad_distance(uvd(bi, ni))
    vals, owner = [dist[keep]], [bi[keep]]
    if "edge" in index:
        be, ev = index["edge"]
        p0, p1 = uvd(be, ev[:, 0]), uvd(be, ev[:, 1])  # (K, 3)
        # sections of the pad front: the rectangle's sides (exact for the flat face) and planes
        # through the rim, where an edge's crossing point is a sample of its contact with the fillet
        offsets = _section_offsets(rim)
        for k, half in ((0, a), (1, b)):
            for sign in (1.0, -1.0):
                for offset in offsets:
                    bound = sign * (half + offset)
                    crosses = (p0[:, k] - bound) * (p1[:, k] - bound) < 0
                    den = torch.where(crosses, p1[:, k] - p0[:, k], torch.ones_like(p0[:, k]))
                    lam = (bound - p0[:, k]) / den
                    dist, keep = pad_distance(p0 + lam[:, None] * (p1 - p0))
                    keep &= crosses
                    vals.append(dist[keep])
                    owner.append(be[keep])
    if "face" in index:
        bf, fv = index["face"]
        p = uvd(bf[:, None], fv)  # (K, 3 vertices, 3)
        du1, dv1 = p[:, 1, 0] - p[:, 0, 0], p[:, 1, 1] - p[:, 0, 1]
        du2, dv2 = p[:, 2, 0] - p[:, 0, 0], p[:, 2, 1] - p[:, 0, 1]
        det = du1 * dv2 - du2 * dv1
        ok = det.abs() > 1e-18
        det = torch.where(ok, det, torch.ones_like(det))
        for uc in (-a, a):
            for vc in (-b, b):
                l1 = ((uc - p[:, 0, 0]) * dv2 - du2 * (vc - p[:, 0, 1])) / det
                l2 = (du1 * (vc - p[:, 0, 1]) - (uc - p[:, 0, 0]) * dv1) / det
                l0 = 1 - l1 - l2
                dd = l0 * p[:, 0, 2] + l1 * p[:, 1, 2] + l2 * p[:, 2, 2]
                keep = ok & (l0 >= 0) & (l1 >= 0) & (l2 >= 0) & (dd >= 0)
                vals.append(dd[keep])
                owner.append(bf[keep])
    return torch.cat(vals), torch.cat(owner)


def _reduce_min(vals: torch.Tensor, owner: torch.Tensor, n: int, limit: float, temperature: float | None):
    """Per-batch ``min(limit, min vals)`` (exact) or ``-tau log(exp(-limit/tau) + sum exp(-vals/tau))``."""
    base = torch.full((n,), limit, dtype=vals.dtype, device=vals.device)
    if temperature is None:
        return base.scatter_reduce(0, owner, vals, reduce="amin", include_self=True).clamp(max=limit)
    z = -vals / temperature
    with torch.no_grad():
        zmax = torch.full((n,), -limit / temperature, dtype=vals.dtype, device=vals.device)
        zmax = zmax.scatter_reduce(0, owner, z, reduce="amax", include_self=True)
    total = torch.exp(-limit / temperature - zmax).index_add(0, owner, torch.exp(z - zmax[owner]))
    return -temperature * (torch.log(total) + zmax)


class SurfaceClosingDistances:
    r""":func:`finger_closing_distances` of one object surface, prepared once for many batches of poses.

    Everything that does not depend on the pose is set up at construction: the surface vertices (N), its
    unique edges (E) and triangles (F) on the device, the longest edge, the S = 2 (1 + 5) section planes
    per in-plane axis of the pad front (the rectangle's sides ``u = +-a``, ``v = +-b`` and the planes
    through the rim) and the four corner lines ``(+-a, +-b)``. ``|u|`` and ``v`` are the same for both
    fingers and the planes and corners are symmetric in ``u``, so crossing points, rim recesses and
    barycentric coordinates are computed once in the gripper frame for both fingers; only the distance
    ``d = q_max -+ y_g`` in front of each open face differs. Candidates and reduction are those of
    :func:`finger_closing_distances`, with the same floating-point operations: the exact minimum agrees
    with it to rounding (bitwise on CPU), tied minima share the gradient in the same way (evenly, the
    limit ``q_max`` included), and the soft-min differs only in the order of its sum.

    Two strategies:

    - ``dense=True`` (default on accelerators): every candidate of every (pose, element) pair, masked
      with ``+inf`` where it is none, then one min (or soft-min) per finger and pose over vertices
      (2, G, N), edge crossings (2, G, E, 2 axes, S) and corner-line piercings (2, G, F, 4). Static
      shapes, no host synchronization, a few dozen kernels. The cost is O(G (N + S E + F)) wherever
      the pads are (on CPU several times that of the host-selected strategy); the autograd graph holds
      ~30 tensors of up to 4 S E G elements (~1 GB for 100 grasps of a 2000-edge surface in float32):
      bound G with the planner's ``batch_size``.
    - ``dense=False`` (default on CPU): the elements near the pads are selected on the host, as in
      :func:`finger_closing_distances`, and only their candidates are computed (sizes depend on the data).

    Args:
        points: (N, 3) surface vertices in the object frame [m] (numpy or torch; not differentiated).
        faces: optional (F, 3) triangles (the exact polyhedral contact, as in the reference).
        gripper: the gripper (contact rectangle, rim, ``q_max``).
        device, dtype: where and in which precision poses are evaluated (default: those of ``points`` if
            a tensor, else CPU float64).
        dense: the strategy (None: dense unless the device is the CPU).
    """

    def __init__(
        self,
        points,
        faces=None,
        gripper: ParallelJawGripper = FRANKA_HAND,
        device: str | torch.device | None = None,
        dtype: torch.dtype | None = None,
        dense: bool | None = None,
    ):
        if dtype is None:
            dtype = points.dtype if torch.is_tensor(points) and points.is_floating_point() else torch.float64
        if device is None:
            device = points.device if torch.is_tensor(points) else "cpu"
        X = torch.as_tensor(points, dtype=dtype, device=device).detach()
        if X.ndim != 2 or X.shape[1] != 3:
            raise ValueError(f"points must have shape (N, 3), got {tuple(X.shape)}")
        if not bool(torch.isfinite(X).all()):
            raise ValueError("points contain non-finite values")
        self.points, self.device, self.dtype, self.gripper = X, X.device, dtype, gripper
        self.dense = self.device.type != "cpu" if dense is None else bool(dense)
        self.edges = self.faces = None
        a, b = (float(v) for v in gripper.contact_half_extents)
        self.a, self.b = a, b
        self.q = float(gripper.max_finger_opening)
        self.rim = float(gripper.pad_edge_radius)
        self._near = a + self.rim, b + self.rim  # |x_g|, |z_g| of vertices in front of the pad
        if faces is not None:
            Fn = np.asarray(faces.cpu() if torch.is_tensor(faces) else faces, dtype=np.int64)
            if Fn.ndim != 2 or Fn.shape[1] != 3 or Fn.min() < 0 or Fn.max() >= len(X):
                raise ValueError(f"faces must be (F, 3) indices into the {len(X)} points")
            En = _surface_edges(Fn)
            Xn = X.cpu().numpy()
            # host-side selection (dense=False): an edge or triangle that crosses the prism boundary of
            # the pad front has all its vertices within the longest edge of it
            self._max_edge = float(np.linalg.norm(Xn[En[:, 0]] - Xn[En[:, 1]], axis=1).max()) * (1 + 1e-9)
            self._edges_np, self._faces_np = En, Fn
            self.edges = torch.as_tensor(En, device=self.device)
            self.faces = torch.as_tensor(Fn, device=self.device)

        def const(values):
            return torch.tensor(values, dtype=dtype, device=self.device)

        offsets = _section_offsets(self.rim)
        # section planes of the u (gripper x) and v (gripper z) axes: bounds (2, S), half extents (2, 1)
        self.bounds = const([[s * (h + o) for s in (1.0, -1.0) for o in offsets] for h in (a, b)])
        self.sections = self.bounds.shape[1]
        self.half_along, self.half_other = const([[a], [b]]), const([[b], [a]])
        self.corner_u, self.corner_v = const([-a, -a, a, a]), const([-b, b, -b, b])
        # d = y_g * sign + q_max: left finger (u = -x_g) sign -1, right finger (u = x_g) sign +1
        self.finger_sign = const([-_SIGNS[LEFT], -_SIGNS[RIGHT]])

    # ------------------------------------------------------------------ candidates (any leading shape)
    def _rim(self, su, sv):
        """Recess of the pad surface at in-plane distances (su, sv) outside the rectangle (0 on it; None
        without a rim), and whether the pad front covers the point (``s^2 <= r^2``)."""
        s2 = su * su + sv * sv
        r = self.rim
        if r > 0:
            recess = r - torch.sqrt(torch.clamp(r * r - s2, min=0.0))
            return torch.where(s2 > 0, recess, 0.0), s2 <= r * r
        return None, s2 <= 0

    @staticmethod
    def _front(dist, rec, covered):
        """Travel ``dist + rec`` of the pad until it reaches covered points in front of it, else +inf."""
        dist = dist if rec is None else dist + rec
        return torch.where(covered & (dist >= 0), dist, torch.inf)

    def _vertex_candidates(self, x, z, d):
        """Vertices (...) in front of the flat face or the rim: (2 fingers, ...); d (2, ...)."""
        rec, covered = self._rim(
            torch.clamp(x.abs() - self.a, min=0.0), torch.clamp(z.abs() - self.b, min=0.0)
        )
        return self._front(d, rec, covered)

    def _edge_candidates(self, a0, a1, o0, o1, d0, d1):
        """Crossings of edges with the section planes: (2 fingers, ..., 2 axes, S).

        a0, a1: (..., 2) endpoint coordinates along each axis (x_g for the u-planes, z_g for the v-planes);
        o0, o1: (..., 2) the other in-plane coordinate; d0, d1: (2 fingers, ...) distances."""
        n0 = self.bounds - a0[..., None]  # (..., 2, S)
        crosses = n0 * (self.bounds - a1[..., None]) < 0
        lam = n0 / torch.where(crosses, (a1 - a0)[..., None], 1.0)
        ac = a0[..., None] + lam * (a1 - a0)[..., None]
        oc = o0[..., None] + lam * (o1 - o0)[..., None]
        rec, covered = self._rim(
            torch.clamp(ac.abs() - self.half_along, min=0.0), torch.clamp(oc.abs() - self.half_other, min=0.0)
        )
        dc = d0[..., None, None] + lam * (d1 - d0)[..., None, None]
        return self._front(dc, rec, crosses & covered)

    def _face_candidates(self, xf, zf, df):
        """Points where the corner lines pierce triangles: (2 fingers, ..., 4 corners); xf, zf (..., 3),
        df (2, ..., 3). Barycentric coordinates in the (x_g, z_g) plane."""
        du1, dv1 = xf[..., 1] - xf[..., 0], zf[..., 1] - zf[..., 0]
        du2, dv2 = xf[..., 2] - xf[..., 0], zf[..., 2] - zf[..., 0]
        det = du1 * dv2 - du2 * dv1
        ok = det.abs() > 1e-18
        det = torch.where(ok, det, 1.0)[..., None]
        ru, rv = self.corner_u - xf[..., :1], self.corner_v - zf[..., :1]  # (..., 4)
        l1 = (ru * dv2[..., None] - du2[..., None] * rv) / det
        l2 = (du1[..., None] * rv - ru * dv1[..., None]) / det
        l0 = 1 - l1 - l2
        dd = l0 * df[..., :1] + l1 * df[..., 1:2] + l2 * df[..., 2:]
        inside = ok[..., None] & (l0 >= 0) & (l1 >= 0) & (l2 >= 0)
        return self._front(dd, None, inside)

    def _dense(self, x, z, d) -> list[torch.Tensor]:
        """(2, G, C_k) candidates of every element: x, z (G, N), d (2, G, N)."""
        G = x.shape[0]
        parts = [self._vertex_candidates(x, z, d)]
        if self.edges is not None:
            along, other = torch.stack([x, z], dim=-1), torch.stack([z, x], dim=-1)  # (G, N, 2)
            e0, e1 = self.edges[:, 0], self.edges[:, 1]
            parts.append(
                self._edge_candidates(
                    along.index_select(1, e0),
                    along.index_select(1, e1),
                    other.index_select(1, e0),
                    other.index_select(1, e1),
                    d.index_select(2, e0),
                    d.index_select(2, e1),
                ).reshape(2, G, -1)
            )
            f = self.faces.reshape(-1)
            F = len(self.faces)
            parts.append(
                self._face_candidates(
                    x.index_select(1, f).reshape(G, F, 3),
                    z.index_select(1, f).reshape(G, F, 3),
                    d.index_select(2, f).reshape(2, G, F, 3),
                ).reshape(2, G, -1)
            )
        return parts

    def _sparse(self, x, z, d) -> tuple[torch.Tensor, torch.Tensor]:
        """(2, K) candidates of the elements near the pads and their poses (K,), selected on the host."""
        ax, az = x.detach().abs().cpu().numpy(), z.detach().abs().cpu().numpy()
        (ua, va), dev = self._near, self.device

        def idx(*arrays):
            return tuple(torch.as_tensor(v, device=dev) for v in arrays)

        bv, nv = idx(*np.nonzero((ax <= ua) & (az <= va)))
        vals, owner = [self._vertex_candidates(x[bv, nv], z[bv, nv], d[:, bv, nv])], [bv]
        if self.edges is not None:
            m = self._max_edge
            near = (ax <= ua + m) & (az <= va + m)
            En, Fn = self._edges_np, self._faces_np
            be, ee = np.nonzero(near[:, En[:, 0]] & near[:, En[:, 1]])
            bf, ff = np.nonzero(near[:, Fn[:, 0]] & near[:, Fn[:, 1]] & near[:, Fn[:, 2]])
            be, i0, i1 = idx(be, En[ee, 0], En[ee, 1])
            along, other = torch.stack([x, z], dim=-1), torch.stack([z, x], dim=-1)
            ce = self._edge_candidates(
                along[be, i0], along[be, i1], other[be, i0], other[be, i1], d[:, be, i0], d[:, be, i1]
            )
            vals.append(ce.reshape(2, -1))
            owner.append(be.repeat_interleave(2 * self.sections))
            bf, fv = idx(bf, Fn[ff])
            cf = self._face_candidates(x[bf[:, None], fv], z[bf[:, None], fv], d[:, bf[:, None], fv])
            vals.append(cf.reshape(2, -1))
            owner.append(bf.repeat_interleave(4))
        return torch.cat(vals, dim=1), torch.cat(owner)

    # ------------------------------------------------------------------ closing distances
    def __call__(self, poses, temperature: float | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Closing distances (..., 2) [m] and contact flags (..., 2) of poses (..., 4, 4) (differentiable;
        the poses are moved to this device and dtype). See :func:`finger_closing_distances`."""
        T = torch.as_tensor(poses, dtype=self.dtype, device=self.device)
        if T.shape[-2:] != (4, 4):
            raise ValueError(f"poses must have shape (..., 4, 4), got {tuple(T.shape)}")
        if temperature is not None and not temperature > 0:
            raise ValueError(f"temperature must be positive (metres) or None, got {temperature}")
        batch_shape = T.shape[:-2]
        T = T.reshape(-1, 4, 4)
        G, q = T.shape[0], self.q
        R, t = T[:, :3, :3], T[:, :3, 3]
        xg = torch.einsum("bki,bnk->bni", R, self.points[None] - t[:, None, :])  # (G, N, 3) = (X - t) R
        x, y, z = xg.unbind(-1)
        d = y * self.finger_sign[:, None, None] + q  # (2, G, N) distance in front of the open faces
        if self.dense:
            parts = self._dense(x, z, d)
            if temperature is None:  # q_max joins the minimum as the initial value (ties share gradients)
                parts.append(torch.full_like(d[..., :1], q))
            vals = torch.cat(parts, dim=-1)  # (2, G, C)
            with torch.no_grad():
                n = vals.shape[-1] - (temperature is None)
                touches = vals[..., :n].amin(dim=-1) <= q
            if temperature is None:
                closing = vals.amin(dim=-1).clamp(max=q)
            else:
                z = -vals / temperature
                with torch.no_grad():
                    zmax = z.amax(dim=-1).clamp(min=-q / temperature)
                total = torch.exp(-q / temperature - zmax) + torch.exp(z - zmax[..., None]).sum(dim=-1)
                closing = -temperature * (torch.log(total) + zmax)
        else:
            vals, owner = self._sparse(x, z, d)  # (2, K), (K,)
            own = owner.expand(2, -1)
            with torch.no_grad():
                none = torch.full((2, G), torch.inf, dtype=vals.dtype, device=vals.device)
                touches = none.scatter_reduce(1, own, vals, reduce="amin") <= q
            if temperature is None:
                base = torch.full((2, G), q, dtype=vals.dtype, device=vals.device)
                closing = base.scatter_reduce(1, own, vals, reduce="amin", include_self=True).clamp(max=q)
            else:
                z = -vals / temperature
                with torch.no_grad():
                    zmax = torch.full((2, G), -q / temperature, dtype=vals.dtype, device=vals.device)
                    zmax = zmax.scatter_reduce(1, own, z, reduce="amax", include_self=True)
                total = torch.exp(-q / temperature - zmax).index_add(1, owner, torch.exp(z - zmax[:, owner]))
                closing = -temperature * (torch.log(total) + zmax)
        closing, touches = closing.T, touches.T  # (G, 2)
        return closing.reshape(*batch_shape, 2), touches.reshape(*batch_shape, 2)
