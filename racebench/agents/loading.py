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
sha256 of their bytes (:data:`TRUSTED_CHECKPOINTS`). ONNX files run no code and need no flag. Training resumes
follow the same rule (:func:`require_trusted`), and also trust what their own run folder's :data:`WRITTEN_FILE`
lists: the sha256 of every checkpoint and statistics file the run wrote itself.

Only built-in agents can be privileged, and the loader, not the agent, decides which
(:data:`BUILTIN_PRIVILEGED`): a user agent is never handed the environment.

**What a policy hash covers** (:func:`policy_identity`, the key of every evaluation record): a built-in's name and
code version; an SB3 checkpoint's bytes and the ``VecNormalize`` statistics it is flown with (found by name
beside it or in rl-baselines3-zoo's run layout, or chosen: :func:`resolve_vecnormalize`); an ONNX file's bytes and
every external-data file its tensors reference (weights saved beside it, :func:`onnx_external_data`); a Python
agent's file and every module it loads from outside the installed code, that is from outside the standard
library, site-packages and racebench itself (:func:`python_agent_modules`: the modules its source imports by name,
found on ``sys.path`` without running them, then theirs, recursively, hashed in sorted order of name), and its
constructor arguments. A Python agent that loads such a module in any other way (``importlib``, a pickle) while it
is imported or constructed is refused, since its hash could not cover that module.
"""

from __future__ import annotations

import importlib
import importlib.util
import io
import logging
import pickle
import sys
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from racebench.agents.base import (
    BUILTIN_AGENTS,
    BUILTIN_PRIVILEGED,
    Agent,
    AgentLoadError,
    obs_mode_of,
)
from racebench.agents.builtin import FollowAgent, HoverAgent, RandomAgent
from racebench.agents.control import command_to_ctbr
from racebench.agents.planner import FastPlannerAgent, PlannerAgent
from racebench.agents.trust import (
    VecNormalizeChoice,
    _check_vecnormalize_spec,
    _is_agent_code,
    _kwargs_json,
    _python_package,
    _python_source,
    _refuse_untrusted,
    _sha256_bytes,
    onnx_policy_sha256,
    python_agent_modules,
    require_trusted,
    resolve_vecnormalize,
    sb3_policy_sha256,
    sb3_stats_sha256,
)
from racebench.envs.env import depth_to_uint8

logger = logging.getLogger("racebench.agents.loading")
_warned_flat_depth = False  # the flattened-depth warning is given once per process


def flattens_depth(policy: Any) -> bool:
    """Whether an SB3 policy reads the ``depth`` image through a plain ``Flatten`` (stock ``MultiInputPolicy`` on
    the default float32 depth, which SB3 does not take for an image) rather than a CNN."""
    from stable_baselines3.common.torch_layers import CombinedExtractor
    from torch import nn

    extractors = [getattr(policy, name, None) for name in ("features_extractor", "pi_features_extractor")]
    return any(
        isinstance(e, CombinedExtractor) and isinstance(e.extractors["depth"], nn.Flatten)
        for e in extractors
        if e is not None and "depth" in getattr(e, "extractors", {})
    )


def warn_flattened_depth(policy: Any, source: str) -> bool:
    """Say once per process that ``policy`` flattens the depth image into an MLP and how to get a CNN; True if it
    does."""
    global _warned_flat_depth
    if not flattens_depth(policy):
        return False
    if not _warned_flat_depth:
        _warned_flat_depth = True
        logger.warning(
            f"{source}: this policy flattens the 64x64 depth image into an MLP input (stock SB3 MultiInputPolicy on "
            "the default float32 depth, which SB3 does not take for an image). Train on "
            'gym.make(..., depth_format="uint8") for a NatureCNN on the depth (docs/training.md'
            "#train-with-stock-stable-baselines3); racebench evaluates either."
        )
    return True


def _unused_schedule(_progress_remaining: float) -> float:
    return 0.0


# SB3 pickles a model's training schedules with cloudpickle, whose pickles do not load across its major versions
# (a zip written under cloudpickle 3 warns "Can't get attribute '_function_setstate'" under 2). Flying a policy
# never uses them and a resumed run rebuilds them from its config (racebench.training.ppo.restore_schedules), so
# they are not unpickled at all: SB3's documented custom_objects replaces them.
UNREAD_SCHEDULES: dict[str, Any] = {
    "learning_rate": 0.0,
    "lr_schedule": _unused_schedule,
    "clip_range": _unused_schedule,
}


class SB3Agent:
    """A stable-baselines3 or sb3-contrib checkpoint, acting deterministically.

    Recurrent policies (sb3-contrib ``RecurrentPPO``, or any policy whose ``predict`` takes a state) have
    their hidden state carried across steps and cleared at each episode start.

    Observations reach the policy as they did in training: a policy trained on ``depth_format="uint8"``
    gets each float depth image through :func:`racebench.envs.env.depth_to_uint8` (the uint8 envs' own
    observation), and ``VecNormalize`` statistics (``vecnormalize``: those matched to the checkpoint by name,
    beside it or in rl-baselines3-zoo's layout, a chosen file, or ``False`` for none; :func:`resolve_vecnormalize`)
    normalise the observations as ``VecNormalize.normalize_obs`` does. The statistics file is a pickle, so it
    needs ``trust_code`` even beside a shipped checkpoint, and its hash is part of :attr:`sha256`
    (:func:`sb3_policy_sha256`); :attr:`checkpoint_sha256` is the zip's alone, :attr:`stats_path` the file used.
    """

    privileged = False

    def __init__(
        self, path: str | Path, device: str = "cpu", trust_code: bool = False, vecnormalize: VecNormalizeChoice = None
    ) -> None:
        path = Path(path)
        if not path.is_file():
            raise AgentLoadError(f"SB3 checkpoint {str(path)!r} does not exist")
        data = path.read_bytes()  # hashed and loaded from the same bytes: no swap between check and load
        self.checkpoint_sha256 = _sha256_bytes(data)
        stats_path = resolve_vecnormalize(path, vecnormalize)
        stats = stats_path.read_bytes() if stats_path is not None else None
        marker = _sha256_bytes(stats) if stats is not None else sb3_stats_sha256(path, None, vecnormalize)
        self.sha256 = sb3_policy_sha256(self.checkpoint_sha256, marker)
        self.stats_path = stats_path
        if not zipfile.is_zipfile(io.BytesIO(data)):
            raise AgentLoadError(f"SB3 checkpoint {str(path)!r} is not a zip archive (corrupt or not a checkpoint)")
        require_trusted(path, data, "an SB3 checkpoint is unpickled when loaded", trust_code, what="agent")
        if stats is not None and not trust_code:
            raise _refuse_untrusted(str(stats_path), "VecNormalize statistics of the checkpoint are unpickled")
        self.model = self._load(path, device, data)
        self.name = path.stem
        self.obs_mode = obs_mode_of(self.model.observation_space)
        self.normalizer = _load_vecnormalize(stats_path, stats) if stats is not None else None
        self.uint8_depth = self.obs_mode == "vision" and self.model.observation_space["depth"].dtype == np.uint8
        if self.obs_mode == "vision":
            warn_flattened_depth(self.model.policy, str(path))
        self.recurrent = "Recurrent" in type(self.model.policy).__name__ or hasattr(self.model.policy, "recurrent")
        self.state: Any = None
        self.episode_start = np.ones((1,), dtype=bool)

    def prepare(self, obs: Any) -> Any:
        """One observation (or a stacked batch) of the standard envs → what the policy was trained on."""
        if self.uint8_depth:
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
            data, _, _ = load_from_zip_file(io.BytesIO(raw), device=device, custom_objects=UNREAD_SCHEDULES,
                                            print_system_info=False)  # fmt: skip
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
                return algorithm.load(io.BytesIO(raw), device=device, custom_objects=UNREAD_SCHEDULES)
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
        self.lean = is_gaussian_actor_critic(policy)
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
        :func:`racebench.agents.control.command_to_ctbr` on the observations' state, any other's unchanged."""
        if getattr(self.model.policy, "action_output", "ctbr") == "ctbr":
            return actions

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


def is_gaussian_actor_critic(policy: Any) -> bool:
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
    if not type(policy).__module__.startswith(("stable_baselines3.", "sb3_contrib.", "racebench.agents.recurrent")):
        return False
    if policy.squash_output or getattr(policy, "shared_lstm", False):
        return False
    if not hasattr(policy.mlp_extractor, "forward_actor"):
        return False
    rnn = getattr(policy, "lstm_actor", None)
    return rnn is None or (rnn.num_layers == 1 and not rnn.batch_first)


def load_vecnormalize_statistics(path: str | Path, data: bytes) -> Any:
    """The ``VecNormalize`` object of a statistics pickle whose bytes ``data`` the caller has decided to trust
    (:func:`require_trusted`): SB3 saves them only as a pickle, so they cannot be read without unpickling."""
    from stable_baselines3.common.vec_env import VecNormalize

    try:
        normalizer = pickle.loads(data)  # noqa: S301 - the caller checked the trust rule; VecNormalize.load does this
    except Exception as exc:  # noqa: BLE001 - unpickling raises many kinds on a damaged file
        raise AgentLoadError(f"VecNormalize statistics {str(path)!r} could not be read: {exc}") from exc
    if not isinstance(normalizer, VecNormalize):
        raise AgentLoadError(f"{str(path)!r} holds a {type(normalizer).__name__}, not SB3 VecNormalize statistics")
    return normalizer


def _load_vecnormalize(path: Path, data: bytes) -> Any:
    """The observation normaliser of a trusted ``VecNormalize`` pickle, or ``None`` if it normalises rewards only."""
    normalizer = load_vecnormalize_statistics(path, data)
    # Reward statistics alone (racebench train's) do not touch what the policy sees.
    return normalizer if normalizer.norm_obs else None


class OnnxAgent:
    """An ONNX policy run with onnxruntime: loading it runs no code from the file.

    Expected graph: inputs named ``state`` (float32 ``[batch, 17]``) and, for vision policies, ``depth``
    (float32 ``[batch, 1, 64, 64]``); the first output is the action (float32 ``[batch, 4]``). A recurrent
    policy adds an input ``hidden`` (float32 ``[batch, H]``, zeros at episode start) and a second output,
    the next hidden state. Weights may be saved as ONNX external data beside the file; :attr:`sha256`
    (:func:`onnx_policy_sha256`) covers them.
    """

    privileged = False

    def __init__(self, path: str | Path) -> None:
        import onnxruntime as ort

        path = Path(path)
        if not path.is_file():
            raise AgentLoadError(f"ONNX file {str(path)!r} does not exist")
        # Checked here first: a missing external-data file is then one line, not onnxruntime's multi-line error.
        self.sha256 = onnx_policy_sha256(path, _sha256_bytes(path.read_bytes()))
        options = ort.SessionOptions()
        # One thread, as for torch (racebench.evaluation.worker.torch_threads): an evaluation runs one process per core.
        options.intra_op_num_threads = 1
        options.inter_op_num_threads = 1
        try:
            # The link's target: its external data are read beside it, as onnx_policy_sha256 hashes them.
            self.session = ort.InferenceSession(str(path.resolve()), options, providers=["CPUExecutionProvider"])
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


def _python_agent(spec: str, trust_code: bool = False, agent_kwargs: dict[str, Any] | None = None) -> Any:
    target, _, cls_name = spec.rpartition(":")
    _python_source(spec)  # a missing file or module is named before the trust question
    if not trust_code:
        raise _refuse_untrusted(spec, "a Python agent is imported and run")
    before = set(sys.modules)
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
    _check_hashed_modules(spec, before)
    agent.name = getattr(agent, "name", cls_name)
    agent.privileged = False
    if agent.obs_mode not in ("vision", "state"):
        raise AgentLoadError(f"agent spec {spec!r}: obs_mode must be 'vision' or 'state', got {agent.obs_mode!r}")
    return agent


def _check_hashed_modules(spec: str, before: set[str]) -> None:
    """Refuse a Python agent that loaded user code its policy hash does not cover (imported other than by name).

    ``before``: the names in ``sys.modules`` before the agent's module was loaded. A module already imported then
    is not seen here; its file is hashed all the same when the agent's source imports it by name.
    """
    covered = {
        _python_source(spec).resolve(),
        *python_agent_modules(_python_source(spec), _python_package(spec)).values(),
    }
    for name, module in sorted(dict(sys.modules).items()):
        file = getattr(module, "__file__", None)
        if name not in before and _is_agent_code(file) and Path(file).resolve() not in covered:
            raise AgentLoadError(
                f"agent spec {spec!r}: it loaded module {name!r} ({file}) without importing it by name, so its policy "
                "hash cannot cover it; import it by name (import x / from x import y) in the agent's source"
            )


def load_agent(
    spec: str,
    trust_code: bool = False,
    agent_kwargs: dict[str, Any] | None = None,
    vecnormalize: VecNormalizeChoice = None,
) -> Agent:
    """Build an agent from a spec string (see the module docstring).

    ``trust_code`` allows specs that run code from a file (SB3 ``.zip`` outside :data:`TRUSTED_CHECKPOINTS`,
    ``module:Class``, ``file.py:Class``); without it they raise :class:`UntrustedCodeError` before any of
    that code runs. ``agent_kwargs`` are the keyword arguments of a ``module:Class`` constructor (an error for
    any other spec). ``vecnormalize`` chooses an SB3 checkpoint's ``VecNormalize`` statistics (see
    :func:`resolve_vecnormalize`; an error for any other spec).
    """
    if agent_kwargs and ":" not in spec:
        raise AgentLoadError(f"agent kwargs apply to module:Class and file.py:Class agents only, not {spec!r}")
    _check_vecnormalize_spec(spec, vecnormalize)
    if spec == "random":
        return RandomAgent()
    if spec == "hover":
        return HoverAgent()
    if spec == "planner":
        return PlannerAgent()
    if spec == "planner-fast":
        return FastPlannerAgent()
    if spec == "follow":
        return FollowAgent()
    if spec.endswith(".zip"):
        return SB3Agent(spec, trust_code=trust_code, vecnormalize=vecnormalize)
    if spec.endswith(".onnx"):
        return OnnxAgent(spec)
    if ":" in spec:
        if agent_kwargs:
            _kwargs_json(agent_kwargs)  # plain JSON values only: they are hashed into the policy identity
        return _python_agent(spec, trust_code, agent_kwargs)
    raise AgentLoadError(
        f"unknown agent spec {spec!r}: expected one of {BUILTIN_AGENTS}, a .zip (SB3) or .onnx file, or module:Class"
    )
