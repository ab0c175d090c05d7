"""``racebench`` command line: list environments, fly, evaluate, tables, figures, scene export."""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import gymnasium as gym

import racebench
from racebench.agents.base import BUILTIN_AGENTS
from racebench.evaluation.records import has_trajectories
from racebench.utils.files import sha256_file

SCENE_FORMATS: tuple[str, ...] = (".glb", ".gltf", ".obj", ".ply", ".stl", ".off")
# From the registry of built-ins, so a new built-in agent is listed without anyone remembering to.
AGENT_HELP = f"agent spec: {' | '.join(BUILTIN_AGENTS)} | model.zip | policy.onnx | module:Class | file.py:Class"
AGENT_KWARGS_HELP = "JSON object of keyword arguments for a module:Class agent's constructor, e.g. '{\"k\": 1}'"
VECNORMALIZE_HELP = (
    "an SB3 .zip's VecNormalize statistics file (default: the one matched to it by name, beside it or in "
    "rl-baselines3-zoo's <run>/<env_id>/vecnormalize.pkl; an error when that is ambiguous)"
)
NO_VECNORMALIZE_HELP = "fly an SB3 .zip without the VecNormalize statistics found near it (part of its policy hash)"
log = logging.getLogger("racebench")


def _make(env_id: str, **kwargs) -> gym.Env:
    if env_id not in gym.registry and env_id not in racebench.ENV_IDS:
        raise SystemExit(f"racebench: unknown environment id {env_id!r}; `racebench envs` lists them")
    return gym.make(env_id, **kwargs)


def fly(
    env_id: str,
    agent: str,
    seed: int,
    obs_mode: str | None = None,
    trust_code: bool = False,
    agent_kwargs: dict | None = None,
    vecnormalize: str | Path | bool | None = None,
) -> dict:
    """Fly one episode of ``env_id`` with any agent spec ``evaluate`` accepts; return its outcome as a dict.
    ``vecnormalize``: an SB3 checkpoint's statistics (:func:`racebench.agents.trust.resolve_vecnormalize`).

    Raises :class:`~racebench.agents.base.AgentLoadError` on a bad spec, an untrusted one without ``trust_code``, or an
    ``obs_mode`` other than the one the policy reads (built-in agents, which never read their observation, fly
    either).
    """
    from racebench.agents.base import AgentLoadError
    from racebench.agents.loading import load_agent
    from racebench.evaluation.rollout import run_episode
    from racebench.evaluation.worker import SingleTorchThread

    pilot = load_agent(agent, trust_code=trust_code, agent_kwargs=agent_kwargs, vecnormalize=vecnormalize)
    if obs_mode is not None and obs_mode != pilot.obs_mode and agent not in BUILTIN_AGENTS:
        # checked before flying: the policy would otherwise fail inside its first act() with an obscure message
        raise AgentLoadError(f"this policy takes {pilot.obs_mode} observations (use --obs-mode {pilot.obs_mode})")
    env = _make(env_id, obs_mode=obs_mode or pilot.obs_mode)
    with SingleTorchThread():
        result = run_episode(pilot, env, seed)
    env.close()
    truncated = not (result["success"] or result["crashed"] or result["error"])
    return {"env_id": env_id, "agent": agent, "seed": seed, **result, "truncated": truncated}


