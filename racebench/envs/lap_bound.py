"""A lower bound on the lap time of a track: no flight within the airframe's thrust finishes a lap faster.

Record validation (:func:`racebench.evaluation.records.validate_record`) rejects a success claiming a lap below it, so a
forged lap that is consistent with its step count still cannot be physically impossible. The derivation is in
``docs/evaluation.md`` ("The lap-time lower bound"); in short:

**What it assumes (first principles only).** Every evaluation episode starts at rest, in the track's start box. The
forces on the drone are gravity, a thrust of at most ``T_max`` (in any direction: the real one points along the body
axis; any direction only helps) and a drag that never adds energy (``f·v ≤ 0``: the quadratic body-axis drag of
:mod:`racebench.sim.quadrotor`, whatever the attitude). Nothing else is assumed: not the attitude dynamics, the motor
lag, the rate limits or the controller, and not the obstacles (a lap through any obstacle layout is at least as long as
the straight one), so the bound holds for every obstacle layout and every policy. A successful lap never touches the
ground, so the drone never falls more than ``H`` (the highest start above the ground).

**Geometry.** The lap goes from the start box through every gate's opening, in order. Each opening, shifted anywhere
within the env's gate-shift ranges, lies in an axis-aligned box, so any lap's path is at least ``L``, the sum of the
straight-line distances between consecutive boxes (:func:`lap_geometry`).

**Energy.** With ``a = T_max / m``, the kinetic energy per unit mass grows at most by the thrust's work and the height
lost: ``½|v|² ≤ a·s + g·H`` after a path ``s``. So ``ds/dt = |v| ≤ √(2 a s + 2 g H)``, and from rest
``s(T) ≤ √(2 g H)·T + a T²/2``: no lap is shorter than the ``T`` at which this reaches ``L``
(:func:`min_time_from_rest`, closed form). The drag's lift (a drone gliding on its body drag while it thrusts forwards)
is inside the bound: the energy argument never asks which way a force points, only that drag does no positive work.

**Physics ticks.** PyBullet integrates semi-implicitly (velocity first, then position), with the drag of the velocity
before the tick. The same argument on those update rules gives, exactly, ``|v_{n+1}|² ≤ 2 a s_n + 2 g H +
(n + 1) dt² (a² − g²)`` and ``s_{n+1} = s_n + dt |v_{n+1}|``, while ``dt·k·|v|/m ≤ 2`` on each body axis (the drag
of one tick cannot reverse a velocity component; checked, see :func:`min_ticks_from_rest`). The env's bound is the
least number of ticks after which this recursion covers ``L``, times ``dt``: a lap stamped below it cannot be flown in
the simulator, and a lap of exactly that many ticks is not refused.
"""

from __future__ import annotations

import dataclasses
import functools
import inspect
import math

import numpy as np

from racebench.envs.env import RaceEnv
from racebench.envs.registration import ENV_KWARGS
from racebench.sim.disturbances import DrydenWind
from racebench.sim.quadrotor import QuadrotorParams
from racebench.sim.track import Gate, Track, load_track
from racebench.sim.track_generator import START_SPREAD, TRACK_SOURCES, shortest_lap


def _check(length: float, height: float, thrust_accel: float, gravity: float) -> None:
    if length < 0 or height < 0 or not thrust_accel > gravity > 0:
        raise ValueError(f"need length >= 0, height >= 0 and thrust_accel > gravity > 0, got {length}, {height}, "
                         f"{thrust_accel}, {gravity}")  # fmt: skip


def min_time_from_rest(length: float, height: float, thrust_accel: float, gravity: float) -> float:
    """Least time (s) for a mass at rest to fly a path of ``length`` m, never more than ``height`` m below its start.

    ``thrust_accel`` (m/s², > ``gravity``) bounds the thrust's acceleration in any direction; every other force but
    gravity does no positive work. Continuous time: the root of ``length = √(2 g H)·T + a T²/2``.
    """
    _check(length, height, thrust_accel, gravity)
    fall = math.sqrt(2.0 * gravity * height)
    return (math.sqrt(fall * fall + 2.0 * thrust_accel * length) - fall) / thrust_accel


def min_ticks_from_rest(
    length: float, height: float, thrust_accel: float, gravity: float, dt: float, drag_per_mass: float = 0.0
) -> int:
    """Least number of physics ticks of length ``dt`` (semi-implicit Euler) in which a mass at rest flies a path of
    ``length`` m, never more than ``height`` m below its start (:func:`min_time_from_rest` tick by tick).

    ``drag_per_mass`` (1/m) is the largest body-axis drag coefficient over the mass: the per-tick argument needs the
    drag of one tick not to reverse a velocity component (``dt·drag_per_mass·|v| ≤ 2``). Should the speed bound ever
    pass that limit before ``length`` is covered, the ticks proven so far are returned (a weaker bound, still a bound).
    """
    _check(length, height, thrust_accel, gravity)
    if dt <= 0 or drag_per_mass < 0:
        raise ValueError(f"need dt > 0 and drag_per_mass >= 0, got {dt}, {drag_per_mass}")
    a, g = thrust_accel, gravity
    top_speed = math.inf if drag_per_mass == 0 else 2.0 / (dt * drag_per_mass)
    path, speed_sq, ticks = 0.0, 0.0, 0  # bounds on s_n and |v_n|², after n ticks
    while path < length:
        if math.sqrt(speed_sq) > top_speed:
            return ticks + 1  # s_n <= path < length: the lap is not done after n ticks
        ticks += 1
        speed_sq = 2.0 * a * path + 2.0 * g * height + ticks * dt * dt * (a * a - g * g)
        path += dt * math.sqrt(speed_sq)
    return ticks


