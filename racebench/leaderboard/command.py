"""``racebench leaderboard add | verify | sign | build``: the command-line side of :mod:`racebench.leaderboard`."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

DEFAULT_LEADERBOARD = "results/leaderboard"


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register ``racebench leaderboard`` and its sub-commands on the top-level sub-parser set."""
    p_lb = sub.add_parser("leaderboard", help="leaderboard entries: add one, verify them, build the static site")
    lb = p_lb.add_subparsers(dest="leaderboard_command", required=True)

    p_add = lb.add_parser("add", help="create results/leaderboard/<name>/entry.yaml for a method's policies")
    from racebench.agents.base import BUILTIN_AGENTS  # light: the built-ins' registry, for the help

    p_add.add_argument("--policy", required=True, action="append", metavar="[TRACK=]POLICY",
                       help="policy file in the repository (.onnx, .zip, file.py:Class) or a built-in agent "
                       f"({', '.join(BUILTIN_AGENTS)}); TRACK=POLICY (S, Circle, J) once per track for per-track "
                       "policies, bare for one policy on every track")  # fmt: skip
    p_add.add_argument("--meta", required=True, help="YAML with name, description, authors, obs_mode, teacher, "
                       "config, command, hardware, training_seeds (see docs/leaderboard.md)")  # fmt: skip
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

    p_ver = lb.add_parser(
        "verify",
        help="re-evaluate entries; test each committed success count and lap time "
        "(a deterministic built-in: each episode)",
    )
    p_ver.add_argument("--entry", nargs="*", default=None, help="entry names (default: every entry)")
    p_ver.add_argument("--episodes", type=int, default=None, help="replay only the first N seeds of each cell")
    p_ver.add_argument("--out", default="runs/verify", help="where the replays go (default runs/verify; resumable)")
    p_ver.add_argument("--fresh", action="store_true", help="discard earlier replays of these entries first")
    p_ver.add_argument("--workers", type=int, default=1, help="evaluation processes (default 1)")
    p_ver.add_argument("--trust-code", action="store_true", help="allow .zip / Python entries outside the shipped ones")
    p_ver.add_argument("--leaderboard", default=DEFAULT_LEADERBOARD, help=f"(default {DEFAULT_LEADERBOARD})")

    p_sign = lb.add_parser(
        "sign",
        help="maintainers: fly an entry's ONNX policies on the private seeds ($RACEBENCH_PRIVATE_SALT) and write "
        "its signed verified.json",
    )
    p_sign.add_argument("--entry", required=True, help="entry name")
    p_sign.add_argument("--key", required=True, help="the maintainers' Ed25519 private key (PKCS#8 PEM)")
    p_sign.add_argument(
        "--private-records",
        required=True,
        metavar="DIR",
        help="folder OUTSIDE the repository for the private records (resumable: <DIR>/<entry>-<track>)",
    )
    p_sign.add_argument(
        "--unseen", action="store_true",
        help="sign the entry's unseen: line instead (its ONNX file on RaceObs-Unseen-v0's private seeds, each a track "
        "of its own) into verified-unseen.json",
    )  # fmt: skip
    p_sign.add_argument("--episodes", type=int, default=None,
                        help="private episodes per own main id (default 50; with --unseen 100)")  # fmt: skip
    p_sign.add_argument("--workers", type=int, default=1, help="evaluation processes (default 1)")
    p_sign.add_argument("--leaderboard", default=DEFAULT_LEADERBOARD, help=f"(default {DEFAULT_LEADERBOARD})")

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

    from racebench.agents.base import AgentLoadError
    from racebench.evaluation.seeds import SeedSetError
    from racebench.leaderboard.entries import EntryError, load_config, load_entries
    from racebench.leaderboard.signing import SignatureError
    from racebench.utils.yamlfile import yaml_problem

    command = f"racebench leaderboard {args.leaderboard_command}"
    try:
        if args.leaderboard_command == "add":
            try:
                meta = yaml.safe_load(Path(args.meta).read_text())
            except (OSError, yaml.YAMLError) as exc:
                why = yaml_problem(exc) if isinstance(exc, yaml.YAMLError) else exc
                raise EntryError(f"--meta {args.meta!r}: unreadable ({why})") from exc
            episodes = args.evaluate if args.evaluate is not None else (0 if args.records else 50)
            policies = _policy_arguments(args.policy)
            from racebench.leaderboard.submit import add_entry

            entry = add_entry(
                args.leaderboard, policies, meta, args.records, evaluate_episodes=episodes,
                trust_code=args.trust_code, workers=args.workers, progress=not args.quiet,
            )  # fmt: skip
            for line in _result_lines(entry):
                print(line)
            print(f"wrote {entry.folder / 'entry.yaml'} ({len(entry.records)} records, tier: self-reported until "
                  "the maintainers sign a verification)")  # fmt: skip
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
            print(f"{len(checks)} cells verified (Fisher exact, α = 0.001 each; lap times within 0.2 s + 4 SE; "
                  "deterministic built-ins episode by episode)")  # fmt: skip
        elif args.leaderboard_command == "sign":
            from racebench.evaluation.seeds import salt_from_env
            from racebench.leaderboard.signing import check_verified, sign_entry

            if args.episodes is not None and args.episodes < 1:
                raise EntryError(f"--episodes must be >= 1, got {args.episodes}")
            (entry,) = load_entries(args.leaderboard, [args.entry])
            salt = salt_from_env()
            if args.unseen:
                from racebench.leaderboard.unseen_signing import (
                    UNSEEN_PRIVATE_EPISODES,
                    check_unseen_verified,
                    sign_unseen,
                )

                episodes = args.episodes or UNSEEN_PRIVATE_EPISODES
                path = sign_unseen(entry, salt, args.key, args.private_records, episodes, args.workers)
                cell = check_unseen_verified(entry, load_config(args.leaderboard))  # what the site will accept
                print(f"{entry.name} {cell.env_id} [private]: {cell.successes}/{cell.n}, mean lap "
                      f"{cell.lap_time_mean:.2f} s")  # fmt: skip
                print(f"wrote {path} (signed; checks against the pinned maintainers' key)")
                return 0
            path = sign_entry(entry, salt, args.key, args.private_records, args.episodes or 50, args.workers)
            result = check_verified(entry, load_config(args.leaderboard))  # what the site will accept
            for env_id, cell in result.cells.items():
                print(
                    f"{entry.name} {env_id} [private]: {cell.successes}/{cell.n}, mean lap {cell.lap_time_mean:.2f} s"
                )
            print(f"wrote {path} (signed; checks against the pinned maintainers' key)")
        elif args.leaderboard_command == "build":
            from racebench.leaderboard.site import build_site

            index = build_site(args.leaderboard, args.out, videos=args.videos, trust_code=args.trust_code)
            print(f"wrote {index}")
    except (EntryError, SignatureError, SeedSetError, AgentLoadError, ValueError, OSError) as exc:
        raise SystemExit(f"{command}: {exc}") from exc
    return 0


