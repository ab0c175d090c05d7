"""``racebench leaderboard verify``: re-evaluate entries and test every committed cell against the replay.

For each cell (env id × seed set) of an entry's records the policy is flown again on the first ``n`` seeds of
that set (``n`` = the committed count, or fewer with ``--episodes``), and

* the **success count** is tested with :func:`racebench.evaluation.statistics.counts_consistent` (two-sided Fisher exact
  test at α = :data:`~racebench.evaluation.statistics.CONSISTENCY_ALPHA` = 0.001): a faithful claim fails by chance
  in at
  most 0.1 % of cells, so an entry of ``c`` cells in at most ``c`` × 0.1 % of verifications (union bound);
* the **mean lap time** (over successes) of the replay must lie within :func:`lap_tolerance` of the committed
  mean over the same seeds: ``LAP_ABS_TOL_S`` + ``LAP_SE_FACTOR`` standard errors of the difference
  (0.2 s + 4 SE). A replay on the same seeds is positively correlated with the claim, so under normal lap
  times this fails a faithful claim far less than the 6e-5 of two independent samples. Checked only when
  both sides have at least two laps;
* for a **deterministic built-in** (:data:`DETERMINISTIC_BUILTINS`) every replayed episode must match its committed
  record in every field that decides the outcome (:data:`REPLAYED_FIELDS`: success, gates, steps, lap time, crash):
  such an agent's episode is a function of its seed, so one edited record fails the entry, where the counts and
  means above would let a single changed episode through.

Why not bit-identical for the others: a learned policy's closed loop amplifies last-bit float differences between
CPUs (docs/evaluation.md, "What is reproducible where"), so the promise is the rate, tested statistically.
"""

from __future__ import annotations

import math
import shutil
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from racebench.evaluation.evaluator import Evaluator
from racebench.evaluation.seeds import salt_from_env, salt_sha256
from racebench.evaluation.statistics import CONSISTENCY_ALPHA, counts_consistent
from racebench.leaderboard.entries import (
    UNSEEN_KEY,
    Cell,
    Entry,
    EntryError,
    Policy,
    _spec_at,
    check_seed_prefixes,
    summarize_cells,
)

LAP_ABS_TOL_S = 0.2
LAP_SE_FACTOR = 4.0
#: Built-ins whose episode is a function of its seed: hover (a constant action), random (its generator reseeded
#: from the episode seed), and the planners and the gate follower (computed from the scene the seed draws, without
#: clocks, threads or unseeded randomness). ``tests/test_records.py`` replays them bit for bit.
DETERMINISTIC_BUILTINS: frozenset[str] = frozenset({"hover", "random", "planner", "planner-fast", "follow"})
#: The record fields a deterministic built-in's replay must reproduce exactly.
REPLAYED_FIELDS: tuple[str, ...] = ("success", "gates_passed", "steps", "lap_time", "crashed", "crash_reason")


@dataclass(frozen=True)
class CellCheck:
    """The verdict on one committed cell: success counts, their p-value, lap times and their tolerance."""

    entry: str
    env_id: str
    seed_set: str
    committed: tuple[int, int]
    replayed: tuple[int, int]
    p_value: float
    lap_committed: float  # committed mean lap time over the replayed seeds (nan: no laps)
    lap_replayed: float
    lap_tolerance: float  # nan: lap times not checked (fewer than two laps on a side)
    episodes_compared: int = 0  # replayed episodes compared field by field (0: not a deterministic built-in)
    mismatches: tuple[str, ...] = ()  # one line per episode that replayed otherwise than its record

    @property
    def count_ok(self) -> bool:
        """The success counts are consistent at α = 0.001."""
        return self.p_value >= CONSISTENCY_ALPHA

    @property
    def lap_ok(self) -> bool:
        """The mean lap times agree within the tolerance (True when not checked)."""
        if math.isnan(self.lap_tolerance):
            return True
        return abs(self.lap_replayed - self.lap_committed) <= self.lap_tolerance

    @property
    def episodes_ok(self) -> bool:
        """Every episode compared replayed as recorded (True when none was compared)."""
        return not self.mismatches

    @property
    def ok(self) -> bool:
        """Every check passes."""
        return self.count_ok and self.lap_ok and self.episodes_ok

    def line(self) -> str:
        """One human-readable line of the verdict."""
        (k0, n0), (k1, n1) = self.committed, self.replayed
        lap = "laps not checked (< 2 on a side)"
        if not math.isnan(self.lap_tolerance):
            delta = self.lap_replayed - self.lap_committed
            lap = f"lap {self.lap_committed:.2f} → {self.lap_replayed:.2f} s"
            lap += f" (Δ {delta:+.2f}, tolerance {self.lap_tolerance:.2f})"
        failed = [what for what, ok in (("count", self.count_ok), ("lap", self.lap_ok), ("episodes", self.episodes_ok))
                  if not ok]  # fmt: skip
        verdict = "ok" if self.ok else f"FAIL ({', '.join(failed)})"
        episodes = ""
        if self.episodes_compared:
            bad = len(self.mismatches)
            episodes = f"; episodes {self.episodes_compared - bad}/{self.episodes_compared} replayed as recorded"
            episodes += f" ({self.mismatches[0]}{', …' if bad > 1 else ''})" if bad else ""
        return (
            f"{verdict:<18} {self.entry} {self.env_id} [{self.seed_set}]: committed {k0}/{n0}, replayed {k1}/{n1}, "
            f"Fisher p={self.p_value:.3g}; {lap}{episodes}"
        )


