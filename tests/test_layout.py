"""The package's layout (docs/layout.md): no import cycle, no import from a higher layer, the page matches the tree."""

from __future__ import annotations

import ast
import base64
import importlib
import json
import re
import zipfile
from pathlib import Path
from types import ModuleType

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "racebench"

#: The layers, lowest first: a module may import its own layer's modules and lower layers' only. Top-level modules
#: (the command line, the benchmark) are the top layer; ``racebench.compat`` imports nothing of racebench; the package
#: itself (``racebench/__init__.py``: the version, registering the envs) counts as the envs' layer.
LAYERS: tuple[str, ...] = ("utils", "sim", "envs", "agents", "evaluation", "reporting", "training", "leaderboard")


def module_files(package_dir: Path) -> dict[str, Path]:
    """``{dotted module name: file}`` of every module of the package in ``package_dir``."""
    found = {}
    for path in sorted(package_dir.rglob("*.py")):
        parts = path.relative_to(package_dir.parent).with_suffix("").parts
        if parts[-1] == "__init__":
            parts = parts[:-1]
        found[".".join(parts)] = path
    return found


def import_graph(package_dir: Path) -> dict[str, set[str]]:
    """``{module: the package's modules it imports}``, from every import statement (in functions too), by AST.

    ``from a import b`` counts as importing ``a.b`` where that is a module, else ``a``; a relative import is resolved
    against the importing module's package. Importing ``a.b`` runs package ``a`` first, which is not counted: a
    package's ``__init__`` is an edge only where it is named.
    """
    modules = module_files(package_dir)
    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        edges: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                edges.update(alias.name for alias in node.names)
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = package.split(".")[: len(package.split(".")) - node.level + 1]
                    source = ".".join([*base, *([node.module] if node.module else [])])
                else:
                    source = node.module or ""
                for alias in node.names:
                    edges.add(f"{source}.{alias.name}" if f"{source}.{alias.name}" in modules else source)
        graph[name] = {edge for edge in edges if edge in modules and edge != name}
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import cycle (``[a, b, ..., a]``), or ``None`` when the graph has none."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        path.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                return [*path[path.index(nxt) :], nxt]
            if nxt not in state and (cycle := visit(nxt)):
                return cycle
        path.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state and (cycle := visit(node)):
            return cycle
    return None


def layer_of(module: str) -> int:
    parts = module.split(".")
    if len(parts) > 1 and parts[1] in LAYERS:
        return LAYERS.index(parts[1])
    if module == "racebench.compat":
        return -1
    if module == "racebench":  # the package registers the envs and holds the version: the envs' layer
        return LAYERS.index("envs")
    return len(LAYERS)  # the command line, the benchmark


def test_the_package_has_no_import_cycle() -> None:
    assert find_cycle(import_graph(PACKAGE)) is None


def test_the_cycle_check_finds_a_planted_cycle(tmp_path: Path) -> None:
    package = tmp_path / "planted"
    (package / "sub").mkdir(parents=True)
    (package / "__init__.py").write_text("")
    (package / "sub" / "__init__.py").write_text("")
    (package / "a.py").write_text("import os\n\nfrom planted.sub import b\n")
    (package / "sub" / "b.py").write_text("def f():\n    from . import c  # hidden in a function: still an import\n")
    (package / "sub" / "c.py").write_text("from planted.a import x\n")
    assert find_cycle(import_graph(package)) == ["planted.a", "planted.sub.b", "planted.sub.c", "planted.a"]
    (package / "sub" / "c.py").write_text("x = 1\n")  # the cycle broken: none left
    assert find_cycle(import_graph(package)) is None


def test_no_module_imports_from_a_higher_layer() -> None:
    upward = sorted(
        f"{module} -> {target}"
        for module, targets in import_graph(PACKAGE).items()
        for target in targets
        if layer_of(target) > layer_of(module)
    )
    assert upward == []


def test_the_layout_page_lists_every_module() -> None:
    text = (ROOT / "docs" / "layout.md").read_text()
    block = re.search(r"```text\n(.*?)```", text, re.S)
    assert block, "docs/layout.md has no ```text tree"
    listed = set()
    stack: list[str] = []
    for line in block.group(1).splitlines():
        match = re.match(r"^(?P<indent>[\s│├└─]*)(?P<name>[\w.]+/?)", line)
        if not match:
            continue
        depth = len(match.group("indent")) // 4
        name = match.group("name")
        stack[depth:] = [name.rstrip("/")]
        if name.endswith(".py"):
            listed.add("/".join(stack))
    actual = {str(path.relative_to(ROOT)) for path in PACKAGE.rglob("*.py")}
    assert listed == actual, (sorted(actual - listed), sorted(listed - actual))


#: Most lines of a module.
MAX_LINES = 600
#: The modules allowed over :data:`MAX_LINES`, each with its one job (and at most this many lines).
LONG_MODULES: dict[str, tuple[int, str]] = {
    "racebench/envs/env.py": (660, "RaceEnv, one class; its docstring is the env's reference (spaces, parameters)"),
    "racebench/benchmark.py": (640, "racebench bench: one throughput table, a section per measured stage"),
    "racebench/leaderboard/entries.py": (640, "an entry: its metadata, records and tier"),
}


