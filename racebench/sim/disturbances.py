"""The sim-to-real gaps of the robustness suite, as simulator parts: command delay, wind, stereo depth, camera mount and
state-estimate noise.

Each part is plain numpy, owns no randomness of its own (a ``numpy.random.Generator`` is passed in) and is off at its
default. Where each magnitude comes from: ``docs/robustness.md``.

* :class:`CommandDelay`: the flight controller applies each command a fixed number of physics ticks late (the authors'
  simulator: 60 ms). Before the first command arrives it applies the hover command, as the authors' does.
* :class:`DrydenWind`: gusts from first-order Gauss–Markov processes with the Dryden low-altitude model's
  intensities and length scales (MIL-F-8785C), frozen at a reference airspeed so that the wind does not depend on how
  the policy flies. Drag acts on the air-relative velocity.
* :class:`StereoDepth`: an active-stereo depth camera in the spirit of the Intel RealSense D435i: noise growing with
  the square of range, occlusion shadows beside depth edges, random dropouts and the sensor's range limits.
* :class:`CameraMount`: the camera mounted a few degrees off the body axes, fixed for an episode.
* :class:`EstimateNoise`: position, velocity and attitude errors of a visual-inertial estimator rather than motion
  capture, as slowly varying (Gauss–Markov) errors.
"""

from __future__ import annotations

import collections
import math
from dataclasses import dataclass

import numpy as np

FEET_PER_M = 1.0 / 0.3048


def gauss_markov_step(value: np.ndarray, sigma: np.ndarray, tau: np.ndarray, dt: float, rng: np.random.Generator):
    """One exact step of a stationary first-order Gauss–Markov (Ornstein–Uhlenbeck) process: ``φ x + σ √(1 − φ²) ε``
    with ``φ = exp(−dt/τ)``, so its standard deviation stays ``σ`` and its autocorrelation is ``exp(−|t|/τ)``."""
    phi = np.exp(-dt / tau)
    return phi * value + sigma * np.sqrt(1.0 - phi * phi) * rng.standard_normal(value.shape)


class CommandDelay:
    """A first-in first-out line of ``ticks`` commands: each physics tick applies the command of ``ticks`` ticks ago.

    Args:
        ticks: the delay in physics ticks (0: none).
    """

    def __init__(self, ticks: int) -> None:
        if ticks < 0:
            raise ValueError(f"command delay must be >= 0 ticks, got {ticks}")
        self.ticks = ticks
        self._line: collections.deque = collections.deque(maxlen=max(ticks, 1))

    def reset(self, thrust: float, rate: tuple[float, float, float]) -> None:
        """Fill the line with ``(thrust, rate)``: what is applied until the first real command arrives."""
        self._line.clear()
        self._line.extend([(thrust, rate)] * self.ticks)

    def push(self, thrust: float, rate: tuple[float, float, float]) -> tuple[float, tuple[float, float, float]]:
        """Send ``(thrust, rate)`` now; return the command the controller applies on this tick."""
        if self.ticks == 0:
            return thrust, rate
        applied = self._line[0]
        self._line.append((thrust, rate))  # the deque's maxlen drops the applied one
        return applied


@dataclass(frozen=True)
class DrydenWind:
    """Turbulence of the Dryden low-altitude model (MIL-F-8785C), in first-order form, per world axis.

    At altitude ``h`` (ft), ``σ_w = 0.1 W20`` and ``σ_u = σ_v = σ_w / (0.177 + 0.000823 h)^0.4``; the length scales are
    ``L_w = h`` and ``L_u = L_v = h / (0.177 + 0.000823 h)^1.2``, and a process of length ``L`` seen at airspeed ``V``
    has the time constant ``τ = L / V``. Each world axis is a first-order Gauss–Markov process (the Dryden spectrum
    of the longitudinal gust, used for all three), clipped at ``clip`` standard deviations so that the wind's force is
    bounded (the lap-time bound needs it).

    Args:
        horizontal_std: ``σ_u = σ_v``, m/s (0: no wind).
        altitude: m, where the turbulence is evaluated (the gates' height).
        airspeed: m/s, the reference speed that turns length scales into time constants.
        clip: the largest gust, in standard deviations.
    """

    horizontal_std: float = 0.0
    altitude: float = 1.5
    airspeed: float = 6.0
    clip: float = 3.0

    @property
    def _shape(self) -> float:
        return 0.177 + 0.000823 * self.altitude * FEET_PER_M

    @property
    def std(self) -> np.ndarray:
        """Per world axis (x, y, z), m/s."""
        vertical = self.horizontal_std * self._shape**0.4
        return np.array([self.horizontal_std, self.horizontal_std, vertical])

    @property
    def time_constants(self) -> np.ndarray:
        """Per world axis (x, y, z), s."""
        vertical = self.altitude / self.airspeed
        horizontal = self.altitude / self._shape**1.2 / self.airspeed
        return np.array([horizontal, horizontal, vertical])

    @property
    def max_speed(self) -> float:
        """The largest wind speed the clipped process can reach, m/s."""
        return float(np.linalg.norm(self.clip * self.std))

    def initial(self, rng: np.random.Generator) -> np.ndarray:
        """A draw from the stationary distribution (an episode starts in turbulence already)."""
        return np.clip(self.std * rng.standard_normal(3), -self.clip * self.std, self.clip * self.std)

    def step(self, wind: np.ndarray, dt: float, rng: np.random.Generator) -> np.ndarray:
        """The wind ``dt`` later."""
        new = gauss_markov_step(wind, self.std, self.time_constants, dt, rng)
        return np.clip(new, -self.clip * self.std, self.clip * self.std)


