"""``scripts/campaign_state.py``: a campaign run's resume state travels in ``main`` (the only thing that lands)."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest
from scripts_loader import load_script

RUN = "baselines/experiments/campaign-4m/vision-ppo-Circle-seed0"


def git(repo: Path, *args: str) -> str:
    return subprocess.run(["git", "-C", str(repo), *args], check=True, capture_output=True, text=True).stdout


@pytest.fixture
def repo(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    for key, value in {"GIT_AUTHOR_NAME": "t", "GIT_AUTHOR_EMAIL": "t@t", "GIT_COMMITTER_NAME": "t",
                       "GIT_COMMITTER_EMAIL": "t@t"}.items():  # fmt: skip
        monkeypatch.setenv(key, value)
    repo = tmp_path / "repo"
    repo.mkdir()
    git(repo, "init", "-q", "-b", "main")
    (repo / "README.md").write_text("main\n")
    git(repo, "add", "README.md")
    git(repo, "commit", "-q", "-m", "main")
    return repo


def write_run(root: Path, checkpoints: list[int]) -> Path:
    run = root / RUN
    (run / "checkpoints").mkdir(parents=True, exist_ok=True)
    for name in ("config.yaml", "curriculum.json", "progress.csv", "written.json"):
        (run / name).write_text(f"{name} at {max(checkpoints)}\n")
    for steps in checkpoints:
        (run / "checkpoints" / f"vision-ppo_{steps}_steps.zip").write_bytes(b"model %d" % steps)
        (run / "checkpoints" / f"vision-ppo_vecnormalize_{steps}_steps.pkl").write_bytes(b"stats %d" % steps)
    (run / "tb").mkdir(exist_ok=True)
    (run / "tb" / "events").write_text("not needed to resume")
    return run


KEPT = (
    "config.yaml",
    "curriculum.json",
    "progress.csv",
    "written.json",
    "checkpoints/vision-ppo_1000000_steps.zip",
    "checkpoints/vision-ppo_vecnormalize_1000000_steps.pkl",
)


def test_save_stages_only_the_newest_checkpoint_and_a_clone_of_main_restores_the_run(
    repo: Path, tmp_path: Path
) -> None:
    script = load_script("campaign_state")
    clone = tmp_path / "clone"
    run = write_run(clone, [500_000, 1_000_000])
    (repo / ".gitignore").write_text("baselines/experiments/campaign-4m/*/checkpoints/\n")  # as the project's
    staged = script.save(repo, clone, [run])
    assert sorted(staged) == sorted(f"{RUN}/{name}" for name in KEPT)
    git(repo, "commit", "-q", "-m", "state")
    assert sorted(git(repo, "ls-files", RUN).split()) == sorted(f"{RUN}/{name}" for name in KEPT)

    # a new machine: a plain clone of main carries the state (a side ref would not have landed)
    fresh_main = tmp_path / "new-machine-main"
    git(tmp_path, "clone", "-q", "--single-branch", str(repo), str(fresh_main))
    fresh = tmp_path / "new-machine-campaign"
    restored = script.restore(fresh_main, fresh)
    assert len(restored) == 6
    for path in restored:
        assert path.read_bytes() == (clone / path.relative_to(fresh)).read_bytes()
    assert not (fresh / RUN / "tb").exists()
    assert script.restore(fresh_main, fresh) == restored  # same content again: nothing refused


def test_a_new_save_unstages_the_old_checkpoint_so_main_carries_one_state(repo: Path, tmp_path: Path) -> None:
    script = load_script("campaign_state")
    clone = tmp_path / "clone"
    run = write_run(clone, [500_000])
    script.save(repo, clone, [run])
    git(repo, "commit", "-q", "-m", "first state")
    write_run(clone, [500_000, 1_000_000])
    script.save(repo, clone, [run])
    git(repo, "commit", "-q", "-m", "second state")
    assert script.tracked_state(repo) == [
        f"{RUN}/checkpoints/vision-ppo_1000000_steps.zip",
        f"{RUN}/checkpoints/vision-ppo_vecnormalize_1000000_steps.pkl",
    ]
    assert not (repo / RUN / "checkpoints" / "vision-ppo_500000_steps.zip").exists()


def test_save_in_place_stages_the_files_where_they_are(repo: Path) -> None:
    script = load_script("campaign_state")
    run = write_run(repo, [500_000])  # the campaign clone is the repository that commits
    staged = script.save(repo, repo, [run])
    assert git(repo, "diff", "--cached", "--name-only").split() == sorted(staged)


def test_restore_refuses_to_overwrite_other_content(repo: Path, tmp_path: Path, capsys) -> None:
    script = load_script("campaign_state")
    clone = tmp_path / "clone"
    script.save(repo, clone, [write_run(clone, [500_000])])
    other = tmp_path / "other"
    write_run(other, [500_000])
    (other / RUN / "progress.csv").write_text("a newer progress\n")
    assert script.main(["restore", "--repo", str(repo), "--root", str(other)]) == 1
    message = capsys.readouterr().err.strip()
    assert message.startswith("campaign_state: ") and "progress.csv: exists with other content" in message
    assert "\n" not in message
    assert (other / RUN / "progress.csv").read_text() == "a newer progress\n"  # nothing written


def test_restore_from_a_main_without_a_state_is_refused(repo: Path, tmp_path: Path, capsys) -> None:
    script = load_script("campaign_state")
    assert script.main(["restore", "--repo", str(repo), "--root", str(tmp_path / "clone")]) == 1
    assert "carries no resume state" in capsys.readouterr().err


def test_a_run_folder_without_a_checkpoint_is_refused_by_name(repo: Path, tmp_path: Path, capsys) -> None:
    script = load_script("campaign_state")
    run = tmp_path / "clone" / RUN
    run.mkdir(parents=True)
    assert script.main(["save", "--repo", str(repo), "--root", str(tmp_path / "clone"), str(run)]) == 1
    assert "no periodic checkpoint under checkpoints/" in capsys.readouterr().err