def build_parser() -> argparse.ArgumentParser:
    """The ``racebench`` argument parser (every option has help text; docs/commands.md's command table is
    checked against it by a test)."""
    parser = argparse.ArgumentParser(prog="racebench", description=__doc__)
    parser.add_argument("--version", action="version", version=f"racebench {racebench.__version__}")
    verbosity = parser.add_mutually_exclusive_group()
    verbosity.add_argument("-q", "--quiet", action="store_true", help="only warnings, errors and the results")
    verbosity.add_argument("-v", "--verbose", action="store_true", help="debug messages too")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    sub.add_parser("envs", help="list the registered environment ids")

    p_fly = sub.add_parser("fly", help="fly one episode with any agent and print the outcome")
    p_fly.add_argument("--env", default="RaceObs-S-v0", help="environment id (default: RaceObs-S-v0)")
    p_fly.add_argument("--agent", default="follow", help=f"{AGENT_HELP} (default: follow)")
    p_fly.add_argument("--seed", type=int, default=0, help="episode seed (default 0)")
    p_fly.add_argument(
        "--obs-mode",
        choices=("vision", "state"),
        default=None,
        help="observation mode (default: the agent's own; another is refused, except by built-ins, which ignore it)",
    )
    p_fly.add_argument("--trust-code", action="store_true", help="allow a .zip or module:Class agent (runs code)")
    p_fly.add_argument("--agent-kwargs", default=None, help=AGENT_KWARGS_HELP)
    _add_vecnormalize_options(p_fly)

    p_scene = sub.add_parser("scene", help="write the scene of one episode as a mesh (.glb/.obj) and JSON")
    p_scene.add_argument("--env", default="RaceObs-S-v0", help="environment id (default: RaceObs-S-v0)")
    p_scene.add_argument("--seed", type=int, default=0, help="episode seed: it fixes the scene (default 0)")
    p_scene.add_argument("--out", default="scene.glb", help="mesh path (.glb .gltf .obj .ply .stl .off), JSON beside")

    p_eval = sub.add_parser("evaluate", help="evaluate an agent on env ids or suites; writes episodes/summary CSVs")
    p_eval.add_argument("--agent", required=True, help=AGENT_HELP)
    p_eval.add_argument(
        "--envs", nargs="+", default=["main"], help="env ids and/or suites: main, density, gates, paper (default: main)"
    )
    p_eval.add_argument("--episodes", type=int, default=10, help="episodes per env id (default 10, as in the paper)")
    p_eval.add_argument(
        "--out",
        default=None,
        help="output directory; holds one policy's records (default: runs/eval/<name>-<policy sha256 prefix>)",
    )
    p_eval.add_argument("--workers", type=int, default=1, help="worker processes (default 1)")
    p_eval.add_argument("--name", default=None, help="label of the agent in the CSVs (default: derived from --agent)")
    p_eval.add_argument("--save-trajectories", action="store_true", help="store flown paths for `racebench plot`")
    p_eval.add_argument(
        "--trust-code",
        action="store_true",
        help="allow agents whose loading runs code from a file: SB3 .zip (unpickled) and module:Class / file.py:Class",
    )
    p_eval.add_argument("--force", action="store_true", help="discard every record already in --out and start afresh")
    p_eval.add_argument(
        "--renderer",
        default="pybullet",
        choices=("pybullet", "raycast"),
        help="depth renderer (default pybullet, the envs' own; raycast: its tested match, ~10x faster)",
    )
    p_eval.add_argument(
        "--batch",
        type=int,
        default=64,
        help="episodes each process flies in lockstep, one batched policy call per step "
        "(SB3/ONNX; default 64, at most the evaluation's episodes)",
    )
    p_eval.add_argument(
        "--seed-set",
        default="public",
        choices=("public", "private"),
        help="public: seeds 1,000,000 + i (default); private: derived from the secret salt in $RACEBENCH_PRIVATE_SALT",
    )
    p_eval.add_argument("--agent-kwargs", default=None, help=AGENT_KWARGS_HELP)
    _add_vecnormalize_options(p_eval)
    _add_backend_options(p_eval)
    p_eval.add_argument("--task-cpus", type=float, default=1.0, help="CPUs each Ray task reserves (default 1)")
    p_eval.add_argument(
        "--task-episodes",
        type=int,
        default=None,
        help="episodes per Ray task (default: the lockstep width, at most 16, if the agent batches; else 1)",
    )

    p_paper = sub.add_parser(
        "paper-tables",
        help="the paper's Tables II-IV, its claims and the learning curves from the committed campaign (no training)",
    )
    p_paper.add_argument("--root", default=".", help="the repository checkout to read (default: .)")
    p_paper.add_argument("--out", default="results", help="output folder (default: results)")
    p_paper.add_argument("--no-readme", action="store_true", help="leave README.md's results block as it is")
    p_paper.add_argument(
        "--trust-code", action="store_true",
        help="--validation-curve: unpickle checkpoints the run folder's written.json does not list (older runs)",
    )  # fmt: skip
    p_paper.add_argument(
        "--validation-curve", nargs="+", default=None, metavar="RUN_DIR",
        help="first fly each sweep run's periodic checkpoints on validation scenes (writes its validation_curve.csv)",
    )  # fmt: skip
    p_compare = sub.add_parser(
        "compare", help="two evaluations paired on the same scenes: exact McNemar test per env id and pooled"
    )
    p_compare.add_argument("a", help="first evaluation directory (racebench evaluate --out), one policy's")
    p_compare.add_argument("b", help="second evaluation directory, one policy's")
    p_compare.add_argument("--out", default=None, help="also write the per-env-id comparison as CSV")

    p_table = sub.add_parser("table", help="the paper's Table II, III or IV from result directories / summary CSVs")
    p_table.add_argument("results", nargs="+", help="result directories or summary.csv files")
    p_table.add_argument(
        "--table", default="II", choices=["II", "III", "IV"],
        help="II: main results; III: ablations; IV: obstacle density and gate shift (default II)",
    )  # fmt: skip
    p_table.add_argument("--format", default="md", choices=["md", "latex"], help="Markdown or LaTeX (default md)")
    p_table.add_argument("--no-ci", action="store_true", help="success rates without Wilson intervals")
    p_table.add_argument(
        "--seeds", default="separate", choices=["separate", "mean"],
        help="rows <config>-seed<k> (a sweep's training seeds): a row each, or one row per config with the seeds' "
        "mean success rate and its range over the seeds (default separate)",
    )  # fmt: skip
    p_table.add_argument("--out", default=None, help="write to this file instead of stdout")

    p_plot = sub.add_parser("plot", help="figures from result directories: SR by track, vs density, vs gate shift")
    p_plot.add_argument("results", nargs="+", help="result directories or summary.csv files")
    p_plot.add_argument(
        "--out", default="runs/figures", help="output directory (default runs/figures, outside version control)"
    )
    p_plot.add_argument(
        "--track-env",
        default=None,
        help="also draw the 3D track plot of this env id (Fig. 4): every result directory's saved trajectories",
    )
    p_plot.add_argument("--format", default="png", choices=("png", "pdf", "svg"), help="file format (default png)")
    p_plot.add_argument("--dpi", type=int, default=300, help="resolution of PNGs in dots per inch (default 300)")
    p_curves = sub.add_parser(
        "curves", help="training curves (the paper's Fig. 5) from `racebench train` run directories"
    )
    p_curves.add_argument("runs", nargs="+", help="run directories or their progress.csv files")
    p_curves.add_argument(
        "--out",
        default=None,
        help="output file, .png, .pdf or .svg (default runs/figures/training_curves.png, or success_curves.png)",
    )
    p_curves.add_argument("--smooth", type=int, default=20, help="rolling mean over this many updates (default 20)")
    p_curves.add_argument(
        "--success",
        action="store_true",
        help="training success vs environment steps and vs wall-clock instead (PPO and DAgger runs alike; "
        "runs of one config name, e.g. its training seeds, as a mean with a min-max band)",
    )
    p_curves.add_argument(
        "--window-steps",
        type=int,
        default=50_000,
        help="with --success: rolling mean over this many environment steps of each run (default 50000)",
    )
    p_curves.add_argument("--dpi", type=int, default=300, help="resolution of a PNG in dots per inch (default 300)")

    p_render = sub.add_parser(
        "render", help="video of one episode (GIF or MP4): chase view, coloured depth with a scale, caption"
    )
    p_render.add_argument("--agent", default="planner", help=f"{AGENT_HELP} (default: planner)")
    p_render.add_argument("--env", default="RaceObs-S-v0", help="environment id (default: RaceObs-S-v0)")
    p_render.add_argument(
        "--seed", type=int, default=1_000_000, help="episode seed (default 1000000, the first evaluation seed)"
    )
    p_render.add_argument("--out", default="episode.mp4", help="video path, .mp4 or .gif (default episode.mp4)")
    p_render.add_argument("--fps", type=int, default=25, help="frames per second of the video (default 25)")
    p_render.add_argument("--trust-code", action="store_true", help="allow a .zip or module:Class agent (runs code)")
    p_render.add_argument("--agent-kwargs", default=None, help=AGENT_KWARGS_HELP)
    _add_vecnormalize_options(p_render)

    p_train = sub.add_parser("train", help="train a baseline (PPO + GRU, curriculum, multi-scene) from a YAML config")
    p_train.add_argument("--config", required=True, help="a shipped config name (e.g. vision-ppo) or a YAML file")
    p_train.add_argument("--track", default="S", choices=["S", "J", "Circle"], help="track to train on (default S)")
    p_train.add_argument(
        "--steps", type=int, default=200_000, help="environment steps (default 200,000; with --resume: steps to add)"
    )
    p_train.add_argument("--seed", type=int, default=0, help="training seed (< 1,000,000: evaluation seeds are above)")
    p_train.add_argument("--out", default=None, help="run directory (default runs/<name>-<track>-seed<seed>)")
    p_train.add_argument(
        "--resume", default=None, help="checkpoint .zip to continue from (a DAgger config: its run folder)"
    )
    p_train.add_argument(
        "--trust-code",
        action="store_true",
        help="allow --resume from a checkpoint (and its VecNormalize statistics) that this run folder did not "
        "write and that is not shipped: both are unpickled, which can run code",
    )
    p_train.add_argument("--n-envs", type=int, default=None, help="override the config's n_envs")
    p_train.add_argument(
        "--num-processes",
        type=int,
        default=None,
        help="override the config's num_processes (e.g. 1 per run when two share 2 cores)",
    )
    p_train.add_argument("--eval-episodes", type=int, default=10, help="final evaluation episodes (0: none)")
    p_train.add_argument(
        "--device",
        default="auto",
        choices=("auto", "cpu", "cuda"),
        help="where the networks train (default auto: CUDA when torch sees a GPU); envs always step on CPU",
    )

    p_sweep = sub.add_parser(
        "sweep", help="a grid of training runs (config x track x seed) plus final evaluations; resumable"
    )
    p_sweep.add_argument("sweep", help="sweep file (YAML), e.g. baselines/sweeps/paper-tables.yaml")
    p_sweep.add_argument("--out", default=None, help="output folder (default: the file's out, or runs/sweeps/<name>)")
    _add_backend_options(p_sweep)
    p_sweep.add_argument("--workers", type=int, default=2, help="CPUs of a private local Ray instance (default 2)")
    p_sweep.add_argument(
        "--max-runs", type=int, default=None, metavar="N",
        help="local backend: train only the next N unfinished runs in the file's order (a campaign, run by run)",
    )  # fmt: skip
    p_sweep.add_argument(
        "--trust-code",
        action="store_true",
        help="resume and evaluate checkpoints that a run's folder did not write itself (e.g. runs begun before "
        "written.json existed): they are unpickled, which can run code",
    )

    p_distill = sub.add_parser(
        "distill", help="teacher-student baseline: a depth policy imitates the privileged planner (DAgger)"
    )
    p_distill.add_argument("--track", default="S", choices=["S", "J", "Circle"], help="track (default S)")
    p_distill.add_argument("--iterations", type=int, default=8, help="DAgger iterations (default 8)")
    p_distill.add_argument("--steps-per-iteration", type=int, default=20_000, help="env steps collected per iteration")
    p_distill.add_argument("--n-envs", type=int, default=16, help="envs flown side by side (default 16)")
    p_distill.add_argument("--epochs", type=int, default=2, help="passes over the aggregate per iteration")
    p_distill.add_argument("--max-samples", type=int, default=250_000, help="aggregate capacity (ring buffer)")
    p_distill.add_argument("--seed", type=int, default=0, help="training seed (< 1,000,000)")
    p_distill.add_argument("--out", default=None, help="run directory (default runs/vision-dagger-<track>-seed<seed>)")
    p_distill.add_argument("--eval-episodes", type=int, default=10, help="final evaluation episodes (0: none)")
    p_distill.add_argument(
        "--teacher", default="planner-fast", choices=["planner-fast", "planner"], help="privileged teacher"
    )
    p_distill.add_argument(
        "--student", default="vision-ppo", help="PPO baseline config whose network the student is (default vision-ppo)"
    )
    p_distill.add_argument(
        "--resume", action="store_true", help="continue the run in --out from its last finished iteration"
    )

    p_onnx = sub.add_parser("export-onnx", help="export an SB3 checkpoint's deterministic actor to ONNX")
    p_onnx.add_argument("checkpoint", help="SB3 / sb3-contrib .zip (PPO/A2C feed-forward or racebench GRU policy)")
    p_onnx.add_argument("--out", default=None, help="ONNX path (default: beside the checkpoint, .onnx)")
    p_onnx.add_argument("--trust-code", action="store_true", help="allow a checkpoint outside the shipped ones")
    _add_vecnormalize_options(p_onnx)

    p_export = sub.add_parser(
        "export-policy", help="write an SB3 checkpoint without its optimizer state (a policy-only .zip to commit)"
    )
    p_export.add_argument("checkpoint", help="SB3 / sb3-contrib .zip")
    p_export.add_argument("--out", required=True, help="the policy-only .zip to write")
    p_export.add_argument("--trust-code", action="store_true", help="allow a checkpoint outside the shipped ones")
    _add_vecnormalize_options(p_export)

    p_bench = sub.add_parser("bench", help="throughput: depth frames/s of both renderers, env steps/s, memory")
    p_bench.add_argument("--quick", action="store_true", help="smoke test of ~10 s (tiny sizes)")
    p_bench.add_argument("--out", default="bench.csv", help="CSV of every measurement (default bench.csv)")
    p_bench.add_argument("--track", default="S", choices=["S", "J", "Circle"], help="track of every env (default S)")
    p_bench.add_argument("--num-envs", type=int, default=None, help="envs of each vector-env run (default 32)")

    from racebench.leaderboard.command import add_parser as add_leaderboard_parser

    add_leaderboard_parser(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``racebench`` console script."""
    parser = build_parser()
    words = list(sys.argv[1:] if argv is None else argv)
    args, unknown = parser.parse_known_args(words)
    if unknown:
        _parser_of(parser, args, words, unknown).error(f"unrecognized arguments: {' '.join(unknown)}")
    _configure_logging(args.quiet, args.verbose)
    log.debug(f"racebench {racebench.__version__} from {Path(racebench.__file__).parent}, env version "
              f"{racebench.ENV_VERSION}, arguments {vars(args)}")  # fmt: skip
    if args.command == "leaderboard":
        from racebench.leaderboard.command import run as run_leaderboard

        return run_leaderboard(args)
    if args.command == "envs":
        _emit("\n".join(racebench.ENV_IDS))
    elif args.command == "fly":
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
    elif args.command == "scene":
        suffix = Path(args.out).suffix.lower()
        if suffix not in SCENE_FORMATS:
            formats = ", ".join(SCENE_FORMATS)
            raise SystemExit(f"racebench scene: --out {args.out!r}: not a mesh format; use one of {formats}")
        env = _make(args.env, obs_mode="state")
        env.reset(seed=args.seed)
        scene = env.unwrapped.scene
        path = scene.export(args.out)
        json_path = path.with_suffix(".json")
        json_path.write_text(json.dumps(scene.to_dict(), indent=2))
        env.close()
        log.info(f"wrote {path} and {json_path}")
    elif args.command == "train":
        from racebench.training.dagger.config import DaggerConfig
        from racebench.training.models import resolve_device
        from racebench.training.run import load_config, run_training

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
            result = run_training(
                config, args.track, args.steps, args.seed, args.out, args.resume,
                eval_episodes=args.eval_episodes, device=args.device, trust_code=args.trust_code,
            )  # fmt: skip
        except (OSError, ValueError) as exc:
            raise SystemExit(f"racebench train: {exc}") from exc
        print(json.dumps(result, indent=2))
    elif args.command == "export-onnx":
        from racebench.agents.base import AgentLoadError
        from racebench.agents.export import export_onnx
        from racebench.agents.loading import SB3Agent

        try:
            agent = SB3Agent(args.checkpoint, trust_code=args.trust_code, vecnormalize=_vecnormalize(args))
            # The checkpoint's statistics change its actions: they go into the graph.
            out = export_onnx(agent.model, args.out or Path(args.checkpoint).with_suffix(".onnx"), agent.normalizer)
        except (AgentLoadError, ValueError) as exc:
            raise SystemExit(f"racebench export-onnx: {exc}") from exc
        log.info(f"wrote {out} (sha256 {sha256_file(out)})")
    elif args.command == "export-policy":
        return _export_policy(args)
    elif args.command == "distill":
        from racebench.training.dagger.config import DaggerConfig
        from racebench.training.dagger.distill.distill import distill

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
    elif args.command == "evaluate":
        return _evaluate(args)
    elif args.command == "sweep":
        return _sweep(args)
    elif args.command == "table":
        from racebench.reporting.tables import make_table

        try:
            text = make_table(_summaries(args.results, "table"), args.table, args.format, ci=not args.no_ci,
                              seeds=args.seeds)  # fmt: skip
        except ValueError as exc:
            raise SystemExit(f"racebench table: {exc}") from exc
        if args.out:
            Path(args.out).write_text(text)
            log.info(f"wrote {args.out}")
        else:
            _emit(text)
    elif args.command == "paper-tables":
        return _paper_tables(args)
    elif args.command == "compare":
        return _compare(args)
    elif args.command == "plot":
        from racebench.reporting import plots

        if not 20 <= args.dpi <= 2400:
            raise SystemExit(f"racebench plot: --dpi must be in [20, 2400], got {args.dpi}")
        summary = _summaries(args.results, "plot")
        out, fmt, dpi = Path(args.out), args.format, args.dpi
        written = []
        for name, make in (
            ("success_by_track", lambda p: plots.plot_success_by_track(summary, p, dpi)),
            ("success_vs_density", lambda p: plots.plot_success_vs(summary, "density", p, dpi)),
            ("success_vs_gate_shift", lambda p: plots.plot_success_vs(summary, "gates", p, dpi)),
            ("success_by_level", lambda p: plots.plot_success_vs(summary, "levels", p, dpi)),
        ):
            try:
                written.append(make(out / f"{name}.{fmt}"))
            except ValueError as exc:  # a figure whose results are absent is skipped, with the reason
                log.warning(f"skipped {name}: {exc}")
        if args.track_env:
            folders = [Path(r) if Path(r).is_dir() else Path(r).parent for r in args.results]  # a CSV: its folder
            sources = [folder for folder in folders if has_trajectories(folder)]
            if not sources:
                raise SystemExit("racebench plot: --track-env needs a result directory made with --save-trajectories")
            if len(sources) < len(folders):
                without = ", ".join(str(folder) for folder in folders if folder not in sources)
                log.warning(f"no saved trajectories in {without}: not in the track figure")
            try:
                written.append(
                    plots.plot_track_3d(sources, args.track_env, out / f"track_{args.track_env}.{fmt}", dpi=dpi)
                )
            except ValueError as exc:
                raise SystemExit(f"racebench plot: {exc}") from exc
        for path in written:
            log.info(f"wrote {path}")
        if not written:
            raise SystemExit("racebench plot: no figure could be drawn from these results (see the reasons above)")
    elif args.command == "curves":
        from racebench.reporting.plots import plot_success_curves, plot_training_curves

        if args.smooth < 1 or args.window_steps < 1:
            raise SystemExit("racebench curves: --smooth and --window-steps must be >= 1")
        try:
            if args.success:
                out = args.out or "runs/figures/success_curves.png"
                written = plot_success_curves(args.runs, out, args.window_steps, args.dpi)
            else:
                out = args.out or "runs/figures/training_curves.png"
                written = plot_training_curves(args.runs, out, args.smooth, args.dpi)
            log.info(f"wrote {written}")
        except ValueError as exc:
            raise SystemExit(f"racebench curves: {exc}") from exc
    elif args.command == "render":
        from racebench.agents.base import AgentLoadError
        from racebench.agents.trust import parse_agent_kwargs
        from racebench.reporting.video import outcome_text, render_episode_video

        _make(args.env)  # validates the id with a clear message
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
    elif args.command == "bench":
        from racebench.benchmark import BenchSettings, run_benchmark

        settings = BenchSettings.quick() if args.quick else BenchSettings()
        settings.track = args.track
        if args.num_envs is not None:
            if args.num_envs < 2:
                raise SystemExit("racebench bench: --num-envs must be >= 2 (one batch per process)")
            settings.vector_envs = args.num_envs
        run_benchmark(settings, out=args.out)
    return 0


def _parser_of(
    parser: argparse.ArgumentParser, args: argparse.Namespace, words: list[str], unknown: list[str]
) -> argparse.ArgumentParser:
    """The (sub-)command parser that should report ``unknown`` words: the innermost command's, so its usage is
    shown (``parse_args`` reports them with the top-level usage); the top-level parser's if they precede the
    command word."""
    command = words.index(args.command) if args.command in words else len(words)
    if set(words[:command]) & set(unknown):
        return parser
    while True:
        action = next((a for a in parser._actions if isinstance(a, argparse._SubParsersAction)), None)
        if action is None or getattr(args, action.dest, None) is None:
            return parser
        parser = action.choices[getattr(args, action.dest)]


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


def _add_backend_options(parser: argparse.ArgumentParser) -> None:
    """``--backend`` and ``--address`` of the commands that can run on Ray."""
    parser.add_argument(
        "--backend",
        default="local",
        choices=("local", "ray"),
        help="local: processes on this machine (default); ray: Ray tasks (needs pip install -e '.[ray]')",
    )
    parser.add_argument(
        "--address",
        default=None,
        help="Ray cluster to join: auto (started here by `ray start`) or HOST:PORT; default: a private local "
        "instance of --workers CPUs",
    )
    parser.add_argument(
        "--max-retries", type=int, default=3, help="times Ray re-runs a task whose worker or node died (default 3)"
    )


def _add_vecnormalize_options(parser: argparse.ArgumentParser) -> None:
    """``--vecnormalize PATH`` and ``--no-vecnormalize`` of the commands that load an SB3 checkpoint."""
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--vecnormalize", default=None, metavar="PATH", help=VECNORMALIZE_HELP)
    group.add_argument("--no-vecnormalize", action="store_true", help=NO_VECNORMALIZE_HELP)


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

    rows = run_sweep(sweep, args.backend, options, on_row=show, max_runs=args.max_runs)
    print(f"wrote {sweep.out / 'sweep.csv'}")
    failed = [row["run"] for row in rows if row["status"].startswith("failed")]
    if failed:
        raise SystemExit(f"racebench sweep: {len(failed)} of {len(rows)} runs failed: {', '.join(failed)}")
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
    from racebench.reporting.paper import validation_curve, write_report

    root = Path(args.root)
    try:
        if not root.is_dir():
            raise ValueError(f"{root} is not a folder")
        for run in args.validation_curve or []:
            curve = validation_curve(run, trust_code=args.trust_code)
            log.info(f"{run}: validation success {', '.join(f'{r:.2f}' for r in curve['success_rate'])}")
        readme = None if args.no_readme else root / "README.md"
        written = write_report(root, args.out, readme)
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
    lines = [
        f"{key}: {side.evaluation}: {side.agent} (policy {side.policy_sha256}) {side.successes}/{side.n} "
        f"({100 * side.success_rate:.0f} % [{100 * side.sr_ci_low:.0f}–{100 * side.sr_ci_high:.0f}]), "
        f"mean lap {side.lap_time_mean:.2f} s; failures {side.failures}"
        for key, side in zip("ab", sides.itertuples(index=False), strict=True)
    ]  # fmt: skip
    lines.append("laps only a / only b finished of the pairs (same env id and seed); p: McNemar's exact test")
    lines.append(pairs.to_string(index=False, formatters={"p": "{:.3f}".format}))
    _emit("\n".join(lines))
    if args.out:
        pairs.to_csv(args.out, index=False)
        log.info(f"wrote {args.out}")
    return 0


def _export_policy(args: argparse.Namespace) -> int:
    """``racebench export-policy``: the checkpoint's policy without optimizer state, checked to act the same."""
    import shutil

    from racebench.agents.base import AgentLoadError
    from racebench.agents.export import export_policy
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
        export_policy(agent.model, out)
        if stats is not None:
            shutil.copyfile(stats, beside)
        copy = SB3Agent(out, trust_code=True)
        theirs, ours = agent.model.policy.state_dict(), copy.model.policy.state_dict()
        if theirs.keys() != ours.keys() or not all(theirs[k].equal(ours[k]) for k in theirs):
            raise ValueError(f"the weights read back from {str(out)!r} differ from the checkpoint's")
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
    print(shown[columns].to_string(index=False, float_format=lambda v: f"{v:.3f}"))
    log.info(f"wrote {evaluator.out_dir / 'episodes.csv'} and {evaluator.out_dir / 'summary.csv'}")
    asked = evaluator.selected  # the asked episodes, as just summarised
    failed = asked["crash_reason"].isin(["agent_error", "env_error"])
    if len(asked) and failed.all():
        first = str(asked.loc[failed, "error"].iloc[0]).strip().splitlines()[-1]
        raise SystemExit(f"racebench evaluate: every episode failed with an agent or env error, e.g. {first}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
