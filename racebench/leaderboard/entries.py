"""Leaderboard entries: ``<leaderboard>/<entry>/entry.yaml``, the records it points to, and its computed tier.

An entry names one policy that is already in the repository (its path and the sha256 of its bytes, or a
built-in agent as ``builtin:<name>``), who made it and how, and the result folders holding its evaluation
records. Paths are relative to the repository root, the folder two levels above the leaderboard folder
(``results/leaderboard`` → the checkout). Every record an entry points to must be valid
(:func:`racebench.records.read_record`) and of exactly that policy and the current env version.

The tier is computed, never declared:

* ``reference``: a privileged built-in (``planner``, ``follow``): it reads the true scene, so it is shown for
  scale and never ranked;
* ``verified``: an ONNX policy (running it runs no code from the file) with records on the **private** seed set
  of a salt the maintainers published the hash of (:data:`CONFIG_FILE`, ``private_salt_sha256``); it is ranked
  on those records only;
* ``self-reported``: anything else (SB3 ``.zip``, Python classes, non-privileged built-ins, public seeds); ranked
  on its public-seed records.
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from racebench.agents import BUILTIN_AGENTS, BUILTIN_PRIVILEGED, AgentLoadError, builtin_identity, policy_identity
from racebench.evaluation import SUITES, TRACK_ORDER, split_env_id
from racebench.records import InvalidRecordError, read_record
from racebench.registration import ENV_VERSION
from racebench.statistics import wilson_interval

ENTRY_FILE = "entry.yaml"
#: Leaderboard-wide settings, beside the entries: the fingerprints of the maintainers' private salts.
CONFIG_FILE = "leaderboard.yaml"
DEFAULT_LEADERBOARD = Path("results") / "leaderboard"
TIERS: tuple[str, ...] = ("verified", "self-reported", "reference")
MAIN_IDS: tuple[str, ...] = tuple(SUITES["main"])
OBS_MODES: tuple[str, ...] = ("vision", "state")
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$")
_HEX64 = re.compile(r"^[0-9a-f]{64}$")
# Field -> (accepted types, required). ``notes`` is free text for what the fields cannot say.
META_FIELDS: dict[str, tuple[tuple[type, ...], bool]] = {
    "name": ((str,), True),
    "authors": ((list,), True),
    "method": ((str,), True),
    "link": ((str,), True),
    "obs_mode": ((str,), True),
    "training_steps": ((int,), True),
    "training_wall_clock_s": ((int, float), True),
    "hardware": ((str,), True),
    "training_seeds": ((list,), True),
    "policy": ((str,), True),
    "policy_sha256": ((str,), True),
    "records": ((list,), True),
    "notes": ((str,), False),
}


class EntryError(ValueError):
    """An entry or its metadata is invalid; the message names the entry (or file) and the reason."""


@dataclass(frozen=True)
class Cell:
    """The summary of one entry's records on one env id and seed set."""

    env_id: str
    seed_set: str
    n: int
    successes: int
    lap_times: tuple[float, ...]

    @property
    def success_rate(self) -> float:
        """Successes over episodes."""
        return self.successes / self.n

    @property
    def interval(self) -> tuple[float, float]:
        """95 % Wilson interval of the success rate."""
        return wilson_interval(self.successes, self.n)

    @property
    def lap_time_mean(self) -> float:
        """Mean lap time over the successful episodes (nan without one)."""
        return sum(self.lap_times) / len(self.lap_times) if self.lap_times else float("nan")


