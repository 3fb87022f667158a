"""Look at a grasp sample: a PNG of the deformed object with its stress and deformation, the finger pads
where the squeeze left them, and a VTU export of the fields for ParaView.

A sample is the entry ``(k, g, s)`` of a grasp shard: modulus k, grasp g, ramp step s.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from defgraspnets.data.grasp_schema import GraspShard

__all__ = ["GraspSample", "draw_grasp", "export_sample_vtu", "load_sample", "render_sample"]


class GraspSample:
    """The fields of one shard entry, in the object frame (SI units)."""

    def __init__(self, shard: GraspShard, k: int, g: int, s: int):
        sizes = (shard.num_moduli, shard.num_grasps, shard.num_steps)
        for name, i, n in zip(("modulus", "grasp", "step"), (k, g, s), sizes):
            if not -n <= i < n:
                raise IndexError(f"{shard.path}: {name} index {i} out of range (0..{n - 1})")
        k, g, s = (i % n for i, n in zip((k, g, s), sizes))
        if shard.status[k, g] != 0:
            raise ValueError(
                f"{shard.path}: entry (modulus {k}, grasp {g}) is not a solved squeeze ramp "
                f"(status {int(shard.status[k, g])}); it has no fields to show"
            )
        von_mises, displacement = shard.fields(k, g, s)
        self.name = shard.attrs.get("object_name", shard.path.stem)
        self.k, self.g, self.s = k, g, s
        self.points = shard.object.points
        self.tets = shard.object.tets
        self.surface_faces = shard.object.surface_faces
        self.youngs_modulus = float(shard.object.youngs_modulus[k])
        self.force = float(shard.force[k, g, s])
        self.von_mises = np.asarray(von_mises, dtype=np.float64)
        self.displacement = np.asarray(displacement, dtype=np.float64)
        travel = shard.finger_travel[k, g, s]  # (2,) along each finger's closing direction
        poses = shard.finger_contact_pose[g].copy()  # (2, 4, 4)
        poses[:, :3, 3] += travel[:, None] * shard.closing_direction[g]
        self.finger_vertices = shard.fingers.vertices_at(poses)  # (2, V, 3)
        self.finger_faces = shard.fingers.faces

    @property
    def deformation(self) -> np.ndarray:
        """(N,) displacement magnitude [m]."""
        return np.linalg.norm(self.displacement, axis=1)

    @property
    def title(self) -> str:
        return (
            f"{self.name}: grasp {self.g}, E = {self.youngs_modulus:.3g} Pa, "
            f"step {self.s + 1}, F = {self.force:.2f} N"
        )


def load_sample(path: str | Path, k: int = 0, g: int = 0, s: int = -1) -> GraspSample:
    """The entry ``(k, g, s)`` of the shard at ``path`` (negative indices count from the end)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no grasp shard at {path}")
    shard = GraspShard(path)
    try:
        return GraspSample(shard, k, g, s)
    finally:
        shard.close()


def render_sample(sample: GraspSample, path: str | Path, exaggeration: float | None = None) -> Path:
    """PNG of the deformed surface coloured by von Mises stress (left) and by deformation (right), with
    the finger pads. ``exaggeration`` scales the displacements for display (default: the largest one
    drawn as 10 % of the object size; 1 = true scale); the colours are always the true values."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    size = float(np.ptp(sample.points, axis=0).max())
    if exaggeration is None:
        biggest = float(sample.deformation.max())
        exaggeration = max(1.0, 0.1 * size / biggest) if biggest > 0 else 1.0
    x = (sample.points + exaggeration * sample.displacement) * 1e3  # [mm]
    panels = (
        ("von Mises stress [kPa]", sample.von_mises / 1e3, "viridis"),
        ("deformation |u| [mm]", sample.deformation * 1e3, "magma"),
    )
    fig = plt.figure(figsize=(11, 5))
    for i, (label, field, cmap) in enumerate(panels):
        ax = fig.add_subplot(1, 2, i + 1, projection="3d")
        mappable = draw_grasp(
            ax, x, sample.surface_faces, field, sample.finger_vertices * 1e3, sample.finger_faces, cmap
        )
        fig.colorbar(mappable, ax=ax, shrink=0.6, pad=0.1, label=label)
    fig.suptitle(f"{sample.title}  (displacements x{exaggeration:.3g})")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def draw_grasp(
    ax, points_mm, surface_faces, field, finger_vertices_mm, finger_faces, cmap="viridis", norm=None
):
    """Draw an object surface coloured by a vertex ``field`` and the finger pads on a 3-D axis (equal
    aspect, millimetres). Returns the ScalarMappable of the colours (for a colour bar)."""
    import matplotlib
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    field = np.asarray(field, dtype=np.float64)
    if norm is None:
        norm = matplotlib.colors.Normalize(float(field.min()), float(field.max()) or 1.0)
    face_value = field[surface_faces].mean(axis=1)
    colors = matplotlib.colormaps[cmap](norm(face_value))
    ax.add_collection3d(Poly3DCollection(points_mm[surface_faces], facecolors=colors, edgecolors="none"))
    for fingers in finger_vertices_mm:
        ax.add_collection3d(Poly3DCollection(fingers[finger_faces], facecolors=(0.6, 0.6, 0.65, 0.35)))
    everything = np.concatenate([points_mm, *finger_vertices_mm])
    mid, span = (everything.max(0) + everything.min(0)) / 2, np.ptp(everything, axis=0).max() / 2
    for setter, m in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), mid):
        setter(m - span, m + span)
    ax.set_xlabel("x [mm]")
    ax.set_ylabel("y [mm]")
    ax.set_zlabel("z [mm]")
    return matplotlib.cm.ScalarMappable(norm=norm, cmap=cmap)


def export_sample_vtu(sample: GraspSample, path: str | Path) -> tuple[Path, Path]:
    """The deformed tet mesh with point data ``von_mises`` [Pa] and ``displacement`` [m] at ``path``, and
    the finger pads as a triangle mesh at ``<stem>_fingers.vtu`` (both VTU, for ParaView)."""
    import meshio

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    meshio.Mesh(
        sample.points + sample.displacement,
        [("tetra", sample.tets)],
        point_data={"von_mises": sample.von_mises, "displacement": sample.displacement},
    ).write(path)
    V = sample.finger_vertices.shape[1]
    faces = np.concatenate([sample.finger_faces, sample.finger_faces + V])
    fingers = path.with_name(path.stem + "_fingers.vtu")
    meshio.Mesh(sample.finger_vertices.reshape(-1, 3), [("triangle", faces)]).write(fingers)
    return path, fingers
