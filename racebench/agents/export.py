"""Exporting a trained SB3 policy: a policy-only checkpoint (:func:`export_policy`) or an ONNX graph
(:func:`export_onnx`)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from racebench.agents.base import obs_mode_of
from racebench.agents.loading import is_gaussian_actor_critic
from racebench.agents.recurrent import LSTMShapedGRU

#: Attributes of an SB3 algorithm that only resuming its training reads: the last rollout's observations, episode
#: starts and recurrent states, and the episode-statistics buffers. A policy-only checkpoint leaves them out.
TRAINING_ONLY_ATTRIBUTES = (
    "_last_obs",
    "_last_original_obs",
    "_last_episode_starts",
    "_last_lstm_states",
    "ep_info_buffer",
    "ep_success_buffer",
)


#: Parameter-name prefixes of an SB3 / sb3-contrib actor-critic's critic: its features extractor (when not the
#: actor's), its GRU / LSTM or linear layer, its MLP and its value head. No action reads them.
CRITIC_PREFIXES: tuple[str, ...] = (
    "lstm_critic.", "critic.", "mlp_extractor.value_net.", "value_net.", "vf_features_extractor.",
)  # fmt: skip


def critic_parameter(name: str) -> bool:
    """Whether a policy parameter belongs to the critic only (its GRU, MLP and head); all else acts."""
    return name.startswith(CRITIC_PREFIXES)


def critic_only_tensors(policy: Any) -> dict[str, Any]:
    """The critic's parameters that no actor module shares, by state-dict name (a shared features extractor
    appears under the critic's name too, and stays out)."""
    named = list(policy.named_parameters(remove_duplicate=False))
    acting = {id(parameter) for name, parameter in named if not critic_parameter(name)}
    return {name: parameter for name, parameter in named if critic_parameter(name) and id(parameter) not in acting}


def export_policy(model: Any, path: str | Path, keep_critic: bool = False) -> Path:
    """Save an SB3 model as a policy-only checkpoint: the weights and what loading and acting need, with the
    optimizer's state (Adam's moments: twice the weights) and :data:`TRAINING_ONLY_ATTRIBUTES` left out.

    Unless ``keep_critic``, the critic's own weights (:func:`critic_only_tensors`, about half of a vision policy)
    are saved as zeros and the model's ``critic_stripped`` attribute is saved true: no action reads them, and
    zeros cost next to nothing in git's compressed history. It loads like any SB3 save and acts exactly as
    ``model`` does; training cannot resume from it (``train`` and ``init_from`` refuse such a file), and without
    the critic a resumed run's Adam moments would be fresh anyway. ``model`` itself is left as it was.
    """
    import torch

    path = Path(path)
    if path.suffix != ".zip":
        raise ValueError(f"a policy-only checkpoint is an SB3 .zip, not {str(path)!r}")
    optimizer = model.policy.optimizer
    # A fresh optimizer of the same kind and settings: its state dict is the settings alone.
    model.policy.optimizer = type(optimizer)(model.policy.parameters(), **optimizer.defaults)
    critic = {} if keep_critic else critic_only_tensors(model.policy)
    kept = {name: tensor.detach().clone() for name, tensor in critic.items()}
    stripped_before = model.__dict__.get("critic_stripped")
    partial = path.with_name(f".{path.stem}.partial.zip")  # renamed into place: never a half-written policy
    try:
        with torch.no_grad():
            for tensor in critic.values():
                tensor.zero_()
        if critic:
            model.critic_stripped = True  # saved with the model's attributes, read back by load
        model.save(partial, exclude=[name for name in TRAINING_ONLY_ATTRIBUTES if name in model.__dict__])
        os.replace(partial, path)
    finally:
        with torch.no_grad():
            for name, tensor in critic.items():
                tensor.copy_(kept[name])
        if critic and stripped_before is None:
            del model.critic_stripped
        elif critic:
            model.critic_stripped = stripped_before
        model.policy.optimizer = optimizer
        partial.unlink(missing_ok=True)
    return path


