"""The A/B table of a training sweep: per run, steps and wall clock to each curriculum promotion, the training
success of the last update at the highest level reached, evaluation success with its Wilson interval, and the
decision rule of ``ab-fast-update.yaml``.

    python scripts/ab_report.py runs/sweeps/ab-fast-update [--baseline vision-ppo --variant vision-ppo-fast]
        [--out baselines/experiments/ab-fast-update.md]

Reads only the run folders ``racebench sweep`` writes (``curriculum.json``, ``progress.csv``, ``summary.json``
and ``eval/``), so it also reports runs still in progress (marked, and never counted in the decision).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pandas as pd

from racebench.evaluation.statistics import wilson_interval


def run_row(folder: Path) -> dict:
    """One run folder → its row: steps and wall clock to each promotion, training and evaluation success."""
    row: dict = {"run": folder.name}
    state_path, progress_path, summary_path = (folder / n for n in ("curriculum.json", "progress.csv", "summary.json"))
    state = json.loads(state_path.read_text()) if state_path.exists() else {"promotions": [], "solved": None}
    progress = pd.read_csv(progress_path) if progress_path.exists() and progress_path.stat().st_size else None
    summary = json.loads(summary_path.read_text()) if summary_path.exists() else {}
    row["steps"] = int(progress["timesteps"].iloc[-1]) if progress is not None else 0
    row["samples_per_s"] = float(progress["samples_per_s"].iloc[-10:].median()) if progress is not None else np.nan
    for promotion in state.get("promotions", []):
        level = promotion["level"]
        row[f"steps_to_L{level}"] = promotion["timestep"]
        row[f"wall_min_to_L{level}"] = round(promotion.get("wall_s", np.nan) / 60, 1)
        row[f"L{level}_by"] = promotion.get("by", "bar")
    solved = state.get("solved")
    row["steps_to_solved"] = solved["timestep"] if solved else np.nan
    if progress is not None:
        last = progress[progress["level"] == progress["level"].max()]
        row["last_level"] = int(last["level"].iloc[-1])
        row["last_train_success"] = float(last["success_rate"].iloc[-1]) if len(last) else np.nan
    evaluation = summary.get("eval")
    row["finished"] = evaluation is not None
    if evaluation:
        n, k = int(evaluation["n"]), int(evaluation["successes"])
        low, high = wilson_interval(k, n)
        row.update(eval_n=n, eval_successes=k, eval_sr=k / n, eval_ci=f"[{100 * low:.0f}–{100 * high:.0f}]",
                   eval_lap_s=evaluation.get("lap_time_mean"))  # fmt: skip
    return row


def decide(table: pd.DataFrame, baseline: str, variant: str) -> str:
    """The sweep file's rule, on finished runs only."""
    done = table[table["finished"]]
    arms = {name: done[done["run"].str.startswith(f"{name}-S-seed")] for name in (baseline, variant)}
    if any(len(arm) < 3 for arm in arms.values()):
        counts = {name: len(arm) for name, arm in arms.items()}
        return f"no decision yet: finished runs per arm {counts}, the rule needs 3 each"
    sr = {name: arm["eval_sr"] for name, arm in arms.items()}
    spread = max(float(s.max() - s.min()) for s in sr.values())
    to_l3 = {name: float(arm.get("steps_to_L3", pd.Series(dtype=float)).mean()) for name, arm in arms.items()}
    keeps_sr = sr[variant].mean() >= sr[baseline].mean() - spread
    not_slower = to_l3[variant] <= to_l3[baseline]
    verdict = "becomes the default" if keeps_sr and not_slower else "stays a named variant"
    return (
        f"mean eval SR {baseline} {sr[baseline].mean():.1%}, {variant} {sr[variant].mean():.1%} (largest seed "
        f"spread {spread:.1%}: {'within' if keeps_sr else 'outside'}); mean steps to level 3 {to_l3[baseline]:,.0f} "
        f"vs {to_l3[variant]:,.0f} ({'not higher' if not_slower else 'higher'}) → {variant} {verdict}"
    )


def main() -> None:
    """Print (and optionally write) the A/B table and the decision."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sweep_out", type=Path, help="the sweep's out folder (its run folders inside)")
    parser.add_argument("--baseline", default="vision-ppo")
    parser.add_argument("--variant", default="vision-ppo-fast")
    parser.add_argument("--out", type=Path, help="also write the table and the decision as Markdown here")
    args = parser.parse_args()
    folders = sorted(p for p in args.sweep_out.iterdir() if p.is_dir())
    if not folders:
        raise SystemExit(f"ab_report: no run folders under {args.sweep_out}")
    table = pd.DataFrame([run_row(f) for f in folders])
    decision = decide(table, args.baseline, args.variant)
    text = table.to_markdown(index=False, floatfmt=".3g") + f"\n\nDecision: {decision}\n"
    print(text)
    if args.out:
        args.out.write_text(f"# A/B: {args.variant} against {args.baseline}\n\n" + text)


if __name__ == "__main__":
    main()