def _result_lines(entry: Any) -> list[str]:
    """One line per policy and env id: successes, success rate with its 95 % interval, mean lap time."""
    from racebench.leaderboard.entries import summarize_cells

    lines = []
    for track, policy in entry.policies.items():
        for seed_set in ("public", "private"):
            cells = summarize_cells([r for r in policy.records if r["seed_set"] == seed_set])
            for env_id, cell in cells.items():
                low, high = cell.interval
                lap = f"{cell.lap_time_mean:.2f} s" if cell.lap_times else "– (no successful lap)"
                lines.append(
                    f"{entry.name} {track} {env_id} [{seed_set}]: {cell.successes}/{cell.n} successes "
                    f"({cell.success_rate:.0%}, 95 % CI {low:.0%}–{high:.0%}), mean lap {lap}"
                )
    return lines


def _policy_arguments(values: list[str]) -> str | dict[str, str]:
    """``--policy`` values: one bare policy (every track) or ``TRACK=POLICY`` once per track."""
    from racebench.leaderboard.entries import EntryError

    if len(values) == 1 and "=" not in values[0]:
        return values[0]
    policies: dict[str, str] = {}
    for value in values:
        track, eq, policy = value.partition("=")
        if not eq or not policy:
            raise EntryError(f"--policy {value!r}: with several policies each is TRACK=POLICY (S, Circle, J)")
        if track in policies:
            raise EntryError(f"--policy: track {track!r} given twice")
        policies[track] = policy
    return policies
