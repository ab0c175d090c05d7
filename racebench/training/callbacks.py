"""The callbacks of a PPO run: curriculum, multi-scene layouts, the progress CSV, atomic checkpoints, torch
threads, critic warm-up and the behaviour-cloning terms (toward a frozen policy or the teacher's labels).
"""

from __future__ import annotations

import csv
import json
import os
import signal
import threading
import time
from collections import deque
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import torch
from stable_baselines3.common.callbacks import BaseCallback, CheckpointCallback
from stable_baselines3.common.vec_env import VecEnv

from racebench.agents.export import critic_parameter
from racebench.agents.trust import record_written
from racebench.envs.vector import TEACHER_KEY
from racebench.training.config import TrainConfig
from racebench.training.student import is_recurrent, student_features, student_head, student_unroll
from racebench.utils.files import atomic_write


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


#: Set while a stop has been asked for (:func:`checkpoint_on_sigterm`): a PPO run then stops at its next rollout end.
STOP_REQUESTED = threading.Event()
_TRAINING = threading.Event()  # a PPO run's learn() is under way in this process


class TrainingInterrupted(RuntimeError):
    """A run stopped on request (SIGTERM under :func:`checkpoint_on_sigterm`) after saving a checkpoint to resume."""


@contextmanager
def checkpoint_on_sigterm() -> Iterator[None]:
    """While active, SIGTERM to this process stops a PPO run cleanly: at the end of the rollout it is collecting it
    saves a periodic-style checkpoint (the one a resume picks up) and ``train`` raises :class:`TrainingInterrupted`.
    Outside training (an evaluation, a DAgger run) and on a second SIGTERM, the signal does what it did before.

    For the command line (``racebench train`` and ``sweep``): a session that must end sends ``kill -TERM <pid>``
    and loses no steps. Send it to the racebench process alone: its env worker processes would die of it.
    """
    if threading.current_thread() is not threading.main_thread():  # signal handlers live in the main thread
        yield
        return
    previous = signal.getsignal(signal.SIGTERM)
    previous = signal.SIG_DFL if previous is None else previous  # None: a handler not installed from Python

    def handler(signum: int, frame: Any) -> None:
        if _TRAINING.is_set() and not STOP_REQUESTED.is_set():
            STOP_REQUESTED.set()
            return
        signal.signal(signal.SIGTERM, previous)
        signal.raise_signal(signal.SIGTERM)

    signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)
        STOP_REQUESTED.clear()


class AtomicCheckpointCallback(CheckpointCallback):
    """SB3's ``CheckpointCallback`` whose files each appear whole or not at all, and which also saves and stops
    the run at the first rollout end after :data:`STOP_REQUESTED` is set (:attr:`interrupted`).

    A run killed mid-save (a sweep's lost Ray worker) used to leave a truncated zip behind. Because an SB3
    archive nests torch's own zip files (``policy.pth``), a truncated one can still open as the *inner*
    archive, without the model's data, and the resumed run failed. Each file is written beside its final
    name and renamed into place; the reward statistics come first, so a checkpoint's zip implies its pkl.
    With ``run_dir`` each file's sha256 is recorded in that folder's :data:`~racebench.agents.trust.WRITTEN_FILE` once
    it is in place, so resuming from it trusts it without ``--trust-code``. ``rollout_calls``: the steps of one
    rollout (``n_steps``), where a stop's checkpoint is taken, as the periodic ones are.

    Periodic checkpoints fall on a grid of absolute steps (the first rollout end at or past each multiple of
    ``save_freq`` vector steps), not counted from where a resumed part started: a run resumed at 2.66 M steps
    still saves at 3.0 M and 4.0 M, the points its validation curve is flown at.
    """

    def __init__(
        self, *args: Any, run_dir: str | Path | None = None, rollout_calls: int | None = None, **kwargs: Any
    ) -> None:
        super().__init__(*args, **kwargs)
        self.run_dir = run_dir
        self.rollout_calls = rollout_calls or self.save_freq
        self.interrupted: Path | None = None  # the checkpoint a stop on request saved
        self.next_save = 0  # env steps: the next grid point, set when training starts

    def _on_training_start(self) -> None:
        _TRAINING.set()
        self._advance_grid(self.model.num_timesteps)

    def _on_training_end(self) -> None:
        _TRAINING.clear()

    def _on_step(self) -> bool:
        rollout_end = self.n_calls % self.rollout_calls == 0
        stop = STOP_REQUESTED.is_set() and rollout_end
        periodic = rollout_end and self.num_timesteps >= self.next_save
        if periodic:
            self._advance_grid(self.num_timesteps)
        if periodic or stop:
            normalizer = self.model.get_vec_normalize_env()
            if self.save_vecnormalize and normalizer is not None:
                stats = Path(self._checkpoint_path("vecnormalize_", extension="pkl"))
                _save_atomically(stats, normalizer.save)
                self._record(stats)
            checkpoint = Path(self._checkpoint_path(extension="zip"))
            _save_atomically(checkpoint, self.model.save)
            self._record(checkpoint)
            if stop:
                self.interrupted = checkpoint
                return False  # SB3 ends learn() here
        return True

    def _advance_grid(self, steps: int) -> None:
        """Set :attr:`next_save` to the first multiple of the period (``save_freq`` vector steps) after ``steps``."""
        period = self.save_freq * self.model.n_envs
        self.next_save = (steps // period + 1) * period

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


def _read_progress(path: Path) -> pd.DataFrame | None:
    """The progress CSV of a run, or ``None`` if there is none yet."""
    if not path.exists() or path.stat().st_size == 0:
        return None
    return pd.read_csv(path)
