"""HDF5 grasp shards, schema ``defgraspnets.grasps/1``: the contract between the grasp-data generator
(DefGraspSim squeeze ramps on the FEM engine) and the learning code.

One file per object shard, named ``<object>__shard<i>of<n>.h5``. All quantities are SI (m, N, Pa, kg/m^3).
``K`` moduli, ``G`` grasps, ``S`` ramp steps, ``N`` object vertices, ``M`` tets, ``F`` surface faces,
``V`` / ``T`` finger-pad vertices / triangles::

    /                          attrs: schema, generator_version, object_name, object_category,
                                      object_source ("primitive" | "real"), config (YAML), created (ISO),
                                      solver_settings (JSON; optional: shards before session 44 lack it)
    /object/points             (N, 3)        float64  rest vertex positions X [m], object frame
    /object/tets               (M, 4)        int64
    /object/surface_faces      (F, 3)        int64    outward oriented
    /material/youngs_modulus   (K,)          float64  E [Pa]
    /material/poisson_ratio    (K,)          float64
    /material/density          (K,)          float64  [kg/m^3]
                               attr model: constitutive energy of fem.Material ("corotated" when absent)
    /gripper/finger_vertices   (V, 3)        float64  finger-pad surface, finger frame [m] (both fingers)
    /gripper/finger_faces      (T, 3)        int64    attr closing_axis_in_finger_frame (3,)
    /grasps/pose               (G, 4, 4)     float64  open-gripper pose in the object frame
    /grasps/finger_contact_pose (G, 2, 4, 4) float64  finger pose at first contact: v -> R v + t
    /grasps/closing_direction  (G, 2, 3)     float64  unit closing direction of each finger
    /ramp/force                (K, G, S)     float64  total normal grasp force F_g (both fingers) [N]
    /ramp/von_mises            (K, G, S, N)  float32  per-vertex von Mises stress [Pa]
    /ramp/displacement         (K, G, S, N, 3) float32 per-vertex displacement x - X [m]
    /ramp/finger_travel        (K, G, S, 2)  float64  travel of each finger along its closing direction
                                                      from the first-contact pose [m]
    /ramp/status               (K, G)        int8     0 = solved at every step; > 0 = failure code

Entries with ``status != 0`` are never training data; their fields may be NaN.

**Optional group /experiments** (an addition within schema ``/1``: readers of ``/1`` that predate it ignore
it, and shards without it stay valid; :attr:`GraspShard.has_experiments`). Written when the generator runs
the DefGraspSim experiments (thesis §6.4-6.5, :mod:`defgraspnets.grasp.experiments`) for every ``(k, g)``;
``D`` acceleration directions, ``A`` reorientation axes, ``J`` reorientation angles, ``X`` = 4 experiments
in the order :data:`EXPERIMENT_NAMES` = (pickup, reorientation, linear, angular)::

    /experiments               attrs: names (JSON list of the experiments run), settings (JSON of
                                      ExperimentSettings)
    /experiments/directions    (D, 3)        float64  linear / angular test directions, gripper frame
    /experiments/axes          (A, 3)        float64  reorientation axes, world frame
    /experiments/angles        (J,)          float64  reorientation angles [rad]
    /experiments/status        (K, G, X)     int8     ExperimentStatus per experiment: 0 OK, 1 NOT_RUN,
                                                      2 NOT_GRASPED, 3 LOST, 4 ERROR (see the enum)
    /experiments/metrics/<m>   (K, G)        float64  the 7 metrics of §6.5, m in METRIC_NAMES (units in
                                                      the name; pickup_success is 1.0 / 0.0)
    /experiments/features/<f>  (K, G)        float64  the 7 features of Table 6.2, f in FEATURE_NAMES
    /experiments/pickup/grasp_force (K, G)   float64  F_p = s m g / mu [N]
    /experiments/pickup/slip_force  (K, G)   float64  F_slip of the reorientation [N]
    /experiments/pickup/slide       (K, G)   float64  pad slide at the end of the pickup [m]
    /experiments/pickup/failure     (K, G)   int8     GraspFailure of the pickup (0 held)
    /experiments/reorientation/held          (K, G, A, J) bool     held in that state (and all before it)
    /experiments/reorientation/max_von_mises (K, G, A, J) float64  largest element stress [Pa]; NaN not held
    /experiments/reorientation/failure       (K, G, A)    int8     GraspFailure per axis
    /experiments/<linear|angular>/threshold     (K, G, D) float64  loss-of-grasp acceleration per direction
                                                       [m/s^2 | rad/s^2]; the test's limit if never lost
    /experiments/<linear|angular>/failure       (K, G, D) int8     GraspFailure per direction (0: limit held)
    /experiments/<linear|angular>/solver_status (K, G, D) int8     fem.SolveStatus at the end of the ramp

A metric is NaN wherever its experiment did not measure it, never a made-up number, and the experiment's
status says why: NOT_RUN (not selected), NOT_GRASPED (the squeeze to the experiment's grasp force found no
equilibrium: nothing measured, features NaN too), LOST (the grasp was lost before the metric's state: a failed
pickup has ``pickup_success`` 0.0 and NaN stress / deformation / strain energy, as in the thesis; a
reorientation that holds no state has NaN controllability), ERROR (the experiment raised; logged). Codes
-1 (int8) and NaN mark directions / axes an experiment did not test. The pickup metrics belong to ``pickup``,
``deformation_controllability_m`` to ``reorientation``, the instabilities to ``linear`` / ``angular``.

Writing (:class:`GraspShardWriter`) is incremental, resumable and atomic: the static groups are written to
``<name>.partial.h5`` when the shard is created, each ``(k, g)`` squeeze result (with its experiment
results, when the shard has ``/experiments``) is written and flushed as it arrives and then marked in
``/progress/done`` (K, G); :meth:`GraspShardWriter.finalize` checks that every
entry is done, drops ``/progress``, fsyncs and renames the file to ``<name>.h5``. A killed generator never
leaves a final file behind, and re-opening the partial file resumes at the first undone entry. Reading
(:class:`GraspShard`) validates the schema version, every dataset's presence, shape and dtype, and raises
:class:`ShardSchemaError` naming the file and the offending dataset.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from enum import IntEnum
from pathlib import Path

import h5py
import numpy as np

from defgraspnets.fem.material import MATERIAL_MODELS
from defgraspnets.grasp.features import FEATURE_NAMES  # the 7 features of Table 6.2 (one definition)

__all__ = [
    "EXPERIMENT_NAMES",
    "FEATURE_NAMES",
    "METRIC_NAMES",
    "SCHEMA_VERSION",
    "STATUS_SOLVED",
    "ExperimentLayout",
    "ExperimentStatus",
    "GraspShard",
    "GraspShardWriter",
    "GripperFingers",
    "ObjectRecord",
    "ShardSchemaError",
    "parse_shard_name",
    "settings_difference",
    "shard_file_name",
]

SCHEMA_VERSION = "defgraspnets.grasps/1"
STATUS_SOLVED = 0
_COMPRESSION = "lzf"
_SHARD_NAME = re.compile(r"^(?P<object>.+)__shard(?P<index>\d+)of(?P<count>\d+)\.h5$")
_OBJECT_SOURCES = ("primitive", "real")


# the optional /experiments group (module docstring); names as in defgraspnets.grasp (metrics, features)
EXPERIMENT_NAMES = ("pickup", "reorientation", "linear", "angular")
METRIC_NAMES = (
    "pickup_success",
    "max_von_mises_stress_pa",
    "max_deformation_m",
    "strain_energy_j",
    "linear_instability_m_s2",
    "angular_instability_rad_s2",
    "deformation_controllability_m",
)
# the experiment that measures each metric
METRIC_EXPERIMENT = {
    "pickup_success": "pickup",
    "max_von_mises_stress_pa": "pickup",
    "max_deformation_m": "pickup",
    "strain_energy_j": "pickup",
    "linear_instability_m_s2": "linear",
    "angular_instability_rad_s2": "angular",
    "deformation_controllability_m": "reorientation",
}
_UNTESTED = -1  # int8 fill of failure / solver-status codes of directions and axes not tested


class ExperimentStatus(IntEnum):
    """Outcome of one experiment of one ``(k, g)`` entry (``/experiments/status``)."""

    OK = 0  # ran; its metrics are measured values
    NOT_RUN = 1  # not selected for this shard: its metrics are NaN
    NOT_GRASPED = 2  # the squeeze to the experiment's grasp force found no equilibrium: nothing measured
    LOST = 3  # the grasp was lost before the metric's state (failed pickup; reorientation holding no state)
    ERROR = 4  # the experiment raised an error (logged by the generator): nothing measured


class ShardSchemaError(ValueError):
    """A grasp shard does not follow schema ``defgraspnets.grasps/1`` (names the file and the dataset)."""


def shard_file_name(object_name: str, shard_index: int, shard_count: int) -> str:
    """``<object>__shard<i>of<n>.h5`` (``0 <= i < n``)."""
    if not 0 <= shard_index < shard_count:
        raise ValueError(f"shard index {shard_index} outside [0, {shard_count})")
    if "/" in object_name or not object_name:
        raise ValueError(f"object name {object_name!r} cannot be used in a file name")
    return f"{object_name}__shard{shard_index}of{shard_count}.h5"


def parse_shard_name(path: str | Path) -> tuple[str, int, int]:
    """``(object_name, shard_index, shard_count)`` from a shard file name."""
    m = _SHARD_NAME.match(Path(path).name)
    if m is None:
        raise ShardSchemaError(f"{path}: file name is not of the form <object>__shard<i>of<n>.h5")
    return m["object"], int(m["index"]), int(m["count"])


# ---------------------------------------------------------------------------------------------- records
@dataclass
class ObjectRecord:
    """The deformable object of a shard: rest mesh and the K materials it is squeezed with.

    Attributes:
        name, category, source: identity (``source`` is ``"primitive"`` or ``"real"``).
        points: (N, 3) rest positions [m]. tets: (M, 4). surface_faces: (F, 3) outward.
        youngs_modulus, poisson_ratio, density: (K,) each [Pa], [-], [kg/m^3].
        material_model: the FEM's constitutive energy (:data:`defgraspnets.fem.MATERIAL_MODELS`).
    """

    name: str
    category: str
    source: str
    points: np.ndarray
    tets: np.ndarray
    surface_faces: np.ndarray
    youngs_modulus: np.ndarray
    poisson_ratio: np.ndarray
    density: np.ndarray
    material_model: str = "corotated"

    def __post_init__(self):
        if self.material_model not in MATERIAL_MODELS:
            raise ValueError(
                f"object {self.name!r}: material_model must be one of {MATERIAL_MODELS}, "
                f"got {self.material_model!r}"
            )
        self.points = np.asarray(self.points, dtype=np.float64)
        self.tets = np.asarray(self.tets, dtype=np.int64)
        self.surface_faces = np.asarray(self.surface_faces, dtype=np.int64)
        self.youngs_modulus = np.atleast_1d(np.asarray(self.youngs_modulus, dtype=np.float64))
        self.poisson_ratio = np.atleast_1d(np.asarray(self.poisson_ratio, dtype=np.float64))
        self.density = np.atleast_1d(np.asarray(self.density, dtype=np.float64))
        if self.source not in _OBJECT_SOURCES:
            raise ValueError(
                f"object {self.name!r}: source must be one of {_OBJECT_SOURCES}, got {self.source!r}"
            )
        k = len(self.youngs_modulus)
        if len(self.poisson_ratio) != k or len(self.density) != k:
            raise ValueError(
                f"object {self.name!r}: youngs_modulus, poisson_ratio and density must have length K; got "
                f"{k}, {len(self.poisson_ratio)}, {len(self.density)}"
            )
        if np.any(~np.isfinite(self.youngs_modulus)) or np.any(self.youngs_modulus <= 0):
            raise ValueError(f"object {self.name!r}: Young's moduli must be finite and positive")

    @property
    def num_moduli(self) -> int:
        return len(self.youngs_modulus)


@dataclass
class GripperFingers:
    """The finger-pad surface mesh shared by both fingers, in the finger frame.

    Attributes:
        vertices: (V, 3) [m]. faces: (T, 3). closing_axis: (3,) unit closing axis in the finger frame.
    """

    vertices: np.ndarray
    faces: np.ndarray
    closing_axis: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))

    def __post_init__(self):
        self.vertices = np.asarray(self.vertices, dtype=np.float64)
        self.faces = np.asarray(self.faces, dtype=np.int64)
        self.closing_axis = np.asarray(self.closing_axis, dtype=np.float64).reshape(3)

    def vertices_at(self, pose: np.ndarray) -> np.ndarray:
        """(..., V, 3) vertices in the object frame for finger poses ``pose`` (..., 4, 4): ``R v + t``."""
        pose = np.asarray(pose)
        return np.einsum("...ij,vj->...vi", pose[..., :3, :3], self.vertices) + pose[..., None, :3, 3]


@dataclass
class ExperimentLayout:
    """What a shard's ``/experiments`` group holds besides the per-entry results: the experiments run, their
    settings, and the directions they test (module docstring).

    Attributes:
        names: the experiments run, a subset of :data:`EXPERIMENT_NAMES` in that order.
        settings: ``ExperimentSettings`` as a JSON-ready dict (stored as JSON).
        directions: (D, 3) linear / angular test directions, gripper frame.
        axes: (A, 3) reorientation axes, world frame. angles: (J,) reorientation angles [rad].
    """

    names: tuple[str, ...]
    settings: dict
    directions: np.ndarray
    axes: np.ndarray
    angles: np.ndarray

    def __post_init__(self):
        if isinstance(self.names, str):
            raise ValueError(f"experiment names must be a sequence of names, got the string {self.names!r}")
        names = tuple(str(n) for n in self.names)
        unknown = [n for n in names if n not in EXPERIMENT_NAMES]
        if unknown or not names:
            raise ValueError(f"experiments {list(names)}: choose one or more of {list(EXPERIMENT_NAMES)}")
        self.names = tuple(n for n in EXPERIMENT_NAMES if n in names)
        self.settings = dict(self.settings)
        self.directions = np.asarray(self.directions, dtype=np.float64).reshape(-1, 3)
        self.axes = np.asarray(self.axes, dtype=np.float64).reshape(-1, 3)
        self.angles = np.asarray(self.angles, dtype=np.float64).reshape(-1)
        if min(len(self.directions), len(self.axes), len(self.angles)) == 0:
            raise ValueError("experiment directions, axes and angles must not be empty")

    @property
    def settings_json(self) -> str:
        return json.dumps(self.settings, sort_keys=True)

    def entry_layout(self) -> dict[str, tuple[tuple[int, ...], np.dtype, object]]:
        """Dataset (relative to ``/experiments``) -> (per-entry shape, dtype, fill value)."""
        return _experiment_entry_layout(len(self.directions), len(self.axes), len(self.angles))

    def empty_entry(self) -> dict[str, np.ndarray]:
        """One entry's results with nothing measured: status NOT_RUN, NaN values, -1 codes."""
        out = {
            name: np.full(shape, fill, dtype=dtype)
            for name, (shape, dtype, fill) in self.entry_layout().items()
        }
        out["status"][:] = ExperimentStatus.NOT_RUN
        return out

    def same_as(self, other: ExperimentLayout | None) -> bool:
        return (
            other is not None
            and self.names == other.names
            and self.settings_json == other.settings_json
            and all(
                a.shape == b.shape and np.array_equal(a, b)
                for a, b in (
                    (self.directions, other.directions),
                    (self.axes, other.axes),
                    (self.angles, other.angles),
                )
            )
        )


