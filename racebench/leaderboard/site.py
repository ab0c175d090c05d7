"""``racebench leaderboard build``: a self-contained static site of the leaderboard (plain HTML and CSS).

No server, no script, no external URL: ``index.html`` (the ranking of methods per tier, aggregate statistics and
the paper's tables), ``entries/<name>.html`` (description, budget, policies, the signed result or why it was
refused, every cell, trajectory plots in ``entries/<name>/`` and, with ``videos=True``, one video per main id) and
``style.css``. The numbers are embedded in ``index.html`` as JSON (``<script type="application/json">``, which a
browser does not execute). The build is deterministic: no timestamps, a fixed bootstrap seed, and it needs no
secret: a verified entry is one whose ``verified.json`` checks against the pinned maintainers' key.

An entry is a method (:mod:`racebench.leaderboard.entries`): each policy is judged on its own track. The **rank
key**, a visible column, is the mean of the three own-track success rates on the main ids, then the mean of the
three own-track mean lap times; a method without all three tracks is listed unranked below. Cross-track
generalisation (per-track policies on the other tracks) is an extra column, never the key. Success rates are
shown as percentage, 95 % Wilson interval and ``k/n``; a cell is bold only when its interval lies entirely above
the interval of every other entry of its tier in that column. References (privileged built-ins) are listed for
scale, never ranked or bold.

Aggregate statistics: the rank key with a 95 % percentile interval from :func:`scipy.stats.bootstrap` resampling
episodes within each track (stratified), and rliable's probability of improvement between neighbours of a tier.
Every policy is one training run: the intervals cover evaluation episodes only, and the page says so.
"""

from __future__ import annotations

import html
import json
import math
import shutil
from collections.abc import Sequence
from dataclasses import dataclass
from itertools import pairwise
from pathlib import Path
from typing import Any

import numpy as np

import racebench
from racebench.agents.base import AgentLoadError
from racebench.envs.registration import DENSITIES, ENV_VERSION, GATE_SHIFTS
from racebench.evaluation.protocol import EVAL_SEED_BASE, TRACK_ORDER, split_env_id
from racebench.evaluation.records import read_trajectories
from racebench.leaderboard import signing
from racebench.leaderboard.entries import (
    MAIN_IDS,
    TIERS,
    TRACK_MAIN,
    Cell,
    Entry,
    _spec_at,
    load_config,
    load_entries,
    summarize_cells,
)
from racebench.leaderboard.signing import VERIFIED_FILE, SignatureError, VerifiedResult
from racebench.reporting import video
from racebench.reporting.plots import plot_track_3d
from racebench.reporting.tables import best_separated

BOOTSTRAP_RESAMPLES = 2000
BOOTSTRAP_SEED = 0
PLOT_DPI = 130  # the trajectory figures are committed with the site: ~600 px wide PNGs
TRACK_LABELS: dict[str, str] = {"RaceObs-S-v0": "S", "RaceObs-Circle-v0": "3D Circle", "RaceObs-J-v0": "J"}
TIER_TEXT: dict[str, str] = {
    "verified": "Methods whose ONNX policies (no code runs) the maintainers re-flew on the private seed set, derived "
    "from a secret salt nobody else has, and whose signed result checks against the maintainers' key pinned in "
    "racebench: nobody can have fitted these scenes, and nobody but the maintainers can have written these numbers. "
    "Ranked on the signed numbers.",
    "self-reported": "Everything else: SB3 checkpoints and Python agents (their code runs, and code can read the "
    "simulator's memory), any policy evaluated on the public seeds only (which can be fitted), and private-seed "
    "records without a valid signature. Ranked on public-seed records.",
    "reference": "Privileged built-ins that read the true scene and state: shown for scale, never ranked.",
}

CSS = """
body { font-family: system-ui, -apple-system, "Segoe UI", sans-serif; margin: 2rem auto; max-width: 75rem;
       padding: 0 1rem; color: #1b1f23; line-height: 1.45; }
h1 { margin-bottom: 0.2rem; } h2 { margin-top: 2.2rem; border-bottom: 1px solid #d0d7de; }
p.lead { color: #57606a; margin-top: 0; }
table { border-collapse: collapse; margin: 0.8rem 0; font-size: 0.92rem; }
th, td { border: 1px solid #d0d7de; padding: 0.3rem 0.55rem; text-align: left; vertical-align: top; }
th { background: #f6f8fa; }
td.num { text-align: right; font-variant-numeric: tabular-nums; white-space: nowrap; }
td.key { font-weight: 600; background: #f3f0ff; }
table.ranking td:nth-child(2) { min-width: 18rem; }
td.best { font-weight: 700; background: #eafbea; }
small, .muted { color: #57606a; }
.tier { display: inline-block; padding: 0 0.45rem; border-radius: 0.6rem; font-size: 0.8rem; color: #fff; }
.tier-verified { background: #1a7f37; } .tier-self-reported { background: #9a6700; }
.tier-reference { background: #57606a; }
code { font-size: 0.85rem; word-break: break-all; }
figure { display: inline-block; margin: 0.5rem 1rem 0.5rem 0; } figcaption { color: #57606a; font-size: 0.85rem; }
img, video { max-width: 100%; height: auto; border: 1px solid #d0d7de; }
.note { background: #fff8c5; border: 1px solid #d4a72c; padding: 0.5rem 0.8rem; border-radius: 0.3rem; }
"""


