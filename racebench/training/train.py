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
4. PPO (``RecurrentPPO`` with :class:`~racebench.training.policies.RecurrentGRUPolicy`, or ``PPO``; torch
   threads switched around the update by :class:`ThreadsCallback`), with
   TensorBoard logs, a CSV row per update (:class:`ProgressCSVCallback`), periodic checkpoints, resume,
   and a final evaluation with the common evaluator.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import os
import platform
import time
import warnings
from collections import deque
from dataclasses import dataclass, field, fields
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import torch
import yaml
from stable_baselines3.common.callbacks import BaseCallback, CallbackList, CheckpointCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv, VecEnv, VecNormalize

from racebench.agents import record_written, written_sha256
from racebench.evaluation import EVAL_SEED_BASE
from racebench.records import atomic_write, sha256_file
from racebench.registration import CURRICULUM
from racebench.sb3 import make_sb3_vec_env
from racebench.track import BUILTIN_TRACKS
from racebench.training.policies import ACTION_OUTPUTS, CNN_KINDS
from racebench.vector import TEACHER_KEY
from racebench.yamlfile import read_yaml

BASELINES: tuple[str, ...] = (
    "vision-ppo",
    "state-ppo",
    "vision-no-gru",
    "vision-no-avoid",
    "vision-one-step",
    "vision-com",
    "vision-ppo-fast",
    "vision-distill",
    "vision-distill-ppo",
)

BC_TARGETS: tuple[str, ...] = ("init", "teacher")  # TrainConfig.bc_target: the frozen init_from policy, the teacher


def baseline_path(name_or_path: str | Path) -> Path:
    """Resolve a built-in baseline name (:data:`BASELINES`) or a YAML file path to a path."""
    if str(name_or_path) in BASELINES:
        return Path(str(resources.files("racebench.configs").joinpath(f"{name_or_path}.yaml")))
    path = Path(name_or_path)
    if not path.is_file():
        raise ValueError(
            f"config {str(name_or_path)!r} is neither a built-in baseline {BASELINES} nor an existing file"
        )
    return path


def load_config(name_or_path: str | Path) -> Any:
    """A training config by built-in name or YAML path: :class:`TrainConfig` (PPO, the default ``method``) or,
    for ``method: dagger``, :class:`racebench.training.dagger.DaggerConfig`."""
    path = baseline_path(name_or_path)
    data = read_yaml(path)
    if isinstance(data, dict) and data.get("method", "ppo") == "dagger":
        from racebench.training.dagger import DaggerConfig

        return DaggerConfig.from_yaml(path)
    return TrainConfig.from_yaml(path)


def run_training(
    config: Any, track: str, steps: int, seed: int, out: str | Path | None, resume: str | Path | None = None,
    eval_episodes: int = 10, device: str = "auto", checkpoint_every: int = 50_000, trust_code: bool = False,
) -> dict[str, Any]:  # fmt: skip
    """Train ``config`` (from :func:`load_config`) on ``track``: PPO through :func:`train`, DAgger through
    :func:`racebench.training.dagger.distill` with ``ceil(steps / steps_per_iteration)`` iterations. As for
    PPO, with ``resume`` the ``steps`` are the steps to add; a DAgger run resumes from its run folder (its
    whole state is kept there, not in a zip), so ``resume`` must name that folder. ``trust_code``: see :func:`train`
    (a DAgger resume reads tensors and arrays only and needs no trust)."""
    from racebench.training.dagger import DaggerConfig, completed_iterations, distill

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


