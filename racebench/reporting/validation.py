"""Validation learning curves: a campaign run's checkpoints flown on validation scenes, and the figure of all runs.

The paper's Fig. 5 plots training reward; training success alone is measured at a different curriculum level per
config. So at every multiple of its sweep's ``validation_every`` (1 M steps in campaign 1, 0.5 M in campaign 2) a
run's checkpoint is flown on its track's main id over validation scenes (seeds ``VALIDATION_SEED_BASE + i``,
disjoint from training and evaluation seeds) with deterministic actions and ray-cast depth
(:func:`validation_curve`), and :func:`learning_curves` draws every committed run's points, each on its own grid
(``racebench paper-tables`` calls it).
"""

from __future__ import annotations

import json
import re
from collections.abc import Collection
from functools import partial
from pathlib import Path

import gymnasium as gym
import numpy as np
import pandas as pd

from racebench.agents.loading import load_agent
from racebench.agents.trust import own_policy_trust
from racebench.evaluation.protocol import TRACK_ORDER, VALIDATION_SEED_BASE, env_id_of
from racebench.evaluation.rollout import run_lockstep
from racebench.evaluation.worker import SingleTorchThread
from racebench.reporting.tables import TRACK_NAMES
from racebench.utils.files import atomic_write

#: A sweep's run folder: ``<config>-<track>-seed<k>``.
RUN_FOLDER = re.compile(r"^(?P<config>.+)-(?P<track>S|J|Circle)-seed(?P<seed>\d+)$")


