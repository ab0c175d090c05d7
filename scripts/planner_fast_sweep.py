"""Fly ``planner-fast`` with other settings on training seeds (tuning never touches the evaluation seeds).

    python scripts/planner_fast_sweep.py --set max_accel=10,13 thrust_accel=none braking_jerk=none \
        > baselines/experiments/planner_fast_accel.txt  # v2's friction-circle profile
    python scripts/planner_fast_sweep.py --seeds 60 --set thrust_accel=none,15 braking_jerk=none,60 \
        > baselines/experiments/planner_fast_profile.txt
    python scripts/planner_fast_sweep.py --seeds 100 --gate-shift 0.3 --set gate_clearance=0.5 \
        wanted_clearance=0.6 integral_gain=0,4 > baselines/experiments/teacher_training_scenes.txt  # DAgger's teacher

Prints, per env id and setting: successes / episodes with the 95 % Wilson interval, the mean lap time of the
successful laps and the crash reasons of the others.
"""

from __future__ import annotations

import argparse
import inspect
import itertools

import gymnasium as gym
import numpy as np

import racebench  # noqa: F401  (registers the ids)
from racebench.agents.planner import FastPlannerAgent
from racebench.evaluation.rollout import run_episode
from racebench.evaluation.statistics import wilson_interval


def parse_settings(items: list[str]) -> dict[str, list[float | None]]:
    """``["max_accel=10,13", "braking_jerk=none,60"]`` → ``{"max_accel": [10.0, 13.0], "braking_jerk": [None,
    60.0]}`` (``none`` turns an optional stage off); a one-line error on bad input."""
    grid = {}
    settings = inspect.signature(FastPlannerAgent).parameters
    for item in items:
        name, _, values = item.partition("=")
        if not values or name not in settings:
            raise SystemExit(f"planner_fast_sweep: expected NAME=V1,V2,... naming a planner setting, got {item!r}")
        optional = "None" in str(settings[name].annotation)  # only these may be turned off
        try:
            grid[name] = [None if optional and v.strip().lower() == "none" else float(v) for v in values.split(",")]
        except ValueError:
            raise SystemExit(f"planner_fast_sweep: {name}: expected comma-separated numbers, got {values!r}") from None
    return grid


def main() -> None:
    """Fly every combination of the given settings on every id and print one line each."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--envs", nargs="+", default=["RaceObs-S-v0", "RaceObs-Circle-v0", "RaceObs-J-v0"])
    parser.add_argument("--seeds", type=int, default=20, help="number of training seeds (default 20)")
    parser.add_argument("--first-seed", type=int, default=0, help="first training seed (default 0)")
    parser.add_argument("--set", nargs="+", default=[], metavar="NAME=V1,V2", help="settings to vary")
    parser.add_argument(
        "--gate-shift",
        type=float,
        default=None,
        metavar="M",
        help="shift the gates up to ±M m per episode (DAgger's training scenes: 0.3; default: the id's)",
    )
    args = parser.parse_args()
    grid = parse_settings(args.set)
    print("env_id, setting, successes/n, SR [95% CI], mean lap (s), failures")
    for env_id in args.envs:
        shift = {} if args.gate_shift is None else {"gate_shift": args.gate_shift}
        env = gym.make(env_id, obs_mode="state", **shift)
        for values in itertools.product(*grid.values()):
            setting = dict(zip(grid, values, strict=True))
            agent = FastPlannerAgent(**setting)
            results = [run_episode(agent, env, seed) for seed in range(args.first_seed, args.first_seed + args.seeds)]
            laps = [r["lap_time"] for r in results if r["success"]]
            low, high = wilson_interval(len(laps), len(results))
            lap = f"{np.mean(laps):.2f}" if laps else "-"
            failures = " ".join(r["crash_reason"] or "timeout" for r in results if not r["success"])
            rate = f"{100 * len(laps) / len(results):.0f} % [{100 * low:.0f}-{100 * high:.0f}]"
            print(f"{env_id}, {setting}, {len(laps)}/{len(results)}, {rate}, {lap}, {failures}")
        env.close()


if __name__ == "__main__":
    main()
