"""Generation of the tactile datasets of thesis §3.3 on the FEM sensor: finger poking and forearm support.

Both experiments are grids of commands (:func:`~defgraspnets.tactile.indenters.poke_grid`,
:func:`~defgraspnets.tactile.indenters.forearm_grid`); a sample's id is its command's index in the grid,
so any subset (a small default, a shard of a cluster job, a resumed run) names its samples the same way.

The commands are simulated as *paths*, as the robot collected them: every poke (phi, rho, theta) is
one indentation read at each of its depths; every forearm shear is one press at depth delta followed by
the shear distances in order (the contact is dragged with Coulomb friction by the FEM engine), every
twist one press followed by the twist angles. A path costs about as much as its deepest state alone.

Both grids name a few states twice. In the forearm grid the twists psi = +0 and -0 of a depth
(m / 400 m: ids 1800 + 18 m and 1809 + 18 m, m = 0..8) are the same pure press; twist 0 joins that
depth's direction-0 shear path, which reads the press twice before its shears (9 pairs). In the poke
grid the pole poke (rho = 0, theta = 0: pushed along -z at the pole) is the same for all 40 phi, 40
paths per depth (5 states, 40 ids each). No shear has distance 0. The ids stay (shards, resumes and
repeats name samples by them); the wrench CNN's split keeps such twins on one side
(:func:`defgraspnets.data.tactile_datamodule.commanded_state_keys`).

Repeats (thesis §3.3: "the forearm experiments are repeated 4 more times so that a total of 8640
datapoints are collected"). The simulator is deterministic, so a plain repeat would reproduce the first
pass bit for bit; here repeat k >= 1 of every forearm path presses a *re-placed* forearm, as a real
re-placement in the brace would: the forearm is moved by (offset_x, offset_y) [m] along the sensor's
tangent axes x (along the forearm) and y (across it), turned by yaw [rad] about the sensor axis z, its
radius scaled by radius_scale (the section of a tapered forearm under the sensor changes with its
placement) and the skin-membrane Coulomb coefficient shifted by friction_offset (skin friction varies
between sessions). Each value is drawn uniformly within +- the magnitudes of a
:class:`ForearmPerturbation` (radius_scale within 1 +- radius_spread) by a generator seeded with
(seed, repeat, the path's first grid id), so the draw of a path does not depend on sharding, batching or
resume order. Repeat 0 is the nominal grid, unchanged. The device's motions (press, shear, twist about
the sensor axis) are the commanded ones in every repeat. Repeat k of grid state i has sample id
i + k n (n: the grid size, 1962), and every reading stores its repeat and perturbation in its params
(``PERTURBATION_PARAM_NAMES``), so a user can see which placement produced it. Streamed (``stream``),
paths of every radius share one batch, each problem with its path's indenter radius
(:meth:`~defgraspnets.fem.QuasiStaticSolver.set_body_radius`); in batches, paths of one radius are
batched together (one simulator, one inflation, per radius).

Each reading is stored as a :class:`~defgraspnets.data.tactile_schema.TactileSamples` row: the
camera's depth image, the base wrench (the force and torque the indenter exerts on the sensor, sensor
frame, about its origin: what the wrist F/T sensor of the thesis reads), the indenter's pose and the
command's parameters. Readings whose equilibrium failed, or whose indenter lost contact or left the
workspace, are recorded under ``failures/`` with the reason and never stored as data.
"""

from __future__ import annotations

import logging
from collections import defaultdict
from collections.abc import Mapping
from dataclasses import dataclass, fields, replace

import numpy as np
from scipy.spatial.transform import Rotation

from defgraspnets.data.tactile_schema import (
    PARAM_NAMES,
    PERTURBATION_PARAM_NAMES,
    TactileFailures,
    TactileReferences,
    TactileSamples,
    TactileShardWriter,
)
from defgraspnets.tactile.indenters import (
    CapsuleIndenter,
    ForearmCommand,
    IndenterError,
    PokeCommand,
    Pose,
    SphereIndenter,
)
from defgraspnets.tactile.membrane import ATMOSPHERIC_PRESSURE
from defgraspnets.tactile.sensor import Indentation, MembraneSimulator

__all__ = [
    "ForearmPerturbation",
    "TactilePath",
    "forearm_paths",
    "generate_tactile_dataset",
    "generate_tactile_from_config",
    "generate_tactile_shard",
    "make_simulator",
    "poke_paths",
    "select_paths",
    "sensor_references",
]

log = logging.getLogger(__name__)

