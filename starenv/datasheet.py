"""A run's attitude errors in the terms of a star-sensor datasheet, with their uncertainty.

The split follows the error terms of ESA's star-sensor standard (ECSS-E-ST-60-20C, EN 16603-60-20, clause 5.2),
estimated from the error series of one axis, ``e[k]`` (arcsec, signed, one sample per frame, at equal steps), of one
run or pooled over runs (differences within runs):

* **bias** -- the mean of ``e``: the standard's bias error (BE), all that a run does not vary;
* **NEA** (noise-equivalent angle) -- the standard deviation of the first differences divided by sqrt(2): the
  standard's temporal error (TE), the part uncorrelated from frame to frame.  For white noise of deviation ``s``,
  ``e[k+1] - e[k]`` has deviation ``s sqrt(2)``; a drift slow against the frame rate adds almost nothing to it;
* **low-frequency** -- ``sqrt(max(var(e) - NEA^2, 0))``: what varies slowly over the run, the standard's
  low-frequency errors (thermo-elastic and field-of-view spatial errors: a star moving across the field);
* **total** 1 sigma -- the root mean square of ``e`` (bias included: ``sqrt(bias^2 + var(e))``); **3 sigma** is
  three times it, the figure datasheets quote as "3 sigma".

Over several runs each figure carries a 95 % interval: a percentile bootstrap over runs (:func:`bootstrap_interval`;
runs are the independent units, steps within a run are not) and, for shares (availability), the exact binomial
(Clopper-Pearson) interval on the pooled steps (:func:`binomial_interval`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
from scipy.stats import beta

LEVEL = 0.95
BOOTSTRAP_DRAWS = 2000
BOOTSTRAP_SEED = 0  # a fixed generator: the same runs give the same interval


def _runs(series) -> list[np.ndarray]:
    """One float array per run, NaN (steps without an estimate) left out: a single array is one run."""
    if isinstance(series, np.ndarray) and series.dtype != object or len(series) and np.isscalar(series[0]):
        series = [series]
    runs = [np.asarray(r, dtype=float) for r in series]
    return [r[np.isfinite(r)] for r in runs]


def error_split(series) -> dict[str, float]:
    """Bias, NEA, low-frequency part and total 1 / 3 sigma of one axis's signed errors (arcsec).

    ``series``: one run's error per step, or a list of runs' (first differences are taken within each run, never
    across two); NaN (no estimate that step) is left out.  Terms without enough samples are NaN: the bias needs one,
    the NEA three in one run (two differences), the rest two."""
    runs = _runs(series)
    pooled = np.concatenate(runs) if runs else np.zeros(0)
    nan = float("nan")
    split = {"bias": nan, "nea": nan, "low_frequency": nan, "total_1s": nan, "total_3s": nan}
    if len(pooled) == 0:
        return split
    split["bias"] = float(pooled.mean())
    differences = [np.diff(r) for r in runs if len(r) > 1]
    differences = np.concatenate(differences) if differences else np.zeros(0)
    if len(differences) > 1:
        split["nea"] = float(np.std(differences, ddof=1) / np.sqrt(2.0))
    if len(pooled) > 1:
        variance = float(np.var(pooled, ddof=1))
        if np.isfinite(split["nea"]):
            split["low_frequency"] = float(np.sqrt(max(variance - split["nea"] ** 2, 0.0)))
        split["total_1s"] = float(np.sqrt(np.mean(pooled**2)))
        split["total_3s"] = 3.0 * split["total_1s"]
    return split


def binomial_interval(successes: int, trials: int, level: float = LEVEL) -> tuple[float, float]:
    """Exact (Clopper-Pearson) ``level`` interval of a share ``successes / trials``; (nan, nan) for no trials."""
    if trials <= 0:
        return float("nan"), float("nan")
    alpha = 1.0 - level
    low = 0.0 if successes == 0 else float(beta.ppf(alpha / 2, successes, trials - successes + 1))
    high = 1.0 if successes == trials else float(beta.ppf(1 - alpha / 2, successes + 1, trials - successes))
    return low, high


def bootstrap_interval(runs: Sequence[np.ndarray], statistic: Callable[[list[np.ndarray]], float],
                       level: float = LEVEL, draws: int = BOOTSTRAP_DRAWS) -> tuple[float, float]:
    """Percentile bootstrap ``level`` interval of ``statistic(runs)``, resampling whole runs with replacement.

    ``runs``: one array of samples per run; ``statistic`` takes a list of runs (e.g.
    ``lambda r: error_split(r)["nea"]``, or ``lambda r: np.concatenate(r).mean()``).  One run has no spread between
    runs to resample: the interval is then (nan, nan), never a falsely narrow one."""
    runs = [np.asarray(r, dtype=float) for r in runs]
    if len(runs) < 2:
        return float("nan"), float("nan")
    rng = np.random.default_rng(BOOTSTRAP_SEED)
    picks = rng.integers(0, len(runs), size=(draws, len(runs)))
    values = np.array([statistic([runs[i] for i in pick]) for pick in picks.tolist()])
    values = values[np.isfinite(values)]
    if len(values) == 0:
        return float("nan"), float("nan")
    alpha = 1.0 - level
    return float(np.quantile(values, alpha / 2)), float(np.quantile(values, 1 - alpha / 2))


def acquisition_times(fixed, time_s) -> dict[str, list[float]]:
    """Times (s) from lost to the first fix: ``first`` from the run's first frame to its first fix (empty when the
    run never fixes), ``reacquisition`` from each loss of fix (the first step without one after a fix) to the next
    fix.  ``fixed``: per-step flags (a solved frame within the threshold); ``time_s``: the frames' times."""
    fixed = np.asarray(fixed, dtype=bool)
    t = np.asarray(time_s, dtype=float)
    out: dict[str, list[float]] = {"first": [], "reacquisition": []}
    if not fixed.any():
        return out
    first = int(np.argmax(fixed))
    out["first"].append(float(t[first] - t[0]))
    lost_at = None
    for k in range(first + 1, len(fixed)):
        if not fixed[k] and lost_at is None:
            lost_at = k
        elif fixed[k] and lost_at is not None:
            out["reacquisition"].append(float(t[k] - t[lost_at]))
            lost_at = None
    return out
