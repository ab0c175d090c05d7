"""Vector envs: the Gymnasium and SB3 front ends against Gymnasium's SyncVectorEnv / SB3's DummyVecEnv over
single envs (bit-identical episodes, autoresets included), worker processes, make_vec and SB3 training."""

from __future__ import annotations

import os

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.vector import AutoresetMode, SyncVectorEnv
from stable_baselines3 import PPO
from stable_baselines3.common.vec_env import DummyVecEnv

import racebench  # noqa: F401  (registers the ids)
from racebench.envs.env import RaceEnv
from racebench.envs.vector import RaceVectorEnv, concat_infos, stack_infos
from racebench.training.sb3 import RaceSB3VecEnv, make_sb3_vec_env

KWARGS = dict(track="S", density=3, renderer="raycast")


def random_actions(steps: int, n: int, seed: int = 0) -> np.ndarray:
    """Uniform actions with a climb bias: episodes end (crash or leaving the arena) after 50-90 steps."""
    rng = np.random.default_rng(seed)
    actions = rng.uniform(-1.0, 1.0, size=(steps, n, 4)).astype(np.float32)
    actions[..., 0] = np.minimum(actions[..., 0] + 0.3, 1.0)
    return actions


def assert_same(a, b, path: str = "") -> None:
    if isinstance(a, dict):
        assert set(a) == set(b), (path, set(a) ^ set(b))
        for key in a:
            assert_same(a[key], b[key], f"{path}.{key}")
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            assert_same(x, y, f"{path}[{i}]")
    elif isinstance(a, np.ndarray) and a.dtype == object:
        assert b.dtype == object and a.shape == b.shape, path
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            assert_same(x, y, f"{path}[{i}]")
    elif isinstance(a, np.ndarray):
        assert isinstance(b, np.ndarray) and a.dtype == b.dtype and a.shape == b.shape, (path, a.dtype, b.dtype)
        assert np.array_equal(a, b), path
    else:
        assert a == b, (path, a, b)


def run_gym(venv, actions: np.ndarray, seed: int) -> list:
    trace = [venv.reset(seed=seed)]
    for a in actions:
        trace.append(venv.step(a))
    return trace


@pytest.mark.parametrize(
    ("obs_mode", "mode", "processes"),
    [
        ("vision", AutoresetMode.NEXT_STEP, 1),
        ("vision", AutoresetMode.SAME_STEP, 2),
        ("state", AutoresetMode.NEXT_STEP, 3),
        ("vision", AutoresetMode.DISABLED, 1),
    ],
)
def test_gymnasium_vector_env_equals_sync_vector_env(obs_mode: str, mode: AutoresetMode, processes: int) -> None:
    n, steps = 3, 100
    kwargs = {**KWARGS, "obs_mode": obs_mode}
    actions = random_actions(steps if mode != AutoresetMode.DISABLED else 8, n)
    reference = SyncVectorEnv([lambda: RaceEnv(**kwargs) for _ in range(n)], autoreset_mode=mode)
    venv = RaceVectorEnv(n, num_processes=processes, autoreset_mode=mode, **kwargs)
    try:
        assert venv.single_observation_space == reference.single_observation_space
        assert venv.observation_space == reference.observation_space
        assert venv.action_space == reference.action_space
        assert venv.metadata["autoreset_mode"] == mode
        expected, got = run_gym(reference, actions, seed=11), run_gym(venv, actions, seed=11)
        dones = sum(int(np.sum(step[2] | step[3])) for step in got[1:])
        if mode != AutoresetMode.DISABLED:
            assert dones >= 2, "the rollout must cover autoresets"
        assert_same(expected, got)
        # A second reset with the same seed replays the same episodes.
        assert_same(run_gym(reference, actions[:5], seed=11), run_gym(venv, actions[:5], seed=11))
    finally:
        venv.close()
        reference.close()


