"""Hostile or careless input: files that cannot run code, results that cannot be silently wrong, crashes that lose
nothing.  Each case below was once accepted or crashed with a raw error; now it is refused with a message naming the
field (or recovered)."""

import gc
import json
import math
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
import tomllib
import tracemalloc
import warnings
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader

from starenv import cli
from starenv import scenario as scenario_mod
from starenv.agents.identify.lost_in_space import LostInSpaceIdentifier
from starenv.agents.pipeline import Pipeline, load_agent
from starenv.bench.runner import comparable, read_run, run_bench, run_file
from starenv.bench.spec import BenchError, parse_bench
from starenv.env import StarSensorEnv
from starenv.episode import run_episode
from starenv.record.mcap import McapRecorder, read_partial, read_steps, recover
from starenv.sim import sky

SMALL = {"heads.0.width": 128, "heads.0.height": 128}
BENCH = """
seeds = [0]
steps = 3
[[runs]]
scenario = "paper_000"
set = { "heads.0.width" = 128, "heads.0.height" = 128 }
"""

# --- files cannot run code -----------------------------------------------------------------------------------------

PROBE = '''
from pathlib import Path
Path(__file__).with_name("imported.marker").write_text("imported")


class Solver:
    """A valid solver (from a module outside starenv)."""

    def solve(self, body, inertial, weights=None):
        from starenv.agents.solve.solvers import SvdSolver
        return SvdSolver().solve(body, inertial, weights)


class NotASolver:
    """Constructing it leaves a marker: it must never be constructed."""

    def __init__(self, **options):
        Path(__file__).with_name("constructed.marker").write_text("constructed")

    def detect(self, image, camera):
        return None
'''


@pytest.fixture
def probe(tmp_path, monkeypatch):
    (tmp_path / "hardening_probe.py").write_text(PROBE)
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, "hardening_probe", raising=False)
    yield tmp_path
    sys.modules.pop("hardening_probe", None)


def test_a_scenario_cannot_run_a_command_through_an_agent(tmp_path, monkeypatch, capsys):
    marker = tmp_path / "X"
    data = tomllib.loads(scenario_mod.resolve("paper_000").read_text())
    data["pipeline"] = {"solver": "subprocess:Popen", "options": {"solver": {"args": ["touch", str(marker)]}}}
    path = tmp_path / "evil.toml"
    path.write_text(scenario_mod.dump_toml(data))
    with pytest.raises(ValueError, match="module 'subprocess' is outside starenv and not trusted"):
        Pipeline.for_scenario(scenario_mod.load(path))
    assert cli.main(["run", str(path), "--steps", "2"]) == 2
    assert "not trusted" in capsys.readouterr().err
    assert not marker.exists()


def test_a_bench_file_cannot_run_code_at_validation(tmp_path):
    marker = tmp_path / "X"
    text = BENCH.replace("[[runs]]", f'[pipelines.x]\nsolver = "subprocess:Popen"\n[pipelines.x.options.solver]\n'
                                      f'args = ["touch", "{marker}"]\n[[runs]]') + 'pipelines = ["x"]\n'
    with pytest.raises(BenchError, match="pipelines.x: solver: agent 'subprocess:Popen'"):
        parse_bench(text)
    with pytest.raises(BenchError, match="recordings: expected true, false.* got 'os:system'"):
        parse_bench('recordings = "os:system"\n' + BENCH)
    with pytest.raises(BenchError, match="trust: unknown key"):  # a file cannot grant trust itself
        parse_bench('trust = ["subprocess"]\n' + BENCH)
    assert not marker.exists()


def test_untrusted_modules_are_not_imported_and_trusted_ones_load(probe):
    with pytest.raises(ValueError, match="trust it explicitly"):
        load_agent("hardening_probe:Solver", "solver")
    assert not (probe / "imported.marker").exists()  # refused before import: no module code ran
    solver = load_agent("hardening_probe:Solver", "solver", trust=["hardening_probe"])
    assert type(solver).__name__ == "Solver" and (probe / "imported.marker").exists()


def test_a_class_is_checked_against_its_protocol_before_construction(probe):
    with pytest.raises(ValueError, match="NotASolver does not implement the AttitudeSolver protocol"):
        load_agent("hardening_probe:NotASolver", "solver", trust=["hardening_probe"], option=1)
    assert not (probe / "constructed.marker").exists()
    for spec, message in (("starenv.cli:main", "not a class"),
                          ("starenv.agents.solve.solvers:Rotation", "defined in 'scipy"),
                          ("starenv.agents.detect:CentroidDetector", "no method solve")):
        with pytest.raises(ValueError, match=message):
            load_agent(spec, "solver")