_BACKOFF = 0.01  # m: indentations start this far before the undeformed contact point


@dataclass(frozen=True)
class TactilePath:
    """One simulated path: a press (``indentation``) and the readings taken along it.

    ``levels`` are fractions of the press depth (an indentation series) or, when ``motions`` is given,
    the press is read after each rigid motion (L, 4, 4) of the indenter in the sensor frame. ``ids``
    and ``params`` (L, len(PARAM_NAMES)) name each reading. ``radius_scale`` (the indenter's radius
    relative to the simulator's) and ``friction_offset`` (added to the simulator's Coulomb coefficient)
    are the physical part of a repeat's perturbation (the pose part is in ``indentation``).
    """

    indentation: Indentation
    ids: np.ndarray
    params: np.ndarray
    levels: np.ndarray | None = None
    motions: np.ndarray | None = None
    radius_scale: float = 1.0
    friction_offset: float = 0.0

    @property
    def kind(self) -> tuple:
        """Paths of one kind, length and indenter radius are simulated in one batch."""
        if self.motions is None:
            return ("series", tuple(np.round(self.levels, 12)), self.radius_scale)
        return ("motion", len(self.motions), self.radius_scale)


@dataclass(frozen=True)
class ForearmPerturbation:
    """How the repeats of the forearm experiment re-place the forearm (module docstring).

    Every repeat k >= 1 of a path draws, uniformly and independently, its forearm offset along the
    sensor x axis (along the forearm) in [-offset_x, offset_x] and along y (across it) in
    [-offset_y, offset_y] [m], its yaw about the sensor z axis in [-yaw, yaw] [rad], its radius scale in
    [1 - radius_spread, 1 + radius_spread] and its friction offset in [-friction_spread,
    friction_spread] (added to the Coulomb coefficient), from a generator seeded with (seed, k, key).
    Zero magnitudes switch a perturbation off. The defaults are the config's (configs/datagen/tactile.yaml):
    a braced forearm re-placed within 5 mm and 5 degrees, its radius within 5 %, friction within 0.1.

    Raises:
        ValueError: a magnitude is negative or not finite, ``radius_spread`` >= 1 (the radius would not
            stay > 0) or ``seed`` is not an integer >= 0; the message names the config key.
    """

    offset_x: float = 0.005
    offset_y: float = 0.005
    yaw: float = 0.0873
    radius_spread: float = 0.05
    friction_spread: float = 0.1
    seed: int = 0

    def __post_init__(self):
        for name in ("offset_x", "offset_y", "yaw", "radius_spread", "friction_spread"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float, np.number)):
                raise ValueError(f"perturbation.{name} must be a number, got {value!r}")
            if not (np.isfinite(value) and value >= 0):
                raise ValueError(f"perturbation.{name} must be a finite magnitude >= 0, got {value!r}")
            object.__setattr__(self, name, float(value))
        if self.radius_spread >= 1:
            raise ValueError(
                "perturbation.radius_spread must be < 1 (the forearm radius is scaled by 1 +- radius_spread, "
                f"which must stay > 0), got {self.radius_spread!r}"
            )
        if isinstance(self.seed, bool) or not isinstance(self.seed, (int, np.integer)) or self.seed < 0:
            raise ValueError(f"perturbation.seed must be an integer >= 0, got {self.seed!r}")
        object.__setattr__(self, "seed", int(self.seed))

    @classmethod
    def from_mapping(cls, values: Mapping | ForearmPerturbation | None) -> ForearmPerturbation:
        """From a config mapping (e.g. the ``perturbation`` block); None = the defaults."""
        if values is None:
            return cls()
        if isinstance(values, cls):
            return values
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(values) - names)
        if unknown:
            raise ValueError(f"unknown perturbation keys {unknown}; known: {sorted(names)}")
        return cls(**dict(values))

    def draw(self, repeat: int, key: int) -> dict[str, float]:
        """The perturbation of repeat ``repeat`` of the path ``key`` (its first grid id): a dict over
        ``PERTURBATION_PARAM_NAMES``. Repeat 0 is the nominal placement."""
        if repeat == 0:
            values = (0.0, 0.0, 0.0, 0.0, 1.0, 0.0)
        else:
            u = np.random.default_rng([self.seed, int(repeat), int(key)]).uniform(-1.0, 1.0, 5)
            values = (
                repeat,
                u[0] * self.offset_x,
                u[1] * self.offset_y,
                u[2] * self.yaw,
                1.0 + u[3] * self.radius_spread,
                u[4] * self.friction_spread,
            )
        return dict(zip(PERTURBATION_PARAM_NAMES, map(float, values)))

    @property
    def is_zero(self) -> bool:
        """No perturbation at all: every repeat would reproduce repeat 0."""
        magnitudes = (self.offset_x, self.offset_y, self.yaw, self.radius_spread, self.friction_spread)
        return not any(magnitudes)


