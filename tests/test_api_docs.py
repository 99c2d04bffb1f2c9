"""The API reference: every public name of the package doors has a docstring, and ``mkdocs build --strict`` renders
them all (warnings as errors: a name the reference points at that no longer exists, or a docstring griffe cannot
parse, fails the build)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

griffe = pytest.importorskip("griffe")
pytest.importorskip("mkdocs")

ROOT = Path(__file__).resolve().parents[1]
ROLES = ("detect", "predict", "fuse", "restore", "identify", "correct", "solve")
DOORS = [f"agents.{r}" for r in ROLES] + ["bench", "datasets", "vector"]


@pytest.fixture(scope="module")
def package():
    """The package as griffe reads it from the source (statically: no torch imported)."""
    return griffe.load("starenv", search_paths=[str(ROOT)], resolve_aliases=True, resolve_external=False)


def exported(module, name: str):
    """A door's exported ``name``: its member, or (a lazy export) the submodule's that defines it."""
    if name in module.members:
        return module.members[name]
    for sub in module.modules.values():
        if name in sub.members and not sub.members[name].is_alias:
            return sub.members[name]
    raise AssertionError(f"{module.path} exports {name!r}, defined nowhere under it")


@pytest.mark.parametrize("door", DOORS)
def test_every_name_a_door_exports_has_a_docstring(package, door):
    module = package[door]
    assert module.docstring is not None and module.docstring.value.strip(), f"{module.path} has no docstring"
    assert module.exports, f"{module.path} names no __all__"
    for name in module.exports:
        member = exported(module, str(name))
        docstring = member.docstring
        assert docstring is not None and len(docstring.value.split()) >= 3, f"{module.path}.{name}: no docstring"


def test_the_api_reference_builds_with_warnings_as_errors_and_shows_every_agent(tmp_path, package):
    site = tmp_path / "site"
    done = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-q", "-d", str(site)], cwd=ROOT,
                          capture_output=True, text=True)
    assert done.returncode == 0, done.stdout + done.stderr
    agents = (site / "api" / "agents" / "index.html").read_text()
    for role in ROLES:
        for name in package[f"agents.{role}"].exports:
            assert f'id="starenv.agents.{role}.{name}"' in agents or f".{name}\"" in agents, name
    env = (site / "api" / "env" / "index.html").read_text()
    assert 'id="starenv.env.StarSensorEnv"' in env
