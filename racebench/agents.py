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

import ast
import functools
import hashlib
import importlib
import importlib.util
import io
import json
import os
import pickle
import re
import site
import sys
import sysconfig
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import numpy as np

if TYPE_CHECKING:
    from racebench.quadrotor import QuadrotorParams
from racebench.records import atomic_write

#: The built-in agents, by spec name: the one registry the loader, the policy identities and the command line's
#: help read. (This module imports nothing heavy at import time, so the command line can read it for its help.)
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
    "ab21b31bfddbbf6add303d7a694b271802ec9b0174ca333f24a6a5938f298373": "vision-distill-S/vision-distill-S.zip",
    "2db06548dde9f2989e1d25394faac2d02a37deaff6e2893bbf4b4eb7da64650a": "vision-distill-ppo-S/vision-distill-ppo-S.zip",
    "5639e53c43a9f9f45ea1dac34c8058f3c8250b76e7d922016a243e329a07a4ed": (
        "vision-distill-Circle/vision-distill-Circle.zip"
    ),
    "b22cd966241f91efae27854bd6313f2ff57b17b89aa7ce9f6b49d6ac4a70b411": "vision-distill-J/vision-distill-J.zip",
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
    ``module:Class``) and of the files that go with it (see the module docstring: :func:`sb3_policy_sha256`,
    :func:`onnx_policy_sha256`, :func:`python_policy_sha256`), or of ``"racebench-builtin:<name>:v<version>"``
    for a built-in agent.
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


@functools.cache
def _installed_roots() -> tuple[Path, ...]:
    """Folders of installed code, which a Python agent's hash does not cover: the standard library,
    site-packages (the user's too) and racebench's own package."""
    paths = sysconfig.get_paths()
    roots = {paths[key] for key in ("stdlib", "platstdlib", "purelib", "platlib")}
    roots |= {*site.getsitepackages(), site.getusersitepackages(), str(Path(__file__).parent)}
    return tuple(Path(root).resolve() for root in roots)


def _is_agent_code(file: str | None) -> bool:
    """Whether a module's file is the user's code (hashed with a Python agent), not installed code."""
    if not file or not Path(file).is_file():
        return False
    path = Path(file).resolve()
    return not any(path.is_relative_to(root) for root in _installed_roots())


def _imported_names(file: Path, package: str | None) -> set[str]:
    """The absolute names of the modules a source file imports by name (anywhere in it), with their parents."""
    try:
        tree = ast.parse(file.read_bytes(), str(file))
    except (SyntaxError, ValueError) as exc:
        raise AgentLoadError(f"agent module {str(file)!r} cannot be parsed: {exc}") from exc
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # relative: resolved against the module's package (none: it would fail when run)
                parts = (package or "").split(".") if package else []
                if node.level > len(parts):
                    continue
                anchor = ".".join(parts[: len(parts) - node.level + 1])
                base = f"{anchor}.{base}" if base else anchor
            names.add(base)
            names.update(f"{base}.{alias.name}" for alias in node.names if alias.name != "*")  # maybe submodules
    parts = [name.split(".") for name in names if name]
    return {".".join(p[:i]) for p in parts for i in range(1, len(p) + 1)}


def _find_module(name: str, found: dict[str, Any]) -> Any:
    """The import system's spec for ``name``, found as ``import`` would find it but without importing anything
    (importlib.util.find_spec imports a dotted name's parents); ``None`` if there is none."""
    if name not in found:
        parent = name.rpartition(".")[0]
        path = None
        if parent:
            parent_spec = _find_module(parent, found)
            path = list(parent_spec.submodule_search_locations or []) if parent_spec is not None else []
        spec = None
        if path is None or path:
            for finder in sys.meta_path:
                try:
                    spec = finder.find_spec(name, path)
                except Exception:  # noqa: BLE001 - a finder that cannot answer: as import, try the next
                    spec = None
                if spec is not None:
                    break
        found[name] = spec
    return found[name]


