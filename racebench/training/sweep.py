"""``racebench sweep``: a grid of training runs (config × track × training seed) plus their final evaluations.

A sweep file (YAML, loaded with ``yaml.safe_load``; ``baselines/sweeps/paper-tables.yaml`` is annotated)::

    name: tiny                      # default: the file's stem
    out: runs/sweeps/tiny           # default: runs/sweeps/<name>
    configs:                        # built-in names or YAML files (relative to the sweep file), PPO or DAgger
      - state-ppo
      - {config: vision-ppo, overrides: {n_envs: 32}}   # overrides of this config only
      - {config: vision-distill, steps: 500000}         # this config's own step budget
      - {config: vision-distill-ppo, after: vision-distill}   # starts from that config's final policy
      - {config: vision-ppo, tracks: [J], seeds: [1, 2]}     # this entry's own tracks and seeds
    tracks: [S, J]
    seeds: [0, 1]                   # training seeds (below the evaluation seeds)
    steps: 200000                   # environment steps per run
    overrides: {num_processes: 1}   # applied to every config (before a config's own)
    eval_episodes: 10               # final evaluation of each run on RaceObs-<track>-v0 (0: none)
    eval_episodes_other: 5          # ... and on each of its track's other ids of eval_suite (default: eval_episodes)
    eval_suite: main                # ... on which ids of its track: main, density, gates or paper (all 9 of them)
    evaluate_policy_only: false     # evaluate the policy-only export policy/<name>-<track>.zip (the file to commit)
    validation_every: 0             # fly the checkpoints at each multiple of this many steps (0: none) ...
    validation_episodes: 100        # ... on this many validation scenes: validation_curve.csv
    (racebench.reporting.paper)
    checkpoint_every: 50000         # steps between checkpoints, the points a killed run resumes from
    device: auto                    # where the networks train (racebench train --device)
    cpus_per_run: null              # Ray: CPUs a run reserves (default: its config's num_processes)
    gpus_per_run: 0                 # Ray: GPUs a run reserves

Each run is :func:`racebench.training.ppo.train` in its own folder ``<out>/<config name>-<track>-seed<seed>``,
resumable through that folder alone: ``summary.json`` with its ``eval`` (or ``eval_episodes: 0``) means
finished, and the run is skipped; otherwise training continues from the newest checkpoint under
``checkpoints/`` (or starts afresh), then the final checkpoint is evaluated into ``eval/`` with the
resumable :class:`~racebench.evaluation.evaluator.Evaluator` (labelled ``<config name>-seed<seed>``, so
``racebench table <out>/*/eval`` puts one row per config and seed, each track's cells from that track's run), on the
ids of ``eval_suite`` (an evaluation suite of ``racebench evaluate``) that belong to the run's track: ``paper`` gives
Tables II–IV from the runs alone. There is no second checkpoint mechanism:
a run killed anywhere, or retried by Ray after its worker or node died, picks up from these files.

``after: NAME`` chains two configs (a teacher–student campaign: the DAgger student, then its PPO fine-tuning):
each run of this config initialises from the final policy of NAME's run on the same track and seed in this
sweep (its ``init_from`` becomes ``<out>/NAME-<track>-seed<seed>/NAME-<track>.zip``) and starts only after that
run has finished; if that run failed, this one is reported failed without starting (unless it is finished or
has checkpoints of its own, which need nothing from it). NAME is the ``name`` of a config listed earlier (after
its overrides: the name in its run folders), so the local order already respects it.

Runs are listed (and the local backend runs them) in the file's order: entry by entry, each entry's tracks, then
its seeds. An entry may name the same config as another with other tracks or seeds (a campaign's extra seeds);
``max_runs`` of :func:`run_sweep` (``racebench sweep --max-runs N``) trains only the next N unfinished runs.

The local backend runs the runs one after another in this process; the Ray backend makes each run a Ray
task reserving the CPUs (and GPUs) its config needs, so a cluster runs as many side by side as fit, each
chained run submitted once the run it starts from has finished.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import re
import shutil
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pandas as pd

from racebench.agents.export import export_policy
from racebench.agents.loading import SB3Agent
from racebench.agents.trust import own_policy_trust, record_written, vecnormalize_path
from racebench.evaluation.evaluator import Evaluator
from racebench.evaluation.protocol import EVAL_SEED_BASE, SUITES, split_env_id
from racebench.evaluation.ray_backend import RayOptions, connected
from racebench.reporting.validation import validation_curve
from racebench.training.callbacks import TrainingInterrupted
from racebench.training.config import BASELINES, TRAIN_TRACKS, TrainConfig
from racebench.training.dagger.resume import completed_iterations, resume_folder
from racebench.training.models import DEVICES
from racebench.training.ppo import _plain
from racebench.training.run import load_config, run_training
from racebench.utils.files import atomic_write
from racebench.utils.yamlfile import read_yaml

SWEEP_KEYS: tuple[str, ...] = (
    "name", "out", "configs", "tracks", "seeds", "steps", "overrides", "eval_episodes", "eval_episodes_other",
    "eval_suite", "validation_every", "validation_episodes", "evaluate_policy_only",
    "checkpoint_every", "device", "cpus_per_run", "gpus_per_run",
)  # fmt: skip
logger = logging.getLogger("racebench")
_CHECKPOINT = re.compile(r"^(?P<prefix>.+)_(?P<steps>\d+)_steps\.zip$")


@dataclass(frozen=True)
class SweepRun:
    """One run of a sweep: everything its job needs, picklable (it travels to a Ray worker)."""

    config: Any  # TrainConfig or DaggerConfig (racebench.training.run.load_config)
    track: str
    seed: int
    steps: int
    out: Path
    eval_episodes: int
    eval_envs: tuple[str, ...]  # the ids its final policy is evaluated on (the main id first)
    checkpoint_every: int
    device: str
    cpus: float
    gpus: float
    after: str | None = None  # the label of the run whose final policy this one starts from (``after:``)
    eval_episodes_other: int | None = None  # episodes on each id after the main one (None: eval_episodes)
    evaluate_policy_only: bool = False  # evaluate policy/<name>-<track>.zip (racebench export-policy) instead
    validation_every: int = 0  # validation curve: checkpoints every this many steps (0: none) ...
    validation_episodes: int = 100  # ... each flown on this many validation scenes
    # Resume from (and evaluate) checkpoints the run folder did not write itself (racebench sweep --trust-code);
    # without it only the files listed in the folder's written.json are unpickled
    # (racebench.agents.trust.require_trusted).
    trust_code: bool = False

    @property
    def label(self) -> str:
        """The run's folder name and its agent label's stem: ``<config name>-<track>-seed<seed>``."""
        return self.out.name


@dataclass(frozen=True)
class Sweep:
    """A loaded, validated sweep file: its output folder and its runs."""

    name: str
    out: Path
    runs: list[SweepRun]


CONFIG_ENTRY_KEYS: tuple[str, ...] = ("config", "overrides", "steps", "after", "tracks", "seeds")


def _config_entry(entry: Any, source: str) -> dict[str, Any]:
    """A ``configs`` entry as a mapping with at least ``config`` (a bare name/file is ``{config: name}``)."""
    if isinstance(entry, str):
        entry = {"config": entry}
    if not isinstance(entry, dict) or set(entry) - set(CONFIG_ENTRY_KEYS) or "config" not in entry:
        raise ValueError(
            f"{source}: each configs entry is a name/file or a mapping with keys among {list(CONFIG_ENTRY_KEYS)}"
            " and config"
        )
    if "steps" in entry and not (type(entry["steps"]) is int and entry["steps"] >= 1):  # not a bool
        raise ValueError(f"{source}: steps of {entry['config']!r} must be an integer >= 1")
    for key in ("tracks", "seeds"):
        if key in entry and (not isinstance(entry[key], list) or not entry[key]):
            raise ValueError(f"{source}: {key} of {entry['config']!r} must be a non-empty list")
    return entry


def _check_tracks_and_seeds(tracks: list[Any], seeds: list[Any], source: str) -> None:
    bad_tracks = [t for t in tracks if t not in TRAIN_TRACKS]
    if bad_tracks:
        raise ValueError(f"{source}: track {bad_tracks[0]!r} is not one of {TRAIN_TRACKS}")
    if not all(type(s) is int and 0 <= s < EVAL_SEED_BASE for s in seeds):
        raise ValueError(f"{source}: seeds must be integers in [0, {EVAL_SEED_BASE}) (evaluation uses the rest)")


def _load_config(entry: dict[str, Any], base: Path, overrides: dict[str, Any], source: str) -> Any:
    name = str(entry["config"])
    path = name if name in BASELINES or Path(name).is_absolute() else str(base / name)
    config = load_config(path)
    own = entry.get("overrides") or {}
    if not isinstance(own, dict):
        raise ValueError(f"{source}: overrides of {name!r} must be a mapping")
    changes = {**overrides, **own}
    known = {f.name for f in dataclasses.fields(config)}
    unknown = sorted(set(changes) - known)
    if unknown:
        raise ValueError(f"{source}: override {unknown[0]!r} of {name!r} is not a config key")
    tuples = {f.name for f in dataclasses.fields(config) if str(f.type).startswith("tuple")}
    for key in tuples & set(changes):  # YAML lists → the config's tuples (TrainConfig's; DaggerConfig has none)
        changes[key] = tuple(changes[key])
    config = dataclasses.replace(config, **changes)
    if "num_processes" in changes and "update_threads" not in changes and hasattr(config, "n_steps"):
        config.update_threads = config.num_processes  # as `racebench train --num-processes` does
    config.validate(f"{source}: {name} with its overrides")
    return config


def load_sweep(path: str | Path, out: str | Path | None = None, trust_code: bool = False) -> Sweep:
    """Load and validate a sweep file (see the module docstring); ``out`` replaces its output folder.

    ``trust_code``: every run may resume from a checkpoint its folder did not write (see :class:`SweepRun`).

    Raises ``ValueError`` (or ``OSError``) naming the first problem, before any run starts.
    """
    path = Path(path)
    data = read_yaml(path)
    source = str(path)
    if not isinstance(data, dict):
        raise ValueError(f"{source}: expected a mapping at the top level")
    unknown = sorted(set(data) - set(SWEEP_KEYS))
    if unknown:
        raise ValueError(f"{source}: unknown key {unknown[0]!r} (known: {sorted(SWEEP_KEYS)})")
    for key in ("configs", "tracks", "seeds", "steps"):
        if key not in data:
            raise ValueError(f"{source}: missing key {key!r}")
    for key in ("configs", "tracks", "seeds"):
        if not isinstance(data[key], list) or not data[key]:
            raise ValueError(f"{source}: {key} must be a non-empty list")
    _check_tracks_and_seeds(data["tracks"], data["seeds"], source)
    numbers = {"steps": 1, "eval_episodes": 0, "eval_episodes_other": 1, "checkpoint_every": 1,
               "validation_every": 0, "validation_episodes": 1}  # fmt: skip
    for key, low in numbers.items():
        if key in data and not (type(data[key]) is int and data[key] >= low):  # a YAML true is no number
            raise ValueError(f"{source}: {key} must be an integer >= {low}")
    suite = data.get("eval_suite", "main")
    if suite not in SUITES:
        raise ValueError(f"{source}: eval_suite must be one of {sorted(SUITES)}, not {suite!r}")
    device = data.get("device", "auto")
    if device not in DEVICES:
        raise ValueError(f"{source}: device must be one of {DEVICES}")
    for key in ("cpus_per_run", "gpus_per_run"):
        value = data.get(key)
        if value is not None and not (isinstance(value, int | float) and value >= 0):
            raise ValueError(f"{source}: {key} must be a number >= 0")
    if not isinstance(data.get("evaluate_policy_only", False), bool):
        raise ValueError(f"{source}: evaluate_policy_only must be true or false")
    every = data.get("validation_every", 0)
    if every and every % data.get("checkpoint_every", 50_000):
        raise ValueError(f"{source}: validation_every must be a multiple of checkpoint_every")
    overrides = data.get("overrides") or {}
    if not isinstance(overrides, dict):
        raise ValueError(f"{source}: overrides must be a mapping")
    name = str(data.get("name", path.stem))
    root = Path(out or data.get("out") or Path("runs") / "sweeps" / name).resolve()  # Ray workers: absolute
    entries = [_config_entry(entry, source) for entry in data["configs"]]
    for entry in entries:
        _check_tracks_and_seeds(entry.get("tracks", data["tracks"]), entry.get("seeds", data["seeds"]), source)
    configs = [_load_config(entry, path.parent, overrides, source) for entry in entries]
    runs = []
    for index, (entry, config) in enumerate(zip(entries, configs, strict=True)):
        after = entry.get("after")
        if after is not None:
            earlier = [c.name for c in configs[:index]]
            if after not in earlier:
                raise ValueError(f"{source}: {config.name!r} is after {after!r}, not a config listed before it")
            if not hasattr(config, "init_from"):
                raise ValueError(f"{source}: {config.name!r} cannot start from another run's policy (no init_from)")
            if "init_from" in (entry.get("overrides") or {}) or "init_from" in overrides:
                raise ValueError(f"{source}: {config.name!r} has both after and an init_from override: keep one")
            folder = str(root).replace("{", "{{").replace("}", "}}")  # a template: train() fills {track}, {seed}
            config = dataclasses.replace(
                config, init_from=f"{folder}/{after}-{{track}}-seed{{seed}}/{after}-{{track}}.zip"
            )
        tracks, seeds = entry.get("tracks", data["tracks"]), entry.get("seeds", data["seeds"])
        if isinstance(config, TrainConfig) and config.track is not None and set(tracks) != {config.track}:
            raise ValueError(f"{source}: {config.name!r} trains on track {config.track!r} (its config's track): sweep "
                             f"it over tracks: [{config.track}], not {tracks}")  # fmt: skip
        several = getattr(config, "train_tracks", None)  # a DAgger student of several tracks: one run per seed
        if several and (len(tracks) != 1 or tracks[0] not in several):
            raise ValueError(
                f"{source}: {config.name!r} trains one student for the tracks {several} (train_tracks): sweep it "
                f"over one of them (tracks: [{several[0]}]), not {tracks}"
            )
        for track in tracks:
            for seed in seeds:
                cpus = data.get("cpus_per_run")
                runs.append(
                    SweepRun(
                        config=config,
                        track=track,
                        seed=seed,
                        steps=entry.get("steps", data["steps"]),
                        out=root / f"{config.name}-{track}-seed{seed}",
                        eval_episodes=data.get("eval_episodes", 10),
                        eval_envs=track_envs(suite, track),
                        checkpoint_every=data.get("checkpoint_every", 50_000),
                        device=device,
                        cpus=float(config.num_processes if cpus is None else cpus),
                        gpus=float(data.get("gpus_per_run") or 0),
                        after=None if after is None else f"{after}-{track}-seed{seed}",
                        eval_episodes_other=data.get("eval_episodes_other"),
                        evaluate_policy_only=data.get("evaluate_policy_only", False),
                        validation_every=every,
                        validation_episodes=data.get("validation_episodes", 100),
                        trust_code=trust_code,
                    )  # fmt: skip
                )
    folders = [run.out.name for run in runs]
    twice = [f for f in folders if folders.count(f) > 1]  # in the sweep's order: the first one is named
    if twice:
        raise ValueError(
            f"{source}: two runs would share the folder {twice[0]!r}: give the configs distinct names (override name)"
        )
    return Sweep(name, root, runs)


def latest_checkpoint(run_dir: Path, prefix: str) -> tuple[Path | None, int]:
    """The newest periodic checkpoint ``checkpoints/<prefix>_<n>_steps.zip`` of a run folder and its ``n``."""
    best: tuple[Path | None, int] = (None, 0)
    for path in (run_dir / "checkpoints").glob(f"{prefix}_*_steps.zip"):
        match = _CHECKPOINT.match(path.name)
        if match and match["prefix"] == prefix and int(match["steps"]) >= best[1]:
            best = (path, int(match["steps"]))
    return best


def track_envs(suite: str, track: str) -> tuple[str, ...]:
    """The ids of evaluation suite ``suite`` on ``track``, the track's main id first (it is always flown). A run on
    ``Random`` tracks is flown on its own id, the held-out tracks and the paper's main ids: its generalisation."""
    main = f"RaceObs-{track}-v0"
    if track == "Random":
        return (main, "RaceObs-Unseen-v0", *SUITES["main"])
    return (main, *(env_id for env_id in SUITES[suite] if split_env_id(env_id)[0] == track and env_id != main))


