"""Reading evaluation results back: episodes and summaries of a result folder, comparing folders."""

from __future__ import annotations

import logging
import re
from collections.abc import Iterable
from pathlib import Path

import pandas as pd

from racebench.evaluation.protocol import TRACK_ORDER, split_env_id
from racebench.evaluation.records import RECORD_FIELDS, RECORDS_FILE, has_records, read_folder
from racebench.evaluation.seeds import PUBLIC_SEED_BASE, public_seeds
from racebench.evaluation.statistics import paired_outcomes, wilson_interval
from racebench.utils.files import atomic_write

logger = logging.getLogger("racebench")


class MixedResultsError(ValueError):
    """An output directory holds records of another policy, label or env version than the one asked."""


EPISODE_COLUMNS: tuple[str, ...] = RECORD_FIELDS  # episodes.csv: every record field


def load_records(out_dir: str | Path, strict: bool = False) -> pd.DataFrame:
    """Every valid record of ``out_dir`` (``records.jsonl``, shards of a running or killed evaluation, legacy
    ``records/*.json``) as a DataFrame with :data:`EPISODE_COLUMNS`.

    An invalid line is named (file, line, reason) in a warning and left out (never counted); :class:`Evaluator`
    sets such lines aside and re-runs their episodes. With ``strict`` (the tables: a result read back) an invalid
    line, or a public cell missing a seed of its protocol (:func:`check_complete_cells`), is a :class:`ValueError`.
    """
    found = read_folder(out_dir)
    for problem in found.problems:
        if strict:
            raise ValueError(f"invalid record (a cell would be counted without it): {problem.error()}")
        logger.warning("racebench: invalid record left out: %s", problem.error())
    rows = found.sorted_records()
    frame = pd.DataFrame(rows, columns=list(EPISODE_COLUMNS))
    frame = frame.sort_values(["agent", "env_id", "seed"], kind="stable").reset_index(drop=True)
    if strict:
        check_complete_cells(frame, out_dir)
    return frame


def check_complete_cells(episodes: pd.DataFrame, where: str | Path) -> None:
    """Each public cell (label, policy, env id) must hold every seed of the protocol up to its last one: a gap is an
    episode left out (e.g. a failure's line deleted), which would count the cell's rate without it."""
    public = episodes[episodes["seed_set"] == "public"]
    for (agent, _, env_id), group in public.groupby(["agent", public["policy_sha256"].astype(str), "env_id"]):
        seeds = {int(s) for s in group["seed"]}
        expected = set(public_seeds(max(seeds) - PUBLIC_SEED_BASE + 1)) if min(seeds) >= PUBLIC_SEED_BASE else set()
        missing = sorted(expected - seeds)
        if missing or not expected:
            shown = ", ".join(map(str, missing[:5])) + (", ..." if len(missing) > 5 else "")
            raise ValueError(f"{where}: {agent} on {env_id}: {len(missing)} public seeds of the protocol are missing "
                             f"({shown or 'seeds outside the public set'}): a cell with dropped episodes is "
                             "refused; evaluate into the folder again (it flies the missing ones)")  # fmt: skip


def summarize(episodes: pd.DataFrame) -> pd.DataFrame:
    """One row per agent × env id: n, successes, success rate, 95 % Wilson interval, lap-time stats.

    Raises :class:`MixedResultsError` if one agent × env id holds episodes of more than one ``policy_sha256``.
    """
    rows = []
    for (agent, env_id), group in episodes.groupby(["agent", "env_id"], sort=True):
        n = len(group)
        if "policy_sha256" in group:
            policies = sorted(group["policy_sha256"].astype(str).unique())
            if len(policies) > 1:  # e.g. two evaluations writing into one folder at once: not one policy's rate
                raise MixedResultsError(
                    f"the {n} {env_id} episodes labelled {agent!r} come from {len(policies)} policies (sha256 "
                    f"{', '.join(h[:12] for h in policies)}): a summary row counts one policy's episodes only"
                )
        k = int(group["success"].astype(bool).sum())
        low, high = wilson_interval(k, n)
        laps = pd.to_numeric(group.loc[group["success"].astype(bool), "lap_time"], errors="coerce").dropna()
        track, variant = split_env_id(env_id)
        rows.append(
            {
                "agent": agent,
                "privileged": bool(group["privileged"].astype(bool).any()),
                "env_id": env_id,
                "track": track,
                "variant": variant,
                "n": n,
                "successes": k,
                "success_rate": k / n,
                "sr_ci_low": low,
                "sr_ci_high": high,
                "lap_time_median": float(laps.median()) if len(laps) else float("nan"),
                "lap_time_mean": float(laps.mean()) if len(laps) else float("nan"),
                "lap_time_std": float(laps.std(ddof=1)) if len(laps) > 1 else float("nan"),
            }
        )
    return pd.DataFrame(rows)


