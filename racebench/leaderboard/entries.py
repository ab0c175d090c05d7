"""Leaderboard entries: ``<leaderboard>/<entry>/entry.yaml``, one **method** each, its policies and their records.

An entry is a method, as a row of the paper's Table II: one policy per track (``S``, ``Circle``, ``J``) or one
policy for all three (``all``). Each policy is one line of ``policies``::

    policies:
      S: {policy: baselines/checkpoints/x-S/x-S.zip, onnx: baselines/checkpoints/x-S/x-S.onnx, records: [...]}

``policy`` is the file (or ``builtin:<name>``) its public records were flown with, ``onnx`` its ONNX export (what
the maintainers verify), ``records`` the result folders of its evaluation records, and optional ``steps`` and
``wall_clock_s`` its training budget (else read from ``summary.json`` beside the policy). Paths are relative to the
repository root, two levels above the leaderboard folder. Every record must be valid
(:func:`racebench.evaluation.records.read_record`) and of exactly that policy and the current env version; a new entry's
records must also come from committed code (``git_dirty: false``).

One more optional line, ``unseen: {policy: ..., records: [...]}``, names the one policy the method flies on the held-out
tracks (``RaceObs-Unseen-v0``): the site's unseen-tracks column and ranking (:mod:`racebench.leaderboard.unseen`), from
its public records, checked like every policy line's; it is outside the signed view (a signature covers the per-track
policies' private cells).

A policy is judged on its **own** track: the track's main id (and its density and gate-shift ids where it has
them). The rank key is the mean of the three own-track success rates, then the mean lap time; a method without
all three tracks is listed unranked. Success of a per-track policy on the other tracks is cross-track
generalisation: shown, never the key.

The tier is computed, never declared: ``reference`` for a privileged built-in (shown for scale, never ranked);
``verified`` for an entry whose signed result (:mod:`racebench.leaderboard.signing`) checks against the pinned
maintainers' key and whose ONNX files are still the signed ones (ranked on the signed private-seed numbers);
``self-reported`` for everything else (ranked on its public-seed records). Private-seed records without a valid
signature never make an entry verified.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from racebench.agents.base import BUILTIN_AGENTS, BUILTIN_PRIVILEGED, AgentLoadError
from racebench.agents.trust import VecNormalizeChoiceError, builtin_identity, policy_identity
from racebench.envs.registration import ENV_VERSION
from racebench.evaluation.protocol import SUITES, TRACK_ORDER, split_env_id
from racebench.evaluation.records import RECORDS_FILE, has_records, name_of, read_folder
from racebench.evaluation.seeds import seeds_for
from racebench.evaluation.statistics import wilson_interval
from racebench.utils.files import sha256_file
from racebench.utils.yamlfile import yaml_problem

ENTRY_FILE = "entry.yaml"
#: Leaderboard-wide settings, beside the entries: the salts' fingerprints and the maintainers' public key.
CONFIG_FILE = "leaderboard.yaml"
DEFAULT_LEADERBOARD = Path("results") / "leaderboard"
TIERS: tuple[str, ...] = ("verified", "self-reported", "reference")
MAIN_IDS: tuple[str, ...] = tuple(SUITES["main"])
TRACK_MAIN: dict[str, str] = {t: f"RaceObs-{t}-v0" for t in TRACK_ORDER}
ALL_TRACKS = "all"  # the key of one policy flown on every track
POLICY_KEYS: tuple[str, ...] = (*TRACK_ORDER, ALL_TRACKS)
#: The entry.yaml key of the one policy a method flies on the held-out tracks (``RaceObs-Unseen-v0``), a policy line
#: beside ``policies``: the unseen-tracks column and ranking (:mod:`racebench.leaderboard.unseen`).
UNSEEN_KEY = "unseen"
UNSEEN_ID = "RaceObs-Unseen-v0"
OBS_MODES: tuple[str, ...] = ("vision", "state")
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$")
_HEX64 = re.compile(r"^[0-9a-f]{64}$")
MAX_DESCRIPTION = 240
# Field -> (accepted types, required). ``notes`` is free text for what the fields cannot say.
META_FIELDS: dict[str, tuple[tuple[type, ...], bool]] = {
    "name": ((str,), True),
    "description": ((str,), True),
    "authors": ((list,), True),
    "obs_mode": ((str,), True),
    "teacher": ((str,), True),
    "config": ((str,), True),
    "command": ((str,), True),
    "hardware": ((str,), True),
    "training_seeds": ((list,), True),
    "policies": ((dict,), True),
    "notes": ((str,), False),
    UNSEEN_KEY: ((dict,), False),
}
POLICY_FIELDS: dict[str, tuple[tuple[type, ...], bool]] = {
    "policy": ((str,), True),
    "records": ((list,), True),
    "onnx": ((str,), False),
    "steps": ((int,), False),
    "wall_clock_s": ((int, float), False),
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
class Policy:
    """One policy of a method entry: its track key, the file its public records were flown with, its ONNX export."""

    track: str  # S | Circle | J | all
    policy: str  # a repository path (or file.py:Class) or builtin:<name>
    sha256: str
    records_dirs: list[str]
    onnx: str | None = None
    onnx_sha256: str | None = None
    steps: int | None = None
    wall_clock_s: float | None = None
    budget_source: str = "unknown"  # "entry.yaml", "summary.json" or "unknown"
    records: list[dict[str, Any]] = field(default_factory=list)

    @property
    def builtin(self) -> str | None:
        """The built-in agent's name for ``builtin:<name>``, else None."""
        return self.policy.split(":", 1)[1] if self.policy.startswith("builtin:") else None

    @property
    def kind(self) -> str:
        """``builtin``, ``onnx``, ``sb3`` or ``python``: how its public records were flown."""
        if self.builtin:
            return "builtin"
        return "onnx" if self.policy.endswith(".onnx") else "sb3" if self.policy.endswith(".zip") else "python"

    @property
    def tracks(self) -> tuple[str, ...]:
        """The tracks this policy is judged on: its own, or all three."""
        return TRACK_ORDER if self.track == ALL_TRACKS else (self.track,)

    @property
    def main_ids(self) -> tuple[str, ...]:
        """The main ids of :attr:`tracks`."""
        return tuple(TRACK_MAIN[t] for t in self.tracks)

    def own(self, env_id: str) -> bool:
        """Whether ``env_id`` (a main, density or gate-shift id) is of one of its own tracks."""
        return split_env_id(env_id)[0] in self.tracks


