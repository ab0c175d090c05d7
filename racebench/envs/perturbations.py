"""The robustness suite on ``RaceEnv``: the options that open a sim-to-real gap, and one registered id per gap.

:class:`Perturbations` holds one env's gaps (built from its options, each off at its default) and applies them: per
physics tick (command delay, wind), per control step (state-estimate error), per image (camera mount, stereo depth).
Its per-episode randomness (gusts, mount error, estimate error) comes from a generator seeded from the env's
``np_random`` after the scene is drawn, and only when such a gap is on: every id's scenes stay those of its main id,
seed for seed, and an env without gaps draws exactly what it drew before.

:data:`ROBUSTNESS` maps each perturbation of the suite (``RaceObs-<track>-<name>-v0``) to the options it sets on top
of the main id's; ``docs/robustness.md`` gives each magnitude's source.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from racebench.sim.camera import DepthCamera
from racebench.sim.disturbances import (
    CameraMount,
    CommandDelay,
    DrydenWind,
    EstimateNoise,
    StereoDepth,
    small_rotation,
)
from racebench.sim.quadrotor import QuadrotorParams
from racebench.utils.validation import check_real

DEPTH_MODELS: tuple[str, ...] = ("gaussian", "stereo")
MAX_COMMAND_DELAY = 0.5  # s
MAX_WIND_GUST_STD = 5.0  # m/s
MAX_CAMERA_TILT = 30.0  # degrees
MAX_STATE_NOISE = 10.0  # × the visual-inertial model

_NOMINAL = QuadrotorParams()
#: The suite: id suffix → the ``RaceEnv`` options it adds to the main id's (density 3, v_d 8 m/s).
ROBUSTNESS: dict[str, dict[str, Any]] = {
    "Latency": {"command_delay": 0.06},  # the authors' simulator
    "Latency30ms": {"command_delay": 0.03},  # half of it: where the 60 ms collapse begins
    "Control30Hz": {"control_freq": 30},  # the paper's onboard rate; physics stays at 200 Hz
    "DepthNoise": {"depth_model": "stereo"},  # D435i-like
    "Mass": {"quadrotor": {"mass": 1.2 * _NOMINAL.mass, "inertia": tuple(1.2 * i for i in _NOMINAL.inertia)}},
    "Thrust": {"quadrotor": {"max_thrust": 0.85 * _NOMINAL.max_thrust}},  # battery sag
    "Drag": {"quadrotor": {"drag_coefficients": tuple(2.0 * c for c in _NOMINAL.drag_coefficients)}},
    "Wind": {"wind_gust_std": 1.5},  # Dryden, light turbulence at 1.5 m
    "CameraTilt": {"camera_tilt": 5.0},
    "StateNoise": {"state_noise": 1.0},  # a visual-inertial estimate instead of motion capture
}


def quaternion_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The Hamilton product ``a ⊗ b`` of two (x, y, z, w) quaternions."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return np.array([
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
        aw * bw - ax * bx - ay * by - az * bz,
    ])  # fmt: skip


def rotation_quaternion(angles: np.ndarray) -> np.ndarray:
    """The (x, y, z, w) quaternion of the rotation vector ``angles`` (rad)."""
    theta = float(np.linalg.norm(angles))
    if theta < 1e-12:
        return np.array([0.0, 0.0, 0.0, 1.0])
    axis = np.asarray(angles, dtype=float) / theta
    return np.array([*(math.sin(theta / 2.0) * axis), math.cos(theta / 2.0)])


class Perturbations:
    """One env's sim-to-real gaps (all off at the defaults).

    Args:
        physics_freq: the env's physics rate, Hz (the delay must be a whole number of its ticks).
        command_delay: s from a command to the flight controller applying it, a multiple of ``1 / physics_freq``,
            0 … 0.5.
        wind_gust_std: horizontal gust standard deviation, m/s, 0 … 5 (:class:`~racebench.sim.disturbances.DrydenWind`).
        camera_tilt: the largest camera mounting error per axis, degrees, 0 … 30.
        state_noise: scale of the visual-inertial estimate error, 0 … 10
            (:class:`~racebench.sim.disturbances.EstimateNoise`).
        depth_model: ``"gaussian"`` (the camera's own noise on inverse depth) or ``"stereo"``
            (:class:`~racebench.sim.disturbances.StereoDepth`).
    """

    def __init__(
        self,
        physics_freq: int,
        command_delay: float = 0.0,
        wind_gust_std: float = 0.0,
        camera_tilt: float = 0.0,
        state_noise: float = 0.0,
        depth_model: str = "gaussian",
    ) -> None:
        check_real("command_delay", command_delay, 0.0, MAX_COMMAND_DELAY, unit="s")
        ticks = command_delay * physics_freq
        if abs(ticks - round(ticks)) > 1e-6:
            raise ValueError(f"command_delay must be a whole number of physics ticks (1/{physics_freq} s), got "
                             f"{command_delay!r}")  # fmt: skip
        check_real("wind_gust_std", wind_gust_std, 0.0, MAX_WIND_GUST_STD, unit="m/s")
        check_real("camera_tilt", camera_tilt, 0.0, MAX_CAMERA_TILT, unit="deg")
        check_real("state_noise", state_noise, 0.0, MAX_STATE_NOISE)
        if depth_model not in DEPTH_MODELS:
            raise ValueError(f"depth_model must be one of {DEPTH_MODELS}, got {depth_model!r}")
        self.delay = CommandDelay(int(round(ticks)))
        self.wind = DrydenWind(float(wind_gust_std))
        self.mount = CameraMount(float(camera_tilt))
        self.estimate = EstimateNoise(float(state_noise))
        self.stereo = StereoDepth() if depth_model == "stereo" else None
        #: whether the physics loop must call :meth:`tick` (else it runs as without perturbations)
        self.per_tick = self.delay.ticks > 0 or wind_gust_std > 0
        self._random = wind_gust_std > 0 or camera_tilt > 0 or state_noise > 0
        self.rng: np.random.Generator | None = None
        self.air = np.zeros(3)  # wind velocity, world frame, m/s
        self.mount_rotation: np.ndarray | None = None
        self.error = np.zeros(9)  # estimate error: position, velocity, attitude

    def reset(self, np_random: np.random.Generator, hover_thrust: float) -> None:
        """Start an episode: the delay line full of hover commands, this episode's gusts, mount and estimate error."""
        self.delay.reset(hover_thrust, (0.0, 0.0, 0.0))
        if not self._random:
            return
        self.rng = np.random.default_rng(int(np_random.integers(2**63)))
        self.air = self.wind.initial(self.rng) if self.wind.horizontal_std > 0 else np.zeros(3)
        self.mount_rotation = self.mount.draw(self.rng) if self.mount.max_error_deg > 0 else None
        self.error = self.estimate.initial(self.rng) if self.estimate.scale > 0 else np.zeros(9)

    def tick(
        self, thrust: float, rate: tuple[float, float, float], velocity: tuple[float, float, float], dt: float
    ) -> tuple[float, tuple[float, float, float], tuple[float, float, float]]:
        """One physics tick: the command applied now and the velocity relative to the air (what drag acts on)."""
        thrust, rate = self.delay.push(thrust, rate)
        if self.wind.horizontal_std > 0:
            self.air = self.wind.step(self.air, dt, self.rng)
            wx, wy, wz = self.air.tolist()
            velocity = (velocity[0] - wx, velocity[1] - wy, velocity[2] - wz)
        return thrust, rate, velocity

    def control_step(self, dt: float) -> None:
        """Advance the estimate error by one control step of ``dt`` s."""
        if self.estimate.scale > 0:
            self.error = self.estimate.step(self.error, dt, self.rng)

    def camera_rotation(self, rotation: np.ndarray) -> np.ndarray:
        """The camera's body→world rotation for a body at ``rotation``."""
        return rotation if self.mount_rotation is None else rotation @ self.mount_rotation

    def estimated(self, position, quaternion, rotation, velocity, angular_velocity) -> tuple[np.ndarray, ...]:
        """What the state estimate reports for the true state (the arguments): the same five arrays, with errors.

        Body rates stay exact: the angular velocity is re-expressed so that the estimated attitude maps it to the
        true body rates.
        """
        if self.estimate.scale == 0:
            return position, quaternion, rotation, velocity, angular_velocity
        e = self.error
        turn = small_rotation(e[6:9])
        rot = rotation @ turn
        quat = quaternion_multiply(quaternion, rotation_quaternion(e[6:9]))
        quat = -quat if quat[3] < 0 else quat
        ang = rot @ (rotation.T @ angular_velocity)
        return position + e[0:3], quat, rot, velocity + e[3:6], ang

    def normalise(self, camera: DepthCamera, depth: np.ndarray, np_random: np.random.Generator) -> np.ndarray:
        """The observed image for true metric depth: the camera's Gaussian model, or the stereo one's reading."""
        if self.stereo is None:
            return camera.normalise(depth, np_random)
        measured = self.stereo.measure(depth, camera.focal_px, np_random)
        inv = camera.min_depth / np.clip(measured, camera.min_depth, camera.max_depth)
        return np.clip(inv, 0.0, 1.0).astype(np.float32)[None]
