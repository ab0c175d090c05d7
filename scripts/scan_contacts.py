"""Scan evaluation episodes for touches the crash detector missed, checked by an independent geometry.

For each agent and main env id, flies the first ``--episodes`` evaluation seeds and records the drone at every
physics substep. Every substep's path is then measured with ``tests/reference_geometry.py`` (closed-form
sphere-to-box / cylinder / ground distances that share no code with ``racebench.sim.scene`` or
``racebench.sim.collision``), sampled at ``--samples`` points per substep. It reports, per agent and env id:

* ``missed_touch``: substeps that came within the contact tolerance without ending the episode in a crash;
* ``false_crash``: crashes whose last substep never came within the tolerance (+ the sweep resolution);
* ``velocity_jump``: substeps whose velocity change exceeds what thrust, gravity and drag can do (a contact
  impulse: the drone has no collision response, so there should be none);
* ``bad_success``: successful episodes containing either of the first or the last.

Usage (the committed output: ``baselines/experiments/contact_scan.txt``)::

    python scripts/scan_contacts.py --episodes 50 --out baselines/experiments/contact_scan.txt
"""

from __future__ import annotations

import argparse
import multiprocessing
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
AGENTS = ("follow", "planner", str(ROOT / "baselines/checkpoints/vision-ppo-S/vision-ppo-S.zip"))
ENV_IDS = ("RaceObs-S-v0", "RaceObs-Circle-v0", "RaceObs-J-v0")


def scan(agent_spec: str, env_id: str, episodes: int, samples: int) -> dict:
    """Fly ``episodes`` evaluation seeds of ``env_id`` with the agent and check every substep."""
    import gymnasium as gym
    import torch

    sys.path.insert(0, str(ROOT / "tests"))
    from reference_geometry import nearest_surface

    from racebench.agents import load_agent
    from racebench.evaluation import eval_seeds, run_episode
    from racebench.sim.collision import CONTACT_TOLERANCE, SWEEP_RESOLUTION

    torch.set_num_threads(1)
    agent = load_agent(agent_spec)
    env = gym.make(env_id, obs_mode=agent.obs_mode)
    raw = env.unwrapped
    params = raw.params
    # Thrust, gravity and a generous drag allowance bound the change of velocity in one substep.
    max_accel = 1.5 * (params.max_thrust / params.mass + params.gravity)
    counts = dict.fromkeys(("episodes", "substeps", "missed_touch", "false_crash", "velocity_jump", "bad_success"), 0)
    successes = 0
    closest = np.inf
    for seed in eval_seeds(episodes):
        trace: list[tuple] = []
        step_raw = raw.sim.step_raw

        def recording(force, torque, position, _step=step_raw, _trace=trace):
            state = _step(force, torque, position)
            _trace.append((state[0], state[2]))
            return state

        obs, _ = env.reset(seed=seed)
        raw.sim.step_raw = recording  # the env looks it up once per control step
        trace.append((tuple(raw.drone.position), tuple(raw.drone.velocity)))
        result = run_episode(agent, env, seed)
        del raw.sim.step_raw
        positions = np.array([t[0] for t in trace])
        velocities = np.array([t[1] for t in trace])
        t = np.linspace(0.0, 1.0, samples)
        path = positions[:-1, None, :] + t[None, :, None] * np.diff(positions, axis=0)[:, None, :]
        distance, _ = nearest_surface(raw.scene.to_dict(), path.reshape(-1, 3))
        per_substep = distance.reshape(len(positions) - 1, samples).min(axis=1) - params.collision_radius
        touched = per_substep <= CONTACT_TOLERANCE
        crashed_on_contact = result["crashed"] and result["crash_reason"] != "out_of_bounds"
        missed = int(touched[:-1].sum() + (touched[-1] and not crashed_on_contact))
        spacing = np.linalg.norm(np.diff(positions, axis=0), axis=1).max() / (samples - 1)
        false_crash = int(crashed_on_contact and per_substep[-1] > CONTACT_TOLERANCE + SWEEP_RESOLUTION + spacing)
        jumps = np.linalg.norm(np.diff(velocities, axis=0), axis=1) > max_accel * raw.dt
        jump = int(jumps[:-1].sum() if crashed_on_contact else jumps.sum())
        counts["episodes"] += 1
        counts["substeps"] += len(per_substep)
        counts["missed_touch"] += missed
        counts["false_crash"] += false_crash
        counts["velocity_jump"] += jump
        counts["bad_success"] += int(result["success"] and (missed or jump))
        successes += int(result["success"])
        clear = per_substep[:-1] if crashed_on_contact else per_substep
        if len(clear):
            closest = min(closest, float(clear.min()))
    env.close()
    name = Path(agent_spec).stem if agent_spec.endswith(".zip") else agent_spec
    return {"agent": name, "env_id": env_id, **counts, "successes": successes, "closest_clear_m": closest}


def main() -> None:
    """Run the scan over agents × main ids on two processes and write the table."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--samples", type=int, default=9, help="points per substep path (ends included)")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--out", default=None, help="also write the table to this file")
    args = parser.parse_args()
    import pandas as pd

    import racebench

    started = time.perf_counter()
    jobs = [(a, e) for a in AGENTS for e in ENV_IDS]
    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(args.workers, mp_context=context) as pool:
        rows = list(pool.map(scan, *zip(*jobs, strict=True), [args.episodes] * len(jobs), [args.samples] * len(jobs)))
    table = pd.DataFrame(rows)
    total = table[["episodes", "substeps", "missed_touch", "false_crash", "velocity_jump", "bad_success"]].sum()
    text = (
        f"# contact scan: racebench {racebench.__version__}, env version {racebench.ENV_VERSION}, "
        f"{args.episodes} evaluation seeds per agent and id, {args.samples} samples per substep path, "
        f"{time.perf_counter() - started:.0f} s\n"
        f"{table.to_string(index=False, float_format=lambda v: f'{v:.4f}')}\n"
        f"# total: {total.to_dict()}\n"
    )
    print(text, end="")
    if args.out:
        Path(args.out).write_text(text)
    if total["missed_touch"] or total["false_crash"] or total["velocity_jump"] or total["bad_success"]:
        raise SystemExit("scan_contacts: the detector and the independent geometry disagree (see above)")


if __name__ == "__main__":
    main()
