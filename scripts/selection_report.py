"""How well a DAgger run's validation flights ranked its kept students: validation against evaluation.

    python scripts/selection_report.py baselines/experiments/distill-select/J/selection.csv \\
        baselines/experiments/distill-select/J/candidates

``SELECTION`` is the ``selection.csv`` a run with ``select_episodes`` wrote (one row per candidate: ``it<k>`` or
``average``, its validation successes, which one was chosen). ``CANDIDATES`` holds one evaluation folder per
candidate, named by its label (``racebench evaluate --out CANDIDATES/it019`` ...; each with ``episodes.csv``).
Prints per candidate its validation count, its evaluation count with the Wilson interval and its mean lap; then
the Spearman rank correlation of the two counts (does validation order the candidates as evaluation does?), and
the chosen candidate against the last iteration's student paired on the same evaluation scenes (an exact McNemar
test): what selection bought over keeping the last student. Validation and evaluation scenes are disjoint seeds.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import pandas as pd
from scipy.stats import spearmanr

from racebench.evaluation.statistics import paired_outcomes, wilson_interval


def candidate_table(selection: pd.DataFrame, folder: Path) -> pd.DataFrame:
    """The selection rows joined with each candidate's evaluation (exits naming a missing folder)."""
    rows = []
    for row in selection.to_dict("records"):
        path = folder / row["candidate"] / "episodes.csv"
        if not path.is_file():
            raise SystemExit(f"selection_report: {path} does not exist (evaluate candidate {row['candidate']} there)")
        episodes = pd.read_csv(path)
        wins = int(episodes["success"].sum())
        low, high = wilson_interval(wins, len(episodes))
        lap = episodes.loc[episodes["success"], "lap_time"].mean()
        rows.append({**row, "eval_successes": wins, "eval_n": len(episodes), "eval_low": low, "eval_high": high,
                     "eval_lap_mean": lap, "episodes_table": episodes})  # fmt: skip
    return pd.DataFrame(rows)


def main() -> None:
    """Print the candidates, the rank correlation and the chosen-against-last comparison."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("selection", type=Path, help="a run's selection.csv")
    parser.add_argument("candidates", type=Path, help="folder of per-candidate evaluation folders")
    args = parser.parse_args()
    if not args.selection.is_file():
        raise SystemExit(f"selection_report: {args.selection} does not exist")
    table = candidate_table(pd.read_csv(args.selection), args.candidates)
    for row in table.to_dict("records"):
        mark = "  <- chosen" if row["chosen"] else ""
        print(f"{row['candidate']:>8}: validation {row['successes']}/{row['episodes']}, evaluation "
              f"{row['eval_successes']}/{row['eval_n']} [{100 * row['eval_low']:.0f}-{100 * row['eval_high']:.0f} %], "
              f"mean lap {row['eval_lap_mean']:.2f} s{mark}")  # fmt: skip
    rho, p = spearmanr(table["successes"], table["eval_successes"])
    n = len(table)
    print(f"Spearman rank correlation, validation against evaluation over {n} candidates: {rho:.2f} (p = {p:.2f})")
    iterations = table[table["candidate"].str.startswith("it")]
    last = iterations.loc[iterations["candidate"].str[2:].astype(int).idxmax()]
    chosen = table[table["chosen"]].iloc[0]
    _, only_chosen, only_last, p = paired_outcomes(chosen["episodes_table"], last["episodes_table"])
    print(f"chosen {chosen['candidate']} against the last student {last['candidate']}: {only_chosen} laps finished "
          f"only by the chosen, {only_last} only by the last; exact McNemar p = {p:.2f}")  # fmt: skip


if __name__ == "__main__":
    main()
