"""The ``racebench`` command line's arguments: the parser of every command and its options.

(The commands themselves: :mod:`racebench.cli`.)
"""

from __future__ import annotations

import argparse
import difflib
import re
import sys
from collections.abc import Sequence

import racebench
from racebench.agents.base import BUILTIN_AGENTS

#: The parser's description: what ``racebench --help`` says first.
DESCRIPTION = (
    "racebench: a benchmark for vision-based quadrotor racing. List the environments, fly an agent, train and sweep "
    "baselines, evaluate and compare agents, make the paper's tables and figures, and add or verify leaderboard "
    "entries. `racebench COMMAND --help` describes each command."
)
_NUMBER = re.compile(r"^-\d+$|^-\d*\.\d+$")


class CommandParser(argparse.ArgumentParser):
    """An argument parser that names a misspelled option (and the closest known one), even where a missing
    required option would otherwise be the only error (``evaluate --agnet hover``)."""

    def parse_known_args(self, args: Sequence[str] | None = None, namespace: argparse.Namespace | None = None):  # type: ignore[override]
        self._words = list(sys.argv[1:] if args is None else args)  # a sub-command's parser: the words after it
        return super().parse_known_args(args, namespace)

    def error(self, message: str):  # type: ignore[override]
        if message.startswith("the following arguments are required"):
            unknown = [w for w in getattr(self, "_words", []) if self.unknown_option(w)]
            if unknown:
                message = unrecognized(self, unknown)
        super().error(message)

    def unknown_option(self, word: str) -> bool:
        """Whether ``word`` looks like an option (not a negative number) that this parser does not know."""
        if not word.startswith("-") or word == "-" or word == "--" or _NUMBER.match(word):
            return False
        name = word.split("=", 1)[0]
        return name not in self._option_string_actions and not self._get_option_tuples(name)


def unrecognized(parser: argparse.ArgumentParser, unknown: Sequence[str]) -> str:
    """argparse's "unrecognized arguments" message, with the known option closest to each misspelled one."""
    known = [s for s in parser._option_string_actions if s.startswith("--")]
    close = {}
    for word in unknown:
        name = word.split("=", 1)[0]
        if name.startswith("--") and (match := difflib.get_close_matches(name, known, n=1, cutoff=0.6)):
            close[name] = match[0]
    hints = [f"{known} (for {name})" for name, known in close.items()] if len(close) > 1 else list(close.values())
    hint = f" (did you mean {', '.join(hints)}?)" if hints else ""
    return f"unrecognized arguments: {' '.join(unknown)}{hint}"


