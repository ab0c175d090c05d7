"""The training campaigns ``racebench paper-tables`` reports, each with what it needs to be read on its own.

A campaign is a folder of sweep runs (``<config>-<track>-seed<k>``) trained under one sweep file, whose decision
rule was committed before its first run, on one env version. Its tables take the built-in agents' and the
teacher–student students' evaluations *on the same env version* as references, so each registered campaign
(:data:`CAMPAIGNS`) names where those lie:

* **campaign 1** (``campaign-4m``, env version 2, racebench's own training distribution: flying mid-leg starts,
  gates ±0.3 m): references and students as kept in ``results/env-v2``, plus the A/B runs of ``vision-ppo`` on S
  (training seeds 1–2, :data:`AB_RUNS`); written into ``results/`` itself;
* **campaign 2** (``campaign-2``, env version 3, the paper's distribution: starts at rest, gates ±1 m on x/y):
  the built-ins in ``results/<agent>``, the students' ``eval/`` folders beside their checkpoints
  (``baselines/checkpoints/<method>-<track>/eval``); written into ``results/campaign-2/``.

The sweep file lists every run the campaign plans (:func:`planned_runs`), so a partial campaign knows which runs are
still missing: its cells show '–', and a claim whose runs are not all committed is not tested yet. A run counts as
committed once it is finished (``summary.json``) and evaluated (``eval/summary.csv``): :func:`committed_runs`.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import NamedTuple

from racebench.evaluation.protocol import TRACK_ORDER
from racebench.utils.yamlfile import read_yaml


class Run(NamedTuple):
    """One training run of a campaign: its config's name, its track and its training seed."""

    config: str
    track: str
    seed: int

    @property
    def folder(self) -> str:
        """The run's folder name: ``<config>-<track>-seed<seed>``."""
        return f"{self.config}-{self.track}-seed{self.seed}"


@dataclass(frozen=True)
class ExtraRun:
    """A run of the campaign that lives outside its run folder (``folder`` under the checkout)."""

    folder: Path
    run: Run


@dataclass(frozen=True)
class Campaign:
    """A training campaign and the evaluations its report reads (paths relative to the checkout's root)."""

    name: str  # the run folder's name, as in its sweep file: campaign-4m, campaign-2
    title: str  # how the reports call it: "campaign 1"
    runs: Path  # its runs: <runs>/<config>-<track>-seed<k>/
    sweep: Path | None  # the sweep file with its runs and its decision rule (None: not known)
    references: Path  # the built-in agents' evaluation folders on its env version: <references>/<agent>/
    students: Path  # the teacher–student students' on its env version: <students>/<method>-<track>/eval/
    env_version: int | None  # the env version of every record it reads (None: whatever they are, but one)
    out: Path  # where its tables go, under the results folder ("." : the results folder itself)
    distribution: str = ""  # its training distribution, in a phrase (claims.md)
    extra_runs: tuple[ExtraRun, ...] = ()
    readme_when_complete: bool = False  # the README's results block shows it once all its runs are in


#: Campaign 1's seeds 1-2 of vision-ppo on S: the A/B runs (its config, budget and env version).
AB_RUNS = tuple(
    ExtraRun(Path("baselines/experiments/ab-fast-update") / f"vision-ppo-S-seed{seed}", Run("vision-ppo", "S", seed))
    for seed in (1, 2)
)
CAMPAIGN_1 = Campaign(
    name="campaign-4m",
    title="campaign 1",
    runs=Path("baselines/experiments/campaign-4m"),
    sweep=Path("baselines/sweeps/campaign-4m.yaml"),
    references=Path("results/env-v2"),
    students=Path("results/env-v2"),
    env_version=2,
    out=Path("."),
    distribution="racebench's own training distribution: flying mid-leg starts (1-2 m before a gate, already flying "
    "towards it), gates randomised ±0.3 m on every axis, obstacles in a box between two gates",
    extra_runs=AB_RUNS,
)
CAMPAIGN_2 = Campaign(
    name="campaign-2",
    title="campaign 2",
    runs=Path("baselines/experiments/campaign-2"),
    sweep=Path("baselines/sweeps/campaign-2.yaml"),
    references=Path("results"),
    students=Path("baselines/checkpoints"),
    env_version=3,
    out=Path("campaign-2"),
    distribution="the paper's training distribution: starts at rest within ±0.5 m of the track start or of a point "
    "2 m before a gate, gates randomised ±1 m on x/y and ±0.3 m on z, obstacles placed along the legs as in the "
    "authors' scenes (vision-com: its own track-start, ±1 m regime); vision-one-step-flying: campaign 1's flying start",
    readme_when_complete=True,
)
#: The registered campaigns, oldest first.
CAMPAIGNS: dict[str, Campaign] = {c.name: c for c in (CAMPAIGN_1, CAMPAIGN_2)}


def find_campaign(spec: str | Path | Campaign, references: str | Path | None = None) -> Campaign:
    """The campaign ``spec`` names: a registered name (``campaign-2``), a registered campaign's run folder
    (``baselines/experiments/campaign-2``), or any other run folder (a campaign of its own, read with ``references``
    for both the built-ins and the students, default campaign 1's, written into ``<results>/<its folder's name>``).
    ``references`` replaces the built-ins' folder; the records' env version must still be the campaign's."""
    if isinstance(spec, Campaign):
        found = spec
    else:
        by_folder = {c.runs.as_posix(): c for c in CAMPAIGNS.values()}
        key = Path(spec).as_posix().rstrip("/")
        if str(spec) in CAMPAIGNS:
            found = CAMPAIGNS[str(spec)]
        elif key in by_folder:
            found = by_folder[key]
        else:
            folder = Path(spec)  # its runs are what the folder holds: no sweep file, nothing known to be missing
            refs = Path(references) if references is not None else CAMPAIGN_1.references
            return Campaign(folder.name, folder.name, folder, None, refs, refs, None, Path(folder.name))
    return found if references is None else replace(found, references=Path(references))