def _esc(value: Any) -> str:
    return html.escape(str(value), quote=True)


def _sr_html(cell: Cell | None) -> str:
    if cell is None:
        return "–"
    low, high = cell.interval
    return (
        f"{100 * cell.success_rate:.0f} % <small>[{100 * low:.0f}–{100 * high:.0f}]</small><br>"
        f"<small>{cell.successes}/{cell.n}</small>"
    )


def _lap_html(value: float, laps: int) -> str:
    return "–" if math.isnan(value) else f"{value:.2f} s <small>({laps} laps)</small>"


def separated_best(cells: dict[str, Cell | None]) -> set[str]:
    """Names whose Wilson interval lies strictly above every other name's interval (needs a rival)."""
    return best_separated({name: c.interval for name, c in cells.items() if c is not None}, lower_is_better=False)


def aggregate(cells: dict[str, Cell], records: Sequence[dict[str, Any]]) -> dict[str, Any] | None:
    """Mean over the main ids' success rates with a stratified bootstrap interval (scipy); None below 2 ids."""
    from scipy.stats import bootstrap

    ids = [i for i in MAIN_IDS if i in cells]
    if len(ids) < 2:
        return None
    samples = [np.array([float(r["success"]) for r in records if r["env_id"] == i]) for i in ids]
    point = float(np.mean([s.mean() for s in samples]))
    if all(np.all(s == s[0]) for s in samples):  # no spread at all: every resample gives the point itself
        low = high = point
    else:
        # Several samples: scipy resamples each one separately, i.e. stratified over tracks.
        result = bootstrap(
            samples,
            lambda *s, axis=-1: np.mean([x.mean(axis=axis) for x in s], axis=0),
            n_resamples=BOOTSTRAP_RESAMPLES,
            confidence_level=0.95,
            method="percentile",
            rng=np.random.default_rng(BOOTSTRAP_SEED),
        )
        low, high = float(result.confidence_interval.low), float(result.confidence_interval.high)
    return {"ids": ids, "mean_sr": point, "low": low, "high": high, "episodes": int(sum(len(s) for s in samples))}


@dataclass
class Row:
    """One entry as the site shows it: its tier and the own-track cells it is ranked on."""

    entry: Entry
    tier: str
    cells: dict[str, Cell]  # main id -> the own-track cell (signed if verified, else public)
    verified: VerifiedResult | None = None
    refusal: str | None = None  # why its verified.json was refused (None: none, or accepted)

    @property
    def name(self) -> str:
        """The entry's name."""
        return self.entry.name

    def key(self) -> tuple[float, float]:
        """The rank key: mean own-track success rate over the three tracks, then mean of the own-track mean laps."""
        rates = [self.cells[i].success_rate if i in self.cells else 0.0 for i in MAIN_IDS]
        laps = [self.cells[i].lap_time_mean if i in self.cells else math.nan for i in MAIN_IDS]
        lap = math.nan if any(math.isnan(x) for x in laps) else sum(laps) / len(laps)
        return sum(rates) / len(rates), lap

    def outcomes(self) -> list[dict[str, Any]]:
        """Per-episode outcomes of its cells (for the bootstrap and P(improvement): order does not matter)."""
        return [
            {"env_id": env_id, "success": i < cell.successes}
            for env_id, cell in self.cells.items()
            for i in range(cell.n)
        ]


def entry_row(entry: Entry, config: dict[str, Any], pinned_key_sha256: str | None = None) -> Row:
    """The tier and ranked cells of ``entry``: verified only when its signed result checks (no secret needed)."""
    verified, refusal = None, None
    if (entry.folder / VERIFIED_FILE).is_file():
        try:
            verified = check_verified(entry, config, pinned_key_sha256)
        except SignatureError as exc:
            refusal = str(exc)
    if entry.privileged:
        return Row(entry, "reference", _public_main_cells(entry), None, refusal)
    if verified is not None:
        return Row(entry, "verified", dict(verified.cells), verified)
    return Row(entry, "self-reported", _public_main_cells(entry), None, refusal)


def check_verified(entry: Entry, config: dict[str, Any], pinned_key_sha256: str | None) -> VerifiedResult:
    """:func:`racebench.leaderboard.signing.check_verified`, against the pinned key unless another is given."""
    return signing.check_verified(entry, config, pinned_key_sha256 or signing.MAINTAINERS_KEY_SHA256)


def _public_main_cells(entry: Entry) -> dict[str, Cell]:
    own = entry.own_cells()
    return {i: own[i] for i in MAIN_IDS if i in own}


