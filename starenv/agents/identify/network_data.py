"""A torch view of a dataset folder written by :func:`starenv.datasets.build_dataset`: shards streamed from disk.

:class:`ShardDataset` is map-style (index = sample index) and keeps the last ``cache_shards`` shards in memory;
every shard read is checked against the SHA-256 the build recorded (``shards.json``) before it is parsed, and its
arrays against the dataset's sizes: a damaged, edited or unfinished shard is a ValueError naming it.
:class:`ShardSampler` draws each epoch's order as a shuffled list of shards, each shuffled inside, so reading stays
shard by shard.  The order of epoch ``e`` depends only on (seed, e), so a resumed run replays it.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections import OrderedDict
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset, Sampler

from starenv.datasets.shards import read_arrays, read_index, shard_path

MAX_DATASET_JSON_BYTES = 1 << 24


class ShardDataset(Dataset):
    """``main_star`` samples of a dataset folder as (image uint16 tensor (H, W) as int32, label int64)."""

    def __init__(self, folder: str | Path, cache_shards: int = 4):
        self.folder = Path(folder)
        manifest = self.folder / "dataset.json"
        try:
            if manifest.stat().st_size > MAX_DATASET_JSON_BYTES:
                raise ValueError(f"larger than {MAX_DATASET_JSON_BYTES} bytes")
            self.info = json.loads(manifest.read_text(encoding="utf-8"))
        except (OSError, ValueError, RecursionError) as exc:
            raise ValueError(f"{self.folder}: not a dataset folder (no readable dataset.json: {exc})") from exc
        if not isinstance(self.info, dict) or self.info.get("kind") != "main_star":
            kind = self.info.get("kind") if isinstance(self.info, dict) else None
            raise ValueError(f"{self.folder}: kind {kind!r}; this loader reads 'main_star' datasets")
        spec = self.info.get("spec")
        sizes = {"samples": self.info.get("samples"), "n_shards": self.info.get("n_shards"),
                 "spec.shard_size": spec.get("shard_size") if isinstance(spec, dict) else None}
        for key, value in sizes.items():
            if type(value) is not int or not 1 <= value <= 2**40:
                raise ValueError(f"{manifest}: {key}: expected a positive integer, got {value!r}")
        self.samples, self.n_shards, self.shard_size = sizes["samples"], sizes["n_shards"], sizes["spec.shard_size"]
        if self.n_shards != math.ceil(self.samples / self.shard_size) or not isinstance(self.spec_digest, str):
            raise ValueError(f"{manifest}: n_shards {self.n_shards} is not samples / shard_size rounded up, or "
                             f"spec_digest is missing")
        self.index = read_index(self.folder, self.spec_digest)
        missing = [i for i in range(self.n_shards) if self._path(i).name not in self.index]
        if missing:
            raise ValueError(f"{self.folder}: shards {missing[:5]} missing or unfinished (no hash recorded in "
                             f"shards.json); run `starenv dataset` to finish it")
        self.cache_shards = max(1, int(cache_shards))
        self._cache: OrderedDict[int, tuple[torch.Tensor, torch.Tensor]] = OrderedDict()

    @property
    def spec_digest(self) -> str:
        return self.info.get("spec_digest")

    def content_digest(self) -> str:
        """SHA-256 of the shards' bytes, in order: the exact samples.  The spec digest names the recipe only; the
        simulator's code decides the pixels, so two builds of one spec by different versions can differ."""
        digest = hashlib.sha256()
        for i in range(self.n_shards):
            digest.update(self._bytes(i))
        return digest.hexdigest()

    def _path(self, shard: int) -> Path:
        return shard_path(self.folder, shard)

    def _bytes(self, shard: int) -> bytes:
        """The bytes of a shard, checked against the hash its build recorded."""
        path = self._path(shard)
        try:
            data = path.read_bytes()
        except OSError as exc:
            raise ValueError(f"{path}: cannot be read ({exc}); run `starenv dataset` to rebuild it") from exc
        if hashlib.sha256(data).hexdigest() != self.index[path.name]:
            raise ValueError(f"{path}: its SHA-256 is not the one shards.json records (damaged or edited); delete "
                             f"it and run `starenv dataset` to rebuild it")
        return data

    def shard(self, shard: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Images (n, H, W) int32 and labels (n,) int64 of one shard (cached)."""
        if shard in self._cache:
            self._cache.move_to_end(shard)
            return self._cache[shard]
        path = self._path(shard)
        count = min(self.shard_size, self.samples - shard * self.shard_size)
        try:
            arrays = read_arrays(self._bytes(shard), ("meta", "image", "label"))
            meta = json.loads(arrays["meta"].tobytes().decode())
        except (ValueError, RecursionError) as exc:  # UnicodeDecodeError and JSONDecodeError are ValueErrors
            raise ValueError(f"{path}: not a readable shard ({exc})") from exc
        image, label = arrays["image"], arrays["label"]
        if not isinstance(meta, dict) or meta.get("spec_digest") != self.spec_digest:
            raise ValueError(f"{path}: from another dataset")
        if (image.ndim != 3 or label.shape != (count,) or len(image) != count or label.dtype.kind not in "iu"
                or (label < 0).any()):
            raise ValueError(f"{path}: expected {count} images (n, H, W) and labels >= 0, got {image.shape} and "
                             f"{label.shape}")
        item = torch.from_numpy(image.astype(np.int32)), torch.from_numpy(label.astype(np.int64))
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