def test_worker_processes_and_attributes() -> None:
    venv = RaceVectorEnv(4, num_processes=2, **KWARGS)
    try:
        pids = venv.process_ids
        assert len(set(pids)) == 2 and pids[0] == os.getpid()  # this process steps envs 0-1, a worker 2-3
        venv.reset(seed=0)
        assert venv.get_attr("renderer") == ("raycast",) * 4
        venv.set_attr("desired_speed", [1.0, 2.0, 3.0, 4.0])
        assert venv.get_attr("desired_speed") == (1.0, 2.0, 3.0, 4.0)
        images = venv.call("depth_image")
        assert len(images) == 4 and all(image.shape == (64, 64) for image in images)
        # A partial reset (reset_mask) touches only the masked envs.
        obs, _ = venv.step(np.zeros((4, 4), dtype=np.float32))[:2]
        mask = np.array([True, False, False, True])
        again, info = venv.reset(seed=[5, None, None, 6], options={"reset_mask": mask})
        np.testing.assert_array_equal(again["state"][~mask], obs["state"][~mask])
        assert list(info["_gates_passed"]) == mask.tolist()
    finally:
        venv.close()


def test_make_vec_uses_the_vector_entry_point() -> None:
    venv = gym.make_vec("RaceObs-J-v0", num_envs=2, renderer="raycast", num_processes=2)
    reference = gym.make_vec("RaceObs-J-v0", num_envs=2, vectorization_mode="sync", renderer="raycast")
    try:
        assert isinstance(venv.unwrapped, RaceVectorEnv)
        assert venv.spec.id == "RaceObs-J-v0" and venv.unwrapped.get_attr("track")[0].name == "J"
        actions = random_actions(70, 2, seed=3)
        assert_same(run_gym(reference, actions, seed=4), run_gym(venv, actions, seed=4))
    finally:
        venv.close()
        reference.close()
    with pytest.raises(ValueError, match="num_processes"):
        gym.make_vec("RaceObs-J-v0", num_envs=2, num_processes=3)
    with pytest.raises(ValueError, match="renderer"):
        gym.make_vec("RaceObs-J-v0", num_envs=2, renderer="opengl")


def run_sb3(venv, actions: np.ndarray, seed: int) -> list:
    venv.seed(seed)
    trace = [(venv.reset(), [dict(i) for i in venv.reset_infos])]
    for a in actions:
        venv.step_async(a)
        obs, rewards, dones, infos = venv.step_wait()
        trace.append((obs, rewards, dones, infos, [dict(i) for i in venv.reset_infos]))
    return trace


@pytest.mark.parametrize("processes", [1, 2])
def test_sb3_vec_env_equals_dummy_vec_env(processes: int) -> None:
    n = 3
    reference = DummyVecEnv([lambda: RaceEnv(**KWARGS) for _ in range(n)])
    venv = RaceSB3VecEnv(n, num_processes=processes, **KWARGS)
    try:
        assert venv.observation_space == reference.observation_space and venv.num_envs == n
        actions = random_actions(100, n, seed=1)
        expected, got = run_sb3(reference, actions, seed=21), run_sb3(venv, actions, seed=21)
        assert sum(int(step[2].sum()) for step in got[1:]) >= 2, "the rollout must cover autoresets"
        assert_same(expected, got)
        assert venv.get_attr("renderer", indices=[1]) == ["raycast"]
        venv.set_attr("desired_speed", 2.5, indices=[0, 2])
        assert venv.get_attr("desired_speed") == [2.5, 8.0, 2.5]
        assert venv.env_method("depth_image", indices=0)[0].shape == (64, 64)
        assert venv.env_is_wrapped(gym.Wrapper) == [False] * n
    finally:
        venv.close()
        reference.close()


def test_sb3_ppo_trains_on_it() -> None:
    venv = make_sb3_vec_env("RaceObs-S-v0", n_envs=2, seed=0, num_processes=2, renderer="raycast")
    try:
        model = PPO("MultiInputPolicy", venv, n_steps=32, batch_size=32, n_epochs=1, seed=0, device="cpu")
        model.learn(total_timesteps=64)
        assert model.num_timesteps == 64
    finally:
        venv.close()


