"""The bench report's headline: the best pipeline per scenario and how far each pipeline keeps working in a sweep."""

from starenv.bench.report import headline, working_limit, working_rates


def case(scenario, pipeline, avail, err, lat, key="", value="", fixed=None):
    """A summary row; its share of fixes is its availability unless given."""
    return {"scenario": scenario, "sweep_key": key, "sweep_value": value, "pipeline": pipeline, "runs": 1, "steps": 10,
            "within_threshold": avail, "fixed": avail if fixed is None else fixed,
            "attitude_error_arcsec_median": err, "attitude_error_arcsec_p95": 2 * err,
            "latency_pipeline_ms_median": lat}


def test_working_limit_is_contiguous_from_the_smallest_value():
    rows = [case("s", "p", a, 1.0, 1.0, "motion.rate_dps", v) for v, a in ((10, 0.95), (0, 1.0), (5, 0.9), (15, 0.5),
                                                                             (20, 1.0))]
    assert working_limit(rows) == 10  # 20 passes again but 15 failed in between
    assert working_limit([case("s", "p", 0.5, 1.0, 1.0, "k", 0)]) is None


def with_interval(row, column, low, high):
    """The row with a 95 % interval on one of its columns."""
    row[column + "_ci_low"], row[column + "_ci_high"] = low, high
    return row


def test_headline_ranks_by_availability_then_error_and_ties_overlapping_intervals():
    def ranked(scenario, pipeline, avail, avail_ci, err, err_ci, lat, key="", value=""):
        row = case(scenario, pipeline, avail, err, lat, key, value)
        with_interval(row, "within_threshold", *avail_ci)
        return with_interval(row, "attitude_error_arcsec_median", *err_ci)

    rows = [
        # fast and slow overlap on both figures: a tie, whatever their latencies (slow's is the lower one)
        ranked("a", "fast", 1.0, (0.9, 1.0), 5.0, (4.0, 6.0), 10.0),
        ranked("a", "slow", 1.0, (0.9, 1.0), 5.5, (4.5, 6.5), 1.0),
        ranked("a", "sloppy", 1.0, (0.9, 1.0), 9.0, (8.0, 10.0), 1.0),  # error interval apart from fast's
        ranked("a", "lost", 0.5, (0.3, 0.7), 1.0, (0.5, 1.5), 1.0),  # availability interval apart
        *(case("a", "fast", av, 1.0, 1.0, "motion.rate_dps", v) for v, av in ((0, 1.0), (5, 0.8))),
        *(case("a", "slow", av, 1.0, 1.0, "motion.rate_dps", v) for v, av in ((0, 1.0), (5, 0.9))),
        # swept only: ranked at its smallest swept value, and y's error interval is apart from x's
        *(ranked("b", p, 0.7, (0.6, 0.8), e, ci, 1.0, "exposure_s", 0.01)
          for p, e, ci in (("x", 3.0, (2.8, 3.2)), ("y", 2.0, (1.9, 2.1)))),
        ranked("b", "x", 1.0, (0.99, 1.0), 0.1, (0.05, 0.15), 1.0, "exposure_s", 0.02),
        # one run each: no error interval tells them apart
        *(ranked("c", p, 1.0, (0.9, 1.0), e, (None, None), 1.0) for p, e in (("p", 1.0), ("q", 2.0))),
    ]
    table = {line.split(" | ")[0].strip("| "): line for line in headline(rows).splitlines() if line.startswith("| ")}
    assert table["a"] == ("| a | tie: fast, slow | 1 [0.9, 1] | 5 [4, 6] / 10 | 10 | "
                          "motion.rate_dps: slow 5 deg/s, fast 0 deg/s |")
    assert table["b"].startswith("| b | y (at exposure_s = 0.01) | 0.7 [0.6, 0.8] | 2 [1.9, 2.1] / 4 |")
    assert table["b"].endswith("exposure_s: x none, y none |")
    assert table["c"].startswith("| c | tie: p, q | 1 [0.9, 1] | 1 / 2 |")
    rows[1]["attitude_error_arcsec_median_ci_low"] = 6.5  # slow's interval now clears fast's: fast alone
    assert "| a | fast | " in headline(rows)


def test_working_rate_table_keeps_axes_apart_and_divides_by_the_same_pipeline_unrestored():
    about = "motion.rate_dps about [1, 0, 0]"
    rows = [case("s", p, a, 1.0, 1.0, about, v) for p, v, a in (
        ("blur", 0, 1.0), ("blur", 5, 0.95), ("blur", 10, 0.5),
        ("filter", 0, 1.0), ("filter", 5, 1.0), ("filter", 10, 1.0),
        ("fit", 0, 1.0), ("fit", 5, 0.9), ("fit", 10, 0.92))]
    rows += [case("s", "other", 0.2, 1.0, 1.0, "motion.rate_dps about [0, 1, 0]", 0)]
    for r in rows:
        r["pipeline_agents"] = {"blur": "A", "filter": "F", "fit": "A+D", "other": "A"}[r["pipeline"]]
        r["pipeline_unrestored"] = {"blur": "A", "filter": "F", "fit": "A", "other": "A"}[r["pipeline"]]
        if r["pipeline"] == "fit":
            r["restoration_stars_after_median"] = 10.0
    text = working_rates(rows)
    cells = {line.split(" | ")[0].strip("| "): line.strip("| ").split(" | ")
             for line in text.splitlines() if line.startswith("| ") and "pipeline" not in line}
    # fit works to 10 against its unrestored twin's 5 (not against the better "filter", a different pipeline)
    assert cells["fit"][:5] == ["fit", "yes", "10", "2.00 (blur)", "10"]
    assert cells["blur"][:5] == ["blur", "no", "5", "-", "5"] and cells["filter"][2] == "10"
    assert text.count("### s: ") == 2  # the Y-axis sweep is its own table
    assert working_rates([case("s", "p", 1.0, 1.0, 1.0, "exposure_s", 0.01)]) == ""


def test_a_filter_coasting_on_the_gyro_is_available_but_has_no_fix():
    """A filter available at every rate whose frames stop giving fixes at 10 deg/s works to 5 deg/s; the coasting
    shows in the "by availability" column only, and the cells are the shares of fixes."""
    about = "motion.rate_dps about [1, 0, 0]"
    rows = [case("s", "filter", 1.0, 1.0, 1.0, about, v, fixed) for v, fixed in ((0, 1.0), (5, 0.95), (10, 0.4))]
    for r in rows:
        r["pipeline_agents"] = r["pipeline_unrestored"] = "F"
    assert working_limit(rows) == 5 and working_limit(rows, "within_threshold") == 10
    line = next(x for x in working_rates(rows).splitlines() if x.startswith("| filter"))
    assert line.strip("| ").split(" | ") == ["filter", "no", "5", "-", "10", "1", "0.95", "0.4"]
