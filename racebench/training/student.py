"""The student network as DAgger and behaviour cloning use it: built from a PPO baseline config, its features,
head and unrolled sequence pass, one batched step, and the depth observations a batch of envs returns.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import torch

from racebench.agents.control import command_to_ctbr
from racebench.sim.raycast import BatchDepthRenderer
from racebench.training.config import TrainConfig
from racebench.training.models import make_model


def make_student(env: gym.Env, seed: int, student: str = "vision-ppo") -> Any:
    """The student: the network of the PPO baseline config ``student`` in its SB3 / sb3-contrib model
    (deterministic action = the actor's mean)."""
    config = TrainConfig.from_yaml(student)
    model = make_model(config, env, seed, tensorboard=None, device="cpu")
    gru = getattr(model.policy, "lstm_actor", None)
    if gru is not None and gru.num_layers != 1:
        raise ValueError(f"student {student!r}: a {gru.num_layers}-layer GRU (the chunk states assume one layer)")
    return model


def is_recurrent(policy: Any) -> bool:
    """Whether the student carries a recurrent state (the paper's GRU network)."""
    return getattr(policy, "lstm_actor", None) is not None


def student_features(policy: Any, obs: dict[str, torch.Tensor]) -> torch.Tensor:
    """The actor's features of a batch of observations (state MLP and depth CNN, concatenated)."""
    from stable_baselines3.common.policies import BaseModel

    return BaseModel.extract_features(policy, obs, policy.pi_features_extractor)


def student_head(policy: Any, features: torch.Tensor) -> torch.Tensor:
    """The deterministic action (before clipping) from the actor's features, or from its GRU's output."""
    return policy.action_net(policy.mlp_extractor.forward_actor(features))


def student_mean(policy: Any, obs: dict[str, torch.Tensor]) -> torch.Tensor:
    """A feed-forward student's deterministic action (before clipping) for a batch of observations."""
    return student_head(policy, student_features(policy, obs))


def student_unroll(
    policy: Any, features: torch.Tensor, hidden: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:  # fmt: skip
    """A recurrent student over ``(time, batch, features)`` from the GRU state ``hidden`` ``(1, batch, H)``.

    The same layers, in the same order, as the evaluator's :meth:`racebench.agents.loading.SB3Agent.act_batch`.
    Returns the actions ``(time, batch, 4)`` and the GRU outputs ``(time, batch, H)`` (each step's new state).
    """
    output, _ = policy.lstm_actor(features, (hidden, torch.zeros_like(hidden)))
    return student_head(policy, output), output


def observe(caster: BatchDepthRenderer, envs: list[Any], indices: list[int]) -> list[dict]:
    """The observations of ``envs[i]`` for ``i`` in ``indices``, their depth images ray-cast in one call."""
    depth = caster.render(
        [envs[i].scene for i in indices],
        np.stack([envs[i].drone.position for i in indices]),
        np.stack([envs[i].camera_rotation() for i in indices]),
    )
    return [envs[i].observation(d) for i, d in zip(indices, depth, strict=True)]


def student_step(policy: Any, obs: list[dict], hidden: torch.Tensor | None) -> tuple[np.ndarray, torch.Tensor | None]:
    """The student's deterministic actions (clipped to [-1, 1]; an acceleration student's commands flown through
    :func:`~racebench.agents.control.command_to_ctbr`, as the evaluator does) for a batch of observations, and a
    recurrent
    student's new GRU state from ``hidden`` ``(1, batch, H)`` (``None`` for a feed-forward one)."""
    batch = {"state": torch.from_numpy(np.stack([o["state"] for o in obs])),
             "depth": torch.from_numpy(np.stack([o["depth"] for o in obs]))}  # fmt: skip
    with torch.no_grad():  # not inference_mode: RaceFeatures converts its CNN weights on first use
        if hidden is not None:
            actions, output = student_unroll(policy, student_features(policy, batch).unsqueeze(0), hidden)
            actions, hidden = actions[0], output[-1:].clone()
        else:
            actions = student_mean(policy, batch)
    actions = actions.numpy().clip(-1.0, 1.0)
    if student_output(policy) == "acceleration":
        actions = command_to_ctbr(actions, batch["state"].numpy())
    return actions, hidden


def student_output(policy: Any) -> str:
    """What the student's actor outputs (:data:`~racebench.agents.recurrent.ACTION_OUTPUTS`), so what it is taught:
    the teacher's CTBR actions, or its acceleration commands
    (:func:`~racebench.agents.control.acceleration_command`)."""
    return getattr(policy, "action_output", "ctbr")