def test_agent_options_that_do_not_fit_the_class_are_a_clear_error(capsys):
    sc = scenario_mod.load("paper_000", {"pipeline.options.solver.bogus": 1})
    with pytest.raises(ValueError, match=r"solver: options \['bogus'\] do not fit QuestSolver"):
        Pipeline.for_scenario(sc)
    assert cli.main(["run", "paper_000", "--steps", "1", "--set", "pipeline.options.solver.bogus=1"]) == 2
    assert "do not fit QuestSolver" in capsys.readouterr().err


def test_cli_and_bench_trust_switches(probe, tmp_path, capsys):
    assert cli.main(["run", "paper_000", "--set", "heads.0.width=128", "--set", "heads.0.height=128", "--steps", "2",
                     "--agent", "solver=hardening_probe:Solver", "--trust", "hardening_probe"]) == 0
    assert "solver=hardening_probe:Solver" in capsys.readouterr().out
    text = BENCH.replace("[[runs]]", '[pipelines.x]\nsolver = "hardening_probe:Solver"\n[[runs]]') + \
        'pipelines = ["x"]\n'
    with pytest.raises(BenchError, match="not trusted"):
        parse_bench(text)
    bench = parse_bench(text, trust=("hardening_probe",))
    assert bench.runs[0].trust == ("hardening_probe",)
    with pytest.raises(ValueError, match="trust: expected module prefixes"):
        parse_bench(text, trust=("bad prefix!",))


# --- results cannot be silently wrong ------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def bench_out(tmp_path_factory):
    """A bench run once: its parsed bench and output folder (tests copy the folder)."""
    out = tmp_path_factory.mktemp("bench")
    bench = parse_bench(BENCH)
    run_bench(bench, out, jobs=1, progress=False, log=lambda *_: None)
    return bench, out


@pytest.mark.parametrize("edit", ["value", "empty object", "not json", "line removed", "header identity"])
def test_an_edited_run_file_is_recomputed_and_listed(bench_out, tmp_path, edit):
    bench, first = bench_out
    shutil.copytree(first, tmp_path, dirs_exist_ok=True)
    files = [run_file(tmp_path, r) for r in bench.runs]
    original = read_run(files[0])[1]
    lines = files[0].read_text().splitlines()
    if edit == "value":
        step = json.loads(lines[2])
        step["attitude_error_arcsec"] = 1e9
        lines[2] = json.dumps(step, sort_keys=True)
    elif edit == "empty object":
        lines[2] = "{}"
    elif edit == "header identity":
        header = json.loads(lines[0])
        header["identity"]["seed"] = 99
        lines[0] = json.dumps(header, sort_keys=True)
    elif edit == "not json":
        lines[2] = lines[2][:-5]
    else:
        del lines[2]
    files[0].write_text("\n".join(lines) + "\n")
    with pytest.raises(ValueError, match="not a complete run file|checksum|identity does not match"):
        read_run(files[0])
    log = []
    run_bench(bench, tmp_path, jobs=1, progress=False, log=log.append)
    assert any(line.startswith(f"  recomputing {bench.runs[0].run_id}: ") for line in log), log
    assert log[-1] == "ran 1 run(s), reused 0"
    assert comparable(read_run(run_file(tmp_path, bench.runs[0]))[1]) == comparable(original)


def _scenario(**overrides):
    return scenario_mod.load("paper_000", overrides)


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"motion.rate_dps": [1e4, 0, 0], "heads.0.width": 256}, "motion: expected star trails of at most 1024 px"),
        # 3000 deg/s x 10 ms x 2450 px/rad x (1 + tan^2 of the 512 px frame's corner, 1.0218) = 1311 px
        ({"motion.rate_dps": [3000, 0, 0]}, "at most 1024 px in one exposure, got 1311 px on heads.0"),
        ({"heads.0.width": 16384, "heads.0.height": 16384}, "heads: expected at most 33554432 pixels per step"),
        ({"duration_s": 1e7}, "duration_s: expected frames x pixels per frame <= 1e+12"),
        ({"mag_limit": 12.0, "motion.rate_dps": [1500, 0, 0]}, "stars in view x render instants <= 8388608"),
        ({"duration_s": 0.015}, "duration_s: expected at least two frame periods (>= 0.02 s"),
        # 500 Hz gyro / 0.001 Hz frames: 500001 samples per observation
        ({"frame_rate_hz": 0.001, "duration_s": 1e4}, "expected at most 262144 gyro samples per frame (frame_rate_hz"
                                                      " >= 0.00191 at gyro.rate_hz = 500), got 500001"),
        ({"motion.kind": "tumble", "motion.inertia_kgm2": [1e308, 1e308, 1e308]}, "each |value| <= 1e+12, got"),
    ],
)
def test_scenario_bounds_on_memory_and_time_name_their_limit(overrides, message):
    with pytest.raises(scenario_mod.ScenarioError, match=re.escape(message)):
        _scenario(**overrides)