def python_agent_modules(source: str | Path, package: str | None = None) -> dict[str, Path]:
    """The modules a Python agent's source loads from outside the installed code, by name -> file.

    Every module that ``source`` imports by name (``import x``, ``from x import y``, anywhere in the file,
    functions included), resolved on the current ``sys.path`` as ``import`` would, without running any of it;
    then, recursively, the same for those modules. Modules of the standard library, of site-packages and of
    racebench itself are not included (:func:`_is_agent_code`). ``package`` is the agent module's package (for its
    relative imports and the parents a ``package.module`` spec imports first).
    """
    source = Path(source).resolve()
    specs: dict[str, Any] = {}
    modules: dict[str, Path] = {}
    todo = [(source, package, _imported_names(source, package) | _parents(package))]
    while todo:
        file, package, names = todo.pop()
        for name in sorted(names - modules.keys()):
            spec = _find_module(name, specs)
            if spec is None or not spec.has_location or not _is_agent_code(spec.origin):
                continue
            path = Path(spec.origin).resolve()
            if path == source:
                continue
            modules[name] = path
            if path.suffix == ".py":
                own = name if spec.submodule_search_locations is not None else name.rpartition(".")[0] or None
                todo.append((path, own, _imported_names(path, own)))
    return modules


def _parents(package: str | None) -> set[str]:
    """``a``, ``a.b`` for package ``a.b``: the packages imported before a module in it."""
    parts = package.split(".") if package else []
    return {".".join(parts[:i]) for i in range(1, len(parts) + 1)}


def _python_package(spec: str) -> str | None:
    """The package of a ``module:Class`` spec's module (``None`` for a ``file.py:Class``, loaded as a top-level)."""
    target = spec.rpartition(":")[0]
    if target.endswith(".py"):
        return None
    return target if _python_source(spec).name == "__init__.py" else target.rpartition(".")[0] or None


def python_policy_sha256(spec: str) -> str:
    """The policy hash of a ``module:Class`` or ``file.py:Class`` agent (before constructor arguments): its file's
    sha256, or with modules from outside the installed code (:func:`python_agent_modules`), the sha256 of
    ``"<file sha256>+modules:<name>=<sha256>;..."`` over them in sorted order of name."""
    source = _python_source(spec)
    digest = _sha256_bytes(source.read_bytes())
    modules = python_agent_modules(source, _python_package(spec))
    if not modules:
        return digest
    parts = ";".join(f"{name}={_sha256_bytes(modules[name].read_bytes())}" for name in sorted(modules))
    return hashlib.sha256(f"{digest}+modules:{parts}".encode()).hexdigest()


#: ``vecnormalize=`` of :func:`load_agent`, :func:`policy_identity` and :class:`SB3Agent`: ``None`` finds the
#: statistics matched to the checkpoint (:func:`resolve_vecnormalize`), ``False`` confirms there are none to use
#: (``--no-vecnormalize``), a path names the file (``--vecnormalize PATH``).
VecNormalizeChoice = str | Path | bool | None
#: What an explicit ``vecnormalize=False`` hashes as, in place of a statistics file's sha256, when statistics lie
#: near the checkpoint (:func:`sb3_policy_sha256`): such an evaluation is never taken for the run's own policy.
NO_VECNORMALIZE = "none"


class VecNormalizeChoiceError(AgentLoadError):
    """``VecNormalize`` statistics lie near an SB3 checkpoint but none, or more than one, is matched to it."""


