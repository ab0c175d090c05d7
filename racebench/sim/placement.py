"""How close obstacles stand to the racing line: the paper's meaning of obstacle density, measured.

The paper counts "obstacles affecting flight" per two gates. Two generators with the same count can differ in how
many of those obstacles stand on the racing line, so racebench matches the *share* near the line to the authors'
released scenes, measured the same way on both (``../shared/reference/authors-code-facts.md`` §2.3):

* the racing line is the polyline of the track's legs in 2D: the start, then every gate centre in order (a sprint:
  S, J), or the closed loop of the gate centres (Circle), with the track's own, unshifted gates;
* an obstacle's distance is from its vertical axis (its footprint centre) to the nearest leg;
* a fraction is the share of all obstacles, pooled over the scenes, within the radius.

Small pure functions; :func:`centreline_fractions` is what ``tests/test_placement.py`` holds to within
:data:`TOLERANCE` of :data:`AUTHORS_FRACTIONS` on every track.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np

from racebench.sim.scene import Scene
from racebench.sim.track import Track

#: Radii (m) at which the share of obstacles near the racing line is matched (the issue's 0.5 and 1.0 m).
MATCHED_RADII: tuple[float, ...] = (0.5, 1.0)
#: Largest allowed difference between racebench's fraction and the authors' at a matched radius.
TOLERANCE = 0.05
#: The authors' measured fractions of obstacles whose axis is within 0.25 / 0.5 / 1.0 m of the racing line
#: (``authors-code-facts.md`` §2.3): S ``demo1_songjiang`` (10,000 scenes, 9 trees), Circle ``demo2_songjiang``
#: files 1-5000 (12 trees), J ``demo3_songjiang`` on the J path (4,991 scenes, 12 trees).
AUTHORS_FRACTIONS: dict[str, dict[float, float]] = {
    "S": {0.25: 0.130, 0.5: 0.258, 1.0: 0.516},
    "Circle": {0.25: 0.177, 0.5: 0.351, 1.0: 0.636},
    "J": {0.25: 0.127, 0.5: 0.265, 1.0: 0.468},
}


def racing_line(track: Track) -> np.ndarray:
    """The legs of ``track``'s racing line as 2D segments ``(n, 2, 2)``: start → gates (sprint), gate loop (closed)."""
    centres = [g.center[:2] for g in track.gates]
    points = [*centres, centres[0]] if track.closed_loop else [track.start.center[:2], *centres]
    return np.array([[points[i], points[i + 1]] for i in range(len(points) - 1)], dtype=float)


def distance_to_line(xy: np.ndarray, legs: np.ndarray) -> np.ndarray:
    """Horizontal distance ``(n,)`` from each point of ``xy`` ``(n, 2)`` to the nearest segment of ``legs``."""
    a, b = legs[None, :, 0], legs[None, :, 1]
    d = b - a
    t = np.clip(np.einsum("nkj,nkj->nk", xy[:, None] - a, d) / np.einsum("nkj,nkj->nk", d, d), 0.0, 1.0)
    closest = a + t[..., None] * d
    return np.linalg.norm(xy[:, None] - closest, axis=-1).min(axis=1)


def obstacle_line_distances(scenes: Iterable[Scene], track: Track) -> np.ndarray:
    """Every obstacle's axis distance to ``track``'s racing line, pooled over ``scenes``."""
    legs = racing_line(track)
    xy = [np.array([o.position[:2] for o in scene.obstacles]) for scene in scenes if scene.obstacles]
    if not xy:
        return np.zeros(0)
    return distance_to_line(np.concatenate(xy), legs)


def centreline_fractions(distances: np.ndarray, radii: Sequence[float] = (0.25, 0.5, 1.0)) -> dict[float, float]:
    """Share of ``distances`` at most each radius (``nan`` where there are none)."""
    if len(distances) == 0:
        return {r: float("nan") for r in radii}
    return {r: float(np.mean(distances <= r)) for r in radii}
