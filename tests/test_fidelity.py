"""``docs/fidelity.md`` states the code's numbers (issue 69, item 2).

Every code span on the page of the form ``name = value`` is a claim. ``name`` is a path into the code: a root
from :func:`roots` followed by ``.attribute`` or ``[key]`` steps. ``value`` is YAML. Each claim must resolve and
equal the code. Every number in :func:`required_claims` must be claimed, so a row cannot silently leave the page.
The training-config table must have one row per PPO config in ``baselines/``, with every cell equal to
``TrainConfig.from_yaml``. Change a number in the code and this fails until the page says the same.
"""

from __future__ import annotations

import dataclasses
import functools
import inspect
import math
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import yaml

from racebench.agents.recurrent import RaceFeatures
from racebench.envs import observations, registration
from racebench.envs.env import RaceEnv
from racebench.envs.reward import RewardWeights
from racebench.envs.starts import START_POINT_DISTANCE, START_POINT_TRIES
from racebench.sim import placement
from racebench.sim.camera import DepthCamera
from racebench.sim.collision import CONTACT_TOLERANCE
from racebench.sim.corridor import CORRIDOR_MARGIN
from racebench.sim.obstacles import ObstacleGenerator
from racebench.sim.quadrotor import QuadrotorParams
from racebench.sim.track import load_track
from racebench.training.config import TrainConfig
from racebench.training.run import load_config
from racebench.utils.yamlfile import read_yaml

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "fidelity.md"
TRACKS = ("S", "J", "Circle")
#: A claim: `name = value` in code font. The name is a root, then `.attribute` / `[key]` steps.
CLAIM = re.compile(r"`([A-Za-z][\w\-]*(?:\.[A-Za-z_]\w*|\[[^\]`]+\])*) = ([^`]+)`")
ROOT_NAME = re.compile(r"[A-Za-z][\w\-]*")
STEP = re.compile(r"\.([A-Za-z_]\w*)|\[([^\]]+)\]")
#: The placement statistics' protocol (``authors-code-facts.md`` §2): 300 scenes of each main id.
MEASURED_SCENES, MEASURED_SEED = 300, 10_000
CONFIG_TABLE_HEADER = "| config |"


# ----------------------------------------------------------------------------------------------- the code's side
def _defaults(cls: type) -> dict[str, Any]:
    """The keyword defaults of ``cls.__init__``."""
    parameters = inspect.signature(cls.__init__).parameters.values()
    return {p.name: p.default for p in parameters if p.default is not inspect.Parameter.empty}


def _track(name: str) -> dict[str, Any]:
    track = load_track(name)
    sizes = [{"inner": g.inner, "outer": g.outer, "depth": g.depth} for g in track.gates]
    return {
        "gates": [g.center for g in track.gates],
        "start": {"center": track.start.center, "spread": track.start.spread, "yaw_deg": math.degrees(track.start.yaw)},
        "closed_loop": track.closed_loop,
        "gate_size": sizes[0] if all(s == sizes[0] for s in sizes) else sizes,
        "obstacle_band": track.obstacle_band,
        "obstacle_regions": len(track.obstacle_regions),
    }


def _airframe() -> dict[str, float]:
    """Derived airframe numbers, rounded as the page states them."""
    p = QuadrotorParams()
    return {
        "thrust_to_weight": round(p.max_thrust / (p.mass * p.gravity), 2),
        "max_acceleration": round(p.max_thrust / p.mass, 1),
        "hover_action": round(p.hover_action, 3),
    }


@functools.cache
def _measured() -> dict[str, dict[float, float]]:
    """Share of obstacles within 0.25 / 0.5 / 1.0 m of the racing line over the main ids' first scenes."""
    registration.register_envs()
    shares = {}
    for track in TRACKS:
        env = gym.make(f"RaceObs-{track}-v0", obs_mode="state")
        scenes = []
        for k in range(MEASURED_SCENES):
            env.reset(seed=MEASURED_SEED + k)
            scenes.append(env.unwrapped.scene)
        distances = placement.obstacle_line_distances(scenes, env.unwrapped.track)
        env.close()
        shares[track] = {r: round(v, 3) for r, v in placement.centreline_fractions(distances).items()}
    return shares


