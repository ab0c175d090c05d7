"""Geometric flight controller that turns a desired acceleration into a CTBR action.

:class:`GateFollower` is a privileged scripted agent: it reads the true gate poses and drone state and
flies along each gate's axis through its opening, ignoring obstacles. It is the reference for
obstacle-free flight (curriculum level 1) and the runnable default of ``racebench fly``.
"""

from __future__ import annotations

import math

import numpy as np

from racebench.quadrotor import QuadrotorParams


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
        """Action for the current state of ``env`` (a :class:`~racebench.env.RaceEnv`, unwrapped)."""
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
        return acceleration_to_ctbr(accel, math.atan2(heading[1], heading[0]), rot, env.params)
