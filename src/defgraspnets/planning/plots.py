"""Figures of a planning run: best and worst grasps on the object (thesis Fig. 7.5 analogue) and the box
plot of simulated Q per grasp group (Fig. 7.4 analogue)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

__all__ = ["plot_grasps", "plot_verification"]


def plot_grasps(
    path: str | Path,
    points: np.ndarray,
    surface_faces: np.ndarray,
    stress: np.ndarray,
    finger_vertices: np.ndarray,
    finger_faces: np.ndarray,
    titles: Sequence[str],
    suptitle: str = "",
    columns: int = 3,
) -> Path:
    """PNG of K grasps on the object at rest, coloured by each grasp's (predicted) von Mises stress with one
    shared colour scale, and the finger pads at first contact.

    Args:
        points: (N, 3) object vertices [m]. surface_faces: (F, 3). stress: (K, N) [Pa].
        finger_vertices: (K, 2, V, 3) pads [m]. finger_faces: (T, 3). titles: K panel titles.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from defgraspnets.grasp.visualize import draw_grasp

    k = len(titles)
    rows = max(1, -(-k // columns))
    fig = plt.figure(figsize=(4.2 * columns, 4.0 * rows + 0.6))
    finite = stress[np.isfinite(stress)]
    norm = matplotlib.colors.Normalize(float(finite.min()) / 1e3, float(finite.max()) / 1e3 or 1.0)
    mappable = None
    for i in range(k):
        ax = fig.add_subplot(rows, columns, i + 1, projection="3d")
        mappable = draw_grasp(
            ax,
            points * 1e3,
            surface_faces,
            stress[i] / 1e3,
            finger_vertices[i] * 1e3,
            finger_faces,
            norm=norm,
        )
        ax.set_title(titles[i], fontsize=9)
    if mappable is not None:
        fig.colorbar(mappable, ax=fig.axes, shrink=0.5, label="predicted von Mises stress [kPa]")
    fig.suptitle(suptitle)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def plot_verification(
    path: str | Path, groups: Mapping[str, np.ndarray], ylabel: str, title: str = ""
) -> Path:
    """Box plot of the simulated Q of each group of grasps (NaN, i.e. failed simulations, left out), with
    the individual grasps as dots."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(groups)
    data = [np.asarray(groups[n], dtype=np.float64) for n in names]
    data = [d[np.isfinite(d)] for d in data]
    fig, ax = plt.subplots(figsize=(1.6 * len(names) + 2, 4.5))
    ax.boxplot(data, showfliers=False)
    ax.set_xticks(range(1, len(names) + 1), names)
    rng = np.random.default_rng(0)
    for i, d in enumerate(data, start=1):
        ax.scatter(i + rng.uniform(-0.12, 0.12, len(d)), d, s=10, alpha=0.6, color="k")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