@functools.cache
def roots() -> dict[str, Callable[[], Any]]:
    """Every name a claim can start with, and how to get its value from the code."""
    table: dict[str, Callable[[], Any]] = {
        "QuadrotorParams": QuadrotorParams,
        "airframe": _airframe,
        "RaceEnv": lambda: _defaults(RaceEnv),
        "DepthCamera": lambda: _defaults(DepthCamera),
        "ObstacleGenerator": lambda: _defaults(ObstacleGenerator),
        "RaceFeatures": lambda: _defaults(RaceFeatures),
        "RewardWeights": RewardWeights,
        "measured": _measured,
    }
    constants = {
        "ENV_VERSION": registration.ENV_VERSION,
        "MAX_EPISODE_STEPS": registration.MAX_EPISODE_STEPS,
        "CURRICULUM": registration.CURRICULUM,
        "DENSITIES": registration.DENSITIES,
        "GATE_SHIFTS": registration.GATE_SHIFTS,
        "HIGH_SPEED": registration.HIGH_SPEED,
        "ENV_KWARGS": registration.ENV_KWARGS,
        "START_POINT_DISTANCE": START_POINT_DISTANCE,
        "START_POINT_TRIES": START_POINT_TRIES,
        "CORRIDOR_MARGIN": CORRIDOR_MARGIN,
        "CONTACT_TOLERANCE": CONTACT_TOLERANCE,
        "AUTHORS_FRACTIONS": placement.AUTHORS_FRACTIONS,
        "TOLERANCE": placement.TOLERANCE,
        "MATCHED_RADII": placement.MATCHED_RADII,
        "STATE_DIM": observations.STATE_DIM,
        "POSITION_SCALE": observations.POSITION_SCALE,
        "VELOCITY_SCALE": observations.VELOCITY_SCALE,
        "STATE_LIMIT": observations.STATE_LIMIT,
    }
    table.update({name: (lambda value=value: value) for name, value in constants.items()})
    table.update({track: functools.partial(_track, track) for track in TRACKS})
    for path in sorted((ROOT / "baselines").glob("*.yaml")):  # a config, by its file name: vision-ppo.n_envs
        table[path.stem] = functools.partial(load_config, path)
    for path in sorted((ROOT / "baselines" / "sweeps").glob("*.yaml")):  # a sweep file: campaign-2.steps
        table[path.stem] = functools.partial(read_yaml, path)
    return table


