r"""Inference API of DefGraspNets: a trained checkpoint -> stress and displacement fields of many grasps.

    predictor = DefGraspNetsPredictor.from_checkpoint("checkpoints/defgraspnets.ckpt", device="cuda")
    out = predictor.predict(tet_mesh, force=15.0, youngs_modulus=2e5, fingers=finger_geometry,
                            gripper_pose=poses, closing_distance=dists)        # G grasps of one object
    out.stress        # (G, N) von Mises stress [Pa] at the object's vertices
    out.displacement  # (G, N, 3) displacement [m]

Fingers can be given three ways (all in the object frame):

1. ``finger_vertices`` (G, 2, V, 3) at first contact, with ``finger_faces`` (T, 3) and ``closing_direction``
   (G, 2, 3);
2. ``finger_pose`` (G, 2, 4, 4) at first contact with a :class:`FingerGeometry`;
3. ``gripper_pose`` (G, 4, 4) of the fully open gripper and ``closing_distance`` (G, 2) [m] (joint states
   ``p_g`` of thesis §7.5) with a :class:`FingerGeometry`: finger ``f`` sits at
   ``T_f = T_gripper T_open,f`` and closes by ``p_f`` along ``c_f = R_f a`` (``a`` the closing axis in the
   finger frame): ``t_f <- t_f + p_f c_f``.

Speed (one H100, L = 15, latent 128; 100 grasps of a 1000-vertex object with two 225-vertex finger pads,
1.4 M mesh edges, random weights): graph construction 3.4 ms (``contact_backend="torch"``); forward 186 ms
in fp32, 76 ms with ``compile=True``, 49 ms with ``precision="bf16", compile=True`` (53 ms end to end;
stress within ~2.5 % of fp32). A 4096-vertex object: 669 ms fp32, 258 ms fp32 compiled. Forward + backward
of 10 grasps (fp32, eager): 72 ms. The cost is the memory traffic of the per-edge MLPs; the fused Triton
message passing (``fused_message_passing``) keeps each edge tile on chip: 100 grasps of a 1573-vertex box,
bf16, network 42 ms fused (47 ms before the kernels read the node terms in place) against 101 ms
compiled, and its backward kernels make the refinement's backward 142 ms against 460 ms (README, planning
benchmark).

All tensor inputs may require grad: :meth:`DefGraspNetsPredictor.predict` with ``grad=True`` keeps the
graph so that an objective ``Q(out)`` can be back-propagated to finger vertices, gripper poses or closing
distances (contact-edge selection is discrete; features and the network are differentiable).
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from defgraspnets.models.fused_message_passing import fused_message_passing_available
from defgraspnets.models.graph import (
    FingerTemplate,
    GraspGraph,
    ObjectTemplate,
    build_grasp_batch,
    contact_pairs,
)
from defgraspnets.models.meshgraphnet import DefGraspNet

__all__ = ["DefGraspNetsPredictor", "FingerGeometry", "GraspFieldPrediction", "finger_contact_poses"]


@dataclass(frozen=True)
class FingerGeometry:
    """The parallel-jaw finger pads.

    Attributes:
        vertices: (V, 3) finger-pad vertices in the finger frame [m]. faces: (T, 3).
        closing_axis: (3,) unit closing axis in the finger frame.
        open_pose: (2, 4, 4) pose of each finger frame in the gripper frame with the gripper fully open
            (needed only for gripper-pose input).
    """

    vertices: np.ndarray
    faces: np.ndarray
    closing_axis: np.ndarray
    open_pose: np.ndarray | None = None


_PER_GRASP = ("finger_vertices", "closing_direction", "finger_pose", "gripper_pose", "closing_distance")


def _t(x, device, dtype) -> Tensor:
    return (
        x.to(device=device, dtype=dtype)
        if isinstance(x, Tensor)
        else torch.as_tensor(np.asarray(x), device=device, dtype=dtype)
    )


def finger_contact_poses(
    gripper_pose: Tensor, open_pose: Tensor, closing_axis: Tensor, closing_distance: Tensor
):
    """Finger poses at first contact and closing directions (differentiable).

    Args:
        gripper_pose: (G, 4, 4) open-gripper poses in the object frame. open_pose: (2, 4, 4) finger frames in
            the gripper frame. closing_axis: (3,) in the finger frame. closing_distance: (G, 2) [m].

    Returns:
        pose (G, 2, 4, 4) and closing direction (G, 2, 3) in the object frame.
    """
    pose = gripper_pose.unsqueeze(1) @ open_pose.unsqueeze(0)  # (G, 2, 4, 4)
    direction = pose[..., :3, :3] @ closing_axis
    direction = direction / direction.norm(dim=-1, keepdim=True)
    translation = pose[..., :3, 3] + closing_distance.unsqueeze(-1) * direction
    top = torch.cat([pose[..., :3, :3], translation.unsqueeze(-1)], dim=-1)
    return torch.cat([top, pose[..., 3:, :]], dim=-2), direction


@dataclass
class GraspFieldPrediction:
    """Predicted fields of G grasps on one object with N vertices.

    Attributes:
        stress: (G, N) von Mises stress [Pa]. displacement: (G, N, 3) [m]. contact_edges: (G,) number of
        (undirected) contact pairs of each grasp (0 means the fingers do not touch the object within eps).
    """

    stress: Tensor
    displacement: Tensor
    contact_edges: Tensor

    @property
    def deformation(self) -> Tensor:
        """(G, N) ``|d|`` [m]."""
        return self.displacement.norm(dim=-1)

    @property
    def mean_stress(self) -> Tensor:
        return self.stress.mean(dim=-1)

    @property
    def mean_deformation(self) -> Tensor:
        return self.deformation.mean(dim=-1)


class DefGraspNetsPredictor:
    """Batched, device-agnostic DefGraspNets inference for grasps of one object.

    Args:
        net: a trained (normalized) :class:`DefGraspNet`; the predictor moves (and may cast) it.
        contact_radius: eps [m] used in training.
        device: ``"cpu"``, ``"cuda"``, ... contact_backend: see ``contact_pairs``.
        precision: ``"fp32"``; ``"bf16"`` runs the encode-process-decode networks in bfloat16 (graph
            features, normalization and outputs stay fp32; for fast GPU scoring); ``"fp64"`` everything.
        compile: ``torch.compile`` the networks (the first calls compile): ``True``, or a dict of
            ``torch.compile`` options (``backend``, ``mode``, ``dynamic``, ...). Without ``dynamic`` given:
            ``dynamic=True`` (symbolic shapes), or with ``static_shapes`` the default automatic dynamic
            (specialized kernels while the shapes stay put).
        activation_checkpointing: recompute each message-passing block's activations in the backward pass
            instead of storing them (forward + backward of many grasps at once, e.g. batched refinement).
        static_shapes: pad the contact edges of a batch of G grasps to a capacity that only grows (to a power
            of two with 25 % headroom, remembered per G), so that the network sees the same shapes at every
            call with the same number of grasps (no recompilation under ``torch.compile``); exact (padding
            edges carry zero messages). Default: on with ``compile``.
        share_object: encode the object part of the multigraph once per batch and broadcast it to every
            grasp (:meth:`DefGraspNet.forward_shared`; exact up to rounding) when the network allows it and
            all grasps share one Young's modulus.
        fused_message_passing: evaluate the message-passing blocks with the fused Triton kernels
            (:mod:`~defgraspnets.models.fused_message_passing`; same function up to rounding), forward and
            backward (gradients with respect to the inputs, e.g. the grasp pose: the predictor's weights are
            frozen). ``None`` (default): on where the kernels run (Triton, CUDA, ``precision="bf16"``).
            ``True`` where they cannot run is an error.
        displacement_target: what the predicted displacement is, ``"total"`` or ``"rigid_removed"``
            (:meth:`from_checkpoint` takes it from the checkpoint; see
            :attr:`~defgraspnets.models.defgraspnets_module.DefGraspNetsModule.displacement_target`).

    ``timer``: an optional callable ``timer(stage)`` returning a context manager (e.g.
    :class:`defgraspnets.planning.timing.StageTimer`) wrapped around the stages ``fingers``, ``graph``,
    ``features`` (shared-object path) and ``network`` of each prediction.
    """

    def __init__(
        self,
        net: DefGraspNet,
        contact_radius: float,
        device: str | torch.device = "cpu",
        contact_backend: str = "auto",
        precision: str = "fp32",
        compile: bool | dict = False,
        activation_checkpointing: bool = False,
        static_shapes: bool | None = None,
        share_object: bool = True,
        fused_message_passing: bool | None = None,
        displacement_target: str = "total",
    ):
        if not net.normalized:
            raise ValueError("the network has no normalization statistics (not trained)")
        if precision not in ("fp32", "bf16", "fp64"):
            raise ValueError(f"precision must be 'fp32', 'bf16' or 'fp64', got {precision!r}")
        self.device = torch.device(device)
        # inference only: frozen weights (gradients flow to the inputs, e.g. grasp poses, never the weights)
        self.net = net.to(self.device).eval().requires_grad_(False)
        if precision == "fp64":
            self.net.double()
        elif precision == "bf16":
            self.net.networks.to(torch.bfloat16)
        available = fused_message_passing_available(self.device, self.net.network_dtype)
        auto = available and self.device.type == "cuda"  # never Triton's (slow) CPU interpreter by default
        if fused_message_passing and not available:
            raise ValueError(
                "fused_message_passing needs Triton, a CUDA device and precision 'bf16', got "
                f"{self.device} and {precision!r}"
            )
        self.fused_message_passing = auto if fused_message_passing is None else bool(fused_message_passing)
        for network in self.net.networks:
            network.activation_checkpointing = bool(activation_checkpointing)
            network.fused_message_passing = self.fused_message_passing
        self.static_shapes = bool(compile) if static_shapes is None else bool(static_shapes)
        self.share_object = bool(share_object)
        self.compiled = bool(compile)
        if compile:
            options = dict(compile) if isinstance(compile, dict) else {}
            if "dynamic" not in options:
                options["dynamic"] = None if self.static_shapes else True
            for network in self.net.networks:
                network.compile(**options)
        self.contact_radius = float(contact_radius)
        self.contact_backend = contact_backend
        self.displacement_target = displacement_target
        self.timer = None
        self._objects: dict[int, tuple[object, ObjectTemplate]] = {}
        self._on_device: dict[int, tuple[object, object]] = {}
        self._fingers: dict[int, tuple[FingerGeometry, FingerTemplate]] = {}
        self._finger_frames: dict[int, tuple[FingerGeometry, Tensor, Tensor | None]] = {}
        self._capacity: dict[int, int] = {}
        # object features and encoder latents of the shared-object path, per (template, modulus): constants
        # of the frozen network, kept across batches (a planner scores and refines one object many times)
        self._object_encodings: dict[tuple[int, float], tuple[ObjectTemplate, tuple]] = {}

    @classmethod
    def from_checkpoint(
        cls, path: str | Path, device: str | torch.device = "cpu", **kwargs
    ) -> DefGraspNetsPredictor:
        """Load a :class:`~defgraspnets.models.defgraspnets_module.DefGraspNetsModule` checkpoint."""
        from defgraspnets.models.checkpoints import read_checkpoint
        from defgraspnets.models.defgraspnets_module import DefGraspNetsModule

        path = Path(path)
        read_checkpoint(path, "DefGraspNetsModule")  # names a missing, unreadable or wrong-model file
        module = DefGraspNetsModule.load_from_checkpoint(path, map_location="cpu")
        kwargs.setdefault("displacement_target", module.displacement_target)
        return cls(module.net, module.contact_radius_m, device, **kwargs)

    @property
    def dtype(self) -> torch.dtype:
        """Dtype of positions, features and outputs (that of the normalization statistics)."""
        return self.net.node_norm.mean.dtype

    def _stage(self, name: str):
        return contextlib.nullcontext() if self.timer is None else self.timer(name)

    def object_template(self, obj) -> ObjectTemplate:
        """Template of a TetMesh, a ``(points, tets)`` pair or an :class:`ObjectTemplate` (cached)."""
        if isinstance(obj, ObjectTemplate):
            return obj
        key = id(obj)
        if key not in self._objects or self._objects[key][0] is not obj:
            if hasattr(obj, "tets") and hasattr(obj, "points"):
                t = ObjectTemplate.from_tet_mesh(obj)
            else:
                points, tets = obj
                t = ObjectTemplate.from_mesh(points, tets)
            self._objects[key] = (obj, t)
        return self._objects[key][1]

    def _device_template(self, t: ObjectTemplate) -> ObjectTemplate:
        """``t`` with its tensors on the predictor's device and dtype (cached: no copies per call)."""
        key = id(t)
        if key not in self._on_device or self._on_device[key][0] is not t:
            moved = ObjectTemplate(
                t.points.to(self.device, self.dtype),
                t.node_type.to(self.device),
                t.mesh_edge_index.to(self.device),
            )
            self._on_device[key] = (t, moved)
        return self._on_device[key][1]

    def _finger_template(self, fingers: FingerGeometry) -> FingerTemplate:
        """Finger template of ``fingers`` on the device (cached: the pad's edges are found once)."""
        key = id(fingers)
        if key not in self._fingers or self._fingers[key][0] is not fingers:
            t = FingerTemplate.from_mesh(fingers.vertices, fingers.faces, dtype=self.dtype)
            t = FingerTemplate(t.vertices.to(self.device), t.mesh_edge_index.to(self.device))
            self._fingers[key] = (fingers, t)
        return self._fingers[key][1]

    def _finger_axes(self, fingers: FingerGeometry) -> tuple[Tensor, Tensor | None]:
        """Closing axis (3,) and open finger frames (2, 4, 4) of ``fingers`` on the device (cached: no host
        copies, which would synchronize an accelerator, per call)."""
        key = id(fingers)
        if key not in self._finger_frames or self._finger_frames[key][0] is not fingers:
            dev, dt = self.device, self.dtype
            open_pose = None if fingers.open_pose is None else _t(fingers.open_pose, dev, dt)
            self._finger_frames[key] = (fingers, _t(fingers.closing_axis, dev, dt), open_pose)
        return self._finger_frames[key][1:]

    @property
    def contact_capacities(self) -> dict[int, int]:
        """``{batch size: padded contact edge count}`` chosen so far (``static_shapes``)."""
        return dict(self._capacity)

    def contact_capacity(self, grasps: int, directed_edges: int) -> int:
        """Padded contact edge count for a batch of ``grasps`` grasps with ``directed_edges`` contact edges:
        grows (to a power of two with 25 % headroom) only when exceeded, remembered per batch size."""
        cap = self._capacity.get(grasps, 0)
        if directed_edges > cap:
            cap = max(64, 1 << math.ceil(math.log2(1.25 * directed_edges)))
            self._capacity[grasps] = cap
        return cap

    def finger_state(
        self,
        *,
        finger_vertices=None,
        finger_faces=None,
        closing_direction=None,
        fingers: FingerGeometry | None = None,
        finger_pose=None,
        gripper_pose=None,
        closing_distance=None,
    ) -> tuple[Tensor, Tensor, FingerTemplate]:
        """Finger vertices (G, 2, V, 3) at first contact, closing directions (G, 2, 3) and the finger template
        from any of the finger inputs (module docstring)."""
        dev, dt = self.device, self.dtype
        if finger_vertices is not None:
            if finger_faces is None or closing_direction is None:
                raise ValueError("finger_vertices needs finger_faces and closing_direction")
            fv = _t(finger_vertices, dev, dt)
            finger = FingerTemplate.from_mesh(np.zeros((fv.shape[2], 3)), finger_faces, dtype=dt)
            return fv, _t(closing_direction, dev, dt), finger
        if fingers is None:
            raise ValueError(
                "give finger_vertices (+ finger_faces, closing_direction), or fingers= with "
                "finger_pose or gripper_pose + closing_distance"
            )
        finger = self._finger_template(fingers)
        axis, open_pose = self._finger_axes(fingers)
        if finger_pose is not None:
            pose = _t(finger_pose, dev, dt)
            cd = pose[..., :3, :3] @ axis
        elif gripper_pose is not None and closing_distance is not None:
            if fingers.open_pose is None:
                raise ValueError(
                    "gripper_pose input needs FingerGeometry.open_pose (finger frames in gripper frame)"
                )
            pose, cd = finger_contact_poses(
                _t(gripper_pose, dev, dt),
                open_pose,
                axis,
                _t(closing_distance, dev, dt),
            )
        else:
            raise ValueError("fingers= needs finger_pose, or gripper_pose and closing_distance")
        verts = finger.vertices
        fv = (pose[..., None, :3, :3] @ verts.unsqueeze(-1)).squeeze(-1) + pose[..., None, :3, 3]
        return fv, cd, finger

    def build(
        self,
        obj,
        force,
        youngs_modulus,
        *,
        finger_vertices=None,
        finger_faces=None,
        closing_direction=None,
        fingers: FingerGeometry | None = None,
        finger_pose=None,
        gripper_pose=None,
        closing_distance=None,
    ) -> GraspGraph:
        """The batched multigraph of G grasps (see the module docstring for the finger inputs); with
        ``static_shapes`` its contact edges are padded (``contact_mask``)."""
        with self._stage("fingers"):
            fv, cd, finger = self.finger_state(
                finger_vertices=finger_vertices,
                finger_faces=finger_faces,
                closing_direction=closing_direction,
                fingers=fingers,
                finger_pose=finger_pose,
                gripper_pose=gripper_pose,
                closing_distance=closing_distance,
            )
        with self._stage("graph"):
            return self._graph(self.object_template(obj), finger, fv, cd, force, youngs_modulus)

    def _graph(self, template, finger, fv, cd, force, youngs_modulus) -> GraspGraph:
        dev, dt = self.device, self.dtype
        g = fv.shape[0]
        if not isinstance(youngs_modulus, Tensor) and not np.all(np.asarray(youngs_modulus) > 0):
            raise ValueError("youngs_modulus must be positive [Pa]")
        force = _t(force, dev, dt).reshape(-1).expand(g)
        youngs = _t(youngs_modulus, dev, dt).reshape(-1).expand(g)
        if isinstance(youngs_modulus, Tensor) and not torch.all(youngs > 0):
            raise ValueError("youngs_modulus must be positive [Pa]")
        obj = self._device_template(template)
        pairs = contact_pairs(
            obj.points, fv.reshape(g, -1, 3), self.contact_radius, backend=self.contact_backend
        )
        capacity = self.contact_capacity(g, 2 * len(pairs)) if self.static_shapes else None
        return build_grasp_batch(
            obj, finger, fv, cd, force, youngs, self.contact_radius, pairs=pairs, contact_capacity=capacity
        )

    def predict(
        self, obj, force, youngs_modulus, *, grad: bool = False, batch_size: int | None = None, **fingers
    ) -> GraspFieldPrediction:
        """Fields of G grasps of object ``obj`` (TetMesh, ``(points, tets)`` or ObjectTemplate).

        Args:
            force: F_g [N], scalar or (G,). youngs_modulus: E [Pa], scalar or (G,).
            grad: keep the autograd graph (for gradient-based grasp refinement).
            batch_size: grasps per forward pass (default: all at once).
            **fingers: finger inputs of :meth:`build`.
        """
        template = self.object_template(obj)
        # one modulus for all grasps (decided on the host): the object part is encoded once per batch
        shared = (
            self.share_object
            and self.net.shares_object_encoding
            and (
                np.size(youngs_modulus) == 1
                if not isinstance(youngs_modulus, Tensor)
                else youngs_modulus.numel() == 1
            )
        )
        # the object part's encoding is kept per (template, modulus) given on the host
        key = None
        if shared and not isinstance(youngs_modulus, Tensor):
            key = (id(template), float(np.asarray(youngs_modulus, dtype=np.float64).reshape(-1)[0]))
        per_grasp = [v for k, v in fingers.items() if k in _PER_GRASP and v is not None]
        count = len(per_grasp[0]) if per_grasp else 0
        with torch.set_grad_enabled(grad):
            step = batch_size or count
            if step >= count:
                return self._predict_batch(
                    self.build(template, force, youngs_modulus, **fingers), template, shared, key
                )
            parts = []
            for start in range(0, count, step):
                sub = {
                    k: (v[start : start + step] if k in _PER_GRASP and v is not None else v)
                    for k, v in fingers.items()
                }
                f = _t(force, self.device, self.dtype).reshape(-1).expand(count)[start : start + step]
                e = (
                    _t(youngs_modulus, self.device, self.dtype)
                    .reshape(-1)
                    .expand(count)[start : start + step]
                )
                parts.append(self._predict_batch(self.build(template, f, e, **sub), template, shared, key))
            return GraspFieldPrediction(
                *(
                    torch.cat([getattr(p, k) for p in parts])
                    for k in ("stress", "displacement", "contact_edges")
                )
            )

    def _object_encoding(self, g: GraspGraph, template: ObjectTemplate, key) -> tuple:
        """Object features and encoder latents of the shared-object path, kept per ``key`` (the
        (template id, modulus) pair) when given, with the template itself (an id is only unique while its
        object lives)."""
        kept = self._object_encodings.get(key) if key is not None else None
        if kept is not None and kept[0] is template:
            return kept[1]
        with torch.no_grad():
            features = self.net.object_features(g, template.num_nodes, template.mesh_edge_index.shape[1])
            encoding = (features, self.net.object_latents(features))
        if key is not None:
            if len(self._object_encodings) >= 8:  # a few objects and moduli at a time
                self._object_encodings.pop(next(iter(self._object_encodings)))
            self._object_encodings[key] = (template, encoding)
        return encoding

    def _predict_batch(
        self, g: GraspGraph, template: ObjectTemplate, shared: bool, key: tuple[int, float] | None
    ) -> GraspFieldPrediction:
        """``key``: the (template id, modulus) of a kept object encoding of the shared path, or None."""
        n_obj = template.num_nodes
        if shared:
            n_edges = template.mesh_edge_index.shape[1]
            with self._stage("features"):
                object_features, object_latents = self._object_encoding(g, template, key)
                features = self.net.shared_features(g, n_obj, n_edges, object_features)
            with self._stage("network"):
                out = self.net.forward_shared(g, n_obj, n_edges, features, object_latents)
                stress, disp = self.net.to_physical(out, g)
        else:
            with self._stage("network"):
                stress, disp = self.net.fields(g)
        count = g.graph_count
        n = g.num_nodes // count
        dst = g.contact_edge_index[1]
        mask = g.contact_edge_mask
        ones = torch.ones_like(dst) if mask is None else mask.long()
        contacts = (
            torch.zeros(count, dtype=torch.long, device=g.pos.device).index_add_(0, g.batch[dst], ones) // 2
        )
        return GraspFieldPrediction(
            stress.reshape(count, n)[:, :n_obj], disp.reshape(count, n, 3)[:, :n_obj], contacts
        )
