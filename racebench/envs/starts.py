"""Where a training episode starts (``RaceEnv(start_mode=...)``): small pure functions of a scene and a generator.

* ``"track"``: the track's start region (evaluation); the scene already holds it.
* ``"points"`` (:func:`start_at_a_point`): the paper's "random initialization around each starting point" (Sec.
  III-C.2), at rest.
* ``"gates"`` (:func:`start_before_a_gate`): campaign 1's flying mid-leg start, kept so that its runs reproduce.

Both draw the first gate ``k`` uniformly; ``k = 0`` (or a start that finds no clear pose) is the track start.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from racebench.sim.scene import Scene

START_MODES: tuple[str, ...] = ("track", "points", "gates")
#: ``start_mode="points"``: the starting point before gate k > 0 lies this far before the gate centre, against its
#: normal. The authors' track starts are 2 m before the first gate (S (1,0,1) → (3,0,1); J and Circle (2,3,1) →
#: (4,3,1)); from 2 m the whole 1.28 m frame fills at most 78° of the 90° field of view at any ±0.5 m offset.
START_POINT_DISTANCE = 2.0  # m
#: ``start_mode="points"``: offsets drawn around a gate's starting point before falling back to the track start.
START_POINT_TRIES = 8
MIN_START_HEIGHT = 0.5  # m: a start lower than this is redrawn


def start_at_a_point(
    scene: Scene, rng: np.random.Generator, spread: np.ndarray, clearance: float
) -> tuple[Scene, int]:
    """``start_mode="points"``: ``scene`` with its start at rest around a uniformly drawn gate's starting point.

    The point lies :data:`START_POINT_DISTANCE` m before gate ``k`` against its normal, offset uniformly by
    ±``spread`` and facing along the normal (the gate fully in view); an offset closer than ``clearance`` to any
    frame or obstacle (or below :data:`MIN_START_HEIGHT`) is redrawn up to :data:`START_POINT_TRIES` times, else the
    track start is kept. Returns the scene and the first gate to pass.
    """
    k = int(rng.integers(len(scene.gates)))
    if k == 0:
        return scene, 0
    gate = scene.gates[k]
    point = gate.center - START_POINT_DISTANCE * gate.normal
    for _ in range(START_POINT_TRIES):
        start = point + rng.uniform(-spread, spread)
        if start[2] >= MIN_START_HEIGHT and scene.point_distance(*start.tolist()) >= clearance:
            return dataclasses.replace(scene, start_position=start, start_yaw=float(gate.yaw)), k
    return scene, 0


def start_before_a_gate(
    scene: Scene, rng: np.random.Generator, spread: np.ndarray, clearance: float, desired_speed: float
) -> tuple[Scene, int, np.ndarray | None]:
    """``start_mode="gates"``: ``scene`` with its start mid-leg before a uniformly drawn gate, already flying.

    Candidates run from the middle of the leg towards gate ``k − 1`` (their leg point at least 1 m from either
    gate), each shifted by one random offset within ±``spread``; the first one at least ``clearance`` from every
    obstacle and frame (and :data:`MIN_START_HEIGHT` above the ground) is used, else the track start. A mid-track
    start flies along the leg (gate ``k − 1`` → ``k``) at a speed drawn uniformly in ``[0, desired_speed]``. Returns
    the scene, the first gate to pass and the start velocity (``None``: at rest).
    """
    k = int(rng.integers(len(scene.gates)))
    if k == 0:
        return scene, 0, None
    before, gate = scene.gates[k - 1].center, scene.gates[k].center
    leg = gate - before
    length = float(np.linalg.norm(leg))
    jitter = rng.uniform(-spread, spread)
    velocity = leg / length * rng.uniform(0.0, desired_speed)
    for fraction in (0.5, 0.4, 0.3, 0.2):
        if min(fraction, 1.0 - fraction) * length < 1.0:
            continue
        start = before + fraction * leg + jitter
        if start[2] < MIN_START_HEIGHT or scene.point_distance(*start.tolist()) < clearance:
            continue
        return dataclasses.replace(scene, start_position=start, start_yaw=math.atan2(leg[1], leg[0])), k, velocity
    return scene, 0, None
