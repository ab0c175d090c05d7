"""Figures from result files alone: success rates with confidence intervals, SR vs density and vs gate
shift, the 3D track plot with flown trajectories (the paper's Fig. 4), training curves; episode videos are
:mod:`racebench.reporting.video`'s.
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")  # files only; never needs a display
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402
from matplotlib.patches import Patch  # noqa: E402
from matplotlib.ticker import MaxNLocator  # noqa: E402
from matplotlib.transforms import Bbox  # noqa: E402

from racebench.envs.registration import CURRICULUM, DENSITIES, GATE_SHIFTS  # noqa: E402
from racebench.evaluation.protocol import TRACK_ORDER  # noqa: E402
from racebench.evaluation.records import read_trajectories  # noqa: E402
from racebench.reporting.tables import TRACK_NAMES  # noqa: E402
from racebench.reporting.video import render_episode_video
from racebench.utils.yamlfile import read_yaml  # noqa: E402

#: File formats of the figures (matplotlib picks the writer from the suffix) and the default resolution of PNGs.
FIGURE_FORMATS: tuple[str, ...] = ("png", "pdf", "svg")
DEFAULT_DPI = 300
NOT_EVALUATED = "n/e"  # the label of a bar slot whose cell has no results
_LABEL_BOX = {"facecolor": "white", "edgecolor": "none", "pad": 0.6}  # a label stays legible over an error bar
#: Colours of the agents' flights in the track figure when it shows several agents (none is the gates' orange,
#: the obstacles' blue or the start's green).
_AGENT_COLOURS = ("tab:red", "tab:purple", "tab:brown", "tab:pink", "tab:olive", "tab:cyan", "tab:gray", "black")
logger = logging.getLogger("racebench.reporting.plots")


def _label(agent: str, privileged: bool) -> str:
    return f"{agent} (privileged)" if privileged else agent


def _agents(summary: pd.DataFrame) -> list[tuple[str, bool]]:
    pairs = summary.drop_duplicates("agent")[["agent", "privileged"]].itertuples(index=False)
    return sorted(((str(a), bool(p)) for a, p in pairs), key=lambda x: (x[1], x[0]))


def plot_success_by_track(summary: pd.DataFrame, path: str | Path, dpi: int = DEFAULT_DPI) -> Path:
    """Grouped bars: SR per track and agent with 95 % Wilson intervals (privileged agents hatched), written to
    ``path`` (PNG, PDF or SVG by its suffix). A 0 % cell is labelled "0 %", a cell without results "n/e"."""
    return _save(success_by_track_figure(summary), path, dpi)


def success_by_track_figure(summary: pd.DataFrame) -> Any:
    """The figure of :func:`plot_success_by_track` (legend outside the axes, so it never hides a bar)."""
    main = summary[summary["variant"] == "default"]
    if main.empty:
        raise ValueError("no results on the main ids (RaceObs-{S,J,Circle}-v0) to plot")
    agents = _agents(main)
    width = 0.8 / len(agents)
    fig, ax = plt.subplots(figsize=(1.8 + 1.6 * len(TRACK_ORDER), 3.4))
    x = np.arange(len(TRACK_ORDER))
    missing = False
    for i, (agent, privileged) in enumerate(agents):
        rows = [main[(main["agent"] == agent) & (main["track"] == t)] for t in TRACK_ORDER]
        sr = np.array([100 * r["success_rate"].iloc[0] if len(r) else np.nan for r in rows])
        low = np.array([100 * r["sr_ci_low"].iloc[0] if len(r) else np.nan for r in rows])
        high = np.array([100 * r["sr_ci_high"].iloc[0] if len(r) else np.nan for r in rows])
        centres = x + (i - (len(agents) - 1) / 2) * width
        bars = ax.bar(
            centres,
            sr,
            width,
            yerr=[sr - low, high - sr],
            capsize=3,
            label=_label(agent, privileged),
            hatch="//" if privileged else None,
            edgecolor="black",
            linewidth=0.5,
        )
        # A 0 % bar has no height and an absent cell draws nothing: without a label the two look the same.
        for centre, value, bar in zip(centres, sr, bars, strict=True):
            if np.isnan(value):
                missing = True
                ax.text(centre, 1.5, NOT_EVALUATED, ha="center", va="bottom", fontsize=7, color="0.4", style="italic")
            elif value == 0:
                ax.plot([centre - width / 2, centre + width / 2], [0, 0], color=bar.get_facecolor(), linewidth=3)
                ax.text(centre, 1.5, "0 %", ha="center", va="bottom", fontsize=7, bbox=_LABEL_BOX)
    ax.set_xticks(x, [TRACK_NAMES[t] for t in TRACK_ORDER])
    ax.set_ylabel("success rate [%]")
    ax.set_ylim(0, 105)
    ax.set_xlim(-0.5, len(TRACK_ORDER) - 0.5)
    n = int(main["n"].min())
    ax.set_title(f"Success rate, 95% Wilson CI (n ≥ {n} per cell)", fontsize=10)
    legend = ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False)
    if missing:
        legend.set_title(f"{NOT_EVALUATED}: not evaluated", prop={"size": 7, "style": "italic"})
    ax.grid(axis="y", alpha=0.3)
    return fig


def entry_summary(
    leaderboard: str | Path, tiers: tuple[str, ...] = ("verified",)
) -> tuple[pd.DataFrame, dict[str, list[int]]]:
    """Rows like :func:`racebench.evaluation.results.read_summaries`'s of the leaderboard's learned entries of
    ``tiers`` (by default the verified ones): each entry's own-track public-seed cells (each track flown by its own
    policy, as the site ranks self-reported entries and as the references are flown), labelled
    ``<name> (<tier>, public seeds)``. Also the env versions of each entry's records, to check that a figure is of
    one env version (:func:`racebench.evaluation.results.check_one_env_version`)."""
    from racebench.evaluation.protocol import split_env_id
    from racebench.leaderboard.entries import load_config, load_entries
    from racebench.leaderboard.ranking import entry_row

    config = load_config(leaderboard)
    rows, versions = [], {}
    for entry in load_entries(leaderboard):
        tier = entry_row(entry, config).tier
        if tier not in tiers:
            continue
        label = f"{entry.name} ({tier}, public seeds)"
        for env_id, found in entry.own_cells().items():
            track, variant = split_env_id(env_id)
            low, high = found.interval
            rows.append({"agent": label, "privileged": False, "env_id": env_id, "track": track, "variant": variant,
                         "n": found.n, "successes": found.successes, "success_rate": found.success_rate,
                         "sr_ci_low": low, "sr_ci_high": high, "lap_time_mean": found.lap_time_mean})  # fmt: skip
        versions[f"leaderboard entry {entry.name}"] = [int(r["env_version"]) for r in entry.records]
    return pd.DataFrame(rows), versions


def plot_success_vs(summary: pd.DataFrame, factor: str, path: str | Path, dpi: int = DEFAULT_DPI) -> Path:
    """SR vs obstacle density (``factor="density"``), gate shift (``"gates"``) or curriculum level (``"levels"``,
    the ``-Level{1,2,3}`` ids), one panel per track; a level, density or shift without results is left out."""
    if factor == "density":
        xs, xlabel = list(DENSITIES), "obstacles per 2 gates"
        variants = [f"Density{d}" for d in DENSITIES]
    elif factor == "gates":
        xs, xlabel = [float(s) for s in GATE_SHIFTS], "gate shift ±[m]"
        variants = [f"GateShift{s}" for s in GATE_SHIFTS]
    elif factor == "levels":
        xs, xlabel = sorted(CURRICULUM), "curriculum level"
        variants = [f"Level{level}" for level in xs]
    else:
        raise ValueError(f"factor must be 'density', 'gates' or 'levels', got {factor!r}")
    data = summary[summary["variant"].isin(variants)]
    if data.empty:
        raise ValueError(f"no results on the {factor} variants to plot")
    absent = sorted(set(summary["agent"].astype(str)) - set(data["agent"].astype(str)))
    if absent:  # said, so that a missing curve is not read as a figure of every agent given
        what = {"density": "obstacle density", "gates": "gate shift", "levels": "curriculum level"}[factor]
        logger.warning(f"{Path(path).name}: no {what} results of {', '.join(absent)}; left out")
    fig, axes = plt.subplots(1, len(TRACK_ORDER), figsize=(10, 3.2), sharey=True)
    for ax, track in zip(axes, TRACK_ORDER, strict=True):
        for agent, privileged in _agents(data):
            mine = data[(data["agent"] == agent) & (data["track"] == track)]
            rows = [mine[mine["variant"] == v] for v in variants]
            sr = np.array([100 * r["success_rate"].iloc[0] if len(r) else np.nan for r in rows])
            low = np.array([100 * r["sr_ci_low"].iloc[0] if len(r) else np.nan for r in rows])
            high = np.array([100 * r["sr_ci_high"].iloc[0] if len(r) else np.nan for r in rows])
            style = "--" if privileged else "-"
            (line,) = ax.plot(xs, sr, style, marker="o", label=_label(agent, privileged))
            ax.fill_between(xs, low, high, color=line.get_color(), alpha=0.15)
        if data[data["track"] == track].empty:  # say so, rather than leave a panel that looks like a failure
            ax.text(0.5, 0.5, "not evaluated", transform=ax.transAxes, ha="center", color="0.4", style="italic")
        ax.set_title(TRACK_NAMES[track], fontsize=10)
        ax.set_xlabel(xlabel)
        ax.set_xticks(xs)
        ax.set_ylim(-4, 105)  # a 0 % point shows whole, not cut in half by the axis
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("success rate [%] (95% CI)")
    axes[-1].legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.02, 1.0), frameon=False)  # off the curves
    return _save(fig, path, dpi)


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


#: SB3's own CSV logger (``configure(folder, ["csv"])``): its column for each of racebench's progress columns.
SB3_PROGRESS_COLUMNS: dict[str, str] = {
    "time/total_timesteps": "timesteps",
    "rollout/ep_rew_mean": "mean_return",
    "rollout/success_rate": "success_rate",
    "time/time_elapsed": "wall_s",
}


def read_progress(csv_path: str | Path) -> pd.DataFrame:
    """A training run's ``progress.csv`` as ``timesteps``, ``mean_return``, ``success_rate``, ``level``.

    ``racebench train``'s file of a PPO run or of a DAgger run (``env_steps`` are its environment steps; it has
    no return or level, which are NaN), or SB3's own (``time/total_timesteps``, ``rollout/ep_rew_mean`` and,
    when the env reports ``is_success``, ``rollout/success_rate``; it has no curriculum level, which is NaN).
    """
    progress = pd.read_csv(csv_path)
    if {"iteration", "samples", "success_rate", "wall_s"} <= set(progress.columns):
        # racebench train --config vision-distill (DAgger): a row per iteration; its success rate is the
        # student's (mixed with the expert's actions by β early on) on the training scenes at full difficulty.
        # env_steps counts every step flown; files written before it existed have only samples, the
        # aggregate's size, which equals the steps flown until the aggregate is full.
        progress = progress.rename(columns={"env_steps" if "env_steps" in progress else "samples": "timesteps"})
        progress["mean_return"] = np.nan
        progress["level"] = np.nan
        return progress
    if {"time/total_timesteps", "rollout/ep_rew_mean"} <= set(progress.columns):
        progress = progress.rename(columns=SB3_PROGRESS_COLUMNS)
        for column in ("success_rate", "level"):
            if column not in progress:
                progress[column] = np.nan
        # SB3 logs a row per update; ep_rew_mean stays empty until the first episode has ended.
        return progress.sort_values("timesteps").reset_index(drop=True)
    missing = {"timesteps", "mean_return", "success_rate", "level"} - set(progress.columns)
    if missing:
        raise ValueError(
            f"{csv_path}: missing columns {sorted(missing)} (neither racebench train's progress.csv nor SB3's)"
        )
    return progress


def _load_runs(runs: list[str | Path]) -> list[tuple[str, pd.DataFrame]]:
    """``(label, progress)`` per run directory or ``progress.csv``; the label is the run's config name
    (``config.yaml``, else ``summary.json``'s config) or its directory's name."""

    loaded = []
    for run in runs:
        run = Path(run)
        csv_path = run / "progress.csv" if run.is_dir() else run
        if not csv_path.is_file():
            raise ValueError(f"{run}: no progress.csv (is it a `racebench train` run directory?)")
        config, summary = csv_path.parent / "config.yaml", csv_path.parent / "summary.json"
        label = csv_path.parent.name
        if config.is_file():
            saved = read_yaml(config)
            label = (saved.get("name") if isinstance(saved, dict) else None) or label
        elif summary.is_file():
            named = json.loads(summary.read_text()).get("config", {})  # a DAgger run's dict, a PPO run's name
            label = named.get("name", label) if isinstance(named, dict) else named if isinstance(named, str) else label
        loaded.append((label, read_progress(csv_path)))
    return loaded


def smoothed_success(progress: pd.DataFrame, window_steps: int = 50_000) -> pd.DataFrame:
    """A run's training success in % (``timesteps``, ``wall_s``, ``success``), a rolling mean over
    ``window_steps`` environment steps' worth of its rows (PPO logs a row per update, DAgger per iteration of
    25 k steps, so runs that log at different rates are smoothed alike)."""
    rows = progress.dropna(subset=["success_rate"])
    spacing = float(np.median(np.diff(rows["timesteps"]))) if len(rows) > 1 else float(window_steps)
    window = max(1, round(window_steps / max(spacing, 1.0)))
    success = 100 * rows["success_rate"].rolling(window=window, min_periods=1).mean()
    return pd.DataFrame({"timesteps": rows["timesteps"], "wall_s": rows["wall_s"], "success": success})


def seed_band(curves: list[pd.DataFrame], x: str, points: int = 200) -> pd.DataFrame:
    """Mean, min and max over several seeds' curves (:func:`smoothed_success`) against ``x`` (``timesteps`` or
    ``wall_s``), each interpolated linearly onto a common grid from the latest first point to the earliest last
    point of the seeds, so every grid point is inside every seed's run (nothing is extrapolated)."""
    start = max(float(c[x].iloc[0]) for c in curves)
    stop = min(float(c[x].iloc[-1]) for c in curves)
    grid = np.linspace(start, stop, points) if stop > start else np.array([stop])
    values = np.stack([np.interp(grid, c[x].to_numpy(float), c["success"].to_numpy(float)) for c in curves])
    return pd.DataFrame({x: grid, "mean": values.mean(0), "min": values.min(0), "max": values.max(0)})


