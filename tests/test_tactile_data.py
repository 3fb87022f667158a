"""Tactile HDF5 schema (round trip, atomic resumable writes, validation) and the wrench datamodule."""

import json
import zlib

import h5py
import numpy as np
import pytest

import defgraspnets.data.tactile_schema as schema
from defgraspnets.data.tactile_datamodule import (
    TactileWrenchDataModule,
    commanded_state_keys,
    grid_size,
    normalize_depth,
    split_groups,
    split_indices,
)
from defgraspnets.data.tactile_schema import (
    PARAM_NAMES,
    SCHEMA_VERSION,
    TactileFailures,
    TactileReferences,
    TactileSamples,
    TactileSchemaError,
    TactileShardWriter,
    read_tactile_shard,
)

H, W = 6, 8


def references(value=0.15):
    depth = np.full((2, H, W), value, np.float32)
    depth[1] -= 0.002  # the inflated PV state bulges towards the pole
    depth[:, 0, 0] = np.nan  # a pixel without return
    return TactileReferences(depth, [[101325.0, 6e-4], [1.2e5, 6.1e-4]], ["free_air", "pv73"])


def samples(ids, seed=0, points=False):
    rng = np.random.default_rng(seed)
    n = len(ids)
    depth = (0.15 - 0.02 * rng.random((n, H, W))).astype(np.float32)
    depth[:, 0, 0] = np.nan
    pose = np.tile([0.0, 0.0, 0.2, 0.0, 0.0, 0.0, 1.0], (n, 1))
    pose[:, :3] += 0.01 * rng.standard_normal((n, 3))
    params = np.full((n, len(PARAM_NAMES)), np.nan)
    params[:, :4] = rng.random((n, 4))
    return TactileSamples(
        depth=depth,
        wrench=rng.standard_normal((n, 6)),
        indenter_pose=pose,
        indenter_kind=["sphere"] * n,
        pv_state=np.tile([101325.0, 6e-4], (n, 1)),
        reference_index=rng.integers(0, 2, n),
        params=params,
        sample_id=np.asarray(ids),
        points=rng.random((n, H, W, 3)).astype(np.float32) if points else None,
    )


def write_shard(path, n, seed=0, experiment="poke", reference_value=0.15):
    writer = TactileShardWriter(path, references(reference_value), experiment)
    writer.append(samples(np.arange(n), seed))
    return writer.finalize()


# --------------------------------------------------------------------------- schema
def test_round_trip_with_points_and_failures(tmp_path):
    path = tmp_path / "poke_000.h5"
    writer = TactileShardWriter(path, references(), "poke", config_yaml="seed: 3\n", store_points=True)
    a, b = samples(np.arange(5), seed=1, points=True), samples(np.arange(5, 12), seed=2, points=True)
    writer.append(a)
    writer.append(b)
    writer.record_failures(TactileFailures([12], np.zeros((1, len(PARAM_NAMES))), ["solver diverged"]))
    assert writer.finalize() == path and not (tmp_path / "poke_000.h5.parts").exists()

    shard = read_tactile_shard(path)
    s = shard.samples
    assert len(s) == 12 and s.image_shape == (H, W)
    for name in (
        "depth",
        "wrench",
        "indenter_pose",
        "pv_state",
        "reference_index",
        "params",
        "sample_id",
        "points",
    ):
        expected = np.concatenate([getattr(a, name), getattr(b, name)])
        np.testing.assert_array_equal(getattr(s, name), expected, err_msg=name)
    assert list(s.indenter_kind) == ["sphere"] * 12
    assert s.depth.dtype == np.float32 and np.isnan(s.depth[:, 0, 0]).all()
    assert shard.references.same_as(references())
    assert list(shard.failures.reason) == ["solver diverged"] and list(shard.failures.sample_id) == [12]
    assert shard.attrs["schema_version"] == SCHEMA_VERSION and shard.attrs["config_yaml"] == "seed: 3\n"
    assert shard.experiment == "poke" and shard.attrs["generator_version"] and shard.attrs["created"]
    np.testing.assert_array_equal(shard.reference_depth(), shard.references.depth[s.reference_index])
    assert read_tactile_shard(path, load_points=False).samples.points is None