def is_finished(run: SweepRun) -> bool:
    """Whether the run's ``summary.json`` says it trained and (if asked) evaluated."""
    path = run.out / "summary.json"
    if not path.exists():
        return False
    if run.eval_episodes == 0:
        return True
    evaluation = json.loads(path.read_text()).get("eval")
    # a run evaluated before the sweep asked for more ids (older summaries: the main id alone) is not finished
    return evaluation is not None and set(run.eval_envs) <= set(evaluation.get("envs", run.eval_envs[:1]))


def run_job(run: SweepRun) -> dict[str, Any]:
    """Train (or resume) one run and evaluate its final checkpoint; skip it if already finished.

    Returns a row of the sweep's table: run, config, track, seed, status (``skipped`` / ``done``),
    timesteps, success rate.
    """
    row = {"run": run.label, "config": run.config.name, "track": run.track, "seed": run.seed}
    summary_path = run.out / "summary.json"
    if is_finished(run):
        return {**row, **_outcome(json.loads(summary_path.read_text())), "status": "skipped"}
    if not summary_path.exists():  # training not finished (train writes summary.json last)
        if hasattr(run.config, "n_steps"):  # PPO: from the newest periodic checkpoint, the steps still to go
            checkpoint, done = latest_checkpoint(run.out, run.config.name)
            steps = max(run.steps - done, 0)
        else:  # DAgger: its whole state after the last finished iteration, kept in the run folder
            done = completed_iterations(run.out) * run.config.steps_per_iteration
            checkpoint = run.out if resume_folder(run.out) is not None else None
            steps = max(run.steps - done, 0) if checkpoint is not None else run.steps
        run_training(
            run.config, run.track, steps, run.seed, run.out, resume=checkpoint,
            checkpoint_every=run.checkpoint_every, eval_episodes=0, device=run.device, trust_code=run.trust_code,
        )  # fmt: skip
    summary = json.loads(summary_path.read_text())
    if run.validation_every:  # incremental: only the multiples not yet in validation_curve.csv are flown
        validation_curve(run.out, run.validation_every, run.validation_episodes, run.trust_code)
    evaluated = summary["checkpoint"]
    if run.evaluate_policy_only and hasattr(run.config, "n_steps"):
        evaluated = str(run.out / "policy" / f"{run.config.name}-{run.track}.zip")
        if not Path(evaluated).is_file():
            export_run_policy(Path(summary["checkpoint"]), Path(evaluated), run.out, run.trust_code)
        summary["policy"] = evaluated
    if run.eval_episodes > 0:
        # Evaluated apart from train() so a run killed while evaluating resumes its evaluation, not its training.
        # The main id with eval_episodes, the others with eval_episodes_other, into one folder of records.
        other = run.eval_episodes if run.eval_episodes_other is None else run.eval_episodes_other
        parts = [([run.eval_envs[0]], run.eval_episodes), ([*run.eval_envs[1:]], other)]
        for envs, episodes in [(envs, n) for envs, n in parts if envs]:
            evaluator = Evaluator(  # this run's own policy: trusted if its folder's written.json lists it
                evaluated, envs, episodes=episodes, out_dir=run.out / "eval",
                agent_name=f"{run.config.name}-seed{run.seed}",
                trust_code=own_policy_trust(run.out, evaluated, run.trust_code),
            )  # fmt: skip
            results = evaluator.run(progress=False).set_index("env_id")
            if envs[0] == run.eval_envs[0]:
                main = results.loc[run.eval_envs[0]]  # the sweep's table: the run's own track, as the paper's
        summary["eval"] = {k: _plain(main[k]) for k in ("n", "successes", "success_rate", "lap_time_mean")}
        summary["eval"]["envs"] = list(run.eval_envs)
    atomic_write(summary_path, json.dumps(summary, indent=2))
    return {**row, **_outcome(summary), "status": "done"}


