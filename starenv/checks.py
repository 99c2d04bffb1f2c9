"""Argument checks shared by every model: bad input raises ``ValueError`` naming the parameter and its allowed range."""

from __future__ import annotations

import math

import numpy as np


def finite(name: str, value, shape: tuple[int, ...] | None = None) -> np.ndarray:
    """Return ``value`` as a float64 array, refusing NaN/inf and (optionally) a wrong shape."""
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be a real number or array of real numbers, got {value!r}") from exc
    if shape is not None and arr.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite (no NaN or inf), got {value!r}")
    return arr


def in_range(
    name: str,
    value,
    low: float = -math.inf,
    high: float = math.inf,
    *,
    low_open: bool = False,
    high_open: bool = False,
    unit: str = "",
) -> float:
    """Return ``value`` as a float, checking ``low <= value <= high`` (``<`` where the bound is open)."""
    if isinstance(value, bool):
        raise ValueError(f"{name} must be a number, got a boolean")
    v = float(finite(name, value, shape=()))
    too_low = v <= low if low_open else v < low
    too_high = v >= high if high_open else v > high
    if too_low or too_high:
        left = "(" if low_open else "["
        right = ")" if high_open else "]"
        u = f" {unit}" if unit else ""
        raise ValueError(f"{name} must be in {left}{low:g}, {high:g}{right}{u}, got {v:g}")
    return v


def positive(name: str, value, unit: str = "") -> float:
    """A finite number > 0."""
    return in_range(name, value, 0.0, math.inf, low_open=True, unit=unit)


def non_negative(name: str, value, unit: str = "") -> float:
    """A finite number >= 0."""
    return in_range(name, value, 0.0, math.inf, unit=unit)


def probability(name: str, value) -> float:
    """A number in [0, 1]."""
    return in_range(name, value, 0.0, 1.0)


def integer(name: str, value, low: int, high: int) -> int:
    """An integer in [low, high]."""
    if isinstance(value, bool) or not float(finite(name, value, shape=())).is_integer():
        raise ValueError(f"{name} must be an integer in [{low}, {high}], got {value!r}")
    v = int(value)
    if not low <= v <= high:
        raise ValueError(f"{name} must be an integer in [{low}, {high}], got {v}")
    return v


def choice(name: str, value, options) -> str:
    """One of ``options`` (strings)."""
    if not isinstance(value, str) or value not in options:
        raise ValueError(f"{name} must be one of {', '.join(map(repr, options))}, got {value!r}")
    return value