def test_killed_run_resumes_without_corruption(tmp_path, monkeypatch):
    path = tmp_path / "forearm_001.h5"
    writer = TactileShardWriter(path, references(), "forearm")
    writer.append(samples(np.arange(4)))

    # the process dies in the middle of writing the next batch
    def crash(group, batch):
        group.create_dataset("depth", data=batch.depth[:1])
        raise KeyboardInterrupt("killed")

    monkeypatch.setattr(schema, "_write_samples", crash)
    with pytest.raises(KeyboardInterrupt):
        writer.append(samples(np.arange(4, 8)))
    monkeypatch.undo()
    parts = tmp_path / "forearm_001.h5.parts"
    assert sorted(p.name for p in parts.iterdir()) == ["header.h5", "part-000000.h5"]
    (parts / ".part-000001.h5.tmp-999").write_bytes(b"garbage from a hard kill")
    assert not path.exists()
    with pytest.raises(FileNotFoundError, match="unfinished run"):
        read_tactile_shard(path)

    resumed = TactileShardWriter(path, references(), "forearm")
    assert resumed.completed_sample_ids == {0, 1, 2, 3} and resumed.num_samples == 4
    assert not (parts / ".part-000001.h5.tmp-999").exists()
    with pytest.raises(TactileSchemaError, match="already written"):
        resumed.append(samples([3, 4]))
    todo = [i for i in range(10) if i not in resumed.completed_sample_ids]
    resumed.append(samples(todo, seed=5))
    resumed.finalize()
    shard = read_tactile_shard(path)
    np.testing.assert_array_equal(shard.samples.sample_id, np.arange(10))
    with pytest.raises(FileExistsError, match="already complete"):
        TactileShardWriter(path, references(), "forearm")


def test_resume_must_match_the_unfinished_run(tmp_path):
    path = tmp_path / "s.h5"
    TactileShardWriter(path, references(), "poke").append(samples([0]))
    with pytest.raises(TactileSchemaError, match="experiment"):
        TactileShardWriter(path, references(), "forearm")
    with pytest.raises(TactileSchemaError, match="reference images"):
        TactileShardWriter(path, references(0.16), "poke")


def test_invalid_batches_raise_clear_errors():
    good = samples(np.arange(3))
    with pytest.raises(TactileSchemaError, match="non-finite wrench"):
        TactileSamples(**{**_fields(good), "wrench": np.where(np.eye(3, 6) > 0, np.nan, good.wrench)})
    pose = good.indenter_pose.copy()
    pose[1, 3:] = [0.0, 0.0, 0.0, 2.0]
    with pytest.raises(TactileSchemaError, match="quaternions must be unit"):
        TactileSamples(**{**_fields(good), "indenter_pose": pose})
    with pytest.raises(TactileSchemaError, match="wrench must have shape"):
        TactileSamples(**{**_fields(good), "wrench": good.wrench[:, :3]})
    with pytest.raises(TactileSchemaError, match="depth must have shape"):
        TactileSamples(**{**_fields(good), "depth": good.depth[0]})
    with pytest.raises(TactileSchemaError, match="inf or negative"):
        TactileSamples(**{**_fields(good), "depth": -good.depth})
    with pytest.raises(TactileSchemaError, match="repeat"):
        TactileSamples(**{**_fields(good), "sample_id": [1, 1, 2]})


def _fields(s):
    names = (
        "depth",
        "wrench",
        "indenter_pose",
        "indenter_kind",
        "pv_state",
        "reference_index",
        "params",
        "sample_id",
        "points",
    )
    return {k: getattr(s, k) for k in names}


def test_writer_rejects_inconsistent_batches(tmp_path):
    writer = TactileShardWriter(tmp_path / "s.h5", references(), "poke")
    wrong = samples([0])
    wrong.depth = np.zeros((1, H + 1, W), np.float32)
    with pytest.raises(TactileSchemaError, match="image size"):
        writer.append(wrong)
    far = samples([0])
    far.reference_index[:] = 5
    with pytest.raises(TactileSchemaError, match="reference_index"):
        writer.append(far)
    with pytest.raises(TactileSchemaError, match="points given"):
        writer.append(samples([0], points=True))


def _to_version_1(f):
    """Rewrite a file (or part) as schema version 1 wrote it: params without the perturbation columns."""
    for g in (f, f.get("failures")):
        if g is not None and "params" in g:
            old = g["params"][()][:, :7]
            del g["params"]
            g["params"] = old
    if "schema_version" in f.attrs:
        f.attrs["schema_version"] = 1
        f.attrs["param_names"] = json.dumps(PARAM_NAMES[:7])


