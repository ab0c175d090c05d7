"""Job: keep the resume state of campaign runs that span sessions on one git ref outside ``main``'s history.

A 4 M-step campaign run takes longer than a session on 2 cores, so a new machine must be able to resume it. Its
resume state (the newest periodic checkpoint with its Adam moments, about 15 MB, and the run folder's small files)
committed to ``main`` would stay in ``main``'s history for good: ~15 MB for every session that ends mid-run, some
360 MB over the campaign (``baselines/experiments/campaign-4m/README.md``). Here it goes to a parentless commit on
one ref (default ``refs/heads/campaign-resume``) that each ``save`` replaces, so the repository holds one resume
state at a time (the replaced one becomes unreachable and ``git gc`` drops it) and ``main`` none.

Usage (run from the root of the campaign's clone; ``--repo`` is the repository that carries the ref)::

    python scripts/campaign_state.py save --repo /work/main baselines/experiments/campaign-4m/<run>
    python scripts/campaign_state.py restore --repo /work/main          # into this clone, before resuming
    python scripts/campaign_state.py show --repo /work/main

``save`` stores, per run folder, ``config.yaml``, ``curriculum.json``, ``progress.csv``, ``written.json``,
``validation_curve.csv`` (those that exist) and the newest ``checkpoints/<prefix>_<n>_steps.zip`` with its
``<prefix>_vecnormalize_<n>_steps.pkl``: what ``racebench sweep`` needs to resume the run (``written.json`` keeps the
checkpoint trusted: its bytes are unchanged). Fly the validation curve first (``racebench.reporting.paper.
validation_curve``): only the newest checkpoint travels. ``restore`` writes the files back at the same paths and
refuses to overwrite a file whose content differs.
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path

DEFAULT_REF = "refs/heads/campaign-resume"
SMALL_FILES = ("config.yaml", "curriculum.json", "progress.csv", "written.json", "validation_curve.csv")
_CHECKPOINT = re.compile(r"^(?P<prefix>.+)_(?P<steps>\d+)_steps\.zip$")


def git(repo: Path, *args: str, env: dict[str, str] | None = None, data: bytes | None = None) -> bytes:
    """Run ``git -C repo args`` and return its stdout; a failure raises with git's message."""
    done = subprocess.run(["git", "-C", str(repo), *args], input=data, capture_output=True,
                          env={**os.environ, **(env or {})})  # fmt: skip
    if done.returncode != 0:
        raise RuntimeError(f"git {' '.join(args[:2])}: {done.stderr.decode().strip()}")
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


def save(repo: Path, root: Path, run_dirs: list[Path], ref: str = DEFAULT_REF, message: str = "") -> str:
    """Store the resume state of ``run_dirs`` (paths under ``root``) as one parentless commit on ``ref``."""
    files = [path for run_dir in run_dirs for path in resume_files(run_dir)]
    with tempfile.TemporaryDirectory() as tmp:
        index = {"GIT_INDEX_FILE": str(Path(tmp) / "index")}
        for path in files:
            relative = path.resolve().relative_to(root.resolve()).as_posix()
            blob = git(repo, "hash-object", "-w", "--no-filters", str(path.resolve())).decode().strip()
            git(repo, "update-index", "--add", "--cacheinfo", f"100644,{blob},{relative}", env=index)
        tree = git(repo, "write-tree", env=index).decode().strip()
    text = message or "campaign resume state: " + ", ".join(run_dir.name for run_dir in run_dirs)
    commit = git(repo, "commit-tree", tree, "-m", text).decode().strip()  # no parent: one state at a time
    git(repo, "update-ref", ref, commit)
    return commit


def listing(repo: Path, ref: str = DEFAULT_REF) -> list[tuple[str, str, int]]:
    """(path, blob sha, size in bytes) of every file of the state on ``ref``."""
    rows = []
    for line in git(repo, "ls-tree", "-r", "-l", ref).decode().splitlines():
        meta, path = line.split("\t", 1)
        _mode, _kind, blob, size = meta.split()
        rows.append((path, blob, int(size)))
    return rows


def restore(repo: Path, root: Path, ref: str = DEFAULT_REF) -> list[Path]:
    """Write the state on ``ref`` under ``root``; a file already there must have the same content."""
    blobs = [(root / path, blob) for path, blob, _size in listing(repo, ref)]
    for target, blob in blobs:  # check everything before writing anything
        if target.exists() and target.read_bytes() != git(repo, "cat-file", "blob", blob):
            raise ValueError(f"{target}: exists with other content; move it away to restore {ref}")
    for target, blob in blobs:
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_bytes(git(repo, "cat-file", "blob", blob))
    return [target for target, _blob in blobs]


def main(argv: list[str] | None = None) -> int:
    """Command line: save, restore or show the campaign's resume state."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("action", choices=["save", "restore", "show"])
    parser.add_argument("run_dirs", nargs="*", type=Path, help="save: the run folders to store")
    parser.add_argument("--repo", type=Path, default=Path("."), help="the repository that carries the ref")
    parser.add_argument("--root", type=Path, default=Path("."), help="paths are stored relative to this folder")
    parser.add_argument("--ref", default=DEFAULT_REF)
    args = parser.parse_intermixed_args(argv)
    try:
        if args.action == "save":
            if not args.run_dirs:
                raise ValueError("save: name at least one run folder")
            commit = save(args.repo, args.root, args.run_dirs, args.ref)
            print(f"{args.ref} = {commit[:12]} (parentless; the state it replaces is no longer reachable)")
        elif args.action == "restore":
            for path in restore(args.repo, args.root, args.ref):
                print(f"restored {path}")
        rows = listing(args.repo, args.ref)
        for path, _blob, size in rows:
            print(f"{size / 1e6:9.2f} MB  {path}")
        print(f"{sum(size for *_rest, size in rows) / 1e6:9.2f} MB in {len(rows)} files on {args.ref}")
    except (ValueError, RuntimeError) as error:
        print(f"campaign_state: {error}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
