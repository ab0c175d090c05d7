"""``racebench leaderboard add``: a new entry from a submitter's policies, metadata and records.

The entry's records must be ones a pull request can carry: made from committed code (:func:`~racebench.leaderboard.
entries.check_clean`) and in folders git does not ignore (:func:`check_not_ignored`).
"""

from __future__ import annotations

import logging
import os
import subprocess
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from racebench.agents.base import BUILTIN_AGENTS
from racebench.evaluation.evaluator import Evaluator
from racebench.leaderboard.entries import (
    _NAME,
    ALL_TRACKS,
    ENTRY_FILE,
    META_FIELDS,
    POLICY_KEYS,
    UNSEEN_KEY,
    Entry,
    EntryError,
    _spec_at,
    _summary_budget,
    check_clean,
    dump_entry,
    load_policy,
    policy_sha256,
    repo_root,
    validate_meta,
)

logger = logging.getLogger("racebench")
#: What ``--meta`` may give of a policy line (``policies: {TRACK: {steps: N, wall_clock_s: S}}``); the rest is written.
BUDGET_FIELDS: tuple[str, ...] = ("steps", "wall_clock_s")


def add_entry(
    leaderboard: str | Path,
    policies: str | dict[str, str],
    meta: dict[str, Any],
    records: Sequence[str] = (),
    evaluate_episodes: int = 0,
    trust_code: bool = False,
    workers: int = 1,
    progress: bool = False,
) -> Entry:
    """Create ``<leaderboard>/<meta name>/entry.yaml`` for a method's policies (repository paths or built-ins).

    ``policies``: track (``S``, ``Circle``, ``J``) -> policy, or one policy for all tracks. ``meta`` holds the
    descriptive fields; each policy line is written from the policy, ``records`` (result folders relative to the
    root; one policy only) and an ONNX policy's own path as ``onnx``. With ``evaluate_episodes > 0`` each policy
    is first evaluated on the main suite's public seeds into ``<entry>/eval-public-<track>`` (resumable). A name
    already used is refused (case-insensitive: it names a folder), and so are records made from uncommitted code
    (:func:`check_clean`) and record folders git ignores (:func:`check_not_ignored`). ``meta`` may give each
    policy's training budget as ``policies: {TRACK: {steps: N, wall_clock_s: S}}``; a policy whose budget is
    neither there nor in a ``summary.json`` beside it is warned about. ``progress``: a progress bar while flying.
    ``entry.yaml`` is written last, so a failed run leaves no entry.
    """
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
    if isinstance(policies, str):
        policies = {ALL_TRACKS: policies}
    if records and len(policies) != 1:
        raise EntryError(f"{name}: --records belongs to one policy; with several, use --evaluate")
    folder = leaderboard / name
    lines: dict[str, dict[str, Any]] = {}
    for track, policy in policies.items():
        if track not in POLICY_KEYS:
            raise EntryError(f"{name}: unknown track {track!r} (allowed: {list(POLICY_KEYS)})")
        if not policy.startswith("builtin:") and policy in BUILTIN_AGENTS:
            policy = f"builtin:{policy}"
        if not policy.startswith("builtin:"):
            file_part, colon, cls_name = policy.partition(":") if ":" in policy else (policy, "", "")
            absolute = Path(file_part).resolve()
            if not absolute.is_relative_to(root):
                raise EntryError(
                    f"policy {policy!r} must be a file inside the repository ({root}); commit it there first"
                )
            policy = f"{absolute.relative_to(root).as_posix()}{colon}{cls_name}"
        policy_sha256(policy, root, name)  # a missing or unreadable policy fails before anything is flown
        folders = [Path(os.path.relpath(Path(r).resolve(), root)).as_posix() for r in records]
        if evaluate_episodes > 0:
            out = folder / f"eval-public-{track}"
            rel = out.resolve().relative_to(root).as_posix()
            folders = [*folders, rel] if rel not in folders else folders
        line: dict[str, Any] = {"policy": policy, "records": folders}
        if policy.endswith(".onnx"):
            line["onnx"] = policy
        lines[track] = line
    _merge_budgets(name, meta.get("policies"), lines)
    full = validate_meta({**meta, "policies": lines}, root, name)  # bad metadata fails before flying
    unseen_folders = full[UNSEEN_KEY]["records"] if UNSEEN_KEY in full else []  # --meta's unseen: line, if any
    check_not_ignored(name, root, [f for line in lines.values() for f in line["records"]] + unseen_folders)
    for track, line in lines.items():
        _warn_unknown_budget(name, track, line, root)
    if evaluate_episodes > 0:
        for track, line in lines.items():
            Evaluator(
                _spec_at(line["policy"], root) if not line["policy"].startswith("builtin:")
                else line["policy"].split(":", 1)[1],
                ["main"], episodes=evaluate_episodes, out_dir=root / line["records"][-1], agent_name=f"{name}-{track}",
                trust_code=trust_code, workers=workers,
            ).run(progress=progress)  # fmt: skip
    unseen = load_policy(name, UNSEEN_KEY, full[UNSEEN_KEY], root) if UNSEEN_KEY in full else None
    entry = Entry(full, folder, root, {t: load_policy(name, t, line, root) for t, line in lines.items()}, unseen)
    check_clean(name, entry.records + (unseen.records if unseen else []))
    folder.mkdir(parents=True, exist_ok=True)
    ordered = {k: full[k] for k in META_FIELDS if k in full}
    (folder / ENTRY_FILE).write_text(dump_entry(ordered))
    return entry


