"""Where DAgger's collection time goes: ``cProfile`` of :func:`racebench.training.dagger.collect`.

    python scripts/profile_dagger_collect.py [--config baselines/experiments/distill-wide-berth/config.yaml]
        [--steps 4000] [--beta 0.0]

Builds the config's training envs, teachers and an untrained student (one torch thread, as in collection), flies
a short warm-up (compilation), then profiles ``--steps`` steps with the student flying (``--beta 0``: the expert
only labels) and prints steps/s and the top functions by cumulative time. An untrained student crashes within
~60 steps, so episode starts, and with them the teacher's planning, are more frequent than in a trained run.
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import time

import numpy as np
import torch

from racebench.training.dagger import DaggerConfig, Dataset, collect, make_student, make_teacher, make_training_envs


def main() -> None:
    """Profile one collection and print where its time went."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default="baselines/experiments/distill-wide-berth/config.yaml")
    parser.add_argument("--steps", type=int, default=4000)
    parser.add_argument("--beta", type=float, default=0.0, help="probability that the teacher acts")
    parser.add_argument("--top", type=int, default=20)
    args = parser.parse_args()
    config = DaggerConfig.from_yaml(args.config)
    made = make_training_envs(config)
    envs = [m.unwrapped for m in made]
    teachers = [make_teacher(config) for _ in envs]
    torch.set_num_threads(1)
    policy = make_student(made[0], config.seed, config.student).policy
    dataset = Dataset(2 * args.steps + 2000, envs[0].camera.size)
    rng, seeds = np.random.default_rng(config.seed), [config.seed * 1000]
    collect(envs, teachers, policy, args.beta, 800, rng, seeds, dataset)  # warm-up: numba kernels compile
    profiler = cProfile.Profile()
    started = time.perf_counter()
    profiler.enable()
    collect(envs, teachers, policy, args.beta, args.steps, rng, seeds, dataset)
    profiler.disable()
    print(f"{args.steps / (time.perf_counter() - started):.0f} steps/s collected")
    pstats.Stats(profiler).sort_stats("cumulative").print_stats(args.top)
    for m in made:
        m.close()


if __name__ == "__main__":
    main()
