"""Resume from any kill point: training killed after (or while) writing any of its checkpoints resumes to the weights
an uninterrupted run gives; a resume whose arguments change the result is refused naming the argument."""

import json

import numpy as np
import pytest
import torch
from test_learned import TOY, _toy_dataset

from starenv.agents.identify import network_train
from starenv.agents.identify.network_train import train

EPOCHS, BATCH, SAMPLES, EVERY = 2, 16, 32, 1  # 2 batches per epoch, a checkpoint after each and at each epoch's end
# checkpoints of a whole run: per epoch one per EVERY batches and one at its end, then the final one
CHECKPOINTS = EPOCHS * (SAMPLES // BATCH // EVERY + 1) + 1


class Killed(BaseException):
    """The process dying (not an Exception: nothing in the trainer may catch it)."""


@pytest.fixture
def tiny(tmp_path, monkeypatch):
    _toy_dataset(tmp_path / "train", SAMPLES, 0)
    _toy_dataset(tmp_path / "val", 16, 1)
    monkeypatch.setattr("starenv.agents.identify.network_train._class_hips", lambda spec: np.arange(1, 5))
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # tiny batches: threads only wait for each other on a shared machine
    yield tmp_path
    torch.set_num_threads(threads)


def _train(tiny, out, **kw):
    options = {"val": tiny / "val", "epochs": EPOCHS, "batch": BATCH, "lr": 1e-2, "seed": 3, "config_pairs": TOY,
               "checkpoint_every": EVERY, "progress": False, "log": lambda *_: None, **kw}
    return train(tiny / "train", tiny / out, **options)


def _same_result(a, b) -> None:
    wa = torch.load(a / "weights.pt", weights_only=True)
    wb = torch.load(b / "weights.pt", weights_only=True)
    assert wa.keys() == wb.keys() and all(torch.equal(wa[k], wb[k]) for k in wa)
    ma, mb = (json.loads((p / "manifest.json").read_text()) for p in (a, b))
    for m in (ma, mb):  # wall-clock figures differ between runs; everything else must not
        m.pop("train_seconds")
        for record in m["metrics"]:
            record.pop("train_seconds")
            record.pop("samples_per_s")
    assert ma["metrics"] == mb["metrics"] and ma["weights_sha256"] == mb["weights_sha256"]


@pytest.mark.parametrize("mid_write", [False, True], ids=["after-write", "mid-write"])
def test_training_resumes_from_every_checkpoint_boundary(tiny, monkeypatch, mid_write):
    """One run killed again and again: each process dies right after the first checkpoint it writes (or while
    writing its second, leaving a stray temporary file), and the next resumes; the last one finishes.  The kills fall
    on every checkpoint of the run in turn, and the result is the uninterrupted run's."""
    real = network_train._atomic_save
    writes = []

    def counting(obj, path):
        writes.append(path.name)
        real(obj, path)

    monkeypatch.setattr(network_train, "_atomic_save", counting)
    _train(tiny, "whole")
    assert writes == ["checkpoint.pt"] * CHECKPOINTS
    kills = 0
    while True:
        seen = []

        def dying(obj, path, seen=seen, kills=kills):
            seen.append(path)
            if mid_write and len(seen) == 2:  # killed while writing: the previous checkpoint is what remains
                path.with_name(f".{path.name}.killed.tmp").write_bytes(b"PK\x03\x04 cut short")
                raise Killed
            real(obj, path)
            if not mid_write and kills < CHECKPOINTS:  # the last process writes the final checkpoint again, lives
                raise Killed

        monkeypatch.setattr(network_train, "_atomic_save", dying)
        try:
            _train(tiny, "killed", resume=kills > 0)
        except Killed:
            kills += 1
            assert not (tiny / "killed" / "weights.pt").exists()
            continue
        break
    # after-write: one kill per checkpoint; mid-write: every process but the last writes one checkpoint and dies in
    # the next, the last one writes the final checkpoint alone
    assert kills == (CHECKPOINTS if not mid_write else CHECKPOINTS - 1)
    _same_result(tiny / "whole", tiny / "killed")


@pytest.mark.parametrize("change", [{"batch": 8}, {"seed": 4}, {"lr": 2e-2}, {"epochs": 3}, {"rot90": True},
                                    {"val": None}])
def test_a_resume_with_other_arguments_is_refused_by_name(tiny, monkeypatch, change):
    real = network_train._atomic_save

    def dying(obj, path):
        real(obj, path)
        raise Killed

    monkeypatch.setattr(network_train, "_atomic_save", dying)
    with pytest.raises(Killed):
        _train(tiny, "run")
    monkeypatch.setattr(network_train, "_atomic_save", real)
    (key,) = change
    with pytest.raises(ValueError, match=f"--resume: .*checkpoint.pt was written with --{key} "):
        _train(tiny, "run", resume=True, **change)


def test_a_damaged_checkpoint_is_refused_naming_it(tiny):
    _train(tiny, "run", max_minutes=0.0)  # stops after the first batch, checkpoint written
    ckpt = tiny / "run" / "checkpoint.pt"
    data = bytearray(ckpt.read_bytes())
    ckpt.write_bytes(bytes(data[: len(data) // 2]))
    with pytest.raises(ValueError, match=f"--resume: {ckpt} cannot be read"):
        _train(tiny, "run", resume=True)


# --- benches -------------------------------------------------------------------------------------------------------

BENCH = """
seeds = [0]
steps = 2
recordings = true
[[runs]]
scenario = "paper_000"
set = { "heads.0.width" = 128, "heads.0.height" = 128 }
"""


def test_a_second_bench_on_one_folder_is_refused_and_a_stale_lock_taken_over(tmp_path):
    import os
    import socket
    import subprocess
    import sys

    from starenv.bench.runner import LOCK, run_bench
    from starenv.bench.spec import BenchError, parse_bench

    bench = parse_bench(BENCH)
    lock = tmp_path / LOCK
    holder = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:  # a bench of a live process holds the folder
        lock.write_text(f"{socket.gethostname()} {holder.pid}\n")
        with pytest.raises(BenchError, match=f"another bench is writing there .*process {holder.pid}"):
            run_bench(bench, tmp_path, jobs=1, progress=False, log=lambda *_: None)
        assert not (tmp_path / "runs").exists()
    finally:
        holder.kill()
        holder.wait()
    # the same lock once its process is gone: a killed bench's, taken over; the bench removes it when it ends
    run_bench(bench, tmp_path, jobs=1, progress=False, log=lambda *_: None)
    assert not lock.exists() and len(os.listdir(tmp_path / "runs")) == 1


def test_a_bench_resume_redoes_a_run_whose_recording_is_empty_or_cut(tmp_path):
    from starenv.bench.runner import recording_file, run_bench
    from starenv.bench.spec import parse_bench
    from starenv.record.mcap import read_steps

    bench = parse_bench(BENCH)
    run_bench(bench, tmp_path, jobs=1, progress=False, log=lambda *_: None)
    recording = recording_file(tmp_path, bench.runs[0])
    whole = recording.read_bytes()
    for damaged in (b"", whole[: len(whole) // 2]):  # killed while the recording was written / renamed empty
        recording.write_bytes(damaged)
        logs = []
        run_bench(bench, tmp_path, jobs=1, progress=False, log=logs.append)
        assert logs[-1] == "ran 1 run(s), reused 0"
        assert len(list(read_steps(recording))) == 2


class _Killed(BaseException):
    """Stands for SIGKILL at a chosen write (a BaseException: no handler in the bench catches it)."""


def test_a_bench_killed_before_any_run_file_resumes_to_the_same_scores(tmp_path, monkeypatch):
    """A bench of three recorded runs killed before each of its run-file writes (a half-written temporary file left
    beside it, as a kill leaves) and started again must end with the scores of a bench never interrupted, every run
    file complete and every recording readable."""
    import starenv.bench.runner as runner
    from starenv.bench.spec import parse_bench
    from starenv.record.mcap import read_steps

    bench = parse_bench(BENCH.replace("seeds = [0]", "seeds = [0, 1, 2]"))

    def scores(out):
        return {p.name: runner.comparable(runner.read_run(p)[1]) for p in sorted((out / "runs").glob("*.jsonl"))}

    runner.run_bench(bench, tmp_path / "whole", jobs=1, progress=False, log=lambda *_: None)
    whole = scores(tmp_path / "whole")
    assert len(whole) == 3
    real_atomic = runner.atomic_file
    for kill_at in range(len(whole)):
        out = tmp_path / f"killed-{kill_at}"
        count = {"n": 0}

        def atomic_file(path, *args, _kill=kill_at, _n=count, **kwargs):
            if _n["n"] == _kill:
                path.parent.mkdir(parents=True, exist_ok=True)
                (path.parent / f".{path.name}.half.tmp").write_bytes(b"{")
                raise _Killed
            _n["n"] += 1
            return real_atomic(path, *args, **kwargs)

        monkeypatch.setattr(runner, "atomic_file", atomic_file)
        with pytest.raises(_Killed):
            runner.run_bench(bench, out, jobs=1, progress=False, log=lambda *_: None)
        monkeypatch.setattr(runner, "atomic_file", real_atomic)
        (out / runner.LOCK).unlink(missing_ok=True)  # a killed bench leaves its lock (taken over on this host anyway)
        logs = []
        runner.run_bench(bench, out, jobs=1, progress=False, log=logs.append)
        assert f"ran {len(whole) - kill_at} run(s), reused {kill_at}" in logs
        assert scores(out) == whole, f"killed before run file {kill_at}"
        for run in bench.runs:
            assert len(list(read_steps(runner.recording_file(out, run)))) == 2
