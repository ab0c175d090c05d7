"""The module paths of racebench before its layered layout (``docs/layout.md``), kept importable.

``import racebench.env`` (or ``from racebench.track import load_track``) still works: a finder on ``sys.meta_path``
answers each former path in :data:`MOVED` with the module it moved to, the very same module object, so that
monkeypatching either name patches both. Modules that were split keep a thin module of their own instead
(``racebench.training.train``, ``racebench.training.policies``, the ``racebench.agents`` and
``racebench.evaluation`` packages, ``racebench.training.dagger``), since no single module stands for them.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import sys
from types import ModuleType

#: Former module path -> its module now.
MOVED: dict[str, str] = {
    "racebench.yamlfile": "racebench.utils.yamlfile",
    "racebench.validation": "racebench.utils.validation",
    "racebench.bullet": "racebench.sim.bullet",
    "racebench.camera": "racebench.sim.camera",
    "racebench.collision": "racebench.sim.collision",
    "racebench.obstacles": "racebench.sim.obstacles",
    "racebench.quadrotor": "racebench.sim.quadrotor",
    "racebench.raycast": "racebench.sim.raycast",
    "racebench.scene": "racebench.sim.scene",
    "racebench.simulation": "racebench.sim.simulation",
    "racebench.track": "racebench.sim.track",
    "racebench.env": "racebench.envs.env",
    "racebench.reward": "racebench.envs.reward",
    "racebench.vector": "racebench.envs.vector",
    "racebench.sb3": "racebench.training.sb3",
    "racebench.registration": "racebench.envs.registration",
    "racebench.lap_bound": "racebench.envs.lap_bound",
    "racebench.control": "racebench.agents.control",
    "racebench.planner": "racebench.agents.planner",
    "racebench.leaderboard.seeds": "racebench.evaluation.seeds",
    "racebench.rollout": "racebench.evaluation.rollout",
    "racebench.records": "racebench.evaluation.records",
    "racebench.statistics": "racebench.evaluation.statistics",
    "racebench.ray_backend": "racebench.evaluation.ray_backend",
    "racebench.tables": "racebench.reporting.tables",
    "racebench.plots": "racebench.reporting.plots",
    "racebench.video": "racebench.reporting.video",
    "racebench.paper": "racebench.reporting.paper",
    "racebench.sweep": "racebench.training.sweep",
}


class _Alias(importlib.abc.Loader):
    """Loads a former path as the module it moved to (the same object, its own ``__spec__`` kept)."""

    def __init__(self, target: str) -> None:
        self.target = target
        self.spec: importlib.machinery.ModuleSpec | None = None

    def create_module(self, spec: importlib.machinery.ModuleSpec) -> ModuleType:
        module = importlib.import_module(self.target)
        self.spec = module.__spec__
        return module

    def exec_module(self, module: ModuleType) -> None:
        module.__spec__ = self.spec  # the import system set the alias's spec on the shared module: put it back


class MovedModuleFinder(importlib.abc.MetaPathFinder):
    """Finds the former module paths of :data:`MOVED`, and nothing else."""

    def find_spec(self, fullname: str, path: object = None, target: object = None) -> importlib.machinery.ModuleSpec:
        if fullname not in MOVED:
            return None
        return importlib.machinery.ModuleSpec(fullname, _Alias(MOVED[fullname]))


def install() -> None:
    """Put the finder first on ``sys.meta_path`` (once): a stale file at a former path (an old editable install's
    mapping, say) must not shadow the module that moved."""
    if not any(isinstance(finder, MovedModuleFinder) for finder in sys.meta_path):
        sys.meta_path.insert(0, MovedModuleFinder())