def _zoo_params_folders(folder: Path, stem: str) -> list[Path]:
    """rl-baselines3-zoo's statistics folders for a checkpoint in run folder ``folder``: ``<run>/<env_id>/``.

    The zoo saves the final model as ``<run>/<env_id>.zip`` (so ``<run>/<stem>/``) and, in every run folder named
    ``<env_id>_<n>`` (``_<uuid>`` after it with ``--uuid``), ``best_model.zip`` beside it: ``<run>/<env_id>/``.
    """
    folders = [folder / stem]
    run = re.fullmatch(r"(.+)_\d+(_[0-9a-f]{8}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{12})?", folder.name)
    if run and stem == "best_model":
        folders.append(folder / run[1])
    return folders


def vecnormalize_candidates(checkpoint: str | Path) -> list[Path]:
    """The ``VecNormalize`` statistics files matched to an SB3 checkpoint by the names their savers give them.

    * ``<prefix>_<n>_steps.zip`` (SB3's ``CheckpointCallback``, rl-baselines3-zoo's ``rl_model_<n>_steps.zip``):
      ``<prefix>_vecnormalize_<n>_steps.pkl`` beside it, and nothing else (later statistics are not its own);
    * any other name: ``vecnormalize.pkl`` beside it (``racebench train``'s), ``<stem>/vecnormalize.pkl`` (the
      zoo's final model ``<run>/<env_id>.zip``) and, for the zoo's ``best_model.zip`` in ``<run>`` =
      ``<env_id>_<n>``, ``<run>/<env_id>/vecnormalize.pkl`` (the file the zoo's own ``enjoy`` pairs it with).

    Only existing files, sorted, each once; more than one is ambiguous (:func:`resolve_vecnormalize`).
    """
    path = Path(checkpoint)
    periodic = re.fullmatch(r"(.*)_(\d+)_steps\.zip", path.name)
    if periodic:
        names = [path.with_name(f"{periodic[1]}_vecnormalize_{periodic[2]}_steps.pkl")]
    else:
        names = [path.parent / "vecnormalize.pkl"]
        names += [folder / "vecnormalize.pkl" for folder in _zoo_params_folders(path.parent, path.stem)]
    found = {name.resolve(): name for name in names if name.is_file()}
    return sorted(found.values())


def nearby_vecnormalize(checkpoint: str | Path) -> list[Path]:
    """Every ``*vecnormalize*.pkl`` in an SB3 checkpoint's folder or one folder below it, sorted."""
    folder = Path(checkpoint).parent
    return sorted(p for pattern in ("*vecnormalize*.pkl", "*/*vecnormalize*.pkl") for p in folder.glob(pattern)
                  if p.is_file())  # fmt: skip


def resolve_vecnormalize(checkpoint: str | Path, vecnormalize: VecNormalizeChoice = None) -> Path | None:
    """The ``VecNormalize`` statistics an SB3 checkpoint is flown with, or ``None`` for none.

    ``vecnormalize``: a path (that file, which must exist), ``False`` (none, confirmed), or ``None``: the one file
    :func:`vecnormalize_candidates` matches. Statistics are never left out silently: with ``None``, several matched
    files, or none matched while :func:`nearby_vecnormalize` finds some, raise :class:`VecNormalizeChoiceError`
    naming them and the choice to make.
    """
    if vecnormalize is False:
        return None
    if vecnormalize is True:
        raise AgentLoadError("vecnormalize=True is no choice: pass the statistics' path, False for none, or None")
    if vecnormalize is not None:
        stats = Path(vecnormalize)
        if not stats.is_file():
            raise AgentLoadError(f"VecNormalize statistics {str(stats)!r} do not exist")
        return stats
    matched = vecnormalize_candidates(checkpoint)
    if len(matched) == 1:
        return matched[0]
    choose = "choose one with --vecnormalize PATH, or confirm none with --no-vecnormalize (vecnormalize= in Python)"
    if matched:
        names = ", ".join(map(str, matched))
        raise VecNormalizeChoiceError(f"SB3 checkpoint {str(checkpoint)!r}: several VecNormalize statistics match it "
                                      f"({names}); {choose}")  # fmt: skip
    nearby = nearby_vecnormalize(checkpoint)
    if nearby:
        names = ", ".join(map(str, nearby))
        raise VecNormalizeChoiceError(f"SB3 checkpoint {str(checkpoint)!r}: VecNormalize statistics lie near it "
                                      f"({names}) but none is named as its own; {choose}")  # fmt: skip
    return None


