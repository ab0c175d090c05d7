"""The fast privileged expert (``planner-fast``): speed profile from first principles, path checks, flight."""

from __future__ import annotations

import dataclasses
import math

import gymnasium as gym
import numpy as np
import pytest
from scripts_loader import load_script

from racebench.agents import BUILTIN_PRIVILEGED, load_agent
from racebench.agents.planner import (
    FastPlannerAgent,
    PlannerAgent,
    gate_crossings,
    limit_braking_onset,
    limit_jerk,
    minimum_time_speeds,
    pull_taut,
    relax,
    resample,
    scene_clearance,
    thrust_limited_speeds,
)
from racebench.evaluation.rollout import run_episode
from racebench.sim.raycast import ObstacleSight
from racebench.sim.track import Gate


def test_a_larger_gate_clearance_crosses_the_openings_nearer_their_centres():
    """gate_clearance 0.5 m (the 1 m opening's centre) against the default 0.4: the planned line passes every
    gate of the same scenes closer to its centre on average, and never beyond what its clearance allows."""
    env = gym.make("RaceObs-S-v0").unwrapped
    offsets: dict[float, list[float]] = {0.4: [], 0.5: []}
    for seed in range(3):
        env.reset(seed=seed)
        for wanted in offsets:
            planner = FastPlannerAgent(gate_clearance=wanted)
            planner.reset(env=env)
            for gate, k in zip(env.scene.gates, gate_crossings(planner.path, env.scene.gates), strict=True):
                a, b = planner.path[k], planner.path[k + 1]
                t = float((gate.center - a) @ gate.normal / ((b - a) @ gate.normal))
                off = a + t * (b - a) - gate.center
                offsets[wanted].append(float(np.abs(off - (off @ gate.normal) * gate.normal).max()))
    env.close()
    assert max(offsets[0.4]) <= 0.5 - 0.32 + 1e-6  # within the default floor everywhere
    assert np.mean(offsets[0.5]) < np.mean(offsets[0.4])


def test_straight_line_from_rest_is_constant_acceleration():
    # No curvature, no drag: the fastest profile from rest is v = sqrt(2 a s), capped at max_speed.
    arc = np.arange(0.0, 20.0, 0.05)
    v = minimum_time_speeds(arc, np.zeros((len(arc), 3)), max_accel=8.0, max_speed=12.0, start_speed=0.0)
    expected = np.minimum(np.sqrt(2 * 8.0 * arc), 12.0)
    np.testing.assert_allclose(v, expected, rtol=1e-9, atol=1e-9)


def test_circle_speed_is_sqrt_a_r_and_braking_respects_the_budget():
    # A straight run into a circle of radius 2: steady speed on the circle is sqrt(a R); before it the
    # profile brakes at no more than the budget; nowhere does the total acceleration exceed it.
    arc = np.arange(0.0, 30.0, 0.05)
    curvature = np.zeros((len(arc), 3))
    curvature[arc >= 15.0, 1] = 0.5
    a_max = 9.0
    v = minimum_time_speeds(arc, curvature, max_accel=a_max, max_speed=20.0, start_speed=0.0)
    assert np.allclose(v[arc >= 15.0], math.sqrt(a_max * 2.0))
    tangential = np.diff(v**2) / (2 * np.diff(arc))
    lateral = v[:-1] ** 2 * np.linalg.norm(curvature[:-1], axis=1)
    assert np.all(np.hypot(tangential, lateral) <= a_max * (1 + 1e-6) + 1e-9)
    assert tangential.min() < -0.9 * a_max  # it does brake as hard as allowed before the turn


def test_drag_lowers_the_forward_budget():
    arc = np.arange(0.0, 40.0, 0.05)
    free = minimum_time_speeds(arc, np.zeros((len(arc), 3)), 8.0, 30.0, 0.0)
    dragged = minimum_time_speeds(arc, np.zeros((len(arc), 3)), 8.0, 30.0, 0.0, drag=0.05)
    assert np.all(dragged <= free + 1e-12) and dragged[-1] < free[-1]
    assert dragged[-1] < math.sqrt(8.0 / 0.05)  # terminal speed where drag eats the whole budget