def test_a_run_that_would_not_fit_fails_before_it_allocates():
    """The issue's case: 1e4 deg/s on a 256 px frame once asked for gigabytes; now the env refuses it at load."""
    tracemalloc.start()
    try:
        with pytest.raises(scenario_mod.ScenarioError, match="star trails of at most 1024 px"):
            StarSensorEnv("paper_000", {"motion.rate_dps": [1e4, 0, 0], "heads.0.width": 256, "heads.0.height": 256})
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 64 * 2**20


def test_trail_bound_is_the_renderers_own_image_speed_bound():
    """A rate just under the bound loads; the renderer's instant count for it is the bound's / max_step_px."""
    sc = _scenario()
    cam = sc.heads[0].camera
    px_per_rad = max(cam.fx, cam.fy) * (1.0 + math.tan(cam.half_diagonal) ** 2)
    rate_dps = math.degrees(1000.0 / (px_per_rad * sc.exposure_s))
    sc = _scenario(**{"motion.rate_dps": [0.0, 0.0, rate_dps]})
    with pytest.raises(scenario_mod.ScenarioError, match="got 1044"):
        _scenario(**{"motion.rate_dps": [0.0, 0.0, rate_dps * 1.044]})
    from starenv.sim.sensor import StarSensor

    renderer = StarSensor(sc).renderers[0]
    assert renderer._instants(sc.trajectory, 0.0, sc.exposure_s) == math.ceil(1000.0 / 0.5)


NONE_KEYS = ["exposure_s", "frame_rate_hz", "duration_s", "heads.0.width", "heads.0.focal_length_mm",
             "motion.rate_dps", "motion.initial_ra_deg", "seed", "gyro.rate_hz", "pipeline", "heads.0.detector"]


@pytest.mark.parametrize("key", NONE_KEYS)
def test_none_is_refused_for_every_key(key):
    with pytest.raises(scenario_mod.ScenarioError, match=rf"{key.replace('.', '[.]')}: expected .*, got None$"):
        _scenario(**{key: None})


@pytest.mark.parametrize(("key", "value"), [("seed", "1"), ("gyro.rate_hz", [500]), ("heads.0.width", 256.0),
                                            ("motion.rate_dps", [1, 2]), ("description", 5)])
def test_wrong_types_are_refused_with_expected_and_got(key, value):
    with pytest.raises(scenario_mod.ScenarioError, match=rf"{key.replace('.', '[.]')}: expected .*, got "):
        _scenario(**{key: value})


def test_render_refuses_a_frame_outside_the_scenario(capsys):
    assert cli.main(["render", "paper_000", "--frame", "1500"]) == 2  # 15 s at 100 Hz: frames 0 .. 1499
    assert "--frame 1500: expected an integer in [0, 1499] (paper_000 has 1500 frames)" in capsys.readouterr().err


# --- crashes lose nothing ------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def killed(tmp_path_factory):
    """A finished recording and the same file cut at 60 %: what a killed run leaves (header, metadata, complete
    chunks, then a chunk cut short)."""
    tmp = tmp_path_factory.mktemp("killed")
    finished = tmp / "run.mcap"
    env = StarSensorEnv("paper_000", SMALL)
    run_episode(env, Pipeline.for_scenario(env.scenario), seed=1, steps=12,
                observers=[McapRecorder(finished, chunk_size=1 << 14)])
    data = finished.read_bytes()
    partial = tmp / "killed.mcap.partial"
    partial.write_bytes(data[: int(len(data) * 0.6)])
    return finished, partial


