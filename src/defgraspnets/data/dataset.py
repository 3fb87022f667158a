"""Torch dataset of DefGraspNets samples read from grasp shards.

One sample is one ramp step of one solved squeeze: index ``(shard, k, g, s)`` ->
input: object rest mesh, both finger meshes at first contact (grasp ``g``), total grasp force
``F_g = /ramp/force[k, g, s]`` and modulus ``E_k``; targets: per-vertex von Mises stress [Pa] and
displacement [m] at step ``s`` (finger nodes carry their rigid travel ``travel_f c_f``). Only entries with
``/ramp/status == 0`` are ever indexed. With ``ramp_stride`` set (multi-step ablation V2), a sample also
carries the ground-truth state at step ``s - ramp_stride`` (the rest state when negative).

Displacement target (``displacement=``): ``"total"`` is the thesis's deformation field (§7.4: each vertex's
position change, the object's rigid motion in the grasp included); ``"rigid_removed"`` removes the best rigid
motion of the object's vertices (Kabsch with equal vertex weights, as the §6.5 metric) and expresses
every node, finger nodes included, in the object's co-moving frame: ``R^T (x - t) - X``. A stiff object turns
into the pads by up to ~14 deg at 3 N (``benchmarks/defgraspnets_scaling_ab_h100.md``) while deforming by
microns: the first target ranks grasps by that turn, the second by the deformation that can damage it.

Static data (meshes, multigraph topology, contact edges of each grasp) are built once per shard / grasp and
cached; the large fields are read lazily, one HDF5 chunk per sample, so DataLoader workers can stream them.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset

from defgraspnets.data.grasp_schema import STATUS_SOLVED, GraspShard
from defgraspnets.grasp.metrics import best_rigid_transform, undo_rigid_motion
from defgraspnets.models.graph import (
    DEFAULT_CONTACT_RADIUS,
    FingerTemplate,
    GraspGraph,
    ObjectTemplate,
    build_grasp_graph,
    contact_pairs,
)

__all__ = [
    "DISPLACEMENT_TARGETS",
    "DataError",
    "GraspFieldDataset",
    "check_displacement_target",
    "discover_shards",
    "sample_index",
]

DISPLACEMENT_TARGETS = ("total", "rigid_removed")


class DataError(ValueError):
    """Training data that cannot be used (NaN fields of a solved entry, bad step indices, ...)."""


def discover_shards(data_dir: str | Path) -> list[Path]:
    """Finished shards ``*.h5`` in ``data_dir`` (sorted; ``*.partial.h5`` are skipped).

    Raises:
        FileNotFoundError: the directory does not exist or holds no finished shard.
    """
    d = Path(data_dir)
    if not d.is_dir():
        raise FileNotFoundError(f"grasp data directory not found: {d}")
    paths = sorted(p for p in d.glob("*.h5") if not p.name.endswith(".partial.h5"))
    if not paths:
        partial = sorted(d.glob("*.partial.h5"))
        hint = f" ({len(partial)} unfinished .partial.h5 shards: resume their generation)" if partial else ""
        raise FileNotFoundError(f"no finished grasp shards (*.h5) in {d}{hint}")
    return paths


def check_displacement_target(displacement: str, ramp_stride: int | None, prefix: str = "") -> None:
    """Raise ValueError unless ``displacement`` is a known target usable with ``ramp_stride``
    (``prefix``: config path of the keys in the message, e.g. ``"data."``)."""
    if displacement not in DISPLACEMENT_TARGETS:
        raise ValueError(f"{prefix}displacement={displacement!r} is not one of {DISPLACEMENT_TARGETS}")
    if displacement != "total" and ramp_stride is not None:
        raise ValueError(
            f"{prefix}displacement={displacement!r} cannot be combined with {prefix}ramp_stride (multi-step "
            f"training adds world-frame increments); use {prefix}displacement=total"
        )


def resolve_steps(steps: Sequence[int] | None, num_steps: int, where: str = "") -> np.ndarray:
    """Sorted unique steps in ``[0, num_steps)`` (``None``: all; negative indices count from the end)."""
    if steps is None:
        return np.arange(num_steps)
    idx = np.asarray(list(steps), dtype=np.int64)
    bad = (idx >= num_steps) | (idx < -num_steps)
    if bad.any():
        raise DataError(f"{where}step indices {idx[bad].tolist()} outside a ramp of {num_steps} steps")
    return np.unique(np.where(idx < 0, idx + num_steps, idx))


def sample_index(
    shards: Sequence[GraspShard], entries: np.ndarray, steps: Sequence[int] | None = None
) -> np.ndarray:
    """Expand ``(shard, k, g)`` entries (P, 3) to samples ``(shard, k, g, s)`` (Q, 4) over ``steps``.

    Raises:
        DataError: an entry is not solved (status != 0) or a step index is out of range.
    """
    entries = np.asarray(entries, dtype=np.int64).reshape(-1, 3)
    out = []
    for sh in np.unique(entries[:, 0]):
        e = entries[entries[:, 0] == sh]
        shard = shards[sh]
        bad = shard.status[e[:, 1], e[:, 2]] != STATUS_SOLVED
        if bad.any():
            raise DataError(
                f"{shard.path}: entries (k, g) {e[bad][:4, 1:].tolist()} are not solved (status != 0)"
            )
        s = resolve_steps(steps, shard.num_steps, f"{shard.path}: ")
        rep = np.repeat(e, len(s), axis=0)
        out.append(np.concatenate([rep, np.tile(s, len(e))[:, None]], axis=1))
    return np.concatenate(out) if out else np.zeros((0, 4), dtype=np.int64)


class GraspFieldDataset(Dataset):
    """Samples ``(shard, k, g, s)`` of grasp shards as :class:`~defgraspnets.models.graph.GraspGraph`.

    Args:
        shards: opened shards. samples: (Q, 4) int ``(shard, k, g, s)``.
        object_ids: object index of each shard (default: shard index) stored as ``object_id``.
        contact_radius: eps [m] of the contact edges. contact_backend: see ``contact_pairs``.
        ramp_stride: if set, also provide the state at step ``s - ramp_stride`` (multi-step training).
        displacement: ``"total"`` or ``"rigid_removed"`` target (module docstring); multi-step training
            (``ramp_stride``) needs ``"total"`` (its increments add up in one frame).

    Each item has ``pos, node_type, finger_id, closing_dir, mesh_edge_index, contact_edge_index, force,
    youngs_modulus, stress, displacement, sample, object_id`` (+ ``prev_displacement, prev_force``).
    """

    def __init__(
        self,
        shards: Sequence[GraspShard],
        samples: np.ndarray,
        object_ids: Sequence[int] | None = None,
        contact_radius: float = DEFAULT_CONTACT_RADIUS,
        contact_backend: str = "kdtree",
        ramp_stride: int | None = None,
        displacement: str = "total",
    ):
        check_displacement_target(displacement, ramp_stride)
        self.displacement = displacement
        self.shards = list(shards)
        self.samples = np.asarray(samples, dtype=np.int64).reshape(-1, 4)
        self.object_ids = list(range(len(self.shards))) if object_ids is None else list(object_ids)
        if len(self.object_ids) != len(self.shards):
            raise ValueError("object_ids must have one entry per shard")
        if contact_radius <= 0:
            raise ValueError(f"contact_radius must be positive [m], got {contact_radius}")
        if ramp_stride is not None and ramp_stride < 1:
            raise ValueError(f"ramp_stride must be >= 1 or None, got {ramp_stride}")
        self.contact_radius = float(contact_radius)
        self.contact_backend = contact_backend
        self.ramp_stride = ramp_stride
        self._templates: dict[int, tuple[ObjectTemplate, FingerTemplate]] = {}
        self._pairs: dict[tuple[int, int], torch.Tensor] = {}

    def __len__(self) -> int:
        return len(self.samples)

    def template(self, shard: int) -> tuple[ObjectTemplate, FingerTemplate]:
        if shard not in self._templates:
            sh = self.shards[shard]
            self._templates[shard] = (
                ObjectTemplate.from_mesh(sh.object.points, sh.object.tets, sh.object.surface_faces),
                FingerTemplate.from_mesh(sh.fingers.vertices, sh.fingers.faces),
            )
        return self._templates[shard]

    def finger_positions(self, shard: int, g: int) -> torch.Tensor:
        """(2, V, 3) finger vertices at first contact of grasp ``g`` in the object frame [m]."""
        sh = self.shards[shard]
        return torch.as_tensor(sh.fingers.vertices_at(sh.finger_contact_pose[g]), dtype=torch.float32)

    def contact_pairs(self, shard: int, g: int) -> torch.Tensor:
        """(C, 2) cached ``[object_index, finger_index]`` contact pairs of grasp ``g`` (float64 distances)."""
        key = (shard, g)
        if key not in self._pairs:
            sh = self.shards[shard]
            fp = torch.as_tensor(sh.fingers.vertices_at(sh.finger_contact_pose[g]).reshape(-1, 3))
            self._pairs[key] = contact_pairs(
                torch.as_tensor(sh.object.points), fp, self.contact_radius, backend=self.contact_backend
            )
        return self._pairs[key]

    def _fields(self, shard: int, k: int, g: int, s: int) -> tuple[torch.Tensor, torch.Tensor]:
        sh = self.shards[shard]
        stress, disp = sh.fields(k, g, s)
        for name, arr in (("von_mises", stress), ("displacement", disp)):
            if not np.all(np.isfinite(arr)):
                raise DataError(
                    f"{sh.path}: /ramp/{name}[k={k}, g={g}, s={s}] contains NaN/inf although "
                    "/ramp/status is 0 (solved); the shard is corrupt or was written by a buggy generator"
                )
        return torch.as_tensor(stress), torch.as_tensor(disp)

    def _finger_displacement(self, shard: int, k: int, g: int, s: int, v: int) -> torch.Tensor:
        sh = self.shards[shard]
        d = sh.finger_travel[k, g, s][:, None] * sh.closing_direction[g]  # (2, 3)
        return torch.as_tensor(np.repeat(d, v, axis=0), dtype=torch.float32)

    @staticmethod
    def _remove_rigid_motion(pos: torch.Tensor, disp: torch.Tensor, n: int) -> torch.Tensor:
        """All nodes' displacements in the co-moving frame of the object's first ``n`` nodes (float64 fit)."""
        rest = pos.double().numpy()
        moved = rest + disp.double().numpy()
        R, t = best_rigid_transform(rest[:n], moved[:n])
        return torch.as_tensor(undo_rigid_motion(moved, R, t) - rest, dtype=disp.dtype)

    def __getitem__(self, i: int) -> GraspGraph:
        shard, k, g, s = (int(x) for x in self.samples[i])
        sh = self.shards[shard]
        obj, finger = self.template(shard)
        v = finger.num_nodes
        data = build_grasp_graph(
            obj,
            finger,
            self.finger_positions(shard, g),
            torch.as_tensor(sh.closing_direction[g], dtype=torch.float32),
            float(sh.force[k, g, s]),
            float(sh.object.youngs_modulus[k]),
            self.contact_radius,
            pairs=self.contact_pairs(shard, g),
        )
        stress, disp = self._fields(shard, k, g, s)
        data.stress = torch.cat([stress, torch.zeros(2 * v)])
        data.displacement = torch.cat([disp, self._finger_displacement(shard, k, g, s, v)])
        if self.displacement == "rigid_removed":
            data.displacement = self._remove_rigid_motion(data.pos, data.displacement, len(disp))
        if self.ramp_stride is not None:
            sp = s - self.ramp_stride
            if sp >= 0:
                _, prev = self._fields(shard, k, g, sp)
                data.prev_displacement = torch.cat([prev, self._finger_displacement(shard, k, g, sp, v)])
                data.prev_force = torch.tensor([float(sh.force[k, g, sp])], dtype=torch.float32)
            else:
                data.prev_displacement = torch.zeros_like(data.displacement)
                data.prev_force = torch.zeros(1)
        data.sample = torch.tensor([[shard, k, g, s]], dtype=torch.long)
        data.object_id = torch.tensor([self.object_ids[shard]], dtype=torch.long)
        return data
