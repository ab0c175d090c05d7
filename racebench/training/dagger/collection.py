"""Collecting a DAgger iteration: the mixed teacher/student rollouts and the teacher's labels (and auxiliary
targets: the teacher's line ahead, the clearance ahead) of every state the student reaches.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from racebench.agents.control import acceleration_command
from racebench.agents.planner import FastPlannerAgent, PlannerAgent
from racebench.sim.raycast import BatchDepthRenderer
from racebench.training.dagger.config import CLEARANCE_CAP_M, CLEARANCE_PROBES, LINE_AHEAD_M, PATH_AUX_SIZE
from racebench.training.dagger.dataset import Dataset
from racebench.training.student import is_recurrent, observe, student_output, student_step


def line_ahead(teacher: Any, drone: Any) -> np.ndarray | None:
    """The auxiliary target at the drone's state: where the teacher's line is :data:`LINE_AHEAD_M` metres along it
    beyond the point the teacher is tracking (its index, advanced by its last ``act``), as body-frame vectors from
    the drone in metres, flattened ``(PATH_AUX_SIZE,)``; ``None`` while it has no line (a
    failed plan: its fallback flies)."""
    path = getattr(teacher, "path", None)
    if path is None:
        return None
    arc = teacher.arc
    ahead = np.searchsorted(arc, arc[teacher._index] + np.asarray(LINE_AHEAD_M))
    points = path[np.minimum(ahead, len(path) - 1)]  # past the line's end: its last point
    body = (points - drone.position) @ drone.rotation  # R^T v per row: world to body
    return body.astype(np.float32).reshape(-1)


def clearance_ahead(scene: Any, drone: Any) -> np.ndarray:
    """The "clearance" auxiliary target at the drone's state: the distance from each of :data:`CLEARANCE_PROBES`
    (body-frame points ahead of the drone, placed in the world by its pose) to the nearest obstacle or gate bar of
    ``scene`` (:meth:`racebench.sim.scene.Scene.distance`), capped at :data:`CLEARANCE_CAP_M`, ``(PATH_AUX_SIZE,)``."""
    points = drone.position + CLEARANCE_PROBES @ drone.rotation.T  # R p per row: body to world
    return np.minimum(scene.distance(points), CLEARANCE_CAP_M).astype(np.float32)


def aux_target(task: str, teacher: Any, env: Any) -> np.ndarray | None:
    """The auxiliary target of ``task`` (:data:`AUX_TASKS`) at ``env``'s current state: :func:`line_ahead` of the
    teacher's line, or :func:`clearance_ahead` of the env's scene."""
    if task == "line":
        return line_ahead(teacher, env.drone)
    return clearance_ahead(env.scene, env.drone)


def make_path_head(hidden_size: int) -> torch.nn.Module:
    """The auxiliary head (training only): GRU output -> the auxiliary target (:func:`aux_target`)."""
    return torch.nn.Sequential(torch.nn.Linear(hidden_size, 128), torch.nn.ReLU(), torch.nn.Linear(128, PATH_AUX_SIZE))


def collect(
    envs: list[Any],
    teachers: list[PlannerAgent | FastPlannerAgent],
    policy: Any,
    beta: float,
    steps: int,
    rng: np.random.Generator,
    seeds: list[int],
    dataset: Dataset,
    crash_weight: float = 1.0,
    crash_window: int = 50,
    replay_failed: float = 0.0,
    failed: list[int] | None = None,
    aux_task: str | None = None,
    groups: list[str] | None = None,
) -> dict[str, float]:
    """Fly ``steps`` env steps with the beta-mixture of teacher and student; label every step with the teacher.

    ``envs`` are unwrapped vision ``RaceEnv``s with the ray caster (depth of all rendered in one call);
    ``seeds`` is a shared counter of training seeds. A recurrent student's state runs through every step
    whoever acts, and is zeroed when its env starts an episode. Each episode is stored as one segment when it
    ends (an episode still flying at the end is stored as far as it got). Returns the episodes' success rate
    and mean length. The last ``crash_window`` steps of an episode that ended in a crash are stored with loss
    weight ``crash_weight`` (the others with 1). With ``replay_failed`` > 0, ``failed`` is the queue of training
    scenes (seeds) whose episodes failed: each failed episode on a new scene appends its seed, and each new episode
    re-flies the last queued scene with probability ``replay_failed`` (taking it off the queue) instead of the next
    new seed. A replayed scene is not queued again: each scene is flown twice at most. With ``aux_task`` (one of
    :data:`AUX_TASKS`) every step is also stored with its auxiliary target (:func:`aux_target`; mask 0 where there
    is none: the teacher has no line). An acceleration student (:func:`student_output`) is labelled with the teacher's
    acceleration commands (its ``command`` after each ``act``) and flies its own through ``command_to_ctbr``.
    With ``groups`` (a label per env: its track) the stats also hold ``success_rate_<label>`` per label.
    """
    caster = BatchDepthRenderer(envs[0].camera)
    replaying = replay_failed > 0.0 and failed is not None
    episode_seed, is_replay = [0] * len(envs), [False] * len(envs)
    replayed = 0
    recurrent = is_recurrent(policy)
    commands = student_output(policy) == "acceleration"
    hidden = torch.zeros(1, len(envs), policy.lstm_actor.hidden_size) if recurrent else None
    segments: list[list[tuple[np.ndarray, ...]]] = [[] for _ in envs]
    no_line = np.zeros(PATH_AUX_SIZE, dtype=np.float32)

    def start(i: int) -> None:
        nonlocal replayed
        is_replay[i] = bool(replaying and failed and rng.random() < replay_failed)  # off: no draw, runs as before
        if is_replay[i]:
            episode_seed[i] = failed.pop()
            replayed += 1
        else:
            episode_seed[i] = seeds[0]
            seeds[0] += 1
        envs[i].reset_state(seed=episode_seed[i])
        teachers[i].reset(env=envs[i], seed=None)
        if hidden is not None:
            hidden[:, i] = 0.0

    def store(i: int, crashed: bool = False) -> None:
        if segments[i]:
            weight = np.ones(len(segments[i]), dtype=np.float32)
            if crashed:
                weight[-crash_window:] = crash_weight
            columns = [np.stack(column) for column in zip(*segments[i], strict=True)]
            dataset.add_segment(*columns[:3], weight, *columns[3:])  # with aux_task: targets and their mask
            segments[i] = []

    for i in range(len(envs)):
        start(i)
    obs = observe(caster, envs, list(range(len(envs))))
    successes, lengths, taken = [], [], 0
    finished_by: list[int] = []  # the env that flew each finished episode
    lengths_now = np.zeros(len(envs), dtype=int)
    while taken < steps:
        teacher = np.array([t.act() for t in teachers], dtype=np.float32).clip(-1.0, 1.0)
        if commands:  # the label is what the teacher asked its last stage for, not what that stage sent
            labels = np.stack([acceleration_command(*t.command, env.drone.rotation)
                               for t, env in zip(teachers, envs, strict=True)])  # fmt: skip
        else:
            labels = teacher
        for i in range(len(envs)):
            step = (obs[i]["state"], obs[i]["depth"], labels[i])
            if aux_task is not None:
                target = aux_target(aux_task, teachers[i], envs[i])
                step += (no_line, np.float32(0.0)) if target is None else (target, np.float32(1.0))
            segments[i].append(step)
        student, hidden = student_step(policy, obs, hidden)
        use_teacher = rng.random(len(envs)) < beta
        actions = np.where(use_teacher[:, None], teacher, student)
        for i, env in enumerate(envs):
            _, terminated, truncated, info = env.advance(actions[i])
            lengths_now[i] += 1
            if terminated or truncated:
                successes.append(bool(info["is_success"]))
                finished_by.append(i)
                if replaying and not info["is_success"] and not is_replay[i]:
                    failed.append(episode_seed[i])
                lengths.append(int(lengths_now[i]))
                lengths_now[i] = 0
                store(i, crashed=info.get("crash_reason") is not None)
                start(i)
        obs = observe(caster, envs, list(range(len(envs))))
        taken += len(envs)
    for i in range(len(envs)):
        store(i)
    stats = {
        "steps": taken,
        "episodes": len(successes),
        "success_rate": float(np.mean(successes)) if successes else float("nan"),
        "mean_length": float(np.mean(lengths)) if lengths else float("nan"),
    }
    for label in dict.fromkeys(groups or []):
        mine = [ok for ok, i in zip(successes, finished_by, strict=True) if groups[i] == label]
        stats[f"success_rate_{label}"] = float(np.mean(mine)) if mine else float("nan")
    if replaying:
        stats["replayed"] = replayed  # episodes that re-flew a failed scene
    return stats
