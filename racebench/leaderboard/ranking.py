"""The leaderboard's rows and tables: one row per entry (its cells, tier and rank key), the ranking, the tier,
aggregate, improvement and paper tables as HTML.
"""

from __future__ import annotations

import functools
import html
import math
from collections.abc import Sequence
from dataclasses import dataclass
from itertools import pairwise
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    import pandas as pd

from racebench.envs.registration import DENSITIES, GATE_SHIFTS
from racebench.evaluation.protocol import TRACK_ORDER
from racebench.evaluation.seeds import public_seeds
from racebench.evaluation.statistics import mean_of_means_interval, probability_of_improvement
from racebench.leaderboard import signing
from racebench.leaderboard.entries import (
    MAIN_IDS,
    TIERS,
    TRACK_MAIN,
    UNSEEN_ID,
    Cell,
    Entry,
    summarize_cells,
)
from racebench.leaderboard.robustness import EntryRobustness, entry_robustness, robustness_column_html
from racebench.leaderboard.signing import VERIFIED_FILE, SignatureError, VerifiedResult
from racebench.leaderboard.unseen import NO_POLICY, UNSEEN_RANKED_EPISODES, UnseenRow, unseen_row
from racebench.reporting.tables import best_separated

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
    ids = [i for i in MAIN_IDS if i in cells]
    if len(ids) < 2:
        return None
    samples = [np.array([float(r["success"]) for r in records if r["env_id"] == i]) for i in ids]
    point, low, high = mean_of_means_interval(samples)
    return {"ids": ids, "mean_sr": point, "low": low, "high": high, "episodes": int(sum(len(s) for s in samples))}


#: The public episodes per own-track main id a self-reported method is ranked on: the first this many seeds of the
#: protocol (``leaderboard add``'s default). A constant of the package, reviewed as code, so that no entry chooses
#: after seeing its results how many of its episodes count: more are shown and never ranked, fewer leave it unranked.
RANKED_EPISODES = 50


@dataclass
class Row:
    """One entry as the site shows it: its tier and the own-track cells it is ranked on."""

    entry: Entry
    tier: str
    cells: dict[str, Cell]  # main id -> the own-track cell (signed if verified, else public)
    verified: VerifiedResult | None = None
    refusal: str | None = None  # why its verified.json was refused (None: none, or accepted)
    short: tuple[str, ...] = ()  # own main ids with fewer public episodes than RANKED_EPISODES (then unranked)
    unseen: UnseenRow | None = None  # its unseen-tracks row (signed private cell or public), shown, never in the key

    @property
    def ranked(self) -> bool:
        """Whether it is ranked: a policy for each track and, unless verified, the protocol's full count on each."""
        return self.entry.complete and not self.short

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

    @functools.cached_property
    def robustness(self) -> EntryRobustness:
        """Its robustness on the suite (:mod:`racebench.leaderboard.robustness`): shown, never part of :meth:`key`."""
        return entry_robustness(self.entry, RANKED_EPISODES)

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
    unseen = unseen_row(entry, config, pinned_key_sha256)
    if entry.privileged:
        return Row(entry, "reference", _public_main_cells(entry), None, refusal, unseen=unseen)
    if verified is not None:
        return Row(entry, "verified", dict(verified.cells), verified, unseen=unseen)
    cells = _public_main_cells(entry, RANKED_EPISODES)
    short = tuple(i for i, cell in cells.items() if cell.n < RANKED_EPISODES)
    return Row(entry, "self-reported", cells, None, refusal, short, unseen)


def check_verified(entry: Entry, config: dict[str, Any], pinned_key_sha256: str | None) -> VerifiedResult:
    """:func:`racebench.leaderboard.signing.check_verified`, against the pinned key unless another is given."""
    return signing.check_verified(entry, config, pinned_key_sha256 or signing.MAINTAINERS_KEY_SHA256)


