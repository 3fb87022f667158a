"""train.py and scripts/evaluate.py end to end on CPU, the Hydra config tree, struct-mode errors."""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.errors import ConfigCompositionException
from omegaconf import OmegaConf
from test_data_synthetic import make_shards

from defgraspnets.data.datamodule import GraspDataModule
from defgraspnets.data.dataset import check_displacement_target

ROOT = Path(__file__).resolve().parents[1]
TINY = [
    "model.latent=8",
    "model.num_blocks=1",
    "data.statistics_samples=8",
    "data.batch_size=8",
    "data.eval_steps=[-1]",
    "extras.print_config=false",
]


def _run(script: str, *args: str, cwd: Path) -> subprocess.CompletedProcess:
    env = {
        **os.environ,
        "OMP_NUM_THREADS": "1",
        "WANDB_MODE": "offline",
        "HYDRA_FULL_ERROR": "1",
        "PYTHONWARNINGS": "ignore",
    }
    return subprocess.run(
        [sys.executable, str(ROOT / script), *args],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )


@pytest.fixture(scope="module")
def data_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("train")
    make_shards(root / "grasps", grasps=3, num_steps=2)
    return root


@pytest.fixture(scope="module")
def first_run(data_root):
    out = data_root / "run1"
    r = _run(
        "train.py",
        "experiment=defgraspnets",
        f"paths.data_dir={data_root}",
        f"paths.log_dir={data_root}/logs",
        f"hydra.run.dir={out}",
        "trainer.max_epochs=1",
        *TINY,
        cwd=data_root,
    )
    assert r.returncode == 0, r.stderr[-4000:]
    return out


def _metrics(run: Path) -> list[dict]:
    with open(next(run.glob("csv/version_*/metrics.csv"))) as f:
        return list(csv.DictReader(f))


def test_train_fits_tests_and_checkpoints(first_run):
    assert (first_run / "checkpoints" / "last.ckpt").exists()
    rows = _metrics(first_run)
    keys = set().union(*(r.keys() for r in rows))
    for k in (
        "train/loss_epoch",
        "val/loss",
        "val/tau_s",
        "val/tau_d",
        "val/mae_stress_kpa",
        "val/mae_deformation_mm",
        "test/loss",
        "test/tau_s",
        "test/mae_stress_pa",
    ):
        assert k in keys, k
    assert any(r.get("test/loss") for r in rows)
    assert list(first_run.glob("wandb/offline-run-*")), "W&B offline run missing"
    ckpt = torch.load(first_run / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=False)
    assert (
        ckpt["hyper_parameters"]["latent"] == 8
        and ckpt["datamodule_hyper_parameters"]["split"] == "unseen_grasps"
    )
    assert float(ckpt["state_dict"]["contact_radius"]) == pytest.approx(0.005)
    assert ckpt["displacement_target"] == "rigid_removed"
    assert ckpt["datamodule_hyper_parameters"]["displacement"] == "rigid_removed"
    assert ckpt["state_dict"]["net.stress_norm.count"] > 0


@pytest.mark.slow
def test_resume_from_checkpoint(first_run, data_root):
    out = data_root / "run2"
    r = _run(
        "train.py",
        "experiment=defgraspnets",
        f"paths.data_dir={data_root}",
        f"hydra.run.dir={out}",
        "trainer.max_epochs=2",
        "test=false",
        "logger=csv",
        f"ckpt_path={first_run}/checkpoints/last.ckpt",
        *TINY,
        cwd=data_root,
    )
    assert r.returncode == 0, r.stderr[-4000:]
    ckpt = torch.load(out / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=False)
    assert ckpt["epoch"] == 1  # resumed at epoch 1 (0-based), trained only the second epoch
    assert {int(row["epoch"]) for row in _metrics(out) if row["epoch"]} == {1}


def _evaluate(first_run: Path, out: Path, *args: str) -> subprocess.CompletedProcess:
    """scripts/evaluate.py on the first run's last checkpoint, writing to ``out``."""
    ckpt = f"ckpt_path={first_run}/checkpoints/last.ckpt"
    return _run(
        "scripts/evaluate.py",
        ckpt,
        f"hydra.run.dir={out}",
        "extras.print_config=false",
        *args,
        cwd=out.parent,
    )


