"""The robustness table (docs/robustness.md, "Results"): each method's success under the suite's perturbations against
its nominal success on the same scenes, from validated evaluation records alone.

Small pure functions over a DataFrame of episodes (one row per record: ``method``, ``privileged``, ``env_id``,
``seed``, ``success``, ``lap_time``), in the spirit of rliable:

* :func:`suite_cell` places an env id in the suite: its track and ``"nominal"`` (the main id) or its perturbation;
* :func:`paired_cells` pairs, per method and track, the main id's episodes with each perturbation's on the same
  seeds: the seeds the main id and every perturbation id flown share (normally the first 50 public ones), so every
  cell of a row is over the same scenes. Per cell: the pairs, both success counts and mean laps (over successful
  laps), the laps finished only nominally and only under the perturbation, and McNemar's exact p on those
  discordant pairs (:func:`racebench.evaluation.statistics.paired_outcomes`);
* :func:`adjusted` adds ΔSR (points), Holm's adjustment across every cell given (the whole table,
  :func:`racebench.evaluation.statistics.holm_adjust`) and the verdict at :data:`ALPHA`;
* :func:`relative_robustness` is the leaderboard's column: per track the mean success under the ten
  perturbations over the nominal success, averaged over tracks;
* :func:`table_frame` / :func:`make_robustness_table` / :func:`csv_frame` render it.

:func:`read_robustness` reads result folders into such episodes (valid records only, one env version).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import pandas as pd

from racebench.envs.perturbations import ROBUSTNESS
from racebench.evaluation.protocol import TRACK_ORDER, split_env_id
from racebench.evaluation.results import _directory_label, check_one_env_version, load_result_dir
from racebench.evaluation.statistics import holm_adjust, paired_outcomes, wilson_interval
from racebench.reporting.tables import TRACK_NAMES, render

logger = logging.getLogger("racebench")

NOMINAL = "nominal"
#: The perturbations in the suite's order (the table's columns).
PERTURBATIONS: tuple[str, ...] = tuple(ROBUSTNESS)
#: Family-wise error rate of the table's tests (Holm over every cell of the table).
ALPHA = 0.05
#: The columns :func:`paired_cells` needs of its episodes.
EPISODE_COLUMNS: tuple[str, ...] = ("method", "privileged", "env_id", "seed", "success", "lap_time")
NOT_EVALUATED = "n/e"


def suite_cell(env_id: str) -> tuple[str, str] | None:
    """``(track, "nominal")`` for a main id, ``(track, perturbation)`` for a robustness id, else ``None``."""
    track, variant = split_env_id(env_id)
    if track not in TRACK_ORDER:
        return None
    if variant == "default":
        return track, NOMINAL
    return (track, variant) if variant in ROBUSTNESS else None


def _lap_mean(frame: pd.DataFrame) -> float:
    laps = pd.to_numeric(frame.loc[frame["success"], "lap_time"], errors="coerce").dropna()
    return float(laps.mean()) if len(laps) else math.nan


def paired_cells(episodes: pd.DataFrame) -> pd.DataFrame:
    """One row per method, track and perturbation flown: the paired cells (see the module's docstring).

    Columns: ``method``, ``privileged``, ``track``, ``perturbation``, ``pairs``, ``nominal_successes``,
    ``successes``, ``only_nominal``, ``only_perturbed``, ``p``, ``nominal_lap_time``, ``lap_time``. A method and track
    with perturbation records but no main-id episode on their seeds is left out, with a warning. An episode slot
    (method, env id, seed) twice is an error: a pair must be one scene flown once on each side.
    """
    missing = [c for c in EPISODE_COLUMNS if c not in episodes.columns]
    if missing:
        raise ValueError(f"robustness episodes need the columns {list(EPISODE_COLUMNS)}; missing {missing}")
    placed = [suite_cell(str(e)) for e in episodes["env_id"]]
    frame = episodes.assign(
        track=[p[0] if p else None for p in placed],
        perturbation=[p[1] if p else None for p in placed],
        success=episodes["success"].astype(bool),
    )
    frame = frame[frame["perturbation"].notna()]
    twice = frame[frame.duplicated(["method", "env_id", "seed"], keep=False)]
    if not twice.empty:
        first = twice.iloc[0]
        raise ValueError(f"{first['method']}: {first['env_id']} seed {first['seed']} is flown more than once (two "
                         "folders or renderers of one policy): a pair is one scene flown once a side")  # fmt: skip
    rows = []
    for (method, track), group in frame.groupby(["method", "track"], sort=False):
        flown = [p for p in PERTURBATIONS if (group["perturbation"] == p).any()]
        if not flown:
            continue  # the main id only: no robustness row
        seeds = set(group.loc[group["perturbation"] == NOMINAL, "seed"])
        for name in flown:
            seeds &= set(group.loc[group["perturbation"] == name, "seed"])
        if not seeds:
            logger.warning(f"robustness: {method} on {track}: no main-id episode on the perturbations' seeds; left out")
            continue
        longest = max(int((group["perturbation"] == name).sum()) for name in flown)
        if longest > len(seeds):  # e.g. an evaluation stopped midway: every cell of the row shrinks to the shortest
            logger.warning(f"robustness: {method} on {track}: paired on the {len(seeds)} scenes the main id and "
                           f"every perturbation share, one has {longest}: finish its evaluation")  # fmt: skip
        paired = group[group["seed"].isin(seeds)]
        nominal = paired[paired["perturbation"] == NOMINAL]
        for name in flown:
            perturbed = paired[paired["perturbation"] == name]
            a, b = (part.assign(env_id=track)[["env_id", "seed", "success"]] for part in (nominal, perturbed))
            n, only_nominal, only_perturbed, p = paired_outcomes(a, b)
            rows.append({
                "method": method, "privileged": bool(group["privileged"].astype(bool).any()), "track": track,
                "perturbation": name, "pairs": n, "nominal_successes": int(nominal["success"].sum()),
                "successes": int(perturbed["success"].sum()), "only_nominal": only_nominal,
                "only_perturbed": only_perturbed, "p": float(p), "nominal_lap_time": _lap_mean(nominal),
                "lap_time": _lap_mean(perturbed),
            })  # fmt: skip
    columns = ["method", "privileged", "track", "perturbation", "pairs", "nominal_successes", "successes",
               "only_nominal", "only_perturbed", "p", "nominal_lap_time", "lap_time"]  # fmt: skip
    return pd.DataFrame(rows, columns=columns)


def adjusted(cells: pd.DataFrame, alpha: float = ALPHA) -> pd.DataFrame:
    """``cells`` with ``delta_sr`` (points: perturbed minus nominal success rate), ``p_holm`` (Holm across every
    row given: the family is the whole table) and ``significant`` (``p_holm < alpha``)."""
    delta = 100.0 * (cells["successes"] - cells["nominal_successes"]) / cells["pairs"]
    p_holm = holm_adjust([float(p) for p in cells["p"]])
    return cells.assign(delta_sr=delta, p_holm=p_holm, significant=[p < alpha for p in p_holm])


def robustness_cells(episodes: pd.DataFrame, alpha: float = ALPHA) -> pd.DataFrame:
    """:func:`paired_cells` then :func:`adjusted`: the table's numbers."""
    return adjusted(paired_cells(episodes), alpha)


@dataclass(frozen=True)
class RobustnessScore:
    """The leaderboard's robustness column (:func:`relative_robustness`).

    ``value``: the mean over ``tracks`` of (mean success rate under the ten perturbations) / (nominal success rate),
    None when no track counts. ``per_track``: that ratio per counted track. ``left_out``: per track with robustness
    records that does not count, why (not all ten perturbations flown, or a nominal success rate of 0).
    """

    value: float | None
    per_track: dict[str, float]
    left_out: dict[str, str]

    @property
    def tracks(self) -> tuple[str, ...]:
        """The tracks the value averages over."""
        return tuple(self.per_track)


def relative_robustness(cells: pd.DataFrame) -> RobustnessScore:
    """Per track of one method's ``cells`` (:func:`paired_cells`, every perturbation on the same seeds): the mean of
    the ten perturbations' success rates divided by the nominal success rate; the score is the mean over tracks.

    A track counts only with all ten perturbations flown (a mean over fewer would not compare with another
    method's). A nominal success rate of 0 leaves the track out: the method has no success to keep there, and a
    ratio to 0 is undefined (the table still shows its perturbed rates). The ratio can exceed 1 where a
    perturbation helps.
    """
    per_track: dict[str, float] = {}
    left_out: dict[str, str] = {}
    for track in TRACK_ORDER:
        mine = cells[cells["track"] == track]
        if mine.empty:
            continue
        if set(mine["perturbation"]) != set(PERTURBATIONS):
            left_out[track] = f"{mine['perturbation'].nunique()}/{len(PERTURBATIONS)} perturbations flown"
        elif int(mine["nominal_successes"].iloc[0]) == 0:
            left_out[track] = "nominal success 0 %"
        else:
            rates = mine["successes"] / mine["pairs"]
            per_track[track] = float(rates.mean()) / float(mine["nominal_successes"].iloc[0] / mine["pairs"].iloc[0])
    value = sum(per_track.values()) / len(per_track) if per_track else None
    return RobustnessScore(value, per_track, left_out)


def _sr_lap(successes: int, n: int, lap: float) -> str:
    return f"{100 * successes / n:.0f} / " + ("–" if math.isnan(lap) else f"{lap:.2f}")


def _delta_text(delta: float) -> str:
    points = round(delta)
    return "±0" if points == 0 else f"{points:+d}"


def _row_label(method: str, privileged: bool, track: str, pairs: int) -> str:
    name = f"{method} (privileged)" if privileged else method
    return f"{name} · {TRACK_NAMES[track]} (n = {pairs})"


def _row_order(cells: pd.DataFrame) -> list[tuple[str, str]]:
    """(method, track) of the rows: learned methods first, privileged references last, then by name and track."""
    keys = cells.drop_duplicates(["method", "track"])[["method", "track", "privileged"]]
    ordered = sorted(keys.itertuples(index=False), key=lambda r: (bool(r[2]), str(r[0]), TRACK_ORDER.index(r[1])))
    return [(str(m), str(t)) for m, t, _ in ordered]


def table_frame(cells: pd.DataFrame) -> tuple[pd.DataFrame, set[tuple[str, str]]]:
    """The table's text cells (rows: method · track; columns: nominal, then each perturbation) and the cells that
    are significant after Holm's adjustment (to be set in bold)."""
    if cells.empty:
        raise ValueError("no robustness results: no method was flown on a perturbation id with its main id on the "
                         "same seeds (racebench evaluate --envs robustness)")  # fmt: skip
    if "p_holm" not in cells:
        cells = adjusted(cells)
    table: dict[str, dict[str, str]] = {}
    bold: set[tuple[str, str]] = set()
    for method, track in _row_order(cells):
        mine = cells[(cells["method"] == method) & (cells["track"] == track)].set_index("perturbation")
        first = mine.iloc[0]
        label = _row_label(method, bool(first["privileged"]), track, int(first["pairs"]))
        row = {"nominal SR [%] / LT [s]": _sr_lap(int(first["nominal_successes"]), int(first["pairs"]),
                                                 float(first["nominal_lap_time"]))}  # fmt: skip
        for name in PERTURBATIONS:
            if name not in mine.index:
                row[name] = NOT_EVALUATED
                continue
            cell = mine.loc[name]
            row[name] = (f"{_sr_lap(int(cell['successes']), int(cell['pairs']), float(cell['lap_time']))} "
                         f"({_delta_text(float(cell['delta_sr']))})")  # fmt: skip
            if bool(cell["significant"]):
                bold.add((label, name))
        table[label] = row
    return pd.DataFrame.from_dict(table, orient="index"), bold


def make_robustness_table(cells: pd.DataFrame, fmt: str = "md") -> str:
    """The robustness table as Markdown (``fmt="md"``) or LaTeX (booktabs), from :func:`robustness_cells`."""
    frame, bold = table_frame(cells)
    tests = len(cells)
    caption = (
        "Robustness: per method and track, the success rate SR [%] and mean lap time LT [s] (over successful laps) "
        "on the main id (nominal) and under each perturbation of the robustness suite, with the change of SR from "
        "nominal in points in brackets; every cell of a row is over the same n scenes (seeds). Bold: the change is "
        f"significant by McNemar's exact test on the paired scenes, Holm-adjusted over the table's {tests} tests "
        f"(family-wise alpha = {ALPHA:g}); a negative change in bold is a significant drop. {NOT_EVALUATED}: not "
        "evaluated."
    )
    return render(frame, bold, fmt, caption)


def csv_frame(cells: pd.DataFrame) -> pd.DataFrame:
    """Every number of the table, one row per method, track and perturbation: counts, rates with their 95 % Wilson
    intervals, mean laps, ΔSR, the discordant pairs and both p-values."""
    if "p_holm" not in cells:
        cells = adjusted(cells)
    rows = []
    for method, track in _row_order(cells):
        mine = cells[(cells["method"] == method) & (cells["track"] == track)]
        for cell in sorted(mine.itertuples(index=False), key=lambda c: PERTURBATIONS.index(c.perturbation)):
            n = int(cell.pairs)
            nominal_low, nominal_high = wilson_interval(int(cell.nominal_successes), n)
            low, high = wilson_interval(int(cell.successes), n)
            rows.append({
                "method": method, "privileged": bool(cell.privileged), "track": track,
                "perturbation": cell.perturbation, "env_id": f"RaceObs-{track}-{cell.perturbation}-v0", "pairs": n,
                "nominal_successes": int(cell.nominal_successes), "nominal_sr": cell.nominal_successes / n,
                "nominal_sr_ci_low": nominal_low, "nominal_sr_ci_high": nominal_high,
                "nominal_lap_time_mean": cell.nominal_lap_time, "successes": int(cell.successes),
                "success_rate": cell.successes / n, "sr_ci_low": low, "sr_ci_high": high,
                "lap_time_mean": cell.lap_time, "delta_sr_points": cell.delta_sr,
                "only_nominal": int(cell.only_nominal), "only_perturbed": int(cell.only_perturbed),
                "p_mcnemar": cell.p, "p_holm": cell.p_holm, "significant": bool(cell.significant),
            })  # fmt: skip
    return pd.DataFrame(rows)


def robustness_episodes(episodes: pd.DataFrame) -> pd.DataFrame:
    """The records (``agent``, ``policy_sha256``, ``env_id``, ...) of each policy on the tracks where it flew a
    perturbation, with their ``method``: the label (``agent``), or ``agent (folder)`` where one label names several
    such policies on one track, so that a row is one policy's. A policy's main-id records on a track it flew no
    perturbation on (e.g. a per-track policy's cross-track cells) are left out: they pair with nothing."""
    placed = [suite_cell(str(e)) for e in episodes["env_id"]]
    keys = list(zip(episodes["agent"].astype(str), episodes["policy_sha256"].astype(str), strict=True))
    flown: dict[tuple[str, str], set[str]] = {}  # (label, policy) -> the tracks it flew a perturbation on
    for key, cell in zip(keys, placed, strict=True):
        if cell is not None and cell[1] != NOMINAL:
            flown.setdefault(key, set()).add(cell[0])
    keep = [cell is not None and cell[0] in flown.get(key, set()) for key, cell in zip(keys, placed, strict=True)]
    shared = {a for (a, p), tracks in flown.items() for (b, q), other in flown.items() if a == b and p != q
              and tracks & other}  # fmt: skip
    folders = episodes["folder"] if "folder" in episodes else pd.Series([p[:10] for _, p in keys], index=episodes.index)
    methods = [f"{a} ({f})" if a in shared else a for (a, _), f in zip(keys, folders, strict=True)]
    return episodes.assign(method=methods)[keep].reset_index(drop=True)


def read_robustness(paths: Iterable[str | Path]) -> pd.DataFrame:
    """The episodes of result folders (their validated records: an invalid record or a missing seed is an error, as
    for every table) with their ``method`` (:func:`method_labels`); folders of several env versions are refused."""
    loaded = [load_result_dir(path) for path in paths]
    if not loaded:
        raise ValueError("no result directories given")
    check_one_env_version({str(path): episodes["env_version"] for path, episodes in loaded})
    episodes = pd.concat([e.assign(folder=_directory_label(p)) for p, e in loaded], ignore_index=True)
    return robustness_episodes(episodes)
