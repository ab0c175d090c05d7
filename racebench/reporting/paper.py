"""The paper's Tables II, III and IV and its claims, regenerated from a training campaign's committed evaluations.

``racebench paper-tables`` (:func:`write_report`) reads, from a repository checkout and without training or flying
anything:

* the campaign's runs (``baselines/experiments/campaign-4m/<config>-<track>-seed<k>/eval``: each run's final policy
  on its own track's nine ids, ``baselines/sweeps/campaign-4m.yaml``), plus the A/B runs of ``vision-ppo`` on S
  (``baselines/experiments/ab-fast-update``: training seeds 1 and 2, same config and budget);
* beyond the paper, the teacher–student policies ``vision-distill`` and ``vision-distill-ppo``
  (``<references>/<name>-<track>/eval``), each counted on its own track only;
* the references: the floors ``follow`` and ``hover`` and the privileged planners (``<references>/<agent>``);

where ``<references>`` holds those folders as flown on the campaign's env version: campaign 1 ran on env version 2,
whose reference records are kept as history in ``results/env-v2`` (:data:`REFERENCES`). A report never mixes env
versions: :func:`load_episodes` refuses records of two.
* two lap times no policy is measured against, shown under their names in Table II and the README block: the
  **lap-time lower bound** (:mod:`racebench.envs.lap_bound`: no lap of the id can be faster) and **planner-fast's
  line at full thrust** (its racing line timed as a point mass at the airframe's full thrust,
  ``baselines/experiments/planner_fast_line_times.txt``: that one line's limit, not a bound).

It writes ``table_ii``, ``table_iii`` and ``table_iv`` as Markdown, CSV and LaTeX, ``claims.md`` (the decision rule
committed in the sweep file before the first run, applied by :func:`judge_claims`), ``at_a_glance.md`` (the README's
results block, copied between its markers) and, from each run's ``validation_curve.csv``, the learning curves
``figures/learning_curves.png`` with their CSV. Every cell puts the paper's number beside ours (``72 [63–80] · paper
100``); a row of several training seeds shows their mean success rate and the range over the seeds.

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
from racebench.envs.registration import DENSITIES, GATE_SHIFTS
from racebench.evaluation.protocol import TRACK_ORDER, env_id_of, split_env_id
from racebench.evaluation.results import check_one_env_version, load_records
from racebench.reporting.cells import Cell, cell  # noqa: F401 (re-exported)
from racebench.reporting.claims import (  # noqa: F401 (re-exported)
    ALPHA,
    Claim,
    claims_markdown,
    difference_claim,
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
from racebench.reporting.validation import RUN_FOLDER, learning_curves
from racebench.utils.files import atomic_write

CAMPAIGN = Path("baselines/experiments/campaign-4m")
#: The reference and teacher–student evaluations on the campaign's env version (campaign 1: env version 2).
REFERENCES = Path("results/env-v2")
BUDGET_STEPS = 4_000_000
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
LINE_TIMES = Path("baselines/experiments/planner_fast_line_times.txt")
LINE_TIMES_COLUMN = "planner-fast's line at full thrust (s)"


@dataclass(frozen=True)
class Source:
    """One evaluation folder feeding the report: a method's policy (one training seed) or a reference agent."""

    method: str
    folder: Path
    training_seed: int | None = None  # None: not trained (references) or a single committed policy
    track: str | None = None  # a per-track policy: only its own track's episodes count


def discover_sources(
    root: str | Path = ".", campaign: str | Path = CAMPAIGN, references: str | Path = REFERENCES
) -> list[Source]:
    """Every evaluation folder the report reads under the checkout ``root`` (see the module docstring)."""
    root = Path(root)
    sources = []
    for run in sorted((root / campaign).glob("*-seed*")):
        match = RUN_FOLDER.match(run.name)
        if match and (run / "eval" / "summary.csv").is_file():
            sources.append(Source(match["config"], run / "eval", int(match["seed"]), match["track"]))
    for seed in (1, 2):  # vision-ppo on S, training seeds 1-2: the A/B runs (campaign 1's config, budget, env version)
        run = root / "baselines/experiments/ab-fast-update" / f"vision-ppo-S-seed{seed}"
        if Path(campaign) == CAMPAIGN and (run / "eval" / "summary.csv").is_file():
            sources.append(Source("vision-ppo", run / "eval", seed, "S"))
    for method in ("vision-distill", "vision-distill-ppo"):
        for track in TRACK_ORDER:
            folder = root / references / f"{method}-{track}" / "eval"
            if (folder / "summary.csv").is_file():
                sources.append(Source(method, folder, None, track))
    for agent in ("follow", "hover", "planner", "planner-fast"):
        if (root / references / agent / "summary.csv").is_file():
            sources.append(Source(agent, root / references / agent))
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