def test_recover_writes_a_finished_mcap_of_the_complete_steps(killed, tmp_path, capsys):
    finished, partial = killed
    with pytest.raises(Exception):  # noqa: B017  the plain reader refuses an unfinished file
        with open(partial, "rb") as f:
            list(make_reader(f).iter_messages())
    out = tmp_path / "recovered.mcap"
    assert cli.main(["recover", str(partial), "--out", str(out)]) == 0
    assert "complete steps recovered" in capsys.readouterr().out
    with open(out, "rb") as f:  # the plain mcap library reads it, summary and all
        reader = make_reader(f)
        summary = reader.get_summary()
        topics = [channel.topic for _, channel, _ in reader.iter_messages()]
    assert summary.statistics.message_count == len(topics)
    steps = list(read_steps(out))
    whole = list(read_steps(finished))
    assert 1 <= len(steps) < len(whole)
    assert [s.frame for s in steps] == list(range(len(steps)))
    for a, b in zip(steps, whole, strict=False):
        assert a.record == b.record and np.array_equal(a.heads[0].image, b.heads[0].image)
    assert read_partial(partial)["/gyro"] == len(steps)  # every complete chunk's steps, no more
    with open(out, "rb") as f:
        meta = {m.name: dict(m.metadata) for m in make_reader(f).iter_metadata()}
    assert meta["starenv.outcome"]["status"] == "recovered" and meta["starenv.outcome"]["steps"] == str(len(steps))
    assert f"--steps {len(steps)}" in meta["starenv.outcome"]["reproduce"]


@pytest.mark.skipif(shutil.which("rerun") is None, reason="the rerun CLI (rerun-sdk) is not installed")
def test_rerun_opens_the_recovered_mcap(killed, tmp_path):
    """Rerun's own MCAP importer checks and converts the recovered file (the unfinished one it refuses)."""
    _, partial = killed
    out = tmp_path / "recovered.mcap"
    recover(partial, out)
    env = {**os.environ, "CI": "1"}
    check = subprocess.run(["rerun", "mcap", "check", str(out)], capture_output=True, text=True, timeout=120, env=env)
    assert check.returncode == 0 and "error" not in check.stdout, check.stdout + check.stderr
    conv = subprocess.run(["rerun", "mcap", "convert", str(out), "-o", str(tmp_path / "r.rrd")], capture_output=True,
                          text=True, timeout=120, env=env)
    assert conv.returncode == 0 and (tmp_path / "r.rrd").stat().st_size > 0, conv.stderr


