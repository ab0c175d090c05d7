"""The ``racebench`` command line: one small function per command (the parser: :mod:`racebench.cli_parser`)."""

from __future__ import annotations

import argparse
import json
import logging
import os
import shutil
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import racebench
from racebench.cli_parser import build_parser, parser_of, unrecognized
from racebench.evaluation.episode import fly, make_env  # noqa: F401 (racebench.cli.fly, as before)
from racebench.utils.files import sha256_file

#: What ``racebench evaluate`` prints above its summary table: what each column is, and its unit.
SUMMARY_LEGEND = (
    "n: episodes; success_rate: the share of them that finished the lap; sr_ci_low/sr_ci_high: its 95 % Wilson "
    "interval; lap_time_mean: mean lap time of the successful episodes in seconds ('–': no successful lap)"
)
SCENE_FORMATS: tuple[str, ...] = (".glb", ".gltf", ".obj", ".ply", ".stl", ".off")
log = logging.getLogger("racebench")


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``racebench`` console script."""
    parser = build_parser()
    words = list(sys.argv[1:] if argv is None else argv)
    args, unknown = parser.parse_known_args(words)
    if unknown:
        reporter = parser_of(parser, args, words, unknown)
        reporter.error(unrecognized(reporter, unknown))
    _configure_logging(args.quiet, args.verbose)
    log.debug(f"racebench {racebench.__version__} from {Path(racebench.__file__).parent}, env version "
              f"{racebench.ENV_VERSION}, arguments {vars(args)}")  # fmt: skip
    if args.command in EPISODE_SEED_COMMANDS and not 0 <= args.seed < 2**63:
        raise SystemExit(f"racebench {args.command}: --seed must be an episode seed from 0 to 2**63 - 1 (Gymnasium "
                         f"seeds are non-negative), got {args.seed}")  # fmt: skip
    return _commands()[args.command](args)


#: The commands whose ``--seed`` is an episode's (reset) seed.
EPISODE_SEED_COMMANDS = ("fly", "render", "scene")


def _commands() -> dict[str, Callable[[argparse.Namespace], int]]:
    """Command word -> the function that runs it (each returns the exit status)."""
    return {
        "leaderboard": _leaderboard,
        "envs": _envs,
        "fly": _fly,
        "scene": _scene,
        "train": _train,
        "export-onnx": _export_onnx,
        "export-policy": _export_policy,
        "distill": _distill,
        "evaluate": _evaluate,
        "sweep": _sweep,
        "trust": _trust,
        "table": _table,
        "paper-tables": _paper_tables,
        "compare": _compare,
        "plot": _plot,
        "curves": _curves,
        "render": _render,
        "bench": _bench,
    }


def _leaderboard(args: argparse.Namespace) -> int:
    """``racebench leaderboard ...``: add, verify, sign and build (:mod:`racebench.leaderboard.command`)."""
    from racebench.leaderboard.command import run as run_leaderboard

    return run_leaderboard(args)


def _envs(args: argparse.Namespace) -> int:
    """``racebench envs``: list the registered environment ids."""
    _emit("\n".join(racebench.ENV_IDS))
    return 0


def _fly(args: argparse.Namespace) -> int:
    """``racebench fly``: fly one episode and print its outcome."""
    from racebench.agents.base import AgentLoadError
    from racebench.agents.trust import parse_agent_kwargs

    try:
        kwargs = parse_agent_kwargs(args.agent_kwargs)
        result = fly(args.env, args.agent, args.seed, args.obs_mode, args.trust_code, kwargs, _vecnormalize(args))
    except AgentLoadError as exc:
        raise SystemExit(f"racebench fly: {exc}") from exc
    outcome = "SUCCESS" if result["success"] else f"FAILED ({result['crash_reason'] or 'time limit'})"
    print(json.dumps(result))
    lap = f", lap time {result['lap_time']:.2f} s" if result["success"] else ""
    log.info(f"{args.env} seed {args.seed} agent {args.agent}: {outcome}, gates {result['gates_passed']}{lap}")
    if result["error"]:
        last = str(result["error"]).strip().splitlines()[-1]
        raise SystemExit(f"racebench fly: the agent failed: {last}")
    return 0


def _scene(args: argparse.Namespace) -> int:
    """``racebench scene``: export a seed's scene as a mesh and JSON."""
    suffix = Path(args.out).suffix.lower()
    if suffix not in SCENE_FORMATS:
        formats = ", ".join(SCENE_FORMATS)
        raise SystemExit(f"racebench scene: --out {args.out!r}: not a mesh format; use one of {formats}")
    env = make_env(args.env, obs_mode="state")
    env.reset(seed=args.seed)
    scene = env.unwrapped.scene
    path = scene.export(args.out)
    json_path = path.with_suffix(".json")
    json_path.write_text(json.dumps(scene.to_dict(), indent=2))
    env.close()
    log.info(f"wrote {path} and {json_path}")
    return 0


