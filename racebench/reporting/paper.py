"""The paper's Tables II, III and IV and its claims, regenerated from the training campaigns' committed evaluations.

``racebench paper-tables`` (:func:`write_report`) reads, from a repository checkout and without training or flying
anything, for each campaign (:mod:`racebench.reporting.campaigns`: campaign 1, ``campaign-4m``, env version 2;
campaign 2, ``campaign-2``, env version 3):

* the campaign's committed runs (``<runs>/<config>-<track>-seed<k>/eval``: each run's final policy on its own
  track's nine ids, as its sweep file plans them), plus its extra runs (campaign 1: the A/B runs of ``vision-ppo``
  on S, ``baselines/experiments/ab-fast-update``, training seeds 1 and 2, same config and budget);
* beyond the paper, the teacher–student policies ``vision-distill`` and ``vision-distill-ppo``
  (``<students>/<name>-<track>/eval``), each counted on its own track only;
* the references: the floors ``follow`` and ``hover`` and the privileged planners (``<references>/<agent>``);
* two lap times no policy is measured against, shown under their names in Table II and the README block: the
  **lap-time lower bound** (:mod:`racebench.envs.lap_bound`: no lap can be faster) and **planner-fast's
  line at full thrust** (its racing line timed as a point mass at the airframe's full thrust, measured on the
  campaign's env version: :data:`LINE_TIMES`; that one line's limit, not a bound);

where ``<students>`` and ``<references>`` hold those folders as flown on the campaign's env version (campaign 1:
``results/env-v2``, kept as history; campaign 2: the students' ``eval/`` beside their checkpoints and
``results/<agent>``). A report never mixes env versions: :func:`load_episodes` refuses records of two, and a
campaign's records must be of its own version.

Per campaign it writes, into ``<out>/<the campaign's folder>`` (campaign 1: ``results/`` itself; campaign 2:
``results/campaign-2/``), ``table_ii``, ``table_iii`` and ``table_iv`` as Markdown, CSV and LaTeX, ``at_a_glance.md``
(the README's results block; the README shows the block of the campaign :func:`readme_campaign` names) and, from
each committed run's ``validation_curve.csv``, the learning curves ``figures/learning_curves.png`` with their CSV;
and ``<out>/claims.md``: every campaign's claims judged by its own decision rule (committed in its sweep file before
its first run, :func:`judge_claims`), side by side. Every cell puts the paper's number beside ours (``72 [63–80] ·
paper 100``); a row of several training seeds shows their mean success rate and the range over the seeds; a run not
committed yet leaves its cells '–'.

The validation curves behind the learning-curve figure are flown by :mod:`racebench.reporting.validation`.
"""

from __future__ import annotations

import json
import math
import os
import re
from dataclasses import dataclass
from pathlib import Path

import pandas as pd

from racebench.envs.lap_bound import env_lap_time_bound
from racebench.envs.registration import DENSITIES, ENV_VERSION, GATE_SHIFTS
from racebench.evaluation.protocol import TRACK_ORDER, env_id_of, split_env_id
from racebench.evaluation.results import check_one_env_version, load_records
from racebench.reporting.campaigns import (  # noqa: F401 (re-exported)
    CAMPAIGN_1,
    CAMPAIGNS,
    Campaign,
    campaign_steps,
    find_campaign,
    readme_campaign,
    run_folders,
    run_set,
)
from racebench.reporting.cells import Cell, cell  # noqa: F401 (re-exported)
from racebench.reporting.claims import (  # noqa: F401 (re-exported)
    ALPHA,
    FLYING_START,
    Claim,
    ClaimsSection,
    claims_markdown,
    claims_page,
    difference_claim,
    flying_start_claim,
    judge_claims,
    one_step_fails,
    trend_claim,
)
from racebench.reporting.paper_figures import (  # noqa: F401 (re-exported)
    FIGURE_FORMATS,
    TABLE_IV_FIGURES,
    table_iv_figure,
    write_table_iv_figures,
)
from racebench.reporting.paper_numbers import PAPER_LAP_TIME, PAPER_SUCCESS, PAPER_VARIANTS  # noqa: F401 (re-exported)
from racebench.reporting.tables import TRACK_NAMES, render
from racebench.reporting.validation import learning_curves
from racebench.utils.files import atomic_write

