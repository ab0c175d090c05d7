"""The paper's policy network (Fig. 2) on stable-baselines3 / sb3-contrib building blocks.

State MLP (2 layers) and depth CNN (3 conv layers, :func:`depth_cnn`) → concatenate → GRU (256) → actor
MLP [192, 96] → CTBR; the critic has its own GRU (256) on the same features and its own MLP [192, 96]
(``train.make_model`` explains why it does not share the actor's). sb3-contrib's ``RecurrentPPO`` supplies
the recurrent machinery (hidden state carried across steps, reset at episode starts, training on
sequences); it is written for LSTMs, so
:class:`LSTMShapedGRU` gives a GRU the LSTM call signature (the unused cell state is carried as zeros) and
:class:`RecurrentGRUPolicy` swaps it in. The feed-forward ablation uses the same extractor with a dense
256-unit layer where the GRU was.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import torch
from sb3_contrib.common.recurrent.policies import RecurrentMultiInputActorCriticPolicy
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from torch import nn

CNN_KINDS: tuple[str, ...] = ("paper", "strided", "fine")
# What the actor outputs: "ctbr", the environment's action (collective thrust and body rates); "acceleration", an
# acceleration command (racebench.agents.control.command_to_ctbr turns it into CTBR from the observation; SB3Agent
# flies it).
ACTION_OUTPUTS: tuple[str, ...] = ("ctbr", "acceleration")
# (out channels, kernel, stride) of each conv of the CNNs that down-sample with strides alone.
_STRIDED_CONVS: dict[str, tuple[tuple[int, int, int], ...]] = {
    "strided": ((16, 8, 4), (32, 4, 2), (32, 3, 1)),
    "fine": ((16, 5, 2), (32, 4, 2), (32, 3, 2)),
}


def depth_cnn(kind: str, size: int, out_dim: int) -> nn.Sequential:
    """The depth branch: three conv layers and a linear layer to ``out_dim`` on a 1×``size``×``size`` image.

    * ``"paper"``: the paper's Fig. 2 shape, three 3×3 convs (16, 32, 32 channels), each followed by ReLU
      and 2×2 max-pool (64×64 → 8×8): ~8 M multiply-adds per image;
    * ``"strided"``: the same three conv layers with the down-sampling done by the convs themselves
      (8×8 stride 4, 4×4 stride 2, 3×3 stride 1, as SB3's ``NatureCNN``; 16, 32, 32 channels): ~0.7 M
      multiply-adds per image, the one that lets vision PPO train at ~1,500 samples/s on 2 CPU cores.
    * ``"fine"``: strided convs that halve the image at each layer (5×5, 4×4, 3×3, all stride 2; 16, 32, 32
      channels; 64×64 → 30 → 14 → 6): ~2.4 M multiply-adds per image, ~3× ``"strided"`` and ~⅓ of ``"paper"``.
      Why: ``"strided"``'s 8×8 stride-4 first layer sees a 64×64 image through a 15×15 grid, coarse for where an
      obstacle stands against the line to the gate, which is what a student must steer around.
    """
    if kind == "paper":
        return nn.Sequential(
            nn.Conv2d(1, 16, 3, padding=1), nn.ReLU(), nn.MaxPool2d(2),
            nn.Conv2d(16, 32, 3, padding=1), nn.ReLU(), nn.MaxPool2d(2),
            nn.Conv2d(32, 32, 3, padding=1), nn.ReLU(), nn.MaxPool2d(2),
            nn.Flatten(), nn.Linear(32 * (size // 8) ** 2, out_dim), nn.ReLU(),
        )  # fmt: skip
    if kind in _STRIDED_CONVS:
        layers: list[nn.Module] = []
        in_channels = 1
        for out_channels, kernel, stride in _STRIDED_CONVS[kind]:
            layers += [nn.Conv2d(in_channels, out_channels, kernel, stride=stride), nn.ReLU()]
            in_channels = out_channels
        convs = nn.Sequential(*layers, nn.Flatten())
        with torch.no_grad():
            flat = convs(torch.zeros(1, 1, size, size)).shape[1]
        # One flat Sequential (convs, Flatten, Linear, ReLU): the state-dict keys that saved policies carry.
        return nn.Sequential(*convs, nn.Linear(flat, out_dim), nn.ReLU())
    raise ValueError(f"cnn must be one of {CNN_KINDS}, got {kind!r}")


class RaceFeatures(BaseFeaturesExtractor):
    """State MLP and depth CNN (:func:`depth_cnn`), concatenated; the depth branch is dropped for state-only
    observations.

    The CNN runs in ``channels_last`` memory format, ~1.8× faster on CPU here. State MLP: 17 → ``state_dim`` →
    ``state_dim``.
    """

    def __init__(
        self, observation_space: gym.Space, state_dim: int = 64, depth_dim: int = 128, cnn: str = "paper"
    ) -> None:
        vision = isinstance(observation_space, gym.spaces.Dict)
        state_space = observation_space["state"] if vision else observation_space
        super().__init__(observation_space, features_dim=state_dim + (depth_dim if vision else 0))
        self.vision = vision
        n_state = int(state_space.shape[0])
        self.state_net = nn.Sequential(
            nn.Linear(n_state, state_dim), nn.ReLU(), nn.Linear(state_dim, state_dim), nn.ReLU()
        )
        if vision:
            self.depth_net = depth_cnn(cnn, observation_space["depth"].shape[-1], depth_dim)
        self._channels_last = False

    def forward(self, observations: Any) -> torch.Tensor:
        """Features of a batch of observations."""
        if not self.vision:
            return self.state_net(observations)
        if not self._channels_last:
            # After SB3's orthogonal init (which needs contiguous weights); parameters keep their identity.
            self.depth_net.to(memory_format=torch.channels_last)
            self._channels_last = True
        depth = observations["depth"].contiguous(memory_format=torch.channels_last)
        return torch.cat([self.state_net(observations["state"]), self.depth_net(depth)], dim=1)


class LSTMShapedGRU(nn.GRU):
    """``nn.GRU`` called like ``nn.LSTM``: ``(output, (h, c)) = gru(x, (h, c))``; ``c`` passes through.

    sb3-contrib's recurrent rollout buffer and ``_process_sequence`` handle (hidden, cell) pairs and the
    resetting of both at episode starts; the GRU uses the hidden state only.
    """

    def forward(self, x: torch.Tensor, states: tuple[torch.Tensor, torch.Tensor]) -> tuple:  # type: ignore[override]
        """Run the GRU over a (sequence, batch, features) input."""
        hidden, cell = states
        output, hidden = super().forward(x, hidden.contiguous())
        return output, (hidden, cell)


class MixtureActionHead(nn.Module):
    """An actor output of ``components`` candidate actions and a score for each; its output (what SB3's
    ``action_net`` returns: the Gaussian's mean, the deterministic action) is the highest-scoring candidate's.

    Why: a student regressed with the mean squared error onto a teacher that, in look-alike scenes, passes an
    obstacle sometimes on the left and sometimes on the right learns the average of the two, a swerve too small
    for either side; a mixture can keep both and commit to one (a mixture density network, Bishop 1994, read out
    at its most probable component). :func:`mixture_action_loss` is its training loss.
    """

    def __init__(self, latent_dim: int, action_dim: int, components: int) -> None:
        super().__init__()
        if components < 2:
            raise ValueError(f"a mixture head needs >= 2 components, got {components}")
        self.action_dim = action_dim
        self.n_components = components
        self.means = nn.Linear(latent_dim, components * action_dim)
        self.scores = nn.Linear(latent_dim, components)
        # SB3's initialisation of an action head (orthogonal, gain 0.01): near-zero actions at the start. The
        # component biases are spread so the candidates differ from the first step (else all get one gradient).
        for layer in (self.means, self.scores):
            nn.init.orthogonal_(layer.weight, gain=0.01)
            nn.init.zeros_(layer.bias)
        with torch.no_grad():
            self.means.bias.copy_(torch.linspace(-0.1, 0.1, components).repeat_interleave(action_dim))

    def components(self, latent: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The candidates ``(..., components, action_dim)`` and their scores (logits) ``(..., components)``."""
        means = self.means(latent).unflatten(-1, (self.n_components, self.action_dim))
        return means, self.scores(latent)

    def forward(self, latent: torch.Tensor) -> torch.Tensor:
        """The highest-scoring candidate ``(..., action_dim)``."""
        means, scores = self.components(latent)
        pick = scores.argmax(dim=-1, keepdim=True).unsqueeze(-1).expand(*scores.shape[:-1], 1, self.action_dim)
        return means.gather(-2, pick).squeeze(-2)  # gather, not take_along_dim: ONNX exports it


def mixture_action_loss(
    head: MixtureActionHead, latent: torch.Tensor, target: torch.Tensor, sigma: float
) -> torch.Tensor:
    """Per-sample loss ``(...,)`` of ``head`` on the labels ``target`` ``(..., action_dim)``: the negative
    log-likelihood of a mixture of isotropic Gaussians of standard deviation ``sigma`` at the candidates, with
    weights the softmax of the scores, times ``2 sigma^2 / action_dim``.

    The scaling makes it the mean squared error per action dimension when one candidate takes all the weight (a
    single Gaussian's NLL up to a constant), so a learning rate tuned for the MSE student fits this one. Each
    candidate is pulled towards a label in proportion to its posterior responsibility for it, and the scores learn
    those responsibilities: small ``sigma`` divides the labels among candidates sharply.
    """
    means, scores = head.components(latent)
    squared = ((means - target.unsqueeze(-2)) ** 2).sum(-1)
    log_likelihood = torch.logsumexp(torch.log_softmax(scores, dim=-1) - squared / (2.0 * sigma**2), dim=-1)
    return -log_likelihood * (2.0 * sigma**2 / target.shape[-1])


class RecurrentGRUPolicy(RecurrentMultiInputActorCriticPolicy):
    """sb3-contrib's recurrent actor-critic with GRUs instead of LSTMs (see the module docstring).

    Works for Dict and Box observations (the features extractor handles both). With ``action_components`` >= 2
    the actor's output layer is a :class:`MixtureActionHead` (the Gaussian's mean is its chosen candidate). With
    ``action_output="acceleration"`` the actor's output is an acceleration command, not the env's action (see
    :data:`ACTION_OUTPUTS`): whoever flies it converts it (``SB3Agent``, the DAgger collector).
    """

    def __init__(
        self, observation_space: gym.Space, action_space: gym.Space, lr_schedule, action_components: int = 1,
        action_output: str = "ctbr", **kwargs: Any,
    ) -> None:  # fmt: skip
        if action_output not in ACTION_OUTPUTS:
            raise ValueError(f"action_output must be one of {ACTION_OUTPUTS}, got {action_output!r}")
        super().__init__(observation_space, action_space, lr_schedule, **kwargs)
        if action_components > 1:
            latent = self.mlp_extractor.latent_dim_pi
            self.action_net = MixtureActionHead(latent, int(action_space.shape[0]), action_components)
        hidden = self.lstm_output_dim
        layers = self.lstm_actor.num_layers
        self.lstm_actor = LSTMShapedGRU(self.features_dim, hidden, num_layers=layers, **self.lstm_kwargs)
        if self.lstm_critic is not None:
            self.lstm_critic = LSTMShapedGRU(self.features_dim, hidden, num_layers=layers, **self.lstm_kwargs)
        # The parent built its optimizer over the LSTM parameters: rebuild it over the GRU ones.
        self.optimizer = self.optimizer_class(self.parameters(), lr=lr_schedule(1), **self.optimizer_kwargs)
        self.action_components = action_components
        self.action_output = action_output

    def _get_constructor_parameters(self) -> dict[str, Any]:
        """The parent's, with ``action_components`` and ``action_output`` (what ``policy.save`` / ``load`` rebuild
        the policy from)."""
        return {**super()._get_constructor_parameters(), "action_components": self.action_components,
                "action_output": self.action_output}  # fmt: skip

    @staticmethod
    def _process_sequence(
        features: torch.Tensor,
        lstm_states: tuple[torch.Tensor, torch.Tensor],
        episode_starts: torch.Tensor,
        lstm: nn.Module,
    ) -> tuple[torch.Tensor, tuple[torch.Tensor, torch.Tensor]]:
        """The parent's recurrent pass, with one fused call where it would loop over time steps.

        sb3-contrib's rollout buffer starts a new sequence at every episode start, so in training batches
        ``episode_starts`` can be 1 only at a sequence's first step. The parent then still steps the RNN one
        time step at a time (its fast path needs no start at all): here the reset is applied to the initial
        state and the whole sequence runs in one call, which is the same computation (tested) and several
        times faster. Starts anywhere else fall back to the parent's loop.
        """
        n_seq = lstm_states[0].shape[1]
        starts = episode_starts.reshape((n_seq, -1)).swapaxes(0, 1)
        if starts.shape[0] > 1 and bool(torch.any(starts[1:] != 0.0)):
            return RecurrentMultiInputActorCriticPolicy._process_sequence(features, lstm_states, episode_starts, lstm)
        sequence = features.reshape((n_seq, -1, lstm.input_size)).swapaxes(0, 1)
        keep = (1.0 - starts[0]).view(1, n_seq, 1)
        output, states = lstm(sequence, (keep * lstm_states[0], keep * lstm_states[1]))
        return torch.flatten(output.transpose(0, 1), start_dim=0, end_dim=1), states