@dataclass
class Entry:
    """One method entry: its metadata (``meta``, as in ``entry.yaml``), folder, repository root and policies."""

    meta: dict[str, Any]
    folder: Path
    root: Path
    policies: dict[str, Policy] = field(default_factory=dict)
    unseen: Policy | None = None  # the policy flown on the held-out tracks (entry.yaml's ``unseen``), if any

    @property
    def name(self) -> str:
        """The entry's unique name (also its folder's name)."""
        return self.meta["name"]

    @property
    def records(self) -> list[dict[str, Any]]:
        """Every record of every policy."""
        return [r for p in self.policies.values() for r in p.records]

    @property
    def tracks(self) -> tuple[str, ...]:
        """The tracks it has a policy for, in the paper's order."""
        covered = {t for p in self.policies.values() for t in p.tracks}
        return tuple(t for t in TRACK_ORDER if t in covered)

    @property
    def complete(self) -> bool:
        """Whether it has a policy for each of the three tracks (only then is it ranked)."""
        return len(self.tracks) == len(TRACK_ORDER)

    @property
    def privileged(self) -> bool:
        """Whether a policy reads the true scene (only built-ins can be, or records say so)."""
        return any(
            (p.builtin and BUILTIN_PRIVILEGED.get(p.builtin, False)) or any(r["privileged"] for r in p.records)
            for p in self.policies.values()
        )

    @property
    def privileged_teacher(self) -> bool:
        """Whether it learned from a teacher that reads the true scene (a privileged built-in)."""
        return self.meta["teacher"] != "none"

    @property
    def kind(self) -> str:
        """The kinds of its policies' files, e.g. ``sb3 + onnx`` (an ONNX export beside each); ``onnx`` once where
        the policy is the ONNX file itself."""
        kinds = sorted({p.kind for p in self.policies.values()})
        exported = all(p.onnx for p in self.policies.values()) and "onnx" not in kinds
        return "/".join(kinds) + (" + onnx" if exported else "")

    def policy_for(self, track: str) -> Policy | None:
        """The policy it flies on ``track`` (its own or the all-track one), None without one."""
        return next((p for p in self.policies.values() if track in p.tracks), None)

    def public_records(self, track: str) -> list[dict[str, Any]]:
        """The public-seed records of its ``track`` policy on ``track``'s ids (main, density, gate shift)."""
        policy = self.policy_for(track)
        if policy is None:
            return []
        return [r for r in policy.records if r["seed_set"] == "public" and split_env_id(r["env_id"])[0] == track]

    def own_cells(self) -> dict[str, Cell]:
        """Public-seed cells of each track's policy on that track's ids (main, density, gate shift)."""
        return summarize_cells([r for t in self.tracks for r in self.public_records(t)])

    def cross_cells(self) -> dict[str, Cell]:
        """Public cells of its per-track policies on the *other* main ids (cross-track generalisation)."""
        cells: dict[str, Cell] = {}
        for policy in self.policies.values():
            if policy.track == ALL_TRACKS:
                continue
            other = [r for r in policy.records if r["seed_set"] == "public" and r["env_id"] in MAIN_IDS
                     and not policy.own(r["env_id"])]  # fmt: skip
            for env_id, cell in summarize_cells(other).items():
                cells[f"{policy.track}→{env_id}"] = cell
        return cells

    def budget(self) -> tuple[int | None, float | None]:
        """Total training steps and wall clock over its policies (None where a policy's budget is unknown)."""
        steps = [p.steps for p in self.policies.values()]
        wall = [p.wall_clock_s for p in self.policies.values()]
        return (
            None if any(s is None for s in steps) else sum(steps),
            None if any(w is None for w in wall) else float(sum(wall)),
        )


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
    """Check an entry's metadata (types, values, each policy line); return it. Hashes are checked on load."""
    if not isinstance(meta, dict):
        raise EntryError(f"{where}: expected a YAML mapping of the entry fields, got {type(meta).__name__}")
    _check_fields(meta, META_FIELDS, where)
    name = meta["name"]
    if not _NAME.match(name):
        raise EntryError(f"{where}: name {name!r} must be 1-64 letters, digits, '.', '_' or '-' (it names a folder)")
    if not meta["authors"] or not all(isinstance(a, str) and a.strip() for a in meta["authors"]):
        raise EntryError(f"{where}: authors must be a non-empty list of names")
    for key in ("description", "config", "command", "hardware", "teacher"):
        if not meta[key].strip():
            raise EntryError(f"{where}: {key} is empty")
    description = meta["description"]
    if "\n" in description.strip() or len(description) > MAX_DESCRIPTION:
        raise EntryError(f"{where}: description must be one line of at most {MAX_DESCRIPTION} characters")
    if meta["teacher"] != "none" and meta["teacher"] not in BUILTIN_AGENTS:
        raise EntryError(f"{where}: teacher {meta['teacher']!r} must be 'none' or a built-in agent {BUILTIN_AGENTS}")
    if meta["obs_mode"] not in OBS_MODES:
        raise EntryError(f"{where}: obs_mode {meta['obs_mode']!r} not in {OBS_MODES}")
    if not all(isinstance(s, int) and not isinstance(s, bool) and 0 <= s < 1_000_000 for s in meta["training_seeds"]):
        raise EntryError(f"{where}: training_seeds must be integers below 1,000,000 (evaluation seeds lie above)")
    policies = meta["policies"]
    if not policies:
        raise EntryError(f"{where}: policies must name at least one track's policy")
    unknown = sorted(set(policies) - set(POLICY_KEYS))
    if unknown:
        raise EntryError(f"{where}: policies has unknown tracks {unknown} (allowed: {list(POLICY_KEYS)})")
    if ALL_TRACKS in policies and len(policies) > 1:
        raise EntryError(f"{where}: a policy for all tracks excludes per-track policies")
    lines = [(f"{where}: policies.{track}", line) for track, line in policies.items()]
    if UNSEEN_KEY in meta:
        lines.append((f"{where}: {UNSEEN_KEY}", meta[UNSEEN_KEY]))
    for at, line in lines:
        if not isinstance(line, dict):
            raise EntryError(f"{at}: expected a mapping {{policy: ..., records: [...]}}, got {type(line).__name__}")
        _check_fields(line, POLICY_FIELDS, at)
        if not line["policy"].startswith("builtin:"):
            _check_policy_form(line["policy"], at)
        if not line["records"] or not all(isinstance(r, str) for r in line["records"]):
            raise EntryError(f"{at}: records must list at least one result folder (paths relative to the root)")
        if "onnx" in line and not line["onnx"].endswith(".onnx"):
            raise EntryError(f"{at}: onnx {line['onnx']!r} is not an .onnx file")
        if (
            line.get("steps", 0) < 0
            or not math.isfinite(line.get("wall_clock_s", 0))
            or line.get("wall_clock_s", 0) < 0
        ):
            raise EntryError(f"{at}: steps and wall_clock_s must be >= 0")
    return meta


