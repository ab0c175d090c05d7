"""Choosing a run's final student among the kept iterations and their weight average, on validation scenes."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pandas as pd
import torch

from racebench.evaluation.protocol import VALIDATION_SEED_BASE
from racebench.sim.raycast import BatchDepthRenderer
from racebench.training.dagger.config import DaggerConfig
from racebench.training.dagger.resume import KEPT_DIR, saved_policy_state
from racebench.training.student import is_recurrent, observe, student_step
from racebench.utils.files import atomic_write


def fly_student(envs: list[Any], policy: Any, seeds: list[int]) -> list[dict[str, Any]]:
    """The student alone (deterministic actions, no teacher) flies one episode of each scene in ``seeds``,
    ``len(envs)`` side by side; returns per episode ``seed``, ``success``, ``steps`` and ``lap_time`` (NaN
    without a lap), in the order of ``seeds``."""
    caster = BatchDepthRenderer(envs[0].camera)
    recurrent = is_recurrent(policy)
    hidden = torch.zeros(1, len(envs), policy.lstm_actor.hidden_size) if recurrent else None
    queue, flying, steps = list(seeds), [None] * len(envs), [0] * len(envs)
    results: dict[int, dict[str, Any]] = {}

    def start(i: int) -> None:
        flying[i] = queue.pop(0) if queue else None
        if flying[i] is not None:
            envs[i].reset_state(seed=flying[i])
            steps[i] = 0
            if hidden is not None:
                hidden[:, i] = 0.0

    for i in range(len(envs)):
        start(i)
    while any(s is not None for s in flying):
        active = [i for i, s in enumerate(flying) if s is not None]
        held = None if hidden is None else hidden[:, active]
        actions, new = student_step(policy, observe(caster, envs, active), held)
        if new is not None:
            hidden[:, active] = new
        for j, i in enumerate(active):
            _, terminated, truncated, info = envs[i].advance(actions[j])
            steps[i] += 1
            if terminated or truncated:
                results[flying[i]] = {"seed": flying[i], "success": bool(info["is_success"]), "steps": steps[i],
                                      "lap_time": float(info.get("lap_time", float("nan")))}  # fmt: skip
                start(i)
    return [results[s] for s in seeds]


def average_weights(states: list[dict[str, torch.Tensor]]) -> dict[str, torch.Tensor]:
    """The element-wise mean of several students' ``state_dict``s (non-float entries from the last)."""
    return {
        key: torch.stack([s[key] for s in states]).mean(0) if value.is_floating_point() else value
        for key, value in states[-1].items()
    }


def choose_student(
    out: Path, config: DaggerConfig, student: Any, envs: list[Any], training_seeds: tuple[int, int]
) -> dict[str, Any]:  # fmt: skip
    """Load the run's final student into ``student``, as ``config.final_student`` says, from the kept students.

    The candidates are the kept students of the last ``keep_iterations`` iterations and, with two or more, their
    element-wise weight average (saved beside them). With ``select_episodes`` > 0 each is flown on that many
    validation scenes and ``selection.csv`` lists what each finished. ``final_student``: ``"average"`` takes the
    average, ``"best"`` the candidate that finished most (ties: the later iteration; the average counts as the
    latest), ``"last"`` the last iteration's student. ``training_seeds`` is the ``[first, end)`` range the run trained
    on: validation scenes must lie outside it. Returns the chosen candidate's row (its label alone without flights).
    """
    seeds = [VALIDATION_SEED_BASE + i for i in range(config.select_episodes)]
    if seeds and max(training_seeds[0], seeds[0]) < min(training_seeds[1], seeds[-1] + 1):
        raise ValueError(f"dagger: validation seeds {seeds[0]}..{seeds[-1]} overlap the training seeds "
                         f"{training_seeds[0]}..{training_seeds[1] - 1}")  # fmt: skip
    kept = [out / KEPT_DIR / f"{config.name}-{config.track}-it{k:03d}.zip"
            for k in range(max(0, config.iterations - config.keep_iterations), config.iterations)]  # fmt: skip
    missing = [path for path in kept if not path.is_file()]
    if missing:
        raise ValueError(f"dagger: kept student {missing[0]} is missing: nothing to choose from")
    candidates = [(path.stem.rsplit("-", 1)[1], saved_policy_state(path)) for path in kept]
    if len(candidates) >= 2:
        candidates.append(("average", average_weights([state for _, state in candidates])))
        student.policy.load_state_dict(candidates[-1][1])
        student.save(out / KEPT_DIR / f"{config.name}-{config.track}-average.zip")  # evaluable like the others
    labels = [label for label, _ in candidates]
    rows = [{"candidate": label} for label in labels]
    if seeds:
        for row, (_, state) in zip(rows, candidates, strict=True):
            student.policy.load_state_dict(state)
            student.policy.set_training_mode(False)
            flown = pd.DataFrame(fly_student(envs, student.policy, seeds))
            laps = flown.loc[flown["success"], "lap_time"]
            row.update(episodes=len(flown), successes=int(flown["success"].sum()),
                       lap_time_mean=float(laps.mean()) if len(laps) else float("nan"))  # fmt: skip
    if config.final_student == "best":
        successes = [row["successes"] for row in rows]
        chosen = max(range(len(rows)), key=lambda i: (successes[i], i))
    else:
        # a run shorter than keep_iterations may have kept one student: its "average" is that student
        wanted = "average" if config.final_student == "average" and "average" in labels else labels[len(kept) - 1]
        chosen = labels.index(wanted)
    if seeds:
        table = pd.DataFrame(rows)
        table["chosen"] = table.index == chosen
        atomic_write(out / "selection.csv", table.to_csv(index=False))
    student.policy.load_state_dict(candidates[chosen][1])
    return {**rows[chosen], "chosen_by": config.final_student}
