"""Does a built dataset regenerate bit for bit?  Shards drawn at random (``--draw`` of them, from ``--seed``) or named
(``--shards``) are made again from the spec (:func:`starenv.datasets.shards.shard_arrays`) and compared with the
stored ones array by array: names, dtypes and every value.

    python benchmarks/dataset_regenerates.py --spec datasets/paper002_sky_small.toml --data data/sky_small \\
        [--draw 3 --seed 7 | --shards 0 177 299]

Prints one line per shard (identical or not, its seconds) and exits 1 when any differs.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from starenv.datasets import load_spec  # noqa: E402
from starenv.datasets.shards import shard_arrays, shard_path  # noqa: E402


def same_shard(spec, data: Path, shard: int) -> bool:
    """Whether shard ``shard`` of ``spec`` made again holds the arrays stored in ``data``."""
    new = shard_arrays(spec, shard)
    with np.load(shard_path(data, shard)) as old:
        return set(old.files) == set(new) and all(
            old[name].dtype == new[name].dtype and np.array_equal(old[name], new[name]) for name in new)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--spec", required=True)
    p.add_argument("--data", required=True, type=Path)
    p.add_argument("--shards", type=int, nargs="*", default=None)
    p.add_argument("--draw", type=int, default=3)
    p.add_argument("--seed", type=int, default=7)
    args = p.parse_args(argv)
    spec = load_spec(args.spec)
    n_shards = -(-spec.samples // spec.shard_size)
    shards = args.shards if args.shards else sorted(
        np.random.default_rng(args.seed).choice(n_shards, size=min(args.draw, n_shards), replace=False).tolist())
    differ = 0
    for shard in shards:
        t0 = time.perf_counter()
        ok = same_shard(spec, args.data, shard)
        differ += not ok
        print(f"{spec.name} shard {shard}: {'identical' if ok else 'DIFFERENT'} ({time.perf_counter() - t0:.0f} s)",
              flush=True)
    print(f"{len(shards) - differ}/{len(shards)} shards identical")
    return 1 if differ else 0


if __name__ == "__main__":
    sys.exit(main())
