"""Time ``starenv.sim.sky.load_catalog`` cold, warm from the on-disk cache, and from the in-process cache.

Run with ``python benchmarks/catalog_cache.py``.  A temporary cache folder is used, so the user's cache is untouched.
"""

from __future__ import annotations

import os
import statistics
import tempfile
import time
from pathlib import Path

from starenv.sim import sky

REPEATS = 5
IN_PROCESS_CALLS = 10_000


def seconds(call) -> float:
    start = time.perf_counter()
    call()
    return time.perf_counter() - start


def cold(folder: Path) -> float:
    """No cache at all: read and parse hip2.dat, write the disk cache, propagate and cut."""
    for file in folder.glob("*.npz"):
        file.unlink()
    sky.clear_memory_cache()
    return seconds(sky.load_catalog)


def warm_from_disk() -> float:
    """Fresh process state, table read back from the .npz."""
    sky.clear_memory_cache()
    return seconds(sky.load_catalog)


def in_process() -> float:
    """Mean time of a repeated call answered from memory."""
    sky.load_catalog()
    return seconds(lambda: [sky.load_catalog() for _ in range(IN_PROCESS_CALLS)]) / IN_PROCESS_CALLS


def main() -> None:
    with tempfile.TemporaryDirectory(prefix="starenv-bench-") as folder:
        os.environ["STARENV_CACHE_DIR"] = folder
        sky.load_catalog()  # first use: imports and file-system caches warmed before timing
        timings = {
            "cold parse (no caches)": statistics.median(cold(Path(folder)) for _ in range(REPEATS)),
            "warm start (disk cache)": statistics.median(warm_from_disk() for _ in range(REPEATS)),
            "in-process cached call": in_process(),
        }
        first_env, second_env = environments()
    base = timings["cold parse (no caches)"]
    print(f"load_catalog(mag_limit=6.5, epoch=2026.0): {len(sky.load_catalog())} stars; median of {REPEATS} runs")
    for label, value in timings.items():
        print(f"  {label:26s} {value * 1e3:10.4f} ms   cold / this = {base / value:10.1f}")
    print(f"StarSensorEnv('paper_000'): first construction {first_env * 1e3:.1f} ms (catalog parsed), second "
          f"{second_env * 1e3:.1f} ms (catalog from memory) = {first_env / second_env:.1f} x faster")


def environments() -> tuple[float, float]:
    """Building an environment with no caches, then a second one in the same process."""
    from starenv.env import StarSensorEnv

    for file in Path(os.environ["STARENV_CACHE_DIR"]).glob("*.npz"):
        file.unlink()
    sky.clear_memory_cache()
    return seconds(lambda: StarSensorEnv("paper_000")), seconds(lambda: StarSensorEnv("paper_000"))


if __name__ == "__main__":
    main()