def _check_repeats(repeats) -> int:
    if isinstance(repeats, bool) or not isinstance(repeats, (int, np.integer)) or repeats < 1:
        raise ValueError(f"repeats must be an integer >= 1 (1 = the grid once), got {repeats!r}")
    return int(repeats)


def _params(**values) -> np.ndarray:
    row = np.full(len(PARAM_NAMES), np.nan)
    for k, v in values.items():
        row[PARAM_NAMES.index(k)] = v
    return row


def poke_paths(commands: dict[int, PokeCommand], indenter: SphereIndenter, sensor) -> list[TactilePath]:
    """Group poke commands {sample id: command} into indentation series (one per phi, rho, theta)."""
    groups: dict[tuple, list[tuple[int, PokeCommand]]] = defaultdict(list)
    for i, c in commands.items():
        groups[(c.phi, c.contact_radius, c.theta)].append((i, c))
    paths = []
    dims = sensor.dimensions
    for (phi, rho, theta), members in groups.items():
        members.sort(key=lambda m: m[1].depth)
        deepest = members[-1][1]
        if deepest.depth <= 0:
            raise IndenterError(f"poke path phi={phi:g}, rho={rho:g}, theta={theta:g} has no positive depth")
        d = deepest.direction()
        p, n = dims.outer_surface_point(phi, rho)
        start = Pose(p + indenter.radius * n - _BACKOFF * d)
        paths.append(
            TactilePath(
                indentation=Indentation(start, deepest.depth, tuple(d)),
                ids=np.array([i for i, _ in members]),
                params=np.stack(
                    [
                        _params(phi=c.phi, contact_radius=c.contact_radius, theta=c.theta, depth=c.depth)
                        for _, c in members
                    ]
                ),
                levels=np.array([c.depth for _, c in members]) / deepest.depth,
            )
        )
    return paths


def _forearm_motion(c: ForearmCommand) -> np.ndarray:
    """The forearm's rigid motion in the sensor frame for a device shear / twist (ForearmCommand)."""
    T = np.eye(4)
    R = Rotation.from_rotvec([0.0, 0.0, -c.twist]).as_matrix()
    shear = c.shear_distance * np.array([np.cos(c.shear_direction), np.sin(c.shear_direction), 0.0])
    T[:3, :3] = R
    T[:3, 3] = -R @ shear
    return T


def forearm_paths(
    commands: dict[int, ForearmCommand],
    forearm: CapsuleIndenter,
    sensor,
    repeats: int = 1,
    perturbation: ForearmPerturbation | Mapping | None = None,
    grid_size: int | None = None,
) -> list[TactilePath]:
    """Group forearm commands into press-and-move paths: one per (depth, shear direction) for shears
    (distances in increasing order) and one per (depth, twist sense) for twists (angles in increasing
    magnitude). The forearm lies across the pole along the sensor x axis, as :class:`ForearmCommand`.

    With ``repeats`` > 1 the paths of repeat 0 (the nominal grid, exactly the paths of ``repeats=1``)
    are followed by those of repeats 1, 2, ... on a forearm re-placed by ``perturbation`` (module
    docstring); repeat k of command i has sample id ``i + k * grid_size`` (default: the largest command
    id + 1, the grid size for the whole grid) and draws its perturbation from (seed, k, the path's
    first command id).
    """
    repeats = _check_repeats(repeats)
    perturbation = ForearmPerturbation.from_mapping(perturbation)
    groups: dict[tuple, list[tuple[int, ForearmCommand]]] = defaultdict(list)
    for i, c in commands.items():
        if c.shear_distance > 0 and c.twist != 0:
            raise IndenterError(f"forearm command {i} both shears and twists; the thesis does one at a time")
        key = ("shear", c.depth, c.shear_direction) if c.twist == 0 else ("twist", c.depth, np.sign(c.twist))
        groups[key].append((i, c))
    if grid_size is None:
        grid_size = max(commands, default=-1) + 1
    elif commands and not int(grid_size) > max(commands):
        raise ValueError(f"grid_size {grid_size!r} must exceed the largest command id {max(commands)}")
    for members in groups.values():
        members.sort(key=lambda m: (m[1].shear_distance, abs(m[1].twist)))
    paths = []
    for repeat in range(repeats):
        for key, members in groups.items():
            ids = np.array([i for i, _ in members])
            draw = perturbation.draw(repeat, int(ids.min()))
            height = forearm.radius * draw["radius_scale"] + _BACKOFF  # nominal: exactly radius + backoff
            top = sensor.dimensions.outer_pole + np.array([draw["offset_x"], draw["offset_y"], height])
            yaw = Rotation.from_rotvec([0.0, 0.0, draw["yaw"]])
            pose = Pose(top) if repeat == 0 else Pose.from_rotation(top, yaw)
            paths.append(
                TactilePath(
                    indentation=Indentation(pose, key[1], (0.0, 0.0, -1.0)),
                    ids=ids + repeat * int(grid_size),
                    params=np.stack(
                        [
                            _params(
                                depth=c.depth,
                                shear_direction=c.shear_direction,
                                shear_distance=c.shear_distance,
                                twist=c.twist,
                                **draw,
                            )
                            for _, c in members
                        ]
                    ),
                    motions=np.stack([_forearm_motion(c) for _, c in members]),
                    radius_scale=float(draw["radius_scale"]),
                    friction_offset=float(draw["friction_offset"]),
                )
            )
    return paths