def rank(rows: Sequence[Row]) -> list[Row]:
    """Rows in order: complete methods first, then the rank key (success, then lap time), then the name."""

    def key(row: Row) -> tuple[int, float, float, str]:
        sr, lap = row.key()
        return (0 if row.entry.complete else 1, -sr, lap if not math.isnan(lap) else math.inf, row.name)

    return sorted(rows, key=key)


def _key_html(row: Row) -> str:
    if not row.entry.complete:
        return f"– <small>({len(row.entry.tracks)}/3 tracks)</small>"
    sr, lap = row.key()
    lap_text = "–" if math.isnan(lap) else f"{lap:.2f} s"
    return f"{100 * sr:.1f} %<br><small>lap {lap_text}</small>"


def _cross_html(entry: Entry) -> str:
    if any(p.track == "all" for p in entry.policies.values()):
        return '<small class="muted">one policy for all</small>'
    cells = list(entry.cross_cells().values())
    if not cells:
        return "–"
    k, n = sum(c.successes for c in cells), sum(c.n for c in cells)
    return _sr_html(Cell("cross", "public", n, k, ())) + f"<br><small>{len(cells)} other-track cells</small>"


def _budget_html(entry: Entry) -> str:
    steps, wall = entry.budget()
    if steps == 0 and wall == 0:
        return '<small class="muted">not trained</small>'
    policies = len(entry.policies)
    steps_text = "steps unknown" if steps is None else f"{steps / 1e6:.2f} M steps"
    wall_text = "wall clock unknown" if wall is None else f"{wall / 3600:.1f} h"
    each = f" ({policies} policies)" if policies > 1 else ""
    return f"{steps_text}, {wall_text}{each}<br><small>{_esc(entry.meta['hardware'])}</small>"


def _teacher_html(entry: Entry) -> str:
    if entry.privileged:
        return "<small>is privileged</small>"
    return f"yes: {_esc(entry.meta['teacher'])}" if entry.privileged_teacher else "no"


def _ranking_table(table_id: str, rows: list[Row], ranked: bool, bold: dict[str, set[str]]) -> str:
    """One table of entries: a rank column when ``ranked``, the key column, bold cells as given per column."""
    head = "".join(f"<th>SR {TRACK_LABELS[i]} <small>(own policy)</small></th>" for i in MAIN_IDS)
    body = []
    for position, row in enumerate(rows, start=1):
        entry = row.entry
        tds = [f'<td class="num">{position if ranked else "–"}</td>']
        tds.append(
            f'<td><a href="entries/{_esc(entry.name)}.html">{_esc(entry.name)}</a><br>'
            f"<small>{_esc(entry.meta['description'])}</small></td>"
        )
        tds.append(f'<td class="num key">{_key_html(row)}</td>')
        for env_id in MAIN_IDS:
            klass = "num best" if row.name in bold.get(env_id, set()) else "num"
            cell = row.cells.get(env_id)
            lap = f"<br><small>lap {cell.lap_time_mean:.2f} s</small>" if cell and cell.lap_times else ""
            tds.append(f'<td class="{klass}">{_sr_html(cell)}{lap}</td>')
        tds.append(f'<td class="num">{_cross_html(entry)}</td>')
        tds.append(f"<td>{_teacher_html(entry)}</td>")
        tds.append(f'<td class="num">{_budget_html(entry)}</td>')
        seeds = ", ".join(sorted({c.seed_set for c in row.cells.values()})) or "–"
        tds.append(f"<td>{_esc(entry.meta['obs_mode'])}, {_esc(entry.kind)}<br><small>{_esc(seeds)} seeds</small></td>")
        body.append("<tr>" + "".join(tds) + "</tr>")
    return (
        f'<table class="ranking" id="{table_id}">\n<tr><th>#</th><th>method</th>'
        "<th>rank key <small>(mean own-track SR, then lap)</small></th>"
        f"{head}<th>cross-track SR <small>(other tracks, not ranked)</small></th><th>privileged teacher</th>"
        "<th>training budget</th><th>sees, policy files</th></tr>\n" + "\n".join(body) + "\n</table>"
    )


def tier_tables(tier: str, members: list[Row]) -> str:
    """The HTML of one tier: ranked methods (all three tracks), then the unranked ones, bold where separated."""
    if tier == "reference":
        return _ranking_table("table-reference", rank(members), ranked=False, bold={})
    full = rank([r for r in members if r.entry.complete])
    partial = rank([r for r in members if not r.entry.complete])
    # Per-track columns compare every entry of the tier flown on that track.
    bold = {i: separated_best({r.name: r.cells.get(i) for r in members}) for i in MAIN_IDS}
    parts = []
    if full:
        parts.append(_ranking_table(f"ranking-{tier}", full, ranked=True, bold=bold))
    else:
        parts.append('<p class="muted">No method of this tier has a policy for all three tracks: none ranked.</p>')
    if partial:
        parts.append(
            "<p><b>Not ranked</b>: methods without a policy for all three tracks (yet), so their rank key is"
            " unknown, not zero. Listed by success on the tracks they have.</p>"
        )
        parts.append(_ranking_table(f"unranked-{tier}", partial, ranked=False, bold=bold))
    return "\n".join(parts)


