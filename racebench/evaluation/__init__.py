"""Evaluation: the seed protocol and seed sets, the evaluator and its workers, rollouts, records, statistics.

* :mod:`~racebench.evaluation.protocol`: seed bases, suites, env-id parsing; :mod:`~racebench.evaluation.seeds`: the
  public and private seed sets;
* :mod:`~racebench.evaluation.evaluator`: :class:`Evaluator`; :mod:`~racebench.evaluation.worker`: what a worker
  process (local or Ray, :mod:`~racebench.evaluation.ray_backend`) runs; :mod:`~racebench.evaluation.rollout`:
  flying episodes;
* :mod:`~racebench.evaluation.records`: the record format and folders; :mod:`~racebench.evaluation.writer`: writing
  them; :mod:`~racebench.evaluation.results`: reading a result folder back, comparing two;
* :mod:`~racebench.evaluation.statistics`: Wilson intervals, paired tests, the bootstrap.

The names of the former module ``racebench.evaluation`` are re-exported here.
"""

from __future__ import annotations

from racebench.utils.lazy import lazy_exports

#: Submodule -> the names this package re-exports from it, imported on first use (PEP 562) so that importing one
#: submodule does not load its siblings.
_EXPORTS: dict[str, tuple[str, ...]] = {
    "protocol": (
        "SEED_PROTOCOL",
        "EVAL_SEED_BASE",
        "VALIDATION_SEED_BASE",
        "TRACK_ORDER",
        "SUITES",
        "SEED_SET",
        "eval_seeds",
        "resolve_envs",
        "split_env_id",
    ),
    "writer": ("RecordWriter",),
    "worker": (
        "WORKER",
        "worker_init",
        "close_pool",
        "fly",
        "torch_threads",
        "SingleTorchThread",
    ),
    "results": (
        "logger",
        "MixedResultsError",
        "EPISODE_COLUMNS",
        "load_records",
        "summarize",
        "write_tables",
        "load_result_dir",
        "read_summaries",
        "paired_comparison",
    ),
    "evaluator": (
        "logger",
        "DEFAULT_BATCH",
        "default_out_dir",
        "Evaluator",
    ),
    "rollout": ("BatchAgent", "env_error_result", "run_episode", "run_lockstep"),
    "statistics": ("paired_outcomes", "wilson_interval"),
}
__all__, __getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
