"""The Ray backend: evaluation episodes (and sweep runs, :mod:`racebench.training.sweep`) as Ray tasks.

Ray is an optional extra (``pip install -e '.[ray]'``); nothing here imports it before it is asked for, so
the local multiprocessing backend never pays for it.

An evaluation on Ray is the local evaluation cut into tasks of a few episodes. Each task runs
:func:`racebench.evaluation.worker.fly` in a Ray worker process with the same
:class:`~racebench.evaluation.writer.RecordWriter`
the local workers use, so every record has the same name and contents as a local run's, and resume,
summaries and tables do not know which backend wrote them. Each Ray worker process appends to a shard of its
own (``records-<pid>-<token>.jsonl``), never to a file another process writes. A task skips the episodes whose
valid record is already on disk, so a task retried after its worker or node died (Ray's ``max_retries``)
re-flies only the episodes that had not finished. A task also returns the records it wrote, and the driver
appends them to its own shard: where a worker's node does not share the output folder with the driver, that is
the driver's copy (records only; trajectories need a shared folder); where it does, the copy is the same line,
skipped on read and dropped when the evaluator merges the shards into ``records.jsonl``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from racebench.evaluation.records import append_line, read_folder, record_line, shard_path, validate_record
from racebench.evaluation.rollout import BatchAgent
from racebench.evaluation.worker import WORKER, fly, torch_threads, worker_init

INSTALL_HINT = "pip install -e '.[ray]'"
BACKENDS: tuple[str, ...] = ("local", "ray")


class RayNotInstalledError(ValueError):
    """``--backend ray`` without Ray installed (a setup error, like a bad option); the message says how to
    install it."""


def require_ray() -> Any:
    """Import and return the ``ray`` module, or raise :class:`RayNotInstalledError` saying how to install it."""
    try:
        import ray
    except ImportError as exc:
        raise RayNotInstalledError(f"the Ray backend needs Ray, which is not installed: {INSTALL_HINT}") from exc
    return ray


@dataclass(frozen=True)
class RayOptions:
    """How racebench uses Ray.

    Args:
        address: cluster to join (``"auto"``: the one ``ray start`` began on this machine; ``"HOST:PORT"``:
            a head node). ``None`` starts a private local instance of ``local_cpus`` CPUs, shut down afterwards.
            Ignored when this process has already called ``ray.init``.
        task_cpus: CPUs each evaluation task reserves (1: one episode stream per core).
        task_episodes: episodes per evaluation task; ``None``: the lockstep width, at most 16, for agents
            that batch (SB3, ONNX), else 1 (a lost worker then costs at most one episode).
        max_retries: times Ray re-runs a task whose worker process or node died.
        local_cpus: CPUs of the private local instance started when ``address`` is ``None``.
    """

    address: str | None = None
    task_cpus: float = 1.0
    task_episodes: int | None = None
    max_retries: int = 3
    local_cpus: int | None = None

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first bad option."""
        if self.task_cpus <= 0:
            raise ValueError(f"Ray task CPUs must be > 0, got {self.task_cpus}")
        if self.task_episodes is not None and self.task_episodes < 1:
            raise ValueError(f"episodes per Ray task must be >= 1, got {self.task_episodes}")
        if self.max_retries < 0:
            raise ValueError(f"Ray max_retries must be >= 0, got {self.max_retries}")
        if self.local_cpus is not None and self.local_cpus < 1:
            raise ValueError(f"CPUs of the local Ray instance must be >= 1, got {self.local_cpus}")


@contextmanager
def connected(options: RayOptions) -> Iterator[Any]:
    """Context: a connected ``ray`` module; disconnects (and stops a private local instance) on exit only if
    it connected itself, so a caller's own ``ray.init`` (a test's, a notebook's) is left as it was."""
    ray = require_ray()
    if ray.is_initialized():
        yield ray
        return
    if options.address is None:
        ray.init(num_cpus=options.local_cpus or 1, include_dashboard=False, log_to_driver=False)
    else:
        ray.init(address=options.address, log_to_driver=False)
    try:
        yield ray
    finally:
        ray.shutdown()


def wait_all(ray: Any, refs: Sequence[Any], on_done: Callable[[Any, Any], None]) -> None:
    """Call ``on_done(ref, value)`` for every task as it finishes (in completion order); a task's error is raised."""
    pending = list(refs)
    while pending:
        ready, pending = ray.wait(pending, num_returns=1)
        for ref in ready:
            on_done(ref, ray.get(ref))


