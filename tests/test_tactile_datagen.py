"""Tactile dataset generation (thesis §3.3) on the FEM sensor: paths, round trip, resume, bad input."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from defgraspnets.data.tactile_schema import (
    COMMAND_PARAM_NAMES,
    PARAM_NAMES,
    PERTURBATION_PARAM_NAMES,
    TactileShardWriter,
    read_tactile_shard,
)
from defgraspnets.tactile.camera import PICO_FLEXX
from defgraspnets.tactile.datasets import (
    ForearmPerturbation,
    TactilePath,
    forearm_paths,
    generate_tactile_dataset,
    generate_tactile_shard,
    make_simulator,
    poke_paths,
    select_paths,
    sensor_references,
)
from defgraspnets.tactile.indenters import (
    FINGERTIP,
    CapsuleIndenter,
    IndenterError,
    SphereIndenter,
    forearm_grid,
    poke_grid,
)
from defgraspnets.tactile.membrane import build_membrane
from defgraspnets.tactile.sensor import MembraneSimulator

CAMERA = PICO_FLEXX.scaled(0.25)


@pytest.fixture(scope="module")
def sensor():
    return build_membrane(cap_divisions=8, layers=2)


def test_poke_paths_cover_the_grid_once():
    sensor = build_membrane(cap_divisions=4, layers=2)
    grid = dict(enumerate(poke_grid()))
    paths = poke_paths(grid, FINGERTIP, sensor)
    assert len(paths) == 40 * 5 * 10
    ids = np.concatenate([p.ids for p in paths])
    assert sorted(ids.tolist()) == list(range(10_000))
    for p in paths[:50]:
        np.testing.assert_allclose(p.levels, [0.2, 0.4, 0.6, 0.8, 1.0])
        np.testing.assert_allclose(p.params[:, 3], p.levels * p.indentation.depth)
    fore = forearm_paths(dict(enumerate(forearm_grid())), CapsuleIndenter(radius=0.04, length=0.2), sensor)
    assert sorted(np.concatenate([p.ids for p in fore]).tolist()) == list(range(len(forearm_grid())))


def test_shards_split_the_selection_disjointly_and_spread_over_the_grid():
    sensor = build_membrane(cap_divisions=4, layers=2)
    paths = poke_paths(dict(enumerate(poke_grid())), FINGERTIP, sensor)
    chosen = select_paths(paths, stride=3, limit=500)
    shards = [select_paths(paths, 3, 500, shard_index=k, shard_count=7) for k in range(7)]
    ids = [np.concatenate([p.ids for p in shard]) for shard in shards]
    assert sorted(np.concatenate(ids).tolist()) == sorted(np.concatenate([p.ids for p in chosen]).tolist())
    assert max(len(s) for s in shards) - min(len(s) for s in shards) <= 1
    # every shard reaches both ends of the selection (interleaved, not contiguous blocks)
    for shard in shards:
        assert shard[0].ids[0] < chosen[7].ids[0] and shard[-1].ids[0] > chosen[-8].ids[0]
    bad_shards = (
        {"shard_index": 7, "shard_count": 7},
        {"shard_index": -1, "shard_count": 2},
        {"shard_count": 0},
    )
    for bad in bad_shards:
        with pytest.raises(ValueError, match="shard_index"):
            select_paths(paths, **bad)


def test_poke_dataset_round_trip_and_resume(sensor, tmp_path):
    out = tmp_path / "poke.h5"
    # the first path of the grid: the pole, straight down, 0.5 to 2.5 cm
    kwargs = dict(closed=True, stride=1, limit=1, intrinsics=CAMERA, progress=False)
    counts = generate_tactile_dataset("poke", out, sensor, SphereIndenter(radius=0.01), 1500.0, **kwargs)
    assert counts["samples"] == 5 and counts["failed"] == 0
    shard = read_tactile_shard(out)
    assert shard.experiment == "poke"
    s = shard.samples
    np.testing.assert_array_equal(s.sample_id, [0, 1, 2, 3, 4])
    grid = poke_grid()
    for i, params in zip(s.sample_id, s.params):
        c = grid[i]
        np.testing.assert_allclose(params[:4], [c.phi, c.contact_radius, c.theta, c.depth])
    force = s.wrench[:, :3]
    # the indenter pushes the sensor down, harder the deeper it goes; axial up to the mesh's asymmetry
    assert np.all(force[:, 2] < 0)
    assert np.all(np.diff(-force[:, 2]) > 0)
    assert np.all(np.hypot(force[:, 0], force[:, 1]) < 0.05 * -force[:, 2])
    # the stored sphere positions went down by the commanded depths
    np.testing.assert_allclose(-np.diff(s.indenter_pose[:, 2]), 0.005, rtol=1e-9)
    # depth images: the membrane comes closer to the camera than in the reference, more so deeper
    ref = shard.references.depth[0]
    assert s.depth.shape == (5, *ref.shape)
    dent = np.nanmin(s.depth - ref[None], axis=(1, 2))
    assert np.all(dent < 0) and np.all(np.diff(dent) < 0)
    # finished shards are left alone
    again = generate_tactile_dataset("poke", out, sensor, SphereIndenter(radius=0.01), 1500.0, **kwargs)
    assert again["skipped"] == -1


@pytest.mark.slow
def test_indefinite_exact_hessians_are_damped_not_lu_solved(sensor, tmp_path, monkeypatch):
    """A tilted poke whose exact Hessian turns indefinite (path 4 of the grid: 3 Newton steps on the 2-core
    CPU): those steps get Levenberg-Marquardt damping instead of an LU step (``report_indefinite``), no LU
    factorization is ever made, and all five readings converge (~25 s)."""
    from defgraspnets.fem.system import BatchedSystem

    seen = {"indefinite": 0, "lu": 0}
    solve_banded = BatchedSystem.solve_banded

    def spy(self, *args, **kwargs):
        out = solve_banded(self, *args, **kwargs)
        seen["indefinite"] += int(self.indefinite.sum())
        factors = self._dense_factors.values()
        seen["lu"] += sum(f[0] == "lu" or (f[0] == "banded" and f[1].lu) for f in factors)
        return out

    monkeypatch.setattr(BatchedSystem, "solve_banded", spy)
    kwargs = dict(closed=True, stride=4, limit=4, shard_index=1, shard_count=4, intrinsics=CAMERA)
    out = tmp_path / "poke.h5"
    counts = generate_tactile_dataset(
        "poke", out, sensor, SphereIndenter(radius=0.01), 1500.0, progress=False, **kwargs
    )
    assert counts["samples"] == 5 and counts["failed"] == 0
    np.testing.assert_array_equal(read_tactile_shard(out).samples.sample_id, np.arange(20, 25))
    assert seen["indefinite"] > 0 and seen["lu"] == 0


def test_forearm_shear_drags_the_membrane_and_resumes(sensor, tmp_path):
    forearm = CapsuleIndenter(radius=0.04, length=0.2)
    grid = dict(enumerate(forearm_grid()))
    paths = forearm_paths(grid, forearm, sensor)
    # depth 5 mm, shear direction 2 pi 20 / 40 = pi: the device moves along -x, the forearm along +x
    path = next(p for p in paths if p.params[0, 3] == 0.005 and p.params[0, 4] == np.pi)
    sim = make_simulator(sensor, forearm, 1500.0, closed=True, intrinsics=CAMERA)
    out = tmp_path / "forearm.h5"
    writer = TactileShardWriter(out, sensor_references(sim), "forearm")
    counts = generate_tactile_shard(sim, [path], writer, progress=False)
    assert counts["samples"] == 5
    # resuming skips the finished path
    assert generate_tactile_shard(sim, [path], writer, progress=False)["skipped"] == 1
    writer.finalize()
    s = read_tactile_shard(out).samples
    f = s.wrench[:, :3]
    # friction drags the sensor along the forearm's motion (+x), at most mu N (this soft membrane lets
    # the forearm slip within the first 3 mm)
    assert np.all(f[:, 0] > 0) and np.all(np.diff(f[:, 0]) >= -1e-3 * f[0, 0])
    np.testing.assert_array_less(f[:, 0], 0.5 * -f[:, 2] * (1 + 1e-3))
    assert f[-1, 0] > 0.45 * -f[-1, 2]
    assert np.all(np.abs(f[:, 1]) < 0.05 * f[:, 0])
    # the stored poses are the forearm's, moved by the shear
    np.testing.assert_allclose(s.indenter_pose[:, 0], s.params[:, 5], atol=1e-9)


def test_bad_experiment_and_indenter_are_named(sensor, tmp_path):
    with pytest.raises(ValueError, match="experiment"):
        generate_tactile_dataset("pinch", tmp_path / "x.h5", sensor, FINGERTIP, 1500.0)
    with pytest.raises(IndenterError, match="capsule"):
        generate_tactile_dataset("forearm", tmp_path / "x.h5", sensor, FINGERTIP, 1500.0)
    assert not (tmp_path / "x.h5").exists()


# --------------------------------------------------------------------------- forearm repeats
FOREARM = CapsuleIndenter(radius=0.04, length=0.2)
PERTURB = ForearmPerturbation(
    offset_x=0.004, offset_y=0.003, yaw=0.05, radius_spread=0.1, friction_spread=0.2, seed=7
)
P = {n: i for i, n in enumerate(PARAM_NAMES)}
NOMINAL = [0.0, 0.0, 0.0, 0.0, 1.0, 0.0]  # repeat, offset_x, offset_y, yaw, radius_scale, friction_offset


@pytest.fixture(scope="module")
def small_sensor():
    return build_membrane(cap_divisions=4, layers=2)


def _perturbation_of(path: TactilePath) -> np.ndarray:
    rows = path.params[:, len(COMMAND_PARAM_NAMES) :]
    assert np.all(rows == rows[0])  # one placement for all readings of a path
    return rows[0]


def test_one_repeat_gives_exactly_the_nominal_forearm_paths(small_sensor):
    grid = forearm_grid()
    top = small_sensor.dimensions.outer_pole + np.array([0.0, 0.0, FOREARM.radius + 0.01])
    for paths in (
        forearm_paths(dict(enumerate(grid)), FOREARM, small_sensor),
        forearm_paths(dict(enumerate(grid)), FOREARM, small_sensor, 3, PERTURB, len(grid))[:378],
    ):
        assert len(paths) == 378
        assert sorted(np.concatenate([p.ids for p in paths]).tolist()) == list(range(len(grid)))
        for p in paths:
            # the forearm as before repeats existed: above the pole, along x, unscaled, nominal friction
            np.testing.assert_array_equal(p.indentation.pose.position, top)
            np.testing.assert_array_equal(p.indentation.pose.quaternion, [0.0, 0.0, 0.0, 1.0])
            assert p.indentation.direction == (0.0, 0.0, -1.0) and p.radius_scale == 1.0
            assert p.friction_offset == 0.0
            for i, row, motion in zip(p.ids, p.params, p.motions):
                c = grid[i]
                command = [np.nan, np.nan, np.nan, c.depth, c.shear_direction, c.shear_distance, c.twist]
                np.testing.assert_array_equal(row[: len(COMMAND_PARAM_NAMES)], command)
                np.testing.assert_array_equal(row[len(COMMAND_PARAM_NAMES) :], NOMINAL)
                assert c.depth == p.indentation.depth
                R = Rotation.from_rotvec([0.0, 0.0, -c.twist]).as_matrix()
                np.testing.assert_array_equal(motion[:3, :3], R)
    assert len(PARAM_NAMES) == len(COMMAND_PARAM_NAMES) + len(PERTURBATION_PARAM_NAMES) == 13


def test_repeats_are_perturbed_deterministically_within_bounds(small_sensor):
    grid = forearm_grid()
    n = len(grid)
    commands = dict(enumerate(grid))
    paths = forearm_paths(commands, FOREARM, small_sensor, 3, PERTURB, n)
    assert len(paths) == 3 * 378
    ids = np.concatenate([p.ids for p in paths])
    assert sorted(ids.tolist()) == list(range(3 * n))  # repeat k of state i is i + k n
    again = forearm_paths(commands, FOREARM, small_sensor, 3, PERTURB, n)
    nominal = {int(p.ids.min()): p for p in paths[:378]}
    draws = {1: [], 2: []}
    for p, q in zip(paths, again):
        np.testing.assert_array_equal(p.params, q.params)
        np.testing.assert_array_equal(p.indentation.pose.to_array(), q.indentation.pose.to_array())
        k = int(p.ids.min()) // n
        base = nominal[int(p.ids.min()) - k * n]
        d = _perturbation_of(p)
        assert d[0] == k
        if k == 0:
            continue
        draws[k].append(d)
        # same command and motions as its nominal path, a different forearm placement
        np.testing.assert_array_equal(p.ids, base.ids + k * n)
        np.testing.assert_array_equal(p.params[:, :7], base.params[:, :7])
        np.testing.assert_array_equal(p.motions, base.motions)
        assert np.all(d[1:] != np.array(NOMINAL[1:]))
        # the stored perturbation is the simulated one
        r = FOREARM.radius * d[4]
        top = small_sensor.dimensions.outer_pole + [d[1], d[2], r + 0.01]
        np.testing.assert_allclose(p.indentation.pose.position, top, rtol=0, atol=1e-15)
        np.testing.assert_allclose(p.indentation.pose.rotation.as_rotvec(), [0, 0, d[3]], atol=1e-12)
        assert p.radius_scale == d[4] and p.friction_offset == d[5]
    for rows in draws.values():
        d = np.array(rows)
        bounds = [
            PERTURB.offset_x,
            PERTURB.offset_y,
            PERTURB.yaw,
            PERTURB.radius_spread,
            PERTURB.friction_spread,
        ]
        assert np.all(np.abs(d[:, 1:] - NOMINAL[1:]) <= bounds)
        # every path draws its own placement, spread over the range, not one per repeat
        assert len(np.unique(d[:, 1])) == 378
        assert np.all(np.abs(d[:, 1:] - NOMINAL[1:]).max(axis=0) > 0.9 * np.array(bounds))
    assert not np.array_equal(np.array(draws[1]), np.array(draws[2]))
    # another seed, another placement; zero magnitudes: the repeat is the nominal path
    other = forearm_paths(commands, FOREARM, small_sensor, 2, {**vars(PERTURB), "seed": 8}, n)
    assert _perturbation_of(other[400])[1] != _perturbation_of(paths[400])[1]
    zero = ForearmPerturbation(offset_x=0, offset_y=0, yaw=0, radius_spread=0, friction_spread=0)
    same = forearm_paths(commands, FOREARM, small_sensor, 2, zero, n)
    a, b = same[400].indentation, same[400 - 378].indentation
    np.testing.assert_array_equal(a.pose.to_array(), b.pose.to_array())
    assert a.depth == b.depth and same[400].radius_scale == 1.0 and same[400].friction_offset == 0


def test_repeat_perturbations_do_not_depend_on_sharding_or_subsets(small_sensor):
    grid = forearm_grid()
    commands = dict(enumerate(grid))
    paths = forearm_paths(commands, FOREARM, small_sensor, 5, PERTURB, len(grid))
    assert len(paths) == 5 * 378
    by_id = {int(p.ids[0]): p for p in paths}

    def same(p):
        q = by_id[int(p.ids[0])]
        np.testing.assert_array_equal(p.ids, q.ids)
        np.testing.assert_array_equal(p.params, q.params, strict=True)
        np.testing.assert_array_equal(p.indentation.pose.to_array(), q.indentation.pose.to_array())
        assert (p.radius_scale, p.friction_offset) == (q.radius_scale, q.friction_offset)

    for stride, limit, count in ((1, None, 7), (3, 200, 4), (97, 8, 3)):
        shards = [select_paths(paths, stride, limit, k, count) for k in range(count)]
        chosen = select_paths(paths, stride, limit)
        assert sorted(int(p.ids[0]) for s in shards for p in s) == sorted(int(p.ids[0]) for p in chosen)
        for shard in shards:
            for p in shard:
                same(p)
    # the thesis scale reaches the perturbed repeats in every shard
    for k in range(16):
        assert max(int(p.ids[0]) for p in select_paths(paths, 1, None, k, 16)) >= 4 * len(grid)
    # a subset of the commands (some paths only) draws the same placements for those paths
    subset = {i: c for i, c in commands.items() if c.depth == 0.005 and c.twist <= 0}
    for p in forearm_paths(subset, FOREARM, small_sensor, 5, PERTURB, len(grid)):
        same(p)


def test_bad_repeat_config_raises_naming_the_key(sensor, tmp_path):
    bad = (
        ({"offset_x": -0.001}, "perturbation.offset_x"),
        ({"offset_y": float("nan")}, "perturbation.offset_y"),
        ({"yaw": -0.1}, "perturbation.yaw"),
        ({"radius_spread": 1.0}, "perturbation.radius_spread"),
        ({"radius_spread": -0.1}, "perturbation.radius_spread"),
        ({"friction_spread": float("inf")}, "perturbation.friction_spread"),
        ({"friction_spread": "0.1"}, "perturbation.friction_spread"),
        ({"seed": -1}, "perturbation.seed"),
        ({"seed": 0.5}, "perturbation.seed"),
        ({"offset": 0.01}, "unknown perturbation keys"),
    )
    for values, key in bad:
        with pytest.raises(ValueError, match=key):
            ForearmPerturbation.from_mapping(values)
    grid = dict(enumerate(forearm_grid()))
    for repeats in (0, -2, 1.5, True):
        with pytest.raises(ValueError, match="repeats"):
            forearm_paths(grid, FOREARM, sensor, repeats=repeats)
    with pytest.raises(ValueError, match="grid_size"):
        forearm_paths(grid, FOREARM, sensor, 2, grid_size=10)
    out = tmp_path / "x.h5"
    kwargs = dict(closed=True, intrinsics=CAMERA, progress=False)
    with pytest.raises(ValueError, match="repeats"):
        generate_tactile_dataset("forearm", out, sensor, FOREARM, 1500.0, repeats=0, **kwargs)
    with pytest.raises(ValueError, match="repeats must be 1 for the poke"):
        generate_tactile_dataset(
            "poke", out, sensor, SphereIndenter(radius=0.01), 1500.0, repeats=5, **kwargs
        )
    with pytest.raises(ValueError, match="perturbation.friction_spread"):
        generate_tactile_dataset("forearm", out, sensor, FOREARM, 1500.0, friction=0.05, repeats=2, **kwargs)
    with pytest.raises(ValueError, match="perturbation.yaw"):
        generate_tactile_dataset(
            "forearm", out, sensor, FOREARM, 1500.0, repeats=2, perturbation={"yaw": -1.0}, **kwargs
        )
    assert not out.exists() and not (tmp_path / "x.h5.parts").exists()


def test_config_perturbation_block_is_valid():
    from pathlib import Path

    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    root = Path(__file__).resolve().parents[1]
    with initialize_config_dir(config_dir=str(root / "configs"), version_base="1.3"):
        cfg = compose(config_name="datagen/tactile", overrides=[f"paths.root_dir={root}"])
        thesis = compose(config_name="datagen/tactile", overrides=["repeats=5", "perturbation.seed=3"])
        plain = compose(config_name="datagen/tactile", overrides=["solver.contact_smoothing=0"])
    assert cfg.repeats == 1
    # solver.*: null keeps the sensor's defaults; a set key reaches the FEM options
    from defgraspnets.tactile.sensor import membrane_solver_options

    default = membrane_solver_options("cpu", **OmegaConf.to_container(cfg.solver))
    assert default == membrane_solver_options("cpu")
    assert membrane_solver_options("cpu", **OmegaConf.to_container(plain.solver)).contact_smoothing == 0.0
    p = ForearmPerturbation.from_mapping(OmegaConf.to_container(cfg.perturbation))
    assert p == ForearmPerturbation()  # the documented defaults are the config's
    assert thesis.repeats == 5 and ForearmPerturbation.from_mapping(thesis.perturbation).seed == 3


def test_perturbed_forearm_repeat_round_trip(small_sensor, tmp_path):
    """One tiny solve (coarsest membrane): the first reading (3 mm shear along +x) of a perturbed 5 mm
    press, batched (a simulator of the scaled forearm) and streamed (the batch's problem takes the scaled
    radius). Off the symmetric nominal placement the cap-8 membrane solves ~3x slower (~25 s here)."""
    sensor = small_sensor
    grid = forearm_grid()
    n = len(grid)
    friction = 0.5
    perturbation = ForearmPerturbation(
        offset_x=0.004, offset_y=0.004, yaw=0.1, radius_spread=0.1, friction_spread=0.3, seed=11
    )
    paths = forearm_paths(dict(enumerate(grid)), FOREARM, sensor, 2, perturbation, n)
    full = next(p for p in paths[378:] if p.params[0, 3] == 0.005 and p.params[0, 4] == np.pi)
    d = _perturbation_of(full)
    assert d[0] == 1 and d[4] != 1.0 and d[5] < 0  # this seed: a scaled radius, lower friction
    path = TactilePath(
        full.indentation,
        full.ids[:1],
        full.params[:1],
        motions=full.motions[:1],
        radius_scale=full.radius_scale,
        friction_offset=full.friction_offset,
    )
    shards = {}
    for stream in (False, True):  # its own simulator with the scaled forearm / one problem's radius set
        sim = make_simulator(sensor, FOREARM, 1500.0, closed=True, friction=friction, intrinsics=CAMERA)
        out = tmp_path / f"forearm_repeat_{stream}.h5"
        writer = TactileShardWriter(out, sensor_references(sim), "forearm")
        counts = generate_tactile_shard(sim, [path], writer, progress=False, stream=stream)
        assert counts == {"samples": 1, "failed": 0, "skipped": 0, "paths": 1}
        assert np.all(sim.solver._friction == friction)  # the shared simulator's friction is restored
        assert np.all(sim.solver._radius == FOREARM.radius)  # and its radius
        writer.finalize()
        shards[stream] = read_tactile_shard(out).samples
    s = shards[False]
    for name in ("wrench", "depth", "indenter_pose", "params"):  # streamed: the same reading, bit for bit
        np.testing.assert_array_equal(getattr(shards[True], name), getattr(s, name), err_msg=name)
    np.testing.assert_array_equal(s.sample_id, full.ids[:1])
    assert s.sample_id[0] >= n
    np.testing.assert_array_equal(s.params, full.params[:1])  # the perturbation is stored per reading
    # the stored forearm pose: re-placed by (offset_x, offset_y), yawed, moved 3 mm along +x by the shear
    np.testing.assert_allclose(s.indenter_pose[0, :2], [d[1] + 0.003, d[2]], atol=1e-9)
    np.testing.assert_allclose(
        Rotation.from_quat(s.indenter_pose[0, 3:]).as_rotvec(), [0, 0, d[3]], atol=1e-9
    )
    f = s.wrench[0, :3]
    assert f[2] < 0 and f[0] > 0
    # friction drags the sensor along +x; the forearm slips, at the perturbed coefficient (not 0.5)
    mu = friction + d[5]
    assert 0.9 * mu * -f[2] < f[0] <= mu * -f[2] * (1 + 1e-3)


def _two_runs_into_one_shard(sensor, indenter, paths, out, experiment, stream):
    """A shard written by a run over the first two paths, then a resumed run over all of them:
    (the first run's counts, the second's, the finished shard's samples)."""
    sim = make_simulator(sensor, indenter, 1500.0, closed=True, batch_size=2, intrinsics=CAMERA)
    writer = TactileShardWriter(out, sensor_references(sim), experiment)
    first = generate_tactile_shard(sim, paths[:2], writer, progress=False, stream=stream)
    counts = generate_tactile_shard(sim, paths, writer, progress=False, stream=stream)
    writer.finalize()
    return first, counts, read_tactile_shard(out).samples


def test_streamed_poke_paths_match_batches_and_resume(small_sensor, tmp_path):
    """stream=True: three poke paths flow through two problems (each from the exact inflated membrane);
    the shard holds the samples the batches give, to the solver's tolerance, and a second run over more
    paths appends only the new ones."""
    sphere = SphereIndenter(radius=0.02)  # wider than the coarsest membrane's vertex spacing
    grid = dict(enumerate(poke_grid()))
    paths = [
        TactilePath(p.indentation, p.ids[:2], p.params[:2], levels=p.levels[:2])
        for p in select_paths(poke_paths(grid, sphere, small_sensor), 97, 3)
    ]
    shards = {}
    for stream in (False, True):
        out = tmp_path / f"poke_{stream}.h5"
        first, counts, shards[stream] = _two_runs_into_one_shard(
            small_sensor, sphere, paths, out, "poke", stream
        )
        assert first["samples"] + first["failed"] == 4
        assert counts["skipped"] == 2 and counts["paths"] == 1
        assert counts["samples"] + counts["failed"] == 2
    a, b = shards[False], shards[True]
    np.testing.assert_array_equal(np.sort(b.sample_id), np.sort(a.sample_id))
    assert len(a.sample_id) == 6
    order_a, order_b = np.argsort(a.sample_id), np.argsort(b.sample_id)
    np.testing.assert_allclose(
        b.wrench[order_b], a.wrench[order_a], rtol=0, atol=2e-3 * np.abs(a.wrench).max()
    )
    np.testing.assert_array_equal(b.params[order_b], a.params[order_a])
    np.testing.assert_allclose(b.indenter_pose[order_b], a.indenter_pose[order_a], atol=1e-9)


def test_streamed_forearm_paths_match_batches_and_resume(small_sensor, tmp_path, monkeypatch):
    """stream=True for the forearm's press-and-move paths: shears and a twist of different lengths flow
    through two problems (press_and_move_stream); the shard holds the samples the batches give, to the
    solver's tolerance, and a second run appends only the paths not yet written."""
    grid = dict(enumerate(forearm_grid()))
    nominal = forearm_paths(grid, FOREARM, small_sensor)
    shears = [p for p in nominal if p.params[0, 3] == 0.005 and p.params[0, 4] in (0.0, np.pi / 2)]
    twist = next(p for p in nominal if p.params[0, 3] == 0.005 and p.params[0, 6] > 0)
    paths = [  # shears of 3, 6 (, 9) mm along x and y; twists of 7.5 and 15 deg
        TactilePath(p.indentation, p.ids[rows], p.params[rows], motions=p.motions[rows])
        for p, rows in zip([*shears, twist], (slice(2, 4), slice(2, 5), slice(0, 2)))
    ]
    assert len(paths) == 3 and paths[2].params[1, 6] > paths[2].params[0, 6] > 0
    streamed = []
    original = MembraneSimulator.press_and_move_stream

    def spy(self, indentations, *args, **kwargs):
        streamed.append(len(indentations))
        return original(self, indentations, *args, **kwargs)

    monkeypatch.setattr(MembraneSimulator, "press_and_move_stream", spy)
    shards = {}
    for stream in (False, True):
        out = tmp_path / f"forearm_{stream}.h5"
        first, counts, shards[stream] = _two_runs_into_one_shard(
            small_sensor, FOREARM, paths, out, "forearm", stream
        )
        assert first["samples"] == 5 and first["failed"] == 0
        assert counts["skipped"] == 2 and counts["paths"] == 1 and counts["samples"] == 2
    assert streamed == [2, 1]  # the streamed runs: all paths of any length in one stream, then the rest
    a, b = shards[False], shards[True]
    order_a, order_b = np.argsort(a.sample_id), np.argsort(b.sample_id)
    np.testing.assert_array_equal(b.sample_id[order_b], a.sample_id[order_a])
    np.testing.assert_array_equal(b.params[order_b], a.params[order_a])
    np.testing.assert_allclose(b.indenter_pose[order_b], a.indenter_pose[order_a], atol=1e-9)
    np.testing.assert_allclose(
        b.wrench[order_b], a.wrench[order_a], rtol=0, atol=5e-3 * np.abs(a.wrench).max()
    )
    assert np.abs(b.wrench[:, :2]).max() > 0.05  # N: the shears drag the sensor sideways


def test_bad_dataset_key_and_out_dir_are_named_before_any_work(tmp_path, monkeypatch):
    """`dataset=foo` names the config key (not the library argument), and an out_dir that is a file is refused
    before the membrane is built: nothing is simulated or written."""
    from pathlib import Path

    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    import defgraspnets.tactile.membrane as membrane
    from defgraspnets.tactile.datasets import generate_tactile_from_config

    def no_build(*args, **kwargs):
        raise AssertionError("the membrane was built before the config was checked")

    monkeypatch.setattr(membrane, "build_membrane", no_build)
    root = Path(__file__).resolve().parents[1]
    afile = tmp_path / "afile"
    afile.write_text("x")
    with initialize_config_dir(config_dir=str(root / "configs"), version_base="1.3"):
        bad_name = compose(
            config_name="datagen/tactile",
            overrides=["dataset=foo", f"out_dir={tmp_path}", f"paths.root_dir={root}"],
        )
        bad_dir = compose(
            config_name="datagen/tactile", overrides=[f"out_dir={afile}", f"paths.root_dir={root}"]
        )
    with pytest.raises(ValueError, match="dataset must be 'poke' or 'forearm', got 'foo'"):
        generate_tactile_from_config(OmegaConf.to_container(bad_name))
    with pytest.raises(NotADirectoryError, match=f"out_dir {afile} is a file, not a directory"):
        generate_tactile_from_config(OmegaConf.to_container(bad_dir))
    assert afile.read_text() == "x" and sorted(p.name for p in tmp_path.iterdir()) == ["afile"]