def lap_tolerance(committed: Sequence[float], replayed: Sequence[float]) -> float:
    """Allowed |difference of mean lap times|: 0.2 s + 4 standard errors (nan with fewer than 2 laps a side)."""
    if len(committed) < 2 or len(replayed) < 2:
        return float("nan")

    def var(x: Sequence[float]) -> float:
        mean = sum(x) / len(x)
        return sum((v - mean) ** 2 for v in x) / (len(x) - 1)

    se = math.sqrt(var(committed) / len(committed) + var(replayed) / len(replayed))
    return LAP_ABS_TOL_S + LAP_SE_FACTOR * se


def _outcome(record: dict[str, Any]) -> dict[str, Any]:
    """The :data:`REPLAYED_FIELDS` of a record or an ``episodes.csv`` row (a missing lap or reason as None)."""
    out = {}
    for key in REPLAYED_FIELDS:
        value = record[key]
        if value is None or (isinstance(value, float) and math.isnan(value)):
            value = None
        elif key in ("success", "crashed"):
            value = bool(value)
        elif key in ("gates_passed", "steps"):
            value = int(value)
        elif key == "lap_time":
            value = float(value)
        out[key] = value
    return out


def compare_episodes(committed: Sequence[dict[str, Any]], replayed: Sequence[dict[str, Any]]) -> list[str]:
    """One line per replayed episode whose outcome differs from its committed record of the same seed.

    A seed replayed but not committed is a mismatch too (the committed cell must hold every seed replayed).
    """
    by_seed = {int(r["seed"]): _outcome(r) for r in committed}
    lines = []
    for row in sorted(replayed, key=lambda r: int(r["seed"])):
        seed, again = int(row["seed"]), _outcome(row)
        claimed = by_seed.get(seed)
        if claimed is None:
            lines.append(f"seed {seed}: replayed, not committed")
            continue
        diff = [f"{k} {claimed[k]!r} → {again[k]!r}" for k in REPLAYED_FIELDS if claimed[k] != again[k]]
        if diff:
            lines.append(f"seed {seed}: {', '.join(diff)}")
    return lines


def check_cell(
    entry: str,
    committed: Cell,
    committed_laps_same_seeds: Sequence[float],
    replayed: Cell,
    mismatches: Sequence[str] = (),
    episodes_compared: int = 0,
) -> CellCheck:
    """Compare one committed cell with its replay (counts: the whole committed cell; laps: the same seeds).

    ``mismatches`` and ``episodes_compared`` carry :func:`compare_episodes`' verdict for a deterministic agent.
    """
    consistency = counts_consistent((committed.successes, committed.n), (replayed.successes, replayed.n))
    laps0, laps1 = list(committed_laps_same_seeds), list(replayed.lap_times)
    return CellCheck(
        entry=entry,
        env_id=committed.env_id,
        seed_set=committed.seed_set,
        committed=(committed.successes, committed.n),
        replayed=(replayed.successes, replayed.n),
        p_value=consistency.p_value,
        lap_committed=sum(laps0) / len(laps0) if laps0 else float("nan"),
        lap_replayed=sum(laps1) / len(laps1) if laps1 else float("nan"),
        lap_tolerance=lap_tolerance(laps0, laps1),
        episodes_compared=episodes_compared,
        mismatches=tuple(mismatches),
    )


