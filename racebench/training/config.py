"""A PPO training config (:class:`TrainConfig`, one baseline YAML file under ``baselines/``) and the
unknown-key check that every training config (PPO and DAgger) shares.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

from racebench.agents.planner import FastPlannerAgent
from racebench.agents.recurrent import ACTION_OUTPUTS, CNN_KINDS
from racebench.envs.registration import CURRICULUM
from racebench.envs.starts import START_MODES
from racebench.sim.obstacles import PLACEMENTS
from racebench.sim.track import BUILTIN_TRACKS
from racebench.utils.data import data_file
from racebench.utils.yamlfile import read_yaml

BASELINES: tuple[str, ...] = (
    "vision-ppo",
    "state-ppo",
    "vision-no-gru",
    "vision-no-avoid",
    "vision-one-step",
    "vision-one-step-flying",
    "vision-com",
    "vision-ppo-fast",
    "vision-distill",
    "vision-distill-ppo",
    "vision-ppo-random",
    "vision-distill-random",
)

#: What a run can train on: a paper track, or ``Random``, a new generated track per episode (``RaceObs-Random-v0``,
#: docs/unseen-tracks.md). ``Unseen`` is held out: nothing trains on it.
TRAIN_TRACKS: tuple[str, ...] = (*BUILTIN_TRACKS, "Random")
BC_TARGETS: tuple[str, ...] = ("init", "teacher")  # TrainConfig.bc_target: the frozen init_from policy, the teacher


def baseline_path(name_or_path: str | Path) -> Path:
    """Resolve a built-in baseline name (:data:`BASELINES`) or a YAML file path to a path."""
    if str(name_or_path) in BASELINES:
        return data_file("baselines", str(name_or_path))
    path = Path(name_or_path)
    if not path.is_file():
        raise ValueError(
            f"config {str(name_or_path)!r} is neither a built-in baseline {BASELINES} nor an existing file"
        )
    return path


def check_keys(path: str | Path, data: dict[str, Any], cls: type) -> None:
    """The checks every training config file shares: no key that ``cls`` (a config dataclass) lacks, a ``name``."""
    known = {f.name for f in fields(cls)}
    unknown = sorted(set(data) - known)
    if unknown:
        raise ValueError(f"{path}: unknown key {unknown[0]!r} (known: {sorted(known)})")
    if "name" not in data:
        raise ValueError(f"{path}: missing key 'name'")


@dataclass
class TrainConfig:
    """A training configuration (one baseline). See ``baselines/*.yaml`` for annotated examples."""

    name: str
    # The track a config is made for (one of TRAIN_TRACKS, e.g. Random for vision-ppo-random): a run's --track
    # defaults to it and may not differ. None: any track, chosen per run (racebench train --track, default S).
    track: str | None = None
    obs_mode: str = "vision"
    recurrent: bool = True
    reward_weights: dict[str, float] = field(default_factory=dict)
    curriculum: bool = True
    start_level: int = 1
    promote_at: float = 0.8
    window: int = 100
    # Steps a level may take before promotion anyway (levels below the last; none: promotion by the bar only).
    # An obstacle-blind policy may never reach the bar at level 2 (state-ppo stalled there for 2.9M steps).
    level_budget: dict[int, int] = field(default_factory=dict)
    levels: dict[int, dict[str, Any]] = field(default_factory=lambda: {k: dict(v) for k, v in CURRICULUM.items()})
    scene_groups: dict[int, int] = field(default_factory=lambda: {1: 2, 2: 4, 3: 8})
    start_spread: tuple[float, float, float] = (0.5, 0.5, 0.5)
    # RaceEnv start_mode: "points" starts at rest around the track start or a point before any gate (the paper's
    # Sec. III-C.2); "gates" is campaign 1's flying mid-leg start; "track" the track start only.
    start_mode: str = "points"
    gate_shift: float = 1.0  # the paper's training gate randomisation: ±1 m on x/y ...
    gate_shift_z: float | None = 0.3  # ... and ±0.3 m on z (None: the same as gate_shift)
    obstacle_placement: str = "band"  # RaceEnv obstacle_placement: "band" (env version 3) or "box" (version 2)
    depth_noise_std: float = 0.02
    renderer: str | None = "raycast"  # training depth: the tested TinyRenderer match, ~30x faster than PyBullet's
    n_envs: int = 8
    vec_env: str = "race"  # "race": batched RaceSB3VecEnv; "subproc"/"dummy": SB3's own VecEnvs of RaceEnvs
    num_processes: int = 2  # processes stepping the envs ("race" only); one per core
    n_steps: int = 256
    batch_size: int = 512
    n_epochs: int = 5
    learning_rate: tuple[float, float] = (1e-4, 1e-5)
    gamma: float = 0.99
    gae_lambda: float = 0.95
    clip_range: float = 0.2
    ent_coef: float = 0.0
    normalize_reward: bool = True  # SB3's VecNormalize on rewards only (observations are already scaled)
    log_std_init: float = 0.0  # initial log σ of the Gaussian policy (SB3's default 0: σ = 1 on [-1, 1] actions)
    gru_hidden: int = 256
    critic_gru: bool = True  # the critic's own GRU (the paper's method); False: an MLP critic on the features
    net_arch: tuple[int, ...] = (192, 96)
    cnn: str = "strided"  # depth CNN, see racebench.agents.recurrent.depth_cnn ("paper": conv + max-pool)
    # Candidate actions of the actor's output (1: SB3's linear mean). >= 2: a MixtureActionHead, the deterministic
    # action is the highest-scoring candidate; its scores learn only from a DAgger student's mixture loss
    # (racebench.training.dagger), so a PPO run takes it only to fine-tune such a student (init_from; train refuses
    # it otherwise).
    action_components: int = 1
    # What the actor outputs (racebench.agents.recurrent.ACTION_OUTPUTS): "ctbr", the env's action, or "acceleration",
    # a command that racebench.agents.control.command_to_ctbr flies from the observation (a DAgger student taught the
    # fast
    # expert's commands; the recurrent policy only; PPO refuses it: its env steps take CTBR).
    action_output: str = "ctbr"
    torch_threads: int = 1  # learner threads while collecting: more oversubscribes the cores the env workers use
    update_threads: int = 2  # learner threads during the PPO update, when the env workers are idle
    # Fine-tuning: a checkpoint whose policy weights start the run ({track} and {seed} are filled in; only its
    # tensors are read, no pickled code) and the steps at the start during which only the critic learns.
    init_from: str | None = None
    critic_warmup: int = 0
    # Behaviour cloning to the init_from policy while fine-tuning (0: none): after each PPO update, one gradient
    # step on bc_coef x the mean squared distance between the policy's deterministic actions and the frozen
    # initial policy's along the last rollout (StudentBCCallback), so PPO improves the student without forgetting it
    bc_coef: float = 0.0
    # What bc_coef pulls towards: "init" (the frozen init_from policy, StudentBCCallback) or "teacher" (the privileged
    # teacher's action for every state the policy visits, TeacherBCCallback: DAgger's labels on PPO's own rollouts).
    # Why "teacher": fine-tuning held to the student lands at S 83-86 %, Circle 75-77 %, J 88-89 % whichever student
    # it starts from, with most failures on obstacles the teacher avoids from the same states.
    bc_target: str = "init"
    # The teacher of bc_target "teacher": FastPlannerAgent kwargs (default: the vision-distill students' teacher).
    teacher: dict[str, Any] = field(
        default_factory=lambda: {"gate_clearance": 0.5, "wanted_clearance": 0.6, "integral_gain": 0.0}
    )

    @classmethod
    def from_yaml(cls, path: str | Path) -> TrainConfig:
        """Load and validate a config file or a built-in baseline name (``"vision-ppo"``, ...; see
        :data:`BASELINES`) with ``yaml.safe_load``; unknown keys are errors."""
        path = baseline_path(path)
        data = read_yaml(path)
        if not isinstance(data, dict):
            raise ValueError(f"{path}: expected a mapping at the top level")
        method = data.pop("method", "ppo")
        if method != "ppo":
            raise ValueError(f"{path}: method {method!r} is not PPO: load it with racebench.training.run.load_config")
        check_keys(path, data, cls)
        for key in ("levels", "scene_groups", "level_budget"):
            if key in data:
                data[key] = {int(k): v for k, v in data[key].items()}
        for key in ("start_spread", "learning_rate", "net_arch"):
            if key in data:
                data[key] = tuple(data[key])
        config = cls(**data)
        config.validate(str(path))
        return config

    def validate(self, source: str = "config") -> None:
        """Raise ``ValueError`` naming the first bad setting."""
        teacher_problem = self.teacher_error()
        checks = [
            (self.track is None or self.track in TRAIN_TRACKS, f"track must be one of {TRAIN_TRACKS} (or unset)"),
            (self.obs_mode in ("vision", "state"), "obs_mode must be 'vision' or 'state'"),
            (self.start_mode in START_MODES, f"start_mode must be one of {list(START_MODES)}"),
            (self.obstacle_placement in PLACEMENTS, f"obstacle_placement must be one of {list(PLACEMENTS)}"),
            (self.start_level in self.levels, f"start_level must be one of {sorted(self.levels)}"),
            (sorted(self.levels) == list(range(1, len(self.levels) + 1)), "levels must be numbered 1, 2, ..., n"),
            (0 < self.promote_at <= 1, "promote_at must be in (0, 1]"),
            (self.window >= 1, "window must be >= 1"),
            (self.n_envs >= 1, "n_envs must be >= 1"),
            (self.vec_env in ("race", "subproc", "dummy"), "vec_env must be 'race', 'subproc' or 'dummy'"),
            (1 <= self.num_processes <= self.n_envs, "num_processes must be in [1, n_envs]"),
            ((self.n_envs * self.n_steps) % self.batch_size == 0, "n_envs * n_steps must be a multiple of batch_size"),
            (len(self.learning_rate) == 2 and min(self.learning_rate) > 0, "learning_rate must be [start, end] > 0"),
            (all(k >= 1 for k in self.scene_groups.values()), "scene_groups values must be >= 1"),
            (
                all(k in self.levels and k < max(self.levels) for k in self.level_budget)
                and all(isinstance(v, int) and v >= 1 for v in self.level_budget.values()),
                "level_budget must map levels below the last to step counts >= 1",
            ),
            (self.cnn in CNN_KINDS, f"cnn must be one of {CNN_KINDS}"),
            (self.action_components >= 1, "action_components must be >= 1"),
            (self.action_components == 1 or self.recurrent, "action_components >= 2 needs the recurrent (GRU) policy"),
            (self.action_output in ACTION_OUTPUTS, f"action_output must be one of {ACTION_OUTPUTS}"),
            (self.action_output == "ctbr" or self.recurrent, "action_output acceleration needs the recurrent policy"),
            (self.torch_threads >= 1 and self.update_threads >= 1, "torch_threads and update_threads must be >= 1"),
            (self.critic_warmup >= 0, "critic_warmup must be >= 0"),
            (self.bc_coef >= 0.0, "bc_coef must be >= 0"),
            (self.bc_target in BC_TARGETS, f"bc_target must be one of {BC_TARGETS}"),
            (
                self.bc_coef == 0.0 or self.bc_target != "init" or self.init_from is not None,
                "bc_coef needs init_from (the policy to stay near) with bc_target 'init'",
            ),
            (
                self.bc_coef == 0.0 or self.bc_target != "teacher" or self.vec_env == "race",
                "bc_target 'teacher' needs vec_env 'race' (its envs carry the teacher's labels)",
            ),
            (teacher_problem is None, f"teacher: {teacher_problem}"),
        ]
        for ok, message in checks:
            if not ok:
                raise ValueError(f"{source}: {message}")

    def teacher_error(self) -> str | None:
        """Why ``teacher`` is not a valid set of ``FastPlannerAgent`` kwargs, else ``None``."""
        if not isinstance(self.teacher, dict):
            return f"must be a mapping of FastPlannerAgent settings, got {self.teacher!r}"
        try:
            FastPlannerAgent(**self.teacher)
        except (TypeError, ValueError) as exc:
            return str(exc)
        return None

    def level_kwargs(self, level: int) -> dict[str, Any]:
        """``RaceEnv.set_task`` kwargs of a curriculum level, with this config's reward overrides on top."""
        kwargs = dict(self.levels[level])
        kwargs["reward_weights"] = {**kwargs.get("reward_weights", {}), **self.reward_weights}
        return kwargs

    def env_kwargs(self, track: str) -> dict[str, Any]:
        """Constructor kwargs of every training env (at the starting level)."""
        level = self.level_kwargs(self.start_level)
        kwargs = {
            "track": track,
            "obs_mode": self.obs_mode,
            "start_spread": self.start_spread,
            "start_mode": self.start_mode,
            "gate_shift": self.gate_shift,
            "gate_shift_z": self.gate_shift_z,
            "obstacle_placement": self.obstacle_placement,
            "depth_noise_std": self.depth_noise_std,
            "density": level.get("density", 3),
            "desired_speed": level.get("desired_speed", 8.0),
            "reward_weights": level["reward_weights"],
        }
        if self.renderer is not None:
            kwargs["renderer"] = self.renderer
        return kwargs
