"""One table cell of a campaign report: a method on one env id, over its training seeds."""

from __future__ import annotations

import math
from dataclasses import dataclass

import pandas as pd

from racebench.evaluation.statistics import wilson_interval


@dataclass(frozen=True)
class Cell:
    """One table cell: a method on one env id, over its training seeds."""

    n: int  # episodes per training seed (the smallest)
    seeds: int
    success_rate: float  # the seeds' mean
    low: float  # one seed: the 95 % Wilson interval; several: the lowest and highest seed
    high: float
    lap_time: float  # the mean of the seeds' mean lap times (nan without a lap)

    def text(self, paper: float | None = None, lap: bool = False) -> str:
        """``72 [63–80]`` (one seed), ``75 (3 seeds 70–80)`` (several), with `` · paper X`` when given."""
        if lap:
            body = "–" if not math.isfinite(self.lap_time) else f"{self.lap_time:.2f}"
        elif self.seeds == 1:
            body = f"{100 * self.success_rate:.0f} [{100 * self.low:.0f}–{100 * self.high:.0f}]"
        else:
            body = f"{100 * self.success_rate:.0f} ({self.seeds} seeds {100 * self.low:.0f}–{100 * self.high:.0f})"
        return body if paper is None else f"{body} · paper {paper:g}"


def cell(episodes: pd.DataFrame, method: str, env_id: str) -> Cell | None:
    """The cell of ``method`` on ``env_id`` (``None`` without episodes)."""
    rows = episodes[(episodes["method"] == method) & (episodes["env_id"] == env_id)]
    if rows.empty:
        return None
    per_seed = rows.groupby("training_seed").agg(
        n=("success", "size"), successes=("success", "sum"), lap_time=("lap_time", "mean")
    )
    rates = per_seed["successes"] / per_seed["n"]
    if len(per_seed) == 1:
        low, high = wilson_interval(int(per_seed["successes"].iloc[0]), int(per_seed["n"].iloc[0]))
    else:
        low, high = float(rates.min()), float(rates.max())
    laps = per_seed["lap_time"].dropna()
    return Cell(
        n=int(per_seed["n"].min()),
        seeds=len(per_seed),
        success_rate=float(rates.mean()),
        low=low,
        high=high,
        lap_time=float(laps.mean()) if len(laps) else float("nan"),
    )
