"""HDF5 schema of the tactile (depth image -> wrench) datasets: writer, reader, validation.

One file per dataset shard. Layout (N samples, H x W images, K reference images)::

    attrs   schema="defgraspnets.tactile", schema_version, generator_version, experiment
            ("poke" | "forearm" | ...), config_yaml, created (ISO 8601, UTC), image_height,
            image_width, wrench_components, param_names, quaternion_convention="xyzw", units
    depth            (N, H, W) float32  depth z [m] in the camera frame; NaN = no return
    points           (N, H, W, 3) float32, optional organized point cloud [m]
    wrench           (N, 6) float64  (F_x, F_y, F_z [N], tau_x, tau_y, tau_z [N m]) exerted by the
                     indenter on the sensor, in the sensor frame, torque about the sensor-frame
                     origin (the camera's optical centre; the thesis's F/T sensor frame shares its
                     orientation, §3.3)
    indenter_pose    (N, 7) float64  position [m] + unit quaternion (x, y, z, w), sensor frame
    indenter_kind    (N,) str        "sphere" | "capsule" | "box" | "ring"
    pv_state         (N, 2) float64  pre-contact gas state (absolute pressure [Pa], volume [m^3])
    reference_index  (N,) int64      row of references/ holding this sample's undeformed image
    params           (N, 13) float64  experiment parameters, NaN where not applicable, columns
                     PARAM_NAMES = phi, contact_radius, theta, depth, shear_direction,
                     shear_distance, twist  [rad, m] (the command), then the perturbation of
                     the repeated forearm experiment (:mod:`defgraspnets.tactile.datasets`):
                     repeat (0 = the nominal grid), offset_x, offset_y [m] (forearm placement
                     along the sensor x, y axes), yaw [rad] (about the sensor z axis),
                     radius_scale (forearm radius / nominal), friction_offset (Coulomb
                     coefficient - nominal); NaN for experiments without repeats (poke)
    sample_id        (N,) int64      unique id (index in the experiment grid, + repeat x grid size
                     for repeats; resuming skips ids)
    references/depth (K, H, W) float32, references/pv_state (K, 2), references/label (K,)
    failures/sample_id, failures/params, failures/reason   solves that failed (never data)

Atomic and resumable: a :class:`TactileShardWriter` writes each appended batch as a complete part
file ``<shard>.parts/part-XXXXXX.h5`` (written to a temporary name, fsynced, then renamed) and
:meth:`TactileShardWriter.finalize` merges the parts into ``<shard>`` the same way. A killed run
leaves only complete parts (stale temporaries are removed on resume), so it never corrupts; a new
writer on the same path resumes and reports :attr:`TactileShardWriter.completed_sample_ids`. One
writer per shard at a time.

Versions: 2 added the six perturbation columns of ``params``. Version 1 files (and unfinished version
1 runs) still load: their 7-column ``params`` (here and under ``failures/``) read with the new columns
NaN (not recorded); in-memory batches given 7-column params are widened the same way.
"""

from __future__ import annotations

import json
import os
import re
import shutil
from contextlib import contextmanager
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import h5py
import numpy as np

__all__ = [
    "COMMAND_PARAM_NAMES",
    "PARAM_NAMES",
    "PERTURBATION_PARAM_NAMES",
    "SCHEMA_NAME",
    "SCHEMA_VERSION",
    "SUPPORTED_SCHEMA_VERSIONS",
    "WRENCH_COMPONENTS",
    "TactileFailures",
    "TactileReferences",
    "TactileSamples",
    "TactileSchemaError",
    "TactileShard",
    "TactileShardWriter",
    "read_tactile_shard",
]

