"""Independent tasks run in any order: in this process, in local worker processes (spawned), or on a Ray cluster.

The benchmark runner and the dataset builder share these executors.  An executor is a generator function
``submit_all(tasks)`` that takes tuples of arguments for ``fn`` and yields ``(key(args), fn(*args))`` as each task
finishes; tasks not yet started are dropped when the consumer stops early (an error or an interrupt).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ProcessPoolExecutor, as_completed
from multiprocessing import get_context
from pathlib import Path
from typing import Any

Executor = Callable[[Iterable[tuple]], Iterator[tuple[Any, Any]]]
POOL_WORKER_ENV = "STARENV_POOL_WORKER"  # set ("1") in the environment of the Ray workers that run the tasks


def usable_cores() -> int:
    """The cores this process may run on: its CPU affinity where the platform tells it, else the CPU count."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def local_executor(fn: Callable, key: Callable[[tuple], Any], jobs: int) -> Executor:
    """``fn`` in this process (``jobs`` <= 1) or in ``jobs`` spawned worker processes."""

    def submit_all(tasks):
        if jobs <= 1:
            for args in tasks:
                yield key(args), fn(*args)
            return
        pool = ProcessPoolExecutor(max_workers=jobs, mp_context=get_context("spawn"))
        try:
            futures = {pool.submit(fn, *args): key(args) for args in tasks}
            for fut in as_completed(futures):
                yield futures[fut], fut.result()
        finally:  # on an error or an interrupt, tasks not yet started are dropped, not run to the end
            pool.shutdown(wait=True, cancel_futures=True)

    return submit_all


def ray_executor(fn: Callable, key: Callable[[tuple], Any], address: str | None, options: dict | None = None,
                 error: type[Exception] = ValueError) -> Executor:
    """``fn`` as Ray tasks on the cluster at ``address`` (None: a local Ray instance started here), with this
    package on the workers' path, the catalogue cache folder passed on and ``POOL_WORKER_ENV`` set (a worker's
    sensors then draw their noise on its own thread); ``error`` is raised when ray is missing."""
    try:
        import ray
    except ImportError as exc:
        raise error("--ray: the ray package is not installed (install the 'ray' extra: pip install 'starenv[ray]')"
                    ) from exc

    def submit_all(tasks):
        if not ray.is_initialized():
            root = str(Path(__file__).resolve().parent.parent)
            env = {"PYTHONPATH": os.pathsep.join([root, *filter(None, [os.environ.get("PYTHONPATH")])]),
                   POOL_WORKER_ENV: "1"}
            if "STARENV_CACHE_DIR" in os.environ:
                env["STARENV_CACHE_DIR"] = os.environ["STARENV_CACHE_DIR"]
            ray.init(address=address or None, include_dashboard=False, runtime_env={"env_vars": env},
                     log_to_driver=False, **(options or {}))
        remote = ray.remote(fn)
        pending = {remote.remote(*args): key(args) for args in tasks}
        try:
            while pending:
                done, _ = ray.wait(list(pending), num_returns=1)
                for ref in done:
                    yield pending.pop(ref), ray.get(ref)
        finally:
            for ref in pending:
                ray.cancel(ref)

    return submit_all
