"""Signed verification results: the verified tier without trusting whoever built the site.

A verification re-flies each ONNX policy of a method entry on the **private** seeds of the maintainers' secret salt
and condenses the private records (which stay outside the repository) into a payload: per env id k/n and the lap
times, the policy file's sha256, the env version, the seed protocol, the salt's fingerprint and the sha256 of the
private records. The maintainers sign its canonical JSON with their Ed25519 key (:func:`sign_entry`) into
``results/leaderboard/<entry>/verified.json``.

``leaderboard build`` accepts it (:func:`check_verified`) only if the public key committed in ``leaderboard.yaml``
is the one whose fingerprint is pinned here (:data:`MAINTAINERS_KEY_SHA256`: a key swapped into the YAML by a pull
request is refused), the signature checks (an edited count is refused), every policy of the entry is signed and its
file still hashes to the signed sha256 (a swapped file is refused), and the env version and salt are current.
Private-seed records alone, however plausible, never make an entry verified: forging them needs no secret, forging
a signature needs the private key.
"""

from __future__ import annotations

import base64
import hashlib
import json
import math
import statistics
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from racebench.envs.registration import ENV_VERSION
from racebench.evaluation.evaluator import Evaluator
from racebench.evaluation.protocol import PERTURBATION_IDS
from racebench.evaluation.records import read_folder
from racebench.evaluation.seeds import salt_sha256
from racebench.leaderboard.entries import UNSEEN_KEY, Cell, Entry, check_seed_prefixes
from racebench.utils.files import sha256_file

VERIFIED_FILE = "verified.json"
#: 2: the payload also signs what the entry's page shows beside the badge (:func:`entry_view_sha256`).
SIGNED_FORMAT = 2
#: sha256 of the raw 32-byte Ed25519 public key of the racebench maintainers (its PEM is in leaderboard.yaml).
#: Pinned in the package so that a pull request which swaps the key in the YAML cannot also swap what it is
#: checked against; rotating the key is a change to this line, reviewed as code.
MAINTAINERS_KEY_SHA256 = "bd807efa2db4e425ba7dac0d02f357f365d462765ca6ffe7fd7356402bb3cef7"


class SignatureError(ValueError):
    """A signed result is refused; the message names the entry and why."""


@dataclass(frozen=True)
class VerifiedResult:
    """A signed result that checked: the signed own-track cells per track and the payload behind them."""

    entry: str
    cells: dict[str, Cell]  # track -> the signed cell of its policy on the track's main id
    payload: dict[str, Any]


def canonical(payload: Mapping[str, Any]) -> bytes:
    """The bytes that are signed: sorted keys, no whitespace, ASCII, no NaN (one spelling per payload)."""
    return json.dumps(payload, sort_keys=True, separators=(",", ":"), ensure_ascii=True, allow_nan=False).encode()


def public_key_sha256(public_key: Any) -> str:
    """The fingerprint of an Ed25519 public key: sha256 of its 32 raw bytes."""
    from cryptography.hazmat.primitives import serialization

    raw = public_key.public_bytes(serialization.Encoding.Raw, serialization.PublicFormat.Raw)
    return hashlib.sha256(raw).hexdigest()


def load_public_key(pem: str) -> Any:
    """An Ed25519 public key from its PEM text; :class:`SignatureError` otherwise."""
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PublicKey

    try:
        key = serialization.load_pem_public_key(pem.encode())
    except (ValueError, TypeError) as exc:
        raise SignatureError(f"the public key in leaderboard.yaml is not a PEM public key ({exc})") from exc
    if not isinstance(key, Ed25519PublicKey):
        raise SignatureError("the public key in leaderboard.yaml is not an Ed25519 key")
    return key