def validation_curve(
    run_dir: str | Path, every: int = 1_000_000, episodes: int = 100, trust_code: bool = False
) -> pd.DataFrame:
    """Fly a run's periodic checkpoints nearest each multiple of ``every`` steps on ``episodes`` validation scenes of
    its track's main id (deterministic actions, ray-cast depth); write and return ``validation_curve.csv``.

    The checkpoints are the periodic ones under ``checkpoints/`` and, once the run has finished, its final model
    (at ``summary.json``'s timesteps). Columns: timesteps (of the checkpoint), episodes, successes, success_rate,
    mean_return (the training return logged nearest that step in ``progress.csv``). Incremental: the rows already
    in the file are kept and only the missing multiples the run has reached are flown, so a run that spans sessions
    adds its points as it goes (a stopped run's checkpoint short of the next multiple never stands in for it). A
    checkpoint is unpickled only if the run folder wrote it (its ``written.json``) or with ``trust_code``.
    """
    run_dir = Path(run_dir)
    match = RUN_FOLDER.match(run_dir.name)
    if match is None:
        raise ValueError(f"{run_dir}: not a sweep run folder <config>-<track>-seed<k>")
    found = {}
    for path in (run_dir / "checkpoints").glob("*_steps.zip"):
        steps = int(re.search(r"_(\d+)_steps\.zip$", path.name)[1])
        found[steps] = path
    final, summary = run_dir / f"{match['config']}-{match['track']}.zip", run_dir / "summary.json"
    if final.is_file() and summary.is_file():  # a finished run's final model is its checkpoint at its last step
        found.setdefault(int(json.loads(summary.read_text())["timesteps"]), final)
    path = run_dir / "validation_curve.csv"
    rows = pd.read_csv(path).to_dict("records") if path.is_file() else []
    if not found and not rows:
        raise ValueError(f"{run_dir}: no periodic checkpoints under checkpoints/")
    progress = pd.read_csv(run_dir / "progress.csv")
    env_id = env_id_of(match["track"])
    seeds = [VALIDATION_SEED_BASE + i for i in range(episodes)]
    done = {round(row["timesteps"] / every) for row in rows}
    for target in range(every, max(found, default=0) + every // 2, every):
        steps = min(found, key=lambda s: abs(s - target))
        # A grid checkpoint sits at the multiple or up to a rollout past it (below it only by the grid's rounding
        # to whole vector steps); one well before it is a stopped run's, which has not reached that point yet.
        if not -(every // 100) <= steps - target <= every // 4 or target // every in done:
            continue
        agent = load_agent(str(found[steps]), trust_code=own_policy_trust(run_dir, found[steps], trust_code))
        results: list[dict] = []
        with SingleTorchThread():
            run_lockstep(agent, [(env_id, s) for s in seeds], partial(_raycast_env, obs_mode=agent.obs_mode),
                         lambda _e, _s, result, _f, kept=results: kept.append(result),
                         width=min(64, episodes))  # fmt: skip
        errors = [r for r in results if r.get("error")]
        if errors:  # an episode the agent could not fly is no failure to count: the curve would lie
            raise ValueError(f"{found[steps]}: {len(errors)} of {len(results)} validation episodes ended in an "
                             f"error, first: {errors[0]['error']}")  # fmt: skip
        near = progress.iloc[(progress["timesteps"] - steps).abs().argsort()[:1]]
        successes = sum(bool(r.get("success")) for r in results)
        rows.append({"timesteps": steps, "episodes": len(results), "successes": successes,
                     "success_rate": successes / len(results),
                     "mean_return": float(near["mean_return"].iloc[0])})  # fmt: skip
        _write_curve(path, rows)  # each point as it is flown: an interrupted call keeps the points it finished
    return _write_curve(path, rows)


def _write_curve(path: Path, rows: list[dict]) -> pd.DataFrame:
    columns = ["timesteps", "episodes", "successes", "success_rate", "mean_return"]
    curve = pd.DataFrame(rows, columns=columns).sort_values("timesteps", ignore_index=True)
    atomic_write(path, curve.to_csv(index=False))
    return curve


def _raycast_env(env_id: str, obs_mode: str):
    return gym.make(env_id, obs_mode=obs_mode, renderer="raycast")  # the observation the agent was trained on


#: Validation points are put on a grid of this resolution at the finest (a run's own spacing, e.g. 0.5 M or 1 M).
GRID_RESOLUTION = 100_000


def validation_spacing(timesteps: pd.Series) -> int:
    """The spacing of a run's validation points (its ``every``): the median gap, to :data:`GRID_RESOLUTION`."""
    steps = sorted(timesteps)
    if len(steps) < 2:
        return GRID_RESOLUTION
    gap = float(pd.Series(steps).diff().median())
    return max(GRID_RESOLUTION, round(gap / GRID_RESOLUTION) * GRID_RESOLUTION)


def on_grid(curve: pd.DataFrame) -> pd.DataFrame:
    """One run's validation points with ``step``, the multiple of its spacing each was flown for.

    A checkpoint lies at or up to a rollout past its multiple (and a resumed run's part may save it later still,
    e.g. 3.16 M for 3 M), so the seeds of a config are joined on ``step``, the absolute step count each point
    stands for, not on the checkpoints' exact counts. Where two points of one run fall on one step, the later is
    kept."""
    every = validation_spacing(curve["timesteps"])
    curve = curve.assign(step=(curve["timesteps"] / every).round().astype(int) * every)
    return curve.sort_values("timesteps").drop_duplicates("step", keep="last").reset_index(drop=True)


def read_promotions(run_dir: Path) -> list[tuple[int, int]]:
    """``(level, timestep)`` of each curriculum promotion of a run (its ``curriculum.json``; none without one)."""
    path = run_dir / "curriculum.json"
    if not path.is_file():
        return []
    return [(int(p["level"]), int(p["timestep"])) for p in json.loads(path.read_text()).get("promotions", [])]


def read_curves(
    root: Path, campaign: Path, only: Collection[str] | None = None
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Every campaign run's validation points (``run``, ``config``, ``track``, ``training_seed``, ``step`` and the
    file's columns) and curriculum promotions (``config``, ``track``, ``training_seed``, ``level``, ``timestep``);
    with ``only``, of the run folders it names only (a report's committed runs: a run still training has points up
    to where it stopped, and is drawn once it is finished)."""
    frames, promotions = [], []
    for path in sorted((root / campaign).glob("*-seed*/validation_curve.csv")):
        match = RUN_FOLDER.match(path.parent.name)
        if match is None or (only is not None and path.parent.name not in only):
            continue
        frame = on_grid(pd.read_csv(path))
        ids = {"run": path.parent.name, "config": match["config"], "track": match["track"],
               "training_seed": int(match["seed"])}  # fmt: skip
        for i, (key, value) in enumerate(ids.items()):
            frame.insert(i, key, value)
        frames.append(frame)
        for level, timestep in read_promotions(path.parent):
            promotions.append({**{k: v for k, v in ids.items() if k != "run"}, "level": level, "timestep": timestep})
    curves = pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()
    columns = ["config", "track", "training_seed", "level", "timestep"]
    return curves, pd.DataFrame(promotions, columns=columns)


def seed_statistics(curves: pd.DataFrame, column: str) -> pd.DataFrame:
    """Per ``config``, ``track`` and ``step``: the mean, min and max of ``column`` over the training seeds with a
    point there, and their number ``seeds``."""
    grouped = curves.groupby(["config", "track", "step"])[column]
    return grouped.agg(["mean", "min", "max", "size"]).rename(columns={"size": "seeds"}).reset_index()


#: Markers of a curriculum promotion, by the level reached.
PROMOTION_MARKERS = {2: "^", 3: "D"}


def learning_curves_figure(curves: pd.DataFrame, promotions: pd.DataFrame, title: str | None = None):
    """The figure of :func:`learning_curves`: a column per track, validation success (top) and training return
    (bottom) per config, the mean over its training seeds with a band for their range; a config's curriculum
    promotions (the median step over its seeds that reached the level) as markers on its success curve; one legend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D

    configs = sorted(curves["config"].unique())
    colours = {c: plt.get_cmap("tab10")(i % 10) for i, c in enumerate(configs)}
    success, returns = seed_statistics(curves, "success_rate"), seed_statistics(curves, "mean_return")
    fig, axes = plt.subplots(2, len(TRACK_ORDER), figsize=(12.5, 6.4), sharex=True, squeeze=False)
    for col, track in enumerate(TRACK_ORDER):
        top, bottom = axes[0][col], axes[1][col]
        for config in configs:
            for ax, stats, scale in ((top, success, 100.0), (bottom, returns, 1.0)):
                mine = stats[(stats["config"] == config) & (stats["track"] == track)]
                if mine.empty:
                    continue
                x = mine["step"] / 1e6
                ax.plot(x, scale * mine["mean"], marker="o", markersize=3, color=colours[config], linewidth=1.4)
                if (mine["seeds"] > 1).any():
                    ax.fill_between(x, scale * mine["min"], scale * mine["max"], color=colours[config], alpha=0.15,
                                    linewidth=0)  # fmt: skip
            mine = success[(success["config"] == config) & (success["track"] == track)]
            reached = promotions[(promotions["config"] == config) & (promotions["track"] == track)]
            for level, group in reached.groupby("level"):
                at = float(group["timestep"].median()) / 1e6
                if mine.empty:
                    continue
                y = 100 * float(np.interp(at, mine["step"] / 1e6, mine["mean"]))
                top.plot([at], [y], PROMOTION_MARKERS.get(int(level), "s"), color=colours[config],
                         markeredgecolor="black", markeredgewidth=0.6, markersize=6, zorder=3)  # fmt: skip
        if not (curves["track"] == track).any():
            for ax in (top, bottom):
                ax.text(0.5, 0.5, "no run committed yet", ha="center", va="center", transform=ax.transAxes,
                        color="grey")  # fmt: skip
        top.set_ylim(-3, 103)
        top.set_title(f"{TRACK_NAMES[track]}: validation success", fontsize=10)
        bottom.set_title(f"{TRACK_NAMES[track]}: training return", fontsize=10)
        bottom.set_xlabel("environment steps [M]")
        for ax in (top, bottom):
            ax.grid(alpha=0.3)
            ax.set_xlim(left=0)
    axes[0][0].set_ylabel("validation success [%]")
    axes[1][0].set_ylabel("training return (mean episode)")
    seeds = curves.groupby(["config", "track"])["training_seed"].nunique().groupby("config").max()
    handles = [
        Line2D([], [], color=colours[c], marker="o", markersize=3,
               label=f"{c} (mean of {seeds[c]} seeds, band: range)" if seeds[c] > 1 else f"{c} (1 seed)")
        for c in configs
    ]  # fmt: skip
    for level, marker in PROMOTION_MARKERS.items():
        if (promotions["level"] == level).any():
            handles.append(Line2D([], [], linestyle="", marker=marker, color="0.6", markeredgecolor="black",
                                  label=f"curriculum promotion to level {level}"))  # fmt: skip
    fig.legend(handles=handles, loc="lower center", ncol=4, fontsize=8, frameon=False, bbox_to_anchor=(0.5, 0.0))
    if title:
        fig.suptitle(title, fontsize=11)
    fig.tight_layout(rect=(0, 0.1, 1, 1))
    return fig


#: The formats the learning-curve figure is written in.
CURVE_FORMATS = ("png", "pdf")


def learning_curves(
    root: Path, out: Path, campaign: Path, only: Collection[str] | None = None, runs: tuple[int, int] | None = None
) -> pd.DataFrame | None:
    """One CSV (``learning_curves.csv``: every campaign run's validation points, with their grid ``step``) and one
    figure (``figures/learning_curves.{png,pdf}``, :func:`learning_curves_figure`) of the campaign's runs (``only``:
    those run folders, :func:`read_curves`). ``runs`` (committed, planned): a partial campaign's title says how many
    of its runs are drawn. Each run is drawn on its own validation grid (every 0.5 M or 1 M steps)."""
    curves, promotions = read_curves(root, campaign, only)
    if curves.empty:
        return None
    atomic_write(out / "learning_curves.csv", curves.to_csv(index=False))
    import matplotlib.pyplot as plt

    every = sorted({validation_spacing(g["timesteps"]) / 1e6 for _, g in curves.groupby("run")})
    episodes = "/".join(str(n) for n in sorted(curves["episodes"].unique()))
    drawn = "" if runs is None or runs[0] >= runs[1] else f" ({runs[0]} of {runs[1]} runs committed)"
    title = (f"{Path(campaign).name}{drawn}: validation success on {episodes} validation scenes per point (every "
             f"{'/'.join(f'{e:g}' for e in every)} M steps) and training return")  # fmt: skip
    fig = learning_curves_figure(curves, promotions, title)
    (out / "figures").mkdir(parents=True, exist_ok=True)
    for fmt in CURVE_FORMATS:
        metadata = {"Software": None} if fmt == "png" else {"Creator": None, "Producer": None, "CreationDate": None}
        fig.savefig(out / "figures" / f"learning_curves.{fmt}", dpi=150, metadata=metadata)
    plt.close(fig)
    return curves