def _train(args: argparse.Namespace) -> int:
    """``racebench train``: train a config (PPO or DAgger)."""
    from racebench.training.callbacks import TrainingInterrupted, checkpoint_on_sigterm
    from racebench.training.dagger.config import DaggerConfig
    from racebench.training.models import resolve_device
    from racebench.training.run import default_track, load_config, run_training

    try:
        config = load_config(args.config)
        if args.n_envs is not None:
            config.n_envs = args.n_envs
        if args.num_processes is not None and not isinstance(config, DaggerConfig):
            config.num_processes = args.num_processes
        if args.num_processes is not None:
            config.update_threads = args.num_processes  # as many learner threads as cores it was given
        config.validate(f"{args.config} with the command-line overrides")
        resolve_device(args.device)
        with checkpoint_on_sigterm():  # kill -TERM: a checkpoint at the next rollout end, then a one-line exit
            result = run_training(
                config, args.track or default_track(config), args.steps, args.seed, args.out, args.resume,
                eval_episodes=args.eval_episodes, device=args.device, trust_code=args.trust_code,
            )  # fmt: skip
    except (OSError, ValueError, TrainingInterrupted) as exc:
        raise SystemExit(f"racebench train: {exc}") from exc
    print(json.dumps(result, indent=2))
    return 0


def _export_onnx(args: argparse.Namespace) -> int:
    """``racebench export-onnx``: export an SB3 checkpoint as ONNX."""
    from racebench.agents.base import AgentLoadError
    from racebench.agents.export import export_onnx
    from racebench.agents.loading import SB3Agent
    from racebench.envs.registration import ENV_IDS

    if args.check_env is not None and args.check_env not in ENV_IDS:
        raise SystemExit(f"racebench export-onnx: --check-env {args.check_env!r} is not a racebench id")
    if args.check_steps < 1:  # zero steps would compare nothing and pass
        raise SystemExit(f"racebench export-onnx: --check-steps must be at least 1, got {args.check_steps}")
    try:
        agent = SB3Agent(args.checkpoint, trust_code=args.trust_code, vecnormalize=_vecnormalize(args))
        # The checkpoint's statistics change its actions: they go into the graph.
        out = export_onnx(agent.model, args.out or Path(args.checkpoint).with_suffix(".onnx"), agent.normalizer)
    except (AgentLoadError, ValueError) as exc:
        raise SystemExit(f"racebench export-onnx: {exc}") from exc
    log.info(f"wrote {out} (sha256 {sha256_file(out)})")
    if args.check_env is not None:
        from racebench.agents.export import ONNX_ACTION_TOLERANCE, onnx_action_gap
        from racebench.evaluation.protocol import EVAL_SEED_BASE

        gap, steps = onnx_action_gap(agent, out, args.check_env, EVAL_SEED_BASE, args.check_steps)
        where = f"over {steps} steps of {args.check_env} (seed {EVAL_SEED_BASE}, the checkpoint flying)"
        if not gap <= ONNX_ACTION_TOLERANCE:  # also NaN
            out.unlink()
            raise SystemExit(f"racebench export-onnx: the ONNX actions differ from the checkpoint's by up to {gap:.3g} "
                             f"{where}, above {ONNX_ACTION_TOLERANCE:g}: {out} removed")  # fmt: skip
        log.info(f"checked: max |ONNX action - checkpoint action| = {gap:.2g} {where}")
    return 0