@dataclass
class TrainConfig:
    """A training configuration (one baseline). See ``baselines/*.yaml`` for annotated examples."""

    name: str
    obs_mode: str = "vision"
    recurrent: bool = True
    reward_weights: dict[str, float] = field(default_factory=dict)
    curriculum: bool = True
    start_level: int = 1
    promote_at: float = 0.8
    window: int = 100
    # Steps a level may take before promotion anyway (levels below the last; none: promotion by the bar only).
    # An obstacle-blind policy may never reach the bar at level 2 (state-ppo stalled there for 2.9M steps).
    level_budget: dict[int, int] = field(default_factory=dict)
    levels: dict[int, dict[str, Any]] = field(default_factory=lambda: {k: dict(v) for k, v in CURRICULUM.items()})
    scene_groups: dict[int, int] = field(default_factory=lambda: {1: 2, 2: 4, 3: 8})
    start_spread: tuple[float, float, float] = (0.5, 0.5, 0.5)
    start_mode: str = "gates"  # RaceEnv start_mode: "gates" starts episodes before any gate (paper Sec. III-C.2)
    gate_shift: float = 0.3
    gate_shift_z: float | None = None  # vertical gate shift (default gate_shift; the paper: ±1 m x/y, ±0.3 m z)
    depth_noise_std: float = 0.02
    renderer: str | None = "raycast"  # training depth: the tested TinyRenderer match, ~30x faster than PyBullet's
    n_envs: int = 8
    vec_env: str = "race"  # "race": batched RaceSB3VecEnv; "subproc"/"dummy": SB3's own VecEnvs of RaceEnvs
    num_processes: int = 2  # processes stepping the envs ("race" only); one per core
    n_steps: int = 256
    batch_size: int = 512
    n_epochs: int = 5
    learning_rate: tuple[float, float] = (1e-4, 1e-5)
    gamma: float = 0.99
    gae_lambda: float = 0.95
    clip_range: float = 0.2
    ent_coef: float = 0.0
    normalize_reward: bool = True  # SB3's VecNormalize on rewards only (observations are already scaled)
    log_std_init: float = 0.0  # initial log σ of the Gaussian policy (SB3's default 0: σ = 1 on [-1, 1] actions)
    gru_hidden: int = 256
    critic_gru: bool = True  # the critic's own GRU (the paper's method); False: an MLP critic on the features
    net_arch: tuple[int, ...] = (192, 96)
    cnn: str = "strided"  # depth CNN, see racebench.training.policies.depth_cnn ("paper": conv + max-pool)
    # Candidate actions of the actor's output (1: SB3's linear mean). >= 2: a MixtureActionHead, the deterministic
    # action is the highest-scoring candidate; its scores learn only from a DAgger student's mixture loss
    # (racebench.training.dagger), so a PPO run takes it only to fine-tune such a student (init_from; train refuses
    # it otherwise).
    action_components: int = 1
    # What the actor outputs (racebench.training.policies.ACTION_OUTPUTS): "ctbr", the env's action, or "acceleration",
    # a command that racebench.control.command_to_ctbr flies from the observation (a DAgger student taught the fast
    # expert's commands; the recurrent policy only; PPO refuses it: its env steps take CTBR).
    action_output: str = "ctbr"
    torch_threads: int = 1  # learner threads while collecting: more oversubscribes the cores the env workers use
    update_threads: int = 2  # learner threads during the PPO update, when the env workers are idle
    # Fine-tuning: a checkpoint whose policy weights start the run ({track} and {seed} are filled in; only its
    # tensors are read, no pickled code) and the steps at the start during which only the critic learns.
    init_from: str | None = None
    critic_warmup: int = 0
    # Behaviour cloning to the init_from policy while fine-tuning (0: none): after each PPO update, one gradient
    # step on bc_coef x the mean squared distance between the policy's deterministic actions and the frozen
    # initial policy's along the last rollout (StudentBCCallback), so PPO improves the student without forgetting it
    bc_coef: float = 0.0
    # What bc_coef pulls towards: "init" (the frozen init_from policy, StudentBCCallback) or "teacher" (the privileged
    # teacher's action for every state the policy visits, TeacherBCCallback: DAgger's labels on PPO's own rollouts).
    # Why "teacher": fine-tuning held to the student lands at S 83-86 %, Circle 75-77 %, J 88-89 % whichever student
    # it starts from, with most failures on obstacles the teacher avoids from the same states.
    bc_target: str = "init"
    # The teacher of bc_target "teacher": FastPlannerAgent kwargs (default: the vision-distill students' teacher).
    teacher: dict[str, Any] = field(
        default_factory=lambda: {"gate_clearance": 0.5, "wanted_clearance": 0.6, "integral_gain": 0.0}
    )

    @classmethod
    def from_yaml(cls, path: str | Path) -> TrainConfig:
        """Load and validate a config file or a built-in baseline name (``"vision-ppo"``, ...; see
        :data:`BASELINES`) with ``yaml.safe_load``; unknown keys are errors."""
        path = baseline_path(path)
        data = read_yaml(path)
        if not isinstance(data, dict):
            raise ValueError(f"{path}: expected a mapping at the top level")
        method = data.pop("method", "ppo")
        if method != "ppo":
            raise ValueError(f"{path}: method {method!r} is not PPO: load it with racebench.training.train.load_config")
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f"{path}: unknown key {unknown[0]!r} (known: {sorted(known)})")
        if "name" not in data:
            raise ValueError(f"{path}: missing key 'name'")
        for key in ("levels", "scene_groups", "level_budget"):
            if key in data:
                data[key] = {int(k): v for k, v in data[key].items()}
        for key in ("start_spread", "learning_rate", "net_arch"):
            if key in data:
                data[key] = tuple(data[key])
        config = cls(**data)
        config.validate(str(path))
        return config

    def validate(self, source: str = "config") -> None:
        """Raise ``ValueError`` naming the first bad setting."""
        teacher_problem = self.teacher_error()
        checks = [
            (self.obs_mode in ("vision", "state"), "obs_mode must be 'vision' or 'state'"),
            (self.start_mode in ("track", "gates"), "start_mode must be 'track' or 'gates'"),
            (self.start_level in self.levels, f"start_level must be one of {sorted(self.levels)}"),
            (sorted(self.levels) == list(range(1, len(self.levels) + 1)), "levels must be numbered 1, 2, ..., n"),
            (0 < self.promote_at <= 1, "promote_at must be in (0, 1]"),
            (self.window >= 1, "window must be >= 1"),
            (self.n_envs >= 1, "n_envs must be >= 1"),
            (self.vec_env in ("race", "subproc", "dummy"), "vec_env must be 'race', 'subproc' or 'dummy'"),
            (1 <= self.num_processes <= self.n_envs, "num_processes must be in [1, n_envs]"),
            ((self.n_envs * self.n_steps) % self.batch_size == 0, "n_envs * n_steps must be a multiple of batch_size"),
            (len(self.learning_rate) == 2 and min(self.learning_rate) > 0, "learning_rate must be [start, end] > 0"),
            (all(k >= 1 for k in self.scene_groups.values()), "scene_groups values must be >= 1"),
            (
                all(k in self.levels and k < max(self.levels) for k in self.level_budget)
                and all(isinstance(v, int) and v >= 1 for v in self.level_budget.values()),
                "level_budget must map levels below the last to step counts >= 1",
            ),
            (self.cnn in CNN_KINDS, f"cnn must be one of {CNN_KINDS}"),
            (self.action_components >= 1, "action_components must be >= 1"),
            (self.action_components == 1 or self.recurrent, "action_components >= 2 needs the recurrent (GRU) policy"),
            (self.action_output in ACTION_OUTPUTS, f"action_output must be one of {ACTION_OUTPUTS}"),
            (self.action_output == "ctbr" or self.recurrent, "action_output acceleration needs the recurrent policy"),
            (self.torch_threads >= 1 and self.update_threads >= 1, "torch_threads and update_threads must be >= 1"),
            (self.critic_warmup >= 0, "critic_warmup must be >= 0"),
            (self.bc_coef >= 0.0, "bc_coef must be >= 0"),
            (self.bc_target in BC_TARGETS, f"bc_target must be one of {BC_TARGETS}"),
            (
                self.bc_coef == 0.0 or self.bc_target != "init" or self.init_from is not None,
                "bc_coef needs init_from (the policy to stay near) with bc_target 'init'",
            ),
            (
                self.bc_coef == 0.0 or self.bc_target != "teacher" or self.vec_env == "race",
                "bc_target 'teacher' needs vec_env 'race' (its envs carry the teacher's labels)",
            ),
            (teacher_problem is None, f"teacher: {teacher_problem}"),
        ]
        for ok, message in checks:
            if not ok:
                raise ValueError(f"{source}: {message}")

    def teacher_error(self) -> str | None:
        """Why ``teacher`` is not a valid set of ``FastPlannerAgent`` kwargs, else ``None``."""
        from racebench.planner import FastPlannerAgent

        if not isinstance(self.teacher, dict):
            return f"must be a mapping of FastPlannerAgent settings, got {self.teacher!r}"
        try:
            FastPlannerAgent(**self.teacher)
        except (TypeError, ValueError) as exc:
            return str(exc)
        return None

    def level_kwargs(self, level: int) -> dict[str, Any]:
        """``RaceEnv.set_task`` kwargs of a curriculum level, with this config's reward overrides on top."""
        kwargs = dict(self.levels[level])
        kwargs["reward_weights"] = {**kwargs.get("reward_weights", {}), **self.reward_weights}
        return kwargs

    def env_kwargs(self, track: str) -> dict[str, Any]:
        """Constructor kwargs of every training env (at the starting level)."""
        level = self.level_kwargs(self.start_level)
        kwargs = {
            "track": track,
            "obs_mode": self.obs_mode,
            "start_spread": self.start_spread,
            "start_mode": self.start_mode,
            "gate_shift": self.gate_shift,
            "gate_shift_z": self.gate_shift_z,
            "depth_noise_std": self.depth_noise_std,
            "density": level.get("density", 3),
            "desired_speed": level.get("desired_speed", 8.0),
            "reward_weights": level["reward_weights"],
        }
        if self.renderer is not None:
            kwargs["renderer"] = self.renderer
        return kwargs