def _experiment_entry_layout(d: int, a: int, j: int) -> dict[str, tuple[tuple[int, ...], np.dtype, object]]:
    f8, i1 = np.dtype(np.float64), np.dtype(np.int8)
    out: dict[str, tuple[tuple[int, ...], np.dtype, object]] = {
        "status": ((len(EXPERIMENT_NAMES),), i1, _UNTESTED)
    }
    out.update({f"metrics/{m}": ((), f8, np.nan) for m in METRIC_NAMES})
    out.update({f"features/{m}": ((), f8, np.nan) for m in FEATURE_NAMES})
    out.update(
        {
            "pickup/grasp_force": ((), f8, np.nan),
            "pickup/slip_force": ((), f8, np.nan),
            "pickup/slide": ((), f8, np.nan),
            "pickup/failure": ((), i1, _UNTESTED),
            "reorientation/held": ((a, j), np.dtype(bool), False),
            "reorientation/max_von_mises": ((a, j), f8, np.nan),
            "reorientation/failure": ((a,), i1, _UNTESTED),
        }
    )
    for kind in ("linear", "angular"):
        out[f"{kind}/threshold"] = ((d,), f8, np.nan)
        out[f"{kind}/failure"] = ((d,), i1, _UNTESTED)
        out[f"{kind}/solver_status"] = ((d,), i1, _UNTESTED)
    return out


