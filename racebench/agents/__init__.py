"""Agents: the protocol and the built-ins, loading a spec and trusting it, export, control, the planners.

* :mod:`~racebench.agents.base`: the :class:`Agent` protocol, the built-ins' registry;
* :mod:`~racebench.agents.builtin`: the built-ins that need no planning (random, hover, follow);
* :mod:`~racebench.agents.trust`: policy identities (hashes) and which files are trusted to unpickle or run;
* :mod:`~racebench.agents.loading`: :func:`load_agent`, SB3 and ONNX agents;
* :mod:`~racebench.agents.export`: policy-only checkpoints and ONNX export;
* :mod:`~racebench.agents.recurrent`: the recurrent (GRU) policy network that training builds and loading unpickles;
* :mod:`~racebench.agents.control`: the CTBR controller; :mod:`~racebench.agents.planner`: the privileged planners.

The names of the former module ``racebench.agents`` are re-exported here.
"""

from __future__ import annotations

from racebench.utils.lazy import lazy_exports

#: Submodule -> the names this package re-exports from it, imported on first use (PEP 562) so that importing one
#: submodule does not load its siblings.
_EXPORTS: dict[str, tuple[str, ...]] = {
    "base": (
        "BUILTIN_AGENTS",
        "BUILTIN_PRIVILEGED",
        "BUILTIN_VERSIONS",
        "AgentLoadError",
        "UntrustedCodeError",
        "Agent",
    ),
    "builtin": ("RandomAgent", "HoverAgent", "FollowAgent"),
    "trust": (
        "TRUSTED_CHECKPOINTS",
        "PolicyIdentity",
        "builtin_identity",
        "python_agent_modules",
        "python_policy_sha256",
        "VecNormalizeChoice",
        "NO_VECNORMALIZE",
        "VecNormalizeChoiceError",
        "vecnormalize_candidates",
        "nearby_vecnormalize",
        "resolve_vecnormalize",
        "vecnormalize_path",
        "sb3_stats_sha256",
        "sb3_policy_sha256",
        "onnx_external_data",
        "onnx_policy_sha256",
        "parse_agent_kwargs",
        "policy_identity",
        "WRITTEN_FILE",
        "record_written",
        "written_sha256",
        "trust_folder",
        "trust_store",
        "state_dir",
        "require_trusted",
    ),
    "loading": (
        "SB3Agent",
        "load_vecnormalize_statistics",
        "OnnxAgent",
        "load_agent",
    ),
    "export": (
        "TRAINING_ONLY_ATTRIBUTES",
        "export_policy",
        "export_onnx",
    ),
}
__all__, __getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