def test_evaluate_script(first_run, data_root):
    out = data_root / "eval"
    r = _evaluate(first_run, out, "plots=1", "chamfer_samples=256")
    assert r.returncode == 0, r.stderr[-4000:]
    text = (out / "results.md").read_text()
    assert "| unseen_grasps | rigid_removed |" in text and "τ_s" in text and "d_C [mm]" in text
    assert "τ_s 95 % CI" in text
    level = json.loads((out / "results.json").read_text())["levels"][0]
    assert level["displacement_target"] == "rigid_removed"
    for key in ("tau_s", "tau_d"):  # several test objects: a defined interval around the mean
        if level[key] is not None:
            assert level[f"{key}_ci_low"] <= level[key] <= level[f"{key}_ci_high"]
    assert (out / "fields_unseen_grasps_0_stress.png").stat().st_size > 10_000


def test_evaluate_script_writes_the_ablation_table(first_run, data_root):
    """ablations=true on the baseline and a V3 model (F_g on every contact edge) trained on the same split:
    the Table 7.2 rows name the variant and carry the thesis's values; one checkpoint alone is refused."""
    v3 = data_root / "run_v3"
    r = _run(
        "train.py",
        "experiment=defgraspnets_v3_total_force",
        f"paths.data_dir={data_root}",
        f"hydra.run.dir={v3}",
        "trainer.max_epochs=1",
        "logger=csv",
        *TINY,
        cwd=data_root,
    )
    assert r.returncode == 0, r.stderr[-4000:]
    out = data_root / "eval_ablations"
    ckpts = f"ckpt_paths=[{first_run}/checkpoints/last.ckpt,{v3}/checkpoints/last.ckpt]"
    r = _evaluate(first_run, out, ckpts, "ablations=true", "plots=1", "chamfer_samples=64", "ckpt_path=null")
    assert r.returncode == 0, r.stderr[-4000:]
    result = json.loads((out / "results.json").read_text())
    base, v3_row = result["ablations"]
    assert base["variant"] == "baseline" and v3_row["variant"] == "V3 force on a contact edge"
    assert v3_row["condition"] == "non-distributed F_g" and v3_row["thesis_tau_d"] == 0.33
    assert [lv["conditions"]["force_feature"] for lv in result["levels"]] == ["distributed", "total"]
    assert base["samples"] == v3_row["samples"] > 0  # one test set
    assert (base["model"], v3_row["model"]) == ("run1", "run_v3")  # the run directories
    text = (out / "results.md").read_text()
    assert "## Ablations (thesis §7.8, Table 7.2)" in text and "| run_v3 | unseen_grasps |" in text
    for model in ("run1", "run_v3"):  # one plot each, not one overwriting the other
        assert (out / f"fields_{model}_unseen_grasps_0_stress.png").exists()
    alone = _evaluate(first_run, data_root / "eval_ablations_alone", "ablations=true", "plots=0")
    assert alone.returncode != 0 and "ablations=true compares several checkpoints" in alone.stderr


