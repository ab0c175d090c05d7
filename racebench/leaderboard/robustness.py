"""An entry's robustness on the site: the main table's robustness column and the robustness table of its page.

Both come from the records the entry already lists (records are keyed by env id, so the suite's records sit in the
same folders), validated on load like every record: of the policy's sha256, the current env version, the first n
seeds of the protocol. For each track the entry has, its policy for that track is paired on the protocol's first
:data:`ROBUSTNESS_EPISODES` public seeds (the count the leaderboard ranks on, ``RANKED_EPISODES``): the main id's
episodes against each perturbation's on the same seeds
(:func:`racebench.reporting.robustness.robustness_cells`, McNemar's exact test, Holm over the entry's table).

The column is :func:`racebench.reporting.robustness.relative_robustness`: per track the mean success rate under the
ten perturbations over the nominal success rate, averaged over the tracks that count (all ten flown, nominal
success above 0). It is never part of the rank key. These are public-seed numbers, never covered by a signature.
"""

from __future__ import annotations

import html
import math
from dataclasses import dataclass
from typing import Any

import pandas as pd

from racebench.evaluation.protocol import TRACK_ORDER
from racebench.evaluation.seeds import public_seeds
from racebench.evaluation.statistics import wilson_interval
from racebench.leaderboard.entries import Entry
from racebench.reporting.robustness import (
    ALPHA,
    EPISODE_COLUMNS,
    PERTURBATIONS,
    RobustnessScore,
    relative_robustness,
    robustness_cells,
    suite_cell,
)
from racebench.reporting.tables import TRACK_NAMES

#: The public episodes per id an entry's robustness is computed on: the leaderboard's ranked count
#: (``racebench.leaderboard.ranking.RANKED_EPISODES``, which passes it; tested equal).
ROBUSTNESS_EPISODES = 50


@dataclass(frozen=True)
class EntryRobustness:
    """An entry's robustness cells (:func:`racebench.reporting.robustness.robustness_cells`), its score, and why
    there are none (``problem``: records that cannot be paired)."""

    cells: pd.DataFrame
    score: RobustnessScore
    episodes: int = ROBUSTNESS_EPISODES  # the first public seeds it is computed on
    problem: str | None = None

    @property
    def flown(self) -> bool:
        """Whether the entry has robustness records that pair with its main ids."""
        return not self.cells.empty


def entry_robustness(entry: Entry, episodes: int = ROBUSTNESS_EPISODES) -> EntryRobustness:
    """The robustness of ``entry``: each track's policy on that track's suite ids, the protocol's first ``episodes``
    public seeds."""
    first = set(public_seeds(episodes))
    rows = [
        {"method": entry.name, "privileged": entry.privileged, "env_id": r["env_id"], "seed": r["seed"],
         "success": r["success"], "lap_time": r["lap_time"]}
        for track in entry.tracks for r in entry.public_records(track)
        if r["seed"] in first and suite_cell(r["env_id"]) is not None
    ]  # fmt: skip
    try:
        cells = robustness_cells(pd.DataFrame(rows, columns=list(EPISODE_COLUMNS)))
    except ValueError as exc:  # e.g. one scene flown with both renderers: the site builds, the page says why
        empty = robustness_cells(pd.DataFrame(columns=list(EPISODE_COLUMNS)))
        return EntryRobustness(empty, relative_robustness(empty), episodes, str(exc))
    return EntryRobustness(cells, relative_robustness(cells), episodes)


def _esc(value: Any) -> str:
    return html.escape(str(value), quote=True)


def robustness_column_html(result: EntryRobustness) -> str:
    """The main table's cell: the score, the tracks it averages, or "–" without robustness records."""
    score = result.score
    if score.value is None:
        why = "; ".join(f"{t}: {w}" for t, w in score.left_out.items()) or result.problem or "no robustness records"
        return f'– <small class="muted">({_esc(why)})</small>' if result.flown or result.problem else "–"
    left = "".join(f"; {t} left out: {w}" for t, w in score.left_out.items())
    return f"{100 * score.value:.0f} %<br><small>{_esc('/'.join(score.tracks) + left)}</small>"


