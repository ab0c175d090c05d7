"""The robustness suite's reporting (issue 72, items 2 and 4): the suites, the paired table (exact McNemar, Holm over
the table) on a hand-computed example, its CSV, LaTeX and figure, and the command that writes them.

Every record here is written by the real record writer (:func:`leaderboard_fixtures.write_records`: sealed with a
digest, validated on read), with chosen outcomes per seed, so the pairs are known exactly.
"""

from __future__ import annotations

import logging
import math
import re
from pathlib import Path

import pandas as pd
import pytest
from leaderboard_fixtures import rewrite_records, write_records

from racebench import cli
from racebench.envs.perturbations import ROBUSTNESS
from racebench.evaluation.protocol import PERTURBATION_IDS, SUITES, TRACK_ORDER, resolve_envs
from racebench.evaluation.records import read_folder, seal
from racebench.reporting.robustness import (
    PERTURBATIONS,
    csv_frame,
    make_robustness_table,
    paired_cells,
    read_robustness,
    relative_robustness,
    robustness_cells,
)
from racebench.reporting.robustness_report import plot_robustness, robustness_figure

ROOT = Path(__file__).parents[1]
# The hand-computed example: 12 scenes. Nominally seeds 0-9 finish and 10-11 fail. Under Latency only seeds 0, 1
# and 11 finish (8 laps lost, 1 gained: McNemar p = 2 P(X <= 1 | 9, 1/2) = 20/512); under Mass seeds 5-9 (5 lost:
# p = 2/32); under Drag none (10 lost: p = 2/1024); under Wind the nominal ones (no discordant pair: p = 1).
NOMINAL = [i < 10 for i in range(12)]
OUTCOMES = {
    "Latency": [i in (0, 1, 11) for i in range(12)],
    "Mass": [5 <= i <= 9 for i in range(12)],
    "Drag": [False] * 12,
    "Wind": NOMINAL,
}
P_VALUES = {"Latency": 20 / 512, "Mass": 2 / 32, "Drag": 2 / 1024, "Wind": 1.0}
# Holm over the four: sorted 2/1024 x 4, 20/512 x 3, 2/32 x 2, 1 x 1, each at least the one before.
HOLM = {"Drag": 8 / 1024, "Latency": 60 / 512, "Mass": 4 / 32, "Wind": 1.0}


def write_example(folder: Path, spec: str = "hover", track: str = "S") -> Path:
    """The example's records of ``spec``: the main id with 20 episodes (seeds 12-19 fail: outside the pairs, they
    would change the nominal rate), each perturbation of :data:`OUTCOMES` with the 12 paired ones."""
    write_records(folder, spec, f"RaceObs-{track}-v0", 0, 0, lap=4.0, outcomes=NOMINAL + [False] * 8)
    for name, outcomes in OUTCOMES.items():
        write_records(folder, spec, f"RaceObs-{track}-{name}-v0", 0, 0, lap=5.0, outcomes=outcomes)
    return folder


