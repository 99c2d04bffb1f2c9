"""A torch view of a dataset folder written by :func:`starenv.datasets.build_dataset`: shards streamed from disk.

:class:`ShardDataset` is map-style (index = sample index) and keeps the last ``cache_shards`` shards in memory;
:class:`ShardSampler` draws each epoch's order as a shuffled list of shards, each shuffled inside, so reading stays
shard by shard.  The order of epoch ``e`` depends only on (seed, e), so a resumed run replays it.
"""

from __future__ import annotations

import hashlib
import json
from collections import OrderedDict
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset, Sampler


class ShardDataset(Dataset):
    """``main_star`` samples of a dataset folder as (image uint16 tensor (H, W) as int32, label int64)."""

    def __init__(self, folder: str | Path, cache_shards: int = 4):
        self.folder = Path(folder)
        manifest = self.folder / "dataset.json"
        try:
            self.info = json.loads(manifest.read_text(encoding="utf-8"))
        except (OSError, json.JSONDecodeError) as exc:
            raise ValueError(f"{self.folder}: not a dataset folder (no readable dataset.json: {exc})") from exc
        if self.info.get("kind") != "main_star":
            raise ValueError(f"{self.folder}: kind {self.info.get('kind')!r}; this loader reads 'main_star' datasets")
        self.samples = int(self.info["samples"])
        self.shard_size = int(self.info["spec"]["shard_size"])
        self.n_shards = int(self.info["n_shards"])
        missing = [i for i in range(self.n_shards) if not self._path(i).is_file()]
        if missing:
            raise ValueError(f"{self.folder}: shards {missing[:5]} missing; run `starenv dataset` to finish it")
        self.cache_shards = max(1, int(cache_shards))
        self._cache: OrderedDict[int, tuple[torch.Tensor, torch.Tensor]] = OrderedDict()

    @property
    def spec_digest(self) -> str:
        return self.info["spec_digest"]

    def content_digest(self) -> str:
        """SHA-256 of the shards' bytes, in order: the exact samples.  The spec digest names the recipe only; the
        simulator's code decides the pixels, so two builds of one spec by different versions can differ."""
        digest = hashlib.sha256()
        for i in range(self.n_shards):
            digest.update(self._path(i).read_bytes())
        return digest.hexdigest()

    def _path(self, shard: int) -> Path:
        return self.folder / f"shard-{shard:05d}.npz"

    def shard(self, shard: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Images (n, H, W) int32 and labels (n,) int64 of one shard (cached)."""
        if shard in self._cache:
            self._cache.move_to_end(shard)
            return self._cache[shard]
        with np.load(self._path(shard)) as z:
            meta = json.loads(bytes(z["meta"]).decode())
            if meta["spec_digest"] != self.spec_digest:
                raise ValueError(f"{self._path(shard)}: from another dataset (spec {meta['spec_digest'][:12]})")
            item = torch.from_numpy(z["image"].astype(np.int32)), torch.from_numpy(z["label"].astype(np.int64))
        self._cache[shard] = item
        while len(self._cache) > self.cache_shards:
            self._cache.popitem(last=False)
        return item

    def __len__(self) -> int:
        return self.samples

    def __getitem__(self, index: int) -> tuple[torch.Tensor, torch.Tensor]:
        images, labels = self.shard(index // self.shard_size)
        return images[index % self.shard_size], labels[index % self.shard_size]

    def batch(self, indices: list[int]) -> tuple[torch.Tensor, torch.Tensor]:
        """Stacked images and labels of ``indices``."""
        items = [self[i] for i in indices]
        return torch.stack([a for a, _ in items]), torch.stack([b for _, b in items])


class ShardSampler(Sampler[int]):
    """Shard-wise shuffled sample order: epoch ``e``'s order is a pure function of (``seed``, ``e``)."""

    def __init__(self, dataset: ShardDataset, seed: int, shuffle: bool = True):
        self.dataset, self.seed, self.shuffle, self.epoch = dataset, seed, shuffle, 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def order(self) -> list[int]:
        ds = self.dataset
        ranges = [list(range(s * ds.shard_size, min(ds.samples, (s + 1) * ds.shard_size))) for s in range(ds.n_shards)]
        if not self.shuffle:
            return [i for r in ranges for i in r]
        g = torch.Generator().manual_seed(self.seed * 100003 + self.epoch)
        out = []
        for s in torch.randperm(len(ranges), generator=g).tolist():
            r = ranges[s]
            out += [r[k] for k in torch.randperm(len(r), generator=g).tolist()]
        return out

    def __iter__(self):
        return iter(self.order())

    def __len__(self) -> int:
        return len(self.dataset)