def _read_experiments(f: h5py.File, path: Path, sizes: dict[str, int]) -> ExperimentLayout | None:
    """Validate the optional ``/experiments`` group against the shard's (K, G); its layout or None."""
    if "experiments" not in f:
        return None
    grp = f["experiments"]
    try:
        layout = ExperimentLayout(
            names=tuple(json.loads(grp.attrs["names"])),
            settings=json.loads(grp.attrs["settings"]),
            directions=grp["directions"][()],
            axes=grp["axes"][()],
            angles=grp["angles"][()],
        )
    except (KeyError, ValueError, TypeError) as e:
        raise ShardSchemaError(
            f"{path}: /experiments has no valid names/settings/directions/axes/angles ({e})"
        ) from e
    kg = (sizes["K"], sizes["G"])
    for name, (shape, dtype, _) in layout.entry_layout().items():
        if name not in grp:
            raise ShardSchemaError(f"{path}: dataset /experiments/{name} missing")
        ds = grp[name]
        if not isinstance(ds, h5py.Dataset) or ds.dtype != dtype or ds.shape != kg + shape:
            raise ShardSchemaError(
                f"{path}: /experiments/{name} has shape {getattr(ds, 'shape', None)} and dtype "
                f"{getattr(ds, 'dtype', None)}, schema requires {kg + shape} {dtype}"
            )
    return layout


def _check_experiment_entry(layout: ExperimentLayout, entry: Mapping, where: str) -> dict[str, np.ndarray]:
    """One entry's experiment results, cast and checked: complete, right shapes, and no metric that its
    experiment's status does not vouch for (a NaN metric needs a status saying why)."""
    spec = layout.entry_layout()
    if not isinstance(entry, Mapping):
        raise ValueError(f"experiment results of {where} must be a mapping, got {type(entry).__name__}")
    missing, extra = sorted(set(spec) - set(entry)), sorted(set(entry) - set(spec))
    if missing or extra:
        raise ValueError(f"experiment results of {where}: missing {missing}, unknown {extra}")
    out = {}
    for name, (shape, dtype, _) in spec.items():
        arr = np.asarray(entry[name])
        if arr.shape != shape:
            raise ValueError(f"experiment results of {where}: {name} has shape {arr.shape}, expected {shape}")
        out[name] = arr.astype(dtype)
    status = out["status"]
    if np.any((status < 0) | (status > max(ExperimentStatus))):
        raise ValueError(
            f"experiment results of {where}: status codes {status.tolist()} outside ExperimentStatus"
        )
    for i, exp in enumerate(EXPERIMENT_NAMES):
        if (exp in layout.names) == (status[i] == ExperimentStatus.NOT_RUN):
            run = "is run" if exp in layout.names else "is not run"
            raise ValueError(
                f"experiment results of {where}: {exp} {run} in this shard but its status is "
                f"{ExperimentStatus(int(status[i])).name}"
            )
    for m in METRIC_NAMES:
        code = ExperimentStatus(int(status[EXPERIMENT_NAMES.index(METRIC_EXPERIMENT[m])]))
        v = float(out[f"metrics/{m}"])
        if m == "pickup_success":
            ok = {ExperimentStatus.OK: v == 1.0, ExperimentStatus.LOST: v == 0.0}.get(code, np.isnan(v))
        elif code == ExperimentStatus.OK:
            ok = np.isfinite(v)
        else:
            ok = np.isnan(v)
        if not ok:
            raise ValueError(
                f"experiment results of {where}: metric {m} = {v} does not match the status {code.name} of "
                f"{METRIC_EXPERIMENT[m]}"
            )
    return out


