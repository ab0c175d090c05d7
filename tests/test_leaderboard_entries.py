"""Leaderboard entries: metadata validated against the policy's bytes, unique names, tiers computed not declared."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml
from leaderboard_fixtures import ENV, GC_AGENT, SALT, add, evaluate, make_repo, meta, write_hover_onnx, write_records

from racebench import cli
from racebench.agents import BUILTIN_PRIVILEGED, TRUSTED_CHECKPOINTS
from racebench.evaluation import EVAL_SEED_BASE
from racebench.leaderboard.entries import (
    DEFAULT_LEADERBOARD,
    MAIN_IDS,
    EntryError,
    load_config,
    load_entries,
    load_entry,
    policy_sha256,
    summarize_cells,
)
from racebench.leaderboard.seeds import salt_sha256

ROOT = Path(__file__).parents[1]


@pytest.fixture(scope="module")
def board(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A fixture repository: an ONNX policy (public and private records), the gc agent, the planner, hover."""
    root = tmp_path_factory.mktemp("repo")
    board = make_repo(root)
    onnx_file = write_hover_onnx(root / "policies" / "hover.onnx")
    (root / "policies" / "sneaky.py").write_text(GC_AGENT)
    sneaky = f"{root / 'policies' / 'sneaky.py'}:Sneaky"
    results = root / "results"
    evaluate(str(onnx_file), results / "onnx-public", 2)
    evaluate(str(onnx_file), results / "onnx-private", 2, "private")
    evaluate(sneaky, results / "sneaky-private", 2, "private", trust_code=True)
    evaluate("planner", results / "planner", 1)
    evaluate("hover", results / "hover", 1)
    add(board, str(onnx_file), "onnx-verified", [results / "onnx-public", results / "onnx-private"])
    add(board, str(onnx_file), "onnx-public-only", [results / "onnx-public"])
    add(board, sneaky, "sneaky", [results / "sneaky-private"])
    add(board, "planner", "planner", [results / "planner"])
    add(board, "hover", "hover", [results / "hover"])
    return board


def tiers(board: Path) -> dict[str, str]:
    """Entry name -> computed tier, with the fixture leaderboard's accepted salts."""
    accepted = load_config(board)["private_salt_sha256"]
    return {e.name: e.tier(accepted) for e in load_entries(board)}


def test_tiers_are_computed_from_the_policy_kind_and_the_seed_set(board: Path) -> None:
    assert tiers(board) == {
        "onnx-verified": "verified",  # ONNX on the maintainers' private seeds
        "onnx-public-only": "self-reported",  # the same graph on public seeds only: fittable
        "sneaky": "self-reported",  # Python code, even on private seeds; it flew the privileged follower
        "planner": "reference",
        "hover": "self-reported",  # a built-in, but code: never verified
    }
    entries = {e.name: e for e in load_entries(board)}
    sneaky = entries["sneaky"]
    assert not any(r["privileged"] for r in sneaky.records)
    # It did cheat successfully (2 of 2 laps), so the tier is what protects the ranking; its private records are
    # not ranked at all (a self-reported entry ranks on public seeds, of which it has none).
    assert summarize_cells(sneaky.records)[ENV].successes == 2 and sneaky.cells() == {}
    accepted = [salt_sha256(SALT)]
    verified = entries["onnx-verified"]
    assert {r["seed_set"] for r in verified.ranked_records(accepted)} == {"private"}
    assert {r["seed_set"] for r in entries["onnx-public-only"].ranked_records(accepted)} == {"public"}


def test_without_the_maintainers_salt_nothing_is_verified(board: Path, tmp_path: Path) -> None:
    entries = load_entries(board)
    assert all(e.tier([]) != "verified" for e in entries)  # a salt of the submitter's own choosing is not enough
    assert all(e.tier([salt_sha256("someone-elses-salt-123456")]) != "verified" for e in entries)


