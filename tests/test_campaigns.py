"""The campaigns ``racebench paper-tables`` reports: what each plans, what is committed, a partial campaign's report
(its own folder, '–' for missing runs, claims not tested yet, only finished runs on the learning curves), the README's
campaign, and env versions never mixed (records, references, the lap-time line figure)."""

from __future__ import annotations

import shutil
from dataclasses import replace
from pathlib import Path

import pandas as pd
import pytest

from racebench.reporting.campaigns import (
    CAMPAIGN_1,
    CAMPAIGN_2,
    CAMPAIGNS,
    Run,
    find_campaign,
    planned_runs,
    readme_campaign,
    run_set,
)
from racebench.reporting.paper import (
    LINE_AT_FULL_THRUST,
    LINE_TIMES,
    LINE_TIMES_COLUMN,
    README_BEGIN,
    README_END,
    campaign_episodes,
    lap_time_references,
    write_report,
)

ROOT = Path(__file__).resolve().parents[1]
TRACKS = ("S", "J", "Circle")


def test_each_campaign_plans_the_runs_of_its_sweep_file() -> None:
    """Campaign 2: 33 runs (six configs and the flying one-step at seed 0, seeds 1-2 of vision-ppo and one-step);
    campaign 1: its sweep's 24 and the two A/B seeds of vision-ppo on S (the long run is another sweep's)."""
    two = planned_runs(ROOT, CAMPAIGN_2)
    assert len(two) == 33
    flying = "vision-one-step-flying"
    assert {r for r in two if r.config == flying} == {Run(flying, t, 0) for t in TRACKS}
    assert {r for r in two if r.config == "vision-ppo"} == {Run("vision-ppo", t, s) for t in TRACKS for s in (0, 1, 2)}
    assert not any("long" in r.config for r in two)
    one = planned_runs(ROOT, CAMPAIGN_1)
    assert len(one) == 26 and {Run("vision-ppo", "S", 1), Run("vision-ppo", "S", 2)} <= one
    assert run_set(ROOT, CAMPAIGN_1).complete  # every campaign 1 run is committed


def test_a_campaign_is_found_by_name_or_run_folder_and_knows_its_references() -> None:
    assert find_campaign("campaign-2") is CAMPAIGN_2
    assert find_campaign("baselines/experiments/campaign-2/") is CAMPAIGN_2
    assert find_campaign(Path("baselines/experiments/campaign-4m")) is CAMPAIGN_1
    assert (CAMPAIGN_1.env_version, CAMPAIGN_2.env_version) == (2, 3)
    assert find_campaign("campaign-2", references="elsewhere").references == Path("elsewhere")
    other = find_campaign("runs/sweeps/mine", references="results")
    assert other.sweep is None and other.runs == Path("runs/sweeps/mine") and other.name not in CAMPAIGNS
    assert other.students == other.references == Path("results")


def _sweeps(root: Path) -> None:
    (root / "baselines").mkdir(parents=True, exist_ok=True)
    shutil.copytree(ROOT / "baselines" / "sweeps", root / "baselines" / "sweeps")


def _finished(folder: Path) -> None:
    """A run folder that counts as committed: finished (summary.json) and evaluated (eval/summary.csv)."""
    (folder / "eval").mkdir(parents=True)
    (folder / "summary.json").write_text("{}")
    (folder / "eval" / "summary.csv").write_text("")


def test_the_readme_shows_campaign_1_until_campaign_2_has_every_run(tmp_path: Path) -> None:
    _sweeps(tmp_path)
    planned = sorted(planned_runs(tmp_path, CAMPAIGN_2))
    for run in planned[:-1]:
        _finished(tmp_path / CAMPAIGN_2.runs / run.folder)
    (tmp_path / CAMPAIGN_2.runs / planned[-1].folder).mkdir()  # in progress: no summary, no eval
    assert readme_campaign(tmp_path) is CAMPAIGN_1
    runs = run_set(tmp_path, CAMPAIGN_2)
    assert len(runs.committed) == 32 and not runs.complete
    _finished(tmp_path / CAMPAIGN_2.runs / planned[-1].folder)  # the last run finishes
    assert readme_campaign(tmp_path) is CAMPAIGN_2
    assert readme_campaign(ROOT) is CAMPAIGN_1 or run_set(ROOT, CAMPAIGN_2).complete


