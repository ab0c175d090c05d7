"""Env and airframe parameters are range-checked when the env is made (issue 50, item 5), and valid input is untouched.

Bad values (the issue's: ``density=10**6`` grew to 17.8 GB in ``reset``, ``gate_shift=1e6`` ran out of memory,
``max_thrust=inf`` gave a NaN observation) must fail in ``gym.make`` with a one-line ``ValueError`` naming the
parameter; every registered id, curriculum level and shipped config must still construct, and the scenes of fixed
seeds must be those the code drew before the checks existed (``tests/data/scene_digests.json``).
"""

from __future__ import annotations

import json
import math
import tracemalloc
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import yaml
from scene_digest import SEED_GROUPS, all_digests  # tests/ is on sys.path (pytest rootdir-less import)

import racebench
from racebench.envs import env as env_module
from racebench.envs.env import RaceEnv
from racebench.envs.registration import CURRICULUM, ENV_KWARGS, ENV_VERSION
from racebench.sim.obstacles import (
    MAX_ATTEMPTS,
    MAX_DENSITY,
    MAX_GATE_SHIFT,
    MAX_GATE_SHIFT_Z,
    MAX_SCENE_OBSTACLES,
    ObstacleGenerator,
)
from racebench.sim.quadrotor import PARAM_RANGES, QuadrotorParams
from racebench.sim.track import load_track, parse_track

ROOT = Path(__file__).parents[1]
NAN, INF = float("nan"), float("inf")


def _refused(kwargs: dict[str, Any]) -> str:
    """The message of the ValueError ``gym.make("RaceObs-S-v0", **kwargs)`` raises (the test fails without one)."""
    with pytest.raises(ValueError) as caught:
        env = gym.make("RaceObs-S-v0", obs_mode="state", **kwargs)
        env.close()
    message = str(caught.value)
    assert "\n" not in message, f"not one line: {message!r}"
    return message


# ----------------------------------------------------------------- bad values are refused at construction
BAD_ENV_VALUES = [
    # the inputs
    ({"density": 10**6}, "density"),
    ({"gate_shift": 1e6}, "gate_shift"),
    ({"gate_shift_z": 1e6}, "gate_shift_z"),
    ({"quadrotor": {"max_thrust": INF}}, "max_thrust"),
    # density: above the bound, negative, wrong type
    ({"density": MAX_DENSITY + 1}, "density"),
    ({"density": -1}, "density"),
    ({"density": 3.0}, "density"),
    ({"density": "3"}, "density"),
    ({"density": None}, "density"),
    # gate shifts: NaN, inf, negative, above the bound, wrong type; a default z shift beyond its bound
    ({"gate_shift": NAN}, "gate_shift"),
    ({"gate_shift": INF}, "gate_shift"),
    ({"gate_shift": -0.1}, "gate_shift"),
    ({"gate_shift": MAX_GATE_SHIFT + 0.01}, "gate_shift"),
    ({"gate_shift": "0.5"}, "gate_shift"),
    ({"gate_shift": 1.5}, "gate_shift_z"),
    ({"gate_shift_z": NAN}, "gate_shift_z"),
    ({"gate_shift_z": -0.3}, "gate_shift_z"),
    ({"gate_shift_z": MAX_GATE_SHIFT_Z + 0.01}, "gate_shift_z"),
    # start spread: NaN, inf, negative, huge, wrong shape or type, below the ground
    ({"start_spread": (NAN, 0.5, 0.5)}, "start_spread"),
    ({"start_spread": (0.5, INF, 0.5)}, "start_spread"),
    ({"start_spread": (0.5, -0.5, 0.5)}, "start_spread"),
    ({"start_spread": (1e9, 0.5, 0.5)}, "start_spread"),
    ({"start_spread": (0.5, 0.5)}, "start_spread"),
    ({"start_spread": "0.5"}, "start_spread"),
    ({"start_spread": 0.5}, "start_spread"),
    ({"start_spread": (0.5, 0.5, 0.9)}, "start_spread"),
    # desired speed, depth noise, time limit, rates
    ({"desired_speed": 0.0}, "desired_speed"),
    ({"desired_speed": -3.0}, "desired_speed"),
    ({"desired_speed": INF}, "desired_speed"),
    ({"desired_speed": 1e3}, "desired_speed"),
    ({"desired_speed": "fast"}, "desired_speed"),
    ({"depth_noise_std": INF}, "depth_noise_std"),
    ({"depth_noise_std": 1e6}, "depth_noise_std"),
    ({"max_episode_time": 1e12}, "max_episode_time"),
    ({"max_episode_time": NAN}, "max_episode_time"),
    ({"physics_freq": 10**6}, "physics_freq"),
    ({"physics_freq": 50, "control_freq": 50}, "physics_freq"),
    ({"control_freq": 0}, "control_freq"),
    ({"control_freq": 50.0}, "control_freq"),
    # airframe: the type of the argument, and fields through the env
    ({"quadrotor": [1.0]}, "quadrotor"),
    ({"quadrotor": {"mass": NAN}}, "mass"),
    ({"quadrotor": {"mass": -1.0}}, "mass"),
    ({"quadrotor": {"max_thrust": 1e4}}, "max_thrust"),
    ({"quadrotor": {"max_thrust": 5.0}}, "max_thrust"),
    ({"quadrotor": {"inertia": (0.0, 1e-3, 1e-3)}}, "inertia"),
    ({"quadrotor": {"max_body_rate": (6.0, 6.0, 0.0)}}, "max_body_rate"),
    ({"quadrotor": {"collision_radius": 0.45}}, "collision_radius"),
    ({"reward_weights": {"passing": INF}}, "reward_weights"),
]


