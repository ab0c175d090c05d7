"""The common evaluator: fly an agent on a suite of env ids over fixed seeds, write tidy CSVs.

Protocol (versioned by :data:`SEED_PROTOCOL`):

* Evaluation episode ``i`` of every env id uses seed ``EVAL_SEED_BASE + i``. Training must only use seeds
  below :data:`EVAL_SEED_BASE` (``racebench`` training does), so no evaluation scene is ever trained on.
* Success = every gate of the track (one lap of a loop) passed in order, without any contact, within the
  time limit. Lap time (LT) = the time of a successful lap; failed episodes have no LT.
* An agent that raises, returns NaN or a wrongly shaped action ends that episode as a failure with the
  reason recorded (``crash_reason = "agent_error"``, ``error`` column); the sweep goes on.

Output, in ``out_dir``: ``episodes.csv`` (one row per episode) and ``summary.csv`` (one row per agent ×
env id: n, successes, success rate with a 95 % Wilson interval, median/mean lap time over successes).
Each finished episode is first stored as its own small JSON record (written to a temporary file and
renamed into place, so never half-written); the CSVs are rebuilt from the records the same way. Running
again with the same ``out_dir`` resumes: finished episodes are kept and skipped, a killed run loses at
most the episodes in flight.
"""

from __future__ import annotations

import atexit
import hashlib
import json
import multiprocessing
import os
import re
import subprocess
import tempfile
import time
import traceback
from collections.abc import Iterable, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pandas as pd
from scipy.stats import binomtest
from tqdm.auto import tqdm

import racebench
from racebench.agents import Agent, load_agent
from racebench.registration import DENSITIES, GATE_SHIFTS

SEED_PROTOCOL = 1
EVAL_SEED_BASE = 1_000_000
TRACK_ORDER: tuple[str, ...] = ("S", "Circle", "J")  # the paper's column order
SUITES: dict[str, list[str]] = {
    "main": [f"RaceObs-{t}-v0" for t in TRACK_ORDER],
    "density": [f"RaceObs-{t}-Density{d}-v0" for d in DENSITIES for t in TRACK_ORDER],
    "gates": [f"RaceObs-{t}-GateShift{s}-v0" for s in GATE_SHIFTS for t in TRACK_ORDER],
}
SUITES["paper"] = SUITES["main"] + SUITES["density"] + SUITES["gates"]
EPISODE_COLUMNS: tuple[str, ...] = (
    "agent", "privileged", "env_id", "track", "variant", "seed", "success", "lap_time", "crashed",
    "crash_reason", "gates_passed", "return", "steps", "error", "racebench_version", "git_commit",
)  # fmt: skip
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


