"""Running a bench: every run scored step by step with ``run_episode``, on local processes or a Ray cluster, resumable.

Each run is a pure function of its :class:`~starenv.bench.spec.RunSpec` (scenario text, overrides, pipeline, seed,
steps): the same run gives bit-identical score records whichever executor ran it, except the agent latencies
(``latency_*_ms``, wall-clock) and the run's ``wall_s``, which are measurements of the machine.

Results: ``OUT/runs/<run_id>.jsonl``, one JSON object per line: a header ``{"identity": ..., "digest": ...,
"run_id": ...}``, one line per step (the flat record of ``starenv.scoring.flatten``, with ``step``),
and a footer ``{"complete": true, "steps": n, "digest": ..., "steps_sha256": ..., "dropped": [...], "lost_at": ...,
"wall_s": ...}``; ``steps_sha256`` is the SHA-256 of the step lines (UTF-8, each line with its ``\n``) and the
header's ``digest`` the SHA-256 of its identity (compact JSON, sorted keys).  The file is
written whole under a temporary name, then moved into place (``os.replace``), so a killed runner leaves either a
complete file or none; on restart a run whose file is complete, carries the same digest and whose step lines match
their checksum is reused; any other existing file (edited, truncated, malformed) is run again and listed.

Workers return their records to the driver, which writes the files.  With recordings, each worker writes
``OUT/recordings/<run_id>.mcap`` itself (on a Ray cluster ``OUT`` must be on a file system every node shares).
"""

from __future__ import annotations

import hashlib
import json
import operator
import os
import socket
import sys
import tempfile
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from starenv import metrics
from starenv.bench.spec import MCAP_RECORDER, BenchError, RunSpec
from starenv.files import atomic_file
from starenv.parallel import local_executor, ray_executor


@dataclass
class RunResult:
    """What a worker hands back: the run's id, its per-step records and the episode's totals."""

    run_id: str
    records: list[dict]
    dropped: list[int]
    lost_at: int | None
    wall_s: float


def execute(run: RunSpec, recording: str | None = None, recorder: str | None = None) -> RunResult:
    """Run one episode; with a ``recorder`` (``MCAP_RECORDER``) it is recorded to the ``recording`` path."""
    from starenv.env import StarSensorEnv
    from starenv.episode import run_episode

    scenario = run.load_scenario()
    env = StarSensorEnv(scenario.data)
    pipeline = run.pipeline.build(scenario, run.trust)
    observers = []
    if recorder is not None and recording is not None:
        if recorder != MCAP_RECORDER:
            raise BenchError(f"recorder {recorder!r}: the only recorder is {MCAP_RECORDER!r}")
        from starenv.record.mcap import McapRecorder

        Path(recording).parent.mkdir(parents=True, exist_ok=True)
        observers.append(McapRecorder(recording))
    result = run_episode(env, pipeline, seed=run.seed, steps=run.steps, observers=observers)
    return RunResult(run.run_id, result.records, [int(d) for d in result.dropped], result.lost_at, result.wall_s)


def run_file(out: Path, run: RunSpec) -> Path:
    return Path(out) / "runs" / f"{run.run_id}.jsonl"


def recording_file(out: Path, run: RunSpec) -> Path:
    return Path(out) / "recordings" / f"{run.run_id}.mcap"


def steps_sha256(lines: list[str]) -> str:
    """SHA-256 of a run file's step lines (each with its newline)."""
    return hashlib.sha256("".join(line + "\n" for line in lines).encode("utf-8")).hexdigest()


