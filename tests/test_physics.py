"""First-principles checks of the flight dynamics, through the environment's own step()."""

from __future__ import annotations

import math

import numpy as np
import pytest

from racebench.envs.env import RaceEnv
from racebench.sim.quadrotor import Quadrotor, QuadrotorParams

G = 9.81
NO_DRAG = {"drag_coefficients": (0.0, 0.0, 0.0)}


def make(**kwargs) -> RaceEnv:
    defaults = dict(track="S", density=0, obs_mode="state", start_spread=(0.0, 0.0, 0.0), quadrotor=NO_DRAG)
    defaults.update(kwargs)
    env = RaceEnv(**defaults)
    env.reset(seed=0)
    return env


def fly(env: RaceEnv, action, seconds: float) -> list:
    states = []
    for _ in range(int(round(seconds * env.control_freq))):
        _, _, terminated, truncated, info = env.step(np.asarray(action, dtype=np.float32))
        assert not terminated, info
        states.append(env.drone)
    return states


def test_hover_thrust_equals_weight() -> None:
    params = QuadrotorParams()
    quad = Quadrotor(params)
    thrust, _ = quad.command(np.array([params.hover_action, 0, 0, 0]))
    assert thrust == pytest.approx(params.mass * G)
    assert params.hover_action == pytest.approx(2 * 0.58 * 9.81 / 14.0 - 1)


def test_hover_command_holds_altitude() -> None:
    env = make()
    z0 = env.drone.position[2]
    states = fly(env, [env.params.hover_action, 0, 0, 0], 3.0)
    assert abs(states[-1].position[2] - z0) < 1e-3
    assert np.linalg.norm(states[-1].velocity) < 1e-3
    np.testing.assert_allclose(states[-1].position[:2], [1.0, 0.0], atol=1e-6)


def test_zero_thrust_falls_at_g() -> None:
    env = make()
    states = fly(env, [-1, 0, 0, 0], 0.36)
    # After 0.2 s the motor lag (30 ms) has decayed to < 0.2 % of hover thrust.
    t0, t1 = 10, len(states) - 1
    accel = (states[t1].velocity[2] - states[t0].velocity[2]) / ((t1 - t0) / env.control_freq)
    assert accel == pytest.approx(-G, rel=2e-3)


def test_full_thrust_accelerates_at_tmax_over_m_minus_g() -> None:
    env = make()
    states = fly(env, [1, 0, 0, 0], 0.5)
    t0, t1 = 10, len(states) - 1
    accel = (states[t1].velocity[2] - states[t0].velocity[2]) / ((t1 - t0) / env.control_freq)
    assert accel == pytest.approx(14.0 / 0.58 - G, rel=2e-3)


def test_motor_lag_is_first_order_with_tau() -> None:
    params = QuadrotorParams()
    quad = Quadrotor(params)
    quad.reset(hover=False)
    dt = 1e-3
    thrust = 0.0
    for _ in range(int(params.motor_time_constant / dt)):
        thrust, _ = quad.actuate(params.max_thrust, np.zeros(3), np.zeros(3), dt)
    assert thrust == pytest.approx(params.max_thrust * (1 - math.exp(-1)), rel=1e-6)


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_body_rate_steps_are_tracked(axis: int) -> None:
    env = make()
    action = np.array([env.params.hover_action, 0.0, 0.0, 0.0])
    action[1 + axis] = 0.5
    target = 0.5 * env.params.max_body_rate[axis]
    states = fly(env, action, 0.3)
    rates = states[-1].body_rates
    assert rates[axis] == pytest.approx(target, rel=0.03)
    others = [i for i in range(3) if i != axis]
    assert np.all(np.abs(rates[others]) < 0.02 * target)


def test_quadratic_drag_opposes_body_velocity() -> None:
    quad = Quadrotor(QuadrotorParams(drag_coefficients=(0.1, 0.2, 0.3)))
    v = np.array([2.0, -1.0, 0.5])
    np.testing.assert_allclose(quad.drag_force(v), [-0.4, 0.2, -0.075])


def test_terminal_velocity_of_a_falling_drone_with_drag() -> None:
    # Falling flat with zero thrust, vertical drag balances weight at v = sqrt(m g / k_z).
    params = QuadrotorParams(drag_coefficients=(0.03, 0.03, 1.5))
    env = make(quadrotor=params)
    env.sim.reset_drone(np.array([1.0, 0.0, 3.3]), 0.0)
    env.drone = env.sim.drone_state()
    states = fly(env, [-1, 0, 0, 0], 0.7)
    assert -states[-1].velocity[2] == pytest.approx(math.sqrt(0.58 * G / 1.5), rel=0.01)


def test_ground_contact_is_a_crash() -> None:
    env = make()
    info = {}
    for _ in range(100):
        _, reward, terminated, truncated, info = env.step(np.array([-1, 0, 0, 0], dtype=np.float32))
        if terminated:
            break
    assert terminated and info["crash_reason"] == "ground" and not info["is_success"]
    assert info["reward_terms"]["crash"] == -4.0


def test_leaving_the_arena_is_a_crash() -> None:
    env = make()
    for _ in range(200):
        _, _, terminated, _, info = env.step(np.array([1, 0, 0, 0], dtype=np.float32))
        if terminated:
            break
    assert info["crash_reason"] == "out_of_bounds"
    assert env.drone.position[2] > env.scene.arena_high[2] - 0.5
