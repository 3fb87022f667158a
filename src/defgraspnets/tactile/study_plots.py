"""Figures of the indentation studies (thesis Figs 2.5, 2.7-2.11), written as PNG files (Agg backend).

Each function takes the dataclasses of :mod:`defgraspnets.tactile.indentation_studies` and a path; lengths
are plotted in mm, areas in cm^2, forces in N.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from defgraspnets.tactile.contact_regions import SurfaceType, region_boundary

__all__ = [
    "plot_area_sweeps",
    "plot_contact_regions",
    "plot_force_curves",
    "plot_force_matching",
    "plot_slope_vs_pv",
]

_TYPE_COLORS = {
    SurfaceType.UNDEFORMED: "0.6",
    SurfaceType.DEFORMED_FREE: "tab:blue",
    SurfaceType.CONTACT: "gold",
}
_OPEN_COLOR = "black"


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120, bbox_inches="tight")
    _pyplot().close(fig)
    return path


def plot_contact_regions(results, path, radius: float = 0.03, stride: int = 3) -> Path:
    """Fig. 2.5: element centres (every ``stride``-th pixel) projected on the xy-plane, coloured Type A
    (grey), B (blue), C (yellow); the true (FEM) contact region's boundary in red; within ``radius`` [m]
    of the axis."""
    plt = _pyplot()
    fig, axes = plt.subplots(1, len(results), figsize=(4.2 * len(results), 4.2), squeeze=False)
    for ax, r in zip(axes[0], results):
        p = r.points[::stride, ::stride]
        lab = r.labels[::stride, ::stride]
        near = np.isfinite(p[..., 0]) & (np.hypot(p[..., 0], p[..., 1]) <= radius)
        for t, color in _TYPE_COLORS.items():
            m = near & (lab == t)
            ax.scatter(
                1e3 * p[m, 0], 1e3 * p[m, 1], s=3, c=color, label=f"Type {'ABC'[int(t)]}", linewidths=0
            )
        edge = r.points[region_boundary(r.true_mask)]
        ax.scatter(1e3 * edge[:, 0], 1e3 * edge[:, 1], s=4, c="red", label="true contact boundary")
        ax.set_aspect("equal")
        ax.set_xlim(-1e3 * radius, 1e3 * radius)
        ax.set_ylim(-1e3 * radius, 1e3 * radius)
        ax.set_xlabel("x [mm]")
        ax.set_ylabel("y [mm]")
        c = r.comparison
        ax.set_title(
            f"{r.indenter}: IoU {c.iou:.2f}, max boundary err {1e3 * c.max_boundary_distance:.1f} mm",
            fontsize=9,
        )
    axes[0][0].legend(fontsize=7, markerscale=3, loc="lower left")
    return _save(fig, path)


def _by_diameter(items):
    out = {}
    for it in items:
        out.setdefault(it.sphere_diameter, []).append(it)
    return dict(sorted(out.items()))


def _state_colors(items):
    closed = sorted({it.pv for it in items if it.closed})
    cmap = _pyplot().get_cmap("viridis")
    return {pv: cmap(i / max(1, len(closed) - 1)) for i, pv in enumerate(closed)}


def _state_style(sweep, colors) -> tuple:
    """(colour, legend label) of one sweep's gas state: closed states by PV, the open capsule in black."""
    if not sweep.closed:
        return _OPEN_COLOR, f"PV {sweep.pv:.1f} N m (open)"
    return colors.get(sweep.pv, _OPEN_COLOR), f"PV {sweep.pv:.1f} N m"


def plot_area_sweeps(sweeps, path, quantity: str = "contact_area") -> Path:
    """Fig. 2.7 (``contact_area``: Type C, with the true FEM contact area dashed and half the sphere's
    surface dotted) or Fig. 2.8 (``deformed_area``: Type B + C; open capsule in black) vs indentation."""
    if quantity not in ("contact_area", "deformed_area"):
        raise ValueError(f"quantity must be 'contact_area' or 'deformed_area', got {quantity!r}")
    plt = _pyplot()
    groups = _by_diameter(sweeps)
    colors = _state_colors(sweeps)
    fig, axes = plt.subplots(1, len(groups), figsize=(4.5 * len(groups), 3.8), squeeze=False)
    for ax, (diameter, items) in zip(axes[0], groups.items()):
        for s in items:
            color, label = _state_style(s, colors)
            ax.plot(1e3 * s.indentation, 1e4 * getattr(s, quantity), "o-", color=color, label=label, ms=3)
            if quantity == "contact_area":
                ax.plot(1e3 * s.indentation, 1e4 * s.true_contact_area, "--", color=color, lw=0.8)
        if quantity == "contact_area":
            ax.axhline(
                1e4 * 2 * np.pi * (diameter / 2) ** 2, color="k", ls=":", lw=1, label="half sphere area"
            )
        ax.set_title(f"{1e3 * diameter:g} mm sphere", fontsize=9)
        ax.set_xlabel("indentation depth [mm]")
        ax.set_ylabel(("contact" if quantity == "contact_area" else "deformed") + " area [cm$^2$]")
    axes[0][0].legend(fontsize=7)
    return _save(fig, path)