def _summary_path(run: str | Path, key: str) -> str | None:
    """``summary.json``'s ``key`` (a checkpoint path) of a run directory, normalised for comparison; None if absent."""
    run = Path(run)
    summary = (run if run.is_dir() else run.parent) / "summary.json"
    if not summary.is_file():
        return None
    value = json.loads(summary.read_text()).get(key)
    # runs record paths relative to where they were started; compared from here, as absolute normalised paths
    return os.path.normpath(os.path.abspath(value)) if isinstance(value, str) else None


def offsets_after_students(runs: list[str | Path], progresses: list[pd.DataFrame]) -> list[tuple[float, float]]:
    """``(steps, wall_s)`` to add to each run's curve so that a fine-tuning starts where its student's run ended.

    A run whose ``summary.json`` has ``init_from`` equal to another given run's ``checkpoint`` started from that
    run's policy: its cost is the student's plus its own, so it is shifted by the student's last ``timesteps`` and
    ``wall_s`` (chains of fine-tunings add up). A run whose student is not among ``runs`` keeps offset 0.
    """
    checkpoints = {_summary_path(run, "checkpoint"): i for i, run in enumerate(runs)}
    checkpoints.pop(None, None)
    offsets: list[tuple[float, float] | None] = [None] * len(runs)

    def offset(i: int, seen: frozenset[int]) -> tuple[float, float]:
        if offsets[i] is None:
            parent = checkpoints.get(_summary_path(runs[i], "init_from"))
            if parent is None or parent in seen:  # no student given (or a cycle of edited summaries)
                offsets[i] = (0.0, 0.0)
            else:
                steps, wall = offset(parent, seen | {i})
                last = progresses[parent]
                offsets[i] = (steps + float(last["timesteps"].max()), wall + float(last["wall_s"].max()))
        return offsets[i]

    return [offset(i, frozenset({i})) for i in range(len(runs))]