def _public_main_cells(entry: Entry, episodes: int | None = None) -> dict[str, Cell]:
    """Its own-track public cells on the main ids; with ``episodes``, of the protocol's first that many seeds only."""
    own = entry.own_cells()
    if episodes is not None:
        first = set(public_seeds(episodes))
        records = [r for t in entry.tracks for r in entry.public_records(t) if r["seed"] in first]
        own = summarize_cells([r for r in records if r["env_id"] in MAIN_IDS])
    return {i: own[i] for i in MAIN_IDS if i in own}


def rank(rows: Sequence[Row]) -> list[Row]:
    """Rows in order: complete methods first, then the rank key (success, then lap time), then the name."""

    def key(row: Row) -> tuple[int, float, float, str]:
        sr, lap = row.key()
        return (0 if row.ranked else 1, -sr, lap if not math.isnan(lap) else math.inf, row.name)

    return sorted(rows, key=key)


def _key_html(row: Row) -> str:
    if not row.entry.complete:
        return f"– <small>({len(row.entry.tracks)}/3 tracks)</small>"
    if row.short:
        return f"– <small>(under {RANKED_EPISODES} episodes)</small>"
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
        tds.append(f'<td class="num">{robustness_column_html(row.robustness)}</td>')
        tds.append(f"<td>{_teacher_html(entry)}</td>")
        tds.append(f'<td class="num budget">{_budget_html(entry)}</td>')
        seeds = ", ".join(sorted({c.seed_set for c in row.cells.values()})) or "–"
        tds.append(f"<td>{_esc(entry.meta['obs_mode'])}, {_esc(entry.kind)}<br><small>{_esc(seeds)} seeds</small></td>")
        tds.append(f'<td class="num">{unseen_cell_html(row.unseen or unseen_row(entry))}</td>')
        body.append("<tr>" + "".join(tds) + "</tr>")
    return (
        f'<table class="ranking" id="{table_id}">\n<tr><th>#</th><th>method</th>'
        "<th>rank key <small>(mean own-track SR, then lap)</small></th>"
        f"{head}<th>cross-track SR <small>(other tracks, not ranked)</small></th>"
        "<th>robustness <small>(perturbed / nominal SR, not ranked)</small></th><th>privileged teacher</th>"
        "<th>training budget</th><th>sees, policy files</th><th>SR unseen tracks <small>(own ranking below)</small>"
        "</th></tr>\n" + "\n".join(body) + "\n</table>"
    )


