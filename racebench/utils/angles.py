"""Angle helpers shared by the reward, the controllers and the planners."""

from __future__ import annotations

import math


def wrap_angle(angle: float) -> float:
    """Wrap an angle to [−π, π)."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi
