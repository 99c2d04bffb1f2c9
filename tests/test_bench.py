"""The benchmark runner: bench-file parsing and validation, executors agreeing bit for bit, resuming, reports."""

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from starenv import scenario as scenario_mod
from starenv.agents.pipeline import Pipeline
from starenv.bench.report import aggregate, markdown_tables, write_report
from starenv.bench.runner import RunResult, comparable, read_run, run_bench, run_file, write_run
from starenv.bench.spec import BENCH_DIR, BenchError, Sweep, load_bench, parse_bench, resolve_bench
from starenv.cli import main
from starenv.env import StarSensorEnv
from starenv.episode import run_episode
from starenv.parallel import ray_executor
from starenv.scenario import SCENARIO_DIR
from starenv.sim.sensor import noise_thread_default

ROOT = Path(__file__).resolve().parent.parent

SMALL = """
name = "small"
seeds = [0]
steps = 3
[[runs]]
scenario = "paper_000"
pipelines = ["scenario", "lost_in_space"]
sweep = { key = "motion.rate_dps", axis = [1, 0, 0], values = [0, 4] }
"""


def _bench(tmp_path, text=SMALL, name="b.toml"):
    path = tmp_path / name
    path.write_text(text)
    return path


def _quiet(*args, **kwargs):
    pass


# --- bench files ---------------------------------------------------------------------------------------------------


def test_runs_are_scenarios_times_pipelines_times_seeds_times_sweep_values():
    bench = parse_bench("""
seeds = [0, 7]
[[runs]]
scenario = "paper_000"
steps = 4
pipelines = ["scenario", "lost_in_space", "tracking"]
sweep = { key = "motion.rate_dps", axis = [0, 0, 2], start = 0, stop = 10, step = 2.5 }
[[runs]]
scenario = "paper_004"
seeds = [3]
""")
    first = [r for r in bench.runs if r.scenario == "paper_000"]
    assert len(first) == 3 * 2 * 5  # pipelines x seeds x {0, 2.5, 5, 7.5, 10}
    assert sorted({r.sweep_value for r in first}) == [0.0, 2.5, 5.0, 7.5, 10.0]
    r = next(r for r in first if r.sweep_value == 7.5)
    assert r.overrides == {"motion.rate_dps": [0.0, 0.0, 7.5]}  # magnitude along the unit axis
    last = [r for r in bench.runs if r.scenario == "paper_004"]
    # defaults: the scenario's own pipeline, the group's seeds, the whole scenario (10 s at 10 Hz = 100 frames)
    assert [(r.pipeline.name, r.seed, r.steps) for r in last] == [("scenario", 3, 99)]
    assert len({r.run_id for r in bench.runs}) == len(bench.runs)


def test_axis_sweep_is_a_magnitude_about_the_unit_axis():
    v = Sweep("motion.rate_dps", (10.0,), (1.0, 1.0, 1.0)).override(10.0)
    assert math.hypot(*v) == pytest.approx(10.0, rel=1e-15)
    assert v[0] == v[1] == v[2] == pytest.approx(10.0 / math.sqrt(3.0))
    assert Sweep("drops.probability", (0.1,)).override(0.1) == 0.1  # no axis: the value as is


@settings(max_examples=40, deadline=None)
@given(start=st.integers(-50, 50), step=st.integers(1, 20), n=st.integers(1, 12), scale=st.sampled_from([1, 0.5]))
def test_range_sweeps_include_stop_and_have_the_expected_count(start, step, n, scale):
    start, step = start * scale, step * scale
    stop = start + (n - 1) * step
    text = f"""[[runs]]
scenario = "paper_000"
steps = 1
seeds = [0]
sweep = {{ key = "exposure_s", start = {start}, stop = {stop}, step = {step} }}"""
    bench = parse_bench(text, check=False)
    values = [r.sweep_value for r in bench.runs]
    assert len(values) == n
    assert values[0] == start and values[-1] == pytest.approx(stop, abs=1e-9)
    assert np.allclose(np.diff(values), step)