@dataclass
class Entry:
    """One leaderboard entry: its metadata (``meta``, as in ``entry.yaml``), folder and repository root."""

    meta: dict[str, Any]
    folder: Path
    root: Path
    records: list[dict[str, Any]] = field(default_factory=list)

    @property
    def name(self) -> str:
        """The entry's unique name (also its folder's name)."""
        return self.meta["name"]

    @property
    def builtin(self) -> str | None:
        """The built-in agent's name for ``policy: builtin:<name>``, else None."""
        policy = self.meta["policy"]
        return policy.split(":", 1)[1] if policy.startswith("builtin:") else None

    @property
    def agent_spec(self) -> str:
        """The spec the evaluator loads this policy from (a path relative to the working directory)."""
        return self.builtin or _spec_at(self.meta["policy"], self.root)

    @property
    def kind(self) -> str:
        """``builtin``, ``onnx``, ``sb3`` or ``python``."""
        if self.builtin:
            return "builtin"
        policy = self.meta["policy"]
        return "onnx" if policy.endswith(".onnx") else "sb3" if policy.endswith(".zip") else "python"

    @property
    def privileged(self) -> bool:
        """Whether the evaluator makes this policy privileged (only built-ins can be)."""
        return bool(self.builtin and BUILTIN_PRIVILEGED[self.builtin])

    def tier(self, accepted_salts: Iterable[str] = ()) -> str:
        """The computed tier (see the module docstring) given the maintainers' salt fingerprints."""
        if self.privileged or any(r["privileged"] for r in self.records):
            return "reference"
        accepted = set(accepted_salts)
        if self.kind == "onnx" and any(r.get("seed_salt_sha256") in accepted for r in self.records):
            return "verified"
        return "self-reported"

    def ranked_records(self, accepted_salts: Iterable[str] = ()) -> list[dict[str, Any]]:
        """The records its ranking is computed from: the accepted private ones if verified, else the public ones."""
        accepted = set(accepted_salts)
        if self.tier(accepted) == "verified":
            return [r for r in self.records if r.get("seed_salt_sha256") in accepted]
        return [r for r in self.records if r["seed_set"] == "public"]

    def cells(self, accepted_salts: Iterable[str] = ()) -> dict[str, Cell]:
        """One :class:`Cell` per env id of :meth:`ranked_records`."""
        return summarize_cells(self.ranked_records(accepted_salts))


def summarize_cells(records: Sequence[dict[str, Any]]) -> dict[str, Cell]:
    """Group records by env id (they must share a seed set) into :class:`Cell` summaries."""
    groups: dict[str, list[dict[str, Any]]] = {}
    for record in records:
        groups.setdefault(record["env_id"], []).append(record)
    cells = {}
    for env_id, group in groups.items():
        sets = {r["seed_set"] for r in group}
        if len(sets) != 1:
            raise EntryError(f"{env_id}: records of several seed sets {sorted(sets)} in one cell")
        laps = tuple(float(r["lap_time"]) for r in group if r["success"])
        cells[env_id] = Cell(env_id, sets.pop(), len(group), sum(bool(r["success"]) for r in group), laps)
    return dict(sorted(cells.items(), key=lambda kv: _id_order(kv[0])))


def _id_order(env_id: str) -> tuple[int, str, int]:
    track, variant = split_env_id(env_id)
    return (0 if variant == "default" else 1, variant, TRACK_ORDER.index(track) if track in TRACK_ORDER else 9)


def _spec_at(policy: str, root: Path) -> str:
    """The policy's spec with its file path resolved against ``root`` (relative to the cwd when inside it)."""
    file_part, colon, cls_name = policy.partition(":") if ":" in policy else (policy, "", "")
    absolute = (root / file_part).resolve()
    try:
        shown = str(absolute.relative_to(Path.cwd().resolve()))
    except ValueError:
        shown = str(absolute)
    return f"{shown}{colon}{cls_name}"


def repo_root(leaderboard: Path) -> Path:
    """The repository root of a leaderboard folder: two levels above it (``results/leaderboard``)."""
    return Path(leaderboard).resolve().parents[1]


def _inside(path: Path, root: Path, what: str, name: str) -> Path:
    resolved = (root / path).resolve()
    if Path(path).is_absolute() or not resolved.is_relative_to(root.resolve()):
        raise EntryError(f"{name}: {what} {str(path)!r} must be a path inside the repository, relative to its root")
    return resolved


