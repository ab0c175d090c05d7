"""What one DAgger fit costs: samples/s of :func:`racebench.training.dagger.fit` at several batch sizes, optionally
under bf16 autocast.

    python scripts/profile_dagger_fit.py [--config baselines/vision-distill.yaml] [--samples 60000]
        [--batch 256 1024] [--threads 2] [--bf16] [--epochs 1] [--frozen-features]

Fills an aggregate with ``--samples`` random steps (segments of 50-250 steps, uniform depth and state: the cost of a
fit does not depend on the values) and times one pass of the config's student over it per batch size. A throughput
probe only: the loss on random labels means nothing. What a recipe learns per second on real data is
``scripts/fit_recipes.py``'s to say (removed; in commit 21690504): there bf16 diverges, and batch 1,024 is 1.25x
cheaper, not the 1.5x measured here (``baselines/experiments/fit_recipes.txt``). ``--frozen-features`` times the
fit of ``freeze_features_after`` (the feature layers fixed: one pass without gradient for the aggregate's features,
then the GRU and heads); samples/s counts ``--epochs`` passes.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from racebench.training.dagger import DaggerConfig, Dataset, fit, make_student, make_training_envs


def main() -> None:
    """Time one fitting pass per batch size and print samples/s."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default="baselines/vision-distill.yaml")
    parser.add_argument("--samples", type=int, default=60_000)
    parser.add_argument("--batch", type=int, nargs="+", default=[256, 1024])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--bf16", action="store_true", help="fit under torch.autocast('cpu', dtype=torch.bfloat16)")
    parser.add_argument("--epochs", type=int, default=1, help="passes per fit (the shipped config: 2)")
    parser.add_argument("--frozen-features", action="store_true", help="the fit of freeze_features_after")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    config = DaggerConfig.from_yaml(args.config)
    config.n_envs, config.epochs = 1, args.epochs
    made = make_training_envs(config)
    policy = make_student(made[0], config.seed, config.student).policy
    size = made[0].unwrapped.camera.size
    dataset = Dataset(args.samples, size)
    rng = np.random.default_rng(0)
    stored = 0
    while stored < args.samples:
        n = min(int(rng.integers(50, 250)), args.samples - stored)
        dataset.add_segment(rng.random((n, 17), dtype=np.float32), rng.random((n, 1, size, size), dtype=np.float32),
                            rng.random((n, 4), dtype=np.float32))  # fmt: skip
        stored += n
    optimizer = torch.optim.Adam(policy.parameters(), lr=config.learning_rate)
    for batch in args.batch:
        config.batch_size = batch
        started = time.perf_counter()
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=args.bf16):
            fit(policy, dataset, config, optimizer, rng, frozen_features=args.frozen_features)
        seconds = time.perf_counter() - started
        label = ("bf16" if args.bf16 else "fp32") + (", frozen features" if args.frozen_features else "")
        rate = args.samples * args.epochs / seconds
        print(f"batch {batch} ({label}, {args.threads} threads): {rate:,.0f} samples/s ({seconds:.1f} s)")
    for m in made:
        m.close()


if __name__ == "__main__":
    main()
