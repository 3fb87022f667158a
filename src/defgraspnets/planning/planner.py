r"""Grasp planning with DefGraspNets (thesis §7.5): batched scoring of sampled grasps and gradient-based
refinement of grasp poses.

A grasp is the pose ``T`` (4, 4) of the *fully open* gripper in the object frame. Everything the network
needs follows from ``T`` differentiably:

1. finger joint states ``c(T)`` (2,): each finger closes from fully open until it first touches the
   object, computed analytically from the object's surface (``grasp.gripper.SurfaceClosingDistances``,
   prepared once per planner: on an accelerator dense tensor math over (grasps x surface elements), with
   static shapes and no host synchronization);
2. finger pads at first contact, ``T_f = T T_open,f`` moved by ``c_f`` along their closing directions,
   and the multigraph with contact edges rebuilt from the pads' positions (``models.predictor``);
3. predicted stress and displacement at grasp force ``F_g``, and the objective ``Q`` (:mod:`.objectives`).

Sampling mode ranks G poses by ``Q`` in batched forward passes. Refinement mode takes gradient steps in the
pose's local coordinates ``xi = (v / l, omega)`` (:mod:`.pose`; ``l`` = ``translation_scale`` makes metres and
radians commensurate), all grasps in one batch:

    d = -grad_xi L / |grad_xi L|,       L = +-Q (minimize / maximize)
    backtracking (Armijo): alpha = alpha_0, alpha_0 / 2, ...  until  L(xi + alpha d) <= L - c alpha |grad L|
    annealing: if no step length passes, the shortest trial is still accepted with probability
               exp(-(L_trial - L) / theta_k),  theta_k = theta_0 |L_0| decay^k  (simulated annealing)

A trial pose is *feasible* only if both fingers reach the object within their travel, the multigraph has
contact edges, Q is finite, and (optionally) the open gripper does not collide with the object (on an
accelerator a dense separating-axis and winding-number test of every collision box against every surface
triangle, on the device). Each grasp returns the best feasible pose it visited, so refinement never returns a
worse grasp than it was given.

The network is deterministic, so a grasp whose pose did not change in a step (rejected, or not movable) would
repeat its gradient and line search exactly in the next one: with ``reuse_rejected`` it skips both, keeps its
last shortest trial for the annealing draw, and the annealing random numbers are drawn for all G grasps every
step, so the result is that of re-evaluating everything, with fewer forward passes.

The gradient is taken w.r.t. the pose coordinates only (``backward(inputs=xi)``: no weight gradients of the
network). With ``pad_trials`` (default: the predictor's ``static_shapes``) the gradient and line-search
batches of the grasps still being refined are padded to the smallest of G, G/2, G/4, ... (``pad_levels``
sizes) that holds them, so that the forward passes see a few fixed shapes (few compilations under
``torch.compile``) and a line-search round of 30 pending grasps out of 100 costs a pass of 50, not of 100.
``timer`` (:mod:`.timing`) times the stages of each evaluation.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from defgraspnets.fem.mesh import TetMesh
from defgraspnets.grasp.gripper import FRANKA_HAND, ParallelJawGripper, SurfaceClosingDistances
from defgraspnets.models.predictor import DefGraspNetsPredictor, FingerGeometry, GraspFieldPrediction

from .objectives import GraspObjective
from .pose import perturb_pose
from .timing import NO_TIMER

__all__ = [
    "GraspEvaluation",
    "GraspPlanner",
    "OpenGripperCollisions",
    "RefinementResult",
    "gripper_finger_geometry",
]

# acceptance codes of a refinement step
REJECTED, ARMIJO, ANNEALED = 0, 1, 2


def gripper_finger_geometry(gripper: ParallelJawGripper = FRANKA_HAND) -> FingerGeometry:
    """The finger pads as the predictor sees them: pad mesh in the finger frame, closing axis +y, finger
    frames of the fully open gripper (same convention as the grasp datasets)."""
    v, f = gripper.pad_mesh
    return FingerGeometry(np.array(v), np.array(f), np.array([0.0, 1.0, 0.0]), gripper.finger_transforms())


class OpenGripperCollisions:
    r"""``ParallelJawGripper.collides`` of the fully open gripper against one object, as dense tensor math on
    a device (float64; no host round trips, shapes fixed by the surface).

    A collision box b overlaps the object at pose g if one of the F surface triangles intersects it
    (separating-axis test, Akenine-Moeller 2001, as ``objects.queries.triangles_overlap_box``: the 3 box
    axes, the triangle normal and the 9 edge cross products; touching counts), or if its centre lies in the
    object's bounding box and inside the object (generalized winding number > 1/2). The NumPy reference
    skips the pairs that cannot meet; here every (pose, box, triangle) is tested: O(G B F) work, a few
    hundred kernels per call; 100 poses of a 1360-triangle surface hold ~50 MB of triangles (+ temporaries).

    Args:
        gripper: its collision boxes (pads, finger links, hand) at full opening are checked.
        points: (N, 3) surface vertices [m]; faces: (F, 3) outward-oriented triangles of the closed surface.
        device: where the poses are checked.
    """

    def __init__(self, gripper: ParallelJawGripper, points, faces, device: str | torch.device = "cpu"):
        boxes = gripper.collision_boxes()
        f64 = torch.float64
        self.device = torch.device(device)
        self.centers = torch.as_tensor(np.stack([b.center for b in boxes]), dtype=f64, device=self.device)
        self.half = torch.as_tensor(np.stack([b.half_extents for b in boxes]), dtype=f64, device=self.device)
        self.points = torch.as_tensor(np.asarray(points), dtype=f64, device=self.device)
        self.faces = torch.as_tensor(np.asarray(faces), dtype=torch.long, device=self.device)
        self.triangles = self.points[self.faces]  # (F, 3, 3) in the object frame

    @staticmethod
    def _sat(tri: Tensor, h: Tensor) -> Tensor:
        """(...,) whether triangles (..., 3, 3) meet the boxes ``|x| <= h`` (..., 3) centred at the origin."""
        v0, v1, v2 = tri.unbind(-2)
        overlap = (torch.minimum(torch.minimum(v0, v1), v2) <= h).all(-1)
        overlap &= (torch.maximum(torch.maximum(v0, v1), v2) >= -h).all(-1)
        e0, e1, e2 = v1 - v0, v2 - v1, v0 - v2
        n = torch.linalg.cross(e0, e1)
        overlap &= (n * v0).sum(-1).abs() <= (n.abs() * h).sum(-1)
        hx, hy, hz = h.unbind(-1)
        vs = [v.unbind(-1) for v in (v0, v1, v2)]
        for e in (e0, e1, e2):
            ex, ey, ez = e.unbind(-1)
            # axis = unit axis k x e: (0, -ez, ey), (ez, 0, -ex), (-ey, ex, 0)
            for (i, ci), (j, cj), r in (
                ((1, -ez), (2, ey), ez.abs() * hy + ey.abs() * hz),
                ((0, ez), (2, -ex), ez.abs() * hx + ex.abs() * hz),
                ((0, -ey), (1, ex), ey.abs() * hx + ex.abs() * hy),
            ):
                p0, p1, p2 = (ci * v[i] + cj * v[j] for v in vs)
                lo = torch.minimum(torch.minimum(p0, p1), p2)
                hi = torch.maximum(torch.maximum(p0, p1), p2)
                overlap &= (lo <= r) & (hi >= -r)
        return overlap

    def _winding(self, p: Tensor) -> Tensor:
        """(...,) generalized winding numbers of points p (..., 3) (object frame)."""
        a, b, c = (self.triangles[:, k] - p[..., None, :] for k in range(3))  # (..., F, 3)
        la, lb, lc = a.norm(dim=-1), b.norm(dim=-1), c.norm(dim=-1)
        num = (a * torch.linalg.cross(b, c)).sum(-1)
        den = la * lb * lc + (a * b).sum(-1) * lc + (b * c).sum(-1) * la + (c * a).sum(-1) * lb
        return torch.atan2(num, den).sum(-1) / (2 * math.pi)

    def collisions(self, poses: Tensor) -> Tensor:
        """(G, B) whether box b of the open gripper at poses (G, 4, 4) overlaps the object."""
        T = poses.detach().to(self.device, torch.float64)
        R, t = T[:, :3, :3], T[:, :3, 3]
        xg = torch.einsum("nk,gkj->gnj", self.points, R) - torch.einsum("gk,gkj->gj", t, R)[:, None]
        lo, hi = xg.amin(dim=1)[:, None], xg.amax(dim=1)[:, None]  # (G, 1, 3) object box, gripper frame
        c, h = self.centers, self.half  # (B, 3)
        near = ((lo <= c + h) & (hi >= c - h)).all(-1)  # (G, B)
        local = xg[:, None, self.faces] - c[None, :, None, None]  # (G, B, F, 3, 3)
        hit = near & self._sat(local, h[None, :, None]).any(-1)
        centred = ((lo <= c) & (hi >= c)).all(-1)
        inside = centred & (self._winding(torch.einsum("gij,bj->gbi", R, c) + t[:, None]) > 0.5)
        return hit | inside

    def __call__(self, poses: Tensor) -> Tensor:
        """(G,) whether any part of the open gripper at poses (G, 4, 4) overlaps the object."""
        return self.collisions(poses).any(-1)


@dataclass
class GraspEvaluation:
    """Q and feasibility of G grasp poses.

    Attributes:
        q: (G,) objective values (units of the objective). loss: (G,) ``+-q`` (what is minimized).
        closing_distance: (G, 2) finger joint states [m]. touches: (G, 2) whether each finger reaches the
        object. contact_edges: (G,) contact pairs in the multigraph. feasible: (G,) all checks passed
        (collision only if checked). prediction: the predicted fields (kept only on request).
    """

    q: Tensor
    loss: Tensor
    closing_distance: Tensor
    touches: Tensor
    contact_edges: Tensor
    feasible: Tensor
    prediction: GraspFieldPrediction | None = None


@dataclass
class RefinementResult:
    """Outcome of :meth:`GraspPlanner.refine` for G grasps over K steps.

    Attributes:
        poses: (G, 4, 4) best feasible pose visited. q: (G,) its objective value. closing_distance: (G, 2)
        its finger joint states (exact minimum, as the simulator needs them). initial_q: (G,) Q of the input
        poses. q_history: (K + 1, G) Q of the current iterate after each step. accepted: (K, G) step codes
        (0 rejected, 1 Armijo step, 2 accepted by annealing). sense: ``"minimize"`` or ``"maximize"``.
        seconds: wall time.
    """

    poses: np.ndarray
    q: np.ndarray
    closing_distance: np.ndarray
    initial_q: np.ndarray
    q_history: np.ndarray
    accepted: np.ndarray
    sense: str
    seconds: float
    translation: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (G,) |t - t_0| [m]
    rotation: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (G,) angle of R_0^T R [rad]


class GraspPlanner:
    """Scores and refines parallel-jaw grasps of one object with a trained DefGraspNets predictor.

    Args:
        predictor: the network (any device / precision).
        mesh: the object's tet mesh in the object frame [m].
        youngs_modulus: E [Pa]. force: grasp force F_g [N] at which Q is evaluated.
        objective: the :class:`GraspObjective`.
        gripper: gripper geometry (finger pads, travel, collision boxes).
        closing_temperature: soft-min temperature [m] of the finger joint states (None: exact minimum,
            piecewise-smooth in T; a small value, e.g. 1e-4, spreads gradients over nearly-touching points).
        batch_size: grasps per forward pass (None: all at once).
        check_collisions: refinement rejects poses where the open gripper overlaps the object.
        pad_trials: pad every forward batch to a fixed size (the refinement batch, or ``batch_size``) with
            copies of its first pose, whose results are dropped (static shapes for ``torch.compile``).
            None: the predictor's ``static_shapes``.
        pad_levels: with ``pad_trials``, the refinement pads the batches of a step's still-pending grasps
            to the smallest of G, G/2, ..., G/2^(pad_levels - 1) that holds them (1: always G).
        dense_geometry: finger joint states and collision checks as dense tensor math on the predictor's
            device (no host round trips; see :class:`SurfaceClosingDistances`), or with the elements near
            the gripper selected on the host (NumPy collision checks), which is faster on a CPU. None: dense
            unless the device is the CPU. Both give the same results (to rounding).
        compile_geometry: ``torch.compile`` the dense finger joint states (inductor fuses their few dozen
            elementwise kernels into a handful; static shapes with ``pad_trials``, else automatic dynamic
            shapes, so that refinement batches of varying size compile once more, not every step). None: on
            when the predictor compiles its networks (with dense geometry).
    """

    def __init__(
        self,
        predictor: DefGraspNetsPredictor,
        mesh: TetMesh,
        youngs_modulus: float,
        objective: GraspObjective,
        force: float = 15.0,
        gripper: ParallelJawGripper = FRANKA_HAND,
        closing_temperature: float | None = None,
        batch_size: int | None = None,
        check_collisions: bool = True,
        pad_trials: bool | None = None,
        pad_levels: int = 3,
        dense_geometry: bool | None = None,
        compile_geometry: bool | None = None,
    ):
        if not isinstance(mesh, TetMesh):
            raise TypeError(f"mesh must be a TetMesh, got {type(mesh).__name__}")
        for key, value in (("youngs_modulus", youngs_modulus), ("force", force)):
            if value is None or isinstance(value, (str, bytes)):
                raise ValueError(f"{key} must be a number, got {value!r} ({type(value).__name__})")
        if not (math.isfinite(youngs_modulus) and youngs_modulus > 0):
            raise ValueError(f"youngs_modulus must be a positive modulus [Pa], got {youngs_modulus!r}")
        if not (math.isfinite(force) and force > 0):
            raise ValueError(f"force must be a positive grasp force [N], got {force!r}")
        if batch_size is not None and batch_size < 1:
            raise ValueError(f"batch_size must be >= 1 or None, got {batch_size}")
        self.predictor = predictor
        self.mesh = mesh
        self.youngs_modulus = float(youngs_modulus)
        self.force = float(force)
        self.objective = objective
        self.gripper = gripper
        self.closing_temperature = closing_temperature
        self.batch_size = batch_size
        self.check_collisions = check_collisions
        if int(pad_levels) != pad_levels or pad_levels < 1:
            raise ValueError(f"pad_levels must be an integer >= 1, got {pad_levels!r}")
        self.pad_trials = predictor.static_shapes if pad_trials is None else bool(pad_trials)
        self.pad_levels = int(pad_levels)
        self.fingers = gripper_finger_geometry(gripper)
        self.template = predictor.object_template(mesh)
        # the object's surface (vertices renumbered) for the finger joint states
        surf = mesh.surface_vertices
        remap = np.full(mesh.num_vertices, -1, dtype=np.int64)
        remap[surf] = np.arange(len(surf))
        self.surface_faces = remap[mesh.surface_faces]
        self.surface_points_np = mesh.points[surf]
        self.surface_points = torch.as_tensor(
            self.surface_points_np, dtype=predictor.dtype, device=predictor.device
        )
        self.dense_geometry = predictor.device.type != "cpu" if dense_geometry is None else dense_geometry
        # pose-independent geometry, prepared once: surface edges, pad sections, collision boxes
        self._closing = SurfaceClosingDistances(
            self.surface_points, self.surface_faces, gripper, dense=self.dense_geometry
        )
        if compile_geometry is None:
            compiled = predictor.compiled and self.dense_geometry
        else:
            compiled = bool(compile_geometry)
        if compiled and not self.dense_geometry:
            raise ValueError("compile_geometry needs dense_geometry (the host-selected strategy syncs)")
        self.compile_geometry = compiled
        # padded batches have a few fixed sizes (static shapes); unpadded ones vary from one refinement
        # step to the next: automatic dynamic shapes then (one recompilation, no more)
        dynamic = False if self.pad_trials else None
        self._closing_fn = (
            torch.compile(self._closing.__call__, dynamic=dynamic) if compiled else self._closing
        )
        self._collisions = (
            OpenGripperCollisions(gripper, self.surface_points_np, self.surface_faces, predictor.device)
            if self.dense_geometry
            else None
        )

    @property
    def device(self) -> torch.device:
        return self.predictor.device

    @property
    def dtype(self) -> torch.dtype:
        return self.predictor.dtype

    @property
    def timer(self):
        """Stage timer shared with the predictor (:mod:`.timing`); None: off."""
        return self.predictor.timer

    @timer.setter
    def timer(self, value) -> None:
        self.predictor.timer = value

    def _stage(self, name: str):
        return (self.predictor.timer or NO_TIMER)(name)

    def _poses(self, poses) -> Tensor:
        T = torch.as_tensor(poses, dtype=self.dtype, device=self.device)
        if T.ndim != 3 or T.shape[1:] != (4, 4):
            raise ValueError(f"poses must have shape (G, 4, 4), got {tuple(T.shape)}")
        if not bool(torch.isfinite(T).all()):
            raise ValueError("poses contain NaN or inf")
        R = T[:, :3, :3].detach()
        eye = torch.eye(3, dtype=T.dtype, device=T.device)
        err = (R.transpose(1, 2) @ R - eye).abs().amax().item() if len(T) else 0.0
        if err > 1e-4:
            raise ValueError(f"poses must hold rotations (|R^T R - I| up to {err:.2g})")
        return T

    # ------------------------------------------------------------------ evaluation
    def closing_distances(self, poses, exact: bool = True) -> tuple[Tensor, Tensor]:
        """Finger joint states (G, 2) [m] and contact flags (G, 2) of poses (G, 4, 4) (differentiable)."""
        T = self._poses(poses) if not torch.is_tensor(poses) else poses
        return self._closing_fn(T, temperature=None if exact else self.closing_temperature)

    def evaluate(
        self, poses, grad: bool = False, keep_prediction: bool = False, pad_to: int | None = None
    ) -> GraspEvaluation:
        """Q of G poses (G, 4, 4) in batches of ``batch_size`` (differentiable with ``grad=True``).

        ``pad_to``: with ``pad_trials``, the size every batch is padded to (default: ``batch_size``, or G).
        """
        T = poses if torch.is_tensor(poses) and poses.requires_grad else self._poses(poses)
        return self._evaluate(T, grad, keep_prediction, pad_to)

    def _evaluate(
        self, T: Tensor, grad: bool = False, keep_prediction: bool = False, pad_to: int | None = None
    ) -> GraspEvaluation:
        parts = []
        step, size = self.batch_size or max(len(T), 1), None
        if self.pad_trials:  # every batch padded to one size: batch_size, else pad_to, else G
            step = size = self.batch_size or pad_to or max(len(T), 1)
        for start in range(0, len(T), step):
            parts.append(self._evaluate_batch(T[start : start + step], grad, keep_prediction, size))
        if len(parts) == 1:
            return parts[0]
        cat = {
            k: torch.cat([getattr(p, k) for p in parts])
            for k in GraspEvaluation.__dataclass_fields__
            if k != "prediction"
        }
        pred = None
        if keep_prediction:
            pred = GraspFieldPrediction(
                *(
                    torch.cat([getattr(p.prediction, k) for p in parts])
                    for k in ("stress", "displacement", "contact_edges")
                )
            )
        return GraspEvaluation(**cat, prediction=pred)

    def _evaluate_batch(
        self, T: Tensor, grad: bool, keep_prediction: bool, pad_to: int | None = None
    ) -> GraspEvaluation:
        k = len(T)
        if pad_to is not None and 0 < k < pad_to:
            T = torch.cat([T, T[:1].detach().expand(pad_to - k, 4, 4)])
        with torch.set_grad_enabled(grad):
            with self._stage("fingers"):
                closing, touches = self.closing_distances(T, exact=False)
            pred = self.predictor.predict(
                self.template,
                self.force,
                self.youngs_modulus,
                grad=grad,
                fingers=self.fingers,
                gripper_pose=T,
                closing_distance=closing,
            )
            with self._stage("objective"):
                if len(T) > k:
                    closing, touches = closing[:k], touches[:k]
                    pred = GraspFieldPrediction(
                        pred.stress[:k], pred.displacement[:k], pred.contact_edges[:k]
                    )
                q = self.objective(pred.stress, pred.displacement)
                loss = self.objective.sign * q
                feasible = touches.all(-1) & (pred.contact_edges > 0) & torch.isfinite(q.detach())
        return GraspEvaluation(
            q, loss, closing, touches, pred.contact_edges, feasible, pred if keep_prediction else None
        )

    def collides(self, poses) -> np.ndarray:
        """(G,) whether the fully open gripper at poses (G, 4, 4) overlaps the object."""
        if self._collisions is not None:
            return self._collisions(torch.as_tensor(poses)).cpu().numpy()
        T = poses.detach().cpu().numpy() if torch.is_tensor(poses) else np.asarray(poses)
        return self.gripper.collides((self.surface_points_np, self.surface_faces), T.astype(np.float64))

    def _collides(self, T: Tensor) -> Tensor:
        """:meth:`collides` as a bool tensor on the device (no host round trip with ``dense_geometry``)."""
        if self._collisions is not None:
            return self._collisions(T)
        return torch.as_tensor(self.collides(T), device=self.device)

    def _padded_size(self, n: int, full: int) -> int:
        """Batch size a padded pass over ``n`` of ``full`` grasps uses: the smallest of full, full / 2, ...
        (``pad_levels`` sizes, halves rounded up) that holds ``n``."""
        size = full
        for _ in range(self.pad_levels - 1):
            half = -(-size // 2)
            if n > half:
                break
            size = half
        return size

    # ------------------------------------------------------------------ sampling mode
    @torch.no_grad()
    def score(self, poses) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Q (G,), feasibility (G,) and the ranking (indices, best first; infeasible grasps last)."""
        ev = self.evaluate(poses)
        q = ev.q.detach().cpu().double().numpy()
        feasible = ev.feasible.cpu().numpy()
        key = np.where(feasible, self.objective.sign * q, np.inf)
        return q, feasible, np.argsort(key, kind="stable")

    # ------------------------------------------------------------------ refinement mode
    def refine(
        self,
        poses,
        steps: int = 12,
        sense: str | None = None,
        step_size: float = 0.2,
        translation_scale: float = 0.01,
        max_backtracks: int = 4,
        armijo: float = 1e-4,
        temperature: float = 0.05,
        temperature_decay: float = 0.7,
        seed: int | None = 0,
        progress: bool = False,
        reuse_rejected: bool = True,
    ) -> RefinementResult:
        """Refine G grasp poses (G, 4, 4) together (see the module docstring).

        Args:
            steps: gradient steps (thesis: 12). sense: override the objective's ``"minimize"``/``"maximize"``.
            step_size: first trial step alpha_0 in local units (translation ``alpha_0 l`` [m], rotation
                ``alpha_0`` [rad]). translation_scale: ``l`` [m].
            max_backtracks: halvings of the step per iteration. armijo: sufficient-decrease constant c.
            temperature, temperature_decay: annealing theta_0 (relative to |L| of the input) and its decay
                per step (0 disables annealing). seed: random stream of the annealing acceptances.
            reuse_rejected: skip the gradient and line search of a grasp whose pose did not change since its
                last rejection; the network is deterministic, so the result is the same, with fewer forward
                passes.
        """
        t0 = time.perf_counter()
        sense = sense or self.objective.sense
        if sense not in ("minimize", "maximize"):
            raise ValueError(f"sense must be 'minimize' or 'maximize', got {sense!r}")
        sign = 1.0 if sense == "minimize" else -1.0
        if steps < 0 or max_backtracks < 0 or not step_size > 0 or not translation_scale > 0:
            raise ValueError("steps and max_backtracks must be >= 0; step_size, translation_scale > 0")
        T = self._poses(poses).detach().clone()
        T_start = T.clone()
        G = len(T)
        scale = torch.tensor([translation_scale] * 3 + [1.0] * 3, dtype=self.dtype, device=self.device)
        gen = torch.Generator(device="cpu").manual_seed(0 if seed is None else int(seed))

        stage, timer = self._stage, self.predictor.timer or NO_TIMER
        with stage("refine.trial"):
            ev = self._evaluate(T)
        timer.count("refine.trial_grasps", G)
        q_now = ev.q.detach().clone()
        loss_now = sign * q_now
        ok_now = ev.feasible.clone()
        if self.check_collisions:
            with stage("refine.collisions"):
                ok_now &= ~self._collides(T)
        best_T, best_loss = T.clone(), torch.where(ok_now, loss_now, torch.full_like(loss_now, math.inf))
        best_q = q_now.clone()
        initial_q = q_now.clone()
        theta0 = temperature * loss_now.abs().nan_to_num(0.0).median().clamp_min(1e-30)
        history = [q_now.clone()]
        accepted = []

        it = range(steps)
        if progress:
            from tqdm.auto import tqdm

            it = tqdm(it, desc=f"refine {G} grasps", unit="step", leave=False)
        # grasps whose pose did not change in the last step (rejected or not movable): their gradient and
        # line search would repeat exactly, so only the annealing draw is redone, on the stored shortest trial
        unchanged = torch.zeros(G, dtype=torch.bool, device=self.device)
        movable = torch.zeros(G, dtype=torch.bool, device=self.device)
        has_trial = torch.zeros(G, dtype=torch.bool, device=self.device)
        trial_T, trial_q = T.clone(), torch.zeros_like(q_now)
        trial_loss, trial_ok = torch.zeros_like(q_now), torch.zeros_like(ok_now)
        for k in it:
            fresh = torch.nonzero(~unchanged).squeeze(1)
            g = torch.zeros(G, 6, dtype=self.dtype, device=self.device)
            if fresh.numel():
                xi = torch.zeros(len(fresh), 6, dtype=self.dtype, device=self.device, requires_grad=True)
                with stage("refine.gradient"):
                    ev = self._evaluate(
                        perturb_pose(T[fresh], xi * scale), grad=True, pad_to=self._padded_size(len(fresh), G)
                    )
                with stage("refine.backward"):
                    # d/dxi only: no weight gradients of the network
                    (sign * ev.q).sum().backward(inputs=[xi])
                g[fresh] = xi.grad.detach()
                del ev
            timer.count("refine.gradient_grasps", len(fresh))
            gnorm = g.norm(dim=1)
            movable = torch.where(unchanged, movable, ok_now & torch.isfinite(gnorm) & (gnorm > 0))
            direction = -g / gnorm.clamp_min(torch.finfo(g.dtype).tiny)[:, None]
            alpha = torch.full((G,), step_size, dtype=self.dtype, device=self.device)
            code = torch.zeros(G, dtype=torch.long, device=self.device)
            pending = movable & ~unchanged
            has_trial &= unchanged  # stored trials of the unchanged grasps; this step's failed trials join
            for _ in range(max_backtracks + 1):
                idx = torch.nonzero(pending).squeeze(1)
                if idx.numel() == 0:
                    break
                with torch.no_grad(), stage("refine.trial"):
                    trial = perturb_pose(T[idx], (alpha[idx, None] * direction[idx]) * scale)
                    tev = self._evaluate(trial, pad_to=self._padded_size(len(idx), G))
                timer.count("refine.trial_grasps", len(idx))
                feasible = tev.feasible.clone()
                if self.check_collisions:
                    with stage("refine.collisions"):
                        feasible &= ~self._collides(trial)
                t_loss = sign * tev.q.detach()
                decrease = t_loss <= loss_now[idx] - armijo * alpha[idx] * gnorm[idx]
                success = feasible & decrease
                win = idx[success]
                T[win], q_now[win], loss_now[win] = trial[success], tev.q.detach()[success], t_loss[success]
                code[win] = ARMIJO
                pending[win] = False
                # each failed trial replaces the grasp's stored one: the shortest remains
                lose, fail = idx[~success], ~success
                trial_T[lose], trial_q[lose] = trial[fail], tev.q.detach()[fail]
                trial_loss[lose], trial_ok[lose], has_trial[lose] = t_loss[fail], feasible[fail], True
                alpha[lose] *= 0.5
            # simulated annealing: the shortest trial of grasps without an Armijo step (this step's or the
            # stored one); random numbers for all G grasps, independent of which grasps were evaluated
            if temperature > 0:
                theta = theta0 * temperature_decay**k
                u = torch.rand(G, generator=gen, dtype=torch.float64).to(self.device, self.dtype)
                rise = (trial_loss - loss_now).clamp_min(0.0)
                take = has_trial & (code == 0) & trial_ok & (u < torch.exp(-rise / theta))
                win = torch.nonzero(take).squeeze(1)
                T[win], q_now[win], loss_now[win] = trial_T[win], trial_q[win], trial_loss[win]
                code[win] = ANNEALED
            if reuse_rejected:
                unchanged = code == 0
            improved = (code > 0) & (loss_now < best_loss)
            best_T[improved], best_loss[improved], best_q[improved] = (
                T[improved],
                loss_now[improved],
                q_now[improved],
            )
            history.append(q_now.clone())
            accepted.append(code.cpu().numpy())

        with torch.no_grad():
            closing, _ = self.closing_distances(best_T, exact=True)
        R0, R1 = T_start[:, :3, :3], best_T[:, :3, :3]
        cos = (((R0.transpose(1, 2) @ R1).diagonal(dim1=1, dim2=2).sum(-1) - 1) / 2).clamp(-1, 1)
        return RefinementResult(
            poses=best_T.cpu().double().numpy(),
            q=best_q.cpu().double().numpy(),
            closing_distance=closing.detach().cpu().double().numpy(),
            initial_q=initial_q.cpu().double().numpy(),
            q_history=torch.stack(history).cpu().double().numpy(),
            accepted=np.array(accepted, dtype=np.int8).reshape(steps, G),
            sense=sense,
            seconds=time.perf_counter() - t0,
            translation=(best_T[:, :3, 3] - T_start[:, :3, 3]).norm(dim=1).cpu().double().numpy(),
            rotation=torch.arccos(cos).cpu().double().numpy(),
        )
