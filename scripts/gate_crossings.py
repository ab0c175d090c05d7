"""Where a policy crosses each gate, beside where the fast expert's planned line crosses it, on the same scenes.

    python scripts/gate_crossings.py baselines/checkpoints/vision-distill-S/eval --env RaceObs-S-v0

Reads the trajectories an evaluation saved (``racebench evaluate --save-trajectories``), plans ``planner-fast``
for each episode's scene (same env id and seed) and prints, per gate: how many episodes crossed it, how many
ended on its frame, and the mean (and spread) of the crossing point's offset from the opening's centre along
the gate's horizontal axis and vertically, for the policy and for the expert. A student that imitates the
expert but crosses systematically nearer a bar shows up here before it shows up as ``gate:k`` crashes.
"""

from __future__ import annotations

import argparse

import gymnasium as gym
import numpy as np

import racebench  # noqa: F401  (registers the ids)
from racebench.agents.planner import FastPlannerAgent
from racebench.evaluation.records import read_trajectories


def crossing_offset(path: np.ndarray, gate) -> np.ndarray | None:
    """(horizontal, vertical) offset from the gate centre where ``path`` first passes the opening, or None."""
    for k in range(len(path) - 1):
        if gate.passed_by(path[k], path[k + 1]):
            a, b = path[k], path[k + 1]
            t = float((gate.center - a) @ gate.normal / ((b - a) @ gate.normal))
            off = a + t * (b - a) - gate.center
            return np.array([off @ gate.lateral, off[2]])
    return None


def main() -> None:
    """Print one line per gate."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("eval_dir", help="an evaluation directory with saved trajectories (--save-trajectories)")
    parser.add_argument("--env", default="RaceObs-S-v0", help="the env id whose episodes to read")
    parser.add_argument("--gate-clearance", type=float, default=0.4, help="the expert's (default 0.4)")
    args = parser.parse_args()

    flown = read_trajectories(args.eval_dir)  # trajectories.npz (or per-episode files of an unfinished run)
    if not flown:
        raise SystemExit(f"gate_crossings: no trajectories in {args.eval_dir} (--save-trajectories)")
    try:
        env = gym.make(args.env, obs_mode="state").unwrapped  # the same scenes as the evaluation's renderer
    except gym.error.Error as exc:
        raise SystemExit(f"gate_crossings: {exc}") from exc
    expert = FastPlannerAgent(gate_clearance=args.gate_clearance)
    policy: dict[int, list[np.ndarray]] = {}
    planned: dict[int, list[np.ndarray]] = {}
    ended: dict[int, int] = {}
    episodes = 0
    for row, positions, _scene in flown:
        if row["env_id"] != args.env:
            continue
        episodes += 1
        env.reset(seed=int(row["seed"]))
        expert.reset(env=env)
        reason = row.get("crash_reason") or ""
        for i, gate in enumerate(env.scene.gates):
            if reason == f"gate:{i}":
                ended[i] = ended.get(i, 0) + 1
            for where, line in ((policy, positions), (planned, expert.path)):
                offset = crossing_offset(line, gate)
                if offset is not None:
                    where.setdefault(i, []).append(offset)
    env.close()
    if not episodes:
        raise SystemExit(f"gate_crossings: no episode of {args.env} in {args.eval_dir}")
    print(f"{args.env}: {episodes} episodes of {args.eval_dir}; offsets from the opening's centre in m, mean (sd)")
    print("gate, crossed, ended on its frame, policy horizontal, policy vertical, expert horizontal, expert vertical")
    for i in sorted(set(policy) | set(planned)):
        p, e = np.array(policy.get(i, np.zeros((0, 2)))), np.array(planned.get(i, np.zeros((0, 2))))

        def cell(values: np.ndarray, axis: int) -> str:
            return f"{values[:, axis].mean():+.2f} ({values[:, axis].std():.2f})" if len(values) else "-"

        print(f"{i}, {len(p)}, {ended.get(i, 0)}, {cell(p, 0)}, {cell(p, 1)}, {cell(e, 0)}, {cell(e, 1)}")


if __name__ == "__main__":
    main()