# ---------------------------------------------------------------------------------------------- layout
# name -> (shape template, dtype); shape letters are resolved from the file, ints are fixed sizes
_LAYOUT: dict[str, tuple[tuple, type]] = {
    "object/points": (("N", 3), np.float64),
    "object/tets": (("M", 4), np.int64),
    "object/surface_faces": (("F", 3), np.int64),
    "material/youngs_modulus": (("K",), np.float64),
    "material/poisson_ratio": (("K",), np.float64),
    "material/density": (("K",), np.float64),
    "gripper/finger_vertices": (("V", 3), np.float64),
    "gripper/finger_faces": (("T", 3), np.int64),
    "grasps/pose": (("G", 4, 4), np.float64),
    "grasps/finger_contact_pose": (("G", 2, 4, 4), np.float64),
    "grasps/closing_direction": (("G", 2, 3), np.float64),
    "ramp/force": (("K", "G", "S"), np.float64),
    "ramp/von_mises": (("K", "G", "S", "N"), np.float32),
    "ramp/displacement": (("K", "G", "S", "N", 3), np.float32),
    "ramp/finger_travel": (("K", "G", "S", 2), np.float64),
    "ramp/status": (("K", "G"), np.int8),
}
_ROOT_ATTRS = (
    "schema",
    "generator_version",
    "object_name",
    "object_category",
    "object_source",
    "config",
    "created",
)
_RAMP_FIELDS = ("force", "von_mises", "displacement", "finger_travel")


def _material_model(f: h5py.File) -> str:
    """The shard's constitutive model (an attribute of /material; older shards lack it: corotated)."""
    model = f["material"].attrs.get("model", "corotated")
    return model.decode() if isinstance(model, bytes) else str(model)


def _check_layout(f: h5py.File, path: Path, require_progress: bool = False) -> dict[str, int]:
    """Validate datasets and attributes of an open shard; return the sizes {N, M, F, K, V, T, G, S}."""
    schema = f.attrs.get("schema")
    if isinstance(schema, bytes):
        schema = schema.decode()
    if schema is None:
        raise ShardSchemaError(f"{path}: root attribute 'schema' missing (not a defgraspnets grasp shard)")
    if schema != SCHEMA_VERSION:
        raise ShardSchemaError(
            f"{path}: schema {schema!r} is not supported (this code reads {SCHEMA_VERSION!r})"
        )
    missing = [a for a in _ROOT_ATTRS if a not in f.attrs]
    if missing:
        raise ShardSchemaError(f"{path}: missing root attributes {missing}")
    source = f.attrs["object_source"]
    if source not in _OBJECT_SOURCES:
        raise ShardSchemaError(f"{path}: attribute object_source={source!r} not in {_OBJECT_SOURCES}")
    sizes: dict[str, int] = {}
    for name, (template, dtype) in _LAYOUT.items():
        if name not in f:
            raise ShardSchemaError(f"{path}: dataset /{name} missing")
        ds = f[name]
        if not isinstance(ds, h5py.Dataset):
            raise ShardSchemaError(f"{path}: /{name} is not a dataset")
        if ds.dtype != np.dtype(dtype):
            raise ShardSchemaError(f"{path}: /{name} has dtype {ds.dtype}, schema requires {np.dtype(dtype)}")
        if len(ds.shape) != len(template):
            raise ShardSchemaError(f"{path}: /{name} has shape {ds.shape}, schema requires {template}")
        for dim, (want, got) in enumerate(zip(template, ds.shape)):
            if isinstance(want, int):
                if got != want:
                    raise ShardSchemaError(
                        f"{path}: /{name} has shape {ds.shape}, schema requires {template}"
                    )
            elif want in sizes and sizes[want] != got:
                raise ShardSchemaError(
                    f"{path}: /{name} dimension {dim} is {got} but {want}={sizes[want]} elsewhere in the file"
                    " "
                    f"(shape {ds.shape}, schema {template})"
                )
            else:
                sizes[want] = got
    if "closing_axis_in_finger_frame" not in f["gripper/finger_faces"].attrs and (
        "closing_axis_in_finger_frame" not in f["gripper"].attrs
    ):
        raise ShardSchemaError(f"{path}: attribute /gripper closing_axis_in_finger_frame missing")
    if require_progress and "progress/done" not in f:
        raise ShardSchemaError(f"{path}: partial shard has no /progress/done dataset")
    return sizes