def test_identity_hash_changes_with_every_input_and_only_then(tmp_path):
    base = parse_bench(SMALL).runs
    again = parse_bench(SMALL).runs
    assert [r.digest for r in base] == [r.digest for r in again]
    seeds = parse_bench(SMALL.replace("seeds = [0]", "seeds = [1]")).runs
    steps = parse_bench(SMALL.replace("steps = 3", "steps = 4")).runs
    rates = parse_bench(SMALL.replace("values = [0, 4]", "values = [0, 5]")).runs
    copy = tmp_path / "paper_000.toml"
    copy.write_text((SCENARIO_DIR / "paper_000.toml").read_text() + "\n# an edited copy\n")
    edited = parse_bench(SMALL.replace('"paper_000"', f'"{copy}"')).runs
    digests = [{r.digest for r in runs} for runs in (base, seeds, steps, rates, edited)]
    assert all(len(d) == 4 for d in digests)
    assert len(digests[0] & digests[3]) == 2  # the rate-0 runs are the same runs
    for other in (digests[1], digests[2], digests[4]):
        assert not digests[0] & other


def test_bundled_bench_covers_every_paper_and_a_30_dps_rate_sweep():
    assert resolve_bench("bundled") == BENCH_DIR / "bundled.toml"
    bench = load_bench("bundled")  # validates every scenario x sweep value and builds every pipeline
    scenarios = {r.scenario for r in bench.runs}
    assert {f"paper_00{i}" for i in range(5)} <= scenarios
    for i in range(5):
        runs = {r.pipeline.name: r for r in bench.runs if r.scenario == f"paper_00{i}"}
        assert {"tracking", "lost_in_space"} <= set(runs)
        # "tracking" is the scenario's own pipeline for every source paper (none names another identifier)
        sc = scenario_mod.load(f"paper_00{i}")
        own = Pipeline.for_scenario(sc).describe()
        assert runs["tracking"].pipeline.build(sc).describe() == own
        lis = runs["lost_in_space"].pipeline.build(sc).describe()
        assert lis == {**own, "identifier": "starenv.agents.identify:LostInSpaceIdentifier"}
    swept = [r for r in bench.runs if r.sweep_key == "motion.rate_dps"]
    assert {r.scenario for r in swept} == {"paper_000", "paper_002"}
    rates = sorted({r.sweep_value for r in swept if r.scenario == "paper_002"})
    assert rates[0] == 0 and rates[-1] == 30
    assert all(math.hypot(*r.overrides["motion.rate_dps"]) == pytest.approx(r.sweep_value) for r in swept)
    # every deblurrer of the source papers runs, each beside a blurred baseline on the same scenario
    deblurrers = {r.pipeline.build(scenario_mod.load(r.scenario)).describe()["deblurrer"] for r in bench.runs}
    assert {"starenv.agents.restore:IterationNetDeblurrer",
            "starenv.agents.restore:CurvatureRLDeblurrer", "starenv.agents.restore:WienerDeblurrer",
            "starenv.agents.restore:TrailFitDeblurrer"} < deblurrers


def test_working_rate_bench_sweeps_each_axis_in_5_dps_steps_with_every_restorer():
    bench = load_bench("working_rate")
    groups = {}
    for r in bench.runs:
        groups.setdefault((r.scenario, r.sweep_axis), set()).add((r.pipeline.name, r.sweep_value, r.seed))
    assert set(groups) == {("paper_000", (1.0, 0.0, 0.0)), ("paper_000", (0.0, 1.0, 0.0)),
                           ("paper_000", (0.0, 0.0, 1.0)), ("paper_002", (1.0, 1.0, 1.0))}
    deblurrers = {r.pipeline.build(scenario_mod.load(r.scenario)).describe()["deblurrer"] for r in bench.runs}
    assert len(deblurrers) == 6  # none (blurred) and the five restorers
    for cases in groups.values():
        rates = sorted({v for _, v, _ in cases})
        assert rates[0] == 0 and max(np.diff(rates)) <= 5
        assert {s for _, _, s in cases} == {0, 1}
    assert {r.steps for r in bench.runs} == {20}


