"""Where, relative to the teacher's racing line, does a student fly into an obstacle?

    python scripts/crash_geometry.py baselines/checkpoints/vision-distill-S/eval \\
        --agent baselines/checkpoints/vision-distill-S/vision-distill-S.zip --env RaceObs-S-v0 --trust-code

Every obstacle crash of the evaluation folder (and, for comparison, up to ``--successes`` finished laps) is flown
again as ``racebench evaluate`` flew it (:mod:`crash_visibility`'s replay: same id, seed, renderer and lockstep
width; a replay that does not end as its record did is skipped), with the DAgger teacher of ``--teacher-config``
following along as in DAgger collection (its line is planned at reset from the true scene). At each step it takes
the student's cross-track offset from that line (the teacher's tracking error, tangent part removed), its speed
against the line's planned speed at the same point, and the squared distance of its action to the teacher's label.

For a crash it reports these at 1 s and 0.5 s before the hit and at its last step (``hit``), plus:

* ``line_clearance``: how close the teacher's line passes the obstacle that was hit, horizontally (its berth, m);
* ``toward_obstacle``: the part of the offset pointing at that obstacle, seen from the line (m): the student
  flew into it by leaving the line toward it;
* ``inside_turn``: the part of the offset along the line's curvature direction (m; > 0: inside the turn, cutting
  it; < 0: outside, understeering);
* ``same_side``: whether, at the hit, student and line are on the same side of the obstacle (False: the student
  went round the other way, e.g. the mean of two ways round).

``--without-obstacle`` asks whether the student reacted to that obstacle at all: the episode is flown twice more
with the analytic ray caster (``renderer="raycast"``; the PyBullet replay's last bits differ), once in the true
scene and once with the hit obstacle taken out of the scene (out of the depth image and of the crash test), and
it prints how far apart the two flights are at the step of the hit (``apart_at_hit``, m) and how close the
obstacle-free flight passes where the obstacle stood in the last 0.5 s up to that step (``blind_pass``, horizontal,
m; at or under the drone's 0.12 m collision radius it would have hit it without ever swerving).

Why: the seed-students fail the same scenes (``failure_overlap.py``) and see the obstacles they hit
(``crash_visibility.py``); this separates an imprecise student (small offsets, on the teacher's side) from one that
cuts or overshoots turns or picks the other way round an obstacle, which call for different remedies.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import gymnasium as gym
import numpy as np
import pandas as pd
import torch
from crash_visibility import Pilot

from racebench.agents import load_agent
from racebench.evaluation import DEFAULT_BATCH
from racebench.training.dagger import make_teacher
from racebench.training.train import load_config


def fly_with_teacher(pilot: Pilot, teacher, env: gym.Env, seed: int) -> tuple[dict, pd.DataFrame]:
    """Fly one episode with the agent while the teacher follows; per step the geometry against its line."""
    obs, _ = env.reset(seed=seed)
    race = env.unwrapped
    pilot.reset(race, seed)
    teacher.reset(env=race, seed=None)
    rows = []
    while True:
        label = np.clip(teacher.act(), -1.0, 1.0)  # also advances the teacher's index along its line
        action = pilot.act(obs)
        if teacher.path is not None:
            i = teacher._index
            pos, vel = np.array(race.drone.position, dtype=float), np.array(race.drone.velocity, dtype=float)
            t = teacher.tangent[i]
            offset = pos - teacher.path[i]
            offset -= (offset @ t) * t
            rows.append(
                {
                    "step": race.steps,
                    "index": i,
                    "offset": offset,
                    "speed": float(np.linalg.norm(vel)),
                    "line_speed": float(teacher.speeds[i]),
                    "curvature": teacher.curvature[i],
                    "action_error": float(np.sum((np.clip(action, -1.0, 1.0) - label) ** 2)),
                }
            )
        obs, _, terminated, truncated, info = env.step(action)
        if terminated or truncated:
            return {**info, "steps": race.steps}, pd.DataFrame(rows)


def fly_positions(pilot: Pilot, env: gym.Env, seed: int, drop: int | None, steps: int) -> np.ndarray:
    """Positions of up to ``steps`` steps of one episode; ``drop``: an obstacle taken out of the scene at reset."""
    env.reset(seed=seed)
    race = env.unwrapped
    if drop is not None:
        race.scene = dataclasses.replace(
            race.scene, obstacles=tuple(o for k, o in enumerate(race.scene.obstacles) if k != drop)
        )
    obs = race._observation()  # in both flights, so the depth noise draws stay in step
    pilot.reset(race, seed)
    positions = [np.array(race.drone.position, dtype=float)]
    while race.steps < steps:
        obs, _, terminated, truncated, _ = env.step(pilot.act(obs))
        positions.append(np.array(race.drone.position, dtype=float))  # the last one is where the hit was
        if terminated or truncated:
            break
    return np.array(positions)


def lateral(vector: np.ndarray, tangent: np.ndarray) -> np.ndarray:
    """``vector`` without its component along the unit ``tangent``."""
    return vector - (vector @ tangent) * tangent


def crash_row(trace: pd.DataFrame, teacher, obstacle, hz: int) -> dict:
    """The crash's geometry against the teacher's line (see the module docstring)."""
    row: dict = {}
    for label, back in (("1s", hz), ("0.5s", hz // 2), ("hit", 1)):
        at = trace.iloc[max(0, len(trace) - back)]
        row[f"offset_{label}"] = float(np.linalg.norm(at["offset"]))
        row[f"speed_excess_{label}"] = at["speed"] - at["line_speed"]
    last = trace.iloc[-1]
    i = int(last["index"])
    t = teacher.tangent[i]
    # the obstacle's nearest point to the line there, seen from the line
    near = np.asarray(obstacle.position, dtype=float).copy()
    near[2] = teacher.path[i][2]  # sides are taken in the horizontal plane: the obstacles are upright
    to_obstacle = lateral(near - teacher.path[i], t)
    direction = to_obstacle / max(np.linalg.norm(to_obstacle), 1e-9)
    row["toward_obstacle"] = float(last["offset"] @ direction)
    kappa = np.asarray(last["curvature"], dtype=float)
    row["inside_turn"] = float(last["offset"] @ kappa / max(np.linalg.norm(kappa), 1e-9))
    row["curvature_at_hit"] = float(np.linalg.norm(kappa))
    row["line_clearance"] = float(np.min(obstacle.xy_distance(teacher.path)))
    # same side: the student's offset from the obstacle centre points the way the line's does (horizontal plane)
    line_side = lateral(teacher.path[i] - near, t)[:2]
    student_side = lateral(teacher.path[i] + last["offset"] - near, t)[:2]
    row["same_side"] = bool(line_side @ student_side > 0)
    row["action_error_last_1s"] = float(trace["action_error"].iloc[-hz:].mean())
    return row


def main() -> None:
    """Print, per obstacle crash of an evaluation, its geometry against the teacher's line, and a summary."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("eval_dir", type=Path, help="an evaluation folder (episodes.csv) of the agent")
    parser.add_argument("--agent", required=True, help="the agent those records are of (a .zip)")
    parser.add_argument("--env", default=None, help="env id (default: the folder's only one)")
    parser.add_argument("--trust-code", action="store_true", help="load a checkpoint outside the shipped ones")
    parser.add_argument("--teacher-config", default="vision-distill", help="the DAgger config whose teacher follows")
    parser.add_argument("--successes", type=int, default=20, help="finished laps flown for comparison")
    parser.add_argument("--without-obstacle", action="store_true", help="fly each crash again without the obstacle")
    args = parser.parse_args()
    torch.set_num_threads(1)
    episodes = pd.read_csv(args.eval_dir / "episodes.csv")
    env_ids = episodes["env_id"].unique().tolist() if args.env is None else [args.env]
    if len(env_ids) != 1:
        parser.error(f"{args.eval_dir} holds several ids ({', '.join(env_ids)}): pick one with --env")
    mine = episodes[episodes["env_id"] == env_ids[0]]
    crashes = mine[mine["crash_reason"].fillna("").str.startswith("obstacle:")]
    finished = mine[mine["success"].astype(bool)].head(args.successes)
    agent = load_agent(args.agent, trust_code=args.trust_code)
    pilot = Pilot(agent, max(1, min(DEFAULT_BATCH, len(episodes))))
    env = gym.make(env_ids[0], obs_mode=agent.obs_mode, renderer=mine["renderer"].iloc[0])
    race = env.unwrapped
    hz = race.control_freq
    cast = gym.make(env_ids[0], obs_mode=agent.obs_mode, renderer="raycast") if args.without_obstacle else None
    config = load_config(args.teacher_config)
    rows, typical = [], []
    for _, record in crashes.iterrows():
        seed, reason, steps = int(record["seed"]), record["crash_reason"], int(record["steps"])
        teacher = make_teacher(config)
        info, trace = fly_with_teacher(pilot, teacher, env, seed)
        if info.get("crash_reason") != reason or info["steps"] != steps:
            print(f"seed {seed}: the replay ended {info.get('crash_reason')} at step {info['steps']}, the record "
                  f"{reason} at step {steps}: skipped")  # fmt: skip
            continue
        if trace.empty:  # the teacher's plan failed on this scene (its fallback flew): no line to measure against
            print(f"seed {seed}: the teacher found no line through this scene: skipped")
            continue
        j = int(reason[9:])
        row = {"seed": seed, "obstacle": reason, **crash_row(trace, teacher, race.scene.obstacles[j], hz)}
        if args.without_obstacle:
            obstacle = race.scene.obstacles[j]
            seen = fly_positions(pilot, cast, seed, None, steps)
            blind = fly_positions(pilot, cast, seed, j, steps)
            n = min(len(seen), len(blind))
            row["apart_at_hit"] = float(np.linalg.norm(seen[n - 1] - blind[n - 1]))
            row["blind_pass"] = float(obstacle.xy_distance(blind[max(0, n - hz // 2) :]).min())
        rows.append(row)
        print(", ".join(f"{k} {v:.2f}" if isinstance(v, float) else f"{k} {v}" for k, v in row.items()), flush=True)
    for _, record in finished.iterrows():
        teacher = make_teacher(config)
        _, trace = fly_with_teacher(pilot, teacher, env, int(record["seed"]))
        if not trace.empty:
            typical.append(trace)
    env.close()
    if cast is not None:
        cast.close()
    table = pd.DataFrame(rows)
    if table.empty:
        print("no obstacle crash replayed")
        return
    print(f"\n{args.eval_dir} ({env_ids[0]}): {len(table)} obstacle crashes replayed of {len(crashes)}")
    for column in table.columns[2:]:
        values = table[column].astype(float)
        count = f", true in {int(values.sum())}" if table[column].dtype == bool else ""
        print(f"  {column}: median {values.median():.2f}, quartiles {values.quantile(0.25):.2f} to "
              f"{values.quantile(0.75):.2f}{count}")  # fmt: skip
    if typical:
        every = pd.concat(typical)
        offsets = np.linalg.norm(np.stack(every["offset"].to_numpy()), axis=1)
        excess = every["speed"] - every["line_speed"]
        print(f"  finished laps ({len(typical)}), every step: offset median {np.median(offsets):.2f} m, 90th "
              f"percentile {np.quantile(offsets, 0.9):.2f} m; speed excess median {excess.median():.2f} m/s; "
              f"action error mean {every['action_error'].mean():.3f}")  # fmt: skip


if __name__ == "__main__":
    main()
