"""Every registered id: Gymnasium and SB3 env checkers, determinism, spec round-trip, rendering."""

from __future__ import annotations

import pickle

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env as gym_check_env
from stable_baselines3.common.env_checker import check_env as sb3_check_env

import racebench
from racebench.envs.registration import ENV_KWARGS

ALL_IDS = racebench.ENV_IDS


def test_id_list() -> None:
    assert len(ALL_IDS) == 68 and len(set(ALL_IDS)) == 68
    assert {"RaceObs-Random-v0", "RaceObs-Unseen-v0"} <= set(ALL_IDS)  # a generated track per episode
    for track in ("S", "J", "Circle"):
        assert f"RaceObs-{track}-v0" in ALL_IDS
        assert f"RaceObs-{track}-Density5-v0" in ALL_IDS
        assert f"RaceObs-{track}-GateShift0.7-v0" in ALL_IDS
        assert f"RaceObs-{track}-Level3-v0" in ALL_IDS
    assert all(env_id in gym.registry for env_id in ALL_IDS)
    assert ENV_KWARGS["RaceObs-J-GateShift0.7-v0"]["gate_shift"] == 0.7
    assert ENV_KWARGS["RaceObs-S-Level1-v0"]["density"] == 0
    assert ENV_KWARGS["RaceObs-S-Level3-v0"]["reward_weights"] == {"speed": 0.0}


@pytest.mark.parametrize("env_id", ALL_IDS)
def test_gymnasium_check_env(env_id: str) -> None:
    env = gym.make(env_id, render_mode="rgb_array")
    gym_check_env(env.unwrapped, skip_render_check=False)
    env.close()


@pytest.mark.parametrize("env_id", ALL_IDS)
def test_sb3_check_env(env_id: str) -> None:
    env = gym.make(env_id)
    with pytest.warns(UserWarning):  # SB3 notes the float depth image is not a uint8 "image"
        sb3_check_env(env.unwrapped, warn=True)
    env.close()


@pytest.mark.parametrize("env_id", [f"RaceObs-{t}-v0" for t in ("S", "J", "Circle")])
def test_state_mode_passes_checkers(env_id: str) -> None:
    env = gym.make(env_id, obs_mode="state")
    gym_check_env(env.unwrapped)
    sb3_check_env(env.unwrapped)
    env.close()


def rollout(env: gym.Env, seed: int, steps: int = 60) -> list:
    obs, info = env.reset(seed=seed)
    rng = np.random.default_rng(123)
    trace = [(obs, info)]
    for _ in range(steps):
        action = rng.uniform(-0.3, 0.3, size=4).astype(np.float32)
        action[0] += env.unwrapped.params.hover_action
        out = env.step(action)
        trace.append(out)
        if out[2] or out[3]:
            obs, info = env.reset()
            trace.append((obs, info))
    return trace


def assert_same(a, b) -> None:
    if isinstance(a, dict):
        assert a.keys() == b.keys()
        for k in a:
            assert_same(a[k], b[k])
    elif isinstance(a, (tuple, list)):
        assert len(a) == len(b)
        for x, y in zip(a, b, strict=True):
            assert_same(x, y)
    elif isinstance(a, np.ndarray):
        assert a.dtype == b.dtype and np.array_equal(a, b)
    else:
        assert a == b


@pytest.mark.parametrize("env_id", ALL_IDS)
def test_same_seed_same_episode_bit_for_bit(env_id: str) -> None:
    a, b = gym.make(env_id), gym.make(env_id)
    assert_same(rollout(a, seed=7), rollout(b, seed=7))
    # The same env reset with the same seed again replays it too, whatever it did in between.
    assert_same(rollout(a, seed=7), rollout(b, seed=7))
    a.close()
    b.close()


