"""The agent protocol, the built-in agents' registry (names, privilege, code versions) and the load errors.

Light on purpose: the command line reads the registry for its help.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import numpy as np
from gymnasium import spaces

if TYPE_CHECKING:
    pass


#: The built-in agents, by spec name: the one registry the loader, the policy identities and the command line's
#: help read. (This module imports nothing heavy at import time, so the command line can read it for its help.)
BUILTIN_AGENTS: tuple[str, ...] = ("random", "hover", "planner", "planner-fast", "follow")
#: Which built-in agents read the true scene and state. Only these are ever privileged.
BUILTIN_PRIVILEGED: dict[str, bool] = {
    "random": False,
    "hover": False,
    "planner": True,
    "planner-fast": True,
    "follow": True,
}
#: Code version of each built-in agent, part of its policy hash: bump it when the agent's behaviour changes.
#: planner-fast v2: compiled clearance queries in its path smoothing, ~2x faster planning; its paths differ from
#: v1's in the last bits (≤ 1e-13 m), which a closed loop may amplify, so its records were flown anew.
#: planner-fast v3: speed profile under a thrust budget (gravity and drag included) with jerk-limited braking
#: onsets, instead of v2's 10 m/s² friction circle; ``FastPlannerAgent(thrust_accel=None, braking_jerk=None)``
#: is v2.
BUILTIN_VERSIONS: dict[str, int] = {"random": 1, "hover": 1, "planner": 1, "planner-fast": 3, "follow": 1}


class AgentLoadError(ValueError):
    """An agent spec could not be turned into an agent; the message names the spec and the reason."""


class UntrustedCodeError(AgentLoadError):
    """Loading the agent would run code from an untrusted file and ``trust_code`` was not given."""


@runtime_checkable
class Agent(Protocol):
    """What the evaluator needs from an agent."""

    name: str
    obs_mode: str  # "vision" or "state": the observation the agent expects
    privileged: bool  # True: reset() receives the unwrapped env and the agent may read the true state

    def reset(self, env: Any = None, seed: int | None = None) -> None:
        """Start of an episode (``env`` is given to privileged agents only; ``seed`` is the episode's)."""

    def act(self, obs: Any) -> np.ndarray:
        """A CTBR action in ``[-1, 1]^4`` for one observation."""


def obs_mode_of(space: Any) -> str:
    """``"vision"`` or ``"state"``: which of racebench's observations a policy's observation space is."""
    if isinstance(space, spaces.Dict) and "depth" in space.spaces:
        return "vision"
    if isinstance(space, spaces.Box) and space.shape == (17,):
        return "state"
    raise AgentLoadError(f"policy observation space {space} is neither racebench's vision Dict nor its 17-d state")
