"""Teacher–student distillation with DAgger: a depth policy imitates a privileged planner.

The field's answer to the cost of learning vision-based flight from reward alone (Loquercio et al. 2021;
Xing et al. 2024): a *teacher* with privileged information (the fast expert
:class:`~racebench.planner.FastPlannerAgent` by default, or the cautious :class:`~racebench.planner.PlannerAgent`;
both plan on the true scene) labels every state the *student* visits, and the student, which sees only what a
deployed policy sees (the 17-d state and the noisy depth image), is trained by supervised regression on the
aggregate of those labels (DAgger, Ross et al. 2011). The algorithm, in full:

1. ``iteration 0``: the teacher flies; every step's observation is stored with the teacher's action.
2. ``iteration k``: each step, the student's action is executed with probability ``1 - beta_k`` (else the
   teacher's), and the teacher's action is stored for the student's observation, so the dataset covers the
   states the student itself reaches. ``beta_k = beta_decay ** k``.
3. After each collection, the student is trained for ``epochs`` passes over the whole aggregate (MSE between its
   deterministic action and the teacher's).

The student is the network of a PPO baseline config (``student``), held in that config's stable-baselines3
model so the result is an ordinary checkpoint: the common evaluator flies it, ``export_onnx`` exports it, and
PPO can fine-tune it. By default it is the paper's network (``vision-ppo``: state MLP + depth CNN → GRU(256) →
[192, 96]); ``vision-no-gru`` gives the feed-forward ablation. Training seeds are below the evaluation seeds.
Depth images are stored as uint8 (1/255 steps of normalised inverse depth, below the 0.02 depth noise).

A recurrent student is trained with truncated backpropagation through time. The aggregate keeps each
episode's steps contiguous (a *run*; :meth:`Dataset.add_segment`), cut into chunks of ``sequence_length``
steps (:meth:`Dataset.chunks`) that never cross an episode boundary. Before each fit the current student
runs, without gradient, through every run in order to give each chunk the GRU state it starts from (zero at
an episode's first step; :func:`chunk_start_states`), then minibatches of chunks are unrolled from those
states with the gradient flowing through at most ``sequence_length`` steps.

Optionally (``keep_iterations``, ``final_student``) the students of the last iterations are kept and the run's
checkpoint is their weight average, or whichever of them (or of the average) the student alone flies best on
validation scenes (``select_episodes``; :func:`choose_student`). DAgger itself (and a resumption) always continues
from the last iteration's student.
"""

from __future__ import annotations

import json
import pickle
import shutil
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from tqdm.auto import tqdm

from racebench.agents import BUILTIN_VERSIONS, load_agent, record_written
from racebench.control import acceleration_command, command_to_ctbr
from racebench.evaluation import EVAL_SEED_BASE, VALIDATION_SEED_BASE
from racebench.planner import OBSTACLE_KNOWLEDGE, FastPlannerAgent, PlannerAgent
from racebench.raycast import BatchDepthRenderer
from racebench.registration import TRACK_IDS
from racebench.training.policies import MixtureActionHead, mixture_action_loss

TEACHERS: tuple[str, ...] = ("planner-fast", "planner")  # privileged built-ins that can label every state
# The auxiliary task's target (DaggerConfig.path_aux_weight): the teacher's line this far ahead along it, m, as
# body-frame vectors from the drone in metres (a 0.2 m error on one axis then costs 0.04, the size of the action loss).
LINE_AHEAD_M: tuple[float, ...] = (1.0, 2.0, 3.0, 4.0)
PATH_AUX_SIZE = 3 * len(LINE_AHEAD_M)
# The other auxiliary target (DaggerConfig.aux_task "clearance"): the free distance (m, to the nearest obstacle or gate
# bar, capped at CLEARANCE_CAP_M) at these body-frame points ahead of the drone, a 4 x 3 grid at 1-4 m ahead and 0.8 m
# left, centre and right: what depth alone can tell, and what decides a swerve's side and size. Same size as the line.
CLEARANCE_PROBES: np.ndarray = np.array(
    [(x, y, 0.0) for x in (1.0, 2.0, 3.0, 4.0) for y in (0.8, 0.0, -0.8)], dtype=np.float64
)
CLEARANCE_CAP_M = 2.0
AUX_TASKS: tuple[str, ...] = ("line", "clearance")
# Validation scene i (choosing among a run's kept students, DaggerConfig.select_episodes) has seed
# VALIDATION_SEED_BASE + i (racebench.evaluation): above the training seeds (seed * 1000 + a counter;
# DaggerConfig.validate checks a bound on that counter) and below the evaluation seeds.
FINAL_STUDENTS: tuple[str, ...] = ("last", "average", "best")  # DaggerConfig.final_student: what the checkpoint is