@pytest.mark.parametrize("env_id", ["RaceObs-S-v0", "RaceObs-Circle-GateShift1.0-v0"])
def test_different_seeds_differ(env_id: str) -> None:
    env = gym.make(env_id)
    env.reset(seed=1)
    first = env.unwrapped.scene.to_dict()
    env.reset(seed=2)
    assert env.unwrapped.scene.to_dict() != first
    env.close()


@pytest.mark.parametrize("env_id", ["RaceObs-S-v0", "RaceObs-J-GateShift0.5-v0", "RaceObs-Circle-Level2-v0"])
def test_spec_pickle_round_trip(env_id: str) -> None:
    env = gym.make(env_id, obs_mode="state")
    spec = pickle.loads(pickle.dumps(env.spec))
    again = gym.make(spec)
    assert again.spec.id == env_id and again.spec.kwargs == env.spec.kwargs
    assert_same(rollout(env, seed=3, steps=10), rollout(again, seed=3, steps=10))
    env.close()
    again.close()


def test_render_rgb_array() -> None:
    env = gym.make("RaceObs-S-v0", render_mode="rgb_array")
    env.reset(seed=0)
    frame = env.render()
    assert frame.shape == (240, 320, 3) and frame.dtype == np.uint8
    assert frame.std() > 5  # not a blank image
    env.close()
    plain = gym.make("RaceObs-S-v0")
    plain.reset(seed=0)
    assert plain.render() is None
    plain.close()


def test_observation_layout_at_reset() -> None:
    env = gym.make("RaceObs-S-v0", start_spread=(0.0, 0.0, 0.0), depth_noise_std=0.0)
    obs, info = env.reset(seed=0)
    state = obs["state"]
    np.testing.assert_allclose(state[0:3], [0.2, 0.0, 0.0], atol=1e-6)  # gate 1 is 2 m ahead
    np.testing.assert_allclose(state[3:6], [0.6, -0.1, 0.0], atol=1e-6)  # gate 2 at (7, -1, 1): to the right
    np.testing.assert_allclose(state[6:9], 0.0, atol=1e-9)
    assert state[9] == pytest.approx(0.8)
    np.testing.assert_allclose(state[10:14], [0, 0, 0, 1], atol=1e-9)
    assert obs["depth"].shape == (1, 64, 64) and obs["depth"].dtype == np.float32
    assert info == {
        "is_success": False,
        "gates_passed": 0,
        "crashed": False,
        "crash_reason": None,
        "reward_terms": dict.fromkeys(("prog", "theta", "cmd", "vd", "avoid", "pass", "crash"), 0.0),
        "time": 0.0,
        "start_gate": 0,
    }
    env.close()


def test_vector_envs() -> None:
    from stable_baselines3.common.env_util import make_vec_env

    vec = gym.make_vec("RaceObs-S-v0", num_envs=2, vectorization_mode="sync")
    obs, _ = vec.reset(seed=0)
    assert obs["depth"].shape == (2, 1, 64, 64)
    vec.step(np.zeros((2, 4), dtype=np.float32))
    vec.close()
    sb3 = make_vec_env("RaceObs-J-v0", n_envs=2, seed=0)
    assert sb3.reset()["state"].shape == (2, 17)
    sb3.close()


def test_bad_kwargs_and_values_are_named() -> None:
    with pytest.raises(TypeError, match="colour"):
        gym.make("RaceObs-S-v0", colour="red")
    with pytest.raises(ValueError, match="obs_mode"):
        gym.make("RaceObs-S-v0", obs_mode="lidar")
    with pytest.raises(ValueError, match="density"):
        gym.make("RaceObs-S-v0", density=-1)
    with pytest.raises(ValueError, match="unknown weight 'lambda9'"):
        gym.make("RaceObs-S-v0", reward_weights={"lambda9": 1.0})
    with pytest.raises(ValueError, match="unknown parameter 'mas'"):
        gym.make("RaceObs-S-v0", quadrotor={"mas": 1.0})
    with pytest.raises(gym.error.NameNotFound):
        gym.make("RaceObs-Q-v0")


