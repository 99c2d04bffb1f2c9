"""Samples drawn from the simulator for learning (numpy only): dataset specs, per-sample generation, shards on disk."""

from starenv.datasets.samples import navigation_stars, sample
from starenv.datasets.shards import build_dataset, read_meta, shard_path
from starenv.datasets.spec import DatasetError, DatasetSpec, load_spec

__all__ = ["DatasetError", "DatasetSpec", "build_dataset", "load_spec", "navigation_stars", "read_meta", "sample",
           "shard_path"]
