"""Evaluation: Kendall tau, errors in SI units, Chamfer distances, generalization splits, reports and plots."""
