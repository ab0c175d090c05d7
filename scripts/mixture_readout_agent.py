"""A mixture-output student flown at the weighted mean of its candidates instead of its top one (experiment, issue 12).

The ``distill-mixture`` students (``racebench.agents.recurrent.MixtureActionHead``, three candidates) fly their
top-scoring candidate, which changes 13-18 times per lap (``baselines/experiments/distill-mixture/
mixture_modes.txt``). This agent flies the same network with the softmax-weighted mean of the candidates, a read-out
that varies smoothly with the scores, to separate what the switching read-out costs from what the mixture fit did to
the network. Used through the common evaluator::

    racebench evaluate --agent scripts/mixture_readout_agent.py:MixtureReadoutAgent --trust-code \\
        --agent-kwargs '{"checkpoint": "student.zip", "sha256": "<sha256 of student.zip>"}' ...

The checkpoint is pinned by its sha256, so the records' key (this file's source and the kwargs) names the policy.
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

import numpy as np
import torch

from racebench.agents import AgentLoadError, SB3Agent
from racebench.agents.recurrent import MixtureActionHead


def weighted_mean(head: MixtureActionHead, latent: torch.Tensor) -> torch.Tensor:
    """The softmax-weighted mean of ``head``'s candidates ``(..., action_dim)``."""
    means, scores = head.components(latent)
    return (torch.softmax(scores, dim=-1).unsqueeze(-1) * means).sum(-2)


class MixtureReadoutAgent:
    """An SB3 mixture-head checkpoint whose deterministic action is its candidates' weighted mean."""

    privileged = False

    def __init__(self, checkpoint: str, sha256: str, name: str = "mixture-mean") -> None:
        path = Path(checkpoint)
        if not path.is_file():
            raise AgentLoadError(f"MixtureReadoutAgent: {checkpoint!r} does not exist")
        digest = hashlib.sha256(path.read_bytes()).hexdigest()
        if digest != sha256:
            raise AgentLoadError(
                f"MixtureReadoutAgent: {checkpoint!r} has sha256 {digest[:12]}, expected {sha256[:12]}"
            )
        self.student = SB3Agent(path, trust_code=True)
        head = self.student.model.policy.action_net
        if not isinstance(head, MixtureActionHead):
            raise AgentLoadError(f"MixtureReadoutAgent: {checkpoint!r} has no mixture head (action_components 1)")
        # Every path that flies the policy (SB3's predict, the lockstep act_batch) calls action_net.
        head.forward = lambda latent: weighted_mean(head, latent)
        self.obs_mode = self.student.obs_mode
        self.name = name

    def reset(self, env: Any = None, seed: int | None = None) -> None:
        """Clear the recurrent state."""
        self.student.reset(env, seed)

    def act(self, obs: Any) -> np.ndarray:
        """The weighted-mean action for one observation."""
        return np.asarray(self.student.act(obs)).reshape(-1)

    def start(self, slots: int) -> None:
        """Prepare ``slots`` parallel episodes (lockstep evaluation)."""
        self.student.start(slots)

    def reset_slot(self, slot: int) -> None:
        """A new episode in ``slot``."""
        self.student.reset_slot(slot)

    def act_batch(self, observations: list[Any]) -> np.ndarray:
        """Actions ``(slots, 4)``, one batched forward pass."""
        return self.student.act_batch(observations)
