"""The privileged reference agent: plan a collision-free path through the gate openings, then track it.

Planning uses the obstacle generator's own soundness machinery: :func:`racebench.obstacles.find_corridor`
returns a polyline that keeps a sphere of ``clearance`` metres clear of every gate bar, obstacle, the
ground and the arena, and passes each gate along its normal through the opening. The polyline is
resampled and tracked with a carrot (pure pursuit) and a velocity loop, whose desired acceleration the
geometric controller of :mod:`racebench.control` turns into CTBR.

It reads the true scene and drone state, so it is marked *privileged* wherever it is shown: it proves a
track variant flyable and gives the leaderboard an upper reference, it is not a learned policy.
"""

from __future__ import annotations

import math

import numpy as np

from racebench.control import GateFollower, acceleration_to_ctbr
from racebench.obstacles import find_corridor
from racebench.reward import wrap_angle


def speed_profile(
    points: np.ndarray,
    arc: np.ndarray,
    v_max: float,
    lateral_accel: float,
    decel: float,
    v_min: float = 0.6,
    end_speed: float = 0.3,
) -> np.ndarray:
    """Speed along a resampled path: limited by curvature (``v² κ ≤ a_lat``), by braking ahead of turns and
    to ``end_speed`` at the end."""
    ds = float(arc[1] - arc[0]) if len(arc) > 1 else 1.0
    span = max(1, int(round(0.3 / ds)))  # estimate curvature over ±0.3 m: grid corners are sharp
    direction = np.diff(points, axis=0, append=points[-1:] + (points[-1:] - points[-2:-1]))
    direction /= np.maximum(np.linalg.norm(direction, axis=1, keepdims=True), 1e-9)
    ahead = direction[np.minimum(np.arange(len(points)) + span, len(points) - 1)]
    behind = direction[np.maximum(np.arange(len(points)) - span, 0)]
    turn = np.arccos(np.clip(np.sum(ahead * behind, axis=1), -1.0, 1.0))
    curvature = turn / (2 * span * ds)
    v = np.clip(np.sqrt(lateral_accel / np.maximum(curvature, 1e-9)), v_min, v_max)
    v[-1] = min(v[-1], end_speed)
    for i in range(len(v) - 2, -1, -1):  # brake in time for what comes
        v[i] = min(v[i], math.sqrt(v[i + 1] ** 2 + 2 * decel * (arc[i + 1] - arc[i])))
    return v


def split_at_cusps(polyline: np.ndarray, max_turn: float = 2.0) -> list[np.ndarray]:
    """Split a polyline where it doubles back (turn > ``max_turn`` rad): each piece is flown to its end."""
    pieces, start = [], 0
    for i in range(1, len(polyline) - 1):
        a, b = polyline[i] - polyline[i - 1], polyline[i + 1] - polyline[i]
        cos = float(a @ b) / max(float(np.linalg.norm(a) * np.linalg.norm(b)), 1e-12)
        if math.acos(max(-1.0, min(1.0, cos))) > max_turn:
            pieces.append(polyline[start : i + 1])
            start = i
    pieces.append(polyline[start:])
    return [p for p in pieces if len(p) >= 2]


