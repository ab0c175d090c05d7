"""Range checks for numeric parameters, each failing with a one-line ``ValueError`` naming the parameter.

Used by :class:`~racebench.envs.env.RaceEnv`, :class:`~racebench.sim.obstacles.ObstacleGenerator` and
:class:`~racebench.sim.quadrotor.QuadrotorParams`, so that an out-of-range setting is refused when the object is made
(``gym.make``), not at the first ``reset`` or ``step``. Messages read ``"<name> must be <what> in <range>, got
<value>"``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

_REAL_TYPES = (int, float, np.integer, np.floating)


def interval(low: float, high: float, *, low_open: bool = False, high_open: bool = False, unit: str = "") -> str:
    """The range ``[low, high]`` as text, with ``(`` / ``)`` for open ends and the unit appended."""
    text = f"{'(' if low_open else '['}{low:g}, {high:g}{')' if high_open else ']'}"
    return f"{text} {unit}" if unit else text


def is_real(value: Any) -> bool:
    """Whether ``value`` is a finite real number (Python or numpy; a bool is not a number here)."""
    return isinstance(value, _REAL_TYPES) and not isinstance(value, (bool, np.bool_)) and math.isfinite(value)


def check_real(
    name: str,
    value: Any,
    low: float,
    high: float,
    *,
    unit: str = "",
    low_open: bool = False,
    high_open: bool = False,
) -> float:
    """``value`` as a float if it is a finite number within the range, else a ValueError naming ``name``."""
    ok = is_real(value)
    if ok:
        ok = (value > low if low_open else value >= low) and (value < high if high_open else value <= high)
    if not ok:
        span = interval(low, high, low_open=low_open, high_open=high_open, unit=unit)
        raise ValueError(f"{name} must be a finite number in {span}, got {value!r}")
    return float(value)


def check_int(name: str, value: Any, low: int, high: int, *, unit: str = "") -> int:
    """``value`` as an int if it is an integer (Python or numpy, not bool) in ``[low, high]``, else a ValueError."""
    ok = isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_)) and low <= value <= high
    if not ok:
        raise ValueError(f"{name} must be an int in {interval(low, high, unit=unit)}, got {value!r}")
    return int(value)


def check_triple(
    name: str,
    value: Any,
    low: float,
    high: float,
    *,
    unit: str = "",
    low_open: bool = False,
) -> tuple[float, float, float]:
    """``value`` as 3 floats if it is a sequence of 3 finite numbers each within the range, else a ValueError."""
    if isinstance(value, np.ndarray):
        value = value.tolist() if value.ndim == 1 else value
    items = list(value) if isinstance(value, Sequence) and not isinstance(value, (str, bytes)) else None
    ok = items is not None and len(items) == 3 and all(is_real(v) for v in items)
    if ok:
        ok = all((v > low if low_open else v >= low) and v <= high for v in items)
    if not ok:
        span = interval(low, high, low_open=low_open, unit=unit)
        raise ValueError(f"{name} must be 3 finite numbers, each in {span}, got {value!r}")
    return tuple(float(v) for v in items)  # type: ignore[return-value]