def plot_force_curves(sweeps, path) -> Path:
    """Fig. 2.9: axial force vs camera-measured indentation per sphere and gas state, with the linear fits."""
    plt = _pyplot()
    groups = _by_diameter(sweeps)
    colors = _state_colors(sweeps)
    fig, axes = plt.subplots(1, len(groups), figsize=(4.5 * len(groups), 3.8), squeeze=False)
    for ax, (diameter, items) in zip(axes[0], groups.items()):
        for s in items:
            color, label = _state_style(s, colors)
            ax.plot(1e3 * s.indentation, s.force, "o", color=color, ms=3, label=label)
            if s.linear is not None:
                d = np.linspace(0.0, np.nanmax(s.indentation), 20)
                ax.plot(1e3 * d, s.linear["slope"] * d + s.linear["intercept"], "-", color=color, lw=0.8)
        ax.set_title(f"{1e3 * diameter:g} mm sphere", fontsize=9)
        ax.set_xlabel("indentation depth [mm]")
        ax.set_ylabel("axial force $F_z$ [N]")
    axes[0][0].legend(fontsize=7)
    return _save(fig, path)


def plot_slope_vs_pv(sweeps, models, path) -> Path:
    """Fig. 2.10: fitted force-indentation slope vs PV, the polynomial per sphere (open state in black)."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(5.5, 4.0))
    cmap = plt.get_cmap("tab10")
    for i, (diameter, items) in enumerate(_by_diameter(sweeps).items()):
        closed = [s for s in items if s.closed and s.linear is not None]
        ax.plot([s.pv for s in closed], [s.linear["slope"] for s in closed], "o", color=cmap(i),
                label=f"{1e3 * diameter:g} mm sphere")  # fmt: skip
        for s in items:
            if not s.closed and s.linear is not None:
                ax.plot(s.pv, s.linear["slope"], "s", color=_OPEN_COLOR, ms=5)
        if diameter in models:
            lo, hi = models[diameter].pv_range
            pv = np.linspace(lo, hi, 100)
            ax.plot(pv, models[diameter].slope_fit(pv), "-", color=cmap(i), lw=1)
    ax.set_xlabel("pre-contact PV [N m]")
    ax.set_ylabel("slope $dF/d\\delta$ [N/m]")
    ax.legend(fontsize=7)
    return _save(fig, path)


def plot_force_matching(results, path) -> Path:
    """Fig. 2.11: actual FEM force (mean and standard error over trials) vs desired force per gas state."""
    plt = _pyplot()
    fig, axes = plt.subplots(1, len(results), figsize=(4.0 * len(results), 3.6), squeeze=False)
    for ax, r in zip(axes[0], results):
        forces = np.unique(r.desired_force)
        mean = np.array([np.nanmean(r.actual_force[r.desired_force == f]) for f in forces])
        n = np.array([np.isfinite(r.actual_force[r.desired_force == f]).sum() for f in forces])
        sd = np.array(
            [
                np.nanstd(r.actual_force[r.desired_force == f], ddof=1) if k > 1 else 0.0
                for f, k in zip(forces, n)
            ]
        )
        ax.errorbar(
            forces, mean, yerr=sd / np.sqrt(np.maximum(n, 1)), fmt="o", capsize=3, label="$F_{actual}$"
        )
        ax.plot(forces, forces, "k--", lw=0.8, label="$F_{desired}$")
        ax.set_title(f"PV {r.pv:.1f} N m: error {r.mean_error:+.3f} N", fontsize=9)
        ax.set_xlabel("desired force [N]")
        ax.set_ylabel("actual FEM force [N]")
    axes[0][0].legend(fontsize=7)
    return _save(fig, path)