def is_lap(info: dict[str, Any]) -> bool:
    """Whether a finished episode started at the track start (``start_mode="gates"`` also starts mid-track)."""
    return int(info.get("start_gate", 0)) == 0


class CurriculumCallback(BaseCallback):
    """Promote to the next level when the rolling success rate over ``window`` episodes reaches ``promote_at``
    (``"by": "bar"``), or when the level has used its ``level_budget`` of steps (``"by": "budget"``).

    Only episodes from the track start count (:func:`is_lap`): success then means a whole run, as evaluated.
    After a promotion, episodes that began at the old level do not count for the new one (``RaceEnv.set_task``
    applies at each env's next reset). At the last level, the first time the rolling success reaches
    ``promote_at`` is recorded as ``solved`` (time to solve). ``clock`` (set by :func:`train`) gives the run's
    wall-clock seconds, resumed parts included, for the promotion and solve records.
    """

    def __init__(
        self,
        config: TrainConfig,
        level: int | None = None,
        verbose: int = 0,
        state_file: Path | None = None,
        promotions: list[dict[str, Any]] | None = None,
        solved: dict[str, Any] | None = None,
    ) -> None:
        super().__init__(verbose)
        self.config = config
        self.level = config.start_level if level is None else level
        self.successes: deque[bool] = deque(maxlen=config.window)
        self.promotions: list[dict[str, Any]] = list(promotions or [])
        self.solved = solved
        self.state_file = state_file
        self.episode_level: np.ndarray | None = None  # the level each env's running episode began at
        self.clock: Any = None

    @property
    def level_started_at(self) -> int:
        """Timestep at which the current level began (0 for the start level)."""
        return max([0] + [int(p["timestep"]) for p in self.promotions if int(p["level"]) == self.level])

    def save_state(self) -> None:
        """Write level, promotions and solve to ``state_file`` (at every change, so a killed run can resume)."""
        if self.state_file is not None:
            state = {"level": self.level, "promotions": self.promotions, "solved": self.solved}
            atomic_write(self.state_file, json.dumps(state))

    def _stamp(self) -> dict[str, Any]:
        stamp: dict[str, Any] = {"timestep": int(self.num_timesteps)}
        if self.clock is not None:
            stamp["wall_s"] = round(float(self.clock()), 1)
        return stamp

    @property
    def last_level(self) -> int:
        """The highest curriculum level."""
        return max(self.config.levels)

    def record(self, success: bool) -> None:
        """Count one finished episode; promote if the window is full and good enough."""
        self.successes.append(bool(success))
        full = len(self.successes) == self.successes.maxlen
        if self.config.curriculum and full and np.mean(self.successes) >= self.config.promote_at:
            if self.level < self.last_level:
                self.promote("bar")
            elif self.solved is None:
                self.solved = {"level": self.level, **self._stamp()}
                self.save_state()

    def promote(self, by: str = "bar") -> None:
        """Move every env to the next level and log it (``by``: ``"bar"`` or ``"budget"``)."""
        self.level += 1
        self.training_env.env_method("set_task", **self.config.level_kwargs(self.level))
        # Shared layouts were drawn at the old level: fresh scenes until the next rollout regroups the envs.
        self.training_env.env_method("set_layout", None)
        self.successes.clear()
        self.promotions.append({"level": self.level, **self._stamp(), "by": by})
        self.save_state()
        if self.verbose:
            print(f"curriculum: level {self.level} at step {self.num_timesteps} (by {by})")

    def _on_training_start(self) -> None:
        self.episode_level = np.full(self.training_env.num_envs, self.level)
        self.save_state()

    def _on_step(self) -> bool:
        # Envs that finished this step were reset inside the VecEnv step, before any promotion below.
        level_at_reset = self.level
        for i, (done, info) in enumerate(zip(self.locals["dones"], self.locals["infos"], strict=True)):
            if not done:
                continue
            if is_lap(info) and self.episode_level[i] == self.level:
                self.record(info.get("is_success", False))
            self.episode_level[i] = level_at_reset
        budget = self.config.level_budget.get(self.level)
        if self.config.curriculum and budget and self.num_timesteps - self.level_started_at >= budget:
            self.promote("budget")
        self.logger.record("curriculum/level", self.level)
        return True


