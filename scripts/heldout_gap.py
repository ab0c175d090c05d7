"""Does a DAgger student generalise, or memorise? Its loss on data it was fitted on against data it never saw.

    python scripts/heldout_gap.py --aggregate runs/distill-batch-1024-S-seed0/resume/dataset.npz \\
        --student runs/distill-batch-1024-S-seed0/iterations/vision-distill-batch-1024-S-it019.zip \\
        --seen 400000 500160 --unseen 500160 600000

A run extended past its first length (``racebench train --resume RUN --steps N``) leaves in its aggregate steps that
an earlier iteration's student (``RUN/iterations/*-itNNN.zip``) was never fitted on: the later iterations' scenes,
flown by later students. ``--seen A B`` and ``--unseen A B`` are step ranges of the aggregate, oldest step first
(``progress.csv``'s ``samples`` column gives each iteration's end). Prints the student's mean squared error to the
teacher's labels on each (every chunk unrolled from its GRU state, as the fit does), per action channel too. A large
gap says the student fits the scenes it has seen better than new ones: a generalisation limit, for which more
labelled scenes or regularisation (weight averaging, augmentation) are the levers, not a longer fit.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from racebench.agents import load_agent
from racebench.training.dagger import Dataset, chunk_start_states, student_features, student_unroll


def load_range(path: str, begin: int, end: int) -> Dataset:
    """Steps ``begin`` to ``end`` (oldest first) of a saved aggregate as a :class:`Dataset`."""
    with np.load(path) as data:
        n = len(data["state"])
        wrapped = bool(data["starts"][int(data["next"]) % n]) and int(data["next"]) > 0
        order = np.roll(np.arange(n), -int(data["next"])) if wrapped else np.arange(n)
        keep = np.sort(order[begin:end]) if not wrapped else order[begin:end]
        part = Dataset(capacity=len(keep), depth_size=data["depth"].shape[-1])
        for name in ("state", "depth", "action", "weight", "starts"):
            getattr(part, name)[:] = data[name][keep]
    part.starts[0] = True
    part.size, part.next = len(keep), 0
    return part


def channel_errors(policy: object, data: Dataset, length: int) -> np.ndarray:
    """Mean squared error per action channel over every step, each chunk from its GRU state under ``policy``
    (the fit's :func:`~racebench.training.dagger.sequence_loss`, per channel)."""
    first, count, position = data.chunks(length)
    states = chunk_start_states(policy, data, (first, count, position))
    offsets = np.arange(length)
    total, steps = torch.zeros(4), 0
    with torch.no_grad():
        for a in range(0, len(first), 256):
            f, c = first[a : a + 256], count[a : a + 256]
            index = np.minimum(f[:, None] + offsets, f[:, None] + c[:, None] - 1)
            batch = data.batch(index.T.reshape(-1))  # time-major, as the fit
            target = batch.pop("action").view(length, len(f), -1)
            batch.pop("weight")
            features = student_features(policy, batch).view(length, len(f), -1)
            actions, _ = student_unroll(policy, features, states[a : a + 256][None])
            mask = torch.from_numpy(offsets[:, None] < c[None, :]).unsqueeze(-1)
            total += ((actions - target) ** 2 * mask).sum(dim=(0, 1))
            steps += int(c.sum())
    return (total / steps).numpy()


def main() -> None:
    """Print the student's loss on the seen and the unseen ranges."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--aggregate", required=True, help="a DAgger run's resume/dataset.npz")
    parser.add_argument("--student", required=True, nargs="+", help="student checkpoints (.zip)")
    parser.add_argument("--seen", type=int, nargs=2, required=True, metavar=("A", "B"))
    parser.add_argument("--unseen", type=int, nargs=2, required=True, metavar=("A", "B"))
    parser.add_argument("--sequence-length", type=int, default=32)
    args = parser.parse_args()
    torch.set_num_threads(2)
    parts = {name: load_range(args.aggregate, *span) for name, span in (("seen", args.seen), ("unseen", args.unseen))}
    for path in args.student:
        policy = load_agent(path, trust_code=True).model.policy
        policy.set_training_mode(False)
        for name, data in parts.items():
            errors = channel_errors(policy, data, args.sequence_length)
            print(f"{path} {name} ({data.size:,} steps): loss {errors.mean():.4f}; per channel (thrust, roll, "
                  f"pitch, yaw rate) {' '.join(f'{e:.4f}' for e in errors)}", flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
