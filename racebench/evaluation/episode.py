"""Flying one episode with any agent spec, as ``racebench fly`` does (:func:`fly`)."""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym

import racebench
from racebench.agents.base import BUILTIN_AGENTS


def make_env(env_id: str, **kwargs) -> gym.Env:
    """``gym.make`` of a registered id; an unknown one is a one-line ``SystemExit`` that says where they are listed."""
    if env_id not in gym.registry and env_id not in racebench.ENV_IDS:
        raise SystemExit(f"racebench: unknown environment id {env_id!r}; `racebench envs` lists them")
    return gym.make(env_id, **kwargs)


def fly(
    env_id: str,
    agent: str,
    seed: int,
    obs_mode: str | None = None,
    trust_code: bool = False,
    agent_kwargs: dict | None = None,
    vecnormalize: str | Path | bool | None = None,
) -> dict:
    """Fly one episode of ``env_id`` with any agent spec ``evaluate`` accepts; return its outcome as a dict.
    ``vecnormalize``: an SB3 checkpoint's statistics (:func:`racebench.agents.trust.resolve_vecnormalize`).

    Raises :class:`~racebench.agents.base.AgentLoadError` on a bad spec, an untrusted one without ``trust_code``, or an
    ``obs_mode`` other than the one the policy reads (built-in agents, which never read their observation, fly
    either).
    """
    from racebench.agents.base import AgentLoadError
    from racebench.agents.loading import load_agent
    from racebench.evaluation.rollout import run_episode
    from racebench.evaluation.worker import SingleTorchThread

    pilot = load_agent(agent, trust_code=trust_code, agent_kwargs=agent_kwargs, vecnormalize=vecnormalize)
    if obs_mode is not None and obs_mode != pilot.obs_mode and agent not in BUILTIN_AGENTS:
        # checked before flying: the policy would otherwise fail inside its first act() with an obscure message
        raise AgentLoadError(f"this policy takes {pilot.obs_mode} observations (use --obs-mode {pilot.obs_mode})")
    env = make_env(env_id, obs_mode=obs_mode or pilot.obs_mode)
    with SingleTorchThread():
        result = run_episode(pilot, env, seed)
    env.close()
    truncated = not (result["success"] or result["crashed"] or result["error"])
    return {"env_id": env_id, "agent": agent, "seed": seed, **result, "truncated": truncated}
