"""Validation learning curves: a campaign run's checkpoints flown on validation scenes, and the figure of all runs.

The paper's Fig. 5 plots training reward; training success alone is measured at a different curriculum level per
config. So every 1 M steps a run's checkpoint is flown on its track's main id over validation scenes (seeds
``VALIDATION_SEED_BASE + i``, disjoint from training and evaluation seeds) with deterministic actions and ray-cast
depth (:func:`validation_curve`), and :func:`learning_curves` draws every committed run's points (``racebench
paper-tables`` calls it).
"""

from __future__ import annotations

import json
import re
from functools import partial
from pathlib import Path

import gymnasium as gym
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


def learning_curves(root: Path, out: Path, campaign: Path) -> pd.DataFrame | None:
    """One CSV and one figure (a panel per track) of every campaign run's validation success and training return."""
    frames = []
    for path in sorted((root / campaign).glob("*-seed*/validation_curve.csv")):
        match = RUN_FOLDER.match(path.parent.name)
        frame = pd.read_csv(path)
        frame.insert(0, "run", path.parent.name)
        frame.insert(1, "config", match["config"])
        frame.insert(2, "track", match["track"])
        frame.insert(3, "training_seed", int(match["seed"]))
        frames.append(frame)
    if not frames:
        return None
    curves = pd.concat(frames, ignore_index=True)
    atomic_write(out / "learning_curves.csv", curves.to_csv(index=False))
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 3, figsize=(12, 6), sharex=True, squeeze=False)
    for col, track in enumerate(TRACK_ORDER):
        for config, group in curves[curves["track"] == track].groupby("config", sort=True):
            mean = group.groupby("timesteps")[["success_rate", "mean_return"]].mean()
            axes[0][col].plot(mean.index / 1e6, 100 * mean["success_rate"], marker="o", label=config)
            axes[1][col].plot(mean.index / 1e6, mean["mean_return"], marker="o", label=config)
        if not (curves["track"] == track).any():
            for row in (0, 1):
                axes[row][col].text(0.5, 0.5, "no run committed yet", ha="center", va="center",
                                    transform=axes[row][col].transAxes, color="grey")  # fmt: skip
        axes[0][col].set_ylim(0, 100)
        axes[0][col].set_title(TRACK_NAMES[track])
        axes[1][col].set_xlabel("environment steps [M]")
    axes[0][0].set_ylabel("validation success [%]")
    axes[1][0].set_ylabel("training return")
    axes[0][-1].legend(fontsize=7)
    fig.tight_layout()
    (out / "figures").mkdir(parents=True, exist_ok=True)
    fig.savefig(out / "figures" / "learning_curves.png", dpi=150, metadata={"Software": None})
    plt.close(fig)
    return curves