def vecnormalize_path(checkpoint: str | Path) -> Path | None:
    """The ``VecNormalize`` statistics matched to an SB3 checkpoint, or ``None``: :func:`resolve_vecnormalize`
    with no explicit choice (so it raises :class:`VecNormalizeChoiceError` when that is ambiguous)."""
    return resolve_vecnormalize(checkpoint)


def sb3_stats_sha256(checkpoint: str | Path, stats: Path | None, vecnormalize: VecNormalizeChoice = None) -> str | None:
    """What :func:`sb3_policy_sha256` hashes for the statistics: the chosen file's sha256; for an explicit
    ``vecnormalize=False`` while statistics lie near the checkpoint, :data:`NO_VECNORMALIZE`; else ``None``."""
    if stats is not None:
        return _sha256_bytes(stats.read_bytes())
    if vecnormalize is False and nearby_vecnormalize(checkpoint) + vecnormalize_candidates(checkpoint):
        return NO_VECNORMALIZE
    return None


def sb3_policy_sha256(checkpoint_sha256: str, stats_sha256: str | None) -> str:
    """The policy hash of an SB3 checkpoint: its bytes' sha256, or with ``VecNormalize`` statistics
    (they change the actions), the sha256 of ``"<checkpoint sha256>+vecnormalize:<statistics sha256>"``
    (``...+vecnormalize:none`` for statistics refused with ``--no-vecnormalize``, :func:`sb3_stats_sha256`)."""
    if stats_sha256 is None:
        return checkpoint_sha256
    return hashlib.sha256(f"{checkpoint_sha256}+vecnormalize:{stats_sha256}".encode()).hexdigest()


def _onnx_tensors(initializers: Any, sparse: Any, nodes: Any) -> Any:
    """Every tensor that may hold weights: initializers and node attributes, subgraphs included."""
    yield from initializers
    for tensor in sparse:
        yield from (tensor.values, tensor.indices)
    for node in nodes:
        for attribute in node.attribute:
            yield from (attribute.t, *attribute.tensors)
            for tensor in (attribute.sparse_tensor, *attribute.sparse_tensors):
                yield from (tensor.values, tensor.indices)
            for graph in (attribute.g, *attribute.graphs):
                yield from _onnx_tensors(graph.initializer, graph.sparse_initializer, graph.node)


def onnx_external_data(path: str | Path) -> list[Path]:
    """The external-data files an ONNX model references (weights saved beside it), sorted, without loading them.

    A location must be a file in the model's folder or below it (as onnxruntime requires); one that is not,
    or that does not exist, raises :class:`AgentLoadError`.
    """
    import onnx
    from onnx.external_data_helper import uses_external_data

    path = Path(path)
    try:
        model = onnx.load(str(path), load_external_data=False)
    except Exception as exc:  # noqa: BLE001 - protobuf raises its own exception types on a damaged file
        raise AgentLoadError(f"ONNX file {str(path)!r} could not be read: {exc}") from exc
    graph = model.graph
    tensors = [_onnx_tensors(graph.initializer, graph.sparse_initializer, graph.node)]
    tensors += [_onnx_tensors([], [], function.node) for function in model.functions]
    locations = set()
    for tensor in (t for group in tensors for t in group):
        if uses_external_data(tensor):
            locations.add(next((e.value for e in tensor.external_data if e.key == "location"), ""))
    folder = path.resolve().parent
    files = []
    for location in sorted(locations):
        file = (folder / location).resolve()
        if not location or Path(location).is_absolute() or not file.is_relative_to(folder):
            raise AgentLoadError(f"ONNX file {str(path)!r}: external data {location!r} is not a file beside it")
        if not file.is_file():
            raise AgentLoadError(f"ONNX file {str(path)!r}: its external data {location!r} does not exist")
        files.append(file)
    return files


