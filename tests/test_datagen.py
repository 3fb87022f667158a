"""The grasp dataset generator: real squeeze ramps written as schema-valid, resumable shards."""

from __future__ import annotations

import json

import numpy as np
import pytest

from defgraspnets.data.datamodule import GraspDataModule
from defgraspnets.data.grasp_schema import GraspShard, GraspShardWriter, shard_file_name
from defgraspnets.grasp import datagen
from defgraspnets.grasp.datagen import generate_object_shards, shard_grasp_indices, structured_box

MODULI = (1e6, 1e7)
STEPS = 3
FORCE = 6.0
GRASPS = 3


def _box():
    return structured_box((0.03, 0.03, 0.03), (3, 3, 3), name="tinybox")


def _generate(out_dir, **kw):
    args = dict(youngs_modulus=MODULI, num_grasps=GRASPS, steps=STEPS, max_force=FORCE, seed=0, device="cpu")
    args.update(kw)
    return generate_object_shards(_box(), out_dir, **args)


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("grasps")
    (result,) = _generate(out)
    assert result.path == out / shard_file_name("tinybox", 0, 1) and result.total == len(MODULI) * GRASPS
    return out


def test_shard_holds_physical_fields(data_dir):
    sh = GraspShard(data_dir / "tinybox__shard0of1.h5")
    mesh = _box()
    assert (sh.num_moduli, sh.num_grasps, sh.num_steps, sh.num_vertices) == (
        2,
        GRASPS,
        STEPS,
        mesh.num_vertices,
    )
    np.testing.assert_array_equal(sh.object.youngs_modulus, MODULI)
    assert sh.object.material_model == "neohookean"  # the generator's default, recorded in the shard
    assert sh.attrs["object_category"] == "cuboid" and sh.attrs["generator_version"].startswith(
        "defgraspnets"
    )
    assert len(sh.solved()) == 2 * GRASPS  # stiff box, small force: every ramp converges
    ramp = FORCE * np.arange(1, STEPS + 1) / STEPS
    for k, g in sh.solved():
        # the total normal grasp force reached equals the prescribed ramp force
        np.testing.assert_allclose(sh.force[k, g], ramp, rtol=1e-5)
        travel = sh.finger_travel[k, g]
        assert np.all(np.diff(travel[:, 0]) > 0) and np.allclose(travel[:, 0], travel[:, 1])
        peak = []
        for s in range(STEPS):
            vm, d = sh.fields(k, g, s)
            assert vm.shape == (mesh.num_vertices,) and d.shape == (mesh.num_vertices, 3)
            assert np.all(np.isfinite(d)) and np.all(vm >= 0)
            peak.append(vm.max())
        assert np.all(np.diff(peak) > 0)
    # the softer material deforms more under the same force
    d_soft = np.abs(sh.fields(0, 0, STEPS - 1)[1]).max()
    d_stiff = np.abs(sh.fields(1, 0, STEPS - 1)[1]).max()
    assert d_soft > 3 * d_stiff
    # closing directions are the pads' +y axes and point at each other
    np.testing.assert_allclose(sh.closing_direction[:, 0], -sh.closing_direction[:, 1], atol=1e-9)
    sh.close()


def test_finished_shard_is_skipped(data_dir):
    (r,) = _generate(data_dir)
    assert r.skipped


class Killed(Exception):
    """A generation killed midway (as by a signal)."""


def _kill_after_writes(monkeypatch, n: int) -> list:
    """GraspShardWriter.write raises Killed right after its n-th entry is written; returns the (k, g)
    written so far."""
    real_write, written = GraspShardWriter.write, []

    def write_then_die(self, k, g, *a, **kw):
        real_write(self, k, g, *a, **kw)
        written.append((k, g))
        if len(written) == n:
            raise Killed

    monkeypatch.setattr(GraspShardWriter, "write", write_then_die)
    return written


