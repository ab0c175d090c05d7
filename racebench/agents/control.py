"""Geometric flight controller that turns a desired acceleration into a CTBR action.

:func:`track_acceleration` is the fast expert's last stage; :func:`command_to_ctbr` flies an *acceleration command*
(heading-frame acceleration and heading change, :func:`acceleration_command`) through it from a state observation
alone, which is how a student that outputs commands instead of CTBR is flown (``action_output: acceleration``).

:class:`GateFollower` is a privileged scripted agent: it reads the true gate poses and drone state and
flies along each gate's axis through its opening, ignoring obstacles. It is the reference for
obstacle-free flight (curriculum level 1) and the runnable default of ``racebench fly``.
"""

from __future__ import annotations

import math

import numpy as np

from racebench.sim.quadrotor import QuadrotorParams
from racebench.utils.angles import wrap_angle


def acceleration_to_ctbr(
    accel: np.ndarray, yaw_des: float, rotation: np.ndarray, params: QuadrotorParams, attitude_gain: float = 6.0
) -> np.ndarray:
    """CTBR action that produces world-frame acceleration ``accel`` (gravity excluded) at heading ``yaw_des``.

    Thrust: the projection of ``accel + g`` on the current body z. Rates: proportional to the
    attitude error between the current rotation and the one whose z axis points along ``accel + g``
    (SO(3) error of Lee et al., 2010).
    """
    f = accel + np.array([0.0, 0.0, params.gravity])
    norm = np.linalg.norm(f)
    z_d = f / norm if norm > 1e-6 else np.array([0.0, 0.0, 1.0])
    x_c = np.array([math.cos(yaw_des), math.sin(yaw_des), 0.0])
    y_d = np.cross(z_d, x_c)
    y_norm = np.linalg.norm(y_d)
    y_d = y_d / y_norm if y_norm > 1e-6 else rotation[:, 1]
    r_d = np.column_stack([np.cross(y_d, z_d), y_d, z_d])
    e = r_d.T @ rotation - rotation.T @ r_d
    e_rot = 0.5 * np.array([e[2, 1], e[0, 2], e[1, 0]])
    rates = -attitude_gain * e_rot
    thrust = params.mass * float(f @ rotation[:, 2])
    action = np.empty(4)
    action[0] = 2.0 * thrust / params.max_thrust - 1.0
    action[1:] = rates / np.asarray(params.max_body_rate)
    return np.clip(action, -1.0, 1.0)


def track_acceleration(
    accel: np.ndarray, yaw_des: float, rotation: np.ndarray, params: QuadrotorParams, attitude_gain: float
) -> np.ndarray:
    """:func:`acceleration_to_ctbr` with altitude first: the fast expert's last stage, and an acceleration student's.

    While the body turns toward a new thrust direction, the projection of the wanted force on body z drops and the
    drone would sink; the collective thrust keeps at least the wanted vertical component (when the body is within
    ~73° of upright).
    """
    action = acceleration_to_ctbr(accel, yaw_des, rotation, params, attitude_gain)
    if rotation[2, 2] > 0.3:
        vertical = params.mass * (accel[2] + params.gravity) / rotation[2, 2]
        action[0] = max(action[0], min(2.0 * vertical / params.max_thrust - 1.0, 1.0))
    return action


# An acceleration command (what a student with ``action_output: acceleration`` outputs, 4 numbers in [-1, 1]): the
# wanted acceleration (gravity excluded) in the heading frame (world axes turned by the drone's yaw; z up), in units of
# COMMAND_ACCEL_SCALE, and the heading change wanted, in units of COMMAND_YAW_SCALE. It is flown by
# :func:`command_to_ctbr` from the observation alone; the fast expert's commands are its labels (acceleration_command).
# m/s² per unit, forward, left, up: the expert asks for up to ~26 m/s² sideways and ~8 m/s² vertically (feedforward and
# feedback); the vertical unit is finer so that a thrust error costs the fit about what it costs a CTBR student.
COMMAND_ACCEL_SCALE = np.array([30.0, 30.0, 10.0])
COMMAND_YAW_SCALE = 0.5  # rad per unit: the fast expert turns by at most this much heading error (max_yaw_error)
COMMAND_ATTITUDE_GAIN = 10.0  # the fast expert's attitude gain (FastPlannerAgent.attitude_gain)


