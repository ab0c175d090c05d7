"""Building a PPO run's envs and model (the policy network of a config), and loading a policy's weights into one."""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

import torch
from stable_baselines3 import PPO
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.save_util import load_from_zip_file
from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv, VecEnv, VecNormalize

from racebench.agents.export import critic_only_tensors
from racebench.agents.recurrent import RaceFeatures, RecurrentGRUPolicy
from racebench.evaluation.protocol import EVAL_SEED_BASE
from racebench.training.config import TrainConfig
from racebench.training.sb3 import make_sb3_vec_env


def policy_weights(path: str | Path, model: Any) -> dict[str, torch.Tensor]:
    """The policy tensors of the SB3 checkpoint ``path``, checked to fit ``model``'s policy (the same network).

    Only the tensors are read (``load_from_zip_file(load_data=False)``: nothing unpickled, so no code runs).
    """
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"init_from: {path} is not a file (train or download the policy it names first)")
    try:
        _, params, _ = load_from_zip_file(path, load_data=False, device=model.device)
    except Exception as exc:  # noqa: BLE001 - a bad archive is named, whatever the zip/torch error
        why = " ".join(str(exc).split())[:300]  # torch's weights_only refusal spans many lines
        raise ValueError(f"init_from: {path} is not an SB3 checkpoint ({type(exc).__name__}: {why})") from None
    weights = params.get("policy") if params else None
    if weights is None:
        raise ValueError(f"init_from: {path} holds no policy weights")
    mine = model.policy.state_dict()
    if set(weights) != set(mine) or any(weights[k].shape != mine[k].shape for k in mine):
        raise ValueError(f"init_from: {path} is another network than this config's ({model.policy.__class__.__name__})")
    critic = critic_only_tensors(model.policy)
    if critic and not any(weights[name].any() for name in critic):  # a zero critic would never learn (no gradient)
        raise ValueError(f"init_from: {path} is a policy-only export without its critic; name the run's own checkpoint")
    return weights


def load_policy_weights(model: Any, path: str | Path, log_std: float) -> None:
    """Start ``model``'s policy from the weights in the SB3 checkpoint ``path`` (:func:`policy_weights`).

    log σ is set to ``log_std``: an imitation-learned student never trained it.
    """
    model.policy.load_state_dict(policy_weights(path, model))
    with torch.no_grad():
        model.policy.log_std.fill_(log_std)


def frozen_initial_policy(model: Any, path: str | Path) -> Any:
    """A frozen copy of ``model``'s policy holding the weights of ``path`` (the anchor of ``bc_coef``)."""
    anchor = copy.deepcopy(model.policy)
    anchor.load_state_dict(policy_weights(path, model))
    anchor.set_training_mode(False)
    for parameter in anchor.parameters():
        parameter.requires_grad_(False)
    return anchor


def linear_schedule(start: float, end: float):
    """Learning rate decaying linearly from ``start`` to ``end`` over training (SB3 passes progress 1 → 0)."""

    def schedule(progress_remaining: float) -> float:
        return end + (start - end) * progress_remaining

    return schedule


