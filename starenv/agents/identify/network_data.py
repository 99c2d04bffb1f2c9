"""A torch view of a dataset folder written by :func:`starenv.datasets.build_dataset`: shards streamed from disk.

:class:`ShardDataset` is map-style (index = sample index) and keeps the last ``cache_shards`` shards in memory;
every shard read is checked against the SHA-256 the build recorded (``shards.json``) before it is parsed, and its
arrays against the dataset's sizes: a damaged, edited or unfinished shard is a ValueError naming it.
:class:`ShardSampler` draws each epoch's order as a shuffled list of shards, each shuffled inside, so reading stays
shard by shard.  The order of epoch ``e`` depends only on (seed, e), so a resumed run replays it.
:class:`InMemory` holds every sample in one tensor (host or GPU memory), read once, for training that must not wait
on the disk; :func:`fits_in_memory` says whether a dataset does.  Either source gives the same batches.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from collections import OrderedDict, deque
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset, Sampler

from starenv.datasets.shards import read_arrays, read_index, shard_path

MAX_DATASET_JSON_BYTES = 1 << 24


class ShardDataset(Dataset):
    """``main_star`` samples of a dataset folder as (network input float32 (S, S), label int64); S is the spec's
    ``input_size`` (:func:`starenv.datasets.preprocess.network_input` of the frame)."""

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
        self._content_digest: str | None = None

    def __getstate__(self) -> dict:
        """Without the cached shards: a ``DataLoader`` worker reads its own."""
        return {**self.__dict__, "_cache": OrderedDict()}

    @property
    def spec_digest(self) -> str:
        return self.info.get("spec_digest")

    def content_digest(self) -> str:
        """SHA-256 of the shards' bytes, in order: the exact samples.  The spec digest names the recipe only; the
        simulator's code decides the pixels, so two builds of one spec by different versions can differ."""
        if self._content_digest is None:
            digest = hashlib.sha256()
            for i in range(self.n_shards):
                digest.update(self._bytes(i))
            self._content_digest = digest.hexdigest()
        return self._content_digest

    def _path(self, shard: int) -> Path:
        return shard_path(self.folder, shard)

    def _bytes(self, shard: int) -> bytearray:
        """The bytes of a shard, checked against the hash its build recorded (a bytearray: the arrays parsed from it
        are writable views)."""
        path = self._path(shard)
        try:
            with open(path, "rb") as f:
                size = os.fstat(f.fileno()).st_size
                data = bytearray(size)
                if f.readinto(data) != size:
                    raise OSError("the file changed size while it was read")
        except OSError as exc:
            raise ValueError(f"{path}: cannot be read ({exc}); run `starenv dataset` to rebuild it") from exc
        if hashlib.sha256(data).hexdigest() != self.index[path.name]:
            raise ValueError(f"{path}: its SHA-256 is not the one shards.json records (damaged or edited); delete "
                             f"it and run `starenv dataset` to rebuild it")
        return data

    def shard(self, shard: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Images (n, S, S) float32 and labels (n,) int64 of one shard (cached)."""
        if shard in self._cache:
            self._cache.move_to_end(shard)
            return self._cache[shard]
        item = self._parse(shard, self._bytes(shard))
        self._cache[shard] = item
        while len(self._cache) > self.cache_shards:
            self._cache.popitem(last=False)
        return item

    def _parse(self, shard: int, data: bytearray) -> tuple[torch.Tensor, torch.Tensor]:
        """Images and labels of shard ``shard`` from its checked bytes (the images a view into ``data``)."""
        path = self._path(shard)
        count = min(self.shard_size, self.samples - shard * self.shard_size)
        try:
            arrays = read_arrays(data, ("meta", "image", "label"))
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
        if image.dtype != np.float32:
            raise ValueError(f"{path}: {image.dtype} images, not the network inputs (float32) this version stores: a "
                             f"dataset of raw frames from an older starenv; build it again with `starenv dataset`")
        return torch.from_numpy(image), torch.from_numpy(label.astype(np.int64))

    def image_shape(self) -> tuple[int, int]:
        """(H, W) of the stored images (those of shard 0)."""
        return tuple(self.shard(0)[0].shape[1:])

    def __len__(self) -> int:
        return self.samples

    def __getitem__(self, index: int) -> tuple[torch.Tensor, torch.Tensor]:
        images, labels = self.shard(index // self.shard_size)
        return images[index % self.shard_size], labels[index % self.shard_size]

    def batch(self, indices: list[int]) -> tuple[torch.Tensor, torch.Tensor]:
        """Stacked images and labels of ``indices``: one gather per run of indices in the same shard."""
        images, labels = [], []
        start = 0
        while start < len(indices):
            shard = indices[start] // self.shard_size
            stop = start + 1
            while stop < len(indices) and indices[stop] // self.shard_size == shard:
                stop += 1
            local = torch.tensor(indices[start:stop], dtype=torch.int64) - shard * self.shard_size
            shard_images, shard_labels = self.shard(shard)
            images.append(shard_images[local])
            labels.append(shard_labels[local])
            start = stop
        if len(images) == 1:
            return images[0], labels[0]
        return torch.cat(images), torch.cat(labels)


class InMemory:
    """Every sample of a :class:`ShardDataset` in one tensor on ``device``: images (n, S, S) float32 and labels (n,)
    int64, each shard read and checked once, ``threads`` shards at a time (its content digest computed in passing,
    so the dataset does not read its shards again for it)."""

    def __init__(self, dataset: ShardDataset, device: str | torch.device = "cpu", threads: int | None = None):
        self.dataset = dataset
        height, width = dataset.image_shape()
        self.images = torch.empty((dataset.samples, height, width), dtype=torch.float32, device=device)
        self.labels = torch.empty(dataset.samples, dtype=torch.int64, device=device)
        digest = hashlib.sha256()
        threads = threads or min(8, os.cpu_count() or 1)
        with ThreadPoolExecutor(threads) as pool:  # file reads and SHA-256 release the GIL
            ahead: deque = deque()
            for shard in range(dataset.n_shards):
                while len(ahead) < 2 * threads and shard + len(ahead) < dataset.n_shards:
                    ahead.append(pool.submit(dataset._bytes, shard + len(ahead)))
                self._place(dataset, shard, ahead.popleft().result(), digest, (height, width))
        dataset._content_digest = digest.hexdigest()

    def _place(self, dataset: ShardDataset, shard: int, data: bytearray, digest, shape: tuple[int, int]) -> None:
        """Parse shard ``shard``'s checked bytes into its rows; ``digest`` takes the bytes in shard order."""
        height, width = shape
        digest.update(data)
        images, labels = dataset._parse(shard, data)
        if tuple(images.shape[1:]) != (height, width):
            raise ValueError(f"{dataset._path(shard)}: {tuple(images.shape[1:])} images, shard 0 has "
                             f"{(height, width)}")
        first = shard * dataset.shard_size
        self.images[first:first + len(images)].copy_(images)
        self.labels[first:first + len(labels)].copy_(labels)

    def __len__(self) -> int:
        return len(self.labels)

    def batch(self, indices: list[int]) -> tuple[torch.Tensor, torch.Tensor]:
        """Images and labels of ``indices``, on this holder's device."""
        index = torch.tensor(indices, dtype=torch.int64).to(self.images.device)
        return self.images[index], self.labels[index]


def fits_in_memory(dataset: ShardDataset, device: str, share: float = 0.5) -> bool:
    """Whether ``dataset``'s images take at most ``share`` of the memory ``device`` has free now (GPU memory for
    ``cuda``, the host's available memory otherwise)."""
    height, width = dataset.image_shape()
    need = dataset.samples * (height * width * 4 + 8)
    if str(device).startswith("cuda"):  # free on the device, and what torch's allocator holds unused
        free = torch.cuda.mem_get_info()[0] + torch.cuda.memory_reserved() - torch.cuda.memory_allocated()
    else:
        free = _host_available_bytes()
    return need <= share * free


def _host_available_bytes() -> int:
    """The host memory available to a new allocation (Linux ``MemAvailable``: free memory and reclaimable cache;
    elsewhere the free pages)."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_AVPHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return 0


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
