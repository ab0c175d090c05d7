"""``racebench leaderboard build``: a self-contained static site of the leaderboard (plain HTML and CSS).

No server, no script, no external URL: ``index.html`` (the ranking per tier, aggregate statistics and the
paper's tables), ``entries/<name>.html`` (metadata, every cell, trajectory plots in ``entries/<name>/`` and,
built on demand with ``videos=True``, one video per main id) and ``style.css``. The data behind the pages is
embedded in ``index.html`` as JSON (``<script type="application/json" id="leaderboard-data">``, which a browser
does not execute) for anyone who wants the numbers without parsing tables. The build is deterministic: no
timestamps, a fixed bootstrap seed.

Ranking, within a tier: the mean over the three main ids of the per-track success rate (each track weighs the
same, even for an entry flown on more episodes of its own track), then the mean lap time over their successful
laps. Entries flown on fewer of the three ids (per-track policies) are listed below,
unranked: success on an id never flown is unknown, not zero. Success rates are shown as ``k/n``, percentage
and 95 % Wilson interval; a cell is bold only when its interval lies entirely above the interval of every
other entry of its tier in that column (the pooled column: of every other ranked entry).
References (privileged built-ins) are listed for scale, never ranked or bold.

Aggregate statistics: the mean over tracks of the per-track success rate, with a 95 % percentile interval from
:func:`scipy.stats.bootstrap` resampling episodes within each track (stratified). Every entry is one policy
file, i.e. one training run: the interval covers the evaluation episodes only, not the spread between training
seeds, and the page says so instead of presenting episodes as if they were seeds.
"""

from __future__ import annotations

import html
import json
import math
import shutil
from collections.abc import Sequence
from itertools import pairwise
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

import racebench
from racebench.leaderboard.entries import MAIN_IDS, TIERS, Cell, Entry, load_config, load_entries, summarize_cells
from racebench.registration import ENV_VERSION

