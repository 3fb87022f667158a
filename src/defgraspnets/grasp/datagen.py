"""The grasp dataset generator (thesis §7.4, DefGraspSim ch. 6): squeeze ramps on the FEM engine, and
optionally the DefGraspSim experiments, written as HDF5 grasp shards (schema ``defgraspnets.grasps/1``,
:mod:`defgraspnets.data.grasp_schema`).

For one object and K Young's moduli ``E_k``::

    mesh   = tet mesh of the object (registry name, cached on disk) or a given TetMesh
    grasps = G antipodal Franka grasps (seeded), split into ``shard_count`` contiguous shards
    for each shard, for each E_k:
        one batched quasi-static problem per grasp of the shard: pads at first contact, total normal
        grasp force F_g ramped 0 -> F_max in S equal steps, zero gravity
        per step s: von Mises stress sigma (N,), displacement d = x - X (N, 3), F_g, finger travel
        optionally (``experiments``, thesis §6.4-6.5): the selected experiments of the same grasps with
        :class:`~defgraspnets.grasp.experiments.GraspExperiments` (pickup always, then reorientation,
        linear and angular acceleration), batched over the grasps: the 7 performance metrics, the 7 grasp
        features, per-direction thresholds and failure codes, and a status per experiment
        (:class:`~defgraspnets.data.grasp_schema.ExperimentStatus`; a metric is NaN where its experiment
        measured nothing, never a made-up number)

Every ``(k, g)`` entry is written with status 0 only if its problem converged at *every* step (and, by
default, has no inverted tet); otherwise its fields are NaN and its status is the first failure code
(:class:`~defgraspnets.fem.SolveStatus` 1-3, 5 and 6, :data:`STATUS_INVERTED` or
:data:`STATUS_SELF_INTERSECTING`). Failed entries are never
training data (thesis: unstable grasps are excluded from D).

A shard is written through :class:`~defgraspnets.data.grasp_schema.GraspShardWriter`: a killed run leaves
``<name>.partial.h5``; running the generator again with the same settings resumes it and simulates only
the grasps not written yet. An entry's ramp and experiment results are written together and marked done
only then, so a resumed shard holds every entry once. Finished shards (``<name>.h5``) are skipped unless
``overwrite``. Independent shards (``shard_index`` = i of ``shard_count``) and objects are the unit of
scale-out (Hydra multirun).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

from defgraspnets import __version__, fem
from defgraspnets.data.grasp_schema import (
    EXPERIMENT_NAMES,
    STATUS_SOLVED,
    ExperimentLayout,
    ExperimentStatus,
    GraspShardWriter,
    GripperFingers,
    ObjectRecord,
    shard_file_name,
)
from defgraspnets.data.output_dir import check_output_dir
from defgraspnets.data.splits import named_rng
from defgraspnets.fem.self_contact import self_contact_depth

from . import features as _features
from .experiments import (
    ExperimentSettings,
    GraspExperiments,
    GraspFailure,
    experiment_solver_options,
    sphere_directions,
)
from .gripper import FRANKA_HAND, ParallelJawGripper
from .sampler import GraspSet, sample_antipodal_grasps
from .squeeze import (
    GRIP_DOF,
    finger_contact_poses,
    make_squeeze_solver,
    squeeze_ramp,
    squeeze_solver_options,
    squeeze_stream,
)

__all__ = [
    "STATUS_INVERTED",
    "STATUS_SELF_INTERSECTING",
    "ShardResult",
    "claim_object",
    "experiment_layout",
    "generate_object_shards",
    "gripper_fingers",
    "load_object_mesh",
    "object_moduli",
    "resolve_experiment_settings",
    "resolve_experiments",
    "resolve_object_mesh",
    "run_experiments",
    "shard_grasp_indices",
    "solver_settings",
    "structured_box",
    "time_grasp_experiments",
]

STATUS_INVERTED = 4  # converged, but with inverted tets (det F <= 0): not a physical answer
# converged, but at its last step the object passes through itself (surface vertices inside its own tets: the
# FEM has no self-contact, so a hollow object squeezed flat lets its walls pass through each other)
STATUS_SELF_INTERSECTING = 7
_log = logging.getLogger(__name__)

#: SolverOptions fields that choose how the Newton systems are solved, not which equilibria the data hold (to
#: round-off with the exact solvers): a shard may be resumed with other values (another device's defaults)
_SOLVE_ONLY_FIELDS = frozenset(
    {
        "linear_solver",
        "banded_min_problems",
        "factor_streams",
        "factor_graphs",
        "cg_rtol",
        "cg_max_iterations",
        "line_search_trials",
        "max_factor_reuse",
        "factor_reuse_contraction",
        "record_tet_stress",
    }
)


def solver_settings(squeeze: fem.SolverOptions, experiments: fem.SolverOptions | None = None) -> dict:
    """The FEM settings a shard records (``solver_settings`` attribute) and must be resumed with: the squeeze
    ramps' and, with experiments, the experiments' :class:`~defgraspnets.fem.SolverOptions`, without the
    fields that only choose the linear solver and its tuning (``_SOLVE_ONLY_FIELDS``). A partial shard made
    with other settings (e.g. before a default changed) is then not silently continued."""

    def value(v):
        """Numbers as floats (1000 and 1000.0 are one setting); flags, names and None as they are."""
        number = isinstance(v, (int, float, np.number)) and not isinstance(v, (bool, np.bool_))
        return float(v) if number else v

    def physics(options: fem.SolverOptions) -> dict:
        fields = dataclasses.asdict(options)
        return {k: value(v) for k, v in fields.items() if k not in _SOLVE_ONLY_FIELDS}

    out = {"squeeze": physics(squeeze)}
    if experiments is not None:
        out["experiments"] = physics(experiments)
    return out


@dataclass
class ShardResult:
    """Outcome of one shard: its final path, solved / total ``(k, g)`` entries, wall time [s], and per
    experiment run the count of entries per :class:`ExperimentStatus` name (``{"pickup": {"OK": 5, "LOST": 1,
    ...}}``; empty without experiments)."""

    path: Path
    solved: int
    total: int
    seconds: float
    skipped: bool = False  # the shard was already finished
    experiments: dict[str, dict[str, int]] = field(default_factory=dict)

    def experiment_summary(self) -> str:
        """``pickup 5 ok / 1 failed (LOST 1), linear 6 ok / 0 failed`` (empty without experiments)."""
        parts = []
        for name, counts in self.experiments.items():
            ok = counts.get("OK", 0)
            bad = {k: v for k, v in counts.items() if k != "OK" and v}
            why = f" ({', '.join(f'{k} {v}' for k, v in bad.items())})" if bad else ""
            parts.append(f"{name} {ok} ok / {sum(bad.values())} failed{why}")
        return ", ".join(parts)


# ---------------------------------------------------------------------------------------------- inputs
def load_object_mesh(
    name: str, target_nodes: int = 1000, mesher: str = "ftetwild", cache_dir=None
) -> tuple[fem.TetMesh, str, str]:
    """``(tet mesh, category, source)`` of the registry object ``name`` (tet mesh cached on disk).

    Raises:
        ValueError: ``name`` is not a registered object.
    """
    from defgraspnets.objects import get_object, list_objects, tet_mesh

    if name not in list_objects():
        close = [n for n in list_objects() if n.split("_")[0] == name.split("_")[0]][:6]
        hint = f"; similar: {', '.join(close)}" if close else ""
        raise ValueError(
            f"unknown object {name!r} (see defgraspnets.objects.list_objects() or "
            f"configs/objects/*.yaml){hint}"
        )
    model = get_object(name)
    mesh = tet_mesh(name, target_nodes=target_nodes, mesher=mesher, cache_dir=cache_dir)
    return mesh, model.category, model.source


_TET_SUFFIXES = (".vtu", ".vtk", ".msh", ".mesh", ".xdmf")


def resolve_object_mesh(
    spec: str,
    box_size=(0.03, 0.03, 0.03),
    box_divisions=(4, 4, 4),
    target_nodes: int = 1000,
    mesher: str = "ftetwild",
    cache_dir=None,
) -> fem.TetMesh:
    """The tet mesh named by ``spec``: ``"box"`` (:func:`structured_box`), a registry object name, a tet
    mesh file (``.vtu``, ``.vtk``, ``.msh``, ...; read with meshio), or a closed surface file (``.obj``,
    ``.stl``, ``.ply``, ...; tetrahedralized to about ``target_nodes`` vertices, cached), in metres.

    Raises:
        FileNotFoundError: ``spec`` looks like a path but no file is there.
        ValueError: neither a registry name nor a file; a file of no mesh format, unreadable, or whose
            vertices are not finite (:class:`~defgraspnets.objects.ObjectMeshError`, naming the file).
    """
    if spec == "box":
        return structured_box(box_size, box_divisions)
    path = Path(spec)
    if path.suffix:
        if not path.is_file():
            raise FileNotFoundError(f"no object mesh file at {path}")
        if path.suffix.lower() in _TET_SUFFIXES:
            return fem.TetMesh.load(path, name=path.stem)
        import trimesh

        from defgraspnets.objects import ObjectMeshError, tetrahedralize

        if path.suffix.lower().lstrip(".") not in trimesh.available_formats():
            raise ObjectMeshError(
                f"{path}: unknown mesh format {path.suffix!r}; expected a tet mesh "
                f"({', '.join(_TET_SUFFIXES)}) or a closed surface (.stl, .obj, .ply, .off, .glb, ...: "
                "trimesh.available_formats())"
            )
        try:
            # unprocessed first: trimesh's processing drops NaN vertices with their faces, which would
            # report the broken coordinates as a hole
            raw = trimesh.load(path, force="mesh", process=False)
        except Exception as e:
            raise ObjectMeshError(f"{path}: not a readable surface mesh ({type(e).__name__}: {e})") from e
        bad = np.flatnonzero(~np.isfinite(np.asarray(raw.vertices)).all(axis=1))
        if bad.size:
            shown = ", ".join(str(i) for i in bad[:8]) + (", ..." if bad.size > 8 else "")
            raise ObjectMeshError(
                f"{path}: non-finite (NaN or inf) coordinates at vertices [{shown}] ({bad.size} in all)"
            )
        surface = raw.process()  # = trimesh.load(path, force="mesh"), without reading the file twice
        return tetrahedralize(surface, target_nodes, mesher, cache_dir=cache_dir, name=path.stem)
    return load_object_mesh(spec, target_nodes, mesher, cache_dir)[0]


def structured_box(size=(0.03, 0.03, 0.03), divisions=(4, 4, 4), name: str | None = None) -> fem.TetMesh:
    """A structured tet box centred at the origin (needs no mesher): ``size`` [m], hexes per axis
    ``divisions`` (6 tets each). Named ``box_<W>x<H>x<D>`` in millimetres unless ``name`` is given."""
    size = np.asarray(size, dtype=np.float64).reshape(3)
    if np.any(~np.isfinite(size)) or np.any(size <= 0):
        raise ValueError(f"box size must be three positive lengths [m], got {size.tolist()}")
    divisions = tuple(int(d) for d in divisions)
    if len(divisions) != 3 or min(divisions) < 1:
        raise ValueError(f"box divisions must be three integers >= 1, got {divisions}")
    if name is None:
        name = "box_" + "x".join(f"{1000 * s:g}" for s in size)
    return fem.TetMesh.box(size=size, divisions=divisions, origin=-size / 2, name=name)


def gripper_fingers(gripper: ParallelJawGripper = FRANKA_HAND) -> GripperFingers:
    """The finger-pad surface in the finger frame, as stored in a shard (closing axis = local +y)."""
    v, f = gripper.pad_mesh
    return GripperFingers(np.array(v), np.array(f), np.array([0.0, 1.0, 0.0]))


def shard_grasp_indices(num_grasps: int, shard_index: int, shard_count: int) -> np.ndarray:
    """Indices of the grasps of shard ``shard_index`` of ``shard_count``: contiguous, near-equal parts
    (the rotations of one grasp axis stay together)."""
    if not 0 <= shard_index < shard_count:
        raise ValueError(f"shard_index {shard_index} outside [0, {shard_count})")
    part = np.array_split(np.arange(num_grasps), shard_count)[shard_index]
    if part.size == 0:
        raise ValueError(f"shard {shard_index} of {shard_count} holds no grasp ({num_grasps} grasps in all)")
    return part


def claim_object(claim_dir: str | Path, name: str) -> bool:
    """Claim object ``name`` for this process in ``claim_dir``, shared by the workers of one run.

    Workers that each walk the whole object list and simulate only what they claim share the set by
    demand (a worker that finished takes the next unclaimed object), instead of a fixed deal that leaves
    GPUs idle behind a slow object. The claim is an ``os.mkdir`` of ``claim_dir/<name>``, atomic on a
    local file system: exactly one worker gets it. Claims say who works on what, not what is done (the
    shards do): clear ``claim_dir`` before a new run; a re-run resumes unfinished shards as always.

    Returns: True if this call claimed the object, False if another worker had.
    """
    root = Path(claim_dir)
    root.mkdir(parents=True, exist_ok=True)
    key = str(name).replace(os.sep, "_").replace("/", "_") or "_"
    try:
        os.mkdir(root / key)
    except FileExistsError:
        return False
    return True


def object_moduli(
    name: str,
    youngs_modulus: Sequence[float],
    per_object: int | None = None,
    seed: int = 0,
    all_moduli_objects: Sequence[str] = (),
) -> list[float]:
    """The Young's moduli [Pa] that object ``name`` is simulated with.

    The thesis's data set (§7.4) holds each object at one modulus, ``N = #objects x 100 grasps x 50 steps
    = 3.55e5``, and tests unseen moduli (level 2) on an object held at ten (a 7 / 3 split). ``per_object``
    moduli of the list are drawn for each object without replacement by a generator seeded with ``seed``
    and a CRC of the name (as the splits are: adding an object does not change the others' draws, and a
    resumed run draws the same), returned in the list's order; objects named in ``all_moduli_objects``
    (the level-2 objects) and every object when ``per_object`` is None keep the whole list.

    Raises:
        ValueError: ``per_object`` not an integer in [1, len(youngs_modulus)].
    """
    moduli = [float(e) for e in youngs_modulus]
    if per_object is not None and not (
        isinstance(per_object, (int, np.integer)) and 1 <= per_object <= len(moduli)
    ):
        raise ValueError(
            f"moduli_per_object must be null or an integer in [1, {len(moduli)}] (the number of moduli "
            f"listed), got {per_object!r}"
        )
    if per_object is None or name in set(all_moduli_objects):
        return moduli
    rng = named_rng(seed, f"moduli/{name}")
    chosen = np.sort(rng.choice(len(moduli), size=int(per_object), replace=False))
    return [moduli[i] for i in chosen]


def _is_number(value) -> bool:
    """A real number (int, float, a numpy scalar or 0-d array of either); not a string, bool or container."""
    try:
        return np.ndim(value) == 0 and np.asarray(value).dtype.kind in "iuf"
    except (TypeError, ValueError):
        return False


def _check_inputs(moduli, num_grasps, steps, max_force, friction, poisson_ratio, density, shard_count):
    listed = isinstance(moduli, (Sequence, np.ndarray)) and not isinstance(moduli, (str, bytes))
    if not all(_is_number(e) for e in (np.asarray(moduli).reshape(-1) if listed else [moduli])):
        raise ValueError(f"youngs_modulus must be a number or a list of numbers [Pa], got {moduli!r}")
    named = dict(num_grasps=num_grasps, steps=steps, max_force=max_force, friction=friction,
                 poisson_ratio=poisson_ratio, density=density, shard_count=shard_count)  # fmt: skip
    for key, value in named.items():
        if not _is_number(value):
            raise ValueError(f"{key} must be a number, got {value!r} ({type(value).__name__})")
    moduli = np.atleast_1d(np.asarray(moduli, dtype=np.float64))
    if moduli.ndim != 1 or moduli.size == 0:
        raise ValueError(f"youngs_modulus must be a non-empty list of moduli [Pa], got {moduli!r}")
    if not np.all(np.isfinite(moduli)) or np.any(moduli <= 0):
        raise ValueError(f"Young's moduli must be finite and positive [Pa], got {moduli.tolist()}")
    if len(np.unique(moduli)) != len(moduli):
        raise ValueError(f"Young's moduli must be distinct, got {moduli.tolist()}")
    if int(num_grasps) != num_grasps or num_grasps < 1:
        raise ValueError(f"num_grasps must be an integer >= 1, got {num_grasps!r}")
    if int(steps) != steps or steps < 1:
        raise ValueError(f"steps must be an integer >= 1, got {steps!r}")
    if not np.isfinite(max_force) or max_force <= 0:
        raise ValueError(f"max_force must be a positive force [N], got {max_force!r}")
    if not np.isfinite(friction) or friction <= 0:
        raise ValueError(f"friction must be a positive Coulomb coefficient, got {friction!r}")
    if not -1.0 < poisson_ratio < 0.5:
        raise ValueError(f"poisson_ratio must lie in (-1, 0.5), got {poisson_ratio!r}")
    if not np.isfinite(density) or density <= 0:
        raise ValueError(f"density must be positive [kg/m^3], got {density!r}")
    if int(shard_count) != shard_count or shard_count < 1:
        raise ValueError(f"shard_count must be an integer >= 1, got {shard_count!r}")
    return moduli


# ---------------------------------------------------------------------------------------------- ramps
def _empty_ramps(b: int, steps: int, n: int) -> dict[str, np.ndarray]:
    """Per-ramp fields of ``b`` ramps of ``steps`` steps on an ``n``-vertex mesh, NaN until reached."""
    return {
        "force": np.full((b, steps), np.nan),
        "von_mises": np.full((b, steps, n), np.nan, dtype=np.float32),
        "displacement": np.full((b, steps, n, 3), np.nan, dtype=np.float32),
        "finger_travel": np.full((b, steps, 2), np.nan),
        "status": np.zeros(b, dtype=np.int8),
    }


def _record_steps(
    out: dict[str, np.ndarray],
    rows: np.ndarray,
    steps: np.ndarray,
    eq: fem.Equilibrium,
    reject_inverted: bool,
    last_step: int | None = None,
    contact_depth: float = 0.0,
) -> None:
    """Store the equilibria ``eq`` (row i: ramp ``rows[i]`` at step ``steps[i]``) in ``out``: a ramp keeps
    the first failure code it meets (inverted tets count as failed with ``reject_inverted``, and so does a
    ramp whose state at ``last_step`` passes through itself: :data:`STATUS_SELF_INTERSECTING`) and its
    fields only while it is solved (NaN from its failure on). ``contact_depth`` [m]: with self-contact,
    surface vertices within it of another part of the surface are held by the penalty, not passed through
    (:func:`_contact_depth`)."""
    code = np.where(eq.converged, STATUS_SOLVED, eq.status).astype(np.int8)
    if reject_inverted:
        code = np.where((code == STATUS_SOLVED) & (eq.inverted_tets > 0), STATUS_INVERTED, code)
        if last_step is not None:
            # (checked at the last step only: ~35 ms a state on a 1000-vertex mesh; squeezing goes one way)
            for i in np.flatnonzero((code == STATUS_SOLVED) & (np.asarray(steps) == last_step)).tolist():
                if eq.mesh.surface_vertices_inside(eq.positions[i], depth=contact_depth).size:
                    code[i] = STATUS_SELF_INTERSECTING
    status = out["status"]
    newly = (status[rows] == STATUS_SOLVED) & (code != STATUS_SOLVED)
    status[rows[newly]] = code[newly]
    ok = status[rows] == STATUS_SOLVED
    r, s = rows[ok], steps[ok]
    out["force"][r, s] = eq.dof_force[GRIP_DOF][ok]
    out["von_mises"][r, s] = eq.von_mises[ok]
    out["displacement"][r, s] = eq.displacement[ok]
    # both pads share the grip dof: each travels this far along its own closing direction
    out["finger_travel"][r, s] = eq.travel[GRIP_DOF][ok, None]


@dataclass(frozen=True)
class _Ramps:
    """How the squeeze ramps of a shard are simulated (the generator's arguments of that name)."""

    mesh: fem.TetMesh
    friction: float
    max_force: float
    steps: int
    device: object
    options: fem.SolverOptions | None
    reject_inverted: bool
    progress: bool
    gripper: ParallelJawGripper


def _contact_depth(ramps: _Ramps) -> float:
    """Penetration [m] that self-contact (``SolverOptions.self_contact`` > 0) holds, else 0: the
    self-intersection check's allowance."""
    if ramps.options is None or not ramps.options.self_contact > 0:
        return 0.0
    return self_contact_depth(ramps.mesh)


def _squeeze_modulus(
    ramps: _Ramps, grasps: GraspSet, material: fem.Material | Sequence[fem.Material]
) -> dict[str, np.ndarray]:
    """One batched squeeze ramp (one material, or one per grasp); per-grasp fields (NaN where failed) and
    status (first failure code)."""
    b = len(grasps)
    out = _empty_ramps(b, ramps.steps, ramps.mesh.num_vertices)
    solver = make_squeeze_solver(
        ramps.mesh, grasps, material, ramps.friction, gripper=ramps.gripper, device=ramps.device,
        options=ramps.options,
    )  # fmt: skip
    rows = np.arange(b)

    def record(s: int, _force: float, eq: fem.Equilibrium) -> None:
        _record_steps(
            out, rows, np.full(b, s), eq, ramps.reject_inverted, ramps.steps - 1, _contact_depth(ramps)
        )

    squeeze_ramp(solver, ramps.max_force, ramps.steps, progress=ramps.progress, on_step=record)
    return out


def _squeeze_streamed(
    ramps: _Ramps,
    grasps: GraspSet,
    jobs: Sequence[tuple[int, int]],
    materials: Mapping[int, fem.Material],
    slots: int,
    on_ramp: Callable[[int, int, dict[str, np.ndarray]], None],
) -> None:
    """The squeeze ramps ``jobs`` ((modulus index, grasp index) pairs) streamed through ``slots`` problems
    (:func:`~defgraspnets.grasp.squeeze.squeeze_stream`); ``on_ramp(k, g, fields)`` is called as soon as a
    ramp has reached (or failed) its last step, with its fields as :func:`_squeeze_modulus` gives them for
    one grasp (``status`` an int)."""
    n, steps = ramps.mesh.num_vertices, ramps.steps
    index = np.array([g for _, g in jobs], dtype=int)
    poses = finger_contact_poses(grasps[index], ramps.gripper)
    solver = make_squeeze_solver(
        ramps.mesh, grasps[index[: min(slots, len(jobs))]], materials[jobs[0][0]], ramps.friction,
        gripper=ramps.gripper, device=ramps.device, options=ramps.options,
    )  # fmt: skip
    # the fields of the ramps under way, one row each (at most one ramp per problem is under way)
    rows_of: dict[int, int] = {}
    free = list(range(min(slots, len(jobs))))
    running = _empty_ramps(len(free), steps, n)

    def on_steps(ramp_ids: np.ndarray, step_ids: np.ndarray, part: fem.Equilibrium) -> None:
        for j in np.unique(ramp_ids).tolist():
            if j not in rows_of:
                rows_of[j] = free.pop()
        rows = np.array([rows_of[j] for j in ramp_ids.tolist()], dtype=int)
        _record_steps(running, rows, step_ids, part, ramps.reject_inverted, steps - 1, _contact_depth(ramps))
        # a ramp's steps arrive in order: one that reached its last step is done
        for j in np.unique(ramp_ids[step_ids == steps - 1]).tolist():
            r = rows_of.pop(j)
            fields = {key: v[r].copy() for key, v in running.items()}
            fields["status"] = int(fields["status"])
            for key, v in running.items():  # the row is free again: as _empty_ramps leaves it
                v[r] = STATUS_SOLVED if key == "status" else np.nan
            free.append(r)
            k, g = jobs[j]
            on_ramp(k, g, fields)

    materials_per_job = [materials[k] for k, _ in jobs]
    squeeze_stream(solver, poses, materials_per_job, on_steps, ramps.max_force, steps, ramps.progress)


@dataclass
class _ShardFill:
    """Simulates the unwritten entries ``todo`` (modulus index -> grasp indices) of one shard and writes
    them: squeeze ramps in batches or streamed, then the experiments of each modulus (if any)."""

    writer: GraspShardWriter
    ramps: _Ramps
    grasps: GraspSet
    todo: dict[int, list[int]]
    materials: dict[int, fem.Material]
    moduli: np.ndarray
    layout: ExperimentLayout | None
    names: tuple[str, ...]
    settings: ExperimentSettings
    experiment_options: fem.SolverOptions | None
    directions_per_solver: int
    bar: object = None

    def write_modulus(self, kk: int, gs: list[int], res: dict[str, np.ndarray]) -> None:
        """Run modulus kk's experiments (if any) and write its ramps ``res`` (rows: grasps ``gs``)."""
        entries = None
        r = self.ramps
        if self.layout is not None:
            entries, _ = run_experiments(
                r.mesh, self.grasps[np.array(gs)], self.materials[kk], self.settings, self.names, r.device,
                self.experiment_options, r.gripper, self.directions_per_solver, r.progress,
            )  # fmt: skip
        # ramp and experiment results of an entry are written together, then marked done
        for j, g in enumerate(gs):
            self.writer.write(
                kk, g, res["force"][j], res["von_mises"][j], res["displacement"][j], res["finger_travel"][j],
                status=int(res["status"][j]), experiments=None if entries is None else entries[j],
            )  # fmt: skip

    def modulus_done(self, kk: int, status: np.ndarray) -> None:
        codes = status[status != STATUS_SOLVED]
        if codes.size:
            _log.warning(
                "%s E=%.3g Pa: %d of %d squeeze ramps failed (status %s); stored as failed",
                self.ramps.mesh.name, self.moduli[kk], codes.size, status.size, np.unique(codes).tolist(),
            )  # fmt: skip
        if self.bar is not None:
            self.bar.update(1)

    def in_batches(self, moduli_per_solver: int) -> None:
        """The squeeze ramps of ``moduli_per_solver`` moduli at a time in one batch; each modulus is written
        as soon as its batch is done."""
        order = list(self.todo)
        for batch in [order[j : j + moduli_per_solver] for j in range(0, len(order), moduli_per_solver)]:
            per_problem = [self.materials[kk] for kk in batch for _ in self.todo[kk]]
            grasps = self.grasps[np.concatenate([self.todo[kk] for kk in batch])]
            batch_ramps = _squeeze_modulus(
                self.ramps, grasps, per_problem if len(batch) > 1 else per_problem[0]
            )
            first = 0
            for kk in batch:
                gs = self.todo[kk]
                res = {key: v[first : first + len(gs)] for key, v in batch_ramps.items()}
                first += len(gs)
                self.write_modulus(kk, gs, res)
                self.modulus_done(kk, res["status"])

    def streamed(self, slots: int) -> None:
        """Every ramp through ``slots`` problems, modulus by modulus in the queue; a ramp is written as soon
        as it is done (a killed run keeps it), or with experiments its modulus once all its ramps are."""
        jobs = [(kk, g) for kk, gs in self.todo.items() for g in gs]
        if not jobs:  # every entry written (killed before the shard was finalized): nothing to solve
            return
        held: dict[int, dict[int, dict]] = {kk: {} for kk in self.todo}

        def on_ramp(kk: int, g: int, fields: dict) -> None:
            if self.layout is None:
                self.write_modulus(kk, [g], {key: np.asarray(v)[None] for key, v in fields.items()})
                fields = {"status": fields["status"]}
            held[kk][g] = fields
            gs = self.todo[kk]
            if len(held[kk]) == len(gs):
                res = {key: np.stack([held[kk][g][key] for g in gs]) for key in held[kk][gs[0]]}
                if self.layout is not None:
                    self.write_modulus(kk, gs, res)
                self.modulus_done(kk, res["status"])
                del held[kk]

        _squeeze_streamed(self.ramps, self.grasps, jobs, self.materials, slots, on_ramp)


# ---------------------------------------------------------------------------------------------- experiments
# what a failing experiment raises (the FEM engine, the metrics on degenerate states): recorded as ERROR for
# the grasps of that batch instead of losing the shard; programming errors (TypeError, ...) still propagate
_EXPERIMENT_ERRORS = (ValueError, RuntimeError, ArithmeticError, np.linalg.LinAlgError)
_PICKUP_METRICS = {
    "max_von_mises_stress_pa": "max_von_mises",
    "max_deformation_m": "max_deformation",
    "strain_energy_j": "strain_energy",
}
_INSTABILITY = {"linear": "linear_instability_m_s2", "angular": "angular_instability_rad_s2"}


def resolve_experiments(names) -> tuple[str, ...]:
    """The experiments to run, in the order of :data:`~defgraspnets.data.grasp_schema.EXPERIMENT_NAMES`:
    ``()`` for none (squeeze ramps only); ``pickup`` is added to any selection (it forms the grasp and gives
    the features and F_slip, as in :meth:`GraspExperiments.run`).

    Raises:
        ValueError: an unknown name, or not a list of names.
    """
    if names is None:
        return ()
    if isinstance(names, str):
        names = [names]
    try:
        names = list(names)
    except TypeError as e:
        raise ValueError(f"experiments must be a list of names, got {names!r}") from e
    unknown = [n for n in names if n not in EXPERIMENT_NAMES]
    if unknown:
        raise ValueError(
            f"unknown experiment(s) {unknown}; choose from {list(EXPERIMENT_NAMES)} "
            "(or [] for squeeze ramps only)"
        )
    if not names:
        return ()
    chosen = set(names) | {"pickup"}
    return tuple(n for n in EXPERIMENT_NAMES if n in chosen)


def resolve_experiment_settings(settings, friction: float) -> ExperimentSettings:
    """:class:`ExperimentSettings` with the generator's pad ``friction``, from None (the defaults), a
    mapping of its fields other than ``friction`` (a Hydra config group), or ``ExperimentSettings`` whose
    friction is ``friction``.

    Raises:
        ValueError: unknown fields, a mapping that sets ``friction``, a different friction, bad values.
        TypeError: anything else.
    """
    if settings is None:
        return ExperimentSettings(friction=float(friction))
    if isinstance(settings, ExperimentSettings):
        if settings.friction != friction:
            raise ValueError(
                f"experiment settings have friction {settings.friction}, the generator {friction}: the "
                "experiments use the generator's friction (the pads are the same)"
            )
        return settings
    if isinstance(settings, Mapping):
        known = {f.name for f in dataclasses.fields(ExperimentSettings)}
        if "friction" in settings:
            raise ValueError(
                "experiment settings must not set friction: the experiments use the generator's `friction`"
            )
        unknown = sorted(set(settings) - known)
        if unknown:
            raise ValueError(
                f"unknown experiment settings {unknown}; ExperimentSettings has "
                f"{sorted(known - {'friction'})}"
            )
        return ExperimentSettings(**dict(settings), friction=float(friction))
    raise TypeError(
        f"experiment settings must be ExperimentSettings, a mapping or None, got {type(settings)}"
    )


def experiment_layout(names, settings: ExperimentSettings) -> ExperimentLayout:
    """The shard's ``/experiments`` layout for the experiments ``names`` run with ``settings``: the test
    directions and reorientation axes of :class:`GraspExperiments` (:func:`sphere_directions`)."""
    j = settings.reorientation_angles
    return ExperimentLayout(
        names=resolve_experiments(names),
        settings=dataclasses.asdict(settings),
        directions=sphere_directions(settings.num_directions),
        axes=sphere_directions(settings.num_directions),
        angles=np.pi * np.arange(1, j + 1) / j,
    )


def run_experiments(
    mesh: fem.TetMesh,
    grasps: GraspSet,
    material: fem.Material,
    settings: ExperimentSettings,
    names=EXPERIMENT_NAMES,
    device=None,
    options: fem.SolverOptions | None = None,
    gripper: ParallelJawGripper = FRANKA_HAND,
    directions_per_solver: int = 1,
    progress: bool = False,
) -> tuple[list[dict[str, np.ndarray]], dict[str, float]]:
    """Run the experiments ``names`` on the B ``grasps`` with :class:`GraspExperiments` (each experiment
    batched over the grasps) and return one shard entry per grasp (:meth:`ExperimentLayout.empty_entry`
    filled in, see :mod:`defgraspnets.data.grasp_schema`) and the wall time of each experiment [s].

    The metrics and features are those of :meth:`GraspExperimentResults.per_grasp`, except that nothing
    unmeasured is reported: a grasp whose squeeze to F_p found no equilibrium gets NaN features and
    metrics and status NOT_GRASPED, and is left out of the later experiments; an experiment that raises
    marks its grasps ERROR (logged) and the others still run.
    """
    names = resolve_experiments(names)
    if not names:
        raise ValueError("run_experiments: no experiment selected")
    layout = experiment_layout(names, settings)
    b = len(grasps)
    entries = [layout.empty_entry() for _ in range(b)]
    seconds: dict[str, float] = {}
    col = {n: i for i, n in enumerate(EXPERIMENT_NAMES)}
    options = options or experiment_solver_options()

    def make(rows=None) -> GraspExperiments:
        return GraspExperiments(
            mesh, grasps if rows is None else grasps[rows], material, settings, gripper=gripper,
            device=device, options=options, progress=progress, directions_per_solver=directions_per_solver,
        )  # fmt: skip

    def attempt(name: str, rows, fn):
        start = time.perf_counter()
        try:
            return fn()
        except _EXPERIMENT_ERRORS:
            _log.exception(
                "%s E=%.3g Pa: the %s experiment of %d grasps raised; recorded as ERROR",
                mesh.name, material.youngs_modulus, name, len(rows),
            )  # fmt: skip
            for j in rows:
                entries[j]["status"][col[name]] = ExperimentStatus.ERROR
            return None
        finally:
            seconds[name] = time.perf_counter() - start

    ex = make()
    pickup = attempt("pickup", range(b), ex.pickup)
    if pickup is None:
        for name in names:
            for e in entries:
                e["status"][col[name]] = ExperimentStatus.ERROR
        return entries, seconds
    grasped = pickup.failure != GraspFailure.NOT_GRASPED
    for j, e in enumerate(entries):
        e["pickup/grasp_force"][...] = pickup.grasp_force
        e["pickup/failure"][...] = pickup.failure[j]
        if not grasped[j]:
            e["status"][col["pickup"]] = ExperimentStatus.NOT_GRASPED
            continue
        e["pickup/slip_force"][...] = pickup.slip_force[j]
        e["pickup/slide"][...] = pickup.slide[j]
        for f in _features.FEATURE_NAMES:
            e[f"features/{f}"][...] = pickup.features[f][j]
        values = {m: float(getattr(pickup, attr)[j]) for m, attr in _PICKUP_METRICS.items()}
        if not pickup.success[j]:
            e["metrics/pickup_success"][...] = 0.0
            e["status"][col["pickup"]] = ExperimentStatus.LOST
        elif all(np.isfinite(v) for v in values.values()):
            e["metrics/pickup_success"][...] = 1.0
            for m, v in values.items():
                e[f"metrics/{m}"][...] = v
            e["status"][col["pickup"]] = ExperimentStatus.OK
        else:  # held, but a metric is not a number: nothing trustworthy was measured
            _log.warning("%s grasp %d: pickup held but metrics %s; recorded as ERROR", mesh.name, j, values)
            e["status"][col["pickup"]] = ExperimentStatus.ERROR

    # the later experiments run on the grasps that formed (a failed squeeze fails again: same problem)
    rows = np.flatnonzero(grasped & np.isfinite(pickup.slip_force) & (pickup.slip_force > 0))
    later = [n for n in names if n != "pickup"]
    for j in np.setdiff1d(np.arange(b), rows):
        for name in later:
            entries[j]["status"][col[name]] = ExperimentStatus.NOT_GRASPED
    if not later:
        return entries, seconds
    if rows.size == 0:
        seconds.update({name: 0.0 for name in later})
        return entries, seconds
    sub = ex if rows.size == b else make(rows)

    if "reorientation" in names:
        r = attempt("reorientation", rows, lambda: sub.reorientation(pickup.slip_force[rows]))
        for i, j in enumerate(rows if r is not None else []):
            e = entries[j]
            e["reorientation/held"][...] = r.held[i]
            e["reorientation/max_von_mises"][...] = r.max_von_mises[i]
            e["reorientation/failure"][...] = r.failure[i]
            c = float(r.controllability[i])
            if np.all(r.failure[i] == GraspFailure.NOT_GRASPED):
                code = ExperimentStatus.NOT_GRASPED
            elif np.isfinite(c):
                code = ExperimentStatus.OK
                e["metrics/deformation_controllability_m"][...] = c
            else:
                code = ExperimentStatus.LOST
            e["status"][col["reorientation"]] = code
    for kind in ("linear", "angular"):
        if kind not in names:
            continue
        a = attempt(kind, rows, lambda kind=kind: sub.acceleration(kind))
        for i, j in enumerate(rows if a is not None else []):
            e = entries[j]
            e[f"{kind}/threshold"][...] = a.threshold[i]
            e[f"{kind}/failure"][...] = a.failure[i]
            e[f"{kind}/solver_status"][...] = a.solver_status[i]
            v = float(a.instability[i])
            if np.isfinite(v):
                e["status"][col[kind]] = ExperimentStatus.OK
                e[f"metrics/{_INSTABILITY[kind]}"][...] = v
            else:  # no direction tested: the grasp did not form
                e["status"][col[kind]] = ExperimentStatus.NOT_GRASPED
    return entries, seconds


def _experiment_counts(path: Path) -> dict[str, dict[str, int]]:
    """Entries per ExperimentStatus name of each experiment run in the shard ``path``."""
    with h5py.File(path, "r") as f:
        if "experiments" not in f:
            return {}
        names = json.loads(f["experiments"].attrs["names"])
        status = f["experiments/status"][()]
    out = {}
    for name in names:
        codes = status[..., EXPERIMENT_NAMES.index(name)].ravel()
        out[name] = {s.name: int(np.count_nonzero(codes == s)) for s in ExperimentStatus if s != s.NOT_RUN}
    return out


def _warn_if_other_experiments(path: Path, layout: ExperimentLayout | None) -> None:
    """A finished shard is skipped: say so if it was made with other experiments than asked for now."""
    try:
        with h5py.File(path, "r") as f:
            found = tuple(json.loads(f["experiments"].attrs["names"])) if "experiments" in f else ()
            settings = f["experiments"].attrs["settings"] if "experiments" in f else None
    except (OSError, KeyError, ValueError):
        return
    wanted = () if layout is None else layout.names
    if found != wanted or (layout is not None and settings != layout.settings_json):
        _log.warning(
            "%s is finished with experiments %s (asked for %s, or other settings); it is kept as it is: "
            "overwrite=true regenerates it",
            path, list(found), list(wanted),
        )  # fmt: skip


def generate_object_shards(
    obj: str | fem.TetMesh,
    out_dir: str | Path,
    youngs_modulus: Sequence[float] = (2e5, 2e6),
    num_grasps: int = 100,
    steps: int = 50,
    max_force: float = 15.0,
    rotations_per_axis: int = 4,
    friction: float = 0.7,
    poisson_ratio: float = 0.3,
    density: float = 1000.0,
    material_model: str = "neohookean",
    shard_count: int = 1,
    shard_index: int | None = None,
    seed: int = 0,
    device=None,
    target_nodes: int = 1000,
    mesher: str = "ftetwild",
    category: str = "cuboid",
    source: str = "primitive",
    solver_options: fem.SolverOptions | None = None,
    reject_inverted: bool = True,
    overwrite: bool = False,
    config_text: str = "",
    progress: bool = False,
    gripper: ParallelJawGripper = FRANKA_HAND,
    experiments: Sequence[str] = (),
    experiment_settings: ExperimentSettings | Mapping | None = None,
    experiment_options: fem.SolverOptions | None = None,
    directions_per_solver: int = 1,
    moduli_per_solver: int = 1,
    stream_slots: int = 0,
    moduli_per_object: int | None = None,
    all_moduli_objects: Sequence[str] = (),
) -> list[ShardResult]:
    """Simulate the squeeze ramps (and optionally the DefGraspSim experiments) of one object and write its
    grasp shard(s).

    Args:
        obj: registry object name (meshed with ``mesher`` to about ``target_nodes`` vertices, cached),
            or a :class:`~defgraspnets.fem.TetMesh` (its ``name`` names the shard; ``category`` and
            ``source`` label it).
        out_dir: directory of the shards ``<object>__shard<i>of<n>.h5``.
        youngs_modulus: the moduli [Pa] (all K in every shard, unless ``moduli_per_object``).
            poisson_ratio, density [kg/m^3]: shared.
        material_model: constitutive energy (:class:`~defgraspnets.fem.Material`): "neohookean" (default;
            no element can invert, so soft moduli converge at 15 N) or "corotated" (the thesis's FleX
            model; soft objects invert and fail there, e.g. E = 1e4 Pa past 7 N on a 50 mm box).
        num_grasps: G antipodal grasps sampled on the object (``seed``), split over ``shard_count`` shards.
        rotations_per_axis: approach directions about each sampled grasp axis (thesis: 4; 1 gives G
            distinct axes, i.e. G pairs of contact points instead of about G / 4).
        steps: S ramp steps; ``max_force``: final total normal grasp force F_g [N].
        friction: Coulomb coefficient of the pads (and of the sampler's friction-cone test).
        shard_index: write only this shard (multirun / array jobs); None writes all ``shard_count``.
        device: Warp device ("cpu", "cuda", ...; None = Warp's default).
        solver_options: FEM settings (default :func:`~defgraspnets.grasp.squeeze.squeeze_solver_options`).
            Recorded in each shard with the experiments' (:func:`solver_settings`): an unfinished shard made
            with other settings is not resumed (ValueError naming them; ``overwrite`` starts it over).
        reject_inverted: mark converged problems with inverted tets as failed (:data:`STATUS_INVERTED`),
            and those whose object passes through itself at the last step (:data:`STATUS_SELF_INTERSECTING`).
        overwrite: regenerate finished shards and discard unfinished ones made with other settings.
        config_text: provenance (YAML) stored in the shard's ``config`` attribute.
        progress: tqdm progress bars (moduli and ramp steps).
        experiments: DefGraspSim experiments to run per ``(k, g)`` as well, any of ``("pickup",
            "reorientation", "linear", "angular")`` (pickup always runs with any; :func:`run_experiments`);
            written to the shard's ``/experiments`` group. ``()``: squeeze ramps only.
        experiment_settings: :class:`ExperimentSettings` (or a mapping of its fields but ``friction``); their
            friction is ``friction``. None: the defaults (thesis values).
        experiment_options: FEM settings of the experiments (default :func:`experiment_solver_options`).
        directions_per_solver: the acceleration pairs stream through grasps x this many problems
            (:class:`GraspExperiments`).
        moduli_per_solver: the squeeze ramps of this many moduli run as one batch (one problem per grasp and
            modulus, each with its own material): fewer, larger launches on a GPU. A problem's ramp does not
            depend on its batch with an exact linear solver ("direct", "dense"), so the data are the same;
            the batch runs in lockstep, so its slowest ramp holds the others. 1: one batch per modulus.
            On the 2-core CPU it does not pay (cuboid_50x50x50, 8 grasps x 2 moduli, 5 steps, AMG-CG: 30.3
            and 43.5 s with 2 against 27.8 and 28.7 s with 1: a Krylov tolerance is shared by the batch); it
            is meant for GPUs: on one H200, 48 grasps x 4 moduli x 10 steps of cuboid_50x50x50, 13.3 s with
            4 against 22.8 s with 1 (``benchmarks/grasp_datagen_moduli_per_solver_h200_s30.json``).
        stream_slots: > 0: all the shard's squeeze ramps (every modulus and grasp) flow through a batch of
            this many problems instead (:func:`~defgraspnets.grasp.squeeze.squeeze_stream`): a problem that
            finished its ramp takes the next one, so a slow ramp holds up no batch. The same data with an
            exact linear solver; each ramp is written as soon as it is done (with ``experiments``: each
            modulus once all its ramps are). ``moduli_per_solver`` is then unused. 0: batches. On one
            H100 128 slots tie ``moduli_per_solver=4`` (400 ramps of 50 steps: 38.5-40.4 against
            39.3-41.9 s; ``benchmarks/grasp_datagen_stream_h100_s32.json``).
        moduli_per_object: simulate only this many of ``youngs_modulus``, drawn per object (the thesis's
            count: 1), except for the objects in ``all_moduli_objects``; None: all (:func:`object_moduli`).

    Returns:
        One :class:`ShardResult` per shard handled.

    Raises:
        ValueError: unknown object or experiment, non-positive moduli / force / density / friction,
            steps < 1, bad experiment settings, ...
    """
    moduli = _check_inputs(
        youngs_modulus, num_grasps, steps, max_force, friction, poisson_ratio, density, shard_count
    )
    if material_model not in fem.MATERIAL_MODELS:
        raise ValueError(f"material_model must be one of {fem.MATERIAL_MODELS}, got {material_model!r}")
    steps, num_grasps, shard_count = int(steps), int(num_grasps), int(shard_count)
    if shard_index is not None and not 0 <= shard_index < shard_count:
        raise ValueError(f"shard_index {shard_index} outside [0, {shard_count})")
    names = resolve_experiments(experiments)
    settings = resolve_experiment_settings(experiment_settings, friction)
    if not (isinstance(directions_per_solver, (int, np.integer)) and directions_per_solver >= 1):
        raise ValueError(f"directions_per_solver must be an integer >= 1, got {directions_per_solver!r}")
    if not (isinstance(moduli_per_solver, (int, np.integer)) and moduli_per_solver >= 1):
        raise ValueError(f"moduli_per_solver must be an integer >= 1, got {moduli_per_solver!r}")
    if not (isinstance(stream_slots, (int, np.integer)) and stream_slots >= 0):
        raise ValueError(f"stream_slots must be an integer >= 0 (0: batches), got {stream_slots!r}")
    object_moduli("", moduli, moduli_per_object)  # a bad count fails before the object is meshed
    layout = experiment_layout(names, settings) if names else None
    out_dir = Path(out_dir)
    check_output_dir(out_dir)  # before the object is meshed and its grasps simulated
    if isinstance(obj, fem.TetMesh):
        mesh = obj
    elif isinstance(obj, str):
        mesh, category, source = load_object_mesh(obj, target_nodes=target_nodes, mesher=mesher)
    else:
        raise ValueError(f"obj must be an object name or a TetMesh, got {type(obj).__name__}")
    name = mesh.name
    moduli = np.asarray(object_moduli(name, moduli, moduli_per_object, seed, all_moduli_objects))
    indices = range(shard_count) if shard_index is None else [int(shard_index)]
    paths = {i: out_dir / shard_file_name(name, i, shard_count) for i in indices}
    if not overwrite and all(p.exists() for p in paths.values()):
        _log.info("%s: all %d shard(s) already finished, nothing to do", name, len(paths))
        for p in paths.values():
            _warn_if_other_experiments(p, layout)
        return [ShardResult(p, -1, -1, 0.0, skipped=True) for p in paths.values()]

    k = len(moduli)
    record = ObjectRecord(
        name, category, source, mesh.points, mesh.tets, mesh.surface_faces,
        moduli, np.full(k, float(poisson_ratio)), np.full(k, float(density)), material_model,
    )  # fmt: skip
    fingers = gripper_fingers(gripper)
    all_grasps = sample_antipodal_grasps(
        mesh,
        num_grasps=num_grasps,
        gripper=gripper,
        friction_coefficient=friction,
        rotations_per_axis=rotations_per_axis,
        seed=seed,
    )
    if len(all_grasps) < shard_count:
        raise ValueError(
            f"{name}: only {len(all_grasps)} grasps could be sampled, fewer than shard_count={shard_count}"
        )
    # the defaults resolved once: the settings a shard records are the ones its ramps and experiments use
    solver_options = solver_options or squeeze_solver_options()
    experiment_options = experiment_options or experiment_solver_options()
    ramps = _Ramps(
        mesh, friction, max_force, steps, device, solver_options, reject_inverted, progress, gripper
    )
    settings_record = solver_settings(solver_options, experiment_options if names else None)
    results = []
    for i, path in paths.items():
        if path.exists() and not overwrite:
            _log.info("%s exists, skipping", path)
            _warn_if_other_experiments(path, layout)
            results.append(ShardResult(path, -1, -1, 0.0, skipped=True))
            continue
        start = time.perf_counter()
        grasps = all_grasps[shard_grasp_indices(len(all_grasps), i, shard_count)]
        fpose = finger_contact_poses(grasps, gripper)  # (G, 2, 4, 4)
        closing = fpose[:, :, :3, :3] @ fingers.closing_axis  # (G, 2, 3)
        writer = GraspShardWriter.create(
            path, record, fingers, grasps.poses, fpose, closing, steps,
            generator_version=f"defgraspnets {__version__}", config=config_text, overwrite=overwrite,
            experiments=layout, solver_settings=settings_record,
        )  # fmt: skip
        try:
            pending = writer.pending()
            if len(pending) < k * len(grasps):
                _log.info(
                    "%s: resuming, %d of %d entries left", writer.partial_path, len(pending), k * len(grasps)
                )
            todo = {kk: [g for k2, g in pending if k2 == kk] for kk in range(k)}
            todo = {kk: gs for kk, gs in todo.items() if gs}
            materials = {
                kk: fem.Material(
                    float(moduli[kk]), float(poisson_ratio), float(density), model=material_model
                )
                for kk in todo
            }
            fill = _ShardFill(
                writer, ramps, grasps, todo, materials, moduli, layout, names, settings, experiment_options,
                directions_per_solver,
            )  # fmt: skip
            if progress:
                from tqdm.auto import tqdm

                fill.bar = tqdm(total=len(todo), desc=f"{name} shard {i + 1}/{shard_count}", unit="E")
            if stream_slots:
                fill.streamed(int(stream_slots))
            else:
                fill.in_batches(moduli_per_solver)
            if fill.bar is not None:
                fill.bar.close()
            final = writer.finalize()
        except BaseException:
            writer.close()
            raise
        with h5py.File(final, "r") as f:
            solved = int(np.count_nonzero(f["ramp/status"][()] == STATUS_SOLVED))
        seconds = time.perf_counter() - start
        result = ShardResult(final, solved, k * len(grasps), seconds, experiments=_experiment_counts(final))
        summary = f"; experiments: {result.experiment_summary()}" if result.experiments else ""
        _log.info("wrote %s: %d/%d solved in %.1f s%s", final, solved, k * len(grasps), seconds, summary)
        results.append(result)
    return results


# ---------------------------------------------------------------------------------------------- timing
def _number(v):
    v = float(v)
    return v if np.isfinite(v) else None


def time_grasp_experiments(
    mesh: fem.TetMesh,
    grasps: GraspSet,
    material: fem.Material,
    settings: ExperimentSettings,
    names=EXPERIMENT_NAMES,
    steps: int = 50,
    max_force: float = 15.0,
    device=None,
    squeeze_options: fem.SolverOptions | None = None,
    experiment_options: fem.SolverOptions | None = None,
    directions_per_solver: int = 1,
    gripper: ParallelJawGripper = FRANKA_HAND,
    warmup: bool = True,
) -> dict:
    """Wall times of what the generator computes for one object and one modulus: the squeeze ramp
    (``steps`` steps to ``max_force``, :func:`generate_object_shards`) and each experiment of
    :func:`run_experiments`, all batched over the B ``grasps`` as the generator batches them.

    ``warmup`` first runs a one-step squeeze and a one-step pickup and angular test of one grasp (loads the
    Warp kernels; its time is reported apart). Returns a JSON-ready dict: per stage ``seconds``,
    ``grasps_per_s`` and the per-grasp status (ramp: failure code, 0 solved; experiments:
    :class:`ExperimentStatus` names) and metrics.
    """
    from defgraspnets.data.grasp_schema import METRIC_EXPERIMENT

    names = resolve_experiments(names)
    b = len(grasps)
    out: dict = {"grasps": b}
    ramps = _Ramps(mesh, settings.friction, max_force, steps, device, squeeze_options, True, False, gripper)
    if warmup:
        start = time.perf_counter()
        one = grasps[np.array([0])]
        _squeeze_modulus(dataclasses.replace(ramps, steps=1), one, material)
        quick = dataclasses.replace(
            settings, squeeze_steps=1, pickup_steps=1, acceleration_steps=1, num_directions=2
        )
        ex = GraspExperiments(mesh, one, material, quick, gripper=gripper, device=device,
                              options=experiment_options or experiment_solver_options())  # fmt: skip
        ex.pickup()
        ex.acceleration("angular", [[0.0, 0.0, 1.0]])
        out["seconds_warmup"] = time.perf_counter() - start
    start = time.perf_counter()
    ramp = _squeeze_modulus(ramps, grasps, material)
    seconds = time.perf_counter() - start
    out["squeeze_ramp"] = {
        "steps": int(steps),
        "max_force_n": float(max_force),
        "seconds": seconds,
        "grasps_per_s": b / seconds,
        "status_per_grasp": ramp["status"].astype(int).tolist(),
        "solved": int(np.count_nonzero(ramp["status"] == STATUS_SOLVED)),
    }
    out["experiments"] = {}
    if not names:
        return out
    entries, times = run_experiments(
        mesh, grasps, material, settings, names, device, experiment_options, gripper, directions_per_solver
    )
    problems = {
        "pickup": 1,
        "reorientation": settings.num_directions,
        "linear": settings.num_directions,
        "angular": settings.num_directions,
    }
    for name in names:
        i = EXPERIMENT_NAMES.index(name)
        codes = [ExperimentStatus(int(e["status"][i])) for e in entries]
        metrics = [m for m, exp in METRIC_EXPERIMENT.items() if exp == name]
        t = times.get(name, 0.0)
        out["experiments"][name] = {
            "seconds": t,
            "grasps_per_s": b / t if t > 0 else None,
            "problems_per_grasp": problems[name],  # FEM problems per grasp in the batch (directions / axes)
            "status_per_grasp": [c.name for c in codes],
            "ok": sum(c == ExperimentStatus.OK for c in codes),
            "metrics_per_grasp": {m: [_number(e[f"metrics/{m}"]) for e in entries] for m in metrics},
        }
    return out