def robustness_data(result: EntryRobustness) -> dict[str, Any] | None:
    """The entry's robustness for the site's embedded JSON (None without robustness records)."""
    if not result.flown:
        return None
    cells = {
        f"{c.track}/{c.perturbation}": {
            "pairs": int(c.pairs), "nominal_successes": int(c.nominal_successes), "successes": int(c.successes),
            "delta_sr_points": float(c.delta_sr), "p_mcnemar": float(c.p), "p_holm": float(c.p_holm),
            "significant": bool(c.significant),
        }
        for c in result.cells.itertuples(index=False)
    }  # fmt: skip
    score = result.score
    return {"score": score.value, "per_track": score.per_track, "left_out": score.left_out, "cells": cells}


def _cell_html(successes: int, n: int, delta: float | None = None, significant: bool = False) -> str:
    low, high = wilson_interval(successes, n)
    text = f"{100 * successes / n:.0f} % <small>[{100 * low:.0f}–{100 * high:.0f}]</small><br><small>{successes}/{n}"
    if delta is not None:
        text += f", Δ {round(delta):+d}" if round(delta) else ", Δ ±0"
    klass = "num drop" if significant and delta is not None and delta < 0 else "num best" if significant else "num"
    return f'<td class="{klass}">{text}</small></td>'


def robustness_section_html(result: EntryRobustness) -> str:
    """The entry page's robustness section: the score and a table per track × perturbation (SR, Δ from nominal)."""
    parts = ['<h2 id="robustness">Robustness</h2>']
    if not result.flown:
        why = f" ({_esc(result.problem)})" if result.problem else ""
        parts.append(f'<p class="muted">No robustness records{why}: <code>racebench evaluate --envs robustness-'
                     "&lt;track&gt; --episodes 50</code> into the policy's record folder adds them"
                     " (docs/robustness.md).</p>")  # fmt: skip
        return "\n".join(parts)
    score = result.score
    value = "–" if score.value is None else f"{100 * score.value:.0f} %"
    left = "".join(f"; {TRACK_NAMES[t]} left out: {_esc(w)}" for t, w in score.left_out.items())
    parts.append(
        f"<p>Robustness score <b>{value}</b>: per track, the mean success rate under the ten perturbations of the"
        " robustness suite over the nominal success rate (the main id on the same scenes), averaged over the tracks"
        f"{left}. Not part of the rank key. Public seeds (the first {result.episodes} of the protocol), never"
        f" covered by a signature. Δ: the change from nominal in points; green or red: significant by McNemar's"
        f" exact test on the paired scenes, Holm-adjusted over this table (α = {ALPHA:g}), red a drop.</p>"
    )
    head = "<th>track</th><th>nominal</th>" + "".join(f"<th>{_esc(p)}</th>" for p in PERTURBATIONS)
    body = []
    for track in TRACK_ORDER:
        mine = result.cells[result.cells["track"] == track].set_index("perturbation")
        if mine.empty:
            continue
        first = mine.iloc[0]
        tds = [_cell_html(int(first["nominal_successes"]), int(first["pairs"]))]
        for name in PERTURBATIONS:
            if name not in mine.index:
                tds.append('<td class="num">–</td>')
                continue
            c = mine.loc[name]
            tds.append(_cell_html(int(c["successes"]), int(c["pairs"]), float(c["delta_sr"]), bool(c["significant"])))
        ratio = score.per_track.get(track)
        shown = "" if ratio is None or math.isnan(ratio) else f"<br><small>score {100 * ratio:.0f} %</small>"
        body.append(f"<tr><th>{_esc(TRACK_NAMES[track])}{shown}</th>{''.join(tds)}</tr>")
    parts.append(f'<table id="robustness-table">\n<tr>{head}</tr>\n' + "\n".join(body) + "\n</table>")
    return "\n".join(parts)
