r"""Verification of planned grasps in the FEM simulator (thesis §7.7).

The planner's predictions are checked against the ground truth that produced the training data: each grasp
(open-gripper pose + finger joint states) is squeezed on the FEM engine exactly as the dataset generator
does (:mod:`defgraspnets.grasp.squeeze`: pads at first contact, total grasp force 0 -> F_g in S steps, zero
gravity), and the *same* objective is evaluated on the simulated fields at F_g.

Threshold experiment (§7.7): of N sampled grasps, the 10 predicted lowest-Q ("threshold low"), the 10
predicted highest-Q ("threshold high") and 10 random others are simulated. Among these 30, a threshold-low
grasp is a hit if its true Q is among the 10 lowest of the 30, a threshold-high grasp if among the 10
highest (the thesis reports 88 % hits). The hit rate of the random baseline, for comparison, is 1/3.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from defgraspnets import fem
from defgraspnets.data.dataset import DISPLACEMENT_TARGETS
from defgraspnets.grasp.gripper import FRANKA_HAND, ParallelJawGripper
from defgraspnets.grasp.metrics import rigid_removed_displacement
from defgraspnets.grasp.squeeze import make_squeeze_solver, squeeze_ramp, squeeze_solver_options

from .objectives import GraspObjective

__all__ = ["GraspPoses", "SimulatedGrasps", "simulate_grasps", "threshold_hits"]


@dataclass(frozen=True)
class GraspPoses:
    """Grasps to simulate: open-gripper poses (G, 4, 4) and finger joint states (G, 2) [m]."""

    poses: np.ndarray
    closing_distances: np.ndarray

    def __post_init__(self):
        p = np.asarray(self.poses, dtype=np.float64)
        c = np.asarray(self.closing_distances, dtype=np.float64)
        if p.ndim != 3 or p.shape[1:] != (4, 4) or c.shape != (len(p), 2):
            raise ValueError(
                f"expected poses (G, 4, 4) and closing_distances (G, 2), got {p.shape}, {c.shape}"
            )
        if not (np.isfinite(p).all() and np.isfinite(c).all()):
            raise ValueError("grasp poses or closing distances contain NaN or inf")
        object.__setattr__(self, "poses", p)
        object.__setattr__(self, "closing_distances", c)

    def __len__(self) -> int:
        return len(self.poses)


@dataclass
class SimulatedGrasps:
    """FEM ground truth at the final force: stress (G, N) [Pa], displacement (G, N, 3) [m] (NaN where the
    ramp failed), converged (G,) bool, and Q (G,) of the objective (NaN where failed)."""

    stress: np.ndarray
    displacement: np.ndarray
    converged: np.ndarray
    q: np.ndarray
    seconds: float


def simulate_grasps(
    mesh: fem.TetMesh,
    grasps: GraspPoses,
    youngs_modulus: float,
    objective: GraspObjective,
    force: float = 15.0,
    steps: int = 10,
    friction: float = 0.7,
    poisson_ratio: float = 0.3,
    density: float = 1000.0,
    gripper: ParallelJawGripper = FRANKA_HAND,
    material_model: str = "neohookean",
    device=None,
    options: fem.SolverOptions | None = None,
    progress: bool = False,
    displacement_target: str = "total",
) -> SimulatedGrasps:
    """Squeeze every grasp to ``force`` [N] in ``steps`` load steps (one batched FEM problem per grasp).

    A grasp whose ramp fails at any step (or inverts a tet) gets NaN fields and Q and ``converged`` False;
    it is reported, never scored as if it had an answer. ``material_model``: the FEM's constitutive energy,
    as the checkpoint's training data (``datagen/grasps.py`` default: neohookean). ``displacement_target``:
    the field the model predicts (``DefGraspNetsPredictor.displacement_target``); ``"rigid_removed"``
    removes each grasp's best rigid motion of the object before Q is computed, as in the training data.
    """
    if displacement_target not in DISPLACEMENT_TARGETS:
        raise ValueError(f"displacement_target={displacement_target!r} is not one of {DISPLACEMENT_TARGETS}")
    import time

    t0 = time.perf_counter()
    material = fem.Material(youngs_modulus, poisson_ratio, density, model=material_model)
    solver = make_squeeze_solver(
        mesh, grasps, material, friction, gripper, device=device, options=options or squeeze_solver_options()
    )
    ok = np.ones(len(grasps), dtype=bool)

    def record(_s, _f, eq: fem.Equilibrium) -> None:
        ok[:] &= np.asarray(eq.converged) & (np.asarray(eq.inverted_tets) == 0)

    eqs = squeeze_ramp(solver, force, steps, progress=progress, on_step=record)
    final = eqs[-1]
    stress = np.where(ok[:, None], final.von_mises, np.nan)
    disp = np.where(ok[:, None, None], final.displacement, np.nan)
    if displacement_target == "rigid_removed" and ok.any():
        disp[ok] = rigid_removed_displacement(mesh.points, mesh.points + disp[ok])
    with torch.no_grad():
        q = objective(torch.as_tensor(np.nan_to_num(stress)), torch.as_tensor(np.nan_to_num(disp))).numpy()
    q = np.where(ok, q, np.nan)
    return SimulatedGrasps(stress, disp, ok, q, time.perf_counter() - t0)


def threshold_hits(true_q: np.ndarray, low: np.ndarray, high: np.ndarray) -> dict:
    """Hits of the threshold experiment among the simulated grasps (see the module docstring).

    Args:
        true_q: (M,) simulated Q of all simulated grasps (NaN: failed, excluded).
        low, high: indices into ``true_q`` of the predicted-low and predicted-high grasps.
    Returns:
        ``low_hits``, ``high_hits`` (fractions of the valid ones), ``hit_rate`` (both together), and the
        counts used.
    """
    true_q = np.asarray(true_q, dtype=np.float64)
    valid = np.flatnonzero(np.isfinite(true_q))
    k_low, k_high = len(low), len(high)
    order = valid[np.argsort(true_q[valid], kind="stable")]
    lowest, highest = set(order[:k_low].tolist()), set(order[len(order) - k_high :].tolist())
    low_ok = [i for i in low if np.isfinite(true_q[i])]
    high_ok = [i for i in high if np.isfinite(true_q[i])]
    lo = sum(i in lowest for i in low_ok)
    hi = sum(i in highest for i in high_ok)
    n = len(low_ok) + len(high_ok)
    return {
        "low_hits": lo / len(low_ok) if low_ok else float("nan"),
        "high_hits": hi / len(high_ok) if high_ok else float("nan"),
        "hit_rate": (lo + hi) / n if n else float("nan"),
        "simulated": int(len(true_q)),
        "failed": int(len(true_q) - len(valid)),
    }
