"""Learned models: DefGraspNets multigraph and MeshGraphNet, the tactile wrench CNN, LightningModules.

Names are imported lazily, so that ``import defgraspnets.models.graph`` does not pull in Lightning.
"""

from importlib import import_module

_EXPORTS = {
    "GraspGraph": "graph",
    "ObjectTemplate": "graph",
    "FingerTemplate": "graph",
    "MultigraphFeaturizer": "graph",
    "build_grasp_batch": "graph",
    "build_grasp_graph": "graph",
    "contact_pairs": "graph",
    "DefGraspNet": "meshgraphnet",
    "EncodeProcessDecode": "meshgraphnet",
    "DefGraspNetsModule": "defgraspnets_module",
    "DefGraspNetsPredictor": "predictor",
    "FingerGeometry": "predictor",
    "GraspFieldPrediction": "predictor",
    "finger_contact_poses": "predictor",
    "CheckpointError": "checkpoints",
    "read_checkpoint": "checkpoints",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name):
    if name in _EXPORTS:
        return getattr(import_module(f".{_EXPORTS[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
