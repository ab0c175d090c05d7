"""Teacher–student distillation (DAgger): the dataset, the beta schedule, a tiny run end to end."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from racebench.agents import SB3Agent
from racebench.training.dagger import DaggerConfig, Dataset, distill


def test_dataset_is_a_ring_buffer_of_quantised_depth() -> None:
    data = Dataset(capacity=3, depth_size=2)
    for k in range(4):
        data.add(
            np.full((1, 17), k, np.float32), np.full((1, 1, 2, 2), 0.5, np.float32), np.full((1, 4), k, np.float32)
        )
    assert data.size == 3 and sorted(data.action[:, 0].tolist()) == [1.0, 2.0, 3.0]  # the oldest was overwritten
    batch = data.batch(np.arange(3))
    assert batch["depth"].dtype.is_floating_point and abs(float(batch["depth"][0, 0, 0, 0]) - 128 / 255) < 1e-6


def test_bad_settings_are_named() -> None:
    with pytest.raises(ValueError, match="beta_decay"):
        DaggerConfig(beta_decay=1.5).validate()
    with pytest.raises(ValueError, match="seed"):
        DaggerConfig(seed=1_000_000).validate()
    with pytest.raises(ValueError, match="teacher"):
        DaggerConfig(teacher="hover").validate()  # not a privileged planner: cannot label every state


def test_a_tiny_distillation_run(tmp_path: Path) -> None:
    config = DaggerConfig(iterations=2, steps_per_iteration=256, n_envs=4, epochs=1, batch_size=64)
    summary = distill(config, tmp_path, eval_episodes=1)
    progress = pd.read_csv(tmp_path / "progress.csv")
    assert progress["beta"].tolist() == [1.0, 0.5]  # the teacher flies first, then less and less
    assert progress["samples"].tolist() == [256, 512]  # every step labelled, aggregated
    assert np.isfinite(progress["loss"]).all()
    saved = json.loads((tmp_path / "summary.json").read_text())
    assert saved["teacher"] == "planner-fast" and saved["eval"]["n"] == 1  # the fast expert by default
    agent = SB3Agent(summary["checkpoint"], trust_code=True)
    assert agent.obs_mode == "vision" and not agent.privileged


def test_an_interrupted_distillation_resumes_to_the_same_student(tmp_path: Path) -> None:
    """One iteration, stopped, then resumed to two: the student, dataset and rows of a run never interrupted."""
    import torch

    from racebench.training.dagger import RESUME_DIR

    config = DaggerConfig(iterations=2, steps_per_iteration=128, n_envs=4, epochs=1, batch_size=64)
    whole = distill(config, tmp_path / "whole", eval_episodes=0)
    first = DaggerConfig(**{**config.__dict__, "iterations": 1})
    distill(first, tmp_path / "parts", eval_episodes=0)
    assert (tmp_path / "parts" / RESUME_DIR / "state.json").is_file()
    resumed = distill(config, tmp_path / "parts", eval_episodes=0, resume=True)
    a, b = (SB3Agent(s["checkpoint"], trust_code=True).model.policy.state_dict() for s in (whole, resumed))
    assert all(torch.equal(a[k], b[k]) for k in a)  # bit for bit: same labels, same minibatches, same Adam state
    columns = ["iteration", "beta", "episodes", "samples", "loss"]
    rows = [pd.read_csv(tmp_path / d / "progress.csv")[columns] for d in ("whole", "parts")]
    pd.testing.assert_frame_equal(*rows)
    assert not list((tmp_path / "parts").glob(f"{RESUME_DIR}.*"))  # no partial or old state left behind

    with pytest.raises(ValueError, match="epochs=1, not 2"):  # another setting: not the same run
        distill(DaggerConfig(**{**config.__dict__, "epochs": 2}), tmp_path / "parts", eval_episodes=0, resume=True)


def test_a_kill_inside_the_state_swap_resumes_from_the_state_it_left(tmp_path: Path) -> None:
    """Killed between moving resume/ aside and renaming resume.partial/ into place: either folder is found."""
    from racebench.training.dagger import RESUME_DIR, completed_iterations, load_resume_state

    config = DaggerConfig(iterations=1, steps_per_iteration=64, n_envs=4, epochs=1, batch_size=32)
    distill(config, tmp_path, eval_episodes=0)
    (tmp_path / RESUME_DIR).rename(tmp_path / f"{RESUME_DIR}.partial")  # the new state, not yet swapped in
    assert completed_iterations(tmp_path) == 1
    state = load_resume_state(tmp_path, DaggerConfig(**{**config.__dict__, "iterations": 2}))
    assert state is not None and state["folder"].endswith(f"{RESUME_DIR}.partial")
    (tmp_path / f"{RESUME_DIR}.partial" / "state.json").unlink()  # written last: without it the copy is partial
    assert completed_iterations(tmp_path) == 0
