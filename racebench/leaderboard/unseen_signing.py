"""Signed private-seed verification of an entry's unseen-tracks line (issue 73): the unseen ranking's verified cell.

The unseen-tracks ranking (:mod:`racebench.leaderboard.unseen`) counts a method's public records on the committed
held-out tracks. Anyone can fly those tracks, and a policy tuned on them would look general. On the private seeds of
the maintainers' salt, ``RaceObs-Unseen-v0`` generates a track of its own for every episode (the seed names the
track), so a private-seed count is on tracks nobody has seen. :func:`sign_unseen` flies the line's ONNX file there
and signs the result into ``<entry>/verified-unseen.json``, with the signing of :mod:`racebench.leaderboard.signing`
(the same key, salt and record checks). :func:`check_unseen_verified` accepts it only if the signature checks against
the pinned key, the ONNX file still hashes to the signed sha256 and the unseen line (its files, records and budget,
:func:`unseen_view`) is what was signed. It is a second file: adding or re-signing it leaves the entry's per-track
signature (``verified.json``) as it was, and either stands alone.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from racebench.envs.registration import ENV_VERSION
from racebench.evaluation.seeds import salt_sha256
from racebench.leaderboard.entries import UNSEEN_ID, UNSEEN_KEY, Cell, Entry
from racebench.leaderboard.signing import (
    SignatureError,
    canonical,
    cell_payload,
    check_private_records,
    check_signed_file,
    fly_private,
    load_private_key,
    outside_repository,
    read_signed,
    records_sha256,
    sign_payload,
    signed_cell,
)

UNSEEN_VERIFIED_FILE = "verified-unseen.json"
UNSEEN_SIGNED_FORMAT = 1
#: Private episodes signed by default: as many as the public ranked count (each its own generated track).
UNSEEN_PRIVATE_EPISODES = 100


def unseen_view(entry: Entry) -> dict[str, Any]:
    """What the entry's pages show of its unseen line beside the signed cell: the policy flown on the public records
    and its sha256, the ONNX file, the records folders and the digest of their records, the training budget."""
    line = entry.unseen
    if line is None:
        raise SignatureError(f"{entry.name}: no {UNSEEN_KEY}: line to verify")
    digests = "\n".join(sorted(r["digest"] for r in line.records))
    return {
        "policy": line.policy, "policy_sha256": line.sha256, "onnx": line.onnx, "onnx_sha256": line.onnx_sha256,
        "records": list(line.records_dirs), "records_sha256": hashlib.sha256(digests.encode()).hexdigest(),
        "steps": line.steps, "wall_clock_s": line.wall_clock_s, "budget_source": line.budget_source,
    }  # fmt: skip


def unseen_view_sha256(entry: Entry) -> str:
    """sha256 of the canonical JSON of :func:`unseen_view`: signed with the private cell."""
    return hashlib.sha256(canonical(unseen_view(entry))).hexdigest()


def build_unseen_payload(entry: Entry, records: Sequence[dict[str, Any]], salt: str) -> dict[str, Any]:
    """The payload of ``entry``'s unseen line from its private records on ``RaceObs-Unseen-v0`` (validated: its
    ONNX file, this salt, the first n seeds, committed code)."""
    line = entry.unseen
    if line is None or line.onnx is None:
        raise SignatureError(f"{entry.name}: its {UNSEEN_KEY} line has no ONNX file: only ONNX policies are verified")
    records = [r for r in records if r["env_id"] == UNSEEN_ID]
    check_private_records(entry.name, UNSEEN_KEY, records, line.onnx_sha256, salt)
    protocols = {int(r["seed_protocol"]) for r in records}
    if len(protocols) != 1:
        raise SignatureError(f"{entry.name}: private records of several seed protocols {sorted(protocols)}")
    return {
        "format": UNSEEN_SIGNED_FORMAT,
        "kind": UNSEEN_KEY,
        "entry": entry.name,
        "env_id": UNSEEN_ID,
        "env_version": ENV_VERSION,
        "seed_set": "private",
        "seed_protocol": protocols.pop(),
        "seed_salt_sha256": salt_sha256(salt),
        "policy": line.onnx,
        "policy_sha256": line.onnx_sha256,
        "cell": cell_payload(records),
        "records_sha256": records_sha256(records),
        "git_commits": sorted({r["git_commit"] for r in records}),
        "unseen_sha256": unseen_view_sha256(entry),
    }


def sign_unseen(
    entry: Entry, salt: str, key_path: str | Path, private_dir: str | Path, episodes: int = UNSEEN_PRIVATE_EPISODES,
    workers: int = 1,
) -> Path:  # fmt: skip
    """Fly the ONNX file of ``entry``'s unseen line on ``episodes`` private seeds of ``RaceObs-Unseen-v0`` into
    ``private_dir/<entry>-unseen`` (resumable), sign the result and write ``<entry folder>/verified-unseen.json``."""
    key = load_private_key(key_path)
    line = entry.unseen
    if line is None or line.onnx is None:
        raise SignatureError(f"{entry.name}: its {UNSEEN_KEY} line has no ONNX file: only ONNX policies are verified")
    out = outside_repository(entry, private_dir) / f"{entry.name}-{UNSEEN_KEY}"
    records = fly_private(entry, line.onnx, (UNSEEN_ID,), out, episodes, workers, salt)
    document = sign_payload(build_unseen_payload(entry, records, salt), key)
    path = entry.folder / UNSEEN_VERIFIED_FILE
    path.write_text(json.dumps(document, indent=1, sort_keys=True) + "\n")
    return path


def check_unseen_verified(
    entry: Entry, config: Mapping[str, Any], pinned_key_sha256: str | None = None
) -> Cell:  # fmt: skip
    """The signed private cell of ``entry``'s unseen line; :class:`SignatureError` names why it is refused."""
    payload = read_signed(entry, UNSEEN_VERIFIED_FILE, config, pinned_key_sha256)
    if payload.get("format") != UNSEEN_SIGNED_FORMAT or payload.get("kind") != UNSEEN_KEY:
        raise SignatureError(f"{entry.name}: {UNSEEN_VERIFIED_FILE} is not a signed unseen-tracks result")
    if payload.get("entry") != entry.name or payload.get("env_id") != UNSEEN_ID:
        raise SignatureError(f"{entry.name}: the signed unseen-tracks result is of entry {payload.get('entry')!r}")
    line = entry.unseen
    if line is None or line.onnx != payload["policy"]:
        now = None if line is None else line.onnx
        raise SignatureError(
            f"{entry.name}: its {UNSEEN_KEY} ONNX file is {now!r}, the signed one {payload['policy']!r}"
        )
    check_signed_file(entry, line.onnx, payload["policy_sha256"])
    cell = signed_cell(entry, UNSEEN_ID, payload["cell"])
    if unseen_view_sha256(entry) != payload.get("unseen_sha256"):
        raise SignatureError(
            f"{entry.name}: its {UNSEEN_KEY} line (files, records or budget) changed after signing: sign it again"
        )
    return cell