def test_version_1_shards_and_unfinished_runs_still_load(tmp_path):
    path = tmp_path / "forearm_old.h5"
    writer = TactileShardWriter(path, references(), "forearm")
    old = samples(np.arange(3))
    writer.append(old)
    writer.record_failures(TactileFailures([3], np.ones((1, len(PARAM_NAMES))), ["diverged"]))
    legacy = TactileSamples(**{**_fields(old), "params": old.params[:, :7]})  # 7-column code still works
    assert legacy.params.shape == (3, 13) and np.isnan(legacy.params[:, 7:]).all()
    parts = tmp_path / "forearm_old.h5.parts"
    for part in parts.glob("*.h5"):
        with h5py.File(part, "r+") as f:
            _to_version_1(f)
    # a version 2 writer resumes the version 1 run and adds a perturbed repeat
    resumed = TactileShardWriter(path, references(), "forearm")
    assert resumed.completed_sample_ids == {0, 1, 2, 3}
    new = samples([1962], seed=1)
    new.params[:, 7:] = [1.0, 0.001, -0.002, 0.03, 1.02, -0.05]
    resumed.append(new)
    resumed.finalize()
    for version in (2, 1):  # the merged shard, then the same shard as a finished version 1 file
        shard = read_tactile_shard(path)
        s = shard.samples
        assert s.params.shape == (4, len(PARAM_NAMES)) == (4, 13)
        np.testing.assert_array_equal(s.params[:3, :7], old.params[:, :7])
        assert np.isnan(s.params[:3, 7:]).all()  # not recorded in version 1
        if version == 2:
            assert shard.attrs["schema_version"] == SCHEMA_VERSION == 2
            np.testing.assert_array_equal(s.params[3], new.params[0])
        else:
            assert shard.attrs["schema_version"] == 1 and np.isnan(s.params[3, 7:]).all()
        assert shard.failures.params.shape == (1, 13)
        np.testing.assert_array_equal(shard.failures.params[0, :7], 1.0)
        assert np.isnan(shard.failures.params[0, 7:]).all()
        with h5py.File(path, "r+") as f:
            _to_version_1(f)


def test_reader_rejects_foreign_and_outdated_files(tmp_path):
    path = write_shard(tmp_path / "s.h5", 3)
    with h5py.File(path, "r+") as f:
        f.attrs["schema_version"] = SCHEMA_VERSION + 1
    with pytest.raises(TactileSchemaError, match="schema_version"):
        read_tactile_shard(path)
    foreign = tmp_path / "foreign.h5"
    with h5py.File(foreign, "w") as f:
        f["x"] = [1]
    with pytest.raises(TactileSchemaError, match="not a tactile dataset"):
        read_tactile_shard(foreign)
    (tmp_path / "text.h5").write_text("not hdf5")
    with pytest.raises(TactileSchemaError, match="not a readable HDF5"):
        read_tactile_shard(tmp_path / "text.h5")
    with pytest.raises(FileNotFoundError, match="not found"):
        read_tactile_shard(tmp_path / "missing.h5")


# --------------------------------------------------------------------------- datamodule
def test_normalization_against_the_reference():
    depth = np.array([[0.14, np.nan], [0.15, 0.16]], np.float32)
    ref = np.array([[0.15, 0.15], [np.nan, 0.15]], np.float32)
    x = normalize_depth(depth, ref, 0.01)
    np.testing.assert_allclose(x, [[-1.0, 0.0], [0.0, 1.0]], atol=1e-5)
    import torch

    np.testing.assert_allclose(normalize_depth(torch.from_numpy(depth), ref, 0.01).numpy(), x, atol=1e-6)
    with pytest.raises(ValueError, match="depth_scale"):
        normalize_depth(depth, ref, 0.0)