def test_view_reviews_a_partial_recording_saying_so(killed, tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("CI", "1")
    _, partial = killed
    rrd = tmp_path / "review.rrd"
    assert cli.main(["view", str(partial), "--rrd", str(rrd)]) == 0
    out = capsys.readouterr().out
    assert "is unfinished: reviewing its" in out and "recovered" in out and rrd.stat().st_size > 0
    cut = tmp_path / "renamed.mcap"  # an unfinished file under a finished name is detected too (no closing magic)
    cut.write_bytes(partial.read_bytes())
    assert cli.main(["view", str(cut), "--rrd", str(tmp_path / "cut.rrd")]) == 0
    assert "is unfinished: reviewing its" in capsys.readouterr().out
    with pytest.raises(ValueError, match="unfinished .* 'starenv recover'"):
        list(read_steps(cut))
    assert cli.main(["recover", str(partial)]) == 0  # default output: the name without .partial
    assert (partial.parent / "killed.mcap").is_file()
    assert cli.main(["recover", str(partial)]) == 2  # never overwrites
    assert "exists" in capsys.readouterr().err


# --- the env refuses bad input naming the key ----------------------------------------------------------------------


@pytest.fixture(scope="module")
def env():
    return StarSensorEnv("paper_000", {**SMALL, "duration_s": 0.03})  # 3 frames: 2 scored steps


@pytest.mark.parametrize(
    ("action", "message"),
    [
        ({"attitude": [[0, 0], [0]]}, r"action\['attitude'\] must be an array of shape \(4,\)"),
        ({1: 2}, "action keys must be strings, got 1"),
        ({"attitude": "abcd"}, r"action\['attitude'\] must hold real numbers"),
        ({"attitude": [0.0, 0.0, 0.0, 0.0]}, "non-zero norm"),
        ({"attitude": [1.0, 0.0, 0.0, float("inf")]}, "finite"),
        ({"attitude_valid": 2}, "0 or 1"),
    ],
)
def test_env_refuses_bad_actions_naming_the_key(env, action, message):
    env.reset(seed=0)
    with pytest.raises(ValueError, match=message):
        env.step(action)


def test_env_accepts_a_huge_quaternion_as_its_direction(env):
    _, info = env.reset(seed=0)
    q = np.asarray(info["truth"]["attitude"])
    _, _, _, _, big = env.step({"attitude": (q * 1e200).tolist()})
    env.reset(seed=0)
    _, _, _, _, unit = env.step({"attitude": q})
    assert big["scores"]["attitude"]["total_arcsec"] == pytest.approx(unit["scores"]["attitude"]["total_arcsec"],
                                                                       abs=1e-6)


@pytest.mark.parametrize("scenario", [None, 123, 1.5, ["paper_000"]])
def test_env_constructor_names_the_scenario(scenario):
    with pytest.raises(ValueError, match="scenario: expected a bundled scenario name"):
        StarSensorEnv(scenario)


def test_env_seeds_options_and_the_episode_end(env):
    a, _ = env.reset(seed=np.int64(7))
    b, _ = env.reset(seed=7)
    assert np.array_equal(a["frames"], b["frames"])
    for seed in (-1, 2**63, 1.5, True, "3"):
        with pytest.raises(ValueError, match="seed: expected None or an integer"):
            env.reset(seed=seed)
    with pytest.raises(ValueError, match="reset options: StarSensorEnv takes none"):
        env.reset(options={"difficulty": 3})
    env.reset(seed=0, options={})
    assert env.step(None)[3] is False
    assert env.step(None)[3] is True  # truncated: the last frame was scored
    with pytest.raises(gym.error.ResetNeeded, match="call reset"):
        env.step(None)
    env.reset(seed=0)
    env.step(None)  # a reset starts a new episode


# --- caches --------------------------------------------------------------------------------------------------------


@pytest.fixture
def own_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("STARENV_CACHE_DIR", str(tmp_path))
    sky.clear_memory_cache()
    yield tmp_path
    sky.clear_memory_cache()


def _rewrite_npz(path: Path, change) -> None:
    """Rewrite a cache file as a valid .npz with one array changed and its stored hash kept."""
    with np.load(path, allow_pickle=False) as stored:
        arrays = {k: stored[k].copy() for k in stored.files}
    change(arrays)
    with open(path, "wb") as f:
        np.savez(f, **arrays)


def test_an_altered_catalogue_cache_is_rebuilt(own_cache):
    truth = sky.hipparcos_table()
    (file,) = own_cache.glob("hip2-*.npz")

    def shift(arrays):
        arrays["ra"] = arrays["ra"] + 1e-3
    _rewrite_npz(file, shift)
    sky.clear_memory_cache()
    again = sky.hipparcos_table()
    assert np.array_equal(again.ra, truth.ra)
    assert sky.load_npz_checked(file) is not None  # rewritten intact


@pytest.mark.parametrize("damage", ["altered", "truncated"])
def test_a_damaged_pattern_database_is_rebuilt_without_warnings(own_cache, damage):
    catalog = sky.load_catalog(5.0, 2026.0)
    cameras = StarSensorEnv("paper_002").cameras
    built = LostInSpaceIdentifier(pattern_stars_per_region=4)
    built.reset(cameras, catalog)
    path = built.database.path
    if damage == "altered":
        def swap(arrays):
            arrays["patterns"] = arrays["patterns"][::-1].copy()  # still valid-looking, wrong patterns
        _rewrite_npz(path, swap)
    else:
        path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a ResourceWarning (unclosed file) would fail here
        rebuilt = LostInSpaceIdentifier(pattern_stars_per_region=4)
        rebuilt.reset(cameras, catalog)
        gc.collect()
    assert not rebuilt.database.from_cache
    assert np.array_equal(rebuilt.database.patterns, built.database.patterns)


# --- fuzz: clear error or success, never another exception, never > 2 GB ---------------------------------------------

SCENARIO_KEYS = ["seed", "duration_s", "frame_rate_hz", "exposure_s", "mag_limit", "epoch", "lost_after_steps",
                 "motion.kind", "motion.rate_dps", "motion.initial_ra_deg", "motion.jitter", "gyro.rate_hz",
                 "gyro.arw_deg_rthr", "drops.probability", "heads", "heads.0", "heads.0.width", "heads.0.height",
                 "heads.0.focal_length_mm", "heads.0.psf_sigma_px", "heads.0.distortion.kind",
                 "heads.0.detector.line_time_s", "heads.0.mounting_matrix", "pipeline.solver", "pipeline.options",
                 "motion.segments", "frobnicate", "heads.7.width", "motion.rate_dps.1"]
scalars = st.one_of(st.none(), st.booleans(), st.integers(-10**20, 10**20),
                    st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=8))
values = st.recursive(scalars, lambda inner: st.one_of(st.lists(inner, max_size=4),
                                                       st.dictionaries(st.text(max_size=6), inner, max_size=3)),
                      max_leaves=8)