def _aggregate_table(rows: list[Row]) -> str:
    body = []
    for row in rows:
        agg = aggregate(row.cells, row.outcomes())
        if agg is None:
            continue
        seeds = row.entry.meta["training_seeds"]
        note = "one training run per policy" + (f" (training seed {seeds[0]})" if len(seeds) == 1 else "")
        body.append(
            f"<tr><td>{_esc(row.name)}</td><td>{_tier_badge(row.tier)}</td>"
            f'<td class="num">{100 * agg["mean_sr"]:.1f} % <small>[{100 * agg["low"]:.1f}–{100 * agg["high"]:.1f}]'
            f'</small></td><td class="num">{len(agg["ids"])} tracks, {agg["episodes"]} episodes</td>'
            f"<td>{_esc(note)}</td></tr>"
        )
    if not body:
        return '<p class="muted">No method has own-track results on two or more tracks.</p>'
    return (
        '<table id="aggregate">\n<tr><th>method</th><th>tier</th><th>mean own-track SR [95 % bootstrap]</th>'
        "<th>evaluated</th><th>what the interval covers</th></tr>\n" + "\n".join(body) + "\n</table>"
    )


def _improvement_table(rows: list[Row]) -> str:
    """Probability of improvement of each ranked non-reference method over the next one of its tier."""
    pairs = []
    for tier in (t for t in TIERS if t != "reference"):
        pairs += list(pairwise(r for r in rows if r.tier == tier and r.entry.complete))
    body = []
    for better, worse in pairs:
        result = probability_of_improvement(better.outcomes(), worse.outcomes(), MAIN_IDS)
        body.append(
            f'<tr><td>{_esc(better.name)}</td><td>{_esc(worse.name)}</td><td class="num">{result["p"]:.2f} '
            f"<small>[{result['low']:.2f}–{result['high']:.2f}]</small></td></tr>"
        )
    if not body:
        return '<p class="muted">Fewer than two ranked methods in a tier: nothing to compare.</p>'
    return (
        '<table id="improvement">\n<tr><th>method X</th><th>method Y (next in X\'s tier)</th>'
        "<th>P(X &gt; Y) [95 % bootstrap]</th></tr>\n" + "\n".join(body) + "\n</table>"
    )


def _label(row: Row) -> str:
    return f"{row.name} (privileged)" if row.tier == "reference" else row.name


def _paper_cell(cell: Cell | None, best: bool) -> str:
    if cell is None:
        return '<td class="num">–</td>'
    low, high = cell.interval
    klass = "num best" if best else "num"
    return f'<td class="{klass}">{100 * cell.success_rate:.0f} <small>[{100 * low:.0f}–{100 * high:.0f}]</small></td>'


def table_ii_html(rows: list[Row]) -> str:
    """Table II: own-track lap time and success rate per track, one row per method (the cells it is ranked on)."""
    learned = [r for r in rows if r.tier != "reference"]
    bold = {i: separated_best({r.name: r.cells.get(i) for r in learned}) for i in MAIN_IDS}
    tracks = [TRACK_LABELS[i] for i in MAIN_IDS]
    head = "".join(f"<th>LT [s] {t}</th>" for t in tracks) + "".join(f"<th>SR [%] {t}</th>" for t in tracks)
    body = []
    for row in rows:
        laps = []
        for i in MAIN_IDS:
            cell = row.cells.get(i)
            laps.append(
                f'<td class="num">{cell.lap_time_mean:.2f}</td>'
                if cell and cell.lap_times
                else '<td class="num">–</td>'
            )
        srs = [_paper_cell(row.cells.get(i), row.name in bold[i]) for i in MAIN_IDS]
        body.append(f"<tr><th>{_esc(_label(row))}</th>{''.join(laps)}{''.join(srs)}</tr>")
    return f'<table id="table-ii">\n<tr><th></th>{head}</tr>\n' + "\n".join(body) + "\n</table>"


VARIANTS: tuple[tuple[str, str], ...] = (
    *((f"Density{d}", f"density {d}") for d in DENSITIES),
    *((f"GateShift{g}", f"gates ±{g} m") for g in GATE_SHIFTS),
)