BAD_ENV_IDS = [f"{named}-{i}" for i, (_, named) in enumerate(BAD_ENV_VALUES)]


@pytest.mark.parametrize(("kwargs", "named"), BAD_ENV_VALUES, ids=BAD_ENV_IDS)
def test_bad_env_values_are_refused_at_make_naming_the_parameter(kwargs: dict[str, Any], named: str) -> None:
    message = _refused(kwargs)
    assert named in message
    assert "got" in message  # the value given is quoted


@pytest.mark.parametrize(
    ("kwargs", "expected"),
    [
        ({"density": 10**6}, "density must be an int in [0, 20], got 1000000"),
        ({"gate_shift": 1e6}, "gate_shift must be a finite number in [0, 2] m, got 1000000.0"),
        ({"gate_shift_z": 1e6}, "gate_shift_z must be a finite number in [0, 1] m, got 1000000.0"),
        ({"desired_speed": NAN}, "desired_speed must be a finite number in (0, 20] m/s, got nan"),
        ({"quadrotor": {"max_thrust": INF}}, "QuadrotorParams.max_thrust must be a finite number in (0, 10000] N"),
        ({"quadrotor": {"max_thrust": 1e3}}, "QuadrotorParams.max_thrust must be in (5.6898, 113.796] N"),
    ],
)
def test_messages_give_the_value_and_the_allowed_range(kwargs: dict[str, Any], expected: str) -> None:
    assert _refused(kwargs).startswith(expected)


def test_refusals_come_before_any_allocation() -> None:
    """The issue's density and shifts used to grow to gigabytes in reset; now construction stops them cold."""
    tracemalloc.start()
    try:
        for kwargs in ({"density": 10**6}, {"gate_shift": 1e6}, {"gate_shift_z": 1e6}):
            _refused(kwargs)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 50e6, f"{peak / 1e6:.0f} MB allocated while refusing"


def test_set_task_checks_the_same_ranges() -> None:
    env = RaceEnv(track="S", obs_mode="state")
    for kwargs, named in (
        ({"density": 10**6}, "density"),
        ({"gate_shift": 1e6}, "gate_shift"),
        ({"gate_shift_z": NAN}, "gate_shift_z"),
        ({"desired_speed": INF}, "desired_speed"),
        ({"desired_speed": 0.0}, "desired_speed"),
    ):
        with pytest.raises(ValueError, match=f"^{named} must"):
            env.set_task(**kwargs)
    assert env.generator.gate_shift_z == 0.0 and env.generator.density == 3  # refused tasks changed nothing
    env.set_task(density=MAX_DENSITY, gate_shift=MAX_GATE_SHIFT_Z, desired_speed=20.0)  # the bounds are allowed
    assert env.generator.density == MAX_DENSITY and env.generator.gate_shift_z == MAX_GATE_SHIFT_Z
    env.close()


def _bad_field_values() -> list[tuple[str, Any]]:
    """For every airframe field: NaN, inf, below and above its range, and wrong types."""
    cases: list[tuple[str, Any]] = []
    for name, (low, high, _, _) in PARAM_RANGES.items():
        triple = name in ("inertia", "max_body_rate", "rate_gain", "drag_coefficients")
        below = low - 1.0 if low == 0 else low / 2.0
        for bad in (NAN, INF, -INF, below, high * 2.0 + 1.0, "1", None, True):
            cases.append((name, (1e-3, 1e-3, bad) if triple else bad))
        if triple:
            cases += [(name, (1e-3, 1e-3)), (name, 1e-3), (name, "abc")]
    return cases


