"""The package's layers run one way: every import (module level or inside a function) of a starenv module names a
module of its own layer or a lower one.  Lowest first:

0. ``checks``, ``datasheet``, ``files``, ``parallel``, ``scenarios`` (argument checks, the datasheet estimators,
   atomic files, task executors, the bundled files' package: no starenv imports);
1. ``sim`` (the simulator: sky, motion, gyro, optics, photometry, render, imager, drops, sensor);
2. ``config``, ``scenario``, ``sensor_sheet`` (TOML files -> simulator models; a scenario from a datasheet);
3. ``datasets`` (samples drawn from the simulator for learning);
4. ``agents`` (contracts in ``agents.base``, the building blocks, one package per role with its agents and their
   training, the pipeline);
5. ``env``, ``episode``, ``scoring``, ``metrics``, ``view``, ``registration``, ``wrappers``, ``vector`` (the
   Gymnasium loop that drives policies, and the metric schema its scores follow);
6. ``record``, ``bench``, ``real``, ``cli`` and the package's ``__init__`` (front ends).
"""

import ast
from pathlib import Path

import pytest

import starenv

ROOT = Path(starenv.__file__).resolve().parent
LAYERS = {
    "checks": 0, "datasheet": 0, "files": 0, "parallel": 0, "scenarios": 0, "sim": 1, "config": 2, "scenario": 2,
    "sensor_sheet": 2, "datasets": 3, "agents": 4,
    "env": 5, "episode": 5, "scoring": 5, "metrics": 5, "view": 5, "registration": 5, "wrappers": 5, "vector": 5,
    "record": 6, "bench": 6, "real": 6, "cli": 6, "__init__": 6,
}


def layer(module: str) -> int:
    """Layer of a dotted ``starenv...`` module name (the first component below ``starenv`` decides)."""
    parts = module.split(".")
    return LAYERS[parts[1] if len(parts) > 1 else "__init__"]


def module_name(path: Path) -> str:
    parts = path.relative_to(ROOT.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def starenv_imports(path: Path) -> list[tuple[int, str]]:
    """(line, module) of every import of a starenv module in ``path``, at any depth."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            found += [(node.lineno, a.name) for a in node.names if a.name.split(".")[0] == "starenv"]
        elif isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] == "starenv":
            names = [f"{node.module}.{a.name}" if node.module == "starenv" else node.module for a in node.names]
            found += [(node.lineno, n) for n in names]
    return found


MODULES = sorted(ROOT.rglob("*.py"))


def test_every_module_has_a_layer():
    for path in MODULES:
        layer(module_name(path) if path.name != "__init__.py" or path.parent != ROOT else "starenv")


@pytest.mark.parametrize("path", MODULES, ids=lambda p: str(p.relative_to(ROOT)))
def test_imports_run_downwards(path):
    own = "starenv" if path == ROOT / "__init__.py" else module_name(path)
    upward = [f"line {line}: {name}" for line, name in starenv_imports(path) if layer(name) > layer(own)]
    assert not upward, f"{own} (layer {layer(own)}) imports from a higher layer: {upward}"


def test_the_checker_sees_an_upward_import(tmp_path):
    """The rule itself: a simulator module importing the env is caught, wherever the import sits."""
    bad = tmp_path / "bad.py"
    bad.write_text("def f():\n    from starenv.env import StarSensorEnv\n    return StarSensorEnv\n")
    assert [layer(name) for _, name in starenv_imports(bad)] == [5] and layer("starenv.sim.render") == 1


def test_the_core_does_not_load_torch():
    """Importing the simulator, the env and the classical agents leaves torch unloaded (it is heavy)."""
    import subprocess
    import sys

    code = ("import sys, starenv, starenv.env, starenv.episode, starenv.agents.pipeline, starenv.bench.spec; "
            "print('torch' in sys.modules)")
    assert subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip() \
        == "False"
