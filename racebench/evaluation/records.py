"""Evaluation records: one JSON record per episode, keyed to the exact policy and env version, validated on read.

An evaluation folder keeps its records in ``records.jsonl``, one sealed record per line (:func:`compact_folder`);
each process of a running evaluation appends to a shard of its own, merged on read (:func:`read_folder`), so
concurrent workers never interleave partial lines and a kill tears at most a shard's last line. The older layout,
one ``records/<name>.json`` file per record, is still read.

A record is the unit every table, figure and leaderboard number is computed from. Format
:data:`RECORD_FORMAT` holds

* **what flew**: ``agent`` (a label only), ``policy_kind`` (``builtin`` / ``sb3`` / ``onnx`` / ``python``),
  ``policy_sha256`` (of the policy file; of ``"racebench-builtin:<name>:v<version>"`` for a built-in agent),
  ``policy_source`` (the spec it was loaded from), ``privileged`` (decided by the evaluator);
* **on what**: ``env_id``, ``track``, ``variant``, ``env_version`` (:data:`racebench.ENV_VERSION`, bumped
  whenever episode outcomes can change), ``renderer`` (of the depth image), ``seed``, ``seed_protocol``,
  ``seed_set`` (``public``, or ``private``: then also ``seed_salt_sha256``, the fingerprint of the secret salt
  the seeds were derived from, :mod:`racebench.evaluation.seeds`);
* **the outcome**: ``success``, ``lap_time``, ``crashed``, ``crash_reason``, ``gates_passed``, ``return``,
  ``steps``, ``error``;
* **where**: ``racebench_version``, ``git_commit``, ``git_dirty``, ``host_cpu``, ``host_platform`` and the
  versions of Python, numpy, torch and pybullet;
* ``digest``: sha256 of the canonical JSON of every other field.

The slot name is derived from (policy, env id, env version, seed protocol, seed set, seed, renderer): one record
per slot is counted, and an old-layout record copied or renamed into another slot's file is detected.
:func:`validate_record` checks the schema, the digest and the consistency of the outcome with the env (a success
passed every gate, its lap time is a physics tick of its last control step and not below the track's lap-time lower
bound, :mod:`racebench.envs.lap_bound`; a failure passed fewer gates, and one that neither crashed nor errored
ran to the time limit; ...). The digest catches corruption and casual edits; a determined forger can recompute
it, which the consistency checks and the replay of committed claims (``racebench leaderboard verify``,
``tests/test_checkpoints.py``) are for.
"""

from __future__ import annotations

import functools
import hashlib
import inspect
import io
import json
import logging
import math
import os
import platform
import re
import subprocess
import zipfile
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np

from racebench.agents.base import BUILTIN_PRIVILEGED
from racebench.envs.env import RaceEnv
from racebench.envs.lap_bound import env_lap_time_bound
from racebench.envs.random_tracks import episode_facts, most_gates
from racebench.envs.registration import ENV_KWARGS
from racebench.evaluation.protocol import EVAL_SEED_BASE, SEED_PROTOCOL, split_env_id
from racebench.evaluation.seeds import seed_in_set
from racebench.utils.files import atomic_write as atomic_write  # re-exported: records.atomic_write
from racebench.utils.files import sha256_file as sha256_file

logger = logging.getLogger("racebench")

RECORD_FORMAT = 2
SEED_SETS: tuple[str, ...] = ("public", "private")  # racebench.evaluation.seeds.SEED_SETS
RENDERERS: tuple[str, ...] = ("pybullet", "raycast")  # racebench.envs.env.RENDERERS, without importing the env
MAX_PUBLIC_EPISODES = 100_000  # public seeds are EVAL_SEED_BASE + i, i < this
POLICY_KINDS: tuple[str, ...] = ("builtin", "sb3", "onnx", "python")
#: What an env crash names (racebench.sim.collision): gate i, obstacle j, the ground, or leaving the arena.
ENV_CRASH_REASON = re.compile(r"^(gate:\d+|obstacle:\d+|ground|out_of_bounds)$")
ERROR_REASONS: tuple[str, ...] = ("agent_error", "env_error")

