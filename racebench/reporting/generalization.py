"""The generalisation table (issue 73): success and lap time on the held-out tracks, from result folders.

One row per policy flown on ``RaceObs-Unseen-v0`` (its label, or label and policy hash where a label names several):
its success rate with the 95 % Wilson interval and mean lap time on the held-out tracks, then on each of the paper's
main ids where the same policy was flown there (for a policy trained on generated tracks, ``RaceObs-Random-v0``,
those are zero-shot too). Rows are sorted by success on the held-out tracks; a cell is bold where its interval lies
above every other non-privileged row's.

Every pair of rows is then compared on the held-out episodes they share (the seed protocol gives both the same
track and obstacles for a seed): the laps only one of them finished, McNemar's exact p and Holm's adjustment over
all pairs, and the mean lap-time difference on the episodes both finished (the held-out tracks differ in length, so
two rows' mean laps compare only where both flew the same tracks).

``racebench table RESULTS... --table unseen`` prints both tables (Markdown or LaTeX).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from itertools import combinations
from pathlib import Path

import pandas as pd

from racebench.evaluation.protocol import SUITES
from racebench.evaluation.results import check_one_env_version, load_result_dir, summarize
from racebench.evaluation.statistics import holm_adjust, paired_outcomes
from racebench.reporting.tables import _interval, _lt_text, _sr_text, best_separated, render

UNSEEN_ID = "RaceObs-Unseen-v0"
#: The columns after the held-out tracks: the paper's main ids, in its order.
PAPER_IDS: tuple[str, ...] = tuple(SUITES["main"])
COLUMN_NAMES: dict[str, str] = {
    UNSEEN_ID: "held-out tracks",
    "RaceObs-S-v0": "S-shaped",
    "RaceObs-Circle-v0": "3D Circle",
    "RaceObs-J-v0": "J-shaped",
}


def _episodes(paths: Iterable[str | Path]) -> pd.DataFrame:
    """Every validated episode of the result folders (one env version), labelled per policy."""
    loaded = [load_result_dir(path) for path in paths]
    if not loaded:
        raise ValueError("no result directories given")
    check_one_env_version({str(path): frame["env_version"] for path, frame in loaded})
    episodes = pd.concat([frame for _, frame in loaded], ignore_index=True)
    episodes = episodes.drop_duplicates(["policy_sha256", "env_id", "seed", "seed_set", "renderer"])
    episodes = episodes.assign(
        success=episodes["success"].astype(bool), policy_sha256=episodes["policy_sha256"].astype(str)
    )
    several = episodes.groupby("agent")["policy_sha256"].nunique()
    shared = set(several[several > 1].index)
    labels = [
        f"{a} ({h[:8]})" if a in shared else str(a)
        for a, h in zip(episodes["agent"], episodes["policy_sha256"], strict=True)
    ]
    return episodes.assign(agent=labels)


def generalization_frames(paths: Iterable[str | Path], ci: bool = True) -> tuple[pd.DataFrame, set, pd.DataFrame]:
    """The table's cells (text), its bold cells and the paired comparisons, from the result folders ``paths``.

    Raises ``ValueError`` when no folder holds a policy flown on ``RaceObs-Unseen-v0``.
    """
    episodes = _episodes(paths)
    unseen = episodes[(episodes["env_id"] == UNSEEN_ID) & (episodes["seed_set"] == "public")]
    if unseen.empty:
        raise ValueError(f"no public-seed episodes of {UNSEEN_ID} in the given result folders")
    summary = summarize(episodes[episodes["agent"].isin(set(unseen["agent"])) & (episodes["seed_set"] == "public")])
    cells = {(r["agent"], r["env_id"]): r for _, r in summary.iterrows()}
    order = summary[summary["env_id"] == UNSEEN_ID].sort_values(["success_rate", "agent"], ascending=[False, True])
    agents = [(str(a), bool(p)) for a, p in zip(order["agent"], order["privileged"], strict=True)]
    labels = {a: f"{a} (privileged)" if p else a for a, p in agents}
    columns: dict[str, dict[str, str]] = {}
    bold: set[tuple[str, str]] = set()
    for env_id in (UNSEEN_ID, *PAPER_IDS):
        name = COLUMN_NAMES[env_id]
        rows = {a: cells.get((a, env_id)) for a, _ in agents}
        if env_id != UNSEEN_ID and all(r is None for r in rows.values()):
            continue  # no policy was flown on this paper track
        columns[f"SR [%] {name}"] = {labels[a]: _sr_text(r, ci) for a, r in rows.items()}
        columns[f"LT [s] {name}"] = {labels[a]: _lt_text(r) for a, r in rows.items()}
        learned = {a: _interval(r, lap_time=False) for a, r in rows.items() if r is not None and not dict(agents)[a]}
        bold |= {(labels[a], f"SR [%] {name}") for a in best_separated(learned, lower_is_better=False)}
    frame = pd.DataFrame(columns, index=[labels[a] for a, _ in agents])
    return frame, bold, _pairs(unseen, [a for a, _ in agents])


def _pairs(unseen: pd.DataFrame, agents: list[str]) -> pd.DataFrame:
    """Every pair of policies on the held-out episodes they share: McNemar's exact test, Holm over the pairs."""
    rows = []
    for a, b in combinations(agents, 2):
        part_a = unseen[unseen["agent"] == a][["env_id", "seed", "success", "lap_time"]]
        part_b = unseen[unseen["agent"] == b][["env_id", "seed", "success", "lap_time"]]
        n, only_a, only_b, p = paired_outcomes(
            part_a[["env_id", "seed", "success"]], part_b[["env_id", "seed", "success"]]
        )
        if n == 0:
            continue
        both = part_a.merge(part_b, on=["env_id", "seed"], suffixes=("_a", "_b"))
        both = both[both["success_a"] & both["success_b"]]
        gap = (pd.to_numeric(both["lap_time_a"]) - pd.to_numeric(both["lap_time_b"])).mean() if len(both) else math.nan
        rows.append({"a": a, "b": b, "pairs": n, "only_a": only_a, "only_b": only_b, "p": p, "lap_gap": gap,
                     "both_finished": len(both)})  # fmt: skip
    frame = pd.DataFrame(rows, columns=["a", "b", "pairs", "only_a", "only_b", "p", "lap_gap", "both_finished"])
    if not frame.empty:
        frame["p_holm"] = holm_adjust(frame["p"].tolist())
    return frame


