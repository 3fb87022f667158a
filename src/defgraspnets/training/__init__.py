"""Training utilities shared by the Lightning runs (callbacks)."""

from defgraspnets.training.throughput import GraphThroughput

__all__ = ["GraphThroughput"]
