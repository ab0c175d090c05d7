"""The common evaluator: fly an agent on a suite of env ids over fixed seeds, write tidy CSVs.

Protocol (versioned by :data:`SEED_PROTOCOL`):

* Evaluation episode ``i`` of every env id uses seed ``EVAL_SEED_BASE + i``. Training must only use seeds
  below :data:`EVAL_SEED_BASE` (``racebench`` training does), so no evaluation scene is ever trained on.
* Success = every gate of the track (one lap of a loop) passed in order, without any contact, within the
  time limit. Lap time (LT) = the time of a successful lap; failed episodes have no LT.
* An agent that raises, returns NaN or a wrongly shaped action ends that episode as a failure with the
  reason recorded (``crash_reason = "agent_error"``, ``error`` column); the sweep goes on.

Every finished episode is stored as its own record (:mod:`racebench.records`), keyed to the exact policy
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

import atexit
import dataclasses
import json
import logging
import multiprocessing
import os
import re
import shutil
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pandas as pd
from tqdm.auto import tqdm

import racebench
from racebench.agents import PolicyIdentity, load_agent, policy_identity
from racebench.ray_backend import BACKENDS, RayOptions, require_ray
from racebench.ray_backend import run_evaluation as run_on_ray
from racebench.records import (
    INVALID_FILE,
    LEGACY_DIR,
    RECORD_FIELDS,
    RECORD_FORMAT,
    RECORDS_FILE,
    SHARD_GLOB,
    TRAJECTORIES_DIR,
    TRAJECTORIES_FILE,
    append_line,
    atomic_write,
    compact_folder,
    compact_trajectories,
    git_state,
    has_records,
    host_info,
    name_of,
    read_folder,
    record_line,
    record_name,
    seal,
    shard_path,
)
from racebench.registration import DENSITIES, ENV_VERSION, GATE_SHIFTS, TRACK_IDS
from racebench.rollout import BatchAgent, env_error_result, run_episode, run_lockstep
from racebench.statistics import paired_outcomes, wilson_interval

logger = logging.getLogger("racebench")

SEED_PROTOCOL = 1
EVAL_SEED_BASE = 1_000_000
# Validation scene i (choosing a DAgger run's student, a campaign run's validation curve) has seed
# VALIDATION_SEED_BASE + i: above the training seeds of a fresh run and below the evaluation seeds, so nothing
# chosen or plotted on validation scenes has seen an evaluation scene.
VALIDATION_SEED_BASE = 800_000
TRACK_ORDER: tuple[str, ...] = ("S", "Circle", "J")  # the paper's column order
SUITES: dict[str, list[str]] = {
    "main": [f"RaceObs-{t}-v0" for t in TRACK_ORDER],
    "density": [f"RaceObs-{t}-Density{d}-v0" for d in DENSITIES for t in TRACK_ORDER],
    "gates": [f"RaceObs-{t}-GateShift{s}-v0" for s in GATE_SHIFTS for t in TRACK_ORDER],
}
SUITES["paper"] = SUITES["main"] + SUITES["density"] + SUITES["gates"]
SEED_SET = "public"
DEFAULT_BATCH = 64  # episodes flown in lockstep per process (learned agents); widths 16/32/64: docs/evaluation.md
EPISODE_COLUMNS: tuple[str, ...] = RECORD_FIELDS  # episodes.csv: every record field
_ID = re.compile(r"^RaceObs-(?P<track>[^-]+)(?:-(?P<variant>.+))?-v0$")


def eval_seeds(episodes: int) -> list[int]:
    """The evaluation seeds of protocol :data:`SEED_PROTOCOL`: ``EVAL_SEED_BASE + i``."""
    return [EVAL_SEED_BASE + i for i in range(episodes)]


def resolve_envs(names: Sequence[str]) -> list[str]:
    """Expand suite names (``main``, ``density``, ``gates``, ``paper``) and check every env id exists."""
    ids: list[str] = []
    for name in names:
        for env_id in SUITES.get(name, [name]):
            if env_id not in gym.registry:
                raise ValueError(f"unknown env id or suite {name!r} (suites: {sorted(SUITES)}; ids: racebench envs)")
            if env_id not in ids:
                ids.append(env_id)
    return ids


def split_env_id(env_id: str) -> tuple[str, str]:
    """``RaceObs-S-Density5-v0`` → (``"S"``, ``"Density5"``); the plain id's variant is ``"default"``."""
    match = _ID.match(env_id)
    if not match:
        return env_id, "custom"
    return match["track"], match["variant"] or "default"


