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
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from racebench.envs.lap_bound import env_lap_time_bound
from racebench.envs.registration import DENSITIES, GATE_SHIFTS
from racebench.evaluation.protocol import TRACK_ORDER, env_id_of, split_env_id
from racebench.evaluation.results import check_one_env_version, load_records
from racebench.evaluation.statistics import holm_adjust, paired_outcomes, trend_test, wilson_interval
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
ALPHA = 0.05


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


#: The two Table IV figures: file stem, the variants' prefix, their x values and the x axis label.
TABLE_IV_FIGURES: dict[str, tuple[list[str], list[float], str]] = {
    "table_iv_density": ([f"Density{d}" for d in DENSITIES], [float(d) for d in DENSITIES], "obstacles per 2 gates"),
    "table_iv_gate_shift": (
        [f"GateShift{s}" for s in GATE_SHIFTS], [float(s) for s in GATE_SHIFTS], "gate shift ±[m]"
    ),
}
FIGURE_FORMATS = ("png", "pdf")


def table_iv_figure(
    episodes: pd.DataFrame, factor: str, method: str = "vision-ppo", reference: str = "planner-fast",
    title: str | None = None,
):  # fmt: skip
    """Table IV as a figure (``factor``: a :data:`TABLE_IV_FIGURES` key), one panel per track: ``method``'s success
    rate per training seed with its 95 % Wilson interval, the mean over seeds with a band for their range, the
    paper's numbers as markers and ``reference`` (the privileged planner, same env version) as a dashed line."""
    import matplotlib

    matplotlib.use("Agg")  # files only; never needs a display
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    names, xs, xlabel = TABLE_IV_FIGURES[factor]
    step = min(np.diff(xs)) if len(xs) > 1 else 1.0
    fig, axes = plt.subplots(1, len(TRACK_ORDER), figsize=(11, 3.6), sharey=True, squeeze=False)
    seeds_seen, n_seen, ref_n = set(), set(), set()
    for ax, track in zip(axes[0], TRACK_ORDER, strict=True):
        rows = episodes[(episodes["method"] == method) & (episodes["track"] == track) & episodes["variant"].isin(names)]
        seeds = sorted(rows["training_seed"].unique())  # those flown on these ids (not only on the main id)
        seeds_seen.add(len(seeds))
        rates = pd.DataFrame(index=names, columns=seeds, dtype=float)
        for j, seed in enumerate(seeds):
            offset = (j - (len(seeds) - 1) / 2) * 0.08 * step
            for x, variant in zip(xs, names, strict=True):
                mine = rows[(rows["training_seed"] == seed) & (rows["variant"] == variant)]
                if mine.empty:
                    continue
                k, n = int(mine["success"].sum()), len(mine)
                n_seen.add(n)
                low, high = wilson_interval(k, n)
                rates.loc[variant, seed] = k / n
                ax.errorbar(x + offset, 100 * k / n, yerr=[[100 * (k / n - low)], [100 * (high - k / n)]],
                            fmt="o", markersize=3, color="tab:blue", alpha=0.55, capsize=2, linewidth=0.8)  # fmt: skip
        if len(seeds):
            mean, low, high = rates.mean(axis=1), rates.min(axis=1), rates.max(axis=1)
            ax.plot(xs, 100 * mean, color="tab:blue", linewidth=1.8)
            if len(seeds) > 1:
                ax.fill_between(xs, 100 * low, 100 * high, color="tab:blue", alpha=0.15, linewidth=0)
        else:
            ax.text(0.5, 0.5, f"no {method} run", transform=ax.transAxes, ha="center", color="0.4", style="italic")
        ref = episodes[(episodes["method"] == reference) & (episodes["track"] == track)]
        ref_rates = [ref.loc[ref["variant"] == v, "success"] for v in names]
        ref_n.update(len(r) for r in ref_rates if len(r))
        ax.plot(xs, [100 * r.mean() if len(r) else np.nan for r in ref_rates], "--", color="0.35", linewidth=1.2,
                marker=".", zorder=1)  # fmt: skip
        ax.plot(xs, [PAPER_VARIANTS[v][track] for v in names], "x", color="tab:red", markersize=8,
                markeredgewidth=1.8, zorder=4)  # fmt: skip
        ax.set_title(f"{TRACK_NAMES[track]} ({len(seeds)} seed{'s' if len(seeds) != 1 else ''})", fontsize=10)
        ax.set_xticks(xs)
        ax.set_xlabel(xlabel)
        ax.set_ylim(-4, 105)
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("success rate [%]")
    per_cell = "/".join(str(n) for n in sorted(n_seen)) or "–"
    ref_cell = "/".join(str(n) for n in sorted(ref_n)) or "–"
    handles = [
        Line2D([], [], color="tab:blue", marker="o", markersize=3, alpha=0.55, linestyle="",
               label=f"{method}: one training seed, 95 % Wilson interval ({per_cell} episodes)"),
        Line2D([], [], color="tab:blue", linewidth=1.8, label=f"{method}: mean over training seeds"),
        Patch(color="tab:blue", alpha=0.15, label=f"{method}: range over training seeds"),
        Line2D([], [], color="tab:red", marker="x", linestyle="", markeredgewidth=1.8,
               label="paper (Sun et al., Table IV; 10 trials)"),
        Line2D([], [], color="0.35", linestyle="--", marker=".",
               label=f"{reference} (privileged reference; {ref_cell} episodes)"),
    ]  # fmt: skip
    fig.legend(handles=handles, loc="lower center", ncol=3, fontsize=8, frameon=False)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout(rect=(0, 0.14, 1, 1))
    return fig