def test_add_validates_the_policy_and_refuses_duplicates(board: Path, tmp_path: Path) -> None:
    root = board.parents[1]
    onnx_file = root / "policies" / "hover.onnx"
    with pytest.raises(EntryError, match="already exists"):
        add(board, str(onnx_file), "ONNX-Verified", [root / "results" / "onnx-public"])  # case-insensitive
    with pytest.raises(EntryError, match="declared policy_sha256"):
        from racebench.leaderboard.entries import add_entry

        add_entry(
            board, str(onnx_file), {**meta("x"), "policy_sha256": "0" * 64}, [str(root / "results" / "onnx-public")]
        )
    outside = write_hover_onnx(tmp_path / "elsewhere.onnx")
    with pytest.raises(EntryError, match="inside the repository"):
        add(board, str(outside), "outside", [root / "results" / "onnx-public"])
    with pytest.raises(EntryError, match="record of another policy"):
        add(board, str(onnx_file), "stolen", [root / "results" / "planner"])  # someone else's results
    with pytest.raises(EntryError, match="obs_mode"):
        from racebench.leaderboard.entries import add_entry

        add_entry(board, str(onnx_file), {**meta("bad"), "obs_mode": "lidar"}, [str(root / "results" / "onnx-public")])
    assert not (board / "stolen").exists() and not (board / "bad" / "entry.yaml").exists()


def test_a_committed_entry_whose_policy_changed_is_refused(board: Path) -> None:
    folder = board / "onnx-public-only"
    text = (folder / "entry.yaml").read_text()
    data = yaml.safe_load(text)
    try:
        (folder / "entry.yaml").write_text(yaml.safe_dump({**data, "policy_sha256": "1" * 64}))
        with pytest.raises(EntryError, match="does not match"):
            load_entry(folder)
        (folder / "entry.yaml").write_text(yaml.safe_dump({**data, "name": "renamed"}))
        with pytest.raises(EntryError, match="differs from its folder"):
            load_entry(folder)
        (folder / "entry.yaml").write_text(yaml.safe_dump({**data, "records": ["../outside"]}))
        with pytest.raises(EntryError, match="inside the repository"):
            load_entry(folder)
    finally:
        (folder / "entry.yaml").write_text(text)


def test_cli_add_evaluates_and_errors_are_one_line(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    board = make_repo(tmp_path)
    meta_file = tmp_path / "meta.yaml"
    meta_file.write_text(yaml.safe_dump(meta("my-hover")))
    monkeypatch.chdir(tmp_path)
    argv = ["leaderboard", "add", "--policy", "hover", "--meta", str(meta_file), "--evaluate", "1"]
    assert cli.main(argv) == 0
    entry = load_entry(board / "my-hover")
    assert entry.meta["records"] == ["results/leaderboard/my-hover/eval-public"]
    assert sorted(entry.cells()) == sorted(MAIN_IDS) and all(c.n == 1 for c in entry.cells().values())
    with pytest.raises(SystemExit, match=r"^racebench leaderboard add: an entry named 'my-hover' already exists"):
        cli.main(argv)
    meta_file.write_text("name: [unclosed")
    with pytest.raises(SystemExit, match=r"^racebench leaderboard add: --meta .* unreadable"):
        cli.main(argv)
    with pytest.raises(SystemExit, match=r"^racebench leaderboard verify: no entry named \['nobody'\]"):
        cli.main(["leaderboard", "verify", "--entry", "nobody"])


def test_every_builtin_reference_and_committed_checkpoint_is_an_entry() -> None:
    board = ROOT / DEFAULT_LEADERBOARD
    entries = {e.name: e for e in load_entries(board)}
    accepted = load_config(board)["private_salt_sha256"]
    checkpoints = {e.meta["policy"] for e in entries.values() if e.kind == "sb3"}
    assert checkpoints == {f"baselines/checkpoints/{p}" for p in TRUSTED_CHECKPOINTS.values()}
    for name in ("planner", "planner-fast", "follow", "hover"):
        assert entries[name].meta["policy"] == f"builtin:{name}"
    privileged = {name for name, flag in BUILTIN_PRIVILEGED.items() if flag}
    assert {n for n, e in entries.items() if e.tier(accepted) == "reference"} == privileged
    for entry in entries.values():
        assert entry.meta["policy_sha256"] == policy_sha256(entry.meta["policy"], ROOT)
        assert entry.records and all(r["policy_sha256"] == entry.meta["policy_sha256"] for r in entry.records)


def test_cherry_picked_episodes_are_refused(tmp_path: Path) -> None:
    board = make_repo(tmp_path)
    folder = write_records(tmp_path / "results" / "hover", "hover", ENV, 0, 3)
    first = next(p for p in (folder / "records").glob("*.json") if json.loads(p.read_text())["seed"] == EVAL_SEED_BASE)
    first.unlink()  # "flew 3, committed the 2 I liked"
    with pytest.raises(EntryError, match=r"not the first 2 seeds .*missing e\.g\. \[1000000\].*none picked"):
        add(board, "hover", "hover", [folder])
