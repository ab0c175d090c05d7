"""The built-in agents that need no planning: random, hover and the privileged gate follower.

(The planners, ``planner`` and ``planner-fast``, are in :mod:`racebench.agents.planner`.)
"""

from __future__ import annotations

from typing import Any

import numpy as np

from racebench.agents.control import GateFollower
from racebench.sim.quadrotor import QuadrotorParams


class RandomAgent:
    """Uniform random actions, seeded per episode so a sweep is reproducible."""

    name = "random"
    obs_mode = "state"
    privileged = False

    def __init__(self) -> None:
        self.rng = np.random.default_rng(0)

    def reset(self, env: Any = None, seed: int | None = None) -> None:
        """Reseed from the episode seed."""
        self.rng = np.random.default_rng(seed)

    def act(self, obs: Any) -> np.ndarray:
        """A uniform sample of ``[-1, 1]^4``."""
        return self.rng.uniform(-1.0, 1.0, size=4).astype(np.float32)


class HoverAgent:
    """Hover thrust, zero body rates: the do-nothing baseline."""

    name = "hover"
    obs_mode = "state"
    privileged = False

    def __init__(self, params: QuadrotorParams | None = None) -> None:
        self.action = np.array([(params or QuadrotorParams()).hover_action, 0.0, 0.0, 0.0], dtype=np.float32)

    def reset(self, env: Any = None, seed: int | None = None) -> None:
        """Nothing to reset."""

    def act(self, obs: Any) -> np.ndarray:
        """The hover action."""
        return self.action


class FollowAgent:
    """Privileged gate-axis follower (:class:`~racebench.agents.control.GateFollower`); it ignores obstacles."""

    name = "follow"
    obs_mode = "state"
    privileged = True

    def __init__(self) -> None:
        self.follower = GateFollower()
        self.env = None

    def reset(self, env: Any = None, seed: int | None = None) -> None:
        """Keep the unwrapped env to read the true state from."""
        if env is None:
            raise ValueError("FollowAgent is privileged: reset() needs the unwrapped RaceEnv")
        self.env = env

    def act(self, obs: Any) -> np.ndarray:
        """Fly along the next gate's axis."""
        return self.follower.act_privileged(self.env)