def wilson_interval(successes: int, n: int, confidence: float = 0.95) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion (``nan, nan`` when ``n == 0``)."""
    if n == 0:
        return float("nan"), float("nan")
    ci = binomtest(successes, n).proportion_ci(confidence_level=confidence, method="wilson")
    return float(ci.low), float(ci.high)


def git_commit() -> str:
    """The commit of the racebench checkout, or ``"unknown"`` outside a git checkout."""
    try:
        out = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"],
            cwd=Path(__file__).parent,
            capture_output=True,
            text=True,
            timeout=5,
            check=True,
        )
        return out.stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def _agent_error(obs_action: Any) -> tuple[np.ndarray | None, str | None]:
    try:
        action = np.asarray(obs_action, dtype=np.float64).reshape(-1) if obs_action is not None else None
    except (TypeError, ValueError) as exc:
        return None, f"action is not numeric: {exc}"
    if action is None:
        return None, "agent returned None"
    if action.shape != (4,):
        return None, f"action has shape {np.shape(obs_action)}, expected (4,)"
    if not np.all(np.isfinite(action)):
        return None, f"action is not finite: {action.tolist()}"
    return action.astype(np.float32), None


def run_episode(agent: Agent, env: gym.Env, seed: int, trajectory: list | None = None) -> dict[str, Any]:
    """Fly one episode; never raises because of the agent (its failures become the episode's outcome)."""
    obs, info = env.reset(seed=seed)
    unwrapped = env.unwrapped
    total, steps, error = 0.0, 0, None
    terminated = truncated = False
    try:
        agent.reset(env=unwrapped if agent.privileged else None, seed=seed)
    except Exception as exc:  # noqa: BLE001 - an agent failure is a result, not a crash of the sweep
        error = f"reset raised {type(exc).__name__}: {exc}"
    if trajectory is not None:
        trajectory.append(unwrapped.drone.position.copy())
    while error is None and not (terminated or truncated):
        try:
            raw = agent.act(obs)
        except Exception as exc:  # noqa: BLE001
            error = f"act raised {type(exc).__name__}: {exc}"
            break
        action, error = _agent_error(raw)
        if error:
            break
        obs, reward, terminated, truncated, info = env.step(action)
        total += float(reward)
        steps += 1
        if trajectory is not None:
            trajectory.append(unwrapped.drone.position.copy())
    return {
        "success": bool(info["is_success"]) and error is None,
        "lap_time": info["lap_time"] if error is None else None,
        "crashed": bool(info["crashed"]),
        "crash_reason": "agent_error" if error else info["crash_reason"],
        "gates_passed": int(info["gates_passed"]),
        "return": total,
        "steps": steps,
        "error": error,
    }


def atomic_write(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` via a synced temporary file and a rename: a kill leaves the old file or the new."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _record_name(agent: str, env_id: str, seed: int) -> str:
    digest = hashlib.sha1(f"{agent}\0{env_id}\0{seed}".encode()).hexdigest()[:16]
    return f"{digest}.json"


# Worker-process state: one agent and one env per id, built once per process.
_WORKER: dict[str, Any] = {}


def _worker_init(agent_spec: str, agent_name: str | None, env_kwargs: dict[str, Any]) -> None:
    _close_worker_envs()
    agent = load_agent(agent_spec)
    _WORKER.update(agent=agent, name=agent_name or agent.name, envs={}, env_kwargs=env_kwargs)


def _close_worker_envs() -> None:
    """Close this process's evaluation envs (PyBullet clients left to interpreter shutdown print errors)."""
    for env in _WORKER.get("envs", {}).values():
        env.close()
    _WORKER["envs"] = {}


def _pool_worker_init(agent_spec: str, agent_name: str | None, env_kwargs: dict[str, Any]) -> None:
    import torch  # here: only learned agents need it, and they have imported it already

    torch.set_num_threads(1)  # one episode at a time per worker, one worker per core
    atexit.register(_close_worker_envs)
    _worker_init(agent_spec, agent_name, env_kwargs)


def _worker_run(env_id: str, seed: int, save_trajectory: bool) -> tuple[str, int, dict[str, Any], dict | None]:
    agent = _WORKER["agent"]
    envs = _WORKER["envs"]
    if env_id not in envs:
        envs[env_id] = gym.make(env_id, obs_mode=agent.obs_mode, **_WORKER["env_kwargs"])
    trajectory: list | None = [] if save_trajectory else None
    try:
        result = run_episode(agent, envs[env_id], seed, trajectory)
    except Exception:  # noqa: BLE001 - an env-side failure is recorded too, the sweep goes on
        result = {
            "success": False, "lap_time": None, "crashed": False, "crash_reason": "env_error",
            "gates_passed": 0, "return": 0.0, "steps": 0, "error": traceback.format_exc(limit=3),
        }  # fmt: skip
    flown = None
    if trajectory:
        flown = {"positions": np.array(trajectory), "scene": envs[env_id].unwrapped.scene.to_dict()}
    return env_id, seed, result, flown


class Evaluator:
    """Evaluate one agent on env ids over the fixed evaluation seeds, resumably.

    Args:
        agent_spec: see :func:`racebench.agents.load_agent`.
        envs: env ids and/or suite names.
        episodes: episodes per env id (the paper: 10).
        out_dir: where ``episodes.csv``, ``summary.csv`` and the per-episode records go.
        workers: processes to use (each builds its own agent and envs).
        agent_name: name in the CSVs (default: the agent's own name).
        save_trajectories: also store each episode's positions and scene (for the 3D track figure).
        env_kwargs: extra kwargs for every ``gym.make`` (e.g. ``renderer``); recorded nowhere, so keep
            them to ones that do not change the task.
    """

    def __init__(
        self,
        agent_spec: str,
        envs: Sequence[str] = ("main",),
        episodes: int = 10,
        out_dir: str | Path = "results",
        workers: int = 1,
        agent_name: str | None = None,
        save_trajectories: bool = False,
        env_kwargs: dict[str, Any] | None = None,
    ) -> None:
        if episodes < 1:
            raise ValueError(f"episodes must be >= 1, got {episodes}")
        if workers < 1:
            raise ValueError(f"workers must be >= 1, got {workers}")
        self.agent_spec = agent_spec
        self.env_ids = resolve_envs(envs)
        self.episodes = episodes
        self.out_dir = Path(out_dir)
        self.workers = workers
        self.save_trajectories = save_trajectories
        self.env_kwargs = env_kwargs or {}
        probe = load_agent(agent_spec)  # fail fast, in this process, on a bad spec
        self.agent_name = agent_name or probe.name
        self.privileged = bool(getattr(probe, "privileged", False))
        self.records_dir = self.out_dir / "records"
        self.version = racebench.__version__
        self.commit = git_commit()

    def pending(self) -> list[tuple[str, int]]:
        """(env id, seed) pairs without a finished record."""
        return [
            (env_id, seed)
            for env_id in self.env_ids
            for seed in eval_seeds(self.episodes)
            if not (self.records_dir / _record_name(self.agent_name, env_id, seed)).exists()
        ]

    def _store(self, env_id: str, seed: int, result: dict[str, Any], flown: dict | None) -> None:
        track, variant = split_env_id(env_id)
        row = {
            "agent": self.agent_name,
            "privileged": self.privileged,
            "env_id": env_id,
            "track": track,
            "variant": variant,
            "seed": seed,
            **result,
            "racebench_version": self.version,
            "git_commit": self.commit,
        }
        if flown is not None:
            traj_dir = self.out_dir / "trajectories"
            traj_dir.mkdir(parents=True, exist_ok=True)
            name = _record_name(self.agent_name, env_id, seed).replace(".json", ".npz")
            tmp = traj_dir / f".{name}.tmp.npz"
            scene = json.dumps(flown["scene"])
            np.savez_compressed(tmp, positions=flown["positions"], scene=scene, row=json.dumps(row))
            os.replace(tmp, traj_dir / name)
        atomic_write(self.records_dir / _record_name(self.agent_name, env_id, seed), json.dumps(row))

    def run(self, progress: bool = True) -> pd.DataFrame:
        """Run every pending episode, then write the CSVs; returns the summary of this output directory."""
        todo = self.pending()
        started = time.perf_counter()
        bar = tqdm(total=len(todo), desc=f"{self.agent_name}", disable=not progress, unit="ep")
        if self.workers == 1 or len(todo) <= 1:
            _worker_init(self.agent_spec, self.agent_name, self.env_kwargs)
            for env_id, seed in todo:
                self._store(*_worker_run(env_id, seed, self.save_trajectories))
                bar.update()
            _close_worker_envs()
        else:
            # "spawn": a forked child of a process that has run torch can deadlock in torch's thread pool
            # (seen: --workers 2 with a GRU checkpoint hung at start).
            with ProcessPoolExecutor(
                self.workers,
                mp_context=multiprocessing.get_context("spawn"),
                initializer=_pool_worker_init,
                initargs=(self.agent_spec, self.agent_name, self.env_kwargs),
            ) as pool:
                futures = [pool.submit(_worker_run, env_id, seed, self.save_trajectories) for env_id, seed in todo]
                for future in as_completed(futures):
                    self._store(*future.result())
                    bar.update()
        bar.close()
        self.elapsed = time.perf_counter() - started
        return write_tables(self.out_dir)


def load_records(out_dir: str | Path) -> pd.DataFrame:
    """Every finished episode under ``out_dir`` as a DataFrame with :data:`EPISODE_COLUMNS`."""
    rows = [json.loads(p.read_text()) for p in sorted((Path(out_dir) / "records").glob("*.json"))]
    frame = pd.DataFrame(rows, columns=list(EPISODE_COLUMNS))
    return frame.sort_values(["agent", "env_id", "seed"], kind="stable").reset_index(drop=True)


def summarize(episodes: pd.DataFrame) -> pd.DataFrame:
    """One row per agent × env id: n, successes, success rate, 95 % Wilson interval, lap-time stats."""
    rows = []
    for (agent, env_id), group in episodes.groupby(["agent", "env_id"], sort=True):
        n = len(group)
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
    """Rebuild ``episodes.csv`` and ``summary.csv`` in ``out_dir`` from its records (atomically)."""
    out_dir = Path(out_dir)
    episodes = load_records(out_dir)
    summary = summarize(episodes)
    atomic_write(out_dir / "episodes.csv", episodes.to_csv(index=False))
    atomic_write(out_dir / "summary.csv", summary.to_csv(index=False, float_format="%.4f"))
    return summary


def read_summaries(paths: Iterable[str | Path]) -> pd.DataFrame:
    """Concatenate summaries from result directories or ``summary.csv``/``episodes.csv`` files."""
    frames = []
    for path in paths:
        path = Path(path)
        if path.is_dir():
            path = path / "summary.csv"
        if not path.is_file():
            raise FileNotFoundError(f"no results at {str(path)!r}")
        frame = pd.read_csv(path)
        frames.append(summarize(frame) if "seed" in frame.columns else frame)
    if not frames:
        raise ValueError("no result files given")
    return pd.concat(frames, ignore_index=True)