G = 9.81


def _thrust(arc, tangent, curvature, v, drag=0.0):
    """Mass-normalised thrust vector that flies the profile: a_t t + v² κ + drag v² t + g ẑ."""
    along = np.diff(v**2) / (2 * np.diff(arc))
    u = v[:-1] ** 2
    return (along + drag * u)[:, None] * tangent[:-1] + u[:, None] * curvature[:-1] + np.array([0.0, 0.0, G])


def test_thrust_budget_level_straight_accelerates_at_sqrt_f2_minus_g2():
    # Level flight: the thrust holds g up and has sqrt(F² − g²) left to push along: v = sqrt(2 a s).
    arc = np.arange(0.0, 20.0, 0.05)
    tangent = np.tile([1.0, 0.0, 0.0], (len(arc), 1))
    v = thrust_limited_speeds(arc, tangent, np.zeros((len(arc), 3)), 15.0, 30.0, 0.0, gravity=G)
    np.testing.assert_allclose(v, np.sqrt(2 * math.sqrt(15.0**2 - G**2) * arc), rtol=1e-9, atol=1e-9)


def test_thrust_budget_vertical_climb_has_f_minus_g_and_dive_f_plus_g():
    arc = np.arange(0.0, 10.0, 0.05)
    up = np.tile([0.0, 0.0, 1.0], (len(arc), 1))
    climb = thrust_limited_speeds(arc, up, np.zeros((len(arc), 3)), 15.0, 30.0, 0.0, gravity=G)
    np.testing.assert_allclose(climb, np.sqrt(2 * (15.0 - G) * arc), rtol=1e-9, atol=1e-9)
    # Straight down to a stop: braking may use the whole thrust less gravity, F − g, like the climb.
    down = -up
    stop = thrust_limited_speeds(arc, down, np.zeros((len(arc), 3)), 15.0, np.where(arc < 9.9, 30.0, 0.0), 30.0, 0.0, G)
    braking = -np.diff(stop**2) / (2 * np.diff(arc))
    assert braking.max() == pytest.approx(15.0 - G, rel=1e-6)


def test_thrust_budget_level_turn_speed_and_no_sample_over_budget():
    # A straight run into a level circle of radius 2: on it v² / R = sqrt(F² − g²); before it the profile
    # brakes; nowhere is the thrust over budget.
    arc = np.arange(0.0, 30.0, 0.05)
    tangent = np.tile([1.0, 0.0, 0.0], (len(arc), 1))
    curvature = np.zeros((len(arc), 3))
    curvature[arc >= 15.0, 1] = 0.5
    v = thrust_limited_speeds(arc, tangent, curvature, 15.0, 20.0, 0.0, gravity=G)
    assert np.allclose(v[arc >= 15.0], math.sqrt(2.0 * math.sqrt(15.0**2 - G**2)))
    assert np.linalg.norm(_thrust(arc, tangent, curvature, v), axis=1).max() <= 15.0 * (1 + 1e-6)
    assert (np.diff(v**2) / (2 * np.diff(arc))).min() < -5.0  # it brakes hard before the turn


@pytest.mark.parametrize("climb", [0.0, 0.5, -0.5])
def test_thrust_budget_with_drag_never_exceeds_the_budget(climb):
    # Level, climbing and diving runs into a turn of radius 5 m, with drag: the thrust stays within the
    # budget everywhere (the speed cap keeps room for drag and gravity along the path), up to the passes'
    # first-order discretisation.
    arc = np.arange(0.0, 40.0, 0.02)
    tangent = np.tile(np.array([1.0, 0.0, climb]) / math.hypot(1.0, climb), (len(arc), 1))
    curvature = np.zeros((len(arc), 3))
    curvature[arc >= 25.0, 1] = 0.2
    v = thrust_limited_speeds(arc, tangent, curvature, 15.0, 30.0, 0.0, drag=0.05, gravity=G)
    assert np.linalg.norm(_thrust(arc, tangent, curvature, v, 0.05), axis=1).max() <= 15.0 * 1.002