def test_bad_actions_are_named() -> None:
    env = gym.make("RaceObs-S-v0", obs_mode="state")
    env.reset(seed=0)
    with pytest.raises(ValueError, match="shape"):
        env.step(np.zeros(3, dtype=np.float32))
    with pytest.raises(ValueError, match="finite"):
        env.step(np.array([0, np.nan, 0, 0], dtype=np.float32))
    env.close()


def test_user_track_file(tmp_path) -> None:
    from pathlib import Path

    text = (Path(__file__).parents[1] / "tracks" / "S.yaml").read_text().replace("name: S", "name: mine")
    path = tmp_path / "mine.yaml"
    path.write_text(text)
    env = gym.make("RaceObs-S-v0", track=str(path), obs_mode="state")
    env.reset(seed=0)
    assert env.unwrapped.track.name == "mine"
    env.close()


# ------------------------------------------------------- copies and bad values


def test_copies_and_pickles_are_refused_with_a_way_out() -> None:
    import copy

    env = gym.make("RaceObs-S-v0")
    env.reset(seed=0)
    for attempt in (copy.deepcopy, pickle.dumps):
        with pytest.raises(TypeError, match="cannot be copied or pickled"):
            attempt(env)
    import cloudpickle

    with pytest.raises(TypeError, match="cannot be copied or pickled"):
        cloudpickle.dumps(env)
    env.step(env.action_space.sample())  # the original is untouched by the attempts
    env.close()
    with pytest.raises(RuntimeError, match=r"step\(\) after close\(\)"):
        env.unwrapped.step(env.action_space.sample())
    with pytest.raises(RuntimeError, match=r"reset\(\) after close\(\)"):
        env.unwrapped.reset(seed=0)


def test_the_simulator_and_its_pybullet_client_refuse_copies_and_pickles() -> None:
    """A copy of the inner simulator would share its PyBullet connection and disconnect it when collected."""
    import copy
    import gc

    env = gym.make("RaceObs-S-v0", obs_mode="state")
    env.reset(seed=0)
    sim = env.unwrapped.sim
    for inner in (sim, sim.client):
        for attempt in (copy.copy, copy.deepcopy, pickle.dumps):
            with pytest.raises(TypeError, match=f"{type(inner).__name__} cannot be copied or pickled"):
                attempt(inner)
    gc.collect()  # no half-made copy is left whose clean-up would disconnect the original
    for _ in range(5):
        env.step(env.action_space.sample())  # the original still reaches its physics server
    assert sim.client.getNumBodies() > 0
    env.close()


@pytest.mark.parametrize(
    "kwargs, named",
    [
        ({"depth_noise_std": float("nan")}, "depth_noise_std"),
        ({"depth_noise_std": -0.1}, "depth_noise_std"),
        ({"max_episode_time": float("inf")}, "max_episode_time"),
        ({"max_episode_time": 0}, "max_episode_time"),
        ({"desired_speed": float("nan")}, "desired_speed"),
        ({"gate_shift": -0.5}, "gate_shift"),
        ({"gate_shift_z": float("inf")}, "gate_shift_z"),
        ({"track": 123}, "track"),
        ({"max_episode_time": True}, "max_episode_time"),
    ],
)
def test_bad_values_are_named(kwargs: dict, named: str) -> None:
    with pytest.raises(ValueError, match=f"^{named} must"):
        gym.make("RaceObs-S-v0", **kwargs)


# ------------------------------------------------------- uint8 depth (stock SB3)


@pytest.mark.parametrize("env_id", ["RaceObs-S-v0", "RaceObs-J-Level1-v0"])
def test_uint8_depth_passes_both_checkers_without_a_warning(env_id: str) -> None:
    import warnings

    env = gym.make(env_id, depth_format="uint8")
    assert env.observation_space["depth"] == gym.spaces.Box(0, 255, (64, 64, 1), np.uint8)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the float format's "not an image" warning must be gone
        sb3_check_env(env.unwrapped, warn=True)
    gym_check_env(env.unwrapped)
    env.close()