def _distill(args: argparse.Namespace) -> int:
    """``racebench distill``: DAgger distillation from the built-in settings."""
    from racebench.training.dagger.config import DaggerConfig
    from racebench.training.dagger.loop import distill

    config = DaggerConfig(
        track=args.track, iterations=args.iterations, steps_per_iteration=args.steps_per_iteration,
        n_envs=args.n_envs, seed=args.seed, epochs=args.epochs, max_samples=args.max_samples,
        teacher=args.teacher, student=args.student,
    )  # fmt: skip
    try:
        config.validate()
    except ValueError as exc:
        raise SystemExit(f"racebench {exc}") from exc
    out = args.out or Path("runs") / f"vision-dagger-{args.track}-seed{args.seed}"
    try:
        summary = distill(config, out, eval_episodes=args.eval_episodes, resume=args.resume)
    except ValueError as exc:
        raise SystemExit(f"racebench distill: {exc}") from exc
    print(json.dumps(summary, indent=2))
    return 0


def _table(args: argparse.Namespace) -> int:
    """``racebench table``: a results table (``--table robustness``: also its CSV and figure)."""
    from racebench.reporting.generalization import generalization_table
    from racebench.reporting.robustness_report import write_robustness
    from racebench.reporting.tables import make_table
    try:
        if args.table != "robustness" and (args.csv or args.figure):
            raise ValueError("--csv and --figure are options of --table robustness")
        if args.table == "unseen":  # per policy, from the records (paired tests need the episodes)
            text = generalization_table(args.results, args.format, ci=not args.no_ci)
        elif args.table == "robustness":
            text = write_robustness(args.results, args.format, args.csv, args.figure, args.seeds)
        else:
            text = make_table(_summaries(args.results, "table"), args.table, args.format, ci=not args.no_ci,
                              seeds=args.seeds)  # fmt: skip
    except (OSError, ValueError) as exc:
        raise SystemExit(f"racebench table: {exc}") from exc
    if args.out:
        Path(args.out).write_text(text)
        log.info(f"wrote {args.out}")
    else:
        _emit(text)
    return 0


