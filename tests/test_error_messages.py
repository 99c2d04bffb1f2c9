"""Error messages and hints that name the real cause and print commands that work: a ``--set`` override's error
names the override, a misspelt key its closest valid key, a misspelt bench role the roles; the trust hint's command
parses; a closed output pipe ends a command quietly; an unfinished recording's reproduce hint runs; the README's
review comparison states the flag it needs."""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from starenv import cli
from starenv.agents.pipeline import Pipeline
from starenv.bench.spec import BenchError, parse_bench
from starenv.config import closest_key
from starenv.env import StarSensorEnv
from starenv.episode import run_episode
from starenv.record.mcap import McapRecorder
from starenv.scenario import AGENT_ROLES, SCENARIO_DIR, ScenarioError, load

ROOT = Path(__file__).resolve().parents[1]
SMALL = ["--set", "heads.0.width=128", "--set", "heads.0.height=128"]


def one_line_error(capsys) -> str:
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("starenv: error: "), err
    return err.removeprefix("starenv: error: ").strip()


@pytest.mark.parametrize(("pair", "expected"), [
    ("exposure_s=abc", "expected a number in (0, 0.01], got 'abc'"),
    ("heads.0.detector.gain_e_per_dn=0", "gain_e_per_dn must be in [0.001, 10000] e-/DN, got 0"),
    ("heads.0=5", "expected a table, got 5"),
    ("camera.fov_deg=abc", "camera: unknown key"),
])
def test_a_set_override_error_names_the_override_as_typed_not_the_bundled_file(pair, expected, capsys):
    assert cli.main(["run", "paper_000", "--steps", "1", "--set", pair]) == 2
    err = one_line_error(capsys)
    assert err.startswith(f"--set {pair}: {expected}"), err
    assert str(SCENARIO_DIR) not in err and "paper_000.toml" not in err


def test_an_override_from_python_is_named_beside_the_file():
    with pytest.raises(ScenarioError) as info:
        load("paper_000", {"exposure_s": "abc"})
    assert str(info.value) == (f"override exposure_s=abc on {SCENARIO_DIR / 'paper_000.toml'}: exposure_s: "
                               "expected a number in (0, 0.01], got 'abc'")
    assert info.value.override == "exposure_s" and info.value.detail == "expected a number in (0, 0.01], got 'abc'"
    with pytest.raises(ScenarioError) as info:  # the file's exposure against an overridden frame rate: the key
        load("paper_000", {"frame_rate_hz": 200.0})  # at fault is the file's, and no override is named
    assert info.value.override is None and str(info.value).startswith(f"{SCENARIO_DIR / 'paper_000.toml'}: "
                                                                      "exposure_s: expected a number in (0, 0.005]")
    with pytest.raises(ScenarioError) as info:
        load("paper_000", {"heads.0.width": 128, "heads.0.detector": {"gain_e_per_dn": 0}})
    assert info.value.override == "heads.0.detector" and str(info.value).startswith("override heads.0.detector={")


def misspelt(tmp_path: Path, old: str, new: str) -> Path:
    """paper_000 with the line starting ``old`` renamed to ``new``."""
    text = (SCENARIO_DIR / "paper_000.toml").read_text(encoding="utf-8")
    assert re.search(rf"^{re.escape(old)} ", text, re.M)
    path = tmp_path / "typo.toml"
    path.write_text(re.sub(rf"^{re.escape(old)} ", f"{new} ", text, flags=re.M), encoding="utf-8")
    return path


@pytest.mark.parametrize(("old", "new", "where", "hint"), [
    ("exposure_s", "exposur_s", "exposure_s", "it is missing (found 'exposur_s': did you mean 'exposure_s'?)"),
    ("focal_length_mm", "focal_lenght_mm", "heads.0.focal_length_mm",
     "it is missing (found 'focal_lenght_mm': did you mean 'focal_length_mm'?)"),
    ("kx_per_px2", "kx_per_px", "heads.0.distortion.kx_per_px", "unknown key (did you mean 'kx_per_px2'?"),
    ("read_noise_e", "readnoise_e", "heads.0.detector.readnoise_e", "unknown key (did you mean 'read_noise_e'?"),
])
def test_a_misspelt_required_or_optional_key_is_named_with_the_closest_valid_key(tmp_path, old, new, where, hint):
    path = misspelt(tmp_path, old, new)
    with pytest.raises(ScenarioError, match=re.escape(f"{path}: {where}: ") + ".*" + re.escape(hint)):
        load(path)


def test_a_sibling_key_is_not_offered_as_a_misspelling():
    # keys that differ by one whole word unlike its counterpart name different things
    assert closest_key("coeffs_x_px", ["coeffs_y_px"]) is None
    assert closest_key("initial_ra_deg", ["initial_dec_deg", "initial_roll_deg"]) is None
    assert closest_key("exposure_s", ["exposur_s", "epoch"]) == "exposur_s"
    assert closest_key("rate_dps", ["rate_dsp"]) == "rate_dsp"
    assert closest_key("seed", ["speed_of_light"]) is None


