"""A scenario's own star files ([catalog]): CSV and hip2.dat-format catalogues parsed with line-numbered errors, the
rendered sky against the bundled Hipparcos-2, and an onboard list that differs from the rendered sky."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from starenv import scenario as scenario_mod
from starenv.sim.conventions import radec_to_unit
from starenv.sim.sky import default_catalog_path, load_catalog, parse_hip2, parse_star_csv

EXAMPLE_CSV = Path(__file__).resolve().parent.parent / "examples" / "data" / "orion_stars.csv"
HEADER = "id,ra_deg,dec_deg,pmra_mas_yr,pmdec_mas_yr,mag,b_v\n"


def write(tmp_path: Path, name: str, text: str) -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


@pytest.mark.parametrize("rows, line, words", [
    (["1,360.0,0,0,0,5,"], 2, "ra_deg: expected a number in [0, 360)"),
    (["1,10,-91,0,0,5,"], 2, "dec_deg: expected a number in [-90, 90]"),
    (["1,10,0,0,0,5,", "1,11,0,0,0,5,"], 3, "id: 1 already given on line 2"),
    (["1,10,0,0,0,5,", "0,11,0,0,0,5,"], 3, "id: expected an integer in [1, 2147483647]"),
    (["1,10,0,0,0,nan,"], 2, "mag: expected a number"),
    (["1,10,0,0,0,5"], 2, "expected 7 fields"),
    (["# comment", "", "1,10,0,0,0,5,x"], 4, "b_v: expected a number"),
])
def test_csv_errors_name_the_line(tmp_path, rows, line, words):
    path = write(tmp_path, "stars.csv", HEADER + "\n".join(rows) + "\n")
    with pytest.raises(ValueError) as exc:
        parse_star_csv(path)
    text = str(exc.value)
    assert text.startswith(f"{path}:{line}: ") and words in text and "\n" not in text


def test_csv_header_is_checked(tmp_path):
    path = write(tmp_path, "stars.csv", "id,ra,dec_deg,pmra_mas_yr,pmdec_mas_yr,mag\n1,10,0,0,0,5\n")
    with pytest.raises(ValueError, match=r"stars.csv:1: expected a header naming the columns"):
        parse_star_csv(path)


def test_csv_columns_in_any_order_without_b_v(tmp_path):
    path = write(tmp_path, "stars.csv",
                 "mag,id,dec_deg,ra_deg,pmdec_mas_yr,pmra_mas_yr\n5,7,-30,45,0,0\n4,3,10,20,0,0\n")
    table = parse_star_csv(path)
    assert table.hip.tolist() == [3, 7]  # sorted by id
    assert np.allclose(np.degrees(table.ra), [20, 45]) and np.isnan(table.b_v).all()
    # at its own epoch a CSV star is exactly at its position
    catalog = load_catalog(14.0, 2016.0, path=path, position_epoch=2016.0)
    assert np.allclose(catalog.unit, radec_to_unit(np.radians([20, 45]), np.radians([10, -30])), atol=1e-15)
    with pytest.raises(ValueError, match="needs the Julian year of its positions"):
        load_catalog(14.0, 2016.0, path=path)


def test_hip2_errors_name_the_line(tmp_path):
    lines = default_catalog_path().read_bytes().splitlines(keepends=True)[:3]
    short = write(tmp_path, "hip2.dat", (lines[0] + lines[1][:100] + b"\n" + lines[2]).decode("latin-1"))
    with pytest.raises(ValueError, match=r"hip2.dat:2: not a hip2.dat line: expected 276 bytes, got 100"):
        parse_hip2(short)
    bad = bytearray(lines[2])
    bad[20:24] = b"abcd"  # inside the right ascension (bytes 16-28)
    damaged = tmp_path / "damaged.dat"
    damaged.write_bytes(lines[0] + lines[1] + bytes(bad))
    with pytest.raises(ValueError, match=r"damaged.dat:3: column ra \(bytes 16-28\): expected a number"):
        parse_hip2(damaged)


def orion(overrides: dict | None = None) -> dict:
    return {"duration_s": 0.05, "catalog": {"file": str(EXAMPLE_CSV), "epoch": 1991.25}, **(overrides or {})}


def test_csv_sky_renders_as_the_bundled_catalogue_in_its_field():
    """The example CSV holds Hipparcos-2's stars within 20 deg of Orion at its own epoch: paper_000's first frame
    (a 12 deg field on Orion) is the same image, bit for bit, from either."""
    from starenv.sim.sensor import StarSensor

    own, bundled = StarSensor(scenario_mod.load("paper_000", orion())), StarSensor(scenario_mod.load("paper_000"))
    frame, reference = own.next_frame(), bundled.next_frame()
    assert len(own.catalog) < len(bundled.catalog)
    assert frame.heads[0].truth.catalog_id.size > 10
    assert np.array_equal(frame.heads[0].truth.catalog_id, reference.heads[0].truth.catalog_id)
    assert np.array_equal(frame.heads[0].image, reference.heads[0].image)


def test_onboard_catalogue_may_differ_from_the_sky(tmp_path):
    """[catalog] onboard_file: the pipeline's catalogue is that list (here the sky less its brightest star), the
    rendered sky stays the file's."""
    from starenv.agents.pipeline import Pipeline
    from starenv.env import StarSensorEnv

    rows = EXAMPLE_CSV.read_text().splitlines()
    table = parse_star_csv(EXAMPLE_CSV)
    brightest = int(table.hip[np.argmin(table.hp)])
    onboard = write(tmp_path, "onboard.csv", "\n".join(r for r in rows if not r.startswith(f"{brightest},")) + "\n")
    env = StarSensorEnv("paper_000", orion({"catalog": {"file": str(EXAMPLE_CSV), "epoch": 1991.25,
                                                        "onboard_file": str(onboard), "onboard_epoch": 1991.25}}))
    pipeline = Pipeline(catalog_mag_limit=env.scenario.mag_limit)  # the rendered sky's cut, to compare lists
    pipeline.reset(env.sensor_info)
    assert brightest in env.sensor.catalog.hip and brightest not in pipeline.catalog.hip
    assert len(pipeline.catalog) == len(env.sensor.catalog) - 1
    # without onboard_file the sensor carries the sky's own list
    default = Pipeline(catalog_mag_limit=env.scenario.mag_limit)
    default.reset(StarSensorEnv("paper_000", orion()).sensor_info)
    assert np.array_equal(default.catalog.hip, env.sensor.catalog.hip)