def read_run(path: Path) -> tuple[dict, list[dict], dict]:
    """Header, step records and footer of a run file; ValueError if it is not a complete, intact run file."""
    try:
        lines = Path(path).read_text(encoding="utf-8").split("\n")
    except UnicodeDecodeError as exc:
        raise ValueError(f"{path}: not a complete run file (not UTF-8: {exc})") from exc
    if lines and lines[-1] == "":
        lines.pop()
    if len(lines) < 2:
        raise ValueError(f"{path}: not a complete run file (fewer than 2 lines)")
    try:
        header, footer = json.loads(lines[0]), json.loads(lines[-1])
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not a complete run file (header or footer: {exc})") from exc
    if not isinstance(header, dict) or not isinstance(footer, dict):
        raise ValueError(f"{path}: not a complete run file (header or footer is not a JSON object)")
    body = lines[1:-1]
    if not footer.get("complete") or footer.get("steps") != len(body) or footer.get("digest") != header.get("digest"):
        raise ValueError(f"{path}: not a complete run file (no matching footer)")
    identity = json.dumps(header.get("identity"), sort_keys=True, separators=(",", ":"))
    if hashlib.sha256(identity.encode()).hexdigest() != header.get("digest"):
        raise ValueError(f"{path}: its header's identity does not match its digest (edited or damaged)")
    if footer.get("steps_sha256") != steps_sha256(body):
        raise ValueError(f"{path}: its step lines do not match their checksum (edited or damaged)")
    steps = []
    for k, line in enumerate(body):
        try:
            record = json.loads(line)
        except json.JSONDecodeError as exc:
            raise ValueError(f"{path}: step line {k + 1} is not JSON ({exc})") from exc
        if not isinstance(record, dict) or record.get("step") != k:
            raise ValueError(f"{path}: step line {k + 1} is not the record of step {k}")
        steps.append(record)
    return header, steps, footer


def damage(path: Path, run: RunSpec) -> str | None:
    """Why the existing file ``path`` cannot be reused for ``run`` (None when it can, or when there is no file)."""
    if not Path(path).is_file():
        return None
    try:
        header, _, _ = read_run(path)
    except (OSError, ValueError) as exc:
        return str(exc)
    return None if header.get("digest") == run.digest else f"{path}: its digest is not the run's"


def write_run(path: Path, run: RunSpec, result: RunResult) -> None:
    """Write a run file atomically (:func:`starenv.files.atomic_file`)."""
    header = {"run_id": run.run_id, "digest": run.digest, "identity": run.identity()}
    body = [json.dumps({"step": k, **rec}, sort_keys=True) for k, rec in enumerate(result.records)]
    footer = {"complete": True, "steps": len(result.records), "digest": run.digest, "steps_sha256": steps_sha256(body),
              "dropped": result.dropped, "lost_at": result.lost_at, "wall_s": result.wall_s}
    lines = [json.dumps(header, sort_keys=True), *body, json.dumps(footer, sort_keys=True)]
    with atomic_file(path, "w", encoding="utf-8") as f:
        f.write("\n".join(lines) + "\n")


def comparable(records: Iterable[dict]) -> list[dict]:
    """Step records without the wall-clock metrics (``starenv.metrics``: the latencies), for bit-for-bit comparison
    between executors."""
    return [{k: v for k, v in r.items() if not metrics.is_wall_clock(k)} for r in records]


def check_writable(out: Path) -> None:
    """Create ``out`` and prove a file can be written in it, or raise BenchError naming the folder."""
    try:
        Path(out).mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=out):
            pass
    except OSError as exc:
        raise BenchError(f"--out {out}: expected a folder that can be created and written ({exc})") from exc


LOCK = ".bench.lock"  # in OUT while a bench writes there: "HOST PID"


def _lock_holder(path: Path) -> str | None:
    """Who holds the lock at ``path`` ("host H, process P"), or None when it is stale: its process on this host is
    gone, or the lock is unreadable (a bench killed between creating it and writing it)."""
    try:
        host, pid = path.read_text(encoding="utf-8").split()
        pid = int(pid)
    except (OSError, ValueError):
        return None
    if host == socket.gethostname():
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return None
        except PermissionError:  # alive, another user's
            pass
    return f"host {host}, process {pid}"


