"""The unseen-tracks baselines' configs and sweep (issue 73): what they train on, and that nothing else changed."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from racebench.evaluation.protocol import SUITES
from racebench.training.config import TRAIN_TRACKS, TrainConfig
from racebench.training.dagger.config import DaggerConfig
from racebench.training.models import make_envs
from racebench.training.ppo import train
from racebench.training.run import default_track, load_config
from racebench.training.sweep import load_sweep, track_envs

BASELINES = Path(__file__).parents[1] / "baselines"


def test_vision_ppo_random_is_vision_ppo_on_generated_tracks() -> None:
    random, paper = TrainConfig.from_yaml("vision-ppo-random"), TrainConfig.from_yaml("vision-ppo")
    assert (random.name, random.track, paper.track) == ("vision-ppo-random", "Random", None)
    assert {**vars(random), "name": "", "track": None} == {**vars(paper), "name": ""}
    assert default_track(random) == "Random" and default_track(paper) == "S"
    assert random.env_kwargs("Random")["track"] == "Random"


def test_vision_distill_random_is_vision_distill_on_generated_tracks() -> None:
    random, paper = load_config("vision-distill-random"), load_config("vision-distill")
    assert isinstance(random, DaggerConfig) and random.env_id == "RaceObs-Random-v0" and paper.env_id == ""
    assert {**vars(random), "name": "", "env_id": ""} == {**vars(paper), "name": ""}
    assert default_track(random) == "Random"


def test_a_config_trains_on_its_own_track_only(tmp_path: Path) -> None:
    config = TrainConfig.from_yaml("vision-ppo-random")
    with pytest.raises(ValueError, match="trains on track 'Random'"):
        train(config, "S", steps=64, out=tmp_path)
    with pytest.raises(ValueError, match="track must be one of"):
        train(TrainConfig.from_yaml("vision-ppo"), "Unseen", steps=64, out=tmp_path)  # held out: never trained on
    path = tmp_path / "bad.yaml"
    path.write_text("name: x\ntrack: Unseen\n")
    with pytest.raises(ValueError, match="track must be one of"):
        TrainConfig.from_yaml(path)
    assert TRAIN_TRACKS == ("S", "J", "Circle", "Random")


def test_the_batched_training_envs_fly_generated_tracks() -> None:
    config = dataclasses.replace(
        TrainConfig.from_yaml("vision-ppo-random"), n_envs=2, num_processes=1, obs_mode="state", renderer=None
    )
    env = make_envs(config, "Random", seed=0)
    try:
        env.reset()
        env.step(np.zeros((2, 4), dtype=np.float32))
        env.env_method("set_task", **config.level_kwargs(2))
        layout = env.env_method("sample_layout", indices=[0])[0]
        env.env_method("set_layout", layout)
        env.reset()
        assert env.get_attr("source") == ["Random", "Random"]  # RandomTrackEnv's: the batched envs are generated-track
        assert [t.name for t in env.get_attr("track")] == [layout.track.name] * 2
    finally:
        env.close()


def test_the_shipped_sweep_trains_both_baselines_and_flies_the_generalisation_ids() -> None:
    sweep = load_sweep(BASELINES / "sweeps" / "unseen-tracks.yaml")
    assert [run.label for run in sweep.runs] == ["vision-ppo-random-Random-seed0", "vision-distill-random-Random-seed0"]
    assert [run.steps for run in sweep.runs] == [4_000_000, 500_000]
    expected = ("RaceObs-Random-v0", "RaceObs-Unseen-v0", *SUITES["main"])
    assert all(run.eval_envs == expected == track_envs("main", "Random") for run in sweep.runs)
    assert {(run.eval_episodes, run.eval_episodes_other) for run in sweep.runs} == {(100, 100)}


def test_a_sweep_of_a_random_config_on_a_paper_track_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "sweep.yaml"
    path.write_text("configs: [vision-ppo-random]\ntracks: [S]\nseeds: [0]\nsteps: 1000\n")
    with pytest.raises(ValueError, match="its config's track"):
        load_sweep(path)
    path.write_text("configs: [vision-ppo]\ntracks: [Unseen]\nseeds: [0]\nsteps: 1000\n")
    with pytest.raises(ValueError, match="Unseen"):
        load_sweep(path)


def test_a_tiny_distillation_on_generated_tracks(tmp_path: Path) -> None:
    """The DAgger pipeline takes the env id: planner-fast labels generated tracks, the student is evaluated there."""
    from racebench.training.dagger.loop import distill

    config = dataclasses.replace(
        load_config("vision-distill-random"), track="Random", iterations=1, steps_per_iteration=128, n_envs=4,
        batch_size=64, epochs=1, final_student="last", max_samples=1024,
    )  # fmt: skip
    config.validate()
    summary = distill(config, tmp_path, eval_episodes=1)
    assert Path(summary["checkpoint"]).name == "vision-distill-random-Random.zip"
    episodes = pd.read_csv(tmp_path / "eval" / "episodes.csv")
    assert list(episodes["env_id"]) == ["RaceObs-Random-v0"]
