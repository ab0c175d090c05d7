"""Single-file PPO on a racebench id, in the style of CleanRL's ``ppo_continuous_action.py`` (Huang et al. 2022).

    python scripts/cleanrl_ppo.py --env-id RaceObs-S-Level1-v0 --total-timesteps 200000 --save agent.pt

Everything the algorithm does is in this file: the envs come from ``gym.make_vec`` (racebench's batched
``RaceVectorEnv``, ray-cast depth as uint8 images), the network is a NatureCNN on the depth image joined with
the 17-d state, actions are a diagonal Gaussian with a state-independent log std, advantages are GAE, the loss
is PPO's clipped surrogate plus value loss. No stable-baselines3. It is a starting point to read and modify,
not one of the paper's baselines (those are ``racebench train``'s configs).

Episodes end on crash, success or the env's time limit; a truncated episode is treated as ended (as in
CleanRL), i.e. its value is not bootstrapped.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from gymnasium.vector import AutoresetMode
from torch import nn
from torch.distributions.normal import Normal

import racebench  # noqa: F401  (registers the ids)
from racebench.sim.quadrotor import QuadrotorParams


def opt(default: Any, help_text: str) -> Any:
    """A dataclass field with its command-line help."""
    return dataclasses.field(default=default, metadata={"help": help_text})


@dataclass
class Args:
    """Hyperparameters; each field is a command-line option (``--total-timesteps``, ...)."""

    env_id: str = opt("RaceObs-S-Level1-v0", "any racebench id; Level1 has no obstacles and v_d = 3 m/s")
    total_timesteps: int = opt(200_000, "env steps over all envs")
    num_envs: int = opt(16, "envs stepped together")
    num_steps: int = opt(64, "steps per env per rollout")
    num_processes: int = opt(1, "processes stepping the envs (RaceVectorEnv)")
    renderer: str = opt("raycast", "depth renderer: raycast (fast) or pybullet (the evaluation's)")
    learning_rate: float = opt(3e-4, "Adam step size")
    anneal_lr: bool = opt(True, "decay the learning rate linearly to 0")
    gamma: float = opt(0.99, "discount")
    gae_lambda: float = opt(0.95, "GAE lambda")
    num_minibatches: int = opt(4, "minibatches per epoch")
    update_epochs: int = opt(4, "passes over each rollout")
    clip_coef: float = opt(0.2, "PPO's ratio clip")
    ent_coef: float = opt(0.0, "entropy bonus")
    vf_coef: float = opt(0.5, "value-loss weight")
    max_grad_norm: float = opt(0.5, "gradient clip")
    seed: int = opt(0, "seeds torch, numpy and the envs (env i gets seed + i; keep it below 1,000,000)")
    torch_threads: int = opt(1, "torch threads (one is fastest on a small shared CPU)")
    save: str = opt("", "write the final network's state_dict here (a .pt file); empty: do not save")


def layer_init(layer: nn.Module, std: float = float(np.sqrt(2)), bias: float = 0.0) -> nn.Module:
    """Orthogonal weights and constant bias, as CleanRL initialises every layer."""
    nn.init.orthogonal_(layer.weight, std)
    nn.init.constant_(layer.bias, bias)
    return layer


class Agent(nn.Module):
    """NatureCNN on the uint8 depth image (H, W, 1) + the state, one 256 layer, then actor mean and critic."""

    def __init__(self, envs: gym.vector.VectorEnv) -> None:
        super().__init__()
        height, width, channels = envs.single_observation_space["depth"].shape
        state_dim = envs.single_observation_space["state"].shape[0]
        actions = int(np.prod(envs.single_action_space.shape))
        self.cnn = nn.Sequential(
            layer_init(nn.Conv2d(channels, 32, 8, stride=4)), nn.ReLU(),
            layer_init(nn.Conv2d(32, 64, 4, stride=2)), nn.ReLU(),
            layer_init(nn.Conv2d(64, 64, 3, stride=1)), nn.ReLU(),
            nn.Flatten(),
        )  # fmt: skip
        with torch.no_grad():
            flat = self.cnn(torch.zeros(1, channels, height, width)).shape[1]
        self.trunk = nn.Sequential(layer_init(nn.Linear(flat + state_dim, 256)), nn.ReLU())
        self.actor_mean = layer_init(nn.Linear(256, actions), std=0.01)
        # Start at hover thrust: a zero mean command (half of max thrust) climbs away from every gate.
        with torch.no_grad():
            self.actor_mean.bias[0] = QuadrotorParams().hover_action
        # exp(-1) = 0.37: a std of 1 on body-rate commands tumbles the drone within a second.
        self.actor_logstd = nn.Parameter(torch.full((1, actions), -1.0))
        self.critic = layer_init(nn.Linear(256, 1), std=1.0)

    def features(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        """Joint features of a batch of observations (depth uint8 (B, H, W, 1), state float (B, 17))."""
        depth = obs["depth"].permute(0, 3, 1, 2).float() / 255.0
        return self.trunk(torch.cat([self.cnn(depth), obs["state"]], dim=1))

    def get_value(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        """V(obs), shape (B, 1)."""
        return self.critic(self.features(obs))

    def get_action_and_value(
        self, obs: dict[str, torch.Tensor], action: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """A sampled (or the given) action, its log-probability, the policy's entropy and V(obs)."""
        hidden = self.features(obs)
        mean = self.actor_mean(hidden)
        dist = Normal(mean, self.actor_logstd.expand_as(mean).exp())
        if action is None:
            action = dist.sample()
        return action, dist.log_prob(action).sum(1), dist.entropy().sum(1), self.critic(hidden)


