"""``racebench export-onnx``: the ONNX graph flies each policy kind it accepts exactly as its checkpoint does."""

from __future__ import annotations

import functools
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from stable_baselines3 import PPO, SAC
from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

import racebench  # noqa: F401  (registers the ids)
from racebench import cli
from racebench.agents import OnnxAgent, SB3Agent, export_onnx, load_agent
from racebench.envs.env import depth_to_uint8

ROOT = Path(__file__).parents[1]
LEVEL1 = "RaceObs-S-Level1-v0"
# ortho_init=False: PyTorch's default initialisation, whose actions are O(0.1), not SB3's O(0.001) action head.
TINY = {
    "n_steps": 32,
    "batch_size": 32,
    "n_epochs": 1,
    "seed": 0,
    "device": "cpu",
    "policy_kwargs": {"ortho_init": False},
}


@functools.cache
def flown_observations(n: int, **env_kwargs) -> list:
    """``n`` observations of a seeded flight with random actions (a new episode when one ends)."""
    env = gym.make(LEVEL1, **env_kwargs)
    rng = np.random.default_rng(0)
    obs, _ = env.reset(seed=3)
    seen = [obs]
    while len(seen) < n:
        obs, _, terminated, truncated, _ = env.step(rng.uniform(-0.3, 0.3, 4).astype(np.float32) + [0.2, 0, 0, 0])
        seen.append(env.reset()[0] if terminated or truncated else obs)
    env.close()
    return seen


def export(checkpoint: Path, tmp_path: Path) -> OnnxAgent:
    """The checkpoint exported by the command, loaded back by racebench's ONNX loader."""
    out = tmp_path / f"{checkpoint.stem}.onnx"
    assert cli.main(["export-onnx", str(checkpoint), "--out", str(out), "--trust-code"]) == 0
    agent = load_agent(str(out))
    assert isinstance(agent, OnnxAgent)
    return agent


def stacked(observations: list) -> dict | np.ndarray:
    if isinstance(observations[0], dict):
        return {key: np.stack([o[key] for o in observations]) for key in observations[0]}
    return np.stack(observations)


@pytest.mark.parametrize("depth_format", ["float32", "uint8"])
def test_a_stock_multi_input_policy_exports_with_the_zips_actions(depth_format: str, tmp_path: Path) -> None:
    """The README's stock-SB3 path: MultiInputPolicy on the vision env, float or uint8 depth (which SB3 scales by
    1/255 itself: the export must not scale it again)."""
    env = gym.make(LEVEL1, depth_format=depth_format)
    PPO("MultiInputPolicy", env, **TINY).save(tmp_path / "stock.zip")
    env.close()
    float_obs = flown_observations(12)
    zip_obs = flown_observations(12, depth_format=depth_format)
    if depth_format == "uint8":  # the same flight: the uint8 envs' depth is the float one, rounded
        np.testing.assert_array_equal(zip_obs[-1]["depth"], depth_to_uint8(float_obs[-1]["depth"]))
    expected, _ = PPO.load(tmp_path / "stock.zip", device="cpu").predict(stacked(zip_obs), deterministic=True)
    assert np.ptp(expected, axis=0).min() > 1e-3, "the actions must depend on the observation for the test to bite"
    onnx = export(tmp_path / "stock.zip", tmp_path)
    assert onnx.obs_mode == "vision"
    onnx.start(len(float_obs))
    np.testing.assert_allclose(onnx.act_batch(float_obs), expected, atol=1e-5)
    onnx.reset()
    np.testing.assert_allclose(onnx.act(float_obs[5]), expected[5], atol=1e-5)


def test_a_state_policy_exports_with_the_zips_actions(tmp_path: Path) -> None:
    PPO("MlpPolicy", gym.make(LEVEL1, obs_mode="state"), **TINY).save(tmp_path / "state.zip")
    observations = flown_observations(12, obs_mode="state")
    expected, _ = PPO.load(tmp_path / "state.zip", device="cpu").predict(np.stack(observations), deterministic=True)
    onnx = export(tmp_path / "state.zip", tmp_path)
    assert onnx.obs_mode == "state"
    onnx.start(len(observations))
    np.testing.assert_allclose(onnx.act_batch(observations), expected, atol=1e-5)


