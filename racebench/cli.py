"""``racebench`` command line: list environments, fly an episode, export a scene."""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence

import gymnasium as gym
import numpy as np

import racebench
from racebench.control import GateFollower

BUILTIN_FLY_AGENTS: tuple[str, ...] = ("follow", "hover", "random")


def _make(env_id: str, **kwargs) -> gym.Env:
    if env_id not in gym.registry and env_id not in racebench.ENV_IDS:
        raise SystemExit(f"racebench: unknown environment id {env_id!r}; `racebench envs` lists them")
    return gym.make(env_id, **kwargs)


def fly(env_id: str, agent: str, seed: int, obs_mode: str | None = None) -> dict:
    """Fly one episode of ``env_id`` with a built-in agent; return its outcome as a dict."""
    if agent not in BUILTIN_FLY_AGENTS:
        raise SystemExit(f"racebench fly: unknown agent {agent!r}; choose from {BUILTIN_FLY_AGENTS}")
    env = _make(env_id, **({"obs_mode": obs_mode} if obs_mode else {}))
    follower = GateFollower()
    _, info = env.reset(seed=seed)
    env.action_space.seed(seed)
    unwrapped = env.unwrapped
    hover = np.array([unwrapped.params.hover_action, 0.0, 0.0, 0.0], dtype=np.float32)
    total, steps = 0.0, 0
    terminated = truncated = False
    while not (terminated or truncated):
        if agent == "follow":
            action = follower.act_privileged(unwrapped)
        elif agent == "hover":
            action = hover
        else:
            action = env.action_space.sample()
        _, reward, terminated, truncated, info = env.step(action)
        total += reward
        steps += 1
    env.close()
    return {
        "env_id": env_id,
        "agent": agent,
        "seed": seed,
        "success": bool(info["is_success"]),
        "lap_time": info["lap_time"],
        "gates_passed": info["gates_passed"],
        "crash_reason": info["crash_reason"],
        "truncated": bool(truncated),
        "return": round(total, 4),
        "steps": steps,
    }


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``racebench`` console script."""
    parser = argparse.ArgumentParser(prog="racebench", description=__doc__)
    parser.add_argument("--version", action="version", version=f"racebench {racebench.__version__}")
    sub = parser.add_subparsers(dest="command", required=True)

    sub.add_parser("envs", help="list the registered environment ids")

    p_fly = sub.add_parser("fly", help="fly one episode with a built-in agent and print the outcome")
    p_fly.add_argument("--env", default="RaceObs-S-v0", help="environment id (default: RaceObs-S-v0)")
    p_fly.add_argument(
        "--agent",
        default="follow",
        choices=BUILTIN_FLY_AGENTS,
        help="follow: privileged gate-axis follower that ignores obstacles; hover; random",
    )
    p_fly.add_argument("--seed", type=int, default=0)
    p_fly.add_argument("--obs-mode", choices=("vision", "state"), default=None)

    p_scene = sub.add_parser("scene", help="write the scene of one episode as a mesh (.glb/.obj) and JSON")
    p_scene.add_argument("--env", default="RaceObs-S-v0")
    p_scene.add_argument("--seed", type=int, default=0)
    p_scene.add_argument("--out", default="scene.glb", help="mesh path; the JSON goes beside it")

    args = parser.parse_args(argv)
    if args.command == "envs":
        print("\n".join(racebench.ENV_IDS))
    elif args.command == "fly":
        result = fly(args.env, args.agent, args.seed, args.obs_mode)
        outcome = "SUCCESS" if result["success"] else f"FAILED ({result['crash_reason'] or 'time limit'})"
        print(json.dumps(result))
        lap = f", lap time {result['lap_time']:.2f} s" if result["success"] else ""
        print(f"{args.env} seed {args.seed} agent {args.agent}: {outcome}, gates {result['gates_passed']}{lap}")
    elif args.command == "scene":
        env = _make(args.env, obs_mode="state")
        env.reset(seed=args.seed)
        scene = env.unwrapped.scene
        path = scene.export(args.out)
        json_path = path.with_suffix(".json")
        json_path.write_text(json.dumps(scene.to_dict(), indent=2))
        env.close()
        print(f"wrote {path} and {json_path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
