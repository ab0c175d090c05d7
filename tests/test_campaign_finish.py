"""``scripts/campaign_finish.py``: a finished campaign run enters the repository as issue 48 asks, nothing more."""

from __future__ import annotations

import ast
import hashlib
import json
import shutil
from pathlib import Path

import pytest
from scripts_loader import load_script

REPO = Path(__file__).resolve().parents[1]
finish_script = load_script("campaign_finish")


def trusted(trust_file: Path) -> dict[str, str]:
    """TRUSTED_CHECKPOINTS as the file defines it (parsed, not imported)."""
    for node in ast.parse(trust_file.read_text()).body:
        if isinstance(node, ast.AnnAssign) and node.target.id == "TRUSTED_CHECKPOINTS":
            return ast.literal_eval(node.value)
    raise AssertionError("no TRUSTED_CHECKPOINTS")


def write_run(campaign: Path, seed: int, track: str = "Circle") -> Path:
    run = campaign / f"fixture-ppo-{track}-seed{seed}"
    for folder in ("eval", "policy", "checkpoints", "tb"):
        (run / folder).mkdir(parents=True)
    (run / "eval" / "summary.csv").write_text("env_id,n,successes\nRaceObs-Circle-v0,100,61\n")
    (run / "policy" / f"fixture-ppo-{track}.zip").write_bytes(b"policy bytes %d" % seed)
    (run / "checkpoints" / "fixture-ppo_999424_steps.zip").write_bytes(b"resume state")
    for name in ("config.yaml", "curriculum.json", "written.json", "validation_curve.csv"):
        (run / name).write_text(f"{name}\n")
    # two sessions: progress.csv's wall_s adds them up; 10 episodes end per row, success 0.5 then 1.0
    rows = [(t * 100_000, 10 * t, 1.0, 0.5 if t <= 38 else 1.0, 2, 300.0, 100.0 * t) for t in range(1, 41)]
    (run / "progress.csv").write_text(
        "timesteps,episodes,mean_return,success_rate,level,samples_per_s,wall_s\n"
        + "".join(",".join(str(v) for v in row) + "\n" for row in rows)
    )
    summary = {
        "config": "fixture-ppo", "track": track, "seed": seed, "timesteps": 4_000_000, "resumed_at": 2_000_000,
        "env_seed": 7, "wall_s": 2000.0, "samples_per_s": 1000.0, "level": 2,
        "promotions": [{"level": 2, "timestep": 1_500_000, "wall_s": 1500.0, "by": "budget"}],
        "checkpoint": "/elsewhere/fixture-ppo-Circle.zip", "policy": "/elsewhere/policy.zip",
        "eval": {"n": 100, "successes": 61},
    }  # fmt: skip
    (run / "summary.json").write_text(json.dumps(summary))
    return run


@pytest.fixture
def root(tmp_path: Path) -> Path:
    root = tmp_path / "main"
    (root / "racebench" / "agents").mkdir(parents=True)
    shutil.copy2(REPO / finish_script.TRUST_FILE, root / finish_script.TRUST_FILE)
    return root


def test_seed0_run_becomes_a_trusted_checkpoint(tmp_path: Path, root: Path) -> None:
    run = write_run(tmp_path / "campaign-4m", seed=0)
    before = trusted(root / finish_script.TRUST_FILE)
    assert finish_script.main([str(run), "--root", str(root), "--trained-by", "sweep X", "--note", "two sessions"]) == 0

    dest = root / (finish_script.EXPERIMENTS / "campaign-4m") / run.name
    assert sorted(p.name for p in dest.iterdir()) == [
        "config.yaml",
        "curriculum.json",
        "eval",
        "policy",
        "progress.csv",
        "summary.json",
        "validation_curve.csv",
        "written.json",
    ]  # fmt: skip  (no checkpoints/, no tb/)
    target = root / "baselines/checkpoints/fixture-ppo-Circle"
    assert sorted(p.name for p in target.iterdir()) == [
        "config.yaml", "curriculum.json", "eval", "fixture-ppo-Circle.zip", "progress.csv", "summary.json",
    ]  # fmt: skip
    summary = json.loads((target / "summary.json").read_text())
    assert summary["wall_s_total"] == 4000.0  # the last row's wall_s: both sessions, not the last part's 2000
    assert summary["samples_per_s_mean"] == 1000.0
    assert summary["steps_at_final_level"] == 2_500_000
    # the last 200k steps are rows 39 and 40 (t > 3.8 M): 20 episodes, all successes
    assert summary["final_training_success"] == 1.0
    assert summary["checkpoint"] == "baselines/checkpoints/fixture-ppo-Circle/fixture-ppo-Circle.zip"
    assert summary["trained_by"] == "sweep X" and summary["wall_s_note"] == "two sessions"
    assert not {"resumed_at", "env_seed", "wall_s", "samples_per_s", "policy"} & set(summary)

    after = trusted(root / finish_script.TRUST_FILE)
    digest = hashlib.sha256(b"policy bytes 0").hexdigest()
    assert after == {**before, digest: "fixture-ppo-Circle/fixture-ppo-Circle.zip"}
    # a second pass changes nothing in the trust list
    assert finish_script.main([str(run), "--root", str(root), "--trained-by", "sweep X", "--note", "n"]) == 0
    assert trusted(root / finish_script.TRUST_FILE) == after


