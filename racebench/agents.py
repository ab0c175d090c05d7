"""Agents that the evaluator can fly, and the loader that turns one spec string into an agent.

An agent follows the :class:`Agent` protocol: ``reset`` at each episode start, ``act`` on one observation,
and a declared ``obs_mode`` (``"vision"`` or ``"state"``). Stateful agents (recurrent policies) keep their
own memory and clear it in ``reset``. A *privileged* agent (``privileged = True``) is handed the
unwrapped environment in ``reset`` and may read the true scene and drone state; it is marked so in every
table and figure.

Spec strings accepted by :func:`load_agent`:

* ``random``, ``hover``, ``planner`` (privileged, cautious), ``planner-fast`` (privileged, the fast expert),
  ``follow`` (privileged, ignores obstacles);
* ``path/to/model.zip``: a stable-baselines3 / sb3-contrib checkpoint (recurrent policies included);
* ``path/to/policy.onnx``: an ONNX policy run with onnxruntime (no code from the file runs), see
  :class:`OnnxAgent` for the expected inputs and outputs and :func:`export_onnx` to make one;
* ``package.module:ClassName`` or ``path/to/file.py:ClassName``: a Python class, built with the keyword
  arguments ``agent_kwargs`` (``--agent-kwargs '{"k": 1}'``; none by default), which must declare ``obs_mode``.

**Untrusted code is refused by default.** Loading an SB3 ``.zip`` unpickles Python objects (which can run
arbitrary code) and a ``module:Class`` spec imports and runs a module, so both need ``trust_code=True``
(``--trust-code`` on the command line). The checkpoints shipped in this repository are trusted by the
sha256 of their bytes (:data:`TRUSTED_CHECKPOINTS`). ONNX files run no code and need no flag.

Only built-in agents can be privileged, and the loader, not the agent, decides which
(:data:`BUILTIN_PRIVILEGED`): a user agent is never handed the environment.
"""

from __future__ import annotations

import hashlib
import importlib
import importlib.util
import io
import json
import os
import pickle
import re
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np

from racebench.control import GateFollower
from racebench.quadrotor import QuadrotorParams

BUILTIN_AGENTS: tuple[str, ...] = ("random", "hover", "planner", "planner-fast", "follow")
#: Which built-in agents read the true scene and state. Only these are ever privileged.
BUILTIN_PRIVILEGED: dict[str, bool] = {
    "random": False,
    "hover": False,
    "planner": True,
    "planner-fast": True,
    "follow": True,
}
#: Code version of each built-in agent, part of its policy hash: bump it when the agent's behaviour changes.
#: planner-fast v2: compiled clearance queries in its path smoothing, ~2x faster planning; its paths differ from
#: v1's in the last bits (≤ 1e-13 m), which a closed loop may amplify, so its records were flown anew.
#: planner-fast v3: speed profile under a thrust budget (gravity and drag included) with jerk-limited braking
#: onsets, instead of v2's 10 m/s² friction circle; ``FastPlannerAgent(thrust_accel=None, braking_jerk=None)``
#: is v2.
BUILTIN_VERSIONS: dict[str, int] = {"random": 1, "hover": 1, "planner": 1, "planner-fast": 3, "follow": 1}
#: sha256 of the first-party checkpoints shipped in ``baselines/checkpoints`` -> their path under it. They load
#: without ``trust_code`` (``tests/test_checkpoints.py`` keeps this list and the committed files in step).
TRUSTED_CHECKPOINTS: dict[str, str] = {
    "a9648364a3a9c09e80189685eaecd34bfa47c1812bb7de8ab5a5cf00bd2bcd92": "vision-ppo-S/vision-ppo-S.zip",
    "3197e89e15de4f01be8cfb9e70d3595d9c50f3a15a5f99ea13b505429dfcc6b9": "state-ppo-S/state-ppo-S.zip",
    "3275c4e846ca85e5265e0a26ee96a550e17145365d5c7b7430f5f37f3c748c20": "vision-dagger-S/vision-dagger-S.zip",
    "284472ccda7ca9bb8dacb0445ab51e0d29cd3d7645e2cb72ff469957506fb600": "vision-distill-v1-S/vision-distill-S.zip",
    "ab21b31bfddbbf6add303d7a694b271802ec9b0174ca333f24a6a5938f298373": "vision-distill-S/vision-distill-S.zip",
    "2db06548dde9f2989e1d25394faac2d02a37deaff6e2893bbf4b4eb7da64650a": "vision-distill-ppo-S/vision-distill-ppo-S.zip",
    "5639e53c43a9f9f45ea1dac34c8058f3c8250b76e7d922016a243e329a07a4ed": (
        "vision-distill-Circle/vision-distill-Circle.zip"
    ),
    "b22cd966241f91efae27854bd6313f2ff57b17b89aa7ce9f6b49d6ac4a70b411": "vision-distill-J/vision-distill-J.zip",
    "75721e4a6e948352f99586a674d9ab24afb3fb07bc62ddaf6949b783c68d8d29": "vision-dagger-J/vision-dagger-J.zip",
    "0cd4efa09868e16ae77ebeb21d6b954b0cb6f81a1db5ad208b059c88020ad403": "vision-dagger-Circle/vision-dagger-Circle.zip",
    "628cf97178bfa842d3c1a74bdc78e56071ede7c8a1cbb70b76b526af3a390853": (
        "vision-distill-ppo-Circle/vision-distill-ppo-Circle.zip"
    ),
    "b95ac725bf00271c31b1cb00bb383e29dc1c887d30fe7311e740e4c051d9510f": "vision-distill-ppo-J/vision-distill-ppo-J.zip",
}


