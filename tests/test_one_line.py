"""One line, always: an error an input causes is one line naming the file or key (``--debug`` adds the traceback),
nesting is bounded before it reaches the interpreter's recursion limit, and the vector env names a worker that died or
stopped answering."""

import os
import signal
import time

import pytest

from starenv import cli
from starenv.env import StarSensorEnv
from starenv.vector import SharedMemoryVectorEnv

SMALL = {"heads.0.width": 128, "heads.0.height": 128}


def _one_line(capsys, *names: str) -> str:
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    for name in names:
        assert name in err, err
    return err


def test_a_deep_set_value_is_one_line_naming_the_key(capsys):
    for value in ("[" * 5000 + "]" * 5000, "[" * 40 + "1" + "]" * 40):  # beyond, and within, the JSON parser's limit
        assert cli.main(["render", "paper_000", "--set", f"motion.rate_dps={value}"]) == 2
        _one_line(capsys, "--set motion.rate_dps: lists and tables nested more than")


def test_nested_composite_distortions_are_bounded_naming_the_key(tmp_path, capsys):
    import re

    from starenv import scenario as scenario_mod

    text = re.sub(r"\[heads\.distortion\][^\[]*", "", scenario_mod.resolve("paper_000").read_text())
    lines, prefix = [text, "[heads.distortion]", 'kind = "composite"'], "heads.distortion"
    for _ in range(300):  # far deeper than the bound (the 1500 levels took the interpreter's limit)
        prefix += ".models"
        lines += [f"[[{prefix}]]", 'kind = "composite"']
    path = tmp_path / "deep.toml"
    path.write_text("\n".join(lines) + "\n")
    assert cli.main(["render", str(path), "--quiet", "--out", str(tmp_path / "x.png")]) == 2
    _one_line(capsys, f"{path}: heads.0.distortion.models.0.models", "composite models nested at most 8 deep")


def test_debug_adds_the_traceback(capsys):
    assert cli.main(["render", "paper_000", "--frame", "-1", "--debug"]) == 2
    err = capsys.readouterr().err
    assert "Traceback" in err and err.rstrip().splitlines()[-1].startswith("starenv: error: --frame -1")


def test_an_unexpected_error_is_one_line_with_a_hint(monkeypatch, capsys):
    def broken(args):
        raise KeyError("a bug, not an input")

    monkeypatch.setattr(cli, "cmd_scenarios", broken)
    assert cli.main(["scenarios"]) == 1
    _one_line(capsys, "unexpected KeyError", "--debug")


def test_train_errors_are_one_line(tmp_path, capsys):
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "dataset.json").write_text('{"kind": "main_star", "samples": "lots"}')
    assert cli.main(["train", "--data", str(tmp_path / "data"), "--out", str(tmp_path / "run")]) == 2
    _one_line(capsys, "dataset.json: samples")


def test_escape_sequences_in_an_error_are_not_sent_to_the_terminal(tmp_path, capsys):
    bad = tmp_path / "evil\x1b[2Jname.toml"
    bad.write_text("x = [")
    assert cli.main(["render", str(bad)]) == 2
    err = _one_line(capsys)
    assert "\x1b" not in err


# --- the vector env names dead and stopped workers -----------------------------------------------------------------


def _envs(timeout_s):
    return SharedMemoryVectorEnv([lambda: StarSensorEnv("paper_000", SMALL)] * 2, workers=2, context="fork",
                                 infos=False, timeout_s=timeout_s)


def test_a_worker_killed_between_steps_is_named(capsys):
    envs = _envs(60.0)
    envs.reset(seed=0)
    os.kill(envs._processes[1].pid, signal.SIGKILL)
    envs._processes[1].join(timeout=10)
    actions = {k: v[None].repeat(2, axis=0) for k, v in StarSensorEnv("paper_000", SMALL).null_action().items()}
    with pytest.raises(RuntimeError, match=r"env 1: the worker of envs 1-1 died \(exit code -9\)"):
        envs.step(actions)
    with pytest.raises(RuntimeError, match="env 1: the worker of envs 1-1 died"):  # and stays refused
        envs.step(actions)
    envs.close()
    assert envs.closed


def test_a_stopped_worker_times_out_naming_its_env():
    envs = _envs(2.0)
    envs.reset(seed=0)
    pid = envs._processes[0].pid
    os.kill(pid, signal.SIGSTOP)
    actions = {k: v[None].repeat(2, axis=0) for k, v in StarSensorEnv("paper_000", SMALL).null_action().items()}
    try:
        t0 = time.monotonic()
        with pytest.raises(TimeoutError, match=r"env 0: the worker of envs 0-0 did not answer within 2 s"):
            envs.step(actions)
        assert time.monotonic() - t0 < 30.0  # the 2 s limit, plus the other worker's step
        t0 = time.monotonic()
        envs.close()  # ends the stopped worker instead of waiting for it
        assert time.monotonic() - t0 < 30.0 and not envs._processes[0].is_alive()
    finally:
        if envs._processes[0].is_alive():
            os.kill(pid, signal.SIGKILL)


def test_a_write_error_names_the_file(tmp_path):
    """A write past the process's file-size limit fails with EFBIG ("File too large"), which names no file; the
    atomic writer names its target and leaves no temporary file behind."""
    import subprocess
    import sys

    target = tmp_path / "big.bin"
    code = ("import resource, signal, sys\n"
            "signal.signal(signal.SIGXFSZ, signal.SIG_IGN)\n"
            "resource.setrlimit(resource.RLIMIT_FSIZE, (4096, 4096))\n"
            "from starenv.files import atomic_file\n"
            "try:\n"
            f"    with atomic_file({str(target)!r}) as f:\n"
            "        f.write(bytes(65536))\n"
            "except OSError as exc:\n"
            "    print(exc.errno, exc.filename)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    import errno

    assert out == [str(errno.EFBIG), str(target)]
    assert list(tmp_path.iterdir()) == []
