"""Every registered Gymnasium id, built from one table of variants.

``RaceObs-{S,J,Circle}-v0``: the paper's evaluation setting (density 3, v_d = 8 m/s);
``-Density{2,3,4,5}-v0``: obstacles per 2 gates (paper Table IV, top);
``-GateShift{0.3,0.5,0.7,1.0}-v0``: gates shifted ±δ m per axis at density 3 (Table IV, bottom);
``-Level{1,2,3}-v0``: the curriculum (Sec. III-C.1): 1 = no obstacles, low v_d; 2 = obstacles, low v_d;
3 = higher v_d, r_vd removed, denser obstacles;
``-{Latency,Latency30ms,Control30Hz,DepthNoise,Mass,Thrust,Drag,Wind,CameraTilt,StateNoise}-v0``: the robustness
suite, the main id with one sim-to-real gap (:data:`racebench.envs.perturbations.ROBUSTNESS`, ``docs/robustness.md``).
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym

from racebench.envs.perturbations import ROBUSTNESS

#: Version of the environments' outcomes. Before racebench 1.0 the ids stay ``-v0``; every evaluation record
#: carries this number instead, and any change that can change an episode's outcome (physics, collision or gate
#: logic, scene generation, time limits) bumps it, so results of different versions are never mixed.
#: History: 1 = first release; 2 = every touch is a crash (exact swept-sphere geometry, no Bullet bounce) and a
#: gate crossed on a substep that touched its frame is not passed; 3 = obstacles placed in a strip along each leg,
#: matched to the authors' scenes' share of obstacles near the racing line (``obstacle_placement="band"``; version 2's
#: box is ``"box"``), so every id's scenes changed.
ENV_VERSION = 3

TRACK_IDS: dict[str, str] = {"S": "S", "J": "J", "Circle": "Circle"}
DENSITIES: tuple[int, ...] = (2, 3, 4, 5)
GATE_SHIFTS: tuple[str, ...] = ("0.3", "0.5", "0.7", "1.0")
#: ``spec.max_episode_steps`` of every id at 50 Hz: ``RaceEnv``'s own time limit at its defaults (max_episode_time 15 s
#: × control_freq 50 Hz; a test keeps them equal; :func:`max_episode_steps` scales it to another control rate).
#: ``gym.make`` wraps the env in a ``TimeLimit`` of this many steps, which truncates on the same step as the env does,
#: so nothing changes at the defaults; an env made with a longer ``max_episode_time`` or a higher ``control_freq``
#: needs ``gym.make(..., max_episode_steps=N)`` as well.
MAX_EPISODE_STEPS = 750
LOW_SPEED = 3.0  # m/s, curriculum levels 1-2
HIGH_SPEED = 8.0  # m/s, level 3 and evaluation
CURRICULUM: dict[int, dict[str, Any]] = {
    1: {"density": 0, "desired_speed": LOW_SPEED},
    2: {"density": 2, "desired_speed": LOW_SPEED},
    3: {"density": 4, "desired_speed": HIGH_SPEED, "reward_weights": {"speed": 0.0}},
}


def variants() -> dict[str, dict[str, Any]]:
    """Map each env id to the ``RaceEnv`` kwargs it stands for."""
    table: dict[str, dict[str, Any]] = {}
    for key, track in TRACK_IDS.items():
        base = {"track": track, "density": 3, "desired_speed": HIGH_SPEED}
        table[f"RaceObs-{key}-v0"] = dict(base)
        for d in DENSITIES:
            table[f"RaceObs-{key}-Density{d}-v0"] = {**base, "density": d}
        for s in GATE_SHIFTS:
            table[f"RaceObs-{key}-GateShift{s}-v0"] = {**base, "gate_shift": float(s)}
        for level, kwargs in CURRICULUM.items():
            table[f"RaceObs-{key}-Level{level}-v0"] = {**base, **kwargs}
        for name, kwargs in ROBUSTNESS.items():
            table[f"RaceObs-{key}-{name}-v0"] = {**base, **kwargs}
    return table


def max_episode_steps(kwargs: dict[str, Any]) -> int:
    """The time limit in control steps of an id with ``kwargs``: 15 s at its control rate (750 at 50 Hz)."""
    return MAX_EPISODE_STEPS * int(kwargs.get("control_freq", 50)) // 50


ENV_KWARGS: dict[str, dict[str, Any]] = variants()
#: Ids on a generated track per episode (racebench.envs.random_tracks, docs/unseen-tracks.md), the paper's evaluation
#: setting otherwise: RaceObs-Random-v0 trains on new tracks, RaceObs-Unseen-v0 flies the held-out ones.
TRACK_SOURCE_IDS: dict[str, dict[str, Any]] = {
    f"RaceObs-{source}-v0": {"track": source, "density": 3, "desired_speed": HIGH_SPEED}
    for source in ("Random", "Unseen")
}
ENV_KWARGS.update(TRACK_SOURCE_IDS)
#: The entry point of an id when it is not RaceEnv itself.
ENTRY_POINTS: dict[str, str] = dict.fromkeys(TRACK_SOURCE_IDS, "racebench.envs.random_tracks:RandomTrackEnv")
ENV_IDS: list[str] = list(ENV_KWARGS)


def register_envs() -> None:
    """Register every id in :data:`ENV_IDS` with Gymnasium (idempotent)."""
    for env_id, kwargs in ENV_KWARGS.items():
        if env_id not in gym.registry:
            gym.register(
                id=env_id,
                entry_point=ENTRY_POINTS.get(env_id, "racebench.envs.env:RaceEnv"),
                vector_entry_point="racebench.envs.vector:RaceVectorEnv",  # gym.make_vec: batched, worker processes
                max_episode_steps=max_episode_steps(kwargs),
                kwargs=kwargs,
            )
