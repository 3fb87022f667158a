"""The grasp generator with the DefGraspSim experiments (thesis §6.4-6.5): the metrics, features and
per-direction results stored in a shard equal a direct GraspExperiments run, a status says why a metric is
NaN, a killed run resumes to the same shard, shards without experiments still load, bad input is named;
scripts/benchmark_grasp_experiments.py writes its JSON."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
from test_data_synthetic import box_object, grasp_poses, pad_fingers, ramp_fields

from defgraspnets import fem
from defgraspnets.data.grasp_schema import (
    EXPERIMENT_NAMES,
    FEATURE_NAMES,
    METRIC_NAMES,
    ExperimentLayout,
    ExperimentStatus,
    GraspShard,
    GraspShardWriter,
)
from defgraspnets.grasp import datagen
from defgraspnets.grasp import features as feat
from defgraspnets.grasp.datagen import experiment_layout, generate_object_shards, structured_box
from defgraspnets.grasp.experiments import ExperimentSettings, GraspExperiments, GraspFailure
from defgraspnets.grasp.sampler import sample_antipodal_grasps

ROOT = Path(__file__).resolve().parents[1]
MODULUS = 1e6
STEPS = 2
FORCE = 5.0
SEED = 4  # two grasps about one axis 1.9 mm beside the centre of mass: the pickup holds, every metric is set
FRICTION = 0.7
# few directions, angles and steps: the whole set of experiments of 2 grasps in ~10 s on 2 CPU cores
SETTINGS = dict(
    num_directions=2,
    acceleration_steps=4,
    reorientation_angles=2,
    reorientation_substeps=1,
    pickup_steps=3,
    squeeze_steps=3,
)
OK, NOT_RUN, NOT_GRASPED, LOST, ERROR = (
    ExperimentStatus.OK,
    ExperimentStatus.NOT_RUN,
    ExperimentStatus.NOT_GRASPED,
    ExperimentStatus.LOST,
    ExperimentStatus.ERROR,
)


def _box():
    return structured_box((0.03, 0.03, 0.03), (4, 4, 4), name="expbox")


def _generate(out_dir, **kw):
    args = dict(
        youngs_modulus=(MODULUS,), num_grasps=2, steps=STEPS, max_force=FORCE, friction=FRICTION, seed=SEED,
        device="cpu", experiments=EXPERIMENT_NAMES, experiment_settings=SETTINGS,
    )  # fmt: skip
    args.update(kw)
    return generate_object_shards(_box(), out_dir, **args)


def _datasets(path: Path) -> dict:
    out = {}
    with h5py.File(path, "r") as f:
        f.visititems(
            lambda name, obj: out.__setitem__(name, obj[()]) if isinstance(obj, h5py.Dataset) else None
        )
        out["attrs"] = {k: v for k, v in f.attrs.items() if k != "created"}
        out["experiment attrs"] = dict(f["experiments"].attrs) if "experiments" in f else None
    return out


_STATIC_EXPERIMENT_DATA = ("experiments/directions", "experiments/axes", "experiments/angles")


def _nan(v):
    return np.nan if v is None else float(v)


@pytest.fixture(scope="module")
def generated(tmp_path_factory):
    (result,) = _generate(tmp_path_factory.mktemp("exp"))
    return result


# ---------------------------------------------------------------------------------------------- round trip
def test_shard_metrics_equal_a_direct_run(generated):
    """Generator -> shard -> reader gives exactly what GraspExperiments computes on the same grasps."""
    sh = GraspShard(generated.path)
    assert sh.has_experiments and sh.experiment_names == EXPERIMENT_NAMES
    assert sh.experiment_layout.settings == dataclasses.asdict(
        ExperimentSettings(friction=FRICTION, **SETTINGS)
    )
    mesh = _box()
    grasps = sample_antipodal_grasps(mesh, num_grasps=2, friction_coefficient=FRICTION, seed=SEED)
    np.testing.assert_array_equal(sh.grasp_pose, grasps.poses)
    settings = ExperimentSettings(friction=FRICTION, **SETTINGS)
    material = fem.Material(MODULUS, 0.3, 1000.0, model="neohookean")  # the generator's default
    direct = GraspExperiments(mesh, grasps, material, settings, device="cpu").run(EXPERIMENT_NAMES)
    per_grasp = direct.per_grasp()
    for g in range(2):
        assert sh.experiment_status(0, g) == {name: OK for name in EXPERIMENT_NAMES}
        metrics = sh.metrics(0, g)
        want = {k: _nan(v) for k, v in per_grasp[g]["metrics"].items()}
        assert list(metrics) == list(METRIC_NAMES) == list(want)
        np.testing.assert_array_equal(list(metrics.values()), list(want.values()))
        assert np.all(np.isfinite(list(metrics.values()))) and metrics["pickup_success"] == 1.0
        features = sh.features(0, g)
        assert tuple(features) == FEATURE_NAMES == feat.FEATURE_NAMES
        np.testing.assert_array_equal(
            list(features.values()), [_nan(per_grasp[g]["features"][f]) for f in FEATURE_NAMES]
        )
        pickup = sh.experiment(0, g, "pickup")
        assert pickup["grasp_force"] == direct.pickup.grasp_force
        assert pickup["slip_force"] == direct.pickup.slip_force[g]
        assert pickup["failure"] == GraspFailure.HELD and pickup["slide"] == direct.pickup.slide[g]
        reo = sh.experiment(0, g, "reorientation")
        np.testing.assert_array_equal(reo["axes"], direct.reorientation.axes)
        np.testing.assert_array_equal(reo["angles"], direct.reorientation.angles)
        np.testing.assert_array_equal(reo["held"], direct.reorientation.held[g])
        np.testing.assert_array_equal(reo["failure"], direct.reorientation.failure[g])
        np.testing.assert_array_equal(reo["max_von_mises"], direct.reorientation.max_von_mises[g])
        for res in (direct.linear, direct.angular):
            got = sh.experiment(0, g, res.kind)
            assert got["status"] == OK
            np.testing.assert_array_equal(got["directions"], res.directions)
            np.testing.assert_array_equal(got["threshold"], res.threshold[g])
            np.testing.assert_array_equal(got["failure"], res.failure[g])
            np.testing.assert_array_equal(got["solver_status"], res.solver_status[g])
    np.testing.assert_array_equal(sh.metric_values("linear_instability_m_s2")[0], direct.linear.instability)
    # the generator's summary counts
    assert generated.experiments == {
        name: {"OK": 2, "NOT_GRASPED": 0, "LOST": 0, "ERROR": 0} for name in EXPERIMENT_NAMES
    }
    assert generated.experiment_summary().startswith("pickup 2 ok / 0 failed, reorientation 2 ok")
    with pytest.raises(KeyError, match="shake"):
        sh.experiment(0, 0, "shake")
    with pytest.raises(IndexError, match="outside"):
        sh.metrics(1, 0)
    sh.close()


# ---------------------------------------------------------------------------------------------- resume
def test_killed_and_resumed_run_equals_an_uninterrupted_one(generated, tmp_path, monkeypatch):
    """Killed after the first entry of the batch was written: the resumed run simulates (ramp and
    experiments) only the other grasp, and the shard holds every entry once with the same results. The
    re-simulated grasp runs in a batch of one instead of two; the FEM batch's floating-point summation
    order then differs, so its floats agree to 1e-9, not bit for bit (codes and flags exactly)."""
    calls = []
    real_run = datagen.run_experiments

    def spy(mesh, grasps, *args, **kwargs):
        calls.append(len(grasps))
        return real_run(mesh, grasps, *args, **kwargs)

    monkeypatch.setattr(datagen, "run_experiments", spy)

    class Killed(Exception):
        pass

    real_write = GraspShardWriter.write

    def write_then_die(self, k, g, *a, **kw):
        real_write(self, k, g, *a, **kw)
        raise Killed

    monkeypatch.setattr(GraspShardWriter, "write", write_then_die)
    with pytest.raises(Killed):
        _generate(tmp_path)
    name = generated.path.name
    partial = tmp_path / name.replace(".h5", ".partial.h5")
    assert partial.exists() and not (tmp_path / name).exists() and calls == [2]
    with h5py.File(partial, "r") as f:
        assert f["progress/done"][()].tolist() == [[True, False]]
        assert f["experiments/status"][0, 0].tolist() == [OK] * 4
        assert f["experiments/status"][0, 1].tolist() == [-1] * 4  # not written: no half entry

    monkeypatch.setattr(GraspShardWriter, "write", real_write)
    calls.clear()
    (resumed,) = _generate(tmp_path)
    assert calls == [1] and not partial.exists()
    assert resumed.experiments == generated.experiments
    a, b = _datasets(generated.path), _datasets(resumed.path)
    assert a.keys() == b.keys()
    for key in a:
        if key in ("attrs", "experiment attrs"):
            assert a[key] == b[key], key
        elif np.asarray(a[key]).dtype.kind == "f":
            np.testing.assert_allclose(b[key], a[key], rtol=1e-9, atol=0, equal_nan=True, err_msg=key)
            # the entry written before the kill came from the same batch: bit for bit
            if key.startswith(("experiments/", "ramp/")) and key not in _STATIC_EXPERIMENT_DATA:
                np.testing.assert_array_equal(b[key][:, 0], a[key][:, 0], err_msg=key)
        else:
            np.testing.assert_array_equal(b[key], a[key], err_msg=key)


def test_streamed_ramps_keep_the_experiments_of_the_batches(generated, tmp_path):
    """stream_slots=1: the squeeze ramps run one after the other through one problem; the experiments still
    run per modulus once its ramps are done, in the same batches, so they are the same bit for bit; the
    ramps agree to 1e-9 (the default multigrid solver's tolerance is shared by its batch)."""
    (streamed,) = _generate(tmp_path, stream_slots=1)
    assert streamed.experiments == generated.experiments
    a, b = _datasets(generated.path), _datasets(streamed.path)
    assert a.keys() == b.keys()
    for key in a:
        if key.startswith("ramp/") and np.asarray(a[key]).dtype.kind == "f":
            np.testing.assert_allclose(b[key], a[key], rtol=1e-9, atol=0, equal_nan=True, err_msg=key)
        else:
            np.testing.assert_array_equal(b[key], a[key], err_msg=key)


# ---------------------------------------------------------------------------------------------- statuses
def test_status_says_why_a_metric_is_nan(tmp_path, monkeypatch):
    """Grasp 1's squeeze to F_p finds no equilibrium (NOT_GRASPED: every metric and feature NaN, left out
    of the later experiments), the angular test raises (ERROR), reorientation is not selected (NOT_RUN)."""
    real_pickup, real_acc = GraspExperiments.pickup, GraspExperiments.acceleration
    batches = []

    def pickup_without_grasp_1(self):
        res = real_pickup(self)
        res.failure[1], res.success[1] = GraspFailure.NOT_GRASPED, False
        return res

    def acceleration(self, kind, directions=None):
        batches.append((kind, self.num_grasps))
        if kind == "angular":
            raise RuntimeError("the solver blew up")
        return real_acc(self, kind, directions)

    monkeypatch.setattr(GraspExperiments, "pickup", pickup_without_grasp_1)
    monkeypatch.setattr(GraspExperiments, "acceleration", acceleration)
    (r,) = _generate(tmp_path, experiments=["linear", "angular"])  # pickup is added
    assert batches == [("linear", 1), ("angular", 1)]
    sh = GraspShard(r.path)
    assert sh.experiment_names == ("pickup", "linear", "angular")
    assert sh.experiment_status(0, 0) == dict(pickup=OK, reorientation=NOT_RUN, linear=OK, angular=ERROR)
    assert sh.experiment_status(0, 1) == dict(
        pickup=NOT_GRASPED, reorientation=NOT_RUN, linear=NOT_GRASPED, angular=NOT_GRASPED
    )
    m0, m1 = sh.metrics(0, 0), sh.metrics(0, 1)
    assert m0["pickup_success"] == 1.0 and m0["max_von_mises_stress_pa"] > 0
    assert m0["linear_instability_m_s2"] >= 0
    assert np.isnan(m0["angular_instability_rad_s2"]) and np.isnan(m0["deformation_controllability_m"])
    assert all(np.isnan(v) for v in m1.values()) and all(np.isnan(v) for v in sh.features(0, 1).values())
    lin1 = sh.experiment(0, 1, "linear")
    assert np.isnan(lin1["threshold"]).all() and (lin1["failure"] == -1).all()
    assert np.isfinite(sh.experiment(0, 0, "linear")["threshold"]).all()
    assert r.experiments["angular"] == {"OK": 0, "NOT_GRASPED": 1, "LOST": 0, "ERROR": 1}
    assert "angular 0 ok / 2 failed (NOT_GRASPED 1, ERROR 1)" in r.experiment_summary()
    assert len(sh.solved()) == 2  # the squeeze ramps are stored as before


def test_failed_pickup_has_nan_stress_not_a_number_made_up(tmp_path):
    """mu F = 0.5 m g cannot carry the weight: pickup_success is 0.0 and the picked-up state's metrics are
    NaN (status LOST); the features of the grasp, formed in zero gravity, are measured."""
    (r,) = _generate(
        tmp_path, num_grasps=1, experiments=["pickup"], experiment_settings={**SETTINGS, "safety_factor": 0.5}
    )
    sh = GraspShard(r.path)
    assert sh.experiment_status(0, 0)["pickup"] == LOST
    m = sh.metrics(0, 0)
    assert m["pickup_success"] == 0.0
    assert all(np.isnan(m[k]) for k in METRIC_NAMES[1:])
    assert sh.experiment(0, 0, "pickup")["failure"] in (GraspFailure.NO_EQUILIBRIUM, GraspFailure.SLID)
    assert np.isfinite(sh.features(0, 0)["pure_dist"])


def test_shard_without_experiments_still_loads(tmp_path):
    (r,) = _generate(tmp_path, experiments=[], num_grasps=1, steps=1)
    assert r.experiments == {} and r.experiment_summary() == ""
    with h5py.File(r.path) as f:
        assert "experiments" not in f
    sh = GraspShard(r.path)
    assert not sh.has_experiments and sh.experiment_names == ()
    assert all(np.isnan(v) for v in sh.metrics(0, 0).values())
    assert all(np.isnan(v) for v in sh.features(0, 0).values())
    assert set(sh.experiment_status(0, 0).values()) == {NOT_RUN}
    assert np.isnan(sh.metric_values("strain_energy_j")).all()
    with pytest.raises(KeyError, match="no experiment"):
        sh.experiment(0, 0, "linear")


# ---------------------------------------------------------------------------------------------- bad input
@pytest.mark.parametrize(
    "kw, match",
    [
        (dict(experiments=["pickup", "shake"]), r"unknown experiment\(s\) \['shake'\]"),
        (dict(experiments=[1]), "unknown experiment"),
        (dict(experiment_settings={"friction": 0.5}), "must not set friction"),
        (dict(experiment_settings={"num_direction": 8}), r"unknown experiment settings \['num_direction'\]"),
        (dict(experiment_settings={"num_directions": 3}), "num_directions"),
        (dict(experiment_settings=ExperimentSettings(friction=0.5)), "friction"),
        (dict(experiment_settings=[1, 2]), None),
        (dict(directions_per_solver=0), "directions_per_solver"),
    ],
)
def test_bad_experiment_input_raises(tmp_path, kw, match):
    with pytest.raises(TypeError if match is None else ValueError, match=match):
        _generate(tmp_path, **kw)
    assert not list(tmp_path.iterdir())  # refused before anything is written


def _layout(**settings):
    s = ExperimentSettings(**{**SETTINGS, **settings})
    return experiment_layout(EXPERIMENT_NAMES, s)


def test_writer_checks_experiment_entries(tmp_path):
    obj = box_object("cube", divisions=(2, 2, 2))
    pose, fpose, cdir = grasp_poses(obj, 2, 0)
    path = tmp_path / "cube__shard0of1.h5"
    layout = _layout()
    w = GraspShardWriter.create(path, obj, pad_fingers(), pose, fpose, cdir, 3, "t", experiments=layout)
    ramp = ramp_fields(obj, fpose[0], cdir[0], obj.youngs_modulus[0], 3)
    with pytest.raises(ValueError, match="pass those"):
        w.write(0, 0, *ramp)
    entry = layout.empty_entry()
    with pytest.raises(ValueError, match="NOT_RUN"):
        w.write(0, 0, *ramp, experiments=entry)  # NOT_RUN for experiments that the shard runs
    entry["status"][:] = NOT_GRASPED
    entry["metrics/strain_energy_j"][...] = 1e-3  # a number no experiment measured
    with pytest.raises(ValueError, match="strain_energy_j"):
        w.write(0, 0, *ramp, experiments=entry)
    entry["metrics/strain_energy_j"][...] = np.nan
    with pytest.raises(ValueError, match="missing"):
        w.write(0, 0, *ramp, experiments={k: v for k, v in entry.items() if k != "linear/threshold"})
    w.write(0, 0, *ramp, experiments=entry)
    w.close()
    # a partial shard of other experiment settings is not resumed
    with pytest.raises(ValueError, match="experiment data"):
        GraspShardWriter.create(
            path, obj, pad_fingers(), pose, fpose, cdir, 3, "t", experiments=_layout(num_directions=4)
        )
    with pytest.raises(ValueError, match="experiment data"):
        GraspShardWriter.create(path, obj, pad_fingers(), pose, fpose, cdir, 3, "t")
    w = GraspShardWriter.create(path, obj, pad_fingers(), pose, fpose, cdir, 3, "t", experiments=layout)
    assert w.pending()[0] == (0, 1)
    w.close()
    with pytest.raises(ValueError, match="pickup"):
        ExperimentLayout(("shake",), {}, np.ones((2, 3)), np.ones((2, 3)), np.ones(2))


# ---------------------------------------------------------------------------------------------- scripts
def test_datagen_cli_with_experiments(tmp_path):
    cmd = [
        sys.executable, str(ROOT / "datagen" / "grasps.py"), "experiments=[linear]",
        "experiment_settings.num_directions=2", "experiment_settings.acceleration_steps=2",
        "experiment_settings.pickup_steps=2", "experiment_settings.squeeze_steps=2",
        f"youngs_modulus=[{MODULUS}]", "num_grasps=2", f"seed={SEED}", f"steps={STEPS}", f"max_force={FORCE}",
        "device=cpu", "progress=false",
        f"out_dir={tmp_path / 'out'}", f"hydra.run.dir={tmp_path / 'run'}",
    ]  # fmt: skip
    done = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    log = done.stdout + done.stderr
    assert "experiment entries: pickup 2 ok / 0 failed, linear 2 ok / 0 failed" in log
    sh = GraspShard(tmp_path / "out" / "box_30x30x30__shard0of1.h5")
    assert sh.experiment_names == ("pickup", "linear") and "experiments:" in sh.attrs["config"]
    assert np.isfinite(sh.metric_values("linear_instability_m_s2")).all()
    for bad, message in (
        ("experiment_settings.frction=1", "frction"),
        ("experiment_settings.friction=0.5", "friction"),  # the generator's friction is used
        ("experiments=[shake]", "unknown experiment"),
    ):
        run = subprocess.run(
            [*cmd[:2], bad, f"hydra.run.dir={tmp_path / 'bad'}", f"out_dir={tmp_path / 'bad'}"],
            capture_output=True, text=True, cwd=tmp_path, timeout=600,
        )  # fmt: skip
        assert run.returncode != 0 and message in run.stderr, (bad, run.stderr[-2000:])


def test_benchmark_grasp_experiments_writes_json(tmp_path):
    out = tmp_path / "bench.json"
    cmd = [
        sys.executable, str(ROOT / "scripts" / "benchmark_grasp_experiments.py"), f"out={out}",
        "box.divisions=[3,3,3]", "num_grasps=2", "steps=2", "youngs_modulus=1e6", "max_force=5",
        "settings.num_directions=2", "settings.acceleration_steps=2", "settings.reorientation_angles=1",
        "settings.reorientation_substeps=1", "settings.squeeze_steps=2", "settings.pickup_steps=2",
    ]  # fmt: skip
    done = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    record = json.loads(out.read_text())
    assert record["benchmark"] == "grasp_experiments" and record["machine"]["device"] == "cpu"
    assert record["experiments"] == list(EXPERIMENT_NAMES) and record["settings"]["num_directions"] == 2
    (obj,) = record["objects"]
    assert obj["object"] == "box_30x30x30" and obj["vertices"] == 64 and obj["grasps"] == 2
    assert obj["seconds_warmup"] > 0
    ramp = obj["squeeze_ramp"]
    assert (
        ramp["steps"] == 2
        and ramp["seconds"] > 0
        and ramp["grasps_per_s"] == pytest.approx(2 / ramp["seconds"])
    )
    assert len(ramp["status_per_grasp"]) == 2
    assert list(obj["experiments"]) == list(EXPERIMENT_NAMES)
    for name, t in obj["experiments"].items():
        assert t["seconds"] > 0 and t["grasps_per_s"] == pytest.approx(2 / t["seconds"]), name
        assert len(t["status_per_grasp"]) == 2 and set(t["status_per_grasp"]) <= set(
            ExperimentStatus.__members__
        )
        assert t["ok"] == t["status_per_grasp"].count("OK")
    typo = subprocess.run(
        [*cmd[:2], "num_grasp=2"], capture_output=True, text=True, cwd=tmp_path, timeout=600
    )
    assert typo.returncode != 0 and "num_grasp" in typo.stderr
