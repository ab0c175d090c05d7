"""The observations of :class:`~racebench.envs.env.RaceEnv`: the 17-float state (its scales, bounds and compiled
kernel) and the depth image's spaces and uint8 form.
"""

from __future__ import annotations

import numpy as np
from gymnasium import spaces
from numba import njit

#: ``"float32"``: depth (1, 64, 64) in [0, 1], the paper's and the default; ``"uint8"``: the same image as
#: (64, 64, 1) uint8 in [0, 255], the layout and dtype stable-baselines3 recognises as an image (NatureCNN).
DEPTH_FORMATS: tuple[str, ...] = ("float32", "uint8")
STATE_DIM = 17
POSITION_SCALE = 10.0  # m per unit
VELOCITY_SCALE = 10.0  # m/s per unit
STATE_LIMIT = 5.0  # |state| is clipped here: 50 m, 50 m/s, 5x the max body rate


def depth_to_uint8(depth: np.ndarray) -> np.ndarray:
    """Float depth ``(..., 1, H, W)`` in [0, 1] → ``(..., H, W, 1)`` uint8 in [0, 255], rounded to nearest.

    The ``depth_format="uint8"`` observation is exactly this function of the float one (same noise draws), so
    a policy trained on uint8 depth can be flown on the float envs by converting
    (:class:`racebench.agents.loading.SB3Agent`
    does), with identical inputs.
    """
    scaled = np.asarray(depth, dtype=np.float32) * np.float32(255.0) + np.float32(0.5)
    return np.ascontiguousarray(np.moveaxis(scaled.astype(np.uint8), -3, -1))


def depth_space(size: int, depth_format: str = "float32") -> spaces.Box:
    """The ``depth`` observation space of a ``size``×``size`` camera in ``depth_format`` (see DEPTH_FORMATS)."""
    if depth_format == "uint8":
        return spaces.Box(0, 255, shape=(size, size, 1), dtype=np.uint8)
    return spaces.Box(0.0, 1.0, shape=(1, size, size), dtype=np.float32)


def state_space() -> spaces.Box:
    """Bounds of the 17-float state observation (quaternion within ±1, everything else within ±5)."""
    high = np.full(STATE_DIM, STATE_LIMIT, dtype=np.float32)
    high[10:14] = 1.0
    return spaces.Box(-high, high, dtype=np.float32)


@njit(cache=True, error_model="numpy")  # numpy's division semantics (x / 0 = inf), as the array version had
def _state_kernel(
    pos: np.ndarray,
    quat: np.ndarray,
    rot: np.ndarray,
    vel: np.ndarray,
    ang: np.ndarray,
    gate1: np.ndarray,
    gate2: np.ndarray,
    desired_speed: float,
    rate_scale: np.ndarray,
    low: np.ndarray,
    high: np.ndarray,
    out: np.ndarray,
) -> None:
    """The 17 state features (see :class:`RaceEnv`), clipped to ``[low, high]``, into ``out`` (float32).

    Compiled: it runs at every step, and numpy's per-call overhead on 3-vectors is most of its cost.
    """
    state = np.empty(STATE_DIM)
    for a in range(3):  # Rᵀ v: body-frame components
        state[a] = (
            rot[0, a] * (gate1[0] - pos[0]) + rot[1, a] * (gate1[1] - pos[1]) + rot[2, a] * (gate1[2] - pos[2])
        ) / POSITION_SCALE
        state[3 + a] = (
            rot[0, a] * (gate2[0] - pos[0]) + rot[1, a] * (gate2[1] - pos[1]) + rot[2, a] * (gate2[2] - pos[2])
        ) / POSITION_SCALE
        state[6 + a] = (rot[0, a] * vel[0] + rot[1, a] * vel[1] + rot[2, a] * vel[2]) / VELOCITY_SCALE
        state[14 + a] = (rot[0, a] * ang[0] + rot[1, a] * ang[1] + rot[2, a] * ang[2]) / rate_scale[a]
    state[9] = desired_speed / VELOCITY_SCALE
    sign = 1.0 if quat[3] >= 0 else -1.0  # q and −q are the same attitude: keep w >= 0
    for a in range(4):
        state[10 + a] = sign * quat[a]
    for a in range(STATE_DIM):
        v = state[a]  # clipped as np.clip does (a NaN stays NaN)
        if v < low[a]:
            v = low[a]
        elif v > high[a]:
            v = high[a]
        out[a] = v
