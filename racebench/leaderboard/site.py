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
generalisation (per-track policies on the other tracks) is an extra column, never the key, and so is robustness
(:mod:`racebench.leaderboard.robustness`: success under the robustness suite's perturbations relative to nominal).
Success rates are shown as percentage, 95 % Wilson interval and ``k/n``; a cell is bold only when its interval lies
entirely above the interval of every other entry of its tier in that column. References (privileged built-ins) are
listed for scale, never ranked or bold.

Aggregate statistics: the rank key with a 95 % percentile interval from :func:`scipy.stats.bootstrap` resampling
episodes within each track (stratified), and rliable's probability of improvement between neighbours of a tier.
Every policy is one training run: the intervals cover evaluation episodes only, and the page says so.
"""

from __future__ import annotations

import json
import os
import shutil
import stat
from pathlib import Path

import racebench
from racebench.envs.registration import ENV_VERSION
from racebench.evaluation.statistics import BOOTSTRAP_RESAMPLES
from racebench.leaderboard.entries import (
    MAIN_IDS,
    TIERS,
    load_config,
    load_entries,
    repo_root,
)
from racebench.leaderboard.pages import _entry_data, _entry_page, _page, entry_media
from racebench.leaderboard.ranking import (
    TIER_TEXT,
    Row,
    _aggregate_table,
    _esc,
    _improvement_table,
    _paper_tables_section,
    _tier_badge,
    above_verified_note,
    entry_row,
    rank,
    tier_tables,
    unseen_section,
)
from racebench.leaderboard.unseen import unseen_rows
from racebench.utils.files import atomic_write

CSS = """
body { font-family: system-ui, -apple-system, "Segoe UI", sans-serif; margin: 2rem auto; max-width: 75rem;
       padding: 0 1rem; color: #1b1f23; line-height: 1.45; }
h1 { margin-bottom: 0.2rem; } h2 { margin-top: 2.2rem; border-bottom: 1px solid #d0d7de; }
p.lead { color: #57606a; margin-top: 0; }
table { border-collapse: collapse; margin: 0.8rem 0; font-size: 0.92rem; }
th, td { border: 1px solid #d0d7de; padding: 0.3rem 0.55rem; text-align: left; vertical-align: top; }
th { background: #f6f8fa; }
td.num { text-align: right; font-variant-numeric: tabular-nums; white-space: nowrap; }
td.budget { white-space: normal; min-width: 6rem; }  /* the hardware line would push the table past the page */
td.key { font-weight: 600; background: #f3f0ff; }
table.ranking td:nth-child(2) { min-width: 18rem; }
td.best { font-weight: 700; background: #eafbea; }
td.drop { font-weight: 700; background: #ffebe9; }
small, .muted { color: #57606a; }
.tier { display: inline-block; padding: 0 0.45rem; border-radius: 0.6rem; font-size: 0.8rem; color: #fff; }
.tier-verified { background: #1a7f37; } .tier-self-reported { background: #9a6700; }
.tier-reference { background: #57606a; }
code { font-size: 0.85rem; word-break: break-all; }
figure { display: inline-block; margin: 0.5rem 1rem 0.5rem 0; } figcaption { color: #57606a; font-size: 0.85rem; }
img, video { max-width: 100%; height: auto; border: 1px solid #d0d7de; }
.note { background: #fff8c5; border: 1px solid #d4a72c; padding: 0.5rem 0.8rem; border-radius: 0.3rem; }
"""


def script_json(text: str) -> str:
    """JSON made safe to embed in a ``<script>`` element: ``<``, ``>`` and ``&`` as JSON escapes (the same data), so
    no text in it (``</script>``, ``<!--``) can end the element or change how the HTML parser reads it."""
    return text.replace("&", "\\u0026").replace("<", "\\u003c").replace(">", "\\u003e")


def check_output_folder(out: Path, root: Path) -> None:
    """Refuse to build into ``out`` if the build could write or delete through a symbolic link: ``out`` or a parent
    of it inside the repository ``root`` is a link, or ``out`` holds a link or anything but folders and regular files
    (a pull request can commit links; the site is written only as regular files inside ``out``)."""
    why = "the site is written only as regular files inside --out; remove it or choose another --out"
    anchors = (Path.cwd(), root.resolve())  # the folders the user chose to work in: trusted, as their parents
    path = Path(os.path.abspath(out))
    inside = [p for p in path.parents if any(p.is_relative_to(a) and p != a for a in anchors)]
    for link in (path, *inside):
        if link.is_symlink():
            raise ValueError(f"{link} is a symbolic link: {why}")
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {str(out)!r} is not a folder")
    for folder, dirs, files in os.walk(out):  # never follows links
        for name in dirs + files:
            path = Path(folder) / name
            mode = path.lstat().st_mode
            if stat.S_ISLNK(mode):
                raise ValueError(f"{path} is a symbolic link: {why}")
            if not (stat.S_ISDIR(mode) or stat.S_ISREG(mode)):
                raise ValueError(f"{path} is not a regular file: {why}")


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
    check_output_folder(out, repo_root(leaderboard))
    if (out / "entries").is_dir():
        shutil.rmtree(out / "entries")  # a removed entry must not keep its page (no link inside: checked above)
    (out / "entries").mkdir(parents=True, exist_ok=True)
    atomic_write(out / "style.css", CSS.lstrip())  # a rename: replaces the file, never writes through a link
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
            if tier == "self-reported":
                sections.append(above_verified_note(list(rows.values())))
        elif tier == "verified":
            sections.append('<p class="note">No verified entries: no signed result checks against the pinned'
                            " maintainers' key (docs/leaderboard.md).</p>")  # fmt: skip
        else:
            sections.append('<p class="muted">No entries.</p>')
        for row in members:
            media = entry_media(row.entry, out / "entries" / row.name, videos=videos, trust_code=trust_code)
            atomic_write(out / "entries" / f"{row.name}.html", _entry_page(row, media))
    data = {r.name: _entry_data(r) for r in ordered}
    blob = json.dumps(
        {"racebench_version": racebench.__version__, "env_version": ENV_VERSION, "entries": data},
        sort_keys=True, allow_nan=False,
    )
    blob = script_json(blob)
    body = (
        "<h1>racebench leaderboard</h1>\n"
        f'<p class="lead">{len(entries)} methods · env version {ENV_VERSION} · racebench '
        f"{_esc(racebench.__version__)} · main ids: {', '.join(MAIN_IDS)}</p>\n"
        "<p>One row per <b>method</b>, as in the paper's Table II: one policy per track (S, 3D Circle, J) or one"
        " policy for all three, each flown on its <b>own</b> track. <b>Rank key</b> (its own column): the mean of"
        " the three own-track success rates, then the mean of the three own-track mean lap times. A method without"
        " all three tracks is listed unranked below its tier. Cross-track success (a per-track policy on the other"
        " tracks) is shown, never ranked, and so is <b>robustness</b>: per track the mean success rate under the nine"
        " perturbations of the robustness suite over the nominal success rate on the same scenes (public seeds),"
        " averaged over the tracks where all nine were flown and the nominal rate is above 0 (each entry's page"
        " has the table). SR cells: percentage, 95 % Wilson interval, successes/episodes."
        " <b>Bold</b> only where a method's interval lies entirely above every other method's of its tier in"
        " that column. The held-out generated tracks have their own ranking (Unseen tracks, below the tiers).</p>\n"
        + "\n".join(sections) + unseen_section(unseen_rows(entries, config, pinned_key_sha256))
        + '\n<h2 id="aggregate-statistics">Aggregate statistics</h2>\n'
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
    atomic_write(index, _page("racebench leaderboard", body, "style.css"))
    return index