def make_envs(config: TrainConfig, track: str, seed: int) -> VecEnv:
    """The training VecEnv: ``n_envs`` RaceEnvs seeded ``seed + i`` (all below the evaluation seeds).

    ``vec_env="race"`` batches them in ``num_processes`` processes (:func:`racebench.training.sb3.make_sb3_vec_env`,
    tested equivalent to ``DummyVecEnv``); ``"subproc"``/``"dummy"`` are SB3's ``make_vec_env``.
    """
    if seed < 0 or seed + config.n_envs > EVAL_SEED_BASE:
        raise ValueError(f"training seeds must lie in [0, {EVAL_SEED_BASE - config.n_envs}] (evaluation uses the rest)")
    if config.vec_env == "race":
        env = make_sb3_vec_env(
            f"RaceObs-{track}-v0",
            n_envs=config.n_envs,
            seed=seed,
            num_processes=min(config.num_processes, config.n_envs),
            teacher=config.teacher if config.bc_coef > 0 and config.bc_target == "teacher" else None,
            **config.env_kwargs(track),
        )
    else:
        vec_cls = SubprocVecEnv if config.vec_env == "subproc" and config.n_envs > 1 else DummyVecEnv
        env = make_vec_env(
            f"RaceObs-{track}-v0",
            n_envs=config.n_envs,
            seed=seed,
            env_kwargs=config.env_kwargs(track),
            vec_env_cls=vec_cls,
        )
    if config.normalize_reward:
        # Returns scaled by their running std, as SB3's zoo does for continuous control; the monitor inside
        # still logs the true returns, and the policy never sees the statistics (nothing to save for acting).
        env = VecNormalize(env, norm_obs=False, norm_reward=True, gamma=config.gamma)
    return env


DEVICES: tuple[str, ...] = ("auto", "cpu", "cuda")


def resolve_device(device: str) -> str:
    """``"auto"`` → ``"cuda"`` when torch sees a GPU, else ``"cpu"``; ``"cuda"`` without one is an error."""
    if device not in DEVICES:
        raise ValueError(f"device must be one of {DEVICES}, got {device!r}")
    available = torch.cuda.is_available()
    if device == "auto":
        return "cuda" if available else "cpu"
    if device == "cuda" and not available:
        raise ValueError("device 'cuda': torch sees no CUDA device (torch.cuda.is_available() is False)")
    return device


def make_model(config: TrainConfig, env: VecEnv, seed: int, tensorboard: str | None, device: str = "cpu") -> Any:
    """PPO (feed-forward) or RecurrentPPO with the GRU policy, with the paper's network sizes, on ``device``."""
    features_kwargs = {"cnn": config.cnn}

    common = dict(
        n_steps=config.n_steps,
        batch_size=config.batch_size,
        n_epochs=config.n_epochs,
        learning_rate=linear_schedule(*config.learning_rate),
        gamma=config.gamma,
        gae_lambda=config.gae_lambda,
        clip_range=config.clip_range,
        ent_coef=config.ent_coef,
        seed=seed,
        device=resolve_device(device),
        tensorboard_log=tensorboard,
        verbose=0,
    )
    arch = list(config.net_arch)
    if config.recurrent:
        from sb3_contrib import RecurrentPPO

        policy_kwargs = dict(
            features_extractor_class=RaceFeatures,
            features_extractor_kwargs=features_kwargs,
            lstm_hidden_size=config.gru_hidden,
            # The critic gets its own GRU on the shared features: with sb3-contrib's shared_lstm the critic reads
            # the actor's GRU output detached, so the value loss never shapes the recurrent features; with it
            # no level-1 run learned here (baselines/experiments/README.md).
            shared_lstm=False,
            enable_critic_lstm=config.critic_gru,
            net_arch=dict(pi=arch, vf=arch),
            log_std_init=config.log_std_init,
        )
        if config.action_components > 1:  # only then: the policies saved before the key keep their kwargs
            policy_kwargs["action_components"] = config.action_components
        if config.action_output != "ctbr":
            policy_kwargs["action_output"] = config.action_output
        return RecurrentPPO(RecurrentGRUPolicy, env, policy_kwargs=policy_kwargs, **common)

    # The feed-forward ablation: a dense layer of the GRU's width where the GRU was.
    wide = [config.gru_hidden, *arch]
    policy_kwargs = dict(
        features_extractor_class=RaceFeatures,
        features_extractor_kwargs=features_kwargs,
        net_arch=dict(pi=wide, vf=wide),
        log_std_init=config.log_std_init,
    )
    policy = "MultiInputPolicy" if config.obs_mode == "vision" else "MlpPolicy"
    return PPO(policy, env, policy_kwargs=policy_kwargs, **common)
