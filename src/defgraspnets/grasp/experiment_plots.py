"""Figure of a DefGraspSim experiment run: the performance metrics per grasp (bars) and the loss-of-grasp
acceleration per test direction (linear and angular), one line per grasp."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .experiments import GraspExperimentResults

__all__ = ["plot_experiments"]


def plot_experiments(path: str | Path, results: GraspExperimentResults, title: str = "") -> Path:
    """PNG with the pickup metrics (stress, deformation, strain energy; red bars: pickup failed, hatched),
    the deformation controllability, and the linear / angular thresholds per direction."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    p = results.pickup
    G = len(p.success)
    x = np.arange(G)
    colors = np.where(p.success, "tab:green", "tab:red")
    bars = [
        ("max von Mises [kPa]", p.max_von_mises / 1e3),
        ("max deformation [mm]", p.max_deformation * 1e3),
        ("strain energy [mJ]", p.strain_energy * 1e3),
    ]
    if results.reorientation is not None:
        bars.append(("deformation controllability [mm]", results.reorientation.controllability * 1e3))
    tests = [r for r in (results.linear, results.angular) if r is not None]
    fig, axes = plt.subplots(2, max(len(bars), 2), figsize=(4.2 * max(len(bars), 2), 7.5), squeeze=False)
    for ax, (label, values) in zip(axes[0], bars):
        ax.bar(x, np.nan_to_num(values), color=colors, hatch=None)
        for g in np.nonzero(~p.success)[0]:
            ax.patches[g].set_hatch("//")
        ax.set_title(label, fontsize=10)
        ax.set_xticks(x)
        ax.set_xlabel("grasp")
    for ax in axes[0, len(bars) :]:
        ax.axis("off")
    units = {"linear": "m/s$^2$", "angular": "rad/s$^2$"}
    for ax, res in zip(axes[1], tests):
        d = np.arange(len(res.directions))
        for g in range(G):
            ax.plot(d, res.threshold[g], marker="o", ms=3, label=f"grasp {g}: mean {res.instability[g]:.3g}")
        ax.axhline(res.limit, color="k", ls="--", lw=0.8, label="test limit")
        ax.set_ylim(0, 1.05 * res.limit)
        ax.set_xlabel("direction (pairs 2i, 2i+1 opposite; gripper frame)")
        ax.set_ylabel(f"loss-of-grasp acceleration [{units[res.kind]}]")
        ax.set_title(f"{res.kind} instability", fontsize=10)
        ax.legend(fontsize=7)
    for ax in axes[1, len(tests) :]:
        ax.axis("off")
    fig.suptitle(
        f"{title}  (pickup force {p.grasp_force:.3g} N; green: picked up, red: not)".strip(), fontsize=11
    )
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