def run_track_and_seed(run: str | Path) -> tuple[str | None, int | None]:
    """A run's track and training seed from its ``summary.json`` (top level, or its config's for a DAgger run)."""
    run = Path(run)
    summary = (run if run.is_dir() else run.parent) / "summary.json"
    if not summary.is_file():
        return None, None
    data = json.loads(summary.read_text())
    config = data.get("config") if isinstance(data.get("config"), dict) else {}
    track, seed = data.get("track", config.get("track")), data.get("seed", config.get("seed"))
    return (str(track) if track else None), (int(seed) if isinstance(seed, int) else None)


def _group_label(label: str, seeds: list[int | None]) -> str:
    """A config's legend label: its training seeds counted as distinct seeds (as the README and tables count them);
    where runs share a seed, the runs are counted and their seeds named."""
    if len(seeds) == 1:
        return label if seeds[0] is None else f"{label} (training seed {seeds[0]})"
    known = sorted(s for s in seeds if s is not None)
    named = ", ".join(str(s) for s in known) if len(known) == len(seeds) else "unknown"
    if len(set(known)) == len(seeds):
        return f"{label} (mean of {len(seeds)} training seeds {named}; band: min–max)"
    return f"{label} (mean of {len(seeds)} runs, training seeds {named}; band: min–max)"