def write_table_iv_figures(
    episodes: pd.DataFrame, out: Path, env_version: int | None, campaign: Path = CAMPAIGN
) -> list[Path]:
    """Both Table IV figures of ``vision-ppo`` under ``out/figures`` as PNG and PDF (none without its episodes)."""
    import matplotlib.pyplot as plt

    if not (episodes["method"] == "vision-ppo").any():
        return []
    written = []
    (out / "figures").mkdir(parents=True, exist_ok=True)
    for stem in TABLE_IV_FIGURES:
        what = "obstacle density" if stem.endswith("density") else "gate shift"
        title = (f"vision-ppo's success rate against {what} ({Path(campaign).name}, "
                 f"env version {env_version}; references on the same env version)")  # fmt: skip
        fig = table_iv_figure(episodes, stem, title=title)
        for fmt in FIGURE_FORMATS:
            path = out / "figures" / f"{stem}.{fmt}"
            metadata = {"Software": None} if fmt == "png" else {"Creator": None, "Producer": None, "CreationDate": None}
            fig.savefig(path, dpi=200, bbox_inches="tight", pad_inches=0.05, metadata=metadata)
            written.append(path)
        plt.close(fig)
    return written


# ----------------------------------------------------------------------------------------------------- claims
@dataclass(frozen=True)
class Claim:
    """One of the paper's claims as tested: both sides' numbers, the test, its p-value and the verdict."""

    claim: str
    evidence: str
    test: str
    p: float | None  # raw p-value (None: not a test, e.g. "one-step fails")
    verdict: str = ""
    p_holm: float | None = None


def _seed_episodes(episodes: pd.DataFrame, method: str, env_id: str, training_seed: int) -> pd.DataFrame:
    rows = episodes[(episodes["method"] == method) & (episodes["env_id"] == env_id)]
    return rows[rows["training_seed"] == training_seed]


def difference_claim(episodes: pd.DataFrame, better: str, worse: str) -> Claim:
    """``better`` > ``worse`` on every track's main id: directions per track and seed pair, pooled McNemar p."""
    directions, evidence, only_better, only_worse = [], [], 0, 0
    for track in TRACK_ORDER:
        env_id = env_id_of(track)
        ours, theirs = cell(episodes, better, env_id), cell(episodes, worse, env_id)
        if ours is None or theirs is None:
            return Claim(f"{better} > {worse}", f"{track}: missing runs", "exact McNemar, pooled", None)
        evidence.append(f"{track} {100 * ours.success_rate:.0f} vs {100 * theirs.success_rate:.0f}")
        seeds_a = sorted(set(episodes.loc[episodes["method"] == better, "training_seed"]))
        seeds_b = sorted(set(episodes.loc[episodes["method"] == worse, "training_seed"]))
        for a in seeds_a:
            for b in seeds_b:
                left, right = _seed_episodes(episodes, better, env_id, a), _seed_episodes(episodes, worse, env_id, b)
                if len(left) and len(right):
                    pairs = left.merge(right, on=["env_id", "seed"], suffixes=("_a", "_b"))
                    directions.append(np.sign(pairs["success_a"].mean() - pairs["success_b"].mean()))
        seed0_a, seed0_b = min(seeds_a), min(seeds_b)  # the pooled test pairs one run per side: the first seed
        _, a_only, b_only, _ = paired_outcomes(
            _seed_episodes(episodes, better, env_id, seed0_a), _seed_episodes(episodes, worse, env_id, seed0_b)
        )
        only_better, only_worse = only_better + a_only, only_worse + b_only
    from scipy.stats import binomtest

    p = binomtest(only_worse, only_better + only_worse).pvalue if only_better + only_worse else 1.0
    signs = set(directions)
    direction = 1 if signs == {1.0} else -1 if signs == {-1.0} else 0
    evidence.append(f"discordant scenes {only_better} vs {only_worse}")
    return Claim(f"{better} > {worse}", "; ".join(evidence), "exact McNemar, pooled over tracks", p,
                 verdict=str(direction))  # fmt: skip