CAMPAIGN = CAMPAIGN_1.runs  # the default campaign: campaign 1
#: The reference and teacher–student evaluations on campaign 1's env version (2).
REFERENCES = CAMPAIGN_1.references
BUDGET_STEPS = 4_000_000  # a campaign's steps per run where its sweep file does not say (both campaigns: 4 M)
PAPER_STEPS = 100_000_000
# Rows and their kinds: the paper's configs, racebench's teacher-student methods, floors, privileged references.
TABLE_II_ROWS: tuple[tuple[str, str], ...] = (
    ("vision-ppo", "paper"), ("state-ppo", "paper"), ("vision-com", "paper"),
    ("vision-distill", "beyond the paper"), ("vision-distill-ppo", "beyond the paper"),
    ("follow", "floor"), ("hover", "floor"), ("planner", "privileged"), ("planner-fast", "privileged"),
)  # fmt: skip
TABLE_III_ROWS: tuple[str, ...] = ("vision-ppo", "vision-no-gru", "vision-no-avoid", "vision-one-step")
# Lap times no policy is measured against (lap_time_references): their row names, and the file with the line's.
LOWER_BOUND = "lap-time lower bound"
LINE_AT_FULL_THRUST = "planner-fast's line at full thrust"
#: Per env version, the file of planner-fast's line at full thrust on its scenes (``scripts/planner_line_times.py``):
#: the line runs between that version's obstacles, so a campaign's table takes its own version's.
LINE_TIMES: dict[int, Path] = {
    2: Path("baselines/experiments/planner_fast_line_times.txt"),
    3: Path("baselines/experiments/planner_fast_line_times_env-v3.txt"),
}
LINE_TIMES_COLUMN = "planner-fast's line at full thrust (s)"


@dataclass(frozen=True)
class Source:
    """One evaluation folder feeding the report: a method's policy (one training seed) or a reference agent."""

    method: str
    folder: Path
    training_seed: int | None = None  # None: not trained (references) or a single committed policy
    track: str | None = None  # a per-track policy: only its own track's episodes count


def discover_sources(
    root: str | Path = ".", campaign: str | Path | Campaign = CAMPAIGN_1, references: str | Path | None = None
) -> list[Source]:
    """Every evaluation folder the report of ``campaign`` (:func:`find_campaign`: a name or a run folder;
    ``references`` replaces its built-ins' folder) reads under the checkout ``root`` (see the module docstring)."""
    root, campaign = Path(root), find_campaign(campaign, references)
    sources = [Source(run.config, folder / "eval", run.seed, run.track)
               for run, folder in run_folders(root, campaign).items()]  # fmt: skip
    for method in ("vision-distill", "vision-distill-ppo"):
        for track in TRACK_ORDER:
            folder = root / campaign.students / f"{method}-{track}" / "eval"
            if (folder / "summary.csv").is_file():
                sources.append(Source(method, folder, None, track))
    for agent in ("follow", "hover", "planner", "planner-fast"):
        if (root / campaign.references / agent / "summary.csv").is_file():
            sources.append(Source(agent, root / campaign.references / agent))
    return sources


def load_episodes(sources: list[Source]) -> pd.DataFrame:
    """The validated episodes of ``sources``: method, training_seed, env_id, track, variant, seed, success, lap_time
    (a per-track policy's episodes on other tracks left out: the paper flies each policy on its own track)."""
    frames = []
    loaded = [(source, load_records(source.folder, strict=True)) for source in sources]  # a dropped record: error
    version = check_one_env_version({str(source.folder): records["env_version"] for source, records in loaded})
    for source, records in loaded:
        if records.empty:
            continue
        parts = [split_env_id(env_id) for env_id in records["env_id"]]
        frame = pd.DataFrame(
            {
                "method": source.method,
                "training_seed": -1 if source.training_seed is None else source.training_seed,
                "env_id": records["env_id"],
                "track": [track for track, _ in parts],
                "variant": [variant for _, variant in parts],
                "seed": records["seed"].astype(int),
                "success": records["success"].astype(bool),
                "lap_time": records["lap_time"].astype(float),
            }
        )
        frames.append(frame if source.track is None else frame[frame["track"] == source.track])
    columns = ["method", "training_seed", "env_id", "track", "variant", "seed", "success", "lap_time"]
    episodes = pd.concat(frames, ignore_index=True) if frames else pd.DataFrame(columns=columns)
    episodes.attrs["env_version"] = version  # the one env version of every record read (None without any)
    return episodes