SCHEMA_NAME = "defgraspnets.tactile"
SCHEMA_VERSION = 2
#: versions :func:`read_tactile_shard` reads (older ones are widened to the current layout)
SUPPORTED_SCHEMA_VERSIONS = (1, 2)
WRENCH_COMPONENTS = ("force_x", "force_y", "force_z", "torque_x", "torque_y", "torque_z")
#: the command's parameters (schema version 1's columns), then the perturbation of a repeat (version 2)
COMMAND_PARAM_NAMES = (
    "phi",
    "contact_radius",
    "theta",
    "depth",
    "shear_direction",
    "shear_distance",
    "twist",
)
PERTURBATION_PARAM_NAMES = ("repeat", "offset_x", "offset_y", "yaw", "radius_scale", "friction_offset")
PARAM_NAMES = COMMAND_PARAM_NAMES + PERTURBATION_PARAM_NAMES
UNITS = {
    "depth": "m",
    "points": "m",
    "wrench": "N (force), N m (torque)",
    "indenter_pose": "m, unit quaternion xyzw",
    "pv_state": "Pa (absolute), m^3",
    "params": "phi rad, contact_radius m, theta rad, depth m, shear_direction rad, shear_distance m, "
    "twist rad, repeat 1, offset_x m, offset_y m, yaw rad, radius_scale 1, friction_offset 1",
}
_STR = h5py.string_dtype()
_REQUIRED_ATTRS = ("generator_version", "experiment", "config_yaml", "created", "image_height", "image_width")
_PART = re.compile(r"^part-(\d{6})\.h5$")


class TactileSchemaError(ValueError):
    """A tactile dataset (file or in-memory batch) violates the schema."""


def _as(array, dtype, shape, name, where) -> np.ndarray:
    a = np.asarray(array)
    if a.shape != shape:
        raise TactileSchemaError(f"{where}: {name} must have shape {shape}, got {a.shape}")
    return np.ascontiguousarray(a.astype(dtype, copy=False))


def _widen_params(params) -> np.ndarray:
    """Version 1 params (N, 7: the command only) -> the current (N, 13) layout, perturbation NaN."""
    a = np.asarray(params)
    if a.ndim == 2 and a.shape[1] == len(COMMAND_PARAM_NAMES):
        a = np.concatenate([a, np.full((len(a), len(PERTURBATION_PARAM_NAMES)), np.nan)], axis=1)
    return a


def _strings(values) -> np.ndarray:
    return np.array(
        [v.decode() if isinstance(v, bytes) else str(v) for v in np.asarray(values).ravel()], dtype=object
    )


@dataclass(eq=False)
class TactileSamples:
    """A batch of N tactile samples (see the module docstring for fields and units)."""

    depth: np.ndarray
    wrench: np.ndarray
    indenter_pose: np.ndarray
    indenter_kind: np.ndarray
    pv_state: np.ndarray
    reference_index: np.ndarray
    params: np.ndarray
    sample_id: np.ndarray
    points: np.ndarray | None = None
    where: str = field(default="samples", repr=False)

    def __post_init__(self):
        w = self.where
        depth = np.asarray(self.depth)
        if depth.ndim != 3:
            raise TactileSchemaError(f"{w}: depth must have shape (N, H, W), got {depth.shape}")
        n, h, wid = depth.shape
        self.depth = _as(depth, np.float32, (n, h, wid), "depth", w)
        self.wrench = _as(self.wrench, np.float64, (n, 6), "wrench", w)
        self.indenter_pose = _as(self.indenter_pose, np.float64, (n, 7), "indenter_pose", w)
        self.indenter_kind = _strings(self.indenter_kind)
        if self.indenter_kind.shape != (n,):
            raise TactileSchemaError(
                f"{w}: indenter_kind must have shape ({n},), got {self.indenter_kind.shape}"
            )
        self.pv_state = _as(self.pv_state, np.float64, (n, 2), "pv_state", w)
        self.reference_index = _as(self.reference_index, np.int64, (n,), "reference_index", w)
        self.params = _as(_widen_params(self.params), np.float64, (n, len(PARAM_NAMES)), "params", w)
        self.sample_id = _as(self.sample_id, np.int64, (n,), "sample_id", w)
        if self.points is not None:
            self.points = _as(self.points, np.float32, (n, h, wid, 3), "points", w)
        self._validate_values()

    def _validate_values(self) -> None:
        w = self.where
        if np.isinf(self.depth).any() or (self.depth < 0).any():
            raise TactileSchemaError(
                f"{w}: depth must be >= 0 m or NaN (no return); found inf or negative values"
            )
        bad = ~np.all(np.isfinite(self.wrench), axis=1)
        if bad.any():
            raise TactileSchemaError(
                f"{w}: non-finite wrench for sample ids {self.sample_id[bad][:8].tolist()}"
            )
        bad = ~np.all(np.isfinite(self.indenter_pose), axis=1)
        if bad.any():
            raise TactileSchemaError(
                f"{w}: non-finite indenter pose for sample ids {self.sample_id[bad][:8].tolist()}"
            )
        qn = np.linalg.norm(self.indenter_pose[:, 3:], axis=1)
        bad = np.abs(qn - 1.0) > 1e-6
        if bad.any():
            raise TactileSchemaError(
                f"{w}: indenter quaternions must be unit (xyzw); norms {qn[bad][:4].tolist()} "
                f"for sample ids {self.sample_id[bad][:4].tolist()}"
            )
        if not np.all(np.isfinite(self.pv_state)) or (self.pv_state <= 0).any():
            raise TactileSchemaError(f"{w}: pv_state (absolute pressure, volume) must be finite and > 0")
        if (self.reference_index < 0).any():
            raise TactileSchemaError(f"{w}: reference_index must be >= 0")
        if len(np.unique(self.sample_id)) != len(self.sample_id):
            raise TactileSchemaError(f"{w}: sample_id values repeat")

    def __len__(self) -> int:
        return len(self.sample_id)

    @property
    def image_shape(self) -> tuple[int, int]:
        return self.depth.shape[1:]

    def subset(self, index) -> TactileSamples:
        return TactileSamples(
            self.depth[index],
            self.wrench[index],
            self.indenter_pose[index],
            self.indenter_kind[index],
            self.pv_state[index],
            self.reference_index[index],
            self.params[index],
            self.sample_id[index],
            None if self.points is None else self.points[index],
            where=self.where,
        )


