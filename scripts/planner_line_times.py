"""Planner-fast's racing line timed as a point mass: how much of a lap-time target's gap is the line's.

For each scene, the fast expert's planned path (up to the finish crossing) is timed with the minimum-time
speed profile of a point mass (no attitude dynamics; :func:`~racebench.agents.planner.thrust_limited_speeds` on the
spline's own curvature) at two budgets:

* the planner's own thrust budget (``thrust_accel``, its drag, its 12 m/s cap): what its profile would be
  without the clearance caps and the jerk limits;
* the airframe's full thrust ``T_max / m`` (24.1 m/s²) in any direction, gravity included, no drag:
  **planner-fast's line at full thrust**. It holds along that one line only: a target below it would need another
  line, not a faster tracker. It is **not** a lower bound on the lap time (another line is shorter).

The next column is the lower bound on any lap, on any line, from :mod:`racebench.envs.lap_bound` (the time a
point mass at full thrust from rest needs for the straight gate-to-gate distance; record validation refuses a
success below it). The last column is the env version the scenes are of: the figures are per env version
(``racebench paper-tables`` reads the file of its campaign's version, :data:`racebench.reporting.paper.LINE_TIMES`).

    python scripts/planner_line_times.py --episodes 20 > baselines/experiments/planner_fast_line_times_env-v3.txt

(``planner_fast_line_times.txt``, without that column, was measured on env version 2 and is kept for campaign 1.)
"""

from __future__ import annotations

import argparse

import gymnasium as gym
import numpy as np

import racebench  # noqa: F401  (registers the ids)
from racebench.agents.planner import FastPlannerAgent, gate_crossings, thrust_limited_speeds
from racebench.envs.lap_bound import env_lap_time_bound
from racebench.envs.registration import ENV_VERSION
from racebench.evaluation import eval_seeds


def lap_time(arc: np.ndarray, speeds: np.ndarray) -> float:
    """Time to travel a sampled path at the given speeds: ``2 ds / (v_i + v_{i+1})`` per segment, exact under
    constant acceleration (and finite from rest, unlike the mean of ``1/v``)."""
    return float(np.sum(2.0 * np.diff(arc) / np.maximum(speeds[1:] + speeds[:-1], 1e-9)))


def main() -> None:
    """Print per-track means of the planned profile's time and its two point-mass times, the lower bound and the env
    version."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=20, help="evaluation seeds per main id")
    args = parser.parse_args()
    print(
        "env_id, n, planned profile (s), planner-fast's line at its thrust budget (s), "
        "planner-fast's line at full thrust (s), lap-time lower bound (s), env_version"
    )
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
            full_thrust = thrust_limited_speeds(arc, tangent, curvature, full, 1e3, 0.0, 0.0, params.gravity)
            rows.append((lap_time(arc, planner.speeds[:end]), lap_time(arc, budget), lap_time(arc, full_thrust)))
        env.close()
        mean = np.mean(rows, axis=0)
        env_id = f"RaceObs-{track}-v0"
        print(f"{env_id}, {len(rows)}, {mean[0]:.2f}, {mean[1]:.2f}, {mean[2]:.2f}, {env_lap_time_bound(env_id):.3f}, "
              f"{ENV_VERSION}")


if __name__ == "__main__":
    main()