BOOTSTRAP_RESAMPLES = 2000
BOOTSTRAP_SEED = 0
PLOT_DPI = 130  # the trajectory figures are committed with the site: ~600 px wide PNGs
TRACK_LABELS: dict[str, str] = {"RaceObs-S-v0": "S", "RaceObs-Circle-v0": "3D Circle", "RaceObs-J-v0": "J"}
TIER_TEXT: dict[str, str] = {
    "verified": "ONNX policies (no code runs) evaluated by the maintainers on the private seed set, derived from "
    "a secret salt: nobody can have fitted these scenes.",
    "self-reported": "Everything else: SB3 checkpoints and Python agents (their code runs, and code can read the "
    "simulator's memory) and any policy evaluated on the public seeds only (which can be fitted). "
    "Ranked on public-seed records.",
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


def pooled(cells: dict[str, Cell]) -> Cell | None:
    """The main ids' cells of an entry pooled into one (successes and laps summed), None without any."""
    main = [cells[i] for i in MAIN_IDS if i in cells]
    if not main:
        return None
    laps = tuple(t for c in main for t in c.lap_times)
    return Cell("main", main[0].seed_set, sum(c.n for c in main), sum(c.successes for c in main), laps)


def rank(entries: Sequence[Entry], accepted: Sequence[str]) -> list[Entry]:
    """Entries in order: more main ids covered, then the mean over those ids of the success rate (each track
    weighs the same even where an entry flew more episodes on one, e.g. its own), then the pooled mean lap time,
    then the name."""

    def key(entry: Entry) -> tuple[float, float, float]:
        cells = entry.cells(accepted)
        main = pooled(cells)
        covered = [cells[i] for i in MAIN_IDS if i in cells]
        if main is None:
            return (0, 0.0, math.inf)
        lap = main.lap_time_mean
        mean_sr = sum(c.success_rate for c in covered) / len(covered)
        return (-len(covered), -mean_sr, lap if not math.isnan(lap) else math.inf)

    return sorted(entries, key=lambda e: (*key(e), e.name))


def separated_best(cells: dict[str, Cell | None]) -> set[str]:
    """Names whose Wilson interval lies strictly above every other name's interval (needs a rival)."""
    from racebench.tables import best_separated

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


def _entry_data(entry: Entry, accepted: Sequence[str]) -> dict[str, Any]:
    tier = entry.tier(accepted)
    cells = entry.cells(accepted)
    main = pooled(cells)
    return {
        "name": entry.name,
        "tier": tier,
        "meta": entry.meta,
        "kind": entry.kind,
        "cells": {
            env_id: {
                "seed_set": c.seed_set,
                "n": c.n,
                "successes": c.successes,
                "wilson95": list(c.interval),
                "lap_time_mean": None if math.isnan(c.lap_time_mean) else c.lap_time_mean,
            }
            for env_id, c in cells.items()
        },  # fmt: skip
        "main": None if main is None else {"n": main.n, "successes": main.successes, "wilson95": list(main.interval)},
        "aggregate": aggregate(cells, entry.ranked_records(accepted)),
    }


def _page(title: str, body: str, css: str) -> str:
    return (
        '<!DOCTYPE html>\n<html lang="en">\n<head>\n<meta charset="utf-8">\n'
        '<meta name="viewport" content="width=device-width, initial-scale=1">\n'
        f'<title>{_esc(title)}</title>\n<link rel="stylesheet" href="{css}">\n</head>\n'
        f"<body>\n{body}\n</body>\n</html>\n"
    )


def _tier_badge(tier: str) -> str:
    return f'<span class="tier tier-{tier}">{tier}</span>'


def covers_main(entry: Entry, accepted: Sequence[str]) -> bool:
    """Whether the entry was flown on all three main ids (the ranking's success is over exactly those)."""
    cells = entry.cells(accepted)
    return all(i in cells for i in MAIN_IDS)


def _ranking_table(
    table_id: str, entries: list[Entry], accepted: Sequence[str], ranked: bool, bold: dict[str, set[str]]
) -> str:
    """One table of entries: a rank column when ``ranked``, bold cells as given per column."""
    columns = [*MAIN_IDS, "main"]
    cells = {e.name: e.cells(accepted) for e in entries}
    head = "".join(f"<th>SR {TRACK_LABELS[i]}</th>" for i in MAIN_IDS)
    rows = []
    for position, entry in enumerate(entries, start=1):
        main = pooled(cells[entry.name])
        tds = [f'<td class="num">{position if ranked else "–"}</td>']
        tds.append(f'<td><a href="entries/{_esc(entry.name)}.html">{_esc(entry.name)}</a><br>'
                   f'<small>{_esc(entry.kind)}, {_esc(entry.meta["obs_mode"])}</small></td>')  # fmt: skip
        for col in columns:
            klass = "num best" if entry.name in bold.get(col, set()) else "num"
            value = main if col == "main" else cells[entry.name].get(col)
            tds.append(f'<td class="{klass}">{_sr_html(value)}</td>')
        lap = _lap_html(main.lap_time_mean, len(main.lap_times)) if main else "–"
        tds.append(f'<td class="num">{lap}</td>')
        covered = sum(i in cells[entry.name] for i in MAIN_IDS)
        seed_set = main.seed_set if main else "–"
        tds.append(f'<td class="num">{covered}/3</td><td>{_esc(seed_set)}</td>')
        steps = entry.meta["training_steps"]
        tds.append(f'<td class="num">{steps:,}</td>')
        rows.append("<tr>" + "".join(tds) + "</tr>")
    return (
        f'<table class="ranking" id="{table_id}">\n<tr><th>#</th><th>entry</th>{head}<th>SR main ids (pooled)</th>'
        "<th>lap time (main ids)</th><th>main ids flown</th><th>seeds</th><th>training steps</th></tr>\n"
        + "\n".join(rows)
        + "\n</table>"
    )


def tier_tables(tier: str, members: list[Entry], accepted: Sequence[str]) -> str:
    """The HTML of one tier: ranked entries (all three main ids), then the unranked ones, bold where separated."""
    if tier == "reference":
        return _ranking_table("table-reference", rank(members, accepted), accepted, ranked=False, bold={})
    full = rank([e for e in members if covers_main(e, accepted)], accepted)
    partial = rank([e for e in members if not covers_main(e, accepted)], accepted)
    cells = {e.name: e.cells(accepted) for e in members}
    # Per-track columns compare every entry of the tier flown on that id; the pooled column only the ranked ones,
    # whose pools are over the same three ids.
    bold = {i: separated_best({e.name: cells[e.name].get(i) for e in members}) for i in MAIN_IDS}
    bold["main"] = separated_best({e.name: pooled(cells[e.name]) for e in full})
    html_parts = []
    if full:
        html_parts.append(_ranking_table(f"ranking-{tier}", full, accepted, ranked=True, bold=bold))
    else:
        html_parts.append('<p class="muted">No entry of this tier was flown on all three main ids: none ranked.</p>')
    if partial:
        html_parts.append(
            "<p><b>Not ranked</b>: flown on fewer than the three main ids (e.g. per-track policies evaluated on their"
            " own track only), so their success over the three ids is unknown. Listed by success on the ids they"
            " were flown on; not comparable with the ranking above.</p>"
        )
        html_parts.append(_ranking_table(f"unranked-{tier}", partial, accepted, ranked=False, bold=bold))
    return "\n".join(html_parts)


def _aggregate_table(entries: list[Entry], data: dict[str, dict[str, Any]]) -> str:
    rows = []
    for entry in entries:
        agg = data[entry.name]["aggregate"]
        if agg is None:
            continue
        seeds = entry.meta["training_seeds"]
        note = "one policy file = one training run" + (f" (training seed {seeds[0]})" if len(seeds) == 1 else "")
        rows.append(
            f"<tr><td>{_esc(entry.name)}</td><td>{_tier_badge(data[entry.name]['tier'])}</td>"
            f'<td class="num">{100 * agg["mean_sr"]:.1f} % <small>[{100 * agg["low"]:.1f}–{100 * agg["high"]:.1f}]'
            f'</small></td><td class="num">{len(agg["ids"])} ids, {agg["episodes"]} episodes</td>'
            f"<td>{_esc(note)}</td></tr>"
        )
    if not rows:
        return '<p class="muted">No entry was evaluated on two or more of the main ids.</p>'
    return (
        '<table id="aggregate">\n<tr><th>entry</th><th>tier</th><th>mean SR over tracks [95 % bootstrap]</th>'
        "<th>evaluated</th><th>what the interval covers</th></tr>\n" + "\n".join(rows) + "\n</table>"
    )


def ranked_summary(entries: Sequence[Entry], accepted: Sequence[str]) -> pd.DataFrame:
    """Every entry's ranked records summarised as ``racebench table`` summarises an evaluation (one agent each)."""
    from racebench.evaluation import summarize

    rows = [
        {"agent": e.name, "privileged": e.tier(accepted) == "reference", "env_id": r["env_id"],
         "success": bool(r["success"]), "lap_time": r["lap_time"]}
        for e in entries
        for r in e.ranked_records(accepted)
    ]  # fmt: skip
    if not rows:
        return pd.DataFrame()
    return summarize(pd.DataFrame(rows))


def paper_table_html(summary: pd.DataFrame, which: str) -> str:
    """Table II or IV of the paper as HTML: the cells of ``racebench table``, bold only where the Wilson interval
    of a non-privileged entry lies entirely above every other non-privileged entry's in the same comparison (a
    track's SR column in II; a row and track in IV). Lap times are never bold: no interval is shown for them."""
    from racebench.tables import TRACK_NAMES, TRACK_ORDER, _agent_label, _lookup, best_separated, table_ii, table_iv

    agents = list(dict.fromkeys(summary["agent"]))
    privileged = {a: bool(summary.loc[summary["agent"] == a, "privileged"].any()) for a in agents}
    learned = [a for a in agents if not privileged[a]]

    def intervals(track: str, variant: str) -> dict[str, tuple[float, float]]:
        rows = {a: _lookup(summary, a, track, variant) for a in learned}
        return {a: (float(r["sr_ci_low"]), float(r["sr_ci_high"])) for a, r in rows.items() if r is not None}

    bold: set[tuple[str, str]] = set()
    if which == "II":
        frame, _ = table_ii(summary, ci=True, lap_time=True)
        for track in TRACK_ORDER:
            bold |= {
                (_agent_label(a, False), f"SR [%] {TRACK_NAMES[track]}")
                for a in best_separated(intervals(track, "default"), lower_is_better=False)
            }
    else:
        frame, _ = table_iv(summary, ci=True)
        for variant in frame.index:
            key = variant.replace("Density ", "Density").replace("Gate ±", "GateShift").removesuffix(" m")
            for track in TRACK_ORDER:
                for a in best_separated(intervals(track, key), lower_is_better=False):
                    bold.add((variant, f"{_agent_label(a, False)} {TRACK_NAMES[track]}"))
    head = "".join(f"<th>{_esc(c)}</th>" for c in frame.columns)
    body = []
    for label, row in frame.iterrows():
        cells = "".join(
            f'<td class="num{" best" if (label, col) in bold else ""}">{_esc(row[col])}</td>' for col in frame.columns
        )
        body.append(f"<tr><th>{_esc(label)}</th>{cells}</tr>")
    return f'<table id="table-{which.lower()}">\n<tr><th></th>{head}</tr>\n' + "\n".join(body) + "\n</table>"


def _paper_tables_section(entries: Sequence[Entry], accepted: Sequence[str]) -> str:
    """The paper's Tables II and IV over every entry's ranked records (Table III holds the ablations)."""
    summary = ranked_summary(entries, accepted)
    parts = ['\n<h2 id="paper-tables">The paper\'s tables</h2>\n<p>The cells of <code>racebench table</code> over'
             " every entry's ranked records: SR in % with the 95 % Wilson interval, n episodes per cell on the entry's"
             " page. Bold only where intervals separate entries (references never bold). Table III (the ablations)"
             " appears here once ablation entries exist.</p>"]  # fmt: skip
    if summary.empty:
        return parts[0] + '<p class="muted">No records.</p>'
    main = summary[summary["variant"] == "default"]
    variants = summary[summary["variant"].str.startswith(("Density", "GateShift"))]
    if not main.empty:
        parts.append("<h3>Table II: lap time (mean over successful laps) and success rate per track</h3>")
        parts.append(paper_table_html(summary, "II"))
    if not variants.empty:
        parts.append("<h3>Table IV: success rate vs obstacle density and gate shift</h3>")
        parts.append(paper_table_html(summary[summary["agent"].isin(set(variants["agent"]))], "IV"))
    return "\n".join(parts)


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


def _improvement_table(entries: list[Entry], accepted: Sequence[str]) -> str:
    """Probability of improvement of each ranked non-reference entry over the next one of its tier."""
    pairs = []
    for tier in (t for t in TIERS if t != "reference"):
        ranked = [e for e in entries if e.tier(accepted) == tier and covers_main(e, accepted)]
        pairs += list(pairwise(ranked))
    rows = []
    for better, worse in pairs:
        result = probability_of_improvement(better.ranked_records(accepted), worse.ranked_records(accepted), MAIN_IDS)
        rows.append(
            f'<tr><td>{_esc(better.name)}</td><td>{_esc(worse.name)}</td><td class="num">{result["p"]:.2f} '
            f"<small>[{result['low']:.2f}–{result['high']:.2f}]</small></td></tr>"
        )
    if not rows:
        return '<p class="muted">Fewer than two ranked entries flown on all three main ids: nothing to compare.</p>'
    return (
        '<table id="improvement">\n<tr><th>entry X</th><th>entry Y (next in X\'s tier)</th>'
        "<th>P(X &gt; Y) [95 % bootstrap]</th></tr>\n" + "\n".join(rows) + "\n</table>"
    )


def _entry_page(entry: Entry, data: dict[str, Any], accepted: Sequence[str], media: str = "") -> str:
    meta = entry.meta
    tier = data["tier"]
    why = {
        "reference": "a privileged built-in (reads the true scene)",
        "verified": "an ONNX policy with records on the maintainers' private seed set",
        "self-reported": "not an ONNX policy evaluated on the maintainers' private seeds",
    }[tier]
    rows = "".join(
        f"<tr><th>{_esc(k)}</th><td>{_esc(', '.join(map(str, v)) if isinstance(v, list) else v)}</td></tr>"
        for k, v in meta.items()
        if k not in ("policy_sha256",)
    )
    rows += f"<tr><th>policy_sha256</th><td><code>{_esc(meta['policy_sha256'])}</code></td></tr>"
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
    for seed_set in sorted({r["seed_set"] for r in records}):
        for env_id, cell in summarize_cells([r for r in records if r["seed_set"] == seed_set]).items():
            laps = np.array(cell.lap_times)
            median = f"{np.median(laps):.2f} s" if len(laps) else "–"
            cell_rows.append(
                f'<tr><td>{_esc(env_id)}</td><td>{_esc(seed_set)}</td><td class="num">{cell.n}</td>'
                f'<td class="num">{_sr_html(cell)}</td><td class="num">{_lap_html(cell.lap_time_mean, len(laps))}'
                f'</td><td class="num">{median}</td></tr>'
            )
    body = (
        f'<p><a href="../index.html">← leaderboard</a></p>\n<h1>{_esc(entry.name)} {_tier_badge(tier)}</h1>\n'
        f'<p class="lead">Tier: {tier}, because it is {why}.</p>\n'
        f"<h2>Metadata</h2>\n<table>{rows}</table>\n"
        '<h2>Every evaluated cell</h2>\n<p class="muted">SR: success rate, 95 % Wilson interval, successes/episodes.'
        " Lap time over successful laps.</p>\n"
        '<table id="cells"><tr><th>env id</th><th>seed set</th><th>n</th><th>SR</th><th>mean lap</th>'
        "<th>median lap</th></tr>\n" + "\n".join(cell_rows) + "\n</table>\n" + media
    )
    return _page(f"{entry.name} · racebench leaderboard", body, "../style.css")


def entry_media(entry: Entry, folder: Path, videos: bool = False, trust_code: bool = False) -> str:
    """Trajectory plots (and, with ``videos``, one episode video) per main id of ``entry``, written into ``folder``;
    return the HTML section that shows them.

    A plot is the paper's Fig. 4 (:func:`racebench.plots.plot_track_3d`) from the trajectories saved with the
    entry's records (``evaluate --save-trajectories``): one scene, the entry's flights in it. A video flies the
    entry's policy on the first public evaluation seed (:func:`racebench.video.render_episode_video`): chase view
    beside the colour-mapped depth image, outcome captioned. Videos are built on demand and not committed.
    """
    from racebench.agents import AgentLoadError
    from racebench.evaluation import EVAL_SEED_BASE
    from racebench.plots import plot_track_3d

    record_dirs = [entry.root / d for d in entry.meta.get("records", [])]
    figures, missing = [], []
    for env_id in MAIN_IDS:
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
        from racebench.video import render_episode_video

        for env_id in MAIN_IDS:
            if any(r["env_id"] == env_id for r in entry.records):
                mp4 = folder / f"{TRACK_LABELS[env_id].replace(' ', '-')}.mp4"
                folder.mkdir(parents=True, exist_ok=True)
                try:
                    render_episode_video(entry.agent_spec, env_id, EVAL_SEED_BASE, mp4, trust_code=trust_code,
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
    """Whether ``records_dir/trajectories`` holds a saved flight of ``env_id``."""
    for path in sorted((records_dir / "trajectories").glob("*.npz")):
        with np.load(path) as data:
            if json.loads(str(data["row"]))["env_id"] == env_id:
                return True
    return False


def build_site(leaderboard: str | Path, out: str | Path, videos: bool = False, trust_code: bool = False) -> Path:
    """Write the site of the entries under ``leaderboard`` into ``out`` (replacing an earlier build); return index."""
    accepted = load_config(leaderboard)["private_salt_sha256"]
    entries = load_entries(leaderboard)
    out = Path(out)
    if (out / "entries").is_dir():
        shutil.rmtree(out / "entries")  # a removed entry must not keep its page
    (out / "entries").mkdir(parents=True, exist_ok=True)
    (out / "style.css").write_text(CSS.lstrip())
    data = {e.name: _entry_data(e, accepted) for e in entries}
    sections = []
    for tier in TIERS:
        members = rank([e for e in entries if data[e.name]["tier"] == tier], accepted)
        sections.append(f"<h2 id=\"tier-{tier}\">{_tier_badge(tier)} {tier.capitalize()}</h2>\n"
                        f"<p>{_esc(TIER_TEXT[tier])}</p>")  # fmt: skip
        if members:
            sections.append(tier_tables(tier, members, accepted))
        elif tier == "verified":
            state = "no maintainer salt is published yet" if not accepted else "no ONNX entry has been verified yet"
            sections.append(f'<p class="note">No verified entries: {state} (results/leaderboard/README.md).</p>')
        else:
            sections.append('<p class="muted">No entries.</p>')
        for entry in members:
            media = entry_media(entry, out / "entries" / entry.name, videos=videos, trust_code=trust_code)
            page = _entry_page(entry, data[entry.name], accepted, media)
            (out / "entries" / f"{entry.name}.html").write_text(page)
    ranked = [e for t in TIERS for e in rank([x for x in entries if data[x.name]["tier"] == t], accepted)]
    blob = json.dumps(
        {"racebench_version": racebench.__version__, "env_version": ENV_VERSION, "entries": data},
        sort_keys=True, allow_nan=False,
    ).replace("</", "<\\/")  # fmt: skip
    body = (
        "<h1>racebench leaderboard</h1>\n"
        f'<p class="lead">{len(entries)} entries · env version {ENV_VERSION} · racebench '
        f"{_esc(racebench.__version__)} · main ids: {', '.join(MAIN_IDS)}</p>\n"
        "<p>Ranking within a tier: the success rate over the three main ids (the mean of the three per-track rates,"
        " so each track weighs the same), then the mean lap time of their successful laps. Entries flown on fewer"
        " of the three are listed unranked below it (success on an id never flown is unknown, not zero)."
        " SR cells: percentage, 95 % Wilson interval,"
        " successes/episodes. <b>Bold</b> only where an entry's interval lies entirely above every other entry's of"
        " its tier in that column (pooled column: every other ranked entry's).</p>\n"
        + "\n".join(sections)
        + '\n<h2 id="aggregate-statistics">Aggregate statistics</h2>\n'
        "<p>Mean over the main ids of the per-track success rate, with a 95 % percentile interval from scipy's"
        f" bootstrap ({BOOTSTRAP_RESAMPLES} resamples of the episodes within each track, i.e. stratified over"
        " tracks). <b>Every entry is a single training run (one training seed)</b>, so these intervals cover the"
        " evaluation scenes only, not the variation between training runs; with several seeds per method they"
        " would be bootstrapped over runs as well (rliable-style). Entries flown on fewer than two main ids are"
        " left out.</p>\n"
        + _aggregate_table(ranked, data)
        + '\n<h3 id="probability-of-improvement">Probability of improvement</h3>\n'
        "<p>P(X &gt; Y): the chance that an episode of X succeeds where one of Y fails, plus half the ties, averaged"
        " over the three main ids (rliable's probability of improvement; Mann–Whitney U / (n·m) per track), between"
        " each ranked entry and the next one of its tier, with a stratified bootstrap interval. With one training"
        " run per entry it compares these two policy files on these scenes, not two training methods.</p>\n"
        + _improvement_table(ranked, accepted)
        + _paper_tables_section(entries, accepted)
        + f'\n<script type="application/json" id="leaderboard-data">{blob}</script>'
    )
    index = out / "index.html"
    index.write_text(_page("racebench leaderboard", body, "style.css"))
    return index
