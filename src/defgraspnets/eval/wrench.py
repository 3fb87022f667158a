"""Evaluation of the wrench CNN (thesis §3.4): errors in SI units and the Fig. 3.4 / 3.7 / 3.8 analogues.

The thesis reports one number per model, the validation MSE over the six wrench components in SI
units (N for forces, N m for torques, all squared errors averaged together): 0.03 (poking), 0.057
(forearm), 0.1 (combined). :func:`wrench_errors` reports that number and, because forces dominate it
(torques are ~100x smaller in N m), also the MSE, RMSE and coefficient of determination R² of each
component.

Plots (:func:`plot_poke_torque_polar`, :func:`plot_forearm_shear`, :func:`plot_forearm_twist`) draw the
ground truth next to each model's prediction on the same samples, as the thesis's figures do:

* Fig. 3.4: tau_x over the pre-indentation contact points (phi, rho) of the poking grid, for one
  indentation angle theta and depth delta; marker size ~ |tau_x|, colour = sign.
* Fig. 3.7: the force components along a forearm shear (direction phi = 3 pi / 4, depth 0.75 cm) vs
  the shear distance.
* Fig. 3.8: tau_z vs the forearm's yaw (twist) angle, one curve per indentation depth.

A figure's slice is a set of grid states, and with the repeated forearm experiment every state is read
once per repeat (on a re-placed forearm, :mod:`defgraspnets.tactile.datasets`): the figures show
repeat 0 only, the nominal placement (rows whose ``repeat`` param is 0 or NaN, i.e. not recorded:
poking and version 1 files), so each curve has one point per state.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from defgraspnets.data.tactile_schema import PARAM_NAMES, WRENCH_COMPONENTS

__all__ = [
    "WrenchErrors",
    "dataset_params",
    "plot_forearm_shear",
    "plot_forearm_twist",
    "plot_poke_torque_polar",
    "predict_dataset",
    "wrench_errors",
]

_P = {name: i for i, name in enumerate(PARAM_NAMES)}


@dataclass(frozen=True)
class WrenchErrors:
    """Errors of predicted wrenches against the simulated ones, SI units.

    Attributes:
        mse: mean over samples and the 6 components of the squared error (the thesis's number).
        component_mse, component_rmse: (6,) per component [N², N m²] / [N, N m].
        component_r2: (6,) coefficient of determination per component (1 = perfect; NaN if the
            component does not vary).
        count: number of samples.
    """

    mse: float
    component_mse: np.ndarray
    component_rmse: np.ndarray
    component_r2: np.ndarray
    count: int

    def to_dict(self) -> dict:
        per = {
            name: {"mse": float(m), "rmse": float(r), "r2": None if np.isnan(q) else float(q)}
            for name, m, r, q in zip(
                WRENCH_COMPONENTS, self.component_mse, self.component_rmse, self.component_r2
            )
        }
        return {"mse": self.mse, "count": self.count, "components": per}


def wrench_errors(true, predicted) -> WrenchErrors:
    """Errors of ``predicted`` against ``true`` wrenches, both (N, 6) [N, N m]."""
    t = np.asarray(true, dtype=np.float64)
    p = np.asarray(predicted, dtype=np.float64)
    if t.ndim != 2 or t.shape[1] != 6 or t.shape != p.shape:
        raise ValueError(f"wrenches must both be (N, 6), got {t.shape} and {p.shape}")
    if len(t) == 0:
        raise ValueError("no samples to evaluate")
    if not (np.isfinite(t).all() and np.isfinite(p).all()):
        raise ValueError("wrenches contain NaN or infinite values")
    sq = (p - t) ** 2
    mse = sq.mean(axis=0)
    var = t.var(axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        r2 = np.where(var > 0, 1.0 - mse / np.where(var > 0, var, 1.0), np.nan)
    return WrenchErrors(float(sq.mean()), mse, np.sqrt(mse), r2, len(t))


def dataset_params(dataset) -> np.ndarray:
    """(N, len(PARAM_NAMES)) parameters (``PARAM_NAMES``: the command, then the repeat and its
    perturbation) of the samples of a
    :class:`~defgraspnets.data.tactile_datamodule.TactileWrenchDataset` or a ConcatDataset of them, in
    the dataset's order."""
    parts = getattr(dataset, "datasets", [dataset])
    return np.concatenate([d.shard.samples.params[d.indices] for d in parts])


def predict_dataset(
    module, dataset, batch_size: int = 256, device: str = "cpu"
) -> tuple[np.ndarray, np.ndarray]:
    """Run a :class:`~defgraspnets.models.wrench_module.WrenchRegressionModule` over a dataset of
    ``(x, wrench)`` pairs (e.g. the datamodule's validation split); returns (true, predicted) (N, 6)."""
    import torch
    from torch.utils.data import DataLoader

    module = module.to(device).eval()
    true, pred = [], []
    with torch.no_grad():
        for x, w in DataLoader(dataset, batch_size=batch_size, shuffle=False):
            pred.append(module(x.to(device)).float().cpu().numpy())
            true.append(w.numpy())
    if not true:
        raise ValueError("the dataset is empty")
    return np.concatenate(true), np.concatenate(pred)


def _nominal(params: np.ndarray) -> np.ndarray:
    """(N,) bool: rows of repeat 0, the nominal placement (``repeat`` 0, or NaN = not recorded; params
    with only the 7 command columns of schema version 1 are all nominal)."""
    if params.shape[1] <= _P["repeat"]:
        return np.ones(len(params), dtype=bool)
    return ~(params[:, _P["repeat"]] > 0)  # NaN > 0 is False


def _nearest(values: np.ndarray, target: float) -> float:
    finite = np.unique(values[np.isfinite(values)])
    if len(finite) == 0:
        raise ValueError("no samples carry this parameter")
    return float(finite[np.argmin(np.abs(finite - target))])


def _figure(n_panels: int, polar: bool = False):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    kw = {"subplot_kw": {"projection": "polar"}} if polar else {}
    fig, axes = plt.subplots(1, n_panels, figsize=(4.2 * n_panels, 4.0), squeeze=False, **kw)
    return plt, fig, axes[0]


def plot_poke_torque_polar(
    params: np.ndarray,
    true: np.ndarray,
    predictions: Mapping[str, np.ndarray],
    path,
    theta: float = 0.35,
    depth: float = 0.015,
) -> dict:
    """Fig. 3.4 analogue: tau_x at the poke contact points (phi, rho) for the grid's theta and depth
    nearest to the requested ones (repeat 0 only). Returns the chosen (theta, depth) and the sample
    count."""
    params = np.asarray(params)
    nominal = _nominal(params)
    th = _nearest(params[nominal, _P["theta"]], theta)
    de = _nearest(params[nominal, _P["depth"]], depth)
    sel = nominal & np.isclose(params[:, _P["theta"]], th) & np.isclose(params[:, _P["depth"]], de)
    columns = {
        "simulated (ground truth)": np.asarray(true)[sel],
        **{k: np.asarray(v)[sel] for k, v in predictions.items()},
    }
    tau = {k: v[:, 3] for k, v in columns.items()}
    scale = max(float(np.max(np.abs(np.concatenate(list(tau.values()))))), 1e-12)
    plt, fig, axes = _figure(len(columns), polar=True)
    for ax, (name, t) in zip(axes, tau.items()):
        ax.scatter(
            params[sel, _P["phi"]],
            params[sel, _P["contact_radius"]] * 100,
            s=15 + 300 * np.abs(t) / scale,
            c=np.sign(t),
            cmap="coolwarm",
            vmin=-1,
            vmax=1,
            alpha=0.8,
        )
        ax.set_title(name, fontsize=10)
        ax.set_rlabel_position(90)
    fig.suptitle(
        f"tau_x [N m] at contact points (phi, rho [cm]); theta = {th:.2f} rad, depth = {de * 100:.1f} cm"
        f"; max |tau_x| = {scale:.3g} N m (red +, blue -)",
        fontsize=9,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return {"theta": th, "depth": de, "samples": int(sel.sum())}


def plot_forearm_shear(
    params: np.ndarray,
    true: np.ndarray,
    predictions: Mapping[str, np.ndarray],
    path,
    direction: float = 3 * np.pi / 4,
    depth: float = 0.0075,
) -> dict:
    """Fig. 3.7 analogue: F_x, F_y, F_z vs shear distance along the grid's shear direction and depth
    nearest to the requested ones (shear samples only, twist = 0; repeat 0 only, the nominal placement:
    one point per shear distance)."""
    params = np.asarray(params)
    shear = _nominal(params) & (params[:, _P["twist"]] == 0)
    d = _nearest(params[shear, _P["shear_direction"]], direction)
    de = _nearest(params[shear, _P["depth"]], depth)
    sel = shear & np.isclose(params[:, _P["shear_direction"]], d) & np.isclose(params[:, _P["depth"]], de)
    order = np.argsort(params[sel, _P["shear_distance"]])
    dist = params[sel, _P["shear_distance"]][order] * 100
    plt, fig, axes = _figure(3)
    for c, ax in enumerate(axes):
        ax.plot(dist, np.asarray(true)[sel][order, c], "k-o", label="simulated")
        for (name, p), m in zip(predictions.items(), "sx^"):
            ax.plot(dist, np.asarray(p)[sel][order, c], "--" + m, label=name)
        ax.set_xlabel("shear distance [cm]")
        ax.set_ylabel(f"{WRENCH_COMPONENTS[c]} [N]")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle(f"forearm shear, direction {d:.2f} rad, depth {de * 100:.2f} cm", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return {"direction": d, "depth": de, "samples": int(sel.sum())}


def plot_forearm_twist(
    params: np.ndarray, true: np.ndarray, predictions: Mapping[str, np.ndarray], path
) -> dict:
    """Fig. 3.8 analogue: tau_z vs the forearm's yaw angle, one panel per model, one curve per depth
    (repeat 0 only, the nominal placement)."""
    params = np.asarray(params)
    twist = np.isfinite(params[:, _P["twist"]]) & (params[:, _P["twist"]] != 0)  # poke rows carry NaN
    twist &= _nominal(params)
    if not twist.any():
        raise ValueError("no twist samples to plot")
    depths = np.unique(params[twist, _P["depth"]])
    columns = {"simulated": np.asarray(true), **{k: np.asarray(v) for k, v in predictions.items()}}
    plt, fig, axes = _figure(len(columns))
    colours = plt.cm.viridis(np.linspace(0, 1, len(depths)))
    for ax, (name, w) in zip(axes, columns.items()):
        for de, col in zip(depths, colours):
            sel = twist & np.isclose(params[:, _P["depth"]], de)
            order = np.argsort(params[sel, _P["twist"]])
            ax.plot(
                params[sel, _P["twist"]][order],
                w[sel][order, 5],
                "-o",
                ms=3,
                color=col,
                label=f"{de * 100:.2f} cm",
            )
        ax.set_title(name, fontsize=10)
        ax.set_xlabel("yaw angle [rad]")
        ax.set_ylabel("tau_z [N m]")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7, title="depth")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return {"depths": depths.tolist(), "samples": int(twist.sum())}