def _check_fields(mapping: dict[str, Any], fields: dict[str, tuple[tuple[type, ...], bool]], where: str) -> None:
    missing = [k for k, (_, required) in fields.items() if required and k not in mapping]
    if missing:
        raise EntryError(f"{where}: missing fields {missing}")
    unknown = sorted(set(mapping) - set(fields))
    if unknown:
        raise EntryError(f"{where}: unknown fields {unknown} (allowed: {list(fields)})")
    for key, (types, _) in fields.items():
        if key in mapping and (not isinstance(mapping[key], types) or isinstance(mapping[key], bool)):
            raise EntryError(f"{where}: {key} is {mapping[key]!r}, expected {'/'.join(t.__name__ for t in types)}")


def _summary_budget(policy: str, root: Path) -> tuple[int | None, float | None]:
    """Steps and wall clock from the ``summary.json`` a training run wrote beside the checkpoint (None if absent)."""
    if policy.startswith("builtin:"):
        return 0, 0.0  # nothing was trained
    summary = (root / policy.partition(":")[0]).parent / "summary.json"
    try:
        data = json.loads(summary.read_text())
    except (OSError, ValueError):
        return None, None
    steps = data.get("env_steps", data.get("timesteps"))
    wall = data.get("wall_s_total", data.get("wall_s"))  # a resumed campaign run: all its sessions (campaign_finish)
    return (int(steps) if isinstance(steps, int) else None, float(wall) if isinstance(wall, (int, float)) else None)


