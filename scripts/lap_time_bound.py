"""Lap-time bounds along planner-fast's racing line: how much of the gap to a target is the airframe's.

For each scene, the fast expert's planned path (up to the finish crossing) is timed with the minimum-time
speed profile of a point mass (no attitude dynamics; :func:`~racebench.agents.planner.thrust_limited_speeds` on the
spline's own curvature) at two budgets:

* the planner's own thrust budget (``thrust_accel``, its drag, its 12 m/s cap): what its profile would be
  without the clearance caps and the jerk limits;
* the airframe's full thrust ``T_max / m`` (24.1 m/s²) in any direction, gravity included, no drag: a lower
  bound on any lap flown along that line (drag's help when braking aside, ≤ 0.05 v² m/s²). A target below it
  would be infeasible on that line; a target above it leaves the gap to path shape and tracking.

Both hold along that one line only. The bound of any lap, on any line, is :mod:`racebench.envs.lap_bound` (about half of
the airframe-ceiling column: the shortest line through the openings, a thrust aimed anywhere); record validation
rejects a success below it.

    python scripts/lap_time_bound.py --episodes 20 > baselines/experiments/lap_time_bound.txt
"""

from __future__ import annotations

import argparse

import gymnasium as gym
import numpy as np

import racebench  # noqa: F401  (registers the ids)
from racebench.agents.planner import FastPlannerAgent, gate_crossings, thrust_limited_speeds
from racebench.evaluation import eval_seeds


def lap_time(arc: np.ndarray, speeds: np.ndarray) -> float:
    """Time to travel a sampled path at the given speeds: ``2 ds / (v_i + v_{i+1})`` per segment, exact under
    constant acceleration (and finite from rest, unlike the mean of ``1/v``)."""
    return float(np.sum(2.0 * np.diff(arc) / np.maximum(speeds[1:] + speeds[:-1], 1e-9)))


def main() -> None:
    """Print per-track means of the planned profile's time and the two point-mass bounds."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=20, help="evaluation seeds per main id")
    args = parser.parse_args()
    print("env_id, n, planned profile (s), point mass at thrust budget (s), point mass at airframe ceiling (s)")
    for track in ("S", "Circle", "J"):
        env = gym.make(f"RaceObs-{track}-v0", obs_mode="state")
        unwrapped = env.unwrapped
        params = unwrapped.params
        drag = params.drag_coefficients[0] / params.mass
        rows = []
        for seed in eval_seeds(args.episodes):
            env.reset(seed=seed)
            planner = FastPlannerAgent()
            if not planner.plan(unwrapped.scene, unwrapped.drone.position, 0.0, params):
                continue
            end = gate_crossings(planner.path, unwrapped.scene.gates)[-1] + 2
            arc, curvature, tangent = planner.arc[:end], planner.profile_curvature[:end], planner.tangent[:end]
            budget = thrust_limited_speeds(
                arc, tangent, curvature, planner.thrust_accel, planner.max_speed, 0.0, drag, params.gravity
            )
            full = params.max_thrust / params.mass
            bound_top = thrust_limited_speeds(arc, tangent, curvature, full, 1e3, 0.0, 0.0, params.gravity)
            rows.append((lap_time(arc, planner.speeds[:end]), lap_time(arc, budget), lap_time(arc, bound_top)))
        env.close()
        mean = np.mean(rows, axis=0)
        print(f"RaceObs-{track}-v0, {len(rows)}, {mean[0]:.2f}, {mean[1]:.2f}, {mean[2]:.2f}")


if __name__ == "__main__":
    main()