def write_tables(out_dir: str | Path) -> pd.DataFrame:
    """Rebuild ``episodes.csv`` and ``summary.csv`` in ``out_dir`` from its valid records; return the episodes."""
    out_dir = Path(out_dir)
    episodes = load_records(out_dir)
    summary = summarize(episodes)  # first: a folder it refuses keeps both of its previous tables
    atomic_write(out_dir / "episodes.csv", episodes.to_csv(index=False))
    atomic_write(out_dir / "summary.csv", summary.to_csv(index=False, float_format="%.4f"))
    return episodes


def _tracks_overlap(track_sets: list[set[str]]) -> bool:
    """Whether any two of these policies' track sets share a track."""
    seen: set[str] = set()
    for flown in track_sets:
        if seen & flown:
            return True
        seen |= flown
    return False


def load_result_dir(path: str | Path, strict: bool = True) -> tuple[Path, pd.DataFrame]:
    """A result directory (or the ``summary.csv`` / ``episodes.csv`` in it) and its valid records' episodes; a path
    without records, or with no valid one, is an error naming it. ``strict`` (tables): an invalid record or a cell
    missing a seed is an error too (:func:`load_records`); a paired comparison pairs only the valid episodes."""
    path = Path(path)
    if path.is_file() and path.name in ("summary.csv", "episodes.csv"):
        path = path.parent
    if not has_records(path):
        raise FileNotFoundError(f"no evaluation records at {str(path)!r} (expected {str(path / RECORDS_FILE)!r})")
    episodes = load_records(path, strict=strict)
    if episodes.empty:
        raise ValueError(f"no valid evaluation records in {str(path)!r}")
    return path, episodes


def _directory_label(path: Path) -> str:
    """A result directory's name for a table row: the run it belongs to, not a generic evaluation folder's name.

    ``eval``, ``eval-*`` and ``exported`` name what was evaluated, not which policy: the parent's name stands
    instead (``distill-ppo-bc/eval-exported`` -> ``distill-ppo-bc``). A per-track or per-seed subfolder (``S``,
    ``Circle``, ``seed1``) keeps its run's name in front (``distill-ppo-gate-centre/Circle``).
    """
    parts = list(path.resolve().parts)
    if parts and (parts[-1] in ("eval", "exported") or parts[-1].startswith("eval-")):
        parts.pop()
    name = parts[-1] if parts else str(path)
    if len(parts) > 1 and (name in TRACK_ORDER or re.fullmatch(r"seed\d+", name)):
        name = f"{parts[-2]}/{name}"
    return name


def check_one_env_version(versions: dict[str, Iterable[int]]) -> int | None:
    """The one env version of the records of several folders (``{folder: their env versions}``), else a ``ValueError``.

    A table never mixes env versions: their scenes (and perhaps their physics) differ, so their cells do not compare.
    Returns ``None`` when no folder holds a record.
    """
    by_version: dict[int, list[str]] = {}
    for folder, found in versions.items():
        for version in sorted({int(v) for v in found}):
            by_version.setdefault(version, []).append(folder)
    if len(by_version) > 1:
        parts = "; ".join(f"env version {v}: {', '.join(folders)}" for v, folders in sorted(by_version.items()))
        raise ValueError(f"records of several env versions in one table ({parts}): a table is of one env version")
    return next(iter(by_version), None)


def read_summaries(paths: Iterable[str | Path]) -> pd.DataFrame:
    """Summaries of result directories, recomputed from their validated records.

    A path to a ``summary.csv`` or ``episodes.csv`` stands for the directory holding it: the CSV itself is
    never read back, so an edited CSV cannot change a table. Several policies under one label form one row when
    their tracks are disjoint (one policy per track), else each is labelled with its directory's name.
    """
    loaded = [load_result_dir(path) for path in paths]
    if not loaded:
        raise ValueError("no result directories given")
    check_one_env_version({str(path): episodes["env_version"] for path, episodes in loaded})
    # One label, several policies. When each policy was flown on tracks no other one was (a sweep's per-track runs
    # of one config and seed, each evaluated on its own track), the label stays one row, as the paper's Table II
    # has one row per method with a policy per track. When their tracks overlap (e.g. per-track students also
    # flown on the other tracks), one row would mix two policies' results on a track: each such policy gets the
    # name of the first directory holding it (see _directory_label), in every directory it appears in.
    tracks: dict[str, dict[str, set[str]]] = {}  # label -> policy -> the tracks it was flown on
    for _, episodes in loaded:
        for (agent, policy), group in episodes.groupby(["agent", episodes["policy_sha256"].astype(str)]):
            tracks.setdefault(str(agent), {}).setdefault(policy, set()).update(group["track"].astype(str))
    shared = {agent for agent, by_policy in tracks.items() if _tracks_overlap(list(by_policy.values()))}
    for agent in sorted(set(tracks) - shared):
        if len(tracks[agent]) > 1:
            per_track = ", ".join(f"{'/'.join(sorted(t))} {h[:12]}" for h, t in sorted(tracks[agent].items()))
            logger.debug("%s: one row of %d policies, one per track (%s)", agent, len(tracks[agent]), per_track)
    renamed: dict[tuple[str, str], str] = {}  # (label, policy) -> label (its first directory's name)
    for path, episodes in loaded:
        where = _directory_label(path)
        for agent, policy in zip(episodes["agent"], episodes["policy_sha256"].astype(str), strict=True):
            if agent in shared:
                renamed.setdefault((agent, policy), f"{agent} ({where})")
    if len(set(renamed.values())) < len(renamed):
        raise ValueError("several policies share a label and a directory name: give them distinct --name labels")
    frames = []
    for _, episodes in loaded:
        if shared & set(episodes["agent"]):
            pairs = zip(episodes["agent"], episodes["policy_sha256"].astype(str), strict=True)
            episodes = episodes.assign(agent=[renamed.get((a, h), a) for a, h in pairs])
        frames.append(summarize(episodes))
    if shared:
        logger.warning("the label(s) %s name several policies: each row is labelled with its directory",
                       ", ".join(sorted(shared)))  # fmt: skip
    return pd.concat(frames, ignore_index=True)


