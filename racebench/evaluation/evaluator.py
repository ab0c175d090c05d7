"""The common evaluator: fly an agent on a suite of env ids over fixed seeds, write tidy CSVs.

Protocol (versioned by :data:`SEED_PROTOCOL`):

* Evaluation episode ``i`` of every env id uses seed ``EVAL_SEED_BASE + i``. Training must only use seeds
  below :data:`EVAL_SEED_BASE` (``racebench`` training does), so no evaluation scene is ever trained on.
* Success = every gate of the track (one lap of a loop) passed in order, without any contact, within the
  time limit. Lap time (LT) = the time of a successful lap; failed episodes have no LT.
* An agent that raises, returns NaN or a wrongly shaped action ends that episode as a failure with the
  reason recorded (``crash_reason = "agent_error"``, ``error`` column); the sweep goes on.

Every finished episode is stored as its own record (:mod:`racebench.evaluation.records`), keyed to the exact policy
(sha256 of its file, or a built-in's name and code version), the env version and the seed protocol: a line
appended (and synced) to the writing process's shard, merged into the folder's ``records.jsonl`` at the start
and end of every run. An output directory holds the records of **one** policy
on one env version: evaluating another policy into it is refused (:class:`MixedResultsError`) unless
``force`` clears it. Running again resumes: valid finished records are kept and skipped, an invalid line is
named (file, line, reason), appended to ``invalid.jsonl`` and its episode re-run, a torn last line (a kill
mid-write) is dropped with a warning, a killed run loses at most the episodes in flight.
``episodes.csv`` and ``summary.csv`` (n, successes, success rate with a 95 % Wilson interval, lap-time
statistics) are rebuilt from the validated records after every run; tables and figures recompute their
summaries from the records too and never read a ``summary.csv`` back.
"""

from __future__ import annotations

import dataclasses
import logging
import multiprocessing
import re
import shutil
import time
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Any

import pandas as pd
from tqdm.auto import tqdm

from racebench.agents.loading import load_agent
from racebench.agents.trust import PolicyIdentity, policy_identity
from racebench.envs.env import RENDERERS
from racebench.envs.registration import ENV_VERSION
from racebench.evaluation.protocol import SEED_PROTOCOL, SEED_SET, resolve_envs
from racebench.evaluation.ray_backend import BACKENDS, RayOptions, require_ray
from racebench.evaluation.ray_backend import run_evaluation as run_on_ray
from racebench.evaluation.records import (
    INVALID_FILE,
    LEGACY_DIR,
    RECORDS_FILE,
    SHARD_GLOB,
    TRAJECTORIES_DIR,
    TRAJECTORIES_FILE,
    compact_folder,
    compact_trajectories,
    has_records,
    name_of,
    read_folder,
)
from racebench.evaluation.results import MixedResultsError, summarize, write_tables
from racebench.evaluation.seeds import check_episodes, salt_from_env, salt_sha256, seeds_for
from racebench.evaluation.worker import SingleTorchThread, close_pool, fly, torch_threads, worker_init
from racebench.evaluation.writer import RecordWriter

logger = logging.getLogger("racebench")

DEFAULT_BATCH = 64  # episodes flown in lockstep per process (learned agents); widths 16/32/64: docs/evaluation.md


def default_out_dir(agent_name: str, identity: PolicyIdentity, seed_set: str = SEED_SET) -> Path:
    """``runs/eval/<agent>-<first 10 hex of the policy sha256>``: fresh per policy, outside version control.

    A seed set other than the public one is appended (``-private``): one folder holds one seed set.
    """
    safe = re.sub(r"[^A-Za-z0-9._-]+", "_", agent_name)
    suffix = "" if seed_set == SEED_SET else f"-{seed_set}"
    return Path("runs") / "eval" / f"{safe}-{identity.sha256[:10]}{suffix}"


