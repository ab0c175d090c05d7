"""The unseen-tracks column and ranking of the site (issue 73): one policy per method on the held-out tracks.

A method names the one policy it flies on ``RaceObs-Unseen-v0`` under ``unseen:`` in its ``entry.yaml``
(:data:`~racebench.leaderboard.entries.UNSEEN_KEY`). Its cell is that policy's public records on the first
:data:`UNSEEN_RANKED_EPISODES` evaluation seeds: evaluation episode ``i`` flies held-out track ``i mod 100``, so the
ranked count is every held-out track once. The ranking is its own, beside the main one (which it never changes): by
success rate, then mean lap time, then name. A method with fewer episodes is shown and not ranked; one without an
``unseen`` line shows "—" and is not ranked there; privileged built-ins are references, shown for scale. A cell is
the line's public-seed records (self-reported), unless the maintainers signed the line's ONNX file on private seeds
(:mod:`racebench.leaderboard.unseen_signing`, ``verified-unseen.json``): then it is the signed private cell, on tracks
generated from seeds nobody knows. A method's per-track signature does not cover this line.

This module holds the cells and the order; the site's HTML of them is
:func:`racebench.leaderboard.ranking.unseen_section` and :func:`racebench.leaderboard.pages.unseen_entry_html`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from racebench.agents.base import BUILTIN_PRIVILEGED
from racebench.evaluation.seeds import public_seeds
from racebench.leaderboard.entries import UNSEEN_ID, Cell, Entry, Policy, summarize_cells
from racebench.leaderboard.signing import SignatureError
from racebench.leaderboard.unseen_signing import UNSEEN_VERIFIED_FILE, check_unseen_verified

#: Public episodes a method is ranked on: the first this many seeds of the protocol, every held-out track once.
UNSEEN_RANKED_EPISODES = 100
NO_POLICY = "—"  # the cell of a method without an unseen-tracks policy


def unseen_cell(entry: Entry, episodes: int | None = UNSEEN_RANKED_EPISODES) -> Cell | None:
    """The public cell of ``entry``'s unseen-tracks policy on ``RaceObs-Unseen-v0``: of the first ``episodes`` seeds
    (``None``: every committed one); ``None`` without such a policy or records."""
    if entry.unseen is None:
        return None
    first = set(public_seeds(episodes)) if episodes is not None else None
    records = [
        r
        for r in entry.unseen.records
        if r["env_id"] == UNSEEN_ID and r["seed_set"] == "public" and (first is None or r["seed"] in first)
    ]
    return summarize_cells(records).get(UNSEEN_ID)


def _privileged(policy: Policy) -> bool:
    builtin = bool(policy.builtin and BUILTIN_PRIVILEGED.get(policy.builtin))
    return builtin or any(r["privileged"] for r in policy.records)


@dataclass
class UnseenRow:
    """One method in the unseen-tracks ranking."""

    entry: Entry
    cell: Cell | None  # the ranked cell: the signed private one if the line is verified, else the public one
    signed: bool = False  # whether ``cell`` is the maintainers' signed private-seed cell
    refusal: str | None = None  # why its verified-unseen.json was refused (None: none, or accepted)

    @property
    def reference(self) -> bool:
        """Whether it reads the true scene (a privileged built-in): shown, never ranked."""
        return self.entry.privileged or (self.entry.unseen is not None and _privileged(self.entry.unseen))

    @property
    def ranked(self) -> bool:
        """A learned method with a signed private cell or the protocol's full public count on the held-out tracks."""
        full = self.cell is not None and (self.signed or self.cell.n >= UNSEEN_RANKED_EPISODES)
        return not self.reference and full

    @property
    def seeds(self) -> str:
        """Which seeds its cell was flown on."""
        return "private (signed)" if self.signed else "public"

    def key(self) -> tuple[float, float]:
        """Success rate on the held-out tracks, then the mean lap time (NaN without a lap)."""
        return (self.cell.success_rate, self.cell.lap_time_mean) if self.cell else (0.0, math.nan)


def unseen_row(
    entry: Entry, config: Mapping[str, Any] | None = None, pinned_key_sha256: str | None = None
) -> UnseenRow:  # fmt: skip
    """``entry``'s row: its signed private cell where ``verified-unseen.json`` checks against ``config``'s key
    (pinned: see :func:`~racebench.leaderboard.signing.read_signed`), else its public cell (and why the signed
    one was refused). Without ``config`` no signature is read."""
    public = unseen_cell(entry)
    if config is None or entry.unseen is None or not (entry.folder / UNSEEN_VERIFIED_FILE).is_file():
        return UnseenRow(entry, public)
    try:
        return UnseenRow(entry, check_unseen_verified(entry, config, pinned_key_sha256), signed=True)
    except SignatureError as exc:
        return UnseenRow(entry, public, refusal=str(exc))


def unseen_rows(
    entries: Sequence[Entry], config: Mapping[str, Any] | None = None, pinned_key_sha256: str | None = None
) -> list[UnseenRow]:  # fmt: skip
    """Every entry in the order the site lists them: ranked, then unranked with a cell, references, then "—"."""

    def order(row: UnseenRow) -> tuple[int, float, float, str]:
        group = 0 if row.ranked else 3 if row.cell is None else 2 if row.reference else 1
        sr, lap = row.key()
        return group, -sr, lap if not math.isnan(lap) else math.inf, row.entry.name

    return sorted((unseen_row(e, config, pinned_key_sha256) for e in entries), key=order)