def one_step_fails(episodes: pd.DataFrame, method: str = "vision-one-step") -> Claim:
    """``method`` fails on every main id: success rate < 10 % and its Wilson upper bound < 20 % on each track."""
    evidence, holds = [], True
    for track in TRACK_ORDER:
        rows = episodes[(episodes["method"] == method) & (episodes["env_id"] == env_id_of(track))]
        if rows.empty:
            return Claim(f"{method} fails", f"{track}: missing run", "success < 10 %, Wilson upper < 20 %", None,
                         verdict="not tested (missing runs)")  # fmt: skip
        k, n = int(rows["success"].sum()), len(rows)
        high = wilson_interval(k, n)[1]
        evidence.append(f"{track} {k}/{n} (upper {100 * high:.0f} %)")
        holds = holds and k / n < 0.10 and high < 0.20
    return Claim(f"{method} fails", "; ".join(evidence), "success < 10 % and Wilson upper < 20 % on every track",
                 None, verdict="holds" if holds else "does not hold")  # fmt: skip


def trend_claim(episodes: pd.DataFrame, kind: str, method: str = "vision-ppo") -> Claim:
    """``method``'s success falls with obstacle density (``kind="density"``) or gate shift (``"gates"``)."""
    if kind == "density":
        levels = [(float(d), f"Density{d}") for d in DENSITIES]
    else:
        levels = [(float(s), f"GateShift{s}") for s in GATE_SHIFTS]
    what = "density 2-5" if kind == "density" else "gate shift 0.3-1.0 m"
    strata, evidence = [], []
    for track in TRACK_ORDER:
        scores, successes, trials, rates = [], [], [], []
        for score, variant in levels:
            rows = episodes[(episodes["method"] == method) & (episodes["env_id"] == env_id_of(track, variant))]
            rows = rows[rows["training_seed"] == rows["training_seed"].min()] if len(rows) else rows
            if rows.empty:
                return Claim(f"{method}: success falls with {what}", f"{track} {variant}: missing",
                             "stratified Cochran-Armitage", None)  # fmt: skip
            scores.append(score)
            successes.append(int(rows["success"].sum()))
            trials.append(len(rows))
            rates.append(f"{100 * successes[-1] / trials[-1]:.0f}")
        strata.append((scores, successes, trials))
        evidence.append(f"{track} {'/'.join(rates)}")
    z, p_down, p_up = trend_test(strata)
    claim = Claim(f"{method}: success falls with {what}", "; ".join(evidence) + f"; z = {z:.2f}",
                  "Cochran-Armitage trend, stratified by track, one-sided", min(p_down, p_up),
                  verdict="1" if p_down <= p_up else "-1")  # fmt: skip
    return claim


def judge_claims(episodes: pd.DataFrame) -> list[Claim]:
    """The paper's claims with their verdicts under the rule committed in ``baselines/sweeps/campaign-4m.yaml``:
    Holm over every tested claim at level 0.05; a difference needs the same direction on every track and seed pair;
    a trend the one-sided stratified Cochran-Armitage test."""
    tested = [
        difference_claim(episodes, "vision-ppo", "state-ppo"),
        difference_claim(episodes, "vision-ppo", "vision-com"),
        difference_claim(episodes, "vision-ppo", "vision-no-gru"),
        difference_claim(episodes, "vision-ppo", "vision-no-avoid"),
        difference_claim(episodes, "vision-ppo", "vision-one-step"),
        trend_claim(episodes, "density"),
        trend_claim(episodes, "gates"),
    ]
    known = [claim for claim in tested if claim.p is not None]
    adjusted = dict(zip([id(c) for c in known], holm_adjust([c.p for c in known]), strict=True))
    judged = []
    for claim in tested:
        if claim.p is None:
            judged.append(Claim(claim.claim, claim.evidence, claim.test, None, "not tested (missing runs)"))
            continue
        p_holm = adjusted[id(claim)]
        direction = int(claim.verdict)
        if p_holm < ALPHA and direction == 1:
            verdict = "holds"
        elif p_holm < ALPHA and direction == -1:
            verdict = "opposite"
        else:
            verdict = "does not hold at this budget"
        judged.append(Claim(claim.claim, claim.evidence, claim.test, claim.p, verdict, p_holm))
    return judged + [one_step_fails(episodes)]