def plain(value: Any) -> Any:
    """Dataclasses, arrays and tuples as plain dicts, lists and numbers."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, np.ndarray):
        return plain(value.tolist())
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, (list, tuple)):
        return [plain(v) for v in value]
    if isinstance(value, dict):
        return {k: plain(v) for k, v in value.items()}
    return value


def resolve(name: str) -> Any:
    """The code's value of a claim's name (``KeyError`` or ``AttributeError`` if the code has no such thing)."""
    root = ROOT_NAME.match(name)
    assert root is not None
    value = roots()[root.group(0)]()
    rest, position = name[root.end() :], 0
    for step in STEP.finditer(rest):
        assert step.start() == position, name
        position = step.end()
        attribute, key = step.groups()
        if attribute is not None:
            value = value[attribute] if isinstance(value, dict) else getattr(value, attribute)
        else:
            value = value[yaml.safe_load(key)]
    assert position == len(rest), name
    return plain(value)


def same(page: Any, code: Any) -> bool:
    """Whether the page's value is the code's: numbers to 1e-9 relative, containers element by element."""
    if isinstance(page, bool) or isinstance(code, bool) or page is None or code is None:
        return page is code
    if isinstance(page, (int, float)) and isinstance(code, (int, float)):
        return math.isclose(page, code, rel_tol=1e-9, abs_tol=1e-12)
    if isinstance(page, list) and isinstance(code, list):
        return len(page) == len(code) and all(same(a, b) for a, b in zip(page, code, strict=True))
    if isinstance(page, dict) and isinstance(code, dict):
        if len(page) != len(code):
            return False
        for key, value in page.items():
            match = [k for k in code if same(key, k)]
            if len(match) != 1 or not same(value, code[match[0]]):
                return False
        return True
    return type(page) is type(code) and page == code


# ----------------------------------------------------------------------------------------------- the page's side
def claims() -> list[tuple[str, str]]:
    """Every ``name = value`` span on the page, in order."""
    return CLAIM.findall(PAGE.read_text(encoding="utf-8"))


def config_table() -> tuple[list[str], list[list[str]]]:
    """The training-config table: its column names and its rows' cells (backticks removed)."""
    lines = PAGE.read_text(encoding="utf-8").splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith(CONFIG_TABLE_HEADER))

    def cells(line: str) -> list[str]:
        return [c.strip().strip("`") for c in line.strip().strip("|").split("|")]

    rows = []
    for line in lines[start + 2 :]:
        if not line.startswith("|"):
            break
        rows.append(cells(line))
    return cells(lines[start]), rows


def required_claims() -> set[str]:
    """The names the page must state: every number the issue asks the page to keep true."""
    vision_ppo = TrainConfig.from_yaml(ROOT / "baselines" / "vision-ppo.yaml")
    names = {f"QuadrotorParams.{f.name}" for f in dataclasses.fields(QuadrotorParams)}
    names |= {f"RewardWeights.{f.name}" for f in dataclasses.fields(RewardWeights)}
    names |= {f"CURRICULUM[{level}]" for level in registration.CURRICULUM}
    names |= {f"vision-ppo.levels[{level}]" for level in vision_ppo.levels}
    names |= {f"AUTHORS_FRACTIONS.{t}" for t in placement.AUTHORS_FRACTIONS} | {f"measured.{t}" for t in TRACKS}
    names |= {f"{t}.{key}" for t in TRACKS for key in ("gates", "start.center", "obstacle_band", "obstacle_regions")}
    names |= {f"RaceEnv.{key}" for key in ("control_freq", "physics_freq", "max_episode_time", "depth_noise_std")}
    names |= {f"DepthCamera.{key}" for key in ("size", "fov_deg", "min_depth", "max_depth", "offset")}
    names |= {f"ObstacleGenerator.{key}" for key in ("clearance", "radius_choices", "pole_height", "drone_radius")}
    ppo = (
        "n_envs", "n_steps", "batch_size", "n_epochs", "learning_rate", "gamma", "gae_lambda", "clip_range",
        "ent_coef", "log_std_init", "normalize_reward", "gru_hidden", "critic_gru", "net_arch", "cnn",
        "scene_groups", "promote_at", "window", "level_budget", "depth_noise_std", "start_mode", "start_spread",
    )  # fmt: skip
    names |= {f"vision-ppo.{key}" for key in ppo}
    names |= {
        "ENV_VERSION", "MAX_EPISODE_STEPS", "START_POINT_DISTANCE", "START_POINT_TRIES", "CORRIDOR_MARGIN",
        "CONTACT_TOLERANCE", "TOLERANCE", "MATCHED_RADII", "DENSITIES", "GATE_SHIFTS", "HIGH_SPEED", "STATE_DIM",
        "POSITION_SCALE", "VELOCITY_SCALE", "STATE_LIMIT", "airframe.thrust_to_weight", "RaceEnv.start_mode",
        "RaceFeatures.state_dim", "RaceFeatures.depth_dim", "ENV_KWARGS[RaceObs-S-v0]", "S.gate_size",
        "S.start.spread", "campaign-2.steps", "campaign-2-long.steps", "vision-distill.gate_shift",
        "vision-distill.gate_shift_z",
    }  # fmt: skip
    return names