def load_policy(name: str, track: str, line: dict[str, Any], root: Path) -> Policy:
    """One policy line, its files hashed and its records loaded (validated, of this policy and env version)."""
    digest = policy_sha256(line["policy"], root, f"{name} {track}")
    onnx, onnx_digest = line.get("onnx"), None
    if onnx is not None:
        path = _inside(Path(onnx), root, "onnx", name)
        if not path.is_file():
            raise EntryError(f"{name}: {track} onnx file {onnx!r} does not exist in the repository")
        onnx_digest = sha256_file(path)
    steps, wall = line.get("steps"), line.get("wall_clock_s")
    source = "entry.yaml"
    if steps is None or wall is None:
        found_steps, found_wall = _summary_budget(line["policy"], root)
        if steps is None and wall is None and found_steps is not None:
            source = "summary.json" if not line["policy"].startswith("builtin:") else "none (not trained)"
        steps = steps if steps is not None else found_steps
        wall = wall if wall is not None else found_wall
        if steps is None or wall is None:
            source = "unknown"
    policy = Policy(track, line["policy"], digest, list(line["records"]), onnx, onnx_digest, steps, wall, source)
    policy.records = load_records(name, policy, root)
    return policy


def load_records(name: str, policy: Policy, root: Path) -> list[dict[str, Any]]:
    """Every record of the policy's result folders, validated, of its policy and the current env version."""
    records: list[dict[str, Any]] = []
    seen: set[str] = set()
    for folder in policy.records_dirs:
        directory = _inside(Path(folder), root, "records folder", name)
        found = read_folder(directory) if has_records(directory) else None
        if found is None or not (found.records or found.problems):
            raise EntryError(f"{name}: no records in {folder!r} (expected {folder}/{RECORDS_FILE})")
        if found.problems:
            raise EntryError(f"{name}: invalid record {found.problems[0].error()}")
        for record in found.sorted_records():
            path = f"{folder}/{RECORDS_FILE} ({record['env_id']} seed {record['seed']})"
            if record["policy_sha256"] != policy.sha256:
                raise EntryError(
                    f"{name}: {path} is a record of another policy (sha256 {record['policy_sha256'][:12]}…), "
                    f"not of its {policy.track} policy {policy.policy}"
                )
            if record["env_version"] != ENV_VERSION:
                raise EntryError(
                    f"{name}: {path} is of env version {record['env_version']}, this racebench is {ENV_VERSION}: "
                    "re-evaluate the entry"
                )
            slot = name_of(record)
            if slot in seen:  # the same slot through two folders would count one episode twice
                raise EntryError(f"{name}: episode {record['env_id']} seed {record['seed']} is in two of its records "
                                 "folders")  # fmt: skip
            seen.add(slot)
            records.append(record)
    check_seed_prefixes(name, records)
    return records


