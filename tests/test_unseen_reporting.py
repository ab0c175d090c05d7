"""The generalisation table and the sample-tracks figure (issue 73)."""

from __future__ import annotations

from pathlib import Path

import pytest
from scripts_loader import load_script

from racebench import cli
from racebench.envs.random_tracks import RandomTrackEnv
from racebench.evaluation import Evaluator
from racebench.evaluation.protocol import EVAL_SEED_BASE
from racebench.reporting.generalization import generalization_frames, generalization_table
from racebench.reporting.track_tops import plot_track_tops


@pytest.fixture(scope="module")
def results(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """planner-fast on 3 held-out episodes and 2 of S's; the random agent on the same 3 held-out episodes."""
    planner, random = tmp_path_factory.mktemp("planner-fast"), tmp_path_factory.mktemp("random")
    Evaluator("planner-fast", ["RaceObs-Unseen-v0"], episodes=3, out_dir=planner).run(progress=False)
    Evaluator("planner-fast", ["RaceObs-S-v0"], episodes=2, out_dir=planner).run(progress=False)
    Evaluator("random", ["RaceObs-Unseen-v0"], episodes=3, out_dir=random).run(progress=False)
    return planner, random


def test_the_table_has_a_row_per_policy_and_pairs_them_on_shared_tracks(results: tuple[Path, Path]) -> None:
    frame, bold, pairs = generalization_frames(results)
    assert list(frame.index) == ["planner-fast (privileged)", "random"]  # sorted by held-out success
    assert frame.loc["planner-fast (privileged)", "SR [%] held-out tracks"].startswith("100 [")
    assert frame.loc["random", "SR [%] held-out tracks"].startswith("0 [")
    assert frame.loc["random", "LT [s] held-out tracks"] == "–"
    assert frame.loc["planner-fast (privileged)", "SR [%] S-shaped"].startswith("100")  # same policy on S
    assert frame.loc["random", "SR [%] S-shaped"] == "–" and "SR [%] J-shaped" not in frame  # J never flown
    assert bold == set()  # a privileged reference is never bold, and one learned row has no rival
    row = pairs.iloc[0]
    assert (row["a"], row["b"], row["pairs"], row["only_a"], row["only_b"], row["both_finished"]) == (
        "planner-fast", "random", 3, 3, 0, 0
    )  # fmt: skip
    assert row["p"] == row["p_holm"] == pytest.approx(0.25)  # exact McNemar: 3 discordant pairs, all one way


def test_the_table_prints_as_markdown_latex_and_from_the_command_line(
    results: tuple[Path, Path], capsys: pytest.CaptureFixture, tmp_path: Path
) -> None:
    text = generalization_table(results)
    assert "held-out tracks" in text and "planner-fast vs random" in text and "0.25" in text
    assert "\\begin{table}" in generalization_table(results, fmt="latex")
    assert cli.main(["table", *map(str, results), "--table", "unseen"]) == 0
    assert "planner-fast vs random" in capsys.readouterr().out
    empty = tmp_path / "no-unseen"
    Evaluator("random", ["RaceObs-S-Level1-v0"], episodes=1, out_dir=empty).run(progress=False)
    with pytest.raises(SystemExit, match="no public-seed episodes of RaceObs-Unseen-v0"):
        cli.main(["table", str(empty), "--table", "unseen"])
    with pytest.raises(SystemExit, match="no evaluation records"):
        cli.main(["table", str(tmp_path / "missing"), "--table", "unseen"])


def test_the_sample_tracks_figure(tmp_path: Path) -> None:
    env = RandomTrackEnv(track="Unseen", obs_mode="state")
    scenes = [env.draw_scene(EVAL_SEED_BASE + i) for i in range(2)]
    env.close()
    out = plot_track_tops(scenes, tmp_path / "tops.svg", columns=2)
    assert out.read_text().count("<svg") == 1 and "unseen-001" in out.read_text()
    with pytest.raises(ValueError, match="png, pdf, svg"):
        plot_track_tops(scenes, tmp_path / "tops.gif")
    with pytest.raises(ValueError, match="at least one scene"):
        plot_track_tops([], tmp_path / "none.png")
    figure = load_script("unseen_tracks_figure").main(["--out", str(tmp_path / "six.png"), "--episodes", "0", "5"])
    assert figure.stat().st_size > 5_000
    committed = Path(__file__).parents[1] / "docs" / "figures" / "unseen-tracks.png"
    assert 5_000 < committed.stat().st_size < 100_000  # a small PNG in the repository
