"""Job: carry a campaign run that spans sessions to the next machine, through ``main`` itself.

A 4 M-step campaign run can take longer than what is left of a session on 2 cores, so a new machine must be able to
resume it. Only ``main`` reaches a new machine: a state kept on a ref of its own (``refs/heads/campaign-resume``,
this script's first design) was gone on 2026-12-06, and with it 0.46 M steps of run 8. So ``save`` stages the resume
state in the main checkout, at the run folder's own path, for the session's last commit; ``main`` carries at most one
state at a time (a new ``save`` unstages every other run's checkpoint, and ``scripts/campaign_finish.py`` replaces
the run folder when the run ends), but git history keeps each committed one, about 15 MB: start a run only when it
can finish within the session where possible, and save only when it cannot.

Usage (``--root`` is the campaign clone; ``--repo`` the main checkout that commits the state)::

    RUN=baselines/experiments/campaign-2/<run>     # or campaign-4m/<run>: any baselines/experiments/campaign-*
    python scripts/campaign_state.py save --repo /work/main --root /work/campaign /work/campaign/$RUN
    git -C /work/main commit -m "campaign: run ... stopped at ... steps, resume state in main"
    python scripts/campaign_state.py restore --repo /work/main --root /work/campaign   # on a new machine
    racebench trust /work/campaign/$RUN   # on the new machine, after reviewing the restored state
    python scripts/campaign_state.py show --repo /work/main

``save`` stores, per run folder, ``config.yaml``, ``curriculum.json``, ``progress.csv``, ``written.json``,
``validation_curve.csv`` (those that exist) and the newest ``checkpoints/<prefix>_<n>_steps.zip`` with its
``<prefix>_vecnormalize_<n>_steps.pkl``: what ``racebench sweep`` needs to resume the run (``written.json`` lists the
checkpoint; on a new machine ``racebench trust RUN_DIR`` adopts that list after review, as a folder's own list
vouches only for files the machine wrote). Fly the validation curve first (``racebench.reporting.validation.
validation_curve``): only the newest checkpoint travels. ``restore`` copies the committed state into the clone at the
same paths and refuses to overwrite a file whose content differs.
"""

from __future__ import annotations

import argparse
import re
import shutil
import subprocess
import sys
from pathlib import Path

CAMPAIGNS = "baselines/experiments/campaign-*"  # campaign-4m (campaign 1), campaign-2, ...
SMALL_FILES = ("config.yaml", "curriculum.json", "progress.csv", "written.json", "validation_curve.csv")
_CHECKPOINT = re.compile(r"^(?P<prefix>.+)_(?P<steps>\d+)_steps\.zip$")


def git(repo: Path, *args: str) -> str:
    """Run ``git -C repo args`` and return its stdout; a failure raises with git's message."""
    done = subprocess.run(["git", "-C", str(repo), *args], capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"git {' '.join(args[:2])}: {done.stderr.strip()}")
    return done.stdout


def resume_files(run_dir: Path) -> list[Path]:
    """The files a run folder needs to be resumed: its small files and its newest checkpoint with its statistics."""
    if not run_dir.is_dir():
        raise ValueError(f"{run_dir}: not a folder")
    newest: tuple[int, Path] | None = None
    for path in (run_dir / "checkpoints").glob("*_steps.zip"):
        match = _CHECKPOINT.match(path.name)
        if match and (newest is None or int(match["steps"]) > newest[0]):
            newest = (int(match["steps"]), path)
    if newest is None:
        raise ValueError(f"{run_dir}: no periodic checkpoint under checkpoints/ to resume from")
    steps, checkpoint = newest
    prefix = _CHECKPOINT.match(checkpoint.name)["prefix"]
    statistics = checkpoint.with_name(f"{prefix}_vecnormalize_{steps}_steps.pkl")
    files = [run_dir / name for name in SMALL_FILES if (run_dir / name).is_file()] + [checkpoint]
    return files + [statistics] if statistics.is_file() else files


def tracked_state(repo: Path) -> list[str]:
    """Paths (relative to ``repo``) of the resume checkpoints ``repo``'s index holds: the state ``main`` carries."""
    listed = git(repo, "ls-files", "--", f"{CAMPAIGNS}/*/checkpoints/*").splitlines()
    return sorted(path for path in listed if (repo / path).is_file())


def state_files(repo: Path) -> list[str]:
    """The state ``main`` carries: each run folder with a committed checkpoint, its checkpoints and small files."""
    checkpoints = tracked_state(repo)
    runs = sorted({str(Path(path).parent.parent.as_posix()) for path in checkpoints})
    small = [f"{run}/{name}" for run in runs for name in SMALL_FILES if (repo / run / name).is_file()]
    return sorted(small + checkpoints)


def save(repo: Path, root: Path, run_dirs: list[Path]) -> list[str]:
    """Copy the resume state of ``run_dirs`` (paths under ``root``) into ``repo`` and stage it; unstage any other."""
    files = [path for run_dir in run_dirs for path in resume_files(run_dir)]
    relative = [path.resolve().relative_to(root.resolve()).as_posix() for path in files]
    for path in tracked_state(repo):  # one state at a time: older checkpoints of these runs and other runs' go
        if path not in relative:
            git(repo, "rm", "-q", "--cached", "--", path)
            (repo / path).unlink()
    for source, path in zip(files, relative, strict=True):
        (repo / path).parent.mkdir(parents=True, exist_ok=True)
        if source.resolve() != (repo / path).resolve():
            shutil.copy2(source, repo / path)
    git(repo, "add", "-f", "--", *relative)  # checkpoints/ is ignored: a resume state is added on purpose
    return relative


def restore(repo: Path, root: Path) -> list[Path]:
    """Copy the state ``repo`` carries into ``root``; a file already there must have the same content."""
    pairs = [(repo / path, root / path) for path in state_files(repo)]
    if not pairs:
        raise ValueError(f"{repo}: carries no resume state (no file under {CAMPAIGNS}/*/checkpoints/ is tracked)")
    for source, target in pairs:  # check everything before writing anything
        if target.exists() and target.read_bytes() != source.read_bytes():
            raise ValueError(f"{target}: exists with other content; move it away to restore the state")
    for source, target in pairs:
        target.parent.mkdir(parents=True, exist_ok=True)
        if source.resolve() != target.resolve():
            shutil.copy2(source, target)
    return [target for _source, target in pairs]


def main(argv: list[str] | None = None) -> int:
    """Command line: save, restore or show the campaign's resume state."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("action", choices=["save", "restore", "show"])
    parser.add_argument("run_dirs", nargs="*", type=Path, help="save: the run folders to store")
    parser.add_argument("--repo", type=Path, default=Path("."), help="the main checkout that carries the state")
    parser.add_argument("--root", type=Path, default=Path("."), help="the campaign clone (paths are relative to it)")
    args = parser.parse_intermixed_args(argv)
    try:
        if args.action == "save":
            if not args.run_dirs:
                raise ValueError("save: name at least one run folder")
            save(args.repo, args.root, args.run_dirs)
            print(f"staged in {args.repo}; commit it there so that a new machine can resume")
        elif args.action == "restore":
            for path in restore(args.repo, args.root):
                print(f"restored {path}")
        rows = [(path, (args.repo / path).stat().st_size) for path in state_files(args.repo)]
        for path, size in rows:
            print(f"{size / 1e6:9.2f} MB  {path}")
        print(f"{sum(size for _path, size in rows) / 1e6:9.2f} MB in {len(rows)} files carried by {args.repo}")
    except (ValueError, RuntimeError) as error:
        print(f"campaign_state: {error}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