def check_policy_export(model: Any, exported: Any, name: str = "the export") -> None:
    """Raise ``ValueError`` unless ``exported`` (the :func:`export_policy` file, loaded) holds ``model``'s weights:
    every tensor equal, except the critic's own, which are equal or, in a critic-stripped export, zero."""
    theirs, ours = model.policy.state_dict(), exported.policy.state_dict()
    if theirs.keys() != ours.keys():
        raise ValueError(f"{name} holds other tensors than the checkpoint's policy")
    stripped = getattr(exported, "critic_stripped", False)
    critic = critic_only_tensors(exported.policy) if stripped else {}
    for key, tensor in theirs.items():
        if not (ours[key].equal(tensor) or (key in critic and not ours[key].any())):
            raise ValueError(f"the weights read back from {name} differ from the checkpoint's ({key})")


def _export_refusal(policy: Any) -> str | None:
    """Why :func:`export_onnx` cannot reproduce ``policy``'s deterministic action, or ``None`` if it can."""
    rnn = getattr(policy, "lstm_actor", None)
    if rnn is not None and not isinstance(rnn, LSTMShapedGRU):
        return "recurrent policies must use racebench's GRU (an LSTM's cell state is not exported)"
    if rnn is not None and rnn.num_layers != 1:
        return f"a GRU of {rnn.num_layers} layers is not supported (1 layer)"
    if getattr(policy, "action_output", "ctbr") != "ctbr":
        return (
            f"the policy outputs {policy.action_output} commands, not the env's CTBR action (its controller, "
            "racebench.agents.control.command_to_ctbr, is not part of the network)"
        )
    # The graph is the actor's mean action: exact only for the forward passes that _gaussian_mean reproduces.
    if not is_gaussian_actor_critic(policy):
        return (
            f"{type(policy).__name__} is not an SB3, sb3-contrib or racebench actor-critic with a diagonal Gaussian "
            "action and unsquashed output (PPO or A2C), whose deterministic action the export reproduces"
        )
    space = policy.action_space
    if space.shape != (4,) or not (np.all(space.low == -1.0) and np.all(space.high == 1.0)):
        return f"the action space is {space}, not the env's CTBR action [-1, 1]^4"
    return None