def test_train_ablations_script_trains_five_models_and_writes_their_table(data_root):
    """scripts/train_ablations.sh: the baseline and V1-V4 with the same overrides, two at a time, each told
    its GPU (GPUS=2: models 0-4 on GPUs 0 1 0 1 0; the CPU trainer ignores it), then one ablation table; a
    failing override stops it before the table, naming the model, and starts no model after the failure."""
    names = ["baseline", "v1_separate", "v2_multi_step", "v3_total_force", "v4_node_force"]
    out = data_root / "ablations"
    env = {**os.environ, "OMP_NUM_THREADS": "1", "WANDB_MODE": "offline", "PYTHONWARNINGS": "ignore"}
    env.update(DATA=str(data_root / "grasps"), OUT=str(out), PARALLEL="2", GPUS="2", STRIDE="1")
    env["EVAL"] = "plots=0 chamfer_samples=64 extras.print_config=false"
    script = ["bash", str(ROOT / "scripts" / "train_ablations.sh")]
    args = [*script, "trainer=cpu", "trainer.max_epochs=1", *TINY]
    r = subprocess.run(args, env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    gpus = dict(line.split(" on GPU ") for line in r.stdout.splitlines() if " on GPU " in line)
    assert gpus == dict(zip(names, "01010"))
    rows = json.loads((out / "evaluation" / "results.json").read_text())["ablations"]
    assert [row["model"] for row in rows] == names
    variables = [[], ["outputs"], ["prediction"], ["force_feature"], ["force_on"]]
    assert [row["differs_in"] for row in rows] == variables
    bad_out = data_root / "ablations_bad"
    env["OUT"] = str(bad_out)
    bad = subprocess.run([*args, "model.latent=-1"], env=env, capture_output=True, text=True, timeout=600)
    assert bad.returncode != 0 and "baseline did not train" in bad.stdout
    # the first two fail together (PARALLEL=2); the other three are never started
    assert {p.name for p in bad_out.glob("*.failed")} == {"baseline.failed", "v1_separate.failed"}
    for name in names[2:]:
        assert f"not starting {name}: a model failed" in bad.stdout
        assert not (bad_out / f"{name}.log").exists()


def test_evaluate_script_on_the_training_part(first_run, data_root):
    """part=train evaluates the training grasps at the test part's steps and says so."""
    runs = {}
    for part in ("test", "train"):
        out = data_root / f"eval_part_{part}"
        r = _evaluate(first_run, out, f"part={part}", "plots=1", "chamfer_samples=64")
        assert r.returncode == 0, r.stderr[-4000:]
        runs[part] = json.loads((out / "results.json").read_text())["levels"][0]
    assert runs["test"]["split"] == "unseen_grasps"
    assert runs["train"]["split"] == "unseen_grasps/train"
    # the training grasps at the test part's one step (data.eval_steps=[-1]), not at both training steps
    hp = torch.load(first_run / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=False)[
        "datamodule_hyper_parameters"
    ]
    assert hp["train_steps"] is None and list(hp["eval_steps"]) == [-1]
    dm = GraspDataModule(**{**hp, "train_steps": [-1]})
    dm.setup("test")
    assert runs["train"]["samples"] == len(dm.datasets["train"]) > runs["test"]["samples"] > 0
    assert (data_root / "eval_part_train" / "fields_unseen_grasps_train_0_stress.png").exists()
    # (an unknown part is named: test_evaluate_script_on_every_squeeze_of_new_data)


def test_evaluate_script_on_every_squeeze_of_new_data(first_run, data_root):
    """part=all on a data directory the checkpoint never saw: every solved squeeze at the evaluation steps,
    and object rows that claim no nearest training object."""
    from defgraspnets.data.dataset import discover_shards
    from defgraspnets.data.grasp_schema import GraspShard

    fresh = make_shards(data_root / "fresh_grasps", grasps=4, num_steps=2)  # one failed ramp
    solved = sum(int((GraspShard(p).status == 0).sum()) for p in discover_shards(fresh))
    out = data_root / "eval_part_all"
    r = _evaluate(first_run, out, "part=all", f"data.data_dir={fresh}", "plots=0")
    assert r.returncode == 0, r.stderr[-4000:]
    results = json.loads((out / "results.json").read_text())
    (level,) = results["levels"]
    assert level["split"] == "unseen_grasps/all"
    assert level["samples"] == solved * 1  # data.eval_steps=[-1]: one step per solved ramp
    assert len(results["objects"]) == 6
    for row in results["objects"]:  # NaN is written as null
        assert row["split"] == "unseen_grasps/all"
        assert row["nearest_train_object"] is None and row["chamfer_mm"] is None
    bad = _evaluate(first_run, data_root / "eval_part_bogus", "part=bogus")
    assert (
        bad.returncode != 0 and "ValueError: part='bogus': choose one of test, val, train, all" in bad.stderr
    )


def test_evaluate_every_squeeze_with_a_checkpoint_of_another_level(first_run, data_root):
    """part=all evaluates whatever the checkpoint's level: an unseen_real model on data without real objects
    (its split could not be made there) runs, and its rows keep its level's name."""
    import torch

    ckpt = torch.load(first_run / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=False)
    ckpt["datamodule_hyper_parameters"]["split"] = "unseen_real"
    real_ckpt = data_root / "unseen_real_model.ckpt"
    torch.save(ckpt, real_ckpt)
    fresh = make_shards(data_root / "fresh_grasps_real", grasps=4, num_steps=2, with_real=False)
    out = data_root / "eval_part_all_real"
    r = _run(
        "scripts/evaluate.py",
        f"ckpt_path={real_ckpt}",
        f"hydra.run.dir={out}",
        "extras.print_config=false",
        "part=all",
        f"data.data_dir={fresh}",
        "plots=0",
        cwd=out.parent,
    )
    assert r.returncode == 0, r.stderr[-4000:]
    (level,) = json.loads((out / "results.json").read_text())["levels"]
    assert level["split"] == "unseen_real/all" and level["samples"] > 0


def test_evaluate_refuses_another_displacement_target(first_run, data_root):
    r = _evaluate(first_run, data_root / "eval_total", "+data.displacement=total", "plots=0")
    assert r.returncode != 0
    assert "data.displacement=total differs from the 'rigid_removed' displacement" in r.stderr


@pytest.mark.slow
def test_multirun_sweep(data_root):
    r = _run(
        "train.py",
        "-m",
        "experiment=defgraspnets",
        f"paths.data_dir={data_root}",
        f"hydra.sweep.dir={data_root}/sweep",
        "model.latent=4,8",
        "trainer.max_epochs=1",
        "test=false",
        "logger=csv",
        "optimized_metric=val/loss",
        "+trainer.limit_train_batches=2",
        *TINY[1:],
        cwd=data_root,
    )
    assert r.returncode == 0, r.stderr[-4000:]
    for job in ("0", "1"):
        assert (data_root / "sweep" / job / "checkpoints" / "last.ckpt").exists()


# ---------------------------------------------------------------------------------------------- config tree
def _compose(*overrides: str):
    os.environ.setdefault("PROJECT_ROOT", str(ROOT))
    with initialize_config_dir(config_dir=str(ROOT / "configs"), version_base="1.3"):
        return compose("train.yaml", overrides=list(overrides), return_hydra_config=True)


def test_config_overrides_and_experiments():
    cfg = _compose(
        "experiment=defgraspnets", "model.latent=64", "trainer.max_epochs=3", "data.split=unseen_E"
    )
    assert cfg.model.latent == 64 and cfg.trainer.max_epochs == 3 and cfg.data.split == "unseen_E"
    assert cfg.model.num_blocks == 15 and cfg.model.hidden_layers == 2 and cfg.data.contact_radius == 0.005
    assert cfg.model.lr == 5e-5 and cfg.model.lr_final == 1e-6 and cfg.model.lr_decay_epochs == 25
    assert cfg.model.global_context is False  # the thesis's network; on: model.global_context=true
    assert set(cfg.logger) == {"csv", "wandb"} and cfg.logger.wandb.offline is True
    assert {"model_checkpoint", "lr_monitor"} <= set(cfg.callbacks)
    for name, key, value in (
        ("v1_separate", "outputs", "separate"),
        ("v3_total_force", "force_feature", "total"),
        ("v4_node_force", "force_on", "nodes"),
        ("v2_multi_step", "prediction", "multi_step"),
    ):
        c = _compose(f"experiment=defgraspnets_{name}")
        assert c.model[key] == value and c.model.latent == 128, name
        check_displacement_target(c.data.displacement, c.data.ramp_stride)  # each ablation's data is valid
    assert cfg.data.displacement == "rigid_removed"  # the default: benchmarks/defgraspnets_target_ab_h100.md
    v2 = _compose("experiment=defgraspnets_v2_multi_step").data
    assert v2.ramp_stride == 10 and v2.displacement == "total"
    ddp = _compose("trainer=ddp", "trainer.num_nodes=4")
    assert ddp.trainer.strategy == "ddp" and ddp.trainer.devices == -1 and ddp.trainer.num_nodes == 4
    assert _compose("trainer=gpu").trainer.accelerator == "gpu"
    grid = _compose("hparams_search=defgraspnets_grid")
    assert grid.optimized_metric == "val/loss" and "model.latent" in grid.hydra.sweeper.params
    # every model/data config instantiates (no missing _target_ arguments)
    OmegaConf.resolve(cfg.model)


def test_learning_rate_decays_exponentially_over_25_epochs():
    from defgraspnets.models.defgraspnets_module import DefGraspNetsModule

    module = DefGraspNetsModule(latent=4, num_blocks=1)
    conf = module.configure_optimizers()
    opt, sched = conf["optimizer"], conf["lr_scheduler"]["scheduler"]
    assert conf["lr_scheduler"]["interval"] == "epoch"
    lrs = []
    for _ in range(30):
        lrs.append(opt.param_groups[0]["lr"])
        opt.step()
        sched.step()
    assert lrs[0] == pytest.approx(5e-5) and lrs[25] == pytest.approx(1e-6) and lrs[29] == pytest.approx(1e-6)
    ratios = [lrs[i + 1] / lrs[i] for i in range(24)]
    assert max(ratios) == pytest.approx(min(ratios)) and ratios[0] == pytest.approx((1e-6 / 5e-5) ** (1 / 25))


def test_adam_is_fused_on_cuda_only():
    """Parameters on the CPU: PyTorch's default Adam; on CUDA (``-m gpu``): the fused implementation."""
    from defgraspnets.models.defgraspnets_module import DefGraspNetsModule

    module = DefGraspNetsModule(latent=4, num_blocks=1)
    assert not module.configure_optimizers()["optimizer"].defaults["fused"]
    if torch.cuda.is_available():
        assert module.cuda().configure_optimizers()["optimizer"].defaults["fused"]


def test_wrong_config_key_is_a_clear_error():
    with pytest.raises(ConfigCompositionException, match="latnt"):
        _compose("model.latnt=64")
    with pytest.raises(ConfigCompositionException, match="experiment"):
        _compose("experiment=does_not_exist")
