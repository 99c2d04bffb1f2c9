"""Packaging: the bundled scenarios and benches are package data found through ``importlib.resources``, the package
is typed, ``starenv --version`` agrees with the metadata, and a built wheel carries the data (``STARENV_SLOW=1``)."""

import os
import shutil
import subprocess
import sys
import tomllib
import zipfile
from importlib import resources
from pathlib import Path

import pytest

import starenv
from starenv.bench.spec import BENCH_DIR, load_bench
from starenv.cli import main
from starenv.scenario import SCENARIO_DIR, bundled_names

ROOT = Path(__file__).resolve().parent.parent
SCENARIOS = {"paper_000", "paper_001", "paper_002", "paper_003", "paper_004", "stress_drops", "stress_stray_light",
             "stress_tumble", "leo_distortion", "leo_bodies",
             "moon_in_field", "hot_sensor", "leo_drift"}


def test_bundled_files_are_package_resources():
    data = resources.files("starenv.scenarios")
    found = {p.name.removesuffix(".toml") for p in data.iterdir() if p.name.endswith(".toml")}
    assert found == SCENARIOS == set(bundled_names())
    assert data.joinpath("benches", "bundled.toml").is_file()
    assert resources.files("starenv").joinpath("py.typed").is_file()
    assert Path(str(data)) == SCENARIO_DIR and Path(str(data.joinpath("benches"))) == BENCH_DIR
    assert load_bench("bundled").runs  # the bundled bench resolves its scenarios by name


def test_the_bundled_files_live_at_the_repository_top_level_once():
    """The design card's layout: scenarios/ at the top (mapped to starenv.scenarios at build time), no second copy
    inside the package, and pyproject's package list is exactly the package tree (a package missing from it would be
    left out of the wheel)."""
    assert SCENARIO_DIR == ROOT / "scenarios" and not (ROOT / "starenv" / "data").exists()
    setuptools = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    tree = {".".join(p.parent.relative_to(ROOT).parts) for p in (ROOT / "starenv").rglob("__init__.py")}
    assert set(setuptools["packages"]) == tree | {"starenv.scenarios"}
    assert setuptools["package-dir"] == {"starenv.scenarios": "scenarios"}


def test_version_flag_matches_package(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    assert capsys.readouterr().out.strip() == f"starenv {starenv.__version__}"


def test_core_dependencies_name_the_viewer():
    deps = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]
    assert any(d.startswith("rerun-sdk") for d in deps)


@pytest.mark.skipif(os.environ.get("STARENV_SLOW") != "1", reason="builds a wheel (~1 min); set STARENV_SLOW=1")
def test_wheel_carries_package_data(tmp_path):
    src = tmp_path / "src"  # a copy, so the build leaves nothing (build/, *.egg-info) in the source tree
    shutil.copytree(ROOT, src, ignore=shutil.ignore_patterns(".git", "build", "*.egg-info", "recordings", "reports",
                                                             ".*cache", ".hypothesis", "__pycache__", ".*venv"))
    subprocess.run([sys.executable, "-m", "pip", "wheel", str(src), "--no-deps", "--no-build-isolation", "-q",
                    "-w", str(tmp_path)], check=True, cwd=tmp_path)
    (wheel,) = tmp_path.glob("starenv-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    assert {f"starenv/scenarios/{n}.toml" for n in SCENARIOS} <= names
    assert {"starenv/scenarios/benches/bundled.toml", "starenv/py.typed",
            "starenv/agents/restore/iteration/iteration_net.npz",
            "starenv/agents/identify/weights/paper002_orion/weights.pt"} <= names
    assert not any(n.startswith(("tests/", "benchmarks/")) for n in names)
    # installed from the wheel and run from another folder: every bundled id (and StarEnv/Scenario-v0) registers and
    # a bundled env steps
    site = tmp_path / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--target", str(site), str(wheel)],
                   check=True)
    code = (f"import gymnasium as gym, starenv; assert starenv.__file__.startswith({str(site)!r}); "
            "ids = [i for i in gym.registry if i.startswith('StarEnv/')]; assert len(ids) == 10, ids; "
            "env = gym.make('StarEnv/Paper000-v0'); env.reset(seed=0); print('ok')")
    out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env={**os.environ, "PYTHONPATH": str(site)},
                         capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "ok"
    listed = subprocess.run([sys.executable, "-m", "starenv.cli", "scenarios"], cwd=tmp_path, capture_output=True,
                            env={**os.environ, "PYTHONPATH": str(site)}, text=True, check=True).stdout
    assert {line.split()[0] for line in listed.splitlines()} == SCENARIOS
