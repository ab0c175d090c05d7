"""The paper's Fig. 4: a track in 3D with its gates, obstacles and flown paths; and one episode's video."""

from __future__ import annotations

import logging
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")  # files only; never needs a display
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402
from matplotlib.patches import Patch  # noqa: E402
from matplotlib.ticker import MaxNLocator  # noqa: E402
from matplotlib.transforms import Bbox  # noqa: E402

from racebench.evaluation.records import read_trajectories  # noqa: E402
from racebench.reporting.figure_files import DEFAULT_DPI, _save  # noqa: E402
from racebench.reporting.video import render_episode_video  # noqa: E402

#: Colours of the agents' flights in the track figure when it shows several agents (none is the gates' orange,
#: the obstacles' blue or the start's green).
logger = logging.getLogger("racebench.reporting.plots")
_AGENT_COLOURS = ("tab:red", "tab:purple", "tab:brown", "tab:pink", "tab:olive", "tab:cyan", "tab:gray", "black")


def _draw_scene(ax, scene: dict) -> None:
    for gate in scene["gates"]:
        c = np.array(gate["center"])
        n = np.array([np.cos(gate["yaw"]), np.sin(gate["yaw"]), 0.0])
        lat = np.array([-n[1], n[0], 0.0])
        up = np.array([0.0, 0.0, 1.0])
        for half, width in ((gate["inner"] / 2, 1.0), (gate["outer"] / 2, 2.0)):
            corners = [c + half * (sx * lat + sy * up) for sx, sy in ((-1, -1), (1, -1), (1, 1), (-1, 1), (-1, -1))]
            ax.plot(*np.array(corners).T, color="tab:orange", linewidth=width)
    theta = np.linspace(0, 2 * np.pi, 16)
    for obs in scene["obstacles"]:
        x, y, z = obs["position"]
        if obs["kind"] == "cylinder":
            r, h = obs["size"]
            ring_x, ring_y = x + r * np.cos(theta), y + r * np.sin(theta)
        else:
            hx, hy, hz = obs["size"]
            h = 2 * hz
            cy, sy = np.cos(obs["yaw"]), np.sin(obs["yaw"])
            local = np.array([[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy], [-hx, -hy]])
            ring_x, ring_y = x + local[:, 0] * cy - local[:, 1] * sy, y + local[:, 0] * sy + local[:, 1] * cy
        zs = np.array([z - h / 2, z + h / 2])
        X, Z = np.meshgrid(ring_x, zs)
        Y, _ = np.meshgrid(ring_y, zs)
        ax.plot_surface(X, Y, Z, color="tab:blue", alpha=0.35, linewidth=0)
    start = scene["start"]["position"]
    ax.scatter(*start, color="tab:green", s=30, label="start")


