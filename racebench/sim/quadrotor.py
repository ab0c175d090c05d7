"""Quadrotor model: CTBR action mapping, body-rate controller, X-layout motor allocation, motor lag, drag.

:mod:`racebench.sim.simulation` applies the forces and torques it returns to a PyBullet rigid body at every
physics step; that per-step arithmetic is compiled with numba (on arrays of 3-4 numbers numpy's and Python's
per-operation overhead costs several times the arithmetic). Defaults are the paper's Table I airframe:
mass 0.58 kg, inertia diag(1.01, 1.53, 2.03) g·m², 14 N maximum total thrust, 0.075 m arms.

Action (CTBR) in ``[-1, 1]^4``:
  * ``a[0]`` → mass-normalised collective thrust ``c = (a[0] + 1) / 2 · T_max / m`` (0 … 24.1 m/s²);
    hover is ``a[0] = 2 m g / T_max − 1 ≈ −0.187``;
  * ``a[1:4]`` → body-rate command ``ω_cmd = a[1:4] · max_body_rate`` (default ±6, ±6, ±3 rad/s).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numba import njit

from racebench.utils.validation import check_real, check_triple, interval

#: Allowed range of each :class:`QuadrotorParams` field: ``(low, high, unit, low end open)``; for the 3-vectors the
#: range of each component. Wide enough for micro (~0.03 kg) to heavy (~5 kg) racing airframes around the paper's
#: 0.58 kg one; narrow enough that every value gives a finite, controllable simulation.
PARAM_RANGES: dict[str, tuple[float, float, str, bool]] = {
    "mass": (0.01, 10.0, "kg", False),
    "inertia": (1e-7, 10.0, "kg m^2", False),  # > 0: the rate loop's torque is J K (w_cmd - w)
    "max_thrust": (0.0, 1e4, "N", True),  # and thrust-to-weight within (1, 20], checked with the mass
    "arm_length": (0.01, 1.0, "m", False),
    "torque_coefficient": (1e-4, 0.1, "m", False),  # > 0: the X-layout allocation must be invertible
    "motor_time_constant": (0.0, 0.5, "s", False),  # 0: instant motors; slower ones cannot follow the rate loop
    "max_body_rate": (0.0, 35.0, "rad/s", True),  # > 0: body rates are observed divided by it; 35 ~ 2000 deg/s
    "rate_gain": (0.0, 50.0, "1/s", True),  # K dt <= 0.5 at the lowest physics rate (100 Hz)
    "drag_coefficients": (0.0, 10.0, "N/(m/s)^2", False),  # at 10 the default airframe's top speed is ~1.1 m/s
    "collision_radius": (0.0, 0.5, "m", True),  # and >= arm_length; a gate opening is 1 m wide
    "gravity": (1.0, 25.0, "m/s^2", False),  # from the Moon (1.6) to Jupiter (24.8)
}
_TRIPLES = ("inertia", "max_body_rate", "rate_gain", "drag_coefficients")
#: Thrust-to-weight ratio ``max_thrust / (mass g)``: above 1 or the drone cannot hover (the paper's airframe: 2.46);
#: at most 20, beyond the ~10-15 of the most powerful racing quadrotors.
MIN_THRUST_TO_WEIGHT = 1.0
MAX_THRUST_TO_WEIGHT = 20.0


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
        # Ranges (see PARAM_RANGES) bound every field finite and physical: an inf or a zero here gives NaN states.
        for name, (low, high, unit, low_open) in PARAM_RANGES.items():
            check = check_triple if name in _TRIPLES else check_real
            check(f"QuadrotorParams.{name}", getattr(self, name), low, high, unit=unit, low_open=low_open)
        jx, jy, jz = self.inertia
        if jx + jy < jz or jy + jz < jx or jz + jx < jy:  # every rigid body's principal moments satisfy it
            raise ValueError(f"QuadrotorParams.inertia must satisfy the triangle inequality, got {self.inertia!r}")
        if self.collision_radius < self.arm_length:
            raise ValueError(
                f"QuadrotorParams.collision_radius must be >= arm_length ({self.arm_length} m: the sphere holds the "
                f"motors), got {self.collision_radius!r}"
            )
        weight = self.mass * self.gravity
        lo, hi = MIN_THRUST_TO_WEIGHT * weight, MAX_THRUST_TO_WEIGHT * weight
        if not lo < self.max_thrust <= hi:
            raise ValueError(
                f"QuadrotorParams.max_thrust must be in {interval(lo, hi, low_open=True, unit='N')} (thrust-to-weight "
                f"in {interval(MIN_THRUST_TO_WEIGHT, MAX_THRUST_TO_WEIGHT, low_open=True)}), got {self.max_thrust!r}"
            )

    @classmethod
    def from_overrides(cls, overrides: dict[str, Any] | QuadrotorParams | None) -> QuadrotorParams:
        """The defaults with ``overrides`` (a dict of fields) on top, or ``overrides`` itself; a one-line error else."""
        if isinstance(overrides, QuadrotorParams):
            return overrides
        if overrides is not None and not isinstance(overrides, dict):
            raise ValueError(f"quadrotor must be a dict of its fields or a QuadrotorParams, got {overrides!r}")
        unknown = sorted(set(overrides or {}) - {f.name for f in dataclasses.fields(cls)})
        if unknown:
            known = sorted(f.name for f in dataclasses.fields(cls))
            raise ValueError(f"quadrotor: unknown parameter {unknown[0]!r} (known: {known})")
        return cls(**(overrides or {}))

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
        # Everything the compiled per-physics-step kernels need, in one array (layout: see _CONSTS).
        self._consts = np.concatenate(
            [
                self.inertia,
                self.inertia * self.rate_gain,
                self.allocation_inv.ravel(),
                self.allocation.ravel(),
                [self.max_motor_thrust, 1.0],  # the motor-lag factor is set per dt (_lag)
                self.drag,
            ]
        )
        self._alpha_dt = math.nan  # dt of the motor-lag factor in _consts
        self._motors = np.zeros(4)

    @property
    def motor_thrusts(self) -> np.ndarray:
        """The four motor thrusts (N), front-right, rear-left, front-left, rear-right."""
        return self._motors.copy()

    @motor_thrusts.setter
    def motor_thrusts(self, value: np.ndarray) -> None:
        self._motors = np.array(value, dtype=np.float64).reshape(4)

    def reset(self, hover: bool = True) -> None:
        """Set the motors to hover thrust (or off), so an episode starts without a thrust transient."""
        self.motor_thrusts = np.full(4, self.params.mass * self.params.gravity / 4.0 if hover else 0.0)

    def command(self, action: np.ndarray) -> tuple[float, np.ndarray]:
        """Map a CTBR action in ``[-1, 1]^4`` to (collective thrust in N, body-rate command in rad/s)."""
        a = np.clip(action, -1.0, 1.0)
        return (a[0] + 1.0) * 0.5 * self.params.max_thrust, a[1:] * self.max_body_rate

    def _lag(self, dt: float) -> None:
        if dt != self._alpha_dt:  # the motor-lag factor only changes with dt: compute exp() once
            tau = self.params.motor_time_constant
            self._consts[_ALPHA] = 1.0 if tau == 0 else 1.0 - math.exp(-dt / tau)
            self._alpha_dt = dt

    def actuate(
        self, thrust_cmd: float, rate_cmd: np.ndarray, body_rates: np.ndarray, dt: float
    ) -> tuple[float, np.ndarray]:
        """Advance the rate controller and motors by ``dt``; return (collective thrust N, body torque N·m).

        The rate loop is ``τ = J K (ω_cmd − ω) + ω × Jω``; motor commands come from inverting the X-layout
        allocation, are clipped to each motor's range and followed with a first-order lag.
        """
        rx, ry, rz = (float(v) for v in rate_cmd)
        wx, wy, wz = (float(v) for v in body_rates)
        thrust, tx, ty, tz = self.actuate_scalar(float(thrust_cmd), rx, ry, rz, wx, wy, wz, dt)
        return thrust, np.array([tx, ty, tz])

    def actuate_scalar(
        self, thrust_cmd: float, rx: float, ry: float, rz: float, wx: float, wy: float, wz: float, dt: float
    ) -> tuple[float, float, float, float]:
        """:meth:`actuate` on plain floats: rate command ``r``, body rates ``w``; returns ``(T, τx, τy, τz)``."""
        self._lag(dt)
        return _actuate(self._consts, self._motors, thrust_cmd, rx, ry, rz, wx, wy, wz)

    def world_wrench(
        self,
        quaternion: tuple[float, float, float, float],
        velocity: tuple[float, float, float],
        angular_velocity: tuple[float, float, float],
        thrust_cmd: float,
        rate_cmd: tuple[float, float, float],
        dt: float,
    ) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        """One physics step of the controller from the world-frame state: (force, torque), world frame.

        Body rates and velocity from the (x, y, z, w) attitude, :meth:`actuate`, quadratic drag, thrust along
        body z; compiled, since it runs at every physics step (Python-level arithmetic cost 3x more here).
        """
        if dt != self._alpha_dt:
            self._lag(dt)
        return _world_wrench(self._consts, self._motors, quaternion, velocity, angular_velocity, thrust_cmd, rate_cmd)

    def drag_force(self, body_velocity: np.ndarray) -> np.ndarray:
        """Quadratic drag in the body frame, opposing the body-frame velocity."""
        return -self.drag * body_velocity * np.abs(body_velocity)


# Layout of Quadrotor._consts: J (3), J K (3), allocation⁻¹ (16, row-major), allocation (16), max motor thrust,
# motor-lag factor α, drag coefficients (3).
_J, _JK, _AINV, _A, _TOP, _ALPHA, _DRAG = 0, 3, 6, 22, 38, 39, 40


@njit(cache=True)
def _actuate(
    c: np.ndarray,
    motors: np.ndarray,
    thrust_cmd: float,
    rx: float,
    ry: float,
    rz: float,
    wx: float,
    wy: float,
    wz: float,
) -> tuple[float, float, float, float]:
    """Rate loop, allocation, per-motor clipping and lag (updates ``motors``); returns ``(T, τx, τy, τz)``."""
    hx, hy, hz = c[_J] * wx, c[_J + 1] * wy, c[_J + 2] * wz  # J ω
    wrench = (
        thrust_cmd,
        c[_JK] * (rx - wx) + (wy * hz - wz * hy),  # J K (ω_cmd − ω) + ω × Jω
        c[_JK + 1] * (ry - wy) + (wz * hx - wx * hz),
        c[_JK + 2] * (rz - wz) + (wx * hy - wy * hx),
    )
    top, alpha = c[_TOP], c[_ALPHA]
    for i in range(4):
        row = _AINV + 4 * i
        cmd = c[row] * wrench[0] + c[row + 1] * wrench[1] + c[row + 2] * wrench[2] + c[row + 3] * wrench[3]
        cmd = 0.0 if cmd < 0.0 else (top if cmd > top else cmd)
        motors[i] += alpha * (cmd - motors[i])
    f0, f1, f2, f3 = motors[0], motors[1], motors[2], motors[3]
    out = [0.0, 0.0, 0.0, 0.0]
    for k in range(4):
        row = _A + 4 * k
        out[k] = c[row] * f0 + c[row + 1] * f1 + c[row + 2] * f2 + c[row + 3] * f3
    return out[0], out[1], out[2], out[3]


@njit(cache=True)
def _world_wrench(
    c: np.ndarray,
    motors: np.ndarray,
    q: tuple[float, float, float, float],
    v: tuple[float, float, float],
    w: tuple[float, float, float],
    thrust_cmd: float,
    rate: tuple[float, float, float],
) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    """:meth:`Quadrotor.world_wrench`: the rotation as Bullet's ``getMatrixFromQuaternion`` computes it."""
    x, y, z, qw = q
    s = 2.0 / (x * x + y * y + z * z + qw * qw)
    xs, ys, zs = x * s, y * s, z * s
    wx_, wy_, wz_ = qw * xs, qw * ys, qw * zs
    xx, xy, xz = x * xs, x * ys, x * zs
    yy, yz, zz = y * ys, y * zs, z * zs
    r0, r1, r2 = 1.0 - (yy + zz), xy - wz_, xz + wy_
    r3, r4, r5 = xy + wz_, 1.0 - (xx + zz), yz - wx_
    r6, r7, r8 = xz - wy_, yz + wx_, 1.0 - (xx + yy)
    vx, vy, vz = v
    ax, ay, az = w
    # Body rates and body velocity: Rᵀ ω, Rᵀ v.
    bwx, bwy, bwz = r0 * ax + r3 * ay + r6 * az, r1 * ax + r4 * ay + r7 * az, r2 * ax + r5 * ay + r8 * az
    bx, by, bz = r0 * vx + r3 * vy + r6 * vz, r1 * vx + r4 * vy + r7 * vz, r2 * vx + r5 * vy + r8 * vz
    thrust, tx, ty, tz = _actuate(c, motors, thrust_cmd, rate[0], rate[1], rate[2], bwx, bwy, bwz)
    # Quadratic drag opposing the body-frame velocity, plus the thrust along body z.
    fx, fy, fz = -c[_DRAG] * bx * abs(bx), -c[_DRAG + 1] * by * abs(by), -c[_DRAG + 2] * bz * abs(bz) + thrust
    force = (r0 * fx + r1 * fy + r2 * fz, r3 * fx + r4 * fy + r5 * fz, r6 * fx + r7 * fy + r8 * fz)
    torque = (r0 * tx + r1 * ty + r2 * tz, r3 * tx + r4 * ty + r5 * tz, r6 * tx + r7 * ty + r8 * tz)
    return force, torque