def lap_time_references(root: str | Path = ".", env_version: int | None = ENV_VERSION) -> dict[str, dict[str, float]]:
    """Per track, the two reference lap times of the main id: :data:`LOWER_BOUND` (computed: no lap can be faster,
    ``docs/evaluation.md``; obstacles never enter it) and :data:`LINE_AT_FULL_THRUST` on ``env_version``'s scenes
    (read from its committed :data:`LINE_TIMES` file; absent, '–' in the tables, when there is none: a line measured
    between another version's obstacles is never shown). A file with an ``env_version`` column must name that
    version."""
    references: dict[str, dict[str, float]] = {
        LOWER_BOUND: {track: env_lap_time_bound(env_id_of(track)) for track in TRACK_ORDER},
        LINE_AT_FULL_THRUST: {},
    }
    path = Path(root) / LINE_TIMES[env_version] if env_version in LINE_TIMES else None
    if path is not None and path.is_file():
        frame = pd.read_csv(path, skipinitialspace=True)
        if "env_version" in frame and set(frame["env_version"].astype(int)) != {env_version}:
            found = sorted(set(frame["env_version"].astype(int)))
            raise ValueError(f"{path}: measured on env version {found}, listed for env version {env_version}")
        for env_id, value in zip(frame["env_id"], frame[LINE_TIMES_COLUMN], strict=True):
            track, variant = split_env_id(env_id)
            if variant == "default" and track in TRACK_ORDER:
                references[LINE_AT_FULL_THRUST][track] = float(value)
    return references


def _reference_text(name: str, seconds: float | None) -> str:
    """A reference lap time: the bound to its physics tick (5 ms), the line's as committed (10 ms)."""
    return "–" if seconds is None else f"{seconds:.3f}" if name == LOWER_BOUND else f"{seconds:.2f}"


def _csv_row(table: str, row: str, track: str, variant: str, found: Cell | None, paper_sr, paper_lt) -> dict:
    return {
        "table": table, "row": row, "track": track, "variant": variant,
        "seeds": None if found is None else found.seeds, "n": None if found is None else found.n,
        "success_rate": None if found is None else round(found.success_rate, 4),
        "low": None if found is None else round(found.low, 4), "high": None if found is None else round(found.high, 4),
        "lap_time_mean": None if found is None or not math.isfinite(found.lap_time) else round(found.lap_time, 3),
        "paper_success_rate": paper_sr, "paper_lap_time": paper_lt,
    }  # fmt: skip


def table_ii(
    episodes: pd.DataFrame, references: dict[str, dict[str, float]] | None = None
) -> tuple[pd.DataFrame, list[dict]]:
    """Table II: lap time and success rate per track (own-track main ids), one row per method; then the reference
    lap times (:func:`lap_time_references`), lap time only."""
    display, rows = {}, []
    for method, kind in TABLE_II_ROWS:
        label = method if kind == "paper" else f"{method} ({kind})"
        line = {}
        for part in ("LT [s]", "SR [%]"):
            for track in TRACK_ORDER:
                found = cell(episodes, method, env_id_of(track))
                lap = part == "LT [s]"
                paper = (PAPER_LAP_TIME if lap else PAPER_SUCCESS).get(method, {}).get(track)
                line[f"{part} {TRACK_NAMES[track]}"] = "–" if found is None else found.text(paper, lap)
                if not lap:
                    rows.append(_csv_row("II", method, track, "default", found, paper,
                                         PAPER_LAP_TIME.get(method, {}).get(track)))  # fmt: skip
        display[label] = line
    for name, per_track in (references or {}).items():
        line = {f"LT [s] {TRACK_NAMES[t]}": _reference_text(name, per_track.get(t)) for t in TRACK_ORDER}
        display[f"{name} (reference)"] = {**line, **{f"SR [%] {TRACK_NAMES[t]}": "–" for t in TRACK_ORDER}}
        for track in TRACK_ORDER:
            row = _csv_row("II", name, track, "default", None, None, None)
            seconds = per_track.get(track)
            rows.append({**row, "lap_time_mean": None if seconds is None else round(seconds, 3)})
    return pd.DataFrame.from_dict(display, orient="index"), rows