@pytest.mark.parametrize(("name", "value"), _bad_field_values())
def test_every_airframe_field_is_bounded(name: str, value: Any) -> None:
    with pytest.raises(ValueError, match=rf"^QuadrotorParams\.{name} must"):
        QuadrotorParams(**{name: value})


@pytest.mark.parametrize(
    ("fields", "named"),
    [
        ({"max_thrust": 0.58 * 9.81}, "max_thrust"),  # thrust-to-weight 1: it cannot hover
        ({"max_thrust": 0.58 * 9.81 * 20.5}, "max_thrust"),  # thrust-to-weight 20.5
        ({"mass": 5.0}, "max_thrust"),  # the default 14 N cannot lift 5 kg
        ({"inertia": (1e-3, 1e-3, 3e-3)}, "inertia"),  # Jx + Jy < Jz: no rigid body has it
        ({"collision_radius": 0.05}, "collision_radius"),  # smaller than the 0.075 m arms
    ],
)
def test_airframe_fields_are_checked_together(fields: dict[str, Any], named: str) -> None:
    with pytest.raises(ValueError, match=rf"^QuadrotorParams\.{named} must"):
        QuadrotorParams(**fields)


def test_extreme_valid_airframes_fly_finite() -> None:
    """At the edges of the ranges the simulation stays finite (``max_thrust=inf`` gave NaN at step 1)."""
    edges = [
        {"max_thrust": 0.58 * 9.81 * 20.0},
        {
            "mass": 10.0,
            "max_thrust": 10 * 9.81 * 20,
            "inertia": (10.0, 10.0, 10.0),
            "arm_length": 0.3,
            "collision_radius": 0.3,
        },
        {"max_body_rate": (35.0, 35.0, 35.0), "rate_gain": (50.0, 50.0, 50.0), "motor_time_constant": 0.5},
    ]
    rng = np.random.default_rng(0)
    for fields in edges:
        env = gym.make("RaceObs-S-Level1-v0", obs_mode="state", quadrotor=fields, physics_freq=100, control_freq=50)
        obs, _ = env.reset(seed=0)
        for _ in range(100):
            obs, reward, terminated, truncated, _ = env.step(rng.uniform(-1, 1, 4).astype(np.float32))
            assert np.all(np.isfinite(obs)) and math.isfinite(reward), fields
            if terminated or truncated:
                obs, _ = env.reset()
        env.close()


# ----------------------------------------------------------------- a layout's cost is bounded up front
def _many_region_track(regions: int, scale: float = 1.0) -> Any:
    """A straight sprint of ``regions + 1`` gates ``4 * scale`` m apart, one obstacle region per leg."""
    gates = [{"center": [4.0 * scale * (i + 1), 0.0, 1.0], "yaw_deg": 0} for i in range(regions + 1)]
    return parse_track(
        {
            "name": "long",
            "closed_loop": False,
            "gates": gates,
            "start": {"center": [1.0, 0.0, 1.0], "yaw_deg": 0},
            "obstacle_regions": [{"between": [i, i + 1]} for i in range(regions)],
        }
    )


def test_obstacles_per_scene_are_bounded_by_the_tracks_regions() -> None:
    regions = 40
    most = MAX_SCENE_OBSTACLES // regions
    track = _many_region_track(regions)
    ObstacleGenerator(track, density=most)
    with pytest.raises(ValueError, match=rf"^density must be at most {most} on track 'long'"):
        ObstacleGenerator(track, density=most + 1)


def test_corridor_grid_and_attempts_are_bounded() -> None:
    with pytest.raises(ValueError, match="^grid_resolution must"):
        ObstacleGenerator(load_track("S"), grid_resolution=1e-4)
    with pytest.raises(ValueError, match="^grid_resolution must"):  # a 1.6 km track at the default 0.1 m
        ObstacleGenerator(_many_region_track(1, scale=200.0), density=0)
    with pytest.raises(ValueError, match="^max_attempts must"):
        ObstacleGenerator(load_track("S"), max_attempts=MAX_ATTEMPTS + 1)
    ObstacleGenerator(load_track("S"), max_attempts=MAX_ATTEMPTS)