# ---------------------------------------------------------------------------------------------- reader
class GraspShard:
    """Read-only access to a finished grasp shard, validated against schema ``defgraspnets.grasps/1``.

    Static groups (mesh, material, gripper, grasps, force, status) are loaded into memory on open; the large
    ramp fields are read lazily: :meth:`fields` returns one ``(k, g, s)`` entry.

    Args:
        path: the ``.h5`` shard.

    Raises:
        FileNotFoundError: the file does not exist.
        ShardSchemaError: wrong schema version, missing or mis-shaped datasets, non-finite static data,
            a still-``.partial`` file.
    """

    def __init__(self, path: str | Path):
        self.path = Path(path)
        if not self.path.exists():
            raise FileNotFoundError(f"grasp shard not found: {self.path}")
        if self.path.name.endswith(".partial.h5"):
            raise ShardSchemaError(
                f"{self.path}: is an unfinished (partial) shard; finish or resume its generation"
            )
        try:
            f = h5py.File(self.path, "r")
        except OSError as e:
            raise ShardSchemaError(f"{self.path}: not a readable HDF5 file ({e})") from e
        with f:
            self.sizes = _check_layout(f, self.path)
            if "progress" in f:
                raise ShardSchemaError(
                    f"{self.path}: still has a /progress group (not finalized by the writer)"
                )
            self.attrs = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in f.attrs.items()}
            g = f["gripper"]
            axis = g["finger_faces"].attrs.get(
                "closing_axis_in_finger_frame", g.attrs.get("closing_axis_in_finger_frame")
            )
            self.object = ObjectRecord(
                name=str(self.attrs["object_name"]),
                category=str(self.attrs["object_category"]),
                source=str(self.attrs["object_source"]),
                points=f["object/points"][()],
                tets=f["object/tets"][()],
                surface_faces=f["object/surface_faces"][()],
                youngs_modulus=f["material/youngs_modulus"][()],
                poisson_ratio=f["material/poisson_ratio"][()],
                density=f["material/density"][()],
                material_model=_material_model(f),
            )
            self.fingers = GripperFingers(g["finger_vertices"][()], g["finger_faces"][()], np.asarray(axis))
            self.grasp_pose = f["grasps/pose"][()]
            self.finger_contact_pose = f["grasps/finger_contact_pose"][()]
            self.closing_direction = f["grasps/closing_direction"][()]
            self.force = f["ramp/force"][()]
            self.finger_travel = f["ramp/finger_travel"][()]
            self.status = f["ramp/status"][()]
            self.experiment_layout = _read_experiments(f, self.path, self.sizes)
            self._experiments = {}
            if self.experiment_layout is not None:
                # small (K, G, ...) arrays: loaded with the static data
                self._experiments = {
                    name: f[f"experiments/{name}"][()] for name in self.experiment_layout.entry_layout()
                }
        self._check_static()
        self._check_experiments()
        self._file: h5py.File | None = None
        self._pid: int | None = None

    def _check_static(self) -> None:
        p, o = self.path, self.object
        for name, arr in (
            ("object/points", o.points),
            ("gripper/finger_vertices", self.fingers.vertices),
            ("grasps/finger_contact_pose", self.finger_contact_pose),
            ("grasps/closing_direction", self.closing_direction),
        ):
            if not np.all(np.isfinite(arr)):
                raise ShardSchemaError(f"{p}: /{name} contains NaN or inf")
        n = len(o.points)
        if o.tets.size and (o.tets.min() < 0 or o.tets.max() >= n):
            raise ShardSchemaError(f"{p}: /object/tets reference vertices outside [0, {n})")
        if o.surface_faces.size and (o.surface_faces.min() < 0 or o.surface_faces.max() >= n):
            raise ShardSchemaError(f"{p}: /object/surface_faces reference vertices outside [0, {n})")
        v = len(self.fingers.vertices)
        if self.fingers.faces.size and (self.fingers.faces.min() < 0 or self.fingers.faces.max() >= v):
            raise ShardSchemaError(f"{p}: /gripper/finger_faces reference vertices outside [0, {v})")
        if np.any(self.status < 0):
            raise ShardSchemaError(f"{p}: /ramp/status has negative codes")
        norms = np.linalg.norm(self.closing_direction, axis=-1)
        if np.any(np.abs(norms - 1.0) > 1e-6):
            raise ShardSchemaError(f"{p}: /grasps/closing_direction is not made of unit vectors")
        solved = self.status == STATUS_SOLVED
        for name, arr in (("ramp/force", self.force), ("ramp/finger_travel", self.finger_travel)):
            if not np.all(np.isfinite(arr[solved])):
                k, g = np.argwhere(solved & ~np.all(np.isfinite(arr.reshape(*arr.shape[:2], -1)), axis=-1))[0]
                raise ShardSchemaError(f"{p}: /{name}[k={k}, g={g}] contains NaN or inf although status == 0")

    def _check_experiments(self) -> None:
        if self.experiment_layout is None:
            return
        status = self._experiments["status"]
        if np.any((status < 0) | (status > max(ExperimentStatus))):
            k, g = np.argwhere(np.any((status < 0) | (status > max(ExperimentStatus)), axis=-1))[0]
            raise ShardSchemaError(
                f"{self.path}: /experiments/status[k={k}, g={g}] = {status[k, g].tolist()} is not an "
                "ExperimentStatus (entry never written?)"
            )
        for m in METRIC_NAMES:
            i = EXPERIMENT_NAMES.index(METRIC_EXPERIMENT[m])
            v = self._experiments[f"metrics/{m}"]
            measured = status[..., i] == ExperimentStatus.OK
            if m == "pickup_success":
                measured |= status[..., i] == ExperimentStatus.LOST
            if np.any(~np.isnan(v[~measured])):
                raise ShardSchemaError(
                    f"{self.path}: /experiments/metrics/{m} has values where {METRIC_EXPERIMENT[m]} measured "
                    "nothing (status not OK)"
                )

    # -------------------------------------------------------------- experiments
    @property
    def has_experiments(self) -> bool:
        """Whether the shard holds DefGraspSim experiment results (the optional ``/experiments`` group)."""
        return self.experiment_layout is not None

    @property
    def experiment_names(self) -> tuple[str, ...]:
        """The experiments run for every entry (empty for a shard of squeeze ramps only)."""
        return () if self.experiment_layout is None else self.experiment_layout.names

    def _entry(self, k: int, g: int) -> tuple[int, int]:
        K, G = self.sizes["K"], self.sizes["G"]
        if not (-K <= k < K and -G <= g < G):
            raise IndexError(f"{self.path.name}: entry (k={k}, g={g}) outside (K, G) = ({K}, {G})")
        return k, g

    def experiment_status(self, k: int, g: int) -> dict[str, ExperimentStatus]:
        """``{experiment: ExperimentStatus}`` of entry ``(k, g)`` for the 4 :data:`EXPERIMENT_NAMES`
        (all NOT_RUN in a shard without experiments)."""
        k, g = self._entry(k, g)
        if self.experiment_layout is None:
            return {name: ExperimentStatus.NOT_RUN for name in EXPERIMENT_NAMES}
        codes = self._experiments["status"][k, g]
        return {name: ExperimentStatus(int(c)) for name, c in zip(EXPERIMENT_NAMES, codes)}

    def metrics(self, k: int, g: int) -> dict[str, float]:
        """The 7 performance metrics (thesis §6.5) of grasp ``g`` with modulus ``k``: ``{name: value}`` with
        the names of :data:`METRIC_NAMES` (units in the name; ``pickup_success`` is 1.0 or 0.0). A metric
        its experiment did not measure is NaN; :meth:`experiment_status` says why (a shard without
        experiments gives all NaN)."""
        k, g = self._entry(k, g)
        if self.experiment_layout is None:
            return {m: float("nan") for m in METRIC_NAMES}
        return {m: float(self._experiments[f"metrics/{m}"][k, g]) for m in METRIC_NAMES}

    def features(self, k: int, g: int) -> dict[str, float]:
        """The 7 grasp features (thesis Table 6.2) of entry ``(k, g)``, measured at the pickup grasp force
        F_p: ``{name: value}`` with the names of :data:`FEATURE_NAMES` (NaN where the grasp did not form or
        the shard has no experiments)."""
        k, g = self._entry(k, g)
        if self.experiment_layout is None:
            return {m: float("nan") for m in FEATURE_NAMES}
        return {m: float(self._experiments[f"features/{m}"][k, g]) for m in FEATURE_NAMES}

    def experiment(self, k: int, g: int, name: str) -> dict:
        """The per-direction results of experiment ``name`` of entry ``(k, g)``, with its ``status``:

        - ``pickup``: ``grasp_force`` F_p [N], ``slip_force`` F_slip [N], ``slide`` [m], ``failure``
          (GraspFailure code);
        - ``reorientation``: ``axes`` (A, 3), ``angles`` (J,), ``held`` (A, J) bool, ``max_von_mises``
          (A, J) [Pa], ``failure`` (A,) GraspFailure codes;
        - ``linear`` / ``angular``: ``directions`` (D, 3) (gripper frame), ``threshold`` (D,) [m/s^2 |
          rad/s^2], ``failure`` (D,) GraspFailure codes, ``solver_status`` (D,) fem.SolveStatus codes.

        Codes -1 and NaN mark what was not tested.

        Raises:
            KeyError: unknown experiment name, or the shard has no experiments.
        """
        if name not in EXPERIMENT_NAMES:
            raise KeyError(f"unknown experiment {name!r}; choose from {list(EXPERIMENT_NAMES)}")
        k, g = self._entry(k, g)
        layout = self.experiment_layout
        if layout is None:
            raise KeyError(f"{self.path.name} holds no experiment results (generated with experiments=[])")
        out: dict = {
            "status": ExperimentStatus(int(self._experiments["status"][k, g, EXPERIMENT_NAMES.index(name)]))
        }
        for key, arr in self._experiments.items():
            if key.startswith(name + "/"):
                v = arr[k, g]
                out[key[len(name) + 1 :]] = v.copy() if v.ndim else v.item()
        if name == "reorientation":
            out.update(axes=layout.axes.copy(), angles=layout.angles.copy())
        elif name in ("linear", "angular"):
            out["directions"] = layout.directions.copy()
        return out

    def metric_values(self, name: str) -> np.ndarray:
        """(K, G) float64 values of the metric ``name`` (:data:`METRIC_NAMES`) for every entry (NaN where
        not measured)."""
        if name not in METRIC_NAMES:
            raise KeyError(f"unknown metric {name!r}; choose from {list(METRIC_NAMES)}")
        if self.experiment_layout is None:
            return np.full((self.sizes["K"], self.sizes["G"]), np.nan)
        return self._experiments[f"metrics/{name}"].copy()

    @property
    def solver_settings(self) -> dict:
        """The simulator settings the shard was made with (``GraspShardWriter.create(solver_settings=...)``);
        {} for shards made before they were recorded (session 44)."""
        text = self.attrs.get("solver_settings", "")
        return json.loads(text) if text else {}

    # -------------------------------------------------------------- sizes
    @property
    def num_moduli(self) -> int:
        return self.sizes["K"]

    @property
    def num_grasps(self) -> int:
        return self.sizes["G"]

    @property
    def num_steps(self) -> int:
        return self.sizes["S"]

    @property
    def num_vertices(self) -> int:
        return self.sizes["N"]

    def solved(self) -> np.ndarray:
        """(P, 2) int64 ``(k, g)`` pairs whose squeeze ramp solved at every step (status 0)."""
        return np.argwhere(self.status == STATUS_SOLVED).astype(np.int64)

    # -------------------------------------------------------------- lazy fields
    def _handle(self) -> h5py.File:
        # one handle per process: h5py handles must not cross a fork (DataLoader workers)
        if self._file is None or self._pid != os.getpid():
            self._file = h5py.File(self.path, "r")
            self._pid = os.getpid()
        return self._file

    def fields(self, k: int, g: int, s: int | slice) -> tuple[np.ndarray, np.ndarray]:
        """Von Mises stress (N,) [Pa] and displacement (N, 3) [m] of entry ``(k, g, s)`` (float32); a slice
        ``s`` reads those steps in one read, (S', N) and (S', N, 3)."""
        f = self._handle()
        return f["ramp/von_mises"][k, g, s], f["ramp/displacement"][k, g, s]

    def close(self) -> None:
        if self._file is not None and self._pid == os.getpid():
            self._file.close()
        self._file = None

    def __getstate__(self):
        state = self.__dict__.copy()
        state["_file"] = None
        state["_pid"] = None
        return state

    def __repr__(self) -> str:
        s = self.sizes
        return (
            f"GraspShard({self.path.name!r}, object={self.object.name!r}, "
            f"K={s['K']}, G={s['G']}, S={s['S']}, "
            f"N={s['N']}, solved={int((self.status == 0).sum())}/{s['K'] * s['G']})"
        )