def table_iii(episodes: pd.DataFrame) -> tuple[pd.DataFrame, list[dict]]:
    """Table III: success rate per track of the full method and its three ablations."""
    display, rows = {}, []
    for method in TABLE_III_ROWS:
        line = {}
        for track in TRACK_ORDER:
            found = cell(episodes, method, env_id_of(track))
            paper = PAPER_SUCCESS[method][track]
            line[f"SR [%] {TRACK_NAMES[track]}"] = "–" if found is None else found.text(paper)
            rows.append(_csv_row("III", method, track, "default", found, paper, None))
        display[method] = line
    return pd.DataFrame.from_dict(display, orient="index"), rows


def table_iv(episodes: pd.DataFrame, method: str = "vision-ppo") -> tuple[pd.DataFrame, list[dict]]:
    """Table IV: ``method``'s success rate per track against obstacle density and gate shift."""
    variants = [(f"density {d}", f"Density{d}") for d in DENSITIES]
    variants += [(f"gate ±{s} m", f"GateShift{s}") for s in GATE_SHIFTS]
    display, rows = {}, []
    for label, variant in variants:
        line = {}
        for track in TRACK_ORDER:
            found = cell(episodes, method, env_id_of(track, variant))
            paper = PAPER_VARIANTS[variant][track]
            line[f"SR [%] {TRACK_NAMES[track]}"] = "–" if found is None else found.text(paper)
            rows.append(_csv_row("IV", method, track, variant, found, paper, None))
        display[label] = line
    return pd.DataFrame.from_dict(display, orient="index"), rows


#: The window of a run's final training success: one rollout's rate is a handful of episodes (a run's last row
#: can read 0 % between rows of 100 %), so the rate is pooled over the episodes of its last 200k steps.
FINAL_WINDOW_STEPS = 200_000


def final_training_success(progress: pd.DataFrame) -> float | None:
    """Training success over the last :data:`FINAL_WINDOW_STEPS` steps of ``progress.csv``: each row's rate
    weighted by the episodes it ended (``episodes`` is cumulative); None without rows."""
    rows = progress.dropna(subset=["success_rate"])
    if rows.empty:
        return None
    ended = rows["episodes"].diff().fillna(rows["episodes"].iloc[0]).clip(lower=0)
    window = rows["timesteps"] > rows["timesteps"].iloc[-1] - FINAL_WINDOW_STEPS
    weights, rates = ended[window], rows["success_rate"][window]
    return float(rates.mean()) if weights.sum() == 0 else float((rates * weights).sum() / weights.sum())


def budget_note(root: Path, campaign: str | Path | Campaign = CAMPAIGN_1, steps: int = BUDGET_STEPS) -> str:
    """Where the budget (``steps`` per run) is the likely reason: each committed run's final curriculum level and its
    training success over the last :data:`FINAL_WINDOW_STEPS` steps (the runs in the campaign's folder)."""
    rows = []
    campaign = find_campaign(campaign)
    folders = [f for f in run_folders(root, campaign).values() if f.parent == Path(root) / campaign.runs]
    for summary_path in sorted(folder / "summary.json" for folder in folders):
        summary = json.loads(summary_path.read_text())
        progress = summary_path.parent / "progress.csv"
        final = final_training_success(pd.read_csv(progress)) if progress.is_file() else None
        rows.append(
            f"{summary_path.parent.name}: level {summary.get('level')}, training success over its last "
            f"{FINAL_WINDOW_STEPS / 1e3:.0f}k steps " + ("–" if final is None else f"{100 * final:.0f} %")
        )
    share = 100 * steps / PAPER_STEPS
    head = (
        f"Budget: {steps / 1e6:.0f} M environment steps per run, {share:.0f} % of the paper's "
        f"{PAPER_STEPS / 1e6:.0f} M. A claim that does not hold here may hold at the paper's budget: a run still "
        "improving at its end (final level below 3, or training success below the 80 % bar) points to the budget."
    )
    return head + ("\n\n" + "\n".join(f"- {row}" for row in rows) if rows else "")