@contextmanager
def bench_lock(out: Path) -> Iterator[None]:
    """Hold ``out``'s bench lock (``OUT/.bench.lock``, created exclusively, removed when the bench ends): a second
    bench on the same folder is refused with a BenchError naming the holder; a lock left by a killed bench on this
    host is taken over."""
    path = Path(out) / LOCK
    for _ in range(2):
        try:
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0), 0o644)
            break
        except FileExistsError:
            holder = _lock_holder(path)
            if holder is not None:
                raise BenchError(f"--out {out}: another bench is writing there ({holder}, {path}); wait for it or "
                                 f"choose another --out (delete the lock only if no bench runs)") from None
            path.unlink(missing_ok=True)  # stale: taken over
    else:
        raise BenchError(f"--out {out}: {path} keeps coming back; another bench is starting there")
    with os.fdopen(fd, "w", encoding="utf-8") as f:
        f.write(f"{socket.gethostname()} {os.getpid()}\n")
    try:
        yield
    finally:
        path.unlink(missing_ok=True)


def _finished_recording(path: Path) -> bool:
    """Whether ``path`` is a finished MCAP recording (a 0-byte or cut file a killed run left is not)."""
    from starenv.record.mcap import is_finished

    try:
        return is_finished(path)
    except ValueError:
        return False


def run_bench(bench, out: str | Path, jobs: int | None = None, ray_address: str | None = None,
              use_ray: bool = False, ray_options: dict | None = None, progress: bool = True,
              log=print) -> list[Path]:
    """Run every run of ``bench`` not already complete in ``out``; return all run files in the bench's order.

    ``jobs``: local worker processes (default: the CPU count; 1 runs in this process).  ``use_ray``: run on the Ray
    cluster at ``ray_address`` (None: a local instance, or the one this process already started; ``ray_options``
    go to ``ray.init``, e.g. ``num_cpus``).  One bench at a time writes to ``out`` (:func:`bench_lock`).
    """
    out = Path(out)
    check_writable(out)
    with bench_lock(out):
        return _run_bench(bench, out, jobs, ray_address, use_ray, ray_options, progress, log)


def _run_bench(bench, out: Path, jobs, ray_address, use_ray, ray_options, progress, log) -> list[Path]:
    from tqdm import tqdm

    key = operator.itemgetter(0)
    jobs = (os.cpu_count() or 1) if jobs is None else jobs
    if use_ray:
        executor = ray_executor(execute, key, ray_address, ray_options, BenchError)
    else:
        executor = local_executor(execute, key, jobs)
    todo, reused = [], []
    for run in bench.runs:
        why = damage(run_file(out, run), run)
        if why is not None:
            log(f"  recomputing {run.run_id}: {why}")
        complete = why is None and run_file(out, run).is_file()
        if complete and bench.recorder is not None and run.record and not _finished_recording(recording_file(out, run)):
            complete = False
        (reused if complete else todo).append(run)
    if reused:
        log(f"reusing {len(reused)} complete run(s) from {out / 'runs'}:")
        for run in reused:
            log(f"  reused {run.run_id}")
    total_steps = sum(r.steps for r in bench.runs)
    done_steps = sum(r.steps for r in reused)
    bar = tqdm(total=len(bench.runs), initial=len(reused), unit="run", disable=not progress, file=sys.stderr,
               desc=bench.name, postfix={"steps": f"{done_steps}/{total_steps}"})
    tasks = [(r, str(recording_file(out, r)) if bench.recorder and r.record else None, bench.recorder) for r in todo]
    try:
        for run, result in executor(tasks):
            write_run(run_file(out, run), run, result)
            done_steps += run.steps
            bar.set_postfix(steps=f"{done_steps}/{total_steps}")
            bar.update(1)
    finally:
        bar.close()
    log(f"ran {len(todo)} run(s), reused {len(reused)}")
    return [run_file(out, r) for r in bench.runs]
