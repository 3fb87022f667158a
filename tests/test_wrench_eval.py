"""Wrench-CNN evaluation (thesis §3.4): SI errors, Fig. 3.4 / 3.7 / 3.8 analogues, the script end to end."""

import json
import subprocess
import sys
from pathlib import Path

import lightning as L
import numpy as np
import pytest
import torch

from defgraspnets.data.tactile_datamodule import TactileWrenchDataModule
from defgraspnets.data.tactile_schema import (
    PARAM_NAMES,
    TactileReferences,
    TactileSamples,
    TactileShardWriter,
)
from defgraspnets.eval.wrench import (
    dataset_params,
    plot_forearm_shear,
    plot_forearm_twist,
    plot_poke_torque_polar,
    predict_dataset,
    wrench_errors,
)
from defgraspnets.models.wrench_cnn import WrenchCNN
from defgraspnets.models.wrench_module import WrenchRegressionModule

H, W = 12, 16
P = {n: i for i, n in enumerate(PARAM_NAMES)}


def test_wrench_errors_match_their_definitions():
    rng = np.random.default_rng(0)
    true = rng.normal(size=(50, 6))
    perfect = wrench_errors(true, true)
    assert perfect.mse == 0 and np.allclose(perfect.component_r2, 1)
    off = true + np.array([1.0, 0, 0, 0, 0, 0.1])
    e = wrench_errors(true, off)
    np.testing.assert_allclose(e.component_mse, [1, 0, 0, 0, 0, 0.01])
    assert np.isclose(e.mse, 1.01 / 6) and e.count == 50
    np.testing.assert_allclose(e.component_rmse[[0, 5]], [1.0, 0.1])
    # predicting the mean gives R^2 = 0; a constant component has no R^2
    flat = true.copy()
    flat[:, 2] = 3.0
    mean = np.tile(flat.mean(axis=0), (50, 1))
    r2 = wrench_errors(flat, mean).component_r2
    assert np.allclose(r2[[0, 1, 3, 4, 5]], 0, atol=1e-12) and np.isnan(r2[2])
    assert json.loads(json.dumps(e.to_dict()))["components"]["force_x"]["rmse"] == pytest.approx(1.0)
    with pytest.raises(ValueError, match=r"\(N, 6\)"):
        wrench_errors(true, true[:, :5])
    with pytest.raises(ValueError, match="NaN"):
        wrench_errors(true, np.where(true > 2, np.nan, true))


def _poke_params():
    rows = []
    for phi in np.linspace(0, 2 * np.pi, 8, endpoint=False):
        for rho in (0.0, 0.02, 0.04):
            for theta in (0.0, 0.35):
                for depth in (0.005, 0.015):
                    rows.append([phi, rho, theta, depth, np.nan, np.nan, np.nan])
    return np.array(rows)


def _forearm_params():
    rows = []
    for depth in (0.0025, 0.0075):
        for direction in (np.pi / 4, 3 * np.pi / 4):
            for dist in (0.003, 0.009, 0.015):
                rows.append([np.nan, np.nan, np.nan, depth, direction, dist, 0.0])
        for twist in (-0.5, -0.25, 0.25, 0.5):
            rows.append([np.nan, np.nan, np.nan, depth, 0.0, 0.0, twist])
    return np.array(rows)


def test_figures_pick_the_nearest_grid_slice(tmp_path):
    poke = _poke_params()
    torque_x = np.sin(poke[:, P["phi"]]) * poke[:, P["contact_radius"]]
    true = np.zeros((len(poke), 6))
    true[:, 3] = torque_x
    info = plot_poke_torque_polar(
        poke, true, {"poke model": -true}, tmp_path / "a.png", theta=0.3, depth=0.012
    )
    assert info == {"theta": 0.35, "depth": 0.015, "samples": 24}
    fore = _forearm_params()
    true = np.zeros((len(fore), 6))
    true[:, 0] = fore[:, P["shear_distance"]]
    true[:, 5] = fore[:, P["twist"]]
    info = plot_forearm_shear(
        fore, true, {"forearm model": true}, tmp_path / "b.png", direction=2.0, depth=0.007
    )
    assert (
        info["direction"] == pytest.approx(3 * np.pi / 4) and info["depth"] == 0.0075 and info["samples"] == 3
    )
    info = plot_forearm_twist(fore, true, {"forearm model": true}, tmp_path / "c.png")
    assert info == {"depths": [0.0025, 0.0075], "samples": 8}
    assert all((tmp_path / f).stat().st_size > 10_000 for f in ("a.png", "b.png", "c.png"))
    with pytest.raises(ValueError, match="twist"):
        plot_forearm_twist(poke, np.zeros((len(poke), 6)), {}, tmp_path / "d.png")