def validate_meta(meta: Any, root: Path, where: str) -> dict[str, Any]:
    """Check an entry's metadata (types, values, the policy's sha256 against its bytes); return it."""
    if not isinstance(meta, dict):
        raise EntryError(f"{where}: expected a YAML mapping of the entry fields, got {type(meta).__name__}")
    missing = [k for k, (_, required) in META_FIELDS.items() if required and k not in meta]
    if missing:
        raise EntryError(f"{where}: missing fields {missing}")
    unknown = sorted(set(meta) - set(META_FIELDS))
    if unknown:
        raise EntryError(f"{where}: unknown fields {unknown} (allowed: {list(META_FIELDS)})")
    for key, (types, _) in META_FIELDS.items():
        if key in meta and (not isinstance(meta[key], types) or isinstance(meta[key], bool)):
            raise EntryError(f"{where}: {key} is {meta[key]!r}, expected {'/'.join(t.__name__ for t in types)}")
    name = meta["name"]
    if not _NAME.match(name):
        raise EntryError(f"{where}: name {name!r} must be 1-64 letters, digits, '.', '_' or '-' (it names a folder)")
    if not meta["authors"] or not all(isinstance(a, str) and a.strip() for a in meta["authors"]):
        raise EntryError(f"{where}: authors must be a non-empty list of names")
    for key in ("method", "link", "hardware"):
        if not meta[key].strip():
            raise EntryError(f"{where}: {key} is empty")
    if meta["obs_mode"] not in OBS_MODES:
        raise EntryError(f"{where}: obs_mode {meta['obs_mode']!r} not in {OBS_MODES}")
    if (
        meta["training_steps"] < 0
        or not math.isfinite(meta["training_wall_clock_s"])
        or (meta["training_wall_clock_s"] < 0)
    ):
        raise EntryError(f"{where}: training_steps and training_wall_clock_s must be >= 0")
    if not all(isinstance(s, int) and not isinstance(s, bool) and 0 <= s < 1_000_000 for s in meta["training_seeds"]):
        raise EntryError(f"{where}: training_seeds must be integers below 1,000,000 (evaluation seeds lie above)")
    if meta["training_steps"] > 0 and not meta["training_seeds"]:
        raise EntryError(f"{where}: a trained policy lists its training seeds")
    if not _HEX64.match(meta["policy_sha256"]):
        raise EntryError(f"{where}: policy_sha256 is not a lower-case sha256 hex digest")
    actual = policy_sha256(meta["policy"], root, name)
    if actual != meta["policy_sha256"]:
        raise EntryError(
            f"{where}: policy_sha256 {meta['policy_sha256'][:12]}… does not match {meta['policy']!r} "
            f"(its bytes hash to {actual[:12]}…)"
        )
    if not meta["records"] or not all(isinstance(r, str) for r in meta["records"]):
        raise EntryError(f"{where}: records must list at least one result folder (paths relative to the root)")
    return meta


def policy_sha256(policy: str, root: Path, name: str = "entry") -> str:
    """The sha256 the records of ``policy`` carry: of the file's bytes, or of a built-in's name and version."""
    if policy.startswith("builtin:"):
        builtin = policy.split(":", 1)[1]
        if builtin not in BUILTIN_AGENTS:
            raise EntryError(f"{name}: unknown built-in {builtin!r} (built-ins: {BUILTIN_AGENTS})")
        return builtin_identity(builtin).sha256
    file_part = policy.partition(":")[0] if ":" in policy else policy
    path = _inside(Path(file_part), root, "policy", name)
    if not path.is_file():
        raise EntryError(f"{name}: policy file {file_part!r} does not exist in the repository")
    try:
        return policy_identity(_spec_at(policy, root)).sha256
    except AgentLoadError as exc:
        raise EntryError(f"{name}: {exc}") from exc


