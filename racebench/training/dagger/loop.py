"""Teacher–student distillation with DAgger: a depth policy imitates a privileged planner.

The field's answer to the cost of learning vision-based flight from reward alone (Loquercio et al. 2021;
Xing et al. 2024): a *teacher* with privileged information (the fast expert
:class:`~racebench.agents.planner.FastPlannerAgent` by default, or the cautious
:class:`~racebench.agents.planner.PlannerAgent`;
both plan on the true scene) labels every state the *student* visits, and the student, which sees only what a
deployed policy sees (the 17-d state and the noisy depth image), is trained by supervised regression on the
aggregate of those labels (DAgger, Ross et al. 2011). The algorithm, in full:

1. ``iteration 0``: the teacher flies; every step's observation is stored with the teacher's action.
2. ``iteration k``: each step, the student's action is executed with probability ``1 - beta_k`` (else the
   teacher's), and the teacher's action is stored for the student's observation, so the dataset covers the
   states the student itself reaches. ``beta_k = beta_decay ** k``.
3. After each collection, the student is trained for ``epochs`` passes over the whole aggregate (MSE between its
   deterministic action and the teacher's).

The student is the network of a PPO baseline config (``student``), held in that config's stable-baselines3
model so the result is an ordinary checkpoint: the common evaluator flies it, ``export_onnx`` exports it, and
PPO can fine-tune it. By default it is the paper's network (``vision-ppo``: state MLP + depth CNN → GRU(256) →
[192, 96]); ``vision-no-gru`` gives the feed-forward ablation. Training seeds are below the evaluation seeds.
Depth images are stored as uint8 (1/255 steps of normalised inverse depth, below the 0.02 depth noise).

A recurrent student is trained with truncated backpropagation through time. The aggregate keeps each
episode's steps contiguous (a *run*; :meth:`Dataset.add_segment`), cut into chunks of ``sequence_length``
steps (:meth:`Dataset.chunks`) that never cross an episode boundary. Before each fit the current student
runs, without gradient, through every run in order to give each chunk the GRU state it starts from (zero at
an episode's first step; :func:`chunk_start_states`), then minibatches of chunks are unrolled from those
states with the gradient flowing through at most ``sequence_length`` steps.

Optionally (``keep_iterations``, ``final_student``) the students of the last iterations are kept and the run's
checkpoint is their weight average, or whichever of them (or of the average) the student alone flies best on
validation scenes (``select_episodes``; :func:`choose_student`). DAgger itself (and a resumption) always continues
from the last iteration's student.
"""

from __future__ import annotations

import json
import shutil
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pandas as pd
import torch
from tqdm.auto import tqdm

from racebench.agents.base import BUILTIN_VERSIONS
from racebench.agents.loading import load_agent
from racebench.agents.planner import FastPlannerAgent, PlannerAgent
from racebench.agents.trust import own_policy_trust, record_written
from racebench.evaluation.evaluator import Evaluator
from racebench.training.dagger.collection import collect, make_path_head
from racebench.training.dagger.config import DaggerConfig
from racebench.training.dagger.dataset import Dataset
from racebench.training.dagger.fitting import fit, iteration_learning_rate
from racebench.training.dagger.resume import (
    KEPT_DIR,
    RESUME_DIR,
    _json_safe,
    load_resume_state,
    restore_state,
    save_resume_state,
)
from racebench.training.dagger.selection import choose_student
from racebench.training.ppo import archive_finished_part
from racebench.training.student import is_recurrent, make_student
from racebench.utils.files import atomic_write


def training_env_ids(config: DaggerConfig) -> list[str]:
    """The id each of the ``n_envs`` training envs flies: the config's id (default ``RaceObs-<track>-v0``), or with
    ``train_tracks`` the main id of each listed track in turn."""
    if config.train_tracks:
        return [f"RaceObs-{config.train_tracks[i % len(config.train_tracks)]}-v0" for i in range(config.n_envs)]
    return [config.env_id or f"RaceObs-{config.track}-v0"] * config.n_envs


def make_training_envs(config: DaggerConfig) -> list[gym.Env]:
    """The ``n_envs`` training envs (:func:`training_env_ids`) with ray-cast depth and the config's gate shifts
    (scene seeds are set per episode by the collector)."""
    shifts = {"gate_shift": config.gate_shift, "gate_shift_z": config.gate_shift_z}
    return [gym.make(env_id, obs_mode="vision", renderer="raycast", **shifts) for env_id in training_env_ids(config)]