def test_datamodule_split_batches_and_combined_dataset(tmp_path):
    write_shard(tmp_path / "poke_000.h5", 50, seed=1)
    write_shard(tmp_path / "poke_001.h5", 30, seed=2)
    write_shard(tmp_path / "forearm_000.h5", 40, seed=3, experiment="forearm")

    poke = TactileWrenchDataModule([str(tmp_path / "poke_*.h5")], batch_size=16, seed=0)
    poke.setup()
    assert (len(poke.data_train), len(poke.data_val)) == (64, 16)  # 80:20 of every shard
    x, y = next(iter(poke.train_dataloader()))
    assert x.shape == (16, 1, H, W) and y.shape == (16, 6) and x.dtype == y.dtype
    # a sample is (depth - reference) / scale of its own shard row
    ds = poke.data_val.datasets[0]
    s = ds.shard.samples
    row = ds.indices[0]
    expected = normalize_depth(s.depth[row], ds.shard.references.depth[s.reference_index[row]], 0.01)
    np.testing.assert_allclose(ds[0][0][0].numpy(), expected)
    np.testing.assert_allclose(ds[0][1].numpy(), s.wrench[row].astype(np.float32))
    assert poke.reference_depth is None  # two PV states

    def val_ids(dm):
        return {
            (d.shard.path.name, int(i))
            for d in dm.data_val.datasets
            for i in d.shard.samples.sample_id[d.indices]
        }

    again = TactileWrenchDataModule([str(tmp_path / "poke_*.h5")], seed=0)
    again.setup()
    assert val_ids(again) == val_ids(poke)  # seeded
    other = TactileWrenchDataModule([str(tmp_path / "poke_*.h5")], seed=1)
    other.setup()
    assert val_ids(other) != val_ids(poke)
    forearm = TactileWrenchDataModule([str(tmp_path / "forearm_*.h5")], batch_size=400)
    forearm.setup()
    combined = TactileWrenchDataModule([str(tmp_path / "poke_*.h5"), str(tmp_path / "forearm_*.h5")])
    combined.setup()
    assert val_ids(combined) == val_ids(poke) | val_ids(forearm)  # same validation samples
    assert len(combined.data_train) == len(poke.data_train) + len(forearm.data_train)

    with pytest.raises(FileNotFoundError, match="no tactile shard"):
        TactileWrenchDataModule([str(tmp_path / "missing_*.h5")]).setup()
    with pytest.raises(ValueError, match="no training data"):
        split_indices(1, 0.6, 0, "x")


# --------------------------------------------------------------------------- split by grid state
def _val_rows(dm):
    """{(file name, row)} of a set-up datamodule's validation split."""
    return {(d.shard.path.name, int(r)) for d in dm.data_val.datasets for r in d.indices}


def _legacy_val_rows(name, n, seed=0, val_fraction=0.2):
    """The split as the datamodule made it before repeats existed (a row permutation per file)."""
    perm = np.random.default_rng([seed, zlib.crc32(name.encode())]).permutation(n)
    return {(name, int(r)) for r in perm[: int(round(val_fraction * n))]}