def test_stack_and_concat_infos_follow_gymnasium() -> None:
    infos = [
        {"a": 1, "b": {"c": 0.5}, "lap_time": None},
        {"a": 2, "lap_time": 3.25, "name": "x"},
        None,
        {"a": 3, "b": {"c": 1.5}, "lap_time": None, "final_obs": np.zeros(2)},
    ]
    stacked = stack_infos(infos, 4)
    assert stacked["a"].dtype == np.int64 and stacked["a"].tolist() == [1, 2, 0, 3]
    assert stacked["_a"].tolist() == [True, True, False, True]
    assert stacked["b"]["c"].tolist() == [0.5, 0.0, 0.0, 1.5] and stacked["_b"].tolist() == [True, False, False, True]
    assert stacked["lap_time"].dtype == object and stacked["lap_time"].tolist() == [None, 3.25, None, None]
    assert stacked["final_obs"].dtype == object and stacked["final_obs"][0] is None
    # Where Gymnasium's own _add_info applies (no None/number mix), it agrees.
    reference = SyncVectorEnv([lambda: RaceEnv(obs_mode="state") for _ in range(4)])
    plain = [{k: v for k, v in (i or {}).items() if k not in ("lap_time", "name", "final_obs")} for i in infos]
    expected: dict = {}
    for i, info in enumerate(plain):
        expected = reference._add_info(expected, info, i)
    assert_same(expected, stack_infos(plain, 4))
    reference.close()
    # Joining slices equals stacking all at once.
    assert_same(stack_infos(infos, 4), concat_infos([stack_infos(infos[:1], 1), stack_infos(infos[1:], 3)], [1, 3]))


def test_uint8_depth_vector_env_equals_sync_vector_env() -> None:
    n, kwargs = 3, {**KWARGS, "depth_format": "uint8"}
    actions = random_actions(60, n, seed=2)
    reference = SyncVectorEnv([lambda: RaceEnv(**kwargs) for _ in range(n)])
    venv = RaceVectorEnv(n, num_processes=2, **kwargs)  # uint8 shared memory from the worker
    try:
        assert venv.single_observation_space == reference.single_observation_space
        got = run_gym(venv, actions, seed=13)
        assert got[0][0]["depth"].dtype == np.uint8 and got[0][0]["depth"].shape == (n, 64, 64, 1)
        assert_same(run_gym(reference, actions, seed=13), got)
    finally:
        venv.close()
        reference.close()


def test_lap_time_has_one_dtype_in_every_vectorization_mode() -> None:
    """Env 0 finishes a lap while env 1 hovers: Gymnasium's SyncVectorEnv and racebench's give float64 both."""
    from racebench.agents.control import GateFollower

    kwargs = dict(track="S", density=0, obs_mode="state", desired_speed=3.0)
    reference = SyncVectorEnv([lambda: RaceEnv(**kwargs) for _ in range(2)])
    venv = RaceVectorEnv(2, **kwargs)
    pilots = [(GateFollower(), reference.envs[0]), (GateFollower(), venv._backend.local.envs[0])]
    try:
        assert_same(reference.reset(seed=0), venv.reset(seed=0))
        hover = np.array([reference.envs[1].params.hover_action, 0, 0, 0])
        lap = False
        for _ in range(700):
            actions = [np.stack([pilot.act_privileged(env), hover]).astype(np.float32) for pilot, env in pilots]
            expected, got = reference.step(actions[0]), venv.step(actions[1])
            if "lap_time" in expected[4] or "lap_time" in got[4]:  # only on a step that finishes a lap
                assert expected[4]["lap_time"].dtype == got[4]["lap_time"].dtype == np.float64
            assert_same(expected, got)
            if got[4]["is_success"][0]:
                lap = True
                assert got[4]["lap_time"][0] > 0 and got[4]["_lap_time"].tolist() == [True, False]
                break
        assert lap, "env 0 must finish its lap for the test to bite"
    finally:
        venv.close()
        reference.close()


def test_make_vec_applies_the_spec_time_limit_as_sync_mode_does() -> None:
    venv = gym.make_vec("RaceObs-S-Level1-v0", num_envs=1, obs_mode="state", max_episode_time=20.0)
    reference = gym.make_vec("RaceObs-S-Level1-v0", num_envs=1, vectorization_mode="sync", obs_mode="state",
                             max_episode_time=20.0)  # fmt: skip
    try:
        assert venv.unwrapped._backend.local.max_episode_steps == venv.spec.max_episode_steps == 750
        hover = np.array([[reference.envs[0].unwrapped.params.hover_action, 0, 0, 0]], dtype=np.float32)
        venv.reset(seed=2)
        reference.reset(seed=2)
        for _ in range(750):  # the env's own limit is 1,000 steps; both cut at the spec's 750, as gym.make does
            expected, got = reference.step(hover), venv.step(hover)
            assert_same(expected, got)
        assert got[3][0] and not got[2][0]
    finally:
        venv.close()
        reference.close()