def verify_entry(
    entry: Entry,
    out_dir: str | Path,
    episodes: int | None = None,
    trust_code: bool = False,
    workers: int = 1,
    salt: str | None = None,
    fresh: bool = False,
) -> list[CellCheck]:
    """Re-evaluate each policy of ``entry`` into ``out_dir/<entry>/<track>`` (resumable); check each committed cell.

    ``episodes`` replays only the first ``episodes`` seeds of each cell (default: as many as committed).
    Private-seed cells need the salt (``salt`` or ``RACEBENCH_PRIVATE_SALT``) whose hash their records carry.
    ``fresh`` discards the replays of an earlier verification first (else they are reused).
    """
    if episodes is not None and episodes < 1:
        raise ValueError(f"--episodes must be >= 1, got {episodes}")
    if fresh:
        shutil.rmtree(Path(out_dir) / entry.name, ignore_errors=True)
    checks: list[CellCheck] = []
    lines = [*entry.policies.items(), *([(UNSEEN_KEY, entry.unseen)] if entry.unseen is not None else [])]
    for track, policy in lines:  # the unseen-tracks policy too: its public cells are replayed like the others
        checks += _verify_policy(entry, track, policy, out_dir, episodes, trust_code, workers, salt)
    return checks


def _verify_policy(
    entry: Entry, track: str, policy: Policy, out_dir: str | Path, episodes: int | None, trust_code: bool,
    workers: int, salt: str | None,
) -> list[CellCheck]:  # fmt: skip
    """:func:`verify_entry` for one policy of the entry (its records, flown again into ``<out>/<entry>/<track>``)."""
    label = f"{entry.name}/{track}"
    spec = policy.builtin or _spec_at(policy.policy, entry.root)
    groups: dict[tuple[str, str | None, str], list[dict[str, Any]]] = {}
    for record in policy.records:
        key = (record["seed_set"], record.get("seed_salt_sha256"), record["renderer"])
        groups.setdefault(key, []).append(record)
    checks: list[CellCheck] = []
    for (seed_set, salt_hash, renderer), records in sorted(groups.items(), key=lambda kv: str(kv[0])):
        group_salt = None
        if seed_set == "private":
            group_salt = salt if salt is not None else salt_from_env()
            if salt_sha256(group_salt) != salt_hash:
                raise EntryError(
                    f"{label}: its private records were made with the salt of sha256 {salt_hash[:12]}…, "
                    f"not the one given (sha256 {salt_sha256(group_salt)[:12]}…)"
                )
            check_seed_prefixes(label, records, group_salt)  # with the salt, private seeds can be checked too
        folder = Path(out_dir) / entry.name / track / f"{seed_set}-{renderer}" / (salt_hash[:12] if salt_hash else "")
        for env_id, cell in summarize_cells(records).items():
            n = min(cell.n, episodes) if episodes else cell.n
            evaluator = Evaluator(
                spec, [env_id], episodes=n, out_dir=folder, workers=workers, agent_name=label,
                renderer=renderer, trust_code=trust_code, seed_set=seed_set, salt=group_salt,
            )  # fmt: skip
            evaluator.run(progress=False)
            rows = evaluator.selected.to_dict("records")
            replayed = summarize_cells(rows)[env_id]
            seeds = set(evaluator.seeds)
            same = [
                float(r["lap_time"]) for r in records if r["env_id"] == env_id and r["success"] and r["seed"] in seeds
            ]
            mismatches: list[str] = []
            if policy.builtin in DETERMINISTIC_BUILTINS:
                mismatches = compare_episodes([r for r in records if r["env_id"] == env_id], rows)
            compared = len(rows) if policy.builtin in DETERMINISTIC_BUILTINS else 0
            checks.append(check_cell(label, cell, same, replayed, mismatches, compared))
    return checks
