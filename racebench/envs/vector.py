"""Vectorized racing: N :class:`~racebench.envs.env.RaceEnv` stepped together, their depth images rendered in one
batched ray-cast call, optionally spread over processes (this one and worker processes, a batch of envs each).

Two front ends share one core (:class:`EnvBatch`, one per process):

* :class:`RaceVectorEnv`, a ``gymnasium.vector.VectorEnv``. Every registered id names it as its
  ``vector_entry_point``, so ``gym.make_vec("RaceObs-S-v0", num_envs=16, renderer="raycast", num_processes=2)``
  builds it; the default autoreset mode is Gymnasium's ``NEXT_STEP`` (``SAME_STEP`` and ``DISABLED`` too).
* :class:`racebench.training.sb3.RaceSB3VecEnv`, a Stable-Baselines3 ``VecEnv`` (same-step autoreset,
  ``terminal_observation`` and ``TimeLimit.truncated`` in the infos, like SB3's ``DummyVecEnv``), in its own
  module so that worker processes never import SB3 (and torch).

Episodes are identical to those of N separate envs seeded alike (``reset(seed=s)`` seeds env i with
``s + i``), whatever the number of processes: each env keeps its own random generator, and the batched
depth of a camera does not depend on the other cameras in its batch. Observations from worker processes come
back through shared memory; actions, rewards and infos through pipes.

Batching only pays for ``renderer="raycast"`` (the default here is ``"pybullet"``, the registered ids'
default, so that ``make_vec`` and ``make`` give the same observations); with PyBullet's renderer each env
renders its own image.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import traceback
from collections.abc import Callable, Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode
from gymnasium.vector.utils import batch_space

from racebench.envs.env import RaceEnv
from racebench.envs.infos import concat_infos, stack_infos
from racebench.envs.observations import STATE_DIM
from racebench.envs.random_tracks import race_env
from racebench.sim.raycast import BatchDepthRenderer

#: ``multiprocessing.RawArray`` type codes of the depth dtypes (``depth_format``) held in shared memory.
_TYPECODES: dict[str, str] = {"float32": "f", "uint8": "B"}
#: Info key of the training teacher's action for the observation returned with the info (``EnvBatch(teacher=...)``).
TEACHER_KEY = "teacher_action"
#: A factory of a privileged labeller: called with no argument, it returns an object with ``reset(env=...)`` (the
#: unwrapped env, at each episode start) and ``act()`` (the action for the env's current state).
Labeller = Callable[[], Any]
GYM_INFOS, SB3_INFOS = "gym", "sb3"  # info formats: Gymnasium's dict of arrays with "_key" masks; SB3's list of dicts


# ------------------------------------------------------------------ core
class EnvBatch:
    """Envs of one process stepped together; with ``renderer="raycast"`` all their depth images come from
    one :class:`~racebench.sim.raycast.BatchDepthRenderer` call per step.

    Observations are written into caller-owned arrays (shared memory in a worker process): ``state``
    ``(n, 17)`` float32 and, for ``obs_mode="vision"``, ``depth`` ``(n, *depth space shape)`` of the depth
    space's dtype (``(n, 1, size, size)`` float32, or ``(n, size, size, 1)`` uint8 with ``depth_format="uint8"``).

    Args:
        env_kwargs: one ``RaceEnv`` kwargs dict per env (same observation mode and camera for all).
        autoreset_mode: Gymnasium's autoreset mode (see :meth:`step`).
        state, depth: the output arrays (allocated here when ``None``).
        max_episode_steps: also truncate an episode after this many steps, as Gymnasium's ``TimeLimit`` does
            around each env that ``gym.make`` builds (``None``: the envs' own time limit alone).
        teacher: for training only: a picklable factory of a privileged labeller (:data:`Labeller`), called once
            per env (``None``: none). The labeller is reset with its env and, after every reset and step, labels the
            observation returned: its action for that state is in the info as ``"teacher_action"``
            (:data:`TEACHER_KEY`), never in the observation. The envs know no agent: training injects the planner
            (:func:`racebench.training.sb3.teacher_factory`).
    """

    def __init__(
        self,
        env_kwargs: Sequence[dict[str, Any]],
        autoreset_mode: AutoresetMode,
        state: np.ndarray | None = None,
        depth: np.ndarray | None = None,
        max_episode_steps: int | None = None,
        teacher: Labeller | None = None,
    ) -> None:
        self.envs = [race_env(**kw) for kw in env_kwargs]
        self.max_episode_steps = max_episode_steps
        self.teachers = None
        if teacher is not None:
            self.teachers = [teacher() for _ in self.envs]
        first = self.envs[0]
        if any(
            (e.obs_mode, e.renderer, e.depth_format) != (first.obs_mode, first.renderer, first.depth_format)
            for e in self.envs
        ):
            raise ValueError("all envs of a vector env need the same obs_mode, renderer and depth_format")
        n = len(self.envs)
        self.autoreset_mode = autoreset_mode
        self.vision = first.obs_mode == "vision"
        self.state = np.zeros((n, STATE_DIM), dtype=np.float32) if state is None else state
        self.depth = None
        if self.vision:
            space = first.observation_space["depth"]
            self.depth = np.zeros((n, *space.shape), dtype=space.dtype) if depth is None else depth
        self.raycaster = None
        if self.vision and first.renderer == "raycast":
            self.raycaster = BatchDepthRenderer(first.camera)
        self._needs_reset = np.zeros(n, dtype=np.bool_)

    def _observe(self, indices: Sequence[int]) -> list[Any]:
        """Observations of envs ``indices`` (written to the output arrays too), depth rendered in one call."""
        envs = [self.envs[i] for i in indices]
        if self.raycaster is not None and envs:
            depth = self.raycaster.render(
                [e.scene for e in envs],
                np.stack([e.drone.position for e in envs]),
                np.stack([e.camera_rotation() for e in envs]),
            )
            observations = [e.observation(d) for e, d in zip(envs, depth, strict=True)]
        else:
            observations = [e.observation() for e in envs]
        for i, obs in zip(indices, observations, strict=True):
            if self.vision:
                self.state[i] = obs["state"]
                self.depth[i] = obs["depth"]
            else:
                self.state[i] = obs
        return observations

    def reset(
        self, seeds: Sequence[int | None], options: Sequence[dict[str, Any] | None], mask: np.ndarray | None = None
    ) -> list[dict[str, Any] | None]:
        """Reset the envs where ``mask`` (default all) with per-env seeds and options; their infos, else ``None``."""
        indices = [i for i in range(len(self.envs)) if mask is None or mask[i]]
        infos: list[dict[str, Any] | None] = [None] * len(self.envs)
        for i in indices:
            infos[i] = self.envs[i].reset_state(seed=seeds[i], options=options[i] or None)
            self._needs_reset[i] = False
            self._reset_teacher(i)
        self._observe(indices)
        return self._label(infos, indices)

    def _reset_teacher(self, i: int) -> None:
        if self.teachers is not None:
            self.teachers[i].reset(env=self.envs[i])

    def _label(self, infos: list[Any], indices: Sequence[int]) -> list[Any]:
        """``infos`` with the teacher's action for the current state of envs ``indices`` (if there is a teacher)."""
        if self.teachers is None:
            return infos
        for i in indices:
            label = np.clip(np.asarray(self.teachers[i].act(), dtype=np.float32), -1.0, 1.0)
            infos[i] = {**infos[i], TEACHER_KEY: label}
        return infos

    def step(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[dict[str, Any]]]:
        """Step every env, autoresetting as Gymnasium's ``SyncVectorEnv`` does in ``self.autoreset_mode``.

        ``NEXT_STEP``: an env that ended on the previous step is reset instead of stepped (reward 0).
        ``SAME_STEP``: an env that ends now is reset at once; its info holds the reset info plus ``final_obs``
        and ``final_info`` (the last step's). ``DISABLED``: no reset. Returns ``(rewards float64,
        terminations, truncations, per-env infos)``; observations are in the output arrays.
        """
        n = len(self.envs)
        rewards = np.zeros(n, dtype=np.float64)
        terminations = np.zeros(n, dtype=np.bool_)
        truncations = np.zeros(n, dtype=np.bool_)
        infos: list[dict[str, Any]] = [{}] * n
        for i, env in enumerate(self.envs):
            if self.autoreset_mode == AutoresetMode.NEXT_STEP and self._needs_reset[i]:
                infos[i] = env.reset_state()
                self._reset_teacher(i)
            else:
                rewards[i], terminations[i], truncations[i], infos[i] = env.advance(actions[i])
                if self.max_episode_steps is not None and env.steps >= self.max_episode_steps:
                    truncations[i] = True  # TimeLimit's rule: also on a terminating step
        observations = self._observe(range(n))
        done = terminations | truncations
        if self.autoreset_mode == AutoresetMode.SAME_STEP and done.any():
            ended = np.flatnonzero(done).tolist()
            for i in ended:
                final = {"final_obs": observations[i], "final_info": infos[i]}
                infos[i] = {**final, **self.envs[i].reset_state()}
                self._reset_teacher(i)
            self._observe(ended)
        self._needs_reset = done
        return rewards, terminations, truncations, self._label(infos, range(n))

    def call(
        self, name: str, args: tuple, kwargs: dict[str, Any], indices: Sequence[int], invoke: bool = True
    ) -> list[Any]:
        """``getattr(env, name)`` of envs ``indices``; called with ``args``/``kwargs`` if ``invoke`` and callable."""
        out = []
        for i in indices:
            value = getattr(self.envs[i], name)
            out.append(value(*args, **kwargs) if invoke and callable(value) else value)
        return out

    def set_attr(self, name: str, values: Sequence[Any], indices: Sequence[int]) -> None:
        """Set attribute ``name`` of envs ``indices`` to ``values`` (one per index)."""
        for i, value in zip(indices, values, strict=True):
            setattr(self.envs[i], name, value)

    def close(self) -> None:
        """Close every env."""
        for env in self.envs:
            env.close()


def _format(result: tuple, info_format: str) -> tuple:
    """A step's per-env infos in the front end's format (done where the batch lives, i.e. in the worker)."""
    rewards, terminations, truncations, infos = result
    if info_format == GYM_INFOS:
        return rewards, terminations, truncations, stack_infos(infos, len(infos))
    # SB3: the step's info plus TimeLimit.truncated and, on episode end, terminal_observation; the reset info
    # goes to reset_infos.
    sb3_infos, reset_infos = [], {}
    for i, info in enumerate(infos):
        if "final_info" in info:
            reset_infos[i] = {k: v for k, v in info.items() if k not in ("final_obs", "final_info")}
            step_info = dict(info["final_info"])
            step_info["terminal_observation"] = info["final_obs"]
            if TEACHER_KEY in info:  # the label of the observation returned, i.e. of the new episode's first
                step_info[TEACHER_KEY] = info[TEACHER_KEY]
        else:
            step_info = dict(info)
        step_info["TimeLimit.truncated"] = bool(truncations[i] and not terminations[i])
        sb3_infos.append(step_info)
    return rewards.astype(np.float32), terminations | truncations, (sb3_infos, reset_infos)


# ------------------------------------------------------------------ backend
def _worker(
    conn: Any,
    env_kwargs: list[dict[str, Any]],
    autoreset_mode: AutoresetMode,
    info_format: str,
    buffers: tuple[Any, Any],
    offset: int,
    total: int,
    state_shape: tuple[int, ...],
    depth_layout: tuple[tuple[int, ...], str] | None,
    max_episode_steps: int | None,
    teacher: Labeller | None = None,
) -> None:
    """Worker process: owns an :class:`EnvBatch` writing into its slice of the shared observation arrays."""
    try:
        n = len(env_kwargs)
        state = np.frombuffer(buffers[0], dtype=np.float32).reshape(total, *state_shape)[offset : offset + n]
        depth = None
        if depth_layout is not None:
            shape, dtype = depth_layout
            depth = np.frombuffer(buffers[1], dtype=dtype).reshape(total, *shape)[offset : offset + n]
        batch = EnvBatch(env_kwargs, autoreset_mode, state, depth, max_episode_steps, teacher)
        conn.send(("ok", os.getpid()))
    except Exception:  # report to the parent, which raises
        conn.send(("error", traceback.format_exc()))
        return
    while True:
        command, data = conn.recv()
        try:
            if command == "step":
                result: Any = _format(batch.step(data), info_format)
            elif command == "reset":
                infos = batch.reset(*data)
                result = stack_infos(infos, len(infos)) if info_format == GYM_INFOS else infos
            elif command == "call":
                result = batch.call(*data)
            elif command == "set_attr":
                result = batch.set_attr(*data)
            elif command == "close":
                batch.close()
                conn.send(("ok", None))
                return
            else:
                raise ValueError(f"unknown command {command!r}")
            conn.send(("ok", result))
        except Exception:
            conn.send(("error", traceback.format_exc()))


class _Backend:
    """The envs split into ``num_processes`` contiguous batches: the first stepped in this process, each other
    one in a worker process; observations in shared memory, the rest through pipes.

    This process owns a batch (rather than only waiting on workers) so that k processes keep k cores busy.
    """

    def __init__(
        self,
        env_kwargs: list[dict[str, Any]],
        autoreset_mode: AutoresetMode,
        info_format: str,
        num_processes: int,
        context: str | None,
        state_shape: tuple[int, ...],
        depth_layout: tuple[tuple[int, ...], str] | None,
        max_episode_steps: int | None = None,
        teacher: Labeller | None = None,
    ) -> None:
        n = len(env_kwargs)
        self.info_format = info_format
        self.sizes = [len(chunk) for chunk in np.array_split(np.arange(n), num_processes)]
        self.offsets = np.cumsum([0, *self.sizes[:-1]]).tolist()
        self.conns: list[Any] = []
        self.processes: list[Any] = []
        self.closed = False
        buffers: tuple[Any, Any] = (None, None)
        if num_processes == 1:
            self.state = np.zeros((n, *state_shape), dtype=np.float32)
            self.depth = None
            if depth_layout is not None:
                self.depth = np.zeros((n, *depth_layout[0]), dtype=depth_layout[1])
        else:
            if context is None:  # as SB3's SubprocVecEnv: fork is unsafe with threads (torch, numba)
                context = "forkserver" if "forkserver" in mp.get_all_start_methods() else "spawn"
            ctx = mp.get_context(context)
            state_buf = ctx.RawArray("f", n * int(np.prod(state_shape)))
            depth_buf = None
            self.depth = None
            if depth_layout is not None:
                shape, dtype = depth_layout
                depth_buf = ctx.RawArray(_TYPECODES[dtype], n * int(np.prod(shape)))
                self.depth = np.frombuffer(depth_buf, dtype=dtype).reshape(n, *shape)
            buffers = (state_buf, depth_buf)
            self.state = np.frombuffer(state_buf, dtype=np.float32).reshape(n, *state_shape)
            for offset, size in zip(self.offsets[1:], self.sizes[1:], strict=True):
                parent, child = ctx.Pipe()
                chunk = env_kwargs[offset : offset + size]
                args = (
                    child, chunk, autoreset_mode, info_format, buffers, offset, n, state_shape, depth_layout,
                    max_episode_steps, teacher,
                )  # fmt: skip
                process = ctx.Process(target=_worker, args=args, daemon=True)
                process.start()
                child.close()
                self.conns.append(parent)
                self.processes.append(process)
        first = self.sizes[0]
        try:
            depth = self.depth[:first] if self.depth is not None else None
            self.local = EnvBatch(
                env_kwargs[:first], autoreset_mode, self.state[:first], depth, max_episode_steps, teacher
            )
            self.pids = [os.getpid(), *self._gather()]
        except BaseException:
            self.close()
            raise

    def _gather(self) -> list[Any]:
        results, errors = [], []
        for conn in self.conns:
            try:
                status, payload = conn.recv()
            except EOFError:  # the worker died without a word (e.g. failed to start, killed)
                status, payload = "error", "the worker process exited unexpectedly"
            (results if status == "ok" else errors).append(payload)
        if errors:
            raise RuntimeError("racebench vector env worker failed:\n" + errors[0])
        return results

    def _slices(self, values: Sequence[Any]) -> list[Sequence[Any]]:
        return [values[o : o + s] for o, s in zip(self.offsets, self.sizes, strict=True)]

    def _merge_infos(self, parts: list[Any]) -> Any:
        if self.info_format == GYM_INFOS:
            return parts[0] if len(parts) == 1 else concat_infos(parts, self.sizes)
        return [info for part in parts for info in part]

    def reset(self, seeds: list, options: list, mask: np.ndarray | None) -> Any:
        """Reset (the masked) envs; their infos in the front end's format."""
        masks = self._slices(mask) if mask is not None else [None] * len(self.sizes)
        jobs = list(zip(self._slices(seeds), self._slices(options), masks, strict=True))
        for conn, job in zip(self.conns, jobs[1:], strict=True):
            conn.send(("reset", job))
        local = self.local.reset(*jobs[0])
        local = stack_infos(local, len(local)) if self.info_format == GYM_INFOS else local
        return self._merge_infos([local, *self._gather()])

    def step(self, actions: np.ndarray) -> tuple:
        """Step every env: ``(rewards, terminations, truncations, infos)`` (Gymnasium) or
        ``(rewards, dones, (infos, reset_infos))`` (SB3); observations in :attr:`state` / :attr:`depth`."""
        chunks = self._slices(actions)
        for conn, chunk in zip(self.conns, chunks[1:], strict=True):
            conn.send(("step", chunk))
        parts = [_format(self.local.step(chunks[0]), self.info_format), *self._gather()]
        rewards = np.concatenate([p[0] for p in parts])
        if self.info_format == GYM_INFOS:
            terminations = np.concatenate([p[1] for p in parts])
            truncations = np.concatenate([p[2] for p in parts])
            return rewards, terminations, truncations, self._merge_infos([p[3] for p in parts])
        dones = np.concatenate([p[1] for p in parts])
        infos = [info for p in parts for info in p[2][0]]
        reset_infos = {o + i: info for p, o in zip(parts, self.offsets, strict=True) for i, info in p[2][1].items()}
        return rewards, dones, (infos, reset_infos)

    def _per_batch(self, indices: Sequence[int]) -> list[list[int]]:
        return [[i - o for i in indices if o <= i < o + s] for o, s in zip(self.offsets, self.sizes, strict=True)]

    def call(self, name: str, args: tuple, kwargs: dict, indices: Sequence[int], invoke: bool = True) -> list[Any]:
        """Attribute ``name`` of envs ``indices`` (called with the arguments if ``invoke`` and callable)."""
        local = self._per_batch(indices)
        for conn, idx in zip(self.conns, local[1:], strict=True):
            conn.send(("call", (name, args, kwargs, idx, invoke)))
        results = [self.local.call(name, args, kwargs, local[0], invoke), *self._gather()]
        by_index = {}
        for o, idx, values in zip(self.offsets, local, results, strict=True):
            by_index.update({o + i: v for i, v in zip(idx, values, strict=True)})
        return [by_index[i] for i in indices]

    def set_attr(self, name: str, values: Sequence[Any], indices: Sequence[int]) -> None:
        """Set attribute ``name`` of envs ``indices`` to ``values`` (one each)."""
        value_of = dict(zip(indices, values, strict=True))
        local = self._per_batch(indices)
        for conn, o, idx in zip(self.conns, self.offsets[1:], local[1:], strict=True):
            conn.send(("set_attr", (name, [value_of[o + i] for i in idx], idx)))
        self.local.set_attr(name, [value_of[i] for i in local[0]], local[0])
        self._gather()

    def close(self) -> None:
        """Close every env and stop the workers."""
        if self.closed:
            return
        self.closed = True
        if hasattr(self, "local"):
            self.local.close()
        for conn in self.conns:
            try:
                conn.send(("close", None))
            except (BrokenPipeError, OSError):
                pass
        for conn in self.conns:
            try:
                conn.recv()
            except (EOFError, OSError):
                pass
            conn.close()
        for process in self.processes:
            process.join(timeout=5)
            if process.is_alive():
                process.terminate()


def make_backend(
    num_envs: int,
    num_processes: int,
    context: str | None,
    autoreset_mode: AutoresetMode,
    info_format: str,
    env_kwargs: dict[str, Any],
    probe: RaceEnv,
    max_episode_steps: int | None = None,
    teacher: Labeller | None = None,
) -> _Backend:
    """The envs of a front end (shared by :class:`RaceVectorEnv` and :class:`racebench.training.sb3.RaceSB3VecEnv`);
    ``teacher``: see :class:`EnvBatch`."""
    if max_episode_steps is not None and (
        isinstance(max_episode_steps, bool) or not isinstance(max_episode_steps, int) or max_episode_steps < 1
    ):
        raise ValueError(f"max_episode_steps must be a positive int or None, got {max_episode_steps!r}")
    if isinstance(num_envs, bool) or not isinstance(num_envs, int) or num_envs < 1:
        raise ValueError(f"num_envs must be a positive int, got {num_envs!r}")
    if isinstance(num_processes, bool) or not isinstance(num_processes, int) or not 1 <= num_processes <= num_envs:
        raise ValueError(f"num_processes must be an int in [1, num_envs={num_envs}], got {num_processes!r}")
    depth_layout = None
    if probe.obs_mode == "vision":
        space = probe.observation_space["depth"]
        depth_layout = (tuple(space.shape), np.dtype(space.dtype).name)
    kwargs = [dict(env_kwargs) for _ in range(num_envs)]
    return _Backend(
        kwargs, autoreset_mode, info_format, num_processes, context, (STATE_DIM,), depth_layout, max_episode_steps,
        teacher,
    )  # fmt: skip


def probe_env(env_kwargs: dict[str, Any]) -> RaceEnv:
    """One env built in this process for its spaces and settings (and to raise bad kwargs here, early)."""
    return race_env(**env_kwargs)


# ------------------------------------------------------------------ Gymnasium
class RaceVectorEnv(gym.vector.VectorEnv):
    """``num_envs`` racing envs as one Gymnasium vector env, stepped (and, with ``renderer="raycast"``,
    rendered) in batches, in this process or spread over ``num_processes`` processes.

    Equivalent to ``gymnasium.vector.SyncVectorEnv`` over ``RaceEnv(**env_kwargs)`` with the same
    ``autoreset_mode``: same observations, rewards, terminations, truncations and infos (tested).

    Args:
        num_envs: number of envs.
        num_processes: 1 runs every env in this process; k > 1 splits them into k batches, one in this process
            and one in each of k − 1 worker processes (e.g. one process per CPU core), each stepping its envs
            and rendering their depth in one call.
        autoreset_mode: Gymnasium's autoreset mode (``NEXT_STEP``, ``SAME_STEP`` or ``DISABLED``, or its value).
        context: multiprocessing start method for the workers (default ``forkserver`` where available).
        max_episode_steps: truncate after this many steps as ``gym.make``'s ``TimeLimit`` does (``gym.make_vec``
            passes the id's ``spec.max_episode_steps``, which equals the envs' own limit at the default
            ``max_episode_time`` and ``control_freq``); ``None``: the envs' own time limit alone.
        **env_kwargs: ``RaceEnv`` kwargs shared by every env (e.g. ``track``, ``obs_mode``, ``renderer``).
    """

    def __init__(
        self,
        num_envs: int = 1,
        *,
        num_processes: int = 1,
        autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP,
        context: str | None = None,
        max_episode_steps: int | None = None,
        **env_kwargs: Any,
    ) -> None:
        self.autoreset_mode = AutoresetMode(autoreset_mode)
        probe = probe_env(env_kwargs)
        self.num_envs = num_envs
        self.single_observation_space = probe.observation_space
        self.single_action_space = probe.action_space
        self.render_mode = probe.render_mode
        self.metadata = {**probe.metadata, "autoreset_mode": self.autoreset_mode}
        try:
            self._backend = make_backend(
                num_envs, num_processes, context, self.autoreset_mode, GYM_INFOS, env_kwargs, probe, max_episode_steps
            )
        finally:
            probe.close()  # only its spaces and settings are used from here on
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)
        self.vision = self._backend.depth is not None

    @property
    def process_ids(self) -> list[int]:
        """Ids of the processes stepping the envs, this one first."""
        return list(self._backend.pids)

    def _observations(self) -> Any:
        if self.vision:
            return {"state": self._backend.state.copy(), "depth": self._backend.depth.copy()}
        return self._backend.state.copy()

    def reset(
        self, *, seed: int | Sequence[int | None] | None = None, options: dict[str, Any] | None = None
    ) -> tuple[Any, dict[str, Any]]:
        """Reset every env (or those of ``options["reset_mask"]``); ``seed`` int s seeds env i with s + i."""
        super().reset(seed=seed if isinstance(seed, int) else None)
        if seed is None:
            seeds: list[int | None] = [None] * self.num_envs
        elif isinstance(seed, int):
            seeds = [seed + i for i in range(self.num_envs)]
        else:
            seeds = list(seed)
            if len(seeds) != self.num_envs:
                raise ValueError(f"reset: need {self.num_envs} seeds, got {len(seeds)}")
        options = dict(options or {})
        mask = options.pop("reset_mask", None)
        if mask is not None:
            mask = np.asarray(mask)
            if mask.shape != (self.num_envs,) or mask.dtype != np.bool_ or not mask.any():
                raise ValueError(f"reset: options['reset_mask'] must be a bool array of shape ({self.num_envs},)")
        infos = self._backend.reset(seeds, [options or None] * self.num_envs, mask)
        return self._observations(), infos

    def step(self, actions: np.ndarray) -> tuple[Any, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """Step every env with its row of ``actions`` ``(num_envs, 4)``."""
        actions = np.asarray(actions)
        if actions.shape != (self.num_envs, *self.single_action_space.shape):
            raise ValueError(f"actions must have shape {(self.num_envs, 4)}, got {actions.shape}")
        rewards, terminations, truncations, infos = self._backend.step(actions)
        return self._observations(), rewards, terminations, truncations, infos

    def call(self, name: str, *args: Any, **kwargs: Any) -> tuple[Any, ...]:
        """``getattr(env, name)`` of every env, called with the arguments if it is a method."""
        return tuple(self._backend.call(name, args, kwargs, range(self.num_envs)))

    def get_attr(self, name: str) -> tuple[Any, ...]:
        """Attribute ``name`` of every env."""
        return self.call(name)

    def set_attr(self, name: str, values: Any) -> None:
        """Set attribute ``name`` of every env: one value each (list or tuple) or the same value for all."""
        if not isinstance(values, (list, tuple)):
            values = [values] * self.num_envs
        if len(values) != self.num_envs:
            raise ValueError(f"set_attr: need {self.num_envs} values, got {len(values)}")
        self._backend.set_attr(name, values, range(self.num_envs))

    def render(self) -> tuple[Any, ...] | None:
        """Each env's ``render()`` (``render_mode="rgb_array"``: chase-camera frames)."""
        return self.call("render")

    def close_extras(self, **kwargs: Any) -> None:
        """Close the envs and stop the worker processes."""
        self._backend.close()