USES_X = SMALL.replace('"lost_in_space"]', '"x"]')
BAD = {
    "unknown top-level key": ("frobnicate = 1\n" + SMALL, "frobnicate: unknown key"),
    "unknown run key": (SMALL + "colour = 'red'\n", "runs.0.colour: unknown key"),
    "unknown pipeline key": (
        SMALL + '[pipelines.x]\nsolvr = "starenv.agents.solve:SvdSolver"\n', "pipelines.x.solvr: unknown key"),
    "unloadable agent": (
        USES_X + '[pipelines.x]\nsolver = "starenv.nowhere:Solver"\n',
        "pipelines.x: solver: cannot load agent starenv.nowhere:Solver"),
    "wrong protocol": (
        USES_X + '[pipelines.x]\nsolver = "starenv.agents.detect:CentroidDetector"\n',
        "does not implement the AttitudeSolver protocol"),
    "agent not module:Class": (
        SMALL + '[pipelines.x]\nsolver = "SvdSolver"\n', "pipelines.x.solver: expected 'module:Class'"),
    "unknown pipeline name": (SMALL.replace('"lost_in_space"]', '"fastest"]'), "runs.0.pipelines: expected names"),
    "missing scenario": (SMALL.replace('"paper_000"', '"paper_999"'), "runs.0.scenario: scenario 'paper_999'"),
    "sweep over an unknown key": (SMALL.replace("motion.rate_dps", "motion.rate_dpz"), "runs.0.sweep = 0:"),
    "sweep value out of range": (
        SMALL.replace('key = "motion.rate_dps", axis = [1, 0, 0], values = [0, 4]',
                      'key = "exposure_s", values = [0.005, 0.5]'), "runs.0.sweep = 0.5:"),
    "sweep with both forms": (SMALL.replace("values = [0, 4]", "values = [0, 4], start = 0"), "runs.0.sweep.values"),
    "bad seeds": (SMALL.replace("seeds = [0]", "seeds = [-1]"), "seeds: expected a non-empty list of integers >= 0"),
    "no runs": ("name = 'x'\n", "runs: expected a non-empty array of tables"),
    "bad recordings": ("recordings = 'yes'\n" + SMALL, "recordings: expected true, false or a non-empty list"),
    "bad group recordings": (SMALL + "recordings = 'no'\n", "runs.0.recordings: expected true or false"),
    "preset name redefined": (SMALL + '[pipelines.scenario]\nsolver = "a:B"\n', "built-in preset name"),
}


