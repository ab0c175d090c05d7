"""Training pipeline: configs, curriculum, multi-scene groups, the GRU policy, checkpoints, smoke runs."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
from payloads import evil_pickle, evil_sb3_zip
from sb3_contrib.common.recurrent.policies import RecurrentMultiInputActorCriticPolicy
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

from racebench import cli
from racebench.agents import WRITTEN_FILE, AgentLoadError, SB3Agent, UntrustedCodeError, record_written, written_sha256
from racebench.agents.recurrent import CNN_KINDS, LSTMShapedGRU, RecurrentGRUPolicy, depth_cnn
from racebench.envs.registration import CURRICULUM
from racebench.evaluation import EVAL_SEED_BASE
from racebench.training.callbacks import _save_atomically
from racebench.training.ppo import _load_model, _restore_reward_stats, _trusted_reward_stats
from racebench.training.sb3 import RaceSB3VecEnv
from racebench.training.train import BASELINES as BASELINE_NAMES
from racebench.training.train import (
    CurriculumCallback,
    MultiSceneCallback,
    ThreadsCallback,
    TrainConfig,
    archive_finished_part,
    load_config,
    make_envs,
    make_model,
    own_policy_trust,
    restore_schedules,
    resume_curriculum,
    resume_seed,
    train,
)

BASELINES = sorted((Path(__file__).parents[1] / "baselines").glob("*.yaml"))
PPO_BASELINES = [p for p in BASELINES if "method: dagger" not in p.read_text()]  # DAgger: its own tests


def small(config: TrainConfig, **changes) -> TrainConfig:
    defaults = dict(n_envs=2, n_steps=32, batch_size=32, n_epochs=1, vec_env="dummy", window=4)
    return dataclasses.replace(config, **{**defaults, **changes})


def test_every_baseline_config_loads() -> None:
    names = {load_config(p).name for p in BASELINES}
    assert names == {
        "vision-ppo", "state-ppo", "vision-no-gru", "vision-no-avoid", "vision-one-step", "vision-com",
        "vision-ppo-fast", "vision-distill", "vision-distill-ppo", "vision-one-step-flying", "vision-ppo-random",
        "vision-distill-random",
    }  # fmt: skip
    assert TrainConfig.from_yaml(BASELINES[0].parent / "vision-no-avoid.yaml").level_kwargs(3)["reward_weights"] == {
        "speed": 0.0,
        "avoid": 0.0,
    }
    one_step = TrainConfig.from_yaml(BASELINES[0].parent / "vision-one-step.yaml")
    assert one_step.start_level == 3 and not one_step.curriculum


def test_bad_configs_are_named(tmp_path: Path) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text("name: x\nlearning_rat: 0.1\n")
    with pytest.raises(ValueError, match="unknown key 'learning_rat'"):
        TrainConfig.from_yaml(path)
    path.write_text("name: x\nobs_mode: lidar\n")
    with pytest.raises(ValueError, match="obs_mode"):
        TrainConfig.from_yaml(path)
    path.write_text("name: x\nn_envs: 3\nn_steps: 10\nbatch_size: 8\n")
    with pytest.raises(ValueError, match="multiple of batch_size"):
        TrainConfig.from_yaml(path)


class FakeVecEnv:
    """Records env_method calls, enough for the curriculum callback."""

    num_envs = 4

    def __init__(self) -> None:
        self.calls: list[tuple[str, dict]] = []

    def env_method(self, name: str, *args, indices=None, **kwargs):
        self.calls.append((name, kwargs))
        return [None]


class FakeModel:
    """What SB3 callbacks read from their model: the env, the step count and a logger."""

    num_timesteps = 0

    def __init__(self, env) -> None:
        self.env = env
        self.logger = type("Logger", (), {"record": lambda *args, **kwargs: None})()

    def get_env(self):
        return self.env


def test_curriculum_promotes_on_a_scripted_success_signal() -> None:
    config = TrainConfig(name="t", window=10, promote_at=0.8)
    callback = CurriculumCallback(config)
    fake = FakeVecEnv()
    callback.init_callback(FakeModel(fake))
    for success in [True] * 7 + [False] * 3:  # 70 % < 80 %: stays
        callback.record(success)
    assert callback.level == 1 and not fake.calls
    for _ in range(7):  # older successes leave the window as new ones come: still 7/10
        callback.record(True)
    assert callback.level == 1
    callback.record(True)  # the first failure leaves: 8/10
    assert callback.level == 2
    assert fake.calls == [("set_task", config.level_kwargs(2)), ("set_layout", {})]
    assert fake.calls[0][1]["density"] == CURRICULUM[2]["density"]
    for _ in range(9):  # a fresh window is needed after a promotion
        callback.record(True)
    assert callback.level == 2
    callback.record(True)
    assert callback.level == 3 and fake.calls[-2][1]["reward_weights"] == {"speed": 0.0}
    for _ in range(30):  # no level past the last
        callback.record(True)
    assert callback.level == 3 and [p["level"] for p in callback.promotions] == [2, 3]


def test_episodes_begun_before_a_promotion_do_not_count() -> None:
    """Episodes in flight at a promotion finish under the old level's task and must not promote the next."""
    callback = CurriculumCallback(TrainConfig(name="t", window=2, promote_at=1.0))
    callback.init_callback(FakeModel(FakeVecEnv()))
    callback.on_training_start({}, {})
    lap = {"is_success": True, "start_gate": 0}

    def step(*finished: int) -> None:
        callback.update_locals({"dones": [i in finished for i in range(4)], "infos": [lap] * 4})
        callback.on_step()

    step(0, 1)  # two laps at level 1: promoted while handling env 1
    assert callback.level == 2
    step(0, 2, 3)  # env 0 was reset before the promotion, envs 2 and 3 began at level 1: none count
    assert callback.level == 2 and len(callback.successes) == 0
    step(1)  # env 1 was reset in the promotion's step, before it: its episode began at level 1
    assert len(callback.successes) == 0
    step(0, 2)  # both began after the promotion
    assert callback.level == 3