class MultiSceneCallback(BaseCallback):
    """New shared layouts for K groups of envs at every rollout start (K from the current level)."""

    def __init__(self, config: TrainConfig, curriculum: CurriculumCallback, verbose: int = 0) -> None:
        super().__init__(verbose)
        self.config = config
        self.curriculum = curriculum
        self.history: list[dict[str, Any]] = []

    def groups(self, n_envs: int) -> list[list[int]]:
        """The env indices of each scene group at the current level (contiguous, sizes differ by ≤ 1)."""
        k = min(self.config.scene_groups.get(self.curriculum.level, n_envs), n_envs)
        return [list(map(int, g)) for g in np.array_split(np.arange(n_envs), k)]

    def _on_rollout_start(self) -> None:
        env: VecEnv = self.training_env
        groups = self.groups(env.num_envs)
        for group in groups:
            layout = env.env_method("sample_layout", indices=[group[0]])[0]
            env.env_method("set_layout", layout, indices=group)
        self.history.append({"timestep": int(self.num_timesteps), "groups": len(groups)})
        self.logger.record("curriculum/scene_groups", len(groups))

    def _on_step(self) -> bool:
        return True


class ProgressCSVCallback(BaseCallback):
    """One CSV row per PPO update: timesteps, episodes, mean return, success rate, level, samples/s.

    ``success_rate`` is over the update's episodes from the track start (whole runs, as the curriculum counts
    them); ``mean_return`` and ``episodes`` are over all of them.
    """

    COLUMNS = ("timesteps", "episodes", "mean_return", "success_rate", "level", "samples_per_s", "wall_s")

    def __init__(self, path: Path, curriculum: CurriculumCallback) -> None:
        super().__init__(0)
        self.path = path
        self.curriculum = curriculum
        self.returns: list[float] = []
        self.successes: list[bool] = []
        self.episodes = 0
        self.started = time.perf_counter()
        self.last_end = self.started
        self.last_steps = 0

    def _on_training_start(self) -> None:
        self.last_steps = self.num_timesteps
        rows = _read_progress(self.path)
        if rows is None or self.num_timesteps == 0:  # a fresh run starts a fresh file
            rows = pd.DataFrame(columns=list(self.COLUMNS))
        rows = rows.dropna(subset=["wall_s"])  # a row cut short by the kill (wall_s is written last)
        # On resume, rows logged after the checkpoint belong to the lost stretch of the killed run: drop
        # them, and continue the episode count and wall clock where the kept rows end.
        kept = rows[rows["timesteps"] <= self.num_timesteps]
        atomic_write(self.path, kept.to_csv(index=False))
        if len(kept):
            self.episodes = int(kept["episodes"].iloc[-1])
            self.started -= float(kept["wall_s"].iloc[-1])

    def _on_step(self) -> bool:
        for done, info in zip(self.locals["dones"], self.locals["infos"], strict=True):
            if done:
                self.episodes += 1
                if is_lap(info):
                    self.successes.append(bool(info.get("is_success", False)))
                if "episode" in info:
                    self.returns.append(float(info["episode"]["r"]))
        return True

    def _on_rollout_end(self) -> None:
        # End-to-end samples/s: the previous update plus this rollout, i.e. what one training iteration costs.
        now = time.perf_counter()
        rate = (self.num_timesteps - self.last_steps) / max(now - self.last_end, 1e-9)
        self.last_end, self.last_steps = now, self.num_timesteps
        row = (
            self.num_timesteps,
            self.episodes,
            f"{np.mean(self.returns):.4f}" if self.returns else "",
            f"{np.mean(self.successes):.4f}" if self.successes else "",
            self.curriculum.level,
            f"{rate:.1f}",
            f"{now - self.started:.1f}",
        )
        with self.path.open("a", newline="") as f:
            csv.writer(f).writerow(row)
            f.flush()
        self.logger.record("rollout/success_rate_window", np.mean(self.successes) if self.successes else 0.0)
        self.returns, self.successes = [], []


