"""Evaluation: Kendall tau, errors in SI units, Chamfer distances, reports and plots (thesis §7.6)."""

from .chamfer import chamfer_distance, nearest_training_object, surface_samples
from .metrics import FieldMetrics, grouped_kendall_tau, kendall_tau, kendall_tau_interval

__all__ = [
    "FieldMetrics",
    "chamfer_distance",
    "grouped_kendall_tau",
    "kendall_tau",
    "kendall_tau_interval",
    "nearest_training_object",
    "surface_samples",
]
