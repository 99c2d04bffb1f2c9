"""The one config engine: typed tables naming ``file: dotted.key``, dotted overrides, the TOML writer, and the one
place pipeline choices merge -- shared by scenarios, bench files and dataset specs."""

import tomllib

import pytest
from hypothesis import given
from hypothesis import strategies as st

from starenv import scenario as scenario_mod
from starenv.agents.pipeline import MOVED, Pipeline, load_agent
from starenv.bench.spec import BenchError, parse_bench
from starenv.config import ConfigError, Table, apply_override, dump_toml
from starenv.datasets import DatasetError, load_spec
from starenv.scenario import PipelineSpec, ScenarioError


def test_table_errors_name_the_file_and_the_dotted_key():
    top = Table({"heads": [{"width": "wide"}]}, "", "f.toml", ScenarioError)
    head = top.tables("heads")[0]
    expected = r"^f\.toml: heads\.0\.width: expected an integer in \[8, 64\], got 'wide'$"
    with pytest.raises(ScenarioError, match=expected):
        head.number("width", low=8, high=64, integer=True)
    with pytest.raises(ScenarioError, match=r"^f\.toml: heads\.0\.height: expected a number in \[-inf, inf\], "
                                            r"it is missing$"):
        head.number("height")
    head.data["colour"] = 1
    with pytest.raises(ScenarioError, match=r"heads\.0\.colour: unknown key \(allowed here: height, width\)"):
        head.finish()


def test_scenarios_bench_files_and_dataset_specs_fail_the_same_way(tmp_path):
    assert all(issubclass(e, ConfigError) for e in (ScenarioError, BenchError, DatasetError))
    expected = r"paper_000\.toml: frame_rate_hz: expected a number in \(0, 1000\], got -1"
    with pytest.raises(ScenarioError, match=expected):
        scenario_mod.load("paper_000", {"frame_rate_hz": -1})
    bench = '[[runs]]\nscenario = "paper_000"\n[pipelines.x]\nsolver = 3\n'
    with pytest.raises(BenchError, match=r"b\.toml: pipelines\.x\.solver: expected a string, got 3"):
        parse_bench(bench, "b.toml", check=False)
    spec = tmp_path / "d.toml"
    spec.write_text('kind = "main_star"\nscenario = "paper_002"\nsamples = 4\n[rates]\nroll_dps = [0.0, 2000.0]\n')
    with pytest.raises(DatasetError, match=r"d\.toml: rates\.roll_dps: expected a non-empty list of numbers in "
                                           r"\[-1000, 1000\], got \[0\.0, 2000\.0\]$"):
        load_spec(spec)
    spec.write_text('kind = "main_star"\nscenario = "paper_002"\nsamples = 4\n[stars]\ncolour = 1\n')
    with pytest.raises(DatasetError, match=r"d\.toml: stars\.colour: unknown key"):
        load_spec(spec)


def test_overrides_reach_tables_and_array_items_and_refuse_what_is_not_there():
    data = {"heads": [{"width": 512}], "motion": {}}
    apply_override(data, "heads.0.width", 256, "s")
    apply_override(data, "motion.rate_dps", [0, 0, 5], "s")
    apply_override(data, "gyro.rate_hz", 200, "s")
    assert data == {"heads": [{"width": 256}], "motion": {"rate_dps": [0, 0, 5]}, "gyro": {"rate_hz": 200}}
    with pytest.raises(ConfigError, match="heads has 1 items, no item '3'"):
        apply_override(data, "heads.3.width", 1, "s")
    with pytest.raises(ConfigError, match="heads.0.width is not a table"):
        apply_override(data, "heads.0.width.x", 1, "s")


scalars = st.one_of(st.integers(-2**63, 2**63 - 1), st.floats(allow_nan=False, allow_infinity=False),
                    st.booleans(), st.text(max_size=20))
keys = st.text(alphabet="abcdefghij_", min_size=1, max_size=8)
tables = st.recursive(st.dictionaries(keys, st.one_of(scalars, st.lists(scalars, max_size=4)), max_size=4),
                      lambda t: st.dictionaries(keys, st.one_of(t, st.lists(t, min_size=1, max_size=2)), max_size=3),
                      max_leaves=12)


@given(tables)
def test_the_toml_writer_round_trips(data):
    """What ``dump_toml`` writes, tomllib reads back as the same document (ints, floats, strings, arrays, tables,
    arrays of tables)."""
    assert tomllib.loads(dump_toml(data)) == data


def test_pipeline_choices_merge_in_one_place():
    scenario = PipelineSpec({"predictor": "a:P"}, {"identifier": {"gate_px": 3.0, "min_matches": 4}}, 7.0)
    bench = PipelineSpec({"solver": "b:S"}, {"identifier": {"gate_px": 5.0}})
    merged = scenario.replaced_by(bench)
    assert merged.agents == {"predictor": "a:P", "solver": "b:S"}
    assert merged.options == {"identifier": {"gate_px": 5.0, "min_matches": 4}} and merged.catalog_mag_limit == 7.0
    assert scenario.options["identifier"]["gate_px"] == 3.0  # the scenario's own choice is not mutated
    sc = scenario_mod.load("paper_000")
    built = Pipeline.for_scenario(sc, {"solver": "starenv.agents.solve:SvdSolver"}, {"identifier": {"gate_px": 4.0}})
    assert built.describe()["predictor"] == "starenv.agents.predict:FirstOrderPredictor"  # paper_000's own
    assert built.describe()["solver"] == "starenv.agents.solve:SvdSolver" and built.agents["identifier"].gate_px == 4.0
    # a bench file's named pipeline is the same record plus its name, merged the same way
    bench_text = '[pipelines.svd]\nsolver = "starenv.agents.solve:SvdSolver"\n[[runs]]\nscenario = "paper_000"\n' \
                 'pipelines = ["svd"]\n'
    named = parse_bench(bench_text, "b.toml", check=False).runs[0].pipeline
    assert isinstance(named, PipelineSpec) and named.name == "svd"
    assert named.as_dict() == {"name": "svd", "agents": {"solver": "starenv.agents.solve:SvdSolver"}, "options": {},
                               "catalog_mag_limit": None}
    direct = Pipeline.for_scenario(sc, {"solver": "starenv.agents.solve:SvdSolver"})
    assert named.build(sc).describe() == direct.describe()


@pytest.mark.parametrize("old", sorted(MOVED))
def test_an_agent_path_that_moved_names_its_new_home(old):
    role = "identifier" if "identify" in MOVED[old] else "predictor" if "fuse" in MOVED[old] else "deblurrer"
    with pytest.raises(ValueError, match=f"has moved: write '{MOVED[old]}'"):
        load_agent(old, role)
    assert type(load_agent(MOVED[old], role)).__name__ == old.split(":")[1]
