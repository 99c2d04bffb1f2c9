"""torch loads only when a learned agent or its training is used: the simulator, the env, the classical agents and
every role's door (which exports the learned agents lazily) leave it unloaded; old module paths are refused with the
new ones."""

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
DOORS = ["detect", "predict", "fuse", "restore", "correct", "identify", "solve", "blocks"]


def _torch_loaded_after(code: str) -> bool:
    probe = f"import sys\n{code}\nprint('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", probe], cwd=ROOT, capture_output=True, text=True, check=True)
    return out.stdout.strip().splitlines()[-1] == "True"


def test_core_and_every_door_do_not_import_torch():
    doors = ", ".join(f"starenv.agents.{d}" for d in DOORS)
    core = "starenv, starenv.env, starenv.sim.sensor, starenv.datasets, starenv.agents.pipeline, starenv.bench"
    assert not _torch_loaded_after(f"import {core}, {doors}")


@pytest.mark.parametrize("code", ["from starenv.agents.identify import NetworkIdentifier",
                                  "import starenv.agents.identify.network_model"])
def test_a_learned_agent_loads_torch_when_used(code):
    assert _torch_loaded_after(code)


@pytest.mark.parametrize("door", DOORS)
def test_every_door_exports_what_it_names(door):
    """``__all__`` names only what the door gives (a misspelt or stale name would break ``from ... import *``)."""
    import importlib

    module = importlib.import_module(f"starenv.agents.{door}")
    assert all(getattr(module, name) is not None for name in module.__all__)
    assert door == "blocks" or module.__all__, f"the {door} door names no agent"


@pytest.mark.parametrize("old, new", [("starenv.agents.fusion", "starenv.agents.fuse"),
                                      ("starenv.agents.learned.identifier", "starenv.agents.identify"),
                                      ("starenv.agents.learned.legendre", "starenv.agents.correct.ground")])
def test_an_old_module_path_is_refused_with_the_new_one(old, new):
    import importlib

    with pytest.raises(ModuleNotFoundError, match=new.replace(".", r"\.")):
        importlib.import_module(old)