OK_ERRORS = (ValueError,)  # ScenarioError, BenchError and the env's errors are ValueErrors


@pytest.fixture(autouse=True)
def under_2_gb(request):
    """Fuzz tests: the peak of Python and numpy allocations (tracemalloc) during the test stays under 2 GiB."""
    if not request.node.name.startswith("test_fuzz_"):
        yield
        return
    tracemalloc.start()
    try:
        yield
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 2 * 1024**3, f"{peak / 2**30:.2f} GiB"


PAPER_000 = tomllib.loads(scenario_mod.resolve("paper_000").read_text())
REMOVABLE = ["duration_s", "exposure_s", "motion", "motion.kind", "motion.rate_dps", "heads", "heads.0.width",
             "heads.0.distortion.kind", "gyro", "name"]


def _without(data: dict, dotted: str) -> dict:
    node = data
    *parents, last = dotted.split(".")
    for part in parents:
        node = node[int(part)] if isinstance(node, list) else node.get(part, {})
    if isinstance(node, dict):
        node.pop(last, None)
    return data


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(removed=st.lists(st.sampled_from(REMOVABLE), max_size=2),
       overrides=st.dictionaries(st.sampled_from(SCENARIO_KEYS), values, max_size=3))
def test_fuzz_scenario_files(removed, overrides):
    """A scenario file (paper_000 written back as TOML, keys removed) loaded with overrides of any type."""
    data = json.loads(json.dumps(PAPER_000))
    for key in removed:
        _without(data, key)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "fuzz.toml"
        path.write_text(scenario_mod.dump_toml(data))
        try:
            sc = scenario_mod.load(path, overrides)
        except OK_ERRORS:
            return
    assert sum(h.camera.width * h.camera.height for h in sc.heads) <= scenario_mod.MAX_FRAME_PIXELS
    assert sc.n_steps >= 2


ACTION_KEYS = ["attitude", "attitude_valid", "detections_xy", "detection_mask", "catalog_ids", "predicted_xy",
               "predicted_ids", "prediction_mask", "other"]
arrays = st.one_of(values, st.builds(lambda shape, x: np.full(shape, x), st.sampled_from([(), (4,), (1, 256),
                                                                                           (1, 256, 2), (2, 3)]),
                                     st.one_of(st.integers(-3, 3), st.floats(allow_nan=True, width=32))))


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(action=st.one_of(values, st.dictionaries(st.one_of(st.sampled_from(ACTION_KEYS), st.integers(0, 2)),
                                                arrays, max_size=4)))
def test_fuzz_actions(env, action):
    env.reset(seed=0)
    try:
        env.step(action)
    except OK_ERRORS:
        pass


BENCH_LINES = ['seeds = [0]', 'seeds = [-1]', 'seeds = []', 'steps = 2', 'steps = 0', 'recordings = true',
               'recordings = "x:y"', 'name = 3', '[pipelines.p]', 'solver = "starenv.agents.solve:SvdSolver"',
               'solver = "os:system"', 'identifier = "none"', '[pipelines.p.options.solver]', 'x = 1',
               '[[runs]]', 'scenario = "paper_000"', 'scenario = "nowhere"', 'scenario = 5', 'pipelines = ["p"]',
               'pipelines = ["scenario"]', 'set = { "heads.0.width" = 128, "heads.0.height" = 128 }',
               'set = { "motion.rate_dps" = [1e4, 0, 0] }', 'sweep = { key = "seed", values = [1, 2] }',
               'sweep = { key = "motion.rate_dps", axis = [0, 0, 0], values = [1] }',
               'sweep = { key = "exposure_s", start = 0, stop = 1, step = 1e-9 }', 'steps = "3"', 'x = {',
               'seeds = [0, 0]']


@settings(max_examples=40, deadline=None)
@given(lines=st.lists(st.sampled_from(BENCH_LINES), max_size=8))
def test_fuzz_bench_files(lines):
    try:
        parse_bench("\n".join(lines), check=False)
    except OK_ERRORS:
        pass




# --- fuzzing the files starenv reads besides scenarios and benches -------------------------------------------------
# Each case: only ValueError (RecordingError, DatasetError, ... are ValueErrors) escapes, within CASE_SECONDS, and the
# traced peak stays under 2 GiB (``under_2_gb``).  The files are small, so the bound on time is generous: a case
# that hits an unbounded loop or allocation (the bugs these tests look for) takes minutes, not seconds.
CASE_SECONDS = 20.0


class Blob(bytes):
    """File contents that hypothesis's reports name instead of printing."""

    def __repr__(self) -> str:
        return f"<{len(self)} bytes>"


