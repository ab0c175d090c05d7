"""Evaluation records: one JSON file per episode, keyed to the exact policy and env version, validated on read.

A record is the unit every table, figure and leaderboard number is computed from. Format
:data:`RECORD_FORMAT` holds

* **what flew**: ``agent`` (a label only), ``policy_kind`` (``builtin`` / ``sb3`` / ``onnx`` / ``python``),
  ``policy_sha256`` (of the policy file; of ``"racebench-builtin:<name>:v<version>"`` for a built-in agent),
  ``policy_source`` (the spec it was loaded from), ``privileged`` (decided by the evaluator);
* **on what**: ``env_id``, ``track``, ``variant``, ``env_version`` (:data:`racebench.ENV_VERSION`, bumped
  whenever episode outcomes can change), ``renderer`` (of the depth image), ``seed``, ``seed_protocol``,
  ``seed_set`` (``public``, or ``private``: then also ``seed_salt_sha256``, the fingerprint of the secret salt
  the seeds were derived from, :mod:`racebench.leaderboard.seeds`);
* **the outcome**: ``success``, ``lap_time``, ``crashed``, ``crash_reason``, ``gates_passed``, ``return``,
  ``steps``, ``error``;
* **where**: ``racebench_version``, ``git_commit``, ``git_dirty``, ``host_cpu``, ``host_platform`` and the
  versions of Python, numpy, torch and pybullet;
* ``digest``: sha256 of the canonical JSON of every other field.

The file name is derived from (policy, env id, env version, seed protocol, seed set, seed, renderer), so a record
copied or renamed into another slot is detected. :func:`validate_record` checks the schema, the digest
and the consistency of the outcome with the env (a success passed every gate and its lap time lies in
its last control step; a failure that neither crashed nor errored ran to the time limit; ...). The
digest catches corruption and casual edits; a determined forger can recompute it, which the
consistency checks and the statistical replay of committed claims (``tests/test_checkpoints.py``) are for.
"""

from __future__ import annotations

import functools
import hashlib
import json
import math
import os
import platform
import re
import subprocess
import tempfile
from importlib import metadata
from pathlib import Path
from typing import Any

RECORD_FORMAT = 2
SEED_SETS: tuple[str, ...] = ("public", "private")  # racebench.leaderboard.seeds.SEED_SETS
RENDERERS: tuple[str, ...] = ("pybullet", "raycast")  # racebench.env.RENDERERS, without importing the env
MAX_PUBLIC_EPISODES = 100_000  # public seeds are EVAL_SEED_BASE + i, i < this
POLICY_KINDS: tuple[str, ...] = ("builtin", "sb3", "onnx", "python")
#: What an env crash names (racebench.collision): gate i, obstacle j, the ground, or leaving the arena.
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
#: Fields present only in some records: ``seed_salt_sha256`` (racebench.leaderboard.seeds.salt_sha256) in
#: exactly the records of the private seed set. Optional, so every public record of format 2 stays valid.
OPTIONAL_FIELDS: dict[str, tuple[tuple[type, ...], bool]] = {"seed_salt_sha256": (_STR, False)}


class InvalidRecordError(ValueError):
    """A record failed validation; the message says which check."""


def sha256_file(path: str | Path) -> str:
    """Hex sha256 of a file's bytes."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


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
    root = Path(__file__).parents[1]
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
    """What a record of ``env_id`` can be checked against: gates per lap, control period, step limit."""
    from racebench.env import RaceEnv
    from racebench.registration import ENV_KWARGS
    from racebench.track import load_track

    if env_id not in ENV_KWARGS:
        raise InvalidRecordError(f"env_id {env_id!r} is not a racebench id")
    import inspect

    defaults = {k: p.default for k, p in inspect.signature(RaceEnv.__init__).parameters.items()}
    kwargs = {**defaults, **ENV_KWARGS[env_id]}
    control_freq = int(kwargs["control_freq"])
    return {
        "gates": load_track(kwargs["track"]).num_gates,
        "control_dt": 1.0 / control_freq,
        "max_steps": int(round(float(kwargs["max_episode_time"]) * control_freq)),
    }


def validate_record(record: Any, file_name: str | None = None) -> dict[str, Any]:
    """Check one record (see the module docstring); return it, or raise :class:`InvalidRecordError`."""
    from racebench.evaluation import EVAL_SEED_BASE, SEED_PROTOCOL, split_env_id

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
        from racebench.leaderboard.seeds import seed_in_set

        # Membership of the salt's set needs the salt; the range alone already excludes public and training seeds.
        if not seed_in_set(record["seed"], "private"):
            raise bad(f"seed {record['seed']} is not a private seed of protocol {SEED_PROTOCOL}")
        salt_hash = record.get("seed_salt_sha256")
        if not (isinstance(salt_hash, str) and re.fullmatch(r"[0-9a-f]{64}", salt_hash)):
            raise bad("a private-seed record needs seed_salt_sha256, the sha256 of its salt")
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
        dt = facts["control_dt"]
        if lap is None or not (steps - 1) * dt - 1e-9 < lap <= steps * dt + 1e-9:
            raise bad(f"success lap_time {lap} is not within its last control step ({steps} steps of {dt} s)")
    else:
        if lap is not None:
            raise bad(f"failed episode with lap_time {lap}")
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
        from racebench.agents import BUILTIN_PRIVILEGED

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


def atomic_write(path: Path, data: str | bytes) -> None:
    """Write ``data`` to ``path`` via a synced temporary file and a rename (mode 0644): a kill leaves old or new."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        os.fchmod(fd, 0o644)  # mkstemp makes 0600; results are meant to be shared
        with os.fdopen(fd, "wb") as f:
            f.write(data.encode() if isinstance(data, str) else data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