def sensor_references(sim: MembraneSimulator, label: str = "") -> TactileReferences:
    """The undeformed depth image of the simulator's gas state, as the shard's single reference."""
    ref = sim.reference
    frame = sim.reference_depth()
    pressure = ATMOSPHERIC_PRESSURE + ref.gauge_pressure
    return TactileReferences(
        depth=frame.depth[None],
        pv_state=np.array([[pressure, ref.gas_volume]]),
        label=np.array([label or f"P={pressure:.0f}Pa V={ref.gas_volume * 1e6:.1f}cm3"]),
    )


def _base_friction(sim: MembraneSimulator) -> float:
    return float(next(b.friction for b in sim.solver.bodies if b.name == "indenter"))


def _scaled_simulator(sim: MembraneSimulator, scale: float) -> MembraneSimulator:
    """A simulator like ``sim`` (sensor, gas state, friction, camera, solver) whose indenter's radius is
    scaled by ``scale``. Its idle indenter is far away, so its inflated reference equals ``sim``'s."""
    if not isinstance(sim.indenter, (SphereIndenter, CapsuleIndenter)):
        raise IndenterError(f"only sphere and capsule radii can be scaled, got {type(sim.indenter).__name__}")
    return MembraneSimulator(
        sim.sensor,
        replace(sim.indenter, radius=sim.indenter.radius * scale),
        sim.gas,
        closed=sim.closed,
        batch_size=sim.batch_size,
        friction=_base_friction(sim),
        intrinsics=None if sim.camera is None else sim.camera.intrinsics,
        options=sim.solver.options,
        inflation_steps=sim._inflation_steps,
        device=sim.solver.device,
    )


def _simulate(sim: MembraneSimulator, batch: list[TactilePath], max_step: float, barrier: bool = False):
    """Simulate one batch (one kind, one radius) with each path's friction offset (``barrier``: poke paths
    wait for each other at every load step, :meth:`MembraneSimulator.indent_series`)."""
    items = [p.indentation for p in batch]
    offsets = np.array([p.friction_offset for p in batch])
    base = _base_friction(sim)
    if np.any(offsets != 0):
        mu = np.full(sim.batch_size, base)
        mu[: len(batch)] += offsets
        if np.any(mu < 0):
            raise ValueError(
                f"friction {base:g} + a path's friction offset {offsets.min():g} is negative: "
                "perturbation.friction_spread must not exceed the friction"
            )
        sim.solver.set_friction("indenter", mu)
    try:
        if batch[0].motions is None:
            return sim.indent_series(items, batch[0].levels, render=True, max_step=max_step, barrier=barrier)
        motions = np.stack([p.motions for p in batch], axis=1)  # (L, n, 4, 4)
        return sim.press_and_move(items, motions, render=True, max_step=max_step)
    finally:
        if np.any(offsets != 0):
            sim.solver.set_friction("indenter", base)


