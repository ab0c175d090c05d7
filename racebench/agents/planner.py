"""The privileged reference agent: plan a collision-free path through the gate openings, then track it.

Planning uses the obstacle generator's own soundness machinery: :func:`racebench.sim.obstacles.find_corridor`
returns a polyline that keeps a sphere of ``clearance`` metres clear of every gate bar, obstacle, the
ground and the arena, and passes each gate along its normal through the opening. The polyline is
resampled and tracked with a carrot (pure pursuit) and a velocity loop, whose desired acceleration the
geometric controller of :mod:`racebench.agents.control` turns into CTBR.

It reads the true scene and drone state, so it is marked *privileged* wherever it is shown: it proves a
track variant flyable and gives the leaderboard an upper reference, it is not a learned policy.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from racebench.agents.control import GateFollower, acceleration_to_ctbr, track_acceleration
from racebench.agents.paths import (
    _arc_length_spline,
    gate_crossings,
    pull_taut,
    relax,
    resample,
    scene_clearance,
    split_at_cusps,
)
from racebench.agents.speeds import (
    limit_braking_onset,
    limit_jerk,
    minimum_time_speeds,
    speed_profile,
    thrust_limited_speeds,
)
from racebench.sim.corridor import find_corridor
from racebench.sim.quadrotor import QuadrotorParams
from racebench.sim.raycast import ObstacleSight
from racebench.sim.scene import Scene
from racebench.utils.angles import wrap_angle


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
        """Plan for the episode that ``env`` (an unwrapped :class:`~racebench.envs.env.RaceEnv`) has just reset."""
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
            action = self._fallback.act_privileged(env)
            self.command = self._fallback.command
            return action
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
        self.command = (accel, yaw)
        return acceleration_to_ctbr(accel, yaw, state.rotation, env.params)


# --------------------------------------------------------------------------- fast expert


#: What :class:`FastPlannerAgent` knows of the obstacles: all of them (privileged), or those its camera has shown.
OBSTACLE_KNOWLEDGE: tuple[str, ...] = ("all", "seen")


class FastPlannerAgent:
    """Privileged fast expert: a racing line through the obstacle corridor, flown at the fastest speed
    profile the airframe's thrust allows and tracked with acceleration feedforward.

    Planning (at reset): corridors at several clearances (:func:`~racebench.sim.obstacles.find_corridor`), each
    pulled taut between the gate centres (:func:`pull_taut`) and smoothed by descending bending energy under
    clearance floors (:func:`relax`); the first candidate (shortest first) whose spline passes every
    opening in order and stays :attr:`min_path_clearance` clear up to the finish is kept, otherwise the
    cautious :class:`PlannerAgent` flies the episode. Speeds: the minimum-time profile under the thrust
    budget ``thrust_accel`` (:func:`thrust_limited_speeds`: gravity and drag included, so level turns pull
    harder than climbs), capped where the path runs close to something, with each switch from speeding up
    to braking spread at ``braking_jerk`` (:func:`limit_braking_onset`) and acceleration changes spread over
    ``flip_time`` (:func:`limit_jerk`).

    Tracking: cross-track PID + velocity loop around the curvature and speed-change feedforward read
    ``anticipation`` seconds ahead, body-frame drag cancelled, altitude-first thrust while the body turns.

    Args:
        max_accel: acceleration budget of the friction-circle profile (:func:`minimum_time_speeds`), used
            when ``thrust_accel`` is ``None`` (v2's profile: 10 m/s² in any direction), m/s².
        max_speed: speed cap, m/s.
        clearance: the smoothed path's clearance floor away from gates, m (drone radius 0.12 plus margin).
        wanted_clearance: the smoothing pushes the path away from obstacles closer than this, m.
        position_gain, velocity_gain, integral_gain: tracking loop gains (1/s², 1/s, 1/s).
        anticipation: how far ahead (s) the feedforward is read: the thrust direction lags the command.
        attitude_gain: gain of the attitude loop that turns the wanted acceleration into body rates, 1/s.
        flip_time: time over which the profile spreads a change of acceleration, s.
        min_path_clearance: a planned path closer than this to anything (up to the finish) is rejected, m.
        tight_speed, room_speed_gain: speed cap ``tight_speed + room_speed_gain · (clearance − min)``.
        yaw_lookahead, max_yaw_error: heading target ``yaw_lookahead`` m ahead on the path, approached by at
            most ``max_yaw_error`` rad of error at a time.
        gate_clearance, gate_floor: the smoothing's wanted clearance and clearance floor within 0.8 m of a gate
            centre, m (:func:`relax`). The opening is 1 m square, so 0.5 asks for its centre; the default 0.4
            lets the line cross up to 0.1 m off it, which rounds a turn. A student imitating the expert
            inherits how close to a bar its line runs.
        thrust_accel: mass-normalised thrust the speed profile may ask for, m/s²; ``None`` for the
            friction circle of ``max_accel``. The airframe has 24.1; 15 leaves the tracking loops ~9.
        braking_jerk: how fast the profile's acceleration may fall (at top speed; e.g. from speeding up to
            braking), m/s³ (``None``: at once). The thrust turns through up to ~90° to brake; 60 spreads that
            over ~0.3 s.
        replan_distance: when the drone is farther than this from the planned line (m), plan again from where
            it is, through the gates still to pass, at most once every ``replan_interval`` s; ``None`` (the
            built-in): never. A plan fixed at reset steers an off-line drone straight back to the line, through
            whatever is in between; as a DAgger teacher, which labels the states a student flies into, it
            needs to plan from them (:mod:`racebench.training.dagger`, ``teacher_replan_distance``). From a spot
            closer to something than the narrowest corridor (0.21 m) no plan is found and the old one is kept
            (counted in ``replan_failures``); a drone past a gate's approach point may be sent back to it.
        replan_interval: least time between two replans, s (a plan costs ~0.15 s of CPU).
        obstacle_knowledge: ``"all"`` (the built-in): every obstacle is known from reset, the line bends for
            obstacles the camera has not shown yet. ``"seen"``: only obstacles the onboard camera has shown so far
            (:class:`~racebench.sim.raycast.ObstacleSight`: at least one depth pixel, occlusion and range included)
            are planned around; it plans at reset around those in view and, whenever one comes into view within
            ``wanted_clearance`` of the line still to fly, plans again from the drone's state (no
            ``replan_interval`` wait; counted in ``sighting_replans``). Gates are always known (the state
            observation points at them). A DAgger teacher whose labels depend only on what the student could
            have seen (:mod:`racebench.training.dagger`, ``teacher_obstacles``).
    """

    name = "planner-fast"
    obs_mode = "state"
    privileged = True

    def __init__(
        self,
        max_accel: float = 10.0,
        max_speed: float = 12.0,
        clearance: float = 0.3,
        wanted_clearance: float = 0.45,
        position_gain: float = 8.0,
        velocity_gain: float = 8.0,
        anticipation: float = 0.12,
        attitude_gain: float = 10.0,
        integral_gain: float = 4.0,
        flip_time: float = 0.1,
        min_path_clearance: float = 0.17,
        tight_speed: float = 2.5,
        room_speed_gain: float = 20.0,
        yaw_lookahead: float = 1.5,
        max_yaw_error: float = 0.5,
        gate_clearance: float = 0.4,
        gate_floor: float = 0.32,
        thrust_accel: float | None = 15.0,
        braking_jerk: float | None = 60.0,
        replan_distance: float | None = None,
        replan_interval: float = 0.3,
        obstacle_knowledge: str = "all",
    ) -> None:
        for name, value in (
            ("thrust_accel", thrust_accel), ("braking_jerk", braking_jerk), ("replan_distance", replan_distance)
        ):  # fmt: skip
            if value is not None and not value > 0:
                raise ValueError(f"FastPlannerAgent: {name} must be a positive number or None, got {value!r}")
        if obstacle_knowledge not in OBSTACLE_KNOWLEDGE:
            raise ValueError(
                f"FastPlannerAgent: obstacle_knowledge must be one of {OBSTACLE_KNOWLEDGE}, got {obstacle_knowledge!r}"
            )
        self.obstacle_knowledge = obstacle_knowledge
        self.sighting_replans = 0  # replans this episode because an obstacle came into view near the line
        self.known: np.ndarray | None = None  # per obstacle of the scene: planned around (True once seen)
        self._sight: ObstacleSight | None = None
        if not replan_interval >= 0:
            raise ValueError(f"FastPlannerAgent: replan_interval must be >= 0 s, got {replan_interval!r}")
        self.replan_distance = replan_distance
        self.replan_interval = replan_interval
        self.replans = 0  # successful replans this episode
        self.replan_failures = 0  # replans tried this episode that found no plan (the old one is kept)
        self.max_accel = max_accel
        self.thrust_accel = thrust_accel
        self.braking_jerk = braking_jerk
        self.max_speed = max_speed
        self.clearance = clearance
        self.wanted_clearance = wanted_clearance
        self.position_gain = position_gain
        self.velocity_gain = velocity_gain
        self.anticipation = anticipation
        self.attitude_gain = attitude_gain
        self.integral_gain = integral_gain
        self.flip_time = flip_time
        self.min_path_clearance = min_path_clearance
        self.tight_speed = tight_speed
        self.room_speed_gain = room_speed_gain
        self.yaw_lookahead = yaw_lookahead
        self.max_yaw_error = max_yaw_error
        self.gate_clearance = gate_clearance
        self.gate_floor = gate_floor
        self.corridor_clearances = (clearance + 0.1, clearance, 0.24, 0.21)
        self.env = None
        self._fallback = PlannerAgent()
        self.path: np.ndarray | None = None

    def _taut_corridor(self, scene, start: np.ndarray, clearance: float, approach: float = 0.25) -> np.ndarray | None:
        """The corridor at ``clearance``, pulled taut between gate centres, run on past the finish."""
        corridor = find_corridor(scene, clearance, start=start, approach=approach)
        if corridor is None:
            return None
        # Pin each gate centre: a straight shortcut between two gates could otherwise pass beside the one
        # in between. The corridor runs through each gate along c - a·n → c + a·n.
        pieces, begin = [], 0
        for gate in scene.gates:
            front = gate.center - approach * gate.normal
            k = begin + int(np.flatnonzero(np.all(np.abs(corridor[begin:] - front) < 1e-9, axis=1))[0])
            pieces.append(np.vstack([corridor[begin : k + 1], gate.center]))
            corridor = np.vstack([corridor[: k + 1], gate.center, corridor[k + 1 :]])
            begin = k + 1
        pieces.append(corridor[begin:])
        taut = [pull_taut(scene, p, clearance) for p in pieces if len(p) >= 2]
        polyline = np.vstack([taut[0]] + [t[1:] for t in taut[1:]])
        # Run on past the finish line: the lap ends at the last gate's plane, the tracker needs road ahead.
        return np.vstack([polyline, polyline[-1] + 2.0 * scene.gates[-1].normal])

    def plan(self, scene, start: np.ndarray, start_speed: float = 0.0, params: QuadrotorParams | None = None) -> bool:
        """Plan for ``scene`` from ``start``; ``False`` when no candidate path passes the final checks.

        Candidates come from corridors at several clearances: a wide one can force a detour (even a
        hairpin behind a gate) that a narrower one avoids, so the shortest taut candidate is smoothed
        first, and the next one if the smoothed path fails its checks."""
        candidates = []
        for clearance in self.corridor_clearances:
            polyline = self._taut_corridor(scene, start, clearance)
            if polyline is not None:
                length = float(np.linalg.norm(np.diff(polyline, axis=0), axis=1).sum())
                candidates.append((length - clearance, clearance, polyline))  # ties go to the wider berth
        for _, clearance, polyline in sorted(candidates, key=lambda c: c[0]):
            smooth = relax(
                scene, polyline, min(self.clearance, clearance), self.wanted_clearance,
                gate_clearance=self.gate_clearance, gate_floor=self.gate_floor,
            )  # fmt: skip
            path, arc, tangent, curvature = _arc_length_spline(smooth, 0.05)
            # Check what will be flown: every opening in order, and clear of everything up to the finish.
            crossings = gate_crossings(path, scene.gates)
            if len(crossings) < len(scene.gates):
                continue
            if scene_clearance(scene, path[: crossings[-1] + 2]).min() < self.min_path_clearance:
                continue
            # The feedforward reads curvature; average it over ±0.15 m so spline wiggles do not jerk the
            # thrust direction (the speed profile keeps the raw, larger values).
            kernel = np.ones(7) / 7.0
            smooth_curvature = np.stack([np.convolve(curvature[:, k], kernel, mode="same") for k in range(3)], 1)
            self.path, self.arc, self.tangent, self.curvature = path, arc, tangent, smooth_curvature
            self.profile_curvature = curvature  # what the speed profile was planned on (raw, larger)
            params = params or QuadrotorParams()
            drag = params.drag_coefficients[0] / params.mass  # forward drag eats into the acceleration budget
            # Where the path runs close to something, fly slower: tracking error grows with speed.
            room = scene_clearance(scene, path) - self.min_path_clearance
            cap = np.minimum(self.max_speed, self.tight_speed + self.room_speed_gain * np.maximum(room, 0.0))
            self.speeds = self._speed_profile(arc, tangent, curvature, cap, start_speed, drag, params.gravity)
            self._index = 0
            self._integral = np.zeros(3)
            if self.thrust_accel is None:
                self._accel_limit = self.max_accel
            else:  # what the thrust budget can pull sideways in level flight
                if self.thrust_accel <= params.gravity:
                    raise ValueError(f"FastPlannerAgent: thrust_accel must exceed gravity, got {self.thrust_accel}")
                self._accel_limit = math.sqrt(self.thrust_accel**2 - params.gravity**2)
            return True
        return False

    def _speed_profile(self, arc, tangent, curvature, cap, start_speed, drag, gravity) -> np.ndarray:
        """The speed profile under ``cap``: minimum-time under the acceleration or thrust budget, then
        smoothed where the acceleration switches."""
        if self.thrust_accel is None:
            speeds = minimum_time_speeds(arc, curvature, self.max_accel, cap, start_speed, drag)
        else:
            speeds = thrust_limited_speeds(arc, tangent, curvature, self.thrust_accel, cap, start_speed, drag, gravity)
        if self.braking_jerk is not None:
            speeds = limit_braking_onset(speeds, arc, self.braking_jerk)
        return limit_jerk(speeds, arc, self.flip_time)

    def _reference_accel(self, arc_length: float) -> np.ndarray:
        """The planned acceleration (centripetal plus speed change) at ``arc_length`` along the path, capped."""
        j = min(int(np.searchsorted(self.arc, arc_length)), len(self.arc) - 2)
        ds = self.arc[j + 1] - self.arc[j]
        along = (self.speeds[j + 1] ** 2 - self.speeds[j] ** 2) / (2.0 * ds)
        accel = self.speeds[j] ** 2 * self.curvature[j] + along * self.tangent[j]
        norm = float(np.linalg.norm(accel))
        limit = 1.2 * self._accel_limit
        return accel * (limit / norm) if norm > limit else accel

    def reset(self, env=None, seed: int | None = None) -> None:
        """Plan for the episode that ``env`` (an unwrapped :class:`~racebench.envs.env.RaceEnv`) has just reset."""
        if env is None:
            raise ValueError("FastPlannerAgent is privileged: reset(env) needs the unwrapped RaceEnv")
        self.env = env
        self.replans = 0
        self.replan_failures = 0
        self.sighting_replans = 0
        self._last_replan = -math.inf
        scene = env.scene
        if self.obstacle_knowledge == "seen":
            self._sight = ObstacleSight(env.camera, scene)
            self.known = self._sight.in_view(env.drone.position, env.drone.rotation)
        else:
            self._sight, self.known = None, np.ones(len(scene.obstacles), dtype=bool)
        if not self.plan(self.known_scene(), env.drone.position, float(np.linalg.norm(env.drone.velocity)), env.params):
            self.path = None
            # The cautious fallback plans around every obstacle: a "seen" teacher finds no plan only when even
            # the obstacles in view leave no corridor, which the full scene cannot widen.
            self._fallback.reset(env)

    def known_scene(self) -> Scene:
        """The env's scene with only the obstacles this agent knows of (all, or those seen so far)."""
        scene = self.env.scene
        if self.known is None or self.known.all():
            return scene
        kept = tuple(o for o, k in zip(scene.obstacles, self.known, strict=True) if k)
        return dataclasses.replace(scene, obstacles=kept)

    def _replan(self, wait: bool = True) -> None:
        """Plan again from the drone's state through the gates it has still to pass (keep the plan if none);
        ``wait``: not sooner than ``replan_interval`` after the last one."""
        env = self.env
        now = env.steps / env.control_freq
        if (wait and now - self._last_replan < self.replan_interval) or env.next_gate >= len(env.scene.gates):
            return
        self._last_replan = now
        ahead = self.known_scene().ahead(env.next_gate)  # the frames already passed are still in the way
        if self.plan(ahead, env.drone.position, float(np.linalg.norm(env.drone.velocity)), env.params):
            self.replans += 1
        else:
            self.replan_failures += 1

    def _look(self) -> bool:
        """Mark the obstacles now in view as known; ``True`` when one of them lies within ``wanted_clearance`` of
        the line still to fly (the plan must change)."""
        unknown = np.flatnonzero(~self.known)
        if len(unknown) == 0:
            return False
        state = self.env.drone
        new = unknown[self._sight.in_view(state.position, state.rotation, unknown)]
        if len(new) == 0:
            return False
        self.known[new] = True
        return self.line_passes_near(new)

    def line_passes_near(self, obstacles: np.ndarray) -> bool:
        """Whether the line still to fly passes within ``wanted_clearance`` of any of the env scene's obstacles with
        these indices (``False`` without a line or indices)."""
        if self.path is None or len(obstacles) == 0:
            return False
        scene = self.env.scene
        chosen = dataclasses.replace(scene, gates=(), obstacles=tuple(scene.obstacles[j] for j in obstacles))
        return bool(chosen.distance(self.path[self._index :]).min() < self.wanted_clearance)

    def act(self, obs=None) -> np.ndarray:
        """CTBR action for the env's current state."""
        env = self.env
        if self.path is None:
            action = self._fallback.act(obs)
            self.command = self._fallback.command
            return action
        state = env.drone
        pos, vel = state.position, state.velocity
        window = self.path[self._index : self._index + 20]
        self._index += int(np.argmin(np.linalg.norm(window - pos, axis=1)))
        if self._sight is not None and self._look():
            replans = self.replans
            self._replan(wait=False)
            self.sighting_replans += self.replans - replans
        if self.replan_distance is not None and np.linalg.norm(self.path[self._index] - pos) > self.replan_distance:
            self._replan()
        i = self._index
        t = self.tangent[i]
        error = self.path[i] - pos
        error -= (error @ t) * t  # cross-track only: progress is the projection
        v_ref = max(self.speeds[i], 1.0) * t  # never stall at the start, where the profile is 0
        # Feedforward from slightly ahead: thrust direction lags the command by the attitude loop.
        ahead = self.arc[i] + self.anticipation * max(self.speeds[i], 1.0)
        feedforward = self._reference_accel(ahead)
        # Cancel the airframe's quadratic drag (body axes) so the loops only fix what the model misses.
        rot = state.rotation
        v_body = rot.T @ vel
        drag = rot @ (np.asarray(env.params.drag_coefficients) * v_body * np.abs(v_body)) / env.params.mass
        dt = 1.0 / env.control_freq
        self._integral = np.clip(self._integral + error * dt, -0.3, 0.3)
        accel = (
            feedforward
            + drag
            + self.position_gain * error
            + self.integral_gain * self.position_gain * self._integral
            + self.velocity_gain * (v_ref - vel)
        )
        yaw = math.atan2(state.rotation[1, 0], state.rotation[0, 0])
        # Face where the path goes over the next metres, not its local wiggles, and turn gently: a large
        # yaw error saturates the rate command and couples into roll and pitch.
        heading = self.path[min(i + int(self.yaw_lookahead / 0.05), len(self.path) - 1)] - pos
        if np.linalg.norm(heading[:2]) > 0.3:
            turn = wrap_angle(math.atan2(heading[1], heading[0]) - yaw)
            yaw += float(np.clip(turn, -self.max_yaw_error, self.max_yaw_error))
        self.command = (accel, yaw)  # what an acceleration student is taught (control.acceleration_command)
        return track_acceleration(accel, yaw, rot, env.params, self.attitude_gain)