def test_drag_helps_braking_and_hinders_speeding_up():
    # Level straight to a stop: with drag the profile reaches less top speed but brakes harder near it.
    arc = np.arange(0.0, 40.0, 0.05)
    tangent = np.tile([1.0, 0.0, 0.0], (len(arc), 1))
    stop = np.where(arc < 39.9, 30.0, 0.0)
    free = thrust_limited_speeds(arc, tangent, np.zeros((len(arc), 3)), 15.0, stop, 0.0, drag=0.0, gravity=G)
    dragged = thrust_limited_speeds(arc, tangent, np.zeros((len(arc), 3)), 15.0, stop, 0.0, drag=0.05, gravity=G)
    assert dragged.max() < free.max()
    braking = -np.diff(dragged**2) / (2 * np.diff(arc))
    k = int(np.argmax(dragged)) + 1  # the first segment wholly on the backward pass's braking curve
    # Braking is sqrt(F² − g²) plus drag's 0.05 v² (the backward pass reads the state at the segment's end).
    assert braking[k] == pytest.approx(math.sqrt(15.0**2 - G**2) + 0.05 * dragged[k + 1] ** 2, rel=1e-9)
    assert braking[k] > math.sqrt(15.0**2 - G**2) + 5.0


def test_v2_profile_is_kept_by_name(s_env):
    # FastPlannerAgent(thrust_accel=None, braking_jerk=None) plans v2's friction-circle profile exactly.
    s_env.reset(seed=0)
    env = s_env.unwrapped
    v2 = FastPlannerAgent(thrust_accel=None, braking_jerk=None)
    assert v2.plan(env.scene, env.drone.position, 0.0, env.params)
    drag = env.params.drag_coefficients[0] / env.params.mass
    room = scene_clearance(env.scene, v2.path) - v2.min_path_clearance
    cap = np.minimum(v2.max_speed, v2.tight_speed + v2.room_speed_gain * np.maximum(room, 0.0))
    speeds = minimum_time_speeds(v2.arc, v2.profile_curvature, v2.max_accel, cap, 0.0, drag)
    np.testing.assert_array_equal(v2.speeds, limit_jerk(speeds, v2.arc, v2.flip_time))
    v3 = FastPlannerAgent()
    assert v3.plan(env.scene, env.drone.position, 0.0, env.params)
    np.testing.assert_array_equal(v3.path, v2.path)  # the same line, another profile
    assert not np.array_equal(v3.speeds, v2.speeds)


def test_limit_braking_onset_rounds_a_speed_peak_at_the_jerk_bound():
    # Accelerate at 8 m/s² then brake at 8 m/s²: the switch is instant; after limiting, u'' ≥ −2 J / v_max
    # everywhere, the profile is never above the original, and away from the peak it is unchanged.
    arc = np.arange(0.0, 20.0, 0.05)
    speeds = np.sqrt(2 * 8.0 * np.minimum(arc, 20.0 - arc))
    limited = limit_braking_onset(speeds, arc, jerk=60.0)
    assert np.all(limited <= speeds + 1e-12)
    c = 2 * 60.0 / speeds.max()
    second = np.diff(limited**2, 2) / 0.05**2
    assert second.min() >= -c * (1 + 1e-6)
    assert limited.max() < speeds.max() - 0.1
    far = np.abs(arc - 10.0) > 3.0
    np.testing.assert_allclose(limited[far], speeds[far], rtol=1e-9)
    # Already smooth enough (a constant-acceleration ramp has u'' = 0): unchanged.
    ramp = np.sqrt(2 * 8.0 * arc)
    np.testing.assert_allclose(limit_braking_onset(ramp, arc, jerk=60.0), ramp, rtol=1e-12)


