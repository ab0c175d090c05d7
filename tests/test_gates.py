"""Gate logic: a gate counts only when crossed inside the opening, along its normal, in order."""

from __future__ import annotations

import numpy as np
import pytest

from racebench.sim.track import Gate

GATE = Gate(center=np.array([3.0, 0.0, 1.0]), yaw=0.0)
SIDE = Gate(center=np.array([0.0, 0.0, 2.0]), yaw=np.pi / 2)  # faces +y


def p(*xyz: float) -> np.ndarray:
    return np.array(xyz, dtype=float)


def test_crossing_through_the_centre_counts() -> None:
    assert GATE.passed_by(p(2.9, 0, 1), p(3.1, 0, 1))
    assert SIDE.passed_by(p(0, -0.05, 2), p(0, 0.05, 2))


def test_crossing_inside_near_the_edge_counts_outside_does_not() -> None:
    assert GATE.passed_by(p(2.9, 0.49, 1.49), p(3.1, 0.49, 1.49))
    assert not GATE.passed_by(p(2.9, 0.51, 1), p(3.1, 0.51, 1))  # through the side bar
    assert not GATE.passed_by(p(2.9, 0, 1.52), p(3.1, 0, 1.52))  # through the top bar
    assert not GATE.passed_by(p(2.9, 2.0, 1), p(3.1, 2.0, 1))  # beside the gate
    assert not SIDE.passed_by(p(0.6, -0.1, 2), p(0.6, 0.1, 2))


def test_the_plane_intersection_not_the_endpoints_decides() -> None:
    # Both endpoints outside the opening, the crossing point (y = 0) inside.
    assert GATE.passed_by(p(2.0, -1.0, 1), p(4.0, 1.0, 1))
    # Both endpoints inside the opening's y-range, the crossing point outside.
    assert not GATE.passed_by(p(2.0, 0.4, 1), p(4.0, 0.4, 3.5))


def test_backwards_and_no_crossing() -> None:
    assert not GATE.passed_by(p(3.1, 0, 1), p(2.9, 0, 1))  # wrong direction
    assert not GATE.passed_by(p(2.5, 0, 1), p(2.9, 0, 1))  # stays in front
    assert not GATE.passed_by(p(3.1, 0, 1), p(3.5, 0, 1))  # stays behind


def test_touching_the_plane_from_behind_counts_once() -> None:
    assert GATE.passed_by(p(2.9, 0, 1), p(3.0, 0, 1))
    assert not GATE.passed_by(p(3.0, 0, 1), p(3.1, 0, 1))  # already on the plane: no second pass


@pytest.mark.parametrize("yaw", [0.3, -2.0, np.pi])
def test_rotated_gate(yaw: float) -> None:
    gate = Gate(center=np.array([1.0, 2.0, 1.5]), yaw=yaw)
    n, lat = gate.normal, gate.lateral
    assert gate.passed_by(gate.center - 0.1 * n + 0.4 * lat, gate.center + 0.1 * n + 0.4 * lat)
    assert not gate.passed_by(gate.center - 0.1 * n + 0.6 * lat, gate.center + 0.1 * n + 0.6 * lat)
    assert not gate.passed_by(gate.center + 0.1 * n, gate.center - 0.1 * n)