def settings_difference(old: Mapping, new: Mapping) -> str:
    """Which entries of two (nested) solver-settings mappings differ: ``key: old -> new`` with dotted paths,
    joined by commas ("" where none does; ``<none>`` for an entry one side lacks)."""

    def flat(d: Mapping, prefix: str = "") -> dict:
        out = {}
        for k, v in d.items():
            if isinstance(v, Mapping):
                out.update(flat(v, f"{prefix}{k}."))
            else:
                out[f"{prefix}{k}"] = v
        return out

    a, b = flat(old), flat(new)
    keys = sorted(k for k in a.keys() | b.keys() if a.get(k, "<none>") != b.get(k, "<none>"))
    return ", ".join(f"{k}: {a.get(k, '<none>')} -> {b.get(k, '<none>')}" for k in keys)


def _settings_difference(partial: Path, settings_text: str) -> str | None:
    """None where the unfinished shard ``partial`` was made with the solver settings ``settings_text``
    (JSON; "" = none recorded), else which differ (:func:`settings_difference`, or that one side has none)."""
    with h5py.File(partial, "r") as f:
        old_text = str(f.attrs.get("solver_settings", ""))
    if old_text == settings_text:
        return None
    if not old_text or not settings_text:
        return "recorded on one side only: made by another generator version?"
    return settings_difference(json.loads(old_text), json.loads(settings_text))