def claims_markdown(claims: list[Claim], budget_note: str) -> str:
    """``claims.md``: one line per claim with both numbers, the test, raw and Holm p, and the verdict."""
    lines = [
        "# The paper's claims, tested at 4 M steps per run",
        "",
        "Generated by `racebench paper-tables`; the decision rule was committed in `baselines/sweeps/campaign-4m.yaml`"
        " before the first run. Success on each track's main id (100 evaluation scenes per run) or on the density and"
        " gate-shift ids (50 each); Holm's correction over every tested claim, level 0.05.",
        "",
        "| claim | evidence (success %) | test | p | p (Holm) | verdict |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for c in claims:
        p = "–" if c.p is None else f"{c.p:.2g}"
        holm = "–" if c.p_holm is None else f"{c.p_holm:.2g}"
        lines.append(f"| {c.claim} | {c.evidence} | {c.test} | {p} | {holm} | **{c.verdict}** |")
    return "\n".join(lines + ["", budget_note, ""])


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
def caption(which: str, episodes: pd.DataFrame) -> str:
    """A table's caption: what it shows, the budget and the episodes per cell."""
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
        f"{what}. Trained configs: {BUDGET_STEPS / 1e6:.0f} M steps per run ({share:.0f} % of the paper's 100 M); "
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


def at_a_glance(episodes: pd.DataFrame, references: dict[str, dict[str, float]] | None = None) -> str:
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
        "Generated by `racebench paper-tables` (no training); Tables II–IV, the paper's claims tested and the "
        "learning curves: [`results/`](results/README.md).",
    ]
    return "\n".join(lines) + "\n"


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
) -> list[Path]:
    """Write every table, ``claims.md``, ``at_a_glance.md``, the learning curves and the Table IV figures under
    ``out``; update the README's results block. ``campaign`` and ``references`` are folders under ``root`` (campaign 1
    and its env-version-2 references by default). Returns the files written."""
    root, out, campaign = Path(root), Path(out), Path(campaign)
    out.mkdir(parents=True, exist_ok=True)
    episodes = load_episodes(discover_sources(root, campaign, references))
    references = lap_time_references(root)
    written = []
    for which, build in (("II", table_ii), ("III", table_iii), ("IV", table_iv)):
        frame, rows = build(episodes, references) if which == "II" else build(episodes)
        stem = out / f"table_{which.lower()}"
        text = caption(which, episodes)
        table = pd.DataFrame(rows)
        if which == "II":  # its reference rows have no counts: keep the counts integers
            table[["seeds", "n"]] = table[["seeds", "n"]].astype("Int64")
        outputs = {".md": render(frame, set(), "md", text), ".tex": render(frame, set(), "latex", text),
                   ".csv": table.to_csv(index=False)}  # fmt: skip
        for suffix, content in outputs.items():
            atomic_write(stem.with_suffix(suffix), content)
            written.append(stem.with_suffix(suffix))
    atomic_write(out / "claims.md", claims_markdown(judge_claims(episodes), budget_note(root, campaign)))
    block = at_a_glance(episodes, references)
    atomic_write(out / "at_a_glance.md", block)
    written += [out / "claims.md", out / "at_a_glance.md"]
    if learning_curves(root, out, campaign) is not None:
        written += [out / "learning_curves.csv", *(out / "figures" / f"learning_curves.{f}" for f in FIGURE_FORMATS)]
    written += write_table_iv_figures(episodes, out, episodes.attrs.get("env_version"), campaign)
    if readme is not None and Path(readme).is_file():
        text = Path(readme).read_text()
        atomic_write(Path(readme), replace_readme_block(text, block))
        written.append(Path(readme))
    return written
