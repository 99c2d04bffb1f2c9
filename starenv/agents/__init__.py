"""Processing agents of a star-sensor pipeline, one package per role.

========== ============================================ =========================================
package    role (protocol in :mod:`starenv.agents.base`)  agents
========== ============================================ =========================================
predict    ``Predictor``: stars and attitude at the next   ``QuaternionPredictor``, ``FirstOrderPredictor``
           frame from the gyro
fuse       ``AttitudeFilter``: a predictor that fuses the  ``MekfPredictor``
           gyro and the solved attitudes
restore    ``Deblurrer``: a smeared frame restored         ``TrailFitDeblurrer``, ``RoiDeblurrer``, ...
detect     ``StarDetector``: star centroids of a frame     ``CentroidDetector``
correct    ``DistortionCorrector``: measured -> calibrated ``LegendreCorrector``
identify   ``Identifier``: catalogue ids of detections     ``TrackingIdentifier``, ``LostInSpaceIdentifier``, ...
solve      ``AttitudeSolver``: attitude from identified    ``QuestSolver``, ``DavenportSolver``, ``SvdSolver``
           stars
========== ============================================ =========================================

Each package's ``__init__`` is its door: it names the role's agents in ``__all__`` and says how to add one, and a
``"module:Class"`` string may name it (``starenv.agents.identify:NetworkIdentifier``).  Learned agents (torch) sit
beside the classical ones of their role; their door imports them lazily, so torch loads only when one is used.
:mod:`starenv.agents.blocks` holds the pure building blocks the agents share.  :mod:`starenv.agents.pipeline`
composes agents into a policy.

A module path an agent had before the packages were sorted by role is refused with the path it has now, both as a
``"module:Class"`` string (:data:`MOVED`) and as a Python import (:data:`MOVED_MODULES`).
"""

from __future__ import annotations

import importlib
import sys
from importlib.abc import MetaPathFinder

MOVED = {  # agents' former "module:Class" paths -> where they live now
    "starenv.agents.deblur:RoiDeblurrer": "starenv.agents.restore:RoiDeblurrer",
    "starenv.agents.deblur:RichardsonLucyDeblurrer": "starenv.agents.restore:RichardsonLucyDeblurrer",
    "starenv.agents.deblur:WienerDeblurrer": "starenv.agents.restore:WienerDeblurrer",
    "starenv.agents.curvature:CurvatureRLDeblurrer": "starenv.agents.restore:CurvatureRLDeblurrer",
    "starenv.agents.neural.agent:IterationNetDeblurrer": "starenv.agents.restore:IterationNetDeblurrer",
    "starenv.agents.fusion:MekfPredictor": "starenv.agents.fuse:MekfPredictor",
    "starenv.agents.learned.identifier:NetworkIdentifier": "starenv.agents.identify:NetworkIdentifier",
}
MOVED_MODULES = {  # former modules -> where their content lives now
    "starenv.agents.deblur": "starenv.agents.restore",
    "starenv.agents.curvature": "starenv.agents.restore.curvature",
    "starenv.agents.neural": "starenv.agents.restore.iteration",
    "starenv.agents.fusion": "starenv.agents.fuse (MekfPredictor)",
    "starenv.agents.learned": "starenv.agents.identify (NetworkIdentifier, network_*) and "
                              "starenv.agents.correct.ground (train_ground)",
    "starenv.agents.learned.identifier": "starenv.agents.identify.network",
    "starenv.agents.learned.seed002": "starenv.agents.identify.network_model (MainStarNet, MainStarConfig)",
    "starenv.agents.learned.data": "starenv.agents.identify.network_data",
    "starenv.agents.learned.train": "starenv.agents.identify.network_train",
    "starenv.agents.learned.legendre": "starenv.agents.correct.ground",
}


class _MovedModules(MetaPathFinder):
    """Refuses the import of a module in :data:`MOVED_MODULES`, naming where its content lives now."""

    def find_spec(self, fullname, path=None, target=None):
        if fullname in MOVED_MODULES:
            raise ModuleNotFoundError(f"{fullname} has moved: import {MOVED_MODULES[fullname]}", name=fullname)
        return None


if not any(isinstance(finder, _MovedModules) for finder in sys.meta_path):
    sys.meta_path.append(_MovedModules())


def lazy_exports(package: str, names: dict[str, str]):
    """A module ``__getattr__`` for a door: ``names`` maps an exported name to the submodule (of ``package``) that
    defines it, imported on first access (how doors export torch agents without loading torch)."""

    def __getattr__(name: str):
        if name not in names:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        return getattr(importlib.import_module(f"{package}.{names[name]}"), name)

    return __getattr__