def test_extra_seed_commits_summaries_not_checkpoints(tmp_path: Path, root: Path) -> None:
    run = write_run(tmp_path / "campaign-4m", seed=1)
    before = (root / finish_script.TRUST_FILE).read_text()
    assert finish_script.main([str(run), "--root", str(root), "--trained-by", "t", "--note", "n"]) == 0
    dest = root / (finish_script.EXPERIMENTS / "campaign-4m") / run.name
    assert (dest / "summary.json").is_file() and (dest / "eval" / "summary.csv").is_file()
    assert not (dest / "policy").exists() and not (root / "baselines/checkpoints").exists()
    assert (root / finish_script.TRUST_FILE).read_text() == before


@pytest.mark.parametrize("missing", ["summary.json", "eval/summary.csv", "policy/fixture-ppo-Circle.zip"])
def test_unfinished_run_is_refused(tmp_path: Path, root: Path, missing: str, capsys: pytest.CaptureFixture) -> None:
    run = write_run(tmp_path / "campaign-4m", seed=0)
    (run / missing).unlink()
    assert finish_script.main([str(run), "--root", str(root), "--trained-by", "t", "--note", "n"]) == 1
    assert capsys.readouterr().err.count("\n") == 1
    assert not (root / "baselines").exists()


def test_a_summary_without_its_fields_is_one_line(tmp_path: Path, root: Path, capsys: pytest.CaptureFixture) -> None:
    run = write_run(tmp_path / "campaign-4m", seed=0)
    (run / "summary.json").write_text(json.dumps({"seed": 0}))
    assert finish_script.main([str(run), "--root", str(root), "--trained-by", "t", "--note", "n"]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "summary.json has no 'config' field" in err


def test_another_digest_for_a_trusted_path_is_refused(root: Path) -> None:
    trust_file = root / finish_script.TRUST_FILE
    path = next(iter(trusted(trust_file).values()))
    with pytest.raises(ValueError, match="another sha256; pass --replace"):
        finish_script.add_trusted(trust_file, "0" * 64, path)


def test_long_trust_entries_wrap_within_the_line_length(root: Path) -> None:
    trust_file = root / finish_script.TRUST_FILE
    long_path = "a-made-up-long-config-Circle/a-made-up-long-config-Circle.zip"  # never a real entry
    assert finish_script.add_trusted(trust_file, "a" * 64, long_path)
    assert trusted(trust_file)["a" * 64] == long_path
    assert max(len(line) for line in trust_file.read_text().splitlines()) <= finish_script.LINE_LENGTH


def test_replace_swaps_the_trusted_policy_of_a_folder_and_nothing_else(tmp_path: Path, root: Path) -> None:
    """Issue 48's new S runs replace the committed S checkpoints: refused without --replace (nothing written),
    with it the old digest leaves the trust list, the new one enters, and no old file stays in the folder."""
    first = write_run(tmp_path / "one" / "campaign-4m", seed=0)
    assert finish_script.main([str(first), "--root", str(root), "--trained-by", "t", "--note", "n"]) == 0
    target = root / "baselines/checkpoints/fixture-ppo-Circle"
    (target / "old-notes.txt").write_text("from the replaced run")
    before = trusted(root / finish_script.TRUST_FILE)
    second = write_run(tmp_path / "two" / "campaign-4m", seed=0)
    (second / "policy" / "fixture-ppo-Circle.zip").write_bytes(b"a retrained policy")
    argv = [str(second), "--root", str(root), "--trained-by", "t2", "--note", "n"]
    assert finish_script.main(argv) == 1
    assert trusted(root / finish_script.TRUST_FILE) == before and (target / "old-notes.txt").is_file()
    assert finish_script.main([*argv, "--replace"]) == 0
    old, new = (hashlib.sha256(data).hexdigest() for data in (b"policy bytes 0", b"a retrained policy"))
    after = trusted(root / finish_script.TRUST_FILE)
    assert old not in after and after[new] == "fixture-ppo-Circle/fixture-ppo-Circle.zip"
    assert {k: v for k, v in after.items() if k != new} == {k: v for k, v in before.items() if k != old}
    assert not (target / "old-notes.txt").exists()
    assert (target / "fixture-ppo-Circle.zip").read_bytes() == b"a retrained policy"
    assert json.loads((target / "summary.json").read_text())["trained_by"] == "t2"


def test_replace_drops_a_wrapped_entry_too(root: Path) -> None:
    trust_file = root / finish_script.TRUST_FILE
    long_path = "a-made-up-long-config-Circle/a-made-up-long-config-Circle.zip"  # never a real entry
    assert finish_script.add_trusted(trust_file, "a" * 64, long_path)
    assert finish_script.add_trusted(trust_file, "b" * 64, long_path, replace=True)
    entries = trusted(trust_file)
    assert "a" * 64 not in entries and entries["b" * 64] == long_path


def test_a_run_goes_to_its_own_campaign_folder(tmp_path: Path, root: Path, capsys: pytest.CaptureFixture) -> None:
    """Campaign 2's runs land in baselines/experiments/campaign-2; a run outside a campaign-* folder is refused."""
    run = write_run(tmp_path / "campaign-2", seed=1)
    assert finish_script.main([str(run), "--root", str(root), "--trained-by", "sweep", "--note", "n"]) == 0
    assert (root / finish_script.EXPERIMENTS / "campaign-2" / run.name / "summary.json").is_file()
    stray = write_run(tmp_path / "elsewhere", seed=1)
    assert finish_script.main([str(stray), "--root", str(root), "--trained-by", "sweep", "--note", "n"]) == 1
    assert "not in a campaign folder" in capsys.readouterr().err