class AtomicCheckpointCallback(CheckpointCallback):
    """SB3's ``CheckpointCallback`` whose files each appear whole or not at all.

    A run killed mid-save (a sweep's lost Ray worker) used to leave a truncated zip behind. Because an SB3
    archive nests torch's own zip files (``policy.pth``), a truncated one can still open as the *inner*
    archive, without the model's data, and the resumed run failed. Each file is written beside its final
    name and renamed into place; the reward statistics come first, so a checkpoint's zip implies its pkl.
    With ``run_dir`` each file's sha256 is recorded in that folder's :data:`~racebench.agents.WRITTEN_FILE` once
    it is in place, so resuming from it trusts it without ``--trust-code``.
    """

    def __init__(self, *args: Any, run_dir: str | Path | None = None, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.run_dir = run_dir

    def _on_step(self) -> bool:
        if self.n_calls % self.save_freq == 0:
            normalizer = self.model.get_vec_normalize_env()
            if self.save_vecnormalize and normalizer is not None:
                stats = Path(self._checkpoint_path("vecnormalize_", extension="pkl"))
                _save_atomically(stats, normalizer.save)
                self._record(stats)
            checkpoint = Path(self._checkpoint_path(extension="zip"))
            _save_atomically(checkpoint, self.model.save)
            self._record(checkpoint)
        return True

    def _record(self, path: Path) -> None:
        if self.run_dir is not None:
            record_written(self.run_dir, path)


def _save_atomically(path: Path, save: Any) -> None:
    """Call ``save(partial)`` on a sibling path, then rename it to ``path`` (atomic on one file system)."""
    partial = path.with_name(f"{path.stem}.partial{path.suffix}")  # keeps the suffix SB3 checks for
    save(str(partial))
    os.replace(partial, path)


class ThreadsCallback(BaseCallback):
    """Give the learner ``update`` torch threads for the PPO update and ``collect`` while collecting rollouts.

    While collecting, the env workers keep every core busy and extra torch threads only contend with them
    (measured 7× slower updates with torch's default); during the update the workers sleep.
    """

    def __init__(self, collect: int, update: int) -> None:
        super().__init__(0)
        self.collect, self.update = collect, update

    def _on_rollout_start(self) -> None:
        torch.set_num_threads(self.collect)

    def _on_rollout_end(self) -> None:
        torch.set_num_threads(self.update)

    def _on_step(self) -> bool:
        return True


CRITIC_PREFIXES: tuple[str, ...] = (
    "lstm_critic.", "critic.", "mlp_extractor.value_net.", "value_net.", "vf_features_extractor.",
)  # fmt: skip


def critic_parameter(name: str) -> bool:
    """Whether a policy parameter belongs to the critic only (its GRU, MLP and head); all else acts."""
    return name.startswith(CRITIC_PREFIXES)


class CriticWarmupCallback(BaseCallback):
    """Freeze everything but the critic for the first ``steps`` steps (fine-tuning a pre-trained actor).

    A policy initialised from an imitation-learned student starts with a critic that knows nothing; PPO's
    first advantages are then noise, and its updates would unlearn the student before the critic catches up.
    During the warm-up the features, the actor's GRU and MLP, the action head and log σ take no gradient
    (Adam skips parameters without one), so only the value loss trains. Decided from the step count at each
    update, so a resumed run freezes exactly when a run never stopped would.
    """

    def __init__(self, steps: int) -> None:
        super().__init__(0)
        self.steps = steps

    def _set(self) -> None:
        warm = self.model.num_timesteps < self.steps
        for name, parameter in self.model.policy.named_parameters():
            parameter.requires_grad_(critic_parameter(name) or not warm)

    def _on_training_start(self) -> None:
        self._set()

    def _on_rollout_end(self) -> None:
        self._set()

    def _on_step(self) -> bool:
        return True


def mean_actions_along(
    policy: Any, obs: dict[str, np.ndarray] | np.ndarray, starts: np.ndarray, hidden: torch.Tensor | None
) -> tuple[torch.Tensor, torch.Tensor | None]:  # fmt: skip
    """A policy's deterministic actions (before clipping) along a rollout: ``(time, envs, actions)``.

    ``obs`` is the rollout buffer's (``(time, envs, ...)`` arrays), ``starts`` ``(time, envs)`` marks each
    episode's first step. A recurrent policy's state ``hidden`` ``(1, envs, H)`` is carried step by step and
    zeroed at every start, as the policy acted; the state after the last step is returned with the actions
    (``None`` for a feed-forward policy). Gradients flow unless the caller disables them.
    """
    from racebench.training.dagger import is_recurrent, student_features, student_head, student_unroll

    steps, envs = starts.shape
    if isinstance(obs, dict):
        flat = {k: torch.as_tensor(v.reshape(steps * envs, *v.shape[2:]), device=policy.device) for k, v in obs.items()}
    else:
        flat = torch.as_tensor(obs.reshape(steps * envs, *obs.shape[2:]), device=policy.device)
    features = student_features(policy, flat).view(steps, envs, -1)
    if not is_recurrent(policy):
        return student_head(policy, features), None
    keep = torch.as_tensor(1.0 - starts, dtype=torch.float32, device=policy.device).view(steps, 1, envs, 1)
    actions = []
    for t in range(steps):
        action, output = student_unroll(policy, features[t : t + 1], hidden * keep[t])
        actions.append(action[0])
        hidden = output[-1:]
    return torch.stack(actions), hidden


class StudentBCCallback(BaseCallback):
    """Keep a fine-tuned policy near the policy it started from: behaviour cloning between PPO updates.

    At each rollout's end the frozen initial policy (``anchor``, e.g. the DAgger student) is run along the
    rollout from its own recurrent state, carried over rollouts, giving its deterministic action at every
    step. After the PPO update (at the next rollout's start, when the buffer is about to be refilled) the
    policy is unrolled along the same rollout from the recurrent state it had when the rollout began, and
    takes one gradient step, with PPO's optimizer and gradient clipping, on ``coef`` x the mean squared
    distance between its actions and the anchor's. While the actor is frozen (a critic warm-up) the step is
    skipped. ``distances`` holds each rollout's distance before its step (also logged as ``train/bc_mse``).
    """

    def __init__(self, anchor: Any, coef: float, threads: int) -> None:
        super().__init__(0)
        self.anchor, self.coef, self.threads = anchor, coef, threads
        self.anchor_hidden: torch.Tensor | None = None
        self.pending: tuple | None = None
        self.distances: list[float] = []

    def _on_rollout_end(self) -> None:
        buffer = self.model.rollout_buffer
        if isinstance(buffer.observations, dict):
            obs: Any = {k: v.copy() for k, v in buffer.observations.items()}
        else:
            obs = buffer.observations.copy()
        starts = buffer.episode_starts.copy()
        recurrent = hasattr(buffer, "hidden_states_pi")
        target = self._targets(obs, starts, buffer)
        start_hidden = torch.as_tensor(buffer.hidden_states_pi[0]).clone() if recurrent else None
        self.pending = (obs, starts, start_hidden, target)

    def _targets(self, obs: Any, starts: np.ndarray, buffer: Any) -> torch.Tensor:
        """The actions to clone along the rollout just collected, ``(time, envs, actions)``: the anchor's."""
        if hasattr(buffer, "hidden_states_pi") and self.anchor_hidden is None:
            self.anchor_hidden = torch.zeros_like(torch.as_tensor(buffer.hidden_states_pi[0]))
        with torch.no_grad():
            target, self.anchor_hidden = mean_actions_along(self.anchor, obs, starts, self.anchor_hidden)
        return target

    def _on_rollout_start(self) -> None:
        if self.pending is None:
            return
        obs, starts, start_hidden, target = self.pending
        self.pending = None
        policy = self.model.policy
        if not any(p.requires_grad for n, p in policy.named_parameters() if not critic_parameter(n)):
            return  # critic warm-up: the actor takes no gradient yet
        threads = torch.get_num_threads()
        torch.set_num_threads(self.threads)
        policy.set_training_mode(True)
        actions, _ = mean_actions_along(policy, obs, starts, start_hidden)
        distance = torch.nn.functional.mse_loss(actions, target)
        policy.optimizer.zero_grad()
        (self.coef * distance).backward()
        torch.nn.utils.clip_grad_norm_(policy.parameters(), self.model.max_grad_norm)
        policy.optimizer.step()
        policy.set_training_mode(False)
        torch.set_num_threads(threads)
        self.distances.append(float(distance.item()))
        self.logger.record("train/bc_mse", self.distances[-1])

    def _on_step(self) -> bool:
        return True


class TeacherBCCallback(StudentBCCallback):
    """:class:`StudentBCCallback` towards a privileged teacher: DAgger's labels on PPO's own rollouts.

    The training envs carry the teacher (``RaceSB3VecEnv(teacher=...)``), which labels every observation they
    return with its action for that state (``infos[i]["teacher_action"]``; the reset infos for the first
    observations). The labels of a rollout's observations are the ones returned with them, i.e. by the reset or
    the step before, so the last label of each rollout starts the next one. Between PPO updates the policy takes
    one gradient step on ``coef`` x the mean squared distance between its deterministic actions along the rollout
    and these labels. The policy never sees a label: they reach only this callback.
    """

    def __init__(self, coef: float, threads: int) -> None:
        super().__init__(None, coef, threads)
        self.labels: list[np.ndarray] = []

    @staticmethod
    def _stack(infos: Any) -> np.ndarray:
        try:
            return np.stack([np.asarray(info[TEACHER_KEY], dtype=np.float32) for info in infos])
        except KeyError:
            raise RuntimeError("TeacherBCCallback: the training envs carry no teacher labels") from None

    def _on_training_start(self) -> None:
        reset_infos = self.training_env.unwrapped.reset_infos  # the labels of the observations PPO starts from
        self.labels = [self._stack(reset_infos)]

    def _on_rollout_start(self) -> None:
        super()._on_rollout_start()
        self.labels = self.labels[-1:]  # the label of the observation this rollout starts from

    def _on_step(self) -> bool:
        self.labels.append(self._stack(self.locals["infos"]))
        return True

    def _targets(self, obs: Any, starts: np.ndarray, buffer: Any) -> torch.Tensor:
        steps = starts.shape[0]
        if len(self.labels) != steps + 1:
            raise RuntimeError(f"TeacherBCCallback: {len(self.labels) - 1} labelled steps in a rollout of {steps}")
        return torch.as_tensor(np.stack(self.labels[:steps]), device=self.model.policy.device)


def policy_weights(path: str | Path, model: Any) -> dict[str, torch.Tensor]:
    """The policy tensors of the SB3 checkpoint ``path``, checked to fit ``model``'s policy (the same network).

    Only the tensors are read (``load_from_zip_file(load_data=False)``: nothing unpickled, so no code runs).
    """
    from stable_baselines3.common.save_util import load_from_zip_file

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"init_from: {path} is not a file (train or download the policy it names first)")
    try:
        _, params, _ = load_from_zip_file(path, load_data=False, device=model.device)
    except Exception as exc:  # noqa: BLE001 - a bad archive is named, whatever the zip/torch error
        why = " ".join(str(exc).split())[:300]  # torch's weights_only refusal spans many lines
        raise ValueError(f"init_from: {path} is not an SB3 checkpoint ({type(exc).__name__}: {why})") from None
    weights = params.get("policy") if params else None
    if weights is None:
        raise ValueError(f"init_from: {path} holds no policy weights")
    mine = model.policy.state_dict()
    if set(weights) != set(mine) or any(weights[k].shape != mine[k].shape for k in mine):
        raise ValueError(f"init_from: {path} is another network than this config's ({model.policy.__class__.__name__})")
    return weights


