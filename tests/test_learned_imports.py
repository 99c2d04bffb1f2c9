"""The simulator and the classical agents never load torch; only ``starenv.agents.learned`` does."""

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def _torch_loaded_after(code: str) -> bool:
    probe = f"import sys\n{code}\nprint('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", probe], cwd=ROOT, capture_output=True, text=True, check=True)
    return out.stdout.strip().splitlines()[-1] == "True"


def test_core_simulator_does_not_import_torch():
    core = "starenv, starenv.env, starenv.sim.sensor, starenv.datasets, starenv.agents.pipeline, starenv.bench"
    assert not _torch_loaded_after(f"import {core}")


def test_learned_package_imports_torch():
    assert _torch_loaded_after("import starenv.agents.learned.seed002")
