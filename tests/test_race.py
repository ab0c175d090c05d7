"""Whole episodes: gates in order, success and lap time, crashes, reward bookkeeping."""

from __future__ import annotations

import dataclasses
import math

import gymnasium as gym
import numpy as np
import pytest

from racebench.agents.control import GateFollower, acceleration_to_ctbr
from racebench.envs.env import RaceEnv


def run_follower(env: gym.Env, seed: int) -> tuple[dict, list[dict], float]:
    follower = GateFollower()
    _, info = env.reset(seed=seed)
    infos, total = [], 0.0
    terminated = truncated = False
    while not (terminated or truncated):
        _, reward, terminated, truncated, info = env.step(follower.act_privileged(env.unwrapped))
        assert reward == pytest.approx(sum(info["reward_terms"].values()))
        infos.append(info)
        total += reward
    return info, infos, total


@pytest.mark.parametrize("track", ["S", "J", "Circle"])
def test_follower_finishes_obstacle_free_tracks(track: str) -> None:
    env = gym.make(f"RaceObs-{track}-Level1-v0", obs_mode="state")
    for seed in range(3):
        info, infos, _ = run_follower(env, seed)
        assert info["is_success"] and not info["crashed"], info
        assert info["gates_passed"] == 4
        # Gates are counted one at a time, in order, and each pays λ7 once.
        counts = [i["gates_passed"] for i in infos]
        assert counts == sorted(counts) and set(counts) == {0, 1, 2, 3, 4} - ({0} if counts[0] else set())
        assert sum(i["reward_terms"]["pass"] for i in infos) == pytest.approx(4 * 5.0)
        steps = len(infos)
        assert info["lap_time"] == pytest.approx(info["time"])
        assert (steps - 1) / 50 < info["lap_time"] <= steps / 50 + 1e-9
    env.close()


def fly_velocity(env: RaceEnv, velocity: np.ndarray, seconds: float) -> dict:
    """Track a world-frame velocity with the geometric controller; return the last info."""
    info: dict = {}
    for _ in range(int(seconds * env.control_freq)):
        state = env.drone
        accel = 4.0 * (velocity - state.velocity)
        action = acceleration_to_ctbr(accel, math.atan2(velocity[1], velocity[0]), state.rotation, env.params)
        _, _, terminated, _, info = env.step(action)
        if terminated:
            break
    return info


def scene_with_start(env: RaceEnv, position, yaw: float = 0.0):
    env.reset(seed=0)
    return dataclasses.replace(env.scene, start_position=np.array(position, float), start_yaw=yaw)


def test_a_gate_out_of_order_does_not_count() -> None:
    env = RaceEnv(track="S", density=0, obs_mode="state")
    # Start just before gate 2 (index 1) and fly through it: gate 1 is still the next gate.
    env.reset(options={"scene": scene_with_start(env, [6.0, -1.0, 1.0])})
    info = fly_velocity(env, np.array([2.0, 0.0, 0.0]), 1.2)
    assert env.drone.position[0] > 7.5 and not info["crashed"]
    assert info["gates_passed"] == 0


def test_a_gate_flown_backwards_does_not_count() -> None:
    env = RaceEnv(track="S", density=0, obs_mode="state")
    env.reset(options={"scene": scene_with_start(env, [4.0, 0.0, 1.0], yaw=math.pi)})
    info = fly_velocity(env, np.array([-2.0, 0.0, 0.0]), 1.2)
    assert env.drone.position[0] < 2.5 and not info["crashed"]
    assert info["gates_passed"] == 0


def test_flying_into_a_gate_bar_is_a_gate_crash() -> None:
    env = RaceEnv(track="S", density=0, obs_mode="state")
    # Aim at the left bar of gate 1: y = inner/2 + bar/2 = 0.57.
    env.reset(options={"scene": scene_with_start(env, [1.5, 0.57, 1.0])})
    info = fly_velocity(env, np.array([2.0, 0.0, 0.0]), 2.0)
    assert info["crashed"] and info["crash_reason"] == "gate:0" and info["gates_passed"] == 0
    assert info["reward_terms"]["crash"] == -4.0


def test_flying_into_an_obstacle_is_an_obstacle_crash() -> None:
    env = RaceEnv(track="S", density=3, obs_mode="state")
    env.reset(seed=0)
    obstacle = env.scene.obstacles[0]
    start = obstacle.position.copy()
    start[0] -= 1.0
    start[2] = 1.0
    scene = dataclasses.replace(env.scene, start_position=start, start_yaw=0.0)
    env.reset(options={"scene": scene})
    info = fly_velocity(env, np.array([2.0, 0.0, 0.0]), 1.5)
    assert info["crash_reason"] == "obstacle:0"


def test_time_limit_truncates() -> None:
    env = RaceEnv(track="S", density=0, obs_mode="state", max_episode_time=0.5)
    env.reset(seed=0)
    hover = np.array([env.params.hover_action, 0, 0, 0], dtype=np.float32)
    for step in range(25):
        _, _, terminated, truncated, info = env.step(hover)
        assert not terminated
        assert truncated == (step == 24)
    assert not info["is_success"] and "lap_time" not in info


