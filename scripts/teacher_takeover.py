"""Are a DAgger teacher's labels sound where a student flies? Hand the controls from a student to the teacher.

    python scripts/teacher_takeover.py --student runs/vision-distill-S-seed0/vision-distill-S.zip \\
        --track S --episodes 100 --replan none 0.3

DAgger labels every state the student reaches with the teacher's action there, so the labels are only as good as
the teacher is *from the student's states*. This measures that directly. On each training scene (seeds from
``--first-seed``, below the evaluation seeds) the student flies a lap from the start. At a handover step ``k``
(drawn per episode, the same for every teacher variant) the teacher takes over and flies to the end. The
teacher is called at every step before the handover too, exactly as in DAgger collection, so it has followed
the flight. Each ``--replan`` value is a ``planner-fast`` variant: ``none`` keeps the plan made at reset (the
built-in); a distance (m) plans again from the drone's state when it is farther than that from the line
(``FastPlannerAgent.replan_distance``). ``--integral-gain 0`` drops the tracker's integral term, which otherwise
sums the student's cross-track errors while the teacher only watches.

The student's flight up to the handover does not depend on the teacher, so every variant is handed the same
states. Per variant it prints the handovers (the student still flying at ``k``), the laps finished after
them, split by the drone's distance from the reset-time plan at the handover, and the replans made.
"""

from __future__ import annotations

import argparse
import time

import gymnasium as gym
import numpy as np
import torch

from racebench.agents import SB3Agent
from racebench.agents.planner import FastPlannerAgent
from racebench.evaluation import EVAL_SEED_BASE
from racebench.evaluation.statistics import wilson_interval


def fly(student: SB3Agent, teacher: FastPlannerAgent, env: gym.Env, seed: int, handover: int) -> dict:
    """One episode: the student until step ``handover``, then the teacher; the teacher is called every step."""
    obs, _ = env.reset(seed=seed)
    race = env.unwrapped
    student.reset(env=race, seed=seed)
    teacher.reset(env=race, seed=None)
    reset_plan = teacher.path.copy() if teacher.path is not None else None
    distance, speed_error, info = float("nan"), float("nan"), {}
    for step in range(race.max_steps):
        label = teacher.act()
        if step == handover and reset_plan is not None:
            distance = float(np.linalg.norm(reset_plan - race.drone.position, axis=1).min())
            if teacher.path is not None:  # the drone's speed against the plan's at the nearest point
                speed_error = float(np.linalg.norm(race.drone.velocity) - teacher.speeds[teacher._index])
        action = student.act(obs) if step < handover else label
        obs, _, terminated, truncated, info = env.step(np.clip(action, -1.0, 1.0))
        if terminated or truncated:
            break
    return {
        "handed_over": race.steps > handover,  # the student was still flying at the handover
        "success": bool(info.get("is_success")),
        "distance": distance,
        "speed_error": speed_error,
        "replans": teacher.replans,
        "replan_failures": teacher.replan_failures,
        "handover": handover,
        "end": race.steps,
        "crash": info.get("crash_reason"),
    }


def main() -> None:
    """Print, per teacher variant, how many handed-over laps the teacher finishes."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--student", required=True, help="student checkpoint (a vision-distill run's .zip)")
    parser.add_argument("--track", default="S", choices=["S", "Circle", "J"])
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--first-seed", type=int, default=900_000, help="training seeds (< evaluation seeds)")
    parser.add_argument("--handover", type=int, nargs=2, default=[25, 150], help="handover step range [a, b)")
    parser.add_argument("--replan", nargs="+", default=["none", "0.3"], help="'none' or a distance in m, each")
    parser.add_argument("--integral-gain", type=float, default=4.0, help="the teacher's (FastPlannerAgent's)")
    parser.add_argument("--details", action="store_true", help="also print each handed-over lap that failed")
    args = parser.parse_args()
    if not (0 <= args.first_seed and args.first_seed + args.episodes <= EVAL_SEED_BASE):
        parser.error(f"--first-seed: the seeds must stay below the evaluation seeds ({EVAL_SEED_BASE})")
    torch.set_num_threads(1)
    student = SB3Agent(args.student, trust_code=True)  # a checkpoint this workspace trained
    # The scenes DAgger trains on: gates shifted up to ±0.3 m (vision-distill's gate_shift).
    env = gym.make(f"RaceObs-{args.track}-v0", obs_mode="vision", renderer="raycast", gate_shift=0.3)
    handovers = np.random.default_rng(args.first_seed).integers(*args.handover, size=args.episodes)
    print(f"{args.student} on {args.track}: {args.episodes} training scenes from seed {args.first_seed}, handover at "
          f"steps {args.handover[0]}-{args.handover[1] - 1}; teacher integral gain {args.integral_gain:g}")  # fmt: skip
    for value in args.replan:
        replan = None if value == "none" else float(value)
        teacher = FastPlannerAgent(replan_distance=replan, integral_gain=args.integral_gain)
        started = time.perf_counter()
        rows = [fly(student, teacher, env, args.first_seed + i, int(k)) for i, k in enumerate(handovers)]
        taken = [r for r in rows if r["handed_over"]]
        ok = sum(r["success"] for r in taken)
        low, high = wilson_interval(ok, len(taken))
        share = 100 * ok / max(len(taken), 1)
        line = (f"replan {value:>4}: {ok}/{len(taken)} handed-over laps finished ({share:.0f} % "
                f"[{100 * low:.0f}-{100 * high:.0f}])")  # fmt: skip
        splits = {
            "<= 0.3 m off the reset plan": [r for r in taken if r["distance"] <= 0.3],
            "> 0.3 m off it": [r for r in taken if r["distance"] > 0.3],
            "no plan at reset (fallback)": [r for r in taken if np.isnan(r["distance"])],
        }
        for name, part in splits.items():
            line += f"; {name}: {sum(r['success'] for r in part)}/{len(part)}"
        tries = sum(r["replan_failures"] for r in rows)
        line += f"; {np.mean([r['replans'] for r in rows]):.1f} replans/episode ({tries} tries found no plan)"
        line += f"; {time.perf_counter() - started:.0f} s"
        print(line, flush=True)
        if args.details:
            for i, r in enumerate(rows):
                if r["handed_over"] and not r["success"]:
                    print(f"    seed {args.first_seed + i}: handover at step {r['handover']}, {r['distance']:.2f} m off"
                          f" the plan, speed {r['speed_error']:+.1f} m/s against it; ended at step {r['end']}"
                          f" ({r['crash']})")  # fmt: skip
    env.close()


if __name__ == "__main__":
    main()
