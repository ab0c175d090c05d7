"""Top views of scenes: gates, obstacles, start and racing line, several tracks side by side (docs/unseen-tracks.md).

``scripts/unseen_tracks_figure.py`` draws six held-out tracks (``RaceObs-Unseen-v0``, each with the obstacles of one
evaluation episode) into ``docs/figures/unseen-tracks.png``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from matplotlib.patches import Circle, Polygon

from racebench.reporting.figure_files import _checked, _save, plt
from racebench.sim.scene import Scene

GATE_COLOUR = "#e8590c"
OBSTACLE_COLOUR = "#5c5fc4"
LINE_COLOUR = "#868e96"


def _box_corners(x: float, y: float, half: Sequence[float], yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    local = np.array([[1, 1], [1, -1], [-1, -1], [-1, 1]]) * np.asarray(half[:2])
    return np.array([x, y]) + local @ np.array([[c, s], [-s, c]])


def draw_top_view(ax, scene: Scene, title: str | None = None) -> None:
    """Draw ``scene`` seen from above on ``ax``: gate frames (numbered, with an arrow along the flight direction),
    obstacle footprints, the start and the racing line through the gate centres."""
    track = scene.track
    centres = [g.center[:2] for g in scene.gates]
    line = [*centres, centres[0]] if track.closed_loop else [scene.start_position[:2], *centres]
    xs, ys = zip(*line, strict=True)
    ax.plot(xs, ys, color=LINE_COLOUR, lw=1.0, ls="--", zorder=1)
    for obstacle in scene.obstacles:
        x, y = obstacle.position[:2]
        if obstacle.kind == "cylinder":
            ax.add_patch(Circle((x, y), obstacle.size[0], color=OBSTACLE_COLOUR, zorder=2))
        else:
            ax.add_patch(Polygon(_box_corners(x, y, obstacle.size, obstacle.yaw), color=OBSTACLE_COLOUR, zorder=2))
    for i, gate in enumerate(scene.gates):
        half = gate.outer / 2.0 * gate.lateral[:2]
        a, b = gate.center[:2] - half, gate.center[:2] + half
        ax.plot([a[0], b[0]], [a[1], b[1]], color=GATE_COLOUR, lw=3.0, solid_capstyle="butt", zorder=3)
        tip = gate.center[:2] + 0.7 * gate.normal[:2]
        ax.annotate("", xy=tip, xytext=gate.center[:2], arrowprops={"arrowstyle": "->", "color": GATE_COLOUR}, zorder=3)
        ax.text(*(gate.center[:2] - 0.55 * gate.normal[:2]), str(i + 1), ha="center", va="center", fontsize=7, zorder=4)
    ax.plot(*scene.start_position[:2], marker="o", color="black", ms=4, zorder=4)
    ax.set_aspect("equal")
    ax.set_xlim(scene.arena_low[0], scene.arena_high[0])
    ax.set_ylim(scene.arena_low[1], scene.arena_high[1])
    ax.tick_params(labelsize=7)
    kind = "loop" if track.closed_loop else "sprint"
    ax.set_title(title or f"{track.name}: {kind}, {track.num_gates} gates", fontsize=9)


def plot_track_tops(
    scenes: Sequence[Scene], path: str | Path, titles: Sequence[str] | None = None, columns: int = 3, dpi: int = 150
) -> Path:
    """Top views of ``scenes`` in a grid of ``columns`` (one panel each) written to ``path`` (png, pdf or svg)."""
    if not scenes:
        raise ValueError("plot_track_tops needs at least one scene")
    if titles is not None and len(titles) != len(scenes):
        raise ValueError(f"got {len(titles)} titles for {len(scenes)} scenes")
    rows = math.ceil(len(scenes) / columns)
    fig, axes = plt.subplots(rows, columns, figsize=(3.6 * columns, 3.0 * rows), squeeze=False)
    path = _checked(path, fig, dpi)
    for k, ax in enumerate(axes.flat):
        if k < len(scenes):
            draw_top_view(ax, scenes[k], titles[k] if titles else None)
        else:
            ax.set_axis_off()
    return _save(fig, path, dpi)
