"""``racebench leaderboard add | verify | build``: the command-line side of :mod:`racebench.leaderboard`."""

from __future__ import annotations

import argparse
from pathlib import Path

DEFAULT_LEADERBOARD = "results/leaderboard"


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register ``racebench leaderboard`` and its sub-commands on the top-level sub-parser set."""
    p_lb = sub.add_parser("leaderboard", help="leaderboard entries: add one, verify them, build the static site")
    lb = p_lb.add_subparsers(dest="leaderboard_command", required=True)

    p_add = lb.add_parser("add", help="create results/leaderboard/<name>/entry.yaml for a policy in the repository")
    p_add.add_argument("--policy", required=True, help="policy file in the repository (.onnx, .zip, file.py:Class) "
                       "or a built-in agent (planner, follow, hover, random)")  # fmt: skip
    p_add.add_argument("--meta", required=True, help="YAML with name, authors, method, link, obs_mode, training_*, "
                       "hardware (see results/leaderboard/README.md)")  # fmt: skip
    p_add.add_argument("--records", nargs="*", default=[], help="result folders already holding its records")
    p_add.add_argument(
        "--evaluate",
        type=int,
        default=None,
        metavar="EPISODES",
        help="first evaluate on the main suite's public seeds, EPISODES per id (default: 50 without --records, else 0)",
    )
    p_add.add_argument("--workers", type=int, default=1, help="evaluation processes for --evaluate (default 1)")
    p_add.add_argument("--trust-code", action="store_true", help="allow a .zip or Python policy (runs its code)")
    p_add.add_argument("--leaderboard", default=DEFAULT_LEADERBOARD, help=f"(default {DEFAULT_LEADERBOARD})")

    p_ver = lb.add_parser("verify", help="re-evaluate entries; test each committed success count and lap time")
    p_ver.add_argument("--entry", nargs="*", default=None, help="entry names (default: every entry)")
    p_ver.add_argument("--episodes", type=int, default=None, help="replay only the first N seeds of each cell")
    p_ver.add_argument("--out", default="runs/verify", help="where the replays go (default runs/verify; resumable)")
    p_ver.add_argument("--fresh", action="store_true", help="discard earlier replays of these entries first")
    p_ver.add_argument("--workers", type=int, default=1, help="evaluation processes (default 1)")
    p_ver.add_argument("--trust-code", action="store_true", help="allow .zip / Python entries outside the shipped ones")
    p_ver.add_argument("--leaderboard", default=DEFAULT_LEADERBOARD, help=f"(default {DEFAULT_LEADERBOARD})")

    p_build = lb.add_parser("build", help="write the static site (plain HTML/CSS, data embedded)")
    p_build.add_argument("--out", required=True, help="output folder of the site")
    p_build.add_argument("--leaderboard", default=DEFAULT_LEADERBOARD, help=f"(default {DEFAULT_LEADERBOARD})")
    p_build.add_argument(
        "--videos",
        action="store_true",
        help="also fly one episode per main id of every entry and show its video (not committed)",
    )
    p_build.add_argument("--trust-code", action="store_true",
                         help="with --videos: allow entries whose policy runs code (.zip, Python)")  # fmt: skip


def run(args: argparse.Namespace) -> int:
    """Run the parsed ``racebench leaderboard`` command; bad input is a one-line :class:`SystemExit`."""
    import yaml

    from racebench.agents import AgentLoadError
    from racebench.leaderboard.entries import EntryError, add_entry, load_config, load_entries

    command = f"racebench leaderboard {args.leaderboard_command}"
    try:
        if args.leaderboard_command == "add":
            try:
                meta = yaml.safe_load(Path(args.meta).read_text())
            except (OSError, yaml.YAMLError) as exc:
                raise EntryError(f"--meta {args.meta!r}: unreadable ({exc})") from exc
            episodes = args.evaluate if args.evaluate is not None else (0 if args.records else 50)
            entry = add_entry(
                args.leaderboard, args.policy, meta, args.records, evaluate_episodes=episodes,
                trust_code=args.trust_code, workers=args.workers,
            )  # fmt: skip
            tier = entry.tier(load_config(args.leaderboard)["private_salt_sha256"])
            print(f"wrote {entry.folder / 'entry.yaml'} ({len(entry.records)} records, tier: {tier})")
        elif args.leaderboard_command == "verify":
            from racebench.leaderboard.verify import verify_entry

            checks = []
            for entry in load_entries(args.leaderboard, args.entry):
                for check in verify_entry(
                    entry, args.out, episodes=args.episodes, trust_code=args.trust_code, workers=args.workers,
                    fresh=args.fresh,
                ):  # fmt: skip
                    print(check.line(), flush=True)
                    checks.append(check)
            failed = [c for c in checks if not c.ok]
            if failed:
                raise SystemExit(f"{command}: {len(failed)} of {len(checks)} cells failed")
            print(f"{len(checks)} cells verified (Fisher exact, α = 0.001 each; lap times within 0.2 s + 4 SE)")
        elif args.leaderboard_command == "build":
            from racebench.leaderboard.site import build_site

            index = build_site(args.leaderboard, args.out, videos=args.videos, trust_code=args.trust_code)
            print(f"wrote {index}")
    except (EntryError, AgentLoadError, ValueError, OSError) as exc:
        raise SystemExit(f"{command}: {exc}") from exc
    return 0
