"""Wrench CNN (thesis §3.4): shapes, overfitting a tiny synthetic set, Lightning fit, inference call."""

import lightning as L
import numpy as np
import pytest
import torch

from defgraspnets.data.tactile_datamodule import TactileWrenchDataModule, normalize_depth
from defgraspnets.data.tactile_schema import (
    PARAM_NAMES,
    TactileReferences,
    TactileSamples,
    TactileShardWriter,
)
from defgraspnets.models.wrench_cnn import WrenchCNN
from defgraspnets.models.wrench_module import WrenchRegressionModule

H, W = 16, 24
REFERENCE_DEPTH = 0.15


def synthetic_dents(n: int, seed: int = 0):
    """Depth images of Gaussian dents (centre u0, v0; depth a) and a smooth wrench of (u0, v0, a)."""
    rng = np.random.default_rng(seed)
    v, u = np.meshgrid(np.arange(H), np.arange(W), indexing="ij")
    p = rng.random((n, 3))
    u0, v0, a = 4 + p[:, 0] * (W - 8), 4 + p[:, 1] * (H - 8), 0.005 + 0.02 * p[:, 2]
    dent = a[:, None, None] * np.exp(-((u - u0[:, None, None]) ** 2 + (v - v0[:, None, None]) ** 2) / 8.0)
    reference = np.full((H, W), REFERENCE_DEPTH, np.float32)
    reference[0, :3] = np.nan  # pixels without return
    depth = (reference - dent).astype(np.float32)
    du, dv = (u0 - W / 2) / W, (v0 - H / 2) / H
    wrench = np.stack([200 * a * du, 200 * a * dv, -300 * a, 10 * a * dv, -10 * a * du, np.zeros(n)], axis=1)
    return depth, reference, wrench.astype(np.float32)


