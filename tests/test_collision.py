"""Every touch is a crash: scripted flights into every kind of surface, grazes, clean passes, and the detector
against an independent sphere-to-primitive distance (``tests/reference_geometry.py``)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from reference_geometry import nearest_surface  # tests/ is on sys.path (pytest rootdir-less import)

from racebench.envs.env import RaceEnv
from racebench.sim.collision import CONTACT_TOLERANCE, SWEEP_RESOLUTION, CollisionChecker
from racebench.sim.scene import Obstacle

SPEEDS = (1.0, 4.0, 10.0, 20.0)
R = 0.12  # QuadrotorParams().collision_radius


@pytest.fixture(scope="module")
def env() -> RaceEnv:
    env = RaceEnv(track="S", density=0, obs_mode="state")
    env.reset(seed=0)
    env.base_scene = env.scene  # obstacle-free; tests that add obstacles pass their own scene
    assert env.params.collision_radius == R
    yield env
    env.close()


def fly(env: RaceEnv, start, velocity, scene=None, seconds: float = 1.5) -> dict:
    """Put the drone at ``start`` moving at ``velocity`` (level, nose along x) and hold hover thrust."""
    scene = dataclasses.replace(scene or env.base_scene, start_position=np.array(start, float), start_yaw=0.0)
    env.reset(options={"scene": scene})
    env.sim.reset_drone(np.array(start, float), 0.0, np.array(velocity, float))
    env.drone = env.sim.drone_state()
    hover = np.array([env.params.hover_action, 0.0, 0.0, 0.0], dtype=np.float32)
    info: dict = {}
    for _ in range(int(seconds * env.control_freq)):
        _, _, terminated, truncated, info = env.step(hover)
        if terminated or truncated:
            return {**info, "terminated": terminated}
    return {**info, "terminated": False}


def gate0(env: RaceEnv):
    gate = env.base_scene.gates[0]
    assert gate.yaw == 0.0  # gate 0 of S faces +x: the offsets below are in world y and z
    return gate


def approach(gate, dy: float, dz: float, speed: float, angle_deg: float = 0.0):
    """Start 0.6 m (+ one control step of travel) before the gate plane, aimed to cross it at (dy, dz)."""
    lead = 0.6 + speed / 50.0
    a = math.radians(angle_deg)
    direction = np.array([math.cos(a), math.sin(a), 0.0])
    target = gate.center + np.array([0.0, dy, dz])
    return target - lead * direction / direction[0], speed * direction


# ---------------------------------------------------------------- crashes


@pytest.mark.parametrize("speed", SPEEDS)
@pytest.mark.parametrize(
    "where, dy, dz",
    [
        ("side bar, head-on", 0.57, 0.0),
        ("top bar, head-on", 0.0, 0.57),
        ("bottom bar, head-on", 0.0, -0.57),
        ("corner", 0.57, 0.57),
        ("side bar, grazing 1 mm overlap", 0.5 - R + 1e-3, 0.0),
        ("top bar, grazing 1 mm overlap", 0.0, 0.5 - R + 1e-3),
        ("outer edge, grazing 1 mm overlap", 0.64 + R - 1e-3, 0.0),
    ],
)
def test_flights_into_a_gate_frame_crash_on_it(env: RaceEnv, speed: float, where: str, dy: float, dz: float) -> None:
    gate = gate0(env)
    start, velocity = approach(gate, dy, dz, speed)
    info = fly(env, start, velocity)
    assert info["terminated"] and info["crashed"] and info["crash_reason"] == "gate:0", (where, info)
    assert info["gates_passed"] == 0 and not info["is_success"]


@pytest.mark.parametrize("speed", SPEEDS)
@pytest.mark.parametrize("angle", [-30.0, 15.0, 45.0])
def test_angled_scrapes_of_the_opening_are_crashes_not_passes(env: RaceEnv, speed: float, angle: float) -> None:
    gate = gate0(env)
    # Aimed so the centre crosses the plane 1 mm less than a radius from the inner edge on the side it moves to.
    side = 1.0 if angle > 0 else -1.0
    start, velocity = approach(gate, side * (0.5 - R * 0.5), 0.0, speed, angle)
    info = fly(env, start, velocity)
    assert info["crashed"] and info["crash_reason"] == "gate:0" and info["gates_passed"] == 0, info


@pytest.mark.parametrize("speed", SPEEDS)
def test_a_clean_pass_through_the_centre_counts(env: RaceEnv, speed: float) -> None:
    gate = gate0(env)
    start, velocity = approach(gate, 0.0, 0.0, speed)
    info = fly(env, start, velocity, seconds=(0.6 + speed / 50.0) / speed + 0.1)
    assert info["gates_passed"] == 1 and not info["crashed"], info


@pytest.mark.parametrize("speed", SPEEDS)
def test_a_pass_clearing_the_frame_by_2_mm_counts(env: RaceEnv, speed: float) -> None:
    gate = gate0(env)
    start, velocity = approach(gate, 0.5 - R - CONTACT_TOLERANCE - 1e-3, 0.0, speed)
    info = fly(env, start, velocity, seconds=0.6 / speed + 0.1)
    assert info["gates_passed"] == 1 and not info["crashed"], info


def scene_with(env: RaceEnv, *obstacles: Obstacle):
    return dataclasses.replace(env.base_scene, obstacles=tuple(obstacles))


@pytest.mark.parametrize("speed", SPEEDS)
@pytest.mark.parametrize("offset", [0.0, 0.3 + R - 1e-3])  # head-on, and grazing the pole's side by 1 mm
def test_flights_into_a_pole_crash(env: RaceEnv, speed: float, offset: float) -> None:
    pole = Obstacle("cylinder", np.array([6.0, 3.0, 1.5]), (0.3, 3.0))
    info = fly(env, [6.0 - 0.6 - 0.3 - speed / 50, 3.0 + offset, 1.0], [speed, 0.0, 0.0], scene_with(env, pole))
    assert info["crashed"] and info["crash_reason"] == "obstacle:0", info


@pytest.mark.parametrize("speed", SPEEDS)
@pytest.mark.parametrize("yaw", [0.0, 0.6])
def test_flights_into_a_box_crash(env: RaceEnv, speed: float, yaw: float) -> None:
    box = Obstacle("box", np.array([6.0, 3.0, 0.75]), (0.3, 0.4, 0.75), yaw)
    other = Obstacle("cylinder", np.array([6.0, 8.0, 1.5]), (0.2, 3.0))
    info = fly(env, [6.0 - 1.2 - speed / 50, 3.0, 1.0], [speed, 0.0, 0.0], scene_with(env, other, box))
    assert info["crashed"] and info["crash_reason"] == "obstacle:1", info


@pytest.mark.parametrize("speed", SPEEDS)
def test_flights_into_the_ground_crash(env: RaceEnv, speed: float) -> None:
    info = fly(env, [6.0, 3.0, 1.0], [speed * 0.6, 0.0, -speed * 0.8])
    assert info["crashed"] and info["crash_reason"] == "ground", info


def test_grazing_the_ground_by_1_mm_is_a_crash(env: RaceEnv) -> None:
    info = fly(env, [6.0, 3.0, R - 1e-3], [4.0, 0.0, 0.0])
    assert info["crashed"] and info["crash_reason"] == "ground", info


def test_the_drone_never_bounces(env: RaceEnv) -> None:
    """No collision response in the physics: a hit stops the episode with the velocity it had."""
    gate = gate0(env)
    start, velocity = approach(gate, 0.57, 0.0, 4.0)
    fly(env, start, velocity)
    assert env.drone.velocity[0] > 3.5  # Bullet used to push it back (e.g. 3.9 → 0.6 m/s)


# ------------------------------------------------- against an independent distance


def test_clearance_matches_the_independent_distance() -> None:
    env = RaceEnv(track="J", density=5, obs_mode="state")
    env.reset(seed=3)
    rng = np.random.default_rng(0)
    low, high = env.scene.arena_low, env.scene.arena_high
    points = rng.uniform(low, high, size=(2000, 3))
    reference, names = nearest_surface(env.scene.to_dict(), points)
    checker = CollisionChecker(env.scene, R)
    ours = np.array([checker.clearance(tuple(p)) for p in points])
    np.testing.assert_allclose(ours, reference - R, atol=1e-9)
    env.close()


@pytest.mark.parametrize("track, density, seed", [("S", 3, 0), ("J", 5, 1), ("Circle", 4, 2)])
def test_swept_detector_agrees_with_dense_sampling_of_the_independent_distance(
    track: str, density: int, seed: int
) -> None:
    """Random substep segments (up to 20 m/s × 5 ms) near surfaces: a touch iff the reference says so."""
    env = RaceEnv(track=track, density=density, obs_mode="state")
    env.reset(seed=seed)
    scene = env.scene.to_dict()
    checker = CollisionChecker(env.scene, R)
    rng = np.random.default_rng(seed)
    # Segments start near surfaces so that touches and near-misses are both common.
    surfaces = np.array([g["center"] for g in scene["gates"]] + [o["position"] for o in scene["obstacles"]])
    anchors = surfaces[rng.integers(len(surfaces), size=3000)] + rng.normal(0.0, 0.5, size=(3000, 3))
    anchors[:, 2] = np.abs(anchors[:, 2])
    steps = rng.normal(size=(3000, 3))
    steps *= (rng.uniform(0.0, 0.1, size=3000) / np.linalg.norm(steps, axis=1))[:, None]
    threshold = R + CONTACT_TOLERANCE
    samples = np.linspace(0.0, 1.0, 401)  # ≤ 0.25 mm apart on a 0.1 m segment
    checked = touches = 0
    for a, d in zip(anchors, steps, strict=True):
        path = a + samples[:, None] * d
        distance, names = nearest_surface(scene, path)
        closest = distance.min()
        spacing = np.linalg.norm(d) / (len(samples) - 1)
        if abs(closest - threshold) <= spacing / 2 + SWEEP_RESOLUTION:
            continue  # within the sampling and sweep resolution of the threshold: either answer is right
        got = checker.contact(tuple(a), tuple(a + d))
        checked += 1
        if closest < threshold:
            touches += 1
            first = int(np.argmax(distance <= threshold))
            assert got is not None, (a, d, closest)
            assert got in {names[max(first - 1, 0)], names[first], names[min(first + 1, len(names) - 1)]}
        else:
            assert got is None, (a, d, closest, got)
    assert checked > 2500 and 300 < touches < checked - 300  # both outcomes well represented
    env.close()