@pytest.fixture(scope="module")
def example(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_example(tmp_path_factory.mktemp("robustness") / "hover")


def test_the_robustness_suites_and_their_docs() -> None:
    assert len(PERTURBATION_IDS) == 30 and set(ROBUSTNESS) == set(PERTURBATIONS)
    assert resolve_envs(["robustness"]) == SUITES["robustness"] and len(SUITES["robustness"]) == 33
    assert set(SUITES["robustness"]) == set(SUITES["main"]) | PERTURBATION_IDS
    for track in TRACK_ORDER:
        ids = resolve_envs([f"robustness-{track}"])
        assert ids == [f"RaceObs-{track}-v0", *(f"RaceObs-{track}-{p}-v0" for p in ROBUSTNESS)]
    # docs/evaluation.md names every suite; docs/robustness.md runs the suite by its names
    suites = re.search(r"^Suites: (.*?)\n\n", (ROOT / "docs" / "evaluation.md").read_text(), re.S | re.M).group(1)
    assert {name for name in SUITES if not name.startswith("robustness-")} <= set(re.findall(r"`([a-z-]+)`", suites))
    assert "`robustness-<track>`" in suites or all(f"`robustness-{t}`" in suites for t in TRACK_ORDER)
    running = (ROOT / "docs" / "robustness.md").read_text().split("## Running it", 1)[1].split("\n## ", 1)[0]
    for suite in re.findall(r"--envs ([\w-]+)", running):
        assert resolve_envs([suite]), suite


def test_mcnemar_and_holm_on_the_hand_computed_example(example: Path) -> None:
    cells = robustness_cells(read_robustness([example])).set_index("perturbation")
    assert sorted(cells.index) == sorted(OUTCOMES)
    assert (cells["pairs"] == 12).all() and (cells["nominal_successes"] == 10).all()  # seeds 12-19 are not paired
    assert cells.loc["Latency", ["only_nominal", "only_perturbed", "successes"]].tolist() == [8, 1, 3]
    assert cells.loc["Mass", ["only_nominal", "only_perturbed", "successes"]].tolist() == [5, 0, 5]
    for name, p in P_VALUES.items():
        assert cells.loc[name, "p"] == pytest.approx(p, rel=1e-12), name
        assert cells.loc[name, "p_holm"] == pytest.approx(HOLM[name], rel=1e-12), name
    assert cells["significant"].to_dict() == {"Latency": False, "Mass": False, "Drag": True, "Wind": False}
    assert cells.loc["Drag", "delta_sr"] == pytest.approx(-100 * 10 / 12)
    # mean laps over the successful paired episodes: lap + 0.1 s x the episode's index (the writer's spread)
    assert cells.loc["Latency", "nominal_lap_time"] == pytest.approx(4.0 + 0.1 * 4.5, abs=0.01)
    assert cells.loc["Latency", "lap_time"] == pytest.approx(5.0 + 0.1 * (0 + 1 + 11) / 3, abs=0.02)
    assert math.isnan(cells.loc["Drag", "lap_time"])


def test_the_table_marks_only_the_holm_significant_change(example: Path) -> None:
    cells = robustness_cells(read_robustness([example]))
    text = make_robustness_table(cells)
    row = next(line for line in text.splitlines() if line.startswith("| hover · S-shaped (n = 12)"))
    columns = [c.strip() for c in row.strip("|").split("|")]
    assert columns[1] == "83 / 4.45"  # nominal on the 12 paired scenes, not on all 20
    by_name = dict(zip(PERTURBATIONS, columns[2:], strict=True))
    assert by_name["Drag"] == "**0 / – (-83)**" and by_name["Latency"] == "25 / 5.40 (-58)"
    assert by_name["Wind"].endswith("(±0)") and by_name["Thrust"] == "n/e"
    assert "Holm-adjusted over the table's 4 tests" in text
    latex = make_robustness_table(cells, "latex")
    assert r"\textbf{0 / -- (-83)}" in latex and r"\begin{table}" in latex


def test_holm_runs_across_the_whole_table(example: Path, tmp_path: Path) -> None:
    """A second method's tests join the family: m = 8, so Latency's 20/512 (ranks 3 and 4) becomes 6 x 20/512."""
    other = write_example(tmp_path / "random", "random", "J")
    cells = robustness_cells(read_robustness([example, other]))
    assert len(cells) == 8
    latency = cells[cells["perturbation"] == "Latency"]
    assert latency["p_holm"].tolist() == pytest.approx([20 / 512 * 6] * 2)  # ranks 3-4 of 8: max(6, 5) x 20/512
    drag = cells[cells["perturbation"] == "Drag"]
    assert drag["p_holm"].tolist() == pytest.approx([2 / 1024 * 8] * 2)


def test_a_row_is_paired_on_the_scenes_every_cell_shares(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    folder = write_example(tmp_path / "hover")
    write_records(folder, "hover", "RaceObs-S-Thrust-v0", 0, 0, lap=5.0, outcomes=[True] * 6)  # stopped midway
    with caplog.at_level(logging.WARNING, logger="racebench"):
        cells = robustness_cells(read_robustness([folder])).set_index("perturbation")
    assert set(cells["pairs"]) == {6} and (cells["nominal_successes"] == 6).all()  # the first 6 scenes, every cell
    assert cells.loc["Latency", ["only_nominal", "only_perturbed"]].tolist() == [4, 0]  # seeds 2-5 lost
    assert "paired on the 6 scenes the main id and every perturbation share, one has 12" in caplog.text


def test_the_csv_holds_every_number(example: Path) -> None:
    table = csv_frame(robustness_cells(read_robustness([example]))).set_index("perturbation")
    assert table.loc["Latency", "env_id"] == "RaceObs-S-Latency-v0"
    assert table.loc["Latency", ["only_nominal", "only_perturbed"]].tolist() == [8, 1]
    assert table.loc["Latency", "p_mcnemar"] == pytest.approx(20 / 512)
    assert table.loc["Latency", "p_holm"] == pytest.approx(60 / 512)
    assert table.loc["Mass", "nominal_sr_ci_low"] < 10 / 12 < table.loc["Mass", "nominal_sr_ci_high"]
    assert list(table.index) == ["Latency", "Mass", "Drag", "Wind"]  # the suite's order


def test_a_label_with_two_policies_on_a_track_gets_a_row_each_and_cross_track_cells_pair_with_nothing(
    tmp_path: Path,
) -> None:
    a = write_example(tmp_path / "a" / "eval", "hover")
    b = write_example(tmp_path / "b" / "eval", "random")
    rewrite_records(b, lambda r: seal({**r, "agent": "hover"}))  # the same label, another policy
    write_records(tmp_path / "a" / "eval", "hover", "RaceObs-J-v0", 3, 5)  # a cross-track main-id cell
    cells = robustness_cells(read_robustness([a, b]))
    assert sorted(set(cells["method"])) == ["hover (a)", "hover (b)"] and set(cells["track"]) == {"S"}


def test_relative_robustness_per_track_and_what_it_leaves_out() -> None:
    rows = []
    n = len(PERTURBATIONS)  # ten
    for track, nominal, perturbed in (("S", 8, [4] * n), ("J", 5, [5] * (n - 1) + [0]), ("Circle", 0, [0] * n)):
        for name, k in zip(PERTURBATIONS, perturbed, strict=True):
            rows.append({"method": "m", "privileged": False, "track": track, "perturbation": name, "pairs": 10,
                         "nominal_successes": nominal, "successes": k})  # fmt: skip
    score = relative_robustness(pd.DataFrame(rows))
    assert score.per_track == {"S": pytest.approx(0.5), "J": pytest.approx((5 * (n - 1) / n) / 5)}
    assert score.value == pytest.approx((0.5 + (n - 1) / n) / 2) and score.left_out == {"Circle": "nominal success 0 %"}
    partial = relative_robustness(pd.DataFrame(rows[:5]))  # S with five of the ten
    assert partial.value is None and partial.left_out == {"S": f"5/{n} perturbations flown"}


def test_one_scene_flown_twice_and_mixed_env_versions_are_refused(example: Path, tmp_path: Path) -> None:
    twice = pd.DataFrame([{"method": "m", "privileged": False, "env_id": "RaceObs-S-Mass-v0", "seed": 1,
                           "success": True, "lap_time": 5.0}] * 2 + [{"method": "m", "privileged": False,
                           "env_id": "RaceObs-S-v0", "seed": 1, "success": True, "lap_time": 5.0}])  # fmt: skip
    with pytest.raises(ValueError, match="flown more than once"):
        paired_cells(twice)
    old = write_example(tmp_path / "old", "random")
    rewrite_records(old, lambda r: seal({**r, "env_version": r["env_version"] - 1}))
    with pytest.raises(ValueError, match="several env versions"):
        read_robustness([example, old])


def test_the_figure_draws_every_method_and_track(example: Path, tmp_path: Path) -> None:
    other = write_example(tmp_path / "planner", "planner", "J")
    cells = robustness_cells(read_robustness([example, other]))
    fig = robustness_figure(cells)
    titles = [ax.get_title() for ax in fig.axes]
    assert titles == ["S-shaped (n ≥ 12 paired scenes per cell)", "J-shaped (n ≥ 12 paired scenes per cell)"]
    labels = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    assert labels[:2] == ["hover", "planner (privileged)"] and "significant drop" in labels
    assert plot_robustness(cells, tmp_path / "r.pdf").read_bytes().startswith(b"%PDF")
    with pytest.raises(ValueError, match="no robustness results"):
        robustness_figure(cells.iloc[:0])


def test_one_command_writes_the_table_its_csv_and_the_figure(example: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "out"
    args = ["table", str(example), "--table", "robustness", "--out", str(out / "robustness.md"), "--csv",
            str(out / "robustness.csv"), "--figure", str(out / "robustness.pdf"), str(out / "robustness.png")]
    assert cli.main(args) == 0  # fmt: skip
    assert "**0 / – (-83)**" in (out / "robustness.md").read_text()
    assert pd.read_csv(out / "robustness.csv")["p_holm"].tolist() == pytest.approx([60 / 512, 4 / 32, 8 / 1024, 1])
    assert (out / "robustness.pdf").read_bytes().startswith(b"%PDF")
    assert (out / "robustness.png").read_bytes().startswith(b"\x89PNG")
    for bad, message in (
        (["--csv", str(out / "x.csv")], "--csv and --figure are options of --table robustness"),
        (["--table", "robustness", "--figure", str(out / "x.jpg")], "figures are written as png, pdf, svg"),
        (["--table", "robustness", "--seeds", "mean"], "one policy's episodes"),
    ):
        with pytest.raises(SystemExit) as exc:
            cli.main(["table", str(example), *bad])
        assert message in str(exc.value) and "\n" not in str(exc.value)
    with pytest.raises(SystemExit, match="no robustness results"):  # the main ids only: nothing to pair
        cli.main(["table", str(write_records(tmp_path / "main", "hover", "RaceObs-S-v0", 1, 2)), "--table",
                  "robustness"])  # fmt: skip


def test_the_evaluation_script_flies_every_method_but_planner_into_its_record_folders() -> None:
    import yaml
    from scripts_loader import load_script

    script = load_script("evaluate_robustness")
    board = ROOT / "results" / "leaderboard"
    jobs = script.plan(board)
    entries = {path.parent.name: yaml.safe_load(path.read_text()) for path in board.glob("*/entry.yaml")}
    assert {job.entry for job in jobs} == set(entries) - {"planner"} and "planner-fast" in {j.entry for j in jobs}
    assert len(jobs) == sum(len(meta["policies"]) for name, meta in entries.items() if name != "planner")
    for job in jobs:
        lines = entries[job.entry]["policies"]
        key, line = next((k, v) for k, v in lines.items() if v["policy"].removeprefix("builtin:") == job.policy)
        assert job.out == line["records"][0] and job.suites == (("robustness",) if key == "all" else
                                                                (f"robustness-{key}",))  # fmt: skip
        assert {r["agent"] for r in read_folder(ROOT / job.out).records.values()} == {job.label}  # --name: its label
        words = job.command(Path("/clone"), 50, 2, False)
        assert words[words.index("--out") + 1] == f"/clone/{job.out}" and words[words.index("--name") + 1] == job.label
        assert ["--episodes", "50", "--workers", "2"] == words[words.index("--episodes") : words.index("--out")]
    only_s = script.plan(board, only=["hover", "vision-ppo"], tracks=["S"])
    assert [(j.entry, j.suites) for j in only_s] == [("hover", ("robustness-S",)), ("vision-ppo", ("robustness-S",))]
    with pytest.raises(SystemExit, match="no entry named"):
        script.plan(board, only=["nobody"])
