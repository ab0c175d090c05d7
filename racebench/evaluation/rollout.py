"""Flying evaluation episodes: one at a time, or many in lockstep with one batched policy call per step.

On a CPU a learned policy's batch-1 forward pass costs more than a simulator step (~2 ms against ~0.2 ms with
the ray caster), and most of it is per-call overhead: 32 observations in one call cost about as much as 1.
:func:`run_lockstep` therefore flies up to ``width`` episodes side by side, each in its own env, and asks the
agent for all their actions at once; a finished episode's slot takes the next pending one at once (its
recurrent memory cleared). An agent takes part when it implements :class:`BatchAgent`; others fly their
episodes one after another with :func:`run_episode`.

Both never raise because of the agent: a failure (exception, NaN, wrong shape) ends that episode as an
``agent_error``, and an exception inside the env ends it as an ``env_error``; the sweep goes on.
"""

from __future__ import annotations

import traceback
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import gymnasium as gym
import numpy as np

from racebench.agents.base import Agent
from racebench.sim.raycast import BatchDepthRenderer

Result = dict[str, Any]
#: Called with (env id, seed, result, flown) as each episode ends; ``flown`` holds the positions and the
#: scene when trajectories are saved, else ``None``.
OnDone = Callable[[str, int, Result, "dict | None"], None]


@runtime_checkable
class BatchAgent(Protocol):
    """An agent that can act for many episodes at once (SB3 and ONNX agents are)."""

    def start(self, slots: int) -> None:
        """Prepare ``slots`` parallel episodes (all memory cleared)."""

    def reset_slot(self, slot: int) -> None:
        """A new episode begins in ``slot``: clear its memory."""

    def act_batch(self, observations: list[Any]) -> np.ndarray:
        """Actions ``(slots, 4)`` for one observation per slot."""


def check_action(raw: Any) -> tuple[np.ndarray | None, str | None]:
    """``(action, None)`` for a finite 4-vector, else ``(None, what is wrong)``."""
    try:
        action = np.asarray(raw, dtype=np.float64).reshape(-1) if raw is not None else None
    except (TypeError, ValueError) as exc:
        return None, f"action is not numeric: {exc}"
    if action is None:
        return None, "agent returned None"
    if action.shape != (4,):
        return None, f"action has shape {np.shape(raw)}, expected (4,)"
    if not np.all(np.isfinite(action)):
        return None, f"action is not finite: {action.tolist()}"
    return action.astype(np.float32), None


def _result(info: dict, total: float, steps: int, error: str | None) -> Result:
    return {
        "success": bool(info.get("is_success")) and error is None,
        "lap_time": info.get("lap_time") if error is None else None,
        "crashed": bool(info.get("crashed", False)),
        "crash_reason": "agent_error" if error else info.get("crash_reason"),
        "gates_passed": int(info.get("gates_passed", 0)),
        "return": total,
        "steps": steps,
        "error": error,
    }


def env_error_result() -> Result:
    """The outcome of an episode that the env itself failed (the traceback is the error)."""
    return {
        "success": False, "lap_time": None, "crashed": False, "crash_reason": "env_error",
        "gates_passed": 0, "return": 0.0, "steps": 0, "error": traceback.format_exc(limit=3),
    }  # fmt: skip


def run_episode(agent: Agent, env: gym.Env, seed: int, trajectory: list | None = None) -> Result:
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
        action, error = check_action(raw)
        if error:
            break
        obs, reward, terminated, truncated, info = env.step(action)
        total += float(reward)
        steps += 1
        if trajectory is not None:
            trajectory.append(unwrapped.drone.position.copy())
    return _result(info, total, steps, error)


@dataclass
class _Slot:
    env_id: str
    seed: int
    env: gym.Env  # as made (closed at the end)
    raw: Any  # its RaceEnv: stepped through advance()/observation() so depth renders in one batch
    info: dict
    obs: Any = None
    total: float = 0.0
    steps: int = 0
    trajectory: list | None = field(default=None)