# ------------------------------------------------------------------ evaluation


def worker_spec(spec: str) -> str:
    """``spec`` with a relative policy file made absolute: Ray workers do not share the driver's directory."""
    target, sep, cls = spec.rpartition(":")
    if sep and target.endswith(".py") and Path(target).is_file():
        return f"{Path(target).resolve()}:{cls}"
    if (spec.endswith(".zip") or spec.endswith(".onnx")) and Path(spec).is_file():
        return str(Path(spec).resolve())
    return spec


def _fly_task(
    agent_spec: str,
    sha256: str,
    renderer: str,
    trust_code: bool,
    jobs: list[tuple[str, int]],
    writer: Any,
    width: int,
    save_trajectories: bool,
    agent_kwargs: dict[str, Any] | None = None,
    vecnormalize: str | bool | None = None,
) -> list[dict[str, Any]]:
    """Body of one Ray evaluation task: fly the jobs without a valid record; return the records of all."""
    # Finished before this task's worker died: a retry keeps it (read only if any record is on disk).
    on_disk = read_folder(writer.out_dir).records
    held = {writer.name(e, s): on_disk[writer.name(e, s)] for e, s in jobs if writer.name(e, s) in on_disk}
    todo = [(e, s) for e, s in jobs if writer.name(e, s) not in held]
    key = (agent_spec, sha256, renderer, trust_code)  # sha256 covers the constructor arguments
    if todo and WORKER.get("key") != key:  # a Ray worker process runs many tasks: build the agent once
        worker_init(agent_spec, renderer, trust_code, torch_threads(), agent_kwargs, vecnormalize)
        if getattr(WORKER["agent"], "sha256", sha256) != sha256:
            raise ValueError(f"{agent_spec!r} on this node is not the policy the driver evaluates (sha256 differs)")
        WORKER["key"] = key
    if todo:
        held.update((writer.name(r["env_id"], r["seed"]), r) for r in fly(todo, writer, width, save_trajectories))
    return [held[writer.name(e, s)] for e, s in jobs]


RAY_TASK_EPISODES = 16  # default episodes per Ray task of a lockstep agent


def run_evaluation(
    evaluator: Any, todo: list[tuple[str, int]], on_episodes: Callable[[int], None]
) -> list[dict[str, Any]]:
    """Fly ``todo`` of a :class:`~racebench.evaluation.evaluator.Evaluator` as Ray tasks; return the records written.

    ``on_episodes(n)`` is called as each task's ``n`` episodes finish (the progress bar).
    """
    options: RayOptions = evaluator.ray_options
    if not todo:
        return []
    size = options.task_episodes
    if size is None:  # lockstep agents: tasks of the lockstep width, at most RAY_TASK_EPISODES (spread the work)
        batching = evaluator.width > 1 and isinstance(evaluator.probe, BatchAgent)
        size = min(evaluator.width, RAY_TASK_EPISODES) if batching else 1
    width = min(evaluator.width, size)  # a task never computes rows for episodes it does not have
    tasks = [todo[i : i + size] for i in range(0, len(todo), size)]
    # Absolute paths: a Ray worker's working directory is not the driver's.
    writer = dataclasses.replace(evaluator.writer, out_dir=Path(evaluator.out_dir).resolve())
    spec = worker_spec(evaluator.agent_spec)
    written: list[dict[str, Any]] = []
    with connected(options) as ray:
        remote = ray.remote(_fly_task).options(num_cpus=options.task_cpus, max_retries=options.max_retries)
        refs = {
            remote.remote(
                spec, evaluator.identity.sha256, evaluator.renderer, evaluator.trust_code, task, writer,
                width, evaluator.save_trajectories, evaluator.agent_kwargs, evaluator.vecnormalize,
            ): len(task)
            for task in tasks
        }  # fmt: skip

        def done(ref: Any, records: list[dict[str, Any]]) -> None:
            for record in records:
                validate_record(record)  # a worker's record is checked before the driver keeps a copy
            # The driver's copy in its own shard: all of a task's records in one append.
            append_line(shard_path(writer.out_dir), b"".join(record_line(r) for r in records))
            written.extend(records)
            on_episodes(refs[ref])

        wait_all(ray, list(refs), done)
    return written