@pytest.mark.parametrize("case", list(BAD))
def test_bad_bench_files_fail_before_any_run_with_exit_code_2(case, tmp_path, capsys):
    text, expected = BAD[case]
    out = tmp_path / "out"
    assert main(["bench", str(_bench(tmp_path, text)), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert expected in err, err
    assert not (out / "runs").exists()


def test_unknown_sweep_key_error_names_the_key(tmp_path, capsys):
    text = SMALL.replace("motion.rate_dps", "motion.rate_dpz")
    assert main(["bench", str(_bench(tmp_path, text)), "--out", str(tmp_path / "o")]) == 2
    assert "motion.rate_dpz" in capsys.readouterr().err


def test_unwritable_output_folder_fails_with_exit_code_2(tmp_path, capsys):
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    assert main(["bench", str(_bench(tmp_path)), "--out", str(blocker / "out"), "--quiet"]) == 2
    assert "--out" in capsys.readouterr().err


def test_missing_bench_file_names_the_bundled_ones(tmp_path, capsys):
    assert main(["bench", "no_such_bench", "--out", str(tmp_path / "o")]) == 2
    assert "bundled" in capsys.readouterr().err


@settings(max_examples=25, deadline=None)
@given(key=st.from_regex(r"[a-z][a-z_]{0,12}", fullmatch=True).filter(
    lambda k: k not in {"name", "description", "seeds", "steps", "recordings", "pipelines", "runs"}))
def test_any_unknown_top_level_key_is_named(key):
    with pytest.raises(BenchError, match=rf"{key}: unknown key"):
        parse_bench(f"{key} = 1\n" + SMALL, check=False)


# --- running -------------------------------------------------------------------------------------------------------


def test_run_records_equal_an_independent_episode(tmp_path):
    bench = parse_bench(SMALL)
    files = run_bench(bench, tmp_path, jobs=1, progress=False, log=_quiet)
    for run, path in zip(bench.runs, files, strict=True):
        header, steps, footer = read_run(path)
        assert header["digest"] == run.digest and header["identity"]["seed"] == 0
        assert footer["steps"] == len(steps) == 3
        sc = scenario_mod.load("paper_000", run.overrides)
        env = StarSensorEnv("paper_000", run.overrides)
        direct = run_episode(env, run.pipeline.build(sc), seed=0, steps=3).records
        assert comparable([{k: v for k, v in s.items() if k != "step"} for s in steps]) == comparable(direct)
        assert [s["step"] for s in steps] == [0, 1, 2]


def test_process_pool_matches_in_process_bit_for_bit(tmp_path):
    bench = parse_bench(SMALL)
    one = run_bench(bench, tmp_path / "one", jobs=1, progress=False, log=_quiet)
    two = run_bench(bench, tmp_path / "two", jobs=2, progress=False, log=_quiet)
    for a, b in zip(one, two, strict=True):
        assert a.name == b.name
        assert comparable(read_run(a)[1]) == comparable(read_run(b)[1])


def test_ray_matches_local_processes_bit_for_bit(tmp_path):
    ray = pytest.importorskip("ray")
    text = SMALL.replace("values = [0, 4]", "values = [3]")
    bench = parse_bench(text)
    local = run_bench(bench, tmp_path / "local", jobs=1, progress=False, log=_quiet)  # pool == in-process above
    options = {"num_cpus": 2, "object_store_memory": 80 * 1024**2}  # the runner starts a local instance
    try:
        remote = run_bench(bench, tmp_path / "ray", use_ray=True, ray_options=options, progress=False, log=_quiet)
        # its workers are marked as a pool's: their sensors draw the noise on their own thread
        assert list(ray_executor(noise_thread_default, len, None)([()])) == [(0, False)]
    finally:
        ray.shutdown()
    assert len(local) == len(remote) == 2
    for a, b in zip(local, remote, strict=True):
        ra, rb = read_run(a)[1], read_run(b)[1]
        assert comparable(ra) == comparable(rb)
        assert all(any(k.startswith("latency_") for k in r) for r in ra)  # latencies exist, just not compared


def test_ray_missing_is_a_clear_error(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray -> ImportError
    assert main(["bench", str(_bench(tmp_path)), "--out", str(tmp_path / "o"), "--ray", "--quiet"]) == 2
    assert "--ray: the ray package is not installed" in capsys.readouterr().err
    assert not (tmp_path / "o" / "runs").exists()


def test_resume_reruns_only_missing_or_incomplete_runs(tmp_path):
    bench = parse_bench(SMALL)
    lines = []
    files = run_bench(bench, tmp_path, jobs=1, progress=False, log=lines.append)
    assert lines[-1] == "ran 4 run(s), reused 0"
    before = {f.name: f.read_text() for f in files}
    mtimes = {f.name: f.stat().st_mtime_ns for f in files}
    files[1].unlink()
    cut = files[2].read_text().splitlines()
    files[2].write_text("\n".join(cut[:-1]) + "\n")  # footer lost: not complete
    lines.clear()
    run_bench(bench, tmp_path, jobs=1, progress=False, log=lines.append)
    assert lines[-1] == "ran 2 run(s), reused 2"
    reused = {line.split()[-1] for line in lines if line.startswith("  reused ")}
    assert reused == {files[0].stem, files[3].stem}
    for f in (files[0], files[3]):
        assert f.stat().st_mtime_ns == mtimes[f.name]  # untouched
    for f in (files[1], files[2]):
        assert comparable(read_run(f)[1]) == comparable(json.loads(x) for x in before[f.name].splitlines()[1:-1])
    assert not list(tmp_path.glob("runs/.*.tmp"))


def test_a_file_with_another_identity_is_not_reused(tmp_path):
    bench = parse_bench(SMALL)
    files = run_bench(bench, tmp_path, jobs=1, progress=False, log=_quiet)
    other = parse_bench(SMALL.replace("seeds = [0]", "seeds = [5]")).runs[0]
    fake = RunResult(other.run_id, [{"frame": 0}], [0], None, 0.0)
    write_run(run_file(tmp_path, bench.runs[0]), other, fake)  # right name, wrong digest inside
    lines = []
    run_bench(bench, tmp_path, jobs=1, progress=False, log=lines.append)
    assert lines[-1] == "ran 1 run(s), reused 3"
    assert read_run(files[0])[0]["digest"] == bench.runs[0].digest


def test_recordings_are_rerun_when_missing_and_skipped_per_group(tmp_path):
    bench = parse_bench("recordings = true\n" + SMALL)
    out = tmp_path / "out"
    run_bench(bench, out, jobs=1, progress=False, log=_quiet)
    assert sorted(p.stem for p in (out / "recordings").glob("*.mcap")) == sorted(r.run_id for r in bench.runs)
    # a run whose recording is missing is run again
    (out / "recordings" / f"{bench.runs[0].run_id}.mcap").unlink()
    lines = []
    run_bench(bench, out, jobs=1, progress=False, log=lines.append)
    assert lines[-1] == "ran 1 run(s), reused 3"
    # a group with recordings = false runs unrecorded, and its missing recordings do not make it run again
    quiet = parse_bench("recordings = true\n" + SMALL + "recordings = false\n")
    assert [r.digest for r in quiet.runs] == [r.digest for r in bench.runs]  # recording is not part of a run
    out2 = tmp_path / "out2"
    run_bench(quiet, out2, jobs=1, progress=False, log=_quiet)
    assert not (out2 / "recordings").exists() or not any((out2 / "recordings").iterdir())
    lines = []
    run_bench(quiet, out2, jobs=1, progress=False, log=lines.append)
    assert lines[-1] == "ran 0 run(s), reused 4"


def test_mcap_recordings_hold_every_scored_step_of_their_run(tmp_path):
    from starenv.record.mcap import read_metadata, read_steps

    bench = parse_bench("recordings = true\n" + SMALL.replace('"scenario", "lost_in_space"', '"scenario"'))
    assert bench.recorder == "starenv.record.mcap:McapRecorder"
    files = run_bench(bench, tmp_path, jobs=1, progress=False, log=_quiet)
    for run, path in zip(bench.runs, files, strict=True):
        rec = tmp_path / "recordings" / f"{run.run_id}.mcap"
        steps = read_run(path)[1]
        recorded = list(read_steps(rec))
        assert [d.frame for d in recorded] == [s["frame"] for s in steps]
        meta = read_metadata(rec)
        assert meta["starenv.run"]["seed"] == str(run.seed) and meta["starenv.outcome"]["status"] == "complete"


def test_killed_bench_resumes_where_it_stopped(tmp_path):
    text = SMALL.replace("steps = 3", "steps = 30")  # 4 runs, each long enough to be killed between two of them
    bench_file = _bench(tmp_path, text)
    out = tmp_path / "out"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    cmd = [sys.executable, "-m", "starenv.cli", "bench", str(bench_file), "--out", str(out), "--jobs", "1", "--quiet"]
    proc = subprocess.Popen(cmd, env=env, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 120
    while not list(out.glob("runs/*.jsonl")) and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.communicate()
    done = sorted(p.name for p in out.glob("runs/*.jsonl"))
    assert 1 <= len(done) < 4, "the bench finished before it could be killed: make its runs longer"
    again = subprocess.run(cmd, env=env, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert again.returncode == 0, again.stderr
    assert f"ran {4 - len(done)} run(s), reused {len(done)}" in again.stdout
    assert {line.split()[-1] + ".jsonl" for line in again.stdout.splitlines() if "  reused " in line} == set(done)
    assert f"report: {out / 'report.md'}" in again.stdout
    assert len(list(out.glob("runs/*.jsonl"))) == 4


# --- reports -------------------------------------------------------------------------------------------------------


def test_aggregate_statistics_match_hand_computed_values(tmp_path):
    runs = parse_bench(SMALL.replace("seeds = [0]", "seeds = [0, 1]")).runs
    group = [r for r in runs if r.pipeline.name == "scenario" and r.sweep_value == 4]
    assert len(group) == 2
    errors = [[1.0, 2.0, None], [3.0, 4.0, 5.0]]  # pooled over the two seeds: 1, 2, 3, 4, 5 (None: unavailable)
    for run, errs in zip(group, errors, strict=True):
        records = [{"frame": k, "attitude_error_arcsec": e, "within_threshold": float(e is not None and e < 3.5),
                    "solved": float(k == 0), "id_rate": 0.5 if k else 1.0, "latency_detector_ms": 10.0 * (k + 1)}
                   for k, e in enumerate(errs)]
        write_run(run_file(tmp_path, run), run, RunResult(run.run_id, records, [0], None, 1.0))
    rows = aggregate([run_file(tmp_path, r) for r in group])
    assert len(rows) == 1
    row = rows[0]
    assert (row["scenario"], row["sweep_key"], row["sweep_value"], row["pipeline"]) == (
        "paper_000", "motion.rate_dps about [1, 0, 0]", 4, "scenario")
    assert row["runs"] == 2 and row["steps"] == 6
    assert row["attitude_error_arcsec_median"] == 3.0
    assert row["attitude_error_arcsec_p95"] == pytest.approx(4.8)  # 0.95 * 4 = 3.8 -> 4 + 0.8 * (5 - 4)
    assert row["within_threshold"] == pytest.approx(3 / 6)  # 1, 2, 3 are under 3.5 arcsec
    assert row["solved"] == pytest.approx(2 / 6)
    assert row["fixed"] == pytest.approx(2 / 6)  # both first frames: solved and within (1 and 3 arcsec)
    assert row["id_rate_mean"] == pytest.approx((1.0 + 0.5 + 0.5) * 2 / 6)
    assert row["latency_detector_ms_median"] == 20.0
    assert row["latency_detector_ms_p95"] == pytest.approx(30.0)


def test_report_links_tables_and_plots_that_exist(tmp_path):
    bench = parse_bench(SMALL)
    files = run_bench(bench, tmp_path, jobs=1, progress=False, log=_quiet)
    report = write_report(bench, files, tmp_path)
    text = report.read_text()
    links = [part.split(")")[0] for part in text.split("](")[1:]]
    assert "summary.md" in links and "summary.csv" in links
    pngs = [link for link in links if link.endswith(".png")]
    # error, ID rate, availability and fixes vs rate for the one swept (scenario, key, axis), latency per role;
    # the datasheet figures and each pipeline's error series and spectra at the smallest swept rate (no plain case)
    assert sorted(Path(p).name for p in pngs) == [
        "paper_000-datasheet.png", "paper_000-latency.png", "paper_000-lost_in_space-spectrum.png",
        "paper_000-motion_rate_dps_about_1_0_0-availability.png",
        "paper_000-motion_rate_dps_about_1_0_0-error.png", "paper_000-motion_rate_dps_about_1_0_0-fixed.png",
        "paper_000-motion_rate_dps_about_1_0_0-id-rate.png", "paper_000-scenario-spectrum.png"]
    assert "## Working rate" in text and "### paper_000: motion.rate_dps about [1, 0, 0] (3 steps per rate)" in text
    for link in links:
        assert (tmp_path / link).exists(), link
    for p in pngs:
        assert (tmp_path / p).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    csv_lines = (tmp_path / "summary.csv").read_text().splitlines()
    assert len(csv_lines) == 1 + 4  # header + (2 rates x 2 pipelines)
    assert "attitude_error_arcsec_p95" in csv_lines[0] and "latency_detector_ms_median" in csv_lines[0]


def test_restoration_table_lists_only_cases_with_a_deblurrer():
    base = {"scenario": "paper_002", "sweep_key": None, "sweep_value": None, "runs": 1, "steps": 4}
    rows = [
        {**base, "pipeline": "tracking"},
        {**base, "pipeline": "roi_rl", "restoration_stars_before_median": 12.0, "restoration_stars_before_p95": 14.0,
         "restoration_stars_after_median": 15.0, "restoration_stars_after_p95": 16.5,
         "restoration_psnr_gain_db_median": 4.25, "restoration_psnr_gain_db_p95": 4.5},
    ]
    text = markdown_tables(rows)
    section = text[text.index("## Restoration"):]  # the last table: these rows carry no latency
    body = [line for line in section.splitlines() if line.startswith("| paper_002")]
    assert len(body) == 1 and "| roi_rl |" in body[0]
    assert "| 12 / 14 | 15 / 16.5 | 4.25 / 4.5 |" in body[0]
    assert "## Restoration" not in markdown_tables(rows[:1])