# ------------------------------------------------------------------------------------------------------- output
def provenance(
    episodes: pd.DataFrame, campaign: str | Path | Campaign = CAMPAIGN, runs: tuple[int, int] | None = None
) -> str:
    """Which campaign and env version a report's numbers are of, as one sentence; with ``runs`` (committed,
    planned), how many of its runs a partial campaign has committed."""
    version = episodes.attrs.get("env_version")
    name = campaign.name if isinstance(campaign, Campaign) else Path(campaign).name
    partial = "" if runs is None or runs[0] >= runs[1] else f" ({runs[0]} of {runs[1]} runs committed)"
    return f"Campaign `{name}`{partial}, env version {version if version is not None else '–'}."


def caption(
    which: str, episodes: pd.DataFrame, campaign: str | Path | Campaign = CAMPAIGN,
    runs: tuple[int, int] | None = None, steps: int = BUDGET_STEPS,
) -> str:  # fmt: skip
    """A table's caption: what it shows, the campaign (with ``runs``: how many of its runs are in) and env version,
    the budget (``steps`` per run) and the episodes per cell."""
    what = {
        "II": "Table II: lap time (mean of successful laps) and success rate per track, each policy on its own track",
        "III": "Table III: success rate of vision-ppo and its ablations per track",
        "IV": "Table IV: vision-ppo's success rate against obstacle density and gate shift",
    }[which]
    share = 100 * steps / PAPER_STEPS
    n = "100 episodes per main-id cell, 50 per density or gate-shift cell (references: 50 and 10)"
    lap_references = (
        f" Reference lap times: the {LOWER_BOUND} (no lap can be faster: a flight from rest at full thrust over the "
        f"straight gate-to-gate distance, docs/evaluation.md) and {LINE_AT_FULL_THRUST} (its racing line timed as a "
        f"point mass at full thrust; that one line's limit, not a bound)."
        if which == "II"
        else ""
    )
    return (
        f"{what}. {provenance(episodes, campaign, runs)} Trained configs: {steps / 1e6:.0f} M steps per run "
        f"({share:.0f} % of the paper's 100 M); "
        f"{n}; SR [95 % Wilson] for one training seed, the mean (range over seeds) for several; "
        f"'· paper' the paper's number (10 trials).{lap_references}"
    )


def method_notes(sweep: str | Path | None = CAMPAIGN_1.sweep, steps: int = BUDGET_STEPS) -> dict[str, tuple[str, str]]:
    """Per README row, its budget per track and the command that reproduces it (the campaign's ``sweep`` file)."""
    train = "–" if sweep is None else f"`racebench sweep {Path(sweep).as_posix()}`"
    students = "`racebench sweep baselines/sweeps/teacher-student.yaml`"
    return {
        "vision-ppo": (f"{steps / 1e6:g} M PPO steps", train),
        "state-ppo": (f"{steps / 1e6:g} M PPO steps", train),
        "vision-distill": ("0.5 M DAgger steps", students),
        "vision-distill-ppo": ("0.5 M DAgger + 2 M PPO steps", students),
        "planner-fast": ("none (privileged: reads the true scene)", "`racebench evaluate --agent planner-fast`"),
    }


