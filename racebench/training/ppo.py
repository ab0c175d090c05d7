"""``racebench train``: the paper's training pipeline (Sec. III-C) on stable-baselines3.

One config (a YAML file under ``baselines/``) names everything: observation mode, recurrent GRU policy or
feed-forward, reward overrides, curriculum, multi-scene groups, randomisation and PPO hyperparameters.
The whole algorithm is here:

1. ``n_envs`` copies of ``RaceEnv`` (batched in ``num_processes`` processes by ``RaceSB3VecEnv``, ray-cast
   depth, episodes starting before any gate) seeded below the evaluation seeds, rewards normalised by
   ``VecNormalize``;
2. :class:`CurriculumCallback`: a rolling success rate over the last ``window`` finished episodes; above
   ``promote_at`` the envs move to the next level (``RaceEnv.set_task``, from each env's next episode on;
   episodes begun before it do not count for the new level); each promotion is logged with its timestep
   and saved at once. "One-step" training starts at the last level;
3. :class:`MultiSceneCallback`: at every rollout start the envs are split into K groups (K per level);
   each group gets one new obstacle layout (and gate perturbation) shared by its envs (``set_layout``),
   which each env flies from its next episode on (episodes run longer than a rollout, so a group's envs
   overlap two layouts for a while); start poses stay random per episode;
4. PPO (``RecurrentPPO`` with :class:`~racebench.agents.recurrent.RecurrentGRUPolicy`, or ``PPO``; torch
   threads switched around the update by :class:`ThreadsCallback`), with
   TensorBoard logs, a CSV row per update (:class:`ProgressCSVCallback`), periodic checkpoints, resume,
   and a final evaluation with the common evaluator.
"""

from __future__ import annotations

import json
import os
import platform
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml
from stable_baselines3.common.callbacks import CallbackList
from stable_baselines3.common.utils import FloatSchedule
from stable_baselines3.common.vec_env import VecEnv, VecNormalize

from racebench.agents.base import AgentLoadError
from racebench.agents.loading import SB3Agent, load_vecnormalize_statistics
from racebench.agents.trust import own_policy_trust, record_written, require_trusted, vecnormalize_path, written_sha256
from racebench.evaluation.evaluator import Evaluator
from racebench.evaluation.protocol import EVAL_SEED_BASE
from racebench.training.callbacks import (
    AtomicCheckpointCallback,
    CriticWarmupCallback,
    CurriculumCallback,
    MultiSceneCallback,
    ProgressCSVCallback,
    StudentBCCallback,
    TeacherBCCallback,
    ThreadsCallback,
    TrainingInterrupted,
    _read_progress,
)
from racebench.training.config import TRAIN_TRACKS, TrainConfig
from racebench.training.models import (
    frozen_initial_policy,
    linear_schedule,
    load_policy_weights,
    make_envs,
    make_model,
    resolve_device,
)


def resume_curriculum(out: Path, timesteps: int, start_level: int) -> tuple[int, list[dict[str, Any]]]:
    """Level and promotions of a run resumed at ``timesteps``: promotions after that step are forgotten.

    Read from ``curriculum.json``; a run killed before this file existed is recovered from the level column
    of ``progress.csv`` (promotion steps then have rollout granularity).
    """
    state_file, rows = out / "curriculum.json", _read_progress(out / "progress.csv")
    if state_file.exists():
        promotions = json.loads(state_file.read_text())["promotions"]
    elif rows is not None:
        changed = rows[rows["level"].diff().fillna(rows["level"].iloc[0] - start_level) > 0]
        promotions = [{"level": int(r.level), "timestep": int(r.timesteps)} for r in changed.itertuples()]
    else:
        promotions = []
    promotions = [p for p in promotions if p["timestep"] <= timesteps]
    level = max([start_level] + [int(p["level"]) for p in promotions])
    return level, promotions