def test_figure_slices_show_the_nominal_placement_only(tmp_path, monkeypatch):
    """With perturbed forearm repeats every grid state is read several times; a figure's slice shows
    repeat 0 (the nominal placement) only, one point per state."""
    nominal = np.full((len(_forearm_params()), len(PARAM_NAMES)), np.nan)
    nominal[:, :7] = _forearm_params()
    nominal[:, 7:] = [0, 0, 0, 0, 1, 0]
    repeats = []
    for k in (1, 2):  # the same commands on a re-placed forearm
        r = nominal.copy()
        r[:, 7:] = [k, 0.003, -0.002, 0.05, 1.03, 0.05]
        repeats.append(r)
    fore = np.concatenate([repeats[0], nominal, repeats[1]])
    true = np.zeros((len(fore), 6))
    true[:, 0] = fore[:, P["shear_distance"]] + fore[:, P["repeat"]]  # repeats read differently
    true[:, 5] = fore[:, P["twist"]]
    info = plot_forearm_shear(fore, true, {"m": true}, tmp_path / "b.png", direction=2.0, depth=0.007)
    assert info["samples"] == 3  # the 3 shear distances of the slice, not 3 x 3 readings
    assert plot_forearm_twist(fore, true, {"m": true}, tmp_path / "c.png")["samples"] == 8
    old = np.concatenate([nominal[:, :7], nominal[:, :7]])  # 7-column (version 1) params: all nominal
    assert plot_forearm_shear(old, np.zeros((len(old), 6)), {}, tmp_path / "d.png")["samples"] == 6
    perturbed = fore[:, P["repeat"]] > 0
    with pytest.raises(ValueError, match="no twist samples"):  # repeats alone show nothing
        plot_forearm_twist(fore[perturbed], true[perturbed], {}, tmp_path / "e.png")
    # the plotted values are those of repeat 0: F_x = shear distance + repeat
    import matplotlib.axes

    curves = []
    original = matplotlib.axes.Axes.plot

    def spy(ax, *args, **kwargs):
        curves.append(np.asarray(args[1]))
        return original(ax, *args, **kwargs)

    monkeypatch.setattr(matplotlib.axes.Axes, "plot", spy)
    plot_forearm_shear(fore, true, {}, tmp_path / "f.png", direction=2.0, depth=0.007)
    np.testing.assert_allclose(curves[0], [0.003, 0.009, 0.015])


def _shard(path, experiment, params, seed):
    """A shard whose wrench is a linear function of a dent's depth: learnable by the CNN."""
    rng = np.random.default_rng(seed)
    n = len(params)
    reference = np.full((H, W), 0.15, np.float32)
    a = 0.002 + 0.01 * rng.random(n)
    depth = (reference - a[:, None, None] * np.ones((1, H, W))).astype(np.float32)
    wrench = np.stack([a, -a, -100 * a, 0.1 * a, 0 * a, 0.2 * a], axis=1).astype(np.float32)
    writer = TactileShardWriter(
        path, TactileReferences(reference[None], [[101325.0, 1e-3]], ["s"]), experiment
    )
    writer.append(
        TactileSamples(
            depth=depth,
            wrench=wrench,
            indenter_pose=np.tile([0, 0, 0.2, 0, 0, 0, 1.0], (n, 1)),
            indenter_kind=["sphere"] * n,
            pv_state=np.tile([101325.0, 1e-3], (n, 1)),
            reference_index=np.zeros(n, int),
            params=params,
            sample_id=np.arange(n),
        )
    )
    return writer.finalize()


