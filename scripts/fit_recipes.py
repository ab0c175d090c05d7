"""Which DAgger fit recipe learns a real aggregate best: held-out loss per pass and per second, recipe by recipe.

    python scripts/fit_recipes.py --aggregate runs/distill-lr-decay-S-seed0/resume/dataset.npz \
        [--samples 100000] [--passes 4] [--threads 2] --recipe float32:256:3e-4 --recipe bfloat16:1024:6e-4 ...

A recipe is ``precision:batch_size:learning_rate`` (precision ``float32``, or ``bfloat16``: the whole fit under bf16
autocast, weights and optimizer float32). The last ``--samples`` steps of a saved aggregate (a DAgger run's
``resume/dataset.npz``: the latest, student-flown iterations) are split by whole segments into 90 % to fit and 10 % held
out. Each recipe fits a fresh student of the config (same initial weights for all) with Adam for ``--passes`` passes
of :func:`racebench.training.dagger.fit`, and after each pass prints the held-out loss (the mean squared error of the
student's actions against the teacher's, every chunk unrolled from its GRU state, float32) and the seconds spent.
Why: a fit that is faster per sample is only worth it if its loss falls as far per second; a diverging recipe shows
here in minutes instead of an hour of DAgger.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from racebench.training.dagger import (
    DaggerConfig,
    Dataset,
    chunk_start_states,
    fit,
    make_student,
    make_training_envs,
    sequence_loss,
)


def load_tail(path: str, samples: int) -> tuple[Dataset, Dataset]:
    """The last ``samples`` steps of a saved aggregate, split by whole segments into (fit 90 %, held out 10 %)."""
    with np.load(path) as data:
        n = len(data["state"])
        # the ring buffer's order: oldest at data["next"] once it has wrapped
        order = np.roll(np.arange(n), -int(data["next"])) if data["starts"][int(data["next"]) % n] else np.arange(n)
        keep = order[-samples:]
        arrays = {k: data[k][keep] for k in ("state", "depth", "action", "weight", "starts")}
    arrays["starts"][0] = True
    bounds = np.append(np.flatnonzero(arrays["starts"]), len(keep))
    cut = bounds[np.searchsorted(bounds, int(0.9 * len(keep)))]
    parts = []
    for a, b in ((0, cut), (cut, len(keep))):
        part = Dataset(capacity=b - a, depth_size=arrays["depth"].shape[-1])
        part.state[:], part.depth[:], part.action[:] = arrays["state"][a:b], arrays["depth"][a:b], arrays["action"][a:b]
        part.weight[:], part.starts[:] = arrays["weight"][a:b], arrays["starts"][a:b]
        part.starts[0] = True
        part.size, part.next = b - a, 0
        parts.append(part)
    return parts[0], parts[1]


def held_out_loss(policy: object, data: Dataset, length: int) -> float:
    """Float32 mean squared error over every held-out step, each chunk from its GRU state under ``policy``."""
    first, count, position = data.chunks(length)
    states = chunk_start_states(policy, data, (first, count, position))
    total, steps = 0.0, 0
    with torch.no_grad():
        for a in range(0, len(first), 256):
            pick = slice(a, a + 256)
            n = int(count[pick].sum())
            total += float(sequence_loss(policy, data, first[pick], count[pick], states[pick], length)) * n
            steps += n
    return total / steps


def main() -> None:
    """Fit each recipe and print its held-out loss after every pass."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default="baselines/vision-distill.yaml")
    parser.add_argument("--aggregate", required=True, help="a DAgger run's resume/dataset.npz")
    parser.add_argument("--samples", type=int, default=100_000)
    parser.add_argument("--passes", type=int, default=4)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--recipe", action="append", required=True, help="precision:batch_size:learning_rate")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    config = DaggerConfig.from_yaml(args.config)
    train, held = load_tail(args.aggregate, args.samples)
    print(f"{train.size:,} steps to fit, {held.size:,} held out")
    made = make_training_envs(config)
    for recipe in args.recipe:
        precision, batch, rate = recipe.split(":")
        run = DaggerConfig.from_yaml(args.config)
        if precision not in ("float32", "bfloat16"):
            raise SystemExit(f"fit_recipes: recipe {recipe!r}: precision must be float32 or bfloat16")
        run.batch_size, run.learning_rate, run.epochs = int(batch), float(rate), 1
        run.validate(recipe)
        torch.manual_seed(0)
        policy = make_student(made[0], config.seed, config.student).policy
        optimizer = torch.optim.Adam(policy.parameters(), lr=run.learning_rate)
        rng = np.random.default_rng(0)
        spent = 0.0
        for k in range(args.passes):
            started = time.perf_counter()
            with torch.autocast("cpu", dtype=torch.bfloat16, enabled=precision == "bfloat16"):
                train_loss = fit(policy, train, run, optimizer, rng)
            spent += time.perf_counter() - started
            loss = held_out_loss(policy, held, run.sequence_length)
            print(f"{recipe}  pass {k + 1}: fit loss {train_loss:.4f}, held-out {loss:.4f}, {spent:.0f} s fitting")
    for m in made:
        m.close()


if __name__ == "__main__":
    main()