@dataclass(eq=False)
class TactileReferences:
    """K undeformed reference images (one per PV state) with their gas states and labels."""

    depth: np.ndarray
    pv_state: np.ndarray
    label: np.ndarray
    where: str = field(default="references", repr=False)

    def __post_init__(self):
        depth = np.asarray(self.depth)
        if depth.ndim != 3 or len(depth) < 1:
            raise TactileSchemaError(
                f"{self.where}: references depth must have shape (K >= 1, H, W), got {depth.shape}"
            )
        k = len(depth)
        self.depth = _as(depth, np.float32, depth.shape, "references depth", self.where)
        self.pv_state = _as(self.pv_state, np.float64, (k, 2), "references pv_state", self.where)
        self.label = _strings(self.label)
        if self.label.shape != (k,):
            raise TactileSchemaError(
                f"{self.where}: references label must have shape ({k},), got {self.label.shape}"
            )
        if np.isinf(self.depth).any() or (self.depth < 0).any():
            raise TactileSchemaError(f"{self.where}: reference depth must be >= 0 m or NaN")
        if not np.all(np.isfinite(self.pv_state)) or (self.pv_state <= 0).any():
            raise TactileSchemaError(f"{self.where}: reference pv_state must be finite and > 0")

    def __len__(self) -> int:
        return len(self.depth)

    def same_as(self, other: TactileReferences) -> bool:
        return (
            self.depth.shape == other.depth.shape
            and np.array_equal(self.depth, other.depth, equal_nan=True)
            and np.array_equal(self.pv_state, other.pv_state)
            and list(self.label) == list(other.label)
        )


@dataclass(eq=False)
class TactileFailures:
    """Samples whose simulation failed: recorded, never stored as data."""

    sample_id: np.ndarray
    params: np.ndarray
    reason: np.ndarray

    def __post_init__(self):
        self.sample_id = np.asarray(self.sample_id, dtype=np.int64).ravel()
        n = len(self.sample_id)
        params = _widen_params(self.params)
        self.params = _as(params, np.float64, (n, len(PARAM_NAMES)), "failure params", "failures")
        self.reason = _strings(self.reason)
        if self.reason.shape != (n,):
            raise TactileSchemaError(f"failures: reason must have shape ({n},), got {self.reason.shape}")

    def __len__(self) -> int:
        return len(self.sample_id)

    @classmethod
    def empty(cls) -> TactileFailures:
        return cls(np.zeros(0, np.int64), np.zeros((0, len(PARAM_NAMES))), np.zeros(0, object))


@dataclass(eq=False)
class TactileShard:
    """A complete shard as read from disk."""

    samples: TactileSamples
    references: TactileReferences
    failures: TactileFailures
    attrs: dict
    path: Path | None = None

    @property
    def experiment(self) -> str:
        return str(self.attrs["experiment"])

    def reference_depth(self) -> np.ndarray:
        """(N, H, W) the reference image of every sample."""
        return self.references.depth[self.samples.reference_index]