def load_entry_records(meta: dict[str, Any], root: Path) -> list[dict[str, Any]]:
    """Every record of the entry's result folders, validated, of its policy and the current env version."""
    name = meta["name"]
    records: list[dict[str, Any]] = []
    seen: set[str] = set()
    for folder in meta["records"]:
        directory = _inside(Path(folder), root, "records folder", name)
        paths = sorted((directory / "records").glob("*.json"))
        if not paths:
            raise EntryError(f"{name}: no records in {folder!r} (expected {folder}/records/*.json)")
        for path in paths:
            try:
                record = read_record(path)
            except InvalidRecordError as exc:
                raise EntryError(f"{name}: invalid record {exc}") from exc
            if record["policy_sha256"] != meta["policy_sha256"]:
                raise EntryError(
                    f"{name}: {path} is a record of another policy (sha256 {record['policy_sha256'][:12]}…)"
                )
            if record["env_version"] != ENV_VERSION:
                raise EntryError(
                    f"{name}: {path} is of env version {record['env_version']}, this racebench is {ENV_VERSION}: "
                    "re-evaluate the entry"
                )
            if path.name in seen:  # the same slot through two folders would count one episode twice
                raise EntryError(f"{name}: episode {path.name} is in two of its records folders")
            seen.add(path.name)
            records.append(record)
    check_seed_prefixes(name, records)
    return records


def check_seed_prefixes(name: str, records: Sequence[dict[str, Any]], salt: str | None = None) -> None:
    """Each public cell must hold exactly the first ``n`` seeds of the protocol (private ones too, given the salt).

    Otherwise a submitter could fly 200 episodes and commit the best 50 (cherry-picking), or drop the crashes.
    """
    from racebench.leaderboard.seeds import seeds_for

    cells: dict[tuple[str, str, str], set[int]] = {}
    for record in records:
        cells.setdefault((record["env_id"], record["seed_set"], record["renderer"]), set()).add(record["seed"])
    for (env_id, seed_set, renderer), seeds in sorted(cells.items()):
        if seed_set == "private" and salt is None:
            continue  # membership of a private set needs its salt: checked by verify
        expected = set(seeds_for(seed_set, len(seeds), salt))
        if seeds != expected:
            missing = sorted(expected - seeds)[:3]
            raise EntryError(
                f"{name}: the {seed_set}-seed episodes of {env_id} ({renderer}) are not the first {len(seeds)} seeds "
                f"of the protocol (missing e.g. {missing}): every episode flown must be committed, none picked"
            )


def load_entry(folder: str | Path, root: str | Path | None = None) -> Entry:
    """Load and validate ``folder/entry.yaml`` and its records (root: see :func:`repo_root`)."""
    folder = Path(folder)
    root = Path(root) if root is not None else repo_root(folder.parent)
    path = folder / ENTRY_FILE
    try:
        meta = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise EntryError(f"{path}: unreadable ({exc})") from exc
    meta = validate_meta(meta, root, str(path))
    if meta["name"] != folder.name:
        raise EntryError(f"{path}: name {meta['name']!r} differs from its folder {folder.name!r}")
    return Entry(meta, folder, root, load_entry_records(meta, root))


def load_config(leaderboard: str | Path) -> dict[str, Any]:
    """``leaderboard.yaml``: ``private_salt_sha256``, the list of accepted salt fingerprints (empty if absent)."""
    path = Path(leaderboard) / CONFIG_FILE
    if not path.is_file():
        return {"private_salt_sha256": []}
    try:
        config = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as exc:
        raise EntryError(f"{path}: unreadable ({exc})") from exc
    salts = config.get("private_salt_sha256") or []
    if not isinstance(salts, list) or not all(isinstance(s, str) and _HEX64.match(s) for s in salts):
        raise EntryError(f"{path}: private_salt_sha256 must be a list of sha256 hex digests")
    return {**config, "private_salt_sha256": salts}


