"""Generation of the tactile datasets of thesis §3.3 on the FEM sensor: finger poking and forearm support.

Both experiments are grids of commands (:func:`~defgraspnets.tactile.indenters.poke_grid`,
:func:`~defgraspnets.tactile.indenters.forearm_grid`); a sample's id is its command's index in the grid,
so any subset (a small default, a shard of a cluster job, a resumed run) names its samples the same way.

The commands are simulated as *paths*, as the robot collected them: every poke (phi, rho, theta) is
one indentation read at each of its depths; every forearm shear is one press at depth delta followed by
the shear distances in order (the contact is dragged with Coulomb friction by the FEM engine), every
twist one press followed by the twist angles. A path costs about as much as its deepest state alone.

Each reading is stored as a :class:`~defgraspnets.data.tactile_schema.TactileSamples` row: the
camera's depth image, the base wrench (the force and torque the indenter exerts on the sensor, sensor
frame, about its origin: what the wrist F/T sensor of the thesis reads), the indenter's pose and the
command's parameters. Readings whose equilibrium failed, or whose indenter lost contact or left the
workspace, are recorded under ``failures/`` with the reason and never stored as data.
"""

from __future__ import annotations

import logging
from collections import defaultdict
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from defgraspnets.data.tactile_schema import (
    PARAM_NAMES,
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
    "TactilePath",
    "forearm_paths",
    "generate_tactile_dataset",
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
    and ``params`` (L, 7) name each reading.
    """

    indentation: Indentation
    ids: np.ndarray
    params: np.ndarray
    levels: np.ndarray | None = None
    motions: np.ndarray | None = None

    @property
    def kind(self) -> tuple:
        """Paths of one kind and length are simulated in one batch."""
        if self.motions is None:
            return ("series", tuple(np.round(self.levels, 12)))
        return ("motion", len(self.motions))


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


def forearm_paths(commands: dict[int, ForearmCommand], forearm: CapsuleIndenter, sensor) -> list[TactilePath]:
    """Group forearm commands into press-and-move paths: one per (depth, shear direction) for shears
    (distances in increasing order) and one per (depth, twist sense) for twists (angles in increasing
    magnitude). The forearm lies across the pole along the sensor x axis, as :class:`ForearmCommand`."""
    groups: dict[tuple, list[tuple[int, ForearmCommand]]] = defaultdict(list)
    for i, c in commands.items():
        if c.shear_distance > 0 and c.twist != 0:
            raise IndenterError(f"forearm command {i} both shears and twists; the thesis does one at a time")
        key = ("shear", c.depth, c.shear_direction) if c.twist == 0 else ("twist", c.depth, np.sign(c.twist))
        groups[key].append((i, c))
    top = sensor.dimensions.outer_pole + np.array([0.0, 0.0, forearm.radius + _BACKOFF])
    paths = []
    for key, members in groups.items():
        members.sort(key=lambda m: (m[1].shear_distance, abs(m[1].twist)))
        depth = key[1]
        paths.append(
            TactilePath(
                indentation=Indentation(Pose(top), depth, (0.0, 0.0, -1.0)),
                ids=np.array([i for i, _ in members]),
                params=np.stack(
                    [
                        _params(
                            depth=c.depth,
                            shear_direction=c.shear_direction,
                            shear_distance=c.shear_distance,
                            twist=c.twist,
                        )
                        for _, c in members
                    ]
                ),
                motions=np.stack([_forearm_motion(c) for _, c in members]),
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


def _simulate(sim: MembraneSimulator, batch: list[TactilePath], max_step: float):
    items = [p.indentation for p in batch]
    if batch[0].motions is None:
        return sim.indent_series(items, batch[0].levels, render=True, max_step=max_step)
    motions = np.stack([p.motions for p in batch], axis=1)  # (L, n, 4, 4)
    return sim.press_and_move(items, motions, render=True, max_step=max_step)


def generate_tactile_shard(
    sim: MembraneSimulator,
    paths: list[TactilePath],
    writer: TactileShardWriter,
    max_step: float = 0.002,
    progress: bool = True,
) -> dict:
    """Simulate ``paths`` (skipping those whose samples the writer already holds) and append them.

    Paths are batched ``sim.batch_size`` at a time (same kind and length). Every batch is written as
    one atomic part, so an interrupted run resumes where it stopped.

    Returns:
        counts: ``samples`` written, ``failed`` readings, ``skipped`` paths (already done), ``paths``.
    """
    done = writer.completed_sample_ids
    todo = [p for p in paths if not set(p.ids.tolist()) <= done]
    kind = "sphere" if isinstance(sim.indenter, SphereIndenter) else "capsule"
    ref = writer.references
    by_kind: dict[tuple, list[TactilePath]] = defaultdict(list)
    for p in todo:
        by_kind[p.kind].append(p)
    batches = [
        group[i : i + sim.batch_size]
        for group in by_kind.values()
        for i in range(0, len(group), sim.batch_size)
    ]
    counts = {"samples": 0, "failed": 0, "skipped": len(paths) - len(todo), "paths": len(todo)}
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(
            total=sum(len(p.ids) for p in todo), desc=f"tactile {writer.attrs['experiment']}", unit="state"
        )
    for batch in batches:
        try:
            readings = _simulate(sim, batch, max_step)
        except IndenterError as error:
            if len(batch) > 1:  # some path leaves the workspace: simulate them one at a time
                for p in batch:
                    one = generate_tactile_shard(sim, [p], writer, max_step, progress=False)
                    counts["samples"] += one["samples"]
                    counts["failed"] += one["failed"]
                if bar is not None:
                    bar.update(sum(len(p.ids) for p in batch))
                continue
            readings, reason = [], f"workspace: {error}"
            outcome = [(batch[0], level, None) for level in range(len(batch[0].ids))]
        else:
            reason = "no equilibrium, or the indenter lost contact (mesh too coarse for the indenter)"
            outcome = [
                (batch[b], level, r if r.converged and r.depth is not None else None)
                for level, per_item in enumerate(readings)
                for b, r in enumerate(per_item)
            ]
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
        if bar is not None:
            bar.update(sum(len(p.ids) for p in batch))
    if bar is not None:
        bar.close()
    return counts


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
    independent processes can generate them in parallel and any finished subset is a fair sample)."""
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
) -> MembraneSimulator:
    """The sensor at its pre-contact gas state: inflated to ``gauge_pressure`` [Pa], then either kept
    at that pressure (open) or sealed there (closed: PV = P V of the inflated state, Boyle's law from
    then on; the thesis's sealed sensor)."""
    from defgraspnets.tactile.camera import PICO_FLEXX
    from defgraspnets.tactile.membrane import PVState

    intrinsics = PICO_FLEXX if intrinsics is None else intrinsics
    neutral = sensor.cavity_volume + sensor.dimensions.housing_volume
    gas = PVState(ATMOSPHERIC_PRESSURE + gauge_pressure, neutral)
    common = dict(batch_size=batch_size, friction=friction, intrinsics=intrinsics)
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

    Returns:
        counts of :func:`generate_tactile_shard` plus ``path`` and ``seconds``.
    """
    import time
    from pathlib import Path

    from defgraspnets.tactile.indenters import forearm_grid, poke_grid

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
        paths = forearm_paths(dict(enumerate(forearm_grid())), indenter, sensor)
    else:
        raise ValueError(f"experiment must be 'poke' or 'forearm', got {experiment!r}")
    paths = select_paths(paths, stride, limit, shard_index, shard_count)
    t0 = time.perf_counter()
    sim = make_simulator(sensor, indenter, gauge_pressure, closed, batch_size, friction, intrinsics)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    writer = TactileShardWriter(
        out_path,
        sensor_references(sim),
        experiment,
        config_yaml=config_text,
        store_points=store_points,
    )
    counts = generate_tactile_shard(sim, paths, writer, max_step=max_step, progress=progress)
    writer.finalize()
    counts.update(path=str(out_path), seconds=time.perf_counter() - t0)
    return counts
