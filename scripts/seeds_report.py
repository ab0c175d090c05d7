"""One config's training seeds side by side: each seed's evaluation, then their mean and spread per env id.

    python scripts/seeds_report.py baselines/experiments/distill-wide-berth/eval \\
        baselines/experiments/distill-wide-berth/seed1/eval baselines/experiments/distill-wide-berth/seed2/eval

Each folder is one seed's evaluation (``racebench evaluate --out``); its numbers are recomputed from the
validated records, as every table is. Per env id it prints each seed's success rate with its Wilson interval and
its mean lap over its successful laps, then the seeds' mean success rate, their spread (max - min) and the mean of
their lap means. The Wilson interval of one seed says how well 100 episodes pin that policy down; the spread says
how much another training seed moves it, which is usually more (a config is its seeds, not its best one).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import pandas as pd

from racebench.evaluation import read_summaries


def seed_table(folders: list[Path]) -> pd.DataFrame:
    """A row per (folder, env id): ``seed`` (the folder), ``env_id``, ``n``, ``successes``, ``success_rate``,
    ``sr_ci_low``, ``sr_ci_high``, ``lap_time_mean``; a folder holding several policies is an error."""
    rows = []
    for folder in folders:
        summary = read_summaries([folder])  # one folder at a time: seeds of one config share the agent's name
        if summary["agent"].nunique() != 1:
            raise SystemExit(f"seeds_report: {folder} holds several agents {sorted(summary['agent'].unique())}")
        rows.append(summary.assign(seed=str(folder)))
    columns = ["seed", "env_id", "n", "successes", "success_rate", "sr_ci_low", "sr_ci_high", "lap_time_mean"]
    return pd.concat(rows, ignore_index=True)[columns]


def across_seeds(table: pd.DataFrame) -> pd.DataFrame:
    """Per env id: ``seeds``, ``sr_mean``, ``sr_min``, ``sr_max``, ``sr_spread`` and ``lap_time_mean`` (the
    mean of the seeds' lap means)."""
    grouped = table.groupby("env_id", sort=False)
    return pd.DataFrame({
        "seeds": grouped["seed"].count(),
        "sr_mean": grouped["success_rate"].mean(),
        "sr_min": grouped["success_rate"].min(),
        "sr_max": grouped["success_rate"].max(),
        "sr_spread": grouped["success_rate"].max() - grouped["success_rate"].min(),
        "lap_time_mean": grouped["lap_time_mean"].mean(),
    }).reset_index()  # fmt: skip


def main() -> None:
    """Print the per-seed table and the summary across seeds (Markdown)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folders", nargs="+", type=Path, help="one evaluation folder per training seed")
    args = parser.parse_args()
    try:
        table = seed_table(args.folders)
    except (FileNotFoundError, ValueError) as exc:
        raise SystemExit(f"seeds_report: {exc}") from None
    lines = ["| seed (evaluation) | env id | SR [95 % CI] | mean lap [s] |", "| --- | --- | --- | --- |"]
    for row in table.itertuples():
        lines.append(f"| {row.seed} | {row.env_id} | {row.successes}/{row.n} = {100 * row.success_rate:.0f} % "
                     f"[{100 * row.sr_ci_low:.0f}–{100 * row.sr_ci_high:.0f}] | {row.lap_time_mean:.2f} |")  # fmt: skip
    lines += ["", "| env id | seeds | mean SR | min–max (spread) | mean lap [s] |", "| --- | --- | --- | --- | --- |"]
    for row in across_seeds(table).itertuples():
        spread = f"{100 * row.sr_min:.0f}–{100 * row.sr_max:.0f} % ({100 * row.sr_spread:.0f} points)"
        lines.append(f"| {row.env_id} | {row.seeds} | {100 * row.sr_mean:.1f} % | {spread} | {row.lap_time_mean:.2f} |")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