def train(
    config: TrainConfig,
    track: str = "S",
    steps: int = 200_000,
    seed: int = 0,
    out: str | Path | None = None,
    resume: str | Path | None = None,
    checkpoint_every: int = 50_000,
    eval_episodes: int = 10,
    device: str = "auto",
    trust_code: bool = False,
) -> dict[str, Any]:
    """Train one baseline on one track; returns a summary (paths, steps, wall time, samples/s, evaluation).

    ``device``: where the networks live (``"auto"``: CUDA when torch sees a GPU); the envs always step on CPU
    worker processes (``config.num_processes``), so the same config runs unchanged on a GPU machine.

    ``resume``: an SB3 checkpoint to continue from. It and its ``VecNormalize`` statistics are pickles, loaded
    under the evaluator's rule (:func:`racebench.agents.trust.require_trusted`): with ``trust_code``, if shipped, or if
    this run folder (``out``) wrote them itself, as listed in its :data:`~racebench.agents.trust.WRITTEN_FILE` (every
    checkpoint and statistics file a run writes is recorded there); anything else is refused before it is read.
    """
    if track not in TRAIN_TRACKS:
        raise ValueError(f"track must be one of {TRAIN_TRACKS}, got {track!r}")
    if config.track is not None and track != config.track:
        raise ValueError(f"{config.name} trains on track {config.track!r} (its config's track), not {track!r}")
    if config.action_components > 1 and config.init_from is None:  # PPO never trains the candidates' scores
        raise ValueError(
            f"{config.name}: action_components {config.action_components} needs init_from (a mixture student to "
            "fine-tune): PPO trains only the chosen candidate, the scores learn from DAgger's mixture loss"
        )
    if config.action_output != "ctbr":  # PPO's rollouts step the env with the actor's output
        raise ValueError(
            f"{config.name}: action_output {config.action_output!r} is for DAgger students (PPO steps the env with "
            "the actor's output, which must be the env's CTBR action)"
        )
    out = Path(out or Path("runs") / f"{config.name}-{track}-seed{seed}")
    out.mkdir(parents=True, exist_ok=True)
    (out / "config.yaml").write_text(yaml.safe_dump({k: _plain(v) for k, v in config.__dict__.items()}))
    state_file = out / "curriculum.json"

    torch.set_num_threads(config.torch_threads)  # measured: 7x faster updates than torch's default here
    init_from = config.init_from.format(track=track, seed=seed) if config.init_from else None
    if resume is None:
        env = make_envs(config, track, seed)
        model = make_model(config, env, seed, str(out / "tb"), device)
        if init_from is not None:
            load_policy_weights(model, init_from, config.log_std_init)
        level, promotions, started_at = config.start_level, [], 0
    else:
        written = written_sha256(out)
        # The checkpoint and its statistics are both checked before either is unpickled.
        stats = _trusted_reward_stats(Path(resume), trust_code, written) if config.normalize_reward else None
        model = _load_model(resume, resolve_device(device), trust_code, written)
        restore_schedules(model, config)
        started_at = model.num_timesteps
        archive_finished_part(out, started_at)
        level, promotions = resume_curriculum(out, started_at, config.start_level)
        if started_at > 0 and not (state_file.exists() or (out / "progress.csv").exists()):
            warnings.warn(
                f"resuming {resume} into {out}, which holds no curriculum.json or progress.csv: "
                f"the curriculum restarts at level {level}; pass the run's own folder as --out to continue it",
                stacklevel=2,
            )
        # New env seeds, so the resumed run does not replay the scenes its first part began with.
        env = make_envs(config, track, resume_seed(seed, started_at, config.n_envs))
        _restore_reward_stats(env, stats)
        if level != config.start_level:
            env.env_method("set_task", **config.level_kwargs(level))  # applies at the reset in set_env
        model.set_env(env)
    solved = None
    if resume is not None and state_file.exists():
        saved = json.loads(state_file.read_text()).get("solved")
        solved = saved if saved and saved["timestep"] <= started_at else None
    curriculum = CurriculumCallback(
        config, level=level, verbose=1, state_file=state_file, promotions=promotions, solved=solved
    )
    progress = ProgressCSVCallback(out / "progress.csv", curriculum)
    bc = None
    if config.bc_coef > 0 and config.bc_target == "teacher":
        bc = TeacherBCCallback(config.bc_coef, config.update_threads)
    elif config.bc_coef > 0:  # init_from is the anchor, also when resuming (the run's start, not the resumed weights)
        bc = StudentBCCallback(frozen_initial_policy(model, init_from), config.bc_coef, config.update_threads)
    curriculum.clock = lambda: time.perf_counter() - progress.started  # the run's wall clock, resumes included
    checkpointer = AtomicCheckpointCallback(
        # at rollout ends, so a resumed run loses no collected samples
        max(round(checkpoint_every / (config.n_envs * config.n_steps)), 1) * config.n_steps,
        str(out / "checkpoints"),
        config.name,
        save_vecnormalize=True,
        run_dir=out,
        rollout_calls=config.n_steps,  # a stop on request (TrainingInterrupted) saves at the next rollout end
    )
    callbacks = CallbackList(
        [
            curriculum,
            MultiSceneCallback(config, curriculum),
            progress,
            checkpointer,
            ThreadsCallback(config.torch_threads, config.update_threads),
            *([CriticWarmupCallback(config.critic_warmup)] if config.critic_warmup else []),
            *([bc] if bc is not None else []),
        ]
    )
    started = time.perf_counter()
    model.learn(steps, callback=callbacks, reset_num_timesteps=resume is None, tb_log_name=config.name)
    wall = time.perf_counter() - started
    if checkpointer.interrupted is not None:  # stopped on request: no final model, no summary (not finished)
        curriculum.save_state()
        env.close()
        raise TrainingInterrupted(
            f"{out}: stopped on request at {model.num_timesteps} steps; resume from {checkpointer.interrupted}"
        )
    final = out / f"{config.name}-{track}.zip"
    model.save(final)
    record_written(out, final)
    if isinstance(env, VecNormalize):
        env.save(str(out / "vecnormalize.pkl"))
        record_written(out, out / "vecnormalize.pkl")
    curriculum.save_state()
    env.close()
    summary: dict[str, Any] = {
        "config": config.name,
        "track": track,
        "seed": seed,
        "timesteps": int(model.num_timesteps),
        "resumed_at": started_at if resume is not None else None,
        "env_seed": resume_seed(seed, started_at, config.n_envs),
        "wall_s": round(wall, 1),  # of this call (progress.csv's wall_s adds up the resumed parts)
        "samples_per_s": round((model.num_timesteps - started_at) / wall, 1),
        "level": curriculum.level,
        "promotions": curriculum.promotions,
        # Time to solve: steps and wall clock to each promotion (and whether the bar or the budget promoted),
        # and to the first time the rolling success at the last level reached promote_at.
        "time_to_solve": {"promotions": curriculum.promotions, "solved": curriculum.solved},
        "device": str(model.device),
        "machine": machine_description(),
        # The load averages (1, 5, 15 min) as training ended: a run that shared its cores is slower per step.
        "load_at_end": [round(x, 2) for x in os.getloadavg()],
        "checkpoint": str(final),
        "init_from": init_from,
    }
    if bc is not None and bc.distances:
        summary["bc_mse_last"] = round(bc.distances[-1], 6)  # the policy's distance from its start, last rollout
    if eval_episodes > 0:
        evaluator = Evaluator(  # this run's own checkpoint, trusted if what it loads is what this run wrote
            str(final), [f"RaceObs-{track}-v0"], episodes=eval_episodes, out_dir=out / "eval",
            trust_code=own_policy_trust(out, final, trust_code),
        )  # fmt: skip
        result = evaluator.run(progress=False).iloc[0]
        summary["eval"] = {k: _plain(result[k]) for k in ("n", "successes", "success_rate", "lap_time_mean")}
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    return summary