@pytest.fixture(scope="module")
def small_recording(tmp_path_factory):
    """A finished recording of three small steps, in chunks of 4 KiB (many chunks, many record boundaries)."""
    path = tmp_path_factory.mktemp("fuzz_mcap") / "run.mcap"
    env = StarSensorEnv("paper_000", SMALL)
    run_episode(env, Pipeline.for_scenario(env.scenario), seed=0, steps=3,
                observers=[McapRecorder(path, chunk_size=1 << 12)])
    return Blob(path.read_bytes())


def _mutate(data: bytes, flips, cut, insert) -> bytes:
    out = bytearray(data)
    for where, mask in flips:
        out[int(where * (len(out) - 1))] ^= mask
    if insert is not None:
        where, blob = insert
        at = int(where * len(out))
        out[at:at] = blob
    if cut is not None:
        del out[int(cut * len(out)):]
    return bytes(out)


mutations = dict(flips=st.lists(st.tuples(st.floats(0, 1), st.integers(1, 255)), max_size=3),
                 cut=st.one_of(st.none(), st.floats(0, 1)),
                 insert=st.one_of(st.none(), st.tuples(st.floats(0, 1), st.binary(min_size=1, max_size=24))))


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(**mutations)
def test_fuzz_recordings(small_recording, flips, cut, insert):
    """A recording with bytes flipped, inserted or cut off, read finished (metadata, steps) and as a killed run's
    partial file (read_partial, recover)."""
    from starenv.record.mcap import read_metadata

    data = _mutate(small_recording, flips, cut, insert)
    with tempfile.TemporaryDirectory() as tmp:
        finished, partial = Path(tmp) / "f.mcap", Path(tmp) / "f.mcap.partial"
        finished.write_bytes(data)
        partial.write_bytes(data)
        t0 = time.perf_counter()
        for read in (lambda: read_metadata(finished), lambda: list(read_steps(finished)),
                     lambda: read_partial(partial), lambda: recover(partial, Path(tmp) / "out.mcap", replace=True)):
            try:
                read()
            except OK_ERRORS:
                pass
        assert time.perf_counter() - t0 < CASE_SECONDS


@pytest.fixture(scope="module")
def shipped_weights():
    from starenv.agents.identify.network import DEFAULT_WEIGHTS

    manifest = json.loads((DEFAULT_WEIGHTS / "manifest.json").read_text())
    return manifest, Blob((DEFAULT_WEIGHTS / "weights.pt").read_bytes())


MANIFEST_KEYS = ["config", "config.n_classes", "config.input_size", "config.widths", "config.widths.2", "config.depth",
                 "config.heads", "config.head_dim", "config.mlp_dim", "config.scale_dn", "classes_hip",
                 "classes_hip.0", "camera", "camera.fov_deg", "camera.fov_deg.0", "weights_sha256",
                 "identity_sha256"]


def _set(data: dict, dotted: str, value) -> None:
    node = data
    *parents, last = dotted.split(".")
    for part in parents:
        if isinstance(node, list) and not (part.isdigit() and int(part) < len(node)):
            return
        node = node[int(part)] if isinstance(node, list) else node.get(part)
        if not isinstance(node, dict | list):
            return
    if isinstance(node, list):
        if last.isdigit() and int(last) < len(node):
            node[int(last)] = value
    else:
        node[last] = value


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(edits=st.dictionaries(st.sampled_from(MANIFEST_KEYS), values, max_size=3), forge=st.booleans(), **mutations)
def test_fuzz_weights_and_manifests(shipped_weights, edits, forge, flips, cut, insert):
    """The shipped run folder with manifest values of any type and weights bytes changed; ``forge``: the hashes
    recomputed after the change (a forger's folder), so the checks behind them are reached too."""
    from starenv.agents.identify.network import load_network, manifest_hashes

    manifest, weights = json.loads(json.dumps(shipped_weights[0])), shipped_weights[1]
    for key, value in edits.items():
        _set(manifest, key, value)
    weights = _mutate(weights, flips, cut, insert)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        if forge:
            try:
                manifest.update(manifest_hashes(manifest, weights))
            except (KeyError, TypeError, ValueError):  # a manifest without the keys the hash covers
                pass
        (folder / "manifest.json").write_text(json.dumps(manifest))
        (folder / "weights.pt").write_bytes(weights)
        t0 = time.perf_counter()
        try:
            load_network(folder)
        except OK_ERRORS:
            pass
        assert time.perf_counter() - t0 < CASE_SECONDS


