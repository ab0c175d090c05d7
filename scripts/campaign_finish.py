"""Job: bring a finished campaign run from the campaign clone into this repository, as issue 48 asks.

Usage (from the root of the main checkout, after ``racebench sweep baselines/sweeps/campaign-4m.yaml`` finished the
run in the campaign clone)::

    python scripts/campaign_finish.py /work/campaign/baselines/experiments/campaign-4m/<run> \\
        --trained-by "racebench sweep baselines/sweeps/campaign-4m.yaml --max-runs 1 (pinned commits ...)" \\
        --note "three sessions on 2 cores shared with other work; ... s paused while the test suite ran"
    racebench paper-tables

It copies the run's small files, ``eval/`` and (seed 0) ``policy/`` to ``baselines/experiments/<campaign>/<run>/`` (the
campaign folder the run is in: ``campaign-4m`` or ``campaign-2``)
(never ``checkpoints/`` or ``tb/``: a resume state committed there by ``scripts/campaign_state.py`` goes). For a
seed-0 run it also writes ``baselines/checkpoints/<config>-<track>/``: the policy-only checkpoint, its evaluation,
``progress.csv``, ``config.yaml``, ``curriculum.json`` and a ``summary.json`` for the whole run (wall clock over all
its sessions from ``progress.csv``, steps at the final level, final training success), and adds the checkpoint's
sha256 to ``TRUSTED_CHECKPOINTS`` in ``racebench/agents/trust.py``. A run without ``summary.json`` or an evaluation
is refused: it has not finished. A checkpoint folder that already holds another trusted policy (the committed
``state-ppo-S`` and ``vision-ppo-S``, trained with older configs, which issue 48's new S runs replace) is refused
unless ``--replace`` says so; then the folder is rewritten whole and the old digest leaves the trust list.
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import sys
from pathlib import Path

import pandas as pd

from racebench.reporting.paper import final_training_success
from racebench.utils.files import sha256_file

EXPERIMENTS = Path("baselines/experiments")  # a run goes to <this>/<its campaign folder: campaign-4m, campaign-2>/
CHECKPOINTS = Path("baselines/checkpoints")
TRUST_FILE = Path("racebench/agents/trust.py")
RUN_FILES = ("config.yaml", "curriculum.json", "progress.csv", "summary.json", "validation_curve.csv", "written.json")
CHECKPOINT_FILES = ("config.yaml", "curriculum.json", "progress.csv")
#: Fields of the sweep's summary that describe only the last resumed part, or a path on the training machine.
PART_FIELDS = ("resumed_at", "env_seed", "wall_s", "samples_per_s", "checkpoint", "policy")
LINE_LENGTH = 120  # ruff's line-length (pyproject.toml)


def finished_summary(run_dir: Path) -> dict:
    """The sweep's ``summary.json`` of a run that finished: trained, exported and evaluated."""
    summary_file = run_dir / "summary.json"
    if not summary_file.is_file():
        raise ValueError(f"{run_dir}: no summary.json, so the run has not finished training")
    summary = json.loads(summary_file.read_text())
    if not (run_dir / "eval" / "summary.csv").is_file():
        raise ValueError(f"{run_dir}: no eval/summary.csv, so the run has not been evaluated")
    if summary.get("seed") == 0 and not policy_file(run_dir, summary).is_file():
        raise ValueError(f"{run_dir}: seed-0 run without its policy-only export {policy_file(run_dir, summary)}")
    return summary


def policy_file(run_dir: Path, summary: dict) -> Path:
    """Where ``racebench sweep`` wrote the run's policy-only export."""
    return run_dir / "policy" / f"{summary['config']}-{summary['track']}.zip"


def copy_run(run_dir: Path, dest: Path, with_policy: bool) -> None:
    """Replace ``dest`` by the run's committed part (small files, ``eval/``, and ``policy/`` when asked)."""
    if dest.exists():
        shutil.rmtree(dest)  # drops a resume state committed here (campaign_state.py save): the run is done
    dest.mkdir(parents=True)
    for name in RUN_FILES:
        if (run_dir / name).is_file():
            shutil.copy2(run_dir / name, dest / name)
    shutil.copytree(run_dir / "eval", dest / "eval")
    if with_policy:
        shutil.copytree(run_dir / "policy", dest / "policy")


def checkpoint_summary(summary: dict, progress: pd.DataFrame, *, checkpoint: str, run: str, trained_by: str,
                       note: str) -> dict:  # fmt: skip
    """The whole run's summary for ``baselines/checkpoints``: the sweep's, with its last-part fields replaced by
    totals over every session (``progress.csv``'s ``wall_s`` adds up the resumed parts)."""
    out = {key: value for key, value in summary.items() if key not in PART_FIELDS and key != "eval"}
    wall = float(progress["wall_s"].iloc[-1])
    promotions = summary.get("promotions") or []
    out["wall_s_total"] = round(wall, 1)
    out["wall_s_note"] = note
    out["samples_per_s_mean"] = round(summary["timesteps"] / wall, 1)
    out["steps_at_final_level"] = summary["timesteps"] - (promotions[-1]["timestep"] if promotions else 0)
    success = final_training_success(progress)
    out["final_training_success"] = None if success is None else round(success, 3)
    out["final_training_success_note"] = (
        "training success over the last 200k steps, rows weighted by the episodes they ended "
        "(racebench.reporting.paper.final_training_success)"
    )
    out["eval"] = summary.get("eval")
    out["checkpoint"], out["run"], out["trained_by"] = checkpoint, run, trained_by
    return out