# --------------------------------------------------------------------------- low-level io
@contextmanager
def _atomic_h5(path: Path):
    """Yield an h5py file at a temporary name; on success fsync and rename it to ``path``."""
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        with h5py.File(tmp, "w") as f:
            yield f
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def _write_samples(g: h5py.Group, s: TactileSamples) -> None:
    _, h, w = s.depth.shape
    g.create_dataset("depth", data=s.depth, chunks=(1, h, w), compression="lzf")
    if s.points is not None:
        g.create_dataset("points", data=s.points, chunks=(1, h, w, 3), compression="lzf")
    for name in ("wrench", "indenter_pose", "pv_state", "reference_index", "params", "sample_id"):
        g.create_dataset(name, data=getattr(s, name))
    g.create_dataset("indenter_kind", data=s.indenter_kind.astype(object), dtype=_STR)


def _write_failures(g: h5py.Group, fl: TactileFailures) -> None:
    g.create_dataset("sample_id", data=fl.sample_id)
    g.create_dataset("params", data=fl.params)
    g.create_dataset("reason", data=fl.reason.astype(object), dtype=_STR)


def _read_samples(g: h5py.Group, where: str, load_points: bool = True) -> TactileSamples:
    required = (
        "depth",
        "wrench",
        "indenter_pose",
        "indenter_kind",
        "pv_state",
        "reference_index",
        "params",
        "sample_id",
    )
    missing = [k for k in required if k not in g]
    if missing:
        raise TactileSchemaError(f"{where}: missing datasets {missing}")
    return TactileSamples(
        g["depth"][()],
        g["wrench"][()],
        g["indenter_pose"][()],
        g["indenter_kind"][()],
        g["pv_state"][()],
        g["reference_index"][()],
        g["params"][()],  # version 1's 7 columns are widened by TactileSamples
        g["sample_id"][()],
        g["points"][()] if load_points and "points" in g else None,
        where=where,
    )


def _read_failures(g: h5py.Group | None) -> TactileFailures:
    if g is None:
        return TactileFailures.empty()
    return TactileFailures(g["sample_id"][()], g["params"][()], g["reason"][()])


def _check_header(f: h5py.File, where: str) -> None:
    if f.attrs.get("schema") != SCHEMA_NAME:
        raise TactileSchemaError(f"{where}: not a tactile dataset (schema attr {f.attrs.get('schema')!r})")
    version = int(f.attrs.get("schema_version", -1))
    if version not in SUPPORTED_SCHEMA_VERSIONS:
        raise TactileSchemaError(
            f"{where}: schema_version {version} is not supported (expected one of "
            f"{list(SUPPORTED_SCHEMA_VERSIONS)})"
        )
    missing = [k for k in _REQUIRED_ATTRS if k not in f.attrs]
    if missing:
        raise TactileSchemaError(f"{where}: missing attributes {missing}")


def read_tactile_shard(path: str | Path, load_points: bool = True) -> TactileShard:
    """Read and validate a finalized shard.

    Raises:
        FileNotFoundError: the file does not exist (the message mentions unfinished ``.parts``).
        TactileSchemaError: wrong schema or version, missing datasets, inconsistent shapes,
            non-finite wrenches or poses, reference indices out of range, image size mismatch.
    """
    path = Path(path)
    if not path.exists():
        parts = path.with_name(path.name + ".parts")
        hint = (
            f" (an unfinished run left {parts}; finalize it with TactileShardWriter)"
            if parts.exists()
            else ""
        )
        raise FileNotFoundError(f"tactile shard not found: {path}{hint}")
    where = str(path)
    try:
        f = h5py.File(path, "r")
    except OSError as e:
        raise TactileSchemaError(f"{where}: not a readable HDF5 file ({e})") from e
    with f:
        _check_header(f, where)
        attrs = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in f.attrs.items()}
        samples = _read_samples(f, where, load_points)
        if "references" not in f:
            raise TactileSchemaError(f"{where}: missing group 'references'")
        r = f["references"]
        references = TactileReferences(
            r["depth"][()], r["pv_state"][()], r["label"][()], where=f"{where}:references"
        )
        failures = _read_failures(f.get("failures"))
    h, w = int(attrs["image_height"]), int(attrs["image_width"])
    if samples.image_shape != (h, w) or references.depth.shape[1:] != (h, w):
        raise TactileSchemaError(
            f"{where}: image size mismatch: attrs {(h, w)}, depth {samples.image_shape}, "
            f"references {references.depth.shape[1:]}"
        )
    if len(samples) and samples.reference_index.max() >= len(references):
        raise TactileSchemaError(
            f"{where}: reference_index up to {samples.reference_index.max()} "
            f"but only {len(references)} references"
        )
    return TactileShard(samples, references, failures, attrs, path)