def export_run_policy(checkpoint: Path, out: Path, run_dir: Path, trust_code: bool = False) -> Path:
    """A run's final checkpoint without its optimizer state (``racebench export-policy``), the file to commit;
    observation-normalising statistics are copied beside it (reward-only ones change no action). Both are listed in
    the run folder's ``written.json``, so the run's evaluation loads them without ``--trust-code``."""
    agent = SB3Agent(checkpoint, trust_code=own_policy_trust(run_dir, checkpoint, trust_code))
    out.parent.mkdir(parents=True, exist_ok=True)
    written = [export_policy(agent.model, out)]
    if agent.normalizer is not None:
        written.append(Path(shutil.copyfile(vecnormalize_path(checkpoint), out.parent / "vecnormalize.pkl")))
    record_written(run_dir, *written)
    return out


def _outcome(summary: dict[str, Any]) -> dict[str, Any]:
    evaluation = summary.get("eval") or {}
    return {"timesteps": summary.get("timesteps"), "success_rate": evaluation.get("success_rate")}


def _failed(run: SweepRun, exc: BaseException) -> dict[str, Any]:
    last = (str(exc).strip().splitlines() or [type(exc).__name__])[-1]
    return {"run": run.label, "config": run.config.name, "track": run.track, "seed": run.seed,
            "timesteps": None, "success_rate": None, "status": f"failed: {last}"}  # fmt: skip


