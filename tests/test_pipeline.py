"""The pipeline: plugging agents (instance, class, 'module:Class', scenario file, CLI) and end-to-end accuracy."""

import numpy as np
import pytest

from starenv import scenario as scenario_mod
from starenv.agents.pipeline import Pipeline, load_agent
from starenv.agents.solve.solvers import SvdSolver
from starenv.cli import main
from starenv.env import StarSensorEnv
from starenv.scoring import flatten, summarize


def run(env, pipeline, steps):
    obs, info = env.reset(seed=0)
    pipeline.reset(env.unwrapped.sensor_info)
    records, sources, latencies = [], [], []
    for _ in range(steps):
        action = pipeline(obs)
        sources.append((pipeline.report.source, bool(obs["frame_valid"].all())))
        latencies.append(dict(pipeline.report.latency_s))
        obs, _, _, _, info = env.step(action)
        records.append(flatten(info["scores"], pipeline.report.latency_s))
    return records, sources, latencies


def test_agents_plug_in_as_instance_class_or_string():
    assert isinstance(load_agent(SvdSolver(), "solver"), SvdSolver)
    assert isinstance(load_agent(SvdSolver, "solver"), SvdSolver)
    assert isinstance(load_agent("starenv.agents.solve:SvdSolver", "solver"), SvdSolver)
    tracking = load_agent("starenv.agents.identify:TrackingIdentifier", "identifier", gate_px=7.0)
    assert tracking.gate_px == 7.0
    assert load_agent(None, "deblurrer") is None


@pytest.mark.parametrize(
    ("spec", "role", "message"),
    [
        ("starenv.agents.solve.solvers.SvdSolver", "solver", "module:Class"),
        ("starenv.agents.nowhere:Thing", "solver", "cannot load"),
        ("starenv.agents.solve.solvers:Nothing", "solver", "cannot load"),
        ("starenv.agents.solve:SvdSolver", "detector", "StarDetector protocol"),
        ("starenv.agents.solve:SvdSolver", "painter", "unknown agent role"),
    ],
)
def test_bad_agents_are_refused_with_a_message(spec, role, message):
    with pytest.raises(ValueError, match=message):
        load_agent(spec, role)


def test_options_need_a_class():
    with pytest.raises(ValueError, match="options"):
        load_agent(SvdSolver(), "solver", tolerance=1)
    with pytest.raises(ValueError, match="unknown agent roles"):
        Pipeline(painter="x:y")


def test_scenario_pipeline_table_and_precedence():
    sc = scenario_mod.load("paper_000", {"pipeline.solver": "starenv.agents.solve:DavenportSolver",
                                         "pipeline.options.identifier.gate_px": 6.0, "pipeline.deblurrer": "none"})
    p = Pipeline.for_scenario(sc)
    described = p.describe()
    assert described["predictor"] == "starenv.agents.predict:FirstOrderPredictor"  # from paper_000.toml
    assert described["solver"] == "starenv.agents.solve:DavenportSolver"  # from the override
    assert p.agents["identifier"].gate_px == 6.0 and p.agents["deblurrer"] is None
    p = Pipeline.for_scenario(sc, {"solver": "starenv.agents.solve:SvdSolver"}, {"identifier": {"gate_px": 4.0}})
    assert p.describe()["solver"] == "starenv.agents.solve:SvdSolver" and p.agents["identifier"].gate_px == 4.0
    with pytest.raises(scenario_mod.ScenarioError, match=r"pipeline\.solver: expected 'module:Class'"):
        scenario_mod.load("paper_000", {"pipeline.solver": "SvdSolver"})
    with pytest.raises(scenario_mod.ScenarioError, match=r"pipeline\.painter: unknown key"):
        scenario_mod.load("paper_000", {"pipeline.painter": "a:b"})


def test_default_pipeline_tracks_paper_000_and_times_every_agent():
    env = StarSensorEnv("paper_000", {"lost_after_steps": 10**6})
    records, sources, latencies = run(env, Pipeline(), 30)
    s = summarize(records)
    assert s["within_threshold"]["mean"] == 1.0
    assert s["head0_cross_boresight_error_arcsec"]["median"] < 10.0
    assert s["solved"]["mean"] >= 0.9 and s["false_id_rate"]["mean"] == 0
    assert s["centroid_error_px_mean"]["median"] < 0.3
    assert s["prediction_error_px_mean"]["median"] < 0.5  # gyro-propagated star positions
    assert all(src == "solved" for src, _ in sources)
    for lat in latencies:
        assert {"predictor", "detector", "identifier", "solver", "pipeline"} <= set(lat)
        assert lat["pipeline"] >= lat["detector"] > 0


def test_predictor_carries_the_pipeline_through_dropped_frames():
    env = StarSensorEnv("paper_000", {"lost_after_steps": 10**6, "drops.probability": 0.4})
    records, sources, _ = run(env, Pipeline(), 40)
    dropped = [i for i, (_, valid) in enumerate(sources) if not valid]
    assert len(dropped) >= 8 and all(sources[i][0] == "predicted" for i in dropped if i > 0)
    errors = [records[i]["attitude_error_arcsec"] for i in dropped if i > 0]
    assert max(errors) < 100.0  # carried on the gyro, still within the availability threshold
    assert all(records[i]["prediction_error_px_mean"] is not None for i in dropped if i > 0)


def test_three_heads_are_solved_together():
    env = StarSensorEnv("paper_004", {"lost_after_steps": 10**6})
    records, sources, _ = run(env, Pipeline(), 6)
    assert all(src == "solved" for src, _ in sources)
    errors = np.array([r["attitude_error_arcsec"] for r in records])
    assert np.median(errors) < 30.0  # three orthogonal 6 deg heads: no weak roll axis


def test_cli_runs_a_pipeline_with_a_replaced_agent(capsys):
    assert main(["run", "paper_000", "--steps", "4", "--agent", "solver=starenv.agents.solve:SvdSolver"]) == 0
    out = capsys.readouterr().out
    assert "solver=starenv.agents.solve:SvdSolver" in out and "availability" in out and "latency_solver_ms" in out
    assert main(["run", "paper_000", "--steps", "2", "--agent", "solver=nowhere:Nothing"]) == 2
    assert "module 'nowhere' is outside starenv and not trusted" in capsys.readouterr().err
    assert main(["run", "paper_000", "--steps", "2", "--agent", "solver=nowhere:Nothing", "--trust", "nowhere"]) == 2
    assert "cannot load agent" in capsys.readouterr().err
