"""Job (issue 72, item 3): evaluate every leaderboard method on the robustness suite, 50 episodes per id, into the
record folders the leaderboard and ``racebench table --table robustness`` read.

For each entry of ``results/leaderboard`` (the verified and self-reported methods and the built-ins
``planner-fast``, ``follow`` and ``hover``; ``planner`` is skipped, as issue 72 lists it not) and each of its
policy lines: the policy the entry's public records were flown with (``policy``: the committed checkpoint, or
``builtin:<name>``) on its track's suite ``robustness-<track>`` (a policy for all tracks: ``robustness``), into the
first of its ``records`` folders (``baselines/checkpoints/<x>/eval``, ``results/<builtin>``), under the label its
records there already carry. The main id's first 50 episodes are there already, so only the 10 perturbation ids per
track are flown: 16,200 episodes for the 12 methods of today. Each evaluation resumes (records already there are
kept), so a killed run is continued by running the same command again. Run it from a clean clone: a record says
whether the code that flew it was committed, and the leaderboard refuses new entries' records that were not.

Usage::

    python scripts/evaluate_robustness.py                         # everything, --workers 2
    python scripts/evaluate_robustness.py --only vision-ppo hover --tracks S
    python scripts/evaluate_robustness.py --dry-run               # print the commands only
    python scripts/evaluate_robustness.py --only hover --tracks S --episodes 1 --out /tmp/try --allow-dirty

then regenerate the table, its CSV, the figure and the site (the commands are printed at the end; results/README.md).
"""

from __future__ import annotations

import argparse
import os
import shlex
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # this checkout's racebench, not an installed one
from racebench.evaluation.protocol import TRACK_ORDER  # noqa: E402
from racebench.evaluation.records import git_state, has_records, read_folder  # noqa: E402
from racebench.leaderboard.entries import ALL_TRACKS, DEFAULT_LEADERBOARD, ENTRY_FILE, validate_meta  # noqa: E402

SKIPPED = ("planner",)  # the slow privileged planner: planner-fast is the suite's privileged reference
EPISODES = 50
WORKERS = 2


@dataclass(frozen=True)
class Job:
    """One ``racebench evaluate`` of one entry's policy on one suite."""

    entry: str
    policy: str  # the agent spec: a built-in's name or the policy file, relative to the repository root
    suites: tuple[str, ...]
    out: str  # the records folder, relative to the output root
    label: str | None  # the label its records carry (None: the evaluator's default)

    def command(self, out_root: Path, episodes: int, workers: int, trust_code: bool) -> list[str]:
        """The ``racebench evaluate`` command line of this job, writing under ``out_root``."""
        words = ["evaluate", "--agent", self.policy, "--envs", *self.suites, "--episodes", str(episodes),
                 "--workers", str(workers), "--out", str(out_root / self.out)]  # fmt: skip
        return words + (["--name", self.label] if self.label else []) + (["--trust-code"] if trust_code else [])


def existing_label(folder: Path) -> str | None:
    """The label the records of ``folder`` carry (an evaluation into it must use the same), None without records."""
    if not has_records(folder):
        return None
    records = read_folder(folder).sorted_records()
    return str(records[0]["agent"]) if records else None


def plan(leaderboard: Path, only: list[str] | None = None, tracks: list[str] | None = None,
         skip: tuple[str, ...] = SKIPPED) -> list[Job]:  # fmt: skip
    """The evaluations of every entry under ``leaderboard`` but ``skip`` (or the ``only`` ones), on ``tracks``."""
    root = leaderboard.resolve().parents[1]
    folders = sorted(p.parent for p in leaderboard.glob(f"*/{ENTRY_FILE}"))
    names = [f.name for f in folders]
    unknown = sorted(set(only or []) - set(names))
    if unknown:
        raise SystemExit(f"evaluate_robustness: no entry named {unknown} in {leaderboard} (entries: {names})")
    wanted = set(tracks or TRACK_ORDER)
    jobs = []
    for folder in folders:
        if (only and folder.name not in only) or (not only and folder.name in skip):
            continue
        meta = validate_meta(yaml.safe_load((folder / ENTRY_FILE).read_text()), root, str(folder / ENTRY_FILE))
        for key, line in meta["policies"].items():
            flown = [t for t in TRACK_ORDER if t in wanted and key in (t, ALL_TRACKS)]
            if not flown:
                continue
            suites = ("robustness",) if len(flown) == len(TRACK_ORDER) else tuple(f"robustness-{t}" for t in flown)
            policy = line["policy"].removeprefix("builtin:")
            out = line["records"][0]
            jobs.append(Job(meta["name"], policy, suites, out, existing_label(root / out)))
    return jobs


def main(argv: list[str] | None = None) -> int:
    """Run (or print) every evaluation, then print the commands that regenerate the table, figure and site."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--leaderboard", default=str(ROOT / DEFAULT_LEADERBOARD), help="the entries' folder")
    parser.add_argument("--only", nargs="+", default=None, metavar="ENTRY", help="these entries only")
    parser.add_argument("--tracks", nargs="+", default=None, choices=TRACK_ORDER, help="these tracks only")
    parser.add_argument("--episodes", type=int, default=EPISODES, help=f"episodes per id (default {EPISODES})")
    parser.add_argument("--workers", type=int, default=WORKERS, help=f"worker processes (default {WORKERS})")
    parser.add_argument("--out", default=str(ROOT), help="root the record folders are written under (default: here)")
    parser.add_argument("--trust-code", action="store_true", help="pass --trust-code (a Python-class policy)")
    parser.add_argument("--allow-dirty", action="store_true", help="run from a checkout with uncommitted code")
    parser.add_argument("--dry-run", action="store_true", help="print the commands, run nothing")
    args = parser.parse_args(argv)
    jobs = plan(Path(args.leaderboard), args.only, args.tracks)
    commit, dirty = git_state()
    if dirty and not args.allow_dirty and not args.dry_run:
        raise SystemExit(
            f"evaluate_robustness: racebench/ of {ROOT} (commit {commit}) has uncommitted changes: "
            "its records would say git_dirty; run from a clean clone (--allow-dirty: a trial)"
        )
    paths = [str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(paths)}  # the evaluations run this checkout's racebench
    out_root = Path(args.out).resolve()
    for i, job in enumerate(jobs, start=1):
        words = job.command(out_root, args.episodes, args.workers, args.trust_code)
        print(f"[{i}/{len(jobs)}] {job.entry}: racebench {shlex.join(words)}", flush=True)
        if not args.dry_run:
            subprocess.run([sys.executable, "-m", "racebench.cli", *words], cwd=ROOT, env=env, check=True)
    folders = sorted({job.out for job in plan(Path(args.leaderboard))})
    print("\nthen, from the repository root:\n"
          f"racebench table {' '.join(folders)} --table robustness --out results/robustness.md "
          "--csv results/robustness.csv --figure results/figures/robustness.pdf results/figures/robustness.png\n"
          "racebench leaderboard build --out results/leaderboard/site")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
