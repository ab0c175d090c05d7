"""Did the agent see the obstacle it hit? Replay an evaluation's obstacle crashes and measure the obstacle's view.

    python scripts/crash_visibility.py baselines/experiments/distill-gate-centre-per-track/Circle/eval \\
        --agent runs/distill-gate-centre-Circle-seed0/vision-distill-gate-centre-Circle.zip

A vision policy can only avoid what its camera has shown it. For every episode of the evaluation folder that
ended on an obstacle (``crash_reason`` ``obstacle:<j>``), this flies the episode again with the agent (same id,
same seed, the same renderer, a batch agent at the evaluation's lockstep width) and checks that the replay ends
the same way (same reason, same step; a replay on another machine or with other code may not, and is then
reported and skipped). Along the replayed flight it renders the onboard
depth image twice per step with the analytic ray caster, once of the whole scene and once without obstacle
``j``, and counts the pixels where obstacle ``j`` is the nearest surface. Per crash it prints when the obstacle
was first and last in view and how many pixels it covered 0.5 s before the hit, and sums them up: a crash into
an obstacle that was in view for a second is the policy's error; one into an obstacle never seen in the last
second (beside or behind the camera's 90° field of view) is what the sensor allows.

``--takeover 1.0 0.5`` then asks whether the label was there to learn: for each such crash and each time before
the hit, the episode is flown once more with the DAgger teacher of ``--teacher-config`` called at every step (as
in DAgger collection, so it has followed the flight) and handed the controls that long before the hit; it prints
how many of those laps the teacher finishes and how many still end on the same obstacle. ``--kind gate`` does the
same for gate strikes (``gate:<i>``; the pixels are gate ``i``'s frame).
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import gymnasium as gym
import numpy as np
import pandas as pd
import torch

from racebench.agents import load_agent
from racebench.evaluation import DEFAULT_BATCH
from racebench.evaluation.rollout import BatchAgent, check_action
from racebench.sim.raycast import BatchDepthRenderer
from racebench.training.dagger import make_teacher
from racebench.training.train import load_config

VISIBLE_PIXELS = 1  # pixels the obstacle must cover to count as "in view"
DEPTH_MARGIN = 0.01  # m: a pixel is the obstacle's when removing it makes the depth deeper by more than this


def obstacle_pixels(
    renderer: BatchDepthRenderer, scene, j: int, positions: np.ndarray, rotations: np.ndarray, kind: str = "obstacle"
) -> np.ndarray:  # fmt: skip
    """Per pose, the number of depth pixels where obstacle ``j`` of ``scene`` (``kind="gate"``: gate ``j``'s frame)
    is the nearest surface."""
    field = "obstacles" if kind == "obstacle" else "gates"
    without = dataclasses.replace(scene, **{field: tuple(o for i, o in enumerate(getattr(scene, field)) if i != j)})
    n = len(positions)
    full = renderer.render([scene] * n, positions, rotations)
    bare = renderer.render([without] * n, positions, rotations)
    return ((bare - full) > DEPTH_MARGIN).sum(axis=(1, 2))


class Pilot:
    """Flies an agent as the evaluator did: a batch agent through ``act_batch`` at the evaluation's lockstep
    width (every call passes ``width`` observations, as ``run_lockstep`` does; the network's last bits depend on
    the batch size), any other agent through ``act``."""

    def __init__(self, agent, width: int) -> None:
        self.agent, self.width = agent, width
        self.batched = width > 1 and isinstance(agent, BatchAgent)

    def reset(self, env, seed: int) -> None:
        """A new episode (the evaluator's reset: the env only for a privileged agent)."""
        if self.batched:
            self.agent.start(self.width)
            self.agent.reset_slot(0)
        else:
            self.agent.reset(env=env if self.agent.privileged else None, seed=seed)

    def act(self, obs) -> np.ndarray:
        """The agent's action for ``obs`` (checked as the evaluator checks it)."""
        raw = self.agent.act_batch([obs] * self.width)[0] if self.batched else self.agent.act(obs)
        action, error = check_action(raw)
        if error:
            raise ValueError(error)
        return action


def replay(pilot: Pilot, env: gym.Env, seed: int) -> tuple[dict, np.ndarray, np.ndarray]:
    """Fly one episode; its last info and the body poses (positions, rotations) the camera saw from."""
    obs, _ = env.reset(seed=seed)
    race = env.unwrapped
    pilot.reset(race, seed)
    positions, rotations, info = [], [], {}
    while True:
        position, _, rotation, _, _ = race.drone
        positions.append(np.array(position, dtype=float))
        rotations.append(np.array(rotation, dtype=float))
        action = pilot.act(obs)
        obs, _, terminated, truncated, info = env.step(action)
        if terminated or truncated:
            return {**info, "steps": race.steps}, np.array(positions), np.array(rotations)


def take_over(pilot: Pilot, teacher, env: gym.Env, seed: int, handover: int) -> dict:
    """The agent flies until step ``handover``, then the teacher (called at every step from the start)."""
    obs, _ = env.reset(seed=seed)
    race = env.unwrapped
    pilot.reset(race, seed)
    teacher.reset(env=race, seed=None)
    while True:
        label = teacher.act()
        action = pilot.act(obs) if race.steps < handover else np.clip(label, -1.0, 1.0)
        obs, _, terminated, truncated, info = env.step(action)
        if terminated or truncated:
            return info


def main() -> None:
    """Print, per obstacle crash of an evaluation, when the obstacle was in view, and a summary."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("eval_dir", type=Path, help="an evaluation folder (episodes.csv) of the agent")
    parser.add_argument("--agent", required=True, help="the agent those records are of (a .zip, or a built-in)")
    parser.add_argument("--env", default=None, help="env id (default: the folder's only one)")
    parser.add_argument("--trust-code", action="store_true", help="load a checkpoint outside the shipped ones")
    parser.add_argument("--width", type=int, default=None,
                        help="the evaluation's lockstep width (default: as racebench evaluate chose it)")  # fmt: skip
    parser.add_argument("--kind", default="obstacle", choices=["obstacle", "gate"], help="the crashes to replay")
    parser.add_argument("--takeover", type=float, nargs="*", default=[], help="seconds before the hit (see above)")
    parser.add_argument("--teacher-config", default="vision-distill", help="the DAgger config whose teacher takes over")
    args = parser.parse_args()
    torch.set_num_threads(1)
    episodes = pd.read_csv(args.eval_dir / "episodes.csv")
    env_ids = episodes["env_id"].unique().tolist() if args.env is None else [args.env]
    if len(env_ids) != 1:
        parser.error(f"{args.eval_dir} holds several ids ({', '.join(env_ids)}): pick one with --env")
    crashes = episodes[
        (episodes["env_id"] == env_ids[0]) & episodes["crash_reason"].fillna("").str.startswith(f"{args.kind}:")
    ]
    agent = load_agent(args.agent, trust_code=args.trust_code)
    # racebench evaluate's width: --batch (64) or the evaluation's size when smaller (all its ids and seeds)
    pilot = Pilot(agent, args.width or max(1, min(DEFAULT_BATCH, len(episodes))))
    renderers = crashes["renderer"].unique().tolist() if len(crashes) else ["pybullet"]
    if len(renderers) != 1:
        parser.error(f"{args.eval_dir}: crashes flown with several renderers ({', '.join(renderers)})")
    env = gym.make(env_ids[0], obs_mode=agent.obs_mode, renderer=renderers[0])
    race = env.unwrapped
    renderer = BatchDepthRenderer(race.camera)
    hz = race.control_freq
    rows = []
    for _, record in crashes.iterrows():
        seed, reason, steps = int(record["seed"]), record["crash_reason"], int(record["steps"])
        info, positions, rotations = replay(pilot, env, seed)
        if info.get("crash_reason") != reason or info["steps"] != steps:
            print(f"seed {seed}: the replay ended {info.get('crash_reason')} at step {info['steps']}, the record "
                  f"{reason} at step {steps}: skipped")  # fmt: skip
            continue
        j = int(reason.split(":")[1])
        pixels = obstacle_pixels(renderer, race.scene, j, positions, rotations, args.kind)
        seen = np.flatnonzero(pixels >= VISIBLE_PIXELS)
        half_second = pixels[max(0, len(pixels) - hz // 2)]
        last_second = pixels[max(0, len(pixels) - hz) :]
        row = {
            "seed": seed,
            args.kind: j,
            "steps": steps,
            "first_seen_s": seen[0] / hz if len(seen) else np.nan,
            "last_seen_before_hit_s": (len(pixels) - 1 - seen[-1]) / hz if len(seen) else np.nan,
            "pixels_0.5s_before": int(half_second),
            "seen_in_last_1s": bool((last_second >= VISIBLE_PIXELS).any()),
            "max_pixels_last_1s": int(last_second.max()),
        }
        for seconds in args.takeover:
            teacher = make_teacher(load_config(args.teacher_config))
            info = take_over(pilot, teacher, env, seed, max(0, steps - round(seconds * hz)))
            row[f"teacher_{seconds:g}s_finishes"] = bool(info.get("is_success"))
            row[f"teacher_{seconds:g}s_same_hit"] = info.get("crash_reason") == reason
        rows.append(row)
        print(", ".join(f"{k} {v:.2f}" if isinstance(v, float) else f"{k} {v}" for k, v in row.items()), flush=True)
    env.close()
    table = pd.DataFrame(rows)
    if table.empty:
        print(f"no {args.kind} crash replayed")
        return
    in_view = int(table["seen_in_last_1s"].sum())
    kind = args.kind
    print(f"{args.eval_dir} ({env_ids[0]}): {len(table)} {kind} crashes replayed of {len(crashes)}; the {kind} "
          f"was in view in the last second before {in_view}, never in it before {len(table) - in_view}; in view "
          f"0.5 s before the hit: {int((table['pixels_0.5s_before'] >= VISIBLE_PIXELS).sum())}; median time from its "
          f"last sighting to the hit {table['last_seen_before_hit_s'].median():.2f} s")  # fmt: skip
    for seconds in args.takeover:
        print(f"the teacher ({args.teacher_config}) handed the controls {seconds:g} s before the hit: finishes "
              f"{int(table[f'teacher_{seconds:g}s_finishes'].sum())} of {len(table)}, hits the same {args.kind} in "
              f"{int(table[f'teacher_{seconds:g}s_same_hit'].sum())}")  # fmt: skip


if __name__ == "__main__":
    main()