def to_torch(obs: dict[str, np.ndarray]) -> dict[str, torch.Tensor]:
    """A vector env's observation dict as tensors (depth stays uint8 until the network scales it)."""
    return {"depth": torch.from_numpy(obs["depth"]), "state": torch.from_numpy(obs["state"])}


def train(args: Args) -> dict[str, Any]:
    """Run PPO for ``args.total_timesteps``; return the last losses and the episode statistics."""
    batch_size = args.num_envs * args.num_steps
    minibatch_size = batch_size // args.num_minibatches
    iterations = args.total_timesteps // batch_size
    if iterations < 1 or minibatch_size < 1:
        raise ValueError(f"total_timesteps ({args.total_timesteps}) must be >= num_envs * num_steps ({batch_size})")
    torch.set_num_threads(args.torch_threads)
    torch.manual_seed(args.seed)
    np.random.seed(args.seed)

    # SAME_STEP autoreset: the observation after an episode's last step is the next episode's first, as in the
    # CleanRL scripts written for Gym; NEXT_STEP would add a dummy step per episode to mask out of the loss.
    envs = gym.make_vec(
        args.env_id, num_envs=args.num_envs, depth_format="uint8", renderer=args.renderer,
        num_processes=args.num_processes, autoreset_mode=AutoresetMode.SAME_STEP,
    )  # fmt: skip
    agent = Agent(envs)
    optimizer = torch.optim.Adam(agent.parameters(), lr=args.learning_rate, eps=1e-5)

    space = envs.single_observation_space
    obs_depth = torch.zeros((args.num_steps, args.num_envs, *space["depth"].shape), dtype=torch.uint8)
    obs_state = torch.zeros((args.num_steps, args.num_envs, *space["state"].shape))
    actions = torch.zeros((args.num_steps, args.num_envs, *envs.single_action_space.shape))
    logprobs, rewards, dones, values = (torch.zeros((args.num_steps, args.num_envs)) for _ in range(4))

    global_step, started = 0, time.perf_counter()
    next_obs_np, _ = envs.reset(seed=args.seed)
    next_obs, next_done = to_torch(next_obs_np), torch.zeros(args.num_envs)
    episode_return = np.zeros(args.num_envs)
    returns: list[float] = []
    successes: list[bool] = []
    stats: dict[str, Any] = {}
    for iteration in range(1, iterations + 1):
        if args.anneal_lr:
            optimizer.param_groups[0]["lr"] = (1.0 - (iteration - 1.0) / iterations) * args.learning_rate
        for step in range(args.num_steps):
            global_step += args.num_envs
            obs_depth[step], obs_state[step], dones[step] = next_obs["depth"], next_obs["state"], next_done
            with torch.no_grad():
                action, logprob, _, value = agent.get_action_and_value(next_obs)
            values[step], actions[step], logprobs[step] = value.flatten(), action, logprob
            next_obs_np, reward, terminated, truncated, infos = envs.step(action.numpy())
            done = np.logical_or(terminated, truncated)
            rewards[step] = torch.as_tensor(reward, dtype=torch.float32)
            next_obs, next_done = to_torch(next_obs_np), torch.as_tensor(done, dtype=torch.float32)
            episode_return += reward
            for i in np.flatnonzero(done):  # the ended episode's last info is in final_info (SAME_STEP)
                returns.append(float(episode_return[i]))
                successes.append(bool(infos["final_info"]["is_success"][i]))
                episode_return[i] = 0.0

        with torch.no_grad():  # GAE
            next_value = agent.get_value(next_obs).reshape(1, -1)
            advantages = torch.zeros_like(rewards)
            last = torch.zeros(args.num_envs)
            for t in reversed(range(args.num_steps)):
                nonterminal = 1.0 - (next_done if t == args.num_steps - 1 else dones[t + 1])
                following = next_value if t == args.num_steps - 1 else values[t + 1]
                delta = rewards[t] + args.gamma * following * nonterminal - values[t]
                advantages[t] = last = delta + args.gamma * args.gae_lambda * nonterminal * last
            targets = advantages + values

        b_obs = {
            "depth": obs_depth.reshape(batch_size, *space["depth"].shape),
            "state": obs_state.reshape(batch_size, -1),
        }
        b_actions = actions.reshape(batch_size, -1)
        b_logprobs, b_advantages = logprobs.reshape(-1), advantages.reshape(-1)
        b_targets, b_values = targets.reshape(-1), values.reshape(-1)
        clipfracs = []
        for _ in range(args.update_epochs):
            order = np.random.permutation(batch_size)
            for start in range(0, batch_size, minibatch_size):
                mb = order[start : start + minibatch_size]
                _, newlogprob, entropy, newvalue = agent.get_action_and_value(
                    {k: v[mb] for k, v in b_obs.items()}, b_actions[mb]
                )
                logratio = newlogprob - b_logprobs[mb]
                ratio = logratio.exp()
                with torch.no_grad():
                    approx_kl = ((ratio - 1) - logratio).mean()
                    clipfracs.append(((ratio - 1.0).abs() > args.clip_coef).float().mean().item())
                mb_adv = b_advantages[mb]
                mb_adv = (mb_adv - mb_adv.mean()) / (mb_adv.std() + 1e-8)
                pg_loss = torch.max(
                    -mb_adv * ratio, -mb_adv * torch.clamp(ratio, 1 - args.clip_coef, 1 + args.clip_coef)
                ).mean()
                v_loss = 0.5 * ((newvalue.view(-1) - b_targets[mb]) ** 2).mean()
                loss = pg_loss - args.ent_coef * entropy.mean() + args.vf_coef * v_loss
                optimizer.zero_grad()
                loss.backward()
                nn.utils.clip_grad_norm_(agent.parameters(), args.max_grad_norm)
                optimizer.step()

        recent = returns[-50:]
        stats = {
            "global_step": global_step,
            "episodes": len(returns),
            "mean_return": float(np.mean(recent)) if recent else None,
            "success_rate": float(np.mean(successes[-50:])) if recent else None,
            "policy_loss": pg_loss.item(),
            "value_loss": v_loss.item(),
            "approx_kl": approx_kl.item(),
            "clipfrac": float(np.mean(clipfracs)),
            "explained_variance": float(1 - torch.var(b_targets - b_values) / torch.var(b_targets)),
            "samples_per_s": round(global_step / (time.perf_counter() - started), 1),
        }
        print(" ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in stats.items()), flush=True)
    envs.close()
    if args.save:
        torch.save(agent.state_dict(), args.save)
    return stats


def parse_args(argv: Sequence[str] | None = None) -> Args:
    """:class:`Args` from the command line: one ``--option`` per field, ``--no-anneal-lr`` for booleans."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    defaults = Args()
    for field in dataclasses.fields(Args):
        option, default = "--" + field.name.replace("_", "-"), getattr(defaults, field.name)
        help_text = f"{field.metadata['help']} (default: {default!r})"
        if isinstance(default, bool):
            parser.add_argument(option, action=argparse.BooleanOptionalAction, default=default, help=help_text)
        else:
            parser.add_argument(option, type=type(default), default=default, help=help_text)
    return Args(**vars(parser.parse_args(argv)))


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Parse the options and train."""
    return train(parse_args(argv))


if __name__ == "__main__":
    main()
