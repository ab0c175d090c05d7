"""The evaluation protocol: seed bases (versioned by :data:`SEED_PROTOCOL`), the suites of env ids, env-id parsing.

Evaluation episode ``i`` of every env id uses seed ``EVAL_SEED_BASE + i``; training uses seeds below
:data:`VALIDATION_SEED_BASE`, validation (choosing a student, a validation curve) the seeds from it up to
:data:`EVAL_SEED_BASE`. The private seed set: :mod:`racebench.evaluation.seeds`.
"""

from __future__ import annotations

import re
from collections.abc import Sequence

import gymnasium as gym

from racebench.envs.perturbations import ROBUSTNESS
from racebench.envs.registration import DENSITIES, GATE_SHIFTS

SEED_PROTOCOL = 1
EVAL_SEED_BASE = 1_000_000
# Validation scene i (choosing a DAgger run's student, a campaign run's validation curve) has seed
# VALIDATION_SEED_BASE + i: above the training seeds of a fresh run and below the evaluation seeds, so nothing
# chosen or plotted on validation scenes has seen an evaluation scene.
VALIDATION_SEED_BASE = 800_000
TRACK_ORDER: tuple[str, ...] = ("S", "Circle", "J")  # the paper's column order
SUITES: dict[str, list[str]] = {
    "main": [f"RaceObs-{t}-v0" for t in TRACK_ORDER],
    "density": [f"RaceObs-{t}-Density{d}-v0" for d in DENSITIES for t in TRACK_ORDER],
    "gates": [f"RaceObs-{t}-GateShift{s}-v0" for s in GATE_SHIFTS for t in TRACK_ORDER],
}
SUITES["paper"] = SUITES["main"] + SUITES["density"] + SUITES["gates"]
# The robustness suite (docs/robustness.md): per track its main id and the ten perturbations of it, which fly the
# main id's scenes seed for seed (the pairs of the robustness table); ``robustness`` is all three tracks.
SUITES.update({f"robustness-{t}": [f"RaceObs-{t}-v0", *(f"RaceObs-{t}-{p}-v0" for p in ROBUSTNESS)]
               for t in TRACK_ORDER})  # fmt: skip
SUITES["robustness"] = SUITES["main"] + [i for t in TRACK_ORDER for i in SUITES[f"robustness-{t}"][1:]]
#: The suite's 30 perturbation ids (the robustness suite without its main ids).
PERTURBATION_IDS: frozenset[str] = frozenset(SUITES["robustness"]) - frozenset(SUITES["main"])
SEED_SET = "public"


_ID = re.compile(r"^RaceObs-(?P<track>[^-]+)(?:-(?P<variant>.+))?-v0$")


def eval_seeds(episodes: int) -> list[int]:
    """The evaluation seeds of protocol :data:`SEED_PROTOCOL`: ``EVAL_SEED_BASE + i``."""
    return [EVAL_SEED_BASE + i for i in range(episodes)]


def resolve_envs(names: Sequence[str]) -> list[str]:
    """Expand suite names (``main``, ``density``, ``gates``, ``paper``, ``robustness``, ``robustness-<track>``) and
    check every env id exists."""
    ids: list[str] = []
    for name in names:
        for env_id in SUITES.get(name, [name]):
            if env_id not in gym.registry:
                raise ValueError(f"unknown env id or suite {name!r} (suites: {sorted(SUITES)}; ids: racebench envs)")
            if env_id not in ids:
                ids.append(env_id)
    return ids


def split_env_id(env_id: str) -> tuple[str, str]:
    """``RaceObs-S-Density5-v0`` → (``"S"``, ``"Density5"``); the plain id's variant is ``"default"``."""
    match = _ID.match(env_id)
    if not match:
        return env_id, "custom"
    return match["track"], match["variant"] or "default"


def env_id_of(track: str, variant: str = "default") -> str:
    """The inverse of :func:`split_env_id`: (``"S"``, ``"Density5"``) → ``RaceObs-S-Density5-v0``."""
    return f"RaceObs-{track}-v0" if variant == "default" else f"RaceObs-{track}-{variant}-v0"