def tier_tables(tier: str, members: list[Row]) -> str:
    """The HTML of one tier: ranked methods (all three tracks), then the unranked ones, bold where separated."""
    if tier == "reference":
        return _ranking_table("table-reference", rank(members), ranked=False, bold={})
    full = rank([r for r in members if r.ranked])
    partial = rank([r for r in members if not r.ranked])
    # Per-track columns compare every entry of the tier flown on that track.
    bold = {i: separated_best({r.name: r.cells.get(i) for r in members}) for i in MAIN_IDS}
    parts = []
    if full:
        parts.append(_ranking_table(f"ranking-{tier}", full, ranked=True, bold=bold))
    else:
        parts.append('<p class="muted">No method of this tier has a policy for all three tracks: none ranked.</p>')
    if partial:
        short = "" if not any(r.short for r in partial) else (
            f", or with fewer than the protocol's {RANKED_EPISODES} public episodes on an own-track main id"
        )
        parts.append(
            f"<p><b>Not ranked</b>: methods without a policy for all three tracks (yet){short}, so their rank key is"
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
        pairs += list(pairwise(r for r in rows if r.tier == tier and r.ranked))
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


#: The paper's Table III: its method and the three ablations of it (its Sec. V-C), plus the [com] variant it also
#: trains; a leaderboard entry is one of them when its name is the config's name.
ABLATION_METHODS: tuple[str, ...] = ("vision-ppo", "vision-no-gru", "vision-no-avoid", "vision-one-step", "vision-com")


def seeds_of(row: Row) -> str:
    """Which seeds a row's ranked cells were flown on: the signed private seeds (verified) or the public ones."""
    return "private (signed)" if row.tier == "verified" else "public"


def above_verified(rows: Sequence[Row]) -> list[str]:
    """The self-reported methods whose rank key (mean own-track success) lies above a verified method's."""
    verified = [r.key()[0] for r in rows if r.tier == "verified"]
    if not verified:
        return []
    return [r.name for r in rows if r.tier == "self-reported" and r.key()[0] > min(verified)]


def above_verified_note(rows: Sequence[Row]) -> str:
    """One line for the site where self-reported methods score above verified ones ("" where none does)."""
    names = above_verified(rows)
    if not names:
        return ""
    return (f'<p class="note">{_esc(", ".join(names))} {"scores" if len(names) == 1 else "score"} above a verified'
            " method on self-reported public-seed records, which nobody has replayed on private seeds; a verified"
            " method's cells are its signed private-seed numbers (different scenes), so the two do not compare"
            " like for like.</p>")  # fmt: skip


def table_iii_html(rows: list[Row]) -> str | None:
    """Table III: own-track success rate per track of ``vision-ppo`` and each ablation entry, in the paper's order,
    with the seeds each row's cells were flown on (:func:`seeds_of`); None until at least one ablation (an entry
    named after an ablation config) is on the board."""
    by_name = {row.name: row for row in rows}
    if not any(name in by_name for name in ABLATION_METHODS[1:]):
        return None
    present = [by_name[name] for name in ABLATION_METHODS if name in by_name]
    bold = {i: separated_best({r.name: r.cells.get(i) for r in present}) for i in MAIN_IDS}
    head = "".join(f"<th>SR [%] {TRACK_LABELS[i]}</th>" for i in MAIN_IDS) + "<th>seeds</th>"
    body = [
        f"<tr><th>{_esc(_label(row))}</th>"
        + "".join(_paper_cell(row.cells.get(i), row.name in bold[i]) for i in MAIN_IDS)
        + f"<td>{_esc(seeds_of(row))}</td></tr>"
        for row in present
    ]
    return f'<table id="table-iii">\n<tr><th></th>{head}</tr>\n' + "\n".join(body) + "\n</table>"


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
        above_verified_note(rows),
        "<h3>Table III: ablations</h3>",
        '<p class="muted">Rows differ in their seeds (column "seeds"): a verified method\'s cells are its signed'
        " private-seed numbers, the others' their public-seed records, so a verified method's cell here can differ"
        " from its committed public-seed evaluation (its page shows both).</p>",
        table_iii_html(rows)
        or '<p class="muted">No ablation entries yet (the paper\'s vision-no-gru, vision-one-step, vision-com and'
        " vision-no-avoid configs): the table appears with them.</p>",
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


def _tier_badge(tier: str) -> str:
    return f'<span class="tier tier-{tier}">{tier}</span>'


def entry_summary(
    leaderboard: str | Path, tiers: tuple[str, ...] = ("verified",)
) -> tuple[pd.DataFrame, dict[str, list[int]]]:
    """Rows like :func:`racebench.evaluation.results.read_summaries`'s of the leaderboard's learned entries of
    ``tiers`` (by default the verified ones): each entry's own-track public-seed cells (each track flown by its own
    policy, as the site ranks self-reported entries and as the references are flown), labelled
    ``<name> (<tier>, public seeds)``. Also the env versions of each entry's records, to check that a figure is of
    one env version (:func:`racebench.evaluation.results.check_one_env_version`)."""
    import pandas as pd

    from racebench.evaluation.protocol import split_env_id
    from racebench.leaderboard.entries import load_config, load_entries

    config = load_config(leaderboard)
    rows, versions = [], {}
    for entry in load_entries(leaderboard):
        tier = entry_row(entry, config).tier
        if tier not in tiers:
            continue
        label = f"{entry.name} ({tier}, public seeds)"
        for env_id, found in entry.own_cells().items():
            track, variant = split_env_id(env_id)
            low, high = found.interval
            rows.append({"agent": label, "privileged": False, "env_id": env_id, "track": track, "variant": variant,
                         "n": found.n, "successes": found.successes, "success_rate": found.success_rate,
                         "sr_ci_low": low, "sr_ci_high": high, "lap_time_mean": found.lap_time_mean})  # fmt: skip
        versions[f"leaderboard entry {entry.name}"] = [int(r["env_version"]) for r in entry.records]
    return pd.DataFrame(rows), versions


# ----------------------------------------------------------------- unseen tracks (racebench.leaderboard.unseen)
def unseen_cell_html(row: UnseenRow) -> str:
    """The main ranking's unseen-tracks column: the success rate (its seeds named), or "—" without a policy."""
    cell = row.cell
    if cell is None:
        return NO_POLICY
    full = row.signed or cell.n >= UNSEEN_RANKED_EPISODES
    short = "" if full else f"<br><small>under {UNSEEN_RANKED_EPISODES} episodes</small>"
    return _sr_html(cell) + f"<br><small>{_esc(row.seeds)} seeds</small>" + short


def unseen_section(rows: Sequence[UnseenRow]) -> str:
    """The site's unseen-tracks ranking (HTML): its own table, after the main ranking (``rows`` in
    :func:`~racebench.leaderboard.unseen.unseen_rows`' order)."""
    bold = separated_best({r.entry.name: r.cell for r in rows if r.ranked})
    body, position = [], 0
    for row in rows:
        position += row.ranked
        policy = row.entry.unseen
        if row.cell is None:
            status = "no unseen-tracks policy" if policy is None else f"no records of {UNSEEN_ID}"
        elif row.reference:
            status = "reference (privileged)"
        else:
            status = "ranked" if row.ranked else f"not ranked: under {UNSEEN_RANKED_EPISODES} episodes"
        if row.refusal:
            status += f"; signed result refused: {row.refusal}"
        lap = _lap_html(row.cell.lap_time_mean, len(row.cell.lap_times)) if row.cell else NO_POLICY
        klass = "num best" if row.entry.name in bold else "num"
        body.append(
            f'<tr><td class="num">{position if row.ranked else "–"}</td>'
            f'<td><a href="entries/{_esc(row.entry.name)}.html">{_esc(row.entry.name)}</a></td>'
            f'<td class="{klass}">{_sr_html(row.cell) if row.cell else NO_POLICY}</td><td class="num">{lap}</td>'
            f"<td>{_esc(row.seeds) if row.cell else NO_POLICY}</td>"
            f"<td>{f'<code>{_esc(policy.policy)}</code>' if policy else NO_POLICY}</td>"
            f"<td>{_teacher_html(row.entry)}</td><td>{_esc(status)}</td></tr>"
        )
    return (
        '\n<h2 id="unseen-tracks">Unseen tracks</h2>\n'
        f"<p>The paper's open problem: one policy per method flown on {UNSEEN_RANKED_EPISODES} held-out generated "
        f"tracks (<code>{UNSEEN_ID}</code>: evaluation episode <i>i</i> flies held-out track <i>i</i> mod 100, with "
        "the paper's obstacles), named under <code>unseen:</code> in the entry. Its own ranking, by success rate, then"
        f" mean lap time, on the first {UNSEEN_RANKED_EPISODES} public seeds, or, where the maintainers signed the"
        " line's ONNX file on private seeds (<code>verified-unseen.json</code>), on those: each private episode flies"
        " a track generated from a seed nobody knows (column \"seeds\"). It never changes the ranking above; a"
        " method's per-track signature does not cover this line. Bold: an interval above every other ranked"
        " method's. A method without such a policy shows —.</p>\n"
        '<table class="ranking" id="ranking-unseen">\n<tr><th>#</th><th>method</th><th>SR held-out tracks</th>'
        "<th>mean lap</th><th>seeds</th><th>policy</th><th>privileged teacher</th><th>status</th></tr>\n"
        + "\n".join(body)
        + "\n</table>"
    )