def table_iv_html(rows: list[Row], track: str) -> str | None:
    """Table IV on one track: a row per method with public records of its ``track`` policy on the track's density
    and gate-shift ids, a column per density and gate shift; None when no method has any."""
    cells: dict[str, dict[str, Cell]] = {}
    for row in rows:
        own = summarize_cells(row.entry.public_records(track))
        found = {v: own[f"RaceObs-{track}-{v}-v0"] for v, _ in VARIANTS if f"RaceObs-{track}-{v}-v0" in own}
        if found:
            cells[row.name] = found
    if not cells:
        return None
    learned = [r.name for r in rows if r.tier != "reference" and r.name in cells]
    bold = {v: separated_best({n: cells[n].get(v) for n in learned}) for v, _ in VARIANTS}
    head = "".join(f"<th>{_esc(label)}</th>" for _, label in VARIANTS)
    body = [
        f"<tr><th>{_esc(_label(row))}</th>"
        + "".join(_paper_cell(cells[row.name].get(v), row.name in bold[v]) for v, _ in VARIANTS)
        + "</tr>"
        for row in rows
        if row.name in cells
    ]
    return f'<table id="table-iv-{track.lower()}">\n<tr><th></th>{head}</tr>\n' + "\n".join(body) + "\n</table>"


def _paper_tables_section(rows: list[Row]) -> str:
    """The paper's Tables II, III and IV over the methods (one Table IV per track)."""
    parts = [
        '\n<h2 id="paper-tables">The paper\'s tables</h2>\n<p>SR in % with the 95 % Wilson interval (n on each'
        " method's page); bold only where a method's interval lies above every other non-privileged method's in"
        " that column (references never bold).</p>",
        "<h3>Table II: own-track lap time (mean over successful laps) and success rate</h3>",
        '<p class="muted">The cells each method is ranked on: signed private-seed numbers for a verified method,'
        " public-seed records otherwise.</p>",
        table_ii_html(rows),
        '<h3>Table III: ablations</h3>\n<p class="muted" id="table-iii">No ablation entries yet (the paper\'s'
        " vision-no-gru, vision-one-step, vision-com and vision-no-avoid configs): the table appears with them.</p>",
        "<h3>Table IV: success rate vs obstacle density and gate shift, per track</h3>",
        '<p class="muted">Public-seed records of each method\'s own policy for the track (the signed results cover'
        " the main ids only).</p>",
    ]
    for track in TRACK_ORDER:
        table = table_iv_html(rows, track)
        title = TRACK_LABELS[TRACK_MAIN[track]]
        parts.append(f"<h4>{_esc(title)} track</h4>")
        parts.append(table or f'<p class="muted">No method was flown on the {_esc(title)} track\'s variants.</p>')
    return "\n".join(parts)


def _page(title: str, body: str, css: str) -> str:
    return (
        '<!DOCTYPE html>\n<html lang="en">\n<head>\n<meta charset="utf-8">\n'
        '<meta name="viewport" content="width=device-width, initial-scale=1">\n'
        f'<title>{_esc(title)}</title>\n<link rel="stylesheet" href="{css}">\n</head>\n'
        f"<body>\n{body}\n</body>\n</html>\n"
    )


def _tier_badge(tier: str) -> str:
    return f'<span class="tier tier-{tier}">{tier}</span>'


def probability_of_improvement(
    x: Sequence[dict[str, Any]], y: Sequence[dict[str, Any]], ids: Sequence[str]
) -> dict[str, float]:
    """P(an episode of X succeeds where one of Y does not) + half the ties, averaged over ``ids`` (rliable's
    probability of improvement, a Mann–Whitney U / (n·m) per track, here over evaluation episodes), with a 95 %
    percentile interval from scipy's bootstrap resampling each entry's episodes within each track (tests check
    the closed form against ``scipy.stats.mannwhitneyu``)."""
    from scipy.stats import bootstrap

    samples = []
    for env_id in ids:
        samples.append(np.array([float(r["success"]) for r in x if r["env_id"] == env_id]))
        samples.append(np.array([float(r["success"]) for r in y if r["env_id"] == env_id]))

    def statistic(*arrays: np.ndarray, axis: int = -1) -> np.ndarray:
        per_track = []
        for a, b in zip(arrays[::2], arrays[1::2], strict=True):
            # P(X > Y) + P(X = Y) / 2 for 0/1 outcomes, vectorised over bootstrap resamples.
            pa, pb = a.mean(axis=axis), b.mean(axis=axis)
            per_track.append(pa * (1 - pb) + 0.5 * (pa * pb + (1 - pa) * (1 - pb)))
        return np.mean(per_track, axis=0)

    point = float(statistic(*samples))
    if all(np.all(a == a[0]) for a in samples):
        return {"p": point, "low": point, "high": point}
    result = bootstrap(samples, statistic, n_resamples=BOOTSTRAP_RESAMPLES, confidence_level=0.95,
                       method="percentile", rng=np.random.default_rng(BOOTSTRAP_SEED))  # fmt: skip
    return {"p": point, "low": float(result.confidence_interval.low), "high": float(result.confidence_interval.high)}