@dataclass(frozen=True)
class RecordWriter:
    """Writes the record (and trajectory) of each finished episode of one evaluation; picklable, so worker
    processes write their own records as episodes end (a killed run loses only the episodes in flight).

    Each process appends whole lines to its own shard (:func:`racebench.records.shard_path`), so no two processes
    write into one file; the evaluator merges the shards into ``records.jsonl``
    (:func:`~racebench.records.compact_folder`).
    """

    out_dir: Path
    identity: PolicyIdentity
    agent_name: str
    renderer: str
    seed_set: str = SEED_SET
    salt_sha256: str | None = None  # of the private seed set's salt; None for public seeds

    def name(self, env_id: str, seed: int) -> str:
        """File name of the record of ``(env_id, seed)``."""
        return record_name(self.identity.sha256, env_id, ENV_VERSION, SEED_PROTOCOL, self.seed_set, seed, self.renderer)

    def write(self, env_id: str, seed: int, result: dict[str, Any], flown: dict | None) -> dict[str, Any]:
        """Seal one episode's record, append it to this process's shard (synced); return the record."""
        track, variant = split_env_id(env_id)
        commit, dirty = git_state()
        record = seal(
            {
                "record_format": RECORD_FORMAT,
                "agent": self.agent_name,
                "policy_kind": self.identity.kind,
                "policy_sha256": self.identity.sha256,
                "policy_source": self.identity.source,
                "privileged": self.identity.privileged,
                "env_id": env_id,
                "track": track,
                "variant": variant,
                "env_version": ENV_VERSION,
                "renderer": self.renderer,
                "seed": seed,
                "seed_protocol": SEED_PROTOCOL,
                "seed_set": self.seed_set,
                **result,
                "racebench_version": racebench.__version__,
                "git_commit": commit,
                "git_dirty": dirty,
                **host_info(),
                **({"seed_salt_sha256": self.salt_sha256} if self.salt_sha256 else {}),
            }
        )
        name = self.name(env_id, seed)
        if flown is not None:
            traj_dir = self.out_dir / TRAJECTORIES_DIR
            traj_dir.mkdir(parents=True, exist_ok=True)
            tmp = traj_dir / f".{name}.tmp.npz"
            scene = json.dumps(flown["scene"])
            np.savez_compressed(tmp, positions=flown["positions"], scene=scene, row=json.dumps(record))
            os.chmod(tmp, 0o644)
            os.replace(tmp, traj_dir / name.replace(".json", ".npz"))
        # The trajectory first: a record on disk promises its trajectory (a kill in between re-flies the episode).
        append_line(shard_path(self.out_dir), record_line(record))
        return record


# Worker-process state: one agent, built once per process, and its settings.
_WORKER: dict[str, Any] = {}


def _worker_init(
    agent_spec: str,
    renderer: str,
    trust_code: bool,
    threads: int,
    agent_kwargs: dict[str, Any] | None = None,
    vecnormalize: str | bool | None = None,
) -> None:
    _close_pool()
    if not _WORKER.get("atexit"):
        atexit.register(_close_pool)  # a worker process's envs, at its exit
        _WORKER["atexit"] = True
    agent = load_agent(agent_spec, trust_code=trust_code, agent_kwargs=agent_kwargs, vecnormalize=vecnormalize)
    _WORKER.update(agent=agent, renderer=renderer, pool={})
    torch = sys.modules.get("torch")  # imported by learned agents only; built-ins need not pay for it
    if torch is not None:
        torch.set_num_threads(threads)


def _close_pool() -> None:
    """Close the envs this process keeps between tasks (PyBullet clients left to interpreter exit print errors)."""
    for envs in _WORKER.get("pool", {}).values():
        for env in envs:
            env.close()
    _WORKER["pool"] = {}


