"""An entry's own page of the site: its policies, verification, downloadable data and media (trajectory plots,
videos).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from racebench.agents.base import AgentLoadError
from racebench.evaluation.protocol import EVAL_SEED_BASE, split_env_id
from racebench.evaluation.records import read_trajectories
from racebench.leaderboard import signing
from racebench.leaderboard.entries import (
    MAIN_IDS,
    UNSEEN_ID,
    UNSEEN_KEY,
    Entry,
    _spec_at,
    summarize_cells,
)
from racebench.leaderboard.ranking import TRACK_LABELS, Row, _esc, _lap_html, _sr_html, _tier_badge, aggregate
from racebench.leaderboard.robustness import robustness_data, robustness_section_html
from racebench.leaderboard.unseen import NO_POLICY, UNSEEN_RANKED_EPISODES, UnseenRow, unseen_cell, unseen_row
from racebench.reporting import video
from racebench.reporting.plots import plot_track_3d

PLOT_DPI = 130  # the trajectory figures are committed with the site: ~600 px wide PNGs


def _page(title: str, body: str, css: str) -> str:
    return (
        '<!DOCTYPE html>\n<html lang="en">\n<head>\n<meta charset="utf-8">\n'
        '<meta name="viewport" content="width=device-width, initial-scale=1">\n'
        f'<title>{_esc(title)}</title>\n<link rel="stylesheet" href="{css}">\n</head>\n'
        f"<body>\n{body}\n</body>\n</html>\n"
    )


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
        if row.ranked
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
        "unseen": _unseen_data(row.unseen or unseen_row(entry)),
        "robustness": robustness_data(row.robustness),
    }


def _unseen_data(row: UnseenRow) -> dict[str, Any] | None:
    """The unseen-tracks cell of the embedded data (signed private, else the public ranked count), None without."""
    cell = row.cell
    if cell is None:
        return None
    return {
        "env_id": UNSEEN_ID, "seed_set": cell.seed_set, "n": cell.n, "successes": cell.successes,
        "wilson95": list(cell.interval),
        "lap_time_mean": None if math.isnan(cell.lap_time_mean) else cell.lap_time_mean,
        "ranked": row.ranked, "verification_refused": row.refusal,
    }  # fmt: skip


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
    shown = {k: v for k, v in meta.items() if k not in ("policies", "name", UNSEEN_KEY)}
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
        + "\n"
        + robustness_section_html(row.robustness)
        + '\n<h2>Every evaluated cell</h2>\n<p class="muted">Each policy\'s records: own track or another one'
        " (cross-track generalisation). SR: success rate, 95 % Wilson interval, successes/episodes. Lap time over"
        " successful laps.</p>\n"
        '<table id="cells"><tr><th>policy</th><th>env id</th><th>track</th><th>seed set</th><th>n</th><th>SR</th>'
        "<th>mean lap</th><th>median lap</th></tr>\n" + "\n".join(cell_rows) + "\n</table>\n"
        + unseen_entry_html(row.unseen or unseen_row(entry)) + "\n" + media
    )  # fmt: skip
    return _page(f"{entry.name} · racebench leaderboard", body, "../style.css")


def unseen_entry_html(row: UnseenRow) -> str:
    """An entry page's unseen-tracks section: its policy line, its signed private cell if any and its public cells
    on the held-out tracks."""
    entry = row.entry
    policy = entry.unseen
    parts = ['<h2 id="unseen-tracks">Unseen tracks</h2>']
    if policy is None:
        parts.append(f'<p class="muted">No <code>{UNSEEN_KEY}:</code> policy: not in the unseen-tracks ranking.</p>')
        return "\n".join(parts)
    parts.append(
        f"<p>Policy <code>{_esc(policy.policy)}</code> (sha256 <code>{_esc(policy.sha256)}</code>), records in "
        f"{_esc(', '.join(policy.records_dirs))}: public seeds, not covered by a signature.</p>"
    )
    if row.signed and row.cell is not None:
        lap = _lap_html(row.cell.lap_time_mean, len(row.cell.lap_times))
        parts.append(
            f"<p>{_tier_badge('verified')} Its ONNX file <code>{_esc(policy.onnx)}</code> re-flown "
            f"by the maintainers on {row.cell.n} private seeds, each a track generated from a seed nobody knows "
            f"(signed, <code>verified-unseen.json</code>): <b>{_sr_html(row.cell)}</b>, mean lap {lap}. The ranked "
            "cell.</p>"
        )
    elif row.refusal:
        parts.append(f'<p class="note">Signed result refused: {_esc(row.refusal)}</p>')
    everything, ranked = unseen_cell(entry, None), unseen_cell(entry)
    if everything is None:
        parts.append(f'<p class="note">Its records hold no public episode of {_esc(UNSEEN_ID)}.</p>')
        return "\n".join(parts)
    lines = [(f"the first {UNSEEN_RANKED_EPISODES} seeds (ranked count)", ranked), ("every committed one", everything)]
    rows = "".join(
        f'<tr><td>{_esc(label)}</td><td class="num">{_sr_html(cell)}</td><td class="num">'
        f"{_lap_html(cell.lap_time_mean, len(cell.lap_times)) if cell else NO_POLICY}</td></tr>\n"
        for label, cell in lines
    )
    parts.append(f'<table id="unseen"><tr><th>episodes</th><th>SR</th><th>mean lap</th></tr>\n{rows}</table>')
    return "\n".join(parts)


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