def test_observation_statistics_beside_the_checkpoint_are_part_of_the_graph(tmp_path: Path) -> None:
    venv = VecNormalize(DummyVecEnv([lambda: gym.make(LEVEL1, obs_mode="state")]), norm_obs=True, norm_reward=False)
    model = PPO("MlpPolicy", venv, **TINY)
    model.learn(64)  # moves the statistics
    model.save(tmp_path / "model.zip")
    venv.save(str(tmp_path / "vecnormalize.pkl"))
    observations = flown_observations(12, obs_mode="state")
    flown = SB3Agent(tmp_path / "model.zip", trust_code=True)
    assert flown.normalizer is not None
    flown.start(len(observations))
    expected = flown.act_batch(observations)
    assert not np.allclose(expected, model.predict(np.stack(observations), deterministic=True)[0], atol=1e-3)
    onnx = export(tmp_path / "model.zip", tmp_path)
    onnx.start(len(observations))
    np.testing.assert_allclose(onnx.act_batch(observations), expected, atol=1e-5)


def test_the_gru_checkpoint_exports_with_the_zips_actions(tmp_path: Path) -> None:
    """racebench's recurrent GRU policy (a shipped checkpoint): one flight step by step, the hidden state carried."""
    from sb3_contrib import RecurrentPPO

    checkpoint = ROOT / "baselines/checkpoints/vision-ppo-S/vision-ppo-S.zip"
    model = RecurrentPPO.load(checkpoint, device="cpu")
    onnx = export(checkpoint, tmp_path)
    assert onnx.hidden_size == model.policy.lstm_actor.hidden_size
    state, start = None, np.ones((1,), dtype=bool)
    onnx.reset()
    for obs in flown_observations(12):
        expected, state = model.predict(
            {k: v[None] for k, v in obs.items()}, state=state, episode_start=start, deterministic=True
        )
        start = np.zeros((1,), dtype=bool)
        np.testing.assert_allclose(onnx.act(obs), expected[0], atol=1e-5)


def test_what_cannot_be_exported_faithfully_is_refused_by_name(tmp_path: Path) -> None:
    from sb3_contrib import RecurrentPPO

    env = gym.make(LEVEL1, obs_mode="state")
    refused = [
        (SAC("MlpPolicy", env, device="cpu", seed=0), "SACPolicy is not an SB3, sb3-contrib or racebench actor-critic"),
        (RecurrentPPO("MlpLstmPolicy", env, device="cpu", seed=0, n_steps=32), "must use racebench's GRU"),
        (PPO("MlpPolicy", env, device="cpu", seed=0, use_sde=True), "is not an SB3, sb3-contrib or racebench"),
    ]
    for model, message in refused:
        with pytest.raises(ValueError, match=message) as caught:
            export_onnx(model, tmp_path / "refused.onnx")
        assert "\n" not in str(caught.value)
        assert not (tmp_path / "refused.onnx").exists()
    env.close()


def test_check_env_compares_the_actions_on_the_checkpoints_own_flight(tmp_path: Path, capsys, monkeypatch) -> None:
    """``--check-env``: the committed GRU checkpoint and its export agree on a real flight; a graph that does not
    (its actions shifted) is an error naming the gap, and its file is removed."""
    from racebench.agents.loading import OnnxAgent as Loaded

    checkpoint = ROOT / "baselines/checkpoints/vision-ppo-S/vision-ppo-S.zip"
    out = tmp_path / "checked.onnx"
    argv = ["export-onnx", str(checkpoint), "--out", str(out), "--check-env", "RaceObs-S-v0", "--check-steps", "20"]
    assert cli.main(argv) == 0
    line = [x for x in capsys.readouterr().out.splitlines() if x.startswith("checked:")]
    assert len(line) == 1 and "over 20 steps of RaceObs-S-v0 (seed 1000000" in line[0]
    assert float(line[0].split("= ")[1].split()[0]) < 1e-4 and out.is_file()

    act = Loaded.act
    monkeypatch.setattr(Loaded, "act", lambda self, obs: act(self, obs) + np.float32(0.01))
    with pytest.raises(SystemExit, match=r"ONNX actions differ from the checkpoint's by up to 0\.01 over 20 steps"):
        cli.main(argv)
    assert not out.exists()
    with pytest.raises(SystemExit, match=r"--check-env 'RaceObs-X-v0' is not a racebench id"):
        cli.main([*argv[:4], "--check-env", "RaceObs-X-v0"])
    assert not out.exists()  # refused before anything is written
    with pytest.raises(SystemExit, match=r"--check-steps must be at least 1, got 0"):
        cli.main([*argv[:-1], "0"])
    assert not out.exists()


def test_the_exporter_choice_is_explained() -> None:
    """The export keeps TorchScript's exporter (dynamo=False); the docs say why the supported one is not used."""
    root = Path(__file__).parents[1]
    assert "dynamo=False" in (root / "racebench" / "agents" / "export.py").read_text()
    text = (root / "docs" / "evaluation.md").read_text()
    assert "Why the ONNX export keeps the TorchScript exporter" in text and "dynamo=True" in text