def _check_policy_form(policy: str, name: str) -> None:
    """A leaderboard policy is a file of the repository: ``.zip``, ``.onnx`` or ``file.py:Class``. A dotted
    ``module:Class`` is refused: finding a module by name can reach code outside the entry's files."""
    file_part, colon, cls_name = policy.partition(":")
    if colon and not (file_part.endswith(".py") and cls_name.isidentifier()):
        raise EntryError(f"{name}: policy {policy!r}: a Python policy in an entry must be file.py:Class (a file of "
                         "the repository), not a dotted module:Class")  # fmt: skip
    if not colon and not policy.endswith((".zip", ".onnx")):
        raise EntryError(f"{name}: policy {policy!r} must be a .zip, .onnx or file.py:Class file of the repository")


def policy_sha256(policy: str, root: Path, name: str = "entry") -> str:
    """The sha256 the records of ``policy`` carry: of the file's bytes, or of a built-in's name and version."""
    if policy.startswith("builtin:"):
        builtin = policy.split(":", 1)[1]
        if builtin not in BUILTIN_AGENTS:
            raise EntryError(f"{name}: unknown built-in {builtin!r} (built-ins: {BUILTIN_AGENTS})")
        return builtin_identity(builtin).sha256
    _check_policy_form(policy, name)
    file_part = policy.partition(":")[0] if ":" in policy else policy
    path = _inside(Path(file_part), root, "policy", name)
    if not path.is_file():
        raise EntryError(f"{name}: policy file {file_part!r} does not exist in the repository")
    try:
        return policy_identity(_spec_at(policy, root)).sha256
    except VecNormalizeChoiceError as exc:
        # An entry names one file, which must say by itself what is flown: no per-entry statistics choice.
        raise EntryError(
            f"{name}: {exc}; a leaderboard policy cannot carry that choice: export it with the choice made "
            "(racebench export-onnx CKPT --vecnormalize PATH | --no-vecnormalize) and submit the .onnx"
        ) from exc
    except AgentLoadError as exc:
        raise EntryError(f"{name}: {exc}") from exc