def test_resume_simulates_only_missing_grasps(tmp_path, monkeypatch):
    calls = []
    real = datagen._squeeze_modulus

    def spy(ramps, grasps, material):
        calls.append(len(grasps))
        return real(ramps, grasps, material)

    monkeypatch.setattr(datagen, "_squeeze_modulus", spy)
    real_write = GraspShardWriter.write
    _kill_after_writes(monkeypatch, GRASPS + 1)  # all of modulus 0 and one grasp of modulus 1
    with pytest.raises(Killed):
        _generate(tmp_path)
    partial = tmp_path / "tinybox__shard0of1.partial.h5"
    assert partial.exists() and not (tmp_path / "tinybox__shard0of1.h5").exists()
    assert calls == [GRASPS, GRASPS]

    monkeypatch.setattr(GraspShardWriter, "write", real_write)
    calls.clear()
    (r,) = _generate(tmp_path)
    assert calls == [GRASPS - 1]  # only the unwritten grasps of modulus 1 are simulated again
    sh = GraspShard(r.path)
    assert len(sh.solved()) == 2 * GRASPS and not partial.exists()
    assert np.all(np.isfinite(sh.force))


def test_shards_record_their_solver_settings_and_are_not_resumed_with_others(data_dir, tmp_path, monkeypatch):
    """Each shard records the FEM settings that decide its equilibria (the squeeze path's defaults here,
    without the linear solver's choice); a run killed midway is not continued with other settings (a
    ValueError names what differs), is continued with another linear solver, and starts over with
    ``overwrite``."""
    from defgraspnets.grasp.datagen import solver_settings
    from defgraspnets.grasp.squeeze import squeeze_solver_options

    recorded = GraspShard(data_dir / shard_file_name("tinybox", 0, 1)).solver_settings
    assert recorded == json.loads(json.dumps(solver_settings(squeeze_solver_options())))
    assert recorded["squeeze"]["friction_lag_check"] == 1000 and "linear_solver" not in recorded["squeeze"]
    defaults = solver_settings(squeeze_solver_options())
    for solve_only in ({"factor_streams": 1}, {"banded_min_problems": 8}, {"linear_solver": "banded"}):
        assert solver_settings(squeeze_solver_options(**solve_only)) == defaults  # resumable across them
    assert "experiments" not in recorded  # squeeze ramps only

    real_write = GraspShardWriter.write
    _kill_after_writes(monkeypatch, 1)
    with pytest.raises(Killed):
        _generate(tmp_path)
    monkeypatch.setattr(GraspShardWriter, "write", real_write)
    late = squeeze_solver_options(friction_lag_check=1)
    with pytest.raises(ValueError, match=r"solver settings \(squeeze.friction_lag_check: 1000.0 -> 1.0\)"):
        _generate(tmp_path, solver_options=late)
    assert (tmp_path / "tinybox__shard0of1.partial.h5").exists()  # left as it was
    (r,) = _generate(tmp_path, solver_options=squeeze_solver_options(linear_solver="dense"))  # resumed
    assert len(GraspShard(r.path).solved()) == len(MODULI) * GRASPS
    (r,) = _generate(tmp_path, solver_options=late, overwrite=True)  # starts over
    assert GraspShard(r.path).solver_settings["squeeze"]["friction_lag_check"] == 1.0


def test_moduli_in_one_batch_give_the_same_data(data_dir, tmp_path, monkeypatch):
    """moduli_per_solver=2: both moduli's ramps in one batched solve (one problem per grasp and modulus),
    written per modulus; with the exact (dense) solver every ramp is the one solved alone per modulus."""
    calls = []
    real = datagen._squeeze_modulus

    def spy(ramps, grasps, material):
        calls.append(
            (len(grasps), [m.youngs_modulus for m in material] if isinstance(material, list) else None)
        )
        return real(ramps, grasps, material)

    monkeypatch.setattr(datagen, "_squeeze_modulus", spy)
    (r,) = _generate(tmp_path, moduli_per_solver=2)
    assert calls == [(2 * GRASPS, [MODULI[0]] * GRASPS + [MODULI[1]] * GRASPS)]
    batched, alone = GraspShard(r.path), GraspShard(data_dir / "tinybox__shard0of1.h5")
    np.testing.assert_array_equal(batched.status, alone.status)
    for k, g in alone.solved():
        np.testing.assert_allclose(batched.force[k, g], alone.force[k, g], rtol=1e-12)
        for s in range(STEPS):
            for a, b in zip(batched.fields(k, g, s), alone.fields(k, g, s)):
                np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-9 * np.abs(b).max())


