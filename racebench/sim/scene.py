"""The geometry of one episode as plain data: placed gates, obstacles, start pose and arena.

A :class:`Scene` is what the simulator builds, what the reward's distance-to-collision uses and what
other tools (plots, checkers, re-renderers) read from ``env.unwrapped.scene``. It converts to a
JSON-able dict and to a trimesh scene that exports as GLB/OBJ for any 3D viewer.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numba import njit

from racebench.sim.track import Gate, Track

ObstacleKind = Literal["cylinder", "box"]


@dataclass(frozen=True)
class Obstacle:
    """A static obstacle primitive standing on the ground.

    Attributes:
        kind: ``"cylinder"`` (vertical pole) or ``"box"``.
        position: centre of the primitive (world frame, m); ``z = height / 2`` for a grounded one.
        size: cylinder ``(radius, height)``; box ``(half_x, half_y, half_z)`` in its own frame.
        yaw: heading of a box about z (rad); ignored for cylinders.
    """

    kind: ObstacleKind
    position: np.ndarray
    size: tuple[float, ...]
    yaw: float = 0.0

    @property
    def height(self) -> float:
        """Full height of the primitive (m)."""
        return float(self.size[1]) if self.kind == "cylinder" else 2.0 * float(self.size[2])

    def xy_distance(self, points: np.ndarray) -> np.ndarray:
        """Horizontal distance from points ``(..., 2+)`` to the obstacle's footprint (0 inside)."""
        p = np.asarray(points, dtype=float)[..., :2] - self.position[:2]
        if self.kind == "cylinder":
            return np.maximum(np.linalg.norm(p, axis=-1) - self.size[0], 0.0)
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        local = np.stack([c * p[..., 0] + s * p[..., 1], -s * p[..., 0] + c * p[..., 1]], axis=-1)
        excess = np.maximum(np.abs(local) - np.asarray(self.size[:2]), 0.0)
        return np.linalg.norm(excess, axis=-1)

    def to_dict(self) -> dict[str, Any]:
        """Plain-data form (JSON-able)."""
        return {
            "kind": self.kind,
            "position": [float(v) for v in self.position],
            "size": [float(v) for v in self.size],
            "yaw": float(self.yaw),
        }