def test_avoid_term_uses_distance_to_nearest_surface() -> None:
    env = RaceEnv(track="S", density=0, obs_mode="state", start_spread=(0, 0, 0))
    env.reset(seed=0)
    hover = np.array([env.params.hover_action, 0, 0, 0], dtype=np.float32)
    _, _, _, _, info = env.step(hover)
    # Hovering at (1, 0, 1): nearest surface is gate 1's frame at x = 3 − depth/2, lateral 0.5 m off axis.
    gate = env.scene.gates[0]
    expected = math.hypot(2.0 - gate.depth / 2, gate.inner / 2) - env.params.collision_radius
    assert info["reward_terms"]["avoid"] == pytest.approx(-0.01 / (expected + 0.1), rel=1e-3)


@pytest.mark.parametrize("track", ["S", "Circle"])
def test_gates_start_mode_starts_before_each_gate_and_counts_the_rest(track: str) -> None:
    env = RaceEnv(track=track, density=3, obs_mode="state", start_mode="gates")
    seen: dict[int, int] = {}
    for seed in range(60):
        obs, info = env.reset(seed=seed)
        k = info["start_gate"]
        seen[k] = seen.get(k, 0) + 1
        assert env.next_gate == k and info["gates_passed"] == 0
        scene = env.scene
        velocity = env.drone.velocity
        if k == 0:
            assert np.all(np.abs(scene.start_position - env.track.start.center) <= env.track.start.spread + 1e-9)
            assert np.all(velocity == 0.0)  # laps start at rest, as evaluated
            continue
        before, gate = scene.gates[k - 1].center, scene.gates[k].center
        # On the leg between the two gates (within the start spread), facing gate k, clear of everything.
        leg = gate - before
        along = float((scene.start_position - before) @ leg) / float(leg @ leg)
        assert 0.1 < along < 0.7
        assert scene.start_yaw == pytest.approx(math.atan2(leg[1], leg[0]))
        assert scene.point_distance(*scene.start_position) >= env.generator.clearance
        # Already flying towards gate k, along the leg, no faster than v_d.
        assert np.linalg.norm(velocity) <= env.desired_speed + 1e-9
        np.testing.assert_allclose(np.cross(velocity, leg), 0.0, atol=1e-9)
        assert velocity @ leg >= 0.0
        # The observation's first vector points at gate k (body frame; the drone starts level, yawed to the leg).
        c, s = math.cos(scene.start_yaw), math.sin(scene.start_yaw)
        body = np.array([[c, s], [-s, c]])
        np.testing.assert_allclose(obs[:2] * 10.0, body @ (gate - scene.start_position)[:2], atol=1e-4)
    assert set(seen) == {0, 1, 2, 3}, seen
    env.close()


def test_a_run_from_a_mid_track_start_succeeds_on_the_remaining_gates() -> None:
    env = RaceEnv(track="S", density=0, obs_mode="state", start_mode="gates")
    for seed in range(20):
        _, info = env.reset(seed=seed)
        if info["start_gate"] == 2:
            break
    follower, terminated, truncated = GateFollower(), False, False
    while not (terminated or truncated):
        _, _, terminated, truncated, info = env.step(follower.act_privileged(env))
    assert info["is_success"] and info["start_gate"] == 2 and info["gates_passed"] == 2
    with pytest.raises(ValueError, match="start_mode"):
        RaceEnv(start_mode="anywhere")


def test_set_task_applies_from_the_next_episode() -> None:
    """A curriculum step changes the running episode's neither speed nor reward, but the next one's both."""
    env = RaceEnv(track="S", obs_mode="state", desired_speed=3.0)
    env.reset(seed=0)
    env.set_task(desired_speed=8.0, reward_weights={"speed": 0.0})
    obs, *_ = env.step(np.zeros(4, dtype=np.float32))
    assert env.desired_speed == 3.0 and env.weights.speed != 0.0 and obs[9] == pytest.approx(0.3)
    obs, _ = env.reset(seed=1)
    assert env.desired_speed == 8.0 and env.weights.speed == 0.0 and obs[9] == pytest.approx(0.8)
    env.close()


def test_set_task_gate_shift_keeps_vertical_range_rule() -> None:
    """``gate_shift_z`` left unset follows ``gate_shift`` through set_task; set explicitly, it stays."""
    follows = RaceEnv(track="S", obs_mode="state", gate_shift=0.3)
    follows.set_task(gate_shift=1.0)
    assert follows.generator.gate_shift == 1.0 and follows.generator.gate_shift_z == 1.0
    fixed = RaceEnv(track="S", obs_mode="state", gate_shift=0.3, gate_shift_z=0.2)
    fixed.set_task(gate_shift=1.0)
    assert fixed.generator.gate_shift == 1.0 and fixed.generator.gate_shift_z == 0.2
    follows.close()
    fixed.close()