def test_moduli_per_object_simulates_the_drawn_moduli_only(data_dir, tmp_path):
    """moduli_per_object=1 (the thesis's count): the shard holds one modulus, the one drawn for the object,
    and its ramps are those of the all-moduli shard at that modulus (the same grasps, solved alone)."""
    (chosen,) = datagen.object_moduli("tinybox", MODULI, per_object=1, seed=0)
    (r,) = _generate(tmp_path, moduli_per_object=1)
    one, every = GraspShard(r.path), GraspShard(data_dir / "tinybox__shard0of1.h5")
    np.testing.assert_array_equal(one.object.youngs_modulus, [chosen])
    assert r.total == GRASPS and one.num_moduli == 1
    k = MODULI.index(chosen)
    np.testing.assert_array_equal(one.status[0], every.status[k])
    np.testing.assert_array_equal(one.grasp_pose, every.grasp_pose)
    for g in range(GRASPS):
        np.testing.assert_allclose(one.force[0, g], every.force[k, g], rtol=1e-12)
        for s in range(STEPS):
            for a, b in zip(one.fields(0, g, s), every.fields(k, g, s)):
                np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-9 * np.abs(b).max())


def test_object_moduli_draws_per_object_and_keeps_the_level2_objects_whole():
    moduli = np.geomspace(1e4, 1e7, 10).tolist()
    names = [f"object_{i}" for i in range(72)]
    draws = {n: datagen.object_moduli(n, moduli, per_object=1, seed=0) for n in names}
    assert all(len(d) == 1 and d[0] in moduli for d in draws.values())
    # reproducible (a resumed run draws the same), independent of the other objects, seeded
    assert draws == {n: datagen.object_moduli(n, moduli, 1, 0) for n in reversed(names)}
    assert [datagen.object_moduli(n, moduli, 1, 1) for n in names] != list(draws.values())
    assert len({d[0] for d in draws.values()}) >= 8  # the moduli are spread over the objects
    three = datagen.object_moduli("object_0", moduli, per_object=3, seed=0)
    assert len(set(three)) == 3 and three == sorted(three)  # distinct, in the list's order
    assert datagen.object_moduli("object_0", moduli, None) == moduli
    assert datagen.object_moduli("object_0", moduli, 1, 0, all_moduli_objects=["object_0"]) == moduli


def test_an_object_is_claimed_once(tmp_path):
    """claim_dir: the first worker to claim an object gets it, every later claim (any process) is refused;
    a file path claims under a flat name (no directories made from it)."""
    claims = tmp_path / "claims"
    assert datagen.claim_object(claims, "cuboid_30x30x30")
    assert not datagen.claim_object(claims, "cuboid_30x30x30")
    assert datagen.claim_object(claims, "lemon")
    assert datagen.claim_object(claims, "/data/meshes/mug.vtu")
    assert not datagen.claim_object(claims, "/data/meshes/mug.vtu")
    assert sorted(p.name for p in claims.iterdir()) == ["_data_meshes_mug.vtu", "cuboid_30x30x30", "lemon"]


def test_failed_ramps_are_not_marked_solved(tmp_path, monkeypatch):
    real = datagen._squeeze_modulus

    def fail_one(*args, **kwargs):
        out = real(*args, **kwargs)
        out["status"][1] = 1  # as if grasp 1 had not converged
        return out

    monkeypatch.setattr(datagen, "_squeeze_modulus", fail_one)
    (r,) = _generate(tmp_path, youngs_modulus=(1e7,), num_grasps=2, steps=2)
    sh = GraspShard(r.path)
    assert sh.status.tolist() == [[0, 1]] and sh.solved().tolist() == [[0, 0]]


