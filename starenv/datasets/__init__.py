"""Samples drawn from the simulator for learning (numpy only, no torch): each reproducible alone from its scenario
and seed.  ``spec``/``samples``/``shards``: dataset specs (TOML), per-sample generation from (spec, seed, index) and
atomic shards on disk (``starenv dataset``; kinds ``main_star``, ``centroids``, ``position_pairs``,
``smear_pairs``); ``smear``: smeared frames with their sharp, noise-free reference (deblurring); ``pairs``:
measured / reference position pairs (distortion); ``star_fields``: centroid sets with truth ids without
rendering."""

from starenv.datasets.samples import navigation_stars, sample
from starenv.datasets.shards import build_dataset, read_meta, shard_path
from starenv.datasets.spec import DatasetError, DatasetSpec, load_spec

__all__ = ["DatasetError", "DatasetSpec", "build_dataset", "load_spec", "navigation_stars", "read_meta", "sample",
           "shard_path"]
