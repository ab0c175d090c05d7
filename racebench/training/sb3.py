"""Stable-Baselines3 front end of the batched racing envs: :class:`RaceSB3VecEnv` and :func:`make_sb3_vec_env`.

Kept apart from :mod:`racebench.envs.vector` so that its worker processes never import SB3 (and torch).
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode
from stable_baselines3.common.vec_env import VecMonitor
from stable_baselines3.common.vec_env.base_vec_env import VecEnv, VecEnvIndices, VecEnvStepReturn

from racebench.agents.planner import FastPlannerAgent
from racebench.envs.vector import SB3_INFOS, Labeller, make_backend, probe_env


def teacher_factory(teacher: dict[str, Any] | None) -> Labeller | None:
    """The labeller factory the envs call once each (:class:`~racebench.envs.vector.EnvBatch`): a
    :class:`~racebench.agents.planner.FastPlannerAgent` built with the kwargs ``teacher`` (``None``: no teacher)."""
    return None if teacher is None else functools.partial(FastPlannerAgent, **teacher)


class RaceSB3VecEnv(VecEnv):
    """``num_envs`` racing envs as one SB3 ``VecEnv``, batched like :class:`~racebench.envs.vector.RaceVectorEnv`.

    Equivalent to SB3's ``DummyVecEnv`` over ``RaceEnv(**env_kwargs)`` (tested): same-step autoreset,
    ``infos[i]["terminal_observation"]`` and ``["TimeLimit.truncated"]``, reset infos in ``reset_infos``,
    seeds from :meth:`seed` (env i gets ``seed + i``) used at the next :meth:`reset`.

    Args:
        num_envs: number of envs.
        num_processes: 1 (every env in this process) or k > 1 (this process and k − 1 worker processes).
        context: multiprocessing start method for the workers (default ``forkserver`` where available).
        max_episode_steps: also truncate after this many steps, as the ``TimeLimit`` around ``gym.make``'s envs
            does (``None``: the envs' own time limit alone).
        teacher: for training only: ``FastPlannerAgent`` kwargs of a privileged teacher that labels each returned
            observation, in ``infos[i]["teacher_action"]`` (on an episode's end: the new episode's first
            observation's label; see :class:`~racebench.envs.vector.EnvBatch`). ``None``: no labels. The envs get
            the planner as a factory (:func:`teacher_factory`).
        **env_kwargs: ``RaceEnv`` kwargs shared by every env.
    """

    def __init__(
        self,
        num_envs: int,
        *,
        num_processes: int = 1,
        context: str | None = None,
        max_episode_steps: int | None = None,
        teacher: dict[str, Any] | None = None,
        **env_kwargs: Any,
    ) -> None:
        probe = probe_env(env_kwargs)
        try:
            mode = AutoresetMode.SAME_STEP
            self._backend = make_backend(
                num_envs,
                num_processes,
                context,
                mode,
                SB3_INFOS,
                env_kwargs,
                probe,
                max_episode_steps,
                teacher_factory(teacher),
            )
        finally:
            probe.close()  # only its spaces and settings are used from here on
        self.vision = self._backend.depth is not None
        self._actions: np.ndarray | None = None
        super().__init__(num_envs, probe.observation_space, probe.action_space)

    @property
    def process_ids(self) -> list[int]:
        """Ids of the processes stepping the envs, this one first."""
        return list(self._backend.pids)

    def _observations(self) -> Any:
        if self.vision:  # in the observation space's key order, like DummyVecEnv
            arrays = {"state": self._backend.state, "depth": self._backend.depth}
            return {key: arrays[key].copy() for key in self.observation_space.spaces}
        return self._backend.state.copy()

    def reset(self) -> Any:
        """Reset every env with the seeds of :meth:`seed` and options of ``set_options`` (then forgotten)."""
        infos = self._backend.reset(list(self._seeds), [dict(o) for o in self._options], None)
        self.reset_infos = infos
        self._reset_seeds()
        self._reset_options()
        return self._observations()

    def step_async(self, actions: np.ndarray) -> None:
        """Remember the actions for :meth:`step_wait`."""
        self._actions = np.asarray(actions)

    def step_wait(self) -> VecEnvStepReturn:
        """Step every env; those that end are reset at once (their last observation in the info)."""
        rewards, dones, (infos, reset_infos) = self._backend.step(self._actions)
        for i, info in reset_infos.items():
            self.reset_infos[i] = info
        return self._observations(), rewards, dones, infos

    def close(self) -> None:
        """Close the envs and stop the worker processes."""
        self._backend.close()

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        """Attribute ``attr_name`` of the envs ``indices`` (default all)."""
        return self._backend.call(attr_name, (), {}, self._get_indices(indices), invoke=False)

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        """Set attribute ``attr_name`` of the envs ``indices`` (default all) to ``value``."""
        idx = list(self._get_indices(indices))
        self._backend.set_attr(attr_name, [value] * len(idx), idx)

    def env_method(
        self, method_name: str, *method_args: Any, indices: VecEnvIndices = None, **method_kwargs: Any
    ) -> list:
        """Call ``method_name`` of the envs ``indices`` (default all)."""
        return self._backend.call(method_name, method_args, method_kwargs, self._get_indices(indices))

    def env_is_wrapped(self, wrapper_class: type[gym.Wrapper], indices: VecEnvIndices = None) -> list[bool]:
        """Always ``False``: the envs are bare ``RaceEnv`` instances."""
        return [False for _ in self._get_indices(indices)]

    def get_images(self) -> Sequence[np.ndarray | None]:
        """Each env's ``render()`` frame (``render_mode="rgb_array"``)."""
        return self.env_method("render")


def make_sb3_vec_env(
    env_id: str, n_envs: int = 1, seed: int | None = None, num_processes: int = 1, monitor: bool = True, **kwargs: Any
) -> VecEnv:
    """SB3's ``make_vec_env`` for a registered id, batched: a :class:`RaceSB3VecEnv` (the id's kwargs updated
    by ``kwargs``, its ``spec.max_episode_steps`` unless ``kwargs`` sets ``max_episode_steps``, as ``gym.make``
    does), env i seeded ``seed + i`` at the first reset, wrapped in ``VecMonitor`` (episode returns and lengths
    in ``info["episode"]``, as ``make_vec_env``'s ``Monitor``) unless ``monitor=False``."""
    spec = gym.spec(env_id)
    kwargs = {"max_episode_steps": spec.max_episode_steps, **spec.kwargs, **kwargs}
    venv: VecEnv = RaceSB3VecEnv(n_envs, num_processes=num_processes, **kwargs)
    if seed is not None:
        venv.seed(seed)
    return VecMonitor(venv) if monitor else venv
