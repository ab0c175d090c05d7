"""A DAgger run's configuration (:class:`DaggerConfig`, a ``method: dagger`` YAML file) and its checks."""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np

from racebench.agents.planner import OBSTACLE_KNOWLEDGE
from racebench.envs.registration import TRACK_IDS
from racebench.evaluation.protocol import EVAL_SEED_BASE, VALIDATION_SEED_BASE
from racebench.training.config import TrainConfig, check_keys
from racebench.utils.yamlfile import read_yaml

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
# VALIDATION_SEED_BASE + i (racebench.evaluation.evaluator): above the training seeds (seed * 1000 + a counter;
# DaggerConfig.validate checks a bound on that counter) and below the evaluation seeds.
FINAL_STUDENTS: tuple[str, ...] = ("last", "average", "best")  # DaggerConfig.final_student: what the checkpoint is


@dataclass
class DaggerConfig:
    """Settings of one distillation run (all recorded in the run's ``summary.json``).

    Also a training config: a YAML file with ``method: dagger`` (``baselines/vision-distill.yaml``) is loaded
    by :func:`racebench.training.run.load_config`, so ``racebench train --config`` and ``racebench sweep``
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
    # fitted on better than new ones (baselines/experiments/heldout_gap.txt: loss 0.060 on its last fitted
    # iterations against 0.086 on the next ones), and the weight average of its last students (final_student) is
    # the one change that helped.
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
    # label a function of the current state (baselines/experiments/teacher_takeover.txt measured what each does)
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
        data = read_yaml(path)
        if not isinstance(data, dict) or data.pop("method", None) != "dagger":
            raise ValueError(f"{path}: not a DAgger config (expected a mapping with method: dagger)")
        per_run = sorted(set(data) & {"track", "seed", "iterations"})
        if per_run:
            raise ValueError(f"{path}: {per_run[0]!r} is set per run (racebench train --track/--seed/--steps)")
        check_keys(path, data, cls)
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
            (
                self.env_id != "RaceObs-Unseen-v0",  # docs/unseen-tracks.md: nothing trains on the held-out tracks
                "env_id RaceObs-Unseen-v0 is held out for evaluation: train on RaceObs-Random-v0",
            ),
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

        try:
            student = TrainConfig.from_yaml(self.student)
        except (OSError, ValueError) as exc:
            raise ValueError(f"{source}: student {self.student!r} is not a PPO baseline config ({exc})") from None
        if student.obs_mode != "vision":
            raise ValueError(f"{source}: student {self.student!r} must see depth (obs_mode vision)")
        if student.action_output == "acceleration" and self.teacher != "planner-fast":
            raise ValueError(f"{source}: an acceleration student ({self.student!r}) needs teacher planner-fast: its "
                             "commands are flown by planner-fast's last stage (control.command_to_ctbr)")  # fmt: skip
