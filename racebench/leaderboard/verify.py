"""``racebench leaderboard verify``: re-evaluate entries and test every committed cell against the replay.

For each cell (env id × seed set) of an entry's records the policy is flown again on the first ``n`` seeds of
that set (``n`` = the committed count, or fewer with ``--episodes``), and

* the **success count** is tested with :func:`racebench.statistics.counts_consistent` (two-sided Fisher exact
  test at α = :data:`~racebench.statistics.CONSISTENCY_ALPHA` = 0.001): a faithful claim fails by chance in at
  most 0.1 % of cells, so an entry of ``c`` cells in at most ``c`` × 0.1 % of verifications (union bound);
* the **mean lap time** (over successes) of the replay must lie within :func:`lap_tolerance` of the committed
  mean over the same seeds: ``LAP_ABS_TOL_S`` + ``LAP_SE_FACTOR`` standard errors of the difference
  (0.2 s + 4 SE). A replay on the same seeds is positively correlated with the claim, so under normal lap
  times this fails a faithful claim far less than the 6e-5 of two independent samples. Checked only when
  both sides have at least two laps.

Why not bit-identical: a learned policy's closed loop amplifies last-bit float differences between CPUs
(README, "What is reproducible where"), so the promise is the rate, tested statistically.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from racebench.leaderboard.entries import Cell, Entry, EntryError, check_seed_prefixes, summarize_cells
from racebench.leaderboard.seeds import salt_from_env, salt_sha256
from racebench.statistics import CONSISTENCY_ALPHA, counts_consistent

LAP_ABS_TOL_S = 0.2
LAP_SE_FACTOR = 4.0


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
    def ok(self) -> bool:
        """Both checks pass."""
        return self.count_ok and self.lap_ok

    def line(self) -> str:
        """One human-readable line of the verdict."""
        (k0, n0), (k1, n1) = self.committed, self.replayed
        lap = "laps not checked (< 2 on a side)"
        if not math.isnan(self.lap_tolerance):
            delta = self.lap_replayed - self.lap_committed
            lap = f"lap {self.lap_committed:.2f} → {self.lap_replayed:.2f} s"
            lap += f" (Δ {delta:+.2f}, tolerance {self.lap_tolerance:.2f})"
        verdict = (
            "ok" if self.ok else "FAIL" + ("" if self.count_ok else " (count)") + ("" if self.lap_ok else " (lap)")
        )
        return (
            f"{verdict:<18} {self.entry} {self.env_id} [{self.seed_set}]: committed {k0}/{n0}, replayed {k1}/{n1}, "
            f"Fisher p={self.p_value:.3g}; {lap}"
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


def check_cell(entry: str, committed: Cell, committed_laps_same_seeds: Sequence[float], replayed: Cell) -> CellCheck:
    """Compare one committed cell with its replay (counts: the whole committed cell; laps: the same seeds)."""
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
    """Re-evaluate ``entry`` into ``out_dir / entry.name`` (resumable) and check each of its committed cells.

    ``episodes`` replays only the first ``episodes`` seeds of each cell (default: as many as committed).
    Private-seed cells need the salt (``salt`` or ``RACEBENCH_PRIVATE_SALT``) whose hash their records carry.
    ``fresh`` discards the replays of an earlier verification first (else they are reused).
    """
    import shutil

    from racebench.evaluation import Evaluator

    if episodes is not None and episodes < 1:
        raise ValueError(f"--episodes must be >= 1, got {episodes}")
    groups: dict[tuple[str, str | None, str], list[dict[str, Any]]] = {}
    for record in entry.records:
        key = (record["seed_set"], record.get("seed_salt_sha256"), record["renderer"])
        groups.setdefault(key, []).append(record)
    if fresh:
        shutil.rmtree(Path(out_dir) / entry.name, ignore_errors=True)
    checks: list[CellCheck] = []
    for (seed_set, salt_hash, renderer), records in sorted(groups.items(), key=lambda kv: str(kv[0])):
        group_salt = None
        if seed_set == "private":
            group_salt = salt if salt is not None else salt_from_env()
            if salt_sha256(group_salt) != salt_hash:
                raise EntryError(
                    f"{entry.name}: its private records were made with the salt of sha256 {salt_hash[:12]}…, "
                    f"not the one given (sha256 {salt_sha256(group_salt)[:12]}…)"
                )
            check_seed_prefixes(entry.name, records, group_salt)  # with the salt, private seeds can be checked too
        folder = Path(out_dir) / entry.name / f"{seed_set}-{renderer}" / (salt_hash[:12] if salt_hash else "")
        for env_id, cell in summarize_cells(records).items():
            n = min(cell.n, episodes) if episodes else cell.n
            evaluator = Evaluator(
                entry.agent_spec, [env_id], episodes=n, out_dir=folder, workers=workers, agent_name=entry.name,
                renderer=renderer, trust_code=trust_code, seed_set=seed_set, salt=group_salt,
            )  # fmt: skip
            evaluator.run(progress=False)
            replayed = summarize_cells(evaluator.selected.to_dict("records"))[env_id]
            seeds = set(evaluator.seeds)
            same = [
                float(r["lap_time"]) for r in records if r["env_id"] == env_id and r["success"] and r["seed"] in seeds
            ]
            checks.append(check_cell(entry.name, cell, same, replayed))
    return checks
