"""Two agents' evaluations on the same scenes, compared pair by pair (an exact McNemar test).

    python scripts/paired_outcomes.py baselines/experiments/distill-teacher-v3/eval \\
        baselines/experiments/distill-stateless-teacher/eval

Each folder is an evaluation's output (``episodes.csv``, as ``racebench evaluate --out`` writes it). Episodes are
paired by ``(env_id, seed)``: the seed protocol gives both agents the same scenes. Prints each agent's success
rate with its Wilson interval, its mean lap over its successful laps, and what ended its failed laps.
Then it prints the discordant pairs (laps only one agent finished) and the two-sided exact binomial p-value on
them, which is McNemar's exact test. Unpaired intervals overlap long before a paired test can tell two agents
apart, which is why this exists. ``racebench compare A B`` is the package's version: from the folders' validated
records (never their CSVs), per env id and pooled.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import pandas as pd

from racebench.evaluation.statistics import paired_outcomes, wilson_interval


def load(folder: Path) -> pd.DataFrame:
    """The evaluation's episodes; exits naming the folder if it holds none."""
    path = folder / "episodes.csv"
    if not path.is_file():
        raise SystemExit(f"paired_outcomes: {path} does not exist (pass an evaluation's --out folder)")
    return pd.read_csv(path)


def main() -> None:
    """Print both agents' outcomes and the paired test."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("a", type=Path, help="first evaluation folder")
    parser.add_argument("b", type=Path, help="second evaluation folder")
    args = parser.parse_args()
    a, b = load(args.a), load(args.b)
    for name, frame in ((args.a, a), (args.b, b)):
        wins = int(frame["success"].sum())
        low, high = wilson_interval(wins, len(frame))
        causes = frame.loc[~frame["success"], "crash_reason"].fillna("timeout").str.split(":").str[0]
        print(f"{name}: {wins}/{len(frame)} ({100 * wins / len(frame):.0f} % [{100 * low:.0f}-{100 * high:.0f}]), "
              f"mean lap {frame.loc[frame['success'], 'lap_time'].mean():.2f} s; "
              f"failures {({k: int(v) for k, v in causes.value_counts().items()})}")  # fmt: skip
    n, only_a, only_b, p = paired_outcomes(a, b)
    if not n:
        raise SystemExit("paired_outcomes: the two evaluations share no (env_id, seed) episode")
    print(f"{n} paired episodes: {only_a} finished only by the first, {only_b} only by the second; "
          f"exact McNemar p = {p:.2f}")  # fmt: skip


if __name__ == "__main__":
    main()