def test_a_misspelt_bench_role_is_named_with_the_roles(tmp_path):
    text = ('steps = 1\n[pipelines.svd]\nsolvr = "starenv.agents.solve:SvdSolver"\n'
            '[[runs]]\nscenario = "paper_000"\npipelines = ["svd"]\n')
    with pytest.raises(BenchError) as info:
        parse_bench(text, "b.toml", check=False)
    message = str(info.value)
    assert "b.toml: pipelines.svd.solvr: unknown key (did you mean 'solver'?" in message
    allowed = message.split("allowed here: ", 1)[1]
    assert all(role in allowed for role in AGENT_ROLES), message


def test_the_trust_hint_prints_a_command_line_the_parser_accepts(capsys):
    with pytest.raises(ValueError) as info:
        Pipeline(solver="numpy.linalg:LinAlgError")
    message = str(info.value)
    assert "starenv --trust" not in message  # the option belongs to run / bench, after the command
    command = re.search(r"\((starenv run [^,]*?\.\.\.)", message).group(1)
    words = shlex.split(command.replace("SCENARIO", "paper_000").replace("...", ""))
    assert words[:3] == ["starenv", "run", "paper_000"] and words[3:] == ["--trust", "numpy"]
    # as the hint says: the module is trusted now, and refused for what it is (no solver class), not for trust
    assert cli.main([*words[1:], "--steps", "1", *SMALL, "--agent", "solver=numpy.linalg:LinAlgError"]) == 2
    err = one_line_error(capsys)
    assert "not trusted" not in err and "LinAlgError" in err


def test_a_closed_output_pipe_ends_a_command_quietly_with_status_0():
    read_end, write_end = os.pipe()
    os.close(read_end)  # the reader is gone before the first line (as `starenv scenarios | head -0`)
    try:
        proc = subprocess.run([sys.executable, "-m", "starenv.cli", "scenarios"], stdout=write_end,
                              stderr=subprocess.PIPE, text=True, timeout=120,
                              env={**os.environ, "PYTHONPATH": str(ROOT)})
    finally:
        os.close(write_end)
    assert proc.returncode == 0 and proc.stderr == "", proc.stderr


def test_head_of_the_scenario_list_reads_one_line_and_the_command_ends_quietly():
    proc = subprocess.run(f"{shlex.quote(sys.executable)} -m starenv.cli scenarios | head -1; "
                          "echo status=${PIPESTATUS[0]}", shell=True, executable="/bin/bash", capture_output=True,
                          text=True, timeout=120, env={**os.environ, "PYTHONPATH": str(ROOT)})
    lines = proc.stdout.splitlines()
    assert len(lines) == 2 and lines[1] == "status=0" and proc.stderr == "", proc.stdout + proc.stderr


@pytest.fixture(scope="module")
def partial(tmp_path_factory) -> Path:
    """A killed run's recording: a finished one of a few steps in several chunks, cut short."""
    folder = tmp_path_factory.mktemp("partial")
    env = StarSensorEnv("paper_000", {"heads.0.width": 128, "heads.0.height": 128})
    run_episode(env, Pipeline.for_scenario(env.scenario), seed=1, steps=4,
                observers=[McapRecorder(folder / "full.mcap", chunk_size=1 << 14)])
    data = (folder / "full.mcap").read_bytes()
    cut = folder / "run.mcap.partial"
    cut.write_bytes(data[: int(len(data) * 0.7)])
    return cut


def test_the_reproduce_hint_of_an_unfinished_recording_runs(partial, tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("CI", "1")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.chdir(tmp_path)
    assert cli.main(["view", str(partial), "--rrd", str(tmp_path / "review.rrd"), "--quiet"]) == 0
    out = capsys.readouterr().out
    view_reproduce = re.search(r"reproduce: (.*?)  \(", out).group(1)
    hint = shlex.split(re.search(r"\((starenv export [^)]*) writes it\)", out).group(1))
    assert hint[2] == str(partial)  # the user's file, no temporary copy
    assert cli.main(hint[1:]) == 0, capsys.readouterr().err
    out = capsys.readouterr().out
    assert (tmp_path / "scenario.toml").is_file()
    assert re.search(r"reproduce: (.*)", out).group(1) == view_reproduce  # the same run, the same complete steps
    load(tmp_path / "scenario.toml")


def test_the_readme_compares_reviews_with_the_flag_rerun_needs():
    # Rerun 0.41's `rrd compare` without --unordered fails on two reviews of one recording (chunk order and
    # chunking follow the logging's timing); tests/test_record.py runs the comparison itself
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    uses = re.findall(r"rerun rrd compare[^`]*", readme)
    assert uses and all("--unordered" in use for use in uses), uses
