"""DAgger: a depth student imitates a privileged planner (``method: dagger`` configs; see :mod:`.loop`).

* :mod:`~racebench.training.dagger.config`: :class:`DaggerConfig`; :mod:`~racebench.training.dagger.dataset`: the
  aggregate;
* :mod:`~racebench.training.dagger.collection`: rollouts and labels; :mod:`~racebench.training.dagger.fitting`:
  fitting the student; :mod:`~racebench.training.dagger.selection`: choosing the final student;
* :mod:`~racebench.training.dagger.resume`: a run's resumable state; :mod:`~racebench.training.dagger.loop`: the
  main loop (:func:`distill`).

The names of the former module ``racebench.training.dagger`` are re-exported here (the student's network
helpers from :mod:`racebench.training.student`). No submodule is named like a function it holds, so that
``from racebench.training.dagger import fit`` is always the function.
"""

from __future__ import annotations

from racebench.utils.lazy import lazy_exports

#: Submodule -> the names this package re-exports from it, imported on first use (PEP 562) so that importing one
#: submodule does not load its siblings.
_EXPORTS: dict[str, tuple[str, ...]] = {
    "config": (
        "TEACHERS",
        "LINE_AHEAD_M",
        "PATH_AUX_SIZE",
        "CLEARANCE_PROBES",
        "CLEARANCE_CAP_M",
        "AUX_TASKS",
        "FINAL_STUDENTS",
        "DaggerConfig",
    ),
    "dataset": ("Dataset",),
    "collection": (
        "line_ahead",
        "clearance_ahead",
        "aux_target",
        "make_path_head",
        "collect",
    ),
    "selection": (
        "fly_student",
        "average_weights",
        "choose_student",
    ),
    "fitting": (
        "dataset_features",
        "chunk_start_states",
        "sequence_loss",
        "sequence_terms",
        "shift_depth",
        "pass_orders",
        "iteration_learning_rate",
        "fit",
    ),
    "resume": (
        "RESUME_DIR",
        "AFTER_TRAINING",
        "RESOURCE_SETTINGS",
        "KEPT_DIR",
        "saved_policy_state",
        "load_optimizer_state",
        "save_resume_state",
        "resume_folder",
        "completed_iterations",
        "load_resume_state",
        "restore_state",
    ),
    "loop": (
        "training_env_ids",
        "make_training_envs",
        "make_teacher",
        "distill",
    ),
    "...evaluation.protocol": ("EVAL_SEED_BASE", "VALIDATION_SEED_BASE"),
    "..student": (
        "make_student",
        "is_recurrent",
        "student_features",
        "student_head",
        "student_mean",
        "student_unroll",
        "observe",
        "student_step",
        "student_output",
    ),
}
__all__, __getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
