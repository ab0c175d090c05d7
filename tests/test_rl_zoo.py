"""rl-baselines3-zoo runs (docs/rl-zoo.md): their VecNormalize statistics are found where the zoo writes them, and
never silently left out: ambiguous or unmatched statistics stop every command until the user chooses.

The zoo is not installed: a fixture lays out a run folder exactly as ``python -m rl_zoo3.train`` does with
``normalize: true`` (``<run>/<env>.zip``, ``<run>/<env>/{vecnormalize.pkl,config.yml,args.yml}``, ``best_model.zip``
and ``rl_model_<n>_steps.zip`` / ``rl_model_vecnormalize_<n>_steps.pkl``) from a tiny PPO trained under
``VecNormalize(norm_obs=True)``.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from stable_baselines3 import PPO
from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

import racebench  # noqa: F401  (registers the ids)
from racebench import cli
from racebench.agents import (
    NO_VECNORMALIZE,
    AgentLoadError,
    OnnxAgent,
    SB3Agent,
    VecNormalizeChoiceError,
    load_agent,
    policy_identity,
    resolve_vecnormalize,
    sb3_policy_sha256,
    vecnormalize_candidates,
)
from racebench.evaluation import Evaluator
from racebench.evaluation.records import read_folder, sha256_file

ENV = "RaceObs-S-Level1-v0"
# What the zoo writes (yaml.dump of OrderedDicts, hence the Python tags): never parsed by racebench.
CONFIG_YML = """!!python/object/apply:collections.OrderedDict
- - - batch_size
    - 32
  - - env_kwargs
    - obs_mode: state
  - - n_steps
    - 64
  - - n_timesteps
    - 128
  - - normalize
    - true
  - - policy
    - MlpPolicy
"""
ARGS_YML = f"""!!python/object/apply:collections.OrderedDict
- - - algo
    - ppo
  - - env
    - {ENV}
  - - gym_packages
    - - racebench
  - - log_folder
    - logs
  - - seed
    - 0