def test_catalog_keys_are_validated(tmp_path):
    with pytest.raises(scenario_mod.ScenarioError, match="catalog.epoch: expected a number in"):
        scenario_mod.load("paper_000", {"catalog": {"file": str(EXAMPLE_CSV)}})
    with pytest.raises(scenario_mod.ScenarioError, match="catalog.epoch: expected no epoch for a hip2.dat"):
        scenario_mod.load("paper_000", {"catalog": {"file": str(default_catalog_path()), "epoch": 2000.0}})
    with pytest.raises(scenario_mod.ScenarioError, match="catalog.file: expected the path of a file"):
        scenario_mod.load("paper_000", {"catalog": {"file": str(tmp_path / "missing.csv"), "epoch": 2000.0}})
    bad = write(tmp_path, "bad.csv", HEADER + "5,10,0,0,0,5,\n5,10,0,0,0,5,\n")
    with pytest.raises(scenario_mod.ScenarioError, match=r"bad.csv:3: id: 5 already given on line 2"):
        scenario_mod.load("paper_000", {"catalog": {"file": str(bad), "epoch": 2000.0}})


def test_paths_are_relative_to_the_scenario_file(tmp_path, monkeypatch):
    """A scenario's file names resolve against its own folder; its TOML (what recordings keep) names the file by
    its absolute path, so it loads from anywhere."""
    folder = tmp_path / "mission"
    folder.mkdir()
    (folder / "stars.csv").write_text(EXAMPLE_CSV.read_text())
    text = scenario_mod.load("paper_000").to_toml()
    (folder / "sc.toml").write_text(text + '\n[catalog]\nfile = "stars.csv"\nepoch = 1991.25\n')
    monkeypatch.chdir(tmp_path)
    sc = scenario_mod.load(folder / "sc.toml")
    assert sc.sky_catalog.path == str((folder / "stars.csv").resolve())
    again = tmp_path / "elsewhere.toml"
    again.write_text(sc.to_toml())
    assert scenario_mod.load(again).sky_catalog == sc.sky_catalog
    assert math.isclose(sc.sky_catalog.epoch, 1991.25)