def _entry_data(row: Row) -> dict[str, Any]:
    entry = row.entry
    steps, wall = entry.budget()
    return {
        "name": entry.name,
        "tier": row.tier,
        "complete": entry.complete,
        "rank_key": {
            "mean_own_track_sr": row.key()[0],
            "mean_lap_time": None if math.isnan(row.key()[1]) else row.key()[1],
        }
        if entry.complete
        else None,
        "description": entry.meta["description"],
        "meta": entry.meta,
        "kind": entry.kind,
        "privileged_teacher": entry.privileged_teacher,
        "training_steps": steps,
        "training_wall_clock_s": wall,
        "cells": {
            env_id: {
                "seed_set": c.seed_set,
                "n": c.n,
                "successes": c.successes,
                "wilson95": list(c.interval),
                "lap_time_mean": None if math.isnan(c.lap_time_mean) else c.lap_time_mean,
            }
            for env_id, c in row.cells.items()
        },  # fmt: skip
        "verification_refused": row.refusal,
        "aggregate": aggregate(row.cells, row.outcomes()),
    }


def _policies_table(entry: Entry) -> str:
    rows = []
    for track, policy in entry.policies.items():
        budget = "?" if policy.steps is None else f"{policy.steps:,} steps"
        budget += "" if policy.wall_clock_s is None else f", {policy.wall_clock_s / 3600:.2f} h"
        onnx = (
            f"<code>{_esc(policy.onnx)}</code><br><small>sha256 <code>{_esc(policy.onnx_sha256)}</code></small>"
            if policy.onnx
            else "–"
        )
        rows.append(
            f"<tr><td>{_esc(track)}</td><td><code>{_esc(policy.policy)}</code><br><small>sha256 "
            f"<code>{_esc(policy.sha256)}</code></small></td><td>{onnx}</td>"
            f"<td>{_esc(', '.join(policy.records_dirs))}</td><td>{budget}<br><small>from "
            f"{_esc(policy.budget_source)}</small></td></tr>"
        )
    return (
        '<table id="policies"><tr><th>track</th><th>policy (public records)</th><th>ONNX export (verified)</th>'
        "<th>record folders</th><th>training budget</th></tr>\n" + "\n".join(rows) + "\n</table>"
    )


def _verification_html(row: Row) -> str:
    parts = ['<h2 id="verification">Verification</h2>']
    if row.verified is not None:
        payload = row.verified.payload
        parts.append(
            f"<p>Signed by the maintainers' key (sha256 <code>{_esc(signing.MAINTAINERS_KEY_SHA256)}</code>, pinned in"
            f" racebench): env version {payload['env_version']}, seed protocol {payload['seed_protocol']}, private"
            f" seeds of the salt with fingerprint <code>{_esc(payload['seed_salt_sha256'])}</code>.</p>"
        )
        lines = []
        for signed in payload["policies"]:
            for env_id in [i for i in MAIN_IDS if i in signed["cells"]]:  # the paper's track order
                c, cell = signed["cells"][env_id], row.verified.cells[env_id]
                lap = "–" if c["lap_time_mean"] is None else f"{c['lap_time_mean']:.2f} s"
                median = "–" if c["lap_time_median"] is None else f"{c['lap_time_median']:.2f} s"
                lines.append(
                    f"<tr><td>{_esc(signed['track'])}</td><td>{_esc(env_id)}</td>"
                    f'<td class="num">{_sr_html(cell)}</td><td class="num">{lap}</td><td class="num">{median}</td>'
                    f"<td><code>{_esc(signed['policy_sha256'])}</code></td>"
                    f"<td><code>{_esc(signed['records_sha256'])}</code></td></tr>"
                )
        parts.append(
            '<table id="signed"><tr><th>policy</th><th>env id</th><th>SR (private)</th><th>mean lap</th>'
            "<th>median lap</th><th>policy sha256</th><th>private records sha256</th></tr>\n"
            + "\n".join(lines)
            + "\n</table>"
        )
    elif row.refusal is not None:
        parts.append(f'<p class="note">Signed result refused: {_esc(row.refusal)}</p>')
    else:
        parts.append('<p class="muted">No signed result: not verified.</p>')
    return "\n".join(parts)