def _partial_checkout(root: Path) -> None:
    """A checkout with campaign 2's sweep file, its first committed run (vision-ppo on S), a second run still
    training (vision-ppo on J: validation points, no summary, no eval), and the env-version-3 references; campaign 1's
    runs absent. The committed folders are links into this repository."""
    _sweeps(root)
    for name in ("results", "baselines/checkpoints"):
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).symlink_to(ROOT / name)
    runs = root / CAMPAIGN_2.runs
    runs.mkdir(parents=True)
    for path in LINE_TIMES.values():
        (root / path).symlink_to(ROOT / path)
    (runs / "vision-ppo-S-seed0").symlink_to(ROOT / CAMPAIGN_2.runs / "vision-ppo-S-seed0")
    training = runs / "vision-ppo-J-seed0"
    training.mkdir()
    pd.DataFrame({"timesteps": [499_712, 999_424], "episodes": 100, "successes": [0, 1], "success_rate": [0.0, 0.01],
                  "mean_return": [-2.8, 3.8]}).to_csv(training / "validation_curve.csv", index=False)  # fmt: skip
    (root / "README.md").write_text(f"head\n{README_BEGIN}\nold\n{README_END}\ntail\n")


def test_a_partial_campaign_writes_its_own_folder_with_missing_runs_as_dashes(tmp_path: Path) -> None:
    """Campaign 2 with one run committed: its tables in results/campaign-2 name campaign 2, env version 3 and how many
    runs are in; cells of missing runs are '–'; the run still training is neither in a table nor on the learning
    curves, which have the committed run's eight points every 0.5 M steps; claims.md has both campaigns' columns,
    each claim waiting for its runs; the README keeps campaign 1's block; campaign 2's Table II takes the line figure
    measured on env version 3."""
    _partial_checkout(tmp_path)
    out = tmp_path / "out"
    written = write_report(tmp_path, out, readme=tmp_path / "README.md")
    two = out / "campaign-2"
    assert two / "table_ii.md" in written and out / "claims.md" in written
    table = (two / "table_ii.md").read_text()
    assert "Campaign `campaign-2` (1 of 33 runs committed), env version 3." in table
    rows = {line.split("|")[1].strip(): [c.strip() for c in line.split("|")[2:-1]] for line in table.splitlines()[3:]}
    ppo = rows["vision-ppo"]  # LT S, Circle, J; SR S, Circle, J
    assert ppo[3] != "–" and ppo[4] == ppo[5] == ppo[1] == ppo[2] == "–"
    assert set(rows["state-ppo"]) == {"–"} and "–" not in rows["planner (privileged)"][3:]
    v3 = pd.read_csv(ROOT / LINE_TIMES[3], skipinitialspace=True)
    line = rows["planner-fast's line at full thrust (reference)"]
    assert line[:3] == [f"{v3.set_index('env_id').loc[f'RaceObs-{t}-v0', LINE_TIMES_COLUMN]:.2f}"
                        for t in ("S", "Circle", "J")]  # fmt: skip
    curves = pd.read_csv(two / "learning_curves.csv")
    assert set(curves["run"]) == {"vision-ppo-S-seed0"}
    assert curves["step"].tolist() == [k * 500_000 for k in range(1, 9)]
    assert (two / "figures" / "learning_curves.png").stat().st_size > 0
    claims = (out / "claims.md").read_text()
    assert "| claim | campaign 1 (env version 2) | campaign 2 (env version 3) |" in claims
    state = next(line for line in claims.splitlines() if line.startswith("| vision-ppo > state-ppo |"))
    assert state.split(" | ")[1:] == ["not tested yet (0 of 12 runs)", "not tested yet (1 of 12 runs) |"]
    flying = next(line for line in claims.splitlines() if line.startswith("| flying-start hypothesis"))
    assert flying.endswith("| – (not in campaign 1's rule) | not tested yet (0 of 6 runs) |")
    assert "Campaign `campaign-4m` (0 of 26 runs committed), env version 2." in (out / "table_ii.md").read_text()
    assert "Campaign `campaign-4m`" in (tmp_path / "README.md").read_text()  # campaign 1's block, not campaign 2's
    assert "campaign-2" not in (tmp_path / "README.md").read_text()