def onnx_policy_sha256(path: str | Path, graph_sha256: str) -> str:
    """The policy hash of an ONNX model: its bytes' sha256 (``graph_sha256``), or with weights saved as external
    data, the sha256 of ``"<graph sha256>+external:<location>=<sha256>;..."`` over its files in sorted order."""
    files = onnx_external_data(path)
    if not files:
        return graph_sha256
    folder = Path(path).resolve().parent
    parts = ";".join(f"{file.relative_to(folder).as_posix()}={_sha256_bytes(file.read_bytes())}" for file in files)
    return hashlib.sha256(f"{graph_sha256}+external:{parts}".encode()).hexdigest()


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


def _check_vecnormalize_spec(spec: str, vecnormalize: VecNormalizeChoice) -> None:
    """A ``vecnormalize`` choice belongs to an SB3 ``.zip`` agent: refused for any other spec."""
    if vecnormalize is not None and not spec.endswith(".zip"):
        raise AgentLoadError(f"--vecnormalize / --no-vecnormalize apply to SB3 .zip agents only, not {spec!r}")


def policy_identity(
    spec: str, agent_kwargs: dict[str, Any] | None = None, vecnormalize: VecNormalizeChoice = None
) -> PolicyIdentity:
    """The :class:`PolicyIdentity` of an agent spec, computed from the files' bytes without running any of them.

    A ``module:Class`` built with ``agent_kwargs`` is another policy than the same class without them: its hash
    is the sha256 of ``"<file sha256>+kwargs:<canonical JSON>"``. ``vecnormalize``: an SB3 checkpoint's statistics
    (:func:`resolve_vecnormalize`), hashed with it (:func:`sb3_stats_sha256`).
    """
    if agent_kwargs and ":" not in spec:
        raise AgentLoadError(f"agent kwargs apply to module:Class and file.py:Class agents only, not {spec!r}")
    _check_vecnormalize_spec(spec, vecnormalize)
    if spec in BUILTIN_AGENTS:
        return builtin_identity(spec)
    if spec.endswith(".zip") or spec.endswith(".onnx"):
        path = Path(spec)
        if not path.is_file():
            raise AgentLoadError(f"policy file {spec!r} does not exist")
        digest = _sha256_bytes(path.read_bytes())
        if spec.endswith(".onnx"):
            return PolicyIdentity("onnx", onnx_policy_sha256(path, digest), spec, False)
        stats = resolve_vecnormalize(path, vecnormalize)
        return PolicyIdentity(
            "sb3", sb3_policy_sha256(digest, sb3_stats_sha256(path, stats, vecnormalize)), spec, False
        )
    if ":" in spec:
        digest = python_policy_sha256(spec)
        if agent_kwargs:
            digest = hashlib.sha256(f"{digest}+kwargs:{_kwargs_json(agent_kwargs)}".encode()).hexdigest()
        return PolicyIdentity("python", digest, spec, False)
    raise AgentLoadError(
        f"unknown agent spec {spec!r}: expected one of {BUILTIN_AGENTS}, a .zip (SB3) or .onnx file, or module:Class"
    )


def _refuse_untrusted(spec: str, why: str, what: str = "agent", onnx_hint: bool = True) -> UntrustedCodeError:
    hint = " (an ONNX export runs no code and needs no flag)" if onnx_hint else ""
    return UntrustedCodeError(
        f"{what} {spec!r}: {why}, which can run arbitrary code; pass --trust-code (trust_code=True) only if you "
        f"trust where it came from{hint}"
    )


#: In a run folder: ``{path: sha256}`` of every checkpoint and statistics file the run wrote itself (paths relative
#: to the folder), so that resuming the run trusts its own pickles without ``--trust-code`` (:func:`record_written`).
WRITTEN_FILE = "written.json"