class Evaluator:
    """Evaluate one agent on env ids over the fixed evaluation seeds, resumably, keyed to the exact policy.

    Args:
        agent_spec: see :func:`racebench.agents.loading.load_agent`.
        envs: env ids and/or suite names.
        episodes: episodes per env id (the paper: 10).
        out_dir: where the records, ``episodes.csv`` and ``summary.csv`` go (default
            :func:`default_out_dir`). It may hold the records of this policy only.
        workers: processes to use (each builds its own agent and envs, and runs torch on one thread).
        agent_name: label in the CSVs (default: the agent's own name); it never selects records.
        save_trajectories: also store each episode's positions and scene (for the 3D track figure).
        renderer: depth renderer of the envs (``"pybullet"``, the envs' default, or ``"raycast"``); recorded in
            every record and part of its key.
        trust_code: allow agents whose loading runs code from a file (see :func:`~racebench.agents.loading.load_agent`).
        force: discard every record already in ``out_dir`` (whatever produced it) and evaluate afresh.
        batch: episodes a process flies in lockstep with one batched policy call per step (agents that
            support it: SB3 and ONNX); 1 flies one episode at a time.
        seed_set: ``"public"`` (``EVAL_SEED_BASE + i``) or ``"private"``: seeds derived from the secret salt
            ``salt`` or, when not given, the environment variable ``RACEBENCH_PRIVATE_SALT``
            (:mod:`racebench.evaluation.seeds`); the records store the salt's hash, never the salt.
        agent_kwargs: constructor keyword arguments of a ``module:Class`` agent (part of its policy identity).
        vecnormalize: an SB3 checkpoint's ``VecNormalize`` statistics: ``None`` those matched to it by name (an
            error if that is ambiguous), a path, or ``False`` for none
            (:func:`racebench.agents.trust.resolve_vecnormalize`;
            part of its policy identity).
        backend: ``"local"`` (worker processes on this machine) or ``"ray"`` (episodes as Ray tasks,
            :mod:`racebench.evaluation.ray_backend`; same records, so resume, summaries and tables are unchanged).
        ray_options: :class:`~racebench.evaluation.ray_backend.RayOptions` of the Ray backend (cluster address, CPUs
            per task, ...); without an address a private local instance of ``workers`` CPUs is started.
    """

    def __init__(
        self,
        agent_spec: str,
        envs: Sequence[str] = ("main",),
        episodes: int = 10,
        out_dir: str | Path | None = None,
        workers: int = 1,
        agent_name: str | None = None,
        save_trajectories: bool = False,
        renderer: str = "pybullet",
        trust_code: bool = False,
        force: bool = False,
        batch: int = DEFAULT_BATCH,
        seed_set: str = SEED_SET,
        salt: str | None = None,
        agent_kwargs: dict[str, Any] | None = None,
        vecnormalize: str | Path | bool | None = None,
        backend: str = "local",
        ray_options: RayOptions | None = None,
    ) -> None:
        check_episodes(episodes)  # 1 to the public set's size: a bound, not a MemoryError
        if workers < 1:
            raise ValueError(f"workers must be >= 1, got {workers}")
        if batch < 1:
            raise ValueError(f"batch must be >= 1, got {batch}")
        if renderer not in RENDERERS:
            raise ValueError(f"renderer must be one of {RENDERERS}, got {renderer!r}")
        if backend not in BACKENDS:
            raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
        self.backend = backend
        if backend == "ray":
            require_ray()  # before any work: a missing extra is a one-line error
            self.ray_options = ray_options or RayOptions()
            if self.ray_options.local_cpus is None:
                self.ray_options = dataclasses.replace(self.ray_options, local_cpus=workers)
            self.ray_options.validate()
        self.agent_spec = agent_spec
        self.env_ids = resolve_envs(envs)
        self.episodes = episodes
        self.workers = workers
        self.batch = batch
        self.save_trajectories = save_trajectories
        self.renderer = renderer
        self.trust_code = trust_code
        self.seed_set = seed_set
        if seed_set == "private" and salt is None:
            salt = salt_from_env()  # before loading anything: a missing secret is a one-line error
        self.seeds = seeds_for(seed_set, episodes, salt, SEED_PROTOCOL)
        # Lockstep width: --batch, or the evaluation's own size when smaller (a 10-episode run computes no
        # idle rows); fixed per evaluation, so a resumed one flies at the width it began with.
        self.width = max(1, min(batch, len(self.env_ids) * len(self.seeds)))
        self.salt_sha256 = salt_sha256(salt) if seed_set == "private" else None
        self.agent_kwargs = agent_kwargs
        # An absolute path: worker processes and Ray tasks load the same file.
        self.vecnormalize = str(Path(vecnormalize).resolve()) if isinstance(vecnormalize, (str, Path)) else vecnormalize
        probe = load_agent(agent_spec, trust_code, agent_kwargs, self.vecnormalize)  # fail fast, here
        self.identity = policy_identity(agent_spec, agent_kwargs, self.vecnormalize)
        if getattr(probe, "sha256", self.identity.sha256) != self.identity.sha256:
            raise ValueError(f"{agent_spec!r} changed while it was being loaded")
        self.agent_name = agent_name or probe.name
        self.probe = probe  # the Ray backend sizes its tasks by whether the agent batches
        self.privileged = self.identity.privileged
        default = default_out_dir(self.agent_name, self.identity, seed_set)
        self.out_dir = Path(out_dir) if out_dir is not None else default
        self.writer = RecordWriter(self.out_dir, self.identity, self.agent_name, renderer, seed_set, self.salt_sha256)
        if force:
            self._clear()
        self.done = self._scan()

    # ----------------------------------------------------------------- records
    def _clear(self) -> None:
        for sub in (LEGACY_DIR, TRAJECTORIES_DIR, "invalid"):
            shutil.rmtree(self.out_dir / sub, ignore_errors=True)
        for path in self.out_dir.glob(SHARD_GLOB):
            path.unlink()
        for name in (RECORDS_FILE, TRAJECTORIES_FILE, INVALID_FILE, "episodes.csv", "summary.csv"):
            (self.out_dir / name).unlink(missing_ok=True)

    def _scan(self) -> set[str]:
        """Validate what ``out_dir`` holds: another policy's records are refused; else the folder is compacted
        (shards and legacy files merged into ``records.jsonl``, invalid lines set aside into ``invalid.jsonl``,
        a torn last line dropped: their episodes are pending again)."""
        if not has_records(self.out_dir):
            return set()
        found = read_folder(self.out_dir)
        for record in found.records.values():
            theirs = (record["policy_sha256"], record["env_version"], record["renderer"])
            if theirs != (self.identity.sha256, ENV_VERSION, self.renderer):
                raise MixedResultsError(
                    f"{self.out_dir} holds results of another policy, env version or renderer "
                    f"({record['policy_source']!r}, sha256 {record['policy_sha256'][:12]}, env version "
                    f"{record['env_version']}, {record['renderer']} depth); this is {self.identity.source!r}, "
                    f"sha256 {self.identity.sha256[:12]}, env version {ENV_VERSION}, {self.renderer} depth: "
                    "choose another --out, or --force to discard them"
                )
            if (record["seed_set"], record.get("seed_salt_sha256")) != (self.seed_set, self.salt_sha256):
                # Seeds of two sets (or two salts) in one folder would make one summary of two protocols.
                raise MixedResultsError(
                    f"{self.out_dir} holds results on the {record['seed_set']} seed set"
                    f"{' of another salt' if record['seed_set'] == self.seed_set else ''}; this evaluation uses "
                    f"the {self.seed_set} one: choose another --out, or --force to discard them"
                )
            if record["agent"] != self.agent_name:
                raise MixedResultsError(
                    f"{self.out_dir} labels this policy {record['agent']!r}, not {self.agent_name!r}: "
                    f"use --name {record['agent']}, another --out, or --force to discard them"
                )
        return set(self._compact().records)

    def _compact(self) -> Any:
        """Merge the folder's records (and trajectories) into one file each; return the records found."""
        found = compact_folder(self.out_dir)
        compact_trajectories(self.out_dir, keep=set(found.records))
        return found

    def pending(self) -> list[tuple[str, int]]:
        """(env id, seed) pairs of this evaluation without a valid finished record."""
        return [
            (env_id, seed)
            for env_id in self.env_ids
            for seed in self.seeds
            if self.writer.name(env_id, seed) not in self.done
        ]

    # --------------------------------------------------------------------- run
    def run(self, progress: bool = True) -> pd.DataFrame:
        """Run every pending episode, rebuild the CSVs; return the summary of exactly the asked ids × seeds."""
        todo = self.pending()
        started = time.perf_counter()
        # Nothing left to fly (a complete run resumed): no bar; `racebench evaluate` has said all are done.
        bar = tqdm(total=len(todo), desc=f"{self.agent_name}", disable=not progress or not todo, unit="ep")
        # Tasks of a few lockstep widths: every worker stays busy, and each record is written as it ends.
        size = max(1, min(2 * self.width, -(-len(todo) // self.workers)))
        tasks = [todo[i : i + size] for i in range(0, len(todo), size)]
        if self.backend == "ray":
            self.done.update(name_of(r) for r in run_on_ray(self, todo, bar.update))
        elif self.workers == 1 or len(tasks) <= 1:
            with SingleTorchThread():
                worker_init(
                    self.agent_spec, self.renderer, self.trust_code, torch_threads(), self.agent_kwargs,
                    self.vecnormalize,
                )  # fmt: skip
                try:  # one lockstep over every episode: its slots idle only at the very end, not after each task
                    flown = fly(todo, self.writer, self.width, self.save_trajectories, lambda: bar.update(1))
                    self.done.update(name_of(r) for r in flown)
                finally:
                    close_pool()
        else:
            # "spawn": a forked child of a process that has run torch can deadlock in torch's thread pool
            # (seen: --workers 2 with a GRU checkpoint hung at start).
            with ProcessPoolExecutor(
                self.workers,
                mp_context=multiprocessing.get_context("spawn"),
                initializer=worker_init,
                initargs=(self.agent_spec, self.renderer, self.trust_code, 1, self.agent_kwargs, self.vecnormalize),
            ) as pool:
                futures = {
                    pool.submit(fly, task, self.writer, self.width, self.save_trajectories): len(task) for task in tasks
                }
                for future in as_completed(futures):
                    self.done.update(name_of(r) for r in future.result())
                    bar.update(futures[future])
        bar.close()
        self.elapsed = time.perf_counter() - started
        self.done = set(self._compact().records)  # one records.jsonl (and trajectories.npz) again
        episodes = write_tables(self.out_dir)
        asked = {(e, s) for e in self.env_ids for s in self.seeds}
        self.selected = episodes[[(e, s) in asked for e, s in zip(episodes["env_id"], episodes["seed"], strict=True)]]
        return summarize(self.selected)