def export_onnx(model: Any, path: str | Path, normalizer: Any = None) -> Path:
    """Export the deterministic actor of an SB3 actor-critic policy to ONNX (see :class:`OnnxAgent`).

    The graph takes the standard envs' observations and returns the action :class:`SB3Agent` flies: a policy
    trained on ``depth_format="uint8"`` gets the depth through :func:`racebench.envs.env.depth_to_uint8`'s rounding
    (and SB3's own image scaling after it), and ``normalizer`` (:attr:`SB3Agent.normalizer`, ``VecNormalize``
    statistics) is applied as ``VecNormalize.normalize_obs`` does. Feed-forward policies and racebench's
    recurrent GRU policies (``RecurrentGRUPolicy``: the actor's GRU state becomes the ``hidden`` input and the
    second output). Anything else (LSTM, SAC/TD3, acceleration-command outputs, a user's policy subclass) is
    refused with a ``ValueError`` naming why.
    """
    import torch
    from stable_baselines3.common.policies import BaseModel

    policy = model.policy.to("cpu").eval()
    refusal = _export_refusal(policy)
    if refusal is not None:
        raise ValueError(f"export_onnx: {refusal}")
    space = model.observation_space
    vision = obs_mode_of(space) == "vision"
    uint8_depth = vision and space["depth"].dtype == np.uint8
    gru = getattr(policy, "lstm_actor", None)

    def statistics(key: str | None) -> tuple[torch.Tensor, torch.Tensor, float] | None:
        """VecNormalize's mean, scale and clip for one observation key (``None``: a Box observation)."""
        if normalizer is None or (key is not None and key not in (normalizer.norm_obs_keys or [])):
            return None
        rms = normalizer.obs_rms[key] if key is not None else normalizer.obs_rms
        scale = np.sqrt(rms.var + normalizer.epsilon)
        return (
            torch.tensor(rms.mean, dtype=torch.float32),
            torch.tensor(scale, dtype=torch.float32),
            normalizer.clip_obs,
        )

    norms = {key: statistics(key) for key in (("state", "depth") if vision else (None,))}

    def normalise(x: torch.Tensor, key: str | None) -> torch.Tensor:
        if norms[key] is None:
            return x
        mean, scale, clip = norms[key]
        return torch.clamp((x - mean) / scale, -clip, clip)

    # SB3Agent.prepare hands uint8 policies depth_to_uint8's channels-last image, and predict (maybe_transpose)
    # transposes an image whose shape is not the space's: decided here, once, from the shapes.
    size = 64
    prepared = (size, size, 1) if uint8_depth else (1, size, size)
    transpose = vision and prepared != tuple(space["depth"].shape)
    if transpose and (prepared[2], prepared[0], prepared[1]) != tuple(space["depth"].shape):
        raise ValueError(f"export_onnx: the policy's depth space {space['depth']} is not a {size}x{size} image")

    def depth_input(depth: torch.Tensor) -> torch.Tensor:
        """The float (batch, 1, H, W) depth → what SB3Agent.prepare and predict hand the features extractor."""
        if uint8_depth:  # depth_to_uint8: round half up, channels last
            depth = torch.floor(torch.clamp(depth * 255.0 + 0.5, 0.0, 255.0)).permute(0, 2, 3, 1)
        depth = normalise(depth, "depth")
        return depth.permute(0, 3, 1, 2) if transpose else depth

    class Actor(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.policy = policy

        def forward(self, state: torch.Tensor, *rest: torch.Tensor) -> Any:
            depth, hidden = (rest[0], rest[1:]) if vision else (None, rest)
            if vision:
                obs = {"state": normalise(state, "state"), "depth": depth_input(depth)}
            else:
                obs = normalise(state, None)
            # BaseModel's: the actor's own features extractor, shared or not (ActorCriticPolicy's returns a pair).
            features = BaseModel.extract_features(self.policy, obs, self.policy.pi_features_extractor)
            if gru is None:
                return torch.clamp(self.policy.action_net(self.policy.mlp_extractor.forward_actor(features)), -1, 1)
            output, next_hidden = torch.nn.GRU.forward(gru, features.unsqueeze(0), hidden[0].unsqueeze(0))
            action = self.policy.action_net(self.policy.mlp_extractor.forward_actor(output[0]))
            return torch.clamp(action, -1.0, 1.0), next_hidden[0]

    args: list[torch.Tensor] = [torch.zeros(1, 17)]
    names = ["state"]
    if vision:
        args.append(torch.zeros(1, 1, size, size))
        names.append("depth")
    outputs = ["action"]
    if gru is not None:
        args.append(torch.zeros(1, gru.hidden_size))
        names.append("hidden")
        outputs.append("next_hidden")
    path = Path(path)
    torch.onnx.export(
        Actor(),
        tuple(args),
        str(path),
        input_names=names,
        output_names=outputs,
        dynamic_axes={n: {0: "batch"} for n in [*names, *outputs]},
        dynamo=False,  # the supported exporter fails on SB3 policies: docs/evaluation.md says why
    )
    return path


#: Largest action difference :func:`onnx_action_gap` accepts: float32 graph arithmetic differs from torch's in the
#: last bits (about 1e-6 on the committed GRU policies), a wrong graph by orders of magnitude more.
ONNX_ACTION_TOLERANCE = 1e-4


def onnx_action_gap(agent: Any, onnx_path: str | Path, env_id: str, seed: int, steps: int = 60) -> tuple[float, int]:
    """Fly ``agent`` (the checkpoint's :class:`~racebench.agents.loading.SB3Agent`) on one episode of ``env_id``
    and feed the ONNX export the same observations: the largest |action difference| and the steps compared.

    Real observations of the checkpoint's own flight, the recurrent state carried by each policy as it flies, up
    to ``steps`` steps or the episode's end.
    """
    import gymnasium as gym

    from racebench.agents.loading import OnnxAgent

    onnx = OnnxAgent(onnx_path)
    env = gym.make(env_id, obs_mode=obs_mode_of(agent.model.observation_space))
    try:
        obs, _ = env.reset(seed=seed)
        agent.reset(env, seed)
        onnx.reset(env, seed)
        gap, flown, ended = 0.0, 0, False
        while flown < steps and not ended:
            action = agent.act(obs)
            difference = float(np.max(np.abs(action - onnx.act(obs))))
            gap = max(gap, difference if np.isfinite(difference) else np.inf)  # a NaN action is no match
            obs, _, terminated, truncated, _ = env.step(action)
            flown, ended = flown + 1, terminated or truncated
    finally:
        env.close()
    return gap, flown