def test_limit_jerk_stays_below_the_profile_and_smooths_a_step():
    arc = np.arange(0.0, 10.0, 0.05)
    speeds = np.where((arc > 4.0) & (arc < 5.0), 2.0, 6.0)
    smooth = limit_jerk(speeds, arc, window=0.2)
    assert np.all(smooth <= speeds + 1e-12)
    assert np.abs(np.diff(smooth)).max() < np.abs(np.diff(speeds)).max()


def test_gate_crossings_count_only_the_opening_in_order():
    gate = Gate(center=np.array([2.0, 0.0, 1.0]), yaw=0.0, inner=1.0, outer=1.28, depth=0.1)
    through = np.array([[0.0, 0.0, 1.0], [1.9, 0.1, 1.0], [2.1, 0.1, 1.0], [4.0, 0.0, 1.0]])
    beside = through + np.array([0.0, 0.8, 0.0])  # crosses the plane outside the opening
    backwards = through[::-1]
    assert gate_crossings(through, [gate]) == [1]
    assert gate_crossings(beside, [gate]) == []
    assert gate_crossings(backwards, [gate]) == []


@pytest.fixture(scope="module")
def s_env():
    env = gym.make("RaceObs-S-v0", obs_mode="state")
    yield env
    env.close()


def test_pull_taut_keeps_ends_and_clearance(s_env):
    s_env.reset(seed=3)
    scene = s_env.unwrapped.scene
    planner = FastPlannerAgent()
    polyline = planner._taut_corridor(scene, s_env.unwrapped.drone.position, 0.24)
    assert polyline is not None
    again = pull_taut(scene, polyline, 0.24)
    np.testing.assert_array_equal(again[0], polyline[0])
    np.testing.assert_array_equal(again[-1], polyline[-1])
    dense = np.concatenate([np.linspace(a, b, 50) for a, b in zip(again[:-1], again[1:], strict=True)])
    assert scene_clearance(scene, dense).min() >= 0.24 - 0.05 / 2  # proven at samples 0.05 apart


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_planned_path_threads_every_gate_and_stays_clear(s_env, seed):
    s_env.reset(seed=seed)
    env = s_env.unwrapped
    planner = FastPlannerAgent()
    assert planner.plan(env.scene, env.drone.position, 0.0, env.params)
    crossings = gate_crossings(planner.path, env.scene.gates)
    assert len(crossings) == len(env.scene.gates)
    up_to_finish = planner.path[: crossings[-1] + 2]
    assert scene_clearance(env.scene, up_to_finish).min() >= planner.min_path_clearance
    # the speed profile never asks for more lateral acceleration than its budget: with a thrust budget (the default),
    # what that thrust can pull sideways in a level turn, sqrt(F^2 - g^2), on the curvature it was planned on
    lateral = planner.speeds**2 * np.linalg.norm(planner.profile_curvature, axis=1)
    g = env.params.gravity
    budget = planner.max_accel if planner.thrust_accel is None else math.sqrt(planner.thrust_accel**2 - g**2)
    assert np.percentile(lateral, 99) <= 1.05 * budget


def test_planner_fast_is_a_privileged_builtin():
    assert BUILTIN_PRIVILEGED["planner-fast"] is True
    agent = load_agent("planner-fast")
    assert isinstance(agent, FastPlannerAgent) and agent.privileged
    with pytest.raises(ValueError, match="privileged"):
        agent.reset(None)


def test_planner_fast_flies_faster_than_the_cautious_planner(s_env):
    # Outcome on a handful of scenes, stated loosely enough to hold on any CPU (closed loops amplify
    # last-bit float differences): most laps finish, and they are clearly faster than the cautious planner's.
    fast = [run_episode(FastPlannerAgent(), s_env, seed) for seed in range(1_000_000, 1_000_005)]
    slow = [run_episode(PlannerAgent(), s_env, seed) for seed in range(1_000_000, 1_000_005)]
    fast_laps = [r["lap_time"] for r in fast if r["success"]]
    slow_laps = [r["lap_time"] for r in slow if r["success"]]
    assert len(fast_laps) >= 4
    assert np.mean(fast_laps) < 0.75 * np.mean(slow_laps)