def plot_track_3d(
    out_dir: str | Path | Iterable[str | Path],
    env_id: str,
    path: str | Path,
    agent: str | None = None,
    seed: int | None = None,
    dpi: int = DEFAULT_DPI,
) -> Path:
    """The paper's Fig. 4: gates, obstacles and flown trajectories of one env id (needs saved trajectories).

    ``out_dir``: one result directory or several (each agent's evaluation). One scene (the episode ``seed``,
    default the smallest saved one) with every saved trajectory flown in it (each agent's, or only ``agent``'s);
    successful flights solid, failures dotted with an x at the crash. Several agents get a colour each, labelled
    in the legend; a given directory without a trajectory in that scene is named in a warning.
    """
    folders = [Path(out_dir)] if isinstance(out_dir, str | Path) else [Path(d) for d in out_dir]
    runs = []  # (row, positions, scene, folder)
    for folder in folders:
        for row, positions, scene in read_trajectories(folder):  # in record-name order, as the files once were
            if row["env_id"] == env_id and (agent is None or row["agent"] == agent):
                runs.append((row, positions, scene, folder))
    where = ", ".join(repr(str(folder)) for folder in folders)
    if not runs:
        raise ValueError(f"no trajectories of {env_id!r} in {where} (evaluate with --save-trajectories)")
    seed = min(r["seed"] for r, *_ in runs) if seed is None else seed
    runs = [run for run in runs if run[0]["seed"] == seed]  # one scene: trajectories of other seeds flew others
    if not runs:
        raise ValueError(f"no trajectory of {env_id!r} with seed {seed} in {where}")
    scene = runs[0][2]
    if any(run[2] != scene for run in runs):  # e.g. records of another env version: not one figure
        raise ValueError(f"the trajectories of {env_id!r} seed {seed} in {where} flew different scenes")
    unused = [str(folder) for folder in folders if not any(run[3] == folder for run in runs)]
    if unused:
        logger.warning(f"no trajectory of {env_id} seed {seed} in {', '.join(unused)}: not in the track figure")
    # One label per policy: its agent name, with its folder's name where two policies share one agent name.
    policies = dict.fromkeys((r["agent"], r.get("policy_sha256"), folder) for r, _, _, folder in runs)
    labels: dict[tuple[str, str | None], str] = {}
    for name, digest, folder in policies:
        shared = len({h for a, h, _ in policies if a == name}) > 1
        labels.setdefault((name, digest), f"{name} ({folder.name})" if shared else name)
    several = len(set(labels.values())) > 1
    colours = {label: _AGENT_COLOURS[i % len(_AGENT_COLOURS)] for i, label in enumerate(dict.fromkeys(labels.values()))}
    fig = plt.figure(figsize=(7.5, 4.6))
    ax = fig.add_subplot(projection="3d")
    _draw_scene(ax, scene)
    for row, positions, _, _ in runs:
        ok = bool(row["success"])
        label = labels[(row["agent"], row.get("policy_sha256"))]
        colour = colours[label] if several else "tab:green" if ok else "tab:red"
        ax.plot(*positions.T, "-" if ok else ":", color=colour, linewidth=1.2, alpha=0.8)
        if not ok:
            ax.scatter(*positions[-1], marker="x", color=colour, s=25)
    all_points = np.concatenate([p for _, p, _, _ in runs] + [np.array([g["center"] for g in scene["gates"]])])
    low, high = all_points.min(axis=0) - 1.0, all_points.max(axis=0) + 1.0
    low[2], high[2] = 0.0, max(high[2], 3.0)
    ax.set_xlim(low[0], high[0])
    ax.set_ylim(low[1], high[1])
    ax.set_zlim(0, high[2])
    # A narrow track gets a thin box: give the short axes a floor so their ticks and labels have room.
    span = high - low
    ax.set_box_aspect(np.maximum(span, 0.35 * span.max()), zoom=0.98)
    ax.set_proj_type("ortho")  # no perspective: heights and gate sizes compare across the track
    for axis, shortest in ((ax.xaxis, span[0]), (ax.yaxis, span[1]), (ax.zaxis, span[2])):
        axis.set_major_locator(MaxNLocator(5 if shortest >= 0.6 * span.max() else 3))
    ax.view_init(elev=28, azim=-62)
    ax.set_xlabel("x [m]", labelpad=10)
    ax.set_ylabel("y [m]", labelpad=6)
    ax.set_zlabel("z [m]", labelpad=4)
    k = sum(bool(r["success"]) for r, *_ in runs)
    who = agent or ", ".join(sorted(set(labels.values())))
    ax.set_title(f"{env_id}, seed {seed}: {who} ({k}/{len(runs)} successful)", fontsize=9)
    handles = [
        Line2D([], [], color="tab:orange", linewidth=2, label="gate"),
        Patch(facecolor="tab:blue", alpha=0.35, label="obstacle"),
        Line2D([], [], color="tab:green", marker="o", linestyle="", label="start"),
    ]
    if several:  # a colour per agent; the line style tells success from failure (said only when both occur)
        for label, colour in colours.items():
            mine = [r for r, *_ in runs if labels[(r["agent"], r.get("policy_sha256"))] == label]
            won = sum(bool(r["success"]) for r in mine)
            handles.append(Line2D([], [], color=colour, label=f"{label} ({won}/{len(mine)} successful)"))
        if 0 < k < len(runs):
            handles.append(Line2D([], [], color="0.3", label="solid: successful flight"))
        if k < len(runs):
            failed = "dotted: failed flight (x: end)"
            handles.append(Line2D([], [], color="0.3", linestyle=":", marker="x", label=failed))
    else:  # an entry only for what is drawn
        if k:
            handles.append(Line2D([], [], color="tab:green", label="successful flight"))
        if k < len(runs):
            handles.append(Line2D([], [], color="tab:red", linestyle=":", marker="x", label="failed flight (x: end)"))
    # Crop to what is drawn: a 3D axes' own box (which "tight" keeps) is mostly blank below the track. The legend
    # goes below that drawing, never over the box.
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    parts = [axis.get_tightbbox(renderer) for axis in (ax.xaxis, ax.yaxis, ax.zaxis)]
    parts += [ax.title.get_window_extent(renderer)]
    box = Bbox.union([b for b in parts if b is not None and b.width > 0])
    anchor = ((box.x0 + box.x1) / 2 / fig.bbox.width, box.y0 / fig.bbox.height)
    legend = fig.legend(handles=handles, fontsize=8, loc="upper center", bbox_to_anchor=anchor, ncol=3, frameon=False)
    fig.canvas.draw()
    drawn = Bbox.union([box, legend.get_window_extent(renderer)])
    return _save(fig, path, dpi, bbox=drawn.transformed(fig.dpi_scale_trans.inverted()).padded(0.18))


def render_episode_gif(
    agent_spec: str,
    env_id: str,
    seed: int,
    path: str | Path,
    fps: int = 25,
    trust_code: bool = False,
    agent_kwargs: dict[str, Any] | None = None,
) -> Path:
    """Fly one episode and write its video (``.gif`` or ``.mp4``): see
    :func:`racebench.reporting.video.render_episode_video`."""
    return render_episode_video(
        agent_spec, env_id, seed, path, fps=fps, trust_code=trust_code, agent_kwargs=agent_kwargs
    )[0]