# Field name -> accepted Python types (after json.loads). ``None`` allowed where listed.
_STR, _INT, _BOOL, _NUM = (str,), (int,), (bool,), (int, float)
SCHEMA: dict[str, tuple[tuple[type, ...], bool]] = {
    "record_format": (_INT, False),
    "agent": (_STR, False),
    "policy_kind": (_STR, False),
    "policy_sha256": (_STR, False),
    "policy_source": (_STR, False),
    "privileged": (_BOOL, False),
    "env_id": (_STR, False),
    "track": (_STR, False),
    "variant": (_STR, False),
    "env_version": (_INT, False),
    "renderer": (_STR, False),
    "seed": (_INT, False),
    "seed_protocol": (_INT, False),
    "seed_set": (_STR, False),
    "success": (_BOOL, False),
    "lap_time": (_NUM, True),
    "crashed": (_BOOL, False),
    "crash_reason": (_STR, True),
    "gates_passed": (_INT, False),
    "return": (_NUM, False),
    "steps": (_INT, False),
    "error": (_STR, True),
    "racebench_version": (_STR, False),
    "git_commit": (_STR, False),
    "git_dirty": (_BOOL, False),
    "host_cpu": (_STR, False),
    "host_platform": (_STR, False),
    "python_version": (_STR, False),
    "numpy_version": (_STR, False),
    "torch_version": (_STR, False),
    "pybullet_version": (_STR, False),
    "digest": (_STR, False),
}
#: Column order of ``episodes.csv``.
RECORD_FIELDS: tuple[str, ...] = tuple(SCHEMA)
#: Fields present only in some records: ``seed_salt_sha256`` (racebench.evaluation.seeds.salt_sha256) in
#: exactly the records of the private seed set. Optional, so every public record of format 2 stays valid.
OPTIONAL_FIELDS: dict[str, tuple[tuple[type, ...], bool]] = {"seed_salt_sha256": (_STR, False)}


class InvalidRecordError(ValueError):
    """A record failed validation; the message says which check."""


def record_digest(record: dict[str, Any]) -> str:
    """sha256 of the canonical JSON of every field but ``digest``."""
    body = {k: v for k, v in record.items() if k != "digest"}
    return hashlib.sha256(json.dumps(body, sort_keys=True, allow_nan=False).encode()).hexdigest()


def record_name(
    policy_sha256: str, env_id: str, env_version: int, seed_protocol: int, seed_set: str, seed: int, renderer: str
) -> str:
    """File name of the record of one episode slot."""
    key = f"{policy_sha256}\0{env_id}\0{env_version}\0{seed_protocol}\0{seed_set}\0{seed}\0{renderer}"
    return hashlib.sha256(key.encode()).hexdigest()[:24] + ".json"


def name_of(record: dict[str, Any]) -> str:
    """The file name a valid record must have."""
    return record_name(
        record["policy_sha256"], record["env_id"], record["env_version"],
        record["seed_protocol"], record["seed_set"], record["seed"], record["renderer"],
    )  # fmt: skip


def _version(package: str) -> str:
    try:
        return metadata.version(package)
    except metadata.PackageNotFoundError:
        return "not installed"


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown"


@functools.lru_cache(maxsize=1)
def host_info() -> dict[str, str]:
    """The host fields of a record: CPU model, platform and the versions that can change a float."""
    return {
        "host_cpu": _cpu_model(),
        "host_platform": platform.platform(),
        "python_version": platform.python_version(),
        "numpy_version": _version("numpy"),
        "torch_version": _version("torch"),
        "pybullet_version": _version("pybullet"),
    }


@functools.lru_cache(maxsize=1)
def git_state() -> tuple[str, bool]:
    """(short commit, dirty) of the racebench checkout; ``("unknown", False)`` outside a git checkout.

    Dirty means uncommitted changes to ``racebench/``, ``tracks/`` or ``setup.cfg``.
    """
    root = Path(__file__).parents[2]
    try:
        commit = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True, text=True, timeout=5, check=True
        ).stdout.strip()
        # Only the code that decides outcomes: results written into the checkout must not make it "dirty".
        status = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no", "--", "racebench", "tracks", "setup.cfg"],
            cwd=root, capture_output=True, text=True, timeout=10, check=True,
        ).stdout  # fmt: skip
        return commit, bool(status.strip())
    except (OSError, subprocess.SubprocessError):
        return "unknown", False


