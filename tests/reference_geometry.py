"""An independent sphere-to-scene distance, written from first principles for checking the crash detector.

It shares no code with :mod:`racebench.sim.scene` or :mod:`racebench.sim.collision`: gate bars are rebuilt from the
gate's inner/outer size and depth, boxes are measured by clamping in their own frame, cylinders by radial
and vertical excess. Vectorised over many points (the contact scan checks every physics substep).
"""

from __future__ import annotations

import numpy as np


def _box_distance(points: np.ndarray, centre: np.ndarray, half: np.ndarray, yaw: float) -> np.ndarray:
    """Distance from points (N, 3) to a solid box yawed about z (0 inside)."""
    c, s = np.cos(yaw), np.sin(yaw)
    rel = points - centre
    local = np.stack([c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1], rel[:, 2]], axis=1)
    nearest = np.clip(local, -half, half)
    return np.linalg.norm(local - nearest, axis=1)


def _cylinder_distance(points: np.ndarray, centre: np.ndarray, radius: float, height: float) -> np.ndarray:
    """Distance from points (N, 3) to a solid vertical cylinder (0 inside)."""
    radial = np.maximum(np.hypot(points[:, 0] - centre[0], points[:, 1] - centre[1]) - radius, 0.0)
    vertical = np.maximum(np.abs(points[:, 2] - centre[2]) - height / 2.0, 0.0)
    return np.hypot(radial, vertical)


def gate_bars(center: np.ndarray, yaw: float, inner: float, outer: float, depth: float) -> list[tuple]:
    """The four bars of a square gate frame as world-frame ``(centre, half_extents, yaw)`` boxes."""
    width = (outer - inner) / 2.0
    offset = inner / 2.0 + width / 2.0
    lateral = np.array([-np.sin(yaw), np.cos(yaw), 0.0])
    up = np.array([0.0, 0.0, 1.0])
    horizontal_half = np.array([depth / 2.0, outer / 2.0, width / 2.0])
    vertical_half = np.array([depth / 2.0, width / 2.0, inner / 2.0])
    return [
        (center + offset * up, horizontal_half, yaw),
        (center - offset * up, horizontal_half, yaw),
        (center + offset * lateral, vertical_half, yaw),
        (center - offset * lateral, vertical_half, yaw),
    ]


def surface_distances(scene: dict, points: np.ndarray) -> dict[str, np.ndarray]:
    """Distance from points (N, 3) to each gate, each obstacle and the ground of a scene given as its dict.

    Keys: ``"gate:<i>"``, ``"obstacle:<j>"``, ``"ground"``; values of shape (N,).
    """
    points = np.atleast_2d(np.asarray(points, dtype=float))
    out: dict[str, np.ndarray] = {"ground": np.maximum(points[:, 2], 0.0)}
    for i, gate in enumerate(scene["gates"]):
        bars = gate_bars(np.array(gate["center"]), gate["yaw"], gate["inner"], gate["outer"], gate["depth"])
        out[f"gate:{i}"] = np.min([_box_distance(points, c, h, y) for c, h, y in bars], axis=0)
    for j, obstacle in enumerate(scene["obstacles"]):
        centre, size = np.array(obstacle["position"]), obstacle["size"]
        if obstacle["kind"] == "cylinder":
            out[f"obstacle:{j}"] = _cylinder_distance(points, centre, size[0], size[1])
        else:
            out[f"obstacle:{j}"] = _box_distance(points, centre, np.array(size), obstacle["yaw"])
    return out


def nearest_surface(scene: dict, points: np.ndarray) -> tuple[np.ndarray, list[str]]:
    """Distance to the nearest surface and its name, per point."""
    distances = surface_distances(scene, points)
    names = list(distances)
    stacked = np.stack([distances[n] for n in names])
    which = stacked.argmin(axis=0)
    return stacked.min(axis=0), [names[k] for k in which]
