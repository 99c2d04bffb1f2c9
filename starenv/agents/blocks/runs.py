"""Runs of equal values in grouped arrays (sorted ones, say): where each run starts."""

from __future__ import annotations

import numpy as np


def run_starts(values: np.ndarray) -> np.ndarray:
    """Mask of the entries that start a run of equal values.

    Parameters
    ----------
    values : (n,) ndarray
        Grouped values: equal ones adjacent (e.g. sorted).

    Returns
    -------
    starts : (n,) ndarray of bool
        True at the first entry and wherever an entry differs from the one before it.
    """
    starts = np.empty(len(values), dtype=bool)
    starts[:1] = True
    np.not_equal(values[1:], values[:-1], out=starts[1:])
    return starts