def test_evaluate_script_scores_each_model_on_its_held_out_split(tmp_path):
    torch.manual_seed(0)
    shards = {"poke": _shard(tmp_path / "poke.h5", "poke", _poke_params(), 1)}
    shards["forearm"] = _shard(tmp_path / "forearm.h5", "forearm", _forearm_params(), 2)
    ckpts = {}
    for name, patterns in {"poke": ["poke"], "forearm": ["forearm"], "combined": ["poke", "forearm"]}.items():
        dm = TactileWrenchDataModule([str(shards[p]) for p in patterns], batch_size=16)
        module = WrenchRegressionModule(
            WrenchCNN(image_shape=(H, W), channels=(2, 2), pool_size=2, hidden_features=(8,)), lr=0.01
        )
        trainer = L.Trainer(
            max_epochs=1,
            accelerator="cpu",
            logger=False,
            enable_checkpointing=False,
            enable_progress_bar=False,
            enable_model_summary=False,
        )
        trainer.fit(module, datamodule=dm)
        ckpts[name] = tmp_path / f"{name}.ckpt"
        trainer.save_checkpoint(ckpts[name])
    out = tmp_path / "eval"
    script = Path(__file__).resolve().parents[1] / "scripts" / "evaluate_wrench.py"
    cmd = [sys.executable, str(script), f"hydra.run.dir={out}"]
    done = subprocess.run(
        cmd + [f"ckpts.{k}={v}" for k, v in ckpts.items()] + [f"shards.{k}=[{v}]" for k, v in shards.items()],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    saved = json.loads((out / "wrench_eval.json").read_text())
    assert saved["models"].keys() == {"poke", "forearm", "combined"}
    assert saved["models"]["combined"]["val"].keys() == {"poke", "forearm", "all"}
    # the reported MSE is the module's own loss on the datamodule's validation split
    dm = TactileWrenchDataModule([str(shards["poke"])], batch_size=16)
    dm.setup("fit")
    module = WrenchRegressionModule.from_checkpoint(ckpts["poke"])
    true, pred = predict_dataset(module, dm.data_val)
    with torch.no_grad():
        x = torch.stack([dm.data_val[i][0] for i in range(len(dm.data_val))])
        expected = torch.nn.functional.mse_loss(module(x), torch.from_numpy(true)).item()
    assert saved["models"]["poke"]["val"]["poke"]["mse"] == pytest.approx(expected, rel=1e-5)
    assert (
        saved["models"]["poke"]["val"]["poke"]["count"]
        == len(dm.data_val)
        == len(dataset_params(dm.data_val))
    )
    assert saved["thesis_val_mse"]["poke"] == 0.03
    assert {"fig3_4_poke_torque_x.png", "fig3_7_forearm_shear.png", "fig3_8_forearm_twist.png"} <= {
        p.name for p in out.iterdir()
    }
    nothing = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path)
    assert nothing.returncode != 0 and "no checkpoint given" in nothing.stderr


def test_shipped_poke_checkpoint_reads_a_simulated_poke():
    """checkpoints/wrench_poke.ckpt maps the FEM sensor's depth image of a poke it never saw (the pole,
    between the grid's depths) to the simulated base wrench."""
    from defgraspnets.tactile.datasets import make_simulator
    from defgraspnets.tactile.indenters import SphereIndenter
    from defgraspnets.tactile.membrane import build_membrane

    module = WrenchRegressionModule.from_checkpoint(
        Path(__file__).resolve().parents[1] / "checkpoints" / "wrench_poke.ckpt"
    )
    sim = make_simulator(
        build_membrane(cap_divisions=8, layers=2), SphereIndenter(radius=0.01), 1500.0, closed=True
    )
    np.testing.assert_allclose(
        sim.reference.depth.depth, module.reference_depth.numpy(), atol=1e-6, equal_nan=True
    )
    readings = sim.indent_series([sim.pole_indentation(0.012)], levels=[0.5, 1.0])
    for level in readings:
        r = level[0]
        assert r.converged
        predicted = module.predict_wrench(r.depth.depth)
        force = r.base_wrench[:3]
        assert abs(force[2]) > 0.2  # a real poke, not a trivially small one
        assert np.linalg.norm(predicted[:3] - force) < 0.1 * np.linalg.norm(force) + 0.05