def load_policy_weights(model: Any, path: str | Path, log_std: float) -> None:
    """Start ``model``'s policy from the weights in the SB3 checkpoint ``path`` (:func:`policy_weights`).

    log σ is set to ``log_std``: an imitation-learned student never trained it.
    """
    model.policy.load_state_dict(policy_weights(path, model))
    with torch.no_grad():
        model.policy.log_std.fill_(log_std)


def frozen_initial_policy(model: Any, path: str | Path) -> Any:
    """A frozen copy of ``model``'s policy holding the weights of ``path`` (the anchor of ``bc_coef``)."""
    import copy

    anchor = copy.deepcopy(model.policy)
    anchor.load_state_dict(policy_weights(path, model))
    anchor.set_training_mode(False)
    for parameter in anchor.parameters():
        parameter.requires_grad_(False)
    return anchor


def _read_progress(path: Path) -> pd.DataFrame | None:
    """The progress CSV of a run, or ``None`` if there is none yet."""
    if not path.exists() or path.stat().st_size == 0:
        return None
    return pd.read_csv(path)


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


def linear_schedule(start: float, end: float):
    """Learning rate decaying linearly from ``start`` to ``end`` over training (SB3 passes progress 1 → 0)."""

    def schedule(progress_remaining: float) -> float:
        return end + (start - end) * progress_remaining

    return schedule


