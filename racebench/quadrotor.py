"""Quadrotor model: CTBR action mapping, body-rate controller, X-layout motor allocation, motor lag, drag.

This module is pure numpy; :mod:`racebench.simulation` applies the forces and torques it returns to a
PyBullet rigid body at every physics step. Defaults are the paper's Table I airframe:
mass 0.58 kg, inertia diag(1.01, 1.53, 2.03) g·m², 14 N maximum total thrust, 0.075 m arms.

Action (CTBR) in ``[-1, 1]^4``:
  * ``a[0]`` → mass-normalised collective thrust ``c = (a[0] + 1) / 2 · T_max / m`` (0 … 24.1 m/s²);
    hover is ``a[0] = 2 m g / T_max − 1 ≈ −0.187``;
  * ``a[1:4]`` → body-rate command ``ω_cmd = a[1:4] · max_body_rate`` (default ±6, ±6, ±3 rad/s).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class QuadrotorParams:
    """Physical and low-level control parameters of the simulated quadrotor.

    Attributes:
        mass: kg.
        inertia: diagonal of the inertia matrix, kg·m².
        max_thrust: maximum total thrust of the four motors, N.
        arm_length: distance from the centre to each motor, m (X layout, motors at ±45°).
        torque_coefficient: yaw reaction torque per newton of motor thrust, m.
        motor_time_constant: first-order lag of each motor's thrust, s.
        max_body_rate: body-rate command at ``|a| = 1`` for roll, pitch, yaw, rad/s.
        rate_gain: proportional gain of the body-rate loop, 1/s (critically damped with the motor lag).
        drag_coefficients: quadratic drag per body axis, N/(m/s)²; ``f = −k ⊙ v_b ⊙ |v_b|``.
        collision_radius: radius of the collision sphere (arms plus propellers), m.
        gravity: m/s².
    """

    mass: float = 0.58
    inertia: tuple[float, float, float] = (1.01e-3, 1.53e-3, 2.03e-3)
    max_thrust: float = 14.0
    arm_length: float = 0.075
    torque_coefficient: float = 0.016
    motor_time_constant: float = 0.03
    max_body_rate: tuple[float, float, float] = (6.0, 6.0, 3.0)
    rate_gain: tuple[float, float, float] = (16.0, 16.0, 10.0)
    drag_coefficients: tuple[float, float, float] = (0.03, 0.03, 0.05)
    collision_radius: float = 0.12
    gravity: float = 9.81

    def __post_init__(self) -> None:
        for name in ("mass", "max_thrust", "arm_length", "torque_coefficient", "collision_radius", "gravity"):
            if not getattr(self, name) > 0:
                raise ValueError(f"QuadrotorParams.{name} must be > 0, got {getattr(self, name)!r}")
        if self.motor_time_constant < 0:
            raise ValueError(f"QuadrotorParams.motor_time_constant must be >= 0, got {self.motor_time_constant!r}")
        for name in ("inertia", "max_body_rate", "rate_gain", "drag_coefficients"):
            value = getattr(self, name)
            if len(value) != 3 or any(v < 0 for v in value):
                raise ValueError(f"QuadrotorParams.{name} must be 3 non-negative numbers, got {value!r}")
        if self.max_thrust <= self.mass * self.gravity:
            raise ValueError("QuadrotorParams.max_thrust must exceed the weight, or the drone cannot hover")

    @property
    def hover_action(self) -> float:
        """The ``a[0]`` whose collective thrust equals the weight."""
        return 2.0 * self.mass * self.gravity / self.max_thrust - 1.0


@dataclass
class Quadrotor:
    """Low-level flight controller and actuators of one quadrotor (state: the four motor thrusts)."""

    params: QuadrotorParams = field(default_factory=QuadrotorParams)

    def __post_init__(self) -> None:
        p = self.params
        d = p.arm_length / math.sqrt(2.0)
        # Motors: front-right, rear-left, front-left, rear-right; diagonal pairs spin the same way.
        xs = np.array([d, -d, d, -d])
        ys = np.array([-d, d, d, -d])
        spin = np.array([1.0, 1.0, -1.0, -1.0])
        # [T, τx, τy, τz] = allocation @ f, with τ = r × (0, 0, f) = (y f, −x f, 0) plus the yaw reaction.
        self.allocation = np.stack([np.ones(4), ys, -xs, spin * p.torque_coefficient])
        self.allocation_inv = np.linalg.inv(self.allocation)
        self.inertia = np.asarray(p.inertia, dtype=float)
        self.rate_gain = np.asarray(p.rate_gain, dtype=float)
        self.max_body_rate = np.asarray(p.max_body_rate, dtype=float)
        self.drag = np.asarray(p.drag_coefficients, dtype=float)
        self.max_motor_thrust = p.max_thrust / 4.0
        self.motor_thrusts = np.zeros(4)

    def reset(self, hover: bool = True) -> None:
        """Set the motors to hover thrust (or off), so an episode starts without a thrust transient."""
        self.motor_thrusts = np.full(4, self.params.mass * self.params.gravity / 4.0 if hover else 0.0)

    def command(self, action: np.ndarray) -> tuple[float, np.ndarray]:
        """Map a CTBR action in ``[-1, 1]^4`` to (collective thrust in N, body-rate command in rad/s)."""
        a = np.clip(action, -1.0, 1.0)
        return (a[0] + 1.0) * 0.5 * self.params.max_thrust, a[1:] * self.max_body_rate

    def actuate(
        self, thrust_cmd: float, rate_cmd: np.ndarray, body_rates: np.ndarray, dt: float
    ) -> tuple[float, np.ndarray]:
        """Advance the rate controller and motors by ``dt``; return (collective thrust N, body torque N·m).

        The rate loop is ``τ = J K (ω_cmd − ω) + ω × Jω``; motor commands come from inverting the X-layout
        allocation, are clipped to each motor's range and followed with a first-order lag.
        """
        w = body_rates
        jw = self.inertia * w
        gyro = np.array([w[1] * jw[2] - w[2] * jw[1], w[2] * jw[0] - w[0] * jw[2], w[0] * jw[1] - w[1] * jw[0]])
        torque_cmd = self.inertia * self.rate_gain * (rate_cmd - w) + gyro  # np.cross costs 10x this
        wrench = np.array([thrust_cmd, torque_cmd[0], torque_cmd[1], torque_cmd[2]])
        motor_cmd = np.clip(self.allocation_inv @ wrench, 0.0, self.max_motor_thrust)
        tau = self.params.motor_time_constant
        alpha = 1.0 if tau == 0 else 1.0 - math.exp(-dt / tau)
        self.motor_thrusts = self.motor_thrusts + alpha * (motor_cmd - self.motor_thrusts)
        out = self.allocation @ self.motor_thrusts
        return float(out[0]), out[1:]

    def drag_force(self, body_velocity: np.ndarray) -> np.ndarray:
        """Quadratic drag in the body frame, opposing the body-frame velocity."""
        return -self.drag * body_velocity * np.abs(body_velocity)
