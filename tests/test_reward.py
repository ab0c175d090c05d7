"""Each reward term against the paper's formula on hand-built states."""

from __future__ import annotations

import math

import numpy as np
import pytest

from racebench.envs.reward import REWARD_TERMS, RewardWeights, reward_terms, wrap_angle

W = RewardWeights()


def terms(**overrides):
    kwargs = dict(
        prev_gate_distance=5.0,
        gate_distance=4.8,
        yaw=0.0,
        bearing_to_gate=0.0,
        action=np.zeros(4),
        prev_action=np.zeros(4),
        speed=2.0,
        desired_speed=3.0,
        collision_distance=1.0,
        passed_gate=False,
        crashed=False,
    )
    kwargs.update(overrides)
    return reward_terms(W, **kwargs)


def test_table_one_defaults() -> None:
    assert (W.progress, W.heading, W.command, W.command_rate) == (0.9, 0.05, -0.005, -0.0025)
    assert (W.speed, W.avoid, W.passing, W.crash) == (-0.05, -0.01, 5.0, -4.0)


def test_terms_are_the_seven_of_the_paper() -> None:
    assert tuple(terms()) == REWARD_TERMS


def test_progress() -> None:
    assert terms()["prog"] == pytest.approx(0.9 * 0.2)
    assert terms(gate_distance=5.3)["prog"] == pytest.approx(-0.9 * 0.3)


def test_heading_wraps_angles() -> None:
    assert terms()["theta"] == pytest.approx(0.05)
    assert terms(yaw=0.5, bearing_to_gate=-0.5)["theta"] == pytest.approx(0.05 * math.exp(-1.0))
    # 179° vs −179° is 2° apart, not 358°.
    a, b = math.radians(179), math.radians(-179)
    assert terms(yaw=a, bearing_to_gate=b)["theta"] == pytest.approx(0.05 * math.exp(-math.radians(2)))
    assert wrap_angle(3 * math.pi / 2) == pytest.approx(-math.pi / 2)


def test_command() -> None:
    u, u_prev = np.array([0.3, 0.4, 0.0, 0.0]), np.array([0.3, 0.0, 0.0, 0.0])
    assert terms(action=u, prev_action=u_prev)["cmd"] == pytest.approx(-0.005 * 0.5 - 0.0025 * 0.4)


def test_speed_penalises_only_the_excess() -> None:
    assert terms(speed=2.0)["vd"] == 0.0
    assert terms(speed=5.0)["vd"] == pytest.approx(-0.05 * 2.0)


def test_avoid() -> None:
    assert terms(collision_distance=0.4)["avoid"] == pytest.approx(-0.01 / (0.4 + 0.1))
    assert terms(collision_distance=-0.05)["avoid"] == pytest.approx(-0.01 / 0.1)  # touching: capped


def test_pass_and_crash() -> None:
    assert terms()["pass"] == 0.0 and terms()["crash"] == 0.0
    assert terms(passed_gate=True)["pass"] == 5.0
    assert terms(crashed=True)["crash"] == -4.0


def test_overrides() -> None:
    weights = RewardWeights.from_overrides({"avoid": 0.0, "speed": 0})
    assert weights.avoid == 0.0 and weights.speed == 0.0 and weights.passing == 5.0
    with pytest.raises(ValueError, match="unknown weight 'avoidance'"):
        RewardWeights.from_overrides({"avoidance": 0.0})
    with pytest.raises(ValueError, match="finite"):
        RewardWeights.from_overrides({"crash": float("nan")})