def _plot(args: argparse.Namespace) -> int:
    """``racebench plot``: the result figures."""
    from racebench.evaluation.records import has_trajectories
    from racebench.reporting import plots

    if not 20 <= args.dpi <= 2400:
        raise SystemExit(f"racebench plot: --dpi must be in [20, 2400], got {args.dpi}")
    summary = _summaries(args.results, "plot")
    out, formats, dpi = Path(args.out), list(dict.fromkeys(args.format)), args.dpi
    if args.leaderboard:
        import pandas as pd

        from racebench.evaluation.results import check_one_env_version, load_result_dir

        try:
            from racebench.leaderboard.ranking import entry_summary

            entries, versions = entry_summary(args.leaderboard)
            for path in args.results:  # a figure is of one env version: the entries' and the results' alike
                folder, records = load_result_dir(path, strict=False)
                versions[str(folder)] = records["env_version"]
            check_one_env_version(versions)
        except (OSError, ValueError) as exc:
            raise SystemExit(f"racebench plot: --leaderboard: {exc}") from exc
        if entries.empty:
            log.warning(f"no verified learned entry in {args.leaderboard}: the figures show the results only")
        summary = pd.concat([summary, entries], ignore_index=True)
    written = []
    for name, make in (
        ("success_by_track", lambda p: plots.plot_success_by_track(summary, p, dpi)),
        ("success_vs_density", lambda p: plots.plot_success_vs(summary, "density", p, dpi)),
        ("success_vs_gate_shift", lambda p: plots.plot_success_vs(summary, "gates", p, dpi)),
        ("success_by_level", lambda p: plots.plot_success_vs(summary, "levels", p, dpi)),
    ):
        for fmt in formats:
            try:
                written.append(make(out / f"{name}.{fmt}"))
            except ValueError as exc:  # a figure whose results are absent is skipped, with the reason
                log.warning(f"skipped {name}: {exc}")
                break
    if args.track_env:
        folders = [Path(r) if Path(r).is_dir() else Path(r).parent for r in args.results]  # a CSV: its folder
        sources = [folder for folder in folders if has_trajectories(folder)]
        if not sources:
            raise SystemExit("racebench plot: --track-env needs a result directory made with --save-trajectories")
        if len(sources) < len(folders):
            without = ", ".join(str(folder) for folder in folders if folder not in sources)
            log.warning(f"no saved trajectories in {without}: not in the track figure")
        try:
            for fmt in formats:
                written.append(plots.plot_track_3d(sources, args.track_env, out / f"track_{args.track_env}.{fmt}",
                                                   dpi=dpi))  # fmt: skip
        except ValueError as exc:
            raise SystemExit(f"racebench plot: {exc}") from exc
    for path in written:
        log.info(f"wrote {path}")
    if not written:
        raise SystemExit("racebench plot: no figure could be drawn from these results (see the reasons above)")
    return 0


def _curves(args: argparse.Namespace) -> int:
    """``racebench curves``: training curves of runs."""
    from racebench.reporting.plots import plot_success_curves, plot_training_curves

    if args.smooth < 1 or args.window_steps < 1:
        raise SystemExit("racebench curves: --smooth and --window-steps must be >= 1")
    given = args.label or []
    labels = dict(label.split("=", 1) for label in given if "=" in label)
    if len(labels) < len({label.split("=", 1)[0] for label in given}):
        raise SystemExit("racebench curves: --label takes RUN=NAME")
    try:
        if args.success:
            outs = args.out or ["runs/figures/success_curves.png"]
            plot_success_curves(args.runs, list(outs), args.window_steps, args.dpi, labels)
        else:
            outs = args.out or ["runs/figures/training_curves.png"]
            for out in outs:
                plot_training_curves(args.runs, out, args.smooth, args.dpi)
        for out in outs:
            log.info(f"wrote {out}")
    except ValueError as exc:
        raise SystemExit(f"racebench curves: {exc}") from exc
    return 0


def _render(args: argparse.Namespace) -> int:
    """``racebench render``: an episode's video."""
    from racebench.agents.base import AgentLoadError
    from racebench.agents.trust import parse_agent_kwargs
    from racebench.reporting.video import outcome_text, render_episode_video

    make_env(args.env)  # validates the id with a clear message
    if not 1 <= args.fps <= 50:
        raise SystemExit(f"racebench render: --fps must be in [1, 50] (the control rate), got {args.fps}")
    try:
        kwargs = parse_agent_kwargs(args.agent_kwargs)
        video, result = render_episode_video(
            args.agent, args.env, args.seed, args.out, args.fps, trust_code=args.trust_code, agent_kwargs=kwargs,
            vecnormalize=_vecnormalize(args),
        )  # fmt: skip
    except (AgentLoadError, ValueError) as exc:
        raise SystemExit(f"racebench render: {exc}") from exc
    log.info(f"wrote {video} ({outcome_text(result)})")
    return 0


def _bench(args: argparse.Namespace) -> int:
    """``racebench bench``: the performance benchmark."""
    from racebench.benchmark import BenchSettings, run_benchmark

    settings = BenchSettings.quick() if args.quick else BenchSettings()
    settings.track = args.track
    if args.num_envs is not None:
        if args.num_envs < 2:
            raise SystemExit("racebench bench: --num-envs must be >= 2 (one batch per process)")
        settings.vector_envs = args.num_envs
    run_benchmark(settings, out=args.out)
    return 0


