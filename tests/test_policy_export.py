"""The policy-only export without its critic: which tensors are the critic's, that the actions stay exactly the
same, and that nothing trains from such a file."""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch
from stable_baselines3 import PPO
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor

from racebench import cli
from racebench.agents import AgentLoadError, load_agent
from racebench.agents.export import CRITIC_PREFIXES, check_policy_export, critic_only_tensors, export_policy
from racebench.evaluation.protocol import EVAL_SEED_BASE

CHECKPOINT = Path(__file__).parents[1] / "baselines/checkpoints/vision-ppo-S/vision-ppo-S.zip"


class LinearFeatures(BaseFeaturesExtractor):
    """A features extractor with weights, so that sharing it between actor and critic can be told apart."""

    def __init__(self, observation_space: gym.Space, features_dim: int = 8) -> None:
        super().__init__(observation_space, features_dim)
        self.linear = torch.nn.Linear(int(np.prod(observation_space.shape)), features_dim)

    def forward(self, observations: torch.Tensor) -> torch.Tensor:
        return torch.tanh(self.linear(observations.flatten(1)))


@pytest.fixture(scope="module", params=[True, False], ids=["shared-features", "own-features"])
def small_ppo(request: pytest.FixtureRequest):
    env = gym.make("RaceObs-S-Level1-v0", obs_mode="state")
    model = PPO("MlpPolicy", env, n_steps=64, batch_size=32, n_epochs=1, seed=0, device="cpu",
                policy_kwargs={"net_arch": [16], "features_extractor_class": LinearFeatures,
                               "share_features_extractor": request.param})  # fmt: skip
    model.learn(64)
    return model, request.param


def test_the_critic_is_the_tensors_no_action_reads(small_ppo) -> None:
    model, shared = small_ppo
    critic = critic_only_tensors(model.policy)
    assert critic and all(name.startswith(CRITIC_PREFIXES) for name in critic)
    # A shared extractor acts, so it is never the critic's, whatever name it appears under.
    assert any(name.startswith("vf_features_extractor.") for name in critic) is not shared
    # The critic's tensors are exactly those the deterministic action has no gradient for.
    obs = torch.as_tensor(np.random.default_rng(0).uniform(-1, 1, (4, 17)), dtype=torch.float32)
    model.policy.zero_grad()
    model.policy.get_distribution(obs).distribution.mean.sum().backward()
    untouched = {n for n, p in model.policy.named_parameters() if p.grad is None and n != "log_std"}
    assert untouched == {n for n, p in critic.items() if n in dict(model.policy.named_parameters())}


def test_stripped_export_acts_the_same_and_values_zero(small_ppo, tmp_path: Path) -> None:
    model, _ = small_ppo
    before = {k: v.clone() for k, v in model.policy.state_dict().items()}
    out = export_policy(model, tmp_path / "policy.zip")
    assert all(before[k].equal(v) for k, v in model.policy.state_dict().items())  # the model keeps its critic
    assert not hasattr(model, "critic_stripped")
    agent = load_agent(str(out), trust_code=True)
    assert agent.model.critic_stripped is True
    check_policy_export(model, agent.model, str(out))
    obs = np.random.default_rng(1).uniform(-1, 1, size=(6, 17)).astype(np.float32)
    for o in obs:
        np.testing.assert_array_equal(agent.act(o), model.predict(o, deterministic=True)[0])
    assert not agent.model.policy.predict_values(torch.as_tensor(obs)).any()
    assert model.policy.predict_values(torch.as_tensor(obs)).any()
    kept = load_agent(str(export_policy(model, tmp_path / "kept.zip", keep_critic=True)), trust_code=True)
    assert not getattr(kept.model, "critic_stripped", False)
    assert all(before[k].equal(v) for k, v in kept.model.policy.state_dict().items())
    # A stripped export of another model's weights is told apart from this model's.
    with torch.no_grad():
        agent.model.policy.action_net.weight.add_(1.0)
    with pytest.raises(ValueError, match="differ from the checkpoint's \\(action_net.weight\\)"):
        check_policy_export(model, agent.model, "x")


def test_nothing_trains_from_a_stripped_export(small_ppo, tmp_path: Path) -> None:
    from racebench.training.models import policy_weights
    from racebench.training.ppo import _load_model

    model, _ = small_ppo
    out = export_policy(model, tmp_path / "policy.zip")
    with pytest.raises(AgentLoadError, match="without its critic"):
        _load_model(out, trust_code=True)
    with pytest.raises(ValueError, match="init_from: .* without its critic"):
        policy_weights(out, model)
    kept = export_policy(model, tmp_path / "kept.zip", keep_critic=True)
    assert _load_model(kept, trust_code=True).policy is not None
    assert set(policy_weights(kept, model)) == set(model.policy.state_dict())


def test_export_policy_cli_strips_the_gru_policys_critic(tmp_path: Path) -> None:
    out = tmp_path / "lean" / "vision-ppo-S.zip"
    assert cli.main(["export-policy", str(CHECKPOINT), "--out", str(out)]) == 0
    full, lean = load_agent(str(CHECKPOINT)), load_agent(str(out), trust_code=True)
    stripped = critic_only_tensors(lean.model.policy)
    # The shipped GRU policies share one features extractor: the critic is its GRU, its MLP and its head.
    assert {n.split(".")[0] for n in stripped} == {"mlp_extractor", "value_net", "lstm_critic"}
    assert lean.model.critic_stripped and not any(t.any() for t in stripped.values())
    env = gym.make("RaceObs-S-v0")
    obs, _ = env.reset(seed=EVAL_SEED_BASE)
    full.reset()
    lean.reset()
    for _ in range(10):  # the GRU's state carried by each
        action = full.act(obs)
        np.testing.assert_array_equal(lean.act(obs), action)
        obs, *_ = env.step(action)
    kept = tmp_path / "kept" / "vision-ppo-S.zip"
    assert cli.main(["export-policy", str(CHECKPOINT), "--out", str(kept), "--keep-critic"]) == 0
    assert load_agent(str(kept), trust_code=True) is not None and kept.read_bytes() != out.read_bytes()
