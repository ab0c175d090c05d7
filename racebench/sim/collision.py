"""Crash detection from the scene's exact geometry: every touch is a crash.

**The rule.** The drone is a sphere of radius ``QuadrotorParams.collision_radius`` whose centre moves along
a straight segment in each physics substep. The episode ends in a crash at the first substep whose swept
sphere comes within :data:`CONTACT_TOLERANCE` of a gate bar, an obstacle or the ground (the plane
``z = 0``), measured by the exact distances of :class:`~racebench.sim.scene.Scene` (oriented boxes, finite
vertical cylinders). PyBullet's contact report plays no part: Bullet resolves hits at a small positive
distance and let the drone bounce on without a reported contact, so the drone has no collision response
in the simulation at all (its collision filter is off) and the outcome is decided here, from geometry
anyone can check.

**The sweep.** The distance ``D`` to the nearest surface is 1-Lipschitz, so on a segment ``a → b`` of length
``L`` no point is closer than ``(D(a) + D(b) − L) / 2``. A segment whose bound clears the threshold is
clear; otherwise it is bisected, left half first (so the first touch along the path is found), until a
point within the threshold is found or the piece is shorter than :data:`SWEEP_RESOLUTION`, which then
counts as a touch. So a path that comes within the tolerance is always caught, and a path is flagged at
most ``SWEEP_RESOLUTION / 2`` beyond it.

``crash_reason`` names what was touched: ``"gate:<i>"`` / ``"obstacle:<j>"`` (indices into ``scene.gates`` /
``scene.obstacles``), ``"ground"``, or ``"out_of_bounds"`` when the centre leaves the arena.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from racebench.sim.scene import Scene

CONTACT_TOLERANCE = 1e-3  # m: a sphere this close to a surface touches it
SWEEP_RESOLUTION = 1e-4  # m: shortest piece of a substep's path the sweep resolves
_GROUND = -1
_CLEAR = -2


class CollisionChecker:
    """Swept-sphere contact test of one scene (see the module docstring).

    Args:
        scene: the episode's geometry.
        radius: the drone's collision radius (m).
        tolerance: contact tolerance (m).
    """

    def __init__(self, scene: Scene, radius: float, tolerance: float = CONTACT_TOLERANCE) -> None:
        if not (math.isfinite(radius) and radius > 0.0):
            raise ValueError(f"radius must be a finite positive number, got {radius!r}")
        if not (math.isfinite(tolerance) and tolerance >= 0.0):
            raise ValueError(f"tolerance must be finite and >= 0, got {tolerance!r}")
        centre, half, yaw, rounding = scene.primitive_arrays
        # One (K, 9) table (centre, half extents, cos yaw, sin yaw, rounding): a single array argument keeps
        # the compiled call's dispatch cost low, which matters at every physics substep.
        self._table = np.ascontiguousarray(
            np.column_stack([centre, half, np.cos(yaw), np.sin(yaw), rounding]).reshape(-1, 9)
        )
        self.radius = float(radius)
        self.tolerance = float(tolerance)
        self.threshold = self.radius + self.tolerance
        # Owner of each primitive, in Scene.primitive_arrays order: gate bars (4 per gate), box obstacles,
        # then cylinder obstacles.
        names = [f"gate:{i}" for i in range(len(scene.gates)) for _ in range(4)]
        names += [f"obstacle:{j}" for j, o in enumerate(scene.obstacles) if o.kind == "box"]
        names += [f"obstacle:{j}" for j, o in enumerate(scene.obstacles) if o.kind == "cylinder"]
        if len(names) != len(self._table):
            raise AssertionError("scene primitives and their owners disagree")
        self.owners = names

    def contact(self, p0: tuple[float, float, float], p1: tuple[float, float, float]) -> str | None:
        """What the sphere swept from ``p0`` to ``p1`` touches first (``"gate:2"``, ``"ground"``, ...), or ``None``."""
        hit = _swept_contact(p0[0], p0[1], p0[2], p1[0], p1[1], p1[2], self.threshold, SWEEP_RESOLUTION, self._table)
        if hit == _CLEAR:
            return None
        return "ground" if hit == _GROUND else self.owners[hit]

    def clearance(self, point: tuple[float, float, float]) -> float:
        """Gap between the sphere at ``point`` and the nearest surface, ground included (negative: overlap)."""
        d, _ = _nearest(float(point[0]), float(point[1]), float(point[2]), self._table)
        return d - self.radius


@njit(cache=True)
def _nearest(x: float, y: float, z: float, table: np.ndarray) -> tuple[float, int]:
    """Distance from a point to the nearest surface (ground plane included) and which one (-1: ground)."""
    ground = max(z, 0.0)
    best = ground * ground
    which = _GROUND
    for k in range(table.shape[0]):
        cx, cy, cz, hx, hy, hz, cos, sin, rounding = table[k]
        lx = abs(cos * (x - cx) + sin * (y - cy)) - hx
        ly = abs(-sin * (x - cx) + cos * (y - cy)) - hy
        lz = abs(z - cz) - hz
        lx, ly, lz = max(lx, 0.0), max(ly, 0.0), max(lz, 0.0)
        horizontal = max(math.sqrt(lx * lx + ly * ly) - rounding, 0.0)
        d2 = horizontal * horizontal + lz * lz
        if d2 < best:
            best = d2
            which = k
    return math.sqrt(best), which


@njit(cache=True)
def _swept_contact(
    x0: float, y0: float, z0: float, x1: float, y1: float, z1: float, threshold: float, resolution: float,
    table: np.ndarray,
) -> int:  # fmt: skip
    """First primitive (-1: ground) the swept sphere touches along ``p0 → p1``, or -2 (clear)."""
    d0, k0 = _nearest(x0, y0, z0, table)
    if d0 <= threshold:
        return k0
    d1, k1 = _nearest(x1, y1, z1, table)
    dx, dy, dz = x1 - x0, y1 - y0, z1 - z0
    length = math.sqrt(dx * dx + dy * dy + dz * dz)
    # Depth-first over pieces [t_a, t_b] of the segment, left piece first: the first touch along the path.
    stack_t = np.empty((64, 2))
    stack_d = np.empty((64, 2))
    stack_k = np.empty((64, 2), dtype=np.int64)
    stack_t[0, 0], stack_t[0, 1] = 0.0, 1.0
    stack_d[0, 0], stack_d[0, 1] = d0, d1
    stack_k[0, 0], stack_k[0, 1] = k0, k1
    top = 1
    while top > 0:
        top -= 1
        ta, tb = stack_t[top, 0], stack_t[top, 1]
        da, db = stack_d[top, 0], stack_d[top, 1]
        ka, kb = stack_k[top, 0], stack_k[top, 1]
        piece = (tb - ta) * length
        if 0.5 * (da + db - piece) > threshold:
            continue  # Lipschitz bound: nothing on this piece comes within the threshold
        if piece <= resolution or top >= 62:
            return ka if da <= db else kb
        tm = 0.5 * (ta + tb)
        dm, km = _nearest(x0 + dx * tm, y0 + dy * tm, z0 + dz * tm, table)
        if dm <= threshold:
            # The left piece may touch earlier: search it first, else this midpoint is the first touch.
            if 0.5 * (da + dm - (tm - ta) * length) > threshold:
                return km
            stack_t[top, 0], stack_t[top, 1] = ta, tm
            stack_d[top, 0], stack_d[top, 1] = da, dm
            stack_k[top, 0], stack_k[top, 1] = ka, km
            top += 1
            continue
        stack_t[top, 0], stack_t[top, 1] = tm, tb  # right piece, searched after the left one
        stack_d[top, 0], stack_d[top, 1] = dm, db
        stack_k[top, 0], stack_k[top, 1] = km, kb
        stack_t[top + 1, 0], stack_t[top + 1, 1] = ta, tm
        stack_d[top + 1, 0], stack_d[top + 1, 1] = da, dm
        stack_k[top + 1, 0], stack_k[top + 1, 1] = ka, km
        top += 2
    if d1 <= threshold:
        return k1
    return _CLEAR
