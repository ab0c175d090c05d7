"""An evaluation worker: the process-wide agent and envs that fly jobs and write their records.

The same interface serves the local process pool (:class:`~racebench.evaluation.evaluator.Evaluator`) and the
Ray actors (:mod:`racebench.evaluation.ray_backend`): :func:`worker_init` once per process, then :func:`fly` per
job list; :data:`WORKER` holds the process's agent.
"""

from __future__ import annotations

import atexit
import sys
from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np

from racebench.agents.loading import load_agent
from racebench.evaluation.rollout import BatchAgent, env_error_result, run_episode, run_lockstep
from racebench.evaluation.writer import RecordWriter

# Worker-process state: one agent, built once per process, and its settings.
WORKER: dict[str, Any] = {}


def worker_init(
    agent_spec: str,
    renderer: str,
    trust_code: bool,
    threads: int,
    agent_kwargs: dict[str, Any] | None = None,
    vecnormalize: str | bool | None = None,
) -> None:
    close_pool()
    if not WORKER.get("atexit"):
        atexit.register(close_pool)  # a worker process's envs, at its exit
        WORKER["atexit"] = True
    agent = load_agent(agent_spec, trust_code=trust_code, agent_kwargs=agent_kwargs, vecnormalize=vecnormalize)
    WORKER.update(agent=agent, renderer=renderer, pool={})
    torch = sys.modules.get("torch")  # imported by learned agents only; built-ins need not pay for it
    if torch is not None:
        torch.set_num_threads(threads)


def close_pool() -> None:
    """Close the envs this process keeps between tasks (PyBullet clients left to interpreter exit print errors)."""
    for envs in WORKER.get("pool", {}).values():
        for env in envs:
            env.close()
    WORKER["pool"] = {}


def fly(
    jobs: list[tuple[str, int]],
    writer: RecordWriter,
    width: int,
    save_trajectories: bool,
    on_written: Callable[[], None] | None = None,
) -> list[dict[str, Any]]:
    """Fly ``jobs`` with this process's agent, writing each record as its episode ends; return the records.

    A :class:`~racebench.evaluation.rollout.BatchAgent` flies ``width`` episodes in lockstep; any other agent one
    episode at a time. ``on_written`` is called after each record (progress).
    """
    agent = WORKER["agent"]
    written: list[dict[str, Any]] = []

    def make_env(env_id: str) -> gym.Env:
        return gym.make(env_id, obs_mode=agent.obs_mode, renderer=WORKER["renderer"])

    def done(env_id: str, seed: int, result: dict[str, Any], flown: dict | None) -> None:
        written.append(writer.write(env_id, seed, result, flown))
        if on_written is not None:
            on_written()

    if width > 1 and isinstance(agent, BatchAgent):
        pool = WORKER["pool"]  # envs kept between this process's tasks: building one costs ~20-50 ms
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