def _entry_page(row: Row, media: str = "") -> str:
    entry = row.entry
    meta = entry.meta
    why = {
        "reference": "a privileged built-in (reads the true scene)",
        "verified": "a method whose ONNX policies' private-seed result is signed by the maintainers' pinned key",
        "self-reported": "a method without a valid signed private-seed result",
    }[row.tier]
    shown = {k: v for k, v in meta.items() if k not in ("policies", "name")}
    rows = "".join(
        f"<tr><th>{_esc(k)}</th><td>{_esc(', '.join(map(str, v)) if isinstance(v, list) else v)}</td></tr>"
        for k, v in shown.items()
    )
    records = entry.records
    facts = {
        "record files": len(records),
        "seed sets": ", ".join(sorted({r["seed_set"] for r in records})),
        "env version": ", ".join(sorted({str(r["env_version"]) for r in records})),
        "renderers": ", ".join(sorted({r["renderer"] for r in records})),
        "racebench commits": ", ".join(sorted({r["git_commit"] for r in records})),
        "host CPUs": ", ".join(sorted({r["host_cpu"] for r in records})),
    }
    rows += "".join(f"<tr><th>{_esc(k)}</th><td>{_esc(v)}</td></tr>" for k, v in facts.items())
    cell_rows = []
    for track, policy in entry.policies.items():
        for seed_set in sorted({r["seed_set"] for r in policy.records}):
            chosen = [r for r in policy.records if r["seed_set"] == seed_set]
            for env_id, cell in summarize_cells(chosen).items():
                laps = np.array(cell.lap_times)
                median = f"{np.median(laps):.2f} s" if len(laps) else "–"
                own = "own" if policy.own(env_id) else "other"
                shown_set = seed_set if seed_set == "public" else f"{seed_set} (unsigned: not ranked)"
                cell_rows.append(
                    f"<tr><td>{_esc(track)}</td><td>{_esc(env_id)}</td><td>{own}</td><td>{_esc(shown_set)}</td>"
                    f'<td class="num">{cell.n}</td><td class="num">{_sr_html(cell)}</td>'
                    f'<td class="num">{_lap_html(cell.lap_time_mean, len(laps))}</td><td class="num">{median}</td></tr>'
                )
    body = (
        f'<p><a href="../index.html">← leaderboard</a></p>\n<h1>{_esc(entry.name)} {_tier_badge(row.tier)}</h1>\n'
        f'<p class="lead">{_esc(meta["description"])}</p>\n<p>Tier: {row.tier}, because it is {why}.</p>\n'
        f"<h2>Metadata</h2>\n<table>{rows}</table>\n<h2>Policies</h2>\n{_policies_table(entry)}\n"
        + _verification_html(row)
        + '\n<h2>Every evaluated cell</h2>\n<p class="muted">Each policy\'s records: own track or another one'
        " (cross-track generalisation). SR: success rate, 95 % Wilson interval, successes/episodes. Lap time over"
        " successful laps.</p>\n"
        '<table id="cells"><tr><th>policy</th><th>env id</th><th>track</th><th>seed set</th><th>n</th><th>SR</th>'
        "<th>mean lap</th><th>median lap</th></tr>\n" + "\n".join(cell_rows) + "\n</table>\n" + media
    )
    return _page(f"{entry.name} · racebench leaderboard", body, "../style.css")


def entry_media(entry: Entry, folder: Path, videos: bool = False, trust_code: bool = False) -> str:
    """Trajectory plots (and, with ``videos``, one episode video) per main id of ``entry``, written into ``folder``;
    return the HTML section that shows them.

    A plot is the paper's Fig. 4 (:func:`racebench.reporting.plots.plot_track_3d`) from the trajectories saved with the
    records of the entry's policy for that track (``evaluate --save-trajectories``): one scene, its flights in it.
    A video flies the track's policy on the first public evaluation seed
    (:func:`racebench.reporting.video.render_episode_video`):
    chase view beside the colour-mapped depth image, outcome captioned. Built on demand and not committed.
    """
    figures, missing = [], []
    for env_id in MAIN_IDS:
        policy = entry.policy_for(split_env_id(env_id)[0])
        record_dirs = [entry.root / d for d in policy.records_dirs] if policy else []
        source = next((d for d in record_dirs if _has_trajectories(d, env_id)), None)
        if source is None:
            missing.append(env_id)
            continue
        png = folder / f"{TRACK_LABELS[env_id].replace(' ', '-')}.png"
        folder.mkdir(parents=True, exist_ok=True)
        plot_track_3d(source, env_id, png, dpi=PLOT_DPI)
        figures.append(f'<figure><img src="{_esc(folder.name)}/{_esc(png.name)}" alt="trajectories on {_esc(env_id)}"'
                       f"><figcaption>{_esc(env_id)}</figcaption></figure>")  # fmt: skip
    parts = ['<h2 id="trajectories">Trajectories</h2>']
    parts += figures or []
    if missing:
        parts.append(f'<p class="muted">No saved trajectories for {_esc(", ".join(missing))}: the records were'
                     " written without <code>--save-trajectories</code>.</p>")  # fmt: skip
    clips = []
    if videos:
        for env_id in MAIN_IDS:
            policy = entry.policy_for(split_env_id(env_id)[0])
            if policy is not None and any(r["env_id"] == env_id for r in policy.records):
                spec = policy.builtin or _spec_at(policy.policy, entry.root)
                mp4 = folder / f"{TRACK_LABELS[env_id].replace(' ', '-')}.mp4"
                folder.mkdir(parents=True, exist_ok=True)
                try:
                    video.render_episode_video(spec, env_id, EVAL_SEED_BASE, mp4, trust_code=trust_code,
                                               label=entry.name)  # fmt: skip
                except AgentLoadError as exc:  # e.g. a .zip without --trust-code: the page says so, the site builds
                    clips.append(f'<p class="note">No video: {_esc(exc)}</p>')
                    break
                caption = f"{_esc(env_id)}, seed {EVAL_SEED_BASE}"
                clips.append(f'<figure><video src="{_esc(folder.name)}/{_esc(mp4.name)}" controls width="640">'
                             f"</video><figcaption>{caption}</figcaption></figure>")  # fmt: skip
    parts.append('<h2 id="videos">Videos</h2>')
    parts += clips or ['<p class="muted">Built on demand, not committed: <code>racebench leaderboard build --out DIR'
                       " --videos</code> flies one episode per main id and shows it here.</p>"]  # fmt: skip
    return "\n".join(parts)


