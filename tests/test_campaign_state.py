"""``scripts/campaign_state.py``: a campaign run's resume state on one replaceable ref, outside ``main``'s history."""

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


def test_save_keeps_only_the_newest_checkpoint_and_restore_rebuilds_the_run(repo: Path, tmp_path: Path) -> None:
    script = load_script("campaign_state")
    clone = tmp_path / "clone"
    run = write_run(clone, [500_000, 1_000_000])
    commit = script.save(repo, clone, [run])
    names = sorted(path for path, _blob, _size in script.listing(repo))
    kept = (
        "config.yaml",
        "curriculum.json",
        "progress.csv",
        "written.json",
        "checkpoints/vision-ppo_1000000_steps.zip",
        "checkpoints/vision-ppo_vecnormalize_1000000_steps.pkl",
    )
    assert names == sorted(f"{RUN}/{name}" for name in kept)
    assert git(repo, "rev-list", "--parents", "-n", "1", commit).split() == [commit]  # parentless
    assert git(repo, "ls-tree", "-r", "--name-only", "main").split() == ["README.md"]  # main untouched

    fresh = tmp_path / "new-machine"
    restored = script.restore(repo, fresh)
    assert len(restored) == 6
    for path in restored:
        assert path.read_bytes() == (clone / path.relative_to(fresh)).read_bytes()
    assert not (fresh / RUN / "tb").exists()
    assert script.restore(repo, fresh) == restored  # same content again: nothing refused


def test_a_new_save_replaces_the_old_state_which_becomes_unreachable(repo: Path, tmp_path: Path) -> None:
    script = load_script("campaign_state")
    clone = tmp_path / "clone"
    run = write_run(clone, [500_000])
    first = script.save(repo, clone, [run])
    old_blob = git(repo, "rev-parse", f"{first}:{RUN}/checkpoints/vision-ppo_500000_steps.zip").strip()
    write_run(clone, [500_000, 1_000_000])
    second = script.save(repo, clone, [run])
    assert git(repo, "rev-parse", script.DEFAULT_REF).strip() == second != first
    reachable = git(repo, "rev-list", "--objects", "--all").split()
    assert old_blob not in reachable and first not in reachable


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


def test_a_run_folder_without_a_checkpoint_is_refused_by_name(repo: Path, tmp_path: Path, capsys) -> None:
    script = load_script("campaign_state")
    run = tmp_path / "clone" / RUN
    run.mkdir(parents=True)
    assert script.main(["save", "--repo", str(repo), "--root", str(tmp_path / "clone"), str(run)]) == 1
    assert "no periodic checkpoint under checkpoints/" in capsys.readouterr().err