def _sweep_run_names(path: Path) -> list[Run]:
    """The runs a sweep file plans, in its order: each ``configs`` entry's tracks and seeds (or the file's), named by
    the config's ``overrides: {name: ...}`` or its built-in name, as ``racebench sweep`` names their folders."""
    data = read_yaml(path)
    if not isinstance(data, dict) or not isinstance(data.get("configs"), list):
        raise ValueError(f"{path}: not a sweep file (no configs list)")
    runs = []
    for entry in data["configs"]:
        entry = {"config": entry} if isinstance(entry, str) else entry
        if not isinstance(entry, dict) or "config" not in entry:
            raise ValueError(f"{path}: a configs entry without a config: {entry!r}")
        config = str(entry["config"])
        name = (entry.get("overrides") or {}).get("name", config)
        if name.endswith((".yaml", ".yml")):
            raise ValueError(f"{path}: {config} is a config file: name its runs with overrides: {{name: ...}}")
        for track in entry.get("tracks", data.get("tracks", [])):
            for seed in entry.get("seeds", data.get("seeds", [])):
                runs.append(Run(name, str(track), int(seed)))
    return runs


def planned_runs(root: str | Path, campaign: Campaign) -> frozenset[Run] | None:
    """Every run ``campaign`` plans: its sweep file's and its extra runs (None when it has no sweep file)."""
    if campaign.sweep is None:
        return None
    path = Path(root) / campaign.sweep
    if not path.is_file():
        raise ValueError(f"{campaign.name}: its sweep file {campaign.sweep} is missing under {root}")
    return frozenset(_sweep_run_names(path)) | {extra.run for extra in campaign.extra_runs}


def is_committed(folder: Path) -> bool:
    """Whether a run folder holds a finished (``summary.json``), evaluated (``eval/summary.csv``) run."""
    return (folder / "summary.json").is_file() and (folder / "eval" / "summary.csv").is_file()


def run_folders(root: str | Path, campaign: Campaign) -> dict[Run, Path]:
    """The committed runs of ``campaign`` and their folders under ``root``: its run folder's (those its sweep plans,
    when it has one: a run of another sweep in the same folder, e.g. the long run, is not one of its table's) and
    its extra runs."""
    root = Path(root)
    planned = planned_runs(root, campaign)
    found: dict[Run, Path] = {}
    for folder in sorted((root / campaign.runs).glob("*-seed*")):
        config, _, rest = folder.name.rpartition("-seed")
        method, _, track = config.rpartition("-")
        if not rest.isdigit() or track not in TRACK_ORDER or not method:
            continue
        run = Run(method, track, int(rest))
        if (planned is None or run in planned) and is_committed(folder):
            found[run] = folder
    for extra in campaign.extra_runs:
        if is_committed(root / extra.folder):
            found[extra.run] = root / extra.folder
    return found


@dataclass(frozen=True)
class RunSet:
    """The runs a campaign plans and those committed: how many of a claim's runs are in."""

    planned: frozenset[Run]
    committed: frozenset[Run]

    def count(self, configs: Iterable[str], seed: int | None = None) -> tuple[int, int]:
        """``(committed, planned)`` runs of ``configs`` (all training seeds, or only ``seed``)."""
        configs = set(configs)
        needed = {r for r in self.planned if r.config in configs and (seed is None or r.seed == seed)}
        return len(needed & self.committed), len(needed)

    @property
    def complete(self) -> bool:
        """Whether every planned run is committed."""
        return self.planned <= self.committed


def run_set(root: str | Path, campaign: Campaign) -> RunSet | None:
    """The planned and committed runs of ``campaign`` (None without a sweep file: nothing is known to be missing)."""
    planned = planned_runs(root, campaign)
    if planned is None:
        return None
    return RunSet(planned, frozenset(run_folders(root, campaign)) & planned)


def readme_campaign(root: str | Path) -> Campaign:
    """The campaign whose results block the README shows: the newest registered campaign marked
    ``readme_when_complete`` whose runs are all committed, else the oldest (campaign 1 until campaign 2 is complete:
    a block of a partial campaign would show '–' where campaign 1 has numbers)."""
    shown = next(iter(CAMPAIGNS.values()))
    for campaign in CAMPAIGNS.values():
        runs = run_set(root, campaign) if campaign.readme_when_complete else None
        if runs is not None and runs.complete:
            shown = campaign
    return shown


#: A campaign's steps per run where its sweep file does not say.
DEFAULT_STEPS = 4_000_000


def campaign_steps(root: str | Path, campaign: Campaign) -> int:
    """The environment steps per run of ``campaign``: its sweep file's ``steps`` (:data:`DEFAULT_STEPS` without)."""
    path = None if campaign.sweep is None else Path(root) / campaign.sweep
    if path is None or not path.is_file():
        return DEFAULT_STEPS
    data = read_yaml(path)
    return int(data.get("steps", DEFAULT_STEPS)) if isinstance(data, dict) else DEFAULT_STEPS