# --------------------------------------------------------------------------- writer
class TactileShardWriter:
    """Append-only, resumable, atomic writer of one tactile shard.

    Args:
        path: the final shard file (``.h5``).
        references: reference images of the shard's PV states.
        experiment: experiment name, e.g. ``"poke"`` or ``"forearm"``.
        config_yaml: the generating configuration (stored verbatim).
        generator_version: version string of the generating code (default: the package version).
        store_points: whether samples carry organized point clouds.

    Raises:
        FileExistsError: the shard is already finalized.
        TactileSchemaError: resuming with a different experiment, image size, references or
            ``store_points`` than the unfinished run.
    """

    def __init__(
        self,
        path: str | Path,
        references: TactileReferences,
        experiment: str,
        config_yaml: str = "",
        generator_version: str | None = None,
        store_points: bool = False,
    ):
        from defgraspnets import __version__

        self.path = Path(path)
        if self.path.exists():
            raise FileExistsError(f"tactile shard {self.path} is already complete; delete it to regenerate")
        self.parts_dir = self.path.with_name(self.path.name + ".parts")
        self.references = references
        self.store_points = bool(store_points)
        self.attrs = {
            "schema": SCHEMA_NAME,
            "schema_version": SCHEMA_VERSION,
            "generator_version": generator_version or __version__,
            "experiment": str(experiment),
            "config_yaml": str(config_yaml),
            "image_height": int(references.depth.shape[1]),
            "image_width": int(references.depth.shape[2]),
            "store_points": int(self.store_points),
            "wrench_components": json.dumps(WRENCH_COMPONENTS),
            "param_names": json.dumps(PARAM_NAMES),
            "quaternion_convention": "xyzw",
            "units": json.dumps(UNITS),
        }
        self._completed: set[int] = set()
        self._num_samples = 0
        if self.parts_dir.exists():
            self._resume()
        else:
            self.parts_dir.mkdir(parents=True)
            self.attrs["created"] = datetime.now(timezone.utc).isoformat()
            with _atomic_h5(self.parts_dir / "header.h5") as f:
                f.attrs.update(self.attrs)
                r = f.create_group("references")
                r.create_dataset("depth", data=references.depth)
                r.create_dataset("pv_state", data=references.pv_state)
                r.create_dataset("label", data=references.label.astype(object), dtype=_STR)

    # ------------------------------------------------------------------ resume
    def _resume(self) -> None:
        for stale in self.parts_dir.glob(".*.tmp-*"):
            stale.unlink()
        header = self.parts_dir / "header.h5"
        if not header.exists():
            raise TactileSchemaError(
                f"{self.parts_dir}: unfinished shard without header.h5; delete the directory"
            )
        with h5py.File(header, "r") as f:
            _check_header(f, str(header))
            r = f["references"]
            old = TactileReferences(r["depth"][()], r["pv_state"][()], r["label"][()])
            for key in ("experiment", "image_height", "image_width", "store_points"):
                if f.attrs[key] != self.attrs[key]:
                    raise TactileSchemaError(
                        f"{self.parts_dir}: cannot resume, {key} was {f.attrs[key]!r}, "
                        f"now {self.attrs[key]!r}"
                    )
            self.attrs["created"] = f.attrs["created"]
        if not old.same_as(self.references):
            raise TactileSchemaError(f"{self.parts_dir}: cannot resume with different reference images")
        for part in self._parts():
            with h5py.File(part, "r") as f:
                ids = f["sample_id"][()] if "sample_id" in f else np.zeros(0, np.int64)
                self._num_samples += len(ids)
                failed = f["failures/sample_id"][()] if "failures" in f else np.zeros(0, np.int64)
                self._completed.update(int(i) for i in np.concatenate([ids, failed]))

    def _parts(self) -> list[Path]:
        return sorted(p for p in self.parts_dir.iterdir() if _PART.match(p.name))

    def _next_part(self) -> Path:
        parts = self._parts()
        k = int(_PART.match(parts[-1].name).group(1)) + 1 if parts else 0
        return self.parts_dir / f"part-{k:06d}.h5"

    # ------------------------------------------------------------------ api
    @property
    def completed_sample_ids(self) -> set[int]:
        """Ids already stored or recorded as failed (skip these when resuming)."""
        return set(self._completed)

    @property
    def num_samples(self) -> int:
        return self._num_samples

    def _check_new_ids(self, ids: np.ndarray) -> None:
        dup = sorted(set(int(i) for i in ids) & self._completed)
        if dup:
            raise TactileSchemaError(f"{self.path}: sample ids already written: {dup[:8]}")

    def append(self, samples: TactileSamples) -> None:
        """Write one batch as a new atomic part file."""
        where = f"{self.path}: append"
        if len(samples) == 0:
            raise TactileSchemaError(f"{where}: empty batch")
        if samples.image_shape != tuple(self.references.depth.shape[1:]):
            raise TactileSchemaError(
                f"{where}: image size {samples.image_shape} differs from the shard's "
                f"{self.references.depth.shape[1:]}"
            )
        if (samples.points is not None) != self.store_points:
            raise TactileSchemaError(
                f"{where}: points {'missing' if self.store_points else 'given'} "
                f"but store_points={self.store_points}"
            )
        if len(samples) and samples.reference_index.max() >= len(self.references):
            raise TactileSchemaError(f"{where}: reference_index beyond the {len(self.references)} references")
        self._check_new_ids(samples.sample_id)
        with _atomic_h5(self._next_part()) as f:
            _write_samples(f, samples)
        self._num_samples += len(samples)
        self._completed.update(int(i) for i in samples.sample_id)

    def record_failures(self, failures: TactileFailures) -> None:
        """Record failed samples (their ids count as completed, their data are not stored)."""
        self._check_new_ids(failures.sample_id)
        with _atomic_h5(self._next_part()) as f:
            _write_failures(f.create_group("failures"), failures)
        self._completed.update(int(i) for i in failures.sample_id)

    def finalize(self) -> Path:
        """Merge the parts into the shard file (atomically) and remove the parts directory."""
        h, w = self.references.depth.shape[1:]
        parts = self._parts()
        with _atomic_h5(self.path) as out:
            out.attrs.update(self.attrs)
            r = out.create_group("references")
            r.create_dataset("depth", data=self.references.depth)
            r.create_dataset("pv_state", data=self.references.pv_state)
            r.create_dataset("label", data=self.references.label.astype(object), dtype=_STR)
            n = self._num_samples
            chunked = {"chunks": (1, h, w), "compression": "lzf"} if n else {}
            out.create_dataset("depth", (n, h, w), np.float32, **chunked)
            if self.store_points:
                pts_chunked = {"chunks": (1, h, w, 3), "compression": "lzf"} if n else {}
                out.create_dataset("points", (n, h, w, 3), np.float32, **pts_chunked)
            small = {
                "wrench": [],
                "indenter_pose": [],
                "pv_state": [],
                "reference_index": [],
                "params": [],
                "sample_id": [],
                "indenter_kind": [],
            }
            fails = []
            start = 0
            for part in parts:
                with h5py.File(part, "r") as f:
                    if "depth" in f:
                        s = _read_samples(f, str(part), self.store_points)
                        out["depth"][start : start + len(s)] = s.depth
                        if self.store_points:
                            out["points"][start : start + len(s)] = s.points
                        for k in small:
                            small[k].append(getattr(s, k))
                        start += len(s)
                    if "failures" in f:
                        fails.append(_read_failures(f["failures"]))
            if start != n:
                raise TactileSchemaError(f"{self.parts_dir}: parts hold {start} samples, expected {n}")
            widths = {"wrench": 6, "indenter_pose": 7, "pv_state": 2, "params": len(PARAM_NAMES)}
            for k, arrays in small.items():
                if k == "indenter_kind":
                    data = np.concatenate(arrays) if arrays else np.zeros(0, object)
                    out.create_dataset(k, data=data.astype(object), dtype=_STR)
                else:
                    dtype = np.int64 if k in ("reference_index", "sample_id") else np.float64
                    empty = np.zeros((0, widths[k]) if k in widths else 0, dtype)
                    out.create_dataset(k, data=np.concatenate(arrays) if arrays else empty)
            failures = (
                TactileFailures(
                    np.concatenate([x.sample_id for x in fails]),
                    np.concatenate([x.params for x in fails]),
                    np.concatenate([x.reason for x in fails]),
                )
                if fails
                else TactileFailures.empty()
            )
            _write_failures(out.create_group("failures"), failures)
        shutil.rmtree(self.parts_dir)
        return self.path