class AgentLoadError(ValueError):
    """An agent spec could not be turned into an agent; the message names the spec and the reason."""


class UntrustedCodeError(AgentLoadError):
    """Loading the agent would run code from an untrusted file and ``trust_code`` was not given."""


@dataclass(frozen=True)
class PolicyIdentity:
    """What exactly an agent spec stands for: the key of every evaluation record it produces.

    ``sha256`` is of the policy file's bytes (the checkpoint, the ONNX graph, the Python file of a
    ``module:Class``), or of ``"racebench-builtin:<name>:v<version>"`` for a built-in agent.
    """

    kind: str  # "builtin", "sb3", "onnx" or "python"
    sha256: str
    source: str  # the spec (built-ins: the name)
    privileged: bool


def builtin_identity(name: str) -> PolicyIdentity:
    """The identity of a built-in agent: its name and code version."""
    digest = hashlib.sha256(f"racebench-builtin:{name}:v{BUILTIN_VERSIONS[name]}".encode()).hexdigest()
    return PolicyIdentity("builtin", digest, name, BUILTIN_PRIVILEGED[name])


def _sha256_bytes(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _python_source(spec: str) -> Path:
    """The file a ``module:Class`` or ``file.py:Class`` spec would execute, found without importing it."""
    target = spec.rpartition(":")[0]
    if target.endswith(".py"):
        path = Path(target)
    else:
        try:
            found = importlib.util.find_spec(target)
        except (ImportError, ValueError) as exc:
            raise AgentLoadError(f"agent spec {spec!r}: cannot find module {target!r}: {exc}") from exc
        if found is None or not found.origin or not Path(found.origin).is_file():
            raise AgentLoadError(f"agent spec {spec!r}: cannot find module {target!r}")
        path = Path(found.origin)
    if not path.is_file():
        raise AgentLoadError(f"agent spec {spec!r}: file {str(path)!r} does not exist")
    return path


def vecnormalize_path(checkpoint: str | Path) -> Path | None:
    """The ``VecNormalize`` statistics saved beside an SB3 checkpoint, or ``None``.

    SB3's ``VecNormalize.save`` takes any path; the usual places are the ones looked at here:
    ``<prefix>_vecnormalize_<n>_steps.pkl`` beside ``<prefix>_<n>_steps.zip`` (``CheckpointCallback`` with
    ``save_vecnormalize=True``) and, for any other name, ``vecnormalize.pkl`` in the checkpoint's folder
    (rl-baselines3-zoo's name, and ``racebench train``'s).
    """
    path = Path(checkpoint)
    periodic = re.fullmatch(r"(.*)_(\d+)_steps\.zip", path.name)
    if periodic:
        stats = path.with_name(f"{periodic[1]}_vecnormalize_{periodic[2]}_steps.pkl")
    else:
        stats = path.parent / "vecnormalize.pkl"
    return stats if stats.is_file() else None


def sb3_policy_sha256(checkpoint_sha256: str, stats_sha256: str | None) -> str:
    """The policy hash of an SB3 checkpoint: its bytes' sha256, or with ``VecNormalize`` statistics beside it
    (they change the actions), the sha256 of ``"<checkpoint sha256>+vecnormalize:<statistics sha256>"``."""
    if stats_sha256 is None:
        return checkpoint_sha256
    return hashlib.sha256(f"{checkpoint_sha256}+vecnormalize:{stats_sha256}".encode()).hexdigest()


def parse_agent_kwargs(text: str | None) -> dict[str, Any] | None:
    """The ``--agent-kwargs`` option: a JSON object of constructor keyword arguments (``None`` if not given)."""
    if text is None:
        return None
    try:
        kwargs = json.loads(text)
    except json.JSONDecodeError as exc:
        raise AgentLoadError(f"--agent-kwargs {text!r} is not valid JSON: {exc}") from exc
    if not isinstance(kwargs, dict):
        raise AgentLoadError(f"--agent-kwargs must be a JSON object such as '{{\"k\": 1}}', got {text!r}")
    return kwargs


def _kwargs_json(agent_kwargs: dict[str, Any]) -> str:
    """Canonical JSON of constructor arguments (sorted keys, no spaces): the form that is hashed."""
    try:
        return json.dumps(agent_kwargs, sort_keys=True, separators=(",", ":"), allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise AgentLoadError(f"agent kwargs must be plain JSON values: {exc}") from exc


def policy_identity(spec: str, agent_kwargs: dict[str, Any] | None = None) -> PolicyIdentity:
    """The :class:`PolicyIdentity` of an agent spec, computed from the file's bytes without running any of it.

    A ``module:Class`` built with ``agent_kwargs`` is another policy than the same class without them: its hash
    is the sha256 of ``"<file sha256>+kwargs:<canonical JSON>"``.
    """
    if agent_kwargs and ":" not in spec:
        raise AgentLoadError(f"agent kwargs apply to module:Class and file.py:Class agents only, not {spec!r}")
    if spec in BUILTIN_AGENTS:
        return builtin_identity(spec)
    if spec.endswith(".zip") or spec.endswith(".onnx"):
        path = Path(spec)
        if not path.is_file():
            raise AgentLoadError(f"policy file {spec!r} does not exist")
        digest = _sha256_bytes(path.read_bytes())
        if spec.endswith(".onnx"):
            return PolicyIdentity("onnx", digest, spec, False)
        stats = vecnormalize_path(path)
        return PolicyIdentity(
            "sb3", sb3_policy_sha256(digest, _sha256_bytes(stats.read_bytes()) if stats else None), spec, False
        )
    if ":" in spec:
        digest = _sha256_bytes(_python_source(spec).read_bytes())
        if agent_kwargs:
            digest = hashlib.sha256(f"{digest}+kwargs:{_kwargs_json(agent_kwargs)}".encode()).hexdigest()
        return PolicyIdentity("python", digest, spec, False)
    raise AgentLoadError(
        f"unknown agent spec {spec!r}: expected one of {BUILTIN_AGENTS}, a .zip (SB3) or .onnx file, or module:Class"
    )


def _refuse_untrusted(spec: str, why: str) -> UntrustedCodeError:
    return UntrustedCodeError(
        f"agent {spec!r}: {why}, which can run arbitrary code; pass --trust-code (trust_code=True) only if you "
        "trust where it came from (an ONNX export runs no code and needs no flag)"
    )


@runtime_checkable
class Agent(Protocol):
    """What the evaluator needs from an agent."""

    name: str
    obs_mode: str  # "vision" or "state": the observation the agent expects
    privileged: bool  # True: reset() receives the unwrapped env and the agent may read the true state

    def reset(self, env: Any = None, seed: int | None = None) -> None:
        """Start of an episode (``env`` is given to privileged agents only; ``seed`` is the episode's)."""

    def act(self, obs: Any) -> np.ndarray:
        """A CTBR action in ``[-1, 1]^4`` for one observation."""


class RandomAgent:
    """Uniform random actions, seeded per episode so a sweep is reproducible."""

    name = "random"
    obs_mode = "state"
    privileged = False

    def __init__(self) -> None:
        self.rng = np.random.default_rng(0)

    def reset(self, env: Any = None, seed: int | None = None) -> None:
        """Reseed from the episode seed."""
        self.rng = np.random.default_rng(seed)

    def act(self, obs: Any) -> np.ndarray:
        """A uniform sample of ``[-1, 1]^4``."""
        return self.rng.uniform(-1.0, 1.0, size=4).astype(np.float32)


class HoverAgent:
    """Hover thrust, zero body rates: the do-nothing baseline."""

    name = "hover"
    obs_mode = "state"
    privileged = False

    def __init__(self, params: QuadrotorParams | None = None) -> None:
        self.action = np.array([(params or QuadrotorParams()).hover_action, 0.0, 0.0, 0.0], dtype=np.float32)

    def reset(self, env: Any = None, seed: int | None = None) -> None:
        """Nothing to reset."""

    def act(self, obs: Any) -> np.ndarray:
        """The hover action."""
        return self.action


class FollowAgent:
    """Privileged gate-axis follower (:class:`~racebench.control.GateFollower`); it ignores obstacles."""

    name = "follow"
    obs_mode = "state"
    privileged = True

    def __init__(self) -> None:
        self.follower = GateFollower()
        self.env = None

    def reset(self, env: Any = None, seed: int | None = None) -> None:
        """Keep the unwrapped env to read the true state from."""
        if env is None:
            raise ValueError("FollowAgent is privileged: reset() needs the unwrapped RaceEnv")
        self.env = env

    def act(self, obs: Any) -> np.ndarray:
        """Fly along the next gate's axis."""
        return self.follower.act_privileged(self.env)


def _obs_mode_of(space: Any) -> str:
    from gymnasium import spaces

    if isinstance(space, spaces.Dict) and "depth" in space.spaces:
        return "vision"
    if isinstance(space, spaces.Box) and space.shape == (17,):
        return "state"
    raise AgentLoadError(f"policy observation space {space} is neither racebench's vision Dict nor its 17-d state")


class SB3Agent:
    """A stable-baselines3 or sb3-contrib checkpoint, acting deterministically.

    Recurrent policies (sb3-contrib ``RecurrentPPO``, or any policy whose ``predict`` takes a state) have
    their hidden state carried across steps and cleared at each episode start.

    Observations reach the policy as they did in training: a policy trained on ``depth_format="uint8"``
    gets each float depth image through :func:`racebench.env.depth_to_uint8` (the uint8 envs' own
    observation), and ``VecNormalize`` statistics saved beside the checkpoint (:func:`vecnormalize_path`)
    normalise the observations as ``VecNormalize.normalize_obs`` does. The statistics file is a pickle, so it
    needs ``trust_code`` even beside a shipped checkpoint, and its hash is part of :attr:`sha256`
    (:func:`sb3_policy_sha256`); :attr:`checkpoint_sha256` is the zip's alone.
    """

    privileged = False

    def __init__(self, path: str | Path, device: str = "cpu", trust_code: bool = False) -> None:
        path = Path(path)
        if not path.is_file():
            raise AgentLoadError(f"SB3 checkpoint {str(path)!r} does not exist")
        data = path.read_bytes()  # hashed and loaded from the same bytes: no swap between check and load
        self.checkpoint_sha256 = _sha256_bytes(data)
        stats_path = vecnormalize_path(path)
        stats = stats_path.read_bytes() if stats_path is not None else None
        self.sha256 = sb3_policy_sha256(self.checkpoint_sha256, _sha256_bytes(stats) if stats is not None else None)
        if not zipfile.is_zipfile(io.BytesIO(data)):
            raise AgentLoadError(f"SB3 checkpoint {str(path)!r} is not a zip archive (corrupt or not a checkpoint)")
        if not (trust_code or self.checkpoint_sha256 in TRUSTED_CHECKPOINTS):
            raise _refuse_untrusted(str(path), "an SB3 checkpoint is unpickled when loaded")
        if stats is not None and not trust_code:
            raise _refuse_untrusted(str(stats_path), "VecNormalize statistics beside the checkpoint are unpickled")
        self.model = self._load(path, device, data)
        self.name = path.stem
        self.obs_mode = _obs_mode_of(self.model.observation_space)
        self.normalizer = _load_vecnormalize(stats_path, stats) if stats is not None else None
        self.uint8_depth = self.obs_mode == "vision" and self.model.observation_space["depth"].dtype == np.uint8
        self.recurrent = "Recurrent" in type(self.model.policy).__name__ or hasattr(self.model.policy, "recurrent")
        self.state: Any = None
        self.episode_start = np.ones((1,), dtype=bool)

    def prepare(self, obs: Any) -> Any:
        """One observation (or a stacked batch) of the standard envs → what the policy was trained on."""
        if self.uint8_depth:
            from racebench.env import depth_to_uint8

            obs = {**obs, "depth": depth_to_uint8(obs["depth"])}
        if self.normalizer is not None:
            obs = self.normalizer.normalize_obs(obs)
        return obs

    @staticmethod
    def _load(path: Path, device: str, raw: bytes | None = None) -> Any:
        """Load with the algorithm class the checkpoint names (the caller has decided to trust it)."""
        from stable_baselines3 import A2C, DDPG, PPO, SAC, TD3
        from stable_baselines3.common.save_util import load_from_zip_file

        raw = path.read_bytes() if raw is None else raw
        try:
            data, _, _ = load_from_zip_file(io.BytesIO(raw), device=device, print_system_info=False)
        except Exception as exc:  # noqa: BLE001 - SB3 raises many kinds on a damaged archive
            raise AgentLoadError(f"SB3 checkpoint {str(path)!r} could not be read: {exc}") from exc
        if data is None:  # e.g. a zip cut short after a nested torch archive, which then opens as that one
            raise AgentLoadError(f"SB3 checkpoint {str(path)!r} holds no model data: truncated or not an SB3 save")
        policy_name = getattr(data.get("policy_class"), "__name__", "")
        candidates: list[Any] = []
        if "Recurrent" in policy_name:
            try:
                from sb3_contrib import RecurrentPPO
            except ImportError as exc:
                raise AgentLoadError(f"{str(path)!r} holds a recurrent policy: pip install sb3-contrib") from exc
            candidates.append(RecurrentPPO)
        candidates += [PPO, SAC, TD3, A2C, DDPG]
        errors = []
        for algorithm in candidates:
            try:
                return algorithm.load(io.BytesIO(raw), device=device)
            except Exception as exc:  # noqa: BLE001 - try the next algorithm class
                errors.append(f"{algorithm.__name__}: {exc}")
        raise AgentLoadError(f"SB3 checkpoint {str(path)!r} could not be loaded by any algorithm ({'; '.join(errors)})")

    def reset(self, env: Any = None, seed: int | None = None) -> None:
        """Clear the recurrent state."""
        self.state = None
        self.episode_start = np.ones((1,), dtype=bool)

    def start(self, slots: int) -> None:
        """Prepare ``slots`` parallel episodes for :meth:`act_batch` (lockstep evaluation)."""
        import torch

        policy = self.model.policy
        policy.set_training_mode(False)  # once here, not per call as ``predict`` does
        self.lean = _is_gaussian_actor_critic(policy)
        self.batch_starts = np.ones((slots,), dtype=np.float32)
        self.batch_state: Any = None
        if self.recurrent:
            zeros = torch.zeros((policy.lstm_hidden_state_shape[0], slots, policy.lstm_hidden_state_shape[2]))
            self.batch_state = (zeros, zeros.clone())

    def reset_slot(self, slot: int) -> None:
        """A new episode in ``slot``: its recurrent state is cleared at the next call."""
        self.batch_starts[slot] = 1.0

    def act_batch(self, observations: list[Any]) -> np.ndarray:
        """Deterministic actions ``(slots, 4)`` for one observation per slot, in one forward pass.

        The same computation as ``model.predict`` on the stacked batch (tested), without its per-call
        overhead (mode switches, state conversions between numpy and torch), which at batch 16 cost as
        much as the network itself.
        """
        import torch

        policy = self.model.policy
        obs, _ = policy.obs_to_tensor(self.prepare(_stack(observations, self.obs_mode)))
        with torch.no_grad():  # not inference_mode: RaceFeatures converts its CNN weights on first use
            if self.lean:
                actions = self._gaussian_mean(policy, obs)
            elif self.recurrent:
                starts = torch.from_numpy(self.batch_starts)
                actions, self.batch_state = policy._predict(
                    obs, lstm_states=self.batch_state, episode_starts=starts, deterministic=True
                )
                self.batch_starts[:] = 0.0
            else:
                actions = policy._predict(obs, deterministic=True)
        actions = actions.cpu().numpy().reshape((-1, *self.model.action_space.shape))
        if policy.squash_output:
            return policy.unscale_action(actions)
        actions = np.clip(actions, self.model.action_space.low, self.model.action_space.high)
        return self._to_ctbr(actions, observations)

    def _to_ctbr(self, actions: np.ndarray, observations: Any) -> np.ndarray:
        """The env's actions for the policy's outputs: an acceleration-command policy's (``action_output``) through
        :func:`racebench.control.command_to_ctbr` on the observations' state, any other's unchanged."""
        if getattr(self.model.policy, "action_output", "ctbr") == "ctbr":
            return actions
        from racebench.control import command_to_ctbr

        observations = observations if isinstance(observations, list) else [observations]
        states = np.stack([o["state"] if isinstance(o, dict) else o for o in observations])
        return command_to_ctbr(actions.reshape(len(states), 4), states).reshape(actions.shape)

    def _gaussian_mean(self, policy: Any, obs: Any) -> Any:
        """The deterministic action of a Gaussian actor-critic, computed as ``_predict`` does, minus its overhead.

        ``_predict`` builds a distribution object (and sb3-contrib re-dispatches the sequence pass) on every
        call, overhead of the size of the small networks' own arithmetic; the mean of a diagonal Gaussian is the
        action head's output, so the same layers run in the same order (tested equal to ``_predict``).
        """
        import torch
        from stable_baselines3.common.policies import BaseModel

        features = BaseModel.extract_features(policy, obs, policy.pi_features_extractor)
        if self.recurrent:
            keep = torch.from_numpy(1.0 - self.batch_starts).view(1, -1, 1)
            hidden, cell = self.batch_state
            output, (hidden, cell) = policy.lstm_actor(features.unsqueeze(0), (keep * hidden, keep * cell))
            self.batch_state = (hidden, cell)
            self.batch_starts[:] = 0.0
            features = output[0]
        return policy.action_net(policy.mlp_extractor.forward_actor(features))

    def act(self, obs: Any) -> np.ndarray:
        """Deterministic action of the policy."""
        raw, obs = obs, self.prepare(obs)
        if self.recurrent:
            action, self.state = self.model.predict(
                obs, state=self.state, episode_start=self.episode_start, deterministic=True
            )
            self.episode_start = np.zeros((1,), dtype=bool)
        else:
            action, _ = self.model.predict(obs, deterministic=True)
        return self._to_ctbr(action, raw)


def _is_gaussian_actor_critic(policy: Any) -> bool:
    """Whether ``policy`` is a (recurrent) SB3 actor-critic with a diagonal Gaussian head and a one-layer RNN.

    For those :meth:`SB3Agent.act_batch` computes the mean action directly; anything else goes through
    ``_predict``.
    """
    from stable_baselines3.common.distributions import DiagGaussianDistribution
    from stable_baselines3.common.policies import ActorCriticPolicy

    if not isinstance(policy, ActorCriticPolicy) or type(policy.action_dist) is not DiagGaussianDistribution:
        return False
    # Only classes whose forward pass is known: SB3's, sb3-contrib's and racebench's own GRU policy. A user's
    # subclass may override _predict or the sequence pass, and must then be run through them.
    if not type(policy).__module__.startswith(("stable_baselines3.", "sb3_contrib.", "racebench.training.")):
        return False
    if policy.squash_output or getattr(policy, "shared_lstm", False):
        return False
    if not hasattr(policy.mlp_extractor, "forward_actor"):
        return False
    rnn = getattr(policy, "lstm_actor", None)
    return rnn is None or (rnn.num_layers == 1 and not rnn.batch_first)


def _load_vecnormalize(path: Path, data: bytes) -> Any:
    """The observation normaliser of a trusted ``VecNormalize`` pickle, or ``None`` if it normalises rewards only."""
    from stable_baselines3.common.vec_env import VecNormalize

    try:
        normalizer = pickle.loads(data)  # noqa: S301 - the caller checked trust_code; VecNormalize.load does this
    except Exception as exc:  # noqa: BLE001 - unpickling raises many kinds on a damaged file
        raise AgentLoadError(f"VecNormalize statistics {str(path)!r} could not be read: {exc}") from exc
    if not isinstance(normalizer, VecNormalize):
        raise AgentLoadError(f"{str(path)!r} holds a {type(normalizer).__name__}, not SB3 VecNormalize statistics")
    # Reward statistics alone (racebench train's) do not touch what the policy sees.
    return normalizer if normalizer.norm_obs else None


class OnnxAgent:
    """An ONNX policy run with onnxruntime: loading it runs no code from the file.

    Expected graph: inputs named ``state`` (float32 ``[batch, 17]``) and, for vision policies, ``depth``
    (float32 ``[batch, 1, 64, 64]``); the first output is the action (float32 ``[batch, 4]``). A recurrent
    policy adds an input ``hidden`` (float32 ``[batch, H]``, zeros at episode start) and a second output,
    the next hidden state.
    """

    privileged = False

    def __init__(self, path: str | Path) -> None:
        import onnxruntime as ort

        path = Path(path)
        if not path.is_file():
            raise AgentLoadError(f"ONNX file {str(path)!r} does not exist")
        options = ort.SessionOptions()
        # One thread, as for torch (racebench.evaluation.torch_threads): an evaluation runs one process per core.
        options.intra_op_num_threads = 1
        options.inter_op_num_threads = 1
        try:
            self.session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
        except Exception as exc:  # noqa: BLE001 - onnxruntime raises its own exception types
            raise AgentLoadError(f"ONNX file {str(path)!r} could not be loaded: {exc}") from exc
        self.inputs = {i.name: i for i in self.session.get_inputs()}
        if "state" not in self.inputs:
            raise AgentLoadError(f"ONNX file {str(path)!r} has no input named 'state' (inputs: {list(self.inputs)})")
        self.name = path.stem
        self.obs_mode = "vision" if "depth" in self.inputs else "state"
        self.hidden_size = self.inputs["hidden"].shape[-1] if "hidden" in self.inputs else None
        self.hidden: np.ndarray | None = None

    def reset(self, env: Any = None, seed: int | None = None) -> None:
        """Zero the hidden state of a recurrent policy."""
        self.hidden = None if self.hidden_size is None else np.zeros((1, self.hidden_size), dtype=np.float32)

    def start(self, slots: int) -> None:
        """Prepare ``slots`` parallel episodes for :meth:`act_batch` (lockstep evaluation)."""
        self.batch_hidden = None if self.hidden_size is None else np.zeros((slots, self.hidden_size), np.float32)

    def reset_slot(self, slot: int) -> None:
        """A new episode in ``slot``: zero its hidden state."""
        if self.batch_hidden is not None:
            self.batch_hidden[slot] = 0.0

    def act_batch(self, observations: list[Any]) -> np.ndarray:
        """Actions ``(slots, 4)`` for one observation per slot, in one run of the graph."""
        obs = _stack(observations, self.obs_mode)
        feed = dict(obs) if self.obs_mode == "vision" else {"state": obs}
        if self.batch_hidden is not None:
            feed["hidden"] = self.batch_hidden
        outputs = self.session.run(None, feed)
        if self.batch_hidden is not None:
            self.batch_hidden = outputs[1]
        return outputs[0]

    def act(self, obs: Any) -> np.ndarray:
        """Run the graph on one observation."""
        if self.obs_mode == "vision":
            feed = {"state": obs["state"][None].astype(np.float32), "depth": obs["depth"][None].astype(np.float32)}
        else:
            feed = {"state": np.asarray(obs, dtype=np.float32)[None]}
        if self.hidden is not None:
            feed["hidden"] = self.hidden
        outputs = self.session.run(None, feed)
        if self.hidden is not None:
            self.hidden = outputs[1]
        return outputs[0][0]


def _stack(observations: list[Any], obs_mode: str) -> Any:
    """One batch from per-episode observations: a dict of stacked float32 arrays (vision) or an array."""
    if obs_mode == "vision":
        return {
            "state": np.stack([o["state"] for o in observations]).astype(np.float32, copy=False),
            "depth": np.stack([o["depth"] for o in observations]).astype(np.float32, copy=False),
        }
    return np.stack([np.asarray(o, dtype=np.float32) for o in observations])


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


def export_policy(model: Any, path: str | Path) -> Path:
    """Save an SB3 model as a policy-only checkpoint: the weights and what loading and acting need, with the
    optimizer's state (Adam's moments: twice the weights) and :data:`TRAINING_ONLY_ATTRIBUTES` left out.

    It loads like any SB3 save and acts exactly as ``model`` does; training resumed from it starts with fresh
    Adam moments. ``model`` itself is left as it was.
    """
    path = Path(path)
    if path.suffix != ".zip":
        raise ValueError(f"a policy-only checkpoint is an SB3 .zip, not {str(path)!r}")
    optimizer = model.policy.optimizer
    # A fresh optimizer of the same kind and settings: its state dict is the settings alone.
    model.policy.optimizer = type(optimizer)(model.policy.parameters(), **optimizer.defaults)
    partial = path.with_name(f".{path.stem}.partial.zip")  # renamed into place: never a half-written policy
    try:
        model.save(partial, exclude=[name for name in TRAINING_ONLY_ATTRIBUTES if name in model.__dict__])
        os.replace(partial, path)
    finally:
        model.policy.optimizer = optimizer
        partial.unlink(missing_ok=True)
    return path


def export_onnx(model: Any, path: str | Path) -> Path:
    """Export the deterministic actor of an SB3 actor-critic policy to ONNX (see :class:`OnnxAgent`).

    Feed-forward policies and racebench's recurrent GRU policies (``RecurrentGRUPolicy``: the actor's GRU
    state becomes the ``hidden`` input and the second output). LSTM policies are refused: their cell state
    has no place in the :class:`OnnxAgent` interface.
    """
    import torch

    from racebench.training.policies import LSTMShapedGRU

    policy = model.policy.to("cpu").eval()
    vision = _obs_mode_of(model.observation_space) == "vision"
    gru = getattr(policy, "lstm_actor", None)
    if gru is not None and not isinstance(gru, LSTMShapedGRU):
        raise ValueError(
            "export_onnx: recurrent policies must use racebench's GRU (an LSTM's cell state is not exported)"
        )
    if gru is not None and gru.num_layers != 1:
        raise ValueError(f"export_onnx: a GRU of {gru.num_layers} layers is not supported (1 layer)")
    if getattr(policy, "action_output", "ctbr") != "ctbr":
        raise ValueError(
            f"export_onnx: the policy outputs {policy.action_output} commands, not the env's CTBR action (its "
            "controller, racebench.control.command_to_ctbr, is not part of the network)"
        )

    class Actor(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.policy = policy

        def forward(self, state: torch.Tensor, *rest: torch.Tensor) -> Any:
            depth, hidden = (rest[0], rest[1:]) if vision else (None, rest)
            obs = {"state": state, "depth": depth} if vision else state
            features = self.policy.extract_features(obs, self.policy.pi_features_extractor)
            if gru is None:
                return torch.clamp(self.policy.action_net(self.policy.mlp_extractor.forward_actor(features)), -1, 1)
            output, next_hidden = torch.nn.GRU.forward(gru, features.unsqueeze(0), hidden[0].unsqueeze(0))
            action = self.policy.action_net(self.policy.mlp_extractor.forward_actor(output[0]))
            return torch.clamp(action, -1.0, 1.0), next_hidden[0]

    args: list[torch.Tensor] = [torch.zeros(1, 17)]
    names = ["state"]
    if vision:
        args.append(torch.zeros(1, 1, 64, 64))
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
        dynamo=False,
    )
    return path


def _python_agent(spec: str, trust_code: bool = False, agent_kwargs: dict[str, Any] | None = None) -> Any:
    target, _, cls_name = spec.rpartition(":")
    _python_source(spec)  # a missing file or module is named before the trust question
    if not trust_code:
        raise _refuse_untrusted(spec, "a Python agent is imported and run")
    try:
        if target.endswith(".py"):
            file = Path(target)
            if not file.is_file():
                raise AgentLoadError(f"agent spec {spec!r}: file {target!r} does not exist")
            module_spec = importlib.util.spec_from_file_location(file.stem, file)
            module = importlib.util.module_from_spec(module_spec)
            module_spec.loader.exec_module(module)
        else:
            module = importlib.import_module(target)
    except AgentLoadError:
        raise
    except Exception as exc:  # noqa: BLE001 - report any import failure with the spec
        raise AgentLoadError(f"agent spec {spec!r}: cannot import {target!r}: {exc}") from exc
    cls = getattr(module, cls_name, None)
    if cls is None:
        raise AgentLoadError(f"agent spec {spec!r}: {target!r} has no attribute {cls_name!r}")
    kwargs = agent_kwargs or {}
    try:
        agent = cls(**kwargs)
    except TypeError as exc:  # wrong or missing constructor arguments: say which, and how to pass them
        raise AgentLoadError(
            f"agent spec {spec!r}: {cls_name}(**{kwargs}) failed: {exc} (pass its arguments with --agent-kwargs JSON)"
        ) from exc
    except Exception as exc:  # noqa: BLE001 - any constructor failure, reported with the spec
        raise AgentLoadError(f"agent spec {spec!r}: {cls_name}(**{kwargs}) raised {type(exc).__name__}: {exc}") from exc
    for attr in ("reset", "act"):
        if not callable(getattr(agent, attr, None)):
            raise AgentLoadError(f"agent spec {spec!r}: {cls_name} has no method {attr}()")
    if getattr(agent, "privileged", False):
        raise AgentLoadError(
            f"agent spec {spec!r}: only built-in agents ({[k for k, v in BUILTIN_PRIVILEGED.items() if v]}) may be "
            "privileged; a user agent acts on its observation alone"
        )
    if not hasattr(agent, "obs_mode"):
        raise AgentLoadError(f"agent spec {spec!r}: {cls_name} must declare obs_mode = 'vision' or 'state'")
    agent.name = getattr(agent, "name", cls_name)
    agent.privileged = False
    if agent.obs_mode not in ("vision", "state"):
        raise AgentLoadError(f"agent spec {spec!r}: obs_mode must be 'vision' or 'state', got {agent.obs_mode!r}")
    return agent


def load_agent(spec: str, trust_code: bool = False, agent_kwargs: dict[str, Any] | None = None) -> Agent:
    """Build an agent from a spec string (see the module docstring).

    ``trust_code`` allows specs that run code from a file (SB3 ``.zip`` outside :data:`TRUSTED_CHECKPOINTS`,
    ``module:Class``, ``file.py:Class``); without it they raise :class:`UntrustedCodeError` before any of
    that code runs. ``agent_kwargs`` are the keyword arguments of a ``module:Class`` constructor (an error for
    any other spec).
    """
    if agent_kwargs and ":" not in spec:
        raise AgentLoadError(f"agent kwargs apply to module:Class and file.py:Class agents only, not {spec!r}")
    if spec == "random":
        return RandomAgent()
    if spec == "hover":
        return HoverAgent()
    if spec == "planner":
        from racebench.planner import PlannerAgent

        return PlannerAgent()
    if spec == "planner-fast":
        from racebench.planner import FastPlannerAgent

        return FastPlannerAgent()
    if spec == "follow":
        return FollowAgent()
    if spec.endswith(".zip"):
        return SB3Agent(spec, trust_code=trust_code)
    if spec.endswith(".onnx"):
        return OnnxAgent(spec)
    if ":" in spec:
        if agent_kwargs:
            _kwargs_json(agent_kwargs)  # plain JSON values only: they are hashed into the policy identity
        return _python_agent(spec, trust_code, agent_kwargs)
    raise AgentLoadError(
        f"unknown agent spec {spec!r}: expected one of {BUILTIN_AGENTS}, a .zip (SB3) or .onnx file, or module:Class"
    )
