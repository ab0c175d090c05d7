"""Policy identity and trust: what a policy hash covers, the trusted checkpoints, files a run wrote itself.

See :mod:`racebench.agents.loading` for what each hash covers and why untrusted code is refused.
"""

from __future__ import annotations

import ast
import functools
import hashlib
import json
import os
import re
import site
import sys
import sysconfig
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from racebench.agents.base import (
    BUILTIN_AGENTS,
    BUILTIN_PRIVILEGED,
    BUILTIN_VERSIONS,
    AgentLoadError,
    UntrustedCodeError,
)
from racebench.utils.files import atomic_write, sha256_file

#: sha256 of the first-party checkpoints shipped in ``baselines/checkpoints`` -> their path under it. They load
#: without ``trust_code`` (``tests/test_checkpoints.py`` keeps this list and the committed files in step).
TRUSTED_CHECKPOINTS: dict[str, str] = {
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
    "1c297ec8d07ba5cdb8b77aacd8be89bd68cc4b43ecd869a1f6a7f4e800aebb12": "state-ppo-S/state-ppo-S.zip",
    "de4138705b1c38955662cd98a4230f8fe281e61abc8834d1dff72dbca0b59b6a": "state-ppo-J/state-ppo-J.zip",
    "5a0cb6a1746be02d978186082627f4a558f5463faed3cf3f9e869bf3b2366df3": "state-ppo-Circle/state-ppo-Circle.zip",
    "fee881723ef52c1a8439d4a27296da5d8e542b256ee43117300cc9e08ee159de": "vision-com-S/vision-com-S.zip",
    "c54280abc7c1fd055f210dd02464f251a548df6a5cbd116cf6fc427829ef45a9": "vision-com-J/vision-com-J.zip",
    "470ae7e6f38c92a4aeebd6a404683b05408fab7602bbfa0d93ffe88cd9907ad2": "vision-com-Circle/vision-com-Circle.zip",
    "478807598a0e4c5de5434c5da7306b5f64f0373fe0a58b87ee345c5f828347f0": "vision-no-avoid-S/vision-no-avoid-S.zip",
    "b1b4e4fcba3f5ab2f857cb5a0f5f3feb67d6fda1617ff4f4c40cf4d670ec200b": "vision-no-avoid-J/vision-no-avoid-J.zip",
    "5c7f53e8a6dffaecff3085990b2738eea6e4b1d17580fee4ade20330e4ce3762": (
        "vision-no-avoid-Circle/vision-no-avoid-Circle.zip"
    ),
    "ccde553d979ab7ec43ad24c0c7b0b3ce7193ad77621ee1281586e33b85e6a7f0": "vision-one-step-S/vision-one-step-S.zip",
    "513a50984e83eb1b99c257772c8711fc83744f76a50821e060158833e5b04e98": "vision-one-step-J/vision-one-step-J.zip",
    "36bc87ea2f75377a5cd52da6d9c6f782ecfdb8eacd26ccafb4d17b5ad71a3ae6": (
        "vision-one-step-Circle/vision-one-step-Circle.zip"
    ),
    "a71b6c79a3e9a7bde889288aeaa59ed3406502995d5d7327462ece55a8ed4fd3": "vision-no-gru-S/vision-no-gru-S.zip",
    "4731e4e37ff4e05629bdfcc1e076bf2a46a452a504067dd3e0342f3e3bef74e6": "vision-no-gru-J/vision-no-gru-J.zip",
    "6770750ec6407172f0795e4d66e7f5372017332d13d69adfff60a5aa65d210e4": "vision-no-gru-Circle/vision-no-gru-Circle.zip",
    "4c187ca78a7743a3740196b49d42cf0a99c7f435b3b0cd707e09ddf2bc85cdeb": "vision-ppo-S/vision-ppo-S.zip",
    "bfbdac773bf7c7d9d1d113703f155332b3471c933962c1fdf4d3d8ab10cc65f3": "vision-ppo-J/vision-ppo-J.zip",
    "8b1a926ac5c716cf179ef9f642d1f514e4a655d5c59249cfc89f7ee1a852e771": "vision-ppo-Circle/vision-ppo-Circle.zip",
}


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
        # Found as import would find it, but without importing anything: importlib.util.find_spec imports a dotted
        # name's parent packages (running their __init__.py) before the trust check could refuse them.
        if not re.fullmatch(r"[A-Za-z_]\w*(\.[A-Za-z_]\w*)*", target):
            raise AgentLoadError(f"agent spec {spec!r}: {target!r} is not a module name")
        found = _find_module(target, {})
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
    roots |= {*site.getsitepackages(), site.getusersitepackages(), str(Path(__file__).parents[1])}
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
#: The folder's list alone vouches for nothing (whoever can write the folder can write the list): a file is trusted
#: through it only if this machine's own store (:func:`trust_store`, outside any repository) also records its sha256.
WRITTEN_FILE = "written.json"