def describe_commands(parser: argparse.ArgumentParser) -> None:
    """Give each sub-command without a description its one-line help as one (``racebench compare --help``)."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            helps = {choice.dest: choice.help for choice in action._choices_actions}
            for name, sub in action.choices.items():
                if sub.description is None and helps.get(name):
                    sub.description = helps[name][0].upper() + helps[name][1:] + "."
                describe_commands(sub)
# From the registry of built-ins, so a new built-in agent is listed without anyone remembering to.
AGENT_HELP = f"agent spec: {' | '.join(BUILTIN_AGENTS)} | model.zip | policy.onnx | module:Class | file.py:Class"
AGENT_KWARGS_HELP = "JSON object of keyword arguments for a module:Class agent's constructor, e.g. '{\"k\": 1}'"
VECNORMALIZE_HELP = (
    "an SB3 .zip's VecNormalize statistics file (default: the one matched to it by name, beside it or in "
    "rl-baselines3-zoo's <run>/<env_id>/vecnormalize.pkl; an error when that is ambiguous)"
)
NO_VECNORMALIZE_HELP = "fly an SB3 .zip without the VecNormalize statistics found near it (part of its policy hash)"


def build_parser() -> argparse.ArgumentParser:
    """The ``racebench`` argument parser (every option has help text; docs/commands.md's command table is
    checked against it by a test)."""
    parser = CommandParser(prog="racebench", description=DESCRIPTION)
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
        "--envs", nargs="+", default=["main"],
        help="env ids and/or suites: main, density, gates, paper, robustness, robustness-S|Circle|J (default: main)",
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
        help="the paper's Tables II-IV, its claims and the learning curves from the committed campaigns (no training)",
    )
    p_paper.add_argument("--root", default=".", help="the repository checkout to read (default: .)")
    p_paper.add_argument(
        "--out", default="results",
        help="the results folder (default: results): campaign 1 writes into it, campaign 2 into its campaign-2/, "
        "claims.md (every campaign side by side) into it",
    )  # fmt: skip
    p_paper.add_argument("--no-readme", action="store_true", help="leave README.md's results block as it is")
    p_paper.add_argument(
        "--campaign", default=None,
        help="only this campaign: a registered name (campaign-4m: campaign 1, env version 2; campaign-2: env version "
        "3), its run folder (baselines/experiments/campaign-2) or another run folder under --root (default: every "
        "registered campaign); each knows its references and env version",
    )  # fmt: skip
    p_paper.add_argument(
        "--references", default=None,
        help="with --campaign: the built-in agents' evaluations on its env version, under --root, instead of its own "
        "(campaign 1: results/env-v2; campaign 2: results)",
    )  # fmt: skip
    p_paper.add_argument(
        "--trust-code", action="store_true",
        help="--validation-curve: unpickle checkpoints this machine did not write (older runs, other machines)",
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

    p_table = sub.add_parser(
        "table", help="the paper's Table II, III or IV, or the robustness table, from result directories / summary CSVs"
    )
    p_table.add_argument("results", nargs="+", help="result directories or summary.csv files")
    p_table.add_argument(
        "--table", default="II", choices=["II", "III", "IV", "unseen", "robustness"],
        help="II: main results; III: ablations; IV: obstacle density and gate shift; unseen: the held-out tracks "
        "(RaceObs-Unseen-v0) per policy with paired tests, docs/unseen-tracks.md; robustness: each method's success "
        "under the robustness suite's perturbations against its main id on the same scenes, paired (exact McNemar, "
        "Holm over the table) (default II)",
    )  # fmt: skip
    p_table.add_argument("--format", default="md", choices=["md", "latex"], help="Markdown or LaTeX (default md)")
    p_table.add_argument("--no-ci", action="store_true", help="success rates without Wilson intervals")
    p_table.add_argument(
        "--seeds", default="separate", choices=["separate", "mean"],
        help="rows <config>-seed<k> (a sweep's training seeds): a row each, or one row per config with the seeds' "
        "mean success rate and its range over the seeds (default separate)",
    )  # fmt: skip
    p_table.add_argument("--out", default=None, help="write to this file instead of stdout")
    p_table.add_argument(
        "--csv", default=None, metavar="FILE",
        help="--table robustness: also write every number as CSV (counts, Wilson intervals, change, McNemar, Holm p)",
    )  # fmt: skip
    p_table.add_argument(
        "--figure", default=None, nargs="+", metavar="FILE",
        help="--table robustness: also draw its figure into each FILE (.png, .pdf or .svg), e.g. --figure f.pdf f.png",
    )  # fmt: skip

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
    p_plot.add_argument(
        "--format", default=["png"], nargs="+", choices=("png", "pdf", "svg"),
        help="file format(s): each figure is written once per format, e.g. --format png pdf (default png)",
    )  # fmt: skip
    p_plot.add_argument(
        "--leaderboard", default=None, metavar="DIR",
        help="also plot the learned methods of this leaderboard (e.g. results/leaderboard) that are verified: each "
        "entry's own-track public-seed cells; their records must be of the results' env version",
    )  # fmt: skip
    p_plot.add_argument("--dpi", type=int, default=300, help="resolution of PNGs in dots per inch (default 300)")
    p_curves = sub.add_parser(
        "curves", help="training curves (the paper's Fig. 5) from `racebench train` run directories"
    )
    p_curves.add_argument("runs", nargs="+", help="run directories or their progress.csv files")
    p_curves.add_argument(
        "--out",
        default=None,
        nargs="+",
        help="output file(s), .png, .pdf or .svg, e.g. --out f.png f.pdf (default runs/figures/training_curves.png, "
        "or success_curves.png)",
    )
    p_curves.add_argument(
        "--label", action="append", default=None, metavar="LABEL",
        help="with --success: RUN=NAME names a run (as given) in the legend, e.g. by its leaderboard method",
    )  # fmt: skip
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
    p_train.add_argument(
        "--track", default=None, choices=["S", "J", "Circle", "Random"],
        help="track to train on (default: the config's own, else S); Random: a new generated track each episode",
    )  # fmt: skip
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

    p_trust = sub.add_parser(
        "trust", help="vouch, on this machine, for the checkpoints a reviewed run folder's written.json lists"
    )
    p_trust.add_argument(
        "folders", nargs="+", metavar="RUN_DIR",
        help="run folders (e.g. a campaign run restored from the repository) whose listed files you have reviewed",
    )  # fmt: skip

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
        help="resume and evaluate checkpoints that this machine did not write itself (e.g. runs begun before "
        "written.json existed, or restored from another machine): they are unpickled, which can run code",
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
    p_onnx.add_argument(
        "--check-env", default=None, metavar="ID",
        help="then fly the checkpoint on ID's first public seed and compare the ONNX actions step by step "
        "(an error, and no file, above 1e-4)",
    )  # fmt: skip
    p_onnx.add_argument("--check-steps", type=int, default=60, help="steps compared by --check-env (default 60)")
    _add_vecnormalize_options(p_onnx)

    p_export = sub.add_parser(
        "export-policy", help="write an SB3 checkpoint without its optimizer state (a policy-only .zip to commit)"
    )
    p_export.add_argument("checkpoint", help="SB3 / sb3-contrib .zip")
    p_export.add_argument("--out", required=True, help="the policy-only .zip to write")
    p_export.add_argument("--trust-code", action="store_true", help="allow a checkpoint outside the shipped ones")
    p_export.add_argument(
        "--keep-critic", action="store_true",
        help="keep the critic's own weights (default: zeros; no action reads them; training cannot resume from it)",
    )  # fmt: skip
    _add_vecnormalize_options(p_export)

    p_bench = sub.add_parser("bench", help="throughput: depth frames/s of both renderers, env steps/s, memory")
    p_bench.add_argument("--quick", action="store_true", help="smoke test of ~10 s (tiny sizes)")
    p_bench.add_argument("--out", default="bench.csv", help="CSV of every measurement (default bench.csv)")
    p_bench.add_argument("--track", default="S", choices=["S", "J", "Circle"], help="track of every env (default S)")
    p_bench.add_argument("--num-envs", type=int, default=None, help="envs of each vector-env run (default 32)")

    from racebench.leaderboard.command import add_parser as add_leaderboard_parser

    add_leaderboard_parser(sub)
    describe_commands(parser)
    return parser


def parser_of(
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