def test_rotations_per_axis_sets_how_many_grasps_share_contact_points(tmp_path, monkeypatch):
    """``rotations_per_axis=1`` puts every grasp of a shard on its own axis (new contact points each); the
    thesis's 4 turn the approach about shared axes. The FEM is not what is tested here: skipped."""
    from defgraspnets.data.splits import grasp_axis_ids

    def no_fem(ramps, grasps, material):
        G, N, steps, max_force = len(grasps), ramps.mesh.num_vertices, ramps.steps, ramps.max_force
        return {
            "force": np.tile(np.linspace(max_force / steps, max_force, steps), (G, 1)),
            "von_mises": np.zeros((G, steps, N), dtype=np.float32),
            "displacement": np.zeros((G, steps, N, 3), dtype=np.float32),
            "finger_travel": np.zeros((G, steps, 2)),
            "status": np.zeros(G, dtype=np.int8),
        }

    monkeypatch.setattr(datagen, "_squeeze_modulus", no_fem)
    axes = {}
    for k in (1, 4):
        (r,) = _generate(tmp_path / f"rot{k}", youngs_modulus=(1e6,), num_grasps=8, rotations_per_axis=k)
        sh = GraspShard(r.path)
        assert len(sh.grasp_pose) == 8
        ids = grasp_axis_ids(sh.grasp_pose, sh.closing_direction)
        axes[k] = np.bincount(ids)
    assert axes[1].tolist() == [1] * 8
    assert len(axes[4]) <= 4 and axes[4].max() >= 2


def test_really_failing_solve_is_recorded(tmp_path):
    # a far too large force for a very soft box: the ramp must not be stored as an answer
    (r,) = _generate(tmp_path, youngs_modulus=(1e3,), num_grasps=1, steps=1, max_force=50.0)
    sh = GraspShard(r.path)
    assert sh.status[0, 0] != 0 and len(sh.solved()) == 0
    assert np.all(np.isnan(sh.fields(0, 0, 0)[0])) and np.isnan(sh.force[0, 0]).all()


def _dense(**kw):
    from defgraspnets.grasp.squeeze import squeeze_solver_options

    return dict(solver_options=squeeze_solver_options(linear_solver="dense"), **kw)


def test_streamed_ramps_give_the_same_data_bit_for_bit(tmp_path, monkeypatch):
    """stream_slots=2: the shard's 6 ramps (2 moduli x 3 grasps) flow through 2 problems, each written when
    done; with the exact dense solver every ramp is bit for bit the one of the per-modulus batches."""
    (batched,) = _generate(tmp_path / "batched", **_dense())
    monkeypatch.setattr(datagen, "_squeeze_modulus", None)  # the stream never builds batches
    order = []
    real_write = GraspShardWriter.write

    def spy_write(self, k, g, *a, **kw):
        order.append((k, g))
        real_write(self, k, g, *a, **kw)

    monkeypatch.setattr(GraspShardWriter, "write", spy_write)
    (streamed,) = _generate(tmp_path / "streamed", **_dense(stream_slots=2))
    assert sorted(order) == [(k, g) for k in range(2) for g in range(GRASPS)]
    a, b = GraspShard(batched.path), GraspShard(streamed.path)
    assert len(a.solved()) == 2 * GRASPS
    np.testing.assert_array_equal(a.status, b.status)
    for key in ("force", "finger_travel"):
        np.testing.assert_array_equal(getattr(a, key), getattr(b, key))
    for k, g in a.solved():
        for s in range(STEPS):
            for x, y in zip(a.fields(k, g, s), b.fields(k, g, s)):
                np.testing.assert_array_equal(x, y)


