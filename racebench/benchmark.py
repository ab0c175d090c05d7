"""Throughput benchmark (``racebench bench``): depth frames/s, env steps/s, training samples/s, peak memory.

One run measures, on this machine:

* depth frames/s of PyBullet's ``getCameraImage`` (TinyRenderer) and of the ray caster on the *same* poses
  (random poses in real episode scenes, biased to be close to obstacles and inside gate openings), the ray
  caster one camera per call (as a single env) and all cameras in one call (as a vector env), their ratio,
  and how well the two images agree on those poses;
* env steps/s for ``obs_mode="state"`` and ``"vision"``: a single env (vision with either renderer), and a
  :class:`~racebench.envs.vector.RaceVectorEnv` (ray caster) in one process and over two worker processes;
* training samples/s end to end (rollout + PPO update) of the ``state-ppo`` and ``vision-ppo`` baselines as
  configured, ``vision-ppo`` with either depth renderer (their ratio), and the share spent in the update;
* evaluation steps/s of the committed ``vision-ppo`` checkpoint (either renderer) and ``state-ppo`` flown in
  lockstep, against the same episodes' actions replayed in one env alone (their ratio), and the policy call
  at batch 1 and 64 on one and two torch threads;
* the step cost of each robustness perturbation (``RaceObs-<track>-<name>-v0``) against its main id, same run;
* the cost of each part of a step (physics substep, collision check, state observation, depth render, noise);
* the CPU time per env step of each vector-env run, summed over its processes (unlike steps/s, not
  lowered by other processes sharing the cores);
* peak resident memory of this process and of the worker processes;
* the machine's load average before and after (other processes share the cores and slow every number).

Everything is printed and written to a CSV (one row per measurement: section, name, value, unit).
``quick=True`` shrinks every run to a few hundred steps for a smoke test.
"""

from __future__ import annotations

import csv
import dataclasses
import math
import os
import platform
import resource
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from racebench.agents.export import export_onnx
from racebench.agents.loading import load_agent
from racebench.agents.planner import FastPlannerAgent
from racebench.envs.env import RaceEnv
from racebench.envs.perturbations import ROBUSTNESS
from racebench.envs.vector import RaceVectorEnv
from racebench.evaluation.protocol import EVAL_SEED_BASE, env_id_of
from racebench.evaluation.rollout import run_lockstep
from racebench.evaluation.worker import SingleTorchThread
from racebench.sim.raycast import BatchDepthRenderer
from racebench.sim.scene import Scene
from racebench.training.callbacks import ThreadsCallback
from racebench.training.config import TrainConfig
from racebench.training.models import make_envs, make_model

# The targets, measured on a 2-core machine (not lowered here when a run misses them).
TARGET_RENDER_RATIO = 10.0
TARGET_VISION_STEPS = 4000.0  # steps/s, vectorized over 2 processes
TARGET_STATE_STEPS = 10000.0  # steps/s, vectorized over 2 processes
TARGET_VISION_TRAINING = 1500.0  # samples/s, vision-ppo end to end (env + update)
TARGET_ROBUSTNESS_COST = 1.5  # a perturbation's cost per simulated second over its main id's, same run
# Training end to end over the vector env's own steps/s (2 processes) in the same run: hosts differ ~2x.
TARGET_VISION_TRAINING_RATIO = 0.25
TARGET_STATE_TRAINING_RATIO = 0.3
TARGET_EVALUATION_RATIO = 0.7  # an evaluation over the same env stepped alone


