"""Figures from result files alone: success rates with confidence intervals, SR vs density and vs gate
shift, the 3D track plot with flown trajectories (the paper's Fig. 4), training curves; episode videos are
:mod:`racebench.reporting.video`'s.
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")  # files only; never needs a display
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402

from racebench.envs.registration import CURRICULUM, DENSITIES, GATE_SHIFTS  # noqa: E402
from racebench.evaluation.protocol import TRACK_ORDER  # noqa: E402
from racebench.reporting.figure_files import DEFAULT_DPI, FIGURE_FORMATS, _checked, _save  # noqa: E402,F401
from racebench.reporting.tables import TRACK_NAMES  # noqa: E402
from racebench.reporting.track_plot import plot_track_3d, render_episode_gif  # noqa: E402,F401 (re-exported)
from racebench.utils.yamlfile import read_yaml  # noqa: E402

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