def test_a_killed_stream_resumes_with_the_unwritten_ramps(tmp_path, monkeypatch):
    """A streamed generation killed after 4 of 6 ramps were written simulates only the other 2 when run
    again, and ends with the shard an uninterrupted run writes."""
    real_write = GraspShardWriter.write
    written = _kill_after_writes(monkeypatch, 4)
    with pytest.raises(Killed):
        _generate(tmp_path / "resumed", **_dense(stream_slots=2))
    monkeypatch.setattr(GraspShardWriter, "write", real_write)
    streamed = []
    real_stream = datagen._squeeze_streamed

    def spy(ramps, grasps, jobs, *args):
        streamed.append(list(jobs))
        return real_stream(ramps, grasps, jobs, *args)

    monkeypatch.setattr(datagen, "_squeeze_streamed", spy)
    (r,) = _generate(tmp_path / "resumed", **_dense(stream_slots=2))
    assert len(streamed) == 1 and sorted(streamed[0]) == sorted(
        set((k, g) for k in range(2) for g in range(GRASPS)) - set(written)
    )
    # killed after its last entry, before the shard was finalized: the re-run solves nothing, finalizes it
    _kill_after_writes(monkeypatch, 6)
    with pytest.raises(Killed):
        _generate(tmp_path / "last", **_dense(stream_slots=2))
    monkeypatch.setattr(GraspShardWriter, "write", real_write)
    streamed.clear()
    (last,) = _generate(tmp_path / "last", **_dense(stream_slots=2))
    assert streamed == [] and len(GraspShard(last.path).solved()) == 2 * GRASPS
    (whole,) = _generate(tmp_path / "whole", **_dense(stream_slots=2))
    a, b = GraspShard(whole.path), GraspShard(r.path)
    np.testing.assert_array_equal(a.status, b.status)
    np.testing.assert_array_equal(a.force, b.force)
    for k, g in a.solved():
        for x, y in zip(a.fields(k, g, STEPS - 1), b.fields(k, g, STEPS - 1)):
            np.testing.assert_array_equal(x, y)


@pytest.mark.parametrize(
    "kw, match",
    [
        (dict(youngs_modulus=(1e6, -1.0)), "positive"),
        (dict(youngs_modulus=()), "non-empty"),
        (dict(max_force=0.0), "max_force"),
        (dict(steps=0), "steps"),
        (dict(num_grasps=0), "num_grasps"),
        (dict(poisson_ratio=0.5), "poisson"),
        (dict(shard_count=2, shard_index=2), "shard_index"),
        (dict(material_model="hookean"), "material_model"),
        (dict(moduli_per_solver=0), "moduli_per_solver"),
        (dict(stream_slots=-1), "stream_slots"),
        (dict(moduli_per_object=0), "moduli_per_object"),
        (dict(moduli_per_object=3), "moduli_per_object"),
        (dict(moduli_per_object=1.5), "moduli_per_object"),
        # wrong types name the key (were numpy's "could not convert string to float" or a TypeError)
        (
            dict(youngs_modulus=["abc"]),
            r"youngs_modulus must be a number or a list of numbers \[Pa\], got \['abc'\]",
        ),
        (dict(youngs_modulus="abc"), "youngs_modulus must be a number or a list of numbers"),
        (dict(poisson_ratio="abc"), "poisson_ratio must be a number, got 'abc' \\(str\\)"),
        (dict(num_grasps="3"), "num_grasps must be a number"),
        (dict(density=None), "density must be a number, got None"),
    ],
)
def test_bad_input_raises(tmp_path, kw, match):
    with pytest.raises(ValueError, match=match):
        _generate(tmp_path, **kw)


def test_an_out_dir_that_is_a_file_is_named_before_any_work(tmp_path):
    afile = tmp_path / "afile"
    afile.write_text("")
    with pytest.raises(NotADirectoryError, match=f"out_dir {afile} is a file, not a directory"):
        _generate(afile)
    with pytest.raises(NotADirectoryError, match=f"out_dir {afile}/sub lies under {afile}, which is a file"):
        _generate(afile / "sub")