def check_seed_prefixes(name: str, records: Sequence[dict[str, Any]], salt: str | None = None) -> None:
    """Each public cell must hold exactly the first ``n`` seeds of the protocol (private ones too, given the salt).

    Otherwise a submitter could fly 200 episodes and commit the best 50 (cherry-picking), or drop the crashes.
    """
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


def check_clean(name: str, records: Sequence[dict[str, Any]]) -> None:
    """Refuse records made from uncommitted code (``git_dirty``): no commit holds the code that flew them."""
    dirty = [r for r in records if r["git_dirty"]]
    if dirty:
        cells = sorted({f"{r['env_id']} ({r['git_commit']})" for r in dirty})
        raise EntryError(
            f"{name}: {len(dirty)} of {len(records)} records were made from uncommitted code (git_dirty: true; "
            f"{', '.join(cells)}; e.g. {dirty[0]['env_id']} seed {dirty[0]['seed']}): re-evaluate them from a clean "
            "checkout"
        )


def load_entry(folder: str | Path, root: str | Path | None = None) -> Entry:
    """Load and validate ``folder/entry.yaml``, its policies and their records (root: see :func:`repo_root`)."""
    folder = Path(folder)
    root = Path(root) if root is not None else repo_root(folder.parent)
    path = folder / ENTRY_FILE
    try:
        meta = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as exc:
        why = yaml_problem(exc) if isinstance(exc, yaml.YAMLError) else exc
        raise EntryError(f"{path}: unreadable ({why})") from exc
    meta = validate_meta(meta, root, str(path))
    if meta["name"] != folder.name:
        raise EntryError(f"{path}: name {meta['name']!r} differs from its folder {folder.name!r}")
    policies = {track: load_policy(meta["name"], track, line, root) for track, line in meta["policies"].items()}
    unseen = load_policy(meta["name"], UNSEEN_KEY, meta[UNSEEN_KEY], root) if UNSEEN_KEY in meta else None
    return Entry(meta, folder, root, policies, unseen)


def load_config(leaderboard: str | Path) -> dict[str, Any]:
    """``leaderboard.yaml``: ``private_salt_sha256`` (accepted salt fingerprints) and ``maintainers_public_key``."""
    path = Path(leaderboard) / CONFIG_FILE
    if not path.is_file():
        return {"private_salt_sha256": [], "maintainers_public_key": None}
    try:
        config = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as exc:
        raise EntryError(f"{path}: unreadable ({yaml_problem(exc)})") from exc
    salts = config.get("private_salt_sha256") or []
    if not isinstance(salts, list) or not all(isinstance(s, str) and _HEX64.match(s) for s in salts):
        raise EntryError(f"{path}: private_salt_sha256 must be a list of sha256 hex digests")
    key = config.get("maintainers_public_key")
    if key is not None and not isinstance(key, str):
        raise EntryError(f"{path}: maintainers_public_key must be a PEM text block")
    return {**config, "private_salt_sha256": salts, "maintainers_public_key": key}


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


def dump_entry(meta: dict[str, Any]) -> str:
    """``entry.yaml`` text: block style for the metadata, one flow-style line per policy (adding a track is a line)."""
    head = {k: v for k, v in meta.items() if k not in ("policies", UNSEEN_KEY)}
    text = yaml.safe_dump(head, sort_keys=False, allow_unicode=True, width=110)
    lines = ["policies:"]
    for track, line in meta["policies"].items():
        lines.append(
            f"  {track}: " + yaml.safe_dump(line, default_flow_style=True, sort_keys=False, width=10_000).strip()
        )
    if UNSEEN_KEY in meta:
        flow = yaml.safe_dump(meta[UNSEEN_KEY], default_flow_style=True, sort_keys=False, width=10_000).strip()
        lines.append(f"{UNSEEN_KEY}: {flow}")
    return text + "\n".join(lines) + "\n"