def generate_tactile_shard(
    sim: MembraneSimulator,
    paths: list[TactilePath],
    writer: TactileShardWriter,
    max_step: float = 0.002,
    progress: bool = True,
    _simulators: dict | None = None,
    barrier: bool = False,
    stream: bool = False,
) -> dict:
    """Simulate ``paths`` (skipping those whose samples the writer already holds) and append them.

    Paths are batched ``sim.batch_size`` at a time (same kind, length and indenter radius). Paths of a
    perturbed repeat (:class:`ForearmPerturbation`) run with their friction offset on ``sim``'s
    Coulomb coefficient and, when their radius is scaled, on a copy of ``sim`` with the scaled
    indenter (built once per radius; one copy is kept at a time). Every batch is written as one atomic
    part, so an interrupted run resumes where it stopped.

    ``stream``: the paths flow through the batch instead (:meth:`MembraneSimulator.indent_stream` for
    poking, :meth:`MembraneSimulator.press_and_move_stream` for the forearm's press-and-move paths: a
    problem takes the next path as soon as it has finished one; every path starts from the exact inflated
    state with its own load-step count), and every ``sim.batch_size`` finished paths are written as one
    part.

    Returns:
        counts: ``samples`` written, ``failed`` readings, ``skipped`` paths (already done), ``paths``.
    """
    done = writer.completed_sample_ids
    todo = [p for p in paths if not set(p.ids.tolist()) <= done]
    kind = "sphere" if isinstance(sim.indenter, SphereIndenter) else "capsule"
    by_kind: dict[tuple, list[TactilePath]] = defaultdict(list)
    for p in todo:  # a stream takes paths of any length and indenter radius: one group per method
        by_kind[p.motions is None if stream else p.kind].append(p)
    counts = {"samples": 0, "failed": 0, "skipped": len(paths) - len(todo), "paths": len(todo)}
    sims = {1.0: sim} if _simulators is None else _simulators

    def simulator(scale: float) -> MembraneSimulator:
        if scale not in sims:
            for old in [k for k in sims if k != 1.0]:
                del sims[old]
            sims[scale] = _scaled_simulator(sim, scale)
        return sims[scale]

    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(
            total=sum(len(p.ids) for p in todo), desc=f"tactile {writer.attrs['experiment']}", unit="state"
        )
    for group in by_kind.values():
        if stream:
            _stream_paths(sim, group, writer, kind, max_step, counts, bar)
            continue
        for batch in (group[i : i + sim.batch_size] for i in range(0, len(group), sim.batch_size)):
            try:
                readings = _simulate(simulator(batch[0].radius_scale), batch, max_step, barrier)
            except IndenterError as error:
                if len(batch) > 1:  # some path leaves the workspace: simulate them one at a time
                    for p in batch:
                        one = generate_tactile_shard(sim, [p], writer, max_step, False, sims, barrier)
                        counts["samples"] += one["samples"]
                        counts["failed"] += one["failed"]
                    if bar is not None:
                        bar.update(sum(len(p.ids) for p in batch))
                    continue
                _write_outcome(writer, kind, _failed_path(batch[0]), f"workspace: {error}", counts)
            else:
                outcome = [
                    (batch[b], level, _usable(r))
                    for level, per_item in enumerate(readings)
                    for b, r in enumerate(per_item)
                ]
                _write_outcome(writer, kind, outcome, _FAILED_READING, counts)
            if bar is not None:
                bar.update(sum(len(p.ids) for p in batch))
    if bar is not None:
        bar.close()
    return counts


_FAILED_READING = "no equilibrium, or the indenter lost contact (mesh too coarse for the indenter)"


def _usable(reading):
    """The reading if it is an answer (converged, rendered), else None (a failure)."""
    return reading if reading.converged and reading.depth is not None else None


def _failed_path(path: TactilePath) -> list[tuple]:
    return [(path, level, None) for level in range(len(path.ids))]


def _stream_paths(sim, group, writer, kind, max_step, counts, bar) -> None:
    """Paths of one kind through :meth:`MembraneSimulator.indent_stream` (poking) or
    :meth:`MembraneSimulator.press_and_move_stream` (the forearm's press-and-move paths); every
    ``sim.batch_size`` finished paths are written as one part (those that do not suit the workspace are
    recorded as failures, as they are found)."""
    pending: list[tuple] = []
    finished = [0]

    def on_invalid(i, error):
        _write_outcome(writer, kind, _failed_path(group[i]), f"workspace: {error}", counts)
        if bar is not None:
            bar.update(len(group[i].ids))

    def on_readings(i, readings):
        p = group[i]
        pending.extend((p, level, _usable(r)) for level, r in enumerate(readings))
        finished[0] += 1
        if finished[0] % sim.batch_size == 0:
            _write_outcome(writer, kind, pending, _FAILED_READING, counts)
            pending.clear()
        if bar is not None:
            bar.update(len(p.ids))

    base = _base_friction(sim)
    indentations = [p.indentation for p in group]
    options = {
        "render": True,
        "max_step": max_step,
        "friction": [base + p.friction_offset for p in group],
        "on_invalid": on_invalid,
        "radius_scale": [p.radius_scale for p in group],
    }
    if group[0].motions is None:
        sim.indent_stream(indentations, [p.levels for p in group], on_readings, **options)
    else:
        sim.press_and_move_stream(indentations, [p.motions for p in group], on_readings, **options)
    if pending:
        _write_outcome(writer, kind, pending, _FAILED_READING, counts)