def test_unknown_object_raises(tmp_path):
    with pytest.raises(ValueError, match="unknown object 'cuboid_nonsense'"):
        generate_object_shards("cuboid_nonsense", tmp_path, youngs_modulus=MODULI)


def test_shard_split():
    parts = [shard_grasp_indices(10, i, 3).tolist() for i in range(3)]
    assert sum(parts, []) == list(range(10))
    with pytest.raises(ValueError, match="no grasp"):
        shard_grasp_indices(2, 2, 3)


def test_datamodule_loads_generated_data(data_dir):
    dm = GraspDataModule(str(data_dir), split="unseen_grasps", batch_size=2, statistics_samples=4)
    dm.setup("fit")
    batch = next(iter(dm.train_dataloader()))
    assert batch.graph_count == 2
    assert np.isfinite(batch.stress.numpy()).all() and np.isfinite(batch.displacement.numpy()).all()
    assert batch.contact_edge_index.shape[1] > 0


def test_show_a_sample_as_png_and_vtu(data_dir, tmp_path):
    import meshio

    from defgraspnets.grasp.visualize import export_sample_vtu, load_sample, render_sample

    path = data_dir / "tinybox__shard0of1.h5"
    sample = load_sample(path, k=0, g=1, s=-1)
    assert sample.s == STEPS - 1 and sample.force == pytest.approx(FORCE, rel=1e-3)
    # the pads sit on the object: each finger's nearest vertex is within a millimetre of the deformed surface
    x = sample.points + sample.displacement
    for pad in sample.finger_vertices:
        gap = np.linalg.norm(pad[:, None, :] - x[None, :, :], axis=-1).min()
        assert gap < 1e-3
    png = render_sample(sample, tmp_path / "s.png")
    assert png.stat().st_size > 10_000
    vtu, fingers = export_sample_vtu(sample, tmp_path / "s.vtu")
    back = meshio.read(vtu)
    np.testing.assert_allclose(back.point_data["von_mises"], sample.von_mises)
    np.testing.assert_allclose(back.points, x)
    assert meshio.read(fingers).cells_dict["triangle"].shape[0] == 2 * len(sample.finger_faces)
    with pytest.raises(IndexError, match="grasp index"):
        load_sample(path, g=GRASPS)
    with pytest.raises(FileNotFoundError):
        load_sample(tmp_path / "missing.h5")


