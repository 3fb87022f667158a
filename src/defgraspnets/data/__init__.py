"""HDF5 schemas, torch Datasets, LightningDataModules and normalization statistics.

Names are imported lazily (``from defgraspnets.data import GraspShardWriter`` does not import Lightning).
"""

from importlib import import_module

_EXPORTS = {
    "SCHEMA_VERSION": "grasp_schema",
    "GraspShard": "grasp_schema",
    "GraspShardWriter": "grasp_schema",
    "GripperFingers": "grasp_schema",
    "ObjectRecord": "grasp_schema",
    "ShardSchemaError": "grasp_schema",
    "shard_file_name": "grasp_schema",
    "parse_shard_name": "grasp_schema",
    "Normalizer": "normalization",
    "TargetScaling": "normalization",
    "DataError": "dataset",
    "GraspFieldDataset": "dataset",
    "discover_shards": "dataset",
    "sample_index": "dataset",
    "SPLITS": "splits",
    "Split": "splits",
    "make_split": "splits",
    "GraspDataModule": "datamodule",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name):
    if name in _EXPORTS:
        return getattr(import_module(f".{_EXPORTS[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
