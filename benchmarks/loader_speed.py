"""Training-data loader speed against the network's: samples/s of each way ``starenv train`` reads a ``main_star``
dataset, beside the paper-size network's forward + backward samples/s on the same machine, in the same run.

    python benchmarks/loader_speed.py [--data DIR] [--samples 400] [--input 256] [--batch 160]
                                      [--workers 0,2,8] [--passes 4] [--device cpu] [--steps 2] [--probe-batch 16]

Without ``--data``, ``datasets/paper002_sky.toml`` is built at ``--input`` px with ``--samples`` samples (shards of
100) into a temporary folder.  Each loader path runs ``--passes`` epochs of the training order as one (seed 0,
``--rot90`` rolls, ``--batch`` samples a batch, no model; the workers' start spread over them): the shards read in
the training process and by each ``--workers`` count of ``DataLoader`` processes (after one untimed pass, so the
files are in the page cache as a set smaller than memory is), and the whole set held in memory (its one-off read
timed apart).  Then the parts of a shard read, per sample: file read, SHA-256 check, parsing the arrays, gathering a
batch, the rolls.  Last, the paper-size network's forward + backward samples/s at that input on ``--device``
(random inputs, batches of ``--probe-batch``, ``--steps`` Adam steps after as many warm-ups).
"""

from __future__ import annotations

import argparse
import hashlib
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import torch  # noqa: E402
from paper002_gpu import build, probe, spec_with  # noqa: E402

from starenv.agents.identify.network_data import InMemory, ShardDataset, ShardSampler  # noqa: E402
from starenv.agents.identify.network_train import batches, rot90  # noqa: E402
from starenv.datasets import load_spec, navigation_stars  # noqa: E402
from starenv.datasets.shards import read_arrays  # noqa: E402


def epoch_rate(source, order: list[int], batch: int, workers: int) -> float:
    """Samples/s of one epoch of ``order`` from ``source`` (rolls included)."""
    t0 = time.perf_counter()
    n = sum(len(x) for x, _ in batches(source, order, batch, workers=workers, turn=(0, 0)))
    return n / (time.perf_counter() - t0)


def parts(dataset: ShardDataset, order: list[int], batch: int) -> dict[str, float]:
    """Milliseconds per sample of each part of reading the shards (every shard once; the first batch's gather and
    rolls)."""
    times = dict.fromkeys(("file read", "SHA-256", "parse", "batch gather", "rolls"), 0.0)
    for shard in range(dataset.n_shards):
        path = dataset._path(shard)
        t0 = time.perf_counter()
        data = bytearray(path.read_bytes())
        t1 = time.perf_counter()
        hashlib.sha256(data).hexdigest()
        t2 = time.perf_counter()
        read_arrays(data, ("meta", "image", "label"))
        times["file read"] += t1 - t0
        times["SHA-256"] += t2 - t1
        times["parse"] += time.perf_counter() - t2
    out = {k: 1e3 * v / dataset.samples for k, v in times.items()}
    t0 = time.perf_counter()
    x, _ = dataset.batch(order[:batch])
    t1 = time.perf_counter()
    rot90(x, 0, 0, 0)
    out["batch gather"] = 1e3 * (t1 - t0) / batch
    out["rolls"] = 1e3 * (time.perf_counter() - t1) / batch
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", default=None)
    p.add_argument("--samples", type=int, default=400)
    p.add_argument("--input", type=int, default=256)
    p.add_argument("--batch", type=int, default=160)
    p.add_argument("--workers", default="0,2,8")
    p.add_argument("--passes", type=int, default=4)
    p.add_argument("--device", default="cpu")
    p.add_argument("--steps", type=int, default=2)
    p.add_argument("--probe-batch", type=int, default=16)
    args = p.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(args.data) if args.data else Path(tmp) / "data"
        if args.data is None:
            seconds = build(spec_with(args.samples, 0, args.input, "loader_speed"), folder, 1)
            print(f"built {args.samples} samples at {args.input} px in {seconds:.1f} s on 1 process")
        dataset = ShardDataset(folder)
        order = ShardSampler(dataset, 0).order() * args.passes
        height, width = dataset.image_shape()
        print(f"{folder}: {dataset.samples} samples of {height} x {width} float32 in {dataset.n_shards} shards, "
              f"batch {args.batch}, torch threads {torch.get_num_threads()}")
        epoch_rate(ShardDataset(folder), order, args.batch, 0)  # the page cache
        for workers in (int(w) for w in args.workers.split(",")):
            rate = epoch_rate(ShardDataset(folder), order, args.batch, workers)
            print(f"shards, {workers} workers: {rate:8.1f} samples/s")
        t0 = time.perf_counter()
        held = InMemory(ShardDataset(folder))
        load_s = time.perf_counter() - t0
        rate = epoch_rate(held, order, args.batch, 0)
        print(f"in memory:          {rate:8.1f} samples/s (read once in {load_s:.2f} s: "
              f"{dataset.samples / load_s:.0f} samples/s)")
        split = parts(dataset, order, args.batch)
        print("parts, ms per sample: " + ", ".join(f"{k} {v:.3f}" for k, v in split.items()))
        n_classes = len(navigation_stars(load_spec(dataset.info["spec"]))[0])
    rate = probe(n_classes, height, args.device, args.probe_batch, steps=args.steps)
    print(f"network forward + backward on {args.device}: {rate:8.1f} samples/s (paper-size, {height} px input, "
          f"batch {args.probe_batch}, {n_classes} classes, torch threads {torch.get_num_threads()})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
