"""``starenv run``'s summary: the episode's figures in a star-tracker datasheet's terms, from its own records."""

import math

import pytest

from starenv import cli
from starenv.agents.pipeline import Pipeline
from starenv.datasheet import acquisition_times, binomial_interval, error_split
from starenv.env import StarSensorEnv
from starenv.episode import run_episode

STEPS, SEED = 8, 2
AXES = {"head0 x": "head0_error_x_arcsec", "head1 roll": "head1_error_roll_arcsec", "head2 y": "head2_error_y_arcsec",
        "body z": "body_error_z_arcsec"}


def test_the_run_summary_prints_each_axis_split_availability_and_acquisition(capsys):
    """The same episode run here (seed, steps, the scenario's pipeline): each printed axis row is
    ``starenv.datasheet.error_split`` of that record key (printed to 4 significant digits: a relative rounding of at
    most 5e-4), the availability its share with the Clopper-Pearson interval, the acquisition its first fix."""
    assert cli.main(["run", "paper_004", "--steps", str(STEPS), "--seed", str(SEED), "--quiet"]) == 0
    out = capsys.readouterr().out
    env = StarSensorEnv("paper_004")
    records = run_episode(env, Pipeline.for_scenario(env.scenario), seed=SEED, steps=STEPS).records
    rows = {" ".join(line.split()[:2]): line.split()[2:] for line in out.splitlines()
            if line.startswith(("    head", "    body"))}
    assert len(rows) == 3 * 3 + 3  # three heads' x, y, roll and the body's x, y, z
    for label, key in AXES.items():
        split = error_split([math.nan if r[key] is None else r[key] for r in records])
        assert [float(v) for v in rows[label]] == pytest.approx(
            [split["bias"], split["nea"], split["total_3s"]], rel=5e-4)
    within = sum(r["within_threshold"] == 1.0 for r in records)
    low, high = binomial_interval(within, STEPS)
    threshold = env.scenario.availability_threshold_arcsec.describe()
    assert f"({threshold}): {within / STEPS:.3f} (95% interval {low:.3f}-{high:.3f}" in out
    first = acquisition_times([r["fixed"] == 1.0 for r in records], [r["time_s"] for r in records])["first"]
    assert f"{first[0]:.3g} s after the first frame" in out