def _fly(
    jobs: list[tuple[str, int]],
    writer: RecordWriter,
    width: int,
    save_trajectories: bool,
    on_written: Callable[[], None] | None = None,
) -> list[dict[str, Any]]:
    """Fly ``jobs`` with this process's agent, writing each record as its episode ends; return the records.

    A :class:`~racebench.rollout.BatchAgent` flies ``width`` episodes in lockstep; any other agent one
    episode at a time. ``on_written`` is called after each record (progress).
    """
    agent = _WORKER["agent"]
    written: list[dict[str, Any]] = []

    def make_env(env_id: str) -> gym.Env:
        return gym.make(env_id, obs_mode=agent.obs_mode, renderer=_WORKER["renderer"])

    def done(env_id: str, seed: int, result: dict[str, Any], flown: dict | None) -> None:
        written.append(writer.write(env_id, seed, result, flown))
        if on_written is not None:
            on_written()

    if width > 1 and isinstance(agent, BatchAgent):
        pool = _WORKER["pool"]  # envs kept between this process's tasks: building one costs ~20-50 ms
        run_lockstep(agent, jobs, make_env, done, width=width, save_trajectories=save_trajectories, pool=pool)
        return written
    envs: dict[str, gym.Env] = {}
    try:
        for env_id, seed in jobs:
            env = envs.get(env_id) or envs.setdefault(env_id, make_env(env_id))
            trajectory: list | None = [] if save_trajectories else None
            try:
                result = run_episode(agent, env, seed, trajectory)
            except Exception:  # noqa: BLE001 - an env-side failure is recorded too, the sweep goes on
                result = env_error_result()
            flown = None
            if trajectory:
                flown = {"positions": np.array(trajectory), "scene": env.unwrapped.scene.to_dict()}
            done(env_id, seed, result, flown)
    finally:
        for env in envs.values():
            env.close()
    return written


class MixedResultsError(ValueError):
    """An output directory holds records of another policy, label or env version than the one asked."""


def default_out_dir(agent_name: str, identity: PolicyIdentity, seed_set: str = SEED_SET) -> Path:
    """``runs/eval/<agent>-<first 10 hex of the policy sha256>``: fresh per policy, outside version control.

    A seed set other than the public one is appended (``-private``): one folder holds one seed set.
    """
    safe = re.sub(r"[^A-Za-z0-9._-]+", "_", agent_name)
    suffix = "" if seed_set == SEED_SET else f"-{seed_set}"
    return Path("runs") / "eval" / f"{safe}-{identity.sha256[:10]}{suffix}"


def torch_threads() -> int:
    """Torch threads for a process that steps envs and runs a policy in turn: one.

    Measured on 2 cores (``racebench bench``, "policy call" rows): the batch-1 call of the vision GRU costs
    ~1 ms on one thread and 7–70 ms with two (the default) while anything else runs, and a 32-observation
    batch is no faster on two threads; the simulator between calls cannot use a second thread anyway.
    """
    return 1


class SingleTorchThread:
    """Context: run a policy in this process with :func:`torch_threads` threads, restored on exit.

    Batch-1 policy calls with torch's default thread count oversubscribe small machines (seen: 15 instead
    of ~150 env steps/s on 2 cores).
    """

    def __enter__(self) -> None:
        self.torch = sys.modules.get("torch")
        if self.torch is not None:
            self.saved = self.torch.get_num_threads()
            self.torch.set_num_threads(torch_threads())

    def __exit__(self, *exc: Any) -> None:
        if self.torch is not None:
            self.torch.set_num_threads(self.saved)