def _write_outcome(
    writer: TactileShardWriter, kind: str, outcome: list[tuple], reason: str, counts: dict
) -> None:
    """Append (path, level, reading or None) triples: readings as samples, None as failures (``reason``);
    samples written before an interruption are not written again."""
    ref = writer.references
    # ids written before an interruption (a path's samples and failures are separate parts) are kept
    done = writer.completed_sample_ids
    outcome = [(p, level, r) for p, level, r in outcome if int(p.ids[level]) not in done]
    good = sorted((o for o in outcome if o[2] is not None), key=lambda o: o[0].ids[o[1]])
    bad = [o for o in outcome if o[2] is None]
    if good:
        writer.append(
            TactileSamples(
                depth=np.stack([r.depth.depth for _, _, r in good]),
                points=np.stack([r.depth.points for _, _, r in good]) if writer.store_points else None,
                wrench=np.stack([r.base_wrench for _, _, r in good]),
                indenter_pose=np.stack([r.indenter_pose.to_array() for _, _, r in good]),
                indenter_kind=np.array([kind] * len(good)),
                pv_state=np.repeat(ref.pv_state[:1], len(good), axis=0),
                reference_index=np.zeros(len(good), dtype=np.int64),
                params=np.stack([p.params[level] for p, level, _ in good]),
                sample_id=np.array([p.ids[level] for p, level, _ in good]),
            )
        )
        counts["samples"] += len(good)
    if bad:
        writer.record_failures(
            TactileFailures(
                np.array([p.ids[level] for p, level, _ in bad]),
                np.stack([p.params[level] for p, level, _ in bad]),
                np.array([reason] * len(bad), dtype=object),
            )
        )
        counts["failed"] += len(bad)
        log.warning("%d tactile readings failed (recorded under failures/): %s", len(bad), reason)


def select_paths(
    paths: list[TactilePath],
    stride: int = 1,
    limit: int | None = None,
    shard_index: int = 0,
    shard_count: int = 1,
) -> list[TactilePath]:
    """Every ``stride``-th path of the grid (a spread-out subset), at most ``limit`` of them, then the
    ``shard_index``-th of ``shard_count`` interleaved shards of those (``chosen[shard_index::shard_count]``:
    the shards are disjoint, cover the selection exactly, and each one spreads over the whole grid, so
    independent processes can generate them in parallel and any finished subset is a fair sample).
    With repeats, the grid is the repeated one (repeat 0's paths first, :func:`forearm_paths`); every
    path carries its own perturbation, so a path's readings do not depend on the selection."""
    if int(stride) < 1 or (limit is not None and int(limit) < 1):
        raise ValueError(f"stride must be >= 1 and limit >= 1 or None, got {stride!r}, {limit!r}")
    if int(shard_count) < 1 or not 0 <= int(shard_index) < int(shard_count):
        raise ValueError(
            "shard_index must lie in [0, shard_count) with shard_count >= 1, "
            f"got {shard_index!r} of {shard_count!r}"
        )
    chosen = paths[:: int(stride)]
    chosen = chosen if limit is None else chosen[: int(limit)]
    return chosen[int(shard_index) :: int(shard_count)]


