"""Does the DAgger teacher need to know obstacles the camera has not shown? Fly both teachers on the same scenes.

    python scripts/seen_teacher.py --config baselines/vision-distill.yaml --tracks S J Circle --episodes 50

The privileged teacher (``teacher_obstacles: all``) plans its line at reset around every obstacle; the "seen"
teacher (``teacher_obstacles: seen``, :class:`racebench.agents.planner.FastPlannerAgent` with
``obstacle_knowledge="seen"``) only around those its onboard camera has shown, planning again when one comes into
view near its line. Both are built from the config's teacher keys (:func:`racebench.training.dagger.make_teacher`)
and fly every scene of the evaluation seeds of ``RaceObs-<T>-v0`` (the same scenes ``racebench evaluate``
flies). Per track it prints each teacher's success rate with its Wilson interval, its mean lap, what ended its
failed laps, the laps only one of them finished (exact McNemar p), the seen teacher's replans per lap, and on how
many scenes the privileged line at reset already bends for an obstacle the camera does not show then (an
obstacle out of view lies within the teacher's berth, ``wanted_clearance``, of that line): there the two
teachers' labels for the same first frames differ.
"""

from __future__ import annotations

import argparse
import dataclasses
from collections import Counter

import gymnasium as gym
import numpy as np
import pandas as pd

from racebench.evaluation import EVAL_SEED_BASE
from racebench.evaluation.rollout import run_episode
from racebench.evaluation.statistics import paired_outcomes, wilson_interval
from racebench.sim.raycast import ObstacleSight
from racebench.training.dagger import DaggerConfig, make_teacher
from racebench.training.train import load_config


def bends_for_the_unseen(env, teacher) -> bool:
    """Whether ``teacher``'s line, planned at reset, passes within its berth of an obstacle not in view then."""
    sight = ObstacleSight(env.camera, env.scene)
    return teacher.line_passes_near(np.flatnonzero(~sight.in_view(env.drone.position, env.drone.rotation)))


def main() -> None:
    """Print, per track, both teachers' outcomes on the same scenes."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default="baselines/vision-distill.yaml", help="a DAgger config (teacher keys)")
    parser.add_argument("--tracks", nargs="+", default=["S", "J", "Circle"], choices=["S", "J", "Circle"])
    parser.add_argument("--episodes", type=int, default=50)
    args = parser.parse_args()
    config = load_config(args.config)
    if not isinstance(config, DaggerConfig) or config.teacher != "planner-fast":
        parser.error(f"--config: {args.config} is not a DAgger config with teacher planner-fast")
    for track in args.tracks:
        env = gym.make(f"RaceObs-{track}-v0", obs_mode="state")
        frames = {}
        bends = 0
        for knowledge in ("all", "seen"):
            teacher = make_teacher(dataclasses.replace(config, teacher_obstacles=knowledge))
            rows = []
            for i in range(args.episodes):
                result = run_episode(teacher, env, EVAL_SEED_BASE + i)
                rows.append({
                    "env_id": f"RaceObs-{track}-v0", "seed": EVAL_SEED_BASE + i,
                    "success": bool(result["success"]), "lap_time": result["lap_time"],
                    "crash": result["crash_reason"], "replans": teacher.sighting_replans,
                })  # fmt: skip
                if knowledge == "all":  # replay the reset to ask whether the line bends for the unseen
                    env.reset(seed=EVAL_SEED_BASE + i)
                    teacher.reset(env=env.unwrapped)
                    bends += bends_for_the_unseen(env.unwrapped, teacher)
            frames[knowledge] = pd.DataFrame(rows)
        env.close()
        print(f"## {track} ({args.episodes} scenes, evaluation seeds)")
        for knowledge, frame in frames.items():
            wins = int(frame["success"].sum())
            low, high = wilson_interval(wins, len(frame))
            crashes = dict(Counter(str(c).split(":")[0] for c in frame.loc[~frame["success"], "crash"]))
            lap = frame.loc[frame["success"], "lap_time"].mean()
            line = (f"teacher_obstacles {knowledge}: {wins}/{len(frame)} [{100 * low:.0f}-{100 * high:.0f} %], "
                    f"mean lap {lap:.2f} s, failures {crashes}")  # fmt: skip
            if knowledge == "seen":
                line += f", sighting replans per lap {frame['replans'].mean():.2f}"
            print(line)
        _, only_all, only_seen, p = paired_outcomes(frames["all"], frames["seen"])
        print(
            f"laps only the privileged teacher finished {only_all}, only the seen one {only_seen} (exact McNemar "
            f"p = {p:.2f}); scenes whose privileged line at reset bends for an obstacle out of view: "
            f"{bends}/{args.episodes}"
        )


if __name__ == "__main__":
    main()