def at_a_glance(
    episodes: pd.DataFrame, references: dict[str, dict[str, float]] | None = None,
    campaign: str | Path | Campaign = CAMPAIGN, runs: tuple[int, int] | None = None, steps: int = BUDGET_STEPS,
) -> str:  # fmt: skip
    """The README's results block: the paper's method and its state-based baseline as trained here, each below the
    paper's numbers, the best racebench method (highest mean own-track success of the teacher-student rows) and the
    privileged reference, per track; then the reference lap times (:func:`lap_time_references`), when given.
    ``campaign`` (:func:`find_campaign`) names the sweep file that reproduces the trained rows, ``runs`` how many of its
    runs are in, ``steps`` its budget per run."""
    found = find_campaign(campaign)
    notes = method_notes(found.sweep, steps)
    table = (Path("results") / found.out / "table_ii.csv").as_posix()  # the campaign's own Table II

    def track_cells(method: str) -> list[str]:  # one format for every row: "SR [low–high] %, lap"
        found = [cell(episodes, method, env_id_of(track)) for track in TRACK_ORDER]
        return ["–" if c is None else f"{100 * c.success_rate:.0f} [{100 * c.low:.0f}–{100 * c.high:.0f}] %, "
                f"{lap_text(c)}" for c in found]  # fmt: skip

    def seeds_note(method: str) -> str:  # what the brackets of the row are: a Wilson interval or a seed range
        found = [cell(episodes, method, env_id_of(track)) for track in TRACK_ORDER]
        seeds = {TRACK_NAMES[t]: c.seeds for t, c in zip(TRACK_ORDER, found, strict=True) if c is not None}
        if not seeds or max(seeds.values()) == 1:
            return ""
        if len(set(seeds.values())) == 1:
            return f" (mean [range] of {next(iter(seeds.values()))} training seeds)"
        return " (mean [range] of " + ", ".join(f"{k} seeds on {t}" for t, k in seeds.items()) + ")"

    def lap_text(c: Cell) -> str:
        return f"{c.text(lap=True)} s" if math.isfinite(c.lap_time) else "no lap"

    def paper_cells(method: str) -> list[str]:
        return [f"{PAPER_SUCCESS[method][t]} %, {PAPER_LAP_TIME[method][t]} s" for t in TRACK_ORDER]

    def mean_rate(method: str) -> float:
        found = [cell(episodes, method, env_id_of(track)) for track in TRACK_ORDER]
        return sum(c.success_rate for c in found if c is not None) / len(TRACK_ORDER)

    best = max(("vision-distill", "vision-distill-ppo"), key=mean_rate)
    rows = [
        ("paper: vision-based (ours), 10 trials", paper_cells("vision-ppo"), "100 M PPO steps", "–"),
        (f"`vision-ppo`: the paper's method, trained here{seeds_note('vision-ppo')}", track_cells("vision-ppo"),
         *notes["vision-ppo"]),
        ("paper: state-based (ours), 10 trials", paper_cells("state-ppo"), "100 M PPO steps", "–"),
        (
            f"`state-ppo`: the paper's method without depth, trained here{seeds_note('state-ppo')}",
            track_cells("state-ppo"),
            *notes["state-ppo"],
        ),
        (f"`{best}`: best racebench method{seeds_note(best)}", track_cells(best), *notes[best]),
        ("`planner-fast` (privileged reference)", track_cells("planner-fast"), *notes["planner-fast"]),
    ]
    reference_rows = {
        LOWER_BOUND: (
            "lap-time lower bound: no lap can be faster ([derivation](docs/evaluation.md#the-lap-time-lower-bound))",
            "–",
            "computed (`racebench.envs.lap_bound`)",
        ),
        LINE_AT_FULL_THRUST: (
            "planner-fast's line at full thrust: a point mass on that one line (not a bound)",
            "–",
            "`python scripts/planner_line_times.py`",
        ),
    }
    for name, per_track in (references or {}).items():
        cells = [f"{_reference_text(name, per_track.get(t))} s" if t in per_track else "–" for t in TRACK_ORDER]
        rows.append((reference_rows[name][0], cells, *reference_rows[name][1:]))
    names = " | ".join(TRACK_NAMES[t] for t in TRACK_ORDER)
    lines = [f"| method | {names} | budget per track | reproduce |", "| --- | --- | --- | --- | --- | --- |"]
    lines += [f"| {name} | {' | '.join(cells)} | {budget} | {command} |" for name, cells, budget, command in rows]
    lines += [
        "",
        "Success rate [95 % Wilson interval] on 50–100 unseen evaluation scenes of each track's main id (n per cell: "
        f"[`{table}`]({table})); a row of several training seeds (its name says how many) "
        "gives their mean success rate [the lowest–highest seed's], on the public evaluation seeds (the leaderboard "
        "site ranks a verified method on private seeds instead), and mean lap "
        "time of the successful laps; one policy per track. '–' marks a run of the campaign not yet committed. "
        "The last two rows are lap times, not policies: the lower bound below which record validation refuses a lap, "
        "and planner-fast's racing line flown at the airframe's full thrust (the fastest that line allows). "
        f"{provenance(episodes, campaign, runs)} Generated by `racebench paper-tables` (no training); "
        "Tables II–IV, the paper's claims tested and the learning curves: [`results/`](results/README.md).",
    ]
    return "\n".join(lines) + "\n"