@dataclass
class BenchSettings:
    """Sizes of one benchmark run (``quick()`` for a smoke test)."""

    track: str = "S"
    scenes: int = 4  # episode scenes the depth poses are drawn in
    poses_per_scene: int = 150
    single_steps: int = 3000  # steps of each single-env measurement
    vector_envs: int = 32  # envs of each vector-env measurement
    vector_steps: int = 150  # vector steps (each steps every env) per measurement
    train_updates: int = 3  # timed PPO updates (rollout + update) of each training measurement, after one warm-up
    train_small: bool = False  # shrink the training configs to 4 envs x 16 steps (smoke test)
    eval_episodes: int = 128  # episodes of each evaluation measurement (an evaluation flies its own in one lockstep)
    eval_batch: int = 64  # lockstep width of the evaluation measurements (the evaluator's default)
    seed: int = 0
    # The evaluation of the committed checkpoints and end-to-end training take minutes whatever their sizes
    # (checkpoint loading, ONNX export, PPO model builds); a run without them has no targets to judge either.
    evaluation_and_training: bool = True

    @classmethod
    def quick(cls) -> BenchSettings:
        """A smoke test of about 10 s: depth, env steps, vector envs, parts and memory at tiny sizes (numbers only
        indicative); no evaluation, no training, and no verdicts against the targets."""
        return cls(
            evaluation_and_training=False,
            scenes=1,
            poses_per_scene=30,
            single_steps=100,
            vector_envs=4,
            vector_steps=25,
            train_updates=1,
            train_small=True,
            eval_episodes=4,
            eval_batch=4,
        )


