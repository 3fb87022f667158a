"""Reports of DefGraspNets evaluations: Markdown and JSON tables (thesis §7.6, Table 7.1) and field plots
(Fig. 7.3 analogue: predicted vs ground-truth fields on the object's vertices, 3-D scatter)."""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

__all__ = ["LEVEL_COLUMNS", "OBJECT_COLUMNS", "markdown_table", "plot_fields", "write_json"]

# (key, header, format); a tuple of keys fills one cell with several values (a confidence interval)
LEVEL_COLUMNS = (
    ("split", "Generalization level", "{}"),
    ("displacement_target", "Displacement", "{}"),
    ("samples", "Test samples", "{:d}"),
    ("tau_s", "τ_s ↑", "{:.2f}"),
    ("tau_d", "τ_d ↑", "{:.2f}"),
    (("tau_s_ci_low", "tau_s_ci_high"), "τ_s 95 % CI", "[{:.2f}, {:.2f}]"),
    (("tau_d_ci_low", "tau_d_ci_high"), "τ_d 95 % CI", "[{:.2f}, {:.2f}]"),
    ("mae_stress_kpa", "Stress MAE [kPa] ↓", "{:.3g}"),
    ("mae_deformation_mm", "Deformation MAE [mm] ↓", "{:.3g}"),
    # within a tau group: the error that can reorder grasps, against the grasps' spread of the true value
    (
        ("relative_error_mean_stress_kpa", "spread_mean_stress_kpa"),
        "Mean stress: ranking error / spread [kPa]",
        "{:.3g} / {:.3g}",
    ),
)
OBJECT_COLUMNS = (
    ("object", "Test object", "{}"),
    ("nearest_train_object", "Nearest train object", "{}"),
    ("chamfer_mm", "d_C [mm] ↓", "{:.2f}"),
    ("mae_deformation_mm", "Deformation MAE [mm] ↓", "{:.3g}"),
    ("tau_d", "τ_d ↑", "{:.2f}"),
    ("mae_stress_kpa", "Stress MAE [kPa] ↓", "{:.3g}"),
    ("tau_s", "τ_s ↑", "{:.2f}"),
)


def _fmt(value, fmt: str) -> str:
    values = list(value) if isinstance(value, tuple) else [value]
    if any(v is None for v in values):
        return "–"
    if any(isinstance(v, float) and not math.isfinite(v) for v in values):
        return "n/a"
    try:
        return fmt.format(*values)
    except (ValueError, TypeError):
        return str(value)


def markdown_table(rows: Sequence[dict], columns=LEVEL_COLUMNS) -> str:
    """A GitHub-Markdown table of ``rows`` (dicts) with ``columns`` = ((key, header, format), ...)."""
    head = "| " + " | ".join(h for _, h, _ in columns) + " |"
    rule = "|" + "|".join("---" for _ in columns) + "|"

    def cell(row: dict, key, fmt: str) -> str:
        return _fmt(tuple(row.get(k) for k in key) if isinstance(key, tuple) else row.get(key), fmt)

    body = ["| " + " | ".join(cell(r, k, f) for k, _, f in columns) + " |" for r in rows]
    return "\n".join([head, rule, *body])


def write_json(path: str | Path, obj) -> None:
    """JSON with NaN written as null."""

    def clean(x):
        if isinstance(x, dict):
            return {str(k): clean(v) for k, v in x.items()}
        if isinstance(x, (list, tuple)):
            return [clean(v) for v in x]
        if isinstance(x, (np.floating, float)):
            return float(x) if math.isfinite(float(x)) else None
        if isinstance(x, np.integer):
            return int(x)
        return x

    Path(path).write_text(json.dumps(clean(obj), indent=2) + "\n")


def plot_fields(
    points: np.ndarray,
    pred: np.ndarray,
    true: np.ndarray,
    path: str | Path,
    title: str = "",
    label: str = "von Mises stress [kPa]",
    displacement: np.ndarray | None = None,
) -> None:
    """Side-by-side 3-D scatter of a predicted and a ground-truth scalar field on object vertices.

    Args:
        points: (N, 3) rest positions [m] (plotted in mm, deformed by ``displacement`` (N, 3) [m] if given).
        pred, true: (N,) field values in the unit of ``label``.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x = np.asarray(points) + (0 if displacement is None else np.asarray(displacement))
    x = x * 1e3
    vmin, vmax = float(min(pred.min(), true.min())), float(max(pred.max(), true.max()))
    fig = plt.figure(figsize=(10, 4.6))
    for i, (name, val) in enumerate((("DefGraspNets", pred), ("ground truth (FEM)", true))):
        ax = fig.add_subplot(1, 2, i + 1, projection="3d")
        sc = ax.scatter(x[:, 0], x[:, 1], x[:, 2], c=val, cmap="viridis", vmin=vmin, vmax=vmax, s=6)
        ax.set_title(name)
        ax.set_xlabel("x [mm]")
        ax.set_ylabel("y [mm]")
        ax.set_zlabel("z [mm]")
        span = (x.max(0) - x.min(0)).max() / 2
        mid = (x.max(0) + x.min(0)) / 2
        ax.set_xlim(mid[0] - span, mid[0] + span)
        ax.set_ylim(mid[1] - span, mid[1] + span)
        ax.set_zlim(mid[2] - span, mid[2] + span)
    fig.colorbar(sc, ax=fig.axes, shrink=0.7, pad=0.08, label=label)
    fig.suptitle(title)
    fig.savefig(path, dpi=110)
    plt.close(fig)