@dataclass(frozen=True)
class Scene:
    """Everything static in one episode, plus the start pose of the drone.

    Attributes:
        track: the track the scene was drawn from (gates before perturbation).
        gates: the gates as placed in this episode (possibly perturbed), in passing order.
        obstacles: obstacle primitives.
        start_position: initial drone position (m).
        start_yaw: initial drone heading (rad).
        arena_low, arena_high: corners of the flight volume; leaving it is a crash.
    """

    track: Track
    gates: tuple[Gate, ...]
    obstacles: tuple[Obstacle, ...]
    start_position: np.ndarray
    start_yaw: float
    arena_low: np.ndarray
    arena_high: np.ndarray

    def to_dict(self) -> dict[str, Any]:
        """Plain-data form (JSON-able): gates, obstacles, start and arena."""
        return {
            "track": self.track.name,
            "closed_loop": self.track.closed_loop,
            "gates": [
                {
                    "center": [float(v) for v in g.center],
                    "yaw": float(g.yaw),
                    "inner": g.inner,
                    "outer": g.outer,
                    "depth": g.depth,
                }
                for g in self.gates
            ],
            "obstacles": [o.to_dict() for o in self.obstacles],
            "start": {"position": [float(v) for v in self.start_position], "yaw": float(self.start_yaw)},
            "arena": {"low": [float(v) for v in self.arena_low], "high": [float(v) for v in self.arena_high]},
        }

    def boxes(self) -> list[tuple[np.ndarray, np.ndarray, float]]:
        """Every gate bar and box obstacle as a world-frame ``(centre, half_extents, yaw)`` box."""
        out = []
        for gate in self.gates:
            c, s = math.cos(gate.yaw), math.sin(gate.yaw)
            rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
            for centre, half in gate.bars():
                out.append((gate.center + rot @ centre, half, gate.yaw))
        for obs in self.obstacles:
            if obs.kind == "box":
                out.append((obs.position, np.asarray(obs.size, dtype=float), obs.yaw))
        return out

    def ahead(self, first_gate: int) -> Scene:
        """The scene from gate ``first_gate`` on, for planning the rest of a lap from mid-course: ``gates`` holds
        the gates still to pass, and the bars of the gates before it stay in the way as box obstacles (same
        geometry: :meth:`distance` is unchanged)."""
        passed = Scene(self.track, self.gates[:first_gate], (), self.start_position, self.start_yaw,
                       self.arena_low, self.arena_high)  # fmt: skip
        frames = tuple(
            Obstacle("box", centre, tuple(float(h) for h in half), yaw) for centre, half, yaw in passed.boxes()
        )
        return Scene(self.track, self.gates[first_gate:], frames + self.obstacles, self.start_position,
                     self.start_yaw, self.arena_low, self.arena_high)  # fmt: skip

    def cylinders(self) -> list[tuple[np.ndarray, float, float]]:
        """Every cylinder obstacle as ``(centre, radius, height)``."""
        return [(o.position, float(o.size[0]), float(o.size[1])) for o in self.obstacles if o.kind == "cylinder"]

    @cached_property
    def primitive_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """All gate bars and obstacles stacked as K rounded boxes: ``(centre, half, yaw, rounding)``.

        Shapes ``(K, 3)``, ``(K, 3)``, ``(K,)``, ``(K,)``. Each primitive is a box yawed about z with half
        extents ``half`` whose footprint is rounded (Minkowski sum with a disc) by ``rounding``: bars and box
        obstacles have rounding 0; a cylinder is a box of zero footprint rounded by its radius. Built once
        per scene; treat the arrays as read-only.
        """
        prims = [(c, h, yaw, 0.0) for c, h, yaw in self.boxes()]
        prims += [(c, np.array([0.0, 0.0, height / 2.0]), 0.0, r) for c, r, height in self.cylinders()]
        centre = np.array([p[0] for p in prims], dtype=float).reshape(-1, 3)
        half = np.array([p[1] for p in prims], dtype=float).reshape(-1, 3)
        yaw = np.array([p[2] for p in prims], dtype=float)
        rounding = np.array([p[3] for p in prims], dtype=float)
        return centre, half, yaw, rounding

    @cached_property
    def _distance_tables(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
        """:attr:`primitive_arrays` arranged for :meth:`distance` (``None`` when there are none).

        One ``(3, 3K)`` matrix maps world points to the local x, y and z of all K primitives at once, so
        a query is a single matmul plus a few element-wise operations (cheap for the per-step call).
        """
        centre, half, yaw, rounding = self.primitive_arrays
        k = len(rounding)
        if k == 0:
            return None
        cos, sin = np.cos(yaw), np.sin(yaw)
        to_local = np.zeros((3, 3 * k))
        to_local[0, :k], to_local[1, :k] = cos, sin  # local x
        to_local[0, k : 2 * k], to_local[1, k : 2 * k] = -sin, cos  # local y
        to_local[2, 2 * k :] = 1.0  # z is unrotated
        offset = np.concatenate(
            [cos * centre[:, 0] + sin * centre[:, 1], -sin * centre[:, 0] + cos * centre[:, 1], centre[:, 2]]
        )
        return to_local, offset, half.T.reshape(-1), rounding

    def distance(self, points: np.ndarray) -> np.ndarray:
        """Euclidean distance from points ``(..., 3)`` to the nearest gate bar or obstacle surface.

        Exact for the oriented boxes of :meth:`boxes` and the finite vertical cylinders of
        :meth:`cylinders`; 0 inside a solid; ``inf`` when the scene has no primitives. The ground and
        the arena walls are not included. Returns an array of shape ``points.shape[:-1]``.
        """
        pts = np.asarray(points, dtype=float)
        if pts.shape[-1:] != (3,):
            raise ValueError(f"points must have shape (..., 3), got {pts.shape}")
        tables = self._distance_tables
        if tables is None:
            return np.full(pts.shape[:-1], np.inf)
        flat = pts.reshape(-1, 3)
        out = np.empty(len(flat))
        chunk = 8192  # bounds the (chunk, 3K) temporaries for large grids
        for i in range(0, len(flat), chunk):
            out[i : i + chunk] = _rounded_box_distance(flat[i : i + chunk], *tables)
        return out.reshape(pts.shape[:-1])

    @cached_property
    def _point_tables(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        centre, half, yaw, rounding = self.primitive_arrays
        return (
            np.ascontiguousarray(centre),
            np.ascontiguousarray(half),
            np.cos(yaw),
            np.sin(yaw),
            np.ascontiguousarray(rounding),
        )

    def clearance(self, points: np.ndarray, low: np.ndarray, high: np.ndarray) -> np.ndarray:
        """Distance from points ``(M, 3)`` to the nearest primitive or face of the box ``[low, high]``.

        :meth:`distance` (same formula, compiled) combined with the distance to the walls of the volume, for
        the many small queries of path smoothing. A primitive is skipped when a lower bound of its distance
        (vertical gap, then footprint circle) is no better than the nearest so far, so the result is the
        same minimum up to rounding in the last bit. Negative outside the volume, NaN for a non-finite point.
        Not used where a layout is decided (the generator's
        and corridor search's grids use :meth:`distance`), so no scene depends on it.
        """
        pts = np.ascontiguousarray(points, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise ValueError(f"points must have shape (M, 3), got {pts.shape}")
        low, high = np.asarray(low, dtype=np.float64), np.asarray(high, dtype=np.float64)
        if low.shape != (3,) or high.shape != (3,):
            raise ValueError(f"low and high must have shape (3,), got {low.shape} and {high.shape}")
        return _clearance_batch(pts, *self._point_tables, self._footprint_reach, low, high)

    def clearance_tables(self) -> tuple[np.ndarray, ...]:
        """The arrays :meth:`clearance` hands its compiled kernel (``_clearance_batch``), for compiled callers
        that query clearances in a loop of their own (:func:`racebench.agents.planner.relax`)."""
        return (*self._point_tables, self._footprint_reach)

    @cached_property
    def _footprint_reach(self) -> np.ndarray:
        """Radius of each primitive's footprint circle about its centre (for :meth:`clearance`'s culling)."""
        _, half, _, _, rounding = self._point_tables
        return np.sqrt(half[:, 0] ** 2 + half[:, 1] ** 2) + rounding

    def point_distance(self, x: float, y: float, z: float) -> float:
        """:meth:`distance` of the single point ``(x, y, z)``, as a float.

        Compiled, for the reward at every env step: for one point the numpy version's call overhead (tens
        of µs) outweighs its work.
        """
        return _point_distance(float(x), float(y), float(z), *self._point_tables)

    def to_trimesh(self, ground: bool = True) -> Any:
        """The scene as a ``trimesh.Scene`` (gates, obstacles, optional ground, start marker)."""
        import trimesh

        scene = trimesh.Scene()
        for i, (centre, half, yaw) in enumerate(self.boxes()):
            transform = trimesh.transformations.rotation_matrix(yaw, [0, 0, 1])
            transform[:3, 3] = centre
            mesh = trimesh.creation.box(extents=2 * half, transform=transform)
            mesh.visual.face_colors = [230, 120, 20, 255] if i < 4 * len(self.gates) else [90, 90, 200, 255]
            scene.add_geometry(mesh, geom_name=f"box_{i}")
        for i, (centre, radius, height) in enumerate(self.cylinders()):
            transform = np.eye(4)
            transform[:3, 3] = centre
            mesh = trimesh.creation.cylinder(radius=radius, height=height, transform=transform)
            mesh.visual.face_colors = [90, 90, 200, 255]
            scene.add_geometry(mesh, geom_name=f"cylinder_{i}")
        if ground:
            size = self.arena_high - self.arena_low
            transform = np.eye(4)
            transform[:3, 3] = [*(self.arena_low[:2] + size[:2] / 2), -0.005]
            mesh = trimesh.creation.box(extents=[size[0], size[1], 0.01], transform=transform)
            mesh.visual.face_colors = [200, 200, 200, 255]
            scene.add_geometry(mesh, geom_name="ground")
        marker = trimesh.creation.icosphere(radius=0.1)
        marker.apply_translation(self.start_position)
        marker.visual.face_colors = [20, 180, 20, 255]
        scene.add_geometry(marker, geom_name="start")
        return scene

    def export(self, path: str | Path) -> Path:
        """Write the scene as a mesh file; the format follows the suffix (``.glb``, ``.obj``, ...)."""
        path = Path(path)
        self.to_trimesh().export(str(path))
        return path


def arena_bounds(track: Track, margin: float = 3.0, headroom: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """The flight volume of a track: gates and start widened by ``margin`` on x/y, floor to top + headroom."""
    points = np.array([g.center for g in track.gates] + [track.start.center])
    low = points.min(axis=0) - margin
    high = points.max(axis=0) + margin
    low[2] = 0.0
    high[2] = points[:, 2].max() + max(g.outer for g in track.gates) / 2.0 + headroom
    return low, high


def _rounded_box_distance(
    points: np.ndarray, to_local: np.ndarray, offset: np.ndarray, half: np.ndarray, rounding: np.ndarray
) -> np.ndarray:
    """Distance from points ``(M, 3)`` to the nearest of the stacked primitives of ``Scene._distance_tables``."""
    k = len(rounding)
    excess = np.abs(points @ to_local - offset)
    excess -= half
    np.maximum(excess, 0.0, out=excess)
    excess *= excess
    horizontal = np.sqrt(excess[:, :k] + excess[:, k : 2 * k])
    horizontal -= rounding
    np.maximum(horizontal, 0.0, out=horizontal)
    horizontal *= horizontal
    horizontal += excess[:, 2 * k :]
    return np.sqrt(horizontal.min(axis=1))


@njit(cache=True)
def _point_distance(
    x: float,
    y: float,
    z: float,
    centre: np.ndarray,
    half: np.ndarray,
    cos: np.ndarray,
    sin: np.ndarray,
    rounding: np.ndarray,
) -> float:
    """The formula of :func:`_rounded_box_distance` for a single point (``inf`` without primitives)."""
    best = np.inf
    for k in range(len(rounding)):
        lx = abs(cos[k] * (x - centre[k, 0]) + sin[k] * (y - centre[k, 1])) - half[k, 0]
        ly = abs(-sin[k] * (x - centre[k, 0]) + cos[k] * (y - centre[k, 1])) - half[k, 1]
        lz = abs(z - centre[k, 2]) - half[k, 2]
        lx, ly, lz = max(lx, 0.0), max(ly, 0.0), max(lz, 0.0)
        horizontal = max(math.sqrt(lx * lx + ly * ly) - rounding[k], 0.0)
        best = min(best, horizontal * horizontal + lz * lz)
    return math.sqrt(best)


@njit(cache=True)
def _clearance_batch(
    points: np.ndarray,
    centre: np.ndarray,
    half: np.ndarray,
    cos: np.ndarray,
    sin: np.ndarray,
    rounding: np.ndarray,
    reach: np.ndarray,
    low: np.ndarray,
    high: np.ndarray,
) -> np.ndarray:
    """:meth:`Scene.clearance`: per point, the walls' distance, then :func:`_point_distance`'s formula over
    the primitives whose lower bound can still beat the best so far (squared distances throughout)."""
    out = np.empty(len(points))
    for i in range(len(points)):
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
            out[i] = math.nan  # min() below would drop a NaN depending on the order of its arguments
            continue
        wall = min(x - low[0], y - low[1], z - low[2], high[0] - x, high[1] - y, high[2] - z)
        if wall <= 0.0:
            out[i] = wall
            continue
        best = wall * wall
        for k in range(len(rounding)):
            dx, dy = x - centre[k, 0], y - centre[k, 1]
            lz = max(abs(z - centre[k, 2]) - half[k, 2], 0.0)
            lz2 = lz * lz
            if lz2 >= best:
                continue
            gap = math.sqrt(dx * dx + dy * dy) - reach[k]
            if gap > 0.0 and gap * gap + lz2 >= best:
                continue
            lx = max(abs(cos[k] * dx + sin[k] * dy) - half[k, 0], 0.0)
            ly = max(abs(-sin[k] * dx + cos[k] * dy) - half[k, 1], 0.0)
            horizontal = max(math.sqrt(lx * lx + ly * ly) - rounding[k], 0.0)
            best = min(best, horizontal * horizontal + lz2)
        out[i] = math.sqrt(best)
    return out