def _has_trajectories(records_dir: Path, env_id: str) -> bool:
    """Whether the result folder ``records_dir`` holds a saved flight of ``env_id``."""
    return any(row["env_id"] == env_id for row, _, _ in read_trajectories(records_dir))


def build_site(
    leaderboard: str | Path,
    out: str | Path,
    videos: bool = False,
    trust_code: bool = False,
    pinned_key_sha256: str | None = None,
) -> Path:
    """Write the site of the entries under ``leaderboard`` into ``out`` (replacing an earlier build); return index.

    Needs no secret: a signed result is checked against the public key in ``leaderboard.yaml``, which must be the
    one whose fingerprint is ``pinned_key_sha256`` (default: the pinned :data:`signing.MAINTAINERS_KEY_SHA256`).
    """
    config = load_config(leaderboard)
    entries = load_entries(leaderboard)
    out = Path(out)
    if (out / "entries").is_dir():
        shutil.rmtree(out / "entries")  # a removed entry must not keep its page
    (out / "entries").mkdir(parents=True, exist_ok=True)
    (out / "style.css").write_text(CSS.lstrip())
    rows = {e.name: entry_row(e, config, pinned_key_sha256) for e in entries}
    sections = []
    ordered: list[Row] = []
    for tier in TIERS:
        members = rank([r for r in rows.values() if r.tier == tier])
        ordered += members
        sections.append(f"<h2 id=\"tier-{tier}\">{_tier_badge(tier)} {tier.capitalize()}</h2>\n"
                        f"<p>{_esc(TIER_TEXT[tier])}</p>")  # fmt: skip
        if members:
            sections.append(tier_tables(tier, members))
        elif tier == "verified":
            sections.append('<p class="note">No verified entries: no signed result checks against the pinned'
                            " maintainers' key (docs/leaderboard.md).</p>")  # fmt: skip
        else:
            sections.append('<p class="muted">No entries.</p>')
        for row in members:
            media = entry_media(row.entry, out / "entries" / row.name, videos=videos, trust_code=trust_code)
            (out / "entries" / f"{row.name}.html").write_text(_entry_page(row, media))
    data = {r.name: _entry_data(r) for r in ordered}
    blob = json.dumps(
        {"racebench_version": racebench.__version__, "env_version": ENV_VERSION, "entries": data},
        sort_keys=True, allow_nan=False,
    ).replace("</", "<\\/")  # fmt: skip
    body = (
        "<h1>racebench leaderboard</h1>\n"
        f'<p class="lead">{len(entries)} methods · env version {ENV_VERSION} · racebench '
        f"{_esc(racebench.__version__)} · main ids: {', '.join(MAIN_IDS)}</p>\n"
        "<p>One row per <b>method</b>, as in the paper's Table II: one policy per track (S, 3D Circle, J) or one"
        " policy for all three, each flown on its <b>own</b> track. <b>Rank key</b> (its own column): the mean of"
        " the three own-track success rates, then the mean of the three own-track mean lap times. A method without"
        " all three tracks is listed unranked below its tier. Cross-track success (a per-track policy on the other"
        " tracks) is shown, never ranked. SR cells: percentage, 95 % Wilson interval, successes/episodes."
        " <b>Bold</b> only where a method's interval lies entirely above every other method's of its tier in"
        " that column.</p>\n" + "\n".join(sections) + '\n<h2 id="aggregate-statistics">Aggregate statistics</h2>\n'
        "<p>The rank key (mean own-track success over the tracks a method has) with a 95 % percentile interval from"
        f" scipy's bootstrap ({BOOTSTRAP_RESAMPLES} resamples of the episodes within each track, i.e. stratified"
        " over tracks). <b>Every policy is a single training run (one training seed)</b>, so these intervals cover"
        " the evaluation scenes only, not the variation between training runs; with several seeds per method they"
        " would be bootstrapped over runs as well (rliable-style).</p>\n"
        + _aggregate_table(ordered)
        + '\n<h3 id="probability-of-improvement">Probability of improvement</h3>\n'
        "<p>P(X &gt; Y): the chance that an own-track episode of X succeeds where one of Y fails, plus half the"
        " ties, averaged over the three tracks (rliable's probability of improvement; Mann–Whitney U / (n·m) per"
        " track), between each ranked method and the next one of its tier, with a stratified bootstrap interval."
        " With one training run per policy it compares these policy files on these scenes, not two training"
        " methods.</p>\n"
        + _improvement_table(ordered)
        + _paper_tables_section(ordered)
        + f'\n<script type="application/json" id="leaderboard-data">{blob}</script>'
    )
    index = out / "index.html"
    index.write_text(_page("racebench leaderboard", body, "style.css"))
    return index