def resample(polyline: np.ndarray, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Points every ``spacing`` m along a polyline, and their arc length."""
    seg = np.linalg.norm(np.diff(polyline, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    s = np.arange(0.0, arc[-1], spacing)
    s = np.append(s, arc[-1])
    points = np.stack([np.interp(s, arc, polyline[:, k]) for k in range(3)], axis=1)
    return points, s


class PlannerAgent:
    """Privileged planner + tracker (see the module docstring).

    Args:
        speed: cruise speed along the path, m/s.
        clearance: distance the planned path keeps from all geometry, m (drone radius + tracking margin).
        lookahead: carrot distance along the path, m.
        velocity_gain: gain of the velocity loop, 1/s.
    """

    name = "planner"
    obs_mode = "state"
    privileged = True

    def __init__(
        self,
        speed: float = 4.0,
        clearance: float = 0.36,
        lookahead: float = 0.5,
        velocity_gain: float = 5.0,
        max_lateral_accel: float = 4.0,
        max_decel: float = 3.0,
    ) -> None:
        self.speed = speed
        self.max_lateral_accel = max_lateral_accel
        self.max_decel = max_decel
        self.clearance = clearance
        self.lookahead = lookahead
        self.velocity_gain = velocity_gain
        self.env = None
        self.path: np.ndarray | None = None
        self._fallback = GateFollower(speed=speed)

    def reset(self, env=None, seed: int | None = None) -> None:
        """Plan for the episode that ``env`` (an unwrapped :class:`~racebench.env.RaceEnv`) has just reset."""
        if env is None:
            raise ValueError("PlannerAgent is privileged: reset(env) needs the unwrapped RaceEnv")
        self.env = env
        start = env.drone.position
        polyline = None
        # Ask for a wide berth first; narrow it only if the layout leaves no such corridor,
        # and a long straight approach through each gate (so the drone arrives aligned).
        tries = ((self.clearance, 0.8), (self.clearance, 0.4), (0.3, 0.4), (0.24, 0.25), (0.21, 0.25))
        for clearance, approach in tries:
            polyline = find_corridor(env.scene, clearance, start=start, approach=approach)
            if polyline is not None:
                break
        if polyline is None:
            self.path = None
            return
        # Cusps (the corridor doubles back, e.g. around a gate approached from behind) split the path into
        # pieces that are each flown to their end, so the tracker never cuts a hairpin short.
        self.pieces = []
        for piece in split_at_cusps(polyline):
            points, arc = resample(piece, 0.05)
            speeds = speed_profile(points, arc, self.speed, self.max_lateral_accel, self.max_decel)
            self.pieces.append((points, arc, speeds))
        self._piece = -1
        self._next_piece()

    def _next_piece(self) -> None:
        self._piece += 1
        self.path, self.arc, self.speeds = self.pieces[self._piece]
        self._index = 0

    def act(self, obs=None) -> np.ndarray:
        """CTBR action for the env's current state (the observation itself is not needed)."""
        env = self.env
        if self.path is None:
            return self._fallback.act_privileged(env)
        state = env.drone
        pos, vel = state.position, state.velocity
        # Progress along the path: nearest point within 0.4 m ahead of the last one. Never backwards, and
        # never a jump, or a hairpin could be skipped together with the gate passage inside it.
        window = self.path[self._index : self._index + 9]
        self._index += int(np.argmin(np.linalg.norm(window - pos, axis=1)))
        if self._piece + 1 < len(self.pieces) and np.linalg.norm(self.path[-1] - pos) < 0.15:
            self._next_piece()
        # Anticipate: the slowest profile speed over the next 0.25 s, since the velocity loop lags.
        horizon = 1 + int(0.25 * float(self.speeds[self._index]) / 0.05)
        speed = float(self.speeds[self._index : self._index + horizon].min())
        s = self.arc[self._index]
        # Carrot distance grows with speed: tight at slow corners, smooth on straights.
        ahead = self.lookahead + 0.15 * speed
        carrot = self.path[min(np.searchsorted(self.arc, s + ahead), len(self.path) - 1)]
        to_carrot = carrot - pos
        dist = float(np.linalg.norm(to_carrot))
        v_ref = to_carrot / max(dist, 1e-6) * speed
        accel = self.velocity_gain * (v_ref - vel)
        # Turn toward the direction of travel, but by at most 0.5 rad of error at a time: a large yaw error
        # couples into roll and pitch, and the privileged planner needs no camera pointing.
        yaw = math.atan2(state.rotation[1, 0], state.rotation[0, 0])
        if np.linalg.norm(v_ref[:2]) > 0.5:
            yaw += float(np.clip(wrap_angle(math.atan2(v_ref[1], v_ref[0]) - yaw), -0.5, 0.5))
        return acceleration_to_ctbr(accel, yaw, state.rotation, env.params)