@pytest.fixture
def one_thread():
    """Small convolutions run faster on one thread than on two contended cores."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def test_thesis_resolution_output_shape_and_input_check():
    net = WrenchCNN()
    assert net(torch.zeros(3, 1, 171, 224)).shape == (3, 6)
    assert sum(p.numel() for p in net.parameters()) < 1_000_000
    dropouts = [m for m in net.modules() if isinstance(m, torch.nn.Dropout)]
    assert dropouts and all(m.p == 0.2 for m in dropouts)
    assert sum(isinstance(m, torch.nn.Conv2d) for m in net.modules()) == 2
    assert sum(isinstance(m, torch.nn.MaxPool2d) for m in net.modules()) == 2
    with pytest.raises(ValueError, match=r"\(B, 1, 171, 224\)"):
        net(torch.zeros(3, 1, 170, 224))
    assert WrenchCNN(input_pool=2)(torch.zeros(1, 1, 171, 224)).shape == (1, 6)
    with pytest.raises(ValueError, match="too small"):
        WrenchCNN(image_shape=(8, 8), pool_size=4)


def test_overfits_a_tiny_synthetic_set(one_thread):
    torch.manual_seed(0)
    depth, reference, wrench = synthetic_dents(16)
    module = WrenchRegressionModule(
        WrenchCNN(image_shape=(H, W), channels=(8, 16), pool_size=2, hidden_features=(64,)),
        lr=0.01,
        momentum=0.9,
    )
    x = torch.from_numpy(normalize_depth(depth, reference, 0.01)[:, None])
    y = torch.from_numpy(wrench)
    optimizer = module.configure_optimizers()
    assert isinstance(optimizer, torch.optim.SGD) and optimizer.defaults["lr"] == 0.01

    def eval_loss():
        module.eval()
        with torch.no_grad():
            return torch.nn.functional.mse_loss(module(x), y).item()

    before = eval_loss()
    module.train()
    for _ in range(100):
        optimizer.zero_grad()
        module.loss_fn(module(x), y).backward()
        optimizer.step()
    assert eval_loss() < before / 50


def _write_shard(path, n, seed):
    depth, reference, wrench = synthetic_dents(n, seed)
    refs = TactileReferences(reference[None], [[101325.0, 6e-4]], ["free_air"])
    writer = TactileShardWriter(path, refs, "poke")
    writer.append(
        TactileSamples(
            depth=depth,
            wrench=wrench,
            indenter_pose=np.tile([0, 0, 0.2, 0, 0, 0, 1.0], (n, 1)),
            indenter_kind=["sphere"] * n,
            pv_state=np.tile([101325.0, 6e-4], (n, 1)),
            reference_index=np.zeros(n, int),
            params=np.full((n, len(PARAM_NAMES)), np.nan),
            sample_id=np.arange(n),
        )
    )
    return writer.finalize()


def _small_net() -> WrenchCNN:
    return WrenchCNN(image_shape=(H, W), channels=(4, 8), pool_size=2, hidden_features=(16,))


def _fit_two_epochs(tmp_path, **module_options):
    """A small CNN fitted for 2 epochs on a 40-sample synthetic shard: (trainer, module, datamodule)."""
    _write_shard(tmp_path / "poke_000.h5", 40, seed=1)
    dm = TactileWrenchDataModule([str(tmp_path / "poke_*.h5")], batch_size=8)
    torch.manual_seed(0)
    module = WrenchRegressionModule(_small_net(), **module_options)
    trainer = L.Trainer(
        max_epochs=2,
        accelerator="cpu",
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
    )
    trainer.fit(module, datamodule=dm)
    return trainer, module, dm


def test_lightning_fit_metrics_and_inference_call(tmp_path, one_thread):
    trainer, module, dm = _fit_two_epochs(tmp_path)
    m = {k: float(v) for k, v in trainer.callback_metrics.items()}
    per_component = [m[f"val/mse_{c}"] for c in ("fx", "fy", "fz", "tx", "ty", "tz")]
    assert np.isclose(m["val/loss"], np.mean(per_component), rtol=1e-4)
    assert np.isclose(m["val/force_rmse"], np.sqrt(np.mean(per_component[:3])), rtol=1e-5)
    assert np.isclose(m["val/torque_rmse"], np.sqrt(np.mean(per_component[3:])), rtol=1e-5)
    assert "train/force_rmse" in m
    tested = trainer.test(module, datamodule=dm, verbose=False)[0]
    assert np.isclose(tested["test/loss"], m["val/loss"], rtol=1e-4)  # the test split is the 20 % split

    # inference on raw depth images equals the module's forward on the normalized input
    depth, reference, _ = synthetic_dents(5, seed=9)
    module.eval()
    with torch.no_grad():
        expected = module(torch.from_numpy(normalize_depth(depth, reference, 0.01)[:, None])).numpy()
    batch = module.predict_wrench(depth)  # reference taken from the datamodule (one PV state)
    assert isinstance(batch, np.ndarray) and batch.shape == (5, 6)
    np.testing.assert_allclose(batch, expected, rtol=1e-5, atol=1e-6)
    single = module.predict_wrench(depth[2], reference)
    assert single.shape == (6,)
    np.testing.assert_allclose(single, expected[2], rtol=1e-5, atol=1e-6)
    as_torch = module.predict_wrench(torch.from_numpy(depth), torch.from_numpy(reference))
    assert isinstance(as_torch, torch.Tensor)
    np.testing.assert_allclose(as_torch.numpy(), expected, rtol=1e-5, atol=1e-6)

    # the reference image travels with the checkpoint
    ckpt = tmp_path / "wrench.ckpt"
    trainer.save_checkpoint(ckpt)
    loaded = WrenchRegressionModule.load_from_checkpoint(ckpt, net=_small_net())
    np.testing.assert_allclose(loaded.predict_wrench(depth), expected, rtol=1e-5, atol=1e-6)
    # ... and so do the network's constructor arguments: no net needed to load it
    rebuilt = WrenchRegressionModule.from_checkpoint(ckpt)
    assert not rebuilt.training
    np.testing.assert_allclose(rebuilt.predict_wrench(depth), expected, rtol=1e-5, atol=1e-6)
    with pytest.raises(FileNotFoundError, match="wrench checkpoint"):
        WrenchRegressionModule.from_checkpoint(tmp_path / "missing.ckpt")

    with pytest.raises(ValueError, match="shape"):
        module.predict_wrench(depth[:, :, :-1], reference)
    with pytest.raises(ValueError, match="no reference"):
        WrenchRegressionModule(WrenchCNN(image_shape=(H, W))).predict_wrench(depth)


def test_depth_scale_mismatch_is_an_error(tmp_path):
    _write_shard(tmp_path / "poke_000.h5", 10, seed=2)
    dm = TactileWrenchDataModule([str(tmp_path / "poke_000.h5")], batch_size=4, depth_scale=0.02)
    module = WrenchRegressionModule(
        WrenchCNN(image_shape=(H, W), channels=(2, 2), pool_size=2, hidden_features=(4,))
    )
    trainer = L.Trainer(
        max_steps=1,
        accelerator="cpu",
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
    )
    with pytest.raises(ValueError, match="depth_scale"):
        trainer.fit(module, datamodule=dm)


@pytest.fixture
def tiny_tactile_tree(tmp_path):
    """Poke and forearm shards of 12 full-size (171 x 224) images under <tmp>/tactile/."""
    rng = np.random.default_rng(0)
    reference = np.full((171, 224), REFERENCE_DEPTH, np.float32)
    refs = TactileReferences(reference[None], [[101325.0, 6e-4]], ["free_air"])
    n = 12
    for kind in ("poke", "forearm"):
        (tmp_path / "tactile" / kind).mkdir(parents=True)
        writer = TactileShardWriter(tmp_path / "tactile" / kind / f"{kind}_000.h5", refs, kind)
        writer.append(
            TactileSamples(
                depth=reference - 0.01 * rng.random((n, 171, 224)).astype(np.float32),
                wrench=rng.normal(size=(n, 6)),
                indenter_pose=np.tile([0, 0, 0.2, 0, 0, 0, 1.0], (n, 1)),
                indenter_kind=["sphere"] * n,
                pv_state=np.tile([101325.0, 6e-4], (n, 1)),
                reference_index=np.zeros(n, int),
                params=np.full((n, len(PARAM_NAMES)), np.nan),
                sample_id=np.arange(n),
            )
        )
        writer.finalize()
    return tmp_path


def _compose(experiment, data_dir, out_dir, *overrides):
    from pathlib import Path

    from hydra import compose, initialize_config_dir

    root = Path(__file__).resolve().parents[1]
    with initialize_config_dir(config_dir=str(root / "configs"), version_base="1.3"):
        return compose(
            config_name="train",
            overrides=[
                f"experiment={experiment}",
                f"paths.root_dir={root}",
                f"paths.data_dir={data_dir}",
                f"paths.output_dir={out_dir}",
                f"paths.log_dir={out_dir}",
                f"paths.work_dir={out_dir}",
                *overrides,
            ],
        )


@pytest.mark.parametrize(
    "experiment, batch_size, n_train",
    [("wrench_poke", 500, 10), ("wrench_forearm", 400, 10), ("wrench_combined", 500, 20)],
)
def test_experiment_configs_compose_and_instantiate(
    tiny_tactile_tree, tmp_path, experiment, batch_size, n_train
):
    import hydra

    cfg = _compose(experiment, tiny_tactile_tree, tmp_path / "out")
    assert cfg.data.batch_size == batch_size and cfg.model.lr == 0.01 and cfg.model.momentum == 0.0
    assert cfg.model.net.dropout == 0.2 and list(cfg.model.net.image_shape) == [171, 224]
    dm = hydra.utils.instantiate(cfg.data)
    model = hydra.utils.instantiate(cfg.model)
    dm.setup()
    assert len(dm.data_train) == n_train and model.hparams.depth_scale == dm.depth_scale
    x, _ = next(iter(dm.train_dataloader()))
    assert model(x).shape == (len(x), 6)


def _tz_r2(module, x, y) -> float:
    module.eval()
    with torch.no_grad():
        tz = module(x)[:, 5]
    return 1.0 - float(((tz - y[:, 5]) ** 2).sum() / ((y[:, 5] - y[:, 5].mean()) ** 2).sum())


def test_standardized_targets_learn_a_torque_that_si_units_drown(one_thread):
    """A twist-like torque (+-0.02 N m beside forces up to 7 N, as the forearm twists' tau_z, which is not a
    function of the forces as tau_x, tau_y are): the SI loss leaves it unlearnt, the standardized one learns
    it, with the same network, data, optimizer and steps."""
    depth, reference, wrench = synthetic_dents(32, seed=3)
    # tau_z, a smooth function of the dent's centre column that the forces do not carry
    _, u = np.meshgrid(np.arange(H), np.arange(W), indexing="ij")
    dent = reference - depth
    centre_u = np.nansum(dent * u, axis=(1, 2)) / np.nansum(dent, axis=(1, 2))
    wrench[:, 5] = 0.02 * (centre_u - W / 2) / W * 2
    x = torch.from_numpy(normalize_depth(depth, reference, 0.01)[:, None])
    y = torch.from_numpy(wrench)
    r2 = {}
    for scaling in ("si", "standardize"):
        torch.manual_seed(0)
        module = WrenchRegressionModule(
            WrenchCNN(image_shape=(H, W), channels=(8, 16), pool_size=2, hidden_features=(64,), dropout=0.0),
            lr=0.01,
            momentum=0.9,
            target_scaling=scaling,
        )
        if scaling == "standardize":
            module.fit_target_scaling(wrench)
            np.testing.assert_allclose(module.wrench_std.numpy(), wrench.std(axis=0, ddof=1), rtol=1e-5)
        optimizer = module.configure_optimizers()
        module.train()
        for _ in range(150):
            optimizer.zero_grad()
            module.wrench_loss(module(x), y).backward()
            optimizer.step()
        r2[scaling] = _tz_r2(module, x, y)
    assert r2["standardize"] > 0.8, r2
    assert r2["si"] < 0.3, r2


def test_standardized_fit_stores_the_training_statistics_and_returns_si_wrenches(tmp_path, one_thread):
    trainer, module, dm = _fit_two_epochs(tmp_path, target_scaling="standardize")
    train_wrench = dm.train_wrenches()
    assert train_wrench.shape == (len(dm.data_train), 6)  # the training split only
    np.testing.assert_allclose(module.wrench_mean.numpy(), train_wrench.mean(axis=0), rtol=1e-5, atol=1e-7)
    expected_std = train_wrench.std(axis=0, ddof=1)
    expected_std[expected_std == 0] = 1.0  # the synthetic tau_z is 0: kept in SI units
    np.testing.assert_allclose(module.wrench_std.numpy(), expected_std, rtol=1e-5)
    # the loss is standardized, the logged per-component errors stay in SI units
    m = {k: float(v) for k, v in trainer.callback_metrics.items()}
    per_component = np.array([m[f"val/mse_{c}"] for c in ("fx", "fy", "fz", "tx", "ty", "tz")])
    assert np.isclose(m["val/loss"], np.mean(per_component / expected_std**2), rtol=1e-3)
    assert not np.isclose(m["val/loss"], np.mean(per_component), rtol=1e-2)

    depth, reference, _ = synthetic_dents(5, seed=9)
    x = torch.from_numpy(normalize_depth(depth, reference, 0.01)[:, None])
    module.eval()
    with torch.no_grad():
        si = module(x).numpy()
        np.testing.assert_allclose(si, (module.wrench_mean + module.wrench_std * module.net(x)).numpy())
    ckpt = tmp_path / "wrench.ckpt"
    trainer.save_checkpoint(ckpt)
    rebuilt = WrenchRegressionModule.from_checkpoint(ckpt)
    assert rebuilt.hparams.target_scaling == "standardize"
    np.testing.assert_allclose(rebuilt.wrench_std.numpy(), module.wrench_std.numpy())
    np.testing.assert_allclose(rebuilt.predict_wrench(depth), si, rtol=1e-5, atol=1e-6)

    # a checkpoint saved before the scaling existed loads as SI (identity statistics)
    old = torch.load(ckpt, weights_only=False)
    del old["state_dict"]["wrench_mean"], old["state_dict"]["wrench_std"]
    old["hyper_parameters"].pop("target_scaling")
    torch.save(old, tmp_path / "old.ckpt")
    legacy = WrenchRegressionModule.from_checkpoint(tmp_path / "old.ckpt")
    assert legacy.hparams.target_scaling == "si"
    np.testing.assert_array_equal(legacy.wrench_mean.numpy(), np.zeros(6))
    np.testing.assert_array_equal(legacy.wrench_std.numpy(), np.ones(6))
    with torch.no_grad():
        np.testing.assert_allclose(legacy(x).numpy(), module.net(x).numpy(), rtol=1e-6)

    with pytest.raises(ValueError, match="target_scaling must be one of"):
        WrenchRegressionModule(_small_net(), target_scaling="normalise")
    with pytest.raises(ValueError, match="NaN or inf"):
        module.fit_target_scaling(np.full((4, 6), np.nan))
    with pytest.raises(ValueError, match=r"\(N >= 2, 6\)"):
        module.fit_target_scaling(np.zeros((4, 3)))