def test_settings_no_layout_can_meet_are_refused() -> None:
    """A start box no gate shift can clear, or a drone too wide for the gates, used to fail every reset."""
    data = yaml.safe_load((ROOT / "tracks" / "S.yaml").read_text())
    data["start"]["center"] = [2.8, 0.0, 1.0]  # 0.2 m before the first gate's plane, 0.52 m from its frame
    near = parse_track(data)
    with pytest.raises(ValueError, match="^start_spread must keep the start region"):
        ObstacleGenerator(near)
    ObstacleGenerator(near, gate_shift=0.3)  # shifted gates can move away from it: some layouts pass
    with pytest.raises(ValueError, match="^drone_radius must be < 0.42"):
        ObstacleGenerator(load_track("S"), drone_radius=0.42)


# ----------------------------------------------------------------- valid input is unchanged
def _shipped_settings() -> list[dict[str, Any]]:
    """Every mapping of env settings in ``baselines/**/*.yaml`` (configs, curriculum levels), deduplicated."""
    keys = {"density", "desired_speed", "gate_shift", "gate_shift_z", "start_spread", "depth_noise_std"}
    found: dict[str, dict[str, Any]] = {}

    def walk(node: Any) -> None:
        if isinstance(node, dict):
            settings = {k: v for k, v in node.items() if k in keys and v is not None}
            if settings:
                found[json.dumps(settings, sort_keys=True)] = settings
            for value in node.values():
                walk(value)
        elif isinstance(node, list):
            for value in node:
                walk(value)

    for path in sorted((ROOT / "baselines").rglob("*.yaml")):
        walk(yaml.safe_load(path.read_text()))
    return list(found.values())


def test_every_shipped_setting_is_valid() -> None:
    settings = _shipped_settings()
    densities = [s["density"] for s in settings if "density" in s]
    assert len(settings) >= 5 and max(densities) <= MAX_DENSITY  # the densest is the curriculum's 4
    for track in ("S", "J", "Circle"):
        for kwargs in settings:
            kwargs = {**kwargs, "start_spread": tuple(kwargs["start_spread"])} if "start_spread" in kwargs else kwargs
            RaceEnv(track=track, obs_mode="state", **kwargs).close()
    env = RaceEnv(track="S", obs_mode="state")
    for level in CURRICULUM.values():
        env.set_task(**level)
    env.close()


def test_every_registered_id_constructs_within_the_ranges() -> None:
    assert max(kwargs.get("density", 3) for kwargs in ENV_KWARGS.values()) <= MAX_DENSITY
    assert max(kwargs.get("gate_shift", 0.0) for kwargs in ENV_KWARGS.values()) <= MAX_GATE_SHIFT_Z
    for env_id in racebench.ENV_IDS:
        gym.make(env_id, obs_mode="state").close()


def test_the_docstring_lists_every_range() -> None:
    doc = RaceEnv.__doc__
    for name in ("density", "gate_shift", "gate_shift_z", "start_spread", "desired_speed", "depth_noise_std"):
        assert f"``{name}``" in doc, name
    for name in ("max_episode_time", "physics_freq", "control_freq", "quadrotor", "reward_weights"):
        assert f"``{name}``" in doc, name
    assert f"0 … {MAX_DENSITY}" in doc and f"0 … {MAX_GATE_SHIFT:.1f} m" in doc and f"{MAX_SCENE_OBSTACLES}" in doc
    assert f"(0, {env_module.MAX_DESIRED_SPEED:g}]" in doc and f"0 … {env_module.MAX_DEPTH_NOISE_STD:g}" in doc
    for name in PARAM_RANGES:
        assert name in doc, name


def test_scenes_of_every_registered_id_are_unchanged() -> None:
    """ENV_VERSION stays 3: the scenes of seeds 0-99 and of evaluation seeds match the digests made for it (version
    2's scenes are kept by ``obstacle_placement="box"``: tests/test_placement.py)."""
    assert ENV_VERSION == 3
    reference = json.loads((Path(__file__).parent / "data" / "scene_digests.json").read_text())
    assert reference["env_version"] == ENV_VERSION
    assert reference["seed_groups"] == SEED_GROUPS
    assert set(reference["digests"]) == set(racebench.ENV_IDS)
    assert all_digests() == reference["digests"]


def test_digests_follow_the_scene_reset_draws() -> None:
    """The digest draws from the env's generator directly: that is the scene ``reset(seed=...)`` builds."""
    from gymnasium.utils import seeding

    env = gym.make("RaceObs-J-GateShift0.5-v0", obs_mode="state")
    for seed in (0, 1_000_005):
        env.reset(seed=seed)
        drawn = env.unwrapped.generator.sample_scene(seeding.np_random(seed)[0])
        assert env.unwrapped.scene.to_dict() == drawn.to_dict()
    env.close()