def run_sweep(
    sweep: Sweep,
    backend: str = "local",
    ray_options: RayOptions | None = None,
    on_row: Callable[[dict[str, Any]], None] | None = None,
    max_runs: int | None = None,
) -> list[dict[str, Any]]:
    """Run every unfinished run of ``sweep``; write ``<out>/sweep.csv``; return its rows (in the sweep's order).

    A failing run is recorded as ``failed: <reason>`` and the others go on. ``on_row`` is called as each
    run ends. ``max_runs`` (local backend): train at most this many unfinished runs, in the file's order, and
    report the rest ``not started`` (a campaign run one run at a time). On Ray each run is a task reserving
    ``cpus``/``gpus``; Ray re-runs a task whose worker or node died (``ray_options.max_retries``), which resumes
    from the run's folder.
    """
    rows: dict[str, dict[str, Any]] = {}

    def finish(run: SweepRun, row: dict[str, Any]) -> None:
        rows[run.label] = row
        if on_row is not None:
            on_row(row)

    def blocked(run: SweepRun) -> bool:  # the run it starts from failed: report it failed, do not start it
        if run.after is None or not str(rows[run.after]["status"]).startswith("failed"):
            return False
        if is_finished(run) or latest_checkpoint(run.out, run.config.name)[0] is not None:
            return False  # finished (skipped) or resumable from its own checkpoint: needs nothing from it
        finish(run, _failed(run, RuntimeError(f"it starts from {run.after}, which failed")))
        return True

    if max_runs is not None and (backend != "local" or max_runs < 1):
        raise ValueError("max_runs is an integer >= 1, for the local backend")
    if backend == "local":
        started, stopped = 0, False
        for run in sweep.runs:  # load_sweep lists a run's `after` before it
            if (stopped or (max_runs is not None and started >= max_runs)) and not is_finished(run):
                finish(run, {"run": run.label, "config": run.config.name, "track": run.track, "seed": run.seed,
                             "timesteps": None, "success_rate": None, "status": "not started"})  # fmt: skip
                continue
            if blocked(run):
                continue
            started += not is_finished(run)
            try:
                finish(run, run_job(run))
            except TrainingInterrupted as exc:  # stopped on request: checkpointed, and no further run starts
                stopped = True
                finish(run, {"run": run.label, "config": run.config.name, "track": run.track, "seed": run.seed,
                             "timesteps": latest_checkpoint(run.out, run.config.name)[1], "success_rate": None,
                             "status": f"interrupted: {exc}"})  # fmt: skip
            except Exception as exc:  # noqa: BLE001 - one failing run must not stop the sweep
                traceback.print_exc()
                finish(run, _failed(run, exc))
    elif backend == "ray":
        options = ray_options or RayOptions()
        options.validate()
        with connected(options) as ray:
            largest = max((n["Resources"].get("CPU", 0) for n in ray.nodes() if n["Alive"]), default=0)
            for run in sweep.runs:
                if run.cpus > largest:  # Ray would wait for such a node for ever (unless an autoscaler adds one)
                    logger.warning("racebench sweep: %s reserves %g CPUs, more than any node has (%g)",
                                   run.label, run.cpus, largest)  # fmt: skip
            job = ray.remote(run_job)
            refs: dict[Any, SweepRun] = {}
            pending: list[Any] = []

            def submit(run: SweepRun) -> None:
                ref = job.options(num_cpus=run.cpus, num_gpus=run.gpus, max_retries=options.max_retries).remote(run)
                refs[ref] = run
                pending.append(ref)

            chained = [run for run in sweep.runs if run.after is not None]

            def release(label: str) -> None:  # the run `label` has ended: start its followers, or fail them
                for run in [r for r in chained if r.after == label]:
                    chained.remove(run)
                    if blocked(run):
                        release(run.label)  # and theirs, which will never start either
                    else:
                        submit(run)

            for run in sweep.runs:
                if run.after is None:
                    submit(run)
            while pending:
                ready, rest = ray.wait(pending, num_returns=1)
                pending[:] = rest
                for ref in ready:
                    try:
                        finish(refs[ref], ray.get(ref))
                    except Exception as exc:  # noqa: BLE001 - a failed run (after Ray's retries) is reported
                        logger.error("racebench sweep: %s failed:\n%s", refs[ref].label, exc)  # the remote traceback
                        finish(refs[ref], _failed(refs[ref], exc))
                    release(refs[ref].label)
    else:
        raise ValueError(f"backend must be 'local' or 'ray', got {backend!r}")
    ordered = [rows[run.label] for run in sweep.runs]
    sweep.out.mkdir(parents=True, exist_ok=True)
    atomic_write(sweep.out / "sweep.csv", pd.DataFrame(ordered).to_csv(index=False))
    return ordered
