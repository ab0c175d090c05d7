"""The paper's seven-term racing reward (Sec. III-B.3, weights from Table I).

``R_t = r_prog + r_theta + r_cmd + r_vd + r_avoid + r_pass + r_crash`` with

* ``r_prog  = λ1 (d_{t-1} − d_t)``, ``d`` = distance to the centre of the gate targeted at the step start;
* ``r_theta = λ2 exp(−|θ_t − θ_gate|)``, drone yaw vs. bearing to the next gate in the x-y plane
  (angle difference wrapped to [−π, π]);
* ``r_cmd   = λ3 ‖u_t‖ + λ4 ‖u_t − u_{t−1}‖``;
* ``r_vd    = λ5 max(0, ‖v_t‖ − v_d)``: the paper's text says this term "penalizes high speed that
  exceeds the desired velocity"; its printed formula ``λ5 (‖v‖ − v_d)`` would instead pay the agent
  for hovering below v_d, so the excess is clipped at zero;
* ``r_avoid = λ6 / (d_col + b)``, ``d_col`` = distance from the drone's collision sphere to the nearest
  gate bar or obstacle surface, ``b`` a small offset;
* ``r_pass  = λ7`` on passing the next gate; ``r_crash = λ8`` on any collision or leaving the arena.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, fields, replace
from typing import Any

from racebench.utils.angles import wrap_angle as wrap_angle  # re-exported: racebench.envs.reward.wrap_angle

REWARD_TERMS: tuple[str, ...] = ("prog", "theta", "cmd", "vd", "avoid", "pass", "crash")


@dataclass(frozen=True)
class RewardWeights:
    """Reward weights λ1..λ8 (paper Table I defaults) and the avoidance offset ``b``."""

    progress: float = 0.9  # λ1
    heading: float = 0.05  # λ2
    command: float = -0.005  # λ3
    command_rate: float = -0.0025  # λ4
    speed: float = -0.05  # λ5, set 0 to remove r_vd (curriculum level 3)
    avoid: float = -0.01  # λ6, set 0 for the "w/o r_avoid" ablation
    passing: float = 5.0  # λ7
    crash: float = -4.0  # λ8
    avoid_offset: float = 0.1  # b, m

    @classmethod
    def from_overrides(cls, overrides: dict[str, Any] | RewardWeights | None) -> RewardWeights:
        """Defaults updated by a dict of overrides; an unknown name raises ``ValueError`` naming it."""
        if overrides is None:
            return cls()
        if isinstance(overrides, RewardWeights):
            return overrides
        if not isinstance(overrides, dict):
            raise ValueError(f"reward_weights must be a dict or RewardWeights, got {type(overrides).__name__}")
        names = {f.name for f in fields(cls)}
        for key, value in overrides.items():
            if key not in names:
                raise ValueError(f"reward_weights: unknown weight {key!r} (known: {sorted(names)})")
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ValueError(f"reward_weights[{key!r}] must be a finite number, got {value!r}")
        weights = replace(cls(), **{k: float(v) for k, v in overrides.items()})
        if weights.avoid_offset <= 0:
            raise ValueError(f"reward_weights['avoid_offset'] must be > 0, got {weights.avoid_offset}")
        return weights

    def to_dict(self) -> dict[str, float]:
        """Plain-data form."""
        return asdict(self)


def reward_terms(
    weights: RewardWeights,
    *,
    prev_gate_distance: float,
    gate_distance: float,
    yaw: float,
    bearing_to_gate: float,
    action: Sequence[float],
    prev_action: Sequence[float],
    speed: float,
    desired_speed: float,
    collision_distance: float,
    passed_gate: bool,
    crashed: bool,
) -> dict[str, float]:
    """Each of the seven reward terms for one step; their sum is the step reward.

    Plain Python floats throughout (``math.hypot`` for the norms): this runs at every env step, where
    numpy's per-call overhead on 4-vectors costs more than the arithmetic.
    """
    return {
        "prog": weights.progress * (prev_gate_distance - gate_distance),
        "theta": weights.heading * math.exp(-abs(wrap_angle(yaw - bearing_to_gate))),
        "cmd": weights.command * math.hypot(*action)
        + weights.command_rate * math.hypot(*(a - b for a, b in zip(action, prev_action, strict=True))),
        "vd": weights.speed * max(0.0, speed - desired_speed),
        "avoid": weights.avoid / (max(collision_distance, 0.0) + weights.avoid_offset),
        "pass": weights.passing if passed_gate else 0.0,
        "crash": weights.crash if crashed else 0.0,
    }
