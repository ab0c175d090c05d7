"""The run dispatcher of ``racebench train``: a config's ``method`` picks PPO (:mod:`racebench.training.ppo`)
or DAgger (:mod:`racebench.training.dagger`).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

from racebench.evaluation.protocol import split_env_id
from racebench.training.config import TrainConfig, baseline_path
from racebench.training.dagger.config import DaggerConfig
from racebench.training.dagger.loop import distill
from racebench.training.dagger.resume import completed_iterations
from racebench.training.ppo import train
from racebench.utils.yamlfile import read_yaml


def load_config(name_or_path: str | Path) -> Any:
    """A training config by built-in name or YAML path: :class:`TrainConfig` (PPO, the default ``method``) or,
    for ``method: dagger``, :class:`racebench.training.dagger.config.DaggerConfig`."""
    path = baseline_path(name_or_path)
    data = read_yaml(path)
    if isinstance(data, dict) and data.get("method", "ppo") == "dagger":
        return DaggerConfig.from_yaml(path)
    return TrainConfig.from_yaml(path)


def default_track(config: Any) -> str:
    """The track a run of ``config`` trains on when ``racebench train`` names none: a PPO config's own ``track``, a
    DAgger config's ``env_id``'s track (``RaceObs-Random-v0``: ``Random``), else ``S``."""
    if isinstance(config, DaggerConfig):
        return split_env_id(config.env_id)[0] if config.env_id else "S"
    return config.track or "S"


def run_training(
    config: Any, track: str, steps: int, seed: int, out: str | Path | None, resume: str | Path | None = None,
    eval_episodes: int = 10, device: str = "auto", checkpoint_every: int = 50_000, trust_code: bool = False,
) -> dict[str, Any]:  # fmt: skip
    """Train ``config`` (from :func:`load_config`) on ``track``: PPO through :func:`train`, DAgger through
    :func:`racebench.training.dagger.loop.distill` with ``ceil(steps / steps_per_iteration)`` iterations. As for
    PPO, with ``resume`` the ``steps`` are the steps to add; a DAgger run resumes from its run folder (its
    whole state is kept there, not in a zip), so ``resume`` must name that folder. ``trust_code``: see :func:`train`
    (a DAgger resume reads tensors and arrays only and needs no trust)."""
    if not isinstance(config, DaggerConfig):
        return train(config, track, steps, seed, out, resume, checkpoint_every=checkpoint_every,
                     eval_episodes=eval_episodes, device=device, trust_code=trust_code)  # fmt: skip
    folder = Path(out) if out is not None else Path("runs") / f"{config.name}-{track}-seed{seed}"
    if resume is not None and Path(resume).resolve() != folder.resolve():
        raise ValueError(f"a DAgger run resumes from its own folder: pass --resume {folder} (or the same --out)")
    more = -(-steps // config.steps_per_iteration)
    iterations = completed_iterations(folder) + more if resume is not None else max(1, more)
    config = dataclasses.replace(config, track=track, seed=seed, iterations=max(iterations, 1))
    config.validate(config.name)
    return distill(config, folder, eval_episodes=eval_episodes, resume=resume is not None)
