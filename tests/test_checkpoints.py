"""The committed baseline checkpoints load with today's code and replay their committed evaluation episodes.

This is the leaderboard's promise in test form: a number in ``baselines/checkpoints/*/eval/episodes.csv`` is
what ``racebench evaluate`` gives for that checkpoint and seed on a fresh clone.
"""

from __future__ import annotations

from pathlib import Path

import pandas as pd
import pytest

from racebench.evaluation import Evaluator

CHECKPOINTS = sorted(Path(__file__).parents[1].glob("baselines/checkpoints/*/*.zip"))


def test_checkpoints_are_committed() -> None:
    names = {p.parent.name for p in CHECKPOINTS}
    assert {"state-ppo-S", "vision-ppo-S"} <= names


@pytest.mark.parametrize("checkpoint", CHECKPOINTS, ids=lambda p: p.parent.name)
def test_checkpoint_replays_its_evaluation(checkpoint: Path, tmp_path: Path) -> None:
    recorded = pd.read_csv(checkpoint.parent / "eval" / "episodes.csv")
    # The first episode of each evaluated env: seed protocol episode 0, so ``episodes=1`` replays it.
    first = recorded.sort_values("seed").groupby("env_id", sort=False).head(1).set_index("env_id")
    evaluator = Evaluator(str(checkpoint), list(first.index), episodes=1, out_dir=tmp_path)
    evaluator.run(progress=False)
    replayed = pd.read_csv(tmp_path / "episodes.csv").set_index("env_id").loc[first.index]
    for column in ("seed", "success", "crashed", "gates_passed", "steps"):
        assert list(replayed[column]) == list(first[column]), column
    pd.testing.assert_series_equal(replayed["return"], first["return"], rtol=1e-6)
