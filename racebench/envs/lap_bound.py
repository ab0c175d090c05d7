"""A lower bound on the lap time of a track: no flight within the airframe's thrust finishes a lap faster.

Record validation (:func:`racebench.evaluation.records.validate_record`) rejects a success claiming a lap below it, so a
forged lap that is consistent with its step count still cannot be physically impossible.

**Model.** The drone is a point mass that starts at rest (every evaluation episode does) and is pushed by a thrust of
at most ``T_max`` in any direction (the real one points along the body axis; any direction only helps), plus
gravity. Attitude dynamics, motor lag, body-rate limits, PyBullet's damping and the drag's braking are left out:
each can only slow the drone. Left out too is the small lift a quadratic body drag gives while braking steeply,
which no airframe can fly at full thrust forwards at the same time; the committed records stay far above the bound
(``tests/test_lap_bound.py`` checks every one).

**Geometry.** The path must go from the start box through every gate's opening, in order. Each opening's
horizontal footprint (widened by the env's random gate shift) lies in an axis-aligned rectangle, so the
horizontal length ``L`` of any lap is at least the sum of the distances between consecutive rectangles. The lap
ends inside the last opening, so it ends at most ``drop`` below the highest start (:func:`lap_geometry`).

**Time.** With thrust ``u(t)``, ``|u| ≤ a = T_max / m``, starting at rest, the horizontal distance flown by time
``T`` is at most ``∫ (T − t) |u_h| dt`` and the height gained is ``∫ (T − t) (u_z − g) dt ≥ −drop``. Over the
weights ``T − t`` (total ``T²/2``), Jensen's inequality on the concave ``√(a² − u_z²)`` gives

    L ≤ T²/2 · √(a² − max(0, g − 2·drop/T²)²),

whose least solution is :func:`min_time_from_rest` (closed form). Example: on level ground (``drop = 0``) it is
``√(2L / √(a² − g²))``, the time of a point mass that holds its height and accelerates horizontally at full tilt.
PyBullet integrates semi-implicitly (velocity first), which moves the drone as the continuous system would in half
a physics step more, so the bound of an env is the continuous one less ``1 / (2 physics_freq)``.
"""

from __future__ import annotations

import dataclasses
import functools
import inspect
import math

import numpy as np

from racebench.envs.env import RaceEnv
from racebench.envs.registration import ENV_KWARGS
from racebench.sim.quadrotor import QuadrotorParams
from racebench.sim.track import Gate, Track, load_track


def min_time_from_rest(horizontal: float, drop: float, thrust_accel: float, gravity: float) -> float:
    """Least time (s) for a point mass at rest to fly ``horizontal`` m sideways ending at most ``drop`` m lower.

    ``thrust_accel`` (m/s², > ``gravity``) bounds the non-gravitational acceleration in any direction; a negative
    ``drop`` is a climb. See the module docstring for the derivation.
    """
    if horizontal < 0 or not thrust_accel > gravity > 0:
        raise ValueError(f"need horizontal >= 0 and thrust_accel > gravity > 0, got {horizontal}, {thrust_accel}, "
                         f"{gravity}")  # fmt: skip
    a2, g = thrust_accel**2, gravity
    # Falling with every bit of thrust horizontal: T² = 2L/a while gravity alone can pay for the drop by then.
    free = 2.0 * horizontal / thrust_accel
    if drop > 0 and g * free <= 2.0 * drop:
        return math.sqrt(free)
    # Otherwise x = T² solves (a² − g²) x² − 4 g·(−drop) x − 4 (drop² + L²) = 0, i.e. a² T⁴ = (g T² − 2 drop)² + 4 L².
    rise = -drop
    root = math.sqrt(g * g * rise * rise + (a2 - g * g) * (rise * rise + horizontal * horizontal))
    x = 2.0 * (g * rise + root) / (a2 - g * g)
    return math.sqrt(max(x, 0.0))


def _opening_rectangle(gate: Gate, shift_xy: float) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned (low, high) x-y corners holding every point of ``gate``'s opening, shifted by up to ``shift_xy``."""
    # The opening's horizontal footprint is the segment centre ± inner/2 · lateral; its bounding box, widened.
    half = gate.inner / 2.0 * np.abs(gate.lateral[:2]) + shift_xy
    return gate.center[:2] - half, gate.center[:2] + half


def _rectangle_gap(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray]) -> float:
    """Euclidean distance between two axis-aligned rectangles (0 when they overlap)."""
    gap = np.maximum(0.0, np.maximum(b[0] - a[1], a[0] - b[1]))
    return float(np.linalg.norm(gap))


def lap_geometry(track: Track, gate_shift: float = 0.0, gate_shift_z: float | None = None) -> tuple[float, float]:
    """``(L, drop)``: a lower bound on any lap's horizontal length (m) and an upper bound on its net descent (m).

    ``gate_shift`` / ``gate_shift_z`` are the env's ranges of random gate displacement (as in ``RaceEnv``).
    """
    shift_z = gate_shift if gate_shift_z is None else gate_shift_z
    start = track.start
    regions = [(start.center[:2] - start.spread[:2], start.center[:2] + start.spread[:2])]
    regions += [_opening_rectangle(g, gate_shift) for g in track.gates]
    length = sum(_rectangle_gap(a, b) for a, b in zip(regions, regions[1:], strict=False))
    last = track.gates[-1]
    lowest_end = max(0.0, float(last.center[2]) - shift_z - last.inner / 2.0)  # below z = 0 is out of bounds
    highest_start = float(start.center[2] + start.spread[2])
    return length, highest_start - lowest_end


def lap_time_lower_bound(
    track: Track,
    params: QuadrotorParams | None = None,
    gate_shift: float = 0.0,
    gate_shift_z: float | None = None,
    physics_freq: int = 200,
) -> float:
    """Lap time (s) below which no lap of ``track`` can be flown by the airframe ``params`` (module docstring)."""
    params = params or QuadrotorParams()
    length, drop = lap_geometry(track, gate_shift, gate_shift_z)
    bound = min_time_from_rest(length, drop, params.max_thrust / params.mass, params.gravity)
    return max(0.0, bound - 0.5 / physics_freq)


@functools.cache
def env_lap_time_bound(env_id: str) -> float:
    """:func:`lap_time_lower_bound` of a registered env id, from its ``RaceEnv`` kwargs (cached per process, which
    holds one env version)."""
    if env_id not in ENV_KWARGS:
        raise ValueError(f"env_id {env_id!r} is not a racebench id")
    defaults = {k: p.default for k, p in inspect.signature(RaceEnv.__init__).parameters.items()}
    kwargs = {**defaults, **ENV_KWARGS[env_id]}
    track = load_track(kwargs["track"])
    if kwargs["start_spread"] is not None:
        spread = np.asarray(kwargs["start_spread"], dtype=float)
        track = dataclasses.replace(track, start=dataclasses.replace(track.start, spread=spread))
    quad = kwargs["quadrotor"]
    params = quad if isinstance(quad, QuadrotorParams) else QuadrotorParams(**(quad or {}))
    return lap_time_lower_bound(track, params, kwargs["gate_shift"], kwargs["gate_shift_z"], kwargs["physics_freq"])