class Evaluator:
    """Evaluate one agent on env ids over the fixed evaluation seeds, resumably, keyed to the exact policy.

    Args:
        agent_spec: see :func:`racebench.agents.load_agent`.
        envs: env ids and/or suite names.
        episodes: episodes per env id (the paper: 10).
        out_dir: where the records, ``episodes.csv`` and ``summary.csv`` go (default
            :func:`default_out_dir`). It may hold the records of this policy only.
        workers: processes to use (each builds its own agent and envs, and runs torch on one thread).
        agent_name: label in the CSVs (default: the agent's own name); it never selects records.
        save_trajectories: also store each episode's positions and scene (for the 3D track figure).
        renderer: depth renderer of the envs (``"pybullet"``, the envs' default, or ``"raycast"``); recorded in
            every record and part of its key.
        trust_code: allow agents whose loading runs code from a file (see :func:`~racebench.agents.load_agent`).
        force: discard every record already in ``out_dir`` (whatever produced it) and evaluate afresh.
        batch: episodes a process flies in lockstep with one batched policy call per step (agents that
            support it: SB3 and ONNX); 1 flies one episode at a time.
        seed_set: ``"public"`` (``EVAL_SEED_BASE + i``) or ``"private"``: seeds derived from the secret salt
            ``salt`` or, when not given, the environment variable ``RACEBENCH_PRIVATE_SALT``
            (:mod:`racebench.leaderboard.seeds`); the records store the salt's hash, never the salt.
        agent_kwargs: constructor keyword arguments of a ``module:Class`` agent (part of its policy identity).
        vecnormalize: an SB3 checkpoint's ``VecNormalize`` statistics: ``None`` those matched to it by name (an
            error if that is ambiguous), a path, or ``False`` for none (:func:`racebench.agents.resolve_vecnormalize`;
            part of its policy identity).
        backend: ``"local"`` (worker processes on this machine) or ``"ray"`` (episodes as Ray tasks,
            :mod:`racebench.ray_backend`; same records, so resume, summaries and tables are unchanged).
        ray_options: :class:`~racebench.ray_backend.RayOptions` of the Ray backend (cluster address, CPUs
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
        from racebench.env import RENDERERS
        from racebench.leaderboard.seeds import salt_from_env, salt_sha256, seeds_for

        if episodes < 1:
            raise ValueError(f"episodes must be >= 1, got {episodes}")
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
        bar = tqdm(total=len(todo), desc=f"{self.agent_name}", disable=not progress, unit="ep")
        # Tasks of a few lockstep widths: every worker stays busy, and each record is written as it ends.
        size = max(1, min(2 * self.width, -(-len(todo) // self.workers)))
        tasks = [todo[i : i + size] for i in range(0, len(todo), size)]
        if self.backend == "ray":
            self.done.update(name_of(r) for r in run_on_ray(self, todo, bar.update))
        elif self.workers == 1 or len(tasks) <= 1:
            with SingleTorchThread():
                _worker_init(
                    self.agent_spec, self.renderer, self.trust_code, torch_threads(), self.agent_kwargs,
                    self.vecnormalize,
                )  # fmt: skip
                try:  # one lockstep over every episode: its slots idle only at the very end, not after each task
                    flown = _fly(todo, self.writer, self.width, self.save_trajectories, lambda: bar.update(1))
                    self.done.update(name_of(r) for r in flown)
                finally:
                    _close_pool()
        else:
            # "spawn": a forked child of a process that has run torch can deadlock in torch's thread pool
            # (seen: --workers 2 with a GRU checkpoint hung at start).
            with ProcessPoolExecutor(
                self.workers,
                mp_context=multiprocessing.get_context("spawn"),
                initializer=_worker_init,
                initargs=(self.agent_spec, self.renderer, self.trust_code, 1, self.agent_kwargs, self.vecnormalize),
            ) as pool:
                futures = {
                    pool.submit(_fly, task, self.writer, self.width, self.save_trajectories): len(task)
                    for task in tasks
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


def load_records(out_dir: str | Path) -> pd.DataFrame:
    """Every valid record of ``out_dir`` (``records.jsonl``, shards of a running or killed evaluation, legacy
    ``records/*.json``) as a DataFrame with :data:`EPISODE_COLUMNS`.

    An invalid line is named (file, line, reason) in a warning and left out (never counted); :class:`Evaluator`
    sets such lines aside and re-runs their episodes.
    """
    found = read_folder(out_dir)
    for problem in found.problems:
        logger.warning("racebench: invalid record left out: %s", problem.error())
    rows = found.sorted_records()
    frame = pd.DataFrame(rows, columns=list(EPISODE_COLUMNS))
    return frame.sort_values(["agent", "env_id", "seed"], kind="stable").reset_index(drop=True)


def summarize(episodes: pd.DataFrame) -> pd.DataFrame:
    """One row per agent × env id: n, successes, success rate, 95 % Wilson interval, lap-time stats.

    Raises :class:`MixedResultsError` if one agent × env id holds episodes of more than one ``policy_sha256``.
    """
    rows = []
    for (agent, env_id), group in episodes.groupby(["agent", "env_id"], sort=True):
        n = len(group)
        if "policy_sha256" in group:
            policies = sorted(group["policy_sha256"].astype(str).unique())
            if len(policies) > 1:  # e.g. two evaluations writing into one folder at once: not one policy's rate
                raise MixedResultsError(
                    f"the {n} {env_id} episodes labelled {agent!r} come from {len(policies)} policies (sha256 "
                    f"{', '.join(h[:12] for h in policies)}): a summary row counts one policy's episodes only"
                )
        k = int(group["success"].astype(bool).sum())
        low, high = wilson_interval(k, n)
        laps = pd.to_numeric(group.loc[group["success"].astype(bool), "lap_time"], errors="coerce").dropna()
        track, variant = split_env_id(env_id)
        rows.append(
            {
                "agent": agent,
                "privileged": bool(group["privileged"].astype(bool).any()),
                "env_id": env_id,
                "track": track,
                "variant": variant,
                "n": n,
                "successes": k,
                "success_rate": k / n,
                "sr_ci_low": low,
                "sr_ci_high": high,
                "lap_time_median": float(laps.median()) if len(laps) else float("nan"),
                "lap_time_mean": float(laps.mean()) if len(laps) else float("nan"),
                "lap_time_std": float(laps.std(ddof=1)) if len(laps) > 1 else float("nan"),
            }
        )
    return pd.DataFrame(rows)


def write_tables(out_dir: str | Path) -> pd.DataFrame:
    """Rebuild ``episodes.csv`` and ``summary.csv`` in ``out_dir`` from its valid records; return the episodes."""
    out_dir = Path(out_dir)
    episodes = load_records(out_dir)
    summary = summarize(episodes)  # first: a folder it refuses keeps both of its previous tables
    atomic_write(out_dir / "episodes.csv", episodes.to_csv(index=False))
    atomic_write(out_dir / "summary.csv", summary.to_csv(index=False, float_format="%.4f"))
    return episodes


def _tracks_overlap(track_sets: list[set[str]]) -> bool:
    """Whether any two of these policies' track sets share a track."""
    seen: set[str] = set()
    for flown in track_sets:
        if seen & flown:
            return True
        seen |= flown
    return False


def load_result_dir(path: str | Path) -> tuple[Path, pd.DataFrame]:
    """A result directory (or the ``summary.csv`` / ``episodes.csv`` in it) and its valid records' episodes; a path
    without records, or with no valid one, is an error naming it."""
    path = Path(path)
    if path.is_file() and path.name in ("summary.csv", "episodes.csv"):
        path = path.parent
    if not has_records(path):
        raise FileNotFoundError(f"no evaluation records at {str(path)!r} (expected {str(path / RECORDS_FILE)!r})")
    episodes = load_records(path)
    if episodes.empty:
        raise ValueError(f"no valid evaluation records in {str(path)!r}")
    return path, episodes


def _directory_label(path: Path) -> str:
    """A result directory's name for a table row: the run it belongs to, not a generic evaluation folder's name.

    ``eval``, ``eval-*`` and ``exported`` name what was evaluated, not which policy: the parent's name stands
    instead (``distill-ppo-bc/eval-exported`` -> ``distill-ppo-bc``). A per-track or per-seed subfolder (``S``,
    ``Circle``, ``seed1``) keeps its run's name in front (``distill-ppo-gate-centre/Circle``).
    """
    parts = list(path.resolve().parts)
    if parts and (parts[-1] in ("eval", "exported") or parts[-1].startswith("eval-")):
        parts.pop()
    name = parts[-1] if parts else str(path)
    if len(parts) > 1 and (name in TRACK_IDS or re.fullmatch(r"seed\d+", name)):
        name = f"{parts[-2]}/{name}"
    return name


def read_summaries(paths: Iterable[str | Path]) -> pd.DataFrame:
    """Summaries of result directories, recomputed from their validated records.

    A path to a ``summary.csv`` or ``episodes.csv`` stands for the directory holding it: the CSV itself is
    never read back, so an edited CSV cannot change a table. Several policies under one label form one row when
    their tracks are disjoint (one policy per track), else each is labelled with its directory's name.
    """
    loaded = [load_result_dir(path) for path in paths]
    if not loaded:
        raise ValueError("no result directories given")
    # One label, several policies. When each policy was flown on tracks no other one was (a sweep's per-track runs
    # of one config and seed, each evaluated on its own track), the label stays one row, as the paper's Table II
    # has one row per method with a policy per track. When their tracks overlap (e.g. per-track students also
    # flown on the other tracks), one row would mix two policies' results on a track: each such policy gets the
    # name of the first directory holding it (see _directory_label), in every directory it appears in.
    tracks: dict[str, dict[str, set[str]]] = {}  # label -> policy -> the tracks it was flown on
    for _, episodes in loaded:
        for (agent, policy), group in episodes.groupby(["agent", episodes["policy_sha256"].astype(str)]):
            tracks.setdefault(str(agent), {}).setdefault(policy, set()).update(group["track"].astype(str))
    shared = {agent for agent, by_policy in tracks.items() if _tracks_overlap(list(by_policy.values()))}
    for agent in sorted(set(tracks) - shared):
        if len(tracks[agent]) > 1:
            per_track = ", ".join(f"{'/'.join(sorted(t))} {h[:12]}" for h, t in sorted(tracks[agent].items()))
            logger.debug("%s: one row of %d policies, one per track (%s)", agent, len(tracks[agent]), per_track)
    renamed: dict[tuple[str, str], str] = {}  # (label, policy) -> label (its first directory's name)
    for path, episodes in loaded:
        where = _directory_label(path)
        for agent, policy in zip(episodes["agent"], episodes["policy_sha256"].astype(str), strict=True):
            if agent in shared:
                renamed.setdefault((agent, policy), f"{agent} ({where})")
    if len(set(renamed.values())) < len(renamed):
        raise ValueError("several policies share a label and a directory name: give them distinct --name labels")
    frames = []
    for _, episodes in loaded:
        if shared & set(episodes["agent"]):
            pairs = zip(episodes["agent"], episodes["policy_sha256"].astype(str), strict=True)
            episodes = episodes.assign(agent=[renamed.get((a, h), a) for a, h in pairs])
        frames.append(summarize(episodes))
    if shared:
        logger.warning("the label(s) %s name several policies: each row is labelled with its directory",
                       ", ".join(sorted(shared)))  # fmt: skip
    return pd.concat(frames, ignore_index=True)


def paired_comparison(a_dir: str | Path, b_dir: str | Path) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Two evaluations compared scene by scene, from their validated records (never their CSVs).

    Each directory must hold one policy's episodes. Episodes are paired by ``(env_id, seed)``: the seed protocol
    gives both policies the same scenes, so a paired test (McNemar's exact test on the laps only one of them
    finished) tells apart rates whose unpaired Wilson intervals overlap. Returns ``(sides, pairs)``: per
    directory its label, policy, episodes, successes, Wilson interval, mean lap and failure causes; per shared
    env id, then ``all`` of them pooled, the pairs, each side's successes, ``only_a``, ``only_b`` and ``p``.
    """
    episodes, sides = [], []
    for path, frame in (load_result_dir(a_dir), load_result_dir(b_dir)):
        policies = sorted(frame["policy_sha256"].astype(str).unique())
        if len(policies) > 1:
            labels = ", ".join(sorted(set(frame["agent"].astype(str))))
            raise ValueError(f"{str(path)!r} holds {len(policies)} policies' episodes ({labels}): compare one "
                             "policy's evaluation with another's")  # fmt: skip
        frame = frame.assign(success=frame["success"].astype(bool))
        wins, n = int(frame["success"].sum()), len(frame)
        low, high = wilson_interval(wins, n)
        causes = frame.loc[~frame["success"], "crash_reason"].fillna("time limit").astype(str).str.split(":").str[0]
        sides.append({"evaluation": str(path), "agent": str(frame["agent"].iloc[0]), "policy_sha256": policies[0][:12],
                      "n": n, "successes": wins, "success_rate": wins / n, "sr_ci_low": low, "sr_ci_high": high,
                      "lap_time_mean": pd.to_numeric(frame.loc[frame["success"], "lap_time"]).mean(),
                      "failures": {str(k): int(v) for k, v in causes.value_counts().items()}})  # fmt: skip
        episodes.append(frame[["env_id", "seed", "success"]])
    a, b = episodes
    shared = [env for env in a["env_id"].unique() if env in set(b["env_id"])]
    rows = []
    for env_id, part_a, part_b in [*((e, a[a["env_id"] == e], b[b["env_id"] == e]) for e in shared), ("all", a, b)]:
        pairs = part_a.merge(part_b, on=["env_id", "seed"], suffixes=("_a", "_b"))
        n, only_a, only_b, p = paired_outcomes(part_a, part_b)
        rows.append({"env_id": env_id, "pairs": n, "successes_a": int(pairs["success_a"].sum()),
                     "successes_b": int(pairs["success_b"].sum()), "only_a": only_a, "only_b": only_b,
                     "p": p})  # fmt: skip
    if rows[-1]["pairs"] == 0:
        raise ValueError(f"{str(a_dir)!r} and {str(b_dir)!r} share no (env_id, seed) episode to pair")
    return pd.DataFrame(sides), pd.DataFrame(rows)
