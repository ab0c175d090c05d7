"""Extra fitting passes over a finished DAgger run's final aggregate, the learning rate falling linearly towards 0.

    python scripts/extra_fit.py runs/distill-berth-075-S-seed0 --epochs 8 --seed 12345 --out runs/extra-fit-S
    racebench evaluate --agent runs/extra-fit-S/vision-distill-berth-075-S.zip ...   # as any checkpoint

A DAgger run's fit loss keeps falling to its last iteration (each fit is ``epochs`` passes at a constant learning
rate), so does a student that fits its aggregate better fly better? This starts from the run's saved state
(:func:`racebench.training.dagger.restore_state`: the student and Adam's state after the last iteration, the whole
aggregate), makes ``--epochs`` more passes with the run's own fit (:func:`racebench.training.dagger.fit`; a
recurrent student's chunk start states are recomputed before each pass; a run with ``fit_samples`` has each pass
cut there), pass ``k`` of ``n`` at the run's learning rate times ``1 - k/n`` (the last at ``1/n`` of it), and
writes into ``OUT``: ``<name>-<track>.zip`` (the student after the last pass, an ordinary checkpoint),
``extra_fit.csv`` (pass, learning rate, the pass's mean loss, wall seconds) and ``extra_fit.json`` (the run and
arguments it was made with). The passes' order is drawn from ``--seed``. The run's folder is only read (``OUT``
may not be in it).
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import asdict, fields
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from racebench.evaluation.records import atomic_write
from racebench.training.dagger import (
    DaggerConfig,
    Dataset,
    fit,
    load_resume_state,
    make_student,
    make_training_envs,
    restore_state,
    resume_folder,
)


def saved_config(run: Path) -> DaggerConfig:
    """The config a DAgger run in ``run`` was saved with (a setting added since: its default); a one-line
    ``SystemExit`` when there is no readable saved state."""
    folder = resume_folder(run)
    if folder is None:
        raise SystemExit(f"extra_fit: {run} holds no saved DAgger state (resume/state.json)")
    try:
        saved = {**asdict(DaggerConfig()), **json.loads((folder / "state.json").read_text())["config"]}
    except (json.JSONDecodeError, KeyError, TypeError) as exc:
        state = folder / "state.json"
        raise SystemExit(f"extra_fit: {state} is not a DAgger state ({type(exc).__name__}: {exc})") from None
    return DaggerConfig(**{f.name: saved[f.name] for f in fields(DaggerConfig)})


def extra_fit(run: Path, out: Path, epochs: int, seed: int, threads: int = 1) -> pd.DataFrame:
    """Make ``epochs`` more passes over the aggregate of the DAgger run in ``run``; write the student and the log
    into ``out`` and return the log (one row a pass)."""
    if epochs < 1 or threads < 1:
        raise SystemExit(f"extra_fit: epochs and threads must be at least 1, got {epochs} and {threads}")
    if out.resolve().is_relative_to(run.resolve()):
        raise SystemExit(f"extra_fit: --out {out} is inside the run {run}, which is only read")
    config = saved_config(run)
    try:
        saved = load_resume_state(run, config)
    except ValueError as exc:
        raise SystemExit(f"extra_fit: {exc}") from None
    torch.set_num_threads(threads)
    config.n_envs = 1  # one env builds the student's spaces; nothing is flown
    made = make_training_envs(config)
    student = make_student(made[0], config.seed, config.student)
    optimizer = torch.optim.Adam(student.policy.parameters(), lr=config.learning_rate)
    dataset = Dataset(config.max_samples, made[0].unwrapped.camera.size)
    restore_state(saved, student, optimizer, dataset, np.random.default_rng())  # the run's own stream is not used
    for env in made:
        env.close()
    rng = np.random.default_rng(seed)  # the passes' order: --seed, so runs of one script compare pass for pass
    config.epochs = 1  # one pass a fit call, each at its own learning rate
    out.mkdir(parents=True, exist_ok=True)
    made_with = {"run": str(run), "iterations": saved["iteration"] + 1, "epochs": epochs, "seed": seed,
                 "threads": threads}  # fmt: skip
    (out / "extra_fit.json").write_text(json.dumps(made_with, indent=2))
    rows, started = [], time.perf_counter()
    for k in range(epochs):
        rate = config.learning_rate * (1 - k / epochs)
        for group in optimizer.param_groups:
            group["lr"] = rate
        loss = fit(student.policy, dataset, config, optimizer, rng)
        rows.append({"pass": k, "learning_rate": rate, "loss": loss, "wall_s": round(time.perf_counter() - started, 1)})
        print(rows[-1], flush=True)
        student.save(out / f"{config.name}-{config.track}.zip")
        # after every pass, whole or not at all: a killed run keeps the log of the passes it finished
        atomic_write(out / "extra_fit.csv", pd.DataFrame(rows).to_csv(index=False))
    return pd.DataFrame(rows)


def main() -> None:
    """Command line: ``RUN --epochs N --seed S --out DIR [--threads T]``."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, help="a DAgger run's folder (racebench train --out), with its resume/ state")
    parser.add_argument("--epochs", type=int, required=True, help="passes over the aggregate")
    parser.add_argument("--seed", type=int, default=0, help="seed of the passes' order (default 0)")
    parser.add_argument("--out", type=Path, required=True, help="folder for the student and extra_fit.csv")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    args = parser.parse_args()
    extra_fit(args.run, args.out, args.epochs, args.seed, args.threads)


if __name__ == "__main__":
    main()