#: Environment variable naming the machine-local state folder (default ``$XDG_STATE_HOME/racebench`` or
#: ``~/.local/state/racebench``).
STATE_DIR_ENV = "RACEBENCH_STATE_DIR"


def state_dir() -> Path:
    """racebench's machine-local state folder, outside any repository: ``$RACEBENCH_STATE_DIR``, else
    ``$XDG_STATE_HOME/racebench``, else ``~/.local/state/racebench``."""
    if os.environ.get(STATE_DIR_ENV):
        return Path(os.environ[STATE_DIR_ENV]).expanduser()
    base = os.environ.get("XDG_STATE_HOME") or str(Path.home() / ".local" / "state")
    return Path(base).expanduser() / "racebench"


def trust_store() -> Path:
    """The folder in which this machine records the sha256 of every pickle racebench wrote itself (one empty file
    per sha256, created with the folder on first use, private to the user): what a pull request cannot change."""
    return state_dir() / "written"


def _store(*digests: str) -> None:
    """Record ``digests`` (sha256 hex, as :func:`_read_written` keeps them) in :func:`trust_store` (idempotent)."""
    trust_store().mkdir(parents=True, exist_ok=True, mode=0o700)
    for digest in digests:
        (trust_store() / digest).touch()


def record_written(folder: str | Path, *paths: str | Path) -> None:
    """Add the sha256 of each file in ``paths`` (written by this process) to ``folder``'s :data:`WRITTEN_FILE` and to
    this machine's :func:`trust_store`.

    The manifest vouches for what the run wrote, not for the folder: a pickle copied in afterwards is not listed,
    and a listed one that this machine did not write is not recorded in its store.
    """
    folder = Path(folder)
    written = _read_written(folder)
    added = []
    for path in map(Path, paths):
        key = str(path.relative_to(folder)) if path.is_relative_to(folder) else str(path.resolve())
        written[key] = _sha256_bytes(path.read_bytes())
        added.append(written[key])
    _store(*added)
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
    """The sha256 of the files the run in ``folder`` wrote itself: listed in its :data:`WRITTEN_FILE` and recorded
    in this machine's :func:`trust_store` (:func:`record_written`, :func:`trust_folder`); none for ``None``."""
    listed = set(_read_written(Path(folder)).values()) if folder is not None else set()
    return frozenset(d for d in listed if (trust_store() / d).is_file())


def trust_folder(folder: str | Path) -> list[str]:
    """Vouch, on this machine, for the files a run folder's :data:`WRITTEN_FILE` lists (``racebench trust``): the
    maintainer's explicit step to resume a run that another machine wrote (a campaign's committed state).

    Only listed files that exist in the folder with the listed bytes are recorded; returns their paths (relative to
    the folder). A folder without a readable manifest raises :class:`ValueError`.
    """
    folder = Path(folder)
    listed = _read_written(folder)
    if not listed:
        raise ValueError(f"{folder}: no {WRITTEN_FILE} listing files to trust")
    trusted = [key for key, digest in sorted(listed.items()) if (folder / key).is_file()
               and not (folder / key).is_symlink() and sha256_file(folder / key) == digest]  # fmt: skip
    _store(*(listed[key] for key in trusted))
    return trusted


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
        error = _refuse_untrusted(str(path), why, what, onnx_hint=what == "agent")
        if what != "agent":  # a run folder's file: its written.json vouches only for what this machine wrote
            error = UntrustedCodeError(f"{error} (or, for a reviewed run folder from another machine, "
                                       "racebench trust FOLDER)")  # fmt: skip
        raise error


def own_policy_trust(out: str | Path, checkpoint: str | Path, trust_code: bool = False) -> bool:
    """The ``trust_code`` of the evaluation of a run's own final ``checkpoint``: whether the run folder ``out`` wrote
    it (its :data:`~racebench.agents.trust.WRITTEN_FILE` lists its sha256), or ``trust_code`` itself.

    The ``VecNormalize`` statistics the evaluator would read beside it must be the run's too: statistics copied
    into the folder are refused (:class:`~racebench.agents.base.UntrustedCodeError`) rather than unpickled.
    """
    if trust_code:
        return True
    written, checkpoint = written_sha256(out), Path(checkpoint)
    stats = vecnormalize_path(checkpoint)
    if stats is not None:
        require_trusted(stats, stats.read_bytes(), "VecNormalize statistics beside the checkpoint are unpickled",
                        written=written, what="statistics")  # fmt: skip
    return checkpoint.is_file() and sha256_file(checkpoint) in written