def plot_success_curves(
    runs: list[str | Path],
    path: str | Path | list[str | Path],
    window_steps: int = 50_000,
    dpi: int = DEFAULT_DPI,
    labels: dict[str, str] | None = None,
) -> Path:
    """Training success against environment steps (left) and against wall-clock time (right), one line per run
    or, where several runs share a config name (training seeds of one config), their mean with a min–max band.

    For comparing methods by cost: a PPO run's success is its training episodes' (from the track start, at
    the curriculum level of the moment: its promotions are marked, over seeds at the median of those that
    reached the level), a DAgger run's the student's on the training scenes. Each run is smoothed by
    :func:`smoothed_success`; seeds are combined by :func:`seed_band` (up to the shortest seed's end).
    Every run needs a ``wall_s`` column (``racebench train`` writes one). A fine-tuning given together with the
    run of the policy it started from (``init_from``) is drawn after that run's steps and wall clock
    (:func:`offsets_after_students`), so its x axes show the whole cost.

    ``labels`` names runs by path (e.g. the leaderboard's method name for the run its entry's policy came from);
    the figure's title names the runs' track; the legend sits below the axes, off the data; ``path`` may be a list
    (e.g. a PNG and a PDF), each written. Returns the first path.
    """
    loaded = _load_runs(runs)
    given = {os.path.normpath(k): v for k, v in (labels or {}).items()}
    loaded = [(given.get(os.path.normpath(str(run)), label), progress) for run, (label, progress) in zip(runs, loaded,
              strict=True)]  # fmt: skip
    meta = [run_track_and_seed(run) for run in runs]
    tracks = sorted({t for t, _ in meta if t}, key=lambda t: TRACK_ORDER.index(t) if t in TRACK_ORDER else 9)
    for label, progress in loaded:
        if "wall_s" not in progress:
            raise ValueError(f"{label}: progress.csv has no wall_s column (wall-clock time is needed)")
        if progress["success_rate"].isna().all():
            raise ValueError(f"{label}: progress.csv has no success rate (does the env report is_success?)")
    offsets = offsets_after_students(runs, [progress for _, progress in loaded])
    loaded = [
        (label, progress.assign(timesteps=progress["timesteps"] + steps, wall_s=progress["wall_s"] + wall))
        for (label, progress), (steps, wall) in zip(loaded, offsets, strict=True)
    ]
    groups: dict[str, list[pd.DataFrame]] = {}
    seeds: dict[str, list[int | None]] = {}
    for (label, progress), (_, seed) in zip(loaded, meta, strict=True):
        groups.setdefault(label, []).append(progress)
        seeds.setdefault(label, []).append(seed)
    fig, axes = plt.subplots(1, 2, figsize=(9.6, 3.6), sharey=True)
    promoted_any = False
    for label, progresses in groups.items():
        curves = [smoothed_success(progress, window_steps) for progress in progresses]
        name = _group_label(label, seeds[label])
        if len(curves) == 1:
            curve = curves[0]
            marker = "o" if len(curve) == 1 else None  # a single row is a point, not a line
            (line,) = axes[0].plot(curve["timesteps"] / 1e6, curve["success"], label=name, marker=marker)
            axes[1].plot(curve["wall_s"] / 60, curve["success"], color=line.get_color(), marker=marker)
        else:
            color = None
            for ax, x, scale in ((axes[0], "timesteps", 1e6), (axes[1], "wall_s", 60)):
                band = seed_band(curves, x)
                (line,) = ax.plot(band[x] / scale, band["mean"], color=color, label=name if color is None else None)
                color = line.get_color()
                ax.fill_between(band[x] / scale, band["min"], band["max"], color=color, alpha=0.2, linewidth=0)
        # Curriculum promotions: a run's own, or over seeds the median of those that reached the level ("L3 2/3")
        promotions: dict[float, list[tuple[float, float]]] = {}
        for progress in progresses:
            promoted = progress["level"].diff() > 0
            for level, steps, wall in zip(progress["level"][promoted], progress["timesteps"][promoted],
                                          progress["wall_s"][promoted], strict=True):  # fmt: skip
                promotions.setdefault(float(level), []).append((steps / 1e6, wall / 60))
        for level, reached in promotions.items():
            promoted_any = True
            name = f"L{level:.0f}" + (f" {len(reached)}/{len(progresses)}" if len(progresses) > 1 else "")
            for ax, at in zip(axes, np.median(np.array(reached), axis=0), strict=True):
                ax.axvline(at, color=line.get_color(), linestyle=":", linewidth=1)
                ax.annotate(name, (at, 100), xytext=(2, -10), textcoords="offset points", fontsize=7,
                            color=line.get_color())  # fmt: skip
    axes[0].set_xlabel("environment steps [millions]")
    axes[1].set_xlabel("wall-clock [min]")
    axes[0].set_ylabel("training success [%]")
    axes[0].set_ylim(-2, 102)
    where = " and ".join(TRACK_NAMES.get(t, t) for t in tracks) if tracks else "its tracks"
    fig.suptitle(f"Training success on {where} against environment steps and wall-clock", fontsize=10)
    handles, names = axes[0].get_legend_handles_labels()
    if promoted_any:
        handles.append(Line2D([], [], color="0.4", linestyle=":", linewidth=1))
        names.append("curriculum promotion to level k (Lk): at the median over the runs that reached it, "
                     "'Lk m/n': m of the n runs did")  # fmt: skip
    fig.legend(handles, names, loc="upper center", bbox_to_anchor=(0.5, 0.0), ncol=1, fontsize=8, frameon=False)
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.set_xlim(left=0)
    paths = list(path) if isinstance(path, list | tuple) else [path]
    for extra in paths[1:]:  # _save closes the figure: the other formats first
        fig.tight_layout()
        fig.savefig(_checked(extra, fig, dpi), dpi=dpi, bbox_inches="tight", pad_inches=0.05)
    return _save(fig, paths[0], dpi)