def lap_time_references(root: str | Path = ".") -> dict[str, dict[str, float]]:
    """Per track, the two reference lap times of the main id: :data:`LOWER_BOUND` (computed: no lap can be faster,
    ``docs/evaluation.md``) and :data:`LINE_AT_FULL_THRUST` (read from the committed :data:`LINE_TIMES`; absent when
    that file is)."""
    references: dict[str, dict[str, float]] = {
        LOWER_BOUND: {track: env_lap_time_bound(env_id_of(track)) for track in TRACK_ORDER},
        LINE_AT_FULL_THRUST: {},
    }
    path = Path(root) / LINE_TIMES
    if path.is_file():
        frame = pd.read_csv(path, skipinitialspace=True)
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


def budget_note(root: Path, campaign: Path = CAMPAIGN) -> str:
    """Where the budget is the likely reason: each campaign run's final curriculum level and its training success
    over the last :data:`FINAL_WINDOW_STEPS` steps."""
    rows = []
    for summary_path in sorted((root / campaign).glob("*-seed*/summary.json")):
        summary = json.loads(summary_path.read_text())
        progress = summary_path.parent / "progress.csv"
        final = final_training_success(pd.read_csv(progress)) if progress.is_file() else None
        rows.append(
            f"{summary_path.parent.name}: level {summary.get('level')}, training success over its last "
            f"{FINAL_WINDOW_STEPS / 1e3:.0f}k steps " + ("–" if final is None else f"{100 * final:.0f} %")
        )
    share = 100 * BUDGET_STEPS / PAPER_STEPS
    head = (
        f"Budget: {BUDGET_STEPS / 1e6:.0f} M environment steps per run, {share:.0f} % of the paper's "
        f"{PAPER_STEPS / 1e6:.0f} M. A claim that does not hold here may hold at the paper's budget: a run still "
        "improving at its end (final level below 3, or training success below the 80 % bar) points to the budget."
    )
    return head + ("\n\n" + "\n".join(f"- {row}" for row in rows) if rows else "")


# ------------------------------------------------------------------------------------------------ validation curve
# ------------------------------------------------------------------------------------------------------- output
def provenance(episodes: pd.DataFrame, campaign: str | Path = CAMPAIGN) -> str:
    """Which campaign and env version a report's numbers are of, as one sentence."""
    version = episodes.attrs.get("env_version")
    return f"Campaign `{Path(campaign).name}`, env version {version if version is not None else '–'}."


def caption(which: str, episodes: pd.DataFrame, campaign: str | Path = CAMPAIGN) -> str:
    """A table's caption: what it shows, the campaign and env version, the budget and the episodes per cell."""
    what = {
        "II": "Table II: lap time (mean of successful laps) and success rate per track, each policy on its own track",
        "III": "Table III: success rate of vision-ppo and its ablations per track",
        "IV": "Table IV: vision-ppo's success rate against obstacle density and gate shift",
    }[which]
    share = 100 * BUDGET_STEPS / PAPER_STEPS
    n = "100 episodes per main-id cell, 50 per density or gate-shift cell (references: 50 and 10)"
    lap_references = (
        f" Reference lap times: the {LOWER_BOUND} (no lap can be faster: a flight from rest at full thrust over the "
        f"straight gate-to-gate distance, docs/evaluation.md) and {LINE_AT_FULL_THRUST} (its racing line timed as a "
        f"point mass at full thrust; that one line's limit, not a bound)."
        if which == "II"
        else ""
    )
    return (
        f"{what}. {provenance(episodes, campaign)} Trained configs: {BUDGET_STEPS / 1e6:.0f} M steps per run "
        f"({share:.0f} % of the paper's 100 M); "
        f"{n}; SR [95 % Wilson] for one training seed, the mean (range over seeds) for several; "
        f"'· paper' the paper's number (10 trials).{lap_references}"
    )


METHOD_NOTES: dict[str, tuple[str, str]] = {  # budget per track, the command that reproduces it
    "vision-ppo": ("4 M PPO steps", "`racebench sweep baselines/sweeps/campaign-4m.yaml`"),
    "state-ppo": ("4 M PPO steps", "`racebench sweep baselines/sweeps/campaign-4m.yaml`"),
    "vision-distill": ("0.5 M DAgger steps", "`racebench sweep baselines/sweeps/teacher-student.yaml`"),
    "vision-distill-ppo": ("0.5 M DAgger + 2 M PPO steps", "`racebench sweep baselines/sweeps/teacher-student.yaml`"),
    "planner-fast": ("none (privileged: reads the true scene)", "`racebench evaluate --agent planner-fast`"),
}