def test_the_script_grasps_a_tet_mesh_file_with_its_labels(tmp_path):
    """``python datagen/grasps.py object=<file>``: a tet mesh file is simulated as it is (its stem names the
    shard, the config labels its category and source); a missing file is a clear error."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    mesh_file = tmp_path / "my_part.vtu"
    _box().save(mesh_file)

    def run(*args):
        env = {**os.environ, "OMP_NUM_THREADS": "1", "HYDRA_FULL_ERROR": "1"}
        return subprocess.run(
            [sys.executable, str(root / "datagen/grasps.py"), *args, f"hydra.run.dir={tmp_path}/run"],
            cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300,
        )  # fmt: skip

    r = run(
        f"object={mesh_file}", "num_grasps=1", "steps=1", "youngs_modulus=[1e6]", "device=cpu",
        f"out_dir={tmp_path}/grasps", "file_labels.category=widget",
    )  # fmt: skip
    assert r.returncode == 0, r.stderr[-3000:]
    shard = GraspShard(tmp_path / "grasps" / shard_file_name("my_part", 0, 1))
    assert (shard.object.name, shard.object.category, shard.object.source) == ("my_part", "widget", "real")
    np.testing.assert_allclose(shard.object.points, _box().points)
    r = run(f"object={tmp_path}/missing.vtu", "device=cpu", f"out_dir={tmp_path}/grasps")
    assert r.returncode != 0 and "no object mesh file at" in r.stderr
    # a bad solver key is an error that names it
    r = run(f"object={mesh_file}", "max_newton_first_step=-5", "device=cpu", f"out_dir={tmp_path}/bad")
    assert r.returncode != 0 and "max_newton_first_step must be None or an integer >= 0, got -5" in r.stderr
    # self-contact with a solver that cannot hold its couplings: refused before a shard file is started
    r = run(
        f"object={mesh_file}",
        "self_contact=1.0",
        "linear_solver=cg",
        "device=cpu",
        f"out_dir={tmp_path}/sc",
    )
    assert (
        r.returncode != 0
        and "self_contact needs linear_solver 'direct', 'dense', 'banded', 'dense_banded' or 'auto'"
        in r.stderr
    )
    assert not (tmp_path / "sc").exists() or not any((tmp_path / "sc").iterdir())


def test_a_ramp_whose_object_passes_through_itself_at_its_last_step_is_failed():
    """The data path flags a converged ramp whose last state passes through itself (without self-contact,
    the squeeze default: a thin ring squeezed flat, e.g. annulus_ro30_ri25_h50 at 100 kPa, ends with 49 of its
    surface vertices inside its own tets) STATUS_SELF_INTERSECTING (7), keeping its earlier steps' fields."""
    from fem_helpers import converged_states, two_unit_boxes

    two, n = two_unit_boxes()
    apart = np.zeros((2 * n, 3))
    through = apart.copy()
    through[n:] -= [1.7, 0.13, 0.07]

    def eq(displacements):
        return converged_states(two, displacements)

    out = datagen._empty_ramps(2, 2, 2 * n)
    rows = np.array([0, 1])
    datagen._record_steps(out, rows, np.array([0, 0]), eq([through, apart]), True, last_step=1)
    np.testing.assert_array_equal(out["status"], [0, 0])  # (checked at the last step only)
    datagen._record_steps(out, rows, np.array([1, 1]), eq([through, apart]), True, last_step=1)
    assert out["status"].tolist() == [datagen.STATUS_SELF_INTERSECTING, 0]
    assert (
        np.isfinite(out["force"][0, 0]) and np.isnan(out["force"][0, 1]) and np.isfinite(out["force"][1, 1])
    )
    out = datagen._empty_ramps(1, 1, 2 * n)
    datagen._record_steps(out, rows[:1], np.array([0]), eq([through]), False, last_step=0)
    assert out["status"].tolist() == [0]  # reject_inverted=False keeps it


def test_a_broken_object_file_is_an_error_naming_the_file_and_its_problem(tmp_path):
    """``object=<file>``: a surface with NaN coordinates is reported as such (trimesh's processing would drop
    those vertices and report a hole), a file of no mesh format and an unreadable tet file name the file."""
    import trimesh

    from defgraspnets.objects import ObjectMeshError

    box = trimesh.creation.box((0.03, 0.03, 0.03))
    v = box.vertices.copy()
    v[5, 1] = np.nan
    obj = tmp_path / "nan_box.obj"
    obj.write_text(
        "".join(f"v {a} {b} {c}\n" for a, b, c in v)
        + "".join(f"f {a} {b} {c}\n" for a, b, c in box.faces + 1)
    )
    with pytest.raises(
        ObjectMeshError, match=r"nan_box\.obj: non-finite \(NaN or inf\) coordinates at vertices \[5\]"
    ):
        datagen.resolve_object_mesh(str(obj), mesher="gmsh", cache_dir=tmp_path)
    txt = tmp_path / "points.txt"
    txt.write_text("1 2 3\n")
    with pytest.raises(
        ObjectMeshError, match=r"points\.txt: unknown mesh format '\.txt'; expected a tet mesh"
    ):
        datagen.resolve_object_mesh(str(txt))
    vtu = tmp_path / "broken.vtu"
    vtu.write_text("not a mesh\n")
    with pytest.raises(ValueError, match=r"broken\.vtu: not a readable tet mesh file"):
        datagen.resolve_object_mesh(str(vtu))