def generalization_table(paths: Iterable[str | Path], fmt: str = "md", ci: bool = True) -> str:
    """The generalisation table and its paired comparisons as Markdown (``fmt="md"``) or LaTeX."""
    frame, bold, pairs = generalization_frames(paths, ci)
    caption = (
        f"Generalisation: success rate (SR{', 95% Wilson interval in brackets' if ci else ''}) and mean lap time "
        f"(LT, over the successful laps) on the {COLUMN_NAMES[UNSEEN_ID]} ({UNSEEN_ID}, public seeds), and on the "
        "paper's tracks where the same policy was flown there (zero-shot for a policy trained on generated tracks; a "
        "per-track policy's own track is its training track). Bold: a non-privileged policy whose interval lies "
        "entirely above every other's."
    )
    text = render(frame, bold, fmt, caption)
    if pairs.empty:
        return text
    table = pd.DataFrame(
        {
            "pairs": pairs["pairs"].astype(str).tolist(),
            "only A": pairs["only_a"].astype(str).tolist(),
            "only B": pairs["only_b"].astype(str).tolist(),
            "p (McNemar)": [f"{p:.3g}" for p in pairs["p"]],
            "p (Holm)": [f"{p:.3g}" for p in pairs["p_holm"]],
            "LT A − B [s]": [_gap(g, n) for g, n in zip(pairs["lap_gap"], pairs["both_finished"], strict=True)],
        },
        index=[f"{a} vs {b}" for a, b in zip(pairs["a"], pairs["b"], strict=True)],
    )
    note = (
        f"Paired on the {COLUMN_NAMES[UNSEEN_ID]}: episodes of the same seed (same track, same obstacles) flown by "
        "both policies A and B; the laps only one finished, McNemar's exact p, Holm's adjustment over all pairs, and "
        "the mean lap-time difference on the episodes both finished (how many in parentheses)."
    )
    return text + "\n" + render(table, set(), fmt, note)


def _gap(seconds: float, laps: int) -> str:
    return "–" if not laps else f"{seconds:+.2f} ({laps})"