def test_no_module_is_over_the_size_limit() -> None:
    sizes = {str(p.relative_to(ROOT)): len(p.read_text().splitlines()) for p in PACKAGE.rglob("*.py")}
    over = {p: n for p, n in sizes.items() if n > LONG_MODULES.get(p, (MAX_LINES,))[0]}
    assert over == {}


def test_setup_cfg_installs_every_subpackage() -> None:
    from setuptools.config.setupcfg import read_configuration

    listed = set(read_configuration(ROOT / "setup.cfg")["options"]["packages"])
    packages = {".".join(p.parent.relative_to(ROOT).parts) for p in PACKAGE.rglob("__init__.py")}
    assert packages <= listed


#: Names the docs, the README and users' code import from racebench's former module paths.
FORMER_NAMES: tuple[tuple[str, str], ...] = (
    ("racebench", "ENV_IDS"),
    ("racebench.env", "RaceEnv"),
    ("racebench.env", "depth_to_uint8"),
    ("racebench.agents", "export_onnx"),
    ("racebench.agents", "export_policy"),
    ("racebench.agents", "load_agent"),
    ("racebench.agents", "resolve_vecnormalize"),
    ("racebench.agents", "SB3Agent"),
    ("racebench.evaluation", "Evaluator"),
    ("racebench.evaluation", "EVAL_SEED_BASE"),
    ("racebench.evaluation", "read_summaries"),
    ("racebench.evaluation", "RecordWriter"),
    ("racebench.records", "read_folder"),
    ("racebench.statistics", "counts_consistent"),
    ("racebench.obstacles", "find_corridor"),
    ("racebench.planner", "FastPlannerAgent"),
    ("racebench.control", "command_to_ctbr"),
    ("racebench.track", "load_track"),
    ("racebench.vector", "RaceVectorEnv"),
    ("racebench.sb3", "make_sb3_vec_env"),
    ("racebench.reward", "wrap_angle"),
    ("racebench.leaderboard.seeds", "seeds_for"),
    ("racebench.leaderboard.signing", "public_key_sha256"),
    ("racebench.training.train", "TrainConfig"),
    ("racebench.training.train", "load_config"),
    ("racebench.training.dagger", "DaggerConfig"),
    ("racebench.training.dagger", "distill"),
    ("racebench.training.policies", "RecurrentGRUPolicy"),
    ("racebench.training.policies", "RaceFeatures"),
    ("racebench.benchmark", "run_benchmark"),
)


@pytest.mark.parametrize(("module", "name"), FORMER_NAMES)
def test_former_import_paths_still_work(module: str, name: str) -> None:
    assert getattr(importlib.import_module(module), name) is not None


@pytest.mark.parametrize("package", ["racebench.agents", "racebench.evaluation", "racebench.training.dagger"])
def test_a_reexported_name_is_never_shadowed_by_a_submodule(package: str) -> None:
    """A package re-exports its former module's names lazily; a submodule of the same name would replace the name
    (the import system sets it on the package) once that submodule is imported."""
    module = importlib.import_module(package)
    for path in sorted((ROOT / package.replace(".", "/")).glob("*.py")):
        if path.stem != "__init__":
            importlib.import_module(f"{package}.{path.stem}")
    assert [name for name in module.__all__ if isinstance(getattr(module, name), ModuleType)] == []


def test_a_former_module_path_is_the_module_that_replaced_it() -> None:
    import racebench.env

    import racebench.envs.env

    assert racebench.env is racebench.envs.env and racebench.env.__spec__.name == "racebench.envs.env"


def pickled_module_paths(checkpoint: Path) -> set[str]:
    """The racebench modules named by the classes pickled in an SB3 checkpoint's ``data`` (policy, features)."""
    data = json.loads(zipfile.ZipFile(checkpoint).read("data"))
    found: set[str] = set()

    def walk(value: object) -> None:
        if isinstance(value, dict):
            for key, item in value.items():
                if key == ":serialized:":
                    found.update(m.decode() for m in re.findall(rb"racebench[\w.]*", base64.b64decode(item)))
                else:
                    walk(item)
        elif isinstance(value, list):
            for item in value:
                walk(item)

    walk(data)
    return found


COMMITTED_ZIPS = sorted(
    [*ROOT.glob("baselines/checkpoints/*/*.zip"), *ROOT.glob("baselines/experiments/campaign-*/*/checkpoints/*.zip")]
)


def test_every_committed_checkpoint_names_importable_modules() -> None:
    assert COMMITTED_ZIPS
    for checkpoint in COMMITTED_ZIPS:
        for module in pickled_module_paths(checkpoint):
            importlib.import_module(module)  # racebench.training.policies (the classes), racebench.training.train


@pytest.mark.parametrize("checkpoint", COMMITTED_ZIPS, ids=lambda p: str(p.relative_to(ROOT / "baselines")))
def test_every_committed_checkpoint_loads(checkpoint: Path) -> None:
    from racebench.agents.loading import SB3Agent

    agent = SB3Agent(str(checkpoint), trust_code=True)
    assert agent.obs_mode in ("vision", "state")
