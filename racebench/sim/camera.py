"""Forward-looking depth camera rendered with PyBullet's ``getCameraImage`` (TinyRenderer).

The camera sits ``offset`` ahead of the body centre and looks along body x with body z up. PyBullet
returns a non-linear z-buffer ``b ∈ [0, 1]``; the metric depth along the optical axis is
``z = f n / (f − (f − n) b)`` for near/far planes ``n``/``f``. The observation is normalised inverse
depth ``d_min / clip(z, d_min, d_max)`` ∈ [d_min/d_max, 1] (1 = as close as the sensor sees, background
= d_min/d_max), plus optional Gaussian noise, clipped to [0, 1].
"""

from __future__ import annotations

import math

import numpy as np

from racebench.sim.bullet import p


class DepthCamera:
    """A pinhole depth camera with a square image.

    Args:
        size: image side in pixels (the paper: 64).
        fov_deg: horizontal (= vertical) field of view in degrees.
        min_depth, max_depth: sensor range in m; closer reads as ``min_depth``, farther as ``max_depth``.
        offset: camera position in the body frame, m.
        noise_std: standard deviation of Gaussian noise added to the normalised inverse depth.
    """

    def __init__(
        self,
        size: int = 64,
        fov_deg: float = 90.0,
        min_depth: float = 0.2,
        max_depth: float = 10.0,
        offset: tuple[float, float, float] = (0.1, 0.0, 0.0),
        noise_std: float = 0.0,
    ) -> None:
        if size < 1:
            raise ValueError(f"camera size must be >= 1, got {size}")
        if not 0 < fov_deg < 180:
            raise ValueError(f"camera fov_deg must be in (0, 180), got {fov_deg}")
        if not 0 < min_depth < max_depth:
            raise ValueError(f"need 0 < min_depth < max_depth, got {min_depth}, {max_depth}")
        if noise_std < 0:
            raise ValueError(f"depth noise_std must be >= 0, got {noise_std}")
        self.size = size
        self.fov_deg = fov_deg
        self.min_depth = min_depth
        self.max_depth = max_depth
        self.offset = np.asarray(offset, dtype=float)
        self.noise_std = noise_std
        # Render near plane below the sensor's minimum range so close surfaces are not clipped away.
        self.near = min(0.02, min_depth / 2.0)
        self.far = max_depth
        self.projection = p.computeProjectionMatrixFOV(fov_deg, 1.0, self.near, self.far)

    def pose(self, position: np.ndarray, rotation: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(eye, forward, up) in the world frame for a body at ``position`` with body→world ``rotation``."""
        return position + rotation @ self.offset, rotation[:, 0], rotation[:, 2]

    def depth(self, client, position: np.ndarray, rotation: np.ndarray) -> np.ndarray:
        """Metric depth along the optical axis, shape ``(size, size)``, float32, in [min, max] depth."""
        eye, forward, up = self.pose(position, rotation)
        view = client.computeViewMatrix(eye.tolist(), (eye + forward).tolist(), up.tolist())
        _, _, _, zbuf, _ = client.getCameraImage(
            self.size,
            self.size,
            viewMatrix=view,
            projectionMatrix=self.projection,
            shadow=0,
            renderer=p.ER_TINY_RENDERER,
            flags=p.ER_NO_SEGMENTATION_MASK,
        )
        b = np.asarray(zbuf, dtype=np.float64).reshape(self.size, self.size)
        z = self.far * self.near / (self.far - (self.far - self.near) * b)
        return np.clip(z, self.min_depth, self.max_depth).astype(np.float32)

    def normalise(self, depth: np.ndarray, np_random: np.random.Generator | None = None) -> np.ndarray:
        """Depth in metres → noisy normalised inverse depth in [0, 1], shape ``(1, size, size)``, float32."""
        inv = self.min_depth / depth
        if self.noise_std > 0 and np_random is not None:
            inv = inv + np_random.normal(0.0, self.noise_std, size=inv.shape)
        return np.clip(inv, 0.0, 1.0).astype(np.float32)[None]

    @property
    def focal_px(self) -> float:
        """Focal length in pixels."""
        return self.size / 2.0 / math.tan(math.radians(self.fov_deg) / 2.0)
