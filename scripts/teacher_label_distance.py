"""How far a policy's actions are from the privileged teacher's labels on the states the policy itself reaches.

    python scripts/teacher_label_distance.py baselines/checkpoints/vision-distill-S/vision-distill-S.zip \\
        --config baselines/experiments/distill-ppo-teacher-bc/config.yaml --track S

The policy flies ``--envs`` training envs for ``--steps`` steps (deterministic actions, ray-cast depth) in two
settings: the fine-tuning's envs (the config's last-level kwargs: start before a random gate with its spread,
its density) and the evaluation id's scenes (``RaceObs-<T>-v0``, track start, gates shifted as in DAgger
training). The envs carry the config's ``teacher`` (``RaceSB3VecEnv(teacher=...)``), which labels every state;
prints the mean squared distance per action channel (collective thrust, roll, pitch and yaw rate, in the
normalised [-1, 1] action space, the policy's action clipped as the env clips it) and the episodes' success.
Why: with ``bc_target: teacher`` the fine-tuning's BC distance stayed at ~0.33 (``distill-ppo-teacher-bc``) where
the DAgger students' fit loss ends at ~0.04; this shows where that distance comes from.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from racebench.agents import load_agent
from racebench.training.sb3 import make_sb3_vec_env
from racebench.training.train import TrainConfig


def label_distance(policy: object, env_kwargs: dict, teacher: dict, n_envs: int, steps: int, seed: int) -> dict:
    """Per-channel mean squared distance of ``policy``'s actions to the teacher's labels, with episode outcomes."""
    env = make_sb3_vec_env("RaceObs-S-v0", n_envs=n_envs, seed=seed, teacher=teacher, **env_kwargs)
    try:
        obs = env.reset()
        labels = np.stack([info["teacher_action"] for info in env.unwrapped.reset_infos])
        state, starts, squared, episodes, successes = None, np.ones(n_envs, dtype=bool), [], 0, 0
        for _ in range(steps):
            action, state = policy.predict(obs, state=state, episode_start=starts, deterministic=True)
            squared.append((np.clip(action, -1.0, 1.0) - labels) ** 2)
            obs, _, starts, infos = env.step(action)
            labels = np.stack([info["teacher_action"] for info in infos])
            episodes += int(starts.sum())
            successes += sum(bool(info.get("is_success")) for info, done in zip(infos, starts, strict=True) if done)
    finally:
        env.close()
    per_channel = np.concatenate(squared).mean(axis=0)
    return {"per_channel": per_channel, "mean": float(per_channel.mean()), "episodes": episodes, "successes": successes}


def main() -> None:
    """Parse the arguments, measure both settings, print them."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("checkpoint", help="an SB3 checkpoint of the policy (e.g. a vision-distill student)")
    parser.add_argument("--config", required=True, help="a PPO fine-tuning config (its levels and teacher)")
    parser.add_argument("--track", default="S", choices=("S", "Circle", "J"))
    parser.add_argument("--envs", type=int, default=8)
    parser.add_argument("--steps", type=int, default=400, help="steps per env")
    parser.add_argument("--seed", type=int, default=123, help="training-range scene seed of env 0")
    args = parser.parse_args()
    torch.set_num_threads(1)  # one env batch and one small network: more threads only oversubscribe the cores
    config = TrainConfig.from_yaml(args.config)
    policy = load_agent(args.checkpoint, trust_code=True).model
    last_level = {**config.env_kwargs(args.track), **config.level_kwargs(max(config.levels))}
    evaluation = {"track": args.track, "obs_mode": "vision", "renderer": "raycast", "gate_shift": config.gate_shift}
    settings = (("fine-tuning envs (last level)", last_level), (f"RaceObs-{args.track}-v0 scenes", evaluation))
    for name, kwargs in settings:
        result = label_distance(policy, kwargs, config.teacher, args.envs, args.steps, args.seed)
        channels = " / ".join(f"{v:.3f}" for v in result["per_channel"])
        print(f"{name}: mean squared distance {result['mean']:.3f} (thrust / roll / pitch / yaw rate: {channels}); "
              f"{result['successes']}/{result['episodes']} episodes finished")  # fmt: skip


if __name__ == "__main__":
    main()