def relink(markdown: str, source: str | Path, target: str | Path) -> str:
    """``markdown``'s relative links, written for a page in folder ``source``, rewritten for a page in ``target``.

    The at-a-glance block's links are the README's (from the repository root); its copy ``results/at_a_glance.md``
    needs them from ``results/``. Links with a scheme (``https:``) and same-page anchors are left as they are.
    """

    def move(match: re.Match) -> str:
        link = match.group(1)
        if re.match(r"[a-z]+:", link) or link.startswith("#"):
            return match.group(0)
        path, hash_, anchor = link.partition("#")
        moved = os.path.relpath(Path(source).resolve() / path, Path(target).resolve())
        return f"]({Path(moved).as_posix()}{'/' if path.endswith('/') else ''}{hash_}{anchor})"

    return re.sub(r"\]\(([^)\s]+)\)", move, markdown)


README_BEGIN = "<!-- results-at-a-glance:begin -->"
README_END = "<!-- results-at-a-glance:end -->"


def replace_readme_block(readme: str, block: str) -> str:
    """``readme`` with the text between the results-at-a-glance markers replaced by ``block``."""
    start, end = readme.find(README_BEGIN), readme.find(README_END)
    if start < 0 or end < start:
        raise ValueError(f"README has no {README_BEGIN} ... {README_END} block")
    return readme[: start + len(README_BEGIN)] + "\n" + block + readme[end:]


def campaign_episodes(root: Path, campaign: Campaign) -> pd.DataFrame:
    """:func:`load_episodes` of ``campaign``'s sources, refused if they are not of the campaign's env version."""
    episodes = load_episodes(discover_sources(root, campaign))
    version = episodes.attrs.get("env_version")
    if campaign.env_version is not None and version not in (None, campaign.env_version):
        raise ValueError(f"{campaign.name} is of env version {campaign.env_version}, but its records under {root} are "
                         f"of env version {version}: a table is of one env version")  # fmt: skip
    return episodes


def claims_section(root: Path, campaign: Campaign, episodes: pd.DataFrame) -> ClaimsSection:
    """``campaign``'s claims judged by its own rule (the flying-start hypothesis where its sweep file plans the
    flying runs), with its budget note: its part of ``claims.md``."""
    runs, steps = run_set(root, campaign), campaign_steps(root, campaign)
    flying = runs is not None and any(run.config == FLYING_START[0] for run in runs.planned)
    return ClaimsSection(
        campaign.title, campaign.name, campaign.env_version or episodes.attrs.get("env_version"),
        campaign.distribution, "its sweep file" if campaign.sweep is None else campaign.sweep.as_posix(), steps,
        None if runs is None else (len(runs.committed), len(runs.planned)),
        judge_claims(episodes, runs, flying_start=flying), budget_note(root, campaign, steps),
    )  # fmt: skip