def load_entries(leaderboard: str | Path, names: Sequence[str] | None = None) -> list[Entry]:
    """Every entry under ``leaderboard`` (or the named ones), sorted by name; names are unique."""
    leaderboard = Path(leaderboard)
    if not leaderboard.is_dir():
        raise EntryError(f"no leaderboard folder at {str(leaderboard)!r}")
    folders = sorted(p.parent for p in leaderboard.glob(f"*/{ENTRY_FILE}"))
    if names:
        known = {f.name for f in folders}
        unknown = [n for n in names if n not in known]
        if unknown:
            raise EntryError(f"no entry named {unknown} in {leaderboard} (entries: {sorted(known)})")
        folders = [f for f in folders if f.name in names]
    root = repo_root(leaderboard)
    return [load_entry(f, root) for f in folders]


def add_entry(
    leaderboard: str | Path,
    policy: str,
    meta: dict[str, Any],
    records: Sequence[str] = (),
    evaluate_episodes: int = 0,
    trust_code: bool = False,
    workers: int = 1,
) -> Entry:
    """Create ``<leaderboard>/<meta name>/entry.yaml`` for ``policy`` (a repository path or ``builtin:<name>``).

    ``meta`` holds the descriptive fields; ``policy`` and ``records`` (result folders, relative to the root) are
    added, ``policy_sha256`` is computed (a declared one must match). With ``evaluate_episodes > 0`` the policy
    is first evaluated on the main suite's public seeds into ``<entry>/eval-public`` (resumable), which becomes
    one of its records folders. A name already used by an entry is refused (case-insensitive: it names a
    folder). ``entry.yaml`` is written last, so a failed run leaves no entry.
    """
    from racebench.evaluation import Evaluator

    leaderboard = Path(leaderboard)
    root = repo_root(leaderboard)
    if not isinstance(meta, dict):
        raise EntryError(f"the metadata must be a YAML mapping of the entry fields, got {type(meta).__name__}")
    name = meta.get("name")
    if not isinstance(name, str) or not _NAME.match(name):
        raise EntryError(f"name {name!r} must be 1-64 letters, digits, '.', '_' or '-' (it names a folder)")
    taken = {p.parent.name.lower() for p in leaderboard.glob(f"*/{ENTRY_FILE}")}
    if name.lower() in taken:
        raise EntryError(f"an entry named {name!r} already exists in {leaderboard}; choose another name")
    if not policy.startswith("builtin:") and policy in BUILTIN_AGENTS:
        policy = f"builtin:{policy}"
    if not policy.startswith("builtin:"):
        file_part, colon, cls_name = policy.partition(":") if ":" in policy else (policy, "", "")
        absolute = Path(file_part).resolve()
        if not absolute.is_relative_to(root):
            raise EntryError(f"policy {policy!r} must be a file inside the repository ({root}); commit it there first")
        policy = f"{absolute.relative_to(root).as_posix()}{colon}{cls_name}"
    digest = policy_sha256(policy, root, name)
    declared = meta.get("policy_sha256")
    if declared is not None and declared != digest:
        raise EntryError(
            f"{name}: declared policy_sha256 {str(declared)[:12]}… but {policy!r} hashes to {digest[:12]}…"
        )
    folder = leaderboard / name
    folders = [Path(os.path.relpath(Path(r).resolve(), root)).as_posix() for r in records]
    full = {**meta, "policy": policy, "policy_sha256": digest, "records": folders}
    if evaluate_episodes > 0:
        out = folder / "eval-public"
        rel = out.resolve().relative_to(root).as_posix()
        full["records"] = [*folders, rel] if rel not in folders else folders
        validate_meta({**full, "records": full["records"]}, root, name)  # bad metadata fails before flying
        spec = Entry(full, folder, root).agent_spec
        Evaluator(
            spec, ["main"], episodes=evaluate_episodes, out_dir=out, agent_name=name,
            trust_code=trust_code, workers=workers,
        ).run(progress=False)  # fmt: skip
    full = validate_meta(full, root, name)
    entry = Entry(full, folder, root, load_entry_records(full, root))
    folder.mkdir(parents=True, exist_ok=True)
    ordered = {k: full[k] for k in META_FIELDS if k in full}
    (folder / ENTRY_FILE).write_text(yaml.safe_dump(ordered, sort_keys=False, allow_unicode=True, width=110))
    return entry