def machine_description() -> dict[str, Any]:
    """The machine a run trained on: CPU model, cores, OS and the torch version (a summary's wall clock needs it)."""
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as info:
            cpu = next((line.split(":", 1)[1].strip() for line in info if line.startswith("model name")), cpu)
    except OSError:
        pass
    return {"cpu": cpu, "cores": os.cpu_count(), "os": platform.platform(), "torch": torch.__version__}


def archive_finished_part(out: Path, started_at: int) -> list[Path]:
    """Move the final ``summary.json`` and ``eval/`` of an earlier, finished part of a run aside before it is resumed.

    They belong to that part's final model, not to the one the resume will write: left in place the final
    evaluation would refuse ``eval/`` (another policy's records) and a failed or skipped evaluation would leave the
    old summary beside the new checkpoint. They become ``summary-<n>-steps.json`` and ``eval-<n>-steps/``, ``n``
    the steps of that final model (the summary's ``timesteps``; ``started_at`` if it cannot be read). Nothing moves
    if either name is taken. Returns the new paths (none for a killed run, which wrote neither).
    """
    summary = out / "summary.json"
    try:
        steps = int(json.loads(summary.read_text())["timesteps"])
    except (OSError, ValueError, KeyError, TypeError):
        steps = started_at
    moves = [(out / name, out / archived) for name, archived in
             (("summary.json", f"summary-{steps}-steps.json"), ("eval", f"eval-{steps}-steps"))]  # fmt: skip
    moves = [(source, target) for source, target in moves if source.exists()]
    for source, target in moves:
        if target.exists():
            raise ValueError(f"resuming into {out}: {source} and {target} both exist; move one of them away")
    for source, target in moves:
        source.rename(target)
    return [target for _, target in moves]


