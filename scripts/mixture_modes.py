"""Does a mixture-output student use more than one of its candidate actions, and where?

    python scripts/mixture_modes.py runs/distill-mixture-S-seed0/vision-distill-mixture-S.zip \\
        --env RaceObs-S-v0 --episodes 20

Flies a student with a :class:`racebench.agents.recurrent.MixtureActionHead` on the first ``--episodes``
evaluation scenes (seeds from ``EVAL_SEED_BASE``; the analytic ray caster, ``renderer="raycast"``, the training
renderer) as the evaluator does (its top-scoring candidate, clipped) and reports, over every step flown:

* ``chosen``: the share of steps on which each candidate flew;
* ``top_weight``: the mean softmax weight of the flown candidate (1: one candidate always takes all);
* ``contested``: the share of steps on which the runner-up holds at least ``--contested`` of the weight, and the
  mean distance (L2 over the 4 actions in [-1, 1]) between the two candidates on those steps (large: two different
  manoeuvres both held likely, the case the head exists for; near 0: two copies of one action);
* ``switches``: how often, per episode, the flown candidate changes from one step to the next;
* the laps finished (a sanity check; the evaluator's own records are the numbers to cite).

Why: the head only helps if the teacher's labels are multi-modal where the students fail; a student whose
candidates collapse into one (``top_weight`` near 1, few contested steps) learned a plain regression.
"""

from __future__ import annotations

import argparse

import gymnasium as gym
import numpy as np
import torch

from racebench.agents import SB3Agent
from racebench.agents.recurrent import MixtureActionHead
from racebench.evaluation import EVAL_SEED_BASE
from racebench.training.dagger import student_features, student_unroll


def fly(policy, env: gym.Env, seed: int) -> tuple[bool, np.ndarray, np.ndarray]:
    """One episode: whether the lap finished, and per step the candidates ``(T, K, 4)`` and their weights ``(T, K)``."""
    obs, _ = env.reset(seed=seed)
    hidden = torch.zeros(1, 1, policy.lstm_actor.hidden_size)
    candidates, weights = [], []
    while True:
        with torch.no_grad():
            tensors = {k: torch.as_tensor(v[None]) for k, v in obs.items()}
            _, output = student_unroll(policy, student_features(policy, tensors)[None], hidden)
            hidden = output[-1:]
            means, scores = policy.action_net.components(policy.mlp_extractor.forward_actor(output[0]))
        candidates.append(means[0].numpy())
        weights.append(torch.softmax(scores[0], -1).numpy())
        action = means[0, int(scores[0].argmax())].numpy().clip(-1.0, 1.0)
        obs, _, terminated, truncated, info = env.step(action)
        if terminated or truncated:
            return bool(info["is_success"]), np.array(candidates), np.array(weights)


def main() -> None:
    """Fly the episodes and print the report."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("checkpoint")
    parser.add_argument("--env", default="RaceObs-S-v0")
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument("--contested", type=float, default=0.2, help="runner-up weight that makes a step contested")
    args = parser.parse_args()
    torch.set_num_threads(1)
    policy = SB3Agent(args.checkpoint, trust_code=True).model.policy
    if not isinstance(policy.action_net, MixtureActionHead):
        raise SystemExit(f"mixture_modes: {args.checkpoint} has no mixture head (action_components 1)")
    env = gym.make(args.env, obs_mode="vision", renderer="raycast")
    finished, switches, all_weights, gaps = 0, [], [], []
    for i in range(args.episodes):
        success, candidates, weights = fly(policy, env, EVAL_SEED_BASE + i)
        finished += success
        top = weights.argmax(1)
        switches.append(int((np.diff(top) != 0).sum()))
        order = np.argsort(-weights, axis=1)
        runner_up = weights[np.arange(len(weights)), order[:, 1]]
        contested = runner_up >= args.contested
        gap = np.linalg.norm(
            candidates[np.arange(len(top)), order[:, 0]] - candidates[np.arange(len(top)), order[:, 1]], axis=1
        )
        gaps.append(np.where(contested, gap, np.nan))
        all_weights.append(weights)
    env.close()
    weights = np.concatenate(all_weights)
    gap = np.concatenate(gaps)
    k = weights.shape[1]
    chosen = np.bincount(weights.argmax(1), minlength=k) / len(weights)
    print(f"{args.checkpoint} on {args.env}: {args.episodes} episodes (raycast), {len(weights)} steps, "
          f"{finished}/{args.episodes} laps finished")  # fmt: skip
    print("  chosen: " + ", ".join(f"candidate {i} {share:.3f}" for i, share in enumerate(chosen)))
    print(f"  top_weight: mean {weights.max(1).mean():.3f}, 10th percentile {np.percentile(weights.max(1), 10):.3f}")
    contested = ~np.isnan(gap)
    print(f"  contested (runner-up >= {args.contested}): {contested.mean():.3f} of steps; distance between the two "
          f"there: median {np.nanmedian(gap) if contested.any() else float('nan'):.3f}")  # fmt: skip
    print(f"  switches per episode: mean {np.mean(switches):.1f}, max {max(switches)}")


if __name__ == "__main__":
    main()
