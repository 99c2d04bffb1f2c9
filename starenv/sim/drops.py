"""Dropped frames: independent losses, and bursty losses from a two-state (Gilbert-Elliott) Markov channel.

In the two-state model the channel is *good* or *bad*; each frame it moves good -> bad with probability
``p_good_to_bad`` and bad -> good with ``p_bad_to_good``, then drops the frame with the current state's drop
probability.  The stationary share of bad frames is ``p_gb / (p_gb + p_bg)`` and a bad spell lasts
``1 / p_bg`` frames on average, so the long-run drop rate is
``(p_bg * drop_good + p_gb * drop_bad) / (p_gb + p_bg)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from starenv import checks


@dataclass(frozen=True)
class DropModel:
    """Frame-loss process; with only ``probability`` set it is memoryless (independent drops)."""

    probability: float = 0.0
    p_good_to_bad: float = 0.0
    p_bad_to_good: float = 1.0
    drop_bad: float = 1.0

    def __post_init__(self):
        checks.probability("drops.probability", self.probability)
        checks.probability("drops.p_good_to_bad", self.p_good_to_bad)
        checks.in_range("drops.p_bad_to_good", self.p_bad_to_good, 0.0, 1.0, low_open=True)
        checks.probability("drops.drop_bad", self.drop_bad)

    @property
    def drop_rate(self) -> float:
        """Long-run fraction of dropped frames."""
        gb, bg = self.p_good_to_bad, self.p_bad_to_good
        return (bg * self.probability + gb * self.drop_bad) / (gb + bg)


class DropChannel:
    """State of one drop process (one per head): starts in the good state."""

    def __init__(self, model: DropModel):
        self.model = model
        self.bad = False

    def dropped(self, rng: np.random.Generator) -> bool:
        """Advance one frame; True when this frame is lost.  Draws exactly two uniforms per frame."""
        m = self.model
        u_state, u_drop = rng.random(2)
        self.bad = (u_state >= m.p_bad_to_good) if self.bad else (u_state < m.p_good_to_bad)
        return bool(u_drop < (m.drop_bad if self.bad else m.probability))