def _forearm_rows(states, repeats, n_grid, seed=0):
    """(sample ids, params) of grid ``states`` read ``repeats`` times as the generator numbers them:
    repeat k of state i has id i + k n_grid, the command of state i and a perturbation (nominal for k = 0)."""
    rng = np.random.default_rng(seed)
    ids, params = [], []
    for k in range(repeats):
        for i in states:
            row = np.full(len(PARAM_NAMES), np.nan)
            row[3:7] = [0.0025 * (i % 9), 0.1 * (i // 9), 0.003 * (1 + i % 5), 0.0]  # the command
            row[7:] = [0, 0, 0, 0, 1, 0] if k == 0 else [k, *rng.uniform(-0.005, 0.005, 3), 1.02, 0.05]
            ids.append(i + k * n_grid)
            params.append(row)
    return np.array(ids), np.array(params)


def _write_rows(path, ids, params, experiment="forearm", seed=0):
    writer = TactileShardWriter(path, references(), experiment)
    writer.append(TactileSamples(**{**_fields(samples(ids, seed)), "params": params}))
    return writer.finalize()


def test_repeats_of_a_grid_state_never_straddle_the_split(tmp_path):
    n_grid = grid_size("forearm")
    assert n_grid == 1962  # the forearm grid; repeat k of state i is sample i + 1962 k
    states = np.arange(0, 600, 10)  # 60 grid states, 5 readings each (the nominal one + 4 repeats)
    ids, params = _forearm_rows(states, 5, n_grid)
    keep = np.ones(len(ids), bool)
    keep[[3, 70, 71, 200]] = False  # failed readings: some states have fewer repeats
    ids, params = ids[keep], params[keep]
    # the generator interleaves the repeated grid over the shard files: a state's repeats lie in several
    for j in range(3):
        _write_rows(tmp_path / f"forearm_{j:03d}.h5", ids[j::3], params[j::3], seed=j)

    def val_states(dm):
        return {
            int(sid % n_grid) for d in dm.data_val.datasets for sid in d.shard.samples.sample_id[d.indices]
        }

    def train_states(dm):
        return {
            int(sid % n_grid) for d in dm.data_train.datasets for sid in d.shard.samples.sample_id[d.indices]
        }

    dm = TactileWrenchDataModule([str(tmp_path / "forearm_*.h5")], seed=0)
    dm.setup()
    val, train = val_states(dm), train_states(dm)
    assert not val & train  # no grid state on both sides
    assert val | train == set(states.tolist())
    assert len(val) == 12 and len(train) == 48  # 80:20 by states
    assert len(dm.data_train) + len(dm.data_val) == len(ids)
    assert 0.1 < len(dm.data_val) / len(ids) < 0.3  # ~20 % of the readings too
    # deterministic for a seed, whatever order the shards are listed in; another seed, another split
    again = TactileWrenchDataModule([str(tmp_path / f"forearm_{j:03d}.h5") for j in (2, 0, 1)], seed=0)
    again.setup()
    assert _val_rows(again) == _val_rows(dm)
    other = TactileWrenchDataModule([str(tmp_path / "forearm_*.h5")], seed=1)
    other.setup()
    assert val_states(other) != val and not val_states(other) & train_states(other)

    # poke ids count in the poke grid: poke samples 0..49 and forearm state 0.. are unrelated, and the
    # poke shard (no repeats) keeps its own per-file split
    write_shard(tmp_path / "poke_000.h5", 50, seed=5)
    poke = TactileWrenchDataModule([str(tmp_path / "poke_*.h5")])
    poke.setup()
    assert _val_rows(poke) == _legacy_val_rows("poke_000.h5", 50)
    combined = TactileWrenchDataModule([str(tmp_path / "poke_*.h5"), str(tmp_path / "forearm_*.h5")])
    combined.setup()
    assert _val_rows(combined) == _val_rows(poke) | _val_rows(dm)

    # ids that do not follow the grid's numbering are an error, not a silent mis-grouping
    ids, params = _forearm_rows(np.arange(5), 2, n_grid)
    params[4, 3] += 0.001  # state 4's nominal reading (shard 0) and its repeat 1 (shard 1) disagree
    _write_rows(tmp_path / "bad" / "forearm_000.h5", ids[:5], params[:5])
    _write_rows(tmp_path / "bad" / "forearm_001.h5", ids[5:], params[5:])
    with pytest.raises(ValueError, match="different commands"):
        TactileWrenchDataModule([str(tmp_path / "bad" / "forearm_*.h5")]).setup()
    _write_rows(tmp_path / "far" / "forearm_000.h5", [2 * n_grid + 1], params[-1:])  # repeat 1, id of 2
    with pytest.raises(ValueError, match="not a state of a forearm grid of 1962"):
        TactileWrenchDataModule([str(tmp_path / "far" / "forearm_000.h5")]).setup()


def test_shards_without_repeats_split_exactly_as_before(tmp_path):
    # version 2, one pass over the grid (repeat 0 everywhere), rows stored out of id order
    ids, params = _forearm_rows(np.arange(37), 1, grid_size("forearm"))
    order = np.random.default_rng(0).permutation(len(ids))
    _write_rows(tmp_path / "forearm_000.h5", ids[order], params[order])
    write_shard(tmp_path / "forearm_001.h5", 23, seed=1, experiment="forearm")  # repeat NaN (poke-like)
    write_shard(tmp_path / "forearm_002.h5", 41, seed=2, experiment="forearm")
    with h5py.File(tmp_path / "forearm_002.h5", "r+") as f:  # a finished version 1 file
        _to_version_1(f)
    assert read_tactile_shard(tmp_path / "forearm_002.h5").attrs["schema_version"] == 1
    for seed in (0, 3):
        dm = TactileWrenchDataModule([str(tmp_path / "forearm_*.h5")], seed=seed)
        dm.setup()
        expected = set()
        for name, n in (("forearm_000.h5", 37), ("forearm_001.h5", 23), ("forearm_002.h5", 41)):
            expected |= _legacy_val_rows(name, n, seed)
        assert _val_rows(dm) == expected
    # grouping one reading per state is the row split itself
    for n in (1, 7, 50):
        for got, want in zip(split_groups(np.arange(n) * 3 + 2, 0.2, 4, "k"), split_indices(n, 0.2, 4, "k")):
            np.testing.assert_array_equal(got, want)
    train, val = split_groups([7, 7, 1, 9, 1, 7, 4, 4, 2, 3], 0.2, 0, "k")
    groups = np.array([7, 7, 1, 9, 1, 7, 4, 4, 2, 3])
    assert len(set(groups[val])) == 1 and not set(groups[val]) & set(groups[train])  # 1 of 5 groups


# --------------------------------------------------------------------------- identical commands, other ids
FOREARM_FIELDS = ("depth", "shear_direction", "shear_distance", "twist")
POKE_FIELDS = ("phi", "contact_radius", "theta", "depth")
# the forearm grid's twist psi = +0 and -0 at depth m / 400 m: one pure press under two ids
FOREARM_TWINS = [(1800 + 18 * m, 1809 + 18 * m) for m in range(9)]


def _grid_rows(grid, fields, states, repeats=1, seed=0):
    """(sample ids, params) of ``states`` of a real command grid, numbered as the generator does
    (repeat k of state i: id i + k len(grid), a perturbation for k >= 1, none recorded for poking)."""
    rng = np.random.default_rng(seed)
    ids, params = [], []
    for k in range(repeats):
        for i in states:
            row = np.full(len(PARAM_NAMES), np.nan)
            for name in fields:
                row[PARAM_NAMES.index(name)] = getattr(grid[i], name)
            if fields == FOREARM_FIELDS:
                row[7:] = [0, 0, 0, 0, 1, 0] if k == 0 else [k, *rng.uniform(-0.005, 0.005, 3), 1.02, 0.05]
            ids.append(i + k * len(grid))
            params.append(row)
    return np.array(ids), np.array(params)


def _side_by_id(dm, n_grid=None):
    """{state id: set of sides ('train'/'val')} of a set-up datamodule (ids mod ``n_grid``)."""
    sides = {}
    for side, data in (("train", dm.data_train), ("val", dm.data_val)):
        for d in data.datasets:
            for sid in d.shard.samples.sample_id[d.indices]:
                sides.setdefault(int(sid % n_grid) if n_grid else int(sid), set()).add(side)
    return sides


def test_commanded_state_keys_find_the_grid_twins():
    from defgraspnets.tactile.indenters import forearm_grid, poke_grid

    def classes(grid, fields, experiment):
        _, params = _grid_rows(grid, fields, range(len(grid)))
        keys = commanded_state_keys(params, experiment)
        assert np.isfinite(keys).all()
        _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
        inverse = inverse.ravel()
        return [np.flatnonzero(inverse == c).tolist() for c in np.flatnonzero(counts > 1)]

    forearm = forearm_grid()
    twins = classes(forearm, FOREARM_FIELDS, "forearm")
    assert sorted(map(tuple, twins)) == FOREARM_TWINS  # 9 pairs, nothing else (no shear of distance 0)
    for a, b in FOREARM_TWINS:
        assert forearm[a].twist == forearm[b].twist == 0 and forearm[a].shear_distance == 0
        assert np.signbit(forearm[b].twist) and forearm[a].depth == forearm[b].depth
    poke = poke_grid()
    pole = classes(poke, POKE_FIELDS, "poke")
    assert sorted(map(len, pole)) == [40] * 5  # the pole poke, every phi, at each of the 5 depths
    assert all(poke[i].contact_radius == poke[i].theta == 0 for c in pole for i in c)
    # a shear of distance 0 is the press whatever its direction; unrecorded params group nothing
    press = np.full((3, len(PARAM_NAMES)), np.nan)
    press[:, 3:7] = [[0.01, 0.0, 0.0, -0.0], [0.01, 1.3, 0.0, 0.0], [0.01, 1.3, 1e-12, 0.0]]
    keys = commanded_state_keys(press, "forearm")
    assert (keys[0] == keys[1]).all() and (keys[1] == keys[2]).all()  # within COMMAND_TOLERANCE
    press[2, 5] = 0.003
    assert not (commanded_state_keys(press, "forearm")[2] == keys[0]).all()
    press[1, 6] = np.nan
    assert np.isnan(commanded_state_keys(press, "forearm")[1]).all()
    assert np.isnan(commanded_state_keys(press, "other")).all()


def test_identical_commands_never_straddle_the_split(tmp_path):
    from defgraspnets.tactile.indenters import forearm_grid, poke_grid

    forearm = forearm_grid()
    n = len(forearm)
    # the whole forearm grid with a repeat; 4 interleaved files put the twins of a pair in different ones
    ids, params = _grid_rows(forearm, FOREARM_FIELDS, range(n), repeats=2)
    for j in range(4):
        _write_rows(tmp_path / "rep" / f"forearm_{j:03d}.h5", ids[j::4], params[j::4], seed=j)
    # one pass (no repeats), in 3 files as the generator writes it: a twin pair in one file (one path)
    ids1, params1 = _grid_rows(forearm, FOREARM_FIELDS, range(n))
    for j in range(3):
        _write_rows(tmp_path / "once" / f"forearm_{j:03d}.h5", ids1[j::3], params1[j::3], seed=j)
    # poking: the 200 pole pokes (40 phi x 5 depths) and every 7th other state, over 5 files
    poke = poke_grid()
    pole = [i for i, c in enumerate(poke) if c.contact_radius == c.theta == 0]
    states = sorted(set(pole) | set(range(0, len(poke), 7)))
    pids, pparams = _grid_rows(poke, POKE_FIELDS, states)
    names = [f"poke_{j:03d}.h5" for j in range(5)]
    for j, name in enumerate(names):
        _write_rows(tmp_path / "poke" / name, pids[j::5], pparams[j::5], experiment="poke", seed=j)
    pole_classes = [[i for i in pole if poke[i].depth == d] for d in sorted({poke[i].depth for i in pole})]

    straddled_before = 0
    for seed in range(5):
        # repeats: the twins of a pair join the side of the pair's smaller id; all else as before
        dm = TactileWrenchDataModule([str(tmp_path / "rep" / "forearm_*.h5")], seed=seed)
        dm.setup()
        sides = _side_by_id(dm, n)
        assert all(len(s) == 1 for s in sides.values())  # repeats stay together, as before
        assert all(sides[a] == sides[b] for a, b in FOREARM_TWINS)  # and so do the twins
        base_val = set(split_indices(n, 0.2, seed, "forearm")[1].tolist())  # grouped split, all n states
        expected = base_val - {b for _, b in FOREARM_TWINS} | {b for a, b in FOREARM_TWINS if a in base_val}
        assert {i for i, s in sides.items() if s == {"val"}} == expected
        straddled_before += sum((a in base_val) != (b in base_val) for a, b in FOREARM_TWINS)

        # one pass: rows of the twins' file(s) keep the per-file split except the larger twin
        once = TactileWrenchDataModule([str(tmp_path / "once" / "forearm_*.h5")], seed=seed)
        once.setup()
        sides = _side_by_id(once)
        for a, b in FOREARM_TWINS:
            assert sides[a] == sides[b] and len(sides[a]) == 1
        moved = {(f"forearm_{b % 3:03d}.h5", b // 3) for _, b in FOREARM_TWINS}
        legacy = set().union(
            *(_legacy_val_rows(f"forearm_{j:03d}.h5", len(ids1[j::3]), seed) for j in range(3))
        )
        assert _val_rows(once) - moved == legacy - moved

        # poking: each depth's 40 pole pokes on one side, across the 5 files and in any listing order
        pk = TactileWrenchDataModule([str(tmp_path / "poke" / "poke_*.h5")], seed=seed)
        pk.setup()
        sides = _side_by_id(pk)
        for c in pole_classes:
            assert len(set().union(*(sides[i] for i in c))) == 1
        rows = {int(i): (names[j], r) for j in range(5) for r, i in enumerate(pids[j::5])}
        legacy = set().union(*(_legacy_val_rows(name, len(pids[j::5]), seed) for j, name in enumerate(names)))
        twins = {rows[i] for c in pole_classes for i in c[1:]}  # all but the representative (smallest id)
        assert _val_rows(pk) - twins == legacy - twins  # the other rows, representatives included: as before
        straddled_before += sum(len({rows[i] in legacy for i in c}) > 1 for c in pole_classes)
        again = TactileWrenchDataModule([str(tmp_path / "poke" / n_) for n_ in reversed(names)], seed=seed)
        again.setup()
        assert _val_rows(again) == _val_rows(pk)
    assert straddled_before > 0  # the split by ids alone put twins on both sides