def ppo_configs() -> dict[str, TrainConfig]:
    """Every PPO config shipped in ``baselines/`` (DAgger configs have their own class), by name."""
    configs = {path.stem: load_config(path) for path in sorted((ROOT / "baselines").glob("*.yaml"))}
    return {name: config for name, config in configs.items() if isinstance(config, TrainConfig)}


# ----------------------------------------------------------------------------------------------- tests
def test_claims_parse_from_first_principles() -> None:
    found = CLAIM.findall("x `QuadrotorParams.mass = 0.58` kg, `vision-ppo.levels[1] = {density: 0}`, `a=b`, `c`")
    assert found == [("QuadrotorParams.mass", "0.58"), ("vision-ppo.levels[1]", "{density: 0}")]
    assert same({0.5: 0.25, "k": [1, 2.0]}, {0.5: 0.25, "k": plain((1.0, 2))})
    assert not same(True, 1) and not same(0.3, None) and not same([1, 2], [1, 2, 3]) and not same("0.3", 0.3)
    assert resolve("vision-ppo.levels[3].reward_weights.speed") == 0.0
    assert resolve("S.obstacle_band") == plain(load_track("S").obstacle_band)


def test_every_claim_on_the_page_is_the_codes() -> None:
    problems = []
    for name, text in claims():
        page = yaml.safe_load(text)
        try:
            code = resolve(name)
        except (KeyError, AttributeError, IndexError, TypeError) as exc:
            problems.append(f"`{name} = {text}`: the code has no {name!r} ({type(exc).__name__}: {exc})")
            continue
        if not same(page, code):
            problems.append(f"`{name} = {text}`: the code says {code!r}")
    assert not problems, "docs/fidelity.md disagrees with the code:\n" + "\n".join(problems)


def test_the_page_states_every_checked_number() -> None:
    stated = {name for name, _ in claims()}
    missing = sorted(required_claims() - stated)
    assert not missing, f"docs/fidelity.md no longer states: {missing}"


def test_the_config_table_is_every_ppo_configs() -> None:
    columns, rows = config_table()
    assert columns[0] == "config"
    configs = ppo_configs()
    assert sorted(row[0] for row in rows) == sorted(configs), "one row per PPO config in baselines/"
    problems = []
    for row in rows:
        config = configs[row[0]]
        for column, cell in zip(columns[1:], row[1:], strict=True):
            code = plain(getattr(config, column))
            if not same(yaml.safe_load(cell), code):
                problems.append(f"{row[0]}.{column}: page {cell!r}, code {code!r}")
    assert not problems, "docs/fidelity.md's config table disagrees with baselines/:\n" + "\n".join(problems)


def test_what_the_page_states_once_holds_everywhere() -> None:
    """The page states these for S and says "the same on J and Circle" ..."""
    for track in TRACKS:
        facts = _track(track)
        assert facts["gate_size"] == _track("S")["gate_size"], track
        assert np.allclose(facts["start"]["spread"], _track("S")["start"]["spread"]), track
        main = registration.ENV_KWARGS[f"RaceObs-{track}-v0"]
        assert main == {**registration.ENV_KWARGS["RaceObs-S-v0"], "track": track}
    # ... and states vision-ppo's levels as "the same in state-ppo, vision-no-*, vision-ppo-fast"
    configs = ppo_configs()
    for name in ("state-ppo", "vision-no-gru", "vision-no-avoid", "vision-ppo-fast"):
        assert configs[name].levels == configs["vision-ppo"].levels, name


@pytest.mark.parametrize("name", ["vision-ppo.n_envs", "QuadrotorParams.mass", "measured.S"])
def test_a_changed_number_fails(name: str) -> None:
    """The check has teeth: a claim off by a little does not pass."""
    code = resolve(name)
    changed = {k: v + 0.01 for k, v in code.items()} if isinstance(code, dict) else code + 1
    assert not same(changed, code)
