"""Distributed data parallel training end to end on 2 CPU processes (gloo), and the throughput callback.

``train.py trainer=ddp trainer.accelerator=cpu trainer.devices=2``: Lightning re-launches the script for
rank 1 (Hydra run dir shared), the DistributedSampler shards (and pads) the splits. Checked: the run finishes
with a checkpoint, the two ranks end with identical weights and normalization buffers, the logged
``val/*`` and ``test/*`` are those of a single-process evaluation of the same checkpoint on the whole split,
and ``train/graphs_per_sec`` counts the graphs of both ranks.
"""

from __future__ import annotations

import csv
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from lightning import Callback, LightningModule, Trainer
from lightning.pytorch.loggers import CSVLogger
from test_train import TINY

ROOT = Path(__file__).resolve().parents[1]
TESTS = Path(__file__).resolve().parent


class SaveRankState(Callback):
    """Test helper run inside train.py: every rank saves its final state_dict to ``<dirpath>/rank<r>.pt``."""

    def __init__(self, dirpath: str):
        self.dirpath = dirpath

    def on_fit_end(self, trainer, pl_module):
        Path(self.dirpath).mkdir(parents=True, exist_ok=True)
        state = {k: v.detach().cpu().clone() for k, v in pl_module.state_dict().items()}
        torch.save(state, Path(self.dirpath) / f"rank{trainer.global_rank}.pt")


def _metrics(run: Path) -> list[dict]:
    files = list(run.glob("csv/version_*/metrics.csv"))
    assert len(files) == 1, files  # rank 0 writes the only CSV log
    with open(files[0]) as f:
        return list(csv.DictReader(f))


def _last(rows: list[dict], prefix: str) -> dict[str, float]:
    out: dict[str, float] = {}
    for r in rows:
        out.update({k: float(v) for k, v in r.items() if k.startswith(prefix) and v != ""})
    return out