def write_campaign(
    root: Path, out: Path, campaign: Campaign, episodes: pd.DataFrame, links_from: Path | None = None
) -> tuple[list[Path], str]:
    """Write ``campaign``'s tables, ``at_a_glance.md``, learning curves and Table IV figures into ``out``; return the
    files written and the README block (its links from the root; ``at_a_glance.md``'s rewritten for ``out``, or for
    ``links_from``: a copy made elsewhere to compare with the committed one)."""
    out.mkdir(parents=True, exist_ok=True)
    runs, steps = run_set(root, campaign), campaign_steps(root, campaign)
    counts = None if runs is None else (len(runs.committed), len(runs.planned))
    version = campaign.env_version or episodes.attrs.get("env_version")
    references = lap_time_references(root, version)
    written = []
    for which, build in (("II", table_ii), ("III", table_iii), ("IV", table_iv)):
        frame, rows = build(episodes, references) if which == "II" else build(episodes)
        stem = out / f"table_{which.lower()}"
        text = caption(which, episodes, campaign.runs, counts, steps)
        table = pd.DataFrame(rows)
        if which == "II":  # its reference rows have no counts: keep the counts integers
            table[["seeds", "n"]] = table[["seeds", "n"]].astype("Int64")
        outputs = {".md": render(frame, set(), "md", text), ".tex": render(frame, set(), "latex", text),
                   ".csv": table.to_csv(index=False)}  # fmt: skip
        for suffix, content in outputs.items():
            atomic_write(stem.with_suffix(suffix), content)
            written.append(stem.with_suffix(suffix))
    block = at_a_glance(episodes, references, campaign, counts, steps)  # its links are the README's, from the root
    atomic_write(out / "at_a_glance.md", relink(block, root, out if links_from is None else links_from))
    written.append(out / "at_a_glance.md")
    committed = {f.name for f in run_folders(root, campaign).values() if f.parent == root / campaign.runs}
    if learning_curves(root, out, campaign.runs, committed, counts) is not None:
        written += [out / "learning_curves.csv", *(out / "figures" / f"learning_curves.{f}" for f in FIGURE_FORMATS)]
    written += write_table_iv_figures(episodes, out, episodes.attrs.get("env_version"), campaign.runs)
    return written, block


def write_report(
    root: str | Path = ".",
    out: str | Path = "results",
    readme: str | Path | None = "README.md",
    campaign: str | Path | Campaign | None = None,
    references: str | Path | None = None,
    links_from: str | Path | None = None,
) -> list[Path]:
    """Write every registered campaign's report (or only ``campaign``'s: a name or a run folder,
    :func:`find_campaign`, with ``references`` replacing its built-ins' folder) under the results folder ``out``:
    each campaign's tables, ``at_a_glance.md``, learning curves and Table IV figures into its own folder
    (:func:`write_campaign`), and ``claims.md`` with every registered campaign's verdicts side by side (another
    sweep's run folder: its own, in its own folder); update the README's results block when the campaign it shows
    (:func:`readme_campaign`) is written. ``links_from``: the results folder ``out`` stands for, under ``root`` (a copy
    made elsewhere to compare with the committed one). Returns the files written."""
    root, out = Path(root), Path(out)
    if campaign is None and references is not None:
        raise ValueError("--references replaces one campaign's references: name the campaign (--campaign)")
    chosen = list(CAMPAIGNS.values()) if campaign is None else [find_campaign(campaign, references)]
    shown = readme_campaign(root)
    loaded = {c.name: campaign_episodes(root, c) for c in chosen}
    written = []
    for c in chosen:
        target = None if links_from is None else root / links_from / c.out
        files, block = write_campaign(root, out / c.out, c, loaded[c.name], target)
        written += files
        if readme is not None and Path(readme).is_file() and c.runs == shown.runs:
            text = Path(readme).read_text()
            atomic_write(Path(readme), replace_readme_block(text, block))
            written.append(Path(readme))
    registered = [CAMPAIGNS.get(c.name) is not None and CAMPAIGNS[c.name].runs == c.runs for c in chosen]
    if all(registered):  # every registered campaign's claims, side by side (the chosen ones as chosen)
        judged, target = [next((c for c in chosen if c.name == r.name), r) for r in CAMPAIGNS.values()], out
    else:  # another sweep's runs: its claims alone, in its own folder
        judged, target = chosen, out / chosen[0].out
    sections = []
    for c in judged:
        episodes = loaded[c.name] if c.name in loaded else campaign_episodes(root, c)
        sections.append(claims_section(root, c, episodes))
    target.mkdir(parents=True, exist_ok=True)
    atomic_write(target / "claims.md", claims_page(sections))
    return [*written, target / "claims.md"]