def test_a_campaign_never_mixes_env_versions(tmp_path: Path) -> None:
    """Campaign 2's runs (env version 3) with campaign 1's references (version 2) are refused, and so are records
    of another version than the campaign's own."""
    with pytest.raises(ValueError, match="several env versions"):
        campaign_episodes(ROOT, find_campaign("campaign-2", references="results/env-v2"))
    with pytest.raises(ValueError, match="campaign-2 is of env version 2, but its records .* are of env version 3"):
        campaign_episodes(ROOT, replace(CAMPAIGN_2, env_version=2))


def test_the_line_at_full_thrust_is_read_for_the_campaigns_env_version(tmp_path: Path) -> None:
    """Version 2's figures for campaign 1, version 3's for campaign 2 (measured again on its scenes); none for a
    version without a file; a file of another version than it is listed for is refused."""
    for version in (2, 3):
        frame = pd.read_csv(ROOT / LINE_TIMES[version], skipinitialspace=True).set_index("env_id")
        line = lap_time_references(ROOT, version)[LINE_AT_FULL_THRUST]
        assert line == {t: frame.loc[f"RaceObs-{t}-v0", LINE_TIMES_COLUMN] for t in ("S", "Circle", "J")}
    assert lap_time_references(ROOT, 2)[LINE_AT_FULL_THRUST] != lap_time_references(ROOT, 3)[LINE_AT_FULL_THRUST]
    assert lap_time_references(ROOT, 1)[LINE_AT_FULL_THRUST] == {}
    assert lap_time_references(tmp_path, 3)[LINE_AT_FULL_THRUST] == {}  # no file: '–' in the tables
    wrong = tmp_path / LINE_TIMES[2]
    wrong.parent.mkdir(parents=True)
    shutil.copy(ROOT / LINE_TIMES[3], wrong)  # version 3's figures under version 2's name
    with pytest.raises(ValueError, match=r"measured on env version \[3\], listed for env version 2"):
        lap_time_references(tmp_path, 2)


def test_another_sweeps_run_folder_is_a_campaign_of_its_own_in_its_own_folder(tmp_path: Path) -> None:
    """A run folder no campaign registers: its runs are what it holds (nothing known to be missing), its tables and
    its claims alone go to <out>/<its name>/, and nothing of the registered campaigns' outputs is written."""
    _partial_checkout(tmp_path)
    mine = tmp_path / "runs" / "sweeps" / "mine"
    mine.mkdir(parents=True)
    (mine / "vision-ppo-S-seed0").symlink_to(ROOT / CAMPAIGN_2.runs / "vision-ppo-S-seed0")
    out = tmp_path / "out"
    written = write_report(tmp_path, out, readme=None, campaign="runs/sweeps/mine", references="results")
    assert {p.relative_to(out).parts[0] for p in written} == {"mine"}
    assert "Campaign `mine`, env version 3." in (out / "mine" / "table_iii.md").read_text()
    claims = (out / "mine" / "claims.md").read_text()
    assert "| claim | mine (env version 3) |" in claims and "campaign 1" not in claims
    assert "| vision-ppo > state-ppo | not tested (missing runs) |" in claims