def make_simulator(
    sensor,
    indenter,
    gauge_pressure: float,
    closed: bool,
    batch_size: int = 1,
    friction: float = 0.5,
    intrinsics=None,
    options=None,
    device: str | None = None,
    contact_subdivisions: int | None = None,
) -> MembraneSimulator:
    """The sensor at its pre-contact gas state: inflated to ``gauge_pressure`` [Pa], then either kept
    at that pressure (open) or sealed there (closed: PV = P V of the inflated state, Boyle's law from
    then on; the thesis's sealed sensor). ``options``: FEM solver options (None: the sensor's default,
    :func:`~defgraspnets.tactile.sensor.membrane_solver_options`); ``device``: Warp device of the solves
    and the camera (None: Warp's default); ``contact_subdivisions``: sub-vertex contact n (None: the
    options' value, 1 by default)."""
    from defgraspnets.tactile.camera import PICO_FLEXX
    from defgraspnets.tactile.membrane import PVState

    intrinsics = PICO_FLEXX if intrinsics is None else intrinsics
    neutral = sensor.cavity_volume + sensor.dimensions.housing_volume
    gas = PVState(ATMOSPHERIC_PRESSURE + gauge_pressure, neutral)
    common = dict(
        batch_size=batch_size,
        friction=friction,
        intrinsics=intrinsics,
        options=options,
        device=device,
        contact_subdivisions=contact_subdivisions,
    )
    sim = MembraneSimulator(sensor, indenter, gas, closed=False, **common)
    if not closed:
        return sim
    volume = sim.reference.gas_volume
    sealed = PVState.from_pv((ATMOSPHERIC_PRESSURE + gauge_pressure) * volume, volume, "sealed")
    return MembraneSimulator(sensor, indenter, sealed, closed=True, **common)


def generate_tactile_dataset(
    experiment: str,
    out_path,
    sensor,
    indenter,
    gauge_pressure: float,
    closed: bool = True,
    friction: float = 0.5,
    batch_size: int = 1,
    stride: int = 1,
    limit: int | None = None,
    max_step: float = 0.002,
    intrinsics=None,
    store_points: bool = False,
    config_text: str = "",
    shard_index: int = 0,
    shard_count: int = 1,
    progress: bool = True,
    repeats: int = 1,
    perturbation: ForearmPerturbation | Mapping | None = None,
    solver_options=None,
    barrier: bool = False,
    stream: bool = False,
) -> dict:
    """Generate (or resume) one shard of the ``"poke"`` or ``"forearm"`` dataset of thesis §3.3.

    Args:
        experiment: ``"poke"`` (sphere indenter, :func:`poke_grid`) or ``"forearm"`` (capsule,
            :func:`forearm_grid`).
        out_path: the shard file; a finished one is left alone (delete it to regenerate).
        sensor, indenter: the membrane (:func:`build_membrane`) and the indenter's geometry.
        gauge_pressure, closed, friction: the gas state (:func:`make_simulator`) and Coulomb friction.
        batch_size: paths simulated together.
        stride, limit: which paths of the grid (:func:`select_paths`; 1, None = the whole grid).
        shard_index, shard_count: this shard's share of those paths (:func:`select_paths`).
        max_step: largest indenter motion per load step [m].
        barrier: the poke paths of a batch wait for each other at every load step (default: each goes on
            as soon as it reached the step; the same readings, :meth:`MembraneSimulator.indent_series`).
        stream: the paths flow through the batch (:func:`generate_tactile_shard`), a problem taking the
            next path as soon as it has finished one, instead of batches that end with their slowest path.
        repeats: passes over the forearm grid (thesis: 5, the original and 4 repeats); repeats 1, 2, ...
            re-place the forearm by ``perturbation`` (:class:`ForearmPerturbation` or its config
            mapping; None = its defaults). Poking has no repeats (``repeats`` must be 1).
        solver_options: FEM :class:`~defgraspnets.fem.SolverOptions` of the sensor (None: its default,
            :func:`~defgraspnets.tactile.sensor.membrane_solver_options`).

    Returns:
        counts of :func:`generate_tactile_shard` plus ``path``, ``seconds``, the simulator's
        ``solver_options`` and the batch's ``newton_passes`` while solving the paths (absent when the
        shard was already finished).

    Raises:
        ValueError: unknown experiment, ``repeats`` < 1 (or > 1 for poking), a bad perturbation
            magnitude, or ``perturbation.friction_spread`` larger than ``friction``; the message names
            the config key.
    """
    import time
    from pathlib import Path

    from defgraspnets.tactile.indenters import forearm_grid, poke_grid

    if experiment not in ("poke", "forearm"):
        raise ValueError(f"experiment must be 'poke' or 'forearm', got {experiment!r}")
    repeats = _check_repeats(repeats)
    perturbation = ForearmPerturbation.from_mapping(perturbation)
    if experiment == "poke" and repeats != 1:
        raise ValueError(
            f"repeats must be 1 for the poke dataset (only the forearm experiment repeats), got {repeats}"
        )
    if repeats > 1 and perturbation.friction_spread > friction:
        raise ValueError(
            f"perturbation.friction_spread ({perturbation.friction_spread:g}) must not exceed friction "
            f"({friction:g}): the Coulomb coefficient would go negative"
        )
    if repeats > 1 and perturbation.is_zero:
        log.warning("repeats=%d with a zero perturbation: every repeat reproduces repeat 0", repeats)
    out_path = Path(out_path)
    if out_path.exists():
        return {"path": str(out_path), "samples": 0, "failed": 0, "skipped": -1, "paths": 0, "seconds": 0.0}
    if experiment == "poke":
        if not isinstance(indenter, SphereIndenter):
            raise IndenterError(f"poking uses a sphere indenter, got {type(indenter).__name__}")
        paths = poke_paths(dict(enumerate(poke_grid())), indenter, sensor)
    elif experiment == "forearm":
        if not isinstance(indenter, CapsuleIndenter):
            raise IndenterError(f"the forearm is a capsule indenter, got {type(indenter).__name__}")
        grid = forearm_grid()
        paths = forearm_paths(dict(enumerate(grid)), indenter, sensor, repeats, perturbation, len(grid))
    paths = select_paths(paths, stride, limit, shard_index, shard_count)
    t0 = time.perf_counter()
    sim = make_simulator(
        sensor, indenter, gauge_pressure, closed, batch_size, friction, intrinsics, solver_options
    )
    out_path.parent.mkdir(parents=True, exist_ok=True)
    writer = TactileShardWriter(
        out_path,
        sensor_references(sim),
        experiment,
        config_yaml=config_text,
        store_points=store_points,
    )
    passes = sim.solver.newton_passes
    counts = generate_tactile_shard(
        sim, paths, writer, max_step=max_step, progress=progress, barrier=barrier, stream=stream
    )
    writer.finalize()
    counts.update(
        path=str(out_path),
        seconds=time.perf_counter() - t0,
        solver_options=sim.solver.options,
        # the batch's Newton passes while solving the paths (one assembly each, for all problems iterating)
        newton_passes=sim.solver.newton_passes - passes,
    )
    return counts