def record_written(folder: str | Path, *paths: str | Path) -> None:
    """Add the sha256 of each file in ``paths`` (written by this process) to ``folder``'s :data:`WRITTEN_FILE`.

    The manifest vouches for what the run wrote, not for the folder: a pickle copied in afterwards is not listed.
    """
    folder = Path(folder)
    written = _read_written(folder)
    for path in map(Path, paths):
        key = str(path.relative_to(folder)) if path.is_relative_to(folder) else str(path.resolve())
        written[key] = _sha256_bytes(path.read_bytes())
    atomic_write(folder / WRITTEN_FILE, json.dumps(written, indent=1, sort_keys=True))


def _read_written(folder: Path) -> dict[str, str]:
    """The manifest of ``folder`` (empty if absent or unreadable: nothing is then trusted through it)."""
    try:
        written = json.loads((folder / WRITTEN_FILE).read_text())
    except (OSError, ValueError):
        return {}
    if not isinstance(written, dict):
        return {}
    return {str(k): v for k, v in written.items() if isinstance(v, str) and re.fullmatch(r"[0-9a-f]{64}", v)}


def written_sha256(folder: str | Path | None) -> frozenset[str]:
    """The sha256 of the files the run in ``folder`` wrote itself (:func:`record_written`); none for ``None``."""
    return frozenset() if folder is None else frozenset(_read_written(Path(folder)).values())


def require_trusted(
    path: str | Path, data: bytes, why: str, trust_code: bool = False, written: frozenset[str] = frozenset(),
    what: str = "checkpoint",
) -> None:  # fmt: skip
    """The evaluator's rule for a file that is unpickled when loaded: allowed with ``trust_code``, for the shipped
    checkpoints (:data:`TRUSTED_CHECKPOINTS`) and for files a run wrote itself (their sha256 in ``written``, see
    :func:`written_sha256`); otherwise :class:`UntrustedCodeError`, before any of it is unpickled.

    ``data`` are the file's bytes, which the caller then loads: hashed and loaded from the same bytes.
    """
    digest = _sha256_bytes(data)
    if not (trust_code or digest in TRUSTED_CHECKPOINTS or digest in written):
        raise _refuse_untrusted(str(path), why, what, onnx_hint=what == "agent")


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
        from racebench.quadrotor import QuadrotorParams  # numba-compiled module: loaded when an agent is built

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
        from racebench.control import GateFollower

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


def _export_refusal(policy: Any) -> str | None:
    """Why :func:`export_onnx` cannot reproduce ``policy``'s deterministic action, or ``None`` if it can."""
    from racebench.training.policies import LSTMShapedGRU

    rnn = getattr(policy, "lstm_actor", None)
    if rnn is not None and not isinstance(rnn, LSTMShapedGRU):
        return "recurrent policies must use racebench's GRU (an LSTM's cell state is not exported)"
    if rnn is not None and rnn.num_layers != 1:
        return f"a GRU of {rnn.num_layers} layers is not supported (1 layer)"
    if getattr(policy, "action_output", "ctbr") != "ctbr":
        return (
            f"the policy outputs {policy.action_output} commands, not the env's CTBR action (its controller, "
            "racebench.control.command_to_ctbr, is not part of the network)"
        )
    # The graph is the actor's mean action: exact only for the forward passes that _gaussian_mean reproduces.
    if not _is_gaussian_actor_critic(policy):
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
    trained on ``depth_format="uint8"`` gets the depth through :func:`racebench.env.depth_to_uint8`'s rounding
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
    vision = _obs_mode_of(space) == "vision"
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
        dynamo=False,
    )
    return path


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
        from racebench.planner import PlannerAgent

        return PlannerAgent()
    if spec == "planner-fast":
        from racebench.planner import FastPlannerAgent

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