# ------------------------------------------------------------------ poses
def rotation_from_euler(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """Body → world rotation ``Rz(yaw) Ry(pitch) Rx(roll)``."""
    cy, sy, cp, sp = math.cos(yaw), math.sin(yaw), math.cos(pitch), math.sin(pitch)
    cr, sr = math.cos(roll), math.sin(roll)
    return np.array([
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ])  # fmt: skip


def sample_camera_poses(
    scene: Scene, n: int, rng: np.random.Generator, clearance: float = 0.12, tilt: float = 0.6
) -> tuple[np.ndarray, np.ndarray]:
    """``n`` drone poses ``(positions (n, 3), rotations (n, 3, 3))`` in ``scene`` for renderer comparisons.

    A third each: anywhere in the arena; close to a random gate bar or obstacle (its surface 0–0.5 m beyond
    ``clearance``, mostly facing it); inside or near a gate opening, roughly along the gate normal. Roll and
    pitch uniform in ±``tilt``. Every drone centre is at least ``clearance`` (the collision radius) from all
    primitives and 0.15 m above the ground, i.e. a pose the drone can reach without touching anything.
    """
    low, high = scene.arena_low, scene.arena_high
    prims = [(c, np.asarray(h, dtype=float), 0.0) for c, h, _ in scene.boxes()]
    prims += [(c, np.array([0.0, 0.0, height / 2.0]), r) for c, r, height in scene.cylinders()]
    positions, rotations = [], []
    while len(positions) < n:
        kind = int(rng.integers(3))
        yaw = rng.uniform(-math.pi, math.pi)
        if kind == 0:
            pos = rng.uniform(low + np.array([0.0, 0.0, 0.15]), high)
        elif kind == 1:
            centre, half, radius = prims[int(rng.integers(len(prims)))]
            angle = rng.uniform(-math.pi, math.pi)
            reach = max(half[0], half[1]) + radius + clearance + rng.uniform(0.0, 0.5)
            height = rng.uniform(-half[2] - 0.3, half[2] + 0.3)
            pos = centre + np.array([reach * math.cos(angle), reach * math.sin(angle), height])
            yaw = angle + math.pi + rng.uniform(-1.2, 1.2)  # mostly looking at it
        else:
            gate = scene.gates[int(rng.integers(len(scene.gates)))]
            along, side, up = rng.uniform([-0.6, -0.4, -0.4], [0.6, 0.4, 0.4])
            pos = gate.center + along * gate.normal + side * gate.lateral + np.array([0.0, 0.0, up])
            yaw = gate.yaw + rng.uniform(-1.0, 1.0) + (math.pi if rng.random() < 0.2 else 0.0)
        if pos[2] < 0.15 or np.any(pos < low) or np.any(pos > high) or scene.point_distance(*pos) < clearance:
            continue
        positions.append(pos)
        rotations.append(rotation_from_euler(yaw, rng.uniform(-tilt, tilt), rng.uniform(-tilt, tilt)))
    return np.array(positions), np.array(rotations)


def depth_agreement(reference: np.ndarray, other: np.ndarray, camera: Any) -> tuple[float, float]:
    """(mean |Δ normalised inverse depth|, fraction of pixels within 2 % of the reference) of two depth stacks."""
    a = camera.min_depth / reference.astype(np.float64)
    b = camera.min_depth / other.astype(np.float64)
    diff = np.abs(a - b)
    return float(diff.mean()), float(np.mean(diff <= 0.02 * a))


# ------------------------------------------------------------------ measurements
class _Recorder:
    """Collects rows, prints each as it comes."""

    def __init__(self, echo: Callable[[str], None]) -> None:
        self.rows: list[dict[str, Any]] = []
        self.echo = echo

    def add(self, section: str, name: str, value: float, unit: str, note: str = "") -> float:
        self.rows.append({"section": section, "name": name, "value": value, "unit": unit, "note": note})
        shown = f"{value:,.0f}" if abs(value) >= 100 else f"{value:.4g}"
        self.echo(f"  {name:<44s} {shown:>12s} {unit}{'   ' + note if note else ''}")
        return value


def _load() -> str:
    return "/".join(f"{v:.2f}" for v in os.getloadavg()) if hasattr(os, "getloadavg") else "n/a"


def _bench_depth(rec: _Recorder, s: BenchSettings) -> None:
    env = RaceEnv(track=s.track, obs_mode="vision", depth_noise_std=0.0)
    rng = np.random.default_rng(s.seed)
    caster = BatchDepthRenderer(env.camera)
    scenes, positions, rotations, reference = [], [], [], []
    pybullet_time = 0.0
    for k in range(s.scenes):
        env.reset(seed=s.seed + k)  # loads the scene into PyBullet
        pos, rot = sample_camera_poses(env.scene, s.poses_per_scene, rng)
        start = time.perf_counter()
        reference += [env.camera.depth(env.sim.client, p, r) for p, r in zip(pos, rot, strict=True)]
        pybullet_time += time.perf_counter() - start
        scenes += [env.scene] * len(pos)
        positions.append(pos)
        rotations.append(rot)
    positions, rotations, reference = np.concatenate(positions), np.concatenate(rotations), np.stack(reference)
    n = len(positions)
    caster.render(scenes[:1], positions[:1], rotations[:1])  # compile (or load the cache) outside the timing
    start = time.perf_counter()
    for i in range(n):
        caster.render(scenes[i : i + 1], positions[i : i + 1], rotations[i : i + 1])
    single_time = time.perf_counter() - start
    batched = caster.render(scenes, positions, rotations)  # packs the scenes' geometry once, as a vector env does
    start = time.perf_counter()
    caster.render(scenes, positions, rotations, out=batched)
    batch_time = time.perf_counter() - start
    env.close()
    pybullet_fps = rec.add("depth", "pybullet getCameraImage (TinyRenderer)", n / pybullet_time, "frames/s")
    single_fps = rec.add("depth", "raycast, one camera per call", n / single_time, "frames/s")
    batch_fps = rec.add("depth", f"raycast, {n} cameras in one call", n / batch_time, "frames/s")
    rec.add("depth", "ratio raycast (per call) / pybullet", single_fps / pybullet_fps, "x")
    rec.add("depth", "ratio raycast (batched) / pybullet", batch_fps / pybullet_fps, "x")
    mean_diff, within = depth_agreement(reference, batched, env.camera)
    rec.add("depth", "agreement: mean |d inverse depth|", mean_diff, "", f"{n} poses, limit 0.01")
    rec.add("depth", "agreement: pixels within 2 %", 100.0 * within, "%", "limit 98 %")


def _policy(n_envs: int, steps: int, hover: float, seed: int) -> np.ndarray:
    """Hover plus noise: episodes last seconds (a mix of flight, crashes and resets, like training)."""
    rng = np.random.default_rng(seed)
    actions = rng.normal(0.0, 0.15, size=(steps, n_envs, 4)).astype(np.float32)
    actions[..., 0] += hover
    return np.clip(actions, -1.0, 1.0)


def _bench_single(rec: _Recorder, s: BenchSettings, obs_mode: str, renderer: str) -> float:
    env = RaceEnv(track=s.track, obs_mode=obs_mode, renderer=renderer)
    env.reset(seed=s.seed)
    actions = _policy(1, s.single_steps + 20, env.params.hover_action, s.seed)[:, 0]
    for a in actions[:20]:  # warm-up (numba cache, allocations)
        env.step(a)
    episodes = 0
    start = time.perf_counter()
    for a in actions[20:]:
        _, _, terminated, truncated, _ = env.step(a)
        if terminated or truncated:
            env.reset()
            episodes += 1
    rate = s.single_steps / (time.perf_counter() - start)
    env.close()
    name = f"single env, {obs_mode}" + (f", {renderer}" if obs_mode == "vision" else "")
    note = f"{episodes} resets included ({s.single_steps / episodes:.0f} steps an episode)" if episodes else "no reset"
    return rec.add("steps", name, rate, "steps/s", note)


def _bench_robustness(rec: _Recorder, s: BenchSettings) -> None:
    """Single-env vision steps/s (ray caster: its cheap frame shows an overhead most) of the main id and each robustness
    id: hover plus noise from the same seed, resets untimed, the ids stepped in turn a tenth at a time (load changes
    hit each alike); cost = the id's time per step over the main id's, and per simulated second (judged)."""
    ids = {n: env_id_of(s.track, "default" if n == "main" else n) for n in ("main", *ROBUSTNESS)}
    envs = {n: gym.make(env_id, obs_mode="vision", renderer="raycast").unwrapped for n, env_id in ids.items()}
    actions = {n: _policy(1, s.single_steps + 20, env.params.hover_action, s.seed)[:, 0] for n, env in envs.items()}
    elapsed = dict.fromkeys(envs, 0.0)
    for env in envs.values():
        env.reset(seed=s.seed)
    for chunk in np.array_split(np.arange(s.single_steps + 20), 10):
        for name, env in envs.items():
            for i in chunk:
                start = time.perf_counter()
                over = any(env.step(actions[name][i])[2:4])
                elapsed[name] += (time.perf_counter() - start) * (i >= 20)  # 20 warm-up steps
                if over:
                    env.reset()
    for name, env in envs.items():
        rec.add("robustness", f"{ids[name]}, vision, raycast", s.single_steps / elapsed[name], "steps/s",
                f"{env.control_freq} Hz control")  # fmt: skip
        env.close()
        if name != "main":
            rec.add("robustness", f"cost {name} / main, per step", elapsed[name] / elapsed["main"], "x")
            per_second = elapsed[name] / elapsed["main"] * env.control_freq / envs["main"].control_freq
            verdict = f"<= {TARGET_ROBUSTNESS_COST:g}: {'met' if per_second <= TARGET_ROBUSTNESS_COST else 'MISSED'}"
            rec.add("robustness", f"cost {name} / main, per second flown", per_second, "x",
                    verdict if s.evaluation_and_training else "")  # no verdict on --quick's tiny sizes  # fmt: skip


def _bench_vector(rec: _Recorder, s: BenchSettings, obs_mode: str, processes: int, peaks: dict[str, float]) -> float:
    venv = RaceVectorEnv(s.vector_envs, num_processes=processes, track=s.track, obs_mode=obs_mode, renderer="raycast")
    try:
        venv.reset(seed=s.seed)
        hover = venv.get_attr("params")[0].hover_action
        actions = _policy(s.vector_envs, s.vector_steps + 5, hover, s.seed)
        for a in actions[:5]:
            venv.step(a)
        cpu_before = sum(_cpu_seconds(pid) for pid in venv.process_ids)
        start = time.perf_counter()
        for a in actions[5:]:
            venv.step(a)
        elapsed = time.perf_counter() - start
        cpu = sum(_cpu_seconds(pid) for pid in venv.process_ids) - cpu_before
        for pid in venv.process_ids[1:]:
            peaks[f"worker {pid}"] = _peak_rss_mb(pid)
    finally:
        venv.close()
    steps = s.vector_envs * s.vector_steps
    where = "1 process" if processes == 1 else f"{processes} processes"
    name = f"vector env, {obs_mode}, {s.vector_envs} envs, {where}"
    # CPU time of all its processes per env step: what the run cost whatever else shared the cores.
    rec.add("cpu", name, cpu / steps * 1e6, "us CPU/step", "all processes")
    return rec.add("steps", name, steps / elapsed, "steps/s")


def _bench_training(rec: _Recorder, s: BenchSettings) -> dict[str, float]:
    """End-to-end training samples/s (env + PPO update) of the ``state-ppo`` and ``vision-ppo`` baselines as
    configured (``vision-ppo`` with both depth renderers), and the share of time spent in the update."""
    import torch
    from stable_baselines3.common.callbacks import BaseCallback, CallbackList

    class PhaseTimer(BaseCallback):
        """Seconds spent in PPO updates: from each rollout's end to the next rollout's start."""

        def __init__(self) -> None:
            super().__init__(0)
            self.update_s, self.mark = 0.0, 0.0

        def _on_rollout_start(self) -> None:
            if self.mark:
                self.update_s += time.perf_counter() - self.mark

        def _on_rollout_end(self) -> None:
            self.mark = time.perf_counter()

        def _on_step(self) -> bool:
            return True

    rates: dict[str, float] = {}
    threads = torch.get_num_threads()
    runs = [("state-ppo", "raycast"), ("vision-ppo", "raycast"), ("vision-ppo", "pybullet")]
    runs.append(("vision-ppo-fast", "raycast"))  # the variant (not the default): its ratio beside the default's
    for name, renderer in runs:
        config = dataclasses.replace(TrainConfig.from_yaml(name), renderer=renderer)
        if s.train_small:
            config = dataclasses.replace(config, n_envs=4, n_steps=16, batch_size=32)
        per_update = config.n_envs * config.n_steps
        torch.set_num_threads(config.torch_threads)
        env = make_envs(config, s.track, s.seed)
        try:
            model = make_model(config, env, s.seed, None)
            model.learn(per_update, callback=ThreadsCallback(config.torch_threads, config.update_threads))
            timer = PhaseTimer()
            callbacks = CallbackList([ThreadsCallback(config.torch_threads, config.update_threads), timer])
            start = time.perf_counter()
            model.learn(per_update * s.train_updates, callback=callbacks, reset_num_timesteps=False)
            elapsed = time.perf_counter() - start
        finally:
            env.close()
            torch.set_num_threads(threads)
        label = f"{name}" + (f", {renderer} depth" if config.obs_mode == "vision" else "")
        setup = f"{config.n_envs} envs x {config.n_steps} steps, {config.num_processes} processes"
        rates[label] = rec.add("training", label, per_update * s.train_updates / elapsed, "samples/s", setup)
        timer._on_rollout_start()  # close the last update
        rec.add("training", f"{label}: share of time in PPO updates", 100 * timer.update_s / elapsed, "%")
    ratio = rates["vision-ppo, raycast depth"] / rates["vision-ppo, pybullet depth"]
    rec.add("training", "ratio vision-ppo raycast / pybullet", ratio, "x", "same config, same run")
    return rates


EVAL_CHECKPOINTS: dict[str, str] = {
    "vision": "baselines/checkpoints/vision-ppo-S/vision-ppo-S.zip",
    "state": "baselines/checkpoints/state-ppo-S/state-ppo-S.zip",
}


def _checkpoint(name: str) -> Path | None:
    """A committed checkpoint, found beside the installed package (a source checkout), else ``None``."""
    path = Path(__file__).resolve().parents[1] / EVAL_CHECKPOINTS[name]
    return path if path.is_file() else None


class _ActionLog:
    """Env factory for a lockstep evaluation that logs every action per seed (to replay them alone)."""

    def __init__(self, obs_mode: str, renderer: str) -> None:
        self.obs_mode, self.renderer = obs_mode, renderer
        self.clear()

    def clear(self) -> None:
        """Forget what was logged."""
        self.actions: dict[int, list[np.ndarray]] = {}
        self.steps = 0

    def done(self, env_id: str, seed: int, result: dict[str, Any], flown: Any) -> None:
        """Count the episode's steps."""
        self.steps += result["steps"]

    def make_env(self, env_id: str) -> Any:
        """A ``gym.make`` env whose ``reset_state``/``advance`` log the seed and the actions."""
        env = gym.make(env_id, obs_mode=self.obs_mode, renderer=self.renderer)
        raw = env.unwrapped
        reset_state, advance = raw.reset_state, raw.advance
        current: list[int] = []

        def logged_reset(*, seed: int | None = None, options: Any = None) -> dict:
            current[:] = [seed]
            self.actions[seed] = []
            return reset_state(seed=seed, options=options)

        def logged_advance(action: np.ndarray) -> tuple:
            self.actions[current[0]].append(np.array(action))
            return advance(action)

        raw.reset_state, raw.advance = logged_reset, logged_advance
        return env


def _bench_evaluation(rec: _Recorder, s: BenchSettings) -> dict[str, float]:
    """Evaluation of the committed checkpoints in lockstep (one process) against the same env stepped alone.

    The lockstep run records every action; "env alone" replays exactly those actions, open loop, in one env:
    the same episodes, so the same simulator work, without the policy. Their ratio is the evaluation's
    efficiency. Also the policy call itself at batch 1 and 64 on one and two torch threads (the evaluator
    runs one thread per process: :func:`racebench.evaluation.worker.torch_threads`).
    """
    import torch

    ratios: dict[str, float] = {}
    env_id, episodes, width = f"RaceObs-{s.track}-v0", s.eval_episodes, s.eval_batch

    exported = Path(tempfile.mkdtemp(prefix="racebench-bench-"))
    runs = []
    for kind, renderers in (("vision", ("pybullet", "raycast")), ("state", ("pybullet",))):
        path = _checkpoint(kind)
        if path is None:
            rec.echo(f"  (no committed {kind} checkpoint beside this install: evaluation rows skipped)")
            continue
        torch_agent = load_agent(str(path))
        onnx_path = export_onnx(torch_agent.model, exported / f"{path.stem}.onnx", torch_agent.normalizer)
        runs += [
            (kind, renderers, path.stem, torch_agent),
            (kind, renderers, f"{path.stem} (ONNX)", load_agent(str(onnx_path))),
        ]
    for kind, renderers, stem, agent in runs:
        for renderer in renderers:
            log = _ActionLog(agent.obs_mode, renderer)
            jobs = [(env_id, EVAL_SEED_BASE + i) for i in range(episodes)]
            # Warm-up, which also builds the envs: an evaluation process keeps them between its tasks.
            pool: dict[str, list] = {}
            run_lockstep(agent, jobs[:width], log.make_env, log.done, width=width, pool=pool)
            log.clear()
            with SingleTorchThread():
                start = time.perf_counter()
                run_lockstep(agent, jobs, log.make_env, log.done, width=width, pool=pool)
                lockstep = log.steps / (time.perf_counter() - start)
            for envs in pool.values():
                for env in envs:
                    env.close()
            actions = log.actions
            env = gym.make(env_id, obs_mode=agent.obs_mode, renderer=renderer)
            start = time.perf_counter()
            for seed, taken in actions.items():
                env.reset(seed=seed)
                for action in taken:
                    env.step(action)
            alone = sum(len(a) for a in actions.values()) / (time.perf_counter() - start)
            env.close()
            label = f"{stem}, {renderer} depth" if kind == "vision" else stem
            rec.add("evaluation", f"env alone, {label} episodes replayed", alone, "steps/s", f"{episodes} episodes")
            rec.add("evaluation", f"evaluation of {label}, lockstep {width}", lockstep, "steps/s", "1 process")
            ratios[label] = rec.add("evaluation", f"ratio evaluation / env alone, {label}", lockstep / alone, "x",
                                    "target >= 0.7")  # fmt: skip
        if kind == "vision" and "ONNX" not in stem:
            threads = torch.get_num_threads()
            probe = gym.make(env_id, obs_mode="vision", renderer="raycast")
            obs, _ = probe.reset(seed=EVAL_SEED_BASE)
            probe.close()
            for batch in (1, 64):
                for n_threads in (1, 2):
                    torch.set_num_threads(n_threads)
                    agent.start(batch)
                    agent.act_batch([obs] * batch)
                    reps = max(20, s.single_steps // 30)
                    start = time.perf_counter()
                    for _ in range(reps):
                        agent.act_batch([obs] * batch)
                    per_call = (time.perf_counter() - start) / reps * 1e3
                    rec.add("evaluation", f"policy call, batch {batch}, {n_threads} torch thread(s)", per_call, "ms")
            torch.set_num_threads(threads)
    return ratios


def _cpu_seconds(pid: int) -> float:
    """User + system CPU time (s) so far of process ``pid`` (Linux ``/proc``; this process anywhere)."""
    if pid == os.getpid():
        usage = resource.getrusage(resource.RUSAGE_SELF)
        return usage.ru_utime + usage.ru_stime
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return math.nan


def _peak_rss_mb(pid: int | None = None) -> float:
    """Peak resident memory (MB) of this process (``pid=None``) or of process ``pid`` (Linux ``VmHWM``)."""
    if pid is None:
        scale = 1.0 / 1024.0 if platform.system() == "Linux" else 1.0 / 2**20  # KB on Linux, bytes on macOS
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * scale
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return float(line.split()[1]) / 1024.0
    except OSError:
        pass
    return math.nan


def _bench_parts(rec: _Recorder, s: BenchSettings) -> None:
    """Cost of each part of a vision step (ray caster), per call, from the env's own functions."""
    env = RaceEnv(track=s.track, obs_mode="vision", renderer="raycast")
    env.reset(seed=s.seed)
    reps = max(s.single_steps // 4, 50)
    hover = np.array([env.params.hover_action, 0.0, 0.0, 0.0], dtype=np.float32)

    def per_call(fn: Callable[[], Any]) -> float:
        fn()
        start = time.perf_counter()
        for _ in range(reps):
            fn()
        return (time.perf_counter() - start) / reps * 1e6

    sim = env.sim
    raw = sim.raw_state
    zero = (0.0, 0.0, 0.0)
    weight = (0.0, 0.0, env.params.mass * env.params.gravity)
    substep_c = per_call(lambda: sim.step_raw(weight, zero, raw[0]))
    env.reset(seed=s.seed)
    p0 = tuple(env.drone.position.tolist())
    p1 = (p0[0] + 0.05, p0[1], p0[2])  # a 10 m/s substep
    collision = per_call(lambda: env.collision.contact(p0, p1))
    advance = per_call(lambda: env.advance(hover))
    env.reset(seed=s.seed)
    state = per_call(env._state_vector)
    render = per_call(env.depth_image)
    depth = env.depth_image()
    noise = per_call(lambda: env.camera.normalise(depth, env.np_random))
    start = time.perf_counter()
    for k in range(10):
        env.reset_state(seed=s.seed + k)
    reset = (time.perf_counter() - start) / 10 * 1e6
    # The fast expert plans at every episode start: in DAgger that is once per collected episode.

    expert = FastPlannerAgent()
    plans = 3 if s.single_steps < 400 else 10
    env.reset_state(seed=s.seed)
    expert.reset(env=env, seed=s.seed)  # warm-up: compiled kernels load, scipy's spline imports
    start = time.perf_counter()
    for k in range(plans):
        env.reset_state(seed=s.seed + k)
        expert.reset(env=env, seed=s.seed + k)
    plan = (time.perf_counter() - start) / plans * 1e6 - reset
    env.close()
    rec.add("parts", "physics substep, PyBullet calls only", substep_c, "us", "step + state query")
    rec.add("parts", "collision check (swept sphere, 1 substep)", collision, "us", "exact geometry, every substep")
    rec.add("parts", f"env.advance ({env.substeps} substeps + reward)", advance, "us")
    rec.add("parts", "collision checks / env.advance", env.substeps * collision / advance, "ratio",
            "target <= 0.10 of a step")  # fmt: skip
    rec.add("parts", "state observation", state, "us")
    rec.add("parts", "depth render (raycast, 1 camera)", render, "us")
    rec.add("parts", "depth normalise + Gaussian noise", noise, "us", "4096 normal draws")
    rec.add("parts", "reset (new scene: obstacles + corridor check)", reset, "us")
    rec.add("parts", "planner-fast plan at reset (path, smoothing, speeds)", plan, "us", f"{plans} scenes, minus reset")


def run_benchmark(
    settings: BenchSettings | None = None,
    out: str | Path | None = "bench.csv",
    echo: Callable[[str], None] = print,
) -> list[dict[str, Any]]:
    """Run every measurement, print it, write the rows to ``out`` (CSV; ``None``: no file); return the rows."""
    s = settings or BenchSettings()
    rec = _Recorder(echo)
    load_before = _load()
    echo(f"racebench bench: track {s.track}, {os.cpu_count()} CPUs, load average {load_before} (1/5/15 min)")
    started = time.perf_counter()
    echo("depth renderers, same poses:")
    _bench_depth(rec, s)
    echo("env steps:")
    _bench_single(rec, s, "state", "pybullet")
    _bench_single(rec, s, "vision", "pybullet")
    _bench_single(rec, s, "vision", "raycast")
    peaks: dict[str, float] = {}
    vector = {}
    for obs_mode in ("state", "vision"):
        for processes in (1, 2):
            vector[obs_mode, processes] = _bench_vector(rec, s, obs_mode, processes, peaks)
    training: dict[str, float] = {}
    if s.evaluation_and_training:
        echo("evaluation of the committed checkpoints (steps/s, same episodes):")
        evaluation = _bench_evaluation(rec, s)
        echo("training (env + PPO update, end to end):")
        training = _bench_training(rec, s)
    else:
        echo("evaluation and training: skipped (--quick); a full run measures them and judges the targets")
    echo("robustness suite: step cost of each perturbation against the main id (single env, same run):")
    _bench_robustness(rec, s)
    echo("parts of a step (µs per call):")
    _bench_parts(rec, s)
    echo("memory:")
    rec.add("memory", "peak RSS, this process", _peak_rss_mb(), "MB")
    if peaks:
        rec.add("memory", "peak RSS, largest worker process", max(peaks.values()), "MB")
    if s.evaluation_and_training:  # tiny sizes measure start-up costs: judging them against targets misleads
        echo("targets (2 cores):")
        ratio = next(r["value"] for r in rec.rows if r["name"] == "ratio raycast (per call) / pybullet")
        for name, value, target in (
            ("raycast / pybullet frames/s", ratio, TARGET_RENDER_RATIO),
            ("vision steps/s, vector env over 2 processes", vector["vision", 2], TARGET_VISION_STEPS),
            ("state steps/s, vector env over 2 processes", vector["state", 2], TARGET_STATE_STEPS),
            ("vision-ppo training samples/s", training["vision-ppo, raycast depth"], TARGET_VISION_TRAINING),
        ):
            verdict = "met" if value >= target else "MISSED"
            rec.add("targets", name, value, "", f">= {target:,.0f}: {verdict}")
        ratios = [
            ("vision-ppo training / vision vector env (2 processes)",
             training["vision-ppo, raycast depth"] / vector["vision", 2], TARGET_VISION_TRAINING_RATIO),
            ("state-ppo training / state vector env (2 processes)",
             training["state-ppo"] / vector["state", 2], TARGET_STATE_TRAINING_RATIO),
            ("vision-ppo-fast (variant) training / vision vector env (2 processes)",
             training["vision-ppo-fast, raycast depth"] / vector["vision", 2], TARGET_VISION_TRAINING_RATIO),
        ]  # fmt: skip
        for label, value in evaluation.items():
            ratios.append((f"evaluation / env alone: {label}", value, TARGET_EVALUATION_RATIO))
        for name, value, target in ratios:
            verdict = "met" if value >= target else "MISSED"
            rec.add("targets", name, value, "x", f">= {target:g}: {verdict}")
    load_after = _load()
    elapsed = time.perf_counter() - started
    rec.add("run", "wall time", elapsed, "s", f"load average before {load_before}, after {load_after}")
    if out is not None:
        path = Path(out)
        with path.open("w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=["section", "name", "value", "unit", "note"])
            writer.writeheader()
            writer.writerows(rec.rows)
        echo(f"wrote {path}")
    return rec.rows
