"""Frame-sized scratch arrays kept between calls, for blocks and agents that run on every frame."""

from __future__ import annotations

import numpy as np


class Workspace:
    """Named arrays of one frame ``shape`` (rows, columns), or of another shape asked for, made on first use and
    handed out again (allocating them anew for every frame costs more than filling them).

    A block given a workspace writes into its arrays and may return views of them: those hold until the next call
    that uses the same workspace.
    """

    def __init__(self, shape: tuple[int, int]):
        self.shape = shape
        self._arrays: dict[tuple[str, np.dtype], np.ndarray] = {}

    def array(self, name: str, dtype=np.float32, shape: tuple[int, int] | None = None) -> np.ndarray:
        """The array ``name`` of ``dtype`` and ``shape`` (default: the frame's), contents left from its last use."""
        key = (name, np.dtype(dtype))
        if key not in self._arrays:
            self._arrays[key] = np.empty(self.shape if shape is None else shape, dtype)
        return self._arrays[key]