@pytest.mark.parametrize("kwargs", [{"thrust_accel": 0.0}, {"thrust_accel": -3.0}, {"braking_jerk": 0.0}])
def test_non_positive_profile_settings_are_refused(kwargs):
    with pytest.raises(ValueError, match=next(iter(kwargs))):
        FastPlannerAgent(**kwargs)


def test_a_thrust_budget_below_gravity_is_refused_at_planning(s_env):
    s_env.reset(seed=0)
    env = s_env.unwrapped
    with pytest.raises(ValueError, match="thrust_accel must exceed gravity"):
        FastPlannerAgent(thrust_accel=9.0).plan(env.scene, env.drone.position, 0.0, env.params)


def test_planner_fast_sweep_settings_parse_none_only_where_a_stage_can_be_off():
    module = load_script("planner_fast_sweep")
    parse_settings = module.parse_settings

    assert parse_settings(["braking_jerk=none,60"]) == {"braking_jerk": [None, 60.0]}
    with pytest.raises(SystemExit, match="max_accel"):
        parse_settings(["max_accel=none"])  # not optional: a one-line error, not a crash mid-sweep
    with pytest.raises(SystemExit, match="naming a planner setting"):
        parse_settings(["path=1"])  # an attribute, not a setting


def displace(env, agent, distance: float) -> np.ndarray:
    """Teleport the drone ``distance`` m off the agent's line (sideways, up or down) to a spot 0.45 m clear of
    everything."""
    i = agent._index
    tangent = agent.tangent[i]
    side = np.cross(tangent, [0.0, 0.0, 1.0])
    side /= np.linalg.norm(side)
    for direction in (side, -side, np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, -1.0])):
        spot = agent.path[i] + distance * direction
        if scene_clearance(env.scene, spot[None])[0] >= 0.45:
            env.sim.reset_drone(spot, 0.0, env.drone.velocity)
            env.drone = env.sim.drone_state()
            return spot
    raise AssertionError("no clear spot beside the line: choose another scene")


def fly_past_first_gate(env, agent, after: int = 10) -> None:
    """Fly ``agent`` through the first gate and ``after`` steps on (failing, not hanging, if the lap ends)."""
    race = env.unwrapped
    for _ in range(race.max_steps):
        if race.next_gate >= 1:
            break
        _, _, terminated, truncated, _ = env.step(agent.act())
        assert not (terminated or truncated), "the expert did not reach its first gate"
    for _ in range(after):
        _, _, terminated, truncated, _ = env.step(agent.act())
        assert not (terminated or truncated)


def test_the_scene_ahead_keeps_the_passed_frames_as_obstacles(s_env):
    s_env.reset(seed=4)
    scene = s_env.unwrapped.scene
    points = np.random.default_rng(0).uniform(scene.arena_low, scene.arena_high, size=(2000, 3))
    for first in range(len(scene.gates) + 1):
        ahead = scene.ahead(first)
        assert ahead.gates == scene.gates[first:]
        assert len(ahead.obstacles) == len(scene.obstacles) + 4 * first  # four bars a frame
        np.testing.assert_allclose(ahead.distance(points), scene.distance(points), atol=1e-9)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_replanning_expert_plans_from_where_it_is_thrown_through_the_gates_still_to_pass(s_env, seed):
    s_env.reset(seed=seed)
    env = s_env.unwrapped
    agent = FastPlannerAgent(replan_distance=0.3)
    agent.reset(env)
    fly_past_first_gate(s_env, agent)
    assert 0 < env.next_gate < len(env.scene.gates)
    before = agent.replans  # on its line it has no reason to (0 on these scenes; not promised on every CPU)
    spot = displace(env, agent, 0.7)
    agent.act()
    assert agent.replans == before + 1
    assert np.linalg.norm(agent.path[0] - spot) < 1e-6  # the new line starts at the drone
    ahead = env.scene.gates[env.next_gate :]
    assert len(gate_crossings(agent.path, ahead)) == len(ahead)  # and threads every gate still to pass, in order
    assert scene_clearance(env.scene, agent.path[: gate_crossings(agent.path, ahead)[-1]]).min() >= 0.17

    # At most once per replan_interval: thrown off again at once, it keeps the new plan for now.
    displace(env, agent, 0.7)
    agent.act()
    assert agent.replans == before + 1

    # The built-in (replan_distance None) keeps the plan it made at reset, wherever the drone is.
    s_env.reset(seed=seed)
    fixed = FastPlannerAgent()
    fixed.reset(env)
    fly_past_first_gate(s_env, fixed)
    path = fixed.path
    displace(env, fixed, 0.7)
    fixed.act()
    assert fixed.path is path and fixed.replans == 0