def test_densest_cone_bounds_every_cone():
    """A custom sky's stars in view are bounded by the most stars within twice the cone's radius of any star: 50
    stars inside 0.1 deg and 10 spread over the sky give at least the 50 for a 1 deg cone and at most all 60; and
    every cone centred on a random direction holds no more than the bound."""
    from starenv.scenario import densest_cone
    from starenv.sim.sky import StarCatalog

    rng = np.random.default_rng(0)
    ra = np.concatenate([np.radians(40.0) + rng.uniform(0, 1e-3, 50), rng.uniform(0, 2 * np.pi, 10)])
    dec = np.concatenate([np.radians(20.0) + rng.uniform(0, 1e-3, 50), np.arcsin(rng.uniform(-1, 1, 10))])
    sky = StarCatalog(np.arange(1, 61), np.full(60, 5.0), radec_to_unit(ra, dec), 2026.0)
    bound = densest_cone(sky, np.radians(1.0))
    assert 50 <= bound <= 60
    directions = rng.normal(size=(2000, 3))
    assert max(len(sky.cone(d, np.radians(1.0))) for d in directions) <= bound


def test_a_bench_reads_a_scenarios_own_files_from_its_folder_and_their_bytes_are_in_the_run_identity(
        tmp_path, monkeypatch):
    """A bench on a scenario naming a catalogue relative to its own folder: run from another folder it reads that
    file; the file's SHA-256 is part of each run's identity, so editing the catalogue makes new runs (never a stale
    resume), and a run loaded before the edit refuses to execute after it."""
    import hashlib

    from starenv.bench import load_bench, read_run, run_bench
    from starenv.bench.spec import BenchError

    mission = tmp_path / "mission"
    mission.mkdir()
    stars = mission / "stars.csv"
    stars.write_bytes(EXAMPLE_CSV.read_bytes())
    text = (scenario_mod.SCENARIO_DIR / "paper_000.toml").read_text()
    (mission / "own.toml").write_text(text + '\n[catalog]\nfile = "stars.csv"\nepoch = 1991.25\n')
    (tmp_path / "bench.toml").write_text('name = "own"\nseeds = 1\n[[runs]]\nscenario = "mission/own.toml"\n'
                                         'pipelines = ["tracking"]\nsteps = 2\n')
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    bench = load_bench(tmp_path / "bench.toml")
    (run,) = bench.runs
    assert dict(run.files_sha256) == {"catalog.file": hashlib.sha256(stars.read_bytes()).hexdigest()}
    (done,) = run_bench(bench, tmp_path / "out", jobs=1, progress=False, log=lambda *a: None)
    header, records, _ = read_run(done)
    assert header["identity"]["files_sha256"] == dict(run.files_sha256) and len(records) == 2
    stars.write_bytes(b"".join(EXAMPLE_CSV.read_bytes().splitlines(keepends=True)[:-1]))  # one star fewer
    (edited,) = load_bench(tmp_path / "bench.toml").runs
    assert edited.run_id != run.run_id
    with pytest.raises(BenchError, match=r"catalog.file: the file .*stars.csv changed since the bench was loaded"):
        run.load_scenario()
