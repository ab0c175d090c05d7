"""The weight average of a DAgger run's last K kept students, as a checkpoint to evaluate.

    python scripts/average_students.py runs/distill-select-J-seed0 --last 3 --out runs/avg/J-seed0-k3.zip

A run with ``keep_iterations`` keeps the students of its last iterations in ``RUN_DIR/iterations/``
(``<name>-<track>-it<k>.zip``) and, with ``final_student: average``, checkpoints the element-wise average of all of
them. This averages only the last ``K`` of them (``racebench.training.dagger.average_weights``, the run's own
averaging), so how many iterations to average can be measured after the run, without training again:
docs/teacher-student.md, "Which students to keep". ``--last`` equal to the run's ``keep_iterations`` reproduces its
average's weights (tested). The students are SB3 checkpoints the run wrote, so they are loaded as trusted code.
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import torch

from racebench.agents import SB3Agent
from racebench.training.dagger import KEPT_DIR, average_weights

KEPT_NAME = re.compile(r"^(?P<run>.+)-it(?P<iteration>\d{3,})\.zip$")


def kept_students(run_dir: Path) -> list[tuple[int, Path]]:
    """``(iteration, path)`` of every kept student in ``run_dir/iterations/``, by iteration (exits if none, or if
    they are of more than one run name)."""
    folder = run_dir / KEPT_DIR
    found = [(m, p) for p in sorted(folder.glob("*.zip")) if (m := KEPT_NAME.match(p.name))]
    if not found:
        raise SystemExit(f"average_students: no kept students (<name>-<track>-it<k>.zip) in {folder}")
    names = sorted({m["run"] for m, _ in found})
    if len(names) > 1:
        raise SystemExit(f"average_students: {folder} holds students of several runs {names}")
    return sorted((int(m["iteration"]), p) for m, p in found)


def average_last(run_dir: Path, last: int, out: Path) -> list[int]:
    """Save the weight average of the last ``last`` kept students of ``run_dir`` to ``out``; returns their
    iterations."""
    kept = kept_students(run_dir)
    if not 1 <= last <= len(kept):
        raise SystemExit(f"average_students: --last {last}, but {run_dir / KEPT_DIR} keeps {len(kept)} students "
                         f"(iterations {', '.join(str(k) for k, _ in kept)})")  # fmt: skip
    chosen = kept[-last:]
    iterations = [iteration for iteration, _ in chosen]
    if iterations != list(range(iterations[0], iterations[0] + last)):  # e.g. a resumed run's older kept students
        raise SystemExit(f"average_students: the last {last} kept students are not consecutive iterations {iterations}")
    models = [SB3Agent(str(path), trust_code=True).model for _, path in chosen]
    student = models[-1]
    student.policy.load_state_dict(average_weights([model.policy.state_dict() for model in models]))
    out.parent.mkdir(parents=True, exist_ok=True)
    student.save(out)
    return iterations


def main() -> None:
    """Command line: average the last ``--last`` kept students of RUN_DIR into ``--out``."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run_dir", type=Path, help="a DAgger run folder (with iterations/)")
    parser.add_argument("--last", type=int, required=True, help="how many of the last kept students to average")
    parser.add_argument("--out", type=Path, required=True, help="the averaged checkpoint (.zip)")
    args = parser.parse_args()
    if args.last < 1:
        parser.error(f"--last must be >= 1, not {args.last}")
    torch.set_num_threads(1)  # loading and averaging a few MB: more threads only contend with whatever else runs
    iterations = average_last(args.run_dir, args.last, args.out)
    print(f"{args.out}: the weight average of iterations {', '.join(map(str, iterations))}")


if __name__ == "__main__":
    main()