def _trusted_reward_stats(checkpoint: Path, trust_code: bool, written: frozenset[str]) -> tuple[Path, bytes] | None:
    """The statistics file saved beside ``checkpoint`` and its bytes, checked under the trust rule; ``None`` if none.

    ``CheckpointCallback`` writes ``<prefix>_vecnormalize_<n>_steps.pkl`` next to ``<prefix>_<n>_steps.zip``;
    a final model has ``vecnormalize.pkl`` in its run folder (:func:`racebench.agents.trust.vecnormalize_path`).
    """
    path = vecnormalize_path(checkpoint)
    if path is None:
        return None
    data = path.read_bytes()
    require_trusted(path, data, "VecNormalize statistics beside the checkpoint are unpickled", trust_code, written,
                    what="statistics")  # fmt: skip
    return path, data


def _restore_reward_stats(env: VecEnv, stats: tuple[Path, bytes] | None) -> None:
    """Load the reward-normalisation statistics (:func:`_trusted_reward_stats`) into ``env``, if both have them.

    Without them the resumed run re-estimates the return scale from scratch, which briefly changes the size of
    the advantages.
    """
    if isinstance(env, VecNormalize) and stats is not None:
        saved = load_vecnormalize_statistics(*stats)
        env.ret_rms = saved.ret_rms  # rewards only: the policy never sees normalised observations


def restore_schedules(model: Any, config: TrainConfig) -> None:
    """Rebuild a resumed model's learning-rate and clip-range schedules from its config.

    SB3 pickles them with cloudpickle, whose pickles do not load across its versions (e.g. a venv without Ray's
    pin), so the loader does not read them (:data:`racebench.agents.loading.UNREAD_SCHEDULES`) and training would
    otherwise go on at a learning rate of 0. The config is the source of truth for both.
    """
    model.learning_rate = linear_schedule(*config.learning_rate)
    model._setup_lr_schedule()
    model.clip_range = FloatSchedule(config.clip_range)


def _load_model(
    path: str | Path, device: str = "cpu", trust_code: bool = False, written: frozenset[str] = frozenset()
) -> Any:  # fmt: skip
    """The SB3 model of a checkpoint to resume, unpickled only under the trust rule (see :func:`train`)."""
    path = Path(path)
    if not path.is_file():
        raise AgentLoadError(f"checkpoint {str(path)!r} to resume does not exist")
    data = path.read_bytes()  # hashed and loaded from the same bytes
    require_trusted(path, data, "an SB3 checkpoint is unpickled when resumed", trust_code, written)
    model = SB3Agent._load(path, device, data)
    if getattr(model, "critic_stripped", False):
        raise AgentLoadError(
            f"{str(path)!r} is a policy-only export without its critic (export-policy); resume from a training "
            "checkpoint (the run folder's checkpoints/)"
        )
    return model


def resume_seed(seed: int, timesteps: int, n_envs: int) -> int:
    """Env seed of a run resumed at ``timesteps``: derived from both, below the evaluation seeds."""
    if timesteps == 0:
        return seed
    drawn = int(np.random.SeedSequence([seed, timesteps]).generate_state(1)[0])
    return drawn % (EVAL_SEED_BASE - n_envs + 1)


def _plain(value: Any) -> Any:
    if isinstance(value, float | np.floating) and not np.isfinite(value):
        return None  # JSON has no NaN: a lap time without a success is null
    if isinstance(value, tuple):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, np.generic):
        return value.item()
    return value
