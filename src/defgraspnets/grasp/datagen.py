"""The grasp dataset generator (thesis §7.4, DefGraspSim ch. 6): squeeze ramps on the FEM engine written
as HDF5 grasp shards (schema ``defgraspnets.grasps/1``, :mod:`defgraspnets.data.grasp_schema`).

For one object and K Young's moduli ``E_k``::

    mesh   = tet mesh of the object (registry name, cached on disk) or a given TetMesh
    grasps = G antipodal Franka grasps (seeded), split into ``shard_count`` contiguous shards
    for each shard, for each E_k:
        one batched quasi-static problem per grasp of the shard: pads at first contact, total normal
        grasp force F_g ramped 0 -> F_max in S equal steps, zero gravity
        per step s: von Mises stress sigma (N,), displacement d = x - X (N, 3), F_g, finger travel

Every ``(k, g)`` entry is written with status 0 only if its problem converged at *every* step (and, by
default, has no inverted tet); otherwise its fields are NaN and its status is the first failure code
(:class:`~defgraspnets.fem.SolveStatus` 1-3, or :data:`STATUS_INVERTED`). Failed entries are never
training data (thesis: unstable grasps are excluded from D).

A shard is written through :class:`~defgraspnets.data.grasp_schema.GraspShardWriter`: a killed run leaves
``<name>.partial.h5``; running the generator again with the same settings resumes it and simulates only
the grasps not written yet. Finished shards (``<name>.h5``) are skipped unless ``overwrite``. Independent
shards (``shard_index`` = i of ``shard_count``) and objects are the unit of scale-out (Hydra multirun).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from defgraspnets import __version__, fem
from defgraspnets.data.grasp_schema import (
    STATUS_SOLVED,
    GraspShardWriter,
    GripperFingers,
    ObjectRecord,
    shard_file_name,
)

from .gripper import FRANKA_HAND, ParallelJawGripper
from .sampler import GraspSet, sample_antipodal_grasps
from .squeeze import GRIP_DOF, finger_contact_poses, make_squeeze_solver, squeeze_ramp

__all__ = [
    "STATUS_INVERTED",
    "ShardResult",
    "generate_object_shards",
    "gripper_fingers",
    "load_object_mesh",
    "resolve_object_mesh",
    "shard_grasp_indices",
    "structured_box",
]

STATUS_INVERTED = 4  # converged, but with inverted tets (det F <= 0): not a physical answer
_log = logging.getLogger(__name__)


@dataclass
class ShardResult:
    """Outcome of one shard: its final path, solved / total ``(k, g)`` entries, wall time [s]."""

    path: Path
    solved: int
    total: int
    seconds: float
    skipped: bool = False  # the shard was already finished


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
        ValueError: neither a registry name nor a file.
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

        from defgraspnets.objects import tetrahedralize

        surface = trimesh.load(path, force="mesh")
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


def _check_inputs(moduli, num_grasps, steps, max_force, friction, poisson_ratio, density, shard_count):
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
def _squeeze_modulus(
    mesh: fem.TetMesh,
    grasps: GraspSet,
    material: fem.Material,
    friction: float,
    max_force: float,
    steps: int,
    device,
    options,
    reject_inverted: bool,
    progress: bool,
) -> dict[str, np.ndarray]:
    """One batched squeeze ramp; per-grasp fields (NaN where failed) and status (first failure code)."""
    b, n = len(grasps), mesh.num_vertices
    out = {
        "force": np.full((b, steps), np.nan),
        "von_mises": np.full((b, steps, n), np.nan, dtype=np.float32),
        "displacement": np.full((b, steps, n, 3), np.nan, dtype=np.float32),
        "finger_travel": np.full((b, steps, 2), np.nan),
        "status": np.zeros(b, dtype=np.int8),
    }
    solver = make_squeeze_solver(mesh, grasps, material, friction, device=device, options=options)
    status = out["status"]

    def record(s: int, _force: float, eq: fem.Equilibrium) -> None:
        code = np.where(eq.converged, STATUS_SOLVED, eq.status).astype(np.int8)
        if reject_inverted:
            code = np.where((code == STATUS_SOLVED) & (eq.inverted_tets > 0), STATUS_INVERTED, code)
        newly = (status == STATUS_SOLVED) & (code != STATUS_SOLVED)
        status[newly] = code[newly]
        ok = status == STATUS_SOLVED
        out["force"][ok, s] = eq.dof_force[GRIP_DOF][ok]
        out["von_mises"][ok, s] = eq.von_mises[ok]
        out["displacement"][ok, s] = eq.displacement[ok]
        # both pads share the grip dof: each travels this far along its own closing direction
        out["finger_travel"][ok, s] = eq.travel[GRIP_DOF][ok, None]

    squeeze_ramp(solver, max_force, steps, progress=progress, on_step=record)
    return out


def generate_object_shards(
    obj: str | fem.TetMesh,
    out_dir: str | Path,
    youngs_modulus: Sequence[float] = (2e5, 2e6),
    num_grasps: int = 100,
    steps: int = 50,
    max_force: float = 15.0,
    friction: float = 0.7,
    poisson_ratio: float = 0.3,
    density: float = 1000.0,
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
) -> list[ShardResult]:
    """Simulate the squeeze ramps of one object and write its grasp shard(s).

    Args:
        obj: registry object name (meshed with ``mesher`` to about ``target_nodes`` vertices, cached),
            or a :class:`~defgraspnets.fem.TetMesh` (its ``name`` names the shard; ``category`` and
            ``source`` label it).
        out_dir: directory of the shards ``<object>__shard<i>of<n>.h5``.
        youngs_modulus: the K moduli [Pa] (all in every shard). poisson_ratio, density [kg/m^3]: shared.
        num_grasps: G antipodal grasps sampled on the object (``seed``), split over ``shard_count`` shards.
        steps: S ramp steps; ``max_force``: final total normal grasp force F_g [N].
        friction: Coulomb coefficient of the pads (and of the sampler's friction-cone test).
        shard_index: write only this shard (multirun / array jobs); None writes all ``shard_count``.
        device: Warp device ("cpu", "cuda", ...; None = Warp's default).
        solver_options: FEM settings (default :func:`~defgraspnets.grasp.squeeze.squeeze_solver_options`).
        reject_inverted: mark converged problems with inverted tets as failed (:data:`STATUS_INVERTED`).
        overwrite: regenerate finished shards and discard unfinished ones made with other settings.
        config_text: provenance (YAML) stored in the shard's ``config`` attribute.
        progress: tqdm progress bars (moduli and ramp steps).

    Returns:
        One :class:`ShardResult` per shard handled.

    Raises:
        ValueError: unknown object, non-positive moduli / force / density / friction, steps < 1, ...
    """
    moduli = _check_inputs(
        youngs_modulus, num_grasps, steps, max_force, friction, poisson_ratio, density, shard_count
    )
    steps, num_grasps, shard_count = int(steps), int(num_grasps), int(shard_count)
    if shard_index is not None and not 0 <= shard_index < shard_count:
        raise ValueError(f"shard_index {shard_index} outside [0, {shard_count})")
    out_dir = Path(out_dir)
    if isinstance(obj, fem.TetMesh):
        mesh = obj
    elif isinstance(obj, str):
        mesh, category, source = load_object_mesh(obj, target_nodes=target_nodes, mesher=mesher)
    else:
        raise ValueError(f"obj must be an object name or a TetMesh, got {type(obj).__name__}")
    name = mesh.name
    indices = range(shard_count) if shard_index is None else [int(shard_index)]
    paths = {i: out_dir / shard_file_name(name, i, shard_count) for i in indices}
    if not overwrite and all(p.exists() for p in paths.values()):
        _log.info("%s: all %d shard(s) already finished, nothing to do", name, len(paths))
        return [ShardResult(p, -1, -1, 0.0, skipped=True) for p in paths.values()]

    k = len(moduli)
    record = ObjectRecord(
        name, category, source, mesh.points, mesh.tets, mesh.surface_faces,
        moduli, np.full(k, float(poisson_ratio)), np.full(k, float(density)),
    )  # fmt: skip
    fingers = gripper_fingers(gripper)
    all_grasps = sample_antipodal_grasps(
        mesh, num_grasps=num_grasps, gripper=gripper, friction_coefficient=friction, seed=seed
    )
    if len(all_grasps) < shard_count:
        raise ValueError(
            f"{name}: only {len(all_grasps)} grasps could be sampled, fewer than shard_count={shard_count}"
        )
    results = []
    for i, path in paths.items():
        if path.exists() and not overwrite:
            _log.info("%s exists, skipping", path)
            results.append(ShardResult(path, -1, -1, 0.0, skipped=True))
            continue
        start = time.perf_counter()
        grasps = all_grasps[shard_grasp_indices(len(all_grasps), i, shard_count)]
        fpose = finger_contact_poses(grasps, gripper)  # (G, 2, 4, 4)
        closing = fpose[:, :, :3, :3] @ fingers.closing_axis  # (G, 2, 3)
        writer = GraspShardWriter.create(
            path, record, fingers, grasps.poses, fpose, closing, steps,
            generator_version=f"defgraspnets {__version__}", config=config_text, overwrite=overwrite,
        )  # fmt: skip
        try:
            pending = writer.pending()
            if len(pending) < k * len(grasps):
                _log.info(
                    "%s: resuming, %d of %d entries left", writer.partial_path, len(pending), k * len(grasps)
                )
            todo = {kk: [g for k2, g in pending if k2 == kk] for kk in range(k)}
            todo = {kk: gs for kk, gs in todo.items() if gs}
            bar = None
            if progress:
                from tqdm.auto import tqdm

                bar = tqdm(total=len(todo), desc=f"{name} shard {i + 1}/{shard_count}", unit="E")
            for kk, gs in todo.items():
                material = fem.Material(float(moduli[kk]), float(poisson_ratio), float(density))
                res = _squeeze_modulus(
                    mesh, grasps[np.array(gs)], material, friction, max_force, steps, device,
                    solver_options, reject_inverted, progress,
                )  # fmt: skip
                for j, g in enumerate(gs):
                    writer.write(
                        kk, g, res["force"][j], res["von_mises"][j], res["displacement"][j],
                        res["finger_travel"][j], status=int(res["status"][j]),
                    )  # fmt: skip
                codes = res["status"][res["status"] != STATUS_SOLVED]
                if codes.size:
                    _log.warning(
                        "%s E=%.3g Pa: %d of %d squeeze ramps failed (status %s); stored as failed",
                        name, moduli[kk], codes.size, len(gs), np.unique(codes).tolist(),
                    )  # fmt: skip
                if bar is not None:
                    bar.update(1)
            if bar is not None:
                bar.close()
            final = writer.finalize()
        except BaseException:
            writer.close()
            raise
        with h5py.File(final, "r") as f:
            solved = int(np.count_nonzero(f["ramp/status"][()] == STATUS_SOLVED))
        seconds = time.perf_counter() - start
        _log.info("wrote %s: %d/%d solved in %.1f s", final, solved, k * len(grasps), seconds)
        results.append(ShardResult(final, solved, k * len(grasps), seconds))
    return results
