"""Building blocks the agents share: one implementation of each idea that more than one agent needs.

A block is a pure function of arrays (numpy / scipy / OpenCV), with no agent state and no knowledge of the pipeline:
its units, frames and conventions are in its docstring (numpydoc), and it checks no more than it must (the agents
check their inputs).  Agents of every role import them from here; a block imports no agent.  Where a block runs on
every frame it may take a :class:`Workspace` whose arrays it reuses (the results are the same without one).

* :func:`wahba_svd` (:mod:`.wahba`): Wahba's problem by SVD, batched; used by every solver, identifier and verifier
  that needs an attitude from matched vector pairs.
* :func:`frame_background`, :func:`background_maps`, :func:`clipped_mean_std` (:mod:`.background`): background
  level and noise of a frame (sigma-clipped statistics; a scalar over the whole frame, or tiled maps).
* :func:`components_above`, :func:`components`, :func:`pixels_above`, :func:`component_peaks`,
  :func:`streak_candidates` (:mod:`.candidates`): candidate stars and streaks, the connected pixels where a matched
  filter stands above its noise, and their peaks.
* :func:`run_starts` (:mod:`.runs`): where each run of equal values of a grouped (e.g. sorted) array starts; the
  detector's deblending and the tracking identifier's candidate choice group by it.
* :func:`row_window`, :func:`frame_span_s`: the exposure window of an image row under a rolling shutter (they live in
  :mod:`starenv.sim.conventions`, since the simulator uses them too, and are re-exported here).
"""

from starenv.agents.blocks.background import background_maps, clipped_mean_std, frame_background
from starenv.agents.blocks.candidates import (
    Components,
    component_peaks,
    components,
    components_above,
    pixels_above,
    streak_candidates,
)
from starenv.agents.blocks.runs import run_starts
from starenv.agents.blocks.wahba import wahba_svd
from starenv.agents.blocks.workspace import Workspace
from starenv.sim.conventions import frame_span_s, row_window

__all__ = ["Components", "Workspace", "background_maps", "clipped_mean_std", "component_peaks", "components",
           "components_above", "frame_background", "frame_span_s", "pixels_above", "row_window", "run_starts",
           "streak_candidates", "wahba_svd"]