@dataclass
class DaggerConfig:
    """Settings of one distillation run (all recorded in the run's ``summary.json``).

    Also a training config: a YAML file with ``method: dagger`` (``baselines/vision-distill.yaml``) is loaded
    by :func:`racebench.training.train.load_config`, so ``racebench train --config`` and ``racebench sweep``
    run it like the PPO baselines (same run folder, resume and final evaluation).
    """

    name: str = "vision-dagger"  # the run's name: checkpoint <name>-<track>.zip, sweep folders, table labels
    track: str = "S"
    env_id: str = ""  # default: RaceObs-<track>-v0, the evaluation task (density 3, v_d 8 m/s)
    # One student for several tracks (empty: the run's track alone): env i of the n_envs flies the main id of
    # train_tracks[i % len], so every track gets the same share of the steps, and the final evaluation flies each
    # track's main id (the run's --track, one of them, names the checkpoint). Why: obstacle avoidance, what ends most
    # of the students' failed laps, does not depend on the track, and more data is the one lever measured to help
    # (experiments/distill-more-data/); the issue counts a policy for all three tracks as a plus.
    train_tracks: list[str] = field(default_factory=list)
    iterations: int = 8
    steps_per_iteration: int = 20_000  # environment steps collected per iteration
    n_envs: int = 16  # envs flown side by side (one batched student call per step)
    beta_decay: float = 0.5  # P(teacher acts) = beta_decay ** iteration
    epochs: int = 2  # passes over the aggregate dataset after each collection
    # at most this many samples per fit (None: no cap): the epochs' passes, in random order, are cut here, so a
    # fit's cost stops growing with the aggregate (a cut pass draws a uniform random subset of it)
    fit_samples: int | None = None
    batch_size: int = 256
    learning_rate: float = 3e-4
    # The fit's learning rate falls linearly over the iterations, from ``learning_rate`` at the first to this at the
    # last (None: constant). Why: late in a run the student swings from one iteration to the next by up to 20 of 100
    # laps (keep_iterations below); smaller steps as the aggregate stops changing much might damp optimiser noise.
    # Measured from 3e-4 to 3e-5 on S and J (seed 0): no gain, fewer hard laps (experiments/distill-lr-decay/), so off.
    learning_rate_final: float | None = None
    # Decoupled weight decay of the fit (AdamW's; 0: plain Adam, as before). Why: a student fits the scenes it was
    # fitted on better than new ones (scripts/heldout_gap.py: loss 0.060 on its last fitted iterations against 0.086
    # on the next ones), and the weight average of its last students (final_student) is the one change that helped.
    weight_decay: float = 0.0
    # Shift each fitted chunk's depth images by a random whole number of pixels, up to this many each way (the same
    # shift for every step of a chunk; edges replicated; 0: off). The augmentation of DrQ (Kostrikov et al. 2021), for
    # the same generalisation gap: a 1-2 px shift moves an obstacle's bearing by 1.4-2.8 degrees at 64 px and 90 deg.
    augment_shift: int = 0
    # From this iteration on (None: never) the student's feature layers (depth CNN and state MLP) stop training: each
    # fit computes the aggregate's features once, without gradient, and trains the GRU and heads on them. Why: ~90 %
    # of a run's hour is fitting, and the CNN's forward and backward passes are ~45 % of a fit (docs/teacher-student.md,
    # "Cost of a run"); the data-scaling projection (experiments/data_scaling.txt) makes the targets a
    # matter of labelled steps per hour. What it may cost: the depth features stop improving with the later data.
    # Recurrent students; not with augment_shift (shifted images need the CNN's pass).
    freeze_features_after: int | None = None
    # Loss weight of an auxiliary task (0: off): a head used only in training (not part of the checkpoint) reads the
    # student's GRU output and predicts the teacher's line ahead, the points 1, 2, 3 and 4 m further along it in the
    # body frame (m; :func:`line_ahead`), and each fit minimises the action MSE plus this times that prediction's
    # MSE. Why: the students see the obstacles they hit but swerve about half as much as the line needs
    # (scripts/crash_geometry.py); asking the depth features to carry the line's bend around what is in view is
    # Loquercio et al. 2021's student output, here as a training signal for the paper's network. Recurrent students.
    path_aux_weight: float = 0.0
    # What that head predicts (its weight is path_aux_weight, named for the first task): "line", the teacher's line
    # ahead (above); "clearance", the free distance at 12 points ahead of the drone (:func:`clearance_ahead`), which
    # only the depth image can tell the student, where the line mostly follows from the gates in the state vector.
    aux_task: str = "line"
    max_samples: int = 250_000  # aggregate capacity; the oldest samples are overwritten beyond it
    gate_shift: float = 0.3  # training scenes: gates shifted ±m, as in RL training (evaluation: none)
    # their vertical shift, ±m (None: gate_shift; the paper trains with ±1 m on x/y and ±0.3 m on z)
    gate_shift_z: float | None = None
    seed: int = 0
    update_threads: int = 2
    teacher: str = "planner-fast"  # a privileged built-in: "planner-fast" (the fast expert) or "planner"
    # planner-fast's wanted clearance at gates (FastPlannerAgent.gate_clearance): 0.5 m crosses the opening's
    # centre, leaving a student that cuts the line more room to the bars
    teacher_gate_clearance: float = 0.4
    # planner-fast's wanted clearance from obstacles (FastPlannerAgent.wanted_clearance): a wider berth than the
    # default 0.45 m leaves a student that strays off the line more room before it strikes something
    teacher_wanted_clearance: float = 0.45
    # planner-fast's integral gain (FastPlannerAgent.integral_gain). Its integral sums the cross-track errors of
    # whoever flies, the student too, so its labels depend on flight history the student cannot see; 0 makes a
    # label a function of the current state (scripts/teacher_takeover.py measures what each does)
    teacher_integral_gain: float = 4.0
    # planner-fast plans again from a student that is farther than this from its line (m; None: never)
    teacher_replan_distance: float | None = None
    # What planner-fast plans around (FastPlannerAgent.obstacle_knowledge): "all" obstacles from reset (privileged),
    # or only those the student's camera has shown so far ("seen"; it plans again when one comes into view near its
    # line), so a label depends only on what the student could have seen.
    teacher_obstacles: str = "all"
    student: str = "vision-ppo"  # the PPO baseline config whose network the student is (vision-ppo: the paper's)
    # With a student of ``action_components`` >= 2 (a MixtureActionHead) the fit minimises the mixture's scaled
    # negative log-likelihood (policies.mixture_action_loss) with Gaussians of this standard deviation (in actions
    # in [-1, 1]) instead of the MSE; ignored for a single-output student.
    mixture_sigma: float = 0.2
    sequence_length: int = 32  # truncated-BPTT chunk of a recurrent student, in steps
    # Loss weight of the last ``crash_window`` steps before each crash (obstacle, gate, ground or out of bounds) of a
    # collected episode (1: unweighted).
    # Why: replayed evaluation crashes (scripts/crash_visibility.py) hit obstacles in view 0.5 s before, which the
    # teacher, handed the controls then, avoids, so the labels exist but are few. Measured at 4 it did not help (worse
    # on Circle; baselines/experiments/distill-crash-weight/), hence off by default.
    crash_weight: float = 1.0
    crash_window: int = 50  # steps (1 s at the 50 Hz control rate)
    # Probability that an episode re-flies a training scene on which an earlier episode failed (the most recent such
    # failure first), instead of a new scene; 0: every episode a new scene. A scene is flown again once at most (a
    # replay that fails does not queue it again), so scenes nobody can fly do not crowd out new ones.
    # Why: the students of different seeds fail the same evaluation scenes far beyond chance
    # (baselines/experiments/failure_overlap.txt), so what limits them is in particular layouts, and flying the
    # layouts a student fails again (as prioritised level replay does for RL) gathers labels where they are scarce.
    replay_failed: float = 0.0
    # Keep the student of each of the last ``keep_iterations`` iterations (``iterations/`` in the run folder) with
    # their weight average; with ``select_episodes`` > 0 fly each on that many validation scenes (training
    # randomisation, seeds VALIDATION_SEED_BASE + i: disjoint from training and evaluation seeds). Why: with the
    # student in control, training success swings by up to 0.3 from one iteration to the next late in a run
    # (distill-gate-centre-per-track/J: 0.47 -> 0.73 -> 0.61), far beyond its sampling error, so the last
    # iteration's student is one draw from a wide spread.
    keep_iterations: int = 0
    select_episodes: int = 0
    # The run's checkpoint (choose_student): "last" (the last iteration's student), "average" (the weight average of
    # the kept students; needs keep_iterations >= 2) or "best" (the candidate that finished most validation scenes;
    # needs select_episodes). Measured on four reruns of the shipped config (experiments/distill-select/): the
    # average of the last 6 finished 69/71/81/71 of 100 against 68/57/72/66 for the last student (pooled paired
    # 69 vs 40, p = 0.007); the validation pick was no better than the average.
    final_student: str = "last"

    @classmethod
    def from_yaml(cls, path: str | Path) -> DaggerConfig:
        """Load a ``method: dagger`` YAML config (``yaml.safe_load``; unknown keys are errors)."""
        from racebench.yamlfile import read_yaml

        data = read_yaml(path)
        if not isinstance(data, dict) or data.pop("method", None) != "dagger":
            raise ValueError(f"{path}: not a DAgger config (expected a mapping with method: dagger)")
        per_run = sorted(set(data) & {"track", "seed", "iterations"})
        if per_run:
            raise ValueError(f"{path}: {per_run[0]!r} is set per run (racebench train --track/--seed/--steps)")
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f"{path}: unknown key {unknown[0]!r} (known: {sorted(known)})")
        if "name" not in data:
            raise ValueError(f"{path}: missing key 'name'")
        for f in fields(cls):  # YAML 1.1 reads 3e-4 as a string: convert numbers, name what does not convert
            kind = str(f.type).removesuffix(" | None")  # an optional number may also be null
            if f.name in data and kind in ("int", "float") and not (data[f.name] is None and kind != f.type):
                try:
                    value = float(data[f.name])
                except (TypeError, ValueError):
                    raise ValueError(f"{path}: {f.name} must be a number, got {data[f.name]!r}") from None
                if kind == "int" and value != int(value):
                    raise ValueError(f"{path}: {f.name} must be an integer, got {data[f.name]!r}")
                data[f.name] = int(value) if kind == "int" else value
        config = cls(**data)
        config.validate(str(path))
        return config

    @property
    def num_processes(self) -> int:
        """CPUs a run uses (a sweep reserves them): one process, ``update_threads`` threads while fitting."""
        return self.update_threads

    def validate(self, source: str = "dagger") -> None:
        """Raise ``ValueError`` naming the first bad setting."""
        tracks = self.train_tracks
        checks = [
            (
                isinstance(tracks, list) and all(t in TRACK_IDS for t in tracks) and len(set(tracks)) == len(tracks),
                f"train_tracks must be a list of distinct tracks from {sorted(TRACK_IDS)}, got {tracks!r}",
            ),
            (
                not tracks or (self.n_envs % len(tracks) == 0 and not self.env_id),
                "train_tracks needs n_envs a multiple of its length (an equal share per track) and no env_id",
            ),
            (self.iterations >= 1, "iterations must be >= 1"),
            (self.steps_per_iteration >= self.n_envs >= 1, "need steps_per_iteration >= n_envs >= 1"),
            (0.0 <= self.beta_decay <= 1.0, "beta_decay must be in [0, 1]"),
            (self.epochs >= 1 and self.batch_size >= 1, "epochs and batch_size must be >= 1"),
            (self.learning_rate > 0, "learning_rate must be > 0"),
            (
                self.learning_rate_final is None or self.learning_rate_final > 0,
                "learning_rate_final must be > 0 (or null: a constant learning_rate)",
            ),
            (self.max_samples >= self.batch_size, "max_samples must be >= batch_size"),
            (
                self.fit_samples is None or self.fit_samples >= self.batch_size,
                "fit_samples must be >= batch_size (or null: no cap)",
            ),
            (0 <= self.seed < EVAL_SEED_BASE, f"seed must be in [0, {EVAL_SEED_BASE})"),
            (self.teacher in TEACHERS, f"teacher must be one of {TEACHERS}, got {self.teacher!r}"),
            (self.sequence_length >= 1, "sequence_length must be >= 1"),
            (self.mixture_sigma > 0.0, "mixture_sigma must be > 0"),
            (self.crash_weight > 0.0 and self.crash_window >= 1, "need crash_weight > 0 and crash_window >= 1"),
            (0.0 <= self.replay_failed < 1.0, "replay_failed must be in [0, 1)"),
            (self.weight_decay >= 0.0, "weight_decay must be >= 0"),
            (0 <= self.augment_shift <= 8, "augment_shift must be a whole number of pixels in [0, 8]"),
            (
                self.freeze_features_after is None or self.freeze_features_after >= 0,
                "freeze_features_after must be an iteration >= 0 (or null: never)",
            ),
            (
                self.freeze_features_after is None or self.augment_shift == 0,
                "freeze_features_after needs augment_shift 0 (a shifted image needs the CNN's pass)",
            ),
            (self.path_aux_weight >= 0.0, "path_aux_weight must be >= 0"),
            (self.aux_task in AUX_TASKS, f"aux_task must be one of {AUX_TASKS}, got {self.aux_task!r}"),
            (
                self.path_aux_weight == 0.0 or self.aux_task != "line" or self.teacher == "planner-fast",
                "path_aux_weight needs teacher planner-fast (the line it predicts is planner-fast's)",
            ),
            (self.gate_shift >= 0.0, "gate_shift must be >= 0 m"),
            (self.gate_shift_z is None or self.gate_shift_z >= 0.0, "gate_shift_z must be >= 0 m (or null)"),
            (0.0 < self.teacher_gate_clearance <= 0.5, "teacher_gate_clearance must be in (0, 0.5] m"),
            (
                self.teacher == "planner-fast" or self.teacher_gate_clearance == 0.4,
                "teacher_gate_clearance applies to teacher planner-fast only",
            ),
            (
                0.3 <= self.teacher_wanted_clearance <= 1.0,
                "teacher_wanted_clearance must be in [0.3, 1.0] m (the planner's clearance floor is 0.3)",
            ),
            (self.teacher_integral_gain >= 0.0, "teacher_integral_gain must be >= 0"),
            (
                self.teacher_replan_distance is None or self.teacher_replan_distance > 0.0,
                "teacher_replan_distance must be > 0 m (or null: never replan)",
            ),
            (
                self.teacher_obstacles in OBSTACLE_KNOWLEDGE,
                f"teacher_obstacles must be one of {OBSTACLE_KNOWLEDGE}, got {self.teacher_obstacles!r}",
            ),
            (
                self.teacher == "planner-fast"
                or (
                    self.teacher_integral_gain == 4.0
                    and self.teacher_replan_distance is None
                    and self.teacher_wanted_clearance == 0.45
                    and self.teacher_obstacles == "all"
                ),
                "teacher_integral_gain, teacher_replan_distance, teacher_wanted_clearance and teacher_obstacles apply "
                "to teacher planner-fast only",
            ),
        ]
        checks.append((self.update_threads >= 1, "update_threads must be >= 1"))
        checks.append((self.keep_iterations >= 0, "keep_iterations must be >= 0"))
        checks.append((
            self.select_episodes >= 0 and (self.select_episodes == 0 or self.keep_iterations >= 1),
            "select_episodes must be >= 0, and needs keep_iterations >= 1",
        ))  # fmt: skip
        checks.append((self.final_student in FINAL_STUDENTS,
                       f"final_student must be one of {FINAL_STUDENTS}, got {self.final_student!r}"))  # fmt: skip
        checks.append((self.final_student != "average" or self.keep_iterations >= 2,
                       "final_student 'average' needs keep_iterations >= 2"))  # fmt: skip
        checks.append((self.final_student != "best" or self.select_episodes >= 1,
                       "final_student 'best' needs select_episodes >= 1"))  # fmt: skip
        # Every step can end an episode and each starts a scene, so a run's seed counter stays below this bound.
        last_training_seed = self.seed * 1000 + self.iterations * (self.steps_per_iteration + self.n_envs)
        checks.append((
            self.select_episodes == 0 or last_training_seed <= VALIDATION_SEED_BASE,
            f"select_episodes: this run's training seeds may reach {last_training_seed}, past the validation seeds "
            f"at {VALIDATION_SEED_BASE} (a smaller seed or fewer steps)",
        ))  # fmt: skip
        checks.append((
            VALIDATION_SEED_BASE + self.select_episodes <= EVAL_SEED_BASE,
            f"select_episodes must be <= {EVAL_SEED_BASE - VALIDATION_SEED_BASE} (validation seeds stay below the "
            "evaluation seeds)",
        ))  # fmt: skip
        for ok, message in checks:
            if not ok:
                raise ValueError(f"{source}: {message}")
        from racebench.training.train import TrainConfig

        try:
            student = TrainConfig.from_yaml(self.student)
        except (OSError, ValueError) as exc:
            raise ValueError(f"{source}: student {self.student!r} is not a PPO baseline config ({exc})") from None
        if student.obs_mode != "vision":
            raise ValueError(f"{source}: student {self.student!r} must see depth (obs_mode vision)")
        if student.action_output == "acceleration" and self.teacher != "planner-fast":
            raise ValueError(f"{source}: an acceleration student ({self.student!r}) needs teacher planner-fast: its "
                             "commands are flown by planner-fast's last stage (control.command_to_ctbr)")  # fmt: skip


