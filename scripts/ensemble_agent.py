"""An output ensemble of SB3 policies: the mean of their deterministic actions (experiment, issue 12).

Weight-averaging a DAgger run's last students lifted its success rate (docs/teacher-student.md, "Which students
to keep"); this asks whether averaging their *actions* does more, and whether students of different runs, whose
failed laps only partly coincide, cover for each other. Used through the common evaluator::

    racebench evaluate --agent scripts/ensemble_agent.py:EnsembleAgent --trust-code \\
        --agent-kwargs '{"checkpoints": ["a.zip", "b.zip"], "sha256": ["<sha256 of a.zip>", "<of b.zip>"]}' ...

Each member is pinned by its file's sha256: a Python agent's records are keyed to its source and its kwargs, so the
digests in the kwargs make that key name the exact member policies (a member whose bytes differ is refused).
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

import numpy as np

from racebench.agents import AgentLoadError, SB3Agent


class EnsembleAgent:
    """The mean deterministic action of several SB3 checkpoints, each with its own recurrent state.

    Every member sees the same observation; in lockstep evaluation each runs its own batched forward pass.
    """

    privileged = False

    def __init__(self, checkpoints: list[str], sha256: list[str], name: str = "ensemble") -> None:
        if not checkpoints:
            raise AgentLoadError("EnsembleAgent: checkpoints is empty")
        if len(sha256) != len(checkpoints):
            raise AgentLoadError(f"EnsembleAgent: {len(checkpoints)} checkpoints but {len(sha256)} sha256 digests")
        self.members: list[SB3Agent] = []
        for path, expected in zip(checkpoints, sha256, strict=True):
            if not Path(path).is_file():
                raise AgentLoadError(f"EnsembleAgent: member {path!r} does not exist")
            digest = hashlib.sha256(Path(path).read_bytes()).hexdigest()
            if digest != expected:
                raise AgentLoadError(
                    f"EnsembleAgent: member {path!r} has sha256 {digest[:12]}, expected {expected[:12]}"
                )
            # Loading a member unpickles it; the ensemble itself only runs under --trust-code (a Python agent).
            self.members.append(SB3Agent(path, trust_code=True))
        modes = {member.obs_mode for member in self.members}
        if len(modes) != 1:
            raise AgentLoadError(f"EnsembleAgent: members expect different observations {sorted(modes)}")
        self.obs_mode = modes.pop()
        self.name = name

    def reset(self, env: Any = None, seed: int | None = None) -> None:
        """Clear every member's recurrent state."""
        for member in self.members:
            member.reset(env, seed)

    def act(self, obs: Any) -> np.ndarray:
        """The mean of the members' deterministic actions for one observation."""
        return np.mean([np.asarray(member.act(obs), dtype=np.float64).reshape(-1) for member in self.members], axis=0)

    def start(self, slots: int) -> None:
        """Prepare ``slots`` lockstep episodes in every member."""
        for member in self.members:
            member.start(slots)

    def reset_slot(self, slot: int) -> None:
        """A new episode in ``slot``: every member clears that slot's state."""
        for member in self.members:
            member.reset_slot(slot)

    def act_batch(self, observations: list[Any]) -> np.ndarray:
        """The mean of the members' batched deterministic actions, ``(slots, 4)``."""
        return np.mean([member.act_batch(observations) for member in self.members], axis=0)


def main() -> None:
    """Print the ``--agent-kwargs`` JSON that pins the given checkpoints (``python scripts/ensemble_agent.py a.zip
    b.zip ...``)."""
    import argparse
    import json

    parser = argparse.ArgumentParser(description=main.__doc__)
    parser.add_argument("checkpoints", nargs="+", help="SB3 checkpoints (.zip), the ensemble's members")
    args = parser.parse_args()
    digests = [hashlib.sha256(Path(path).read_bytes()).hexdigest() for path in args.checkpoints]
    print(json.dumps({"checkpoints": args.checkpoints, "sha256": digests}))


if __name__ == "__main__":
    main()