@pytest.mark.parametrize("kwargs", [{"replan_distance": 0.0}, {"replan_distance": -1.0}, {"replan_interval": -0.1}])
def test_bad_replanning_settings_are_refused(kwargs):
    with pytest.raises(ValueError, match=next(iter(kwargs))):
        FastPlannerAgent(**kwargs)


def relax_in_numpy(
    scene,
    polyline: np.ndarray,
    min_clearance: float,
    wanted_clearance: float,
    gate_clearance: float = 0.4,
    gate_floor: float = 0.32,
    spacings: tuple[float, ...] = (0.4, 0.2),
    iterations: int = 350,
    bending: float = 0.06,
    tension: float = 0.05,
    push: float = 0.1,
) -> np.ndarray:
    """:func:`racebench.agents.planner.relax` as it was written before it was compiled: whole-array numpy steps, the
    reference the compiled stage must match bit for bit."""
    gate_centres = np.array([g.center for g in scene.gates])
    offsets = np.concatenate([np.zeros((1, 3)), np.eye(3) * 0.02, -np.eye(3) * 0.02])
    points = polyline
    for spacing in spacings:
        points, _ = resample(points, spacing)
        if len(points) < 5:
            continue
        for _ in range(iterations):
            step = np.zeros_like(points)
            fourth = points[:-4] - 4 * points[1:-3] + 6 * points[2:-2] - 4 * points[3:-1] + points[4:]
            step[2:-2] -= bending * fourth
            step[1:-1] += tension * (0.5 * (points[:-2] + points[2:]) - points[1:-1])
            probes = (points[None, :, :] + offsets[:, None, :]).reshape(-1, 3)
            values = scene_clearance(scene, probes).reshape(7, -1)
            grad = (values[1:4] - values[4:7]).T
            clearance, gradient = values[0], grad / np.maximum(np.linalg.norm(grad, axis=1, keepdims=True), 1e-9)
            at_gate = np.any(np.linalg.norm(points[:, None, :] - gate_centres[None], axis=2) < 0.8, axis=1)
            wanted = np.where(at_gate, gate_clearance, wanted_clearance)
            near = np.flatnonzero(clearance < wanted)
            if len(near):
                step[near] += push * (wanted - clearance)[near, None] * gradient[near]
            step[[0, 1, -2, -1]] = 0.0
            length = np.linalg.norm(step, axis=1, keepdims=True)
            step *= np.minimum(1.0, 0.05 / np.maximum(length, 1e-12))
            target = points + step
            floor = np.where(at_gate, max(min_clearance, gate_floor), min_clearance)
            both = scene_clearance(scene, np.concatenate([target, 0.5 * (target[:-1] + target[1:])]))
            after, middle = both[: len(target)], both[len(target) :]
            ok = (after >= floor) | (after >= np.minimum(clearance, floor))
            moved = np.where(ok[:, None], target, points)
            if not ok.all():
                middle = scene_clearance(scene, 0.5 * (moved[:-1] + moved[1:]))
            while True:
                bad = np.flatnonzero(middle < min_clearance - 1e-9)
                bad = bad[ok[bad] | ok[bad + 1]]
                if not len(bad):
                    break
                ok[bad] = ok[bad + 1] = False
                moved = np.where(ok[:, None], target, points)
                middle = scene_clearance(scene, 0.5 * (moved[:-1] + moved[1:]))
            points = moved
    return points