class Dataset:
    """The DAgger aggregate: observations (depth as uint8), the teacher's actions, each step's loss weight and its
    auxiliary target (``aux``, with ``aux_mask`` 0 where there is none; :func:`line_ahead`), a ring buffer.

    Samples are stored one episode segment at a time (:meth:`add_segment`), so consecutive indices are
    consecutive steps of one episode except where ``starts`` marks a new segment. Index 0 and the oldest
    surviving sample after an overwrite also start one (their predecessor is gone or at the far end).
    """

    def __init__(self, capacity: int, depth_size: int) -> None:
        self.state = np.zeros((capacity, 17), dtype=np.float32)
        self.depth = np.zeros((capacity, 1, depth_size, depth_size), dtype=np.uint8)
        self.action = np.zeros((capacity, 4), dtype=np.float32)
        self.weight = np.ones(capacity, dtype=np.float32)
        self.aux = np.zeros((capacity, PATH_AUX_SIZE), dtype=np.float32)
        self.aux_mask = np.zeros(capacity, dtype=np.float32)
        self.starts = np.zeros(capacity, dtype=bool)
        self.size = self.next = 0

    def add_segment(
        self, state: np.ndarray, depth: np.ndarray, action: np.ndarray, weight: np.ndarray | None = None,
        aux: np.ndarray | None = None, aux_mask: np.ndarray | None = None,
    ) -> None:  # fmt: skip
        """Store consecutive steps of one episode (depth quantised to uint8; loss weights default 1; auxiliary
        targets default none: mask 0); the first starts a sequence."""
        capacity = len(self.state)
        quantised = np.round(depth * 255.0).astype(np.uint8)
        weight = np.ones(len(state), dtype=np.float32) if weight is None else weight
        aux = np.zeros((len(state), PATH_AUX_SIZE), dtype=np.float32) if aux is None else aux
        aux_mask = np.zeros(len(state), dtype=np.float32) if aux_mask is None else aux_mask
        for k in range(len(state)):
            i = self.next
            self.state[i], self.depth[i], self.action[i] = state[k], quantised[k], action[k]
            self.weight[i], self.aux[i], self.aux_mask[i] = weight[k], aux[k], aux_mask[k]
            self.starts[i] = k == 0 or i == 0
            self.next = (i + 1) % capacity
            self.size = min(self.size + 1, capacity)
        if self.size == capacity and len(state):
            self.starts[self.next] = True  # the oldest surviving step lost its predecessor

    def chunks(self, length: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The stored steps cut into sequences of at most ``length`` that never cross a segment start.

        Returns ``(first, count, position)``: each chunk's first index, its number of steps, and its ordinal
        within its segment (0: the chunk starts a segment, so a recurrent state of zero). Chunks are in index
        order and cover every stored step exactly once.
        """
        bounds = np.flatnonzero(self.starts[: self.size])  # index 0 is always one (add_segment)
        ends = np.append(bounds[1:], self.size)
        per_run = -(-(ends - bounds) // length)
        run = np.repeat(np.arange(len(bounds)), per_run)
        position = np.arange(len(run)) - np.repeat(np.cumsum(per_run) - per_run, per_run)
        first = bounds[run] + position * length
        count = np.minimum(length, ends[run] - first)
        return first, count, position

    def batch(self, index: np.ndarray) -> dict[str, torch.Tensor]:
        """A minibatch as the student's observation dict (depth back to [0, 1] floats) plus its labels
        (``action``) and their loss weights (``weight``)."""
        return {
            **self.observations(index),
            "action": torch.from_numpy(self.action[index]),
            "weight": torch.from_numpy(self.weight[index]),
        }

    def observations(self, index: np.ndarray) -> dict[str, torch.Tensor]:
        """The student's observation dict of ``index`` alone (no labels)."""
        return {
            "state": torch.from_numpy(self.state[index]),
            "depth": torch.from_numpy(self.depth[index].astype(np.float32) / 255.0),
        }


def make_student(env: gym.Env, seed: int, student: str = "vision-ppo") -> Any:
    """The student: the network of the PPO baseline config ``student`` in its SB3 / sb3-contrib model
    (deterministic action = the actor's mean)."""
    from racebench.training.train import TrainConfig, make_model

    config = TrainConfig.from_yaml(student)
    model = make_model(config, env, seed, tensorboard=None, device="cpu")
    gru = getattr(model.policy, "lstm_actor", None)
    if gru is not None and gru.num_layers != 1:
        raise ValueError(f"student {student!r}: a {gru.num_layers}-layer GRU (the chunk states assume one layer)")
    return model


def is_recurrent(policy: Any) -> bool:
    """Whether the student carries a recurrent state (the paper's GRU network)."""
    return getattr(policy, "lstm_actor", None) is not None


def student_features(policy: Any, obs: dict[str, torch.Tensor]) -> torch.Tensor:
    """The actor's features of a batch of observations (state MLP and depth CNN, concatenated)."""
    from stable_baselines3.common.policies import BaseModel

    return BaseModel.extract_features(policy, obs, policy.pi_features_extractor)


def student_head(policy: Any, features: torch.Tensor) -> torch.Tensor:
    """The deterministic action (before clipping) from the actor's features, or from its GRU's output."""
    return policy.action_net(policy.mlp_extractor.forward_actor(features))


def student_mean(policy: Any, obs: dict[str, torch.Tensor]) -> torch.Tensor:
    """A feed-forward student's deterministic action (before clipping) for a batch of observations."""
    return student_head(policy, student_features(policy, obs))


def student_unroll(
    policy: Any, features: torch.Tensor, hidden: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:  # fmt: skip
    """A recurrent student over ``(time, batch, features)`` from the GRU state ``hidden`` ``(1, batch, H)``.

    The same layers, in the same order, as the evaluator's :meth:`racebench.agents.SB3Agent.act_batch`.
    Returns the actions ``(time, batch, 4)`` and the GRU outputs ``(time, batch, H)`` (each step's new state).
    """
    output, _ = policy.lstm_actor(features, (hidden, torch.zeros_like(hidden)))
    return student_head(policy, output), output


def observe(caster: BatchDepthRenderer, envs: list[Any], indices: list[int]) -> list[dict]:
    """The observations of ``envs[i]`` for ``i`` in ``indices``, their depth images ray-cast in one call."""
    depth = caster.render(
        [envs[i].scene for i in indices],
        np.stack([envs[i].drone.position for i in indices]),
        np.stack([envs[i].drone.rotation for i in indices]),
    )
    return [envs[i].observation(d) for i, d in zip(indices, depth, strict=True)]


def student_step(policy: Any, obs: list[dict], hidden: torch.Tensor | None) -> tuple[np.ndarray, torch.Tensor | None]:
    """The student's deterministic actions (clipped to [-1, 1]; an acceleration student's commands flown through
    :func:`~racebench.control.command_to_ctbr`, as the evaluator does) for a batch of observations, and a recurrent
    student's new GRU state from ``hidden`` ``(1, batch, H)`` (``None`` for a feed-forward one)."""
    batch = {"state": torch.from_numpy(np.stack([o["state"] for o in obs])),
             "depth": torch.from_numpy(np.stack([o["depth"] for o in obs]))}  # fmt: skip
    with torch.no_grad():  # not inference_mode: RaceFeatures converts its CNN weights on first use
        if hidden is not None:
            actions, output = student_unroll(policy, student_features(policy, batch).unsqueeze(0), hidden)
            actions, hidden = actions[0], output[-1:].clone()
        else:
            actions = student_mean(policy, batch)
    actions = actions.numpy().clip(-1.0, 1.0)
    if student_output(policy) == "acceleration":
        actions = command_to_ctbr(actions, batch["state"].numpy())
    return actions, hidden


def student_output(policy: Any) -> str:
    """What the student's actor outputs (:data:`~racebench.training.policies.ACTION_OUTPUTS`), so what it is taught:
    the teacher's CTBR actions, or its acceleration commands (:func:`~racebench.control.acceleration_command`)."""
    return getattr(policy, "action_output", "ctbr")


def line_ahead(teacher: Any, drone: Any) -> np.ndarray | None:
    """The auxiliary target at the drone's state: where the teacher's line is :data:`LINE_AHEAD_M` metres along it
    beyond the point the teacher is tracking (its index, advanced by its last ``act``), as body-frame vectors from
    the drone in metres, flattened ``(PATH_AUX_SIZE,)``; ``None`` while it has no line (a
    failed plan: its fallback flies)."""
    path = getattr(teacher, "path", None)
    if path is None:
        return None
    arc = teacher.arc
    ahead = np.searchsorted(arc, arc[teacher._index] + np.asarray(LINE_AHEAD_M))
    points = path[np.minimum(ahead, len(path) - 1)]  # past the line's end: its last point
    body = (points - drone.position) @ drone.rotation  # R^T v per row: world to body
    return body.astype(np.float32).reshape(-1)


def clearance_ahead(scene: Any, drone: Any) -> np.ndarray:
    """The "clearance" auxiliary target at the drone's state: the distance from each of :data:`CLEARANCE_PROBES`
    (body-frame points ahead of the drone, placed in the world by its pose) to the nearest obstacle or gate bar of
    ``scene`` (:meth:`racebench.scene.Scene.distance`), capped at :data:`CLEARANCE_CAP_M`, ``(PATH_AUX_SIZE,)``."""
    points = drone.position + CLEARANCE_PROBES @ drone.rotation.T  # R p per row: body to world
    return np.minimum(scene.distance(points), CLEARANCE_CAP_M).astype(np.float32)


def aux_target(task: str, teacher: Any, env: Any) -> np.ndarray | None:
    """The auxiliary target of ``task`` (:data:`AUX_TASKS`) at ``env``'s current state: :func:`line_ahead` of the
    teacher's line, or :func:`clearance_ahead` of the env's scene."""
    if task == "line":
        return line_ahead(teacher, env.drone)
    return clearance_ahead(env.scene, env.drone)


def make_path_head(hidden_size: int) -> torch.nn.Module:
    """The auxiliary head (training only): GRU output -> the auxiliary target (:func:`aux_target`)."""
    return torch.nn.Sequential(torch.nn.Linear(hidden_size, 128), torch.nn.ReLU(), torch.nn.Linear(128, PATH_AUX_SIZE))


def collect(
    envs: list[Any],
    teachers: list[PlannerAgent | FastPlannerAgent],
    policy: Any,
    beta: float,
    steps: int,
    rng: np.random.Generator,
    seeds: list[int],
    dataset: Dataset,
    crash_weight: float = 1.0,
    crash_window: int = 50,
    replay_failed: float = 0.0,
    failed: list[int] | None = None,
    aux_task: str | None = None,
    groups: list[str] | None = None,
) -> dict[str, float]:
    """Fly ``steps`` env steps with the beta-mixture of teacher and student; label every step with the teacher.

    ``envs`` are unwrapped vision ``RaceEnv``s with the ray caster (depth of all rendered in one call);
    ``seeds`` is a shared counter of training seeds. A recurrent student's state runs through every step
    whoever acts, and is zeroed when its env starts an episode. Each episode is stored as one segment when it
    ends (an episode still flying at the end is stored as far as it got). Returns the episodes' success rate
    and mean length. The last ``crash_window`` steps of an episode that ended in a crash are stored with loss
    weight ``crash_weight`` (the others with 1). With ``replay_failed`` > 0, ``failed`` is the queue of training
    scenes (seeds) whose episodes failed: each failed episode on a new scene appends its seed, and each new episode
    re-flies the last queued scene with probability ``replay_failed`` (taking it off the queue) instead of the next
    new seed. A replayed scene is not queued again: each scene is flown twice at most. With ``aux_task`` (one of
    :data:`AUX_TASKS`) every step is also stored with its auxiliary target (:func:`aux_target`; mask 0 where there
    is none: the teacher has no line). An acceleration student (:func:`student_output`) is labelled with the teacher's
    acceleration commands (its ``command`` after each ``act``) and flies its own through ``command_to_ctbr``.
    With ``groups`` (a label per env: its track) the stats also hold ``success_rate_<label>`` per label.
    """
    caster = BatchDepthRenderer(envs[0].camera)
    replaying = replay_failed > 0.0 and failed is not None
    episode_seed, is_replay = [0] * len(envs), [False] * len(envs)
    replayed = 0
    recurrent = is_recurrent(policy)
    commands = student_output(policy) == "acceleration"
    hidden = torch.zeros(1, len(envs), policy.lstm_actor.hidden_size) if recurrent else None
    segments: list[list[tuple[np.ndarray, ...]]] = [[] for _ in envs]
    no_line = np.zeros(PATH_AUX_SIZE, dtype=np.float32)

    def start(i: int) -> None:
        nonlocal replayed
        is_replay[i] = bool(replaying and failed and rng.random() < replay_failed)  # off: no draw, runs as before
        if is_replay[i]:
            episode_seed[i] = failed.pop()
            replayed += 1
        else:
            episode_seed[i] = seeds[0]
            seeds[0] += 1
        envs[i].reset_state(seed=episode_seed[i])
        teachers[i].reset(env=envs[i], seed=None)
        if hidden is not None:
            hidden[:, i] = 0.0

    def store(i: int, crashed: bool = False) -> None:
        if segments[i]:
            weight = np.ones(len(segments[i]), dtype=np.float32)
            if crashed:
                weight[-crash_window:] = crash_weight
            columns = [np.stack(column) for column in zip(*segments[i], strict=True)]
            dataset.add_segment(*columns[:3], weight, *columns[3:])  # with aux_task: targets and their mask
            segments[i] = []

    for i in range(len(envs)):
        start(i)
    obs = observe(caster, envs, list(range(len(envs))))
    successes, lengths, taken = [], [], 0
    finished_by: list[int] = []  # the env that flew each finished episode
    lengths_now = np.zeros(len(envs), dtype=int)
    while taken < steps:
        teacher = np.array([t.act() for t in teachers], dtype=np.float32).clip(-1.0, 1.0)
        if commands:  # the label is what the teacher asked its last stage for, not what that stage sent
            labels = np.stack([acceleration_command(*t.command, env.drone.rotation)
                               for t, env in zip(teachers, envs, strict=True)])  # fmt: skip
        else:
            labels = teacher
        for i in range(len(envs)):
            step = (obs[i]["state"], obs[i]["depth"], labels[i])
            if aux_task is not None:
                target = aux_target(aux_task, teachers[i], envs[i])
                step += (no_line, np.float32(0.0)) if target is None else (target, np.float32(1.0))
            segments[i].append(step)
        student, hidden = student_step(policy, obs, hidden)
        use_teacher = rng.random(len(envs)) < beta
        actions = np.where(use_teacher[:, None], teacher, student)
        for i, env in enumerate(envs):
            _, terminated, truncated, info = env.advance(actions[i])
            lengths_now[i] += 1
            if terminated or truncated:
                successes.append(bool(info["is_success"]))
                finished_by.append(i)
                if replaying and not info["is_success"] and not is_replay[i]:
                    failed.append(episode_seed[i])
                lengths.append(int(lengths_now[i]))
                lengths_now[i] = 0
                store(i, crashed=info.get("crash_reason") is not None)
                start(i)
        obs = observe(caster, envs, list(range(len(envs))))
        taken += len(envs)
    for i in range(len(envs)):
        store(i)
    stats = {
        "steps": taken,
        "episodes": len(successes),
        "success_rate": float(np.mean(successes)) if successes else float("nan"),
        "mean_length": float(np.mean(lengths)) if lengths else float("nan"),
    }
    for label in dict.fromkeys(groups or []):
        mine = [ok for ok, i in zip(successes, finished_by, strict=True) if groups[i] == label]
        stats[f"success_rate_{label}"] = float(np.mean(mine)) if mine else float("nan")
    if replaying:
        stats["replayed"] = replayed  # episodes that re-flew a failed scene
    return stats


def fly_student(envs: list[Any], policy: Any, seeds: list[int]) -> list[dict[str, Any]]:
    """The student alone (deterministic actions, no teacher) flies one episode of each scene in ``seeds``,
    ``len(envs)`` side by side; returns per episode ``seed``, ``success``, ``steps`` and ``lap_time`` (NaN
    without a lap), in the order of ``seeds``."""
    caster = BatchDepthRenderer(envs[0].camera)
    recurrent = is_recurrent(policy)
    hidden = torch.zeros(1, len(envs), policy.lstm_actor.hidden_size) if recurrent else None
    queue, flying, steps = list(seeds), [None] * len(envs), [0] * len(envs)
    results: dict[int, dict[str, Any]] = {}

    def start(i: int) -> None:
        flying[i] = queue.pop(0) if queue else None
        if flying[i] is not None:
            envs[i].reset_state(seed=flying[i])
            steps[i] = 0
            if hidden is not None:
                hidden[:, i] = 0.0

    for i in range(len(envs)):
        start(i)
    while any(s is not None for s in flying):
        active = [i for i, s in enumerate(flying) if s is not None]
        held = None if hidden is None else hidden[:, active]
        actions, new = student_step(policy, observe(caster, envs, active), held)
        if new is not None:
            hidden[:, active] = new
        for j, i in enumerate(active):
            _, terminated, truncated, info = envs[i].advance(actions[j])
            steps[i] += 1
            if terminated or truncated:
                results[flying[i]] = {"seed": flying[i], "success": bool(info["is_success"]), "steps": steps[i],
                                      "lap_time": float(info.get("lap_time", float("nan")))}  # fmt: skip
                start(i)
    return [results[s] for s in seeds]


def average_weights(states: list[dict[str, torch.Tensor]]) -> dict[str, torch.Tensor]:
    """The element-wise mean of several students' ``state_dict``s (non-float entries from the last)."""
    return {
        key: torch.stack([s[key] for s in states]).mean(0) if value.is_floating_point() else value
        for key, value in states[-1].items()
    }


def choose_student(
    out: Path, config: DaggerConfig, student: Any, envs: list[Any], training_seeds: tuple[int, int]
) -> dict[str, Any]:  # fmt: skip
    """Load the run's final student into ``student``, as ``config.final_student`` says, from the kept students.

    The candidates are the kept students of the last ``keep_iterations`` iterations and, with two or more, their
    element-wise weight average (saved beside them). With ``select_episodes`` > 0 each is flown on that many
    validation scenes and ``selection.csv`` lists what each finished. ``final_student``: ``"average"`` takes the
    average, ``"best"`` the candidate that finished most (ties: the later iteration; the average counts as the
    latest), ``"last"`` the last iteration's student. ``training_seeds`` is the ``[first, end)`` range the run trained
    on: validation scenes must lie outside it. Returns the chosen candidate's row (its label alone without flights).
    """
    import pandas as pd

    from racebench.records import atomic_write

    seeds = [VALIDATION_SEED_BASE + i for i in range(config.select_episodes)]
    if seeds and max(training_seeds[0], seeds[0]) < min(training_seeds[1], seeds[-1] + 1):
        raise ValueError(f"dagger: validation seeds {seeds[0]}..{seeds[-1]} overlap the training seeds "
                         f"{training_seeds[0]}..{training_seeds[1] - 1}")  # fmt: skip
    kept = [out / KEPT_DIR / f"{config.name}-{config.track}-it{k:03d}.zip"
            for k in range(max(0, config.iterations - config.keep_iterations), config.iterations)]  # fmt: skip
    missing = [path for path in kept if not path.is_file()]
    if missing:
        raise ValueError(f"dagger: kept student {missing[0]} is missing: nothing to choose from")
    candidates = [(path.stem.rsplit("-", 1)[1], saved_policy_state(path)) for path in kept]
    if len(candidates) >= 2:
        candidates.append(("average", average_weights([state for _, state in candidates])))
        student.policy.load_state_dict(candidates[-1][1])
        student.save(out / KEPT_DIR / f"{config.name}-{config.track}-average.zip")  # evaluable like the others
    labels = [label for label, _ in candidates]
    rows = [{"candidate": label} for label in labels]
    if seeds:
        for row, (_, state) in zip(rows, candidates, strict=True):
            student.policy.load_state_dict(state)
            student.policy.set_training_mode(False)
            flown = pd.DataFrame(fly_student(envs, student.policy, seeds))
            laps = flown.loc[flown["success"], "lap_time"]
            row.update(episodes=len(flown), successes=int(flown["success"].sum()),
                       lap_time_mean=float(laps.mean()) if len(laps) else float("nan"))  # fmt: skip
    if config.final_student == "best":
        successes = [row["successes"] for row in rows]
        chosen = max(range(len(rows)), key=lambda i: (successes[i], i))
    else:
        # a run shorter than keep_iterations may have kept one student: its "average" is that student
        wanted = "average" if config.final_student == "average" and "average" in labels else labels[len(kept) - 1]
        chosen = labels.index(wanted)
    if seeds:
        table = pd.DataFrame(rows)
        table["chosen"] = table.index == chosen
        atomic_write(out / "selection.csv", table.to_csv(index=False))
    student.policy.load_state_dict(candidates[chosen][1])
    return {**rows[chosen], "chosen_by": config.final_student}


def training_env_ids(config: DaggerConfig) -> list[str]:
    """The id each of the ``n_envs`` training envs flies: the config's id (default ``RaceObs-<track>-v0``), or with
    ``train_tracks`` the main id of each listed track in turn."""
    if config.train_tracks:
        return [f"RaceObs-{config.train_tracks[i % len(config.train_tracks)]}-v0" for i in range(config.n_envs)]
    return [config.env_id or f"RaceObs-{config.track}-v0"] * config.n_envs


def make_training_envs(config: DaggerConfig) -> list[gym.Env]:
    """The ``n_envs`` training envs (:func:`training_env_ids`) with ray-cast depth and the config's gate shifts
    (scene seeds are set per episode by the collector)."""
    shifts = {"gate_shift": config.gate_shift, "gate_shift_z": config.gate_shift_z}
    return [gym.make(env_id, obs_mode="vision", renderer="raycast", **shifts) for env_id in training_env_ids(config)]


def make_teacher(config: DaggerConfig) -> PlannerAgent | FastPlannerAgent:
    """The config's teacher: the named privileged built-in; planner-fast with the config's ``teacher_*`` settings."""
    if config.teacher == "planner-fast":
        return FastPlannerAgent(
            gate_clearance=config.teacher_gate_clearance,
            wanted_clearance=config.teacher_wanted_clearance,
            integral_gain=config.teacher_integral_gain,
            replan_distance=config.teacher_replan_distance,
            obstacle_knowledge=config.teacher_obstacles,
        )
    return load_agent(config.teacher)


def dataset_features(policy: Any, dataset: Dataset, batch: int = 4096) -> torch.Tensor:
    """The student's features (:func:`student_features`) of every stored step, without gradient: ``(size, F)``."""
    with torch.no_grad():
        return torch.cat([
            student_features(policy, dataset.observations(np.arange(a, min(a + batch, dataset.size))))
            for a in range(0, dataset.size, batch)
        ])  # fmt: skip


def chunk_start_states(
    policy: Any, dataset: Dataset, chunks: tuple, batch: int = 4096, features: torch.Tensor | None = None
) -> torch.Tensor:  # fmt: skip
    """The GRU state each chunk starts from under the current student: ``(n_chunks, H)``.

    The student runs without gradient through every segment in order, chunk by chunk, all segments side by
    side (their ``position``-th chunks together); a chunk at position 0 starts from zero. ``features``: the
    stored steps' features if already computed (:func:`dataset_features`).
    """
    first, count, position = chunks
    length = int(count.max()) if len(count) else 1
    if features is None:
        features = dataset_features(policy, dataset, batch)
    with torch.no_grad():
        states = torch.zeros(len(first), policy.lstm_actor.hidden_size)
        segment = np.cumsum(position == 0) - 1  # each chunk's segment
        carried = torch.zeros(int(segment[-1]) + 1 if len(segment) else 0, policy.lstm_actor.hidden_size)
        for p in range(int(position.max()) + 1 if len(position) else 0):
            sel = np.flatnonzero(position == p)
            steps = np.minimum(first[sel, None] + np.arange(length), first[sel, None] + count[sel, None] - 1)
            start = carried[segment[sel]] if p > 0 else torch.zeros(len(sel), policy.lstm_actor.hidden_size)
            states[sel] = start
            output, _ = policy.lstm_actor(features[steps].transpose(0, 1), (start[None], torch.zeros_like(start[None])))
            carried[segment[sel]] = output[torch.from_numpy(count[sel] - 1), torch.arange(len(sel))]
    return states


def sequence_loss(
    policy: Any, dataset: Dataset, first: np.ndarray, count: np.ndarray, states: torch.Tensor, length: int,
    weighted: bool = False, shifts: np.ndarray | None = None,
) -> torch.Tensor:  # fmt: skip
    """Mean squared error over the real steps of the chunks ``(first, count)``, each unrolled from its start
    state in ``states`` ``(chunks, H)``; a chunk shorter than ``length`` is padded and its padding masked.
    With ``weighted``, each step's error counts by its stored loss weight (a weighted mean); ``shifts``
    ``(chunks, 2)``: each chunk's depth images shifted by that many pixels (:func:`shift_depth`)."""
    return sequence_terms(policy, dataset, first, count, states, length, weighted, shifts)[0]


def sequence_terms(
    policy: Any, dataset: Dataset, first: np.ndarray, count: np.ndarray, states: torch.Tensor, length: int,
    weighted: bool = False, shifts: np.ndarray | None = None, path_head: torch.nn.Module | None = None,
    mixture_sigma: float = 0.2, features: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor | None]:  # fmt: skip
    """:func:`sequence_loss` and, with ``path_head``, the auxiliary loss: the mean squared error of the head's
    prediction from each step's GRU output against the stored target, over the real steps that have one
    (``aux_mask``; unweighted). Without a head the second term is ``None``. A student with a mixture head
    (:class:`~racebench.training.policies.MixtureActionHead`) is fitted with its scaled mixture loss
    (:func:`~racebench.training.policies.mixture_action_loss`, standard deviation ``mixture_sigma``) in place of
    the squared error, averaged the same way. ``features``: every stored step's features, fixed
    (:func:`dataset_features`; the feature layers then get no gradient), in place of the depth CNN's pass."""
    offsets = np.arange(length)
    steps = np.minimum(first[:, None] + offsets, first[:, None] + count[:, None] - 1)
    index = steps.T.reshape(-1)  # time-major: (length * chunks)
    if features is None:
        batch = dataset.batch(index)
        if shifts is not None:
            batch["depth"] = shift_depth(batch["depth"], np.tile(shifts, (length, 1)))
        target, weight = batch.pop("action"), batch.pop("weight")
        inputs = student_features(policy, batch)
    else:
        if shifts is not None:
            raise ValueError("dagger: fixed features cannot be shifted (augment_shift needs the CNN's pass)")
        target, weight = torch.from_numpy(dataset.action[index]), torch.from_numpy(dataset.weight[index])
        inputs = features[torch.from_numpy(index)]
    target, weight = target.view(length, len(first), -1), weight.view(length, len(first), 1)
    actions, output = student_unroll(policy, inputs.view(length, len(first), -1), states[None])
    real = torch.from_numpy(offsets[:, None] < count[None, :]).unsqueeze(-1)
    mask = real * weight if weighted else real
    if isinstance(policy.action_net, MixtureActionHead):
        latent = policy.mlp_extractor.forward_actor(output)
        per_step = mixture_action_loss(policy.action_net, latent, target, mixture_sigma).unsqueeze(-1)
        loss = (per_step * mask).sum() / mask.sum()
    else:
        loss = ((actions - target) ** 2 * mask).sum() / (mask.sum() * target.shape[-1])
    if path_head is None:
        return loss, None
    aux_target = torch.from_numpy(dataset.aux[index]).view(length, len(first), -1)
    aux_mask = real * torch.from_numpy(dataset.aux_mask[index]).view(length, len(first), 1)
    aux_error = ((path_head(output) - aux_target) ** 2 * aux_mask).sum()
    return loss, aux_error / (aux_mask.sum().clamp(min=1.0) * aux_target.shape[-1])


def shift_depth(depth: torch.Tensor, shifts: np.ndarray) -> torch.Tensor:
    """Each image of ``depth`` ``(N, 1, H, W)`` moved by ``shifts[i] = (dx, dy)`` whole pixels (content moves right
    and down for positive values), the edge pixels replicated into the gap."""
    k = int(np.abs(shifts).max(initial=0))
    if k == 0:
        return depth
    height, width = depth.shape[-2:]
    padded = torch.nn.functional.pad(depth, (k, k, k, k), mode="replicate")
    out = torch.empty_like(depth)
    for dx, dy in np.unique(shifts, axis=0):
        rows = torch.from_numpy(np.flatnonzero((shifts[:, 0] == dx) & (shifts[:, 1] == dy)))
        out[rows] = padded[rows, :, k - dy : k - dy + height, k - dx : k - dx + width]
    return out


def pass_orders(items: int, epochs: int, cap: int | None, rng: np.random.Generator) -> Iterator[np.ndarray]:
    """Each pass's random order over ``items`` indices: ``epochs`` passes, cut once ``cap`` indices have been
    given in all (``None``: never), so a cut pass is a uniform random subset."""
    budget = items * epochs if cap is None else cap
    for epoch in range(epochs):
        order = rng.permutation(items)[: max(0, budget - epoch * items)]
        if not len(order):
            return
        yield order


def iteration_learning_rate(config: DaggerConfig, iteration: int) -> float:
    """The fit's learning rate at ``iteration``: ``learning_rate``, or with ``learning_rate_final`` set the linear
    ramp from ``learning_rate`` (iteration 0) to ``learning_rate_final`` (iteration ``iterations - 1``)."""
    if config.learning_rate_final is None or config.iterations == 1:
        return config.learning_rate
    fraction = min(iteration, config.iterations - 1) / (config.iterations - 1)
    return (1.0 - fraction) * config.learning_rate + fraction * config.learning_rate_final


def fit(
    policy: Any, dataset: Dataset, config: DaggerConfig, optimizer: Any, rng: np.random.Generator,
    path_head: torch.nn.Module | None = None, aux_losses: list[float] | None = None, frozen_features: bool = False,
) -> float:  # fmt: skip
    """``config.epochs`` passes of minibatch MSE regression over the dataset, cut at ``config.fit_samples``
    samples (a recurrent student's: ``fit_samples // sequence_length`` chunks); returns the last pass's loss.

    With ``path_head`` (a recurrent student, ``config.path_aux_weight`` > 0) each minibatch minimises the action loss
    plus ``path_aux_weight`` times the auxiliary loss (:func:`sequence_terms`; the optimizer holds the head's
    parameters too); the returned loss is the action part alone, and the last pass's auxiliary losses are appended
    to ``aux_losses``.

    A recurrent student trains on chunks of ``config.sequence_length`` steps (``batch_size // sequence_length``
    chunks a minibatch), each unrolled from the state :func:`chunk_start_states` gave it; the loss averages
    the chunks' real steps (a short chunk's padding is masked). With ``config.crash_weight`` other than 1 the
    loss is the mean weighted by each step's stored weight (:func:`collect`). With ``frozen_features`` (a recurrent
    student) the feature layers are not trained: their outputs for the whole aggregate are computed once, without
    gradient, and the GRU and heads are fitted on them (``freeze_features_after``).
    """
    if frozen_features and not is_recurrent(policy):
        raise ValueError("dagger: freeze_features_after fits a GRU on fixed features: it needs a recurrent student")
    if path_head is not None and not is_recurrent(policy):
        raise ValueError("dagger: the auxiliary path head reads a GRU's output: it needs a recurrent student")
    policy.set_training_mode(True)
    losses: list[float] = []
    aux: list[float] = []
    weighted = config.crash_weight != 1.0  # unweighted runs keep the plain mean (bit for bit as before)
    if is_recurrent(policy):
        length = config.sequence_length
        chunks = dataset.chunks(length)
        policy.set_training_mode(False)
        features = dataset_features(policy, dataset) if frozen_features else None
        states = chunk_start_states(policy, dataset, chunks, features=features)
        policy.set_training_mode(True)
        first, count, _ = chunks
        per_batch = max(1, config.batch_size // length)
        cap = None if config.fit_samples is None else config.fit_samples // length
        for order in pass_orders(len(first), config.epochs, cap, rng):
            losses, aux = [], []
            for a in range(0, len(order), per_batch):
                pick = order[a : a + per_batch]
                shifts = (  # drawn only when on, so runs without it keep their random stream
                    rng.integers(-config.augment_shift, config.augment_shift + 1, size=(len(pick), 2))
                    if config.augment_shift
                    else None
                )
                error, aux_error = sequence_terms(
                    policy, dataset, first[pick], count[pick], states[pick], length, weighted, shifts, path_head,
                    config.mixture_sigma, features,
                )  # fmt: skip
                total = error if aux_error is None else error + config.path_aux_weight * aux_error
                optimizer.zero_grad()
                total.backward()
                optimizer.step()
                losses.append(error.item())
                if aux_error is not None:
                    aux.append(aux_error.item())
        if aux_losses is not None:
            aux_losses.extend(aux)
    else:
        if isinstance(policy.action_net, MixtureActionHead):
            raise ValueError("dagger: a mixture action head is fitted on sequences: it needs a recurrent student")
        for order in pass_orders(dataset.size, config.epochs, config.fit_samples, rng):
            if len(order) < config.batch_size:
                break  # too few left for one minibatch
            losses = []
            for start in range(0, len(order) - config.batch_size + 1, config.batch_size):
                batch = dataset.batch(order[start : start + config.batch_size])
                if config.augment_shift:
                    shifts = rng.integers(-config.augment_shift, config.augment_shift + 1, size=(config.batch_size, 2))
                    batch["depth"] = shift_depth(batch["depth"], shifts)
                target, weight = batch.pop("action"), batch.pop("weight")
                if weighted:
                    error = (student_mean(policy, batch) - target) ** 2 * weight[:, None]
                    loss = error.sum() / (weight.sum() * target.shape[-1])
                else:
                    loss = torch.nn.functional.mse_loss(student_mean(policy, batch), target)
                optimizer.zero_grad()
                loss.backward()
                optimizer.step()
                losses.append(loss.item())
    policy.set_training_mode(False)
    return float(np.mean(losses)) if losses else float("nan")


RESUME_DIR = "resume"  # in a run folder: the state after the last finished iteration
# settings a resumption may change: they do not change the iterations already run
AFTER_TRAINING: tuple[str, ...] = ("iterations", "select_episodes", "final_student")
# Settings of the machine, not of the run: a run started beside another (one fit thread) may go on alone with two. The
# resumed part's fits then differ from an unstopped run's in their last bits (a sum's order follows the thread count).
RESOURCE_SETTINGS: tuple[str, ...] = ("update_threads",)
KEPT_DIR = "iterations"  # in a run folder: the students kept for selection (DaggerConfig.keep_iterations)


def saved_policy_state(path: Path) -> dict[str, torch.Tensor]:
    """The policy weights of an SB3 zip the run saved, read as tensors only (``torch.load(weights_only=True)``):
    the zip's pickled ``data`` is not read, so nothing in the file can run code."""
    from stable_baselines3.common.save_util import load_from_zip_file

    try:
        _, params, _ = load_from_zip_file(path, load_data=False, device="cpu")
    except (ValueError, pickle.UnpicklingError, RuntimeError) as exc:  # a bad zip, or a .pth with more than tensors
        why = " ".join(str(exc).split())[:200]  # torch's weights_only message spans many lines
        raise ValueError(f"dagger: {path} holds no readable policy weights ({why})") from None
    if not params or "policy" not in params:
        raise ValueError(f"dagger: {path} holds no policy weights")
    return params["policy"]


def load_optimizer_state(path: Path) -> dict[str, Any]:
    """The optimizer, random and auxiliary-head state :func:`save_resume_state` wrote, read with
    ``torch.load(weights_only=True)``: tensors, numbers and containers only; a file asking for more is refused."""
    try:
        return torch.load(path, weights_only=True)
    except pickle.UnpicklingError:
        raise ValueError(f"dagger: {path} holds more than tensors and numbers (weights_only refused it)") from None


def save_resume_state(
    out: Path, iteration: int, student: Any, optimizer: Any, dataset: Dataset, rng: np.random.Generator,
    seeds: list[int], rows: list[dict[str, Any]], config: DaggerConfig, failed: list[int] | None = None,
    path_head: torch.nn.Module | None = None,
) -> None:  # fmt: skip
    """Everything iteration ``iteration + 1`` needs, written beside the run and swapped in whole.

    The student (SB3 zip), the optimizer's state (and the auxiliary head's weights, ``path_head``), the aggregate
    dataset (with the auxiliary targets when there is a head), the numpy generator's state, the scene
    seed counter, the queue of failed scenes to replay (``failed``) and the progress rows. Episodes never span
    iterations (``collect`` starts every env afresh), so nothing of the envs needs saving. The folder is written
    under another name and renamed into place, so a kill leaves either the previous iteration's state or this one's.
    """

    partial, final, old = out / f"{RESUME_DIR}.partial", out / RESUME_DIR, out / f"{RESUME_DIR}.old"
    shutil.rmtree(partial, ignore_errors=True)
    partial.mkdir(parents=True)
    student.save(partial / "student.zip")
    extra = {"optimizer": optimizer.state_dict(), "torch_rng": torch.get_rng_state()}
    if path_head is not None:
        extra["path_head"] = path_head.state_dict()
    torch.save(extra, partial / "optimizer.pt")
    n = dataset.size
    aux = {"aux": dataset.aux[:n], "aux_mask": dataset.aux_mask[:n]} if path_head is not None else {}
    np.savez(partial / "dataset.npz", state=dataset.state[:n], depth=dataset.depth[:n], action=dataset.action[:n],
             weight=dataset.weight[:n], starts=dataset.starts[:n], next=np.array(dataset.next), **aux)  # fmt: skip
    state = {"iteration": iteration, "rng": rng.bit_generator.state, "seeds": seeds, "failed": failed or [],
             "rows": rows, "config": asdict(config)}  # fmt: skip
    (partial / "state.json").write_text(json.dumps(_json_safe(state), allow_nan=False))
    if final.exists():
        shutil.rmtree(old, ignore_errors=True)
        final.rename(old)
    partial.rename(final)
    shutil.rmtree(old, ignore_errors=True)


def resume_folder(out: Path) -> Path | None:
    """The folder holding the newest complete saved state of the run in ``out``, if any.

    Normally ``resume/``. A kill inside :func:`save_resume_state`'s swap can leave ``resume.partial/`` (complete
    once its ``state.json``, written last, exists) and ``resume.old/`` (the previous state) instead.
    """
    for name in (RESUME_DIR, f"{RESUME_DIR}.partial", f"{RESUME_DIR}.old"):
        if (out / name / "state.json").is_file():
            return out / name
    return None


def completed_iterations(out: Path) -> int:
    """How many iterations the saved state of the run in ``out`` has finished (0 without one)."""
    folder = resume_folder(out)
    return 0 if folder is None else int(json.loads((folder / "state.json").read_text())["iteration"]) + 1


def load_resume_state(out: Path, config: DaggerConfig) -> dict[str, Any] | None:
    """The state :func:`save_resume_state` left in ``out`` (``None`` if there is none), checked against ``config``.

    Every setting must match the saved run's except ``iterations``, which may grow (a finished run continues), those
    that only choose the final checkpoint (:data:`AFTER_TRAINING`) and ``update_threads`` (:data:`RESOURCE_SETTINGS`).
    The returned dict's ``folder`` is where the state was found (:func:`resume_folder`).
    """
    folder = resume_folder(out)
    if folder is None:
        return None
    try:
        state = json.loads((folder / "state.json").read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"dagger: {folder / 'state.json'} is not valid JSON ({exc})") from exc
    # A setting added after the state was saved: that run had the setting's default.
    saved, asked = {**asdict(DaggerConfig()), **state["config"]}, asdict(config)
    for key in asked:
        if key not in AFTER_TRAINING + RESOURCE_SETTINGS and saved[key] != asked[key]:
            raise ValueError(f"dagger: cannot resume {out}: it was run with {key}={saved[key]!r}, not {asked[key]!r}")
    if state["iteration"] + 1 > config.iterations:
        raise ValueError(
            f"dagger: {out} has finished {state['iteration'] + 1} iterations, more than the {config.iterations} asked"
        )
    return {**state, "folder": str(folder)}


def restore_state(
    saved: dict[str, Any], student: Any, optimizer: Any, dataset: Dataset, rng: np.random.Generator,
    path_head: torch.nn.Module | None = None,
) -> None:  # fmt: skip
    """Load a state :func:`load_resume_state` returned into the student (SB3 model), its optimizer, the auxiliary
    head, the aggregate, the numpy generator and torch's random state, as the run left them after its last finished
    iteration."""
    folder = Path(saved["folder"])
    student.policy.load_state_dict(saved_policy_state(folder / "student.zip"))
    extra = load_optimizer_state(folder / "optimizer.pt")
    optimizer.load_state_dict(extra["optimizer"])
    torch.set_rng_state(extra["torch_rng"])
    if path_head is not None:
        path_head.load_state_dict(extra["path_head"])  # the config matched (load_resume_state): it was saved
    with np.load(folder / "dataset.npz") as data:
        n = len(data["state"])
        dataset.state[:n], dataset.depth[:n], dataset.action[:n] = data["state"], data["depth"], data["action"]
        dataset.starts[:n] = data["starts"]
        if "weight" in data:  # a state saved before loss weights existed: all 1
            dataset.weight[:n] = data["weight"]
        if "aux" in data:
            dataset.aux[:n], dataset.aux_mask[:n] = data["aux"], data["aux_mask"]
        dataset.size, dataset.next = n, int(data["next"])
    rng.bit_generator.state = saved["rng"]


def distill(config: DaggerConfig, out: str | Path, eval_episodes: int = 10, resume: bool = False) -> dict[str, Any]:
    """Run DAgger (see the module docstring); write the student checkpoint, ``progress.csv`` and ``summary.json``.

    After every iteration the run's state is saved in ``out/resume/``; ``resume=True`` continues from it (the
    same student, optimizer, dataset and random streams: the same result as a run never interrupted, tested).
    """
    import pandas as pd

    from racebench.records import atomic_write

    config.validate()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    saved = load_resume_state(out, config) if resume else None
    if resume and saved is None:
        raise ValueError(f"dagger: nothing to resume in {out} (no {RESUME_DIR}/state.json): run it without resume")
    if config.train_tracks and config.track not in config.train_tracks:
        raise ValueError(f"dagger: the run's track {config.track!r} is not one of train_tracks {config.train_tracks}")
    env_id = config.env_id or f"RaceObs-{config.track}-v0"
    # the final evaluation: the run's id first, then the other training tracks' main ids
    eval_ids = list(dict.fromkeys([env_id, *training_env_ids(config)]))
    groups = [eid.split("-")[1] for eid in training_env_ids(config)] if config.train_tracks else None
    made = make_training_envs(config)
    envs = [m.unwrapped for m in made]
    teachers = [make_teacher(config) for _ in envs]
    # The student's initial weights come out of LAPACK (orthogonal init), whose last bits depend on the thread
    # count: fix it here, not wherever the caller left it, so a run and its resumption build the same student.
    torch.set_num_threads(config.update_threads)
    torch.manual_seed(config.seed)
    rng = np.random.default_rng(config.seed)
    policy_model = make_student(made[0], config.seed, config.student)
    policy = policy_model.policy
    path_head = None
    if config.path_aux_weight > 0:
        if not is_recurrent(policy):
            raise ValueError(f"dagger: path_aux_weight reads a GRU's output; student {config.student!r} has none")
        path_head = make_path_head(policy.lstm_actor.hidden_size)  # after the student: its weights are unchanged
    parameters = list(policy.parameters()) + ([] if path_head is None else list(path_head.parameters()))
    optimizer = (
        torch.optim.AdamW(parameters, lr=config.learning_rate, weight_decay=config.weight_decay)
        if config.weight_decay > 0
        else torch.optim.Adam(parameters, lr=config.learning_rate)
    )
    dataset = Dataset(config.max_samples, envs[0].camera.size)
    seeds = [config.seed * 1000]  # training seeds, far below the evaluation seeds
    failed: list[int] = []  # training scenes queued for replay (DaggerConfig.replay_failed)
    rows: list[dict[str, Any]] = []
    first, offset = 0, 0.0
    if saved is None:  # a fresh run: students another run kept in this folder must not become candidates
        shutil.rmtree(out / KEPT_DIR, ignore_errors=True)
    else:
        from racebench.training.train import archive_finished_part

        restore_state(saved, policy_model, optimizer, dataset, rng, path_head)
        seeds, rows = saved["seeds"], saved["rows"]
        failed = list(saved.get("failed", []))  # a state saved before replay existed queued none
        # A finished run extended to more iterations: its summary.json and eval/ are the old checkpoint's. Moved
        # aside (summary-<n>-steps.json, eval-<n>-steps/), they stay on record and the final evaluation can run.
        archive_finished_part(out, int(rows[-1]["env_steps"]) if rows else 0)
        first, offset = saved["iteration"] + 1, float(rows[-1]["wall_s"]) if rows else 0.0
    started = time.perf_counter() - offset  # wall clock over the resumed parts
    for k in tqdm(range(first, config.iterations), desc="dagger", unit="it", initial=first, total=config.iterations):
        beta = config.beta_decay**k
        torch.set_num_threads(1)
        tick = time.perf_counter()
        flown = collect(envs, teachers, policy, beta, config.steps_per_iteration, rng, seeds, dataset,
                        config.crash_weight, config.crash_window, config.replay_failed, failed,
                        config.aux_task if path_head is not None else None, groups)  # fmt: skip
        torch.set_num_threads(config.update_threads)
        collected = time.perf_counter()
        learning_rate = iteration_learning_rate(config, k)
        for group in optimizer.param_groups:
            group["lr"] = learning_rate
        aux_losses: list[float] = []
        frozen = config.freeze_features_after is not None and k >= config.freeze_features_after
        loss = fit(policy, dataset, config, optimizer, rng, path_head, aux_losses, frozen_features=frozen)
        if path_head is not None:  # the auxiliary task's loss over the last pass (m²)
            flown["aux_loss"] = float(np.mean(aux_losses)) if aux_losses else float("nan")
        # where an iteration's time goes: flying (teacher, student, envs) against fitting (grows with the aggregate)
        flown["collect_s"], flown["fit_s"] = round(collected - tick, 1), round(time.perf_counter() - collected, 1)
        # env_steps: every step flown so far (samples, the aggregate's size, stops growing at max_samples)
        flown["env_steps"] = flown.pop("steps") + (int(rows[-1].get("env_steps", rows[-1]["samples"])) if rows else 0)
        rows.append({"iteration": k, "beta": beta, **flown, "samples": dataset.size, "loss": loss,
                     "learning_rate": learning_rate, "wall_s": round(time.perf_counter() - started, 1)})  # fmt: skip
        atomic_write(out / "progress.csv", pd.DataFrame(rows).to_csv(index=False))
        # The student after every iteration, so a killed run leaves its latest policy behind.
        policy_model.save(out / f"{config.name}-{config.track}.zip")
        record_written(out, out / f"{config.name}-{config.track}.zip")  # so its evaluation (a sweep's) trusts it
        if k >= config.iterations - config.keep_iterations:
            (out / KEPT_DIR).mkdir(exist_ok=True)
            policy_model.save(out / KEPT_DIR / f"{config.name}-{config.track}-it{k:03d}.zip")
        save_resume_state(out, k, policy_model, optimizer, dataset, rng, seeds, rows, config, failed, path_head)
    checkpoint = out / f"{config.name}-{config.track}.zip"
    selection = None
    try:
        if config.keep_iterations > 0 and (config.select_episodes > 0 or config.final_student != "last"):
            selection = choose_student(out, config, policy_model, envs, (config.seed * 1000, seeds[0]))
            policy_model.save(checkpoint)  # the last iteration's student stays in iterations/
            record_written(out, checkpoint)
    finally:
        for m in made:
            m.close()
    summary: dict[str, Any] = {
        "method": "dagger",
        "teacher": config.teacher,
        "teacher_version": BUILTIN_VERSIONS[config.teacher],  # a bumped built-in plans and flies differently
        "student": config.student,
        "config": asdict(config),
        "checkpoint": str(checkpoint),
        "wall_s": round(time.perf_counter() - started, 1),
        "env_steps": int(rows[-1]["env_steps"]),
        "timesteps": int(rows[-1]["env_steps"]),  # as a PPO run's summary.json says it
        "last": rows[-1],
    }
    if selection is not None:
        summary["selection"] = selection
    if eval_episodes > 0:
        from racebench.evaluation import Evaluator
        from racebench.training.train import own_policy_trust

        result = Evaluator(  # this run's own checkpoint: trusted if what the evaluator loads is what the run wrote
            str(checkpoint), eval_ids, episodes=eval_episodes, out_dir=out / "eval",
            trust_code=own_policy_trust(out, checkpoint),
        ).run(progress=False)  # fmt: skip
        columns = ("n", "successes", "success_rate", "lap_time_mean")
        own = result[result["env_id"] == env_id].iloc[0]  # the summary's rows are sorted by id
        summary["eval"] = {k: float(own[k]) for k in columns}
        if len(eval_ids) > 1:  # a student of several tracks: each track's main id
            per_id = result.set_index("env_id")
            summary["eval_tracks"] = {eid: {k: float(per_id.loc[eid, k]) for k in columns} for eid in eval_ids}
    summary = _json_safe(summary)
    (out / "summary.json").write_text(json.dumps(summary, indent=2, allow_nan=False))
    return summary


def _json_safe(value: Any) -> Any:
    """NaN (an iteration without a finished episode, a lap time without a success) as JSON ``null``."""
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_json_safe(v) for v in value]
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value