def plot_training_curves(runs: list[str | Path], path: str | Path, smooth: int = 20, dpi: int = DEFAULT_DPI) -> Path:
    """The paper's Fig. 5 from training runs: mean episode return (rolling mean over ``smooth`` updates),
    success rate from the track start, and curriculum level, against environment steps.

    ``runs``: run directories (holding ``progress.csv``) or ``progress.csv`` files, of ``racebench train`` or of
    SB3's CSV logger (:func:`read_progress`); each is labelled as :func:`_load_runs` says. The level panel is
    left out when no run has a curriculum.
    """
    loaded = _load_runs(runs)
    levels = any(progress["level"].notna().any() for _, progress in loaded)
    rows, ratios = (3, [2, 1.4, 1]) if levels else (2, [2, 1.4])
    fig, axes = plt.subplots(rows, 1, figsize=(6.4, 6.4 if levels else 5.0), sharex=True, height_ratios=ratios)
    for label, progress in loaded:
        steps = progress["timesteps"] / 1e6
        window = dict(window=smooth, min_periods=1)
        (line,) = axes[0].plot(steps, progress["mean_return"].rolling(**window).mean(), label=label)
        axes[1].plot(steps, 100 * progress["success_rate"].rolling(**window).mean(), color=line.get_color())
        if levels:
            axes[2].step(steps, progress["level"], where="post", color=line.get_color())
    axes[0].set_ylabel("mean episode return")
    axes[0].legend(loc="best", fontsize=8)
    axes[1].set_ylabel("success from start [%]" if levels else "success rate [%]")
    axes[1].set_ylim(-2, 102)
    if levels:
        axes[2].set_ylabel("level")
        axes[2].set_yticks([1, 2, 3])
    axes[-1].set_xlabel("environment steps [millions]")
    for ax in axes:
        ax.grid(alpha=0.3)
    return _save(fig, path, dpi)


