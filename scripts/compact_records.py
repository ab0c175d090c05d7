"""Job: convert every evaluation folder under the given roots from one file per record (``records/*.json``,
``trajectories/*.npz``) to one ``records.jsonl`` and one ``trajectories.npz``, checking that every record round-trips.

Usage (the one-off migration of issue 47; a folder already converted is left alone)::

    python scripts/compact_records.py results baselines/checkpoints baselines/experiments

Strict where the evaluator is lenient: a committed record that fails validation stops the conversion (it would
otherwise be set aside and its episode re-run), and so does any difference between a record (or trajectory)
before and after, digest included. Prints one line per converted folder and a total.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # this checkout's racebench, not an installed one
from racebench.evaluation.records import (  # noqa: E402
    LEGACY_DIR,
    TRAJECTORIES_DIR,
    InvalidRecordError,
    compact_folder,
    compact_trajectories,
    read_folder,
    read_record,
    read_trajectories,
)


def legacy_folders(roots: list[Path]) -> list[Path]:
    """Evaluation folders under ``roots`` holding legacy per-record files (``records/*.json``)."""
    found = {path.parent.parent for root in roots for path in root.rglob(f"{LEGACY_DIR}/*.json")}
    found |= {path.parent.parent for root in roots for path in root.rglob(f"{TRAJECTORIES_DIR}/*.npz")}
    return sorted(found)


def convert(folder: Path) -> tuple[int, int]:
    """Convert one folder; return (records, trajectories). Raises ``InvalidRecordError`` on any mismatch."""
    before = {path.name: read_record(path) for path in sorted((folder / LEGACY_DIR).glob("*.json"))}
    flights = {f"{r['env_id']}/{r['seed']}": (r, p, s) for r, p, s in read_trajectories(folder)}
    found = compact_folder(folder, set_aside=False)
    if found.problems:  # read_record passed them all: only a concurrent writer could get here
        raise found.problems[0].error()
    after = read_folder(folder)
    if after.problems or after.records != before or (folder / LEGACY_DIR).exists():
        raise InvalidRecordError(f"{folder}: records.jsonl does not hold exactly the records of {LEGACY_DIR}/")
    if any(after.records[name]["digest"] != before[name]["digest"] for name in before):
        raise InvalidRecordError(f"{folder}: a digest changed")
    compact_trajectories(folder)
    moved = {f"{r['env_id']}/{r['seed']}": (r, p, s) for r, p, s in read_trajectories(folder)}
    if moved.keys() != flights.keys() or (folder / TRAJECTORIES_DIR).exists():
        raise InvalidRecordError(
            f"{folder}: trajectories.npz does not hold exactly the trajectories of {TRAJECTORIES_DIR}/"
        )
    for key, (row, positions, scene) in flights.items():
        new_row, new_positions, new_scene = moved[key]
        same = new_row == row and new_scene == scene and new_positions.dtype == positions.dtype
        if not (same and np.array_equal(new_positions, positions)):
            raise InvalidRecordError(f"{folder}: the trajectory of {key} changed")
    return len(before), len(flights)


def main(argv: list[str] | None = None) -> int:
    """Convert every legacy folder under the roots given; print one line per folder."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("roots", nargs="+", type=Path, help="folders to search for legacy evaluation folders")
    args = parser.parse_args(argv)
    totals = [0, 0, 0]
    for folder in legacy_folders(args.roots):
        try:
            records, flights = convert(folder)
        except InvalidRecordError as exc:
            raise SystemExit(f"compact_records: {exc}") from exc
        print(f"{folder}: {records} records, {flights} trajectories")
        totals = [totals[0] + 1, totals[1] + records, totals[2] + flights]
    print(f"{totals[0]} folders converted: {totals[1]} records, {totals[2]} trajectories")
    return 0


if __name__ == "__main__":
    sys.exit(main())