def _merge_budgets(name: str, given: Any, lines: dict[str, dict[str, Any]]) -> None:
    """Copy the budgets ``--meta`` gives (``policies: {TRACK: {steps, wall_clock_s}}``) into the written lines."""
    if given is None:
        return
    if not isinstance(given, dict):
        raise EntryError(f"{name}: --meta policies must map a track to {{steps: N, wall_clock_s: S}} (its budget)")
    for track, budget in given.items():
        if track not in lines:
            raise EntryError(f"{name}: --meta policies.{track}: no --policy for that track (given: {list(lines)})")
        if not isinstance(budget, dict) or not set(budget) <= set(BUDGET_FIELDS):
            raise EntryError(f"{name}: --meta policies.{track} may hold only {list(BUDGET_FIELDS)} (the command "
                             "writes policy, records and onnx)")  # fmt: skip
        lines[track].update(budget)


def _warn_unknown_budget(name: str, track: str, line: dict[str, Any], root: Path) -> None:
    """Warn when a policy line will have no training budget: none given, no ``summary.json`` beside the policy."""
    steps, wall = _summary_budget(line["policy"], root)
    if line.get("steps", steps) is None or line.get("wall_clock_s", wall) is None:
        logger.warning(
            f"warning: {name}: the {track} policy's training budget is unknown ({line['policy']} has no summary.json "
            f"beside it), so the site shows it as unknown; set it in --meta: "
            f"policies: {{{track}: {{steps: N, wall_clock_s: SECONDS}}}}"
        )


def check_not_ignored(name: str, root: Path, folders: Sequence[str]) -> None:
    """Refuse record folders that git ignores (``runs/``): a record a pull request cannot carry.

    Outside a git repository (or without git) there is nothing to check.
    """
    if not folders:
        return
    try:
        done = subprocess.run(
            ["git", "-C", str(root), "check-ignore", "--verbose", "--", *folders],
            capture_output=True, text=True, check=False,
        )  # fmt: skip
    except OSError:
        return
    if done.returncode != 0:  # 1: none ignored; 128: not a repository
        return
    source, _, path = done.stdout.splitlines()[0].partition("\t")
    raise EntryError(
        f"{name}: records folder {path!r} is ignored by git ({source}), so a pull request cannot carry its "
        "records; evaluate into (or copy them to) a tracked folder, e.g. with --evaluate (<leaderboard>/<name>/)"
    )