def at_a_glance(
    episodes: pd.DataFrame, references: dict[str, dict[str, float]] | None = None, campaign: str | Path = CAMPAIGN
) -> str:
    """The README's results block: the paper's method and its state-based baseline as trained here, each below the
    paper's numbers, the best racebench method (highest mean own-track success of the teacher-student rows) and the
    privileged reference, per track; then the reference lap times (:func:`lap_time_references`), when given."""

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
         *METHOD_NOTES["vision-ppo"]),
        ("paper: state-based (ours), 10 trials", paper_cells("state-ppo"), "100 M PPO steps", "–"),
        (
            f"`state-ppo`: the paper's method without depth, trained here{seeds_note('state-ppo')}",
            track_cells("state-ppo"),
            *METHOD_NOTES["state-ppo"],
        ),
        (f"`{best}`: best racebench method{seeds_note(best)}", track_cells(best), *METHOD_NOTES[best]),
        ("`planner-fast` (privileged reference)", track_cells("planner-fast"), *METHOD_NOTES["planner-fast"]),
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
        "[`results/table_ii.csv`](results/table_ii.csv)); a row of several training seeds (its name says how many) "
        "gives their mean success rate [the lowest–highest seed's], on the public evaluation seeds (the leaderboard "
        "site ranks a verified method on private seeds instead), and mean lap "
        "time of the successful laps; one policy per track. '–' marks a run of the campaign not yet committed. "
        "The last two rows are lap times, not policies: the lower bound below which record validation refuses a lap, "
        "and planner-fast's racing line flown at the airframe's full thrust (the fastest that line allows). "
        f"{provenance(episodes, campaign)} Generated by `racebench paper-tables` (no training); Tables II–IV, the "
        "paper's claims tested and the learning curves: [`results/`](results/README.md).",
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


def write_report(
    root: str | Path = ".",
    out: str | Path = "results",
    readme: str | Path | None = "README.md",
    campaign: str | Path = CAMPAIGN,
    references: str | Path = REFERENCES,
    links_from: str | Path | None = None,
) -> list[Path]:
    """Write every table, ``claims.md``, ``at_a_glance.md``, the learning curves and the Table IV figures under
    ``out``; update the README's results block. ``campaign`` and ``references`` are folders under ``root`` (campaign 1
    and its env-version-2 references by default). ``at_a_glance.md``'s links are the README block's, rewritten for
    ``out`` (or for ``root / links_from``: a copy made elsewhere to compare with the committed one). Returns the files
    written."""
    root, out, campaign = Path(root), Path(out), Path(campaign)
    out.mkdir(parents=True, exist_ok=True)
    episodes = load_episodes(discover_sources(root, campaign, references))
    references = lap_time_references(root)
    written = []
    for which, build in (("II", table_ii), ("III", table_iii), ("IV", table_iv)):
        frame, rows = build(episodes, references) if which == "II" else build(episodes)
        stem = out / f"table_{which.lower()}"
        text = caption(which, episodes, campaign)
        table = pd.DataFrame(rows)
        if which == "II":  # its reference rows have no counts: keep the counts integers
            table[["seeds", "n"]] = table[["seeds", "n"]].astype("Int64")
        outputs = {".md": render(frame, set(), "md", text), ".tex": render(frame, set(), "latex", text),
                   ".csv": table.to_csv(index=False)}  # fmt: skip
        for suffix, content in outputs.items():
            atomic_write(stem.with_suffix(suffix), content)
            written.append(stem.with_suffix(suffix))
    atomic_write(out / "claims.md", claims_markdown(judge_claims(episodes), budget_note(root, campaign)))
    block = at_a_glance(episodes, references, campaign)  # its links are the README's, from the root
    atomic_write(out / "at_a_glance.md", relink(block, root, out if links_from is None else root / links_from))
    written += [out / "claims.md", out / "at_a_glance.md"]
    if learning_curves(root, out, campaign) is not None:
        written += [out / "learning_curves.csv", *(out / "figures" / f"learning_curves.{f}" for f in FIGURE_FORMATS)]
    written += write_table_iv_figures(episodes, out, episodes.attrs.get("env_version"), campaign)
    if readme is not None and Path(readme).is_file():
        text = Path(readme).read_text()
        atomic_write(Path(readme), replace_readme_block(text, block))
        written.append(Path(readme))
    return written