@pytest.fixture(scope="module")
def small_dataset(tmp_path_factory):
    """A built main_star dataset of two shards of two 64 px samples: its spec and its files' bytes."""
    from starenv.datasets import build_dataset, load_spec

    spec = load_spec({"name": "tiny", "kind": "main_star", "scenario": "paper_002", "samples": 4, "shard_size": 2,
                      "overrides": {"heads.0.width": 64, "heads.0.height": 64},
                      "pointing": {"center_ra_deg": 83.8, "center_dec_deg": -5.4, "radius_deg": 10.0}})
    out = tmp_path_factory.mktemp("fuzz_data")
    build_dataset(spec, out, jobs=1, progress=False, log=lambda *_: None)
    return spec.name, {p.name: Blob(p.read_bytes()) for p in out.iterdir()}


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(target=st.sampled_from(["shard-00001.npz", "dataset.json", "shards.json"]), forge=st.booleans(), **mutations)
def test_fuzz_shards(small_dataset, target, forge, flips, cut, insert):
    """A dataset with one of its files' bytes changed, read for training (every shard) and resumed by a build;
    ``forge``: a changed shard's new hash recorded in shards.json, so the parser behind the hash check is reached."""
    import hashlib

    from starenv.agents.identify.network_data import ShardDataset
    from starenv.datasets import build_dataset, load_spec
    from starenv.datasets.shards import INDEX

    _, files = small_dataset
    spec = load_spec(json.loads(files["dataset.json"])["spec"])
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        for name, data in files.items():
            (out / name).write_bytes(data)
        changed = _mutate(files[target], flips, cut, insert)
        (out / target).write_bytes(changed)
        if forge and target.endswith(".npz"):
            index = json.loads(files[INDEX])
            index["sha256"][target] = hashlib.sha256(changed).hexdigest()
            (out / INDEX).write_text(json.dumps(index))
        t0 = time.perf_counter()
        try:
            dataset = ShardDataset(out)
            for shard in range(dataset.n_shards):
                dataset.shard(shard)
        except OK_ERRORS:
            pass
        try:
            build_dataset(spec, out, jobs=1, progress=False, log=lambda *_: None)
        except OK_ERRORS:
            pass
        else:  # a build that went through leaves every shard as a fresh build writes it, unless a forger recorded
            # the hash of a changed shard whose meta still fits (only building it again would tell)
            assert forge or all((out / n).read_bytes() == d for n, d in files.items() if n.endswith(".npz"))
        assert time.perf_counter() - t0 < CASE_SECONDS


def test_a_bench_run_longer_than_its_scenario_or_absurdly_long_is_refused_by_name():
    """steps = 2**63 (or any run past the scenario's last frame) would fail or end early mid-bench; both are one
    error naming the key before anything runs."""
    from starenv.bench.spec import BenchError, parse_bench

    body = 'name = "b"\nseeds = [0]\nsteps = {steps}\n[[runs]]\nscenario = "paper_000"\npipelines = ["tracking"]\n'
    with pytest.raises(BenchError, match=r"b\.toml: steps: expected an integer in \[1, 1e\+07\]"):
        parse_bench(body.format(steps=2**63), "b.toml")
    with pytest.raises(BenchError, match=r"runs\.0\.steps: expected at most \d+ \(the frames of paper_000"):
        parse_bench(body.format(steps=10**6), "b.toml")


def test_a_gain_that_would_saturate_every_pixel_and_too_many_segments_are_refused():
    """gain_e_per_dn = 1e-300 turns one electron into 1e300 DN (frames of only 0 and full scale): the gain must be a
    camera's (>= 1e-3 e-/DN); a sequence motion's segments are each built at load, so their count is bounded."""
    from starenv import scenario

    with pytest.raises(scenario.ScenarioError, match=r"heads\.0\.detector\.gain_e_per_dn: .*\[0\.001, 10000\]"):
        scenario.load("paper_000", {"heads.0.detector.gain_e_per_dn": 1e-300})
    segments = [{"kind": "constant_rate", "rate_dps": [0, 0, 0.1], "duration_s": 1.0}] * (scenario.MAX_SEGMENTS + 1)
    motion = {"kind": "sequence", "initial_ra_deg": 0.0, "initial_dec_deg": 0.0, "initial_roll_deg": 0.0,
              "segments": segments}
    with pytest.raises(scenario.ScenarioError, match=rf"motion\.segments: expected at most {scenario.MAX_SEGMENTS}"):
        scenario.load("paper_000", {"motion": motion})