def _opening_box(gate: Gate, shift_xy: float, shift_z: float) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned (low, high) corners holding every point of ``gate``'s opening, shifted by up to the given ranges."""
    # The opening is the square centre ± inner/2 · lateral ± inner/2 · z; its bounding box, widened by the shift.
    half_xy = gate.inner / 2.0 * np.abs(gate.lateral[:2]) + shift_xy
    half = np.array([half_xy[0], half_xy[1], gate.inner / 2.0 + shift_z])
    return gate.center - half, gate.center + half


def _box_gap(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray]) -> float:
    """Euclidean distance between two axis-aligned boxes (0 when they overlap)."""
    gap = np.maximum(0.0, np.maximum(b[0] - a[1], a[0] - b[1]))
    return float(np.linalg.norm(gap))


def lap_geometry(track: Track, gate_shift: float = 0.0, gate_shift_z: float | None = None) -> tuple[float, float]:
    """``(L, H)``: a lower bound on any lap's path length (m) and an upper bound on how far below its start the drone
    can ever be (m: the highest start above the ground, which a successful lap never touches).

    ``gate_shift`` / ``gate_shift_z`` are the env's ranges of random gate displacement (as in ``RaceEnv``).
    """
    shift_z = gate_shift if gate_shift_z is None else gate_shift_z
    start = track.start
    boxes = [(start.center - start.spread, start.center + start.spread)]
    boxes += [_opening_box(g, gate_shift, shift_z) for g in track.gates]
    length = sum(_box_gap(a, b) for a, b in zip(boxes, boxes[1:], strict=False))
    return length, max(0.0, float(start.center[2] + start.spread[2]))


def lap_time_lower_bound(
    track: Track,
    params: QuadrotorParams | None = None,
    gate_shift: float = 0.0,
    gate_shift_z: float | None = None,
    physics_freq: int = 200,
    max_wind: float = 0.0,
) -> float:
    """Lap time (s) below which no lap of ``track`` can be flown by the airframe ``params`` (module docstring): a whole
    number of physics ticks; a lap of exactly this time is possible as far as the bound can tell.

    ``max_wind`` (m/s): the largest wind speed. Drag on the air-relative velocity can then do positive work, but only
    on a body axis where the drone is slower than the wind, and there ``f_i v_i ≤ k_i w² |v_i|``: in all at most
    ``√3 k_max w² |v|``, which the bound counts as extra thrust ``√3 k_max w² / m``.
    """
    geometry = lap_geometry(track, gate_shift, gate_shift_z)
    return _geometry_bound(*geometry, params or QuadrotorParams(), physics_freq, max_wind)


def _geometry_bound(
    length: float, height: float, params: QuadrotorParams, physics_freq: int, max_wind: float = 0.0
) -> float:
    """The lap-time bound (s) of a lap at least ``length`` m long starting at most ``height`` m up."""
    drag = max(params.drag_coefficients) / params.mass
    accel = (params.max_thrust + math.sqrt(3.0) * max(params.drag_coefficients) * max_wind**2) / params.mass
    ticks = min_ticks_from_rest(length, height, accel, params.gravity, 1.0 / physics_freq, drag)
    return ticks / physics_freq


@functools.cache
def env_lap_time_bound(env_id: str) -> float:
    """:func:`lap_time_lower_bound` of a registered env id, from its ``RaceEnv`` kwargs (cached per process, which
    holds one env version). It does not depend on the id's obstacles. For a track source (``RaceObs-Random-v0``,
    ``RaceObs-Unseen-v0``) it is the bound of every track the generator can make
    (:func:`racebench.sim.track_generator.shortest_lap`); a record is also held to its own track's."""
    if env_id not in ENV_KWARGS:
        raise ValueError(f"env_id {env_id!r} is not a racebench id")
    defaults = {k: p.default for k, p in inspect.signature(RaceEnv.__init__).parameters.items()}
    kwargs = {**defaults, **ENV_KWARGS[env_id]}
    quad = kwargs["quadrotor"]
    params = quad if isinstance(quad, QuadrotorParams) else QuadrotorParams(**(quad or {}))
    wind = DrydenWind(kwargs["wind_gust_std"]).max_speed
    if kwargs["track"] in TRACK_SOURCES:
        spread = (START_SPREAD,) * 3 if kwargs["start_spread"] is None else tuple(kwargs["start_spread"])
        geometry = shortest_lap(spread, kwargs["gate_shift"], kwargs["gate_shift_z"])
        return _geometry_bound(*geometry, params, kwargs["physics_freq"], wind)
    track = load_track(kwargs["track"])
    if kwargs["start_spread"] is not None:
        spread = np.asarray(kwargs["start_spread"], dtype=float)
        track = dataclasses.replace(track, start=dataclasses.replace(track.start, spread=spread))
    return lap_time_lower_bound(track, params, kwargs["gate_shift"], kwargs["gate_shift_z"], kwargs["physics_freq"],
                                wind)  # fmt: skip