class _BelowWarning(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        return record.levelno < logging.WARNING


def _configure_logging(quiet: bool, verbose: bool) -> None:
    """racebench's messages: info (``wrote ...``, progress) to stdout, warnings and errors to stderr.

    ``-q`` keeps warnings, errors and each command's results (tables, JSON); ``-v`` adds debug messages.
    """
    level = logging.WARNING if quiet else logging.DEBUG if verbose else logging.INFO
    out = logging.StreamHandler(sys.stdout)
    out.addFilter(_BelowWarning())
    err = logging.StreamHandler(sys.stderr)
    err.setLevel(logging.WARNING)
    for handler in (out, err):
        handler.setFormatter(logging.Formatter("%(message)s"))
    log.handlers[:] = [out, err]
    log.setLevel(level)
    log.propagate = False  # our own handlers; the root logger (and library loggers) stay as they are


def _vecnormalize(args: argparse.Namespace) -> str | bool | None:
    """The ``vecnormalize`` choice of the command line: a path, ``False`` (``--no-vecnormalize``) or ``None``."""
    return False if args.no_vecnormalize else args.vecnormalize


def _ray_options(args: argparse.Namespace, **options: Any) -> Any:
    """The :class:`~racebench.evaluation.ray_backend.RayOptions` of the command line (``None`` for the local
    backend)."""
    from racebench.evaluation.ray_backend import RayOptions

    if args.backend != "ray":
        if args.address is not None:
            raise SystemExit(f"racebench {args.command}: --address needs --backend ray")
        return None
    return RayOptions(address=args.address, max_retries=args.max_retries, **options)


def _sweep(args: argparse.Namespace) -> int:
    """``racebench sweep``: run the grid, print one line per run; non-zero exit if any run failed."""
    from racebench.evaluation.ray_backend import require_ray
    from racebench.training.callbacks import checkpoint_on_sigterm
    from racebench.training.sweep import load_sweep, run_sweep

    try:
        if args.backend == "ray":
            require_ray()
        sweep = load_sweep(args.sweep, args.out, trust_code=args.trust_code)
        if args.max_runs is not None and (args.backend != "local" or args.max_runs < 1):
            raise ValueError("--max-runs is an integer >= 1, for the local backend")
        options = _ray_options(args, local_cpus=args.workers)
        if options is not None:
            options.validate()
    except (OSError, ValueError) as exc:
        raise SystemExit(f"racebench sweep: {exc}") from exc
    print(f"sweep {sweep.name}: {len(sweep.runs)} runs in {sweep.out} ({args.backend} backend)")

    def show(row: dict) -> None:
        rate = "" if row["success_rate"] is None else f", success rate {row['success_rate']:.2f}"
        print(f"{row['run']}: {row['status']} ({row['timesteps']} steps{rate})", flush=True)

    with checkpoint_on_sigterm():  # local runs: kill -TERM checkpoints the run in progress and ends the sweep
        rows = run_sweep(sweep, args.backend, options, on_row=show, max_runs=args.max_runs)
    print(f"wrote {sweep.out / 'sweep.csv'}")
    stopped = [row["run"] for row in rows if row["status"].startswith("interrupted")]
    if stopped:
        raise SystemExit(f"racebench sweep: stopped on request during {stopped[0]} (checkpointed); "
                         "the same command resumes it")  # fmt: skip
    failed = [row["run"] for row in rows if row["status"].startswith("failed")]
    if failed:
        raise SystemExit(f"racebench sweep: {len(failed)} of {len(rows)} runs failed: {', '.join(failed)}")
    return 0


def _trust(args: argparse.Namespace) -> int:
    """``racebench trust``: record a reviewed run folder's listed checkpoints in this machine's trust store."""
    from racebench.agents.trust import trust_folder, trust_store

    for folder in args.folders:
        try:
            trusted = trust_folder(folder)
        except (OSError, ValueError) as exc:
            raise SystemExit(f"racebench trust: {exc}") from exc
        _emit(f"{folder}: trusted {len(trusted)} file(s) on this machine ({trust_store()})"
              + "".join(f"\n  {name}" for name in trusted))  # fmt: skip
    return 0


def _emit(text: str) -> None:
    """Print a command's result; a reader that leaves early (`racebench table ... | head`) is no error."""
    try:
        print(text)
        sys.stdout.flush()
    except BrokenPipeError:  # stdout's reader is gone: send the rest nowhere, so the exit's flush cannot fail
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())


