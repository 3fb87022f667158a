"""Results of a quasi-static solve, on the host, one entry per batched problem."""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from enum import IntEnum

import numpy as np

from .mesh import TetMesh

__all__ = ["SolveStatus", "Equilibrium"]


class SolveStatus(IntEnum):
    """Outcome of a problem's solve; anything but CONVERGED is not an equilibrium and is never an answer."""

    CONVERGED = 0
    NOT_CONVERGED = 1  # Newton failed even at the smallest load increment
    ESCAPED = 2  # no equilibrium exists: the object ran away (slip, lost contact, unsupported load)
    NONFINITE = 3  # NaN or inf appeared
    # (4 is the grasp generator's STATUS_INVERTED, 7 its STATUS_SELF_INTERSECTING)
    PINCHED = 5  # one vertex pressed from opposite sides by two bodies: a body passed between the vertices
    # the controlled force passed a maximum of the equilibrium path: a force-controlled increment's travel
    # ran away in repeated failed attempts (SolverOptions.force_maximum_runaway; else NOT_CONVERGED)
    FORCE_MAXIMUM = 6


@dataclass
class Equilibrium:
    """Equilibrium fields of B problems on one mesh (SI units). Arrays are indexed by problem first.

    Fields of problems whose ``status`` is not CONVERGED hold their last converged state (at
    ``load_fraction`` of the requested increment) and must not be used as an answer.
    """

    mesh: TetMesh
    status: np.ndarray  # (B,) SolveStatus codes
    load_fraction: np.ndarray  # (B,) fraction of the last requested increment reached
    newton_iterations: np.ndarray  # (B,) Newton iterations in the last solve call
    linear_iterations: np.ndarray  # (B,) Krylov iterations (solver-wide count per Newton step, summed)
    residual: np.ndarray  # (B,) max |free residual force component| [N]
    displacement: np.ndarray  # (B, N, 3) u = x - X [m]
    travel: dict[str, np.ndarray]  # dof name -> (B,) travel [m]
    dof_force: dict[str, np.ndarray]  # dof name -> (B,) total contact force along the axis [N]
    vertex_stress: np.ndarray  # (B, N, 3, 3) volume-weighted mean Cauchy stress of adjacent tets [Pa]
    von_mises: np.ndarray  # (B, N) von Mises stress of vertex_stress [Pa]
    strain_energy: np.ndarray  # (B,) elastic energy [J]
    inverted_tets: np.ndarray  # (B,) number of tets with det F <= 0
    body_force: dict[str, np.ndarray]  # body name -> (B, 3) force the object exerts on the body [N]
    body_torque: dict[str, np.ndarray]  # body name -> (B, 3) torque of that force about the body origin [N m]
    contact_normal_force: dict[str, np.ndarray]  # body name -> (B, S) normal force per surface vertex [N]
    contact_friction_force: dict[str, np.ndarray]  # body name -> (B, S, 3) friction force on the vertex [N]
    contact_sticking: dict[str, np.ndarray]  # body name -> (B, S) bool, friction in stick
    max_penetration: np.ndarray  # (B,) deepest penetration into any body [m]
    reaction_force: np.ndarray  # (B, N, 3) support force on fixed vertices [N] (zero elsewhere)
    tet_stress: np.ndarray | None = None  # (B, M, 3, 3) Cauchy stress per tet [Pa] (if recorded)
    # (B,) largest vertex force of the increment stabilization at the last converged increment [N]
    # (SolverOptions.stabilization; zero when off)
    stabilization_force: np.ndarray | None = None
    # (B,) load steps since the reset reached past a force maximum by a jump of the equilibrium path
    # (SolverOptions.force_maximum_snap; zero when off)
    snaps: np.ndarray | None = None
    # gas pressure (solvers with a pressure surface only)
    gauge_pressure: np.ndarray | None = None  # (B,) p(V) of the cavity [Pa]
    cavity_volume: np.ndarray | None = None  # (B,) V of the pressurized cavity (without V_h) [m^3]
    pressure_force: np.ndarray | None = None  # (B, N, 3) lumped gas force on each vertex, -p A n / 3 [N]
    extras: dict = field(default_factory=dict)

    @property
    def batch_size(self) -> int:
        return len(self.status)

    def take(self, rows) -> Equilibrium:
        """The equilibria of problems ``rows`` (integer indices, repeats allowed): every per-problem array
        (and every array of the per-body / per-dof dicts) indexed by ``rows`` along its first axis, as copies;
        ``mesh`` shared and ``extras`` copied shallowly."""
        rows = np.asarray(rows)
        if rows.ndim != 1 or not np.issubdtype(rows.dtype, np.integer):
            raise ValueError(f"rows must be a 1-D integer array, got dtype {rows.dtype} shape {rows.shape}")
        B = self.batch_size
        if rows.size and (rows.min() < -B or rows.max() >= B):
            raise IndexError(f"rows must index the {B} problems, got {rows.min()}..{rows.max()}")
        out = {}
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name == "mesh":
                out[f.name] = v
            elif f.name == "extras":
                out[f.name] = dict(v)
            elif v is None:
                out[f.name] = None
            elif isinstance(v, dict):
                out[f.name] = {k: np.asarray(a)[rows] for k, a in v.items()}
            else:
                out[f.name] = np.asarray(v)[rows]
        return Equilibrium(**out)

    def put(self, rows, other: Equilibrium) -> None:
        """Problems ``rows`` (integer indices) <- the problems of ``other`` (one per row), in place: every
        per-problem array and every array of the per-body / per-dof dicts. Both must hold the same fields."""
        rows = np.asarray(rows)
        if rows.ndim != 1 or len(rows) != other.batch_size:
            raise ValueError(f"{other.batch_size} problems cannot fill rows of shape {rows.shape}")
        for f in fields(self):
            if f.name in ("mesh", "extras"):
                continue
            mine, theirs = getattr(self, f.name), getattr(other, f.name)
            if (mine is None) != (theirs is None):
                raise ValueError(f"field {f.name!r} is recorded in only one of the equilibria")
            if mine is None:
                continue
            if isinstance(mine, dict):
                for k, a in mine.items():
                    a[rows] = theirs[k]
            else:
                mine[rows] = theirs

    @property
    def converged(self) -> np.ndarray:
        return self.status == SolveStatus.CONVERGED

    @property
    def positions(self) -> np.ndarray:
        """(B, N, 3) deformed vertex positions [m]."""
        return self.mesh.points[None] + self.displacement

    @property
    def surface_vertices(self) -> np.ndarray:
        return self.mesh.surface_vertices

    def contact_vertices(self, body: str, problem: int = 0, min_force: float = 0.0) -> np.ndarray:
        """Mesh vertex indices in contact with ``body`` (normal force > ``min_force``)."""
        f = self.contact_normal_force[body][problem]
        return self.mesh.surface_vertices[f > min_force]

    def deformation(self) -> np.ndarray:
        """(B, N) |u| per vertex [m] (the DefGraspNets deformation field)."""
        return np.linalg.norm(self.displacement, axis=-1)

    def require_converged(self) -> None:
        """Raise if any problem did not reach equilibrium."""
        bad = np.nonzero(~self.converged)[0]
        if bad.size:
            names = ", ".join(f"{int(i)}: {SolveStatus(int(self.status[i])).name}" for i in bad[:8])
            raise RuntimeError(f"{bad.size} of {self.batch_size} problems did not converge ({names})")

    def save_vtu(self, path, problem: int = 0) -> None:
        """Write problem ``problem`` as a VTU (deformed mesh with displacement, von Mises, stress)."""
        cell = {} if self.tet_stress is None else {"cauchy_stress": self.tet_stress[problem].reshape(-1, 9)}
        self.mesh.save(
            path,
            points=self.positions[problem],
            point_data={
                "displacement": self.displacement[problem],
                "von_mises": self.von_mises[problem],
                "reaction_force": self.reaction_force[problem],
            },
            cell_data=cell,
        )
