"""Tactile dataset generation (thesis §3.3) on the FEM sensor: paths, round trip, resume, bad input."""

import numpy as np
import pytest

from defgraspnets.data.tactile_schema import TactileShardWriter, read_tactile_shard
from defgraspnets.tactile.camera import PICO_FLEXX
from defgraspnets.tactile.datasets import (
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