def _summaries(results: Sequence[str], command: str):
    """Summaries recomputed from the records of result directories; a bad path is a one-line error."""
    from racebench.evaluation.results import read_summaries

    try:
        return read_summaries(results)
    except (OSError, ValueError) as exc:
        raise SystemExit(f"racebench {command}: {exc}") from exc


def _paper_tables(args: argparse.Namespace) -> int:
    """``racebench paper-tables``: Tables II-IV, claims.md, the README block and the learning curves."""
    from racebench.reporting.paper import write_report
    from racebench.reporting.validation import validation_curve

    root = Path(args.root)
    try:
        if not root.is_dir():
            raise ValueError(f"{root} is not a folder")
        for run in args.validation_curve or []:
            curve = validation_curve(run, trust_code=args.trust_code)
            log.info(f"{run}: validation success {', '.join(f'{r:.2f}' for r in curve['success_rate'])}")
        readme = None if args.no_readme else root / "README.md"
        written = write_report(root, args.out, readme, args.campaign, args.references)
    except (OSError, ValueError) as exc:
        raise SystemExit(f"racebench paper-tables: {exc}") from exc
    _emit("\n".join(f"wrote {path}" for path in written))
    return 0


def _compare(args: argparse.Namespace) -> int:
    """``racebench compare``: each side's outcome, then the paired test per shared env id and pooled."""
    from racebench.evaluation.results import paired_comparison

    try:
        sides, pairs = paired_comparison(args.a, args.b)
    except (OSError, ValueError) as exc:
        raise SystemExit(f"racebench compare: {exc}") from exc
    paired = int(pairs["pairs"].iloc[-1])
    lines = [
        f"{key}: {side.evaluation}: {side.agent} (policy {side.policy_sha256}): {side.n} episodes in the folder, "
        f"{paired} paired; failures of all {side.n}: {side.failures}"
        for key, side in zip("ab", sides.itertuples(index=False), strict=True)
    ]  # fmt: skip
    lines.append(
        "Per env id, on the paired episodes only (same env id and seed on both sides; a folder's other episodes are "
        "left out): SR = successes/pairs, success rate in % [its 95 % Wilson interval]; lap = mean lap time of the "
        "successful laps in seconds ('–': no successful lap)"
    )
    from racebench.reporting.tables import compare_header

    lines.append(compare_header(pairs).to_string(index=False))
    lines.append("laps only a / only b finished of the pairs; p: McNemar's exact test on those discordant pairs")
    lines.append(
        pairs[["env_id", "pairs", "only_a", "only_b", "p"]].to_string(index=False, formatters={"p": "{:.3f}".format})
    )
    _emit("\n".join(lines))
    if args.out:
        pairs.to_csv(args.out, index=False)
        log.info(f"wrote {args.out}")
    return 0