def make_envs(config: TrainConfig, track: str, seed: int) -> VecEnv:
    """The training VecEnv: ``n_envs`` RaceEnvs seeded ``seed + i`` (all below the evaluation seeds).

    ``vec_env="race"`` batches them in ``num_processes`` processes (:func:`racebench.sb3.make_sb3_vec_env`,
    tested equivalent to ``DummyVecEnv``); ``"subproc"``/``"dummy"`` are SB3's ``make_vec_env``.
    """
    if seed < 0 or seed + config.n_envs > EVAL_SEED_BASE:
        raise ValueError(f"training seeds must lie in [0, {EVAL_SEED_BASE - config.n_envs}] (evaluation uses the rest)")
    if config.vec_env == "race":
        env = make_sb3_vec_env(
            f"RaceObs-{track}-v0",
            n_envs=config.n_envs,
            seed=seed,
            num_processes=min(config.num_processes, config.n_envs),
            teacher=config.teacher if config.bc_coef > 0 and config.bc_target == "teacher" else None,
            **config.env_kwargs(track),
        )
    else:
        vec_cls = SubprocVecEnv if config.vec_env == "subproc" and config.n_envs > 1 else DummyVecEnv
        env = make_vec_env(
            f"RaceObs-{track}-v0",
            n_envs=config.n_envs,
            seed=seed,
            env_kwargs=config.env_kwargs(track),
            vec_env_cls=vec_cls,
        )
    if config.normalize_reward:
        # Returns scaled by their running std, as SB3's zoo does for continuous control; the monitor inside
        # still logs the true returns, and the policy never sees the statistics (nothing to save for acting).
        env = VecNormalize(env, norm_obs=False, norm_reward=True, gamma=config.gamma)
    return env


DEVICES: tuple[str, ...] = ("auto", "cpu", "cuda")


def resolve_device(device: str) -> str:
    """``"auto"`` → ``"cuda"`` when torch sees a GPU, else ``"cpu"``; ``"cuda"`` without one is an error."""
    if device not in DEVICES:
        raise ValueError(f"device must be one of {DEVICES}, got {device!r}")
    available = torch.cuda.is_available()
    if device == "auto":
        return "cuda" if available else "cpu"
    if device == "cuda" and not available:
        raise ValueError("device 'cuda': torch sees no CUDA device (torch.cuda.is_available() is False)")
    return device