@dataclass(frozen=True)
class StereoDepth:
    """An active-stereo depth camera: the metric depth it reports, with holes, for a true depth image.

    * noise: Gaussian, ``σ_z = relative_rms · z_ref · (z / z_ref)²`` (stereo depth error grows with the square of
      range; the D435i's datasheet: at most 2 % RMS at 2 m);
    * occlusion shadows: the left imager is the reference, so the background just left of a nearer surface is seen
      by one imager only. That band is ``f · B · (1/z_near − 1/z_far)`` pixels wide (focal length ``f`` in pixels of
      this image, baseline ``B``); the background pixel next to the edge is lost with that probability (capped at 1);
    * dropouts: a fraction of pixels with no match at all, drawn independently;
    * range: nothing is reported nearer than ``min_range`` or at or beyond ``max_range``.

    A pixel with no depth reads ``max_range``, as a depth pipeline that fills its holes with "far" passes it on.

    Args:
        relative_rms: RMS depth error at ``reference_range``, as a fraction of it.
        reference_range: m.
        baseline: the imagers' distance, m.
        dropout: the fraction of pixels lost at random.
        min_range, max_range: m.
    """

    relative_rms: float = 0.02
    reference_range: float = 2.0
    baseline: float = 0.05
    dropout: float = 0.03
    min_range: float = 0.28
    max_range: float = 10.0

    def sigma(self, depth: np.ndarray) -> np.ndarray:
        """The noise's standard deviation at ``depth``, m."""
        return self.relative_rms * self.reference_range * (depth / self.reference_range) ** 2

    def shadow_width(self, depth: np.ndarray, focal_px: float) -> np.ndarray:
        """Width in pixels of the occlusion shadow left of each pixel: ``f B (1/z(c+1) − 1/z(c))`` where the pixel
        to the right is nearer, else 0; shape ``(rows, cols)``, last column 0."""
        width = np.zeros_like(depth, dtype=np.float64)
        width[:, :-1] = focal_px * self.baseline * (1.0 / depth[:, 1:] - 1.0 / depth[:, :-1])
        return np.maximum(width, 0.0)

    def measure(self, depth: np.ndarray, focal_px: float, rng: np.random.Generator) -> np.ndarray:
        """The reported depth (m, float64) for true metric depth ``depth`` of shape ``(rows, cols)``."""
        depth = np.asarray(depth, dtype=np.float64)
        shadow = rng.random(depth.shape) < np.minimum(self.shadow_width(depth, focal_px), 1.0)
        lost = shadow | (rng.random(depth.shape) < self.dropout)
        lost |= (depth < self.min_range) | (depth >= self.max_range)
        measured = depth + self.sigma(depth) * rng.standard_normal(depth.shape)
        return np.where(lost, self.max_range, measured)


def small_rotation(angles: np.ndarray) -> np.ndarray:
    """The rotation matrix of the rotation vector ``angles`` (rad), by Rodrigues' formula."""
    theta = float(np.linalg.norm(angles))
    if theta < 1e-12:
        return np.eye(3)
    k = np.asarray(angles, dtype=float) / theta
    skew = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(theta) * skew + (1.0 - math.cos(theta)) * skew @ skew


def euler_rotation(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """``Rz(yaw) Ry(pitch) Rx(roll)``."""
    cr, sr, cp, sp, cy, sy = (math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch), math.cos(yaw),
                              math.sin(yaw))  # fmt: skip
    return np.array([
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ])  # fmt: skip


@dataclass(frozen=True)
class CameraMount:
    """A camera mounting error: roll, pitch and yaw each uniform in ``±max_error_deg``, drawn once per episode.

    The camera's rotation is the body's times the mount's (body → camera-body), so the image is the one a camera
    turned by that error would see.
    """

    max_error_deg: float = 0.0

    def draw(self, rng: np.random.Generator) -> np.ndarray:
        """One episode's mount rotation (3×3)."""
        roll, pitch, yaw = np.radians(rng.uniform(-self.max_error_deg, self.max_error_deg, size=3))
        return euler_rotation(roll, pitch, yaw)


@dataclass(frozen=True)
class EstimateNoise:
    """The errors of a visual-inertial state estimate, per axis, as first-order Gauss–Markov processes.

    ``scale`` multiplies every standard deviation (0: the exact state, as motion capture gives). At 1: position
    0.10 m (τ 2 s: drift that the estimator corrects slowly), velocity 0.10 m/s (τ 0.5 s), attitude 1° per axis
    (τ 1 s). Body rates come from the gyroscope in either case and stay exact.
    """

    scale: float = 0.0
    position_std: float = 0.10
    position_tau: float = 2.0
    velocity_std: float = 0.10
    velocity_tau: float = 0.5
    attitude_std: float = math.radians(1.0)
    attitude_tau: float = 1.0

    @property
    def std(self) -> np.ndarray:
        """Standard deviations of the 9 error states: position (m), velocity (m/s), attitude (rad), 3 axes each."""
        per = (self.position_std, self.velocity_std, self.attitude_std)
        return self.scale * np.repeat(np.array(per), 3)

    @property
    def time_constants(self) -> np.ndarray:
        """Time constants of the 9 error states, s."""
        return np.repeat(np.array((self.position_tau, self.velocity_tau, self.attitude_tau)), 3)

    def initial(self, rng: np.random.Generator) -> np.ndarray:
        """The error at the start of an episode, from the stationary distribution."""
        return self.std * rng.standard_normal(9)

    def step(self, error: np.ndarray, dt: float, rng: np.random.Generator) -> np.ndarray:
        """The error ``dt`` later."""
        return gauss_markov_step(error, self.std, self.time_constants, dt, rng)