@pytest.fixture(scope="module")
def ddp_run(tmp_path_factory):
    from test_data_synthetic import make_shards

    root = tmp_path_factory.mktemp("ddp")
    # 88 training samples (44 per rank, 6 batches of <= 8), 39 validation and 21 test samples: odd, so the
    # DistributedSampler pads each with a repeated sample; groups of >= 2 grasps for Kendall tau
    make_shards(root / "grasps", grasps=5, num_steps=2)
    out = root / "run"
    env = {
        **os.environ,
        "OMP_NUM_THREADS": "1",
        "WANDB_MODE": "offline",
        "HYDRA_FULL_ERROR": "1",
        "PYTHONWARNINGS": "ignore",
        "PYTHONPATH": os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")]),
    }
    r = subprocess.run(
        [
            sys.executable,
            str(ROOT / "train.py"),
            "experiment=quickstart",
            "trainer=ddp",
            "trainer.accelerator=cpu",
            "trainer.devices=2",
            "trainer.max_epochs=1",
            "callbacks=[default,throughput]",
            "callbacks.throughput.warmup_steps=1",
            "+callbacks.rank_state._target_=test_ddp.SaveRankState",
            f"+callbacks.rank_state.dirpath={out}/ranks",
            "logger=csv",
            "data.val_fraction=0.4",
            f"paths.data_dir={root}",
            f"paths.log_dir={root}/logs",
            f"hydra.run.dir={out}",
            *TINY,
        ],
        cwd=root,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stderr[-4000:]
    return out


def test_ddp_fit_checkpoints_and_keeps_ranks_identical(ddp_run):
    assert (ddp_run / "checkpoints" / "last.ckpt").exists()
    assert "GLOBAL_RANK: 1, MEMBER: 2/2" in (ddp_run / "quickstart.log").read_text()
    states = [torch.load(ddp_run / "ranks" / f"rank{r}.pt") for r in (0, 1)]
    assert states[0].keys() == states[1].keys()
    for k in states[0]:
        assert torch.equal(states[0][k], states[1][k]), k
    assert states[0]["net.stress_norm.count"] > 0
    # the checkpoint holds the (common) trained weights, not the initial ones
    ckpt = torch.load(ddp_run / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=False)
    for k, v in states[0].items():
        assert torch.equal(ckpt["state_dict"][k], v), k


def test_ddp_metrics_are_those_of_the_whole_split(ddp_run):
    from defgraspnets.data.datamodule import GraspDataModule
    from defgraspnets.models.defgraspnets_module import DefGraspNetsModule

    rows = _metrics(ddp_run)
    logged_val, logged_test = _last(rows, "val/"), _last(rows, "test/")
    assert logged_val["val/tau_groups"] > 0 and logged_test["test/loss"] > 0
    ckpt = ddp_run / "checkpoints" / "last.ckpt"
    model = DefGraspNetsModule.load_from_checkpoint(ckpt, map_location="cpu")
    dm = GraspDataModule.load_from_checkpoint(ckpt, map_location="cpu")
    trainer = Trainer(
        accelerator="cpu", devices=1, logger=False, enable_progress_bar=False, enable_model_summary=False
    )
    single = trainer.validate(model, datamodule=dm, verbose=False)[0]
    single.update(trainer.test(model, datamodule=dm, verbose=False)[0])
    assert len(dm.datasets["val"]) == 39 and len(dm.datasets["test"]) == 21
    for k, v in {**logged_val, **logged_test}.items():
        assert k in single, k
        if math.isnan(v):
            assert math.isnan(single[k]), k
        else:
            assert v == pytest.approx(single[k], rel=1e-5, abs=1e-9), k


def test_ddp_throughput_sums_the_ranks(ddp_run):
    logged = _last(_metrics(ddp_run), "train/")
    # 44 samples per rank in batches 8, 8, 8, 8, 8, 4; the first batch is warm-up: 36 graphs per rank
    assert logged["train/throughput_graphs"] == 72
    assert logged["train/graphs_per_sec"] > 0
    assert logged["train/graphs_per_sec_per_device"] == pytest.approx(logged["train/graphs_per_sec"] / 2)


class _Graphs:
    def __init__(self, x: torch.Tensor):
        self.x = x
        self.graph_count = x.shape[0]


class _Toy(LightningModule):
    def __init__(self):
        super().__init__()
        self.layer = torch.nn.Linear(4, 1)

    def training_step(self, batch, batch_idx):
        return self.layer(batch.x).square().mean()

    def train_dataloader(self):
        data = [torch.randn(n, 4) for n in (3, 3, 3, 3, 2)]
        return torch.utils.data.DataLoader(data, batch_size=None, collate_fn=_Graphs)

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=0.1)


def test_throughput_callback_logs_graphs_per_second(tmp_path):
    from defgraspnets.training import GraphThroughput

    trainer = Trainer(
        accelerator="cpu",
        devices=1,
        max_epochs=2,
        callbacks=[GraphThroughput(warmup_steps=2)],
        logger=CSVLogger(tmp_path, name="csv"),
        enable_progress_bar=False,
        enable_model_summary=False,
        enable_checkpointing=False,
    )
    trainer.fit(_Toy())
    with open(next(tmp_path.glob("csv/version_*/metrics.csv"))) as f:
        rows = [r for r in csv.DictReader(f) if r.get("train/graphs_per_sec")]
    assert len(rows) == 2  # once per epoch
    for r in rows:
        assert float(r["train/graphs_per_sec"]) > 0
        assert float(r["train/throughput_graphs"]) == 3 + 3 + 2  # batches 3..5 after 2 warm-up batches
        assert float(r["train/graphs_per_sec_per_device"]) == pytest.approx(float(r["train/graphs_per_sec"]))
    with pytest.raises(ValueError, match="warmup_steps"):
        GraphThroughput(warmup_steps=-1)


