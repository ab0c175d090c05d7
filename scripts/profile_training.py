"""Where one training iteration of a baseline spends its time: collection vs PPO update, and the update's top calls.

    python scripts/profile_training.py --config vision-ppo [--track S] [--top 12]

Builds the config's training envs and model exactly as ``racebench train`` does, runs one warm-up iteration,
times one full iteration (rollout + update), then profiles one more update alone with ``cProfile``.
Run it on an otherwise idle machine: other processes on the cores change every figure.
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import time

import torch

from racebench.training.train import ThreadsCallback, TrainConfig, make_envs, make_model


def main() -> None:
    """Print the iteration time, the update time and the update's most expensive calls."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default="vision-ppo", help="built-in baseline name or YAML path")
    parser.add_argument("--track", default="S", choices=["S", "J", "Circle"])
    parser.add_argument("--top", type=int, default=12, help="profiled calls to list")
    args = parser.parse_args()

    config = TrainConfig.from_yaml(args.config)
    torch.set_num_threads(config.torch_threads)
    env = make_envs(config, args.track, seed=0)
    model = make_model(config, env, seed=0, tensorboard=None)
    samples = config.n_envs * config.n_steps
    threads = ThreadsCallback(config.torch_threads, config.update_threads)
    model.learn(samples, callback=threads)  # warm-up: first resets, allocations
    started = time.perf_counter()
    model.learn(samples, callback=threads, reset_num_timesteps=False)
    iteration = time.perf_counter() - started

    torch.set_num_threads(config.update_threads)
    profiler = cProfile.Profile()
    started = time.perf_counter()
    profiler.enable()
    model.train()
    profiler.disable()
    update = time.perf_counter() - started
    env.close()

    print(f"{config.name}: {samples} samples per iteration")
    print(f"  iteration (rollout + update)  {iteration:.2f} s  ({samples / iteration:,.0f} samples/s)")
    print(f"  update alone (profiled)       {update:.2f} s; rollout ≈ {max(iteration - update, 0):.2f} s")
    pstats.Stats(profiler).sort_stats("tottime").print_stats(args.top)


if __name__ == "__main__":
    main()