def paired_comparison(a_dir: str | Path, b_dir: str | Path) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Two evaluations compared scene by scene, from their validated records (never their CSVs).

    Each directory must hold one policy's episodes. Episodes are paired by ``(env_id, seed)``: the seed protocol
    gives both policies the same scenes, so a paired test (McNemar's exact test on the laps only one of them
    finished) tells apart rates whose unpaired Wilson intervals overlap. Returns ``(sides, pairs)``: per
    directory its label, policy, episodes, successes, Wilson interval, mean lap and failure causes (every episode of
    the folder); per shared env id, then ``all`` of them pooled, the pairs and, on those paired episodes only, each
    side's successes, 95 % Wilson interval (``sr_ci_low_a`` ...) and mean lap time of its successful laps
    (``lap_time_mean_a``, seconds, NaN without one), then ``only_a``, ``only_b`` and ``p``.
    """
    episodes, sides = [], []
    for path, frame in (load_result_dir(a_dir, strict=False), load_result_dir(b_dir, strict=False)):
        policies = sorted(frame["policy_sha256"].astype(str).unique())
        if len(policies) > 1:
            labels = ", ".join(sorted(set(frame["agent"].astype(str))))
            raise ValueError(f"{str(path)!r} holds {len(policies)} policies' episodes ({labels}): compare one "
                             "policy's evaluation with another's")  # fmt: skip
        frame = frame.assign(success=frame["success"].astype(bool))
        wins, n = int(frame["success"].sum()), len(frame)
        low, high = wilson_interval(wins, n)
        causes = frame.loc[~frame["success"], "crash_reason"].fillna("time limit").astype(str).str.split(":").str[0]
        sides.append({"evaluation": str(path), "agent": str(frame["agent"].iloc[0]), "policy_sha256": policies[0][:12],
                      "n": n, "successes": wins, "success_rate": wins / n, "sr_ci_low": low, "sr_ci_high": high,
                      "lap_time_mean": pd.to_numeric(frame.loc[frame["success"], "lap_time"]).mean(),
                      "failures": {str(k): int(v) for k, v in causes.value_counts().items()}})  # fmt: skip
        frame = frame.assign(lap_time=pd.to_numeric(frame["lap_time"]).where(frame["success"]))
        episodes.append(frame[["env_id", "seed", "success", "lap_time"]])
    a, b = episodes
    shared = [env for env in a["env_id"].unique() if env in set(b["env_id"])]
    rows = []
    for env_id, part_a, part_b in [*((e, a[a["env_id"] == e], b[b["env_id"] == e]) for e in shared), ("all", a, b)]:
        pairs = part_a.merge(part_b, on=["env_id", "seed"], suffixes=("_a", "_b"))
        n, only_a, only_b, p = paired_outcomes(part_a[["env_id", "seed", "success"]],
                                               part_b[["env_id", "seed", "success"]])  # fmt: skip
        row = {"env_id": env_id, "pairs": n}
        for side in "ab":  # each side on the paired episodes only: what the test compares
            wins = int(pairs[f"success_{side}"].sum())
            low, high = wilson_interval(wins, n) if n else (float("nan"), float("nan"))
            row |= {f"successes_{side}": wins, f"sr_ci_low_{side}": low, f"sr_ci_high_{side}": high,
                    f"lap_time_mean_{side}": pairs[f"lap_time_{side}"].mean()}  # fmt: skip
        rows.append({**row, "only_a": only_a, "only_b": only_b, "p": p})
    if rows[-1]["pairs"] == 0:
        raise ValueError(f"{str(a_dir)!r} and {str(b_dir)!r} share no (env_id, seed) episode to pair")
    return pd.DataFrame(sides), pd.DataFrame(rows)