def _checked(path: str | Path, fig, dpi: int) -> Path:
    """``path`` with its folder made, once its suffix and ``dpi`` are ones :func:`_save` accepts."""
    path = Path(path)
    if path.suffix.lower().lstrip(".") not in FIGURE_FORMATS or isinstance(dpi, bool) or not 20 <= dpi <= 2400:
        plt.close(fig)
        raise ValueError(f"{str(path)!r}: figures are written as {', '.join(FIGURE_FORMATS)}, at dpi in [20, 2400]")
    path.parent.mkdir(parents=True, exist_ok=True)
    return path


def _save(fig, path: str | Path, dpi: int = DEFAULT_DPI, bbox: Bbox | None = None) -> Path:
    """Write ``fig`` to ``path`` in the format of its suffix (see FIGURE_FORMATS), cropped to what is drawn
    (``bbox``, in inches, where matplotlib's own "tight" box would keep blank space)."""
    path = Path(path)
    fmt = path.suffix.lower().lstrip(".")
    if fmt not in FIGURE_FORMATS:
        plt.close(fig)
        raise ValueError(
            f"{str(path)!r}: figures are written as {', '.join(FIGURE_FORMATS)}, not {fmt or 'no suffix'!r}"
        )
    if isinstance(dpi, bool) or not isinstance(dpi, int) or not 20 <= dpi <= 2400:
        plt.close(fig)
        raise ValueError(f"dpi must be an int in [20, 2400], got {dpi!r}")
    path.parent.mkdir(parents=True, exist_ok=True)
    if not any(getattr(ax, "name", "") == "3d" for ax in fig.axes):  # tight_layout cannot place 3D axes
        fig.tight_layout()
    # "tight" crops the blank margin and keeps legends placed outside the axes.
    fig.savefig(path, dpi=dpi, bbox_inches=bbox or "tight", pad_inches=0.05)
    plt.close(fig)
    return path