def make_teacher(config: DaggerConfig) -> PlannerAgent | FastPlannerAgent:
    """The config's teacher: the named privileged built-in; planner-fast with the config's ``teacher_*`` settings."""
    if config.teacher == "planner-fast":
        return FastPlannerAgent(
            gate_clearance=config.teacher_gate_clearance,
            wanted_clearance=config.teacher_wanted_clearance,
            integral_gain=config.teacher_integral_gain,
            replan_distance=config.teacher_replan_distance,
            obstacle_knowledge=config.teacher_obstacles,
        )
    return load_agent(config.teacher)


def distill(config: DaggerConfig, out: str | Path, eval_episodes: int = 10, resume: bool = False) -> dict[str, Any]:
    """Run DAgger (see the module docstring); write the student checkpoint, ``progress.csv`` and ``summary.json``.

    After every iteration the run's state is saved in ``out/resume/``; ``resume=True`` continues from it (the
    same student, optimizer, dataset and random streams: the same result as a run never interrupted, tested).
    """
    config.validate()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    saved = load_resume_state(out, config) if resume else None
    if resume and saved is None:
        raise ValueError(f"dagger: nothing to resume in {out} (no {RESUME_DIR}/state.json): run it without resume")
    if config.train_tracks and config.track not in config.train_tracks:
        raise ValueError(f"dagger: the run's track {config.track!r} is not one of train_tracks {config.train_tracks}")
    env_id = config.env_id or f"RaceObs-{config.track}-v0"
    # the final evaluation: the run's id first, then the other training tracks' main ids
    eval_ids = list(dict.fromkeys([env_id, *training_env_ids(config)]))
    groups = [eid.split("-")[1] for eid in training_env_ids(config)] if config.train_tracks else None
    made = make_training_envs(config)
    envs = [m.unwrapped for m in made]
    teachers = [make_teacher(config) for _ in envs]
    # The student's initial weights come out of LAPACK (orthogonal init), whose last bits depend on the thread
    # count: fix it here, not wherever the caller left it, so a run and its resumption build the same student.
    torch.set_num_threads(config.update_threads)
    torch.manual_seed(config.seed)
    rng = np.random.default_rng(config.seed)
    policy_model = make_student(made[0], config.seed, config.student)
    policy = policy_model.policy
    path_head = None
    if config.path_aux_weight > 0:
        if not is_recurrent(policy):
            raise ValueError(f"dagger: path_aux_weight reads a GRU's output; student {config.student!r} has none")
        path_head = make_path_head(policy.lstm_actor.hidden_size)  # after the student: its weights are unchanged
    parameters = list(policy.parameters()) + ([] if path_head is None else list(path_head.parameters()))
    optimizer = (
        torch.optim.AdamW(parameters, lr=config.learning_rate, weight_decay=config.weight_decay)
        if config.weight_decay > 0
        else torch.optim.Adam(parameters, lr=config.learning_rate)
    )
    dataset = Dataset(config.max_samples, envs[0].camera.size)
    seeds = [config.seed * 1000]  # training seeds, far below the evaluation seeds
    failed: list[int] = []  # training scenes queued for replay (DaggerConfig.replay_failed)
    rows: list[dict[str, Any]] = []
    first, offset = 0, 0.0
    if saved is None:  # a fresh run: students another run kept in this folder must not become candidates
        shutil.rmtree(out / KEPT_DIR, ignore_errors=True)
    else:
        restore_state(saved, policy_model, optimizer, dataset, rng, path_head)
        seeds, rows = saved["seeds"], saved["rows"]
        failed = list(saved.get("failed", []))  # a state saved before replay existed queued none
        # A finished run extended to more iterations: its summary.json and eval/ are the old checkpoint's. Moved
        # aside (summary-<n>-steps.json, eval-<n>-steps/), they stay on record and the final evaluation can run.
        archive_finished_part(out, int(rows[-1]["env_steps"]) if rows else 0)
        first, offset = saved["iteration"] + 1, float(rows[-1]["wall_s"]) if rows else 0.0
    started = time.perf_counter() - offset  # wall clock over the resumed parts
    for k in tqdm(range(first, config.iterations), desc="dagger", unit="it", initial=first, total=config.iterations):
        beta = config.beta_decay**k
        torch.set_num_threads(1)
        tick = time.perf_counter()
        flown = collect(envs, teachers, policy, beta, config.steps_per_iteration, rng, seeds, dataset,
                        config.crash_weight, config.crash_window, config.replay_failed, failed,
                        config.aux_task if path_head is not None else None, groups)  # fmt: skip
        torch.set_num_threads(config.update_threads)
        collected = time.perf_counter()
        learning_rate = iteration_learning_rate(config, k)
        for group in optimizer.param_groups:
            group["lr"] = learning_rate
        aux_losses: list[float] = []
        frozen = config.freeze_features_after is not None and k >= config.freeze_features_after
        loss = fit(policy, dataset, config, optimizer, rng, path_head, aux_losses, frozen_features=frozen)
        if path_head is not None:  # the auxiliary task's loss over the last pass (m²)
            flown["aux_loss"] = float(np.mean(aux_losses)) if aux_losses else float("nan")
        # where an iteration's time goes: flying (teacher, student, envs) against fitting (grows with the aggregate)
        flown["collect_s"], flown["fit_s"] = round(collected - tick, 1), round(time.perf_counter() - collected, 1)
        # env_steps: every step flown so far (samples, the aggregate's size, stops growing at max_samples)
        flown["env_steps"] = flown.pop("steps") + (int(rows[-1].get("env_steps", rows[-1]["samples"])) if rows else 0)
        rows.append({"iteration": k, "beta": beta, **flown, "samples": dataset.size, "loss": loss,
                     "learning_rate": learning_rate, "wall_s": round(time.perf_counter() - started, 1)})  # fmt: skip
        atomic_write(out / "progress.csv", pd.DataFrame(rows).to_csv(index=False))
        # The student after every iteration, so a killed run leaves its latest policy behind.
        policy_model.save(out / f"{config.name}-{config.track}.zip")
        record_written(out, out / f"{config.name}-{config.track}.zip")  # so its evaluation (a sweep's) trusts it
        if k >= config.iterations - config.keep_iterations:
            (out / KEPT_DIR).mkdir(exist_ok=True)
            policy_model.save(out / KEPT_DIR / f"{config.name}-{config.track}-it{k:03d}.zip")
        save_resume_state(out, k, policy_model, optimizer, dataset, rng, seeds, rows, config, failed, path_head)
    checkpoint = out / f"{config.name}-{config.track}.zip"
    selection = None
    try:
        if config.keep_iterations > 0 and (config.select_episodes > 0 or config.final_student != "last"):
            selection = choose_student(out, config, policy_model, envs, (config.seed * 1000, seeds[0]))
            policy_model.save(checkpoint)  # the last iteration's student stays in iterations/
            record_written(out, checkpoint)
    finally:
        for m in made:
            m.close()
    summary: dict[str, Any] = {
        "method": "dagger",
        "teacher": config.teacher,
        "teacher_version": BUILTIN_VERSIONS[config.teacher],  # a bumped built-in plans and flies differently
        "student": config.student,
        "config": asdict(config),
        "checkpoint": str(checkpoint),
        "wall_s": round(time.perf_counter() - started, 1),
        "env_steps": int(rows[-1]["env_steps"]),
        "timesteps": int(rows[-1]["env_steps"]),  # as a PPO run's summary.json says it
        "last": rows[-1],
    }
    if selection is not None:
        summary["selection"] = selection
    if eval_episodes > 0:
        result = Evaluator(  # this run's own checkpoint: trusted if what the evaluator loads is what the run wrote
            str(checkpoint), eval_ids, episodes=eval_episodes, out_dir=out / "eval",
            trust_code=own_policy_trust(out, checkpoint),
        ).run(progress=False)  # fmt: skip
        columns = ("n", "successes", "success_rate", "lap_time_mean")
        own = result[result["env_id"] == env_id].iloc[0]  # the summary's rows are sorted by id
        summary["eval"] = {k: float(own[k]) for k in columns}
        if len(eval_ids) > 1:  # a student of several tracks: each track's main id
            per_id = result.set_index("env_id")
            summary["eval_tracks"] = {eid: {k: float(per_id.loc[eid, k]) for k in columns} for eid in eval_ids}
    summary = _json_safe(summary)
    (out / "summary.json").write_text(json.dumps(summary, indent=2, allow_nan=False))
    return summary