def test_a_level_budget_promotes_a_policy_that_cannot_reach_the_bar() -> None:
    config = TrainConfig(name="t", window=2, promote_at=1.0, level_budget={1: 100, 2: 50})
    callback = CurriculumCallback(config)
    model = FakeModel(FakeVecEnv())
    callback.init_callback(model)
    callback.on_training_start({}, {})
    callback.clock = lambda: 12.5
    failed_lap = {"is_success": False, "start_gate": 0}

    def step_to(timestep: int) -> None:
        model.num_timesteps = timestep
        callback.update_locals({"dones": [True] * 4, "infos": [failed_lap] * 4})
        callback.on_step()

    step_to(99)
    assert callback.level == 1
    step_to(100)  # budget of level 1 spent, never a success
    assert callback.level == 2 and callback.promotions[-1] == {"level": 2, "timestep": 100, "wall_s": 12.5,
                                                               "by": "budget"}  # fmt: skip
    step_to(149)
    assert callback.level == 2
    step_to(150)
    assert callback.level == 3 and callback.promotions[-1]["by"] == "budget"
    step_to(10_000)  # no budget past the last level
    assert callback.level == 3 and callback.solved is None


def test_the_bar_still_promotes_first_and_solving_the_last_level_is_recorded(tmp_path: Path) -> None:
    config = TrainConfig(name="t", window=2, promote_at=1.0, level_budget={1: 1000, 2: 1000})
    callback = CurriculumCallback(config, state_file=tmp_path / "curriculum.json")
    model = FakeModel(FakeVecEnv())
    callback.init_callback(model)
    callback.on_training_start({}, {})
    lap = {"is_success": True, "start_gate": 0}
    for timestep in (10, 20, 30, 40, 50):  # a promotion's in-flight episodes do not count (one step each)
        model.num_timesteps = timestep
        callback.update_locals({"dones": [True, True, False, False], "infos": [lap] * 4})
        callback.on_step()
    assert [(p["level"], p["by"]) for p in callback.promotions] == [(2, "bar"), (3, "bar")]
    assert callback.solved == {"level": 3, "timestep": 50}
    saved = json.loads((tmp_path / "curriculum.json").read_text())
    assert saved["solved"] == callback.solved and len(saved["promotions"]) == 2


def test_bad_level_budgets_are_named(tmp_path: Path) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text("name: x\nlevel_budget: {3: 1000}\n")  # the last level has no promotion to make
    with pytest.raises(ValueError, match="level_budget"):
        TrainConfig.from_yaml(path)
    path.write_text("name: x\nlevel_budget: {1: -5}\n")
    with pytest.raises(ValueError, match="level_budget"):
        TrainConfig.from_yaml(path)


def test_device_selection() -> None:
    import torch

    from racebench.training.train import resolve_device

    assert resolve_device("cpu") == "cpu"
    assert resolve_device("auto") == ("cuda" if torch.cuda.is_available() else "cpu")
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="no CUDA device"):
            resolve_device("cuda")
    with pytest.raises(ValueError, match="device must be one of"):
        resolve_device("tpu")


def test_no_promotion_without_curriculum() -> None:
    config = TrainConfig(name="t", window=2, curriculum=False, start_level=3)
    callback = CurriculumCallback(config)
    callback.init_callback(FakeModel(FakeVecEnv()))
    for _ in range(10):
        callback.record(True)
    assert callback.level == 3 and not callback.promotions


def test_scene_groups_share_a_layout_and_change_every_rollout() -> None:
    config = TrainConfig(name="t", obs_mode="state", scene_groups={1: 2}, start_level=1)
    env = make_vec_env(
        "RaceObs-S-v0",
        n_envs=4,
        seed=0,
        vec_env_cls=DummyVecEnv,
        env_kwargs={"obs_mode": "state", "density": 3},
    )
    curriculum = CurriculumCallback(config)
    callback = MultiSceneCallback(config, curriculum)
    callback.init_callback(FakeModel(env))
    assert callback.groups(4) == [[0, 1], [2, 3]]
    callback._on_rollout_start()
    layouts = env.get_attr("layout")
    key = [json.dumps(layout.to_dict()["obstacles"]) for layout in layouts]
    assert key[0] == key[1] and key[2] == key[3] and key[0] != key[2]
    env.reset()
    scenes = env.get_attr("scene")
    assert json.dumps(scenes[0].to_dict()["obstacles"]) == key[0]
    assert not np.array_equal(scenes[0].start_position, scenes[1].start_position)  # start poses stay random
    callback._on_rollout_start()
    again = [json.dumps(layout.to_dict()["obstacles"]) for layout in env.get_attr("layout")]
    assert again[0] != key[0] and again[2] != key[2]
    env.close()


def test_gru_with_lstm_signature_resets_with_zero_state() -> None:
    torch.manual_seed(0)
    gru = LSTMShapedGRU(5, 7)
    x = torch.randn(3, 2, 5)
    zeros = (torch.zeros(1, 2, 7), torch.zeros(1, 2, 7))
    out, (h, c) = gru(x, zeros)
    reference, h_ref = torch.nn.GRU.forward(gru, x, zeros[0])
    assert torch.equal(out, reference) and torch.equal(h, h_ref) and torch.equal(c, zeros[1])