def _export_policy(args: argparse.Namespace) -> int:
    """``racebench export-policy``: the checkpoint's policy without optimizer state, checked to act the same."""
    from racebench.agents.base import AgentLoadError
    from racebench.agents.export import check_policy_export, export_policy
    from racebench.agents.loading import SB3Agent

    source, out = Path(args.checkpoint), Path(args.out)
    try:
        agent = SB3Agent(source, trust_code=args.trust_code, vecnormalize=_vecnormalize(args))
        if out.resolve() == source.resolve():
            raise ValueError(f"--out {str(out)!r} is the checkpoint itself; write the policy-only copy elsewhere")
        # Observation statistics change the actions, so they travel with the policy (rewards-only ones do not).
        stats = agent.stats_path if agent.normalizer is not None else None
        beside = out.parent / "vecnormalize.pkl"
        if beside.exists() and (stats is None or beside.read_bytes() != stats.read_bytes()):
            raise ValueError(f"{str(beside)!r} would be read as this policy's observation statistics; remove it")
        out.parent.mkdir(parents=True, exist_ok=True)
        export_policy(agent.model, out, keep_critic=args.keep_critic)
        if stats is not None:
            shutil.copyfile(stats, beside)
        copy = SB3Agent(out, trust_code=True)
        check_policy_export(agent.model, copy.model, str(out))
    except (AgentLoadError, OSError, ValueError) as exc:
        raise SystemExit(f"racebench export-policy: {exc}") from exc
    print(f"wrote {out} ({out.stat().st_size / 1e6:.1f} MB, {source.stat().st_size / 1e6:.1f} MB before); "
          f"policy sha256 {copy.sha256}")  # fmt: skip
    return 0


def _evaluate(args: argparse.Namespace) -> int:
    from racebench.agents.base import AgentLoadError
    from racebench.agents.trust import parse_agent_kwargs
    from racebench.evaluation.evaluator import Evaluator

    try:
        agent_kwargs = parse_agent_kwargs(args.agent_kwargs)
        evaluator = Evaluator(
            args.agent,
            envs=args.envs,
            episodes=args.episodes,
            out_dir=args.out,
            workers=args.workers,
            agent_name=args.name,
            save_trajectories=args.save_trajectories,
            trust_code=args.trust_code,
            force=args.force,
            renderer=args.renderer,
            batch=args.batch,
            seed_set=args.seed_set,
            agent_kwargs=agent_kwargs,
            vecnormalize=_vecnormalize(args),
            backend=args.backend,
            ray_options=_ray_options(args, task_cpus=args.task_cpus, task_episodes=args.task_episodes),
        )
    except (AgentLoadError, ValueError) as exc:
        raise SystemExit(f"racebench evaluate: {exc}") from exc
    todo = len(evaluator.pending())
    total = len(evaluator.env_ids) * evaluator.episodes
    identity = evaluator.identity
    what = f"{identity.kind}, sha256 {identity.sha256[:12]}, env version {racebench.ENV_VERSION}"
    if evaluator.seed_set != "public":
        what += f", {evaluator.seed_set} seeds of salt sha256 {evaluator.salt_sha256[:12]}"
    log.debug(f"policy {identity.source}: sha256 {identity.sha256}, privileged {identity.privileged}")
    log.info(
        f"{evaluator.agent_name} ({what}): "
        f"{total - todo}/{total} episodes already done in {evaluator.out_dir}, {todo} to run"
    )
    summary = evaluator.run(progress=not args.quiet)
    # the mean lap of the successful episodes, as the paper's tables and `racebench table` give it
    columns = ["env_id", "n", "successes", "success_rate", "sr_ci_low", "sr_ci_high", "lap_time_mean"]
    order = {env_id: i for i, env_id in enumerate(evaluator.env_ids)}
    shown = summary.sort_values("env_id", key=lambda ids: ids.map(order))
    print(SUMMARY_LEGEND)  # what each column is, and its unit
    print(shown[columns].to_string(index=False, float_format=lambda v: f"{v:.3f}", na_rep="–"))
    log.info(f"wrote {evaluator.out_dir / 'episodes.csv'} and {evaluator.out_dir / 'summary.csv'}")
    asked = evaluator.selected  # the asked episodes, as just summarised
    failed = asked["crash_reason"].isin(["agent_error", "env_error"])
    if len(asked) and failed.all():
        first = str(asked.loc[failed, "error"].iloc[0]).strip().splitlines()[-1]
        raise SystemExit(f"racebench evaluate: every episode failed with an agent or env error, e.g. {first}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
