"""The bench report's headline: the best pipeline per scenario and how far each pipeline keeps working in a sweep."""

from starenv.bench.report import headline, working_limit


def case(scenario, pipeline, avail, err, lat, key="", value=""):
    return {"scenario": scenario, "sweep_key": key, "sweep_value": value, "pipeline": pipeline, "runs": 1, "steps": 10,
            "within_threshold": avail, "attitude_error_arcsec_median": err, "attitude_error_arcsec_p95": 2 * err,
            "latency_pipeline_ms_median": lat}


def test_working_limit_is_contiguous_from_the_smallest_value():
    rows = [case("s", "p", a, 1.0, 1.0, "motion.rate_dps", v) for v, a in ((10, 0.95), (0, 1.0), (5, 0.9), (15, 0.5),
                                                                             (20, 1.0))]
    assert working_limit(rows) == 10  # 20 passes again but 15 failed in between
    assert working_limit([case("s", "p", 0.5, 1.0, 1.0, "k", 0)]) is None


def test_headline_picks_by_availability_then_error_then_latency():
    rows = [case("a", "fast", 1.0, 5.0, 10.0), case("a", "slow", 1.0, 5.0, 90.0), case("a", "sloppy", 1.0, 9.0, 1.0),
            case("a", "lost", 0.5, 1.0, 1.0),
            *(case("a", "fast", av, 1.0, 1.0, "motion.rate_dps", v) for v, av in ((0, 1.0), (5, 0.8))),
            *(case("a", "slow", av, 1.0, 1.0, "motion.rate_dps", v) for v, av in ((0, 1.0), (5, 0.9))),
            *(case("b", p, av, e, 1.0, "exposure_s", 0.01) for p, av, e in (("x", 0.7, 3.0), ("y", 0.7, 2.0)))]
    table = {line.split(" | ")[0].strip("| "): line for line in headline(rows).splitlines() if line.startswith("| ")}
    assert table["a"] == ("| a | fast | 1 | 5 / 10 | 10 | motion.rate_dps: slow 5 deg/s, fast 0 deg/s |")
    assert table["b"].startswith("| b | y (exposure_s = 0.01) | 0.7 | 2 / 4 |")
    assert table["b"].endswith("exposure_s: x none, y none |")