@pytest.mark.parametrize("env_id", ["RaceObs-S-v0", "RaceObs-Circle-v0", "RaceObs-J-Density5-v0"])
def test_compiled_relax_gives_the_numpy_path_bit_for_bit(env_id: str) -> None:
    """The compiled smoothing stage is the numpy algorithm, operation for operation: same path to the last bit
    on every corridor candidate of several scenes (so planner-fast's plans, and its records, do not move)."""
    env = gym.make(env_id).unwrapped
    planner = FastPlannerAgent()
    compared = 0
    for seed in range(10):  # until 3 candidates are compared: a scene may have no taut corridor at a clearance
        if compared >= 3:
            break
        env.reset(seed=seed)
        start = np.array(env.drone.position, dtype=float)
        for clearance in planner.corridor_clearances[:2]:
            polyline = planner._taut_corridor(env.scene, start, clearance)
            if polyline is None:
                continue
            args = (env.scene, polyline, min(planner.clearance, clearance), planner.wanted_clearance)
            kwargs = {"gate_clearance": planner.gate_clearance, "gate_floor": planner.gate_floor}
            np.testing.assert_array_equal(relax(*args, **kwargs), relax_in_numpy(*args, **kwargs))
            compared += 1
    env.close()
    assert compared >= 3


def test_the_experts_acceleration_command_flown_from_the_observation_is_its_action(s_env):
    """What an acceleration student is taught (``acceleration_command`` of the expert's ``command``), turned back into
    CTBR by ``command_to_ctbr`` from the public state observation alone, is the expert's own action at every step of a
    lap; the attitude read from the observed quaternion is the simulator's."""
    from racebench.agents.control import acceleration_command, command_to_ctbr, rotation_from_state

    expert = FastPlannerAgent(integral_gain=0.0, gate_clearance=0.5, wanted_clearance=0.6)
    obs, _ = s_env.reset(seed=1)
    expert.reset(env=s_env.unwrapped)
    state = s_env.unwrapped._state_vector
    done, steps = False, 0
    while not done:
        action = expert.act(obs)
        drone = s_env.unwrapped.drone
        np.testing.assert_allclose(rotation_from_state(state()), drone.rotation, atol=1e-6)
        command = acceleration_command(*expert.command, drone.rotation)
        assert command.dtype == np.float32 and np.all(np.abs(command) <= 1.0)
        np.testing.assert_allclose(command_to_ctbr(command, state()), action, atol=1e-5)
        obs, _, terminated, truncated, info = s_env.step(action)
        done, steps = terminated or truncated, steps + 1
    assert info["is_success"] and steps > 100


def test_an_acceleration_command_is_in_the_heading_frame():
    """Level and facing +y (yaw 90 degrees), the command "forward at 10 m/s^2" tilts the thrust toward world +y: a
    positive roll rate ... by the sign of the SO(3) error; and with no acceleration asked, hover thrust (the weight)."""
    from racebench.agents.control import COMMAND_ACCEL_SCALE, acceleration_command, command_to_ctbr, heading_yaw
    from racebench.sim.quadrotor import QuadrotorParams

    params = QuadrotorParams()
    yaw = math.pi / 2
    rotation = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # body x along world +y
    assert heading_yaw(rotation) == pytest.approx(yaw)
    quat = np.array([0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)])
    state = np.zeros(17, np.float32)
    state[10:14] = quat
    command = acceleration_command(np.array([0.0, 10.0, 0.0]), yaw, rotation)  # world +y is forward
    np.testing.assert_allclose(command, [10.0 / COMMAND_ACCEL_SCALE[0], 0.0, 0.0, 0.0], atol=1e-7)
    action = command_to_ctbr(command, state)
    # pitch forward (body y rate > 0 tips body z toward body x), no roll, no yaw
    assert action[2] > 0.0 and abs(action[1]) < 1e-6 and abs(action[3]) < 1e-6
    hover = command_to_ctbr(np.zeros(4, np.float32), state)
    assert (hover[0] + 1.0) / 2.0 * params.max_thrust == pytest.approx(params.mass * params.gravity, rel=1e-6)
    np.testing.assert_allclose(hover[1:], 0.0, atol=1e-7)
    # batched: one row per state
    batch = command_to_ctbr(np.stack([command, np.zeros(4, np.float32)]), np.stack([state, state]))
    np.testing.assert_allclose(batch, np.stack([action, hover]))