def generate_tactile_from_config(cfg: Mapping, out_path=None, config_text: str = "") -> dict:
    """Build the sensor, indenter and solver options of a ``datagen/tactile`` config (a plain mapping:
    ``dataset``, ``membrane``, ``gas``, ``friction``, ``solver``, ``indenter`` / ``forearm``, the path
    selection, batching and camera keys; configs/datagen/tactile.yaml) and generate its shard
    (:func:`generate_tactile_dataset`) at ``out_path`` (None: ``out_dir/<dataset>/<shard_name>.h5``),
    on Warp's current device. Shared by ``datagen/tactile.py`` and ``scripts/benchmark_tactile.py``."""
    from pathlib import Path

    from defgraspnets.data.output_dir import check_output_dir
    from defgraspnets.tactile.camera import PICO_FLEXX
    from defgraspnets.tactile.membrane import build_membrane
    from defgraspnets.tactile.sensor import membrane_solver_options

    if cfg["dataset"] not in ("poke", "forearm"):
        raise ValueError(f"dataset must be 'poke' or 'forearm', got {cfg['dataset']!r}")
    if out_path is None:
        check_output_dir(cfg["out_dir"])  # before the membrane is built and any state simulated
    solver_options = membrane_solver_options(cfg["device"], **dict(cfg["solver"]))
    sensor = build_membrane(cap_divisions=cfg["membrane"]["cap_divisions"], layers=cfg["membrane"]["layers"])
    if cfg["dataset"] == "poke":
        indenter = SphereIndenter(radius=cfg["indenter"]["radius"])
    else:
        indenter = CapsuleIndenter(radius=cfg["forearm"]["radius"], length=cfg["forearm"]["length"])
    if out_path is None:
        out_path = Path(cfg["out_dir"]) / cfg["dataset"] / f"{cfg['shard_name']}.h5"
    return generate_tactile_dataset(
        cfg["dataset"],
        out_path,
        sensor,
        indenter,
        gauge_pressure=cfg["gas"]["gauge_pressure"],
        closed=cfg["gas"]["closed"],
        friction=cfg["friction"],
        batch_size=cfg["batch_size"],
        stride=cfg["stride"],
        limit=cfg["limit"],
        shard_index=cfg["shard_index"],
        shard_count=cfg["shard_count"],
        max_step=cfg["max_step"],
        barrier=cfg["barrier"],
        stream=cfg["stream"],
        intrinsics=PICO_FLEXX.scaled(cfg["camera_scale"]),
        store_points=cfg["store_points"],
        config_text=config_text,
        progress=cfg["progress"],
        repeats=cfg["repeats"],
        perturbation=dict(cfg["perturbation"]),
        solver_options=solver_options,
    )
