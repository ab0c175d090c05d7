"""The names of the former module ``racebench.training.train``, which was split by job (docs/layout.md):

* :mod:`~racebench.training.config`: :class:`TrainConfig`; :mod:`~racebench.training.run`: the run dispatcher
  (:func:`load_config`, :func:`run_training`);
* :mod:`~racebench.training.callbacks`: the callbacks; :mod:`~racebench.training.models`: envs and model;
* :mod:`~racebench.training.ppo`: the PPO loop (:func:`train`).

Checkpoints saved before the split name this module in their pickled learning-rate schedule, and user code imports
from it: it stays importable.
"""

from racebench.agents.export import CRITIC_PREFIXES, critic_parameter
from racebench.agents.trust import own_policy_trust
from racebench.training.callbacks import (
    AtomicCheckpointCallback,
    CriticWarmupCallback,
    CurriculumCallback,
    MultiSceneCallback,
    ProgressCSVCallback,
    StudentBCCallback,
    TeacherBCCallback,
    ThreadsCallback,
    is_lap,
    mean_actions_along,
)
from racebench.training.config import (
    BASELINES,
    BC_TARGETS,
    TrainConfig,
    baseline_path,
)
from racebench.training.models import (
    DEVICES,
    frozen_initial_policy,
    linear_schedule,
    load_policy_weights,
    make_envs,
    make_model,
    policy_weights,
    resolve_device,
)
from racebench.training.ppo import (
    archive_finished_part,
    machine_description,
    restore_schedules,
    resume_curriculum,
    resume_seed,
    train,
)
from racebench.training.run import (
    load_config,
    run_training,
)

__all__ = [
    "AtomicCheckpointCallback",
    "BASELINES",
    "BC_TARGETS",
    "CRITIC_PREFIXES",
    "CriticWarmupCallback",
    "CurriculumCallback",
    "DEVICES",
    "MultiSceneCallback",
    "ProgressCSVCallback",
    "StudentBCCallback",
    "TeacherBCCallback",
    "ThreadsCallback",
    "TrainConfig",
    "archive_finished_part",
    "baseline_path",
    "critic_parameter",
    "frozen_initial_policy",
    "is_lap",
    "linear_schedule",
    "load_config",
    "load_policy_weights",
    "machine_description",
    "make_envs",
    "make_model",
    "mean_actions_along",
    "own_policy_trust",
    "policy_weights",
    "resolve_device",
    "restore_schedules",
    "resume_curriculum",
    "resume_seed",
    "run_training",
    "train",
]