def seal(record: dict[str, Any]) -> dict[str, Any]:
    """Return ``record`` in schema order with its ``digest`` set."""
    body = {k: record[k] for k in RECORD_FIELDS if k != "digest"}
    body.update({k: record[k] for k in OPTIONAL_FIELDS if k in record})
    return {**body, "digest": record_digest(body)}


@functools.cache
def env_facts(env_id: str) -> dict[str, Any]:
    """What a record of ``env_id`` can be checked against: gates per lap, control period, physics rate, step limit
    and the lower bound on its lap time (:mod:`racebench.envs.lap_bound`)."""
    if env_id not in ENV_KWARGS:
        raise InvalidRecordError(f"env_id {env_id!r} is not a racebench id")

    defaults = {k: p.default for k, p in inspect.signature(RaceEnv.__init__).parameters.items()}
    kwargs = {**defaults, **ENV_KWARGS[env_id]}
    control_freq = int(kwargs["control_freq"])
    physics_freq = int(kwargs["physics_freq"])
    return {
        "gates": most_gates(kwargs["track"]),  # a track source's episodes: see episode_facts
        "control_dt": 1.0 / control_freq,
        "physics_freq": physics_freq,
        "control_freq": control_freq,
        "max_steps": int(round(float(kwargs["max_episode_time"]) * control_freq)),
        "lap_time_bound": env_lap_time_bound(env_id),
    }