def load_private_key(path: str | Path) -> Any:
    """The maintainers' Ed25519 private key (PKCS#8 PEM, unencrypted); errors never show the key's bytes."""
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

    try:
        key = serialization.load_pem_private_key(Path(path).read_bytes(), password=None)
    except OSError as exc:
        raise SignatureError(f"--key {str(path)!r}: unreadable ({exc.strerror})") from exc
    except (ValueError, TypeError) as exc:
        raise SignatureError(f"--key {str(path)!r}: not an unencrypted PKCS#8 PEM private key") from exc
    if not isinstance(key, Ed25519PrivateKey):
        raise SignatureError(f"--key {str(path)!r}: not an Ed25519 key")
    return key


def records_sha256(records: Sequence[dict[str, Any]]) -> str:
    """sha256 of the records' own digests in (env id, seed) order: pins the private records without publishing them."""
    ordered = sorted(records, key=lambda r: (r["env_id"], int(r["seed"])))
    return hashlib.sha256("\n".join(r["digest"] for r in ordered).encode()).hexdigest()


def cell_payload(records: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """k/n and lap statistics of one env id's records (lap times in seed order, rounded to the microsecond)."""
    ordered = sorted(records, key=lambda r: int(r["seed"]))
    laps = [round(float(r["lap_time"]), 6) for r in ordered if r["success"]]
    return {
        "n": len(ordered),
        "successes": sum(bool(r["success"]) for r in ordered),
        "lap_times": laps,
        "lap_time_mean": round(statistics.fmean(laps), 6) if laps else None,
        "lap_time_std": round(statistics.stdev(laps), 6) if len(laps) > 1 else None,
        "lap_time_median": round(statistics.median(laps), 6) if laps else None,
    }


def check_private_records(name: str, line: str, records: Sequence[dict[str, Any]], onnx_sha256: str, salt: str) -> None:
    """:class:`SignatureError` unless ``records`` (entry ``name``'s policy line ``line``) are of the ONNX file
    ``onnx_sha256``, on this salt's private seeds (the first n, none picked), of this env version, made from
    committed code and unprivileged."""
    if not records:
        raise SignatureError(f"{name}: no private records of its {line} policy")
    fingerprint = salt_sha256(salt)
    for record in records:
        problem = None
        if record["policy_sha256"] != onnx_sha256:
            problem = f"is of another policy (sha256 {record['policy_sha256'][:12]}…)"
        elif record["seed_set"] != "private" or record.get("seed_salt_sha256") != fingerprint:
            problem = "is not on the private seeds of this salt"
        elif record["env_version"] != ENV_VERSION:
            problem = f"is of env version {record['env_version']}, this racebench is {ENV_VERSION}"
        elif record["git_dirty"]:
            problem = "was made from uncommitted code (git_dirty): evaluate from a clean checkout"
        elif record["privileged"]:
            problem = "is privileged"
        if problem:
            where = f"({record['env_id']}, seed {record['seed']})"
            raise SignatureError(f"{name}: a record of its {line} policy {where} {problem}")
    check_seed_prefixes(name, records, salt)  # every episode flown, none picked


def build_payload(entry: Entry, private_records: Mapping[str, Sequence[dict[str, Any]]], salt: str) -> dict[str, Any]:
    """The payload of ``entry`` from each track's private records (validated: ONNX, this salt, first n seeds, clean).

    ``private_records``: track key of the entry (``S``, ``Circle``, ``J`` or ``all``) -> that policy's records.
    """
    fingerprint = salt_sha256(salt)
    policies = []
    for track, policy in entry.policies.items():
        if policy.onnx is None:
            raise SignatureError(f"{entry.name}: its {track} policy has no ONNX file: only ONNX policies are verified")
        records = list(private_records.get(track, ()))
        check_private_records(entry.name, track, records, policy.onnx_sha256, salt)
        by_id: dict[str, list[dict[str, Any]]] = {}
        for record in records:
            by_id.setdefault(record["env_id"], []).append(record)
        missing = [i for i in policy.main_ids if i not in by_id]
        if missing:
            raise SignatureError(f"{entry.name}: its {track} policy has no private records on {missing}")
        policies.append(
            {
                "track": track,
                "policy": policy.onnx,
                "policy_sha256": policy.onnx_sha256,
                "cells": {env_id: cell_payload(group) for env_id, group in sorted(by_id.items())},
                "records_sha256": records_sha256(records),
                "git_commits": sorted({r["git_commit"] for r in records}),
            }
        )
    protocols = {int(r["seed_protocol"]) for group in private_records.values() for r in group}
    if len(protocols) != 1:
        raise SignatureError(f"{entry.name}: private records of several seed protocols {sorted(protocols)}")
    return {
        "format": SIGNED_FORMAT,
        "entry": entry.name,
        "env_version": ENV_VERSION,
        "seed_set": "private",
        "seed_protocol": protocols.pop(),
        "seed_salt_sha256": fingerprint,
        "policies": policies,
        "entry_sha256": entry_view_sha256(entry),
    }


def entry_view(entry: Entry) -> dict[str, Any]:
    """What an entry's page shows beside the verified badge, besides the signed private cells: its metadata
    (description, authors, teacher, what it sees, ...) and each policy line (the public-records policy and its
    sha256, the ONNX export, the record folders and their records' digests, the training budget).

    The records of the robustness suite's perturbation ids (:data:`~racebench.evaluation.protocol.PERTURBATION_IDS`)
    are left out of the digests: they join an entry's record folders after it is signed (the maintainers evaluate
    every method on the suite), they are public-seed numbers that are never ranked, and the page shows them as
    such, not as signed ones. Leaving them out keeps every signature made before the suite existed: without them
    the view is byte for byte what was signed. They are validated on load like every record (of the policy's
    sha256, the current env version, the first n seeds)."""
    policies = {}
    for track, policy in sorted(entry.policies.items()):
        digests = "\n".join(sorted(r["digest"] for r in policy.records if r["env_id"] not in PERTURBATION_IDS))
        policies[track] = {
            "policy": policy.policy, "policy_sha256": policy.sha256, "onnx": policy.onnx,
            "onnx_sha256": policy.onnx_sha256, "records": list(policy.records_dirs),
            "records_sha256": hashlib.sha256(digests.encode()).hexdigest(),
            "steps": policy.steps, "wall_clock_s": policy.wall_clock_s, "budget_source": policy.budget_source,
        }  # fmt: skip
    # the unseen-tracks line is not signed (its cells are public records, shown as such): adding one keeps a signature
    meta = {k: v for k, v in entry.meta.items() if k not in ("policies", UNSEEN_KEY)}
    return {"meta": meta, "policies": policies}


def entry_view_sha256(entry: Entry) -> str:
    """sha256 of the canonical JSON of :func:`entry_view`: signed with the private cells (format 2)."""
    return hashlib.sha256(canonical(entry_view(entry))).hexdigest()


#: The entries signed in format 1 (whose payload did not cover :func:`entry_view`), with the sha256 of their view
#: when they were signed: such a signature stands only while the entry's page shows exactly that. Pinned here, as
#: the key is, so that a pull request cannot change both; a new signature (format 2) needs no line here.
FORMAT1_VIEWS: dict[str, str] = {
    "state-ppo": "1311bc4d3bf966c5b4a6108f86c038cecd584a0c7de5f94b0589e8ff571ac9ee",
    "vision-com": "65ac1818c05af213eaa00299c5337bd657107bb2a5ca4a40701f4780c1587119",
    "vision-distill": "23d32ce1903acbaefd3671c4ba243cf80e7f0f3f7226498a6b8b7d66956d4602",
    "vision-distill-ppo": "27a6568d168ac7bfe5d728826ed96d43e1f5ed129c259e4738276f0fdce49801",
    "vision-ppo": "22380e793dee78fd09f3bbdce84d6f223c0ff66d3232dccdd1279131f9900a44",
}


def sign_payload(payload: Mapping[str, Any], private_key: Any) -> dict[str, Any]:
    """The ``verified.json`` document: the payload, its Ed25519 signature and the signing key's fingerprint."""
    signature = private_key.sign(canonical(payload))
    return {
        "payload": dict(payload),
        "signature": base64.b64encode(signature).decode(),
        "key_sha256": public_key_sha256(private_key.public_key()),
    }


def outside_repository(entry: Entry, private_dir: str | Path) -> Path:
    """``private_dir`` resolved; :class:`SignatureError` if it lies inside the repository (private seeds and
    records are never committed)."""
    private_dir = Path(private_dir).resolve()
    if private_dir.is_relative_to(entry.root.resolve()):
        raise SignatureError(f"--private-records {str(private_dir)!r} lies inside the repository; the private "
                             "records must stay outside it")  # fmt: skip
    return private_dir


def fly_private(
    entry: Entry, onnx: str, env_ids: Sequence[str], out: Path, episodes: int, workers: int, salt: str
) -> list[dict[str, Any]]:  # fmt: skip
    """Fly the entry's ONNX file ``onnx`` on the first ``episodes`` private seeds of each of ``env_ids`` into
    ``out`` (resumable: records already there are reused) and return those records."""
    earlier = read_folder(out).sorted_records() if out.is_dir() else []
    # Resuming keeps the label the earlier records carry (the evaluator refuses two labels in one folder).
    label = earlier[0]["agent"] if earlier else out.name
    evaluator = Evaluator(
        str(entry.root / onnx), list(env_ids), episodes=episodes, out_dir=out, workers=workers,
        agent_name=label, seed_set="private", salt=salt,
    )  # fmt: skip
    evaluator.run(progress=False)
    wanted = {(env_id, seed) for env_id in env_ids for seed in evaluator.seeds}
    found = read_folder(out)
    if found.problems:
        raise SignatureError(f"{entry.name}: invalid private record {found.problems[0].error()}")
    return [record for record in found.sorted_records() if (record["env_id"], record["seed"]) in wanted]


def sign_entry(
    entry: Entry, salt: str, key_path: str | Path, private_dir: str | Path, episodes: int = 50, workers: int = 1
) -> Path:
    """Fly each ONNX policy of ``entry`` on its own main ids' private seeds into ``private_dir/<entry>-<track>``
    (resumable: records already there are reused), sign the result and write ``<entry folder>/verified.json``.

    ``private_dir`` must lie outside the repository: private seeds and records are never committed.
    """
    key = load_private_key(key_path)
    private_dir = outside_repository(entry, private_dir)
    private: dict[str, list[dict[str, Any]]] = {}
    for track, policy in entry.policies.items():
        if policy.onnx is None:
            raise SignatureError(f"{entry.name}: its {track} policy has no ONNX file: only ONNX policies are verified")
        out = private_dir / f"{entry.name}-{track}"
        private[track] = fly_private(entry, policy.onnx, policy.main_ids, out, episodes, workers, salt)
    document = sign_payload(build_payload(entry, private, salt), key)
    path = entry.folder / VERIFIED_FILE
    path.write_text(json.dumps(document, indent=1, sort_keys=True) + "\n")
    return path


def read_signed(
    entry: Entry, filename: str, config: Mapping[str, Any], pinned_key_sha256: str | None = None
) -> dict[str, Any]:  # fmt: skip
    """The payload of the entry's signed document ``filename`` once its signature checks against the pinned
    maintainers' key and it is of this env version and a listed salt; :class:`SignatureError` names why not."""
    pinned_key_sha256 = pinned_key_sha256 or MAINTAINERS_KEY_SHA256  # read now: tests pin their own key
    path = entry.folder / filename
    if not path.is_file():
        raise SignatureError(f"{entry.name}: no signed result ({filename})")
    try:
        document = json.loads(path.read_text())
        payload, signature = document["payload"], base64.b64decode(document["signature"], validate=True)
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise SignatureError(f"{entry.name}: {filename} is not a signed result ({exc})") from exc
    pem = config.get("maintainers_public_key")
    if not isinstance(pem, str):
        raise SignatureError(f"{entry.name}: leaderboard.yaml has no maintainers_public_key to check the signature")
    public_key = load_public_key(pem)
    if public_key_sha256(public_key) != pinned_key_sha256:
        raise SignatureError(
            f"{entry.name}: the public key in leaderboard.yaml (sha256 {public_key_sha256(public_key)[:12]}…) is not "
            f"the maintainers' key pinned in racebench (sha256 {pinned_key_sha256[:12]}…): signature not trusted"
        )
    from cryptography.exceptions import InvalidSignature

    try:
        public_key.verify(signature, canonical(payload))
    except (InvalidSignature, ValueError, TypeError) as exc:
        raise SignatureError(
            f"{entry.name}: the signature of {filename} does not check against the maintainers' key "
            "(the result was edited after signing, or signed by another key)"
        ) from exc
    # Signed, so the payload is the maintainers' own words: what remains is whether it still describes this entry.
    if payload.get("env_version") != ENV_VERSION:
        raise SignatureError(
            f"{entry.name}: signed on env version {payload.get('env_version')}, this racebench is {ENV_VERSION}: "
            "verify again"
        )
    if payload.get("seed_salt_sha256") not in config.get("private_salt_sha256", []):
        raise SignatureError(f"{entry.name}: signed on the seeds of a salt not listed in leaderboard.yaml")
    return payload


def check_signed_file(entry: Entry, path: str, signed_sha256: str) -> None:
    """:class:`SignatureError` unless the entry's file ``path`` still hashes to the signed sha256."""
    actual = sha256_file(entry.root / path) if (entry.root / path).is_file() else "missing"
    if actual != signed_sha256:
        raise SignatureError(
            f"{entry.name}: the policy file {path} (sha256 {actual[:12]}…) is not the one signed "
            f"(sha256 {signed_sha256[:12]}…): swapped after signing"
        )


def signed_cell(entry: Entry, env_id: str, c: Mapping[str, Any]) -> Cell:
    """The :class:`Cell` of a signed cell payload, once its counts and lap times agree."""
    laps = tuple(float(t) for t in c["lap_times"])
    if not (0 <= c["successes"] <= c["n"] and len(laps) == c["successes"] and all(map(math.isfinite, laps))):
        raise SignatureError(f"{entry.name}: the signed {env_id} cell is inconsistent")
    return Cell(env_id, "private", c["n"], c["successes"], laps)


def check_verified(entry: Entry, config: Mapping[str, Any], pinned_key_sha256: str | None = None) -> VerifiedResult:
    """Check ``entry``'s ``verified.json`` against the pinned key; :class:`SignatureError` names why it is refused."""
    payload = read_signed(entry, VERIFIED_FILE, config, pinned_key_sha256)
    if payload.get("format") not in (1, SIGNED_FORMAT) or payload.get("entry") != entry.name:
        raise SignatureError(f"{entry.name}: the signed result is of entry {payload.get('entry')!r}")
    signed = {p["track"]: p for p in payload["policies"]}
    if set(signed) != set(entry.policies):
        raise SignatureError(
            f"{entry.name}: the signed result covers tracks {sorted(signed)}, the entry has {sorted(entry.policies)}"
        )
    cells: dict[str, Cell] = {}
    for track, policy in entry.policies.items():
        mine = signed[track]
        if policy.onnx != mine["policy"]:
            raise SignatureError(
                f"{entry.name}: the {track} policy is {policy.onnx!r}, the signed one {mine['policy']!r}"
            )
        check_signed_file(entry, policy.onnx, mine["policy_sha256"])
        for env_id in policy.main_ids:
            c = mine["cells"].get(env_id)
            if c is None:
                raise SignatureError(f"{entry.name}: the signed result has no {env_id} cell for its {track} policy")
            cells[env_id] = signed_cell(entry, env_id, c)
    view = entry_view_sha256(entry)
    signed_view = payload.get("entry_sha256") if payload["format"] == SIGNED_FORMAT else FORMAT1_VIEWS.get(entry.name)
    if view != signed_view:
        raise SignatureError(
            f"{entry.name}: its metadata or policy lines (what its page shows beside the badge, sha256 {view[:12]}…) "
            "changed after signing: sign it again"
        )
    return VerifiedResult(entry.name, cells, payload)