def _train_module():
    import importlib.util

    spec = importlib.util.spec_from_file_location("train_entry", ROOT / "train.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_ranks_started_by_srun_or_torchrun_share_one_run_dir(monkeypatch):
    pin = _train_module().pin_run_dir_for_external_launch
    for var in ("SLURM_NTASKS", "SLURM_JOB_ID", "SLURM_STEP_ID", "TORCHELASTIC_RUN_ID"):
        monkeypatch.delenv(var, raising=False)
    argv = ["train.py", "trainer=ddp"]
    pin(argv)
    assert argv == ["train.py", "trainer=ddp"]  # plain run: Hydra's ${now:...} directory
    monkeypatch.setenv("SLURM_NTASKS", "8")
    monkeypatch.setenv("SLURM_JOB_ID", "4242")
    monkeypatch.setenv("SLURM_STEP_ID", "0")
    pin(argv)
    assert argv[-1] == "hydra.run.dir=${paths.log_dir}/${task_name}/runs/slurm_4242_0"
    for given in (["train.py", "hydra.run.dir=/x"], ["train.py", "-m", "model.latent=4,8"]):
        before = list(given)
        pin(given)
        assert given == before  # an explicit run dir, or a multirun (sweep dirs), is left alone
    monkeypatch.delenv("SLURM_NTASKS")
    monkeypatch.setenv("TORCHELASTIC_RUN_ID", "abc")
    argv = ["train.py"]
    pin(argv)
    assert argv[-1].endswith("/runs/torchrun_abc")


def test_multirun_with_self_launching_ddp_is_refused(tmp_path):
    r = subprocess.run(
        [
            sys.executable,
            str(ROOT / "train.py"),
            "-m",
            "experiment=quickstart",
            "trainer=ddp",
            "trainer.accelerator=cpu",
            "trainer.devices=2",
            f"paths.data_dir={tmp_path}",
            f"hydra.sweep.dir={tmp_path}/sweep",
            "logger=csv",
            "data._target_=builtins.dict",  # never reached: the check runs before fitting
            *TINY,
        ],
        cwd=tmp_path,
        env={**os.environ, "OMP_NUM_THREADS": "1", "HYDRA_FULL_ERROR": "1", "PYTHONWARNINGS": "ignore"},
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode != 0
    assert "cannot use a multi-process trainer" in r.stderr, r.stderr[-2000:]


@pytest.mark.slow
def test_benchmark_ddp_script_on_cpu(tmp_path):
    env = {
        **os.environ,
        "OMP_NUM_THREADS": "1",
        "PYTHONWARNINGS": "ignore",
        "PYTHON": sys.executable,
        "ACCELERATOR": "cpu",
        "DEVICES": "1 2",
        "LATENT": "8",
        "BLOCKS": "1",
        "OBJECTS": "2",
        "GRASPS": "6",
        "STEPS": "2",
        "DIVISIONS": "4,3,3",
        "PAD_N": "3",
        "BATCH": "4",
        "WORKERS": "0",
        "EPOCHS": "1",
        "WARMUP": "1",
        "DATA": str(tmp_path / "data"),
        "OUT": str(tmp_path / "out"),
    }
    r = subprocess.run(
        ["bash", str(ROOT / "scripts" / "benchmark_ddp.sh")],
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    result = json.loads((tmp_path / "out" / "benchmark_ddp.json").read_text())
    runs = {run["devices"]: run for run in result["runs"]}
    assert set(runs) == {1, 2} and result["accelerator"] == "cpu"
    assert all(run["graphs_per_sec"] > 0 for run in runs.values())
    # 48 training graphs: 1 device, 12 batches of 4 less 1 warm-up; 2 devices, 6 per rank less 1 each
    assert runs[1]["graphs_measured_last_epoch"] == 44 and runs[2]["graphs_measured_last_epoch"] == 40
    assert runs[2]["speedup"] == pytest.approx(runs[2]["graphs_per_sec"] / runs[1]["graphs_per_sec"])