def test_uint8_depth_is_the_float_image_rounded_and_deterministic() -> None:
    from racebench.envs.env import depth_to_uint8

    small, plain = gym.make("RaceObs-S-v0", depth_format="uint8"), gym.make("RaceObs-S-v0")
    a, b = rollout(small, seed=5, steps=40), rollout(plain, seed=5, steps=40)
    assert len(a) == len(b)
    for got, float_step in zip(a, b, strict=True):
        obs, float_obs = got[0], float_step[0]
        assert obs["depth"].dtype == np.uint8 and obs["depth"].shape == (64, 64, 1)
        np.testing.assert_array_equal(obs["depth"], depth_to_uint8(float_obs["depth"]))
        np.testing.assert_array_equal(obs["state"], float_obs["state"])
        assert_same(got[1:], float_step[1:])  # rewards, flags and infos do not depend on the format
    first = b[0][0]["depth"]  # rounded to the nearest of 256 levels
    assert np.abs(depth_to_uint8(first) / 255.0 - first[0, :, :, None]).max() <= 0.5 / 255 + 1e-6
    assert_same(rollout(small, seed=5, steps=40), rollout(gym.make("RaceObs-S-v0", depth_format="uint8"), 5, 40))
    small.close()
    plain.close()
    with pytest.raises(ValueError, match="^depth_format must"):
        gym.make("RaceObs-S-v0", depth_format="float16")


# ------------------------------------------------------- time limit in the spec


def test_the_spec_time_limit_is_the_envs_own() -> None:
    from racebench.envs.registration import MAX_EPISODE_STEPS

    for env_id in ALL_IDS:
        env = gym.make(env_id, obs_mode="state")
        assert gym.spec(env_id).max_episode_steps == env.unwrapped.max_steps  # 15 s at the id's control rate
        assert env.unwrapped.max_steps == (450 if "Control30Hz" in env_id else MAX_EPISODE_STEPS)
        env.close()
    env = gym.make("RaceObs-Circle-GateShift0.5-v0", obs_mode="state")
    assert env.spec.max_episode_steps == env.unwrapped.max_steps == MAX_EPISODE_STEPS
    env.close()


def test_time_limit_truncates_once_on_the_envs_own_step() -> None:
    """gym.make's TimeLimit and the env's own limit end the same episode on the same step, with the same flags."""
    from racebench.envs.env import RaceEnv

    wrapped = gym.make("RaceObs-S-Level1-v0", obs_mode="state")
    bare = RaceEnv(**{**ENV_KWARGS["RaceObs-S-Level1-v0"], "obs_mode": "state"})
    hover = np.array([bare.params.hover_action, 0, 0, 0], dtype=np.float32)
    flags = []
    for env in (wrapped, bare):
        env.reset(seed=1)
        trace = []
        while not (trace and (trace[-1][0] or trace[-1][1])):
            trace.append(env.step(hover)[2:4])
        flags.append(trace)
        env.close()
    assert flags[0] == flags[1]
    assert len(flags[0]) == wrapped.spec.max_episode_steps and flags[0][-1] == (False, True)


@pytest.mark.parametrize("track", ["S", "J", "Circle"])
def test_density3_is_an_alias_of_the_main_id(track: str) -> None:
    alias, main = f"RaceObs-{track}-Density3-v0", f"RaceObs-{track}-v0"
    assert ENV_KWARGS[alias] == ENV_KWARGS[main]  # docs/environment.md says so
    a, b = gym.make(alias, obs_mode="state"), gym.make(main, obs_mode="state")
    a.reset(seed=9)
    b.reset(seed=9)
    assert a.unwrapped.scene.to_dict() == b.unwrapped.scene.to_dict()
    assert_same(rollout(a, seed=9, steps=30), rollout(b, seed=9, steps=30))
    a.close()
    b.close()