def heading_yaw(rotation: np.ndarray) -> float:
    """The yaw (rad) of the body x axis's horizontal projection."""
    return math.atan2(rotation[1, 0], rotation[0, 0])


def acceleration_command(accel: np.ndarray, yaw_des: float, rotation: np.ndarray) -> np.ndarray:
    """The acceleration command (4 float32, clipped to [-1, 1]) that asks a drone at ``rotation`` for world-frame
    acceleration ``accel`` (m/s², gravity excluded) at heading ``yaw_des`` (rad)."""
    yaw = heading_yaw(rotation)
    c, s = math.cos(yaw), math.sin(yaw)
    heading_frame = np.array([c * accel[0] + s * accel[1], c * accel[1] - s * accel[0], accel[2]])
    command = np.append(heading_frame / COMMAND_ACCEL_SCALE, wrap_angle(yaw_des - yaw) / COMMAND_YAW_SCALE)
    return command.clip(-1.0, 1.0).astype(np.float32)


def rotation_from_state(state: np.ndarray) -> np.ndarray:
    """The body-to-world rotation matrix from a 17-float state observation (its quaternion x, y, z, w at 10-13)."""
    quat = np.asarray(state[10:14], dtype=np.float64)
    x, y, z, w = quat / np.linalg.norm(quat)  # float32 in the observation: renormalised
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])  # fmt: skip


def command_to_ctbr(command: np.ndarray, state: np.ndarray, params: QuadrotorParams | None = None) -> np.ndarray:
    """CTBR actions ``(..., 4)`` that fly acceleration commands ``(..., 4)`` from the state observations ``(..., 17)``.

    Reads only what every agent observes (the attitude quaternion): the command, turned from the heading frame to
    the world, goes through :func:`track_acceleration` with the fast expert's attitude gain, so the expert's own
    command at a state reproduces its action there (tested).
    """
    params = params or QuadrotorParams()
    command = np.asarray(command, dtype=np.float64)
    state = np.asarray(state)
    flat_command, flat_state = command.reshape(-1, 4), state.reshape(-1, state.shape[-1])
    actions = np.empty((len(flat_command), 4), dtype=np.float32)
    for k, (u, obs) in enumerate(zip(flat_command, flat_state, strict=True)):
        rotation = rotation_from_state(obs)
        yaw = heading_yaw(rotation)
        c, s = math.cos(yaw), math.sin(yaw)
        a = np.clip(u[:3], -1.0, 1.0) * COMMAND_ACCEL_SCALE
        accel = np.array([c * a[0] - s * a[1], s * a[0] + c * a[1], a[2]])
        yaw_des = yaw + float(np.clip(u[3], -1.0, 1.0)) * COMMAND_YAW_SCALE
        actions[k] = track_acceleration(accel, yaw_des, rotation, params, COMMAND_ATTITUDE_GAIN)
    return actions.reshape(command.shape)


class GateFollower:
    """Fly along the axis of each gate in turn: a carrot on the gate axis, a PD velocity loop.

    Args:
        speed: cruise speed in m/s.
        lookahead: carrot distance ahead of the drone's projection on the gate axis, m.
    """

    obs_mode = "state"

    def __init__(self, speed: float = 3.0, lookahead: float = 1.5, velocity_gain: float = 3.0) -> None:
        self.speed = speed
        self.lookahead = lookahead
        self.velocity_gain = velocity_gain

    def act_privileged(self, env) -> np.ndarray:
        """Action for the current state of ``env`` (a :class:`~racebench.envs.env.RaceEnv`, unwrapped)."""
        scene = env.scene
        pos, _, rot, vel, _ = env.drone
        gate = scene.gates[min(env.next_gate, len(scene.gates) - 1)]
        n = gate.normal
        along = float((pos - gate.center) @ n)
        carrot = gate.center + n * min(along + self.lookahead, 1.0)
        to_carrot = carrot - pos
        dist = float(np.linalg.norm(to_carrot))
        v_ref = to_carrot / max(dist, 1e-6) * min(self.speed, 2.0 * dist + 0.5)
        accel = self.velocity_gain * (v_ref - vel)
        heading = to_carrot if np.linalg.norm(to_carrot[:2]) > 0.3 else n
        self.command = (accel, math.atan2(heading[1], heading[0]))  # (world acceleration, heading) it flies
        return acceleration_to_ctbr(accel, self.command[1], rot, env.params)