# ---------------------------------------------------------------------------------------------- writer
class GraspShardWriter:
    """Incremental, resumable, atomic writer of one grasp shard.

    Usage (the generator)::

        writer = GraspShardWriter.create(out_dir / shard_file_name(obj.name, i, n), obj, fingers,
                                         pose, finger_contact_pose, closing_direction, num_steps=S,
                                         generator_version=__version__, config=yaml_text)
        for k, g in writer.pending():                       # all (k, g), or what a killed run left undone
            ...run the squeeze ramp...
            writer.write(k, g, force, von_mises, displacement, finger_travel, status)
        writer.finalize()                                    # -> <name>.h5, atomically

    ``create`` resumes instead of starting over when ``<name>.partial.h5`` exists and holds the same static
    data (same mesh, materials, gripper and grasps; otherwise it raises unless ``overwrite=True``). Each
    :meth:`write` flushes the fields before it marks ``(k, g)`` done, so an entry interrupted mid-write is
    redone on resume. ``<name>.h5`` only ever appears through the final ``os.replace``.
    """

    def __init__(self, partial_path: Path, final_path: Path, f: h5py.File):
        self.partial_path = partial_path
        self.path = final_path
        self._f = f
        self.sizes = _check_layout(f, partial_path, require_progress=True)
        self.experiment_layout = _read_experiments(f, partial_path, self.sizes)

    # -------------------------------------------------------------- construction
    @staticmethod
    def partial_path_for(path: str | Path) -> Path:
        path = Path(path)
        if not path.name.endswith(".h5") or path.name.endswith(".partial.h5"):
            raise ValueError(f"shard path must end in .h5 (not .partial.h5): {path}")
        return path.with_name(path.name[: -len(".h5")] + ".partial.h5")

    @classmethod
    def create(
        cls,
        path: str | Path,
        obj: ObjectRecord,
        fingers: GripperFingers,
        pose: np.ndarray,
        finger_contact_pose: np.ndarray,
        closing_direction: np.ndarray,
        num_steps: int,
        generator_version: str,
        config: str = "",
        overwrite: bool = False,
        experiments: ExperimentLayout | None = None,
        solver_settings: Mapping | None = None,
    ) -> GraspShardWriter:
        """Start (or resume) the shard ``path`` (a ``.h5`` name; data go to ``<name>.partial.h5`` first).

        Args:
            path: final shard path ``<dir>/<object>__shard<i>of<n>.h5``.
            obj: object mesh and the K materials. fingers: finger-pad mesh in the finger frame.
            pose: (G, 4, 4) open-gripper poses. finger_contact_pose: (G, 2, 4, 4).
            closing_direction: (G, 2, 3).
            num_steps: S, ramp steps stored per grasp.
            generator_version, config: provenance, stored as root attributes.
            overwrite: discard an existing final or partial file with different content.
            experiments: the experiments every entry will hold (creates ``/experiments``); None: squeeze
                ramps only. A partial file made with other experiments or settings is not resumed.
            solver_settings: the simulator settings that decide which equilibria the entries hold (a
                JSON-serializable mapping, stored as the ``solver_settings`` attribute); a partial file made
                with other ones (or without them) is not resumed, so a shard never mixes entries of two
                settings. None: not recorded.

        Raises:
            FileExistsError: the final shard already exists (and not ``overwrite``).
            ValueError: inconsistent input shapes, or a partial file of different static content.
        """
        path = Path(path)
        partial = cls.partial_path_for(path)
        parse_shard_name(path)
        pose = np.asarray(pose, dtype=np.float64)
        finger_contact_pose = np.asarray(finger_contact_pose, dtype=np.float64)
        closing_direction = np.asarray(closing_direction, dtype=np.float64)
        g = len(pose)
        if (
            pose.shape != (g, 4, 4)
            or finger_contact_pose.shape != (g, 2, 4, 4)
            or closing_direction.shape != (g, 2, 3)
        ):
            raise ValueError(
                f"grasp arrays must be (G,4,4), (G,2,4,4), (G,2,3); got {pose.shape}, "
                f"{finger_contact_pose.shape}, "
                f"{closing_direction.shape}"
            )
        if num_steps < 1:
            raise ValueError(f"num_steps must be >= 1, got {num_steps}")
        if experiments is not None and not isinstance(experiments, ExperimentLayout):
            raise TypeError(
                f"experiments must be an ExperimentLayout or None, got {type(experiments).__name__}"
            )
        static = {
            "object/points": obj.points,
            "object/tets": obj.tets,
            "object/surface_faces": obj.surface_faces,
            "material/youngs_modulus": obj.youngs_modulus,
            "material/poisson_ratio": obj.poisson_ratio,
            "material/density": obj.density,
            "gripper/finger_vertices": fingers.vertices,
            "gripper/finger_faces": fingers.faces,
            "grasps/pose": pose,
            "grasps/finger_contact_pose": finger_contact_pose,
            "grasps/closing_direction": closing_direction,
        }
        if path.exists():
            if not overwrite:
                raise FileExistsError(
                    f"{path}: shard already finished (pass overwrite=True to regenerate it)"
                )
            path.unlink()
        settings_text = "" if solver_settings is None else json.dumps(dict(solver_settings), sort_keys=True)
        if partial.exists():
            same = cls._same_static(partial, static, obj, num_steps, experiments)
            differ = _settings_difference(partial, settings_text) if same else None
            if same and differ is None:
                return cls(partial, path, h5py.File(partial, "a"))
            if not overwrite:
                what = f"solver settings ({differ})" if same else "object/material/grasp/experiment data"
                raise ValueError(
                    f"{partial}: an unfinished shard with different {what} exists; delete it or pass "
                    "overwrite=True"
                )
            partial.unlink()
        path.parent.mkdir(parents=True, exist_ok=True)
        k, n, s = obj.num_moduli, len(obj.points), int(num_steps)
        f = h5py.File(partial, "w")
        f.attrs["schema"] = SCHEMA_VERSION
        f.attrs["generator_version"] = str(generator_version)
        f.attrs["object_name"] = obj.name
        f.attrs["object_category"] = obj.category
        f.attrs["object_source"] = obj.source
        f.attrs["config"] = str(config)
        if settings_text:
            f.attrs["solver_settings"] = settings_text
        f.attrs["created"] = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
        for name, arr in static.items():
            f.create_dataset(name, data=np.asarray(arr, dtype=_LAYOUT[name][1]))
        f["gripper/finger_faces"].attrs["closing_axis_in_finger_frame"] = fingers.closing_axis
        f["gripper"].attrs["closing_axis_in_finger_frame"] = fingers.closing_axis
        f["material"].attrs["model"] = obj.material_model
        nan = np.nan
        f.create_dataset("ramp/force", shape=(k, g, s), dtype=np.float64, fillvalue=nan)
        f.create_dataset("ramp/finger_travel", shape=(k, g, s, 2), dtype=np.float64, fillvalue=nan)
        # one chunk per (k, g, s): the Dataset reads exactly one step of one grasp at a time
        f.create_dataset(
            "ramp/von_mises",
            shape=(k, g, s, n),
            dtype=np.float32,
            fillvalue=nan,
            chunks=(1, 1, 1, n),
            compression=_COMPRESSION,
            shuffle=True,
        )
        f.create_dataset(
            "ramp/displacement",
            shape=(k, g, s, n, 3),
            dtype=np.float32,
            fillvalue=nan,
            chunks=(1, 1, 1, n, 3),
            compression=_COMPRESSION,
            shuffle=True,
        )
        f.create_dataset("ramp/status", shape=(k, g), dtype=np.int8, fillvalue=-1)
        if experiments is not None:
            grp = f.create_group("experiments")
            grp.attrs["names"] = json.dumps(list(experiments.names))
            grp.attrs["settings"] = experiments.settings_json
            grp.create_dataset("directions", data=experiments.directions)
            grp.create_dataset("axes", data=experiments.axes)
            grp.create_dataset("angles", data=experiments.angles)
            for name, (shape, dtype, fill) in experiments.entry_layout().items():
                grp.create_dataset(name, shape=(k, g, *shape), dtype=dtype, fillvalue=fill)
        f.create_dataset("progress/done", shape=(k, g), dtype=bool, fillvalue=False)
        f.flush()
        return cls(partial, path, f)

    @staticmethod
    def _same_static(
        partial: Path, static: dict, obj: ObjectRecord, num_steps: int, experiments: ExperimentLayout | None
    ) -> bool:
        try:
            with h5py.File(partial, "r") as f:
                sizes = _check_layout(f, partial, require_progress=True)
                if f["ramp/force"].shape[2] != num_steps:
                    return False
                found = _read_experiments(f, partial, sizes)
                if (found is None) != (experiments is None) or (
                    experiments is not None and not experiments.same_as(found)
                ):
                    return False
                if (f.attrs["object_name"], f.attrs["object_category"], f.attrs["object_source"]) != (
                    obj.name,
                    obj.category,
                    obj.source,
                ) or _material_model(f) != obj.material_model:
                    return False
                return all(
                    f[name].shape == np.shape(arr) and np.array_equal(f[name][()], arr)
                    for name, arr in static.items()
                )
        except (OSError, ShardSchemaError, KeyError) as e:
            raise ShardSchemaError(
                f"{partial}: unfinished shard cannot be resumed ({e}); delete it to start this shard over"
            ) from e

    # -------------------------------------------------------------- progress
    @property
    def done(self) -> np.ndarray:
        """(K, G) bool: entries already written."""
        return self._f["progress/done"][()]

    def pending(self) -> list[tuple[int, int]]:
        """``(k, g)`` entries not yet written, in row-major order."""
        return [(int(k), int(g)) for k, g in np.argwhere(~self.done)]

    # -------------------------------------------------------------- writing
    def write(
        self,
        k: int,
        g: int,
        force: np.ndarray,
        von_mises: np.ndarray,
        displacement: np.ndarray,
        finger_travel: np.ndarray,
        status: int = STATUS_SOLVED,
        experiments: Mapping | None = None,
    ) -> None:
        """Store the squeeze ramp of grasp ``g`` with modulus ``k`` (and its experiment results) and mark it
        done: everything of the entry is flushed before it is marked, so a kill never leaves half an entry.

        Args:
            force: (S,) total normal grasp force [N]. von_mises: (S, N) [Pa]. displacement: (S, N, 3) [m].
            finger_travel: (S, 2) [m]. status: 0 if every step solved, else a positive failure code
                (then fields may be NaN; they are never used for training).
            experiments: required iff the shard has ``/experiments``: ``{dataset: value}`` for every dataset
                of :meth:`ExperimentLayout.entry_layout` (start from :meth:`ExperimentLayout.empty_entry`).

        Raises:
            ValueError: wrong shapes, a negative status, non-finite values with ``status == 0``, missing or
                unexpected experiment results, or a metric its experiment's status does not vouch for.
        """
        sz = self.sizes
        if not (0 <= k < sz["K"] and 0 <= g < sz["G"]):
            raise ValueError(f"(k, g) = ({k}, {g}) outside (K, G) = ({sz['K']}, {sz['G']})")
        if status < 0 or status > 127:
            raise ValueError(f"status must be in [0, 127], got {status}")
        arrays = {
            "force": (np.asarray(force, dtype=np.float64), (sz["S"],)),
            "von_mises": (np.asarray(von_mises, dtype=np.float32), (sz["S"], sz["N"])),
            "displacement": (np.asarray(displacement, dtype=np.float32), (sz["S"], sz["N"], 3)),
            "finger_travel": (np.asarray(finger_travel, dtype=np.float64), (sz["S"], 2)),
        }
        for name, (arr, shape) in arrays.items():
            if arr.shape != shape:
                raise ValueError(f"{name} of (k={k}, g={g}) has shape {arr.shape}, expected {shape}")
            if status == STATUS_SOLVED and not np.all(np.isfinite(arr)):
                raise ValueError(f"{name} of (k={k}, g={g}) has NaN/inf values but status is 0 (solved)")
        results = None
        if self.experiment_layout is not None:
            if experiments is None:
                raise ValueError(
                    f"{self.partial_path.name}: the shard holds experiments; pass those of (k={k}, g={g})"
                )
            results = _check_experiment_entry(self.experiment_layout, experiments, f"(k={k}, g={g})")
        elif experiments is not None:
            raise ValueError(
                f"{self.partial_path.name}: the shard was created without experiments; cannot store them"
            )
        f = self._f
        f["progress/done"][k, g] = False
        f.flush()
        for name, (arr, _) in arrays.items():
            f[f"ramp/{name}"][k, g] = arr
        f["ramp/status"][k, g] = status
        for name, arr in (results or {}).items():
            f[f"experiments/{name}"][k, g] = arr
        f.flush()
        f["progress/done"][k, g] = True
        f.flush()

    def finalize(self) -> Path:
        """Check that every entry is written, fsync and rename ``<name>.partial.h5`` -> ``<name>.h5``.

        Raises:
            RuntimeError: entries are still pending.
        """
        pending = self.pending()
        if pending:
            raise RuntimeError(
                f"{self.partial_path}: {len(pending)} (k, g) entries not written yet, e.g. {pending[:4]}"
            )
        del self._f["progress"]
        self._f.flush()
        self._f.close()
        with open(self.partial_path, "rb+") as fh:
            os.fsync(fh.fileno())
        os.replace(self.partial_path, self.path)
        try:  # persist the rename itself
            dir_fd = os.open(self.path.parent, os.O_RDONLY)
            try:
                os.fsync(dir_fd)
            finally:
                os.close(dir_fd)
        except OSError:
            pass
        GraspShard(self.path)  # validate what was written
        return self.path

    def close(self) -> None:
        """Close the partial file without finishing it (it can be resumed with :meth:`create`)."""
        if self._f.id.valid:
            self._f.close()

    def __enter__(self) -> GraspShardWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