"""


@pytest.fixture(scope="module")
def zoo_run(tmp_path_factory: pytest.TempPathFactory):
    """``logs/ppo/<env>_1`` as the zoo leaves it; returns the model, its VecNormalize and the run folder."""
    venv = VecNormalize(DummyVecEnv([lambda: gym.make(ENV, obs_mode="state")]), norm_obs=True, norm_reward=False)
    model = PPO("MlpPolicy", venv, n_steps=64, batch_size=32, n_epochs=1, seed=0,
                policy_kwargs={"net_arch": [16]}, device="cpu")  # fmt: skip
    model.learn(128)
    assert np.any(np.abs(venv.obs_rms.mean) > 0.05), "the statistics must move observations for the test to bite"
    run = tmp_path_factory.mktemp("logs") / "ppo" / f"{ENV}_1"
    params = run / ENV
    params.mkdir(parents=True)
    model.save(run / f"{ENV}.zip")  # exp_manager: model.save(f"{save_path}/{env_name}")
    venv.save(str(params / "vecnormalize.pkl"))  # exp_manager: params_path/vecnormalize.pkl
    (params / "config.yml").write_text(CONFIG_YML)
    (params / "args.yml").write_text(ARGS_YML)
    venv.training = False
    return model, venv, run


def copy_run(run: Path, tmp_path: Path) -> Path:
    """A fresh copy of the zoo run for a test that adds or removes files."""
    return Path(shutil.copytree(run, tmp_path / "logs" / "ppo" / run.name))


def observations(n: int = 6) -> np.ndarray:
    return np.random.default_rng(0).uniform(-1, 1, size=(n, 17)).astype(np.float32)


def actions(agent: SB3Agent | OnnxAgent, obs: np.ndarray) -> np.ndarray:
    agent.reset()
    return np.array([agent.act(o) for o in obs])


def fail(argv: list[str]) -> str:
    """The one-line error a command stops with."""
    with pytest.raises(SystemExit) as exc:
        cli.main(argv)
    message = str(exc.value.code)
    assert "\n" not in message, f"not one line: {message!r}"
    return message


def test_a_zoo_run_evaluates_with_its_statistics(zoo_run, tmp_path: Path) -> None:
    model, venv, run = zoo_run
    checkpoint, stats = run / f"{ENV}.zip", run / ENV / "vecnormalize.pkl"
    assert resolve_vecnormalize(checkpoint) == stats
    expected_sha = sb3_policy_sha256(sha256_file(checkpoint), sha256_file(stats))
    assert policy_identity(str(checkpoint)).sha256 == expected_sha != sha256_file(checkpoint)
    agent = load_agent(str(checkpoint), trust_code=True)
    assert agent.sha256 == expected_sha and agent.stats_path == stats and agent.normalizer is not None
    obs = observations()
    want = np.array([model.predict(venv.normalize_obs(o), deterministic=True)[0] for o in obs])
    np.testing.assert_array_equal(actions(agent, obs), want)  # SB3's own predict on normalised observations
    bare = tmp_path / "bare.zip"  # the zip alone, with no statistics near it: other actions, the zip's hash
    shutil.copy(checkpoint, bare)
    assert not np.allclose(actions(load_agent(str(bare), trust_code=True), obs), want)
    assert policy_identity(str(bare)).sha256 == sha256_file(bare)
    # The documented command line: the records carry the hash that includes the statistics.
    out = tmp_path / "eval"
    argv = ["evaluate", "--agent", str(checkpoint), "--trust-code", "--envs", ENV, "--episodes", "1"]
    assert cli.main([*argv, "--out", str(out)]) == 0
    (record,) = read_folder(out).records.values()
    assert record["policy_sha256"] == expected_sha


def test_the_zoos_best_and_periodic_checkpoints_find_their_statistics(zoo_run, tmp_path: Path) -> None:
    run = copy_run(zoo_run[2], tmp_path)
    shutil.copy(run / f"{ENV}.zip", run / "best_model.zip")  # EvalCallback(best_model_save_path=save_path)
    assert vecnormalize_candidates(run / "best_model.zip") == [run / ENV / "vecnormalize.pkl"]  # as the zoo's enjoy
    # CheckpointCallback(save_path=save_path, name_prefix="rl_model", save_vecnormalize=True)
    shutil.copy(run / f"{ENV}.zip", run / "rl_model_128_steps.zip")
    shutil.copy(run / ENV / "vecnormalize.pkl", run / "rl_model_vecnormalize_128_steps.pkl")
    assert resolve_vecnormalize(run / "rl_model_128_steps.zip") == run / "rl_model_vecnormalize_128_steps.pkl"
    # The final model is still matched to its own statistics alone, with the periodic ones beside it.
    assert resolve_vecnormalize(run / f"{ENV}.zip") == run / ENV / "vecnormalize.pkl"


COMMANDS = {
    "evaluate": lambda spec: ["evaluate", "--agent", spec, "--envs", ENV, "--episodes", "1"],
    "fly": lambda spec: ["fly", "--agent", spec, "--env", ENV],
    "render": lambda spec: ["render", "--agent", spec, "--env", ENV],
    "export-onnx": lambda spec: ["export-onnx", spec],
    "export-policy": lambda spec: ["export-policy", spec, "--out", str(Path(spec).with_name("policy.zip"))],
}


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_ambiguous_statistics_stop_every_command(command: str, zoo_run, tmp_path: Path) -> None:
    run = copy_run(zoo_run[2], tmp_path)
    shutil.copy(run / ENV / "vecnormalize.pkl", run / "vecnormalize.pkl")  # beside the zip too: which one?
    message = fail([*COMMANDS[command](str(run / f"{ENV}.zip")), "--trust-code"])
    assert message.startswith(f"racebench {command}: ") and "several VecNormalize statistics" in message
    assert str(run / "vecnormalize.pkl") in message and str(run / ENV / "vecnormalize.pkl") in message
    assert "--vecnormalize PATH" in message and "--no-vecnormalize" in message
    assert not (run / "policy.zip").exists() and not (run / f"{ENV}.onnx").exists(), "nothing written"


def test_unmatched_statistics_stop_the_evaluation(zoo_run, tmp_path: Path) -> None:
    run = copy_run(zoo_run[2], tmp_path)
    # A periodic checkpoint saved without its own statistics: the final ones in <run>/<env>/ are not its own.
    shutil.copy(run / f"{ENV}.zip", run / "rl_model_64_steps.zip")
    spec = str(run / "rl_model_64_steps.zip")
    message = fail(["evaluate", "--agent", spec, "--trust-code", "--envs", ENV, "--episodes", "1"])
    assert "none is named as its own" in message and str(run / ENV / "vecnormalize.pkl") in message
    assert "--vecnormalize PATH" in message and "--no-vecnormalize" in message
    with pytest.raises(VecNormalizeChoiceError):
        policy_identity(spec)
    with pytest.raises(VecNormalizeChoiceError):
        load_agent(spec, trust_code=True)
    # A statistics file of another name beside a final model is not matched either.
    (run / ENV / "vecnormalize.pkl").rename(run / "vecnormalize_final.pkl")
    assert "vecnormalize_final.pkl" in fail(["fly", "--agent", str(run / f"{ENV}.zip"), "--trust-code"])


def test_the_choice_resolves_it_and_is_part_of_the_hash(zoo_run, tmp_path: Path) -> None:
    model, venv, original = zoo_run
    run = copy_run(original, tmp_path)
    shutil.copy(run / ENV / "vecnormalize.pkl", run / "vecnormalize.pkl")  # ambiguous, as above
    checkpoint, stats = run / f"{ENV}.zip", run / ENV / "vecnormalize.pkl"
    zip_sha, obs = sha256_file(checkpoint), observations()
    chosen = load_agent(str(checkpoint), trust_code=True, vecnormalize=stats)
    assert chosen.sha256 == sb3_policy_sha256(zip_sha, sha256_file(stats))
    assert policy_identity(str(checkpoint), vecnormalize=str(stats)).sha256 == chosen.sha256
    normalised = np.array([model.predict(venv.normalize_obs(o), deterministic=True)[0] for o in obs])
    np.testing.assert_array_equal(actions(chosen, obs), normalised)
    # --no-vecnormalize: the raw observations, and a hash that says so (neither the zip's nor the run's).
    none = load_agent(str(checkpoint), trust_code=True, vecnormalize=False)
    assert none.normalizer is None and none.sha256 == sb3_policy_sha256(zip_sha, NO_VECNORMALIZE)
    assert none.sha256 not in (zip_sha, chosen.sha256)
    assert policy_identity(str(checkpoint), vecnormalize=False).sha256 == none.sha256
    raw = np.array([model.predict(o, deterministic=True)[0] for o in obs])
    np.testing.assert_array_equal(actions(none, obs), raw)
    # The same on the command line, and the evaluator keys its records to the choice.
    argv = ["evaluate", "--agent", str(checkpoint), "--trust-code", "--envs", ENV, "--episodes", "1"]
    for option, sha in ((["--vecnormalize", str(stats)], chosen.sha256), (["--no-vecnormalize"], none.sha256)):
        out = tmp_path / f"eval{len(option)}"
        assert cli.main([*argv, *option, "--out", str(out)]) == 0
        (record,) = read_folder(out).records.values()
        assert record["policy_sha256"] == sha
    evaluator = Evaluator(str(checkpoint), [ENV], episodes=1, out_dir=tmp_path / "api", trust_code=True,
                          vecnormalize=stats)  # fmt: skip
    assert evaluator.identity.sha256 == chosen.sha256
    # A choice only means something for an SB3 checkpoint.
    with pytest.raises(AgentLoadError, match="SB3 .zip agents only"):
        load_agent("hover", vecnormalize=False)
    with pytest.raises(AgentLoadError, match="do not exist"):
        load_agent(str(checkpoint), trust_code=True, vecnormalize=run / "missing.pkl")


def test_export_onnx_folds_the_zoo_statistics_in(zoo_run, tmp_path: Path) -> None:
    _, _, run = zoo_run
    checkpoint, out = run / f"{ENV}.zip", tmp_path / "zoo.onnx"
    assert cli.main(["export-onnx", str(checkpoint), "--out", str(out), "--trust-code"]) == 0
    onnx, flown = load_agent(str(out)), load_agent(str(checkpoint), trust_code=True)
    assert isinstance(onnx, OnnxAgent) and flown.normalizer is not None
    obs = observations(16)
    np.testing.assert_allclose(actions(onnx, obs), actions(flown, obs), atol=1e-5)


def test_a_leaderboard_entry_refuses_an_ambiguous_checkpoint(zoo_run, tmp_path: Path) -> None:
    from racebench.leaderboard.entries import EntryError, policy_sha256

    run = copy_run(zoo_run[2], tmp_path)
    shutil.copy(run / f"{ENV}.zip", run / "rl_model_64_steps.zip")  # unmatched: only a choice could resolve it
    policy = (run / "rl_model_64_steps.zip").relative_to(tmp_path).as_posix()
    with pytest.raises(EntryError, match="export-onnx"):
        policy_sha256(policy, tmp_path)
    # The final model's own statistics need no choice: its entry hash includes them.
    final = (run / f"{ENV}.zip").relative_to(tmp_path).as_posix()
    assert policy_sha256(final, tmp_path) == policy_identity(str(run / f"{ENV}.zip")).sha256


def test_the_docs_hyperparameter_file_names_our_ids_and_settings() -> None:
    """docs/rl-zoo.md's hp.yml: valid YAML (anchors as the zoo's yaml loader reads them), registered ids, PPO on the
    uint8 depth with VecNormalize; the env it asks for gives SB3 an image."""
    import re

    import yaml

    text = (Path(__file__).parents[1] / "docs" / "rl-zoo.md").read_text()
    (block,) = re.findall(r"```yaml\n(.*?)```", text, re.S)
    hyperparams = yaml.safe_load(block)
    assert set(hyperparams) == {f"RaceObs-S-Level{level}-v0" for level in (1, 2, 3)} <= set(racebench.ENV_IDS)
    for settings in hyperparams.values():
        assert settings["policy"] == "MultiInputPolicy" and settings["normalize"] is True
        assert settings["env_kwargs"] == {"depth_format": "uint8"}
    env = gym.make(ENV, **hyperparams[ENV]["env_kwargs"])
    assert env.observation_space["depth"].dtype == np.uint8
    env.close()
    assert f"racebench evaluate --agent logs/ppo/{ENV}_1/{ENV}.zip --trust-code" in text