def trust_line(sha256: str, relative: str) -> str:
    """The ``TRUSTED_CHECKPOINTS`` entry, wrapped as ruff formats it when it is too long for one line."""
    line = f'    "{sha256}": "{relative}",\n'
    return line if len(line) - 1 <= LINE_LENGTH else f'    "{sha256}": (\n        "{relative}"\n    ),\n'


def add_trusted(trust_file: Path, sha256: str, relative: str, replace: bool = False) -> bool:
    """Add ``sha256 -> relative`` to ``TRUSTED_CHECKPOINTS`` (False if it is there already). Another digest for the
    same path is refused unless ``replace``, which drops it: replacing a trusted checkpoint is a decision (issue 48's
    new S runs), so it is asked for by name."""
    text = trust_file.read_text()
    start = text.index("TRUSTED_CHECKPOINTS: dict[str, str] = {")
    end = text.index("\n}\n", start) + 1
    if f'"{sha256}"' in text[start:end]:
        return False
    for old in re.findall(r'"([0-9a-f]{64})": \(?\s*"([^"]+)"', text[start:end]):
        if old[1] != relative:
            continue
        if not replace:
            raise ValueError(f"{trust_file}: {relative} is trusted under another sha256; pass --replace to replace it")
        if trust_line(*old) not in text:
            raise ValueError(f"{trust_file}: the entry for {relative} is not in the form this script writes")
        text = text.replace(trust_line(*old), "", 1)
        end = text.index("\n}\n", start) + 1
    trust_file.write_text(text[:end] + trust_line(sha256, relative) + text[end:])
    return True


def finish(run_dir: Path, root: Path, trained_by: str, note: str, replace: bool = False) -> list[Path]:
    """Copy a finished run into the repository at ``root``; return the folders written. ``replace``: the run's
    checkpoint folder may hold another trusted policy, which it replaces."""
    campaign = EXPERIMENTS / run_dir.resolve().parent.name
    if not campaign.name.startswith("campaign-"):  # checked before anything is written
        raise ValueError(f"{run_dir}: not in a campaign folder (baselines/experiments/campaign-*/<run>)")
    summary = finished_summary(run_dir)
    seed0 = summary["seed"] == 0
    name = f"{summary['config']}-{summary['track']}"
    policy = policy_file(run_dir, summary)
    if seed0:  # first, so that a refused replacement writes nothing
        add_trusted(root / TRUST_FILE, sha256_file(policy), f"{name}/{policy.name}", replace=replace)
    dest = root / campaign / run_dir.name
    copy_run(run_dir, dest, with_policy=seed0)
    if not seed0:  # extra seeds: summaries and evaluations, not checkpoints (issue 48)
        return [dest]
    target = root / CHECKPOINTS / name
    if replace and target.exists():
        shutil.rmtree(target)  # nothing of the replaced run's files stays beside the new policy
    target.mkdir(parents=True, exist_ok=True)
    shutil.copy2(policy, target / policy.name)
    for file in CHECKPOINT_FILES:
        shutil.copy2(run_dir / file, target / file)
    if (target / "eval").exists():
        shutil.rmtree(target / "eval")
    shutil.copytree(run_dir / "eval", target / "eval")
    whole = checkpoint_summary(
        summary, pd.read_csv(run_dir / "progress.csv"), checkpoint=str(CHECKPOINTS / name / policy.name),
        run=str(campaign / run_dir.name), trained_by=trained_by, note=note,
    )  # fmt: skip
    (target / "summary.json").write_text(json.dumps(whole, indent=2) + "\n")
    return [dest, target]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", type=Path, help="the finished run's folder in the campaign clone")
    parser.add_argument("--root", type=Path, default=Path("."), help="the main checkout (default: here)")
    parser.add_argument("--trained-by", required=True, help="the command and pinned commits that trained it")
    parser.add_argument("--note", required=True, help="sessions, sharing and pauses behind its wall clock")
    parser.add_argument("--replace", action="store_true", help="replace the trusted policy already in its folder")
    args = parser.parse_args(argv)
    try:
        written = finish(args.run_dir, args.root, args.trained_by, args.note, args.replace)
    except KeyError as error:  # a summary.json without a field the sweep always writes
        print(f"campaign_finish: {args.run_dir}/summary.json has no {error} field", file=sys.stderr)
        return 1
    except (ValueError, OSError) as error:
        print(f"campaign_finish: {error}", file=sys.stderr)
        return 1
    for path in written:
        print(f"wrote {path}")
    print("next: racebench paper-tables; git add -f the policy zip; update the campaign README's status")
    return 0


if __name__ == "__main__":
    sys.exit(main())