def make_model(config: TrainConfig, env: VecEnv, seed: int, tensorboard: str | None, device: str = "cpu") -> Any:
    """PPO (feed-forward) or RecurrentPPO with the GRU policy, with the paper's network sizes, on ``device``."""
    from racebench.training.policies import RaceFeatures, RecurrentGRUPolicy

    features_kwargs = {"cnn": config.cnn}

    common = dict(
        n_steps=config.n_steps,
        batch_size=config.batch_size,
        n_epochs=config.n_epochs,
        learning_rate=linear_schedule(*config.learning_rate),
        gamma=config.gamma,
        gae_lambda=config.gae_lambda,
        clip_range=config.clip_range,
        ent_coef=config.ent_coef,
        seed=seed,
        device=resolve_device(device),
        tensorboard_log=tensorboard,
        verbose=0,
    )
    arch = list(config.net_arch)
    if config.recurrent:
        from sb3_contrib import RecurrentPPO

        policy_kwargs = dict(
            features_extractor_class=RaceFeatures,
            features_extractor_kwargs=features_kwargs,
            lstm_hidden_size=config.gru_hidden,
            # The critic gets its own GRU on the shared features: with sb3-contrib's shared_lstm the critic reads
            # the actor's GRU output detached, so the value loss never shapes the recurrent features; with it
            # no level-1 run learned here (baselines/experiments/README.md).
            shared_lstm=False,
            enable_critic_lstm=config.critic_gru,
            net_arch=dict(pi=arch, vf=arch),
            log_std_init=config.log_std_init,
        )
        if config.action_components > 1:  # only then: the policies saved before the key keep their kwargs
            policy_kwargs["action_components"] = config.action_components
        if config.action_output != "ctbr":
            policy_kwargs["action_output"] = config.action_output
        return RecurrentPPO(RecurrentGRUPolicy, env, policy_kwargs=policy_kwargs, **common)
    from stable_baselines3 import PPO

    # The feed-forward ablation: a dense layer of the GRU's width where the GRU was.
    wide = [config.gru_hidden, *arch]
    policy_kwargs = dict(
        features_extractor_class=RaceFeatures,
        features_extractor_kwargs=features_kwargs,
        net_arch=dict(pi=wide, vf=wide),
        log_std_init=config.log_std_init,
    )
    policy = "MultiInputPolicy" if config.obs_mode == "vision" else "MlpPolicy"
    return PPO(policy, env, policy_kwargs=policy_kwargs, **common)


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
    under the evaluator's rule (:func:`racebench.agents.require_trusted`): with ``trust_code``, if shipped, or if
    this run folder (``out``) wrote them itself, as listed in its :data:`~racebench.agents.WRITTEN_FILE` (every
    checkpoint and statistics file a run writes is recorded there); anything else is refused before it is read.
    """
    if track not in BUILTIN_TRACKS:
        raise ValueError(f"track must be one of {BUILTIN_TRACKS}, got {track!r}")
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
    callbacks = CallbackList(
        [
            curriculum,
            MultiSceneCallback(config, curriculum),
            progress,
            AtomicCheckpointCallback(
                # at rollout ends, so a resumed run loses no collected samples
                max(round(checkpoint_every / (config.n_envs * config.n_steps)), 1) * config.n_steps,
                str(out / "checkpoints"),
                config.name,
                save_vecnormalize=True,
                run_dir=out,
            ),
            ThreadsCallback(config.torch_threads, config.update_threads),
            *([CriticWarmupCallback(config.critic_warmup)] if config.critic_warmup else []),
            *([bc] if bc is not None else []),
        ]
    )
    started = time.perf_counter()
    model.learn(steps, callback=callbacks, reset_num_timesteps=resume is None, tb_log_name=config.name)
    wall = time.perf_counter() - started
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
        from racebench.evaluation import Evaluator

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


def own_policy_trust(out: str | Path, checkpoint: str | Path, trust_code: bool = False) -> bool:
    """The ``trust_code`` of the evaluation of a run's own final ``checkpoint``: whether the run folder ``out`` wrote
    it (its :data:`~racebench.agents.WRITTEN_FILE` lists its sha256), or ``trust_code`` itself.

    The ``VecNormalize`` statistics the evaluator would read beside it must be the run's too: statistics copied
    into the folder are refused (:class:`~racebench.agents.UntrustedCodeError`) rather than unpickled.
    """
    from racebench.agents import require_trusted, vecnormalize_path

    if trust_code:
        return True
    written, checkpoint = written_sha256(out), Path(checkpoint)
    stats = vecnormalize_path(checkpoint)
    if stats is not None:
        require_trusted(stats, stats.read_bytes(), "VecNormalize statistics beside the checkpoint are unpickled",
                        written=written, what="statistics")  # fmt: skip
    return checkpoint.is_file() and sha256_file(checkpoint) in written


def _trusted_reward_stats(checkpoint: Path, trust_code: bool, written: frozenset[str]) -> tuple[Path, bytes] | None:
    """The statistics file saved beside ``checkpoint`` and its bytes, checked under the trust rule; ``None`` if none.

    ``CheckpointCallback`` writes ``<prefix>_vecnormalize_<n>_steps.pkl`` next to ``<prefix>_<n>_steps.zip``;
    a final model has ``vecnormalize.pkl`` in its run folder (:func:`racebench.agents.vecnormalize_path`).
    """
    from racebench.agents import require_trusted, vecnormalize_path  # the same files the evaluator's loader reads

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
    from racebench.agents import load_vecnormalize_statistics

    if isinstance(env, VecNormalize) and stats is not None:
        saved = load_vecnormalize_statistics(*stats)
        env.ret_rms = saved.ret_rms  # rewards only: the policy never sees normalised observations


def restore_schedules(model: Any, config: TrainConfig) -> None:
    """Rebuild a resumed model's learning-rate and clip-range schedules from its config.

    SB3 pickles them with cloudpickle; a checkpoint written under another cloudpickle version (e.g. a venv without
    Ray's pin) loads without them, SB3 only warns, and training would go on at the class defaults (PPO's constant
    3e-4). The config is the source of truth for both.
    """
    from stable_baselines3.common.utils import FloatSchedule

    model.learning_rate = linear_schedule(*config.learning_rate)
    model._setup_lr_schedule()
    model.clip_range = FloatSchedule(config.clip_range)


def _load_model(
    path: str | Path, device: str = "cpu", trust_code: bool = False, written: frozenset[str] = frozenset()
) -> Any:  # fmt: skip
    """The SB3 model of a checkpoint to resume, unpickled only under the trust rule (see :func:`train`)."""
    from racebench.agents import AgentLoadError, SB3Agent, require_trusted

    path = Path(path)
    if not path.is_file():
        raise AgentLoadError(f"checkpoint {str(path)!r} to resume does not exist")
    data = path.read_bytes()  # hashed and loaded from the same bytes
    require_trusted(path, data, "an SB3 checkpoint is unpickled when resumed", trust_code, written)
    return SB3Agent._load(path, device, data)


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