def validate_record(record: Any, file_name: str | None = None) -> dict[str, Any]:
    """Check one record (see the module docstring); return it, or raise :class:`InvalidRecordError`."""

    def bad(why: str) -> InvalidRecordError:
        return InvalidRecordError(why)

    if not isinstance(record, dict):
        raise bad(f"not a JSON object but {type(record).__name__}")
    missing = [k for k in RECORD_FIELDS if k not in record]
    if missing:
        raise bad(f"missing fields {missing}")
    extra = sorted(set(record) - set(RECORD_FIELDS) - set(OPTIONAL_FIELDS))
    if extra:
        raise bad(f"unknown fields {extra}")
    for key, (types, nullable) in {**SCHEMA, **OPTIONAL_FIELDS}.items():
        if key not in record:
            continue
        value = record[key]
        if value is None and nullable:
            continue
        if isinstance(value, bool) and bool not in types or not isinstance(value, types):
            raise bad(f"field {key!r} is {value!r}, expected {'/'.join(t.__name__ for t in types)}")
    if record["record_format"] != RECORD_FORMAT:
        raise bad(f"record_format {record['record_format']} (this racebench reads {RECORD_FORMAT})")
    if record["digest"] != record_digest(record):
        raise bad("digest does not match the contents (corrupt or edited)")
    if file_name is not None and file_name != name_of(record):
        raise bad(f"stored as {file_name}, but its policy/env/seed give {name_of(record)} (copied or renamed)")
    if record["policy_kind"] not in POLICY_KINDS:
        raise bad(f"policy_kind {record['policy_kind']!r} not in {POLICY_KINDS}")
    if len(record["policy_sha256"]) != 64 or any(c not in "0123456789abcdef" for c in record["policy_sha256"]):
        raise bad("policy_sha256 is not a sha256 hex digest")
    facts = env_facts(record["env_id"])
    if (record["track"], record["variant"]) != split_env_id(record["env_id"]):
        raise bad(f"track/variant {record['track']}/{record['variant']} do not match env_id {record['env_id']}")
    if record["seed_protocol"] != SEED_PROTOCOL:
        raise bad(f"seed_protocol {record['seed_protocol']} (this racebench uses {SEED_PROTOCOL})")
    if record["renderer"] not in RENDERERS:
        raise bad(f"renderer {record['renderer']!r} not in {RENDERERS}")
    if record["seed_set"] not in SEED_SETS:
        raise bad(f"seed_set {record['seed_set']!r} not in {SEED_SETS}")
    if record["seed_set"] == "public":
        if not EVAL_SEED_BASE <= record["seed"] < EVAL_SEED_BASE + MAX_PUBLIC_EPISODES:
            raise bad(f"seed {record['seed']} is not an evaluation seed of protocol {SEED_PROTOCOL}")
        if "seed_salt_sha256" in record:
            raise bad("a public-seed record with a seed_salt_sha256")
    else:
        # Membership of the salt's set needs the salt; the range alone already excludes public and training seeds.
        if not seed_in_set(record["seed"], "private"):
            raise bad(f"seed {record['seed']} is not a private seed of protocol {SEED_PROTOCOL}")
        salt_hash = record.get("seed_salt_sha256")
        if not (isinstance(salt_hash, str) and re.fullmatch(r"[0-9a-f]{64}", salt_hash)):
            raise bad("a private-seed record needs seed_salt_sha256, the sha256 of its salt")
    facts = {**facts, **episode_facts(record["env_id"], record["seed"])}  # a track source: the episode's own track
    steps, gates, lap = record["steps"], record["gates_passed"], record["lap_time"]
    reason, error = record["crash_reason"], record["error"]
    if not 0 <= steps <= facts["max_steps"]:
        raise bad(f"steps {steps} outside [0, {facts['max_steps']}]")
    if not 0 <= gates <= facts["gates"]:
        raise bad(f"gates_passed {gates} outside [0, {facts['gates']}]")
    if not math.isfinite(record["return"]):
        raise bad("return is not finite")
    if record["success"]:
        if gates != facts["gates"]:
            raise bad(f"success with {gates} of {facts['gates']} gates passed")
        if record["crashed"] or reason or error:
            raise bad("success with a crash or an error")
        # The env stamps the lap at the physics tick that crossed the last gate: ticks / physics_freq, exactly.
        freq, control = facts["physics_freq"], facts["control_freq"]
        ticks = round(lap * freq) if isinstance(lap, (int, float)) and math.isfinite(lap) else None
        # control step k holds ticks (k·freq // control, (k + 1)·freq // control]: RaceEnv._ticks_of_step
        window = ((steps - 1) * freq // control, steps * freq // control)
        if ticks is None or abs(lap * freq - ticks) > 1e-6 or not window[0] < ticks <= window[1]:
            raise bad(
                f"success lap_time {lap} is not a physics tick (1/{freq} s) of its last control step "
                f"({steps} steps of {facts['control_dt']} s)"
            )
        # The bound is a whole number of ticks too: compare ticks, so a lap of exactly the bound is accepted.
        if ticks < round(facts["lap_time_bound"] * freq):
            raise bad(
                f"success lap_time {lap} s is below {facts['lap_time_bound']:.3f} s, the lower bound on any lap of "
                f"{record['env_id']}: a flight from rest at full thrust along the straight gate-to-gate distance "
                f"(racebench.envs.lap_bound)"
            )
    else:
        if lap is not None:
            raise bad(f"failed episode with lap_time {lap}")
        if gates == facts["gates"]:
            raise bad(f"failed episode with all {gates} gates passed (the last gate ends the lap as a success)")
        if error:
            if reason not in ERROR_REASONS:
                raise bad(f"error recorded with crash_reason {reason!r}")
        elif record["crashed"]:
            if not (isinstance(reason, str) and ENV_CRASH_REASON.match(reason)):
                raise bad(f"crash with crash_reason {reason!r} (not gate:<i>, obstacle:<j>, ground, out_of_bounds)")
        elif reason is not None or steps != facts["max_steps"]:
            raise bad(f"neither success, crash nor error, yet stopped after {steps} of {facts['max_steps']} steps")
    if not record["crashed"] and isinstance(reason, str) and ENV_CRASH_REASON.match(reason):
        raise bad(f"crash_reason {reason!r} without crashed")
    if reason in ERROR_REASONS and not error:
        raise bad(f"crash_reason {reason!r} without an error message")
    if record["policy_kind"] == "builtin":
        name = record["policy_source"]
        if name not in BUILTIN_PRIVILEGED or record["privileged"] != BUILTIN_PRIVILEGED[name]:
            raise bad(f"built-in policy {name!r} with privileged={record['privileged']}")
    return record


def read_record(path: Path) -> dict[str, Any]:
    """Load and validate the record at ``path``; :class:`InvalidRecordError` names the file and the reason."""
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InvalidRecordError(f"{path}: unreadable ({exc})") from exc
    try:
        return validate_record(data, path.name)
    except InvalidRecordError as exc:
        raise InvalidRecordError(f"{path}: {exc}") from exc


# ------------------------------------------------------------------ records files of an evaluation folder
#: The compacted records of an evaluation folder: one sealed record per line, sorted by record name.
RECORDS_FILE = "records.jsonl"
#: Records appended by one process of a running evaluation (``records-<pid>-<token>.jsonl``), merged on read.
SHARD_GLOB = "records-*.jsonl"
#: Invalid lines set aside by the evaluator, one JSON object per line: ``source``, ``reason`` and ``text``.
INVALID_FILE = "invalid.jsonl"
#: The layout before records.jsonl: one file per record, named :func:`record_name`; still read, migrated on resume.
LEGACY_DIR = "records"
# One token per process: a spawned worker, a Ray worker and the parent each append to a shard of their own, so no
# two processes ever write into one file (no interleaved partial lines).
_TOKEN = os.urandom(4).hex()


def record_line(record: dict[str, Any]) -> bytes:
    """One record as a line of ``records.jsonl``: compact JSON in field order (the digest ignores formatting)."""
    return json.dumps(record, separators=(",", ":"), allow_nan=False).encode() + b"\n"


def shard_path(folder: Path) -> Path:
    """This process's shard of ``folder``: ``records-<pid>-<token>.jsonl`` (the pid alone may be reused)."""
    return Path(folder) / f"records-{os.getpid()}-{_TOKEN}.jsonl"


def append_line(path: Path, line: bytes) -> None:
    """Append one whole line to ``path`` and sync it: a kill leaves at most this line torn (the shard's last)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    try:
        view = memoryview(line)
        while view:  # a regular file takes it in one write; loop for the rare short one
            view = view[os.write(fd, view) :]
        os.fsync(fd)
    finally:
        os.close(fd)


@dataclass(frozen=True)
class RecordProblem:
    """A line or legacy file of an evaluation folder that holds no valid record."""

    source: str  # "<folder>/records.jsonl:<line>" or the legacy file's path
    reason: str
    text: str  # what was there (a legacy file's or a line's text, undecodable bytes replaced)
    torn: bool = False  # the unterminated last line of a file: a write cut off by a kill

    def error(self) -> InvalidRecordError:
        """The one-line error naming the file, the line and the reason."""
        return InvalidRecordError(f"{self.source}: {self.reason}")


@dataclass
class FolderRecords:
    """What an evaluation folder holds: its valid records by name (first occurrence wins), the problems, the files."""

    records: dict[str, dict[str, Any]] = field(default_factory=dict)
    lines: dict[str, bytes] = field(default_factory=dict)  # name -> its line as stored (byte-stable copies)
    problems: list[RecordProblem] = field(default_factory=list)
    files: list[tuple[Path, int]] = field(default_factory=list)  # (path, size read): shards/legacy files merged

    def sorted_records(self) -> list[dict[str, Any]]:
        """The valid records in record-name order (the order of a compacted ``records.jsonl``)."""
        return [self.records[name] for name in sorted(self.records)]

    def add(self, record: dict[str, Any], line: bytes) -> None:
        """Keep ``record`` unless its episode slot already holds one (a copy of a shard merged twice)."""
        name = name_of(record)
        if name not in self.records:
            self.records[name] = record
            self.lines[name] = line


def has_records(folder: str | Path) -> bool:
    """Whether ``folder`` holds records in either layout (``records.jsonl``, shards, or ``records/*.json``)."""
    folder = Path(folder)
    return (folder / RECORDS_FILE).is_file() or any(folder.glob(SHARD_GLOB)) or (folder / LEGACY_DIR).is_dir()


def _read_jsonl(path: Path, found: FolderRecords) -> None:
    try:
        data = path.read_bytes()
    except OSError as exc:
        found.problems.append(RecordProblem(str(path), f"unreadable ({exc})", ""))
        return
    found.files.append((path, len(data)))
    lines = data.split(b"\n")
    last = len(lines) - 1  # split leaves b"" after a final newline; a non-empty one is unterminated
    for number, raw in enumerate(lines, start=1):
        if not raw.strip():
            continue
        torn = number - 1 == last
        source = f"{path}:{number}"
        try:
            record = validate_record(json.loads(raw))
        except (UnicodeDecodeError, json.JSONDecodeError) as exc:
            why = "torn last line (a write cut off)" if torn else f"not a JSON record ({exc})"
            found.problems.append(RecordProblem(source, why, raw.decode(errors="replace"), torn))
            continue
        except InvalidRecordError as exc:
            found.problems.append(RecordProblem(source, str(exc), raw.decode(errors="replace")))
            continue
        found.add(record, raw + b"\n")


def read_folder(folder: str | Path) -> FolderRecords:
    """Every record of an evaluation folder, validated: ``records.jsonl``, then this run's shards, then legacy
    ``records/*.json`` files. Read-only; each line that fails is a :class:`RecordProblem` naming file, line and
    reason. A record whose episode slot is already held is skipped (shards merged twice after a kill)."""
    folder = Path(folder)
    found = FolderRecords()
    if (folder / RECORDS_FILE).is_file():
        _read_jsonl(folder / RECORDS_FILE, found)
    for shard in sorted(folder.glob(SHARD_GLOB)):
        _read_jsonl(shard, found)
    for path in sorted((folder / LEGACY_DIR).glob("*.json")):
        try:
            record = read_record(path)
        except InvalidRecordError as exc:
            data = path.read_bytes() if path.is_file() else b""
            found.problems.append(
                RecordProblem(str(path), str(exc).removeprefix(f"{path}: "), data.decode(errors="replace"))
            )
            found.files.append((path, len(data)))
            continue
        found.files.append((path, path.stat().st_size))
        found.add(record, record_line(record))
    return found


def compact_folder(folder: str | Path, set_aside: bool = True) -> FolderRecords:
    """Merge an evaluation folder's shards and legacy files into one sorted ``records.jsonl``; return what it holds.

    Invalid lines and files are appended to ``invalid.jsonl`` with their reason (``set_aside``) and left out, a
    torn last line is dropped with a warning: either way the episode has no record and is re-run. The new file is
    written atomically before the merged files are removed, so a kill leaves duplicates (skipped on read), never a
    loss; a shard that grew while being merged (another process still appending) is kept.
    """
    folder = Path(folder)
    found = read_folder(folder)
    if not found.problems and [path for path, _ in found.files] == [folder / RECORDS_FILE]:
        return found  # already one clean file: left as it is (a committed folder is not rewritten)
    for problem in found.problems:
        if problem.torn:
            logger.warning("racebench: torn record line dropped, its episode will be re-run: %s", problem.source)
        else:
            logger.warning("racebench: invalid record set aside, its episode will be re-run: %s", problem.error())
    if set_aside and any(not p.torn for p in found.problems):
        lines = b"".join(
            record_line({"source": p.source, "reason": p.reason, "text": p.text}) for p in found.problems if not p.torn
        )
        append_line(folder / INVALID_FILE, lines)
    names = sorted(found.records)
    if names or found.problems or (folder / RECORDS_FILE).exists():
        atomic_write(folder / RECORDS_FILE, b"".join(found.lines[name] for name in names))
    for path, size in found.files:
        if path == folder / RECORDS_FILE:
            continue
        try:
            if path.stat().st_size == size:
                path.unlink()
        except FileNotFoundError:
            pass
    legacy = folder / LEGACY_DIR
    if legacy.is_dir() and not any(legacy.iterdir()):
        legacy.rmdir()
    return found


# ------------------------------------------------------------------ trajectories of an evaluation folder
#: The compacted trajectories of an evaluation folder: per episode ``<env_id>/<seed>/positions`` (metres, one row
#: per control step), ``.../scene`` (JSON) and ``.../row`` (its sealed record, JSON).
TRAJECTORIES_FILE = "trajectories.npz"
#: Per-episode ``<record name>.npz`` files written while an evaluation runs (and the layout before), merged on read.
TRAJECTORIES_DIR = "trajectories"
_TRAJECTORY_PARTS = ("positions", "scene", "row")


def has_trajectories(folder: str | Path) -> bool:
    """Whether ``folder`` holds saved trajectories in either layout."""
    folder = Path(folder)
    return (folder / TRAJECTORIES_FILE).is_file() or any((folder / TRAJECTORIES_DIR).glob("*.npz"))


def read_trajectories(folder: str | Path) -> list[tuple[dict[str, Any], Any, dict[str, Any]]]:
    """Every saved trajectory of ``folder`` as ``(record, positions, scene)``, in record-name order (one per
    episode slot: a per-episode file not yet merged, else ``trajectories.npz``)."""
    folder = Path(folder)
    found: dict[str, tuple[dict[str, Any], Any, dict[str, Any]]] = {}
    # Per-episode files first: one re-flown after a kill replaces what the merged file holds of its slot.
    for path in sorted((folder / TRAJECTORIES_DIR).glob("*.npz")):
        with np.load(path) as data:
            row = json.loads(str(data["row"]))
            found.setdefault(name_of(row), (row, data["positions"], json.loads(str(data["scene"]))))
    if (folder / TRAJECTORIES_FILE).is_file():
        with np.load(folder / TRAJECTORIES_FILE) as data:
            for key in data.files:
                if key.endswith("/row"):
                    stem = key[: -len("/row")]
                    row = json.loads(str(data[key]))
                    flown = (row, data[f"{stem}/positions"], json.loads(str(data[f"{stem}/scene"])))
                    found.setdefault(name_of(row), flown)
    return [found[name] for name in sorted(found)]


def write_trajectories(path: Path, flights: list[tuple[dict[str, Any], Any, dict[str, Any]]]) -> None:
    """Write ``flights`` as one compressed ``.npz`` (fixed zip timestamps: the same flights give the same bytes)."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as archive:
        for row, positions, scene in flights:
            stem = f"{row['env_id']}/{row['seed']}"
            arrays = {
                "positions": np.asarray(positions),
                "scene": np.array(json.dumps(scene)),
                "row": np.array(json.dumps(row)),
            }
            for part in _TRAJECTORY_PARTS:
                info = zipfile.ZipInfo(f"{stem}/{part}.npy", date_time=(1980, 1, 1, 0, 0, 0))
                info.compress_type = zipfile.ZIP_DEFLATED
                array = io.BytesIO()
                np.lib.format.write_array(array, arrays[part], allow_pickle=False)
                archive.writestr(info, array.getvalue())
    atomic_write(path, buffer.getvalue())


def compact_trajectories(folder: str | Path, keep: set[str] | None = None) -> int:
    """Merge ``folder``'s per-episode trajectory files into ``trajectories.npz``; return the trajectories it holds.

    ``keep``: the record names whose trajectories stay (those of valid records; a trajectory whose record was
    never written, a kill in between, is dropped). The merged file is written atomically before the per-episode
    files are removed (a kill leaves duplicates)."""
    folder = Path(folder)
    loose = sorted((folder / TRAJECTORIES_DIR).glob("*.npz"))
    flights = read_trajectories(folder)
    kept = [f for f in flights if keep is None or name_of(f[0]) in keep]
    if not loose and len(kept) == len(flights):
        return len(flights)
    flights = kept
    write_trajectories(folder / TRAJECTORIES_FILE, flights)
    for path in loose:
        path.unlink(missing_ok=True)
    if not any((folder / TRAJECTORIES_DIR).iterdir()):
        (folder / TRAJECTORIES_DIR).rmdir()
    return len(flights)