def run_lockstep(
    agent: BatchAgent,
    jobs: Iterable[tuple[str, int]],
    make_env: Callable[[str], gym.Env],
    on_done: OnDone,
    width: int = 16,
    save_trajectories: bool = False,
    pool: dict[str, list[gym.Env]] | None = None,
) -> None:
    """Fly every ``(env id, seed)`` of ``jobs``, ``width`` episodes side by side, one batched call per step.

    Every call passes exactly ``width`` observations (idle slots repeat an active one and their actions are
    dropped), so a slot's numbers never depend on how many episodes are left. ``make_env(env_id)`` builds a
    ``RaceEnv`` (possibly wrapped); envs are reused across episodes of the same id, and across calls when the
    caller passes a ``pool`` (env id → idle envs; the caller then closes them). The envs are stepped as
    :class:`~racebench.envs.vector.RaceVectorEnv` steps them: ``advance`` each, then one depth render for all
    (ray caster), so each episode is exactly what ``env.step`` would give.
    """
    if width < 1:
        raise ValueError(f"width must be >= 1, got {width}")
    pending = deque(jobs)
    free: dict[str, list[gym.Env]] = {} if pool is None else pool
    made: list[gym.Env] = []
    slots: list[_Slot | None] = [None] * width
    unobserved: list[int] = []  # slots whose current observation is still to be made
    casters: dict[int, BatchDepthRenderer] = {}
    agent.start(width)

    def finish(i: int, error: str | None = None, result: Result | None = None) -> None:
        slot = slots[i]
        slots[i] = None
        flown = None
        if slot.trajectory:
            flown = {"positions": np.array(slot.trajectory), "scene": slot.raw.scene.to_dict()}
        on_done(slot.env_id, slot.seed, result or _result(slot.info, slot.total, slot.steps, error), flown)
        free.setdefault(slot.env_id, []).append(slot.env)
        fill(i)

    def fill(i: int) -> None:
        while pending:
            env_id, seed = pending.popleft()
            if free.get(env_id):
                env = free[env_id].pop()
            else:
                env = make_env(env_id)
                made.append(env)
            try:
                info = env.unwrapped.reset_state(seed=seed)
            except Exception:  # noqa: BLE001 - an env-side failure is recorded, the sweep goes on
                on_done(env_id, seed, env_error_result(), None)
                free.setdefault(env_id, []).append(env)
                continue
            raw = env.unwrapped
            trajectory = [raw.drone.position.copy()] if save_trajectories else None
            slots[i] = _Slot(env_id, seed, env, raw, info, trajectory=trajectory)
            unobserved.append(i)
            try:
                agent.reset_slot(i)
            except Exception as exc:  # noqa: BLE001
                unobserved.remove(i)
                finish(i, f"reset raised {type(exc).__name__}: {exc}")
            return

    def observe() -> None:
        """Observations of the slots in ``unobserved``; ray-cast depth of all of them in one call."""
        todo = [i for i in unobserved if slots[i] is not None]
        unobserved.clear()
        cast = [i for i in todo if slots[i].raw.raycaster is not None and slots[i].raw.obs_mode == "vision"]
        if cast:
            raws = [slots[i].raw for i in cast]
            camera = raws[0].camera
            caster = casters.setdefault(id(camera), BatchDepthRenderer(camera))
            depth = caster.render(
                [r.scene for r in raws], np.stack([r.drone.position for r in raws]),
                np.stack([r.camera_rotation() for r in raws]),
            )  # fmt: skip
            for i, d in zip(cast, depth, strict=True):
                slots[i].obs = slots[i].raw.observation(d)
        for i in todo:
            if i not in cast:
                slots[i].obs = slots[i].raw.observation()

    for i in range(width):
        if slots[i] is None:
            fill(i)
    try:
        while True:
            observe()
            active = [i for i, slot in enumerate(slots) if slot is not None]
            if not active:
                break
            filler = slots[active[0]].obs
            observations = [slot.obs if slot is not None else filler for slot in slots]
            try:
                actions = np.asarray(agent.act_batch(observations), dtype=np.float64)
                if actions.shape != (width, 4):
                    raise ValueError(f"act_batch returned shape {actions.shape}, expected ({width}, 4)")
            except Exception as exc:  # noqa: BLE001 - every episode in flight fails with the reason
                for i in active:
                    finish(i, f"act raised {type(exc).__name__}: {exc}")
                continue
            finite = np.isfinite(actions).all(axis=1)  # checked for the whole batch at once
            actions = actions.astype(np.float32)
            for i in active:
                slot = slots[i]
                action = actions[i]
                if not finite[i]:
                    finish(i, f"action is not finite: {action.tolist()}")
                    continue
                try:
                    reward, terminated, truncated, slot.info = slot.raw.advance(action)
                except Exception:  # noqa: BLE001
                    finish(i, result=env_error_result())
                    continue
                slot.total += float(reward)
                slot.steps += 1
                if slot.trajectory is not None:
                    slot.trajectory.append(slot.raw.drone.position.copy())
                if terminated or truncated:
                    finish(i)
                else:
                    unobserved.append(i)
    finally:
        if pool is None:
            for env in made:
                env.close()
        else:  # envs still in a slot (an exception escaped) go back to the caller's pool too
            for slot in slots:
                if slot is not None:
                    free.setdefault(slot.env_id, []).append(slot.env)