@pytest.mark.parametrize("starts_inside", [False, True], ids=["starts-first-only", "starts-inside"])
def test_fused_sequence_pass_equals_sb3_contribs_loop(starts_inside: bool) -> None:
    torch.manual_seed(0)
    gru = LSTMShapedGRU(5, 7)
    n_seq, length = 4, 6
    features = torch.randn(n_seq * length, 5)
    states = (torch.randn(1, n_seq, 7), torch.zeros(1, n_seq, 7))
    starts = torch.zeros(n_seq, length)
    starts[[0, 2], 0] = 1.0  # what sb3-contrib's buffer gives: episode starts begin sequences
    if starts_inside:
        starts[1, 3] = 1.0
    ours, (h, _) = RecurrentGRUPolicy._process_sequence(features, states, starts.flatten(), gru)
    # The parent's step-by-step loop (it always loops when any start is set).
    reference, (h_ref, _) = RecurrentMultiInputActorCriticPolicy._process_sequence(
        features, states, starts.flatten(), gru
    )
    torch.testing.assert_close(ours, reference, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(h, h_ref, rtol=1e-5, atol=1e-6)


def test_a_resumed_model_gets_its_schedules_from_its_config(tmp_path: Path) -> None:
    """A checkpoint written under another cloudpickle version loads without its pickled schedules (SB3 warns and
    keeps the class defaults): the resume rebuilds both from the config."""
    config = small(TrainConfig(name="t", obs_mode="state", learning_rate=(5e-4, 2e-5), clip_range=0.1))
    env = make_vec_env("RaceObs-S-Level1-v0", n_envs=1, env_kwargs={"obs_mode": "state"}, vec_env_cls=DummyVecEnv)
    model = make_model(config, env, seed=0, tensorboard=None)
    model.learning_rate, model.clip_range = 3e-4, 0.2  # what a failed deserialisation leaves (PPO's defaults)
    model._setup_lr_schedule()
    restore_schedules(model, config)
    assert model.lr_schedule(1.0) == pytest.approx(5e-4) and model.lr_schedule(0.0) == pytest.approx(2e-5)
    assert model.clip_range(0.5) == pytest.approx(0.1)
    env.close()


def test_gru_policy_state_is_carried_and_reset_at_episode_start() -> None:
    config = small(TrainConfig(name="t", obs_mode="state"))
    env = make_vec_env("RaceObs-S-Level1-v0", n_envs=1, env_kwargs={"obs_mode": "state"}, vec_env_cls=DummyVecEnv)
    model = make_model(config, env, seed=0, tensorboard=None)
    obs = np.random.default_rng(0).uniform(-1, 1, size=(6, 1, 17)).astype(np.float32)
    state, start, actions = None, np.ones(1, dtype=bool), []
    for o in obs:
        a, state = model.predict(o, state=state, episode_start=start, deterministic=True)
        start = np.zeros(1, dtype=bool)
        actions.append(a)
    # Memory matters: the same observation after a different history gives a different action...
    fresh, _ = model.predict(obs[-1], state=None, episode_start=np.ones(1, dtype=bool), deterministic=True)
    assert not np.allclose(fresh, actions[-1])
    # ...and an episode start clears it, whatever the carried state.
    reset, _ = model.predict(obs[-1], state=state, episode_start=np.ones(1, dtype=bool), deterministic=True)
    np.testing.assert_array_equal(reset, fresh)
    env.close()


@pytest.mark.parametrize("config_path", PPO_BASELINES, ids=[p.stem for p in PPO_BASELINES])
def test_training_smoke_run(tmp_path: Path, config_path: Path) -> None:
    # A fine-tuning config starts from its student (test_fine_tuning_starts_from_the_student): here from scratch.
    config = small(
        TrainConfig.from_yaml(config_path), n_envs=4, n_steps=64, batch_size=128, init_from=None, bc_coef=0.0
    )
    track = config.track or "S"  # vision-ppo-random: a generated track per episode
    result = train(config, track, steps=2048, seed=0, out=tmp_path, checkpoint_every=1024, eval_episodes=1)
    assert result["timesteps"] >= 2048 and Path(result["checkpoint"]).is_file()
    progress = pd.read_csv(tmp_path / "progress.csv")
    assert len(progress) >= 4 and progress["level"].iloc[0] == config.start_level
    assert list((tmp_path / "checkpoints").glob("*.zip"))
    assert (tmp_path / "eval" / "summary.csv").is_file()
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["config"] == config.name and summary["device"] == "cpu"
    assert summary["time_to_solve"] == {"promotions": summary["promotions"], "solved": None}


def test_training_on_the_batched_vec_env(tmp_path: Path) -> None:
    """The configs' default path: RaceSB3VecEnv over 2 processes under VecNormalize, scenes and curriculum
    driven through env_method, threads switched around the update."""
    config = dataclasses.replace(
        small(TrainConfig.from_yaml("state-ppo")), vec_env="race", num_processes=2, n_envs=4, scene_groups={1: 2}
    )
    env = make_envs(config, "S", seed=3)
    try:
        assert isinstance(env, VecNormalize) and isinstance(env.venv.venv, RaceSB3VecEnv)
        assert len(set(env.venv.venv.process_ids)) == 2
        assert env.get_attr("start_mode") == ["points"] * 4  # the paper's starts (issue 69)
        assert env.get_attr("weights")[0].heading == 0.0  # level 1 of the baselines: r_theta off
        # Scene groups through the batched env and the VecNormalize wrapper: {0, 1} and {2, 3} share a layout.
        callback = MultiSceneCallback(config, CurriculumCallback(config))  # gates shifted ±1 m: layouts differ
        callback.init_callback(FakeModel(env))
        callback._on_rollout_start()
        gates = [json.dumps(layout.to_dict()["gates"]) for layout in env.get_attr("layout")]
        assert gates[0] == gates[1] and gates[2] == gates[3] and gates[0] != gates[2]
    finally:
        env.close()
    result = train(config, "S", steps=256, seed=3, out=tmp_path, eval_episodes=0)
    assert result["timesteps"] == 256 and len(pd.read_csv(tmp_path / "progress.csv")) == 2  # 4 envs x 32 steps


def test_threads_callback_switches_around_the_update() -> None:
    callback = ThreadsCallback(collect=1, update=2)
    before = torch.get_num_threads()
    try:
        callback._on_rollout_end()
        assert torch.get_num_threads() == 2
        callback._on_rollout_start()
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(before)


def test_importing_racebench_makes_idle_openmp_threads_sleep_unless_the_user_chose() -> None:
    """OMP_WAIT_POLICY=PASSIVE is set by ``import racebench`` before torch loads OpenMP; a user's value is kept."""
    import os
    import subprocess
    import sys

    script = "import os, racebench, torch; print(os.environ['OMP_WAIT_POLICY'])"
    clean = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    seen = subprocess.run([sys.executable, "-c", script], env=clean, capture_output=True, text=True, check=True)
    assert seen.stdout.split()[-1] == "PASSIVE"
    chosen = subprocess.run(
        [sys.executable, "-c", script],
        env={**clean, "OMP_WAIT_POLICY": "ACTIVE"},
        capture_output=True,
        text=True,
        check=True,
    )
    assert chosen.stdout.split()[-1] == "ACTIVE"


def test_the_fast_variant_differs_from_the_paper_config_only_by_its_two_switches() -> None:
    """vision-ppo-fast: an MLP critic (no critic GRU) and 2 epochs; the actor and everything else as vision-ppo."""
    paper, fast = TrainConfig.from_yaml("vision-ppo"), TrainConfig.from_yaml("vision-ppo-fast")
    changed = {f.name for f in dataclasses.fields(TrainConfig) if getattr(paper, f.name) != getattr(fast, f.name)}
    assert changed == {"name", "critic_gru", "n_epochs"} and paper.critic_gru and paper.n_epochs == 4
    built = {}
    for config in (paper, fast):
        config = small(config, n_epochs=config.n_epochs)
        env = make_envs(config, "S", 0)
        built[config.name] = make_model(config, env, seed=0, tensorboard=None)
        env.close()
    gru, mlp = built["vision-ppo"].policy, built["vision-ppo-fast"].policy
    assert isinstance(gru.lstm_critic, LSTMShapedGRU) and mlp.lstm_critic is None
    assert isinstance(mlp.critic, torch.nn.Linear) and mlp.critic.in_features == gru.features_dim
    assert isinstance(mlp.lstm_actor, LSTMShapedGRU) and mlp.lstm_actor.hidden_size == gru.lstm_actor.hidden_size
    assert built["vision-ppo-fast"].n_epochs == 2 and built["vision-ppo"].n_epochs == 4
    n_params = {name: sum(p.numel() for p in m.policy.parameters()) for name, m in built.items()}
    critic_gru = sum(p.numel() for p in gru.lstm_critic.parameters()) - sum(p.numel() for p in mlp.critic.parameters())
    assert n_params["vision-ppo"] - n_params["vision-ppo-fast"] == critic_gru


def test_builtin_baseline_names_resolve_and_unknown_ones_are_named() -> None:
    assert {load_config(name).name for name in BASELINE_NAMES} == set(BASELINE_NAMES)
    with pytest.raises(ValueError, match="neither a built-in baseline"):
        TrainConfig.from_yaml("vision-ppo-typo")


def _grids_and_multiply_adds(net: torch.nn.Sequential, size: int) -> tuple[list[int], int]:
    """Each conv's output grid side and the multiply-adds of the convs and linear layers, by a forward pass."""
    x, grids, macs = torch.zeros(1, 1, size, size), [], 0
    for layer in net:
        y = layer(x)
        if isinstance(layer, torch.nn.Conv2d):
            grids.append(int(y.shape[-1]))
            macs += y.numel() * layer.in_channels * layer.kernel_size[0] * layer.kernel_size[1]
        elif isinstance(layer, torch.nn.Linear):
            macs += layer.in_features * layer.out_features
        x = y
    return grids, macs


@pytest.mark.parametrize(
    "kind, grids, macs_millions",
    [("paper", [64, 32, 16], 7.9), ("strided", [15, 6, 4], 0.74), ("fine", [30, 14, 6], 2.4)],
)
def test_depth_cnns_have_the_documented_grids_and_cost(kind: str, grids: list[int], macs_millions: float) -> None:
    """Each kind's conv grids on a 64x64 image and its multiply-adds per image, as depth_cnn's docstring states."""
    assert kind in CNN_KINDS
    net = depth_cnn(kind, 64, 128)
    found_grids, macs = _grids_and_multiply_adds(net, 64)
    assert found_grids == grids
    assert macs / 1e6 == pytest.approx(macs_millions, rel=0.05)
    assert net(torch.rand(3, 1, 64, 64)).shape == (3, 128)
    with pytest.raises(ValueError, match="cnn must be one of"):
        depth_cnn("coarse", 64, 128)


def test_a_fine_cnn_policy_trains_saves_and_reloads_for_evaluation(tmp_path: Path) -> None:
    """A student with the fine CNN (distill-fine-cnn's) goes through a checkpoint as the evaluator loads it."""
    config = small(TrainConfig.from_yaml(BASELINES[0].parent / "vision-ppo.yaml"), cnn="fine")
    result = train(config, "S", steps=64, seed=0, out=tmp_path, eval_episodes=0)
    agent = SB3Agent(result["checkpoint"], trust_code=True)
    assert agent.model.policy.features_extractor.depth_net[0].stride == (2, 2)
    agent.reset()
    obs = {"state": np.zeros(17, np.float32), "depth": np.full((1, 64, 64), 0.5, np.float32)}
    action = agent.act(obs)
    assert action.shape == (4,) and np.all(np.isfinite(action))


def test_checkpoint_save_load_same_actions(tmp_path: Path) -> None:
    config = small(TrainConfig.from_yaml(BASELINES[0].parent / "vision-ppo.yaml"))
    result = train(config, "S", steps=64, seed=0, out=tmp_path, eval_episodes=0)
    agent_a = SB3Agent(result["checkpoint"], trust_code=True)
    agent_b = SB3Agent(result["checkpoint"], trust_code=True)
    assert agent_a.recurrent and agent_a.obs_mode == "vision"
    rng = np.random.default_rng(0)
    obs = [
        {"state": rng.uniform(-1, 1, 17).astype(np.float32), "depth": rng.uniform(0, 1, (1, 64, 64)).astype(np.float32)}
        for _ in range(5)
    ]
    agent_a.reset()
    agent_b.reset()
    for o in obs:
        np.testing.assert_array_equal(agent_a.act(o), agent_b.act(o))
    # Resume continues from the checkpoint and the saved curriculum level.
    resumed = train(config, "S", steps=64, seed=0, out=tmp_path, resume=result["checkpoint"], eval_episodes=0)
    assert resumed["timesteps"] >= 128
    # The first part's summary is kept aside, not overwritten, and the new one is this part's.
    first = json.loads((tmp_path / f"summary-{result['timesteps']}-steps.json").read_text())
    assert first["timesteps"] == result["timesteps"] and resumed["resumed_at"] == result["timesteps"]
    assert json.loads((tmp_path / "summary.json").read_text())["timesteps"] == resumed["timesteps"]


def test_resuming_a_finished_run_evaluates_the_new_checkpoint(tmp_path: Path) -> None:
    """A finished run's ``eval/`` holds its checkpoint's records; resumed, the final evaluation is the new policy's."""
    config = small(TrainConfig.from_yaml(BASELINES[0].parent / "vision-ppo.yaml"))
    result = train(config, "S", steps=64, seed=0, out=tmp_path, eval_episodes=1)
    resumed = train(config, "S", steps=64, seed=0, out=tmp_path, resume=result["checkpoint"], eval_episodes=1)
    assert resumed["eval"]["n"] == 1
    archived = tmp_path / f"eval-{result['timesteps']}-steps"
    old, new = (pd.read_csv(d / "episodes.csv") for d in (archived, tmp_path / "eval"))
    assert len(old) == len(new) == 1
    assert old["policy_sha256"][0] != new["policy_sha256"][0]
    assert new["policy_sha256"][0] == SB3Agent(resumed["checkpoint"], trust_code=True).sha256
    # Archived under the steps of the model they describe; a taken name moves nothing rather than overwrite.
    (tmp_path / f"eval-{resumed['timesteps']}-steps").mkdir()
    with pytest.raises(ValueError, match="both exist"):
        archive_finished_part(tmp_path, result["timesteps"])
    assert (tmp_path / "summary.json").is_file() and (tmp_path / "eval" / "episodes.csv").is_file()


def test_resume_after_a_killed_run(tmp_path: Path) -> None:
    """A run killed after a checkpoint resumes at that checkpoint's level and reward scale, with its progress rows."""
    config = small(TrainConfig.from_yaml(BASELINES[0].parent / "state-ppo.yaml"))
    rollout = config.n_envs * config.n_steps
    first = train(config, "S", steps=3 * rollout, out=tmp_path, eval_episodes=0, checkpoint_every=1)
    checkpoints = sorted((tmp_path / "checkpoints").glob("*_steps.zip"), key=lambda p: int(p.stem.split("_")[-2]))
    at = int(checkpoints[1].stem.split("_")[-2])  # the second of three: the run went on after it
    assert at == 2 * rollout < first["timesteps"]
    # The lost stretch also saw a promotion the checkpoint never did.
    with (tmp_path / "progress.csv").open("a") as f:
        f.write("6")  # and the kill cut its last row short
    promoted = {"level": 2, "promotions": [{"level": 2, "timestep": at + 1}]}
    (tmp_path / "curriculum.json").write_text(json.dumps(promoted))
    env = make_envs(config, "S", 0)
    _restore_reward_stats(env, _trusted_reward_stats(checkpoints[1], False, written_sha256(tmp_path)))
    saved = VecNormalize.load(str(checkpoints[1].with_name(f"state-ppo_vecnormalize_{at}_steps.pkl")), env.venv)
    assert env.ret_rms.count == saved.ret_rms.count > 1 and env.ret_rms.var == pytest.approx(saved.ret_rms.var)
    env.close()

    resumed = train(config, "S", steps=64, out=tmp_path, resume=checkpoints[1], eval_episodes=0, checkpoint_every=1)
    assert resumed["resumed_at"] == at and resumed["level"] == 1 and resumed["promotions"] == []
    assert resumed["env_seed"] == resume_seed(0, at, config.n_envs) != first["env_seed"] == 0
    progress = pd.read_csv(tmp_path / "progress.csv")
    assert list(progress["timesteps"]) == [at // 2, at, resumed["timesteps"]]
    assert (progress["level"] == 1).all() and progress["wall_s"].is_monotonic_increasing
    assert progress["episodes"].is_monotonic_increasing
    assert not list((tmp_path / "checkpoints").glob("*partial*")), "a finished save left its partial file behind"


def test_periodic_checkpoints_fall_on_absolute_steps_after_a_resume(tmp_path: Path) -> None:
    """A part resumed off the grid still saves at the multiples of ``checkpoint_every`` (where the campaign's
    validation curve is flown), not at multiples counted from where it resumed."""
    config = small(TrainConfig.from_yaml(BASELINES[0].parent / "state-ppo.yaml"))
    rollout = config.n_envs * config.n_steps
    train(config, "S", steps=rollout, out=tmp_path, eval_episodes=0, checkpoint_every=1)
    first = tmp_path / "checkpoints" / f"state-ppo_{rollout}_steps.zip"
    assert first.is_file()
    resumed = train(config, "S", steps=3 * rollout, out=tmp_path, resume=first, eval_episodes=0,
                    checkpoint_every=2 * rollout)  # fmt: skip
    assert resumed["timesteps"] == 4 * rollout
    saved = sorted(int(p.stem.split("_")[-2]) for p in (tmp_path / "checkpoints").glob("state-ppo_*_steps.zip"))
    assert saved == [rollout, 2 * rollout, 4 * rollout]  # counted from the resume it would be 3 rollouts


def test_a_checkpoint_killed_mid_save_never_appears_under_its_name(tmp_path: Path) -> None:
    """The save goes to a sibling file: a kill inside it leaves no ``*_steps.zip`` a resume could pick up."""
    final = tmp_path / "run_128_steps.zip"

    def killed_while_writing(path: str) -> None:
        Path(path).write_bytes(b"PK\x03\x04 half an archive")
        raise KeyboardInterrupt  # stands in for SIGKILL: the save never returns

    with pytest.raises(KeyboardInterrupt):
        _save_atomically(final, killed_while_writing)
    assert not final.exists() and not list(tmp_path.glob("*_steps.zip"))
    _save_atomically(final, lambda path: Path(path).write_bytes(b"whole"))
    assert final.read_bytes() == b"whole" and [p.name for p in tmp_path.iterdir()] == [final.name]


def test_a_truncated_checkpoint_is_a_named_load_error(tmp_path: Path) -> None:
    """An SB3 zip cut right after a nested torch archive opens as that inner archive: refuse it by name."""
    config = small(TrainConfig.from_yaml(BASELINES[0].parent / "state-ppo.yaml"))
    env = make_envs(config, "S", 0)
    path = tmp_path / "whole.zip"
    make_model(config, env, seed=0, tensorboard=None).save(path)
    env.close()
    raw = path.read_bytes()
    inner_end = raw.index(b"PK\x05\x06") + 22  # the end record of the first nested .pth archive
    cut = tmp_path / "cut_128_steps.zip"
    cut.write_bytes(raw[:inner_end])
    with pytest.raises(AgentLoadError, match="cut_128_steps.zip.*no model data"):
        SB3Agent._load(cut, "cpu")


def test_resume_seed_is_new_and_below_the_evaluation_seeds() -> None:
    seeds = {resume_seed(0, 2048 * k, 64) for k in range(1, 200)}
    assert len(seeds) == 199 and all(0 <= s <= EVAL_SEED_BASE - 64 for s in seeds)
    assert resume_seed(7, 0, 64) == 7 and resume_seed(1, 2048, 64) != resume_seed(0, 2048, 64)


def test_resume_curriculum_from_progress_alone(tmp_path: Path) -> None:
    """Without ``curriculum.json`` (a run killed before writing it) the level column of the CSV tells."""
    pd.DataFrame(
        {"timesteps": [100, 200, 300, 400], "episodes": [1, 2, 3, 4], "level": [1, 2, 2, 3], "wall_s": [1, 2, 3, 4]}
    ).to_csv(tmp_path / "progress.csv", index=False)
    assert resume_curriculum(tmp_path, 350, 1) == (2, [{"level": 2, "timestep": 200}])
    assert resume_curriculum(tmp_path, 400, 1) == (3, [{"level": 2, "timestep": 200}, {"level": 3, "timestep": 400}])
    assert resume_curriculum(tmp_path / "nothing", 400, 1) == (1, [])


def test_a_dagger_config_trains_through_racebench_train_and_resumes_from_its_folder(tmp_path: Path) -> None:
    """``method: dagger`` configs run like the PPO baselines: ``racebench train --config``, a run folder, resume."""
    from racebench import cli
    from racebench.training.dagger import DaggerConfig

    shipped = load_config("vision-distill")
    assert isinstance(shipped, DaggerConfig) and shipped.teacher == "planner-fast" and shipped.name == "vision-distill"
    with pytest.raises(ValueError, match="load_config"):
        TrainConfig.from_yaml("vision-distill")  # not a PPO config: named, with where to load it
    config = tmp_path / "tiny-distill.yaml"
    config.write_text("method: dagger\nname: tiny-distill\nsteps_per_iteration: 128\nn_envs: 4\nepochs: 1\n"
                      "batch_size: 64\n")  # fmt: skip
    out = tmp_path / "run"
    args = ["train", "--config", str(config), "--steps", "128", "--out", str(out), "--eval-episodes", "0"]
    assert cli.main(args) == 0
    assert json.loads((out / "summary.json").read_text())["timesteps"] == 128 and (out / "tiny-distill-S.zip").is_file()
    assert cli.main([*args, "--resume", str(out)]) == 0  # --steps 128 more: one more iteration, resumed
    progress = pd.read_csv(out / "progress.csv")
    assert progress["iteration"].tolist() == [0, 1] and progress["samples"].tolist() == [128, 256]
    with pytest.raises(SystemExit, match="resumes from its own folder"):
        cli.main([*args, "--resume", str(tmp_path / "elsewhere")])
    fresh = [*args[:6], str(tmp_path / "fresh"), *args[7:]]
    with pytest.raises(SystemExit, match="nothing to resume"):  # never a silent restart over a folder
        cli.main([*fresh, "--resume", str(tmp_path / "fresh")])
    (tmp_path / "typed.yaml").write_text("method: dagger\nname: typed\nlearning_rate: 3e-4\nseed: 2\n")
    with pytest.raises(SystemExit, match="'seed' is set per run"):
        cli.main(["train", "--config", str(tmp_path / "typed.yaml")])
    (tmp_path / "bad.yaml").write_text("method: dagger\nname: bad\nbeta_decay: 3\n")
    with pytest.raises(SystemExit, match="beta_decay"):
        cli.main(["train", "--config", str(tmp_path / "bad.yaml")])


def test_fine_tuning_starts_from_the_student_and_warms_up_the_critic_alone(tmp_path: Path) -> None:
    """vision-distill-ppo: the policy starts as the named checkpoint (log sigma reset), and during the critic
    warm-up only critic parameters change."""
    import torch

    from racebench.agents import SB3Agent
    from racebench.training.train import critic_parameter

    config = small(TrainConfig.from_yaml("vision-distill-ppo"), n_envs=4, n_steps=32, batch_size=64)
    env = make_vec_env("RaceObs-S-v0", n_envs=1, env_kwargs=config.env_kwargs("S"), vec_env_cls=DummyVecEnv)
    student = make_model(config, env, seed=7, tensorboard=None)
    env.close()
    names = [name for name, _ in student.policy.named_parameters()]
    critic = {n for n in names if n.startswith(("lstm_critic.", "mlp_extractor.value_net.", "value_net."))}
    assert critic and {n for n in names if critic_parameter(n)} == critic  # the GRU policy's own names
    with torch.no_grad():
        student.policy.log_std.fill_(0.0)  # a DAgger student's sigma: whatever it was, the run resets it
    (tmp_path / "student-S-seed3").mkdir()
    student.save(tmp_path / "student-S-seed3" / "student.zip")
    start = {k: v.clone() for k, v in student.policy.state_dict().items()}

    config = dataclasses.replace(config, init_from=str(tmp_path / "student-{track}-seed{seed}" / "student.zip"),
                                 critic_warmup=10**6)  # fmt: skip
    result = train(config, "S", steps=256, seed=3, out=tmp_path / "run", eval_episodes=0)
    assert result["init_from"] == str(tmp_path / "student-S-seed3" / "student.zip")
    tuned = SB3Agent(result["checkpoint"], trust_code=True).model.policy.state_dict()
    changed = {k for k in start if k != "log_std" and not torch.equal(start[k], tuned[k])}
    assert changed and changed <= critic  # the critic learned, nothing else moved
    assert any(k.startswith("lstm_critic.") for k in changed) and any(k.startswith("value_net.") for k in changed)
    assert torch.all(tuned["log_std"] == config.log_std_init)

    after = train(dataclasses.replace(config, critic_warmup=0), "S", steps=256, seed=3, out=tmp_path / "free",
                  eval_episodes=0)  # fmt: skip
    free = SB3Agent(after["checkpoint"], trust_code=True).model.policy.state_dict()
    assert any(not torch.equal(start[k], free[k]) for k in start if not critic_parameter(k))  # without: all learn

    with pytest.raises(ValueError, match="init_from: .* is not a file"):
        train(dataclasses.replace(config, init_from=str(tmp_path / "missing.zip")), "S", steps=64, out=tmp_path / "x",
              eval_episodes=0)  # fmt: skip
    other = small(TrainConfig.from_yaml("vision-no-gru"), n_envs=4, n_steps=32, batch_size=64,
                  init_from=config.init_from)  # fmt: skip
    with pytest.raises(ValueError, match="another network"):
        train(other, "S", steps=64, seed=3, out=tmp_path / "y", eval_episodes=0)


def bc_distance(policy, pending: tuple) -> float:  # noqa: ANN001 - an SB3 policy
    """The BC loss of ``policy`` on a callback's pending rollout ``(obs, starts, start_hidden, target)``."""
    from racebench.training.train import mean_actions_along

    obs, starts, start_hidden, target = pending
    with torch.no_grad():
        actions = mean_actions_along(policy, obs, starts, start_hidden)[0]
    return float(torch.nn.functional.mse_loss(actions, target))


def test_bc_to_the_student_steps_towards_it_along_the_rollout(tmp_path: Path) -> None:
    """bc_coef: the anchor's actions along a rollout are the ones it takes stepping it (state carried, reset
    at episode starts); one BC step brings the policy's actions on that rollout closer to them."""
    from racebench.training.train import StudentBCCallback, frozen_initial_policy, mean_actions_along

    config = small(TrainConfig(name="t", obs_mode="state"), n_envs=2, n_steps=16, batch_size=32,
                   learning_rate=(1e-3, 1e-3))  # fmt: skip
    env = make_vec_env("RaceObs-S-Level1-v0", n_envs=2, env_kwargs={"obs_mode": "state"}, vec_env_cls=DummyVecEnv)
    model = make_model(config, env, seed=0, tensorboard=None)
    model.save(tmp_path / "student.zip")

    # Along a made-up rollout with an episode start inside it, the actions are predict()'s, one step at a time.
    anchor = frozen_initial_policy(model, tmp_path / "student.zip")
    obs = np.random.default_rng(1).uniform(-1, 1, size=(6, 2, 17)).astype(np.float32)
    starts = np.zeros((6, 2), dtype=np.float32)
    starts[0], starts[3, 1] = 1.0, 1.0
    with torch.no_grad():
        along, last = mean_actions_along(anchor, obs, starts, torch.zeros(1, 2, config.gru_hidden))
    state, stepped = None, []
    for o, s in zip(obs, starts, strict=True):
        action, state = model.predict(o, state=state, episode_start=s.astype(bool), deterministic=True)
        stepped.append(action)
    np.testing.assert_allclose(along.numpy().clip(-1, 1), np.stack(stepped), atol=1e-5)
    np.testing.assert_allclose(last.numpy(), state[0], atol=1e-5)  # the state after the last step, too

    # Move the actor away from the student, fly one rollout (and its PPO update), then take the BC step.
    with torch.no_grad():
        for name, parameter in model.policy.named_parameters():
            if name.startswith("action_net."):
                parameter.add_(0.3 * torch.randn_like(parameter))
    bc = StudentBCCallback(anchor, coef=1.0, threads=1)
    model.learn(config.n_envs * config.n_steps, callback=bc)
    obs, starts, start_hidden, target = bc.pending
    assert target.shape == (config.n_steps, config.n_envs, 4)

    before = bc_distance(model.policy, bc.pending)
    bc._on_rollout_start()
    assert bc.distances == [pytest.approx(before, rel=1e-4)] and before > 1e-3
    # one step of the BC loss moved the policy's actions towards the student's
    assert bc_distance(model.policy, (obs, starts, start_hidden, target)) < before
    env.close()

    with pytest.raises(ValueError, match="bc_coef needs init_from"):
        TrainConfig(name="t", bc_coef=0.5).validate()
    with pytest.raises(ValueError, match="bc_coef must be >= 0"):
        TrainConfig(name="t", bc_coef=-1.0, init_from="x.zip").validate()


TEACHER = {"gate_clearance": 0.5, "wanted_clearance": 0.6, "integral_gain": 0.0}


def replay_teacher_labels(env_kwargs: dict, seed: int, actions: np.ndarray) -> np.ndarray:
    """The teacher's action for each state of one env flown alone with ``actions`` from ``reset(seed)``, reset
    (unseeded, as a vector env autoresets) whenever an episode ends: the labels a labelled vector env must give."""
    import gymnasium as gym

    from racebench.agents.planner import FastPlannerAgent
    from racebench.envs.env import RaceEnv

    limit = gym.spec("RaceObs-S-v0").max_episode_steps
    env, teacher = RaceEnv(**env_kwargs), FastPlannerAgent(**TEACHER)
    env.reset_state(seed=seed)
    teacher.reset(env=env)
    labels = []
    for action in actions:
        labels.append(np.clip(teacher.act(), -1.0, 1.0))
        _, terminated, truncated, _ = env.advance(np.clip(action, -1.0, 1.0))
        if terminated or truncated or env.steps >= limit:
            env.reset_state()
            teacher.reset(env=env)
    env.close()
    return np.stack(labels).astype(np.float32)


@pytest.mark.parametrize("num_processes", [1, 2])
def test_teacher_labels_are_its_actions_for_the_observations_returned(num_processes: int) -> None:
    """RaceSB3VecEnv(teacher=...): each observation comes with the teacher's action for that state, the first ones
    in reset_infos, the first of a new episode in the ending step's info; the observation itself is unchanged."""
    import gymnasium as gym

    from racebench.training.sb3 import make_sb3_vec_env

    kwargs = {"obs_mode": "state", "start_mode": "gates"}
    env = make_sb3_vec_env("RaceObs-S-v0", n_envs=2, seed=11, num_processes=num_processes, teacher=TEACHER, **kwargs)
    plain = make_sb3_vec_env("RaceObs-S-v0", n_envs=2, seed=11, **kwargs)
    labelled_obs, plain_obs = env.reset(), plain.reset()
    labels = [np.stack([info["teacher_action"] for info in env.unwrapped.reset_infos])]
    rng = np.random.default_rng(0)
    actions, ends = [], 0
    for _ in range(60):  # random actions end episodes within tens of steps: autoresets are exercised
        actions.append(rng.uniform(-1, 1, size=(2, 4)).astype(np.float32))
        labelled_obs, _, dones, infos = env.step(actions[-1])
        plain_obs, *_ = plain.step(actions[-1])
        np.testing.assert_array_equal(labelled_obs, plain_obs)  # labels never reach the observation
        labels.append(np.stack([info["teacher_action"] for info in infos]))
        ends += int(dones.sum())
    env.close()
    plain.close()
    assert ends >= 2
    spec_kwargs = {**gym.spec("RaceObs-S-v0").kwargs, **kwargs}
    for i in range(2):
        expected = replay_teacher_labels(spec_kwargs, 11 + i, np.stack(actions)[:, i])
        np.testing.assert_allclose(np.stack(labels)[:-1, i], expected, atol=1e-6)


def test_bc_to_the_teacher_clones_its_labels_of_the_rollout(tmp_path: Path) -> None:
    """bc_target "teacher": the targets of each rollout are the teacher's actions for exactly the states in the
    rollout buffer (replayed alone from the buffer's actions, across rollouts and episode ends), and one BC step
    brings the policy's actions closer to them."""
    from racebench.training.sb3 import make_sb3_vec_env
    from racebench.training.train import TeacherBCCallback

    config = small(TrainConfig(name="t", obs_mode="state", bc_coef=1.0, bc_target="teacher"), vec_env="race",
                   learning_rate=(1e-3, 1e-3))  # fmt: skip
    kwargs = config.env_kwargs("S")
    env = make_sb3_vec_env("RaceObs-S-v0", n_envs=2, seed=0, teacher=config.teacher, **kwargs)
    model = make_model(config, env, seed=0, tensorboard=None)  # seeds env i with 0 + i
    bc = TeacherBCCallback(coef=1.0, threads=1)
    rollouts = []
    targets = bc._targets

    def record(obs, starts, buffer):  # noqa: ANN001, ANN202 - the callback's own signature
        target = targets(obs, starts, buffer)
        rollouts.append((target.numpy().copy(), buffer.actions.copy(), starts.copy()))
        return target

    bc._targets = record
    model.learn(3 * config.n_envs * config.n_steps, callback=bc)
    target, actions, starts = (np.concatenate(column) for column in zip(*rollouts, strict=True))
    assert target.shape == (3 * config.n_steps, 2, 4) and starts[1:].sum() >= 1  # an episode ended on the way
    import gymnasium as gym

    for i in range(2):
        expected = replay_teacher_labels({**gym.spec("RaceObs-S-v0").kwargs, **kwargs}, i, actions[:, i])
        np.testing.assert_allclose(target[:, i], expected, atol=1e-6)

    pending = bc.pending
    before = bc_distance(model.policy, pending)
    bc._on_rollout_start()
    assert bc.distances[-1] == pytest.approx(before, rel=1e-4) and bc_distance(model.policy, pending) < before
    env.close()


def test_bc_target_settings_are_checked() -> None:
    TrainConfig(name="t", bc_coef=1.0, bc_target="teacher", vec_env="race").validate()  # no init_from needed
    with pytest.raises(ValueError, match="bc_target must be one of"):
        TrainConfig(name="t", bc_target="expert").validate()
    with pytest.raises(ValueError, match="bc_target 'teacher' needs vec_env 'race'"):
        TrainConfig(name="t", bc_coef=1.0, bc_target="teacher", vec_env="dummy").validate()
    with pytest.raises(ValueError, match="teacher: .*unexpected keyword argument 'berth'"):
        TrainConfig(name="t", teacher={"berth": 0.5}).validate()
    with pytest.raises(ValueError, match="teacher: must be a mapping"):
        TrainConfig(name="t", teacher=[0.5]).validate()


def test_fine_tuning_with_bc_runs_on_depth_and_reports_its_distance(tmp_path: Path) -> None:
    config = small(TrainConfig.from_yaml("vision-distill-ppo"), n_envs=4, n_steps=32, batch_size=64)
    env = make_vec_env("RaceObs-S-v0", n_envs=1, env_kwargs=config.env_kwargs("S"), vec_env_cls=DummyVecEnv)
    make_model(config, env, seed=7, tensorboard=None).save(tmp_path / "student.zip")
    env.close()
    config = dataclasses.replace(config, init_from=str(tmp_path / "student.zip"), critic_warmup=0, bc_coef=1.0)
    result = train(config, "S", steps=3 * 4 * 32, seed=3, out=tmp_path / "run", eval_episodes=0)
    assert np.isfinite(result["bc_mse_last"]) and result["bc_mse_last"] >= 0


# ------------------------------------------------------- untrusted checkpoints are never unpickled


def test_train_resume_refuses_a_pickled_payload(tmp_path: Path) -> None:
    """``racebench train --resume evil.zip``: one line naming --trust-code, and nothing of the file runs."""
    marker = tmp_path / "ran"
    evil = evil_sb3_zip(tmp_path / "evil.zip", marker)
    argv = ["train", "--config", "state-ppo", "--num-processes", "1", "--steps", "64",
            "--eval-episodes", "0", "--resume", str(evil), "--out", str(tmp_path / "run")]  # fmt: skip
    with pytest.raises(SystemExit) as exc:
        cli.main(argv)
    message = str(exc.value.code)
    assert message.startswith("racebench train: checkpoint") and "--trust-code" in message and "\n" not in message
    assert not marker.exists()
    with pytest.raises(AgentLoadError):  # the payload is live: a trusted load runs it
        _load_model(evil, trust_code=True)
    assert marker.exists()


def test_a_run_trusts_only_what_it_wrote(tmp_path: Path) -> None:
    """written.json lists every checkpoint and statistics file a run wrote; a resume trusts those and nothing else."""
    config = small(TrainConfig.from_yaml(BASELINES[0].parent / "state-ppo.yaml"))
    run = tmp_path / "run"
    result = train(config, "S", steps=64, out=run, eval_episodes=0, checkpoint_every=1)
    written = json.loads((run / WRITTEN_FILE).read_text())
    expected = {"state-ppo-S.zip", "vecnormalize.pkl", *(str(p.relative_to(run)) for p in run.glob("checkpoints/*"))}
    assert set(written) == expected and len(expected) == 4
    assert own_policy_trust(run, result["checkpoint"])
    # Another folder did not write this checkpoint: resuming from it there needs --trust-code.
    with pytest.raises(UntrustedCodeError, match="--trust-code"):
        train(config, "S", steps=64, out=tmp_path / "other", resume=result["checkpoint"], eval_episodes=0)
    # Statistics swapped for a pickle payload are refused, before the checkpoint is loaded.
    marker = tmp_path / "ran"
    (run / "vecnormalize.pkl").write_bytes(evil_pickle(marker))
    with pytest.raises(UntrustedCodeError, match=r"statistics .*vecnormalize\.pkl.*--trust-code"):
        train(config, "S", steps=64, out=run, resume=result["checkpoint"], eval_episodes=0)
    with pytest.raises(UntrustedCodeError, match="statistics"):  # nor does the final evaluation read them
        own_policy_trust(run, result["checkpoint"])
    assert not marker.exists()
    # The CLI says it in one line.
    with pytest.raises(SystemExit) as exc:
        cli.main(["train", "--config", "state-ppo", "--num-processes", "1", "--steps", "64",
                  "--eval-episodes", "0", "--resume", result["checkpoint"], "--out", str(run)])  # fmt: skip
    assert "vecnormalize.pkl" in str(exc.value.code) and "\n" not in str(exc.value.code)
    assert not marker.exists()


def test_own_policy_trust_needs_the_checkpoint_listed(tmp_path: Path) -> None:
    checkpoint = tmp_path / "model.zip"
    checkpoint.write_bytes(b"not listed")
    assert not own_policy_trust(tmp_path, checkpoint) and own_policy_trust(tmp_path, checkpoint, trust_code=True)
    record_written(tmp_path, checkpoint)
    assert own_policy_trust(tmp_path, checkpoint)
    checkpoint.write_bytes(b"changed after it was written")
    assert not own_policy_trust(tmp_path, checkpoint)
    (tmp_path / WRITTEN_FILE).write_text("not json")  # a damaged manifest vouches for nothing
    assert written_sha256(tmp_path) == frozenset()


def test_init_from_reads_no_pickled_code(tmp_path: Path) -> None:
    """``init_from`` reads tensors only: a payload in the zip's data or in its policy.pth never runs."""
    marker = tmp_path / "ran"
    evil = evil_sb3_zip(tmp_path / "evil.zip", marker)
    config = small(TrainConfig.from_yaml(BASELINES[0].parent / "state-ppo.yaml"), init_from=str(evil))
    with pytest.raises(ValueError, match="init_from: .*evil.zip is not an SB3 checkpoint") as exc:
        train(config, "S", steps=64, out=tmp_path / "run", eval_episodes=0)
    assert "\n" not in str(exc.value)
    assert not marker.exists()