def _without(scene, drop):
    """``scene`` without the obstacles whose indices are in ``drop``."""
    return dataclasses.replace(scene, obstacles=tuple(o for j, o in enumerate(scene.obstacles) if j not in drop))


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_seen_only_expert_plans_at_reset_around_what_the_camera_shows(s_env, seed):
    """At reset the "seen" expert knows exactly the obstacles in view from the start pose, and its line is the
    privileged expert's line in the scene without the others; on these scenes an obstacle out of view lies within
    the privileged line's berth, so the privileged line differs (it bends for what the camera has not shown)."""
    s_env.reset(seed=seed)
    env = s_env.unwrapped
    seen = FastPlannerAgent(obstacle_knowledge="seen")
    seen.reset(env)
    sight = ObstacleSight(env.camera, env.scene)
    np.testing.assert_array_equal(seen.known, sight.in_view(env.drone.position, env.drone.rotation))
    hidden = set(np.flatnonzero(~seen.known).tolist())
    assert hidden and seen.known.any()
    reference = FastPlannerAgent()
    assert reference.plan(_without(env.scene, hidden), env.drone.position, 0.0, env.params)
    np.testing.assert_array_equal(seen.path, reference.path)
    privileged = FastPlannerAgent()
    privileged.reset(env)
    assert privileged.known.all()
    assert seen.path.shape != privileged.path.shape or not np.array_equal(seen.path, privileged.path)


def test_a_seen_only_experts_knowledge_is_what_its_camera_has_shown_over_a_lap(s_env):
    """Flying a lap, the expert's known obstacles after each step are those in view at any step so far (checked
    with a separate sight), and at least one comes into view near its line and makes it plan again. It flies most of
    the lap (3 of the 4 gates: on env version 3's seed 1 it clips the last frame, seeing only what its camera shows)."""
    s_env.reset(seed=1)
    env = s_env.unwrapped
    agent = FastPlannerAgent(obstacle_knowledge="seen")
    agent.reset(env)
    sight = ObstacleSight(env.camera, env.scene)
    shown = sight.in_view(env.drone.position, env.drone.rotation)
    info: dict = {}
    for _ in range(1000):
        shown |= sight.in_view(env.drone.position, env.drone.rotation)
        action = agent.act()
        np.testing.assert_array_equal(agent.known, shown)
        _, _, terminated, truncated, info = s_env.step(action)
        if terminated or truncated:
            break
    assert info["gates_passed"] >= 3, info
    assert agent.sighting_replans >= 1 and agent.replan_failures == 0
    assert agent.replans == agent.sighting_replans  # no replan_distance: every replan came from a sighting


def test_a_sighting_replans_only_when_the_new_obstacle_is_near_the_line(s_env):
    """Forgetting an obstacle in view, the next look marks it known again and asks for a new plan exactly when it
    lies within the berth (``wanted_clearance``) of the line still to fly."""
    s_env.reset(seed=2)
    env = s_env.unwrapped
    agent = FastPlannerAgent(obstacle_knowledge="seen")
    agent.reset(env)
    in_view = np.flatnonzero(agent.known)
    for j in in_view:  # forget one obstacle in view at a time: looking again marks it known
        agent.known[j] = False
        single = dataclasses.replace(env.scene, gates=(), obstacles=(env.scene.obstacles[j],))
        near = float(single.distance(agent.path).min()) < agent.wanted_clearance
        assert agent._look() is near
        assert agent.known[j]
    assert agent._look() is False  # nothing new in view


def test_an_unknown_obstacle_knowledge_is_refused():
    with pytest.raises(ValueError, match="obstacle_knowledge must be one of"):
        FastPlannerAgent(obstacle_knowledge="some")
